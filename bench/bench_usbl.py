"""Camera-off ablation under each acoustic (USBL) model: how far the acoustic approach alone gets.

Usage::

    python bench/bench_usbl.py [--episodes 30] [--seed 50000] [--workers 2]
        [--presets ideal,cerulean-rovl,evologics-s2cr] [--sources acoustic,error-model]

For every USBL preset (``uwdock.sim.usbl.USBL_PRESETS``) and observation source, the PID
baseline (``PIDController.for_env``) flies the same seeded episodes (episode k: seed + k) with
``terminate_on = "strict"`` (so paper and strict success are measured on the same episodes):
``acoustic`` is the camera-off row (the filter lives on the acoustic fixes alone),
``error-model`` the camera row (the image-derived error model of the clear tank at 480 px, with
the same acoustic fixes). The table gives the strict and paper success rates and the median and
mean final horizontal docking error.

Writes ``bench/results/usbl_ablation.json`` (rows + machine, commit, packages).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from uwdock.dockcore.bench import format_table, save_results
from uwdock.dockcore.config import replace
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.evaluate.episodes import run_episodes_parallel
from uwdock.sim.usbl import USBL_PRESETS

ERROR_MODEL = "rl/models/error_model_clear_tank_480.json"


def row(preset: str, source: str, episodes: int, seed: int, workers: int) -> dict:
    """One table row: the PID baseline over ``episodes`` seeded episodes."""
    cfg = replace(
        EnvConfig(),
        obs_source=source,
        error_model_path=ERROR_MODEL if source == "error-model" else None,
        terminate_on="strict",
        usbl={"preset": preset},
    )
    t0 = time.perf_counter()
    res = run_episodes_parallel("pid", cfg, episodes, seed, workers=workers, record=False)
    eps = res.episodes
    e_xy = [e["final_e_xy_m"] for e in eps]
    return {
        "usbl": preset,
        "obs": source,
        "episodes": len(eps),
        "strict_%": 100.0 * sum(e["success_strict"] for e in eps) / len(eps),
        "paper_%": 100.0 * sum(e["success"] for e in eps) / len(eps),
        "e_xy_median_m": statistics.median(e_xy),
        "e_xy_mean_m": statistics.fmean(e_xy),
        "e_yaw_median_deg": statistics.median(e["final_e_yaw_deg"] for e in eps),
        "wall_s": time.perf_counter() - t0,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--episodes", type=int, default=30)
    ap.add_argument("--seed", type=int, default=50000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--presets", default=",".join(USBL_PRESETS))
    ap.add_argument("--sources", default="acoustic,error-model")
    ap.add_argument("--out-dir", type=Path, default=None)
    a = ap.parse_args()
    rows = []
    for preset in a.presets.split(","):
        for source in a.sources.split(","):
            rows.append(row(preset, source, a.episodes, a.seed, a.workers))
            print(f"{preset:>16} {source:>12}: strict {rows[-1]['strict_%']:.0f} %", flush=True)
    cols = ["usbl", "obs", "episodes", "strict_%", "paper_%", "e_xy_median_m", "e_xy_mean_m"]
    print(format_table(rows, [*cols, "e_yaw_median_deg", "wall_s"]))
    config = {"episodes": a.episodes, "seed": a.seed, "policy": "pid", "error_model": ERROR_MODEL}
    print(save_results("usbl_ablation", rows, config, a.out_dir))


if __name__ == "__main__":
    main()
