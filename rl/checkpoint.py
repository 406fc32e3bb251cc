"""Training checkpoints as transactions.

A checkpoint is one folder ``checkpoints/step_<N>/`` holding everything a run needs to go on
exactly as if it had never stopped:

* ``model.zip``: the SB3 model (policy, optimiser, step counter, last observation), written
  byte-deterministically (fixed zip timestamps, no wall-clock fields), so two runs that reach
  the same state write the same bytes;
* ``vecnormalize.pkl``: the observation/reward normalisation, when the run normalises;
* ``replay_buffer.pkl``: SAC's replay buffer;
* ``best/policy.zip`` (+ ``best/vecnormalize.pkl``): the best evaluated policy so far;
* ``state.json``: the training schedule (next checkpoint, next evaluation), the evaluation
  state (best score and step, evaluations done), the critic warm-up phase and the random
  number generators (Python, NumPy, PyTorch, the action space);
* ``manifest.json``, written last: every file's size and SHA-256.

The folder is assembled under a hidden temporary name and renamed into place, so it either
exists complete or not at all; :func:`latest_unit` takes the newest unit whose manifest checks
out and falls back past damaged ones (a truncated file, a missing manifest), saying so.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import io
import json
import os
import pickle
import random
import re
import shutil
import sys
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import TEMP_MARK, temp_sibling

FORMAT = "uwdock.checkpoint"
VERSION = 1
MANIFEST = "manifest.json"
STATE = "state.json"
_UNIT_RE = re.compile(r"^step_(\d+)$")
#: SB3 attributes that hold wall-clock time, the folder's path or where this process started;
#: left out, so a checkpoint depends on the run's state only (the loader sets
#: ``tensorboard_log`` again).
_WALL_CLOCK = [
    "start_time",
    "ep_info_buffer",
    "ep_success_buffer",
    "tensorboard_log",
    "_num_timesteps_at_start",
]
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)


def unit_name(step: int) -> str:
    """The folder name of the checkpoint at environment step ``step``."""
    return f"step_{step:010d}"


# ----------------------------------------------------------------------------- byte formats


def _interned(obj: Any) -> Any:
    """``obj`` with every string in its dicts, lists and tuples interned."""
    if isinstance(obj, str):
        return sys.intern(obj)
    if isinstance(obj, dict):
        return {_interned(k): _interned(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_interned(v) for v in obj)
    return obj


def _canonical_torch(body: bytes) -> bytes:
    """A ``torch.save`` file re-saved from a canonical object graph.

    Pickle memoises by object identity, so equal states can serialise differently: an
    optimiser loaded from a checkpoint holds its state keys as unpickled strings, one that
    never stopped holds the interned literals of ``torch.optim``. Interning every string first
    makes the bytes depend on the content only.
    """
    import torch

    obj = torch.load(io.BytesIO(body), map_location="cpu", weights_only=False)
    out = io.BytesIO()
    torch.save(_interned(obj), out)
    return out.getvalue()


def _repack(data: bytes) -> bytes:
    """A zip with fixed timestamps, canonical torch files, and the memory addresses in SB3's
    readable ``data`` blurbs masked (only the ``:serialized:`` fields are read back)."""
    src = zipfile.ZipFile(io.BytesIO(data))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as dst:
        for info in src.infolist():
            body = src.read(info.filename)
            if info.filename == "data":
                body = re.sub(rb" at 0x[0-9a-f]+>", b" at 0x0>", body)
            elif info.filename.endswith(".pth"):
                body = _canonical_torch(body)
            zi = zipfile.ZipInfo(info.filename, date_time=_ZIP_TIME)
            zi.compress_type = info.compress_type
            zi.external_attr = 0o644 << 16
            dst.writestr(zi, body)
    return out.getvalue()


def model_bytes(model) -> bytes:
    """``model.save`` as deterministic bytes (same state -> same bytes)."""
    buf = io.BytesIO()
    model.save(buf, exclude=list(_WALL_CLOCK))
    return _repack(buf.getvalue())


def load_model(algo_cls, data: bytes, env=None):
    """An SB3 model from :func:`model_bytes`, on ``env`` (None: no env, to predict only), on
    the CPU."""
    return algo_cls.load(io.BytesIO(data), env=env, device="cpu")


def pickle_bytes(obj: Any) -> bytes:
    """``obj`` pickled without the memo ("fast" mode), so the bytes depend on its content only,
    not on which parts happen to share objects (a loaded and a live ``VecNormalize`` differ
    there). For acyclic objects (normalisation statistics, replay buffers)."""
    buf = io.BytesIO()
    pickler = pickle.Pickler(buf, protocol=4)
    pickler.fast = True
    pickler.dump(obj)
    return buf.getvalue()


def replay_buffer_bytes(model) -> bytes:
    return pickle_bytes(model.replay_buffer)


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
        if final.exists():
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
    if manifest.get("version") != VERSION:
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


def require_finite_policy(model, what: str) -> None:
    """Raise DockError when any weight of ``model``'s policy is NaN or infinite."""
    import torch

    for name, tensor in model.policy.state_dict().items():
        if torch.is_floating_point(tensor) and not bool(torch.isfinite(tensor).all()):
            raise DockError(f"{what}: weight {name} holds NaN or infinity")
