"""benchmarks/quality/parallax.py measures the depth part of a warp: checked against geometry."""

import importlib.util
from pathlib import Path

import numpy as np

_spec = importlib.util.spec_from_file_location(
    "parallax", Path(__file__).resolve().parents[1] / "benchmarks" / "quality" / "parallax.py")
parallax = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(parallax)

K = np.array([[105.0, 0.0, 63.5], [0.0, 105.0, 47.5], [0.0, 0.0, 1.0]])


def _rot_y(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def _depth() -> np.ndarray:
    rng = np.random.default_rng(0)
    D = rng.uniform(1.0, 3.0, size=(96, 128))
    D[:5] = 0.0  # invalid pixels are left out
    return D


def test_rotation_alone_has_no_depth_part():
    T_t, T_s = np.eye(4), np.eye(4)
    T_s[:3, :3] = _rot_y(5.0)
    dflow, flow = parallax.depth_flow(K, _depth(), T_t, T_s)
    assert dflow.shape == ((96 - 5) * 128,)
    assert np.abs(dflow).max() < 1e-9
    assert np.median(flow) > 5.0  # the whole warp is large: 5 deg at fx 105 is ~9 px


def test_sideways_translation_matches_fx_t_inverse_depth_difference():
    D = _depth()
    T_t, T_s = np.eye(4), np.eye(4)
    T_s[0, 3] = 0.02  # the source camera 2 cm to the right
    dflow, flow = parallax.depth_flow(K, D, T_t, T_s)
    d = D[D > 0]
    expected = 105.0 * 0.02 * np.abs(1.0 / d - 1.0 / np.median(d))
    np.testing.assert_allclose(dflow, expected, atol=1e-9)
    np.testing.assert_allclose(flow, 105.0 * 0.02 / d, atol=1e-9)


def test_walkthrough_folder_is_read_as_one_sequence(tmp_path: Path):
    import cv2

    (tmp_path / "depth").mkdir()
    T = np.stack([np.eye(4)] * 3)
    T[:, 0, 3] = [0.0, 0.01, 0.02]
    np.savetxt(tmp_path / "poses.txt", T.reshape(3, 16))
    np.savetxt(tmp_path / "K.txt", K)
    for i in range(3):
        cv2.imwrite(str(tmp_path / "depth" / f"{i:05d}.png"), np.full((96, 128), 1500 + i, np.uint16))
    [(K2, T2, D2)] = parallax.sequences(tmp_path)
    np.testing.assert_allclose(K2, K)
    np.testing.assert_allclose(T2, T)
    assert D2.shape == (3, 96, 128) and D2[2, 0, 0] == 1.502
