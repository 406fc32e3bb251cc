"""ROS bags as footage: images, camera info and poses from ROS 1 and ROS 2 recordings.

Read with the pure-Python ``rosbags`` package (no ROS installation): a ROS 1 ``.bag`` file, or a
ROS 2 recording, given as its folder (with ``metadata.yaml``) or as its ``.db3`` (SQLite) or
``.mcap`` storage file. Message definitions come from the bag where it holds them, else from
the ROS 2 Humble type store (standard ``sensor_msgs`` / ``geometry_msgs`` / ``nav_msgs``).

* Images: ``sensor_msgs/Image`` (encodings ``mono8``, ``mono16``, ``bgr8``, ``rgb8``,
  ``bgra8``, ``rgba8``, ``8UC1``/``8UC3``/``16UC1``, ``bayer_*8``, ``yuv422``/``uyvy``,
  ``yuyv``) and ``sensor_msgs/CompressedImage`` (JPEG, PNG). They come out as OpenCV reads
  images: (H, W) grey or (H, W, 3) BGR, uint8 or uint16. A message that cannot be decoded gives
  None (a corrupt frame); an encoding this module does not read is a one-line error.
* Time: a message's time is its header stamp (ns) when the header has one, else the time the
  bag recorded it.
* Camera info: ``sensor_msgs/CameraInfo`` as a plain dict (``width``, ``height``, ``k``, ``d``,
  ``distortion_model``, ``r``, ``p``); ``calibration.formats`` turns it into a camera model.
* Poses: ``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped``, ``TransformStamped`` and
  ``nav_msgs/Odometry`` as times and (position, quaternion) rows; ``perception.groundtruth``
  turns them into poses with the pose CSV's rules.

Every failure to open or read a bag is a one-line :class:`DockError` naming the file.

Example:
    >>> with Bag("tank_run.mcap") as bag:
    ...     print(format_topics(bag.topics()))
    ...     for stamp_ns, image in bag.images("/camera/image_raw/compressed"):
    ...         ...
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from uwdock.dockcore.errors import DockError
from uwdock.dockcore.media import quiet_native_stderr

__all__ = [
    "BAG_SUFFIXES",
    "CAMERA_INFO_TYPE",
    "IMAGE_TYPES",
    "POSE_TYPES",
    "Bag",
    "BagTopic",
    "camera_info_topic_for",
    "format_topics",
    "is_bag",
    "nearest_in_time",
    "resolve_image_topic",
]

#: Files read as bags: ROS 1, ROS 2 SQLite storage, ROS 2 MCAP storage.
BAG_SUFFIXES = (".bag", ".db3", ".mcap")
IMAGE_TYPES = frozenset({"sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"})
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
POSE_TYPES = frozenset(
    {
        "geometry_msgs/msg/PoseStamped",
        "geometry_msgs/msg/PoseWithCovarianceStamped",
        "geometry_msgs/msg/TransformStamped",
        "nav_msgs/msg/Odometry",
    }
)


def is_bag(path: str | os.PathLike[str]) -> bool:
    """A ROS bag: a ``.bag`` / ``.db3`` / ``.mcap`` file, or a folder with ``metadata.yaml``."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").is_file()
    return p.suffix.lower() in BAG_SUFFIXES


@dataclass(frozen=True)
class BagTopic:
    """One topic of a bag: name, message type (``pkg/msg/Type``) and message count."""

    name: str
    msgtype: str
    count: int

    @property
    def kind(self) -> str:
        """ "image", "camera_info", "pose" or "other"."""
        if self.msgtype in IMAGE_TYPES:
            return "image"
        if self.msgtype == CAMERA_INFO_TYPE:
            return "camera_info"
        return "pose" if self.msgtype in POSE_TYPES else "other"


def format_topics(topics: list[BagTopic]) -> str:
    """The topics as an aligned listing, one per line (name, messages, type, what it is for)."""
    if not topics:
        return "(no topics)"
    width = max(len(t.name) for t in topics)
    use = {"image": "frames", "camera_info": "camera", "pose": "ground truth", "other": ""}
    return "\n".join(
        f"{t.name:<{width}}  {t.count:>7d}  {t.msgtype}"
        + (f"  [{use[t.kind]}]" if use[t.kind] else "")
        for t in topics
    )


