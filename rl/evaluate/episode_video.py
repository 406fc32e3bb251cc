"""Record one docking episode as a side-by-side video: the downward camera and an outside view.

Left: the vehicle's downward camera (:class:`sim.render.CameraRig` of the env's render scene)
with the water model applied. Right: a second :class:`CameraRig` in the same scene, placed at a
fixed offset from the DS (above and to the side, clipped into the tank), looking at the point
between the vehicle and the DS, lit by a directional "sun" of its own and seen through a light
haze. The vehicle has no visual mesh in the simulator, so :func:`add_vehicle_visual` gives it
render shapes copied from its PhysX collision shapes; they are shown in the outside view only
(hidden while the downward camera renders). The vehicle's body axes are drawn on top (x red,
y green, z blue).

The env is duck-typed: anything with the Gymnasium
``reset``/``step`` API whose ``world`` has ``scene``, ``render_scene``, ``vehicle`` (a
:class:`sim.physics.VehicleBody`), ``ds_cfg``, ``T_world_body`` and ``T_world_ds``, such as
``rl.env.docking_env.DockingEnv(render_mode="rgb_array")``; ``info`` may carry ``e_true``,
``e_psi_true``, ``detected``, ``success_paper``, ``success_strict``, ``collided`` and
``reward_terms``.

Example:
    >>> env = DockingEnv(EnvConfig(episode_s=30), render_mode="rgb_array")
    >>> summary = record_episode(env, PIDController(env._limits), "out/ep", seed=3)
"""

from __future__ import annotations

import dataclasses
import gc
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Protocol

import cv2
import numpy as np
import sapien

from uwdock.calibration.camera import CameraModel
from uwdock.calibration.frames import inv_T, make_T, transform_points
from uwdock.dockcore.cli import interrupt_name
from uwdock.dockcore.config import check_fields, validated
from uwdock.dockcore.domains import Interval
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_json, clean_stale_temps
from uwdock.dockcore.media import AtomicVideoWriter
from uwdock.dockcore.outdir import claimed_by
from uwdock.sim.camera import SimCamera
from uwdock.sim.domains import RGB
from uwdock.sim.render import CameraRig, RenderConfig
from uwdock.sim.water import PRESETS, WaterConfig, apply_water, preset

__all__ = [
    "EpisodeVideoConfig",
    "Policy",
    "add_vehicle_visual",
    "look_at",
    "record_episode",
]


#: A side of a view of the video (px): 4096 x 4096 renders fit in memory and in an MP4.
VideoSide_px = Annotated[int, Interval(ge=16, le=4096)]
#: A coordinate of the outside camera relative to the DS (m).
_Offset_m = Annotated[float, Interval(ge=-1000, le=1000)]


@dataclass(frozen=True)
class EpisodeVideoConfig:
    """The episode video.

    Attributes:
        outside_width_px: outside view width (px).
        outside_height_px: outside view height (px).
        outside_hfov_deg: outside view horizontal field of view (deg).
        outside_offset_m: outside camera position relative to the DS origin, world NED axes (m);
            clipped to stay 0.3 m inside the tank and below the surface.
        outside_sun_intensity: a directional light from above (z-up direction (0.35, 0.25, -1)),
            on only while the outside view renders (SAPIEN radiance units).
        outside_haze: water preset giving the outside view a range haze (no noise, no
            vignetting, lit by ambient and lamps), or None for a clear view.
        outside_haze_scale: factor on the haze preset's attenuation coefficients (-; < 1 keeps
            the vehicle's colour recognisable across the tank).
        panel_height_px: both views are scaled to this height and put side by side (px; even).
        vehicle_rgb: colour of the vehicle's render shapes (linear RGB in [0, 1]).
        overlay: draw the text lines and the vehicle axes.
    """

    outside_width_px: VideoSide_px = 480
    outside_height_px: VideoSide_px = 360
    outside_hfov_deg: Annotated[float, Interval(gt=0, lt=170)] = 70.0
    outside_offset_m: tuple[_Offset_m, _Offset_m, _Offset_m] = (-6.0, -3.5, -4.3)
    outside_sun_intensity: Annotated[float, Interval(ge=0, le=100)] = 1.5
    outside_haze: str | None = "clear_tank"
    outside_haze_scale: Annotated[float, Interval(ge=0, le=10)] = 0.35
    panel_height_px: VideoSide_px = 360
    vehicle_rgb: RGB = (0.95, 0.45, 0.08)
    overlay: bool = True

    def validate(self) -> None:
        """Raise ValueError naming the first field outside its declared domain (NaN included)
        or an unknown ``outside_haze``."""
        check_fields(self)
        if self.outside_haze is not None and self.outside_haze not in PRESETS:
            raise ValueError(
                f"outside_haze: unknown water preset {self.outside_haze[:100]!r}; known: "
                f"{', '.join(PRESETS)}"
            )


