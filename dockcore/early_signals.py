"""Signals that land while a console script is still importing its command-line machinery.

From the interpreter's start to :func:`dockcore.cli.run_group` installing its handlers, a
console script imports click and the toolkit's CLI (about 40 ms). A SIGTERM there would end
the process by the signal (no line, status -15) and a SIGINT by a traceback. :func:`hold`,
called first thing by the module the console scripts import, records such a signal instead;
``run_group`` then ends the command as interrupted, with its one line and 143 or 130, before
parsing anything. Only the interpreter's own start-up (before any of the toolkit's code runs)
is left unguarded.

Imports nothing beyond the standard library's ``signal``, ``sys`` and ``os``, so holding costs
no start-up time.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from typing import Any

#: the signals held so far, in the order they landed
HELD: list[int] = []


def _hold(signum: int, frame: Any) -> None:
    HELD.append(signum)


def holding(signum: int) -> bool:
    """Whether ``signum``'s handler is the one :func:`hold` installed."""
    return signal.getsignal(signum) is _hold


def _is_program() -> bool:
    """Whether this process runs a console script (its ``__main__`` is the file ``argv[0]``
    names), not a library caller that imported the toolkit's CLI."""
    main_file = getattr(sys.modules.get("__main__"), "__file__", None)
    if main_file is None or not sys.argv or not sys.argv[0]:
        return False
    try:
        return os.path.realpath(main_file) == os.path.realpath(sys.argv[0])
    except (OSError, ValueError):
        return False


def hold() -> None:
    """In a console script's main thread: hold SIGTERM, and SIGINT where it is not ignored,
    until ``run_group`` takes them over. Does nothing in a library caller."""
    if threading.current_thread() is not threading.main_thread() or not _is_program():
        return
    signal.signal(signal.SIGTERM, _hold)
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _hold)
