"""Detection on real footage: markers found, false IDs and time per frame, per method and set.

Usage::

    python bench/bench_real.py [--real-dir ../shared/real] [--repeats 3] [--quick]
        [--methods opencv,default,...] [--dictionary DICT_APRILTAG_36h11] [--name real]

Every set under ``--real-dir`` (default ``../shared/real`` relative to the repository root; one
subfolder per set, its images in it and in its subfolders, e.g. ``video_crops/``; other files,
videos included, are skipped) is read frame by frame (``dockcore.media.read_image``, as
``perception detect`` reads a folder) and given to every method:

* ``opencv``: plain ``cv2.aruco.ArucoDetector`` with OpenCV's default parameters on the grey
  image (``cv2.COLOR_BGR2GRAY``), the reference;
* ``default``: the toolkit's ``default`` pipeline (``perception detect --pipeline default``);
* ``default_own``: ``default`` without its OpenCV pass (``DetectorConfig(opencv_pass=False)``,
  the toolkit's own passes alone), to show what each part finds;
* the published pipelines (:func:`perception.detector.list_pipelines`): ``reference_3dbm``,
  ``threshold_sweep``, ``normalise_invert`` (they look for inverted 3DBMs) and ``plain``.

Dictionary and valid IDs per set come from :data:`KNOWN_SETS` (taken from each set's
README.txt); a set not in it takes its dictionary from its README.txt line ``Family`` (an
AprilTag or ArUco family name) or ``--dictionary``, and its false IDs are not counted (``-``).
False IDs = decoded IDs outside the set's valid ID range (a lower bound on wrong reads: a wrong
ID inside the range is not caught). No method is given an allow-list.

Time: detection only (the image already decoded), one thread (``cv2.setNumThreads(1)``); each
frame runs every method once untimed (its IDs), then ``--repeats`` timed rounds that visit the
methods in turn (so a change of load on the machine touches them alike); the median of the
rounds per frame. Tables: per group (a set or a set's subfolder) the markers found (an ID per
frame), frames with at least one, false IDs, the median ms per frame and its ratio to
``opencv``'s; then IDs per frame. Writes ``bench/results/<name>.json`` (per-frame rows, the
group table, the sets' dictionaries and ID ranges; machine, commit and packages) and a figure
``<name>.png``.
"""

from __future__ import annotations

import argparse
import re
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from uwdock.dockcore.bench import RESULTS_DIR, format_table
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_path, atomic_write_json
from uwdock.dockcore.media import IMAGE_SUFFIXES, read_image
from uwdock.dockcore.provenance import provenance
from uwdock.markers.dictionary import get_dictionary, normalise_dictionary_name
from uwdock.perception.detector import Detector, DetectorConfig, list_pipelines
from uwdock.perception.preprocess import as_uint8, to_grey

REPO_ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class RealSet:
    """What a real set's README.txt says about its markers.

    Attributes:
        dictionary: OpenCV dictionary name of the markers.
        valid_ids: (lowest, highest) ID that is in the set, inclusive; a decoded ID outside is
            a false ID. None: not known (false IDs not counted).
        source: where the range comes from.
    """

    dictionary: str
    valid_ids: tuple[int, int] | None
    source: str


#: The shared real sets: dictionary and valid ID range, from each set's README.txt.
KNOWN_SETS: dict[str, RealSet] = {
    "apl_sediment_tag36h11": RealSet(
        "DICT_APRILTAG_36h11", (0, 0), 'README.txt: "AprilTag 36h11, ID 0", the one tag'
    ),
    "fav_tank_tag36h11": RealSet(
        "DICT_APRILTAG_36h11", (0, 90), 'README.txt: "IDs 0 to 90 are used for the tags"'
    ),
}

#: Methods in table order; the published pipelines follow ``default_own``.
BASE_METHODS = ("opencv", "default", "default_own")
#: Columns of the printed tables.
SUMMARY_COLUMNS = ("group", "frames", "method", "markers", "frames_with_one", "false_ids")
SUMMARY_COLUMNS += ("ms_med", "ms_max", "x_opencv")
SIZE_COLUMNS = ("size_px", "frames", "method", "ms_med", "x_opencv_med", "x_opencv_max")


