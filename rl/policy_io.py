"""Policies on disk: loading a ``policy.zip`` (PPO/SAC, with its observation normalisation) or an
exported ``.onnx``, the interface of the env a policy was trained in, and the controller that
``rl eval``, the deployment runner and training's evaluations drive.

The bottom of ``rl`` above the env: evaluation, the report writer, export and training import
it; it imports none of them.
"""

from __future__ import annotations

import json
import os
import pickle
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from uwdock.dockcore.config import read_toml
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import check_regular_file
from uwdock.rl.baselines import PIDController
from uwdock.rl.checkpoint import require_finite_policy
from uwdock.rl.config import EnvConfig
from uwdock.rl.observation import observation_size

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


def policy_train_env(policy: str) -> dict[str, Any]:
    """The ``[train.env]`` table of the run a policy comes from: the ``config.toml`` of its run
    folder (beside ``policy.zip`` or one level up, as for ``best/``) or, for an exported
    ``.onnx``, the ``.json`` written beside it; {} if none."""
    if policy == "pid":
        return {}
    p = Path(policy)
    if p.suffix == ".onnx":
        meta = p.with_suffix(".json")
        try:
            data = json.loads(meta.read_text(encoding="utf-8")) if meta.is_file() else {}
        except (OSError, ValueError) as exc:
            raise DockError(f"cannot read {meta}: {exc}") from None
        env = data.get("env", {}) if isinstance(data, dict) else {}
        return env if isinstance(env, dict) else {}
    train, cand = policy_train_settings(p)
    env = train.get("env", {})
    if not isinstance(env, dict):
        raise DockError(f"{cand}: [train.env] is not a table")
    return env


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
    ``.json`` sidecar, or the ``policy.zip``, its ``vecnormalize.pkl`` and run config where
    they exist; none for 'pid'."""
    if policy == "pid":
        return []
    p = Path(policy).expanduser().resolve()
    if p.suffix == ".onnx":
        return [f for f in (p, p.with_suffix(".json")) if f.is_file()] or [p]
    zip_path = p / "policy.zip" if p.is_dir() else p
    files = [zip_path]
    if zip_path.with_name("vecnormalize.pkl").is_file():
        files.append(zip_path.with_name("vecnormalize.pkl"))
    _, run_config = policy_train_settings(zip_path)
    if run_config is not None:
        files.append(run_config.resolve())
    return files


def load_controller(policy: str, env_cfg: EnvConfig):
    """'pid', an .onnx file, or a policy.zip / run folder -> (controller, vecnorm, label)."""
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
    """Load ``policy.zip`` (PPO or SAC) and, if beside it, ``vecnormalize.pkl``.

    Raises:
        DockError: one line for a missing, truncated or garbage policy or normalisation file,
            or a policy whose weights or statistics hold NaN or infinity.
    """
    from stable_baselines3 import PPO, SAC

    p = Path(path)
    if p.is_dir():
        p = p / "policy.zip"
    check_regular_file(p, "policy file")
    model, reasons = None, []
    for cls in (PPO, SAC):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                model = cls.load(str(p), device="cpu")
            break
        except Exception as exc:  # SB3 raises anything from zip, pickle and torch errors
            reasons.append(" ".join(str(exc).split())[:160] or type(exc).__name__)
    if model is None:
        raise DockError(f"cannot read policy {p}: not a PPO or SAC model ({reasons[0]})")
    require_finite_policy(model, f"policy {p}")
    vecnorm = None
    vn = p.with_name("vecnormalize.pkl")
    train, run_config = policy_train_settings(p)
    normalised = train.get("normalize_obs") is True
    if normalised and not vn.exists():
        raise DockError(
            f"policy {p}: its run config {run_config} says normalize_obs = true but "
            f"{vn.name} is missing beside it (the policy reads normalised observations)"
        )
    if vn.exists():
        try:
            with vn.open("rb") as fh:
                vecnorm = pickle.load(fh)
            stats = (vecnorm.obs_rms.mean, vecnorm.obs_rms.var)
        except Exception as exc:
            raise DockError(f"cannot read normalisation {vn}: {type(exc).__name__}") from None
        if not all(np.all(np.isfinite(a)) for a in stats):
            raise DockError(f"normalisation {vn} holds NaN or infinity")
        if normalised and not getattr(vecnorm, "norm_obs", False):
            raise DockError(
                f"normalisation {vn} does not normalise observations, but the run config "
                f"{run_config} says normalize_obs = true"
            )
        vecnorm.training = False
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
