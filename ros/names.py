"""ROS 2 names: topic names checked as ROS 2 checks them, and their DDS topic names."""

from __future__ import annotations

__all__ = ["check_topic", "dds_topic_name"]


def check_topic(topic: str, key: str = "topic") -> str:
    """``topic`` when it is an absolute ROS 2 topic name (``/a/b``).

    Raises:
        ValueError: ``"<key>: ..."`` for a name ROS 2 would refuse: empty, relative,
            characters outside ``[A-Za-z0-9_/]``, ``//``, a trailing ``/``, a token starting
            with a digit.
    """
    if not isinstance(topic, str) or not topic.startswith("/") or topic == "/":
        raise ValueError(f"{key}: must be an absolute ROS name like /a/b, got {topic!r}")
    body = topic[1:]
    ok = all(c.isascii() and (c.isalnum() or c in "_/") for c in body)
    if not ok or any(t == "" or t[0].isdigit() for t in body.split("/")):
        raise ValueError(f"{key}: invalid ROS topic name {topic!r}")
    return topic


def dds_topic_name(topic: str) -> str:
    """The DDS topic of a ROS 2 topic: ``/a/b`` -> ``rt/a/b`` (checked first)."""
    return "rt/" + check_topic(topic)[1:]
