"""The umbrella command ``uwdock`` and the CLI options every group shares
(:mod:`dockcore.options`), through the CLI runner."""

from __future__ import annotations

import click
import pytest

from uwdock import cli as uwdock_cli
from uwdock.calibration import cli as calibration_cli
from uwdock.datasets import cli as datasets_cli
from uwdock.dockcore.options import command_group, config_option, out_dir_option, quiet_option
from uwdock.markers import cli as markers_cli
from uwdock.perception import cli as perception_cli
from uwdock.rl import cli as rl_cli
from uwdock.sim import cli as sim_cli

GROUPS = ("markers", "perception", "calibration", "datasets", "sim", "rl")


def test_uwdock_help_lists_the_six_groups(run_cli):
    res = run_cli(uwdock_cli.main, "--help")
    assert res.code == 0, res.err
    rows = res.out.split("Commands:")[1].splitlines()
    names = [row.split()[0] for row in rows if row.startswith("  ") and row[2] != " "]
    assert names == list(GROUPS)  # continuation lines of a wrapped summary are indented deeper
    for name, (summary, _) in uwdock_cli.COMMANDS.items():
        assert summary.split()[0] in res.out, name


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (("perception", "--help"), ["detect", "eval", "pipelines"]),
        (("perception", "eval", "-h"), ["--ground-truth", "--config", "--quiet", "--json"]),
        (("rl", "eval", "--help"), ["--policy", "--obs", "--seed", "--workers", "--out"]),
        (("rl", "--help"), ["train", "eval", "export", "fit-error-model", "episode"]),
        (("datasets", "-h"), ["synth", "render"]),
        (("sim", "--help"), ["water", "fit-water"]),
    ],
)
def test_uwdock_reaches_every_group(run_cli, args, expected):
    """``uwdock GROUP ...`` is ``GROUP ...``: the same help, word for word."""
    res = run_cli(uwdock_cli.main, *args)
    assert res.code == 0, res.err
    for word in expected:
        assert word in res.out, word
    direct = {"perception": perception_cli, "rl": rl_cli, "datasets": datasets_cli, "sim": sim_cli}
    # a group that shows another's command (``sim fit-water``): its console script is the one
    # the umbrella matches; tests/test_startup.py checks it against the module's own group
    lent = args[0] in uwdock_cli.LENT and args[1] in ("-h", "--help")
    main = getattr(uwdock_cli, args[0]) if lent else direct[args[0]].main
    alone = run_cli(main, *args[1:])
    assert alone.code == 0
    assert (
        alone.out.split("Usage:")[1].split(None, 1)[1]
        == res.out.split("Usage:")[1].split(None, 2)[2]
    )


def test_uwdock_unknown_group_is_a_one_line_usage_error(run_cli):
    res = run_cli(uwdock_cli.main, "simulate")
    assert res.code == 2
    assert res.err.count("\n") == 1 and "simulate" in res.err


@pytest.mark.parametrize(
    "module", [markers_cli, perception_cli, calibration_cli, datasets_cli, sim_cli, rl_cli]
)
def test_every_command_takes_dash_h(run_cli, module):
    """Every command and sub-group of every group answers ``-h`` (the shared context settings)."""

    def walk(group: click.Group, path: tuple[str, ...]):
        for name, cmd in group.commands.items():
            yield (*path, name)
            if isinstance(cmd, click.Group):
                yield from walk(cmd, (*path, name))

    paths = list(walk(module.cli, ()))
    assert paths
    for path in paths:
        res = run_cli(module.main, *path, "-h")
        assert res.code == 0, (path, res.err)
        assert res.out.startswith("Usage:"), path


def test_shared_options_keep_their_names_and_destinations(run_cli, tmp_path):
    seen = {}

    @command_group()
    def grp() -> None:
        """A group."""

    @grp.command()
    @config_option("A config.")
    @out_dir_option(required=True)
    @quiet_option("Quiet.")
    def cmd(config_path, out_dir, quiet) -> None:
        seen.update(config_path=config_path, out_dir=out_dir, quiet=quiet)

    from uwdock.dockcore.cli import run_group

    def main() -> None:
        run_group(grp)

    res = run_cli(main, "cmd", "--config", tmp_path / "c.toml", "--out", tmp_path, "--quiet")
    assert res.code == 0, res.err
    assert seen == {"config_path": tmp_path / "c.toml", "out_dir": tmp_path, "quiet": True}
    res = run_cli(main, "cmd", "-h")
    assert "--config FILE" in res.out and "--out DIRECTORY" in res.out and "Quiet." in res.out
    assert run_cli(main, "cmd").code == 2  # --out is required
