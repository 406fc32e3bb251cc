"""The docking env's per-step maths over many envs at once (arrays with a leading env axis).

Each function or class here is the batched twin of one scalar piece of
:class:`rl.env.docking_env.DockingEnv`, kept beside it because the two round differently (an
``einsum`` over the env axis against one matrix product, a norm of rows against one norm): each
twin is tested against the other on the same inputs, draws included, in one place
(``tests/test_batch_twins.py``, which also checks that every row of this table is tested there):

=============================  ===========================================================
batched                        scalar
=============================  ===========================================================
:func:`yaw_b`                  :func:`rl.env.task.yaw_of` (away from gimbal lock)
:func:`rotvec_to_R_b`          :func:`rl.env.error_model.apply_error` (its rotation)
:func:`docking_errors_b`       :func:`rl.env.task.docking_errors`
:func:`ds_visible_b`           :func:`rl.env.task.ds_visible`
:func:`pegs_seated_b`          :func:`rl.env.task.pegs_seated`
:class:`BatchFilter`           :class:`rl.env.estimator.DSPoseFilter`
:func:`reward_terms_b`         :class:`rl.env.rewards.DockingReward` (``__call__``)
:class:`BatchErrorModel`       :class:`rl.env.error_model.ErrorModelSource` (``measure``)
:func:`proxy_measure_b`        :class:`rl.env.obs_sources.ProxySource` (``measure``)
:func:`observation_frames_b`   :func:`rl.env.observation.observation_frame`
=============================  ===========================================================

Where a piece is exact elementwise arithmetic it is written once, batched, and the scalar env
calls it with a batch of one: :func:`rl.env.task.paper_success_b` (comparisons only).

Poses are (N, 4, 4) ``T_world_body`` (world NED, body FRD) and ``T_world_ds``.
"""

from __future__ import annotations

import math

import numpy as np

from uwdock.calibration.frames import inv_T_b, wrap_angle_rad
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.error_model import MIN_VIEW_DEPTH_M, N_ERR, N_VISIBLE_BINS, ErrorModel
from uwdock.rl.env.observation import ACC_SCALE_MPS2, FINE_ERROR_SCALE_M, OBS_BOUND, POS_SCALE_M
from uwdock.rl.env.rewards import RewardConfig
from uwdock.rl.env.task import DockingTaskConfig

__all__ = [
    "BATCH_SOURCES",
    "BatchErrorModel",
    "BatchFilter",
    "docking_errors_b",
    "ds_visible_b",
    "inv_T_b",
    "observation_frames_b",
    "pegs_seated_b",
    "proxy_measure_b",
    "reward_terms_b",
    "rotvec_to_R_b",
    "yaw_b",
]


#: The observation sources a batch can step (the camera renders per env and step).
BATCH_SOURCES = ("proxy", "error-model", "acoustic")


# --------------------------------------------------------------------------- geometry


def yaw_b(T: np.ndarray) -> np.ndarray:
    """(N,) yaw (rad, ZYX) of (N, 4, 4) poses (:func:`rl.env.task.yaw_of` away from gimbal lock)."""
    return np.arctan2(T[:, 1, 0], T[:, 0, 0])


