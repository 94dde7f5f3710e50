"""The walk-through layout of the quality rows: which frames test, and that the 7-Scenes reader
sees the split and each frame's own pose."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from relocdepth.ingest.sevenscenes import read_splits

_spec = importlib.util.spec_from_file_location(
    "walkthrough", Path(__file__).resolve().parents[1] / "benchmarks" / "quality" / "walkthrough.py")
walkthrough = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(walkthrough)


def test_test_frames_are_the_end_or_blocks_inside_the_walk():
    assert walkthrough.test_ranges(120, 30) == [(90, 120)]
    inside = walkthrough.test_ranges(120, 30, blocks=3)
    assert inside == [(15, 25), (55, 65), (95, 105)]
    assert sum(hi - lo for lo, hi in walkthrough.test_ranges(100, 29, blocks=4)) == 29
    with pytest.raises(SystemExit, match="no training frames between"):
        walkthrough.test_ranges(10, 8, blocks=3)
    with pytest.raises(SystemExit, match="must number 1..9"):
        walkthrough.test_ranges(10, 10)
    with pytest.raises(SystemExit, match="2 frames in 3 blocks"):
        walkthrough.test_ranges(100, 2, blocks=3)


def _walk(root: Path, n: int) -> np.ndarray:
    import cv2

    (root / "images").mkdir(parents=True)
    (root / "depth").mkdir()
    T = np.stack([np.eye(4)] * n)
    T[:, 0, 3] = 0.1 * np.arange(n)  # frame i stands at x = 0.1 i
    np.savetxt(root / "poses.txt", T.reshape(n, 16))
    np.savetxt(root / "K.txt", np.array([[50.0, 0, 16], [0, 50.0, 12], [0, 0, 1]]))
    for i in range(n):
        cv2.imwrite(str(root / "images" / f"{i:05d}.png"), np.full((24, 32, 3), i, np.uint8))
        cv2.imwrite(str(root / "depth" / f"{i:05d}.png"), np.full((24, 32), 1000, np.uint16))
    return T


def test_blocks_alternate_train_and_test_sequences_with_their_own_poses(tmp_path):
    _walk(tmp_path / "walk", 12)
    counts = walkthrough.lay_out(tmp_path / "walk", tmp_path / "scene", test=4, blocks=2)
    assert counts == {"train": 8, "test": 4, "train_sequences": 3, "test_sequences": 2}
    # frames 2-3 and 8-9 test: seq-01 = 0-1 train, seq-02 = 2-3 test, seq-03 = 4-7, seq-04 = 8-9, seq-05 = 10-11
    assert read_splits(tmp_path / "scene") == {"seq-01": "train", "seq-02": "test", "seq-03": "train",
                                               "seq-04": "test", "seq-05": "train"}
    x = {seq: [np.loadtxt(p)[0, 3] for p in sorted((tmp_path / "scene" / seq).glob("*.pose.txt"))]
         for seq in ("seq-02", "seq-03")}
    np.testing.assert_allclose(x["seq-02"], [0.2, 0.3])
    np.testing.assert_allclose(x["seq-03"], [0.4, 0.5, 0.6, 0.7])
    tail = walkthrough.lay_out(tmp_path / "walk", tmp_path / "tail", test=4)
    assert tail["test_sequences"] == 1 and read_splits(tmp_path / "tail") == {"seq-01": "train", "seq-02": "test"}


def test_every_nth_frame_tests_between_training_frames(tmp_path):
    train, test = walkthrough.interleaved(9, 3)
    assert test == [1, 4, 7] and train == [0, 2, 3, 5, 6, 8]
    with pytest.raises(SystemExit, match="--every"):
        walkthrough.interleaved(9, 1)
    _walk(tmp_path / "walk", 10)
    counts = walkthrough.lay_out(tmp_path / "walk", tmp_path / "scene", test=4, blocks=2, every=2)
    assert counts == {"train": 5, "test": 5, "train_sequences": 1, "test_sequences": 1}
    assert read_splits(tmp_path / "scene") == {"seq-01": "train", "seq-02": "test"}
    x = {seq: [np.loadtxt(p)[0, 3] for p in sorted((tmp_path / "scene" / seq).glob("*.pose.txt"))]
         for seq in ("seq-01", "seq-02")}
    np.testing.assert_allclose(x["seq-01"], [0.0, 0.2, 0.4, 0.6, 0.8])
    np.testing.assert_allclose(x["seq-02"], [0.1, 0.3, 0.5, 0.7, 0.9])
