"""How well the simulator renders each 3DBM construction: marker recall on rendered frames.

For each marker style (``solid``, ``published``) the DS marker set is generated
(``markers generate --style``), a labelled dataset is rendered from random AUV poses
(``datasets synth``: clear tank, 480 px, seed 0, the same poses for both styles) and the
rendered-3DBM detector (:func:`perception.detector.rendered_3dbm_config`) runs on every frame.
Recall = decoded markers that the labels call visible / markers the labels call visible; a
decoded ID the labels do not call visible counts as a false ID.

Usage::

    python bench/bench_marker_styles.py [--frames 20] [--width 480] [--water clear_tank]

Prints a table and writes ``bench/results/marker_styles.json`` (config, per-style counts,
provenance).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2

ROOT = Path(__file__).resolve().parents[1]

from uwdock.datasets import cli as datasets_cli  # noqa: E402
from uwdock.dockcore.io import atomic_write_json  # noqa: E402
from uwdock.dockcore.provenance import provenance  # noqa: E402
from uwdock.markers import cli as markers_cli  # noqa: E402
from uwdock.perception.detector import Detector, rendered_3dbm_config  # noqa: E402
from uwdock.perception.groundtruth import load_labels  # noqa: E402

STYLES = ("solid", "published")


def _run(main, *args: str) -> None:
    """Run a console entry point in-process with ``args``; raise on a non-zero exit."""
    sys.argv = ["prog", *args]
    try:
        main()
    except SystemExit as exc:
        if exc.code:
            raise RuntimeError(f"{' '.join(args)}: exit {exc.code}") from None


def measure_style(style: str, work: Path, frames: int, width: int, water: str, seed: int) -> dict:
    """Generate the style's set, render ``frames`` labelled frames and count detections."""
    mdir, sdir = work / f"markers_{style}", work / f"synth_{style}"
    _run(markers_cli.main, "generate", "--style", style, "--out", str(mdir), "--quiet")
    t0 = time.perf_counter()
    _run(
        datasets_cli.main, "synth", "--n", str(frames), "--water", water, "--width", str(width),
        "--seed", str(seed), "--markers", str(mdir / "markerset.toml"), "--out", str(sdir),
        "--quiet",
    )  # fmt: skip
    render_s = time.perf_counter() - t0
    labels = load_labels(sdir / "labels.jsonl")
    det = Detector(rendered_3dbm_config())
    visible = decoded = false_ids = 0
    per_frame = []
    for idx in sorted(labels):
        truth = labels[idx]
        img = cv2.imread(str(sdir / str(truth.image)), cv2.IMREAD_COLOR)
        seen = {m.marker_id for m in truth.markers if m.visible}
        found = {d.marker_id for d in det.detect(img)}
        visible += len(seen)
        decoded += len(found & seen)
        false_ids += len(found - {m.marker_id for m in truth.markers if m.in_image})
        per_frame.append({"frame": idx, "visible": len(seen), "decoded": len(found & seen)})
    return {
        "style": style,
        "frames": frames,
        "visible": visible,
        "decoded": decoded,
        "recall": decoded / visible if visible else None,
        "false_ids": false_ids,
        "render_s": render_s,
        "per_frame": per_frame,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--width", type=int, default=480)
    ap.add_argument("--water", default="clear_tank")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=ROOT / "bench/results/marker_styles.json")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="uwdock_styles_") as tmp:
        for style in STYLES:
            print(f"[{style}] generating, rendering {args.frames} frames ...", flush=True)
            rows.append(measure_style(style, Path(tmp), args.frames, args.width, args.water,
                                      args.seed))  # fmt: skip
    print(f"\n{'style':<10} {'visible':>8} {'decoded':>8} {'recall':>7} {'false IDs':>9}")
    for r in rows:
        print(f"{r['style']:<10} {r['visible']:>8} {r['decoded']:>8} {r['recall']:>7.2f} "
              f"{r['false_ids']:>9}")  # fmt: skip
    config = {k: getattr(args, k) for k in ("frames", "width", "water", "seed")}
    atomic_write_json(args.out, {"rows": rows, "config": config,
                                 "provenance": provenance({"bench": config})})  # fmt: skip
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
