"""Worker processes that never outlive the command that started them.

A worker calls :func:`die_with_parent` first thing. On Linux the kernel then sends it SIGKILL
the moment its parent dies, whatever killed the parent (SIGKILL included): ``prctl`` with
``PR_SET_PDEATHSIG``. Elsewhere a daemon thread polls the parent's pid twice a second and ends
the worker when it changes. Either way a killed ``rl train`` or ``datasets synth`` leaves no
simulator processes behind.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

_PR_SET_PDEATHSIG = 1


def _prctl_pdeathsig(sig: int) -> bool:
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        return libc.prctl(_PR_SET_PDEATHSIG, sig, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch(parent: int, period_s: float) -> None:
    while True:
        time.sleep(period_s)
        if os.getppid() != parent:
            os._exit(1)


def die_with_parent(expected_parent: int | None = None, period_s: float = 0.5) -> None:
    """Make this process end when its parent does (module docstring).

    Args:
        expected_parent: the parent's pid as the parent saw it before starting this worker; if
            the parent is already gone (this process was re-parented in between), exit now.
        period_s: polling period of the fallback thread (s).
    """
    parent = os.getppid()
    armed = _prctl_pdeathsig(signal.SIGKILL)
    if expected_parent is not None and parent != expected_parent:
        os._exit(1)
    if not armed:
        threading.Thread(target=_watch, args=(parent, period_s), daemon=True).start()


#: Seconds a worker process has to end after SIGTERM before it is killed (SIGKILL).
STOP_GRACE_S = 0.5


def end_pool_processes(pool: Any, grace_s: float = STOP_GRACE_S) -> int:
    """End the worker processes of a local :class:`dockcore.pool.WorkerPool` now: SIGTERM, then
    SIGKILL after ``grace_s``. Their results are lost, nothing else: the workers of the
    toolkit's pools write no files (their results travel back to the caller, which writes
    them). A Ray pool (no local processes) is left to its own ``close``. Returns the number of
    processes ended."""
    executor = getattr(pool, "_ex", None)
    procs = [p for p in list((getattr(executor, "_processes", None) or {}).values()) if p]
    for p in procs:
        try:
            p.terminate()
        except (OSError, ValueError, AttributeError):  # already gone, or closed
            pass
    deadline = time.monotonic() + grace_s
    for p in procs:
        try:
            p.join(max(deadline - time.monotonic(), 0.0))
            if p.is_alive():
                p.kill()
                p.join(1.0)
        except (OSError, ValueError, AssertionError, AttributeError):
            pass
    return len(procs)


@contextmanager
def workers_ended_on_error(pool: Any) -> Iterator[Any]:
    """Around the use of a worker pool: when anything leaves the block by an exception (SIGINT
    and SIGTERM above all, which the CLI raises as interrupts), the pool's worker processes are
    ended at once (:func:`end_pool_processes`) instead of being waited for. The pool's own
    close waits for the tasks they are running: a frame render, or a worker still building its
    scene, 9-45 s of a ``datasets synth --workers 2`` stopped by Ctrl-C on a busy machine."""
    try:
        yield pool
    except BaseException:
        end_pool_processes(pool)
        raise
