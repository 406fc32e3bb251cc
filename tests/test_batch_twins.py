"""The batched twins of the docking env's step (``rl.env.batch_parts``) against their scalar
originals, in one place: each twin on the same inputs as its original (the same random draws
where it draws), and every row of ``batch_parts``' table of twins tested here.

Whole batched episodes against per-env episodes are ``tests/test_batch_env.py``'s."""

from __future__ import annotations

import ast
import math
import re
from pathlib import Path

import numpy as np
import pytest

from uwdock.calibration.frames import R_from_rpy, make_T
from uwdock.rl.env import batch_parts
from uwdock.rl.env.batch_parts import (
    BatchErrorModel,
    BatchFilter,
    docking_errors_b,
    ds_visible_b,
    inv_T_b,
    observation_frames_b,
    pegs_seated_b,
    proxy_measure_b,
    reward_terms_b,
    rotvec_to_R_b,
    yaw_b,
)
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.error_model import (
    ErrorModelSource,
    apply_error,
    count_in_view,
    load_error_model,
    pose_error,
)
from uwdock.rl.env.estimator import DSPoseFilter, EstimatorConfig
from uwdock.rl.env.obs_sources import ProxySource, StepContext
from uwdock.rl.env.observation import observation_frame
from uwdock.rl.env.rewards import DockingReward, RewardConfig
from uwdock.rl.env.task import (
    DockingTaskConfig,
    docking_errors,
    ds_visible,
    paper_success,
    paper_success_b,
    pegs_seated,
    yaw_of,
)

MODEL = "rl/models/error_model_clear_tank_480_ar1.json"
TASK = DockingTaskConfig()


