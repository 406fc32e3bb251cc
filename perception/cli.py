"""``perception``: command group. Commands appear here as they are implemented."""

from __future__ import annotations

import click

from dockcore.cli import run_group


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def cli() -> None:
    """Perception: 3DBM detection and docking-station pose from the marker board."""


def main() -> None:
    run_group(cli)
