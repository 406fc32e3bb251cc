"""The vehicle node's latency budget: a camera frame from arrival to command, per stage, on one
core, at 720p and 1080p; and the node's start time.

Usage::

    python bench/bench_node.py [--quick] [--frames 40] [--repeats 5] [--json] [--out-dir DIR]

Frames: the docking station rendered by ``datasets synth`` (coastal water, seed 0) through a
16:9 camera of 55 deg horizontal field of view at 1280x720 and 1920x1080, seen from the heights
and angles of a docking approach. Each frame is sent as the node receives it, as
``sensor_msgs/Image`` (bgr8) and as ``sensor_msgs/CompressedImage`` (JPEG quality 90, and 25:
heavy compression, where the detector's views for compressed frames add the most work), and
runs through the node's own chain (:class:`uwdock.rl.deploy.chain.DockingChain` with the shipped
policy, ONNX): deserialise the CDR bytes, decode the image, detect the markers and solve the
board pose (the chain resizes the frame to the policy's camera width first, as the simulated
camera rendered it in training), fuse it in the DS filter, run the policy. The process is
pinned to one core (``sched_setaffinity``; OpenCV and onnxruntime on one thread). Each frame is
timed ``repeats`` times after a warm-up pass; the table gives p50 and p99 over all frames and
repeats, per stage.

Start time: ``rl node`` started as a process until its first ``/diagnostics`` message arrives on
a loopback DDS domain (median of ``repeats`` starts).

``--json`` prints one line last: ``{"p50_ms": {"720": ..., "1080": ...}, "p99_ms": {...}}`` for
the JPEG quality 90 frames (what vehicles send). Writes ``bench/results/node_latency.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from uwdock.calibration.camera import REFERENCE_T_BODYFRD_CAMCV, CameraModel, save_camera
from uwdock.dockcore.bench import format_table, save_results
from uwdock.dockcore.config import from_dict
from uwdock.rl.deploy.cli import SHIPPED_POLICY, build_chain
from uwdock.rl.deploy.config import NodeConfig
from uwdock.rl.deploy.inputs import NavSample, read_image
from uwdock.ros import messages as rm

ROOT = Path(__file__).resolve().parent.parent
SIZES = {"720": (1280, 720), "1080": (1920, 1080)}
STAGES = ("deserialize", "decode", "perception", "filter", "policy", "total")


def render(folder: Path, size: tuple[int, int], n: int) -> tuple[list[np.ndarray], list, Path]:
    """``n`` rendered frames of the DS at ``size`` with their camera poses, and the camera
    file."""
    w, h = size
    cam_file = folder / f"cam_{h}.yaml"
    save_camera(
        cam_file, CameraModel.from_hfov(w, h, 55.0, "bench_16x9"), REFERENCE_T_BODYFRD_CAMCV
    )
    out = folder / f"synth_{h}"
    subprocess.run(
        [sys.executable, "-m", "uwdock.cli", "datasets", "synth", "--n", str(n), "--water",
         "coastal", "--seed", "0", "--camera", str(cam_file), "--width", str(w), "--quiet",
         "--out", str(out)],
        check=True, stdout=subprocess.DEVNULL,
    )  # fmt: skip
    labels = [json.loads(line) for line in (out / "labels.jsonl").read_text().splitlines()]
    frames = [cv2.imread(str(out / lab["image"])) for lab in labels]
    return frames, labels, cam_file


def time_chain(frames, labels, cam_file: Path, jpeg_quality: int | None, repeats: int) -> dict:
    """Per-stage times (ms) of every frame through the node's chain, ``repeats`` passes, sent
    as raw ``Image`` (``jpeg_quality`` None) or as JPEG ``CompressedImage``."""
    cfg = from_dict(NodeConfig, {"flat_markers": True})
    chain = build_chain(SHIPPED_POLICY, cam_file, None, cfg, armed=True)
    T_body_cam = chain.runner.T_body_cam
    msgs = []
    for k, (img, lab) in enumerate(zip(frames, labels, strict=True)):
        t = (k + 1) * chain.period_ns
        compressed = jpeg_quality is not None
        m = (
            rm.compressed_image_msg(img, t, "camera", jpeg_quality)
            if compressed
            else rm.image_msg(img, t, "camera")
        )
        typename = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
        T_cam_ds = np.array(lab["T_cam_ds"], dtype=np.float64)
        msgs.append((t, rm.serialize(m, typename), typename, T_cam_ds))
    samples = {s: [] for s in STAGES}
    t_base, frames_with_pose = 0, 0
    for rep in range(repeats + 1):
        t_base += (len(msgs) + 10) * chain.period_ns
        T_world_ds = np.eye(4)
        T_world_ds[2, 3] = 8.0
        chain.on_ds_prior(t_base, T_world_ds, np.array([1.0, 1.0, 0.09, 0.07]))
        for t, cdr, typename, T_cam_ds in msgs:
            now = t_base + t
            # the vehicle where the frame was taken: T_world_ds T_ds_cam T_cam_body
            T_wb = T_world_ds @ np.linalg.inv(T_cam_ds) @ np.linalg.inv(T_body_cam)
            chain.on_nav(NavSample(now, T_wb, np.zeros(3), np.zeros(3)))
            t0 = time.perf_counter()
            msg = rm.deserialize(cdr, typename)
            t_des = (time.perf_counter() - t0) * 1e3
            chain.on_frame(now, lambda msg=msg: read_image(msg))
            tick = chain.tick(now)
            if rep == 0:
                frames_with_pose += tick.measurement is not None
                continue  # warm-up pass
            samples["deserialize"].append(t_des)
            for s in ("decode", "perception", "filter", "policy"):
                samples[s].append(tick.latency_ms[s])
            samples["total"].append(t_des + tick.latency_ms["total"])
    return {"samples": samples, "frames_with_pose": frames_with_pose}


def start_time(repeats: int) -> list[float]:
    """Seconds from starting ``rl node`` to its first diagnostics on a loopback domain."""
    from uwdock.ros.dds import DdsGraph
    from uwdock.ros.qos import QosProfile

    domain = 200 + os.getpid() % 30
    graph = DdsGraph(domain)
    sub = graph.subscription("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", QosProfile())
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        proc = subprocess.Popen(
            [sys.executable, "-m", "uwdock.cli", "rl", "node", "--domain-id", str(domain),
             "--duration-s", "30"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            while time.perf_counter() - t0 < 60:
                graph.wait(0.05)
                if sub.take():
                    out.append(time.perf_counter() - t0)
                    break
        finally:
            proc.terminate()
            proc.wait(timeout=60)
        time.sleep(0.5)
        sub.take()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="12 frames, 3 repeats, 2 starts")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--out-dir", type=Path, default=None)
    a = ap.parse_args()
    n, repeats = (12, 3) if a.quick else (a.frames, a.repeats)
    if not (1 <= n <= 1000 and 1 <= repeats <= 100):
        ap.error("--frames 1 ... 1000 and --repeats 1 ... 100")
    core = min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {core})
    cv2.setNumThreads(1)
    rows, p50, p99 = [], {}, {}
    with tempfile.TemporaryDirectory(prefix="uwdock-bench-node-") as tmp:
        for label, size in SIZES.items():
            frames, labels, cam = render(Path(tmp), size, n)
            for quality in (None, 90, 25):
                r = time_chain(frames, labels, cam, quality, repeats)
                fmt = "raw bgr8" if quality is None else f"jpeg q{quality}"
                for stage in STAGES:
                    v = np.array(r["samples"][stage])
                    rows.append({
                        "size": f"{size[0]}x{size[1]}", "message": fmt, "stage": stage,
                        "p50_ms": float(np.percentile(v, 50)),
                        "p99_ms": float(np.percentile(v, 99)),
                        "n": int(v.size), "frames_with_pose": r["frames_with_pose"],
                    })  # fmt: skip
                total = np.array(r["samples"]["total"])
                if quality == 90:
                    p50[label] = float(np.percentile(total, 50))
                    p99[label] = float(np.percentile(total, 99))
    starts = start_time(2 if a.quick else repeats)
    cols = ["size", "message", "stage", "p50_ms", "p99_ms", "n", "frames_with_pose"]
    print(format_table(rows, cols))
    start_s = float(np.median(starts)) if starts else None
    print(f"rl node start to first diagnostics: {start_s} s (median of {len(starts)})")
    config = {"frames": n, "repeats": repeats, "core": core, "start_s": starts,
              "water": "coastal", "hfov_deg": 55.0}  # fmt: skip
    path = save_results("node_latency", rows, config, a.out_dir)
    print(f"wrote {path}")
    if a.json:
        print(json.dumps({"p50_ms": p50, "p99_ms": p99, "start_s": start_s}))


if __name__ == "__main__":
    main()
