"""``rl train``: PPO (or SAC) on the docking env, in a self-describing, resumable run folder.

Run folder layout::

    RUN/
      config.toml, provenance.json   resolved TrainConfig (env included), commit, versions
      checkpoints/step_<N>/          checkpoint units (rl.train.checkpoint): model, normalisation,
                                     best/, schedule, evaluation state, RNG states, manifest
      tb/                            TensorBoard scalars (charts/, losses/, eval/)
      eval_history.jsonl, .png       periodic deterministic evaluation (success rates)
      best/                          the best evaluated policy (model.json, weights.npz)
      imitation.json                 the DAgger warm start's history (when there is one)
      model.json, weights.npz        the final policy (rl.policy.policy_format); DONE is written
      last resume_log.jsonl               one line per resume (step, command, commit, config change)

``--resume`` continues from the newest complete checkpoint (falling back past damaged ones)
and gives a run identical to an uninterrupted one (:mod:`rl.train.session`).
"""

from __future__ import annotations

import datetime
import gc
import hashlib
import io
import json
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

from uwdock.dockcore.config import changed_keys, dumps_toml, load_config, to_dict, validated
from uwdock.dockcore.domains import Count, Fraction, Interval, Seed, check, split_annotated
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_json, atomic_write_text
from uwdock.dockcore.outdir import claim_output_dir
from uwdock.dockcore.pool import PoolConfig, preflight
from uwdock.dockcore.provenance import git_commit, write_provenance
from uwdock.rl.env.batch_parts import BATCH_SOURCES
from uwdock.rl.env.config import EnvConfig, check_env_files
from uwdock.rl.env.curriculum import CurriculumConfig
from uwdock.rl.env.observation import actor_observation_size, observation_size
from uwdock.rl.policy.env_settings import policy_training_env
from uwdock.rl.policy.policy_format import require_finite_policy, write_policy
from uwdock.rl.policy.policy_io import check_obs_dim, load_policy
from uwdock.rl.train.batch_workers import BatchWorkers
from uwdock.rl.train.checkpoint import (
    Unit,
    has_legacy_checkpoints,
    latest_unit,
    list_units,
    load_model,
    normaliser_for,
    read_training,
    restore_training,
)
from uwdock.rl.train.imitation import ImitationConfig, warm_start
from uwdock.rl.train.ray_envs import RayEnvWorkers
from uwdock.rl.train.session import TrainingSession, load_vecnormalize
from uwdock.rl.train.vec_envs import EnvsPerWorker, EnvWorkers, env_groups
from uwdock.rl.train.widen import widen_obs_rms, widen_state_dict, widening_index

