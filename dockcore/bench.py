"""Benchmark plumbing: time a function several times, print a table, write JSON with provenance.

Benchmarks are scripts under ``bench/`` (never timed tests). Each records the median and spread
of several runs after a warm-up, the machine and the git commit, and writes
``bench/results/<name>.json`` atomically.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from uwdock.dockcore.io import atomic_write_json
from uwdock.dockcore.provenance import provenance

RESULTS_DIR = Path(__file__).resolve().parent.parent / "bench" / "results"


def time_call(
    fn: Callable[[], Any], repeats: int = 5, warmup: int = 1, inner: int = 1
) -> dict[str, float]:
    """Median/min/max wall time of ``fn`` in milliseconds per call.

    Args:
        fn: the work to time.
        repeats: timed runs (the median is reported).
        warmup: untimed runs first.
        inner: calls per timed run (for sub-millisecond work); times are divided by it.
    """
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        samples.append((time.perf_counter() - t0) * 1e3 / inner)
    return {
        "median_ms": statistics.median(samples),
        "min_ms": min(samples),
        "max_ms": max(samples),
        "repeats": repeats,
    }


def format_table(rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> str:
    """A plain-text table of ``rows`` (dicts) restricted to ``columns``."""

    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"
        return str(v)

    cells = [[fmt(r.get(c, "")) for c in columns] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(columns)]
    line = "  ".join(c.ljust(w) for c, w in zip(columns, widths, strict=True))
    sep = "  ".join("-" * w for w in widths)
    body = ["  ".join(v.ljust(w) for v, w in zip(row, widths, strict=True)) for row in cells]
    return "\n".join([line, sep, *body])


def save_results(
    name: str,
    rows: Sequence[dict[str, Any]],
    config: dict[str, Any] | None = None,
    out_dir: Path | None = None,
) -> Path:
    """Write ``rows`` with provenance (machine, commit, packages) to ``<out_dir>/<name>.json``."""
    path = (out_dir or RESULTS_DIR) / f"{name}.json"
    record = provenance(extra={"benchmark": name, "bench_config": config or {}, "rows": list(rows)})
    atomic_write_json(path, record)
    return path
