"""The env a command runs a policy in, and where each of its settings came from.

``rl eval``, ``rl episode`` and ``rl export`` run (or describe) a policy in the env it was
trained in unless told otherwise: the settings are layered, each layer overriding the ones
before it,

1. the command's own defaults (e.g. ``rl eval``'s ``terminate_on = "strict"``),
2. the policy's training env (the ``[train.env]`` table of its run folder's ``config.toml``, or
   the ``env`` of the ``.json`` beside an exported ``.onnx``; ``--env-from`` names another
   policy folder whose settings to take, e.g. to run the PID under a policy's settings),
3. the ``--config`` file (over the bases it ``extends``, each its own layer:
   ``dockcore.config.config_layers``),
4. the command's flags (:class:`EnvFlags`: typed at the edge, presets as objects),

then the policy's interface (observation layout, action scaling: what its weights were made
for, not a setting a layer may change),

and the command prints one line naming the settings that decide a result (USBL and navigation
presets, water, camera width, termination, observation source) and the layer each came from
(:meth:`ResolvedEnv.line`), so an evaluation can not silently run another sensor model than the
policy was trained with.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from uwdock.dockcore.config import config_layers, field_path, from_dict, has_path, merge, to_dict
from uwdock.rl.env.config import EnvConfig, ObsSourceName
from uwdock.rl.policy.policy_io import POLICY_INTERFACE_FIELDS, policy_train_source
from uwdock.sim.navigation import NavConfig
from uwdock.sim.usbl import UsblConfig
from uwdock.sim.water import Water


@dataclass(frozen=True)
class Reported:
    """A setting :meth:`ResolvedEnv.line` reports: its short name and the :class:`EnvConfig`
    field it is, as a typed selector (``lambda c: c.usbl.preset``; :attr:`path` is checked
    against the config when the module loads)."""

    name: str
    select: Callable[[EnvConfig], Any]
    path: tuple[str, ...] = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", field_path(EnvConfig, self.select))


#: The settings :meth:`ResolvedEnv.line` reports, in its order.
REPORTED = (
    Reported("usbl", lambda c: c.usbl.preset),
    Reported("nav", lambda c: c.nav.preset),
    Reported("water", lambda c: c.world.water_preset),
    Reported("camera_width_px", lambda c: c.world.camera_width_px),
    Reported("terminate_on", lambda c: c.terminate_on),
    Reported("obs", lambda c: c.obs_source),
    Reported("error_model", lambda c: c.error_model_path),
    Reported("episode_s", lambda c: c.episode_s),
)

#: ``[train.env]`` fields a command never takes from a policy's training env: the observation
#: source is the command's choice (``rl eval`` measures the camera in the loop by default,
#: whatever source a policy trained on).
NOT_FROM_POLICY = (field_path(EnvConfig, lambda c: c.obs_source),)


@dataclass(frozen=True)
class EnvFlags:
    """What a command's flags say about the env, typed where they are parsed (None: not given).

    Presets are objects here, not names: ``usbl`` is a :class:`UsblConfig` (the preset with no
    field of its own: ``--usbl`` names a whole model, so the training env's fields of its model
    do not apply), ``nav`` a :class:`NavConfig` likewise, ``water`` a :class:`Water` (a water
    file already read and checked).
    """

    obs_source: ObsSourceName | None = None
    error_model_path: Path | None = None
    terminate_on: Literal["paper", "strict"] | None = None
    episode_s: float | None = None
    usbl: UsblConfig | None = None
    nav: NavConfig | None = None
    water: Water | None = None
    camera_width_px: int | None = None

    def layer(self) -> dict[str, Any]:
        """The flags given, as a layer of :class:`EnvConfig` data."""
        data: dict[str, Any] = {}
        for name in ("obs_source", "terminate_on", "episode_s"):
            if (value := getattr(self, name)) is not None:
                data[name] = value
        if self.error_model_path is not None:
            data["error_model_path"] = str(self.error_model_path)
        for name in ("usbl", "nav"):
            if (model := getattr(self, name)) is not None:
                data[name] = {k: v for k, v in to_dict(model).items() if v is not None}
        world: dict[str, Any] = {}
        if self.water is not None:
            world["water_preset"] = self.water.spec
        if self.camera_width_px is not None:
            world["camera_width_px"] = self.camera_width_px
        if world:
            data["world"] = world
        return data


@dataclass(frozen=True)
class ResolvedEnv:
    """An env config and the layer each reported setting came from.

    Attributes:
        cfg: the env config the command runs.
        sources: :attr:`Reported.path` -> the label of the layer that set it (``"default"``,
            ``"policy config"``, ``"--config"``, ``"--config base <path>"`` for a value set by
            a file the ``--config`` file extends, ``"flag"``).
        policy_config: the file the ``"policy"`` layer was read from (a run's ``config.toml``
            or an exported policy's ``.json``); None without one.
    """

    cfg: EnvConfig
    sources: Mapping[tuple[str, ...], str]
    policy_config: str | None = None

    def settings(self) -> dict[str, dict[str, Any]]:
        """``{short name: {"value": v, "from": layer}}`` of the reported settings (JSON-ready)."""
        out: dict[str, dict[str, Any]] = {}
        for r in REPORTED:
            if r.name == "error_model" and self.cfg.obs_source != "error-model":
                continue  # not read by the other sources
            out[r.name] = {"value": r.select(self.cfg), "from": self.sources.get(r.path, "default")}
        return out

    def line(self, command: str) -> str:
        """One line: ``<command> env: usbl evologics-s2cr (policy ...), water ... (flag), ...``."""
        parts = []
        for name, s in self.settings().items():
            value = s["value"]
            shown = f"{value:g}" if isinstance(value, float) else str(value)
            parts.append(f"{name} {shown} ({s['from']})")
        origin = f" [policy: {self.policy_config}]" if self.policy_config else ""
        return f"{command} env{origin}: " + ", ".join(parts)


def policy_env_layer(policy: str) -> tuple[dict[str, Any], str | None]:
    """The training env of ``policy`` (a run folder, ``policy.zip``, ``.onnx`` or "pid") in the
    current layout, without :data:`NOT_FROM_POLICY`, and the file it was read from; ``({},
    None)`` for "pid" or a policy without a run config."""
    env, origin = policy_train_source(policy)
    if origin is None:
        return {}, None
    skipped = {path[0] for path in NOT_FROM_POLICY}
    return {k: v for k, v in env.items() if k not in skipped}, str(origin)


def resolve_env(
    layers: Sequence[tuple[str, Mapping[str, Any]]], policy_config: str | None = None
) -> ResolvedEnv:
    """Merge ``(label, EnvConfig data in the current layout)`` layers, later over earlier, into
    an :class:`EnvConfig` and record which layer set each reported field (a field no layer sets:
    "default", the EnvConfig default).

    Raises:
        ConfigError (a DockError): a layer's key unknown to EnvConfig or a value out of its
            domain, named by its key.
    """
    data: dict[str, Any] = {}
    sources: dict[tuple[str, ...], str] = {}
    for label, layer in layers:
        data = merge(data, layer)
        for r in REPORTED:
            if has_path(layer, r.path):
                sources[r.path] = label
    return ResolvedEnv(from_dict(EnvConfig, data), sources, policy_config)


def policy_training_env(policy: str) -> ResolvedEnv | None:
    """The whole env ``policy`` was trained in (its ``[train.env]``, observation source
    included, every other field at its EnvConfig default), as :func:`resolve_env` gives it; None
    for "pid" or a policy without a run config (or an ``.onnx`` without its ``.json``)."""
    env, origin = policy_train_source(policy)
    if origin is None:
        return None
    return resolve_env([("policy config", env)], policy_config=str(origin))


def command_env(
    policy: str,
    env_from: Path | None = None,
    config_path: Path | None = None,
    flags: EnvFlags | None = None,
    defaults: Mapping[str, Any] | None = None,
) -> ResolvedEnv:
    """The env a command runs ``policy`` in (module docstring): ``defaults``, the training env of
    ``env_from`` (else of ``policy``), the ``--config`` file's ``[env]`` (its bases first), the
    ``flags``, then ``policy``'s own interface fields (read from the same file, once)."""
    flags = flags or EnvFlags()
    source = str(env_from) if env_from is not None else policy
    layer, origin = policy_env_layer(source)
    given = flags.layer()
    for model in ("usbl", "nav"):  # --usbl/--nav name a whole model: the policy's own fields
        if model in given:  # of it do not apply
            layer.pop(model, None)
    layers = [("default", dict(defaults or {})), ("policy config", layer)]
    if config_path is not None:
        for file in config_layers(config_path, section="env", cls=EnvConfig):
            label = f"--config base {_shown(file.path)}" if file.base else "--config"
            layers.append((label, file.data))
    layers.append(("flag", given))
    own = layer if env_from is None else policy_train_source(policy)[0]
    interface = {k: own[k] for k in POLICY_INTERFACE_FIELDS if k in own}
    if interface:
        layers.append(("policy interface", interface))
    return resolve_env(layers, policy_config=origin)


def _shown(path: Path) -> str:
    """``path`` relative to the current folder when inside it, else absolute."""
    full = path.absolute()
    try:
        return str(full.relative_to(Path.cwd()))
    except ValueError:
        return str(full)
