"""Research: how fast does the DSC network learn absolute pose from absolute targets?

Trains the DSC network alone (random init, batch 18 images, Adam 3e-4, one thread) with every
cell's pose pulled towards a target pose (centre error over the image's median depth plus rotation
angle; no photometric loss), for a wall-clock budget, and scores it with the evaluation protocol
(Sim(3) fitted on the training frames, median errors on the test frames, relative pose of test
frames 5 apart vs the identity) every 100 steps. Targets and depth:

- ``gt``: ground-truth poses and depth (the ceiling: what the network can learn at all);
- ``vo``: the trajectory from the bootstrap's own geometry (``relocdepth.vo``: odometry and
  registration with a trained run's depth network, no ground truth), with that network's depth.

    python benchmarks/quality/dsc_targets.py SHARDS --targets gt --minutes 20
    python benchmarks/quality/dsc_targets.py SHARDS --targets vo --checkpoint RUN --minutes 20
    python benchmarks/quality/dsc_targets.py SHARDS --targets gt --size 192x128 --device cuda
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import vo_trajectory as V

from relocdepth import geometry as geo
from relocdepth.dataset import open_dataset
from relocdepth.evaluate import pose_report
from relocdepth.models.dsc import DSCNet
from relocdepth.vo import VOConfig


def as_tensor(images: list[np.ndarray]) -> torch.Tensor:
    return torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).float() / 255


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("shards", type=Path)
    ap.add_argument("--targets", choices=("gt", "vo"), default="gt")
    ap.add_argument("--checkpoint", help="a trained run (its depth network) for --targets vo")
    ap.add_argument("--minutes", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", help="train and score at WxH (images and depth resized; K follows)")
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    args = ap.parse_args()
    if args.targets == "vo" and not args.checkpoint:
        ap.error("--targets vo needs --checkpoint")
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)

    size = tuple(int(v) for v in args.size.lower().split("x")) if args.size else None
    dev = torch.device(args.device)
    seqs = [V._resize(s, size) for s in V.load(args.shards, 10**9)]
    ds = open_dataset(args.shards)
    te = sorted(ds.frames("test"), key=lambda r: (r.sequence, r.frame))
    test = V._resize(V.Sequence("test", [ds.read_image(r) for r in te], te[0].intrinsics,
                                np.stack([ds.read_pose(r) for r in te]), [ds.read_depth(r) for r in te]), size)
    if args.targets == "vo":
        maps, _ = V.network_depth(args.checkpoint, [*seqs, test])  # one load of the checkpoint
        depths, depth_te = maps[:-1], maps[-1]
        T_target = np.concatenate(V.odometry_world(seqs, depths, VOConfig()).world)
    else:
        depths, depth_te = [s.depth_gt for s in seqs], test.depth_gt
        T_target = np.concatenate([s.T_gt for s in seqs])
    T_gt = np.concatenate([s.T_gt for s in seqs])
    I_tr, I_te = as_tensor([im for s in seqs for im in s.images]).to(dev), as_tensor(test.images).to(dev)
    D_tr = torch.from_numpy(np.stack([d for ds_ in depths for d in ds_]))[:, None].float().to(dev)
    D_te = torch.from_numpy(np.stack(depth_te))[:, None].float().to(dev)
    K = torch.from_numpy(seqs[0].intrinsics.K()).float().to(dev)
    T_t = torch.from_numpy(T_target).float().to(dev)
    q_t = geo.quat_from_matrix(T_t[:, :3, :3])
    D_med = torch.stack([d[d > 0].median() for d in D_tr])

    net = DSCNet().to(dev)
    opt = torch.optim.Adam(net.parameters(), lr=3e-4)

    def cells(I: torch.Tensor, D: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return geo.cell_poses(net(I), geo.pool_depth(D), K.expand(len(I), 3, 3))

    def predict(I: torch.Tensor, D: torch.Tensor) -> np.ndarray:
        net.eval()
        with torch.no_grad():
            out = [geo.pose_matrix(*geo.median_cell_pose(*cells(I[i:i + 50], D[i:i + 50])))
                   for i in range(0, len(I), 50)]
        net.train()
        return torch.cat(out).double().cpu().numpy()

    def score(step: int) -> None:
        rep, _, _ = pose_report(predict(I_tr, D_tr), T_gt, predict(I_te, D_te), test.T_gt,
                                [r.sequence for r in te], 5)
        t, rel = rep["test"], rep["relative"]
        print(f"step {step}: test {t['median_t_m']:.3f} m / {t['median_r_deg']:.1f} deg, rotation-only "
              f"{rep['rotation_only']['median_r_deg']:.1f} deg, relative (5 apart) {rel['median_t_m']:.4f} m / "
              f"{rel['median_r_deg']:.2f} deg (identity {rel['identity_median_t_m']:.4f} / "
              f"{rel['identity_median_r_deg']:.2f})", flush=True)

    g = torch.Generator().manual_seed(args.seed)
    t0, step = time.time(), 0
    while time.time() - t0 < args.minutes * 60:
        idx = torch.randint(0, len(I_tr), (18,), generator=g).to(dev)
        q, c = cells(I_tr[idx], D_tr[idx])
        loss = ((c - T_t[idx, None, :3, 3]).norm(dim=-1) / D_med[idx, None]).mean() \
            + geo.quat_angle(q, q_t[idx, None].expand_as(q)).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        if step % 100 == 0:
            score(step)
    score(step)


if __name__ == "__main__":
    main()
