"""Single-image absolute-pose regression head, for the paper's ``w/o DSC`` ablation.

monodepth2's pose decoder (1x1 squeeze, two 3x3 convs with ReLU, 3x3 -> 6, spatial mean), fed with
one image instead of two, so it regresses an absolute pose; relative poses then come from two of them.
"""

from __future__ import annotations

from torch import Tensor, nn

from relocdepth.models.encoder import ResNet18Encoder

HEAD_CHANNELS = 256
# Small initial outputs: every image starts near the identity pose (see dsc.OUTPUT_INIT_STD).
OUTPUT_INIT_STD = 1e-3


def pose_decoder(cin: int) -> nn.Sequential:
    """monodepth2's pose decoder: 1x1 squeeze, two 3x3 convs with ReLU, 1x1 -> 6 (its caller takes
    the spatial mean). ``(B, cin, h, w)`` -> ``(B, 6, h, w)``."""
    return nn.Sequential(
        nn.Conv2d(cin, HEAD_CHANNELS, 1),
        nn.ReLU(inplace=True),
        nn.Conv2d(HEAD_CHANNELS, HEAD_CHANNELS, 3, padding=1),
        nn.ReLU(inplace=True),
        nn.Conv2d(HEAD_CHANNELS, HEAD_CHANNELS, 3, padding=1),
        nn.ReLU(inplace=True),
        nn.Conv2d(HEAD_CHANNELS, 6, 1),
    )


class AbsPoseNet(nn.Module):
    """``forward(x (B, 3, H, W) in [0, 1])`` -> ``(B, 6)`` = ``[axis-angle of R_wc, camera centre]``."""

    def __init__(self) -> None:
        super().__init__()
        self.encoder = ResNet18Encoder()
        self.head = pose_decoder(self.encoder.num_ch_enc[-1])
        nn.init.normal_(self.head[-1].weight, std=OUTPUT_INIT_STD)
        nn.init.zeros_(self.head[-1].bias)

    def forward(self, x: Tensor) -> Tensor:
        return self.head(self.encoder(x)[-1]).mean(dim=(2, 3))
