"""A generated indoor scene in the exact Microsoft 7-Scenes layout: the demo data, test fixture
and evaluation ground truth of the project.

A kitchen-sized textured room lined with furniture and cluttered with objects (:mod:`.scene`),
procedural textures evaluated at the 3-D hit point and prefiltered by the pixel footprint
(:mod:`.textures`), exact analytic ray casting in numpy, so depth and poses are exact
(:mod:`.render`), camera paths that move like handheld 7-Scenes video, tremor included
(:mod:`.paths`), and the 7-Scenes folder layout with videos (:mod:`.writer`); what is generated
is a :class:`SynthConfig` (:mod:`.config`). Everything is deterministic from the seed.
"""

from relocdepth.synth.config import SEVEN_SCENES_INTRINSICS, SynthConfig
from relocdepth.synth.paths import (
    camera_paths,
    motion_steps,
    pair_motion,
    rotation_from_angles,
    sequence_names,
)
from relocdepth.synth.render import cast_rays, pixel_rays, render, shade
from relocdepth.synth.scene import Box, Cylinder, Scene, Sphere, build_scene, clearance
from relocdepth.synth.writer import generate_scene, write_pose

__all__ = [
    "SEVEN_SCENES_INTRINSICS",
    "Box",
    "Cylinder",
    "Scene",
    "Sphere",
    "SynthConfig",
    "build_scene",
    "camera_paths",
    "cast_rays",
    "clearance",
    "generate_scene",
    "motion_steps",
    "pair_motion",
    "pixel_rays",
    "render",
    "rotation_from_angles",
    "sequence_names",
    "shade",
    "write_pose",
]
