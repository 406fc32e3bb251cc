"""The shape of the tree, read from the source with ``ast`` (nothing is imported):

(a) no import from a package to one of the same or a higher rank (``uwdock.LAYERS``; perception
    and sim are peers and never import each other);
(b) no import cycle between modules (module-level and function-level imports both count);
(c) no function-local import of a ``uwdock`` module, and function-local imports otherwise only of
    a short list of heavy optional third-party modules (those an extra installs, or that take
    seconds to import);
(d) the bare folder names (``import datasets`` ...) never give the project.

Each check is a function over a folder, shown to fail on a planted violation in a temporary tree.
"""

from __future__ import annotations

import ast
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest

from uwdock import LAYERS

ROOT = Path(__file__).resolve().parents[1]

#: Third-party modules a function may import lazily: each is installed by an extra or takes
#: seconds to import, so a command that does not need it must not pay for it (``<group> --help``
#: and ``import uwdock.rl.env`` are timed by ``bench/bench_startup.py``).
HEAVY_OPTIONAL = frozenset(
    {
        # base dependencies, but each costs 0.2-1 s to import on 2 busy cores and only a few
        # functions use it: trimesh (~1 s with networkx: the marker meshes), scipy (0.5 s for
        # scipy.spatial or scipy.optimize: batch rotations, one fit, one hull), matplotlib
        # (0.2-0.4 s: sheets, previews, plots)
        "trimesh",
        "scipy",
        # ROS bags: ~0.1 s (rosbags.highlevel with its type stores), only when a bag is read
        "rosbags",
        "torch",
        "stable_baselines3",
        "sapien",
        "numba",
        "onnxruntime",
        "onnx",
        "gymnasium",
        "tensorboard",
        "open3d",
        "matplotlib",
        "mpl_toolkits",
        "av",  # FFmpeg's libraries, loaded only where a video is written
        "ray",  # the uwdock[ray] extra, only for --backend ray (dockcore.pool)
    }
)

#: Rank of the namespace's own modules: its ``__init__`` (LAYERS, the version) sits below every
#: package, its umbrella command above them all.
_TOP_RANKS = {"uwdock": -1, "uwdock.cli": max(LAYERS.values()) + 1}


@dataclass(frozen=True)
class Import:
    """One import statement: ``importer`` (a module of the tree) imports ``target`` (a dotted
    name: a module of the tree where it resolves to one, else the third-party name)."""

    importer: str
    target: str
    line: int
    local: bool  # inside a function (or a class body inside one)
    typing_only: bool = False  # under ``if TYPE_CHECKING:``: never executed

    def where(self, files: dict[str, Path]) -> str:
        return f"{files[self.importer]}:{self.line}: {self.importer} imports {self.target}"


def module_files(root: Path, layers: dict[str, int]) -> dict[str, Path]:
    """Dotted module name (``uwdock.rl.env``) -> source file, for every ``.py`` under the package
    folders named in ``layers`` and the ``uwdock`` namespace folder itself."""
    files: dict[str, Path] = {}
    folders = {"uwdock": root / "uwdock"}
    folders.update({pkg: root / pkg for pkg in layers})
    for pkg, folder in folders.items():
        prefix = ["uwdock"] if pkg == "uwdock" else ["uwdock", pkg]
        for path in sorted(folder.rglob("*.py")):
            parts = list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            files[".".join(prefix + parts)] = path
    return files


