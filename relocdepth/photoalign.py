"""Direct alignment: the camera pose that best explains posed views with depth, pixel by pixel.

Given views (grey image, depth, intrinsics and camera-to-world pose ``T_wn``) and a query image,
:func:`align` finds the query's ``T_wq`` by Levenberg-Marquardt on the photometric residual of the
views' pixels seen from the query:

    r_i = I_n(p_i) - (a_n I_q(pi(K_q T_wq^-1 T_wn D_n(p_i) K_n^-1 p_i)) + b_n)

over each view's pixels with the strongest image gradient, coarse to fine on image pyramids
(``levels``, each half the size: a wide basin at the coarsest level, precision at the finest),
with a Huber loss (``huber``, on intensities in [0, 1]) and an affine brightness ``(a_n, b_n)`` per
view fitted in closed form at every step (exposure changes between real frames). The Jacobian is
analytic: the query's image gradient at the warped pixel times the projection's derivative
times ``dX_q/d(delta)`` for the update ``T_wq <- T_wq exp(delta)``, ``delta = (v, w)``:
``dX_q = -v + X_q x w`` (README, *Localize*: the refined pose).

:attr:`AlignResult.cost` is the mean robust residual over all selected pixels at the finest
level; a pixel that leaves the query's image costs what its view's pixels cost when explained by
nothing but the view's mean brightness (the *null* cost), so that looking away explains nothing.
It compares poses of one query against the same views (lower: explains them better), and an
aligned pose is trusted (:attr:`AlignResult.accepted`) when it is clearly below the null cost:
on real images, converged poses reached 0.43-0.89x of it, poses with too little overlap
0.94-1.01x (README, *Quality*).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from relocdepth.camera import scale_K
from relocdepth.twoview import as_grey


@dataclass(frozen=True)
class AlignConfig:
    levels: int = 3  # pyramid levels, each half the size of the one above
    max_width: int = 320  # the finest level at most this wide (views and query)
    iters: int = 25  # Levenberg-Marquardt steps per level at most
    points: int = 2500  # pixels of each view per level (strongest gradient first)
    huber: float = 0.05  # Huber threshold on intensities in [0, 1]
    # an aligned pose is trusted when its cost is at most this share of the null cost (its pixels
    # explained clearly better than by each view's mean brightness)
    accept_ratio: float = 0.9


@dataclass
class View:
    """One posed view: ``image`` RGB/grey uint8, ``depth (H, W)`` (<= 0: unknown) in the pose's
    units, ``K (3, 3)``, ``T_wc (4, 4)``."""

    image: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    T_wc: np.ndarray


@dataclass
class AlignResult:
    T_wc: np.ndarray  # the aligned query pose
    cost: float  # mean robust residual at the finest level (see module doc)
    start_cost: float  # the same at the start pose
    inside: float  # share of the selected pixels inside the query's image at the end
    null_cost: float  # the cost of a query that explains nothing but each view's mean brightness
    accepted: bool  # cost <= accept_ratio * null_cost (never when null_cost is 0: nothing to explain)


def _pyramid(grey: np.ndarray, K: np.ndarray, levels: int, max_width: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(image float32 in [0, 1], K) from the finest level (at most ``max_width`` wide) to the
    coarsest."""
    h, w = grey.shape
    s = min(1.0, max_width / w)
    fw, fh = max(1, round(w * s)), max(1, round(h * s))
    img = grey if (fw, fh) == (w, h) else cv2.resize(grey, (fw, fh), interpolation=cv2.INTER_AREA)
    out = [(img.astype(np.float32) / 255.0, scale_K(K, fw / w, fh / h))]
    for _ in range(levels - 1):
        prev, Kp = out[-1]
        if min(prev.shape) < 16:
            break
        nxt = cv2.pyrDown(prev)
        out.append((nxt, scale_K(Kp, nxt.shape[1] / prev.shape[1], nxt.shape[0] / prev.shape[0])))
    return out


