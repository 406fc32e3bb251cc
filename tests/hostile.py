"""Hostile values for the property tests: walk a config dataclass down to its scalar fields,
and draw values outside (or inside) each field's declared domain.

A *leaf* is one scalar field of a config, addressed by its path from the root config as the
loader names it in errors: ``("env", "vehicle", "thrusters", 2, "x_m")`` ->
``env.vehicle.thrusters[2].x_m``.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass
from typing import Any, Literal

from hypothesis import strategies as st

from uwdock.dockcore.config import to_dict
from uwdock.dockcore.domains import bounds, domain_of, split_annotated


@dataclass(frozen=True)
class Leaf:
    """A scalar field: its path, its type without ``None`` (int, float, str, bool, Literal) and
    its domain metadata (empty: none declared); ``optional`` when None is allowed."""

    path: tuple[str | int, ...]
    tp: Any
    meta: tuple[Any, ...]
    optional: bool
    owner: str = ""

    @property
    def key(self) -> str:
        out = ""
        for p in self.path:
            out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else p)
        return out

    @property
    def base(self) -> Any:
        return split_annotated(self.tp)[0]

    @property
    def numeric(self) -> bool:
        return self.base in (int, float)


def _strip_none(tp: Any) -> tuple[Any, bool]:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0], len(args) < len(typing.get_args(tp))
    return tp, False


def _walk(tp: Any, value: Any, path: tuple, owner: str = "") -> list[Leaf]:
    tp, optional = _strip_none(tp)
    base, _ = split_annotated(tp)
    if dataclasses.is_dataclass(base):
        hints = typing.get_type_hints(base, include_extras=True)
        data = value if isinstance(value, dict) else to_dict(value) if value is not None else {}
        out = []
        for f in dataclasses.fields(base):
            if f.init and f.name in data:
                out += _walk(
                    hints[f.name], data[f.name], (*path, f.name), f"{base.__qualname__}.{f.name}"
                )
        return out
    origin = typing.get_origin(base)
    if origin in (tuple, list) and isinstance(value, (list, tuple)):
        args = typing.get_args(base)
        out = []
        for i, v in enumerate(value):
            arg = args[0] if (not args or args[-1] is Ellipsis or origin is list) else args[i]
            out += _walk(arg, v, (*path, i), owner)
        return out
    if origin is dict and isinstance(value, dict):
        inner = typing.get_args(base)[1] if typing.get_args(base) else Any
        out = []
        for k, v in value.items():
            out += _walk(inner, v, (*path, str(k)), owner)
        return out
    if base in (int, float, str, bool) or typing.get_origin(base) is Literal:
        return [Leaf(path, tp, domain_of(tp) or (), optional, owner)]
    return []


def leaves(cls: type) -> list[Leaf]:
    """The scalar fields of config ``cls`` with their default values present."""
    return _walk(cls, to_dict(cls()), ())


def nested_classes(cls: type, seen: set | None = None) -> set[type]:
    """``cls`` and every dataclass its fields contain (through tuples, lists, dicts, unions)."""
    seen = set() if seen is None else seen
    if cls in seen:
        return seen
    seen.add(cls)

    def visit(tp: Any) -> None:
        tp, _ = split_annotated(tp)
        if dataclasses.is_dataclass(tp):
            nested_classes(tp, seen)
        for a in typing.get_args(tp):
            if a is not Ellipsis:
                visit(a)

    for t in typing.get_type_hints(cls, include_extras=True).values():
        visit(t)
    return seen


def set_path(data: dict, path: tuple, value: Any) -> dict:
    """A copy of ``data`` (nested dicts/lists) with ``value`` at ``path``."""
    if not path:
        return value
    head, *rest = path
    if isinstance(data, list):
        out = list(data)
        out[head] = set_path(out[head], tuple(rest), value)
        return out
    out = dict(data)
    out[head] = set_path(out.get(head), tuple(rest), value)
    return out


def _outside(leaf: Leaf) -> list[Any]:
    """Values the leaf must refuse."""
    base = leaf.base
    if base is bool:
        return ["yes", 1, 0.0, [True]]
    if base is str:
        return [3, 2.5, True, ["x"], {"a": 1}]
    if typing.get_origin(base) is Literal:
        return ["no-such-choice", 7, None if not leaf.optional else 7.5]
    wrong = ["1", "nan", True, [1.0], {"v": 1}]
    special = [math.nan, math.inf, -math.inf]
    b = bounds(leaf.meta)
    edges: list[Any] = []
    step = 1 if base is int else 1e-9
    if "gt" in b:
        edges += [b["gt"], b["gt"] - 1, b["gt"] - 1e6]
    if "ge" in b:
        edges += [b["ge"] - step * max(1.0, abs(b["ge"])), b["ge"] - 1e6]
    if "lt" in b:
        edges += [b["lt"], b["lt"] + 1, b["lt"] + 1e6]
    if "le" in b:
        edges += [b["le"] + step * max(1.0, abs(b["le"])), b["le"] + 1e6]
    if base is int:
        edges = [math.floor(e) if e < 0 or "ge" in b else int(e) for e in edges]
        edges = [e for e in edges if _refused(leaf, e)]
        return [*wrong, 1.5, 2.0, *special, *edges]
    return [*wrong, *special, *[float(e) for e in edges if _refused(leaf, float(e))]]


def _refused(leaf: Leaf, v: Any) -> bool:
    from uwdock.dockcore.domains import check

    return check(v, leaf.base, leaf.meta, "k") is not None


def hostile(leaf: Leaf) -> st.SearchStrategy:
    """A value ``leaf`` must refuse (type, NaN/inf, outside its bounds)."""
    return st.sampled_from(_outside(leaf))


def inside(leaf: Leaf) -> st.SearchStrategy:
    """A value inside ``leaf``'s declared domain (the loader must accept it or give a
    ConfigError from a cross-field check, nothing else)."""
    base = leaf.base
    if base is bool:
        return st.booleans()
    if base is str:
        return st.text(max_size=12)
    if typing.get_origin(base) is Literal:
        return st.sampled_from(typing.get_args(base))
    b = bounds(leaf.meta)
    lo = b.get("ge", b.get("gt"))
    hi = b.get("le", b.get("lt"))
    if base is int:
        lo_i = (
            None if lo is None else math.ceil(lo) + (1 if "gt" in b and lo == math.ceil(lo) else 0)
        )
        hi_i = (
            None
            if hi is None
            else math.floor(hi) - (1 if "lt" in b and hi == math.floor(hi) else 0)
        )
        return st.integers(min_value=lo_i, max_value=hi_i)
    return st.floats(
        min_value=lo, max_value=hi, exclude_min="gt" in b, exclude_max="lt" in b,
        allow_nan=False, allow_infinity=False,
    )  # fmt: skip
