"""Keyframe odometry and cross-sequence registration on rendered sequences with known poses."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from relocdepth.eval_geometry import apply_sim3, rotation_angle_deg, umeyama
from relocdepth.synth import SEVEN_SCENES_INTRINSICS, SynthConfig, build_scene, camera_paths, render
from relocdepth.twoview import as_grey, detect_corners, track_points
from relocdepth.vo import (
    VOConfig,
    align_chain,
    chain,
    depth_pair_pose,
    pair_pose,
    register,
    robust_mean_transform,
    sample_depth,
    wide_pair_pose,
)

INTR = SEVEN_SCENES_INTRINSICS.scaled(128, 96)  # the demo scene's camera
STRIDE = 2  # every other frame of the demo path: ~1.5 cm and ~1 deg apart


def _rigid(rotvec_deg: tuple[float, float, float], t: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.radians(np.asarray(rotvec_deg, np.float64)))[0]
    T[:3, 3] = t
    return T


@pytest.fixture(scope="module")
def rendered() -> dict:
    """Sequence A: 20 frames of the demo scene's first path; sequence B: 8 frames of the same path
    (odd frames, from frame 9 on) seen from a camera rig moved by a known rigid transform."""
    cfg = SynthConfig(seed=0, frames=60, width=INTR.width, height=INTR.height)
    scene = build_scene(cfg.seed, cfg)
    path = camera_paths(cfg)["seq-01"]
    T_a = path[0:40:STRIDE]
    shift = _rigid((1.0, -2.0, 1.5), (0.04, -0.03, 0.02))  # world from the rig's world
    T_b = np.stack([shift @ T for T in path[9:25:STRIDE]])
    out = {"T_a": T_a, "T_b": T_b}
    for name, poses in (("a", T_a), ("b", T_b)):
        frames = [render(scene, T, INTR) for T in poses]
        out[f"img_{name}"] = [f[0] for f in frames]
        out[f"depth_{name}"] = [f[1] for f in frames]
    return out


def _aligned_centres(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[float, np.ndarray]:
    fit = umeyama(T_est[:, :3, 3], T_gt[:, :3, 3], with_scale=True)
    s, R, t = fit.scale, fit.R, fit.t
    T_al = apply_sim3(float(s), R, t, T_est)
    return float(s), np.linalg.norm(T_al[:, :3, 3] - T_gt[:, :3, 3], axis=1)


def test_sample_depth_is_bilinear_and_skips_invalid() -> None:
    y, x = np.mgrid[0:6, 0:8].astype(np.float64)
    depth = 1.0 + 0.5 * x + 0.25 * y  # bilinear interpolation reproduces a plane exactly
    pts = np.array([[2.5, 3.25], [0.0, 0.0], [7.0, 5.0], [6.9, 4.1]])
    assert np.allclose(sample_depth(depth, pts), 1.0 + 0.5 * pts[:, 0] + 0.25 * pts[:, 1])
    depth[3, 2] = 0.0  # invalid: any sample that touches it is unknown
    out = sample_depth(depth, np.array([[2.5, 3.25], [5.5, 1.5], [-0.5, 1.0], [8.5, 1.0]]))
    assert np.isnan(out[0]) and np.isfinite(out[1]) and np.isnan(out[2:]).all()


def test_robust_mean_ignores_outlying_links() -> None:
    rng = np.random.default_rng(0)
    truth = _rigid((10.0, -20.0, 5.0), (0.3, -0.1, 0.2))
    links = [truth @ _rigid(tuple(rng.normal(0, 0.5, 3)), tuple(rng.normal(0, 0.01, 3)))
             for _ in range(20)]
    links += [_rigid(tuple(rng.uniform(-90, 90, 3)), tuple(rng.uniform(-1, 1, 3))) for _ in range(8)]
    T, inl = robust_mean_transform(np.stack(links), inlier_deg=5.0)
    assert inl[:20].all() and not inl[20:].any()
    assert rotation_angle_deg(T[:3, :3].T @ truth[:3, :3]) < 0.5
    assert np.linalg.norm(T[:3, 3] - truth[:3, 3]) < 0.01


def test_chain_with_true_depth_is_metric(rendered: dict) -> None:
    T_gt = rendered["T_a"]
    depth = rendered["depth_a"]
    traj = chain(rendered["img_a"], INTR.K(), depth.__getitem__)
    assert np.allclose(traj.T_wc[0], np.eye(4))
    assert len(traj.keyframes) >= 5 and not traj.lost
    scale, err = _aligned_centres(traj.T_wc, T_gt)
    path_len = np.linalg.norm(np.diff(T_gt[:, :3, 3], axis=0), axis=1).sum()
    assert path_len > 0.2  # the camera does travel: the errors below mean something
    assert abs(scale - 1.0) < 0.1, scale  # true depth in metres: the chain is in metres
    assert np.sqrt(np.mean(err ** 2)) < 0.1 * path_len, (err, path_len)
    # relative rotations need no alignment
    R_rel = np.linalg.inv(traj.T_wc[0])[:3, :3] @ traj.T_wc[-1][:3, :3]
    R_gt = T_gt[0, :3, :3].T @ T_gt[-1, :3, :3]
    assert rotation_angle_deg(R_rel.T @ R_gt) < 2.0


def test_chain_scale_follows_the_depth_units(rendered: dict) -> None:
    depth = [3.0 * d for d in rendered["depth_a"][:10]]  # a depth in other units (x3)
    traj = chain(rendered["img_a"][:10], INTR.K(), depth.__getitem__)
    scale, _ = _aligned_centres(traj.T_wc, rendered["T_a"][:10])
    assert abs(scale - 1 / 3) < 0.05, scale


def test_register_recovers_the_rig_transform(rendered: dict) -> None:
    K = INTR.K()
    tr_a = chain(rendered["img_a"], K, rendered["depth_a"].__getitem__)
    tr_b = chain(rendered["img_b"], K, rendered["depth_b"].__getitem__)
    reg = register(rendered["img_a"], tr_a.T_wc, K, rendered["depth_a"].__getitem__,
                   rendered["img_b"], tr_b.T_wc, K)
    truth = np.linalg.inv(rendered["T_a"][0]) @ rendered["T_b"][0]  # A's world from B's world
    assert reg.inliers >= 3
    assert rotation_angle_deg(reg.T[:3, :3].T @ truth[:3, :3]) < 2.0
    assert np.linalg.norm(reg.T[:3, 3] - truth[:3, 3]) < 0.03, (reg.T[:3, 3], truth[:3, 3])


@pytest.mark.parametrize("frame,move,turn", [
    (0, (0.25, 0.05, 0.0), (0.0, -15.0, 0.0)),  # 25 cm sideways, turned back toward the scene
    (40, None, None),  # 40 frames along the demo path: 11 cm and 14 deg, beyond KLT's reach
])
def test_wide_pair_pose_is_metric_across_wide_baselines(frame: int, move: tuple | None,
                                                        turn: tuple | None) -> None:
    cfg = SynthConfig(seed=0, frames=frame + 1, width=INTR.width, height=INTR.height)
    scene = build_scene(cfg.seed, cfg)
    path = camera_paths(cfg)["seq-01"]
    T_a = path[0]
    T_b = path[frame] if move is None else T_a @ _rigid(turn, move)  # moved in camera a's axes
    (img_a, depth_a), (img_b, _) = render(scene, T_a, INTR), render(scene, T_b, INTR)
    truth = np.linalg.inv(T_b) @ T_a  # T_{b<-a}, metres
    assert rotation_angle_deg(truth[:3, :3]) > 10 and np.linalg.norm(truth[:3, 3]) > 0.1
    p = wide_pair_pose(img_a, img_b, INTR.K(), INTR.K(), depth_a)
    assert p.ok and p.measured
    assert rotation_angle_deg(p.T[:3, :3].T @ truth[:3, :3]) < 1.0
    assert np.linalg.norm(p.T[:3, 3] - truth[:3, 3]) < 0.03, (p.T[:3, 3], truth[:3, 3])


@pytest.fixture(scope="module")
def fast_turns() -> list[tuple]:
    """Pairs of the demo scene's first frame and a view turned 20-25 deg about a 4-6 cm move (a
    head turning): (image a, depth a, image b, T_{b<-a})."""
    cfg = SynthConfig(seed=0, frames=1, width=INTR.width, height=INTR.height)
    scene = build_scene(cfg.seed, cfg)
    T_a = camera_paths(cfg)["seq-01"][0]
    img_a, depth_a = render(scene, T_a, INTR)
    out = []
    for turn, move in (((0.0, 20.0, 0.0), (0.05, 0.0, 0.0)), ((5.0, 20.0, 0.0), (0.04, 0.02, 0.0)),
                       ((0.0, -22.0, 3.0), (0.06, 0.0, 0.0))):
        T_b = T_a @ _rigid(turn, move)
        out.append((img_a, depth_a, render(scene, T_b, INTR)[0], np.linalg.inv(T_b) @ T_a))
    return out


def _pose_errors(T: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    return rotation_angle_deg(T[:3, :3].T @ truth[:3, :3]), float(np.linalg.norm(T[:3, 3] - truth[:3, 3]))


def test_depth_pair_pose_measures_fast_turns_the_essential_matrix_misses(fast_turns: list) -> None:
    for img_a, depth_a, img_b, truth in fast_turns:
        essential = pair_pose(img_a, img_b, INTR.K(), INTR.K(), depth_a)
        assert _pose_errors(essential.T, truth)[0] > 3.0  # the case this is for
        p = depth_pair_pose(img_a, img_b, INTR.K(), INTR.K(), depth_a)
        assert p.ok and p.measured
        r_err, t_err = _pose_errors(p.T, truth)
        assert r_err < 1.0 and t_err < 0.015, (r_err, t_err)
        # the translation is in the depth's units, the rotation does not depend on them
        p3 = depth_pair_pose(img_a, img_b, INTR.K(), INTR.K(), 3.0 * depth_a)
        assert rotation_angle_deg(p3.T[:3, :3].T @ p.T[:3, :3]) < 0.1
        assert np.allclose(p3.T[:3, 3], 3.0 * p.T[:3, 3], atol=1e-3)
        assert abs(p.baseline_px - INTR.fx * np.linalg.norm(truth[:3, 3]) / np.median(depth_a)) < 1.0


def test_pair_pose_takes_pnp_only_for_pairs_with_few_tracks(fast_turns: list, rendered: dict) -> None:
    K = INTR.K()
    img_a, depth_a, img_b, truth = fast_turns[0]
    tracks = len(track_points(as_grey(img_a), as_grey(img_b), detect_corners(as_grey(img_a)))[0])
    few = pair_pose(img_a, img_b, K, K, depth_a, VOConfig(pnp_below=tracks + 1))
    assert np.allclose(few.T, depth_pair_pose(img_a, img_b, K, K, depth_a).T)
    assert _pose_errors(few.T, truth)[0] < 1.0
    enough = pair_pose(img_a, img_b, K, K, depth_a, VOConfig(pnp_below=tracks))
    assert np.allclose(enough.T, pair_pose(img_a, img_b, K, K, depth_a).T)
    # PnP with too few inliers keeps the essential matrix's pose
    kept = pair_pose(img_a, img_b, K, K, depth_a, VOConfig(pnp_below=tracks + 1, pnp_min_inliers=10**6))
    assert np.allclose(kept.T, enough.T)
    # neighbouring frames track well: their pose is the essential matrix's
    a, b, d = rendered["img_a"][0], rendered["img_a"][1], rendered["depth_a"][0]
    n = len(track_points(as_grey(a), as_grey(b), detect_corners(as_grey(a)))[0])
    assert n > 60
    assert np.allclose(pair_pose(a, b, K, K, d, VOConfig(pnp_below=60)).T, pair_pose(a, b, K, K, d).T)


def test_pairs_without_texture_fail() -> None:
    blank = np.full((INTR.height, INTR.width, 3), 128, np.uint8)
    depth = np.ones((INTR.height, INTR.width), np.float32)
    for pose in (pair_pose, wide_pair_pose, depth_pair_pose):
        p = pose(blank, blank, INTR.K(), INTR.K(), depth)
        assert not p.ok and not p.measured and np.allclose(p.T, np.eye(4))


def test_world_trajectory_puts_every_sequence_in_the_first_ones_world(rendered: dict) -> None:
    from relocdepth.vo import world_trajectory

    K = INTR.K()
    w = world_trajectory([rendered["img_a"], rendered["img_b"]], [K, K],
                         [rendered["depth_a"].__getitem__, rendered["depth_b"].__getitem__])
    assert len(w.trajs) == 2 and len(w.regs) == 1 and [len(x) for x in w.world] == [20, 8]
    world_of_a = np.linalg.inv(rendered["T_a"][0])  # A's first frame is the world
    for est, T_gt in zip(w.world, (rendered["T_a"], rendered["T_b"])):
        truth = world_of_a @ T_gt
        assert np.linalg.norm(est[:, :3, 3] - truth[:, :3, 3], axis=1).max() < 0.05
        assert rotation_angle_deg(np.swapaxes(est[:, :3, :3], -1, -2) @ truth[:, :3, :3]).max() < 3.0
    with pytest.raises(ValueError):
        world_trajectory([rendered["img_a"]], [K, K], [rendered["depth_a"].__getitem__])


def test_join_sequences_puts_poses_of_other_worlds_in_the_first_ones(rendered: dict) -> None:
    """Each sequence's poses right within themselves but in a world of its own (B's moved by a
    known 12 deg / 30 cm transform): the links put B's in A's world, the first stays as given."""
    from relocdepth.vo import join_sequences

    K = INTR.K()
    world_of_a = np.linalg.inv(rendered["T_a"][0])
    T_a = world_of_a @ rendered["T_a"]
    elsewhere = _rigid((4.0, 10.0, -5.0), (0.2, -0.1, 0.2))  # B's own world
    T_b_own = elsewhere @ world_of_a @ rendered["T_b"]
    regs, world = join_sequences([rendered["img_a"], rendered["img_b"]], [K, K], [T_a, T_b_own],
                                 [rendered["depth_a"].__getitem__, rendered["depth_b"].__getitem__])
    assert len(regs) == 1 and regs[0].inliers >= 3 and np.allclose(world[0], T_a)
    truth = world_of_a @ rendered["T_b"]
    assert rotation_angle_deg(np.swapaxes(T_b_own[:, :3, :3], -1, -2) @ truth[:, :3, :3]).min() > 10  # can fail
    assert np.linalg.norm(world[1][:, :3, 3] - truth[:, :3, 3], axis=1).max() < 0.05
    assert rotation_angle_deg(np.swapaxes(world[1][:, :3, :3], -1, -2) @ truth[:, :3, :3]).max() < 3.0
    with pytest.raises(ValueError):
        join_sequences([rendered["img_a"]], [K, K], [T_a], [rendered["depth_a"].__getitem__])


def test_join_sequences_leaves_a_sequence_without_consensus_where_it_was(rendered: dict) -> None:
    """A sequence with nothing to link (blank frames) is not placed: its registration says so
    (no agreeing link) and its poses stay as given; the others are placed as without it."""
    from relocdepth.vo import MIN_LINK_INLIERS, join_sequences

    K = INTR.K()
    world_of_a = np.linalg.inv(rendered["T_a"][0])
    T_a, T_b = world_of_a @ rendered["T_a"], world_of_a @ rendered["T_b"]
    blank = [np.full_like(rendered["img_a"][0], 128) for _ in range(6)]
    T_blank = np.repeat(_rigid((0.0, 30.0, 0.0), (1.0, 0.0, 0.0))[None], 6, axis=0)
    flat = np.ones_like(rendered["depth_a"][0])
    regs, world = join_sequences([rendered["img_a"], blank, rendered["img_b"]], [K] * 3, [T_a, T_blank, T_b],
                                 [rendered["depth_a"].__getitem__, lambda j: flat, rendered["depth_b"].__getitem__])
    assert len(regs) == 2 and regs[0].inliers < MIN_LINK_INLIERS <= regs[1].inliers
    assert np.allclose(world[1], T_blank) and np.allclose(world[0], T_a)
    assert np.linalg.norm(world[2][:, :3, 3] - T_b[:, :3, 3], axis=1).max() < 0.05


def test_join_sequences_places_a_sequence_by_the_ones_it_overlaps() -> None:
    """Four paths of a generated scene (every 10th frame of 500), each in a world of its own: the
    fourth shares too little view with the first to be registered into it alone, so the
    sequences are placed best linked first, each linked to every one placed before it. Listed
    second, the fourth is still placed last, by the paths it overlaps."""
    from relocdepth.vo import MIN_LINK_INLIERS, join_sequences

    cfg = SynthConfig(seed=0, frames=500, width=INTR.width, height=INTR.height, train_sequences=4)
    scene = build_scene(cfg.seed, cfg)
    paths = camera_paths(cfg)
    K = INTR.K()
    rng = np.random.default_rng(0)
    world_of_first = np.linalg.inv(paths["seq-01"][0])
    images, depth, T_own, truth = [], [], [], []
    for i, name in enumerate(("seq-01", "seq-04", "seq-02", "seq-03")):
        poses = paths[name][::10]
        frames = [render(scene, T, INTR) for T in poses]
        images.append([f[0] for f in frames])
        depth.append([f[1] for f in frames])
        own = np.eye(4) if i == 0 else _rigid(tuple(rng.normal(0, 8, 3)), tuple(rng.normal(0, 0.2, 3)))
        truth.append(world_of_first @ poses)
        T_own.append(own @ truth[-1])
    alone = register(images[0], T_own[0], K, depth[0].__getitem__, images[1], T_own[1], K)
    misplaced = np.linalg.norm((alone.T @ T_own[1])[:, :3, 3] - truth[1][:, :3, 3], axis=1).max()
    assert alone.inliers < MIN_LINK_INLIERS or misplaced > 0.1, (alone, misplaced)  # can fail
    regs, world = join_sequences(images, [K] * 4, T_own, [d.__getitem__ for d in depth])
    assert all(r.inliers >= MIN_LINK_INLIERS for r in regs), regs
    assert regs[0].links > alone.links  # the fourth was linked to more than the first path
    for est, T_gt in zip(world, truth):
        assert np.linalg.norm(est[:, :3, 3] - T_gt[:, :3, 3], axis=1).max() < 0.05
        assert rotation_angle_deg(np.swapaxes(est[:, :3, :3], -1, -2) @ T_gt[:, :3, :3]).max() < 3.0


def test_align_chain_with_true_depth_is_more_precise_than_the_pairs(rendered: dict) -> None:
    # 3 mm against the pairs' 11 mm here (the rotation over the 20 frames: 1.3 deg against 0.9)
    T_gt, depth, images = rendered["T_a"], rendered["depth_a"], rendered["img_a"]
    traj = chain(images, INTR.K(), depth.__getitem__)
    T, trusted = align_chain(images, INTR.K(), depth.__getitem__, traj.T_wc)
    assert trusted == len(images) - 1 and np.array_equal(T[0], traj.T_wc[0])
    _, err_pairs = _aligned_centres(traj.T_wc, T_gt)
    scale, err = _aligned_centres(T, T_gt)
    assert abs(scale - 1.0) < 0.05, scale  # still metric
    rms = lambda e: float(np.sqrt(np.mean(e ** 2)))  # noqa: E731
    assert rms(err) < 0.5 * rms(err_pairs) and rms(err) < 0.01, (rms(err), rms(err_pairs))


def test_world_trajectory_aligns_each_sequence_when_asked(rendered: dict) -> None:
    """``VOConfig(align=True)``: every sequence's odometry is refined frame to frame before the
    sequences are joined (the first sequence, the world, is then its refined chain), and the world
    counts the trusted alignments."""
    from relocdepth.vo import VOConfig, world_trajectory

    K = INTR.K()
    args = ([rendered["img_a"], rendered["img_b"]], [K, K], [rendered["depth_a"].__getitem__,
                                                            rendered["depth_b"].__getitem__])
    plain, aligned = world_trajectory(*args), world_trajectory(*args, VOConfig(align=True))
    assert plain.aligned == 0 and aligned.aligned == (20 - 1) + (8 - 1)
    refined, _ = align_chain(rendered["img_a"], K, rendered["depth_a"].__getitem__, plain.trajs[0].T_wc)
    assert np.allclose(aligned.world[0], refined)
    rms = lambda e: float(np.sqrt(np.mean(e ** 2)))  # noqa: E731
    errs = [rms(_aligned_centres(w.world[0], rendered["T_a"])[1]) for w in (plain, aligned)]
    assert errs[1] < 0.5 * errs[0], errs


def test_align_chain_keeps_the_odometry_where_no_alignment_is_trusted(rendered: dict) -> None:
    blank = [np.full_like(im, 128) for im in rendered["img_a"][:5]]
    traj = chain(rendered["img_a"][:5], INTR.K(), rendered["depth_a"].__getitem__)
    T, trusted = align_chain(blank, INTR.K(), rendered["depth_a"].__getitem__, traj.T_wc)
    assert trusted == 0 and np.allclose(T, traj.T_wc)
