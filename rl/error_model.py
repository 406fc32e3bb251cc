"""The ``error-model`` observation source: the camera pipeline's behaviour, fitted from images.

Fitting (:func:`fit_error_model`): every frame of a labelled dataset (``datasets synth``) is run
through the perception package (3DBM detector + board PnP); the estimate is compared with the
label. Per water preset, the model keeps

* the detection probability by camera-to-DS range (0.5 m bins) and number of markers
  geometrically in view (0, 1, 2, 3+), with Laplace smoothing;
* per range bin, the bias and covariance of the pose error ``[dt_cam (m), drot (rad)]`` (DS
  translation error in the camera frame and rotation-vector error) over inlier detections, and
  the rate and samples of gross errors (rotation error above ``outlier_deg``, e.g. PnP flips).

The model file (JSON) records the dataset's checksum, frame count, the perception configs and
provenance: it is versioned with its data. Sampling (:class:`ErrorModelSource`) costs a few
microseconds: it projects the board markers to count those in view, draws detection, then an
error from the bin, and applies it to the true pose.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import cv2
import numpy as np
from tqdm import tqdm

from uwdock.calibration.camera import (
    REFERENCE_T_BODYFRD_CAMCV,
    CameraModel,
    resolve_camera,
)
from uwdock.calibration.frames import inv_T, make_T
from uwdock.dockcore.config import to_dict
from uwdock.dockcore.domains import Interval
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_json
from uwdock.dockcore.provenance import provenance
from uwdock.markers.markerset import load_marker_set
from uwdock.markers.view import markers_in_view
from uwdock.perception.ds_pose import DSPoseEstimator
from uwdock.perception.groundtruth import load_dataset
from uwdock.rl.obs_sources import Measurement, SourceNeeds, StepContext
from uwdock.rl.task import DockingTaskConfig

FORMAT = "uwdock.error_model"
VERSION = 1
N_VISIBLE_BINS = 4  # 0, 1, 2, 3+ markers in view


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
    """

    range_bin_m: Annotated[float, Interval(gt=0, le=100)] = 0.5
    range_max_m: Annotated[float, Interval(gt=0, le=1000)] = 8.0
    outlier_deg: Annotated[float, Interval(gt=0, le=180)] = 10.0
    min_inliers: Annotated[int, Interval(ge=1, le=1_000_000)] = 8
    max_outlier_samples: Annotated[int, Interval(ge=0, le=1_000_000)] = 40

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


def fit_error_model(
    dataset: str | os.PathLike[str], cfg: ErrorModelConfig | None = None, progress: bool = True
) -> dict[str, Any]:
    """Fit the model from a labelled dataset folder (see the module docstring)."""
    cfg = cfg or ErrorModelConfig()
    ds = load_dataset(dataset)
    camera, T_bc = resolve_camera(ds.camera_path)
    ms = load_marker_set(ds.marker_set_path)
    estimator = DSPoseEstimator.from_marker_set(ms)
    board = ms.corners_ds()
    corners = np.stack([board[i] for i in sorted(board)])
    n_bins = math.ceil(cfg.range_max_m / cfg.range_bin_m)
    samples: dict[str, list[tuple[int, int, bool, np.ndarray | None]]] = {}
    frames = sorted(ds.frames.items())
    for _, ft in tqdm(frames, desc="fit error model", unit="frame", disable=not progress):
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
        samples.setdefault(water, []).append((r_bin, n_vis, err is not None, err))
    if not samples:
        raise DockError(f"no readable frames in dataset {ds.root}")
    all_samples = [s for v in samples.values() for s in v]
    tables = {w: _tables(v, n_bins, cfg) for w, v in samples.items()}
    tables["all"] = _tables(all_samples, n_bins, cfg)
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
        "tables": tables,
        "provenance": provenance(),
    }


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


def save_error_model(model: dict[str, Any], path: str | os.PathLike[str]) -> Path:
    return atomic_write_json(path, model)


