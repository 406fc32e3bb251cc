"""Simulation benchmark: physics rate, render time, camera-in-the-loop rate, detection range.

Usage::

    python bench/bench_sim.py [--quick] [--seed 0] [--out-dir DIR --name sim_gpu]
    python bench/bench_sim.py --baseline 248412c [--quick] [--baseline-repeats 3]

(a) Physics without camera, one process: control steps per second of
    ``rl.env.docking_env.DockingEnv`` (proxy observation source, 300 Hz physics, 5 Hz control,
    uniform random actions, resets when an episode ends) and of the bare
    ``sim.physics.VehicleBody.step`` (60 substeps per control step; in the tank with the DS, random
    wrenches up to half the env limits, a new random pose every 50 steps), with the free-flight fast
    path on and off where the vehicle has one (``fast_share`` = steps that took it). Median and
    spread over ``runs`` runs of ``steps`` steps after a warm-up.
(b) Render time per frame on the CPU (SAPIEN rasteriser on lavapipe, its default thread count),
    reference camera scaled to 320x240, 640x480 and 968x732, over aimed poses of the synth
    sampler (DS at 1-6 m); also ``render + water`` (coastal preset).
(c) Camera in the loop: per control step the env camera source's path: capture (render + water,
    coastal; ``sim.camera.SimCamera``), the RGB -> BGR conversion at the seam, and the DS-pose
    estimator as the camera source builds it (``perception.ds_pose`` with
    ``perception.detector.rendered_3dbm_config``: the default pipeline without the OpenCV pass,
    which decodes no 3DBM; one OpenCV thread, board PnP, level-DS refinement), at widths 320,
    480, 640 and 968; the physics step time from (a) is added for the control-step rate. Also the
    share of frames with a pose.
(d) Detection range: the reference camera at 968, 640 and 480 px wide straight above the DS
    origin (image x along DS y), altitude 1-10 m above the DS floor in 0.5 m steps, in a 12 m
    deep tank (so the camera stays under water); per water preset the greatest altitude at
    which the median over noise draws of the number of decoded DS markers is >= 3 and >= 1.
    (Two DS markers are on the rim, 1.76 m up: below ~2.3 m altitude the camera sees only the
    floor markers.)

Writes ``bench/results/sim.json`` (rows + machine, commit, packages).

``--baseline COMMIT`` runs only section (c) (with the physics step of (a) it adds), for the
working tree and for COMMIT side by side in one run: COMMIT is extracted with ``git archive``
into a temporary folder (the repository and its git state are only read), given the
``uwdock/<pkg>`` links an installed checkout has, and each side runs in its own subprocess of
this Python, importing only its own tree (checked: a module loaded from elsewhere stops the
run), with its own ``bench_loop``/``bench_physics`` (so a side is timed by the bench of its
day: before ``perception.ds_pose`` existed, "estimate" is detect + board PnP and "capture" is
render + water + RGB->BGR). The sides alternate (old, new, new, old, ...) over
``--baseline-repeats`` rounds; the table gives per width the medians over rounds and the ratio
new/old of control steps/s, capture ms and estimate ms. Writes ``sim_baseline.json``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from uwdock.calibration.camera import reference_camera, scaled_to_width
from uwdock.calibration.frames import make_T
from uwdock.dockcore.bench import format_table, save_results, time_call

RESOLUTIONS = ((320, 240), (640, 480), (968, 732))
LOOP_WIDTHS = (320, 480, 640, 968)
RANGE_WIDTHS = (968, 640, 480)


def _rate(fn, steps: int, runs: int) -> dict[str, float]:
    """Steps per second of ``fn`` (one step per call): median, min, max over runs."""
    fn()  # warm-up
    rates = []
    for _ in range(runs):
        t0 = time.perf_counter()
        for _ in range(steps):
            fn()
        rates.append(steps / (time.perf_counter() - t0))
    return {"median": statistics.median(rates), "min": min(rates), "max": max(rates)}


def bench_physics(steps: int, runs: int, seed: int) -> list[dict]:
    import inspect

    from uwdock.rl.env.config import EnvConfig
    from uwdock.rl.env.docking_env import DockingEnv
    from uwdock.sim.docking_station import build_docking_station, build_tank
    from uwdock.sim.physics import VehicleBody, make_physics_scene

    env = DockingEnv(EnvConfig())
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)

    def env_step() -> None:
        _, _, term, trunc, _ = env.step(rng.uniform(-1.0, 1.0, 6))
        if term or trunc:
            env.reset(seed=int(rng.integers(1 << 31)))

    env_rate = _rate(env_step, steps, runs)
    rows = [
        {
            "what": "DockingEnv.step (proxy)",
            "steps_per_s": env_rate["median"],
            "min": env_rate["min"],
            "max": env_rate["max"],
            "ms_per_step": 1e3 / env_rate["median"],
        }
    ]
    # the bare vehicle in the env's tank with the DS; reset every 50 steps to a spawn-like pose
    has_fast = "fast_path" in inspect.signature(VehicleBody).parameters
    for fast in (True, False) if has_fast else (None,):
        scene = make_physics_scene()
        build_tank(scene, visual=False, surface_lid=True)
        build_docking_station(scene, visual=False)
        vb = VehicleBody(scene) if fast is None else VehicleBody(scene, fast_path=fast)
        pose_rng = np.random.default_rng(seed)
        wrench_scale = np.array([140.0, 70.0, 134.0, 0.0, 20.0, 36.0])  # half the env limits
        count = {"steps": 0, "fast": 0}

        def raw_step(vb=vb, pose_rng=pose_rng, count=count, wrench_scale=wrench_scale) -> None:
            if count["steps"] % 50 == 0:
                p = pose_rng.uniform([-5.0, -3.0, 1.0], [5.0, 3.0, 3.5])
                vb.reset(make_T(t=p))
            vb.step(pose_rng.uniform(-1.0, 1.0, 6) * wrench_scale, 0.2)
            count["steps"] += 1
            count["fast"] += int(bool(getattr(vb, "last_step_fast", False)))

        r = _rate(raw_step, steps, runs)
        label = {None: "", True: ", fast path on", False: ", fast path off"}[fast]
        rows.append(
            {
                "what": f"VehicleBody.step (60 substeps{label})",
                "steps_per_s": r["median"],
                "min": r["min"],
                "max": r["max"],
                "ms_per_step": 1e3 / r["median"],
                "fast_share": count["fast"] / max(count["steps"], 1),
            }
        )
    return rows


def _aimed_poses(camera, T_body_cam, T_world_ds, n: int, seed: int) -> list[np.ndarray]:
    from uwdock.datasets.synth import PoseSamplingConfig, frame_rng, sample_pose

    cfg = PoseSamplingConfig(aimed_fraction=1.0)
    draws = (sample_pose(cfg, frame_rng(seed, k), camera, T_body_cam, T_world_ds) for k in range(n))
    return [T for T, _ in draws]


def bench_render(n_poses: int, repeats: int, seed: int) -> list[dict]:
    from uwdock.sim.render import CameraRig, make_render_scene
    from uwdock.sim.water import PRESETS, apply_water

    base = reference_camera()
    rs = make_render_scene()
    T_body_cam = rs.rig.T_bodyfrd_camcv
    rows = []
    for w, h in RESOLUTIONS:
        cam = base.scaled(w, h)  # fixed sizes (4:3 and the reference), not a width
        rig = CameraRig(rs.scene, cam, name=f"bench_{w}")
        rs.rig.set_lamp(False)
        poses = _aimed_poses(cam, T_body_cam, rs.ds.T_worldned_ds, n_poses, seed)
        rig.render(poses[0])  # warm-up (pipeline creation)
        t_render = time_call(lambda rig=rig, poses=poses: [rig.render(T) for T in poses], repeats)
        results = [rig.render(T) for T in poses]
        water_rng = np.random.default_rng(seed)
        t_water = time_call(
            lambda results=results, rng=water_rng: [
                apply_water(r.radiance, r.range_m, PRESETS["coastal"], rng) for r in results
            ],
            repeats,
        )
        rows.append(
            {
                "resolution": f"{w}x{h}",
                "render_ms": t_render["median_ms"] / n_poses,
                "render_ms_min": t_render["min_ms"] / n_poses,
                "water_ms": t_water["median_ms"] / n_poses,
                "render_water_ms": (t_render["median_ms"] + t_water["median_ms"]) / n_poses,
                "frames_per_s": 1e3 * n_poses / (t_render["median_ms"] + t_water["median_ms"]),
            }
        )
        rig.set_lamp(False)
    return rows


def bench_loop(n_poses: int, repeats: int, seed: int, physics_ms: float) -> list[dict]:
    from uwdock.perception.detector import rendered_3dbm_config
    from uwdock.perception.ds_pose import DSPoseEstimator
    from uwdock.sim.camera import SimCamera
    from uwdock.sim.render import CameraRig, make_render_scene
    from uwdock.sim.water import PRESETS

    base = reference_camera()
    rs = make_render_scene()
    rs.rig.set_lamp(False)
    estimator = DSPoseEstimator.from_marker_set(rs.ds.marker_set, rendered_3dbm_config())
    rows = []
    for width in LOOP_WIDTHS:
        cam = scaled_to_width(base, width)
        rig = CameraRig(rs.scene, cam, name=f"loop_{width}")
        sim_cam = SimCamera(rig, PRESETS["coastal"])
        T_bc = sim_cam.T_body_cam
        poses = _aimed_poses(cam, T_bc, rs.ds.T_worldned_ds, n_poses, seed)
        rig.render(poses[0])
        stage = {"capture": [], "to_bgr": [], "estimate": []}
        solved = 0
        rng = np.random.default_rng(seed)
        for _ in range(repeats):
            solved = 0
            for T in poses:
                # the env's camera source: capture, convert at the seam, estimate (level DS)
                t0 = time.perf_counter()
                frame = sim_cam.capture(T, rng)
                t1 = time.perf_counter()
                img_bgr = frame.img_bgr()
                t2 = time.perf_counter()
                est = estimator.estimate(img_bgr, cam, T @ T_bc)
                t3 = time.perf_counter()
                solved += est.T_cam_ds is not None
                for key, dt in zip(stage, (t1 - t0, t2 - t1, t3 - t2), strict=True):
                    stage[key].append(dt * 1e3)
        med = {k: statistics.median(v) for k, v in stage.items()}
        camera_ms = sum(med.values())
        rows.append(
            {
                "width": f"{cam.width_px}x{cam.height_px}",
                "capture_ms": med["capture"],
                "to_bgr_ms": med["to_bgr"],
                "estimate_ms": med["estimate"],
                "camera_ms": camera_ms,
                "control_steps_per_s": 1e3 / (camera_ms + physics_ms),
                "pose_rate": solved / len(poses),
            }
        )
        rig.set_lamp(False)
    return rows


def bench_range(altitudes: np.ndarray, draws: int, seed: int, width_px: int) -> list[dict]:
    """Section (d) through the tank report's own function
    (:func:`uwdock.datasets.tank_report.detection_ranges`), so the two cannot drift apart."""
    from uwdock.datasets.tank_report import TankReportConfig, detection_ranges
    from uwdock.sim.water import PRESET_ORDER, PRESETS

    step = float(altitudes[1] - altitudes[0]) if altitudes.size > 1 else 1.0
    cfg = TankReportConfig(
        altitude_min_m=float(altitudes[0]),
        altitude_max_m=float(altitudes[-1]),
        altitude_step_m=step,
        draws=draws,
        seed=seed,
    )
    cam = scaled_to_width(reference_camera(), width_px)
    rows = detection_ranges(cam, {p: PRESETS[p] for p in PRESET_ORDER}, cfg)
    return [
        {
            "width": r["width"],
            "water": r["water"],
            "max_alt_3_markers_m": r["max_alt_3_markers_m"],
            "max_alt_1_marker_m": r["max_alt_1_marker_m"],
            "detected_by_altitude": " ".join(f"{v:g}" for v in r["decoded_median"]),
        }
        for r in rows
    ]


def render_device() -> str:
    """The renderer SAPIEN picked (first line of its device summary, e.g. llvmpipe or a GPU)."""
    import sapien

    sapien.render.RenderSystem()  # creates the default device
    lines = sapien.render.get_device_summary().splitlines()
    return lines[0].removeprefix("GPU:").strip() if lines else "unknown"


#: The subprocess of one side of ``--baseline``: argv = tree, config JSON. Imports nothing of
#: uwdock before the tree is first on sys.path; prints one JSON line last.
_SIDE = r"""
import importlib.util, json, os, sys
tree, cfg = os.path.realpath(sys.argv[1]), json.loads(sys.argv[2])
sys.path.insert(0, tree)
import cv2
cv2.setNumThreads(1)
path = os.path.join(tree, "bench", "bench_sim.py")
spec = importlib.util.spec_from_file_location("bench_side", path)
mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)
mod.LOOP_WIDTHS = tuple(cfg["widths"])
phys = mod.bench_physics(cfg["physics_steps"], cfg["physics_runs"], cfg["seed"])
physics_ms = phys[0]["ms_per_step"]
loop = mod.bench_loop(cfg["loop_poses"], cfg["loop_repeats"], cfg["seed"], physics_ms)
pkgs = ("uwdock", "calibration", "dockcore", "markers", "perception", "sim", "datasets", "rl")
foreign = sorted(
    name for name, m in list(sys.modules.items())
    if name.split(".")[0] in pkgs and getattr(m, "__file__", None)
    and not os.path.realpath(m.__file__).startswith(tree + os.sep)
)
print(json.dumps({"physics_ms": physics_ms, "loop": loop, "foreign_modules": foreign}))
"""

#: The uwdock subpackages an installed checkout links into ``uwdock/`` (the editable install's
#: finder would otherwise load them from the working tree).
_PKGS = ("calibration", "dockcore", "markers", "perception", "sim", "datasets", "rl")


def _extract(commit: str, root: Path, dest: Path) -> str:
    """``git archive`` COMMIT into ``dest`` (read-only on the repository); its full hash."""
    import subprocess
    import tarfile

    full = subprocess.run(
        ["git", "-C", str(root), "rev-parse", "--verify", f"{commit}^{{commit}}"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    if full.returncode != 0:
        raise SystemExit(f"error: --baseline {commit}: not a commit of {root}")
    sha = full.stdout.strip()
    tar = dest.with_suffix(".tar")
    with tar.open("wb") as fh:
        subprocess.run(["git", "-C", str(root), "archive", sha], stdout=fh, check=True)
    with tarfile.open(tar) as tf:
        tf.extractall(dest, filter="data")
    tar.unlink()
    if (dest / "uwdock").is_dir():  # the namespace package: its subpackages as links
        for pkg in _PKGS:
            if (dest / pkg).is_dir() and not (dest / "uwdock" / pkg).exists():
                (dest / "uwdock" / pkg).symlink_to(Path("..") / pkg)
    return sha


def _side(tree: Path, cfg: dict) -> dict:
    import json
    import subprocess

    res = subprocess.run(
        [sys.executable, "-c", _SIDE, str(tree), json.dumps(cfg)],
        capture_output=True, text=True, cwd=tree, check=False,
    )  # fmt: skip
    lines = res.stdout.strip().splitlines()
    if res.returncode != 0 or not lines:
        tail = " | ".join(res.stderr.strip().splitlines()[-3:])
        raise SystemExit(f"error: the bench of {tree} failed: {tail}")
    out = json.loads(lines[-1])
    if out["foreign_modules"]:
        raise SystemExit(f"error: {tree} loaded modules of another tree: {out['foreign_modules']}")
    return out


def _loop_numbers(row: dict) -> dict[str, float]:
    """capture / estimate ms of a ``bench_loop`` row of either day's layout."""
    capture = row.get("capture_ms")
    if capture is None:  # before sim.camera: render + water (RGB->BGR included)
        capture = row["render_ms"] + row["water_ms"]
    estimate = row.get("estimate_ms")
    if estimate is None:  # before perception.ds_pose: detect + board PnP
        estimate = row["detect_ms"] + row["pnp_ms"]
    return {
        "control_steps_per_s": row["control_steps_per_s"],
        "capture_ms": capture,
        "estimate_ms": estimate,
        "camera_ms": row["camera_ms"],
    }


