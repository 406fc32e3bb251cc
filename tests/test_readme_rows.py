"""The README's tables state what stands now: short rows, no commit hashes, no work log."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"
MAX_ROW = 200
HEX = re.compile(r"\b[0-9a-f]{7,40}\b")
SESSION = re.compile(r"\bsession \d+", re.IGNORECASE)
SEPARATOR = re.compile(r"^\|(\s*:?-+:?\s*\|)+\s*$")


def _lines() -> list[str]:
    return README.read_text(encoding="utf-8").splitlines()


def _table_lines() -> list[tuple[int, str]]:
    return [
        (number, line)
        for number, line in enumerate(_lines(), 1)
        if line.startswith("|") and not SEPARATOR.match(line)
    ]


def _commit_like(line: str) -> list[str]:
    return [
        token
        for token in HEX.findall(line)
        if re.search(r"[0-9]", token) and re.search(r"[a-f]", token)
    ]


def test_readme_has_tables():
    assert len(_table_lines()) >= 10


def test_table_rows_are_short():
    long = [(n, len(line)) for n, line in _table_lines() if len(line) > MAX_ROW]
    assert not long, f"README table lines over {MAX_ROW} characters (line, length): {long}"


def test_table_rows_name_no_commit():
    found = [(n, _commit_like(line)) for n, line in _table_lines() if _commit_like(line)]
    assert not found, f"README table lines with commit-like tokens: {found}"


def test_readme_names_no_session():
    found = [(n, line) for n, line in enumerate(_lines(), 1) if SESSION.search(line)]
    assert not found, f"README lines naming a session: {found}"


def test_checks_catch_what_they_should():
    assert _commit_like("| speed against 248412c |") == ["248412c"]
    assert _commit_like("| 2,862 vs 244, deadbeef, 1234567 |") == []
    assert SESSION.search("measured in Session 27")
    assert not SESSION.search("docking.md#the-seeds-session-27")
    assert SEPARATOR.match("|---|---|---|") and SEPARATOR.match("| :--- | ---: |")
