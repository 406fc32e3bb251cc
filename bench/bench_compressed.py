"""What a vehicle's camera sends: 3DBM detection on JPEG-compressed renders and a real sea photo.

Usage::

    python bench/bench_compressed.py [--quick] [--seed 20] [--frames 40] [--quality 25]
        [--repeats 3] [--work /tmp/uwdock-bench-compressed] [--real-dir ../shared/real]

Part 1, held-out renders: ``datasets synth`` frames of the docking station (the SAPIEN
renderer, the reference camera, poses drawn as the dataset tool draws them) in clear-tank,
coastal and turbid water at 968x732, and coastal water at 1920 px wide cropped to its middle
1920x1080 rows (the markers wholly inside the crop count), rendered once into ``--work``
(resumed if there). Seeds ``--seed`` and ``--seed + 1`` (20 and 21): no frame of them was used
while tuning the detector (its development frames came from seeds 0-6 and 11-17). Each frame
is given to every pipeline as rendered ("none") and after a JPEG round trip at ``--quality``
(OpenCV's encoder, 4:2:0, as ``bench_degradations.py``'s ``jpeg q20``), the same frames each.
Truth: the markers labelled visible; the allow-list is the DS set. Recall = decoded visible
markers / visible markers; false = decoded IDs that are not labelled visible; gate = the
fraction of frames on which ``default`` ran its views for block-compressed frames
(``Detector.last_compressed``).

Part 2, a real sea photo: ``obsea_ds_top/ds_top_b.jpg`` under ``--real-dir`` (read there,
never copied: no licence), the published DS from above at sea, DICT_4X4_50, markers 15-30 px.
No allow-list: every ID of the dictionary may come out, and an ID outside the station's set
(:data:`STATION_IDS`) is a false ID.

Pipelines: ``default``; ``default`` without its OpenCV pass (``rendered_3dbm_config``: the
simulator's camera source and the vehicle node's detector); the published ``reference_3dbm``,
``threshold_sweep`` and ``normalise_invert`` (``plain`` decodes no 3DBM).

Time: detection only (the image already decoded), one thread (``cv2.setNumThreads(1)``); per
frame every pipeline runs once untimed (its IDs), then ``--repeats`` timed rounds that visit
the pipelines in turn; the median of the rounds per frame; the table gives the median and the
90th percentile over frames. Writes ``bench/results/perception_compressed.json`` (rows + config,
machine, commit, packages).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from uwdock.dockcore.bench import format_table, save_results
from uwdock.markers.config import MarkerConfig
from uwdock.markers.markerset import marker_set_from_config
from uwdock.perception.detector import Detector, DetectorConfig, rendered_3dbm_config

REPO_ROOT = Path(__file__).resolve().parent.parent
DS_IDS = marker_set_from_config(MarkerConfig()).ids
#: The published station's marker IDs (docs/reference-system.md), the sea photo's truth set.
STATION_IDS = (13, 14, 15, 28, 30, 34, 35, 41, 42, 43, 49)
SEA_PHOTO = Path("obsea_ds_top") / "ds_top_b.jpg"
WATERS_968 = ("clear_tank", "coastal", "turbid")
CROP_1080 = 1080
#: Row label of ``default`` without its OpenCV pass.
NODE = "default, no OpenCV pass"
PIPELINES = ("default", NODE, "reference_3dbm", "threshold_sweep", "normalise_invert")

Item = tuple[str, np.ndarray, set[int]]  # (water, BGR image, visible IDs)


def detectors(ids: tuple[int, ...] | None) -> dict[str, Detector]:
    """Row name -> detector (allow-list ``ids``)."""
    out = {}
    for name in PIPELINES:
        cfg = rendered_3dbm_config(ids) if name == NODE else DetectorConfig(pipeline=name, ids=ids)
        out[name] = Detector(cfg)
    return out


def jpeg(img: np.ndarray, quality: int) -> np.ndarray:
    """``img`` after a JPEG round trip at ``quality`` (OpenCV's encoder)."""
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:  # pragma: no cover - OpenCV always encodes a uint8 image
        raise RuntimeError("JPEG encoding failed")
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)


