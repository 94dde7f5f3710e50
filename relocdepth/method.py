"""The method: loop-closed view synthesis on a triplet (training loss) and single-image prediction.

``triplet_loss`` is the whole forward pass of one training step (paper Sec. III): depth and DSC
of the three frames, per-cell poses averaged to one pose per frame, relative poses, view synthesis
over the pairs, and ``L = L_p + w_s L_s + w_c L_c``. ``predict`` is the test-time path (median
aggregation, Sec. IV-C).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from relocdepth import geometry as geo
from relocdepth.geometry.lcvs import PAIRS_LCVS, PAIRS_MIDDLE
from relocdepth.losses import (
    photometric_loss,
    pose_coordinate_loss,
    relative_pose_consistency,
    smoothness_loss,
    translation_direction_angle,
)
from relocdepth.models import Networks, disp_to_depth

# Confidence = 1 / (1 + rot_spread / CONF_ROT_DEG + centre_spread / (CONF_TRANS_REL * median depth)):
# a monotone score from the agreement of the per-cell poses, not a calibrated probability.
CONF_ROT_DEG = 5.0
CONF_TRANS_REL = 0.05

__all__ = ["LOSS_RESOLUTIONS", "PAIRS_LCVS", "PAIRS_MIDDLE", "PHOTOMETRIC_PIXELS", "Bootstrap", "MethodConfig",
           "bootstrap_poses", "novel_view_loss", "pairs_for", "predict", "preview", "triplet_loss", "two_view_poses"]

# The pixel sets L_p can average over (MethodConfig.photometric_pixels).
PHOTOMETRIC_PIXELS = ("valid", "all")
# Where each scale's L_p is computed (MethodConfig.loss_resolution).
LOSS_RESOLUTIONS = ("input", "decoder")


@dataclass(frozen=True)
class MethodConfig:
    """Loss options; defaults are the paper's (Sec. III-B, IV-B)."""

    lcvs: bool = True  # loop-closed view synthesis: all 6 ordered pairs (False: 2 pairs into the middle)
    use_dsc: bool = True  # False: "w/o DSC" ablation, absolute pose from a regression head
    alpha: float = 0.85  # SSIM weight in L_p (monodepth2)
    w_s: float = 0.001  # smoothness weight
    w_c: float = 0.03  # pose-coordinate weight
    # Weight of L_g, the disagreement of each warped pair's depths (the target's depth carried into
    # the source against the source's own, at full resolution; relocdepth.geometry.depth_disagreement):
    # not the paper's (SC-SfMLearner's geometry consistency). It ties the frames' depth scales to
    # each other directly, where L_p ties them only through the parallax they explain. 0: off.
    w_depth_consistency: float = 0.0
    num_scales: int = 4  # decoder scales used in the loss
    # Pixels L_p averages over: "valid" (in the source image, positive depth; DESIGN.md) or "all"
    # (monodepth2: border-padded samples count too). "valid" can be gamed by warping off-image
    # (depth collapses to the minimum, the valid fraction falls; seen at 640x480 on a GPU).
    photometric_pixels: str = "valid"
    # Recompute each scale's warps and SSIM in the backward pass instead of keeping them
    # (torch.utils.checkpoint): same gradients, a fraction of the loss's activation memory (the
    # paper's 640x480 batch of 6 triplets needs more than 21 GB on CPU without it), ~10-20 % more time.
    recompute_warps: bool = False
    # Resolution of each scale's warp and L_p: "input" (monodepth2: the scale's disparity upsampled
    # to the input size) or "decoder" (paper Sec. III-B: "at the resolution of each decoder's
    # layer": images area-downsampled and K scaled to the scale's own size; the default: it learned
    # as well as "input" at equal steps in the measured rows and its steps take 0.64-0.69x the time).
    loss_resolution: str = "decoder"
    # Weight of L_nv (not the paper's): each triplet's middle frame seen from a camera moved back
    # along its optical axis by up to ``novel_view_back`` times its median depth, synthesised from its
    # image and the network's depth (:func:`relocdepth.geometry.moved_view`); the depth network is
    # held to that view's depth and the DSC network's pose of it to the frame's own pose moved back
    # (both detached): views farther from the scene than any training frame, which the networks
    # otherwise place at the training frames' distances. 0: off.
    w_novel_view: float = 0.0
    novel_view_back: float = 0.2
    # With w_novel_view: the most the new views move forward instead, as a fraction of the median
    # depth (the move drawn uniformly from [-novel_view_forward, novel_view_back]); 0: back only.
    novel_view_forward: float = 0.0
    # With w_novel_view: whether L_nv also holds the DSC network's pose of the new view (L_nv_pose);
    # False: the depth network's term alone (L_nv_depth), which needs no DSC network.
    novel_view_pose: bool = True
    # With w_novel_view: L_nv_depth teaches the new view from the frame and not the frame from it:
    # the frame's depth takes the term's gradient only through its scale (its mean log over the
    # pixels the new view shows), which keeps the term unchanged by a scale of all depths, and not
    # through its shape, which the paper's terms alone then teach. False: through both.
    novel_view_one_way: bool = False
    # With w_novel_view: the new views teach the depth network's decoder alone (its encoder runs on
    # them without gradient), so that the encoder's features of real images are shaped by real
    # images only. False: both.
    novel_view_decoder_only: bool = False
    # With w_novel_view: the term in the first N training steps only (the trainer leaves it out from
    # step N on); 0: in every step.
    novel_view_steps: int = 0
    min_depth: float = 0.1
    max_depth: float = 100.0

    def __post_init__(self) -> None:
        if self.photometric_pixels not in PHOTOMETRIC_PIXELS:
            raise ValueError(f"photometric_pixels must be one of {PHOTOMETRIC_PIXELS}, not {self.photometric_pixels!r}")
        if self.loss_resolution not in LOSS_RESOLUTIONS:
            raise ValueError(f"loss_resolution must be one of {LOSS_RESOLUTIONS}, not {self.loss_resolution!r}")
        if not self.w_depth_consistency >= 0:
            raise ValueError(f"w_depth_consistency must be >= 0, not {self.w_depth_consistency}")
        if not self.w_novel_view >= 0:
            raise ValueError(f"w_novel_view must be >= 0, not {self.w_novel_view}")
        if self.w_novel_view > 0 and self.novel_view_pose and not self.use_dsc:
            raise ValueError("w_novel_view needs the DSC network (it holds the DSC's pose of the new view; "
                             "novel_view_pose False does without)")
        if self.novel_view_steps < 0:
            raise ValueError(f"novel_view_steps must be >= 0, not {self.novel_view_steps}")
        if not 0 < self.novel_view_back <= 1:
            raise ValueError(f"novel_view_back must be in (0, 1], not {self.novel_view_back}")
        if not 0 <= self.novel_view_forward <= 0.5:
            raise ValueError(f"novel_view_forward must be in [0, 0.5], not {self.novel_view_forward}")


