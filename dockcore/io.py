"""Atomic file output: a reader (or a crash) never sees a half-written file.

Temporary files are hidden siblings named ``.<name>.<pid>.<random>.uwtmp`` (a video keeps its
container suffix after that: ``….uwtmp.mp4``). A process killed with SIGKILL cannot remove its
own; :func:`clean_stale_temps` removes those whose process is gone, and every command does so in
its output folder when it starts (:func:`dockcore.outdir.claim_output_dir`).
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import shutil
import stat
import tempfile
from collections.abc import Iterator, Mapping
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


#: errors of a write that has run out of room or cannot go to the disk
_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EIO, errno.EFBIG})


def _name_target(exc: OSError, path: Path) -> OSError:
    """The same error, naming ``path`` instead of the hidden temporary file."""
    return type(exc)(exc.errno, exc.strerror or str(exc), str(path))


def _sync(path: Path) -> int:
    """Flush a written temporary file to the disk and return its size (bytes).

    The step between a write and its rename: a write error the kernel reports late (a full
    disk or quota under delayed allocation, NFS) surfaces here as an ``OSError``, while the
    file it would replace still holds its bytes; and a crash after the rename cannot leave a
    0-byte file in its place (the data is on the disk before the name moves). Tests simulate
    a full disk by making this raise ``OSError(errno.ENOSPC)``.
    """
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
        return os.fstat(fd).st_size
    finally:
        os.close(fd)


def _write_all(path: Path, data: bytes) -> None:
    """Write ``data`` into the (temporary) file ``path``, replacing its content."""
    path.write_bytes(data)


#: Largest payload :func:`atomic_write_bytes` reads back after writing (bytes); larger ones are
#: checked by size only.
READ_BACK_MAX_BYTES = 64 * 2**20


def _verify(path: Path, data: bytes) -> None:
    """Check that the temporary file ``path`` holds exactly ``data`` (size, then a read-back of
    payloads up to ``READ_BACK_MAX_BYTES``); an ``OSError`` (EIO) naming ``path`` if not."""
    size = _sync(path)
    ok = size == len(data)
    if ok and len(data) <= READ_BACK_MAX_BYTES:
        ok = path.read_bytes() == data
    if not ok:
        raise OSError(
            errno.EIO,
            f"the written file does not read back ({size} of {len(data)} bytes)",
            str(path),
        )


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is flushed to the disk
    (:func:`_sync`) and renamed onto ``path``.

    On an exception the temporary file is removed and ``path`` is left as it was; a failed
    write (disk full, read-only disk) is an ``OSError`` naming ``path``, not the temporary file.
    What is at ``path`` must be a regular file (a symbolic link to one is followed: the file it
    leads to is replaced) or nothing (:func:`output_target`, checked before the block runs and
    again right before the rename): a device, FIFO, socket, folder or symlink loop there is a
    ``DockError`` and is left as it is.
    """
    with _atomic_path(path, sync=True) as tmp:
        yield tmp


