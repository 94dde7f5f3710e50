"""The generated scene: exact depth and poses (reprojection), layout, determinism, motion, CLI."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from relocdepth.cli.main import app
from typer.testing import CliRunner

from relocdepth.camera import Intrinsics
from relocdepth.synth import (
    SEVEN_SCENES_INTRINSICS,
    SynthConfig,
    build_scene,
    camera_paths,
    cast_rays,
    clearance,
    generate_scene,
    motion_steps,
    pair_motion,
    pixel_rays,
    render,
)

# The shared `synth_scene` fixture (tests/conftest.py): 3 x 24 frames at 128x96, seed 0.
SCENE_FRAMES = 24
SCENE_SIZE = (128, 96)

# ----------------------------------------------------------------------------------------------
# helpers


def read_frame(seq_dir: Path, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RGB float (H, W, 3), depth metres (H, W) and T_wc (4, 4) of one frame, from the files."""
    stem = seq_dir / f"frame-{i:06d}"
    bgr = cv2.imread(f"{stem}.color.png", cv2.IMREAD_UNCHANGED)
    depth = cv2.imread(f"{stem}.depth.png", cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16
    return bgr[:, :, ::-1].astype(np.float64), depth.astype(np.float64) / 1000.0, np.loadtxt(
        f"{stem}.pose.txt")


def bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Sample img (H, W, C) at float pixel coordinates (N,), all inside [0, W-1] x [0, H-1]."""
    u0 = np.clip(np.floor(u).astype(int), 0, img.shape[1] - 2)
    v0 = np.clip(np.floor(v).astype(int), 0, img.shape[0] - 2)
    a, b = (u - u0)[:, None], (v - v0)[:, None]
    return ((1 - a) * (1 - b) * img[v0, u0] + a * (1 - b) * img[v0, u0 + 1]
            + (1 - a) * b * img[v0 + 1, u0] + a * b * img[v0 + 1, u0 + 1])


def reprojection(rgb_a, depth_a, T_a, rgb_b, depth_b, T_b, K) -> tuple[float, float]:
    """Warp frame A's pixels into B with A's depth and the poses; on pixels visible in B (inside,
    in front, agreeing with B's depth at all 4 bilinear neighbours) return the median absolute
    colour difference (grey levels) and the fraction of A's pixels used."""
    h, w = depth_a.shape
    v, u = np.mgrid[0:h, 0:w]
    ok = depth_a.ravel() > 0
    pix = np.stack([u.ravel(), v.ravel(), np.ones(h * w)])[:, ok]
    X_a = np.linalg.inv(K) @ pix * depth_a.ravel()[ok]
    T_ba = np.linalg.inv(T_b) @ T_a
    X_b = T_ba[:3, :3] @ X_a + T_ba[:3, 3:]
    z = X_b[2]
    ub, vb = (K @ X_b)[:2] / np.where(z > 0, z, 1)
    inside = (z > 0) & (ub >= 0) & (ub <= w - 1) & (vb >= 0) & (vb <= h - 1)
    ub, vb, z = ub[inside], vb[inside], z[inside]
    u0, v0 = np.clip(np.floor(ub).astype(int), 0, w - 2), np.clip(np.floor(vb).astype(int), 0, h - 2)
    neighbours = np.stack([depth_b[v0, u0], depth_b[v0, u0 + 1], depth_b[v0 + 1, u0],
                           depth_b[v0 + 1, u0 + 1]])
    visible = np.all(np.abs(neighbours - z) < 0.01 * z + 0.002, axis=0)
    colour_a = rgb_a.reshape(-1, 3)[ok][inside][visible]
    colour_b = bilinear(rgb_b, ub[visible], vb[visible])
    diff = np.abs(colour_a - colour_b).mean(axis=1)
    return float(np.median(diff)), visible.sum() / (h * w)


def perturbed(T: np.ndarray, metres: float, degrees: float) -> np.ndarray:
    """T followed by a camera-frame shift of ``metres`` along (1, 1, 0)/sqrt 2 and a rotation of
    ``degrees`` about (0, 1, 1)/sqrt 2."""
    axis = np.array([0.0, 1.0, 1.0]) / np.sqrt(2)
    R, _ = cv2.Rodrigues(axis * np.radians(degrees))
    delta = np.eye(4)
    delta[:3, :3] = R
    delta[:3, 3] = metres * np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    return T @ delta


def intrinsics_of(scene_dir: Path) -> Intrinsics:
    return Intrinsics.from_dict(yaml.safe_load((scene_dir / "intrinsics.yaml").read_text()))


# ----------------------------------------------------------------------------------------------
# exactness


@pytest.mark.parametrize("seq, a, b", [("seq-01", 0, 3), ("seq-02", 10, 14), ("seq-03", 20, 16)])
def test_reprojection_with_true_poses_matches_colours(synth_scene: Path, seq, a, b):
    K = intrinsics_of(synth_scene).K()
    fa, fb = read_frame(synth_scene / seq, a), read_frame(synth_scene / seq, b)
    err, used = reprojection(*fa, *fb, K)
    assert used > 0.5, "most pixels of a frame a few frames away should be visible"
    assert err < 3.0, f"median colour difference {err:.2f} grey levels with the true poses"
    # The check can fail: a pose 5 cm / 2 deg off gives a clearly larger difference.
    wrong = (fb[0], fb[1], perturbed(fb[2], 0.05, 2.0))
    err_wrong, used_wrong = reprojection(*fa, *wrong, K)
    assert err_wrong > 3 * err and err_wrong > 6.0, (err, err_wrong, used_wrong)


def test_depth_is_z_depth_of_rendered_geometry():
    """Back-projected depth lands on the surface the ray hit: every point is on a surface (its
    signed distance to the scene's primitives is zero), re-casting the ray from the camera gives
    the same depth, and looking straight down past the island the floor has z = 0."""
    scene = build_scene(0)
    intr = SEVEN_SCENES_INTRINSICS.scaled(64, 48)
    rays = pixel_rays(intr)
    for T in camera_paths(SynthConfig(frames=200))["seq-01"][::40]:
        _, depth = render(scene, T, intr)
        points = T[:3, 3] + (rays * depth.reshape(-1, 1).astype(np.float64)) @ T[:3, :3].T
        assert np.abs(clearance(scene, points)).max() < 1e-4  # float32 depth: ~0.1 mm at 2 m
        t, _, _ = cast_rays(scene, T[:3, 3], rays @ T[:3, :3].T)
        np.testing.assert_allclose(depth.ravel(), t, rtol=1e-6)
    island = max(scene.boxes, key=lambda b: b.half[0] * b.half[1] * (b.centre[2] < 1.0))
    T_down = np.eye(4)  # straight down from 1.4 m, beside the island
    T_down[:3, :3] = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])
    T_down[:3, 3] = [island.centre[0] + island.half[0] + 0.3, 0.0, 1.4]
    _, depth = render(scene, T_down, SEVEN_SCENES_INTRINSICS.scaled(32, 24))
    assert np.isclose(depth, 1.4, atol=1e-5).mean() > 0.2 and depth.max() <= 1.4 + 1e-5


