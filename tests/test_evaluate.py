"""Evaluate: the protocol's numbers on hand-built cases, and `reloc evaluate` end to end."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import SCENE_FRAMES
from reloc_fixtures import copy_run, trained_run, with_anchors
from relocdepth.cli.main import app
from relocdepth.schemas import validate
from typer.testing import CliRunner

from relocdepth import eval_geometry as EG
from relocdepth import metrics as M
from relocdepth.dataset import open_dataset
from relocdepth.errors import UserError
from relocdepth.evaluate import baselines_report, pose_report
from relocdepth.refine import REFINED_BY
from relocdepth.trajectory import read_tum


def trajectory(n: int, seed: int, offset=(0.0, 0.0, 0.0)) -> np.ndarray:
    """A wandering camera: smooth centres over ~1 m, rotations up to ~40 deg."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0, 2 * np.pi, n)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = np.stack([np.cos(s + seed), 0.5 * np.sin(2 * s), 0.2 * s], 1) + offset
    axis = rng.normal(size=3)
    for i, a in enumerate(s):
        q = np.r_[np.cos(0.3 * np.sin(a)), np.sin(0.3 * np.sin(a)) * axis / np.linalg.norm(axis)]
        T[i, :3, :3] = EG.quat_wxyz_to_rotmat(q)
    return T


