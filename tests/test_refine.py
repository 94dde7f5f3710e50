"""Pose refinement against the nearest training frames, on rendered frames with known poses and
depth: a rough pose comes back to the true one, in the map's own units."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from relocdepth.eval_geometry import rotation_angle_deg
from relocdepth.refine import Reference, RefFrame, RefineConfig, refine_pose, track_size
from relocdepth.synth import SEVEN_SCENES_INTRINSICS, SynthConfig, build_scene, camera_paths, render

INTR = SEVEN_SCENES_INTRINSICS.scaled(128, 96)  # the demo scene's camera
UNITS = 0.25  # the map's units per metre: a network's world has its own scale


def _rigid(rotvec_deg, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.radians(np.asarray(rotvec_deg, np.float64)))[0]
    T[:3, 3] = t
    return T


def _scaled(T: np.ndarray, s: float) -> np.ndarray:
    T = T.copy()
    T[..., :3, 3] *= s
    return T


@pytest.fixture(scope="module")
def rendered() -> dict:
    """The map: every 6th frame of the demo path's first 60 (~5 cm apart), poses and depth in
    map units; the queries: frames between them."""
    cfg = SynthConfig(seed=0, frames=60, width=INTR.width, height=INTR.height)
    scene = build_scene(cfg.seed, cfg)
    path = camera_paths(cfg)["seq-01"]
    mine, queries = list(range(0, 60, 6)), [9, 21, 33, 45]
    frames = {i: render(scene, path[i], INTR) for i in mine + queries}
    return {"path": path, "map": mine, "queries": queries, "frames": frames}


def _reference(rendered: dict, loads: list[int] | None = None) -> Reference:
    mine = rendered["map"]

    def load(j: int) -> RefFrame:
        if loads is not None:
            loads.append(j)
        img, depth = rendered["frames"][mine[j]][:2]
        return RefFrame(img, INTR.K(), depth * UNITS)

    return Reference(_scaled(rendered["path"][mine], UNITS), load)


def _refine(*args) -> tuple[np.ndarray, int, str]:
    r = refine_pose(*args)
    return r.T_wc, r.pairs, r.by


def _errors(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Centre error in metres (the map is in UNITS), rotation error in degrees."""
    return (float(np.linalg.norm(T[:3, 3] - T_true[:3, 3]) / UNITS),
            float(rotation_angle_deg(T[:3, :3].T @ T_true[:3, :3])))


def test_rough_pose_comes_back_to_the_true_one(rendered: dict) -> None:
    """Poses ~4 cm and ~4 deg off (under the map's spacing) come back to within the pairs' own
    precision at 128x96 (0.1-3 cm, 0.1-1.5 deg per pair), the pairs alone (no alignment)."""
    ref = _reference(rendered)
    t_errs = []
    for q in rendered["queries"]:
        truth = _scaled(rendered["path"][q], UNITS)
        rough = truth @ _rigid((2.0, -3.0, 1.5), (0.03 * UNITS, -0.02 * UNITS, 0.02 * UNITS))
        assert _errors(rough, truth)[0] > 0.04
        T, agreeing, by = _refine(ref, rendered["frames"][q][0], INTR, rough, RefineConfig(align=False))
        t_err, r_err = _errors(T, truth)
        assert agreeing >= 2 and by == "pairs", q
        assert t_err < 0.025 and r_err < 1.0, (q, t_err, r_err)
        t_errs.append(t_err)
    assert np.mean(t_errs) < 0.015, t_errs


def test_neighbours_face_the_same_way_first() -> None:
    centres = np.array([[0.0, 0, 0], [0.01, 0, 0], [0.2, 0, 0], [0.3, 0, 0]])
    T = np.tile(np.eye(4), (4, 1, 1))
    T[:, :3, 3] = centres
    T[1] = T[1] @ _rigid((0.0, 180.0, 0.0), (0, 0, 0))  # nearest, but looking backwards
    ref = Reference(T, lambda i: None)
    query = _rigid((0.0, 10.0, 0.0), (0.02, 0.0, 0.0))
    assert list(ref.neighbours(query, 3, max_view_deg=30.0)) == [0, 2, 3]
    assert list(ref.neighbours(query, 4, max_view_deg=30.0)) == [0, 2, 3, 1]  # then the others
    assert list(ref.neighbours(query, 2, max_view_deg=180.0)) == [1, 0]  # no view limit: nearest


