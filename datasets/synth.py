"""Labelled synthetic datasets: render the docking station from random AUV poses, apply water,
write images and ground truth in the ``uwdock.dataset`` format (see :mod:`perception.groundtruth`).

Poses (:func:`sample_pose`). Each frame is either

* *aimed* (probability ``aimed_fraction``, default 80 %): the DS origin is put on a random pixel
  (uniform over the image minus a margin) at a random range (``aimed_range_m``) from a camera
  whose optical axis is tilted up to ``aimed_tilt_max_deg`` from straight down (vehicle roll and
  pitch), any yaw; so the DS is in view, or at least its origin is;
* *uniform*: the AUV origin uniform within +-``uniform_range_m`` of the point
  ``uniform_height_m`` above the DS origin (the env's spawn box), any yaw, a small tilt.

A pose is redrawn (up to 200 times) when the camera would be above the water surface (less than
``min_depth_m`` deep), less than ``min_height_m`` above the DS floor, or the vehicle outside the
tank; so aimed ranges that the tank cannot hold (e.g. 6 m straight down in a 5 m tank) come out
as oblique views.

Determinism: frame k draws everything (pose, random water, sensor noise) from
``np.random.default_rng(SeedSequence([seed, k]))``; the frame's output depends only on
``(config, k)``, so any number of worker processes gives byte-identical files. (A
``SeedSequence`` of the pair rather than ``seed + k``: datasets with seeds 0 and 1 share no frame.)

Crash safety and resume: the output folder is claimed (:func:`dockcore.outdir.claim_output_dir`:
locked while a run writes it, so a second run into it stops at once; refused when another tool
made it; temporary files of killed runs removed). A frame's image is written (atomic rename)
before its label, which goes to its own file ``.partial/<k>.json`` (atomic rename). A frame
counts as done when its image is a complete PNG of the right size (its chunks and checksums are
read, so an empty, truncated or corrupted file is rendered again) and its label (a partial file
or a line of an existing ``labels.jsonl``) is there; a rerun renders only the other frames, then
``labels.jsonl`` is assembled atomically in frame order, the partial files removed, and
``dataset.json`` written last (its presence marks a complete dataset; it is removed when a run
starts). A rerun with another config (other than ``n_frames``) is refused, and so is a smaller
``n_frames`` than the folder holds (it would delete frames); a larger one extends the dataset.
Worker processes end with the run, however it ends (:func:`dockcore.procs.die_with_parent`).

Example:
    >>> cfg = SynthConfig(n_frames=200, water="coastal")
    >>> result = generate("data/synth_coastal", cfg, workers=2)
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import cv2
import numpy as np
from numpy.typing import ArrayLike
from tqdm import tqdm

from uwdock.calibration.camera import CameraModel, resolve_camera
from uwdock.calibration.frames import R_from_rpy, check_T, inv_T, make_T
from uwdock.datasets.sequences import FrameSequences
from uwdock.datasets.synth_config import PoseSamplingConfig, SynthConfig, station_config
from uwdock.datasets.synth_folder import (
    IMAGE_NAME,
    PARTIAL_DIR,
    STATE_FILE,
    assemble_labels,
    check_folder,
    done_frames,
    folder_state,
    prepare_folder,
)
from uwdock.dockcore.config import from_dict, to_dict, validated
from uwdock.dockcore.domains import Interval, check, split_annotated
from uwdock.dockcore.errors import ConfigError, DockError
from uwdock.dockcore.io import atomic_path, atomic_write_bytes, atomic_write_json
from uwdock.dockcore.outdir import claim_output_dir
from uwdock.dockcore.pool import PoolConfig, preflight, worker_pool
from uwdock.dockcore.procs import workers_ended_on_error
from uwdock.markers.markerset import MarkerSet, marker_set_files
from uwdock.perception.groundtruth import (
    FrameTruth,
    MarkerTruth,
    frame_truth_to_json,
    range_m,
    view_angle_deg,
    write_dataset_json,
)
from uwdock.sim.camera import SimCamera
from uwdock.sim.docking_station import DockingStationConfig, resolve_marker_set
from uwdock.sim.domains import TANK_SIZE_M
from uwdock.sim.render import make_render_scene, project_markers
from uwdock.sim.water import (
    WaterConfig,
    is_water_file,
    resolve_water,
)

__all__ = [
    "PoseSamplingConfig",
    "SynthConfig",
    "SynthResult",
    "Workers",
    "camera_outside_tank",
    "frame_rng",
    "generate",
    "sample_pose",
]

_MAX_DRAWS = 200

#: Worker processes of a run (each holds a renderer: a few hundred MB).
Workers = Annotated[int, Interval(ge=1, le=64)]


@dataclass(frozen=True)
class SynthResult:
    """What :func:`generate` did.

    Attributes:
        out_dir: the dataset folder.
        frames: frames in the dataset.
        rendered: frame indices rendered by this run (ascending).
        seconds: wall time of the run (s).
        ray: with the Ray backend, where the frames were rendered (``tasks_by_node``: node ID
            -> frames) and how many lost workers were replaced (``workers_replaced``); empty
            otherwise.
    """

    out_dir: Path
    frames: int
    rendered: tuple[int, ...]
    seconds: float
    ray: dict[str, Any] = field(default_factory=dict)


# ----------------------------------------------------------------------------- poses


def frame_rng(seed: int, k: int) -> np.random.Generator:
    """The generator of frame ``k`` (pose, water draw, sensor noise)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(k)]))


