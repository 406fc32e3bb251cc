"""The policy file format: a trained policy as data, loaded without running any code from it.

A policy folder holds two files (beside its run's ``config.toml`` and records):

* ``model.json``: what the network is (algorithm, policy class, layer sizes, activation,
  observation and action spaces), its observation normalisation's settings, the SHA-256 of
  ``weights.npz``, and the format's name and version;
* ``weights.npz``: the network's parameters and the normalisation statistics, NumPy arrays
  only (read with ``allow_pickle=False``), written with fixed zip timestamps so the same weights
  give the same bytes.

Loading rebuilds the policy from ``model.json`` through a fixed table of known classes (no
name in the file is imported), then copies the arrays in. SB3's own ``policy.zip`` and a pickled
``vecnormalize.pkl`` can run code when read (its ``data`` entry and the pickle are
cloudpickled); they are read by one command only, ``rl convert-policy --trust-pickle``, which
writes this format.
"""

from __future__ import annotations

import hashlib
import importlib
import io
import json
import math
import os
import sys
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_files, check_regular_file, read_text

FORMAT = "uwdock.policy"
VERSION = 1
MODEL = "model.json"
WEIGHTS = "weights.npz"
#: the files of the legacy (pickled) format, refused by the loaders
LEGACY = ("policy.zip", "vecnormalize.pkl")
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)
#: the largest weights file read (the shipped ones are ~0.1 MB)
MAX_WEIGHTS_BYTES = 256 * 1024 * 1024
_ALGORITHMS = ("ppo", "sac")
#: The modules a pickled-format file may name by path (SB3's cloudpickled ``data`` entry names
#: its policy class), where they live since ``rl`` was split into rooms.
LEGACY_MODULES = {"uwdock.rl.asymmetric": "uwdock.rl.policy.asymmetric"}

# ----------------------------------------------------------------------------- known classes


def _policy_classes() -> dict[str, type]:
    from stable_baselines3.common.policies import ActorCriticPolicy
    from stable_baselines3.sac.policies import SACPolicy

    from uwdock.rl.policy.asymmetric import AsymmetricPolicy  # torch and SB3 at module level

    return {
        "ActorCriticPolicy": ActorCriticPolicy,
        "AsymmetricPolicy": AsymmetricPolicy,
        "SACPolicy": SACPolicy,
    }


def _class_tables() -> dict[str, dict[str, type]]:
    """Constructor arguments that are classes: name -> class, the only ones a file may name."""
    import torch
    from stable_baselines3.common.torch_layers import FlattenExtractor

    acts = ("Tanh", "ReLU", "ELU", "LeakyReLU", "GELU", "SiLU", "Softplus", "Identity")
    return {
        "activation_fn": {n: getattr(torch.nn, n) for n in acts},
        "optimizer_class": {"Adam": torch.optim.Adam, "AdamW": torch.optim.AdamW},
        "features_extractor_class": {"FlattenExtractor": FlattenExtractor},
    }


#: constructor arguments that are plain JSON values
_PLAIN = {
    "net_arch",
    "use_sde",
    "log_std_init",
    "squash_output",
    "full_std",
    "use_expln",
    "ortho_init",
    "normalize_images",
    "optimizer_kwargs",
    "features_extractor_kwargs",
    "share_features_extractor",
    "n_critics",
    "clip_mean",
    "actor_obs_dim",
}
#: constructor arguments rebuilt from elsewhere (spaces) or not needed to predict
_REBUILT = {"observation_space", "action_space", "lr_schedule"}