def test_no_working_pair_keeps_the_network_pose(rendered: dict) -> None:
    ref = _reference(rendered)
    blank = np.full((INTR.height, INTR.width, 3), 128, np.uint8)  # nothing to track
    rough = _scaled(rendered["path"][21], UNITS)
    T, agreeing, by = _refine(ref, blank, INTR, rough)
    assert agreeing == 0 and by == "none"
    np.testing.assert_array_equal(T, rough)


def test_frames_load_once_while_cached(rendered: dict) -> None:
    loads: list[int] = []
    ref = _reference(rendered, loads)
    q = rendered["queries"][1]
    pose = _scaled(rendered["path"][q], UNITS)
    for _ in range(2):
        refine_pose(ref, rendered["frames"][q][0], INTR, pose, RefineConfig(neighbours=3))
    assert sorted(loads) == sorted(set(loads)) and len(loads) == 3
    with pytest.raises(ValueError, match="training poses"):
        Reference(np.zeros((0, 4, 4)), lambda i: None)


def test_one_pair_alone_does_not_move_the_pose(rendered: dict) -> None:
    ref = _reference(rendered)
    q = rendered["queries"][1]
    truth = _scaled(rendered["path"][q], UNITS)
    rough = truth @ _rigid((1.0, 1.0, 0.0), (0.03 * UNITS, 0.0, 0.0))
    image = rendered["frames"][q][0]
    T, agreeing, by = _refine(ref, image, INTR, rough, RefineConfig(neighbours=1, align=False))
    assert agreeing == 1 and by == "none"
    np.testing.assert_array_equal(T, rough)
    T, agreeing, by = _refine(ref, image, INTR, rough, RefineConfig(neighbours=1, min_pairs=1, align=False))
    assert agreeing == 1 and by == "pairs" and _errors(T, truth)[0] < 0.02 < _errors(rough, truth)[0]


def test_alignment_makes_the_pairs_precise(rendered: dict) -> None:
    """Direct alignment to the neighbours after the pairs: within 5 mm and 0.3 deg of the truth,
    more precise than the pairs' mean at every query."""
    ref = _reference(rendered)
    for q in rendered["queries"]:
        truth = _scaled(rendered["path"][q], UNITS)
        rough = truth @ _rigid((2.0, -3.0, 1.5), (0.03 * UNITS, -0.02 * UNITS, 0.02 * UNITS))
        image = rendered["frames"][q][0]
        pairs = _errors(refine_pose(ref, image, INTR, rough, RefineConfig(align=False)).T_wc, truth)
        r = refine_pose(ref, image, INTR, rough)
        aligned = _errors(r.T_wc, truth)
        assert r.by == "aligned" and r.pairs >= 2
        assert aligned[0] < 0.005 and aligned[1] < 0.3, (q, aligned)
        assert aligned[0] < pairs[0], (q, aligned, pairs)


