"""Training throughput: env steps per second of a training recipe, per-env and batched simulator.

Usage::

    python bench/bench_train_speed.py [--quick] [--json] [--recipe shipped]
        [--config CONFIG]
        [--simulators per-env,batched,batched-shared,batched-own,batched-kernel] [--envs 2]
        [--batch-envs 64] [--batch-workers 2]
        [--rollouts 8]
        [--repeats 3] [--seed 1] [--init-policy POLICY] [--name train_speed]

The configuration measured is the first stage of ``--recipe`` (``configs/recipes/``, default
``shipped``: what ``rl train --recipe shipped`` trains first), or ``--config``. Each
measurement trains it (``rl.train.training.train``, no progress bar) from scratch in a temporary run
folder, in a fresh process (a process that has started SAPIEN cannot fork working env workers
on a GPU's Vulkan driver), with the periodic evaluation and checkpoints switched off, for
``rollouts`` PPO rollouts of ``n_steps x n_envs`` steps (PPO alone: the recipe's DAgger warm
start is a fixed cost, timed with the whole run by ``bench/bench_recipe_time.py``), after one
uncounted warm-up run (numba compiles its kernels into an on-disk cache on first use). Each run
gives two rates, both from that one run, never the difference of two noisy runs, so never
negative: its steps over its wall time, start included (processes, the first observations),
and the steady rate, the steps of its rollouts after the first over the time from the end of
the first rollout to the end of the last on the run's own clock (its TensorBoard stamps,
updates included). The table gives the median, min and max over ``repeats`` runs per row, the
seconds per rollout, and the minutes the recipe's PPO steps would take at the steady rate
(``recipe_min``: every stage's ``total_steps``; the warm start and the periodic evaluations
come on top) against the 5-minute target, and the rate of the same rollouts alone (the
simulator and the policy's actions, without PPO's update: the run's ``time/rollout_s``). The
summary's ``ratio`` is of the steady rates, ``ratio_start_included`` of the whole runs',
``ratio_rollouts_alone`` of the rollouts alone (the update, the same work in both, is not in
it).

Simulators, side by side in one run on the same machine (``--simulators``, default the first
two):

* ``per-env``: the recipe as written, one :class:`rl.env.docking_env.DockingEnv` per worker process
  (``--envs`` env counts; more than the recipe's change its batches: those rows measure the
  machine, not a validated recipe); a batched recipe (``simulator = "batched"``, the shipped
  realistic one) runs on 2 per-env workers (``--envs``) with rollouts as long as its own;
* ``batched``: :class:`rl.env.batch_env.BatchDockingEnv`, ``--batch-envs`` envs stepped as arrays,
  split over ``--batch-workers`` processes (1: the trainer's own), ``n_steps`` scaled so that a
  rollout holds as many steps as the recipe's (``n_steps x n_envs``); the update (batch size,
  epochs) is the recipe's; its vehicles in contact with the DS stepped as the recipe says
  (``[env.world] batch_contact``: one shared PhysX scene, ``"shared"``,
  :mod:`uwdock.sim.contact_scene`, or the kernel's own contact model, ``"kernel"``,
  :mod:`uwdock.sim.kernel_contact`);
* ``batched-shared``, ``batched-own``, ``batched-kernel``: the same with ``batch_contact`` set
  to ``"shared"``, ``"own"`` (each vehicle's PhysX in its own scene, bit-equal to the per-env
  physics) or ``"kernel"``, whatever the recipe says, to compare them.

``--init-policy`` starts every run from a trained policy (``rl train --init-policy``): an early
policy's episodes are mostly free flight far from the DS, a trained one's end in contact, which
costs the physics more per step, so the two bracket a training run's mix. ``--quick``: 3
rollouts, 1 repeat. ``--json`` prints one JSON line last: ``batched_steps_per_s``,
``per_env_steps_per_s`` (the recipe's env count) and their ratio (and
``batched_<contact>_steps_per_s`` for each ``batched-<contact>`` row measured).

Writes ``bench/results/<name>.json`` (rows + machine, commit, packages).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import statistics
import sys
import tempfile
import time
from pathlib import Path

from uwdock.dockcore.bench import format_table, save_results
from uwdock.dockcore.config import load_config, replace
from uwdock.rl.train.recipe import load_recipe
from uwdock.rl.train.training import TrainConfig, train

#: The recipe's wall time to aim for: both stages in 5 minutes on 2 idle cores.
TARGET_MIN = 5.0

OFF = 10**9  # an evaluation / checkpoint interval no run reaches
#: --simulators' rows
SIMULATORS = ("per-env", "batched", "batched-shared", "batched-own", "batched-kernel")


def _measure(
    cfg: TrainConfig, envs: int, rollouts: int, init: str | None = None, batch_workers: int = 1
) -> tuple[int, float, int, float, float | None]:
    """Train ``rollouts`` rollouts with ``envs`` envs (from policy ``init`` if given), PPO
    alone (a warm start by imitation is a fixed cost of a run, not a rate: the recipe's is in
    ``bench/bench_recipe_time.py``'s whole run); returns (steps, wall seconds) of the whole run
    and (steps, seconds, rollout seconds) from the end of its first rollout to the end of its
    last, on the run's own clock (:func:`rollout_clock`)."""
    steps = rollouts * cfg.ppo.n_steps * envs
    run_cfg = replace(cfg, n_envs=envs, total_steps=steps, eval_every=OFF, checkpoint_every=OFF,
                      imitation=replace(cfg.imitation, teacher="none"))  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="bench_train_") as tmp:
        t0 = time.perf_counter()
        train(
            run_cfg, Path(tmp) / "run", progress=False, init_policy=init,
            note=lambda _m: None, batch_workers=batch_workers,
        )  # fmt: skip
        wall_s = time.perf_counter() - t0
        return (steps, wall_s, *rollout_clock(Path(tmp) / "run"))


