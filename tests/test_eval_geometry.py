"""Evaluation geometry (numpy) against geometry: known Sim(3)s, degenerate point sets, Rodrigues'
formula for quaternions, TUM files."""

from __future__ import annotations

import numpy as np
import pytest

from relocdepth import eval_geometry as EG
from relocdepth.trajectory import read_tum, tum_lines, write_tum


def rodrigues(axis, deg: float) -> np.ndarray:
    """Rotation by ``deg`` about ``axis`` (Rodrigues' formula, independent of the module)."""
    n = np.asarray(axis, np.float64)
    n = n / np.linalg.norm(n)
    K = np.array([[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]])
    a = np.radians(deg)
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def poses(R: np.ndarray, c: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (len(c), 1, 1))
    T[:, :3, :3], T[:, :3, 3] = R, c
    return T


def random_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    return np.stack([rodrigues(rng.normal(size=3), rng.uniform(0, 180)) for _ in range(n)])


def handheld_trajectory(n: int, rng: np.random.Generator) -> np.ndarray:
    """Camera poses walking round a room: a 1.5 m circle, head height bobbing 10 cm, looking in."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    c = np.stack((1.5 * np.cos(a), 0.1 * np.sin(3 * a) + 1.6, 1.5 * np.sin(a)), -1)
    R = np.stack([rodrigues([0, 1, 0], np.degrees(-x) - 90) @ rodrigues(rng.normal(size=3), 5)
                  for x in a])
    return poses(R, c)


# ----------------------------------------------------------------------------- rotations


def test_rotation_angle_precise_near_0_and_180() -> None:
    axis = [0.3, -1.0, 0.4]
    for deg in (1e-6, 0.01, 30.0, 179.9, 180.0 - 1e-6):
        assert EG.rotation_angle_deg(rodrigues(axis, deg)) == pytest.approx(deg, rel=1e-7)
    assert EG.rotation_angle_deg(np.eye(3)) == 0.0


def test_chordal_mean_and_spread() -> None:
    R = np.stack([rodrigues([0, 0, 1], 10), rodrigues([0, 0, 1], 30)])
    np.testing.assert_allclose(EG.chordal_mean_rotation(R), rodrigues([0, 0, 1], 20), atol=1e-12)
    T = poses(R, np.array([[-1.0, 0, 0], [1.0, 0, 0]]))
    assert EG.pose_spread(T) == pytest.approx({"centre_rms": 1.0, "rot_median_deg": 10.0})
    mean = np.eye(4)
    mean[:3, :3] = rodrigues([0, 0, 1], 20)
    np.testing.assert_allclose(EG.mean_pose(T), mean, atol=1e-12)


def test_rotation_only_alignment_recovers_offset() -> None:
    rng = np.random.default_rng(1)
    gt = poses(random_rotations(10, rng), rng.normal(size=(10, 3)))
    A = rodrigues([1, 0, 0], 30) @ rodrigues([0, 0, 1], -50)
    # predictions in another world frame and with collapsed centres: the rotation-only
    # alignment still gives zero rotation error.
    est = gt.copy()
    est[:, :3, :3] = A.T @ gt[:, :3, :3]
    est[:, :3, 3] = 0.0
    err = EG.rotation_only_errors(est[:5, :3, :3], gt[:5, :3, :3], est[5:, :3, :3], gt[5:, :3, :3])
    np.testing.assert_allclose(err, 0.0, atol=1e-5)


def test_pose_errors_known_offsets() -> None:
    rng = np.random.default_rng(4)
    gt = poses(random_rotations(3, rng), rng.normal(size=(3, 3)))
    est = gt.copy()
    est[1, :3, 3] += [0.0, 0.03, 0.04]
    est[2, :3, :3] = est[2, :3, :3] @ rodrigues([1, 1, 0], 179.0)
    t, r = EG.pose_errors(est, gt)
    np.testing.assert_allclose(t, [0.0, 0.05, 0.0], atol=1e-12)
    np.testing.assert_allclose(r, [0.0, 0.0, 179.0], atol=1e-9)
    with pytest.raises(ValueError):
        EG.pose_errors(est[:2], gt)


# ----------------------------------------------------------------------------- alignment


def test_apply_sim3_maps_centres_and_keeps_rotations_rigid() -> None:
    rng = np.random.default_rng(2)
    T = poses(random_rotations(3, rng), rng.normal(size=(3, 3)))
    R = rodrigues([0, 1, 0], 40)
    out = EG.apply_sim3(2.0, R, np.array([1.0, 2.0, 3.0]), T)
    np.testing.assert_allclose(out[:, :3, 3], 2.0 * T[:, :3, 3] @ R.T + [1, 2, 3])
    np.testing.assert_allclose(out[:, :3, :3], R @ T[:, :3, :3])
    Rs = out[:, :3, :3]
    np.testing.assert_allclose(Rs @ np.swapaxes(Rs, 1, 2), np.tile(np.eye(3), (3, 1, 1)),
                               atol=1e-12)


def test_umeyama_recovers_known_sim3_from_noisy_poses() -> None:
    rng = np.random.default_rng(7)
    gt = handheld_trajectory(60, rng)
    # the predictions live in another frame: gt = s R pred + t, i.e. pred = R^T (gt - t) / s
    s, R, t = 2.5, rodrigues([0.3, -1.2, 0.7], 75.0), np.array([1.0, -2.0, 0.5])
    pred = EG.apply_sim3(1.0 / s, R.T, -R.T @ t / s, gt)
    pred[:, :3, 3] += rng.normal(scale=0.004, size=(60, 3))  # 4 mm in prediction units = 1 cm
    fit = EG.umeyama(pred[:, :3, 3], gt[:, :3, 3])
    assert fit.degenerate is None
    assert fit.scale == pytest.approx(s, rel=0.01)
    assert EG.rotation_angle_deg(fit.R.T @ R) < 0.5
    np.testing.assert_allclose(fit.t, t, atol=0.02)
    t_err, r_err = EG.pose_errors(EG.apply_sim3(fit.scale, fit.R, fit.t, pred), gt)
    assert np.median(t_err) < 0.02 and r_err.max() < 0.5
    # without scale (SE(3)): a rigid motion of the same trajectory is recovered exactly
    moved = EG.apply_sim3(1.0, R, t, gt)
    rigid = EG.umeyama(gt[:, :3, 3], moved[:, :3, 3], with_scale=False)
    assert rigid.scale == 1.0 and rigid.degenerate is None
    np.testing.assert_allclose(rigid.R, R, atol=1e-9)
    np.testing.assert_allclose(rigid.t, t, atol=1e-9)


def test_umeyama_coplanar_positions_are_not_degenerate() -> None:
    a = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    src = np.stack((np.cos(a), np.sin(a), np.zeros_like(a)), -1)  # a planar circle
    R = rodrigues([1, 2, 3], 120.0)
    fit = EG.umeyama(src, 3.0 * src @ R.T + 1.0)
    assert fit.degenerate is None
    np.testing.assert_allclose(fit.R, R, atol=1e-9)
    assert fit.scale == pytest.approx(3.0)


@pytest.mark.parametrize(
    "case, match",
    [
        ("collinear", "source positions are collinear"),
        ("nearly collinear", "source positions are collinear"),
        ("identical", "source positions coincide"),
        ("collapsed float32", "source positions coincide"),
        ("collinear target", "target positions are collinear"),
        ("two", "2 positions"),
    ],
)
def test_umeyama_degeneracy_flag(case: str, match: str) -> None:
    rng = np.random.default_rng(3)
    gt = handheld_trajectory(40, rng)[:, :3, 3]
    line = np.linspace(0, 2, 40)[:, None] * np.array([0.6, 0.0, 0.8]) + [1.0, 2.0, 3.0]
    src, dst = {
        "collinear": (line, gt),
        # a dolly shot: 2 m along a line, 2 mm of wobble across it
        "nearly collinear": (line + rng.normal(scale=0.002, size=line.shape), gt),
        "identical": (np.tile([[0.4, -1.0, 2.0]], (40, 1)), gt),
        # a collapsed network: one pose for every image, up to float32 rounding
        "collapsed float32": (np.float32([[0.4, -1.0, 2.0]]) + rng.normal(scale=1e-8, size=(40, 3)),
                              gt),
        "collinear target": (gt, line),
        "two": (gt[:2], gt[:2] + 1.0),
    }[case]
    fit = EG.umeyama(src, dst)
    assert fit.degenerate is not None and match in fit.degenerate
    assert np.isfinite(fit.scale) and np.isfinite(fit.R).all() and np.isfinite(fit.t).all()


def test_umeyama_rejects_malformed_input() -> None:
    with pytest.raises(ValueError):
        EG.umeyama(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError):
        EG.umeyama(np.zeros((5, 3)), np.zeros((4, 3)))


# ----------------------------------------------------------------------------- quaternions


def _test_rotations() -> list[tuple[np.ndarray, float]]:
    rng = np.random.default_rng(5)
    axes = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [-0.2, 0.5, 0.9], *rng.normal(size=(10, 3))]
    degs = [0.0, 1e-6, 37.0, 90.0, 179.0, 180.0 - 1e-7, 180.0]
    return [(np.asarray(a, np.float64), d) for a in axes for d in degs]


def test_matrix_to_quaternion_matches_axis_angle_both_orders() -> None:
    cases = _test_rotations()
    R = np.stack([rodrigues(a, d) for a, d in cases])
    q = EG.rotmat_to_quat_wxyz(R)  # one vectorised call for all of them
    for (axis, deg), qi in zip(cases, q):
        half = np.radians(deg) / 2
        expect = np.concatenate(([np.cos(half)], np.sin(half) * axis / np.linalg.norm(axis)))
        # q and -q are one rotation; at exactly 180 deg (w = 0) either sign is canonical
        sign = 1.0 if np.dot(qi, expect) >= 0 else -1.0
        np.testing.assert_allclose(sign * qi, expect, atol=1e-9)
        assert qi[0] >= 0
    np.testing.assert_allclose(EG.quat_wxyz_to_rotmat(q), R, atol=1e-12)
    # scalar-last: the same numbers rolled, and back
    q_xyzw = EG.quat_wxyz_to_xyzw(q)
    np.testing.assert_array_equal(q_xyzw[:, 3], q[:, 0])
    np.testing.assert_array_equal(q_xyzw[:, :3], q[:, 1:])
    np.testing.assert_array_equal(EG.quat_xyzw_to_wxyz(q_xyzw), q)
    # shapes: a single matrix and a (2, N) batch keep their leading dimensions
    assert EG.rotmat_to_quat_wxyz(np.eye(3)).tolist() == [1.0, 0.0, 0.0, 0.0]
    assert EG.rotmat_to_quat_wxyz(R.reshape(-1, 7, 3, 3)).shape == (len(cases) // 7, 7, 4)


def test_quaternion_to_matrix_round_trip_any_norm() -> None:
    rng = np.random.default_rng(6)
    q = rng.normal(size=(50, 4))
    q[0] = [1e-9, 1.0, 0.0, 0.0]  # 180 deg about x
    q[1] = [-3.0, 0.0, 0.0, 0.0]  # the identity, negative and not unit
    R = EG.quat_wxyz_to_rotmat(q)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.tile(np.eye(3), (50, 1, 1)), atol=1e-12)
    q_back = EG.rotmat_to_quat_wxyz(R)
    unit = q / np.linalg.norm(q, axis=-1, keepdims=True)
    np.testing.assert_allclose(np.abs(np.sum(q_back * unit, axis=-1)), 1.0, atol=1e-12)


# ----------------------------------------------------------------------------- TUM


def test_tum_lines_known_pose_and_round_trip(tmp_path) -> None:
    T = handheld_trajectory(20, np.random.default_rng(8))
    T[0, :3, :3] = rodrigues([1, 0, 0], 180.0)  # the unstable case for naive conversions
    T[1, :3, :3] = rodrigues([0, 0, 1], 90.0)
    T[1, :3, 3] = [1.0, 2.0, 3.0]
    ts = 1.5 + np.arange(20) / 30.0
    lines = tum_lines(ts, T)
    # TUM: timestamp tx ty tz qx qy qz qw; 90 deg about z is qz = qw = sqrt(1/2)
    fields = [float(v) for v in lines[1].split()]
    expect = [1.5 + 1 / 30, 1, 2, 3, 0, 0, np.sqrt(0.5), np.sqrt(0.5)]
    np.testing.assert_allclose(fields, expect, atol=1e-6)
    write_tum(tmp_path / "t.txt", ts, T)
    ts2, T2 = read_tum(tmp_path / "t.txt")
    np.testing.assert_allclose(ts2, ts, atol=1e-6)
    np.testing.assert_allclose(T2, T, atol=1e-7)
    np.testing.assert_allclose(EG.poses_from_tum_rows(EG.poses_to_tum_rows(T)), T, atol=1e-12)