def test_ray_culling_changes_nothing():
    """Rendering tests each object only on pixels inside its projected bounds; a full cast
    agrees exactly."""
    scene = build_scene(3)
    intr = SEVEN_SCENES_INTRINSICS.scaled(80, 60)
    rays = pixel_rays(intr)
    for T in camera_paths(SynthConfig(seed=3, frames=300))["seq-02"][::25]:
        t, _, _ = cast_rays(scene, T[:3, 3], rays @ T[:3, :3].T)
        _, depth = render(scene, T, intr)
        np.testing.assert_array_equal(depth.ravel(), t.astype(np.float32))


# ----------------------------------------------------------------------------------------------
# layout


def test_layout_splits_intrinsics_and_poses(synth_scene: Path):
    cfg = json.loads((synth_scene / "synth.json").read_text())["config"]
    assert (cfg["frames"], cfg["width"], cfg["height"]) == (SCENE_FRAMES, *SCENE_SIZE)
    names = sorted(p.name for p in synth_scene.iterdir())
    assert names == ["TestSplit.txt", "TrainSplit.txt", "intrinsics.yaml", "seq-01", "seq-02",
                     "seq-03", "synth.json", "videos"]
    assert (synth_scene / "TrainSplit.txt").read_text() == "sequence1\nsequence2\n"
    assert (synth_scene / "TestSplit.txt").read_text() == "sequence3\n"
    intr = intrinsics_of(synth_scene)
    assert intr == SEVEN_SCENES_INTRINSICS.scaled(*SCENE_SIZE)
    assert intr.fx == pytest.approx(525 * SCENE_SIZE[0] / 640)
    assert intr.cx == pytest.approx((320 + 0.5) * SCENE_SIZE[0] / 640 - 0.5)
    w, h = SCENE_SIZE
    for seq in ("seq-01", "seq-02", "seq-03"):
        files = sorted(p.name for p in (synth_scene / seq).iterdir())
        assert files == sorted(f"frame-{i:06d}.{kind}" for i in range(SCENE_FRAMES)
                               for kind in ("color.png", "depth.png", "pose.txt"))
        color = cv2.imread(str(synth_scene / seq / "frame-000000.color.png"), cv2.IMREAD_UNCHANGED)
        depth = cv2.imread(str(synth_scene / seq / "frame-000000.depth.png"), cv2.IMREAD_UNCHANGED)
        assert color.shape == (h, w, 3) and color.dtype == np.uint8 and color.std() > 10
        assert depth.shape == (h, w) and depth.dtype == np.uint16
        assert 300 < depth.min() and depth.max() < 6000  # millimetres inside a 4 m room
        for i in range(SCENE_FRAMES):
            text = (synth_scene / seq / f"frame-{i:06d}.pose.txt").read_text()
            rows = [line.split() for line in text.splitlines()]
            assert len(rows) == 4 and all(len(r) == 4 for r in rows)
            T = np.array(rows, dtype=float)
            np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-7)
            assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-7)
            np.testing.assert_array_equal(T[3], [0, 0, 0, 1])


