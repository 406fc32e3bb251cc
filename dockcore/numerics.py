"""Pinned numerics: one training seed, the same weights on any x86-64 CPU with AVX2 and FMA.

NumPy, torch (MKL's matrix products, ATen's vector kernels) and numba pick their kernels by the
CPU they run on, and kernels of different vector widths round differently: the same seed and
config trained on two CPU kinds part after ~100k steps (``bench/bench_numerics.py``,
docs/results/docking.md). A *pinned* process holds each library to kernels every such CPU
runs the same way:

==============================  ==========================================================
``NPY_DISABLE_CPU_FEATURES``    NumPy's dispatched SIMD targets off: its baseline loops
                                (x86-64-v2) only
``MKL_CBWR=AVX2,STRICT``        MKL's AVX2 code path on every CPU that has AVX2, in strict
                                conditional numerical reproducibility: its matrix products
                                give the same bits with any thread count (oneMKL developer
                                guide, "Reproducibility Conditions"); ``COMPATIBLE`` (SSE2)
                                on a CPU without AVX2
``OPENBLAS_CORETYPE=Haswell``   the OpenBLAS that NumPy and SciPy bundle (their matrix
                                products, small ones included, and LAPACK) on its AVX2
                                kernels on every CPU that has AVX2 and FMA, not the AVX-512
                                ones it picks where they exist; ``Prescott`` (SSE3) on a CPU
                                without them
``ATEN_CPU_CAPABILITY=default`` torch's ATen without its AVX2/AVX-512 kernels
``NUMBA_CPU_NAME=generic``      numba compiles for a generic x86-64 CPU, not this one
``*_NUM_THREADS=1``             no reduction split over a CPU-dependent thread count (a
``*_DYNAMIC=FALSE``             run sets torch's threads itself: ``ppo.update_threads``)
==============================  ==========================================================

The variables are read when the libraries load, so a process pins itself by starting again
with them (:func:`ensure`, an ``exec`` before any work); worker processes inherit them
and Ray actors are given them (:func:`pinned_env_vars`). Provenance records them
(``dockcore.provenance.numerics_env``) with :data:`MARK`.

Why AVX2 and not MKL's SSE2 path on every CPU: the SSE2 path makes the recipe's PPO update
(two 64-unit layers) 1.2x slower on one thread here, 1.5x against the AVX2 path on the
recipe's two threads (``bench/bench_update_kernels.py``), and the pin already holds only
among CPUs with FMA, since the C library's own ``exp``/``log`` (glibc picks an FMA variant on
CPUs that have it) are not pinned; every x86-64 CPU with FMA has AVX2 (Intel since 2013, AMD
since 2015). A CPU without them trains its own weights; its provenance says so.
"""

from __future__ import annotations

import os
import platform
import sys
from collections.abc import Mapping
from typing import NoReturn

from uwdock.dockcore.cli import runs_program_command

#: The variable a pinned process carries (value ``"pinned"``), so it is not started again.
MARK = "UWDOCK_NUMERICS"

#: NumPy 2.x's dispatch targets on x86-64 above its x86-64-v2 baseline.
_NUMPY_TARGETS = "X86_V3 X86_V4 AVX512_ICL AVX512_SPR"


def cpu_flags(cpuinfo: str = "/proc/cpuinfo") -> frozenset[str]:
    """The first CPU's feature flags in ``cpuinfo`` (Linux's format); empty where it cannot be
    read."""
    try:
        with open(cpuinfo, encoding="utf-8", errors="replace") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() == "flags":
                    return frozenset(value.split())
    except OSError:
        pass
    return frozenset()


def mkl_branch(flags: frozenset[str]) -> str:
    """MKL's reproducible code path for a CPU with ``flags`` (module docstring)."""
    return "AVX2,STRICT" if {"avx2", "fma"} <= flags else "COMPATIBLE"


def openblas_core(flags: frozenset[str]) -> str:
    """The OpenBLAS core whose kernels a CPU with ``flags`` runs (module docstring): its
    choice for the first CPUs with AVX2 and FMA, which every such CPU runs the same way."""
    return "Haswell" if {"avx2", "fma"} <= flags else "Prescott"


