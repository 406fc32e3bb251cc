"""The figures the README and the results pages state are those of their result files.

A page marks a figure it takes from a result file with an HTML comment right after it,
``**98 %**<!--fig:ship.camera.strict-->``; ``docs/results/figures.toml`` says which file, which
value in it and how that value is written (its header explains the keys). This test finds
every marker in the README and under ``docs/``, reads the value from its file, formats it and
checks that the text just before the marker is that figure, so no figure stays behind when its
file changes. It also checks that each results page and the README keep at least a few
markers (a page cannot silently drop them), that every file the registry names exists and that
every registry entry is used.
"""

from __future__ import annotations

import json
import re
import sys
from functools import cache
from pathlib import Path
from typing import Any

import pytest

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
REGISTRY = ROOT / "docs" / "results" / "figures.toml"
MARKER = re.compile(r"<!--fig:([A-Za-z0-9_.-]+)-->")
#: Any HTML comment that looks like a figure marker (so a misspelt one is not silently skipped).
LOOSE = re.compile(r"<!--\s*fig\b.*?-->", re.IGNORECASE)
MINUS = "\u2212"

#: The least number of checked figures each page must keep.
MIN_MARKERS = {
    "README.md": 18,
    "docs/results/index.md": 20,
    "docs/results/docking.md": 150,
    "docs/results/learning.md": 60,
    "docs/results/perception.md": 150,
    "docs/results/real-footage.md": 40,
    "docs/results/speed.md": 60,
    "docs/results/shortfalls.md": 15,
    "docs/getting-started.md": 8,
}
#: Pages under docs/results/ that state no figure of their own.
NO_FIGURES = {"docs/results/archive.md"}


# --- the checker -----------------------------------------------------------------------------


def _segments(key: str) -> list[tuple[str | None, list[str]]]:
    """``a.b[k=v,x=y][0]."quoted name".c`` as (name, selectors) pairs; dots inside brackets and
    quotes do not split."""
    parts: list[str] = []
    buf, depth, quoted = "", 0, False
    for ch in key:
        if ch == '"' and depth == 0:
            quoted = not quoted
        elif ch == "[" and not quoted:
            depth += 1
        elif ch == "]" and not quoted:
            depth -= 1
        if ch == "." and depth == 0 and not quoted:
            parts.append(buf)
            buf = ""
        else:
            buf += ch
    parts.append(buf)
    out = []
    for part in parts:
        m = re.fullmatch(r'(?:"([^"]*)"|([^\[\]"]*))((?:\[[^\]]*\])*)', part)
        if m is None:
            raise ValueError(f"bad key segment {part!r} in {key!r}")
        name = m.group(1) if m.group(1) is not None else (m.group(2) or None)
        out.append((name, re.findall(r"\[([^\]]*)\]", m.group(3))))
    return out


def lookup(data: Any, key: str) -> Any:
    """The value at ``key`` in ``data`` (see ``docs/results/figures.toml``)."""
    for name, selectors in _segments(key):
        if name is not None:
            if not isinstance(data, dict) or name not in data:
                raise KeyError(f"{name!r} not found (key {key!r})")
            data = data[name]
        for sel in selectors:
            if re.fullmatch(r"-?\d+", sel):
                data = data[int(sel)]
                continue
            # conditions split at a comma that starts the next ``field=`` (a value may hold one)
            pairs = re.split(r",(?=\s*[^=,\s]+=)", sel)
            want = dict(pair.strip().split("=", 1) for pair in pairs)
            hits = [
                item
                for item in data
                if isinstance(item, dict)
                and all(k in item and str(item[k]) == v for k, v in want.items())
            ]
            if len(hits) != 1:
                raise KeyError(f"[{sel}] picks {len(hits)} items, not 1 (key {key!r})")
            data = hits[0]
    return data


def fmt(value: float, spec: str) -> str:
    """``value`` written as the pages write it (``docs/results/figures.toml``: formats)."""
    m = re.fullmatch(r"(pct|pp|f|sf|af)(\d)|int", spec)
    if m is None:
        raise ValueError(f"unknown format {spec!r}")
    if spec == "int":
        text = f"{round(value):,}"
        return text.replace("-", MINUS)
    kind, places = m.group(1), int(m.group(2))
    if kind in ("pct", "pp"):
        value *= 100
    if kind == "af":
        value = abs(value)
    text = f"{value:.{places}f}"
    if float(text) == 0:  # no "-0.0"
        text = text.lstrip("-")
    if kind == "sf" and not text.startswith("-"):
        text = "+" + text
    text = text.replace("-", MINUS)
    return text + " %" if kind == "pct" else text


def written(text_before: str, figure: str) -> bool:
    """Whether ``text_before`` (the page up to a marker) ends with ``figure``, emphasis and code
    marks aside, and ``figure`` is a whole number there (no digit or sign just before it)."""
    head = text_before.rstrip("*_`")
    if not head.endswith(figure):
        return False
    rest = head[: len(head) - len(figure)]
    return not rest or rest[-1] not in "0123456789.,+-" + MINUS


@cache
def registry() -> dict[str, Any]:
    return tomllib.loads(REGISTRY.read_text(encoding="utf-8"))


@cache
def _load(rel: str) -> Any:
    """A result file: JSON, or JSON lines (a list of the lines' objects)."""
    text = (ROOT / rel).read_text(encoding="utf-8")
    if rel.endswith(".jsonl"):
        return [json.loads(line) for line in text.splitlines() if line.strip()]
    return json.loads(text)