def _tilted_yaw(rng: np.random.Generator, tilt_max_deg: float) -> np.ndarray:
    """(3, 3) R_world_body: any yaw, then a tilt uniform over the cap about a random horizontal
    axis."""
    yaw = rng.uniform(-math.pi, math.pi)
    cos_t = rng.uniform(math.cos(math.radians(tilt_max_deg)), 1.0)
    tilt, azimuth = math.acos(cos_t), rng.uniform(-math.pi, math.pi)
    axis = np.array([math.cos(azimuth), math.sin(azimuth), 0.0])
    from scipy.spatial.transform import Rotation  # half a second to import: only when sampling

    return Rotation.from_rotvec(tilt * axis).as_matrix() @ R_from_rpy(0.0, 0.0, yaw)


def _aimed(
    cfg: PoseSamplingConfig,
    rng: np.random.Generator,
    camera: CameraModel,
    T_body_cam: np.ndarray,
    T_world_ds: np.ndarray,
) -> np.ndarray:
    R_world_cam = _tilted_yaw(rng, cfg.aimed_tilt_max_deg) @ T_body_cam[:3, :3]
    m = cfg.aimed_image_margin
    uv = np.array(
        [
            rng.uniform(m * camera.width_px, (1 - m) * camera.width_px) - 0.5,
            rng.uniform(m * camera.height_px, (1 - m) * camera.height_px) - 0.5,
        ]
    )
    xy = cv2.undistortPoints(uv.reshape(1, 1, 2), camera.K, camera.dist_coeffs).reshape(2)
    ray_cam = np.array([xy[0], xy[1], 1.0]) / math.hypot(xy[0], xy[1], 1.0)
    r = rng.uniform(*cfg.aimed_range_m)
    T_world_cam = make_T(R_world_cam, T_world_ds[:3, 3] - r * (R_world_cam @ ray_cam))
    return T_world_cam @ inv_T(T_body_cam)


def _uniform(
    cfg: PoseSamplingConfig, rng: np.random.Generator, T_world_ds: np.ndarray
) -> np.ndarray:
    half = np.asarray(cfg.uniform_range_m, np.float64)
    centre = T_world_ds[:3, 3] - np.array([0.0, 0.0, cfg.uniform_height_m])
    return make_T(_tilted_yaw(rng, cfg.uniform_tilt_max_deg), centre + rng.uniform(-half, half))


