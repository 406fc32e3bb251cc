"""Training checkpoints as transactions.

A checkpoint is one folder ``checkpoints/step_<N>/`` holding everything a run needs to go on
exactly as if it had never stopped, as data (nothing in it is unpickled):

* ``training.json`` + ``training.npz``: the model's training state: the policy's weights, its
  optimisers' state (and SAC's entropy coefficient and replay buffer), the step counters, the
  last observation, and the observation/reward normalisation when the run normalises; arrays in
  the ``.npz`` (read with ``allow_pickle=False``), the rest in the JSON; the network and its
  hyperparameters are rebuilt from the run's ``config.toml``;
* ``best/model.json`` + ``best/weights.npz``: the best evaluated policy so far
  (:mod:`rl.policy.policy_format`);
* ``state.json``: the training schedule (next checkpoint, next evaluation), the evaluation
  state (best score and step, evaluations done), the critic warm-up phase and the random
  number generators (Python, NumPy, PyTorch, the action space);
* ``manifest.json``, written last: every file's size and SHA-256.

Every file is written byte-deterministically (fixed zip timestamps, sorted keys), so two runs
that reach the same state write the same bytes. The folder is assembled under a hidden
temporary name and renamed into place, so it either exists complete or not at all;
:func:`latest_unit` takes the newest unit whose manifest checks out and falls back past damaged
ones (a truncated file, a missing manifest), saying so. Units of format version 1 (SB3's
``model.zip`` and pickles) are read only when the user trusts the run folder
(``rl train --resume --trust-pickle``).
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import io
import json
import os
import random
import re
import shutil
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import TEMP_MARK, check_output_dir, temp_sibling
from uwdock.rl.policy.policy_format import (
    legacy_module_paths,
    normalisation_data,
    npz_bytes,
    read_arrays,
)

FORMAT = "uwdock.checkpoint"
VERSION = 2
#: the versions read: 1 held SB3's zip and pickles (read only with --trust-pickle)
READ_VERSIONS = (1, 2)
TRAINING = "training.json"
TRAINING_ARRAYS = "training.npz"
MANIFEST = "manifest.json"
STATE = "state.json"
_UNIT_RE = re.compile(r"^step_(\d+)$")
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)
#: the SB3 attributes a run's training moves on (everything else is rebuilt from its config)
_COUNTERS = (
    "num_timesteps",
    "_n_updates",
    "_episode_num",
    "_current_progress_remaining",
    "_total_timesteps",
)
_LAST = ("_last_obs", "_last_episode_starts", "_last_original_obs")
#: SAC's replay buffer arrays
_REPLAY = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


def unit_name(step: int) -> str:
    """The folder name of the checkpoint at environment step ``step``."""
    return f"step_{step:010d}"


# ----------------------------------------------------------------------------- training state


def _tensor_table(sd: dict[str, Any], prefix: str, arrays: dict[str, np.ndarray]) -> list[str]:
    import torch

    names = []
    for key, value in sd.items():
        if not torch.is_tensor(value):
            raise DockError(f"{prefix}.{key} is not a tensor")
        arrays[f"{prefix}/{key}"] = value.detach().cpu().numpy()
        names.append(key)
    return names


def _optimizer_data(sd: dict[str, Any], prefix: str, arrays: dict[str, np.ndarray]) -> dict:
    """An optimiser's ``state_dict``: tensors into ``arrays``, the rest as JSON."""
    import torch

    state = {}
    for index, entry in sd["state"].items():
        item = {}
        for key, value in entry.items():
            if torch.is_tensor(value):
                arrays[f"{prefix}/{index}/{key}"] = value.detach().cpu().numpy()
                item[key] = {"array": f"{prefix}/{index}/{key}"}
            else:
                item[key] = {"value": value}
        state[str(index)] = item
    return {"state": state, "param_groups": sd["param_groups"]}