def yaw_T_b(xyz: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(N, 4, 4) level poses from positions (N, 3) and yaws (N,)."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.zeros((len(yaw), 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 2, 2] = T[:, 3, 3] = 1.0
    T[:, :3, 3] = xyz
    return T


def rotvec_to_R_b(rv: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices of rotation vectors (N, 3): SciPy's, as the scalar
    :func:`rl.env.error_model.apply_error` uses."""
    from scipy.spatial.transform import Rotation  # as apply_error: loaded on first use

    return Rotation.from_rotvec(np.asarray(rv, dtype=np.float64)).as_matrix()


# --------------------------------------------------------------------------- task


def docking_errors_b(
    T_world_body: np.ndarray, T_world_ds: np.ndarray, cfg: DockingTaskConfig
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) target position in the body frame (m) and (N,) wrapped yaw error (rad)."""
    T_target = T_world_ds @ cfg.T_ds_target
    d = T_target[:, :3, 3] - T_world_body[:, :3, 3]
    e = np.einsum("nji,nj->ni", T_world_body[:, :3, :3], d)
    psi = wrap_angle_rad(yaw_b(T_target) - yaw_b(T_world_body))
    return e, psi


def ds_visible_b(T_body_ds: np.ndarray, cfg: DockingTaskConfig) -> np.ndarray:
    """(N,) bool: the reference visibility test of each ``T_body_ds``."""
    p = T_body_ds[:, :3, 3]
    ax, ay = (math.tan(math.radians(a)) for a in cfg.visibility_half_angles_deg)
    z = np.where(p[:, 2] > 0, p[:, 2], 1.0)
    inside = (p[:, 0] / (z * ax)) ** 2 + (p[:, 1] / (z * ay)) ** 2 <= 1.0
    return (p[:, 2] > 0) & (np.linalg.norm(p, axis=1) <= cfg.visibility_range_m) & inside


def pegs_seated_b(
    T_world_body: np.ndarray, T_world_ds: np.ndarray, cfg: DockingTaskConfig
) -> np.ndarray:
    """(N,) bool: every peg within tolerance of its nearest notch seat (strict criterion)."""
    T_ds_body = inv_T_b(T_world_ds) @ T_world_body
    pegs_body = np.asarray(cfg.peg_positions_body_m, dtype=np.float64)  # (P, 3)
    pegs = np.einsum("nij,pj->npi", T_ds_body[:, :3, :3], pegs_body) + T_ds_body[:, None, :3, 3]
    notches = np.asarray(cfg.notch_positions_ds_m, dtype=np.float64)  # (Q, 3)
    d = notches[None, None, :, :] - pegs[:, :, None, :]  # (N, P, Q, 3)
    dxy = np.linalg.norm(d[..., :2], axis=3)
    k = np.argmin(dxy, axis=2)  # (N, P)
    best_xy = np.take_along_axis(dxy, k[..., None], axis=2)[..., 0]
    best_z = np.take_along_axis(d[..., 2], k[..., None], axis=2)[..., 0]
    ok = (best_xy <= cfg.strict_peg_xy_m) & (np.abs(best_z) <= cfg.strict_peg_z_m)
    return ok.all(axis=1)


# --------------------------------------------------------------------------- filter


class BatchFilter:
    """:class:`rl.env.estimator.DSPoseFilter` for N envs: states ``x`` (N, 4) [x, y, z, yaw] of the
    DS in the world and covariances ``P`` (N, 4, 4). Every env shares the filter's config
    (``fuse``, ``gate_sigma``, drift)."""

    def __init__(self, n: int, fuse: bool, gate_sigma: float, q_per_s: np.ndarray) -> None:
        self.fuse = bool(fuse)
        self.gate_sigma = float(gate_sigma)
        self.q_per_s = np.asarray(q_per_s, dtype=np.float64)  # (4,) variance growth per second
        self.x = np.zeros((n, 4))
        self.P = np.tile(np.eye(4), (n, 1, 1))

    def predict(self, dt_s: float) -> None:
        self.P = self.P + np.diag(self.q_per_s * dt_s)[None]

    def T_world_ds(self) -> np.ndarray:
        """(N, 4, 4) estimated DS poses (level)."""
        return yaw_T_b(self.x[:, :3], self.x[:, 3])

    def update(self, mask: np.ndarray, z: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Fuse measurements ``z`` (N, 4) with covariances ``R`` (N, 4, 4) into the envs of
        ``mask``; (N,) bool of the envs that accepted theirs (gating)."""
        idx = np.flatnonzero(mask)
        accepted = np.zeros(len(mask), dtype=bool)
        if idx.size == 0:
            return accepted
        zi, Ri = z[idx], R[idx]
        if not self.fuse:
            self.x[idx], self.P[idx] = zi, Ri
            accepted[idx] = True
            return accepted
        x, P = self.x[idx], self.P[idx]
        innov = zi - x
        innov[:, 3] = wrap_angle_rad(innov[:, 3])
        S = P + Ri
        S_inv = np.linalg.inv(S)
        ok = np.ones(idx.size, dtype=bool)
        if self.gate_sigma > 0:
            d2 = np.einsum("ni,nij,nj->n", innov, S_inv, innov)
            ok = d2 <= self.gate_sigma**2
        K = P @ S_inv
        x_new = x + np.einsum("nij,nj->ni", K, innov)
        x_new[:, 3] = wrap_angle_rad(x_new[:, 3])
        P_new = (np.eye(4)[None] - K) @ P
        self.x[idx[ok]], self.P[idx[ok]] = x_new[ok], P_new[ok]
        accepted[idx[ok]] = True
        return accepted

    def update_position(self, mask: np.ndarray, p_m: np.ndarray, sigma_m: np.ndarray) -> None:
        """Fuse position-only fixes (N, 3) with standard deviations (N,) (m); yaw kept."""
        z = np.concatenate([p_m, self.x[:, 3:4]], axis=1)
        var = np.asarray(sigma_m, dtype=np.float64) ** 2
        R = np.zeros((len(var), 4, 4))
        R[:, 0, 0] = R[:, 1, 1] = R[:, 2, 2] = var
        R[:, 3, 3] = 1e6
        self.update(mask, z, R)

    def sigma_xy_m(self) -> np.ndarray:
        """(N,) the observation's horizontal standard deviation (m)."""
        return np.sqrt(0.5 * (self.P[:, 0, 0] + self.P[:, 1, 1]))


# --------------------------------------------------------------------------- reward


def reward_terms_b(
    cfg: RewardConfig,
    weights: dict[str, float],
    smooth_mask: np.ndarray,
    e_xyz: np.ndarray,
    e_psi: np.ndarray,
    action: np.ndarray,
    prev_action: np.ndarray,
    collided: np.ndarray,
    docked: np.ndarray,
    truncated: np.ndarray,
    prev_e_xy_m: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """The weighted reward terms (N,) each, as :class:`rl.env.rewards.DockingReward` computes them.
    ``prev_e_xy_m`` (N,): each env's horizontal error at the step before (NaN after a reset),
    for r_stall; it is updated in place (with ``cfg.stall_penalty`` > 0)."""
    da = np.abs(action - prev_action)[:, smooth_mask]
    abs_psi = np.abs(e_psi)
    precision = np.zeros(len(e_psi))
    if cfg.precision_gain > 0:
        x = np.linalg.norm(e_xyz, axis=1) / cfg.precision_scale_m
        if cfg.precision_yaw_scale_rad > 0:
            x = x + abs_psi / cfg.precision_yaw_scale_rad
        precision = cfg.precision_gain * np.exp(-x)
    stall = np.zeros(len(e_psi))
    if cfg.stall_penalty > 0 and prev_e_xy_m is not None:
        e_xy = np.hypot(e_xyz[:, 0], e_xyz[:, 1])
        pushing = np.abs(action).max(axis=1) >= cfg.stall_saturated
        with np.errstate(invalid="ignore"):
            stuck = ~(prev_e_xy_m - e_xy >= cfg.stall_progress_m) & ~np.isnan(prev_e_xy_m)
        stall = np.where(pushing & (e_xy > cfg.stall_clearance_m) & stuck, -cfg.stall_penalty, 0.0)
        prev_e_xy_m[:] = e_xy
    terms = {
        # a row-wise sum, not a BLAS matrix-vector product: that one's rounding depends on how
        # many rows there are, so a batch split over processes would differ in the last bit
        "dist": -(np.abs(e_xyz) * np.asarray(cfg.w_xyz, dtype=np.float64)).sum(axis=1),
        "angle": np.exp(-cfg.angle_gain * abs_psi) - 1.0 - cfg.angle_linear * abs_psi / math.pi,
        "smooth": -(cfg.smooth_scale / max(da.shape[1], 1)) * np.exp(da.sum(axis=1)),
        "collision": np.where(collided, -cfg.collision_penalty, 0.0),
        "mission": np.where(
            docked, cfg.success_reward, np.where(truncated, -cfg.truncation_penalty, 0.0)
        ),
        "precision": precision,
        "stall": stall,
    }
    return {k: weights[k] * v for k, v in terms.items()}


# --------------------------------------------------------------------------- sources


class BatchErrorModel:
    """:class:`rl.env.error_model.ErrorModelSource` for N envs (same model, water and memory flag):
    detection drawn from the table cell (range bin, markers in view), then an outlier or the
    biased, correlated (AR(1)) error; per env the memory of the last inlier."""

    def __init__(self, model: ErrorModel, water: str, temporal: bool, n: int) -> None:
        self.model = model
        self.table = model.table(water)
        self.temporal = bool(temporal)
        self.z_prev = np.zeros((n, N_ERR))
        self.has_prev = np.zeros(n, dtype=bool)
        self.t_prev_s = np.zeros(n)
        self._corners = np.asarray(model.corners_ds, dtype=np.float64).reshape(-1, 3)
        self._n_markers = len(model.corners_ds)
        # per range bin: whether the table holds gross-error samples to draw from
        self._has_outliers = np.array([o.size > 0 for o in self.table["outliers"]])

    def reset(self, i: int) -> None:
        """Forget env ``i``'s memory (a new episode)."""
        self.has_prev[i] = False

    def count_in_view(self, T_cam_ds: np.ndarray) -> np.ndarray:
        """(N,) markers with all four corners in front of the camera and in the image."""
        cam = self.model.camera
        p = np.einsum("nij,mj->nmi", T_cam_ds[:, :3, :3], self._corners) + T_cam_ds[:, None, :3, 3]
        flat = p.reshape(-1, 3)
        # the camera model's projection (one OpenCV call for every corner of every env)
        inside = cam.in_image(cam.project(flat)) & (flat[:, 2] > MIN_VIEW_DEPTH_M)
        per_marker = inside.reshape(len(T_cam_ds), self._n_markers, 4).all(axis=2)
        return per_marker.sum(axis=1)

    def measure(
        self,
        T_world_body: np.ndarray,
        T_world_ds: np.ndarray,
        time_s: np.ndarray,
        uniforms: np.ndarray,
        normals: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(detected (N,) bool, T_world_ds measured (N, 4, 4), cov (N, 4, 4))``; rows of
        undetected envs are meaningless. The draws: ``uniforms`` (N, 3) in [0, 1) (detection,
        outlier, which outlier sample) and ``normals`` (N, 6) standard normal."""
        m, t = self.model, self.table
        n = len(T_world_body)
        T_world_cam = T_world_body @ m.T_body_cam
        T_cam_ds = inv_T_b(T_world_cam) @ T_world_ds
        r = np.linalg.norm(T_cam_ds[:, :3, 3], axis=1)
        n_vis = np.minimum(self.count_in_view(T_cam_ds), N_VISIBLE_BINS - 1)
        k = np.minimum((r / m.range_bin_m).astype(np.int64), m.n_bins - 1)
        u = np.asarray(uniforms, dtype=np.float64)
        w = np.asarray(normals, dtype=np.float64)
        detected = u[:, 0] < t["p"][k, n_vis]
        outlier = detected & self._has_outliers[k] & (u[:, 1] < t["p_out"][k])
        inlier = detected & ~outlier
        # the AR(1) memory of each env's last inlier (misses and gross errors break the chain)
        z = w.copy()
        rho = t["rho"]
        if self.temporal and m.step_s and np.any(rho != 0):
            chained = inlier & self.has_prev
            steps = (time_s - self.t_prev_s) / m.step_s
            chained &= steps > 0
            if chained.any():
                s = steps[chained][:, None]
                c = np.sign(rho) ** np.round(s) * np.abs(rho) ** s
                z[chained] = c * self.z_prev[chained] + np.sqrt(1.0 - c * c) * w[chained]
        err = np.zeros((n, N_ERR))
        err[inlier] = t["bias"][k[inlier]] + np.einsum(
            "nij,nj->ni", t["chol"][k[inlier]], z[inlier]
        )
        for i in np.flatnonzero(outlier):
            samples = t["outliers"][k[i]]
            err[i] = samples[min(int(u[i, 2] * len(samples)), len(samples) - 1)]
        self.z_prev[inlier] = z[inlier]
        self.t_prev_s[inlier] = time_s[inlier]
        self.has_prev = inlier.copy()
        # the measured pose: the error applied in the camera frame
        T_est = T_cam_ds.copy()
        T_est[:, :3, :3] = rotvec_to_R_b(err[:, 3:]) @ T_cam_ds[:, :3, :3]
        T_est[:, :3, 3] += err[:, :3]
        T_meas = T_world_cam @ T_est
        R = T_world_cam[:, :3, :3]
        cov = np.zeros((n, 4, 4))
        cov[:, :3, :3] = R @ t["cov"][k][:, :3, :3] @ np.swapaxes(R, 1, 2) + np.eye(3) * 1e-4
        cov[:, 3, 3] = t["cov"][k][:, 5, 5] + 2.5e-5
        return detected, T_meas, cov


def proxy_measure_b(
    T_world_body: np.ndarray,
    T_world_ds: np.ndarray,
    cfg: DockingTaskConfig,
    normals: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The paper's proxy for N envs: ``(visible (N,), T_world_ds measured, cov)`` (it always
    measures; ``visible`` is its detection flag); ``normals`` (N, 6) standard normal draws."""
    e, _ = docking_errors_b(T_world_body, T_world_ds, cfg)
    visible = ds_visible_b(inv_T_b(T_world_body) @ T_world_ds, cfg)
    sigma = np.linalg.norm(e, axis=1) / 6.0
    draws = np.asarray(normals, dtype=np.float64)
    noise = draws[:, :3] * (sigma / 2.0)[:, None]
    noise += np.where(visible, 0.0, sigma)[:, None] * draws[:, 3:]
    var = (sigma / 2.0) ** 2 + np.where(visible, 0.0, sigma**2)
    T = T_world_ds.copy()
    T[:, :3, 3] += np.einsum("nij,nj->ni", T_world_body[:, :3, :3], noise)
    cov = np.zeros((len(sigma), 4, 4))
    cov[:, 0, 0] = cov[:, 1, 1] = cov[:, 2, 2] = var
    cov[:, 3, 3] = 1e-6
    return visible, T, cov


# --------------------------------------------------------------------------- observation


def observation_frames_b(
    cfg: EnvConfig,
    T_world_body: np.ndarray,
    T_world_ds_est: np.ndarray,
    sigma_xy_m: np.ndarray,
    velocity_frd_mps: np.ndarray,
    yaw_rate_radps: np.ndarray,
    acceleration_frd_mps2: np.ndarray,
    prev_action: np.ndarray,
    detected: np.ndarray,
    contact: np.ndarray | None = None,
) -> np.ndarray:
    """(N, frame_dim) float32 observation frames (:func:`rl.env.observation.observation_frame`;
    ``contact``: (N, 2) :meth:`rl.env.observation.ContactMemory.features`, for ``obs_contact``)."""
    e_hat, psi_hat = docking_errors_b(T_world_body, T_world_ds_est, cfg.task)
    parts = [
        np.clip(e_hat, -POS_SCALE_M, POS_SCALE_M) / POS_SCALE_M,
        (psi_hat / math.pi)[:, None],
        velocity_frd_mps,
        yaw_rate_radps[:, None],
        acceleration_frd_mps2 / ACC_SCALE_MPS2,
    ]
    if cfg.obs_last_action:
        parts.append(prev_action)
    if cfg.obs_uncertainty:
        parts.append(np.stack([np.minimum(sigma_xy_m, 2.0), detected.astype(np.float64)], axis=1))
    if cfg.obs_contact:
        if contact is None:
            raise ValueError("obs_contact: the frames need the contact values")
        parts.append(np.asarray(contact, dtype=np.float64).reshape(-1, 2))
    if cfg.obs_fine_error:
        parts.append(np.tanh(np.asarray(e_hat, dtype=np.float64) / FINE_ERROR_SCALE_M))
    return np.clip(np.concatenate(parts, axis=1), -OBS_BOUND, OBS_BOUND).astype(np.float32)
