"""Solvers for eq. 3 and eq. 5: non-negative pose weights and a sparse change term.

Eq. 5 is ``min ||g - F w - chi||^2 + lam (||w||_1 + ||chi||_1)`` s.t. ``w >= 0`` (``chi`` free).
For fixed ``w`` the best ``chi`` is the soft-thresholding of the residual ``r = g - F w`` at
``delta = lam / 2``, and eliminating it leaves the Huber-loss non-negative lasso

    ``min_w  sum_i rho(r_i) + lam * sum(w)``,  ``rho(r) = r^2`` if ``|r| <= delta``
    else ``2 delta |r| - delta^2``,

with the same optimum (``tests/test_solve.py`` checks it against a joint FISTA solve).
Eq. 3 (no occlusion) is the same with ``rho(r) = r^2``.

:func:`active_set` solves it the way METHOD.md sec. 3 measured to be fast on this badly
conditioned problem: batched Lawson-Hanson on the pose weights.  The gradient over ALL poses
comes from one FFT adjoint per outer iteration; the most negative entries join the active set;
the small problem on the active columns (explicit columns are free: shifted slices of the
rotated stack) is solved exactly by IRLS on the Huber weights, each step an NNLS on the
Cholesky factor of the active Gram matrix.  :func:`fista` (accelerated proximal gradient on
the joint ``(w, chi)`` problem) is kept as a slow cross-check for small problems.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np
import scipy.linalg as sla
from scipy.optimize import nnls

from .operator import BlurOperator

#: Pixels per block when building explicit active columns (bounds the solver's memory).
_CHUNK = 32768

__all__ = ["active_set", "fista", "huber_objective", "joint_objective", "power_norm"]


def _rho(r: np.ndarray, delta: float | None) -> np.ndarray:
    if delta is None:
        return r * r
    a = np.abs(r)
    return np.where(a <= delta, r * r, 2.0 * delta * a - delta * delta)


def huber_objective(
    ops: Sequence[BlurOperator],
    gs: Sequence[np.ndarray],
    w: np.ndarray,
    lam: float,
    occlusion: bool = True,
    masks: Sequence[np.ndarray] | None = None,
) -> float:
    """Value of eq. 5 with ``chi`` eliminated (eq. 3 if ``occlusion`` is False)."""
    delta = lam / 2.0 if occlusion else None
    total = lam * float(np.sum(w))
    for i, (op, g) in enumerate(zip(ops, gs, strict=True)):
        m = op.valid if masks is None else masks[i]
        r = g - op.matvec(w)
        total += float(_rho(r[m], delta).sum())
    return total


def joint_objective(op, g, w, chi, lam, mask=None) -> float:
    """Value of eq. 5 for an explicit ``(w, chi)`` (on ``mask`` pixels)."""
    m = op.valid if mask is None else mask
    r = (g - op.matvec(w) - chi)[m]
    return float(np.sum(r * r) + lam * (np.abs(w).sum() + np.abs(chi[m]).sum()))


class _Window:
    """Per-window state of the active-set solver."""

    def __init__(self, op: BlurOperator, g: np.ndarray, mask: np.ndarray):
        self.op = op
        self.g = np.asarray(g, dtype=float).reshape(op.dimsd)
        self.m = np.asarray(mask, bool)
        self.m3 = np.broadcast_to(self.m[:, :, None], op.dimsd)
        self.gm = np.where(self.m3, self.g, 0.0)

    def forward(self, active: list[int], wa: np.ndarray) -> np.ndarray:
        out = np.zeros(self.op.dimsd)
        for k, v in zip(active, wa, strict=True):
            if v != 0.0:
                out += v * self.op.column(k)
        return out

    def residual(self, active: list[int], wa: np.ndarray) -> np.ndarray:
        """``M (g - A w)``: the masked residual of the active columns."""
        r = self.gm - self.forward(active, wa)
        r[~self.m3] = 0.0
        return r

    def block_products(self, cols_all: list[int], cols_new: list[int]):
        """``A_all^T M A_new`` and ``A_new^T M g`` over valid pixels, by row blocks.

        The columns of a block are copied as contiguous rows (``A^T``), so each copy is
        one contiguous write and the product one GEMM.
        """
        h, w = self.op.box.h, self.op.box.w
        C = self.op.dimsd[2]
        rows = max(1, _CHUNK // (w * C))
        n_all, n_new = len(cols_all), len(cols_new)
        G = np.zeros((n_all, n_new))
        b = np.zeros(n_new)
        buf = np.empty((n_all, rows * w * C))
        for r0 in range(0, h, rows):
            r1 = min(r0 + rows, h)
            mk = self.m[r0:r1]
            if not mk.any():
                continue
            if mk.all():
                n_pix = (r1 - r0) * w * C
                At = buf[:, :n_pix]
                for j, k in enumerate(cols_all):
                    np.copyto(At[j].reshape(r1 - r0, w, C), self.op.column(k)[r0:r1])
                gb = self.g[r0:r1].reshape(-1)
            else:
                n_pix = int(mk.sum()) * C
                At = buf[:, :n_pix]
                for j, k in enumerate(cols_all):
                    At[j] = self.op.column(k)[r0:r1][mk].ravel()
                gb = self.g[r0:r1][mk].ravel()
            Atn = At[n_all - n_new :]
            G += At @ Atn.T
            b += Atn @ gb
        return G, b


def active_set(
    ops: Sequence[BlurOperator],
    gs: Sequence[np.ndarray],
    *,
    lam: float = 0.1,
    occlusion: bool = True,
    masks: Sequence[np.ndarray] | None = None,
    batch: int = 24,
    max_outer: int = 60,
    max_irls: int = 10,
    tol: float = 1e-7,
    w0: np.ndarray | None = None,
    time_limit: float | None = None,
    callback: Callable[[np.ndarray], None] | None = None,
) -> tuple[np.ndarray, dict]:
    """Solve eq. 5 (or eq. 3) over one or more windows sharing one set of pose weights.

    Parameters
    ----------
    ops : sequence of BlurOperator
        One operator per estimation window, all on the same grid.
    gs : sequence of ndarray
        The observation in each window, shape ``op.dimsd`` (values scaled to about [0, 1]).
    lam : float
        Eq. 5's ``lambda``.  The change term is ``chi = soft(r, lam / 2)``.
    occlusion : bool
        Solve eq. 5 (True) or eq. 3 (False).
    masks : sequence of (h, w) bool arrays, optional
        Pixels that enter the data term (default: ``op.valid``).
    batch : int
        Poses added to the active set per outer iteration.
    max_outer, max_irls : int
        Iteration caps.
    tol : float
        Stop when the relative objective change of an outer iteration is below ``tol`` and
        no inactive pose has a clearly negative gradient.
    w0 : ndarray, optional
        Warm start (its non-zero poses start the active set).
    time_limit : float, optional
        Seconds; the loop stops (``converged=False``) when exceeded.
    callback : callable, optional
        Called with the full weight array after every outer iteration (observes only).

    Returns
    -------
    w : ndarray, shape ``grid.shape``
    info : dict
        ``objective`` (per outer iteration), ``n_outer``, ``n_active``, ``converged``,
        ``time_s``, ``kkt`` (most negative inactive gradient, relative).
    """
    t_start = time.perf_counter()
    grid = ops[0].grid
    P = grid.size
    delta = lam / 2.0 if occlusion else None
    wins = [
        _Window(op, g, op.valid if masks is None else masks[i])
        for i, (op, g) in enumerate(zip(ops, gs, strict=True))
    ]
    if sum(int(w.m.sum()) for w in wins) == 0:
        raise ValueError("no valid pixel to estimate the motion from")

    active: list[int] = []
    wa = np.zeros(0)
    G0 = np.zeros((0, 0))  # unweighted (mask only) Gram of active columns
    b0 = np.zeros(0)  # A^T M g
    if w0 is not None:
        nz = np.flatnonzero(np.asarray(w0).ravel() > 0)
        active = [int(k) for k in nz]
        wa = np.asarray(w0).ravel()[nz].astype(float)
        G0, b0 = _gram_add(wins, [], active, G0, b0)

    history: list[float] = []
    res: list[np.ndarray] | None = None  # residuals of (active, wa), when known
    grad_scale = None
    converged = False
    kkt = np.nan
    n_outer = 0
    for n_outer in range(1, max_outer + 1):  # noqa: B007 (reported after the loop)
        # residuals, Huber weights and the full gradient (one FFT adjoint per window)
        grad = np.full(P, lam)
        obj = lam * float(wa.sum())
        if res is None:
            res = [win.residual(active, wa) for win in wins]
        for win, r in zip(wins, res, strict=True):
            psi = 2.0 * r if delta is None else 2.0 * np.clip(r, -delta, delta)
            obj += float(_rho(r[win.m3], delta).sum())
            grad -= win.op.rmatvec(psi).ravel()
        history.append(obj)
        if grad_scale is None:
            grad_scale = max(float(np.max(np.abs(grad - lam))), 1e-300)
        cand = grad.copy()
        if active:
            cand[active] = np.inf
        kkt = float(cand.min()) / grad_scale
        small_change = (
            len(history) >= 2 and abs(history[-2] - history[-1]) <= tol * max(history[-1], 1e-300)
        )
        if kkt > -1e-6 or (small_change and kkt > -1e-3):
            converged = True
            break
        if time_limit is not None and time.perf_counter() - t_start > time_limit:
            break
        order = np.argsort(cand)[:batch]
        new = [int(k) for k in order if cand[k] < 0]
        G0, b0 = _gram_add(wins, active, new, G0, b0)
        active = active + new
        wa = np.concatenate([wa, np.zeros(len(new))])
        # new columns enter at weight zero: the residuals are unchanged
        wa, res = _irls(wins, active, wa, G0, b0, lam, delta, max_irls, res)
        keep = wa > 0
        if not keep.all():
            idx = np.flatnonzero(keep)
            active = [active[i] for i in idx]
            wa, G0, b0 = wa[idx], G0[np.ix_(idx, idx)], b0[idx]
        if callback is not None:
            callback(_full(grid, active, wa))

    w = _full(grid, active, wa)
    info = dict(
        objective=history,
        n_outer=n_outer,
        n_active=len(active),
        converged=converged,
        kkt=kkt,
        time_s=time.perf_counter() - t_start,
        solver="active-set",
    )
    return w, info


def _full(grid, active, wa) -> np.ndarray:
    w = np.zeros(grid.size)
    if active:
        w[active] = wa
    return w.reshape(grid.shape)


def _gram_add(wins, active, new, G0, b0):
    """Grow the cached Gram matrix and ``A^T M g`` by the columns ``new``."""
    if not new:
        return G0, b0
    cols = active + new
    k, kn = len(active), len(new)
    Gn = np.zeros((k + kn, kn))
    bn = np.zeros(kn)
    for win in wins:
        G, b = win.block_products(cols, new)
        Gn += G
        bn += b
    out = np.zeros((k + kn, k + kn))
    out[:k, :k] = G0
    out[:, k:] = Gn
    out[k:, :] = Gn.T
    return out, np.concatenate([b0, bn])


def _nnls_gram(G: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``argmin_{w >= 0} 1/2 w^T G w - b^T w`` via NNLS on the Cholesky factor of ``G``."""
    k = G.shape[0]
    ridge = 1e-12 * max(float(np.trace(G)) / max(k, 1), 1e-300)
    L = None
    for _ in range(8):
        try:
            L = np.linalg.cholesky(G + ridge * np.eye(k))
            break
        except np.linalg.LinAlgError:
            ridge *= 100.0
    if L is None:
        raise np.linalg.LinAlgError("Gram matrix of the active poses is not positive definite")
    z = sla.solve_triangular(L, b, lower=True)
    w, _ = nnls(L.T, z, maxiter=50 * k + 100)
    return w


