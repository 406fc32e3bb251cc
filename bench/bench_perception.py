"""Perception benchmark: time and detection rate per pipeline, and PnP error single marker vs board.

Usage::

    python bench/bench_perception.py [--quick] [--seed 0]

Part 1, detection: synthetic 3DBM views of the docking station's markers (default DS marker set)
seen by the reference camera (HFOV 55 deg) scaled to 640x480, 968x732 and 1920x1080, from
1.2-3.5 m above the floor markers (tilt <= 15 deg), degraded like turbid water: contrast squeezed
to 255/40/20/12/8 grey levels, optical blur (sigma 1 px at 968 px width, scaled with the
width), sensor noise (1.5 grey levels), a green-blue colour cast, on a seabed whose texture
varies from bland sand to rock (relief 0.05-0.35 of the contrast). The same
frames go to every pipeline. Time: detection only, median of ``repeats`` runs per frame after a
warm-up, ``cv2.setNumThreads(1)``; the table gives the median over frames and contrast levels
and the slowest contrast level. Rate: recall = decoded visible markers / visible markers
(markers fully inside the image), false = decoded IDs that are not visible. Two more rows:
"default + prior" searches around the visible markers' corners predicted by a prior a few
pixels off (``PRIOR_SHIFT_PX``, ``PRIOR_NOISE_PX``), the whole frame when one is missed
(``in_regions``: the fraction of frames that needed no whole-frame search); "default, no OpenCV
pass" is ``opencv_pass = False`` (what the simulator's camera source runs); "opencv" is plain
OpenCV ArUco (grey, OpenCV's default parameters, both polarities), the speed reference.

Part 2, PnP: the reference camera (968x732) aimed at the floor markers' centre from 1-5 m
(tilt <= 20 deg, any yaw); true corners of the markers fully in view plus 0.5 px Gaussian noise.
"board" solves the DS pose from every visible marker (:func:`perception.pose.solve_board`),
"single" from the visible marker nearest the image centre alone (IPPE, no prior). Errors on
``T_cam_ds``: translation of the DS origin (m), rotation (deg); flip rate = rotation error
> 10 deg. ``marker_t_err`` is the single marker's own centre error (m).

Writes ``bench/results/perception_detection.json`` and ``perception_pnp.json`` (rows + machine,
commit, packages).
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import cv2
import numpy as np

from uwdock.calibration.camera import CameraModel, reference_camera
from uwdock.calibration.frames import inv_T, make_T, rotation_angle_deg, transform_points
from uwdock.dockcore.bench import format_table, save_results, time_call
from uwdock.markers.config import MarkerConfig
from uwdock.markers.dictionary import get_dictionary
from uwdock.markers.markerset import marker_set_from_config
from uwdock.perception.detector import Detector, DetectorConfig, rendered_3dbm_config
from uwdock.perception.pose import solve_board
from uwdock.perception.preprocess import PIPELINES

MARKER_SET = marker_set_from_config(MarkerConfig())
CORNERS_DS = MARKER_SET.corners_ds()
FLOOR_CENTRE = np.array([0.0, 0.233, -0.26])
RESOLUTIONS = ((640, 480), (968, 732), (1920, 1080))
LEVELS = (255, 40, 20, 12, 8)
NOISE_LEVELS = 1.5
FLIP_DEG = 10.0


# --------------------------------------------------------------------------- synthesis


def look_at(range_m: float, tilt_deg: float, az_deg: float, yaw_deg: float) -> np.ndarray:
    """T_cam_ds of a camera ``range_m`` from the floor markers' centre, tilted ``tilt_deg`` from
    straight down (towards azimuth ``az_deg``), image x along DS yaw ``yaw_deg``."""
    t, a, y = np.radians([tilt_deg, az_deg, yaw_deg])
    eye = FLOOR_CENTRE + range_m * np.array(
        [np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), -np.cos(t)]
    )
    z = (FLOOR_CENTRE - eye) / np.linalg.norm(FLOOR_CENTRE - eye)
    x = np.array([np.cos(y), np.sin(y), 0.0])
    x = (x - z * (x @ z)) / np.linalg.norm(x - z * (x @ z))
    return inv_T(make_T(np.stack([x, np.cross(z, x), z], axis=1), eye))


def random_view(rng: np.random.Generator, r_lo: float, r_hi: float, tilt_max: float) -> np.ndarray:
    return look_at(
        rng.uniform(r_lo, r_hi), rng.uniform(0, tilt_max), rng.uniform(0, 360), rng.uniform(0, 360)
    )


def visible_corners(T_cam_ds: np.ndarray, cam: CameraModel, margin_px: float) -> dict:
    """ID -> (4, 2) true pixel corners of the markers fully inside the image."""
    out = {}
    for marker_id, corners in CORNERS_DS.items():
        p = transform_points(T_cam_ds, corners)
        if np.any(p[:, 2] <= 0.05):
            continue
        px = cam.project(p)
        if np.all(cam.in_image(px, margin_px)):
            out[marker_id] = px
    return out


def _patch_3dbm(marker_id: int, cell_px: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """The 3DBM seen from above (inverted tag on a black enclosure 26 % wider), float32 [0, 1],
    and the (4, 2) tag corners TL, TR, BR, BL in patch pixels."""
    side = 6 * cell_px
    tag = cv2.aruco.generateImageMarker(
        get_dictionary(MARKER_SET.dictionary), marker_id, side, borderBits=1
    )
    margin = round(0.13 * side)
    patch = np.zeros((side + 2 * margin,) * 2, np.float32)
    patch[margin : margin + side, margin : margin + side] = (255 - tag) / 255.0
    e0, e1 = margin - 0.5, margin + side - 0.5
    return patch, np.array([[e0, e0], [e1, e0], [e1, e1], [e0, e1]])


def render(
    T_cam_ds: np.ndarray, cam: CameraModel, rng: np.random.Generator, levels: float
) -> tuple[np.ndarray, dict]:
    """Degraded BGR view and the visible markers' true corners."""
    w, h = cam.width_px, cam.height_px
    img = np.full((h, w), 0.45, np.float32)
    tex = rng.random((max(h // 24, 2), max(w // 24, 2))).astype(np.float32)
    relief = rng.uniform(0.05, 0.35)  # bland sand .. textured rock
    img += relief * (cv2.resize(tex, (w, h), interpolation=cv2.INTER_CUBIC) - 0.5)
    truth = visible_corners(T_cam_ds, cam, 2.0)
    for marker_id, dst in truth.items():
        patch, src = _patch_3dbm(marker_id)
        Hm = cv2.getPerspectiveTransform(src.astype(np.float32), dst.astype(np.float32))
        warped = cv2.warpPerspective(patch, Hm, (w, h), flags=cv2.INTER_LINEAR)
        mask = cv2.warpPerspective(np.ones_like(patch), Hm, (w, h), flags=cv2.INTER_LINEAR)
        img = img * (1 - mask) + warped
    g = 127.5 + (np.clip(img, 0, 1) - 0.5) * levels
    g = cv2.GaussianBlur(g, (0, 0), max(0.5, w / 968.0))
    g = np.stack([0.75 * g + 20, g + 30, 0.35 * g], axis=-1)
    g += rng.normal(0, NOISE_LEVELS, g.shape)
    return np.clip(g + 0.5, 0, 255).astype(np.uint8), truth


# --------------------------------------------------------------------------- part 1


#: A prior's error in the "with prior" rows: the whole board shifted by N(0, 3 px) per axis,
#: each corner by N(0, 0.5 px) more (a filter's DS pose a few centimetres off at 1-3.5 m).
PRIOR_SHIFT_PX, PRIOR_NOISE_PX = 3.0, 0.5


def _detectors() -> dict[str, tuple[Detector, bool]]:
    """Row name -> (detector, searches from a prior)."""
    ids = MARKER_SET.ids
    out = {p: (Detector(DetectorConfig(pipeline=p, ids=ids)), False) for p in PIPELINES}
    out["default + prior"] = (Detector(DetectorConfig(ids=ids)), True)
    # default without its OpenCV pass (decodes no 3DBM negative): the simulator's camera source
    out["default, no OpenCV pass"] = (Detector(rendered_3dbm_config(ids)), False)
    # plain OpenCV: grey, OpenCV's defaults, both polarities (it must decode the 3DBM negative)
    out["opencv"] = (
        Detector(DetectorConfig(pipeline="plain", ids=ids, detect_inverted=True)),
        False,
    )
    return out


def _predicted(truth: dict, rng: np.random.Generator) -> dict:
    shift = rng.normal(0, PRIOR_SHIFT_PX, 2)
    return {i: q + shift + rng.normal(0, PRIOR_NOISE_PX, q.shape) for i, q in truth.items()}


def bench_detection(n_frames: int, repeats: int, seed: int) -> list[dict]:
    rows = []
    detectors = _detectors()
    for w, h in RESOLUTIONS:
        cam = reference_camera().scaled(w, h)
        rng = np.random.default_rng(seed)
        frames = {}
        for level in LEVELS:
            frames[level] = []
            while len(frames[level]) < n_frames:
                img, truth = render(random_view(rng, 1.2, 3.5, 15.0), cam, rng, level)
                if truth:
                    frames[level].append((img, truth))
        for name, (det, with_prior) in detectors.items():
            row: dict = {"resolution": f"{w}x{h}", "pipeline": name}
            ms_all, per_level_ms, false_ids, hit_frames, n_all = [], [], 0, 0, 0
            in_regions = 0
            prng = np.random.default_rng([seed, w])
            for level, items in frames.items():
                hits = total = 0
                level_ms = []
                for img, truth in items:
                    pred = _predicted(truth, prng) if with_prior else None
                    found = {d.marker_id for d in det.detect(img, pred)}
                    in_regions += det.last_search == "regions"
                    hits += len(found & set(truth))
                    total += len(truth)
                    false_ids += len(found - set(truth))
                    hit_frames += bool(found & set(truth))
                    n_all += 1
                    level_ms.append(
                        time_call(lambda d=det, im=img, p=pred: d.detect(im, p), repeats, 0)[
                            "median_ms"
                        ]
                    )
                row[f"recall@{level}"] = hits / total
                per_level_ms.append(float(np.median(level_ms)))
                ms_all += level_ms
            row["ms_med"] = float(np.median(ms_all))
            row["ms_worst_level"] = max(per_level_ms)
            row["frame_rate"] = hit_frames / n_all
            row["false_ids"] = false_ids
            row["in_regions"] = in_regions / n_all if with_prior else ""
            rows.append(row)
            print(f"  {w}x{h} {name}: {row['ms_med']:.1f} ms", file=sys.stderr, flush=True)
    return rows


# --------------------------------------------------------------------------- part 2


def bench_pnp(trials: int, seed: int, noise_px: float = 0.5) -> list[dict]:
    cam = reference_camera()
    K, dist = cam.K, cam.dist_coeffs
    rng = np.random.default_rng(seed)
    rows = []
    centre = np.array([(cam.width_px - 1) / 2, (cam.height_px - 1) / 2])
    for range_m in (1.0, 2.0, 3.0, 4.0, 5.0):
        res = {"board": [], "single": []}
        marker_err, n_markers, ms = [], [], {"board": [], "single": []}
        done = 0
        while done < trials:
            T = look_at(range_m, rng.uniform(0, 20), rng.uniform(0, 360), rng.uniform(0, 360))
            vis = visible_corners(T, cam, 4.0)
            if not vis:
                continue
            done += 1
            noisy = {i: c + rng.normal(0, noise_px, c.shape) for i, c in vis.items()}
            nearest = min(noisy, key=lambda i: np.linalg.norm(vis[i].mean(axis=0) - centre))
            for kind, obs in (("board", noisy), ("single", {nearest: noisy[nearest]})):
                t0 = time.perf_counter()
                pose = solve_board(obs, CORNERS_DS, K, dist)
                ms[kind].append((time.perf_counter() - t0) * 1e3)
                if pose is None:
                    res[kind].append((math.inf, 180.0))
                    continue
                e_t = float(np.linalg.norm(pose.T_cam_ds[:3, 3] - T[:3, 3]))
                res[kind].append((e_t, rotation_angle_deg(pose.T_cam_ds, T)))
                if kind == "single":
                    T_ds_m = MARKER_SET[nearest].T_ds_marker
                    marker_err.append(
                        float(np.linalg.norm((pose.T_cam_ds @ T_ds_m)[:3, 3] - (T @ T_ds_m)[:3, 3]))
                    )
            n_markers.append(len(vis))
        for kind, errs in res.items():
            e = np.array(errs)
            rows.append(
                {
                    "range_m": range_m,
                    "solver": kind,
                    "markers_mean": float(np.mean(n_markers)) if kind == "board" else 1.0,
                    "t_err_med_m": float(np.median(e[:, 0])),
                    "t_err_p90_m": float(np.percentile(e[:, 0], 90)),
                    "r_err_med_deg": float(np.median(e[:, 1])),
                    "flip_rate": float(np.mean(e[:, 1] > FLIP_DEG)),
                    "marker_t_err_med_m": float(np.median(marker_err)) if kind == "single" else "",
                    "ms_med": float(np.median(ms[kind])),
                    "trials": len(errs),
                }
            )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames and trials (< 1 min)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    n_frames, repeats, trials = (2, 1, 60) if args.quick else (6, 3, 300)
    config = {
        "quick": args.quick,
        "seed": args.seed,
        "frames_per_level": n_frames,
        "repeats": repeats,
        "levels": list(LEVELS),
        "noise_levels": NOISE_LEVELS,
        "resolutions": [list(r) for r in RESOLUTIONS],
        "pnp_trials": trials,
        "pnp_noise_px": 0.5,
        "cv2_threads": 1,
    }
    t0 = time.perf_counter()
    det_rows = bench_detection(n_frames, repeats, args.seed)
    cols = ["resolution", "pipeline", "ms_med", "ms_worst_level", "frame_rate"]
    cols += [f"recall@{lv}" for lv in LEVELS] + ["false_ids", "in_regions"]
    print("\nDetection (ms = detection only, one thread; recall = visible markers decoded)")
    print(format_table(det_rows, cols))
    pnp_rows = bench_pnp(trials, args.seed)
    print("\nPnP, reference camera 968x732, 0.5 px corner noise (errors on T_cam_ds)")
    print(
        format_table(
            pnp_rows,
            [
                "range_m",
                "solver",
                "markers_mean",
                "t_err_med_m",
                "t_err_p90_m",
                "r_err_med_deg",
                "flip_rate",
                "marker_t_err_med_m",
                "ms_med",
                "trials",
            ],
        )
    )
    p1 = save_results("perception_detection", det_rows, config)
    p2 = save_results("perception_pnp", pnp_rows, config)
    print(f"\nwrote {p1} and {p2} in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
