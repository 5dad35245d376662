"""Rolling-shutter motion blur: row bands with their own pose weights.

A rolling shutter exposes row ``y`` over its own time window, so each row has its own
blur kernel.  The model here keeps the unknowns few and the operator linear:

* ``B`` row bands with centres ``c_b = (b + 1/2) H / B - 1/2`` (``H`` the observation's
  rows); band ``b`` carries a non-negative weight vector ``W_b`` over the existing
  :class:`~reblur.grid.PoseGrid`.
* Row ``y``'s kernel is ``w(y) = sum_b phi_b(y) W_b`` with ``phi_b`` the hat functions of
  the band centres (linear interpolation between neighbouring centres, constant beyond
  the first and last): a convex combination of at most two neighbouring bands' weights.
  ``sum_b phi_b = 1``, so equal band weights give exactly the global model, and ``B = 1``
  is the global model.
* ``g(x, y) = sum_b phi_b(y) (F W_b)(x, y)``: the operator is linear in the stacked
  weights ``(B, *grid.shape)`` and is a sum of row-weighted global operators
  (:class:`~reblur.operator.BlurOperator`), so it reuses their FFT products and explicit
  columns; :func:`reblur.solve.active_set` solves it unchanged (column ``(b, p)`` is
  pose ``p``'s column with its rows scaled by ``phi_b``).

Why bands rather than one weight per (time sample, pose) with a row-to-time map: the time
model needs the readout fraction before the fit (a search over it multiplies the cost) and
its slots are only identifiable through the unit mass each must carry; the bands need no
readout, their number is the user's resolution knob, and the estimate starts from the
global solution (every band equal), restricted to the poses near its support.  The
interpolation is exact for a kernel that varies linearly with the row; for a path moving
``v`` px per exposure, the kernel of a row between two centres differs from the truth at
its two ends over ``v r / (2 B)`` px (a trapezoid instead of a box).  The readout is then
read from the bands' drift (:func:`readout_fraction`), and the coupling between bands is
the interpolation itself: every band is fitted on the rows of both of its neighbours'
halves, and :func:`rolling_windows` puts estimation windows on every band centre, at the
left edge, the centre and the right edge of the width (``RollingParams.columns``), so no
band is left without data and its kernel is fitted where it varies across the columns
(a roll).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ._bands import BandMean
from .estimate import (
    RTOL,
    _shrink,
    check_bands,
    coarse_side,
    intensity_scale,
    soft_threshold,
)
from .grid import PoseGrid, carry_weights, map_points
from .operator import BlurOperator
from .solve import active_set
from .tiled import SparsePoses, iter_tiles, reblur_tile, run_tiles
from .warp import Box, as_box, read_window

__all__ = [
    "BandGrid",
    "RollingMotion",
    "RollingOperator",
    "RollingParams",
    "RollingPoses",
    "RowBands",
    "ShutterChoice",
    "choose_shutter",
    "estimate_rolling",
    "readout_fraction",
    "reblur_rolling",
    "reblur_rolling_tile",
    "rolling_windows",
    "support_grid",
]


@dataclass(frozen=True)
class RowBands:
    """``n_bands`` row bands of an ``height``-row observation and their hat functions."""

    height: int
    n_bands: int

    def __post_init__(self) -> None:
        if int(self.height) < 1:
            raise ValueError(f"height must be a positive number of rows, got {self.height}")
        if int(self.n_bands) < 1 or int(self.n_bands) > int(self.height):
            raise ValueError(f"n_bands must be between 1 and the {self.height} rows, "
                             f"got {self.n_bands}")
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "n_bands", int(self.n_bands))

    @property
    def centres(self) -> np.ndarray:
        """Centre row of every band, ``(b + 1/2) H / B - 1/2``."""
        return (np.arange(self.n_bands) + 0.5) * self.height / self.n_bands - 0.5

    def weights(self, rows: np.ndarray) -> np.ndarray:
        """``phi_b(y)``: ``(n_bands, len(rows))``, non-negative, summing to 1 per row."""
        y = np.asarray(rows, dtype=float)
        c = self.centres
        if self.n_bands == 1:
            return np.ones((1, y.size))
        yc = np.clip(y, c[0], c[-1])
        step = self.height / self.n_bands
        return np.maximum(0.0, 1.0 - np.abs(yc[None, :] - c[:, None]) / step)

    def row_span(self, b: int) -> tuple[int, int]:
        """Rows ``[y0, y1)`` where band ``b``'s hat is positive (whole image rows)."""
        c = self.centres
        step = self.height / self.n_bands
        y0 = 0 if b == 0 else int(np.floor(c[b] - step)) + 1
        y1 = self.height if b == self.n_bands - 1 else int(np.ceil(c[b] + step))
        return max(y0, 0), min(y1, self.height)


@dataclass(frozen=True)
class BandGrid:
    """The stacked unknowns of the band model: ``n_bands`` copies of ``grid``."""

    grid: PoseGrid
    n_bands: int

    @property
    def shape(self) -> tuple[int, ...]:
        return (self.n_bands, *self.grid.shape)

    @property
    def size(self) -> int:
        return self.n_bands * self.grid.size


class _RowScaled:
    """A column whose rows are scaled by ``phi``: slicing rows returns the product."""

    __slots__ = ("a", "phi")

    def __init__(self, a: np.ndarray, phi: np.ndarray):
        self.a, self.phi = a, phi

    def __getitem__(self, key):
        if isinstance(key, tuple):
            return np.asarray(self)[key]
        return self.a[key] * self.phi[key][:, None, None]

    def __array__(self, dtype=None, copy=None):
        out = self.a * self.phi[:, None, None]
        return out if dtype is None else out.astype(dtype)


