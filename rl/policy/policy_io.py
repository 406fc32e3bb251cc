"""Policies on disk: loading a policy folder (PPO/SAC with its observation normalisation, as
data: :mod:`rl.policy.policy_format`) or an exported ``.onnx``, the interface of the env a policy
was trained in, and the controller that ``rl eval``, the deployment runner and training's
evaluations drive.

The bottom of ``rl`` above the env: evaluation, the report writer, export and training import
it; it imports none of them.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from uwdock.dockcore.config import ROOT as CHECKOUT
from uwdock.dockcore.config import current_layout, read_toml
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import check_regular_file
from uwdock.rl.env.config import EnvConfig, with_input_files
from uwdock.rl.env.observation import observation_size
from uwdock.rl.policy.baselines import PIDController
from uwdock.rl.policy.policy_format import MODEL, WEIGHTS, legacy_refusal, read_policy

#: EnvConfig fields that define a policy's interface (observation layout, action scaling).
POLICY_INTERFACE_FIELDS = (
    "obs_last_action",
    "obs_uncertainty",
    "obs_contact",
    "obs_fine_error",
    "obs_frames",
    "obs_privileged",
    "wrench_limits",
    "wrench_scale",
    "control_hz",
)


#: the files a training env names (key paths in ``[train.env]``)
_FILE_KEYS = (
    ("error_model_path",),
    ("world", "marker_set_path"),
    ("world", "camera_file"),
    ("world", "water_preset"),
)


def _beside(value: str, folder: Path) -> str:
    """A relative file name of a policy's config, resolved where the policy is: in its folder,
    else in the nearest folder above it that holds it (a run inside a checkout names files from
    the checkout's root), else in this toolkit's own checkout (a recipe's policy names the
    data it trained on from there, wherever its folder is); as given (relative to the current
    folder) when none does."""
    p = Path(value)
    if p.is_absolute() or (len(p.parts) == 1 and p.suffix == ""):  # a preset's name
        return value
    for base in (folder, *folder.parents, CHECKOUT):
        if (base / p).is_file():
            return str(base / p)
    return value


def named_from_checkout(cfg: EnvConfig) -> EnvConfig:
    """``cfg`` with its input files inside this toolkit's checkout named from its root (what
    :func:`_beside` finds again in any checkout), the others as they are: what a file written
    for another machine (an export's sidecar) records."""

    def name(p: str) -> str:
        path = Path(p)
        return path.relative_to(CHECKOUT).as_posix() if path.is_relative_to(CHECKOUT) else p

    return with_input_files(cfg, name)


def _files_beside(env: dict[str, Any], folder: Path) -> dict[str, Any]:
    """``env`` with the files it names resolved against ``folder`` (:func:`_beside`)."""
    out = dict(env)
    for keys in _FILE_KEYS:
        table = out
        for k in keys[:-1]:
            if not isinstance(table.get(k), dict):
                break
            table[k] = table = dict(table[k])
        else:
            value = table.get(keys[-1])
            if isinstance(value, str) and value:
                table[keys[-1]] = _beside(value, folder.absolute())
    return out


def policy_train_env(policy: str) -> dict[str, Any]:
    """The ``[train.env]`` table of the run a policy comes from (:func:`policy_train_source`)."""
    return policy_train_source(policy)[0]


def policy_train_source(policy: str) -> tuple[dict[str, Any], Path | None]:
    """The ``[train.env]`` table of the run a policy comes from, in the current layout
    (:func:`uwdock.dockcore.config.current_layout`: a run folder written before a key moved
    reads as if written today), and the file it was read from: the ``config.toml`` of its run
    folder (the policy folder or one level up, as for ``best/``) or, for an exported ``.onnx``,
    the ``.json`` written beside it; ``({}, None)`` if none (or "pid"). The files it names are
    resolved where the policy is (:func:`_beside`), so a policy folder works from any current
    folder."""
    if policy == "pid":
        return {}, None
    p = Path(policy)
    if p.suffix == ".onnx":
        meta = p.with_suffix(".json")
        if not meta.is_file():
            return {}, None
        try:
            data = json.loads(meta.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise DockError(f"cannot read {meta}: {exc}") from None
        env = data.get("env", {}) if isinstance(data, dict) else {}
        if not isinstance(env, dict):
            return {}, meta
        return _files_beside(current_layout(EnvConfig, env), p.parent), meta
    train, cand = policy_train_settings(p)
    if cand is None:
        return {}, None
    env = train.get("env", {})
    if not isinstance(env, dict):
        raise DockError(f"{cand}: [train.env] is not a table")
    return _files_beside(current_layout(EnvConfig, env), cand.parent), cand


def policy_train_settings(policy: str | os.PathLike[str]) -> tuple[dict[str, Any], Path | None]:
    """The ``[train]`` table of the run config a policy folder or ``policy.zip`` comes from
    (``config.toml`` beside it or one level up, as for ``best/``) and that file; ``({}, None)``
    without one."""
    p = Path(policy)
    folder = p if p.is_dir() else p.parent
    for cand in (folder / "config.toml", folder.parent / "config.toml"):
        if cand.is_file():
            train = read_toml(cand, what="run config").get("train", {})
            if not isinstance(train, dict):
                raise DockError(f"{cand}: [train] is not a table")
            return train, cand
    return {}, None


def policy_env_settings(policy: str) -> dict[str, Any]:
    """The interface fields (observation layout, action scaling) of the env a policy was
    trained in (see :func:`policy_train_env`); {} if unknown."""
    env = policy_train_env(policy)
    return {k: env[k] for k in POLICY_INTERFACE_FIELDS if k in env}


def policy_error_model(policy: str) -> str | None:
    """The error model file the policy's run trained on, if its run config names one."""
    path = policy_train_env(policy).get("error_model_path")
    return path if isinstance(path, str) and path else None


def policy_input_files(policy: str) -> list[Path]:
    """The files :func:`load_controller` reads for ``policy`` (absolute): the ``.onnx`` and its
    ``.json`` sidecar, or a policy folder's ``model.json``, ``weights.npz`` and run config
    where it has one; none for 'pid'."""
    if policy == "pid":
        return []
    p = Path(policy).expanduser().resolve()
    if p.suffix == ".onnx":
        return [f for f in (p, p.with_suffix(".json")) if f.is_file()] or [p]
    folder = p if p.is_dir() else p.parent
    files = [folder / "model.json", folder / "weights.npz"]
    _, run_config = policy_train_settings(folder)
    if run_config is not None:
        files.append(run_config.resolve())
    return files


def load_controller(policy: str, env_cfg: EnvConfig):
    """'pid', an .onnx file, or a policy folder -> (controller, vecnorm, label)."""
    if policy == "pid":
        return PIDController.for_env(env_cfg), None, "pid"
    path = Path(policy)
    env_dim = observation_size(env_cfg)
    if path.suffix == ".onnx":
        onnx = OnnxPolicy(path)
        if onnx.obs_dim is not None:
            check_obs_dim(onnx.obs_dim, env_dim, str(path))
        return onnx, None, path.name
    model, vecnorm = load_policy(path)
    check_obs_dim(int(model.observation_space.shape[0]), env_dim, str(path))
    return model, vecnorm, str(path)


def load_policy(path: str | os.PathLike[str]):
    """Load a policy folder (``model.json`` + ``weights.npz``, :mod:`rl.policy.policy_format`) and
    its observation normalisation, without running any code from the folder: ``(model,
    vecnorm)``, ``model`` a :class:`rl.policy.policy_format.LoadedPolicy`, ``vecnorm`` a
    ``VecNormalize`` without env or None. ``path`` may name the folder, its ``model.json``, or a
    ``policy.zip`` in it.

    Raises:
        DockError: one line for a missing, damaged or non-finite policy, for normalisation that
            contradicts the run config, and for a folder in the pickled format (refused: it can
            run code when loaded; ``rl convert-policy --trust-pickle`` converts it).
    """
    p = Path(path)
    folder = p if p.is_dir() else p.parent
    if not p.exists():
        raise DockError(f"policy file not found: {p}")
    if not (folder / MODEL).exists():
        legacy = ("policy.zip", "vecnormalize.pkl")
        if p.suffix in (".zip", ".pkl") or any((folder / n).exists() for n in legacy):
            raise legacy_refusal(p)
        raise DockError(f"{folder} holds no policy ({MODEL} and {WEIGHTS})")
    model, vecnorm = read_policy(folder)
    train, run_config = policy_train_settings(folder)
    normalised = train.get("normalize_obs") is True
    if normalised and (vecnorm is None or not vecnorm.norm_obs):
        raise DockError(
            f"policy {folder}: its run config {run_config} says normalize_obs = true but its "
            f"{MODEL} has no observation normalisation (the policy reads normalised observations)"
        )
    return model, vecnorm


def check_obs_dim(policy_dim: int, env_dim: int, policy: str, why: str = "") -> None:
    """Raise DockError when a policy's observation size differs from the env's (``why``: a
    reason to append)."""
    if policy_dim != env_dim:
        raise DockError(
            f"policy {policy} takes {policy_dim} observation values, the env gives {env_dim}: "
            "it was trained with another observation layout (obs_last_action, obs_uncertainty, "
            "obs_contact, obs_fine_error, obs_frames); keep its run's config.toml (or the .json "
            "beside an .onnx) next to it" + (f" ({why})" if why else "")
        )


class OnnxPolicy:
    """Run an exported policy with onnxruntime: ``act(obs) -> action`` (a Controller)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        import onnxruntime as ort

        p = Path(path)
        check_regular_file(p, "ONNX policy")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1
        opts.log_severity_level = 4
        try:
            self.session = ort.InferenceSession(str(p), opts, providers=["CPUExecutionProvider"])
        except Exception as exc:
            text = " ".join(str(exc).split())[:160]
            raise DockError(f"cannot read ONNX policy {p}: {text or type(exc).__name__}") from None
        shape = self.session.get_inputs()[0].shape
        self.obs_dim = shape[-1] if isinstance(shape[-1], int) else None
        meta = p.with_suffix(".json")
        try:
            self.meta = json.loads(meta.read_text(encoding="utf-8")) if meta.exists() else {}
        except (OSError, ValueError) as exc:
            raise DockError(f"cannot read {meta}: {exc}") from None

    def reset(self) -> None:
        pass

    def act(self, obs: np.ndarray) -> np.ndarray:
        x = np.asarray(obs, dtype=np.float32).reshape(1, -1)
        return self.session.run(["action"], {"obs": x})[0][0].astype(np.float64)
