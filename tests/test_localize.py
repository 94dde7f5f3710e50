"""`reloc localize` on a run trained for one step: proper rotations, determinism, outputs, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from reloc_fixtures import copy_run, trained_run, with_anchors
from relocdepth.cli.main import app
from relocdepth.ingest.intrinsics import write_intrinsics_yaml
from typer.testing import CliRunner

from relocdepth.camera import Intrinsics
from relocdepth.eval_geometry import quat_wxyz_to_rotmat, quat_xyzw_to_wxyz
from relocdepth.refine import REFINED_BY
from relocdepth.trajectory import read_tum

FRAMES = 6  # frames of the query folder / video (few: forward passes are the slow part)


@pytest.fixture(scope="module")
def run(synth_shards: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return trained_run(synth_shards, tmp_path_factory)


@pytest.fixture(scope="module")
def folder(synth_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 7-Scenes sequence folder with FRAMES frames (colour, depth and pose files)."""
    out = tmp_path_factory.mktemp("query") / "seq-03"
    out.mkdir()
    for i in range(FRAMES):
        for ext in (".color.png", ".depth.png", ".pose.txt"):
            name = f"frame-{i:06d}{ext}"
            (out / name).write_bytes((synth_scene / "seq-03" / name).read_bytes())
    return out


@pytest.fixture(scope="module")
def video(folder: Path) -> Path:
    path = folder.parent / "query.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (128, 96))
    for i in range(FRAMES):
        writer.write(cv2.imread(str(folder / f"frame-{i:06d}.color.png")))
    writer.release()
    return path


def invoke(*args: str):
    return CliRunner().invoke(app, ["localize", *args])


def records(result) -> list[dict]:
    assert result.exit_code == 0, result.output
    return [json.loads(line) for line in result.stdout.splitlines() if line.startswith("{")]


def assert_user_error(result, *words: str) -> None:
    assert result.exit_code == 2, result.output
    last = result.output.strip().splitlines()[-1]
    assert last.startswith("error: "), result.output
    assert "Traceback" not in result.output
    for w in words:
        assert w in last, last


def test_folder_gives_proper_rotations_and_is_deterministic(run: Path, folder: Path) -> None:
    first = invoke(str(folder), "--checkpoint", str(run), "--batch-size", "4")
    recs = records(first)
    assert [r["name"] for r in recs] == [f"frame-{i:06d}" for i in range(FRAMES)]
    for r in recs:
        T = np.array(r["T_wc"])
        R = T[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-6)
        np.testing.assert_allclose(T[3], [0, 0, 0, 1])
        np.testing.assert_allclose(quat_wxyz_to_rotmat(quat_xyzw_to_wxyz(r["q"])), R, atol=1e-6)
        np.testing.assert_allclose(r["t"], T[:3, 3])
        assert 0.0 < r["confidence"] <= 1.0
        assert r["aligned"] is False and r["units"] == "network"
    again = invoke(str(folder), "--checkpoint", str(run), "--batch-size", "4")
    assert again.stdout == first.stdout


def test_tum_output_parses_back(run: Path, folder: Path, tmp_path: Path) -> None:
    recs = records(invoke(str(folder), "--checkpoint", str(run)))
    out = tmp_path / "traj.tum"
    res = invoke(str(folder), "--checkpoint", str(run), "--format", "tum", "--output", str(out))
    assert res.exit_code == 0, res.output
    ts, T = read_tum(out)
    np.testing.assert_allclose(ts, np.arange(FRAMES))
    np.testing.assert_allclose(T, np.array([r["T_wc"] for r in recs]), atol=1e-6)


