"""Component configuration: one frozen dataclass per component, overridden from TOML.

Conventions:
    * Defaults live in code, in the dataclass. Every field is documented in the class docstring
      with its unit, and the unit sits in the field name (``size_mm``, ``hfov_deg``).
    * A TOML file overrides any subset of fields; nested dataclasses are TOML tables.
    * An unknown key, a wrong type or an out-of-range value raises :class:`ConfigError`
      naming the key (``marker.size_mm: must be a finite number > 0, got -3``).
    * A numeric field declares its domain in its type (:mod:`dockcore.domains`:
      ``size_mm: Positive``, ``gamma: Annotated[float, Interval(ge=0, le=1)]``); every float is
      finite (NaN and infinity are refused everywhere), an int is an int.
    * A dataclass may define ``validate(self) -> None`` that raises ``ValueError``; it is called
      after every load and on :func:`replace`.
    * Files written in an older layout load unchanged; the loader puts them in the current one
      (:func:`current_layout`) before anything reads them. A field that moved into a nested
      table is listed in ``MOVED_KEYS: ClassVar[Mapping[str, str]]`` (old key -> the table it
      moved into, under the same name) and lifted there (a key given at both places is an
      error); a dataclass whose old layout needs more than a move defines a classmethod
      ``upgrade_layout(data) -> data`` that rewrites its level of plain data.
    * Code names a field by a typed selector, not a dotted string: :func:`field_path` turns
      ``lambda c: c.world.camera_width_px`` into ``("world", "camera_width_px")``, checked
      against the dataclass (an editor follows and renames the attributes).
    * A file may start from another: ``extends = "configs/realistic/policy.toml"`` (top level)
      loads that base first, then merges the file's own values over it (tables merge key by
      key, other values replace), recursively (:func:`config_layers`). A relative path is looked
      for beside the file, then in the folders above it, then in the repository's root
      (:func:`resolve_extends`).

Example:
    >>> cfg = load_config(MarkerConfig, "marker.toml", overrides={"size_mm": 80})
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import re
import sys
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

import tomli_w

from uwdock.dockcore.domains import check as check_domain
from uwdock.dockcore.domains import split_annotated
from uwdock.dockcore.errors import ConfigError
from uwdock.dockcore.io import read_text

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

C = TypeVar("C")
_KEYED = re.compile(r"^[A-Za-z_][\w.\[\]]*: ")


def read_toml(path: str | os.PathLike[str], what: str = "config file") -> dict[str, Any]:
    """Read a UTF-8 TOML file (a byte-order mark is accepted); a missing, unreadable, non-UTF-8
    or malformed file raises a one-line :class:`ConfigError` that calls it ``what``."""
    path = Path(path)
    text = read_text(path, what)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"malformed TOML in {path}: {exc}") from None


def _coerce(value: Any, tp: Any, key: str) -> Any:
    """Convert a TOML value to the annotated type ``tp`` or raise ConfigError naming ``key``."""
    base, meta = split_annotated(tp)
    if meta and base in (int, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            what = "an integer" if base is int else "a number"
            raise ConfigError(f"{key}: expected {what}, got {value!r}")
        if base is int and not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        reason = check_domain(value, base, meta, key)
        if reason:
            raise ConfigError(reason)
        return base(value)
    if meta:
        return _coerce(value, base, key)
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, key)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if errors else f"{key}: invalid value {value!r}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{key}: must be one of {list(args)}, got {value!r}")
        return value
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key}: expected a table, got {type(value).__name__}")
        return _build(tp, value, prefix=f"{key}.")
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: expected a list, got {type(value).__name__}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f"{key}: expected {len(args)} values, got {len(value)}")
            pairs = enumerate(zip(value, args, strict=True))
            items = [_coerce(v, a, f"{key}[{i}]") for i, (v, a) in pairs]
        else:
            inner = args[0] if args else Any
            items = [_coerce(v, inner, f"{key}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key}: expected a table, got {type(value).__name__}")
        inner = args[1] if len(args) == 2 else Any
        return {str(k): _coerce(v, inner, f"{key}.{k}") for k, v in value.items()}
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true/false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{key}: must be a finite number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return value
    return value


def _lift_here(cls: type, data: Mapping[str, Any], prefix: str) -> Mapping[str, Any]:
    """``data`` in ``cls``'s current layout at this level: the old keys of ``cls.MOVED_KEYS``
    moved into their tables, then ``cls.upgrade_layout`` where the class has one."""
    upgrade = getattr(cls, "upgrade_layout", None)
    if callable(upgrade):
        data = upgrade(data)
    moved: Mapping[str, str] = getattr(cls, "MOVED_KEYS", None) or {}
    if not any(k in moved for k in data):
        return data
    out = dict(data)
    for old, table in moved.items():
        if old not in out:
            continue
        inner = out.get(table, {})
        if not isinstance(inner, Mapping):
            raise ConfigError(f"{prefix}{table}: expected a table, got {type(inner).__name__}")
        if old in inner:
            raise ConfigError(
                f"{prefix}{table}.{old}: given twice, as '{prefix}{old}' (the flat layout of "
                f"older files) and in the '{prefix}{table}' table; keep one"
            )
        out[table] = {**inner, old: out.pop(old)}
    return out


def current_layout(cls: type, data: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Plain config data of ``cls`` in its current layout, here and in nested tables: the keys
    of each dataclass's ``MOVED_KEYS`` moved into their tables and its ``upgrade_layout``
    applied (module docstring).

    The loader does this on every load. Readers of stored configs (a run folder's
    ``config.toml``, an exported policy's ``.json``) call it at their edge, before merging the
    data with data in the current layout (:func:`merge`), or an old key would be seen at both
    places.

    Raises:
        ConfigError: a key given both at its old place and in its table, or a moved-into key
            that is not a table. Unknown keys are left for the loader to refuse.
    """
    out = dict(_lift_here(cls, data, prefix))
    hints = typing.get_type_hints(cls, include_extras=True)
    for f in dataclasses.fields(cls):
        value = out.get(f.name)
        tp = split_annotated(hints[f.name])[0]
        if isinstance(value, Mapping) and isinstance(tp, type) and dataclasses.is_dataclass(tp):
            out[f.name] = current_layout(tp, value, f"{prefix}{f.name}.")
    return out