@dataclass(frozen=True)
class Bootstrap:
    """This step's relative-pose bootstrap (not the paper's; see ``TrainConfig.bootstrap``).

    Early in training the DSC network cannot yet tell where an image was taken, so the relative
    poses it implies are wrong, the warps are wrong, and depth cannot learn (nor, without depth,
    the DSC). The bootstrap takes the triplet's poses from another source for the warps, so depth
    learns first, and teaches the DSC network those relative poses through a consistency term;
    then the warps switch to the DSC poses (the paper's loss) while the term fades out.

    ``warps``: the warps use the bootstrap poses (else the DSC's). ``w_consistency``: weight of
    ``L_boot`` (0: not computed). The source, first match wins: ``T_wc`` ``(B, 3, 4, 4)``, poses of
    the triplet's frames given from outside (the research oracle: ground truth); ``two_view``, the
    essential-matrix poses of the pairs middle -> source ``(T (B, 2, 4, 4) with unit translations,
    points (B, 2, N, 3), ok (B, 2))`` from :func:`relocdepth.twoview.bootstrap_pair`, their
    translations scaled by the current depth; else ``nets.relpose``.

    ``T_anchor`` ``(B, 3, 4, 4)``: world poses of the triplet's frames from the training frames'
    own odometry (:mod:`relocdepth.vo`, in the depth network's units), which every DSC cell's pose
    is pulled towards with weight ``w_anchor`` (``L_anchor``): absolute targets, where ``L_boot``
    teaches relative poses only.

    ``w_direction``: weight (times ``w_consistency``) of ``L_dir``, the angle (radians) between the
    DSC's and the bootstrap's translation directions of the pairs whose translation the bootstrap
    measured, each times its baseline (the smaller of the two) over the scene's depth, averaged over
    those pairs; it moves the camera centres only (the orientations, and the DSC's ray rotations
    that the centres depend on, detached). ``L_boot``
    counts a translation by the image motion it causes, so a pair 7 cm apart in a room 1.7 m deep
    weighs a 15 deg error of its direction like a 0.6 deg rotation; ``L_dir`` is that error's
    direction part alone, which ``w_direction`` can weigh up without also weighing up the length
    (which the bootstrap takes from the current depth). The direction is what keeps the cameras'
    orientations and positions in one world (README, trial 18).

    ``depth_ref`` ``(B, 3)``: each frame's mean log depth when the anchors were first built, which
    the batch's mean log depth is held to with weight ``w_depth_scale`` (``L_scale``, the square of
    the mean difference, ``scale_drift``): every other term leaves the depth's scale free (the
    bootstrap's translations take their length from the depth, the novel views' ratios are scale
    free), and the anchors are rebuilt in whatever units it has drifted to. Only the batch's mean
    is held, so the term moves nothing but the one scale of all depths.
    """

    warps: bool
    w_consistency: float
    T_wc: Tensor | None = None
    two_view: tuple[Tensor, Tensor, Tensor] | None = None
    T_anchor: Tensor | None = None
    w_anchor: float = 0.0
    w_direction: float = 0.0
    depth_ref: Tensor | None = None
    w_depth_scale: float = 0.0

    @property
    def active(self) -> bool:
        return self.warps or self.w_consistency > 0

    @property
    def anchored(self) -> bool:
        return self.T_anchor is not None and self.w_anchor > 0


def bootstrap_poses(nets: Networks, inputs: Tensor, T_wc: Tensor | None = None) -> Tensor:
    """The triplet's poses ``(B, 3, 4, 4)`` in the middle camera's frame (frame 1 = identity).

    From ``T_wc`` (any world frame) when given, else from the two-frame network on the jittered
    ``inputs (B, 3, 3, H, W)``: ``T_wc(i) = T_{1->i}^-1`` with ``T_{1->i} = relpose(I_1, I_i)``.
    """
    if T_wc is not None:
        return geo.invert_pose(T_wc[:, 1:2]) @ T_wc
    B = inputs.shape[0]
    mid = inputs[:, 1]
    T_1i = nets.relpose(torch.cat((mid, mid)), torch.cat((inputs[:, 0], inputs[:, 2])))  # (2B, 4, 4)
    return _triplet_from_middle(T_1i.to(_geometry_dtype(inputs)).reshape(2, B, 4, 4).transpose(0, 1))


def _triplet_from_middle(T_1i: Tensor) -> Tensor:
    """``T_1i (B, 2, 4, 4)`` (middle -> source 0 and -> source 2) -> the triplet's poses
    ``(B, 3, 4, 4)`` in the middle camera's frame: ``T_wc(i) = T_{1->i}^-1``, ``T_wc(1) = I``."""
    eye = torch.eye(4, dtype=T_1i.dtype, device=T_1i.device).expand(T_1i.shape[0], 4, 4)
    return torch.stack((geo.invert_pose(T_1i[:, 0]), eye, geo.invert_pose(T_1i[:, 1])), dim=1)


def pairs_for(cfg: MethodConfig) -> tuple[tuple[int, int], ...]:
    """The (target, source) pairs of a triplet that ``cfg`` synthesises."""
    return PAIRS_LCVS if cfg.lcvs else PAIRS_MIDDLE


