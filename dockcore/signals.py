"""Steps a signal must not cut in half.

SIGINT and SIGTERM become Python exceptions (:mod:`dockcore.cli`), raised at whatever line runs
when they arrive. Inside some library constructors that leaves an object no one can destroy:
a SIGTERM landing while ``sapien.Scene()`` creates its systems (the render system takes a
second or more on a loaded machine) left a scene whose ``__del__`` segfaulted (exit 139 after
"error: interrupted", 3 of 51 SIGTERMs to ``rl episode`` 2.0-2.6 s in, with both cores busy;
0 of 58 with the signal held).
Such steps run inside :func:`interrupts_deferred`: a signal that arrives meanwhile is held and
delivered again as soon as the step is done.
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["interrupts_deferred"]

_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold SIGINT and SIGTERM for the duration of the block, then deliver what came.

    The signals' Python handlers are swapped for ones that only note the signal (the C-level
    handler keeps running, so the process does not die of a default action meanwhile); on
    leaving, the handlers are put back and each noted signal is sent to this process again, so
    its own handler runs once the block's object is whole. Off the main thread (where handlers
    cannot be set) the block runs as is.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    saved = {}
    for signum in _SIGNALS:
        handler = signal.getsignal(signum)
        if callable(handler):  # Python handlers only: SIG_IGN / SIG_DFL stay as they are
            saved[signum] = handler
            signal.signal(signum, lambda s, _frame: held.append(s))
    try:
        yield
    finally:
        for signum, handler in saved.items():
            signal.signal(signum, handler)
        for signum in dict.fromkeys(held):
            os.kill(os.getpid(), signum)
