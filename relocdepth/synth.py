"""A generated indoor scene in the exact Microsoft 7-Scenes layout: the demo data, test fixture
and evaluation ground truth of the project.

The scene is a kitchen-sized textured room (a box, z up, floor at z = 0) lined with furniture
(counters with objects on them and wall shelves above, a table with a chair, a bookcase, low
cabinets) and a low island under the cameras with objects on it: boxes, cylinders and spheres
0.5-1.5 m from the camera paths, with depth discontinuities everywhere, as a real kitchen has.
Frames are rendered by exact analytic ray casting in numpy, so depth (z-depth along the camera
axis, as 7-Scenes stores it) and poses are exact. Colours come from procedural textures evaluated
at the 3-D hit point (sums of sinusoids at several scales plus soft-edged stripes), prefiltered
analytically by the pixel footprint so that bilinear resampling works, and shaded by a
view-independent (Lambertian) light term, so photometric consistency holds.

Camera paths move like handheld 7-Scenes video at 30 fps: a smooth path (sums of low-frequency
sinusoids) at a median 0.72 cm per frame whose heading turns slowly (0.3 deg per frame), plus
a bounded hand tremor (about 0.85 deg RMS, periods of a few frames) that makes the per-frame
rotation about 1.5 deg without adding up over longer gaps. The test sequence follows the first
training path offset by 18-26 cm with a slightly perturbed orientation: near, but not on, the
training paths. Everything is deterministic from the seed.
"""

from __future__ import annotations

import functools
import itertools
import json
import logging
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from relocdepth.camera import Intrinsics
from relocdepth.errors import UserError

log = logging.getLogger(__name__)

# The 7-Scenes RGB camera (the values DSAC* and ACE use) at its native 640x480.
SEVEN_SCENES_INTRINSICS = Intrinsics(525.0, 525.0, 320.0, 240.0, 640, 480)

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class SynthConfig:
    """What `reloc synth` generates. Lengths in metres, angles in degrees."""

    seed: int = 0                      # one seed fixes scene, textures and paths
    frames: int = 300                  # per sequence: 10 s at 30 fps
    width: int = 640                   # 7-Scenes RGB image size
    height: int = 480
    train_sequences: int = 2           # seq-01..seq-N train, seq-(N+1) test (7-Scenes scenes: 2-12)
    fps: float = 30.0                  # 7-Scenes (Kinect) frame rate; also the mp4 rate
    step_m: float = 0.0072             # median translation per frame (7-Scenes: 0.74 cm)
    turn_deg: float = 0.3              # median smooth (heading) rotation per frame, tremor aside
    tremor_deg: float = 0.85           # RMS per axis of the hand tremor (7-Scenes: 1.6 deg/frame)
    calibration_frames: int = 300      # the speeds are medians over this many frames
    room: Vec3 = (3.5, 2.7, 2.6)       # room size x, y, z (a kitchen-sized box)
    camera_lo: Vec3 = (-0.8, -0.5, 1.15)  # every camera centre stays in this box ...
    camera_hi: Vec3 = (0.8, 0.5, 1.65)    # ... which furniture keeps min_clearance away from
    min_clearance: float = 0.3         # no surface nearer than this to a camera centre
    path_amplitude: Vec3 = (0.5, 0.22, 0.12)  # reach of a training path about its centre
    yaw_amplitude: float = 100.0       # how far a path pans left/right about its base heading
    pitch_base: float = -30.0          # looking down, at the island, counters and tables
    pitch_amplitude: float = 12.0
    roll_amplitude: float = 4.0        # handheld cameras roll a little
    test_offset: float = 0.22          # horizontal offset of the test path from seq-01 (+-4 cm)
    test_angle_offset: float = 6.0     # orientation perturbation of the test path
    texture_blur_px: float = 0.6       # Gaussian sigma (pixels) of the analytic texture prefilter


# ----------------------------------------------------------------------------------------------
# Scene


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