def _irls(wins, active, wa, G0, b0, lam, delta, max_irls, res=None):
    """Exact Huber NNLS on the active columns by IRLS (each step an exact weighted NNLS).

    The weighted Gram ``A^T D A`` is the cached ``A^T M A`` minus a correction over the
    outlier pixels only (``|r| > delta``, weight ``delta / |r| < 1``): few pixels, cheap.
    ``res`` (optional) are the residuals of ``wa``.  Returns the new weights and their
    residuals when they were computed (else None), so the caller need not recompute them.
    """
    prev = np.inf
    exact = False  # ``wa`` solves the problem of a step without outliers
    for _ in range(max_irls):
        if res is None:
            res = [win.residual(active, wa) for win in wins]
        G = G0.copy()
        b = b0 - lam / 2.0
        obj = lam * float(wa.sum())
        n_out = 0
        for win, r in zip(wins, res, strict=True):
            obj += float(_rho(r[win.m3], delta).sum())
            if delta is None:
                continue
            out = np.abs(r) > delta
            if not out.any():
                continue
            n_out += 1
            rows_all, cols_all, chans_all = np.nonzero(out)
            for c0 in range(0, rows_all.size, _CHUNK):  # bounded memory
                rows = rows_all[c0 : c0 + _CHUNK]
                cols = cols_all[c0 : c0 + _CHUNK]
                chans = chans_all[c0 : c0 + _CHUNK]
                om = 1.0 - delta / np.abs(r[rows, cols, chans])  # 1 - omega
                sel = np.arange(rows.size)
                A = np.stack([win.op.gather(k, rows, cols)[sel, chans] for k in active], axis=1)
                Aw = A * om[:, None]
                G -= A.T @ Aw
                b -= Aw.T @ win.g[rows, cols, chans]
        if exact and n_out == 0:
            break  # the least-squares step had no outlier and its result has none: optimal
        if prev - obj <= 1e-6 * max(obj, 1e-300) and np.isfinite(prev):
            break
        prev = obj
        wa = _nnls_gram(G, b)
        res = None
        exact = n_out == 0
        if delta is None:
            break
    return wa, res


