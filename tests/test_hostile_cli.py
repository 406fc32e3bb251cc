"""Property tests over every command of every group: each numeric option declares its domain
(a :class:`dockcore.cli.DomainType`), and any value outside it stops the command with exit
status 2, one ``error:`` line naming the option, no traceback and nothing written."""

from __future__ import annotations

import contextlib
import io
import math
import sys
from pathlib import Path

import click
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uwdock.dockcore.cli import DomainType, run_group
from uwdock.dockcore.domains import bounds, check

GROUPS = ("markers", "perception", "calibration", "datasets", "sim", "rl")


def _group(name: str) -> click.Group:
    import importlib

    return importlib.import_module(f"uwdock.{name}.cli").cli


def _commands(
    group: click.Group, prefix: tuple[str, ...]
) -> list[tuple[tuple[str, ...], click.Command]]:
    out = []
    for name, cmd in sorted(group.commands.items()):
        if isinstance(cmd, click.Group):
            out += _commands(cmd, (*prefix, name))
        else:
            out.append(((*prefix, name), cmd))
    return out


COMMANDS = [(g, path, cmd) for g in GROUPS for path, cmd in _commands(_group(g), ())]


def _numeric(param: click.Parameter) -> bool:
    t = param.type
    return (
        isinstance(t, DomainType)
        or t in (click.INT, click.FLOAT)
        or isinstance(t, (click.IntRange, click.FloatRange))
    )


NUMERIC = [
    (g, path, cmd, p)
    for g, path, cmd in COMMANDS
    for p in cmd.params
    if isinstance(p, click.Option) and not p.is_flag and _numeric(p)
]


def test_every_numeric_option_declares_its_domain():
    plain = [
        f"{g} {' '.join(path)} {p.opts[0]}"
        for g, path, _, p in NUMERIC
        if not isinstance(p.type, DomainType)
    ]
    assert not plain, f"numeric options without a declared domain: {plain}"


def _placeholder(param: click.Parameter, tmp: Path) -> list[str]:
    """A value a required parameter accepts at parse time."""
    t = param.type
    if isinstance(t, click.Choice):
        value = str(t.choices[0])
    elif isinstance(t, DomainType):
        b = bounds(t.meta)
        lo = b.get("ge", b.get("gt", 1))
        value = str(int(lo) + 1 if t.base is int else float(lo) + 1.0)
    else:
        value = str(tmp / f"arg_{param.name}")
    return [value] if isinstance(param, click.Argument) else [param.opts[0], value]


def _hostile_texts(t: DomainType) -> list[str]:
    out = ["nan", "inf", "-inf", "1e999", "abc", "", "1,5"]
    if t.base is int:
        out += ["1.5", "2.0", "0x10", "nan"]
    b = bounds(t.meta)
    for k, v in b.items():
        step = {"gt": 0, "ge": -1, "lt": 0, "le": 1}[k]
        edge = v + step * (1 if t.base is int else max(1e-6, abs(v) * 1e-6))
        out.append(str(int(edge) if t.base is int else float(edge)))
        out.append(str(int(v - 1e6) if k in ("gt", "ge") else int(v + 1e6)))
    return [s for s in out if _refused(t, s)]


def _refused(t: DomainType, text: str) -> bool:
    try:
        v = int(text, 10) if t.base is int else float(text)
    except ValueError:
        return True
    if t.base is float and not math.isfinite(v):
        return True
    return check(v, t.base, t.meta, "k") is not None


def _invoke(group: str, args: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    argv = sys.argv
    sys.argv = [group, *args]
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                run_group(_group(group), args)
                code = 0
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else 1
    finally:
        sys.argv = argv
    return code, out.getvalue(), err.getvalue()


@pytest.mark.skipif(not NUMERIC, reason="no numeric options")
@settings(
    max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture],
    derandomize=True,
)  # fmt: skip
@given(data=st.data())
def test_hostile_numeric_options_stop_with_one_line(tmp_path_factory, data):
    g, path, cmd, param = data.draw(
        st.sampled_from([n for n in NUMERIC if isinstance(n[3].type, DomainType)]), label="option"
    )
    text = data.draw(st.sampled_from(_hostile_texts(param.type)), label="value")
    tmp = tmp_path_factory.mktemp("cli")
    args = list(path)
    for p in cmd.params:
        if p.required and p is not param:
            args += _placeholder(p, tmp)
    filler = _placeholder(param, tmp)[1:] * (param.nargs - 1) if param.nargs > 1 else []
    args += [param.opts[0], text, *filler]
    code, out, err = _invoke(g, args)
    assert code == 2, (args, code, out, err)
    assert out == ""
    assert err.count("\n") == 1 and err.startswith("error: "), err
    assert "Traceback" not in err
    assert param.opts[0] in err, err
    assert list(tmp.iterdir()) == [], f"{args} wrote {list(tmp.iterdir())}"


@pytest.mark.parametrize("group", GROUPS)
def test_a_bare_group_prints_its_help_not_an_error(group):
    code, out, err = _invoke(group, [])
    assert code == 2 and out.startswith("Usage:") and err == ""