def run_baseline(commit: str, quick: bool, repeats: int, seed: int, out_dir: Path | None) -> None:
    """``--baseline``: section (c) of the working tree and of ``commit``, interleaved."""
    import tempfile

    root = Path(__file__).resolve().parent.parent
    cfg = {
        "seed": seed,
        "widths": list(LOOP_WIDTHS),
        "physics_steps": 100 if quick else 300,
        "physics_runs": 3 if quick else 7,
        "loop_poses": 5 if quick else 24,
        "loop_repeats": 1 if quick else 3,
    }
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="uwdock-baseline-") as tmp:
        old_tree = Path(tmp) / "tree"
        sha = _extract(commit, root, old_tree)
        sides = {"old": old_tree, "new": root}
        runs: dict[str, list[dict]] = {"old": [], "new": []}
        for k in range(repeats):
            for name in ("old", "new") if k % 2 == 0 else ("new", "old"):
                print(f"round {k + 1}/{repeats}: {name} ({sides[name]})", flush=True)
                runs[name].append(_side(sides[name], cfg))
    rows = []
    for i, width in enumerate(LOOP_WIDTHS):
        med = {}
        for name in ("old", "new"):
            per = [_loop_numbers(r["loop"][i]) for r in runs[name]]
            med[name] = {k: statistics.median(p[k] for p in per) for k in per[0]}
            med[name]["physics_ms"] = statistics.median(r["physics_ms"] for r in runs[name])
        o, n = med["old"], med["new"]
        rows.append(
            {
                "width_px": width,
                "old_steps_per_s": o["control_steps_per_s"],
                "new_steps_per_s": n["control_steps_per_s"],
                "steps_ratio": n["control_steps_per_s"] / o["control_steps_per_s"],
                "old_capture_ms": o["capture_ms"],
                "new_capture_ms": n["capture_ms"],
                "capture_ratio": n["capture_ms"] / o["capture_ms"],
                "old_estimate_ms": o["estimate_ms"],
                "new_estimate_ms": n["estimate_ms"],
                "estimate_ratio": n["estimate_ms"] / o["estimate_ms"],
                "old_physics_ms": o["physics_ms"],
                "new_physics_ms": n["physics_ms"],
            }
        )
    print(
        f"\n(c) Camera in the loop, working tree (new) against {commit} = {sha[:12]} (old), "
        f"{repeats} interleaved rounds, medians; ratio = new / old (steps: > 1 is faster; "
        "ms: < 1 is faster)"
    )
    print(
        format_table(
            rows,
            ["width_px", "old_steps_per_s", "new_steps_per_s", "steps_ratio", "old_capture_ms",
             "new_capture_ms", "capture_ratio", "old_estimate_ms", "new_estimate_ms",
             "estimate_ratio", "old_physics_ms", "new_physics_ms"],
        )
    )  # fmt: skip
    config = {**cfg, "quick": quick, "baseline": commit, "baseline_commit": sha,
              "rounds": repeats, "opencv_threads": 1,
              "lp_num_threads": os.environ.get("LP_NUM_THREADS"), "raw": runs}  # fmt: skip
    path = save_results("sim_baseline", rows, config, out_dir=out_dir)
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer runs and poses (~1 min)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--out-dir", type=Path, default=None, help="results folder (default bench/results)"
    )
    parser.add_argument(
        "--name", default="sim", help="results file stem (e.g. sim_gpu for a GPU machine)"
    )
    parser.add_argument(
        "--baseline",
        metavar="COMMIT",
        help="only the camera loop (c), of the working tree and of COMMIT side by side in one "
        "run, interleaved; reports new/old ratios (sim_baseline.json)",
    )
    parser.add_argument(
        "--baseline-repeats",
        type=int,
        default=None,
        help="interleaved rounds of each side with --baseline [2 with --quick, else 4]",
    )
    args = parser.parse_args()
    cv2.setNumThreads(1)
    quick = args.quick
    if args.baseline:
        repeats = args.baseline_repeats or (2 if quick else 4)
        run_baseline(args.baseline, quick, repeats, args.seed, args.out_dir)
        return
    config = {
        "quick": quick,
        "seed": args.seed,
        "physics_steps": 100 if quick else 300,
        "physics_runs": 3 if quick else 7,
        "render_poses": 5 if quick else 16,
        "render_repeats": 2 if quick else 5,
        "loop_poses": 5 if quick else 24,
        "loop_repeats": 1 if quick else 3,
        "range_step_m": 1.0 if quick else 0.5,
        "range_draws": 1 if quick else 5,
        "lp_num_threads": os.environ.get("LP_NUM_THREADS"),
        "opencv_threads": 1,
        "render_device": render_device(),
    }
    t0 = time.perf_counter()
    rows: list[dict] = []

    phys = bench_physics(config["physics_steps"], config["physics_runs"], args.seed)
    print("\n(a) Physics, no camera (300 Hz physics, 5 Hz control, one process)")
    cols = ["what", "steps_per_s", "min", "max", "ms_per_step", "fast_share"]
    print(format_table(phys, cols))
    rows += [{"section": "physics", **r} for r in phys]

    rend = bench_render(config["render_poses"], config["render_repeats"], args.seed)
    print(
        f"\n(b) Render per frame on {config['render_device']}, aimed poses 1-6 m; "
        "water = coastal preset"
    )
    print(
        format_table(
            rend,
            ["resolution", "render_ms", "render_ms_min", "water_ms", "render_water_ms",
             "frames_per_s"],
        )
    )  # fmt: skip
    rows += [{"section": "render", **r} for r in rend]

    physics_ms = phys[0]["ms_per_step"]
    loop = bench_loop(config["loop_poses"], config["loop_repeats"], args.seed, physics_ms)
    print(
        f"\n(c) Camera in the loop per control step (+ {physics_ms:.1f} ms env physics step); "
        "coastal water, default pipeline, level DS"
    )
    print(
        format_table(
            loop,
            ["width", "capture_ms", "to_bgr_ms", "estimate_ms", "camera_ms",
             "control_steps_per_s", "pose_rate"],
        )
    )  # fmt: skip
    rows += [{"section": "camera_loop", **r} for r in loop]

    altitudes = np.arange(1.0, 10.0 + 1e-9, config["range_step_m"])
    rng_rows = [
        r for w in RANGE_WIDTHS for r in bench_range(altitudes, config["range_draws"], args.seed, w)
    ]
    print(
        "\n(d) Detection range straight above the DS origin (altitude above the DS floor; "
        f"counts = median decoded markers at {altitudes[0]:g}..{altitudes[-1]:g} m)"
    )
    print(
        format_table(
            rng_rows,
            ["width", "water", "max_alt_3_markers_m", "max_alt_1_marker_m", "detected_by_altitude"],
        )
    )
    rows += [{"section": "range", **r} for r in rng_rows]
    path = save_results(args.name, rows, config, out_dir=args.out_dir)
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
