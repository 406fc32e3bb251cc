"""``rl convert-policy``: a policy folder of the pickled format (SB3's ``policy.zip`` and a
pickled ``vecnormalize.pkl``) rewritten in the data format of :mod:`rl.policy.policy_format`.

Reading the pickled format can run code from the folder, so this is the one place that reads it,
and only when the user says they trust the folder (``--trust-pickle``); every other command
refuses it. The run's records (config, provenance, evaluation history) are copied beside the
converted policy, so the folder loads as the original did.
"""

from __future__ import annotations

import io
import os
import pickle
import shutil
import warnings
from pathlib import Path

from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import check_regular_file
from uwdock.rl.policy.policy_format import (
    LEGACY,
    MODEL,
    legacy_module_paths,
    require_finite_policy,
    write_policy,
)

#: the run records copied beside the converted policy, where the source has them
RECORDS = ("config.toml", "provenance.json", "eval_history.jsonl", "imitation.json")


def _legacy_folder(source: Path) -> Path:
    folder = source if source.is_dir() else source.parent
    if not (folder / LEGACY[0]).exists():
        raise DockError(f"{source} holds no {LEGACY[0]} to convert")
    return folder


def read_legacy(folder: Path):
    """SB3's model and ``VecNormalize`` (None without one) of a pickled-format folder. This
    runs whatever code the pickles hold: callers ask the user first."""
    from stable_baselines3 import PPO, SAC

    zip_path = check_regular_file(folder / LEGACY[0], "policy file")
    model, reasons = None, []
    for cls in (PPO, SAC):
        try:
            with warnings.catch_warnings(), legacy_module_paths():
                warnings.simplefilter("ignore")
                model = cls.load(str(zip_path), device="cpu")
            break
        except Exception as exc:  # SB3 raises anything from zip, pickle and torch errors
            reasons.append(" ".join(str(exc).split())[:160] or type(exc).__name__)
    if model is None:
        raise DockError(f"cannot read policy {zip_path}: not a PPO or SAC model ({reasons[0]})")
    vecnorm = None
    vn = folder / LEGACY[1]
    if vn.exists():
        check_regular_file(vn, "normalisation file")
        try:
            vecnorm = pickle.load(io.BytesIO(vn.read_bytes()))
            stats = (vecnorm.obs_rms.mean, vecnorm.obs_rms.var)
        except Exception as exc:  # a pickle raises anything
            raise DockError(f"cannot read normalisation {vn}: {type(exc).__name__}") from None
        del stats
    return model, vecnorm


def convert_policy(
    source: str | os.PathLike[str], out: str | os.PathLike[str], trust_pickle: bool
) -> Path:
    """Write the policy of ``source`` (a pickled-format folder or its ``policy.zip``) into the
    folder ``out`` in the data format, with its run records; ``out``.

    Raises:
        DockError: without ``trust_pickle`` (before anything is read), for a source that is not
            a pickled-format policy, or an ``out`` that already holds a policy.
    """
    src = Path(source)
    if not trust_pickle:
        raise DockError(
            f"converting {src} reads pickles, which can run code: pass --trust-pickle if you "
            "trust where it came from"
        )
    folder = _legacy_folder(src)
    dest = Path(out)
    if (dest / MODEL).exists() or any((dest / n).exists() for n in LEGACY):
        raise DockError(f"{dest} already holds a policy: use another --out")
    if dest.resolve() == folder.resolve():
        raise DockError("--out must be another folder than the source")
    model, vecnorm = read_legacy(folder)
    require_finite_policy(model, f"policy {folder}")
    write_policy(dest, model, vecnorm)
    for name in RECORDS:
        if (folder / name).is_file():
            shutil.copyfile(folder / name, dest / name)
    return dest