N_SMOOTH = 12          # sinusoids per face, wavelengths log-spaced over WAVELENGTHS
N_EDGE = 4             # soft-edged stripe terms per face, wavelengths over EDGE_WAVELENGTHS
WAVELENGTHS = (0.03, 1.2)
EDGE_WAVELENGTHS = (0.08, 0.45)
EDGE_SHARPNESS = 8.0   # tanh gain of the stripes when the pixel footprint is negligible


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
    faces = _FaceTextures(rng)
    _room_faces(faces, rng)
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
        corners=np.array([_bounds(p) for p in (*b.boxes, *b.spheres, *b.cylinders)]).reshape(-1, 8, 3),
    )


class _FaceTextures:
    """Accumulates per-face texture parameters while the scene is built."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.base: list[np.ndarray] = []
        self.freq: list[np.ndarray] = []
        self.phase: list[np.ndarray] = []
        self.weight: list[np.ndarray] = []

    def palette(self, sat: tuple[float, float] = (0.2, 0.6), val: tuple[float, float] = (0.35, 0.6)
                ) -> np.ndarray:
        """A random base colour (3,) from hue/saturation/value ranges."""
        h, s, v = self.rng.uniform(0, 1), self.rng.uniform(*sat), self.rng.uniform(*val)
        rgb = np.clip(np.abs((h * 6 + np.array([0.0, 4.0, 2.0])) % 6 - 3) - 1, 0, 1)
        return v * (1 - s + s * rgb)

    def add(self, base: np.ndarray, normal: np.ndarray | None) -> int:
        """Add a face with colour ``base``; frequencies lie in the plane of ``normal`` (a planar
        face) or point anywhere (a curved one: a solid texture). Returns the face id."""
        rng = self.rng
        lam = np.concatenate([
            np.exp(np.linspace(np.log(WAVELENGTHS[0]), np.log(WAVELENGTHS[1]), N_SMOOTH)),
            np.exp(rng.uniform(np.log(EDGE_WAVELENGTHS[0]), np.log(EDGE_WAVELENGTHS[1]), N_EDGE)),
        ]) * rng.uniform(0.8, 1.25, N_SMOOTH + N_EDGE)
        dirs = rng.normal(size=(len(lam), 3))
        if normal is not None:
            dirs -= np.outer(dirs @ normal, normal)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        # Coarse scales carry more contrast, but fine ones stay visible (no flat areas).
        amp = np.concatenate([0.06 * (lam[:N_SMOOTH] / WAVELENGTHS[1]) ** 0.2,
                              np.full(N_EDGE, 0.05)])
        tint = rng.normal(size=(len(lam), 3)) * 0.3 + 1.0  # mostly luminance, some chroma
        tint /= np.linalg.norm(tint, axis=1, keepdims=True) / np.sqrt(3)
        sign = rng.choice([-1.0, 1.0], size=(len(lam), 1))
        self.base.append(base * rng.uniform(0.9, 1.1, 3))
        self.freq.append(dirs / lam[:, None])
        self.phase.append(rng.uniform(0, 2 * np.pi, len(lam)))
        self.weight.append(sign * amp[:, None] * tint)
        return len(self.base) - 1


def _room_faces(faces: _FaceTextures, rng: np.random.Generator) -> None:
    wall = faces.palette()
    for axis in range(3):
        for side in (-1.0, 1.0):
            n = np.zeros(3)
            n[axis] = -side  # pointing into the room
            if axis < 2:
                base = wall * rng.uniform(0.85, 1.15) + rng.uniform(-0.05, 0.05, 3)
            elif side < 0:
                base = faces.palette(sat=(0.3, 0.6), val=(0.3, 0.45))  # floor
            else:
                base = faces.palette(sat=(0.0, 0.15), val=(0.55, 0.65))  # ceiling
            faces.add(np.clip(base, 0.1, 0.8), n)


def _box_faces(faces: _FaceTextures, yaw: float) -> int:
    base = faces.palette()
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    first = -1
    for axis in range(3):
        for side in (-1.0, 1.0):
            f = faces.add(base * faces.rng.uniform(0.85, 1.15), rot[:, axis] * side)
            first = f if first < 0 else first
    return first


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

    def __init__(self, faces: _FaceTextures, rng: np.random.Generator) -> None:
        self.faces, self.rng = faces, rng
        self.boxes: list[Box] = []
        self.spheres: list[Sphere] = []
        self.cylinders: list[Cylinder] = []

    def box(self, lo: np.ndarray, hi: np.ndarray, yaw: float = 0.0) -> None:
        """A box between world corners ``lo`` and ``hi`` (before turning by ``yaw`` about z)."""
        centre, half = (lo + hi) / 2, (hi - lo) / 2
        self.boxes.append(Box(centre, half, yaw, _box_faces(self.faces, yaw)))

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


# ----------------------------------------------------------------------------------------------
# Rendering


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


def _corners(lo: np.ndarray, hi: np.ndarray, rot: np.ndarray | None = None,
             centre: np.ndarray | None = None) -> np.ndarray:
    """The 8 corners (8, 3) of the box [lo, hi], optionally rotated by ``rot`` about ``centre``;
    corner i takes hi on axis a where bit a of i is set (so edges join i and i ^ 2**a)."""
    bits = (np.arange(8)[:, None] >> np.arange(3)) & 1
    c = np.where(bits == 1, hi, lo)
    return c if rot is None else centre + (c - centre) @ rot.T


def _bounds(prim: Box | Sphere | Cylinder) -> np.ndarray:
    """Corners (8, 3) of a box bounding the primitive (used to cull rays)."""
    if isinstance(prim, Box):
        return _corners(prim.centre - prim.half, prim.centre + prim.half, prim.rotation(),
                        prim.centre)
    if isinstance(prim, Sphere):
        return _corners(prim.centre - prim.radius, prim.centre + prim.radius)
    r = prim.radius
    return _corners(np.array([*(prim.centre_xy - r), prim.z0]),
                    np.array([*(prim.centre_xy + r), prim.z1]))


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


# Pairs of corner indices (12, 2) joined by an edge of a box (see _corners).
_BOX_EDGES = np.array([(i, i | 1 << a) for a in range(3) for i in range(8) if not i >> a & 1])
_NO_PIXELS = np.empty(0, np.int64)
# Depth (metres) of the plane that culling clips boxes with; visible points are much farther.
NEAR_CLIP = 0.05


def _screen_select(T_wc: np.ndarray, intr: Intrinsics
                   ) -> Callable[[np.ndarray], Selection]:
    """For row-major pixel rays of a camera (unit z, so ``t`` is the z-depth): per box given by
    its corners (P, 8, 3, ordered as :func:`_corners`), the pixels inside the image rectangle
    bounding its projection, clipped by the plane z = NEAR_CLIP in front of the camera (nothing
    visible is nearer: cameras keep clear of surfaces), and the box's least z-depth; no pixels
    when the box is wholly behind that plane or off the image."""
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


def _texture(scene: Scene, f: int, p: np.ndarray, footprint: np.ndarray) -> np.ndarray:
    """Unshaded colour (m, 3) float32 of face ``f`` at points (m, 3) float32, prefiltered by a
    Gaussian of sigma ``footprint`` (m,) metres: a sinusoid of frequency k (cycles per metre) is
    attenuated by exp(-2 pi^2 k^2 sigma^2), and the stripes' tanh gain is capped so that their
    edges are never sharper than the footprint. Blocks of m <= SHADE_BLOCK keep the thin matrix
    products below the size where BLAS starts threads."""
    k, ns = scene.freq[f], scene.n_smooth                             # (K, 3)
    arg = p @ (2 * np.pi * k.T).astype(np.float32)
    arg += scene.phase[f]
    terms = np.sin(arg, out=arg)                                      # (m, K)
    kf = footprint[:, None] * scene.freq_norm[f]                      # (m, K) cycles per sigma
    gain = 1.0 / np.sqrt(EDGE_SHARPNESS**-2 + (2 * np.pi * kf[:, ns:]) ** 2)
    terms[:, ns:] = np.tanh(gain * terms[:, ns:])
    kf *= kf
    kf *= -2 * np.pi**2
    terms *= np.exp(kf, out=kf)
    return scene.base[f] + terms @ scene.weight[f]


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
            colour[idx] = _texture(scene, int(f), p32[idx], fp32[idx])
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


# ----------------------------------------------------------------------------------------------
# Camera paths


@dataclass(frozen=True)
class _Sinusoids:
    """``centre + sum_j amp[:, j] sin(freq[:, j] tau + phase[:, j])``, per dimension (D rows)."""

    centre: np.ndarray  # (D,)
    amp: np.ndarray     # (D, J)
    freq: np.ndarray    # (D, J), radians per unit tau
    phase: np.ndarray   # (D, J)

    def __call__(self, tau: np.ndarray) -> np.ndarray:
        """Values (N, D) at ``tau`` (N,)."""
        return self.centre + np.sum(self.amp * np.sin(self.freq * tau[:, None, None] + self.phase), -1)

    def plus(self, other: _Sinusoids) -> _Sinusoids:
        """The sum of two sinusoid sets (same D)."""
        return _Sinusoids(self.centre + other.centre, np.hstack([self.amp, other.amp]),
                          np.hstack([self.freq, other.freq]), np.hstack([self.phase, other.phase]))


def _random_sinusoids(rng: np.random.Generator, centre: np.ndarray, reach: np.ndarray
                      ) -> _Sinusoids:
    """Three octave-ish components per dimension whose amplitudes sum to ``reach`` (D,)."""
    d = len(centre)
    rel_amp = np.array([1.0, 0.35, 0.1]) * rng.uniform(0.8, 1.2, (d, 3))
    amp = rel_amp / rel_amp.sum(1, keepdims=True) * np.asarray(reach)[:, None]
    freq = np.array([1.0, 2.3, 4.9]) * rng.uniform(0.7, 1.3, (d, 3))
    return _Sinusoids(np.asarray(centre, float), amp, freq, rng.uniform(0, 2 * np.pi, (d, 3)))


def rotation_from_angles(angles: np.ndarray) -> np.ndarray:
    """World-from-camera rotations (N, 3, 3) for (N, 3) (yaw, pitch, roll) radians in a z-up
    world: the camera looks along (cos p cos y, cos p sin y, sin p), image x to the right, image
    y down, then rolled about its optical axis."""
    yaw, pitch, roll = angles[:, 0], angles[:, 1], angles[:, 2]
    fwd = np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], 1)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd], axis=2)
    c, s = np.cos(roll), np.sin(roll)
    z, o = np.zeros_like(roll), np.ones_like(roll)
    R_roll = np.stack([np.stack([c, -s, z], 1), np.stack([s, c, z], 1), np.stack([z, z, o], 1)], 1)
    return R @ R_roll


def motion_steps(T_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame translation (N-1,) in metres and rotation (N-1,) in degrees of poses (N, 4, 4)."""
    return pair_motion(T_wc, 1)


