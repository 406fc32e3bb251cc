"""Library warnings as the toolkit's own lines.

Libraries speak through Python's ``warnings``: Stable-Baselines3's mini-batch advice is four
lines with a source path and a ``warnings.warn(`` echo, gymnasium's and torch's ``UserWarning``
two. Inside :func:`library_notes` each becomes one ``note: ...`` line on stderr (said once per
process), in the toolkit's words where the toolkit knows what it means (:data:`REWRITES`: the
config key to change), else the library's first line, named by its package. A warning that
tells the user nothing they can act on is dropped (:data:`SILENCED`).

The warnings filters are left as they are (what Python hides by default stays hidden); only the
way a shown warning is written changes. Worker processes forked inside the block inherit it.
"""

from __future__ import annotations

import functools
import re
import sys
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

__all__ = ["REWRITES", "SILENCED", "library_notes", "note_for", "with_library_notes"]


def _sb3_minibatch(m: re.Match[str]) -> str:
    batch, rollout, rest = m["batch"], m["rollout"], m["rest"]
    return (
        f"ppo.batch_size {batch} does not divide the rollout of {rollout} steps "
        f"(ppo.n_steps x n_envs): each epoch ends with a mini-batch of {rest}; "
        f"a batch_size that divides {rollout} avoids it"
    )


#: (pattern over a warning's text, its note): warnings the toolkit words itself.
REWRITES: list[tuple[re.Pattern[str], Callable[[re.Match[str]], str]]] = [
    (
        re.compile(
            r"mini-batch size of (?P<batch>\d+), but because the `RolloutBuffer` is of size "
            r"`n_steps \* n_envs = (?P<rollout>\d+)`.*truncated mini-batch of size (?P<rest>\d+)",
            re.S,
        ),
        _sb3_minibatch,
    ),
]

#: Patterns of warnings that are dropped: nothing a user of the toolkit can do about them.
SILENCED: list[re.Pattern[str]] = [
    # torch, on the first tensor made from an array that SB3 keeps read-only: harmless
    re.compile(r"The given NumPy array is not writable"),
    # gymnasium's checker about the toolkit's own env internals, which its tests cover
    re.compile(r"env\.\w+ to get variables from other wrappers is deprecated"),
]


_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def _package(filename: str, module: str | None) -> str:
    """The top-level package a warning came from (``stable_baselines3``), from its module name
    or its file's path under ``site-packages``."""
    if module:
        return module.split(".")[0]
    parts = re.split(r"[\\/]", filename)
    for marker in ("site-packages", "dist-packages"):
        if marker in parts and parts.index(marker) + 1 < len(parts):
            return parts[parts.index(marker) + 1].removesuffix(".py")
    return parts[-1].removesuffix(".py") if parts else "python"


def note_for(message: Warning | str, category: type[Warning], filename: str) -> str | None:
    """The one-line note of a warning (without ``note: ``), or None to drop it."""
    text = _ANSI.sub("", str(message))  # gymnasium colours its warnings
    for pattern in SILENCED:
        if pattern.search(text):
            return None
    for pattern, word in REWRITES:
        m = pattern.search(text)
        if m:
            return word(m)
    first = next((line.strip() for line in text.splitlines() if line.strip()), "")
    first = first.removeprefix("WARN: ")  # gymnasium's logger prefix
    if len(first) > 200:
        first = first[:197] + "..."
    return f"{_package(filename, None)} {category.__name__}: {first or '(no message)'}"


@contextmanager
def library_notes(stream: Any = None) -> Iterator[None]:
    """Write the warnings shown inside the block as one ``note: ...`` line each (module
    docstring), each text once, to ``stream`` (stderr at the time of writing by default)."""
    said: set[str] = set()

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        try:
            note = note_for(message, category, filename)
        except Exception:  # a note must never be what breaks a command
            note = f"{category.__name__}: {' '.join(str(message).split())[:200]}"
        if note is None or note in said:
            return
        said.add(note)
        out = stream if stream is not None else sys.stderr
        try:
            out.write(f"note: {note}\n")
            out.flush()
        except (OSError, ValueError):  # a closed or broken stream: nothing to say it on
            pass

    with warnings.catch_warnings():
        warnings.showwarning = show
        yield


def with_library_notes(group: Any) -> Any:
    """Run every command of a click group inside :func:`library_notes` (each command's callback
    wrapped, so it holds however the command is reached: its group's console script, which
    loads the commands lazily without the group's own callback, or ``uwdock <group>``).
    Returns the group."""
    for command in group.commands.values():
        callback = command.callback
        if callback is None or getattr(callback, "_library_notes", False):
            continue

        @functools.wraps(callback)
        def wrapped(*args: Any, _callback: Callable[..., Any] = callback, **kwargs: Any) -> Any:
            with library_notes():
                return _callback(*args, **kwargs)

        wrapped._library_notes = True  # type: ignore[attr-defined]
        command.callback = wrapped
    return group