def test_pairs_agreeing_on_a_wrong_pose_lose_to_the_better_start(rendered: dict,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """Pairs that agree on a pose 50 cm and 15 deg off: the alignment from the network's pose (4 cm
    off) explains the neighbours better and is kept; without alignment the wrong pose wins. With
    the wrong pose as the network's and no pairs, its alignment explains too little to be used:
    the pose stays as it was."""
    import relocdepth.refine as R
    from relocdepth.vo import PairPose

    ref = _reference(rendered)
    q = rendered["queries"][2]
    truth = _scaled(rendered["path"][q], UNITS)
    wrong = truth @ _rigid((0.0, 15.0, 0.0), (0.5 * UNITS, 0.0, 0.0))
    rough = truth @ _rigid((2.0, -3.0, 1.5), (0.03 * UNITS, -0.02 * UNITS, 0.02 * UNITS))
    picked = [int(n) for n in ref.neighbours(rough, 3, 30.0)]
    pose_of = {id(rendered["frames"][rendered["map"][n]][0]): n for n in picked}

    def agreeing_on_wrong(a, *rest):  # T_{q<-n} that puts the query at `wrong`
        return PairPose(np.linalg.inv(wrong) @ ref.T_wc[pose_of[id(a)]], True, True)

    monkeypatch.setattr(R, "pair_pose", agreeing_on_wrong)
    image = rendered["frames"][q][0]
    T, agreeing, by = _refine(ref, image, INTR, rough, RefineConfig(align=False))
    assert agreeing == 3 and by == "pairs" and _errors(T, truth)[0] > 0.45
    T, agreeing, by = _refine(ref, image, INTR, rough)
    assert agreeing == 3 and by == "aligned" and _errors(T, truth)[0] < 0.005
    monkeypatch.setattr(R, "pair_pose", lambda *a: PairPose(np.eye(4), False, False))
    monkeypatch.setattr(R, "wide_pair_pose", lambda *a: PairPose(np.eye(4), False, False))
    T, agreeing, by = _refine(ref, image, INTR, wrong)
    assert agreeing == 0 and by == "none"
    np.testing.assert_array_equal(T, wrong)


def test_query_of_another_size_is_resized_to_the_map(rendered: dict) -> None:
    """A query rendered at 256x192 (its own intrinsics) is placed as its 128x96 copy is, by the
    pairs and by the alignment (which works on the query at its own size)."""
    cfg = SynthConfig(seed=0, frames=60, width=INTR.width, height=INTR.height)
    scene = build_scene(cfg.seed, cfg)
    big = SEVEN_SCENES_INTRINSICS.scaled(256, 192)
    q = rendered["queries"][2]
    truth = _scaled(rendered["path"][q], UNITS)
    rough = truth @ _rigid((2.0, 0.0, -1.0), (0.0, 0.02 * UNITS, 0.02 * UNITS))
    image = render(scene, rendered["path"][q], big)[0]
    T, agreeing, by = _refine(_reference(rendered), image, big, rough, RefineConfig(align=False))
    assert agreeing >= 2 and by == "pairs" and _errors(T, truth)[0] < 0.025
    T, agreeing, by = _refine(_reference(rendered), image, big, rough)
    assert by == "aligned" and _errors(T, truth)[0] < 0.005


def test_track_size() -> None:
    assert track_size(640, 480, (128, 96), 640) == (640, 480)  # stored 640x480: tracked there
    assert track_size(1280, 960, (128, 96), 640) == (640, 480)  # wider: down to 640
    assert track_size(540, 360, (192, 128), 640) == (540, 360)
    assert track_size(128, 96, (128, 96), 640) == (128, 96)  # stored at the network size
    assert track_size(640, 480, (128, 96), 0) == (128, 96)  # 0: the network's size
    assert track_size(640, 480, (128, 96), 100) == (128, 96)  # never below the network's size


def test_matchers_klt_sift_and_the_fallback(rendered: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    """"klt" pairs by tracks only, "sift" by descriptors only, "klt+sift" by descriptors exactly
    where the tracks failed."""
    import relocdepth.refine as R
    from relocdepth.vo import PairPose

    calls: list[tuple[str, int]] = []
    refs = [rendered["frames"][i][0] for i in rendered["map"]]

    def which(image: np.ndarray) -> int:
        return next(j for j, im in enumerate(refs) if im is image)

    def klt(a, *rest):  # works for even map frames only
        calls.append(("klt", which(a)))
        return PairPose(np.eye(4), True, which(a) % 2 == 0)

    def sift(a, *rest):
        calls.append(("sift", which(a)))
        return PairPose(np.eye(4), True, True)

    monkeypatch.setattr(R, "pair_pose", klt)
    monkeypatch.setattr(R, "wide_pair_pose", sift)
    ref = _reference(rendered)
    q = rendered["queries"][1]
    pose = _scaled(rendered["path"][q], UNITS)
    picked = [int(n) for n in ref.neighbours(pose, 3, 30.0)]
    for matcher, expect in (
        ("klt", [("klt", n) for n in picked]),
        ("sift", [("sift", n) for n in picked]),
        ("klt+sift", [c for n in picked for c in ([("klt", n)] + ([("sift", n)] if n % 2 else []))]),
    ):
        calls.clear()
        refine_pose(ref, rendered["frames"][q][0], INTR, pose, RefineConfig(matcher=matcher))
        assert calls == expect, matcher
    assert any(n % 2 for n in picked) and any(n % 2 == 0 for n in picked)  # both kinds were asked
    with pytest.raises(ValueError, match="matcher"):
        refine_pose(ref, rendered["frames"][q][0], INTR, pose, RefineConfig(matcher="orb"))