def _optimizer_state(meta: dict, arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    import torch

    state = {}
    for index, entry in meta["state"].items():
        state[int(index)] = {
            k: torch.tensor(arrays[v["array"]]) if "array" in v else v["value"]
            for k, v in entry.items()
        }
    groups = [dict(g) for g in meta["param_groups"]]
    for g in groups:
        if isinstance(g.get("betas"), list):
            g["betas"] = tuple(g["betas"])
    return {"state": state, "param_groups": groups}


def training_files(model, vecnorm) -> dict[str, bytes]:
    """``training.json`` and ``training.npz``: ``model``'s training state (module docstring)
    and its ``VecNormalize`` (or None), as deterministic bytes."""
    arrays: dict[str, np.ndarray] = {}
    params = model.get_parameters()  # the policy's state, then each optimiser's
    meta: dict[str, Any] = {
        "algorithm": type(model).__name__.lower(),
        "policy": _tensor_table(params.pop("policy"), "policy", arrays),
        "optimizers": {n: _optimizer_data(sd, f"opt/{n}", arrays) for n, sd in params.items()},
        "variables": [],
        "counters": {k: getattr(model, k) for k in _COUNTERS},
        "last": [],
        "normalization": None,
        "replay_buffer": None,
    }
    for name in model._get_torch_save_params()[1]:  # SAC's log_ent_coef
        arrays[f"var/{name}"] = getattr(model, name).detach().cpu().numpy()
        meta["variables"].append(name)
    for name in _LAST:
        value = getattr(model, name, None)
        if value is not None:
            arrays[f"last/{name}"] = np.asarray(value)
            meta["last"].append(name)
    if vecnorm is not None:
        meta["normalization"] = {
            **normalisation_data(vecnorm, arrays),
            "training": bool(vecnorm.training),
        }
    buffer = getattr(model, "replay_buffer", None)
    if buffer is not None:
        for name in _REPLAY:
            if getattr(buffer, name, None) is not None:
                arrays[f"replay/{name}"] = np.asarray(getattr(buffer, name))
        meta["replay_buffer"] = {"pos": int(buffer.pos), "full": bool(buffer.full)}
    text = json.dumps(meta, indent=1, sort_keys=True, allow_nan=False) + "\n"
    return {TRAINING: text.encode("utf-8"), TRAINING_ARRAYS: npz_bytes(arrays)}


def read_training(files: dict[str, bytes]) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The JSON and arrays of :func:`training_files` (the unit's manifest checked them)."""
    try:
        meta = json.loads(files[TRAINING].decode("utf-8"))
    except (KeyError, ValueError) as exc:
        raise DockError(f"checkpoint {TRAINING} unreadable: {exc}") from None
    return meta, read_arrays(files[TRAINING_ARRAYS], f"checkpoint {TRAINING_ARRAYS}")


def normaliser_for(venv, meta: dict[str, Any], arrays: dict[str, np.ndarray]):
    """``venv`` wrapped in the ``VecNormalize`` a checkpoint records (its statistics, settings
    and training flag)."""
    from stable_baselines3.common.vec_env import VecNormalize

    n = meta
    vecnorm = VecNormalize(
        venv,
        training=n["training"],
        norm_obs=n["norm_obs"],
        norm_reward=n["norm_reward"],
        clip_obs=n["clip_obs"],
        clip_reward=n["clip_reward"],
        gamma=n["gamma"],
        epsilon=n["epsilon"],
    )
    for name in ("obs_rms", "ret_rms"):
        rms = getattr(vecnorm, name)
        rms.mean = arrays[f"{name}/mean"].copy()
        rms.var = arrays[f"{name}/var"].copy()
    vecnorm.obs_rms.count, vecnorm.ret_rms.count = n["obs_count"], n["ret_count"]
    return vecnorm


def restore_training(model, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
    """Put a checkpoint's training state into ``model``, built from the run's config.

    Raises:
        DockError: the state does not fit the model (another algorithm or network).
    """
    import torch

    if meta.get("algorithm") != type(model).__name__.lower():
        raise DockError(
            f"the checkpoint is of {meta.get('algorithm')!r}, the run's config trains "
            f"{type(model).__name__}"
        )
    params = {"policy": {k: torch.tensor(arrays[f"policy/{k}"]) for k in meta["policy"]}}
    for name, opt in meta["optimizers"].items():
        params[name] = _optimizer_state(opt, arrays)
    try:
        model.set_parameters(params, exact_match=True, device="cpu")
    except (ValueError, RuntimeError, KeyError) as exc:
        raise DockError(f"the checkpoint does not fit the run's network: {exc}") from None
    for name in meta["variables"]:
        getattr(model, name).data = torch.tensor(arrays[f"var/{name}"])
    for key, value in meta["counters"].items():
        if key in _COUNTERS:
            setattr(model, key, value)
    for name in _LAST:
        setattr(model, name, arrays[f"last/{name}"].copy() if name in meta["last"] else None)
    if meta["replay_buffer"] is not None:
        buffer = model.replay_buffer
        for name in _REPLAY:
            if f"replay/{name}" in arrays:
                got, want = arrays[f"replay/{name}"], getattr(buffer, name)
                if want is None or got.shape != want.shape:
                    raise DockError("the checkpoint's replay buffer does not fit the run's")
                setattr(buffer, name, got.copy())
        buffer.pos, buffer.full = meta["replay_buffer"]["pos"], meta["replay_buffer"]["full"]


# ----------------------------------------------------------------------------- version 1


def load_model(algo_cls, data: bytes, env=None):
    """An SB3 model from a version-1 checkpoint's ``model.zip`` (or a best/ ``policy.zip``)
    on ``env``, on the CPU. Unpickles: only for a run folder the user trusts."""
    with legacy_module_paths():
        return algo_cls.load(io.BytesIO(data), env=env, device="cpu")


def rng_state(model) -> dict[str, Any]:
    """The states of every random generator training draws from (JSON-serialisable)."""
    import torch

    # SB3 draws minibatches from the legacy global generator
    name, keys, pos, has_gauss, cached = np.random.get_state()  # noqa: NPY002
    version, internal, gauss_next = random.getstate()
    space = getattr(model.action_space, "_np_random", None)
    return {
        "python": [version, list(internal), gauss_next],
        "numpy": [name, keys.tolist(), int(pos), int(has_gauss), float(cached)],
        "torch": base64.b64encode(torch.get_rng_state().numpy().tobytes()).decode("ascii"),
        "action_space": None if space is None else space.bit_generator.state,
    }


@contextlib.contextmanager
def global_rng_kept() -> Iterator[None]:
    """Run the block, then put Python's, NumPy's legacy and torch's global generators back as
    they were: SB3's ``load`` reseeds them with the saved model's seed, which in the trainer's
    process (an evaluation share run there) would change the training's own draws."""
    import torch

    py, legacy, th = random.getstate(), np.random.get_state(), torch.get_rng_state()  # noqa: NPY002
    try:
        yield
    finally:
        random.setstate(py)
        np.random.set_state(legacy)  # noqa: NPY002
        torch.set_rng_state(th)


def restore_rng(model, state: dict[str, Any]) -> None:
    """Put the generators of :func:`rng_state` back (after loading, which reseeds them)."""
    import torch

    version, internal, gauss_next = state["python"]
    random.setstate((version, tuple(internal), gauss_next))
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))  # noqa: NPY002
    raw = np.frombuffer(base64.b64decode(state["torch"]), dtype=np.uint8).copy()
    torch.set_rng_state(torch.from_numpy(raw))
    if state.get("action_space") is not None:
        model.action_space.seed(0)  # creates the generator, then its state is replaced
        model.action_space._np_random.bit_generator.state = state["action_space"]


# ----------------------------------------------------------------------------- units


@dataclass(frozen=True)
class Unit:
    """A verified checkpoint read back: its step, files (name -> bytes) and ``state.json``."""

    path: Path
    step: int
    files: dict[str, bytes]
    state: dict[str, Any]


class DamagedUnit(Exception):
    """A checkpoint folder that fails its manifest (the message says why)."""


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_unit(
    checkpoints: Path, step: int, files: dict[str, bytes], state: dict[str, Any]
) -> Path:
    """Write a checkpoint folder atomically (module docstring); returns its path.

    An existing unit of the same step (a resumed run saving the step it resumed from again) is
    replaced only after the new one is complete.
    """
    checkpoints.mkdir(parents=True, exist_ok=True)
    name = unit_name(step)
    tmp = temp_sibling(checkpoints / name, folder=True)
    try:
        body = {**files, STATE: (json.dumps(state, indent=1, sort_keys=True) + "\n").encode()}
        entries = {}
        for rel, data in sorted(body.items()):
            p = tmp / rel
            p.parent.mkdir(parents=True, exist_ok=True)
            with p.open("wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            entries[rel] = {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
        manifest = {"format": FORMAT, "version": VERSION, "step": step, "files": entries}
        with (tmp / MANIFEST).open("w", encoding="utf-8") as fh:
            json.dump(manifest, fh, indent=1, sort_keys=True)
            fh.write("\n")
            fh.flush()
            os.fsync(fh.fileno())
        _fsync_dir(tmp)
        final = checkpoints / name
        check_output_dir(final, "checkpoint")  # a device, FIFO or loop there is not replaced
        if os.path.lexists(final):
            old = checkpoints / f".{name}.{os.getpid()}.replaced{TEMP_MARK}"
            os.replace(final, old)
            os.replace(tmp, final)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, final)
        _fsync_dir(checkpoints)
        return final
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def read_unit(path: Path) -> Unit:
    """Read and verify one checkpoint folder.

    Raises:
        DamagedUnit: no or unreadable manifest, a missing file, a size or checksum mismatch.
    """
    try:
        manifest = json.loads((path / MANIFEST).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DamagedUnit("no manifest.json: written incompletely") from None
    except (OSError, ValueError) as exc:
        raise DamagedUnit(f"unreadable manifest.json ({exc})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise DamagedUnit("manifest.json is not a uwdock checkpoint manifest")
    if manifest.get("version") not in READ_VERSIONS:
        raise DamagedUnit(f"checkpoint format version {manifest.get('version')} (need {VERSION})")
    files: dict[str, bytes] = {}
    for rel, meta in dict(manifest.get("files", {})).items():
        try:
            data = (path / rel).read_bytes()
        except OSError as exc:
            raise DamagedUnit(f"{rel}: {exc.strerror or exc}") from None
        if len(data) != meta.get("bytes") or hashlib.sha256(data).hexdigest() != meta.get("sha256"):
            raise DamagedUnit(f"{rel} is {len(data)} bytes, its checksum does not match")
        files[rel] = data
    if STATE not in files:
        raise DamagedUnit("no state.json")
    state = json.loads(files.pop(STATE))
    return Unit(path, int(manifest["step"]), files, state)


def list_units(checkpoints: Path) -> list[tuple[int, Path]]:
    """(step, folder) of the checkpoint folders, newest first (unverified)."""
    out = []
    if checkpoints.is_dir():
        for p in checkpoints.iterdir():
            m = _UNIT_RE.match(p.name)
            if m and p.is_dir():
                out.append((int(m.group(1)), p))
    return sorted(out, reverse=True)


def latest_unit(checkpoints: Path, note: Callable[[str], None] | None = None) -> Unit | None:
    """The newest checkpoint that verifies; damaged newer ones are reported through ``note``
    and skipped. None when there is none."""
    for _step, path in list_units(checkpoints):
        try:
            return read_unit(path)
        except DamagedUnit as exc:
            if note is not None:
                note(f"checkpoint {path.name} is damaged ({exc}); using the one before it")
    return None


def has_legacy_checkpoints(checkpoints: Path) -> bool:
    """Checkpoints of the format before units (``step_N.zip`` files)."""
    return checkpoints.is_dir() and any(checkpoints.glob("step_*.zip"))
