"""The simulated world of one docking env: SAPIEN scene, tank, docking station, AUV, camera.

Built once per env (scene construction is slow); :meth:`DockingWorld.reset` only moves things.
Without a camera the scene is physics-only (collision shapes, no Vulkan needed); with one, the
tank, DS and markers are also visual and the downward camera renders them.
"""

from __future__ import annotations

import numpy as np

from uwdock.rl.config import EnvConfig
from uwdock.sim.docking_station import DockingStationConfig, build_docking_station, build_tank
from uwdock.sim.physics import VehicleBody, make_physics_scene
from uwdock.sim.vehicle import Current


class DockingWorld:
    """Scene + vehicle + DS for :class:`rl.env.DockingEnv` (poses in world NED, body FRD)."""

    def __init__(self, cfg: EnvConfig, with_camera: bool = False) -> None:
        self.cfg = cfg
        self.with_camera = with_camera
        L, W, D = cfg.tank_size_m
        self.ds_cfg = DockingStationConfig(
            tank_length_m=L, tank_width_m=W, tank_depth_m=D, marker_set_path=cfg.marker_set_path
        )
        self.render_scene = None
        if with_camera:
            import sapien

            from uwdock.calibration.camera import load_camera
            from uwdock.sim.render import make_render_scene

            scene = sapien.Scene()
            scene.set_timestep(1.0 / cfg.physics_hz)
            cam, T_body_cam = None, None
            if cfg.camera_file:
                cam, T_body_cam = load_camera(cfg.camera_file)
            if cfg.camera_width_px:
                from uwdock.calibration.camera import reference_camera

                base = cam or reference_camera()
                h = round(base.height_px * cfg.camera_width_px / base.width_px)
                cam = base.scaled(cfg.camera_width_px, h)
            self.render_scene = make_render_scene(
                self.ds_cfg,
                camera_model=cam,
                T_bodyfrd_camcv=T_body_cam,
                scene=scene,
                surface_lid=True,
            )
            self.scene = scene
            self.ds = self.render_scene.ds
        else:
            self.scene = make_physics_scene(1.0 / cfg.physics_hz)
            build_tank(self.scene, self.ds_cfg, visual=False, surface_lid=True)
            self.ds = build_docking_station(self.scene, self.ds_cfg, visual=False)
        self.current = Current(cfg.current)
        self.vehicle = VehicleBody(self.scene, cfg.vehicle, self.current)

    @property
    def floor_z_m(self) -> float:
        """World NED z of the DS origin when the DS stands on the tank floor."""
        return self.ds_cfg.tank_depth_m - self.ds_cfg.floor_thickness_m

    @property
    def T_world_ds(self) -> np.ndarray:
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
        """Move the DS, draw the current and (optionally) the vehicle, place the vehicle."""
        self.ds.set_pose(T_world_ds)
        self.current.reset(rng)
        if self.cfg.randomise_vehicle:
            drawn = self.cfg.vehicle_randomisation.sample(self.cfg.vehicle, rng)
            self.vehicle.set_config(drawn, nominal_config=self.cfg.vehicle)
        self.vehicle.reset(T_world_body, rng=rng)

    def step(self, wrench_body: np.ndarray, dt_s: float) -> None:
        self.vehicle.step(wrench_body, dt_s)

    def render(self):
        """Render the downward camera at the vehicle's pose (a :class:`sim.render.RenderResult`)."""
        if self.render_scene is None:
            return None
        return self.render_scene.render(self.T_world_body)

    def render_camera(self) -> np.ndarray | None:
        res = self.render()
        return None if res is None else res.rgb

    def close(self) -> None:
        self.render_scene = None
        self.scene = None
