"""The room of the generated scene: primitives (boxes, spheres, vertical cylinders), the furniture
built from them, and the signed distance to the nearest surface.

The room is a kitchen-sized box (z up, floor at z = 0) lined with furniture (counters with objects
on them and wall shelves above, a table with a chair, a bookcase, low cabinets) and a low island
under the cameras with objects on it: boxes, cylinders and spheres 0.5-1.5 m from the camera
paths, with depth discontinuities everywhere, as a real kitchen has.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from relocdepth.errors import UserError
from relocdepth.synth.config import SynthConfig
from relocdepth.synth.textures import N_SMOOTH, FaceTextures, box_faces, room_faces


@dataclass(frozen=True)
class Box:
    """An oriented box: ``centre`` (3,), half sizes ``half`` (3,), ``yaw`` about world z (rad).
    Faces ``face0 .. face0+5`` in the order -x, +x, -y, +y, -z, +z of the box frame."""

    centre: np.ndarray
    half: np.ndarray
    yaw: float
    face0: int

    def rotation(self) -> np.ndarray:
        """World-from-box rotation (3, 3)."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Sphere:
    """A sphere: ``centre`` (3,), ``radius``; one face ``face0``."""

    centre: np.ndarray
    radius: float
    face0: int


@dataclass(frozen=True)
class Cylinder:
    """A vertical capped cylinder: axis at ``centre_xy`` (2,), ``radius``, from ``z0`` to ``z1``.
    Faces ``face0`` (side), ``face0+1`` (top), ``face0+2`` (bottom)."""

    centre_xy: np.ndarray
    radius: float
    z0: float
    z1: float
    face0: int


@dataclass(frozen=True)
class Scene:
    """The room (faces 0-5: -x, +x, -y, +y, floor, ceiling), its objects, and per-face textures.

    Texture of face f at world point p (colour in [0, 1] before shading):
    ``base[f] + sum_k weight[f, k] * term_k(2 pi freq[f, k] . p + phase[f, k])`` where the first
    ``n_smooth`` terms are sinusoids and the rest soft-edged stripes ``tanh(g sin(.))``.
    """

    lo: np.ndarray            # (3,) room corner
    hi: np.ndarray            # (3,) opposite corner
    boxes: tuple[Box, ...]
    spheres: tuple[Sphere, ...]
    cylinders: tuple[Cylinder, ...]
    base: np.ndarray          # (F, 3) float32
    freq: np.ndarray          # (F, K, 3) float32, cycles per metre
    phase: np.ndarray         # (F, K) float32
    weight: np.ndarray        # (F, K, 3) float32
    freq_norm: np.ndarray     # (F, K) float32, |freq|
    n_smooth: int
    light_dir: np.ndarray     # (3,) unit, towards the light
    light_pos: np.ndarray     # (3,) a soft ceiling light for a smooth spatial falloff
    corners: np.ndarray       # (P, 8, 3) bounding-box corners of boxes, spheres, cylinders (culling)


MAX_FURNITURE_DEPTH = 0.65  # metres from the wall: a kitchen counter
MIN_FURNITURE_DEPTH = 0.3   # less leaves no room for a table and a chair


