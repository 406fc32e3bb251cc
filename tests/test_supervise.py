"""dockcore.supervise: a command whose work holds the interpreter (a native call that runs no
signal handler) still stops within the grace time of SIGTERM/SIGINT, with one line, 143/130
and its outputs marked by ``on_killed``; otherwise the process behaves as the command did.

The held interpreter is ``sum(range(2e9))``: a C loop that checks for no signal (seconds, as
SAPIEN's first shader compile)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")

SCRIPT = """\
import sys, time
from pathlib import Path
import click
from uwdock.dockcore.cli import run_group
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.supervise import supervise

OUT = Path(sys.argv[3])

def killed(name, pid):
    (OUT / "killed.txt").write_text(f"{name} {pid}")

@click.group()
def cli():
    pass

@cli.command()
@click.argument("what")
@click.argument("out")
def work(what, out):
    supervise(killed, grace_s=1.0)
    (OUT / "child.pid").write_text(str(__import__("os").getpid()))
    try:
        if what == "hold":  # ~40 s of C with the interpreter held
            sum(range(2 * 10**9))
        elif what == "sleep":
            time.sleep(60)
        elif what == "nap":
            time.sleep(5)
        elif what == "fail":
            raise DockError("a bad input")
        print("done")
    except KeyboardInterrupt:
        (OUT / "cleaned.txt").write_text("the command's own cleanup ran")
        raise

if __name__ == "__main__":
    run_group(cli)
