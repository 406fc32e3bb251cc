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
