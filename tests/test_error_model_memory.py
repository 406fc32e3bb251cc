"""The error model's memory: sequence labels of a dataset, the AR(1) fit, the sampler with
memory, bit-identity of the memoryless cases, malformed files, and the trajectory recorder."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tests.error_models import N_BINS, STEP_S, above_ds, synthetic_model
from uwdock.calibration.frames import R_from_rpy, inv_T, make_T
from uwdock.datasets.loaders import load_pose_track_csv, write_pose_track_csv
from uwdock.datasets.sequences import check_sequences, sequences_from_manifest
from uwdock.dockcore.errors import DockError
from uwdock.rl.env.error_model import (
    N_VISIBLE_BINS,
    VERSION,
    ErrorModel,
    ErrorModelConfig,
    ErrorModelSource,
    FrameSample,
    apply_error,
    ar1_fit,
    count_in_view,
    fit_error_model,
    fit_tables,
    load_error_model,
    pose_error,
    standardise,
)
from uwdock.rl.env.obs_sources import StepContext
from uwdock.rl.env.task import DockingTaskConfig


def _cov(sd: np.ndarray, corr: float = 0.3) -> np.ndarray:
    """A full (6, 6) covariance with standard deviations ``sd`` and a dt_x-drot_y coupling."""
    c = np.diag(sd**2)
    c[0, 4] = c[4, 0] = corr * sd[0] * sd[4]
    return c


BIAS = np.array([0.01, -0.02, 0.03, 0.002, 0.0, 0.01])
SD = np.array([0.01, 0.02, 0.03, 0.01, 0.01, 0.02])


# ----------------------------------------------------------------------------- fit


def _simulated_samples(rho: float, seed: int) -> tuple[list[FrameSample], object, int]:
    """60 sequences of 80 steps: standardised AR(1) errors through per-bin bias and Cholesky
    factors (range falling along each sequence), 10 % misses and 3 % gross errors, which
    break the chain. Returns the samples, their sequences and the expected pair count."""
    rng = np.random.default_rng(seed)
    n_seq, n_step = 60, 80
    samples, seq, step, time_s = [], [], [], []
    inlier = []
    frame = 0
    for s in range(n_seq):
        z = rng.standard_normal(6)
        for k in range(n_step):
            if k:
                z = rho * z + math.sqrt(1 - rho * rho) * rng.standard_normal(6)
            r_bin = int(np.interp(k, [0, n_step - 1], [9, 2]))  # 4.5 m -> 1 m
            L = np.linalg.cholesky(_cov(SD * (1 + 0.2 * r_bin)))
            err = BIAS * (1 + 0.1 * r_bin) + L @ z
            u = rng.random()
            if u < 0.10:
                err = None
            elif u < 0.13:
                err = np.array([0.0, 0.0, 0.0, 0.6, 0.0, 0.0])  # 34 deg: a gross error
            samples.append(FrameSample(frame, "clear_tank", r_bin, 3, err))
            # (a rare large inlier draw counts as a gross error, as in the fit)
            inlier.append(err is not None and np.linalg.norm(err[3:]) <= math.radians(10))
            seq.append(s)
            step.append(k)
            time_s.append(k * STEP_S)
            frame += 1
    sequences = check_sequences(seq, step, time_s, frame, "test")
    i, j = sequences.consecutive_pairs()
    inl = np.asarray(inlier)
    return samples, sequences, int((inl[i] & inl[j]).sum())


@pytest.mark.parametrize("rho", [0.8, 0.0])
def test_fit_recovers_a_known_ar1_correlation(rho):
    samples, sequences, n_pairs = _simulated_samples(rho, seed=11)
    tables = fit_tables(samples, N_BINS, ErrorModelConfig(), sequences)
    for water in ("clear_tank", "all"):
        ar1 = tables[water]["ar1"]
        assert ar1["pairs"] == n_pairs > 3000
        np.testing.assert_allclose(ar1["rho"], rho, atol=0.05)
        lo, hi = np.asarray(ar1["rho_ci95"]).T
        assert np.all(hi - lo < 0.1)
        assert np.all((lo <= rho + 0.02) & (rho - 0.02 <= hi))
        np.testing.assert_allclose(ar1["rho_per_axis"], rho, atol=0.06)
        acf = ar1["autocorrelation"]  # an AR(1) decays as rho^lag
        assert acf["lag"] == [1, 2, 3, 4, 5] and acf["rho"][0] == ar1["rho"]
        np.testing.assert_allclose(acf["rho"][1], rho**2, atol=0.06)
        assert acf["pairs"][1] < acf["pairs"][0]
    # the detection diagnostic: misses are independent here, so the model predicts them
    after = tables["all"]["detection_pairs"]["after_detection"]
    assert after["detected"] == pytest.approx(0.9, abs=0.02)


def test_ar1_fit_needs_enough_pairs_and_is_memoryless_without():
    samples, sequences, _ = _simulated_samples(0.8, seed=2)
    few = fit_tables(samples, N_BINS, ErrorModelConfig(min_pairs=100_000), sequences)
    assert few["all"]["ar1"]["rho"] is None and few["all"]["ar1"]["pairs"] > 3000
    plain = fit_tables(samples, N_BINS, ErrorModelConfig())
    assert "ar1" not in plain["all"]  # no sequences: the version-1 tables
    with pytest.raises(ValueError, match="ar1_fit"):
        ar1_fit(np.zeros((1, 6)), np.zeros((1, 6)))


def test_standardise_whitens_with_the_samplers_cholesky_factor():
    rng = np.random.default_rng(0)
    cov = _cov(SD)
    err = BIAS + rng.multivariate_normal(np.zeros(6), cov, size=20_000)
    z = standardise(err, BIAS, cov)
    np.testing.assert_allclose(np.cov(z.T), np.eye(6), atol=0.03)


# ----------------------------------------------------------------------------- sampling


def _run(src: ErrorModelSource, n: int, dt_s: float = STEP_S, height_m: float = 3.0):
    """Errors (n, 6) (NaN rows for misses) over ``n`` steps ``dt_s`` apart, and the
    measurements' DS poses."""
    T_world_ds, T_world_body = above_ds(height_m)
    T_world_cam = T_world_body @ src.model.T_body_cam
    T_cam_ds = inv_T(T_world_cam) @ T_world_ds
    errs, poses = np.full((n, 6), np.nan), []
    for k in range(n):
        m = src.measure(StepContext(T_world_body, T_world_ds, k * dt_s))
        poses.append(None if m is None else m.T_world_ds)
        if m is not None:
            errs[k] = pose_error(inv_T(T_world_cam) @ m.T_world_ds, T_cam_ds)
    return errs, poses


