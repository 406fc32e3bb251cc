"""Output benchmark: video write speed (H.264 through PyAV vs OpenCV's MPEG-4 Part 2) and the
cost of the printability check of ``markers generate``.

Usage::

    python bench/bench_media.py [--quick] [--seed 0]

Part 1, video: ``frames`` frames of a rendered-looking BGR scene (a smooth water gradient, a
seabed texture, sensor noise, and a bright marker board and an overlay box that move a few
pixels a frame) written at 480x363 (the README's camera views) and 968x732 (the reference
camera) by :class:`dockcore.media.AtomicVideoWriter` (``.mp4`` = H.264 ``yuv420p``
+faststart, the writer now) and by ``cv2.VideoWriter`` with FourCC ``mp4v`` (MPEG-4 Part 2,
the writer before), each into a temporary file. Time: open + every frame + close, median of
``repeats`` runs after a warm-up; ``fps`` = frames / median time. Also the file size and the
PSNR of the decoded video against the input (dB, read back through OpenCV).

Part 2, mesh check: :func:`markers.meshcheck.check_printable` on the STL parts of a marker set
(the default DS set of 5 IDs; with relief bosses; one AprilTag 36h11 marker), open3d already
imported; the one-time open3d import is timed separately (a fresh interpreter).

Writes ``bench/results/media_video.json`` and ``media_meshcheck.json``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from uwdock.dockcore.bench import format_table, save_results, time_call
from uwdock.dockcore.media import H264_CRF, H264_PRESET, AtomicVideoWriter
from uwdock.markers.config import MarkerConfig
from uwdock.markers.generate import file_stem
from uwdock.markers.geometry import build_solids
from uwdock.markers.meshcheck import check_printable

SIZES_PX = ((480, 363), (968, 732))


def scene_frames(w: int, h: int, n: int, seed: int) -> list[np.ndarray]:
    """``n`` BGR frames: water gradient + seabed texture + noise, a moving board and overlay."""
    rng = np.random.default_rng(seed)
    yy = np.linspace(0.0, 1.0, h, dtype=np.float32)[:, None, None]
    water = np.array([90.0, 120.0, 40.0], np.float32) * (1.0 - 0.5 * yy)  # BGR, darker below
    tex = cv2.resize(rng.random((h // 8, w // 8)).astype(np.float32), (w, h))
    base = water + 40.0 * tex[:, :, None]
    board = np.kron((rng.random((6, 6)) > 0.5).astype(np.float32), np.ones((h // 24, h // 24)))
    frames = []
    for k in range(n):
        img = base + rng.normal(0.0, 2.0, (h, w, 3)).astype(np.float32)
        x0, y0 = w // 4 + 2 * k, h // 3 + k
        bh, bw = board.shape
        img[y0 : y0 + bh, x0 : x0 + bw] = 40.0 + 180.0 * board[:, :, None]
        img = np.clip(img, 0, 255).astype(np.uint8)
        cv2.rectangle(img, (x0 - 4, y0 - 4), (x0 + bw + 4, y0 + bh + 4), (60, 220, 60), 2)
        cv2.putText(img, f"t = {k / 5:.1f} s", (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255,) * 3)
        frames.append(img)
    return frames


def write_h264(path: Path, frames: list[np.ndarray], fps: float) -> None:
    with AtomicVideoWriter(path, fps) as video:
        for f in frames:
            video.write(f)


def write_mp4v(path: Path, frames: list[np.ndarray], fps: float) -> None:
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    if not writer.isOpened():
        raise RuntimeError("OpenCV's mp4v writer did not open")
    for f in frames:
        writer.write(f)
    writer.release()


def read_back(path: Path, frames: list[np.ndarray]) -> tuple[float, str, int]:
    """(PSNR dB over the area both share, decoded size "WxH", decoded frame count)."""
    cap = cv2.VideoCapture(str(path))
    errors, size, count = [], "", 0
    for f in frames:
        ok, got = cap.read()
        if not ok:
            break
        count += 1
        size = f"{got.shape[1]}x{got.shape[0]}"
        h, w = min(got.shape[0], f.shape[0]), min(got.shape[1], f.shape[1])
        errors.append(np.mean((got[:h, :w].astype(np.float64) - f[:h, :w]) ** 2))
    cap.release()
    return float(10 * np.log10(255.0**2 / np.mean(errors))), size, count


def bench_video(n: int, repeats: int, seed: int) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for w, h in SIZES_PX:
            frames = scene_frames(w, h, n, seed)
            for name, fn in (("h264 (PyAV)", write_h264), ("mp4v (OpenCV)", write_mp4v)):
                path = Path(tmp) / f"{w}x{h}_{name.split()[0]}.mp4"
                t = time_call(
                    lambda fn=fn, path=path, frames=frames: fn(path, frames, 5.0), repeats=repeats
                )
                psnr, decoded, count = read_back(path, frames)
                rows.append(
                    {
                        "size_px": f"{w}x{h}",
                        "writer": name,
                        "frames": n,
                        "fps": n / (t["median_ms"] / 1e3),
                        "fps_min": n / (t["max_ms"] / 1e3),
                        "fps_max": n / (t["min_ms"] / 1e3),
                        "kB": path.stat().st_size / 1e3,
                        "psnr_db": psnr,
                        "decoded_px": decoded,
                        "decoded_frames": count,
                        **t,
                    }
                )
    return rows


def bench_meshcheck(repeats: int) -> list[dict]:
    code = "import time; t = time.perf_counter(); import open3d; print(time.perf_counter() - t)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    import_s = float(out.stdout.strip().splitlines()[-1])
    import open3d  # noqa: F401  (imported once, as markers generate does)

    sets = {
        "DS set (5 IDs, DICT_4X4_50)": MarkerConfig(),
        "DS set, relief 2 mm (bosses)": MarkerConfig(relief_depth_mm=2.0),
        "1 ID, DICT_APRILTAG_36h11": MarkerConfig(dictionary="DICT_APRILTAG_36h11", ids=(7,)),
    }
    rows = []
    for name, cfg in sets.items():
        stl = {}
        for i in cfg.ids:
            s = build_solids(cfg, i)
            for part, mesh in (("insert", s.insert), ("enclosure", s.enclosure)):
                stl[f"{file_stem(cfg.dictionary, i)}_{part}.stl"] = mesh.export(file_type="stl")
        t = time_call(lambda stl=stl: check_printable(stl), repeats=repeats)
        reports = check_printable(stl)
        rows.append(
            {
                "marker_set": name,
                "parts": len(reports),
                "triangles": sum(r.triangles for r in reports),
                **t,
                "open3d_import_s": import_s,
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer frames and repeats")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    n, repeats = (30, 3) if args.quick else (100, 5)
    cv2.setNumThreads(1)
    config = {
        "frames": n,
        "repeats": repeats,
        "seed": args.seed,
        "h264_crf": H264_CRF,
        "h264_preset": H264_PRESET,
        "cpu_count": os.cpu_count(),
    }
    t0 = time.perf_counter()
    video = bench_video(n, repeats, args.seed)
    print(
        format_table(
            video, ["size_px", "writer", "fps", "fps_min", "fps_max", "kB", "psnr_db", "decoded_px"]
        )
    )
    print(save_results("media_video", video, config))
    mesh = bench_meshcheck(repeats)
    print(
        format_table(
            mesh, ["marker_set", "parts", "triangles", "median_ms", "max_ms", "open3d_import_s"]
        )
    )
    print(save_results("media_meshcheck", mesh, {"repeats": repeats}))
    print(f"{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
