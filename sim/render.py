"""Camera rendering with SAPIEN: RGB, range and depth images from a vehicle pose, and ground truth.

The camera is SAPIEN's rasteriser posed from a :class:`calibration.camera.CameraModel` and the
extrinsics ``T_bodyfrd_camcv``; the lamp (a point or spot light beside the camera) moves with it,
so its light falls off physically (SAPIEN: diffuse radiance = albedo * I * cos / (pi d**2)).

Intrinsics: SAPIEN's ``cx, cy`` are measured from the image corner (pixel centres at +0.5), while
OpenCV's (and CameraModel's) put pixel centres on integers. Measured on this renderer: a SAPIEN
camera given ``(cx + 0.5, cy + 0.5)`` renders exactly what ``cv2.projectPoints`` with ``K``
predicts (tests/test_render.py checks the principal point and the corners to sub-pixel level).
Lens distortion, when the model has any, is applied after rendering with a precomputed remap.

Scene creation (tank, DS, lights, camera) happens once in :func:`make_render_scene`; each frame
only sets one entity pose, renders and reads two pictures back.

Example:
    >>> rs = make_render_scene()
    >>> res = rs.render(T_worldned_bodyfrd)
    >>> img = apply_water(res.radiance, res.range_m, PRESETS["coastal"], rng)
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import cv2
import numpy as np
import sapien
from numpy.typing import ArrayLike

from uwdock.calibration.camera import REFERENCE_T_BODYFRD_CAMCV, CameraModel, reference_camera
from uwdock.calibration.frames import (
    T_CAMCV_CAMSAPIEN,
    check_T,
    inv_T,
    make_T,
    transform_points,
)
from uwdock.dockcore.config import check_fields, validated
from uwdock.dockcore.domains import Interval
from uwdock.dockcore.errors import DockError
from uwdock.markers.markerset import MarkerSet
from uwdock.markers.view import markers_in_view
from uwdock.sim.docking_station import (
    DockingStation,
    DockingStationConfig,
    build_chessboard,
    build_docking_station,
    build_tank,
    sapien_pose,
)
from uwdock.sim.domains import RGB, BodyCoord_m
from uwdock.sim.scene import new_scene
from uwdock.sim.shaders import DEPTH_IN_ALPHA, hdr_shader_dir

__all__ = [
    "CameraRig",
    "MarkerProjection",
    "RenderConfig",
    "RenderResult",
    "RenderScene",
    "board_views",
    "display_rgb",
    "make_render_scene",
    "project_markers",
]


#: Ambient light (SAPIEN radiance units: 1 lights a white surface fully).
_Ambient = Annotated[float, Interval(ge=0, le=10)]

#: SAPIEN's own shaders, rendered through their linear variants (:mod:`sim.shaders`).
SHADERS: tuple[str, ...] = ("minimal", "default")


def check_shader(shader: str) -> None:
    """Raise ValueError (one line ``shader: ...`` naming the choices) unless ``shader`` is one
    of :data:`SHADERS` or the path of a shader folder (holding ``gbuffer.vert``)."""
    if shader in SHADERS:
        return
    try:
        found = bool(shader) and (Path(shader) / "gbuffer.vert").is_file()
    except (OSError, ValueError):  # a name too long for the file system, a NUL byte
        found = False
    if not found:
        raise ValueError(
            f"shader: must be {' or '.join(SHADERS)} or a shader folder holding gbuffer.vert, "
            f"got {shader[:200]!r}"
        )


def shader_dir(shader: str) -> str:
    """The folder a camera loads: the linear variant of one of :data:`SHADERS`
    (:func:`sim.shaders.hdr_shader_dir`) or the shader folder given (its ``Color`` picture is
    read as linear radiance).

    Raises:
        ValueError: as :func:`check_shader`.
        DockError: the linear variant cannot be derived.
    """
    check_shader(shader)
    return hdr_shader_dir(shader) if shader in SHADERS else shader


@dataclass(frozen=True)
class RenderConfig:
    """Renderer and lighting settings.

    Attributes:
        shader: SAPIEN camera shader: ``minimal`` (fast forward shading, ~2.5x faster on the CPU,
            range quantised to 1 mm), ``default`` (SAPIEN's deferred PBR), both rendered
            through their linear variants (:mod:`sim.shaders`), or the path of a shader folder
            (with ``gbuffer.vert``, its ``Color`` read as linear radiance; one SAPIEN cannot use
            is an error when the camera is built).
        near_m: near clipping distance (m).
        far_m: far clipping distance (m); farther surfaces count as "no hit".
        ambient_rgb: ambient light (SAPIEN units: adds ``ambient * albedo`` to the radiance).
        lamp: add the vehicle lamp that moves with the camera.
        lamp_intensity: lamp emission (SAPIEN units: a white diffuse surface facing the lamp at
            d metres has radiance ``albedo * intensity / (pi d**2)``).
        lamp_rgb: lamp colour (multiplies the intensity).
        lamp_offset_camcv_m: lamp position in the OpenCV camera frame (m).
        lamp_fov_deg: None for a point lamp; else a spot lamp along the optical axis with this
            full outer cone angle (deg; the inner, fully lit cone is 70 % of it).
    """

    shader: str = "minimal"
    near_m: Annotated[float, Interval(ge=0.001, le=100)] = 0.05
    far_m: Annotated[float, Interval(gt=0, le=10_000)] = 60.0
    ambient_rgb: tuple[_Ambient, _Ambient, _Ambient] = (0.18, 0.18, 0.18)
    lamp: bool = True
    lamp_intensity: Annotated[float, Interval(ge=0, le=10_000)] = 14.0
    lamp_rgb: RGB = (1.0, 0.97, 0.92)
    lamp_offset_camcv_m: tuple[BodyCoord_m, BodyCoord_m, BodyCoord_m] = (0.0, -0.10, 0.0)
    lamp_fov_deg: Annotated[float, Interval(gt=0, lt=180)] | None = None

    def validate(self) -> None:
        """Raise ValueError naming the first invalid field: one outside its declared domain
        (NaN included), an unusable shader, or ``near_m >= far_m``."""
        check_fields(self)
        check_shader(self.shader)
        if not self.near_m < self.far_m:
            raise ValueError(f"near_m, far_m: need near < far, got {self.near_m}, {self.far_m}")


@dataclass(frozen=True)
class RenderResult:
    """One rendered frame.

    Attributes:
        radiance: (H, W, 3) float32 linear RGB radiance in air, unclipped (SAPIEN units: a white
            diffuse surface lit by the ambient light alone is ``ambient``; near the lamp values
            well above 1 occur). Feed it to :func:`sim.water.apply_water`, which applies the
            water, the exposure and the sensor (the only place light is clipped).
        range_m: (H, W) float32 distance from the camera centre to the surface seen (m);
            ``inf`` where nothing was hit.
        depth_m: (H, W) float32 z of that point in ``cam_cv`` (m); ``inf`` where nothing was hit.
        T_worldned_camcv: (4, 4) camera pose used.
        camera: the camera model the images follow.
    """

    radiance: np.ndarray
    range_m: np.ndarray
    depth_m: np.ndarray
    T_worldned_camcv: np.ndarray
    camera: CameraModel

    @property
    def rgb(self) -> np.ndarray:
        """(H, W, 3) uint8 RGB: the radiance as a display image in air (clipped at 1, encoded
        ``linear ** (1 / 2.2)``), for views without water or sensor."""
        return display_rgb(self.radiance)


def display_rgb(radiance: np.ndarray, gamma: float = 2.2) -> np.ndarray:
    """(H, W, 3) uint8: linear radiance clipped at 1 and encoded ``v ** (1 / gamma)``."""
    v = np.clip(radiance, 0.0, 1.0, dtype=np.float32)
    cv2.pow(v, 1.0 / gamma, dst=v)
    return cv2.convertScaleAbs(v, alpha=255.0)


class CameraRig:
    """A SAPIEN camera (plus lamp) that follows a vehicle pose.

    Args:
        scene: the SAPIEN scene to render.
        camera_model: intrinsics and image size; default :func:`reference_camera`.
        T_bodyfrd_camcv: (4, 4) camera extrinsics; default ``REFERENCE_T_BODYFRD_CAMCV``.
        cfg: renderer and lamp settings.
        name: entity name.
    """

    def __init__(
        self,
        scene: sapien.Scene,
        camera_model: CameraModel | None = None,
        T_bodyfrd_camcv: ArrayLike | None = None,
        cfg: RenderConfig | None = None,
        name: str = "downward_camera",
    ) -> None:
        self.cfg = validated(cfg or RenderConfig())
        self.camera = camera_model or reference_camera()
        self.camera.validate()
        T_bc = REFERENCE_T_BODYFRD_CAMCV if T_bodyfrd_camcv is None else T_bodyfrd_camcv
        self.T_bodyfrd_camcv = check_T(T_bc, "T_bodyfrd_camcv")
        cam = self.camera
        try:  # SAPIEN parses the shader here and when the camera joins the scene
            self._component = sapien.render.RenderCameraComponent(
                cam.width_px, cam.height_px, shader_dir(self.cfg.shader)
            )
        except RuntimeError as exc:
            raise _camera_error(self.cfg.shader, exc) from None
        self._component.set_perspective_parameters(
            self.cfg.near_m,
            self.cfg.far_m,
            cam.fx_px,
            cam.fy_px,
            cam.cx_px + 0.5,  # SAPIEN: pixel centres at +0.5 (see the module docstring)
            cam.cy_px + 0.5,
            0.0,
        )
        self.entity = sapien.Entity()
        self.entity.name = name
        self.entity.add_component(self._component)
        self.lamp: sapien.render.RenderLightComponent | None = None
        if self.cfg.lamp:
            self.lamp = self._make_lamp()
            self.entity.add_component(self.lamp)
        try:
            scene.add_entity(self.entity)
        except RuntimeError as exc:
            raise _camera_error(self.cfg.shader, exc) from None
        self._maps = _distortion_maps(cam) if np.any(cam.dist_coeffs != 0.0) else None
        # the fast minimal variant's depth is the Color's alpha (sim.shaders.DEPTH_IN_ALPHA);
        # other shaders: a position picture, which one known after the first picture (asking
        # the names before segfaults)
        self._depth_in_alpha = self.cfg.shader in DEPTH_IN_ALPHA
        self._minimal: bool | None = None
        v, u = np.mgrid[0 : cam.height_px, 0 : cam.width_px].astype(np.float64)
        self._ray_norm = np.sqrt(
            1.0 + ((u - cam.cx_px) / cam.fx_px) ** 2 + ((v - cam.cy_px) / cam.fy_px) ** 2
        ).astype(np.float32)

    def _make_lamp(self) -> sapien.render.RenderLightComponent:
        c = self.cfg
        if c.lamp_fov_deg is None:
            lamp: sapien.render.RenderLightComponent = sapien.render.RenderPointLightComponent()
        else:
            lamp = sapien.render.RenderSpotLightComponent()
            lamp.outer_fov = np.deg2rad(c.lamp_fov_deg)
            lamp.inner_fov = 0.7 * np.deg2rad(c.lamp_fov_deg)
        lamp.color = [c.lamp_intensity * v for v in c.lamp_rgb]
        lamp.shadow = False
        # the entity frame is cam_sapien (x = optical axis, the spot light's direction)
        p = transform_points(inv_T(T_CAMCV_CAMSAPIEN), np.asarray(c.lamp_offset_camcv_m))
        lamp.local_pose = sapien.Pose(p.astype(np.float32))
        return lamp

    def set_lamp(self, on: bool) -> None:
        """Switch this rig's lamp on or off (several rigs in a scene: light the active one)."""
        if self.lamp is not None:
            scale = self.cfg.lamp_intensity if on else 0.0
            self.lamp.color = [scale * v for v in self.cfg.lamp_rgb]

    def set_pose(
        self,
        T_worldned_bodyfrd: ArrayLike | None = None,
        *,
        T_worldned_camcv: ArrayLike | None = None,
    ) -> np.ndarray:
        """Place camera and lamp from a vehicle pose or directly from a camera pose.

        Args:
            T_worldned_bodyfrd: (4, 4) vehicle pose (body FRD in world NED).
            T_worldned_camcv: (4, 4) OpenCV camera pose in world NED (instead of the above).

        Returns:
            (4, 4) ``T_worldned_camcv`` used.
        """
        if (T_worldned_bodyfrd is None) == (T_worldned_camcv is None):
            raise ValueError("give exactly one of T_worldned_bodyfrd and T_worldned_camcv")
        if T_worldned_camcv is None:
            T = check_T(T_worldned_bodyfrd, "T_worldned_bodyfrd") @ self.T_bodyfrd_camcv
        else:
            T = check_T(T_worldned_camcv, "T_worldned_camcv")
        self.entity.set_pose(sapien_pose(T @ T_CAMCV_CAMSAPIEN))
        return T

    def render(
        self,
        T_worldned_bodyfrd: ArrayLike | None = None,
        *,
        T_worldned_camcv: ArrayLike | None = None,
    ) -> RenderResult:
        """Render one frame from a vehicle pose or a camera pose (see :meth:`set_pose`)."""
        T = self.set_pose(T_worldned_bodyfrd, T_worldned_camcv=T_worldned_camcv)
        self.entity.scene.update_render()  # the entity's scene: a world may move it to a new one
        self._component.take_picture()
        rgba = self._component.get_picture("Color")  # float32 (H, W, 4), linear, unclipped
        rgb = cv2.cvtColor(rgba, cv2.COLOR_RGBA2RGB)
        if self._depth_in_alpha:
            depth_m = np.ascontiguousarray(rgba[:, :, 3])
            hit = depth_m > 0.0
        else:
            depth_m, hit = self._depth()
        depth_m[~hit] = np.inf
        range_m = depth_m * self._ray_norm  # pinhole: range = depth * |K^-1 (u, v, 1)|
        if self._maps is not None:
            mx, my = self._maps
            rgb = cv2.remap(rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            inf = (np.inf,) * 4
            range_m = cv2.remap(range_m, mx, my, cv2.INTER_NEAREST, borderValue=inf)
            depth_m = cv2.remap(depth_m, mx, my, cv2.INTER_NEAREST, borderValue=inf)
        return RenderResult(rgb, range_m, depth_m, T, self.camera)

    def _depth(self) -> tuple[np.ndarray, np.ndarray]:
        """Depth (z in cam_cv, m) as (H, W) float32 and the hit mask (H, W) bool."""
        comp = self._component
        if self._minimal is None:
            self._minimal = "PositionSegmentation" in comp.get_picture_names()
        if self._minimal:  # int32 camera-space (OpenGL) position in mm, truncated toward zero
            z_mm = comp.get_picture("PositionSegmentation")[:, :, 2]
            hit = z_mm != 0  # a hit is at least near_m in front; the clear value is 0
            depth = z_mm.astype(np.float32)
            depth *= np.float32(-1e-3)
            depth += np.float32(0.5e-3)  # undo the truncation bias: |z| lies in [n, n + 1) mm
            return depth, hit
        pos = comp.get_picture("Position")  # float32 (x, y, z, depth buffer value in [0, 1])
        return -pos[:, :, 2], pos[:, :, 3] < 1.0


def _camera_error(shader: str, exc: RuntimeError) -> DockError:
    """One line for a camera SAPIEN refused (e.g. a shader folder it cannot compile)."""
    reason = " ".join(str(exc).split())[:300] or type(exc).__name__
    return DockError(f"cannot set up a camera with the shader {shader!r}: {reason}")


def _distortion_maps(cam: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps taking a pinhole render (same K) to the distorted image of ``cam``."""
    v, u = np.mgrid[0 : cam.height_px, 0 : cam.width_px].astype(np.float32)
    pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    ideal = cv2.undistortPoints(
        pts,
        cam.K,
        cam.dist_coeffs,
        R=None,
        P=cam.K,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-6),
    )
    ideal = ideal.reshape(cam.height_px, cam.width_px, 2).astype(np.float32)
    return np.ascontiguousarray(ideal[:, :, 0]), np.ascontiguousarray(ideal[:, :, 1])


# ----------------------------------------------------------------------------- ground truth


@dataclass(frozen=True)
class MarkerProjection:
    """Ground truth of one marker in one frame.

    Attributes:
        marker_id: the marker's ID.
        corners_px: (4, 2) float64 pixels of the corners TL, TR, BR, BL (nan behind the camera).
        centre_px: (2,) float64 pixel of the marker centre.
        corners_range_m: (4,) distances from the camera centre to the corners (m).
        in_front: all corners in front of the camera (z_camcv > 0).
        in_image: all corners inside the image.
        occluded: some corner or the centre lies behind a nearer surface in ``range_m``
            (False when no range image was given).
        visible: ``in_front and in_image and not occluded``.
    """

    marker_id: int
    corners_px: np.ndarray
    centre_px: np.ndarray
    corners_range_m: np.ndarray
    in_front: bool
    in_image: bool
    occluded: bool
    visible: bool


def project_markers(
    camera_model: CameraModel,
    T_camcv_ds: ArrayLike,
    marker_set: MarkerSet,
    range_m: np.ndarray | None = None,
    occlusion_tol_m: float = 0.03,
) -> dict[int, MarkerProjection]:
    """Project every marker's corners into the image (``cv2.projectPoints`` via the model).

    Args:
        camera_model: intrinsics and distortion.
        T_camcv_ds: (4, 4) DS pose in the OpenCV camera frame.
        marker_set: the markers (their ``T_ds_marker`` and side).
        range_m: optional (H, W) rendered range image of the same frame, for the occlusion test:
            a corner (or the centre) is occluded when the rendered range at its pixel is shorter
            than its own range by more than ``occlusion_tol_m``.
        occlusion_tol_m: occlusion tolerance (m).

    Returns:
        marker ID -> :class:`MarkerProjection`.
    """
    T = check_T(T_camcv_ds, "T_camcv_ds")
    out: dict[int, MarkerProjection] = {}
    in_view = markers_in_view(  # all markers in one call (one projection batch per frame)
        camera_model, T, np.stack([spec.corners_ds_m for spec in marker_set.markers])
    )
    for spec, in_image in zip(marker_set.markers, in_view.tolist(), strict=True):
        pts_ds = np.vstack([spec.corners_ds_m, spec.T_ds_marker[:3, 3]])
        pts_cam = transform_points(T, pts_ds)  # (5, 3): 4 corners + centre
        px = camera_model.project(pts_cam)
        in_front = bool(np.all(pts_cam[:, 2] > 0.0))
        dist = np.linalg.norm(pts_cam, axis=1)
        occluded = False
        if range_m is not None and in_image:
            uv = np.rint(px).astype(int)
            seen = range_m[uv[:, 1], uv[:, 0]]
            occluded = bool(np.any(seen < dist - occlusion_tol_m))
        out[spec.marker_id] = MarkerProjection(
            marker_id=spec.marker_id,
            corners_px=px[:4],
            centre_px=px[4],
            corners_range_m=dist[:4],
            in_front=in_front,
            in_image=in_image,
            occluded=occluded,
            visible=in_image and not occluded,
        )
    return out


# ----------------------------------------------------------------------------- scene


@dataclass
class RenderScene:
    """A scene with the tank, the DS (with markers), a lamp-lit camera: built once, reused.

    Attributes:
        scene: the SAPIEN scene (add the vehicle or more actors to it as needed).
        ds: the docking station (its ``T_worldned_ds`` and marker set).
        tank: the tank entity.
        rig: the camera.
    """

    scene: sapien.Scene
    ds: DockingStation
    tank: sapien.Entity
    rig: CameraRig

    def render(
        self,
        T_worldned_bodyfrd: ArrayLike | None = None,
        *,
        T_worldned_camcv: ArrayLike | None = None,
    ) -> RenderResult:
        """Render a frame (see :meth:`CameraRig.render`)."""
        return self.rig.render(T_worldned_bodyfrd, T_worldned_camcv=T_worldned_camcv)

    def T_camcv_ds(self, T_worldned_camcv: ArrayLike) -> np.ndarray:
        """(4, 4) DS pose in the camera frame for a camera pose in world NED."""
        return inv_T(check_T(T_worldned_camcv, "T_worldned_camcv")) @ self.ds.T_worldned_ds

    def ground_truth(self, result: RenderResult) -> dict[int, MarkerProjection]:
        """Marker corners and visibility for a frame rendered by this scene."""
        return project_markers(
            result.camera,
            self.T_camcv_ds(result.T_worldned_camcv),
            self.ds.marker_set,
            result.range_m,
        )


def make_render_scene(
    ds_cfg: DockingStationConfig | None = None,
    marker_set: MarkerSet | str | os.PathLike[str] | None = None,
    T_worldned_ds: ArrayLike | None = None,
    camera_model: CameraModel | None = None,
    T_bodyfrd_camcv: ArrayLike | None = None,
    render_cfg: RenderConfig | None = None,
    cache_dir: str | os.PathLike[str] | None = None,
    scene: sapien.Scene | None = None,
    surface_lid: bool = False,
    tank_collision: bool = True,
) -> RenderScene:
    """Build (once) a scene with the tank, the DS, ambient light and the camera with its lamp.

    Args:
        ds_cfg: DS and tank geometry.
        marker_set: markers (object or file); None: ``ds_cfg.marker_set_path`` or the default.
        T_worldned_ds: DS pose in world NED; None: on the tank floor at the centre.
        camera_model: camera intrinsics; None: the reference camera.
        T_bodyfrd_camcv: camera extrinsics; None: the reference extrinsics.
        render_cfg: renderer and lighting.
        cache_dir: where the default marker set is generated.
        scene: an existing scene to add everything to; None: a new ``sapien.Scene()``.
        surface_lid: close the tank at the water surface (see :func:`build_tank`).
        tank_collision: give the tank PhysX collision shapes (see :func:`build_tank`).

    Returns:
        The :class:`RenderScene`.
    """
    render_cfg = validated(render_cfg or RenderConfig())
    scene = scene if scene is not None else new_scene()
    scene.ambient_light = list(render_cfg.ambient_rgb)
    tank = build_tank(scene, ds_cfg, surface_lid=surface_lid, collision=tank_collision)
    ds = build_docking_station(scene, ds_cfg, marker_set, T_worldned_ds, cache_dir)
    rig = CameraRig(scene, camera_model, T_bodyfrd_camcv, render_cfg)
    return RenderScene(scene, ds, tank, rig)


def board_views(
    altitudes_m: ArrayLike,
    cols: int = 8,
    rows: int = 6,
    square_m: float = 0.06,
    white_rgb: tuple[float, float, float] = (0.6, 0.6, 0.6),
    render_cfg: RenderConfig | None = None,
    camera_model: CameraModel | None = None,
    seed: int = 0,
    max_tilt_deg: float = 10.0,
) -> list[RenderResult]:
    """A chessboard on the tank floor seen by the lamp-lit camera from each altitude (in air:
    apply :func:`sim.water.apply_water` to the results), as a diver films a board to fit the
    water (``sim fit-water``): the camera looks down with a seeded tilt of up to
    ``max_tilt_deg`` per axis and a seeded sideways offset that moves the board across the
    image as far as it still fits in view.

    The board (:func:`sim.docking_station.build_chessboard`) follows OpenCV's chessboard
    object frame. The renders are linear and unclipped (:class:`RenderResult`): the sensor
    model clips, after the water and the exposure."""
    from scipy.spatial.transform import Rotation  # half a second to import, only needed here

    alts = np.asarray(altitudes_m, dtype=float).ravel()
    depth = max(8.0, float(alts.max(initial=0.0)) + 2.0)
    ds_cfg = DockingStationConfig(tank_depth_m=depth)
    render_cfg = validated(render_cfg or RenderConfig())
    scene = new_scene()
    scene.ambient_light = list(render_cfg.ambient_rgb)
    build_tank(scene, ds_cfg)
    half = np.array([cols / 2.0, rows / 2.0]) * square_m
    build_chessboard(scene, cols, rows, square_m, make_T(None, [-half[0], -half[1], depth - 1e-3]),
                     white_rgb=white_rgb)  # fmt: skip
    rig = CameraRig(scene, camera_model, None, render_cfg)
    cam = rig.camera
    # half the view at 1 m (m), less the tilt's reach: the board moves only where it still fits
    view = np.array([cam.width_px / (2 * cam.fx_px), cam.height_px / (2 * cam.fy_px)])
    view -= math.tan(math.radians(max_tilt_deg))
    rng = np.random.default_rng(seed)
    out = []
    for alt in alts:
        R = Rotation.from_euler("xyz", rng.uniform(-max_tilt_deg, max_tilt_deg, 3), degrees=True)
        room = np.maximum(view * alt - half, 0.0)
        off = rng.uniform(-1.0, 1.0, 2) * room
        T = make_T(R.as_matrix(), [off[0], off[1], depth - float(alt)])
        out.append(rig.render(T_worldned_camcv=T))
    return out
