"""``rl train``: PPO (or SAC) on the docking env, in a self-describing, resumable run folder.

Run folder layout::

    RUN/
      config.toml, provenance.json   resolved TrainConfig (env included), commit, versions
      checkpoints/step_<N>.zip       policy + optimiser (atomic), plus vecnormalize_<N>.pkl
      tb/                            TensorBoard scalars (charts/, losses/, eval/)
      eval_history.jsonl             periodic deterministic evaluation (success rates)
      policy.zip, vecnormalize.pkl   the final (or best) policy

``--resume`` continues from the newest checkpoint with the step counter, optimiser state and
observation-normalisation statistics, so nothing is lost.
"""

from __future__ import annotations

import io
import os
import pickle
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from dockcore.errors import DockError
from dockcore.io import atomic_write_bytes, atomic_write_json
from dockcore.provenance import write_provenance
from rl.config import EnvConfig
from rl.imitation import ImitationConfig


@dataclass(frozen=True)
class PPOConfig:
    """PPO hyperparameters (paper appendix table: lr 5e-4, n_steps 512, batch 1024, gamma 0.99,
    ent_coef 0.01, clip 0.2).

    Attributes:
        learning_rate: Adam step size (-); ``learning_rate_final`` < it gives a linear decay.
        learning_rate_final: final learning rate of a linear schedule (None: constant).
        n_steps: rollout length per environment (steps).
        batch_size: minibatch size (transitions).
        n_epochs: passes over each rollout (-).
        gamma: discount (-).
        gae_lambda: GAE lambda (-).
        ent_coef: entropy bonus (-).
        clip_range: PPO clip (-).
        net_arch: hidden layer sizes of policy and value networks.
    """

    learning_rate: float = 5e-4
    learning_rate_final: float | None = None
    n_steps: int = 512
    batch_size: int = 1024
    n_epochs: int = 10
    gamma: float = 0.99
    gae_lambda: float = 0.95
    ent_coef: float = 0.01
    clip_range: float = 0.2
    net_arch: tuple[int, ...] = (64, 64)


@dataclass(frozen=True)
class SACConfig:
    """SAC hyperparameters (paper: tau 0.005, buffer 500k, learning_starts 1000, lr 5e-4).

    Attributes:
        learning_rate: Adam step size (-).
        buffer_size: replay buffer (transitions).
        batch_size: minibatch (transitions).
        tau: target smoothing (-).
        gamma: discount (-).
        learning_starts: random steps before learning (steps).
        train_freq: env steps between updates (steps).
        gradient_steps: updates per train step (-).
        net_arch: hidden layer sizes.
    """

    learning_rate: float = 5e-4
    buffer_size: int = 500_000
    batch_size: int = 1024
    tau: float = 0.005
    gamma: float = 0.99
    learning_starts: int = 1000
    train_freq: int = 1
    gradient_steps: int = 1
    net_arch: tuple[int, ...] = (256, 256)


