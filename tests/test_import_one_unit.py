"""``calibration import`` of a stereo pair writes the camera file and the stereo file as one unit
(issue 54: writes as one unit).

Before, the stereo file (both twins) was written and renamed, then the camera file (both twins)
as a second unit: a full disk, a failed rename or an interrupt between them left a new stereo
file beside the old camera file. Now the four files go through one
``dockcore.io.atomic_write_files``: a failure at any of them leaves every previous file byte for
byte as it was, and no temporary file.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np
import pytest

from tests.test_camera_formats import KALIBR, KALIBR_T_CN_CNM1
from uwdock.calibration import cli as calibration_cli
from uwdock.calibration.camera import camera_file_bytes, load_camera, save_camera
from uwdock.calibration.formats import read_camera_yaml, read_yaml_mapping
from uwdock.calibration.stereo_formats import ros_stereo_camera_info_yaml, stereo_from_kalibr
from uwdock.calibration.stereo_rig import load_stereo, stereo_file_bytes
from uwdock.dockcore import io as dio
from uwdock.dockcore.io import TEMP_MARK

#: The files one import of a pair writes, in the order of their renames.
TARGETS = ("cam.yaml", "cam.json", "cam_stereo.yaml", "cam_stereo.json")
#: The camchain imported over the first one: other intrinsics, another baseline.
KALIBR_2 = KALIBR.replace("1116.5402", "1120.25").replace("-0.110073808127", "-0.150073808127")


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def _import(run_cli, folder: Path, text: str):
    src = folder / "chain.yaml"
    src.write_text(text)
    return run_cli(calibration_cli.main, "import", src, "--out", folder / "cam.yaml")


def _expected(folder: Path, text: str) -> dict[str, bytes]:
    """The bytes an import of the camchain ``text`` writes (camera file without T_body_cam)."""
    src = folder / "check.yaml"
    src.write_text(text)
    cam = read_camera_yaml(src).camera
    rig = stereo_from_kalibr(read_yaml_mapping(src), "cam0", str(src))[0]
    src.unlink()
    return {
        **{p.name: b for p, b in camera_file_bytes(folder / "cam.yaml", cam).items()},
        **{p.name: b for p, b in stereo_file_bytes(folder / "cam_stereo.yaml", rig).items()},
    }


def test_a_pair_is_written_whole(run_cli, tmp_path):
    res = _import(run_cli, tmp_path, KALIBR)
    assert res.code == 0, res.err
    assert f"wrote {tmp_path / 'cam.yaml'} and {tmp_path / 'cam.json'}" in res.out
    assert "stereo pair cam0 -> cam1" in res.out and "cam_stereo.json" in res.out
    written = _files(tmp_path)
    assert set(written) == {"chain.yaml", *TARGETS}
    cam, T = load_camera(tmp_path / "cam.yaml")
    assert T is None and cam == read_camera_yaml(tmp_path / "chain.yaml").camera
    assert load_camera(tmp_path / "cam.json")[0] == cam
    rig = load_stereo(tmp_path / "cam_stereo.yaml")
    assert np.array_equal(rig.T_right_left, KALIBR_T_CN_CNM1)
    assert load_stereo(tmp_path / "cam_stereo.json").T_right_left.tolist() == (
        rig.T_right_left.tolist()
    )
    expected = _expected(tmp_path, KALIBR)
    assert {k: written[k] for k in TARGETS} == expected
    # again over the first: the new content everywhere, T_body_cam of the old camera kept
    T_body_cam = np.eye(4)
    T_body_cam[:3, 3] = (0.4, 0.0, 0.2)
    save_camera(tmp_path / "cam.yaml", cam, T_body_cam)
    res = _import(run_cli, tmp_path, KALIBR_2)
    assert res.code == 0, res.err
    assert "kept T_body_cam" in res.out
    cam2, T2 = load_camera(tmp_path / "cam.yaml")
    assert cam2.fx_px == 1120.25 and np.array_equal(T2, T_body_cam)
    assert load_stereo(tmp_path / "cam_stereo.yaml").baseline_m > 0.15
    assert not [p for p in tmp_path.iterdir() if TEMP_MARK in p.name]


def test_a_ros_pair_with_right_is_one_unit_too(run_cli, tmp_path):
    assert _import(run_cli, tmp_path, KALIBR).code == 0
    rig = load_stereo(tmp_path / "cam_stereo.yaml")
    left_text, right_text = ros_stereo_camera_info_yaml(rig)
    (tmp_path / "left.yaml").write_text(left_text)
    (tmp_path / "right.yaml").write_text(right_text)
    out = tmp_path / "ros" / "cam.yaml"
    res = run_cli(calibration_cli.main, "import", tmp_path / "left.yaml", "--right",
                  tmp_path / "right.yaml", "--out", out)  # fmt: skip
    assert res.code == 0, res.err
    assert sorted(p.name for p in out.parent.iterdir()) == sorted(TARGETS)
    back = load_stereo(out.parent / "cam_stereo.yaml")
    np.testing.assert_allclose(back.T_right_left, rig.T_right_left, atol=1e-9)


def test_out_over_the_right_input_is_refused(run_cli, tmp_path):
    """``--out`` naming the ``--right`` file being imported (or its twin): one line, the
    input as it was."""
    assert _import(run_cli, tmp_path, KALIBR).code == 0
    rig = load_stereo(tmp_path / "cam_stereo.yaml")
    left_text, right_text = ros_stereo_camera_info_yaml(rig)
    (tmp_path / "left.yaml").write_text(left_text)
    (tmp_path / "right.yaml").write_text(right_text)
    res = run_cli(calibration_cli.main, "import", tmp_path / "left.yaml", "--right",
                  tmp_path / "right.yaml", "--out", tmp_path / "right.yaml")  # fmt: skip
    assert res.code == 2 and res.err.count("\n") == 1 and "would overwrite" in res.err, res.err
    assert (tmp_path / "right.yaml").read_text() == right_text


def _failing_rename(fail_on: str, seen: list[str]):
    real = dio.replace_checked

    def replace_checked(tmp, target):
        seen.append(Path(target).name)
        if Path(target).name == fail_on:
            raise OSError(errno.EIO, os.strerror(errno.EIO), str(target))
        real(tmp, target)

    return replace_checked


def _full_disk(fail_on: str, seen: list[str]):
    real = dio._sync

    def _sync(path):
        name = Path(path).name  # ".cam_stereo.json.<pid>.<random>.uwtmp"
        seen.append(name)
        if name.startswith(f".{fail_on}.") and TEMP_MARK in name:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return real(path)

    return _sync


@pytest.mark.parametrize("fail_on", TARGETS)
@pytest.mark.parametrize("how", ["rename", "full-disk"])
def test_a_failure_at_any_file_leaves_the_previous_set(
    run_cli, tmp_path, monkeypatch, fail_on, how
):
    """The old camera file and the old stereo file stay as they were, byte for byte, when the
    write (ENOSPC) or the rename (EIO) of any one of the four new files fails; in particular
    the second unit of before (the camera file after the stereo file, or the other way)."""
    assert _import(run_cli, tmp_path, KALIBR).code == 0
    before = _files(tmp_path)
    (tmp_path / "chain.yaml").write_text(KALIBR_2)
    before["chain.yaml"] = KALIBR_2.encode()
    seen: list[str] = []
    if how == "rename":
        monkeypatch.setattr(dio, "replace_checked", _failing_rename(fail_on, seen))
    else:
        monkeypatch.setattr(dio, "_sync", _full_disk(fail_on, seen))
    res = run_cli(calibration_cli.main, "import", tmp_path / "chain.yaml", "--out",
                  tmp_path / "cam.yaml")  # fmt: skip
    assert res.code == 2, (res.code, res.out, res.err)
    lines = res.err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and fail_on in lines[0], res.err
    if how == "rename":  # the renames before the failing one did happen, and were undone
        assert seen == list(TARGETS[: TARGETS.index(fail_on) + 1])
    assert _files(tmp_path) == before  # every old file as it was, no temporary file left
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(before)


def test_a_failure_with_no_previous_files_leaves_none(run_cli, tmp_path, monkeypatch):
    (tmp_path / "chain.yaml").write_text(KALIBR)
    monkeypatch.setattr(dio, "replace_checked", _failing_rename("cam_stereo.json", []))
    res = _import(run_cli, tmp_path, KALIBR)
    assert res.code == 2 and "cam_stereo.json" in res.err, res.err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["chain.yaml"]


def test_a_target_that_is_a_folder_refuses_the_whole_unit(run_cli, tmp_path):
    assert _import(run_cli, tmp_path, KALIBR).code == 0
    (tmp_path / "cam_stereo.json").unlink()
    (tmp_path / "cam_stereo.json").mkdir()
    before = _files(tmp_path)
    (tmp_path / "chain.yaml").write_text(KALIBR_2)
    before["chain.yaml"] = KALIBR_2.encode()
    res = run_cli(calibration_cli.main, "import", tmp_path / "chain.yaml", "--out",
                  tmp_path / "cam.yaml")  # fmt: skip
    assert res.code == 2 and res.err.count("\n") == 1, res.err
    assert "cam_stereo.json" in res.err and "folder" in res.err, res.err
    assert _files(tmp_path) == before  # the camera file not written either
    assert (tmp_path / "cam_stereo.json").is_dir()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([*before, "cam_stereo.json"])


def test_stereo_out_naming_the_camera_file_is_refused(run_cli, tmp_path):
    (tmp_path / "chain.yaml").write_text(KALIBR)
    res = run_cli(calibration_cli.main, "import", tmp_path / "chain.yaml", "--out",
                  tmp_path / "cam.yaml", "--stereo-out", tmp_path / "cam.json")  # fmt: skip
    assert res.code == 2 and res.err.count("\n") == 1, res.err
    assert "--stereo-out" in res.err and "are the same files" in res.err, res.err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["chain.yaml"]
