"""Two-frame relative-pose network: the bootstrap's source of relative motion early in training.

monodepth2's pose network: a ResNet18 encoder on the two frames stacked along channels, its pose
decoder (1x1 squeeze, two 3x3 convs with ReLU, 1x1 -> 6, spatial mean) and outputs scaled by 0.01,
so that at initialisation every relative pose is near the identity. Unlike the DSC network it sees
both frames and only has to regress ego-motion, which it learns in a few hundred steps; the
trainer uses it to warp while the DSC network is still memorising the scene (see ``BootstrapConfig``
in :mod:`relocdepth.method`). Not part of the paper's method; off unless asked for.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from relocdepth.geometry import pose_vector_to_matrix
from relocdepth.models.encoder import ResNet18Encoder
from relocdepth.models.pose import pose_decoder

# monodepth2 multiplies the decoder's mean output by 0.01: small first motions, well-scaled gradients.
OUTPUT_SCALE = 0.01


class RelPoseNet(nn.Module):
    """``forward(x_a, x_b (B, 3, H, W) in [0, 1])`` -> ``T_ab (B, 4, 4)``, the rigid transform that
    maps points in camera ``a`` into camera ``b`` (``relocdepth.geometry.relative_pose``'s ``T_t2s``
    with ``a = t``, ``b = s``): ``[R(axis-angle) | t]`` from the 6 outputs."""

    def __init__(self) -> None:
        super().__init__()
        self.encoder = ResNet18Encoder(num_images=2)
        self.head = pose_decoder(self.encoder.num_ch_enc[-1])

    def vector(self, x_a: Tensor, x_b: Tensor) -> Tensor:
        """``(B, 6)`` = ``[axis-angle, translation]`` of ``T_ab``."""
        return OUTPUT_SCALE * self.head(self.encoder(_stack(x_a, x_b))[-1]).mean(dim=(2, 3))

    def forward(self, x_a: Tensor, x_b: Tensor) -> Tensor:
        return pose_vector_to_matrix(self.vector(x_a, x_b))


def _stack(x_a: Tensor, x_b: Tensor) -> Tensor:
    """The two frames stacked along channels, ``(B, 6, H, W)``."""
    if x_a.shape != x_b.shape or x_a.ndim != 4 or x_a.shape[1] != 3:
        raise ValueError(f"RelPoseNet needs two (B, 3, H, W) images, got {tuple(x_a.shape)} and {tuple(x_b.shape)}")
    return torch.cat((x_a, x_b), dim=1)
