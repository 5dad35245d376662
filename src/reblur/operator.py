"""The matrix-free blur operator ``F`` of eq. 1-5: pose weights -> blurred observation window.

``F w = sum_k w_k warp(f, H_k)`` restricted to an observation window.  ``F`` is never stored:

* ``engine="exact"``: one OpenCV homography warp per pose (any grid).  The reference
  implementation.
* ``engine="fast"`` (grids with whole-pixel translations): the reference is warped once per
  *base* pose (rotation / scale / tilt) onto the window grown by the translation range; the
  column of pose ``(b, ty, tx)`` is then that image shifted by ``(tx, ty)``.  ``F w`` is, per
  base, a convolution with the ``len(ty) x len(tx)`` translation kernel and ``F^T r`` a
  cross-correlation at the translation lags: both by ``scipy.fft`` with the spectra of the
  warped stack, computed once, on first use (for an operator restricted to every k-th row,
  :meth:`BlurOperator.rows`, the adjoint correlates the kept rows with each row phase of
  the stack, whose spectra are computed once too).  The adjoint of convolution is
  correlation with the same kernel.

Boundary handling: the window of the observation is fixed; every pose reads the reference
pixels it needs from a larger reference window (read once).  Pixels for which some pose would
read outside the reference are *unknown*: :attr:`BlurOperator.valid` is False there and the
solver ignores them; they are never treated as "no change".
"""

from __future__ import annotations

import copy
import threading

import cv2
import numpy as np
import scipy.fft as sfft

from ._memory import available_cpus, opencv_single, split_sum, thread_map
from ._memory import zeros as _zeros
from .grid import PoseGrid
from .warp import Box, as_box, read_window, source_box, warp_window

__all__ = ["BlurOperator", "dottest"]

#: Bytes of cross spectra per block in :meth:`BlurOperator.rmatvec` (fits a shared L3).
_BLOCK_BYTES = 16 * 2**20

#: :meth:`BlurOperator.matvec` sums columns while there are at most this many weighted
#: poses per base angle with weight: a 400 x 400 column costs ~0.1 ms, a base's share of
#: the spectral product (its kernel's transform and product) ~1.5 ms on 2 cores.
_COLUMNS_PER_BASE = 8

#: ... and while there are at most this many per base angle of the grid when the spectra
#: are not computed yet (they are computed on first use: a base's spectra cost about 25
#: columns, 2.6 / 0.1 ms on a 500 px window, one thread).
_COLUMNS_PER_COLD_BASE = 24

#: :meth:`BlurOperator.combine` splits sums of at least this many column pixels across
#: threads (smaller ones cost less than the threads' start) ...
_PARALLEL_SUM = 2**22
#: ... into this many parts, whatever the number of threads: the parts' sums are added in
#: order, so the result does not depend on the machine's cores.
SUM_PARTS = 4

#: :meth:`BlurOperator.combine` (fast engine) sums this many float32 columns in single
#: precision before adding them into the working-precision result: the error bound then
#: stays ``(_SINGLE_RUN + 1)`` float32 unit roundoffs of the terms whatever the number of
#: poses.
_SINGLE_RUN = 16


def _channels(reference) -> int:
    return int(reference.shape[2]) if len(reference.shape) == 3 else 1


