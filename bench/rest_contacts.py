"""Where a controller rests on the docking station in chosen episodes: its error to the target
and PhysX's contact points with the station, in the DS frame, at chosen moments.

Usage::

    python bench/rest_contacts.py --policy rl/policies/realistic_ppo --row all --seed 60000
        --episodes 14,51,84,95 [--at-s 20,30,40,50,59] [--name rest_contacts]
        [--out-dir bench/results]

Runs each episode (seed ``--seed`` + index, as ``bench_docking.py`` and ``rl eval`` number
them) in ``bench_docking.py``'s env of the row (its conditions, EvoLogics USBL, drifting
navigation, the policy's training settings, strict termination) and, at each ``--at-s``
moment, records the true error to the docking target (body frame), the vehicle's position in
the DS frame, the action, and every contact between the vehicle and the station (point in the
DS frame, impulse over the physics step). Prints one line per moment and writes
``<NAME>.json``. This is how the docking page's "Why the combined row misses" was found.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
from bench_docking import ROWS, env_for  # a sibling: the script's folder is on the path

from uwdock.dockcore.bench import save_results

HERE = Path(__file__).resolve().parent


def contacts_in_ds_frame(scene, vehicle: str = "auv", ds: str = "docking_station") -> list:
    """The scene's contacts between ``vehicle`` and ``ds`` (entity names) with an impulse:
    ``{"point_ds_m", "impulse_ns"}`` per contact point, positions in the station's frame."""
    by_name = {e.name: e for e in scene.entities}
    T_ds_world = np.linalg.inv(by_name[ds].pose.to_transformation_matrix())
    out = []
    for c in scene.get_contacts():
        if {b.entity.name for b in c.bodies} != {vehicle, ds}:
            continue
        for p in c.points:
            impulse = float(np.linalg.norm(p.impulse))
            if impulse > 0:
                point = (T_ds_world @ np.append(p.position, 1.0))[:3]
                out.append({"point_ds_m": np.round(point, 4).tolist(), "impulse_ns": impulse})
    return out


def trace(policy: str, row_name: str, seed: int, episode: int, at_s: list[float]) -> list:
    """The episode's records at each moment of ``at_s`` it lives to (module docstring)."""
    from uwdock.calibration.frames import inv_T
    from uwdock.rl.env.docking_env import DockingEnv
    from uwdock.rl.evaluate.episodes import as_controller
    from uwdock.rl.policy.policy_io import load_controller

    row = next(r for r in ROWS if r.name == row_name)
    cfg = env_for(row, policy, "evologics-s2cr", "mems-ahrs-dvl")
    model, vecnorm, _ = load_controller(policy, cfg)
    ctrl = as_controller(model, vecnorm)
    env = DockingEnv(cfg)
    records: list[dict[str, Any]] = []
    try:
        obs, info = env.reset(seed=seed + episode)
        ctrl.reset()
        done, moments = False, iter(sorted(at_s))
        moment = next(moments, None)
        while not done and moment is not None:
            action = np.asarray(ctrl.act(obs), dtype=np.float64)
            obs, _, term, trunc, info = env.step(action)
            done = term or trunc
            if info["time_s"] >= moment - 1e-6:
                T_ds_body = inv_T(info["T_world_ds"]) @ info["T_world_body"]
                records.append({
                    "episode": episode, "time_s": round(float(info["time_s"]), 2),
                    "e_true_m": np.round(info["e_true"], 4).tolist(),
                    "body_in_ds_m": np.round(T_ds_body[:3, 3], 4).tolist(),
                    "action": np.round(action, 3).tolist(),
                    "success_paper": bool(info["success_paper"]),
                    "success_strict": bool(info["success_strict"]),
                    "contacts": contacts_in_ds_frame(env.world.scene),
                })  # fmt: skip
                moment = next(moments, None)
    finally:
        env.close()
    return records


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--policy", required=True, help="policy.zip / run folder / .onnx, or pid")
    ap.add_argument("--row", default="all", help="a condition of bench_docking.py")
    ap.add_argument("--seed", type=int, default=60000, help="seed of episode 0")
    ap.add_argument("--episodes", required=True, help="episode indices (comma)")
    ap.add_argument("--at-s", default="20,30,40,50,59", help="moments to record (s, comma)")
    ap.add_argument("--name", default="rest_contacts")
    ap.add_argument("--out-dir", type=Path, default=HERE / "results")
    a = ap.parse_args(argv)
    try:
        episodes = [int(x) for x in a.episodes.split(",")]
        at_s = [float(x) for x in a.at_s.split(",")]
    except ValueError as exc:
        ap.error(f"--episodes takes integers, --at-s numbers, each comma-separated ({exc})")
    if min(episodes) < 0 or not all(0 < t < 1e6 for t in at_s):
        ap.error("--episodes must be >= 0 and --at-s moments finite and > 0 s")
    if a.row not in {r.name for r in ROWS}:
        ap.error(f"--row {a.row!r} is not a condition of bench_docking.py")
    rows = []
    for k in episodes:
        for r in trace(a.policy, a.row, a.seed, k, at_s):
            rows.append(r)
            pts = "; ".join(f"{c['point_ds_m']}" for c in r["contacts"]) or "none"
            print(f"episode {k} t={r['time_s']:5.1f} s  e_true {r['e_true_m']}  "
                  f"strict {r['success_strict']}  contacts (DS frame): {pts}")  # fmt: skip
    bench_config = {"policy": a.policy, "row": a.row, "seed": a.seed, "episodes": a.episodes,
                    "at_s": at_s}  # fmt: skip
    print(f"wrote {save_results(a.name, rows, bench_config, a.out_dir)}")


if __name__ == "__main__":
    main()
