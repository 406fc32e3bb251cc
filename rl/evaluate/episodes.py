"""Seeded evaluation episodes: summary, per-episode rows and traces for the figures."""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from uwdock.dockcore.config import to_dict
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_bytes, atomic_write_json
from uwdock.dockcore.pool import PoolConfig, worker_pool
from uwdock.dockcore.procs import workers_ended_on_error
from uwdock.rl.env.config import EnvConfig, absolute_inputs
from uwdock.rl.env.docking_env import DockingEnv
from uwdock.rl.env.observation import POS_SCALE_M, frame_dim
from uwdock.rl.evaluate.episode_media import write_frames_sheet, write_video
from uwdock.rl.evaluate.failures import FailureTracker, failure_counts
from uwdock.rl.policy.policy_format import SUMS
from uwdock.rl.policy.policy_io import load_controller, policy_input_files


class Controller(Protocol):
    def reset(self) -> None: ...

    def act(self, obs: np.ndarray) -> np.ndarray: ...


class SB3Controller:
    """A stable-baselines3 policy (deterministic), with its observation normalisation.

    Args:
        model: the SB3 model.
        vecnorm: its observation normalisation, or None.
        pre_clip: return a PPO policy's Gaussian mean *before* clipping to [-1, 1] (the env
            clips; diagnostics see means beyond +-1 that ``predict`` would hide).
    """

    def __init__(self, model, vecnorm=None, pre_clip: bool = False) -> None:
        self.model = model
        self.vecnorm = vecnorm
        self.pre_clip = pre_clip

    def reset(self) -> None:
        pass

    def act(self, obs: np.ndarray) -> np.ndarray:
        return self.act_batch(obs[None, :])[0]

    def act_batch(self, obs: np.ndarray) -> np.ndarray:
        """The actions (n, 6) of a batch of observations (n, d)."""
        o = obs if self.vecnorm is None else self.vecnorm.normalize_obs(obs)
        if not np.all(np.isfinite(o)):
            raise DockError(
                "the policy's observation normalisation gives NaN or infinity "
                "(broken normalisation statistics)"
            )
        if self.pre_clip:
            import torch

            with torch.no_grad():
                t = torch.as_tensor(o, dtype=torch.float32)
                mean = self.model.policy.get_distribution(t).distribution.mean
            return mean.numpy().astype(np.float64)
        try:
            action, _ = self.model.predict(o, deterministic=True)
        except ValueError:  # torch's distribution refuses a NaN mean
            action = np.full((o.shape[0], 6), np.nan)
        action = np.asarray(action, dtype=np.float64)
        if not np.all(np.isfinite(action)):
            raise DockError("the policy outputs NaN or infinity (its weights overflow)")
        return action


@dataclass
class EpisodeTrace:
    """Per-step record of one episode (world NED, body FRD)."""

    time_s: list[float] = field(default_factory=list)
    pos_body_m: list[np.ndarray] = field(default_factory=list)
    pos_ds_m: list[np.ndarray] = field(default_factory=list)
    wrench: list[np.ndarray] = field(default_factory=list)
    e_true: list[np.ndarray] = field(default_factory=list)
    e_obs: list[np.ndarray] = field(default_factory=list)
    detected: list[bool] = field(default_factory=list)
    collided: list[bool] = field(default_factory=list)
    frames: list[np.ndarray] = field(default_factory=list)


@dataclass
class EvalResult:
    summary: dict[str, Any]
    episodes: list[dict[str, Any]]
    traces: list[EpisodeTrace]
    #: Ray: episodes run per node and workers replaced (where the work ran); local: empty
    ray_nodes: dict[str, Any] = field(default_factory=dict)


def as_controller(policy, vecnorm) -> Controller:
    """A controller as given, or an SB3 model wrapped with its normalisation."""
    return policy if hasattr(policy, "act") else SB3Controller(policy, vecnorm)


