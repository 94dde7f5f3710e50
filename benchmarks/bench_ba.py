"""What the cameras' reduced system of the bundle adjustment costs, three ways of multiplying it
and two of solving it, measured in one run.

Each Levenberg-Marquardt step of :func:`relocdepth.ba.bundle_adjust` eliminates the points and
solves for the cameras, whose system needs ``E B^-1 E^T`` (``E``: the cameras' and points' cross
terms, ``B``: the points' 3x3 blocks). On generated problems of the anchors' shapes (cameras along
a path, each point seen from a run of consecutive cameras, random blocks: the cost depends on the
pattern only):

- ``scalar``: scipy's CSR product ``E @ B @ E.T`` of the scalar entries (how the fit multiplied
  before :func:`relocdepth.ba.schur_product`);
- ``block``: :func:`relocdepth.ba.schur_product` (BSR, 6x3 blocks by 3x6; the fit's way beyond
  ``relocdepth.ba.DENSE_CAMERAS`` cameras);
- ``dense``: :func:`relocdepth.ba.dense_schur_product` (dense products over groups of points;
  the fit's way up to ``DENSE_CAMERAS``);

and the system (the product with a dominant diagonal added, as the damping's) solved by scipy's
sparse LU (``spsolve``, SuperLU) and by a dense Cholesky factorisation
(``relocdepth.ba._solve_positive_definite``).

Shapes: ``long`` as one of the demo scene's two paths in a build (149 cameras, ~1300 points
seen from ~34 cameras on average: the small room stays in view), ``short`` as a walk through
a larger place (120 cameras, 3000 points seen from ~8), ``500`` as a 500-frame sequence of the
demo's generator (500 cameras, 5570 points whose tracks' lengths are log-normal, median 8,
clipped to 2-320 frames: the real one's were 1-318, median 5, a tenth over 85; the sum of their
squares, which the product's cost follows, 17.0 million, the real one's 15.2). Interleaved, best of
``--reps``. Also checks that the products and the solutions agree.

    python benchmarks/bench_ba.py [--reps 5]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

# cameras, points, mean track length (Poisson), or with a spread the median of log-normal lengths
SHAPES = {"long": (149, 1300, 34, None), "short": (120, 3000, 8, None), "500": (500, 5570, 8, 1.6)}


def problem(n_cam: int, n_pt: int, length: int, spread: float | None = None, seed: int = 0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    if spread is None:
        lengths = np.clip(rng.poisson(length, n_pt), 2, n_cam)
    else:
        lengths = np.clip(np.round(np.exp(rng.normal(np.log(length), spread, n_pt))), 2, min(320, n_cam)).astype(int)
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
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    from relocdepth.ba import _solve_positive_definite, dense_schur_product, schur_product

    print("| shape | cameras | points | observations | scalar (ms) | block (ms) | dense (ms) | scalar / block "
          "| block / dense | sparse LU (ms) | Cholesky (ms) | LU / Cholesky |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, (n_cam, n_pt, length, spread) in SHAPES.items():
        E, B, cam, pt = problem(n_cam, n_pt, length, spread)
        products = {"scalar": scalar_product, "block": schur_product, "dense": dense_schur_product}
        best = {k: float("inf") for k in [*products, "lu", "cholesky"]}
        out = {}
        for _ in range(a.reps):
            for k, fn in products.items():
                t0 = time.perf_counter()
                out[k] = fn(E, B, cam, pt, n_cam)
                best[k] = min(best[k], time.perf_counter() - t0)
            S = out["block"] + sp.identity(6 * n_cam) * (abs(out["block"]).sum(axis=1).max() + 1.0)
            b = np.ones(6 * n_cam)
            t0 = time.perf_counter()
            out["lu"] = spsolve(S.tocsc(), b)
            best["lu"] = min(best["lu"], time.perf_counter() - t0)
            t0 = time.perf_counter()
            out["cholesky"] = _solve_positive_definite(S.toarray(), b)
            best["cholesky"] = min(best["cholesky"], time.perf_counter() - t0)
        ref = out["scalar"].toarray()
        for k in ("block", "dense"):
            got = out[k] if isinstance(out[k], np.ndarray) else out[k].toarray()
            diff = np.abs(ref - got).max() / np.abs(ref).max()
            if diff > 1e-10:
                raise SystemExit(f"{name}: the {k} product differs from the scalar one by {diff:.2e} (relative)")
        diff = np.abs(out["lu"] - out["cholesky"]).max() / np.abs(out["lu"]).max()
        if diff > 1e-8:
            raise SystemExit(f"{name}: the two solutions differ by {diff:.2e} (relative)")
        ms = {k: 1e3 * v for k, v in best.items()}
        print(f"| {name} | {n_cam} | {n_pt} | {len(pt)} | {ms['scalar']:.0f} | {ms['block']:.0f} | {ms['dense']:.0f} "
              f"| {best['scalar'] / best['block']:.2f} | {best['block'] / best['dense']:.2f} | {ms['lu']:.0f} "
              f"| {ms['cholesky']:.0f} | {best['lu'] / best['cholesky']:.2f} |")


if __name__ == "__main__":
    main()