def pair_motion(T_wc: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Translation (N-k,) in metres and rotation (N-k,) in degrees between frames t and t + k of
    poses (N, 4, 4), for every t."""
    T_wc = np.asarray(T_wc, np.float64)
    trans = np.linalg.norm(T_wc[k:, :3, 3] - T_wc[:-k, :3, 3], axis=1)
    rel = np.einsum("nji,njk->nik", T_wc[:-k, :3, :3], T_wc[k:, :3, :3])
    # The angle from the skew part (atan2) stays accurate for the small rotations of tremor.
    sin = np.linalg.norm(np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0],
                                   rel[:, 1, 0] - rel[:, 0, 1]], axis=1), axis=1) / 2
    cos = (np.trace(rel, axis1=1, axis2=2) - 1) / 2
    return trans, np.degrees(np.arctan2(sin, cos))


def _time_step(steps: Callable[[float], np.ndarray], target: float) -> float:
    """The tau increment per frame that makes the median of ``steps(dt)`` equal ``target``.
    Steps grow about linearly with the increment; damped rescalings converge."""
    dt = 0.02
    for _ in range(12):
        med = float(np.median(steps(dt)))
        if med <= 0:
            break
        dt *= (target / med) ** 0.7
    return dt


# Hand tremor: sinusoids per camera axis with periods of 2.5-12 frames at 30 fps (physiological
# tremor and the shake of a handheld camera), bounded, so it adds to every step but not to the
# rotation between frames far apart. Camera-frame axes x (tilt), y (pan), z (roll: less).
TREMOR_TERMS = 8
TREMOR_FREQ = (0.5, 2.5)  # radians per frame
TREMOR_AXES = (1.0, 1.0, 0.5)


def _tremor(rng: np.random.Generator, rms_deg: float) -> _Sinusoids:
    """Rotation vectors (camera frame, radians) of a tremor with ``rms_deg`` per axis (x, y), as a
    function of the frame index."""
    amp = rng.uniform(0.5, 1.5, (3, TREMOR_TERMS))
    amp *= np.radians(rms_deg) * np.array(TREMOR_AXES)[:, None] / np.sqrt(
        (amp**2).sum(1, keepdims=True) / 2)
    return _Sinusoids(np.zeros(3), amp, rng.uniform(*TREMOR_FREQ, (3, TREMOR_TERMS)),
                      rng.uniform(0, 2 * np.pi, (3, TREMOR_TERMS)))


def _rotvec_matrices(v: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of rotation vectors (N, 3) (Rodrigues)."""
    theta = np.linalg.norm(v, axis=1)[:, None, None]
    k = v / np.maximum(theta[:, :, 0], 1e-300)
    z = np.zeros(len(v))
    K = np.stack([np.stack([z, -k[:, 2], k[:, 1]], 1), np.stack([k[:, 2], z, -k[:, 0]], 1),
                  np.stack([-k[:, 1], k[:, 0], z], 1)], 1)
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K


def _poses(pos: _Sinusoids, ang: _Sinusoids, dt_pos: float, dt_ang: float, n: int,
           tremor: _Sinusoids | None = None) -> np.ndarray:
    i = np.arange(n, dtype=np.float64)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = rotation_from_angles(ang(i * dt_ang))
    if tremor is not None:
        T[:, :3, :3] = T[:, :3, :3] @ _rotvec_matrices(tremor(i))
    T[:, :3, 3] = pos(i * dt_pos)
    return T


def _as_written(T: np.ndarray) -> np.ndarray:
    """The poses exactly as the pose files store them (so images match the files)."""
    return np.array([float(_fmt(v)) for v in T.ravel()]).reshape(T.shape)


def _fmt(v: float) -> str:
    return f"{v: .8e}"


def sequence_names(cfg: SynthConfig) -> list[str]:
    """``seq-01`` ... for the training sequences, then the test sequence."""
    return [f"seq-{i + 1:02d}" for i in range(cfg.train_sequences + 1)]


def camera_paths(cfg: SynthConfig) -> dict[str, np.ndarray]:
    """World-from-camera poses (frames, 4, 4) of every sequence, training ones first, the test
    sequence last. Depends only on the seed and the motion fields of ``cfg`` (not on the size);
    the speeds are calibrated over the first ``calibration_frames`` frames, so a sequence of
    fewer frames is a prefix of a longer one."""
    _check_config(cfg)
    rng = np.random.default_rng([cfg.seed, 1])
    cam_lo, cam_hi = np.array(cfg.camera_lo), np.array(cfg.camera_hi)
    reach = np.array(cfg.path_amplitude)
    off_wobble = np.array([0.04, 0.04, 0.03])
    off_max = np.array([cfg.test_offset, cfg.test_offset, 0.05]) + off_wobble
    slack = np.maximum((cam_hi - cam_lo) / 2 - reach - off_max, 0)
    deg = np.radians
    names = sequence_names(cfg)
    specs = []
    for _ in range(cfg.train_sequences):
        centre = (cam_lo + cam_hi) / 2 + rng.uniform(-slack, slack)
        pos = _random_sinusoids(rng, centre, reach)
        ang0 = np.array([rng.uniform(0, 2 * np.pi), deg(cfg.pitch_base), 0.0])
        ang = _random_sinusoids(rng, ang0, deg([cfg.yaw_amplitude, cfg.pitch_amplitude,
                                                cfg.roll_amplitude]))
        specs.append((pos, ang, None))
    # Test: the first training path, shifted by a slowly varying offset, looking a bit aside.
    heading = rng.uniform(0, 2 * np.pi)
    offset = np.array([cfg.test_offset * np.cos(heading), cfg.test_offset * np.sin(heading),
                       rng.uniform(-0.05, 0.05)])
    wobble = _Sinusoids(offset, off_wobble[:, None], rng.uniform(0.3, 0.6, (3, 1)),
                        rng.uniform(0, 2 * np.pi, (3, 1)))
    a_off = deg(cfg.test_angle_offset)
    turn = _Sinusoids(rng.uniform(-a_off / 2, a_off / 2, 3) * [1, 1, 0],
                      np.array([[a_off], [a_off * 0.6], [a_off * 0.3]]),
                      rng.uniform(0.3, 0.8, (3, 1)), rng.uniform(0, 2 * np.pi, (3, 1)))
    specs.append((specs[0][0].plus(wobble), specs[0][1].plus(turn), 0))
    tremor_rng = np.random.default_rng([cfg.seed, 2])
    paths: dict[str, np.ndarray] = {}
    dts: list[tuple[float, float]] = []
    for name, (pos, ang, like) in zip(names, specs):
        if like is None:  # calibrated on a fixed window, so shorter sequences are prefixes
            n = cfg.calibration_frames
            dt_pos = _time_step(
                lambda dt, p=pos, a=ang, n=n: motion_steps(_poses(p, a, dt, 0, n))[0], cfg.step_m)
            dt_ang = _time_step(
                lambda dt, p=pos, a=ang, n=n: motion_steps(_poses(p, a, 0, dt, n))[1], cfg.turn_deg)
        else:  # the test path keeps its reference's timing, so views follow the positions
            dt_pos, dt_ang = dts[like]
        dts.append((dt_pos, dt_ang))
        tremor = _tremor(tremor_rng, cfg.tremor_deg) if cfg.tremor_deg > 0 else None
        paths[name] = _as_written(_poses(pos, ang, dt_pos, dt_ang, cfg.frames, tremor))
    return paths


# ----------------------------------------------------------------------------------------------
# Output


def _check_config(cfg: SynthConfig) -> None:
    if cfg.frames < 1:
        raise UserError(f"--frames must be a positive number of frames per sequence, got {cfg.frames}")
    if cfg.width < 16 or cfg.height < 16 or cfg.width % 2 or cfg.height % 2:
        raise UserError(f"--size must be even and at least 16x16 (the mp4 needs even sizes), "
                        f"got {cfg.width}x{cfg.height}")
    if cfg.train_sequences < 2:
        raise UserError(f"need at least 2 training sequences, got {cfg.train_sequences}")
    if cfg.fps <= 0 or cfg.step_m <= 0 or cfg.turn_deg <= 0 or cfg.tremor_deg < 0:
        raise UserError("fps, step_m and turn_deg must be positive, tremor_deg not negative")


def _check_output(out: Path, force: bool) -> None:
    if out.exists() and not force:
        if not out.is_dir():
            raise UserError(f"{out} exists and is not a folder; pass --force to replace it")
        if any(out.iterdir()):
            raise UserError(f"{out} exists and is not empty; pass --force to replace it")


def write_pose(path: Path, T_wc: np.ndarray) -> None:
    """A 7-Scenes pose file: 4 lines of 4 tab-separated floats (world-from-camera)."""
    path.write_text("".join("\t".join(_fmt(v) for v in row) + "\t\n" for row in T_wc))


def _write_sequence(seq_dir: Path, video: Path, scene: Scene, poses: np.ndarray,
                    intr: Intrinsics, cfg: SynthConfig, tick: Callable[[], None]) -> None:
    import cv2

    seq_dir.mkdir()
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), cfg.fps,
                             (intr.width, intr.height))
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV cannot write an mp4v video to {video}")
    try:
        for i, T in enumerate(poses):
            rgb, depth = render(scene, T, intr, cfg.texture_blur_px)
            bgr = np.ascontiguousarray(rgb[:, :, ::-1])
            stem = seq_dir / f"frame-{i:06d}"
            mm = np.clip(np.rint(depth * 1000.0), 0, 65535).astype(np.uint16)
            if not (cv2.imwrite(f"{stem}.color.png", bgr) and cv2.imwrite(f"{stem}.depth.png", mm)):
                raise RuntimeError(f"could not write {stem}.*.png")
            write_pose(Path(f"{stem}.pose.txt"), T)
            writer.write(bgr)
            tick()
    finally:
        writer.release()


