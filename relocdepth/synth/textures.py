"""Procedural textures of the generated scene: per-face parameters drawn while the scene is built,
and their colour at 3-D points, prefiltered analytically by the pixel footprint.

Texture of face f at world point p (colour in [0, 1] before shading):
``base[f] + sum_k weight[f, k] * term_k(2 pi freq[f, k] . p + phase[f, k])`` where the first
``n_smooth`` terms are sinusoids and the rest soft-edged stripes ``tanh(g sin(.))``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from relocdepth.synth.scene import Scene

N_SMOOTH = 12          # sinusoids per face, wavelengths log-spaced over WAVELENGTHS
N_EDGE = 4             # soft-edged stripe terms per face, wavelengths over EDGE_WAVELENGTHS
WAVELENGTHS = (0.03, 1.2)
EDGE_WAVELENGTHS = (0.08, 0.45)
EDGE_SHARPNESS = 8.0   # tanh gain of the stripes when the pixel footprint is negligible


class FaceTextures:
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


def room_faces(faces: FaceTextures, rng: np.random.Generator) -> None:
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


def box_faces(faces: FaceTextures, yaw: float) -> int:
    base = faces.palette()
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    first = -1
    for axis in range(3):
        for side in (-1.0, 1.0):
            f = faces.add(base * faces.rng.uniform(0.85, 1.15), rot[:, axis] * side)
            first = f if first < 0 else first
    return first


def texture(scene: Scene, f: int, p: np.ndarray, footprint: np.ndarray) -> np.ndarray:
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