class _FieldRecorder:
    """Stands in for a config dataclass in :func:`field_path`: records the fields read."""

    def __init__(self, cls: type, path: tuple[str, ...]) -> None:
        self._cls = cls
        self._path = path

    def __getattr__(self, name: str) -> _FieldRecorder:
        cls = self.__dict__["_cls"]
        path = self.__dict__["_path"]
        if cls is None or not dataclasses.is_dataclass(cls):
            raise AttributeError(f"{'.'.join(path)} is not a table: no field {name!r}")
        hints = typing.get_type_hints(cls, include_extras=True)
        if name not in {f.name for f in dataclasses.fields(cls)}:
            raise AttributeError(f"{cls.__name__} has no field {name!r}")
        tp = split_annotated(hints[name])[0]
        inner = tp if isinstance(tp, type) and dataclasses.is_dataclass(tp) else None
        return _FieldRecorder(inner, (*path, name))


def field_path(cls: type, select: typing.Callable[[Any], Any]) -> tuple[str, ...]:
    """The field a selector reads: ``field_path(EnvConfig, lambda c: c.world.camera_width_px)``
    is ``("world", "camera_width_px")``.

    Raises:
        AttributeError: the selector reads a field ``cls`` does not have (checked through the
            nested dataclasses), or reads nothing.
    """
    got = select(_FieldRecorder(cls, ()))
    path = got.__dict__.get("_path") if isinstance(got, _FieldRecorder) else None
    if not path:
        raise AttributeError(f"the selector reads no field of {cls.__name__}")
    return path


def value_at(cfg: Any, path: tuple[str, ...]) -> Any:
    """The value of the field at ``path`` (:func:`field_path`) of a config dataclass."""
    for part in path:
        cfg = getattr(cfg, part)
    return cfg


def replace_at(cfg: C, path: tuple[str, ...], value: Any) -> C:
    """``cfg`` with the field at ``path`` (:func:`field_path`) set to ``value``, the dataclasses
    above it copied (``dataclasses.replace``: not re-validated)."""
    head, *rest = path
    inner = replace_at(getattr(cfg, head), tuple(rest), value) if rest else value
    return dataclasses.replace(cfg, **{head: inner})  # type: ignore[type-var]


