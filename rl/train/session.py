"""One training run's state between rollouts: the schedule, evaluations, ``best/`` and the
checkpoints (:mod:`rl.train.checkpoint`), so that a run killed at any moment and resumed gives the
same checkpoints, the same evaluation history and the same ``best/`` as one never stopped.

How resuming can be exact: everything happens at *rollout boundaries* (after a policy update,
before the next rollout), where the learner holds no half-collected data. At a checkpoint the
training envs are reset with seeds drawn from ``(seed, step)`` (episodes in flight end as a
truncation, which PPO has already bootstrapped with the value of the last observation), then
the unit is written. A resumed run loads the unit and resets its fresh envs with the same
seeds, so learner, normalisation, random generators and envs are all where they were.
Evaluations run at boundaries too, on their own envs with fixed seeds: with several training
envs, in the env workers (:class:`rl.train.workers.EvalJob`), a share each, the same rows as in one
process.
"""

from __future__ import annotations

import json
import pickle
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from uwdock.dockcore.io import atomic_write_files, atomic_write_text
from uwdock.rl.env.curriculum import curriculum_level, curriculum_z_end, near_start_share
from uwdock.rl.evaluate.batched import batched_episodes
from uwdock.rl.evaluate.episodes import run_episodes, summarise
from uwdock.rl.evaluate.report import plot_eval_history
from uwdock.rl.policy.policy_format import LEGACY, MODEL, WEIGHTS, policy_files
from uwdock.rl.train.checkpoint import (
    Unit,
    load_model,
    restore_rng,
    rng_state,
    training_files,
    write_unit,
)
from uwdock.rl.train.workers import EvalJob

HISTORY = "eval_history.jsonl"
EVAL_SEED = 10_000


def eval_score(summary: dict[str, Any], terminate_on: str, select_best: str) -> list[float]:
    """What an evaluation is ranked by for ``best/`` (higher is better, compared as a list).

    ``select_best`` "success": the success rate that ends the episode (``terminate_on``), then
    the other, then the mean return; "return": the mean return alone. A rate on 30 episodes
    moves in steps of 3.3 points, so under "success" one more episode docked outranks any
    difference in collisions or time; "return" weighs them as the reward does.
    """
    if select_best == "return":
        return [float(summary["mean_return"])]
    paper, strict = summary["success_rate"], summary["success_rate_strict"]
    first, second = (strict, paper) if terminate_on == "strict" else (paper, strict)
    return [first, second, summary["mean_return"]]


def replaces_best(
    summary: dict[str, Any], best: dict[str, Any] | None, history: list[dict[str, Any]],
    terminate_on: str, select_best: str,
) -> bool:  # fmt: skip
    """Whether a new evaluation's ``summary`` takes ``best/`` from ``best`` (the kept
    evaluation's record, None before the first); ``history`` is the run's earlier evaluations.

    "success" and "return" rank by :func:`eval_score`. "fastest": of the evaluations whose
    success rate (the one that ends the episode, ``terminate_on``) is within one episode of the
    run's highest so far, the one whose docked episodes took the least mean time. A rate on
    30 episodes cannot tell 29 docked from 30 (its standard error is ~3 points), while the
    time to dock keeps falling as PPO trains, so under "success" an early evaluation with one
    more episode docked outranks a later one that docks as often, seconds faster. Online: the
    kept evaluation stays until a faster one within reach comes, or until the highest rate
    rises more than one episode above it (then the evaluation that raised it is kept).
    """
    if best is None:
        return True
    if select_best != "fastest":
        return eval_score(summary, terminate_on, select_best) > eval_score(
            best, terminate_on, select_best
        )
    key = "success_rate_strict" if terminate_on == "strict" else "success_rate"
    top = max([float(r[key]) for r in history] + [float(summary[key])])
    slack = 1.0 / int(summary["episodes"]) + 1e-9  # one episode
    if float(best[key]) < top - slack:  # out of reach: ``summary`` raised the highest rate
        return True
    return float(summary[key]) >= top - slack and _dock_time(summary) < _dock_time(best)


def _dock_time(summary: dict[str, Any]) -> float:
    """The mean time to dock of an evaluation (infinite when nothing docked)."""
    t = summary.get("mean_time_to_dock_s")
    return float("inf") if t is None else float(t)


def boundary_seed(seed: int, step: int) -> int:
    """The seed the training envs are reset with at a checkpoint at ``step``."""
    return int(np.random.SeedSequence([seed, step]).generate_state(1, np.uint32)[0])