class RollingOperator:
    """Matrix-free band-model operator on one observation window.

    ``(A W)(x, y) = sum_b phi_b(y) (F W_b)(x, y)`` with ``F`` the
    :class:`~reblur.operator.BlurOperator` of the window and ``W`` of shape
    ``(n_bands, *grid.shape)``.  It offers what :func:`reblur.solve.active_set` uses
    (``matvec``, ``rmatvec``, ``column``, ``combine``, ``gather_many``, ``valid``,
    ``dimsd``, ``box``, ``threads``), so the solver runs on it unchanged.

    Parameters
    ----------
    reference, grid, box
        As :class:`~reblur.operator.BlurOperator`.
    bands : RowBands
        The row bands (their ``height`` is the full observation's).
    **options
        Further :class:`~reblur.operator.BlurOperator` keywords (``base``, ``engine``,
        ``scale``, ``spectra_precision``, ``threads``, ...).
    """

    def __init__(self, reference, grid: PoseGrid, box, bands: RowBands, **options: Any):
        self._attach(BlurOperator(reference, grid, box, **options), bands)

    @classmethod
    def on(cls, op: BlurOperator, bands: RowBands) -> RollingOperator:
        """The band model on an existing window operator (shares its stack and spectra)."""
        new = cls.__new__(cls)
        new._attach(op, bands)
        return new

    def _attach(self, op: BlurOperator, bands: RowBands) -> None:
        if bands.height != op.grid.image_shape[0]:
            raise ValueError(f"the bands cover {bands.height} rows, the grid's image has "
                             f"{op.grid.image_shape[0]}")
        self.op = op
        self.bands = bands
        self.box = op.box
        self.phi = bands.weights(np.arange(self.box.y0, self.box.y1))
        self.touch = [int(b) for b in np.flatnonzero(self.phi.any(axis=1))]
        # window rows [r0, r1) where each band's hat is positive, and the rows where the
        # set of positive hats changes (the solver's Gram blocks are cut there)
        self._band_rows = np.zeros((bands.n_bands, 2), np.int64)
        for b in self.touch:
            pos = np.flatnonzero(self.phi[b] > 0)
            self._band_rows[b] = (pos[0], pos[-1] + 1)
        self.row_breaks = sorted({int(v) for v in self._band_rows[self.touch].ravel()})
        self.grid = BandGrid(op.grid, bands.n_bands)
        self._P = op.grid.size  # poses per band (PoseGrid.size is a product each call)
        self.dimsd = op.dimsd
        self.shape = (op.shape[0], self.grid.size)
        self.valid = op.valid
        self.engine = op.engine

    @property
    def threads(self) -> int:
        return self.op.threads

    @threads.setter
    def threads(self, n: int) -> None:
        self.op.threads = n

    def _rows(self, b: int) -> np.ndarray:
        return self.phi[b][:, None, None]

    def matvec(self, weights: np.ndarray) -> np.ndarray:
        """``A W``: the window blurred with each row's interpolated weights."""
        W = np.asarray(weights, dtype=float).reshape(self.grid.shape)
        out = np.zeros(self.dimsd, self.op.dtype)
        for b in self.touch:
            if W[b].any():
                out += self._rows(b) * self.op.matvec(W[b])
        return out

    def rmatvec(self, residual: np.ndarray) -> np.ndarray:
        """``A^T r``: per band, the global adjoint of the row-weighted residual."""
        r = np.asarray(residual, dtype=float).reshape(self.dimsd)
        out = np.zeros(self.grid.shape)
        for b in self.touch:
            out[b] = self.op.rmatvec(self._rows(b) * r)
        return out

    def column(self, k: int) -> _RowScaled:
        """Column ``k = b * P + p``: pose ``p``'s column, rows scaled by ``phi_b``."""
        b, p = divmod(int(k), self._P)
        return _RowScaled(self.op.column(p), self.phi[b])

    def column_rows(self, k: int) -> tuple[int, int]:
        """Window rows ``[r0, r1)`` outside which column ``k`` is zero (band ``b``'s hat);
        ``(0, 0)`` for a band the window does not reach."""
        b = int(k) // self._P
        return int(self._band_rows[b, 0]), int(self._band_rows[b, 1])

    def combine(self, ks, values) -> np.ndarray:
        """``sum_i values[i] * column(ks[i])``, by band."""
        ks = np.asarray(ks, dtype=np.int64)
        values = np.asarray(values, dtype=float)
        band, pose = np.divmod(ks, self._P)
        out = np.zeros(self.dimsd, self.op.dtype)
        for b in np.unique(band):
            if int(b) not in self.touch:
                continue
            sel = band == b
            out += self._rows(int(b)) * self.op.combine(pose[sel], values[sel])
        return out

    def gather_many(self, ks, rows: np.ndarray, cols: np.ndarray,
                    chans: np.ndarray) -> np.ndarray:
        """Values of the columns ``ks`` at pixels ``(rows, cols, chans)``: ``(n, len(ks))``."""
        ks = np.asarray(ks, dtype=np.int64)
        if ks.size == 0:
            return np.zeros((rows.size, 0))
        band, pose = np.divmod(ks, self._P)
        vals = self.op.gather_many(pose, rows, cols, chans)
        return vals * self.phi[band][:, rows].T