def camera_info_topic_for(image_topic: str, topics: list[BagTopic]) -> str | None:
    """The ``camera_info`` topic that goes with ``image_topic`` by ROS convention (the one in
    the same namespace or the nearest enclosing one, e.g. ``/cam/image_raw/compressed`` ->
    ``/cam/camera_info``), else the only camera-info topic of the bag, else None."""
    infos = [t.name for t in topics if t.kind == "camera_info"]
    parts = image_topic.rstrip("/").split("/")
    for k in range(len(parts) - 1, 0, -1):
        candidate = "/".join(parts[:k]) + "/camera_info"
        if candidate in infos:
            return candidate
    return infos[0] if len(infos) == 1 else None


def nearest_in_time(stamps_ns: np.ndarray, query_ns: int, tolerance_ns: int) -> int | None:
    """Index of the stamp in sorted ``stamps_ns`` nearest ``query_ns`` when within
    ``tolerance_ns``, else None."""
    if stamps_ns.size == 0:
        return None
    k = int(np.searchsorted(stamps_ns, query_ns))
    best = None
    for j in (k - 1, k):
        if 0 <= j < stamps_ns.size:
            d = abs(int(stamps_ns[j]) - int(query_ns))
            if d <= tolerance_ns and (best is None or d < best[0]):
                best = (d, j)
    return None if best is None else best[1]


class Bag:
    """An opened bag (a context manager; :meth:`close` is safe to call twice).

    Args:
        path: ``.bag``, ``.db3``, ``.mcap`` or a ROS 2 recording folder.

    Raises:
        DockError: missing path, not a bag, or a bag that cannot be opened (one line).
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        if not self.path.exists():
            raise DockError(f"bag not found: {self.path}")
        if not is_bag(self.path):
            raise DockError(
                f"{self.path} is not a ROS bag (a {', '.join(BAG_SUFFIXES)} file or a ROS 2 "
                "folder with metadata.yaml)"
            )
        self._reader = AnyReader([self.path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        try:
            self._reader.open()
        except Exception as exc:  # rosbags raises its own errors, and OSError/ValueError
            raise DockError(f"cannot read bag {self.path}: {_one_line(exc)}") from None

    def __enter__(self) -> Bag:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        reader, self._reader = getattr(self, "_reader", None), None
        if reader is not None:
            try:
                reader.close()
            except Exception:  # closing a half-opened reader: nothing more to release
                pass

    # ------------------------------------------------------------------ topics

    def topics(self) -> list[BagTopic]:
        """Every topic, sorted by name."""
        counts: dict[tuple[str, str], int] = {}
        for c in self._reader.connections:
            key = (c.topic, c.msgtype)
            counts[key] = counts.get(key, 0) + int(c.msgcount)
        return sorted((BagTopic(t, m, n) for (t, m), n in counts.items()), key=lambda t: t.name)

    def topic(self, name: str, kinds: tuple[str, ...]) -> BagTopic:
        """The topic ``name``, checked to be one of ``kinds``.

        Raises:
            DockError: no such topic (the message lists the topics of those kinds), or one of
                another type.
        """
        found = [t for t in self.topics() if t.name == name]
        if not found:
            same = [t.name for t in self.topics() if t.kind in kinds]
            raise DockError(
                f"bag {self.path.name} has no topic {name!r} "
                f"({' / '.join(kinds)} topics: {', '.join(same) or 'none'})"
            )
        t = found[0]
        if t.kind not in kinds:
            raise DockError(
                f"topic {name!r} of {self.path.name} is {t.msgtype}, not {' / '.join(kinds)}"
            )
        return t

    def _messages(self, name: str) -> Iterator[tuple[int, Any | None]]:
        """(time ns, message or None when it cannot be deserialised), in recorded order."""
        conns = [c for c in self._reader.connections if c.topic == name]
        try:
            for conn, logtime, raw in self._reader.messages(connections=conns):
                try:
                    msg = self._reader.deserialize(raw, conn.msgtype)
                except Exception:  # a damaged message is one corrupt frame, not the end
                    yield int(logtime), None
                    continue
                yield _stamp_ns(msg, int(logtime)), msg
        except DockError:
            raise
        except Exception as exc:
            raise DockError(
                f"cannot read topic {name!r} of bag {self.path}: {_one_line(exc)}"
            ) from None

    def messages(self, names: list[str]) -> Iterator[tuple[str, str, int, Any | None, bytes, str]]:
        """Every message of the topics ``names``, in the order the bag recorded them:
        ``(topic, type, record time (ns), message or None, raw bytes, error)``; a message that
        does not deserialise comes with None and the reason. The raw bytes are CDR for ROS 2
        recordings, the ROS 1 serialisation for ``.bag`` files."""
        conns = [c for c in self._reader.connections if c.topic in set(names)]
        try:
            for conn, logtime, raw in self._reader.messages(connections=conns):
                try:
                    msg, error = self._reader.deserialize(raw, conn.msgtype), ""
                except Exception as exc:  # a damaged message is refused, not the end
                    msg, error = None, _one_line(exc)
                yield conn.topic, conn.msgtype, int(logtime), msg, bytes(raw), error
        except Exception as exc:
            raise DockError(f"cannot read bag {self.path}: {_one_line(exc)}") from None

    @property
    def is_ros1(self) -> bool:
        """Whether the bag is a ROS 1 ``.bag`` (its raw bytes are not CDR)."""
        return self.path.suffix == ".bag"

    # ------------------------------------------------------------------ content

    def stamps(self, name: str, limit: int | None = None) -> list[int]:
        """Times (ns) of a topic's messages, in order (header stamps where present); the first
        ``limit`` only when given."""
        out: list[int] = []
        for t, _ in self._messages(name):
            if limit is not None and len(out) >= limit:
                break
            out.append(t)
        return out

    def images(self, name: str) -> Iterator[tuple[int, np.ndarray | None]]:
        """(time ns, image or None) for each message of an image topic, in order.

        Raises:
            DockError: not an image topic, or an image encoding this module does not read.
        """
        self.topic(name, ("image",))
        for stamp, msg in self._messages(name):
            if msg is None:
                yield stamp, None
                continue
            with quiet_native_stderr():  # libpng / libjpeg warnings on fd 2 (frames as read)
                image = decode_image_msg(msg, name)
            yield stamp, image

    def camera_info(self, name: str) -> dict[str, Any]:
        """The first ``CameraInfo`` message of a topic as a dict (see the module docstring)."""
        self.topic(name, ("camera_info",))
        for _, msg in self._messages(name):
            if msg is not None:
                return {
                    "width": int(_field(msg, "width")),
                    "height": int(_field(msg, "height")),
                    "distortion_model": str(_field(msg, "distortion_model")),
                    "d": [float(v) for v in np.asarray(_field(msg, "d")).ravel()],
                    "k": [float(v) for v in np.asarray(_field(msg, "k")).ravel()],
                    "r": [float(v) for v in np.asarray(_field(msg, "r")).ravel()],
                    "p": [float(v) for v in np.asarray(_field(msg, "p")).ravel()],
                }
        raise DockError(f"topic {name!r} of bag {self.path.name} holds no readable CameraInfo")

    def poses(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(sorted times ns (N,), poses (N, 7): x, y, z (m), qw, qx, qy, qz) of a pose topic;
        unreadable messages are skipped.

        Raises:
            DockError: not a pose topic.
        """
        self.topic(name, ("pose",))
        items = sorted(
            (
                (stamp, pose_msg_values(msg))
                for stamp, msg in self._messages(name)
                if msg is not None
            ),
            key=lambda it: it[0],
        )
        stamps = np.array([s for s, _ in items], np.int64)
        return stamps, np.array([v for _, v in items], float).reshape(-1, 7)


