"""The CLI convention shared by every command group.

A command group's ``main()`` calls :func:`run_group`: any :class:`DockError` (bad input, bad
config) or ``OSError`` becomes one line on stderr, ``error: ...``, and exit status 2.
"""

from __future__ import annotations

import sys

import click

from dockcore.errors import DockError


def run_group(group: click.Group, args: list[str] | None = None) -> None:
    """Run a click group with the toolkit's error convention."""
    try:
        group.main(args=args, standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("error: aborted", err=True)
        sys.exit(130)
    except click.ClickException as exc:  # usage errors: click's own one-line message
        click.echo(f"error: {exc.format_message()}", err=True)
        sys.exit(exc.exit_code)
    except click.exceptions.Exit as exc:
        sys.exit(exc.exit_code)
    except DockError as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(2)
    except OSError as exc:
        name = f" {exc.filename}" if exc.filename else ""
        click.echo(f"error:{name}: {exc.strerror or exc}", err=True)
        sys.exit(2)
    sys.exit(0)