class Policy(Protocol):
    """A controller: ``act(obs) -> action in [-1, 1]^6``; ``reset()`` between episodes."""

    def reset(self) -> None: ...

    def act(self, obs: np.ndarray) -> np.ndarray: ...


# ----------------------------------------------------------------------------- helpers


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) ``T_worldned_camcv`` of a camera at ``eye`` looking at ``target`` (world NED),
    image rows pointing down (+z NED) as far as possible."""
    z = np.asarray(target, np.float64) - np.asarray(eye, np.float64)
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 0.0, 1.0], z)
    if np.linalg.norm(x) < 1e-6:  # looking straight up or down: any image x
        x = np.cross([1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    return make_T(np.column_stack([x, np.cross(z, x), z]), eye)


def add_vehicle_visual(
    component: sapien.physx.PhysxRigidDynamicComponent, rgb: tuple[float, float, float]
) -> sapien.render.RenderBodyComponent:
    """Give the vehicle render shapes equal to its collision boxes and capsules.

    Args:
        component: the vehicle's PhysX body (``VehicleBody.component``); its entity gets the
            render body.
        rgb: colour (linear RGB).

    Returns:
        The render body (set ``visibility`` to 0 to hide it from a camera).
    """
    body = sapien.render.RenderBodyComponent()
    material = sapien.render.RenderMaterial(base_color=[*rgb, 1.0], roughness=0.6)
    for shape in component.get_collision_shapes():
        if isinstance(shape, sapien.physx.PhysxCollisionShapeBox):
            visual = sapien.render.RenderShapeBox(np.asarray(shape.half_size, np.float32), material)
        elif isinstance(shape, sapien.physx.PhysxCollisionShapeCapsule):
            visual = sapien.render.RenderShapeCapsule(shape.radius, shape.half_length, material)
        else:  # pragma: no cover - the vehicle is built from boxes and capsules only
            continue
        visual.local_pose = shape.local_pose
        body.attach(visual)
    component.entity.add_component(body)
    return body


def _text(img: np.ndarray, lines: list[str]) -> None:
    scale = max(0.35, img.shape[0] / 900.0)
    step = int(28 * scale) + 4
    font = cv2.FONT_HERSHEY_SIMPLEX
    for i, line in enumerate(lines):
        org = (6, step * (i + 1))
        for colour, thickness in (((0, 0, 0), 3), ((255, 255, 255), 1)):
            cv2.putText(img, line, org, font, scale, colour, thickness, cv2.LINE_AA)


def _draw_axes(img: np.ndarray, cam: CameraModel, T_cam_body: np.ndarray, length_m: float) -> None:
    pts = transform_points(T_cam_body, np.vstack([np.zeros(3), np.eye(3) * length_m]))
    if np.any(pts[:, 2] <= 0.05):
        return
    px = np.rint(cam.project(pts)).astype(int)
    for i, colour in ((1, (0, 0, 255)), (2, (0, 200, 0)), (3, (255, 80, 0))):  # BGR: x r, y g, z b
        cv2.line(img, tuple(px[0]), tuple(px[i]), colour, 2, cv2.LINE_AA)


def _fit_height(bgr: np.ndarray, height: int) -> np.ndarray:
    width = max(2, round(bgr.shape[1] * height / bgr.shape[0]) // 2 * 2)
    return cv2.resize(bgr, (width, height), interpolation=cv2.INTER_AREA)


# ----------------------------------------------------------------------------- recording


class _Views:
    """The two renders of a frame (downward with water, outside with haze and overlay)."""

    def __init__(self, env: Any, cfg: EpisodeVideoConfig, water: WaterConfig | None, rng) -> None:
        world = env.world
        if getattr(world, "render_scene", None) is None:
            raise DockError("the env has no camera: create it with render_mode='rgb_array'")
        self.world, self.cfg, self.water, self.rng = world, cfg, water, rng
        self.down = SimCamera(world.render_scene.rig, water)
        camera = CameraModel.from_hfov(
            cfg.outside_width_px, cfg.outside_height_px, cfg.outside_hfov_deg, name="outside"
        )
        self.outside = CameraRig(world.scene, camera, cfg=RenderConfig(lamp=False), name="outside")
        # a sun from above, switched on for the outside view only (the downward camera keeps
        # the physical lighting: ambient + the vehicle's lamp)
        self.sun = world.scene.add_directional_light(
            [0.35, 0.25, -1.0], [0.0, 0.0, 0.0], shadow=False
        )
        self.vehicle_visual = add_vehicle_visual(world.vehicle.component, cfg.vehicle_rgb)
        self.haze = None
        if cfg.outside_haze is not None:
            base = preset(cfg.outside_haze)
            k = cfg.outside_haze_scale
            self.haze = dataclasses.replace(
                base,
                beta_D_rgb=tuple(k * v for v in base.beta_D_rgb),
                beta_B_rgb=tuple(k * v for v in base.beta_B_rgb),
                artificial_light=False,
                photons_at_white=None,
                vignetting=0.0,
                jpeg_quality=None,
            )

    def close(self) -> None:
        """Let go of the renderer objects this adds to the env's scene (outside camera, sun,
        vehicle shapes, the downward view) now, before the env's scene goes: left to the
        interpreter's last collection (an interrupted episode's traceback holds them), their
        destructors could run after the scene's and crash the process."""
        self.outside = self.sun = self.vehicle_visual = self.down = None
        gc.collect()

    def _outside_pose(self) -> np.ndarray:
        ds_cfg = self.world.ds_cfg
        T_ds, T_body = self.world.T_world_ds, self.world.T_world_body
        eye = T_ds[:3, 3] + np.asarray(self.cfg.outside_offset_m, np.float64)
        hx, hy = ds_cfg.tank_length_m / 2 - 0.3, ds_cfg.tank_width_m / 2 - 0.3
        eye = np.clip(eye, [-hx, -hy, 0.3], [hx, hy, ds_cfg.tank_depth_m - 0.3])
        target = 0.5 * (T_ds[:3, 3] + T_body[:3, 3])
        return look_at(eye, target)

    def render(self, down_lines: list[str], outside_lines: list[str]) -> np.ndarray:
        """(H, W, 3) uint8 BGR side-by-side frame."""
        self.vehicle_visual.visibility = 0.0
        down = self.down.capture(self.world.T_world_body, self.rng)
        self.vehicle_visual.visibility = 1.0
        self.sun.color = [self.cfg.outside_sun_intensity] * 3
        out = self.outside.render(T_worldned_camcv=self._outside_pose())
        self.sun.color = [0.0, 0.0, 0.0]
        if self.haze is None:
            outside_rgb = out.rgb
        else:
            outside_rgb = apply_water(out.radiance, out.range_m, self.haze)
        down_bgr = down.img_bgr()
        out_bgr = cv2.cvtColor(outside_rgb, cv2.COLOR_RGB2BGR)
        if self.cfg.overlay:
            T_cam_body = inv_T(out.T_worldned_camcv) @ self.world.T_world_body
            _draw_axes(out_bgr, out.camera, T_cam_body, 0.6)
        h = self.cfg.panel_height_px // 2 * 2
        down_bgr, out_bgr = _fit_height(down_bgr, h), _fit_height(out_bgr, h)
        if self.cfg.overlay:
            _text(down_bgr, down_lines)
            _text(out_bgr, outside_lines)
        return np.hstack([down_bgr, out_bgr])


