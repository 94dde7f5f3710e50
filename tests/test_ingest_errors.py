"""Bad input to ``reloc ingest``: one clear line, exit code 2, nothing written."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import pytest
from ingest_fixtures import write_images, write_K, write_sevenscenes, write_video
from relocdepth.cli.main import app
from relocdepth.ingest.intrinsics import load_calibration
from typer.testing import CliRunner

from relocdepth.errors import UserError

runner = CliRunner()


def fails(tmp_path: Path, args: list, *needles: str) -> str:
    """Run ``reloc ingest ARGS -o tmp/out``; assert exit 2, one error line naming the problem, nothing written."""
    before = sorted(p.name for p in tmp_path.iterdir())
    res = runner.invoke(app, ["ingest", *[str(a) for a in args], "-o", str(tmp_path / "out")])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.output
    for n in needles:
        assert n in lines[0], lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no output, no temp folder
    return lines[0]


def test_missing_source(tmp_path: Path) -> None:
    fails(tmp_path, [tmp_path / "nope.mp4"], "source not found", "nope.mp4")


def test_unreadable_source(tmp_path: Path) -> None:
    # a named pipe: no user, root included, can read a video from it (and opening it would block)
    os.mkfifo(tmp_path / "walk.mp4")
    fails(tmp_path, [tmp_path / "walk.mp4", "--K", write_K(tmp_path / "K.yaml")], "not readable", "walk.mp4")
    if os.geteuid() != 0:  # permissions stop everyone but root
        folder = tmp_path / "cam"
        write_images(folder, ["a.png"])
        folder.chmod(0)
        try:
            fails(tmp_path, [folder, "--K", tmp_path / "K.yaml"], "not readable", "permissions")
        finally:
            folder.chmod(0o755)


def test_unknown_source_kind(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("hello")
    fails(tmp_path, [tmp_path / "notes.txt"], "unknown source kind", "notes.txt")
    (tmp_path / "stuff").mkdir()
    (tmp_path / "stuff" / "a.txt").write_text("x")
    fails(tmp_path, [tmp_path / "stuff"], "unknown source kind")


def test_K_required_for_video_and_images(tmp_path: Path) -> None:
    write_video(tmp_path / "v.mp4", frames=3)
    write_images(tmp_path / "cam", ["a.png"])
    fails(tmp_path, [tmp_path / "v.mp4"], "--K")
    fails(tmp_path, [tmp_path / "cam"], "--K")


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("fy: 60\ncx: 31.5\ncy: 23.5\nwidth: 64\nheight: 48\n", "fx"),
        ("fx: -1\nfy: 60\ncx: 31.5\ncy: 23.5\nwidth: 64\nheight: 48\n", "fx"),
        ("fx: 60\nfy: 60\ncx: 31.5\ncy: 23.5\nwidth: 64.5\nheight: 48\n", "width"),
        ("fx: 60\nfy: 60\ncx: abc\ncy: 23.5\nwidth: 64\nheight: 48\n", "cx"),
        ("fx: 60\nfy: 60\ncx: 31.5\ncy: 23.5\nwidth: 64\nheight: 48\ndistortion: [0.1, 0.2, 0.3]\n", "distortion"),
        ("camera_matrix: {rows: 3, cols: 3, data: [1, 0, 2]}\nimage_width: 64\nimage_height: 48\n", "camera_matrix"),
        ("- just\n- a list\n", "fx"),
    ],
)
def test_malformed_intrinsics_names_the_field(tmp_path: Path, text: str, field: str) -> None:
    write_images(tmp_path / "cam", ["a.png"])
    (tmp_path / "K.yaml").write_text(text)
    fails(tmp_path, [tmp_path / "cam", "--K", tmp_path / "K.yaml"], field)


def test_malformed_opencv_calibration(tmp_path: Path) -> None:
    fs = cv2.FileStorage(str(tmp_path / "calib.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 64)
    fs.write("image_height", 48)
    fs.release()
    with pytest.raises(UserError, match="camera_matrix"):
        load_calibration(tmp_path / "calib.yml")
    write_images(tmp_path / "cam", ["a.png"])
    fails(tmp_path, [tmp_path / "cam", "--K", tmp_path / "calib.yml"], "camera_matrix")
    with pytest.raises(UserError, match="not found"):
        load_calibration(tmp_path / "missing.yaml")


def test_intrinsics_inconsistent_with_frame_size(tmp_path: Path) -> None:
    write_images(tmp_path / "cam", ["a.png"], size=(64, 48))
    K = write_K(tmp_path / "K.yaml", size=(64, 64))
    fails(tmp_path, [tmp_path / "cam", "--K", K], "64x64", "64x48", "aspect")
    write_video(tmp_path / "v.mp4", frames=2, size=(64, 48))
    fails(tmp_path, [tmp_path / "v.mp4", "--K", K], "aspect")


def test_video_without_decodable_frame(tmp_path: Path) -> None:
    (tmp_path / "broken.mp4").write_bytes(os.urandom(2000))
    fails(tmp_path, [tmp_path / "broken.mp4", "--K", write_K(tmp_path / "K.yaml")], "no decodable frame", "broken.mp4")


def test_empty_folder(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    fails(tmp_path, [tmp_path / "empty"], "empty folder")
    write_sevenscenes(tmp_path / "scene", {"seq-01": "train"}, frames=1)
    for p in (tmp_path / "scene" / "seq-01").iterdir():
        p.unlink()
    fails(tmp_path, [tmp_path / "scene"], "empty")


def test_existing_output_without_force(tmp_path: Path) -> None:
    write_sevenscenes(tmp_path / "scene", {"seq-01": "train"}, frames=1)
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("mine")
    fails(tmp_path, [tmp_path / "scene"], "output exists", "--force")
    assert (tmp_path / "out" / "keep.txt").read_text() == "mine"


def test_bad_options(tmp_path: Path) -> None:
    write_sevenscenes(tmp_path / "scene", {"seq-01": "train"}, frames=1)
    fails(tmp_path, [tmp_path / "scene", "--resize", "64by48"], "640x480")
    fails(tmp_path, [tmp_path / "scene", "--split", "val"], "--split")
    (tmp_path / "root").mkdir()
    (tmp_path / "scene").rename(tmp_path / "root" / "chess")
    fails(tmp_path, [tmp_path / "root", "--scene", "kitchen"], "kitchen", "chess")