def _check_triplets(images: Tensor, inputs: Tensor, K: Tensor) -> None:
    if images.ndim != 5 or images.shape[1:3] != (3, 3):
        raise ValueError(f"images must be (B, 3, 3, H, W), got {tuple(images.shape)}")
    if inputs.shape != images.shape:
        raise ValueError(f"inputs {tuple(inputs.shape)} must have the shape of images {tuple(images.shape)}")
    if K.shape != (images.shape[0], 3, 3, 3):
        raise ValueError(f"K must be (B, 3, 3, 3), got {tuple(K.shape)}")
    geo.check_image_size(images.shape[-2], images.shape[-1])


def _absolute_poses(
    net_out: Tensor, depth0: Tensor, K: Tensor, use_dsc: bool, aggregate: str
) -> tuple[Tensor, Tensor | None, Tensor | None, Tensor | None, Tensor, Tensor]:
    """Poses of a flat batch from the pose network's output (DSC ``(N, 6, h, w)`` or, w/o DSC,
    ``(N, 6)``) and the full-res depth ``depth0 (N, 1, H, W)``.

    Returns ``T_wc (N, 4, 4)``, per-cell ``q (N, n, 4)``, ``c (N, n, 3)`` (None w/o DSC), the
    per-image L_c ``(N,)`` (None w/o DSC) and the aggregate ``q (N, 4)``, ``c (N, 3)``.
    """
    if not use_dsc:
        T = geo.pose_vector_to_matrix(net_out)
        return T, None, None, None, geo.quat_from_matrix(T[:, :3, :3]), net_out[:, 3:]
    q_cells, c_cells = geo.cell_poses(net_out, geo.pool_depth(depth0), K)
    agg = geo.mean_cell_pose if aggregate == "mean" else geo.median_cell_pose
    q, c = agg(q_cells, c_cells)
    l_c = pose_coordinate_loss(q_cells, c_cells, q, c)
    return geo.pose_matrix(q, c), q_cells, c_cells, l_c, q, c


def _geometry_dtype(x: Tensor) -> torch.dtype:
    # Geometry and losses run in at least float32 with autocast off: under AMP the networks may
    # return bf16/fp16, whose 3 significant digits are far too few for poses and reprojection
    # (and CUDA has no bf16 eigh).
    return torch.promote_types(x.dtype, torch.float32)


def triplet_loss(
    nets: Networks, images: Tensor, inputs: Tensor, K: Tensor, cfg: MethodConfig, boot: Bootstrap | None = None,
    depth_override: Tensor | None = None,
) -> tuple[Tensor, dict[str, Tensor], dict[str, float]]:
    """Training loss of a batch of triplets (loop-closed view synthesis).

    Args:
        nets: the networks (``nets.dsc``, or ``nets.pose`` when ``cfg.use_dsc`` is False).
        images: ``(B, 3, 3, H, W)`` in [0, 1], the un-jittered frames (loss targets and sources);
            the middle frame is index 1.
        inputs: ``(B, 3, 3, H, W)``, the colour-jittered network inputs.
        K: ``(B, 3, 3, 3)`` per-image intrinsics at ``H x W``.
        cfg: loss options.
        boot: this step's relative-pose bootstrap, or None (the paper's loss).
        depth_override: ``(B, 3, 1, H, W)`` depth used instead of the depth network's for the poses
            and the warps (RESEARCH ONLY: the ground-truth depth oracle, which trains the pose half
            alone); None: the network's.

    Returns:
        ``total`` (scalar), ``parts`` and ``diagnostics``.

        ``parts`` (tensors attached to the graph; ``.detach()`` before logging): ``L_p``, ``L_s``,
        ``L_c``; ``L_p/scale{k}`` and ``L_s/scale{k}`` (k = 0 full resolution ... 3; L_p of scale k
        warped at the input size or at scale k's own size, as ``cfg.loss_resolution`` says);
        ``L_p/pair_{t}{s}`` (target t synthesised from source s, mean over scales and batch).
        ``total = L_p + w_s L_s + w_c L_c`` (``+ w_depth_consistency L_g`` with ``parts["L_g"]``
        when that weight is set); L_p and L_s are means over scales (L_s of scale k
        weighted 1/2^k as monodepth2), pairs and batch; L_s over the frames used as targets.

        ``diagnostics`` (floats): ``centre_spread`` (RMS distance of the batch's camera centres to
        their mean), ``rot_spread_deg`` (mean angle of its rotations to their mean), ``rel_trans``
        and ``rel_rot_deg`` (mean size of the relative poses of the pairs), ``cell_spread`` (mean
        per-image L_c; 0 w/o DSC), ``valid_frac`` (valid-pixel fraction at scale 0),
        ``median_depth``, and ``lp_identity`` (L_p of the unwarped source images: the no-motion
        reference that L_p must beat). With an active ``boot``: ``parts["L_boot"]`` (the consistency
        of the DSC's relative poses with the bootstrap's, added with weight ``boot.w_consistency``)
        and diagnostics ``boot_warps`` (1 when the warps use the bootstrap poses), ``boot_rel_trans``,
        ``boot_rel_rot_deg`` (size of the bootstrap's relative poses) and ``dsc_boot_trans``,
        ``dsc_boot_rot_deg`` (how far the DSC's relative poses are from them), ``dsc_boot_dir_deg``
        (median angle between their translation directions, over the pairs the bootstrap measured;
        absent when it measured none); with ``boot.w_direction > 0`` also ``parts["L_dir"]`` (added
        with weight ``boot.w_consistency * boot.w_direction``). With ``boot.anchored``:
        ``parts["L_anchor"]`` (added with weight ``boot.w_anchor``) and diagnostics ``anchor_trans``,
        ``anchor_rot_deg`` (how far the DSC's poses are from the anchors).
    """
    _check_triplets(images, inputs, K)
    B, _, C, H, W = images.shape
    x = inputs.reshape(B * 3, C, H, W)

    dt = _geometry_dtype(images)
    disps = [d.to(dt) for d in nets.depth(x)[: cfg.num_scales]]
    pose_out = (nets.dsc(x) if cfg.use_dsc else nets.pose(x)).to(dt)
    T_boot = None
    # (two-view poses need the depth for their scale: _triplet_loss_fp32 makes them)
    if boot is not None and boot.active and (boot.T_wc is not None or boot.two_view is None):
        # The two-frame network learns only through the warps it drives; otherwise its poses are a
        # fixed target for the consistency term.
        with torch.set_grad_enabled(torch.is_grad_enabled() and boot.warps):
            T_boot = bootstrap_poses(nets, inputs, None if boot.T_wc is None else boot.T_wc.to(dt)).to(dt)
    with torch.autocast(images.device.type, enabled=False):
        total, parts, diag = _triplet_loss_fp32(disps, pose_out, images.to(dt), K.to(dt), cfg, T_boot, boot,
                                                None if depth_override is None else depth_override.to(dt))
    if cfg.w_novel_view > 0:
        dsc_mid = pose_out.reshape(B, 3, *pose_out.shape[1:])[:, 1].detach() if cfg.novel_view_pose else None
        parts_nv, diag_nv = novel_view_loss(nets, inputs[:, 1], disps[0].reshape(B, 3, 1, H, W)[:, 1],
                                            dsc_mid, K[:, 1].to(dt), cfg)
        total = total + cfg.w_novel_view * (parts_nv["L_nv_depth"] + parts_nv["L_nv_pose"])
        parts.update(parts_nv)
        diag.update(diag_nv)
    return total, parts, diag


