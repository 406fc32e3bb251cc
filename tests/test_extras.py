"""The base install: markers, perception and calibration work without the optional stacks.

``pip install uwdock`` (no extra) must give the footage tools. Two checks prove it here without
a second environment:

* the commands run (``perception eval`` on a small labelled folder, ``markers generate``,
  ``calibration intrinsics``) through their console entry points in a subprocess whose import
  system refuses the optional modules (a ``sys.meta_path`` finder raising
  ModuleNotFoundError, exactly what a missing package raises), and their results are checked
  against ground truth;
* every third-party module those packages (and ``dockcore`` below them) import is provided by
  a distribution in the base ``dependencies`` of ``pyproject.toml``; the only exception is the
  optional mesh check's open3d, imported inside a function and declared in the ``check`` extra.
"""

from __future__ import annotations

import ast
import importlib.metadata as md
import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from tests.test_calibration import CB_COLS, CB_ROWS, DIST_TRUE, H_PX, K_TRUE, W_PX, chessboard_views
from tests.test_perception_cli import CAM, CORNERS_DS, FLOOR_IDS, MARKER_SET, look_at, render_board
from uwdock.calibration.camera import load_camera, save_camera
from uwdock.markers.markerset import load_marker_set, save_marker_set
from uwdock.perception.groundtruth import label_frame, write_dataset_json, write_labels

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parent.parent

#: Modules of the optional stacks (sim, rl, check extras and what they pull in).
OPTIONAL_MODULES = (
    "sapien",
    "torch",
    "stable_baselines3",
    "gymnasium",
    "numba",
    "open3d",
    "onnxruntime",
    "tensorboard",
    "ray",
)

#: The packages of the base install (their folders in the repository).
BASE_PACKAGES = ("dockcore", "markers", "perception", "calibration")

#: Third-party modules a base package may import only inside a function, guarded, with the
#: extra that declares them.
GUARDED_OPTIONAL = {"open3d": "check", "ray": "ray", "grpc": "ray", "psutil": "ray"}

# Runs one console script with the optional modules refused; writes what was tried and loaded.
_RUNNER = r"""
import importlib.abc, importlib.metadata, json, os, sys

BLOCKED = set(os.environ["UWDOCK_BLOCKED"].split(","))
tried = []

class Refuse(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in BLOCKED:
            tried.append(name)
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None

sys.meta_path.insert(0, Refuse())
script = sys.argv[1]
(entry,) = importlib.metadata.entry_points(group="console_scripts", name=script)
sys.argv = [script, *sys.argv[2:]]
code = 0
try:
    entry.load()()
except SystemExit as exc:
    code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
finally:
    loaded = sorted(m for m in sys.modules if m.partition(".")[0] in BLOCKED)
    uwdock = sorted({".".join(m.split(".")[:2]) for m in sys.modules if m.startswith("uwdock.")})
    with open(os.environ["UWDOCK_RUN_REPORT"], "w") as fh:
        json.dump({"code": code, "tried": sorted(set(tried)), "loaded": loaded,
                   "uwdock": uwdock}, fh)
"""


def run_without_optional(
    tmp_path: Path, script: str, *args, blocked: tuple[str, ...] = OPTIONAL_MODULES
) -> tuple[dict, str, str]:
    """Run console script ``script`` with ``args`` where the optional modules (``blocked``)
    cannot be imported; returns (report, stdout, stderr)."""
    report = tmp_path / f"run_{script}.json"
    env = {**os.environ, "UWDOCK_BLOCKED": ",".join(blocked)}
    env["UWDOCK_RUN_REPORT"] = str(report)
    res = subprocess.run(
        [sys.executable, "-c", _RUNNER, script, *map(str, args)],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=300,
    )
    assert report.is_file(), res.stderr[-2000:]
    return json.loads(report.read_text()), res.stdout, res.stderr


def _assert_base_only(report: dict) -> None:
    assert report["loaded"] == []  # nothing optional got in through another route
    assert not {"uwdock.sim", "uwdock.rl", "uwdock.datasets"} & set(report["uwdock"])


# --------------------------------------------------------------------------- the commands


def test_the_refusing_finder_refuses(tmp_path):
    """The harness itself: an optional module imported by the command fails as missing."""
    report, _, err = run_without_optional(tmp_path, "uwdock", "rl", "eval", "--help")
    assert report["code"] == 2 and report["tried"] == ["gymnasium"]
    assert err == (
        "error: 'rl' needs the Python package 'gymnasium', not installed here "
        "(pip install 'uwdock[rl]')\n"
    )
    assert report["loaded"] == []


