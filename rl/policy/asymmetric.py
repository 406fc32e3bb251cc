"""Asymmetric actor-critic for PPO: the critic sees privileged state, the actor only the estimate.

The env's observation with ``obs_privileged`` is ``[actor frames | privileged block]``
(:mod:`rl.env.observation`). :class:`AsymmetricPolicy` is SB3's ``ActorCriticPolicy`` whose actor
network reads only the first ``actor_obs_dim`` values and whose value network reads all of
them: the value of a state is learned from the truth (where the DS really is, how wrong the
estimate is, how much time is left), while the policy acts on what the vehicle can know. This
is the standard sim-to-real construction (Pinto et al. 2018, "Asymmetric actor critic for
image-based robot learning").

Only training envs fill the privileged block; evaluation envs, ``rl eval``, the ONNX export
(which slices the actor's inputs) and the deployment runner give zeros there, and the actor's
output does not depend on it (tests/test_asymmetric.py).

This module subclasses torch's ``nn.Module`` and SB3's ``ActorCriticPolicy``, so it imports them
at module level: only the functions that build or load a model import it (``rl.train.training``),
never a module that a light command imports (``tests/test_architecture.py``: heavy modules of the
tree). SB3 saves and loads the policy class by name,
``uwdock.rl.policy.asymmetric.AsymmetricPolicy``.
"""

from __future__ import annotations

from typing import Any

import torch
from stable_baselines3.common.policies import ActorCriticPolicy
from torch import nn

__all__ = ["AsymmetricPolicy", "SplitMlpExtractor"]


def mlp(in_dim: int, sizes: list[int], activation_fn: type[nn.Module]) -> tuple[nn.Sequential, int]:
    """A stack of ``Linear`` + ``activation_fn`` layers of the given hidden ``sizes`` on an
    ``in_dim`` input, and its output size (``in_dim`` when ``sizes`` is empty)."""
    layers: list[nn.Module] = []
    last = in_dim
    for size in sizes:
        layers += [nn.Linear(last, size), activation_fn()]
        last = size
    return nn.Sequential(*layers), last


class SplitMlpExtractor(nn.Module):
    """SB3's ``MlpExtractor`` with the actor reading only the first ``actor_dim`` features.

    Args:
        feature_dim: length of the whole (flattened) observation.
        actor_dim: how many leading values the actor reads.
        net_arch: hidden sizes, a list (both networks) or ``{"pi": [...], "vf": [...]}``.
        activation_fn: activation class.
    """

    def __init__(
        self,
        feature_dim: int,
        actor_dim: int,
        net_arch: list[int] | dict[str, list[int]],
        activation_fn: type[nn.Module],
    ) -> None:
        super().__init__()
        if not 0 < actor_dim <= feature_dim:
            raise ValueError(f"actor_dim {actor_dim} must be in 1..{feature_dim}")
        pi = net_arch.get("pi", []) if isinstance(net_arch, dict) else list(net_arch)
        vf = net_arch.get("vf", []) if isinstance(net_arch, dict) else list(net_arch)
        self.actor_dim = actor_dim
        self.policy_net, self.latent_dim_pi = mlp(actor_dim, pi, activation_fn)
        self.value_net, self.latent_dim_vf = mlp(feature_dim, vf, activation_fn)

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.forward_actor(features), self.forward_critic(features)

    def forward_actor(self, features: torch.Tensor) -> torch.Tensor:
        return self.policy_net(features[..., : self.actor_dim])

    def forward_critic(self, features: torch.Tensor) -> torch.Tensor:
        return self.value_net(features)


class AsymmetricPolicy(ActorCriticPolicy):
    """``ActorCriticPolicy`` with a :class:`SplitMlpExtractor` (module docstring).

    Args:
        actor_obs_dim: how many leading observation values the actor reads.
        *args, **kwargs: as SB3's ``ActorCriticPolicy`` (the features extractor must keep
            the observation's order: the default flatten extractor does).
    """

    def __init__(self, *args: Any, actor_obs_dim: int, **kwargs: Any) -> None:
        self.actor_obs_dim = int(actor_obs_dim)
        super().__init__(*args, **kwargs)

    def _build_mlp_extractor(self) -> None:
        self.mlp_extractor = SplitMlpExtractor(
            self.features_dim, self.actor_obs_dim, self.net_arch, self.activation_fn
        )

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {**super()._get_constructor_parameters(), "actor_obs_dim": self.actor_obs_dim}
