"""What ``calibration intrinsics`` writes: the camera file, its JSON report and a figure of the
per-view errors and the folds' spread (:func:`write_outputs`).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from uwdock.calibration.camera import camera_file_bytes, load_camera, twin_paths
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_files
from uwdock.dockcore.provenance import provenance

if TYPE_CHECKING:
    from uwdock.calibration.intrinsics import IntrinsicsResult

__all__ = ["output_paths", "write_outputs"]


def _plot_errors(result: IntrinsicsResult) -> bytes:
    """Per-view RMS error in the fit and held out (px), and each fold's fx / fy against the
    final fit's (the spread the uncertainty comes from), as PNG bytes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    used = [v for v in result.views if v.status == "calibration" or v.reason == "outlier"]
    fig, (ax, ax2) = plt.subplots(
        1,
        2,
        figsize=(max(8.0, 0.3 * len(used) + 5.0), 3.8),
        dpi=100,
        gridspec_kw={"width_ratios": [max(2.0, 0.3 * len(used)), 3.0]},
    )
    x = np.arange(len(used))
    fit_err = [v.error_px or 0.0 for v in used]
    cv_err = [v.cv_error_px if v.cv_error_px is not None else 0.0 for v in used]
    ax.bar(x - 0.2, fit_err, 0.4, color="tab:blue", label="in the fit")
    colours = ["tab:red" if v.reason == "outlier" else "tab:orange" for v in used]
    ax.bar(x + 0.2, cv_err, 0.4, color=colours, label="held out (red: outlier)")
    rms = result.camera.rms_px or 0.0
    ax.axhline(rms, color="tab:blue", ls="--", lw=1, label=f"fit RMS {rms:.3f} px")
    ax.axhline(
        result.cv_rms_px,
        color="tab:orange",
        ls="--",
        lw=1,
        label=f"{result.cv.scheme} RMS {result.cv_rms_px:.3f} px",
    )
    ax.set_xticks(x)
    ax.set_xticklabels([v.name for v in used], rotation=90, fontsize=6)
    ax.set_ylabel("RMS reprojection error (px)")
    ax.set_title("Per view")
    ax.legend(fontsize=7)
    cam = result.camera
    p = result.cv.params
    for j, (label, value, colour) in enumerate(
        (("fx", cam.fx_px, "tab:blue"), ("fy", cam.fy_px, "tab:green"))
    ):
        rel = 100.0 * (p[:, j] - value) / value
        ax2.plot(np.arange(len(rel)), rel, "o", ms=3, color=colour, label=label)
    unc = result.uncertainty_frac()
    fx_band = 100.0 * unc["fx_px"]
    limit = 100.0 * result.config.uncertainty_warn_frac
    ax2.axhspan(-fx_band, fx_band, color="0.88", zorder=0, label="fx +-1 sigma (jackknife)")
    for sign in (-1.0, 1.0):
        ax2.axhline(sign * limit, color="tab:red", ls=":", lw=1)
    ax2.axhline(0.0, color="k", lw=0.8)
    ax2.set_xlabel(f"fold ({result.cv.scheme}; red: {limit:g} % warning limit)")
    ax2.set_ylabel("fold's value - final (%)")
    ax2.set_title(
        f"Folds: fx +-{100 * unc['fx_px']:.2f} %, fy +-{100 * unc['fy_px']:.2f} % (jackknife)",
        fontsize=9,
    )
    ax2.legend(fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png")
    finally:
        plt.close(fig)
    return buf.getvalue()


def output_paths(out: str | os.PathLike[str]) -> list[Path]:
    """Every file :func:`write_outputs` writes for ``out``: the camera twins,
    ``<stem>_report.json`` and ``<stem>_errors.png`` (checked by the command before it
    calibrates: ``dockcore.io.check_output_path``).

    Raises:
        DockError: ``out`` has an unsupported suffix.
    """
    out = Path(out)
    return [
        *twin_paths(out),
        out.with_name(f"{out.stem}_report.json"),
        out.with_name(f"{out.stem}_errors.png"),
    ]


def write_outputs(
    result: IntrinsicsResult, out: str | os.PathLike[str], keep_extrinsics: bool = True
) -> tuple[list[Path], bool]:
    """Write the camera file twins, ``<stem>_report.json`` and ``<stem>_errors.png``, as one
    unit (``dockcore.io.atomic_write_files``): all four are written and verified before any is
    renamed, so a failure (a full disk) leaves the existing files as they were.

    Args:
        result: a calibration.
        out: camera file path (``.yaml``, ``.yml`` or ``.json``).
        keep_extrinsics: when ``out`` already holds a readable camera file with ``T_body_cam``,
            carry it over (intrinsics do not change where the camera is mounted).

    Returns:
        (the paths written, whether ``T_body_cam`` was carried over).
    """
    out = Path(out)
    T = None
    if keep_extrinsics and out.is_file():
        with contextlib.suppress(DockError):
            T = load_camera(out)[1]
    files = camera_file_bytes(out, result.camera, T)
    report = result.report()
    report["T_body_cam_kept"] = T is not None
    report["provenance"] = provenance()  # code version, packages, machine, command line
    report_path = out.with_name(f"{out.stem}_report.json")
    plot_path = out.with_name(f"{out.stem}_errors.png")
    files[report_path] = (json.dumps(report, indent=2) + "\n").encode("utf-8")
    files[plot_path] = _plot_errors(result)
    return atomic_write_files(files), T is not None
