"""Ingest round trips: 7-Scenes (synth scene), videos, image folders -> shards -> reader/webdataset."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import webdataset as wds
import yaml
from ingest_fixtures import write_images, write_K, write_sevenscenes, write_video
from relocdepth.cli.main import app
from relocdepth.schemas import validate
from typer.testing import CliRunner

from relocdepth.dataset import open_dataset

runner = CliRunner()
# The project's shared real data, beside the repository (CI lays a copy of shared/ there too).
HOLOLENS = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "hololens-office"


def reloc(*args) -> object:
    result = runner.invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, result.output
    return result


def read_back(out: Path) -> dict[str, dict]:
    """Every sample through plain webdataset, by key."""
    urls = [str(out / s["name"]) for s in json.loads((out / "manifest.json").read_text())["shards"]]
    return {s["__key__"]: s for s in wds.WebDataset(urls, shardshuffle=False)}


def test_synth_scene_round_trip(synth_scene: Path, synth_shards: Path) -> None:
    ds = open_dataset(synth_shards)
    validate("manifest", ds.manifest)
    K = yaml.safe_load((synth_scene / "intrinsics.yaml").read_text())
    seqs = sorted(p.name for p in synth_scene.glob("seq-*"))
    files = {s: sorted((synth_scene / s).glob("frame-*.color.png")) for s in seqs}
    assert len(ds) == sum(len(v) for v in files.values()) == ds.manifest["totals"]["frames"]
    assert ds.sequences() == seqs
    train = {ln.strip() for ln in (synth_scene / "TrainSplit.txt").read_text().split()}
    samples = read_back(synth_shards)
    assert list(samples) == [r.key for r in ds.records]  # webdataset order == index order
    for r in ds.records:
        src = synth_scene / r.sequence / f"frame-{r.frame:06d}"
        assert r.key == f"{r.sequence}-{r.frame:06d}"
        assert r.split == ("train" if f"sequence{int(r.sequence[4:])}" in train else "test")
        assert r.timestamp == pytest.approx(r.frame / 30.0)
        assert r.intrinsics.to_dict() == pytest.approx({k: K[k] for k in r.intrinsics.to_dict()})
        # byte identity, through the reader (offsets) and through webdataset
        assert ds.read_image_bytes(r) == Path(f"{src}.color.png").read_bytes() == samples[r.key]["png"]
        assert samples[r.key]["depth.png"] == Path(f"{src}.depth.png").read_bytes()
        assert samples[r.key]["pose.txt"] == Path(f"{src}.pose.txt").read_bytes()
        meta = ds.read_meta(r)  # validates the frame schema
        assert json.loads(samples[r.key]["json"]) == meta
    r = ds.records[0]
    assert np.allclose(ds.read_pose(r), np.loadtxt(synth_scene / "seq-01" / "frame-000000.pose.txt"))
    depth_mm = cv2.imread(str(synth_scene / "seq-01" / "frame-000000.depth.png"), cv2.IMREAD_UNCHANGED)
    assert np.allclose(ds.read_depth(r), depth_mm / 1000.0)
    assert ds.read_image(r).shape == (K["height"], K["width"], 3)
    assert {s["name"]: s["split"] for s in ds.manifest["sequences"]}["seq-03"] == "test"
    # a shard never mixes sequences, and frames of a sequence are in order
    by_shard: dict[str, set] = {}
    for r in ds.records:
        by_shard.setdefault(r.shard, set()).add(r.sequence)
    assert all(len(v) == 1 for v in by_shard.values())
    for s in seqs:
        idx = [r.frame for r in ds.records if r.sequence == s]
        assert idx == sorted(idx)
    assert all(s["samples"] <= 16 for s in ds.manifest["shards"])


def test_resize_and_stride(synth_scene: Path, tmp_path: Path) -> None:
    out = tmp_path / "small"
    reloc("ingest", synth_scene, "-o", out, "--resize", "64x48", "--stride", "5", "--name", "tiny")
    ds = open_dataset(out)
    K = yaml.safe_load((synth_scene / "intrinsics.yaml").read_text())
    assert ds.manifest["name"] == "tiny"
    assert [r.frame for r in ds.records if r.sequence == "seq-01"] == [0, 5, 10, 15, 20]
    r = ds.records[1]
    assert r.key == "seq-01-000005"
    intr = r.intrinsics
    assert (intr.width, intr.height) == (64, 48)
    assert intr.fx == pytest.approx(K["fx"] * 64 / K["width"])
    assert intr.cx == pytest.approx((K["cx"] + 0.5) * 64 / K["width"] - 0.5)
    assert ds.read_image(r).shape == (48, 64, 3)
    assert ds.read_depth(r).shape == (48, 64)
    assert ds.read_meta(r)["intrinsics"] == intr.to_dict()


def test_video_round_trip(tmp_path: Path) -> None:
    decoded_a = write_video(tmp_path / "walk a.mp4", frames=12, fps=10.0)
    write_video(tmp_path / "b.mp4", frames=6, fps=10.0)
    K = write_K(tmp_path / "K.yaml", size=(128, 96))  # calibrated at 2x: scaled to 64x48
    out = tmp_path / "shards"
    reloc("ingest", tmp_path / "walk a.mp4", tmp_path / "b.mp4", "--K", K, "--stride", "2", "-o", out,
          "--video-format", "png")
    ds = open_dataset(out)
    assert ds.sequences() == ["walk_a", "b"]
    a = [r for r in ds.records if r.sequence == "walk_a"]
    assert [r.frame for r in a] == [0, 2, 4, 6, 8, 10]
    assert [r.key for r in a][:2] == ["walk_a-000000", "walk_a-000002"]
    assert [r.timestamp for r in a] == pytest.approx([0.0, 0.2, 0.4, 0.6, 0.8, 1.0])
    assert len([r for r in ds.records if r.sequence == "b"]) == 3
    assert {r.split for r in ds.records} == {"train"}
    assert not any(r.has_depth or r.has_pose for r in ds.records)
    assert a[0].intrinsics.to_dict() == pytest.approx(
        {"fx": 30.0, "fy": 30.0, "cx": 31.5, "cy": 23.5, "width": 64, "height": 48}
    )
    for r in a:  # lossless: exactly the frames OpenCV decodes
        assert r.image_ext == "png"
        assert np.array_equal(ds.read_image(r), cv2.cvtColor(decoded_a[r.frame], cv2.COLOR_BGR2RGB))
    assert len(read_back(out)) == 9
    assert ds.manifest["sources"][0]["kind"] == "video"
    # default: JPEG (quality 95), close to the decoded frames
    reloc("ingest", tmp_path / "b.mp4", "--K", K, "-o", tmp_path / "jpg")
    ds = open_dataset(tmp_path / "jpg")
    assert [r.frame for r in ds.records] == list(range(6))
    r = ds.records[3]
    assert r.image_ext == "jpg" and ds.read_image_bytes(r)[:2] == b"\xff\xd8"
    ref = cv2.cvtColor(write_video(tmp_path / "b2.mp4", frames=6)[3], cv2.COLOR_BGR2RGB)
    assert np.abs(ds.read_image(r).astype(int) - ref.astype(int)).mean() < 4.0


def test_image_folder_round_trip(tmp_path: Path) -> None:
    names = ["img10.png", "img2.jpg", "img1.png", "img3.jpeg"]
    paths = write_images(tmp_path / "cam", names)
    (tmp_path / "cam" / "times.txt").write_text("img1.png 0.5\nimg2.jpg 0.75\nimg3.jpeg 1.0\nimg10.png 2.0\n")
    K = write_K(tmp_path / "K.yaml")
    out = tmp_path / "shards"
    reloc("ingest", tmp_path / "cam", "--K", K, "-o", out, "--split", "test", "--shard-size", "3")
    ds = open_dataset(out)
    order = ["img1.png", "img2.jpg", "img3.jpeg", "img10.png"]  # natural sort
    assert [Path(ds.read_meta(r)["source"]).name for r in ds.records] == order
    assert [r.frame for r in ds.records] == [0, 1, 2, 3]
    assert [r.timestamp for r in ds.records] == [0.5, 0.75, 1.0, 2.0]
    assert [r.image_ext for r in ds.records] == ["png", "jpg", "jpg", "png"]
    assert {r.split for r in ds.records} == {"test"}
    assert len(ds.manifest["shards"]) == 2
    by_name = {p.name: p for p in paths}
    for r, n in zip(ds.records, order):
        assert ds.read_image_bytes(r) == by_name[n].read_bytes()
    samples = read_back(out)
    assert samples["cam-000001"]["jpg"] == by_name["img2.jpg"].read_bytes()


def test_undistortion_and_opencv_calibration(tmp_path: Path) -> None:
    write_images(tmp_path / "cam", ["a.png", "b.png"])
    Kmat = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    dist = np.array([[-0.2, 0.05, 0.001, -0.001, 0.0]])
    fs = cv2.FileStorage(str(tmp_path / "calib.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 64)
    fs.write("image_height", 48)
    fs.write("camera_matrix", Kmat)
    fs.write("distortion_coefficients", dist)
    fs.release()
    out = tmp_path / "shards"
    reloc("ingest", tmp_path / "cam", "--K", tmp_path / "calib.yml", "-o", out)
    ds = open_dataset(out)
    r = ds.records[0]
    assert r.intrinsics.to_dict() == {"fx": 60.0, "fy": 60.0, "cx": 31.5, "cy": 23.5, "width": 64, "height": 48}
    src = cv2.imread(str(tmp_path / "cam" / "a.png"))
    expected = cv2.cvtColor(cv2.undistort(src, Kmat, dist, None, Kmat), cv2.COLOR_BGR2RGB)
    got = ds.read_image(r)
    assert ds.read_image_bytes(r) != (tmp_path / "cam" / "a.png").read_bytes()
    assert np.abs(got.astype(int) - expected.astype(int)).mean() < 2.0
    assert np.abs(got.astype(int) - src[..., ::-1].astype(int)).mean() > 5.0  # it did change
    # the project YAML with distortion, plus --resize: K scaled after undistortion
    write_K(tmp_path / "K.yaml", distortion=dist.ravel().tolist())
    reloc("ingest", tmp_path / "cam", "--K", tmp_path / "K.yaml", "-o", tmp_path / "s2", "--resize", "32x24")
    r2 = open_dataset(tmp_path / "s2").records[0]
    assert r2.intrinsics.to_dict() == pytest.approx(
        {"fx": 30.0, "fy": 30.0, "cx": 15.5, "cy": 11.5, "width": 32, "height": 24}
    )


def test_sevenscenes_root_scene_choice_and_default_intrinsics(tmp_path: Path) -> None:
    write_sevenscenes(tmp_path / "root" / "chess", {"seq-01": "train", "seq-02": "test"}, size=(64, 48))
    write_sevenscenes(tmp_path / "root" / "fire", {"seq-01": "train"}, size=(64, 48))
    res = runner.invoke(app, ["ingest", str(tmp_path / "root"), "-o", str(tmp_path / "x")])
    assert res.exit_code == 2 and "--scene" in res.output
    reloc("ingest", tmp_path / "root", "--scene", "chess", "-o", tmp_path / "x")
    ds = open_dataset(tmp_path / "x")
    assert ds.manifest["totals"] == {"frames": 8, "train": 4, "test": 4, "sequences": 2, "skipped": 0}
    # no intrinsics.yaml in the scene: the 7-Scenes RGB camera, scaled from 640x480 to 64x48
    assert ds.records[0].intrinsics.to_dict() == pytest.approx(
        {"fx": 52.5, "fy": 52.5, "cx": 31.55, "cy": 23.55, "width": 64, "height": 48}
    )
    assert all(r.has_depth and r.has_pose for r in ds.records)
    assert ds.read_pose(ds.records[1])[0, 3] == pytest.approx(0.01)
    assert ds.read_pose(ds.records[5])[2, 3] == pytest.approx(1.0)


def test_corrupt_frame_skipped_or_strict(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    write_images(tmp_path / "cam", ["0.png", "1.png", "2.png"])
    bad = tmp_path / "cam" / "1.png"
    bad.write_bytes(bad.read_bytes()[:100])  # truncated
    K = write_K(tmp_path / "K.yaml")
    res = runner.invoke(app, ["ingest", str(tmp_path / "cam"), "--K", str(K), "-o", str(tmp_path / "s")])
    assert res.exit_code == 0, res.output
    m = open_dataset(tmp_path / "s").manifest
    assert m["totals"]["frames"] == 2 and m["totals"]["skipped"] == 1
    assert m["skipped"][0]["source"].endswith("1.png") and "truncated" in m["skipped"][0]["reason"]
    assert any("1 corrupt frame" in rec.message for rec in caplog.records)
    res = runner.invoke(app, ["ingest", str(tmp_path / "cam"), "--K", str(K), "-o", str(tmp_path / "t"), "--strict"])
    assert res.exit_code == 2 and "1.png" in res.output
    assert not (tmp_path / "t").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["K.yaml", "cam", "s"]  # no temp folder left


def test_force_replaces_and_inspect_verify_catches_tampering(tmp_path: Path) -> None:
    write_sevenscenes(tmp_path / "scene", {"seq-01": "train", "seq-02": "test"})
    out = tmp_path / "shards"
    reloc("ingest", tmp_path / "scene", "-o", out, "--shard-size", "3")
    reloc("ingest", tmp_path / "scene", "-o", out, "--shard-size", "2", "--force")
    assert len(open_dataset(out).manifest["shards"]) == 4
    res = reloc("inspect", out, "--verify")
    assert "seq-01: 4 frames, train" in res.output and "verify: 4 shard(s)" in res.output
    shard = out / "shard-000001.tar"
    data = bytearray(shard.read_bytes())
    data[700] ^= 0xFF
    shard.write_bytes(bytes(data))
    res = runner.invoke(app, ["inspect", str(out), "--verify"])
    assert res.exit_code == 2
    err = [ln for ln in res.output.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "shard-000001.tar" in err[0] and "sha256" in err[0]


def test_reader_refuses_incomplete_or_invalid(tmp_path: Path) -> None:
    from relocdepth.errors import UserError

    write_sevenscenes(tmp_path / "scene", {"seq-01": "train"}, frames=2)
    out = tmp_path / "shards"
    reloc("ingest", tmp_path / "scene", "-o", out)
    m = json.loads((out / "manifest.json").read_text())
    m["totals"]["frames"] = "two"
    (out / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(UserError, match="totals/frames"):
        open_dataset(out)
    (out / "manifest.json").unlink()
    with pytest.raises(UserError, match="no manifest.json"):
        open_dataset(out)
    with pytest.raises(UserError, match="not found"):
        open_dataset(tmp_path / "nope")


def test_real_hololens_folder(tmp_path: Path) -> None:
    if not (HOLOLENS / "images").is_dir():
        pytest.fail(f"the shared real data is missing: {HOLOLENS} (../shared/data/hololens-office "
                    "from the repository root)")
    K = np.loadtxt(HOLOLENS / "K.txt")
    kfile = tmp_path / "K.yaml"
    kfile.write_text(yaml.safe_dump({
        "fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
        "width": 540, "height": 360,
    }))
    out = tmp_path / "shards"
    reloc("ingest", HOLOLENS / "images", "--K", kfile, "-o", out)
    ds = open_dataset(out)
    files = sorted((HOLOLENS / "images").iterdir())
    assert len(ds) == 120 == len(files)
    assert [Path(ds.read_meta(r)["source"]).name for r in ds.records] == [p.name for p in files]
    assert ds.records[0].intrinsics.fx == pytest.approx(K[0, 0])
    assert (ds.records[0].intrinsics.width, ds.records[0].intrinsics.height) == (540, 360)
    assert ds.read_image_bytes(ds.records[-1]) == files[-1].read_bytes()
    assert ds.read_image(ds.records[0]).shape == (360, 540, 3)