def test_videos_hold_every_frame(synth_scene: Path):
    for seq in ("seq-01", "seq-02", "seq-03"):
        cap = cv2.VideoCapture(str(synth_scene / "videos" / f"{seq}.mp4"))
        frames = []
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            frames.append(frame)
        cap.release()
        assert len(frames) == SCENE_FRAMES
        assert frames[0].shape == (SCENE_SIZE[1], SCENE_SIZE[0], 3)
        png = cv2.imread(str(synth_scene / seq / "frame-000000.color.png"))
        assert np.abs(frames[0].astype(int) - png).mean() < 12  # lossy, but the same picture


def test_same_seed_same_bytes_other_seed_differs(tmp_path: Path):
    cfg = SynthConfig(seed=5, frames=3, width=64, height=48)
    generate_scene(tmp_path / "a", cfg)
    generate_scene(tmp_path / "b", cfg)
    generate_scene(tmp_path / "c", SynthConfig(seed=6, frames=3, width=64, height=48))
    files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").glob("seq-*/*"))
    assert len(files) == 3 * 3 * 3
    for f in files:
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    differ = [f for f in files if (tmp_path / "a" / f).read_bytes() != (tmp_path / "c" / f).read_bytes()]
    assert len(differ) == len(files)


# A small scene's content: sha256 over the files' relative paths and contents, PNGs decoded (their
# pixels, not the encoder's bytes), the mp4 videos and synth.json (which names the folder) left
# out. Recorded from the generator; a change of it is a change of every generated scene, which
# must be deliberate (and then re-recorded here).
SCENE_DIGEST = "85f635c5907405c07b07e29735eef7cce449eccd008bf01b57f029d7cf35d73d"


def test_scene_content_is_pinned(tmp_path: Path):
    import hashlib

    generate_scene(tmp_path / "scene", SynthConfig(seed=3, frames=4, width=64, height=48))
    root = tmp_path / "scene"
    h = hashlib.sha256()
    files = [p for p in sorted(root.rglob("*"))
             if p.is_file() and p.suffix != ".mp4" and p.name != "synth.json"]
    assert len(files) == 3 + 3 * 4 * 3  # splits + intrinsics, 3 sequences x 4 frames x 3 files
    for p in files:
        h.update(str(p.relative_to(root)).encode())
        h.update(cv2.imread(str(p), cv2.IMREAD_UNCHANGED).tobytes() if p.suffix == ".png"
                 else p.read_bytes())
    assert h.hexdigest() == SCENE_DIGEST


# ----------------------------------------------------------------------------------------------
# camera motion


# Real 7-Scenes handheld video (a kitchen, two sequences, 30 fps): median translation (m) and
# rotation (deg) between frames k apart.
SEVEN_SCENES_MOTION = {1: (0.0074, 1.57), 5: (0.0346, 2.38), 10: (0.0693, 3.72), 20: (0.140, 6.60)}


def test_motion_per_frame_like_handheld_7scenes():
    cfg = SynthConfig()
    paths = camera_paths(cfg)
    assert list(paths) == ["seq-01", "seq-02", "seq-03"]
    for name, T in paths.items():
        assert T.shape == (cfg.frames, 4, 4)
        trans, rot = motion_steps(T)
        assert 0.005 <= np.median(trans) <= 0.010, (name, np.median(trans))
        assert 1.1 <= np.median(rot) <= 2.0, (name, np.median(rot))
        assert trans.max() < 0.025 and rot.max() < 6.0  # smooth: tremor, but no jumps


@pytest.mark.parametrize("seed", [0, 1])
def test_motion_over_frame_gaps_matches_7scenes(seed):
    """Translation accumulates with the gap; rotation mostly does not (tremor): within 30 % of
    real handheld video at gaps of 5 and 20 frames, poses alone."""
    paths = camera_paths(SynthConfig(seed=seed))
    for k, (real_m, real_deg) in SEVEN_SCENES_MOTION.items():
        trans, rot = (np.concatenate(v) for v in zip(*(pair_motion(T, k) for T in paths.values())))
        tol = 0.3 if k in (5, 20) else 0.4
        assert abs(np.median(trans) / real_m - 1) < tol, (k, np.median(trans))
        assert abs(np.median(rot) / real_deg - 1) < tol, (k, np.median(rot))
    # Without the tremor the same paths turn 5x less per frame: the tremor does not accumulate.
    smooth = camera_paths(SynthConfig(seed=seed, tremor_deg=0.0))
    rot1 = np.median(np.concatenate([pair_motion(T, 1)[1] for T in smooth.values()]))
    rot20 = np.median(np.concatenate([pair_motion(T, 20)[1] for T in smooth.values()]))
    assert rot1 < 0.5 and rot20 > 4.0, (rot1, rot20)


def test_cameras_keep_clear_of_surfaces_and_test_path_is_near_not_on():
    for seed in (0, 1):
        cfg = SynthConfig(seed=seed, frames=900)  # longer than the default: still clear
        scene = build_scene(seed, cfg)
        paths = camera_paths(cfg)
        for T in paths.values():
            assert clearance(scene, T[:, :3, 3]).min() >= max(cfg.min_clearance, 0.3)
        # Every surface keeps the clearance from the whole box the cameras move in, so any path
        # length is safe: its corners and face centres are clear too.
        lo, hi = np.array(cfg.camera_lo), np.array(cfg.camera_hi)
        grid = np.stack(np.meshgrid(*[np.linspace(a, b, 5) for a, b in zip(lo, hi)]), -1)
        assert clearance(scene, grid.reshape(-1, 3)).min() >= cfg.min_clearance - 1e-9
        assert np.all(T[:, :3, 3] >= lo - 1e-9) and np.all(T[:, :3, 3] <= hi + 1e-9)
        paths = camera_paths(SynthConfig(seed=seed))  # the default length: a test split
        train = np.concatenate([paths["seq-01"], paths["seq-02"]])[:, :3, 3]
        test = paths["seq-03"][:, :3, 3]
        nearest = np.linalg.norm(test[:, None] - train[None], axis=2).min(axis=1)
        assert 0.05 < np.median(nearest) < 0.3 and nearest.max() < 0.4


def test_clutter_near_the_cameras_gives_7scenes_like_depth_parallax():
    """The depth part of a warp between frames 20 apart (where the true depth, instead of the
    frame's median depth, sends a pixel) is as large as in a real 7-Scenes kitchen (6.0 px median,
    29 px at the 90th percentile at 640x480): clutter 0.5-1.5 m from the cameras. Rendered at
    80x60 on the first 150 frames (what the demo sees); pixel distances scale with fx."""
    cfg = SynthConfig(frames=150)
    scene, paths = build_scene(0, cfg), camera_paths(cfg)
    intr = SEVEN_SCENES_INTRINSICS.scaled(80, 60)
    K, k = intr.K(), 20
    rays = pixel_rays(intr)
    medians, p90s = [], []
    for T in paths.values():
        for t in range(0, cfg.frames - k, 13):
            _, depth = render(scene, T[t], intr)
            d = depth.reshape(-1, 1).astype(np.float64)
            T_st = np.linalg.inv(T[t + k]) @ T[t]
            moved = []
            for dd in (d, np.full_like(d, np.median(d))):
                X = (rays * dd) @ T_st[:3, :3].T + T_st[:3, 3]
                x = X @ K.T
                moved.append(x[:, :2] / x[:, 2:])
            dist = np.linalg.norm(moved[0] - moved[1], axis=1) * 640 / intr.width
            medians.append(np.median(dist))
            p90s.append(np.percentile(dist, 90))
    assert 4.0 < np.median(medians) < 9.0, np.median(medians)
    assert 18.0 < np.median(p90s) < 45.0, np.median(p90s)


def test_shorter_sequences_are_prefixes_and_more_training_sequences():
    long = camera_paths(SynthConfig(frames=60, train_sequences=3))
    short = camera_paths(SynthConfig(frames=20, train_sequences=3))
    assert list(long) == ["seq-01", "seq-02", "seq-03", "seq-04"]
    for name in long:
        np.testing.assert_array_equal(short[name], long[name][:20])


# ----------------------------------------------------------------------------------------------
# CLI


def test_cli_writes_refuses_and_forces(tmp_path: Path):
    runner = CliRunner()
    out = tmp_path / "scene"
    args = ["synth", str(out), "--frames", "2", "--size", "64x48", "--seed", "1"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert (out / "seq-03" / "frame-000001.pose.txt").exists()
    result = runner.invoke(app, args)
    assert result.exit_code == 2
    assert result.output.strip().startswith("error:") and len(result.output.strip().splitlines()) == 1
    assert runner.invoke(app, [*args, "--force"]).exit_code == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]  # no temporary folders left


@pytest.mark.parametrize("extra", [["--size", "64by48"], ["--size", "63x48"], ["--frames", "0"],
                                   ["--frames", "-3"], ["--train-sequences", "1"]])
def test_cli_bad_input_exits_2_and_writes_nothing(tmp_path: Path, extra):
    result = CliRunner().invoke(app, ["synth", str(tmp_path / "scene"), *extra])
    assert result.exit_code == 2, result.output
    assert "error" in result.output.lower()
    assert list(tmp_path.iterdir()) == []


def test_crash_leaves_nothing_half_written(tmp_path: Path, monkeypatch):
    from relocdepth.synth import writer

    calls = []

    def failing_render(*args, **kwargs):
        calls.append(1)
        if len(calls) > 2:
            raise RuntimeError("disk on fire")
        return render(*args, **kwargs)

    monkeypatch.setattr(writer, "render", failing_render)
    with pytest.raises(RuntimeError):
        generate_scene(tmp_path / "scene", SynthConfig(frames=2, width=32, height=32))
    assert list(tmp_path.iterdir()) == []
