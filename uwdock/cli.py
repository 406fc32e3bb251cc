"""``uwdock``: one command over every command group (``uwdock perception eval`` is
``perception eval``). A group is imported only when it is called, so the footage commands run
without the simulator or the learning stack installed."""

from __future__ import annotations

import importlib

import click

from uwdock.dockcore.cli import CONTEXT, run_group

#: command group -> (the extra that installs what it needs, its one-line summary)
GROUPS = {
    "markers": (None, "3D Binary Markers: printable STL, PDF/SVG sheets, the marker set file."),
    "perception": (None, "3DBM detection, DS pose from the marker board, footage evaluation."),
    "calibration": (None, "Camera intrinsics from images, camera-to-vehicle extrinsics."),
    "datasets": (
        "sim",
        "Labelled synthetic datasets rendered with SAPIEN; frames for given poses.",
    ),
    "sim": ("sim", "The simulator's own commands: the water presets."),
    "rl": (
        "rl",
        "Docking env, PPO training, evaluation with the camera in the loop, export, videos.",
    ),
}


class _LazyGroups(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(GROUPS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in GROUPS:
            return None
        extra, _ = GROUPS[name]
        try:
            module = importlib.import_module(f"uwdock.{name}.cli")
        except ModuleNotFoundError as exc:
            if exc.name and not exc.name.startswith("uwdock"):
                hint = f"pip install 'uwdock[{extra}]'" if extra else "reinstall uwdock"
                raise click.UsageError(
                    f"'{name}' needs the Python package {exc.name!r}, not installed here ({hint})"
                ) from None
            raise
        return module.cli

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        rows = [(name, summary) for name, (_, summary) in GROUPS.items()]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


@click.group(cls=_LazyGroups, context_settings=CONTEXT)
@click.version_option(package_name="uwdock", prog_name="uwdock")
def cli() -> None:
    """Vision-in-the-loop underwater docking.

    Each group is also its own command: `uwdock rl eval` is `rl eval`.
    """


def main() -> None:
    run_group(cli)


if __name__ == "__main__":  # pragma: no cover
    main()
