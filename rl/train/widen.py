"""Fine-tuning a policy on a wider observation: inputs it was not trained with, added at zero.

``rl train --init-policy P`` normally needs P's observation layout to equal the run's. A run may
instead *add* observation entries that P never saw (:data:`WIDENING_FIELDS`: ``obs_fine_error``
off in P's training env, on in the run's). The new model then starts as P exactly: every weight
that reads an input P had is copied to that input's new position, the weights reading the new
inputs start at 0, and the observation normalisation keeps P's statistics for the old entries
(mean 0, variance 1 for the new ones, which are tanh values within +-1). The first update sees
P's actions and values; PPO's gradients then reach the new weights. This is the input half of
function-preserving network growth (Chen, Goodfellow and Shlens, "Net2Net: Accelerating Learning
via Knowledge Transfer", ICLR 2016), used here so a shipped stage 1 can be fine-tuned with the
fine error without training stage 1 again.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from uwdock.rl.env.config import EnvConfig
from uwdock.rl.env.observation import frame_dim, observation_size
from uwdock.rl.policy.policy_io import POLICY_INTERFACE_FIELDS

#: Observation options a fine-tune may switch on over its init policy's layout.
WIDENING_FIELDS = ("obs_fine_error",)


def widening_index(old_env: EnvConfig, new_env: EnvConfig) -> np.ndarray | None:
    """Where each entry of ``old_env``'s observation sits in ``new_env``'s, when the new layout
    only switches on :data:`WIDENING_FIELDS` (their entries end each frame); None when the two
    layouts are the same.

    Raises:
        ValueError: one line naming what differs when the new layout is not a widening of the
            old one (another observation option changed, a widening option switched off, or
            a privileged block, whose critic-only layout this does not map).
    """
    differs = [
        f
        for f in POLICY_INTERFACE_FIELDS
        if getattr(old_env, f) != getattr(new_env, f) and f not in WIDENING_FIELDS
    ]
    if differs:
        raise ValueError(f"the observation differs in {', '.join(differs)}")
    added = [f for f in WIDENING_FIELDS if getattr(old_env, f) != getattr(new_env, f)]
    if not added:
        return None
    off = [f for f in added if getattr(old_env, f)]
    if off:
        raise ValueError(f"{', '.join(off)} is on in the init policy and off here")
    if new_env.obs_privileged:
        raise ValueError("widening a policy with a privileged (critic-only) block")
    # the widening entries end each frame (rl.env.observation): the old frame is the new one's start
    fo, fn = frame_dim(old_env), frame_dim(new_env)
    frames = new_env.obs_frames
    index = (np.arange(frames)[:, None] * fn + np.arange(fo)[None, :]).reshape(-1)
    assert index.size == observation_size(old_env) and index.max() < observation_size(new_env)
    return index


def widen_state_dict(
    src: dict[str, Any], dst: dict[str, Any], index: np.ndarray, old_dim: int, new_dim: int
) -> dict[str, Any]:
    """``dst``'s state dict (tensors) filled from ``src``'s: equal shapes copied, and every 2-D
    weight that reads the observation (``old_dim`` columns in ``src``, ``new_dim`` in ``dst``)
    copied into the columns ``index`` with zeros in the others.

    Raises:
        ValueError: a tensor that is neither equal in shape nor such an input weight.
    """
    import torch

    out = {}
    cols = torch.as_tensor(index, dtype=torch.long)
    for key, d in dst.items():
        s = src[key]
        if tuple(s.shape) == tuple(d.shape):
            out[key] = s.clone()
        elif s.ndim == 2 and s.shape[1] == old_dim and tuple(d.shape) == (s.shape[0], new_dim):
            w = torch.zeros_like(d)
            w[:, cols] = s
            out[key] = w
        else:
            raise ValueError(
                f"{key}: the init policy's {tuple(s.shape)} does not widen to {tuple(d.shape)}"
            )
    return out


def widen_obs_rms(src_rms, index: np.ndarray, new_dim: int):
    """A copy of the running observation statistics ``src_rms`` (SB3's RunningMeanStd) over
    ``new_dim`` entries: the old ones at ``index``, mean 0 and variance 1 elsewhere."""
    rms = copy.deepcopy(src_rms)
    mean = np.zeros(new_dim, dtype=np.asarray(src_rms.mean).dtype)
    var = np.ones(new_dim, dtype=np.asarray(src_rms.var).dtype)
    mean[index] = src_rms.mean
    var[index] = src_rms.var
    rms.mean, rms.var = mean, var
    return rms
