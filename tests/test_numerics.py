"""Pinned numerics (issue 53): ``rl train`` runs with NumPy, MKL, ATen and numba held to
kernels every x86-64 CPU runs alike, so a seed gives the same weights whatever SIMD the CPU
offers; the setting is recorded and a resumed run keeps its own."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.hostile_runs import ROOT
from uwdock.dockcore import numerics as N

pytestmark = pytest.mark.skipif(not N.applies(), reason="the pin is x86-64's")

TINY = """\
n_envs = 4
simulator = "batched"
total_steps = 64
checkpoint_every = 64
eval_every = 0
[env]
episode_s = 3.0
[ppo]
n_steps = 16
batch_size = 64
n_epochs = 1
"""


def test_an_in_process_call_is_never_started_again(monkeypatch):
    """A library's or a test's call (no command run as its process's program) keeps its
    process: ``ensure`` would otherwise replace the caller (a test runner) by the command."""
    monkeypatch.setattr(N.os, "execve", lambda *a: pytest.fail("the caller was replaced"))
    N.ensure("pinned")
    N.ensure("native")


def test_the_pinned_environment_overrides_what_would_pick_other_kernels():
    env = {"NPY_ENABLE_CPU_FEATURES": "X86_V3", "NPY_DISABLE_CPU_FEATURES": "X86_V4",
           "MKL_CBWR": "AVX512", "OMP_NUM_THREADS": "8", "HOME": "/root"}  # fmt: skip
    pinned = N.pinned_environ(env)
    assert "NPY_ENABLE_CPU_FEATURES" not in pinned and pinned["HOME"] == "/root"
    assert {k: pinned[k] for k in N.PINNED} == N.PINNED
    assert N.is_pinned(pinned) and not N.is_pinned(env)
    native = N.native_environ(pinned)
    assert not any(k in native for k in N.PINNED) and native["HOME"] == "/root"
    # a user's own setting in a process that was never pinned is theirs
    assert N.native_environ(env) == env
    assert N.recorded_mode({N.MARK: "pinned"}) == "pinned"
    assert N.recorded_mode({}) == N.recorded_mode(None) == "native"


def test_mkl_runs_its_avx2_path_where_the_cpu_has_avx2_and_fma(tmp_path):
    """MKL's code path follows the CPU's flags: AVX2 in strict reproducibility where AVX2 and
    FMA are there (the same bits with any thread count), its SSE2 path elsewhere."""
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx avx2 fma bmi2\n\nflags : x\n")
    assert N.cpu_flags(str(info)) >= {"avx2", "fma", "sse2"}
    assert N.mkl_branch(N.cpu_flags(str(info))) == "AVX2,STRICT"
    info.write_text("processor\t: 0\nflags\t\t: fpu sse2 sse4_2 avx\n")
    assert N.mkl_branch(N.cpu_flags(str(info))) == "COMPATIBLE"
    assert N.mkl_branch(frozenset({"avx2"})) == "COMPATIBLE"  # AVX2 without FMA: not pinned to it
    assert N.cpu_flags(str(tmp_path / "absent")) == frozenset()
    info.write_bytes(b"flags : avx2 fma \xff\n")  # not UTF-8: read, not refused
    assert N.mkl_branch(N.cpu_flags(str(info))) == "AVX2,STRICT"
    assert N.PINNED["MKL_CBWR"] == N.mkl_branch(N.cpu_flags())
    assert N.PINNED["MKL_DYNAMIC"] == N.PINNED["OMP_DYNAMIC"] == "FALSE"


def test_openblas_runs_its_avx2_kernels_where_the_cpu_has_avx2_and_fma():
    assert N.openblas_core(frozenset({"sse2", "avx", "avx2", "fma", "avx512f"})) == "Haswell"
    assert N.openblas_core(frozenset({"sse2", "avx", "avx2"})) == "Prescott"
    assert N.openblas_core(frozenset()) == "Prescott"
    assert N.PINNED["OPENBLAS_CORETYPE"] == N.openblas_core(N.cpu_flags())


_PRODUCTS = """import hashlib, sys
from uwdock.dockcore import numerics
if sys.argv[1] == "pinned":
    numerics.pin_before_loading()
import numpy as np
rng, h = np.random.default_rng(0), hashlib.sha256()
for _ in range(300):  # NumPy's products through its OpenBLAS, the small ones of a step included
    R, v, M, N = (rng.normal(size=s) for s in ((3, 3), (3,), (40, 30), (30, 20)))
    h.update((R @ v).tobytes() + (M @ N).tobytes() + np.linalg.pinv(M).tobytes())
print(h.hexdigest())
"""


def _products(mode: str, coretype: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k not in N.PINNED}
    if coretype is not None:
        env["OPENBLAS_CORETYPE"] = coretype
    res = subprocess.run([sys.executable, "-c", _PRODUCTS, mode], capture_output=True,
                         text=True, timeout=120, cwd=ROOT, env=env)  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    return res.stdout.strip()


@pytest.mark.skipif(N.PINNED.get("OPENBLAS_CORETYPE") != "Haswell", reason="an AVX2 CPU's pin")
def test_the_pin_holds_numpys_openblas_to_one_kernel_set():
    """NumPy's matrix products, 3x3 ones included, round by the OpenBLAS kernels it picks for
    the CPU (an older CPU's, here ``Prescott``'s, give other bits): pinned, a process runs the
    AVX2 kernels whatever the CPU or the environment would have picked."""
    assert _products("native", "Prescott") != _products("native", "Haswell")  # the control
    assert (
        _products("pinned", "Prescott")
        == _products("pinned", None)
        == _products("native", "Haswell")
    )


def _train(out: Path, config: Path, *args: object, env: dict | None = None, timeout: int = 600):
    """``rl train`` through the console script, as a user runs it (a process that is the
    command's own program: one it may start again pinned)."""
    script = Path(sys.executable).with_name("rl")
    if not script.exists():
        pytest.skip("the rl console script is not installed next to this Python")
    return subprocess.run(
        [script, "train", "--config", config, "--out", out, *map(str, args)],
        capture_output=True, text=True, timeout=timeout, cwd=ROOT,
        env={**{k: v for k, v in os.environ.items() if k not in N.PINNED}, **(env or {})},
    )  # fmt: skip


def _numerics(run: Path) -> dict:
    return json.loads((run / "provenance.json").read_text())["machine"]["numerics"]


@pytest.mark.slow  # a real training run (~15 s): in the slow set, run in CI
def test_a_training_run_pins_itself_and_records_it(tmp_path):
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(TINY)
    res = _train(tmp_path / "run", cfg)
    assert res.returncode == 0, res.stderr[-2000:]
    rec = _numerics(tmp_path / "run")
    assert {k: rec.get(k) for k in N.PINNED} == N.PINNED
    assert rec["numpy_simd"] == []  # NumPy ran its baseline loops only
    # --numerics native: this CPU's kernels, recorded as such; a resume keeps them
    res = _train(tmp_path / "native", cfg, "--numerics", "native")
    assert res.returncode == 0, res.stderr[-2000:]
    assert N.MARK not in _numerics(tmp_path / "native")
    assert _numerics(tmp_path / "native")["numpy_simd"] != []


def _weights(run: Path) -> str:
    return hashlib.sha256((run / "weights.npz").read_bytes()).hexdigest()


@pytest.mark.slow  # ~7 min: four runs of the shipped recipe's first 151,552 steps
def test_two_cpu_feature_sets_train_the_same_weights_when_pinned(tmp_path):
    """The shipped recipe's config for 151,552 steps (its DAgger warm start, the critic alone,
    then PPO; 37 rollouts of 64 envs, six evaluations), seed 2, as on this CPU and as with
    NumPy's dispatched SIMD kernels and torch's ATen vector kernels off (those of an x86-64 CPU
    without AVX2): with the pin, the weights are the same bytes; without it (the control), they
    differ. Measured on this machine (a Zen 3) with the earlier two-stage recipe: NumPy's
    kernels alone did not change its weights, ATen's did (its tanh and exp round otherwise). On
    a Zen 4, with and without NumPy's AVX-512 kernels, the runs parted after 102,400 steps
    (docs/changelog.md)."""
    config = ROOT / "configs" / "realistic" / "policy.toml"
    args = ("--steps", 151552, "--seed", 2, "--batch-workers", 2)
    no_avx2 = {"NPY_DISABLE_CPU_FEATURES": N.PINNED["NPY_DISABLE_CPU_FEATURES"],
               "ATEN_CPU_CAPABILITY": "default"}  # fmt: skip
    runs = {}
    for numerics in ("pinned", "native"):
        for name, env in (("all", {}), ("none", no_avx2)):
            run = tmp_path / f"{numerics}_{name}"
            res = _train(run, config, *args, "--numerics", numerics, env=env, timeout=900)
            assert res.returncode == 0, res.stderr[-2000:]
            runs[numerics, name] = run
    simd = {k: _numerics(run)["numpy_simd"] for k, run in runs.items()}
    assert simd["native", "none"] == [] != simd["native", "all"]  # two kernel sets
    assert simd["pinned", "all"] == simd["pinned", "none"] == []
    assert _weights(runs["native", "all"]) != _weights(runs["native", "none"])
    assert _weights(runs["pinned", "all"]) == _weights(runs["pinned", "none"])
