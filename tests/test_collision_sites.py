"""bench/collision_sites.py: the classes of the IMU-detected collisions, and a real run."""

import json
from pathlib import Path

import pytest

from tests.conftest import load_bench

cs = load_bench("collision_sites")
ROOT = Path(__file__).resolve().parents[1]


def _ev(t, xy, k=0):
    return {"episode": k, "time_s": t, "e_xy_m": xy, "e_z_m": 0.0}


def test_a_landing_counted_twice_is_a_bounce_and_far_hits_are_away():
    ep = [_ev(2.4, 4.5), _ev(2.8, 4.1), _ev(8.6, 0.006), _ev(9.0, 0.012), _ev(12.0, 0.03)]
    cs.classify(ep, seat_xy_m=0.1, bounce_s=0.5)
    assert [e["site"] for e in ep] == ["away", "away", "seat", "bounce", "seat"]
    # a hit right after an away one, at the seat, is a bounce too: the IMU cannot tell
    ep2 = [_ev(5.0, 0.3, k=1), _ev(5.2, 0.05, k=1)]
    cs.classify(ep2, seat_xy_m=0.1, bounce_s=0.5)
    assert [e["site"] for e in ep2] == ["away", "bounce"]
    s = cs.summarise(ep + ep2, n_episodes=4)
    assert s == {"episodes": 4, "collisions": 7 / 4, "seat": 2 / 4, "bounce": 2 / 4,
                 "away": 3 / 4, "episodes_with_bounce": 2}  # fmt: skip


def test_one_pid_episode_under_the_shipped_policy_settings(tmp_path):
    policy = str(ROOT / "rl/policies/realistic_ppo")
    cs.main(["--policy", policy, "--controllers", "pid", "--episodes", "1", "--seed", "0",
             "--out-dir", str(tmp_path), "--name", "cs"])  # fmt: skip
    data = json.loads((tmp_path / "cs.json").read_text())
    (row,) = data["rows"]
    assert row["controller"] == "pid" and row["episodes"] == 1
    assert row["collisions"] == len(row["events"]) == 1  # the PID's landing on the seat (seed 0)
    assert row["seat"] + row["bounce"] + row["away"] == pytest.approx(row["collisions"])
    (e,) = row["events"]
    assert e["site"] == "seat" and e["e_xy_m"] < 0.1 and e["time_s"] > 0
    assert data["bench_config"]["controllers"] == "pid" and data["git"]["commit"]


@pytest.mark.parametrize("args", [["--controllers", "sac"], ["--episodes", "0"]])
def test_bad_arguments_are_one_line(args, tmp_path):
    with pytest.raises(SystemExit, match="error: "):
        cs.main(["--policy", str(ROOT / "rl/policies/realistic_ppo"), "--out-dir", str(tmp_path),
                 *args])  # fmt: skip
