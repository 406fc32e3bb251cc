"""``default`` against plain OpenCV on synthetic scenes made like the real footage it lost on.

On the shared real sets (``bench/bench_real.py``) the ``default`` pipeline's own pass (noise-aware
stretch, blur, one 23 px threshold window) missed flat AprilTags that plain
``cv2.aruco.ArucoDetector`` reads: a full-size tag whose white margin a rope crosses at one
corner, and tags of 16-35 px seen through the water surface. Its OpenCV pass
(``DetectorConfig.opencv_pass``) closes that. The scenes here are drawn by the tests themselves
(never the real frames), each with its ground truth: AprilTag 36h11 bitmaps
(``cv2.aruco.generateImageMarker``) warped by known homographies onto texture, then blurred and
noised. Each scene is first checked to reproduce the failure (the own pass alone misses what
OpenCV finds), so the test cannot pass without the fix.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from uwdock.perception.detector import Detector, DetectorConfig

APRILTAG = "DICT_APRILTAG_36h11"
_TAG_DICT = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
_SQUARE = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])


def _texture(rng: np.random.Generator, w: int, h: int, grain_px: int) -> np.ndarray:
    """Smooth random texture in [0, 1] (gravel-like at a few px of grain), float32 (h, w)."""
    coarse = rng.random((max(h // grain_px, 2), max(w // grain_px, 2))).astype(np.float32)
    return np.clip(cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC), 0.0, 1.0)


def _tag_bitmap(marker_id: int, cell_px: int, margin_cells: float, white: float, black: float):
    """A flat printed tag: (float32 patch, (4, 2) tag corners in patch pixel coordinates)."""
    side = 8 * cell_px  # 36h11: 6x6 bits + one black border cell a side
    tag = cv2.aruco.generateImageMarker(_TAG_DICT, marker_id, side, borderBits=1)
    m = round(margin_cells * cell_px)
    patch = np.full((side + 2 * m,) * 2, white, np.float32)
    patch[m : m + side, m : m + side] = np.where(tag > 0, white, black)
    e0, e1 = m - 0.5, m + side - 0.5  # pixel edges, centre-based coordinates
    return patch, np.array([[e0, e0], [e1, e0], [e1, e1], [e0, e1]])


def _paste(img: np.ndarray, patch: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """``patch`` warped so that its points ``src`` land on ``dst``, composited over ``img``."""
    h, w = img.shape
    hm = cv2.getPerspectiveTransform(src.astype(np.float32), dst.astype(np.float32))
    warped = cv2.warpPerspective(patch, hm, (w, h), flags=cv2.INTER_LINEAR)
    mask = cv2.warpPerspective(np.ones_like(patch), hm, (w, h), flags=cv2.INTER_LINEAR)
    return img * (1.0 - mask) + warped


def _finish(img: np.ndarray, rng: np.random.Generator, blur_px: float, noise: float) -> np.ndarray:
    img = cv2.GaussianBlur(img, (0, 0), blur_px) + rng.normal(0.0, noise, img.shape)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def rope_scene(rng: np.random.Generator, marker_id: int = 7, gap_px: float = 1.0):
    """A 170 px tag on gravel with a dark rope (7 px) crossing its white margin at the top-left
    corner, ``gap_px`` outside the black border's corner, perpendicular to the diagonal.

    Returns:
        (960x720 uint8 grey image, (4, 2) true tag corners TL, TR, BR, BL).
    """
    w, h, side = 960, 720, 170.0
    img = 60.0 + 80.0 * _texture(rng, w, h, 6)
    patch, src = _tag_bitmap(marker_id, 16, 1.5, 235.0, 25.0)
    a = rng.uniform(0, 2 * np.pi)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    quad = _SQUARE * side / 2 + rng.normal(0, 0.04 * side, (4, 2))
    truth = quad @ rot.T + np.array([w / 2, h / 2]) + rng.uniform(-40, 40, 2)
    img = _paste(img, patch, src, truth)
    rope_w = 7
    diag = (truth[0] - truth[2]) / np.linalg.norm(truth[0] - truth[2])
    centre = truth[0] + diag * (gap_px + rope_w / 2)
    along = np.array([-diag[1], diag[0]]) * 400
    rope = np.zeros((h, w), np.float32)
    ends = [tuple(round(v * 16) for v in p) for p in (centre + along, centre - along)]
    cv2.line(rope, ends[0], ends[1], 1.0, rope_w, cv2.LINE_AA, 4)  # 4 fractional bits
    img = img * (1 - rope) + 70.0 * rope
    return _finish(img, rng, 1.0, 2.0), truth


def small_tags_scene(rng: np.random.Generator, near_px: float = 35.0, far_px: float = 16.0):
    """A floor of 8x5 tags (random IDs) under perspective: 16 px wide at the far edge, 35 px
    at the near one (2-4 px cells), blurred, noised and JPEG-compressed (quality 85).

    Returns:
        (960x720 uint8 grey image, {id: (4, 2) true corners}).
    """
    w, h, cols, rows, cell = 960, 720, 8, 5, 12
    tag_px = 8 * cell
    pitch = 2 * tag_px
    pw, ph = cols * pitch, rows * pitch
    plane = 50.0 + 60.0 * _texture(rng, pw, ph, 24)
    ids = rng.choice(len(_TAG_DICT.bytesList), cols * rows, replace=False)
    corners = {}
    for k, marker_id in enumerate(ids.tolist()):
        patch, src = _tag_bitmap(marker_id, cell, 1.0, 220.0, 30.0)
        x0 = (k % cols) * pitch + (pitch - patch.shape[1]) // 2
        y0 = (k // cols) * pitch + (pitch - patch.shape[0]) // 2
        plane[y0 : y0 + patch.shape[0], x0 : x0 + patch.shape[1]] = patch
        corners[marker_id] = src + np.array([x0, y0])
    near, far = near_px / tag_px, far_px / tag_px
    top, bottom = pw * far, pw * near
    y_top = 60.0 + rng.uniform(-10, 10)
    y_bottom = y_top + 0.8 * ph * (far + near) / 2  # a floor seen obliquely
    cx = w / 2 + rng.uniform(-30, 30)
    dst = np.array(
        [[cx - top / 2, y_top], [cx + top / 2, y_top], [cx + bottom / 2, y_bottom],
         [cx - bottom / 2, y_bottom]]
    )  # fmt: skip
    a = np.radians(rng.uniform(-8, 8))
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    dst = (dst - dst.mean(0)) @ rot.T + dst.mean(0)
    src = np.array([[0.0, 0.0], [pw, 0.0], [pw, ph], [0.0, ph]]) - 0.5
    hm = cv2.getPerspectiveTransform(src.astype(np.float32), dst.astype(np.float32))
    img = _paste(40.0 + 60.0 * _texture(rng, w, h, 8), plane, src, dst)
    img = _finish(img, rng, 0.8, 2.0)
    img = cv2.imdecode(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])[1], 0)
    truth = {
        i: cv2.perspectiveTransform(q.reshape(-1, 1, 2), hm).reshape(4, 2)
        for i, q in corners.items()
    }
    return img, truth


def charuco_scene(rng: np.random.Generator, dictionary: str, scale: float):
    """A 7x5 ChArUco board (17 markers) photographed in air: board ``scale`` of the image width,
    tilted (top edge further), rotated, lit from one side, blurred and noised, on texture.

    Returns:
        (1280x960 BGR uint8 image, {id: (4, 2) true corners}).
    """
    w, h = 1280, 960
    board = cv2.aruco.CharucoBoard(
        (7, 5), 0.04, 0.03, cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    )
    bw, bh, margin = 1400, 1000, 40
    bitmap = board.generateImage((bw, bh), marginSize=margin, borderBits=1).astype(np.float32)
    px_per_m = min((bw - 2 * margin) / 0.28, (bh - 2 * margin) / 0.20)
    origin = np.array([(bw - 0.28 * px_per_m) / 2, (bh - 0.20 * px_per_m) / 2])
    in_bitmap = {
        int(i): origin + np.asarray(o).reshape(4, 3)[:, :2] * px_per_m - 0.5
        for i, o in zip(board.getIds().ravel(), board.getObjPoints(), strict=True)
    }
    sx, sy = scale * w, scale * w * bh / bw
    quad = _SQUARE * (sx / 2, sy / 2)
    quad[:2] *= (0.75, 0.875)  # the top edge further away
    a = np.radians(rng.uniform(-20, 20))
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    dst = quad @ rot.T + np.array([w / 2, h / 2]) + rng.uniform(-40, 40, 2)
    dst += rng.normal(0, 10, (4, 2))
    src = np.array([[0.0, 0.0], [bw, 0.0], [bw, bh], [0.0, bh]]) - 0.5
    hm = cv2.getPerspectiveTransform(src.astype(np.float32), dst.astype(np.float32))
    light = 0.65 + 0.35 * np.arange(w, dtype=np.float32)[None, :] / w  # a lamp to one side
    img = _paste(60.0 + 120.0 * _texture(rng, w, h, 20), bitmap, src, dst) * light
    img = _finish(img, rng, 1.0, 2.0)
    truth = {
        i: cv2.perspectiveTransform(q.reshape(-1, 1, 2), hm).reshape(4, 2)
        for i, q in in_bitmap.items()
    }
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), truth


def _opencv_ids(img: np.ndarray, dictionary: str) -> set[int]:
    """IDs plain OpenCV decodes (default parameters, grey image)."""
    aruco = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)),
        cv2.aruco.DetectorParameters(),
    )
    grey = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    _c, ids, _r = aruco.detectMarkers(grey)
    return set() if ids is None else {int(i) for i in ids.ravel()}


def _corner_error_px(corners: np.ndarray, truth: np.ndarray) -> float:
    """Largest corner distance (px) of one marker."""
    return float(np.linalg.norm(corners - truth, axis=1).max())


# --------------------------------------------------------------------------- tests


def test_a_rope_across_the_margin_at_a_corner():
    """The own pass's single 23 px threshold window merges the rope with the tag's border (no
    quad); OpenCV's 3 and 13 px windows keep them apart. ``default`` finds the tag with its
    right ID in every view, its corners within 1 px of the truth."""
    default = Detector(DetectorConfig(dictionary=APRILTAG))
    own = Detector(DetectorConfig(dictionary=APRILTAG, opencv_pass=False))
    own_hits = 0
    for seed in range(4):
        img, truth = rope_scene(np.random.default_rng(seed))
        assert _opencv_ids(img, APRILTAG) == {7}
        own_hits += any(d.marker_id == 7 for d in own.detect(img))
        found = default.detect(img)
        assert [d.marker_id for d in found] == [7]
        assert _corner_error_px(found[0].corners_px, truth) < 1.0
    assert own_hits <= 1  # the scene reproduces the real miss (the own pass: 1 of 4)


def test_small_tags_under_perspective_at_least_as_many_as_opencv():
    """Tags of 16-30 px (2-4 px cells): the own pass's blur and stretch lose about half of what
    OpenCV finds (measured 47 of 89); ``default`` finds every tag OpenCV finds in every frame
    (74 % of all tags; the rest are too small for either), with a median mean corner error
    under 0.9 px (measured 0.74; the own pass's corners of these flat tags, biased by
    ``detectInvertedMarker``: 1.6 px), and no ID that is not there."""
    default = Detector(DetectorConfig(dictionary=APRILTAG))
    own = Detector(DetectorConfig(dictionary=APRILTAG, opencv_pass=False))
    hits = total = own_hits = opencv_hits = 0
    errors = []
    for seed in range(3):
        img, truth = small_tags_scene(np.random.default_rng(seed))
        found = {d.marker_id: d.corners_px for d in default.detect(img)}
        ref = _opencv_ids(img, APRILTAG)
        assert ref <= found.keys()
        assert found.keys() <= truth.keys()
        hits += len(found)
        total += len(truth)
        opencv_hits += len(ref)
        own_hits += len({d.marker_id for d in own.detect(img)} & truth.keys())
        errors += [np.linalg.norm(c - truth[i], axis=1).mean() for i, c in found.items()]
    assert hits / total > 0.65
    assert own_hits < 0.7 * opencv_hits  # the scene reproduces the real misses
    assert float(np.median(errors)) < 0.9


@pytest.mark.parametrize("dictionary", ["DICT_4X4_50", APRILTAG])
@pytest.mark.parametrize("scale", [0.75, 0.3])
def test_every_marker_of_a_charuco_board_in_air(dictionary, scale):
    """All 17 markers of a 7x5 ChArUco board, near (markers 70-100 px) and far (30-40 px), with
    every corner within 1.5 px (measured at most 0.96 px far)."""
    default = Detector(DetectorConfig(dictionary=dictionary))
    for seed in range(2):
        img, truth = charuco_scene(np.random.default_rng(seed), dictionary, scale)
        found = {d.marker_id: d.corners_px for d in default.detect(img)}
        assert sorted(found) == sorted(truth)
        assert max(_corner_error_px(c, truth[i]) for i, c in found.items()) < 1.5


@pytest.mark.parametrize("dictionary", ["DICT_4X4_50", APRILTAG])
def test_no_ids_on_noise_texture_and_compression_blocks(dictionary):
    """Every ID of the dictionary allowed: nothing decodes on sensor noise, smooth texture at
    four grains, random blocks, or those blocks JPEG-compressed at quality 15."""
    det = Detector(DetectorConfig(dictionary=dictionary))
    rng = np.random.default_rng(11)
    w, h = 640, 480
    images = [np.clip(rng.normal(128, 40, (h, w)), 0, 255).astype(np.uint8)]
    for grain in (4, 8, 16, 32):
        images.append((255 * _texture(rng, w, h, grain)).astype(np.uint8))
        blocks = (rng.random((h // grain, w // grain)) > 0.5).astype(np.uint8) * 200 + 25
        images.append(cv2.resize(blocks, (w, h), interpolation=cv2.INTER_NEAREST))
        jpeg = cv2.imencode(".jpg", images[-1], [cv2.IMWRITE_JPEG_QUALITY, 15])[1]
        images.append(cv2.imdecode(jpeg, cv2.IMREAD_GRAYSCALE))
    assert sum(len(det.detect(img)) for img in images) == 0


def test_opencv_pass_is_a_config_switch_and_keeps_the_allow_list():
    """``opencv_pass`` follows the pipeline preset (on for ``default`` only) unless set; its
    detections obey the allow-list."""
    img, _truth = small_tags_scene(np.random.default_rng(5))
    ref = _opencv_ids(img, APRILTAG)
    assert len(ref) >= 10
    plain_plus = Detector(DetectorConfig(dictionary=APRILTAG, pipeline="plain", opencv_pass=True))
    assert {d.marker_id for d in plain_plus.detect(img)} == ref
    keep = sorted(ref)[: len(ref) // 2]
    only = Detector(DetectorConfig(dictionary=APRILTAG, ids=tuple(keep)))
    assert sorted(d.marker_id for d in only.detect(img)) == keep
