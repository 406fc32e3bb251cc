"""MCAP recordings of ROS 2 messages: what ``ros2 bag record`` writes, without ROS.

One ``.mcap`` file, profile ``ros2``, each type's schema in ``ros2msg`` encoding (its Jazzy
definition and the nested ones, :func:`uwdock.ros.messages.msgdef`) and each message as its CDR
bytes: ``ros2 bag info``, Foxglove and ``rosbags`` read it (``dockcore.bags.Bag`` reads it back
in the toolkit). The file is written beside its final name and renamed into place by
:meth:`McapRecorder.close`, so an interrupted run leaves the previous recording (or nothing),
never half a file under the name asked for; a path that exists and is not a regular file is
refused.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import output_target, replace_checked, temp_sibling
from uwdock.ros import messages as rm

__all__ = ["McapRecorder"]


class McapRecorder:
    """Write ROS 2 messages to ``path`` (module docstring).

    Args:
        path: the ``.mcap`` file to write.

    Raises:
        DockError: ``path`` is a folder, a device or FIFO, or its folder cannot be written.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        # a regular file (a symlink to one is followed) or nothing; a folder, device, FIFO,
        # socket or symlink loop is refused
        self._target = output_target(self.path, "--record")
        if self.path.suffix.lower() != ".mcap":
            raise DockError(f"--record {self.path}: the recording must be a .mcap file")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._tmp = temp_sibling(self._target, ".mcap")
            self._fh = self._tmp.open("wb")
        except OSError as exc:
            raise DockError(f"cannot write {self.path}: {exc.strerror or exc}") from None
        self._writer = Writer(self._fh, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library="uwdock")
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self.count = 0
        self._closed = False

    def _channel(self, topic: str, typename: str) -> int:
        key = (topic, typename)
        ch = self._channels.get(key)
        if ch is None:
            sid = self._schemas.get(typename)
            if sid is None:
                sid = self._schemas[typename] = self._writer.register_schema(
                    typename, "ros2msg", rm.msgdef(typename).encode()
                )
            ch = self._channels[key] = self._writer.register_channel(
                topic, "cdr", sid, {"offered_qos_profiles": ""}
            )
        return ch

    def write_cdr(self, topic: str, typename: str, cdr: bytes, log_time_ns: int) -> None:
        """Record one message's CDR bytes on ``topic`` at ``log_time_ns``."""
        t = max(0, int(log_time_ns))
        self._writer.add_message(self._channel(topic, typename), t, bytes(cdr), t)
        self.count += 1

    def write(self, topic: str, typename: str, msg: Any, log_time_ns: int) -> bytes:
        """Serialise and record ``msg``; returns its CDR bytes."""
        cdr = rm.serialize(msg, typename)
        self.write_cdr(topic, typename, cdr, log_time_ns)
        return cdr

    def close(self) -> Path:
        """Finish the file and move it to its name (the previous file there is replaced only
        now). Returns the path."""
        if self._closed:
            return self.path
        self._closed = True
        try:
            self._writer.finish()
            self._fh.flush()
            os.fsync(self._fh.fileno())
            self._fh.close()
            replace_checked(self._tmp, self._target)  # a node that appeared meanwhile: kept
        except DockError:
            self.discard()
            raise
        except OSError as exc:
            self.discard()
            raise DockError(f"cannot write {self.path}: {exc.strerror or exc}") from None
        return self.path

    def discard(self) -> None:
        """Drop the recording (an interrupted or failed run): nothing is left behind."""
        self._closed = True
        try:
            self._fh.close()
        except OSError:
            pass
        self._tmp.unlink(missing_ok=True)