def has_path(data: Mapping[str, Any], path: tuple[str, ...]) -> bool:
    """Whether plain config data sets the field at ``path`` (:func:`field_path`)."""
    obj: Any = data
    for part in path:
        if not isinstance(obj, Mapping) or part not in obj:
            return False
        obj = obj[part]
    return True


def _build(cls: type[C], data: Mapping[str, Any], prefix: str = "") -> C:
    data = _lift_here(cls, data, prefix)
    hints = typing.get_type_hints(cls, include_extras=True)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(
            f"unknown config key '{prefix}{unknown[0]}' for {cls.__name__} "
            f"(valid keys: {', '.join(sorted(names))})"
        )
    kwargs = {k: _coerce(v, hints[k], f"{prefix}{k}") for k, v in data.items()}
    try:
        obj = cls(**kwargs)
        _validate(obj, prefix)
    except ConfigError:
        raise
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{prefix.rstrip('.') or cls.__name__}: {exc}") from None
    return obj


def _validate(obj: Any, prefix: str = "") -> None:
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            _validate(value, f"{prefix}{f.name}.")
    check = getattr(obj, "validate", None)
    if callable(check):
        try:
            check()
        except ConfigError:
            raise
        except ValueError as exc:
            text = str(exc)
            if _KEYED.match(text):  # "key: reason"
                raise ConfigError(f"{prefix}{text}") from None
            raise ConfigError(f"{prefix.rstrip('.') or type(obj).__name__}: {text}") from None


def from_dict(cls: type[C], data: Mapping[str, Any]) -> C:
    """Build ``cls`` from a (possibly partial, possibly nested) mapping of overrides."""
    return _build(cls, data)


@functools.cache
def _numeric_fields(cls: type) -> tuple[tuple[str, bool, tuple[tuple[type, tuple], ...]], ...]:
    """``(name, variadic, ((base, domain), ...))`` of the numeric fields of dataclass ``cls``,
    resolved once: one element for a scalar, one per element for a fixed tuple, one for every
    element of a ``tuple[T, ...]`` (``variadic``); ``None`` dropped from optional fields."""
    hints = typing.get_type_hints(cls, include_extras=True)
    out = []
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if typing.get_origin(tp) in (typing.Union, types.UnionType):
            args = [a for a in typing.get_args(tp) if a is not type(None)]
            tp = args[0] if len(args) == 1 else tp
        if typing.get_origin(tp) is tuple:
            args = typing.get_args(tp)
            variadic = len(args) == 2 and args[1] is Ellipsis
            elems = tuple(split_annotated(a) for a in (args[:1] if variadic else args))
            if all(base in (int, float) for base, _ in elems):
                out.append((f.name, variadic, elems))
        elif split_annotated(tp)[0] in (int, float):
            out.append((f.name, False, (split_annotated(tp),)))
    return tuple(out)


def check_fields(cfg: Any) -> None:
    """Raise ValueError naming the first numeric field of ``cfg`` outside its declared domain.

    The loader's check (:func:`dockcore.config.validated`) for a flat config built in Python,
    without its round trip through a dict: for configs checked on every frame.
    """
    for name, variadic, elems in _numeric_fields(type(cfg)):
        value = getattr(cfg, name)
        if value is None:
            continue
        if not isinstance(value, (tuple, list)):
            items = [(name, value)]
        else:
            if not variadic and len(value) != len(elems):
                raise ValueError(f"{name}: expected {len(elems)} values, got {value!r}")
            items = [(f"{name}[{i}]", v) for i, v in enumerate(value)]
            elems = elems * len(value) if variadic else elems
        if len(items) != len(elems):
            raise ValueError(f"{name}: expected {len(elems)} values, got {value!r}")
        for (key, item), (base, meta) in zip(items, elems, strict=True):
            reason = check_domain(item, base, meta, key) if meta else None
            if reason:
                raise ValueError(reason)


def validated(cfg: C) -> C:
    """``cfg`` checked as if it had been loaded from a file: every field's type and domain, then
    ``validate()``. Returns an equal config or raises :class:`ConfigError` naming the key.

    Library entry points call it on configs built in Python (``SynthConfig(n_frames=...)``), so
    the API refuses what a TOML file or a flag would."""
    return from_dict(type(cfg), to_dict(cfg))


