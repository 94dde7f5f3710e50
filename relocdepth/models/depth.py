"""Depth network: ResNet18 encoder + monodepth2's U-Net decoder (4 sigmoid disparity scales)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from relocdepth.models.encoder import ResNet18Encoder

# monodepth2's decoder widths, from the 1/1 to the 1/16 level.
NUM_CH_DEC = (16, 32, 64, 128, 256)
NUM_SCALES = 4


class ConvBlock(nn.Module):
    """3x3 conv with reflection padding + ELU (monodepth2's ``ConvBlock``); with ``bn``, batch
    normalisation between them (paper Sec. IV-B) and no conv bias (BN's shift replaces it).
    Without ``bn`` the block has monodepth2's parameters and state-dict keys exactly."""

    def __init__(self, cin: int, cout: int, bn: bool = False) -> None:
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, 3, padding=1, padding_mode="reflect", bias=not bn)
        self.norm: nn.Module = nn.BatchNorm2d(cout) if bn else nn.Identity()
        self.act = nn.ELU(inplace=True)

    def forward(self, x: Tensor) -> Tensor:
        return self.act(self.norm(self.conv(x)))


class DepthDecoder(nn.Module):
    """monodepth2 decoder: upconv (ConvBlock, nearest x2, skip concat, ConvBlock) per level.

    ``forward(features)`` (the 5 encoder maps) -> 4 sigmoid disparity maps, scale 0 first:
    ``(B, 1, H, W)``, ``(B, 1, H/2, W/2)``, ``(B, 1, H/4, W/4)``, ``(B, 1, H/8, W/8)``.
    ``bn``: batch normalisation in every upconv block (not in the disparity outputs).
    """

    def __init__(self, num_ch_enc: tuple[int, ...], num_scales: int = NUM_SCALES, bn: bool = False) -> None:
        super().__init__()
        self.num_scales = num_scales
        self.upconv0 = nn.ModuleList()
        self.upconv1 = nn.ModuleList()
        for i in range(4, -1, -1):  # index k = 4 - i
            cin = num_ch_enc[-1] if i == 4 else NUM_CH_DEC[i + 1]
            self.upconv0.append(ConvBlock(cin, NUM_CH_DEC[i], bn))
            cin = NUM_CH_DEC[i] + (num_ch_enc[i - 1] if i > 0 else 0)
            self.upconv1.append(ConvBlock(cin, NUM_CH_DEC[i], bn))
        self.dispconv = nn.ModuleList(
            nn.Conv2d(NUM_CH_DEC[s], 1, 3, padding=1, padding_mode="reflect") for s in range(num_scales)
        )

    def forward(self, features: list[Tensor]) -> list[Tensor]:
        x = features[-1]
        out: list[Tensor | None] = [None] * self.num_scales
        for k, i in enumerate(range(4, -1, -1)):
            x = F.interpolate(self.upconv0[k](x), scale_factor=2, mode="nearest")
            if i > 0:
                x = torch.cat((x, features[i - 1]), dim=1)
            x = self.upconv1[k](x)
            if i < self.num_scales:
                out[i] = torch.sigmoid(self.dispconv[i](x))
        return out  # type: ignore[return-value]


class DepthNet(nn.Module):
    """Encoder + decoder. ``forward(x (B, 3, H, W) in [0, 1])`` -> list of 4 sigmoid disparities,
    scale 0 (full resolution) first; :func:`disp_to_depth` turns them into depth.
    ``decoder_bn``: batch normalisation in the decoder (see :class:`DepthDecoder`)."""

    def __init__(self, num_scales: int = NUM_SCALES, decoder_bn: bool = False) -> None:
        super().__init__()
        self.encoder = ResNet18Encoder()
        self.decoder = DepthDecoder(self.encoder.num_ch_enc, num_scales, bn=decoder_bn)

    def forward(self, x: Tensor) -> list[Tensor]:
        return self.decoder(self.encoder(x))


def disp_to_depth(sigma: Tensor, min_depth: float = 0.1, max_depth: float = 100.0) -> Tensor:
    """Sigmoid output -> depth ``1 / (a sigma + b)`` in ``[min_depth, max_depth]`` (monodepth2):
    ``b = 1 / max_depth``, ``a = 1 / min_depth - 1 / max_depth``. Any shape."""
    b = 1.0 / max_depth
    a = 1.0 / min_depth - b
    return 1.0 / (a * sigma + b)
