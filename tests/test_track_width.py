"""The essential bootstrap's pairs tracked on the stored images (``--bootstrap-track-width``):
their poses and points are those of the training crop, checked against the scene's geometry."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from relocdepth.camera import Intrinsics
from relocdepth.data import AugmentConfig, ImageFrames, TripletData, crop_box, track_to_crop
from relocdepth.errors import UserError
from relocdepth.eval_geometry import rotation_angle_deg
from relocdepth.sampler import Triplet


def test_track_to_crop_moves_a_pixel_to_where_the_crop_camera_sees_its_point() -> None:
    """A 3D point seen by the tracking camera (the stored image resized) and by the training crop's
    camera (resized, cropped): the helper takes the one pixel to the other; off-crop rows are NaN."""
    intr = Intrinsics(fx=262.5, fy=260.0, cx=160.2, cy=119.7, width=320, height=240)
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-1.2, 1.2, (200, 2)), rng.uniform(1.0, 3.0, 200)]
    for track, (scale, fx0, fy0) in (((200, 150), (1.1, 0.7, 0.3)), ((320, 240), (1.0, 0.0, 0.0)),
                                     ((320, 240), (1.1, 1.0, 1.0))):
        box = crop_box(128, 96, scale, fx0, fy0)
        K_t = intr.scaled(*track).K()
        K_c = intr.scaled(box[0], box[1]).cropped(box[2], box[3], 128, 96).K()
        p_t, p_c = X @ K_t.T, X @ K_c.T
        p_t, p_c = p_t[:, :2] / p_t[:, 2:], p_c[:, :2] / p_c[:, 2:]
        got = track_to_crop(np.c_[p_t, X[:, 2]], track, box, (128, 96))
        inside = (p_c[:, 0] >= 0) & (p_c[:, 0] <= 127) & (p_c[:, 1] >= 0) & (p_c[:, 1] <= 95)
        assert 20 < inside.sum() < len(X)  # some fall outside: the test sees both
        np.testing.assert_allclose(got[inside, :2], p_c[inside], atol=1e-3)
        np.testing.assert_allclose(got[inside, 2], X[inside, 2], rtol=1e-6)
        assert np.isnan(got[~inside]).all()


def _truth(shards: Path, frames: ImageFrames, idx: tuple[int, int, int]) -> tuple[list[np.ndarray], np.ndarray]:
    from relocdepth.dataset import open_dataset

    ds = open_dataset(shards)
    recs = {r.key: r for r in ds.frames("train")}
    return [ds.read_pose(recs[frames.frames[i].key]) for i in idx], ds.read_depth(recs[frames.frames[idx[1]].key])


# (tracking width, rotation error bound in degrees, relative baseline error bound): on the
# training crops (0) the +-10 frame pairs of this scene, which turn ~9 deg, come out coarser.
@pytest.mark.parametrize("track_width,max_deg,max_rel", [(320, 0.5, 0.06), (200, 0.5, 0.06), (0, 5.0, 0.25)])
def test_tracked_pairs_give_the_crop_true_rotations_and_baselines(synth_shards_320: Path, track_width: int,
                                                                 max_deg: float, max_rel: float) -> None:
    """Whatever the tracking size: each pair's rotation is the true one, and the target's true depth
    at each point (in the augmented crop) over the point's depth in baselines is the pair's true
    baseline: the points sit where they belong in the crop. Tracked on the stored images, both
    are finer."""
    frames = ImageFrames.open(synth_shards_320)
    idx = (2, 12, 22)  # +-10 frames of one sequence (~8 cm)
    assert len({frames.frames[i].sequence for i in idx}) == 1
    T_w, depth = _truth(synth_shards_320, frames, idx)
    t = Triplet(idx[0], idx[1], idx[2], aug_seed=7, is_global=False, epoch=0, position=0)
    data = TripletData(frames, AugmentConfig(128, 96, scale_min=1.1, scale_max=1.1), two_view=True,
                       track_width=track_width)
    item = data[t]
    sw, sh, x0, y0 = item["crop"][1]
    assert x0 + y0 > 0  # the crop is offset: a mapping that ignores it fails
    crop_depth = cv2.resize(depth, (int(sw), int(sh)), interpolation=cv2.INTER_NEAREST)[y0:y0 + 96, x0:x0 + 128]
    for j, src in enumerate((0, 2)):
        truth = np.linalg.inv(T_w[src]) @ T_w[1]  # T_{source<-target}
        assert item["two_view_ok"][j]
        assert rotation_angle_deg(item["two_view_T"][j][:3, :3].T @ truth[:3, :3]) < max_deg
        pts = item["two_view_points"][j]
        pts = pts[np.isfinite(pts[:, 2])]
        assert len(pts) >= 10
        xy = np.round(pts[:, :2]).astype(int)
        assert (xy >= 0).all() and (xy[:, 0] < 128).all() and (xy[:, 1] < 96).all()
        baseline = crop_depth[xy[:, 1], xy[:, 0]] / pts[:, 2]
        assert np.median(baseline) == pytest.approx(np.linalg.norm(truth[:3, 3]), rel=max_rel), track_width


def test_a_scene_stored_at_the_training_size_is_tracked_on_its_crops(synth_shards: Path) -> None:
    """The test scene is stored at 128x96, the training size: the stored images are no finer than
    the crops, so with a tracking width the pairs are the crops' own (the same as without one);
    asked to track at 64 px, coarser than the crops, likewise."""
    frames = ImageFrames.open(synth_shards)
    assert frames.frames[0].intrinsics.width == 128
    t = Triplet(2, 5, 8, aug_seed=3, is_global=False, epoch=0, position=0)
    items = [TripletData(frames, AugmentConfig(128, 96), two_view=True, track_width=w)[t] for w in (0, 640, 64)]
    for item in items[1:]:
        for key in ("two_view_T", "two_view_points", "two_view_ok"):
            np.testing.assert_array_equal(item[key], items[0][key])


def test_track_width_must_not_be_negative(synth_shards_320: Path) -> None:
    from relocdepth.train import TrainConfig

    with pytest.raises(ValueError, match="track_width"):
        TripletData(ImageFrames.open(synth_shards_320), AugmentConfig(128, 96), two_view=True, track_width=-1)
    with pytest.raises(UserError, match="--bootstrap-track-width"):
        TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10, "bootstrap_track_width": -5})
    with pytest.raises(UserError, match="is for --bootstrap essential"):
        TrainConfig.from_dict({"bootstrap": "posenet", "bootstrap_steps": 10, "bootstrap_track_width": 320})
    assert TrainConfig.from_dict({"bootstrap": "essential", "bootstrap_steps": 10,
                                  "bootstrap_track_width": 320}).bootstrap_track_width == 320
