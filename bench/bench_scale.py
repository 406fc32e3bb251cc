"""Scale-out: throughput against the number of workers, local processes against Ray actors.

Usage::

    python bench/bench_scale.py [--workers 1,2] [--repeats 3] [--frames 40] [--episodes 12]
        [--train-steps 2048] [--jobs synth,eval,train]

Each timing is one whole command run as a user runs it (a fresh process: imports, workers
started, each building its SAPIEN scene or env, the work, the files written), the median of
``--repeats``:

* ``datasets synth --n FRAMES --width 480 --water random`` (frames/s);
* ``rl eval --policy pid --obs camera`` over ``--episodes`` episodes of 20 s at 480 px
  (episodes/s and control steps/s);
* ``rl train`` (PPO, proxy source, ``--envs`` = workers, ``--train-steps`` env steps, no
  checkpoints or evaluations in between) (env steps/s).

Each command runs with ``--backend local`` and with ``--backend ray --ray-address`` of a Ray
instance started once beforehand with ``ray start --head`` (as on a cluster, where the instance
is up before the jobs; its start time is reported on its own), here through
``python -m uwdock.dockcore.rayloop``, which keeps it on 127.0.0.1. The rows give Ray's overhead
against the local pool at the same worker count and, for the evaluation, the balance of the
work: the makespan of its episodes as handed out now (one at a time to a free worker) against
the old static split (``range(w, n, workers)``) and the ideal, in control steps.

Writes ``bench/results/scale.json`` (rows + machine, commit, packages).
"""

from __future__ import annotations

import argparse
import csv
import heapq
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from uwdock.dockcore.bench import format_table, save_results

BIN = Path(sys.executable).parent
TRAIN_TOML = """\
checkpoint_every = 1000000000
eval_every = 0
[env]
obs_source = "proxy"
"""


