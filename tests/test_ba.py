"""Bundle adjustment of odometry: its derivatives against finite differences, and its fit on a
rendered sequence with known poses and depth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from relocdepth.ba import (
    BAConfig,
    build_tracks,
    bundle_adjust,
    dense_schur_product,
    matrix_to_rotvec,
    path_scale,
    reprojection_jacobians,
    rescale_steps,
    rotation_prior_jacobians,
    rotvec_to_matrix,
    schur_product,
    triangulate,
)
from relocdepth.eval_geometry import apply_sim3, rotation_angle_deg, umeyama
from relocdepth.synth import SEVEN_SCENES_INTRINSICS, SynthConfig, build_scene, camera_paths, render
from relocdepth.vo import VOConfig, chain, world_trajectory

INTR = SEVEN_SCENES_INTRINSICS.scaled(128, 96)  # the demo scene's camera


@pytest.fixture(scope="module")
def rendered() -> dict:
    """24 frames of the demo scene's first path, every third (~2-3 cm and ~1.5 deg apart)."""
    cfg = SynthConfig(seed=0, frames=72, width=INTR.width, height=INTR.height)
    scene = build_scene(cfg.seed, cfg)
    T = camera_paths(cfg)["seq-01"][0:72:3]
    frames = [render(scene, P, INTR) for P in T]
    return {"T": T, "images": [f[0] for f in frames], "depth": [f[1] for f in frames]}


def _ate(T_est: np.ndarray, T_gt: np.ndarray, with_scale: bool = True) -> float:
    fit = umeyama(T_est[:, :3, 3], T_gt[:, :3, 3], with_scale=with_scale)
    T_al = apply_sim3(float(fit.scale), fit.R, fit.t, T_est)
    return float(np.sqrt(np.mean(np.sum((T_al[:, :3, 3] - T_gt[:, :3, 3]) ** 2, axis=1))))


def _relative_to_first(T: np.ndarray) -> np.ndarray:
    return np.linalg.inv(T[0]) @ T


def test_rotation_vectors_round_trip_against_opencv() -> None:
    rng = np.random.default_rng(0)
    r = np.concatenate([rng.normal(0, 1, (20, 3)), rng.normal(0, 1e-9, (3, 3)), np.zeros((1, 3))])
    R = rotvec_to_matrix(r)
    assert np.allclose(R, np.stack([cv2.Rodrigues(v)[0] for v in r]), atol=1e-12)
    assert np.allclose(matrix_to_rotvec(R[:20]), r[:20], atol=1e-9)


def test_triangulation_recovers_points_seen_from_known_cameras() -> None:
    rng = np.random.default_rng(1)
    X = rng.uniform([-1, -1, 3], [1, 1, 5], (10, 3))
    T_cw = np.stack([np.linalg.inv(np.r_[np.c_[rotvec_to_matrix(rng.normal(0, 0.05, (1, 3)))[0],
                                               rng.normal(0, 0.3, 3)], [[0, 0, 0, 1]]]) for _ in range(3)])
    frame, track = np.repeat(np.arange(3), 10), np.tile(np.arange(10), 3)
    Xc = np.einsum("mij,mj->mi", T_cw[frame, :3, :3], X[track]) + T_cw[frame, :3, 3]
    assert np.allclose(triangulate(T_cw, Xc[:, :2] / Xc[:, 2:], frame, track, 10), X, atol=1e-9)


