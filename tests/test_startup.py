"""What starting a command costs, as the modules it imports (no timing: ``bench/bench_startup.py``
measures the seconds).

* ``<group> --help`` (each console script) lists its commands from ``uwdock.cli.COMMANDS``
  without importing the group's module: no numpy, no OpenCV, no simulator; the listing is the
  group's own help, word for word, and every command's summary is the command's own;
* importing a module of the tree does not import trimesh, matplotlib or scipy (about 2 s on 2
  busy cores together): only the functions that use them do.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import inspect
import json
import subprocess
import sys

import click
import pytest

import uwdock
from uwdock import cli as uwdock_cli
from uwdock.dockcore.cli import run_group

GROUPS = ("markers", "perception", "calibration", "datasets", "sim", "rl")

#: Modules of the heavy kind (``tests/test_architecture.py``: ``HEAVY_OPTIONAL``) that importing
#: a module must not pull in (scipy's own ``__init__`` is cheap, and numba imports it).
HEAVY = (
    "trimesh",
    "matplotlib",
    "scipy.spatial",
    "scipy.optimize",
    "networkx",
    "torch",
    "stable_baselines3",
    "open3d",
)

_LOADED = r"""
import json, sys
sys.argv = [sys.argv[1], *sys.argv[2:]]
code = {code!r}
try:
    exec(code)
except SystemExit:
    pass
print(json.dumps(sorted(sys.modules)))
"""


def loaded_modules(code: str, *argv: str) -> set[str]:
    """``sys.modules`` after running ``code`` (with ``sys.argv`` = ``argv``) in a fresh Python;
    whatever ``code`` prints goes before the JSON line that is read."""
    res = subprocess.run(
        [sys.executable, "-c", _LOADED.format(code=code), *argv],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr[-2000:]
    return set(json.loads(res.stdout.strip().splitlines()[-1]))


@pytest.mark.parametrize("group", GROUPS)
def test_group_help_imports_neither_the_group_nor_numpy(group):
    mods = loaded_modules(f"from uwdock.cli import {group}; {group}()", group, "--help")
    assert "uwdock.cli" in mods  # the entry point did run
    assert not {m for m in mods if m.startswith(f"uwdock.{group}")}
    assert not {m.partition(".")[0] for m in mods} & {"numpy", "cv2", "sapien", "scipy"}
    assert not mods & set(HEAVY)
    assert "importlib.metadata" not in mods  # the version is a literal in uwdock/__init__.py


def test_version_is_the_installed_distributions():
    assert uwdock.__version__ == importlib.metadata.version("uwdock")


def test_umbrella_help_of_a_group_imports_nothing_of_it():
    mods = loaded_modules("from uwdock.cli import main; main()", "uwdock", "rl", "--help")
    assert "uwdock.cli" in mods
    assert not {m for m in mods if m.startswith("uwdock.rl")}
    assert not {m.partition(".")[0] for m in mods} & {"numpy", "gymnasium", "sapien"}


@pytest.mark.parametrize("group", GROUPS)
def test_lazy_listing_is_the_groups_own(run_cli, group):
    """The table in ``uwdock.cli`` is the group: same command names, each command's summary
    (first sentence, untruncated) its own, and ``--help`` the same text word for word through
    the console script, ``uwdock <group>`` and the group's module."""
    real = importlib.import_module(f"uwdock.{group}.cli")
    help_text, summaries = uwdock_cli.COMMANDS[group]
    lent = uwdock_cli.LENT.get(group, {})
    assert sorted(set(summaries) - set(lent)) == sorted(real.cli.commands)
    assert help_text == inspect.cleandoc(real.cli.help or "")
    for name, text in summaries.items():
        owner = importlib.import_module(f"uwdock.{lent[name]}.cli") if name in lent else real
        ours = click.Command(name, help=text).get_short_help_str(10_000)
        assert ours == owner.cli.commands[name].get_short_help_str(10_000), (group, name)
    alone = run_cli(real.main, "--help")
    lazy = run_cli(getattr(uwdock_cli, group), "--help")
    umbrella = run_cli(uwdock_cli.main, group, "--help")
    assert alone.code == lazy.code == umbrella.code == 0

    if lent:  # the lazy group lists the lent commands too (the column widths follow)
        head = lazy.out.split("Commands:")[0]
        assert head == alone.out.split("Commands:")[0]
        listed = [r.split()[0] for r in lazy.out.split("Commands:")[1].splitlines() if r.strip()]
        assert listed == sorted(summaries)
    else:
        assert lazy.out == alone.out
    assert umbrella.out.split("Usage:")[1].split(None, 2)[2] == lazy.out.split(None, 2)[2]


def test_a_lent_command_is_the_lending_groups_own(run_cli):
    """``sim fit-water`` (the umbrella joins sim and datasets) runs ``datasets fit-water``; ``rl
    node`` and ``sim vehicle`` run the vehicle module's commands."""
    for group, lent in uwdock_cli.LENT.items():
        for name, owner in lent.items():
            via = run_cli(getattr(uwdock_cli, group), name, "--help")
            own = run_cli(lambda o=owner: run_group(uwdock_cli.load_group(o)), name, "--help")
            assert via.code == own.code == 0
            assert via.out.split(None, 3)[3] == own.out.split(None, 3)[3]  # past "Usage: x y"


def test_lazy_group_runs_the_command_and_refuses_an_unknown_one(run_cli):
    res = run_cli(uwdock_cli.perception, "pipelines")
    alone = run_cli(importlib.import_module("uwdock.perception.cli").main, "pipelines")
    assert res.code == 0 and res.out == alone.out and res.out.strip()
    res = run_cli(uwdock_cli.sim, "waterr")
    assert res.code == 2 and res.err.count("\n") == 1 and "waterr" in res.err


@pytest.mark.parametrize(
    "module",
    [
        "uwdock.markers.cli",
        "uwdock.markers.generate",
        "uwdock.calibration.cli",
        "uwdock.perception.cli",
        "uwdock.sim.cli",
        "uwdock.datasets.cli",
        "uwdock.rl.env.docking_env",
    ],
)
def test_importing_a_module_does_not_import_the_heavy_libraries(module):
    mods = loaded_modules(f"import {module}", "python")
    assert module in mods
    assert not mods & set(HEAVY), module
