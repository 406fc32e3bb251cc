"""bench/gpu_physx_probe.py: the library search and the child's report, without SAPIEN's
download (a machine with network would fetch the library for minutes)."""

from __future__ import annotations

import pytest

from tests.conftest import bench_module


@pytest.fixture(scope="module")
def probe_mod():
    yield from bench_module("gpu_physx_probe")


def test_the_library_is_found_where_sapien_looks_and_where_it_was_put(
    probe_mod, tmp_path, monkeypatch
):
    home, other = tmp_path / "home", tmp_path / "opt"
    monkeypatch.setenv("HOME", str(home))
    assert probe_mod._find_library("5.3.1", roots=(other,)) == []
    own = home / ".sapien" / "physx" / "5.3.1" / "libPhysXGpu_64.so"
    own.parent.mkdir(parents=True)
    own.write_bytes(b"\x7fELF")
    placed = other / "physx" / "bin" / "libPhysXGpu_64.so"
    placed.parent.mkdir(parents=True)
    placed.write_bytes(b"\x7fELF")
    assert probe_mod._find_library("5.3.1", roots=(other,)) == [str(own), str(placed)]


def test_the_child_report_a_crash_and_a_hang_each_give_one_finding(probe_mod, tmp_path):
    ok = 'import json; print("PROBE " + json.dumps({"physx": "9.9", "enable_gpu": "ok"}))'
    found = probe_mod.probe(30, child=ok, roots=(tmp_path,))
    assert found["enable_gpu"] == "ok" and found["physx"] == "9.9"
    assert found["library_found"] == [] and isinstance(found["gpu"], str)
    found = probe_mod.probe(30, child="raise SystemExit('no sapien here')", roots=(tmp_path,))
    assert found["child"] == "exit 1" and "no sapien here" in found["stderr"]
    found = probe_mod.probe(0.5, child="import time; time.sleep(5)", roots=(tmp_path,))
    assert found["enable_gpu"].startswith("no answer within 0.5 s")
