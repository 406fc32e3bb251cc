"""markers: dictionaries, 3DBM solids, marker set file, `markers generate` end to end."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import manifold3d as mf
import numpy as np
import pytest
import trimesh

from uwdock.dockcore.config import load_config, validated
from uwdock.dockcore.errors import ConfigError, DockError
from uwdock.markers import cli
from uwdock.markers.config import DS_MARKER_IDS, MarkerConfig
from uwdock.markers.dictionary import (
    check_ids,
    dictionary_size,
    marker_cells,
    normalise_dictionary_name,
)
from uwdock.markers.generate import file_stem, generate
from uwdock.markers.geometry import build_solids, print_estimate, rasterise_top_view
from uwdock.markers.markerset import (
    T_ds_marker_face_up,
    load_marker_set,
    marker_set_from_config,
    save_marker_set,
)
from uwdock.markers.meshcheck import check_printable, check_stl, stl_triangles

PX_PER_MM = 4.0


def decode_top_view(insert: trimesh.Trimesh, dictionary: str, size_mm: float) -> tuple:
    """Rasterise the insert from above (white material on black), invert, run ArUco."""
    half = 0.7 * size_mm
    top = rasterise_top_view([(insert, 255)], PX_PER_MM, half, background=0)
    tag = 255 - top  # the photometric negative: openings become white cells, material black
    det = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)),
        cv2.aruco.DetectorParameters(),
    )
    corners, ids, _ = det.detectMarkers(tag)
    return corners, (ids.ravel().tolist() if ids is not None else []), half


def to_manifold(mesh: trimesh.Trimesh) -> mf.Manifold:
    return mf.Manifold(
        mf.Mesh(
            vert_properties=np.asarray(mesh.vertices, np.float32),
            tri_verts=np.asarray(mesh.faces, np.uint32),
        )
    )


# ------------------------------------------------------------------ dictionaries
def test_dictionary_names_are_normalised():
    assert normalise_dictionary_name("4x4_50") == "DICT_4X4_50"
    assert normalise_dictionary_name("dict_apriltag_36h11") == "DICT_APRILTAG_36h11"
    assert dictionary_size("DICT_4X4_50") == 50
    with pytest.raises(DockError, match="unknown marker dictionary 'DICT_9X9_1'"):
        normalise_dictionary_name("DICT_9X9_1")


def test_check_ids_rejects_out_of_range_and_duplicates():
    assert check_ids("DICT_4X4_50", [0, 49]) == (0, 49)
    with pytest.raises(DockError, match="marker ID 50 is outside dictionary DICT_4X4_50"):
        check_ids("DICT_4X4_50", [13, 50])
    with pytest.raises(DockError, match="ID 13 is listed more than once"):
        check_ids("DICT_4X4_50", [13, 13])
    with pytest.raises(DockError, match="outside"):
        check_ids("DICT_4X4_50", [-1])


def test_marker_cells_match_opencv_bitmap():
    cells = marker_cells("DICT_4X4_50", 13)
    assert cells.shape == (6, 6) and cells.dtype == bool
    assert cells[0].all() and cells[-1].all() and cells[:, 0].all() and cells[:, -1].all()
    big = cv2.aruco.generateImageMarker(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), 13, 60
    )
    np.testing.assert_array_equal(cells, big[5::10, 5::10] == 0)


# ------------------------------------------------------------------ solids
@pytest.mark.parametrize(
    "dictionary,marker_id",
    [
        *[("DICT_4X4_50", i) for i in DS_MARKER_IDS],
        ("DICT_4X4_50", 0),
        ("DICT_5X5_100", 77),
        ("DICT_APRILTAG_36h11", 5),
    ],
)
def test_insert_top_view_decodes_as_its_id(dictionary, marker_id):
    cfg = MarkerConfig(dictionary=dictionary, ids=(marker_id,))
    solids = build_solids(cfg, marker_id)
    corners, ids, half = decode_top_view(solids.insert, dictionary, cfg.size_mm)
    assert ids == [marker_id]
    # corners land on the insert's outline: (+-50 mm) -> pixels, within a pixel
    px = np.array([[-50, 50], [50, 50], [50, -50], [-50, -50]], float)
    expected = np.stack([(px[:, 0] + half) * PX_PER_MM, (half - px[:, 1]) * PX_PER_MM], 1)
    assert np.abs(corners[0][0] - expected).max() <= 1.0


@pytest.mark.parametrize("relief_depth_mm", [5.0, 2.0])
def test_solids_are_watertight_and_fit(relief_depth_mm):
    cfg = MarkerConfig(relief_depth_mm=relief_depth_mm)
    for marker_id in DS_MARKER_IDS:
        s = build_solids(cfg, marker_id)
        for mesh in (s.insert, s.enclosure):
            assert mesh.is_watertight and mesh.is_winding_consistent
            assert mesh.volume > 0
        # insert volume: tag square minus the (slightly widened) white cells, times thickness
        cells = marker_cells(cfg.dictionary, marker_id)
        a = cfg.size_mm / cells.shape[0]
        nominal = (cells.sum() * a * a) * cfg.insert_thickness_mm
        assert s.insert.volume == pytest.approx(nominal, rel=0.02)
        # the parts touch only on the designed seat: zero overlap volume
        overlap = (to_manifold(s.insert) ^ to_manifold(s.enclosure)).volume()
        assert overlap < 1e-3
        # the insert rests on the pocket floor and its top is flush with the column top
        assert s.insert.bounds[0, 2] == pytest.approx(-cfg.insert_thickness_mm)
        assert s.insert.bounds[1, 2] == pytest.approx(0.0)
        assert s.enclosure.bounds[1, 2] == pytest.approx(0.0)
        # inside the insert's footprint the enclosure rises exactly to the relief depth
        column = mf.Manifold.cube((cfg.size_mm, cfg.size_mm, 50.0), center=True)
        under = to_manifold(s.enclosure) ^ column
        expected_top = -min(cfg.relief_depth_mm, cfg.insert_thickness_mm)
        assert under.bounding_box()[5] == pytest.approx(expected_top, abs=1e-4)
        total_height = cfg.enclosure_height_mm + cfg.base_height_mm
        assert s.enclosure.bounds[0, 2] == pytest.approx(-total_height)


def test_geometry_config_is_validated():
    with pytest.raises(ConfigError, match=r"size_mm: must be a finite number in \[5, 1000\]"):
        load_config(MarkerConfig, overrides={"size_mm": 0})
    with pytest.raises(ConfigError, match="relief_depth_mm"):
        load_config(MarkerConfig, overrides={"relief_depth_mm": 9.0})
    with pytest.raises(ConfigError, match="enclosure_side_mm"):
        load_config(MarkerConfig, overrides={"enclosure_side_mm": 100.0})


# ------------------------------------------------------------------ marker set
def test_face_up_pose_points_marker_normal_up():
    T = T_ds_marker_face_up(0.0, -0.30, -0.26, 0.0)
    np.testing.assert_allclose(T[:3, 2], [0, 0, -1])  # marker z = -z_ds (up)
    np.testing.assert_allclose(T[:3, 0], [1, 0, 0])
    T90 = T_ds_marker_face_up(0, 0, 0, 90.0)
    np.testing.assert_allclose(T90[:3, 0], [0, 1, 0], atol=1e-12)


def test_marker_set_default_layout_and_round_trip(tmp_path):
    ms = marker_set_from_config(MarkerConfig())
    assert ms.ids == DS_MARKER_IDS
    corners = ms.corners_ds()
    # marker 14 at (0, -0.30, -0.26) face up: TL corner (-s/2, +s/2) in the marker frame
    np.testing.assert_allclose(corners[14][0], [-0.05, -0.35, -0.26], atol=1e-12)
    np.testing.assert_allclose(corners[13].mean(0), [0.87, -1.05, -1.756], atol=1e-12)
    for suffix in (".toml", ".json"):
        path = save_marker_set(tmp_path / f"set{suffix}", ms)
        back = load_marker_set(path)
        assert back.ids == ms.ids and back.dictionary == "DICT_4X4_50"
        for i in ms.ids:
            np.testing.assert_allclose(back[i].T_ds_marker, ms[i].T_ds_marker)
            np.testing.assert_allclose(back.corners_ds()[i], corners[i])


def test_unlisted_ids_get_distinct_floor_poses():
    ms = marker_set_from_config(MarkerConfig(ids=(41, 42, 43, 13)))
    centres = np.array([ms[i].T_ds_marker[:3, 3] for i in (41, 42, 43)])
    assert len({tuple(np.round(c, 6)) for c in centres}) == 3
    assert np.allclose(centres[:, 2], -0.26)
    np.testing.assert_allclose(ms[13].T_ds_marker[:3, 3], [0.87, -1.05, -1.756])


@pytest.mark.parametrize(
    "mutate,message",
    [
        (lambda d: d["markers"][0].pop("side_m"), "missing key 'side_m'"),
        (lambda d: d["markers"][1].update(id=d["markers"][0]["id"]), "appears twice"),
        (lambda d: d["markers"][0].update(id=50), "outside dictionary"),
        (lambda d: d["markers"][0]["T_ds_marker"][0].__setitem__(0, 2.0), "T_ds_marker"),
        (lambda d: d.update(version=99), "unsupported version 99"),
        (lambda d: d["markers"][0].update(side_m=0.2), "corners_marker_m disagree"),
    ],
)
def test_marker_set_rejects_bad_files(tmp_path, mutate, message):
    data = marker_set_from_config(MarkerConfig()).to_dict()
    mutate(data)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ConfigError, match=message):
        load_marker_set(path)


def test_marker_set_malformed_toml(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("format = [unclosed\n")
    with pytest.raises(ConfigError, match="malformed TOML"):
        load_marker_set(path)


# ------------------------------------------------------------------ generate, end to end
@pytest.fixture(scope="module")
def generated(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("markers")
    generate(MarkerConfig(), out)
    return out


def test_generate_writes_every_file(generated):
    for i in DS_MARKER_IDS:
        stem = file_stem("DICT_4X4_50", i)
        for suffix in ("_insert.stl", "_enclosure.stl", ".glb", "_preview.png"):
            assert (generated / f"{stem}{suffix}").stat().st_size > 0
    for name in ("sheet.pdf", "sheet.svg", "markerset.toml", "config.toml", "provenance.json"):
        assert (generated / name).is_file()
    hidden = {p.name for p in generated.glob(".*")}
    # the folder's claim and the list of files it wrote (a rerun removes the ones it drops)
    assert hidden <= {".uwdock.lock", ".uwdock-owner.json", ".uwdock-files.json"}, hidden
    assert json.loads((generated / ".uwdock-owner.json").read_text())["tool"] == "markers generate"
    prov = json.loads((generated / "provenance.json").read_text())
    assert prov["config"]["marker"]["ids"] == list(DS_MARKER_IDS)
    assert "numpy" in prov["packages"] and "commit" in prov["git"]
    # the written config reproduces the run
    again = load_config(MarkerConfig, generated / "config.toml", section="marker")
    assert again == MarkerConfig()


def test_generated_stl_files_decode_and_are_watertight(generated):
    """The shipped files themselves (reloaded as a slicer would) decode as their IDs."""
    for i in DS_MARKER_IDS:
        stem = generated / file_stem("DICT_4X4_50", i)
        insert = trimesh.load_mesh(f"{stem}_insert.stl")
        enclosure = trimesh.load_mesh(f"{stem}_enclosure.stl")
        assert insert.is_watertight and enclosure.is_watertight
        assert insert.volume > 0 and enclosure.volume > 0
        _, ids, _ = decode_top_view(insert, "DICT_4X4_50", 100.0)
        assert ids == [i]


def test_render_mesh_is_in_metres_with_two_materials(generated):
    scene = trimesh.load(generated / f"{file_stem('DICT_4X4_50', 13)}.glb")
    assert set(scene.geometry) == {"insert", "enclosure"}
    ins = scene.geometry["insert"]
    np.testing.assert_allclose(ins.bounds, [[-0.05, -0.05, -0.005], [0.05, 0.05, 0.0]], atol=1e-6)
    colours = {n: tuple(g.visual.material.baseColorFactor[:3]) for n, g in scene.geometry.items()}
    assert colours["insert"][0] > 200 and colours["enclosure"][0] < 50


def test_generated_marker_set_points_at_render_meshes(generated):
    ms = load_marker_set(generated / "markerset.toml")
    assert ms.ids == DS_MARKER_IDS
    for i in ms.ids:
        assert ms.render_mesh_path(i).is_file()


# ------------------------------------------------------------------ CLI
def test_cli_generate_with_flags(run_cli, tmp_path):
    out = tmp_path / "o"
    res = run_cli(
        cli.main,
        "generate",
        "--ids",
        "3,7",
        "--dictionary",
        "DICT_5X5_100",
        "--size-mm",
        "60",
        "--relief-depth-mm",
        "3",
        "--out",
        out,
        "--quiet",
    )
    assert res.code == 0, res.err
    ms = load_marker_set(out / "markerset.toml")
    assert ms.ids == (3, 7) and ms.dictionary == "DICT_5X5_100"
    assert ms[3].side_m == pytest.approx(0.06)
    insert = trimesh.load_mesh(out / "3dbm_DICT_5X5_100_7_insert.stl")
    np.testing.assert_allclose(insert.extents, [60, 60, 5], atol=1e-6)


def test_cli_help_lists_commands(run_cli):
    res = run_cli(cli.main, "--help")
    assert res.code == 0 and "generate" in res.out and "dictionaries" in res.out


@pytest.mark.parametrize(
    "args,message",
    [
        (["--ids", "13,50"], "marker ID 50 is outside dictionary DICT_4X4_50"),
        (["--size-mm", "0"], "'--size-mm': must be a finite number in [5, 1000], got 0"),
        (["--size-mm", "-3"], "'--size-mm': must be a finite number in [5, 1000], got -3"),
        (["--enclosure-mm", "nan"], "'--enclosure-mm': must be a finite number in (0, 2000]"),
        (["--clearance-mm", "6"], "clearance_mm: 6 mm would close the openings"),
        (["--ids", "13,x"], "--ids must be comma-separated integers"),
        (["--dictionary", "DICT_NOPE"], "unknown marker dictionary"),
    ],
)
def test_cli_bad_input_one_line_error_and_no_files(run_cli, tmp_path, args, message):
    out = tmp_path / "o"
    res = run_cli(cli.main, "generate", *args, "--out", out)
    assert res.code == 2 and res.out == ""
    assert message in res.err and res.err.count("\n") == 1, res.err
    assert res.err.startswith("error: ") and "Traceback" not in res.err
    assert not out.exists()


def test_cli_unwritable_output(run_cli, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    res = run_cli(cli.main, "generate", "--out", blocker / "sub")
    assert res.code != 0 and "cannot write to output folder" in res.err
    assert res.err.count("\n") == 1


@pytest.mark.parametrize(
    "text,message",
    [
        ("size_mm = 80\nbogus_key = 1\n", "unknown config key 'bogus_key'"),
        ("size_mm = 'big'\n", "size_mm: expected a number"),
        ("ids = [13, \n", "malformed TOML"),
    ],
)
def test_cli_bad_config(run_cli, tmp_path, text, message):
    cfg = tmp_path / "m.toml"
    cfg.write_text(text)
    out = tmp_path / "o"
    res = run_cli(cli.main, "generate", "--config", cfg, "--out", out)
    assert res.code != 0 and message in res.err and res.err.count("\n") == 1, res.err
    assert not out.exists()


def test_config_file_values_are_used_and_flags_win(run_cli, tmp_path):
    cfg = tmp_path / "m.toml"
    cfg.write_text("ids = [1, 2]\nsize_mm = 70\n")
    out = tmp_path / "o"
    res = run_cli(cli.main, "generate", "--config", cfg, "--size-mm", "50", "--out", out, "--quiet")
    assert res.code == 0, res.err
    ms = load_marker_set(out / "markerset.toml")
    assert ms.ids == (1, 2) and ms[1].side_m == pytest.approx(0.05)


def test_failure_midway_leaves_only_complete_files(tmp_path, monkeypatch):
    import uwdock.markers.generate as gen

    def boom(*_a, **_k):
        raise DockError("disk full (simulated)")

    monkeypatch.setattr(gen, "save_marker_set", boom)
    with pytest.raises(DockError):
        generate(MarkerConfig(ids=(13,)), tmp_path)
    assert not (tmp_path / "markerset.toml").exists()
    assert not list(tmp_path.glob("*.uwtmp*"))
    # what was written is complete
    assert trimesh.load_mesh(tmp_path / "3dbm_DICT_4X4_50_13_insert.stl").is_watertight


# ------------------------------------------------------------------ printability (open3d)
def _box(offset=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    box = trimesh.creation.box((10.0, 10.0, 10.0))
    box.apply_translation(offset)
    return box


def _stl(*meshes: trimesh.Trimesh) -> bytes:
    return trimesh.util.concatenate(list(meshes)).export(file_type="stl")


def _without_first_face(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    mesh.update_faces(np.arange(len(mesh.faces)) != 0)
    return mesh


def _first_face_flipped(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    mesh.faces[0] = mesh.faces[0][::-1]
    return mesh


def _inverted() -> trimesh.Trimesh:
    box = _box()
    box.invert()
    return box


def test_generated_parts_pass_the_mesh_check(generated):
    """The STL files as written (welded as a slicer welds them) are closed 2-manifold solids."""
    for i in DS_MARKER_IDS:
        for part in ("insert", "enclosure"):
            path = generated / f"{file_stem('DICT_4X4_50', i)}_{part}.stl"
            report = check_stl(path.read_bytes(), path.name)
            assert report.ok, report.problems
            mesh = trimesh.load_mesh(path)
            assert report.triangles == len(mesh.faces) and report.vertices == len(mesh.vertices)
            assert report.volume == pytest.approx(mesh.volume, rel=1e-6)


def test_relief_bosses_and_other_dictionaries_pass_the_mesh_check():
    for cfg, marker_id in (
        (MarkerConfig(relief_depth_mm=2.0), 28),
        (MarkerConfig(dictionary="DICT_APRILTAG_36h11", ids=(7,), size_mm=80.0), 7),
    ):
        s = build_solids(cfg, marker_id)
        reports = check_printable(
            {"insert.stl": _stl(s.insert), "enclosure.stl": _stl(s.enclosure)}
        )
        assert [r.ok for r in reports] == [True, True]


def test_stl_welding_matches_the_box():
    vertices, faces = stl_triangles(_stl(_box()))
    assert vertices.shape == (8, 3) and faces.shape == (12, 3)
    np.testing.assert_allclose(np.abs(vertices), 5.0)
    assert check_stl(_stl(_box())).volume == pytest.approx(1000.0)
    with pytest.raises(DockError, match="not a binary STL"):
        stl_triangles(b"solid ascii\nendsolid\n" * 20, "a.stl")


@pytest.mark.parametrize(
    "make,message",
    [
        (lambda: _stl(_box(), _box((5.0, 5.0, 5.0))), "self-intersecting triangle pairs"),
        (lambda: _stl(_box(), _box((10.0, 10.0, 10.0))), "1 non-manifold vertex"),
        (lambda: _stl(_box(), _box((10.0, 10.0, 0.0))), "1 non-manifold edge"),
        (lambda: _stl(_without_first_face(_box())), "3 open edges"),
        (lambda: _stl(_first_face_flipped(_box())), "3 flipped edges"),
        (lambda: _stl(_inverted()), "inside out (volume -1000)"),
    ],
)
def test_mesh_check_rejects_broken_parts_in_one_line(make, message):
    with pytest.raises(DockError) as err:
        check_printable({"good.stl": _stl(_box()), "bad.stl": make()})
    text = str(err.value)
    assert text.startswith("printable part bad.stl failed the mesh check: ")
    assert message in text and "\n" not in text


def test_generate_refuses_a_self_intersecting_part_and_writes_nothing(
    run_cli, tmp_path, monkeypatch
):
    import uwdock.markers.generate as gen

    real = gen.build_solids

    def overlapping(cfg, marker_id):
        s = real(cfg, marker_id)
        twin = s.enclosure.copy()
        twin.apply_translation((3.0, 0.0, 0.0))  # two enclosures cutting through each other
        return type(s)(marker_id, s.insert, trimesh.util.concatenate([s.enclosure, twin]))

    monkeypatch.setattr(gen, "build_solids", overlapping)
    out = tmp_path / "o"
    res = run_cli(cli.main, "generate", "--ids", "13", "--out", out)
    assert res.code == 2 and res.err.count("\n") == 1, res.err
    assert res.err.startswith(
        "error: printable part 3dbm_DICT_4X4_50_13_enclosure.stl failed the mesh check: "
    )
    assert "self-intersecting triangle pairs" in res.err
    assert not out.exists()  # checked before the folder is claimed


def test_generate_says_whether_the_mesh_check_ran(run_cli, tmp_path, monkeypatch):
    import uwdock.markers.generate as gen

    res = run_cli(cli.main, "generate", "--ids", "13,14", "--out", tmp_path / "a")
    assert res.code == 0, res.err
    assert "mesh check: 4 STL parts watertight, manifold" in res.out
    assert generate(MarkerConfig(ids=(13,)), tmp_path / "c", check_meshes=True).mesh_checked
    monkeypatch.setattr(gen, "open3d_available", lambda: False)
    res = run_cli(cli.main, "generate", "--ids", "13", "--out", tmp_path / "b")
    assert res.code == 0, res.err
    assert "mesh check skipped: open3d is not installed (pip install 'uwdock[check]')" in res.out
    assert (tmp_path / "b" / "3dbm_DICT_4X4_50_13_insert.stl").is_file()
    with pytest.raises(DockError, match=r"the mesh check needs open3d: pip install"):
        generate(MarkerConfig(ids=(13,)), tmp_path / "d", check_meshes=True)
    assert not (tmp_path / "d").exists()


# --------------------------------------------------------------------------- published style


def test_published_style_decodes_from_its_own_parts_and_passes_the_mesh_check():
    cfg = MarkerConfig(style="published")
    for marker_id in DS_MARKER_IDS:
        s = build_solids(cfg, marker_id)
        # from above: the white plate over the shell, whose openings look into the black cavity
        half = 0.7 * cfg.size_mm
        top = rasterise_top_view([(s.enclosure, 0), (s.insert, 255)], PX_PER_MM, half, 128)
        det = cv2.aruco.ArucoDetector(
            cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50),
            cv2.aruco.DetectorParameters(),
        )
        corners, ids, _ = det.detectMarkers(255 - top)
        assert ids is not None and ids.ravel().tolist() == [marker_id]
        px = np.array([[-50, 50], [50, 50], [50, -50], [-50, -50]], float)
        expected = np.stack([(px[:, 0] + half) * PX_PER_MM, (half - px[:, 1]) * PX_PER_MM], 1)
        assert np.abs(corners[0][0] - expected).max() <= 1.0
        # the parts meet only on the ledge and in the slots: no overlap
        assert (to_manifold(s.insert) ^ to_manifold(s.enclosure)).volume() < 1e-3
        assert s.insert.bounds[1, 2] == pytest.approx(0.0)  # flush with the shell's top
        assert s.enclosure.bounds[1, 2] == pytest.approx(0.0)
        reports = check_printable(
            {"insert.stl": _stl(s.insert), "enclosure.stl": _stl(s.enclosure)}
        )
        assert [r.ok for r in reports] == [True, True], [r.problems for r in reports]


def test_published_style_uses_under_30_percent_of_the_solid_enclosure_material():
    solid = print_estimate(build_solids(MarkerConfig(), 13))
    published = print_estimate(build_solids(MarkerConfig(style="published"), 13))
    # the solid column: 126^2 x 98 + 162^2 x 10 mm^3 minus the 5 mm pocket, ~1,768 cm^3
    assert solid["enclosure_cm3"] == pytest.approx(
        (126.0**2 * 98 + 162.0**2 * 10 - 100.2**2 * 5) / 1e3, rel=1e-3
    )
    assert published["enclosure_cm3"] < 0.3 * solid["enclosure_cm3"]
    assert 150 < published["enclosure_cm3"] < 350  # walls, ledge, chamfer, floor, posts
    assert published["print_hours_estimate"] < 0.3 * solid["print_hours_estimate"]


def test_published_cavity_is_closed_and_dark_below_the_openings():
    """Looking straight down an opening, the first surface below the plate is the shell's own
    floor (black), not the ground: a ray through a white cell hits the enclosure at the floor."""
    cfg = MarkerConfig(style="published")
    s = build_solids(cfg, 13)
    cells = marker_cells(cfg.dictionary, 13)
    a = cfg.size_mm / cells.shape[0]
    r, c = np.argwhere(~cells)[0]  # a white cell: an opening in the plate
    x, y = -cfg.size_mm / 2 + (c + 0.5) * a, cfg.size_mm / 2 - (r + 0.5) * a
    probe = mf.Manifold.cube((0.5, 0.5, 200.0), center=True).translate((x, y, 0.0))
    assert (to_manifold(s.insert) ^ probe).volume() == 0.0  # nothing of the plate: an opening
    below = to_manifold(s.enclosure) ^ probe  # the first enclosure surface under it: the floor
    assert below.bounding_box()[5] == pytest.approx(-cfg.enclosure_height_mm + cfg.shell_floor_mm)


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"style": "hollow"}, "style"),
        ({"style": "published", "lip_mm": 20.0}, "lip_mm"),
        ({"style": "published", "shell_wall_mm": 20.0}, "shell_wall_mm"),
        ({"style": "published", "post_hole_mm": 9.0}, "post_hole_mm"),
        ({"style": "published", "enclosure_height_mm": 15.0}, "enclosure_height_mm"),
    ],
)
def test_published_style_config_is_validated(fields, message):
    with pytest.raises(ConfigError, match=message):
        validated(MarkerConfig(**fields))