@contextlib.contextmanager
def _atomic_path(path: str | os.PathLike[str], sync: bool) -> Iterator[Path]:
    """:func:`atomic_path`; ``sync=False`` when the block has flushed and verified the file."""
    path = Path(path)
    target = output_target(path)  # refused before anything is written
    tmp_path = temp_sibling(target)
    try:
        yield tmp_path
        if sync:
            _sync(tmp_path)
        os.chmod(tmp_path, 0o644)
        replace_checked(tmp_path, target)
    except OSError as exc:
        tmp_path.unlink(missing_ok=True)
        # a failed write through a file object (fh.write, close) names no file at all
        unnamed_write = exc.filename is None and exc.errno in _WRITE_ERRNOS
        if exc.filename == str(tmp_path) or unnamed_write:
            raise _name_target(exc, path) from None
        raise
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically, verified before the rename (size and read-back),
    and return the path."""
    with _atomic_path(path, sync=False) as tmp:
        _write_all(tmp, data)
        _verify(tmp, data)  # flushes it
    return Path(path)


def atomic_write_files(files: Mapping[str | os.PathLike[str], bytes]) -> list[Path]:
    """Write several files as one unit: a file and its sidecar (``.onnx`` + ``.json``), a
    camera's YAML and JSON twins.

    Every file is written to a temporary sibling and verified (:func:`_verify`) before any is
    renamed; the renames then run one after the other, and if one fails the files already
    renamed get their previous content back (kept as hard links until the end). So a failure
    (a full disk, an interrupt) leaves either all the new files or the old set as it was
    (a file that did not exist before is removed again). Each target must be a regular file
    (or a symbolic link to one, followed) or nothing: checked before anything is written,
    before the first rename and before each (:func:`output_target`).

    Args:
        files: target path -> content, in the order of the renames.

    Returns:
        The paths written.

    Raises:
        OSError: naming the target whose write or rename failed.
        DockError: a target is not a regular file (:func:`output_target`).
    """
    given = [Path(p) for p in files]
    # every target checked before anything is written: a device, FIFO, socket, folder or
    # symlink loop at any of them refuses the whole unit (a symlink to a file is followed)
    targets = [output_target(p) for p in given]
    if len(set(targets)) < len(targets):
        raise DockError(f"the files {', '.join(map(str, given))} are not all different files")
    temps: list[Path] = []
    backups: dict[Path, Path | None] = {}
    done: list[Path] = []
    try:
        for shown, target, data in zip(given, targets, files.values(), strict=True):
            tmp = temp_sibling(target)
            temps.append(tmp)
            try:
                _write_all(tmp, data)
                _verify(tmp, data)
                os.chmod(tmp, 0o644)
            except OSError as exc:
                raise _name_target(exc, shown) from None
        for target in targets:  # again, now that all is written: before the first rename
            output_target(target)
        for target in targets:  # keep the old versions until every rename went through
            backups[target] = None
            if target.is_file():
                backup = temp_sibling(target)
                backup.unlink()
                try:
                    os.link(target, backup)
                except OSError:  # a file system without hard links: a copy
                    shutil.copy2(target, backup)
                backups[target] = backup
        for shown, target, tmp in zip(given, targets, temps, strict=True):
            try:
                replace_checked(tmp, target)
            except OSError as exc:
                raise _name_target(exc, shown) from None
            done.append(target)
    except BaseException:
        for target in reversed(done):  # put the old set back
            with contextlib.suppress(OSError):
                backup = backups.get(target)
                if backup is not None:
                    os.replace(backup, target)
                else:
                    target.unlink()
        raise
    finally:
        for p in [*temps, *(b for b in backups.values() if b is not None)]:
            with contextlib.suppress(OSError):
                p.unlink(missing_ok=True)
    return given


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically and return the path."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike[str], obj: Any) -> Path:
    """Write ``obj`` as indented JSON atomically and return the path."""
    return atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")


def ensure_writable_dir(path: str | os.PathLike[str]) -> Path:
    """Create ``path`` if needed and check that files can be created in it.

    Raises:
        DockError: one line naming the folder, if it cannot be created or written, or if
            something other than a folder is there (:func:`check_output_dir`).
    """
    path = check_output_dir(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        temp_sibling(path / "write-probe").unlink()
    except OSError as exc:
        raise DockError(f"cannot write to output folder {path}: {exc.strerror or exc}") from None
    return path


_SPECIAL_KINDS = (
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def special_file_kind(path: str | os.PathLike[str]) -> str | None:
    """What ``path`` is when it is a special file ("a FIFO (named pipe)", "a character device",
    "a block device", "a socket"; a symlink is followed), else None (a regular file, a folder,
    or nothing there). Only ``stat``: nothing is opened, so a FIFO does not block."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None
    for test, kind in _SPECIAL_KINDS:
        if test(mode):
            return kind
    return None


def check_regular_file(path: str | os.PathLike[str], what: str = "file") -> Path:
    """``path`` as a ``Path`` when it is a regular file (or a symlink to one), checked before
    anything reads it: a FIFO would block the reader until someone writes into it, a device
    may never end.

    Raises:
        DockError: one line calling the file ``what``: missing, a folder, or a special file.
    """
    path = Path(path)
    kind = special_file_kind(path)
    if kind is not None:
        raise DockError(f"{what} {path} is {kind}, not a regular file")
    if path.is_dir():
        raise DockError(f"{what} is a folder, not a file: {path}")
    if not path.is_file():
        raise DockError(f"{what} not found: {path}")
    return path


# ----------------------------------------------------------------- what an output may replace


def _node_kind(mode: int) -> str | None:
    """What a file of ``mode`` is when it is not a regular file ("a folder", "a FIFO (named
    pipe)", ...), else None."""
    if stat.S_ISDIR(mode):
        return "a folder"
    for test, kind in _SPECIAL_KINDS:
        if test(mode):
            return kind
    return None if stat.S_ISREG(mode) else "a special file"


