"""Camera paths of the generated scene, moving like handheld 7-Scenes video at 30 fps.

A smooth path (sums of low-frequency sinusoids) at a median 0.72 cm per frame whose heading turns
slowly (0.3 deg per frame), plus a bounded hand tremor (about 0.85 deg RMS, periods of a few
frames) that makes the per-frame rotation about 1.5 deg without adding up over longer gaps. The
test sequence follows the first training path offset by 18-26 cm with a slightly perturbed
orientation: near, but not on, the training paths.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from relocdepth.synth.config import SynthConfig, check_config


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
    return np.array([float(format_pose_value(v)) for v in T.ravel()]).reshape(T.shape)


def format_pose_value(v: float) -> str:
    return f"{v: .8e}"


def sequence_names(cfg: SynthConfig) -> list[str]:
    """``seq-01`` ... for the training sequences, then the test sequence."""
    return [f"seq-{i + 1:02d}" for i in range(cfg.train_sequences + 1)]


def camera_paths(cfg: SynthConfig) -> dict[str, np.ndarray]:
    """World-from-camera poses (frames, 4, 4) of every sequence, training ones first, the test
    sequence last. Depends only on the seed and the motion fields of ``cfg`` (not on the size);
    the speeds are calibrated over the first ``calibration_frames`` frames, so a sequence of
    fewer frames is a prefix of a longer one."""
    check_config(cfg)
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