def rendered_sets(work: Path, n_frames: int, seed: int) -> dict[str, list[Item]]:
    """Set label -> frames with a visible marker: the 968 px waters, and 1080p coastal."""
    from uwdock.datasets.loaders import LabelledDataset
    from uwdock.datasets.synth import SynthConfig, generate

    out: dict[str, list[Item]] = {"968x732": [], "1920x1080": []}
    plan = [(w, 968, seed, n_frames) for w in WATERS_968]
    plan.append(("coastal", 1920, seed + 1, n_frames))
    for water, width, s, n in plan:
        folder = work / f"synth_{water}_{width}_s{s}_n{n}"
        cfg = SynthConfig(n_frames=n, seed=s, water=water, width_px=width)
        print(f"  rendering {n} {water} frames into {folder}", file=sys.stderr, flush=True)
        generate(folder, cfg, workers=2, progress=False)
        for sample in LabelledDataset(folder):
            img = sample.image
            visible = {m.marker_id: m.corners_px for m in sample.truth.markers if m.visible}
            if width == 968:
                key = "968x732"
            else:  # the middle 1080 rows; markers wholly inside them
                y0 = (img.shape[0] - CROP_1080) // 2
                img = np.ascontiguousarray(img[y0 : y0 + CROP_1080])
                visible = {
                    i: c
                    for i, c in visible.items()
                    if c[:, 1].min() >= y0 and c[:, 1].max() <= y0 + CROP_1080 - 1
                }
                key = "1920x1080"
            if visible:
                out[key].append((water, img, set(visible)))
    return out


def timed(
    fns: dict[str, Callable[[np.ndarray], object]], img: np.ndarray, repeats: int
) -> dict[str, float]:
    """Median ms per call of each function on ``img``, ``repeats`` rounds visiting them in turn."""
    samples: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn(img)
            samples[k].append((time.perf_counter() - t0) * 1e3)
    return {k: statistics.median(v) for k, v in samples.items()}


def measure_rendered(sets: dict[str, list[Item]], quality: int, repeats: int) -> list[dict]:
    """Rows per (size, compression, pipeline), pooled over waters, then per water at 968 px."""
    dets = detectors(DS_IDS)
    rows = []
    for size, items in sets.items():
        for comp in ("none", f"jpeg q{quality}"):
            per: dict[str, list[dict]] = {p: [] for p in dets}
            for water, img, ids in items:
                frame = img if comp == "none" else jpeg(img, quality)
                for name, det in dets.items():
                    found = {d.marker_id for d in det.detect(frame)}
                    per[name].append(
                        {
                            "water": water,
                            "hits": len(found & ids),
                            "markers": len(ids),
                            "false": len(found - ids),
                            "gate": getattr(det, "last_compressed", False),
                        }
                    )
                ms = timed({n: d.detect for n, d in dets.items()}, frame, repeats)
                for name in dets:
                    per[name][-1]["ms"] = ms[name]
            for name, recs in per.items():
                groups = [("all", recs)]
                if size == "968x732":
                    groups += [(w, [r for r in recs if r["water"] == w]) for w in WATERS_968]
                for water, sel in groups:
                    if not sel:
                        continue
                    hits, total = sum(r["hits"] for r in sel), sum(r["markers"] for r in sel)
                    ms = [r["ms"] for r in sel]
                    rows.append(
                        {
                            "set": f"rendered {size}",
                            "water": water,
                            "compression": comp,
                            "pipeline": name,
                            "frames": len(sel),
                            "markers": total,
                            "decoded": hits,
                            "recall": hits / max(total, 1),
                            "false_ids": sum(r["false"] for r in sel),
                            "gate": sum(r["gate"] for r in sel) / len(sel),
                            "ms_med": float(np.median(ms)),
                            "ms_p90": float(np.percentile(ms, 90)),
                        }
                    )
            line = ", ".join(
                f"{r['pipeline']} {r['recall']:.2f}"
                for r in rows
                if r["set"] == f"rendered {size}"
                and r["compression"] == comp
                and r["water"] == "all"
            )
            print(f"  {size} {comp}: {line}", file=sys.stderr, flush=True)
    return rows


