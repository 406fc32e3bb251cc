"""``perception detect`` / ``perception eval`` through the CLI, against synthetic ground truth.

Frames are rendered with a known ``T_cam_ds``: the default DS marker set's floor markers (14, 15,
28) are projected through a 640 x 480 pinhole camera (HFOV 55 deg) looking down from 1.2-2.4 m,
and 3DBM bitmaps (the inverted tag on a black enclosure, ``tests.test_detector._marker_patch``)
are warped onto those corners over a textured background, then blurred, tinted green and given
sensor noise. Frames 0-5 share one pose (a static stretch for the jitter), frames 6-11 approach
from 2.0 m to 1.3 m.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.test_detector import _marker_patch
from uwdock.calibration.camera import CameraModel, save_camera
from uwdock.calibration.frames import inv_T, make_T, transform_points
from uwdock.markers.config import MarkerConfig
from uwdock.markers.markerset import marker_set_from_config, save_marker_set
from uwdock.perception.cli import main
from uwdock.perception.groundtruth import (
    label_frame,
    load_ground_truth,
    write_dataset_json,
    write_labels,
    write_pose_csv,
)

CAM = CameraModel.from_hfov(640, 480, 55.0, name="synthetic")
MARKER_SET = marker_set_from_config(MarkerConfig())
CORNERS_DS = MARKER_SET.corners_ds()
FLOOR_CENTRE = np.array([0.0, 0.233, -0.26])
FLOOR_IDS = [14, 15, 28]


# --------------------------------------------------------------------------- synthesis


def look_at(range_m: float, tilt_deg: float, az_deg: float, yaw_deg: float) -> np.ndarray:
    """T_cam_ds of a camera ``range_m`` from the floor markers' centre, tilted ``tilt_deg`` from
    straight down, image x along DS yaw ``yaw_deg``."""
    t, a = np.radians(tilt_deg), np.radians(az_deg)
    eye = FLOOR_CENTRE + range_m * np.array(
        [np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), -np.cos(t)]
    )
    z = (FLOOR_CENTRE - eye) / np.linalg.norm(FLOOR_CENTRE - eye)
    x = np.array([np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg)), 0.0])
    x = (x - z * (x @ z)) / np.linalg.norm(x - z * (x @ z))
    return inv_T(make_T(np.stack([x, np.cross(z, x), z], axis=1), eye))


def render_board(T_cam_ds: np.ndarray, rng: np.random.Generator, cam=CAM) -> np.ndarray:
    """A BGR view of the DS markers fully inside the image (3DBM, green cast, noise)."""
    w, h = cam.width_px, cam.height_px
    img = np.full((h, w), 0.5, np.float32)
    tex = rng.random((h // 16, w // 16)).astype(np.float32)
    img += 0.3 * (cv2.resize(tex, (w, h), interpolation=cv2.INTER_LINEAR) - 0.5)
    for marker_id, corners in CORNERS_DS.items():
        p_cam = transform_points(T_cam_ds, corners)
        dst = cam.project(p_cam)
        if np.any(p_cam[:, 2] <= 0) or not np.all(cam.in_image(dst)):
            continue
        patch, src = _marker_patch(marker_id, negative=True)
        Hm = cv2.getPerspectiveTransform(src.astype(np.float32), dst.astype(np.float32))
        warped = cv2.warpPerspective(patch, Hm, (w, h), flags=cv2.INTER_LINEAR)
        mask = cv2.warpPerspective(np.ones_like(patch), Hm, (w, h), flags=cv2.INTER_LINEAR)
        img = img * (1 - mask) + warped
    g = cv2.GaussianBlur(127.5 + (np.clip(img, 0, 1) - 0.5) * 200.0, (0, 0), 0.7)
    g = np.stack([0.75 * g + 20, g + 30, 0.35 * g], axis=-1) + rng.normal(0, 0.8, (h, w, 3))
    return np.clip(g + 0.5, 0, 255).astype(np.uint8)


def sequence_poses() -> list[np.ndarray]:
    static = look_at(1.4, 8.0, 30.0, 90.0)
    moving = [
        look_at(r, 10.0, az, 90.0 + dy)
        for r, az, dy in zip(
            np.linspace(2.0, 1.3, 6), range(0, 360, 60), (-8, 5, -3, 8, 0, -5), strict=True
        )
    ]
    return [static] * 6 + moving


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Frames, poses, a camera file, a marker set, a labelled dataset and a pose CSV."""
    root = tmp_path_factory.mktemp("scene")
    poses = sequence_poses()
    rng = np.random.default_rng(0)
    frames = [render_board(T, rng) for T in poses]
    images = root / "images"
    images.mkdir()
    for k, img in enumerate(frames):
        cv2.imwrite(str(images / f"{k:06d}.png"), img)
    camera = save_camera(root / "camera.yaml", CAM)[0]
    markers = save_marker_set(root / "markerset.toml", MARKER_SET)
    labels = [
        label_frame(k, T, CAM, CORNERS_DS, image=f"images/{k:06d}.png", water={"preset": "clear"})
        for k, T in enumerate(poses)
    ]
    for ft in labels:  # the synthesis keeps all three floor markers well inside the image
        assert sorted(ft.visible_ids) == FLOOR_IDS
        for m in ft.markers:
            assert not m.visible or np.all(CAM.in_image(m.corners_px, margin_px=15))
    write_labels(root / "labels.jsonl", labels)
    write_dataset_json(root, len(frames), config={"seed": 0})
    gt_csv = root / "mocap.csv"
    write_pose_csv(gt_csv, dict(enumerate(poses)))
    with gt_csv.open() as fh:  # add an extra column: allowed
        rows = list(csv.reader(fh))
    with gt_csv.open("w", newline="") as fh:
        csv.writer(fh).writerows(
            [[*rows[0], "timestamp_s"]] + [[*r, f"{0.2 * i:.1f}"] for i, r in enumerate(rows[1:])]
        )
    return {
        "root": root,
        "images": images,
        "frames": frames,
        "poses": poses,
        "camera": camera,
        "markers": markers,
        "csv": gt_csv,
    }


