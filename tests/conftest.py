"""Shared test helpers."""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import pytest

from uwdock.dockcore import numerics

# The suite runs with the numerics `rl train` pins itself to (dockcore.numerics), set before
# NumPy, torch and numba load: a run trained in this process and one trained by the command in
# a process of its own are then the same bytes.
if not numerics.pin_before_loading() and numerics.applies():
    raise RuntimeError("NumPy was imported before tests/conftest.py could pin the numerics")


@dataclass
class CliResult:
    code: int
    out: str
    err: str


@pytest.fixture
def run_cli(capsys, monkeypatch) -> Callable[..., CliResult]:
    """Run a console entry point (e.g. ``markers.cli.main``) in-process with ``args``."""

    def run(main: Callable[[], None], *args: str) -> CliResult:
        monkeypatch.setattr(sys, "argv", ["prog", *map(str, args)])
        capsys.readouterr()
        try:
            main()
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        cap = capsys.readouterr()
        return CliResult(code, cap.out, cap.err)

    return run


BENCH_DIR = Path(__file__).resolve().parent.parent / "bench"


def load_bench(name: str, register: bool = False) -> ModuleType:
    """``bench/<name>.py`` imported as a module (the bench scripts are not a package), with
    ``bench/`` first on the import path while it loads, as when the script runs (it may import
    a sibling by name); ``register``: also as ``sys.modules[name]``."""
    spec = importlib.util.spec_from_file_location(name, BENCH_DIR / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    if register:
        sys.modules[name] = mod
    sys.path.insert(0, str(BENCH_DIR))
    try:
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(BENCH_DIR))
    return mod


def bench_module(name: str) -> Iterator[ModuleType]:
    """:func:`load_bench` registered, for the length of a fixture."""
    yield load_bench(name, register=True)
    sys.modules.pop(name, None)