def sample_pose(
    cfg: PoseSamplingConfig,
    rng: np.random.Generator,
    camera: CameraModel,
    T_body_cam: ArrayLike,
    T_world_ds: ArrayLike,
    tank_size_m: tuple[float, float, float] = TANK_SIZE_M,
) -> tuple[np.ndarray, str]:
    """Draw one vehicle pose (module docstring).

    Args:
        cfg: sampling ranges.
        rng: the frame's generator.
        camera: intrinsics (the aimed pixel is drawn inside its image).
        T_body_cam: (4, 4) camera extrinsics ``T_bodyfrd_camcv``.
        T_world_ds: (4, 4) DS pose in world NED (origin on its floor).
        tank_size_m: tank length, width, depth (m); world origin at the surface above its centre.

    Returns:
        ``(T_world_body, kind)``: (4, 4) body FRD in world NED and "aimed" or "uniform".
    """
    T_bc = check_T(T_body_cam, "T_body_cam")
    T_wd = check_T(T_world_ds, "T_world_ds")
    kind = "aimed" if rng.random() < cfg.aimed_fraction else "uniform"
    hx = tank_size_m[0] / 2 - cfg.tank_margin_m
    hy = tank_size_m[1] / 2 - cfg.tank_margin_m
    T_wb = np.eye(4)
    for _ in range(_MAX_DRAWS):
        if kind == "aimed":
            T_wb = _aimed(cfg, rng, camera, T_bc, T_wd)
        else:
            T_wb = _uniform(cfg, rng, T_wd)
        cam_z = (T_wb @ T_bc)[2, 3]
        if (
            cam_z >= cfg.min_depth_m
            and T_wd[2, 3] - cam_z >= cfg.min_height_m
            and abs(T_wb[0, 3]) <= hx
            and abs(T_wb[1, 3]) <= hy
        ):
            break
    return T_wb, kind


# ----------------------------------------------------------------------------- setup


@functools.lru_cache(maxsize=8)
def _fixed_water(spec: str) -> WaterConfig:
    """A preset or a water file (read once per process)."""
    w = resolve_water(spec)
    assert w is not None  # "none" is handled by the caller
    return w


def _water_for_frame(cfg: SynthConfig, rng: np.random.Generator) -> tuple[WaterConfig | None, dict]:
    if cfg.water == "none":
        return None, {}
    w = cfg.water_randomisation.sample(rng) if cfg.water == "random" else _fixed_water(cfg.water)
    return w, {"preset": cfg.water, **to_dict(w)}


#: Render scenes of this process by scene key (camera, extrinsics, marker set, renderer), kept
#: alive on purpose: building one is cheap, but once the last SAPIEN scene is gone the renderer
#: drops its compiled pipelines, and the next first picture recompiles them (~6 s on lavapipe).
_SCENES: dict[str, Any] = {}
_MAX_SCENES = 3


def _render_scene(cfg: SynthConfig, camera: CameraModel, T_body_cam: np.ndarray) -> Any:
    """The cached render scene for ``cfg``'s camera, marker set and renderer settings."""
    key = json.dumps(
        [to_dict(camera), T_body_cam.tolist(), cfg.marker_set_path, to_dict(cfg.render)],
        sort_keys=True,
    )
    rs = _SCENES.get(key)
    if rs is None:
        rs = make_render_scene(
            station_config(cfg),
            camera_model=camera,
            T_bodyfrd_camcv=T_body_cam,
            render_cfg=cfg.render,
        )
        while len(_SCENES) >= _MAX_SCENES:  # evict the oldest; at least one stays alive
            _SCENES.pop(next(iter(_SCENES)))
        _SCENES[key] = rs
    return rs