# ----------------------------------------------------------------------------- writing


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """An ``.npz`` (what ``np.load`` reads) with fixed timestamps, in key order: same arrays,
    same bytes."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for key in sorted(arrays):
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asarray(arrays[key], order="C"), allow_pickle=False)
            info = zipfile.ZipInfo(key + ".npy", date_time=_ZIP_TIME)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue())
    return out.getvalue()


def _space(space: Any, name: str, arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    from gymnasium import spaces

    if not isinstance(space, spaces.Box):
        raise DockError(f"the policy's {name} is a {type(space).__name__}: only Box is supported")
    arrays[f"{name}/low"] = np.asarray(space.low)
    arrays[f"{name}/high"] = np.asarray(space.high)
    return {"type": "Box", "shape": [int(n) for n in space.shape], "dtype": str(space.dtype)}


def _constructor(policy: Any) -> dict[str, Any]:
    tables = _class_tables()
    out: dict[str, Any] = {}
    for key, value in policy._get_constructor_parameters().items():
        if key in _REBUILT:
            continue
        if key in tables:
            names = [n for n, cls in tables[key].items() if cls is value]
            if not names:
                raise DockError(f"the policy's {key} {value!r} has no name in the policy format")
            out[key] = names[0]
        elif key in _PLAIN:
            out[key] = value
        else:
            raise DockError(f"the policy's constructor argument {key!r} is not in the format")
    try:
        json.dumps(out, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise DockError(f"the policy's constructor arguments are not plain data: {exc}") from None
    return out


def normalisation_data(vecnorm: Any, arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    """A ``VecNormalize``'s settings and counts (JSON), its statistics into ``arrays``."""
    for name in ("obs_rms", "ret_rms"):
        rms = getattr(vecnorm, name)
        arrays[f"{name}/mean"] = np.asarray(rms.mean, dtype=np.float64)
        arrays[f"{name}/var"] = np.asarray(rms.var, dtype=np.float64)
    return {
        "norm_obs": bool(vecnorm.norm_obs),
        "norm_reward": bool(vecnorm.norm_reward),
        "clip_obs": float(vecnorm.clip_obs),
        "clip_reward": float(vecnorm.clip_reward),
        "gamma": float(vecnorm.gamma),
        "epsilon": float(vecnorm.epsilon),
        "obs_count": float(vecnorm.obs_rms.count),
        "ret_count": float(vecnorm.ret_rms.count),
    }


def policy_files(model: Any, vecnorm: Any | None) -> dict[str, bytes]:
    """``model.json`` and ``weights.npz`` of an SB3 model (PPO or SAC, or a
    :class:`LoadedPolicy`) and its normalisation (a ``VecNormalize`` or None): name -> bytes,
    the same bytes for the same weights."""
    import torch

    algorithm = model.algorithm if isinstance(model, LoadedPolicy) else type(model).__name__.lower()
    policy = model.policy
    classes = {cls: name for name, cls in _policy_classes().items()}
    if algorithm not in _ALGORITHMS or type(policy) not in classes:
        raise DockError(
            f"cannot write a {type(model).__name__} with a {type(policy).__name__}: the policy "
            f"format holds PPO or SAC with {', '.join(sorted(classes.values()))}"
        )
    arrays: dict[str, np.ndarray] = {}
    for key, tensor in policy.state_dict().items():
        arrays[f"policy/{key}"] = (
            tensor.detach().cpu().numpy() if torch.is_tensor(tensor) else (np.asarray(tensor))
        )
    meta: dict[str, Any] = {
        "format": FORMAT,
        "version": VERSION,
        "algorithm": algorithm,
        "policy_class": classes[type(policy)],
        "policy_kwargs": _constructor(policy),
        "observation_space": _space(policy.observation_space, "observation_space", arrays),
        "action_space": _space(policy.action_space, "action_space", arrays),
        "num_timesteps": int(getattr(model, "num_timesteps", 0)),
        "normalization": None,
    }
    if vecnorm is not None:
        meta["normalization"] = normalisation_data(vecnorm, arrays)
    weights = npz_bytes(arrays)
    meta["weights_sha256"] = hashlib.sha256(weights).hexdigest()
    text = json.dumps(meta, indent=2, sort_keys=True, allow_nan=False) + "\n"
    return {MODEL: text.encode("utf-8"), WEIGHTS: weights}


def write_policy(folder: str | os.PathLike[str], model: Any, vecnorm: Any | None) -> Path:
    """Write ``folder``/model.json and weights.npz as one unit; the folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    files = policy_files(model, vecnorm)
    atomic_write_files({folder / WEIGHTS: files[WEIGHTS], folder / MODEL: files[MODEL]})
    return folder


# ----------------------------------------------------------------------------- reading


@dataclass
class LoadedPolicy:
    """A policy read from the format: SB3's policy network (``predict`` as the algorithm's),
    its algorithm's name ("ppo" or "sac") and training steps."""

    algorithm: str
    policy: Any
    num_timesteps: int

    @property
    def observation_space(self) -> Any:
        return self.policy.observation_space

    @property
    def action_space(self) -> Any:
        return self.policy.action_space

    @property
    def actor(self) -> Any:
        """SAC's actor network (PPO has none)."""
        return self.policy.actor

    def predict(self, observation: np.ndarray, state=None, episode_start=None, deterministic=False):
        return self.policy.predict(observation, state, episode_start, deterministic)