@pytest.fixture(scope="module")
def labelled(tmp_path_factory) -> Path:
    """Six frames of the DS floor markers with their labels, camera and marker set files."""
    root = tmp_path_factory.mktemp("labelled")
    (root / "images").mkdir()
    poses = [
        look_at(r, 8.0, az, 90.0)
        for r, az in zip((1.4, 1.6, 1.8, 2.0, 1.5, 1.7), range(0, 360, 60), strict=True)
    ]
    rng = np.random.default_rng(3)
    for k, T in enumerate(poses):
        cv2.imwrite(str(root / "images" / f"{k:06d}.png"), render_board(T, rng))
    save_camera(root / "camera.yaml", CAM)
    save_marker_set(root / "markerset.toml", MARKER_SET)
    labels = [
        label_frame(k, T, CAM, CORNERS_DS, image=f"images/{k:06d}.png", water={"preset": "clear"})
        for k, T in enumerate(poses)
    ]
    assert all(sorted(ft.visible_ids) == FLOOR_IDS for ft in labels)
    write_labels(root / "labels.jsonl", labels)
    write_dataset_json(root, len(poses), config={"seed": 3})
    return root


def test_perception_eval_runs_without_the_optional_stacks(tmp_path, labelled):
    out = tmp_path / "eval"
    report, stdout, err = run_without_optional(
        tmp_path, "perception", "eval", labelled, "--out", out
    )
    assert report["code"] == 0, err
    _assert_base_only(report)
    result = json.loads((out / "report.json").read_text())
    assert result["frames"] == 6 and result["pose_rate"] == 1.0
    assert result["per_id_counts"] == {"14": 6, "15": 6, "28": 6}
    assert result["translation_error_m_median"] < 0.02
    assert result["rotation_error_deg_median"] < 1.0
    assert "translation median" in stdout


def test_markers_generate_runs_without_the_optional_stacks(tmp_path):
    out = tmp_path / "markers"
    report, stdout, err = run_without_optional(
        tmp_path, "markers", "generate", "--ids", "13", "--out", out
    )
    assert report["code"] == 0, err
    _assert_base_only(report)
    assert report["tried"] == ["open3d"]  # looked for the mesh check, found it missing
    assert "mesh check skipped: open3d is not installed (pip install 'uwdock[check]')" in stdout
    assert load_marker_set(out / "markerset.toml").ids == (13,)
    insert = trimesh.load_mesh(out / "3dbm_DICT_4X4_50_13_insert.stl")
    assert insert.is_watertight
    np.testing.assert_allclose(insert.extents, [100.0, 100.0, 5.0], atol=1e-6)


def test_calibration_intrinsics_runs_without_the_optional_stacks(tmp_path):
    uv = np.stack(np.meshgrid(np.arange(W_PX), np.arange(H_PX)), -1).astype(np.float64)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    rays = cv2.undistortPoints(uv.reshape(-1, 1, 2), K_TRUE, DIST_TRUE, criteria=crit)
    folder = tmp_path / "views"
    folder.mkdir()
    for i, img in enumerate(chessboard_views(rays.reshape(H_PX, W_PX, 2), 12, seed=4)):
        cv2.imwrite(str(folder / f"view_{i:03d}.png"), img)
    out = tmp_path / "cam" / "tank.yaml"
    args = ("--pattern", "chessboard", "--cols", CB_COLS, "--rows", CB_ROWS, "--square-mm", 25)
    report, _, err = run_without_optional(
        tmp_path, "calibration", "intrinsics", folder, *args, "--out", out
    )
    assert report["code"] == 0, err
    _assert_base_only(report)
    cam, _ = load_camera(out)
    np.testing.assert_allclose([cam.fx_px, cam.fy_px], [800.0, 800.0], rtol=0.01)
    np.testing.assert_allclose([cam.cx_px, cam.cy_px], [319.5, 239.5], rtol=0.01)


# --------------------------------------------------------------------------- declared deps


def _normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _requirement_name(req: str) -> str:
    return _normalise(re.split(r"[\s<>=!~;\[(]", req.strip(), maxsplit=1)[0])


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))


