"""Colour order at the sim -> perception seam: what handing the detector RGB instead of BGR does.

Usage::

    python bench/bench_seam.py [--frames 40] [--width 480] [--seed 0] [--out-dir DIR]

Per water preset (clear_tank, coastal, turbid): ``frames`` frames of the ``datasets synth`` pose
sampler (aimed poses, default sampling) captured through the water by the env's camera
(:class:`uwdock.sim.camera.SimCamera`, reference camera at ``width`` px). Each frame is given to
the DS detector twice: in the renderer's RGB order (what the env's camera source passed before
the seam was fixed) and converted to BGR (:meth:`uwdock.sim.camera.Frame.img_bgr`, perception's
contract). The table gives the mean absolute difference of the two grey images the detector
computes (``COLOR_BGR2GRAY``), the decoded markers summed over the frames each way, and the
frames whose decoded ID set differs.

Writes ``bench/results/seam.json`` (rows + machine, commit, packages).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from uwdock.dockcore.bench import format_table, save_results

WATERS = ("clear_tank", "coastal", "turbid")


def measure(n_frames: int, width_px: int, seed: int) -> list[dict]:
    from uwdock.datasets.synth import FrameRenderer, SynthConfig, frame_rng
    from uwdock.perception.detector import Detector, DetectorConfig
    from uwdock.sim.water import PRESETS

    rows = []
    for water in WATERS:
        renderer = FrameRenderer(SynthConfig(n_frames=n_frames, seed=seed, width_px=width_px))
        ms = renderer.rs.ds.marker_set
        detector = Detector(DetectorConfig(dictionary=ms.dictionary, ids=tuple(ms.ids)))
        grey_diff, n_rgb, n_bgr, changed = [], 0, 0, 0
        for k in range(n_frames):
            rng = frame_rng(seed, k)
            T_world_body = renderer.pose(k, rng)
            frame = renderer.sim_camera.capture(T_world_body, rng, water=PRESETS[water])
            img_bgr = frame.img_bgr()
            g_rgb = cv2.cvtColor(frame.img_rgb, cv2.COLOR_BGR2GRAY).astype(np.int16)
            g_bgr = cv2.cvtColor(img_bgr, cv2.COLOR_BGR2GRAY).astype(np.int16)
            grey_diff.append(float(np.abs(g_rgb - g_bgr).mean()))
            ids_rgb = [d.marker_id for d in detector.detect(frame.img_rgb)]
            ids_bgr = [d.marker_id for d in detector.detect(img_bgr)]
            n_rgb += len(ids_rgb)
            n_bgr += len(ids_bgr)
            changed += ids_rgb != ids_bgr
        rows.append(
            {
                "water": water,
                "frames": n_frames,
                "grey_abs_diff_mean": float(np.mean(grey_diff)),
                "markers_rgb_old": n_rgb,
                "markers_bgr_new": n_bgr,
                "frames_with_other_ids": changed,
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--width", type=int, default=480)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out-dir", type=Path, default=None)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    rows = measure(args.frames, args.width, args.seed)
    cols = ["water", "frames", "grey_abs_diff_mean", "markers_rgb_old", "markers_bgr_new"]
    print(format_table(rows, [*cols, "frames_with_other_ids"]))
    config = {"frames": args.frames, "width_px": args.width, "seed": args.seed}
    path = save_results("seam", rows, config, args.out_dir)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