def _run(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{done.stderr[-2000:]}")
    return wall


def _backend(backend: str, address: str) -> list[str]:
    return ["--backend", "ray", "--ray-address", address] if backend == "ray" else []


def _timed(make_cmd, repeats: int) -> tuple[float, list[float], Path]:
    """Median wall time of ``repeats`` runs of ``make_cmd(out_dir)``; the last out dir kept."""
    times, keep = [], Path(tempfile.mkdtemp(prefix="bench-scale-keep-"))
    for i in range(repeats):
        with tempfile.TemporaryDirectory(prefix="bench-scale-") as tmp:
            out = Path(tmp) / "out"
            times.append(_run(make_cmd(out)))
            if i == repeats - 1:
                shutil.rmtree(keep)
                shutil.copytree(out, keep)
    return statistics.median(times), times, keep


def synth_row(backend: str, w: int, a, address: str) -> dict:
    def cmd(out: Path) -> list[str]:
        return [str(BIN / "datasets"), "synth", "--n", str(a.frames), "--width", "480",
                "--water", "random", "--workers", str(w), "--out", str(out), "--quiet",
                *_backend(backend, address)]  # fmt: skip

    wall, runs, keep = _timed(cmd, a.repeats)
    shutil.rmtree(keep, ignore_errors=True)
    return {"job": "synth", "backend": backend, "workers": w, "units": a.frames,
            "unit": "frames", "wall_s": round(wall, 2), "runs_s": [round(t, 2) for t in runs],
            "per_s": round(a.frames / wall, 2)}  # fmt: skip


def _makespans(steps: list[int], workers: int) -> dict:
    """Makespan (control steps) of the episodes split statically, handed out in order to the
    first free worker, and the ideal."""
    static = max(sum(steps[w::workers]) for w in range(workers))
    free = [0] * workers
    for s in steps:
        heapq.heappush(free, heapq.heappop(free) + s)
    return {"static": static, "dynamic": max(free), "ideal": sum(steps) / workers}


def eval_row(backend: str, w: int, a, address: str, env_toml: Path) -> dict:
    def cmd(out: Path) -> list[str]:
        return [str(BIN / "rl"), "eval", "--policy", "pid", "--obs", "camera",
                "--episodes", str(a.episodes), "--seed", "3000", "--videos", "",
                "--config", str(env_toml), "--workers", str(w), "--out", str(out),
                *_backend(backend, address)]  # fmt: skip

    wall, runs, keep = _timed(cmd, a.repeats)
    with (keep / "episodes.csv").open() as fh:
        steps = [int(r["steps"]) for r in csv.DictReader(fh)]
    shutil.rmtree(keep, ignore_errors=True)
    span = _makespans(steps, w)
    return {"job": "eval", "backend": backend, "workers": w, "units": a.episodes,
            "unit": "episodes", "wall_s": round(wall, 2), "runs_s": [round(t, 2) for t in runs],
            "per_s": round(a.episodes / wall, 3),
            "control_steps_per_s": round(sum(steps) / wall, 1),
            "makespan_static_steps": span["static"], "makespan_dynamic_steps": span["dynamic"],
            "makespan_ideal_steps": round(span["ideal"], 1)}  # fmt: skip


def train_row(backend: str, w: int, a, address: str, train_toml: Path) -> dict:
    def cmd(out: Path) -> list[str]:
        return [str(BIN / "rl"), "train", "--config", str(train_toml), "--envs", str(w),
                "--steps", str(a.train_steps), "--seed", "5", "--out", str(out),
                *_backend(backend, address)]  # fmt: skip

    wall, runs, keep = _timed(cmd, a.repeats)
    shutil.rmtree(keep, ignore_errors=True)
    return {"job": "train", "backend": backend, "workers": w, "units": a.train_steps,
            "unit": "env steps", "wall_s": round(wall, 2), "runs_s": [round(t, 2) for t in runs],
            "per_s": round(a.train_steps / wall, 1)}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--episodes", type=int, default=12)
    ap.add_argument("--train-steps", type=int, default=2048)
    ap.add_argument("--jobs", default="synth,eval,train")
    ap.add_argument("--out-dir", type=Path, default=None)
    a = ap.parse_args()
    counts = [int(w) for w in a.workers.split(",")]
    work = Path(tempfile.mkdtemp(prefix="bench-scale-cfg-"))
    env_toml, train_toml = work / "env.toml", work / "train.toml"
    env_toml.write_text("episode_s = 20.0\ncamera_width_px = 480\n")
    train_toml.write_text(TRAIN_TOML)
    port = 6391
    address = f"127.0.0.1:{port}"  # the head started just now, on loopback only
    # the documented cluster (docs/guides/scale-out.md): token authentication for the head and
    # every job run against it (their processes inherit these), the token made if there is none
    os.environ.update(RAY_AUTH_MODE="token", RAY_USAGE_STATS_ENABLED="0")
    subprocess.run([str(Path(sys.executable).with_name("ray")), "get-auth-token", "--generate"],
                   check=True, capture_output=True)  # fmt: skip
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    t0 = time.perf_counter()
    # rayloop: RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 equivalent (loopback, nodes may join)
    subprocess.run([sys.executable, "-m", "uwdock.dockcore.rayloop", "start", "--head", "--port",
                    str(port), "--num-cpus", str(max(counts)), "--include-dashboard=false",
                    "--disable-usage-stats"],
                   check=True, capture_output=True, env=env)  # fmt: skip
    ray_start_s = time.perf_counter() - t0
    print(f"Ray head up in {ray_start_s:.1f} s (port {port})", flush=True)
    rows = []
    try:
        for job in a.jobs.split(","):
            for w in counts:
                pair = []
                for backend in ("local", "ray"):
                    if job == "synth":
                        pair.append(synth_row(backend, w, a, address))
                    elif job == "eval":
                        pair.append(eval_row(backend, w, a, address, env_toml))
                    else:
                        pair.append(train_row(backend, w, a, address, train_toml))
                local, remote = pair
                remote["ray_overhead_%"] = round(
                    100.0 * (remote["wall_s"] / local["wall_s"] - 1), 1
                )
                rows += pair
                print(f"{job} x{w}: local {local['per_s']} / ray {remote['per_s']} "
                      f"{local['unit']}/s (overhead {remote['ray_overhead_%']} %)",
                      flush=True)  # fmt: skip
    finally:
        subprocess.run([str(BIN / "ray"), "stop", "--force"], capture_output=True, env=env)
        shutil.rmtree(work, ignore_errors=True)
    cols = ["job", "backend", "workers", "units", "unit", "wall_s", "per_s", "ray_overhead_%"]
    print(format_table(rows, cols))
    config = {
        "workers": counts, "repeats": a.repeats, "frames": a.frames, "episodes": a.episodes,
        "train_steps": a.train_steps, "ray_head_start_s": round(ray_start_s, 2),
        "note": "each timing is a whole command in a fresh process",
    }  # fmt: skip
    print(save_results("scale", rows, config, a.out_dir))


if __name__ == "__main__":
    main()