class FrameRenderer:
    """Renders and labels single frames of a config (the scene is built once per process).

    Args:
        cfg: the dataset config.
        poses: optional (N, 4, 4) vehicle poses; frame k then uses ``poses[k]`` instead of a draw.
    """

    def __init__(self, cfg: SynthConfig, poses: np.ndarray | None = None) -> None:
        self.cfg = cfg
        self.poses = poses
        self.camera, self.T_body_cam = resolve_camera(cfg.camera_file, cfg.width_px)
        self.tank_size_m = station_config(cfg).tank_size_m
        self.rs = _render_scene(cfg, self.camera, self.T_body_cam)
        self.sim_camera = SimCamera(self.rs.rig)
        self.T_world_ds = self.rs.ds.T_worldned_ds.copy()

    def pose(self, k: int, rng: np.random.Generator) -> np.ndarray:
        """(4, 4) T_world_body of frame k (drawn from ``rng`` unless poses were given)."""
        if self.poses is not None:
            return np.array(self.poses[k], np.float64)
        T, _ = sample_pose(
            self.cfg.poses, rng, self.camera, self.T_body_cam, self.T_world_ds, self.tank_size_m
        )
        return T

    def frame(self, k: int) -> tuple[np.ndarray, dict[str, Any]]:
        """Render frame k: (H, W, 3) uint8 BGR image and its ``labels.jsonl`` object."""
        rng = frame_rng(self.cfg.seed, k)
        T_world_body = self.pose(k, rng)
        water, water_label = _water_for_frame(self.cfg, rng)
        frame = self.sim_camera.capture(T_world_body, rng, water=water)
        T_cam_ds = inv_T(frame.T_world_cam) @ self.T_world_ds
        proj = project_markers(
            self.camera, T_cam_ds, self.rs.ds.marker_set, frame.range_m, self.cfg.occlusion_tol_m
        )
        markers = tuple(
            MarkerTruth(p.marker_id, p.corners_px, p.in_image, p.visible)
            for p in sorted(proj.values(), key=lambda p: p.marker_id)
        )
        truth = FrameTruth(
            frame=k,
            T_cam_ds=T_cam_ds,
            image=f"images/{IMAGE_NAME.format(k)}",
            T_world_body=T_world_body,
            range_m=range_m(T_cam_ds),
            view_angle_deg=view_angle_deg(T_cam_ds),
            water=water_label or None,
            markers=markers,
        )
        return frame.img_bgr(), frame_truth_to_json(truth)

    def encoded(self, k: int) -> tuple[bytes, dict[str, Any]]:
        """Render frame k: its PNG file's bytes and its ``labels.jsonl`` object."""
        bgr, label = self.frame(k)
        ok, png = cv2.imencode(".png", bgr)
        if not ok:  # pragma: no cover - OpenCV encodes any uint8 BGR image
            raise DockError(f"PNG encoding of frame {k} failed")
        return png.tobytes(), label

    def write(self, out_dir: Path, k: int) -> int:
        """Render frame k and write its image, then its partial label (both atomically)."""
        return _write_frame(out_dir, k, *self.encoded(k))


def _write_frame(out_dir: Path, k: int, png: bytes, label: dict[str, Any]) -> int:
    """Frame k's image, then its partial label, each written atomically (so a frame whose
    partial label exists is complete)."""
    atomic_write_bytes(out_dir / "images" / IMAGE_NAME.format(k), png)
    atomic_write_text_line(out_dir / PARTIAL_DIR / f"{k:06d}.json", label)
    return k


