"""Direct alignment against geometry: rendered views with known poses and depth, the Jacobian
against finite differences, a known pose recovered from a rough one."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from relocdepth.eval_geometry import rotation_angle_deg
from relocdepth.photoalign import AlignConfig, View, _Level, _pyramid, _select, _update, align
from relocdepth.synth import SEVEN_SCENES_INTRINSICS, SynthConfig, build_scene, camera_paths, render

INTR = SEVEN_SCENES_INTRINSICS.scaled(160, 120)


def _rigid(rotvec_deg, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.radians(np.asarray(rotvec_deg, np.float64)))[0]
    T[:3, 3] = t
    return T


def _errors(T: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    return (float(np.linalg.norm(T[:3, 3] - truth[:3, 3])),
            float(rotation_angle_deg(T[:3, :3].T @ truth[:3, :3])))


@pytest.fixture(scope="module")
def scene() -> dict:
    """Frames 0-40 of the demo path (~1 cm apart): views 12 and 28, queries between them."""
    cfg = SynthConfig(seed=0, frames=60, width=INTR.width, height=INTR.height)
    world = build_scene(cfg.seed, cfg)
    path = camera_paths(cfg)["seq-01"]
    frames = {i: render(world, path[i], INTR) for i in (12, 16, 20, 24, 28)}
    views = [View(frames[i][0], frames[i][1], INTR.K(), path[i]) for i in (12, 28)]
    return {"path": path, "frames": frames, "views": views}


def test_jacobian_matches_finite_differences(scene: dict) -> None:
    """The analytic J^T r equals the finite-difference gradient of the squared residual (no
    Huber clipping), brightness refitted at each point (it is optimal, so it does not move it).
    The query is blurred: on the rendered scene's sharp edges the central-difference image
    gradient and the bilinear interpolant's own slope differ (as on any sampled image)."""
    cfg = AlignConfig(huber=10.0)
    grey = cv2.GaussianBlur(cv2.cvtColor(scene["frames"][20][0], cv2.COLOR_RGB2GRAY), (0, 0), 1.5)
    query = _pyramid(grey, INTR.K(), 1, 320)[0]
    level = _Level([_select(v, 1, cfg)[0] for v in scene["views"]], *query, cfg)
    T = scene["path"][20] @ _rigid((0.5, -0.4, 0.3), (0.004, -0.003, 0.002))
    cost, inside, (J, r, w) = level.evaluate(T, jacobian=True)
    assert inside > 0.8 and np.all(w == 1.0)
    analytic = J.T @ r / level.n
    eps = 1e-3
    numeric = np.array([(level.evaluate(_update(T, e), False)[0] - level.evaluate(_update(T, -e), False)[0]) / (2 * eps)
                        for e in np.eye(6) * eps])
    np.testing.assert_allclose(numeric, analytic, rtol=0.15, atol=0.02 * np.abs(analytic).max())


@pytest.mark.parametrize("offset", [((2.0, -3.0, 1.5), (0.03, -0.02, 0.02)),
                                    ((0.0, 4.0, -2.0), (-0.08, 0.04, 0.06)),
                                    ((0.0, 0.0, 0.0), (0.15, 0.0, 0.1))])
def test_a_rough_pose_comes_back_to_the_true_one(scene: dict, offset) -> None:
    """Starts 4-18 cm and up to 4.5 deg off come back to within 5 mm and 0.3 deg, also when the
    query's exposure differs from the views' (gain 0.8, offset +20 grey levels)."""
    truth = scene["path"][16]
    image = np.clip(scene["frames"][16][0].astype(np.float32) * 0.8 + 20, 0, 255).astype(np.uint8)
    start = truth @ _rigid(*offset)
    assert _errors(start, truth)[0] > 0.035
    res = align(scene["views"], image, INTR.K(), start)
    t_err, r_err = _errors(res.T_wc, truth)
    assert t_err < 0.005 and r_err < 0.3, (t_err, r_err)
    assert res.accepted and res.cost < 0.5 * res.start_cost and res.inside > 0.8


def test_the_truth_stays(scene: dict) -> None:
    """From the true pose it stays; a query at half the exposure explains the views as well (the
    brightness gain and offset are fitted)."""
    truth = scene["path"][24]
    res = align(scene["views"], scene["frames"][24][0], INTR.K(), truth)
    t_err, r_err = _errors(res.T_wc, truth)
    assert t_err < 0.002 and r_err < 0.1, (t_err, r_err)
    assert res.cost <= res.start_cost and res.cost < 0.3 * res.null_cost
    dark = (scene["frames"][24][0] // 2 + 10).astype(np.uint8)
    res_dark = align(scene["views"], dark, INTR.K(), truth)
    assert res_dark.start_cost < 1.5 * res.start_cost, (res_dark.start_cost, res.start_cost)


def test_a_query_the_views_do_not_explain_is_not_accepted(scene: dict) -> None:
    """A blank query, or views of another place (the query's pose turned 180 deg), explain nothing
    beyond the views' mean brightness: not accepted."""
    truth = scene["path"][20]
    blank = np.full_like(scene["frames"][20][0], 128)
    assert not align(scene["views"], blank, INTR.K(), truth).accepted
    away = truth @ _rigid((0.0, 180.0, 0.0), (0.0, 0.0, 0.0))
    res = align(scene["views"], scene["frames"][20][0], INTR.K(), away)
    assert not res.accepted and res.inside < 0.1
    assert align(scene["views"], scene["frames"][20][0], INTR.K(), truth).accepted
