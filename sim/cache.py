"""The toolkit's cache of generated files (marker meshes, derived shaders): where it is and how
a folder in it is built once, safely against concurrent processes and kills.

The cache is ``$UWDOCK_CACHE_DIR``, else ``$XDG_CACHE_HOME/uwdock``, else ``~/.cache/uwdock``.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

from uwdock.dockcore.io import clean_stale_temps, temp_sibling

__all__ = ["build_once", "cache_root"]


def cache_root() -> Path:
    """The cache folder (not created here)."""
    env = os.environ.get("UWDOCK_CACHE_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "uwdock"


def build_once(final: Path, marker: str, make: Callable[[Path], None]) -> Path:
    """The folder ``final``, built by ``make(tmp)`` into a temporary sibling that is renamed
    onto ``final`` when complete; skipped when ``final / marker`` already exists.

    Temporaries of killed processes are removed first; when another process finishes the same
    folder first, its folder is kept.

    Args:
        final: the folder to build (its parent is created).
        marker: a file ``make`` writes last: its presence means the folder is complete.
        make: writes the folder's content into the path it is given.

    Returns:
        ``final``.
    """
    if (final / marker).is_file():
        return final
    clean_stale_temps(final.parent, recursive=False)
    tmp = temp_sibling(final, folder=True)  # creates the parent
    try:
        make(tmp)
        try:
            os.replace(tmp, final)
        except OSError:  # another process won the race: keep its folder
            if not (final / marker).is_file():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final
