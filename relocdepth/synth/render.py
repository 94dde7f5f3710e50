"""Rendering of the generated scene by exact analytic ray casting in numpy: z-depth at pixel centres
(as 7-Scenes stores it), and colours from the textures at the hit points, shaded by a
view-independent (Lambertian) light term, so photometric consistency holds."""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np

from relocdepth.camera import Intrinsics
from relocdepth.synth.config import SynthConfig
from relocdepth.synth.scene import Box, Cylinder, Scene, Sphere
from relocdepth.synth.textures import texture


@functools.lru_cache(maxsize=4)
def pixel_rays(intrinsics: Intrinsics) -> np.ndarray:
    """Camera-frame rays (H*W, 3) through pixel centres, scaled to unit z (so that the ray
    parameter of a hit is its z-depth), in row-major pixel order. Cached: read-only."""
    u = (np.arange(intrinsics.width) - intrinsics.cx) / intrinsics.fx
    v = (np.arange(intrinsics.height) - intrinsics.cy) / intrinsics.fy
    uu, vv = np.meshgrid(u, v)
    rays = np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)], axis=1)
    rays.flags.writeable = False
    return rays


def _lin(x: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``x @ M`` for x (N, 3) and M (3, ...) as three multiply-adds: numpy hands such thin
    products to a multi-threaded BLAS whose thread start-up costs more than the product."""
    return x[:, :1] * M[0] + x[:, 1:2] * M[1] + x[:, 2:3] * M[2] if M.ndim == 2 else (
        x[:, 0] * M[0] + x[:, 1] * M[1] + x[:, 2] * M[2])



Surface = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def _hit_box(b: Box, o: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, Surface]:
    """Slab test: entry ``t`` (N,), ``hit`` (N,), and ``surface(mask)``: face (M,) and outward
    normal (M, 3) of the rays in ``mask`` (computed only for the rays that need them). One axis
    at a time on 1-D arrays: faster than reductions over an axis of length 3."""
    rot = b.rotation()
    o_l = rot.T @ (o - b.centre)
    d_l = dirs if b.yaw == 0.0 else _lin(dirs, rot)  # furniture is mostly axis-aligned
    near, far = [], []
    for k in range(3):
        inv = 1.0 / d_l[:, k]
        t1, t2 = (-b.half[k] - o_l[k]) * inv, (b.half[k] - o_l[k]) * inv
        near.append(np.minimum(t1, t2))
        far.append(np.maximum(t1, t2))
    t_in = np.maximum(np.maximum(near[0], near[1]), near[2])
    hit = (t_in < np.minimum(np.minimum(far[0], far[1]), far[2])) & (t_in > 0)

    def surface(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n0, n1, n2 = near[0][mask], near[1][mask], near[2][mask]
        a = np.where((n0 >= n1) & (n0 >= n2), 0, np.where(n1 >= n2, 1, 2))  # the entry axis
        plus = d_l[mask][np.arange(len(a)), a] < 0  # going towards -axis: enters the + face
        local = 2 * a + plus
        normals = np.stack([-rot[:, 0], rot[:, 0], -rot[:, 1], rot[:, 1], -rot[:, 2], rot[:, 2]])
        return b.face0 + local, normals[local]

    return t_in, hit, surface


def _hit_sphere(s: Sphere, o: np.ndarray, dirs: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, Surface]:
    oc = o - s.centre
    a, bh = np.einsum("ij,ij->i", dirs, dirs), _lin(dirs, oc)
    disc = bh * bh - a * (oc @ oc - s.radius**2)
    t = (-bh - np.sqrt(disc)) / a
    normal = (o + t[:, None] * dirs - s.centre) / s.radius
    return t, (disc > 0) & (t > 0), _surface(np.full(len(dirs), s.face0), normal)


def _hit_cylinder(c: Cylinder, o: np.ndarray, dirs: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, Surface]:
    """Side (a quadratic in x, y) and the two caps; the nearest valid of the three."""
    oc = o[:2] - c.centre_xy
    d2 = dirs[:, :2]
    a, bh = np.einsum("ij,ij->i", d2, d2), d2[:, 0] * oc[0] + d2[:, 1] * oc[1]
    disc = bh * bh - a * (oc @ oc - c.radius**2)
    t = (-bh - np.sqrt(disc)) / a
    z = o[2] + t * dirs[:, 2]
    hit = (disc > 0) & (t > 0) & (z >= c.z0) & (z <= c.z1)
    t = np.where(hit, t, np.inf)
    face = np.full(len(dirs), c.face0)
    normal = np.zeros((len(dirs), 3))
    normal[:, :2] = (oc + t[:, None] * d2) / c.radius
    for cap_z, cap_face, nz in ((c.z1, c.face0 + 1, 1.0), (c.z0, c.face0 + 2, -1.0)):
        t_c = (cap_z - o[2]) / dirs[:, 2]
        xy = oc + t_c[:, None] * d2
        on = (t_c > 0) & (np.einsum("ij,ij->i", xy, xy) <= c.radius**2) & ((o[2] - cap_z) * nz > 0)
        on &= t_c < t
        t[on], face[on], normal[on] = t_c[on], cap_face, (0.0, 0.0, nz)
    return t, np.isfinite(t), _surface(face, normal)


def _surface(face: np.ndarray, normal: np.ndarray) -> Surface:
    """``surface(mask)`` of precomputed faces (N,) and normals (N, 3)."""
    return lambda mask: (face[mask], normal[mask])


_HIT = {Box: _hit_box, Sphere: _hit_sphere, Cylinder: _hit_cylinder}


Selection = list[tuple[np.ndarray, float]]


def cast_rays(scene: Scene, origin: np.ndarray, dirs: np.ndarray,
              select: Callable[[np.ndarray], Selection] | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest hits of rays ``origin + t * dirs`` (origin (3,), dirs (N, 3)) from inside the room.

    ``select(corners (P, 8, 3))`` may return, per object, the indices of the rays that can hit it
    inside those bounds and a lower bound on their ``t`` there (default: all rays, 0); it only
    saves time: objects are tested nearest first, each only on rays whose hit so far lies beyond
    its lower bound. Returns ``t`` (N,) in units of ``dirs``, face id (N,) int and unit normal
    (N, 3)."""
    o = np.asarray(origin, np.float64)
    n = len(dirs)
    rows = np.arange(n)
    prims = (*scene.boxes, *scene.spheres, *scene.cylinders)
    chosen = [(rows, 0.0)] * len(prims) if select is None else select(scene.corners)
    order = sorted((i for i in range(len(prims)) if len(chosen[i][0])), key=lambda i: chosen[i][1])
    with np.errstate(divide="ignore", invalid="ignore"):
        # Room: the ray leaves the box through the face with the smallest exit distance.
        t_axis = np.where(dirs > 0, (scene.hi - o) / dirs,
                          np.where(dirs < 0, (scene.lo - o) / dirs, np.inf))
        axis = np.argmin(t_axis, axis=1)
        t = t_axis[rows, axis]
        positive = dirs[rows, axis] > 0
        face = 2 * axis + positive
        normal = np.zeros((n, 3))
        normal[rows, axis] = np.where(positive, -1.0, 1.0)
        for i in order:
            prim, (idx, t_min) = prims[i], chosen[i]
            if t_min > 0 and len(idx):
                idx = idx[t[idx] > t_min]
            if len(idx) == 0:
                continue
            t_new, hit, surface = _HIT[type(prim)](prim, o, dirs[idx])
            better = hit & (t_new < t[idx])
            if better.any():
                sel = idx[better]
                t[sel] = t_new[better]
                face[sel], normal[sel] = surface(better)
    return t, face, normal


# Pairs of corner indices (12, 2) joined by an edge of a box (see scene.box_corners).
_BOX_EDGES = np.array([(i, i | 1 << a) for a in range(3) for i in range(8) if not i >> a & 1])
_NO_PIXELS = np.empty(0, np.int64)
# Depth (metres) of the plane that culling clips boxes with; visible points are much farther.
NEAR_CLIP = 0.05


def _screen_select(T_wc: np.ndarray, intr: Intrinsics
                   ) -> Callable[[np.ndarray], Selection]:
    """For row-major pixel rays of a camera (unit z, so ``t`` is the z-depth): per box given by
    its corners (P, 8, 3, ordered as :func:`~relocdepth.synth.scene.box_corners`), the pixels
    inside the image rectangle bounding its projection, clipped by the plane z = NEAR_CLIP in
    front of the camera (nothing visible is nearer: cameras keep clear of surfaces), and the box's
    least z-depth; no pixels when the box is wholly behind that plane or off the image."""
    R, c = T_wc[:3, :3], T_wc[:3, 3]
    w, h = intr.width, intr.height

    def rectangle(p: np.ndarray) -> np.ndarray:
        """Pixel bounds (u0, u1, v0, v1) of camera-frame points (M, 3), all in front."""
        u = intr.fx * p[:, 0] / p[:, 2] + intr.cx
        v = intr.fy * p[:, 1] / p[:, 2] + intr.cy
        return np.array([u.min(), u.max(), v.min(), v.max()])

    def select(corners: np.ndarray) -> Selection:
        p = (corners - c) @ R                                             # (P, 8, 3)
        front = p[:, :, 2] >= NEAR_CLIP
        # All corners in front (most boxes): the projected rectangles in one go.
        z = np.where(front, p[:, :, 2], 1.0)
        u = intr.fx * p[:, :, 0] / z + intr.cx
        v = intr.fy * p[:, :, 1] / z + intr.cy
        bounds = np.stack([u.min(1), u.max(1), v.min(1), v.max(1)], 1)
        for i in np.flatnonzero(front.any(1) & ~front.all(1)):
            # Partly behind the clipping plane: add where the box's edges cross it.
            q, f = p[i], front[i]
            j, k = _BOX_EDGES[f[_BOX_EDGES[:, 0]] != f[_BOX_EDGES[:, 1]]].T
            s = (NEAR_CLIP - q[j, 2]) / (q[k, 2] - q[j, 2])
            bounds[i] = rectangle(np.concatenate([q[f], q[j] + s[:, None] * (q[k] - q[j])]))
        u0 = np.maximum(np.floor(bounds[:, 0]), 0).astype(np.int64)
        u1 = np.minimum(np.ceil(bounds[:, 1]), w - 1).astype(np.int64)
        v0 = np.maximum(np.floor(bounds[:, 2]), 0).astype(np.int64)
        v1 = np.minimum(np.ceil(bounds[:, 3]), h - 1).astype(np.int64)
        visible = front.any(1) & (u0 <= u1) & (v0 <= v1)
        z_min = np.maximum(p[:, :, 2].min(1), NEAR_CLIP)  # z is linear: least at a corner
        out: Selection = [(_NO_PIXELS, np.inf)] * len(p)
        for i in np.flatnonzero(visible):
            pixels = (np.arange(v0[i], v1[i] + 1)[:, None] * w + np.arange(u0[i], u1[i] + 1))
            out[i] = (pixels.ravel(), float(z_min[i]))
        return out

    return select


# Pixels per block of texture evaluation: small enough for the (block, K) temporaries to stay
# in cache, which makes the evaluation several times faster than one pass over the image.
SHADE_BLOCK = 4096


def shade(scene: Scene, points: np.ndarray, face: np.ndarray, normal: np.ndarray,
          footprint: np.ndarray) -> np.ndarray:
    """Colour (N, 3) float32 in [0, 1] of surface points (N, 3) on faces (N,) with normals (N, 3);
    ``footprint`` (N,) is the Gaussian sigma (metres on the surface) the texture is filtered by."""
    colour = np.empty((len(points), 3), np.float32)
    order = np.argsort(face, kind="stable")
    ids, starts = np.unique(face[order], return_index=True)
    ends = np.append(starts[1:], len(order))
    p32, fp32 = points.astype(np.float32), footprint.astype(np.float32)
    for f, a, b in zip(ids, starts, ends):
        for c in range(a, b, SHADE_BLOCK):
            idx = order[c:min(c + SHADE_BLOCK, b)]
            colour[idx] = texture(scene, int(f), p32[idx], fp32[idx])
    # View-independent Lambertian light plus a smooth falloff from a ceiling light.
    lambert = 0.6 + 0.4 * np.clip(_lin(normal, scene.light_dir), 0, None)
    falloff = 0.8 + 0.35 * np.exp(-np.sum((points - scene.light_pos) ** 2, axis=1) / 6.0)
    return np.clip(colour * (lambert * falloff)[:, None].astype(np.float32), 0, 1)


def render(scene: Scene, T_wc: np.ndarray, intrinsics: Intrinsics,
           texture_blur_px: float = SynthConfig.texture_blur_px) -> tuple[np.ndarray, np.ndarray]:
    """Render one frame.

    Args:
        T_wc: (4, 4) world-from-camera pose, OpenCV camera axes (x right, y down, z forward).
        intrinsics: the pinhole camera (pixel centres at integer coordinates).
    Returns:
        rgb (H, W, 3) uint8 and depth (H, W) float32: exact z-depth in metres at pixel centres.
    """
    T_wc = np.asarray(T_wc, np.float64)
    rays = pixel_rays(intrinsics)
    dirs = _lin(rays, T_wc[:3, :3].T)
    t, face, normal = cast_rays(scene, T_wc[:3, 3], dirs, _screen_select(T_wc, intrinsics))
    points = T_wc[:3, 3] + t[:, None] * dirs
    ray_norm = np.linalg.norm(rays, axis=1)  # = |dirs|
    ray_len = t * ray_norm
    cos = np.abs(np.einsum("ij,ij->i", normal, dirs)) / ray_norm
    # Pixel footprint on the surface: a pixel spans ray_len / f metres across the ray, stretched
    # by 1 / cos along the slope (geometric mean of the two directions).
    f = 0.5 * (intrinsics.fx + intrinsics.fy)
    footprint = texture_blur_px * ray_len / f / np.sqrt(np.maximum(cos, 0.1))
    colour = shade(scene, points, face, normal, footprint)
    h, w = intrinsics.height, intrinsics.width
    rgb = np.rint(colour * 255).astype(np.uint8).reshape(h, w, 3)
    return rgb, t.astype(np.float32).reshape(h, w)

