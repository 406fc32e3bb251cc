"""Commands that can hold the interpreter for seconds still stop within moments of a signal.

Python runs a signal handler only between bytecodes of the main thread. A native call that
keeps the interpreter lock (SAPIEN's first ``take_picture`` compiles the renderer's shaders for
about 5 s on a CPU-only machine) puts off SIGINT/SIGTERM until it returns, so a command that
renders in its own process could take 5 s to stop.

:func:`supervise`, called by such a command before its work starts, forks: the child runs the
command as before (its handlers, its one line, its cleanup of interrupted outputs); the parent
only waits for it and answers signals. On SIGINT/SIGTERM the parent passes the signal on and,
if the child has not ended within :data:`GRACE_S`, kills the child and what it started,
calls the command's ``on_killed`` (which marks the outputs incomplete as the child would have),
writes the one line and exits with 130 or 143. A second signal kills at once. The parent exits
with the child's status otherwise, so callers see one process that behaves as before.

Supervision is skipped (the command runs in this process, as before) outside a command that
``dockcore.cli.run_group`` runs as a console script's program (a test's or a library's call
runs in its own process), outside the main thread, where ``fork`` is not there, while other
Python threads run (a fork would copy their locks), or when ``UWDOCK_NO_SUPERVISE=1``.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable

from uwdock.dockcore import cli as _cli
from uwdock.dockcore.io import clean_stale_temps
from uwdock.dockcore.outdir import claimed_by
from uwdock.dockcore.procs import die_with_parent

#: Seconds the parent gives its child to end by itself after the first signal.
GRACE_S = 2.0

_STOP = (signal.SIGTERM, signal.SIGINT)
# SIGALRM: the parent's own interval timer (the grace deadline). The parent waits with
# ``sigwaitinfo``, never ``sigtimedwait``: CPython's ``sigtimedwait`` returns an uninitialised
# siginfo when the wait was interrupted (the process stopped and continued: Ctrl-Z then ``fg``,
# a debugger or profiler attaching) and its timeout ran out meanwhile, i.e. a made-up signal
# number, sometimes SIGINT's.
_WATCHED = {*_STOP, signal.SIGCHLD, signal.SIGALRM}


def _can_supervise() -> bool:
    return (
        hasattr(os, "fork")
        and hasattr(signal, "sigwaitinfo")
        and hasattr(signal, "setitimer")
        and threading.current_thread() is threading.main_thread()
        and threading.active_count() == 1
        and _cli.runs_program_command()
        and os.environ.get("UWDOCK_NO_SUPERVISE", "") not in ("1", "true", "yes")
    )


def supervise(
    on_killed: Callable[[str, int], None] | None = None, grace_s: float = GRACE_S
) -> None:
    """Go on in a child process watched by this one (module docstring); return in the child
    (or here, unsupervised). ``on_killed(signal_name, pid)`` runs in the parent after it
    killed a child (process id ``pid``) that did not stop in time (``"SIGTERM"`` or
    ``"SIGINT"``)."""
    if not _can_supervise():
        return
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, _WATCHED)
    parent = os.getpid()
    pid = os.fork()
    if pid == 0:
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
        die_with_parent(parent)  # a supervisor killed with SIGKILL leaves no orphan
        _cli.ignore_repeated_signals()  # the parent passes on what it receives: once is enough
        return
    os._exit(_watch(pid, on_killed, grace_s))


def _watch(pid: int, on_killed: Callable[[str, int], None] | None, grace_s: float) -> int:
    """The parent: wait for ``pid``; its exit status, or 130/143 after killing it. Every wake-up
    is a real signal: the child's SIGCHLD, a stop signal, or the timer (after the first stop
    signal: ``grace_s``, then every 0.2 s until the killed child is reaped)."""
    first: int | None = None
    killed = False
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        signo = signal.sigwaitinfo(_WATCHED).si_signo
        if signo == signal.SIGCHLD or (signo == signal.SIGALRM and (first is None or killed)):
            continue
        if signo == signal.SIGALRM or first is not None:  # the grace ran out, or a second signal
            if not killed:
                _kill_tree(pid)
                killed = True
                signal.setitimer(signal.ITIMER_REAL, 0.2, 0.2)
            continue
        first = signo
        signal.setitimer(signal.ITIMER_REAL, max(grace_s, 1e-3))
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signo)
    signal.setitimer(signal.ITIMER_REAL, 0)
    if not killed:
        code = os.waitstatus_to_exitcode(status)
        return code if code >= 0 else 128 - code
    name = "SIGTERM" if first == signal.SIGTERM else "SIGINT"
    if on_killed is not None:
        try:
            on_killed(name, pid)
        except Exception:  # the outputs stay as the child left them; the exit says interrupted
            pass
    # from the start of the line: the killed child may have left a progress bar on it
    start = "\r\x1b[K" if _isatty(sys.stderr) else "\r"
    sys.stderr.write(
        f"{start}error: interrupted{' (SIGTERM)' if first == signal.SIGTERM else ''}\n"
    )
    sys.stderr.flush()
    return 128 + signal.SIGTERM if first == signal.SIGTERM else 130


def _isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


def descendants(pid: int) -> list[int]:
    """The processes ``pid`` started, and theirs (Linux ``/proc``; empty elsewhere)."""
    children: dict[int, list[int]] = {}
    with contextlib.suppress(OSError):
        for entry in os.scandir("/proc"):
            if not entry.name.isdigit():
                continue
            try:
                with open(f"/proc/{entry.name}/stat", "rb") as f:
                    stat = f.read()
            except OSError:
                continue
            ppid = int(stat[stat.rindex(b")") + 2 :].split()[1])
            children.setdefault(ppid, []).append(int(entry.name))
    found, todo = [], [pid]
    while todo:
        kids = children.get(todo.pop(), [])
        found += kids
        todo += kids
    return found


def _kill_tree(pid: int) -> None:
    """SIGKILL ``pid`` and its descendants; reap ``pid``."""
    for p in [*descendants(pid), pid]:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(p, signal.SIGKILL)


def clean_after_kill(out_dir: str | os.PathLike[str] | None) -> Callable[[str, int], None]:
    """``on_killed`` for a command whose outputs survive SIGKILL by design (resumable runs,
    a completion mark written last): the killed child's temporary files in ``out_dir`` removed,
    if the child had claimed the folder (``dockcore.outdir.claim_output_dir``)."""

    def on_killed(signal_name: str, pid: int) -> None:
        if out_dir is not None and claimed_by(out_dir) == pid:
            clean_stale_temps(out_dir)

    return on_killed
