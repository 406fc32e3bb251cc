"""dockcore's defences: value domains, hostile config files, the CLI error convention, output
folders claimed and locked, stale temporary files, workers that die with their parent."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass
from typing import Annotated

import click
import pytest

from uwdock.dockcore.cli import domain_type, field_type, run_group
from uwdock.dockcore.config import from_dict, load_config, read_toml, validated
from uwdock.dockcore.domains import Count, Finite, Interval, Positive, Seed, check, describe
from uwdock.dockcore.errors import ConfigError, DockError
from uwdock.dockcore.io import TEMP_MARK, atomic_path, atomic_write_text, clean_stale_temps
from uwdock.dockcore.outdir import LOCK_FILE, OWNER_FILE, claim_output_dir, folder_owner


@dataclass(frozen=True)
class Dom:
    size_mm: Positive = 10.0
    gamma: Annotated[float, Interval(ge=0, le=1)] = 0.5
    n: Count = 3
    seed: Seed = 0
    offset_m: Finite = -1.0
    plain: float = 1.0
    limit_m: Positive | None = None


@pytest.mark.parametrize(
    "key,value,message",
    [
        ("size_mm", math.nan, "size_mm: must be a finite number > 0, got nan"),
        ("size_mm", math.inf, "size_mm: must be a finite number > 0, got inf"),
        ("size_mm", 0.0, "size_mm: must be a finite number > 0, got 0"),
        ("size_mm", -3, "size_mm: must be a finite number > 0, got -3"),
        ("size_mm", "ten", "size_mm: expected a number, got 'ten'"),
        ("gamma", 1.5, "gamma: must be a finite number in [0, 1], got 1.5"),
        ("n", 0, "n: must be an integer in [1, 1000000000], got 0"),
        ("n", 2.0, "n: expected an integer, got 2.0"),
        ("n", True, "n: expected an integer, got True"),
        ("seed", -1, "seed: must be an integer in [0, 4294967295], got -1"),
        ("offset_m", -math.inf, "offset_m: must be a finite number, got -inf"),
        ("plain", math.nan, "plain: must be a finite number, got nan"),
        ("limit_m", -1.0, "limit_m: must be a finite number > 0, got -1"),
    ],
)
def test_every_number_is_checked_against_its_domain(key, value, message):
    with pytest.raises(ConfigError) as err:
        from_dict(Dom, {key: value})
    assert str(err.value) == message


def test_equal_domains_with_int_and_float_bounds_are_described_each_their_own_way():
    # Interval(le=1e9) == Interval(le=10**9) and they hash alike; the description must not
    # depend on which of the two was checked first (it did: CI ran them in another order).
    as_float = (Interval(ge=1, le=1e9),)
    as_int = (Interval(ge=1, le=10**9),)
    assert describe(as_float, integer=True) == "an integer in [1, 1e+09]"
    assert describe(as_int, integer=True) == "an integer in [1, 1000000000]"
    assert describe(as_float, integer=True) == "an integer in [1, 1e+09]"


def test_values_inside_the_domain_load():
    cfg = from_dict(Dom, {"size_mm": 1e-9, "gamma": 1, "n": 10**9, "seed": 2**32 - 1})
    assert cfg.gamma == 1.0 and isinstance(cfg.gamma, float)
    assert from_dict(Dom, {"limit_m": None}).limit_m is None


def test_validated_refuses_what_python_code_built():
    with pytest.raises(ConfigError, match="size_mm"):
        validated(Dom(size_mm=math.nan))
    assert validated(Dom()) == Dom()


def test_describe_and_check_words():
    assert describe((Interval(ge=0, lt=90),)) == "a finite number in [0, 90)"
    assert check(5, int, (Interval(ge=1),), "k") is None
    assert check(5.0, int, (Interval(ge=1),), "k") == "k: must be an integer >= 1, got 5.0"


def test_toml_nan_and_inf_are_refused(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("size_mm = nan\n")
    with pytest.raises(ConfigError, match="size_mm: must be a finite number > 0, got nan"):
        load_config(Dom, p)
    p.write_text("plain = -inf\n")
    with pytest.raises(ConfigError, match="plain: must be a finite number, got -inf"):
        load_config(Dom, p)


def test_non_utf8_bom_and_folder_configs(tmp_path):
    bad = tmp_path / "latin1.toml"
    bad.write_bytes("name = 'caf\xe9'\n".encode("latin-1"))
    with pytest.raises(ConfigError, match=r"latin1.toml is not UTF-8 text \(byte 11: 0xe9\)"):
        read_toml(bad)
    bom = tmp_path / "bom.toml"
    bom.write_bytes(b"\xef\xbb\xbfsize_mm = 2.0\n")
    assert load_config(Dom, bom).size_mm == 2.0
    with pytest.raises(ConfigError, match="marker set file not found"):
        read_toml(tmp_path / "nope.toml", what="marker set file")
    with pytest.raises(ConfigError, match="is a folder, not a file"):
        read_toml(tmp_path)


# ----------------------------------------------------------------------------- CLI


@click.group()
def _group() -> None:
    pass


@_group.command("cmd")
@click.option("--size-mm", type=field_type(Dom, "size_mm"))
@click.option("--limit-m", type=field_type(Dom, "limit_m"))
@click.option("--n", type=domain_type(Count))
@click.option("--fail", type=click.Choice(["dock", "os", "bug", "term", "disk", "int-import"]))
def _cmd(size_mm, limit_m, n, fail) -> None:
    if fail == "dock":
        raise DockError("bad input,\nreally")
    if fail == "os":
        raise FileNotFoundError(2, "No such file or directory", "/x/y.toml")
    if fail == "disk":
        raise OSError(28, "No space left on device", "/x/out.json")
    if fail == "bug":
        raise ZeroDivisionError("division by zero")
    if fail == "term":
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)
    if fail == "int-import":  # Ctrl-C while a C extension initialises: Python reports that as
        try:  # "ImportError: initialization failed", the KeyboardInterrupt swallowed
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
        except KeyboardInterrupt:
            pass
        raise ImportError("initialization failed")
    click.echo(f"ok {size_mm} {limit_m} {n}")


def _run(capsys, *args):
    with pytest.raises(SystemExit) as ex:
        run_group(_group, list(args))
    cap = capsys.readouterr()
    return ex.value.code, cap.out, cap.err


_POS = "must be a finite number > 0, got"
_CNT = "must be an integer in [1, 1000000000], got"


@pytest.mark.parametrize(
    "args,message",
    [
        (["--size-mm", "nan"], f"'--size-mm': {_POS} nan"),
        (["--size-mm", "1e999"], f"'--size-mm': {_POS} inf"),
        (["--size-mm", "-2"], f"'--size-mm': {_POS} -2"),
        (["--size-mm", "abc"], f"'--size-mm': {_POS} 'abc'"),
        (["--limit-m", "0"], f"'--limit-m': {_POS} 0"),
        (["--n", "1.5"], f"'--n': {_CNT} '1.5'"),
        (["--n", "0"], f"'--n': {_CNT} 0"),
    ],
)
def test_numeric_options_refuse_hostile_values_in_one_line(capsys, args, message):
    code, out, err = _run(capsys, "cmd", *args)
    assert code == 2 and out == ""
    assert err == f"error: Invalid value for {message}\n"


def test_numeric_options_accept_their_domain(capsys):
    code, out, _ = _run(capsys, "cmd", "--size-mm", "2.5", "--n", "7")
    assert code == 0 and out == "ok 2.5 None 7\n"


@pytest.mark.parametrize(
    "fail,code,message",
    [
        ("dock", 2, "error: bad input, really\n"),
        ("os", 2, "error: /x/y.toml: No such file or directory\n"),
        ("disk", 2, "error: /x/out.json: no space left on the device\n"),
        ("term", 143, "error: interrupted (SIGTERM)\n"),
        ("int-import", 130, "error: interrupted\n"),  # what the interrupt left behind
    ],
)
def test_errors_are_one_line(capsys, fail, code, message):
    # Ctrl-C as at a terminal: a process started in the background by a non-interactive shell
    # (`cmd &`) inherits SIGINT ignored, and run_group leaves an ignored SIGINT alone
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        assert _run(capsys, "cmd", "--fail", fail) == (code, "", message)
    finally:
        signal.signal(signal.SIGINT, old)


def test_a_bug_is_one_line_exit_1_without_traceback(capsys):
    code, out, err = _run(capsys, "cmd", "--fail", "bug")
    assert code == 1 and out == ""
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith("error: internal error (ZeroDivisionError: division by zero)")


def test_bare_group_prints_its_help_without_error_prefix(capsys):
    code, out, err = _run(capsys)
    assert code == 2 and "Usage:" in out and "error" not in err


# ----------------------------------------------------------------------------- files


def test_failed_atomic_write_names_the_target_not_the_temp(tmp_path):
    target = tmp_path / "ro" / "a.json"
    target.parent.mkdir()
    target.parent.chmod(0o500)
    try:
        if os.access(target.parent, os.W_OK):
            pytest.skip("running as a user who can write a read-only folder")
        with pytest.raises(PermissionError) as err, atomic_path(target) as tmp:
            tmp.write_text("x")
        assert err.value.filename == str(target)
    finally:
        target.parent.chmod(0o700)


def test_stale_temps_of_dead_processes_are_removed(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True).stdout.strip()  # fmt: skip
    (tmp_path / "sub").mkdir()
    stale = [tmp_path / f".a.json.{dead}.k2j4h1x0{TEMP_MARK}",
             tmp_path / "sub" / f".v.mp4.{dead}.abcdefgh{TEMP_MARK}.mp4"]  # fmt: skip
    live = tmp_path / f".b.json.{os.getpid()}.zzzzzzzz{TEMP_MARK}"
    for p in [*stale, live]:
        p.write_text("x")
    (tmp_path / "keep.json").write_text("{}")
    assert clean_stale_temps(tmp_path) == 2
    assert not any(p.exists() for p in stale) and live.exists()
    assert (tmp_path / "keep.json").exists()


def test_output_folder_is_claimed_by_one_tool(tmp_path):
    out = tmp_path / "run"
    with claim_output_dir(out, "rl train") as d:
        atomic_write_text(d / "config.toml", "x = 1\n")
    assert folder_owner(out) == "rl train"
    with pytest.raises(DockError, match=r"holds the output of `rl train`; `rl eval` will not"):
        with claim_output_dir(out, "rl eval"):
            pass
    assert (out / "config.toml").read_text() == "x = 1\n"
    with claim_output_dir(out, "rl train"):  # the same tool may come back (resume, rerun)
        pass


def test_legacy_folder_owner_from_provenance(tmp_path):
    (tmp_path / "provenance.json").write_text(json.dumps({"command": "markers generate --out x"}))
    assert folder_owner(tmp_path) == "markers generate"
    with pytest.raises(DockError, match="`markers generate`"):
        with claim_output_dir(tmp_path, "datasets synth"):
            pass


def test_a_locked_folder_is_refused_while_its_process_lives(tmp_path):
    out = tmp_path / "ds"
    code = textwrap.dedent(f"""
        import time
        from uwdock.dockcore.outdir import claim_output_dir
        with claim_output_dir({str(out)!r}, "datasets synth"):
            print("locked", flush=True)
            time.sleep(60)
    """)
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "locked"
        with pytest.raises(DockError, match=r"in use by `datasets synth`, pid \d+"):
            with claim_output_dir(out, "datasets synth"):
                pass
    finally:
        proc.kill()
        proc.wait()
    with claim_output_dir(out, "datasets synth"):  # SIGKILL released it
        assert (out / LOCK_FILE).exists() and (out / OWNER_FILE).exists()


def test_workers_die_with_their_parent(tmp_path):
    """A parent that starts a worker (which calls die_with_parent) is SIGKILLed: the worker
    is gone within a second."""
    pidfile = tmp_path / "worker.pid"
    parent = textwrap.dedent(f"""
        import multiprocessing as mp, os, time
        def work(path, parent):
            from uwdock.dockcore.procs import die_with_parent
            die_with_parent(parent)
            open(path, "w").write(str(os.getpid()))
            time.sleep(120)
        if __name__ == "__main__":
            p = mp.get_context("fork").Process(target=work, args=({str(pidfile)!r}, os.getpid()))
            p.start()
            time.sleep(120)
    """)
    script = tmp_path / "parent.py"
    script.write_text(parent)
    proc = subprocess.Popen([sys.executable, str(script)])
    try:
        for _ in range(100):
            if pidfile.exists() and pidfile.read_text():
                break
            time.sleep(0.05)
        worker = int(pidfile.read_text())
        os.kill(worker, 0)
    finally:
        proc.kill()
        proc.wait()
    for _ in range(40):
        try:
            os.kill(worker, 0)
        except ProcessLookupError:
            return
        # a zombie of a dead parent is reaped by init; check its state
        try:
            state = open(f"/proc/{worker}/stat").read().split()[2]
            if state == "Z":
                return
        except OSError:
            return
        time.sleep(0.05)
    pytest.fail(f"worker {worker} outlived its parent")


@pytest.mark.parametrize("err", [28, 30])  # ENOSPC, EROFS
def test_disk_full_or_read_only_names_the_target(tmp_path, monkeypatch, err):
    target = tmp_path / "labels.jsonl"

    def fail(src, dst):
        raise OSError(err, os.strerror(err), str(src))

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError) as exc:
        atomic_write_text(target, "x")
    assert exc.value.filename == str(target) and exc.value.errno == err
    assert list(tmp_path.iterdir()) == []


def test_a_signal_landing_in_importlib_is_delivered_again_not_lost():
    """A SIGTERM/SIGINT that lands while importlib runs a module lock's weakref callback would
    raise there, where Python prints "Exception ignored ... Traceback" and drops it (seen in the
    killed-training test): the handler delivers it again a moment later instead, and raises at
    once anywhere else."""
    from uwdock.dockcore import cli as dcli

    ns: dict = {}
    code = compile("import sys\nframe = sys._getframe()", "<frozen importlib._bootstrap>", "exec")
    exec(code, ns)
    got: list[int] = []
    old = signal.signal(signal.SIGUSR1, lambda s, f: got.append(s))
    try:
        dcli._interrupt(signal.SIGUSR1, ns["frame"], KeyboardInterrupt)  # no raise here
        assert dcli._received == [signal.SIGUSR1]  # but recorded: an error before it lands is it
        deadline = time.monotonic() + 5.0
        while not got and time.monotonic() < deadline:
            time.sleep(0.005)
        assert got == [signal.SIGUSR1]
        with pytest.raises(KeyboardInterrupt):
            dcli._interrupt(signal.SIGUSR1, sys._getframe(), KeyboardInterrupt)
        assert dcli._received == [signal.SIGUSR1, signal.SIGUSR1]
    finally:
        signal.signal(signal.SIGUSR1, old)
        dcli._received.clear()


def test_an_error_before_a_put_off_interrupt_lands_is_reported_as_the_interrupt(capsys):
    """The int-import case with the SIGINT landing in importlib: its handler puts the raise off,
    the C extension's ImportError surfaces first; that is the interrupt (130), not a bug (1)."""
    from uwdock.dockcore import cli as dcli

    ns: dict = {}
    code = compile("import sys\nframe = sys._getframe()", "<frozen importlib._bootstrap>", "exec")
    exec(code, ns)

    @click.group()
    def grp():
        pass

    @grp.command()
    def cmd():
        dcli._interrupt(signal.SIGINT, ns["frame"], KeyboardInterrupt)  # put off
        raise ImportError("initialization failed")

    delivered: list[int] = []
    orig_kill = os.kill
    old = signal.signal(signal.SIGUSR1, lambda s, f: delivered.append(s))
    try:  # the redelivery is sent as SIGUSR1 and only counted, so pytest sees no Ctrl-C
        os.kill = lambda pid, sig: orig_kill(pid, signal.SIGUSR1)
        with pytest.raises(SystemExit) as ex:
            run_group(grp, ["cmd"])
        deadline = time.monotonic() + 5.0
        while not delivered and time.monotonic() < deadline:
            time.sleep(0.005)
    finally:
        os.kill = orig_kill
        signal.signal(signal.SIGUSR1, old)
    assert delivered == [signal.SIGUSR1]  # it was put off, and delivered again
    assert ex.value.code == 130 and capsys.readouterr().err == "error: interrupted\n"