def test_reprojection_derivatives_match_finite_differences() -> None:
    rng = np.random.default_rng(2)
    R = rotvec_to_matrix(rng.normal(0, 0.3, (5, 3)))
    t = rng.normal(0, 0.5, (5, 3))
    X = rng.normal(0, 0.5, (5, 3)) + (np.swapaxes(R, 1, 2) @ np.array([0, 0, 4.0]))  # in front
    f = np.array([300.0, 280.0])

    def pixels(R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
        Xc = np.einsum("mij,mj->mi", R, X) + t
        return f * Xc[:, :2] / Xc[:, 2:]

    Xc = np.einsum("mij,mj->mi", R, X) + t
    Jc, Jp = reprojection_jacobians(Xc, R, f)
    h = 1e-6
    for k in range(6):  # the camera's move X_c -> exp(w) X_c + v
        d = np.zeros((5, 6))
        d[:, k] = h
        step = rotvec_to_matrix(d[:, :3])
        moved = pixels(step @ R, np.einsum("mij,mj->mi", step, t) + d[:, 3:], X)
        assert np.allclose((moved - pixels(R, t, X)) / h, Jc[:, :, k], rtol=1e-4, atol=1e-3)
    for k in range(3):
        d = np.zeros((5, 3))
        d[:, k] = h
        assert np.allclose((pixels(R, t, X + d) - pixels(R, t, X)) / h, Jp[:, :, k], rtol=1e-4, atol=1e-3)


def test_rotation_prior_derivatives_match_finite_differences() -> None:
    """At the measured rotations (residual 0, where the fit holds them) the first-order
    derivatives are exact."""
    rng = np.random.default_rng(3)
    R = rotvec_to_matrix(rng.normal(0, 0.4, (4, 3)))
    M_T = np.swapaxes(R[1:] @ np.swapaxes(R[:-1], 1, 2), 1, 2)
    J = rotation_prior_jacobians(M_T, R)
    h = 1e-5  # OpenCV's Rodrigues rounds far smaller angles to 0
    for j in range(3):
        for side in range(2):  # move camera j (side 0) or j + 1 (side 1) of pair j
            for k in range(3):
                w = np.zeros((4, 3))
                w[j + side, k] = h
                Rm = rotvec_to_matrix(w) @ R
                r = matrix_to_rotvec(M_T[j:j + 1] @ Rm[j + 1:j + 2] @ Rm[j:j + 1].transpose(0, 2, 1))[0]
                assert np.allclose(r / h, J[j, side, :, k], atol=1e-4)


def test_the_reduced_systems_block_product_is_the_dense_one() -> None:
    """``schur_product`` is ``E B E^T`` written out densely: observations in any order, two at one
    (camera, point) place adding up, a camera that sees nothing with zero rows."""
    rng = np.random.default_rng(3)
    n_cam, n_pt, m = 5, 7, 40
    cam, pt = rng.integers(0, n_cam - 1, m), rng.integers(0, n_pt, m)  # the last camera sees nothing
    cam[1], pt[1] = cam[0], pt[0]  # two blocks at one place
    E, B = rng.normal(size=(m, 6, 3)), rng.normal(size=(n_pt, 3, 3))
    Ed, Bd = np.zeros((6 * n_cam, 3 * n_pt)), np.zeros((3 * n_pt, 3 * n_pt))
    for k in range(m):
        Ed[6 * cam[k]:6 * cam[k] + 6, 3 * pt[k]:3 * pt[k] + 3] += E[k]
    for p in range(n_pt):
        Bd[3 * p:3 * p + 3, 3 * p:3 * p + 3] = B[p]
    S = schur_product(E, B, cam, pt, n_cam)
    assert S.shape == (6 * n_cam, 6 * n_cam)
    np.testing.assert_allclose(S.toarray(), Ed @ Bd @ Ed.T, rtol=1e-12, atol=1e-12)
    assert not S.toarray()[-6:].any()
    for chunk in (2, 3, 256):  # several groups of points (one left short), and one group
        np.testing.assert_allclose(dense_schur_product(E, B, cam, pt, n_cam, chunk), Ed @ Bd @ Ed.T,
                                   rtol=1e-12, atol=1e-12)
    assert not dense_schur_product(E[:0], B, cam[:0], pt[:0], n_cam).any()  # no observations


def test_the_reduced_system_is_solved_when_rounding_leaves_it_indefinite() -> None:
    """Positive definite: Cholesky's solution; indefinite (no Cholesky factor): still solved;
    singular: NaN, which the fit answers with more damping."""
    from relocdepth.ba import _solve_positive_definite

    rng = np.random.default_rng(0)
    A = rng.normal(size=(12, 12))
    b = rng.normal(size=12)
    for S in (A @ A.T + np.eye(12), A + A.T):
        np.testing.assert_allclose(S @ _solve_positive_definite(S, b), b, atol=1e-9)
    assert np.isnan(_solve_positive_definite(np.zeros((12, 12)), b)).all()


def test_tracks_last_several_frames_and_follow_the_scene(rendered: dict) -> None:
    """Tracks on the rendered frames: most last 3 frames or more, and each track's pixels are the
    projections of one scene point (triangulated with the true poses, they reproject within 1 px)."""
    tr = build_tracks(rendered["images"])
    counts = np.bincount(tr.track)
    assert np.mean(counts[tr.track] >= 3) > 0.7
    T_cw = np.linalg.inv(rendered["T"])
    K = INTR.K()
    rays = (tr.xy - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
    X = triangulate(T_cw, rays, tr.frame, tr.track, tr.n_tracks)
    Xc = np.einsum("mij,mj->mi", T_cw[tr.frame, :3, :3], X[tr.track]) + T_cw[tr.frame, :3, 3]
    err = np.linalg.norm((Xc[:, :2] / Xc[:, 2:] - rays) * K[0, 0], axis=1)
    long = counts[tr.track] >= 3
    assert np.median(err[long]) < 0.3 and np.mean(err[long] < 1.0) > 0.9


def test_true_poses_stay_and_the_scale_comes_from_depth(rendered: dict) -> None:
    """Started at the truth, the fit stays near it (the tracks' own errors move it a few mm over
    the 0.6 m path), in metres; started at the truth shrunk to half its size, it comes to the same
    poses in metres: the points start at the depth maps' depths."""
    T = _relative_to_first(rendered["T"])
    K, depth = INTR.K(), rendered["depth"].__getitem__
    out = bundle_adjust(rendered["images"], K, T, depth)
    assert out.tracks > 300 and out.final_px < out.start_px and out.scale == pytest.approx(1.0, abs=0.05)
    assert _ate(out.T_wc, T, with_scale=False) < 0.025 and _ate(out.T_wc, T) < 0.01
    half = T.copy()
    half[:, :3, 3] *= 0.5
    shrunk = bundle_adjust(rendered["images"], K, half, depth)
    assert np.abs(shrunk.T_wc[:, :3, 3] - out.T_wc[:, :3, 3]).max() < 0.002
    # depth in other units (a network's): the result is in those units
    doubled = bundle_adjust(rendered["images"], K, T, lambda j: 2.0 * rendered["depth"][j])
    assert np.abs(doubled.T_wc[:, :3, 3] - 2.0 * out.T_wc[:, :3, 3]).max() < 0.004


def test_a_path_rescaled_step_by_step_recovers_known_step_lengths() -> None:
    """Steps shrunk by known per-frame factors, observations whose depth ratios say so: the path's
    scale per frame is read back (median over a frame's observations, no smoothing to speak of)
    and the rescaled path is the true one; frames without enough observations take their
    neighbours' scale; a window wider than the path gives one scale."""
    rng = np.random.default_rng(0)
    n = 12
    T = np.repeat(np.eye(4)[None], n, axis=0)
    T[:, :3, :3] = rotvec_to_matrix(np.c_[np.zeros(n), np.linspace(0, 0.5, n), np.zeros(n)])
    T[:, :3, 3] = np.cumsum(rng.normal(0, 0.1, (n, 3)), axis=0)
    log_s = 0.3 * np.sin(np.arange(n) / 3.0)  # the path's own scale error per frame
    frame = np.repeat(np.arange(n), 15)
    log_ratio = log_s[frame] + rng.normal(0, 0.003, len(frame))
    log_ratio[::15] = 5.0  # an outlier per frame: the median ignores it
    got = path_scale(frame, log_ratio, n, window=0.2)
    np.testing.assert_allclose(got, log_s, atol=0.01)
    shrunk = T.copy()  # each step scaled down by its frames' mean factor
    for j in range(1, n):
        shrunk[j, :3, 3] = shrunk[j - 1, :3, 3] + np.exp(-0.5 * (log_s[j] + log_s[j - 1])) * (T[j, :3, 3] - T[j - 1, :3, 3])
    back = rescale_steps(shrunk, got)
    np.testing.assert_allclose(back[:, :3, 3], T[:, :3, 3], atol=0.01)
    np.testing.assert_array_equal(back[:, :3, :3], shrunk[:, :3, :3])
    sparse = path_scale(frame[frame != 5], log_ratio[frame != 5], n, window=0.6)
    assert min(sparse[4], sparse[6]) - 0.01 <= sparse[5] <= max(sparse[4], sparse[6]) + 0.01
    wide = path_scale(frame, log_ratio, n, window=1e4)
    np.testing.assert_allclose(wide, np.mean(got), atol=0.01)
    assert not path_scale(frame, log_ratio, n, 1.0, min_observations=16).any()  # no frame has 16


def test_a_drift_along_the_path_is_fitted_through_stretches_of_error() -> None:
    """The path's scale drifting linearly, the depth maps' scale off by +-0.25 in stretches of
    eight frames (a network's kind of error): a line through the frames' scales follows the drift
    where a window follows the stretches; the fit weights frames by their observations, keeps to
    what two frames can say, and gives one scale at degree 0."""
    rng = np.random.default_rng(1)
    n = 48
    drift = np.linspace(0.2, -0.2, n)
    stretch = np.zeros(n)
    stretch[4:12], stretch[16:24], stretch[28:36], stretch[40:48] = 0.25, -0.25, -0.25, 0.25
    frame = np.repeat(np.arange(n), 20)
    log_ratio = (drift + stretch)[frame] + rng.normal(0, 0.01, len(frame))
    line = path_scale(frame, log_ratio, n, 0.0, degree=1)
    window = path_scale(frame, log_ratio, n, 3.0)
    assert np.abs(line - drift).max() < 0.06
    assert np.abs(window - drift).max() > 0.15
    obs = np.arange(len(frame))
    heavy = np.isin(frame, np.r_[4:12, 40:48])  # these frames keep all 20 observations, the rest 10
    keep = heavy | (obs % 20 < 10)
    count = np.where(np.isin(np.arange(n), np.r_[4:12, 40:48]), 20, 10)
    truth = drift + stretch
    weighted = np.sum(count * truth) / count.sum()
    assert abs(weighted - truth.mean()) > 0.03  # weighting matters here
    leaned = path_scale(frame[keep], log_ratio[keep], n, 0.0, degree=0)
    np.testing.assert_allclose(leaned, weighted, atol=0.01)
    two = np.isin(frame, [10, 30])
    got = path_scale(frame[two], log_ratio[two], n, 0.0, degree=3)  # a line through two frames
    np.testing.assert_allclose(np.diff(got, 2), 0.0, atol=1e-9)
    np.testing.assert_allclose(got[[10, 30]], [np.median(log_ratio[frame == 10]), np.median(log_ratio[frame == 30])],
                               atol=1e-9)
    assert np.ptp(path_scale(frame, log_ratio, n, 0.0, degree=0)) < 1e-12


@pytest.mark.parametrize("bad", [dict(scale_window=-1.0), dict(scale_window=float("nan")),
                                 dict(scale_window=float("inf")), dict(min_scale_observations=0),
                                 dict(max_iterations=-1), dict(scale_degree=-1),
                                 dict(scale_window=5.0, scale_degree=1)])
def test_a_config_that_cannot_be_fitted_is_refused(bad: dict) -> None:
    """A negative or undefined smoothing window (which would weight frames by a nonsense Gaussian),
    no observations needed for a frame's scale, or a negative number of steps: refused up front."""
    with pytest.raises(ValueError, match=list(bad)[-1]):
        BAConfig(**bad)
    BAConfig(scale_window=0.0, min_scale_observations=1, max_iterations=0)  # the edges are fine


def test_the_scale_along_the_path_follows_the_depth(rendered: dict) -> None:
    """Depth maps whose scale grows along the path (1.0 to 1.5, a network's kind of error): with
    ``scale_window``, or a line (``scale_degree`` 1), the fitted path's steps grow with it and the
    summary gives the factors' range; without either the path keeps one scale; with the true depth
    the window and the line leave the fit where it was."""
    T = _relative_to_first(rendered["T"])
    K, n = INTR.K(), len(T)
    grow = np.linspace(1.0, 1.5, n)
    plain = bundle_adjust(rendered["images"], K, T, lambda j: grow[j] * rendered["depth"][j])
    held = bundle_adjust(rendered["images"], K, T, lambda j: grow[j] * rendered["depth"][j],
                         BAConfig(scale_window=1.0))
    steps = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)

    def growth(out: np.ndarray) -> float:  # the last 8 steps' length over the first 8's, against the truth's
        got = np.linalg.norm(np.diff(out[:, :3, 3], axis=0), axis=1)
        return (got[-8:].sum() / steps[-8:].sum()) / (got[:8].sum() / steps[:8].sum())

    mid = 0.5 * (grow[1:] + grow[:-1])
    expected = mid[-8:].mean() / mid[:8].mean()  # ~1.41
    assert growth(held.T_wc) == pytest.approx(expected, rel=0.05)  # the steps follow the depth's scale
    assert growth(plain.T_wc) == pytest.approx(1.0, abs=0.05)  # one scale
    line = bundle_adjust(rendered["images"], K, T, lambda j: grow[j] * rendered["depth"][j],
                         BAConfig(scale_degree=1))
    assert growth(line.T_wc) == pytest.approx(expected, rel=0.05)
    for out in (held, line):
        low, high = out.summary()["held"]
        assert high / low == pytest.approx(1.5, rel=0.1)  # the frames' factors span the depth's growth
    assert plain.held is None and "held" not in plain.summary()
    true = bundle_adjust(rendered["images"], K, T, rendered["depth"].__getitem__)
    for cfg in (BAConfig(scale_window=1.0), BAConfig(scale_degree=1)):
        true_held = bundle_adjust(rendered["images"], K, T, rendered["depth"].__getitem__, cfg)
        assert np.abs(true_held.T_wc[:, :3, 3] - true.T_wc[:, :3, 3]).max() < 0.01


def test_drift_is_taken_out(rendered: dict) -> None:
    """The truth with a steady turn of 0.4 deg a frame added to every step (the odometry's kind of
    error, 9 deg by the last frame): the fit comes to the same poses as from the truth itself."""
    T = _relative_to_first(rendered["T"])
    turn = np.eye(4)
    turn[:3, :3] = rotvec_to_matrix(np.radians([[0.0, 0.4, 0.0]]))[0]
    drifted = [T[0]]
    for j in range(1, len(T)):
        drifted.append(drifted[-1] @ np.linalg.inv(T[j - 1]) @ T[j] @ turn)
    drifted = np.stack(drifted)
    K, depth = INTR.K(), rendered["depth"].__getitem__
    out = bundle_adjust(rendered["images"], K, drifted, depth)
    from_truth = bundle_adjust(rendered["images"], K, T, depth)
    assert rotation_angle_deg(drifted[-1, :3, :3].T @ T[-1, :3, :3]) > 9.0
    assert np.abs(out.T_wc[:, :3, 3] - from_truth.T_wc[:, :3, 3]).max() < 0.002
    assert rotation_angle_deg(np.swapaxes(out.T_wc[:, :3, :3], 1, 2) @ from_truth.T_wc[:, :3, :3]).max() < 0.2


@pytest.mark.parametrize("dense_cameras", [1000, 0])
def test_the_odometry_is_refined(rendered: dict, dense_cameras: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """From the odometry of the same frames (true depth), the fit is much nearer the truth, with
    the cameras' reduced system dense (Cholesky) and sparse (SuperLU) alike."""
    import relocdepth.ba as ba

    monkeypatch.setattr(ba, "DENSE_CAMERAS", dense_cameras)
    T = _relative_to_first(rendered["T"])
    K, depth = INTR.K(), rendered["depth"].__getitem__
    odometry = chain(rendered["images"], K, depth).T_wc
    out = bundle_adjust(rendered["images"], K, odometry, depth)
    assert _ate(out.T_wc, T) < 0.5 * _ate(odometry, T)


def test_a_frame_without_tracks_keeps_its_step_from_the_one_before(rendered: dict) -> None:
    images, T = rendered["images"][:8], _relative_to_first(rendered["T"][:8])
    tr = build_tracks(images)
    keep = tr.frame != 7
    tr.frame, tr.track, tr.xy = tr.frame[keep], tr.track[keep], tr.xy[keep]
    start = T.copy()
    start[7, :3, 3] += 0.05  # a start the tracks cannot correct
    out = bundle_adjust(images, INTR.K(), start, tracks=tr)
    step_in = np.linalg.inv(start[6]) @ start[7]
    assert np.allclose(np.linalg.inv(out.T_wc[6]) @ out.T_wc[7], step_in, atol=1e-9)


def test_world_trajectory_refines_each_sequence_when_asked(rendered: dict) -> None:
    """``VOConfig.bundle``: the odometry in the world trajectory is refined, and it says how."""
    images, K, depth = rendered["images"], INTR.K(), rendered["depth"].__getitem__
    w = world_trajectory([images], [K], [depth], VOConfig(bundle=True))
    assert w.bundled is not None and w.bundled[0]["tracks"] > 300
    assert w.bundled[0]["final_px"] < w.bundled[0]["start_px"]
    assert np.allclose(w.world[0], bundle_adjust(images, K, chain(images, K, depth).T_wc, depth).T_wc)
    assert world_trajectory([images], [K], [depth], VOConfig()).bundled is None
    chained = BAConfig(first_view_px=0.0)  # ... with the fit it is given
    w = world_trajectory([images], [K], [depth], VOConfig(bundle=True, bundle_cfg=chained))
    expected = bundle_adjust(images, K, chain(images, K, depth).T_wc, depth, chained).T_wc
    assert np.allclose(w.world[0], expected)
    assert not np.allclose(expected, bundle_adjust(images, K, chain(images, K, depth).T_wc, depth).T_wc)


def test_nothing_to_fit_returns_the_poses_as_given() -> None:
    """No track seen twice: the poses come back as given."""
    T = np.repeat(np.eye(4)[None], 3, axis=0)
    T[:, 0, 3] = [0.0, 0.1, 0.2]
    flat = [np.full((96, 128, 3), 128, np.uint8)] * 3  # no corners at all
    out = bundle_adjust(flat, INTR.K(), T, cfg=BAConfig())
    assert out.tracks == 0 and np.allclose(out.T_wc, T)


def test_track_steps_off_the_pairs_epipolar_geometry_are_dropped() -> None:
    """Two views 30 cm apart of 150 points, 20 more points that move on their own (3-6 px, across
    the epipolar lines): the check keeps the first and ends the others; with too few points to fit
    a fundamental matrix it keeps all."""
    from relocdepth.ba import _epipolar_inliers

    rng = np.random.default_rng(4)
    K = INTR.K()
    X = rng.uniform([-1.5, -1, 2], [1.5, 1, 5], (170, 3))
    R = rotvec_to_matrix(np.radians([[1.0, 3.0, 0.5]]))[0]
    a = X @ K.T
    b = (X @ R.T + np.array([0.3, 0.02, 0.05])) @ K.T
    a, b = a[:, :2] / a[:, 2:], b[:, :2] / b[:, 2:]
    b[150:, 1] += rng.choice([-1, 1], 20) * rng.uniform(3, 6, 20)  # the baseline is along x
    keep = np.ones(170, bool)
    kept = _epipolar_inliers(a.astype(np.float32), b.astype(np.float32), keep, 1.0)
    assert kept[:150].mean() > 0.97 and not kept[150:].any()
    few = np.zeros(170, bool)
    few[:10] = True
    assert (_epipolar_inliers(a.astype(np.float32), b.astype(np.float32), few, 1.0) == few).all()


def test_tracks_go_on_where_no_fundamental_matrix_can_be_fitted(rendered: dict, monkeypatch) -> None:
    """OpenCV's MAGSAC++ asserts (cv2.error) on some sets of moves, e.g. KLT tracks that ran into
    one another: the check keeps every move then, and the tracks go on as without it."""
    from relocdepth.ba import _epipolar_inliers

    def asserts(*args, **kwargs):
        raise cv2.error("(-215:Assertion failed) !model.empty() in function 'setModelParameters'")

    unchecked = build_tracks(rendered["images"][:6], epipolar_px=0.0)
    monkeypatch.setattr(cv2, "findFundamentalMat", asserts)
    a = np.random.default_rng(0).uniform(0, 90, (40, 2)).astype(np.float32)
    keep = np.ones(40, bool)
    keep[3] = False
    assert (_epipolar_inliers(a, a + 2, keep, 1.0) == keep).all()
    tr = build_tracks(rendered["images"][:6])
    assert np.array_equal(tr.track, unchecked.track) and np.allclose(tr.xy, unchecked.xy)


def test_tracks_from_their_first_views_keep_the_fit_from_bending() -> None:
    """The demo scene's first path, 50 frames ~2 cm apart, adjusted from its true poses with the
    true depth: frame-to-frame steps alone drift (sub-pixel each, adding up along a track), and
    the fit bends to them, the path coming out >10 % too long and turned >3 deg; each step tracked
    again from the track's first view keeps it within 5 % and 2 deg."""
    cfg = SynthConfig(seed=0, frames=150, width=INTR.width, height=INTR.height)
    scene = build_scene(cfg.seed, cfg)
    T = camera_paths(cfg)["seq-01"][0:150:3]
    frames = [render(scene, P, INTR) for P in T]
    images, depth = [f[0] for f in frames], [f[1] for f in frames]
    T = _relative_to_first(T)

    def bend(first_view_px: float) -> tuple[float, float]:
        out = bundle_adjust(images, INTR.K(), T, depth.__getitem__, BAConfig(first_view_px=first_view_px)).T_wc
        length = np.linalg.norm(np.diff(out[:, :3, 3], axis=0), axis=1).sum() \
            / np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1).sum()
        turned = rotation_angle_deg(np.swapaxes(out[:, :3, :3], -1, -2) @ T[:, :3, :3])
        return float(length), float(np.median(turned))

    length, turned = bend(0.0)
    assert length > 1.1 and turned > 3.0
    length, turned = bend(BAConfig().first_view_px)
    assert abs(length - 1) < 0.05 and turned < 2.0
