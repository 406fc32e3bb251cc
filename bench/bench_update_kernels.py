"""What the pinned numerics cost PPO's update, and which pins keep its bits.

Usage::

    python bench/bench_update_kernels.py [--config configs/realistic/policy.toml]
        [--repeats 5] [--threads 1,2] [--out-dir DIR] [--name update_kernels]

One row per (MKL code path, torch threads): a fresh process, pinned as ``rl train`` pins
itself (``uwdock.dockcore.numerics``) except for ``MKL_CBWR`` (``native``: unset, this CPU's
own kernels, none of the pin), builds the config's PPO model (its networks, batch size and
epochs) on its env, fills one rollout of ``n_steps x n_envs`` seeded random transitions and
times Stable-Baselines3's own ``PPO.train`` on it (one whole update: every epoch and
minibatch), ``--repeats`` times after one untimed update, each from the same starting weights,
optimiser state and minibatch order (NumPy's global seed, which the buffer shuffles with). It
reports the median and the spread in seconds, the ratio to the ``COMPATIBLE`` path on one
thread (MKL's SSE2 path, the pin before it ran MKL's AVX2 path), and the SHA-256 (first 12 hex
digits) of the weights after one update: a pinned path whose digest is the same for every
thread count gives the same bits whichever count a run uses.

Writes ``bench/results/<name>.json`` (rows, machine, commit).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from uwdock.dockcore.bench import format_table, save_results
from uwdock.dockcore.numerics import PINNED, pinned_environ

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "configs" / "realistic" / "policy.toml"
#: MKL code paths compared: the pin's SSE2 path, its AVX2 path (strict), this CPU's own.
PATHS = ("COMPATIBLE", "AVX2,STRICT", "native")

#: The child: one config, one thread count; prints one JSON line.
CHILD = r"""
import hashlib, json, statistics, sys, time
from pathlib import Path
import numpy as np, torch
from stable_baselines3.common.logger import configure
from uwdock.dockcore.config import load_config
from uwdock.rl.env.batch_env import BatchDockingEnv
from uwdock.rl.train.training import TrainConfig, build_model

config, threads, repeats = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
cfg = load_config(TrainConfig, config, section="train")
torch.manual_seed(0)
venv = BatchDockingEnv(cfg.env, cfg.n_envs)
model = build_model(cfg, venv, None)
model.set_logger(configure(None, []))
buf, rng = model.rollout_buffer, np.random.default_rng(0)
obs_dim, act_dim = venv.observation_space.shape[0], venv.action_space.shape[0]
n = cfg.n_envs
for _ in range(buf.buffer_size):
    buf.add(rng.normal(size=(n, obs_dim)).astype(np.float32),
            rng.uniform(-1, 1, size=(n, act_dim)).astype(np.float32),
            rng.normal(size=n).astype(np.float32), np.zeros(n, dtype=bool),
            torch.as_tensor(rng.normal(size=n), dtype=torch.float32),
            torch.as_tensor(rng.normal(size=n) - 3.0, dtype=torch.float32))
buf.compute_returns_and_advantage(torch.zeros(n), np.zeros(n, dtype=bool))
start = {k: v.clone() for k, v in model.policy.state_dict().items()}
torch.set_num_threads(threads)

def update():  # from the same weights, with a new optimiser: every update is the first
    model.policy.load_state_dict(start)
    np.random.seed(0)  # the rollout buffer shuffles its minibatches with NumPy's global RNG
    pol = model.policy
    pol.optimizer = pol.optimizer_class(pol.parameters(), lr=1e-4, **pol.optimizer_kwargs)
    model._current_progress_remaining = 1.0
    t0 = time.perf_counter()
    model.train()
    return time.perf_counter() - t0

update()
times = [update() for _ in range(repeats)]
digest = hashlib.sha256(b"".join(
    p.detach().numpy().tobytes() for p in model.policy.parameters())).hexdigest()[:12]
print(json.dumps({"times_s": times, "weights_sha256": digest,
                  "grad_steps": cfg.ppo.n_epochs * (buf.buffer_size * n // cfg.ppo.batch_size),
                  "torch_threads": torch.get_num_threads()}))
"""


def child_env(path: str) -> dict[str, str]:
    """The pinned environment with MKL's code path ``path`` (``native``: the pin's variables
    all unset, this CPU's kernels)."""
    if path == "native":
        return {k: v for k, v in os.environ.items() if k not in PINNED}
    return {**pinned_environ(), "MKL_CBWR": path}


def run_child(config: Path, path: str, threads: int, repeats: int) -> dict:
    res = subprocess.run(
        [sys.executable, "-c", CHILD, str(config), str(threads), str(repeats)],
        capture_output=True, text=True, env=child_env(path), cwd=ROOT, timeout=1800,
    )  # fmt: skip
    if res.returncode != 0:
        raise SystemExit(f"error: the update under MKL_CBWR={path}, {threads} threads failed: "
                         f"{(res.stderr.strip().splitlines() or ['?'])[-1]}")  # fmt: skip
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", type=Path, default=CONFIG)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", default="1,2", help="torch thread counts (comma)")
    ap.add_argument("--out-dir", type=Path, default=None)
    ap.add_argument("--name", default="update_kernels")
    args = ap.parse_args(argv)
    try:
        threads = [int(t) for t in args.threads.split(",")]
    except ValueError:
        raise SystemExit(
            f"error: --threads: comma-separated integers, got {args.threads!r}"
        ) from None
    if args.repeats < 1 or not threads or min(threads) < 1:
        raise SystemExit("error: --repeats and every --threads value must be at least 1")
    if not args.config.is_file():
        raise SystemExit(f"error: --config {args.config}: not a file")
    rows = []
    for path in PATHS:
        for t in threads:
            print(f"MKL_CBWR={path}, {t} torch threads ...", file=sys.stderr, flush=True)
            out = run_child(args.config, path, t, args.repeats)
            times = out["times_s"]
            rows.append({"mkl_cbwr": path, "threads": t,
                         "update_s": statistics.median(times),
                         "min_s": min(times), "max_s": max(times),
                         "grad_steps": out["grad_steps"],
                         "weights_sha256": out["weights_sha256"]})  # fmt: skip
    ref = [r for r in rows if r["mkl_cbwr"] == "COMPATIBLE" and r["threads"] == 1] or rows
    base = ref[0]["update_s"]
    for r in rows:
        r["vs_compatible_1_thread"] = base / r["update_s"]
    for path in PATHS:
        digests = {r["weights_sha256"] for r in rows if r["mkl_cbwr"] == path}
        for r in rows:
            if r["mkl_cbwr"] == path:
                r["same_bits_any_threads"] = len(digests) == 1
    print(format_table(rows, ["mkl_cbwr", "threads", "update_s", "min_s", "max_s",
                              "vs_compatible_1_thread", "weights_sha256",
                              "same_bits_any_threads"]))  # fmt: skip
    cfg_rel = args.config.resolve()
    cfg_rel = cfg_rel.relative_to(ROOT) if cfg_rel.is_relative_to(ROOT) else cfg_rel
    out = save_results(args.name, rows, {"config": str(cfg_rel), "repeats": args.repeats,
                                         "threads": threads, "pinned": dict(PINNED)},
                       out_dir=args.out_dir)  # fmt: skip
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
