"""What `reloc synth` generates: :class:`SynthConfig` (sizes, motion, room) and the camera it
scales (the 7-Scenes RGB camera)."""

from __future__ import annotations

from dataclasses import dataclass

from relocdepth.camera import Intrinsics
from relocdepth.errors import UserError

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


def check_config(cfg: SynthConfig) -> None:
    if cfg.frames < 1:
        raise UserError(f"--frames must be a positive number of frames per sequence, got {cfg.frames}")
    if cfg.width < 16 or cfg.height < 16 or cfg.width % 2 or cfg.height % 2:
        raise UserError(f"--size must be even and at least 16x16 (the mp4 needs even sizes), "
                        f"got {cfg.width}x{cfg.height}")
    if cfg.train_sequences < 2:
        raise UserError(f"need at least 2 training sequences, got {cfg.train_sequences}")
    if cfg.fps <= 0 or cfg.step_m <= 0 or cfg.turn_deg <= 0 or cfg.tremor_deg < 0:
        raise UserError("fps, step_m and turn_deg must be positive, tremor_deg not negative")