def changed_keys(a: Any, b: Any, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two plain config dicts (:func:`to_dict`)."""
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        out = []
        for k in sorted(set(a) | set(b), key=str):
            out += changed_keys(a.get(k), b.get(k), f"{prefix}{k}.")
        return out
    return [] if a == b else [prefix.rstrip(".")]


def merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """Recursively merge ``over`` onto ``base`` (tables merge, other values replace)."""
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = merge(out[k], v)
        else:
            out[k] = v
    return out


def _sets_nothing(data: Mapping[str, Any]) -> bool:
    """Whether a TOML document holds no value at all (nothing, or only empty tables)."""
    return all(isinstance(v, Mapping) and _sets_nothing(v) for v in data.values())


#: The repository's root: the last place a relative ``extends`` is looked for.
ROOT = Path(__file__).resolve().parent.parent
#: The most files one ``extends`` chain may hold (the file itself included).
EXTENDS_DEPTH = 8


@dataclasses.dataclass(frozen=True)
class ConfigLayer:
    """One file of a config's ``extends`` chain (:func:`config_layers`).

    Attributes:
        path: the file, as given (the first layer) or as resolved (a base).
        data: the values it sets itself (``extends`` removed, ``section`` unwrapped, in the
            current layout when the loader was told the class).
        base: whether it is a base of the file asked for (not that file itself).
    """

    path: Path
    data: dict[str, Any]
    base: bool


def resolve_extends(value: str, file: Path) -> Path:
    """The file an ``extends = value`` in ``file`` names: an absolute path as given; a relative
    one in ``file``'s folder, else in the nearest folder above it that holds it (a config inside
    a checkout names its base from the checkout's root, as configs name their data files), else
    in the repository's root (:data:`ROOT`: a config anywhere can extend a shipped one,
    ``extends = "configs/realistic/policy.toml"``).

    Raises:
        ConfigError: nothing there.
    """
    p = Path(value).expanduser()
    if p.is_absolute():
        if not os.path.lexists(p):
            raise ConfigError(f"{file}: extends {value!r}: no such file")
        return p
    folder = file.absolute().parent
    for base in (folder, *folder.parents, ROOT):
        if os.path.lexists(base / p):
            return base / p
    raise ConfigError(
        f"{file}: extends {value!r}: no such file in {folder}, the folders above it or {ROOT}"
    )


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve() or os.path.samefile(a, b)
    except OSError:
        return False


def config_layers(
    path: str | os.PathLike[str], section: str | None = None, cls: type | None = None
) -> list[ConfigLayer]:
    """The files of the config at ``path``, its furthest base first and ``path`` last: a file
    that says ``extends = "BASE"`` (top level, a path resolved by :func:`resolve_extends`) is
    that base's values with its own merged over them (:func:`merge`: tables merge key by key,
    other values, arrays included, replace). Each file is read as :func:`config_data` reads one
    (``section`` unwrapped); with ``cls``, each file's keys are put in the current layout
    (:func:`current_layout`) before they merge, so a file in the current layout can extend one
    written before a key moved.

    Raises:
        ConfigError: one line: a file missing, unreadable, not UTF-8 or malformed; an
            ``extends`` that is not a non-empty string or names nothing; a cycle; a chain of
            more than :data:`EXTENDS_DEPTH` files; a file that sets nothing and extends nothing.
    """
    layers: list[ConfigLayer] = []
    chain: list[Path] = []
    file: Path | None = Path(path)
    while file is not None:
        if any(_same_file(file, seen) for seen in chain):
            shown = " -> ".join(str(p) for p in (*chain, file))
            raise ConfigError(f"config {chain[0]}: extends goes round in a cycle: {shown}")
        if len(chain) == EXTENDS_DEPTH:
            raise ConfigError(
                f"config {chain[0]}: its extends chain holds more than {EXTENDS_DEPTH} files "
                f"(at {file})"
            )
        chain.append(file)
        what = "config file" if len(chain) == 1 else f"base config (extended by {chain[-2]})"
        data: dict[str, Any] = read_toml(file, what)
        value = data.pop("extends", None)
        inner = data.get(section) if section else None
        if isinstance(inner, Mapping) and "extends" in inner:
            raise ConfigError(f"{file}: extends goes at the top of the file, not in [{section}]")
        if value is not None and (not isinstance(value, str) or not value.strip()):
            raise ConfigError(f"{file}: extends: expected a config file's path, got {value!r}")
        if value is None and _sets_nothing(data):
            empty = "0 bytes" if not file.stat().st_size else "only comments or empty tables"
            table = f" [{section}]" if section else ""
            if len(chain) > 1:
                raise ConfigError(
                    f"base config {file} (extended by {chain[-2]}) is empty ({empty}): it sets "
                    f"no{table} value"
                )
            raise ConfigError(
                f"config {file} is empty ({empty}): it sets no{table} value; "
                "leave --config out to run with the defaults"
            )
        if section is not None and set(data) == {section} and isinstance(data[section], Mapping):
            data = dict(data[section])
        if cls is not None:
            data = current_layout(cls, data)
        layers.append(ConfigLayer(file, data, base=len(chain) > 1))
        file = resolve_extends(value, file) if value is not None else None
    return layers[::-1]


def config_data(
    path: str | os.PathLike[str], section: str | None = None, cls: type | None = None
) -> dict[str, Any]:
    """The plain data of a TOML config file, merged over the bases it ``extends``
    (:func:`config_layers`); with ``section``, a file whose only top-level key is that table (an
    output's ``config.toml``) is read from inside it; with ``cls``, in that class's current
    layout.

    Raises:
        ConfigError: also for a file that sets nothing (0 bytes, only comments, blank lines or
            empty tables) and extends nothing: a ``--config`` given is meant to change
            something, and an empty one (a truncated copy, the wrong file) would otherwise run
            with every default, e.g. ``rl train`` for two million steps, without a word.
    """
    data: dict[str, Any] = {}
    for layer in config_layers(path, section, cls):
        data = merge(data, layer.data)
    return data


def load_config(
    cls: type[C],
    path: str | os.PathLike[str] | None = None,
    overrides: Mapping[str, Any] | None = None,
    section: str | None = None,
) -> C:
    """Defaults of ``cls``, then the TOML file at ``path`` (over the bases it ``extends``,
    :func:`config_layers`), then ``overrides`` (e.g. CLI flags).

    ``None`` values in ``overrides`` are skipped, so unset CLI options leave the file's values.
    With ``section``, a file whose only top-level key is that table (as in the ``config.toml``
    written next to every output) is read from inside it, so an output's config can be reused.
    """
    data = config_data(path, section, cls) if path is not None else {}
    if overrides:
        data = merge(data, {k: v for k, v in overrides.items() if v is not None})
    return _build(cls, data)


def replace(cfg: C, **changes: Any) -> C:
    """``dataclasses.replace`` that re-validates (raises ConfigError on a bad value).

    Values may be plain data or config dataclasses (which replace that table whole); a partial
    mapping changes those keys of a table (``replace(env, world={"water_preset": "turbid"})``).
    A key in an older layout (:func:`current_layout`) changes the field it became.
    """
    plain = {k: to_dict(v) if dataclasses.is_dataclass(v) else v for k, v in changes.items()}
    return from_dict(type(cfg), merge(to_dict(cfg), current_layout(type(cfg), plain)))


def to_dict(cfg: Any) -> dict[str, Any]:
    """A plain, TOML-serialisable dict of a config dataclass (tuples become lists)."""

    def conv(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, (tuple, list)):
            return [conv(x) for x in v]
        if isinstance(v, Mapping):
            return {str(k): conv(x) for k, x in v.items()}
        if isinstance(v, Path):
            return str(v)
        if hasattr(v, "item") and callable(v.item):  # numpy scalar
            return v.item()
        return v

    return conv(cfg)


def dumps_toml(cfg: Any) -> str:
    """Serialise a config dataclass (or a dict of them) as TOML; ``None`` fields are omitted."""

    def drop_none(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: drop_none(x) for k, x in v.items() if x is not None}
        return v

    data = {k: to_dict(v) for k, v in cfg.items()} if isinstance(cfg, Mapping) else to_dict(cfg)
    return tomli_w.dumps(drop_none(data))