# ---------------------------------------------------------------------------- estimate
@dataclass(frozen=True)
class RollingParams:
    """Settings of the rolling-shutter estimate and of the model choice.

    Attributes
    ----------
    n_bands : int
        Row bands ``B``.  6: a readout of a full exposure then moves a band centre's window
        by a sixth of an exposure from its neighbour's; with 4 the interpolated kernels
        between centres were too wide for a full readout (``python -m benchmarks.rolling
        --size 512 --readouts 1 --no-change-only --no-save --bands 4``: 1.60 % false
        alarms; 0.08 % with 6 bands, 0.00 % with 8 at 1.4x the CPU of 6).
    side : int
        Side (px) of the estimation windows (:func:`rolling_windows`).
    columns : int
        Estimation windows per band across the width (:func:`rolling_windows`): 3, the
        left edge, the centre and the right edge; with the edges alone (2) the kernels of
        the centre strip were left free and reblurred a textured centre wrongly under a
        roll (``python -m benchmarks.rolling --size 768 [--columns 2]``, pasted changes,
        readouts 0.25 / 0.5 / 1: 1.45 / 0.67 / 0.41 % false alarms with 2, 0.018 / 0.049 /
        0.036 % with 3; at 512 px auto's CPU over the eight pairs 56 s with 2, 64 s with 3).
    t_margin, b_margin : int
        The band weights live on the poses within ``t_margin`` translation steps and
        ``b_margin`` base steps of the global estimate's support (:func:`support_grid`).
    bic_margin : float
        The rolling model is kept when its Bayesian information criterion on the windows
        is lower than the global one's by more than this (see :func:`choose_shutter`).
    min_drop : float
        ... and when it lowers the windows' inlier residual sum of squares by at least
        this fraction (a clearly better fit, not one of model error's small gains).
    min_readout : float
        ... and when the estimated readout fraction (:func:`readout_fraction`) is at least
        this: the bands of a global shutter differ only where the grid approximates the
        blur differently on different rows (a tilt), not by a drift along the path (0.02
        on the test bed's global pair), and below a tenth of an exposure across the frame
        the rows' windows differ by less than a tenth of the exposure's motion.
    max_outer : int
        Outer iterations of the active-set solve.
    coarse : bool
        :func:`choose_shutter` decides on the windows' central parts and fits the band
        model on the full windows only when it keeps it (the choice's cost: at 512 px and
        a full readout the two full-window fits took 3x the global pipeline's CPU).
    """

    n_bands: int = 6
    side: int = 160
    columns: int = 3
    t_margin: int = 3
    b_margin: int = 2
    bic_margin: float = 10.0
    min_drop: float = 0.05
    min_readout: float = 0.1
    max_outer: int = 40
    coarse: bool = True

    def __post_init__(self) -> None:
        for name in ("n_bands", "side", "columns", "max_outer"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"RollingParams.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("t_margin", "b_margin", "bic_margin", "min_drop", "min_readout"):
            if not float(getattr(self, name)) >= 0:
                raise ValueError(f"RollingParams.{name} must be >= 0, got {getattr(self, name)}")


@dataclass
class RollingMotion:
    """Band weights of a rolling-shutter estimate.

    Attributes
    ----------
    weights : ndarray, ``(n_bands, *grid.shape)``
    grid : PoseGrid
        The (sub-)grid the weights live on (full-image geometry).
    bands : RowBands
    boxes : list of tuple
        Estimation windows ``(y0, x0, h, w)``.
    chi : list of ndarray
        The change term of each window (``(h, w, C)``, [0, 1] units).
    info : dict
        Solver information, ``psnr`` per window, ``readout`` (:func:`readout_fraction`).
    """

    weights: np.ndarray
    grid: PoseGrid
    bands: RowBands
    boxes: list[tuple[int, int, int, int]] = field(default_factory=list)
    chi: list[np.ndarray] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)

    def row_weights(self, y: float) -> np.ndarray:
        """The kernel of row ``y`` on :attr:`grid` (``grid.shape``)."""
        phi = self.bands.weights(np.array([y]))[:, 0]
        return np.tensordot(phi, self.weights, axes=1)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary: bands, readout, per-band weight sums and kernel centroids."""
        per_band = []
        poses = self.grid.poses()
        for b in range(self.bands.n_bands):
            w = self.weights[b].ravel()
            s = float(w.sum())
            mean = (poses * w[:, None]).sum(0) / s if s > 0 else np.full(6, np.nan)
            per_band.append(dict(centre_row=float(self.bands.centres[b]), weight_sum=s,
                                 n_poses=int(np.count_nonzero(w)),
                                 mean_pose=dict(zip(("tx", "ty", "tz", "rx", "ry", "rz"),
                                                    map(float, mean), strict=True))))
        return dict(n_bands=self.bands.n_bands, readout=self.info.get("readout"),
                    boxes=[list(b) for b in self.boxes], bands=per_band,
                    grid=self.grid.to_dict())


def rolling_windows(shape: tuple[int, int], n_bands: int, side: int, columns: int = 3
                    ) -> list[tuple[int, int, int, int]]:
    """``columns`` windows per band, centred on its centre row, spread across the width.

    Parameters
    ----------
    shape : tuple of int
        The observation's ``(H, W)`` (further axes ignored).
    n_bands : int
        Row bands (:class:`RowBands`).
    side : int
        Side (px) of the windows, at most the image's height; across, at most half the
        width when the width holds two windows, else the whole width.
    columns : int
        Windows per band: the first ``W / 32`` from the left edge, the last as far from
        the right edge, the others evenly spaced between them (3: left edge, centre,
        right edge); 1: one centred window.  2 is the layout of the first band model (the
        edges only).

    Returns
    -------
    list of (y0, x0, h, w)
        Row by row (bands from the top), left to right; windows that coincide (a narrow
        image) are kept once.

    Notes
    -----
    Every band then has data on its own rows, and the far-apart edge windows make its
    roll observable.  The edges alone do not fix the kernels between them: a weight
    spread over translations and rolls is seen there only through two projections
    (``t + rz (x - x_c)`` at two columns ``x``), and a roll's rolling-shutter drift makes
    the kernel vary across the columns, so a band fitted on its edges can reblur the
    centre strip wrongly (``python -m benchmarks.rolling --size 768``: 1.45 % false
    alarms with pasted changes at readout 0.25 with two columns, 0.018 % with three).
    The centre window adds the third projection.
    """
    if int(columns) < 1:
        raise ValueError(f"columns must be >= 1, got {columns}")
    H, W = (int(s) for s in shape[:2])
    s_y, s_x = min(int(side), H), min(int(side), W // 2 if W >= 2 * side else W)
    bands = RowBands(H, n_bands)
    if int(columns) == 1:
        xs = [(W - s_x) // 2]
    else:
        left, right = W // 32, W - s_x - W // 32
        xs = [int(round(v)) for v in np.linspace(left, right, int(columns))]
    xs = sorted({int(np.clip(x0, 0, W - s_x)) for x0 in xs})
    out = []
    for c in bands.centres:
        y0 = int(np.clip(round(c - s_y / 2), 0, H - s_y))
        for x0 in xs:
            out.append((y0, x0, s_y, s_x))
    return list(dict.fromkeys(out))


def _axis_index(grid: PoseGrid) -> list[np.ndarray]:
    """Per base, the indices of its ``(tz, rx, ry, rz)`` values."""
    dims = (len(grid.tz), len(grid.rx), len(grid.ry), len(grid.rz))
    return list(np.unravel_index(np.arange(grid.n_bases), dims))


def support_grid(grid: PoseGrid, weights: np.ndarray, t_margin: int = 3,
                 b_margin: int = 2, mass: float = 0.9) -> PoseGrid:
    """The part of ``grid`` around the poses that carry weight.

    Per axis, the values between the smallest and largest index of the heaviest poses
    that hold ``mass`` of the weight, grown by ``t_margin`` (translations) or
    ``b_margin`` (``tz``, ``rx``, ``ry``, ``rz``) steps.

    Raises
    ------
    ValueError
        When no pose carries weight.
    """
    w = grid.check_weights(weights)
    if not np.any(w > 0):
        raise ValueError("the global estimate has no pose with weight: nothing to refine")
    # the heaviest poses holding ``mass`` of the weight (a global fit of a rolling shutter
    # spreads small weights far: rolls that mimic the rows' shear)
    order = np.sort(w.ravel())[::-1]
    cut = order[min(int(np.searchsorted(np.cumsum(order), mass * order.sum())), order.size - 1)]
    nz = np.argwhere(w >= cut)
    def span(values, idx, m):
        lo, hi = max(int(idx.min()) - m, 0), min(int(idx.max()) + m, len(values) - 1)
        return values[lo:hi + 1]

    axes = _axis_index(grid)
    used = np.unique(nz[:, 0])
    kw = {name: span(getattr(grid, name), axes[i][used], int(b_margin))
          for i, name in enumerate(("tz", "rx", "ry", "rz"))}
    return grid._replace(tx=span(grid.tx, nz[:, 2], int(t_margin)),
                         ty=span(grid.ty, nz[:, 1], int(t_margin)), **kw)


def embed_weights(w: np.ndarray, sub: PoseGrid, full: PoseGrid) -> np.ndarray:
    """Weights of ``full`` carried over to ``sub`` (poses of ``sub`` missing from ``full``
    get 0; weight on poses of ``full`` outside ``sub`` is dropped):
    :func:`reblur.grid.carry_weights`."""
    return carry_weights(w, full, sub)


def _window_operators(reference, observed, grid: PoseGrid, boxes, base, scale,
                      band_mean: bool = False, spectra: bool = True):
    """Window operators (global, on ``grid``) and the observation windows in [0, 1]; on
    the band mean of both images with ``band_mean`` (their own scales); without the
    spectra (``spectra=False``) when only ``matvec`` will be asked of them."""
    s_ref = intensity_scale(reference.dtype) if scale is None else scale
    s_obs = intensity_scale(observed.dtype) if scale is None else scale
    if band_mean:
        reference, observed = BandMean(reference), BandMean(observed)
    ops = [BlurOperator(reference, grid, b, base=base, scale=s_ref, spectra=spectra)
           for b in boxes]
    gs = [read_window(observed, b, np.float64) / s_obs for b in boxes]
    for op, g in zip(ops, gs, strict=True):  # no data (NaN) in the observation: left out
        fin = np.isfinite(g)
        if not fin.all():
            g[~fin] = 0.0
            op.valid = op.valid & fin.all(axis=2)
    return ops, gs


def _fit(ops, gs, bands: RowBands, w0: np.ndarray, lam: float, occlusion: bool,
         max_outer: int) -> tuple[np.ndarray, dict, list]:
    """Eq. 5 (or eq. 3) of the band model ``bands`` on the windows, from ``w0``."""
    rops = [RollingOperator.on(op, bands) for op in ops]
    # poses enter by bands: as many per outer iteration per band as a global solve takes
    w, info = active_set(rops, gs, lam=lam, occlusion=occlusion, max_outer=max_outer, w0=w0,
                         rtol=RTOL, batch=24 * bands.n_bands)
    return w, info, rops


def _motion(w, info, rops, gs, grid, bands, boxes, lam, occlusion) -> RollingMotion:
    chis, psnr = [], []
    for op, g in zip(rops, gs, strict=True):
        r = g - op.matvec(w)
        chi = soft_threshold(r, lam / 2.0) if occlusion else np.zeros_like(r)
        chi[~op.valid] = 0.0
        chis.append(chi)
        mse = float(np.mean(r[op.valid] ** 2)) if op.valid.any() else np.nan
        psnr.append(10 * np.log10(1.0 / mse) if mse > 0 else float("inf"))
    motion = RollingMotion(weights=w, grid=grid, bands=bands,
                           boxes=[b.as_tuple() for b in boxes], chi=chis,
                           info=dict(info, psnr=psnr, lam=lam, occlusion=occlusion))
    r, rinfo = readout_fraction(motion)
    motion.info.update(readout=r, readout_fit=rinfo)
    return motion


def estimate_rolling(
    reference,
    observed,
    grid: PoseGrid,
    *,
    w_global: np.ndarray,
    boxes: Sequence | None = None,
    base: np.ndarray | None = None,
    lam: float = 0.1,
    occlusion: bool = True,
    params: RollingParams | None = None,
    scale: float | None = None,
) -> RollingMotion:
    """Estimate band weights on windows spread over the rows, from a global estimate.

    The unknowns are the band weights on :func:`support_grid` of the global weights
    ``w_global`` (the poses the whole exposure visits, with a margin); every band starts
    from ``w_global`` (the global model) and :func:`reblur.solve.active_set` solves eq. 5
    (or eq. 3) on :class:`RollingOperator` windows.

    Parameters
    ----------
    reference, observed : array-like
        As :func:`reblur.estimate.estimate_motion`.
    grid : PoseGrid
        The grid of ``w_global`` (full observation geometry).
    w_global : ndarray, ``grid.shape``
        Global-shutter weights (e.g. ``estimate_motion(...).weights``).
    boxes : sequence of (y0, x0, h, w), optional
        Windows; default :func:`rolling_windows`.
    base : (3, 3) ndarray, optional
        Coarse alignment composed before every pose.
    lam, occlusion
        Eq. 5's ``lambda``, and eq. 5 (True) or eq. 3.
    params : RollingParams, optional
    scale : float, optional
        Intensity full scale (default from the dtypes).

    Returns
    -------
    RollingMotion
        On the sub-grid, with ``info["readout"]`` from :func:`readout_fraction`.
    """
    t0 = time.perf_counter()
    p = params or RollingParams()
    bands = RowBands(grid.image_shape[0], p.n_bands)
    if boxes is None:
        boxes = rolling_windows(observed.shape[:2], p.n_bands, p.side, p.columns)
    boxes = [as_box(b) for b in boxes]
    sub = support_grid(grid, w_global, p.t_margin, p.b_margin)
    ops, gs = _window_operators(reference, observed, sub, boxes, base, scale)
    w0 = np.broadcast_to(embed_weights(w_global, sub, grid), (p.n_bands, *sub.shape)).copy()
    w, info, rops = _fit(ops, gs, bands, w0, lam, occlusion, p.max_outer)
    motion = _motion(w, info, rops, gs, sub, bands, boxes, lam, occlusion)
    motion.info["time_total_s"] = time.perf_counter() - t0
    return motion


# ---------------------------------------------------------------------------- readout
def _band_moments(grid: PoseGrid, w: np.ndarray, pts: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Mean ``(n, 2)`` and covariance ``(n, 2, 2)`` of the displacement ``H_p^-1 pt - pt``
    under weights ``w``, at every point of ``pts`` ``(n, 2)``."""
    poses = grid.nonzero(w)
    pts = np.asarray(pts, dtype=float).reshape(-1, 2)
    d = np.stack([map_points(np.linalg.inv(grid.homography((b, i, j))), pts) - pts
                  for b, i, j, _ in poses])  # (poses, n, 2)
    v = np.array([p[3] for p in poses])
    v = v / v.sum()
    mu = np.tensordot(v, d, axes=1)
    dc = d - mu
    return mu, np.einsum("p,pni,pnj->nij", v, dc, dc)