"""


def _start(tmp_path: Path, what: str, env: dict | None = None) -> subprocess.Popen:
    script = tmp_path / "cmd.py"
    script.write_text(SCRIPT)
    return subprocess.Popen(
        [sys.executable, str(script), "work", what, str(tmp_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
        env={**os.environ, **(env or {})},
    )


def _wait_child(tmp_path: Path) -> int:
    deadline = time.monotonic() + 30
    while not (tmp_path / "child.pid").exists():
        assert time.monotonic() < deadline, "the command never started"
        time.sleep(0.05)
    time.sleep(0.3)  # inside the held call
    return int((tmp_path / "child.pid").read_text())


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read()
    except OSError:
        return False
    return stat[stat.rindex(b")") + 2 :][:1] != b"Z"  # a zombie is dead, awaiting its reaper


@pytest.mark.parametrize("sig, code, line", [
    (signal.SIGTERM, 143, "error: interrupted (SIGTERM)"),
    (signal.SIGINT, 130, "error: interrupted"),
])  # fmt: skip
def test_a_held_interpreter_is_stopped_in_the_grace_time(tmp_path, sig, code, line):
    proc = _start(tmp_path, "hold")
    child = _wait_child(tmp_path)
    assert child != proc.pid  # the work runs in a child
    t0 = time.monotonic()
    os.killpg(proc.pid, sig) if sig == signal.SIGINT else proc.send_signal(sig)  # as a terminal
    _, err = proc.communicate(timeout=30)
    took = time.monotonic() - t0
    assert proc.returncode == code
    assert err.decode().strip().splitlines() == [line]
    assert 0.9 < took < 2.5  # the grace time (1 s), then killed
    name = "SIGTERM" if sig == signal.SIGTERM else "SIGINT"
    assert (tmp_path / "killed.txt").read_text() == f"{name} {child}"
    assert not _alive(child)


def test_without_supervision_the_same_call_is_deaf(tmp_path):
    """The control: unsupervised, the signal waits for the held call (the test's premise)."""
    proc = _start(tmp_path, "hold", {"UWDOCK_NO_SUPERVISE": "1"})
    child = _wait_child(tmp_path)
    assert child == proc.pid
    proc.send_signal(signal.SIGTERM)
    with pytest.raises(subprocess.TimeoutExpired):
        proc.communicate(timeout=4)
    proc.kill()
    proc.communicate()


def test_a_child_that_stops_by_itself_does_its_own_cleanup(tmp_path):
    """An interruptible command: the child's handler runs, its cleanup too, one line (not two:
    the terminal's Ctrl-C and the parent's copy of it), and on_killed is not needed."""
    proc = _start(tmp_path, "sleep")
    _wait_child(tmp_path)
    t0 = time.monotonic()
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130 and time.monotonic() - t0 < 1.0
    assert err.decode().strip().splitlines() == ["error: interrupted"]
    assert (tmp_path / "cleaned.txt").exists() and not (tmp_path / "killed.txt").exists()


def test_the_status_and_output_of_the_command_pass_through(tmp_path):
    proc = _start(tmp_path, "fine")
    out, err = proc.communicate(timeout=60)
    assert (proc.returncode, out.decode(), err.decode()) == (0, "done\n", "")
    proc = _start(tmp_path, "fail")
    out, err = proc.communicate(timeout=60)
    assert (proc.returncode, err.decode()) == (2, "error: a bad input\n")


def test_a_supervisor_stopped_and_continued_reads_no_signal_into_it(tmp_path):
    """Ctrl-Z then ``fg``, or a debugger or profiler attaching, stops the waiting parent; after
    it goes on, the command runs to its end (CPython's ``sigtimedwait`` returns an
    uninitialised siginfo when stopped past its timeout: a made-up signal, often SIGINT's)."""
    proc = _start(tmp_path, "nap")
    _wait_child(tmp_path)
    for _ in range(2):
        os.kill(proc.pid, signal.SIGSTOP)  # the supervisor alone, its child runs on
        time.sleep(1.3)
        os.kill(proc.pid, signal.SIGCONT)
        time.sleep(0.2)
    out, err = proc.communicate(timeout=60)
    assert (proc.returncode, out.decode(), err.decode()) == (0, "done\n", "")
    assert not (tmp_path / "killed.txt").exists()


def test_a_second_signal_kills_at_once(tmp_path):
    proc = _start(tmp_path, "hold")
    _wait_child(tmp_path)
    proc.send_signal(signal.SIGTERM)
    time.sleep(0.1)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    proc.communicate(timeout=30)
    assert proc.returncode == 143 and time.monotonic() - t0 < 0.6


def test_a_killed_supervisor_takes_its_child_along(tmp_path):
    proc = _start(tmp_path, "hold")
    child = _wait_child(tmp_path)
    proc.kill()
    proc.communicate(timeout=30)
    deadline = time.monotonic() + 5
    while _alive(child):
        assert time.monotonic() < deadline, "the child outlived its supervisor"
        time.sleep(0.05)


def test_in_process_callers_are_not_forked():
    """A library caller or a test (no command run as the program) is never forked."""
    from uwdock.dockcore.supervise import supervise

    pid = os.getpid()
    supervise()
    assert os.getpid() == pid


EARLY = """\
import os, signal, sys

class SignalWhileClickLoads:  # a signal landing while the console script imports click
    def find_spec(self, name, path=None, target=None):
        if name == "click":
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.{sig})
        return None

sys.meta_path.insert(0, SignalWhileClickLoads())
from uwdock.cli import rl
sys.exit(rl())
"""


@pytest.mark.parametrize("sig, code, line", [
    ("SIGTERM", 143, "error: interrupted (SIGTERM)"),
    ("SIGINT", 130, "error: interrupted"),
])  # fmt: skip
def test_a_signal_while_the_console_script_starts_is_held(tmp_path, sig, code, line):
    """dockcore.early_signals: held from the first line of the module the console scripts
    import, then ended as an interrupt by run_group, before the command runs."""
    script = tmp_path / "rl_script.py"
    script.write_text(EARLY.format(sig=sig))
    out = subprocess.run([sys.executable, str(script), "eval", "--help"], capture_output=True,
                         text=True, timeout=60)  # fmt: skip
    assert (out.returncode, out.stderr.strip().splitlines(), out.stdout) == (code, [line], "")
