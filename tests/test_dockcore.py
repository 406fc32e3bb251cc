"""dockcore: config loading from TOML, atomic writes, provenance."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Literal

import pytest

from uwdock.dockcore.config import dumps_toml, from_dict, load_config, read_toml, replace, to_dict
from uwdock.dockcore.errors import ConfigError, DockError
from uwdock.dockcore.io import atomic_path, atomic_write_text, ensure_writable_dir
from uwdock.dockcore.provenance import write_provenance


@dataclass(frozen=True)
class Inner:
    """Test component. Attributes: gain (-), limits_n (N)."""

    gain: float = 1.0
    limits_n: tuple[float, float] = (-1.0, 1.0)

    def validate(self) -> None:
        if self.gain < 0:
            raise ValueError(f"gain: must be >= 0, got {self.gain}")


@dataclass(frozen=True)
class Outer:
    name: str = "x"
    steps: int = 3
    mode: Literal["a", "b"] = "a"
    scale: float | None = None
    inner: Inner = field(default_factory=Inner)
    table: dict[str, tuple[float, ...]] = field(default_factory=dict)


def write(tmp_path, text):
    p = tmp_path / "c.toml"
    p.write_text(text)
    return p


def test_defaults_file_and_overrides_layer(tmp_path):
    p = write(tmp_path, "steps = 5\n[inner]\ngain = 2\nlimits_n = [-3, 3]\n[table]\na = [1, 2]\n")
    cfg = load_config(Outer, p, overrides={"name": "y", "steps": None})
    assert cfg == Outer(name="y", steps=5, inner=Inner(2.0, (-3.0, 3.0)), table={"a": (1.0, 2.0)})
    assert isinstance(cfg.inner.gain, float)


@pytest.mark.parametrize(
    "text,message",
    [
        ("stepz = 1\n", "unknown config key 'stepz' for Outer"),
        ("[inner]\ngian = 1\n", "unknown config key 'inner.gian' for Inner"),
        ("steps = 1.5\n", "steps: expected an integer"),
        ("steps = true\n", "steps: expected an integer"),
        ("mode = 'c'\n", "mode: must be one of ['a', 'b']"),
        ("[inner]\nlimits_n = [1]\n", "inner.limits_n: expected 2 values"),
        ("[inner]\ngain = -1\n", "inner.gain: must be >= 0"),
        ("inner = 3\n", "inner: expected a table"),
        ("steps = \n", "malformed TOML"),
    ],
)
def test_bad_config_names_the_key(tmp_path, text, message):
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        load_config(Outer, write(tmp_path, text))


def test_missing_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        read_toml(tmp_path / "nope.toml")


def test_round_trip_through_toml_and_replace(tmp_path):
    cfg = Outer(scale=2.5, inner=Inner(3.0), table={"k": (1.0,)})
    p = write(tmp_path, dumps_toml(cfg))
    assert load_config(Outer, p) == cfg
    assert from_dict(Outer, to_dict(cfg)) == cfg
    assert replace(cfg, steps=9).steps == 9
    with pytest.raises(ConfigError, match="gain"):
        replace(cfg, inner={"gain": -2.0})


def test_atomic_write_leaves_old_file_on_failure(tmp_path):
    target = tmp_path / "a.txt"
    atomic_write_text(target, "old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("crash")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_ensure_writable_dir_fails_with_one_line(tmp_path):
    f = tmp_path / "f"
    f.write_text("")
    with pytest.raises(DockError, match="cannot write to output folder"):
        ensure_writable_dir(f / "sub")


def test_provenance_keeps_the_tree_state_the_process_first_read(monkeypatch):
    from uwdock.dockcore import provenance as P

    states = iter([{"commit": "a" * 40, "dirty": False}, {"commit": "a" * 40, "dirty": True}])
    monkeypatch.setattr(P, "git_commit", lambda: next(states))
    monkeypatch.setattr(P, "_GIT_AT_START", None)
    first = P.provenance()["git"]
    # the process then writes over a committed results file: the tree reads dirty now
    assert P.provenance()["git"] == first == {"commit": "a" * 40, "dirty": False}


def test_provenance_records_config_commit_versions(tmp_path):
    rec = write_provenance(tmp_path, {"outer": Outer(steps=7)})
    on_disk = json.loads((tmp_path / "provenance.json").read_text())
    assert on_disk["config"]["outer"]["steps"] == 7 == rec["config"]["outer"]["steps"]
    assert set(on_disk["git"]) == {"commit", "dirty"}
    assert on_disk["packages"]["numpy"]
    assert load_config(Outer, tmp_path / "config.toml", section="outer").steps == 7


def test_provenance_records_the_cpu_a_run_compiled_for(tmp_path):
    """The first processor's identity and a hash of its sorted flags: the same flags in another
    order hash alike, one flag more does not; an unreadable file gives {}."""
    from uwdock.dockcore.provenance import cpu_description

    block = (
        "processor\t: {i}\nvendor_id\t: AuthenticAMD\ncpu family\t: 25\nmodel\t\t: 1\n"
        "model name\t: AMD EPYC 7B13\nstepping\t: 1\nflags\t\t: {flags}\n\n"
    )
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    a.write_text(block.format(i=0, flags="fpu sse avx2") + block.format(i=1, flags="other"))
    b.write_text(block.format(i=0, flags="avx2 fpu sse"))
    c.write_text(block.format(i=0, flags="avx2 fpu sse avx512f"))
    da = cpu_description(a)
    assert {k: da[k] for k in ("vendor", "model_name", "family", "model", "stepping")} == {
        "vendor": "AuthenticAMD",
        "model_name": "AMD EPYC 7B13",
        "family": "25",
        "model": "1",
        "stepping": "1",
    }
    assert da["flags_sha256"] == cpu_description(b)["flags_sha256"]
    assert da["flags_sha256"] != cpu_description(c)["flags_sha256"]
    assert len(da["flags_sha256"]) == 16
    assert cpu_description(tmp_path / "missing") == {}
    assert "cpu" in write_provenance(tmp_path / "run", {})["machine"]


def test_provenance_records_what_picks_the_arithmetic(tmp_path, monkeypatch):
    """The numerics variables set (only those), and NumPy's enabled SIMD targets: a subset of
    its dispatch list that agrees with its own feature table."""
    import numpy  # noqa: F401  (imported: its dispatcher's targets are recorded)
    from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

    from uwdock.dockcore.provenance import NUMERICS_ENV, numerics_env

    got = numerics_env({"MKL_CBWR": "COMPATIBLE", "HOME": "/root", "NUMBA_CPU_NAME": "generic"})
    assert {k: got[k] for k in got if k != "numpy_simd"} == {
        "MKL_CBWR": "COMPATIBLE",
        "NUMBA_CPU_NAME": "generic",
    }
    assert got["numpy_simd"] == [t for t in __cpu_dispatch__ if __cpu_features__.get(t)]
    assert numerics_env({}).keys() == {"numpy_simd"}
    for k in NUMERICS_ENV:
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("NPY_DISABLE_CPU_FEATURES", "X86_V4 AVX512_ICL")
    machine = write_provenance(tmp_path / "run", {})["machine"]
    assert machine["numerics"]["NPY_DISABLE_CPU_FEATURES"] == "X86_V4 AVX512_ICL"


def test_interrupts_deferred_holds_a_signal_until_the_step_is_whole():
    """A SIGTERM sent inside the block reaches the process's handler only after the block (a
    scene whose constructor it cut in half segfaulted on its destruction); one sent after it
    at once; a SIG_IGN handler stays ignored."""
    import os
    import signal

    from uwdock.dockcore.signals import interrupts_deferred

    class Landed(Exception):
        pass

    def handler(signum, _frame):
        raise Landed(signum)

    previous = signal.signal(signal.SIGTERM, handler)
    steps = []
    try:
        with pytest.raises(Landed):
            with interrupts_deferred():
                os.kill(os.getpid(), signal.SIGTERM)
                for k in range(3):  # bytecode runs on: a handler would have raised here
                    steps.append(k)
        assert steps == [0, 1, 2]
        assert signal.getsignal(signal.SIGTERM) is handler
        with pytest.raises(Landed):
            os.kill(os.getpid(), signal.SIGTERM)
            sum(range(10))
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        with interrupts_deferred():
            os.kill(os.getpid(), signal.SIGTERM)
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_a_failed_write_through_a_file_object_names_the_target(tmp_path):
    """``fh.write`` on a full disk raises an OSError with no file name: the error names the file
    being replaced (it said only "no space left on the device"), and the old file stays."""
    import errno

    target = tmp_path / "labels.jsonl"
    target.write_text("old\n")
    with pytest.raises(OSError) as info:
        with atomic_path(target) as tmp, tmp.open("w") as fh:
            fh.write("new\n")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert info.value.filename == str(target) and info.value.errno == errno.ENOSPC
    assert target.read_text() == "old\n" and list(tmp_path.iterdir()) == [target]
    with pytest.raises(OSError) as info:  # not a write error: left as it was
        with atomic_path(target):
            raise OSError(errno.EINVAL, "bad argument")
    assert info.value.filename is None