def _moments(grid: PoseGrid, w: np.ndarray, pt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of the displacement ``H_p^-1 pt - pt`` under weights ``w``."""
    mu, cov = _band_moments(grid, w, np.asarray(pt, dtype=float)[None])
    return mu[0], cov[0]


def readout_fraction(motion: RollingMotion) -> tuple[float, dict]:
    """The readout fraction the band weights' drift implies.

    Two bands whose centres lie ``d`` rows apart (``d / H`` of the frame) see windows
    ``r d / H`` exposures apart.  At a point, for a camera moving at a constant velocity
    ``v`` (pixels per exposure) the kernel is a uniform segment of length ``|v|``, whose
    variance along ``v`` is ``|v|^2 / 12``, and its centroid moves by ``r (d / H) v``
    between the bands.  So ``r = |dm| / ((d / H) sqrt(12 s^2))`` with ``dm`` the centroid
    drift and ``s^2`` the kernels' variance along it (the mean of the two bands').  It is
    computed at the centre of every estimation window for every pair of neighbouring
    bands, and the median is returned (clipped to [0, 1]).  A path that curves within an
    exposure, or a fit that spreads a kernel over neighbouring poses, widens the kernel
    and biases ``r`` low; a camera that stands still has no drift (``r`` is then
    unobservable, and so is the rolling shutter).

    The spread of the estimates is reported with it: on a constant-velocity path every
    window and band pair gives the same value.  It does not bound the bias: on the test
    bed's curved 6-D paths fitted on the 3-D grid (``python -m benchmarks.rolling``), the
    median reads 0.16 / 0.35 / 0.23 for readouts 0.25 / 0.5 / 1 with quartiles
    0.14-0.18 / 0.30-0.39 / 0.11-0.69, where the formula on the true kernels gives
    0.25 / 0.51 / 0.85.  The fitted kernels are right where they were fitted: at each
    window's own row their centroid lies 0.06 / 0.17 / 0.62 px (median) from the true
    one, and its change from one window to the next down the image matches the truth's
    (``python -m benchmarks.rolling_readout``).  What goes wrong is the split of that
    change into the time drift (band ``b`` to ``b + 1`` at one point, which the formula
    needs) and the change of the displacement across the rows, and what takes the
    difference is the alignment: along the true drift, per band, the geometric part
    reads -0.48 / -0.48 / 1.59 px fitted against -0.64 / -0.76 / -0.78 true, the time
    part 0.34 / 0.59 / 0.00 against 0.50 / 0.98 / 2.62, their sums -0.14 / 0.12 / 1.58
    against -0.13 / 0.22 / 1.84; and against the readout-0 pair of the same path and
    viewpoint the pipeline's alignment (a homography, refined over the whole image)
    shears by -0.39 px per 100 rows in x where the rows' true centroids move by -0.55
    at r = 0.25, and by (-3.75, -1.69) in (x, y) against (-2.95, -1.25) at r = 1
    (``--readouts 0.25,1 --against-global``).  A camera moving at a constant velocity under a
    rolling shutter is a global blur plus an affine shear of the rows, which a homography
    represents exactly, so no estimator of the band kernels relative to an alignment
    fitted to the observation can recover the drift's affine part: the readout is then
    observable only through how the kernels' SHAPE changes down the rows (the path's
    curvature).  That signal is there on these pairs (the trace of the row kernels'
    covariance at the windows' own rows follows the truth's from 12 to 77 px^2 at
    r = 1), but no estimator from it is in place yet, so the drift formula stays: it
    reports the time drift the band model keeps after the alignment, below the true
    readout on these pairs.  A richer pose family reads lower, not closer: on the 6-D
    grid (``--grid 6d``) r = 0.25 reads 0.08 (own rows within 0.03 px), and the choice
    keeps the global model there.

    Returns
    -------
    r : float
    info : dict
        ``per_pair``: the median estimate of every neighbouring band pair; ``quartiles``:
        the lower and upper quartiles of all the estimates (windows x band pairs),
        clipped to [0, 1].
    """
    bands = motion.bands
    c = bands.centres / bands.height
    pts = np.array([[x0 + (w - 1) / 2.0, y0 + (h - 1) / 2.0]
                    for y0, x0, h, w in motion.boxes], dtype=float)
    per_pair, all_r = [], []
    moments = [_band_moments(motion.grid, motion.weights[b], pts)
               if motion.weights[b].any() else None for b in range(bands.n_bands)]
    for b in range(bands.n_bands - 1):
        if moments[b] is None or moments[b + 1] is None:
            continue
        (m0, s0), (m1, s1) = moments[b], moments[b + 1]
        rs = []
        for i in range(len(pts)):
            dm = m1[i] - m0[i]
            norm = float(np.linalg.norm(dm))
            if norm == 0.0:
                rs.append(0.0)
                continue
            u = dm / norm
            var = 0.5 * float(u @ s0[i] @ u + u @ s1[i] @ u)
            rs.append(norm / ((c[b + 1] - c[b]) * np.sqrt(12.0 * var)) if var > 0 else 1.0)
        per_pair.append(float(np.median(rs)))
        all_r += rs
    if not all_r:
        return 0.0, dict(per_pair=[], quartiles=[0.0, 0.0])
    q = np.clip(np.percentile(all_r, [25, 75]), 0.0, 1.0)
    return float(np.clip(np.median(all_r), 0.0, 1.0)), dict(
        per_pair=per_pair, quartiles=[float(q[0]), float(q[1])])


# ---------------------------------------------------------------------------- reblur
class RollingPoses:
    """The non-zero poses of every band (:class:`~reblur.tiled.SparsePoses` each), and the
    local displacement field applied after them (``field``, as
    :class:`~reblur.tiled.SparsePoses`; None: none)."""

    def __init__(self, motion: RollingMotion, base: np.ndarray | None = None,
                 rtol: float = 0.0, field=None):
        self.bands = motion.bands
        self.grid = motion.grid
        self.field = field
        self.per_band = [SparsePoses(motion.weights[b], motion.grid, base, rtol)
                         for b in range(motion.bands.n_bands)]

    @property
    def n_poses(self) -> int:
        return sum(p.n_poses for p in self.per_band)

    def reblur_tile(self, reference, box, *, dtype=np.float32):
        """:func:`reblur_rolling_tile` with the field applied (lets tile jobs call it as a
        method)."""
        if self.field is None:
            return reblur_rolling_tile(self, reference, box, dtype=dtype)
        return self.field.displaced(
            lambda b: reblur_rolling_tile(self, reference, b, dtype=dtype), box)


def reblur_rolling_tile(poses: RollingPoses, reference, box, *, dtype=np.float32):
    """Reblurred reference on one observation window, each row with its own weights.

    For every band whose hat reaches the window's rows, the rows it reaches are reblurred
    with the band's poses (:func:`reblur.tiled.reblur_tile`: one reference read per band,
    halos from the poses) and added with the rows' ``phi_b``; so a row costs the warps of
    at most two bands.

    Returns
    -------
    out : (h, w, C) ndarray
    valid : (h, w) bool ndarray
        True where every pose of every band the row uses reads real reference pixels.
    """
    box = as_box(box)
    C = reference.shape[2] if len(reference.shape) == 3 else 1
    out = np.zeros((box.h, box.w, C), dtype)
    valid = np.ones((box.h, box.w), bool)
    phi = poses.bands.weights(np.arange(box.y0, box.y1)).astype(dtype)
    for b, sp in enumerate(poses.per_band):
        rows = np.flatnonzero(phi[b] > 0)
        if rows.size == 0:
            continue
        r0, r1 = int(rows[0]), int(rows[-1]) + 1
        part, ok = reblur_tile(sp, reference, Box(box.y0 + r0, box.x0, r1 - r0, box.w),
                               dtype=dtype)
        out[r0:r1] += phi[b, r0:r1, None, None] * part
        valid[r0:r1] &= ok
    return out, valid


def reblur_rolling(reference, motion: RollingMotion, *, base: np.ndarray | None = None,
                   tile_size: int = 1024, workers: int = 1, dtype=np.float32
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Reblur the whole reference with band weights, tile by tile (numpy output)."""
    poses = RollingPoses(motion, base)
    H, W = motion.grid.image_shape
    C = reference.shape[2] if len(reference.shape) == 3 else 1
    two_d = len(reference.shape) == 2
    out = np.zeros((H, W) if two_d else (H, W, C), dtype)
    valid = np.zeros((H, W), bool)

    def run(b: Box) -> None:
        img, ok = reblur_rolling_tile(poses, reference, b, dtype=dtype)
        out[b.slices] = img[:, :, 0] if two_d else img
        valid[b.slices] = ok

    run_tiles(run, list(iter_tiles((H, W), tile_size)), workers)
    return out, valid


