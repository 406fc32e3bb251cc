"""Value domains of configuration fields and CLI options: one declaration, checked everywhere.

A numeric config field states its domain in its type with ``typing.Annotated`` and the
constraint vocabulary of the ``annotated-types`` package (the one pydantic and others read)::

    size_mm: Positive = 100.0                       # finite, > 0
    gamma: Annotated[float, Interval(ge=0, le=1)] = 0.99
    n_envs: Annotated[int, Interval(ge=1, le=256)] = 2

Every float is finite unless stated otherwise (no field of the toolkit takes NaN or infinity);
an int is an int (a float or a bool is a wrong type). :func:`check` applies a domain and returns
one line naming the key (``ppo.gamma: must be in [0, 1], got 1.5``); :mod:`dockcore.config`
calls it on every field it loads and :class:`dockcore.cli.DomainType` on every numeric option,
so a TOML file and a flag cannot disagree about what a value may be.

The aliases below name the common domains; a field with a domain of its own writes it out with
``Interval`` (or ``Ge``/``Gt``/``Le``/``Lt``). ``Finite`` marks a number that may take any finite
value (a coordinate, an offset): declared, so a test can tell it from a forgotten domain.
"""

from __future__ import annotations

import math
import typing
from typing import Annotated, Any

from annotated_types import BaseMetadata, Ge, GroupedMetadata, Gt, Interval, Le, Lt

__all__ = [
    "Count",
    "Finite",
    "Fraction",
    "Ge",
    "Gt",
    "Interval",
    "Le",
    "Lt",
    "NonNegative",
    "NonNegativeInt",
    "Positive",
    "PositiveInt",
    "Seed",
    "bounds",
    "check",
    "describe",
    "domain_of",
    "split_annotated",
]

#: Any finite number (a coordinate, an offset, a signed quantity).
Finite = Annotated[float, Interval()]
#: A finite number > 0 (sizes, rates, times, masses).
Positive = Annotated[float, Gt(0)]
#: A finite number >= 0.
NonNegative = Annotated[float, Ge(0)]
#: A fraction or probability in [0, 1].
Fraction = Annotated[float, Interval(ge=0, le=1)]
#: An integer >= 1.
PositiveInt = Annotated[int, Ge(1)]
#: An integer >= 0.
NonNegativeInt = Annotated[int, Ge(0)]
#: A count of things a person asks for (frames, episodes, steps): 1 ... 10^9.
Count = Annotated[int, Interval(ge=1, le=10**9)]
#: A random seed NumPy, PyTorch and Gymnasium all accept: 0 ... 2^32 - 1.
Seed = Annotated[int, Interval(ge=0, le=2**32 - 1)]


def split_annotated(tp: Any) -> tuple[Any, tuple[Any, ...]]:
    """``Annotated[T, *meta]`` -> ``(T, meta)``; any other type -> ``(tp, ())``."""
    if typing.get_origin(tp) is Annotated:
        base, *meta = typing.get_args(tp)
        return base, tuple(meta)
    return tp, ()


def _flatten(meta: tuple[Any, ...]) -> tuple[BaseMetadata, ...]:
    out: list[BaseMetadata] = []
    for m in meta:
        if isinstance(m, GroupedMetadata):
            out.extend(_flatten(tuple(m)))
        elif isinstance(m, (Gt, Ge, Lt, Le)):
            out.append(m)
    return tuple(out)


#: ``ids of the metadata objects -> (the metadata, its bounds)``; the metadata is held so that
#: its ids cannot be reused by other objects while the entry lives.
_CONSTRAINTS: dict[tuple[int, ...], tuple[tuple[Any, ...], tuple[BaseMetadata, ...]]] = {}


def _constraints(meta: tuple[Any, ...]) -> tuple[BaseMetadata, ...]:
    """The bounds in ``meta``, groups (``Interval``) flattened. Cached: ``GroupedMetadata`` is a
    runtime-checkable Protocol, so each ``isinstance`` costs tens of microseconds, and configs
    checked per frame (:func:`dockcore.config.check_fields`) would pay it every time.

    Keyed by the identity of the metadata objects, not by equality: ``Interval(le=1e9)`` equals
    ``Interval(le=10**9)`` and hashes alike, and an equality-keyed cache would describe the
    second with the first one's float bound (``1e+09``) depending on which was checked first.
    """
    key = tuple(map(id, meta))
    hit = _CONSTRAINTS.get(key)
    if hit is None:
        hit = _CONSTRAINTS[key] = (meta, _flatten(meta))
    return hit[1]


def domain_of(tp: Any) -> tuple[Any, ...] | None:
    """The domain metadata of an annotated type, or None when the type declares none."""
    _, meta = split_annotated(tp)
    if not any(isinstance(m, (GroupedMetadata, BaseMetadata)) for m in meta):
        return None
    return meta


def bounds(meta: tuple[Any, ...]) -> dict[str, float]:
    """The bounds of a domain as ``{"gt"|"ge"|"lt"|"le": value}``."""
    out: dict[str, float] = {}
    for c in _constraints(meta):
        name = type(c).__name__.lower()
        out[name] = getattr(c, name)
    return out


def _fmt(v: float) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def describe(meta: tuple[Any, ...], integer: bool = False) -> str:
    """A domain in words: ``> 0``, ``in [0, 1]``, ``an integer >= 1``, ``a finite number``."""
    b = bounds(meta)
    lo = ("[", b["ge"]) if "ge" in b else ("(", b["gt"]) if "gt" in b else None
    hi = ("]", b["le"]) if "le" in b else (")", b["lt"]) if "lt" in b else None
    kind = "an integer" if integer else "a finite number"
    if lo and hi:
        return f"{kind} in {lo[0]}{_fmt(lo[1])}, {_fmt(hi[1])}{hi[0]}"
    if lo:
        return f"{kind} {'>=' if lo[0] == '[' else '>'} {_fmt(lo[1])}"
    if hi:
        return f"{kind} {'<=' if hi[0] == ']' else '<'} {_fmt(hi[1])}"
    return kind


def check(value: Any, base: type, meta: tuple[Any, ...], key: str) -> str | None:
    """Why ``value`` is outside the domain ``(base, meta)``, as one line naming ``key``; None
    when it is inside. ``base`` is ``int`` or ``float``."""
    integer = base is int
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return f"{key}: must be {describe(meta, integer)}, got {value!r}"
    if integer and not isinstance(value, int):
        return f"{key}: must be {describe(meta, integer)}, got {value!r}"
    if not integer and not math.isfinite(value):
        return f"{key}: must be {describe(meta, integer)}, got {value!r}"
    for c in _constraints(meta):
        ok = (
            value > c.gt
            if isinstance(c, Gt)
            else value >= c.ge
            if isinstance(c, Ge)
            else value < c.lt
            if isinstance(c, Lt)
            else value <= c.le
        )
        if not ok:
            return f"{key}: must be {describe(meta, integer)}, got {_fmt(value)}"
    return None