def sim3(T: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return EG.apply_sim3(s, R, t, T)


R0 = EG.quat_wxyz_to_rotmat(np.array([0.8, 0.3, -0.2, 0.5]))
T0 = np.array([2.0, -1.0, 0.5])


def test_known_sim3_gives_zero_error() -> None:
    train_gt, test_gt = trajectory(30, 0), trajectory(12, 1, offset=(0.1, 0.0, 0.0))
    # the "network" predicts the GT in another frame and unit: x_net = (R0^T (x - T0)) / 3
    R_inv, s_inv = R0.T, 1.0 / 3.0
    to_net = (s_inv, R_inv, -s_inv * R_inv @ T0)
    report, fit, aligned = pose_report(
        sim3(train_gt, *to_net), train_gt, sim3(test_gt, *to_net), test_gt, ["seq-03"] * 12
    )
    assert fit.degenerate is None
    assert fit.scale == pytest.approx(3.0)
    np.testing.assert_allclose(fit.R, R0, atol=1e-9)
    np.testing.assert_allclose(fit.t, T0, atol=1e-9)
    np.testing.assert_allclose(aligned, test_gt, atol=1e-9)
    assert report["test"]["median_t_m"] == pytest.approx(0.0, abs=1e-9)
    assert report["test"]["median_r_deg"] == pytest.approx(0.0, abs=1e-4)
    assert report["test"]["pct_5cm_5deg"] == 100.0
    assert report["rotation_only"]["median_r_deg"] == pytest.approx(0.0, abs=1e-4)
    assert report["relative"]["median_t_m"] == pytest.approx(0.0, abs=1e-9)
    assert report["relative"]["identity_median_t_m"] > 0.05
    assert report["spread"]["prediction_raw"]["centre_rms"] == pytest.approx(
        report["spread"]["ground_truth"]["centre_rms"] / 3.0)


def test_error_along_the_optical_axis() -> None:
    """Test predictions that are the ground truth moved 7 cm along each true camera's optical axis
    (and 4 cm across it, which must not count), in another frame and unit: the along-axis error
    is +0.07 m, -0.07 m when moved back; the exact case gives 0."""
    train_gt, test_gt = trajectory(30, 0), trajectory(12, 1, offset=(0.1, 0.0, 0.0))
    to_net = (0.5, R0.T, -0.5 * R0.T @ T0)
    for step in (0.07, -0.07, 0.0):
        moved = test_gt.copy()
        moved[:, :3, 3] += step * test_gt[:, :3, 2] + 0.04 * test_gt[:, :3, 0]
        report, _, _ = pose_report(sim3(train_gt, *to_net), train_gt, sim3(moved, *to_net), test_gt, ["s"] * 12)
        ax = report["along_axis"]
        assert ax["median_m"] == pytest.approx(step, abs=1e-9)
        assert ax["mean_m"] == pytest.approx(step, abs=1e-9)
        assert ax["median_abs_m"] == pytest.approx(abs(step), abs=1e-9)
        assert report["test"]["median_t_m"] == pytest.approx(np.hypot(step, 0.04), abs=1e-9)


def test_depth_in_the_poses_units() -> None:
    """A network whose poses are the ground truth at 1/3 scale (the Sim(3)'s scale is 3) and whose
    depth is the ground truth's at 1/3.3 on one frame, 1/3 on another: the depth is 10 % short of
    its poses' units on the first (ratio 1.1) and in them on the second (1.0); a frame without
    depth is left out; none at all gives no summary."""
    from relocdepth.evaluate import depth_pose_ratios, depth_pose_summary

    rng = np.random.default_rng(3)
    gt = rng.uniform(0.5, 4.0, size=(24, 32))
    frames = [M.depth_errors(gt / 3.3, gt), M.depth_errors(gt / 3.0, gt), None]
    ratios = depth_pose_ratios(frames, 3.0)
    np.testing.assert_allclose(ratios[:2], [1.1, 1.0], rtol=1e-9)
    assert np.isnan(ratios[2])
    summary = depth_pose_summary(ratios)
    assert summary["frames"] == 2 and summary["median"] == pytest.approx(1.05)
    assert summary["p10"] == pytest.approx(1.01) and summary["p90"] == pytest.approx(1.09)
    assert summary["train_median"] is None
    # the training frames' depth in the poses' units (1.0, and a frame without depth): beside it
    train = depth_pose_ratios([M.depth_errors(gt / 3.0, gt), None, M.depth_errors(gt / 2.7, gt)], 3.0)
    assert depth_pose_summary(ratios, train)["train_median"] == pytest.approx(0.95)
    assert depth_pose_summary(np.array([np.nan])) is None


def test_alignment_gap_when_centres_and_orientations_disagree() -> None:
    """Predictions whose centres are the GT's in one frame and whose orientations are the GT's
    turned a further 7 deg about the vertical: the rotation-only alignment recovers the
    orientations exactly and says it is 7 deg from the centre fit, which hands its 7 deg to every
    aligned rotation; with one world (the known-Sim(3) case) the gap is 0."""
    train_gt, test_gt = trajectory(30, 0), trajectory(12, 1, offset=(0.1, 0.0, 0.0))
    to_net = (0.5, R0.T, -0.5 * R0.T @ T0)
    train_est, test_est = sim3(train_gt, *to_net), sim3(test_gt, *to_net)
    report, _, _ = pose_report(train_est, train_gt, test_est, test_gt, ["s"] * 12)
    assert report["rotation_only"]["fit_gap_deg"] == pytest.approx(0.0, abs=1e-4)
    turn = EG.quat_wxyz_to_rotmat(np.array([np.cos(np.radians(3.5)), 0.0, np.sin(np.radians(3.5)), 0.0]))
    for T in (train_est, test_est):
        T[:, :3, :3] = R0.T @ turn @ R0 @ T[:, :3, :3]  # a world-side turn in GT axes
    report, fit, _ = pose_report(train_est, train_gt, test_est, test_gt, ["s"] * 12)
    np.testing.assert_allclose(fit.R, R0, atol=1e-9)  # the centres still fit exactly
    assert report["rotation_only"]["median_r_deg"] == pytest.approx(0.0, abs=1e-4)
    assert report["rotation_only"]["fit_gap_deg"] == pytest.approx(7.0, abs=1e-4)
    assert report["test"]["median_r_deg"] == pytest.approx(7.0, abs=1e-4)


def test_constructed_test_errors_of_known_size() -> None:
    train_gt, test_gt = trajectory(30, 0), trajectory(10, 1)
    test_est = test_gt.copy()
    # frames 0-4: 4 cm off along x; frames 5-9: 8 deg off about the camera's z
    test_est[:5, :3, 3] += [0.04, 0.0, 0.0]
    test_est[5:, :3, :3] = test_est[5:, :3, :3] @ EG.quat_wxyz_to_rotmat(
        np.r_[np.cos(np.radians(4.0)), 0.0, 0.0, np.sin(np.radians(4.0))])
    report, fit, _ = pose_report(train_gt, train_gt, test_est, test_gt, ["a"] * 5 + ["b"] * 5)
    assert fit.scale == pytest.approx(1.0)
    assert report["per_sequence"]["a"]["median_t_m"] == pytest.approx(0.04)
    assert report["per_sequence"]["a"]["median_r_deg"] == pytest.approx(0.0, abs=1e-4)
    assert report["per_sequence"]["b"]["median_r_deg"] == pytest.approx(8.0)
    assert report["test"]["pct_5cm_5deg"] == 50.0
    assert report["test"]["pct_10cm_10deg"] == 100.0
    assert report["train"]["median_t_m"] == pytest.approx(0.0, abs=1e-9)


def test_threshold_columns_on_known_errors() -> None:
    """5cm/5deg, 10cm/5deg (ACE's and DSAC*'s) and 10cm/10deg shares; bounds are inclusive."""
    t = np.array([0.03, 0.07, 0.07, 0.20, 0.10, 0.05])
    r = np.array([1.0, 3.0, 7.0, 1.0, 5.0, 5.0])
    # in 5/5: frames 0, 5; 10/5: 0, 1, 4, 5; 10/10: 0, 1, 2, 4, 5
    s = M.pose_summary(t, r)
    assert s["pct_5cm_5deg"] == pytest.approx(100 * 2 / 6)
    assert s["pct_10cm_5deg"] == pytest.approx(100 * 4 / 6)
    assert s["pct_10cm_10deg"] == pytest.approx(100 * 5 / 6)
    assert M.pose_summary(t[:0], r[:0])["pct_10cm_5deg"] is None


def test_baselines() -> None:
    train_gt = trajectory(20, 0)
    test_gt = train_gt[[2, 7, 11]].copy()
    test_gt[:, :3, 3] += [0.0, 0.02, 0.0]  # 2 cm from training frames 2, 7, 11
    rng = np.random.default_rng(0)
    thumbs = np.stack([M.thumbnail(rng.integers(0, 255, (24, 32))) for _ in range(20)])
    out = baselines_report(train_gt, test_gt, thumbs, thumbs[[2, 7, 11]])
    assert out["retrieval"]["median_t_m"] == pytest.approx(0.02)
    assert out["retrieval"]["median_r_deg"] == pytest.approx(0.0, abs=1e-4)
    mean_c = train_gt[:, :3, 3].mean(0)
    expect = np.median(np.linalg.norm(test_gt[:, :3, 3] - mean_c, axis=1))
    assert out["mean_pose"]["median_t_m"] == pytest.approx(expect)


def test_nearest_centre_baseline_measures_distance_to_training_cameras() -> None:
    """The oracle picks the training camera nearest each test camera's true centre, whatever the
    images look like; its translation error is that distance and its rotation error the angle
    between the two cameras."""
    train = np.tile(np.eye(4), (5, 1, 1))
    train[:, 0, 3] = np.arange(5.0)  # centres at x = 0, 1, 2, 3, 4
    query = np.tile(np.eye(4), (3, 1, 1))
    query[:, :3, 3] = [[2.3, 0.0, 0.0], [-0.5, 0.0, 0.0], [3.9, 0.4, 0.0]]
    query[0, :3, :3] = EG.quat_wxyz_to_rotmat(np.r_[np.cos(np.radians(10)), 0.0, np.sin(np.radians(10)), 0.0])
    poses, idx, dist = M.nearest_centre_baseline(train, query)
    assert idx.tolist() == [2, 0, 4]
    np.testing.assert_allclose(dist, [0.3, 0.5, np.hypot(0.1, 0.4)], atol=1e-12)
    t_err, r_err = EG.pose_errors(poses, query)
    np.testing.assert_allclose(t_err, dist, atol=1e-12)
    np.testing.assert_allclose(r_err, [20.0, 0.0, 0.0], atol=1e-6)
    # in the report: thumbnails that send retrieval to the wrong frames do not move the oracle
    rng = np.random.default_rng(0)
    thumbs = np.stack([M.thumbnail(rng.integers(0, 255, (24, 32))) for _ in range(5)])
    out = baselines_report(train, query, thumbs, thumbs[[0, 4, 0]])
    assert out["nearest_training_centre"]["median_t_m"] == pytest.approx(np.hypot(0.1, 0.4))
    assert out["retrieval"]["median_t_m"] == pytest.approx(np.hypot(3.9, 0.4))  # 2.3, 4.5, 3.92 m off


def test_report_schema_rejects_missing_fields() -> None:
    with pytest.raises(UserError, match="report"):
        validate("report", {"format": "relocdepth-report"}, what="report")


# ----------------------------------------------------------------------------- end to end


@pytest.fixture(scope="module")
def run(synth_shards: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return trained_run(synth_shards, tmp_path_factory)


def invoke(*args: str):
    return CliRunner().invoke(app, list(args))


def test_evaluate_end_to_end_and_alignment_in_localize(
    run: Path, synth_shards: Path, synth_scene: Path, tmp_path: Path
) -> None:
    run = copy_run(run, tmp_path / "run")  # --save-alignment writes into the run
    report_path = tmp_path / "out" / "report.json"
    res = invoke("evaluate", str(synth_shards), "--checkpoint", str(run), "-o", str(report_path),
                 "--plots", str(tmp_path / "plots"), "--save-alignment")
    assert res.exit_code == 0, res.output
    assert "thumbnail retrieval" in res.stdout and "constant depth" in res.stdout
    report = json.loads(report_path.read_text())
    validate("report", report)
    gap = report["pose"]["rotation_only"]["fit_gap_deg"]
    assert f"{gap:.2f} deg from the centre-fitted Sim(3)" in res.stdout
    assert report["dataset"]["train_frames"] == 2 * SCENE_FRAMES
    assert report["dataset"]["test_frames"] == SCENE_FRAMES
    assert report["pose"]["test"]["frames"] == SCENE_FRAMES
    assert report["depth"]["prediction"]["frames"] == SCENE_FRAMES
    assert 0.0 < report["depth"]["constant_reference"]["abs_rel"] < 1.0
    assert report["saved_alignment"] is True
    flagged = report["alignment"]["degenerate"]
    assert flagged == (report["alignment"]["degenerate_reason"] is not None)
    assert ("warning: the Sim(3) fit is degenerate" in res.stdout) == flagged

    # the TUM files parse back: GT equals the shards' poses, errors recomputed from them match
    ds = open_dataset(synth_shards)
    test = ds.frames("test")
    tum = report["outputs"]["tum"]["seq-03"]
    ts, T_est = read_tum(tum["estimate"])
    ts_gt, T_gt = read_tum(tum["groundtruth"])
    np.testing.assert_allclose(ts, [r.timestamp for r in test], atol=1e-6)
    np.testing.assert_allclose(ts_gt, ts)
    np.testing.assert_allclose(T_gt, np.stack([ds.read_pose(r) for r in test]), atol=1e-6)
    t_err, _ = EG.pose_errors(T_est, T_gt)
    assert np.median(t_err) == pytest.approx(report["pose"]["test"]["median_t_m"], abs=1e-6)

    for plot in report["outputs"]["plots"]:
        assert cv2.imread(plot) is not None
    assert {Path(p).name for p in report["outputs"]["plots"]} == {"trajectory.png", "depth_strips.png"}

    # localize now reports the aligned pose: the same as evaluate's estimate for that frame
    res = invoke("localize", str(synth_scene / "seq-03" / "frame-000000.color.png"), "--checkpoint", str(run))
    assert res.exit_code == 0, res.output
    rec = json.loads(res.stdout.splitlines()[-1])
    assert rec["aligned"] is True and rec["units"] == "m"
    np.testing.assert_allclose(np.array(rec["T_wc"]), T_est[0], atol=1e-4)


def test_evaluate_flags_a_degenerate_fit(
    run: Path, synth_shards: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A collapsed network (one pose for every image): the Sim(3) cannot be fitted, and says so."""
    from relocdepth.predictor import Predictor

    predict = Predictor.predict

    def collapsed(self, *args, **kwargs):
        pred = predict(self, *args, **kwargs)
        pred.T_wc[:] = np.array([[1.0, 0, 0, 0.3], [0, 1, 0, -0.2], [0, 0, 1, 1.0], [0, 0, 0, 1]])
        return pred

    monkeypatch.setattr(Predictor, "predict", collapsed)
    report_path = tmp_path / "collapsed" / "report.json"
    res = invoke("evaluate", str(synth_shards), "--checkpoint", str(run), "-o", str(report_path))
    assert res.exit_code == 0, res.output
    report = json.loads(report_path.read_text())
    validate("report", report)
    assert report["alignment"]["degenerate"] is True
    assert "the predicted positions coincide" in report["alignment"]["degenerate_reason"]
    warnings = [line for line in res.stdout.splitlines() if line.startswith("warning: ")]
    assert len(warnings) == 1 and "degenerate" in warnings[0] and "coincide" in warnings[0]
    # the Sim(3)'s rotation is arbitrary then: no gap between it and the rotation-only fit
    assert "fit_gap_deg" not in report["pose"]["rotation_only"]
    assert "from the centre-fitted" not in res.stdout


def test_evaluate_bad_inputs(run: Path, synth_scene: Path, synth_shards: Path, tmp_path: Path) -> None:
    from relocdepth.ingest.run import IngestConfig, ingest

    no_gt = tmp_path / "video_shards"
    ingest([synth_scene / "videos" / "seq-01.mp4"], no_gt,
           IngestConfig(intrinsics=str(synth_scene / "intrinsics.yaml")))
    for args, word in [
        ((str(no_gt), "--checkpoint", str(run)), "ground-truth"),
        ((str(synth_shards), "--checkpoint", str(tmp_path / "nope")), "does not exist"),
        ((str(tmp_path / "no_shards"), "--checkpoint", str(run)), "not found"),
    ]:
        res = invoke("evaluate", *args)
        assert res.exit_code == 2, res.output
        last = res.output.strip().splitlines()[-1]
        assert last.startswith("error: ") and word in last, res.output


def test_evaluate_on_chosen_sequences(run: Path, synth_shards: Path, tmp_path: Path) -> None:
    report_path = tmp_path / "train_seq" / "report.json"
    res = invoke("evaluate", str(synth_shards), "--checkpoint", str(run), "-o", str(report_path),
                 "--test-sequences", "seq-01")
    assert res.exit_code == 0, res.output
    report = json.loads(report_path.read_text())
    validate("report", report)
    assert report["dataset"]["test_sequences"] == ["seq-01"]
    assert report["dataset"]["test_frames"] == SCENE_FRAMES
    ds = open_dataset(synth_shards)
    splits = {r.sequence: r.split for r in ds.records}
    assert splits == {"seq-01": "train", "seq-02": "train", "seq-03": "test"}
    # only seq-02 fits the Sim(3): the test split's frames, which the networks never saw, do not
    assert report["dataset"]["train_frames"] == SCENE_FRAMES
    assert report["pose"]["train"]["frames"] == SCENE_FRAMES
    seq1 = [r for r in ds.records if r.sequence == "seq-01"]
    _, T_gt = read_tum(report["outputs"]["tum"]["seq-01"]["groundtruth"])
    np.testing.assert_allclose(T_gt, np.stack([ds.read_pose(r) for r in seq1]), atol=1e-6)

    res = invoke("evaluate", str(synth_shards), "--checkpoint", str(run), "--test-sequences", "seq-09")
    assert res.exit_code == 2, res.output
    last = res.output.strip().splitlines()[-1]
    assert last.startswith("error: ") and "seq-09" in last and "seq-01" in last, res.output
    # every training sequence named: nothing left to fit the Sim(3) on
    res = invoke("evaluate", str(synth_shards), "--checkpoint", str(run), "--test-sequences", "seq-01,seq-02")
    assert res.exit_code == 2, res.output
    last = res.output.strip().splitlines()[-1]
    assert last.startswith("error: ") and "0 training frames" in last, res.output


def test_per_frame_csv_confidence_ranking_and_evo_ape(
    run: Path, synth_shards: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The per-frame CSV and the TUM files agree with the report; evo reads the TUM files and
    its APE (no alignment: the estimate is already in the GT frame) equals the report's errors."""
    import csv

    report_path = tmp_path / "eval" / "office.json"
    res = invoke("evaluate", str(synth_shards), "--checkpoint", str(run), "-o", str(report_path))
    assert res.exit_code == 0, res.output
    assert "10cm/5deg" in res.stdout and "Spearman" in res.stdout
    report = json.loads(report_path.read_text())
    validate("report", report)
    csv_path = tmp_path / "eval" / "office.frames.csv"
    assert report["outputs"]["frames_csv"] == str(csv_path)
    with csv_path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["sequence", "frame", "t_err_m", "r_err_deg", "confidence", "nearest_train_m",
                             "along_axis_m", "depth_pose_ratio"]
    test = open_dataset(synth_shards).frames("test")
    assert [(r["sequence"], int(r["frame"])) for r in rows] == [(x.sequence, x.frame) for x in test]
    t_csv = np.array([float(r["t_err_m"]) for r in rows])
    r_csv = np.array([float(r["r_err_deg"]) for r in rows])
    conf = np.array([float(r["confidence"]) for r in rows])
    assert np.all((conf > 0) & (conf <= 1))

    # the CSV's errors are the errors between the TUM files, frame by frame
    tum = report["outputs"]["tum"]["seq-03"]
    _, T_est = read_tum(tum["estimate"])
    _, T_gt = read_tum(tum["groundtruth"])
    t_tum, r_tum = EG.pose_errors(T_est, T_gt)
    np.testing.assert_allclose(t_csv, t_tum, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(r_csv, r_tum, rtol=1e-4, atol=1e-3)
    # each frame's distance to the nearest training camera, from the ground truth
    ds = open_dataset(synth_shards)
    train_c = np.stack([ds.read_pose(x) for x in ds.frames("train")])[:, :3, 3]
    near = np.array([float(r["nearest_train_m"]) for r in rows])
    expect = np.linalg.norm(T_gt[:, None, :3, 3] - train_c[None], axis=2).min(1)
    np.testing.assert_allclose(near, expect, rtol=1e-4, atol=1e-5)
    assert near.min() > 0.0
    nearest = report["baselines"]["nearest_training_centre"]
    assert np.median(near) == pytest.approx(nearest["median_t_m"], rel=1e-4)
    test_summary = report["pose"]["test"]
    assert np.median(t_csv) == pytest.approx(test_summary["median_t_m"], rel=1e-4)
    assert 100 * np.mean((t_csv <= 0.10) & (r_csv <= 5.0)) == pytest.approx(test_summary["pct_10cm_5deg"])
    # the error along each true optical axis, from the TUM files; the depth's ratio to the poses' units
    along = np.array([float(r["along_axis_m"]) for r in rows])
    np.testing.assert_allclose(along, np.einsum("ni,ni->n", T_est[:, :3, 3] - T_gt[:, :3, 3], T_gt[:, :3, 2]),
                               rtol=1e-4, atol=1e-5)
    assert np.all(np.abs(along) <= t_csv * (1 + 1e-4) + 1e-6)
    assert report["pose"]["along_axis"]["median_m"] == pytest.approx(np.median(along), rel=1e-4, abs=1e-6)
    ratio = np.array([float(r["depth_pose_ratio"]) for r in rows])
    assert np.all(ratio > 0)
    assert report["depth"]["pose_units"]["median"] == pytest.approx(np.median(ratio), rel=1e-4)
    assert report["depth"]["pose_units"]["frames"] == len(rows)
    assert report["depth"]["pose_units"]["train_median"] > 0  # the synthetic scene's training frames have depth
    assert "training frames" in res.stdout
    ranking = report["confidence"]
    assert ranking["frames"] == len(rows)
    assert ranking["median"] == pytest.approx(np.median(conf), rel=1e-4)
    assert ranking["spearman_t"] == pytest.approx(M.spearman(conf, t_csv), abs=1e-3)
    assert ranking["spearman_r"] == pytest.approx(M.spearman(conf, r_csv), abs=1e-3)

    # evo (the tool people use on TUM files) agrees with the report
    monkeypatch.setenv("HOME", str(tmp_path))  # evo keeps its settings under ~/.evo
    evo_metrics = pytest.importorskip("evo.core.metrics")
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(tum["groundtruth"])
    est = file_interface.read_tum_trajectory_file(tum["estimate"])
    stats = {}
    for name, relation in (("t", evo_metrics.PoseRelation.translation_part),
                           ("r", evo_metrics.PoseRelation.rotation_angle_deg)):
        ape = evo_metrics.APE(relation)
        ape.process_data((ref, est))
        stats[name] = {k: ape.get_statistic(getattr(evo_metrics.StatisticsType, k))
                       for k in ("median", "mean", "rmse")}
    seq = report["pose"]["per_sequence"]["seq-03"]
    assert stats["t"]["median"] == pytest.approx(seq["median_t_m"], rel=1e-5, abs=1e-7)
    assert stats["t"]["mean"] == pytest.approx(seq["mean_t_m"], rel=1e-5, abs=1e-7)
    assert stats["r"]["median"] == pytest.approx(seq["median_r_deg"], rel=1e-4, abs=1e-3)
    assert stats["r"]["mean"] == pytest.approx(seq["mean_r_deg"], rel=1e-4, abs=1e-3)
    assert stats["t"]["rmse"] == pytest.approx(float(np.sqrt(np.mean(t_csv**2))), rel=1e-4)


def test_evaluate_refine_reports_both_and_the_csv_agrees(run: Path, synth_shards: Path, tmp_path: Path) -> None:
    """--refine adds pose.refined under the same alignment, a table row and per-frame columns;
    a frame with under two agreeing pairs keeps the network's error."""
    import csv

    report_path = tmp_path / "r.json"
    res = invoke("evaluate", str(synth_shards), "--checkpoint", str(run), "-o", str(report_path),
                 "--refine", "--refine-neighbours", "2")
    assert res.exit_code == 0, res.output
    report = json.loads(report_path.read_text())
    validate("report", report)
    refined = report["pose"]["refined"]
    assert refined["neighbours"] == 2 and refined["test"]["frames"] == SCENE_FRAMES
    assert refined["matcher"] == "klt+sift"
    rel = refined["relative"]
    assert f"refined relative pose, frames {rel['k']} apart: {rel['median_t_m']:.3f} m" in res.stdout
    assert "refined, nearest train" in res.stdout and "against the 2 nearest training frames" in res.stdout
    with (tmp_path / "r.frames.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0])[-4:] == ["refined_t_err_m", "refined_r_err_deg", "refined_pairs", "refined_by"]
    pairs = np.array([int(r["refined_pairs"]) for r in rows])
    by = np.array([r["refined_by"] for r in rows])
    t_net = np.array([float(r["t_err_m"]) for r in rows])
    t_ref = np.array([float(r["refined_t_err_m"]) for r in rows])
    assert np.all((pairs >= 0) & (pairs <= 2)) and set(by) <= set(REFINED_BY)
    kept = by == "none"
    assert refined["min_pairs"] == 2 and refined["network_pose_kept"] == int(np.sum(kept))
    assert refined["map"] == "network"  # the run has no anchors: auto takes the network's poses
    assert refined["align"] is True and refined["aligned"] == int(np.sum(by == "aligned"))
    assert np.all(pairs[kept] < 2) and np.all(pairs[by == "pairs"] >= 2)
    np.testing.assert_allclose(t_ref[kept], t_net[kept], rtol=1e-4, atol=1e-6)
    assert np.median(t_ref) == pytest.approx(refined["test"]["median_t_m"], rel=1e-4)
    # --no-refine-align: the pairs alone, the same pairs
    res = invoke("evaluate", str(synth_shards), "--checkpoint", str(run), "-o", str(tmp_path / "pairs.json"),
                 "--refine", "--refine-neighbours", "2", "--no-refine-align")
    assert res.exit_code == 0, res.output
    pairs_only = json.loads((tmp_path / "pairs.json").read_text())["pose"]["refined"]
    assert pairs_only["align"] is False and pairs_only["aligned"] == 0
    with (tmp_path / "pairs.frames.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["refined_pairs"]) for r in rows] == pairs.tolist()
    assert [r["refined_by"] for r in rows] == ["pairs" if p >= 2 else "none" for p in pairs]
    # without --refine the report and the CSV stay as they were
    res = invoke("evaluate", str(synth_shards), "--checkpoint", str(run), "-o", str(tmp_path / "plain.json"))
    assert res.exit_code == 0, res.output
    assert "refined" not in json.loads((tmp_path / "plain.json").read_text())["pose"]
    assert "refined" not in (tmp_path / "plain.frames.csv").read_text().splitlines()[0]


def test_evaluate_refines_against_the_runs_anchors(run: Path, synth_shards: Path, tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """A run with anchors (here the training frames' true poses moved by a known similarity) is
    refined against them (--refine-map auto or anchors), in the training frames' order, and the
    refined poses are scored under the Sim(3) fitted on them (in the report's alignment): a
    refinement that puts every test frame at its true pose in the anchors' world scores no error,
    and frames it leaves at the network's pose score the network's errors. --refine-map network
    keeps the network's poses; anchors asked of a run that has none is one error line."""
    from relocdepth.refine import Refined, Refiner

    sim3 = (2.5, cv2.Rodrigues(np.radians([10.0, -30.0, 5.0]))[0], np.array([0.4, -1.0, 2.0]))
    anchored, anchors = with_anchors(run, synth_shards, tmp_path / "run", sim3)
    ds = open_dataset(synth_shards)
    truth = {ds.read_image(r).tobytes(): EG.apply_sim3(*sim3, ds.read_pose(r)[None].astype(np.float64))[0]
             for r in ds.records if r.split == "test"}
    maps = []

    def refine(self: Refiner, image: np.ndarray, intrinsics, T_wc: np.ndarray) -> Refined:
        maps.append(self.ref.T_wc)
        return Refined(truth[image.tobytes()], 2, "aligned")

    monkeypatch.setattr(Refiner, "refine", refine)
    for which in ("auto", "anchors", "network"):
        out = tmp_path / f"{which}.json"
        res = invoke("evaluate", str(synth_shards), "--checkpoint", str(anchored), "-o", str(out),
                     "--refine", "--refine-map", which)
        assert res.exit_code == 0, res.output
        refined = json.loads(out.read_text())["pose"]["refined"]
        validate("report", json.loads(out.read_text()), "report")
        # the anchors' own alignment into the ground truth's frame (the inverse of sim3), whatever the map
        stored = json.loads(out.read_text())["alignment"]["anchors"]
        assert abs(stored["scale"] - 1 / sim3[0]) < 1e-5 and stored["degenerate"] is False
        np.testing.assert_allclose(np.array(stored["rotation"]), sim3[1].T, atol=1e-5)
        if which == "network":
            assert refined["map"] == "network" and not np.allclose(maps[-1], anchors, atol=1e-3)
            assert refined["test"]["median_t_m"] > 0.01  # the anchors' world is not the network's
        else:
            assert refined["map"] == "anchors" and np.allclose(maps[-1], anchors, atol=1e-5)
            assert refined["test"]["median_t_m"] < 1e-4 and refined["test"]["median_r_deg"] < 0.01
            assert "(the map: the run's anchors)" in res.output
    # frames the refinement leaves at the network's pose are in the network's world: under its
    # alignment they score the network's own errors, not those of the anchors' alignment
    monkeypatch.setattr(Refiner, "refine", lambda self, image, intrinsics, T_wc: Refined(T_wc, 0, "none"))
    res = invoke("evaluate", str(synth_shards), "--checkpoint", str(anchored), "-o", str(tmp_path / "kept.json"),
                 "--refine")
    assert res.exit_code == 0, res.output
    pose = json.loads((tmp_path / "kept.json").read_text())["pose"]
    assert pose["refined"]["map"] == "anchors" and pose["refined"]["network_pose_kept"] == len(truth)
    assert pose["refined"]["test"] == pose["test"]
    res = invoke("evaluate", str(synth_shards), "--checkpoint", str(run), "-o", str(tmp_path / "x.json"),
                 "--refine", "--refine-map", "anchors")
    assert res.exit_code == 2 and "holds no anchors" in res.output
    assert len(res.output.strip().splitlines()) == 1 and not (tmp_path / "x.json").exists()
