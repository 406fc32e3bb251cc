"""The simulated world of one docking env: SAPIEN scene, tank, docking station, AUV, currents,
and the downward camera, composed once from a :class:`~uwdock.sim.world_config.WorldConfig`.

Built once per env (scene construction is slow); :meth:`DockingWorld.reset` moves things, and
gives the entities a fresh PhysX system: PhysX keeps contact state (pair caches, friction
anchors) from one episode into the next, so without it an episode's contacts, and so its
trajectory, depended on the episodes the process had run before (seen as run-to-run differences
of the camera loop between one and two evaluation workers). It costs ~0.16 ms per episode (the
static actors keep their shapes, so the fast path reads nothing again).
Without a camera the scene is physics-only (collision shapes, no Vulkan needed); with one, the
tank, DS and markers are also visual and the downward camera (:class:`uwdock.sim.camera.SimCamera`,
resolved by :func:`uwdock.calibration.camera.resolve_camera` from the config's camera file and
width) captures them through the config's water.
"""

from __future__ import annotations

import numpy as np
import sapien

from uwdock.calibration.camera import resolve_camera
from uwdock.calibration.frames import R_from_rpy, inv_T, make_T
from uwdock.sim.camera import Frame, SimCamera
from uwdock.sim.docking_station import DockingStationConfig, build_docking_station
from uwdock.sim.physics import VehicleBody, make_physics_scene, tank_planes
from uwdock.sim.render import make_render_scene
from uwdock.sim.scene import new_scene
from uwdock.sim.vehicle import Current
from uwdock.sim.world_config import WorldConfig

__all__ = ["DockingWorld", "WorldConfig"]