def _jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _one_line_error(res) -> None:
    assert res.code != 0, res.out
    lines = res.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), res.err


# --------------------------------------------------------------------------- detect


def test_detect_folder_rows_have_the_visible_ids_and_poses(run_cli, scene, tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    for k in (0, 6, 11):
        cv2.imwrite(
            str(folder / f"f{k:02d}.jpg"), scene["frames"][k], [cv2.IMWRITE_JPEG_QUALITY, 95]
        )
    # another resolution in the same folder: 1.25x, same aspect ratio
    big = cv2.resize(scene["frames"][11], (800, 600), interpolation=cv2.INTER_LINEAR)
    cv2.imwrite(str(folder / "f99.png"), big)
    out = tmp_path / "out"
    res = run_cli(main, "detect", folder, "--out", out)
    assert res.code == 0, res.err
    assert "reference camera" in res.err  # no --camera: says so
    rows = _jsonl(out / "detections.jsonl")
    assert [r["name"] for r in rows] == ["f00.jpg", "f06.jpg", "f11.jpg", "f99.png"]
    for r in rows:
        assert r["ids"] == FLOOR_IDS and r["T_cam_ds"] is not None
        assert r["reprojection_rms_px"] < 1.0
    # approximate camera (reference scaled), so only a loose check on the range
    for r, k in zip(rows, (0, 6, 11, 11), strict=True):
        est = np.linalg.norm(np.array(r["T_cam_ds"])[:3, 3])
        assert est == pytest.approx(np.linalg.norm(scene["poses"][k][:3, 3]), rel=0.05)
    with (out / "detections.csv").open() as fh:
        table = list(csv.DictReader(fh))
    assert [t["ids"] for t in table] == ["14 15 28"] * 4 and all(t["pose"] == "1" for t in table)
    for name in ("f00.jpg", "f06.jpg", "f11.jpg", "f99.png"):
        img = cv2.imread(str(out / "annotated" / name))
        assert img is not None and img.shape[:2] == (
            (600, 800) if name == "f99.png" else (480, 640)
        )


def test_detect_single_markers_with_dictionary_and_size(run_cli, scene, tmp_path):
    out = tmp_path / "out"
    img = scene["images"] / "000007.png"
    res = run_cli(
        main,
        "detect",
        img,
        "--camera",
        scene["camera"],
        "--dictionary",
        "DICT_4X4_50",
        "--marker-size-m",
        "0.1",
        "--out",
        out,
        "--no-annotate",
    )
    assert res.code == 0, res.err
    (row,) = _jsonl(out / "detections.jsonl")
    assert row["ids"] == FLOOR_IDS and row["T_cam_ds"] is None
    T_true = scene["poses"][7]
    for m in row["markers"]:  # each marker's own pose against its true pose (~33 px markers:
        # the bearing is precise, the range to a few percent)
        true = (T_true @ MARKER_SET[m["id"]].T_ds_marker)[:3, 3]
        est = np.array(m["T_cam_marker"])[:3, 3]
        cos = est @ true / np.linalg.norm(est) / np.linalg.norm(true)
        assert np.degrees(np.arccos(min(cos, 1.0))) < 0.2
        assert np.linalg.norm(est) == pytest.approx(np.linalg.norm(true), rel=0.05)
    assert not (out / "annotated").exists()


def test_detect_video_writes_an_annotated_video(run_cli, scene, tmp_path):
    video = tmp_path / "dive.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 5.0, (640, 480))
    for img in scene["frames"][6:]:
        writer.write(img)
    writer.release()
    out = tmp_path / "out"
    res = run_cli(main, "detect", video, "--camera", scene["camera"], "--out", out)
    assert res.code == 0, res.err
    rows = _jsonl(out / "detections.jsonl")
    assert [r["name"] for r in rows] == [f"frame_{k:06d}" for k in range(6)]
    assert all(r["ids"] == FLOOR_IDS for r in rows)
    errors = [
        np.linalg.norm(np.array(r["T_cam_ds"])[:3, 3] - T[:3, 3])
        for r, T in zip(rows, scene["poses"][6:], strict=True)
    ]
    assert np.median(errors) < 0.02, errors
    (annotated,) = [p for p in out.iterdir() if p.name.startswith("annotated.")]
    cap = cv2.VideoCapture(str(annotated))
    n = 0
    while cap.read()[0]:
        n += 1
    cap.release()
    assert n == 6
    assert not list(out.glob(".*partial*"))


def test_a_corrupt_video_frame_is_counted_and_skipped(run_cli, scene, tmp_path):
    video = tmp_path / "dive.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 5.0, (640, 480))
    for img in scene["frames"][6:]:
        writer.write(img)
    writer.release()
    data = bytearray(video.read_bytes())
    starts = [i for i in range(len(data) - 1) if data[i : i + 3] == b"\xff\xd8\xff"]
    assert len(starts) == 6
    data[starts[2] : starts[2] + 3000] = bytes(3000)  # wipe frame 2's JPEG header
    video.write_bytes(bytes(data))
    poses = {k: T for k, T in enumerate(scene["poses"][6:])}
    write_pose_csv(tmp_path / "gt.csv", poses)
    out = tmp_path / "out"
    res = run_cli(
        main,
        "eval",
        video,
        "--camera",
        scene["camera"],
        "--ground-truth",
        tmp_path / "gt.csv",
        "--out",
        out,
    )
    assert res.code == 0, res.err
    report = json.loads((out / "report.json").read_text())
    assert report["corrupt_frames"] == 1 and report["frames"] == 5
    rows = _jsonl(out / "frames.jsonl")
    assert [r["corrupt"] for r in rows] == [False, False, True, False, False, False]
    # frames after the corrupt one keep their index: their poses still match the ground truth
    assert report["translation_error_m_median"] < 0.02 and report["detection_rate"] == 1.0


# --------------------------------------------------------------------------- eval


def _check_accuracy(report: dict, n: int) -> None:
    assert report["frames"] == n and report["corrupt_frames"] == 0
    assert report["detection_rate"] == 1.0 and report["pose_rate"] == 1.0
    assert report["per_id_counts"] == {"14": n, "15": n, "28": n}
    assert report["markers_detected_total"] == 3 * n
    assert report["translation_error_m_median"] < 0.02
    assert report["rotation_error_deg_median"] < 1.0
    assert report["translation_error_m_p95"] >= report["translation_error_m_median"]
    assert report["ms_per_frame_median"] > 0
    # ranges 1.6-2.3 m -> 0.5 m bins; every frame in exactly one bin, every bin fully detected
    by_range = report["by_range"]
    assert sum(b["frames"] for b in by_range) == n and len(by_range) >= 2
    assert all(b["hi"] - b["lo"] == pytest.approx(0.5) for b in by_range)
    assert all(b["detection_rate"] == 1.0 for b in by_range if b["frames"])
    assert sum(b["frames"] for b in report["by_view_angle"]) == n
    jitter = report["pose_jitter"]
    assert jitter["stretches"] == 1 and jitter["frames"] == 6
    assert 0 < jitter["translation_std_m_median"] < 0.01


def test_eval_labelled_dataset(run_cli, scene, tmp_path):
    out = tmp_path / "out"
    res = run_cli(main, "eval", scene["root"], "--out", out)  # camera, markers, labels inside
    assert res.code == 0, res.err
    report = json.loads((out / "report.json").read_text())
    _check_accuracy(report, 12)
    assert report["marker_recall"] == 1.0 and report["false_detections"] == 0
    assert report["corner_error_px_median"] < 0.5
    assert report["by_water"]["clear"]["frames"] == 12
    assert report["config"]["detector"]["pipeline"] == "default"
    assert report["provenance"]["git"] is not None
    assert len(_jsonl(out / "frames.jsonl")) == 12
    for name in ("timeline.png", "rate_vs_range.png", "error_vs_range.png", "contact_sheet.png"):
        assert name in report["plots"]
        img = cv2.imread(str(out / name))
        assert img is not None and img.shape[0] > 100, name
    assert (out / "config.toml").is_file() and (out / "provenance.json").is_file()
    assert "translation median" in res.out


def test_eval_pose_csv_with_extra_columns(run_cli, scene, tmp_path):
    out = tmp_path / "out"
    res = run_cli(
        main,
        "eval",
        scene["images"],
        "--camera",
        scene["camera"],
        "--markers",
        scene["markers"],
        "--ground-truth",
        scene["csv"],
        "--out",
        out,
        "--quiet",
    )
    assert res.code == 0, res.err
    assert res.out.strip() == str(out / "report.json")
    report = json.loads((out / "report.json").read_text())
    _check_accuracy(report, 12)
    assert report["marker_recall"] is None  # a pose CSV has no marker labels
    truth = load_ground_truth(scene["csv"])
    np.testing.assert_allclose(truth[7].T_cam_ds, scene["poses"][7], atol=1e-6)


def test_eval_config_file_sets_bins_and_contact_sheet(run_cli, scene, tmp_path):
    cfg = tmp_path / "perception.toml"
    cfg.write_text("[report]\nrange_bin_m = 1.0\nangle_bin_deg = 5.0\ncontact_sheet_frames = 0\n")
    out = tmp_path / "out"
    res = run_cli(main, "eval", scene["root"], "--config", cfg, "--out", out, "--quiet")
    assert res.code == 0, res.err
    report = json.loads((out / "report.json").read_text())
    assert all(b["hi"] - b["lo"] == pytest.approx(1.0) for b in report["by_range"])
    assert all(b["hi"] - b["lo"] == pytest.approx(5.0) for b in report["by_view_angle"])
    assert "contact_sheet.png" not in report["plots"] and not (out / "contact_sheet.png").exists()
    bad = tmp_path / "bad.toml"
    bad.write_text("[report]\nrange_bin_mm = 1.0\n")
    res = run_cli(main, "eval", scene["root"], "--config", bad, "--out", out)
    _one_line_error(res)
    assert "range_bin_mm" in res.err


def test_eval_compare_gives_a_row_per_pipeline(run_cli, scene, tmp_path):
    out = tmp_path / "out"
    res = run_cli(
        main, "eval", scene["root"], "--compare", "default,reference_3dbm,plain", "--out", out
    )
    assert res.code == 0, res.err
    cmp = json.loads((out / "compare.json").read_text())
    assert [r["pipeline"] for r in cmp["rows"]] == ["default", "reference_3dbm", "plain"]
    rows = {r["pipeline"]: r for r in cmp["rows"]}
    assert rows["default"]["detection_rate"] == 1.0
    assert rows["reference_3dbm"]["detection_rate"] == 1.0  # designed for the 3DBM negative
    assert rows["plain"]["detection_rate"] == 0.0  # flat-tag polarity: decodes nothing here
    assert rows["plain"]["translation_error_m_median"] is None
    assert rows["default"]["translation_error_m_median"] < 0.02
    md = (out / "compare.md").read_text().splitlines()
    assert len(md) == 2 + 3 and md[2].startswith("| default |")
    for name in ("default", "reference_3dbm", "plain"):
        assert name in res.out
    assert json.loads((out / "report.json").read_text())["pipeline"] == "default"


def test_eval_counts_an_unreadable_image_among_good_ones(run_cli, scene, tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    for k in range(4):
        (folder / f"{k:06d}.png").write_bytes((scene["images"] / f"{k + 6:06d}.png").read_bytes())
    (folder / "000002.png").write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
    poses = {k: scene["poses"][k + 6] for k in range(4)}
    write_pose_csv(tmp_path / "gt.csv", poses)
    out = tmp_path / "out"
    res = run_cli(
        main,
        "eval",
        folder,
        "--camera",
        scene["camera"],
        "--ground-truth",
        tmp_path / "gt.csv",
        "--out",
        out,
    )
    assert res.code == 0, res.err
    report = json.loads((out / "report.json").read_text())
    assert report["corrupt_frames"] == 1 and report["frames"] == 3
    assert report["detection_rate"] == 1.0 and report["translation_error_m_median"] < 0.02
    assert report["pose_jitter"]["stretches"] == 0
    assert _jsonl(out / "frames.jsonl")[2] == {"frame": 2, "name": "000002.png", "corrupt": True}


def test_eval_without_ground_truth_reports_nulls(run_cli, scene, tmp_path):
    out = tmp_path / "out"
    res = run_cli(
        main,
        "eval",
        scene["images"] / "000008.png",
        "--camera",
        scene["camera"],
        "--out",
        out,
        "--json",
    )
    assert res.code == 0, res.err
    report = json.loads(res.out)
    assert report["frames"] == 1 and report["detection_rate"] == 1.0
    assert report["ground_truth"] is None and report["pose_jitter"] is None
    assert report["translation_error_m_median"] is None and report["by_range"] is None
    assert report["plots"] == ["timeline.png", "contact_sheet.png"]


def test_default_pipeline_decodes_small_high_contrast_markers_on_a_bland_background():
    from uwdock.perception.detector import Detector, DetectorConfig

    det = Detector(DetectorConfig(ids=tuple(CORNERS_DS)))
    found = []
    for seed, range_m in enumerate((2.4, 2.8)):
        img = render_board(look_at(range_m, 10.0, 60.0 * seed, 90.0), np.random.default_rng(seed))
        found.append({d.marker_id for d in det.detect(img)})
    assert found == [set(FLOOR_IDS)] * 2


# --------------------------------------------------------------------------- bad inputs


def _bad_inputs(tmp_path: Path, scene: dict) -> dict[str, list]:
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("no images here")
    bad_video = tmp_path / "broken.mp4"
    bad_video.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 8)
    bad_csv = tmp_path / "bad.csv"
    bad_csv.write_text("frame,x_m,y_m,z_m,qw,qx,qy,qz\n0,0,0,2,1,0,0,0\n1,0,0,two,1,0,0,0\n")
    short_csv = tmp_path / "short.csv"
    short_csv.write_text("frame,x_m,y_m,z_m,qw,qx,qy\n0,0,0,2,1,0,0\n")
    bad_jsonl = tmp_path / "labels.jsonl"
    good = (scene["root"] / "labels.jsonl").read_text().splitlines()[0]
    bad_jsonl.write_text(good + '\n{"frame": 1, "T_cam_ds": [[1, 0]]}\n')
    cam, images = scene["camera"], scene["images"]
    ev = ["eval", images, "--camera", cam, "--out", tmp_path / "o"]
    return {
        "empty folder": (["detect", empty, "--out", tmp_path / "o"], "no images"),
        "corrupt video": (["detect", bad_video, "--out", tmp_path / "o"], "cannot read video"),
        "missing input": (["detect", tmp_path / "nope", "--out", tmp_path / "o"], "not found"),
        "wrong dictionary": ([*ev, "--dictionary", "DICT_9X9_1"], "DICT_9X9_1"),
        "unknown pipeline": ([*ev, "--compare", "default,magic"], "magic"),
        "missing camera": (
            ["eval", images, "--camera", tmp_path / "c.yaml", "--out", tmp_path / "o"],
            "camera file not found",
        ),
        "no camera": (["eval", images, "--out", tmp_path / "o"], "--camera is required"),
        "malformed csv": ([*ev, "--ground-truth", bad_csv], "bad.csv line 3: column 'z_m'"),
        "csv missing column": ([*ev, "--ground-truth", short_csv], "lacks column(s) qz"),
        "malformed jsonl": ([*ev, "--ground-truth", bad_jsonl], "labels.jsonl line 2: T_cam_ds"),
        "markers and dictionary": (
            [*ev, "--markers", scene["markers"], "--dictionary", "4x4_50"],
            "cannot be combined",
        ),
    }


@pytest.mark.parametrize(
    "case",
    [
        "empty folder",
        "corrupt video",
        "missing input",
        "wrong dictionary",
        "unknown pipeline",
        "missing camera",
        "no camera",
        "malformed csv",
        "csv missing column",
        "malformed jsonl",
        "markers and dictionary",
    ],
)
def test_bad_inputs_fail_with_one_line(run_cli, scene, tmp_path, case):
    args, match = _bad_inputs(tmp_path, scene)[case]
    res = run_cli(main, *args)
    _one_line_error(res)
    assert match in res.err, res.err
    assert res.code == 2 and not (tmp_path / "o").exists()  # nothing written, not even the folder


def test_ground_truth_that_matches_no_frame_is_an_error(run_cli, scene, tmp_path):
    write_pose_csv(tmp_path / "gt.csv", {500: scene["poses"][0]})
    res = run_cli(
        main,
        "eval",
        scene["images"],
        "--camera",
        scene["camera"],
        "--ground-truth",
        tmp_path / "gt.csv",
        "--out",
        tmp_path / "o",
    )
    _one_line_error(res)
    assert "matches none" in res.err


def test_labels_round_trip_and_derived_quantities(tmp_path):
    T = make_T(np.eye(3), [1.0, 0.0, 1.0])  # DS origin 45 deg off the optical axis
    ft = label_frame(3, T, CAM, CORNERS_DS, image="images/000003.png", water={"preset": "turbid"})
    assert ft.range_m == pytest.approx(np.sqrt(2)) and ft.view_angle_deg == pytest.approx(45.0)
    behind = label_frame(4, make_T(np.eye(3), [0.0, 0.0, -2.0]), CAM, CORNERS_DS)
    assert behind.view_angle_deg == pytest.approx(180.0) and not behind.visible_ids
    write_labels(tmp_path / "labels.jsonl", [ft, behind])
    loaded = load_ground_truth(tmp_path / "labels.jsonl")
    assert sorted(loaded) == [3, 4]
    np.testing.assert_allclose(loaded[3].T_cam_ds, T)
    assert loaded[3].water == {"preset": "turbid"} and loaded[3].image == "images/000003.png"
    for a, b in zip(loaded[3].markers, ft.markers, strict=True):
        assert (a.marker_id, a.in_image, a.visible) == (b.marker_id, b.in_image, b.visible)
        np.testing.assert_allclose(a.corners_px, b.corners_px)  # nan (behind) survives as nan
    assert np.isnan(loaded[4].markers[0].corners_px).all()


def test_eval_level_ds_flag_overrides_the_config(run_cli, scene, tmp_path):
    """--level-ds/--no-level-ds set the estimator's level-DS re-solve; the flag beats [pose]."""
    cfg = tmp_path / "p.toml"
    cfg.write_text("[pose]\nlevel_ds = false\n")
    cases = {
        (): True,  # the default: as the env's camera source
        ("--no-level-ds",): False,
        ("--config", cfg): False,
        ("--config", cfg, "--level-ds"): True,
    }
    for k, (args, want) in enumerate(cases.items()):
        out = tmp_path / f"o{k}"
        res = run_cli(main, "eval", scene["root"], *args, "--out", out, "--quiet")
        assert res.code == 0, res.err
        report = json.loads((out / "report.json").read_text())
        assert report["config"]["pose"]["level_ds"] is want, args


def test_eval_of_a_video_searching_from_the_last_pose_gives_the_same_poses(
    run_cli, scene, tmp_path, monkeypatch
):
    from uwdock.perception.detector import Detector

    searches = []
    detect = Detector.detect

    def spy(self, img_bgr, predicted=None):
        out = detect(self, img_bgr, predicted)
        searches.append(self.last_search)
        return out

    monkeypatch.setattr(Detector, "detect", spy)
    video = tmp_path / "dive.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 5.0, (640, 480))
    for img in scene["frames"][:6]:  # the hovering part: the last pose predicts the next
        writer.write(img)
    writer.release()
    (tmp_path / "prior.toml").write_text("[pose]\nsearch_from_prior = true\n")
    rows = {}
    for name, extra in (("whole", ()), ("prior", ("--config", tmp_path / "prior.toml"))):
        out = tmp_path / name
        res = run_cli(main, "eval", video, "--camera", scene["camera"], *extra, "--out", out)
        assert res.code == 0, res.err
        rows[name] = _jsonl(out / "frames.jsonl")
    # whole run: 6 whole frames; prior run: the first frame whole, the next 5 in regions (the
    # moving part of the scene jumps 60 deg of azimuth per frame, too far for a prior)
    assert searches == ["frame"] * 7 + ["regions"] * 5
    for a, b in zip(rows["whole"], rows["prior"], strict=True):
        assert a["ids"] == b["ids"] == FLOOR_IDS
        dt = np.array(a["T_cam_ds"])[:3, 3] - np.array(b["T_cam_ds"])[:3, 3]
        assert np.abs(dt).max() < 0.01