_LearningRate = Annotated[float, Interval(gt=0, le=1)]
_Width = Annotated[int, Interval(ge=1, le=4096)]  # units in a hidden layer


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
        log_std_init: initial log standard deviation of the Gaussian policy (-); SB3's 0 gives
            std 1, whose action changes alone cost as much as r_dist through r_smooth's
            exponential (bench/diagnose_reward.py).
        use_sde: generalised state-dependent exploration (gSDE) instead of independent noise.
        target_kl: stop an update's epochs early when the approximate KL divergence exceeds
            this (None: never).
        update_threads: torch's threads while PPO updates its networks (1 while the envs
            step). The env workers wait during the update, so their cores are free; the count
            is the config's, never the machine's, so a run trains the same weights anywhere.
    """

    learning_rate: _LearningRate = 5e-4
    learning_rate_final: _LearningRate | None = None
    n_steps: Annotated[int, Interval(ge=1, le=1_000_000)] = 512
    batch_size: Annotated[int, Interval(ge=2, le=1_000_000)] = 1024
    n_epochs: Annotated[int, Interval(ge=1, le=1000)] = 10
    gamma: Fraction = 0.99
    gae_lambda: Fraction = 0.95
    ent_coef: Annotated[float, Interval(ge=0, le=10)] = 0.01
    clip_range: Annotated[float, Interval(gt=0, le=10)] = 0.2
    net_arch: tuple[_Width, ...] = (64, 64)
    log_std_init: Annotated[float, Interval(ge=-10, le=2)] = 0.0
    use_sde: bool = False
    target_kl: Annotated[float, Interval(gt=0, le=10)] | None = None
    update_threads: Annotated[int, Interval(ge=1, le=64)] = 1


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

    learning_rate: _LearningRate = 5e-4
    buffer_size: Annotated[int, Interval(ge=1, le=100_000_000)] = 500_000
    batch_size: Annotated[int, Interval(ge=1, le=1_000_000)] = 1024
    tau: Annotated[float, Interval(gt=0, le=1)] = 0.005
    gamma: Fraction = 0.99
    learning_starts: Annotated[int, Interval(ge=0, le=10**9)] = 1000
    train_freq: Annotated[int, Interval(ge=1, le=1_000_000)] = 1
    gradient_steps: Annotated[int, Interval(ge=1, le=10_000)] = 1
    net_arch: tuple[_Width, ...] = (256, 256)


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
        select_best: which evaluation ``best/`` keeps: "success" (the success rate that ends
            the episode, then the other, then the mean return), "return" (the mean return
            alone, as SB3's ``EvalCallback`` keeps its best model): for a stage whose reward
            says what it is for, such as the gentle landing's collision penalty, or "fastest"
            (the least mean time to dock among the evaluations within one episode of the
            highest success rate: :func:`rl.train.session.replaces_best`).
        normalize_obs: running observation normalisation (VecNormalize).
        normalize_reward: running reward scaling (VecNormalize).
        env: the environment.
        ppo: PPO hyperparameters.
        sac: SAC hyperparameters.
        imitation: teacher-guided warm start before RL (``teacher = "none"``: pure RL).
        curriculum: success-tolerance and spawn-distance curriculum (:mod:`rl.env.curriculum`).
        simulator: "per-env" (one :class:`rl.env.docking_env.DockingEnv` per env, in worker
            processes) or "batched" (all ``n_envs`` stepped as arrays in this process:
            :class:`rl.env.batch_env.BatchDockingEnv`; not the camera source); the same env model.
    """

    algo: Literal["ppo", "sac"] = "ppo"
    total_steps: Count = 2_000_000
    n_envs: Annotated[int, Interval(ge=1, le=256)] = 2
    seed: Seed = 0
    checkpoint_every: Annotated[int, Interval(ge=1, le=10**9)] = 50_000
    eval_every: Annotated[int, Interval(ge=0, le=10**9)] = 100_000
    eval_episodes: Annotated[int, Interval(ge=1, le=100_000)] = 20
    select_best: Literal["success", "return", "fastest"] = "success"
    normalize_obs: bool = True
    normalize_reward: bool = True
    env: EnvConfig = field(default_factory=EnvConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    sac: SACConfig = field(default_factory=SACConfig)
    imitation: ImitationConfig = field(default_factory=lambda: ImitationConfig(teacher="none"))
    curriculum: CurriculumConfig = field(default_factory=CurriculumConfig)
    simulator: Literal["per-env", "batched"] = "per-env"

    def validate(self) -> None:
        if self.simulator == "batched" and self.env.obs_source not in BATCH_SOURCES:
            raise ValueError(
                f"simulator: 'batched' cannot run obs_source '{self.env.obs_source}' (one render "
                f"per env and step); it runs {', '.join(BATCH_SOURCES)}"
            )
        if self.algo == "ppo" and self.ppo.n_steps * self.n_envs < 2:
            raise ValueError("ppo.n_steps: n_steps x n_envs must be >= 2 (a rollout to learn from)")
        if self.algo == "sac" and self.env.obs_privileged:
            raise ValueError("env.obs_privileged: the asymmetric critic is built for PPO only")
        if self.algo == "sac" and self.sac.batch_size > self.sac.buffer_size:
            raise ValueError(
                f"sac.batch_size: {self.sac.batch_size} exceeds buffer_size {self.sac.buffer_size}"
            )


#: The domain of ``batch_workers`` (``rl train --batch-workers``).
BatchWorkerCount = Annotated[int, Interval(ge=1, le=64)]


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
        policy: Any = "MlpPolicy"
        kwargs: dict[str, Any] = {
            "net_arch": list(p.net_arch),
            "log_std_init": p.log_std_init,
            # Adam over all tensors at once: the same bits as one tensor at a time, ~30 % less
            # update time at 64-128 units. eps is SB3's own default for its policies, which it
            # sets only when no optimizer_kwargs are given.
            "optimizer_kwargs": {"eps": 1e-5, "foreach": True},
        }
        if cfg.env.obs_privileged:  # asymmetric actor-critic
            from uwdock.rl.policy.asymmetric import (
                AsymmetricPolicy,
            )  # torch and SB3 at module level

            policy = AsymmetricPolicy
            kwargs["actor_obs_dim"] = actor_observation_size(cfg.env)
        return PPO(
            policy,
            venv,
            learning_rate=_lr(p),
            n_steps=p.n_steps,
            batch_size=p.batch_size,
            n_epochs=p.n_epochs,
            gamma=p.gamma,
            gae_lambda=p.gae_lambda,
            ent_coef=p.ent_coef,
            clip_range=p.clip_range,
            use_sde=p.use_sde,
            target_kl=p.target_kl,
            policy_kwargs=kwargs,
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


def rollout_steps(cfg: TrainConfig) -> int:
    """Environment steps between two policy updates (PPO: ``n_steps`` per env; SAC:
    ``train_freq`` per env); checkpoints and evaluations fall on these boundaries."""
    per_env = cfg.ppo.n_steps if cfg.algo == "ppo" else cfg.sac.train_freq
    return per_env * cfg.n_envs


def run_config(run_dir: str | os.PathLike[str]) -> TrainConfig:
    """The ``TrainConfig`` a run folder was started with (its ``config.toml``).

    Raises:
        DockError: no ``config.toml``: not a run folder of ``rl train``.
    """
    path = Path(run_dir) / "config.toml"
    if not path.is_file():
        raise DockError(
            f"{run_dir} has no config.toml: not a run folder of `rl train` (nothing to resume)"
        )
    return load_config(TrainConfig, path, section="train")


def _check_config(cfg: TrainConfig, run: Path, allow_change: bool) -> list[str]:
    changed = changed_keys(to_dict(run_config(run)), to_dict(cfg))
    if changed and not allow_change:
        shown = ", ".join(changed[:5]) + (" ..." if len(changed) > 5 else "")
        raise DockError(
            f"the config differs from the run's config.toml in {shown}: resume with the run's "
            "own config (drop --config and the flags), or pass --allow-config-change"
        )
    return changed


def _note_rollout_rounding(cfg: TrainConfig, note: Callable[[str], None]) -> None:
    per = rollout_steps(cfg)
    total = -(-cfg.total_steps // per) * per
    if total != cfg.total_steps:
        note(
            f"training {total:,} steps: {cfg.algo.upper()} steps in rollouts of {per:,} "
            f"({'n_steps' if cfg.algo == 'ppo' else 'train_freq'} x n_envs), so total_steps "
            f"{cfg.total_steps:,} is rounded up"
        )


def _stderr_note(msg: str) -> None:
    print(f"note: {msg}", file=sys.stderr, flush=True)


def train(
    cfg: TrainConfig,
    run_dir: str | os.PathLike[str],
    resume: bool = False,
    progress: bool = True,
    init_policy: str | None = None,
    allow_config_change: bool = False,
    note: Callable[[str], None] = _stderr_note,
    backend: str = "local",
    ray_address: str | None = None,
    envs_per_worker: int = 1,
    batch_workers: int = 1,
    trust_pickle: bool = False,
) -> Path:
    """Train (or resume) into ``run_dir``; returns the final policy path.

    A run killed at any moment (SIGINT, SIGTERM, SIGKILL, a failed worker) and resumed gives
    the same checkpoints, evaluation history and ``best/`` as an uninterrupted run
    (:mod:`rl.train.session`).

    Args:
        cfg: the run's configuration; on resume it must equal the run's ``config.toml``
            unless ``allow_config_change`` (the change is recorded in ``resume_log.jsonl``).
        run_dir: the run folder.
        resume: continue from the newest complete checkpoint in ``run_dir`` (from the start
            when the run stopped before its first checkpoint).
        progress: show a progress bar.
        init_policy: start from this policy's weights (fine-tuning; not with ``resume``).
        allow_config_change: resume with a config that differs from the run's.
        note: where one-line notes go (stderr by default).
        backend: where the ``cfg.n_envs`` env workers run: ``"local"`` processes or ``"ray"``
            actors (:mod:`rl.train.ray_envs`; the same rollouts). Not part of the run's config: a
            run may be resumed on either.
        ray_address: the Ray cluster (None: a local Ray instance with a CPU per worker).
        envs_per_worker: envs each worker process or actor holds, sharing its renderer
            (:mod:`rl.train.vec_envs`; the same rollouts). Not part of the run's config either.
        batch_workers: with ``simulator = "batched"``, the processes the batch is split over
            (1: the trainer's own; the same rollouts). Not part of the run's config.
        trust_pickle: resume from checkpoints of format version 1 (SB3's zip and pickles,
            which run any code they hold): only for a run folder that is the user's own.

    Raises:
        DockError: a bad config, a run folder that does not fit the request, a damaged or
            non-finite policy, a failed environment worker.
    """
    cfg = validated(cfg)
    pool, init = _check_request(
        cfg, resume, init_policy, backend, ray_address, envs_per_worker, batch_workers
    )
    with claim_output_dir(run_dir, "rl train") as run:
        _check_run_folder(run, resume)
        changed = _check_config(cfg, run, allow_config_change) if resume else []
        if resume and _is_complete(run, cfg, note):
            return run
        if resume and init is None and not list_units(run / "checkpoints"):
            init = _recorded_init(run, cfg)  # killed before its first checkpoint
        unit = _prepare_run(
            cfg, run, resume, changed, note, trust_pickle, _init_record(init_policy)
        )
        return _run(cfg, run, unit, init, progress, note, pool, envs_per_worker, batch_workers)


def _check_request(
    cfg: TrainConfig,
    resume: bool,
    init_policy: str | None,
    backend: str,
    ray_address: str | None,
    envs_per_worker: int,
    batch_workers: int,
) -> tuple[PoolConfig, Any]:
    """Refuse a bad request before the run folder is claimed; the env pool (answering) and the
    ``init_policy`` loaded (None without one)."""
    why = check(envs_per_worker, *split_annotated(EnvsPerWorker), "envs_per_worker")
    if why is not None:
        raise DockError(why)
    workers = len(env_groups(cfg.n_envs, envs_per_worker))
    pool = PoolConfig(backend, workers, ray_address)
    try:
        pool.validate()
    except ValueError as exc:
        raise DockError(str(exc)) from None
    preflight(pool)  # before the run folder is claimed
    why = check(batch_workers, *split_annotated(BatchWorkerCount), "batch_workers")
    if why is not None:
        raise DockError(why)
    if resume and init_policy:
        raise DockError("--init-policy starts a new run; it cannot be combined with --resume")
    check_env_files(cfg.env)
    return pool, _load_init(init_policy, cfg) if init_policy else None


def _load_init(init_policy: str, cfg: TrainConfig) -> tuple[Any, Any, Any]:
    """The policy a run starts from: (model, normalisation, where its observation entries sit
    in the run's when the run's widens it, else None)."""
    model, vn = load_policy(init_policy)  # refuses damaged or non-finite policies
    env_dim = observation_size(cfg.env)
    policy_dim = int(model.observation_space.shape[0])
    index, why = _widening(init_policy, cfg.env) if policy_dim != env_dim else (None, "")
    if index is None or index.size != policy_dim:
        check_obs_dim(policy_dim, env_dim, init_policy, why)
    return model, vn, index


def _recorded_init(run: Path, cfg: TrainConfig) -> tuple[Any, Any, Any] | None:
    """For a run resumed before its first checkpoint: the policy it started from (its
    provenance's ``init_policy``), checked to be the same files; None if it started from
    scratch."""
    try:
        prov = json.loads((run / "provenance.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    record = prov.get("init_policy") if isinstance(prov, dict) else None
    if not isinstance(record, dict) or not isinstance(record.get("path"), str):
        return None
    now = _init_record(record["path"]) or {}
    if any(now.get(k) != v for k, v in record.items()):
        raise DockError(
            f"{run} started from the policy {record['path']}, which is gone or has changed "
            "since: start the run again (another --out) with the --init-policy you mean"
        )
    return _load_init(record["path"], cfg)


def _widening(init_policy: str, env: EnvConfig) -> tuple[Any, str]:
    """Where the init policy's observation entries sit in ``env``'s when ``env`` only adds
    inputs it lacks (:mod:`rl.train.widen`), or None and why not: its layout is unknown (no run
    config) or not a widening of ``env``'s (the dimension check then refuses it)."""
    trained = policy_training_env(init_policy)
    if trained is None:
        return None, "it has no run config to widen it from"
    try:
        return widening_index(trained.cfg, env), ""
    except ValueError as exc:
        return None, f"not a widening of it: {exc}"


def _check_run_folder(run: Path, resume: bool) -> None:
    """Refuse a new run over an existing one, and a resume of checkpoints it cannot read."""
    ckpts = run / "checkpoints"
    if not resume and ((run / "config.toml").exists() or list_units(ckpts)):
        raise DockError(f"{run} already holds a run: use --resume or another --out")
    if resume and has_legacy_checkpoints(ckpts) and not list_units(ckpts):
        raise DockError(
            f"{run} holds checkpoints of an older version (step_N.zip) that cannot be "
            "resumed exactly: start a new run (--init-policy RUN keeps its weights, after `rl "
            "convert-policy RUN --trust-pickle`)"
        )


def _is_complete(run: Path, cfg: TrainConfig, note: Callable[[str], None]) -> bool:
    """Whether the run's ``DONE`` already counts ``cfg.total_steps`` (noted: nothing to do)."""
    done = run / "DONE"
    if done.is_file():
        steps = int(json.loads(done.read_text(encoding="utf-8")).get("steps", 0))
        if steps >= cfg.total_steps:
            note(f"{run} is complete ({steps:,} steps): nothing to resume")
            return True
    return False


def _init_record(init_policy: str | None) -> dict[str, str] | None:
    """What a run started from (its provenance's ``init_policy``): the policy folder, absolute,
    and the SHA-256 of its files."""
    if not init_policy:
        return None
    p = Path(init_policy).expanduser().resolve()
    folder = p if p.is_dir() else p.parent
    record = {"path": str(folder)}
    for name in ("model.json", "weights.npz"):
        try:
            record[f"{name.split('.')[0]}_sha256"] = hashlib.sha256(
                (folder / name).read_bytes()
            ).hexdigest()
        except OSError:
            pass
    return record


def _prepare_run(
    cfg: TrainConfig,
    run: Path,
    resume: bool,
    changed: list[str],
    note: Callable[[str], None],
    trust_pickle: bool = False,
    init: dict[str, str] | None = None,
) -> Unit | None:
    """The checkpoint unit to start from (None: the beginning), with the resume logged or the
    provenance written (``init``: the policy it starts from, :func:`_init_record`), and
    ``DONE`` removed."""
    ckpts = run / "checkpoints"
    unit = latest_unit(ckpts, note) if resume else None
    if unit is not None and "model.zip" in unit.files:
        if not trust_pickle:
            raise DockError(
                f"checkpoint {unit.path.name} of {run} is of an older version (SB3's model.zip "
                "and pickles, which can run code when loaded): resume with --trust-pickle if "
                "the run folder is your own"
            )
        note(f"--trust-pickle: reading the pickles of checkpoint {unit.path.name}")
    if resume and unit is None:
        note(f"no complete checkpoint in {run}: starting the run again from the beginning")
    if resume:
        _log_resume(run, unit, changed, cfg)
    else:
        write_provenance(run, {"train": cfg}, extra={"init_policy": init} if init else None)
    (run / "DONE").unlink(missing_ok=True)
    _note_rollout_rounding(cfg, note)
    return unit


def _log_resume(run: Path, unit, changed: list[str], cfg: TrainConfig) -> None:
    record = {
        "resumed_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "from_step": unit.step if unit is not None else None,
        "git": git_commit(),
        "config_changed": changed,
    }
    log = run / "resume_log.jsonl"
    old = log.read_text(encoding="utf-8") if log.is_file() else ""
    atomic_write_text(log, old + json.dumps(record) + "\n")
    if changed:
        atomic_write_text(run / "config.toml", dumps_toml({"train": cfg}))


def _run(
    cfg: TrainConfig,
    run: Path,
    unit,
    init,
    progress: bool,
    note,
    pool: PoolConfig,
    per_worker: int,
    batch_workers: int = 1,
) -> Path:
    """Train ``run`` from ``unit`` (None: the beginning) in env workers of ``pool``; returns
    the run folder (its final policy, then ``DONE``, written)."""
    import torch

    torch.set_num_threads(1)
    from uwdock.rl.train.callbacks import drop_tensorboard_events_after  # SB3 at module level

    # a resumed run logs again from its checkpoint: what the killed run logged later goes
    drop_tensorboard_events_after(run / "tb", unit.step if unit is not None else 0)
    workers = _env_workers(cfg, pool, per_worker, batch_workers)
    # what is built by now (the libraries, the envs) and before learning (the model) lives as
    # long as the run: out of the cyclic collector's scans, whose full passes over it cost
    # 0.1-0.5 s each, and out of the one at exit. Reference counting still frees it.
    gc.freeze()
    session = None
    try:
        venv = workers.venv
        if unit is not None:
            model, vecnorm = _restored_model(cfg, run, unit, venv)
            session = TrainingSession(cfg, run, model, vecnorm, note)
            session.restore(unit)
        else:
            model, vecnorm, warm = _new_model(cfg, run, init, venv, progress, note)
            session = TrainingSession(cfg, run, model, vecnorm, note)
            session.start(warm_started=warm)
        gc.freeze()
        if model.num_timesteps < cfg.total_steps:
            _learn(model, session, cfg.total_steps, unit is None, progress)
        return _write_final(run, model, vecnorm, session)
    except (EOFError, ConnectionError) as exc:  # a worker died (BrokenPipe included)
        workers.raise_worker_error(exc)
        raise  # unreachable: raise_worker_error raises
    except KeyboardInterrupt:
        last = session.last_checkpoint if session is not None else None
        where = f"step {last:,}" if last is not None else "the beginning"
        note(f"interrupted: `rl train --out {run} --resume` goes on from {where}")
        workers.close(force=True)
        raise
    finally:
        workers.close()


def _env_workers(cfg: TrainConfig, pool: PoolConfig, per_worker: int, batch_workers: int) -> Any:
    """The env workers ``cfg.simulator`` and ``pool`` ask for (their ``venv`` steps the envs)."""
    if cfg.simulator == "batched":
        if pool.backend == "ray":
            raise DockError("simulator 'batched' runs in this process: use --backend local")
        return BatchWorkers(cfg.env, cfg.n_envs, cfg.seed, batch_workers)
    if pool.backend == "ray":
        return RayEnvWorkers(cfg.env, cfg.n_envs, cfg.seed, pool.ray_address, per_worker)
    return EnvWorkers(cfg.env, cfg.n_envs, cfg.seed, per_worker)


def _restored_model(cfg: TrainConfig, run: Path, unit: Unit, venv) -> tuple[Any, Any]:
    """The model and normalisation (None without one) of checkpoint ``unit`` on ``venv``: the
    network and hyperparameters built from ``cfg``, the training state from the unit
    (:mod:`rl.train.checkpoint`; a version-1 unit through SB3's loader, trusted by the caller)."""
    from stable_baselines3 import PPO, SAC

    if "model.zip" in unit.files:  # version 1
        vecnorm = None
        if "vecnormalize.pkl" in unit.files:
            venv = vecnorm = load_vecnormalize(unit.files["vecnormalize.pkl"], venv)
        model = load_model(PPO if cfg.algo == "ppo" else SAC, unit.files["model.zip"], venv)
        model.tensorboard_log = str(run / "tb")
        if "replay_buffer.pkl" in unit.files:
            model.load_replay_buffer(io.BytesIO(unit.files["replay_buffer.pkl"]))
        return model, vecnorm
    meta, arrays = read_training(unit.files)
    vecnorm = None
    if meta["normalization"] is not None:
        venv = vecnorm = normaliser_for(venv, meta["normalization"], arrays)
    model = build_model(cfg, venv, run / "tb")
    restore_training(model, meta, arrays)
    return model, vecnorm


def _new_model(
    cfg: TrainConfig,
    run: Path,
    init,
    venv,
    progress: bool,
    note: Callable[[str], None] = _stderr_note,
) -> tuple[Any, Any, bool]:
    """A new run's model and normalisation (None without one), warm-started by imitation or
    from ``init``'s weights; and whether it was warm-started."""
    from stable_baselines3.common.vec_env import VecNormalize

    gamma = cfg.ppo.gamma if cfg.algo == "ppo" else cfg.sac.gamma
    # the batched simulator split over processes splits the warm start's batch too
    split = venv if hasattr(venv, "split_batch") else None
    vecnorm = None
    if cfg.normalize_obs or cfg.normalize_reward:
        venv = vecnorm = VecNormalize(
            venv, norm_obs=cfg.normalize_obs, norm_reward=cfg.normalize_reward, gamma=gamma
        )
    model = build_model(cfg, venv, run / "tb")
    warm = cfg.imitation.teacher != "none" and init is None
    if warm:
        hist = warm_start(
            model, vecnorm, cfg.env, cfg.imitation, cfg.seed, gamma, progress=progress,
            batched=cfg.simulator == "batched",
            threads=cfg.ppo.update_threads if cfg.algo == "ppo" else 1,
            workers=split,
        )  # fmt: skip
        atomic_write_json(run / "imitation.json", hist)
        if vecnorm is not None:
            # the imitated policy was fitted on these statistics: freeze them, or PPO's
            # rollouts would shift the network's inputs under it
            vecnorm.training = False
    if init is not None:
        src, vn_src, index = init
        if index is None:
            model.policy.load_state_dict(src.policy.state_dict())
        else:  # the run's observation adds inputs the init policy lacks (rl.train.widen): at zero
            old_dim, new_dim = index.size, observation_size(cfg.env)
            model.policy.load_state_dict(
                widen_state_dict(
                    src.policy.state_dict(), model.policy.state_dict(), index, old_dim, new_dim
                )
            )
            note(f"--init-policy: widened from {old_dim} to {new_dim} observation values")
        if vecnorm is not None and vn_src is not None:
            obs_rms = (
                vn_src.obs_rms if index is None else widen_obs_rms(vn_src.obs_rms, index, new_dim)
            )
            vecnorm.obs_rms, vecnorm.ret_rms = obs_rms, vn_src.ret_rms
    return model, vecnorm, warm


def _learn(model, session: TrainingSession, total_steps: int, fresh: bool, progress: bool) -> None:
    """Train ``model`` up to ``total_steps`` (``fresh``: its step count starts at 0)."""
    from uwdock.rl.train.callbacks import TrainingCallback  # SB3 at module level

    cb = TrainingCallback(session, total_steps, progress=progress)
    try:
        model.learn(
            total_timesteps=total_steps - model.num_timesteps,
            callback=cb,
            reset_num_timesteps=fresh,
            tb_log_name="tb",
        )
    finally:
        cb.close()


def _write_final(run: Path, model, vecnorm, session: TrainingSession) -> Path:
    """The last checkpoint, then the final policy (``model.json`` + ``weights.npz``,
    :mod:`rl.policy.policy_format`) and ``DONE`` (last); the run folder."""
    session.boundary(final=True)
    session.plot_history()
    require_finite_policy(model, "the trained policy")
    write_policy(run, model, vecnorm)
    atomic_write_json(run / "DONE", {"steps": int(model.num_timesteps)})
    return run
