"""Rendered beside real: a chessboard's black level and contrast against range, real tank frames
against the simulator's renders of the same board at the same ranges.

Real: the shared apl_sediment frames (17 x 1920x1080, an 8 x 6 inner-corner board of 25 mm
squares moved under a fixed downward camera; ``../shared/real``, not part of the repository),
posed with the camera calibrated on them (``bench/results/water_fit_real/camera.yaml``).
Rendered: the same board (``sim.render.board_views``) seen by that camera (its intrinsics and
distortion, 1920x1080) at each real frame's range, under the simulator's default lamp, through
clear-tank water, two ways:

* ``linear`` -- the renderer now: linear light, the camera's auto exposure, clipped only at the
  sensor (``apply_water(res.radiance, ...)``);
* ``clipped_in_air`` -- as before: the render clipped at white in air, then the water
  (``apply_water(res.rgb, ...)``, what the renderer did before it kept light linear).

Every frame, real or rendered, goes through the water fit's own sampler
(:func:`datasets.water_fit.sample_frames`: PnP of the board, the inner half of each square,
clipped patches dropped), so both sides are measured the same way. Per frame: the median range
of the patches, the black and white levels (display grey, 0-255) and the contrast
``(W - B) / (W + B)`` of the linear levels.

Usage::

    python bench/bench_render_vs_real.py [--real ../shared/real/apl_sediment_tag36h11]

Prints a table and writes ``bench/results/render_vs_real.json`` and ``render_vs_real.png``
(a real frame beside its renders, and the levels against range).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from uwdock.calibration.camera import load_camera  # noqa: E402
from uwdock.datasets.water_fit import FitWaterConfig, PatchSamples, sample_frames  # noqa: E402
from uwdock.dockcore.io import atomic_path, atomic_write_json  # noqa: E402
from uwdock.dockcore.provenance import provenance  # noqa: E402
from uwdock.perception.video import open_frames  # noqa: E402
from uwdock.sim.render import RenderConfig, board_views  # noqa: E402
from uwdock.sim.water import apply_water, preset  # noqa: E402

VARIANTS = ("linear", "clipped_in_air")


def _grey8(linear: np.ndarray, gamma: float) -> np.ndarray:
    """Display grey (0-255) of linear RGB rows (N, 3)."""
    return 255.0 * np.clip(linear.mean(axis=1), 0.0, 1.0) ** (1.0 / gamma)


def per_frame(s: PatchSamples, gamma: float) -> list[dict]:
    """Range, black and white levels and contrast of each frame with both kinds of patch."""
    rows = []
    for f in np.unique(s.frame):
        m = s.frame == f
        w, b = m & s.white, m & ~s.white
        if not (w.any() and b.any()):
            continue
        lw, lb = s.rgb[w].mean(axis=1).mean(), s.rgb[b].mean(axis=1).mean()
        rows.append({
            "frame": s.names.get(int(f), str(f)),
            "range_m": float(np.median(s.range_m[m])),
            "black_grey": float(np.median(_grey8(s.rgb[b], gamma))),
            "white_grey": float(np.median(_grey8(s.rgb[w], gamma))),
            "contrast": float((lw - lb) / (lw + lb)) if lw + lb > 0 else 0.0,
        })  # fmt: skip
    return sorted(rows, key=lambda r: r["range_m"])


def render_frames(ranges_m: list[float], camera, cfg: FitWaterConfig, water: str, seed: int):
    """The board rendered at each range; yields per variant the (index, name, BGR) frames."""
    views = board_views(
        ranges_m, cols=cfg.cols, rows=cfg.rows, square_m=cfg.square_mm / 1000.0,
        white_rgb=(0.8, 0.8, 0.8), render_cfg=RenderConfig(), camera_model=camera, seed=seed,
        max_tilt_deg=10.0,
    )  # fmt: skip
    w = preset(water)
    out: dict[str, list] = {v: [] for v in VARIANTS}
    for i, res in enumerate(views):
        for v, img in (("linear", res.radiance), ("clipped_in_air", res.rgb)):
            rgb = apply_water(img, res.range_m, w, np.random.default_rng(seed + i))
            out[v].append((i, f"render_{i:02d}", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)))
    return out


def plot(path: Path, results: dict, images: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(13, 8.5), constrained_layout=True)
    gs = fig.add_gridspec(2, 3, height_ratios=[1.0, 1.1])
    titles = {"real": "real (apl tank)", "linear": "rendered: linear light (now)",
              "clipped_in_air": "rendered: clipped in air (before)"}  # fmt: skip
    for k, name in enumerate(("real", "linear", "clipped_in_air")):
        ax = fig.add_subplot(gs[0, k])
        img, rng = images[name]
        ax.imshow(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
        ax.set_title(f"{titles[name]}, board at {rng:.2f} m", fontsize=10)
        ax.axis("off")
    style = {"real": ("k", "o"), "linear": ("tab:blue", "s"), "clipped_in_air": ("tab:red", "^")}
    panels = (
        ("black_grey", "black level (grey, 0-255)"),
        ("white_grey", "white level (grey, 0-255)"),
        ("contrast", "contrast (W - B) / (W + B), linear"),
    )
    for k, (key, label) in enumerate(panels):
        ax = fig.add_subplot(gs[1, k])
        for name, rows in results.items():
            c, m = style[name]
            ax.plot([r["range_m"] for r in rows], [r[key] for r in rows], m, color=c,
                    label=titles[name], alpha=0.8)  # fmt: skip
        ax.set_xlabel("range to the board (m)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if k == 0:
            ax.legend(fontsize=8)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80, format="png")
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--real", type=Path, default=ROOT.parent / "shared/real/apl_sediment_tag36h11")
    ap.add_argument("--camera", type=Path,
                    default=ROOT / "bench/results/water_fit_real/camera.yaml")  # fmt: skip
    ap.add_argument("--water", default="clear_tank")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=ROOT / "bench/results/render_vs_real.json")
    args = ap.parse_args()
    t0 = time.perf_counter()
    camera, _ = load_camera(args.camera)
    cfg = FitWaterConfig(target="chessboard", cols=8, rows=6, square_mm=25.0,
                         min_range_spread_m=0.5)  # fmt: skip
    print(f"sampling the real frames in {args.real} ...", flush=True)
    real_frames = list(open_frames(args.real))
    real = sample_frames(real_frames, camera, cfg)
    results = {"real": per_frame(real, cfg.gamma)}
    dropped = {"real": real.dropped_saturated}
    ranges = [r["range_m"] for r in results["real"]]
    print(f"rendering the board at {len(ranges)} ranges ({min(ranges):.2f}-{max(ranges):.2f} m)"
          " ...", flush=True)  # fmt: skip
    rendered = render_frames(ranges, camera, cfg, args.water, args.seed)
    for v in VARIANTS:
        s = sample_frames(rendered[v], camera, cfg)
        results[v] = per_frame(s, cfg.gamma)
        dropped[v] = s.dropped_saturated
    # the nearest real frame beside its two renders
    near = results["real"][0]
    real_img = next(img for _, name, img in real_frames if name == near["frame"])
    images = {"real": (real_img, near["range_m"])}
    for v in VARIANTS:
        images[v] = (rendered[v][0][2], ranges[0])
    print(f"\n{'source':<16} {'frames':>6} {'range m':>11} {'black grey':>11} {'white grey':>11} "
          f"{'contrast':>9} {'clipped patches':>15}")  # fmt: skip
    summary = {}
    for name, rows in results.items():
        b = np.array([r["black_grey"] for r in rows])
        w = np.array([r["white_grey"] for r in rows])
        c = np.array([r["contrast"] for r in rows])
        rg = np.array([r["range_m"] for r in rows])
        summary[name] = {
            "frames": len(rows), "range_m": [float(rg.min()), float(rg.max())],
            "black_grey_median": float(np.median(b)), "white_grey_median": float(np.median(w)),
            "contrast_median": float(np.median(c)), "white_grey_max": float(w.max()),
            "patches_dropped_clipped": int(dropped[name]),
        }  # fmt: skip
        print(f"{name:<16} {len(rows):>6} {rg.min():>5.2f}-{rg.max():<5.2f} {np.median(b):>11.1f} "
              f"{np.median(w):>11.1f} {np.median(c):>9.2f} {dropped[name]:>15}")  # fmt: skip
    config = {
        "real": str(args.real), "camera": str(args.camera), "water": args.water,
        "seed": args.seed, "board": "8x6 inner corners, 25 mm", "lamp": "RenderConfig()",
    }  # fmt: skip
    atomic_write_json(args.out, {
        "summary": summary, "frames": results, "config": config,
        "wall_s": time.perf_counter() - t0, "provenance": provenance({"bench": config}),
    })  # fmt: skip
    png = args.out.with_suffix(".png")
    plot(png, results, images)
    print(f"written {args.out} and {png} in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