def run_episodes(
    policy,
    env_cfg: EnvConfig,
    n_episodes: int,
    seed: int = 0,
    vecnorm=None,
    record: bool = True,
    video_episodes: tuple[int, ...] = (),
    progress=None,
    episodes: list[int] | None = None,
    video_dir: str | None = None,
) -> EvalResult:
    """Run seeded episodes (episode k uses seed + k) and summarise them.

    Args:
        policy: a :class:`Controller` or an SB3 model.
        env_cfg: the environment (its ``obs_source`` decides what the policy sees).
        n_episodes: number of episodes (indices 0 .. n-1 unless ``episodes`` is given).
        seed: seed of episode 0.
        vecnorm: observation normalisation of an SB3 model.
        record: keep per-step traces (for the figures).
        video_episodes: episode indices whose camera view is filmed.
        progress: optional callable(done, total) called after each episode.
        episodes: the episode indices to run (for splitting work between processes).
        video_dir: write ``camera_ep<k>.mp4`` there (frames are not kept in the traces);
            None keeps the frames in ``EpisodeTrace.frames``.
    """
    ctrl = as_controller(policy, vecnorm)
    todo = list(range(n_episodes)) if episodes is None else list(episodes)
    env = DockingEnv(env_cfg, render_mode="rgb_array" if video_episodes else None)
    rows, traces = [], []
    try:
        for done_count, k in enumerate(todo, start=1):
            row, tr = _episode(env, ctrl, k, seed, record, k in video_episodes)
            if video_dir is not None and tr.frames:
                _write_film(tr, k, env_cfg, Path(video_dir))
            rows.append(row)
            traces.append(tr)
            if progress is not None:
                progress(done_count, len(todo))
    finally:
        env.close()
    return EvalResult(summarise(rows), rows, traces)


def _episode(
    env, ctrl: Controller, k: int, seed: int, record: bool, film: bool
) -> tuple[dict[str, Any], EpisodeTrace]:
    obs, info = env.reset(seed=seed + k)
    ctrl.reset()
    tr = EpisodeTrace()
    failures = FailureTracker()
    ret, collisions, steps = 0.0, 0, 0
    dock_time = None
    done = False
    while not done:
        a = np.asarray(ctrl.act(obs), dtype=np.float64)
        if a.shape != (6,) or not np.all(np.isfinite(a)):
            raise DockError(
                f"the policy gave a non-finite or malformed action {a.tolist()} in episode {k} "
                f"at step {steps} (seed {seed + k}): its weights or normalisation are broken"
            )
        obs, r, term, trunc, info = env.step(a)
        ret += r
        steps += 1
        collisions += int(info["collided"])
        failures.update(info["time_s"], info["T_world_body"][:3, 3], info["e_true"], a)
        if info["success_paper"] and dock_time is None:
            dock_time = info["time_s"]
        if record:
            tr.time_s.append(info["time_s"])
            tr.pos_body_m.append(info["T_world_body"][:3, 3].copy())
            tr.pos_ds_m.append(info["T_world_ds"][:3, 3].copy())
            tr.wrench.append(np.asarray(a) * env._limits)
            tr.e_true.append(np.append(info["e_true"], info["e_psi_true"]))
            latest = obs[-frame_dim(env.cfg) :]  # the newest frame of a stacked observation
            tr.e_obs.append(np.append(latest[0:3] * POS_SCALE_M, latest[3] * math.pi))
            tr.detected.append(info["detected"])
            tr.collided.append(bool(info["collided"]))
        if film:
            frame = env.camera_frame()
            if frame is not None:
                tr.frames.append(frame)
        done = term or trunc
    row = episode_row(k, seed, info, dock_time, steps, ret, collisions, failures)
    return row, tr


