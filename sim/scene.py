"""SAPIEN scenes, made whole or not at all.

``sapien.Scene()`` creates its systems (PhysX, and the render system: a Vulkan device, seconds
on a loaded machine) before the scene object itself is initialised; a Ctrl-C or SIGTERM raised
in between leaves a half-made scene whose destructor segfaults. :func:`new_scene` makes it
with those signals held (:func:`uwdock.dockcore.signals.interrupts_deferred`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import sapien

from uwdock.dockcore.signals import interrupts_deferred

__all__ = ["new_scene"]


def new_scene(systems: Sequence[Any] | None = None) -> sapien.Scene:
    """``sapien.Scene(systems)`` (None: SAPIEN's default PhysX CPU and render systems), with
    SIGINT / SIGTERM delivered only once it is whole."""
    with interrupts_deferred():
        return sapien.Scene() if systems is None else sapien.Scene(list(systems))
