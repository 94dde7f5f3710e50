"""ResNet18 encoder with torchvision's state-dict layout, and loading of ImageNet weights.

torchvision is not a dependency, so the network is written out here; its parameter names
(``conv1``, ``bn1``, ``layer1.0.conv1`` ... ``layer4.1.bn2``) match ``torchvision.models.resnet18``
so the official weights load unchanged (``fc.*`` is ignored: the encoder stops at ``layer4``).
"""

from __future__ import annotations

import hashlib
import logging
import re
from pathlib import Path

import torch
from torch import Tensor, nn

from relocdepth.errors import UserError
from relocdepth.geometry import check_image_size

log = logging.getLogger(__name__)

# The official torchvision ResNet18 ImageNet weights; the 8 hex digits in the name are the prefix of
# the file's sha256 (torch.hub's check_hash convention).
IMAGENET_URL = "https://download.pytorch.org/models/resnet18-f37072fd.pth"
# Channels of the 5 feature maps (1/2, 1/4, 1/8, 1/16, 1/32 of the input), as monodepth2.
NUM_CH_ENC = (64, 64, 128, 256, 512)
# monodepth2 normalises [0, 1] inputs by (x - 0.45) / 0.225 before the encoder.
INPUT_MEAN = 0.45
INPUT_STD = 0.225


class BasicBlock(nn.Module):
    """torchvision's ResNet basic block (two 3x3 convs, identity or 1x1 downsample shortcut)."""

    def __init__(self, cin: int, cout: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.downsample: nn.Module | None = None
        if stride != 1 or cin != cout:
            self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x: Tensor) -> Tensor:
        idt = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + idt)


class ResNet18Encoder(nn.Module):
    """ResNet18 up to ``layer4``; forward returns the 5 feature maps monodepth2's decoder uses.

    ``forward(x (B, 3, H, W) in [0, 1])`` -> ``[f1 (B,64,H/2,W/2), f2 (B,64,H/4,W/4),
    f3 (B,128,H/8,W/8), f4 (B,256,H/16,W/16), f5 (B,512,H/32,W/32)]``; H and W multiples of 32.
    """

    num_ch_enc = NUM_CH_ENC

    def __init__(self, num_images: int = 1) -> None:
        super().__init__()
        # num_images > 1: the images are stacked along channels (monodepth2's two-frame pose encoder).
        self.in_channels = 3 * num_images
        self.conv1 = nn.Conv2d(self.in_channels, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        self.layer1 = nn.Sequential(BasicBlock(64, 64), BasicBlock(64, 64))
        self.layer2 = nn.Sequential(BasicBlock(64, 128, 2), BasicBlock(128, 128))
        self.layer3 = nn.Sequential(BasicBlock(128, 256, 2), BasicBlock(256, 256))
        self.layer4 = nn.Sequential(BasicBlock(256, 512, 2), BasicBlock(512, 512))
        # torchvision's initialisation (kaiming normal fan_out for convs, BN weight 1 bias 0).
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, x: Tensor) -> list[Tensor]:
        if x.ndim != 4 or x.shape[1] != self.in_channels:
            raise ValueError(f"encoder input must be (B, {self.in_channels}, H, W), got {tuple(x.shape)}")
        check_image_size(x.shape[-2], x.shape[-1])
        f1 = self.relu(self.bn1(self.conv1((x - INPUT_MEAN) / INPUT_STD)))
        f2 = self.layer1(self.maxpool(f1))
        f3 = self.layer2(f2)
        f4 = self.layer3(f3)
        f5 = self.layer4(f4)
        return [f1, f2, f3, f4, f5]

    def load_imagenet_weights(self, path_or_imagenet: str | Path) -> str:
        """Load torchvision-format ResNet18 weights; returns a one-line description of the source.

        ``"imagenet"``: the official file (torch.hub cache, else downloaded from
        :data:`IMAGENET_URL`, sha256 prefix checked). Anything else: a local ``.pth`` state dict.
        Raises :class:`UserError` for a missing, unreadable or non-ResNet18 file.
        """
        state = read_imagenet_state_dict(path_or_imagenet)
        load_torchvision_state_dict(self, state, source=str(path_or_imagenet))
        return f"ImageNet ResNet18 weights from {path_or_imagenet}"


def _hash_prefix(name: str) -> str | None:
    m = re.search(r"-([a-f0-9]{8,})\.", name)
    return m.group(1) if m else None


def read_imagenet_state_dict(path_or_imagenet: str | Path) -> dict[str, Tensor]:
    """Read a torchvision ResNet18 state dict from a local file or ``"imagenet"`` (official URL)."""
    if str(path_or_imagenet) == "imagenet":
        try:
            return torch.hub.load_state_dict_from_url(
                IMAGENET_URL, map_location="cpu", check_hash=True, progress=False
            )
        except RuntimeError as e:  # torch.hub raises RuntimeError on a hash mismatch
            raise UserError(f"the downloaded ImageNet weights failed their checksum ({e}); delete the "
                            "file in the torch hub cache and retry") from e
        # network errors (URLError, OSError) propagate to build_networks, which falls back
    path = Path(path_or_imagenet)
    if not path.is_file():
        raise UserError(f"pretrained weights file {path} does not exist; give a torchvision resnet18 "
                        f".pth file, 'imagenet' to download it, or none for random initialisation")
    prefix = _hash_prefix(path.name)
    if prefix is not None:
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        if not digest.startswith(prefix):
            raise UserError(f"{path} does not match the checksum prefix {prefix} in its name "
                            f"(sha256 {digest[:12]}...); the file is corrupt or not the official one")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # any unreadable file is the user's to fix
        raise UserError(f"cannot read {path} as a PyTorch state dict ({type(e).__name__}: {e}); "
                        "give a torchvision resnet18 .pth file") from e
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise UserError(f"{path} holds a {type(state).__name__}, not a state dict of a torchvision resnet18")
    return state


def load_torchvision_state_dict(encoder: nn.Module, state: dict[str, Tensor], source: str) -> None:
    """Copy a torchvision ResNet18 state dict into ``encoder`` (``fc.*`` ignored); UserError naming
    the first missing key or wrong shape otherwise."""
    own = encoder.state_dict()
    n_img = own["conv1.weight"].shape[1] // 3 if "conv1.weight" in own else 1
    if n_img > 1 and isinstance(state.get("conv1.weight"), Tensor) and state["conv1.weight"].shape[1] == 3:
        # monodepth2's multi-image encoder: the RGB filters repeated per image, divided by their count
        state = {**state, "conv1.weight": state["conv1.weight"].repeat(1, n_img, 1, 1) / n_img}
    missing = [k for k in own if k not in state]
    if missing:
        raise UserError(f"{source} is not a torchvision resnet18 state dict: {len(missing)} keys missing "
                        f"(first: {missing[0]!r})")
    for k, v in own.items():
        if not isinstance(state[k], Tensor) or tuple(state[k].shape) != tuple(v.shape):
            got = tuple(state[k].shape) if isinstance(state[k], Tensor) else type(state[k]).__name__
            raise UserError(f"{source} is not a torchvision resnet18 state dict: {k!r} has shape "
                            f"{got}, expected {tuple(v.shape)}")
    encoder.load_state_dict({k: state[k] for k in own}, strict=True)
