"""Water fit recovery: how well ``sim fit-water`` recovers a known water from rendered films.

Usage::

    python bench/bench_water_fit.py [--seeds 0,1,2] [--presets clear_tank,coastal,...]

For each film seed, SAPIEN renders a 9 x 7-square chessboard (60 mm squares) on the tank floor
from 0.7 to 6.0 m in 0.1 m steps (``sim.render.board_views``: seeded tilts and offsets, lamp
dimmed to 2.0 so the nearest white stays below white in air). Each water preset is applied
with its sensor noise (frame i: noise seed 1000 * film seed + i), the fit runs on the frames,
and the table gives, per channel, the fitted attenuation, veiling light and backscatter
coefficient against the preset's, the vignetting and noise read from the frames, the modelled
contrast's error and the residual. A last block does the same with the DS marker board as the
target (the DS rendered from 1 to 5 m), for the coastal and clear presets.

Each fit chooses its lighting model on held-out frames (``--lighting auto``) and reports what
the frames determine: per row the chosen model, whether beta_D is determined in every channel,
and beta_D's uncertainty (the larger of the bootstrap over frames and the Jacobian) beside the
Jacobian's alone. ``--ambient`` adds lamp-off films (the board lit by the tank's ambient light
only, 0.7-4 m): the ambient model must be chosen.

Quick run: ``--seeds 0 --marker-presets ""``.

Writes ``bench/results/water_fit.json`` (rows + machine, commit, packages) and
``docs/results/water_fit_coastal.png`` (the fit's own plot, film seed 0).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import cv2
import numpy as np

from uwdock.calibration.frames import make_T
from uwdock.datasets.water_fit import FitWaterConfig, fit_water, sample_frames
from uwdock.datasets.water_fit_report import plot_fit
from uwdock.dockcore.bench import format_table, save_results
from uwdock.dockcore.config import to_dict
from uwdock.dockcore.errors import DockError
from uwdock.sim.docking_station import DockingStationConfig
from uwdock.sim.render import RenderConfig, board_views, make_render_scene
from uwdock.sim.water import PRESET_ORDER, PRESETS, apply_water

ROOT = Path(__file__).resolve().parent.parent
ALTITUDES_M = np.arange(0.7, 6.01, 0.1)
RENDER = RenderConfig(lamp_intensity=2.0)
FIT = FitWaterConfig(square_mm=60.0)


AMBIENT_ALTITUDES_M = np.arange(0.7, 4.01, 0.15)
AMBIENT_RENDER = RenderConfig(lamp=False, ambient_rgb=(0.6, 0.6, 0.6))


def _frames(renders, water, seed: int):
    """The renders filmed through ``water`` with the exposure locked (a fit needs one exposure
    for all frames, as a diver sets the camera's before filming)."""
    water = dataclasses.replace(water, auto_exposure=False)
    for i, r in enumerate(renders):
        img = apply_water(r.radiance, r.range_m, water, np.random.default_rng(1000 * seed + i))
        yield i, f"f{i:03d}", cv2.cvtColor(img, cv2.COLOR_RGB2BGR)


def _row(name: str, target: str, seed: int, fit, samples, wall_s: float) -> dict:
    truth = PRESETS[name]
    row = {
        "water": name,
        "target": target,
        "film_seed": seed,
        "frames": f"{samples.frames_used}/{samples.frames_read}",
        "range_m": f"{fit.range_m[0]:.2f}-{fit.range_m[1]:.2f}",
    }
    for key in ("beta_D", "B_inf", "beta_B"):
        want = np.asarray(getattr(truth, f"{key}_rgb"))
        got = np.asarray(fit.params[key])
        row[f"{key}_true"] = [round(float(v), 4) for v in want]
        row[f"{key}_fit"] = [round(float(v), 4) for v in got]
        row[f"{key}_rel_std"] = [round(float(v), 3) for v in fit.rel_std[key]]
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.where(want > 0, (got - want) / want, np.nan)
        row[f"{key}_err_%"] = [None if np.isnan(v) else round(100 * float(v), 1) for v in rel]
    row["beta_D_max_err_%"] = max(abs(v) for v in row["beta_D_err_%"])
    row["lighting"] = fit.lighting
    row["beta_D_determined"] = fit.beta_D_determined
    row["undetermined"] = fit.undetermined_names()
    row["beta_D_rel_std_jacobian"] = [
        round(float(v), 3) for v in fit.models[fit.lighting].rel_std_jacobian["beta_D"]
    ]
    row["heldout_rms_8bit"] = {
        k: round(m.heldout_rms_8bit, 2) for k, m in fit.models.items() if m.heldout_rms_8bit > 0
    }
    row["vignetting"] = round(fit.vignetting, 3)
    row["photons"] = round(fit.water.photons_at_white, 0)
    row["read_noise"] = round(fit.water.read_noise, 4)
    row["contrast_err_%"] = max(round(100 * e, 2) for e in fit.contrast_error)
    row["residual_8bit"] = round(fit.residual_rms_8bit, 2)
    row["warnings"] = len(fit.warnings)
    row["wall_s"] = round(wall_s, 1)
    return row


def board_rows(
    seeds: list[int], presets: list[str], figure: Path | None, ambient: bool = False
) -> list[dict]:
    rows = []
    for seed in seeds:
        if ambient:
            renders = board_views(AMBIENT_ALTITUDES_M, square_m=0.06, render_cfg=AMBIENT_RENDER,
                                  seed=seed)  # fmt: skip
        else:
            renders = board_views(ALTITUDES_M, square_m=0.06, render_cfg=RENDER, seed=seed)
        for name in presets:
            t0 = time.perf_counter()
            truth = dataclasses.replace(PRESETS[name], artificial_light=not ambient)
            samples = sample_frames(_frames(renders, truth, seed), renders[0].camera, FIT)
            try:
                fit = fit_water(samples, FIT)
            except DockError as exc:  # e.g. the board found over too short a range of distances
                rows.append({"water": name, "target": "chessboard", "film_seed": seed,
                             "refused": str(exc)})  # fmt: skip
                print(f"board seed {seed} {name:>12}: refused: {exc}", flush=True)
                continue
            target = "chessboard, lamp off" if ambient else "chessboard"
            rows.append(_row(name, target, seed, fit, samples, time.perf_counter() - t0))
            print(f"{target} seed {seed} {name:>12}: {fit.lighting}, beta_D max error "
                  f"{rows[-1]['beta_D_max_err_%']:.1f} %", flush=True)  # fmt: skip
            if figure is not None and seed == seeds[0] and name == "coastal" and not ambient:
                plot_fit(fit, figure)
    return rows


def marker_rows(presets: list[str]) -> list[dict]:
    rs = make_render_scene(DockingStationConfig(tank_depth_m=10.0), render_cfg=RENDER)
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(7)
    renders = []
    for alt in np.arange(1.0, 5.01, 0.25):
        off = rng.uniform(-0.4, 0.4, 2)
        T = rs.ds.T_worldned_ds @ make_T(R, [off[0], off[1], -float(alt)])
        renders.append(rs.render(T_worldned_camcv=T))
    cfg = FitWaterConfig(target="markers")
    rows = []
    for name in presets:
        t0 = time.perf_counter()
        samples = sample_frames(
            _frames(renders, PRESETS[name], 0), renders[0].camera, cfg, rs.ds.marker_set
        )
        fit = fit_water(samples, cfg)
        rows.append(_row(name, "markers", 0, fit, samples, time.perf_counter() - t0))
        print(f"markers {name:>12}: beta_D max error {rows[-1]['beta_D_max_err_%']:.1f} %")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--presets", default=",".join(PRESET_ORDER))
    ap.add_argument("--marker-presets", default="clear_tank,coastal")
    ap.add_argument("--ambient", action="store_true", help="Add lamp-off films.")
    ap.add_argument("--out-dir", type=Path, default=None)
    ap.add_argument("--figure", type=Path, default=ROOT / "docs/results/water_fit_coastal.png")
    a = ap.parse_args()
    seeds = [int(s) for s in a.seeds.split(",")]
    rows = board_rows(seeds, a.presets.split(","), a.figure)
    if a.ambient:
        rows += board_rows(seeds, a.presets.split(","), None, ambient=True)
    rows += marker_rows([p for p in a.marker_presets.split(",") if p])
    cols = ["water", "target", "film_seed", "frames", "range_m", "lighting", "beta_D_determined",
            "beta_D_err_%", "beta_D_rel_std", "beta_D_rel_std_jacobian", "B_inf_err_%",
            "beta_B_err_%", "contrast_err_%", "residual_8bit", "vignetting", "photons",
            "read_noise"]  # fmt: skip
    print(format_table([r for r in rows if "refused" not in r], cols))
    config = {
        "altitudes_m": [round(float(a_), 2) for a_ in ALTITUDES_M],
        "board": "9 x 7 squares of 60 mm, white 0.6, black 0.03",
        "lamp_intensity": RENDER.lamp_intensity,
        "lamp_off_films": {
            "altitudes_m": [round(float(a_), 2) for a_ in AMBIENT_ALTITUDES_M],
            "ambient_rgb": list(AMBIENT_RENDER.ambient_rgb),
        }
        if a.ambient
        else None,
        "fit": to_dict(FIT),
        "film_seeds": seeds,
        "noise_seed": "1000 * film seed + frame",
    }
    print(save_results("water_fit", rows, config, a.out_dir))


if __name__ == "__main__":
    main()
