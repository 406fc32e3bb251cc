"""Training callback: the rollout boundaries of :class:`rl.train.session.TrainingSession`
(checkpoints, evaluations), the critic warm-up, the progress bar, and ``charts/`` (episode success
rates, reward terms) in TensorBoard; and, for a resumed run, its TensorBoard events cut back to the
checkpoint it resumes from (:func:`drop_tensorboard_events_after`), so each step is logged once.

This module subclasses Stable-Baselines3's ``BaseCallback``, so it imports SB3 (and torch under
it) at module level: only the function that trains imports it (``rl.train.training``), so importing
``rl.train.training`` (``rl --help``, ``rl eval``) does not pay for it
(``tests/test_architecture.py``: heavy modules of the tree).
"""

from __future__ import annotations

import os
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from tqdm import tqdm

from uwdock.dockcore.io import atomic_path

__all__ = ["TrainingCallback", "drop_tensorboard_events_after"]


def drop_tensorboard_events_after(tb_dir: str | os.PathLike[str], step: int) -> int:
    """Cut a run's TensorBoard event files back to ``step``: every event of a later step is
    removed (each file rewritten atomically, its other events byte for byte).

    A run killed after its checkpoint at ``step`` had logged the steps up to the kill; resumed
    from that checkpoint (SB3 goes on writing into the same ``tb/tb_N`` folder) it logs them
    again, and TensorBoard would show both (34 duplicated points in a killed and resumed
    run). Called before the resumed run's writer opens: what it logs from ``step`` on is then
    the only record of those steps. A record cut short by the kill (the file's tail) goes too.

    Args:
        tb_dir: the run's ``tb/`` folder (searched recursively; missing: nothing to do).
        step: the checkpoint's step (0: a run started again from the beginning).

    Returns:
        The number of events removed.
    """
    files = sorted(Path(tb_dir).rglob("events.out.tfevents.*")) if Path(tb_dir).is_dir() else []
    if not files:
        return 0
    from tensorboard.backend.event_processing.event_file_loader import RawEventFileLoader
    from tensorboard.compat.proto.event_pb2 import Event
    from tensorboard.summary.writer.record_writer import RecordWriter

    dropped = 0
    for path in files:
        if not path.is_file() or path.is_symlink():
            continue
        records, keep = [], []
        for r in RawEventFileLoader(str(path)).Load():
            try:
                event_step = Event.FromString(r).step
            except Exception:  # protobuf's DecodeError: a damaged record, cut with the rest
                break
            records.append(r)
            if event_step <= step:
                keep.append(r)
        cut_tail = path.stat().st_size != sum(len(r) + 16 for r in records)  # 16: framing
        if len(keep) == len(records) and not cut_tail:
            continue
        dropped += len(records) - len(keep)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            writer = RecordWriter(fh)
            for r in keep:
                writer.write(r)
    return dropped


class TrainingCallback(BaseCallback):
    """The run's Stable-Baselines3 callback: calls ``session.boundary()`` before every rollout;
    freezes the actor while the critic warms up; logs rollouts; gives PPO's update
    ``ppo.update_threads`` torch threads and the rollouts one.

    Args:
        session: the run's :class:`rl.train.session.TrainingSession`.
        total_steps: the run's length (for the progress bar).
        progress: show a progress bar.
    """

    def __init__(self, session, total_steps: int, progress: bool = True) -> None:
        super().__init__()
        self.session = session
        self.total_steps = total_steps
        self.progress = progress
        self._bar = None
        self._terms: dict[str, list[float]] = defaultdict(list)
        self._episodes: list[tuple[bool, bool]] = []
        self._rollout_t0 = time.perf_counter()

    def _actor_params(self):
        pol = self.model.policy
        if not hasattr(pol, "action_net"):  # SAC: no shared actor-critic module
            return []
        return [
            *pol.mlp_extractor.policy_net.parameters(),
            *pol.action_net.parameters(),
            pol.log_std,
        ]

    def _on_training_start(self) -> None:
        if self.progress:
            self._bar = tqdm(
                total=self.total_steps,
                initial=self.model.num_timesteps,
                unit="step",
                desc="train",
                smoothing=0.05,
            )

    def _update_threads(self) -> int:
        cfg = getattr(self.session, "cfg", None)
        return cfg.ppo.update_threads if cfg is not None and cfg.algo == "ppo" else 1

    def _on_rollout_start(self) -> None:
        import torch

        torch.set_num_threads(1)
        self.session.boundary()
        self._rollout_t0 = time.perf_counter()

    def _on_rollout_end(self) -> None:
        # the rollout alone (env steps and the policy's actions; not the update, not the
        # boundary's checkpoints and evaluations), in the run's TensorBoard log
        self.logger.record("time/rollout_s", time.perf_counter() - self._rollout_t0)
        if self._update_threads() > 1:
            import torch

            torch.set_num_threads(self._update_threads())
        freeze = self.model.num_timesteps < self.session.critic_warmup_until
        for p in self._actor_params():
            p.requires_grad_(not freeze)
        self._log_rollout()

    def _on_step(self) -> bool:
        for info, done in zip(self.locals["infos"], self.locals["dones"], strict=True):
            for k, v in info.get("reward_terms", {}).items():
                self._terms[k].append(v)
            if done:
                self._episodes.append(
                    (bool(info.get("success_paper")), bool(info.get("success_strict")))
                )
        if self._bar is not None:
            self._bar.update(self.model.num_timesteps - self._bar.n)
            if self._episodes:
                recent = np.array(self._episodes[-100:], dtype=float)
                self._bar.set_postfix(success=f"{recent[:, 0].mean():.2f}", refresh=False)
        return True

    def _on_training_end(self) -> None:
        self.close()

    def close(self) -> None:
        """Close the progress bar (also when training stops on an exception)."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def _log_rollout(self) -> None:
        for k, v in self._terms.items():
            self.logger.record(f"charts/reward_{k}", float(np.mean(v)))
        if self._episodes:
            arr = np.array(self._episodes[-100:], dtype=float)
            self.logger.record("charts/success_rate_paper", float(arr[:, 0].mean()))
            self.logger.record("charts/success_rate_strict", float(arr[:, 1].mean()))
        self._terms.clear()
