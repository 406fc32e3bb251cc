"""The ``error-model`` observation source: the camera pipeline's behaviour, fitted from images.

Fitting (:func:`fit_error_model`): every frame of a labelled dataset (``datasets synth``) is run
through the perception package (3DBM detector + board PnP); the estimate is compared with the
label. Per water preset, the model keeps

* the detection probability by camera-to-DS range (0.5 m bins) and number of markers
  geometrically in view (0, 1, 2, 3+), with Laplace smoothing;
* per range bin, the bias and covariance of the pose error ``[dt_cam (m), drot (rad)]`` (DS
  translation error in the camera frame and rotation-vector error) over inlier detections, and
  the rate and samples of gross errors (rotation error above ``outlier_deg``, e.g. PnP flips).

* memory (version 2, from a dataset whose frames form time sequences, e.g. rendered along PID
  docking trajectories: ``rl trajectories`` + ``datasets render --poses``): per error component,
  the AR(1) coefficient ``rho`` of the *standardised* inlier error ``z = L_k^-1 (err - bias_k)``
  (``L_k`` the range bin's Cholesky factor; so ``z`` is white with unit variance in every bin),
  i.e. its lag-1 autocorrelation over pairs of consecutive frames of a sequence that were both
  inlier detections, with an approximate 95 % interval and the pair count; and, as
  diagnostics, the autocorrelation at lags up to ``MAX_LAG`` steps (an AR(1) decays as
  ``rho^lag``: a slower decay says the memory is longer than the model's) and how often a
  detection follows a detection (or a miss) against what the memoryless model predicts for
  the same frames.

The model file (JSON) records the dataset's checksum, frame count, the perception configs and
provenance: it is versioned with its data. Version-1 files (and tables without a fitted
``rho``) are memoryless. Sampling (:class:`ErrorModelSource`) costs a few microseconds: it
projects the board markers to count those in view, draws detection, then an error from the bin,
and applies it to the true pose. With memory, the standardised error follows
``z_t = rho z_{t-1} + sqrt(1 - rho^2) w_t`` (``w_t`` white) between consecutive inlier
detections and restarts (``z_t = w_t``) after a reset, a miss or a gross error, so the marginal
distribution of each step's error is the memoryless model's.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, NamedTuple

import cv2
import numpy as np
from tqdm import tqdm

from uwdock.calibration.camera import (
    REFERENCE_T_BODYFRD_CAMCV,
    CameraModel,
    check_camera,
    check_T_body_cam,
    resolve_camera,
)
from uwdock.calibration.frames import inv_T, make_T
from uwdock.datasets.loaders import load_checked_dataset
from uwdock.datasets.sequences import FrameSequences, sequences_from_manifest
from uwdock.dockcore.config import to_dict
from uwdock.dockcore.domains import Interval
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_json, check_regular_file, read_text
from uwdock.dockcore.provenance import provenance
from uwdock.markers.markerset import load_marker_set
from uwdock.markers.view import markers_in_view
from uwdock.perception.detector import rendered_3dbm_config
from uwdock.perception.ds_pose import DSPoseEstimator
from uwdock.rl.env.obs_sources import Measurement, SourceNeeds, StepContext
from uwdock.rl.env.task import DockingTaskConfig

FORMAT = "uwdock.error_model"
VERSION = 2
#: Versions :func:`load_error_model` reads (1: no memory).
READ_VERSIONS = (1, 2)
N_VISIBLE_BINS = 4  # 0, 1, 2, 3+ markers in view
N_ERR = 6  # error components: dt_cam xyz (m), rotation vector (rad)


@dataclass(frozen=True)
class ErrorModelConfig:
    """Binning of the fitted error model.

    Attributes:
        range_bin_m: width of the range bins (m).
        range_max_m: ranges beyond this share the last bin (m).
        outlier_deg: a detection whose rotation error exceeds this is a gross error (deg).
        min_inliers: fewest inlier detections for a bin's own covariance; sparser bins borrow
            from their neighbours (-).
        max_outlier_samples: gross-error samples kept per bin (-).
        min_pairs: fewest pairs of consecutive inlier detections for a table's AR(1) fit;
            with fewer, the table stays memoryless (-).
    """

    range_bin_m: Annotated[float, Interval(gt=0, le=100)] = 0.5
    range_max_m: Annotated[float, Interval(gt=0, le=1000)] = 8.0
    outlier_deg: Annotated[float, Interval(gt=0, le=180)] = 10.0
    min_inliers: Annotated[int, Interval(ge=1, le=1_000_000)] = 8
    max_outlier_samples: Annotated[int, Interval(ge=0, le=1_000_000)] = 40
    min_pairs: Annotated[int, Interval(ge=2, le=1_000_000)] = 30

    def validate(self) -> None:
        bins = self.range_max_m / self.range_bin_m
        if bins > 1000:
            raise ValueError(
                f"range_bin_m: {self.range_bin_m:g} m over {self.range_max_m:g} m gives "
                f"{bins:.0f} bins (at most 1000)"
            )


def _dataset_checksum(root: Path) -> str:
    h = hashlib.sha256()
    for name in ("dataset.json", "labels.jsonl"):
        h.update((root / name).read_bytes())
    return h.hexdigest()


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """(6,) ``[t_est - t_true (m), rotvec(R_est R_true^T) (rad)]`` of two camera-frame poses."""
    from scipy.spatial.transform import Rotation  # half a second to import: only when used

    dt = T_est[:3, 3] - T_true[:3, 3]
    drot = Rotation.from_matrix(T_est[:3, :3] @ T_true[:3, :3].T).as_rotvec()
    return np.concatenate([dt, drot])


def apply_error(T_true: np.ndarray, err: np.ndarray) -> np.ndarray:
    """Inverse of :func:`pose_error`: the estimate with error ``err`` from the truth."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(err[3:]).as_matrix() @ T_true[:3, :3]
    return make_T(R, T_true[:3, 3] + err[:3])