class DockingWorld:
    """Scene + vehicle + DS (+ camera) of one docking env (poses in world NED, body FRD).

    Args:
        cfg: the world.
        with_camera: build the visual scene and the downward camera (needs Vulkan).
    """

    def __init__(self, cfg: WorldConfig, with_camera: bool = False) -> None:
        cfg.validate()
        self.cfg = cfg
        self.with_camera = with_camera
        L, W, D = cfg.tank_size_m
        self.ds_cfg = DockingStationConfig(
            tank_length_m=L, tank_width_m=W, tank_depth_m=D, marker_set_path=cfg.marker_set_path
        )
        self.render_scene = None
        self.camera: SimCamera | None = None
        # a vehicle without a free surface (surface_band_m = 0) needs a lid to stay in the water
        lid = cfg.vehicle.surface_band_m <= 0
        if with_camera:
            scene = new_scene()
            scene.set_timestep(1.0 / cfg.physics_hz)
            cam, T_body_cam = resolve_camera(cfg.camera_file, cfg.camera_width_px)
            self.render_scene = make_render_scene(
                self.ds_cfg,
                camera_model=cam,
                T_bodyfrd_camcv=T_body_cam,
                scene=scene,
                tank_collision=False,  # the vehicle's own plane contact (below)
            )
            self.camera = SimCamera(self.render_scene.rig, cfg.water.config, cfg.water_device)
            self.scene = scene
            self.ds = self.render_scene.ds
        else:
            self.scene = make_physics_scene(1.0 / cfg.physics_hz)
            self.ds = build_docking_station(self.scene, self.ds_cfg, visual=False)
        self.current = Current(cfg.current)
        self.vehicle = VehicleBody(self.scene, cfg.vehicle, self.current)
        # the tank's floor and walls (and the surface, for a vehicle without a free surface)
        # are planes of the vehicle's own contact model: only the DS needs PhysX
        self.vehicle.set_tank_planes(
            tank_planes(L, W, D, lid=lid), friction=self.ds_cfg.dynamic_friction
        )
        #: give the entities a fresh PhysX system at every reset (module docstring); False
        #: where this scene's PhysX never steps and the reset only places the bodies for
        #: another simulator to read (:class:`uwdock.rl.env.batch_env.BatchDockingEnv` with
        #: the kernel's or the shared scene's contact)
        self.fresh_physics = True
        #: (4, 4) this episode's mounting error, the true camera frame in the calibrated one
        self.T_camcal_camtrue = np.eye(4)
        self._T_body_rendered: np.ndarray | None = None  # the body pose correction it implies

    @property
    def floor_z_m(self) -> float:
        """World NED z of the DS origin when the DS stands on the tank floor."""
        return self.ds_cfg.tank_depth_m - self.ds_cfg.floor_thickness_m

    @property
    def T_world_ds(self) -> np.ndarray:
        """(4, 4) DS pose in world NED."""
        return self.ds.T_worldned_ds

    @property
    def T_world_body(self) -> np.ndarray:
        """(4, 4) vehicle pose, body FRD in world NED."""
        return self.vehicle.T_world_ned_body_frd

    @property
    def time_s(self) -> float:
        return self.vehicle.time_s

    def reset(
        self, T_world_ds: np.ndarray, T_world_body: np.ndarray, rng: np.random.Generator
    ) -> None:
        """Move the DS, draw the current, (optionally) the vehicle and the camera's mounting
        error, place the vehicle. Nothing is drawn for a zero range (same random stream)."""
        if self.fresh_physics:
            self._fresh_physics()
        self.ds.set_pose(T_world_ds)
        self.current.reset(rng)
        if self.cfg.randomise_vehicle:
            drawn = self.cfg.vehicle_randomisation.sample(self.cfg.vehicle, rng)
            self.vehicle.set_config(drawn, nominal_config=self.cfg.vehicle)
        self.vehicle.reset(T_world_body, rng=rng)
        err_m, err_deg = self.cfg.camera_mount_error_m, self.cfg.camera_mount_error_deg
        if err_m > 0 or err_deg > 0:
            t_m = rng.uniform(-err_m, err_m, 3)
            rpy = np.radians(rng.uniform(-err_deg, err_deg, 3))
            self.set_camera_mount_error(make_T(R_from_rpy(*rpy), t_m))

    def _fresh_physics(self) -> None:
        """Move every entity into a new scene with a new PhysX system (same render system), so
        no contact state survives from the last episode (module docstring)."""
        old = self.scene
        entities = list(old.entities)
        for e in entities:
            old.remove_entity(e)
        systems: list = [sapien.physx.PhysxCpuSystem()]
        if self.render_scene is not None:
            systems.append(old.render_system)
        scene = new_scene(systems)
        scene.set_timestep(old.timestep)
        for e in entities:
            scene.add_entity(e)
        self.scene = scene
        if self.render_scene is not None:
            self.render_scene.scene = scene
        self.vehicle.rebind(scene)

    def set_camera_mount_error(self, T_camcal_camtrue: np.ndarray) -> None:
        """Mount the camera off its calibration by ``T_camcal_camtrue`` (4, 4) until the next
        draw; perception keeps the calibration (``camera.T_body_cam``)."""
        self.T_camcal_camtrue = np.asarray(T_camcal_camtrue, dtype=np.float64)
        self._T_body_rendered = None
        if self.camera is not None and not np.array_equal(self.T_camcal_camtrue, np.eye(4)):
            # the rig mounts the camera at its calibration: hand it this body pose instead
            T_body_cam = self.camera.T_body_cam
            self._T_body_rendered = T_body_cam @ self.T_camcal_camtrue @ inv_T(T_body_cam)

    def _rendered_from(self, T_world_body: np.ndarray | None) -> np.ndarray:
        T = self.T_world_body if T_world_body is None else T_world_body
        return T if self._T_body_rendered is None else T @ self._T_body_rendered

    def step(self, wrench_body: np.ndarray, dt_s: float) -> None:
        self.vehicle.step(wrench_body, dt_s)

    def capture(
        self, rng: np.random.Generator | None, T_world_body: np.ndarray | None = None
    ) -> Frame | None:
        """The downward camera's frame, water applied (None: no camera), rendered from the
        true camera mounting (calibration plus this episode's mounting error).

        Args:
            rng: generator for the sensor noise of the water model.
            T_world_body: (4, 4) vehicle pose to render from (None: the vehicle's own).
        """
        if self.camera is None:
            return None
        return self.camera.capture(self._rendered_from(T_world_body), rng)

    def render_camera_rgb(self) -> np.ndarray | None:
        """(H, W, 3) uint8 RGB view of the downward camera in air, or None without a camera."""
        if self.camera is None:
            return None
        return self.camera.render(self._rendered_from(None)).rgb

    def close(self) -> None:
        self.render_scene = None
        self.camera = None
        self.scene = None
