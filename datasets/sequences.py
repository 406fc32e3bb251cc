"""Frames that form time sequences: which frames of a labelled dataset were taken one after the
other (e.g. along a docking trajectory at the control rate), so temporal statistics (the error
model's lag-1 autocorrelation) can be fitted from them.

A dataset rendered from a pose CSV with the columns ``sequence, step, time_s`` (``datasets render
--poses``, e.g. written by ``rl trajectories``) records them in ``dataset.json``::

    "sequences": {"sequence": [0, 0, 0, 1, ...],      # per frame: which sequence (int >= 0)
                  "step": [0, 1, 2, 0, ...],          # per frame: control step in it (int >= 0)
                  "time_s": [0.0, 0.2, 0.4, 0.0, ...]} # per frame: time in the sequence (s)

one entry per frame, in frame order. Two frames are *consecutive* when they belong to the same
sequence and the second's step is the first's + 1; a gap in the steps (a pose left out) breaks
the chain there. Datasets without the key are plain sets of independent frames.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from uwdock.dockcore.errors import DockError

__all__ = ["FrameSequences", "check_sequences", "sequences_from_manifest"]

#: The pose-CSV columns (and ``dataset.json`` keys) of a sequence label, in order.
SEQUENCE_COLUMNS: tuple[str, ...] = ("sequence", "step", "time_s")
#: Consecutive frames whose time steps differ by more than this fraction do not share one
#: step duration (s/s).
STEP_TOL = 1e-3


@dataclass(frozen=True)
class FrameSequences:
    """Sequence labels of the N frames of a dataset (module docstring).

    Attributes:
        sequence: (N,) int64, the sequence of each frame (>= 0).
        step: (N,) int64, the control step of each frame in its sequence (>= 0).
        time_s: (N,) float64, the time of each frame in its sequence (s).
    """

    sequence: np.ndarray
    step: np.ndarray
    time_s: np.ndarray

    def __len__(self) -> int:
        return len(self.sequence)

    def to_json(self) -> dict[str, list]:
        """The ``dataset.json`` object (lists in frame order)."""
        return {
            "sequence": [int(v) for v in self.sequence],
            "step": [int(v) for v in self.step],
            "time_s": [float(v) for v in self.time_s],
        }

    def consecutive_pairs(self, lag: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Frame indices ``(i, j)`` (each (P,) int64, ascending in ``i``) of the consecutive
        pairs: same sequence, ``step[j] == step[i] + lag`` (lag >= 1 steps)."""
        keys = list(zip(self.sequence.tolist(), self.step.tolist(), strict=True))
        where = {key: f for f, key in enumerate(keys)}
        pairs = [(f, where[(s, k + lag)]) for f, (s, k) in enumerate(keys) if (s, k + lag) in where]
        a = np.asarray(pairs, np.int64).reshape(-1, 2)
        return a[:, 0], a[:, 1]

    def step_s(self) -> float | None:
        """The duration of one step (s): the median time difference of the consecutive pairs,
        None without pairs.

        Raises:
            DockError: when the pairs' time differences disagree by more than ``STEP_TOL``.
        """
        i, j = self.consecutive_pairs()
        if len(i) == 0:
            return None
        dt = self.time_s[j] - self.time_s[i]
        mid = float(np.median(dt))
        if not mid > 0 or np.any(np.abs(dt - mid) > STEP_TOL * mid):
            raise DockError(
                f"sequences: consecutive steps are {dt.min():.6g}-{dt.max():.6g} s apart; "
                "they must share one positive step duration"
            )
        return mid


def check_sequences(
    sequence: ArrayLike, step: ArrayLike, time_s: ArrayLike, n_frames: int, where: str
) -> FrameSequences:
    """Validated :class:`FrameSequences` of ``n_frames`` frames.

    Raises:
        DockError: one line naming ``where``: lengths other than ``n_frames``, negative or
            non-integer sequence/step values, non-finite times, a (sequence, step) given
            twice, or time not increasing with the step inside a sequence.
    """
    cols = {}
    for name, values in zip(SEQUENCE_COLUMNS, (sequence, step, time_s), strict=True):
        try:
            a = np.asarray(values, np.float64)
        except (TypeError, ValueError):
            raise DockError(f"{where}: '{name}' must be a list of numbers") from None
        if a.shape != (n_frames,):
            raise DockError(f"{where}: '{name}' must hold {n_frames} values, got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise DockError(f"{where}: '{name}' holds a non-finite value")
        if name != "time_s" and (np.any(a < 0) or np.any(a != np.round(a)) or np.any(a > 2**62)):
            raise DockError(f"{where}: '{name}' must hold integers >= 0")
        cols[name] = a
    seq = cols["sequence"].astype(np.int64)
    stp = cols["step"].astype(np.int64)
    t = cols["time_s"]
    order = np.lexsort((stp, seq))
    s_o, k_o, t_o = seq[order], stp[order], t[order]
    same = s_o[1:] == s_o[:-1]
    dup = same & (k_o[1:] == k_o[:-1])
    if np.any(dup):
        f = int(order[1:][dup][0])
        raise DockError(f"{where}: frame {f} repeats sequence {seq[f]} step {stp[f]}")
    back = same & ~(t_o[1:] > t_o[:-1])
    if np.any(back):
        f = int(order[1:][back][0])
        raise DockError(
            f"{where}: frame {f} (sequence {seq[f]} step {stp[f]}) is not later than the "
            "previous step"
        )
    return FrameSequences(seq, stp, t.astype(np.float64))


def sequences_from_manifest(
    manifest: Mapping[str, Any], n_frames: int, where: str = "dataset.json"
) -> FrameSequences | None:
    """The sequence labels of a ``dataset.json`` object, or None when it has none.

    Raises:
        DockError: a malformed ``sequences`` entry (see :func:`check_sequences`).
    """
    raw = manifest.get("sequences")
    if raw is None:
        return None
    if not isinstance(raw, Mapping) or any(k not in raw for k in SEQUENCE_COLUMNS):
        raise DockError(f"{where}: 'sequences' must map {', '.join(SEQUENCE_COLUMNS)} to lists")
    return check_sequences(*(raw[k] for k in SEQUENCE_COLUMNS), n_frames, f"{where} sequences")