def novel_view_loss(
    nets: Networks, inputs: Tensor, disp: Tensor, dsc: Tensor | None, K: Tensor, cfg: MethodConfig,
    back: Tensor | None = None,
) -> tuple[dict[str, Tensor], dict[str, float]]:
    """``L_nv`` (see ``MethodConfig.w_novel_view``) of frames ``inputs (B, 3, H, W)`` (the network
    inputs), from their disparity ``disp (B, 1, H, W)`` (sigmoid, scale 0; L_nv_depth's gradient
    reaches it) and DSC output ``dsc`` (detached; None, or ``cfg.novel_view_pose`` False: no
    ``L_nv_pose``, returned as 0, and no ``nv_trans``).

    Each frame is seen from ``back (B,)`` (default: uniform in [-``cfg.novel_view_forward``,
    ``cfg.novel_view_back``]) times its median depth behind it (negative: in front). The new
    view's pixels outside a central window (what a view moved back by ``cfg.novel_view_back``
    shows of a wall the frame sees whole) are grey whatever the move, so that the border's width
    says nothing of it; those that the frame does not show (valid = False) count in neither term.

    Returns ``parts``: ``L_nv_depth`` (mean over valid pixels of |log| of the depth network's
    depth on the new view over its depth there, that is the frame's depth carried into the new view:
    ``D_new(p') / (D(p) (z(p') / D(p)))``, ``p`` the frame's pixel that ``p'`` shows, the ratio
    ``z / D`` the move's, detached; so it is unchanged by a scale of all depths, which it cannot
    push: the frame's depth has its gradient too, with ``cfg.novel_view_one_way`` only through its
    mean log over the valid pixels; with ``cfg.novel_view_decoder_only`` the new view's gradient
    reaches the depth network's decoder and not its encoder) and ``L_nv_pose`` (mean over cells of
    :func:`relative_pose_consistency` of the DSC's cell poses of the new view, on that depth, with
    the frame's pose moved back; translations relative to the median depth); ``diagnostics``:
    ``nv_depth_ratio`` (median of that depth ratio: under 1, the network places the new view's
    scene too near), ``nv_back`` (mean move over the median depth), ``nv_trans`` (mean centre error
    of the new views' poses over the median depth), ``nv_valid`` (valid fraction).
    """
    B, _, H, W = inputs.shape
    dt = _geometry_dtype(inputs)
    with torch.autocast(inputs.device.type, enabled=False):
        depth_grad = disp_to_depth(disp.to(dt), cfg.min_depth, cfg.max_depth)
    with torch.no_grad(), torch.autocast(inputs.device.type, enabled=False):
        depth = depth_grad.detach()
        with_pose = dsc is not None and cfg.novel_view_pose
        med = depth.reshape(B, -1).median(dim=1).values
        if back is None:
            span = cfg.novel_view_back + cfg.novel_view_forward
            back = torch.rand(B, dtype=dt, device=inputs.device) * span - cfg.novel_view_forward
        t = torch.zeros(B, 3, dtype=dt, device=inputs.device)
        t[:, 2] = -back.to(dt) * med
        image, z, valid, grid = geo.moved_view(inputs.to(dt), depth, t, K)
        # the move's ratio at each new pixel: its depth over the frame's at the pixel it shows
        move_ratio = z / F.grid_sample(depth, grid, mode="bilinear", padding_mode="border", align_corners=True)
        keep = 1.0 / (1.0 + cfg.novel_view_back)  # the window's half-size over the image's
        u = torch.arange(W, dtype=dt, device=inputs.device) - (W - 1) / 2
        v = torch.arange(H, dtype=dt, device=inputs.device) - (H - 1) / 2
        window = (u.abs()[None, :] <= keep * W / 2) & (v.abs()[:, None] <= keep * H / 2)
        image = torch.where(window, image, torch.full_like(image, 0.5))
        valid = valid & window
        m = valid.to(dt)
        if with_pose:
            # each cell's depth from its valid pixels (every cell keeps some: the window is central)
            z_cells = geo.pool_depth(z * m) / geo.pool_depth(m).clamp(min=1e-6)
            T_src = _absolute_poses(dsc.detach().to(dt), depth, K, True, "mean")[0]
            shift = torch.eye(4, dtype=dt, device=inputs.device).repeat(B, 1, 1)
            shift[:, :3, 3] = t
            T_new = T_src @ shift
    x = image.to(inputs.dtype)
    with _running_statistics_kept(nets.depth):
        if cfg.novel_view_decoder_only:
            with torch.no_grad():
                features = nets.depth.encoder(x)
            disp_new = nets.depth.decoder(features)[0]
        else:
            disp_new = nets.depth(x)[0]
        depth_new = disp_to_depth(disp_new.to(dt), cfg.min_depth, cfg.max_depth)
    with torch.autocast(inputs.device.type, enabled=False):
        carried = F.grid_sample(depth_grad, grid, mode="bilinear", padding_mode="border", align_corners=True)
        log_target = torch.log(carried * move_ratio)
        if cfg.novel_view_one_way:
            # the same value; the gradient reaches the frame's depth through its mean log alone
            log_carried = torch.log(carried)
            n_image = m.sum(dim=(1, 2, 3), keepdim=True).clamp(min=1)
            mean_log = (log_carried * m).sum(dim=(1, 2, 3), keepdim=True) / n_image
            log_target = log_target.detach() + (mean_log - mean_log.detach())
        log_ratio = torch.log(depth_new) - log_target
        n_valid = m.sum().clamp(min=1)
        l_depth = (log_ratio.abs() * m).sum() / n_valid
        with torch.no_grad():
            ratio = torch.exp(log_ratio.detach()[valid]).median() if bool(valid.any()) else log_ratio.new_ones(())
            diag = {"nv_depth_ratio": float(ratio), "nv_back": float(back.mean()), "nv_valid": float(m.mean())}
    if not with_pose:
        return {"L_nv_depth": l_depth, "L_nv_pose": l_depth.new_zeros(())}, diag
    with _running_statistics_kept(nets.dsc):
        dsc_new = nets.dsc(x).to(dt)
    with torch.autocast(inputs.device.type, enabled=False):
        q_cells, c_cells = geo.cell_poses(dsc_new, z_cells, K)
        T_cells = geo.pose_matrix(q_cells.reshape(-1, 4), c_cells.reshape(-1, 3)).reshape(B, -1, 4, 4)
        l_pose = _pose_target_loss(T_cells, T_new, med)
        with torch.no_grad():
            diag["nv_trans"] = float(((c_cells.detach().mean(dim=1) - T_new[:, :3, 3]).norm(dim=-1) / med).mean())
    return {"L_nv_depth": l_depth, "L_nv_pose": l_pose}, diag


