"""Perception under degradations: recall, false IDs and time per pipeline, the same frames each.

Usage::

    python bench/bench_degradations.py [--quick] [--seed 0] [--frames 24] [--water-frames 40]
        [--work /tmp/uwdock-bench-water] [--no-water]

Part 1, image degradations: synthetic 3DBM views of the DS marker board by the reference camera
at 968x732 (``bench_perception.render``: 1.2-3.5 m, tilt <= 15 deg, green-blue cast, blur,
1.5 grey levels of noise), at a moderate contrast of 60 grey levels, then one degradation each:

* ``none``; ``salt 1 %`` / ``salt 5 %``: that fraction of pixels set to white (impulse noise);
* ``jpeg q20``: JPEG at quality 20 (8x8 blocking);
* ``green cast``: red x0.15, blue x0.5, + 40 on green (deep-water colour);
* ``motion blur 15 px``: a 15 px line kernel at a random angle;
* ``gamma 0.5`` / ``gamma 2.2``: grey levels 255 (x / 255)^gamma;
* ``bar occlusion``: a dark bar 2.5 % of the width across the image (a cable or a strut);
* ``contrast 12``: the contrast squeezed to 12 grey levels (the low end of part 1 of
  ``bench_perception.py``).

Part 2, rendered water: ``datasets synth`` frames (the real SAPIEN renderer, 968 px wide, poses
drawn as the dataset tool draws them) in clear, coastal and turbid water, rendered once into
``--work`` (resumed if there); truth = the markers labelled visible.

Recall = decoded visible markers / visible markers; frames = frames with at least one visible
marker decoded; false = decoded IDs not visible in the frame (the allow-list is the DS set).
Time: detection only, one thread (``cv2.setNumThreads(1)``), median over frames of the median of
``repeats`` runs. Writes ``bench/results/perception_degradations.json`` (rows + machine, commit,
packages) and a recall figure ``perception_degradations.png``.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from bench_perception import MARKER_SET, random_view, render

from uwdock.calibration.camera import reference_camera
from uwdock.dockcore.bench import RESULTS_DIR, format_table, save_results, time_call
from uwdock.dockcore.io import atomic_path
from uwdock.perception.detector import Detector, DetectorConfig
from uwdock.perception.preprocess import PIPELINES

WIDTH_PX, HEIGHT_PX = 968, 732
BASE_LEVELS = 60.0
WATERS = ("clear_tank", "coastal", "turbid")

Degrade = Callable[[np.ndarray, np.random.Generator], np.ndarray]


def salt(fraction: float) -> Degrade:
    def f(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        out = img.copy()
        out[rng.random(img.shape[:2]) < fraction] = 255
        return out

    return f


def jpeg(quality: int) -> Degrade:
    def f(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
        assert ok
        return cv2.imdecode(buf, cv2.IMREAD_COLOR)

    return f


def green_cast(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    f = img.astype(np.float32) * np.array([0.5, 1.0, 0.15], np.float32) + np.array([0, 40, 0])
    return np.clip(f + 0.5, 0, 255).astype(np.uint8)


def motion_blur(length_px: int) -> Degrade:
    def f(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        k = np.zeros((length_px, length_px), np.float32)
        k[length_px // 2, :] = 1.0 / length_px
        rot = cv2.getRotationMatrix2D(((length_px - 1) / 2,) * 2, rng.uniform(0, 180), 1.0)
        k = cv2.warpAffine(k, rot, (length_px, length_px))
        return cv2.filter2D(img, -1, k / k.sum())

    return f


def gamma(g: float) -> Degrade:
    lut = np.clip(255.0 * (np.arange(256) / 255.0) ** g + 0.5, 0, 255).astype(np.uint8)

    def f(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return cv2.LUT(img, lut)

    return f


def bar_occlusion(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    h, w = img.shape[:2]
    out = img.copy()
    c = np.array([rng.uniform(0.3, 0.7) * w, rng.uniform(0.3, 0.7) * h])
    a = rng.uniform(0, np.pi)
    d = np.array([np.cos(a), np.sin(a)]) * 2 * (w + h)
    p0, p1 = (c - d).astype(int), (c + d).astype(int)
    cv2.line(out, tuple(map(int, p0)), tuple(map(int, p1)), (12, 18, 10), round(0.025 * w))
    return out


DEGRADATIONS: dict[str, Degrade | None] = {
    "none": lambda img, rng: img,
    "salt 1 %": salt(0.01),
    "salt 5 %": salt(0.05),
    "jpeg q20": jpeg(20),
    "green cast": green_cast,
    "motion blur 15 px": motion_blur(15),
    "gamma 0.5": gamma(0.5),
    "gamma 2.2": gamma(2.2),
    "bar occlusion": bar_occlusion,
    "contrast 12": None,  # rendered at 12 grey levels instead of BASE_LEVELS
}


def synthetic_sets(n_frames: int, seed: int) -> dict[str, list[tuple[np.ndarray, set[int]]]]:
    """Degradation name -> [(BGR image, visible IDs)]: the same views under each degradation."""
    cam = reference_camera().scaled(WIDTH_PX, HEIGHT_PX)
    rng = np.random.default_rng(seed)
    views = []
    while len(views) < n_frames:
        T = random_view(rng, 1.2, 3.5, 15.0)
        img, truth = render(T, cam, rng, BASE_LEVELS)
        if truth:
            views.append((T, img, set(truth)))
    sets: dict[str, list[tuple[np.ndarray, set[int]]]] = {}
    for k, (name, fn) in enumerate(DEGRADATIONS.items()):
        sets[name] = []
        for i, (T, img, ids) in enumerate(views):
            drng = np.random.default_rng([seed, k, i])
            if fn is None:  # the same view rendered at 12 grey levels
                img, truth = render(T, cam, drng, 12.0)
                ids = set(truth)
            else:
                img = fn(img, drng)
            sets[name].append((img, ids))
    return sets


def water_sets(work: Path, n_frames: int, seed: int) -> dict[str, list[tuple[np.ndarray, set]]]:
    """Water preset -> [(BGR image, visible IDs)] from rendered ``datasets synth`` frames (only
    frames with a visible marker)."""
    from uwdock.datasets.loaders import LabelledDataset
    from uwdock.datasets.synth import SynthConfig, generate

    out: dict[str, list[tuple[np.ndarray, set]]] = {}
    for water in WATERS:
        folder = work / f"synth_{water}_{WIDTH_PX}_s{seed}_n{n_frames}"
        cfg = SynthConfig(n_frames=n_frames, seed=seed, water=water, width_px=WIDTH_PX)
        print(f"  rendering {n_frames} {water} frames into {folder}", file=sys.stderr, flush=True)
        generate(folder, cfg, workers=2, progress=False)
        ds = LabelledDataset(folder)
        out[f"water {water}"] = [
            (s.image, set(s.truth.visible_ids)) for s in ds if s.truth.visible_ids
        ]
    return out


def measure(sets: dict, repeats: int) -> list[dict]:
    detectors = {p: Detector(DetectorConfig(pipeline=p, ids=MARKER_SET.ids)) for p in PIPELINES}
    rows = []
    for cond, items in sets.items():
        for name, det in detectors.items():
            hits = total = false_ids = frames_hit = 0
            ms = []
            for img, ids in items:
                found = {d.marker_id for d in det.detect(img)}
                hits += len(found & ids)
                total += len(ids)
                false_ids += len(found - ids)
                frames_hit += bool(found & ids)
                ms.append(time_call(lambda d=det, im=img: d.detect(im), repeats, 0)["median_ms"])
            rows.append(
                {
                    "condition": cond,
                    "pipeline": name,
                    "recall": hits / max(total, 1),
                    "frames": f"{frames_hit}/{len(items)}",
                    "frames_hit": frames_hit,
                    "n_frames": len(items),
                    "markers": total,
                    "false_ids": false_ids,
                    "ms_med": float(np.median(ms)),
                }
            )
        best = max(r["recall"] for r in rows if r["condition"] == cond)
        line = ", ".join(
            f"{r['pipeline']} {r['recall']:.2f}" for r in rows if r["condition"] == cond
        )
        print(f"  {cond}: {line} (best {best:.2f})", file=sys.stderr, flush=True)
    return rows


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conds = list(dict.fromkeys(r["condition"] for r in rows))
    pipes = list(dict.fromkeys(r["pipeline"] for r in rows))
    rec = {(r["condition"], r["pipeline"]): r["recall"] for r in rows}
    fig, ax = plt.subplots(figsize=(max(8, 0.9 * len(conds)), 4.2))
    width = 0.8 / len(pipes)
    for j, p in enumerate(pipes):
        x = np.arange(len(conds)) + (j - (len(pipes) - 1) / 2) * width
        ax.bar(x, [rec[(c, p)] for c in conds], width, label=p)
    ax.set_xticks(np.arange(len(conds)), conds, rotation=30, ha="right")
    ax.set_ylabel("recall (visible markers decoded)")
    ax.set_ylim(0, 1.05)
    ax.set_title("Marker recall per pipeline and degradation (968x732, same frames each)")
    ax.legend(fontsize=8, ncol=len(pipes), loc="upper center", bbox_to_anchor=(0.5, -0.32))
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="4 frames per condition, no water")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=24, help="synthetic views per degradation")
    ap.add_argument("--water-frames", type=int, default=40, help="rendered frames per water")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per frame")
    ap.add_argument("--work", type=Path, default=Path("/tmp/uwdock-bench-water"))
    ap.add_argument("--no-water", action="store_true", help="skip the rendered water frames")
    ap.add_argument("--name", default="perception_degradations")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    n_frames = 4 if args.quick else args.frames
    water = not (args.quick or args.no_water)
    t0 = time.perf_counter()
    sets = synthetic_sets(n_frames, args.seed)
    if water:
        sets.update(water_sets(args.work, args.water_frames, args.seed))
    rows = measure(sets, 1 if args.quick else args.repeats)
    print("\nRecall per condition (968x732; ms = detection only, one thread)")
    print(format_table(rows, ["condition", "pipeline", "recall", "frames", "false_ids", "ms_med"]))
    config = {
        "quick": args.quick,
        "seed": args.seed,
        "frames_per_degradation": n_frames,
        "water_frames": args.water_frames if water else 0,
        "waters": list(WATERS) if water else [],
        "repeats": 1 if args.quick else args.repeats,
        "size_px": [WIDTH_PX, HEIGHT_PX],
        "base_contrast_levels": BASE_LEVELS,
        "degradations": list(DEGRADATIONS),
        "cv2_threads": 1,
    }
    path = save_results(args.name, rows, config)
    plot(rows, RESULTS_DIR / f"{args.name}.png")
    print(f"\nwrote {path} and its figure in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
