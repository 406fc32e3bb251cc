"""Training callback: checkpoints, periodic evaluation, reward-term and success logging."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback


class TrainingCallback(BaseCallback):
    """Checkpoint every ``cfg.checkpoint_every`` steps, evaluate every ``cfg.eval_every``,
    and log ``charts/`` (episode success rates, reward terms) to TensorBoard."""

    def __init__(self, cfg, run_dir: Path, vecnorm, save_checkpoint, progress: bool = True) -> None:
        super().__init__()
        self.progress = progress
        self._bar = None
        self.best: tuple[float, float, float] | None = None
        self.critic_warmup_until = 0
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.vecnorm = vecnorm
        self._save = save_checkpoint
        self._next_ckpt = None
        self._next_eval = None
        self._terms: dict[str, list[float]] = defaultdict(list)
        self._episodes: list[tuple[bool, bool]] = []

    def _actor_params(self):
        pol = self.model.policy
        if not hasattr(pol, "action_net"):  # SAC: no shared actor-critic module
            return []
        return [
            *pol.mlp_extractor.policy_net.parameters(),
            *pol.action_net.parameters(),
            pol.log_std,
        ]

    def _on_rollout_end(self) -> None:
        freeze = self.model.num_timesteps < self.critic_warmup_until
        for p in self._actor_params():
            p.requires_grad_(not freeze)
        self._log_rollout()

    def _on_training_start(self) -> None:
        n = self.model.num_timesteps
        if self.progress:
            from tqdm import tqdm

            self._bar = tqdm(
                total=self.cfg.total_steps, initial=n, unit="step", desc="train", smoothing=0.05
            )
        self._next_ckpt = n + self.cfg.checkpoint_every
        self._next_eval = n + self.cfg.eval_every if self.cfg.eval_every else None
        if self.cfg.eval_every and self.critic_warmup_until:
            self._evaluate(n)  # the warm-started policy competes for best/ too

    def _on_step(self) -> bool:
        for info, done in zip(self.locals["infos"], self.locals["dones"], strict=True):
            for k, v in info.get("reward_terms", {}).items():
                self._terms[k].append(v)
            if done:
                self._episodes.append(
                    (bool(info.get("success_paper")), bool(info.get("success_strict")))
                )
        n = self.model.num_timesteps
        if self._bar is not None:
            self._bar.update(n - self._bar.n)
            if self._episodes:
                recent = np.array(self._episodes[-100:], dtype=float)
                self._bar.set_postfix(success=f"{recent[:, 0].mean():.2f}", refresh=False)
        if n >= self._next_ckpt:
            self._save(self.model, self.vecnorm, self.run_dir, n)
            self._next_ckpt += self.cfg.checkpoint_every
        if self._next_eval is not None and n >= self._next_eval:
            self._evaluate(n)
            self._next_eval += self.cfg.eval_every
        return True

    def _on_training_end(self) -> None:
        if self._bar is not None:
            self._bar.close()

    def _log_rollout(self) -> None:
        for k, v in self._terms.items():
            self.logger.record(f"charts/reward_{k}", float(np.mean(v)))
        if self._episodes:
            arr = np.array(self._episodes[-100:], dtype=float)
            self.logger.record("charts/success_rate_paper", float(arr[:, 0].mean()))
            self.logger.record("charts/success_rate_strict", float(arr[:, 1].mean()))
        self._terms.clear()

    def _evaluate(self, step: int) -> None:
        from rl.evaluate import run_episodes

        summary = run_episodes(
            self.model,
            self.cfg.env,
            self.cfg.eval_episodes,
            seed=10_000,
            vecnorm=self.vecnorm,
            record=False,
        ).summary
        for k in ("success_rate", "success_rate_strict", "mean_time_to_dock_s"):
            if summary.get(k) is not None:
                self.logger.record(f"eval/{k}", summary[k])
        # the same seeded episodes each time; ranked by the success that ends the episode, then
        # the other one, then the return (faster, smoother docking)
        paper, strict = summary["success_rate"], summary["success_rate_strict"]
        first, second = (
            (strict, paper) if self.cfg.env.terminate_on == "strict" else (paper, strict)
        )
        score = (first, second, summary["mean_return"])
        if self.best is None or score > self.best:
            self.best = score
            best = self.run_dir / "best"
            best.mkdir(exist_ok=True)
            from rl.train import save_model, save_vecnormalize

            save_model(self.model, best / "policy.zip")
            if self.vecnorm is not None:
                save_vecnormalize(self.vecnorm, best / "vecnormalize.pkl")
            summary = {**summary, "best": True}
        history = self.run_dir / "eval_history.jsonl"
        with history.open("a") as fh:
            fh.write(json.dumps({"step": step, **summary}) + "\n")
        from rl.report import plot_eval_history

        plot_eval_history(history, self.run_dir / "eval_history.png")