@contextmanager
def _running_statistics_kept(net: object) -> Iterator[None]:
    """Within it the BatchNorm layers of ``net`` (if a module) normalise by the batch's statistics
    as in training but leave their running statistics, which ``localize`` and ``evaluate`` use, as
    they were: the novel views (grey border, zoomed out) are not the images those will see, and
    one pass of them a step would otherwise pull the statistics halfway towards theirs."""
    layers = [m for m in net.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)
              and m.training and m.track_running_stats] if isinstance(net, torch.nn.Module) else []
    saved = [(m.momentum, m.num_batches_tracked.clone()) for m in layers]
    for m in layers:
        m.momentum = 0.0  # running = (1 - momentum) running + momentum batch
    try:
        yield
    finally:
        for m, (momentum, tracked) in zip(layers, saved):
            m.momentum = momentum
            m.num_batches_tracked.copy_(tracked)


def _pose_target_loss(T_cells: Tensor, T_ref: Tensor, depth: Tensor) -> Tensor:
    """Mean of :func:`relative_pose_consistency` of every cell's pose ``T_cells (N, n, 4, 4)`` with
    its image's target ``T_ref (N, 4, 4)``, translations over the image's scene depth ``(N,)``."""
    N, n = T_cells.shape[:2]
    T_t = T_ref[:, None].expand(N, n, 4, 4).reshape(-1, 4, 4)
    w_t = (1.0 / depth)[:, None].expand(N, n).reshape(-1)
    return relative_pose_consistency(T_cells.reshape(-1, 4, 4), T_t, w_t).mean()