def build_scene(seed: int, cfg: SynthConfig | None = None) -> Scene:
    """The room and its furniture for ``seed`` (geometry from ``cfg``, whose own seed is ignored).

    Every wall is lined with one piece of furniture, in a random order per seed: two kitchen
    counters (objects on top, a wall shelf with objects above), a table (objects, a chair, a
    picture above) and a bookcase (objects on every board) beside a low cabinet. Furniture reaches
    into the room up to ``min_clearance`` from the box the cameras move in, so whatever way a
    camera looks, clutter stands 0.5-1.5 m in front of it and the wall behind."""
    cfg = cfg or SynthConfig()
    rng = np.random.default_rng([seed, 0])
    half = np.array(cfg.room) / 2
    lo, hi = np.array([-half[0], -half[1], 0.0]), np.array([half[0], half[1], cfg.room[2]])
    faces = FaceTextures(rng)
    room_faces(faces, rng)
    b = _Builder(faces, rng)
    cam_lo, cam_hi = np.array(cfg.camera_lo), np.array(cfg.camera_hi)
    # Room-depth (metres from the wall) each wall's furniture may take: up to the clearance.
    walls = [(axis, side) for axis in (1, 0) for side in (-1.0, 1.0)]
    room_depth = [float((cam_lo[a] - lo[a] if s < 0 else hi[a] - cam_hi[a]) - cfg.min_clearance)
                  for a, s in walls]
    if min(room_depth) < MIN_FURNITURE_DEPTH:
        raise UserError("the camera box leaves no room for furniture: enlarge the room")
    kinds = [str(k) for k in rng.permutation(["counter", "counter", "table", "bookcase"])]
    for w, ((axis, side), kind) in enumerate(zip(walls, kinds)):
        depth = min(room_depth[w], MAX_FURNITURE_DEPTH)
        if axis == 1:  # the long walls run corner to corner; the short ones fit between them
            s0, s1 = lo[0] + 0.02, hi[0] - 0.02
        else:
            s0 = lo[1] + min(room_depth[0], MAX_FURNITURE_DEPTH) + 0.05
            s1 = hi[1] - min(room_depth[1], MAX_FURNITURE_DEPTH) - 0.05
        wall = _Wall(axis, side, lo, hi)
        {"counter": _counter, "table": _table, "bookcase": _bookcase}[kind](b, wall, s0, s1, depth)
    _island(b, cam_lo, cam_hi, cfg.min_clearance)
    light = np.array([0.35, 0.55, 1.0])
    return Scene(
        lo=lo, hi=hi, boxes=tuple(b.boxes), spheres=tuple(b.spheres), cylinders=tuple(b.cylinders),
        base=np.array(faces.base, np.float32), freq=np.array(faces.freq, np.float32),
        phase=np.array(faces.phase, np.float32), weight=np.array(faces.weight, np.float32),
        freq_norm=np.linalg.norm(np.array(faces.freq, np.float32), axis=2),
        n_smooth=N_SMOOTH, light_dir=light / np.linalg.norm(light),
        light_pos=np.array([0.3 * lo[0], 0.2 * hi[1], hi[2] - 0.2]),
        corners=np.array([bounding_corners(p) for p in (*b.boxes, *b.spheres, *b.cylinders)]
                         ).reshape(-1, 8, 3),
    )


@dataclass(frozen=True)
class _Wall:
    """Coordinates along a wall: ``s`` along it (world axis ``1 - axis``), ``n`` metres from it
    into the room, ``z`` up. The wall is the room face at ``axis`` on ``side`` (-1: lo, +1: hi)."""

    axis: int
    side: float
    lo: np.ndarray
    hi: np.ndarray

    def bounds(self, s: tuple[float, float], n: tuple[float, float], z: tuple[float, float]
               ) -> tuple[np.ndarray, np.ndarray]:
        """World corners (lo, hi) of the box spanning ``s``, ``n`` and ``z`` intervals."""
        a = self.axis
        at = self.lo[a] if self.side < 0 else self.hi[a]
        ends = sorted((at - self.side * n[0], at - self.side * n[1]))
        box_lo, box_hi = np.zeros(3), np.zeros(3)
        box_lo[1 - a], box_hi[1 - a] = s
        box_lo[a], box_hi[a] = ends
        box_lo[2], box_hi[2] = z
        return box_lo, box_hi

    def point(self, s: float, n: float, z: float) -> np.ndarray:
        """The world point at ``(s, n, z)``."""
        return self.bounds((s, s), (n, n), (z, z))[0]


class _Builder:
    """Collects the primitives (and their textures) of the furniture while the scene is built."""

    def __init__(self, faces: FaceTextures, rng: np.random.Generator) -> None:
        self.faces, self.rng = faces, rng
        self.boxes: list[Box] = []
        self.spheres: list[Sphere] = []
        self.cylinders: list[Cylinder] = []

    def box(self, lo: np.ndarray, hi: np.ndarray, yaw: float = 0.0) -> None:
        """A box between world corners ``lo`` and ``hi`` (before turning by ``yaw`` about z)."""
        centre, half = (lo + hi) / 2, (hi - lo) / 2
        self.boxes.append(Box(centre, half, yaw, box_faces(self.faces, yaw)))

    def cylinder(self, xy: np.ndarray, radius: float, z0: float, z1: float) -> None:
        base = self.faces.palette()
        f0 = self.faces.add(base, None)
        self.faces.add(base * 0.9, np.array([0.0, 0.0, 1.0]))
        self.faces.add(base * 0.9, np.array([0.0, 0.0, 1.0]))
        self.cylinders.append(Cylinder(np.asarray(xy, float), radius, z0, z1, f0))

    def sphere(self, centre: np.ndarray, radius: float) -> None:
        self.spheres.append(Sphere(np.asarray(centre, float), radius,
                                   self.faces.add(self.faces.palette(val=(0.4, 0.65)), None)))


