"""Geometry of the method in torch: DSC + depth -> camera pose, and view synthesis.

Conventions (DESIGN.md): a pose is a 4x4 world-from-camera matrix ``T_wc`` with OpenCV camera axes
(x right, y down, z forward); pixel centres sit at integer coordinates; quaternions are
``(w, x, y, z)`` as in kornia. All functions are pure, batched, and follow the device and dtype of
their inputs. Evaluation geometry (Sim(3) alignment, errors, TUM quaternions) is numpy, in
:mod:`relocdepth.eval_geometry`.

Where each part of the paper lives (submodules of this package):

- ``rotations`` (III-A): SO(3) exp/log, quaternions, the ray rotation ``R_p``;
- ``dsc`` (III-A): DSC ``[theta, tau]`` <-> per-cell poses ``P(p)``; ``P`` = their mean
  (training) or median (test); their spread (confidence);
- ``poses``: ``T(P)``, inverse, pose errors;
- ``intrinsics`` (III-B): ``K`` after a resize, back-projection ``D K^-1 p``;
- ``warp`` (III-B): ``T_{t->s} = T(P_s)^-1 T(P_t)`` and the warp ``K_s T_{t->s} D_t K_t^-1 p`` (and,
  not the paper's, the disagreement of two frames' depths under it);
- ``lcvs`` (III-C): loop-closed view synthesis, the pairs of a triplet that are warped.
"""

from relocdepth.geometry.dsc import (
    DSC_STRIDE,
    cell_pose_spread,
    cell_poses,
    cell_rays,
    check_image_size,
    dsc_cell_centres,
    dsc_from_pose,
    dsc_grid_size,
    mean_cell_pose,
    median_cell_pose,
    pool_depth,
)
from relocdepth.geometry.intrinsics import backproject, scale_intrinsics
from relocdepth.geometry.lcvs import PAIRS_LCVS, PAIRS_MIDDLE
from relocdepth.geometry.poses import invert_pose, pose_errors, pose_matrix, pose_vector_to_matrix
from relocdepth.geometry.rotations import (
    minimal_rotation_quat,
    quat_angle,
    quat_conj,
    quat_from_matrix,
    quat_log,
    quat_mul,
    quat_to_matrix,
    so3_exp,
    so3_log,
)
from relocdepth.geometry.warp import MIN_WARP_DEPTH, depth_disagreement, moved_view, relative_pose, warp

__all__ = [
    "DSC_STRIDE",
    "MIN_WARP_DEPTH",
    "PAIRS_LCVS",
    "PAIRS_MIDDLE",
    "backproject",
    "cell_pose_spread",
    "cell_poses",
    "cell_rays",
    "check_image_size",
    "depth_disagreement",
    "dsc_cell_centres",
    "dsc_from_pose",
    "dsc_grid_size",
    "invert_pose",
    "mean_cell_pose",
    "median_cell_pose",
    "minimal_rotation_quat",
    "pool_depth",
    "pose_errors",
    "pose_matrix",
    "pose_vector_to_matrix",
    "quat_angle",
    "quat_conj",
    "quat_from_matrix",
    "quat_log",
    "quat_mul",
    "quat_to_matrix",
    "moved_view",
    "relative_pose",
    "scale_intrinsics",
    "so3_exp",
    "so3_log",
    "warp",
]
