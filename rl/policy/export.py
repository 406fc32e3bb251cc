"""``rl export``: the policy as ONNX, observation normalisation included.

The exported graph maps the raw observation (as :class:`rl.env.docking_env.DockingEnv` builds it) to
the deterministic action in [-1, 1]^6: ``clip((obs - mean) / std, -clip, clip)`` -> actor network ->
mean action (PPO) or tanh(mean) (SAC) -> clip to [-1, 1]. An asymmetric actor-critic's actor
reads only the leading ``actor_obs_dim`` values (its privileged block is ignored).
"""

from __future__ import annotations

import io
import json
import os
import warnings
from pathlib import Path

import numpy as np

from uwdock.dockcore.config import to_dict
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_files, check_output_path
from uwdock.rl.policy.env_settings import policy_training_env
from uwdock.rl.policy.policy_io import load_policy, named_from_checkout, policy_env_settings


def _actor_module(model, vecnorm):
    """The exported network of ``model`` (:class:`rl.policy.export_actor.ExportActor`), in eval
    mode."""
    from uwdock.rl.policy.export_actor import ExportActor  # torch at module level

    return ExportActor(model, vecnorm).eval()


def export_onnx(policy_path: str | os.PathLike[str], out: str | os.PathLike[str]) -> Path:
    """Write ``out`` (.onnx) and ``<out>.json`` (observation layout, limits, the training env,
    provenance) as one unit (:func:`dockcore.io.atomic_write_files`): both new, or the old
    pair as it was."""
    import torch

    out = Path(out)
    if out.suffix == ".json":
        raise DockError(f"--out {out}: the ONNX file's .json sidecar would be the file itself")
    check_output_path(out, "--out", [out.with_suffix(".json")])  # before the policy loads
    model, vecnorm = load_policy(policy_path)
    actor = _actor_module(model, vecnorm)
    dim = model.observation_space.shape[0]
    _require_finite_outputs(actor, dim, str(policy_path))
    buf = io.BytesIO()
    with warnings.catch_warnings():  # the TorchScript exporter needs no onnxscript
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(
            actor,
            torch.zeros(1, dim),
            buf,
            input_names=["obs"],
            output_names=["action"],
            dynamic_axes={"obs": {0: "batch"}, "action": {0: "batch"}},
            opset_version=17,
            dynamo=False,
        )
    trained = policy_training_env(str(policy_path))
    sidecar = {
        "obs_dim": int(dim),
        "action_dim": 6,
        "source_policy": str(policy_path),
        "action_meaning": "body wrench / wrench_limits, [Fx, Fy, Fz, Mx, My, Mz]",
        # the env the policy was trained in (every EnvConfig field: observation layout, limits,
        # rate, USBL, water, camera width, termination, ...), so `rl eval` and the runner
        # rebuild the observation and the settings it was trained with; without a run config,
        # only what is known of its interface
        "env": (
            to_dict(named_from_checkout(trained.cfg))
            if trained
            else policy_env_settings(str(policy_path))
        ),
        "env_from": trained.policy_config if trained else None,
    }
    # one unit: an .onnx without its .json would be run with another observation layout
    atomic_write_files(
        {
            out: buf.getvalue(),
            out.with_suffix(".json"): (json.dumps(sidecar, indent=2) + "\n").encode("utf-8"),
        }
    )
    return out


def _require_finite_outputs(actor, dim: int, policy: str) -> None:
    """Raise DockError when the actor maps typical observations to NaN or infinity."""
    import torch

    probe = torch.as_tensor(np.random.default_rng(0).uniform(-2, 2, (64, dim)), dtype=torch.float32)
    with torch.no_grad():
        out = actor(torch.cat([torch.zeros(1, dim), probe]))
    if not bool(torch.isfinite(out).all()):
        raise DockError(f"policy {policy} outputs NaN or infinity: refusing to export it")
