"""The CLI convention shared by every command group.

A command group's ``main()`` calls :func:`run_group`: any :class:`DockError` (bad input, bad
config) or ``OSError`` becomes one line on stderr, ``error: ...``, and exit status 2; a usage
error (an unknown option, a value outside its domain) is click's one line, also exit 2; SIGINT
and SIGTERM end the command the same way (``error: interrupted``, exit 130 / 143) after the
open atomic writes have been rolled back; anything else is a bug: one line, exit 1, and the
traceback only with ``UWDOCK_DEBUG=1``.

Numeric options take their domain from :mod:`dockcore.domains`, the same declaration the config
fields use: ``click.option("--size-mm", type=domain_type(Positive))``, or straight from the field
they override, ``type=field_type(MarkerConfig, "size_mm")``.
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import functools
import gc
import importlib
import os
import signal
import sys
import threading
import traceback
import types
import typing
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import click

from uwdock.dockcore.domains import check, describe, domain_of, split_annotated
from uwdock.dockcore.early_signals import HELD, holding
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.names import display_name

#: ``context_settings`` of every group and command (``-h`` as well as ``--help``).
CONTEXT = {"help_option_names": ["-h", "--help"]}


def _lookup(ref: str) -> Any:
    """``"package.module:Name"`` -> the object (imported on first use)."""
    module, _, name = ref.partition(":")
    return getattr(importlib.import_module(module), name)


class DomainType(click.ParamType):
    """A click type for an int or float option with a declared domain (finite, bounds).

    ``"nan"``, ``"inf"``, ``"1e999"``, ``"1.5"`` for an integer, or a value outside the bounds is
    click's one-line usage error naming the option, before the command runs.

    Args:
        tp: ``Annotated[int | float, <domain>]``, or a zero-argument callable returning it: the
            type is then resolved when first needed, so a command group can declare options of
            heavy modules (the simulator's configs) without importing them at start-up.
    """

    name = "number"

    def __init__(self, tp: Any) -> None:
        self._tp = tp

    @functools.cached_property
    def _spec(self) -> tuple[type, tuple[Any, ...]]:
        tp = self._tp() if callable(self._tp) and domain_of(self._tp) is None else self._tp
        base, meta = split_annotated(tp)
        if base not in (int, float) or domain_of(tp) is None:
            raise TypeError(f"DomainType needs Annotated[int|float, <domain>], got {tp!r}")
        return base, meta

    @property
    def base(self) -> type:
        return self._spec[0]

    @property
    def meta(self) -> tuple[Any, ...]:
        return self._spec[1]

    def get_metavar(self, param: click.Parameter, ctx: click.Context | None = None) -> str:
        return "INTEGER" if self.base is int else "FLOAT"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if isinstance(value, self.base) and not isinstance(value, bool):
            parsed = value
        else:
            text = str(value).strip()
            try:
                parsed = int(text, 10) if self.base is int else float(text)
            except ValueError:
                self.fail(f"must be {describe(self.meta, self.base is int)}, got {text!r}")
        reason = check(parsed, self.base, self.meta, "value")
        if reason:
            self.fail(reason.removeprefix("value: "), param, ctx)
        return parsed

    def __repr__(self) -> str:
        return f"DomainType({self.base.__name__}, {describe(self.meta, self.base is int)})"


def domain_type(tp: Any) -> DomainType:
    """The click type of an option whose values are ``tp`` (an annotated int or float, or
    ``"package.module:Alias"`` naming one, imported when first needed)."""
    return DomainType((lambda: _lookup(tp)) if isinstance(tp, str) else tp)


def field_type(cls: type | str, name: str) -> DomainType:
    """The click type of an option that overrides config field ``cls.name`` (same domain).

    ``cls`` may be ``"package.module:Class"``: imported when the option is first used, not when
    the command group is. A field ``float | None`` gives the type of its number (an unset
    option stays None)."""

    def resolve() -> Any:
        owner = _lookup(cls) if isinstance(cls, str) else cls
        tp = typing.get_type_hints(owner, include_extras=True)[name]
        if typing.get_origin(tp) in (typing.Union, types.UnionType):
            tp = next(a for a in typing.get_args(tp) if a is not type(None))
        return tp

    return DomainType(resolve)


class PresetType(click.Choice):
    """A click choice among named presets whose value is the preset's object, ``make(name)``
    (a config object, not a name that travels on as a string); an unknown name is click's
    one-line usage error listing the names."""

    def __init__(self, names: Iterable[str], make: Callable[[str], Any]) -> None:
        super().__init__(list(names))
        self._make = make

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if not isinstance(value, str):
            return value  # already the object (a default given as one)
        return self._make(super().convert(value, param, ctx))


class ParsedType(click.ParamType):
    """A click type whose value is ``parse(text)``: the object an argument names, built (and
    any file it names read) where the command line is parsed; a :class:`DockError` or
    ``ValueError`` from ``parse`` is click's one-line usage error naming the option."""

    def __init__(self, name: str, parse: Callable[[str], Any]) -> None:
        self.name = name
        self._parse = parse

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if not isinstance(value, str):
            return value
        try:
            return self._parse(value)
        except (DockError, ValueError) as exc:
            self.fail(str(exc), param, ctx)


class _Interrupted(KeyboardInterrupt):
    """SIGTERM, delivered as an interrupt so cleanup code runs as for Ctrl-C."""


#: the signals received while a command runs: an exception that follows one is reported as
#: the interrupt (a signal that lands while a C extension initialises surfaces as an
#: ``ImportError: initialization failed``, not as KeyboardInterrupt)
_received: list[int] = []


#: Delay (s) before a signal that landed inside importlib's machinery is delivered again.
REDELIVER_DELAY_S = 0.02


def _in_import_machinery(frame: Any) -> bool:
    """Whether the interrupted code is importlib's own (a module lock's weakref callback, for
    one): an exception raised there is printed as "Exception ignored ... Traceback" and
    dropped, so the interrupt would be lost and a traceback shown."""
    return frame is not None and frame.f_code.co_filename.startswith("<frozen importlib")


#: whether a signal after the first is only recorded (a supervised child: dockcore.supervise)
_repeats_ignored: list[bool] = []
#: whether an interrupt has been raised (and not lost where Python could not propagate it)
_raised: list[bool] = []


def ignore_repeated_signals() -> None:
    """From now on a SIGINT/SIGTERM after the first is recorded, not raised: a supervised
    child (:mod:`dockcore.supervise`) gets a terminal's Ctrl-C twice (from the terminal and
    from its parent), and its cleanup must not be interrupted by the copy; the parent kills
    it if it does not end in time."""
    _repeats_ignored[:] = [True]


def _interrupt(signum: int, frame: Any, exc: type[BaseException]) -> None:
    # recorded first, also when the raise is put off: an error that surfaces before the signal
    # is delivered again (the C extension whose import it broke) is then still reported as the
    # interrupt, not as a bug
    _received.append(signum)
    if _repeats_ignored and _raised:
        return
    if _in_import_machinery(frame):
        _redeliver(signum)
        return
    _raised[:] = [True]
    raise exc()


def interrupt_name(exc: BaseException) -> str:
    """``"SIGTERM"`` or ``"SIGINT"``: the signal behind an interrupt that is ending a command
    (what an interrupted run writes into the outputs it marks incomplete)."""
    if isinstance(exc, _Interrupted) or _received[-1:] == [signal.SIGTERM]:
        return "SIGTERM"
    return "SIGINT"


def _redeliver(signum: int) -> None:
    """Send ``signum`` to this process again in a moment, from a timer thread."""
    threading.Timer(REDELIVER_DELAY_S, os.kill, (os.getpid(), signum)).start()


def _interrupt_unraisable(unraisable: Any) -> None:
    """``sys.unraisablehook`` while a command runs: an interrupt that :func:`_interrupt` raised
    where Python cannot propagate it (an ``os.fork`` hook such as logging's ``_releaseLock``, a
    weakref callback, a ``__del__``) is delivered again a moment later instead of being printed
    as "Exception ignored ... Traceback" and lost (seen in the killed-training test: a SIGINT
    that landed while a worker forked was dropped and the run trained on to its end).
    Everything else goes to the hook that was there before."""
    exc = unraisable.exc_value
    if isinstance(exc, KeyboardInterrupt) and _received:
        _raised.clear()  # lost: the next delivery raises again
        _redeliver(_received[-1])
        return
    _previous_unraisable(unraisable)


#: the ``sys.unraisablehook`` that :func:`run_group` replaced (the interpreter's own outside)
_previous_unraisable: Any = sys.__unraisablehook__


def _on_sigterm(signum: int, frame: Any) -> None:
    _interrupt(signal.SIGTERM, frame, _Interrupted)


def _on_sigint(signum: int, frame: Any) -> None:
    _interrupt(signal.SIGINT, frame, KeyboardInterrupt)


#: the signals whose handlers :func:`run_group` installed, while its command runs
_installed: dict[int, Any] = {}
#: The exception that ended an interrupted command, kept until the process ends: its traceback
#: holds the frames, and so the native objects (a SAPIEN scene, its renderer) that the command
#: was using when the signal landed. Released at the end of the ``except`` block, they would be
#: destroyed there, mid-work, which can segfault after the one line has been written.
_interrupt_kept: list[BaseException] = []


def reclaim_signals() -> None:
    """Put :func:`run_group`'s SIGTERM/SIGINT handlers back after a library replaced them (Ray's
    ``ray.init`` installs a native failure handler that turns SIGTERM into a crash dump and an
    abort, exit 134). Nothing happens outside a running command."""
    for signum, handler in _installed.items():
        if signal.getsignal(signum) is not handler:
            signal.signal(signum, handler)


def _oserror_line(exc: OSError) -> str:
    """One line for a failed file operation: the file first, then the reason."""
    reason = exc.strerror or str(exc) or type(exc).__name__
    if exc.errno == errno.ENOSPC:
        reason = "no space left on the device"
    elif exc.errno == errno.EROFS:
        reason = "read-only file system"
    name = exc.filename
    return f"{name}: {reason}" if name else reason


#: set while :func:`run_group` runs a command as its process's program (a console script,
#: given no ``args``): what :mod:`dockcore.supervise` may fork
_program_command: list[bool] = []


def runs_program_command() -> bool:
    """Whether a command is running as this process's program (not a library caller's or a
    test's in-process call)."""
    return bool(_program_command)


def _is_process_entry() -> bool:
    """Whether this process runs the command as its program (a console script, ``python -m``):
    its ``__main__`` is the file ``argv[0]`` names. In-process callers (tests) are not."""
    main_file = getattr(sys.modules.get("__main__"), "__file__", None)
    if main_file is None:
        return sys.argv[:1] == ["-c"]  # python -c "...main()": the program is the command
    try:
        return main_file is not None and Path(main_file).resolve() == Path(sys.argv[0]).resolve()
    except (OSError, RuntimeError):
        return False


def _print_names_as_given() -> None:
    """Let the process's standard output print a path that is not UTF-8 (``--quiet`` prints
    the output path) as its bytes, as Python does in the C locale, instead of failing with a
    UnicodeEncodeError in a strict UTF-8 locale after the work is done."""
    out = sys.stdout
    if out is sys.__stdout__ and getattr(out, "errors", None) == "strict":
        with contextlib.suppress(AttributeError, ValueError, OSError):
            out.reconfigure(errors="surrogateescape")


def run_group(group: click.Group, args: list[str] | None = None) -> None:
    """Run a click group with the toolkit's error convention (module docstring)."""
    global _previous_unraisable
    previous = previous_int = None
    _received.clear()
    _raised.clear()
    _installed.clear()
    hook = sys.unraisablehook
    if hook is not _interrupt_unraisable:
        _previous_unraisable = hook
        sys.unraisablehook = _interrupt_unraisable
    try:
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
        _installed[signal.SIGTERM] = _on_sigterm
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler or holding(signal.SIGINT):
            previous_int = signal.signal(signal.SIGINT, _on_sigint)
            _installed[signal.SIGINT] = _on_sigint
    except ValueError:  # not the main thread (embedded use): leave the signals alone
        previous = None
        _installed.clear()
    argv = list(sys.argv[1:] if args is None else args)
    _print_names_as_given()
    _program_command[:] = [True] if args is None and _is_process_entry() else []
    try:
        code = _invoke(group, argv)
    finally:
        _program_command.clear()
        # A program whose command has finished only has the interpreter's shutdown left
        # (joining workers, atexit): a signal landing there would end it by an unhandled
        # KeyboardInterrupt (exit -2, no message) instead of the status the command chose, so
        # from here such a process ignores them. An in-process caller (given ``args``, or
        # with another ``__main__``) gets its handlers back.
        _installed.clear()
        if hook is not _interrupt_unraisable:
            sys.unraisablehook = hook
        late = signal.SIG_IGN if args is None and _is_process_entry() else None
        if previous is not None:
            signal.signal(signal.SIGTERM, late if late is not None else previous)
        if previous_int is not None:
            signal.signal(signal.SIGINT, late if late is not None else previous_int)
    if _received and code in (130, 128 + signal.SIGTERM) and args is None and _is_process_entry():
        _end_interrupted(code)
    _interrupt_kept.clear()  # an in-process caller goes on: its frames may go
    sys.exit(code)


def _end_interrupted(code: int) -> None:
    """End an interrupted program now, with ``code``: its command's own cleanup has run (the
    workers closed, files written atomically or not at all), then the exit handlers run here
    (multiprocessing's, temporary folders'); what is skipped is the interpreter's teardown of
    every module, where native libraries interrupted mid-work (SAPIEN's renderer, Vulkan) can
    still crash and turn the one-line exit 143 into a segfault (seen once in ~14 SIGTERMs of
    ``rl episode`` three seconds in: ``tests/test_hostile_rl.py``). The interrupted command's
    frames stay alive to the end (``_interrupt_kept``) and the cyclic garbage collector is off,
    so no native object is destroyed on the way out."""
    gc.disable()
    try:
        atexit._run_exitfuncs()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:  # a closed or broken stream: nothing more can be said on it
                pass
        os._exit(code)


def _invoke(group: click.Group, argv: list[str]) -> int:
    """Run the command; its exit status, with the one line for an error written (module
    docstring). ``UWDOCK_DEBUG=1`` adds the traceback of a bug, or of where a SIGTERM landed."""
    try:
        if HELD:  # a signal that landed before the handlers were in place (early_signals)
            _received.append(HELD[-1])
            _raised[:] = [True]
            raise _Interrupted() if HELD[-1] == signal.SIGTERM else KeyboardInterrupt()
        # click's main() without its standalone handling (which prints a blank line on an
        # interrupt): make the context, invoke, and let every exception come here
        with group.make_context(Path(sys.argv[0]).name or group.name, argv) as ctx:
            group.invoke(ctx)
    except _Interrupted as exc:
        _interrupt_kept.append(exc)
        if os.environ.get("UWDOCK_DEBUG"):  # where the signal landed
            traceback.print_exc()
        click.echo("error: interrupted (SIGTERM)", err=True)
        return 128 + signal.SIGTERM
    except (KeyboardInterrupt, click.exceptions.Abort) as exc:
        _interrupt_kept.append(exc)
        if _received[-1:] == [signal.SIGTERM]:  # a library re-raised it as a plain interrupt
            click.echo("error: interrupted (SIGTERM)", err=True)
            return 128 + signal.SIGTERM
        click.echo("error: interrupted", err=True)
        return 130
    except click.exceptions.NoArgsIsHelpError as exc:  # a bare group: its help, not an error
        click.echo(exc.ctx.get_help() if exc.ctx else group.get_help(click.Context(group)))
        return 2
    except click.ClickException as exc:  # usage errors: click's own one-line message
        message = " ".join(exc.format_message().split())
        click.echo(f"error: {message}", err=True)
        return exc.exit_code
    except click.exceptions.Exit as exc:
        return exc.exit_code
    except DockError as exc:  # a name that is not UTF-8 shown as \\xNN (dockcore.names)
        click.echo(f"error: {display_name(' '.join(str(exc).split()))}", err=True)
        return 2
    except OSError as exc:
        click.echo(f"error: {display_name(_oserror_line(exc))}", err=True)
        return 2
    except Exception as exc:  # a bug: one line, the traceback on request
        if _received:  # what an interrupt left behind (e.g. a module that failed to load)
            _interrupt_kept.append(exc)
            sigterm = signal.SIGTERM in _received
            click.echo(f"error: interrupted{' (SIGTERM)' if sigterm else ''}", err=True)
            return 128 + signal.SIGTERM if sigterm else 130
        if os.environ.get("UWDOCK_DEBUG"):
            traceback.print_exc()
        text = " ".join(str(exc).split()) or type(exc).__name__
        click.echo(
            f"error: internal error ({type(exc).__name__}: {text[:300]}); "
            "rerun with UWDOCK_DEBUG=1 for the traceback and please report it",
            err=True,
        )
        return 1
    return 0