def _follow(path: Path, what: str) -> os.stat_result | None:
    """``lstat`` of ``path`` and, for a symbolic link, ``stat`` of what it leads to; None when
    nothing is there. A symlink loop (at ``path`` or in a folder above it) or a dangling link
    is a ``DockError`` (one line, naming ``path``); another failure (a file where a folder of
    the path should be, no permission) the ``OSError``, naming ``path``."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise DockError(f"{what} {path}: a folder on its path is a symlink loop") from None
        raise _name_target(exc, path) from None
    if not stat.S_ISLNK(st.st_mode):
        return st
    try:
        return os.stat(path)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise DockError(f"{what} {path} is a symlink loop") from None
        if exc.errno in (errno.ENOENT, errno.ENOTDIR):
            try:
                link = os.readlink(path)
            except OSError:
                link = "?"
            raise DockError(f"{what} {path} is a dangling symlink (to {link})") from None
        raise _name_target(exc, path) from None


def output_target(path: str | os.PathLike[str], what: str = "output file") -> Path:
    """The file a write to ``path`` replaces, checked: ``path`` itself when nothing or a regular
    file is there, the file a symbolic link leads to when it leads to a regular file.

    Only ``lstat``/``stat``: nothing is opened (a FIFO does not block).

    Raises:
        DockError: one line naming ``path`` (called ``what``) and what is there: a folder, a
            character or block device, a FIFO, a socket, a symlink loop or a dangling symlink.
        OSError: ``path`` cannot be looked at (a file where a folder of it should be).
    """
    path = Path(path)
    st = _follow(path, what)
    if st is None:
        return path
    kind = _node_kind(st.st_mode)
    if kind == "a folder":
        raise DockError(f"{what} {path} is a folder, not a file")
    if kind is not None:
        raise DockError(f"{what} {path} is {kind}, not a regular file: it is not replaced")
    return Path(os.path.realpath(path)) if os.path.islink(path) else path


def replace_checked(tmp: str | os.PathLike[str], target: str | os.PathLike[str]) -> None:
    """``os.replace(tmp, target)`` when ``target`` is still a regular file or nothing (a node
    can appear between an output's first check and its rename); a ``DockError`` otherwise, and
    ``tmp`` is left for the caller to remove."""
    output_target(target)
    os.replace(tmp, target)


def check_output_path(
    path: str | os.PathLike[str],
    what: str = "--out",
    sidecars: tuple[str | os.PathLike[str], ...] | list[Path] = (),
) -> Path:
    """Check an output file and the files written with it (``x.json`` beside ``x.yaml``,
    ``<stem>_report.json``) before any work: each must be a regular file (or a symbolic link
    to one) or nothing (:func:`output_target`).

    Returns:
        ``path`` as a ``Path``.

    Raises:
        DockError: one line naming the first path that is refused and what it is.
    """
    path = Path(path)
    output_target(path, what)
    for sidecar in sidecars:
        output_target(sidecar, f"{what} {path}: its sidecar")
    return path


def check_output_dir(path: str | os.PathLike[str], what: str = "output folder") -> Path:
    """Check an output folder before any work: nothing there (it is created later), a folder,
    or a symbolic link to one.

    Returns:
        ``path`` as a ``Path``.

    Raises:
        DockError: one line naming ``path`` and what it is: a file, a device, a FIFO, a socket,
            a symlink loop or a dangling symlink; or that it cannot be looked at.
    """
    path = Path(path)
    try:
        st = _follow(path, what)
    except OSError as exc:
        raise DockError(f"cannot write to output folder {path}: {exc.strerror or exc}") from None
    if st is None or stat.S_ISDIR(st.st_mode):
        return path
    kind = _node_kind(st.st_mode) or "a file"
    raise DockError(f"{what} {path} is {kind}, not a folder")


def read_text(path: str | os.PathLike[str], what: str = "file") -> str:
    """A user's UTF-8 text file (a byte-order mark is accepted), as text.

    Raises:
        ConfigError: one line calling the file ``what``: missing, a folder, a special file
            (FIFO, device, socket: refused before it is opened), unreadable, or not UTF-8
            (naming the first bad byte).
    """
    path = Path(path)
    kind = special_file_kind(path)
    if kind is not None:
        raise ConfigError(f"{what} {path} is {kind}, not a regular file")
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