def family_from_readme(readme: Path) -> str | None:
    """The dictionary named on a README.txt's ``Family`` line (AprilTag NhM or ArUco NxN), or
    None when there is no such line or it names no family OpenCV has."""
    if not readme.is_file():
        return None
    for line in readme.read_text(encoding="utf-8", errors="replace").splitlines():
        if not line.strip().lower().startswith("family"):
            continue
        tag = re.search(r"apriltag\s*(\d+h\d+)", line, re.IGNORECASE)
        aruco = re.search(r"(\d)\s*x\s*(\d)(?:[_ ](\d+))?", line)
        name = None
        if tag:
            name = f"DICT_APRILTAG_{tag.group(1).lower()}"
        elif aruco and aruco.group(3):
            name = f"DICT_{aruco.group(1)}X{aruco.group(2)}_{aruco.group(3)}"
        if name is None:
            return None
        try:
            return normalise_dictionary_name(name)
        except DockError:
            return None
    return None


def find_sets(real_dir: Path, fallback_dictionary: str) -> dict[str, tuple[RealSet, list[Path]]]:
    """Set name -> (its markers, its image files sorted, subfolders included)."""
    if not real_dir.is_dir():
        raise DockError(f"no real footage folder at {real_dir} (give --real-dir)")
    out = {}
    for folder in sorted(p for p in real_dir.iterdir() if p.is_dir()):
        files = sorted(
            p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
        )
        if not files:
            continue
        info = KNOWN_SETS.get(folder.name)
        if info is None:
            family = family_from_readme(folder / "README.txt")
            info = RealSet(
                family or fallback_dictionary,
                None,
                "README.txt Family line" if family else "--dictionary",
            )
        out[folder.name] = (info, files)
    if not out:
        raise DockError(f"no set with images under {real_dir}")
    return out


def methods_for(dictionary: str, names: list[str]) -> dict[str, Callable[[np.ndarray], list[int]]]:
    """Method name -> fn(image) -> decoded IDs (one per marker, sorted)."""
    out: dict[str, Callable[[np.ndarray], list[int]]] = {}
    for name in names:
        if name == "opencv":
            aruco = cv2.aruco.ArucoDetector(
                get_dictionary(dictionary), cv2.aruco.DetectorParameters()
            )

            def run_opencv(img: np.ndarray, aruco=aruco) -> list[int]:
                _corners, ids, _rejected = aruco.detectMarkers(to_grey(img))
                return [] if ids is None else sorted(int(i) for i in ids.ravel())

            out[name] = run_opencv
            continue
        if name == "default_own":
            cfg = DetectorConfig(dictionary=dictionary, opencv_pass=False)
        else:
            cfg = DetectorConfig(dictionary=dictionary, pipeline=name)
        det = Detector(cfg)
        out[name] = lambda img, det=det: sorted(d.marker_id for d in det.detect(img))
    return out


def measure(
    sets: dict[str, tuple[RealSet, list[Path]]], real_dir: Path, names: list[str], repeats: int
) -> list[dict]:
    """One row per frame and method: IDs, false IDs, median ms."""
    rows = []
    for set_name, (info, files) in sets.items():
        methods = methods_for(info.dictionary, names)
        lo, hi = info.valid_ids if info.valid_ids is not None else (None, None)
        for path in files:
            image = read_image(path)
            if image is None:
                print(f"  skipped {path} (not decodable)", file=sys.stderr)
                continue
            image = as_uint8(image)
            rel = path.relative_to(real_dir / set_name)
            group = set_name if rel.parent == Path(".") else f"{set_name}/{rel.parent.as_posix()}"
            found = {m: fn(image) for m, fn in methods.items()}
            samples: dict[str, list[float]] = {m: [] for m in methods}
            for _ in range(repeats):
                for m, fn in methods.items():
                    t0 = time.perf_counter()
                    fn(image)
                    samples[m].append((time.perf_counter() - t0) * 1e3)
            for m in methods:
                ids = found[m]
                false = (
                    sum(not lo <= i <= hi for i in ids)  # type: ignore[operator]
                    if info.valid_ids is not None
                    else None
                )
                rows.append(
                    {
                        "set": set_name,
                        "group": group,
                        "frame": rel.as_posix(),
                        "size_px": [int(image.shape[1]), int(image.shape[0])],
                        "method": m,
                        "ids": ids,
                        "n": len(ids),
                        "false_ids": false,
                        "ms": statistics.median(samples[m]),
                        "ms_min": min(samples[m]),
                    }
                )
            line = " ".join(f"{m} {len(found[m])}" for m in methods)
            print(f"  {group}/{rel.name}: {line}", file=sys.stderr, flush=True)
    return rows