def _third_party_imports(packages) -> dict[str, dict[str, bool]]:
    """top-level module -> {file: imported at module level (not inside a function)}."""
    found: dict[str, dict[str, bool]] = {}
    for package in packages:
        for path in sorted((ROOT / package).rglob("*.py")):
            tree = ast.parse(path.read_text(encoding="utf-8"))
            local = set()
            for fn in ast.walk(tree):
                if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    local.update(id(n) for n in ast.walk(fn))
            for node in ast.walk(tree):
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                for name in names:
                    top = name.partition(".")[0]
                    if top in sys.stdlib_module_names or top == "uwdock":
                        continue
                    where = str(path.relative_to(ROOT))
                    found.setdefault(top, {})[where] = (
                        found.get(top, {}).get(where, False) or id(node) not in local
                    )
    return found


def _distributions(module: str, top_level: dict[str, list[str]]) -> set[str]:
    """The installed distributions that provide top-level ``module`` (empty: not installed);
    ``top_level`` is :func:`importlib.metadata.packages_distributions`."""
    names = set(top_level.get(module, []))
    if not names:  # a bare extension module (manifold3d.*.so) is missing from that map
        spec = importlib.util.find_spec(module)
        if spec is not None and spec.origin:
            origin = Path(spec.origin).resolve()
            for dist in md.distributions():
                for f in dist.files or ():
                    if f.name == origin.name and Path(dist.locate_file(f)).resolve() == origin:
                        names.add(dist.metadata["Name"])
    return {_normalise(n) for n in names}


def test_base_packages_import_only_base_dependencies():
    project = _pyproject()["project"]
    base = {_requirement_name(r) for r in project["dependencies"]}
    extras = {
        k: {_requirement_name(r) for r in v} for k, v in project["optional-dependencies"].items()
    }
    imports = _third_party_imports(BASE_PACKAGES)
    assert {"numpy", "cv2", "click", "av", "trimesh"} <= set(imports)  # the walk finds them
    top_level = md.packages_distributions()
    problems = []
    for module, files in sorted(imports.items()):
        dists = _distributions(module, top_level)
        if not dists:  # not installed here: only a requirement for another Python (tomli)
            if _normalise(module) not in base:
                problems.append(f"{module}: not installed and not a base dependency ({files})")
            continue
        if dists & base:
            continue
        extra = GUARDED_OPTIONAL.get(module)
        if extra and dists & extras[extra] and not any(files.values()):
            continue  # imported only inside functions, declared in its extra
        problems.append(f"{module} (from {sorted(dists)}) is not a base dependency: {files}")
    assert problems == []


def test_optional_stacks_are_not_base_dependencies():
    project = _pyproject()["project"]
    base = {_requirement_name(r) for r in project["dependencies"]}
    optional = {_normalise(m) for m in OPTIONAL_MODULES} | {"stable-baselines3"}
    assert base & optional == set()
    extras = project["optional-dependencies"]
    assert "open3d" in {_requirement_name(r) for r in extras["check"]}
    assert {"sapien", "numba"} <= {_requirement_name(r) for r in extras["sim"]}


#: What ``uwdock[vehicle]`` leaves out (the simulator and the learning stack), and Cyclone DDS,
#: which it has only where PyPI has a wheel (x86-64): a replay needs no DDS.
NOT_IN_VEHICLE = (*(m for m in OPTIONAL_MODULES if m != "onnxruntime"), "cyclonedds")


def test_rl_replay_runs_with_the_vehicle_extra_only(tmp_path):
    """``rl replay`` (and so ``rl node``'s chain) needs neither SAPIEN, torch, SB3, Gymnasium,
    numba nor Cyclone DDS: the vehicle install (``tests/test_vehicle_install.py`` installs it
    for real); ``rl node`` without DDS is one line naming what to install."""
    from tests.test_replay import _ros2

    _ros2(tmp_path / "m.mcap")
    out = tmp_path / "replay"
    report, stdout, err = run_without_optional(
        tmp_path, "rl", "replay", tmp_path / "m.mcap", "--out", out, blocked=NOT_IN_VEHICLE
    )
    assert report["code"] == 0, err
    assert report["loaded"] == []
    assert set(report["tried"]) <= {"gymnasium"}  # the env's registration, skipped
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"]["used"] == 12
    assert "rl replay:" in stdout
    report, _, err = run_without_optional(tmp_path, "rl", "node", blocked=NOT_IN_VEHICLE)
    assert report["code"] == 2 and report["loaded"] == []
    assert err.count("\n") == 1 and "needs Cyclone DDS's Python binding" in err
