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
* **no stale files**: a command that tracks its outputs (:func:`tracked_outputs`: ``markers
  generate``, ``perception detect``, ``perception eval``) lists them in ``.uwdock-files.json``;
  its rerun into the same folder removes the files of the previous run it did not write again
  (only those listed: never a user's own files).
* **ownership up the tree**: a folder inside another tool's output folder is refused too
  (``perception detect --out`` into a synth dataset's ``images/``).

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
from uwdock.dockcore.io import (
    atomic_write_json,
    check_output_dir,
    clean_stale_temps,
    ensure_writable_dir,
)

OWNER_FILE = ".uwdock-owner.json"
LOCK_FILE = ".uwdock.lock"
#: The files a command wrote into its output folder on its last run (relative paths), so that a
#: rerun removes what it no longer writes (:func:`tracked_outputs`).
MANIFEST_FILE = ".uwdock-files.json"

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


def claimed_by(path: str | os.PathLike[str]) -> int | None:
    """The process id in the claim :func:`claim_output_dir` wrote into ``path``, or None."""
    try:
        owner = json.loads((Path(path) / OWNER_FILE).read_text(encoding="utf-8"))
        pid = owner.get("pid") if isinstance(owner, dict) else None
    except (OSError, ValueError):
        return None
    return pid if isinstance(pid, int) and not isinstance(pid, bool) else None


def _holder(path: Path) -> str:
    try:
        owner = json.loads((path / OWNER_FILE).read_text(encoding="utf-8"))
        return f"`{owner.get('tool')}`, pid {owner.get('pid')}"
    except (OSError, ValueError, AttributeError):
        return "another process"


def _refuse_foreign(folder: Path, tool: str) -> None:
    """Refuse ``folder`` when it, or a folder above it, holds the output of another tool
    (``perception detect --out`` into a synth dataset's ``images/``), as named and with its
    symbolic links followed (a link to the dataset's ``images/`` is that folder)."""
    real = folder.resolve()
    if real != folder:
        _refuse_foreign_at(real, tool)
    _refuse_foreign_at(folder, tool)


def _refuse_foreign_at(folder: Path, tool: str) -> None:
    owner = folder_owner(folder) if folder.is_dir() else None
    if owner is not None and owner != tool:
        raise DockError(
            f"{folder} holds the output of `{owner}`; `{tool}` will not write into it: "
            "use another --out"
        )
    for parent in folder.parents:
        owner = folder_owner(parent) if parent.is_dir() else None
        if owner is not None and owner != tool:
            raise DockError(
                f"{folder} is inside {parent}, the output of `{owner}`; `{tool}` will not "
                "write into it: use another --out"
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
            belongs to another tool, or is not a folder (a file, device, FIFO, socket or
            symlink loop: :func:`dockcore.io.check_output_dir`).
    """
    check_output_dir(path)  # a device, FIFO, socket, file or symlink loop: refused first
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
        if {p.name for p in folder.iterdir()} <= {OWNER_FILE, LOCK_FILE, MANIFEST_FILE}:
            for name in (OWNER_FILE, LOCK_FILE, MANIFEST_FILE):
                (folder / name).unlink(missing_ok=True)
            for d in made:  # innermost first; each is empty by now
                d.rmdir()


# ---------------------------------------------------------------------------- stale outputs


class OutputSet:
    """The files a run writes into its output folder (see :func:`tracked_outputs`).

    Args:
        folder: the claimed output folder.
    """

    def __init__(self, folder: Path) -> None:
        self.folder = Path(os.path.realpath(folder))
        self.previous = _read_manifest(self.folder)
        self.written: set[str] = set()

    def add(self, *paths: str | os.PathLike[str]) -> None:
        """Record files written by this run (absolute, or relative to the folder); paths
        outside the folder are ignored."""
        for p in paths:
            rel = _relative(self.folder, Path(p))
            if rel is not None:
                self.written.add(rel)

    def stale(self) -> list[Path]:
        """Files of the previous run that this run did not write (and that still exist)."""
        out = []
        for rel in sorted(self.previous - self.written):
            p = self.folder / rel
            if p.is_file() and not p.is_symlink():
                out.append(p)
        return out

    def prune(self) -> list[Path]:
        """Remove :meth:`stale` files (and folders they leave empty); returns them."""
        removed = []
        for p in self.stale():
            with contextlib.suppress(OSError):
                p.unlink()
                removed.append(p)
                for parent in p.parents:  # a folder of the run's own left empty
                    if parent == self.folder or not parent.is_relative_to(self.folder):
                        break
                    parent.rmdir()  # OSError when not empty: stop
        return removed

    def save(self, keep_previous: bool = False) -> None:
        """Write the manifest: this run's files (with the previous run's, after a failure)."""
        files = self.written | (self.previous if keep_previous else set())
        atomic_write_json(self.folder / MANIFEST_FILE, {"files": sorted(files)})


def _relative(folder: Path, path: Path) -> str | None:
    """``path`` relative to ``folder`` as a POSIX string, or None when outside it."""
    p = path if path.is_absolute() else folder / path
    try:
        rel = Path(os.path.realpath(p)).relative_to(folder)
    except ValueError:
        return None
    text = rel.as_posix()
    return None if text in (".", "") or text.startswith("..") else text


def _read_manifest(folder: Path) -> set[str]:
    """The previous run's files (relative paths inside ``folder``); empty when the manifest is
    missing or unreadable. Entries that would leave the folder are dropped."""
    try:
        data = json.loads((folder / MANIFEST_FILE).read_text(encoding="utf-8"))
        files = data["files"] if isinstance(data, dict) else []
    except (OSError, ValueError, KeyError):
        return set()
    out = set()
    for f in files if isinstance(files, list) else []:
        if isinstance(f, str) and f and not Path(f).is_absolute():
            rel = _relative(folder, Path(f))
            if rel is not None and rel != MANIFEST_FILE:
                out.add(rel)
    return out


@contextlib.contextmanager
def tracked_outputs(
    folder: str | os.PathLike[str], written: list[Path] | None = None
) -> Iterator[OutputSet]:
    """Track the files a run writes into its (claimed) output folder, so that a rerun into the
    same folder removes the files of the previous run that it no longer writes.

    The block records what it writes with :meth:`OutputSet.add`, or appends the paths to
    ``written`` (read when the block ends, however it ends). On success the previous run's
    files not written again are removed (only files listed in ``.uwdock-files.json``: the
    toolkit's own, never a user's) and the manifest is rewritten; on a failure nothing is
    removed and the manifest lists the files of both runs, so the next successful run removes
    what it does not write.
    """
    outputs = OutputSet(Path(folder))
    try:
        yield outputs
    except BaseException:
        outputs.add(*(written or ()))
        if outputs.written - outputs.previous:
            with contextlib.suppress(OSError):
                outputs.save(keep_previous=True)
        raise
    outputs.add(*(written or ()))
    outputs.prune()
    outputs.save()
