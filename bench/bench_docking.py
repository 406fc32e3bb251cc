"""Policy against the PID baseline, same seeds, over the headline and the harder conditions.

Usage::

    python bench/bench_docking.py --policy RUN/best [--episodes 100] [--stress-episodes 30]
        [--seed 50000] [--usbl evologics-s2cr] [--nav mems-ahrs-dvl] [--workers 2]
        [--rows all|headline|NAME,...] [--name docking]

Every row flies the policy and the PID baseline (``PIDController.for_env``) over the same
seeded episodes (episode k: seed + k; seeds 50000... were never used in training, whose
episodes draw from the run's own seed), ``terminate_on = "strict"`` so that the strict
success (pegs seated and held) and the paper's one-instant condition are measured on the same
episodes, the USBL preset ``--usbl`` and the vehicle's navigation ``--nav`` (dead reckoning
that drifts, by default; ``ideal``: the true pose) in every row:

headline rows (``--episodes``):
    camera            the camera in the loop: render -> 3DBM detector -> PnP -> filter
                      (clear tank, 480 px)
    camera off        acoustic fixes only (the filter never sees the camera)
    error model       the policy's training observation (its run's error model)
harder rows (``--stress-episodes``, camera in the loop):
    coastal, turbid   the water between the camera and the DS
    current 0.4       a drifting current up to 0.4 m/s (the training draws reach 0.28)
    long approach     the AUV spawned 8-10 m from the DS (training: up to ~7.5 m)
    camera mount      the camera's true mounting off its calibration by up to 1 cm / 1 deg
                      per axis
    thrusters         thruster placement off by up to 5 cm and 5 deg (training: 1 cm, 2 deg)
    all               all of the above at once, in coastal water

Success rates carry Wilson 95 % intervals (scipy). Each row keeps its episodes' outcomes
(``per_episode``), and every other camera row is compared with the ``camera`` row of the same
controller on the episodes both flew (the same seeds): the change in strict success with an
exact McNemar test on the discordant episodes, and the paired change in time to dock over the
episodes both docked, with a bootstrap 95 % interval (``paired_vs_camera`` in the JSON). Each
row counts its failure modes (:mod:`uwdock.rl.evaluate.failures`: wedged against the DS frame,
landed off the seat, other; ``failure_modes``, and ``failure_mode`` per episode).
Writes ``bench/results/<name>.json`` (rows, config, machine, commit; rewritten after every
cell, ``complete`` false until the last) and ``<name>.png`` (strict success per condition,
policy beside PID). An interrupted run resumes: run the same command again and the cells its
unfinished output holds, flown with the same settings, are kept (each marked
``resumed_from``: the commit that flew it), the others flown.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field, is_dataclass
from pathlib import Path
from typing import Any

from uwdock.dockcore.bench import format_table, save_results
from uwdock.dockcore.config import merge, replace, to_dict
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.policy.policy_io import policy_env_settings, policy_error_model
from uwdock.sim.navigation import NAV_PRESETS
from uwdock.sim.thrusters import ThrusterRandomisation
from uwdock.sim.usbl import USBL_PRESETS
from uwdock.sim.vehicle import CurrentConfig, VehicleRandomisation

RESULTS = Path(__file__).resolve().parent / "results"

HARD_CURRENT = CurrentConfig(
    mode="varying", range_x_mps=(-0.4, 0.4), range_y_mps=(-0.4, 0.4), max_speed_mps=0.4
)
LONG_APPROACH = {"spawn_auv_range_m": (8.5, 4.0, 1.4), "spawn_horizontal_range_m": (8.0, 10.0)}
# the world's conditions go to EnvConfig.world ([env.world])
CAMERA_MOUNT = {"world": {"camera_mount_error_m": 0.01, "camera_mount_error_deg": 1.0}}
THRUSTERS = {
    "world": {
        "vehicle_randomisation": to_dict(
            VehicleRandomisation(thrusters=ThrusterRandomisation(position_m=0.05, axis_deg=5.0))
        )
    }
}


def _world(**changes: Any) -> dict[str, Any]:
    """EnvConfig overrides of ``world`` fields (config dataclasses as plain data)."""
    return {"world": {k: to_dict(v) if is_dataclass(v) else v for k, v in changes.items()}}


@dataclass(frozen=True)
class Row:
    """One condition: its name, the observation source, EnvConfig overrides, and whether it is
    a headline row (``--episodes``) or a harder one (``--stress-episodes``)."""

    name: str
    obs: str
    overrides: dict[str, Any] = field(default_factory=dict)
    headline: bool = False


ROWS = (
    Row("camera", "camera", headline=True),
    Row("camera off", "acoustic", headline=True),
    Row("error model", "error-model", headline=True),
    Row("coastal", "camera", _world(water_preset="coastal")),
    Row("turbid", "camera", _world(water_preset="turbid")),
    Row("current 0.4", "camera", _world(current=HARD_CURRENT)),
    Row("long approach", "camera", LONG_APPROACH),
    Row("camera mount", "camera", CAMERA_MOUNT),
    Row("thrusters", "camera", THRUSTERS),
    Row(
        "all",
        "camera",
        merge(
            merge(_world(water_preset="coastal", current=HARD_CURRENT), LONG_APPROACH),
            merge(CAMERA_MOUNT, THRUSTERS),
        ),
    ),
)


def wilson_ci(successes: int, n: int) -> tuple[float, float]:
    """Wilson 95 % interval of a success rate."""
    from scipy.stats import binomtest

    if n == 0:
        return (0.0, 1.0)
    ci = binomtest(successes, n).proportion_ci(0.95, method="wilson")
    return (float(ci.low), float(ci.high))


def env_for(row: Row, policy: str, usbl: str, nav: str = "mems-ahrs-dvl") -> EnvConfig:
    """The row's env: defaults, the policy's observation interface, strict termination, the
    USBL and navigation presets."""
    cfg = replace(
        EnvConfig(),
        obs_source=row.obs,
        terminate_on="strict",
        usbl={"preset": usbl},
        nav={"preset": nav},
        error_model_path=policy_error_model(policy) if row.obs == "error-model" else None,
        **row.overrides,
    )
    return replace(cfg, **policy_env_settings(policy))


def finished_cells(path: Path, config: dict[str, Any]) -> dict[tuple[str, str], dict[str, Any]]:
    """The cells of an unfinished output at ``path`` flown with ``config`` (a resumed run keeps
    them), by (condition, controller), each marked with the commit that flew it; none when
    there is no such output, it is finished (the command runs again from the start) or its
    settings differ."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    if not isinstance(data, dict) or not isinstance(data.get("bench_config"), dict):
        return {}
    old = dict(data["bench_config"])
    if old.pop("complete", True) or old != json.loads(json.dumps(config)):
        return {}
    made = data.get("git") or {}
    cells = {}
    for r in data.get("rows", []):
        if isinstance(r, dict) and {"condition", "controller"} <= r.keys():
            cells[r["condition"], r["controller"]] = {"resumed_from": made, **r}
    return cells