def summarise(rows: list[dict], names: list[str]) -> list[dict]:
    """One row per group and method: markers, frames with one, false IDs, ms per frame."""
    out = []
    for group in dict.fromkeys(r["group"] for r in rows):
        ref = [r["ms"] for r in rows if r["group"] == group and r["method"] == "opencv"]
        ref_ms = float(np.median(ref)) if ref else None
        sizes = {tuple(r["size_px"]) for r in rows if r["group"] == group}
        for m in names:
            sel = [r for r in rows if r["group"] == group and r["method"] == m]
            if not sel:
                continue
            ms = float(np.median([r["ms"] for r in sel]))
            false = [r["false_ids"] for r in sel]
            out.append(
                {
                    "group": group,
                    "frames": len(sel),
                    "size_px": " ".join(f"{w}x{h}" for w, h in sorted(sizes)),
                    "method": m,
                    "markers": sum(r["n"] for r in sel),
                    "frames_with_one": sum(r["n"] > 0 for r in sel),
                    "false_ids": "-" if None in false else sum(false),
                    "ms_med": ms,
                    "ms_max": max(r["ms"] for r in sel),
                    "x_opencv": ms / ref_ms if ref_ms else "",
                }
            )
    return out


def per_size(rows: list[dict], names: list[str]) -> list[dict]:
    """Median ms per frame size and method, and the ratio to ``opencv``'s on the same frames."""
    out = []
    for size in sorted({tuple(r["size_px"]) for r in rows}, key=lambda s: s[0] * s[1]):
        sel = [r for r in rows if tuple(r["size_px"]) == size]
        ref = {r["frame"]: r["ms"] for r in sel if r["method"] == "opencv"}
        for m in names:
            mine = [r for r in sel if r["method"] == m]
            if not mine:
                continue
            ratios = [r["ms"] / ref[r["frame"]] for r in mine if ref.get(r["frame"])]
            out.append(
                {
                    "size_px": f"{size[0]}x{size[1]}",
                    "frames": len(mine),
                    "method": m,
                    "ms_med": float(np.median([r["ms"] for r in mine])),
                    "x_opencv_med": float(np.median(ratios)) if ratios else "",
                    "x_opencv_max": max(ratios) if ratios else "",
                }
            )
    return out


def per_frame_table(rows: list[dict], names: list[str]) -> str:
    """IDs per frame (columns: methods), frames where some method found a marker."""
    table = []
    for frame in dict.fromkeys((r["group"], r["frame"]) for r in rows):
        sel = {r["method"]: r for r in rows if (r["group"], r["frame"]) == frame}
        if not any(sel[m]["n"] for m in sel):
            continue
        row = {"frame": f"{frame[0].split('/')[0]}/{frame[1]}"}
        row.update({m: sel[m]["n"] for m in names if m in sel})
        ref = set(sel["opencv"]["ids"]) if "opencv" in sel else set()
        if "default" in sel:
            mine = set(sel["default"]["ids"])
            row["default-opencv"] = (
                " ".join(
                    [f"+{i}" for i in sorted(mine - ref)] + [f"-{i}" for i in sorted(ref - mine)]
                )
                or "="
            )
        table.append(row)
    cols = ["frame", *names] + (["default-opencv"] if "default" in names else [])
    return format_table(table, cols)