def _clutter(b: _Builder, wall: _Wall, s: tuple[float, float], n: tuple[float, float], z: float,
             max_height: float, fill: float = 0.6) -> None:
    """Objects standing on the surface at height ``z`` over ``s`` x ``n`` (wall coordinates):
    boxes (turned at random), cylinders and spheres up to ``max_height`` tall, side by side along
    the wall with gaps, covering about ``fill`` of its length."""
    rng = b.rng
    cursor = s[0] + rng.uniform(0.0, 0.1)
    while True:
        r = min(rng.uniform(0.04, 0.13), (n[1] - n[0]) / 2 - 0.01)
        if cursor + 2 * r > s[1] or r < 0.02:
            return
        centre_s = cursor + r
        centre_n = rng.uniform(n[0] + r, n[1] - r)
        xy = wall.point(centre_s, centre_n, z)[:2]
        height = rng.uniform(min(0.06, max_height), max_height)
        kind = rng.choice(["box", "box", "cylinder", "cylinder", "sphere"])
        if kind == "box":  # half sizes up to r / sqrt 2: fits its footprint at any turn
            half = np.append(rng.uniform(0.45, 0.7, 2) * r, height / 2)
            centre = np.append(xy, z + height / 2)
            b.box(centre - half, centre + half, float(rng.uniform(0, np.pi)))
        elif kind == "cylinder":
            b.cylinder(xy, float(r * rng.uniform(0.5, 1.0)), z, z + height)
        else:
            radius = min(r, height / 2)
            b.sphere(np.append(xy, z + radius), float(radius))
        cursor += 2 * r + rng.uniform(0.02, 0.3) * (1 - fill) / 0.4


def _counter(b: _Builder, wall: _Wall, s0: float, s1: float, depth: float) -> None:
    """A kitchen counter along the whole wall with objects on it, and a wall shelf above it with
    smaller objects."""
    rng = b.rng
    top = rng.uniform(0.86, 0.94)
    b.box(*wall.bounds((s0, s1), (0.0, depth), (0.0, top)))
    _clutter(b, wall, (s0, s1), (0.03, depth - 0.03), top, 0.42, fill=0.65)
    length = rng.uniform(0.9, 1.6)
    a = s0 + rng.uniform(0.0, max(s1 - length - s0, 0.0))
    shelf_z, shelf_n = rng.uniform(1.45, 1.65), min(0.3, depth)
    b.box(*wall.bounds((a, a + length), (0.0, shelf_n), (shelf_z - 0.03, shelf_z)))
    _clutter(b, wall, (a, a + length), (0.02, shelf_n - 0.02), shelf_z, 0.3, fill=0.6)


def _table(b: _Builder, wall: _Wall, s0: float, s1: float, depth: float) -> None:
    """A table against the wall with objects on it, a chair beside it and a picture above."""
    rng = b.rng
    width = min(rng.uniform(1.1, 1.6), s1 - s0 - 0.6)
    a = s0 + 0.6 + rng.uniform(0.0, max(s1 - width - s0 - 0.6, 0.0))
    top = rng.uniform(0.72, 0.78)
    b.box(*wall.bounds((a, a + width), (0.0, depth), (top - 0.04, top)))
    for s in (a + 0.03, a + width - 0.08):
        for n in (0.03, depth - 0.08):
            b.box(*wall.bounds((s, s + 0.05), (n, n + 0.05), (0.0, top - 0.04)))
    _clutter(b, wall, (a, a + width), (0.03, depth - 0.03), top, 0.4, fill=0.7)
    seat = min(0.44, depth - 0.1)
    c = a - seat - rng.uniform(0.05, 0.12)  # a chair at the table's end, its back to the table
    n0 = 0.05 + rng.uniform(0.0, max(depth - seat - 0.1, 0.0))
    b.box(*wall.bounds((c, c + seat), (n0, n0 + seat), (0.42, 0.47)))
    b.box(*wall.bounds((c, c + 0.04), (n0, n0 + seat), (0.47, 0.92)))
    b.cylinder(wall.point(c + seat / 2, n0 + seat / 2, 0.0)[:2], 0.03, 0.0, 0.42)
    pw = rng.uniform(0.4, 0.8)
    p0 = rng.uniform(a, a + width - pw)
    pz = rng.uniform(1.2, 1.6)
    b.box(*wall.bounds((p0, p0 + pw), (0.0, 0.025), (pz, pz + rng.uniform(0.3, 0.55))))
    if a + width + 0.5 < s1:  # a low cabinet fills the rest of the wall
        _cabinet(b, wall, a + width + 0.1, s1, depth)


ISLAND_SIZE = (0.8, 1.1)


