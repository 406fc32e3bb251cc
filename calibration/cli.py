"""``calibration``: command group. Commands appear here as they are implemented."""

from __future__ import annotations

import click

from dockcore.cli import run_group


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def cli() -> None:
    """Calibration: camera intrinsics and the camera-to-vehicle extrinsics."""


def main() -> None:
    run_group(cli)