def atomic_write_text_line(path: Path, obj: dict[str, Any]) -> None:
    """Write ``obj`` as one compact JSON line (the ``labels.jsonl`` encoding), atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(_jsonl_line(obj), encoding="utf-8")


def _jsonl_line(obj: dict[str, Any]) -> str:
    return json.dumps(obj, separators=(",", ":")) + "\n"


# ----------------------------------------------------------------------------- workers


class FrameWorker:
    """A pool worker (:func:`dockcore.pool.worker_pool`): its renderer (scene built once) turns
    frame indices into PNG bytes and labels, which the caller writes (so Ray workers on other
    machines need no shared folder)."""

    def __init__(self, cfg_dict: dict[str, Any], poses: list | None) -> None:
        cfg = from_dict(SynthConfig, cfg_dict)
        self.renderer = FrameRenderer(cfg, None if poses is None else np.asarray(poses))

    def render(self, k: int) -> tuple[bytes, dict[str, Any]]:
        """Frame k: PNG bytes and label."""
        return self.renderer.encoded(int(k))


# ----------------------------------------------------------------------------- the run


def _absolute_inputs(cfg: SynthConfig) -> tuple[SynthConfig, list[str]]:
    """``cfg`` with its input files (camera, marker set, water file) as absolute paths from this
    process's working directory, and those files."""
    changes = {}
    for name in ("camera_file", "marker_set_path"):
        if getattr(cfg, name):
            changes[name] = str(Path(getattr(cfg, name)).expanduser().resolve())
    if is_water_file(cfg.water):
        changes["water"] = str(Path(cfg.water).expanduser().resolve())
    files = list(changes.values())
    if "marker_set_path" in changes:  # and the meshes it names, beside it or elsewhere
        files += marker_set_files(changes["marker_set_path"])[1:]
    return dataclasses.replace(cfg, **changes), files


def _render_all(
    out_dir: Path,
    cfg: SynthConfig,
    todo: Sequence[int],
    pool_cfg: PoolConfig,
    poses: np.ndarray | None,
    on_frame: Callable[[int], None],
) -> dict[str, Any]:
    """Render the frames ``todo`` into the folder; with Ray, where they ran (SynthResult.ray)."""
    if not todo:
        return {}
    if pool_cfg.backend == "local" and (pool_cfg.workers <= 1 or len(todo) == 1):
        renderer = FrameRenderer(cfg, poses)
        for k in todo:
            on_frame(renderer.write(out_dir, k))
        return {}
    # local: 'spawn' processes (SAPIEN/Vulkan must not be forked after initialisation), each
    # dying with this process even when it is killed with SIGKILL; ray: actors. Either way the
    # frames come back here and are written as they arrive, in any order.
    if pool_cfg.backend == "local":
        pool_cfg = dataclasses.replace(pool_cfg, workers=min(pool_cfg.workers, len(todo)))
    pose_list = None if poses is None else np.asarray(poses).tolist()
    if pool_cfg.backend == "ray":  # the actors' input files, sent to them as content
        cfg, inputs = _absolute_inputs(cfg)
        pool_cfg = dataclasses.replace(pool_cfg, inputs=tuple(inputs))
    with (
        worker_pool(pool_cfg, FrameWorker, (to_dict(cfg), pose_list)) as pool,
        workers_ended_on_error(pool),  # an interrupt stops the workers now, mid-frame
    ):
        for k, (png, label) in pool.imap_unordered("render", todo):
            on_frame(_write_frame(out_dir, k, png, label))
        if pool_cfg.backend != "ray":
            return {}
        return {"tasks_by_node": dict(pool.tasks_by_node), "workers_replaced": pool.replaced}


def camera_outside_tank(
    T_world_body: np.ndarray, T_body_cam: np.ndarray, ds_cfg: DockingStationConfig
) -> str | None:
    """Why the camera of vehicle pose ``T_world_body`` (4, 4, body FRD in world NED, m) is not
    under water inside the tank of ``ds_cfg`` (e.g. "0.2 m above the water surface"), or None
    when it is: the renderer models the underwater view only."""
    length_m, width_m, depth_m = ds_cfg.tank_length_m, ds_cfg.tank_width_m, ds_cfg.tank_depth_m
    x, y, z = (T_world_body @ T_body_cam)[:3, 3]
    if z <= 0.0:
        return f"{-z:.3g} m above the water surface"
    if z >= depth_m:
        return f"below the tank floor ({depth_m:g} m deep)"
    if abs(x) >= length_m / 2 or abs(y) >= width_m / 2:
        return f"outside the {length_m:g} x {width_m:g} m tank"
    return None


