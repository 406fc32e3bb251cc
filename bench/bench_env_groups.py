"""Several training envs per worker (``rl train --envs-per-worker K``): speed and memory.

Usage::

    python bench/bench_env_groups.py [--envs 4] [--per-worker 1,2,4] [--repeats 3]
        [--proxy-steps 6144] [--camera-steps 2048] [--sources proxy,camera]
        [--backends local,ray]

Each timing is one whole ``rl train`` command in a fresh process (PPO, ``--envs`` envs, no
checkpoints or evaluations in between; the steps are the ones the run did, ``--steps`` rounded
up to whole rollouts of 512 steps per env), the median of ``--repeats``, for every ``K`` of
``--per-worker`` and every backend (Ray through a head started once with ``ray start``, as on a
cluster; here ``python -m uwdock.dockcore.rayloop start``, which keeps it on 127.0.0.1). While
it runs, the proportional set size (PSS: shared pages divided among the processes sharing them)
of the command's whole process tree is sampled every 0.2 s; its peak is the memory the job
takes. Ray's own daemons (the head) are not counted, only the command and
its actors.

* ``proxy``: the paper's visibility test (cheap steps: the transport is what is measured);
* ``camera``: render (SAPIEN, lavapipe on a CPU) -> water -> detector -> PnP at 480 px, the
  envs of a worker sharing its renderer.

Writes ``bench/results/env_groups.json`` (rows + machine, commit, packages).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil

from uwdock.dockcore.bench import format_table, save_results

BIN = Path(sys.executable).parent
#: The port of the Ray head the Ray rows run on (127.0.0.1 only).
RAY_PORT = 6392
TOML = """\
checkpoint_every = 1000000000
eval_every = 0
[env]
obs_source = "{source}"
[env.world]
camera_width_px = 480
"""


def _tree_pss(root: psutil.Process, actor_marker: str) -> int:
    """PSS (bytes) of ``root`` and its descendants plus this machine's Ray actors of the job."""
    procs = [root]
    try:
        procs += root.children(recursive=True)
    except psutil.Error:
        pass
    seen = {p.pid for p in procs}
    for p in psutil.process_iter(["pid", "cmdline"]):
        if p.info["pid"] not in seen and actor_marker in " ".join(p.info["cmdline"] or ()):
            procs.append(p)
    total = 0
    for p in procs:
        try:
            total += p.memory_full_info().pss
        except psutil.Error:  # gone meanwhile, or not ours
            pass
    return total


def _run(cmd: list[str]) -> tuple[float, int]:
    """Wall time (s) and peak PSS (bytes) of one command."""
    peak = 0
    stop = threading.Event()
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    root = psutil.Process(proc.pid)

    def sample() -> None:
        nonlocal peak
        while not stop.is_set():
            peak = max(peak, _tree_pss(root, "ray::_RayGroup"))
            stop.wait(0.2)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    _, err = proc.communicate()
    wall = time.perf_counter() - t0
    stop.set()
    thread.join()
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{err[-2000:]}")
    return wall, peak


def row(source: str, backend: str, k: int, a, toml: Path) -> dict:
    steps = a.proxy_steps if source == "proxy" else a.camera_steps
    walls, peaks = [], []
    for _ in range(a.repeats):
        with tempfile.TemporaryDirectory(prefix="bench-groups-") as tmp:
            run = Path(tmp) / "run"
            cmd = [str(BIN / "rl"), "train", "--config", str(toml), "--envs", str(a.envs),
                   "--steps", str(steps), "--seed", "5", "--out", str(run),
                   "--envs-per-worker", str(k)]  # fmt: skip
            if backend == "ray":
                cmd += ["--backend", "ray", "--ray-address", f"127.0.0.1:{RAY_PORT}"]
            wall, peak = _run(cmd)
            steps = int(json.loads((run / "DONE").read_text())["steps"])  # whole rollouts
        walls.append(wall)
        peaks.append(peak)
    wall = statistics.median(walls)
    workers = -(-a.envs // k)
    return {"source": source, "backend": backend, "envs": a.envs, "envs_per_worker": k,
            "workers": workers, "env_steps": steps, "wall_s": round(wall, 2),
            "runs_s": [round(t, 2) for t in walls], "steps_per_s": round(steps / wall, 1),
            "peak_pss_mib": round(statistics.median(peaks) / 2**20),
            "peaks_mib": [round(p / 2**20) for p in peaks]}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--envs", type=int, default=4)
    ap.add_argument("--per-worker", default="1,2,4")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--proxy-steps", type=int, default=6144)
    ap.add_argument("--camera-steps", type=int, default=2048)
    ap.add_argument("--sources", default="proxy,camera")
    ap.add_argument("--backends", default="local,ray")
    ap.add_argument("--out-dir", type=Path, default=None)
    a = ap.parse_args()
    ks = [int(k) for k in a.per_worker.split(",")]
    backends = a.backends.split(",")
    work = Path(tempfile.mkdtemp(prefix="bench-groups-cfg-"))
    # the documented cluster (docs/guides/scale-out.md): token authentication for the head and
    # every job run against it (their processes inherit these), the token made if there is none
    os.environ.update(RAY_AUTH_MODE="token", RAY_USAGE_STATS_ENABLED="0")
    subprocess.run([str(Path(sys.executable).with_name("ray")), "get-auth-token", "--generate"],
                   check=True, capture_output=True)  # fmt: skip
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    if "ray" in backends:  # a head on 127.0.0.1 only (docs/guides/scale-out.md)
        # rayloop: RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 equivalent (loopback, nodes may join)
        subprocess.run([sys.executable, "-m", "uwdock.dockcore.rayloop", "start", "--head",
                        "--port", str(RAY_PORT), "--num-cpus", str(a.envs),
                        "--include-dashboard=false", "--disable-usage-stats"],
                       check=True, capture_output=True, env=env)  # fmt: skip
    rows = []
    try:
        for source in a.sources.split(","):
            toml = work / f"{source}.toml"
            toml.write_text(TOML.format(source=source))
            for backend in backends:
                for k in ks:
                    r = row(source, backend, k, a, toml)
                    rows.append(r)
                    print(f"{source} {backend} K={k}: {r['steps_per_s']} steps/s, "
                          f"{r['peak_pss_mib']} MiB", flush=True)  # fmt: skip
    finally:
        if "ray" in backends:
            subprocess.run([str(BIN / "ray"), "stop", "--force"], capture_output=True, env=env)
        shutil.rmtree(work, ignore_errors=True)
    cols = ["source", "backend", "envs", "envs_per_worker", "workers", "env_steps", "wall_s",
            "steps_per_s", "peak_pss_mib"]  # fmt: skip
    print(format_table(rows, cols))
    config = {
        "envs": a.envs, "per_worker": ks, "repeats": a.repeats, "proxy_steps": a.proxy_steps,
        "camera_steps": a.camera_steps, "camera_width_px": 480,
        "note": "each timing is a whole rl train command in a fresh process; peak PSS of its "
        "process tree (and its Ray actors) sampled every 0.2 s",
    }  # fmt: skip
    print(save_results("env_groups", rows, config, a.out_dir))


if __name__ == "__main__":
    main()
