"""The evaluation report's numbers and pictures.

* Statistics: :class:`EvalRecord` (one frame of one pipeline against its ground truth),
  :func:`summarise` (rates, time, reprojection error, pose-error percentiles, bins by range and
  viewing angle, pose jitter on static stretches), :func:`compare_rows` / :func:`markdown_table`.
* Plots (matplotlib, Agg backend, written atomically as PNG): detection rate and pose error vs
  range, and a per-frame timeline. Annotated frames and the contact sheet are drawn in
  :mod:`perception.video`.

Error definitions (on ``T_cam_ds``): translation error = distance between the estimated and the
true DS origin in the camera frame (m); rotation error = geodesic angle between the estimated and
the true rotation (deg). Percentiles are linear-interpolated (numpy's default).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np

from uwdock.calibration.frames import rotation_angle_deg
from uwdock.dockcore.domains import Interval, Positive
from uwdock.dockcore.io import atomic_path
from uwdock.dockcore.media import display_name
from uwdock.perception.groundtruth import FrameTruth

__all__ = [
    "COMPARE_COLUMNS",
    "EvalRecord",
    "ReportConfig",
    "compare_rows",
    "markdown_table",
    "plot_error_vs_range",
    "plot_rate_vs_range",
    "plot_timeline",
    "pose_jitter",
    "summarise",
]


#: A binned table lists every bin between its first and last occupied one up to this many bins
#: (then only the occupied ones).
MAX_BINS = 1000


@dataclass(frozen=True)
class ReportConfig:
    """What ``perception eval`` measures and draws.

    Attributes:
        range_bin_m: width of the range bins (m, 0.01 ... 1000).
        angle_bin_deg: width of the viewing-angle bins (deg, 0.1 ... 180).
        static_tol_m: a ground-truth stretch is static while every pose stays within this
            distance of the stretch's first pose (m, > 0)...
        static_tol_deg: ...and within this rotation angle of it (deg, (0, 180]).
        static_min_frames: shortest static stretch used for the jitter (frames, >= 2).
        flip_threshold_deg: rotation errors above this count as gross errors / flips (deg,
            (0, 180]).
        contact_sheet_frames: annotated frames on the contact sheet (0: none; at most 64).
        thumbnail_width_px: width of each contact-sheet tile (px, 16 ... 1024).
        axis_length_m: length of the drawn DS axes (m, (0, 100]).
    """

    range_bin_m: Annotated[float, Interval(ge=0.01, le=1000.0)] = 0.5
    angle_bin_deg: Annotated[float, Interval(ge=0.1, le=180.0)] = 10.0
    static_tol_m: Positive = 0.001
    static_tol_deg: Annotated[float, Interval(gt=0.0, le=180.0)] = 0.1
    static_min_frames: Annotated[int, Interval(ge=2, le=10**9)] = 5
    flip_threshold_deg: Annotated[float, Interval(gt=0.0, le=180.0)] = 10.0
    contact_sheet_frames: Annotated[int, Interval(ge=0, le=64)] = 12
    thumbnail_width_px: Annotated[int, Interval(ge=16, le=1024)] = 400
    axis_length_m: Annotated[float, Interval(gt=0.0, le=100.0)] = 0.3


# --------------------------------------------------------------------------- statistics


@dataclass
class EvalRecord:
    """One frame as one pipeline saw it, with its ground truth when there is one.

    Attributes:
        frame: frame index.
        name: image file name or ``frame_000123``.
        corrupt: the frame could not be decoded (nothing else is set).
        ids: detected marker IDs, ascending.
        ms: detection + pose time (ms).
        T_cam_ds: (4, 4) estimated DS pose, or None.
        rms_px: RMS corner reprojection error of the pose (px), or None.
        truth: the frame's ground truth, or None.
        corner_errors_px: mean corner distance (px) to the labelled corners, per detected marker
            that is labelled visible.
    """

    frame: int
    name: str
    corrupt: bool = False
    ids: tuple[int, ...] = ()
    ms: float = float("nan")
    T_cam_ds: np.ndarray | None = None
    rms_px: float | None = None
    truth: FrameTruth | None = None
    corner_errors_px: tuple[float, ...] = ()

    @property
    def translation_error_m(self) -> float | None:
        if self.truth is None or self.T_cam_ds is None:
            return None
        return float(np.linalg.norm(self.T_cam_ds[:3, 3] - self.truth.T_cam_ds[:3, 3]))

    @property
    def rotation_error_deg(self) -> float | None:
        if self.truth is None or self.T_cam_ds is None:
            return None
        return rotation_angle_deg(self.T_cam_ds, self.truth.T_cam_ds)

    def labelled(self) -> bool:
        """True when the ground truth lists markers (a labelled dataset, not a pose CSV)."""
        return self.truth is not None and len(self.truth.markers) > 0

    def to_json(self) -> dict[str, Any]:
        """The ``frames.jsonl`` object of this frame."""
        name = display_name(self.name)  # not UTF-8: its bytes as \\xNN (valid text)
        if self.corrupt:
            return {"frame": self.frame, "name": name, "corrupt": True}
        out: dict[str, Any] = {
            "frame": self.frame,
            "name": name,
            "corrupt": False,
            "ids": list(self.ids),
            "n_markers": len(self.ids),
            "T_cam_ds": None if self.T_cam_ds is None else self.T_cam_ds.tolist(),
            "reprojection_rms_px": self.rms_px,
            "ms": self.ms,
        }
        t = self.truth
        if t is not None:
            out.update(
                range_m=t.range_m,
                view_angle_deg=t.view_angle_deg,
                translation_error_m=self.translation_error_m,
                rotation_error_deg=self.rotation_error_deg,
                water_preset=None if t.water is None else t.water.get("preset"),
            )
            if self.labelled():
                in_image = {m.marker_id for m in t.markers if m.in_image}
                out.update(
                    visible_ids=sorted(t.visible_ids),
                    missed_ids=sorted(t.visible_ids - set(self.ids)),
                    false_ids=sorted(set(self.ids) - in_image),
                    corner_error_px_mean=_mean(self.corner_errors_px),
                )
        return out


def _mean(values: Sequence[float]) -> float | None:
    return float(np.mean(values)) if len(values) else None


def _pct(values: Sequence[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if len(values) else None


def _rate(num: int, den: int) -> float | None:
    return num / den if den else None


def _errors(recs: Sequence[EvalRecord], prefix: str = "") -> dict[str, Any]:
    """Pose and marker statistics of frames with ground truth."""
    e_t = [r.translation_error_m for r in recs if r.translation_error_m is not None]
    e_r = [r.rotation_error_deg for r in recs if r.rotation_error_deg is not None]
    out: dict[str, Any] = {}
    for key, vals in (("translation_error_m", e_t), ("rotation_error_deg", e_r)):
        for q, tag in ((50, "median"), (90, "p90"), (95, "p95")):
            out[f"{prefix}{key}_{tag}"] = _pct(vals, q)
    labelled = [r for r in recs if r.labelled()]
    visible = sum(len(r.truth.visible_ids) for r in labelled)
    hits = sum(len(r.truth.visible_ids & set(r.ids)) for r in labelled)
    out[f"{prefix}marker_recall"] = _rate(hits, visible)
    return out


def _bins(
    recs: Sequence[EvalRecord], value: Callable[[EvalRecord], float], width: float
) -> list[dict[str, Any]]:
    vals = np.array([value(r) for r in recs], np.float64)
    ok = np.isfinite(vals)
    if not ok.any():
        return []
    groups: dict[int, list[EvalRecord]] = {}
    for r, v, g in zip(recs, vals, ok, strict=True):
        if g:
            groups.setdefault(math.floor(v / width), []).append(r)
    occupied = sorted(groups)
    if occupied[-1] - occupied[0] < MAX_BINS:  # every bin from the first to the last
        occupied = list(range(occupied[0], occupied[-1] + 1))
    out = []
    for k in occupied:  # (a sparse run, e.g. one outlying range, lists the occupied bins only)
        members = groups.get(k, [])
        n = len(members)
        entry = {
            "lo": round(k * width, 9),
            "hi": round((k + 1) * width, 9),
            "frames": n,
            "detection_rate": _rate(sum(1 for r in members if r.ids), n),
            "pose_rate": _rate(sum(1 for r in members if r.T_cam_ds is not None), n),
        }
        entry.update(_errors(members))
        out.append(entry)
    return out


def _same_pose(a: np.ndarray, b: np.ndarray, tol_m: float, tol_deg: float) -> bool:
    return bool(
        np.linalg.norm(a[:3, 3] - b[:3, 3]) <= tol_m and rotation_angle_deg(a, b) <= tol_deg
    )


def _spread(poses: Sequence[np.ndarray]) -> tuple[float, float]:
    """(translation std (m, root of the summed per-axis variances), rotation RMS angle to the
    chordal mean rotation (deg)) of a set of poses."""
    t = np.array([T[:3, 3] for T in poses])
    t_std = float(np.sqrt(np.sum(np.var(t, axis=0, ddof=1))))
    U, _, Vt = np.linalg.svd(np.sum([T[:3, :3] for T in poses], axis=0))
    R_mean = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    angles = [rotation_angle_deg(R_mean, T[:3, :3]) for T in poses]
    return t_std, float(np.sqrt(np.mean(np.square(angles))))


def pose_jitter(recs: Sequence[EvalRecord], cfg: ReportConfig) -> dict[str, Any]:
    """Spread of the estimated pose over static stretches of the ground truth.

    A stretch is a run of consecutive frame indices (decoded, with ground truth) whose true
    poses all stay within ``static_tol_m`` / ``static_tol_deg`` of the run's first pose, at
    least ``static_min_frames`` long. Per stretch with >= 2 solved frames: ``translation_std_m``
    (root of the summed per-axis sample variances of the estimated DS origin) and
    ``rotation_std_deg`` (RMS angle of the estimated rotations to their chordal mean).

    Returns:
        ``stretches``, ``frames``, medians over stretches and ``per_stretch`` details.
    """
    seq = sorted((r for r in recs if r.truth is not None and not r.corrupt), key=lambda r: r.frame)
    runs, i = [], 0
    while i < len(seq):
        j = i + 1
        while (
            j < len(seq)
            and seq[j].frame == seq[j - 1].frame + 1
            and _same_pose(
                seq[i].truth.T_cam_ds, seq[j].truth.T_cam_ds, cfg.static_tol_m, cfg.static_tol_deg
            )
        ):
            j += 1
        if j - i >= cfg.static_min_frames:
            runs.append(seq[i:j])
        i = j
    per = []
    for run in runs:
        est = [r.T_cam_ds for r in run if r.T_cam_ds is not None]
        t_std, r_std = _spread(est) if len(est) >= 2 else (None, None)
        per.append(
            {
                "first_frame": run[0].frame,
                "last_frame": run[-1].frame,
                "frames": len(run),
                "solved": len(est),
                "range_m": run[0].truth.range_m,
                "translation_std_m": t_std,
                "rotation_std_deg": r_std,
            }
        )
    t = [p["translation_std_m"] for p in per if p["translation_std_m"] is not None]
    r = [p["rotation_std_deg"] for p in per if p["rotation_std_deg"] is not None]
    return {
        "stretches": len(per),
        "frames": sum(p["frames"] for p in per),
        "translation_std_m_median": _pct(t, 50),
        "rotation_std_deg_median": _pct(r, 50),
        "per_stretch": per,
    }


def summarise(recs: Sequence[EvalRecord], cfg: ReportConfig, with_truth: bool) -> dict[str, Any]:
    """Report numbers of one pipeline.

    Args:
        recs: every frame of the input, decoded or corrupt.
        cfg: bins, static-stretch tolerances, flip threshold.
        with_truth: ground truth was given; without it the error entries are None.

    Returns:
        A JSON-serialisable dict (see ``perception eval``'s report).
    """
    ok = [r for r in recs if not r.corrupt]
    n = len(ok)
    solved = [r for r in ok if r.T_cam_ds is not None]
    per_id: dict[str, int] = {}
    for r in ok:
        for i in r.ids:
            per_id[str(i)] = per_id.get(str(i), 0) + 1
    ms = [r.ms for r in ok]
    rms = [r.rms_px for r in solved if r.rms_px is not None]
    out: dict[str, Any] = {
        "frames": n,
        "corrupt_frames": len(recs) - n,
        "frames_with_detection": sum(1 for r in ok if r.ids),
        "detection_rate": _rate(sum(1 for r in ok if r.ids), n),
        "frames_with_pose": len(solved),
        "pose_rate": _rate(len(solved), n),
        "markers_detected_total": sum(len(r.ids) for r in ok),
        "per_id_counts": dict(sorted(per_id.items(), key=lambda kv: int(kv[0]))),
        "ms_per_frame_median": _pct(ms, 50),
        "ms_per_frame_p90": _pct(ms, 90),
        "reprojection_rms_px_median": _pct(rms, 50),
        "reprojection_rms_px_p90": _pct(rms, 90),
    }
    gt = [r for r in ok if r.truth is not None]
    out["frames_with_truth"] = len(gt) if with_truth else None
    out.update(_errors(gt) if with_truth else _errors([]))
    e_r = [r.rotation_error_deg for r in gt if r.rotation_error_deg is not None]
    corner = [e for r in gt for e in r.corner_errors_px]
    labelled = [r for r in gt if r.labelled()]
    false_ids = 0
    for r in labelled:
        false_ids += len(set(r.ids) - {m.marker_id for m in r.truth.markers if m.in_image})
    out.update(
        {
            "gross_rotation_error_rate": _rate(
                sum(1 for e in e_r if e > cfg.flip_threshold_deg), len(e_r)
            ),
            "false_detections": false_ids if labelled else None,
            "corner_error_px_median": _pct(corner, 50),
            "corner_error_px_p90": _pct(corner, 90),
            "by_range": _bins(gt, lambda r: r.truth.range_m, cfg.range_bin_m)
            if with_truth
            else None,
            "by_view_angle": _bins(gt, lambda r: r.truth.view_angle_deg, cfg.angle_bin_deg)
            if with_truth
            else None,
            "by_water": _by_water(gt) if with_truth else None,
            "pose_jitter": pose_jitter(gt, cfg) if with_truth else None,
        }
    )
    return out


def _by_water(recs: Sequence[EvalRecord]) -> dict[str, Any] | None:
    groups: dict[str, list[EvalRecord]] = {}
    for r in recs:
        if r.truth.water is not None:
            groups.setdefault(str(r.truth.water.get("preset", "unknown")), []).append(r)
    if not groups:
        return None
    out = {}
    for preset, members in sorted(groups.items()):
        n = len(members)
        out[preset] = {
            "frames": n,
            "detection_rate": _rate(sum(1 for r in members if r.ids), n),
            "pose_rate": _rate(sum(1 for r in members if r.T_cam_ds is not None), n),
            **_errors(members),
        }
    return out


#: Columns of the pipeline comparison table.
COMPARE_COLUMNS: tuple[str, ...] = (
    "pipeline",
    "frames",
    "detection_rate",
    "pose_rate",
    "markers_detected_total",
    "ms_per_frame_median",
    "translation_error_m_median",
    "rotation_error_deg_median",
    "marker_recall",
)


def compare_rows(summaries: Mapping[str, Mapping[str, Any]]) -> list[dict[str, Any]]:
    """One row of :data:`COMPARE_COLUMNS` per pipeline, in the given order."""
    return [
        {"pipeline": name, **{c: s.get(c) for c in COMPARE_COLUMNS if c != "pipeline"}}
        for name, s in summaries.items()
    ]


def _cell(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def markdown_table(rows: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> str:
    """A GitHub-flavoured markdown table (None shows as "-")."""
    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    lines += ["| " + " | ".join(_cell(r.get(c)) for c in columns) + " |" for r in rows]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- plots


def _figure(nrows: int = 1, height: float = 3.2):
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(nrows, 1, figsize=(8, height * nrows), squeeze=False, sharex=True)
    return plt, fig, axes[:, 0]


def _save(plt, fig, path: str | os.PathLike[str]) -> Path:
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return Path(path)


def _bin_centres(bins: Sequence[Mapping[str, Any]]) -> np.ndarray:
    return np.array([0.5 * (b["lo"] + b["hi"]) for b in bins], np.float64)


def _series(bins: Sequence[Mapping[str, Any]], key: str) -> np.ndarray:
    return np.array([np.nan if b.get(key) is None else b[key] for b in bins], np.float64)


def plot_rate_vs_range(
    path: str | os.PathLike[str], by_range: Mapping[str, Sequence[Mapping[str, Any]]]
) -> Path:
    """Detection rate (solid) and pose rate (dashed) per range bin, one colour per pipeline.

    Args:
        path: output PNG.
        by_range: pipeline -> its report's ``by_range`` bins (``lo``, ``hi`` in m,
            ``detection_rate``, ``pose_rate``, ``frames``).
    """
    plt, fig, (ax,) = _figure()
    for k, (name, bins) in enumerate(by_range.items()):
        x = _bin_centres(bins)
        colour = f"C{k}"
        ax.plot(x, _series(bins, "detection_rate"), "o-", color=colour, label=f"{name} detection")
        ax.plot(x, _series(bins, "pose_rate"), "s--", color=colour, alpha=0.7, label=f"{name} pose")
    ax.set_xlabel("range camera -> DS origin (m)")
    ax.set_ylabel("fraction of frames")
    ax.set_ylim(-0.03, 1.03)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("Detection rate vs range")
    return _save(plt, fig, path)


def plot_error_vs_range(
    path: str | os.PathLike[str], by_range: Mapping[str, Sequence[Mapping[str, Any]]]
) -> Path:
    """Median (solid) and p90 (dotted) translation and rotation error per range bin."""
    plt, fig, (ax_t, ax_r) = _figure(2)
    for k, (name, bins) in enumerate(by_range.items()):
        x, colour = _bin_centres(bins), f"C{k}"
        for ax, key, scale in (
            (ax_t, "translation_error_m", 100.0),
            (ax_r, "rotation_error_deg", 1.0),
        ):
            ax.plot(x, scale * _series(bins, f"{key}_median"), "o-", color=colour, label=name)
            ax.plot(x, scale * _series(bins, f"{key}_p90"), ":", color=colour)
    ax_t.set_ylabel("translation error (cm)")
    ax_r.set_ylabel("rotation error (deg)")
    ax_r.set_xlabel("range camera -> DS origin (m)")
    for ax in (ax_t, ax_r):
        ax.grid(alpha=0.3)
        ax.set_yscale("symlog", linthresh=1.0)
    ax_t.legend(fontsize=8)
    ax_t.set_title("Pose error vs range (solid: median, dotted: p90)")
    return _save(plt, fig, path)


def plot_timeline(path: str | os.PathLike[str], frames: Sequence[Mapping[str, Any]]) -> Path:
    """Per frame: markers detected (and whether a pose was solved), pose error, time.

    Args:
        path: output PNG.
        frames: per-frame records (``frame``, ``n_markers``, ``T_cam_ds``, ``ms``, optional
            ``translation_error_m`` and ``rotation_error_deg``); corrupt frames are marked.
    """
    with_error = any(f.get("translation_error_m") is not None for f in frames)
    plt, fig, axes = _figure(3 if with_error else 2, height=2.4)
    ok = [f for f in frames if not f.get("corrupt")]
    x = np.array([f["frame"] for f in ok])
    n = np.array([f["n_markers"] for f in ok])
    solved = np.array([f.get("T_cam_ds") is not None for f in ok], bool)
    ax = axes[0]
    ax.step(x, n, where="mid", color="C0", label="markers detected")
    if solved.any():
        ax.plot(x[solved], n[solved], "|", color="C2", label="pose solved")
    bad = [f["frame"] for f in frames if f.get("corrupt")]
    if bad:
        ax.plot(bad, np.zeros(len(bad)), "x", color="C3", label="corrupt")
    ax.set_ylabel("markers")
    ax.legend(fontsize=8, loc="upper right")
    if with_error:
        e_t = np.array(
            [
                np.nan if f.get("translation_error_m") is None else f["translation_error_m"]
                for f in ok
            ]
        )
        e_r = np.array(
            [np.nan if f.get("rotation_error_deg") is None else f["rotation_error_deg"] for f in ok]
        )
        axes[1].plot(x, 100 * e_t, ".", color="C1", label="translation (cm)")
        axes[1].plot(x, e_r, ".", color="C4", label="rotation (deg)")
        if np.nanmin(np.concatenate([e_t, e_r]), initial=np.inf) > 0:
            axes[1].set_yscale("log")
        axes[1].set_ylabel("pose error")
        axes[1].legend(fontsize=8, loc="upper right")
    axes[-1].plot(x, [f["ms"] for f in ok], ".", color="C5")
    axes[-1].set_ylabel("ms / frame")
    axes[-1].set_xlabel("frame")
    for a in axes:
        a.grid(alpha=0.3)
    axes[0].set_title("Per-frame timeline")
    return _save(plt, fig, path)