def measure_sea(real_dir: Path, repeats: int) -> list[dict]:
    """Rows per pipeline on the sea photo (no allow-list), or none when it is not there."""
    path = real_dir / SEA_PHOTO
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        print(f"  no sea photo at {path}: part 2 skipped", file=sys.stderr)
        return []
    dets = detectors(None)
    ms = timed({n: d.detect for n, d in dets.items()}, img, repeats)
    rows = []
    for name, det in dets.items():
        ids = sorted(d.marker_id for d in det.detect(img))
        right = [i for i in ids if i in STATION_IDS]
        rows.append(
            {
                "set": f"sea photo {SEA_PHOTO.parent.name}/{SEA_PHOTO.name}",
                "size_px": f"{img.shape[1]}x{img.shape[0]}",
                "pipeline": name,
                "decoded": len(right),
                "ids": " ".join(map(str, right)) or "-",
                "false_ids": len(ids) - len(right),
                "false_list": " ".join(str(i) for i in ids if i not in STATION_IDS) or "-",
                "gate": float(getattr(det, "last_compressed", False)),
                "ms_med": ms[name],
            }
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="8 frames per water, one timed round")
    ap.add_argument("--seed", type=int, default=20, help="968 px sets; the 1080p set: seed + 1")
    ap.add_argument("--frames", type=int, default=40, help="rendered frames per water (968 px)")
    ap.add_argument("--quality", type=int, default=25, help="JPEG quality of the compressed rows")
    ap.add_argument("--repeats", type=int, default=3, help="timed rounds per frame (median)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/uwdock-bench-compressed"))
    ap.add_argument(
        "--real-dir",
        type=Path,
        default=REPO_ROOT.parent / "shared" / "real",
        help="folder of the shared real sets (default: ../shared/real of the repo)",
    )
    ap.add_argument("--name", default="perception_compressed")
    args = ap.parse_args()
    if not 1 <= args.quality <= 100 or args.repeats < 1 or args.frames < 1:
        sys.exit("error: --quality must be 1-100, --repeats and --frames >= 1")
    cv2.setNumThreads(1)
    n_frames = 8 if args.quick else args.frames
    repeats = 1 if args.quick else args.repeats
    t0 = time.perf_counter()
    sets = rendered_sets(args.work, n_frames, args.seed)
    rows = measure_rendered(sets, args.quality, repeats)
    sea = measure_sea(args.real_dir.resolve(), repeats)
    cols = ["set", "water", "compression", "pipeline", "frames", "markers", "recall"]
    cols += ["false_ids", "gate", "ms_med", "ms_p90"]
    print("\nHeld-out renders (recall of visible markers; ms = detection only, one thread)")
    print(format_table([r for r in rows if r["water"] == "all"], cols))
    print("\nPer water, 968x732")
    print(format_table([r for r in rows if r["water"] != "all"], cols))
    if sea:
        print("\nReal sea photo (no allow-list; false = IDs outside the station's set)")
        print(
            format_table(
                sea, ["set", "size_px", "pipeline", "decoded", "ids", "false_ids", "gate", "ms_med"]
            )
        )
    config = {
        "quick": args.quick,
        "seed_968": args.seed,
        "seed_1080": args.seed + 1,
        "frames_per_water_968": n_frames,
        "frames_1080": n_frames,
        "waters_968": list(WATERS_968),
        "water_1080": "coastal",
        "frames_with_a_marker": {k: len(v) for k, v in sets.items()},
        "jpeg_quality": args.quality,
        "repeats": repeats,
        "allow_list_rendered": list(DS_IDS),
        "station_ids_sea_photo": list(STATION_IDS),
        "sea_photo": str(args.real_dir / SEA_PHOTO),
        "cv2_threads": 1,
    }
    path = save_results(args.name, [*rows, *sea], config)
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