# ---------------------------------------------------------------------------- choice
@dataclass
class ShutterChoice:
    """Outcome of :func:`choose_shutter`.

    Attributes
    ----------
    model : {"global", "rolling"}
    global_ : RollingMotion
        The global fit (one band) on the windows the choice was made on (their central
        parts with ``RollingParams.coarse``) and the same sub-grid.
    rolling : RollingMotion
        The band model: refitted on the full windows when it was kept, else the fit on
        the parts.
    criterion : dict
        On the windows the choice was made on (``windows``): ``n`` (pixels compared),
        ``rss_global``, ``rss_rolling`` (inlier residual sums of squares), ``k_global``,
        ``k_rolling`` (weights in use), ``bic_global``, ``bic_rolling``, ``drop``
        (relative RSS drop), ``readout`` (the parts' band fit), ``rule``; ``fits`` (every
        window fit: bands, outer iterations, ``full`` for the full-window refit),
        ``readout_final`` (:attr:`rolling`'s readout) and ``refit_rejected`` (True when
        the parts kept the band model and the full-window refit's readout fell below
        ``RollingParams.min_readout``, so the global model is kept).
    """

    model: str
    global_: RollingMotion
    rolling: RollingMotion

    @property
    def motion(self) -> RollingMotion:
        """The chosen model's fit."""
        return self.rolling if self.model == "rolling" else self.global_
    criterion: dict[str, Any]