def _gradients(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference image gradients (per pixel)."""
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=1, borderType=cv2.BORDER_REPLICATE) * 0.5
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=1, borderType=cv2.BORDER_REPLICATE) * 0.5
    return gx, gy


def _sample(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear ``img`` at pixels ``uv (N, 2)``."""
    m = uv.astype(np.float32).reshape(-1, 1, 2)
    return cv2.remap(img, m, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1)


@dataclass
class _Points:
    """One view's selected pixels at one level: points in the world, their intensities."""

    X_w: np.ndarray  # (N, 3)
    I: np.ndarray  # (N,)


def _select(view: View, levels: int, cfg: AlignConfig) -> list[_Points]:
    """Each level's pixels of ``view`` with known depth and the strongest gradients, in the world."""
    grey = as_grey(view.image)
    out = []
    for img, K in _pyramid(grey, view.K, levels, cfg.max_width):
        lh, lw = img.shape
        depth = cv2.resize(np.asarray(view.depth, np.float32), (lw, lh), interpolation=cv2.INTER_NEAREST)
        gx, gy = _gradients(img)
        mag = np.hypot(gx, gy)
        mag[[0, -1], :], mag[:, [0, -1]] = 0, 0
        mag[~(np.isfinite(depth) & (depth > 0))] = 0
        idx = np.argsort(mag, axis=None)[::-1][: cfg.points]
        idx = idx[mag.reshape(-1)[idx] > 0]
        v, u = np.divmod(idx, lw)
        d = depth.reshape(-1)[idx].astype(np.float64)
        rays = np.linalg.solve(K, np.stack([u, v, np.ones_like(u)]).astype(np.float64)).T
        X_c = rays * d[:, None]
        T = np.asarray(view.T_wc, np.float64)
        out.append(_Points(X_c @ T[:3, :3].T + T[:3, 3], img.reshape(-1)[idx].astype(np.float64)))
    return out


def _huber(r: np.ndarray, k: float) -> np.ndarray:
    a = np.abs(r)
    return np.where(a <= k, 0.5 * r * r, k * (a - 0.5 * k))


class _Level:
    """The residuals of all views at one pyramid level against the query's image there."""

    def __init__(self, points: list[_Points], query: np.ndarray, K_q: np.ndarray, cfg: AlignConfig) -> None:
        self.points, self.img, self.K, self.cfg = points, query, K_q, cfg
        self.gx, self.gy = _gradients(query)
        self.n = sum(len(p.I) for p in points)
        # per view: the mean cost of explaining nothing but its mean brightness, which is also
        # what each of its pixels outside the query's image costs
        self.nulls = [float(_huber(p.I - p.I.mean(), cfg.huber).mean()) if len(p.I) else 0.0 for p in points]
        self.null_cost = sum(c * len(p.I) for c, p in zip(self.nulls, points)) / max(self.n, 1)

    def evaluate(self, T_wq: np.ndarray, jacobian: bool
                 ) -> tuple[float, float, tuple[np.ndarray, np.ndarray, np.ndarray] | None]:
        """(cost, inside share, linearisation): with ``jacobian``, (J (M, 6), r (M,), IRLS
        weights (M,)) over the pixels inside the query's image, else (or with none inside) None."""
        T_qw = np.linalg.inv(T_wq)
        h, w = self.img.shape
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        k, total, inside, Js, rs, ws = self.cfg.huber, 0.0, 0, [], [], []
        for p, null in zip(self.points, self.nulls):
            X = p.X_w @ T_qw[:3, :3].T + T_qw[:3, 3]
            z = X[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                u, v = fx * X[:, 0] / z + cx, fy * X[:, 1] / z + cy
            ok = (z > 1e-9) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
            inside += int(ok.sum())
            total += null * int((~ok).sum())
            if ok.sum() < 10:
                total += null * int(ok.sum())
                continue
            X, z, uv = X[ok], z[ok], np.stack([u[ok], v[ok]], 1)
            Iq, In = _sample(self.img, uv).astype(np.float64), p.I[ok]
            # brightness In ~ a Iq + b, least squares in closed form (gain kept in [0.5, 2])
            var = float(np.var(Iq))
            cov = float(np.mean((Iq - Iq.mean()) * (In - In.mean())))
            a = float(np.clip(cov / var, 0.5, 2.0)) if var > 1e-12 else 1.0
            b = float(In.mean() - a * Iq.mean())
            r = In - a * Iq - b
            total += float(_huber(r, k).sum())
            if jacobian:
                gx, gy = _sample(self.gx, uv).astype(np.float64), _sample(self.gy, uv).astype(np.float64)
                # G = dI_q/dX_q (the image gradient through the projection); X_q moves by
                # -v + X_q x w, so dI_q/dv = -G and dI_q/dw = G x X_q (as G . (X_q x w) = w . (G x X_q));
                # r's Jacobian is -a times that
                G = np.stack([gx * fx / z, gy * fy / z, -(gx * fx * X[:, 0] + gy * fy * X[:, 1]) / z**2], 1)
                Js.append(-a * np.concatenate([-G, np.cross(G, X)], 1))
                rs.append(r)
                ws.append(np.where(np.abs(r) <= k, 1.0, k / np.maximum(np.abs(r), 1e-12)))
        lin = (np.concatenate(Js), np.concatenate(rs), np.concatenate(ws)) if Js else None
        return total / max(self.n, 1), inside / max(self.n, 1), lin


def _update(T_wq: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """``T_wq exp(delta)`` (first-order translation, exact rotation), ``delta = (v, w)``."""
    D = np.eye(4)
    D[:3, :3] = cv2.Rodrigues(delta[3:].reshape(3, 1))[0]
    D[:3, 3] = delta[:3]
    return T_wq @ D


def _lm(level: _Level, T: np.ndarray, iters: int) -> np.ndarray:
    """Levenberg-Marquardt (Marquardt's diagonal damping, IRLS Huber weights) at one level: a step
    is taken only when it lowers the cost; stops after ``iters`` steps, on a relative decrease
    under 1e-4, or when no damping finds a lower cost."""
    cost, _, lin = level.evaluate(T, jacobian=True)
    lam = 1e-3
    for _ in range(iters):
        if lin is None:
            break
        J, r, wt = lin
        H = J.T @ (J * wt[:, None])
        g = J.T @ (wt * r)
        while lam < 1e8:
            try:
                delta = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            T_new = _update(T, delta)
            new_cost = level.evaluate(T_new, jacobian=False)[0]
            if new_cost < cost:
                break
            lam *= 10
        else:
            break
        converged = cost - new_cost < 1e-4 * cost
        T, lam = T_new, max(lam / 10, 1e-6)
        cost, _, lin = level.evaluate(T, jacobian=True)
        if converged:
            break
    return T


def align_from(views: list[View], image: np.ndarray, K: np.ndarray, starts: list[np.ndarray],
               cfg: AlignConfig = AlignConfig()) -> list[AlignResult]:
    """The query's pose (``image`` RGB/grey uint8 with intrinsics ``K``) aligned to ``views``
    from each of ``starts`` (``T_wc (4, 4)``), coarse to fine; the pyramids and the views'
    pixels are built once for all starts."""
    query = _pyramid(as_grey(image), K, cfg.levels, cfg.max_width)
    selected = [_select(v, len(query), cfg) for v in views]
    levels = [_Level([s[i] for s in selected if i < len(s)], *query[i], cfg) for i in range(len(query))]
    null = levels[0].null_cost
    out = []
    for T_wc in starts:
        T = np.asarray(T_wc, np.float64)
        start = levels[0].evaluate(T, jacobian=False)[0]
        for level in reversed(levels):
            T = _lm(level, T, cfg.iters)
        cost, inside, _ = levels[0].evaluate(T, jacobian=False)
        out.append(AlignResult(T, cost, start, inside, null, bool(null > 0 and cost <= cfg.accept_ratio * null)))
    return out


def align(views: list[View], image: np.ndarray, K: np.ndarray, T_wc: np.ndarray,
          cfg: AlignConfig = AlignConfig()) -> AlignResult:
    """:func:`align_from` one start."""
    return align_from(views, image, K, [T_wc], cfg)[0]
