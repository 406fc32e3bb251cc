"""MkDocs hooks of the uwdock handbook (``hooks:`` in mkdocs.yml; run by ``mkdocs build``).

**API sources.** The packages live in top-level folders (``markers/``) but are imported as
``uwdock.markers`` (``pyproject.toml`` maps them). mkdocstrings reads the sources statically
(griffe), which looks for ``uwdock/markers/``; :func:`on_startup` stages that layout, a copy of
the ``.py`` files, under ``build/api-src/`` (git-ignored), which mkdocs.yml names as the
handler's search path. The pages' figures live in ``docs/results/`` beside them.
"""

from __future__ import annotations

import shutil
from pathlib import Path

#: The package folders, in rank order (``uwdock.LAYERS``).
_PACKAGES = ("dockcore", "calibration", "markers", "ros", "perception", "sim", "datasets", "rl")


#: The repository root (this file is ``scripts/mkdocs_hooks.py``).
_ROOT = Path(__file__).resolve().parent.parent


def on_startup(*, command: str, dirty: bool) -> None:
    """Stage ``build/api-src/uwdock/<pkg>/`` from the top-level package folders.

    Runs before any plugin reads its configuration, so the staged folder exists when
    mkdocstrings resolves its search paths (it drops paths that do not exist).
    """
    root = _ROOT
    stage = root / "build" / "api-src" / "uwdock"
    if stage.exists():
        shutil.rmtree(stage)
    stage.mkdir(parents=True)
    for src in (root / "uwdock").glob("*.py"):
        shutil.copy2(src, stage / src.name)
    for pkg in _PACKAGES:
        for src in (root / pkg).rglob("*.py"):
            dst = stage / pkg / src.relative_to(root / pkg)
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst)
