"""Property tests: every field of every config dataclass declares its domain, and the loader
refuses any value outside it with one ConfigError naming the key (NaN, infinity, out of range,
wrong type), before anything else runs."""

from __future__ import annotations

import dataclasses
import importlib
import pkgutil

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.hostile import hostile, inside, leaves, nested_classes, set_path
from uwdock.dockcore.config import from_dict, to_dict
from uwdock.dockcore.errors import ConfigError

PACKAGES = tuple(
    f"uwdock.{p}"
    for p in ("dockcore", "markers", "ros", "perception", "calibration", "sim", "datasets", "rl")
)


def _roots() -> list[type]:
    """The configs a user loads from TOML (``--config``) or that commands build from flags."""
    from uwdock.calibration.intrinsics import IntrinsicsConfig
    from uwdock.calibration.stereo import StereoConfig
    from uwdock.datasets.synth import SynthConfig
    from uwdock.datasets.tank_report import TankReportConfig
    from uwdock.datasets.water_fit import FitWaterConfig
    from uwdock.dockcore.pool import PoolConfig
    from uwdock.markers.config import MarkerConfig
    from uwdock.perception.evaluate import PerceptionConfig
    from uwdock.rl.deploy.config import NodeConfig
    from uwdock.rl.env.error_model import ErrorModelConfig
    from uwdock.rl.evaluate.episode_video import EpisodeVideoConfig
    from uwdock.rl.policy.baselines import PIDConfig
    from uwdock.rl.train.sweep import SweepConfig
    from uwdock.rl.train.training import TrainConfig
    from uwdock.sim.docking_station import DockingStationConfig
    from uwdock.sim.water import WaterConfig
    from uwdock.sim.world_config import WorldConfig

    return [
        MarkerConfig,
        IntrinsicsConfig,
        StereoConfig,
        PerceptionConfig,
        SynthConfig,
        TankReportConfig,
        FitWaterConfig,
        PoolConfig,
        SweepConfig,
        TrainConfig,
        ErrorModelConfig,
        EpisodeVideoConfig,
        PIDConfig,
        WaterConfig,
        DockingStationConfig,
        WorldConfig,
        NodeConfig,
    ]


ROOTS = _roots()
LEAVES = {root: leaves(root) for root in ROOTS}
ALL = [(root, leaf) for root in ROOTS for leaf in LEAVES[root]]


def _config_like_classes() -> set[type]:
    out = set()
    for pkg in PACKAGES:
        mod = importlib.import_module(pkg)
        for info in pkgutil.walk_packages(mod.__path__, f"{pkg}."):
            m = importlib.import_module(info.name)
            for obj in vars(m).values():
                if (
                    isinstance(obj, type)
                    and dataclasses.is_dataclass(obj)
                    and obj.__module__ == m.__name__
                    and obj.__name__.endswith(("Config", "Randomisation"))
                ):
                    out.add(obj)
    return out


def test_every_config_class_is_reached_from_a_root():
    reached = set().union(*(nested_classes(r) for r in ROOTS))
    missing = sorted(c.__qualname__ for c in _config_like_classes() - reached)
    assert not missing, f"config classes no property test reaches: {missing}"


def test_every_numeric_field_declares_its_domain():
    undeclared = sorted({leaf.owner for _, leaf in ALL if leaf.numeric and not leaf.meta})
    assert not undeclared, f"numeric fields without a declared domain: {undeclared}"


def test_defaults_are_inside_their_domains():
    for root in ROOTS:
        assert from_dict(root, to_dict(root())) == root()


_SETTINGS = settings(
    max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True
)


@_SETTINGS
@given(st.data())
def test_hostile_values_are_refused_naming_the_key(data):
    root, leaf = data.draw(st.sampled_from(ALL), label="field")
    value = data.draw(hostile(leaf), label="value")
    cfg = set_path(to_dict(root()), leaf.path, value)
    with pytest.raises(ConfigError) as err:
        from_dict(root, cfg)
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith(f"{leaf.key}:") or f"'{leaf.key}'" in message, message


@_SETTINGS
@given(st.data())
def test_values_inside_the_domain_load_or_fail_one_line(data):
    root, leaf = data.draw(st.sampled_from(ALL), label="field")
    value = data.draw(inside(leaf), label="value")
    cfg = set_path(to_dict(root()), leaf.path, value)
    try:
        from_dict(root, cfg)
    except ConfigError as err:
        assert "\n" not in str(err)