def plot(summary: list[dict], names: list[str], path: Path) -> None:
    """Markers found and ms per frame, per group and method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = list(dict.fromkeys(r["group"] for r in summary))
    val = {(r["group"], r["method"]): r for r in summary}
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.4))
    width = 0.8 / len(names)
    for j, m in enumerate(names):
        x = np.arange(len(groups)) + (j - (len(names) - 1) / 2) * width
        markers = [val[(g, m)]["markers"] if (g, m) in val else 0 for g in groups]
        ms = [val[(g, m)]["ms_med"] if (g, m) in val else np.nan for g in groups]
        axes[0].bar(x, markers, width, label=m)
        axes[1].bar(x, ms, width, label=m)
    for ax, label in zip(
        axes, ("markers found (an ID per frame)", "ms per frame (median)"), strict=True
    ):
        ax.set_xticks(np.arange(len(groups)), groups, rotation=15, ha="right", fontsize=8)
        ax.set_ylabel(label)
    axes[1].set_yscale("log")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(names), fontsize=8)
    fig.suptitle("Real footage: markers and time per method (one thread)")
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--real-dir",
        type=Path,
        default=REPO_ROOT.parent / "shared" / "real",
        help="folder of real sets, one subfolder each (default: ../shared/real of the repo)",
    )
    ap.add_argument("--repeats", type=int, default=3, help="timed rounds per frame (median)")
    ap.add_argument("--quick", action="store_true", help="one timed round, no threshold sweep")
    ap.add_argument(
        "--methods",
        default=",".join([*BASE_METHODS, *list_pipelines().keys() - {"default"}]),
        help="comma-separated: opencv, default, default_own and pipeline names",
    )
    ap.add_argument(
        "--dictionary",
        default="DICT_APRILTAG_36h11",
        help="dictionary of a set that is not in KNOWN_SETS and names no Family in README.txt",
    )
    ap.add_argument("--name", default="real", help="results file name (bench/results/NAME.json)")
    args = ap.parse_args()
    known = {*BASE_METHODS, *list_pipelines()}
    names = [m.strip() for m in args.methods.split(",") if m.strip()]
    bad = [m for m in names if m not in known]
    if bad or args.repeats < 1:
        sys.exit(f"error: unknown method {bad[0]!r}" if bad else "error: --repeats must be >= 1")
    if args.quick:
        names = [m for m in names if m != "threshold_sweep"]
    names = [m for m in dict.fromkeys([*BASE_METHODS, *list_pipelines()]) if m in names]
    repeats = 1 if args.quick else args.repeats
    cv2.setNumThreads(1)
    real_dir = args.real_dir.resolve()
    try:
        sets = find_sets(real_dir, normalise_dictionary_name(args.dictionary))
    except DockError as exc:
        sys.exit(f"error: {exc}")
    t0 = time.perf_counter()
    rows = measure(sets, real_dir, names, repeats)
    summary = summarise(rows, names)
    sizes = per_size(rows, names)
    print("\nPer set (markers = IDs decoded, summed over frames; ms = detection, one thread)")
    print(
        format_table(
            summary,
            [*SUMMARY_COLUMNS],
        )
    )
    print("\nTime per frame size (median ms; x_opencv = ratio to opencv on the same frames)")
    print(format_table(sizes, [*SIZE_COLUMNS]))
    print("\nIDs per frame (frames where some method decoded one)")
    print(per_frame_table(rows, names))
    config = {
        "real_dir": str(real_dir),
        "methods": names,
        "repeats": repeats,
        "quick": args.quick,
        "cv2_threads": 1,
        "sets": {
            name: {
                "dictionary": info.dictionary,
                "valid_ids": list(info.valid_ids) if info.valid_ids else None,
                "source": info.source,
                "frames": len(files),
            }
            for name, (info, files) in sets.items()
        },
    }
    path = RESULTS_DIR / f"{args.name}.json"
    extra = {"benchmark": args.name, "bench_config": config, "summary": summary}
    atomic_write_json(path, provenance(extra={**extra, "per_size": sizes, "rows": rows}))
    plot(summary, names, RESULTS_DIR / f"{args.name}.png")
    print(f"\nwrote {path} and its figure in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
