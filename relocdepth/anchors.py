"""Absolute anchors for the DSC network from the training frames' own odometry (not in the paper).

The bootstrap teaches the DSC network relative poses; what it must learn is where each image was
taken, in one world. Once the depth network has learned (the bootstrap's warps teach it in a few
hundred steps), keyframe odometry over each training sequence with that depth, and registration
of the sequences into the first one's world (:mod:`relocdepth.vo`), give every training frame a
world pose without ground truth; the trainer pulls each DSC cell's pose towards it
(:class:`relocdepth.method.Bootstrap`, ``L_anchor``). The world is the first training sequence's
first frame, in the depth network's units at the time of the build.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from relocdepth.data import ImageFrames, scale_and_crop
from relocdepth.models import disp_to_depth
from relocdepth.vo import VOConfig, world_trajectory


@dataclass
class Anchors:
    """``T_wc (N, 4, 4)`` float32: a world pose per training frame (``ImageFrames`` order), and what
    the build found: keyframes, frames whose pose could not be measured, registration inliers per
    sequence after the first (out of links), seconds."""

    T_wc: np.ndarray
    keyframes: int
    lost: int
    registration: list[tuple[int, int]]
    seconds: float


def sequences_of(frames: ImageFrames) -> list[list[int]]:
    """Indices of ``frames`` per sequence, in frame order; the sequences in order of first appearance."""
    by_seq: dict[str, list[int]] = {}
    for i, f in enumerate(frames.frames):
        by_seq.setdefault(f.sequence, []).append(i)
    return [sorted(ix, key=lambda i: frames.frames[i].frame) for ix in by_seq.values()]


@torch.no_grad()
def network_depth(depth_net: Any, images: list[np.ndarray], device: Any, min_depth: float, max_depth: float,
                  batch: int = 16) -> list[np.ndarray]:
    """Depth maps ``(H, W)`` float32 of RGB uint8 ``images`` from ``depth_net`` (eval mode while it runs)."""
    was_training = depth_net.training
    depth_net.eval()
    out = []
    try:
        for i in range(0, len(images), batch):
            x = torch.from_numpy(np.stack(images[i:i + batch])).permute(0, 3, 1, 2).to(device).float() / 255.0
            d = disp_to_depth(depth_net(x)[0].float(), min_depth, max_depth)
            out += list(d[:, 0].cpu().numpy())
    finally:
        depth_net.train(was_training)
    return out


# Depth maps (H, W) of frames: given their indices and their images at the anchors' size.
DepthOf = Callable[[list[int], list[np.ndarray]], list[np.ndarray]]


def build_anchors(frames: ImageFrames, depth: DepthOf, size: tuple[int, int],
                  cfg: VOConfig | None = None) -> Anchors:
    """World poses of every training frame from odometry at ``size`` (W, H: images resized, as the
    trainer's un-augmented input) with ``depth``'s maps (in the trainer: the depth network's,
    :func:`network_depth`)."""
    t0 = time.perf_counter()
    W, H = size
    seqs = sequences_of(frames)
    images, Ks = [], []
    for ix in seqs:
        pairs = [scale_and_crop(frames.read_image(i), frames.frames[i].intrinsics, W, H, 1.0, 0.0, 0.0) for i in ix]
        images.append([p[0] for p in pairs])
        Ks.append(pairs[0][1].K())
    depths = [depth(ix, im) for ix, im in zip(seqs, images)]
    w = world_trajectory(images, Ks, [d.__getitem__ for d in depths], cfg or VOConfig())
    T = np.repeat(np.eye(4, dtype=np.float32)[None], len(frames), axis=0)
    for ix, T_seq in zip(seqs, w.world):
        T[ix] = T_seq.astype(np.float32)
    return Anchors(T, sum(len(t.keyframes) for t in w.trajs), sum(len(t.lost) for t in w.trajs),
                   [(r.inliers, r.links) for r in w.regs], time.perf_counter() - t0)
