"""Output folders: claimed by one tool, locked while it writes.

Every command that writes a folder (``markers generate``, ``datasets synth``, ``rl train`` ...)
claims it first with :func:`claim_output_dir`:

* **an owner**: ``.uwdock-owner.json`` names the tool that made the folder. Another tool will not
  write into it (``rl eval --out RUN`` cannot overwrite the ``config.toml`` and
  ``provenance.json`` of ``rl train``'s run). Folders made before the marker existed are
  recognised by the command recorded in their ``provenance.json``.
* **a lock**: ``.uwdock.lock`` is held (``flock``, through the ``filelock`` package) for as long
  as the command runs, so a second process writing the same folder stops at once with a line
  naming the holder. The kernel releases the lock when its process dies, even by SIGKILL.
* **no leftovers**: temporary files of processes that were killed are removed
  (:func:`dockcore.io.clean_stale_temps`); a folder made for a command that then fails before
  writing anything is removed again.

Example:
    >>> with claim_output_dir("runs/a", "rl train") as run:
    ...     (run / "config.toml").write_text("...")
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
from collections.abc import Iterator
from pathlib import Path

from filelock import FileLock, Timeout

from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_json, clean_stale_temps, ensure_writable_dir

OWNER_FILE = ".uwdock-owner.json"
LOCK_FILE = ".uwdock.lock"

#: Tools recognised from the ``command`` of a legacy ``provenance.json`` (first two words).
_GROUPS = ("markers", "perception", "calibration", "datasets", "sim", "rl")


def folder_owner(path: str | os.PathLike[str]) -> str | None:
    """The tool that made output folder ``path`` (None: no marker and no provenance)."""
    path = Path(path)
    try:
        owner = json.loads((path / OWNER_FILE).read_text(encoding="utf-8"))
        if isinstance(owner, dict) and isinstance(owner.get("tool"), str):
            return owner["tool"]
    except (OSError, ValueError):
        pass
    try:
        prov = json.loads((path / "provenance.json").read_text(encoding="utf-8"))
        words = str(prov.get("command", "")).split()
    except (OSError, ValueError, AttributeError):
        return None
    if len(words) >= 2 and words[0] in _GROUPS and not words[1].startswith("-"):
        return f"{words[0]} {words[1]}"
    return None


def _holder(path: Path) -> str:
    try:
        owner = json.loads((path / OWNER_FILE).read_text(encoding="utf-8"))
        return f"`{owner.get('tool')}`, pid {owner.get('pid')}"
    except (OSError, ValueError, AttributeError):
        return "another process"


def _refuse_foreign(folder: Path, tool: str) -> None:
    owner = folder_owner(folder) if folder.is_dir() else None
    if owner is not None and owner != tool:
        raise DockError(
            f"{folder} holds the output of `{owner}`; `{tool}` will not write into it: "
            "use another --out"
        )


@contextlib.contextmanager
def claim_output_dir(path: str | os.PathLike[str], tool: str) -> Iterator[Path]:
    """Create (if needed), lock and claim ``path`` for ``tool`` while the block runs.

    Args:
        path: the output folder.
        tool: the command writing it, e.g. ``"datasets synth"``.

    Yields:
        The folder as a ``Path``.

    Raises:
        DockError: one line when the folder cannot be written, is locked by another process,
            or belongs to another tool.
    """
    absolute = Path(path).absolute()
    made = [p for p in (absolute, *absolute.parents) if not p.exists()]  # innermost first
    _refuse_foreign(absolute, tool)  # before the lock: nothing is created in their folder
    folder = ensure_writable_dir(path)
    lock = FileLock(str(folder / LOCK_FILE), timeout=0)
    try:
        lock.acquire()
    except Timeout:
        raise DockError(
            f"output folder {folder} is in use by {_holder(folder)}: wait for it to finish or "
            "use another --out"
        ) from None
    except OSError as exc:
        raise DockError(f"cannot lock output folder {folder}: {exc.strerror or exc}") from None
    failed = False
    try:
        _refuse_foreign(folder, tool)  # again under the lock
        atomic_write_json(
            folder / OWNER_FILE,
            {
                "tool": tool,
                "pid": os.getpid(),
                "claimed_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            },
        )
        clean_stale_temps(folder)
        yield folder
    except BaseException:
        failed = True
        raise
    finally:
        lock.release()
        if failed:
            _remove_if_untouched(folder, made)


def _remove_if_untouched(folder: Path, made: list[Path]) -> None:
    """Remove the folders a failed claim made, if the run wrote nothing into them."""
    if not made:
        return
    with contextlib.suppress(OSError):
        if {p.name for p in folder.iterdir()} <= {OWNER_FILE, LOCK_FILE}:
            for name in (OWNER_FILE, LOCK_FILE):
                (folder / name).unlink(missing_ok=True)
            for d in made:  # innermost first; each is empty by now
                d.rmdir()
