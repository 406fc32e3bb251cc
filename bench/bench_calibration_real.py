"""Intrinsic calibration on real tank footage: does the answer depend on anything but the views?

Usage::

    python bench/bench_calibration_real.py [--real-dir ../shared/real] [--orders 3]

For every real set with a chessboard (the table ``SETS`` below: folder, inner corners), it runs
``calibration intrinsics`` as a user would (``calibrate_intrinsics``) with:

- the default (automatic corner method, leave-one-view-out cross-validation);
- classic corners with leave-one-view-out, 5 and 10 folds;
- the same views under ``--orders`` shuffled file names (links in a temporary folder): the
  spread of fx over the orders must be 0 for leave-one-view-out (folds do not depend on order);
- an independent reference: plain ``cv2.findChessboardCorners`` + ``cornerSubPix`` (11 px) +
  ``cv2.calibrateCamera`` on every view where the board is found, no rejection.

Each row gives fx, fy, cx, cy, the folds' jackknife uncertainty, the cross-validated error, the
views kept and rejected, and the wall time (median of ``--repeats`` runs). Writes
``bench/results/calibration_real.json`` (rows + machine, commit, packages). The frames are read
from ``--real-dir``; nothing is copied.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from uwdock.calibration.intrinsics import IntrinsicsConfig, calibrate_intrinsics, iter_views
from uwdock.dockcore.bench import format_table, save_results

ROOT = Path(__file__).resolve().parent.parent

#: Real sets with a chessboard: folder under --real-dir -> (inner corners cols, rows, note).
#: apl_sediment_tag36h11: 8 x 6 inner corners (its README; square size not stated, which does
#: not change K).
SETS = {"apl_sediment_tag36h11": (8, 6)}


def _row(label: str, res, wall_s: list[float]) -> dict:
    cam, unc, n = res.camera, res.uncertainty_frac(), res.counts()
    return {
        "run": label,
        "fx_px": round(cam.fx_px, 2),
        "fy_px": round(cam.fy_px, 2),
        "cx_px": round(cam.cx_px, 2),
        "cy_px": round(cam.cy_px, 2),
        "fx_unc_%": round(100 * unc["fx_px"], 3),
        "fy_unc_%": round(100 * unc["fy_px"], 3),
        "cx_unc_%": round(100 * unc["cx_px"], 3),
        "cy_unc_%": round(100 * unc["cy_px"], 3),
        "rms_px": round(cam.rms_px or 0.0, 4),
        "cv_rms_px": round(res.cv_rms_px, 4),
        "cv": res.cv.scheme,
        "views": n["calibration"],
        "outliers": n["rejected_by_reason"].get("outlier", 0),
        "rejected": n["rejected"],
        "corners": (res.corner_methods or {}).get("chosen", res.config.corner_method),
        "warnings": sum(x.startswith("warning") for x in res.notes),
        "wall_s": round(statistics.median(wall_s), 2),
    }


def _timed(source, cfg, repeats: int):
    walls, res = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = calibrate_intrinsics(source, cfg)
        walls.append(time.perf_counter() - t0)
    return res, walls


def _reference(folder: Path, cols: int, rows: int) -> dict:
    """Plain OpenCV on every view where the classic finder sees the board."""
    obj = np.zeros((cols * rows, 3), np.float32)
    obj[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2)
    objs, imgs, size = [], [], None
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
    for _, grey in iter_views(folder)[1]:
        if grey is None:
            continue
        size = (grey.shape[1], grey.shape[0])
        ok, c = cv2.findChessboardCorners(grey, (cols, rows))
        if ok:
            objs.append(obj)
            imgs.append(cv2.cornerSubPix(grey, c, (11, 11), (-1, -1), crit))
    rms, K, *_ = cv2.calibrateCamera(objs, imgs, size, None, None)
    return {
        "run": "reference: plain OpenCV, all views",
        "fx_px": round(float(K[0, 0]), 2),
        "fy_px": round(float(K[1, 1]), 2),
        "cx_px": round(float(K[0, 2]), 2),
        "cy_px": round(float(K[1, 2]), 2),
        "rms_px": round(float(rms), 4),
        "views": len(objs),
    }


def _shuffled(folder: Path, tmp: Path, seed: int) -> Path:
    """The folder's images under shuffled names (symbolic links), so the input order changes."""
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    order = np.random.default_rng(seed).permutation(len(files))
    out = tmp / f"order{seed}"
    out.mkdir()
    for k, i in enumerate(order):
        (out / f"v{k:03d}{files[i].suffix}").symlink_to(files[i].resolve())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--real-dir", type=Path, default=ROOT.parent / "shared" / "real")
    ap.add_argument("--orders", type=int, default=3, help="shuffled input orders [3]")
    ap.add_argument("--repeats", type=int, default=3, help="timing runs per row [3]")
    args = ap.parse_args()
    rows: list[dict] = []
    for name, (cols, rows_) in SETS.items():
        folder = args.real_dir / name
        if not folder.is_dir():
            print(f"skip {name}: {folder} not found", file=sys.stderr)
            continue
        base = IntrinsicsConfig(cols=cols, rows=rows_)
        classic = dataclasses.replace(base, corner_method="classic")
        runs = [
            ("default (auto corners, leave-one-out)", base, args.repeats),
            ("classic, leave-one-out", classic, args.repeats),
            ("classic, 5 folds", dataclasses.replace(classic, cv_folds=5), 1),
            ("classic, 10 folds", dataclasses.replace(classic, cv_folds=10), 1),
        ]
        for label, cfg, repeats in runs:
            res, walls = _timed(folder, cfg, repeats)
            rows.append({"set": name, **_row(label, res, walls)})
            print(f"{name}: {label}: fx {res.camera.fx_px:.2f}", file=sys.stderr, flush=True)
            if label.startswith("default"):
                for note in res.notes:
                    print(f"  note: {note}", file=sys.stderr)
        with tempfile.TemporaryDirectory() as tmp:
            for seed in range(args.orders):
                src = _shuffled(folder, Path(tmp), seed)
                res, walls = _timed(src, classic, 1)
                rows.append(
                    {"set": name, **_row(f"classic, leave-one-out, order {seed}", res, walls)}
                )
        rows.append({"set": name, **_reference(folder, cols, rows_)})
    cols_ = ["set", "run", "fx_px", "fy_px", "cx_px", "cy_px", "fx_unc_%", "fy_unc_%", "rms_px",
             "cv_rms_px", "views", "outliers", "corners", "warnings", "wall_s"]  # fmt: skip
    print(format_table(rows, cols_))
    path = save_results(
        "calibration_real",
        rows,
        {"real_dir": str(args.real_dir), "orders": args.orders, "repeats": args.repeats},
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