def rollout_clock(run: Path) -> tuple[int, float, float | None]:
    """(steps, seconds, rollout seconds) between the end of a run's first rollout and the end
    of its last, from the times its TensorBoard log stamped on them (SB3's ``time/fps``, one a
    rollout): the steady rate of the rollouts and updates, without the start; the rollout
    seconds are those of the same rollouts alone (``time/rollout_s``, the simulator and the
    policy's actions, no update; None in a log without them); (0, 0.0, None) for one rollout."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    files = sorted((run / "tb").rglob("events.out.tfevents.*"))
    if not files:
        raise RuntimeError(f"{run}: no TensorBoard log to time the rollouts by")
    acc = EventAccumulator(str(files[-1]))
    acc.Reload()
    marks = acc.Scalars("time/fps")
    if len(marks) < 2:
        return (0, 0.0, None)
    alone = None
    if "time/rollout_s" in acc.Tags()["scalars"]:
        later = [e.value for e in acc.Scalars("time/rollout_s") if e.step > marks[0].step]
        alone = float(sum(later)) if len(later) == len(marks) - 1 else None
    return (marks[-1].step - marks[0].step, marks[-1].wall_time - marks[0].wall_time, alone)


def _child(cfg: TrainConfig, envs: int, rollouts: int, init, workers: int, out) -> None:
    out.put(_measure(cfg, envs, rollouts, init, workers))


def measure(
    cfg: TrainConfig, envs: int, rollouts: int, init: str | None = None, batch_workers: int = 1
):
    """:func:`_measure` in a fresh (spawned, non-daemonic: it starts env workers) process."""
    ctx = multiprocessing.get_context("spawn")
    out = ctx.Queue()
    proc = ctx.Process(target=_child, args=(cfg, envs, rollouts, init, batch_workers, out))
    proc.start()
    proc.join()
    if proc.exitcode != 0:
        sys.exit(f"error: the measurement with {envs} envs failed (exit {proc.exitcode})")
    return out.get()


def _rescaled(cfg: TrainConfig, simulator: str, envs: int) -> TrainConfig:
    """The recipe on ``simulator`` with ``envs`` envs and a rollout as long as its own
    (``n_steps`` scaled, at least 1 per env); the update (batch size, epochs) is the recipe's."""
    n_steps = max(1, cfg.ppo.n_steps * cfg.n_envs // envs)
    return replace(cfg, simulator=simulator, n_envs=envs, ppo=replace(cfg.ppo, n_steps=n_steps))


def batched(cfg: TrainConfig, batch_envs: int, contact: str | None = None) -> TrainConfig:
    """The recipe on the batched simulator with ``batch_envs`` envs, its DS contact stepped as
    ``contact`` says (:class:`uwdock.sim.world_config.WorldConfig`'s ``batch_contact``; None:
    the recipe's)."""
    world = replace(cfg.env.world, batch_contact=contact or cfg.env.world.batch_contact)
    return _rescaled(replace(cfg, env=replace(cfg.env, world=world)), "batched", batch_envs)


def per_env(cfg: TrainConfig, envs: int | None) -> TrainConfig:
    """The recipe on the per-env simulator: as written when it is a per-env recipe; a batched
    recipe with ``envs`` (default 2) worker envs and a rollout as long as its own."""
    if cfg.simulator != "batched":
        return cfg if envs is None else replace(cfg, n_envs=envs)
    return _rescaled(cfg, "per-env", 2 if envs is None else envs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--recipe", default="shipped", help="the recipe whose first stage to measure")
    ap.add_argument("--config", default=None, help="measure this config instead")
    ap.add_argument("--simulators", default="per-env,batched")
    ap.add_argument("--envs", default=None, help="per-env: comma-separated env counts [recipe's]")
    ap.add_argument("--batch-envs", type=int, default=64, help="batched: envs in the batch")
    ap.add_argument(
        "--batch-workers", type=int, default=2, help="batched: processes the batch is split over"
    )
    ap.add_argument("--rollouts", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="3 rollouts, 1 repeat")
    ap.add_argument("--json", action="store_true", help="print one JSON summary line last")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--init-policy", default=None, help="start every run from this policy")
    ap.add_argument("--name", default="train_speed")
    ap.add_argument("--out-dir", type=Path, default=None)
    a = ap.parse_args()
    if a.quick:
        a.rollouts, a.repeats = 3, 1
    sims = [x.strip() for x in a.simulators.split(",") if x.strip()]
    if a.rollouts < 1 or a.repeats < 1:
        sys.exit("error: --rollouts and --repeats must be at least 1")
    if not sims or any(x not in SIMULATORS for x in sims):
        sys.exit(f"error: --simulators takes {', '.join(SIMULATORS)}")
    _, stages, _ = load_recipe(a.recipe)
    recipe_steps = sum(c.total_steps for c in stages.values())
    first = next(iter(stages.values()))
    base = load_config(TrainConfig, a.config, section="train") if a.config else first
    recipe = replace(base, seed=a.seed)
    runs = []
    if "per-env" in sims:
        counts = [int(e) for e in a.envs.split(",")] if a.envs else [None]
        runs += [("per-env", per_env(recipe, e)) for e in counts]
    if "batched" in sims:
        runs.append(("batched", batched(recipe, a.batch_envs)))
    for sim in SIMULATORS[2:]:
        if sim in sims:
            runs.append((sim, batched(recipe, a.batch_envs, sim.removeprefix("batched-"))))
    workers = {sim: a.batch_workers for sim in SIMULATORS[1:]} | {"per-env": 1}
    rows = []
    for sim, cfg in runs:
        rates, walls, steady, alone = [], [], [], []
        envs = cfg.n_envs
        # a first run fills the on-disk caches (numba kernels) that the first measured run
        # would otherwise pay for alone; not counted
        measure(cfg, envs, 1, a.init_policy, workers[sim])
        for k in range(a.repeats):
            steps, wall_s, n_steady, t_steady, t_alone = measure(
                cfg, envs, a.rollouts, a.init_policy, workers[sim]
            )
            rates.append(steps / wall_s)
            walls.append(wall_s)
            steady.append(n_steady / t_steady if t_steady > 0 else None)
            alone.append(n_steady / t_alone if t_alone else None)
            print(
                f"{sim}, {envs} envs, run {k + 1}/{a.repeats}: {steps:,} steps in {wall_s:.1f} s "
                f"(start included): {rates[-1]:.0f} steps/s; after the first rollout "
                f"{steady[-1] or 0:.0f} steps/s, the rollouts alone {alone[-1] or 0:.0f} steps/s",
                flush=True,
            )
        med = statistics.median(rates)
        ok = [r for r in steady if r is not None]
        steady_med = statistics.median(ok) if ok else None
        ok_alone = [r for r in alone if r is not None]
        rows.append(
            {
                "simulator": sim,
                "envs": envs,
                "processes": envs if sim == "per-env" and envs > 1 else workers[sim],
                "n_steps": cfg.ppo.n_steps,
                "contact": cfg.env.world.batch_contact if sim != "per-env" else "physx",
                "recipe": sim == "batched" or (sim == "per-env" and cfg == per_env(recipe, None)),
                "steps_per_run": a.rollouts * cfg.ppo.n_steps * envs,
                "steps_per_s_median": med,
                "steps_per_s_min": min(rates),
                "steps_per_s_max": max(rates),
                "s_per_rollout_median": statistics.median(walls) / a.rollouts,
                "steady_steps_per_s_median": steady_med,
                "steady_steps_per_s_min": min(ok) if ok else None,
                "steady_steps_per_s_max": max(ok) if ok else None,
                "rollout_steps_per_s_median": (statistics.median(ok_alone) if ok_alone else None),
                "recipe_min": recipe_steps / (steady_med or med) / 60.0,
            }
        )
    print(format_table(rows, list(rows[0])))
    mine = [r for r in rows if r["recipe"] or r["simulator"].startswith("batched-")]
    whole = {r["simulator"]: r["steps_per_s_median"] for r in mine}
    rate = {r["simulator"]: r["steady_steps_per_s_median"] or r["steps_per_s_median"] for r in mine}
    both = "batched" in rate and "per-env" in rate
    alone = {r["simulator"]: r["rollout_steps_per_s_median"] for r in mine}
    both_alone = both and alone["batched"] is not None and alone["per-env"] is not None
    summary = {
        "recipe_min_at_batched_rate": (
            recipe_steps / rate["batched"] / 60.0 if "batched" in rate else None
        ),
        "target_min": TARGET_MIN,
        "batched_steps_per_s": rate.get("batched"),
        "per_env_steps_per_s": rate.get("per-env"),
        "ratio": rate["batched"] / rate["per-env"] if both else None,
        "ratio_start_included": whole["batched"] / whole["per-env"] if both else None,
        "batched_rollout_steps_per_s": alone.get("batched"),
        "per_env_rollout_steps_per_s": alone.get("per-env"),
        "ratio_rollouts_alone": alone["batched"] / alone["per-env"] if both_alone else None,
    }
    for sim in SIMULATORS[2:]:
        if sim in rate:
            summary = {f"{sim.replace('-', '_')}_steps_per_s": rate[sim], **summary}
    bench_cfg = {
        "recipe": a.recipe,
        "recipe_steps": recipe_steps,
        "config": a.config or f"the {a.recipe} recipe's first stage",
        "seed": a.seed,
        "init_policy": a.init_policy,
        "rollouts": a.rollouts,
        "repeats": a.repeats,
        "batch_envs": a.batch_envs,
        "batch_workers": a.batch_workers,
        "recipe_n_steps": recipe.ppo.n_steps,
        "recipe_n_envs": recipe.n_envs,
        "recipe_total_steps": recipe.total_steps,
        "summary": summary,
    }
    print("wrote", save_results(a.name, rows, bench_cfg, a.out_dir))
    if summary["ratio"] is not None:
        print(f"batched / per-env: {summary['ratio']:.1f}x after the first rollout, "
              f"{summary['ratio_start_included']:.1f}x with the start")  # fmt: skip
    if summary["ratio_rollouts_alone"] is not None:
        print(f"batched / per-env, the rollouts alone (no update): "
              f"{summary['ratio_rollouts_alone']:.1f}x")  # fmt: skip
    if summary["recipe_min_at_batched_rate"] is not None:
        print(
            f"the {a.recipe} recipe's {recipe_steps:,} steps at the batched rate: "
            f"{summary['recipe_min_at_batched_rate']:.1f} min (target {TARGET_MIN:g} min; "
            "evaluations not included)"
        )
    if a.json:
        print(json.dumps(summary))


if __name__ == "__main__":
    main()
