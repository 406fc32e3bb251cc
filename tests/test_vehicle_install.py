"""``pip install "uwdock[vehicle]"`` in a fresh virtual environment runs ``rl replay`` with no
torch, no SAPIEN, no Gymnasium and no numba installed (slow: it installs from PyPI)."""

from __future__ import annotations

import json
import subprocess
import venv
from pathlib import Path

import numpy as np
import pytest

from uwdock.calibration.frames import R_from_rpy, make_T
from uwdock.ros import messages as rm
from uwdock.ros.mcap import McapRecorder

ROOT = Path(__file__).resolve().parents[1]


def _mission(path: Path) -> None:
    """A 3 s recording on the default (COLA2-like) topics: a DS prior, odometry and blank
    frames at 5 Hz."""
    rec = McapRecorder(path)
    t0 = 10_000_000_000
    T_ds = make_T(R_from_rpy(0, 0, 0.5), [1.0, 0.0, 8.0])
    cov = np.diag([1.0, 1.0, 0.09, 0, 0, 0.07])
    rec.write("/uwdock/ds_prior", "geometry_msgs/msg/PoseWithCovarianceStamped",
              rm.pose_cov_stamped_msg(T_ds, cov, t0, "world_ned"), t0)  # fmt: skip
    img = np.full((363, 480, 3), 80, np.uint8)
    for k in range(16):
        t = t0 + k * 200_000_000
        T = make_T(R_from_rpy(0, 0, 0.2), [0.0, 0.0, 4.0])
        rec.write(
            "/girona500/navigator/odometry",
            "nav_msgs/msg/Odometry",
            rm.odometry_msg(T, np.zeros(3), np.zeros(3), t, "world_ned", "base"),
            t,
        )
        rec.write("/girona500/down_camera/image_raw", "sensor_msgs/msg/Image",
                  rm.image_msg(img, t, "camera"), t)  # fmt: skip
    rec.close()


@pytest.mark.slow
def test_vehicle_extra_replays_without_torch_or_sapien(tmp_path):
    env = tmp_path / "venv"
    venv.create(env, with_pip=True)
    py = env / "bin" / "python"
    subprocess.run(
        [str(py), "-m", "pip", "install", "-q", f"{ROOT}[vehicle]"], check=True, timeout=1800
    )
    probe = "import importlib.util as u; print([m for m in ('torch', 'sapien', 'gymnasium', " \
        "'numba', 'stable_baselines3') if u.find_spec(m)])"  # fmt: skip
    found = subprocess.run([str(py), "-c", probe], capture_output=True, text=True, check=True)
    assert found.stdout.strip() == "[]"
    bag = tmp_path / "mission.mcap"
    _mission(bag)
    res = subprocess.run(
        [str(env / "bin" / "rl"), "replay", str(bag), "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert s["frames"]["used"] == 16 and s["ticks"] >= 16
    assert s["states"]["armed"] + s["states"]["holding"] == s["ticks"]
    assert (tmp_path / "out" / "replay.mcap").is_file()
    # the full install's sim vehicle is refused in one line here
    res = subprocess.run(
        [str(env / "bin" / "sim"), "vehicle", "--episodes", "1"], capture_output=True, text=True
    )
    assert res.returncode != 0 and res.stderr.count("\n") == 1, res.stderr