def _lag1(z: np.ndarray) -> np.ndarray:
    ok = ~np.isnan(z[:-1, 0]) & ~np.isnan(z[1:, 0])
    return ar1_fit(z[:-1][ok], z[1:][ok])["rho"]


def test_sampling_reproduces_the_fitted_rho_and_the_marginal():
    rho = [0.8, 0.6, 0.9, 0.5, 0.7, 0.0]
    cov = _cov(SD)
    model = ErrorModel(synthetic_model(1.0, BIAS, cov, rho))
    src = ErrorModelSource(model, DockingTaskConfig())
    src.reset(np.random.default_rng(3))
    errs, _ = _run(src, 12_000)
    z = standardise(errs, BIAS, cov)
    np.testing.assert_allclose(_lag1(z), rho, atol=0.03)
    np.testing.assert_allclose(errs.mean(axis=0), BIAS, atol=0.15 * SD.max())
    np.testing.assert_allclose(errs.std(axis=0), SD, rtol=0.1)  # marginal unchanged
    # measured every two fitted steps, the correlation is rho^2
    src.reset(np.random.default_rng(4))
    z2 = standardise(_run(src, 6_000, dt_s=2 * STEP_S)[0], BIAS, cov)
    np.testing.assert_allclose(_lag1(z2), np.square(rho), atol=0.04)
    # memory off: the same model samples independent steps
    off = ErrorModelSource(model, DockingTaskConfig(), temporal=False)
    off.reset(np.random.default_rng(3))
    z0 = standardise(_run(off, 6_000)[0], BIAS, cov)
    np.testing.assert_allclose(_lag1(z0), 0.0, atol=0.04)


