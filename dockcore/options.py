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

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from uwdock.dockcore.cli import CONTEXT
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import check_output_dir, check_output_path

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


def ray_job_id() -> str | None:
    """The submission ID of the ``ray job submit`` job this process is the command of (Ray
    passes it to the job's command in ``RAY_JOB_CONFIG_JSON_ENV_VAR``), else None."""
    raw = os.environ.get("RAY_JOB_CONFIG_JSON_ENV_VAR")
    if not raw:
        return None
    try:
        metadata = json.loads(raw).get("metadata") or {}
        job = metadata.get("job_submission_id")
    except (ValueError, AttributeError):
        return None
    return job if isinstance(job, str) and job else None


def refuse_relative_in_ray_job(path: Path, what: str = "--out") -> Path:
    """Under ``ray job submit`` a relative output path is refused in one line: the job's
    command runs in Ray's temporary copy of ``--working-dir`` (or in Ray's own folder), not in
    the submitter's folder, and what it wrote there is deleted when the cluster stops."""
    job = ray_job_id()
    if job is not None and not path.is_absolute():
        raise DockError(
            f"{what} {path} is relative, and under `ray job submit` (job {job}) this command "
            f"runs in Ray's temporary working dir {Path.cwd()}, deleted when the cluster "
            f"stops: give {what} as an absolute path on the node that runs the job"
        )
    return path


def _checked_dir(ctx: click.Context, param: click.Parameter, value: Path | None) -> Path | None:
    """``--out DIRECTORY`` checked as it is parsed, before the command does any work: a file,
    device, FIFO, socket or symlink loop there is refused (:func:`dockcore.io.check_output_dir`),
    and a relative path under ``ray job submit`` (:func:`refuse_relative_in_ray_job`)."""
    if value is None:
        return None
    return check_output_dir(refuse_relative_in_ray_job(value), "--out")


def _checked_file(ctx: click.Context, param: click.Parameter, value: Path | None) -> Path | None:
    """``--out FILE`` checked as it is parsed, before the command does any work: a folder,
    device, FIFO, socket or symlink loop there is refused (:func:`dockcore.io.output_target`;
    the files written beside it are checked by the command), and a relative path under
    ``ray job submit`` (:func:`refuse_relative_in_ray_job`)."""
    if value is None:
        return None
    return check_output_path(refuse_relative_in_ray_job(value), "--out")


def out_dir_option(help_text: str | None = "Output folder.", **kwargs: Any) -> Decorator:
    """``--out DIRECTORY`` (-> ``out_dir``, a Path); ``kwargs`` add ``required``, ``default``,
    ``show_default``. What is there must be a folder or nothing (checked when parsed)."""
    return click.option(
        "--out",
        "out_dir",
        type=click.Path(file_okay=False, path_type=Path),
        help=help_text,
        callback=_checked_dir,
        **kwargs,
    )


def out_file_option(help_text: str, **kwargs: Any) -> Decorator:
    """``--out FILE`` (-> ``out_path``, a Path); ``kwargs`` as for :func:`out_dir_option`. What
    is there must be a regular file (or a symbolic link to one) or nothing (checked when
    parsed)."""
    return click.option(
        "--out",
        "out_path",
        type=click.Path(dir_okay=False, path_type=Path),
        help=help_text,
        callback=_checked_file,
        **kwargs,
    )


def out_path_checked(ctx: click.Context, param: click.Parameter, value: Any) -> Any:
    """A click callback for another output file option (``--right-out``, ``--stereo-out``):
    checked as :func:`out_file_option`'s ``--out``, under the option's own name."""
    if value is None:
        return None
    what = param.opts[0] if param.opts else "output file"
    return check_output_path(refuse_relative_in_ray_job(Path(value), what), what)


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