class ErrorModel:
    """A loaded error model (see :func:`load_error_model`)."""

    def __init__(self, data: dict[str, Any], path: Path | None = None) -> None:
        self.data = data
        self.path = path
        c = data["config"]
        self.range_bin_m = float(c["range_bin_m"])
        self.n_bins = len(data["tables"]["all"]["bins"])
        cam = data["camera"]
        self.camera = CameraModel(
            width_px=int(cam["width_px"]),
            height_px=int(cam["height_px"]),
            fx_px=float(cam["fx_px"]),
            fy_px=float(cam["fy_px"]),
            cx_px=float(cam["cx_px"]),
            cy_px=float(cam["cy_px"]),
            dist=tuple(cam["dist"]),
        )
        tb = cam.get("T_body_cam")
        self.T_body_cam = np.asarray(tb) if tb is not None else np.array(REFERENCE_T_BODYFRD_CAMCV)
        self.corners_ds = np.asarray(data["board_corners_ds_m"], dtype=np.float64)
        self._tables = {}
        for water, t in data["tables"].items():
            bins = t["bins"]
            self._tables[water] = {
                "p": np.asarray(t["p_detect"]),
                "bias": np.asarray([b["bias"] for b in bins]),
                "chol": np.stack([np.linalg.cholesky(_psd(np.asarray(b["cov"]))) for b in bins]),
                "cov": np.stack([np.asarray(b["cov"]) for b in bins]),
                "p_out": np.asarray([b["p_outlier"] for b in bins]),
                "outliers": [np.asarray(b["outliers"]) for b in bins],
            }

    def table(self, water: str) -> dict[str, Any]:
        return self._tables.get(water, self._tables["all"])

    def range_bin(self, range_m: float) -> int:
        return min(int(range_m / self.range_bin_m), self.n_bins - 1)


def _psd(c: np.ndarray) -> np.ndarray:
    w, v = np.linalg.eigh(0.5 * (c + c.T))
    return (v * np.maximum(w, 1e-10)) @ v.T


def load_error_model(path: str | os.PathLike[str] | None) -> ErrorModel:
    """Read and validate an error model file (one-line DockError on any problem)."""
    if path is None:
        raise DockError("no error model given: fit one with `rl fit-error-model`")
    p = Path(path)
    if not p.is_file():
        raise DockError(f"error model file not found: {p}")
    try:
        data = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DockError(f"{p}: malformed JSON ({exc})") from None
    if data.get("format") != FORMAT or data.get("version") != VERSION:
        raise DockError(f"{p}: not a version-{VERSION} '{FORMAT}' file")
    try:
        return ErrorModel(data, p)
    except (KeyError, ValueError, TypeError, np.linalg.LinAlgError) as exc:
        raise DockError(f"{p}: malformed error model ({exc})") from None


class ErrorModelSource:
    """Sample camera-pipeline measurements from a fitted :class:`ErrorModel`."""

    name = "error-model"
    needs = SourceNeeds(camera=False, fusion=True, acoustic_fixes=True)

    def __init__(self, model: ErrorModel, task: DockingTaskConfig, water: str = "all") -> None:
        self.model = model
        self.task = task
        self.water = water
        self.rng = np.random.default_rng(0)

    def reset(self, rng: np.random.Generator) -> None:
        self.rng = rng

    def measure(self, ctx: StepContext) -> Measurement | None:
        m = self.model
        T_world_cam = ctx.T_world_body @ m.T_body_cam
        T_cam_ds = inv_T(T_world_cam) @ ctx.T_world_ds
        r = float(np.linalg.norm(T_cam_ds[:3, 3]))
        n_vis = min(count_in_view(m.camera, T_cam_ds, m.corners_ds), N_VISIBLE_BINS - 1)
        t = m.table(self.water)
        k = m.range_bin(r)
        if self.rng.random() >= t["p"][k, n_vis]:
            return None
        if t["outliers"][k].size and self.rng.random() < t["p_out"][k]:
            err = t["outliers"][k][self.rng.integers(len(t["outliers"][k]))]
        else:
            err = t["bias"][k] + t["chol"][k] @ self.rng.standard_normal(6)
        T_meas = T_world_cam @ apply_error(T_cam_ds, err)
        R = T_world_cam[:3, :3]
        cov = np.zeros((4, 4))
        cov[:3, :3] = R @ t["cov"][k][:3, :3] @ R.T + np.eye(3) * 1e-4
        cov[3, 3] = float(t["cov"][k][5, 5]) + 2.5e-5
        return Measurement(T_meas, cov, True)
