"""bench/rest_contacts.py: a real episode's records, and its one-line argument errors."""

import json
from pathlib import Path

import pytest

from tests.conftest import load_bench

rc = load_bench("rest_contacts")
ROOT = Path(__file__).resolve().parents[1]
POLICY = str(ROOT / "rl/policies/realistic_ppo")


def test_records_at_the_moments_asked_and_no_contact_far_above_the_station(tmp_path):
    """Spawned at least 1.5 m above the station, the vehicle touches nothing in its first
    second; the records fall on the moments asked, in order."""
    rc.main(["--policy", POLICY, "--row", "error model", "--seed", "0", "--episodes", "0",
             "--at-s", "1.0,0.4", "--out-dir", str(tmp_path), "--name", "rc"])  # fmt: skip
    data = json.loads((tmp_path / "rc.json").read_text())
    rows = data["rows"]
    assert [r["time_s"] for r in rows] == [0.4, 1.0]
    for r in rows:
        assert r["episode"] == 0 and r["contacts"] == []
        assert r["body_in_ds_m"][2] < -1.5  # the DS frame's z points down: the vehicle is above
        assert len(r["e_true_m"]) == 3 and len(r["action"]) == 6
    assert data["bench_config"]["row"] == "error model" and data["git"]["commit"]


@pytest.mark.parametrize(
    "args",
    [["--episodes", "x"], ["--episodes", "-1"], ["--episodes", "0", "--at-s", "nan"],
     ["--episodes", "0", "--row", "no such row"]],
)  # fmt: skip
def test_bad_arguments_are_one_line(args, tmp_path, capsys):
    with pytest.raises(SystemExit):
        rc.main(["--policy", POLICY, "--out-dir", str(tmp_path), *args])
    err = capsys.readouterr().err.strip().splitlines()
    assert "error: " in err[-1]