def _check_cameras_in_water(
    poses: np.ndarray, T_body_cam: np.ndarray, ds_cfg: DockingStationConfig
) -> None:
    """Refuse a given pose whose camera is not under water inside the tank: the renderer models
    the underwater view only, so a camera above the surface (or in a wall) would be labelled
    as seeing markers it could not see."""
    for k, T_world_body in enumerate(poses):
        where = camera_outside_tank(T_world_body, T_body_cam, ds_cfg)
        if where:
            x, y, z = (T_world_body @ T_body_cam)[:3, 3]
            raise DockError(
                f"poses[{k}]: the camera (world NED {x:.3g}, {y:.3g}, {z:.3g} m) is {where}: "
                "only underwater views inside the tank are rendered"
            )


def _checked_poses(poses: ArrayLike | None, n: int) -> np.ndarray | None:
    """(n, 4, 4) float64 vehicle poses, each a valid transform, or None (where the camera
    is, :func:`_check_cameras_in_water`)."""
    if poses is None:
        return None
    pose_arr = np.asarray(poses, np.float64)
    if pose_arr.shape != (n, 4, 4):
        raise DockError(f"poses: expected ({n}, 4, 4), got {pose_arr.shape}")
    for k, T in enumerate(pose_arr):
        try:
            check_T(T, f"poses[{k}]")
        except ValueError as exc:  # a non-finite or non-rigid matrix: the user's input
            raise DockError(str(exc)) from None
    return pose_arr


def generate(
    out_dir: str | os.PathLike[str],
    cfg: SynthConfig,
    workers: int = 1,
    poses: ArrayLike | None = None,
    progress: bool | None = None,
    tool: str = "datasets synth",
    sequences: FrameSequences | None = None,
    backend: str = "local",
    ray_address: str | None = None,
) -> SynthResult:
    """Render a labelled dataset into ``out_dir`` (resuming an interrupted run).

    Everything is checked before anything is written: the config (as the loader checks a
    file), ``workers``, the poses, the camera and marker set files, and the folder (another
    tool's output, another config, or more frames than ``cfg.n_frames`` are refused). The
    folder is then claimed for ``tool`` until the run ends (module docstring).

    Args:
        out_dir: the dataset folder (created).
        cfg: the dataset config.
        workers: worker processes or Ray actors (1 ... 64; 1 local worker renders in this
            process). The output does not depend on it.
        poses: optional (N, 4, 4) vehicle poses ``T_world_body`` (body FRD in world NED, the DS
            on the tank floor at the centre, see ``default_T_worldned_ds``); N must equal
            ``cfg.n_frames``.
        progress: show a tqdm bar (None: only on a terminal).
        tool: the command claiming the folder (``"datasets synth"``, ``"sim render"``).
        sequences: optional sequence labels of the given poses (which frames follow each other
            in time, :mod:`uwdock.datasets.sequences`); written to ``dataset.json``.
        backend: ``"local"`` (processes) or ``"ray"`` (Ray actors,
            :mod:`uwdock.dockcore.pool`): the same bytes either way.
        ray_address: the Ray cluster to use (None: a local Ray instance for the job).

    Returns:
        A :class:`SynthResult`.

    Raises:
        DockError: an unwritable folder, a folder in use or holding something else, bad
            poses, or a bad camera / marker set file; :class:`dockcore.errors.ConfigError`
            (a DockError) for an invalid config or ``workers``.
    """
    t0 = time.perf_counter()
    cfg = validated(cfg)
    pool_cfg = _checked_pool(workers, backend, ray_address)
    pose_arr = _checked_poses(poses, cfg.n_frames)
    if sequences is not None and (pose_arr is None or len(sequences) != cfg.n_frames):
        raise DockError(f"sequences: need one label per given pose ({cfg.n_frames})")
    camera, T_body_cam, marker_set = _checked_scene(cfg, pose_arr)
    state = folder_state(cfg, pose_arr, sequences)
    n = cfg.n_frames
    check_folder(Path(out_dir), state, n)
    with claim_output_dir(out_dir, tool) as out:
        old_lines = _start_folder(out, cfg, state, camera, T_body_cam, marker_set)
        rendered, ray = _render_missing(out, cfg, old_lines, camera, pool_cfg, pose_arr, progress)
        _finish_folder(out, cfg, old_lines, tool, sequences)
    return SynthResult(out, n, tuple(sorted(rendered)), time.perf_counter() - t0, ray)


