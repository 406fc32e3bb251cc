"""Warm start: DAgger from the classical baseline into the PPO policy, before PPO fine-tuning.

The teacher (:class:`rl.policy.baselines.PIDController`) reads the *same* observation as the student
(the filtered estimate, whatever the observation source), so imitation needs no privileged
information. Iteration 0 rolls out the teacher; later iterations roll out the student (its mean
action) while the teacher labels every visited observation (DAgger), so the student learns to
recover from its own mistakes. The policy mean is fitted by mean-squared error, its log standard
deviation is set to ``log_std``; the value network is fitted to the normalised discounted
returns of the rollouts, so PPO starts with a critic that matches its actor.

An iteration's episodes run on the simulator the policy trains on: one at a time in a
:class:`rl.env.docking_env.DockingEnv`, or all at once in a
:class:`rl.env.batch_env.BatchDockingEnv` (episode ``k`` is env ``k``, reset with the same
seed; the per-step noise is the batch's own).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
from tqdm import tqdm

from uwdock.dockcore.domains import Interval
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.docking_env import DockingEnv
from uwdock.rl.policy.baselines import PIDController


@dataclass(frozen=True)
class ImitationConfig:
    """Teacher-guided warm start.

    Attributes:
        teacher: "pid" (the classical baseline) or "none" (pure PPO).
        iterations: DAgger iterations (the first rolls out the teacher).
        episodes_per_iteration: episodes collected per iteration.
        epochs: passes over the aggregated data per iteration.
        batch_size: minibatch size (transitions).
        learning_rate: Adam step size of the supervised fit.
        log_std: the policy's log standard deviation after the warm start (PPO explores from it).
        critic_warmup_steps: after the warm start, PPO first trains only its value function for
            this many environment steps (the actor frozen), so the first policy updates use
            advantages from a critic that matches the imitated policy.
    """

    teacher: Literal["pid", "none"] = "pid"
    iterations: Annotated[int, Interval(ge=1, le=1000)] = 4
    episodes_per_iteration: Annotated[int, Interval(ge=1, le=100_000)] = 16
    epochs: Annotated[int, Interval(ge=1, le=100_000)] = 30
    batch_size: Annotated[int, Interval(ge=1, le=1_000_000)] = 512
    learning_rate: Annotated[float, Interval(gt=0, le=1)] = 1e-3
    log_std: Annotated[float, Interval(ge=-20, le=2)] = -1.0
    critic_warmup_steps: Annotated[int, Interval(ge=0, le=10**9)] = 30_000


def _discounted(rewards: np.ndarray, gamma: float) -> np.ndarray:
    out = np.zeros_like(rewards)
    acc = 0.0
    for k in range(len(rewards) - 1, -1, -1):
        acc = rewards[k] + gamma * acc
        out[k] = acc
    return out


def warm_start(
    model,
    vecnorm,
    env_cfg: EnvConfig,
    cfg: ImitationConfig,
    seed: int,
    gamma: float,
    progress: bool = True,
    batched: bool = False,
    threads: int = 1,
    workers: Any = None,
) -> dict[str, list[float]]:
    """Fit ``model``'s policy (and value) to the teacher by DAgger; updates ``vecnorm``'s stats.

    The student of every iteration is scored by the docked fraction of the next iteration's
    rollouts (the last one by an extra batch); the best-scoring student is kept, since the
    imitation of a controller with sharp decisions does not improve monotonically.

    ``batched``: each iteration's episodes at once on the batched simulator (the training
    simulator ``"batched"``), else one at a time; ``workers``: with ``batched``, the training's
    batch workers (:class:`rl.train.grouped_vec_env.BatchGroupsVecEnv`) to split that batch
    over (the same episodes, on every core). ``threads``: torch's threads while fitting
    (PPO's ``update_threads``: the simulator waits meanwhile); the rollouts run on one.

    Returns:
        Per iteration: the imitation loss, the docked fraction of the rollouts (iteration 0:
        the teacher; k > 0: the student fitted at k - 1) and the number of transitions; the
        selected iteration and the environment steps.
    """
    import torch

    success_key = f"success_{env_cfg.terminate_on}"  # the condition that ends an episode
    policy = model.policy
    total = (cfg.iterations + 1) * cfg.episodes_per_iteration
    bar = tqdm(total=total, desc="imitation", unit="ep", disable=not progress)
    args = (env_cfg, success_key, policy, vecnorm, cfg, gamma, bar)
    if not batched:
        rollouts = _Rollouts(*args, ep_seed=seed + 500_000)
    elif workers is None:
        rollouts = _BatchRollouts(*args, ep_seed=seed + 500_000)
    else:
        rollouts = _SplitRollouts(*args, ep_seed=seed + 500_000, workers=workers)
    history, states = _dagger(model, vecnorm, rollouts, cfg, bar, threads)
    final_frac, *_ = rollouts.collect(student=True)
    history["docked"].append(final_frac)
    best = _keep_best_student(policy, vecnorm, history["docked"][1:], states)
    history["selected_iteration"] = [best]
    history["env_steps"] = [rollouts.steps]
    bar.close()
    rollouts.close()
    with torch.no_grad():
        policy.log_std.fill_(cfg.log_std)
    return history


class _Rollouts:
    """The episodes of a warm start, one at a time: the teacher (or the student's mean action)
    acting, the teacher labelling every observation; the episode seeds run on, the env steps
    counted."""

    def __init__(
        self,
        env_cfg: EnvConfig,
        success_key: str,
        policy: Any,
        vecnorm: Any,
        cfg: ImitationConfig,
        gamma: float,
        bar: tqdm,
        ep_seed: int,
    ) -> None:
        self.env_cfg, self.success_key = env_cfg, success_key
        self.policy, self.vecnorm, self.cfg, self.gamma, self.bar = policy, vecnorm, cfg, gamma, bar
        self.ep_seed = ep_seed
        self.steps = 0
        self.env = self._open()

    def _open(self) -> Any:
        return DockingEnv(self.env_cfg)

    def close(self) -> None:
        self.env.close()

    def collect(self, student: bool) -> tuple[float, list, list, list]:
        """One iteration's episodes: the docked fraction and, per episode, its observations,
        the teacher's labels and the discounted returns."""
        docked, O, A, G = 0, [], [], []
        for ep_obs, ep_act, ep_rew, success in self._episodes(student):
            docked += int(success)
            O.append(np.asarray(ep_obs))
            A.append(np.asarray(ep_act))
            G.append(_discounted(np.asarray(ep_rew), self.gamma))
        return docked / self.cfg.episodes_per_iteration, O, A, G

    def _episodes(self, student: bool):
        """Each episode of an iteration: (observations, teacher labels, rewards, docked)."""
        teacher = PIDController.for_env(self.env_cfg)
        for _ in range(self.cfg.episodes_per_iteration):
            obs, _ = self.env.reset(seed=self.ep_seed)
            self.ep_seed += 1
            teacher.reset()
            ep_obs, ep_act, ep_rew = [], [], []
            done = False
            while not done:
                label = teacher.act(obs)
                action = self._student_actions(obs[None])[0] if student else label
                ep_obs.append(obs)
                ep_act.append(label)
                obs, r, term, trunc, info = self.env.step(action)
                self.steps += 1
                ep_rew.append(r)
                done = term or trunc
            self.bar.update(1)
            yield ep_obs, ep_act, ep_rew, bool(info[self.success_key])

    def _student_actions(self, obs: np.ndarray) -> np.ndarray:
        """The student's mean actions for a batch of observations, clipped to [-1, 1]."""
        import torch

        vecnorm = self.vecnorm
        o = vecnorm.normalize_obs(obs) if vecnorm is not None else obs
        with torch.no_grad():
            dist = self.policy.get_distribution(torch.as_tensor(o, dtype=torch.float32))
            return np.clip(dist.distribution.mean.numpy(), -1, 1)


class _BatchRollouts(_Rollouts):
    """The episodes of a warm start all at once on the batched simulator: episode ``k`` of an
    iteration is env ``k``, reset with the seed the one-at-a-time episodes use; an env whose
    episode ended flies on with zero thrust (its steps neither kept nor counted) until the last
    one ends."""

    def _open(self) -> Any:
        from uwdock.rl.env.batch_env import BatchDockingEnv  # SB3 at module level

        return BatchDockingEnv(self.env_cfg, self.cfg.episodes_per_iteration, seed=self.ep_seed)

    def _episodes(self, student: bool):
        n = self.cfg.episodes_per_iteration
        self.env.seed(self.ep_seed)  # env k resets with ep_seed + k, as a new batch
        self.ep_seed += n
        teachers = [PIDController.for_env(self.env_cfg) for _ in range(n)]
        eps: list[tuple[list, list, list]] = [([], [], []) for _ in range(n)]
        success = [False] * n
        live = np.ones(n, dtype=bool)
        obs = self.env.reset()
        while live.any():
            labels = np.stack([t.act(o) for t, o in zip(teachers, obs, strict=True)])
            actions = self._student_actions(obs) if student else labels.copy()
            actions[~live] = 0.0
            next_obs, rew, done, infos = self.env.step(actions)
            for i in np.flatnonzero(live):
                ep_obs, ep_act, ep_rew = eps[i]
                ep_obs.append(obs[i])
                ep_act.append(labels[i])
                ep_rew.append(float(rew[i]))
                self.steps += 1
                if done[i]:
                    success[i] = bool(infos[i][self.success_key])
                    live[i] = False
                    self.bar.update(1)
            obs = next_obs
        for i in range(n):
            yield (*eps[i], success[i])


class _SplitRollouts(_BatchRollouts):
    """:class:`_BatchRollouts` on a batch split over the training's batch workers
    (``workers``, :meth:`rl.train.grouped_vec_env.BatchGroupsVecEnv.split_batch`): the teacher
    and the student act here on the whole batch's observations, as in one process (the
    network's products round by batch size), and each env's draws are its own, so the episodes
    are those of :class:`_BatchRollouts` while every core steps them."""

    def __init__(self, *args: Any, workers: Any, **kwargs: Any) -> None:
        self.workers = workers
        super().__init__(*args, **kwargs)

    def _open(self) -> Any:
        n = self.cfg.episodes_per_iteration
        return self.workers.split_batch(self.env_cfg, n, self.ep_seed)


def _dagger(
    model, vecnorm, rollouts: _Rollouts, cfg: ImitationConfig, bar: tqdm, threads: int = 1
) -> tuple[dict[str, list[float]], list[tuple[dict, Any]]]:
    """The DAgger iterations: roll out (the teacher first, then the student), aggregate, refit;
    returns the history and each iteration's student with its normalisation."""
    policy = model.policy
    rms = vecnorm.obs_rms if vecnorm is not None else None
    obs_all, act_all, ret_all = [], [], []
    history: dict[str, list[float]] = {"loss": [], "docked": [], "samples": []}
    states: list[tuple[dict, Any]] = []
    for it in range(cfg.iterations):
        frac, O, A, G = rollouts.collect(student=it > 0)
        obs_all += O
        act_all += A
        ret_all += G
        X = np.concatenate(obs_all).astype(np.float64)
        if rms is not None:
            rms.update(np.concatenate(O).astype(np.float64))
        loss = _fit(
            model, vecnorm, X, np.concatenate(act_all), np.concatenate(ret_all), cfg, threads
        )
        # the student is only valid with the normalisation it was fitted under: keep both
        norm = copy.deepcopy((vecnorm.obs_rms, vecnorm.ret_rms)) if vecnorm is not None else None
        states.append((copy.deepcopy(policy.state_dict()), norm))
        history["loss"].append(loss)
        history["docked"].append(frac)
        history["samples"].append(sum(len(o) for o in O))
        bar.set_postfix(loss=f"{loss:.4f}", docked=f"{frac:.2f}")
    return history, states


def _keep_best_student(policy, vecnorm, scores: list[float], states: list[tuple[dict, Any]]) -> int:
    """Load the best-scoring student (``scores[k]``: the student fitted at iteration k) and its
    normalisation; returns its iteration."""
    best = len(scores) - 1 - int(np.argmax(scores[::-1]))  # ties: the later, better-fed student
    weights, norm = states[best]
    policy.load_state_dict(weights)
    if vecnorm is not None:
        vecnorm.obs_rms, vecnorm.ret_rms = norm
    return best


def _fit(
    model,
    vecnorm,
    X: np.ndarray,
    A: np.ndarray,
    G: np.ndarray,
    cfg: ImitationConfig,
    threads: int = 1,
) -> float:
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        return _fit_epochs(model, vecnorm, X, A, G, cfg)
    finally:
        torch.set_num_threads(before)


def _fit_epochs(
    model, vecnorm, X: np.ndarray, A: np.ndarray, G: np.ndarray, cfg: ImitationConfig
) -> float:
    import torch

    policy = model.policy
    Xn = vecnorm.normalize_obs(X) if vecnorm is not None else X
    if vecnorm is not None and vecnorm.norm_reward:
        # PPO sees rewards divided by the running return std: fit the critic on that scale
        scale = float(np.std(G)) + 1e-8
        vecnorm.ret_rms.mean = np.zeros(())
        vecnorm.ret_rms.var = np.array(scale**2)
        vecnorm.ret_rms.count = float(len(G))
        G = G / scale
    x = torch.as_tensor(Xn, dtype=torch.float32)
    a = torch.as_tensor(np.clip(A, -1, 1), dtype=torch.float32)
    g = torch.as_tensor(G, dtype=torch.float32)
    # over all tensors at once: the same bits as one at a time (as PPO's, training.build_model)
    opt = torch.optim.Adam(policy.parameters(), lr=cfg.learning_rate, foreach=True)
    n = len(x)
    gen = torch.Generator().manual_seed(0)
    last = 0.0
    for _ in range(cfg.epochs):
        perm = torch.randperm(n, generator=gen)
        for k in range(0, n, cfg.batch_size):
            idx = perm[k : k + cfg.batch_size]
            dist = policy.get_distribution(x[idx])
            pi_loss = torch.mean((dist.distribution.mean - a[idx]) ** 2)
            v_loss = torch.mean((policy.predict_values(x[idx]).squeeze(-1) - g[idx]) ** 2)
            loss = pi_loss + 0.5 * v_loss
            opt.zero_grad()
            loss.backward()
            opt.step()
            last = pi_loss.item()
    return last
