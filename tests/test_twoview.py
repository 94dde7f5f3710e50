"""Two-view relative pose from KLT tracks + essential matrix, on rendered frames with known poses."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from relocdepth.camera import Intrinsics
from relocdepth.errors import UserError
from relocdepth.eval_geometry import rotation_angle_deg
from relocdepth.geometry import relative_pose
from relocdepth.synth import SynthConfig, build_scene, camera_paths, render
from relocdepth.twoview import (
    homography_residual,
    relative_pose_essential,
    relative_pose_images,
)

INTR = Intrinsics(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)


def _angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    c = np.dot(u, v) / (np.linalg.norm(u) * np.linalg.norm(v))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _pair(move: np.ndarray, turn_deg: tuple[float, float, float]) -> tuple[np.ndarray, ...]:
    """Two rendered views of the demo scene: the first pose of its first path, and that pose
    moved by ``move`` (metres, world) and turned by the axis-angle ``turn_deg`` (camera axes)."""
    cfg = SynthConfig(seed=0, frames=2, width=INTR.width, height=INTR.height)
    scene = build_scene(cfg.seed, cfg)
    T_a = camera_paths(cfg)["seq-01"][0]
    T_b = T_a.copy()
    T_b[:3, 3] += move
    T_b[:3, :3] = T_a[:3, :3] @ cv2.Rodrigues(np.radians(np.asarray(turn_deg)))[0]  # camera axes
    img_a, _ = render(scene, T_a, INTR)
    img_b, _ = render(scene, T_b, INTR)
    return img_a, img_b, T_a, T_b


@pytest.mark.parametrize("move,turn", [
    (np.array([0.10, 0.04, 0.02]), (3.0, -2.0, 1.0)),
    (np.array([-0.06, 0.08, -0.03]), (-4.0, 1.5, -2.0)),
    (np.array([0.0, 0.05, 0.12]), (1.0, -3.0, 2.0)),  # mostly forward
    (np.array([0.05, 0.0, 0.0]), (2.0, 0.0, 0.0)),  # 5 cm, little parallax
])
def test_recovers_rendered_relative_pose(move: np.ndarray, turn: tuple[float, float, float]) -> None:
    img_a, img_b, T_a, T_b = _pair(move, turn)
    T_ba = relative_pose(torch.from_numpy(T_a)[None], torch.from_numpy(T_b)[None])[0].numpy()
    assert rotation_angle_deg(T_ba[:3, :3]) > 1.5  # the pair does rotate (2 deg or more): the test can fail
    pose = relative_pose_images(img_a, img_b, INTR.K())
    err_R = rotation_angle_deg(pose.R.T @ T_ba[:3, :3])
    err_t = _angle_deg(pose.t, T_ba[:3, 3])
    assert pose.inliers >= 50
    assert err_R < 1.0, err_R
    assert err_t < 5.0, err_t
    assert abs(np.linalg.norm(pose.t) - 1.0) < 1e-9


def _points_and_yaw(seed: int, n: int, z: tuple[float, float], yaw_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """``n`` random points in front of a camera (depth in ``z``) and a rotation about the y axis."""
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-1.5, 1.5, n), rng.uniform(-1, 1, n), rng.uniform(*z, n)]
    a = np.radians(yaw_deg)
    return X, np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def _project(X: np.ndarray) -> np.ndarray:
    x = X @ INTR.K().T
    return x[:, :2] / x[:, 2:]


def test_points_in_camera_a_map_into_camera_b() -> None:
    """Synthetic correspondences: X_b = R X_a + t with the returned (R, t) (direction of t)."""
    K = INTR.K()
    X_a, R = _points_and_yaw(1, 200, (2, 6), 5.0)
    t = np.array([0.3, -0.05, 0.1])
    X_b = X_a @ R.T + t
    pose = relative_pose_essential(_project(X_a), _project(X_b), K)
    assert rotation_angle_deg(pose.R.T @ R) < 0.05
    assert _angle_deg(pose.t, t) < 0.2


def test_homography_residual_zero_for_rotation_positive_for_translation() -> None:
    X, R = _points_and_yaw(2, 300, (1, 5), 4.0)

    def project(X: np.ndarray) -> np.ndarray:
        return _project(X).astype(np.float32)

    assert homography_residual(project(X), project(X @ R.T), 1.0) < 0.01
    moved = homography_residual(project(X), project(X @ R.T + [0.1, 0, 0]), 1.0)
    assert moved > 1.0  # 0.1 m sideways at 1-5 m: several pixels of depth-dependent motion
    assert np.isnan(homography_residual(project(X[:5]), project(X[:5]), 1.0))


def test_too_few_points_is_an_error() -> None:
    with pytest.raises(UserError):
        relative_pose_essential(np.zeros((4, 2)), np.zeros((4, 2)), INTR.K())


def test_bootstrap_pair_pose_and_metric_depth_with_two_cameras() -> None:
    """The training bootstrap's pair: images with *different* intrinsics (as after scale/crop
    augmentation); the rotation and translation direction come back, and the triangulated depths
    times the true baseline are the rendered depths at those pixels."""
    from relocdepth.twoview import bootstrap_pair

    cfg = SynthConfig(seed=0, frames=2, width=320, height=240)
    scene = build_scene(cfg.seed, cfg)
    T_a = camera_paths(cfg)["seq-01"][0]
    T_b = T_a.copy()
    T_b[:3, 3] += np.array([0.08, 0.03, 0.02])
    T_b[:3, :3] = T_a[:3, :3] @ cv2.Rodrigues(np.radians([2.0, -3.0, 1.0]))[0]
    K_b = Intrinsics(fx=290.0, fy=290.0, cx=150.0, cy=125.0, width=320, height=240)
    img_a, depth_a = render(scene, T_a, INTR)
    img_b, _ = render(scene, T_b, K_b)
    T, points, ok = bootstrap_pair(img_a, img_b, INTR.K(), K_b.K())
    assert ok
    T_ba = relative_pose(torch.from_numpy(T_a)[None], torch.from_numpy(T_b)[None])[0].numpy()
    assert rotation_angle_deg(T[:3, :3].T @ T_ba[:3, :3]) < 1.0
    assert _angle_deg(T[:3, 3], T_ba[:3, 3]) < 5.0
    pts = points[np.isfinite(points[:, 2])]
    assert len(pts) >= 30
    baseline = np.linalg.norm(T_ba[:3, 3])
    x, y = np.round(pts[:, 0]).astype(int), np.round(pts[:, 1]).astype(int)
    ratio = pts[:, 2] * baseline / depth_a[y, x]
    assert abs(np.median(ratio) - 1.0) < 0.05, np.median(ratio)
    # Too little baseline to see (2 mm: ~0.3 px of parallax): the rotation only, no translation
    # and no points; a pure rotation either so or not at all (no essential matrix).
    for shift in (0.002, 0.0):
        T_c = T_a.copy()
        T_c[:3, 3] += np.array([shift, 0.0, 0.0])
        T_c[:3, :3] = T_a[:3, :3] @ cv2.Rodrigues(np.radians([1.0, 3.0, 0.0]))[0]
        img_c, _ = render(scene, T_c, INTR)
        T_rot, pts_rot, ok_rot = bootstrap_pair(img_a, img_c, INTR.K(), INTR.K())
        if shift or ok_rot:
            assert ok_rot
            T_ca = relative_pose(torch.from_numpy(T_a)[None], torch.from_numpy(T_c)[None])[0].numpy()
            assert rotation_angle_deg(T_rot[:3, :3].T @ T_ca[:3, :3]) < 0.5
            assert np.all(T_rot[:3, 3] == 0) and np.all(np.isnan(pts_rot))
    # The same rotation with the 8 cm baseline above is measured in full.
    T_c[:3, 3] = T_b[:3, 3]
    img_c, _ = render(scene, T_c, INTR)
    T_full, _, ok_full = bootstrap_pair(img_a, img_c, INTR.K(), INTR.K())
    assert ok_full and np.linalg.norm(T_full[:3, 3]) == pytest.approx(1.0, abs=1e-5)


def test_tracks_follow_a_fast_turn_at_640x480() -> None:
    """A 10 deg turn at 640x480 moves the image ~120 px: the default pyramid follows it (each
    track lands where the rendered depth and the true pose put it), three levels lose it, and the
    bootstrap's pair is measured."""
    from relocdepth.twoview import TrackConfig, as_grey, bootstrap_pair, detect_corners, track_points

    K = Intrinsics(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)
    cfg = SynthConfig(seed=0, frames=2, width=K.width, height=K.height)
    scene = build_scene(cfg.seed, cfg)
    T_a = camera_paths(cfg)["seq-01"][0]
    T_b = T_a.copy()
    T_b[:3, 3] += np.array([0.08, 0.03, 0.02])
    T_b[:3, :3] = T_a[:3, :3] @ cv2.Rodrigues(np.radians([1.0, 10.0, 0.0]))[0]
    img_a, depth_a = render(scene, T_a, K)
    img_b, _ = render(scene, T_b, K)
    T_ba = relative_pose(torch.from_numpy(T_a)[None], torch.from_numpy(T_b)[None])[0].numpy()

    def track_errors(track: TrackConfig) -> tuple[np.ndarray, np.ndarray]:
        """Per track: the distance (px) from where the truth puts it, and how far it moved."""
        grey_a = as_grey(img_a)
        pa, pb = track_points(grey_a, as_grey(img_b), detect_corners(grey_a, track), track)
        x, y = np.round(pa).astype(int).T
        X = np.c_[(pa - K.K()[:2, 2]) / K.fx, np.ones(len(pa))] * depth_a[y, x][:, None]
        Xb = X @ T_ba[:3, :3].T + T_ba[:3, 3]
        truth = Xb[:, :2] / Xb[:, 2:] * K.fx + K.K()[:2, 2]
        return np.linalg.norm(pb - truth, axis=1), np.linalg.norm(truth - pa, axis=1)

    err, moved = track_errors(TrackConfig())
    assert np.median(moved) > 100  # the motion is beyond three levels' reach: the test can fail
    assert (err < 1.0).sum() >= 30 and np.median(err) < 1.0, (len(err), np.median(err))
    err3, _ = track_errors(TrackConfig(max_level=3))
    assert (err3 < 1.0).sum() < 10
    T, _, ok = bootstrap_pair(img_a, img_b, K.K(), K.K())
    assert ok and rotation_angle_deg(T[:3, :3].T @ T_ba[:3, :3]) < 3.0