#: What a pinned process runs with (module docstring).
PINNED: dict[str, str] = {
    "NPY_DISABLE_CPU_FEATURES": _NUMPY_TARGETS,
    "MKL_CBWR": mkl_branch(cpu_flags()),
    "OPENBLAS_CORETYPE": openblas_core(cpu_flags()),
    "ATEN_CPU_CAPABILITY": "default",
    "NUMBA_CPU_NAME": "generic",
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_DYNAMIC": "FALSE",
    "OMP_DYNAMIC": "FALSE",
    MARK: "pinned",
}

#: Variables that would pick kernels against the pin (NumPy refuses ENABLE with DISABLE).
_UNSET = ("NPY_ENABLE_CPU_FEATURES", "MKL_ENABLE_INSTRUCTIONS", "NUMBA_CPU_FEATURES")


def applies() -> bool:
    """Whether pinning applies here: x86-64 (the names above are x86's)."""
    return platform.machine().lower() in ("x86_64", "amd64")


def pinned_env_vars() -> dict[str, str]:
    """The variables a pinned worker needs (a Ray actor's ``runtime_env``); {} off x86-64."""
    return dict(PINNED) if applies() else {}


def pinned_environ(environ: Mapping[str, str] | None = None) -> dict[str, str]:
    """``environ`` (default ``os.environ``) with the pin applied."""
    env = dict(os.environ if environ is None else environ)
    for key in _UNSET:
        env.pop(key, None)
    env.update(pinned_env_vars())
    return env


def is_pinned(environ: Mapping[str, str] | None = None) -> bool:
    """Whether a process with ``environ`` runs pinned (off x86-64: always, nothing to pin)."""
    env = os.environ if environ is None else environ
    if not applies():
        return True
    return all(env.get(k) == v for k, v in PINNED.items()) and not any(k in env for k in _UNSET)


def native_environ(environ: Mapping[str, str] | None = None) -> dict[str, str]:
    """``environ`` without the variables a pin set (those of a process that carries
    :data:`MARK`; a user's own settings are kept in a process that does not)."""
    env = dict(os.environ if environ is None else environ)
    if env.get(MARK) == "pinned":
        for key, value in PINNED.items():
            if env.get(key) == value:
                del env[key]
    return env


def ensure(mode: str) -> None:
    """Make this process run with numerics ``mode`` (``"pinned"`` or ``"native"``): start it
    again with the variables changed when they are not already so (before any work: the
    libraries read them when they load). Only a command run as its process's program
    (``dockcore.cli.runs_program_command``) is started again; an in-process call runs with the
    numerics its process has (provenance records which). Off x86-64 nothing is pinned."""
    if mode not in ("pinned", "native"):
        raise ValueError(f"numerics mode {mode!r}: pinned or native")
    if not applies() or not runs_program_command():
        return  # a library's or a test's call: its process is not ours to start again
    if mode == "pinned" and not is_pinned():
        _restart(pinned_environ())
    if mode == "native" and os.environ.get(MARK) == "pinned":
        _restart(native_environ())


def recorded_mode(numerics: Mapping[str, object] | None) -> str:
    """The mode a run was trained with, from its provenance's ``machine.numerics``: pinned
    when it carries :data:`MARK`, else native (runs from before pinning included)."""
    return (
        "pinned" if isinstance(numerics, Mapping) and numerics.get(MARK) == "pinned" else "native"
    )


def _restart(environ: dict[str, str]) -> NoReturn:
    argv = list(getattr(sys, "orig_argv", None) or [sys.executable, *sys.argv])
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *argv[1:]], environ)


def pin_before_loading() -> bool:
    """Pin this process by setting its variables, for a process whose numerical libraries have
    not loaded yet (a test runner's start, before NumPy, torch or numba is imported); returns
    whether it could (False once NumPy is imported: the setting would come too late)."""
    if "numpy" in sys.modules or not applies():
        return False
    for key in _UNSET:
        os.environ.pop(key, None)
    os.environ.update(pinned_env_vars())
    return True
