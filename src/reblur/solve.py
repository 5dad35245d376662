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
over every outlier pixel).  Several windows share the weights: every step sums their
parts, and with ``workers`` threads each thread computes the parts of a group of windows
(``_Windows``).  :func:`fista` (accelerated proximal gradient on the joint ``(w, chi)``
problem) is kept as a slow cross-check for small problems.
"""

from __future__ import annotations

import time
import weakref
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack

import numpy as np
import scipy.linalg as sla
from scipy.optimize import nnls
from threadpoolctl import threadpool_limits

from ._memory import parts
from .operator import BlurOperator

#: Pixel scale of the gathers' blocks (:meth:`_Window.repartition`: ``8 * _CHUNK`` values).
_CHUNK = 32768
#: Pixels per row block of the Gram products, in every window (bounds the solver's
#: memory: one block of the active columns per window solved at once).  It was 32768
#: shared by the windows solved in parallel, so the blocks' rows, and the products'
#: rounding, changed with the number of cores (GoPro 0477 / 16 frames flagged 2.22 % on
#: one core and 2.02 % on two); 16384 is the share two windows had.
_SLOT_CHUNK = 16384
#: Share of valid pixels from which a row block of the Gram products copies all of its
#: pixels (the masked ones then add zeros) rather than gathering the valid ones: a gather
#: by boolean mask costs ~4x a plain copy per pixel (10 against 2.5-3 ns per column and
#: pixel on the 1 MP cost pairs, whose windows are a few per cent invalid or excluded).
_DENSE_BLOCK = 0.3
#: New columns from which a Gram growth computes their symmetric new-by-new block by SYRK
#: (numpy's ``X @ X.T``, half the arithmetic) apart from the old-by-new GEMM.  Single
#: thread, 16000-pixel blocks, this machine's OpenBLAS (0.3.31, SkylakeX; ``python -m
#: benchmarks.gram_work``, ``split_times``): 126 new columns against 640 take 54.5 ms split
#: against 58.8 ms in one GEMM, 96 against 200 10.8 / 13.0 ms; for few new columns the
#: second call costs more than it saves (24 against 164: 3.6 / 3.5 ms).  A warm start (no
#: old columns) is one SYRK either way: 572 columns 83 ms, against 154 ms for the GEMMs of
#: 48 new columns each it replaced.
_SYRK_FROM = 64
#: Share of a warm start's valid pixels, at most, whose partition may differ from that of
#: the Gram matrix a :class:`Scratch` carries for the same operators (:class:`_Carry`) for
#: the solve to start from that matrix: its update over a changed pixel costs one
#: ``k x k`` outer product, a fresh Gram half of one per pixel (SYRK).
_CARRY_CHANGED = 0.5

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
    Windows processed one after the other share it; windows processed in parallel threads
    (``active_set(workers=)``) use one buffer per thread (``slot``), each for blocks of
    :data:`_SLOT_CHUNK` pixels.  A caller that solves several related problems (the levels
    of a coarse-to-fine schedule, photometric refits) can pass the same ``Scratch`` to
    each: the buffer then grows a few times in all instead of once per window and call,
    and a solve warm-started on the operators of the last one starts from the inlier Gram
    that one ended with (:class:`_Carry`).
    Fresh memory is not free: its pages fault in on first touch, which on some virtual
    machines costs more than the products themselves (2-7 ms per MB on the benchmark
    machine, varying with its host, against 0.1 ms for pages the host still backs:
    ``python -m benchmarks.first_touch``).
    """

    def __init__(self) -> None:
        self._bufs: dict[int, np.ndarray] = {}
        #: the last solve's inlier Gram (see :class:`_Carry`)
        self.carry = _Carry()

    def take(self, n: int, slot: int = 0) -> np.ndarray:
        """A float64 array of ``n`` elements (contents undefined), valid until the next call
        with the same ``slot`` (windows solved in parallel each use their group's slot)."""
        buf = self._bufs.get(slot, np.empty(0))
        if buf.size < n:
            buf = self._bufs[slot] = np.empty(max(int(n), 3 * buf.size // 2))
        return buf[:n]

    @property
    def nbytes(self) -> int:
        return int(sum(b.nbytes for b in self._bufs.values()))


class _Carry:
    """The inlier Gram ``A^T D A`` a solve ended with, its poses and its windows'
    partition, for the next solve on the same operators.

    A photometric round (:func:`reblur.estimate._refit_photometry`) solves again on the
    same windows and operators, against the observation less an offset, from the weights
    found.  Its warm start's Gram matrix over a few hundred poses was the largest product
    of the round, while an offset small against the Huber threshold moves few pixels
    across it (a large one, a first round far from the offset, moves most: the matrix is
    then computed afresh).  ``python -m benchmarks.gram_work --one REF OBS``, the 1 MP
    defocus pair: 135.7 -> 116.9 GMAC in the whole estimate.  The carried matrix,
    restricted to the warm start's poses and updated over the pixels whose partition
    differs, is the same sum in another order; ``A^T D g`` and ``A^T s`` are computed
    afresh (one pass over the columns, no products between them).  Operators are held by
    weak references: a level's stacks and spectra go with the level.
    """

    def __init__(self) -> None:
        self.key: tuple | None = None
        self.active: list[int] = []
        self.G = np.zeros((0, 0))
        # per window: its mask, its polarities (or None) and the outlier signs held
        self.parts: list[tuple[np.ndarray, np.ndarray | None, np.ndarray]] = []
        self.used = 0  # warm starts that started from a carried matrix (for the tests)

    @staticmethod
    def _key(ops, step: int, delta) -> tuple | None:
        try:
            return (tuple(weakref.ref(op) for op in ops), int(step), delta)
        except TypeError:  # an operator without weak references: nothing is carried
            return None

    def keep(self, key: tuple | None, ws, active: list[int], G: np.ndarray) -> None:
        """Hold ``G`` over ``active`` and the windows' partition (copies)."""
        self.key = key
        self.active = list(active) if key is not None else []
        self.G = G.copy() if key is not None else np.zeros((0, 0))
        self.parts = ([] if key is None else
                      [(w.m.copy(), None if w.s is None else w.s.copy(), w.sgn.copy())
                       for w in ws.wins])

    def matches(self, key: tuple | None, ws) -> bool:
        """Whether the held matrix belongs to these operators, masks and polarities."""
        if key is None or self.key is None or len(key[0]) != len(self.key[0]):
            return False
        if key[1:] != self.key[1:] or any(a() is None or a() is not b()
                                          for a, b in zip(self.key[0], key[0], strict=True)):
            return False
        for w, (m, sg, _) in zip(ws.wins, self.parts, strict=True):
            if not np.array_equal(w.m, m):
                return False
            if (w.s is None) != (sg is None) or (sg is not None and not np.array_equal(w.s, sg)):
                return False
        return True

    def start(self, key: tuple | None, ws, active: list[int], res):
        """``G, b, d`` of the warm start ``active`` (the windows already in the partition
        of their residuals ``res``) from the held matrix, or None where it does not apply:
        other operators, a pose it does not hold, or too many pixels moved."""
        if not active or not self.matches(key, ws):
            return None
        where = {k: i for i, k in enumerate(self.active)}
        if any(k not in where for k in active):
            return None
        moved = sum(int(np.count_nonzero(w.sgn != sg)) for w, (_, _, sg)
                    in zip(ws.wins, self.parts, strict=True))
        if moved > _CARRY_CHANGED * sum(int(np.count_nonzero(w.m3)) for w in ws.wins):
            return None
        idx = np.array([where[k] for k in active])
        G = self.G[np.ix_(idx, idx)]

        def move(win, r, sg):
            # back to the held partition, then to that of ``r``: the Gram's update over
            # the pixels that differ (its b, d parts are for the old g: recomputed below)
            win.sgn = sg.copy()
            win.inl = win.m3 & (sg == 0)
            upd = win.repartition(r, active)[1]
            return None if upd is None else upd[0], *win.rhs(active)

        out = ws.map(move, res, [sg for _, _, sg in self.parts])
        b, d = np.zeros(len(active)), np.zeros(len(active))
        for dG, bw, dw in out:  # window order: independent of the threads' timing
            if dG is not None:
                G = G + dG
            b, d = b + bw, d + dw
        self.used += 1
        return G, b, d


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
        self.slot = 0  # this window's buffer in the shared scratch (set by _Windows)
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
        """Inlier mask and outlier signs of the residual ``r``.  The inliers are the
        mask's pixels of sign 0 (an outlier's residual is beyond ``delta >= 0``, so not
        0): the solver keeps ``inl == m3 & (sgn == 0)`` for every partition it holds."""
        sgn = self.signs(r)
        return self.m3 & (sgn == 0), sgn

    def signs(self, r: np.ndarray) -> np.ndarray:
        """Outlier signs of the residual ``r`` (int8; 0: inlier or off the mask)."""
        out = self.outliers(r)
        if out is None:
            return np.zeros(self.op.dimsd, np.int8)
        return np.where(out, np.sign(r), 0).astype(np.int8)

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
        copied as contiguous rows (``A^T``), so each copy is one contiguous write, and the
        product is one GEMM, or from :data:`_SYRK_FROM` new columns one GEMM of the old
        columns against the new ones and one SYRK of the new ones against themselves.

        An operator whose columns vanish outside row ranges (the band model of
        :class:`reblur.rolling.RollingOperator`) may say so with ``row_breaks`` (rows at
        which the blocks are cut) and ``column_rows(k)`` (the rows ``[r0, r1)`` where
        column ``k`` may be non-zero): a block then copies and multiplies only the columns
        that reach it, and the products of the others stay zero, which they are.
        """
        h, w, C = self.op.dimsd
        # a fixed block height, whatever the number of windows solved at once: the blocks'
        # products are summed block by block, so their rows decide the rounding, which
        # must not depend on the machine's cores (see _SLOT_CHUNK)
        rows = max(1, _SLOT_CHUNK // (w * C))
        n_all, n_new = len(cols_all), len(cols_new)
        G = np.zeros((n_all, n_new))
        b = np.zeros(n_new)
        d = np.zeros(n_new)
        # one buffer shared by the windows (and the calls that share the Scratch), grown
        # geometrically with the active set: a fresh one per call is a fresh mmap whose
        # pages fault in on first touch (slow on this kind of VM)
        buf = self.scratch.take(n_all * rows * w * C, self.slot).reshape(n_all, rows * w * C)
        views = [self.op.column(k) for k in cols_all]
        spans = None
        cuts = set(range(0, h, rows)) | {h}
        if hasattr(self.op, "column_rows"):
            spans = np.array([self.op.column_rows(k) for k in cols_all]).reshape(-1, 2)
            cuts |= {int(c) for c in self.op.row_breaks if 0 < c < h}
        cuts = sorted(cuts)
        for r0, r1 in zip(cuts[:-1], cuts[1:], strict=True):
            mk = self.m[r0:r1]
            if not mk.any():
                continue
            live = None
            if spans is not None:
                reach = (spans[:, 0] < r1) & (spans[:, 1] > r0)
                if not reach[n_all - n_new:].any():
                    continue
                if not reach.all():
                    live = np.flatnonzero(reach)
            if live is None:
                self._block(views, n_new, r0, r1, mk, buf, G, b, d)
                continue
            # the columns that reach the block: their products, added in place
            lv_new = live[live >= n_all - n_new]
            Gs = np.zeros((live.size, lv_new.size))
            bs, ds = np.zeros(lv_new.size), np.zeros(lv_new.size)
            self._block([views[j] for j in live], lv_new.size, r0, r1, mk, buf, Gs, bs, ds)
            G[np.ix_(live, lv_new - (n_all - n_new))] += Gs
            b[lv_new - (n_all - n_new)] += bs
            d[lv_new - (n_all - n_new)] += ds
        return G, b, d

    def _block(self, views, n_new: int, r0: int, r1: int, mk: np.ndarray, buf: np.ndarray,
               G: np.ndarray, b: np.ndarray, d: np.ndarray) -> None:
        """Add one row block's products of ``views`` (the last ``n_new`` of them new) to
        ``G``, ``b`` and ``d`` (see :meth:`block_products`)."""
        C = self.op.dimsd[2]
        n_all = len(views)
        if mk.mean() >= _DENSE_BLOCK:
            # every pixel of the block, the masked ones included: they are outside the
            # inlier set (``inl``) and carry no sign, so the new columns are zeroed there
            # below and add nothing; ``gm`` is ``g`` zeroed off the mask (no NaN)
            At = _copy_rows(views, r0, r1, buf, self.op.dimsd[1:])
            gb = self.gm[r0:r1].reshape(-1)
            ib = self.inl[r0:r1].reshape(-1)
            sb = self.sgn[r0:r1].reshape(-1)
        else:
            n_pix = int(mk.sum()) * C
            At = buf[:n_all, :n_pix]
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
        n_old = n_all - n_new
        if n_old and n_new >= _SYRK_FROM:
            G[:n_old] += At[:n_old] @ Atn.T
            # a matrix times its own transpose: numpy calls SYRK (the block comes symmetric)
            G[n_old:] += Atn @ Atn.T
        else:  # one GEMM (without old columns, At is Atn: numpy calls SYRK)
            G += At @ Atn.T
        b += Atn @ gb

    def rhs(self, cols: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """``A^T D g`` and ``A^T s`` over the columns ``cols`` for the current partition
        (by the row blocks of :meth:`block_products`, without their products between
        columns)."""
        h, w, C = self.op.dimsd
        rows = max(1, _SLOT_CHUNK // (w * C))
        n = len(cols)
        b, d = np.zeros(n), np.zeros(n)
        buf = self.scratch.take(n * rows * w * C, self.slot).reshape(n, rows * w * C)
        views = [self.op.column(k) for k in cols]
        dg = np.where(self.inl, self.g, 0.0)
        for r0 in range(0, h, rows):
            r1 = min(h, r0 + rows)
            if not self.m[r0:r1].any():
                continue
            At = _copy_rows(views, r0, r1, buf, (w, C))
            b += At @ dg[r0:r1].reshape(-1)
            sb = self.sgn[r0:r1].reshape(-1)
            if sb.any():
                d += At @ sb.astype(float)
        return b, d

    def repartition(self, r: np.ndarray, active: list[int]):
        """Move to the partition of ``r``.  Returns the number of pixels that change and
        the changes they make to the cached ``G, b, d`` (None when none changes)."""
        if self.delta is None:
            return 0, None
        # the partition is its signs (see partition): a pixel changes with its sign
        sgn = self.signs(r)
        changed = sgn != self.sgn
        if not changed.any():
            return 0, None
        inl = self.m3 & (sgn == 0)
        k = len(active)
        G, b, d = np.zeros((k, k)), np.zeros(k), np.zeros(k)
        rows_all, cols_all, chans_all = np.nonzero(changed)
        n = rows_all.size
        step = max(1, _CHUNK * 8 // max(k, 1))  # bounded gather memory
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
        return n, (G, b, d)


def _copy_rows(views, r0: int, r1: int, buf: np.ndarray, row: tuple[int, int]) -> np.ndarray:
    """Rows ``r0:r1`` of the column images ``views`` (rows of shape ``row = (w, C)``),
    each copied into one row of ``buf`` (one contiguous write per column): the
    ``(len(views), pixels)`` block of ``A^T``."""
    At = buf[: len(views), : (r1 - r0) * row[0] * row[1]]
    for j, v in enumerate(views):
        np.copyto(At[j].reshape(r1 - r0, *row), v[r0:r1])
    return At


class _Windows:
    """The windows of one :func:`active_set` call and how their work runs.

    With ``workers > 1`` and several windows, the windows are cut into ``workers``
    contiguous groups, one thread each, and every per-window step (residuals, adjoints,
    Gram products, line-search sums, repartitions) runs in those threads; their results
    are summed in window order, so the solve does not depend on the thread timing; every
    operator's own products (:attr:`BlurOperator.threads`) then run on one thread: the
    windows are the parallel work.  BLAS runs on one thread in every case: its threaded
    sums round with the number of threads, and the solve must not depend on the cores
    (``tests/test_solve.py``: one thread or two, the same weights bit for bit).
    """

    def __init__(self, wins: list[_Window], workers: int = 1):
        self.wins = wins
        n = max(1, min(int(workers), len(wins)))
        self.groups = parts(list(range(len(wins))), n)
        for slot, grp in enumerate(self.groups):
            for i in grp:
                wins[i].slot = slot
        self._stack = ExitStack()
        self._ex = None

    def __enter__(self) -> _Windows:
        # BLAS on one thread whatever the groups: OpenBLAS splits the long sums of some
        # products (a Gram block's few columns over thousands of pixels) across its
        # threads, so their rounding would change with the machine's cores
        self._stack.enter_context(threadpool_limits(1, user_api="blas"))
        if len(self.groups) > 1:
            try:
                self._ex = self._stack.enter_context(ThreadPoolExecutor(len(self.groups)))
                saved = [w.op.threads for w in self.wins]
                self._stack.callback(_restore_threads, self.wins, saved)
                for w in self.wins:
                    w.op.threads = 1
            except BaseException:
                self._stack.close()
                raise
        return self

    def __exit__(self, *exc) -> None:
        self._stack.close()

    def map(self, fn: Callable, *seqs) -> list:
        """``[fn(win, *items) for win, *items in zip(wins, *seqs)]``, by groups."""
        args = list(zip(self.wins, *seqs, strict=True))
        if self._ex is None:
            return [fn(*a) for a in args]

        def run(grp):
            return [fn(*args[i]) for i in grp]

        out: list = []
        for res in self._ex.map(run, self.groups):
            out.extend(res)
        return out


def _restore_threads(wins, saved) -> None:
    for w, t in zip(wins, saved, strict=True):
        w.op.threads = t


def check_max_active(max_active) -> None:
    """Raise ``ValueError`` unless ``max_active`` is None or an integer >= 1."""
    if max_active is not None and (isinstance(max_active, bool)
                                   or not isinstance(max_active, (int, np.integer))
                                   or max_active < 1):
        raise ValueError(f"max_active must be an integer >= 1 or None, got {max_active!r}")


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
    rtol: float = 0.0,
    w0: np.ndarray | None = None,
    time_limit: float | None = None,
    callback: Callable[[np.ndarray], None] | None = None,
    scratch: Scratch | None = None,
    workers: int = 1,
    row_step: int = 1,
    max_active: int | None = None,
    pixel_weight: float = 1.0,
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
    rtol : float
        Stop when an outer iteration lowered the objective by less than ``rtol`` of its
        value, whatever the gradient says (``info["stalled"]``): the poses it added no
        longer pay.  On a pair the model fits, the last outer iterations lower it by
        ~1e-3 and the KKT test ends the loop anyway; on windows the model does not fit
        (mostly change, content years apart) the weights spread over hundreds of poses,
        each outer iteration costing more than the last for a gain of 1e-4 to 1e-6, for
        tens of iterations.  0 (default): the KKT test and ``tol`` only.
    w0 : ndarray, optional
        Warm start (its non-zero poses start the active set).
    time_limit : float, optional
        Seconds; the loop stops (``converged=False``) when exceeded.
    callback : callable, optional
        Called with the full weight array after every outer iteration (observes only).
    scratch : Scratch, optional
        Work memory to reuse (e.g. across the levels of a coarse-to-fine schedule); default
        a fresh one, shared by the windows of this call.
    workers : int
        Threads over the windows: with several windows, each thread solves the per-window
        steps of a contiguous group of them, BLAS and the operators' products then running
        one thread each (the result does not depend on it beyond rounding).  1 (default):
        the windows one after the other, each product using the threads BLAS and the
        operator have.
    row_step : int
        Fit every ``row_step``-th row of each window only (:meth:`BlurOperator.rows`;
        ``gs``, ``masks`` and ``signs`` are given whole and restricted here), the weights'
        l1 term divided by ``row_step``: the data term of the rows kept, times
        ``row_step``, estimates that of the whole window without bias, so the objective
        minimised estimates eq. 5's at ``1 / row_step`` of the products' cost.  The
        objective is reported in the whole window's units (times ``row_step``).  1
        (default): every row.
    max_active : int, optional
        Poses the active set may hold, at most (None, the default: no bound).  An outer
        iteration adds no more poses than leave room under it; once it has filled the
        bound, the loop stops at the next outer iteration that does not meet the KKT test
        (``info["capped"]``), with the weights optimal over the poses it holds.  The Gram
        products grow as the square of the active poses and the Newton steps' NNLS as
        their cube, so the bound caps a solve's cost whatever the blur; a warm start
        holding more poses keeps them (the bound limits growth only).
    pixel_weight : float
        How many pixels of the problem each pixel fitted stands for (>= 1): 4 for the
        2 x 2 block means of a half-resolution level.  As with ``row_step``, the weights'
        l1 term is divided by it (the Huber threshold, a property of each pixel, stays
        ``lam / 2``) and the objective reported multiplied by it, so the balance of the
        two terms, and objectives compared across resolutions, are those of the problem
        at full resolution.  1 (default).

    Returns
    -------
    w : ndarray, shape ``grid.shape``
    info : dict
        ``objective`` (per outer iteration), ``n_outer``, ``n_active``, ``converged``,
        ``stalled`` (stopped by ``rtol``), ``capped`` (stopped by ``max_active``),
        ``time_s``, ``kkt`` (most negative inactive
        gradient, relative to ``kkt_scale``:
        the largest gradient of the data term at ``w = 0``, the same whether the solve
        starts cold or from ``w0``); from ``w0``, ``warm_start``: its non-zero poses
        (``poses``) and those still non-zero once its own weights are optimised, before
        any pose is added (``kept``), and ``carried`` (True) when it started from the
        Gram matrix the last solve on the same operators left in ``scratch``.
    """
    t_start = time.perf_counter()
    grid = ops[0].grid
    delta = lam / 2.0 if occlusion else None
    scratch = Scratch() if scratch is None else scratch
    step = int(row_step)
    if step < 1:
        raise ValueError(f"row_step must be at least 1, got {row_step}")
    if isinstance(pixel_weight, bool) or not (
            isinstance(pixel_weight, (int, float, np.number)) and 1 <= pixel_weight < np.inf):
        raise ValueError(f"pixel_weight must be a finite number >= 1, got {pixel_weight!r}")
    units = step * float(pixel_weight)  # problem pixels per pixel fitted
    check_max_active(max_active)
    if step > 1:
        gs = [np.ascontiguousarray(np.asarray(g, dtype=float).reshape(op.dimsd)[::step])
              for op, g in zip(ops, gs, strict=True)]
        masks = None if masks is None else [np.asarray(m, bool)[::step] for m in masks]
        signs = None if signs is None else [
            None if s is None else np.asarray(s, float).reshape(op.dimsd)[::step]
            for op, s in zip(ops, signs, strict=True)]
    key = _Carry._key(ops, step, delta)  # the caller's operators, before any row view
    if step > 1:
        ops = [op.rows(step) for op in ops]
    wins = [
        _Window(op, g, op.valid if masks is None else masks[i], delta,
                None if signs is None else signs[i], scratch)
        for i, (op, g) in enumerate(zip(ops, gs, strict=True))
    ]
    if sum(int(w.m.sum()) for w in wins) == 0:
        raise ValueError("no valid pixel to estimate the motion from")
    with _Windows(wins, workers) as ws:
        # the l1 term over the sampled data term: lam / units (the Huber threshold, a
        # property of each pixel, stays lam / 2)
        w, info = _active_set(ws, grid, lam / units, batch, max_outer, max_irls, tol, w0,
                              time_limit, callback, t_start, rtol, max_active,
                              carry=(scratch.carry, key))
    if units != 1:
        info["objective"] = [units * v for v in info["objective"]]
    if step > 1:
        info["row_step"] = step
    return w, info


def _active_set(ws, grid, lam, batch, max_outer, max_irls, tol, w0, time_limit, callback,
                t_start, rtol=0.0, max_active=None, carry=None):
    """The loop of :func:`active_set` over the windows ``ws`` (a :class:`_Windows`);
    ``lam`` is the weights' l1 coefficient (the windows hold the Huber threshold).
    ``carry``: a :class:`_Carry` and the key of these operators: a warm start starts from
    its matrix where it applies, and the solve leaves its own there."""
    held, key = (None, None) if carry is None else carry
    P = grid.size

    active: list[int] = []
    wa = np.zeros(0)
    # cached over the active columns, for the windows' current partition (see _Window)
    G = np.zeros((0, 0))  # A^T D A
    b = np.zeros(0)  # A^T D g
    d = np.zeros(0)  # A^T s
    res: list[np.ndarray] | None = None  # residuals of (active, wa), when known
    grad_scale = None  # the KKT test's scale (see below)
    carried = False  # the warm start's Gram came from ``carry``
    if w0 is not None:
        nz = np.flatnonzero(np.asarray(w0).ravel() > 0)
        active = [int(k) for k in nz]
        wa = np.asarray(w0).ravel()[nz].astype(float)

        def start(win):  # the warm start's residual, and its partition to start from
            r = win.residual(active, wa)
            win.inl, win.sgn = win.partition(r)
            return r

        res = ws.map(start)
        out = None if held is None else held.start(key, ws, active, res)
        carried = out is not None
        G, b, d = _gram_add(ws, [], active, G, b, d) if out is None else out
        # the KKT test's scale is the data term's gradient at w = 0, as a cold start has it
        # at its first iteration: a property of the problem, not of the start (scaled by
        # a warm start's own gradient, a better warm start made the test stricter)
        grad_scale = _scale_at_zero(ws)
    # (a cold start keeps the all-inlier partition: its first step is least squares)

    history: list[float] = []
    converged = False
    stalled = False
    capped = False  # stopped by max_active
    full = False  # an outer iteration filled max_active: no pose may enter after it
    kkt = np.nan
    n_outer = 0
    n_newton = 0
    warm: dict[str, int] | None = None
    if active:
        # optimise the warm start's weights first: the KKT test below looks at the inactive
        # poses only, and a warm start from other data (a coarser level, other windows, a
        # corrected observation) would otherwise pass it unchanged
        wa, res, n_newton, G, b, d = _huber_newton(ws, active, wa, res, G, b, d, lam,
                                                   max_irls)
        keep = wa > 0
        warm = dict(poses=len(active), kept=int(keep.sum()))
        if carried:
            warm["carried"] = True
        if not keep.all():
            idx = np.flatnonzero(keep)
            active = [active[i] for i in idx]
            wa, G, b, d = wa[idx], G[np.ix_(idx, idx)], b[idx], d[idx]

    for n_outer in range(1, max_outer + 1):  # noqa: B007 (reported after the loop)
        # residuals, Huber weights and the full gradient (one FFT adjoint per window)
        grad = np.full(P, lam)
        obj = lam * float(wa.sum())

        def adjoint(win, r, active=active, wa=wa):
            if r is None:
                r = win.residual(active, wa)
            return r, win.loss(r), win.op.rmatvec(win.psi(r)).ravel()

        out = ws.map(adjoint, [None] * len(ws.wins) if res is None else res)
        res = [o[0] for o in out]
        for _, loss, gw in out:
            obj += loss
            grad -= gw
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
        if rtol > 0 and len(history) >= 2 and history[-2] - history[-1] < rtol * abs(history[-1]):
            stalled = True
            break
        if time_limit is not None and time.perf_counter() - t_start > time_limit:
            break
        if full:
            capped = True
            break
        order = np.argsort(cand)[: max(batch, len(active) // 4)]
        new = [int(k) for k in order if cand[k] < 0]
        if max_active is not None and len(active) + len(new) >= max_active:
            new = new[: max(0, max_active - len(active))]
            full = True
            if not new:
                capped = True
                break
        G, b, d = _gram_add(ws, active, new, G, b, d)
        active = active + new
        # new columns enter at weight zero: the residuals are unchanged
        wa = np.concatenate([wa, np.zeros(len(new))])
        wa, res, steps, G, b, d = _huber_newton(ws, active, wa, res, G, b, d, lam, max_irls)
        n_newton += steps
        keep = wa > 0
        if not keep.all():
            idx = np.flatnonzero(keep)
            active = [active[i] for i in idx]
            wa, G, b, d = wa[idx], G[np.ix_(idx, idx)], b[idx], d[idx]
        if callback is not None:
            callback(_full(grid, active, wa))

    if held is not None:
        held.keep(key, ws, active, G)
    w = _full(grid, active, wa)
    info = dict(
        objective=history,
        n_outer=n_outer,
        n_active=len(active),
        n_newton=n_newton,
        converged=converged,
        stalled=stalled,
        capped=capped,
        kkt=kkt,
        kkt_scale=grad_scale,
        time_s=time.perf_counter() - t_start,
        solver="active-set",
    )
    if warm is not None:
        info["warm_start"] = warm
    return w, info


def _scale_at_zero(ws) -> float:
    """``max |F^T psi(g)|`` over the poses: the data term's gradient at ``w = 0`` (one
    adjoint per window, summed in window order)."""
    parts = ws.map(lambda win: win.op.rmatvec(win.psi(win.gm)).ravel())
    return max(float(np.max(np.abs(np.sum(parts, axis=0)))), 1e-300)


def _full(grid, active, wa) -> np.ndarray:
    w = np.zeros(grid.size)
    if active:
        w[active] = wa
    return w.reshape(grid.shape)


def _gram_add(ws, active, new, G, b, d):
    """Grow the cached ``A^T D A``, ``A^T D g`` and ``A^T s`` by the columns ``new``
    (the windows ``ws``' products, summed in window order)."""
    if not new:
        return G, b, d
    cols = active + new
    k, kn = len(active), len(new)
    Gn = np.zeros((k + kn, kn))
    bn = np.zeros(kn)
    dn = np.zeros(kn)
    for Gw, bw, dw in ws.map(lambda win: win.block_products(cols, new)):
        Gn += Gw
        bn += bw
        dn += dw
    out = np.zeros((k + kn, k + kn))
    out[:k, :k] = G
    out[:, k:] = Gn
    out[k:, :] = Gn.T
    return out, np.concatenate([b, bn]), np.concatenate([d, dn])


#: Non-zero sets :func:`_nnls_exchange` tries before scipy's NNLS.  On the 1 MP test-bed
#: tilt, the defocus pair and GoPro 0477 / 16 frames (397 solves of 24-640 poses; ``python
#: -m benchmarks.nnls_exchange``) every exchange ended within 11 sets, the median within 3.
_EXCHANGES = 12


def _nnls_gram(G: np.ndarray, b: np.ndarray, support: np.ndarray | None = None) -> np.ndarray:
    """``argmin_{w >= 0} 1/2 w^T G w - b^T w`` via NNLS on the Cholesky factor of ``G``;
    first from the guess ``support`` of the solution's non-zero set (:func:`_nnls_exchange`)
    when one is given."""
    k = G.shape[0]
    ridge = 1e-12 * max(float(np.trace(G)) / max(k, 1), 1e-300)
    if support is not None:
        w = _nnls_exchange(G, b, ridge, support)
        if w is not None:
            return w
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


def _nnls_exchange(G: np.ndarray, b: np.ndarray, ridge: float,
                   support: np.ndarray) -> np.ndarray | None:
    """The minimiser of :func:`_nnls_gram`'s problem (``G + ridge I``) by block principal
    pivoting from the non-zero set ``support``, or None after :data:`_EXCHANGES` sets.

    Each set's unconstrained minimiser (one Cholesky of its block) is the solution when
    it is positive on the set and the gradient keeps every other weight at 0: the KKT
    conditions, which only the minimiser of a strictly convex problem meets, so a returned
    point is the NNLS solution up to rounding (``python -m benchmarks.nnls_exchange``: the
    same non-zero sets as scipy's, weights within 4e-9 of the largest).  Otherwise the
    next set drops the weights that came out non-positive and takes in those whose
    gradient asks for weight (the full exchange of Kim & Park's block principal pivoting;
    it may cycle, hence the bound and the caller's NNLS).  The active set's Newton steps
    start from all of their columns, the new ones at 0, then from the last solution's
    set, which a step that moves only the Huber partition keeps: one Cholesky.  scipy's
    NNLS (Lawson-Hanson) takes a column in or out per iteration: on the 1 MP tilt pair its
    227 solves took 2.74 s, the exchanges 0.54 s.
    """
    P = np.asarray(support, bool).copy()
    for _ in range(_EXCHANGES):
        idx = np.flatnonzero(P)
        if idx.size == 0:
            return None
        try:
            c = sla.cho_factor(G[np.ix_(idx, idx)] + ridge * np.eye(idx.size), lower=True,
                               check_finite=False)
        except np.linalg.LinAlgError:
            return None
        wP = sla.cho_solve(c, b[idx], check_finite=False)
        if not np.isfinite(wP).all():  # a block that rounds to singular
            return None
        grad = b - G[:, idx] @ wP  # minus the gradient, off the set
        grad[idx] = 0.0
        pos = wP > 0.0
        up = grad > 0.0
        if pos.all() and not up.any():
            w = np.zeros(G.shape[0])
            w[idx] = wP
            return w
        P[idx[~pos]] = False
        P |= up
    return None


class _Slope:
    """One window's share of the line search's ``phi'(t)`` and ``phi''(t)`` on [0, 1].

    ``r - t D`` is linear in ``t`` and each piece of the loss (inlier; outlier of either
    sign) is an interval of the residual, so a pixel in the same piece at ``t = 0`` and
    ``t = 1`` stays in it throughout: those pixels' shares are fixed sums, computed once
    (inliers ``-2 (sum r D - t sum D^2)``, outliers ``-2 delta sum sign D``), and only the
    pixels that change piece on the way (few, near the optimum) are evaluated at each
    ``t``.  ``r`` and ``D`` are zero off the window's mask.
    """

    def __init__(self, win, r: np.ndarray, D: np.ndarray):
        self.delta = win.delta
        if win.delta is None:  # squared loss: every pixel an inlier
            self.rd, self.dd, self.cs = float(np.vdot(r, D)), float(np.vdot(D, D)), 0.0
            self.idx = None
            return
        p0 = _piece(win, r)
        p1 = _piece(win, r - D)
        same = p0 == p1
        Dm = np.where(same & (p0 == 0), D, 0.0)
        self.rd, self.dd = float(np.vdot(r, Dm)), float(np.vdot(Dm, Dm))
        self.cs = float(np.vdot(np.where(same, p0, 0.0), D))
        idx = np.flatnonzero(~same)
        self.idx = idx
        self.r, self.D = r.reshape(-1)[idx], D.reshape(-1)[idx]
        sg = getattr(win, "s", None)
        self.s = None if sg is None else np.asarray(sg).reshape(-1)[idx]

    def at(self, t: float) -> tuple[float, float]:
        """This window's share of the slope at ``t`` and of its derivative."""
        s = -2.0 * (self.rd - t * self.dd)
        c = 2.0 * self.dd
        if self.delta is None:
            return s, c
        s -= 2.0 * self.delta * self.cs
        if self.idx.size:
            rt = self.r - t * self.D
            out = (np.abs(rt) if self.s is None else self.s * rt) > self.delta
            psi = np.where(out, 2.0 * self.delta * np.sign(rt), 2.0 * rt)
            Di = np.where(out, 0.0, self.D)
            s -= float(np.vdot(psi, self.D))
            c += 2.0 * float(np.vdot(Di, Di))
        return s, c


def _piece(win, r: np.ndarray) -> np.ndarray:
    """The loss's piece at every pixel of ``r``: 0 inlier (or off the mask), the sign of
    ``r`` where an outlier."""
    return np.where(win.outliers(r), np.sign(r), 0.0)


def _line_search(ws, res, deltas, dw_sum, lam, iters: int = 40) -> float:
    """Exact step ``t`` in [0, 1] minimising the (convex) objective along a direction.

    ``phi(t) = lam * t * dw_sum + sum loss(r - t D)`` (plus constants).  Its derivative is
    non-decreasing and piecewise linear (the Huber loss is piecewise quadratic), with
    slope ``2 sum D^2`` over the inlier pixels, so Newton's step from the lower end of a
    bracket of its sign change lands on the root once in the root's linear piece; a step
    outside the bracket is replaced by the secant of the bracket, and a step that does not
    halve the bracket is followed by a bisection.  A few evaluations reach what ``iters``
    bisections give (the root to ``2^-iters``, or a slope ``1e-10`` of the start's).  Each
    window's pixels are read in full once (:class:`_Slope`); the evaluations then visit
    only the pixels that change piece between ``t = 0`` and ``t = 1``.
    """
    parts = ws.map(_Slope, res, deltas)

    def slope(t: float) -> tuple[float, float]:
        s, c = lam * dw_sum, 0.0
        for p in parts:  # in window order
            ds, dc = p.at(t)
            s += ds
            c += dc
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


def _unbounded(G: np.ndarray, c: np.ndarray) -> bool:
    """Whether the partition's quadratic model has no minimiser: a weight whose columns
    meet no inlier pixel (no curvature) while its outlier pixels ask for more of it (``c >
    0``).  Every pixel an outlier does that: a warm start far from the data (a photometric
    refit's offset step, say)."""
    flat = np.diag(G) <= 0.0
    return bool(np.any(c[flat] > 0.0))


def _all_inliers(ws, active, res, G, b, d):
    """Move every window to the all-inlier partition, a cold start's (its Newton step is
    least squares); the cached ``G, b, d`` updated over the pixels that change."""
    moved = ws.map(lambda win, r: win.repartition(np.zeros_like(r), active), res)
    return _updated(G, b, d, [upd for _, upd in moved])


def _updated(G, b, d, upds):
    """``G, b, d`` plus the windows' repartition changes ``upds`` (None: no change), added
    in window order: independent of the threads' timing."""
    for upd in upds:
        if upd is not None:
            G, b, d = G + upd[0], b + upd[1], d + upd[2]
    return G, b, d


def _huber_newton(ws, active, wa, res, G, b, d, lam, max_steps):
    """Exact Huber NNLS on the active columns: a finite Newton method on the partition.

    For the current partition (inliers quadratic, outliers linear with their sign) the
    objective is a quadratic whose gradient equals the true one at ``wa``; its
    non-negative minimiser (NNLS on the Cholesky factor of the cached inlier Gram) gives a
    descent direction, an exact line search the step, and the partition then moves to
    that of the new residuals, updating the cache over the pixels that changed only.  It
    stops at a full step that changes no pixel: the exact optimum.  A partition whose
    model has no minimiser (:func:`_unbounded`) gives way, for that step, to the
    all-inlier one of a cold start (least squares; the line search still follows the true
    objective): from a warm start that left every pixel an outlier, Newton's step was
    infinite and the solve stalled at its start.  Returns the weights,
    their residuals, the number of steps and the updated ``G, b, d``.
    """
    steps = 0
    # every column: the positive ones and those just taken in at 0 (the solver drops a
    # column whose weight falls to 0), then the last solution's
    support = np.ones(len(active), bool)
    for steps in range(1, max_steps + 1):  # noqa: B007
        delta = ws.wins[0].delta
        if delta is not None and _unbounded(G, b + delta * d - lam / 2.0):
            G, b, d = _all_inliers(ws, active, res, G, b, d)
        c = b - lam / 2.0 if delta is None else b + delta * d - lam / 2.0
        wq = _nnls_gram(G, c, support)
        support = wq > 0.0
        dw = wq - wa
        if not np.any(dw):
            break

        def direction(win, dw=dw):
            D = win.forward(active, dw)
            D[~win.m3] = 0.0
            return D

        deltas = ws.map(direction)
        t = _line_search(ws, res, deltas, float(dw.sum()), lam)
        if t <= 0.0:
            break
        wa = np.maximum(wa + t * dw, 0.0) if t < 1.0 else wq

        def step(win, r, D, t=t):
            r = r - t * D
            return (r, *win.repartition(r, active))

        out = ws.map(step, res, deltas)
        res = [o[0] for o in out]
        n_changed = sum(n for _, n, _ in out)
        G, b, d = _updated(G, b, d, [upd for _, _, upd in out])
        if n_changed == 0 and t == 1.0:
            break
    return wa, res, steps, G, b, d


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
