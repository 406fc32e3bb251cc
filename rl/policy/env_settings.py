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
4. the command's flags,

and the command prints one line naming the settings that decide a result (USBL and navigation
presets, water, camera width, termination, observation source) and the layer each came from
(:meth:`ResolvedEnv.line`), so an evaluation can not silently run another sensor model than the
policy was trained with.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from uwdock.dockcore.config import config_layers, from_dict, lift_moved_keys, merge
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.policy.policy_io import policy_train_env, policy_train_settings

#: The settings :meth:`ResolvedEnv.line` reports: (dotted EnvConfig key, short name).
REPORTED = (
    ("usbl.preset", "usbl"),
    ("nav.preset", "nav"),
    ("world.water_preset", "water"),
    ("world.camera_width_px", "width_px"),
    ("terminate_on", "terminate_on"),
    ("obs_source", "obs"),
    ("error_model_path", "error_model"),
    ("episode_s", "episode_s"),
)

#: ``[train.env]`` keys a command never takes from a policy's training env: the observation
#: source is the command's choice (``rl eval`` measures the camera in the loop by default,
#: whatever source a policy trained on).
NOT_FROM_POLICY = ("obs_source",)


@dataclass(frozen=True)
class ResolvedEnv:
    """An env config and the layer each reported setting came from.

    Attributes:
        cfg: the env config the command runs.
        sources: dotted key (:data:`REPORTED`) -> the label of the layer that set it
            (``"default"``, ``"policy config"``, ``"--config"``, ``"--config base <path>"``
            for a value set by a file the ``--config`` file extends, ``"flag"``).
        policy_config: the file the ``"policy"`` layer was read from (a run's ``config.toml``
            or an exported policy's ``.json``); None without one.
    """

    cfg: EnvConfig
    sources: Mapping[str, str]
    policy_config: str | None = None

    def value(self, key: str) -> Any:
        """The value of a dotted key of :attr:`cfg` (e.g. ``"world.camera_width_px"``)."""
        obj: Any = self.cfg
        for part in key.split("."):
            obj = getattr(obj, part)
        return obj

    def settings(self) -> dict[str, dict[str, Any]]:
        """``{short name: {"value": v, "from": layer}}`` of the reported settings (JSON-ready)."""
        out: dict[str, dict[str, Any]] = {}
        for key, name in REPORTED:
            if key == "error_model_path" and self.cfg.obs_source != "error-model":
                continue  # not read by the other sources
            out[name] = {"value": self.value(key), "from": self.sources.get(key, "default")}
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


def _has(data: Mapping[str, Any], key: str) -> bool:
    obj: Any = data
    for part in key.split("."):
        if not isinstance(obj, Mapping) or part not in obj:
            return False
        obj = obj[part]
    return True


def policy_env_layer(policy: str) -> tuple[dict[str, Any], str | None]:
    """The training env of ``policy`` (a run folder, ``policy.zip``, ``.onnx`` or "pid") in the
    current layout, without :data:`NOT_FROM_POLICY`, and the file it was read from; ``({},
    None)`` for "pid" or a policy without a run config."""
    if policy == "pid":
        return {}, None
    p = Path(policy)
    if p.suffix == ".onnx":
        origin = p.with_suffix(".json")
    else:
        origin = policy_train_settings(p)[1]
    if origin is None or not origin.is_file():
        return {}, None
    env = lift_moved_keys(EnvConfig, policy_train_env(policy))
    return {k: v for k, v in env.items() if k not in NOT_FROM_POLICY}, str(origin)


def resolve_env(
    layers: Sequence[tuple[str, Mapping[str, Any]]], policy_config: str | None = None
) -> ResolvedEnv:
    """Merge ``(label, EnvConfig data)`` layers, later over earlier, into an :class:`EnvConfig`
    and record which layer set each reported key (a key no layer sets: "default", the
    EnvConfig default).

    Raises:
        ConfigError (a DockError): a layer's key unknown to EnvConfig or a value out of its
            domain, named by its key.
    """
    data: dict[str, Any] = {}
    sources: dict[str, str] = {}
    for label, layer in layers:
        lifted = lift_moved_keys(EnvConfig, layer)
        data = merge(data, lifted)
        for key, _ in REPORTED:
            if _has(lifted, key):
                sources[key] = label
    return ResolvedEnv(from_dict(EnvConfig, data), sources, policy_config)


def policy_training_env(policy: str) -> ResolvedEnv | None:
    """The whole env ``policy`` was trained in (its ``[train.env]``, observation source
    included, every other field at its EnvConfig default), as :func:`resolve_env` gives it; None
    for "pid" or a policy without a run config (or an ``.onnx`` without its ``.json``)."""
    origin = policy_env_layer(policy)[1]
    if origin is None:
        return None
    env = lift_moved_keys(EnvConfig, policy_train_env(policy))
    return resolve_env([("policy config", env)], policy_config=origin)


def command_env(
    policy: str,
    env_from: Path | None,
    config_path: Path | None,
    flags: dict,
    defaults: dict,
):
    """The env of a command (module docstring): ``defaults``, the training env of ``env_from``
    (else of ``policy``), the ``--config`` file's ``[env]``, then ``flags`` (None values and
    empty tables: not given)."""
    source = str(env_from) if env_from is not None else policy
    layer, origin = policy_env_layer(source)
    given = {k: v for k, v in flags.items() if v is not None and v != {}}
    for model in ("usbl", "nav"):  # --usbl/--nav name a whole model: the policy's own fields
        if model in given:  # of it do not apply
            layer.pop(model, None)
    layers = [("default", defaults), ("policy config", layer)]
    if config_path is not None:
        for file in config_layers(config_path, section="env"):
            label = f"--config base {_shown(file.path)}" if file.base else "--config"
            layers.append((label, file.data))
    layers.append(("flag", given))
    return resolve_env(layers, policy_config=origin)


def _shown(path: Path) -> str:
    """``path`` relative to the current folder when inside it, else absolute."""
    full = path.absolute()
    try:
        return str(full.relative_to(Path.cwd()))
    except ValueError:
        return str(full)
