"""File names as text: a name that is not UTF-8 shown the same way in every output.

On POSIX a file name is bytes; Python carries the bytes that are not UTF-8 as lone surrogates
(``os.fsdecode``: ``b"caf\\xe9.png"`` -> ``"caf\\udce9.png"``), which round-trip to the file
but crash what expects text: OpenCV's Python binding (exit 139), a UTF-8 CSV or JSON writer, a
terminal in a strict UTF-8 locale. Files are always opened by their real name; what the toolkit
*writes about* a name (a row of detections.jsonl, a label on an image, an error line) is
:func:`display_name`.
"""

from __future__ import annotations

import os
from typing import Any

__all__ = ["ascii_text", "display_name"]


def display_name(name: str | bytes | os.PathLike[Any]) -> str:
    """A file or folder name as text that any output can hold (a JSON or CSV file, an image
    label, a plot, a terminal): the bytes of a name that are not UTF-8, which Python carries as
    lone surrogates (``os.fsdecode``), are shown as ``\\xNN`` (``caf\\xe9.png``); any other
    name comes back unchanged. The files themselves are always opened by their real name."""
    raw = os.fspath(name)
    if isinstance(raw, str):
        try:
            raw = raw.encode("utf-8", "surrogateescape")
        except UnicodeEncodeError:  # a lone surrogate that no file name decodes to
            return raw.encode("utf-8", "backslashreplace").decode("utf-8")
    return raw.decode("utf-8", "backslashreplace")


def ascii_text(text: str) -> str:
    """``text`` for OpenCV's Hershey fonts, which draw ASCII only (and whose Python binding
    crashes on a lone surrogate): :func:`display_name`, other characters as ``\\xNN``,
    ``\\uNNNN``."""
    return display_name(text).encode("ascii", "backslashreplace").decode("ascii")
