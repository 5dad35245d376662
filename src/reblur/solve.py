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
rotated stack) is solved exactly by a finite Newton method on the Huber partition (inliers
quadratic, outliers linear): each step an NNLS on the Cholesky factor of the cached inlier
Gram matrix plus an exact line search, the cache updated over the pixels that change
partition only -- so a window that is mostly change costs about what a clean one does
(an IRLS on the Huber weights, used before, rebuilt the outlier correction at every step,
over every outlier pixel).  :func:`fista` (accelerated proximal gradient on the joint
``(w, chi)`` problem) is kept as a slow cross-check for small problems.
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
#: New columns per GEMM when many enter the Gram at once (a warm start): the products
#: then skip the lower triangle of the symmetric new-by-new block, all but a group's
#: diagonal block (a warm start of 260 poses: 60 % of the full product's arithmetic).
#: OpenBLAS's SYRK did the same job slower than the full GEMM (docs/NOTES.md).
_TRI_GROUP = 48

__all__ = ["Scratch", "active_set", "fista", "huber_objective", "joint_objective", "power_norm"]


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


class Scratch:
    """Scratch memory of :func:`active_set`, reusable across windows and calls.

    The Gram products copy the active columns of a row block into one float64 buffer.
    Windows are processed one after the other, so they can share it, and a caller that
    solves several related problems (the levels of a coarse-to-fine schedule, photometric
    refits) can pass the same ``Scratch`` to each: the buffer then grows a few times in
    all instead of once per window and call.  Fresh memory is not free: its pages fault in
    on first touch, which on some virtual machines costs more than the products
    themselves (2-7 ms per MB on the benchmark machine, varying with its host, against
    0.1 ms for pages the host still backs: ``python -m benchmarks.first_touch``).
    """

    def __init__(self) -> None:
        self._buf = np.empty(0)

    def take(self, n: int) -> np.ndarray:
        """A float64 array of ``n`` elements (contents undefined), valid until the next call."""
        if self._buf.size < n:
            self._buf = np.empty(max(int(n), 3 * self._buf.size // 2))
        return self._buf[:n]

    @property
    def nbytes(self) -> int:
        return int(self._buf.nbytes)


class _Window:
    """Per-window state of the active-set solver.

    The Huber loss is handled by a *partition* of the valid pixels: inliers (``|r| <=
    delta``, quadratic) and outliers with their sign (linear).  The solver caches, for the
    active columns ``A``, the inlier Gram ``A^T D A``, ``A^T D g`` and ``A^T s`` (``D`` the
    inlier indicator, ``s`` the outlier signs) and updates them over the pixels that change
    partition only.
    """

    def __init__(self, op: BlurOperator, g: np.ndarray, mask: np.ndarray,
                 delta: float | None, signs: np.ndarray | None = None,
                 scratch: Scratch | None = None):
        self.op = op
        self.delta = delta
        self.g = np.asarray(g, dtype=float).reshape(op.dimsd)
        self.m = np.asarray(mask, bool)
        self.m3 = np.broadcast_to(self.m[:, :, None], op.dimsd)
        self.gm = np.where(self.m3, self.g, 0.0)
        # allowed polarity of the change term (one-sided Huber); None: either
        self.s = None if signs is None else np.asarray(signs, float).reshape(op.dimsd)
        self.inl = self.m3.copy()  # inlier pixels of the current partition
        self.sgn = np.zeros(op.dimsd, np.int8)  # outlier signs (0: inlier or masked)
        self.scratch = Scratch() if scratch is None else scratch  # block_products' copies

    def forward(self, active: list[int], wa: np.ndarray) -> np.ndarray:
        return self.op.combine(active, wa)

    def residual(self, active: list[int], wa: np.ndarray) -> np.ndarray:
        """``M (g - A w)``: the masked residual of the active columns."""
        r = self.gm - self.forward(active, wa)
        r[~self.m3] = 0.0
        return r

    def outliers(self, r: np.ndarray) -> np.ndarray | None:
        """Pixels of ``r`` in the linear part of the loss (None: no Huber term)."""
        if self.delta is None:
            return None
        if self.s is None:
            return self.m3 & (np.abs(r) > self.delta)
        return self.m3 & (self.s * r > self.delta)

    def partition(self, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Inlier mask and outlier signs of the residual ``r``."""
        out = self.outliers(r)
        if out is None:
            return self.m3.copy(), np.zeros(self.op.dimsd, np.int8)
        return self.m3 & ~out, np.where(out, np.sign(r), 0).astype(np.int8)

    def loss(self, r: np.ndarray) -> float:
        """Data term of the objective at residual ``r`` (valid pixels)."""
        out = self.outliers(r)
        if out is None:
            return float(np.sum(r[self.m3] ** 2))
        d = self.delta
        return float(np.where(out, 2.0 * d * np.abs(r) - d * d, r * r)[self.m3].sum())

    def psi(self, r: np.ndarray) -> np.ndarray:
        """Derivative of the loss with respect to ``r`` (0 off the mask)."""
        out = self.outliers(r)
        v = 2.0 * r if out is None else np.where(out, 2.0 * self.delta * np.sign(r), 2.0 * r)
        return np.where(self.m3, v, 0.0)

    def block_products(self, cols_all: list[int], cols_new: list[int]):
        """``A_all^T D A_new``, ``A_new^T D g`` and ``A_new^T s`` by row blocks.

        ``cols_new`` are the last columns of ``cols_all``.  The columns of a block are
        copied as contiguous rows (``A^T``), so each copy is one contiguous write and the
        product one GEMM -- or, for many new columns, one GEMM per group of
        :data:`_TRI_GROUP` of them over the rows up to that group's end: the new-by-new
        block is symmetric, so only its upper triangle (and the groups' diagonal blocks)
        is computed, and the rest of it is left zero (:func:`_gram_add` mirrors it).
        """
        h, w = self.op.box.h, self.op.box.w
        C = self.op.dimsd[2]
        rows = max(1, _CHUNK // (w * C))
        n_all, n_new = len(cols_all), len(cols_new)
        G = np.zeros((n_all, n_new))
        b = np.zeros(n_new)
        d = np.zeros(n_new)
        # one buffer shared by the windows (and the calls that share the Scratch), grown
        # geometrically with the active set: a fresh one per call is a fresh mmap whose
        # pages fault in on first touch (slow on this kind of VM)
        buf = self.scratch.take(n_all * rows * w * C).reshape(n_all, rows * w * C)
        views = [self.op.column(k) for k in cols_all]
        for r0 in range(0, h, rows):
            r1 = min(r0 + rows, h)
            mk = self.m[r0:r1]
            if not mk.any():
                continue
            if mk.all():
                n_pix = (r1 - r0) * w * C
                At = buf[:, :n_pix]
                for j, v in enumerate(views):
                    np.copyto(At[j].reshape(r1 - r0, w, C), v[r0:r1])
                gb = self.g[r0:r1].reshape(-1)
                ib = self.inl[r0:r1].reshape(-1)
                sb = self.sgn[r0:r1].reshape(-1)
            else:
                n_pix = int(mk.sum()) * C
                At = buf[:, :n_pix]
                for j, v in enumerate(views):
                    At[j] = v[r0:r1][mk].ravel()
                gb = self.g[r0:r1][mk].ravel()
                ib = self.inl[r0:r1][mk].ravel()
                sb = self.sgn[r0:r1][mk].ravel()
            Atn = At[n_all - n_new :]
            if sb.any():
                d += Atn @ sb.astype(float)
            if not ib.all():
                # zero the new columns' outlier pixels in place (the block is a fresh copy):
                # D A_new, and D^2 = D makes the new-by-new part A_new^T D A_new as well
                Atn[:, ~ib] = 0.0
            if n_new <= 2 * _TRI_GROUP:
                G += At @ Atn.T
            else:
                n_old = n_all - n_new
                for s0 in range(0, n_new, _TRI_GROUP):
                    s1 = min(s0 + _TRI_GROUP, n_new)
                    G[: n_old + s1, s0:s1] += At[: n_old + s1] @ Atn[s0:s1].T
            b += Atn @ gb
        return G, b, d

    def repartition(self, r: np.ndarray, active: list[int],
                    G: np.ndarray, b: np.ndarray, d: np.ndarray) -> int:
        """Move to the partition of ``r``, updating ``G, b, d`` in place over the pixels
        that change.  Returns their number."""
        if self.delta is None:
            return 0
        inl, sgn = self.partition(r)
        changed = (inl != self.inl) | (sgn != self.sgn)
        if not changed.any():
            return 0
        rows_all, cols_all, chans_all = np.nonzero(changed)
        n = rows_all.size
        step = max(1, _CHUNK * 8 // max(len(active), 1))  # bounded gather memory
        for c0 in range(0, n, step):
            rows = rows_all[c0 : c0 + step]
            cols = cols_all[c0 : c0 + step]
            chans = chans_all[c0 : c0 + step]
            A = self.op.gather_many(active, rows, cols, chans)
            di = (inl[rows, cols, chans].astype(float)
                  - self.inl[rows, cols, chans].astype(float))
            ds = (sgn[rows, cols, chans].astype(float)
                  - self.sgn[rows, cols, chans].astype(float))
            Ad = A * di[:, None]
            G += A.T @ Ad
            b += Ad.T @ self.g[rows, cols, chans]
            d += A.T @ ds
        self.inl, self.sgn = inl, sgn
        return n


def active_set(
    ops: Sequence[BlurOperator],
    gs: Sequence[np.ndarray],
    *,
    lam: float = 0.1,
    occlusion: bool = True,
    masks: Sequence[np.ndarray] | None = None,
    signs: Sequence[np.ndarray | None] | None = None,
    batch: int = 24,
    max_outer: int = 60,
    max_irls: int = 10,
    tol: float = 1e-7,
    w0: np.ndarray | None = None,
    time_limit: float | None = None,
    callback: Callable[[np.ndarray], None] | None = None,
    scratch: Scratch | None = None,
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
    signs : sequence of ``op.dimsd`` arrays (or None), optional
        Allowed polarity of the change term per pixel and band: ``+1``, ``-1`` or ``0``
        (no change term there).  The loss is then one-sided: linear only where
        ``signs * r > lam / 2``.  None (default): either polarity everywhere (eq. 5).
    batch : int
        Poses added to the active set per outer iteration, at most, or a quarter of the
        active set when that is more.  Every outer iteration costs one adjoint per window
        over the whole grid and a copy of the active columns for the Gram update, so a
        large active set (a warm start of a few hundred poses) grows in few, large steps,
        while a small one is not flooded with poses it drops again.
    max_outer : int
        Outer iterations (active-set growth) at most.
    max_irls : int
        Huber Newton steps per outer iteration at most (the name is historical: the
        steps were IRLS steps).
    tol : float
        Stop when the relative objective change of an outer iteration is below ``tol`` and
        no inactive pose has a clearly negative gradient.
    w0 : ndarray, optional
        Warm start (its non-zero poses start the active set).
    time_limit : float, optional
        Seconds; the loop stops (``converged=False``) when exceeded.
    callback : callable, optional
        Called with the full weight array after every outer iteration (observes only).
    scratch : Scratch, optional
        Work memory to reuse (e.g. across the levels of a coarse-to-fine schedule); default
        a fresh one, shared by the windows of this call.

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
    scratch = Scratch() if scratch is None else scratch
    wins = [
        _Window(op, g, op.valid if masks is None else masks[i], delta,
                None if signs is None else signs[i], scratch)
        for i, (op, g) in enumerate(zip(ops, gs, strict=True))
    ]
    if sum(int(w.m.sum()) for w in wins) == 0:
        raise ValueError("no valid pixel to estimate the motion from")

    active: list[int] = []
    wa = np.zeros(0)
    # cached over the active columns, for the windows' current partition (see _Window)
    G = np.zeros((0, 0))  # A^T D A
    b = np.zeros(0)  # A^T D g
    d = np.zeros(0)  # A^T s
    res: list[np.ndarray] | None = None  # residuals of (active, wa), when known
    if w0 is not None:
        nz = np.flatnonzero(np.asarray(w0).ravel() > 0)
        active = [int(k) for k in nz]
        wa = np.asarray(w0).ravel()[nz].astype(float)
        res = [win.residual(active, wa) for win in wins]
        for win, r in zip(wins, res, strict=True):  # start from the warm start's partition
            win.inl, win.sgn = win.partition(r)
        G, b, d = _gram_add(wins, [], active, G, b, d)
    # (a cold start keeps the all-inlier partition: its first step is least squares)

    history: list[float] = []
    grad_scale = None
    converged = False
    kkt = np.nan
    n_outer = 0
    n_newton = 0
    if active:
        # optimise the warm start's weights first: the KKT test below looks at the inactive
        # poses only, and a warm start from other data (a coarser level, other windows, a
        # corrected observation) would otherwise pass it unchanged
        wa, res, n_newton = _huber_newton(wins, active, wa, res, G, b, d, lam, max_irls)
        keep = wa > 0
        if not keep.all():
            idx = np.flatnonzero(keep)
            active = [active[i] for i in idx]
            wa, G, b, d = wa[idx], G[np.ix_(idx, idx)], b[idx], d[idx]

    for n_outer in range(1, max_outer + 1):  # noqa: B007 (reported after the loop)
        # residuals, Huber weights and the full gradient (one FFT adjoint per window)
        grad = np.full(P, lam)
        obj = lam * float(wa.sum())
        if res is None:
            res = [win.residual(active, wa) for win in wins]
        for win, r in zip(wins, res, strict=True):
            obj += win.loss(r)
            grad -= win.op.rmatvec(win.psi(r)).ravel()
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
        order = np.argsort(cand)[: max(batch, len(active) // 4)]
        new = [int(k) for k in order if cand[k] < 0]
        G, b, d = _gram_add(wins, active, new, G, b, d)
        active = active + new
        # new columns enter at weight zero: the residuals are unchanged
        wa = np.concatenate([wa, np.zeros(len(new))])
        wa, res, steps = _huber_newton(wins, active, wa, res, G, b, d, lam, max_irls)
        n_newton += steps
        keep = wa > 0
        if not keep.all():
            idx = np.flatnonzero(keep)
            active = [active[i] for i in idx]
            wa, G, b, d = wa[idx], G[np.ix_(idx, idx)], b[idx], d[idx]
        if callback is not None:
            callback(_full(grid, active, wa))

    w = _full(grid, active, wa)
    info = dict(
        objective=history,
        n_outer=n_outer,
        n_active=len(active),
        n_newton=n_newton,
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


def _gram_add(wins, active, new, G, b, d):
    """Grow the cached ``A^T D A``, ``A^T D g`` and ``A^T s`` by the columns ``new``."""
    if not new:
        return G, b, d
    cols = active + new
    k, kn = len(active), len(new)
    Gn = np.zeros((k + kn, kn))
    bn = np.zeros(kn)
    dn = np.zeros(kn)
    for win in wins:
        Gw, bw, dw = win.block_products(cols, new)
        Gn += Gw
        bn += bw
        dn += dw
    if kn > 2 * _TRI_GROUP:  # the new-by-new block came as its upper triangle
        N = np.triu(Gn[k:])
        Gn[k:] = N + np.triu(N, 1).T
    out = np.zeros((k + kn, k + kn))
    out[:k, :k] = G
    out[:, k:] = Gn
    out[k:, :] = Gn.T
    return out, np.concatenate([b, bn]), np.concatenate([d, dn])


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


def _line_search(wins, res, deltas, dw_sum, lam, iters: int = 40) -> float:
    """Exact step ``t`` in [0, 1] minimising the (convex) objective along a direction.

    ``phi(t) = lam * t * dw_sum + sum loss(r - t D)`` (plus constants).  Its derivative is
    non-decreasing and piecewise linear (the Huber loss is piecewise quadratic), with
    slope ``2 sum D^2`` over the inlier pixels, so Newton's step from the lower end of a
    bracket of its sign change lands on the root once in the root's linear piece; a step
    outside the bracket is replaced by the secant of the bracket, and a step that does not
    halve the bracket is followed by a bisection.  A few evaluations reach what ``iters``
    bisections give (the root to ``2^-iters``, or a slope ``1e-10`` of the start's).
    """

    def slope(t: float) -> tuple[float, float]:
        s, c = lam * dw_sum, 0.0
        for win, r, D in zip(wins, res, deltas, strict=True):
            rt = r - t * D
            out = win.outliers(rt)
            if out is None:
                s -= 2.0 * float(np.vdot(rt, D))  # D is 0 off the mask
                c += 2.0 * float(np.vdot(D, D))
                continue
            psi = np.where(out, 2.0 * win.delta * np.sign(rt), 2.0 * rt)
            s -= float(np.vdot(psi, D))
            Di = np.where(out, 0.0, D)
            c += 2.0 * float(np.vdot(Di, Di))
        return s, c

    s_hi, _ = slope(1.0)
    if s_hi <= 0.0:
        return 1.0
    lo, hi = 0.0, 1.0
    s_lo, c_lo = slope(0.0)
    if s_lo >= 0.0:
        return 0.0
    tol = 1e-10 * abs(s_lo)
    width = hi - lo
    bisect = False
    for _ in range(2 * iters):
        if hi - lo <= 2.0**-iters:
            break
        if bisect:
            t = 0.5 * (lo + hi)
        else:
            t = lo - s_lo / c_lo if c_lo > 0.0 else hi
            if not lo < t < hi:
                t = lo - s_lo * (hi - lo) / (s_hi - s_lo)
            if not lo < t < hi:
                t = 0.5 * (lo + hi)
        s_t, c_t = slope(t)
        if abs(s_t) <= tol:
            return t
        if s_t < 0.0:
            lo, s_lo, c_lo = t, s_t, c_t
        else:
            hi, s_hi = t, s_t
        bisect = not bisect and (hi - lo) > 0.5 * width
        width = hi - lo
    return lo


def _huber_newton(wins, active, wa, res, G, b, d, lam, max_steps):
    """Exact Huber NNLS on the active columns: a finite Newton method on the partition.

    For the current partition (inliers quadratic, outliers linear with their sign) the
    objective is a quadratic whose gradient equals the true one at ``wa``; its
    non-negative minimiser (NNLS on the Cholesky factor of the cached inlier Gram) gives a
    descent direction, an exact line search the step, and the partition then moves to
    that of the new residuals, updating the cache over the pixels that changed only.  It
    stops at a full step that changes no pixel: the exact optimum.  ``G, b, d`` are
    updated in place.  Returns the weights, their residuals and the number of steps.
    """
    steps = 0
    for steps in range(1, max_steps + 1):  # noqa: B007
        delta = wins[0].delta
        c = b - lam / 2.0 if delta is None else b + delta * d - lam / 2.0
        wq = _nnls_gram(G, c)
        dw = wq - wa
        if not np.any(dw):
            break
        deltas = [win.forward(active, dw) for win in wins]
        for win, D in zip(wins, deltas, strict=True):
            D[~win.m3] = 0.0
        t = _line_search(wins, res, deltas, float(dw.sum()), lam)
        if t <= 0.0:
            break
        wa = np.maximum(wa + t * dw, 0.0) if t < 1.0 else wq
        res = [r - t * D for r, D in zip(res, deltas, strict=True)]
        n_changed = sum(
            win.repartition(r, active, G, b, d) for win, r in zip(wins, res, strict=True)
        )
        if n_changed == 0 and t == 1.0:
            break
    return wa, res, steps


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
