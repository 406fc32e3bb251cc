"""The water fit's outputs (used by :mod:`datasets.water_fit`, which re-exports them): the water
file with the fit's notes (lighting model, uncertainty, values the frames did not determine) and
the plot of measured against modelled contrast and black level."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from uwdock.datasets.water_fit_judge import CHANNELS, JUDGED
from uwdock.dockcore.config import dumps_toml
from uwdock.dockcore.io import atomic_path, atomic_write_text

if TYPE_CHECKING:
    from uwdock.datasets.water_fit import WaterFit

__all__ = ["plot_fit", "water_toml", "write_water_file"]


# ----------------------------------------------------------------------------- outputs


def water_toml(fit: WaterFit, source: str = "") -> str:
    """The fitted water as a ``[water]`` TOML file (read by every ``--water`` option)."""
    head = [
        "# Water fitted by `sim fit-water`" + (f" to {source}" if source else ""),
        f"# {len(fit.samples)} patches in {fit.samples.frames_used} frames, ranges "
        f"{fit.range_m[0]:.2f}-{fit.range_m[1]:.2f} m; residual RMS {fit.residual_rms_8bit:.2f} "
        "grey levels; contrast error R/G/B "
        + "/".join(f"{100 * e:.1f} %" for e in fit.contrast_error),
        f"# blur from the '{fit.config.base}' preset; lighting model '{fit.lighting}'; [fit]: "
        "the fit's uncertainty (relative, the larger of bootstrap over frames and Jacobian; "
        "beta_D_low/high: beta_D at -+1 of it)",
    ]
    undetermined = fit.undetermined_names()
    if undetermined:
        head.append(
            "# NOT DETERMINED by the frames (kept for the renders, marked in [fit.undetermined]): "
            + "; ".join(f"{b} {', '.join(chs)}" for b, chs in undetermined.items())
        )
    head.append("")
    notes = {
        "lighting": fit.lighting,
        "range_m": [round(v, 4) for v in fit.range_m],
        "rel_std": {b: [float(v) for v in fit.rel_std[b]] for b in JUDGED},
        "beta_D_low_rgb": [float(v * math.exp(-u)) for v, u in
                           zip(fit.params["beta_D"], fit.rel_std["beta_D"], strict=True)],
        "beta_D_high_rgb": [float(v * math.exp(u)) for v, u in
                            zip(fit.params["beta_D"], fit.rel_std["beta_D"], strict=True)],
        "undetermined": undetermined,
    }  # fmt: skip
    return "\n".join(head) + "\n" + dumps_toml({"water": fit.water, "fit": notes})


def write_water_file(fit: WaterFit, path: str | Path, source: str = "") -> Path:
    """Write :func:`water_toml` atomically."""
    return atomic_write_text(path, water_toml(fit, source))


def plot_fit(fit: WaterFit, path: str | Path) -> None:
    """Measured vs modelled contrast (white - black) and black level against range, per
    channel; written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = fit.samples
    model = fit.model()
    r_pairs, meas, mod = fit.contrast_pairs()
    fig, axes = plt.subplots(2, 3, figsize=(11, 6.2), sharex=True)
    colours = ("tab:red", "tab:green", "tab:blue")
    for c, ch in enumerate(CHANNELS):
        ax = axes[0, c]
        ax.scatter(r_pairs, meas[:, c], s=4, color=colours[c], alpha=0.35, label="frames")
        order = np.argsort(r_pairs)
        ax.plot(r_pairs[order], mod[order, c], ".", ms=2, color="k", label="model")
        ax.set_yscale("log")
        ax.set_title(f"{ch}: contrast white - black (error {100 * fit.contrast_error[c]:.1f} %)",
                     fontsize=9)  # fmt: skip
        black = ~s.white
        ax = axes[1, c]
        ax.scatter(s.range_m[black], s.rgb[black, c], s=4, color=colours[c], alpha=0.35,
                   label="frames")  # fmt: skip
        ax.plot(s.range_m[black], model[black, c], ".", ms=2, color="k", label="model")
        ax.set_title(f"{ch}: black level (B_inf {fit.params['B_inf'][c]:.3f}, beta_B "
                     f"{fit.params['beta_B'][c]:.3f}/m)", fontsize=9)  # fmt: skip
        ax.set_xlabel("range (m)")
    axes[0, 0].set_ylabel("linear intensity")
    axes[1, 0].set_ylabel("linear intensity")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(
        f"Water fit ({fit.lighting} lighting): beta_D "
        + ", ".join(
            f"{v:.3f}" + ("" if ok else " (undetermined)")
            for v, ok in zip(fit.params["beta_D"], fit.determined["beta_D"], strict=True)
        )
        + f" /m; residual {fit.residual_rms_8bit:.2f} grey levels",
        fontsize=10,
    )
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
