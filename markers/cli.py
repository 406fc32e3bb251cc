"""``markers``: generate printable 3D Binary Markers and the marker set file."""

from __future__ import annotations

from pathlib import Path

import click

from uwdock.dockcore.cli import DomainType, field_type, run_group
from uwdock.dockcore.config import load_config
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.media import silence_opencv_log
from uwdock.dockcore.options import command_group, config_option, out_dir_option, quiet_option
from uwdock.markers.config import MarkerConfig
from uwdock.markers.dictionary import DICTIONARY_NAMES, bits_per_side, dictionary_size
from uwdock.markers.generate import generate as run


def _parse_ids(text: str | None) -> tuple[int, ...] | None:
    """``"13, 14,15"`` -> ``(13, 14, 15)``; the IDs' range is checked with the config."""
    if text is None:
        return None
    try:
        return tuple(int(t, 10) for t in text.replace(" ", "").split(",") if t)
    except ValueError:
        raise DockError(f"--ids must be comma-separated integers, got '{text}'") from None


def _mm(name: str) -> DomainType:
    """The click type of the option that overrides ``MarkerConfig.<name>`` (its domain)."""
    return field_type(MarkerConfig, name)


@command_group()
def cli() -> None:
    """3D Binary Markers: printable parts, flat sheets, the marker set file."""
    silence_opencv_log()  # the toolkit's own lines only (library noise: dockcore.media)


@cli.command()
@click.option("--ids", help="Comma-separated marker IDs [default: the DS set 13,14,15,28,34].")
@click.option("--dictionary", help="OpenCV dictionary, e.g. DICT_4X4_50, DICT_APRILTAG_36h11.")
@click.option("--size-mm", type=_mm("size_mm"), help="Insert (tag) side in mm [default: 100].")
@click.option(
    "--relief-depth-mm",
    type=_mm("relief_depth_mm"),
    help="Depth of the openings seen from above [5].",
)
@click.option(
    "--insert-thickness-mm", type=_mm("insert_thickness_mm"), help="White insert thickness [5]."
)
@click.option(
    "--clearance-mm", type=_mm("clearance_mm"), help="Fit clearance insert/enclosure [0.1]."
)
@click.option(
    "--enclosure-mm",
    "enclosure_side_mm",
    type=_mm("enclosure_side_mm"),
    help="Black column side [1.26 x size].",
)
@click.option(
    "--enclosure-height-mm", type=_mm("enclosure_height_mm"), help="Black column height [98]."
)
@click.option(
    "--base-mm", "base_side_mm", type=_mm("base_side_mm"), help="Base plate side [1.62 x size]."
)
@click.option("--base-height-mm", type=_mm("base_height_mm"), help="Base plate thickness [10].")
@click.option("--paper", type=click.Choice(["A4", "A3", "letter"]), help="Sheet paper size [A4].")
@click.option(
    "--style",
    type=click.Choice(["solid", "published"]),
    help="solid column with a pocket, or the published construction: a thin plate on a hollow "
    "shell with a dark cavity, ~13 % of the material [solid].",
)
@config_option("TOML file overriding MarkerConfig defaults (flags override the file).")
@out_dir_option("Output folder.", default=Path("markers_out"), show_default=True)
@quiet_option("Print only the marker set path.")
def generate(
    ids,
    dictionary,
    size_mm,
    relief_depth_mm,
    insert_thickness_mm,
    clearance_mm,
    enclosure_side_mm,
    enclosure_height_mm,
    base_side_mm,
    base_height_mm,
    paper,
    style,
    config_path,
    out_dir,
    quiet,
) -> None:
    """Write STL parts (white insert, black enclosure), render meshes, previews, a true-scale
    PDF/SVG sheet and the marker set file for the given IDs."""
    cfg = load_config(
        MarkerConfig,
        config_path,
        overrides={
            "ids": _parse_ids(ids),
            "dictionary": dictionary,
            "size_mm": size_mm,
            "relief_depth_mm": relief_depth_mm,
            "insert_thickness_mm": insert_thickness_mm,
            "clearance_mm": clearance_mm,
            "enclosure_side_mm": enclosure_side_mm,
            "enclosure_height_mm": enclosure_height_mm,
            "base_side_mm": base_side_mm,
            "base_height_mm": base_height_mm,
            "paper": paper,
            "style": style,
        },
        section="marker",
    )
    result = run(cfg, out_dir, progress=None if quiet else click.echo)
    click.echo(
        str(result.marker_set) if quiet else f"wrote {len(result.files)} files to {result.out_dir}"
    )


@cli.command()
def dictionaries() -> None:
    """List the marker dictionaries OpenCV offers, with bits and marker count."""
    for name in DICTIONARY_NAMES:
        click.echo(
            f"{name:28s} {bits_per_side(name)}x{bits_per_side(name)} bits "
            f"{dictionary_size(name):5d} markers"
        )


def main() -> None:
    run_group(cli)