class TrainingSession:
    """The run's state at rollout boundaries (module docstring).

    Args:
        cfg: the run's ``TrainConfig``.
        run: the run folder.
        model: the SB3 model (its env is ``vecnorm`` or the raw VecEnv).
        vecnorm: the ``VecNormalize`` wrapper, or None.
        note: where notes go (one line each).
    """

    def __init__(self, cfg, run: Path, model, vecnorm, note: Callable[[str], None]) -> None:
        self.cfg = cfg
        self.run = run
        self.model = model
        self.vecnorm = vecnorm
        self.note = note
        self.schedule: dict[str, Any] = {}
        self.history: list[dict[str, Any]] = []
        self.best_files: dict[str, bytes] = {}
        self.last_checkpoint: int | None = None

    # ------------------------------------------------------------------ start

    def start(self, warm_started: bool) -> None:
        """A new run: first checkpoint at step 0; the warm-started policy is evaluated first."""
        every = self.cfg.eval_every
        warmup = self.cfg.imitation.critic_warmup_steps if warm_started else 0
        self.schedule = {
            "next_checkpoint": 0,
            "next_eval": (0 if warm_started else every) if every else None,
            "critic_warmup_until": warmup,
            "best_score": None,
            "best_step": None,
        }
        self._write_history()

    def restore(self, unit: Unit) -> None:
        """Continue from ``unit`` (the model and normalisation are already loaded)."""
        self.schedule = dict(unit.state["schedule"])
        self.history = list(unit.state["eval_history"])
        self.best_files = {k[5:]: v for k, v in unit.files.items() if k.startswith("best/")}
        if LEGACY[0] in self.best_files:  # a checkpoint of an older version: best/ as data
            self.best_files = legacy_best_files(type(self.model), self.best_files)
        self.last_checkpoint = unit.step
        self._write_history()
        self.plot_history()
        self._write_best()
        saved = self.model._last_obs
        self.apply_curriculum(unit.step)  # before the reset: its spawns follow the schedule
        self.reset_envs(unit.step)
        if saved is not None and not np.array_equal(saved, self.model._last_obs):
            self.note(
                "the environments do not come back to the checkpoint's state: the resumed run "
                "will differ from an uninterrupted one"
            )
        restore_rng(self.model, unit.state["rng"])

    # ------------------------------------------------------------------ at boundaries

    @property
    def critic_warmup_until(self) -> int:
        return int(self.schedule.get("critic_warmup_until", 0))

    def boundary(self, final: bool = False) -> None:
        """Evaluate and/or checkpoint if due at the current step (``final``: always save)."""
        n = int(self.model.num_timesteps)
        self.apply_curriculum(n)
        s = self.schedule
        if s["next_eval"] is not None and n >= s["next_eval"]:
            self.evaluate(n)
            while s["next_eval"] <= n:
                s["next_eval"] += self.cfg.eval_every
        if n >= s["next_checkpoint"] or (final and self.last_checkpoint != n):
            while s["next_checkpoint"] <= n:
                s["next_checkpoint"] += self.cfg.checkpoint_every
            self.checkpoint(n)

    def reset_envs(self, step: int) -> None:
        """Reset the training envs with the seeds of ``step`` (no normalisation update)."""
        model, vecnorm = self.model, self.vecnorm
        raw_venv = vecnorm.venv if vecnorm is not None else model.get_env()
        raw_venv.seed(boundary_seed(self.cfg.seed, step))
        raw = raw_venv.reset()
        obs = raw
        if vecnorm is not None:
            vecnorm.old_obs = raw
            vecnorm.returns = np.zeros(vecnorm.num_envs)
            obs = vecnorm.normalize_obs(raw)
        model._last_obs = obs
        model._last_episode_starts = np.ones((raw_venv.num_envs,), dtype=bool)
        if hasattr(model, "_last_original_obs"):
            model._last_original_obs = raw

    def apply_curriculum(self, step: int) -> None:
        """Push the curriculum's level at ``step`` (:mod:`rl.env.curriculum`) to the training envs
        (nothing when the run has no curriculum)."""
        cur = self.cfg.curriculum
        if cur.steps <= 0:
            return
        z_m, spawn = curriculum_level(cur, step, curriculum_z_end(self.cfg.env))
        near = near_start_share(cur, step)
        self.model.get_env().env_method("set_curriculum", z_m, spawn, near, cur.near_start_box)

    def checkpoint(self, step: int) -> Path:
        """Reset the envs, then write the unit of ``step``."""
        self.reset_envs(step)
        files = training_files(self.model, self.vecnorm)
        files.update({f"best/{k}": v for k, v in self.best_files.items()})
        state = {
            "step": step,
            "schedule": self.schedule,
            "eval_history": self.history,
            "rng": rng_state(self.model),
        }
        path = write_unit(self.run / "checkpoints", step, files, state)
        self.last_checkpoint = step
        return path

    def evaluate(self, step: int) -> dict[str, Any]:
        """Evaluate the deterministic policy on the fixed episodes; keep it in ``best/`` when
        the config's rule says so (:func:`replaces_best`)."""
        summary = self._frozen_summary(step)
        if summary is None:
            summary = summarise(self._eval_rows())
        logger = getattr(self.model, "_logger", None)
        if logger is not None:
            for k in ("success_rate", "success_rate_strict", "mean_time_to_dock_s"):
                if summary.get(k) is not None:
                    logger.record(f"eval/{k}", summary[k])
        score = eval_score(summary, self.cfg.env.terminate_on, self.cfg.select_best)
        kept = next((r for r in self.history if r["step"] == self.schedule["best_step"]), None)
        record = {"step": step, **summary}
        if replaces_best(summary, kept, self.history, self.cfg.env.terminate_on,
                         self.cfg.select_best):  # fmt: skip
            self.schedule["best_score"], self.schedule["best_step"] = score, step
            self.best_files = policy_files(self.model, self.vecnorm)
            self._write_best()
            record["best"] = True
        self.history.append(record)
        self._write_history()
        return record

    def _frozen_summary(self, step: int) -> dict[str, Any] | None:
        """The last evaluation's summary when the policy evaluated at ``step`` is the one it
        evaluated, else None. While PPO trains the critic alone after the warm start, the actor
        and the observation normalisation (frozen after imitation) do not change, and an
        evaluation is deterministic on fixed episodes: evaluating again gives the same rows
        (tested), so the record is repeated instead of flown again."""
        if not self.history or step >= self.critic_warmup_until:
            return None
        last = self.history[-1]
        if int(last["step"]) >= self.critic_warmup_until:
            return None
        return {k: v for k, v in last.items() if k not in ("step", "best")}

    def _eval_rows(self) -> list[dict[str, Any]]:
        """The evaluation episodes' rows: on the batched simulator when training on it (a
        consecutive share in each batch worker, all at once, in batches the workers keep; with
        one batch process one batch of all episodes, here), else in the env workers when there
        are several, else here."""
        from stable_baselines3.common.vec_env import SubprocVecEnv

        n = self.cfg.eval_episodes
        raw_venv = self.vecnorm.venv if self.vecnorm is not None else self.model.get_env()
        if self.cfg.simulator == "batched":  # the simulator it trains on, all episodes at once
            from uwdock.rl.train.grouped_vec_env import BatchGroupsVecEnv  # SB3 at module level

            if isinstance(raw_venv, BatchGroupsVecEnv):  # a share in each batch worker
                return raw_venv.evaluate(self._eval_job(n, len(raw_venv.groups)))
            return batched_episodes(self.model, self.cfg.env, n, EVAL_SEED, self.vecnorm)
        if not isinstance(raw_venv, SubprocVecEnv):
            return run_episodes(
                self.model, self.cfg.env, n, EVAL_SEED, vecnorm=self.vecnorm, record=False
            ).episodes
        parts = raw_venv.env_method("evaluate_share", self._eval_job(n, raw_venv.num_envs))
        return sorted((r for p in parts for r in p), key=lambda r: r["episode"])

    def _eval_job(self, n: int, n_workers: int) -> EvalJob:
        """The evaluation of the current policy, for ``n_workers`` workers to share."""
        return EvalJob(
            policy_files(self.model, self.vecnorm),
            self.cfg.env,
            n,
            EVAL_SEED,
            n_workers,
        )

    # ------------------------------------------------------------------ files

    def _write_history(self) -> None:
        text = "".join(json.dumps(r, sort_keys=True) + "\n" for r in self.history)
        atomic_write_text(self.run / HISTORY, text)

    def plot_history(self) -> None:
        """``eval_history.png`` from the history written so far: when the run ends or resumes,
        not at every evaluation (a plot costs about 0.4 s of the trainer's time, ten
        seconds over a run; ``eval_history.jsonl`` and TensorBoard follow the run meanwhile)."""
        if self.history:
            plot_eval_history(self.run / HISTORY, self.run / "eval_history.png")

    def _write_best(self) -> None:
        best = self.run / "best"
        atomic_write_files({best / name: data for name, data in self.best_files.items()})
        for stale in (*LEGACY, MODEL, WEIGHTS):
            if best.is_dir() and stale not in self.best_files:
                (best / stale).unlink(missing_ok=True)


def legacy_best_files(algo_cls: Any, files: dict[str, bytes]) -> dict[str, bytes]:
    """``best/`` of a version-1 checkpoint (``policy.zip`` and ``vecnormalize.pkl``) in the
    policy format. Unpickles: only for a run folder the user trusts (``--trust-pickle``)."""
    model = load_model(algo_cls, files[LEGACY[0]])
    vecnorm = pickle.loads(files[LEGACY[1]]) if LEGACY[1] in files else None
    return policy_files(model, vecnorm)


def load_vecnormalize(data: bytes, venv):
    """A version-1 checkpoint's pickled ``VecNormalize`` put back on ``venv``. Unpickles: only
    for a run folder the user trusts (``--trust-pickle``)."""
    vecnorm = pickle.loads(data)
    vecnorm.set_venv(venv)
    return vecnorm
