"""The network that ``rl export`` writes as ONNX (:mod:`rl.policy.export`): the raw observation to
the deterministic action in [-1, 1]^6, observation normalisation included.

This module subclasses torch's ``nn.Module``, so it imports torch at module level: only the
functions that export (:func:`rl.policy.export.export_onnx`) import it, never a module that a light
command imports (``tests/test_architecture.py``: heavy modules of the tree).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from stable_baselines3.sac.policies import SACPolicy

__all__ = ["ExportActor"]


class ExportActor(torch.nn.Module):
    """``clip((obs - mean) / std, -clip, clip)`` -> the policy's actor network -> mean action
    (PPO) or ``tanh`` of it (SAC) -> clip to [-1, 1].

    An asymmetric actor-critic's actor (:class:`rl.policy.asymmetric.AsymmetricPolicy`) reads only
    the leading ``actor_obs_dim`` values of the normalised observation.

    Args:
        model: the SB3 model or loaded policy (PPO or SAC; :mod:`rl.policy.policy_format`); its
            networks are shared, not copied.
        vecnorm: its ``VecNormalize`` (observation statistics), or None (no normalisation).

    Input ``obs``: ``(batch, obs_dim)`` float32; output: ``(batch, 6)`` in [-1, 1].
    """

    def __init__(self, model: Any, vecnorm: Any | None) -> None:
        super().__init__()
        if vecnorm is not None and vecnorm.norm_obs:
            mean = torch.as_tensor(vecnorm.obs_rms.mean, dtype=torch.float32)
            var = vecnorm.obs_rms.var + vecnorm.epsilon
            std = torch.as_tensor(np.sqrt(var), dtype=torch.float32)
            clip = float(vecnorm.clip_obs)
        else:
            dim = model.observation_space.shape[0]
            mean, std, clip = torch.zeros(dim), torch.ones(dim), float("inf")
        self.register_buffer("mean", mean)
        self.register_buffer("std", std)
        self.clip = clip
        if isinstance(model.policy, SACPolicy):
            actor = model.policy.actor
            self.net = torch.nn.Sequential(actor.latent_pi, actor.mu)
            self.squash = True
        else:
            pol = model.policy
            self.net = torch.nn.Sequential(pol.mlp_extractor.policy_net, pol.action_net)
            self.squash = False
        # an asymmetric actor-critic's actor reads only the leading values
        self.actor_dim = int(getattr(model.policy, "actor_obs_dim", len(mean)))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        x = torch.clamp((obs - self.mean) / self.std, -self.clip, self.clip)
        a = self.net(x[..., : self.actor_dim])
        if self.squash:
            a = torch.tanh(a)
        return torch.clamp(a, -1.0, 1.0)