def _lines(info: dict[str, Any], water_name: str) -> tuple[list[str], list[str]]:
    t = float(info.get("time_s", 0.0))
    down = ["downward camera", f"water: {water_name}", f"t = {t:5.1f} s"]
    e = np.asarray(info.get("e_true", np.full(3, np.nan)), np.float64)
    psi = math.degrees(float(info.get("e_psi_true", math.nan)))
    state = "DOCKED" if info.get("success_paper") else ""
    outside = [
        f"e = ({e[0]:+.2f}, {e[1]:+.2f}, {e[2]:+.2f}) m  e_psi = {psi:+.0f} deg",
        f"DS detected: {'yes' if info.get('detected') else 'no'}  {state}",
    ]
    return down, outside


def record_episode(
    env: Any,
    policy: Policy,
    out_dir: str | os.PathLike[str],
    seed: int = 0,
    water: WaterConfig | None = None,
    water_name: str = "none",
    max_steps: int | None = None,
    cfg: EpisodeVideoConfig | None = None,
    video_name: str = "episode.mp4",
    on_step: Callable[[int], None] | None = None,
    summary_name: str | None = None,
    previous_outputs: tuple[str, ...] = (),
) -> dict[str, Any]:
    """Run one episode with ``policy`` and write ``out_dir/episode.mp4``.

    Args:
        env: the env (module docstring), e.g. ``DockingEnv(render_mode="rgb_array")``.
        policy: the controller.
        out_dir: output folder (created).
        seed: env reset seed; the water noise uses ``SeedSequence([seed, 1])``.
        water: water applied to the downward view; None for the clean render.
        water_name: its label (overlay and summary).
        max_steps: stop after this many control steps (None: when the env ends the episode).
        cfg: video settings.
        video_name: the video file name inside ``out_dir``.
        on_step: called with the step index after each step (progress).
        summary_name: the summary file the caller writes into ``out_dir`` on success (e.g.
            ``"summary.json"``), or None. Given, an interrupted episode (SIGINT, SIGTERM)
            writes it as ``{"complete": false, "interrupted": "SIGTERM", "steps": ...,
            "video": null, ...}`` and removes a previous run's video from the folder (so an
            interrupted rerun cannot leave another run's outputs looking like its own); its
            own video is discarded, never renamed into place
            (:class:`dockcore.media.AtomicVideoWriter`). Any other failure leaves the folder's
            files as they were.
        previous_outputs: further files of a previous run in ``out_dir`` (its provenance) that
            an interrupted episode removes with its video.

    Returns:
        The summary (JSON-serialisable): ``complete`` (true), frames, steps, simulated time,
        success flags, final errors, return and reward-term sums, collisions, the fraction of
        steps with the DS detected (``info["detected"]``), video name, fps.
        One video frame per control step plus the initial one.
    """
    cfg = validated(cfg or EpisodeVideoConfig())
    if water is not None:
        water = validated(water)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 1]))
    views = _Views(env, cfg, water, rng)
    fps = float(getattr(getattr(env, "cfg", None), "control_hz", 5.0))  # real time
    t0 = time.perf_counter()
    done = {"steps": 0, "sim_time_s": 0.0}  # how far the episode got (an interrupt's summary)
    try:
        summary = _film(env, policy, views, out / video_name, fps, seed, water_name, max_steps,
                        on_step, done)  # fmt: skip
    except KeyboardInterrupt as exc:  # SIGINT, and SIGTERM (raised as an interrupt)
        if summary_name is not None:  # a previous run's video is not this summary's
            for name in (video_name, *previous_outputs):
                (out / name).unlink(missing_ok=True)
            _write_interrupted(out / summary_name, exc, done, seed, water_name, fps, t0)
        raise
    finally:
        views.close()
    summary["wall_s"] = time.perf_counter() - t0
    return summary