def _island(b: _Builder, cam_lo: np.ndarray, cam_hi: np.ndarray, clear: float) -> None:
    """A low kitchen island (a block) under the cameras with objects on it, its top (objects
    included) kept ``clear`` below the lowest camera: the near clutter of a look down."""
    rng = b.rng
    centre = (cam_lo[:2] + cam_hi[:2]) / 2
    half = (cam_hi[:2] - cam_lo[:2]) / 2 * rng.uniform(ISLAND_SIZE[0], ISLAND_SIZE[1], 2)
    objects = rng.uniform(0.08, 0.14)
    top = cam_lo[2] - clear - objects
    xy_lo, xy_hi = centre - half, centre + half
    b.box(np.append(xy_lo, 0.0), np.append(xy_hi, top))
    wall = _Wall(1, -1.0, np.append(xy_lo, 0.0), np.append(xy_hi, 0.0))  # rows along x
    rows = int(max(1, (xy_hi[1] - xy_lo[1]) // 0.3))
    edges = np.linspace(0.0, xy_hi[1] - xy_lo[1], rows + 1)
    for n0, n1 in itertools.pairwise(edges):
        _clutter(b, wall, (xy_lo[0] + 0.03, xy_hi[0] - 0.03), (n0 + 0.02, n1 - 0.02), top,
                 objects, fill=0.6)


def _cabinet(b: _Builder, wall: _Wall, s0: float, s1: float, depth: float) -> None:
    """A low cabinet with objects on it."""
    top = b.rng.uniform(0.5, 0.9)
    d = b.rng.uniform(0.35, depth)
    b.box(*wall.bounds((s0, s1), (0.0, d), (0.0, top)))
    _clutter(b, wall, (s0, s1), (0.03, d - 0.03), top, 0.45, fill=0.5)


def _bookcase(b: _Builder, wall: _Wall, s0: float, s1: float, depth: float) -> None:
    """An open bookcase (sides, boards, objects on every board) and a low cabinet beside it."""
    rng = b.rng
    width = min(rng.uniform(0.8, 1.3), (s1 - s0) / 2)
    a = s0 + rng.uniform(0.0, max(s1 - width - s0, 0.0))
    d, height = min(0.38, depth), rng.uniform(1.8, 2.1)
    for s in (a, a + width - 0.03):
        b.box(*wall.bounds((s, s + 0.03), (0.0, d), (0.0, height)))
    levels = np.linspace(0.05, height - 0.03, 5)
    for z0, z1 in itertools.pairwise(levels):
        b.box(*wall.bounds((a + 0.03, a + width - 0.03), (0.0, d), (z0 - 0.03, z0)))
        _clutter(b, wall, (a + 0.04, a + width - 0.04), (0.02, d - 0.02), z0, z1 - z0 - 0.06,
                 fill=0.8)
    b.box(*wall.bounds((a + 0.03, a + width - 0.03), (0.0, d), (height - 0.03, height)))
    for lo_s, hi_s in ((s0, a - 0.1), (a + width + 0.1, s1)):
        if hi_s - lo_s > 0.5:
            _cabinet(b, wall, lo_s, hi_s, depth)


def clearance(scene: Scene, points: np.ndarray) -> np.ndarray:
    """Distance (N,) from each point (N, 3) inside the room to the nearest surface (negative
    inside an object): the minimum of the signed distance functions of all primitives."""
    p = np.asarray(points, np.float64)
    d = np.minimum(p - scene.lo, scene.hi - p).min(axis=1)
    for b in scene.boxes:
        q = np.abs((p - b.centre) @ b.rotation()) - b.half
        sdf = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
        d = np.minimum(d, sdf)
    for s in scene.spheres:
        d = np.minimum(d, np.linalg.norm(p - s.centre, axis=1) - s.radius)
    for c in scene.cylinders:
        q = np.stack([np.linalg.norm(p[:, :2] - c.centre_xy, axis=1) - c.radius,
                      np.abs(p[:, 2] - (c.z0 + c.z1) / 2) - (c.z1 - c.z0) / 2], axis=1)
        sdf = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
        d = np.minimum(d, sdf)
    return d



def box_corners(lo: np.ndarray, hi: np.ndarray, rot: np.ndarray | None = None,
             centre: np.ndarray | None = None) -> np.ndarray:
    """The 8 corners (8, 3) of the box [lo, hi], optionally rotated by ``rot`` about ``centre``;
    corner i takes hi on axis a where bit a of i is set (so edges join i and i ^ 2**a)."""
    bits = (np.arange(8)[:, None] >> np.arange(3)) & 1
    c = np.where(bits == 1, hi, lo)
    return c if rot is None else centre + (c - centre) @ rot.T


def bounding_corners(prim: Box | Sphere | Cylinder) -> np.ndarray:
    """Corners (8, 3) of a box bounding the primitive (used to cull rays)."""
    if isinstance(prim, Box):
        return box_corners(prim.centre - prim.half, prim.centre + prim.half, prim.rotation(),
                        prim.centre)
    if isinstance(prim, Sphere):
        return box_corners(prim.centre - prim.radius, prim.centre + prim.radius)
    r = prim.radius
    return box_corners(np.array([*(prim.centre_xy - r), prim.z0]),
                    np.array([*(prim.centre_xy + r), prim.z1]))