class BlurOperator:
    """Matrix-free ``F`` (and ``F^T``) for one observation window.

    Parameters
    ----------
    reference : array-like, (H, W) or (H, W, C)
        Full reference image (numpy, zarr, ...); only the needed window is read.
    grid : PoseGrid
        Pose grid (defined on the FULL observation image geometry).
    box : Box or (y0, x0, h, w)
        Observation window, full-image coordinates.
    base : (3, 3) ndarray, optional
        Coarse alignment homography (reference -> observation) applied before every pose.
    engine : {"auto", "fast", "exact"}
        ``auto`` picks ``fast`` when the grid's translations are whole pixels.
    dtype : numpy dtype
        Working precision of the warped stack and FFTs (float64 default).
    spectra : bool
        Spectral products (dense ``matvec``, ``rmatvec``) on the fast engine; the FFT
        spectra they use are computed on first use (:attr:`spec`, and per row phase for a
        :meth:`rows` view).  False: sums of columns and explicit inner products only.
    spectra_precision : {"single", "double"}
        Precision of the spectra.  ``"single"`` (default) computes them from the float32
        stack in single precision and stores them as complex64; ``rmatvec``'s products
        with them are single precision too (twice as fast), while ``matvec``'s stay in the
        working precision.  ``"double"`` computes, stores and uses them in the working
        precision.  The spectra are the operator's largest memory (twice the float32 stack
        in complex128), and on a virtual machine whose fresh pages fault in slowly, their
        first touch was a large share of a gigapixel estimate (docs/NOTES.md, "Memory of
        the estimate").  ``rmatvec``'s error relative to ``|F^T r|`` is ~4e-7 (~2e-7 from
        the rounded spectra alone): relative to the current residual, which is small near
        the optimum, so far below the solver's KKT tolerance (1e-6 of the gradient's
        scale).  ``matvec`` and ``rmatvec`` stay adjoints of each other to that rounding.
    scale : float
        Reference values are divided by ``scale`` (e.g. 255 for uint8 data).
    threads : int, optional
        Threads of the products: :meth:`combine`'s large sums and the FFTs (default: the
        CPUs available).  An attribute: a caller that runs several operators in parallel
        threads sets it to 1 for the time (:func:`reblur.solve.active_set`).

    Attributes
    ----------
    shape : (int, int)
        ``(n_pixels * n_bands, n_poses)``.
    dimsd : (int, int, int)
        Output image shape ``(h, w, C)``.
    valid : (h, w) bool ndarray
        Pixels where every pose of the grid reads real reference pixels.
    row_step : int
        1, or the step of the window's rows the operator is restricted to (see
        :meth:`rows`): its outputs, inputs of the adjoint and :attr:`valid` then hold
        rows ``0, row_step, 2 row_step, ...`` of the window only.

    Raises
    ------
    ValueError
        ``engine="fast"`` with non-integer translations, or an empty window.
    """

    def __init__(
        self,
        reference,
        grid: PoseGrid,
        box,
        *,
        base: np.ndarray | None = None,
        engine: str = "auto",
        dtype=np.float64,
        spectra: bool = True,
        scale: float = 1.0,
        spectra_precision: str = "single",
        threads: int | None = None,
    ):
        self.grid = grid
        self.box = as_box(box)
        self.base = np.eye(3) if base is None else np.asarray(base, dtype=float)
        if engine == "auto":
            engine = "fast" if grid.integer_translations else "exact"
        if engine not in ("fast", "exact"):
            raise ValueError(f"engine must be 'auto', 'fast' or 'exact', got {engine!r}")
        if engine == "fast" and not grid.integer_translations:
            raise ValueError("the fast engine needs whole-pixel translations in the grid")
        if spectra_precision not in ("single", "double"):
            raise ValueError(
                f"spectra_precision must be 'single' or 'double', got {spectra_precision!r}"
            )
        self.spectra_precision = spectra_precision
        self.threads = available_cpus() if threads is None else max(1, int(threads))
        self.engine = engine
        self.reference = reference
        self.dtype = np.dtype(dtype)
        self.scale = float(scale)
        C = _channels(reference)
        h, w = self.box.h, self.box.w
        self.dimsd = (h, w, C)
        self.shape = (h * w * C, grid.size)
        self.row_step = 1
        # spectra, computed on first use and shared with the row-restricted views
        # (:meth:`rows`): ``"full"`` for the window, ``("rows", k)`` per row phase
        self._cache: dict = {}
        self._spectral = engine == "fast" and bool(spectra)
        self._tx = np.asarray(grid.tx)
        self._ty = np.asarray(grid.ty)
        self._n_tx = len(grid.tx)
        self._n_t = len(grid.ty) * len(grid.tx)
        if engine == "fast":
            self._build_fast(spectra)
        else:
            self._build_exact()

    # ------------------------------------------------------------------ construction
    def _base_h(self, b: int) -> np.ndarray:
        return self.grid.base_homography(b) @ self.base

    def _build_fast(self, spectra: bool) -> None:
        tx = self._tx.astype(int)
        ty = self._ty.astype(int)
        self.txmax, self.txmin = int(tx.max()), int(tx.min())
        self.tymax, self.tymin = int(ty.max()), int(ty.min())
        self.Dx, self.Dy = self.txmax - self.txmin, self.tymax - self.tymin
        # column (b, t) at window pixel u reads ext[u + tmax - t]
        self.ext = self.box.grow(self.tymax, -self.tymin, self.txmax, -self.txmin)
        nb = self.grid.n_bases
        Hs = [self._base_h(b) for b in range(nb)]
        # the stack is allocated at the FFT size and every base is warped onto a whole
        # plane of it (``ext`` grown to the FFT size): the warps write it in place, in
        # OpenCV's threads, and its spectra need no padded copy.  The pixels beyond ``ext``
        # are never read: the columns are views into ``ext``, and the products' lags
        # (``0..Dy``, ``0..Dx``) reach no further, so their circular wrap never meets them.
        self._fshape = (
            sfft.next_fast_len(self.ext.h, real=True),
            sfft.next_fast_len(self.ext.w, real=True),
        )
        plane = Box(self.ext.y0, self.ext.x0, *self._fshape)
        # one read of the union of what all bases need
        boxes = [source_box(H, plane) for H in Hs]
        Href, Wref = self.reference.shape[:2]
        y0 = max(min(b.y0 for b in boxes), 0)
        x0 = max(min(b.x0 for b in boxes), 0)
        y1 = min(max(b.y1 for b in boxes), Href)
        x1 = min(max(b.x1 for b in boxes), Wref)
        C = self.dimsd[2]
        eh, ew = self.ext.h, self.ext.w
        # float32: the warps are single precision, so the stack holds their values exactly
        # at half the memory (columns are promoted where they meet float64 weights)
        self.stack = np.empty((nb, *self._fshape, C), np.float32)
        # ext pixels that some base does not cover (one mask, not one per base)
        bad = np.ones((eh, ew), bool)
        if not (y0 < y1 and x0 < x1):
            self.stack[...] = 0.0
        else:
            sbox = Box(y0, x0, y1 - y0, x1 - x0)
            src = read_window(self.reference, sbox, self.dtype)
            if self.scale != 1.0:
                src /= self.scale
            src = src.astype(np.float32, copy=False)
            bad[...] = False
            lock = threading.Lock()

            def warp(b: int) -> None:
                """Base ``b``'s plane of the stack; the ext pixels it leaves uncovered
                marked in ``bad`` (an OR: the order of the bases does not matter)."""
                # warp in float32: OpenCV then keeps single-precision coordinates, while
                # float64 warps snap them to a 1/32-px table (less accurate)
                _, ok = warp_window(self.reference, Hs[b], plane, dtype=np.float32,
                                    source=(src, sbox), out=self.stack[b])
                if not ok.all():
                    with lock:
                        bad[...] |= ~ok[:eh, :ew]
                fin = np.isfinite(self.stack[b])
                if not fin.all():  # no data (NaN) in the reference: not covered either
                    self.stack[b][~fin] = 0.0
                    with lock:
                        bad[...] |= ~fin[:eh, :ew].all(axis=-1)

            # the bases on the operator's threads, each warp on one OpenCV thread: OpenCV's
            # threaded bilinear warps differ with the number of its threads (a unit
            # roundoff at a few pixels), which the solver's iterations then amplify
            with opencv_single():
                thread_map(warp, range(nb), self.threads)
            del src
        self.valid = self._all_pose_valid(bad)
        # flat-index helpers: lag offsets of every pose
        self._oy = self.tymax - ty  # row offset into ext for each iy
        self._ox = self.txmax - tx
        self._xbuf = None  # rmatvec's work buffer (reused: see rmatvec)

    @property
    def spec(self) -> np.ndarray | None:
        """Spectra of the warped stack (``(n_bases, Fh, Fw // 2 + 1, C)``), computed on
        first use; None without spectral products (``spectra=False``, exact engine)."""
        if not self._spectral:
            return None
        if "full" not in self._cache:
            self._cache["full"] = self._spectra()
        return self._cache["full"]

    def _phase_spectra(self) -> np.ndarray:
        """Spectra of the stack's row phases for :attr:`row_step` ``k``: ``[p, b]`` is the
        transform of rows ``p, p + k, p + 2k, ...`` of base ``b``'s plane, on
        ``Fh_k = next_fast_len(n + Dy // k)`` rows (``n`` the window's rows kept), so the
        correlation of the kept rows with a phase at its ``(Dy - p) // k + 1`` row lags
        does not wrap.  Computed on first use and shared with the operator."""
        k = self.row_step
        key = ("rows", k)
        if key not in self._cache:
            fh = sfft.next_fast_len(self.dimsd[0] + self.Dy // k)
            spec = _zeros((k, self.grid.n_bases, fh, *self._spectra_shape()), self._ctype())
            for p in range(k):
                self._spectra_into(spec[p], slice(p, None, k))
            self._cache[key] = spec
        return self._cache[key]

    def _idft_rows(self, n_lags: int, fh: int, ctype) -> np.ndarray:
        """The inverse DFT's rows for lags ``0 .. n_lags - 1`` of a length-``fh`` transform
        (``n_lags x fh``, in ``ctype``), cached."""
        key = ("idft", n_lags, fh, np.dtype(ctype).str)
        if key not in self._cache:
            m = np.exp(2j * np.pi * np.outer(np.arange(n_lags), np.arange(fh)) / fh) / fh
            self._cache[key] = m.astype(ctype)
        return self._cache[key]

    def _chunk(self) -> int:
        """Bases per block of the spectral products: a block of cross spectra of about
        ``_BLOCK_BYTES`` stays in cache between its product and its inverse transform."""
        Fh, Fw = self._fshape
        per_base = Fh * (Fw // 2 + 1) * np.dtype(np.result_type(self.dtype, np.complex64)).itemsize
        return int(max(1, min(self.grid.n_bases, _BLOCK_BYTES // per_base)))

    def _ctype(self):
        """Complex type of the stored spectra (``spectra_precision``)."""
        if self.spectra_precision == "single":
            return np.dtype(np.complex64)
        return np.result_type(self.dtype, np.complex64)

    def _spectra_shape(self) -> tuple[int, int]:
        """Columns and bands of a spectrum: ``(Fw // 2 + 1, C)``."""
        return self._fshape[1] // 2 + 1, self.dimsd[2]

    def _spectra(self) -> np.ndarray:
        """Spectra of the stack (stored as ``spectra_precision`` says)."""
        spec = _zeros((self.grid.n_bases, self._fshape[0], *self._spectra_shape()),
                      self._ctype())
        self._spectra_into(spec)
        return spec

    def _spectra_into(self, out: np.ndarray, rows: slice = slice(None)) -> None:
        """Fill ``out`` (``(n_bases, fh, Fw // 2 + 1, C)``) with the transforms of the
        stack's ``rows`` on ``fh`` rows (zero-padded or cut), computed in the operator's
        precision a block of bases at a time (no full-size temporary)."""
        fh, Fw = out.shape[1], self._fshape[1]
        step = self._chunk()
        for c0 in range(0, self.grid.n_bases, step):
            c1 = min(c0 + step, self.grid.n_bases)
            blk = self.stack[c0:c1, rows]
            if out.dtype != np.complex64:
                blk = blk.astype(self.dtype)
            out[c0:c1] = sfft.rfft2(blk, s=(fh, Fw), axes=(1, 2), workers=self.threads)

    def _all_pose_valid(self, bad: np.ndarray) -> np.ndarray:
        """Window pixels valid for every base and every translation, from the ``ext``
        pixels ``bad`` that some base does not cover (summed-area table)."""
        h, w = self.box.h, self.box.w
        bad = bad.astype(np.int64)
        sat = np.zeros((bad.shape[0] + 1, bad.shape[1] + 1), np.int64)
        sat[1:, 1:] = bad.cumsum(0).cumsum(1)
        Dy, Dx = self.Dy, self.Dx
        cnt = (
            sat[Dy + 1 : Dy + 1 + h, Dx + 1 : Dx + 1 + w]
            - sat[0:h, Dx + 1 : Dx + 1 + w]
            - sat[Dy + 1 : Dy + 1 + h, 0:w]
            + sat[0:h, 0:w]
        )
        return cnt == 0

    def _build_exact(self) -> None:
        self.stack = None
        valid = np.ones((self.box.h, self.box.w), bool)
        # validity of all poses: the extreme translations at every base suffice only for
        # affine bases; check every pose for exactness (cheap relative to any use of exact)
        for k in range(self.grid.size):
            _, v = warp_window(
                self.reference, self.grid.homography(k) @ self.base, self.box, dtype=np.float32
            )
            valid &= v
        self.valid = valid

    def rows(self, step: int) -> BlurOperator:
        """This operator restricted to every ``step``-th row of its window: ``S F``, with
        ``S`` the selection of rows ``0, step, 2 step, ...`` (adjoint ``F^T S^T``).

        A view: it shares the warped stack and the spectra (no copy).  Its columns are
        strided views of the stack, so the products over the columns (the solver's Gram
        blocks, forward sums and line searches) read ``1 / step`` of the pixels;
        :meth:`rmatvec` correlates the kept rows with each row phase of the stack (spectra
        computed once per step, :meth:`_phase_spectra`).  :attr:`valid` and ``excluded``
        are restricted the same way.

        Parameters
        ----------
        step : int
            Row step, at least 1 (1: the operator itself).

        Returns
        -------
        BlurOperator
        """
        step = int(step)
        if step < 1:
            raise ValueError(f"row step must be at least 1, got {step}")
        if step == 1:
            return self
        if self.row_step != 1:
            raise ValueError("the operator is already restricted to a row step")
        out = copy.copy(self)
        out.row_step = step
        h, w, C = self.dimsd
        n = -(-h // step)
        out.dimsd = (n, w, C)
        out.shape = (n * w * C, self.grid.size)
        out.valid = self.valid[::step]
        if getattr(self, "excluded", None) is not None:
            out.excluded = self.excluded[::step]
        out._xbuf = None  # rmatvec's work buffer: not shared with the full operator
        return out

    # ------------------------------------------------------------------ columns
    def column(self, k: int) -> np.ndarray:
        """Column ``k`` of ``F`` as an image of shape :attr:`dimsd` (for the fast engine a
        float32 view into the warped stack, whose values are single precision by
        construction; strided over the rows under a :attr:`row_step`)."""
        s = self.row_step
        if self.engine == "fast":
            # plain integer arithmetic (np.unravel_index costs more than the view; the
            # solver asks for tens of thousands of columns)
            b, rest = divmod(int(k), self._n_t)
            iy, ix = divmod(rest, self._n_tx)
            oy, ox = int(self._oy[iy]), int(self._ox[ix])
            return self.stack[b, oy : oy + self.box.h : s, ox : ox + self.box.w]
        b, iy, ix = np.unravel_index(int(k), self.grid.shape)
        H = self.grid.homography((int(b), int(iy), int(ix))) @ self.base
        col = warp_window(self.reference, H, self.box, dtype=np.float32)[0][::s]
        col = col.astype(self.dtype)
        return col / self.scale if self.scale != 1.0 else col

    def gather(self, k: int, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Values of column ``k`` at pixels ``(rows, cols)`` of :attr:`dimsd`: ``(n, C)``
        array."""
        if self.engine == "fast":
            rows = np.asarray(rows) * self.row_step
            b, iy, ix = np.unravel_index(int(k), self.grid.shape)
            return self.stack[b, rows + self._oy[iy], cols + self._ox[ix]]
        return self.column(k)[rows, cols]

    def gather_many(self, ks, rows: np.ndarray, cols: np.ndarray,
                    chans: np.ndarray) -> np.ndarray:
        """Values of the columns ``ks`` at pixels ``(rows, cols, chans)`` of :attr:`dimsd`:
        an ``(n, len(ks))`` array (one flat ``take`` on the fast engine)."""
        ks = np.asarray(ks, dtype=np.int64)
        if ks.size == 0:
            return np.zeros((rows.size, 0))
        if self.engine == "fast":
            b, iy, ix = np.unravel_index(ks, self.grid.shape)
            _, He, We, C = self.stack.shape
            col_off = ((b * He + self._oy[iy]) * We + self._ox[ix]) * C
            pix_off = (rows.astype(np.int64) * self.row_step * We + cols) * C + chans
            return np.take(self.stack.reshape(-1), pix_off[:, None] + col_off[None, :])
        sel = np.arange(rows.size)
        return np.stack([self.gather(int(k), rows, cols)[sel, chans] for k in ks], axis=1)

    # ------------------------------------------------------------------ products
    def combine(self, ks, values) -> np.ndarray:
        """``sum_i values[i] * column(ks[i])``, returned in the working precision (zero
        values skipped), summed in column order (a base's columns are then neighbours in memory),
        by :attr:`threads` threads when the sum is large, each summing a contiguous part of
        the columns (the solver's forward products: 1.6x faster on 2 cores).

        The fast engine's columns are float32 views into the stack: runs of
        :data:`_SINGLE_RUN` of them are scaled and summed in float32 (OpenCV's
        ``scaleAdd``, in place) and each run's sum added into the result.  A float64
        temporary per column moved three times the memory, and this sum is the solver's
        most frequent product (13 % of the gigapixel estimate's CPU before).  The
        rounding, at most 17 float32 unit roundoffs (``1e-6``) of the terms' magnitudes and
        ``~1e-8`` in practice, is of the order of the single-precision spectra of
        :meth:`rmatvec` and far below the residuals the solver compares
        (``tests/test_operator.py`` checks the bound against the explicit float64 sum)."""
        ks = np.asarray(ks, dtype=np.int64)
        values = np.asarray(values, dtype=float)
        order = [int(i) for i in np.argsort(ks, kind="stable") if values[i] != 0.0]
        h, wd, C = self.dimsd

        def part(idx: list[int]) -> np.ndarray:
            out = np.zeros(self.dimsd, self.dtype)
            if self.engine != "fast":
                for i in idx:
                    out += values[i] * self.column(int(ks[i]))
                return out
            run = np.zeros((h, wd * C), np.float32)
            flat = out.reshape(h, wd * C)
            for j, i in enumerate(idx, 1):
                col = self.column(int(ks[i])).reshape(h, wd * C)  # a view: rows contiguous
                cv2.scaleAdd(col, float(values[i]), run, dst=run)
                if j % _SINGLE_RUN == 0 or j == len(idx):
                    cv2.accumulate(run, flat)
                    run.fill(0.0)
            return out

        big = len(order) * h * wd * C >= _PARALLEL_SUM
        return split_sum(part, order, self.threads, SUM_PARTS if big else 1)

    def matvec(self, weights: np.ndarray) -> np.ndarray:
        """``F w``: the window of the reference blurred with pose weights ``w``.

        A sum of columns when that is cheaper than the spectral product (a few weighted
        poses per base angle with weight: a column costs a tenth or less of a base's
        spectral product), else the spectral product."""
        w = np.asarray(weights, dtype=float).reshape(self.grid.shape)
        nz = np.flatnonzero(w)
        sparse = nz.size <= 64
        if not sparse and self.engine == "fast":
            n_bases = np.unique(np.unravel_index(nz, self.grid.shape)[0]).size
            sparse = nz.size <= _COLUMNS_PER_BASE * n_bases
            if not sparse and "full" not in self._cache:  # the spectra are still to compute
                sparse = nz.size <= _COLUMNS_PER_COLD_BASE * self.grid.n_bases
        if not self._spectral or sparse:
            return self.combine(nz, w.ravel()[nz])
        kern = np.zeros((self.grid.n_bases, self.Dy + 1, self.Dx + 1))
        iy = (self._ty - self.tymin).astype(int)
        ix = (self._tx - self.txmin).astype(int)
        kern[:, iy[:, None], ix[None, :]] = w
        prod = np.zeros(self.spec.shape[1:], np.result_type(self.dtype, np.complex64))
        step = self._chunk()
        for c0 in range(0, self.grid.n_bases, step):  # blocks: no full-size kernel spectra
            c1 = min(c0 + step, self.grid.n_bases)
            if not kern[c0:c1].any():
                continue
            ks = sfft.rfft2(kern[c0:c1], s=self._fshape, axes=(1, 2), workers=self.threads)
            prod += np.einsum("byxc,byx->yxc", self.spec[c0:c1], ks)
        full = sfft.irfft2(prod, s=self._fshape, axes=(0, 1), workers=self.threads)
        h, wd = self.box.h, self.box.w
        out = full[self.Dy : self.Dy + h : self.row_step, self.Dx : self.Dx + wd]
        return out.astype(self.dtype, copy=False)

    def rmatvec(self, residual: np.ndarray) -> np.ndarray:
        """``F^T r``: one inner product per pose, returned with shape ``grid.shape``.

        On the fast engine, the cross-correlation of ``r`` with every base's plane at the
        translation lags (rows ``0..Dy``, columns ``0..Dx``).  Under a :attr:`row_step`
        ``k`` the kept rows are correlated with each row phase of the planes
        (:meth:`_phase_spectra`): the lags ``p, p + k, ...`` of phase ``p``, the same
        values at ``1 / k`` of the transform of ``r`` and of the inverse DFT along the
        rows."""
        r = np.asarray(residual, dtype=self.dtype).reshape(self.dimsd)
        if not self._spectral:
            out = np.empty(self.grid.size)
            for k in range(self.grid.size):
                out[k] = float(np.vdot(self.column(k), r))
            return out.reshape(self.grid.shape)
        k = self.row_step
        spec = self.spec[None] if k == 1 else self._phase_spectra()
        fh = spec.shape[2]
        Rc = np.conj(sfft.rfft2(r, s=(fh, self._fshape[1]), axes=(0, 1),
                                workers=self.threads))
        if spec.dtype == np.complex64:
            # single-precision spectra: the products in single precision too (half the
            # memory traffic, twice the arithmetic rate).  Their rounding is of the
            # spectra's own order, relative to |r| (the current residual, small near the
            # optimum where the solver's KKT test needs the gradient's sign)
            Rc = Rc.astype(np.complex64)
        ctype = np.result_type(spec.dtype, Rc.dtype)
        rows = np.empty((self.grid.n_bases, self.Dy + 1, spec.shape[3]), ctype)
        for p in range(min(k, self.Dy + 1)):
            self._lag_rows(spec[p], Rc, rows[:, p::k])
        corr = sfft.irfft(rows, n=self._fshape[1], axis=2, workers=self.threads)
        return corr[:, self._oy[:, None], self._ox[None, :]].astype(self.dtype, copy=False)

    def _lag_rows(self, spec: np.ndarray, Rc: np.ndarray, out: np.ndarray) -> None:
        """``out[b, q] = IDFT_rows(spec[b] * Rc summed over bands)[q]`` for the lags ``q``
        of ``out``'s second axis.

        Sum over bands before the inverse transform (linearity).  Only the first lags are
        needed: the inverse DFT along the rows is a small matrix product (one output row
        per lag), then a real inverse FFT along the columns (by the caller) -- the same
        values as irfft2, a few times cheaper.  Done a block of bases at a time in one
        reused buffer: a full-size cross spectrum is a fresh allocation per call whose
        first-touch page faults cost more than the products on this kind of VM."""
        nb, fh, F2, C = spec.shape
        step = self._chunk()
        xb = self._xbuf
        if xb is None or xb.dtype != out.dtype or xb.shape[1:] != (fh, F2):
            self._xbuf = np.empty((step, fh, F2), out.dtype)
        idft = self._idft_rows(out.shape[1], fh, out.dtype)
        for c0 in range(0, nb, step):
            c1 = min(c0 + step, nb)
            buf = self._xbuf[: c1 - c0]
            if C == 1:
                np.multiply(spec[c0:c1, :, :, 0], Rc[:, :, 0], out=buf)
            else:
                np.einsum("byxc,yxc->byx", spec[c0:c1], Rc, out=buf)
            np.matmul(idft, buf, out=out[c0:c1])

    @property
    def H(self) -> _Adjoint:
        """The adjoint operator (``F.H @ r == F.rmatvec(r)``)."""
        return _Adjoint(self)

    def __matmul__(self, w):
        return self.matvec(w)


class _Adjoint:
    def __init__(self, op: BlurOperator):
        self.op = op

    def __matmul__(self, r):
        return self.op.rmatvec(r)


def dottest(op: BlurOperator, rng=None) -> tuple[float, float]:
    """Return ``(<F u, v>, <u, F^T v>)`` for random ``u >= 0`` and ``v`` (they must agree)."""
    rng = np.random.default_rng(rng)
    u = rng.random(op.grid.shape)
    v = rng.standard_normal(op.dimsd)
    return float(np.vdot(op.matvec(u), v)), float(np.vdot(u, op.rmatvec(v)))

