"""Error-model hybrids for diagnosis: one model's detection table with another's error tables.

Usage::

    python bench/error_model_hybrid.py ERRORS.json DETECTION.json OUT.json [--cells R:N,...]

``OUT`` is ``ERRORS`` (its bias, covariance, outliers and AR(1) memory per range bin) with the
detection probabilities ``p_detect`` of ``DETECTION``: the whole table, or with ``--cells`` only
the cells named, ``R:N`` = range bin R (0.5 m bins from 0) and N markers in view (0, 1, 2, 3+),
e.g. ``1:1,2:1`` for one marker at 0.5-1.5 m. Every water table of the file is changed alike. The
output records both inputs' sha256 and the cells taken, under ``hybrid``. Used to separate which
part of a refitted model changed how fast a recipe learns (its records:
``bench/results/scratch_runs/error_model_hybrids/`` in the tag ``lab-notebook-2026-12``).
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from uwdock.dockcore.io import atomic_write_json
from uwdock.rl.error_model import load_error_model


def _cells(text: str | None) -> list[tuple[int, int]] | None:
    if not text:
        return None
    out = []
    for item in text.split(","):
        r, _, n = item.partition(":")
        out.append((int(r), int(n)))
    return out


def hybrid(errors: dict, detection: dict, cells: list[tuple[int, int]] | None) -> dict:
    """``errors`` with ``detection``'s p_detect (all cells, or ``cells``) in every table."""
    out = copy.deepcopy(errors)
    for water, table in out["tables"].items():
        src = detection["tables"][water]["p_detect"]
        if cells is None:
            table["p_detect"] = copy.deepcopy(src)
        else:
            for r, n in cells:
                table["p_detect"][r][n] = src[r][n]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("errors", type=Path)
    ap.add_argument("detection", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--cells", help="R:N,... cells of p_detect to take (default: all)")
    args = ap.parse_args()
    cells = _cells(args.cells)
    data = [json.loads(p.read_text(encoding="utf-8")) for p in (args.errors, args.detection)]
    out = hybrid(data[0], data[1], cells)
    out["hybrid"] = {
        "errors_from": str(args.errors),
        "errors_sha256": hashlib.sha256(args.errors.read_bytes()).hexdigest(),
        "detection_from": str(args.detection),
        "detection_sha256": hashlib.sha256(args.detection.read_bytes()).hexdigest(),
        "cells": "all" if cells is None else [list(c) for c in cells],
    }
    atomic_write_json(args.out, out)
    load_error_model(args.out)  # what rl train reads: refuse a broken result here
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
