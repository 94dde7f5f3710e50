"""What the points' part of the bundle adjustment's reduced system costs, block by block against
scalar by scalar, measured in one run.

Each Levenberg-Marquardt step of :func:`relocdepth.ba.bundle_adjust` eliminates the points and
solves for the cameras, whose system needs ``E B^-1 E^T`` (``E``: the cameras' and points' cross
terms, ``B``: the points' 3x3 blocks). Two ways to multiply it, on generated problems of the
anchors' shapes (cameras along a path, each point seen from a run of consecutive cameras, random
blocks: the cost depends on the pattern only):

- ``scalar``: scipy's CSR product ``E @ B @ E.T`` of the scalar entries (how the fit multiplied
  before :func:`relocdepth.ba.schur_product`);
- ``block``: :func:`relocdepth.ba.schur_product` (BSR, 6x3 blocks by 3x6).

Shapes: ``long`` as one of the demo scene's two paths in a build (149 cameras, ~1300 points
seen from ~34 cameras on average: the small room stays in view), ``short`` as a walk through
a larger place (120 cameras, 3000 points seen from ~8). Interleaved, best of ``--reps``; the
ratio is scalar / block. Also checks that the two agree.

    python benchmarks/bench_ba.py [--reps 5]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

SHAPES = {"long": (149, 1300, 34), "short": (120, 3000, 8)}  # cameras, points, mean track length


def problem(n_cam: int, n_pt: int, length: int, seed: int = 0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    lengths = np.clip(rng.poisson(length, n_pt), 2, n_cam)
    first = rng.integers(0, n_cam - lengths + 1)
    pt = np.repeat(np.arange(n_pt), lengths)
    cam = np.concatenate([np.arange(f, f + n) for f, n in zip(first, lengths)])
    E = rng.normal(size=(len(pt), 6, 3))
    A = rng.normal(size=(n_pt, 3, 3))
    B = A @ np.swapaxes(A, 1, 2) + np.eye(3)  # symmetric positive definite, as the points' blocks
    return E, B, cam, pt


def scalar_product(E: np.ndarray, B: np.ndarray, cam: np.ndarray, pt: np.ndarray, n_cam: int):
    from relocdepth.ba import sparse_blocks

    n_pt = len(B)
    Es = sparse_blocks(E, cam, pt, (6 * n_cam, 3 * n_pt))
    Bs = sparse_blocks(B, np.arange(n_pt), np.arange(n_pt), (3 * n_pt, 3 * n_pt))
    return Es @ Bs @ Es.T


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=5, help="interleaved passes (best of)")
    a = ap.parse_args()
    from relocdepth.ba import schur_product

    print("| shape | cameras | points | observations | scalar (ms) | block (ms) | scalar / block |")
    print("|---|---|---|---|---|---|---|")
    for name, (n_cam, n_pt, length) in SHAPES.items():
        E, B, cam, pt = problem(n_cam, n_pt, length)
        ways = {"scalar": scalar_product, "block": schur_product}
        best = {k: float("inf") for k in ways}
        out = {}
        for _ in range(a.reps):
            for k, fn in ways.items():
                t0 = time.perf_counter()
                out[k] = fn(E, B, cam, pt, n_cam)
                best[k] = min(best[k], time.perf_counter() - t0)
        diff = abs(out["scalar"] - out["block"]).max() / abs(out["scalar"]).max()
        if diff > 1e-10:
            raise SystemExit(f"{name}: the two products differ by {diff:.2e} (relative)")
        print(f"| {name} | {n_cam} | {n_pt} | {len(pt)} | {1e3 * best['scalar']:.0f} | {1e3 * best['block']:.0f} "
              f"| {best['scalar'] / best['block']:.2f} |")


if __name__ == "__main__":
    main()
