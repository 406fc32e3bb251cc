"""Does this machine train the shipped policy's run, and which library's arithmetic decides it?

Usage::

    python bench/bench_numerics.py [--steps 151552] [--seed 0] [--batch-workers 2]
        [--config configs/realistic/policy.toml]
        [--reference rl/policies/realistic_ppo/eval_history.jsonl]
        [--switches default,NUMBA_CPU_NAME=generic,...] [--work DIR] [--name numerics]

Trains the first ``--steps`` of the shipped recipe (the seed the shipped policy was trained
with) once per *switch*, each an environment variable that changes which kernels a
library runs without changing the code or the config (``default``: none set):

* ``NUMBA_CPU_NAME=generic``: numba compiles the simulator's kernels for a generic x86-64 CPU
  instead of this one;
* ``ATEN_CPU_CAPABILITY=avx2``: torch's own vector kernels (ATen) held to AVX2;
* ``NPY_DISABLE_CPU_FEATURES=X86_V4 AVX512_ICL``: NumPy's AVX-512 kernels off (its AVX2 ones
  and scalar loops instead);
* ``MKL_CBWR=COMPATIBLE``: MKL (torch's matrix products on x86) in its CPU-independent mode.

A run's periodic evaluations (``eval_history.jsonl``: mean return over the same 30 episodes,
every 25k steps) are compared with the reference run's, written where the shipped policy was
trained, and with this machine's ``default`` run: the table gives for each switch the last
step up to which every evaluation equals the reference's (or the default's) to the last digit
(``-`` where the first one already differs). A machine that repeats the reference to the last
evaluation trains the shipped weights; a switch that moves where the runs part names a library
whose kernels the run's arithmetic depends on.

Each run is ``rl train`` in a fresh process (the variables are read when the libraries load),
its run folder in ``--work`` (a temporary folder by default). Writes
``bench/results/<name>.json`` (rows, each with the evaluations and the run's provenance, which
records the variables set: ``machine.numerics``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from uwdock.dockcore.bench import format_table, save_results

ROOT = Path(__file__).resolve().parent.parent

SWITCHES = (
    "default",
    "NUMBA_CPU_NAME=generic",
    "ATEN_CPU_CAPABILITY=avx2",
    "NPY_DISABLE_CPU_FEATURES=X86_V4 AVX512_ICL",
    "MKL_CBWR=COMPATIBLE",
)
CONFIG = ROOT / "configs" / "realistic" / "policy.toml"
REFERENCE = ROOT / "rl" / "policies" / "realistic_ppo" / "eval_history.jsonl"


def read_history(path: Path) -> list[tuple[int, float]]:
    """(step, mean return) of each evaluation in an ``eval_history.jsonl``."""
    out = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            if line.strip():
                row = json.loads(line)
                out.append((int(row["step"]), float(row["mean_return"])))
    return out


def agrees_through(run: list[tuple[int, float]], ref: list[tuple[int, float]]) -> int | None:
    """The last step up to which every evaluation of ``run`` equals ``ref``'s exactly (None
    when the first differs); only the steps both have are compared."""
    last = None
    for (s, v), (s_ref, v_ref) in zip(run, ref, strict=False):
        if s != s_ref or v != v_ref:
            break
        last = s
    return last


def parse_switch(text: str) -> dict[str, str]:
    if text == "default":
        return {}
    name, sep, value = text.partition("=")
    if not sep or not name.isidentifier():
        raise SystemExit(f"error: --switches: {text!r} is not 'default' or NAME=VALUE")
    return {name: value}


def train(
    switch: str, a: argparse.Namespace, work: Path, index: int
) -> tuple[list[tuple[int, float]], dict, float]:
    run = work / f"run{index}"
    env = {k: v for k, v in os.environ.items() if k not in _switch_names(a.switches)}
    env.update(parse_switch(switch))
    cmd = [
        str(Path(sys.executable).parent / "rl"), "train", "--config", str(a.config),
        "--seed", str(a.seed), "--steps", str(a.steps), "--batch-workers", str(a.batch_workers),
        "--out", str(run),
    ]  # fmt: skip
    t0 = time.perf_counter()
    done = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["no output"]
        raise SystemExit(f"error: the run with {switch} failed: {tail[0]}")
    prov = json.loads((run / "provenance.json").read_text(encoding="utf-8"))
    return read_history(run / "eval_history.jsonl"), prov, wall


def _switch_names(switches: list[str]) -> set[str]:
    return {n for s in switches for n in parse_switch(s)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--config", type=Path, default=CONFIG)
    p.add_argument("--reference", type=Path, default=REFERENCE)
    p.add_argument("--steps", type=int, default=151_552, help="training steps per run")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch-workers", type=int, default=2)
    p.add_argument("--switches", default=",".join(SWITCHES))
    p.add_argument("--work", type=Path, help="where the run folders go [a temporary folder]")
    p.add_argument("--name", default="numerics")
    p.add_argument("--out-dir", type=Path)
    a = p.parse_args()
    a.switches = [s.strip() for s in a.switches.split(",") if s.strip()]
    if not a.switches:
        raise SystemExit("error: --switches: none given")
    if a.steps <= 0:
        raise SystemExit(f"error: --steps must be positive, got {a.steps}")
    _switch_names(a.switches)  # refuses a malformed one before any run
    try:
        ref = read_history(a.reference)
    except (OSError, ValueError, KeyError) as exc:
        raise SystemExit(f"error: --reference {a.reference}: {exc}") from None
    with tempfile.TemporaryDirectory(prefix="uwdock-numerics-") as tmp:
        work = a.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        runs = []
        for i, switch in enumerate(a.switches):
            print(f"[{i + 1}/{len(a.switches)}] {a.steps:,} steps with {switch} ...", flush=True)
            runs.append((switch, *train(switch, a, work, i)))
    default = next((h for s, h, _, _ in runs if s == "default"), None)
    rows = []
    for switch, hist, prov, wall in runs:
        rows.append(
            {
                "switch": switch,
                "evaluations": len(hist),
                "agrees_with_reference_through_step": agrees_through(hist, ref),
                "agrees_with_default_through_step": (
                    agrees_through(hist, default) if default is not None else None
                ),
                "mean_returns": [v for _, v in hist],
                "steps": [s for s, _ in hist],
                "wall_s": wall,
                "cpu": prov.get("machine", {}).get("cpu"),
                "numerics": prov.get("machine", {}).get("numerics"),
                "git": prov.get("git"),
            }
        )
    table = [
        {
            "switch": r["switch"],
            "= reference through": r["agrees_with_reference_through_step"] or "-",
            "= default through": r["agrees_with_default_through_step"] or "-",
            "last return": r["mean_returns"][-1] if r["mean_returns"] else "",
            "wall_s": r["wall_s"],
        }
        for r in rows
    ]
    print(format_table(table, list(table[0])))
    print(f"reference: {a.reference} (steps {[s for s, _ in ref][: len(rows[0]['steps'])]})")
    bench_cfg = {
        "config": str(a.config),
        "reference": str(a.reference),
        "reference_mean_returns": [v for _, v in ref],
        "steps": a.steps,
        "seed": a.seed,
        "batch_workers": a.batch_workers,
        "switches": a.switches,
    }
    print("wrote", save_results(a.name, rows, bench_cfg, a.out_dir))


if __name__ == "__main__":
    main()
