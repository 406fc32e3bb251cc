"""``rl export``: the policy as ONNX, observation normalisation included.

The exported graph maps the raw observation (as :class:`rl.env.DockingEnv` builds it) to the
deterministic action in [-1, 1]^6: ``clip((obs - mean) / std, -clip, clip)`` -> actor network ->
mean action (PPO) or tanh(mean) (SAC) -> clip to [-1, 1].
"""

from __future__ import annotations

import io
import json
import os
import warnings
from pathlib import Path

import numpy as np

from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_bytes, atomic_write_json


def load_policy(path: str | os.PathLike[str]):
    """Load ``policy.zip`` (PPO or SAC) and, if beside it, ``vecnormalize.pkl``.

    Raises:
        DockError: one line for a missing, truncated or garbage policy or normalisation file,
            or a policy whose weights or statistics hold NaN or infinity.
    """
    import pickle

    from stable_baselines3 import PPO, SAC

    from uwdock.rl.checkpoint import require_finite_policy

    p = Path(path)
    if p.is_dir():
        p = p / "policy.zip"
    if not p.is_file():
        raise DockError(f"policy file not found: {p}")
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
    if vn.exists():
        try:
            with vn.open("rb") as fh:
                vecnorm = pickle.load(fh)
            stats = (vecnorm.obs_rms.mean, vecnorm.obs_rms.var)
        except Exception as exc:
            raise DockError(f"cannot read normalisation {vn}: {type(exc).__name__}") from None
        if not all(np.all(np.isfinite(a)) for a in stats):
            raise DockError(f"normalisation {vn} holds NaN or infinity")
        vecnorm.training = False
    return model, vecnorm


def check_obs_dim(policy_dim: int, env_dim: int, policy: str) -> None:
    """Raise DockError when a policy's observation size differs from the env's."""
    if policy_dim != env_dim:
        raise DockError(
            f"policy {policy} takes {policy_dim} observation values, the env gives {env_dim}: "
            "it was trained with another observation layout (obs_last_action, obs_uncertainty, "
            "obs_frames); keep its run's config.toml (or the .json beside an .onnx) next to it"
        )


def _actor_module(model, vecnorm):
    import torch
    from stable_baselines3 import SAC

    if vecnorm is not None and vecnorm.norm_obs:
        mean = torch.as_tensor(vecnorm.obs_rms.mean, dtype=torch.float32)
        std = torch.as_tensor(np.sqrt(vecnorm.obs_rms.var + vecnorm.epsilon), dtype=torch.float32)
        clip = float(vecnorm.clip_obs)
    else:
        dim = model.observation_space.shape[0]
        mean, std, clip = torch.zeros(dim), torch.ones(dim), float("inf")

    class Actor(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.register_buffer("mean", mean)
            self.register_buffer("std", std)
            self.clip = clip
            if isinstance(model, SAC):
                self.net = torch.nn.Sequential(model.actor.latent_pi, model.actor.mu)
                self.squash = True
            else:
                pol = model.policy
                self.net = torch.nn.Sequential(pol.mlp_extractor.policy_net, pol.action_net)
                self.squash = False

        def forward(self, obs):
            x = torch.clamp((obs - self.mean) / self.std, -self.clip, self.clip)
            a = self.net(x)
            if self.squash:
                a = torch.tanh(a)
            return torch.clamp(a, -1.0, 1.0)

    return Actor().eval()


def export_onnx(policy_path: str | os.PathLike[str], out: str | os.PathLike[str]) -> Path:
    """Write ``out`` (.onnx) and ``<out>.json`` (observation layout, limits, provenance)."""
    import torch

    from uwdock.rl.report import policy_env_settings

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
    out = atomic_write_bytes(Path(out), buf.getvalue())
    atomic_write_json(
        out.with_suffix(".json"),
        {
            "obs_dim": int(dim),
            "action_dim": 6,
            "source_policy": str(policy_path),
            "action_meaning": "body wrench / wrench_limits, [Fx, Fy, Fz, Mx, My, Mz]",
            # the EnvConfig fields of the policy's interface (observation layout, limits, rate),
            # so `rl eval` and the runner rebuild the observation it was trained on
            "env": policy_env_settings(str(policy_path)),
        },
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


class OnnxPolicy:
    """Run an exported policy with onnxruntime: ``act(obs) -> action`` (a Controller)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        import onnxruntime as ort

        p = Path(path)
        if not p.is_file():
            raise DockError(f"ONNX policy not found: {p}")
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
