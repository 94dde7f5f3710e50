"""Geometry of the method, tested against geometry: round trips, known poses, warps, gradcheck."""

from __future__ import annotations

import math

import pytest
import torch

from relocdepth import geometry as geo
from relocdepth.errors import UserError

torch.set_num_threads(1)
D64 = torch.float64


def _K(B: int, W: int = 128, H: int = 96, f: float = 110.0, dtype: torch.dtype = D64) -> torch.Tensor:
    K = torch.tensor([[f, 0, (W - 1) / 2 + 1.3], [0, f * 1.02, (H - 1) / 2 - 0.7], [0, 0, 1]], dtype=dtype)
    return K.expand(B, 3, 3).clone()


def _random_poses(B: int, gen: torch.Generator, max_angle: float = math.pi) -> torch.Tensor:
    axis = torch.randn(B, 3, generator=gen, dtype=D64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = torch.rand(B, 1, generator=gen, dtype=D64) * max_angle
    t = torch.randn(B, 3, generator=gen, dtype=D64) * 3
    return geo.pose_vector_to_matrix(torch.cat((axis * angle, t), dim=-1))


# ------------------------------------------------------------------------------------ round trips


@pytest.mark.parametrize("size", [(96, 128), (192, 256), (480, 640)])
def test_identity_round_trip_every_cell_mean_and_median(size: tuple[int, int]) -> None:
    gen = torch.Generator().manual_seed(1)
    B = 8
    H, W = size
    h, w = geo.dsc_grid_size(H, W)
    T = _random_poses(B, gen)
    depth = 0.1 + 10 * torch.rand(B, 1, h, w, generator=gen, dtype=D64)
    K = _K(B, W, H, f=0.9 * W)
    dsc = geo.dsc_from_pose(T, depth, K)
    assert dsc.shape == (B, 6, h, w)
    q, c = geo.cell_poses(dsc, depth, K)
    R = geo.quat_to_matrix(q)
    assert (R - T[:, None, :3, :3]).abs().max() < 1e-6
    assert (c - T[:, None, :3, 3]).abs().max() < 1e-6
    for agg in (geo.mean_cell_pose, geo.median_cell_pose):
        qa, ca = agg(q, c)
        assert (geo.pose_matrix(qa, ca) - T).abs().max() < 1e-6, agg.__name__


def test_round_trip_near_pi_and_identity() -> None:
    """Rotations at 0 and within 1e-9 of pi: the log map, the mean and the median stay exact."""
    axes = torch.tensor([[0.0, 0, 1], [1, 0, 0], [0.6, 0.8, 0]], dtype=D64)
    angles = torch.tensor([[0.0], [math.pi - 1e-9], [math.pi]], dtype=D64)
    T = geo.pose_vector_to_matrix(torch.cat((axes * angles, torch.ones(3, 3, dtype=D64)), -1))
    depth = torch.full((3, 1, 3, 4), 2.0, dtype=D64)
    K = _K(3)
    q, c = geo.cell_poses(geo.dsc_from_pose(T, depth, K), depth, K)
    for agg in (geo.mean_cell_pose, geo.median_cell_pose):
        qa, ca = agg(q, c)
        assert geo.pose_errors(geo.pose_matrix(qa, ca), T)[1].max() < 1e-5
    assert torch.allclose(geo.so3_exp(geo.so3_log(T[:, :3, :3])), T[:, :3, :3], atol=1e-7)


def test_cell_geometry_sign_and_distance() -> None:
    """Camera at the origin looking down +z at a wall z = 2: tau is the wall point on each cell's
    ray, and the centre is recovered with ``c = tau - |Q| G e_z`` (|Q| = distance, not depth)."""
    B, H, W = 1, 96, 128
    T = torch.eye(4, dtype=D64)[None]
    depth = torch.full((B, 1, 3, 4), 2.0, dtype=D64)
    K = _K(B, W, H)
    dsc = geo.dsc_from_pose(T, depth, K)
    uv = geo.dsc_cell_centres(3, 4, dtype=D64)
    assert uv[0].tolist() == [15.5, 15.5] and uv[5].tolist() == [47.5, 47.5]
    tau = dsc[0, 3:].flatten(1).T
    expected = 2.0 * torch.cat((uv, torch.ones(12, 1, dtype=D64)), 1) @ torch.linalg.inv(K[0]).T
    assert torch.allclose(tau, expected, atol=1e-12)
    assert torch.allclose(tau[:, 2], torch.full((12,), 2.0, dtype=D64))


def test_pool_depth_and_grid() -> None:
    d = torch.arange(96 * 128, dtype=D64).reshape(1, 1, 96, 128)
    p = geo.pool_depth(d)
    assert p.shape == (1, 1, 3, 4)
    assert p[0, 0, 0, 0] == d[0, 0, :32, :32].mean()
    with pytest.raises(UserError, match="multiple of 32"):
        geo.dsc_grid_size(100, 128)


def test_median_is_robust_to_outlier_cells() -> None:
    gen = torch.Generator().manual_seed(2)
    T = _random_poses(2, gen, max_angle=2.0)
    depth = 1 + torch.rand(2, 1, 6, 8, generator=gen, dtype=D64)
    K = _K(2, 256, 192)
    dsc = geo.dsc_from_pose(T, depth, K)
    dsc = dsc + 0.002 * torch.randn(dsc.shape, generator=gen, dtype=D64)
    bad = torch.rand(2, 1, 6, 8, generator=gen) < 0.3
    dsc = torch.where(bad, dsc + 2.0 * torch.randn(dsc.shape, generator=gen, dtype=D64), dsc)
    q, c = geo.cell_poses(dsc, depth, K)
    t_med, r_med = geo.pose_errors(geo.pose_matrix(*geo.median_cell_pose(q, c)), T)
    t_mean, r_mean = geo.pose_errors(geo.pose_matrix(*geo.mean_cell_pose(q, c)), T)
    assert t_med.max() < 0.05 and r_med.max() < 1.0
    assert (t_mean > 3 * t_med).all() and (r_mean > 3 * r_med).all()
    spread_t, spread_r = geo.cell_pose_spread(q, c, *geo.median_cell_pose(q, c))
    assert (spread_t > 0).all() and (spread_r > 0).all()


def test_relative_pose_maps_target_points_to_source() -> None:
    gen = torch.Generator().manual_seed(3)
    T_t, T_s = _random_poses(4, gen), _random_poses(4, gen)
    X_t = torch.randn(4, 3, 1, generator=gen, dtype=D64)
    X_w = T_t[:, :3, :3] @ X_t + T_t[:, :3, 3:]
    X_s = T_s[:, :3, :3].transpose(1, 2) @ (X_w - T_s[:, :3, 3:])
    T_ts = geo.relative_pose(T_t, T_s)
    assert torch.allclose(T_ts[:, :3, :3] @ X_t + T_ts[:, :3, 3:], X_s, atol=1e-10)
    assert torch.allclose(geo.invert_pose(T_t) @ T_t, torch.eye(4, dtype=D64).expand(4, 4, 4), atol=1e-12)


# ------------------------------------------------------------------------------------------ warp


def _plane_view(T_wc: torch.Tensor, K: torch.Tensor, H: int, W: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact image and depth of a textured plane ``n . X = d`` seen by camera ``T_wc (4, 4)``."""
    n = torch.tensor([0.1, -0.2, 1.0], dtype=D64)
    n = n / n.norm()
    d = 3.0
    v, u = torch.meshgrid(torch.arange(H, dtype=D64), torch.arange(W, dtype=D64), indexing="ij")
    rays_c = torch.stack((u, v, torch.ones_like(u)), -1) @ torch.linalg.inv(K).T  # z = 1
    rays_w = rays_c @ T_wc[:3, :3].T
    c = T_wc[:3, 3]
    z = (d - n @ c) / (rays_w @ n)  # along rays with unit camera z: this is the depth
    X = c + z[..., None] * rays_w
    tex = torch.stack(
        [0.5 + 0.2 * torch.sin(7 * X[..., 0] + 3 * X[..., 1]) + 0.2 * torch.cos(11 * X[..., 1]),
         0.5 + 0.3 * torch.sin(5 * X[..., 0] - 9 * X[..., 1]),
         0.5 + 0.3 * torch.cos(8 * X[..., 0] + 4 * X[..., 1])], 0)
    return tex[None], z[None, None]


def test_warp_matches_exact_render_of_a_plane() -> None:
    H, W = 48, 64
    K = _K(1, W, H, f=60.0)[0]
    T_t = geo.pose_vector_to_matrix(torch.tensor([0.02, -0.03, 0.01, 0.0, 0.0, 0.0], dtype=D64))
    T_s = geo.pose_vector_to_matrix(torch.tensor([-0.03, 0.05, 0.02, 0.12, -0.05, 0.08], dtype=D64))
    I_t, D_t = _plane_view(T_t, K, H, W)
    I_s, _ = _plane_view(T_s, K, H, W)
    warped, valid = geo.warp(I_s, D_t, geo.relative_pose(T_t[None], T_s[None]), K[None], K[None])
    assert 0.7 < valid.mean() < 1.0
    err = ((warped - I_t).abs() * valid).sum() / valid.sum() / 3
    assert err < 0.01  # bilinear interpolation of a smooth texture
    T_bad = geo.pose_vector_to_matrix(torch.tensor([0.0, 0.035, 0.0, 0.05, 0, 0], dtype=D64)) @ T_s
    warped_b, valid_b = geo.warp(I_s, D_t, geo.relative_pose(T_t[None], T_bad[None]), K[None], K[None])
    err_b = ((warped_b - I_t).abs() * valid_b).sum() / valid_b.sum() / 3
    assert err_b > 5 * err


def test_warp_identity_and_validity() -> None:
    gen = torch.Generator().manual_seed(4)
    img = torch.rand(2, 3, 16, 24, generator=gen, dtype=D64)
    depth = 1 + torch.rand(2, 1, 16, 24, generator=gen, dtype=D64)
    K = _K(2, 24, 16, f=20.0)
    eye = torch.eye(4, dtype=D64).expand(2, 4, 4)
    warped, valid = geo.warp(img, depth, eye, K, K)
    assert torch.allclose(warped, img, atol=1e-10) and bool(valid.all())
    behind = eye.clone()
    behind[:, 2, 3] = -10.0  # every point ends up behind the source camera
    _, valid = geo.warp(img, depth, behind, K, K)
    assert not bool(valid.any())


def test_depth_disagreement_of_two_exact_views_of_a_plane() -> None:
    """Zero for the true depths under the true pose; (s - 1) / (s + 1) when the source's depth is
    s times too deep; unchanged by a common scale of both depths and the translation."""
    H, W = 48, 64
    K = _K(1, W, H, f=60.0)
    T_t = geo.pose_vector_to_matrix(torch.tensor([0.02, -0.03, 0.01, 0.0, 0.0, 0.0], dtype=D64))
    T_s = geo.pose_vector_to_matrix(torch.tensor([-0.03, 0.05, 0.02, 0.12, -0.05, 0.08], dtype=D64))
    _, D_t = _plane_view(T_t, K[0], H, W)
    _, D_s = _plane_view(T_s, K[0], H, W)
    T_ts = geo.relative_pose(T_t[None], T_s[None])

    def mean(g: torch.Tensor, valid: torch.Tensor) -> float:
        return float((g * valid).sum() / valid.sum())

    g, valid = geo.depth_disagreement(D_t, D_s, T_ts, K, K)
    _, valid_warp = geo.warp(D_s, D_t, T_ts, K, K)
    assert torch.equal(valid, valid_warp) and 0.7 < float(valid.mean()) < 1.0
    assert mean(g, valid) < 1e-4 and float(g.max()) < 2e-3  # bilinear sampling of an exact plane
    g, valid = geo.depth_disagreement(D_t, 1.2 * D_s, T_ts, K, K)
    assert mean(g, valid) == pytest.approx(0.2 / 2.2, abs=2e-4)
    T_scaled = T_ts.clone()
    T_scaled[:, :3, 3] *= 3.0
    g3, _ = geo.depth_disagreement(3.0 * D_t, 3.0 * 1.2 * D_s, T_scaled, K, K)
    assert torch.allclose(g3, g, atol=1e-9)
    # a wrong translation's length shows: the target's points land too near or too far
    T_long = T_ts.clone()
    T_long[:, :3, 3] *= 4.0
    g, valid = geo.depth_disagreement(D_t, D_s, T_long, K, K)
    assert mean(g, valid) > 0.01
    behind = T_ts.clone()
    behind[:, 2, 3] = -10.0  # no point in front of the source: nothing to disagree on
    g, valid = geo.depth_disagreement(D_t, D_s, behind, K, K)
    assert not bool(valid.any()) and float(g.abs().max()) == 0.0


# -------------------------------------------------------------------------------------- gradcheck


def test_gradcheck_cell_poses() -> None:
    gen = torch.Generator().manual_seed(5)
    dsc = torch.randn(1, 6, 1, 2, generator=gen, dtype=D64, requires_grad=True)
    depth = (1 + torch.rand(1, 1, 1, 2, generator=gen, dtype=D64)).requires_grad_()
    K = _K(1, 64, 32, f=40.0)

    def fn(dsc: torch.Tensor, depth: torch.Tensor) -> tuple[torch.Tensor, ...]:
        q, c = geo.cell_poses(dsc, depth, K)
        qm, cm = geo.mean_cell_pose(q, c)
        return q, c, qm, cm

    assert torch.autograd.gradcheck(fn, (dsc, depth))


def test_gradcheck_warp_and_depth_disagreement() -> None:
    gen = torch.Generator().manual_seed(6)
    img = torch.rand(1, 1, 6, 7, generator=gen, dtype=D64, requires_grad=True)
    depth = (2 + torch.rand(1, 1, 6, 7, generator=gen, dtype=D64)).requires_grad_()
    depth_s = (2.5 + torch.rand(1, 1, 6, 7, generator=gen, dtype=D64)).requires_grad_()
    pose = torch.tensor([[0.01, -0.02, 0.015, 0.05, 0.03, -0.02]], dtype=D64, requires_grad=True)
    K = _K(1, 7, 6, f=8.0)

    def fn(
        img: torch.Tensor, depth: torch.Tensor, depth_s: torch.Tensor, pose: torch.Tensor
    ) -> tuple[torch.Tensor, ...]:
        T = geo.pose_vector_to_matrix(pose)
        return geo.warp(img, depth, T, K, K)[0], geo.depth_disagreement(depth, depth_s, T, K, K)[0]

    assert torch.autograd.gradcheck(fn, (img, depth, depth_s, pose), atol=1e-6)


def test_log_map_gradients_finite_at_zero_and_pi() -> None:
    q = torch.tensor([[1.0, 0, 0, 0], [0.0, 1, 0, 0], [1e-12, 0, 0.6, 0.8]], dtype=D64, requires_grad=True)
    v = geo.quat_log(q)
    v.norm(dim=-1).sum().backward()
    assert torch.isfinite(q.grad).all()
    assert torch.allclose(v[1].norm(), torch.tensor(math.pi, dtype=D64))
    x = torch.zeros(1, 6, 1, 1, dtype=D64, requires_grad=True)  # theta = 0 exactly
    qc, cc = geo.cell_poses(x, torch.ones(1, 1, 1, 1, dtype=D64), _K(1, 32, 32, f=30.0))
    (qc.sum() + cc.sum()).backward()
    assert torch.isfinite(x.grad).all()


# ------------------------------------------------------------------------------ errors, intrinsics


def test_pose_errors_near_0_and_180_degrees() -> None:
    rotvec = torch.tensor([[0.0, 0.0, math.radians(30)], [1e-7, 0, 0], [math.pi, 0, 0]], dtype=D64)
    centres = torch.tensor([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=D64)
    T = geo.pose_vector_to_matrix(torch.cat((rotvec, centres), -1))
    t_err, r_err = geo.pose_errors(torch.eye(4, dtype=D64).expand(3, 4, 4), T)
    assert torch.allclose(r_err, torch.tensor([30.0, math.degrees(1e-7), 180.0], dtype=D64), atol=1e-9)
    assert torch.allclose(t_err, torch.tensor([5.0, 0.0, 1.0], dtype=D64))


def test_scale_intrinsics_half_pixel() -> None:
    from relocdepth.camera import scale_K

    K = _K(1)[0]
    assert torch.allclose(geo.scale_intrinsics(K, 0.5, 0.25), torch.as_tensor(scale_K(K.numpy(), 0.5, 0.25)))