def test_video_and_depth_outputs(run: Path, video: Path, tmp_path: Path) -> None:
    recs = records(invoke(str(video), "--checkpoint", str(run), "--depth-out", str(tmp_path / "d"),
                          "--batch-size", "16"))
    assert len(recs) == FRAMES
    np.testing.assert_allclose([r["timestamp"] for r in recs], np.arange(FRAMES) / 30.0, atol=1e-6)
    depth = cv2.imread(recs[3]["depth_png"], cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and depth.shape == (96, 128)
    assert (depth > 0).all()
    assert cv2.imread(recs[3]["depth_preview"]).shape == (96, 128, 3)
    assert sorted(p.name for p in (tmp_path / "d").iterdir() if p.name.startswith(".")) == []


def test_other_aspect_needs_K(run: Path, synth_scene: Path, tmp_path: Path) -> None:
    img = cv2.imread(str(synth_scene / "seq-03" / "frame-000000.color.png"))
    square = tmp_path / "square.png"
    cv2.imwrite(str(square), img[:, :96])
    assert_user_error(invoke(str(square), "--checkpoint", str(run)), "--K")
    K = tmp_path / "K.yaml"
    write_intrinsics_yaml(K, Intrinsics(100.0, 100.0, 47.5, 47.5, 96, 96))
    assert len(records(invoke(str(square), "--checkpoint", str(run), "--K", str(K)))) == 1


def test_default_checkpoint_is_newest_run(run: Path, synth_scene: Path, tmp_path: Path,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    img = str(synth_scene / "seq-03" / "frame-000000.color.png")
    monkeypatch.chdir(tmp_path)
    assert_user_error(invoke(img), "runs")
    copy_run(run, tmp_path / "runs" / "office")
    assert len(records(invoke(img))) == 1


def test_bad_inputs(run: Path, synth_scene: Path, tmp_path: Path) -> None:
    img = str(synth_scene / "seq-03" / "frame-000000.color.png")
    assert_user_error(invoke(img, "--checkpoint", str(tmp_path / "nope")), "does not exist")
    (tmp_path / "empty_run").mkdir()
    assert_user_error(invoke(img, "--checkpoint", str(tmp_path / "empty_run")), "no checkpoint")
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    assert_user_error(invoke(str(broken), "--checkpoint", str(run)), "cannot read image")
    assert_user_error(invoke(str(tmp_path / "missing.png"), "--checkpoint", str(run)), "does not exist")
    empty = tmp_path / "empty.mp4"
    writer = cv2.VideoWriter(str(empty), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (128, 96))
    writer.release()
    assert_user_error(invoke(str(empty), "--checkpoint", str(run)), "video")
    (tmp_path / "no_images").mkdir()
    assert_user_error(invoke(str(tmp_path / "no_images"), "--checkpoint", str(run)), "no images")
    bad_format = invoke(img, "--checkpoint", str(run), "--format", "xml")  # a choice: usage error
    assert bad_format.exit_code == 2 and "xml" in bad_format.output and "json" in bad_format.output
    assert_user_error(invoke(img, "--checkpoint", str(run), "--device", "gpu"), "--device", "cuda:N")


def test_json_lines_stream_per_batch(run: Path, folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each batch's lines are handed out before the next batch is predicted."""
    from relocdepth.localize import LocalizeConfig, localize
    from relocdepth.predictor import Predictor

    events: list[str] = []
    real = Predictor.predict

    def predict(self, *args, **kwargs):
        events.append("predict")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Predictor, "predict", predict)
    texts: list[str] = []
    records, text = localize([folder], LocalizeConfig(checkpoint=str(run), batch_size=4),
                             on_text=lambda t: (events.append("text"), texts.append(t)))
    assert events == ["predict", "text", "predict", "text"]
    assert [t.count("\n") for t in texts] == [4, FRAMES - 4]
    assert "".join(texts) == text
    assert [json.loads(line)["name"] for line in text.splitlines()] == [r["name"] for r in records]


def test_progress_lines_on_stderr_without_terminal(run: Path, video: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    from relocdepth import progress

    monkeypatch.setattr(progress, "PLAIN_EVERY_S", 0.0)
    res = invoke(str(video), "--checkpoint", str(run), "--batch-size", "4")
    assert len(records(res)) == FRAMES
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("localize:")]
    assert [ln.split(",")[0] for ln in lines] == [f"localize: 4/{FRAMES} images (67%)",
                                                  f"localize: {FRAMES}/{FRAMES} images (100%)"]
    assert all("localize" not in ln for ln in res.stdout.splitlines())  # stdout: poses only


def test_depth_png_scale(run: Path, folder: Path, tmp_path: Path) -> None:
    """depth PNG x depth_scale = the networks' depth; x the Sim(3) scale (metres) when aligned."""
    from relocdepth.checkpoint import save_alignment
    from relocdepth.localize import read_image
    from relocdepth.predictor import Predictor
    from relocdepth.trajectory import sim3_to_dict

    img_path = folder / "frame-000002.color.png"
    img = read_image(img_path)
    predictor = Predictor.from_checkpoint(str(run))
    pred = predictor.predict([img], [predictor.intrinsics_for(img.shape[1], img.shape[0])],
                             with_depth=True)
    net_depth = cv2.resize(pred.depth[0], (img.shape[1], img.shape[0]), interpolation=cv2.INTER_LINEAR)
    assert float(net_depth.max()) < 60.0  # fits a uint16 in millimetres even x 1.7

    aligned_run = copy_run(run, tmp_path / "aligned")
    scale = 1.7
    save_alignment(aligned_run, sim3_to_dict(scale, np.eye(3), np.zeros(3)))
    for which, expect in ((run, net_depth), (aligned_run, scale * net_depth)):
        out = tmp_path / f"depth-{which.name}"
        rec = records(invoke(str(img_path), "--checkpoint", str(which), "--depth-out", str(out)))[0]
        png = cv2.imread(rec["depth_png"], cv2.IMREAD_UNCHANGED)
        assert png.dtype == np.uint16 and png.shape == expect.shape
        assert rec["depth_scale"] == 0.001  # millimetres
        np.testing.assert_allclose(png * rec["depth_scale"], expect, atol=0.0005 + 1e-9)
        assert rec["units"] == ("m" if which == aligned_run else "network")


def test_refine_against_the_training_frames(run: Path, folder: Path, synth_shards: Path,
                                            tmp_path: Path) -> None:
    """--refine SHARDS: each line says how many pairs agreed and what placed it; a frame placed by
    nothing ("none": under the agreeing pairs needed, no trusted alignment) keeps the network's
    pose, the others move; a missing dataset is a one-line error."""
    run = copy_run(run, tmp_path / "run")  # --refine stores its map with the run
    plain = records(invoke(str(folder), "--checkpoint", str(run)))
    # a network trained for one step: its poses agree rarely, so also 1; alignment on and off
    moved = 0
    for need, align in ((2, "--no-refine-align"), (1, "--no-refine-align"), (2, "--refine-align")):
        refined = records(invoke(str(folder), "--checkpoint", str(run), "--refine", str(synth_shards),
                                 "--refine-min-pairs", str(need), align))
        assert len(refined) == len(plain) == FRAMES
        for p, r in zip(plain, refined):
            assert 0 <= r["refined_pairs"] <= 3 and "refined_pairs" not in p
            assert r["refined_by"] in (("pairs", "none") if align == "--no-refine-align" else REFINED_BY)
            assert (r["refined_by"] == "pairs") == (r["refined_pairs"] >= need) or r["refined_by"] == "aligned"
            R = np.array(r["T_wc"])[:3, :3]
            np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)
            same = np.allclose(r["T_wc"], p["T_wc"], atol=1e-9)
            assert same == (r["refined_by"] == "none"), r
            moved += not same
    assert moved > 0
    assert_user_error(invoke(str(folder), "--checkpoint", str(run), "--refine", str(folder.parent / "nope")),
                      "nope")
    bad = invoke(str(folder), "--checkpoint", str(run), "--refine", str(synth_shards), "--refine-matcher", "orb")
    assert bad.exit_code == 2 and "orb" in bad.output and not bad.stdout.startswith("{")


def test_refine_map_takes_the_runs_anchors_when_it_has_them(run: Path, folder: Path, synth_shards: Path,
                                                             tmp_path: Path) -> None:
    """--refine-map auto (the default) and anchors refine against the run's anchors, in the shards'
    order, without predicting the training frames; network against the network's poses; anchors
    asked of a run that has none is one error line."""
    from relocdepth.localize import training_refiner
    from relocdepth.predictor import Predictor
    from relocdepth.refine import MAP_NAME, RefineConfig

    anchored, anchors = with_anchors(run, synth_shards, tmp_path / "run", (1.0, np.eye(3), np.zeros(3)))
    predictor = Predictor.from_checkpoint(anchored)
    for which in ("auto", "anchors"):
        refiner = training_refiner(predictor, synth_shards, RefineConfig(), which)
        np.testing.assert_allclose(refiner.ref.T_wc, anchors, atol=1e-6)
    assert not (anchored / "checkpoints" / MAP_NAME).exists()  # the network's poses were not asked for
    refiner = training_refiner(predictor, synth_shards, RefineConfig(), "network")
    assert not np.allclose(refiner.ref.T_wc, anchors, atol=1e-3) and (anchored / "checkpoints" / MAP_NAME).exists()
    lines = records(invoke(str(folder), "--checkpoint", str(anchored), "--refine", str(synth_shards),
                           "--refine-map", "anchors"))
    assert len(lines) == FRAMES and all(r["refined_by"] in REFINED_BY for r in lines)
    assert_user_error(invoke(str(folder), "--checkpoint", str(run), "--refine", str(synth_shards),
                             "--refine-map", "anchors"), "holds no anchors")


def test_poses_refined_against_the_anchors_take_their_alignment(run: Path, folder: Path, synth_shards: Path,
                                                                 tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """After `evaluate --save-alignment` on a run with anchors (the true training poses moved by a
    known similarity), a pose refined against the anchors is aligned by the anchors' Sim(3): a
    refinement that finds the true pose in the anchors' world prints the true pose, metric; a pose
    the refinement left at the network's is aligned by the network's, as without --refine. An
    alignment stored without the anchors' aligns both by the network's."""
    from relocdepth.checkpoint import save_alignment
    from relocdepth.eval_geometry import apply_sim3
    from relocdepth.localize import read_image
    from relocdepth.predictor import Predictor
    from relocdepth.refine import Refined, Refiner
    from relocdepth.trajectory import apply_sim3_dict

    sim3 = (2.5, cv2.Rodrigues(np.radians([10.0, -30.0, 5.0]))[0], np.array([0.4, -1.0, 2.0]))
    anchored, _ = with_anchors(run, synth_shards, tmp_path / "run", sim3)
    res = CliRunner().invoke(app, ["evaluate", str(synth_shards), "--checkpoint", str(anchored),
                                   "-o", str(tmp_path / "report.json"), "--save-alignment"])
    assert res.exit_code == 0, res.output
    truth = {read_image(folder / f"frame-{i:06d}.color.png").tobytes():
             (i, np.loadtxt(folder / f"frame-{i:06d}.pose.txt")) for i in range(FRAMES)}

    def refine(self: Refiner, image: np.ndarray, intrinsics, T_wc: np.ndarray) -> Refined:
        i, T_gt = truth[image.tobytes()]
        if i % 2:
            return Refined(T_wc, 0, "none")
        return Refined(apply_sim3(*sim3, T_gt[None])[0], 2, "aligned")

    monkeypatch.setattr(Refiner, "refine", refine)
    plain = records(invoke(str(folder), "--checkpoint", str(anchored)))
    refined = records(invoke(str(folder), "--checkpoint", str(anchored), "--refine", str(synth_shards)))
    assert len(refined) == FRAMES and all(r["units"] == "m" for r in refined)
    for i, (p, r) in enumerate(zip(plain, refined)):
        if i % 2:
            assert r["refined_by"] == "none" and np.allclose(r["T_wc"], p["T_wc"], atol=1e-9)
        else:
            assert r["refined_by"] == "aligned"
            np.testing.assert_allclose(np.array(r["T_wc"]), np.loadtxt(folder / f"frame-{i:06d}.pose.txt"), atol=1e-4)
    # an alignment stored before the anchors' was: both kinds of pose by the network's
    align = Predictor.from_checkpoint(anchored).alignment
    save_alignment(anchored, {k: v for k, v in align.items() if k != "anchors"})
    older = records(invoke(str(folder), "--checkpoint", str(anchored), "--refine", str(synth_shards)))
    for i, r in enumerate(older):
        T_anchor = apply_sim3(*sim3, np.loadtxt(folder / f"frame-{i:06d}.pose.txt")[None])
        expect = plain[i]["T_wc"] if i % 2 else apply_sim3_dict(align, T_anchor)[0]
        np.testing.assert_allclose(np.array(r["T_wc"]), expect, atol=1e-6)


def test_refine_map_is_stored_with_the_run(run: Path, folder: Path, synth_shards: Path, tmp_path: Path,
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """The map's training poses are predicted once per checkpoint and shards; a checkpoint file
    that changed, or an unreadable map file, makes it predicted again."""
    import os

    import relocdepth.localize as L

    run = copy_run(run, tmp_path / "run")
    (run / "checkpoints" / "refine-map.npz").unlink(missing_ok=True)
    calls = []
    real = L.predict_poses
    monkeypatch.setattr(L, "predict_poses", lambda *a, **k: calls.append(1) or real(*a, **k))
    args = (str(folder), "--checkpoint", str(run), "--refine", str(synth_shards), "--refine-min-pairs", "1")
    first = records(invoke(*args))
    stored = run / "checkpoints" / "refine-map.npz"
    assert stored.is_file() and len(calls) == 1
    again = records(invoke(*args))
    assert len(calls) == 1  # from the stored map
    assert [r["T_wc"] for r in again] == [r["T_wc"] for r in first]
    ckpt = sorted((run / "checkpoints").glob("ckpt-*.pt"))[-1]
    st = ckpt.stat()
    os.utime(ckpt, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # the checkpoint changed
    records(invoke(*args))
    assert len(calls) == 2
    stored.write_bytes(b"not a map")
    assert [r["T_wc"] for r in records(invoke(*args))] == [r["T_wc"] for r in first]
    assert len(calls) == 3
