"""Where the IMU-detected collisions of a controller happen: at the seat, as a bounce, or away.

Usage::

    python bench/collision_sites.py --policy rl/policies/realistic_ppo [--controllers policy,pid]
        [--episodes 20] [--seed 70000] [--name collision_sites] [--out-dir bench/results]

Runs seeded episodes of each controller in the policy's training env (its observation source,
navigation, USBL and reward; the PID under the same settings) and logs every step that the
reward's collision detector (an IMU jump above Gamma, ``DockingReward.collision``) counts. Each
collision is classed by the vehicle's true error to the docking point at that step:

* ``seat``: within ``--seat-xy-m`` horizontally (default 0.1 m) of the docking point;
* ``bounce``: a ``seat`` collision within ``--bounce-s`` (default 0.5 s) of the collision
  before it (the landing counted twice: Gamma doubles at a hit and halves back a step later);
* ``away``: farther than ``--seat-xy-m``: a hard manoeuvre or a hit on the station's frame.

Prints one row per controller (collisions per episode, by class; episodes with a bounce) and
writes ``<NAME>.json`` (each row with its collisions' episode, time, errors and class) in
``--out-dir``.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import numpy as np

from uwdock.dockcore.bench import format_table, save_results

HERE = Path(__file__).resolve().parent


def classify(events: list[dict[str, Any]], seat_xy_m: float, bounce_s: float) -> None:
    """Set each event's ``site`` (seat / bounce / away) in place; ``events`` are one episode's,
    in time order, each with ``time_s`` and ``e_xy_m``."""
    prev_t = -math.inf
    for e in events:
        if e["e_xy_m"] > seat_xy_m:
            e["site"] = "away"
        elif e["time_s"] - prev_t <= bounce_s + 1e-9:
            e["site"] = "bounce"
        else:
            e["site"] = "seat"
        prev_t = e["time_s"]


def summarise(events: list[dict[str, Any]], n_episodes: int) -> dict[str, Any]:
    """Collisions per episode in total and by site, and the episodes with a bounce."""
    out: dict[str, Any] = {"episodes": n_episodes, "collisions": len(events) / n_episodes}
    for site in ("seat", "bounce", "away"):
        out[site] = sum(e["site"] == site for e in events) / n_episodes
    out["episodes_with_bounce"] = len({e["episode"] for e in events if e["site"] == "bounce"})
    return out


def run(
    policy: str, controller: str, episodes: int, seed: int, seat_xy_m: float, bounce_s: float
) -> list[dict[str, Any]]:
    """Every collision of ``episodes`` seeded episodes of ``controller`` ("policy" or "pid") in
    ``policy``'s training env (``rl.evaluate.episodes.run_episodes``' traces), classed
    (:func:`classify`)."""
    from tqdm import tqdm

    from uwdock.rl.evaluate.episodes import run_episodes
    from uwdock.rl.policy.env_settings import policy_training_env
    from uwdock.rl.policy.policy_io import load_controller

    resolved = policy_training_env(policy)
    if resolved is None:
        raise SystemExit(f"error: {policy} has no run config to take the training env from")
    model, vecnorm, _ = load_controller("pid" if controller == "pid" else policy, resolved.cfg)
    with tqdm(total=episodes, desc=controller, unit="ep") as bar:
        res = run_episodes(
            model, resolved.cfg, episodes, seed, vecnorm=vecnorm,
            progress=lambda done, _n: bar.update(done - bar.n),
        )  # fmt: skip
    events: list[dict[str, Any]] = []
    for k, (row, tr) in enumerate(zip(res.episodes, res.traces, strict=True)):
        ep = [
            {"episode": k, "time_s": round(float(t), 3), "e_xy_m": float(np.hypot(e[0], e[1])),
             "e_z_m": float(e[2]), "docked_strict": bool(row["success_strict"])}
            for t, e, hit in zip(tr.time_s, tr.e_true, tr.collided, strict=True) if hit
        ]  # fmt: skip
        classify(ep, seat_xy_m, bounce_s)
        events += ep
    return events


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--policy", required=True, help="a run folder or policy folder with config.toml"
    )
    ap.add_argument("--controllers", default="policy,pid")
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--seed", type=int, default=70000)
    ap.add_argument("--seat-xy-m", type=float, default=0.1)
    ap.add_argument("--bounce-s", type=float, default=0.5)
    ap.add_argument("--name", default="collision_sites")
    ap.add_argument("--out-dir", type=Path, default=HERE / "results")
    args = ap.parse_args(argv)
    if args.episodes < 1:
        raise SystemExit("error: --episodes must be at least 1")
    controllers = [c.strip() for c in args.controllers.split(",") if c.strip()]
    if not controllers or set(controllers) - {"policy", "pid"}:
        raise SystemExit("error: --controllers takes policy and/or pid")
    rows = []
    for c in controllers:
        events = run(args.policy, c, args.episodes, args.seed, args.seat_xy_m, args.bounce_s)
        rows.append({"controller": c, **summarise(events, args.episodes), "events": events})
    cols = [
        "controller",
        "episodes",
        "collisions",
        "seat",
        "bounce",
        "away",
        "episodes_with_bounce",
    ]
    print(format_table(rows, cols))
    config = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    path = save_results(args.name, rows, config=config, out_dir=args.out_dir)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
