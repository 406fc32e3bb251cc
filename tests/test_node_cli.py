"""The vehicle commands refuse bad input in one line with exit status 2, before they join a DDS
domain or write anything: a pickled policy folder, a missing policy or sidecar, a config with an
unknown key or a bad value, a rate other than the policy's, a recording path that is a device or
a folder, a domain id out of range, a malformed camera outage."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "rl" / "policies" / "realistic_ppo"


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "uwdock.cli", *args],
        capture_output=True, text=True, timeout=120, cwd=cwd,
    )  # fmt: skip


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["rl", "node", "--policy", str(SHIPPED)], "rl export --policy"),
        (["rl", "node", "--policy", str(SHIPPED / "policy.zip")], "a pickle"),
        (["rl", "node", "--policy", "missing.onnx"], "not found"),
        (["rl", "node", "--config", "bad_key.toml"], "unknown config key 'topics.imagee'"),
        (["rl", "node", "--config", "bad_qos.toml"], "qos.image.depth: must be an integer"),
        (["rl", "node", "--config", "bad_topic.toml"], "odometry: must be an absolute ROS"),
        (["rl", "node", "--config", "bad_rate.toml"], "trained at 5 Hz"),
        (["rl", "node", "--record", "null.mcap"], "character device"),
        (["rl", "node", "--domain-id", "300"], "--domain-id"),
        (["rl", "node", "--duration-s", "nan"], "--duration-s"),
        (["sim", "vehicle", "--camera-outage-s", "5:2"], "START < END"),
        (["sim", "vehicle", "--camera-outage-s", "x"], "START:END"),
        (["rl", "replay", "nothing.mcap", "--out", "o"], "not found"),
    ],
)
def test_bad_input_is_one_line(tmp_path, args, message):
    (tmp_path / "bad_key.toml").write_text('[node.topics]\nimagee = "/x"\n')
    (tmp_path / "bad_qos.toml").write_text("[node.qos.image]\ndepth = 0\n")
    (tmp_path / "bad_topic.toml").write_text('[node.topics]\nodometry = "no slash"\n')
    (tmp_path / "bad_rate.toml").write_text("[node]\ncontrol_hz = 10.0\n")
    os.mknod(tmp_path / "null.mcap", stat.S_IFCHR | 0o666, os.makedev(1, 3))  # a /dev/null
    res = _run(*args, cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert res.stderr.count("\n") == 1 and res.stderr.startswith("error: "), res.stderr
    assert message in res.stderr
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())