@dataclass(frozen=True)
class TrainConfig:
    """A training run.

    Attributes:
        algo: "ppo" or "sac".
        total_steps: environment steps to train for, over all environments.
        n_envs: parallel environments (subprocesses when > 1).
        seed: base seed (env i gets seed + i).
        checkpoint_every: steps between checkpoints.
        eval_every: steps between evaluations (0: off).
        eval_episodes: episodes per evaluation.
        normalize_obs: running observation normalisation (VecNormalize).
        normalize_reward: running reward scaling (VecNormalize).
        env: the environment.
        ppo: PPO hyperparameters.
        sac: SAC hyperparameters.
        imitation: teacher-guided warm start before RL (``teacher = "none"``: pure RL).
    """

    algo: Literal["ppo", "sac"] = "ppo"
    total_steps: int = 2_000_000
    n_envs: int = 2
    seed: int = 0
    checkpoint_every: int = 50_000
    eval_every: int = 100_000
    eval_episodes: int = 20
    normalize_obs: bool = True
    normalize_reward: bool = True
    env: EnvConfig = field(default_factory=EnvConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    sac: SACConfig = field(default_factory=SACConfig)
    imitation: ImitationConfig = field(default_factory=lambda: ImitationConfig(teacher="none"))

    def validate(self) -> None:
        if self.total_steps <= 0 or self.n_envs < 1:
            raise ValueError("total_steps must be > 0 and n_envs >= 1")


def _make_env_fn(env_cfg: EnvConfig, seed: int):
    def make():
        from stable_baselines3.common.monitor import Monitor

        from rl.env import DockingEnv

        env = Monitor(DockingEnv(env_cfg), info_keywords=("success_paper", "success_strict"))
        env.reset(seed=seed)
        return env

    return make


def make_vec_env(env_cfg: EnvConfig, n_envs: int, seed: int):
    """``n_envs`` docking envs, in subprocesses when more than one."""
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    fns = [_make_env_fn(env_cfg, seed + i) for i in range(n_envs)]
    if n_envs == 1:
        return DummyVecEnv(fns)
    return SubprocVecEnv(fns, start_method="fork" if os.name == "posix" else "spawn")


_CKPT = re.compile(r"step_(\d+)\.zip$")


def latest_checkpoint(run_dir: Path) -> tuple[Path, int] | None:
    """The newest ``checkpoints/step_N.zip`` and N, or None."""
    found = []
    for p in (run_dir / "checkpoints").glob("step_*.zip"):
        m = _CKPT.search(p.name)
        if m:
            found.append((int(m.group(1)), p))
    if not found:
        return None
    n, p = max(found)
    return p, n


def save_checkpoint(model, vecnorm, run_dir: Path, step: int) -> Path:
    """Policy (+ optimiser) and normalisation statistics, each written atomically."""
    ck = run_dir / "checkpoints"
    ck.mkdir(parents=True, exist_ok=True)
    path = save_model(model, ck / f"step_{step}.zip")
    if vecnorm is not None:
        save_vecnormalize(vecnorm, ck / f"vecnormalize_{step}.pkl")
    return path


def save_model(model, path: Path) -> Path:
    """``model.save`` into memory, then one atomic write."""
    buf = io.BytesIO()
    model.save(buf)
    return atomic_write_bytes(path, buf.getvalue())


def save_vecnormalize(vecnorm, path: Path) -> Path:
    """Pickle the normalisation statistics atomically (VecNormalize drops its envs itself)."""
    return atomic_write_bytes(path, pickle.dumps(vecnorm))


def _lr(cfg: PPOConfig):
    if cfg.learning_rate_final is None:
        return cfg.learning_rate
    lo, hi = cfg.learning_rate_final, cfg.learning_rate
    return lambda progress_remaining: lo + (hi - lo) * progress_remaining


def build_model(cfg: TrainConfig, venv, tb_dir: Path):
    """A fresh SB3 model for ``cfg``."""
    from stable_baselines3 import PPO, SAC

    if cfg.algo == "ppo":
        p = cfg.ppo
        return PPO(
            "MlpPolicy",
            venv,
            learning_rate=_lr(p),
            n_steps=p.n_steps,
            batch_size=p.batch_size,
            n_epochs=p.n_epochs,
            gamma=p.gamma,
            gae_lambda=p.gae_lambda,
            ent_coef=p.ent_coef,
            clip_range=p.clip_range,
            policy_kwargs={"net_arch": list(p.net_arch)},
            tensorboard_log=str(tb_dir),
            seed=cfg.seed,
            device="cpu",
            verbose=0,
        )
    s = cfg.sac
    return SAC(
        "MlpPolicy",
        venv,
        learning_rate=s.learning_rate,
        buffer_size=s.buffer_size,
        batch_size=s.batch_size,
        tau=s.tau,
        gamma=s.gamma,
        learning_starts=s.learning_starts,
        train_freq=s.train_freq,
        gradient_steps=s.gradient_steps,
        policy_kwargs={"net_arch": list(s.net_arch)},
        tensorboard_log=str(tb_dir),
        seed=cfg.seed,
        device="cpu",
        verbose=0,
    )


def train(
    cfg: TrainConfig,
    run_dir: str | os.PathLike[str],
    resume: bool = False,
    progress: bool = True,
    init_policy: str | None = None,
) -> Path:
    """Train (or resume) into ``run_dir``; returns the final policy path.

    Args:
        cfg: the run's configuration (on resume, must match the folder's).
        run_dir: the run folder.
        resume: continue from the newest checkpoint in ``run_dir``.
        progress: show a progress bar.
        init_policy: start from this policy's weights (fine-tuning, e.g. error-model -> camera).
    """
    import torch
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.vec_env import VecNormalize

    from rl.callbacks import TrainingCallback

    torch.set_num_threads(1)
    run = Path(run_dir)
    found = latest_checkpoint(run)
    if resume and found is None:
        raise DockError(f"nothing to resume in {run}: no checkpoints/step_*.zip")
    if not resume and found is not None:
        raise DockError(f"{run} already holds a run: use --resume or another --out")
    ckpt = found if resume else None
    run.mkdir(parents=True, exist_ok=True)
    write_provenance(run, {"train": cfg}, extra={"resumed_from": str(ckpt[0]) if ckpt else None})

    venv = make_vec_env(cfg.env, cfg.n_envs, cfg.seed)
    vecnorm = None
    algo_cls = PPO if cfg.algo == "ppo" else SAC
    gamma = cfg.ppo.gamma if cfg.algo == "ppo" else cfg.sac.gamma
    if ckpt is not None:
        path, step = ckpt
        vn_path = run / "checkpoints" / f"vecnormalize_{step}.pkl"
        if vn_path.exists():
            venv = vecnorm = VecNormalize.load(str(vn_path), venv)
        model = algo_cls.load(str(path), env=venv, device="cpu")
        model.tensorboard_log = str(run / "tb")
    else:
        if cfg.normalize_obs or cfg.normalize_reward:
            venv = vecnorm = VecNormalize(
                venv,
                norm_obs=cfg.normalize_obs,
                norm_reward=cfg.normalize_reward,
                gamma=gamma,
            )
        model = build_model(cfg, venv, run / "tb")
        if cfg.imitation.teacher != "none" and not init_policy:
            from rl.imitation import warm_start

            hist = warm_start(
                model, vecnorm, cfg.env, cfg.imitation, cfg.seed, gamma, progress=progress
            )
            atomic_write_json(run / "imitation.json", hist)
            if vecnorm is not None:
                # the imitated policy was fitted on these statistics: freeze them, or PPO's
                # rollouts would shift the network's inputs under it
                vecnorm.training = False
            save_checkpoint(model, vecnorm, run, 0)
        if init_policy:
            from rl.export import load_policy

            src, vn_src = load_policy(init_policy)
            model.policy.load_state_dict(src.policy.state_dict())
            if vecnorm is not None and vn_src is not None:
                vecnorm.obs_rms, vecnorm.ret_rms = vn_src.obs_rms, vn_src.ret_rms
    remaining = cfg.total_steps - model.num_timesteps
    if remaining > 0:
        cb = TrainingCallback(cfg, run, vecnorm, save_checkpoint, progress=progress)
        if cfg.imitation.teacher != "none" and ckpt is None and not init_policy:
            cb.critic_warmup_until = cfg.imitation.critic_warmup_steps
        model.learn(
            total_timesteps=remaining,
            callback=cb,
            reset_num_timesteps=ckpt is None,
            tb_log_name="tb",
        )
        save_checkpoint(model, vecnorm, run, model.num_timesteps)
    final = save_model(model, run / "policy.zip")
    if vecnorm is not None:
        save_vecnormalize(vecnorm, run / "vecnormalize.pkl")
    venv.close()
    atomic_write_json(run / "DONE", {"steps": int(model.num_timesteps)})
    return final