def test_misses_and_gross_errors_restart_the_chain():
    model = ErrorModel(synthetic_model(0.6, BIAS, _cov(SD), [0.95] * 6, p_outlier=0.2))
    src = ErrorModelSource(model, DockingTaskConfig())
    src.reset(np.random.default_rng(5))
    errs, _ = _run(src, 15_000)
    gross = np.abs(errs[:, 3] - 0.5) < 1e-9
    inl = ~np.isnan(errs[:, 0]) & ~gross
    z = standardise(errs, BIAS, _cov(SD))
    first = np.flatnonzero(inl[1:] & ~inl[:-1]) + 1  # first inliers after a miss or gross error
    idx = np.flatnonzero(inl)
    last = idx[np.searchsorted(idx, first) - 1]  # the inlier before each break
    first, last = first[last < first], last[last < first]
    # a fresh draw: unit variance and no memory of the inlier before the break
    np.testing.assert_allclose(z[first].std(axis=0), 1.0, rtol=0.08)
    np.testing.assert_allclose(ar1_fit(z[last], z[first])["rho"], 0.0, atol=0.06)
    np.testing.assert_allclose(z[inl].std(axis=0), 1.0, rtol=0.05)
    both = inl[1:] & inl[:-1]
    np.testing.assert_allclose(ar1_fit(z[:-1][both], z[1:][both])["rho"], 0.95, atol=0.02)
    src.reset(np.random.default_rng(6))
    assert src._z_prev is None


def _memoryless_reference(model: ErrorModel, rng: np.random.Generator, n: int) -> list:
    """The sampler before memory, written out: its draws in its order."""
    T_world_ds, T_world_body = above_ds(3.0)
    T_world_cam = T_world_body @ model.T_body_cam
    T_cam_ds = inv_T(T_world_cam) @ T_world_ds
    r = float(np.linalg.norm(T_cam_ds[:3, 3]))
    t, k = model.table("all"), model.range_bin(r)
    n_vis = min(count_in_view(model.camera, T_cam_ds, model.corners_ds), N_VISIBLE_BINS - 1)
    out = []
    for _ in range(n):
        if rng.random() >= t["p"][k, n_vis]:
            out.append(None)
            continue
        if t["outliers"][k].size and rng.random() < t["p_out"][k]:
            err = t["outliers"][k][rng.integers(len(t["outliers"][k]))]
        else:
            err = t["bias"][k] + t["chol"][k] @ rng.standard_normal(6)
        out.append(err)
    return out


@pytest.mark.parametrize(
    "rho, version, temporal",
    [
        ([0.0] * 6, VERSION, True),  # a fitted rho of zero
        (None, VERSION, True),  # a table without memory
        ([0.7] * 6, 1, True),  # a version-1 file: rho ignored
        ([0.7] * 6, VERSION, False),  # memory switched off
    ],
)
def test_rho_zero_v1_or_memory_off_give_the_memoryless_draws(rho, version, temporal):
    cov = _cov(SD)
    model = ErrorModel(synthetic_model(0.8, BIAS, cov, rho, version=version, p_outlier=0.1))
    ref_rng = np.random.default_rng(9)
    ref = _memoryless_reference(model, ref_rng, 400)
    src = ErrorModelSource(model, DockingTaskConfig(), temporal=temporal)
    src.reset(np.random.default_rng(9))
    _, poses = _run(src, 400)
    T_world_ds, T_world_body = above_ds(3.0)
    T_world_cam = T_world_body @ model.T_body_cam
    T_cam_ds = inv_T(T_world_cam) @ T_world_ds
    for want, got in zip(ref, poses, strict=True):
        assert (want is None) == (got is None)
        if got is not None:  # bit-identical
            assert np.array_equal(got, T_world_cam @ apply_error(T_cam_ds, want))
    assert src.rng.bit_generator.state == ref_rng.bit_generator.state  # same draws consumed


# ----------------------------------------------------------------------------- files