def episode_row(
    k: int,
    seed: int,
    info: dict[str, Any],
    dock_time_s: float | None,
    steps: int,
    ret: float,
    collisions: int,
    failures: FailureTracker,
) -> dict[str, Any]:
    """The summary row of episode ``k`` (seed ``seed + k``) from its last step's ``info`` and
    its running counts: what :func:`run_episodes` and ``rl.evaluate.batched.batched_episodes``
    give."""
    e = info["e_true"]
    strict = bool(info["success_strict"])
    return {
        "episode": int(k),
        "seed": seed + int(k),
        "success": bool(info["success_paper"]),
        "success_strict": strict,
        "time_to_dock_s": dock_time_s,
        "steps": int(steps),
        "return": float(ret),
        "collisions": int(collisions),
        "final_e_xy_m": float(np.hypot(e[0], e[1])),
        "final_e_z_m": float(abs(e[2])),
        "final_e_yaw_deg": float(abs(math.degrees(info["e_psi_true"]))),
        "final_nav_error_m": float(info.get("nav_error_m", 0.0)),
        "failure_mode": failures.failure_mode(strict),
        "wedged_s": round(failures.longest_s["wedged"], 3),
        "landed_off_s": round(failures.longest_s["landed_off"], 3),
    }


class EpisodeWorker:
    """A pool worker (:func:`dockcore.pool.worker_pool`): the policy and an env, built once,
    running single seeded episodes. A filmed episode's video and frame sheet come back as file
    bytes (the caller writes them), so Ray workers on other machines need no shared folder.

    Args:
        policy_spec: what :func:`~uwdock.rl.policy.policy_io.load_controller` loads.
        env_cfg: the evaluation env.
        seed: seed of episode 0 (episode k: ``seed + k``).
        record: keep per-step traces.
        video_episodes: the episodes filmed.
        encode_films: return a filmed episode as MP4 and JPEG bytes; False keeps its frames in
            the trace (``EpisodeTrace.frames``).
    """

    def __init__(
        self,
        policy_spec: str,
        env_cfg: EnvConfig,
        seed: int,
        record: bool,
        video_episodes: tuple[int, ...],
        encode_films: bool = True,
    ) -> None:
        _one_thread()
        self.ctrl, vecnorm, _ = load_controller(policy_spec, env_cfg)
        self.ctrl = as_controller(self.ctrl, vecnorm)
        self.env_cfg, self.seed, self.record = env_cfg, int(seed), bool(record)
        self.video_episodes = tuple(int(v) for v in video_episodes)
        self.encode_films = bool(encode_films)
        self.env = DockingEnv(env_cfg, render_mode="rgb_array" if video_episodes else None)

    def episode(self, k: int) -> tuple[dict[str, Any], EpisodeTrace, dict[str, bytes]]:
        """Episode k: its row, its trace and, when filmed, ``{file name: bytes}``."""
        k = int(k)
        row, tr = _episode(self.env, self.ctrl, k, self.seed, self.record, k in self.video_episodes)
        files: dict[str, bytes] = {}
        if tr.frames and self.encode_films:
            with tempfile.TemporaryDirectory(prefix="uwdock-film-") as tmp:
                files = {
                    p.name: p.read_bytes() for p in _write_film(tr, k, self.env_cfg, Path(tmp))
                }
        return row, tr, files


def _write_film(tr: EpisodeTrace, k: int, env_cfg: EnvConfig, folder: Path) -> list[Path]:
    """Episode k's camera frames as ``camera_ep<k>.mp4`` and a frame sheet in ``folder``; the
    frames are dropped from the trace. Returns the files written."""
    dt_s = 1.0 / env_cfg.control_hz  # frames are taken after each control step
    video = write_video(tr.frames, folder / f"camera_ep{k}.mp4")
    sheet = write_frames_sheet(tr.frames, folder / f"camera_ep{k}_frames.jpg", dt_s, first_s=dt_s)
    tr.frames = []
    return [p for p in (video, sheet) if p is not None]


def _one_thread() -> None:
    """One torch thread per worker: the workers are the parallelism (and a forked or spawned
    worker must not wait on a thread pool it inherited, see ``rl.train.workers``)."""
    import torch  # heavy; only the evaluation workers need it here

    torch.set_num_threads(1)


