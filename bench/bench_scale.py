"""Scale-out: throughput against the number of workers, local processes against Ray actors.

Usage::

    python bench/bench_scale.py [--workers 1,2] [--repeats 3] [--frames 40] [--episodes 12]
        [--train-steps 2048] [--ray-address ADDRESS]

Three jobs, each on ``--workers`` workers with the local pool and with Ray
(``uwdock.dockcore.pool``; ``rl.ray_envs`` for training), the median of ``--repeats`` runs:

* ``datasets synth``: ``--frames`` frames at 480 px with random water (frames/s);
* ``rl eval``: the PID baseline over ``--episodes`` camera episodes at 480 px, 20 s each
  (episodes/s and control steps/s);
* ``rl train``: PPO on the proxy source with ``n_envs`` = workers for ``--train-steps`` env
  steps (env steps/s).

Ray runs on a local instance with as many CPUs as workers, started once before the timings (a
cluster user's instance is already up; its start time is reported on its own), or on the
cluster at ``--ray-address``. Each timing includes starting the workers (processes or actors,
each building its SAPIEN scene). The rows also give Ray's overhead against the local pool at
the same worker count, and, for the evaluation, the balance of the work: the makespan of the
episodes as handed out (one at a time to a free worker) against the old static split
(``range(w, n, workers)``) and the ideal, in control steps.

Writes ``bench/results/scale.json`` (rows + machine, commit, packages).
"""

from __future__ import annotations

import argparse
import heapq
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from uwdock.datasets.synth import SynthConfig, generate
from uwdock.dockcore.bench import format_table, save_results
from uwdock.dockcore.config import replace
from uwdock.dockcore.pool import start_ray
from uwdock.rl.config import EnvConfig
from uwdock.rl.evaluate import run_episodes_parallel
from uwdock.rl.train import TrainConfig, train


def _median_time(fn, repeats: int) -> tuple[float, list[float], object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times, out


def synth_row(backend: str, workers: int, frames: int, repeats: int, address) -> dict:
    cfg = SynthConfig(n_frames=frames, water="random", width_px=480, seed=11)

    def once():
        with tempfile.TemporaryDirectory(prefix="bench-scale-") as tmp:
            generate(Path(tmp) / "ds", cfg, workers=workers, progress=False, backend=backend,
                     ray_address=address)  # fmt: skip

    wall, runs, _ = _median_time(once, repeats)
    return {"job": "synth", "backend": backend, "workers": workers, "units": frames,
            "wall_s": round(wall, 2), "runs_s": [round(t, 2) for t in runs],
            "per_s": round(frames / wall, 2), "unit": "frames"}  # fmt: skip


def _makespans(steps: list[int], workers: int) -> dict:
    """Makespan (control steps) of the episodes split statically, handed out dynamically (in
    order, to the first free worker), and the ideal."""
    static = max(sum(steps[w::workers]) for w in range(workers))
    free = [0] * workers
    heapq.heapify(free)
    for s in steps:
        heapq.heappush(free, heapq.heappop(free) + s)
    return {"static": static, "dynamic": max(free), "ideal": sum(steps) / workers}


def eval_row(backend: str, workers: int, episodes: int, repeats: int, address) -> dict:
    cfg = replace(EnvConfig(), obs_source="camera", camera_width_px=480, episode_s=20.0)

    def once():
        return run_episodes_parallel("pid", cfg, episodes, 3000, workers=workers, record=False,
                                     backend=backend, ray_address=address)  # fmt: skip

    wall, runs, res = _median_time(once, repeats)
    steps = [r["steps"] for r in res.episodes]
    span = _makespans(steps, workers)
    return {"job": "eval", "backend": backend, "workers": workers, "units": episodes,
            "wall_s": round(wall, 2), "runs_s": [round(t, 2) for t in runs],
            "per_s": round(episodes / wall, 3), "unit": "episodes",
            "control_steps_per_s": round(sum(steps) / wall, 1),
            "makespan_static_steps": span["static"], "makespan_dynamic_steps": span["dynamic"],
            "makespan_ideal_steps": round(span["ideal"], 1),
            "success_rate": res.summary["success_rate"]}  # fmt: skip


def train_row(backend: str, workers: int, steps: int, repeats: int, address) -> dict:
    cfg = replace(
        TrainConfig(), n_envs=workers, total_steps=steps, checkpoint_every=10**9, eval_every=0,
        seed=5, env=replace(EnvConfig(), obs_source="proxy"),
    )  # fmt: skip

    def once():
        with tempfile.TemporaryDirectory(prefix="bench-scale-") as tmp:
            train(cfg, Path(tmp) / "run", progress=False, note=lambda _m: None, backend=backend,
                  ray_address=address)  # fmt: skip

    wall, runs, _ = _median_time(once, repeats)
    return {"job": "train", "backend": backend, "workers": workers, "units": steps,
            "wall_s": round(wall, 2), "runs_s": [round(t, 2) for t in runs],
            "per_s": round(steps / wall, 1), "unit": "env steps"}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--episodes", type=int, default=12)
    ap.add_argument("--train-steps", type=int, default=2048)
    ap.add_argument("--jobs", default="synth,eval,train")
    ap.add_argument("--ray-address", default=None)
    ap.add_argument("--out-dir", type=Path, default=None)
    a = ap.parse_args()
    counts = [int(w) for w in a.workers.split(",")]
    import ray

    t0 = time.perf_counter()
    start_ray(ray, max(counts), a.ray_address)
    ray_start_s = time.perf_counter() - t0
    print(f"Ray instance up in {ray_start_s:.1f} s", flush=True)

    def run(job: str, backend: str, w: int) -> dict:
        address = a.ray_address if backend == "ray" else None
        if job == "synth":
            return synth_row(backend, w, a.frames, a.repeats, address)
        if job == "eval":
            return eval_row(backend, w, a.episodes, a.repeats, address)
        return train_row(backend, w, a.train_steps, a.repeats, address)

    rows = []
    for job in a.jobs.split(","):
        for w in counts:
            local = run(job, "local", w)
            remote = run(job, "ray", w)
            remote["ray_overhead_%"] = round(100.0 * (remote["wall_s"] / local["wall_s"] - 1), 1)
            rows += [local, remote]
            print(f"{job} x{w}: local {local['per_s']} / ray {remote['per_s']} {local['unit']}/s "
                  f"(overhead {remote['ray_overhead_%']} %)", flush=True)  # fmt: skip
    cols = ["job", "backend", "workers", "units", "unit", "wall_s", "per_s", "ray_overhead_%"]
    print(format_table(rows, cols))
    config = {
        "workers": counts, "repeats": a.repeats, "frames": a.frames, "episodes": a.episodes,
        "train_steps": a.train_steps, "ray_address": a.ray_address,
        "ray_instance_start_s": round(ray_start_s, 2),
    }  # fmt: skip
    print(save_results("scale", rows, config, a.out_dir))


if __name__ == "__main__":
    main()