#: Corners nearer than this to the camera plane count as out of view (m): nothing of the DS is
#: imaged that close.
MIN_VIEW_DEPTH_M = 0.05


def count_in_view(camera: CameraModel, T_cam_ds: np.ndarray, corners_ds: np.ndarray) -> int:
    """Markers with all four corners in front of the camera and inside the image (lens
    distortion applied: :func:`uwdock.markers.view.markers_in_view`).

    Args:
        camera: the camera model.
        T_cam_ds: (4, 4) DS pose in the OpenCV camera frame.
        corners_ds: (M, 4, 3) board corners in the DS frame (m).
    """
    return int(markers_in_view(camera, T_cam_ds, corners_ds, MIN_VIEW_DEPTH_M).sum())


class FrameSample(NamedTuple):
    """One dataset frame run through the perception package (the fit's input).

    Attributes:
        frame: frame index in the dataset.
        water: water preset name ("unknown" without one).
        r_bin: range bin of the true camera-to-DS distance.
        n_vis: markers geometrically in view, capped at ``N_VISIBLE_BINS - 1``.
        err: (6,) pose error ``[dt_cam (m), drot (rad)]`` of the estimate, None when the DS was
            not detected.
    """

    frame: int
    water: str
    r_bin: int
    n_vis: int
    err: np.ndarray | None