def is_policy_folder(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a folder in the format (or its ``model.json``)."""
    p = Path(path)
    return (p / MODEL).is_file() if p.is_dir() else (p.name == MODEL and p.is_file())


def legacy_refusal(path: Path) -> DockError:
    """The one line for a folder or file in the pickled format."""
    folder = path if path.is_dir() else path.parent
    return DockError(
        f"policy {path} is in the pickled format (policy.zip, vecnormalize.pkl), which can run "
        f"code when loaded: if you trust where it came from, convert it once with `rl "
        f"convert-policy {folder} --trust-pickle --out NEW_FOLDER` and load NEW_FOLDER"
    )


def _read_model(path: Path) -> dict[str, Any]:
    check_regular_file(path, "policy model file")
    try:
        if path.stat().st_size > 1024 * 1024:
            raise ValueError("larger than 1 MiB")
        data = path.read_bytes()
    except (OSError, ValueError) as exc:
        raise DockError(f"cannot read policy model {path}: {exc}") from None
    return _parse_model(data, path)


def _parse_model(data: bytes, path: Path | str) -> dict[str, Any]:
    try:
        meta = json.loads(data.decode("utf-8"), parse_constant=_no_constant)
    except (ValueError, RecursionError) as exc:
        raise DockError(f"cannot read policy model {path}: {exc}") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise DockError(f"{path} is not a policy model file (format {FORMAT!r})")
    if meta.get("version") != VERSION:
        raise DockError(
            f"{path}: policy format version {meta.get('version')!r}, this toolkit reads {VERSION}"
        )
    return meta


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number")


def _read_weights(path: Path, sha256: Any) -> dict[str, np.ndarray]:
    check_regular_file(path, "policy weights file")
    try:
        if path.stat().st_size > MAX_WEIGHTS_BYTES:
            raise DockError(f"policy weights {path} are larger than {MAX_WEIGHTS_BYTES >> 20} MiB")
        data = path.read_bytes()
    except OSError as exc:
        raise DockError(f"cannot read policy weights {path}: {exc.strerror or exc}") from None
    return _parse_weights(data, sha256, path)


def _parse_weights(data: bytes, sha256: Any, path: Path | str) -> dict[str, np.ndarray]:
    if hashlib.sha256(data).hexdigest() != sha256:
        raise DockError(
            f"policy weights {path} differ from the SHA-256 its {MODEL} records (damaged or "
            "replaced)"
        )
    return read_arrays(data, f"policy weights {path}")


def read_arrays(data: bytes, what: str) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` (``allow_pickle=False``: an object array is refused)."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            return {k: npz[k] for k in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise DockError(f"cannot read {what}: {exc}") from None


def _box(meta: Any, name: str, arrays: dict[str, np.ndarray], where: Path) -> Any:
    from gymnasium import spaces

    if not isinstance(meta, dict) or meta.get("type") != "Box":
        raise DockError(f"{where}: {name} is not a Box")
    shape, dtype = meta.get("shape"), meta.get("dtype")
    if (
        not isinstance(shape, list)
        or not all(isinstance(n, int) and 0 < n <= 100_000 for n in shape)
        or dtype not in ("float32", "float64")
    ):
        raise DockError(f"{where}: {name} has a bad shape or dtype ({shape!r}, {dtype!r})")
    low, high = arrays.get(f"{name}/low"), arrays.get(f"{name}/high")
    if low is None or high is None or low.shape != tuple(shape) or high.shape != tuple(shape):
        raise DockError(f"{where}: {name} bounds missing or not of shape {tuple(shape)}")
    return spaces.Box(low=low, high=high, shape=tuple(shape), dtype=np.dtype(dtype))


def _kwargs(meta: Any, where: Path) -> dict[str, Any]:
    if not isinstance(meta, dict):
        raise DockError(f"{where}: policy_kwargs is not a table")
    tables = _class_tables()
    out: dict[str, Any] = {}
    for key, value in meta.items():
        if key in tables:
            if value not in tables[key]:
                raise DockError(
                    f"{where}: {key} {value!r} is not one of {', '.join(sorted(tables[key]))}"
                )
            out[key] = tables[key][value]
        elif key in _PLAIN:
            out[key] = value
        else:
            raise DockError(f"{where}: unknown policy argument {key!r}")
    return out


def _finite(values: dict[str, Any], where: Path) -> None:
    for key, value in values.items():
        if isinstance(value, float) and not math.isfinite(value):
            raise DockError(f"{where}: {key} is not finite")


def _normaliser(meta: Any, arrays: dict[str, np.ndarray], obs_space: Any, act_space: Any, where):
    """A ``VecNormalize`` (no env attached: ``set_venv`` attaches one) from its data."""
    from stable_baselines3.common.running_mean_std import RunningMeanStd
    from stable_baselines3.common.vec_env import VecNormalize

    keys = {
        "norm_obs": bool,
        "norm_reward": bool,
        "clip_obs": float,
        "clip_reward": float,
        "gamma": float,
        "epsilon": float,
        "obs_count": float,
        "ret_count": float,
    }
    if not isinstance(meta, dict) or set(meta) != set(keys):
        raise DockError(f"{where}: normalization must hold exactly {', '.join(sorted(keys))}")
    for key, tp in keys.items():
        ok = (
            isinstance(meta[key], bool)
            if tp is bool
            else (isinstance(meta[key], (int, float)) and not isinstance(meta[key], bool))
        )
        if not ok:
            raise DockError(f"{where}: normalization.{key} is not a {tp.__name__}")
    _finite({k: float(meta[k]) for k in keys if keys[k] is float}, where)
    if meta["epsilon"] <= 0 or meta["clip_obs"] <= 0 or meta["obs_count"] <= 0:
        raise DockError(f"{where}: normalization epsilon, clip_obs and obs_count must be > 0")
    dim = obs_space.shape

    def rms(name: str, shape: tuple, count: float) -> Any:
        mean, var = arrays.get(f"{name}/mean"), arrays.get(f"{name}/var")
        if mean is None or var is None or mean.shape != shape or var.shape != shape:
            raise DockError(f"{where}: {name} statistics missing or not of shape {shape}")
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(var)) and np.all(var >= 0)):
            raise DockError(f"{where}: {name} statistics hold NaN, infinity or a negative variance")
        out = RunningMeanStd(shape=shape)
        out.mean, out.var, out.count = mean.astype(np.float64), var.astype(np.float64), count
        return out

    state = {
        "num_envs": 1,
        "observation_space": obs_space,
        "action_space": act_space,
        "render_mode": None,
        "norm_obs": meta["norm_obs"],
        "norm_obs_keys": None,
        "obs_rms": rms("obs_rms", dim, float(meta["obs_count"])),
        "ret_rms": rms("ret_rms", (), float(meta["ret_count"])),
        "clip_obs": float(meta["clip_obs"]),
        "clip_reward": float(meta["clip_reward"]),
        "gamma": float(meta["gamma"]),
        "epsilon": float(meta["epsilon"]),
        "training": False,
        "norm_reward": meta["norm_reward"],
        "old_reward": np.array([]),
        "old_obs": np.array([]),
    }
    vecnorm = VecNormalize.__new__(VecNormalize)
    vecnorm.__setstate__(state)  # what unpickling does, from checked data
    vecnorm.returns = np.zeros(1)
    return vecnorm


SUMS = "checksums.sha256"


def check_folder_sums(folder: Path) -> None:
    """Check the policy files a folder's ``checksums.sha256`` lists (``sha256sum`` lines; other
    files it lists are not read here)."""
    sums = folder / SUMS
    if not sums.exists():
        return
    check_regular_file(sums, "checksum file")
    for n, line in enumerate(read_text(sums, "checksum file").splitlines(), 1):
        if not line.strip():
            continue
        digest, sep, name = line.partition("  ")
        if not sep or len(digest) != 64:
            raise DockError(f"{sums}, line {n}: not a `sha256sum` line")
        if name not in (MODEL, WEIGHTS, "config.toml"):
            continue
        try:
            data = (folder / name).read_bytes()
        except OSError as exc:
            raise DockError(f"{sums} lists {name}, which cannot be read: {exc.strerror}") from None
        if hashlib.sha256(data).hexdigest() != digest.lower():
            raise DockError(
                f"policy {folder}: {name} differs from its {SUMS} (damaged or replaced)"
            )


def read_policy(path: str | os.PathLike[str]) -> tuple[LoadedPolicy, Any | None]:
    """The policy of a folder in the format (or its ``model.json``) and its normalisation (a
    ``VecNormalize`` without env, or None); no code from the folder runs.

    Raises:
        DockError: one line for a missing, damaged, unknown or non-finite policy.
    """
    p = Path(path)
    folder = p if p.is_dir() else p.parent
    model_path = folder / MODEL
    check_folder_sums(folder)
    meta = _read_model(model_path)
    arrays = _read_weights(folder / WEIGHTS, meta.get("weights_sha256"))
    return _build(meta, arrays, model_path)


def policy_from_files(files: dict[str, bytes]) -> tuple[LoadedPolicy, Any | None]:
    """:func:`read_policy` of the files :func:`policy_files` gave (name -> bytes)."""
    meta = _parse_model(files[MODEL], MODEL)
    return _build(meta, _parse_weights(files[WEIGHTS], meta.get("weights_sha256"), WEIGHTS), MODEL)


def _build(meta: dict[str, Any], arrays: dict[str, np.ndarray], model_path: Path | str):
    import torch

    folder = Path(model_path).parent
    algorithm, cls_name = meta.get("algorithm"), meta.get("policy_class")
    classes = _policy_classes()
    if algorithm not in _ALGORITHMS or cls_name not in classes:
        raise DockError(
            f"{model_path}: unknown algorithm or policy class ({algorithm!r}, {cls_name!r})"
        )
    obs_space = _box(meta.get("observation_space"), "observation_space", arrays, model_path)
    act_space = _box(meta.get("action_space"), "action_space", arrays, model_path)
    kwargs = _kwargs(meta.get("policy_kwargs"), model_path)
    try:
        policy = classes[cls_name](obs_space, act_space, lambda _: 0.0, **kwargs)
    except (TypeError, ValueError, RuntimeError, KeyError, IndexError) as exc:
        raise DockError(f"{model_path}: cannot build the policy: {exc}") from None
    state = {k[len("policy/") :]: v for k, v in arrays.items() if k.startswith("policy/")}
    expected = policy.state_dict()
    if set(state) != set(expected):
        missing = sorted(set(expected) - set(state))[:3]
        extra = sorted(set(state) - set(expected))[:3]
        raise DockError(
            f"{folder / WEIGHTS}: weights do not fit the network (missing "
            f"{missing}, unexpected {extra})"
        )
    tensors = {}
    for key, ref in expected.items():
        arr = state[key]
        if arr.shape != tuple(ref.shape) or arr.dtype.kind not in "fiub":
            raise DockError(
                f"{folder / WEIGHTS}: weight {key} has shape {arr.shape}, the "
                f"network {tuple(ref.shape)}"
            )
        if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            raise DockError(f"policy {folder}: weight {key} holds NaN or infinity")
        tensors[key] = torch.as_tensor(arr, dtype=ref.dtype)
    policy.load_state_dict(tensors)
    policy.set_training_mode(False)
    vecnorm = None
    if meta.get("normalization") is not None:
        vecnorm = _normaliser(meta["normalization"], arrays, obs_space, act_space, model_path)
    steps = meta.get("num_timesteps", 0)
    return LoadedPolicy(algorithm, policy, steps if isinstance(steps, int) else 0), vecnorm


def require_finite_policy(model, what: str) -> None:
    """Raise DockError when any weight of ``model``'s policy is NaN or infinite."""
    import torch

    for name, tensor in model.policy.state_dict().items():
        if torch.is_floating_point(tensor) and not bool(torch.isfinite(tensor).all()):
            raise DockError(f"{what}: weight {name} holds NaN or infinity")


@contextmanager
def legacy_module_paths() -> Iterator[None]:
    """While reading a pickled-format file (``rl convert-policy``, a version-1 checkpoint), the
    module paths it was written under (:data:`LEGACY_MODULES`) name their modules' new places;
    afterwards they name nothing again."""
    added = []
    for old, new in LEGACY_MODULES.items():
        if old not in sys.modules:
            sys.modules[old] = importlib.import_module(new)
            added.append(old)
    try:
        yield
    finally:
        for old in added:
            sys.modules.pop(old, None)
