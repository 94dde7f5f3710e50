"""Networks of the method: depth (ResNet18 + monodepth2 decoder), DSC, and the ``w/o DSC`` pose head."""

from __future__ import annotations

import logging
from dataclasses import dataclass

from torch import nn

from relocdepth.models.depth import DepthNet, disp_to_depth
from relocdepth.models.dsc import DSCNet
from relocdepth.models.encoder import ResNet18Encoder
from relocdepth.models.pose import AbsPoseNet
from relocdepth.models.relpose import RelPoseNet

log = logging.getLogger(__name__)

__all__ = [
    "AbsPoseNet",
    "DSCNet",
    "DepthNet",
    "ModelConfig",
    "Networks",
    "RelPoseNet",
    "ResNet18Encoder",
    "build_networks",
    "disp_to_depth",
]


@dataclass(frozen=True)
class ModelConfig:
    """Network options. Paper Sec. III-D: ImageNet-pretrained ResNet18 encoders, depth in [0.1, 100]."""

    pretrained: str | None = None  # None: random init; "imagenet": official URL; else a local .pth file
    use_dsc: bool = True  # False: the paper's "w/o DSC" ablation (absolute-pose head)
    relpose: bool = False  # a two-frame relative-pose network for the training bootstrap (not the paper's)
    # Paper Sec. IV-B: batch normalisation "for all the layers except for the output layers"; the
    # monodepth2 depth decoder has none, so off by default (checkpoints without it load unchanged).
    decoder_bn: bool = False
    min_depth: float = 0.1
    max_depth: float = 100.0


class Networks(nn.Module):
    """The trained networks: ``.depth`` (:class:`DepthNet`) and ``.dsc`` (:class:`DSCNet`), or
    ``.pose`` (:class:`AbsPoseNet`) instead of ``.dsc`` when ``cfg.use_dsc`` is False; plus
    ``.relpose`` (:class:`RelPoseNet`, training only) when ``cfg.relpose`` is True."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.depth = DepthNet(decoder_bn=cfg.decoder_bn)
        if cfg.use_dsc:
            self.dsc = DSCNet()
        else:
            self.pose = AbsPoseNet()
        if cfg.relpose:
            self.relpose = RelPoseNet()

    @property
    def pose_net(self) -> nn.Module:
        """The absolute-pose network in use (DSC or the ablation's pose head)."""
        return self.dsc if self.cfg.use_dsc else self.pose


def build_networks(cfg: ModelConfig) -> Networks:
    """Build the networks and initialise their encoders as ``cfg.pretrained`` says, logging which.

    A missing/unreadable/wrong local file is a :class:`~relocdepth.errors.UserError`; when
    ``"imagenet"`` cannot be downloaded (offline) the encoders stay randomly initialised, with a
    warning in the log.
    """
    nets = Networks(cfg)
    encoders = [nets.depth.encoder, nets.pose_net.encoder]
    if cfg.relpose:
        encoders.append(nets.relpose.encoder)
    if cfg.pretrained is None:
        log.info("encoders randomly initialised (no pretrained weights asked for)")
        return nets
    from relocdepth.models.encoder import load_torchvision_state_dict, read_imagenet_state_dict

    try:
        state = read_imagenet_state_dict(cfg.pretrained)
    except OSError as e:  # offline: urllib's URLError is an OSError
        log.warning("could not fetch ImageNet weights (%s); encoders are RANDOMLY initialised", e)
        return nets
    for enc in encoders:
        load_torchvision_state_dict(enc, state, source=str(cfg.pretrained))
    log.info("encoders initialised from ImageNet ResNet18 weights (%s)", cfg.pretrained)
    return nets