def _triplet_loss_fp32(
    disps: list[Tensor], pose_out: Tensor, images: Tensor, K: Tensor, cfg: MethodConfig,
    T_boot: Tensor | None = None, boot: Bootstrap | None = None, depth_override: Tensor | None = None,
) -> tuple[Tensor, dict[str, Tensor], dict[str, float]]:
    """The part of :func:`triplet_loss` after the networks (full precision)."""
    B, _, C, H, W = images.shape
    Kf = K.reshape(B * 3, 3, 3)
    # "input": every scale's depth at the input size; "decoder": at its own size (scale 0 is the
    # input size either way, so the poses below see the same full-res depth in both modes)
    at_input = cfg.loss_resolution == "input"
    depths = [
        disp_to_depth(
            d if d.shape[-2:] == (H, W) or not at_input
            else F.interpolate(d, (H, W), mode="bilinear", align_corners=False),
            cfg.min_depth,
            cfg.max_depth,
        )
        for d in disps
    ]
    if depth_override is not None:  # each scale's depth from the given one, at that scale's size
        given = depth_override.reshape(B * 3, 1, H, W)
        depths = [given if d.shape[-2:] == (H, W) else F.interpolate(given, d.shape[-2:], mode="nearest")
                  for d in depths]
    T, _, _, l_c_img, q_img, c_img = _absolute_poses(pose_out, depths[0], Kf, cfg.use_dsc, "mean")
    T = T.reshape(B, 3, 4, 4)
    t_known = None  # (B, 3): frames whose translation from the middle one the bootstrap measured
    if T_boot is None and boot is not None and boot.active and boot.two_view is not None:
        T_boot, t_known = two_view_poses(boot.two_view, depths[0].reshape(B, 3, 1, H, W)[:, 1], T)

    pairs = pairs_for(cfg)
    P = len(pairs)
    t_idx = torch.tensor([p[0] for p in pairs], device=images.device)
    s_idx = torch.tensor([p[1] for p in pairs], device=images.device)

    def flat(a: Tensor) -> Tensor:  # (B, P, ...) -> (B * P, ...)
        return a.reshape(B * P, *a.shape[2:])

    def pair_poses(T_wc: Tensor) -> Tensor:  # (B, 3, 4, 4) -> T_t2s of every pair (B * P, 4, 4)
        return flat(geo.relative_pose(T_wc[:, t_idx], T_wc[:, s_idx]))

    use_boot = T_boot is not None and boot is not None
    anchored = boot is not None and boot.anchored
    T_t2s = pair_poses(T_boot if use_boot and boot.warps else T)  # type: ignore[union-attr]
    boot_parts: dict[str, Tensor] = {}
    boot_diag: dict[str, float] = {}
    # The bootstrap's terms teach the DSC network, not the depth network, where the cameras are:
    # its poses on detached depth (w/o DSC the pose does not depend on depth).
    cons = (_absolute_poses(pose_out, depths[0].detach(), Kf, True, "mean")
            if cfg.use_dsc and (use_boot or anchored) else None)
    T_cons = (T if cons is None else cons[0]).reshape(B, 3, 4, 4)
    # Translations count relative to the scene's depth (the triplet's median, detached): a camera
    # shift t moves the image of points at depth D by t / D radians, so this weighs it like a
    # rotation whatever units the depth network has settled on (monocular training leaves its
    # scale free: ~0.2 units for ~1.7 m on the demo scene, where an unscaled translation error
    # was ~8x too light to teach the DSC network anything but rotation).
    scene_depth = depths[0].detach().reshape(B, -1).median(dim=1).values  # (B,)
    if use_boot:
        assert T_boot is not None and boot is not None
        rel_net, rel_boot = pair_poses(T_cons), pair_poses(T_boot.detach())
        # Pairs whose bootstrap translation was not measured teach the rotation only.
        t_weight = (1.0 / scene_depth)[:, None].expand(B, P)
        if t_known is not None:
            t_weight = t_weight * (t_known[:, t_idx] & t_known[:, s_idx]).to(T.dtype)
        err = relative_pose_consistency(rel_net, rel_boot, flat(t_weight))  # (B * P,)
        boot_parts["L_boot"] = err.mean()
        measured = flat(t_weight) > 0  # pairs with a bootstrap translation
        if boot.w_direction > 0:
            # The cameras' orientations detached: the term moves the centres to where the
            # orientations and the bootstrap's directions put them (the relative rotations are
            # L_boot's to teach; noisy directions early in training would only shake them). Each
            # pair's angle weighs by the parallax it measures (its baseline over the scene's depth):
            # a short baseline has no direction to teach, and the angle's gradient on the centres
            # (1 / baseline) stays bounded.
            t_net = pair_poses(_centres_only(T_cons, pose_out, depths[0], Kf, cfg.use_dsc))[:, :3, 3]
            t_ref = rel_boot[:, :3, 3]
            ang = translation_direction_angle(t_net, t_ref)
            # min(|t_dsc|, |t_boot|): the angle's gradient on t_dsc is 1 / |t_dsc|, so this keeps
            # it below 1 / D also where the DSC's own baseline is (nearly) zero
            baseline = torch.minimum(t_net.detach().norm(dim=-1), t_ref.norm(dim=-1))
            weighted = ang * baseline * flat(t_weight)
            boot_parts["L_dir"] = (torch.where(measured, weighted, torch.zeros_like(ang)).sum()
                                   / measured.sum().clamp(min=1))
        with torch.no_grad():
            t_b, r_b = geo.pose_errors(rel_boot, torch.eye(4, dtype=T.dtype, device=T.device))
            t_d, r_d = geo.pose_errors(rel_net.detach(), rel_boot)
            boot_diag = {"boot_warps": float(boot.warps), "boot_rel_trans": float(t_b.mean()),
                         "boot_rel_rot_deg": float(r_b.mean()), "dsc_boot_trans": float(t_d.mean()),
                         "dsc_boot_rot_deg": float(r_d.mean())}
            if bool(measured.any()):
                a_d = translation_direction_angle(rel_net[measured, :3, 3], rel_boot[measured, :3, 3])
                boot_diag["dsc_boot_dir_deg"] = float(torch.rad2deg(a_d).median())
    if anchored:
        assert boot is not None and boot.T_anchor is not None
        # every cell's pose (w/o DSC the image's) against its frame's anchor
        if cons is not None:
            q_cells, c_cells = cons[1], cons[2]  # (B * 3, n, 4), (B * 3, n, 3)
            T_cells = geo.pose_matrix(q_cells.reshape(-1, 4), c_cells.reshape(-1, 3)).reshape(B * 3, -1, 4, 4)
        else:
            T_cells = T.reshape(B * 3, 1, 4, 4)
        T_anchor = boot.T_anchor.to(T.dtype).reshape(B * 3, 4, 4)
        boot_parts["L_anchor"] = _pose_target_loss(T_cells, T_anchor, scene_depth.repeat_interleave(3))
        with torch.no_grad():
            t_a, r_a = geo.pose_errors(T_cons.detach().reshape(-1, 4, 4), T_anchor)
            boot_diag.update({"anchor_trans": float(t_a.mean()), "anchor_rot_deg": float(r_a.mean())})
    if boot is not None and boot.depth_ref is not None and boot.w_depth_scale > 0:
        # the one scale of all depths, as a log: the mean over the batch's frames of their mean
        # log depth against their references
        drift = (torch.log(depths[0]).reshape(B * 3, -1).mean(dim=1)
                 - boot.depth_ref.to(depths[0].dtype).reshape(-1)).mean()
        boot_parts["L_scale"] = drift.square()
        boot_diag["scale_drift"] = float(drift.detach())
    K_t, K_s = flat(K[:, t_idx]), flat(K[:, s_idx])
    I_t, I_s = flat(images[:, t_idx]), flat(images[:, s_idx])

    targets = sorted({t for t, _ in pairs})
    parts: dict[str, Tensor] = {}
    lp_pairs = images.new_zeros(P)
    lp_scales, ls_scales = [], []
    valid_frac = 0.0
    for k, (disp, depth) in enumerate(zip(disps, depths)):
        h, w = disp.shape[-2:]
        images_k = _downsample(images, h, w)  # L_s always, L_p too at decoder resolution
        if at_input or (h, w) == (H, W):
            Ik_t, Ik_s, Kk_t, Kk_s = I_t, I_s, K_t, K_s
        else:
            Kk = geo.scale_intrinsics(K, w / W, h / H)
            Ik_t, Ik_s = flat(images_k[:, t_idx]), flat(images_k[:, s_idx])
            Kk_t, Kk_s = flat(Kk[:, t_idx]), flat(Kk[:, s_idx])
        depth_t = flat(depth.reshape(B, 3, 1, *depth.shape[-2:])[:, t_idx])
        if cfg.recompute_warps and torch.is_grad_enabled():
            lp_img, valid_mean = checkpoint(_warp_loss, Ik_s, depth_t, T_t2s, Kk_t, Kk_s, Ik_t, cfg,
                                            use_reentrant=False)
        else:
            lp_img, valid_mean = _warp_loss(Ik_s, depth_t, T_t2s, Kk_t, Kk_s, Ik_t, cfg)
        lp = lp_img.reshape(B, P).mean(0)  # (P,)
        lp_pairs = lp_pairs + lp / len(disps)
        lp_scales.append(lp.mean())
        disp_t = disp.reshape(B, 3, 1, h, w)[:, targets].reshape(-1, 1, h, w)
        img_k = images_k[:, targets].reshape(-1, C, h, w)
        ls_scales.append(smoothness_loss(disp_t, img_k).mean() / 2**k)
        parts[f"L_p/scale{k}"] = lp_scales[-1]
        parts[f"L_s/scale{k}"] = ls_scales[-1]
        if k == 0:
            valid_frac = float(valid_mean)
    L_p = torch.stack(lp_scales).mean()
    L_s = torch.stack(ls_scales).mean()
    L_c = l_c_img.mean() if l_c_img is not None else images.new_zeros(())
    total = L_p + cfg.w_s * L_s + cfg.w_c * L_c
    if cfg.w_depth_consistency > 0:  # (a warp's cost: not computed otherwise)
        depth0 = depths[0].reshape(B, 3, 1, H, W)
        g_img, g_valid = geo.depth_disagreement(flat(depth0[:, t_idx]), flat(depth0[:, s_idx]), T_t2s, K_t, K_s)
        parts["L_g"] = (g_img * g_valid).sum() / g_valid.sum().clamp(min=1)
        total = total + cfg.w_depth_consistency * parts["L_g"]
    if "L_boot" in boot_parts and boot is not None and boot.w_consistency > 0:
        total = total + boot.w_consistency * boot_parts["L_boot"]
    if "L_dir" in boot_parts and boot is not None:
        total = total + boot.w_consistency * boot.w_direction * boot_parts["L_dir"]
    if "L_anchor" in boot_parts and boot is not None:
        total = total + boot.w_anchor * boot_parts["L_anchor"]
    if "L_scale" in boot_parts and boot is not None:
        total = total + boot.w_depth_scale * boot_parts["L_scale"]
    parts.update({"L_p": L_p, "L_s": L_s, "L_c": L_c, **boot_parts})
    for i, (t, s) in enumerate(pairs):
        parts[f"L_p/pair_{t}{s}"] = lp_pairs[i]

    with torch.no_grad():
        diag = _diagnostics(q_img, c_img, T_t2s, l_c_img, depths[0])
        ones = torch.ones_like(I_t[:, :1])
        diag["lp_identity"] = float(photometric_loss(I_t, I_s, ones, cfg.alpha).mean())
        diag["valid_frac"] = valid_frac
        diag.update(boot_diag)
    return total, parts, diag