def resolve_image_topic(
    path: str | os.PathLike[str], topic: str | None, note: Any = None
) -> str | None:
    """The image topic to read from ``path``: None when ``path`` is not a bag; ``topic`` when
    given (checked); else the bag's only image topic, after showing the listing through
    ``note`` (one line per topic).

    Raises:
        DockError: ``topic`` is not an image topic of the bag, or none was given and the bag
            holds no image topic or several (the message names them).
    """
    if not is_bag(path):
        if topic is not None:
            raise DockError(f"--topic is for bags; {path} is not one")
        return None
    with Bag(path) as bag:
        if topic is not None:
            bag.topic(topic, ("image",))
            return topic
        topics = bag.topics()
    images = [t.name for t in topics if t.kind == "image"]
    if note is not None:
        for line in format_topics(topics).splitlines():
            note(line)
    if len(images) == 1:
        if note is not None:
            note(f"reading the bag's only image topic {images[0]} (--topic to choose)")
        return images[0]
    if not images:
        raise DockError(f"bag {Path(path).name} holds no image topic")
    raise DockError(f"bag {Path(path).name} holds {len(images)} image topics: choose one with "
                    f"--topic ({', '.join(images)})")  # fmt: skip


# --------------------------------------------------------------------------- messages


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:300]


def _field(msg: Any, name: str) -> Any:
    """A message field by its ROS 2 name, or its ROS 1 spelling (``K`` for ``k``)."""
    if hasattr(msg, name):
        return getattr(msg, name)
    return getattr(msg, name.upper())