def generate_scene(out_dir: str | Path, cfg: SynthConfig = SynthConfig(), *, force: bool = False,
                   progress: Callable[[int], None] | None = None) -> dict:
    """Write the scene to ``out_dir`` in the 7-Scenes layout and return a summary dict.

    Writes ``seq-XX/frame-XXXXXX.{color.png,depth.png,pose.txt}``, ``TrainSplit.txt``,
    ``TestSplit.txt``, ``intrinsics.yaml``, ``videos/seq-XX.mp4`` and ``synth.json`` (config and
    motion statistics), into a temporary folder beside ``out_dir`` renamed at the end.
    ``progress(n)`` is called with the number of frames written so far (of frames x sequences).
    """
    import yaml

    _check_config(cfg)
    out = Path(out_dir)
    _check_output(out, force)
    start = time.perf_counter()
    intr = SEVEN_SCENES_INTRINSICS.scaled(cfg.width, cfg.height)
    scene = build_scene(cfg.seed, cfg)
    paths = camera_paths(cfg)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    done = 0

    def tick() -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done)

    sequences = []
    try:
        (tmp / "videos").mkdir()
        for i, (name, poses) in enumerate(paths.items()):
            _write_sequence(tmp / name, tmp / "videos" / f"{name}.mp4", scene, poses, intr, cfg, tick)
            trans, rot = motion_steps(poses)
            split = "train" if i < cfg.train_sequences else "test"
            sequences.append({
                "name": name, "split": split, "frames": len(poses),
                "median_step_cm": float(np.median(trans) * 100) if len(trans) else 0.0,
                "median_step_deg": float(np.median(rot)) if len(rot) else 0.0,
            })
        train = "".join(f"sequence{i + 1}\n" for i in range(cfg.train_sequences))
        (tmp / "TrainSplit.txt").write_text(train)
        (tmp / "TestSplit.txt").write_text(f"sequence{cfg.train_sequences + 1}\n")
        (tmp / "intrinsics.yaml").write_text(
            "# pinhole intrinsics of the colour images (pixels; 7-Scenes RGB camera, scaled)\n"
            + yaml.safe_dump(intr.to_dict(), sort_keys=False))
        summary = {"out": str(out), "config": asdict(cfg), "intrinsics": intr.to_dict(),
                   "sequences": sequences}
        (tmp / "synth.json").write_text(json.dumps(summary, indent=2) + "\n")
        _replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    summary["seconds"] = time.perf_counter() - start
    log.info("wrote %d frames to %s in %.1f s", done, out, summary["seconds"])
    return summary


def _replace(tmp: Path, out: Path) -> None:
    """Move the finished ``tmp`` to ``out``, replacing what is there (checked beforehand)."""
    if out.is_dir() and not any(out.iterdir()):
        out.rmdir()
    if out.exists() or out.is_symlink():
        old = out.parent / f".{out.name}.old-{os.getpid()}"
        os.replace(out, old)
        os.replace(tmp, out)
        if old.is_dir() and not old.is_symlink():
            shutil.rmtree(old)
        else:
            old.unlink()
    else:
        os.replace(tmp, out)