def _centres_only(T: Tensor, pose_out: Tensor, depth0: Tensor, K: Tensor, use_dsc: bool) -> Tensor:
    """``T (B, 3, 4, 4)`` whose gradients reach the camera centres only, never the orientations:
    the rotations detached, and with the DSC the centres recomputed from its output with the ray
    rotations ``theta`` detached (``c = tau - |Q| G e_z`` depends on them) and the depth detached."""
    if use_dsc:
        out = torch.cat((pose_out[:, :3].detach(), pose_out[:, 3:]), dim=1)
        T = _absolute_poses(out, depth0.detach(), K, True, "mean")[0].reshape(T.shape)
    return torch.cat((torch.cat((T[..., :3, :3].detach(), T[..., :3, 3:]), dim=-1), T[..., 3:, :]), dim=-2)


def two_view_poses(two_view: tuple[Tensor, Tensor, Tensor], depth_mid: Tensor,
                   T_fallback: Tensor) -> tuple[Tensor, Tensor]:
    """The triplet's poses ``(B, 3, 4, 4)`` (middle frame = identity) from essential-matrix pairs,
    and which of the triplet's frames have a measured translation from the middle one ``(B, 3)``.

    Each pair's unit translation is scaled by the median, over its triangulated points, of the
    current depth of the middle frame (``depth_mid (B, 1, H, W)``, gradients flow) at the point over
    the point's depth in baselines: the translation in the depth network's units. A rotation-only
    pair (too little parallax to measure its translation: no points) keeps its rotation with a zero
    translation. A pair whose two-view pose failed takes its relative pose from ``T_fallback
    (B, 3, 4, 4)`` (the DSC's, detached). Neither has a measured translation.
    """
    T_1i, points, ok = two_view
    B, _, H, W = depth_mid.shape
    n = points.shape[2]
    x = points[..., 0] / (W - 1) * 2 - 1
    y = points[..., 1] / (H - 1) * 2 - 1
    grid = torch.stack((x, y), dim=-1).reshape(B, 2 * n, 1, 2).to(depth_mid.dtype)
    # Not detached: the translation then scales with the depth, so the warps (and L_p) do not
    # change with the depth's global scale, which monocular training cannot fix; with a detached
    # scale every step pushes that scale, and it ran away (0.2 -> 11 units in 50 steps).
    d = F.grid_sample(depth_mid, torch.nan_to_num(grid, nan=0.0), align_corners=True)
    z = points[..., 2].to(depth_mid.dtype)
    has = torch.isfinite(z)
    # NaN where no point, without NaN gradients (0 x 1/NaN would be NaN)
    ratio = torch.where(has, d.reshape(B, 2, n) / torch.where(has, z, torch.ones_like(z)), torch.nan)
    scale = torch.nanmedian(ratio, dim=-1).values  # (B, 2)
    measured = torch.isfinite(scale) & (scale > 0)
    usable = ok.bool()
    T_1i = T_1i.to(depth_mid.dtype)
    t = T_1i[..., :3, 3:] * torch.where(measured, scale, torch.zeros_like(scale))[..., None, None]
    T = torch.cat((torch.cat((T_1i[..., :3, :3], t), dim=-1), T_1i[..., 3:, :]), dim=-2)
    fallback = torch.stack((geo.relative_pose(T_fallback[:, 1], T_fallback[:, 0]),
                            geo.relative_pose(T_fallback[:, 1], T_fallback[:, 2])), dim=1).detach()
    known = usable & measured
    t_known = torch.stack((known[:, 0], torch.ones_like(known[:, 0]), known[:, 1]), dim=1)
    return _triplet_from_middle(torch.where(usable[..., None, None], T, fallback)), t_known