@pytest.mark.parametrize(
    "rho, why",
    [
        ([float("nan")] * 6, "NaN"),
        ([1.0] + [0.0] * 5, "|rho| = 1"),
        ([-1.5] + [0.0] * 5, "|rho| > 1"),
        ([0.5] * 5, "5 values"),
        ("high", "a string"),
        ([[0.1] * 6], "nested"),
    ],
)
def test_malformed_rho_is_a_one_line_dock_error(tmp_path, rho, why):
    path = tmp_path / "em.json"
    path.write_text(json.dumps(synthetic_model(0.8, BIAS, _cov(SD), rho)))
    with pytest.raises(DockError) as exc:
        load_error_model(path)
    msg = str(exc.value)
    assert "ar1 rho must be 6 numbers in (-1, 1)" in msg and "\n" not in msg, why


def test_model_files_load_with_and_without_memory(tmp_path):
    path = tmp_path / "em.json"
    data = synthetic_model(0.8, BIAS, _cov(SD), [0.5] * 6)
    del data["sequences"]  # rho without a step duration
    path.write_text(json.dumps(data))
    with pytest.raises(DockError, match=r"needs sequences\.step_s"):
        load_error_model(path)
    data = synthetic_model(0.8, BIAS, _cov(SD), [0.5] * 6, version=1)  # version 1: rho ignored
    path.write_text(json.dumps(data))
    assert not load_error_model(path).table("all")["rho"].any()
    data["version"] = 3
    path.write_text(json.dumps(data))
    with pytest.raises(DockError, match="not a version-1/2"):
        load_error_model(path)
    shipped = load_error_model("rl/models/error_model_clear_tank_480.json")  # version 1
    assert shipped.step_s is None and not shipped.table("clear_tank")["rho"].any()


# ----------------------------------------------------------------------------- sequences


def test_sequence_labels_pairs_and_checks():
    times = [0, 0.2, 0.6, 0, 0.2, 0.8]
    seqs = check_sequences([0, 0, 0, 1, 1, 0], [0, 1, 3, 0, 1, 4], times, 6, "t")
    i, j = seqs.consecutive_pairs()
    assert list(zip(i.tolist(), j.tolist(), strict=True)) == [(0, 1), (2, 5), (3, 4)]
    assert seqs.step_s() == pytest.approx(0.2)
    assert sequences_from_manifest({"sequences": seqs.to_json()}, 6).to_json() == seqs.to_json()
    assert sequences_from_manifest({}, 6) is None
    for args, match in [
        (([0, 0], [1, 1], [0, 1]), "repeats sequence 0 step 1"),
        (([0, 0], [0, 1], [1, 1]), "not later than"),
        (([0, -1], [0, 1], [0, 1]), "integers >= 0"),
        (([0, 0], [0, 1.5], [0, 1]), "integers >= 0"),
        (([0], [0], [0]), "must hold 2 values"),
    ]:
        with pytest.raises(DockError, match=match):
            check_sequences(*args, 2, "t")
    uneven = check_sequences([0, 0, 0], [0, 1, 2], [0, 0.2, 0.5], 3, "t")
    with pytest.raises(DockError, match="one positive step duration"):
        uneven.step_s()
    with pytest.raises(DockError, match="'sequences' must map"):
        sequences_from_manifest({"sequences": {"sequence": [0]}}, 1)


def test_pose_track_csv_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    poses = np.stack(
        [make_T(R_from_rpy(*rng.uniform(-3, 3, 3)), rng.uniform(-2, 2, 3)) for _ in range(5)]
    )
    seqs = check_sequences([0, 0, 0, 1, 1], [0, 1, 2, 4, 5], np.arange(5) * 0.2, 5, "t")
    path = write_pose_track_csv(tmp_path / "p.csv", poses, seqs)
    back, back_seqs = load_pose_track_csv(path)
    np.testing.assert_allclose(back, poses, atol=1e-15)
    assert back_seqs.to_json() == seqs.to_json()
    plain, none = load_pose_track_csv(write_pose_track_csv(tmp_path / "q.csv", poses))
    assert none is None and np.allclose(plain, poses)
    text = path.read_text().replace(",time_s", ",t").splitlines()
    (tmp_path / "bad.csv").write_text("\n".join(text) + "\n")
    with pytest.raises(DockError, match="missing time_s"):
        load_pose_track_csv(tmp_path / "bad.csv")


# ----------------------------------------------------------------------------- trajectories