def power_norm(op: BlurOperator, n_iter: int = 30, rng=None) -> float:
    """Estimate ``||F||_2^2`` (largest eigenvalue of ``F^T F``) by power iteration."""
    rng = np.random.default_rng(rng)
    x = rng.random(op.grid.shape)
    x /= np.linalg.norm(x)
    lam = 0.0
    for _ in range(n_iter):
        y = op.rmatvec(op.matvec(x))
        lam = float(np.linalg.norm(y))
        x = y / max(lam, 1e-300)
    return lam


def fista(
    op: BlurOperator,
    g: np.ndarray,
    *,
    lam: float = 0.1,
    n_iter: int = 500,
    tol: float = 0.0,
    mask: np.ndarray | None = None,
    callback: Callable[[np.ndarray, np.ndarray], None] | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Accelerated proximal gradient (FISTA) on the joint eq. 5 in ``(w, chi)``.

    ``min ||g - F w - chi||^2 + lam (||w||_1 + ||chi||_1)``, ``w >= 0``: the paper's solver
    (SLEP).  Step ``1 / L`` with ``L = 2 (||F||^2 + 1)`` from :func:`power_norm`.  Slow on this
    badly conditioned problem (METHOD.md sec. 3): a cross-check for small problems.

    Returns
    -------
    w : ndarray, ``grid.shape``
    chi : ndarray, ``op.dimsd`` (zero outside ``mask``)
    info : dict with ``objective`` history and ``n_iter``.
    """
    m = op.valid if mask is None else np.asarray(mask, bool)
    m3 = np.broadcast_to(m[:, :, None], op.dimsd)
    g = np.where(m3, np.asarray(g, dtype=float).reshape(op.dimsd), 0.0)
    L = 2.0 * (power_norm(op) + 1.0) * 1.01
    step = 1.0 / L
    w = np.zeros(op.grid.shape)
    chi = np.zeros(op.dimsd)
    yw, yc = w.copy(), chi.copy()
    t = 1.0
    hist = []
    for it in range(n_iter):
        r = np.where(m3, g - op.matvec(yw) - yc, 0.0)
        gw = -2.0 * op.rmatvec(r)
        gc = -2.0 * r
        w_new = np.maximum(yw - step * gw - step * lam, 0.0)
        v = yc - step * gc
        chi_new = np.where(m3, np.sign(v) * np.maximum(np.abs(v) - step * lam, 0.0), 0.0)
        t_new = (1.0 + np.sqrt(1.0 + 4.0 * t * t)) / 2.0
        yw = w_new + (t - 1.0) / t_new * (w_new - w)
        yc = chi_new + (t - 1.0) / t_new * (chi_new - chi)
        w, chi, t = w_new, chi_new, t_new
        hist.append(joint_objective(op, g, w, chi, lam, m))
        if callback is not None:
            callback(w, chi)
        if tol and it > 0 and abs(hist[-2] - hist[-1]) <= tol * hist[-1]:
            break
    return w, chi, dict(objective=hist, n_iter=len(hist), solver="fista")
