"""Loading a policy never runs code from its folder (``rl.policy.policy_format``): crafted payloads
in every file of a policy folder, through every command that loads one; the shipped policies load
from the data format with the actions they had."""

from __future__ import annotations

import base64
import hashlib
import io
import json
import os
import pickle
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

from uwdock.dockcore.errors import DockError
from uwdock.rl import cli
from uwdock.rl.policy.policy_format import npz_bytes

ROOT = Path(__file__).resolve().parent.parent
SHIPPED = ROOT / "rl" / "policies" / "realistic_ppo"


class _Payload:
    """Unpickling this runs ``touch <marker>``."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch '{self.marker}'",))


def _one_error(res) -> str:
    assert res.code == 2, (res.code, res.err)
    errors = [line for line in res.err.splitlines() if line.startswith("error")]
    assert len(errors) == 1 and "Traceback" not in res.err, res.err
    return errors[0]


@pytest.fixture(scope="module")
def legacy_zip(tmp_path_factory) -> bytes:
    """A genuine SB3 ``policy.zip`` (PPO, the shipped policy's spaces)."""
    import gymnasium as gym
    from stable_baselines3 import PPO

    class _Env(gym.Env):
        observation_space = gym.spaces.Box(-5.0, 5.0, (18,), np.float32)
        action_space = gym.spaces.Box(-1.0, 1.0, (6,), np.float32)

    path = tmp_path_factory.mktemp("legacy") / "policy.zip"
    PPO("MlpPolicy", _Env(), n_steps=8, batch_size=8, device="cpu", seed=0).save(path)
    return path.read_bytes()


def _crafted_folder(tmp_path: Path, legacy_zip: bytes, marker: Path, safe: bool) -> Path:
    """A policy folder whose pickled files run the payload when read: SB3's ``data`` entry
    (its observation space is cloudpickled) and ``vecnormalize.pkl``; ``safe``: the data
    format's files beside them too."""
    folder = tmp_path / ("mixed" if safe else "legacy")
    folder.mkdir()
    src = zipfile.ZipFile(io.BytesIO(legacy_zip))
    data = json.loads(src.read("data"))
    blob = base64.b64encode(pickle.dumps(_Payload(marker))).decode()
    data["observation_space"][":serialized:"] = blob
    with zipfile.ZipFile(folder / "policy.zip", "w") as dst:
        for info in src.infolist():
            body = json.dumps(data).encode() if info.filename == "data" else src.read(info)
            dst.writestr(info, body)
    (folder / "vecnormalize.pkl").write_bytes(pickle.dumps(_Payload(marker)))
    shutil.copy(SHIPPED / "config.toml", folder / "config.toml")
    if safe:
        for name in ("model.json", "weights.npz"):
            shutil.copy(SHIPPED / name, folder / name)
    return folder


def test_the_crafted_pickles_do_run_when_unpickled(tmp_path, legacy_zip):
    """The payloads are live: unpickling either file creates the marker (so the tests below,
    where it stays absent, show the loaders never unpickle)."""
    from stable_baselines3 import PPO

    marker = tmp_path / "ran"
    folder = _crafted_folder(tmp_path, legacy_zip, marker, safe=False)
    pickle.loads((folder / "vecnormalize.pkl").read_bytes())
    assert marker.exists()
    marker.unlink()
    try:
        PPO.load(folder / "policy.zip", device="cpu")
    except Exception:  # the space is not a space once the payload ran
        pass
    assert marker.exists()


def test_no_command_runs_a_pickled_folder(run_cli, tmp_path, legacy_zip):
    """rl eval, rl export, rl train --init-policy and rl node refuse the pickled format in one
    line naming the conversion; the payload never runs."""
    from uwdock import cli as uwdock_cli

    marker = tmp_path / "ran"
    folder = _crafted_folder(tmp_path, legacy_zip, marker, safe=False)
    out = tmp_path / "out"
    for policy in (folder, folder / "policy.zip"):
        line = _one_error(run_cli(cli.main, "eval", "--policy", policy, "--episodes", "1",
                                  "--obs", "proxy", "--out", out))  # fmt: skip
        assert "pickled format" in line and "rl convert-policy" in line, line
        line = _one_error(run_cli(cli.main, "export", "--policy", policy, "--out", out / "p.onnx"))
        assert "pickled format" in line
        line = _one_error(run_cli(cli.main, "train", "--init-policy", policy, "--out", out))
        assert "pickled format" in line
    for policy in (folder / "policy.zip", folder / "vecnormalize.pkl"):
        line = _one_error(run_cli(uwdock_cli.rl, "node", "--policy", policy))
        assert "a pickle, which can run code" in line
    assert not out.exists()
    assert not marker.exists()
    # converting needs the user's word, before anything is read
    line = _one_error(run_cli(cli.main, "convert-policy", folder, "--out", out))
    assert "--trust-pickle" in line and not out.exists() and not marker.exists()


def test_pickles_beside_the_data_format_are_never_read(run_cli, tmp_path, legacy_zip):
    """A folder holding both formats loads from the data: the payloads stay unread and the
    actions are the shipped policy's."""
    from uwdock.rl.evaluate.episodes import SB3Controller
    from uwdock.rl.policy.policy_io import load_policy

    marker = tmp_path / "ran"
    folder = _crafted_folder(tmp_path, legacy_zip, marker, safe=True)
    obs = np.random.default_rng(0).normal(size=(64, 18)).astype(np.float32)
    got = SB3Controller(*load_policy(folder)).act_batch(obs)
    want = SB3Controller(*load_policy(SHIPPED)).act_batch(obs)
    assert np.array_equal(got, want)
    res = run_cli(cli.main, "export", "--policy", folder, "--out", tmp_path / "p.onnx")
    assert res.code == 0, res.err
    assert not marker.exists()


def _rewrite_model(folder: Path, change) -> None:
    meta = json.loads((folder / "model.json").read_text())
    change(meta)
    (folder / "model.json").write_text(json.dumps(meta))


def _copy_shipped(tmp_path: Path) -> Path:
    folder = tmp_path / "p"
    folder.mkdir()
    for name in ("model.json", "weights.npz", "config.toml"):
        shutil.copy(SHIPPED / name, folder / name)
    return folder


@pytest.mark.parametrize(
    "change, fragment",
    [
        (lambda m: m["policy_kwargs"].update(activation_fn="os.system"), "activation_fn"),
        (lambda m: m["policy_kwargs"].update(optimizer_class="builtins.eval"), "optimizer_class"),
        (lambda m: m["policy_kwargs"].update(features_extractor_class="x.Y"), "features_extractor"),
        (lambda m: m.update(policy_class="subprocess.Popen"), "unknown algorithm or policy class"),
        (lambda m: m["policy_kwargs"].update(exec_hook="print(1)"), "unknown policy argument"),
        (lambda m: m.update(format="uwdock.other"), "is not a policy model file"),
        (lambda m: m.update(version=99), "policy format version 99"),
        (lambda m: m["normalization"].update(clip_obs=float("nan")), "NaN is not a number"),
        (lambda m: m["normalization"].pop("epsilon"), "normalization must hold exactly"),
        (lambda m: m["observation_space"].update(shape=[10**9]), "bad shape or dtype"),
    ],
)
def test_a_crafted_model_file_is_refused_in_one_line(run_cli, tmp_path, change, fragment):
    """model.json names classes only from a fixed table; nothing it says is imported."""
    folder = _copy_shipped(tmp_path)
    _rewrite_model(folder, change)
    with pytest.raises(DockError, match=fragment):
        from uwdock.rl.policy.policy_io import load_policy

        load_policy(folder)
    out = tmp_path / "e"
    line = _one_error(run_cli(cli.main, "eval", "--policy", folder, "--episodes", "1",
                              "--obs", "proxy", "--out", out))  # fmt: skip
    assert fragment in line and not out.exists()


def test_an_object_array_in_the_weights_is_refused(tmp_path):
    """A .npy entry holding pickled objects is refused by NumPy's reader (allow_pickle=False),
    its payload unread, though model.json records the file's digest."""
    from uwdock.rl.policy.policy_io import load_policy

    marker = tmp_path / "ran"
    folder = _copy_shipped(tmp_path)
    arrays = dict(np.load(folder / "weights.npz", allow_pickle=False))
    buf = io.BytesIO()
    np.save(buf, np.array([_Payload(marker)], dtype=object), allow_pickle=True)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        zf.writestr("policy/action_net.bias.npy", buf.getvalue())
        for key, arr in arrays.items():
            if key != "policy/action_net.bias":
                a = io.BytesIO()
                np.save(a, arr)
                zf.writestr(key + ".npy", a.getvalue())
    data = out.getvalue()
    (folder / "weights.npz").write_bytes(data)
    _rewrite_model(folder, lambda m: m.update(weights_sha256=hashlib.sha256(data).hexdigest()))
    with pytest.raises(DockError, match="cannot read policy weights"):
        load_policy(folder)
    assert not marker.exists()


def test_the_folders_checksums_are_checked(tmp_path):
    from uwdock.rl.policy.policy_io import load_policy

    folder = _copy_shipped(tmp_path)
    shutil.copy(SHIPPED / "checksums.sha256", folder / "checksums.sha256")
    load_policy(folder)  # as shipped
    _rewrite_model(folder, lambda m: m.update(num_timesteps=1))  # digest still right inside
    with pytest.raises(DockError, match=r"model\.json differs from its checksums\.sha256"):
        load_policy(folder)
    (folder / "checksums.sha256").write_text("$(touch x)  model.json\n")
    with pytest.raises(DockError, match="not a `sha256sum` line"):
        load_policy(folder)


def test_weights_that_do_not_fit_the_network_are_refused(tmp_path):
    from uwdock.rl.policy.policy_io import load_policy

    folder = _copy_shipped(tmp_path)
    arrays = dict(np.load(folder / "weights.npz", allow_pickle=False))
    arrays["policy/action_net.weight"] = arrays["policy/action_net.weight"][:, :5]
    data = npz_bytes(arrays)
    (folder / "weights.npz").write_bytes(data)
    _rewrite_model(folder, lambda m: m.update(weights_sha256=hashlib.sha256(data).hexdigest()))
    with pytest.raises(DockError, match=r"weight action_net\.weight has shape"):
        load_policy(folder)


def test_the_shipped_policy_acts_as_its_onnx_export_of_the_pickled_original():
    """policy.onnx was exported from the pickled policy before the conversion: the data
    format's policy gives its actions (to float32 rounding), and exporting it again gives the
    same ONNX bytes."""
    from uwdock.rl.evaluate.episodes import SB3Controller
    from uwdock.rl.policy.policy_io import OnnxPolicy, load_policy

    obs = np.random.default_rng(1).normal(scale=2.0, size=(500, 18)).astype(np.float32)
    sb3 = SB3Controller(*load_policy(SHIPPED)).act_batch(obs)
    onnx = OnnxPolicy(SHIPPED / "policy.onnx")
    ref = np.stack([onnx.act(o) for o in obs])
    assert np.max(np.abs(sb3 - ref)) < 1e-5


def test_exporting_the_shipped_policy_again_gives_the_shipped_onnx(tmp_path):
    from uwdock.rl.policy.export import export_onnx

    written = export_onnx(SHIPPED, tmp_path / "policy.onnx")
    assert written.read_bytes() == (SHIPPED / "policy.onnx").read_bytes()


def test_writing_is_deterministic_and_reads_back_bit_for_bit(tmp_path):
    """The same weights give the same bytes; a read policy written again is the same file."""
    from uwdock.rl.policy.policy_format import policy_files, read_policy

    model, vecnorm = read_policy(SHIPPED)
    files = policy_files(model, vecnorm)
    assert files["weights.npz"] == (SHIPPED / "weights.npz").read_bytes()
    assert files["model.json"] == (SHIPPED / "model.json").read_bytes()


def test_a_policy_folder_works_from_any_current_folder(run_cli, tmp_path, monkeypatch):
    """The error model its config names (from the checkout's root) is found from the policy's
    folder, not the current one."""
    monkeypatch.chdir(tmp_path)
    env = tmp_path / "env.toml"
    env.write_text("episode_s = 1.0\n")
    for name in ("error_model_ppo", "realistic_ppo"):
        res = run_cli(cli.main, "eval", "--policy", ROOT / "rl" / "policies" / name,
                      "--obs", "error-model", "--episodes", "1", "--config", env,
                      "--videos", "", "--out", tmp_path / name)  # fmt: skip
        assert res.code == 0, res.err
        summary = json.loads((tmp_path / name / "summary.json").read_text())
        assert Path(summary["config"]["error_model_path"]).is_file()


def test_resuming_a_checkpoint_of_the_pickled_format_needs_the_users_word(
    run_cli, tmp_path, legacy_zip
):
    """Checkpoints are data too: a unit of format version 1 (SB3's zip, pickles) with a
    payload is refused in one line, unread, unless ``--trust-pickle``."""
    from uwdock.rl.train.checkpoint import FORMAT, MANIFEST

    cfg = tmp_path / "tiny.toml"
    cfg.write_text(
        "n_envs = 1\ntotal_steps = 64\ncheckpoint_every = 32\neval_every = 0\n"
        "[env]\nepisode_s = 2.0\n[ppo]\nn_steps = 32\nbatch_size = 32\nn_epochs = 1\n"
    )
    run = tmp_path / "run"
    assert run_cli(cli.main, "train", "--config", cfg, "--out", run).code == 0
    unit = run / "checkpoints" / "step_0000000064"
    assert sorted(p.name for p in unit.iterdir()) == [
        "manifest.json", "state.json", "training.json", "training.npz"
    ]  # fmt: skip
    marker = tmp_path / "ran"
    crafted = _crafted_folder(tmp_path, legacy_zip, marker, safe=False)
    files = {"model.zip": (crafted / "policy.zip").read_bytes(),
             "state.json": (unit / "state.json").read_bytes()}  # fmt: skip
    shutil.rmtree(unit)
    unit.mkdir()
    entries = {}
    for name, data in files.items():
        (unit / name).write_bytes(data)
        entries[name] = {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    manifest = {"format": FORMAT, "version": 1, "step": 64, "files": entries}
    (unit / MANIFEST).write_text(json.dumps(manifest))
    (run / "DONE").unlink()
    res = run_cli(cli.main, "train", "--out", run, "--resume")
    line = _one_error(res)
    assert "older version" in line and "--trust-pickle" in line, line
    assert not marker.exists()


def test_a_pickled_folder_from_before_the_rooms_converts(run_cli, tmp_path):
    """SB3's pickled ``data`` names the policy class by its module path: a folder saved while the
    asymmetric actor-critic was ``uwdock.rl.asymmetric`` (before ``rl`` had rooms) converts with
    the user's word, and the old path names nothing before or after."""
    import importlib
    import sys

    import gymnasium as gym
    from stable_baselines3 import PPO

    from uwdock.rl.policy.asymmetric import AsymmetricPolicy

    class _Env(gym.Env):
        observation_space = gym.spaces.Box(-5.0, 5.0, (18,), np.float32)
        action_space = gym.spaces.Box(-1.0, 1.0, (6,), np.float32)

    kw = {"policy_kwargs": {"actor_obs_dim": 13}, "n_steps": 8, "batch_size": 8, "seed": 0}
    buf = io.BytesIO()
    PPO(AsymmetricPolicy, _Env(), device="cpu", **kw).save(buf)
    src = zipfile.ZipFile(io.BytesIO(buf.getvalue()))
    data = json.loads(src.read("data"))
    old_ref = b"cuwdock.rl.asymmetric\nAsymmetricPolicy\n."  # pickle's GLOBAL, as SB3 wrote it
    data["policy_class"][":serialized:"] = base64.b64encode(old_ref).decode()
    folder = tmp_path / "old"
    folder.mkdir()
    with zipfile.ZipFile(folder / "policy.zip", "w") as dst:
        for info in src.infolist():
            body = json.dumps(data).encode() if info.filename == "data" else src.read(info)
            dst.writestr(info, body)
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("uwdock.rl.asymmetric")
    out = tmp_path / "converted"
    res = run_cli(cli.main, "convert-policy", str(folder), "--out", str(out), "--trust-pickle")
    assert res.code == 0, res.err
    assert json.loads((out / "model.json").read_text())["policy_class"] == "AsymmetricPolicy"
    assert "uwdock.rl.asymmetric" not in sys.modules
