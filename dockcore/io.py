"""Atomic file output: a reader (or a crash) never sees a half-written file.

Temporary files are hidden siblings named ``.<name>.<pid>.<random>.uwtmp`` (a video keeps its
container suffix after that: ``….uwtmp.mp4``). A process killed with SIGKILL cannot remove its
own; :func:`clean_stale_temps` removes those whose process is gone, and every command does so in
its output folder when it starts (:func:`dockcore.outdir.claim_output_dir`).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from uwdock.dockcore.errors import ConfigError, DockError

#: The mark in the name of every temporary file or folder the toolkit writes.
TEMP_MARK = ".uwtmp"
_TEMP_RE = re.compile(r"^\..*\.(\d+)\.[A-Za-z0-9_]+\.uwtmp(\.[A-Za-z0-9]+)?$")


def temp_prefix(name: str) -> str:
    """The ``mkstemp``/``mkdtemp`` prefix of a temporary sibling of ``name`` (this process)."""
    return f".{name}.{os.getpid()}."


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def clean_stale_temps(folder: str | os.PathLike[str], recursive: bool = True) -> int:
    """Remove temporary files and folders left in ``folder`` by processes that are gone.

    Returns:
        How many were removed. Unreadable folders are skipped; files of live processes kept.
    """
    folder = Path(folder)
    removed = 0
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return 0
    for entry in entries:
        m = _TEMP_RE.match(entry.name)
        if m and not _pid_alive(int(m.group(1))):
            try:
                if entry.is_dir(follow_symlinks=False):
                    shutil.rmtree(entry.path)
                else:
                    os.unlink(entry.path)
                removed += 1
            except OSError:
                pass
        elif recursive and entry.is_dir(follow_symlinks=False):
            removed += clean_stale_temps(entry.path, recursive=True)
    return removed


def temp_sibling(path: str | os.PathLike[str], suffix: str = "", folder: bool = False) -> Path:
    """Create a hidden temporary file (or folder) beside ``path`` and return it.

    Named ``.<name>.<pid>.<random>.uwtmp<suffix>``, so :func:`clean_stale_temps` can remove it
    once this process is gone. ``suffix`` keeps a container suffix (``".mp4"``) for writers that
    pick the format from the name. An ``OSError`` names ``path``, not the temporary file.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        kw = {"prefix": temp_prefix(path.name), "suffix": TEMP_MARK + suffix, "dir": path.parent}
        if folder:
            return Path(tempfile.mkdtemp(**kw))
        fd, tmp = tempfile.mkstemp(**kw)
    except OSError as exc:
        raise _name_target(exc, path) from None
    os.close(fd)
    return Path(tmp)


def _name_target(exc: OSError, path: Path) -> OSError:
    """The same error, naming ``path`` instead of the hidden temporary file."""
    return type(exc)(exc.errno, exc.strerror or str(exc), str(path))


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed onto ``path``.

    On an exception the temporary file is removed and ``path`` is left as it was; a failed
    write (disk full, read-only disk) is an ``OSError`` naming ``path``, not the temporary file.
    """
    path = Path(path)
    tmp_path = temp_sibling(path)
    try:
        yield tmp_path
        os.chmod(tmp_path, 0o644)
        os.replace(tmp_path, path)
    except OSError as exc:
        tmp_path.unlink(missing_ok=True)
        if exc.filename == str(tmp_path):
            raise _name_target(exc, path) from None
        raise
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically and return the path."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically and return the path."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike[str], obj: Any) -> Path:
    """Write ``obj`` as indented JSON atomically and return the path."""
    return atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")


def ensure_writable_dir(path: str | os.PathLike[str]) -> Path:
    """Create ``path`` if needed and check that files can be created in it.

    Raises:
        DockError: one line naming the folder, if it cannot be created or written.
    """
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        temp_sibling(path / "write-probe").unlink()
    except OSError as exc:
        raise DockError(f"cannot write to output folder {path}: {exc.strerror or exc}") from None
    return path


def read_text(path: str | os.PathLike[str], what: str = "file") -> str:
    """A user's UTF-8 text file (a byte-order mark is accepted), as text.

    Raises:
        ConfigError: one line calling the file ``what``: missing, a folder, unreadable, or not
            UTF-8 (naming the first bad byte).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{what} not found: {path}") from None
    except IsADirectoryError:
        raise ConfigError(f"{what} is a folder, not a file: {path}") from None
    except OSError as exc:
        raise ConfigError(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{what} {path} is not UTF-8 text (byte {exc.start}: {data[exc.start]:#04x})"
        ) from None
