"""Metrics against hand-computed cases (pure numpy, fast)."""

from __future__ import annotations

import numpy as np
import pytest

from relocdepth import metrics as M
from relocdepth.eval_geometry import pose_errors, quat_wxyz_to_rotmat


def rot(axis: str, deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        q = rng.normal(size=4)
        out.append(pose(quat_wxyz_to_rotmat(q), rng.normal(size=3)))
    return np.stack(out)


def test_pose_errors_known_sizes() -> None:
    gt = random_poses(4)
    est = gt.copy()
    # frame 0 exact; frame 1 moved 3 cm; frame 2 rotated 7 deg about its own x; frame 3 both
    est[1, :3, 3] += [0.03, 0.0, 0.0]
    est[2, :3, :3] = est[2, :3, :3] @ rot("x", 7.0)
    est[3, :3, 3] += [0.0, 0.06, 0.08]
    est[3, :3, :3] = rot("z", 12.0) @ est[3, :3, :3]
    t, r = pose_errors(est, gt)
    np.testing.assert_allclose(t, [0.0, 0.03, 0.0, 0.10], atol=1e-12)
    np.testing.assert_allclose(r, [0.0, 0.0, 7.0, 12.0], atol=1e-5)
    s = M.pose_summary(t, r)
    assert s["median_t_m"] == pytest.approx(0.015)
    assert s["median_r_deg"] == pytest.approx(3.5)
    assert s["pct_5cm_5deg"] == pytest.approx(50.0)  # frames 0 and 1
    assert s["pct_10cm_10deg"] == pytest.approx(75.0)  # frame 3 fails on rotation
    per = M.pose_summary_by_sequence(t, r, ["a", "a", "b", "b"])
    assert list(per) == ["a", "b"]
    assert per["a"]["median_t_m"] == pytest.approx(0.015)
    assert per["b"]["median_r_deg"] == pytest.approx(9.5)


def test_relative_pose_errors_vs_identity() -> None:
    # a camera moving 1 cm and 1 deg per frame along x / about y
    gt = np.stack([pose(rot("y", i), [0.01 * i, 0, 0]) for i in range(8)])
    out = M.relative_pose_errors(gt.copy(), gt, ["s"] * 4 + ["t"] * 4, k=2)
    assert out["pairs"] == 4
    assert out["median_t_m"] == pytest.approx(0.0, abs=1e-12)
    assert out["median_r_deg"] == pytest.approx(0.0, abs=1e-5)
    assert out["identity_median_t_m"] == pytest.approx(0.02)
    assert out["identity_median_r_deg"] == pytest.approx(2.0)
    # a constant prediction is exactly the identity reference
    const = np.repeat(gt[:1], 8, axis=0)
    out = M.relative_pose_errors(const, gt, ["s"] * 8, k=3)
    assert out["median_t_m"] == pytest.approx(out["identity_median_t_m"])
    assert out["median_r_deg"] == pytest.approx(out["identity_median_r_deg"], abs=1e-5)
    assert M.relative_pose_errors(gt, gt, ["s"] * 8, k=8)["pairs"] == 0


def test_mean_pose_baseline() -> None:
    gt = np.stack([pose(rot("z", a), [x, 0, 0]) for x, a in ((-1.0, 10.0), (1.0, 30.0))])
    base = M.mean_pose_baseline(gt, 3)
    assert base.shape == (3, 4, 4)
    np.testing.assert_allclose(base[0], pose(rot("z", 20.0), [0, 0, 0]), atol=1e-12)


def test_thumbnail_and_retrieval() -> None:
    rng = np.random.default_rng(0)
    imgs = rng.integers(0, 255, size=(5, 96, 128, 3)).astype(np.uint8)
    th = np.stack([M.thumbnail(im) for im in imgs])
    assert th.shape == (5, 16 * 12)
    np.testing.assert_allclose(th.mean(axis=1), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(th, axis=1), 1.0)
    # brightness/contrast changes do not change the thumbnail
    np.testing.assert_allclose(M.thumbnail(imgs[0] * 0.5 + 20), th[0], atol=1e-9)
    # a block-constant image: exact cell averages
    grey = np.kron(np.arange(12 * 16, dtype=float).reshape(12, 16), np.ones((8, 8)))
    v = np.arange(12 * 16, dtype=float)
    np.testing.assert_allclose(M.thumbnail(grey), (v - v.mean()) / np.linalg.norm(v - v.mean()))
    T = random_poses(5)
    poses, nn = M.retrieval_baseline(th, T, th[[3, 1]] + 1e-3)
    assert nn.tolist() == [3, 1]
    np.testing.assert_array_equal(poses, T[[3, 1]])


def test_depth_errors_hand_computed() -> None:
    gt = np.array([[1.0, 2.0], [4.0, 0.0]])  # one invalid pixel
    pred = 3.0 * np.array([[1.0, 2.0], [2.0, 7.0]])  # scaled wrongly by 3, last gt pixel is wrong
    out = M.depth_errors(pred, gt)
    assert out["scale"] == pytest.approx(1.0 / 3.0)  # median gt 2 / median pred 6
    # after scaling pred = [1, 2, 2] vs gt [1, 2, 4]
    assert out["abs_rel"] == pytest.approx((0 + 0 + 0.5) / 3)
    assert out["sq_rel"] == pytest.approx((4.0 / 4.0) / 3)
    assert out["rmse"] == pytest.approx(np.sqrt(4.0 / 3))
    assert out["rmse_log"] == pytest.approx(np.sqrt(np.log(2.0) ** 2 / 3))
    assert out["delta1"] == pytest.approx(2 / 3)
    assert out["delta2"] == pytest.approx(2 / 3)  # ratio 2 > 1.5625
    assert out["delta3"] == pytest.approx(2 / 3)  # 1.25**3 = 1.953 < 2 still
    assert M.depth_errors(np.ones((2, 2)), np.zeros((2, 2))) is None


def test_depth_perfect_up_to_scale_and_summary() -> None:
    rng = np.random.default_rng(3)
    gt = rng.uniform(0.5, 5.0, size=(4, 12, 16))
    frames = [M.depth_errors(g * s, g) for g, s in zip(gt, (1.0, 2.0, 4.0, 2.0))]
    summ = M.depth_summary(frames + [None])
    assert summ["frames"] == 4
    assert summ["abs_rel"] == pytest.approx(0.0, abs=1e-12)
    assert summ["delta1"] == 1.0
    scales = np.array([1.0, 0.5, 0.25, 0.5])
    assert summ["scale_median"] == pytest.approx(0.5)
    assert summ["scale_std_over_median"] == pytest.approx(np.std(scales) / 0.5)


def test_constant_depth_reference() -> None:
    gt = np.array([[1.0, 2.0, 3.0]])
    out = M.constant_depth_errors(gt)  # flat map at median 2
    assert out["abs_rel"] == pytest.approx((1.0 + 0.0 + 1.0 / 3.0) / 3)
    assert out["rmse"] == pytest.approx(np.sqrt(2.0 / 3))