def _write_interrupted(
    path: Path, exc: BaseException, done: dict[str, Any], seed, water_name, fps, t0
) -> None:
    """The summary of an interrupted episode: says so, and how far it got; no video."""
    summary = {
        "complete": False,
        "interrupted": interrupt_name(exc),
        "video": None,
        **done,
        "fps": fps,
        "seed": int(seed),
        "water": water_name,
        "wall_s": time.perf_counter() - t0,
    }
    try:
        atomic_write_json(path, summary)
    except OSError:  # a full disk: the run still ends as interrupted, without the mark
        pass


def mark_killed(
    out_dir: str | os.PathLike[str],
    signal_name: str,
    pid: int,
    summary_name: str = "summary.json",
    outputs: tuple[str, ...] = ("episode.mp4",),
) -> None:
    """What :func:`record_episode` leaves on an interrupt, written for it by the process that
    supervised a run it had to kill (``dockcore.supervise``: the renderer held the interpreter
    past the grace time): the temporary files of the killed run and ``outputs`` of a previous
    run removed, ``summary_name`` saying the run was interrupted (how far it got unknown).
    Nothing is touched in a folder that the killed process ``pid`` had not claimed (it was
    killed before it got there)."""
    out = Path(out_dir)
    if claimed_by(out) != pid:
        return
    clean_stale_temps(out, recursive=False)
    for name in outputs:
        (out / name).unlink(missing_ok=True)
    summary = {
        "complete": False,
        "interrupted": signal_name,
        "video": None,
        "steps": None,
        "killed": "did not stop within the grace time after the signal (renderer busy)",
    }
    try:
        atomic_write_json(out / summary_name, summary)
    except OSError:  # a full disk: the run still ends as interrupted, without the mark
        pass