def _inlier_rss(ops, gs, ws, delta: float | None) -> tuple[list[float], int]:
    """Sums of squared residuals of every fit in ``ws`` (with its operators) over the
    pixels all of them leave as inliers (``|r| <= delta``; every valid pixel when
    ``delta`` is None), and their count."""
    rss = [0.0] * len(ws)
    n = 0
    for i_win, g in enumerate(gs):
        rs = [g - fit_ops[i_win].matvec(w) for fit_ops, w in zip(ops, ws, strict=True)]
        m = np.broadcast_to(ops[0][i_win].valid[:, :, None], g.shape)
        if delta is not None:
            for r in rs:
                m = m & (np.abs(r) <= delta)
        n += int(m.sum())
        for i, r in enumerate(rs):
            rss[i] += float(np.sum(r[m] ** 2))
    return rss, n


def _evidence(ops, gs, sub: PoseGrid, boxes, w_start: np.ndarray, lam: float,
              occlusion: bool, p: RollingParams) -> tuple[RollingMotion, RollingMotion, dict]:
    """Both models fitted on the windows ``ops, gs`` (the global one from ``w_start``, the
    band model from the global fit), and the criterion of :func:`choose_shutter` on them
    (``crit["rolling"]``: whether it keeps the band model)."""
    H = sub.image_shape[0]
    one, many = RowBands(H, 1), RowBands(H, p.n_bands)
    wg, ginfo, gops = _fit(ops, gs, one, w_start[None], lam, occlusion, p.max_outer)
    w0 = np.broadcast_to(wg, (p.n_bands, *sub.shape)).copy()
    wr, rinfo, rops = _fit(ops, gs, many, w0, lam, occlusion, p.max_outer)
    glob = _motion(wg, ginfo, gops, gs, sub, one, boxes, lam, occlusion)
    roll = _motion(wr, rinfo, rops, gs, sub, many, boxes, lam, occlusion)
    (rss_g, rss_r), n = _inlier_rss([gops, rops], gs, [wg, wr],
                                    lam / 2.0 if occlusion else None)
    k_g, k_r = int(np.count_nonzero(wg)), int(np.count_nonzero(wr))
    n = max(n, 1)
    bic_g = n * np.log(max(rss_g, 1e-300) / n) + k_g * np.log(n)
    bic_r = n * np.log(max(rss_r, 1e-300) / n) + k_r * np.log(n)
    drop = 1.0 - rss_r / rss_g if rss_g > 0 else 0.0
    rolling = bool(bic_r < bic_g - p.bic_margin and drop >= p.min_drop
                   and roll.info["readout"] >= p.min_readout)
    crit = dict(n=n, rss_global=rss_g, rss_rolling=rss_r, k_global=k_g, k_rolling=k_r,
                bic_global=float(bic_g), bic_rolling=float(bic_r), drop=float(drop),
                readout=roll.info["readout"], rolling=rolling,
                fits=[dict(n_bands=1, n_outer=ginfo["n_outer"]),
                      dict(n_bands=p.n_bands, n_outer=rinfo["n_outer"])])
    return glob, roll, crit