def run_row(row: Row, controller: str, cfg: EnvConfig, episodes: int, seed: int, workers: int):
    """One (condition, controller) cell: the eval summary plus intervals and wall time."""
    from tqdm import tqdm

    from uwdock.rl.evaluate.episodes import run_episodes_parallel

    t0 = time.perf_counter()
    label = "policy" if controller != "pid" else "pid"
    with tqdm(total=episodes, desc=f"{row.name} / {label}", unit="ep", leave=False) as bar:
        res = run_episodes_parallel(
            controller, cfg, episodes, seed, workers=workers, record=False,
            progress=lambda k, n: bar.update(k - bar.n),
        )  # fmt: skip
    s = res.summary
    n = s["episodes"]
    strict, paper = s["success_rate_strict"], s["success_rate"]
    return {
        "condition": row.name,
        "obs": row.obs,
        "controller": label,
        "episodes": n,
        "strict": strict,
        "strict_ci95": wilson_ci(round(strict * n), n),
        "paper": paper,
        "paper_ci95": wilson_ci(round(paper * n), n),
        "time_to_dock_s": s["mean_time_to_dock_s"],
        "collisions": s["mean_collisions"],
        "final_e_xy_m_median": s["final_e_xy_m_median"],
        "final_e_yaw_deg_median": s["final_e_yaw_deg_median"],
        "failure_modes": s["failure_modes"],
        "final_nav_error_m_median": s["final_nav_error_m_median"],
        "wall_s": time.perf_counter() - t0,
        "per_episode": [
            {k: e[k] for k in ("episode", "success_strict", "success", "time_to_dock_s",
                               "collisions", "failure_mode", "wedged_s", "landed_off_s")}
            for e in res.episodes
        ],
    }  # fmt: skip


