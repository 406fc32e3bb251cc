"""ArUco / AprilTag marker detection behind a named preprocessing pipeline.

Example:
    >>> det = Detector(DetectorConfig(ids=(13, 14, 15, 28, 34)))
    >>> for d in det.detect(image_bgr):
    ...     print(d.marker_id, d.corners_px)      # (4, 2) TL, TR, BR, BL in pixels

Corner order is OpenCV's (TL, TR, BR, BL of the marker as printed, i.e. the marker-frame
corners (-s/2, s/2), (s/2, s/2), (s/2, -s/2), (-s/2, -s/2)); pixel coordinates follow OpenCV
(integer = pixel centre). The detector does not change OpenCV's thread count: time it under
``cv2.setNumThreads(1)`` for one-core figures.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any

import cv2
import numpy as np

from uwdock.dockcore.config import validated
from uwdock.dockcore.domains import Interval
from uwdock.dockcore.errors import DockError
from uwdock.markers.config import MarkerId
from uwdock.markers.dictionary import dictionary_size, get_dictionary, normalise_dictionary_name
from uwdock.perception.preprocess import (
    MIN_IMAGE_PX,
    PIPELINES,
    Pipeline,
    as_uint8,
    get_pipeline,
    to_grey,
)
from uwdock.perception.rescue import QuadReader

__all__ = [
    "CORNER_REFINEMENTS",
    "Detection",
    "Detector",
    "DetectorConfig",
    "list_pipelines",
    "rendered_3dbm_config",
]

#: An ArUco adaptive-threshold window side (px, odd; OpenCV makes an even one odd).
ThreshWindowPx = Annotated[int, Interval(ge=3, le=999)]
#: Most adaptive-threshold windows one detection may run (each is a pass over the image).
MAX_THRESHOLD_WINDOWS = 64

#: Corner refinement names -> OpenCV constants.
CORNER_REFINEMENTS: dict[str, int] = {
    "none": int(cv2.aruco.CORNER_REFINE_NONE),
    "subpix": int(cv2.aruco.CORNER_REFINE_SUBPIX),
    "contour": int(cv2.aruco.CORNER_REFINE_CONTOUR),
    "apriltag": int(cv2.aruco.CORNER_REFINE_APRILTAG),
}


@dataclass(frozen=True)
class DetectorConfig:
    """Marker detector settings. ``None`` fields take the pipeline's preset
    (:data:`perception.preprocess.PIPELINES`; ``default`` presets: 7.0, (23, 23, 10), "subpix",
    True, rescue and OpenCV pass on; the published pipelines and ``plain`` use OpenCV's
    defaults: 7.0, (3, 23, 10), "none", False, rescue and OpenCV pass off).

    Attributes:
        dictionary: OpenCV dictionary name, any ``cv2.aruco.DICT_*`` incl. AprilTag families
            (case-insensitive, ``DICT_`` optional).
        ids: allow-list of marker IDs; detections of other IDs are dropped. None keeps all.
        pipeline: preprocessing pipeline name (see :func:`perception.preprocess.get_pipeline`).
        adaptive_thresh_constant: ArUco ``adaptiveThreshConstant`` (grey levels of the candidate
            image subtracted from the local mean, -255 ... 255). Lower finds lower-contrast
            markers and more noise (slower). None: pipeline preset.
        adaptive_thresh_win_sizes_px: (min, max, step) of ArUco's adaptive threshold windows
            (px, odd, 3 ... 999; step >= 1; at most ``MAX_THRESHOLD_WINDOWS`` windows). None:
            pipeline preset.
        corner_refinement: "none", "subpix" (~0.2 px corners), "contour" or "apriltag".
            None: pipeline preset.
        detect_inverted: also decode photometric negatives of the candidate image (OpenCV's
            ``detectInvertedMarker``). None: pipeline preset (True only for ``default``, whose
            candidate is not inverted).
        roi_margin: with predicted marker corners (:meth:`Detector.detect`'s ``predicted``),
            each search region is the predicted quad's bounding box widened on every side by
            this fraction of its larger side (-), for the prior's error.
        roi_min_pad_px: ... and by at least this many pixels.
        rescue_rejected: read the quads ArUco rejected again, by splits of their
            shading-corrected cell means (:mod:`perception.rescue`). None: pipeline preset
            (True only for ``default``).
        rescue_max_quads: most rejected quads read again per candidate image (largest
            first); bounds the cost on noisy frames.
        rescue_min_side_px: rejected quads with a mean side below this are not read again
            (px). ArUco's own size floor is relative to the image (3 % of its larger side),
            so in the small crops of a prior search it hands back noise specks of 1-2 px a
            side (median perimeter 5 px, ~35 a frame at 1080p).
        roi_accept_fraction: the regions' detections stand when they hold at least this
            fraction of the markers predicted in the image (and at least one); fewer, and the
            whole frame is searched. 1 demands every predicted marker; below 1, a marker hidden
            behind the station's structure does not cost a whole-frame search, while a prior
            that is off finds few or none and falls back.
        opencv_pass: also run OpenCV's ArUco detector with OpenCV's default parameters on the
            plain grey image: the allow-listed IDs it decodes are reported from it (corners
            refined like rescued ones when the pipeline refines to sub-pixel), the pipeline's
            own candidates (and the rescue) add the IDs it missed. The pipeline then decodes
            every marker plain OpenCV decodes, by construction. ``default``'s own pass is tuned
            for murky, noisy views and loses flat tags that plain OpenCV reads on real footage
            (``bench/bench_real.py``: 8 of 41 on the shared sets): its single 23 px threshold
            window merges a rope crossing a tag's white margin with the tag (windows of 5-13 px
            keep them apart) and loses some oblique tags; its Gaussian, and the 3x3 median it
            takes where a textured JPEG reads as impulse noise, blur away the 2-4 px cells of
            tags under ~40 px. Its corners of flat tags are biased by ``detectInvertedMarker``
            (the smallest nested contour; median 1.6 px on 16-30 px tags, against 0.6 px from
            this pass refined).
            OpenCV's pass decodes no 3DBM (a negative): those keep the pipeline's corners. Costs
            one more detection (three threshold windows) per frame, about OpenCV's own time,
            less in the small regions of a prior search. None: pipeline preset (True only for
            ``default``).
        compressed_pass: on frames that show a block-coding grid (JPEG, intra-coded video:
            :func:`perception.preprocess.block_grid_fraction`), also detect on the pipeline's
            extra views (:class:`perception.preprocess.CompressedViews`: its candidate inverted,
            the brightest channel inverted, each with its own threshold window); the IDs they
            decode that the rest missed are added, unless they lie on a marker already found.
            The gate is measured once on the whole frame, so an uncompressed frame (a render)
            takes exactly the path it took without this pass. Measured on held-out rendered
            frames at JPEG quality 25 (``bench/bench_compressed.py``). Explicit
            ``adaptive_thresh_*``, ``corner_refinement`` and ``detect_inverted`` settings do not
            reach the views. None: pipeline preset (True only for ``default``, also in
            :func:`rendered_3dbm_config`).
    """

    dictionary: str = "DICT_4X4_50"
    ids: tuple[MarkerId, ...] | None = None
    pipeline: str = "default"
    adaptive_thresh_constant: Annotated[float, Interval(ge=-255.0, le=255.0)] | None = None
    adaptive_thresh_win_sizes_px: (
        tuple[ThreshWindowPx, ThreshWindowPx, Annotated[int, Interval(ge=1, le=999)]] | None
    ) = None
    corner_refinement: str | None = None
    detect_inverted: bool | None = None
    roi_margin: Annotated[float, Interval(ge=0.0, le=10.0)] = 0.5
    roi_min_pad_px: Annotated[int, Interval(ge=0, le=10000)] = 16
    roi_accept_fraction: Annotated[float, Interval(gt=0.0, le=1.0)] = 0.5
    rescue_rejected: bool | None = None
    rescue_max_quads: Annotated[int, Interval(ge=0, le=10000)] = 16
    rescue_min_side_px: Annotated[float, Interval(ge=0.0, le=10000.0)] = 16.0
    opencv_pass: bool | None = None
    compressed_pass: bool | None = None

    def validate(self) -> None:
        """Raise ValueError naming the first bad field (names, IDs, the window sequence; each
        field's own range is its declared domain)."""
        try:
            name = normalise_dictionary_name(self.dictionary)
        except DockError as exc:
            raise ValueError(f"dictionary: {exc}") from None
        try:
            get_pipeline(self.pipeline)
        except DockError as exc:
            raise ValueError(f"pipeline: {exc}") from None
        if self.ids is not None:
            n = dictionary_size(name)
            bad = [i for i in self.ids if not 0 <= int(i) < n]
            if bad:
                raise ValueError(f"ids: {bad[0]} is outside {name} (valid IDs: 0..{n - 1})")
        w = self.adaptive_thresh_win_sizes_px
        if w is not None:
            lo, hi, step = (int(v) for v in w)
            if hi < lo:
                raise ValueError(f"adaptive_thresh_win_sizes_px: need max >= min, got {w}")
            if (hi - lo) // step + 1 > MAX_THRESHOLD_WINDOWS:
                raise ValueError(
                    f"adaptive_thresh_win_sizes_px: {w} gives {(hi - lo) // step + 1} threshold "
                    f"windows (at most {MAX_THRESHOLD_WINDOWS}: each is a pass over the image)"
                )
        r = self.corner_refinement
        if r is not None and r not in CORNER_REFINEMENTS:
            raise ValueError(
                f"corner_refinement: {r!r} is not one of {', '.join(CORNER_REFINEMENTS)}"
            )


@dataclass
class Detection:
    """One decoded marker.

    Attributes:
        marker_id: dictionary ID.
        corners_px: (4, 2) float64 pixel coordinates (u, v) of the TL, TR, BR, BL corners.
    """

    marker_id: int
    corners_px: np.ndarray


def _preset_parameters(preset: Mapping[str, Any]) -> cv2.aruco.DetectorParameters:
    """OpenCV's default parameters with ``preset``'s attributes set."""
    params = cv2.aruco.DetectorParameters()
    for key, value in preset.items():
        setattr(params, key, value)
    return params


def _overlaps(d: Detection, found: list[Detection]) -> bool:
    """True when ``d``'s centre lies in a quad of ``found`` or the centre of one of them lies in
    ``d``'s quad: the same physical marker (or its enclosure) read again."""
    q = d.corners_px.astype(np.float32).reshape(-1, 1, 2)
    c = d.corners_px.mean(axis=0)
    for o in found:
        oc = o.corners_px.mean(axis=0)
        oq = o.corners_px.astype(np.float32).reshape(-1, 1, 2)
        if (
            cv2.pointPolygonTest(oq, (float(c[0]), float(c[1])), False) >= 0
            or cv2.pointPolygonTest(q, (float(oc[0]), float(oc[1])), False) >= 0
        ):
            return True
    return False


def _aruco_parameters(cfg: DetectorConfig, pipeline: Pipeline) -> cv2.aruco.DetectorParameters:
    """OpenCV parameters: OpenCV defaults, then the pipeline preset, then explicit config."""
    params = cv2.aruco.DetectorParameters()
    overrides: dict[str, Any] = dict(pipeline.aruco_preset)
    if cfg.adaptive_thresh_constant is not None:
        overrides["adaptiveThreshConstant"] = float(cfg.adaptive_thresh_constant)
    if cfg.adaptive_thresh_win_sizes_px is not None:
        lo, hi, step = (int(v) for v in cfg.adaptive_thresh_win_sizes_px)
        overrides["adaptiveThreshWinSizeMin"] = lo
        overrides["adaptiveThreshWinSizeMax"] = hi
        overrides["adaptiveThreshWinSizeStep"] = step
    if cfg.corner_refinement is not None:
        overrides["cornerRefinementMethod"] = CORNER_REFINEMENTS[cfg.corner_refinement]
    if cfg.detect_inverted is not None:
        overrides["detectInvertedMarker"] = bool(cfg.detect_inverted)
    for key, value in overrides.items():
        setattr(params, key, value)
    return params


class Detector:
    """Runs a preprocessing pipeline and OpenCV's ArUco detector on camera images.

    Args:
        cfg: detector settings (validated here).

    Raises:
        ConfigError: an invalid config (unknown dictionary or pipeline names it).
    """

    def __init__(self, cfg: DetectorConfig | None = None) -> None:
        cfg = validated(DetectorConfig() if cfg is None else cfg)
        self.cfg = cfg
        self.pipeline = get_pipeline(cfg.pipeline)
        self.dictionary_name = normalise_dictionary_name(cfg.dictionary)
        self.parameters = _aruco_parameters(cfg, self.pipeline)
        self._allowed = None if cfg.ids is None else frozenset(int(i) for i in cfg.ids)
        self._dictionary = get_dictionary(self.dictionary_name)
        self._aruco = cv2.aruco.ArucoDetector(self._dictionary, self.parameters)
        rescue = (
            self.pipeline.rescue_rejected if cfg.rescue_rejected is None else cfg.rescue_rejected
        ) and cfg.rescue_max_quads > 0
        self._reader = QuadReader(self._dictionary, self._allowed) if rescue else None
        opencv_pass = self.pipeline.opencv_pass if cfg.opencv_pass is None else cfg.opencv_pass
        self._opencv = (
            cv2.aruco.ArucoDetector(self._dictionary, cv2.aruco.DetectorParameters())
            if opencv_pass
            else None
        )
        compressed = (
            self.pipeline.compressed is not None
            if cfg.compressed_pass is None
            else cfg.compressed_pass and self.pipeline.compressed is not None
        )
        #: the pipeline's extra views for block-compressed frames (None: off)
        self.compressed_views = self.pipeline.compressed if compressed else None
        self._view_arucos = (
            [
                cv2.aruco.ArucoDetector(self._dictionary, _preset_parameters(p))
                for p in self.compressed_views.presets(self.pipeline.aruco_preset)
            ]
            if self.compressed_views is not None
            else []
        )
        #: where the last :meth:`detect` found its markers: "regions" (the prior's) or "frame"
        self.last_search = "frame"
        #: whether the last :meth:`detect` ran the extra views of a block-compressed frame
        self.last_compressed = False

    def detect_candidate(self, grey: np.ndarray) -> list[Detection]:
        """ArUco on one preprocessed uint8 grey image; allow-listed IDs only, in OpenCV's order,
        then the rejected quads read again (``rescue_rejected``), IDs not yet found only."""
        subpix = self.parameters.cornerRefinementMethod == cv2.aruco.CORNER_REFINE_SUBPIX
        return self._decode(grey, self._aruco, subpix)

    def _decode(self, grey: np.ndarray, aruco: Any, subpix: bool) -> list[Detection]:
        """:meth:`detect_candidate` with another ArUco detector; ``subpix``: refine rescued
        quads' corners (:meth:`_refine_subpix`)."""
        corners, ids, rejected = aruco.detectMarkers(grey)
        out = []
        if ids is not None:
            for marker_id, c in zip(ids.ravel().tolist(), corners, strict=True):
                if self._allowed is None or marker_id in self._allowed:
                    out.append(Detection(int(marker_id), np.asarray(c, np.float64).reshape(4, 2)))
        if self._reader is not None and len(rejected):
            out.extend(self._read_rejected(grey, rejected, {d.marker_id for d in out}, subpix))
        return out

    def _read_rejected(
        self,
        grey: np.ndarray,
        rejected: tuple[np.ndarray, ...],
        have: set[int],
        subpix: bool = True,
    ) -> list[Detection]:
        """Rejected quads decoded by :class:`perception.rescue.QuadReader`, largest first."""
        sized = []
        for r in rejected:
            q = np.asarray(r, np.float32).reshape(4, 2)
            perimeter = cv2.arcLength(q, True)
            if perimeter >= 4.0 * self.cfg.rescue_min_side_px:
                sized.append((perimeter, q))
        sized.sort(key=lambda pq: -pq[0])
        out = []
        for _, q in sized[: self.cfg.rescue_max_quads]:
            got = self._reader.read(grey, q)  # type: ignore[union-attr]
            if got is None or got[0] in have:
                continue
            marker_id, c = got
            if subpix:
                c = self._refine_subpix(grey, c)
            out.append(Detection(marker_id, c))
            have.add(marker_id)
        return out

    def _refine_subpix(self, grey: np.ndarray, corners: np.ndarray) -> np.ndarray:
        """``cv2.cornerSubPix`` with a half-window of a quarter cell (2 px at least, ArUco's
        ``cornerRefinementWinSize`` at most). Measured on the 11 rescued markers of the
        rendered water frames (27-60 px): mean corner error 1.12 px unrefined, 0.74 px at
        half-window 2, 1.15 px at ArUco's 5 (the window reaches the next cell's edges); ArUco's
        own corners there: median 0.73 px.

        Markers whose cells are no larger than the half-window plus the gradient's 1 px are
        left as they are: there the window reaches the inner cells' edges, which pull the
        corner. Measured on OpenCV's corners of synthetic flat tags (small AprilTags under
        perspective, ChArUco boards, 20-60 px 4x4 tags; median of the mean corner error):
        cells under 3 px 0.85 px unrefined, 1.27 px refined; 3-3.5 px 0.75 / 0.76; 3.5-4 px
        0.75 / 0.43; 4-20 px 0.77-0.86 / 0.39-0.45."""
        p = self.parameters
        cell_px = (
            cv2.arcLength(corners.astype(np.float32), True) / 4 / (self._dictionary.markerSize + 2)
        )
        win = int(max(2, min(int(p.cornerRefinementWinSize), round(cell_px / 4))))
        if cell_px <= win + 1:
            return corners
        pts = corners.astype(np.float32).reshape(-1, 1, 2).copy()
        criteria = (
            cv2.TERM_CRITERIA_MAX_ITER | cv2.TERM_CRITERIA_EPS,
            int(p.cornerRefinementMaxIterations),
            float(p.cornerRefinementMinAccuracy),
        )
        cv2.cornerSubPix(grey, pts, (win, win), (-1, -1), criteria)
        return pts.reshape(4, 2).astype(np.float64)

    def detect(
        self,
        img_bgr: Any,
        predicted: dict[int, np.ndarray] | None = None,
        compressed: bool | None = None,
    ) -> list[Detection]:
        """Detect markers in a camera image.

        Args:
            img_bgr: (H, W) grey or (H, W, 3) BGR (or BGRA) array, uint8, uint16 or float
                [0, 1]. BGR is OpenCV's order: a simulator's RGB frame must be converted first
                (``uwdock.sim.camera.Frame.img_bgr``); RGB here weights red as blue.
            predicted: optional prior: marker ID -> (4, 2) predicted pixel corners (e.g. the
                board projected from a filter's DS pose, or the last frame's detections). The
                detector first searches only around the predicted markers that lie wholly in
                the image (regions widened by ``roi_margin`` / ``roi_min_pad_px``, overlapping
                ones merged) and returns those detections when enough of them are found
                (``roi_accept_fraction``); otherwise, or when none is predicted in the image,
                it searches the whole frame.
            compressed: whether the frame was block-coded, for ``compressed_pass``: None
                measures it (:func:`perception.preprocess.block_grid_fraction` of the frame);
                True runs the extra views whatever the frame shows, for a caller that knows
                (a ``CompressedImage`` resized before detection: area averaging by 2x or more
                blurs the 8 px grid away); False never runs them. Without ``compressed_pass``
                it is ignored.

        Returns:
            Detections sorted by marker ID. An ID decoded in several candidate images is
            reported once, from the candidate with the most detections (ties: the earlier one),
            or, for a pipeline that merges "first", from the earliest candidate. With
            ``opencv_pass`` the IDs OpenCV's own pass decodes come from it (flat tags, corners
            free of the inversion bias), the candidates add the IDs it missed; on a
            block-compressed frame (``compressed_pass``) the extra views add the IDs all of
            those missed.
            An ID seen twice in the same candidate (two physical markers) is kept twice.

        Raises:
            DockError: None, empty, or not an image.
        """
        image = as_uint8(img_bgr)
        self.last_search = "frame"
        grey = to_grey(image) if (self._opencv is not None or self._view_arucos) else None
        views = self.compressed_views
        if views is None or grey is None:
            compressed = False
        elif compressed is None:
            compressed = views.applies(grey)
        self.last_compressed = bool(compressed)
        if predicted:
            found = self._detect_in_regions(image, predicted, grey, bool(compressed))
            if found is not None:
                self.last_search = "regions"
                return found
        return self._detect_image(image, grey, bool(compressed))

    def _detect_image(
        self, image: np.ndarray, grey: np.ndarray | None = None, compressed: bool = False
    ) -> list[Detection]:
        """The pipeline's candidates of one uint8 image, detected and merged; ``grey``: the
        image's :func:`to_grey` when already computed; ``compressed``: add the extra views'
        IDs (the gate decided on the whole frame)."""
        if self._opencv is None:
            merged = []
        else:
            merged = self._opencv_pass(to_grey(image) if grey is None else grey)
        seen = {d.marker_id for d in merged}
        candidates = self.pipeline(grey if grey is not None and self.pipeline.grey_input else image)
        per_candidate = [self.detect_candidate(c) for c in candidates]
        order = list(range(len(per_candidate)))  # "first": in the pipeline's order
        if self.pipeline.merge != "first":
            order.sort(key=lambda i: -len(per_candidate[i]))
        if self.pipeline.merge == "best":
            order = order[:1]
        for i in order:
            new = [d for d in per_candidate[i] if d.marker_id not in seen]
            merged.extend(new)
            seen.update(d.marker_id for d in new)
        if compressed and candidates:
            views = self.compressed_views.views(image, candidates)  # type: ignore[union-attr]
            for view, aruco in zip(views, self._view_arucos, strict=True):
                for d in self._decode(view, aruco, subpix=False):
                    if d.marker_id not in seen and not _overlaps(d, merged):
                        merged.append(d)
                        seen.add(d.marker_id)
        return sorted(merged, key=lambda d: d.marker_id)

    def _opencv_pass(self, grey: np.ndarray) -> list[Detection]:
        """OpenCV's ArUco with its default parameters on ``grey``: allow-listed IDs, corners
        refined as rescued ones are (when the pipeline refines to sub-pixel)."""
        corners, ids, _ = self._opencv.detectMarkers(grey)  # type: ignore[union-attr]
        if ids is None:
            return []
        subpix = self.parameters.cornerRefinementMethod == cv2.aruco.CORNER_REFINE_SUBPIX
        out = []
        for marker_id, c in zip(ids.ravel().tolist(), corners, strict=True):
            if self._allowed is None or marker_id in self._allowed:
                q = np.asarray(c, np.float64).reshape(4, 2)
                out.append(Detection(int(marker_id), self._refine_subpix(grey, q) if subpix else q))
        return out

    def search_regions(
        self, shape: tuple[int, ...], predicted: dict[int, np.ndarray]
    ) -> tuple[list[tuple[int, int, int, int]], set[int]]:
        """Pixel boxes (x0, y0, x1, y1), end-exclusive, to search for the ``predicted`` markers
        in an image of ``shape``, and the IDs expected there (predicted wholly in the image).
        Overlapping boxes are merged; predictions with non-finite corners are ignored."""
        h, w = int(shape[0]), int(shape[1])
        boxes: list[list[int]] = []
        expected: set[int] = set()
        for marker_id, quad in predicted.items():
            q = np.asarray(quad, dtype=np.float64).reshape(-1, 2)
            if q.shape != (4, 2) or not np.isfinite(q).all():
                continue
            lo, hi = q.min(axis=0), q.max(axis=0)
            if lo[0] < 0 or lo[1] < 0 or hi[0] > w - 1 or hi[1] > h - 1:
                continue  # partly outside: not expected whole, the full frame will look
            pad = max(self.cfg.roi_margin * float(np.max(hi - lo)), self.cfg.roi_min_pad_px)
            x0, y0 = (int(np.floor(v - pad)) for v in lo)
            x1, y1 = (int(np.ceil(v + pad)) + 1 for v in hi)
            boxes.append([max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)])
            expected.add(int(marker_id))
        merged = True
        while merged:  # union overlapping boxes until none overlap
            merged, out = False, []
            for box in boxes:
                for k, o in enumerate(out):
                    if box[0] < o[2] and o[0] < box[2] and box[1] < o[3] and o[1] < box[3]:
                        out[k] = [min(box[0], o[0]), min(box[1], o[1]), max(box[2], o[2]),
                                  max(box[3], o[3])]  # fmt: skip
                        merged = True
                        break
                else:
                    out.append(box)
            boxes = out
        return [tuple(b) for b in boxes], expected  # type: ignore[misc]

    def _detect_in_regions(
        self,
        image: np.ndarray,
        predicted: dict[int, np.ndarray],
        grey: np.ndarray | None = None,
        compressed: bool = False,
    ) -> list[Detection] | None:
        """Detections in the predicted regions, or None when too few of the expected markers
        are found there (``roi_accept_fraction``) or none is expected."""
        boxes, expected = self.search_regions(image.shape, predicted)
        if not expected:
            return None
        found: dict[int, Detection] = {}
        for x0, y0, x1, y1 in boxes:
            if min(x1 - x0, y1 - y0) < MIN_IMAGE_PX:
                return None
            crop_grey = None if grey is None else grey[y0:y1, x0:x1]
            for d in self._detect_image(image[y0:y1, x0:x1], crop_grey, compressed):
                if d.marker_id not in found:
                    found[d.marker_id] = Detection(d.marker_id, d.corners_px + np.array([x0, y0]))
        hits = len(expected & found.keys())
        if hits == 0 or hits < self.cfg.roi_accept_fraction * len(expected):
            return None
        return sorted(found.values(), key=lambda d: d.marker_id)

    def __repr__(self) -> str:
        return f"Detector({self.cfg!r})"


def rendered_3dbm_config(ids: tuple[int, ...] | None = None) -> DetectorConfig:
    """The detector for frames that show only 3DBMs, as the simulator renders them (the camera
    source, the error-model fit, the tank report) and as the vehicle node receives them:
    ``default`` without its OpenCV pass, which decodes no negative marker, so the same
    detections in about half the time (``bench/bench_perception.py``: 5.3 against 9.5 ms at
    968 px). Its views for block-compressed frames (``compressed_pass``) stay on: a vehicle's
    ``CompressedImage`` opens their gate, a render does not (it takes the path it took before
    they existed, bit for bit).

    Args:
        ids: the marker IDs allowed (None: any of the dictionary).
    """
    return DetectorConfig(ids=ids, opencv_pass=False)


def list_pipelines() -> dict[str, str]:
    """Pipeline name -> one-line description."""
    return {name: p.description for name, p in PIPELINES.items()}