def test_small_step_at_640x480_is_measured() -> None:
    """A 1 cm step at 640x480 with the scene ~1.2 m away: ~4 px of parallax, measured (a unit
    translation in the true direction), though its points lie farther than OpenCV's default 50
    baselines; a 5 mm step is measured or rotation only, never lost."""
    from relocdepth.twoview import BOOTSTRAP_FAR_BASELINES, bootstrap_pair

    K = Intrinsics(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)
    cfg = SynthConfig(seed=0, frames=2, width=K.width, height=K.height)
    scene = build_scene(cfg.seed, cfg)
    T_a = camera_paths(cfg)["seq-01"][0]
    img_a, depth_a = render(scene, T_a, K)
    assert np.median(depth_a[depth_a > 0]) * 1.0 / 0.01 > 50  # beyond the default: the test can fail
    for step in (0.01, 0.005):
        T_b = T_a.copy()
        T_b[:3, 3] += T_a[:3, :3] @ np.array([step, 0.0, 0.0])  # sideways in the camera's frame
        T_b[:3, :3] = T_a[:3, :3] @ cv2.Rodrigues(np.radians([0.5, 1.0, 0.0]))[0]
        img_b, _ = render(scene, T_b, K)
        T_ba = relative_pose(torch.from_numpy(T_a)[None], torch.from_numpy(T_b)[None])[0].numpy()
        T, points, ok = bootstrap_pair(img_a, img_b, K.K(), K.K())
        assert ok, step
        assert rotation_angle_deg(T[:3, :3].T @ T_ba[:3, :3]) < 0.2
        if step == 0.01:
            assert _angle_deg(T[:3, 3], T_ba[:3, 3]) < 3.0
            assert np.isfinite(points[:, 2]).sum() >= 30
            assert np.nanmax(points[:, 2]) <= BOOTSTRAP_FAR_BASELINES
