"""The click options every command group shares, written once.

Each is a decorator factory with the option's name, destination and type fixed and its help text
given by the command (a config file of *which* dataclass, an output *file* or *folder*)::

    @command_group()
    def cli() -> None: ...

    @cli.command()
    @config_option("TOML overriding MarkerConfig defaults (flags override the file).")
    @out_dir_option(default=Path("markers_out"), show_default=True)
    @quiet_option("Print only the marker set path.")
    def generate(config_path, out_dir, quiet): ...

Destinations: ``--config`` -> ``config_path``, ``--out`` -> ``out_dir`` (a folder) or
``out_path`` (a file), ``--json`` -> ``as_json``, ``--quiet`` -> ``quiet``, ``--seed`` ->
``seed``, ``--workers`` -> ``workers``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from uwdock.dockcore.cli import CONTEXT

Decorator = Callable[[Callable[..., Any]], Callable[..., Any]]


class DockGroup(click.Group):
    """A command group whose commands and sub-groups take the toolkit's context settings
    (``-h`` as well as ``--help``) without repeating them."""

    group_class = type  # sub-groups are DockGroups too

    def command(self, *args: Any, **kwargs: Any) -> Any:
        if args and callable(args[0]):  # bare ``@cli.command``
            return self.command(*args[1:], **kwargs)(args[0])
        kwargs.setdefault("context_settings", CONTEXT)
        return super().command(*args, **kwargs)

    def group(self, *args: Any, **kwargs: Any) -> Any:
        if args and callable(args[0]):
            return self.group(*args[1:], **kwargs)(args[0])
        kwargs.setdefault("context_settings", CONTEXT)
        return super().group(*args, **kwargs)


def command_group(**kwargs: Any) -> Decorator:
    """``click.group`` as a :class:`DockGroup` with the toolkit's context settings."""
    kwargs.setdefault("context_settings", CONTEXT)
    return click.group(cls=DockGroup, **kwargs)


def config_option(help_text: str) -> Decorator:
    """``--config FILE`` (-> ``config_path``, a Path or None): the TOML file of a config."""
    return click.option(
        "--config",
        "config_path",
        type=click.Path(dir_okay=False, path_type=Path),
        help=help_text,
    )


def out_dir_option(help_text: str | None = "Output folder.", **kwargs: Any) -> Decorator:
    """``--out DIRECTORY`` (-> ``out_dir``, a Path); ``kwargs`` add ``required``, ``default``,
    ``show_default``."""
    return click.option(
        "--out",
        "out_dir",
        type=click.Path(file_okay=False, path_type=Path),
        help=help_text,
        **kwargs,
    )


def out_file_option(help_text: str, **kwargs: Any) -> Decorator:
    """``--out FILE`` (-> ``out_path``, a Path); ``kwargs`` as for :func:`out_dir_option`."""
    return click.option(
        "--out",
        "out_path",
        type=click.Path(dir_okay=False, path_type=Path),
        help=help_text,
        **kwargs,
    )


def quiet_option(help_text: str) -> Decorator:
    """``--quiet`` (-> ``quiet``, a flag): no progress bar, print only the output's path."""
    return click.option("--quiet", is_flag=True, help=help_text)


def json_option(help_text: str) -> Decorator:
    """``--json`` (-> ``as_json``, a flag): machine-readable output on stdout."""
    return click.option("--json", "as_json", is_flag=True, help=help_text)


def seed_option(type_: click.ParamType, help_text: str | None = None, **kwargs: Any) -> Decorator:
    """``--seed INTEGER`` (-> ``seed``) of domain ``type_`` (``domain_type(Seed)`` or the
    seed field it overrides)."""
    return click.option("--seed", type=type_, help=help_text, **kwargs)


def workers_option(
    type_: click.ParamType, help_text: str | None = None, **kwargs: Any
) -> Decorator:
    """``--workers INTEGER`` (-> ``workers``, default 1) of domain ``type_``."""
    kwargs.setdefault("default", 1)
    kwargs.setdefault("show_default", True)
    return click.option("--workers", type=type_, help=help_text, **kwargs)


def backend_options(what: str) -> Decorator:
    """``--backend local|ray`` (-> ``backend``) and ``--ray-address`` (-> ``ray_address``): where
    the workers of ``--workers`` run (:mod:`dockcore.pool`)."""

    def decorate(f: Callable[..., Any]) -> Callable[..., Any]:
        f = click.option(
            "--ray-address",
            "ray_address",
            help="With --backend ray: a running Ray cluster's address ('auto': the one this "
            "machine belongs to) [default: a local Ray instance for the job].",
        )(f)
        return click.option(
            "--backend",
            type=click.Choice(["local", "ray"]),
            default="local",
            show_default=True,
            help=f"Where the workers run: local processes or Ray actors ({what}).",
        )(f)

    return decorate