def paired_change(base: list[dict[str, Any]], other: list[dict[str, Any]]) -> dict[str, Any] | None:
    """``other``'s episodes against ``base``'s, on the episodes both flew (same ``episode``
    index, so the same seed); None if they share none.

    ``strict_change``: strict success of ``other`` minus ``base``'s on the common episodes,
    with the exact McNemar p-value (binomial test on the episodes where exactly one docked).
    ``time_change_s``: mean paired change in time to dock over the episodes both docked
    (strict), with a percentile bootstrap 95 % interval (10,000 resamples, seed 0).
    ``collisions_change``: mean paired change in collisions per episode over all the common
    episodes, with the same kind of interval.
    """
    import numpy as np
    from scipy.stats import binomtest, bootstrap

    def mean_ci(x: np.ndarray) -> tuple[float | None, float | None]:
        if len(x) >= 2 and np.ptp(x) > 0:
            ci = bootstrap((x,), np.mean, n_resamples=10_000, method="percentile",
                           random_state=0).confidence_interval  # fmt: skip
            return (float(ci.low), float(ci.high))
        return (float(x.mean()), float(x.mean())) if len(x) else (None, None)

    a = {e["episode"]: e for e in base}
    common = [(a[e["episode"]], e) for e in other if e["episode"] in a]
    if not common:
        return None
    gained = sum(1 for x, y in common if y["success_strict"] and not x["success_strict"])
    lost = sum(1 for x, y in common if x["success_strict"] and not y["success_strict"])
    p = binomtest(gained, gained + lost).pvalue if gained + lost else 1.0
    dt = np.array([
        y["time_to_dock_s"] - x["time_to_dock_s"]
        for x, y in common
        if x["success_strict"] and y["success_strict"]
        and x["time_to_dock_s"] is not None and y["time_to_dock_s"] is not None
    ])  # fmt: skip
    dc = np.array([float(y["collisions"] - x["collisions"]) for x, y in common])
    return {
        "episodes": len(common),
        "strict_change": (gained - lost) / len(common),
        "strict_gained": gained,
        "strict_lost": lost,
        "strict_mcnemar_p": p,
        "both_docked": len(dt),
        "time_change_s": float(dt.mean()) if len(dt) else None,
        "time_change_ci95_s": mean_ci(dt),
        "collisions_change": float(dc.mean()),
        "collisions_change_ci95": mean_ci(dc),
    }