_LATE_SIGNAL_PROGRAM = """
import atexit, pathlib, sys, time
import click
from uwdock.dockcore.cli import run_group

@click.group()
def grp():
    pass

@grp.command()
@click.argument("marker")
def work(marker):
    atexit.register(time.sleep, 3.0)  # a slow shutdown: what joining workers looks like
    pathlib.Path(marker).write_text("done")

run_group(grp)
"""


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_shutdown_keeps_the_finished_commands_status(tmp_path, sig):
    """Ctrl-C or SIGTERM after the command finished, while the interpreter shuts down: the
    status the command chose (0 here), no traceback, not death by the signal."""
    import subprocess

    prog = tmp_path / "prog.py"
    prog.write_text(_LATE_SIGNAL_PROGRAM, encoding="utf-8")
    marker = tmp_path / "done"
    proc = subprocess.Popen(
        [sys.executable, str(prog), "work", str(marker)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 60
    while not marker.exists() and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(0.5)  # inside the atexit sleep
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, (proc.returncode, err)
    assert "Traceback" not in err and "KeyboardInterrupt" not in err


_SWALLOWED_SIGNAL_PROGRAM = """
import os, pathlib, signal, sys, time
import click
from uwdock.dockcore.cli import run_group

SIG = getattr(signal, os.environ["SWALLOWED_SIGNAL"])
# Ctrl-C as at a terminal: started from a suite run in the background by a non-interactive
# shell (`cmd &`), this process would inherit SIGINT ignored, which run_group leaves alone
signal.signal(signal.SIGINT, signal.default_int_handler)

class Dropped:
    def __del__(self):
        signal.raise_signal(SIG)  # the handler raises here, inside __del__

@click.group()
def grp():
    pass

@grp.command()
@click.argument("where")
@click.argument("marker")
def work(where, marker):
    if where == "fork":  # as when the signal lands in logging's after-fork hook
        os.register_at_fork(after_in_parent=lambda: signal.raise_signal(SIG))
        pid = os.fork()
        if pid == 0:
            os._exit(0)
        os.waitpid(pid, 0)
    else:
        Dropped()
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline:
        time.sleep(0.01)
    pathlib.Path(marker).write_text("trained on to the end")

run_group(grp)
"""


@pytest.mark.parametrize("where", ["fork", "del"])
@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_an_interrupt_python_would_swallow_is_delivered_again(tmp_path, where, sig):
    """A signal whose handler raises where Python cannot propagate the exception (an os.fork
    hook, as logging's ``_releaseLock`` in CI's killed-training run; a ``__del__``) was printed
    as "Exception ignored ... Traceback" and lost, and the command ran on to its end: it is
    delivered again and ends the command as an interrupt."""
    prog = tmp_path / "prog.py"
    prog.write_text(_SWALLOWED_SIGNAL_PROGRAM, encoding="utf-8")
    marker = tmp_path / "finished"
    proc = subprocess.run(
        [sys.executable, str(prog), "work", where, str(marker)],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "SWALLOWED_SIGNAL": sig},
    )
    code = 130 if sig == "SIGINT" else 128 + signal.SIGTERM
    assert proc.returncode == code, (proc.returncode, proc.stderr)
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr
    assert proc.stderr.startswith("error: interrupted"), proc.stderr
    assert not marker.exists()
