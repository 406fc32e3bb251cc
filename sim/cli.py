"""``sim``: the simulator's own commands (no higher layer is composed here).

Commands that compose several packages live in the package above all of them: rendered frames
for given poses are ``datasets render`` (the ``datasets synth`` engine), a video of a docking
episode is ``rl episode`` (the env and a controller).
"""

from __future__ import annotations

import json

import click

from uwdock.dockcore.cli import run_group
from uwdock.dockcore.config import to_dict
from uwdock.dockcore.options import command_group, json_option
from uwdock.sim.water import PRESET_ORDER, PRESETS


@command_group()
def cli() -> None:
    """Simulation: SAPIEN AUV and docking-station physics, underwater camera rendering.

    Rendered frames for given poses: `datasets render`; a docking episode video: `rl episode`.
    """


@cli.command()
@json_option("Print every preset's full WaterConfig as JSON.")
def water(as_json) -> None:
    """List the water presets, clearest first: attenuation and backscatter per channel (1/m),
    veiling light and forward-scatter blur."""
    if as_json:
        click.echo(json.dumps({name: to_dict(PRESETS[name]) for name in PRESET_ORDER}, indent=2))
        return

    def rgb(values) -> str:
        return " ".join(f"{v:.3f}" for v in values)

    for name in PRESET_ORDER:
        w = PRESETS[name]
        click.echo(
            f"{name:12s} beta_D {rgb(w.beta_D_rgb)}  beta_B {rgb(w.beta_B_rgb)}  "
            f"B_inf {rgb(w.B_inf_rgb)}  blur {w.blur_sigma_per_m:g}/m"
        )


def main() -> None:
    run_group(cli)


if __name__ == "__main__":  # pragma: no cover
    main()