def fit_error_model(
    dataset: str | os.PathLike[str], cfg: ErrorModelConfig | None = None, progress: bool = True
) -> dict[str, Any]:
    """Fit the model from a labelled dataset folder (see the module docstring); its memory when
    the dataset's frames form time sequences (``dataset.json`` ``sequences``)."""
    cfg = cfg or ErrorModelConfig()
    ds = load_checked_dataset(dataset)  # labels inside it, in range, images regular files
    frames = sorted(ds.frames.items())
    sequences = sequences_from_manifest(ds.manifest, len(frames), str(ds.root / "dataset.json"))
    if sequences is not None and [k for k, _ in frames] != list(range(len(frames))):
        raise DockError(f"{ds.root}: a dataset with sequences must number its frames 0..N-1")
    camera, T_bc = resolve_camera(ds.camera_path)
    ms = load_marker_set(ds.marker_set_path)
    estimator = DSPoseEstimator.from_marker_set(ms, rendered_3dbm_config())  # as the camera
    board = ms.corners_ds()
    corners = np.stack([board[i] for i in sorted(board)])
    n_bins = math.ceil(cfg.range_max_m / cfg.range_bin_m)
    samples: list[FrameSample] = []
    for k, ft in tqdm(frames, desc="fit error model", unit="frame", disable=not progress):
        img_bgr = cv2.imread(str(ds.root / ft.image)) if ft.image else None
        if img_bgr is None:
            continue
        water = (ft.water or {}).get("preset", "unknown")
        r_bin = min(int(ft.range_m / cfg.range_bin_m), n_bins - 1)
        n_vis = min(count_in_view(camera, ft.T_cam_ds, corners), N_VISIBLE_BINS - 1)
        # the camera source's estimator, with the attitude when the label has it
        T_world_cam = None if ft.T_world_body is None else ft.T_world_body @ T_bc
        T_est = estimator.estimate(img_bgr, camera, T_world_cam).T_cam_ds
        err = None if T_est is None else pose_error(T_est, ft.T_cam_ds)
        samples.append(FrameSample(k, water, r_bin, n_vis, err))
    if not samples:
        raise DockError(f"no readable frames in dataset {ds.root}")
    return {
        "format": FORMAT,
        "version": VERSION,
        "dataset": {
            "path": str(ds.root.resolve()),
            "sha256": _dataset_checksum(ds.root),
            "frames": len(frames),
        },
        "config": to_dict(cfg),
        "detector": to_dict(estimator.detector.cfg),
        "board_pose": to_dict(estimator.board_cfg),
        "camera": {
            **to_dict(camera),
            "T_body_cam": T_bc.tolist(),
        },
        "board_corners_ds_m": corners.tolist(),
        "sequences": _sequence_summary(sequences),
        "tables": fit_tables(samples, n_bins, cfg, sequences),
        "provenance": provenance(),
    }


def _sequence_summary(sequences: FrameSequences | None) -> dict[str, Any] | None:
    """What the dataset's sequences are: count, frames, step duration (s); None without."""
    if sequences is None:
        return None
    return {
        "sequences": len(set(sequences.sequence.tolist())),
        "frames": len(sequences),
        "consecutive_pairs": len(sequences.consecutive_pairs()[0]),
        "step_s": sequences.step_s(),
    }


def fit_tables(
    samples: Sequence[FrameSample],
    n_bins: int,
    cfg: ErrorModelConfig,
    sequences: FrameSequences | None = None,
) -> dict[str, dict[str, Any]]:
    """The model's tables from per-frame samples: one per water preset and "all" (module
    docstring), each with its memory (``ar1``, ``detection_pairs``) when ``sequences`` (indexed
    by ``FrameSample.frame``) are given."""
    by_water: dict[str, list[FrameSample]] = {}
    for smp in samples:
        by_water.setdefault(smp.water, []).append(smp)
    by_water["all"] = [s for group in by_water.values() for s in group]  # grouped, as in v1
    tables = {}
    for water, group in by_water.items():
        table = _tables([(s.r_bin, s.n_vis, s.err is not None, s.err) for s in group], n_bins, cfg)
        if sequences is not None:
            table.update(_memory(group, table, sequences, cfg))
        tables[water] = table
    return tables


def _tables(samples, n_bins: int, cfg: ErrorModelConfig) -> dict[str, Any]:
    det = np.zeros((n_bins, N_VISIBLE_BINS))
    tot = np.zeros((n_bins, N_VISIBLE_BINS))
    errs: list[list[np.ndarray]] = [[] for _ in range(n_bins)]
    for r_bin, n_vis, ok, err in samples:
        tot[r_bin, n_vis] += 1
        det[r_bin, n_vis] += ok
        if ok:
            errs[r_bin].append(err)
    p_detect = (det + 0.5) / (tot + 1.0)  # Jeffreys-smoothed rate
    p_detect[:, 0] = np.minimum(p_detect[:, 0], det[:, 0].sum() / max(tot[:, 0].sum(), 1))
    bins = []
    thr = math.radians(cfg.outlier_deg)
    for k in range(n_bins):
        # borrow neighbours until enough inliers
        lo, hi = k, k
        while True:
            pool = [e for j in range(lo, hi + 1) for e in errs[j]]
            inl = [e for e in pool if np.linalg.norm(e[3:]) <= thr]
            if len(inl) >= cfg.min_inliers or (lo == 0 and hi == n_bins - 1):
                break
            lo, hi = max(lo - 1, 0), min(hi + 1, n_bins - 1)
        out = [e for e in pool if np.linalg.norm(e[3:]) > thr]
        if inl:
            a = np.asarray(inl)
            mean = a.mean(axis=0)
            cov = np.cov(a.T) if len(a) > 1 else np.diag(np.full(6, 1e-4))
        else:
            mean, cov = np.zeros(6), np.diag([0.05**2] * 3 + [math.radians(3) ** 2] * 3)
        cov = cov + np.diag([1e-6] * 3 + [1e-6] * 3)
        bins.append(
            {
                "range_m": [k * cfg.range_bin_m, (k + 1) * cfg.range_bin_m],
                "detections": len(errs[k]),
                "pooled_inliers": len(inl),
                "bias": mean.tolist(),
                "cov": cov.tolist(),
                "p_outlier": len(out) / max(len(pool), 1),
                "outliers": [e.tolist() for e in out[: cfg.max_outlier_samples]],
            }
        )
    return {"p_detect": p_detect.tolist(), "frames": tot.tolist(), "bins": bins}