def _policy_inputs(policy_spec: str) -> list[str]:
    """The files loading ``policy_spec`` reads (:func:`policy_input_files`), with the policy
    folder's checksum file, which the loader checks them against."""
    files = [str(f) for f in policy_input_files(policy_spec)]
    if files:
        sums = Path(files[0]).parent / SUMS
        if sums.is_file():
            files.append(str(sums))
    return files


#: The folder (in an evaluation's output folder) that keeps its finished episodes until the
#: report is written: a rerun after a failure or an interrupt goes on from them.
PARTIAL_EVAL_DIR = ".partial-episodes"


class EpisodeStore:
    """Finished episodes of an evaluation, kept on disk as they come (``ep<k>.json``: the row;
    ``ep<k>.npz``: the trace, plain arrays), under a key naming what they are episodes of (the
    policy's and the env's input files by content, the env config, the seed): a rerun of the
    same evaluation reuses them, any other starts afresh."""

    def __init__(self, folder: Path, key: str) -> None:
        self.folder, self.key = folder, key
        try:
            same = json.loads((folder / "key.json").read_text(encoding="utf-8")).get("key") == key
        except (OSError, ValueError, AttributeError):
            same = False
        if not same and folder.is_dir():  # another evaluation's episodes: not these
            for f in folder.iterdir():
                if f.is_file():
                    f.unlink()

    def load(self, n_episodes: int) -> dict[int, tuple[dict[str, Any], EpisodeTrace]]:
        """The episodes below ``n_episodes`` kept whole (a damaged one is run again)."""
        out = {}
        for k in range(n_episodes):
            row_file, trace_file = self.folder / f"ep{k}.json", self.folder / f"ep{k}.npz"
            if not row_file.is_file() or not trace_file.is_file():
                continue
            try:
                row = json.loads(row_file.read_text(encoding="utf-8"))
                with np.load(trace_file, allow_pickle=False) as arrays:
                    trace = EpisodeTrace(**{
                        f.name: (arrays[f.name].tolist() if arrays[f.name].ndim == 1
                                 else list(arrays[f.name]))
                        for f in dataclasses.fields(EpisodeTrace)
                    })  # fmt: skip
            except (OSError, ValueError, KeyError, TypeError):
                continue
            if isinstance(row, dict) and row.get("episode") == k:
                out[k] = (row, trace)
        return out

    def save(self, k: int, row: dict[str, Any], trace: EpisodeTrace) -> None:
        """Episode ``k`` kept (its trace first: the row marks it whole)."""
        if not (self.folder / "key.json").is_file():
            self.folder.mkdir(exist_ok=True)
            atomic_write_json(self.folder / "key.json", {"key": self.key})
        arrays = {}
        for f in dataclasses.fields(EpisodeTrace):
            value = getattr(trace, f.name)
            arrays[f.name] = np.asarray(value) if len(value) else np.zeros(0)
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        atomic_write_bytes(self.folder / f"ep{k}.npz", buf.getvalue())
        atomic_write_json(self.folder / f"ep{k}.json", row)


def episodes_key(policy_spec: str, env_cfg: EnvConfig, seed: int, record: bool) -> str:
    """What an evaluation's episodes depend on, as a digest (:class:`EpisodeStore`)."""
    _, env_files = absolute_inputs(env_cfg)
    files = _policy_inputs(policy_spec) if policy_spec != "pid" else []
    h = hashlib.sha256()
    h.update(json.dumps([policy_spec == "pid", to_dict(env_cfg), seed, record], default=str,
                        sort_keys=True).encode())  # fmt: skip
    for f in sorted(set(files + env_files)):
        h.update(Path(f).name.encode() + b"\0" + Path(f).read_bytes())
    return h.hexdigest()