def paired_vs_camera(rows: list[dict[str, Any]], ref: str = "camera") -> list[dict[str, Any]]:
    """Each camera row against the ``ref`` row of the same controller, episode by episode
    (:func:`paired_change`)."""
    refs = {b["controller"]: b for b in rows if b["condition"] == ref}
    out = []
    for r in rows:
        base = refs.get(r["controller"])
        if base is None or r is base or r["obs"] != "camera":
            continue
        change = paired_change(base["per_episode"], r["per_episode"])
        if change is not None:
            out.append({"condition": r["condition"], "controller": r["controller"], **change})
    return out


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    """Strict success per condition, policy beside PID, with the Wilson intervals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from uwdock.dockcore.io import atomic_path

    conds = list(dict.fromkeys(r["condition"] for r in rows))
    x = np.arange(len(conds))
    fig, ax = plt.subplots(figsize=(max(6.0, 1.1 * len(conds)), 3.8))
    for k, (ctrl, colour) in enumerate((("policy", "tab:blue"), ("pid", "tab:grey"))):
        cells = {r["condition"]: r for r in rows if r["controller"] == ctrl}
        val = np.array([100 * cells[c]["strict"] if c in cells else np.nan for c in conds])
        lo = np.array([100 * cells[c]["strict_ci95"][0] if c in cells else np.nan for c in conds])
        hi = np.array([100 * cells[c]["strict_ci95"][1] if c in cells else np.nan for c in conds])
        at = x + (k - 0.5) * 0.38
        ax.bar(at, val, 0.38, color=colour, label="PID baseline" if ctrl == "pid" else "PPO")
        ax.errorbar(at, val, yerr=[val - lo, hi - val], fmt="none", ecolor="k", capsize=2, lw=0.8)
    n_of = {r["condition"]: r["episodes"] for r in rows}
    ax.set_xticks(x, [f"{c}\n({n_of[c]} ep)" for c in conds], fontsize=8)
    ax.set_ylabel("strict success (%)")
    ax.set_ylim(0, 105)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)
    ax.set_title("docking success by condition (Wilson 95 % intervals)", fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--policy", required=True, help="policy.zip / run folder / .onnx")
    ap.add_argument("--episodes", type=int, default=100, help="episodes per headline row")
    ap.add_argument("--stress-episodes", type=int, default=30, help="episodes per harder row")
    ap.add_argument("--seed", type=int, default=50000)
    ap.add_argument("--usbl", default="evologics-s2cr", choices=list(USBL_PRESETS))
    ap.add_argument(
        "--nav",
        default="mems-ahrs-dvl",
        choices=list(NAV_PRESETS),
        help="the vehicle's navigation (uwdock.sim.navigation) [mems-ahrs-dvl]",
    )
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--rows", default="all", help="all, headline, or condition names (comma)")
    ap.add_argument("--controllers", default="policy,pid")
    ap.add_argument("--name", default="docking")
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    a = ap.parse_args()
    names = {r.name for r in ROWS}
    if a.rows == "all":
        chosen = list(ROWS)
    elif a.rows == "headline":
        chosen = [r for r in ROWS if r.headline]
    else:
        wanted = [w.strip() for w in a.rows.split(",")]
        unknown = [w for w in wanted if w not in names]
        if unknown:
            sys.exit(f"error: --rows: unknown condition {unknown[0]!r} (known: {sorted(names)})")
        chosen = [r for r in ROWS if r.name in wanted]
    controllers = [c.strip() for c in a.controllers.split(",")]
    if not set(controllers) <= {"policy", "pid"}:
        sys.exit("error: --controllers: policy, pid or both")
    # reads the policy's config
    envs = {r.name: env_for(r, a.policy, a.usbl, a.nav) for r in chosen}
    config = {
        "policy": a.policy,
        "episodes": a.episodes,
        "stress_episodes": a.stress_episodes,
        "seed": a.seed,
        "usbl": a.usbl,
        "nav": a.nav,
        "rows": [r.name for r in chosen],
        "controllers": controllers,
        "env": {name: to_dict(cfg) for name, cfg in envs.items()},
    }
    results: list[dict[str, Any]] = []
    kept = finished_cells(a.out_dir / f"{a.name}.json", config)
    if kept:
        print(f"resuming: {len(kept)} cells of {a.out_dir / a.name}.json kept", flush=True)
    for row in chosen:
        n = a.episodes if row.headline else a.stress_episodes
        for ctrl in controllers:
            spec = a.policy if ctrl == "policy" else "pid"
            old = kept.get((row.name, "pid" if ctrl == "pid" else "policy"))
            results.append(old or run_row(row, spec, envs[row.name], n, a.seed, a.workers))
            r = results[-1]
            print(
                f"{row.name:>14} {r['controller']:>6}: strict {100 * r['strict']:.0f} % "
                f"paper {100 * r['paper']:.0f} % ({r['wall_s']:.0f} s)",
                flush=True,
            )
            save_results(a.name, results, {**config, "complete": False}, a.out_dir)  # so far
    cols = ["condition", "controller", "episodes", "strict", "paper", "time_to_dock_s"]
    print(format_table(results, [*cols, "collisions", "final_e_xy_m_median", "wall_s"]))
    paired = paired_vs_camera(results)
    if paired:
        print("against the camera row (clear tank), episode by episode:")
        print(format_table(paired, list(paired[0])))
    final = {**config, "complete": True, "paired_vs_camera": paired}
    print(save_results(a.name, results, final, a.out_dir))
    if set(controllers) == {"policy", "pid"}:
        plot(results, a.out_dir / f"{a.name}.png")


if __name__ == "__main__":
    main()
