"""The paper's numbers in the method: the confidence formula on per-cell poses of known spread,
confidence ranking errors, and the loss weights w_s = 0.001, w_c = 0.03 (Sec. IV-B)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from relocdepth import geometry as geo
from relocdepth import metrics as M
from relocdepth.eval_geometry import pose_errors, quat_wxyz_to_rotmat
from relocdepth.method import MethodConfig, predict, triplet_loss
from relocdepth.models import ModelConfig, build_networks

torch.set_num_threads(1)
W, H = 128, 96  # DSC grid 4 x 3: 12 cells
GW, GH = W // 32, H // 32
MIN_D, MAX_D = 0.1, 100.0
DEPTH = 2.0  # metres-like units of the fake depth network
K = torch.tensor([[100.0, 0.0, (W - 1) / 2], [0.0, 100.0, (H - 1) / 2], [0.0, 0.0, 1.0]],
                 dtype=torch.float64)
R0 = quat_wxyz_to_rotmat(np.array([0.9, 0.2, -0.4, 0.1]))
C0 = np.array([0.5, -1.0, 2.0])


def rot_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


class FakeNets(torch.nn.Module):
    """Networks that output a constant depth and a given DSC (one image per row of ``dsc``)."""

    def __init__(self, dsc: torch.Tensor, depth: float = DEPTH) -> None:
        super().__init__()
        self.cfg = SimpleNamespace(use_dsc=True, min_depth=MIN_D, max_depth=MAX_D)
        # invert depth = 1 / (a sigma + b), b = 1/max, a = 1/min - 1/max (monodepth2's mapping)
        b, a = 1.0 / MAX_D, 1.0 / MIN_D - 1.0 / MAX_D
        self.sigma = (1.0 / depth - b) / a
        self.out = dsc

    def depth(self, x: torch.Tensor) -> list[torch.Tensor]:
        return [torch.full((x.shape[0], 1, H, W), self.sigma, dtype=x.dtype)]

    def dsc(self, x: torch.Tensor) -> torch.Tensor:
        return self.out


def dsc_of_cell_poses(rotations: list[np.ndarray], centres: list[np.ndarray]) -> torch.Tensor:
    """A (1, 6, GH, GW) DSC whose cell i (row-major) gives the camera pose (rotations[i], centres[i])
    at depth DEPTH."""
    n = GH * GW
    assert len(rotations) == len(centres) == n
    T = torch.zeros(n, 4, 4, dtype=torch.float64)
    T[:, :3, :3] = torch.from_numpy(np.stack(rotations))
    T[:, :3, 3] = torch.from_numpy(np.stack(centres))
    T[:, 3, 3] = 1.0
    full = geo.dsc_from_pose(T, torch.full((n, 1, GH, GW), DEPTH, dtype=torch.float64),
                             K.expand(n, 3, 3))
    out = torch.zeros(1, 6, GH, GW, dtype=torch.float64)
    for i in range(n):
        out[0, :, i // GW, i % GW] = full[i, :, i // GW, i % GW]
    return out


def run_predict(dsc: torch.Tensor) -> dict[str, torch.Tensor]:
    B = dsc.shape[0]
    return predict(FakeNets(dsc), torch.zeros(B, 3, H, W, dtype=torch.float64), K.expand(B, 3, 3))


# Twelve centres: C0 +- d along each axis, twice. Each is d from C0 and C0 is their
# per-component median, so the centre spread (median distance to the aggregate) is d.
AXES = [s * e for e in np.eye(3) for s in (1.0, -1.0)] * 2
# Twelve rotations R0 Rz(a): the geodesic median is R0 (a = 0) and the median angle from it is
# 2 deg (sorted |a|: 0 0 0 1 1 2 2 3 3 4 4 5).
ANGLES = [-4.0, -3.0, -2.0, -1.0, 0.0, 0.0, 0.0, 1.0, 2.0, 3.0, 4.0, 5.0]


@pytest.mark.parametrize(("d", "angles", "spread_t", "spread_r", "confidence"), [
    (0.0, [0.0] * 12, 0.0, 0.0, 1.0),
    # d = 0.05 * median depth: the translation term is 1
    (0.1, [0.0] * 12, 0.1, 0.0, 1.0 / (1.0 + 1.0)),
    (0.0, ANGLES, 0.0, 2.0, 1.0 / (1.0 + 2.0 / 5.0)),
    (0.1, ANGLES, 0.1, 2.0, 1.0 / (1.0 + 2.0 / 5.0 + 1.0)),
    (0.3, ANGLES, 0.3, 2.0, 1.0 / (1.0 + 2.0 / 5.0 + 3.0)),
])
def test_confidence_formula_on_known_spreads(
    d: float, angles: list[float], spread_t: float, spread_r: float, confidence: float
) -> None:
    """confidence = 1 / (1 + spread_r / 5 deg + spread_t / (0.05 * median depth))."""
    dsc = dsc_of_cell_poses([R0 @ rot_z(a) for a in angles], [C0 + d * u for u in AXES])
    out = run_predict(dsc)
    assert float(out["depth"].median()) == pytest.approx(DEPTH, rel=1e-9)
    assert float(out["cell_spread_t"][0]) == pytest.approx(spread_t, abs=1e-6)
    assert float(out["cell_spread_r_deg"][0]) == pytest.approx(spread_r, abs=1e-4)
    assert float(out["confidence"][0]) == pytest.approx(confidence, abs=1e-5)
    T = out["T_wc"][0].numpy()  # the aggregate is the pose the cells are spread around
    np.testing.assert_allclose(T[:3, 3], C0, atol=1e-6)
    np.testing.assert_allclose(T[:3, :3], R0, atol=1e-6)


def test_confidence_ranks_errors_when_some_predictions_are_worse() -> None:
    """Images whose cells are noisier get worse poses and lower confidence: Spearman < 0."""
    rng = np.random.default_rng(0)
    noise = [0.0025, 0.005, 0.01, 0.02, 0.04, 0.08, 0.16, 0.32]  # per image, growing
    dscs = []
    for sigma in noise:
        rots, cents = [], []
        for _ in range(GH * GW):
            axis = rng.normal(size=3)
            angle = np.radians(20.0) * sigma * abs(rng.normal())
            q = np.r_[np.cos(angle / 2), np.sin(angle / 2) * axis / np.linalg.norm(axis)]
            rots.append(R0 @ quat_wxyz_to_rotmat(q))
            cents.append(C0 + sigma * rng.normal(size=3))
        dscs.append(dsc_of_cell_poses(rots, cents))
    out = run_predict(torch.cat(dscs))
    T_gt = np.tile(np.eye(4), (len(noise), 1, 1))
    T_gt[:, :3, :3], T_gt[:, :3, 3] = R0, C0
    t_err, r_err = pose_errors(out["T_wc"].numpy(), T_gt)
    conf = out["confidence"].numpy()
    assert np.all(np.diff(conf) < 0)  # confidence falls with the noise
    ranking = M.confidence_ranking(conf, t_err, r_err)
    assert ranking["spearman_t"] < -0.8 and ranking["spearman_r"] < -0.8, ranking
    # the worst-confidence half holds the larger errors
    order = np.argsort(conf)
    assert t_err[order[:4]].mean() > 5 * t_err[order[4:]].mean()


def test_spearman_on_known_cases() -> None:
    a = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    assert M.spearman(a, a**3) == pytest.approx(1.0)
    assert M.spearman(a, -np.exp(a)) == pytest.approx(-1.0)
    # ties get average ranks: x ranks 1 2.5 2.5 4, y ranks 1 2 3 4 -> rho = 4.5 / sqrt(4.5 * 5)
    assert M.spearman(np.array([1.0, 2.0, 2.0, 3.0]), np.array([1.0, 2.0, 3.0, 4.0])) == \
        pytest.approx(4.5 / np.sqrt(4.5 * 5.0))
    assert M.spearman(np.ones(4), a[:4]) is None  # constant column: undefined
    assert M.spearman(a[:2], a[:2]) is None
    scipy_stats = pytest.importorskip("scipy.stats")
    rng = np.random.default_rng(1)
    x, y = rng.integers(0, 5, 40).astype(float), rng.normal(size=40)
    assert M.spearman(x, y) == pytest.approx(scipy_stats.spearmanr(x, y).statistic)


def test_loss_weights_are_the_papers() -> None:
    """L = L_p + 0.001 L_s + 0.03 L_c (Sec. IV-B), with the paper's numbers written out here."""
    torch.manual_seed(0)
    nets = build_networks(ModelConfig())
    gen = torch.Generator().manual_seed(0)
    h, w = 64, 96
    imgs = torch.rand(1, 3, 3, h, w, generator=gen)
    Kt = torch.tensor([[80.0, 0, (w - 1) / 2], [0, 80.0, (h - 1) / 2], [0, 0, 1]]).expand(1, 3, 3, 3)
    cfg = MethodConfig()
    assert (cfg.w_s, cfg.w_c) == (0.001, 0.03)
    total, parts, _ = triplet_loss(nets, imgs, imgs, Kt.clone(), cfg)
    total, parts = total.detach(), {k: v.detach() for k, v in parts.items()}
    assert float(parts["L_s"]) > 0 and float(parts["L_c"]) > 0  # both terms take part
    expect = parts["L_p"] + 0.001 * parts["L_s"] + 0.03 * parts["L_c"]
    assert float(total) == pytest.approx(float(expect), rel=1e-6)
    # and not, say, the weights swapped
    swapped = parts["L_p"] + 0.03 * parts["L_s"] + 0.001 * parts["L_c"]
    assert float(total) != pytest.approx(float(swapped), rel=1e-6)