def choose_shutter(
    reference,
    observed,
    grid: PoseGrid,
    *,
    w_start: np.ndarray,
    base: np.ndarray | None = None,
    lam: float = 0.1,
    occlusion: bool = True,
    params: RollingParams | None = None,
    boxes: Sequence | None = None,
    scale: float | None = None,
    bands: str = "all",
) -> ShutterChoice:
    """Fit the global and the rolling model on the same windows and pick one.

    Both live on :func:`support_grid` of ``w_start`` (a global estimate, e.g. the
    pipeline's on its own windows) and are solved on the same windows
    (:func:`rolling_windows` by default): the global model (one band) from ``w_start``,
    then the band model from the global fit (every band equal to it).  They are compared
    on the windows' pixels that both fits leave as inliers (``|r| <= lam / 2``) with the
    Bayesian information criterion of a Gaussian residual,
    ``BIC = n log(RSS / n) + k log n`` (``k`` the weights in use).  The rolling model is
    kept when ``BIC_rolling < BIC_global - params.bic_margin`` AND its RSS is lower by at
    least ``params.min_drop`` (a fraction) AND the estimated readout is at least
    ``params.min_readout``: the BIC alone treats the pixels as independent, while the
    model's error (bilinear warps, the grid's discretisation, the bands' interpolation)
    is spatially correlated, so more weights always win a little; the drop asks for a
    clearly better fit, and the readout for the drift a rolling shutter makes (a tilting
    global-shutter camera lets the bands fit their rows better too, without drift).

    With ``params.coarse`` (default) both fits and the criterion run on the windows'
    central parts (:func:`reblur.estimate.coarse_side` px each, 64 px: a sixth of the pixels
    of eighteen 160 px windows), and only when they keep the band model is it fitted again on
    the full windows, from the parts' band weights: a global-shutter pair costs two fits
    on the parts, a rolling one a band fit on the full windows more (``criterion["fits"]``
    lists them).  The parts decided as the full windows did on every benchmark pair
    (``python -m benchmarks.rolling``); the full-window band fit is the model the
    reblur uses (on the parts alone, recall of pasted changes fell at a full readout).
    That refit must read a readout of at least ``params.min_readout`` too, else the
    global model is kept (``criterion["refit_rejected"]``): the band model is worth its
    unknowns only for the drift, and the parts' estimate of it can be a fluke of their
    few pixels.

    ``bands="mean"`` solves that full-window refit of an image of several bands on their
    mean (a third of its cost for RGB: it is most of a rolling pair's choice), its change
    term and fit figures then computed per band (as
    :func:`reblur.estimate.estimate_motion`'s ``bands``); the choice itself is made on
    every band either way.
    """
    t0 = time.perf_counter()
    check_bands(bands)
    p = params or RollingParams()
    if boxes is None:
        boxes = rolling_windows(observed.shape[:2], p.n_bands, p.side, p.columns)
    boxes = [as_box(b) for b in boxes]
    sub = support_grid(grid, w_start, p.t_margin, p.b_margin)
    parts = [_shrink(b, coarse_side(len(boxes))) for b in boxes] if p.coarse else boxes
    coarse = any(a != b for a, b in zip(parts, boxes, strict=True))
    ops, gs = _window_operators(reference, observed, sub, parts, base, scale)
    glob, roll, crit = _evidence(ops, gs, sub, parts, embed_weights(w_start, sub, grid), lam,
                                 occlusion, p)
    rolling = crit.pop("rolling")
    crit["refit_rejected"] = False
    if rolling and coarse:
        del ops, gs
        on_mean = bands == "mean" and len(observed.shape) == 3 and observed.shape[2] > 1
        ops, gs = _window_operators(reference, observed, sub, boxes, base, scale,
                                    band_mean=on_mean)
        many = RowBands(grid.image_shape[0], p.n_bands)
        wr, rinfo, rops = _fit(ops, gs, many, roll.weights, lam, occlusion, p.max_outer)
        if on_mean:  # the change term and the fit per band, from the weights found
            ops, gs = _window_operators(reference, observed, sub, boxes, base, scale,
                                        spectra=False)
            rops = [RollingOperator.on(op, many) for op in ops]
        roll = _motion(wr, rinfo, rops, gs, sub, many, boxes, lam, occlusion)
        roll.info["bands"] = "mean" if on_mean else "all"
        crit["fits"].append(dict(n_bands=p.n_bands, n_outer=rinfo["n_outer"], full=True))
        if not roll.info["readout"] >= p.min_readout:  # the full windows see no drift
            rolling = False
            crit["refit_rejected"] = True
    crit.update(windows=[b.as_tuple() for b in parts], readout_final=roll.info["readout"],
                time_s=time.perf_counter() - t0,
                rule=f"rolling when BIC_rolling < BIC_global - {p.bic_margin:g}, the "
                     f"inlier RSS drops by >= {p.min_drop:g} and the estimated readout is "
                     f">= {p.min_readout:g}" + (" (on the windows' central parts), and the "
                                                "full-window refit's readout is >= "
                                                f"{p.min_readout:g} too" if coarse else ""))
    return ShutterChoice("rolling" if rolling else "global", glob, roll, crit)