def _poses(n: int, seed: int, near_dock: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Random DS poses on a floor and vehicle poses above them (half of them nearly docked)."""
    rng = np.random.default_rng(seed)
    T_ds = np.stack(
        [
            make_T(R_from_rpy(0, 0, rng.uniform(-3, 3)), [*rng.uniform(-2, 2, 2), 4.9])
            for _ in range(n)
        ]
    )
    T_body = []
    for i in range(n):
        if near_dock or i % 2:
            dT = make_T(R_from_rpy(*rng.normal(0, 0.02, 3)), rng.normal(0, 0.03, 3))
            T_body.append(T_ds[i] @ TASK.T_ds_target @ dT)
        else:
            rpy = rng.normal(0, 0.1, 3) + np.array([0.0, 0.0, rng.uniform(-3, 3)])
            T_body.append(make_T(R_from_rpy(*rpy), [*rng.uniform(-4, 4, 2), rng.uniform(1, 4.5)]))
    return np.stack(T_body), T_ds


def _looking_at_the_ds(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Poses of which a third are 1.5-3 m above their DS, looking at it (the camera sees it)."""
    T_body, T_ds = _poses(n, seed)
    rng = np.random.default_rng(seed + 100)
    for i in range(0, n, 3):
        up = make_T(
            R_from_rpy(0, 0, rng.uniform(-3, 3)), [*rng.normal(0, 0.3, 2), -rng.uniform(1.5, 3)]
        )
        T_body[i] = T_ds[i] @ up
    return T_body, T_ds


# --------------------------------------------------------------------------- the table


def _table() -> list[tuple[str, str]]:
    """``batch_parts``' table of twins: (batched name, scalar dotted name) per row."""
    row = re.compile(r"^:(?:func|class):`(\w+)`\s+:(?:func|class):`([\w.]+)`", re.M)
    return row.findall(batch_parts.__doc__ or "")


def test_every_twin_of_the_table_is_tested_here():
    """Every twin that ``batch_parts`` defines is a row of its table, and a test of this module
    calls both sides of every row."""
    rows = _table()
    assert len(rows) >= 10
    defined = {
        n
        for n in batch_parts.__all__
        if (n.endswith("_b") or n.startswith("Batch")) and n != "inv_T_b"  # calibration's
    }
    assert defined == {b for b, _ in rows}
    tree = ast.parse(Path(__file__).read_text(encoding="utf-8"))
    used: set[str] = set()
    for fn in tree.body:
        if (
            isinstance(fn, ast.FunctionDef)
            and fn.name.startswith("test_")
            and fn.name != ("test_every_twin_of_the_table_is_tested_here")
        ):
            used |= {n.id for n in ast.walk(fn) if isinstance(n, ast.Name)}
            used |= {n.attr for n in ast.walk(fn) if isinstance(n, ast.Attribute)}
    for batched, scalar in rows:
        assert batched in used, batched
        assert scalar.rsplit(".", 1)[-1] in used, scalar


# --------------------------------------------------------------------------- geometry, task


def test_yaw_equals_the_scalar_yaw():
    T_body, T_ds = _poses(200, 1)
    T = np.concatenate([T_body, T_ds])
    np.testing.assert_allclose(yaw_b(T), [yaw_of(t) for t in T], atol=1e-12)


def test_task_tests_equal_the_scalar_ones():
    T_body, T_ds = _poses(200, 0)
    e, psi = docking_errors_b(T_body, T_ds, TASK)
    vis = ds_visible_b(inv_T_b(T_body) @ T_ds, TASK)
    paper = paper_success_b(e, psi, vis, TASK)
    seated = pegs_seated_b(T_body, T_ds, TASK)
    assert 0 < seated.sum() < 200 and 0 < vis.sum() < 200 and paper.sum() > 0
    for i in range(200):
        e_s, psi_s = docking_errors(T_body[i], T_ds[i], TASK)
        np.testing.assert_allclose(e[i], e_s, atol=1e-12)
        assert psi[i] == pytest.approx(psi_s, abs=1e-12)
        v = ds_visible(np.linalg.inv(T_body[i]) @ T_ds[i], TASK)
        assert vis[i] == v
        assert paper[i] == paper_success(e_s, psi_s, v, TASK)  # one definition: a batch of one
        assert seated[i] == pegs_seated(T_body[i], T_ds[i], TASK)


def test_rotvec_and_error_application_match_scipy():
    rng = np.random.default_rng(4)
    rv = np.concatenate([rng.normal(0, 0.5, (50, 3)), np.zeros((1, 3))])
    T = make_T(R_from_rpy(0.1, 0.2, 0.3), [0.1, 0.2, 1.5])
    for i, R in enumerate(rotvec_to_R_b(rv)):
        np.testing.assert_allclose(
            R, apply_error(T, np.r_[0, 0, 0, rv[i]])[:3, :3] @ T[:3, :3].T, atol=1e-12
        )


# --------------------------------------------------------------------------- filter


def test_filter_equals_the_scalar_filter():
    cfg = EstimatorConfig(gate_sigma=3.0)
    rng = np.random.default_rng(2)
    n = 6
    scalars = [DSPoseFilter(cfg) for _ in range(n)]
    T0 = [make_T(R_from_rpy(0, 0, rng.uniform(-3, 3)), rng.normal(0, 2, 3)) for _ in range(n)]
    for f, T in zip(scalars, T0, strict=True):
        f.reset(T, rng)
    q = np.array([cfg.drift_xyz_m_per_sqrt_s] * 3 + [math.radians(cfg.drift_yaw_deg_per_sqrt_s)])
    batch = BatchFilter(n, cfg.fuse, cfg.gate_sigma, q**2)
    batch.x[:] = [f.x for f in scalars]
    batch.P[:] = [f.P for f in scalars]
    for step in range(40):
        batch.predict(0.2)
        for f in scalars:
            f.predict(0.2)
        if step % 5 == 0:  # a position fix for some
            mask = rng.random(n) < 0.6
            p = np.stack(T0)[:, :3, 3] + rng.normal(0, 0.3, (n, 3))
            sig = rng.uniform(0.1, 0.5, n)
            batch.update_position(mask, p, sig)
            for i in np.flatnonzero(mask):
                scalars[i].update_position(p[i], sig[i])
        mask = rng.random(n) < 0.5
        z = np.concatenate([np.stack(T0)[:, :3, 3], np.zeros((n, 1))], axis=1)
        z += rng.normal(0, 0.2, (n, 4)) * (1 + 20 * (rng.random((n, 1)) < 0.1))  # outliers
        z[:, 3] += [math.atan2(T[1, 0], T[0, 0]) for T in T0]
        R = np.stack([np.diag(rng.uniform(0.01, 0.1, 4)) for _ in range(n)])
        acc = batch.update(mask, z, R)
        for i in np.flatnonzero(mask):
            Tm = make_T(R_from_rpy(0, 0, z[i, 3]), z[i, :3])
            assert acc[i] == scalars[i].update(Tm, R[i])
        np.testing.assert_allclose(batch.x, [f.x for f in scalars], atol=1e-9)
        np.testing.assert_allclose(batch.P, [f.P for f in scalars], atol=1e-9)
    np.testing.assert_allclose(batch.T_world_ds(), [f.T_world_ds for f in scalars], atol=1e-9)


# --------------------------------------------------------------------------- reward


def test_reward_terms_equal_the_scalar_reward():
    cfg = RewardConfig(precision_gain=2.0, precision_yaw_scale_rad=0.5, angle_linear=1.0)
    actuated = np.array([1, 1, 1, 0, 1, 1], dtype=bool)
    scalar = DockingReward(cfg, actuated)
    rng = np.random.default_rng(3)
    n = 50
    e, psi = rng.normal(0, 1, (n, 3)), rng.uniform(-3, 3, n)
    a, prev = rng.uniform(-1, 1, (n, 6)), rng.uniform(-1, 1, (n, 6))
    col, docked, trunc = rng.random(n) < 0.3, rng.random(n) < 0.2, rng.random(n) < 0.2
    docked &= ~trunc
    terms = reward_terms_b(
        cfg, scalar.weights, scalar.smooth_mask, e, psi, a, prev, col, docked, trunc
    )
    for i in range(n):
        ref = scalar(e[i], psi[i], a[i], prev[i], col[i], docked[i], trunc[i])
        for k, v in ref.items():
            assert terms[k][i] == pytest.approx(v, rel=1e-12, abs=1e-12), k


def test_stall_terms_equal_the_scalar_reward_step_by_step():
    """r_stall keeps a memory (the error at the step before): the batched twin's, in place,
    pays what the scalar reward pays over a sequence of steps of one env."""
    cfg = RewardConfig(stall_penalty=2.0)
    full, soft = np.array([1.0, 0, 0, 0, 0, 0]), np.array([0.5, 0, 0, 0, 0, 0])
    steps = [(0.60, full), (0.60, full), (0.595, full), (0.50, full), (0.50, soft), (0.20, full)]
    scalar = DockingReward(cfg)
    prev = np.full(1, np.nan)
    paid = []
    for x, a in steps:
        e = np.array([x, 0.0, 1.0])
        ref = scalar(e, 0.0, a, a, False, False, False)["stall"]
        terms = reward_terms_b(
            cfg, scalar.weights, scalar.smooth_mask, e[None], np.zeros(1), a[None], a[None],
            np.zeros(1, bool), np.zeros(1, bool), np.zeros(1, bool), prev,
        )  # fmt: skip
        assert float(terms["stall"][0]) == ref
        paid.append(ref)
    assert paid == [0.0, -2.0, -2.0, 0.0, 0.0, 0.0]


# --------------------------------------------------------------------------- observation


@pytest.mark.parametrize(
    "settings",
    [
        {"obs_last_action": True},
        {"obs_contact": True},
        {"obs_contact": True, "obs_fine_error": True, "obs_uncertainty": True},
    ],
)
def test_observation_frames_equal_the_scalar_frames(settings):
    cfg = EnvConfig(**settings)
    T_body, T_ds = _poses(20, 5)
    rng = np.random.default_rng(6)
    f = DSPoseFilter(cfg.estimator)
    vel, acc = rng.normal(0, 0.3, (20, 3)), rng.normal(0, 2, (20, 3))
    w, prev, det = rng.normal(0, 0.1, 20), rng.uniform(-1, 1, (20, 6)), rng.random(20) < 0.5
    contact = np.stack([rng.uniform(0, 1, 20), rng.uniform(0, 1, 20)], axis=1)
    pair = cfg.obs_contact
    for i in range(20):
        f.reset(T_ds[i], rng)
        sig = math.sqrt(0.5 * (f.P[0, 0] + f.P[1, 1]))
        ref = observation_frame(
            cfg, T_body[i], f, vel[i], w[i], acc[i], prev[i], bool(det[i]),
            contact[i] if pair else None,
        )  # fmt: skip
        out = observation_frames_b(
            cfg, T_body[i : i + 1], f.T_world_ds[None], np.array([sig]), vel[i : i + 1],
            w[i : i + 1], acc[i : i + 1], prev[i : i + 1], det[i : i + 1],
            contact[i : i + 1] if pair else None,
        )  # fmt: skip
        np.testing.assert_allclose(out[0], ref, atol=1e-6)


# --------------------------------------------------------------------------- sources


class _Draws:
    """A generator that gives a source the draws the batch takes from its arrays: uniforms
    ``u`` (detection, outlier, which outlier sample) and standard normals ``w``."""

    def __init__(self, u: np.ndarray, w: np.ndarray) -> None:
        self._u = list(u[:2])
        self._pick = float(u[2])
        self._w = list(np.asarray(w, dtype=np.float64).reshape(-1, 3))

    def random(self) -> float:
        return self._u.pop(0)

    def integers(self, n: int) -> int:
        return min(int(self._pick * n), n - 1)  # the batch's choice of an outlier sample

    def standard_normal(self, size: int) -> np.ndarray:
        return np.concatenate([self._w.pop(0) for _ in range(size // 3)])

    def normal(self, loc: float, scale: float, size: int) -> np.ndarray:
        return loc + scale * self.standard_normal(size)


def test_error_model_counts_in_view_as_the_scalar_count():
    model = load_error_model(MODEL)
    T_body, T_ds = _looking_at_the_ds(60, 7)
    b = BatchErrorModel(model, "clear_tank", temporal=False, n=60)
    T_cam_ds = inv_T_b(T_body @ model.T_body_cam) @ T_ds
    counts = b.count_in_view(T_cam_ds)
    assert counts.max() >= 3
    for i in range(60):
        assert counts[i] == count_in_view(model.camera, T_cam_ds[i], model.corners_ds)


@pytest.mark.parametrize("temporal", [False, True])
def test_error_model_measures_as_the_scalar_source_on_the_same_draws(temporal):
    """Step by step, the batch's detections, outliers, AR(1) memory and measured poses are the
    scalar source's, given the same draws (the batch takes a fixed number per env and step, the
    scalar source only those it uses: here it reads them from the batch's arrays)."""
    model = load_error_model(MODEL)
    n = 45
    T_body, T_ds = _looking_at_the_ds(n, 11)
    batch = BatchErrorModel(model, "clear_tank", temporal=temporal, n=n)
    scalars = [ErrorModelSource(model, TASK, "clear_tank", temporal=temporal) for _ in range(n)]
    rng = np.random.default_rng(12)
    seen = {"detected": 0, "outlier": 0}
    for step in range(12):
        t = 0.2 * (step + 1) + (0.2 if step == 6 else 0.0)  # a skipped step once
        drift = make_T(R_from_rpy(0, 0, 0.02 * step), [0.01 * step, 0.0, 0.0])
        body = T_body @ drift
        u, w = rng.random((n, 3)), rng.standard_normal((n, 6))
        det, T_meas, cov = batch.measure(body, T_ds, np.full(n, t), u, w)
        for i, src in enumerate(scalars):
            src.rng = _Draws(u[i], w[i])
            m = src.measure(StepContext(body[i], T_ds[i], t))
            assert det[i] == (m is not None), (step, i)
            if m is None:
                continue
            seen["detected"] += 1
            np.testing.assert_allclose(T_meas[i], m.T_world_ds, atol=1e-10, err_msg=f"{step} {i}")
            np.testing.assert_allclose(cov[i], m.cov_xyzyaw, atol=1e-12)
    assert seen["detected"] > 50


def test_error_model_samples_as_the_table_says():
    """One pose, many draws: the batch's detection rate and error moments are the table's."""
    model = load_error_model(MODEL)
    T_body, T_ds = _looking_at_the_ds(60, 7)
    T_world_cam = T_body @ model.T_body_cam
    T_cam_ds = inv_T_b(T_world_cam) @ T_ds
    counts = BatchErrorModel(model, "clear_tank", temporal=False, n=60).count_in_view(T_cam_ds)
    n = 4000
    i = int(np.flatnonzero(counts >= 3)[0])
    b = BatchErrorModel(model, "clear_tank", temporal=False, n=n)
    t = b.table = dict(b.table, p_out=np.zeros_like(b.table["p_out"]))
    rng = np.random.default_rng(8)
    body, ds = np.repeat(T_body[i : i + 1], n, 0), np.repeat(T_ds[i : i + 1], n, 0)
    det, T_meas, _ = b.measure(
        body, ds, np.full(n, 1.0), rng.random((n, 3)), rng.standard_normal((n, 6))
    )
    k = model.range_bin(np.linalg.norm(T_cam_ds[i, :3, 3]))
    p = t["p"][k, 3]
    assert abs(det.mean() - p) < 4 * math.sqrt(p * (1 - p) / n) + 1e-9
    cam_inv = np.linalg.inv(T_world_cam[i])
    errs = np.array([pose_error(cam_inv @ T_meas[j], T_cam_ds[i]) for j in np.flatnonzero(det)])
    sem = np.sqrt(np.diag(t["cov"][k]) / len(errs))
    assert np.all(np.abs(errs.mean(0) - t["bias"][k]) < 4 * sem + 1e-9)
    np.testing.assert_allclose(np.cov(errs.T), t["cov"][k], atol=0.1 * np.abs(t["cov"][k]).max())


def test_proxy_measures_as_the_scalar_source_on_the_same_draws():
    T_body, T_ds = _poses(80, 13)
    rng = np.random.default_rng(14)
    w = rng.standard_normal((80, 6))
    vis, T_meas, cov = proxy_measure_b(T_body, T_ds, TASK, w)
    assert 0 < vis.sum() < 80
    src = ProxySource(TASK)
    for i in range(80):
        src.reset(_Draws(np.zeros(3), w[i]))
        m = src.measure(StepContext(T_body[i], T_ds[i], 0.2))
        assert vis[i] == m.detected
        np.testing.assert_allclose(T_meas[i], m.T_world_ds, atol=1e-12)
        np.testing.assert_allclose(cov[i], m.cov_xyzyaw, atol=1e-15)
