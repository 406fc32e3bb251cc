"""Provenance: what made an output folder (resolved config, git commit, package versions)."""

from __future__ import annotations

import datetime as _dt
import functools
import hashlib
import importlib.metadata
import os
import platform
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from uwdock.dockcore.config import dumps_toml, to_dict
from uwdock.dockcore.io import atomic_write_json, atomic_write_text

#: Distributions whose versions are recorded next to every output.
TRACKED_PACKAGES = (
    "uwdock",
    "numpy",
    "scipy",
    "opencv-python-headless",
    "trimesh",
    "manifold3d",
    "sapien",
    "gymnasium",
    "stable-baselines3",
    "torch",
    "open3d",
)

_REPO_ROOT = Path(__file__).resolve().parent.parent


def _git(repo: Path, *args: str) -> str | None:
    """``git -C repo ARGS``'s output, or None (no git, not a checkout, a failure)."""
    try:
        out = subprocess.run(
            ["git", "-C", str(repo), *args],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip()


def git_commit(repo: Path = _REPO_ROOT) -> dict[str, Any]:
    """The source tree's commit and whether it has uncommitted changes (``None`` outside git)."""
    commit = _git(repo, "rev-parse", "HEAD")
    status = _git(repo, "status", "--porcelain", "--untracked-files=no") if commit else None
    return {"commit": commit, "dirty": bool(status) if status is not None else None}


def source_state(repo: Path = _REPO_ROOT) -> tuple[str | None, str | None]:
    """The source tree's commit and a SHA-256 of its uncommitted changes to tracked files
    (``git diff HEAD``): equal for two readings when the code a command runs is the same."""
    diff = _git(repo, "diff", "HEAD")
    digest = hashlib.sha256(diff.encode()).hexdigest() if diff is not None else None
    return _git(repo, "rev-parse", "HEAD"), digest


_GIT_AT_START: dict[str, Any] | None = None


def git_commit_at_start() -> dict[str, Any]:
    """:func:`git_commit` as this process first read it, before it had written any record: its
    own outputs (a benchmark's partial results over a committed file, a second results file)
    must not mark its later records dirty."""
    global _GIT_AT_START
    if _GIT_AT_START is None:
        _GIT_AT_START = git_commit()
    return dict(_GIT_AT_START)


def package_versions(names: tuple[str, ...] = TRACKED_PACKAGES) -> dict[str, str | None]:
    """Installed versions of ``names`` (``None`` where not installed)."""
    out: dict[str, str | None] = {}
    for name in names:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    return out


#: Environment variables that change a run's floating-point results without changing its code
#: or config (which SIMD kernels NumPy, torch's MKL and ATen, and numba use; thread counts that
#: split reductions): :func:`numerics_env` records those set.
NUMERICS_ENV = (
    "NPY_DISABLE_CPU_FEATURES",
    "NPY_ENABLE_CPU_FEATURES",
    "MKL_CBWR",
    "MKL_ENABLE_INSTRUCTIONS",
    "ATEN_CPU_CAPABILITY",
    "NUMBA_CPU_NAME",
    "NUMBA_CPU_FEATURES",
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "OPENBLAS_CORETYPE",
    "MKL_DYNAMIC",
    "OMP_DYNAMIC",
    "UWDOCK_NUMERICS",  # "pinned": dockcore.numerics
)


def numerics_env(environ: Mapping[str, str] | None = None) -> dict[str, Any]:
    """What besides the CPU picks a run's arithmetic: the :data:`NUMERICS_ENV` variables set in
    ``environ`` (default ``os.environ``), and, when NumPy is already imported, the SIMD targets
    its dispatcher enabled on this CPU (``numpy_simd``; NumPy is not imported for it).

    Measured on one machine (docs/results/docking.md): the same training run gave
    the same evaluations with numba compiled for a generic x86-64 CPU and with ATen held to
    AVX2, but another run from 102,400 steps on with NumPy's AVX-512 kernels disabled, and
    another from the start with ``MKL_CBWR=COMPATIBLE``."""
    env = os.environ if environ is None else environ
    out: dict[str, Any] = {k: env[k] for k in NUMERICS_ENV if k in env}
    umath = sys.modules.get("numpy._core._multiarray_umath")
    features = getattr(umath, "__cpu_features__", None)
    dispatch = getattr(umath, "__cpu_dispatch__", None)
    if isinstance(features, dict) and dispatch is not None:
        out["numpy_simd"] = [str(t) for t in dispatch if features.get(t)]
    return out


def cpu_description(cpuinfo: str | os.PathLike[str] = "/proc/cpuinfo") -> dict[str, Any]:
    """The first CPU of ``cpuinfo`` (Linux's format): vendor, model name, family, model and
    stepping, and the SHA-256 (first 16 hex digits) of its sorted feature flags. NumPy, MKL and
    numba pick their kernels by the CPU's features (:func:`numerics_env`), so two runs of one
    recipe repeat bit for bit only where these agree. ``{}`` where the file cannot be read (not
    Linux). Read once per file and process (every record a process writes names the same CPU)."""
    return dict(_cpu_fields(str(cpuinfo)))


@functools.cache
def _cpu_fields(cpuinfo: str) -> tuple[tuple[str, str], ...]:
    try:
        text = Path(cpuinfo).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return ()
    fields: dict[str, str] = {}
    for line in text.splitlines():
        if not line.strip():
            if fields:
                break  # the first processor's block only
            continue
        key, sep, value = line.partition(":")
        if sep:
            fields.setdefault(key.strip(), value.strip())
    names = {
        "vendor_id": "vendor",
        "model name": "model_name",
        "cpu family": "family",
        "model": "model",
        "stepping": "stepping",
    }
    out = [(new, fields[old]) for old, new in names.items() if old in fields]
    flags = fields.get("flags") or fields.get("Features")  # x86 / arm64
    if flags:
        joined = " ".join(sorted(flags.split()))
        out.append(("flags_sha256", hashlib.sha256(joined.encode()).hexdigest()[:16]))
    return tuple(out)


def provenance(
    configs: Mapping[str, Any] | None = None, extra: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """A JSON-serialisable record of the configs, code version, packages and machine."""
    return {
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "git": git_commit_at_start(),
        "packages": package_versions(),
        "python": platform.python_version(),
        "machine": {
            "platform": platform.platform(),
            "processor": platform.machine(),
            "cpus": os.cpu_count(),
            "cpu": cpu_description(),
            "numerics": numerics_env(),
        },
        "config": {k: to_dict(v) for k, v in (configs or {}).items()},
        **(dict(extra) if extra else {}),
    }


def write_provenance(
    out_dir: str | os.PathLike[str],
    configs: Mapping[str, Any],
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Write ``config.toml`` (the resolved config) and ``provenance.json`` into ``out_dir``."""
    out_dir = Path(out_dir)
    record = provenance(configs, extra)
    atomic_write_text(out_dir / "config.toml", dumps_toml(dict(configs)))
    atomic_write_json(out_dir / "provenance.json", record)
    return record
