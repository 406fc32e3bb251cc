"""Thruster geometry, allocation, saturation, thrust curve and first-order response."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from uwdock.dockcore.config import ConfigError, from_dict, to_dict
from uwdock.sim.thrusters import (
    DEFAULT_THRUSTERS,
    ThrusterArray,
    ThrusterArrayConfig,
    ThrusterConfig,
    ThrusterRandomisation,
)

ACTUATED = [0, 1, 2, 4, 5]  # surge, sway, heave, pitch, yaw (roll is a by-product)
SWAY_LEVER_M = 0.021  # the sway thruster sits 21 mm above the origin


@pytest.fixture(scope="module")
def arr() -> ThrusterArray:
    return ThrusterArray()


def test_allocation_matrix_from_geometry(arr):
    assert arr.names == ("SurgePort", "SurgeStarboard", "Sway", "HeaveBow", "HeaveStern")
    # column = [axis, r x axis]
    np.testing.assert_allclose(arr.B[:, 0], [1, 0, 0, 0, -0.021, 0.259])
    np.testing.assert_allclose(arr.B[:, 2], [0, 1, 0, 0.021, 0, -0.063])
    np.testing.assert_allclose(arr.B[:, 3], [0, 0, 1, 0, -0.535, 0])
    np.testing.assert_allclose(arr.B[:, 4], [0, 0, 1, 0, 0.583, 0])


def test_allocation_reproduces_wrench_inside_limits(arr):
    rng = np.random.default_rng(0)
    for _ in range(200):
        wrench = rng.uniform(-1, 1, 6) * [120, 60, 110, 0, 60, 30]
        thrust = arr.allocate(wrench)
        assert np.all(np.abs(thrust) <= arr.max_thrust_n)
        produced = arr.wrench_from_thrust(thrust)
        np.testing.assert_allclose(produced[ACTUATED], wrench[ACTUATED], atol=1e-6)
        assert produced[3] == pytest.approx(SWAY_LEVER_M * wrench[1], abs=1e-9)


def test_saturation_scales_uniformly_and_keeps_direction(arr):
    rng = np.random.default_rng(1)
    for _ in range(100):
        wrench = rng.uniform(-1, 1, 6) * [1000, 500, 1000, 0, 400, 300]
        thrust = arr.allocate(wrench)
        peak = np.max(np.abs(thrust) / arr.max_thrust_n)
        assert peak == pytest.approx(1.0, abs=1e-12)  # the worst thruster sits at its limit
        produced = arr.wrench_from_thrust(thrust)[ACTUATED]
        scale = produced @ wrench[ACTUATED] / (wrench[ACTUATED] @ wrench[ACTUATED])
        assert 0 < scale < 1
        np.testing.assert_allclose(produced, scale * wrench[ACTUATED], atol=1e-6)
        np.testing.assert_allclose(thrust, scale * arr.allocate_unsaturated(wrench), atol=1e-9)


def test_max_wrench_matches_geometry(arr):
    mw = arr.max_wrench()
    assert mw[0] == pytest.approx(280.0)  # two surge thrusters
    assert mw[1] == pytest.approx(140.0)  # one sway thruster
    assert mw[3] == 0.0  # roll not actuated
    # heave: bow and stern levers differ, pure heave needs 0.583 / 1.118 of it on the bow
    assert mw[2] == pytest.approx(140.0 * (0.535 + 0.583) / 0.583)
    assert mw[4] == pytest.approx(140.0 * (0.535 + 0.583))  # pitch: heave pair in opposition
    assert mw[5] == pytest.approx(140.0 * 2 * 0.259)  # yaw: surge pair in opposition
    # each is exactly the unsaturated limit
    for j in ACTUATED:
        e = np.zeros(6)
        e[j] = mw[j]
        assert np.max(np.abs(arr.allocate_unsaturated(e)) / arr.max_thrust_n) == pytest.approx(1)


def test_thrust_curve_and_inverse(arr):
    s = np.array([-1.0, -0.5, 0.0, 0.5, 1.0])
    np.testing.assert_allclose(arr.thrust_from_setpoint(s), [-140, -35, 0, 35, 140])
    rng = np.random.default_rng(2)
    t = rng.uniform(-140, 140, 5)
    np.testing.assert_allclose(arr.thrust_from_setpoint(arr.setpoint_from_thrust(t)), t)
    np.testing.assert_allclose(arr.setpoint_from_thrust([500, -500, 0, 0, 0]), [1, -1, 0, 0, 0])
    np.testing.assert_allclose(arr.thrust_from_setpoint([2, 0, 0, 0, 0])[0], 140)


def test_first_order_response_63_percent_at_tau(arr):
    dt = 1.0 / 300.0
    n = round(0.2 / dt)
    out = arr.response(np.zeros(5), np.full(5, 100.0), dt, n)
    assert out.shape == (n, 5)
    np.testing.assert_allclose(out[-1], 100.0 * (1 - math.exp(-1)), rtol=1e-12)
    assert np.all(np.diff(out[:, 0]) > 0)  # monotone, no overshoot
    # exact discretisation: one long step equals many short ones
    np.testing.assert_allclose(arr.response(np.zeros(5), np.full(5, 100.0), 0.2, 1)[0], out[-1])
    instant = ThrusterArray(
        replace(
            ThrusterArrayConfig(),
            thrusters=tuple(replace(t, time_constant_s=0.0) for t in DEFAULT_THRUSTERS),
        )
    )
    np.testing.assert_allclose(instant.response(np.zeros(5), np.ones(5), dt, 3), np.ones((3, 5)))


def test_placement_randomisation_within_ranges_and_seeded():
    rnd = ThrusterRandomisation(position_m=0.02, axis_deg=3.0, max_thrust_rel=0.1)
    base = ThrusterArrayConfig()
    a = rnd.sample(base, np.random.default_rng(4))
    assert a == rnd.sample(base, np.random.default_rng(4))
    for t0, t1 in zip(base.thrusters, a.thrusters, strict=True):
        assert np.max(np.abs(np.subtract(t1.position_m, t0.position_m))) <= 0.02
        assert np.linalg.norm(t1.axis) == pytest.approx(1.0)
        tilt = math.degrees(math.acos(min(1.0, float(np.dot(t1.axis, t0.axis)))))
        assert tilt <= 3.0 + 1e-9
        assert abs(t1.max_thrust_n / t0.max_thrust_n - 1) <= 0.1
    # a perturbed array still allocates exactly on the actuated axes
    arr = ThrusterArray(a)
    wrench = np.array([80.0, 30.0, -60.0, 0.0, 20.0, 10.0])
    produced = arr.wrench_from_thrust(arr.allocate(wrench))
    np.testing.assert_allclose(produced[ACTUATED], wrench[ACTUATED], atol=1e-6)


def test_config_round_trip_and_validation():
    cfg = ThrusterArrayConfig()
    assert from_dict(ThrusterArrayConfig, to_dict(cfg)) == cfg
    with pytest.raises(ConfigError, match="max_thrust_n"):
        from_dict(
            ThrusterArrayConfig,
            {"thrusters": [{"name": "a", "position_m": [0, 0, 0], "axis": [1, 0, 0],
                            "max_thrust_n": -1.0}]},
        )  # fmt: skip
    with pytest.raises(ValueError, match="axis"):
        ThrusterConfig("bad", (0, 0, 0), (0, 0, 0)).validate()