def _film(
    env, policy, views, path, fps, seed, water_name, max_steps, on_step, done=None
) -> dict[str, Any]:
    """The episode into ``path`` (record_episode's loop); its summary without ``wall_s``.
    ``done`` (a dict), when given, is kept up to date with the steps and simulated time."""
    done = {} if done is None else done
    with AtomicVideoWriter(path, fps) as writer:
        obs, info = env.reset(seed=seed)
        policy.reset()
        writer.write(views.render(*_lines(info, water_name)))
        steps, ret, collisions, detected = 0, 0.0, 0, 0
        terms: dict[str, float] = {}
        terminated = truncated = False
        while not (terminated or truncated) and (max_steps is None or steps < max_steps):
            obs, reward, terminated, truncated, info = env.step(policy.act(obs))
            steps += 1
            ret += float(reward)
            collisions += int(bool(info.get("collided", False)))
            detected += int(bool(info.get("detected", False)))
            for k, v in info.get("reward_terms", {}).items():
                terms[k] = terms.get(k, 0.0) + float(v)
            done.update(steps=steps, sim_time_s=float(info.get("time_s", math.nan)))
            writer.write(views.render(*_lines(info, water_name)))
            if on_step is not None:
                on_step(steps)
    e = np.asarray(info.get("e_true", np.full(3, np.nan)), np.float64)
    return {
        "complete": True,
        "video": writer.path.name,
        "frames": writer.frames,
        "fps": fps,
        "size_px": [int(v) for v in (writer.size_px or (0, 0))],
        "steps": steps,
        "sim_time_s": float(info.get("time_s", math.nan)),
        "terminated": bool(terminated),
        "truncated": bool(truncated),
        "success_paper": bool(info.get("success_paper", False)),
        "success_strict": bool(info.get("success_strict", False)),
        "final_error_m": e.tolist(),
        "final_distance_m": float(np.linalg.norm(e)),
        "final_yaw_error_deg": math.degrees(float(info.get("e_psi_true", math.nan))),
        "return": ret,
        "reward_terms": terms,
        "collisions": collisions,
        "detected_fraction": detected / steps if steps else 0.0,
        "seed": int(seed),
        "water": water_name,
    }