def _checked_pool(workers: int, backend: str, ray_address: str | None) -> PoolConfig:
    """The run's worker pool: ``workers`` and the backend checked, and the pool answering."""
    reason = check(workers, int, split_annotated(Workers)[1], "workers")
    if reason:
        raise ConfigError(reason)
    pool_cfg = PoolConfig(backend, workers, ray_address)
    try:
        pool_cfg.validate()
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    preflight(pool_cfg)  # before anything is written
    return pool_cfg


def _checked_scene(
    cfg: SynthConfig, pose_arr: np.ndarray | None
) -> tuple[CameraModel, np.ndarray, MarkerSet]:
    """The camera, its mount ``T_body_cam`` and the marker set, read from their files; the
    given poses' cameras checked to be under water in the tank."""
    camera, T_body_cam = resolve_camera(cfg.camera_file, cfg.width_px)
    ds_cfg = station_config(cfg)
    if pose_arr is not None:
        _check_cameras_in_water(pose_arr, T_body_cam, ds_cfg)
    marker_set = resolve_marker_set(ds_cfg)
    return camera, T_body_cam, marker_set


def _start_folder(
    out: Path,
    cfg: SynthConfig,
    state: dict[str, Any],
    camera: CameraModel,
    T_body_cam: np.ndarray,
    marker_set: MarkerSet,
) -> dict[int, str]:
    """The claimed folder checked again, marked incomplete and given its state, subfolders and
    input files; returns the lines of its old ``labels.jsonl`` by frame."""
    old_lines = check_folder(out, state, cfg.n_frames)  # again: no other run can change it now
    (out / "dataset.json").unlink(missing_ok=True)  # incomplete until written again
    atomic_write_json(out / STATE_FILE, state)
    (out / "images").mkdir(exist_ok=True)
    (out / PARTIAL_DIR).mkdir(exist_ok=True)
    prepare_folder(out, cfg, camera, T_body_cam, marker_set)
    return old_lines


def _render_missing(
    out: Path,
    cfg: SynthConfig,
    old_lines: dict[int, str],
    camera: CameraModel,
    pool_cfg: PoolConfig,
    pose_arr: np.ndarray | None,
    progress: bool | None,
) -> tuple[list[int], dict[str, Any]]:
    """Render the frames the folder lacks, under a bar over all ``cfg.n_frames``; returns the
    frames rendered (in the order they came) and, with Ray, where they ran."""
    n = cfg.n_frames
    done = done_frames(out, n, old_lines, (camera.width_px, camera.height_px))
    todo = [k for k in range(n) if k not in done]
    rendered: list[int] = []
    disable = None if progress is None else not progress  # None: tqdm shows it on a tty
    with tqdm(total=n, initial=len(done), unit="frame", desc="synth", disable=disable) as bar:

        def on_frame(k: int) -> None:
            rendered.append(k)
            bar.update(1)

        ray = _render_all(out, cfg, todo, pool_cfg, pose_arr, on_frame)
    return rendered, ray


def _finish_folder(
    out: Path,
    cfg: SynthConfig,
    old_lines: dict[int, str],
    tool: str,
    sequences: FrameSequences | None,
) -> None:
    """``labels.jsonl`` assembled in frame order, then ``dataset.json`` (last: it marks a
    complete dataset)."""
    n = cfg.n_frames
    assemble_labels(out, n, old_lines)
    extra = {} if sequences is None else {"sequences": sequences.to_json()}
    write_dataset_json(
        out, n, config=to_dict(cfg), generator=tool, seed=cfg.seed, water=cfg.water, **extra
    )