def _downsample(images: Tensor, h: int, w: int) -> Tensor:
    """``(B, 3, C, H, W)`` frames area-averaged to ``h x w`` (unchanged at their own size)."""
    B, n, C, H, W = images.shape
    if (h, w) == (H, W):
        return images
    return F.interpolate(images.reshape(B * n, C, H, W), (h, w), mode="area").reshape(B, n, C, h, w)


def _warp_loss(
    I_s: Tensor, depth_t: Tensor, T_t2s: Tensor, K_t: Tensor, K_s: Tensor, I_t: Tensor, cfg: MethodConfig
) -> tuple[Tensor, Tensor]:
    """Per-image L_p of the target synthesised from the source, and the valid-pixel fraction."""
    warped, valid = geo.warp(I_s, depth_t, T_t2s, K_t, K_s)
    counted = valid if cfg.photometric_pixels == "valid" else torch.ones_like(valid)
    return photometric_loss(I_t, warped, counted, cfg.alpha), valid.mean().detach()


def _diagnostics(
    q: Tensor, c: Tensor, T_t2s: Tensor, l_c: Tensor | None, depth0: Tensor
) -> dict[str, float]:
    q, c = q.detach(), c.detach()
    qm, cm = geo.mean_cell_pose(q.unsqueeze(0), c.unsqueeze(0))
    t_rel, r_rel = geo.pose_errors(T_t2s.detach(), torch.eye(4, dtype=T_t2s.dtype, device=T_t2s.device))
    return {
        "centre_spread": float((c - cm).norm(dim=-1).pow(2).mean().sqrt()),
        "rot_spread_deg": float(torch.rad2deg(geo.quat_angle(q, qm)).mean()),
        "rel_trans": float(t_rel.mean()),
        "rel_rot_deg": float(r_rel.mean()),
        "cell_spread": float(l_c.detach().mean()) if l_c is not None else 0.0,
        "median_depth": float(depth0.detach().median()),
    }


@torch.no_grad()
def preview(nets: Networks, images: Tensor, inputs: Tensor, K: Tensor, cfg: MethodConfig) -> dict[str, Tensor]:
    """What the first triplet of a batch looks like to the method (for TensorBoard): the middle
    frame ``target (3, H, W)``, its ``depth (H, W)``, and ``warped (3, H, W)``, the target
    synthesised from the first source with the DSC's (or w/o DSC the pose head's) poses."""
    x = inputs[:1].reshape(3, *inputs.shape[2:])
    dt = _geometry_dtype(images)
    depth = disp_to_depth(nets.depth(x)[0].to(dt), cfg.min_depth, cfg.max_depth)
    pose_out = (nets.dsc(x) if cfg.use_dsc else nets.pose(x)).to(dt)
    T = _absolute_poses(pose_out, depth, K[0].to(dt), cfg.use_dsc, "mean")[0]
    warped, _ = geo.warp(images[0, 0:1].to(dt), depth[1:2], geo.relative_pose(T[1:2], T[0:1]),
                         K[0, 1:2].to(dt), K[0, 0:1].to(dt))
    return {"target": images[0, 1], "depth": depth[1, 0], "warped": warped[0]}


@torch.no_grad()
def predict(nets: Networks, inputs: Tensor, K: Tensor) -> dict[str, Tensor]:
    """Absolute pose, confidence and depth of single images (test time: median aggregation).

    The networks run in eval mode (BatchNorm running statistics); their previous mode is restored.

    Args:
        nets: the networks; depth range from ``nets.cfg``.
        inputs: ``(B, 3, H, W)`` in [0, 1], H and W multiples of 32.
        K: ``(B, 3, 3)`` intrinsics at ``H x W``.

    Returns:
        ``T_wc (B, 4, 4)``, ``confidence (B,)`` in (0, 1] (1 = all cells agree; 1 w/o DSC),
        ``cell_spread_t (B,)`` median centre distance of the cells to the pose (depth units),
        ``cell_spread_r_deg (B,)`` their median rotation angle, ``depth (B, 1, H, W)``.
    """
    if inputs.ndim != 4 or inputs.shape[1] != 3 or K.shape != (inputs.shape[0], 3, 3):
        raise ValueError(f"predict needs inputs (B, 3, H, W) and K (B, 3, 3), got "
                         f"{tuple(inputs.shape)} and {tuple(K.shape)}")
    geo.check_image_size(inputs.shape[-2], inputs.shape[-1])
    was_training = nets.training
    nets.eval()
    try:
        dt = _geometry_dtype(inputs)
        sigma = nets.depth(inputs)[0].to(dt)
        pose_out = (nets.dsc(inputs) if nets.cfg.use_dsc else nets.pose(inputs)).to(dt)
        with torch.autocast(inputs.device.type, enabled=False):
            depth = disp_to_depth(sigma, nets.cfg.min_depth, nets.cfg.max_depth)
            T, q_cells, c_cells, _, q, c = _absolute_poses(pose_out, depth, K.to(dt), nets.cfg.use_dsc, "median")
    finally:
        nets.train(was_training)
    B = inputs.shape[0]
    if q_cells is None or c_cells is None:
        zeros = inputs.new_zeros(B)
        return {"T_wc": T, "confidence": torch.ones_like(zeros), "cell_spread_t": zeros,
                "cell_spread_r_deg": zeros, "depth": depth}
    spread_t, spread_r = geo.cell_pose_spread(q_cells, c_cells, q, c)
    scale = depth.flatten(1).median(dim=1).values
    confidence = 1.0 / (1.0 + spread_r / CONF_ROT_DEG + spread_t / (CONF_TRANS_REL * scale))
    return {"T_wc": T, "confidence": confidence, "cell_spread_t": spread_t,
            "cell_spread_r_deg": spread_r, "depth": depth}