def run_episodes_parallel(
    policy_spec: str,
    env_cfg: EnvConfig,
    n_episodes: int,
    seed: int = 0,
    workers: int = 2,
    record: bool = True,
    video_episodes: tuple[int, ...] = (),
    video_dir: str | None = None,
    progress=None,
    backend: str = "local",
    ray_address: str | None = None,
    store: EpisodeStore | None = None,
) -> EvalResult:
    """:func:`run_episodes` over ``workers`` processes or Ray actors (each loads the policy and
    builds its own simulator once), the episodes handed out one at a time to whichever worker is
    free (:mod:`dockcore.pool`); the result is the same as in one process. With a ``store``,
    the episodes it holds are not run again and each finished one is kept there as it comes
    (so a failed or interrupted evaluation goes on where it stopped)."""
    if backend == "local" and (workers <= 1 or n_episodes <= 1):
        ctrl, vecnorm, _ = load_controller(policy_spec, env_cfg)
        return run_episodes(
            ctrl,
            env_cfg,
            n_episodes,
            seed,
            vecnorm,
            record,
            video_episodes,
            progress,
            video_dir=video_dir,
        )
    if backend == "local":
        workers = min(workers, n_episodes)
        pool_cfg = PoolConfig(backend, workers, ray_address)
    else:  # Ray workers may start in another folder or on another node: the input files
        # by absolute path, sent to them as content (a node needs none of this machine's)
        if policy_spec != "pid":
            policy_spec = str(Path(policy_spec).expanduser().resolve())
        env_cfg, inputs = absolute_inputs(env_cfg)
        inputs += _policy_inputs(policy_spec)
        pool_cfg = PoolConfig(backend, workers, ray_address, tuple(inputs))
    args = (policy_spec, env_cfg, seed, record, tuple(video_episodes), video_dir is not None)
    results = store.load(n_episodes) if store is not None else {}
    todo = [k for k in range(n_episodes) if k not in results]
    if progress is not None and results:
        progress(len(results), n_episodes)
    ray_nodes: dict[str, Any] = {}
    if todo:
        pool_cfg = dataclasses.replace(pool_cfg, workers=min(pool_cfg.workers, len(todo)))
        with (
            worker_pool(pool_cfg, EpisodeWorker, args) as pool,
            workers_ended_on_error(pool),  # an interrupt stops the workers now, mid-episode
        ):
            for k, (row, trace, files) in pool.imap_unordered("episode", todo):
                for name, data in files.items():
                    atomic_write_bytes(Path(str(video_dir)) / name, data)
                results[k] = (row, trace)
                if store is not None:
                    store.save(k, row, trace)
                if progress is not None:
                    progress(len(results), n_episodes)
            if backend == "ray":
                ray_nodes = {"tasks_by_node": dict(pool.tasks_by_node),
                             "workers_replaced": pool.replaced}  # fmt: skip
    rows = [results[k][0] for k in range(n_episodes)]
    traces = [results[k][1] for k in range(n_episodes)]
    return EvalResult(summarise(rows), rows, traces, ray_nodes)


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The summary of per-episode rows (success rates, time to dock, collisions, errors)."""
    n = len(rows)
    succ = [r for r in rows if r["success"]]
    times = [r["time_to_dock_s"] for r in succ if r["time_to_dock_s"] is not None]

    def med(key: str) -> float:
        return float(np.median([r[key] for r in rows])) if rows else float("nan")

    return {
        "episodes": n,
        "success_rate": len(succ) / n if n else 0.0,
        "success_rate_strict": sum(r["success_strict"] for r in rows) / n if n else 0.0,
        "mean_time_to_dock_s": float(np.mean(times)) if times else None,
        "mean_collisions": float(np.mean([r["collisions"] for r in rows])) if n else 0.0,
        "mean_return": float(np.mean([r["return"] for r in rows])) if n else 0.0,
        "final_e_xy_m_median": med("final_e_xy_m"),
        "final_e_z_m_median": med("final_e_z_m"),
        "final_e_yaw_deg_median": med("final_e_yaw_deg"),
        "final_nav_error_m_median": med("final_nav_error_m"),
        "failure_modes": failure_counts(rows),
    }
