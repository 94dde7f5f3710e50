"""Shards read by webdataset's ``wids``; ``reloc localize`` reading videos and removing distortion
exactly as ingest does; the calibration file formats the README lists."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from ingest_fixtures import write_images, write_K, write_video
from relocdepth.ingest.intrinsics import load_calibration
from relocdepth.ingest.run import IngestConfig, ingest

from relocdepth.dataset import open_dataset
from relocdepth.localize import Calibrated, expand_inputs, iter_frames


def test_wids_reads_the_shards(synth_shards: Path, tmp_path: Path) -> None:
    import wids  # a test extra (pip install -e '.[test]'): webdataset 1.x no longer ships it
    ds = open_dataset(synth_shards)
    desc = json.loads((synth_shards / "wids.json").read_text())
    assert [s["url"] for s in desc["shardlist"]] == [s["name"] for s in ds.manifest["shards"]]
    wd = wids.ShardListDataset(str(synth_shards / "wids.json"), cache_dir=str(tmp_path / "cache"),
                               transformations=[])
    assert len(wd) == len(ds)
    for i in (0, 17, len(ds) - 1):  # first, mid-shard, last of another shard
        sample, rec = wd[i], ds.records[i]
        assert sample["__key__"] == rec.key
        assert sample[".png"].read() == ds.read_image_bytes(rec)
        assert json.loads(sample[".json"].read()) == ds.read_meta(rec)
        pose = np.array(sample[".pose.txt"].read().split(), dtype=np.float64).reshape(4, 4)
        assert np.array_equal(pose, ds.read_pose(rec))


@pytest.mark.parametrize("name", ["walk.mp4", "walk.ts"])
def test_localize_reads_a_video_as_ingest_does(tmp_path: Path, name: str) -> None:
    # an MPEG-TS stream reports a frame rate of 15 for these 7.5 fps frames: only the container's
    # timestamps are right, and they are what ingest stores
    video = tmp_path / name
    write_video(video, frames=8, fps=7.5)
    ingest([video], tmp_path / "s", IngestConfig(intrinsics=str(write_K(tmp_path / "K.yaml")),
                                                 video_format="png"), progress=False)
    ds = open_dataset(tmp_path / "s")
    frames = list(iter_frames(expand_inputs([video])))
    assert [f.timestamp for f in frames] == [r.timestamp for r in ds.records]
    assert [f.timestamp for f in frames] == pytest.approx(np.arange(8) / 7.5, abs=1e-3)
    assert [f.name for f in frames] == [f"walk-{r.frame:06d}" for r in ds.records]
    for f, r in zip(frames, ds.records):
        assert np.array_equal(f.image, ds.read_image(r))  # lossless shards: the same decoded pixels


def test_localize_undistorts_as_ingest_does(tmp_path: Path) -> None:
    write_images(tmp_path / "cam", ["a.png"], size=(64, 48))
    dist = [-0.25, 0.08, 0.002, -0.001, 0.0]
    calib = write_K(tmp_path / "K.yaml", size=(128, 96), distortion=dist)  # calibrated at 2x
    ingest([tmp_path / "cam"], tmp_path / "s", IngestConfig(intrinsics=str(calib)), progress=False)
    ds = open_dataset(tmp_path / "s")
    (frame,) = list(iter_frames(expand_inputs([tmp_path / "cam" / "a.png"])))
    image, K = Calibrated(calib).apply(frame.image)
    stored = ds.read_image(ds.records[0])
    assert K == ds.records[0].intrinsics
    assert np.array_equal(image, stored)  # PNG is lossless: identical pixels, not just close
    assert np.abs(image.astype(int) - frame.image.astype(int)).mean() > 5.0  # distortion was removed


K_VALUES = {"fx": 60.0, "fy": 61.0, "cx": 31.5, "cy": 23.5, "width": 64, "height": 48}
DIST = (-0.2, 0.05, 0.001, -0.001, 0.0)
OPENCV_YAML_BODY = """---
image_width: 64
image_height: 48
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 60., 0., 31.5, 0., 61., 23.5, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ -0.2, 0.05, 0.001, -0.001, 0. ]
"""
CALIBRATION_FILES = {
    # what OpenCV 4's calibration tools write
    "opencv4.yml": "%YAML:1.0\n" + OPENCV_YAML_BODY,
    # what OpenCV 5 writes
    "opencv5.yml": "%YAML 1.2\n" + OPENCV_YAML_BODY,
    "opencv.xml": """<?xml version="1.0"?>
<opencv_storage>
<image_width>64</image_width>
<image_height>48</image_height>
<camera_matrix type_id="opencv-matrix">
  <rows>3</rows>
  <cols>3</cols>
  <dt>d</dt>
  <data>
    60. 0. 31.5 0. 61. 23.5 0. 0. 1.</data></camera_matrix>
<distortion_coefficients type_id="opencv-matrix">
  <rows>1</rows>
  <cols>5</cols>
  <dt>d</dt>
  <data>
    -0.2 0.05 0.001 -0.001 0.</data></distortion_coefficients>
</opencv_storage>
""",
    # ROS camera_calibration's ost.yaml
    "ros.yaml": """image_width: 64
image_height: 48
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [60.0, 0.0, 31.5, 0.0, 61.0, 23.5, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.2, 0.05, 0.001, -0.001, 0.0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
projection_matrix:
  rows: 3
  cols: 4
  data: [60.0, 0.0, 31.5, 0.0, 0.0, 61.0, 23.5, 0.0, 0.0, 0.0, 1.0, 0.0]
""",
}


@pytest.mark.parametrize("name", sorted(CALIBRATION_FILES))
def test_calibration_file_formats(tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    path.write_text(CALIBRATION_FILES[name])
    calib = load_calibration(path)
    assert calib.intrinsics.to_dict() == K_VALUES
    assert calib.distortion == pytest.approx(DIST)
    # and ingest takes it: frames at half the calibration size get K scaled, distortion removed
    write_images(tmp_path / "cam", ["a.png"], size=(32, 24))
    ingest([tmp_path / "cam"], tmp_path / "s", IngestConfig(intrinsics=str(path)), progress=False)
    rec = open_dataset(tmp_path / "s").records[0]
    assert rec.intrinsics.to_dict() == pytest.approx(
        {"fx": 30.0, "fy": 30.5, "cx": 15.5, "cy": 11.5, "width": 32, "height": 24})
    assert open_dataset(tmp_path / "s").read_image_bytes(rec) != (tmp_path / "cam" / "a.png").read_bytes()


def test_undistorter_matches_opencv_undistort() -> None:
    """The cached fixed-point maps agree with OpenCV's reference ``cv2.undistort`` (K kept)."""
    from relocdepth.ingest.intrinsics import Calibration
    from relocdepth.ingest.undistort import Undistorter

    from relocdepth.camera import Intrinsics

    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8), (5, 5), 1.5)
    cal = Calibration(Intrinsics(60.0, 61.0, 31.5, 23.5, 64, 48), DIST)
    got = Undistorter().apply(img, cal)
    ref = cv2.undistort(img, cal.intrinsics.K(), np.asarray(DIST))
    assert np.array_equal(got, ref)
    assert np.abs(got.astype(int) - img.astype(int)).mean() > 1.0