def expected(name: str) -> str:
    """The figure registry entry ``name`` stands for, formatted."""
    reg = registry()
    entry = reg["fig"][name]
    file, key, spec = entry[:3]
    value = lookup(_load(reg["files"][file]), key)
    if len(entry) == 5:
        value = value / lookup(_load(reg["files"][entry[3]]), entry[4])
    return fmt(float(value), spec)


def pages() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def _prose_lines(path: Path) -> list[tuple[int, str, str]]:
    """(line number, line, the line with its code spans blanked) outside fenced code blocks: a
    marker shown as code (`<!--fig:NAME-->`) is an example, not a marker."""
    out, fenced = [], False
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if not fenced:
            out.append((number, line, re.sub(r"`[^`]*`", lambda m: " " * len(m.group(0)), line)))
    return out


def markers(path: Path) -> list[tuple[int, str, str]]:
    """(line, name, text before the marker on its line) for each marker in ``path``."""
    return [
        (number, m.group(1), line[: m.start()])
        for number, line, prose in _prose_lines(path)
        for m in MARKER.finditer(prose)
    ]


# --- the checks ------------------------------------------------------------------------------


def test_the_registry_names_existing_files_and_values():
    reg = registry()
    missing = [f"{k} = {v}" for k, v in reg["files"].items() if not (ROOT / v).is_file()]
    assert not missing, (
        f"result files named in docs/results/figures.toml that do not exist: {missing}"
    )
    unused_files = (
        set(reg["files"])
        - {e[0] for e in reg["fig"].values()}
        - {e[3] for e in reg["fig"].values() if len(e) == 5}
    )
    assert not unused_files, f"files in figures.toml that no figure reads: {sorted(unused_files)}"
    for name, entry in reg["fig"].items():
        assert len(entry) in (3, 5), f"{name}: [file, key, format] or [..., over-file, over-key]"
        expected(name)  # the key resolves and the value formats


def test_every_marker_names_a_figure_and_every_figure_is_marked():
    reg = registry()
    used: set[str] = set()
    unknown = []
    for path in pages():
        for number, name, _ in markers(path):
            used.add(name)
            if name not in reg["fig"]:
                unknown.append(f"{path.relative_to(ROOT)}:{number}: {name}")
    assert not unknown, f"markers naming no entry of docs/results/figures.toml: {unknown}"
    malformed = [
        f"{path.relative_to(ROOT)}:{number}: {m.group(0)}"
        for path in pages()
        for number, _, prose in _prose_lines(path)
        for m in LOOSE.finditer(prose)
        if not MARKER.fullmatch(m.group(0))
    ]
    assert not malformed, f"figure markers not written <!--fig:NAME-->: {malformed}"
    unused = sorted(set(reg["fig"]) - used)
    assert not unused, f"figures.toml entries no page marks: {unused}"


def test_each_marked_figure_is_its_result_files_value():
    wrong = []
    for path in pages():
        for number, name, before in markers(path):
            figure = expected(name)
            if not written(before, figure):
                shown = before.rstrip("*_`")[-len(figure) - 6 :]
                where = f"{path.relative_to(ROOT)}:{number}"
                wrong.append(f"{where}: {name} is {figure!r}, the page says …{shown!r}")
    assert not wrong, "figures that differ from their result files:\n" + "\n".join(wrong)


@pytest.mark.parametrize("page", sorted(MIN_MARKERS))
def test_pages_keep_their_checked_figures(page):
    count = len(markers(ROOT / page))
    assert count >= MIN_MARKERS[page], (
        f"{page}: {count} checked figures, at least {MIN_MARKERS[page]}"
    )


def test_every_results_page_is_checked():
    results = {p.relative_to(ROOT).as_posix() for p in (ROOT / "docs" / "results").glob("*.md")}
    unlisted = sorted(results - set(MIN_MARKERS) - NO_FIGURES)
    assert not unlisted, f"results pages with no MIN_MARKERS entry: {unlisted}"


def test_the_checker_catches_a_changed_figure():
    assert fmt(0.98, "pct0") == "98 %" and fmt(0.9455, "pp0") == "95"
    assert fmt(-0.73, "f2") == MINUS + "0.73" and fmt(1.14, "sf2") == "+1.14"
    assert fmt(-0.73, "af2") == "0.73" and fmt(2862.4, "int") == "2,862"
    assert fmt(-0.004, "f2") == "0.00"
    assert written("docks **98 %", "98 %") and written("| 9.2", "9.2")
    assert not written("docks **97 %", "98 %")  # a changed number
    assert not written("docks **198 %", "98 %")  # not the whole number
    assert not written("change " + MINUS + "0.73", "0.73")  # a sign the figure does not have
    assert written("93–99", "99")  # a range's upper end
    data = {"rows": [{"condition": "camera", "v": 1}, {"condition": "current 0.4", "v": 2}]}
    assert lookup(data, "rows[condition=current 0.4].v") == 2
    rows = {"rows": [{"p": "default", "r": 1, "v": 3}, {"p": "default, no pass", "r": 1, "v": 4}]}
    assert lookup(rows, "rows[r=1,p=default, no pass].v") == 4
    assert lookup({"a": {"b c": [5, 6]}}, 'a."b c"[1]') == 6
    with pytest.raises(KeyError):
        lookup(data, "rows[condition=blind].v")