def _resolve(name: str, modules: dict[str, Path]) -> str:
    """The longest prefix of ``name`` that is a module of the tree ('' if none)."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name


def imports_in(modules: dict[str, Path]) -> list[Import]:
    """Every import statement of every module, each name of a ``from x import a, b`` resolved to
    a module of the tree where it is one (``from uwdock.rl import env`` -> ``uwdock.rl.env``)."""
    found: list[Import] = []
    for name, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        is_pkg = path.name == "__init__.py"
        _walk(tree, name, is_pkg, modules, False, False, found)
    return found


def _is_type_checking(node: ast.AST) -> bool:
    test = node.test if isinstance(node, ast.If) else None
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _walk(node, name, is_pkg, modules, local, typing_only, found) -> None:
    for child in ast.iter_child_nodes(node):
        inner = local or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
        typed = typing_only or _is_type_checking(child)
        if isinstance(child, ast.Import):
            for alias in child.names:
                target = _resolve(alias.name, modules) or alias.name
                found.append(Import(name, target, child.lineno, local, typing_only))
        elif isinstance(child, ast.ImportFrom):
            base = child.module or ""
            if child.level:
                pkg = name.split(".") if is_pkg else name.split(".")[:-1]
                pkg = pkg[: len(pkg) - child.level + 1]
                base = ".".join([*pkg, base] if base else pkg)
            if base == "__future__":
                continue
            for alias in child.names:
                target = _resolve(f"{base}.{alias.name}", modules) or _resolve(base, modules)
                found.append(Import(name, target or base, child.lineno, local, typing_only))
        _walk(child, name, is_pkg, modules, inner, typed, found)


def _rank(module: str, layers: dict[str, int]) -> tuple[str, int]:
    if module in _TOP_RANKS:
        return module, _TOP_RANKS[module]
    pkg = module.split(".")[1]
    return pkg, layers[pkg]


def upward_imports(root: Path, layers: dict[str, int]) -> list[str]:
    """Imports from a package to one of the same rank (a peer) or a higher one."""
    files = module_files(root, layers)
    bad = []
    for imp in imports_in(files):
        if imp.target not in files:
            continue
        (pa, ra), (pb, rb) = _rank(imp.importer, layers), _rank(imp.target, layers)
        if pa != pb and rb >= ra:
            bad.append(imp.where(files))
    return bad


def import_cycles(root: Path, layers: dict[str, int]) -> list[list[str]]:
    """The module sets that import each other in a ring (strongly connected components of the
    import graph with more than one module, or a module importing itself). Imports under
    ``if TYPE_CHECKING:`` (annotations only, never run) are not edges."""
    files = module_files(root, layers)
    graph: dict[str, set[str]] = {m: set() for m in files}
    for imp in imports_in(files):
        if imp.target in files and not imp.typing_only:
            graph[imp.importer].add(imp.target)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    rings: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            ring = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                ring.append(w)
                if w == v:
                    break
            if len(ring) > 1 or v in graph[v]:
                rings.append(sorted(ring))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return rings


def local_import_violations(
    root: Path,
    layers: dict[str, int],
    allowed: frozenset[str] = HEAVY_OPTIONAL,
) -> list[str]:
    """Function-local imports of a ``uwdock`` module, of the standard library or of a
    third-party module not in ``allowed``."""
    files = module_files(root, layers)
    hits = [
        imp.where(files)
        for imp in imports_in(files)
        if imp.local and imp.target.split(".")[0] not in allowed
    ]
    return list(dict.fromkeys(hits))  # one line per imported module


def bare_name_gives_project(name: str, cwd: Path, root: Path = ROOT) -> str | None:
    """Run ``python -c "import <name>"`` in ``cwd``; a description of what it gave if that is a
    folder of ``root`` (the project under a bare name), else None (another package, or an
    ImportError that names ``uwdock.<name>``, or no such module)."""
    code = (
        "import sys\n"
        "try:\n"
        f"    import {name} as m\n"
        "except ModuleNotFoundError:\n"
        "    print('absent'); sys.exit(0)\n"
        "except ImportError as exc:\n"
        "    print('refused', exc); sys.exit(0)\n"
        "print('file', getattr(m, '__file__', None) or list(getattr(m, '__path__', [])))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=60
    )
    if out.returncode != 0:
        return f"import {name} in {cwd} crashed: {out.stderr.strip().splitlines()[-1:]}"
    text = out.stdout.strip()
    if text == "absent":
        return None
    if text.startswith("refused"):
        return None if f"uwdock.{name}" in text else f"import {name} in {cwd}: {text}"
    if str(root.resolve()) in text:
        return f"import {name} in {cwd} gives the project: {text}"
    return None


# --- the tree ---------------------------------------------------------------------------------


def test_packages_are_the_layers():
    """Every package folder of the tree is ranked (so none escapes the checks below)."""
    assert set(LAYERS) == {
        "dockcore",
        "calibration",
        "markers",
        "perception",
        "sim",
        "datasets",
        "rl",
    }
    files = module_files(ROOT, LAYERS)
    assert {m.split(".")[1] for m in files if m.count(".") >= 1} >= set(LAYERS)
    assert len(files) > 60


def test_no_upward_or_peer_imports():
    assert upward_imports(ROOT, LAYERS) == []


def test_no_import_cycles():
    assert import_cycles(ROOT, LAYERS) == []


def test_function_local_imports_only_for_heavy_optional_modules():
    assert local_import_violations(ROOT, LAYERS) == []


@pytest.mark.parametrize("where", ["root", "elsewhere"])
def test_bare_folder_names_are_not_the_project(where, tmp_path):
    cwd = ROOT if where == "root" else tmp_path
    for name in LAYERS:
        assert bare_name_gives_project(name, cwd) is None


# --- each check fails on a planted violation --------------------------------------------------

_PLANT_LAYERS = {"low": 0, "mid": 1, "peer_a": 2, "peer_b": 2, "top": 3}


def _plant(root: Path, files: dict[str, str]) -> Path:
    for rel, text in {
        "uwdock/__init__.py": "",
        **{f"{pkg}/__init__.py": "" for pkg in _PLANT_LAYERS},
        **files,
    }.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text), encoding="utf-8")
    return root


def test_clean_planted_tree_passes(tmp_path):
    root = _plant(
        tmp_path,
        {
            "low/a.py": "import json\n",
            "mid/b.py": "from uwdock.low.a import x\nfrom . import c\n",
            "mid/c.py": "def f():\n    import torch\n",
            "top/d.py": "from uwdock.mid import b\nfrom uwdock.peer_a import e\n",
            "peer_a/e.py": "from uwdock.mid.b import y\n",
            # a back-reference for annotations only is not a ring
            "low/t.py": "from uwdock.low import u\n",
            "low/u.py": "import typing\nif typing.TYPE_CHECKING:\n    from . import t\n",
        },
    )
    assert upward_imports(root, _PLANT_LAYERS) == []
    assert import_cycles(root, _PLANT_LAYERS) == []
    assert local_import_violations(root, _PLANT_LAYERS) == []


def test_upward_import_is_found(tmp_path):
    root = _plant(tmp_path, {"low/a.py": "def f():\n    from uwdock.top.d import g\n"})
    root = _plant(root, {"top/d.py": "g = 1\n"})
    (hit,) = upward_imports(root, _PLANT_LAYERS)
    assert "uwdock.low.a imports uwdock.top.d" in hit


def test_peer_import_is_found(tmp_path):
    root = _plant(tmp_path, {"peer_a/e.py": "from uwdock.peer_b import f\n", "peer_b/f.py": ""})
    (hit,) = upward_imports(root, _PLANT_LAYERS)
    assert "uwdock.peer_a.e imports uwdock.peer_b.f" in hit


def test_import_cycle_is_found_through_a_function_level_import(tmp_path):
    root = _plant(
        tmp_path,
        {
            "top/a.py": "from uwdock.top.b import x\n",
            "top/b.py": "from . import c\n",
            "top/c.py": "def f():\n    from uwdock.top import a\n",
            "top/d.py": "from uwdock.top import a\n",
        },
    )
    assert import_cycles(root, _PLANT_LAYERS) == [["uwdock.top.a", "uwdock.top.b", "uwdock.top.c"]]
    _plant(root, {"low/s.py": "from uwdock.low import s\n"})  # a module importing itself
    assert ["uwdock.low.s"] in import_cycles(root, _PLANT_LAYERS)


def test_local_imports_of_the_project_or_light_modules_are_found(tmp_path):
    root = _plant(
        tmp_path,
        {
            "top/a.py": """
                import numpy

                def f():
                    from uwdock.low import b
                    import json
                    import torch

                class C:
                    def g(self):
                        import cv2
                """,
            "low/b.py": "",
        },
    )
    hits = local_import_violations(root, _PLANT_LAYERS)
    assert [h.split(": ", 1)[1] for h in hits] == [
        "uwdock.top.a imports uwdock.low.b",
        "uwdock.top.a imports json",
        "uwdock.top.a imports cv2",
    ]


def test_unguarded_bare_folder_is_found(tmp_path):
    (tmp_path / "datasets").mkdir()
    (tmp_path / "datasets" / "__init__.py").write_text("x = 1\n", encoding="utf-8")
    hit = bare_name_gives_project("datasets", tmp_path, root=tmp_path)
    assert hit is not None and "gives the project" in hit
    guarded = tmp_path / "guarded"
    (guarded / "datasets").mkdir(parents=True)
    (guarded / "datasets" / "__init__.py").write_text(
        "raise ImportError('installed as uwdock.datasets')\n", encoding="utf-8"
    )
    assert bare_name_gives_project("datasets", guarded, root=guarded) is None
    (guarded / "datasets" / "__init__.py").write_text(
        "raise ImportError('something else')\n", encoding="utf-8"
    )
    assert "refused" in (bare_name_gives_project("datasets", guarded, root=guarded) or "")
