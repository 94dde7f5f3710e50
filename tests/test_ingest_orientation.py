"""EXIF orientation: phone JPEGs tagged "rotate 90" are read as the sensor wrote them, everywhere,
so the pixels are always the ones the stored intrinsics describe; a mismatch is an error."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from ingest_fixtures import texture, with_exif_orientation, write_K
from relocdepth.cli.main import app
from typer.testing import CliRunner

from relocdepth.data import AugmentConfig, ImageFrames, TripletData
from relocdepth.dataset import open_dataset
from relocdepth.errors import UserError
from relocdepth.localize import iter_frames
from relocdepth.sampler import Triplet

SENSOR = (100, 60)  # width x height as the sensor wrote the pixels
ROTATE_90_CW = 6  # EXIF Orientation value a phone held upright writes
TRIPLET = Triplet(source_a=0, target=1, source_b=2, aug_seed=0, is_global=False, epoch=0, position=0)


def tagged_folder(folder: Path, n: int = 6) -> np.ndarray:
    """``n`` copies of one 100x60 JPEG tagged Orientation=6; returns its pixels (RGB) untagged."""
    folder.mkdir(parents=True)
    ok, buf = cv2.imencode(".jpg", texture(7, *SENSOR), [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    plain = buf.tobytes()
    tagged = with_exif_orientation(plain, ROTATE_90_CW)
    # the tag is real: OpenCV's default decode turns these pixels to 60x100
    assert cv2.imdecode(np.frombuffer(tagged, np.uint8), cv2.IMREAD_COLOR).shape == (100, 60, 3)
    for i in range(n):
        (folder / f"img{i}.jpg").write_bytes(tagged)
    return cv2.cvtColor(cv2.imdecode(np.frombuffer(plain, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def ingest(*args: object) -> None:
    res = CliRunner().invoke(app, ["ingest", *[str(a) for a in args]])
    assert res.exit_code == 0, res.output


@pytest.fixture()
def tagged_shards(tmp_path: Path) -> tuple[Path, np.ndarray]:
    sensor = tagged_folder(tmp_path / "phone")
    ingest(tmp_path / "phone", "--K", write_K(tmp_path / "K.yaml", size=SENSOR, f=80.0), "-o", tmp_path / "s")
    return tmp_path / "s", sensor


def test_ingest_and_dataset_read_see_the_sensor_pixels(tagged_shards, tmp_path: Path) -> None:
    out, sensor = tagged_shards
    ds = open_dataset(out)
    assert len(ds) == 6
    for r in ds.records:
        assert (r.intrinsics.width, r.intrinsics.height) == SENSOR
        assert ds.read_image_bytes(r) == (tmp_path / "phone" / f"img{r.frame}.jpg").read_bytes()  # tag kept
        assert np.array_equal(ds.read_image(r), sensor)  # 60 rows x 100 columns, not rotated


def test_resize_reencodes_the_sensor_pixels(tmp_path: Path) -> None:
    sensor = tagged_folder(tmp_path / "phone", n=2)
    ingest(tmp_path / "phone", "--K", write_K(tmp_path / "K.yaml", size=SENSOR), "--resize", "50x30",
           "-o", tmp_path / "s")
    ds = open_dataset(tmp_path / "s")
    got = ds.read_image(ds.records[0])
    expected = cv2.resize(sensor, (50, 30), interpolation=cv2.INTER_AREA)
    assert got.shape == (30, 50, 3)
    assert np.abs(got.astype(int) - expected.astype(int)).mean() < 3.0


def test_intrinsics_of_the_displayed_orientation_are_refused(tmp_path: Path) -> None:
    tagged_folder(tmp_path / "phone", n=2)
    res = CliRunner().invoke(app, ["ingest", str(tmp_path / "phone"), "--K",
                                   str(write_K(tmp_path / "K.yaml", size=(60, 100))), "-o", str(tmp_path / "s")])
    assert res.exit_code == 2 and "aspect ratio" in res.output
    assert not (tmp_path / "s").exists()


def test_training_read_keeps_the_stored_intrinsics(tagged_shards) -> None:
    out, sensor = tagged_shards
    frames = ImageFrames.open(out)
    assert np.array_equal(frames.read_image(0), sensor)
    item = TripletData(frames, AugmentConfig(96, 64, scale_max=1.0))[TRIPLET]
    assert "skipped" not in item, item
    # the whole 100x60 image resized to 96x64: K follows that resize, at the sensor's aspect
    stored = open_dataset(out).records[1].intrinsics
    np.testing.assert_allclose(item["K"][1], stored.scaled(96, 64).K(), rtol=1e-6)
    assert item["K"][1][0, 0] == pytest.approx(80.0 * 96 / 100)


def test_localize_reads_the_sensor_pixels(tmp_path: Path) -> None:
    sensor = tagged_folder(tmp_path / "phone", n=1)
    (frame,) = list(iter_frames([("image", tmp_path / "phone" / "img0.jpg")]))
    assert np.array_equal(frame.image, sensor)


def _rewrite_index_size(out: Path, width: int, height: int) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    t = pq.read_table(out / "index.parquet")
    n = t.num_rows
    t = t.set_column(t.schema.get_field_index("width"), "width", pa.array([width] * n, pa.int32()))
    t = t.set_column(t.schema.get_field_index("height"), "height", pa.array([height] * n, pa.int32()))
    pq.write_table(t, out / "index.parquet")


@pytest.mark.parametrize("size", [(60, 100), (200, 120)], ids=["rotated", "uniform-2x"])
def test_decoded_size_other_than_the_intrinsics_is_an_error(tagged_shards, size) -> None:
    out, _ = tagged_shards
    _rewrite_index_size(out, *size)
    ds = open_dataset(out)
    with pytest.raises(UserError, match=rf"decodes to 100x60 but its intrinsics describe {size[0]}x{size[1]}"):
        ds.read_image(ds.records[0])
    item = TripletData(ImageFrames.open(out), AugmentConfig(96, 64))[TRIPLET]
    assert "decodes to 100x60" in item["error"]  # skipped and reported, never rescaled
