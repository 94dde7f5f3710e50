"""Pair parallax: geometry on rendered pairs, the stored table, adding it later, the sampler option
through the trainer and the CLI, and agreement with the ground-truth depth part of the warp."""

from __future__ import annotations

import hashlib
import importlib.util
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from relocdepth.cli.main import app
from relocdepth.ingest.parallax import ParallaxConfig, pair_parallax, track_image
from relocdepth.ingest.run import IngestConfig, ingest
from typer.testing import CliRunner

from relocdepth.camera import Intrinsics
from relocdepth.dataset import open_dataset, read_parallax, verify
from relocdepth.errors import UserError
from relocdepth.synth import SynthConfig, build_scene, camera_paths, generate_scene, render

runner = CliRunner()
OFFSETS = ParallaxConfig().offsets

_spec = importlib.util.spec_from_file_location(
    "quality_parallax", Path(__file__).resolve().parents[1] / "benchmarks" / "quality" / "parallax.py")
quality_parallax = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(quality_parallax)


def _png(rgb: np.ndarray) -> bytes:
    return cv2.imencode(".png", rgb[:, :, ::-1])[1].tobytes()


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _rank_corr(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's rank correlation (no ties in continuous data)."""
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    return float(np.corrcoef(ra, rb)[0, 1])


@pytest.fixture(scope="module")
def parallax_shards(synth_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The synth scene ingested with pair parallax (read-only)."""
    out = tmp_path_factory.mktemp("pshards") / "shards"
    ingest([synth_scene], out, IngestConfig(shard_size=16, pair_parallax=True), progress=False)
    return out


# -- geometry ------------------------------------------------------------------------------------
def test_rotation_gives_no_parallax_translation_does() -> None:
    """Turning about the camera centre moves every pixel by a homography: ~0 px left over. The
    same turn plus a sideways step leaves depth-dependent motion, growing with the step, of the
    size of the ground-truth depth part of the warp."""
    intr = Intrinsics(262.5, 262.5, 159.5, 119.5, 320, 240)
    cfg_s = SynthConfig(seed=0, frames=2, width=320, height=240)
    scene = build_scene(0, cfg_s)
    T_a = camera_paths(cfg_s)["seq-01"][0]
    rgb_a, depth_a = render(scene, T_a, intr)
    cfg = ParallaxConfig()
    img_a = track_image(_png(rgb_a), cfg)
    assert img_a.scale == 2.0  # stored px per tracking px (320 -> 160)
    for turn in ([2.0, -3.0, 1.0], [0.0, 6.0, 0.0]):
        T_rot = T_a.copy()
        T_rot[:3, :3] = T_a[:3, :3] @ cv2.Rodrigues(np.radians(turn))[0]
        still = pair_parallax(img_a, track_image(_png(render(scene, T_rot, intr)[0]), cfg), cfg)
        assert still < 0.2, still
        last = still
        for step in (0.04, 0.08, 0.15):
            T_move = T_rot.copy()
            T_move[:3, 3] += T_a[:3, :3] @ np.array([step, 0.0, 0.0])  # along the camera's x axis
            moved = pair_parallax(img_a, track_image(_png(render(scene, T_move, intr)[0]), cfg), cfg)
            depth_part, _ = quality_parallax.depth_flow(intr.K(), depth_a.astype(np.float64), T_a, T_move)
            truth = float(np.median(depth_part))
            # within 3x of the truth: the homography absorbs the dominant plane, so near clutter in front of a
            # wall reads low (0.39x at a 6 deg turn and 15 cm step on the demo scene)
            assert truth / 3 < moved < 2.0 * truth, (turn, step, moved, truth)
            assert moved > last
            last = moved
    blank = track_image(_png(np.zeros((240, 320, 3), np.uint8)), cfg)  # nothing to track
    assert np.isnan(pair_parallax(img_a, blank, cfg))


# -- the stored table ----------------------------------------------------------------------------
def test_ingest_stores_a_verified_table(parallax_shards: Path, tmp_path: Path) -> None:
    ds = open_dataset(parallax_shards)
    entry = ds.manifest["parallax"]
    path = parallax_shards / entry["file"]
    assert entry["sha256"] == _sha(path) and entry["bytes"] == path.stat().st_size
    table = read_parallax(ds)
    per_seq = {s["name"]: s["frames"] for s in ds.manifest["sequences"]}
    expected = sum(n - k for n in per_seq.values() for k in OFFSETS if k < n)
    assert len(table["key"]) == entry["pairs"] == expected
    frames = {r.key: (r.sequence, r.frame) for r in ds.records}
    order = {s: [r.frame for r in ds.records if r.sequence == s] for s in per_seq}
    for key, seq, frame, k, frame_b in zip(table["key"], table["sequence"], table["frame"],
                                           table["offset"], table["frame_b"]):
        assert frames[key] == (seq, frame)
        assert order[seq][order[seq].index(frame) + k] == frame_b  # the k-th stored frame after
    finite = table["parallax_px"][np.isfinite(table["parallax_px"])]
    assert len(finite) > 0.5 * expected and finite.min() >= 0
    assert verify(ds) == len(ds.manifest["shards"])
    # A changed table no longer matches the manifest.
    bad = tmp_path / "bad"
    shutil.copytree(parallax_shards, bad)
    with open(bad / entry["file"], "ab") as f:
        f.write(b"x")
    with pytest.raises(UserError, match="parallax"):
        verify(open_dataset(bad))


def test_ingest_option_through_the_cli(synth_scene: Path, tmp_path: Path) -> None:
    out = tmp_path / "shards"
    res = runner.invoke(app, ["ingest", str(synth_scene), "-o", str(out), "--pair-parallax"])
    assert res.exit_code == 0, res.output
    pairs = open_dataset(out).manifest["parallax"]["pairs"]
    assert f"{pairs} parallax pairs" in res.output
    res = runner.invoke(app, ["inspect", str(out)])
    assert res.exit_code == 0 and "offset  16: median" in res.output and "offset  32" not in res.output


def test_add_parallax_to_an_existing_dataset(synth_scene: Path, parallax_shards: Path, tmp_path: Path) -> None:
    out = tmp_path / "plain"
    res = runner.invoke(app, ["ingest", str(synth_scene), "-o", str(out), "--shard-size", "16",
                              "--no-pair-parallax"])
    assert res.exit_code == 0, res.output
    assert "parallax" not in open_dataset(out).manifest
    res = runner.invoke(app, ["inspect", str(out)])
    assert res.exit_code == 0 and "--add-parallax" in res.output  # says how to add it
    before = {p.name: _sha(p) for p in out.iterdir() if p.suffix in (".tar", ".parquet")}
    res = runner.invoke(app, ["inspect", str(out), "--add-parallax", "--verify"])
    assert res.exit_code == 0, res.output
    for k in OFFSETS[:5]:  # 24 frames: offsets up to 16
        assert f"offset {k:3d}: median" in res.output
    assert "verify: " in res.output
    after = {p.name: _sha(p) for p in out.iterdir() if p.suffix in (".tar", ".parquet")}
    assert {n: h for n, h in after.items() if n in before} == before  # shards and index untouched
    ds = open_dataset(out)
    added, stored = read_parallax(ds), read_parallax(open_dataset(parallax_shards))
    for col in ("key", "offset", "frame_b"):
        assert list(added[col]) == list(stored[col])
    np.testing.assert_allclose(added["parallax_px"], stored["parallax_px"], atol=1e-9)  # same estimate
    # Adding again replaces the table: one table file, listed, nothing left behind.
    assert runner.invoke(app, ["inspect", str(out), "--add-parallax"]).exit_code == 0
    tables = [p.name for p in out.iterdir() if "parallax" in p.name]
    assert tables == [open_dataset(out).manifest["parallax"]["file"]]


# -- training -------------------------------------------------------------------------------------
def test_min_parallax_without_data_is_one_error_line(synth_scene: Path, tmp_path: Path) -> None:
    plain = tmp_path / "plain"
    ingest([synth_scene], plain, IngestConfig(pair_parallax=False), progress=False)
    run = tmp_path / "run"
    res = runner.invoke(app, ["train", str(plain), "-o", str(run), "--min-parallax", "1.5",
                              "--size", "128x96", "--pretrained", "none", "--workers", "0", "--no-progress"])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "--add-parallax" in lines[0], res.output
    assert not run.exists()


def test_trainer_samples_with_parallax_at_the_training_size(parallax_shards: Path, tmp_path: Path) -> None:
    from relocdepth.train import TrainConfig, setup

    cfg = TrainConfig.from_dict({"size": (256, 192), "batch_size": 1, "pretrained": None,
                                 "workers": 0, "progress": False, "min_parallax": 1.0})
    tr, _ = setup(parallax_shards, tmp_path / "run", cfg)
    tr.log.close()
    ds = open_dataset(parallax_shards)
    table = read_parallax(ds)
    train_keys = [r.key for r in ds.frames("train")]
    stored = {(k, int(o)): v for k, o, v in zip(table["key"], table["offset"], table["parallax_px"])}
    px = tr.sampler.parallax
    for i, key in enumerate(train_keys):
        for j, k in enumerate(px.offsets):
            want = stored.get((key, int(k)), np.nan) * 256 / 128  # stored at 128 px wide
            assert (np.isnan(want) and np.isnan(px.px[i, j])) or px.px[i, j] == pytest.approx(want)
    for t in list(tr.sampler.iter_epoch(0))[:20]:
        assert len({t.source_a, t.target, t.source_b}) == 3


# -- against ground truth -------------------------------------------------------------------------
@pytest.mark.slow
def test_rank_agrees_with_the_ground_truth_depth_part_of_the_warp(tmp_path: Path) -> None:
    """Over all stored pairs of a rendered scene (3 x 60 frames, 160x120), the estimate ranks
    pairs like the ground-truth depth part of the warp (benchmarks/quality/parallax.py: pixels
    moved when true depth replaces the frame's median depth)."""
    scene = tmp_path / "scene"
    generate_scene(scene, SynthConfig(seed=0, frames=60, width=160, height=120))
    shards = tmp_path / "shards"
    ingest([scene], shards, IngestConfig(pair_parallax=True), progress=False)
    ds = open_dataset(shards)
    table = read_parallax(ds)
    recs = {(r.sequence, r.frame): r for r in ds.records}
    est, gt = [], []
    for seq, frame, frame_b, px in zip(table["sequence"], table["frame"], table["frame_b"],
                                       table["parallax_px"]):
        if not np.isfinite(px):
            continue
        a, b = recs[(seq, int(frame))], recs[(seq, int(frame_b))]
        depth_part, _ = quality_parallax.depth_flow(a.intrinsics.K(), ds.read_depth(a).astype(np.float64),
                                                    ds.read_pose(a), ds.read_pose(b))
        est.append(px)
        gt.append(np.median(depth_part))
    assert len(est) > 0.6 * len(table["key"])
    rho = _rank_corr(np.array(est), np.array(gt))
    print(f"Spearman rank correlation with the ground-truth depth part: {rho:.3f} over {len(est)} pairs")
    assert rho >= 0.7
