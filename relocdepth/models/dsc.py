"""Directed scene coordinate network: ResNet18 encoder + 3 conv layers -> 6 channels at 1/32."""

from __future__ import annotations

from torch import Tensor, nn

from relocdepth.models.encoder import ResNet18Encoder

# Width of the two hidden layers of the head (the paper gives only "three CNN layers with ReLU").
HEAD_CHANNELS = 256
# Std of the output layer's initial weights: the first DSCs are small (G ~ I, tau ~ 0), so every
# cell's camera starts finite near the origin looking along its own ray (R_wc = R_p^T, c = -|Q| e_z),
# with a mean pose near identity; a default init gives tau of tens of units and random rotations.
OUTPUT_INIT_STD = 1e-3


class DSCHead(nn.Module):
    """conv3x3+BN+ReLU, conv3x3+BN+ReLU, conv1x1 -> 6 (no BN/activation on the output layer, as the
    paper uses BN everywhere but output layers). ``(B, 512, h, w)`` -> ``(B, 6, h, w)``."""

    def __init__(self, cin: int = 512, ch: int = HEAD_CHANNELS) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(cin, ch, 3, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(ch)
        self.conv2 = nn.Conv2d(ch, ch, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(ch)
        self.out = nn.Conv2d(ch, 6, 1)
        self.relu = nn.ReLU(inplace=True)
        nn.init.normal_(self.out.weight, std=OUTPUT_INIT_STD)
        nn.init.zeros_(self.out.bias)

    def forward(self, x: Tensor) -> Tensor:
        x = self.relu(self.bn1(self.conv1(x)))
        x = self.relu(self.bn2(self.conv2(x)))
        return self.out(x)


class DSCNet(nn.Module):
    """``forward(x (B, 3, H, W) in [0, 1])`` -> DSC ``(B, 6, H/32, W/32)`` = ``[theta, tau]`` per cell."""

    def __init__(self) -> None:
        super().__init__()
        self.encoder = ResNet18Encoder()
        self.head = DSCHead(self.encoder.num_ch_enc[-1])

    def forward(self, x: Tensor) -> Tensor:
        return self.head(self.encoder(x)[-1])