def standardise(err: np.ndarray, bias: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(..., 6) standardised errors ``L^-1 (err - bias)`` (``L L^T = cov``, the Cholesky factor
    the sampler uses), white with unit variance when ``err`` follows the bin's distribution.

    Args:
        err: (..., 6) pose errors ``[dt_cam (m), drot (rad)]``.
        bias: (6,) the bin's bias (m, rad).
        cov: (6, 6) the bin's covariance (m^2, rad^2).
    """
    L = np.linalg.cholesky(_psd(np.asarray(cov, np.float64)))
    d = np.asarray(err, np.float64) - np.asarray(bias, np.float64)
    return np.linalg.solve(L, d.reshape(-1, N_ERR).T).T.reshape(d.shape)


def ar1_fit(z_prev: np.ndarray, z_next: np.ndarray) -> dict[str, Any]:
    """Per-component lag-1 autocorrelation of standardised errors over consecutive pairs.

    ``rho_k = sum(a_k b_k) / sqrt(sum(a_k^2) sum(b_k^2))`` (not centred: the errors are already
    bias-free, and a view-dependent bias that persists from frame to frame is part of the
    memory), with Bartlett's approximate 95 % interval for an AR(1) series,
    ``rho +- 1.96 sqrt((1 - rho^2) / P)``, clipped to [-1, 1].

    Args:
        z_prev: (P, K) standardised errors at step t.
        z_next: (P, K) the same components at step t + 1.

    Returns:
        ``{"rho": [K], "rho_ci95": [[lo, hi] x K], "pairs": P}``.
    """
    a = np.asarray(z_prev, np.float64)
    b = np.asarray(z_next, np.float64)
    if a.shape != b.shape or a.ndim != 2 or len(a) < 2:
        raise ValueError(f"ar1_fit: need two (P >= 2, K) arrays, got {a.shape} and {b.shape}")
    rho = (a * b).sum(axis=0) / np.sqrt((a * a).sum(axis=0) * (b * b).sum(axis=0))
    rho = np.clip(np.nan_to_num(rho), -0.999, 0.999)  # a constant component: no evidence
    half = 1.96 * np.sqrt((1.0 - rho**2) / len(a))
    ci = np.clip(np.stack([rho - half, rho + half], axis=1), -1.0, 1.0)
    return {"rho": rho.tolist(), "rho_ci95": ci.tolist(), "pairs": len(a)}


#: Longest lag of the autocorrelation diagnostic (steps).
MAX_LAG = 5


def _autocorrelation(z: dict[int, np.ndarray], sequences: FrameSequences) -> dict[str, list]:
    """Standardised autocorrelation at lags 1..``MAX_LAG`` over pairs of inlier frames that
    many steps apart in a sequence (the frames between may be anything): ``{"lag", "rho"
    (per lag, 6 values or None with < 2 pairs), "pairs"}``."""
    out: dict[str, list] = {"lag": [], "rho": [], "pairs": []}
    for lag in range(1, MAX_LAG + 1):
        first, then = (a.tolist() for a in sequences.consecutive_pairs(lag))
        ij = [(i, j) for i, j in zip(first, then, strict=True) if i in z and j in z]
        fit = None
        if len(ij) >= 2:
            fit = ar1_fit(np.stack([z[i] for i, _ in ij]), np.stack([z[j] for _, j in ij]))
        out["lag"].append(lag)
        out["rho"].append(None if fit is None else fit["rho"])
        out["pairs"].append(len(ij))
    return out


def _memory(
    group: Sequence[FrameSample],
    table: dict[str, Any],
    sequences: FrameSequences,
    cfg: ErrorModelConfig,
) -> dict[str, Any]:
    """A table's memory: AR(1) of the standardised inlier errors (``ar1``; ``rho`` null with
    fewer than ``cfg.min_pairs`` pairs) and the detection persistence diagnostic."""
    thr = math.radians(cfg.outlier_deg)
    by_frame = {s.frame: s for s in group}
    bins = table["bins"]
    p_detect = np.asarray(table["p_detect"])
    z, u = {}, {}  # inlier frame -> standardised error; error scaled by the bin's std only
    for s in group:
        if s.err is not None and np.linalg.norm(s.err[3:]) <= thr:
            bias, cov = np.asarray(bins[s.r_bin]["bias"]), np.asarray(bins[s.r_bin]["cov"])
            z[s.frame] = standardise(s.err, bias, cov)
            u[s.frame] = (s.err - bias) / np.sqrt(np.diag(cov))
    pairs = []
    counts = {True: [0, 0, 0.0], False: [0, 0, 0.0]}  # prev detected -> [pairs, hits, expected]
    for i, j in zip(*sequences.consecutive_pairs(), strict=True):
        si, sj = by_frame.get(int(i)), by_frame.get(int(j))
        if si is None or sj is None:
            continue
        c = counts[si.err is not None]
        c[0] += 1
        c[1] += sj.err is not None
        c[2] += float(p_detect[sj.r_bin, sj.n_vis])
        if si.frame in z and sj.frame in z:
            pairs.append((si.frame, sj.frame))
    if len(pairs) >= cfg.min_pairs:
        fi, fj = zip(*pairs, strict=True)
        ar1 = ar1_fit(np.stack([z[f] for f in fi]), np.stack([z[f] for f in fj]))
        # diagnostics: each error component's own lag-1 autocorrelation (m or rad, not mixed),
        # and the standardised autocorrelation at longer lags (AR(1): rho^lag)
        ar1["rho_per_axis"] = ar1_fit(np.stack([u[f] for f in fi]), np.stack([u[f] for f in fj]))[
            "rho"
        ]
        ar1["autocorrelation"] = _autocorrelation(z, sequences)
    else:
        ar1 = {"rho": None, "rho_ci95": None, "pairs": len(pairs)}
    persistence = {
        ("after_detection" if prev else "after_miss"): {
            "pairs": n,
            "detected": hits / n if n else None,
            "memoryless": expected / n if n else None,
        }
        for prev, (n, hits, expected) in counts.items()
    }
    return {"ar1": ar1, "detection_pairs": persistence}


def save_error_model(model: dict[str, Any], path: str | os.PathLike[str]) -> Path:
    return atomic_write_json(path, model)


class ErrorModel:
    """A loaded error model (see :func:`load_error_model`)."""

    def __init__(self, data: dict[str, Any], path: Path | None = None) -> None:
        self.data = data
        self.path = path
        c = data["config"]
        self.range_bin_m = float(_numbers(c["range_bin_m"], "config.range_bin_m", (), gt=0))
        if not isinstance(data["tables"], dict) or "all" not in data["tables"]:
            raise ValueError("tables: must hold an 'all' table")
        self.n_bins = len(data["tables"]["all"]["bins"])
        cam = data["camera"]
        try:
            self.camera = CameraModel(
                width_px=int(cam["width_px"]),
                height_px=int(cam["height_px"]),
                fx_px=float(cam["fx_px"]),
                fy_px=float(cam["fy_px"]),
                cx_px=float(cam["cx_px"]),
                cy_px=float(cam["cy_px"]),
                dist=tuple(cam["dist"]),
            )
            check_camera(self.camera)
        except ValueError as exc:
            raise ValueError(f"camera.{exc}") from None
        tb = cam.get("T_body_cam")
        self.T_body_cam = (
            check_T_body_cam(_numbers(tb, "camera.T_body_cam", (4, 4)), "camera.T_body_cam")
            if tb is not None
            else np.array(REFERENCE_T_BODYFRD_CAMCV)
        )
        self.corners_ds = _numbers(data["board_corners_ds_m"], "board_corners_ds_m", (-1, 4, 3))
        memory = data.get("version", VERSION) >= 2  # version 1: memoryless
        seqs = data.get("sequences") if memory else None
        step = seqs.get("step_s") if isinstance(seqs, dict) else None
        #: duration of the fitted AR(1) step (s), None without sequences
        self.step_s: float | None = None if step is None else float(step)
        self._tables = {}
        for water, t in data["tables"].items():
            rho = _rho(t.get("ar1") if memory else None, water)
            if np.any(rho != 0) and not (self.step_s is not None and 0 < self.step_s < math.inf):
                raise ValueError(f"table '{water}': ar1 rho needs sequences.step_s > 0")
            table = _checked_table(t, f"tables.{water}", self.n_bins)
            table["rho"] = rho
            self._tables[water] = table

    def table(self, water: str) -> dict[str, Any]:
        return self._tables.get(water, self._tables["all"])

    def range_bin(self, range_m: float) -> int:
        return min(int(range_m / self.range_bin_m), self.n_bins - 1)


def _numbers(
    value: Any,
    key: str,
    shape: tuple[int, ...] | None = None,
    lo: float = -math.inf,
    hi: float = math.inf,
    gt: float | None = None,
) -> np.ndarray:
    """``value`` of a model file as a float64 array of ``shape`` (-1: any length) whose every
    element is finite and in ``[lo, hi]`` (``> gt`` when given).

    Raises:
        ValueError: one line naming ``key`` and the first bad element (``key[3][1]``).
    """
    if isinstance(value, (bool, str)) or value is None:
        raise ValueError(f"{key}: must be numbers, got {_show(value)}")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{key}: must be numbers, got {_show(value)}") from None
    fits = shape is None or (
        arr.ndim == len(shape) and all(n in (-1, m) for n, m in zip(shape, arr.shape, strict=True))
    )
    if not fits:
        want = " x ".join("N" if n == -1 else str(n) for n in shape) or "a number"
        raise ValueError(f"{key}: must be {want}, got shape {arr.shape}")
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(arr) | (arr < lo) | (arr > hi)
        if gt is not None:
            bad |= arr <= gt
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        where = key + "".join(f"[{i}]" for i in idx)
        if gt is not None:
            domain = f" > {gt:g}"
        elif lo > -math.inf and hi < math.inf:
            domain = f" in [{lo:g}, {hi:g}]"
        elif lo > -math.inf:
            domain = f" >= {lo:g}"
        else:
            domain = ""
        raise ValueError(f"{where}: must be a finite number{domain}, got {float(arr[idx])!r}")
    return arr


def _show(value: Any) -> str:
    text = " ".join(repr(value).split())
    return text if len(text) <= 60 else text[:57] + "..."


def _checked_table(t: Any, key: str, n_bins: int) -> dict[str, Any]:
    """A table of a model file as arrays, every value in its domain: detection and outlier
    probabilities in [0, 1], finite biases, covariances with non-negative variances, finite
    outlier samples (ValueError naming the key otherwise)."""
    if not isinstance(t, dict):
        raise ValueError(f"{key}: must be a table, got {_show(t)}")
    bins = t["bins"]
    if not isinstance(bins, list) or len(bins) != n_bins:
        raise ValueError(f"{key}.bins: must be a list of {n_bins} bins (as tables.all)")
    p = _numbers(t["p_detect"], f"{key}.p_detect", (n_bins, N_VISIBLE_BINS), 0.0, 1.0)
    bias, cov, p_out, outliers = [], [], [], []
    for k, b in enumerate(bins):
        where = f"{key}.bins[{k}]"
        if not isinstance(b, dict):
            raise ValueError(f"{where}: must be a table, got {_show(b)}")
        bias.append(_numbers(b["bias"], f"{where}.bias", (N_ERR,)))
        c = _numbers(b["cov"], f"{where}.cov", (N_ERR, N_ERR))
        _numbers(np.diag(c), f"{where}.cov diagonal (variances)", (N_ERR,), lo=0.0)
        cov.append(_checked_cov(c, f"{where}.cov"))
        p_out.append(float(_numbers(b["p_outlier"], f"{where}.p_outlier", (), 0.0, 1.0)))
        raw = b["outliers"]
        outliers.append(
            np.zeros((0, N_ERR))
            if isinstance(raw, list) and not raw
            else _numbers(raw, f"{where}.outliers", (-1, N_ERR))
        )
    return {
        "p": p,
        "bias": np.asarray(bias),
        "chol": np.stack([np.linalg.cholesky(_psd(c)) for c in cov]),
        "cov": np.stack(cov),
        "p_out": np.asarray(p_out),
        "outliers": outliers,
    }


def _rho(ar1: Any, water: str) -> np.ndarray:
    """(6,) AR(1) coefficients of a table's ``ar1`` entry (zeros: memoryless, for a missing
    entry or a null ``rho``); ValueError naming the table when malformed."""
    raw = None if ar1 is None else ar1["rho"]
    if raw is None:
        return np.zeros(N_ERR)
    try:
        rho = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError):
        rho = np.full(1, np.nan)
    if rho.shape != (N_ERR,) or not np.all(np.abs(rho) < 1.0):  # also refuses NaN
        shown = " ".join(str(raw).split())[:80]
        raise ValueError(
            f"table '{water}': ar1 rho must be {N_ERR} numbers in (-1, 1), got {shown}"
        )
    return rho


#: Largest asymmetry ``|C - C^T|`` a covariance may carry, relative to its largest element
#: ``max|C|`` (-): JSON round-trips float64 exactly, so a fitted model is symmetric to the bit;
#: 1e-9 leaves room for a file written by other tools (a few ulps of a 6x6 product), while any
#: asymmetry a person or a bug puts in (a copied entry, a transposed block) is orders larger.
COV_SYMMETRY_RTOL = 1e-9


def _checked_cov(c: np.ndarray, key: str) -> np.ndarray:
    """A (6, 6) covariance of a model file, symmetric (to :data:`COV_SYMMETRY_RTOL` of its
    scale) and positive semi-definite (no eigenvalue below ``-COV_SYMMETRY_RTOL`` of its scale:
    a zero variance, an exact component, is a covariance), as it is: nothing is symmetrised or
    projected, since a projected indefinite matrix is another error model (one whose
    off-diagonal entries were wrong gave 0.7 m errors where the file's variances said 5 mm).
    The sampler's Cholesky factor floors eigenvalues at 1e-10 (:func:`_psd`), as it always did.

    Raises:
        ValueError: one line naming ``key`` and what is wrong (the worst entry, or the smallest
            eigenvalue).
    """
    scale = float(np.max(np.abs(c)))
    asym = np.abs(c - c.T)
    if asym.max() > COV_SYMMETRY_RTOL * scale:
        i, j = (int(k) for k in np.unravel_index(int(np.argmax(asym)), asym.shape))
        raise ValueError(
            f"{key}: not symmetric ({key}[{i}][{j}] = {c[i, j]:.6g} but [{j}][{i}] = {c[j, i]:.6g})"
        )
    w = np.linalg.eigvalsh(c)
    if w[0] < -COV_SYMMETRY_RTOL * scale:
        raise ValueError(
            f"{key}: not positive semi-definite (smallest eigenvalue {w[0]:.3g}): "
            "not the covariance of any error"
        )
    return c


def _psd(c: np.ndarray) -> np.ndarray:
    w, v = np.linalg.eigh(0.5 * (c + c.T))
    return (v * np.maximum(w, 1e-10)) @ v.T


def load_error_model(path: str | os.PathLike[str] | None) -> ErrorModel:
    """Read and validate an error model file (one-line DockError on any problem)."""
    if path is None:
        raise DockError("no error model given: fit one with `rl fit-error-model`")
    p = Path(path)
    check_regular_file(p, "error model file")
    try:
        data = json.loads(read_text(p, "error model file"))
    except json.JSONDecodeError as exc:
        raise DockError(f"{p}: malformed JSON ({exc})") from None
    except ValueError as exc:  # an integer past Python's int-to-str limit (4300 digits)
        why = "a number too long" if "digits" in str(exc) else " ".join(str(exc).split())[:120]
        raise DockError(f"{p}: malformed JSON ({why})") from None
    except RecursionError:
        raise DockError(f"{p}: malformed JSON (nested too deeply)") from None
    if not isinstance(data, dict):
        raise DockError(f"{p}: not an error model (a JSON {type(data).__name__}, not an object)")
    version = data.get("version")
    if data.get("format") != FORMAT or isinstance(version, bool) or version not in READ_VERSIONS:
        raise DockError(f"{p}: not a version-{'/'.join(map(str, READ_VERSIONS))} '{FORMAT}' file")
    try:
        return ErrorModel(data, p)
    except (KeyError, ValueError, TypeError, np.linalg.LinAlgError) as exc:
        raise DockError(f"{p}: malformed error model ({exc})") from None


class ErrorModelSource:
    """Sample camera-pipeline measurements from a fitted :class:`ErrorModel`.

    Args:
        model: the loaded model.
        task: docking geometry.
        water: the table to sample ("all" when the model has none of that name).
        temporal: sample the table's fitted memory (AR(1) per standardised error component,
            module docstring); False, or a table without it: every step independent. With
            ``rho = 0`` the draws are bit-identical to the memoryless sampler's.
    """

    name = "error-model"
    needs = SourceNeeds(camera=False, fusion=True, acoustic_fixes=True)

    def __init__(
        self, model: ErrorModel, task: DockingTaskConfig, water: str = "all", temporal: bool = True
    ) -> None:
        self.model = model
        self.task = task
        self.water = water
        self.temporal = temporal
        self.rng = np.random.default_rng(0)
        #: standardised error of the last inlier detection and its time (s); None: no memory
        self._z_prev: np.ndarray | None = None
        self._t_prev_s = 0.0

    def reset(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self._z_prev = None

    def _standard_error(self, rho: np.ndarray, time_s: float) -> np.ndarray:
        """(6,) this step's standardised error: one ``standard_normal(6)`` draw ``w``, carried
        through the AR(1) recursion from the previous inlier detection when there is one.

        Over ``n = dt / step_s`` fitted steps the coefficient is ``rho^n`` (``dt`` since that
        detection, s); a measurement at the same or an earlier time starts afresh."""
        w = self.rng.standard_normal(N_ERR)
        z = w
        prev, step_s = self._z_prev, self.model.step_s
        if self.temporal and prev is not None and step_s and np.any(rho != 0):
            n = (time_s - self._t_prev_s) / step_s
            if n > 0:
                r = np.sign(rho) ** round(n) * np.abs(rho) ** n
                z = r * prev + np.sqrt(1.0 - r * r) * w
        self._z_prev, self._t_prev_s = z, time_s
        return z

    def measure(self, ctx: StepContext) -> Measurement | None:
        m = self.model
        T_world_cam = ctx.T_world_body @ m.T_body_cam
        T_cam_ds = inv_T(T_world_cam) @ ctx.T_world_ds
        r = float(np.linalg.norm(T_cam_ds[:3, 3]))
        n_vis = min(count_in_view(m.camera, T_cam_ds, m.corners_ds), N_VISIBLE_BINS - 1)
        t = m.table(self.water)
        k = m.range_bin(r)
        if self.rng.random() >= t["p"][k, n_vis]:
            self._z_prev = None  # a miss breaks the chain
            return None
        if t["outliers"][k].size and self.rng.random() < t["p_out"][k]:
            err = t["outliers"][k][self.rng.integers(len(t["outliers"][k]))]
            self._z_prev = None  # so does a gross error
        else:
            err = t["bias"][k] + t["chol"][k] @ self._standard_error(t["rho"], ctx.time_s)
        T_meas = T_world_cam @ apply_error(T_cam_ds, err)
        R = T_world_cam[:3, :3]
        cov = np.zeros((4, 4))
        cov[:3, :3] = R @ t["cov"][k][:3, :3] @ R.T + np.eye(3) * 1e-4
        cov[3, 3] = float(t["cov"][k][5, 5]) + 2.5e-5
        return Measurement(T_meas, cov, True)