def test_render_world_pose_keeps_the_view_of_the_ds():
    from uwdock.rl.evaluate.trajectories import render_world_pose

    T_world_ds = make_T(R_from_rpy(0, 0, 2.0), [0.7, -1.5, 4.98])
    T_world_body = make_T(R_from_rpy(0.05, -0.02, -1.0), [2.0, 1.0, 2.5])
    T_render_ds = make_T(t=[0.0, 0.0, 4.98])
    T_render_body = render_world_pose(T_world_body, T_world_ds, T_render_ds)
    np.testing.assert_allclose(
        inv_T(T_render_body) @ T_render_ds, inv_T(T_world_body) @ T_world_ds, atol=1e-12
    )


def test_rl_trajectories_writes_consecutive_pid_poses(run_cli, tmp_path):
    from uwdock.rl import cli

    env = tmp_path / "env.toml"
    env.write_text("episode_s = 3.0\n")
    args = ["trajectories", "--episodes", "2", "--seed", "4", "--config", env, "--quiet"]
    em = "rl/models/error_model_clear_tank_480.json"
    res = run_cli(cli.main, *args, "--error-model", em, "--out", tmp_path / "t")
    assert res.code == 0, res.err
    poses, seqs = load_pose_track_csv(tmp_path / "t" / "poses.csv")
    summary = json.loads((tmp_path / "t" / "episodes.json").read_text())
    assert summary["poses"] == len(poses) and summary["step_s"] == pytest.approx(0.2, rel=1e-6)
    assert set(seqs.sequence.tolist()) <= {0, 1}
    kept = sum(r["kept"] for r in summary["rows"])
    assert kept == len(poses) and all(r["steps"] == 15 for r in summary["rows"])
    # consecutive steps of one episode: poses a step apart move by less than 0.5 m
    i, j = seqs.consecutive_pairs()
    assert len(i) >= len(poses) - 2 - summary["left_out"]
    assert np.all(np.linalg.norm(poses[j, :3, 3] - poses[i, :3, 3], axis=1) < 0.5)
    # the same seeds give the same poses
    res = run_cli(cli.main, *args, "--error-model", em, "--out", tmp_path / "t2")
    assert res.code == 0, res.err
    again = (tmp_path / "t2" / "poses.csv").read_bytes()
    assert again == (tmp_path / "t" / "poses.csv").read_bytes()
    # no error model for the error-model source: one line
    res = run_cli(cli.main, *args, "--out", tmp_path / "t3")
    assert res.code != 0 and res.err.count("\n") == 1 and "error_model_path" in res.err


@pytest.mark.render
def test_rendered_sequences_reach_the_fit(tmp_path):
    """The seam: poses + sequence labels -> datasets render -> dataset.json -> the fit."""
    from uwdock.datasets.loaders import LabelledDataset
    from uwdock.datasets.synth import SynthConfig, generate

    T_ds = make_T(t=[0.0, 0.0, 4.98])
    task = DockingTaskConfig()
    T_target = T_ds @ task.T_ds_target
    poses = np.stack(
        [make_T(T_target[:3, :3], T_target[:3, 3] - [0.05 * k, 0.0, 2.0]) for k in range(4)]
    )
    seqs = check_sequences([0, 0, 0, 0], [0, 1, 2, 3], [0.0, 0.2, 0.4, 0.6], 4, "t")
    cfg = SynthConfig(n_frames=4, water="clear_tank", width_px=320)
    generate(tmp_path / "ds", cfg, poses=poses, sequences=seqs, progress=False)
    ds = LabelledDataset(tmp_path / "ds")
    assert ds.sequences is not None and ds.sequences.to_json() == seqs.to_json()
    model = fit_error_model(tmp_path / "ds", ErrorModelConfig(min_pairs=2), progress=False)
    assert model["version"] == VERSION and model["sequences"]["consecutive_pairs"] == 3
    assert model["sequences"]["step_s"] == pytest.approx(0.2)
    assert model["tables"]["clear_tank"]["ar1"]["pairs"] <= 3
    ErrorModel(model)  # loads
    # resuming the folder with other sequence labels is refused
    other = check_sequences([0, 0, 1, 1], [0, 1, 0, 1], [0.0, 0.2, 0.0, 0.2], 4, "t")
    with pytest.raises(DockError, match="differs in sequences"):
        generate(tmp_path / "ds", cfg, poses=poses, sequences=other, progress=False)