def _stamp_ns(msg: Any, fallback_ns: int) -> int:
    header = getattr(msg, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None:
        return fallback_ns
    ns = int(getattr(stamp, "sec", 0)) * 1_000_000_000 + int(getattr(stamp, "nanosec", 0))
    return ns if ns > 0 else fallback_ns


def _image_codes() -> dict[str, tuple[int, Any, int | None]]:
    """``sensor_msgs/Image`` encodings -> (channels, dtype, OpenCV conversion to BGR or None)."""

    u8, u16 = np.uint8, np.uint16
    return {
        "mono8": (1, u8, None),
        "8uc1": (1, u8, None),
        "mono16": (1, u16, None),
        "16uc1": (1, u16, None),
        "bgr8": (3, u8, None),
        "8uc3": (3, u8, None),
        "rgb8": (3, u8, cv2.COLOR_RGB2BGR),
        "bgra8": (4, u8, cv2.COLOR_BGRA2BGR),
        "8uc4": (4, u8, cv2.COLOR_BGRA2BGR),
        "rgba8": (4, u8, cv2.COLOR_RGBA2BGR),
        "bgr16": (3, u16, None),
        "rgb16": (3, u16, cv2.COLOR_RGB2BGR),
        # ROS names the Bayer pattern by its first row; OpenCV by the second row's pair
        "bayer_rggb8": (1, u8, cv2.COLOR_BayerBG2BGR),
        "bayer_bggr8": (1, u8, cv2.COLOR_BayerRG2BGR),
        "bayer_gbrg8": (1, u8, cv2.COLOR_BayerGR2BGR),
        "bayer_grbg8": (1, u8, cv2.COLOR_BayerGB2BGR),
        "yuv422": (2, u8, cv2.COLOR_YUV2BGR_UYVY),
        "uyvy": (2, u8, cv2.COLOR_YUV2BGR_UYVY),
        "yuv422_yuy2": (2, u8, cv2.COLOR_YUV2BGR_YUYV),
        "yuyv": (2, u8, cv2.COLOR_YUV2BGR_YUYV),
    }


def decode_image_msg(msg: Any, topic: str = "") -> np.ndarray | None:
    """An ``Image`` or ``CompressedImage`` message as an OpenCV image, None when its data is
    damaged (wrong length, undecodable compressed data).

    Raises:
        DockError: an encoding or compressed format this module does not read.
    """

    data = np.asarray(msg.data, dtype=np.uint8).ravel()
    if hasattr(msg, "format") and not hasattr(msg, "encoding"):  # CompressedImage
        fmt = str(msg.format).lower()
        if "compresseddepth" in fmt:
            raise DockError(f"topic {topic!r}: compressedDepth images are depth, not camera frames")
        image = cv2.imdecode(data, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
        return image if image is not None and image.size else None
    encoding = str(msg.encoding).lower()
    codes = _image_codes()
    if encoding not in codes:
        raise DockError(
            f"topic {topic!r}: image encoding {msg.encoding!r} is not one this toolkit reads "
            f"({', '.join(sorted(codes))})"
        )
    channels, dtype, conversion = codes[encoding]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = w * channels * np.dtype(dtype).itemsize
    if h <= 0 or w <= 0 or step < row_bytes or data.size < step * h:
        return None
    rows = data[: step * h].reshape(h, step)[:, :row_bytes]
    image = np.ascontiguousarray(rows).view(dtype).reshape(h, w, channels)
    if np.dtype(dtype).itemsize > 1 and bool(getattr(msg, "is_bigendian", 0)) == np.little_endian:
        image = image.byteswap()  # the data's byte order is not this machine's
    if conversion is not None:
        image = cv2.cvtColor(image if channels > 1 else image[:, :, 0], conversion)
    elif channels == 1:
        image = image[:, :, 0]
    return np.ascontiguousarray(image)


def pose_msg_values(msg: Any) -> np.ndarray:
    """Position (m) and orientation quaternion (w, x, y, z) of a ``PoseStamped``,
    ``PoseWithCovarianceStamped``, ``TransformStamped`` or ``Odometry`` message, as 7 floats
    (unchecked: the caller owns the rule for a valid pose)."""
    if hasattr(msg, "transform"):
        t, q = msg.transform.translation, msg.transform.rotation
    else:
        pose = msg.pose
        pose = getattr(pose, "pose", pose)  # WithCovariance and Odometry nest one level more
        t, q = pose.position, pose.orientation
    return np.array([t.x, t.y, t.z, q.w, q.x, q.y, q.z], float)
