"""The change decision: observed vs reblurred reference, tile by tile.

The reblurred reference ``m`` should match the observation ``g`` except where the scene
changed.  The decision runs in four stages, built so that a gigapixel image can be processed
as a stream of tiles:

1. **Photometry** (:func:`fit_photometry`; global, fitted once from a sample of tiles or a
   downsampled image).  Per band, ``g ~ a * m + b`` by Huber IRLS (convex, so unique and
   stable even for weakly correlated captures; a minority of changed pixels has a bounded
   influence).  Optionally a smooth field: gain and offset on a grid of ``field_block``-pixel
   blocks, bilinearly interpolated between block centres (linearly extrapolated to the
   edges), fitted *jointly* in that same interpolated form by Huber IRLS with a small
   second-difference penalty (linear trends such as illumination ramps are free).  The
   residual scale ``sigma`` of each band (MAD of the inliers) is the unit of the statistic.
2. **Statistic** (:func:`change_statistic`; local).  ``z_c = (g_c - a_c m_c - b_c) / sigma_c``
   per band, ``sigma_c`` grown where the reblurred reference has edges and fine texture
   (model error: ``sigma_c^2 + (k |grad m|)^2 + (c lap m)^2``, fitted from the data), and
   ``S = sqrt(G * mean_c z_c^2 / G * 1)``: the RMS of the z-scores over a
   Gaussian window of ``smooth`` pixels, normalised over known pixels only (unknown pixels
   neither contribute nor receive a value).  Every band enters the sum, so a change in any
   one band counts; the window averages about ``4 pi smooth^2 C`` squared z-scores, which
   cuts the variance of the statistic accordingly.
3. **Threshold** (:func:`estimate_threshold`; global, from a sample of ``S`` values).  The
   robust bound ``median + 4 MAD`` of the bulk of ``S``, or Otsu's split of its histogram
   when that is lower AND the bulk is broad (``MAD >= 0.4 median``): on pairs taken years
   apart the "unchanged" class is a continuum of real appearance changes, far wider than
   noise, and Otsu is the lower, adaptive split.  Where the bulk is as narrow as noise
   makes it (``S`` averages ~``4 pi smooth^2`` squared z-scores: a relative spread of
   ~0.1) it is the unchanged class, and Otsu would cut through it: with no change in the
   sample (a gigapixel image sampled on 1.7 % of its area) it fell just above the median,
   and 2.9 % of an unchanged image came out as change despite the hysteresis below.  When
   the changes are well separated, Otsu lands midway between the classes and the robust
   bound keeps faint changes.  ``threshold=`` overrides it.
4. **Regions** (local up to the extent of a change region).  A component tree over the
   levels ``threshold * levels``: at each level ``S > level`` is opened with a disc of
   ``open_radius`` (removes the thin bands that parallax and residual mis-registration leave
   along edges) and labelled (8-connectivity).  A component is

   * dropped if smaller than ``min_area`` or if it holds no *strong* pixel
     (``S >= strong_factor * threshold``: hysteresis, a region needs strong evidence somewhere
     and then keeps its weaker surroundings down to the threshold);
   * **accepted** if it looks like an object: solidity (area / convex-hull area)
     ``>= min_solidity`` and aspect ``area / (2 r_in)^2 <= max_aspect`` (``r_in``: radius of
     the largest inscribed disc; an ``a x b`` rectangle has aspect ``a / b``);
   * otherwise (a branching network of roads or vegetation edges, or several objects merged
     through weak bridges) passed to the next, stricter level, where it may split into
     object-like parts.  What is still not object-like at the last level is dropped.

   Accepted regions are trimmed to their half-energy contour
   (``S >= boundary_fraction * median(S in region)``: an absolute threshold lies far down the
   flank of a strong change and would bleed outwards), pieces below ``min_area`` go, each
   region is closed on its own with a disc of ``close_radius`` (an object whose inside
   partly matches the background -- a low-contrast object, a roof like the ground -- is
   found with bays cut into it; the closing fills those narrower than the disc), enclosed
   holes up to ``max_hole_area`` are filled, and unknown pixels are never change.

Tiling
------
Stages 1 and 3 are global: fit them on a sample of tiles, then pass ``photometry`` and
``threshold`` to :func:`decide_tile` for every tile.  Stage 2 is a filter of radius
``int(truncate * smooth + 0.5)``; stage 4 looks at whole connected regions.
:func:`decide_tile` takes a padded tile (core plus halo) and returns the core; its result
equals the whole-image :func:`decide` (same photometry and threshold) exactly when every
candidate region reaching the core stays ``params.local_radius`` pixels clear of every tile
edge that is not an image border.  Hence the halo requirement

    ``halo >= params.local_radius + R``

with ``R`` how far a candidate region (a connected set of ``S > threshold`` after the
opening) reaches out of the core.  ``R`` depends on the data: take the largest change object
expected (``params.halo(R)``) and check ``info["complete"]``; False means a region came too
close to the tile edge, and the tile should be re-run with a larger halo.

Defaults
--------
Pixel sizes (``smooth=2``, ``open_radius=3``, ``min_area=100``, ``close_radius=8``) suit
imagery where the objects of interest are at least ~10 x 10 px; scale them with the ground
resolution (``close_radius=8`` fills bays up to 16 px wide; docs/NOTES.md, fifth stop, for
its effect and the radii tried).  The
shape limits are generic: L- or T-shaped objects have solidity 0.7-0.9, branching networks
0.1-0.5 (``min_solidity=0.65`` lies between, on the flat part of the measured curve: 0.6 and
0.7 give the same Jaccard on the development pairs, 0.75 loses 0.03); ``max_aspect=8``
rejects strips.  The smooth photometric field is off by default: on real pairs years apart
(``benchmarks/decision.py``) the differences are real appearance changes, not illumination,
and a 256-px field absorbs area-wide changes (mean Jaccard 0.30 -> 0.21); turn it on
(``field_block``, several times the largest change object) for illumination, haze or
vignetting differences.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import cv2
import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from skimage.filters import threshold_otsu
from skimage.morphology import convex_hull_image

from .robust import MAD_TO_SIGMA, huber_line, mad

__all__ = [
    "Photometry",
    "fit_photometry",
    "DecisionParams",
    "change_statistic",
    "estimate_threshold",
    "fit_model_error",
    "decide_tile",
    "decide",
    "tile_boxes",
]


# --------------------------------------------------------------------------- helpers
def _channels(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    return a[:, :, None] if a.ndim == 2 else a


def _float(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    if a.dtype in (np.float32, np.float64):
        return a
    return a.astype(np.float32)


def _box(box) -> tuple[int, int, int, int]:
    if hasattr(box, "as_tuple"):
        box = box.as_tuple()
    y0, x0, h, w = (int(v) for v in box)
    if h < 1 or w < 1:
        raise ValueError(f"box must have positive size, got {(y0, x0, h, w)}")
    return y0, x0, h, w


def _robust_scale(r: np.ndarray, k: float = 3.5, n_iter: int = 5) -> float:
    """Standard deviation of the inliers: MAD, re-estimated on ``|r - med| < k * scale``.

    The plain MAD is inflated by a large fraction of changed pixels (by 30 % with 20 %
    gross outliers); trimming beyond ``k = 3.5`` scales removes them and biases a Gaussian's
    MAD by less than 0.1 %.
    """
    r = r[np.isfinite(r)]
    if r.size == 0:
        return float("nan")
    med = float(np.median(r))
    d = np.abs(r - med)
    s = MAD_TO_SIGMA * float(np.median(d))
    for _ in range(n_iter):
        keep = d < k * s
        if not keep.any():
            break
        s_new = MAD_TO_SIGMA * float(np.median(d[keep]))
        if s_new == s:
            break
        s = s_new
    return s


def _grid_coords(f: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cell index, next index and weight of block coordinates ``f`` on ``n`` block centres.

    Linear between the centres and linearly extrapolated to the image edge (at most half a
    block beyond the outer centres): a linear ramp is reproduced exactly everywhere.
    """
    f = np.clip(f, -0.5, n - 0.5)
    i = np.clip(np.floor(f).astype(int), 0, max(n - 2, 0))
    i1 = np.minimum(i + 1, n - 1)
    wgt = f - i if n > 1 else np.zeros_like(f)
    return i, i1, wgt


def _grid_interp(grid: np.ndarray, y0: int, x0: int, h: int, w: int, block: int) -> np.ndarray:
    """Bilinear interpolation of block-centre values on a pixel window (per pixel exact)."""
    ny, nx = grid.shape
    iy, iy1, wy = _grid_coords((np.arange(y0, y0 + h) + 0.5) / block - 0.5, ny)
    ix, ix1, wx = _grid_coords((np.arange(x0, x0 + w) + 0.5) / block - 0.5, nx)
    wy = wy[:, None]
    wx = wx[None, :]
    g00 = grid[iy][:, ix]
    g01 = grid[iy][:, ix1]
    g10 = grid[iy1][:, ix]
    g11 = grid[iy1][:, ix1]
    return (1 - wy) * ((1 - wx) * g00 + wx * g01) + wy * ((1 - wx) * g10 + wx * g11)


def _grid_sample(grid: np.ndarray, ys: np.ndarray, xs: np.ndarray, block: int) -> np.ndarray:
    """The same interpolation at scattered full-image points ``(ys, xs)``."""
    ny, nx = grid.shape
    iy, iy1, wy = _grid_coords((ys + 0.5) / block - 0.5, ny)
    ix, ix1, wx = _grid_coords((xs + 0.5) / block - 0.5, nx)
    return (1 - wy) * ((1 - wx) * grid[iy, ix] + wx * grid[iy, ix1]) + wy * (
        (1 - wx) * grid[iy1, ix] + wx * grid[iy1, ix1]
    )


# --------------------------------------------------------------------------- photometry
@dataclass(frozen=True, eq=False)
class Photometry:
    """Per-band photometric model ``observed ~ gain(x) * reblurred + offset(x)``.

    Attributes
    ----------
    gain, offset : (C,) ndarray
        Global robust gain and offset per band.
    sigma : (C,) ndarray
        Robust (MAD) scale of the residual ``observed - model`` per band: the unit of the
        change statistic.
    image_shape : (int, int) or None
        Full-image ``(height, width)`` the model lives on (needed by the field and by
        :func:`decide_tile` to tell image borders from tile edges).
    field_block : int or None
        Block size (pixels) of the smooth field, None when there is no field.
    field_gain, field_offset : (C, ny, nx) ndarray or None
        Gain and offset at the block centres ``((i + 0.5) * block - 0.5)``, interpolated
        bilinearly (constant beyond the outer centres).
    edge_k, curv_k : (C,) ndarray or None
        Model error of the reblur per band (:func:`fit_model_error`): the residual variance
        grows by ``(edge_k |grad m|)^2 + (curv_k lap m)^2`` (see :func:`change_statistic`).
    info : dict
        Fit details (samples used, blocks fitted).
    """

    gain: np.ndarray
    offset: np.ndarray
    sigma: np.ndarray
    image_shape: tuple[int, int] | None = None
    field_block: int | None = None
    field_gain: np.ndarray | None = None
    field_offset: np.ndarray | None = None
    edge_k: np.ndarray | None = None
    curv_k: np.ndarray | None = None
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def n_bands(self) -> int:
        return int(np.asarray(self.gain).size)

    @property
    def has_field(self) -> bool:
        return self.field_gain is not None

    def apply(self, reblurred: np.ndarray, box=None) -> np.ndarray:
        """Map a reblurred tile into the observation's photometry.

        Parameters
        ----------
        reblurred : (h, w) or (h, w, C) ndarray
            Reblurred reference tile.
        box : (y0, x0, h, w) or Box, optional
            Position of the tile in the full image (needed only with a field; default the
            top-left corner).

        Returns
        -------
        ndarray
            Same shape, float32 (float64 stays float64).
        """
        r = _float(reblurred)
        rc = _channels(r)
        if rc.shape[2] != self.n_bands:
            raise ValueError(
                f"reblurred has {rc.shape[2]} band(s), the photometric model has {self.n_bands}"
            )
        y0, x0, h, w = (0, 0, *rc.shape[:2]) if box is None else _box(box)
        if (h, w) != rc.shape[:2]:
            raise ValueError(f"box size {(h, w)} does not match the tile shape {rc.shape[:2]}")
        out = np.empty(rc.shape, dtype=r.dtype)
        for c in range(rc.shape[2]):
            if self.has_field:
                g = _grid_interp(self.field_gain[c], y0, x0, h, w, self.field_block)
                o = _grid_interp(self.field_offset[c], y0, x0, h, w, self.field_block)
                out[:, :, c] = g * rc[:, :, c] + o
            else:
                out[:, :, c] = self.gain[c] * rc[:, :, c] + self.offset[c]
        return out[:, :, 0] if r.ndim == 2 else out

    def residual_sigma(
        self, observed: np.ndarray, reblurred: np.ndarray, valid=None, box=None
    ) -> np.ndarray:
        """Robust scale (MAD of the inliers) per band of ``observed - apply(reblurred, box)``.

        Use it on full-resolution tiles when the model was fitted on a downsampled image.
        """
        o = _channels(_float(observed))
        m = _channels(self.apply(reblurred, box))
        if o.shape != m.shape:
            raise ValueError(f"observed has shape {o.shape}, reblurred {m.shape}")
        ok = np.all(np.isfinite(o), axis=2) & np.all(np.isfinite(m), axis=2)
        if valid is not None:
            ok &= np.asarray(valid, dtype=bool)
        return np.array([_robust_scale((o[:, :, c] - m[:, :, c])[ok]) for c in range(o.shape[2])])

    def with_sigma(self, sigma) -> Photometry:
        """Copy with another residual scale (e.g. measured on full-resolution tiles)."""
        s = np.asarray(sigma, dtype=np.float64).reshape(-1)
        if s.size != self.n_bands or not np.all(s > 0):
            raise ValueError(f"sigma must hold {self.n_bands} positive value(s), got {sigma}")
        return dataclasses.replace(self, sigma=s)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description."""
        d: dict[str, Any] = {
            "gain": [float(v) for v in self.gain],
            "offset": [float(v) for v in self.offset],
            "sigma": [float(v) for v in self.sigma],
            "image_shape": None if self.image_shape is None else list(self.image_shape),
            "field_block": self.field_block,
            "edge_k": None if self.edge_k is None else [float(v) for v in self.edge_k],
            "curv_k": None if self.curv_k is None else [float(v) for v in self.curv_k],
        }
        if self.has_field:
            d["field_gain"] = np.asarray(self.field_gain).tolist()
            d["field_offset"] = np.asarray(self.field_offset).tolist()
        d["info"] = dict(self.info)
        return d


def _collect_samples(observed, reblurred, valid, boxes, scale, rng, max_samples):
    """Gather ``(y, x, obs (n, C), reb (n, C))`` samples in full-image coordinates."""
    if isinstance(observed, np.ndarray) or not isinstance(observed, Sequence):
        observed, reblurred = [observed], [reblurred]
        valid = [valid]
        if boxes is not None:
            boxes = [boxes]
    else:
        if not isinstance(reblurred, Sequence) or len(reblurred) != len(observed):
            raise ValueError("observed and reblurred must be sequences of the same length")
        if valid is None:
            valid = [None] * len(observed)
        elif len(valid) != len(observed):
            raise ValueError("valid must be a sequence as long as observed")
        if boxes is None or len(boxes) != len(observed):
            raise ValueError("tiles need their boxes: pass boxes=[(y0, x0, h, w), ...]")
    per_tile = max(1, int(max_samples) // len(observed))
    ys, xs, os_, rs = [], [], [], []
    n_bands = None
    for k, (o, r, v) in enumerate(zip(observed, reblurred, valid, strict=True)):
        o = _channels(_float(o))
        r = _channels(_float(r))
        if o.shape != r.shape:
            raise ValueError(f"observed tile {k} has shape {o.shape}, reblurred {r.shape}")
        if n_bands is None:
            n_bands = o.shape[2]
        elif o.shape[2] != n_bands:
            raise ValueError("all tiles must have the same number of bands")
        ok = np.all(np.isfinite(o), axis=2) & np.all(np.isfinite(r), axis=2)
        if v is not None:
            v = np.asarray(v, dtype=bool)
            if v.shape != o.shape[:2]:
                raise ValueError(f"valid mask {k} has shape {v.shape}, expected {o.shape[:2]}")
            ok &= v
        idx = np.flatnonzero(ok)
        if idx.size > per_tile:
            idx = np.sort(rng.choice(idx, per_tile, replace=False))
        iy, ix = np.divmod(idx, o.shape[1])
        y0, x0 = (0, 0) if boxes is None else _box(boxes[k])[:2]
        ys.append((iy + 0.5) * scale - 0.5 + y0)
        xs.append((ix + 0.5) * scale - 0.5 + x0)
        os_.append(o.reshape(-1, n_bands)[idx])
        rs.append(r.reshape(-1, n_bands)[idx])
    return np.concatenate(ys), np.concatenate(xs), np.concatenate(os_), np.concatenate(rs)


def _fit_field(
    ys: np.ndarray,
    xs: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    shape: tuple[int, int],
    block: int,
    start: tuple[float, float],
    smoothness: float,
    n_iter: int = 10,
) -> tuple[np.ndarray, np.ndarray]:
    """Joint robust fit of gain and offset grids, interpolated exactly as applied.

    Model: ``y_i = sum_k phi_k(i) (g_k x_i + o_k)`` with ``phi`` the bilinear weights of
    :func:`_grid_interp`.  Huber IRLS; the penalty ``smoothness * (n / N)`` times the
    squared second differences of the node values (gain scaled by the reference spread so
    that both are intensities) does not penalise linear trends, and keeps nodes with little
    data or a flat reference (no gain to fit) in line with their neighbours.
    """
    ny, nx = shape
    N = ny * nx
    n = x.size
    iy, iy1, wy = _grid_coords((ys + 0.5) / block - 0.5, ny)
    ix, ix1, wx = _grid_coords((xs + 0.5) / block - 0.5, nx)
    cols = np.stack([iy * nx + ix, iy * nx + ix1, iy1 * nx + ix, iy1 * nx + ix1], axis=1)
    phi = np.stack([(1 - wy) * (1 - wx), (1 - wy) * wx, wy * (1 - wx), wy * wx], axis=1)
    rows = np.repeat(np.arange(n), 4)
    A = sp.csr_matrix(
        (
            np.concatenate([(phi * x[:, None]).ravel(), phi.ravel()]),
            (np.concatenate([rows, rows]), np.concatenate([cols.ravel(), cols.ravel() + N])),
        ),
        shape=(n, 2 * N),
    )
    sx = max(mad(x), 1e-3)
    diffs = []
    eye_y, eye_x = sp.identity(ny), sp.identity(nx)
    if ny >= 3:
        d = sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(ny - 2, ny))
        diffs.append(sp.kron(d, eye_x))
    if nx >= 3:
        d = sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(nx - 2, nx))
        diffs.append(sp.kron(eye_y, d))
    lam = smoothness * n / N
    R = sp.csr_matrix((2 * N, 2 * N))
    if diffs:
        D = sp.vstack(diffs)
        DtD = (D.T @ D).tocsr()
        R = sp.block_diag([sx * sx * DtD, DtD]).tocsr() * lam
    mu = 1e-6 * n / N  # tiny ridge towards the global model: keeps the system definite
    prior = np.concatenate([np.full(N, start[0]), np.full(N, start[1])])
    Rmu = R + sp.block_diag([sx * sx * sp.identity(N), sp.identity(N)]) * mu
    p = prior.copy()
    for _ in range(n_iter):
        r = y - A @ p
        s = mad(r)
        if not s > 0:
            break
        w = np.minimum(1.0, 1.345 * s / np.maximum(np.abs(r), 1e-12))
        AtW = A.T.multiply(w).tocsr()
        M = (AtW @ A + Rmu).tocsc()
        rhs = AtW @ y + (Rmu - R) @ prior
        p_new = spla.spsolve(M, rhs)
        done = np.max(np.abs(p_new - p)) < 1e-6
        p = p_new
        if done:
            break
    return p[:N].reshape(ny, nx), p[N:].reshape(ny, nx)


def fit_photometry(
    observed,
    reblurred,
    valid=None,
    *,
    boxes=None,
    image_shape: tuple[int, int] | None = None,
    scale: float = 1.0,
    field_block: int | None = None,
    max_samples: int = 200_000,
    smoothness: float = 0.01,
    edge_error: bool = True,
    rng=None,
) -> Photometry:
    """Fit the per-band photometric model robustly, from a whole image or from a sample.

    Parameters
    ----------
    observed, reblurred : ndarray or sequence of ndarray
        The observation and the (aligned) reblurred reference, ``(h, w)`` or ``(h, w, C)``:
        either one array (the whole image, or a downsampled version of it, see ``scale``) or
        a sequence of tiles with their ``boxes``.
    valid : bool ndarray or sequence of them, optional
        Pixels to use (known and trusted); non-finite pixels are always left out.
    boxes : sequence of (y0, x0, h, w), optional
        Full-image position of each tile (required for a sequence of tiles).
    image_shape : (int, int), optional
        Full-image ``(height, width)``; default the array shape times ``scale`` (one array)
        or the bounding box of the tiles.
    scale : float
        For one array: its pixel ``(i, j)`` stands for full-image position
        ``((i + 0.5) * scale - 0.5, (j + 0.5) * scale - 0.5)``.  Gain and offset commute with
        averaging, so a downsampled image gives the same model; its residual scale
        ``sigma`` however is that of the downsampled data: measure it on full-resolution
        tiles before deciding,
        ``ph = ph.with_sigma(ph.residual_sigma(obs_tile, reb_tile, valid_tile, box))``.
    field_block : int, optional
        Block size (full-image pixels) of the smooth gain/offset field; None (default): a
        global model only.  Each block centre's values are fitted on the 2 x 2 blocks around
        it; a change covering much of that support is partly absorbed, so pick blocks
        several times larger than the largest change object.
    max_samples : int
        Samples drawn (seeded) for the fit; with a field at least ``2048`` per block.
    smoothness : float
        Weight of the field's second-difference penalty, relative to the samples per block
        (see ``_fit_field``); linear trends are not penalised.
    rng : int or numpy.random.Generator, optional
        Seed of the subsampling (default 0: reproducible).

    edge_error : bool
        Also fit the model error ``edge_k`` and ``curv_k`` (:func:`fit_model_error`) on
        full-resolution input (not when ``scale != 1``).

    Returns
    -------
    Photometry

    Raises
    ------
    ValueError
        On mismatched shapes, a missing box, or too few valid pixels (< 10).
    """
    rng = np.random.default_rng(0 if rng is None else rng)
    if field_block is not None and int(field_block) < 8:
        raise ValueError(f"field_block must be at least 8 pixels, got {field_block}")
    if not scale > 0:
        raise ValueError(f"scale must be positive, got {scale}")
    single = isinstance(observed, np.ndarray) or not isinstance(observed, Sequence)
    if image_shape is None:
        if single:
            a = np.asarray(observed)
            image_shape = (int(round(a.shape[0] * scale)), int(round(a.shape[1] * scale)))
        else:
            if boxes is None:
                raise ValueError("tiles need their boxes: pass boxes=[(y0, x0, h, w), ...]")
            bb = [_box(b) for b in boxes]
            image_shape = (max(b[0] + b[2] for b in bb), max(b[1] + b[3] for b in bb))
    image_shape = (int(image_shape[0]), int(image_shape[1]))
    n_blocks = 0
    if field_block is not None:
        field_block = int(field_block)
        ny = -(-image_shape[0] // field_block)
        nx = -(-image_shape[1] // field_block)
        n_blocks = ny * nx
        max_samples = max(int(max_samples), 2048 * n_blocks)
    ys, xs, obs, reb = _collect_samples(observed, reblurred, valid, boxes, scale, rng, max_samples)
    if obs.shape[0] < 10:
        raise ValueError(f"only {obs.shape[0]} valid pixel(s) to fit the photometry on")
    C = obs.shape[1]
    gain = np.empty(C)
    offset = np.empty(C)
    sigma = np.empty(C)
    for c in range(C):
        gain[c], offset[c] = huber_line(reb[:, c], obs[:, c])
        sigma[c] = _robust_scale(obs[:, c] - gain[c] * reb[:, c] - offset[c])
    info: dict[str, Any] = {"n_samples": int(obs.shape[0]), "method": "Huber IRLS"}
    fg = fo = None
    if field_block is not None:
        fg = np.repeat(gain[:, None, None], ny * nx, 1).reshape(C, ny, nx)
        fo = np.repeat(offset[:, None, None], ny * nx, 1).reshape(C, ny, nx)
        for c in range(C):
            fg[c], fo[c] = _fit_field(
                ys, xs, reb[:, c], obs[:, c], (ny, nx), field_block,
                (gain[c], offset[c]), smoothness,
            )
        info.update(field_shape=[ny, nx], smoothness=float(smoothness))
        # residual scale of the full model
        for c in range(C):
            gg = _grid_sample(fg[c], ys, xs, field_block)
            oo = _grid_sample(fo[c], ys, xs, field_block)
            sigma[c] = _robust_scale(obs[:, c] - gg * reb[:, c] - oo)
    sigma = np.where(sigma > 0, sigma, np.finfo(np.float32).eps)
    ph = Photometry(
        gain=gain, offset=offset, sigma=sigma, image_shape=image_shape,
        field_block=field_block, field_gain=fg, field_offset=fo, info=info,
    )
    if edge_error and scale == 1.0:
        # gradients need full-resolution data: tiles or the whole image
        if isinstance(observed, np.ndarray) or not isinstance(observed, Sequence):
            tiles = [(observed, reblurred, valid, None)]
        else:
            vs = valid if valid is not None else [None] * len(observed)
            tiles = list(zip(observed, reblurred, vs, boxes, strict=True))
        os_, ms_, ks_ = [], [], []
        for o, r, v, b in tiles:
            o = _channels(_float(o))
            k = np.all(np.isfinite(o), axis=2)
            if v is not None:
                k &= np.asarray(v, bool)
            os_.append(o)
            ms_.append(_channels(ph.apply(r, b)))
            ks_.append(k)
        ek, ck = fit_model_error(os_, ms_, ks_, sigma)
        ph = dataclasses.replace(ph, edge_k=ek, curv_k=ck)
    return ph



# --------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class DecisionParams:
    """Parameters of the statistic and of the region-level decision.

    Attributes
    ----------
    smooth : float
        Standard deviation (pixels) of the Gaussian window of the local RMS statistic;
        0 for none.
    truncate : float
        Gaussian window radius in units of ``smooth``.
    open_radius : int
        Radius of the disc of the opening at each level (0 for none).
    min_area : int
        Smallest region kept, in pixels.
    strong_factor : float
        A region must contain a pixel with ``S >= strong_factor * threshold``.
    levels : tuple of float
        Threshold multipliers of the component tree, increasing, starting at 1.
    min_solidity : float
        Smallest area / convex-hull area of an accepted region.
    max_aspect : float
        Largest ``area / (2 r_in)^2`` of an accepted region (``r_in``: inscribed radius).
    boundary_fraction : float
        Accepted regions are trimmed to ``S >= boundary_fraction * median(S in region)``
        (0: no trimming).  ``S`` is an RMS, so ``1/sqrt(2)`` is the half-energy contour,
        which lies on the edge of a sharp step; about 0.5 suits edges blurred over more
        than the statistic's window.
    close_radius : int
        Radius of the disc with which each accepted region is closed (on its own, so
        neighbouring regions never merge) before the hole filling: bays narrower than
        ``2 close_radius`` that open to the outside are filled.  0 for none.
    max_hole_area : int
        Largest enclosed hole filled, in pixels (0: no filling).
    region_tests : bool
        False skips the shape tests and the component tree (one level, area and
        hysteresis only): the pixel-level decision, for comparison.
    """

    smooth: float = 2.0
    truncate: float = 4.0
    open_radius: int = 3
    min_area: int = 100
    strong_factor: float = 2.0
    levels: tuple[float, ...] = (1.0, 1.25, 1.5, 2.0, 2.5, 3.0)
    min_solidity: float = 0.65
    max_aspect: float = 8.0
    boundary_fraction: float = 0.7071
    close_radius: int = 8
    max_hole_area: int = 1024
    region_tests: bool = True

    def __post_init__(self):
        lv = tuple(float(v) for v in self.levels)
        object.__setattr__(self, "levels", lv)
        if not lv or lv[0] != 1.0 or any(b <= a for a, b in zip(lv, lv[1:], strict=False)):
            raise ValueError(f"levels must increase from 1.0, got {self.levels}")
        if self.smooth < 0 or self.truncate <= 0:
            raise ValueError("smooth must be >= 0 and truncate > 0")
        if min(self.open_radius, self.min_area, self.max_hole_area, self.close_radius) < 0:
            raise ValueError("open_radius, min_area, close_radius and max_hole_area must be >= 0")
        if self.strong_factor < 1.0:
            raise ValueError(f"strong_factor must be >= 1, got {self.strong_factor}")
        if not 0.0 <= self.boundary_fraction < 1.0:
            raise ValueError(f"boundary_fraction must lie in [0, 1), got {self.boundary_fraction}")
        if not 0.0 <= self.min_solidity <= 1.0 or self.max_aspect < 1.0:
            raise ValueError("min_solidity must lie in [0, 1] and max_aspect be >= 1")

    @property
    def smooth_radius(self) -> int:
        """Radius of the statistic's Gaussian window (as scipy.ndimage truncates it)."""
        return int(self.truncate * self.smooth + 0.5) if self.smooth > 0 else 0

    @property
    def local_radius(self) -> int:
        """Reach of the pixel-local steps: statistic window + opening (2 r) + 1."""
        return self.smooth_radius + 2 * int(self.open_radius) + 2  # + 1 for the gradient

    def halo(self, max_region_extent: int = 256) -> int:
        """Tile halo for exact tiled results with regions reaching ``max_region_extent`` px."""
        return self.local_radius + int(max_region_extent)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["levels"] = list(self.levels)
        return d


def _params(params: DecisionParams | None, overrides: dict[str, Any]) -> DecisionParams:
    p = params if params is not None else DecisionParams()
    if overrides:
        names = {f.name for f in dataclasses.fields(DecisionParams)}
        bad = sorted(set(overrides) - names)
        if bad:
            raise TypeError(f"unknown decision parameter(s) {bad}; known: {sorted(names)}")
        p = dataclasses.replace(p, **overrides)
    return p


# --------------------------------------------------------------------------- statistic
def change_statistic(
    observed: np.ndarray,
    matched: np.ndarray,
    known: np.ndarray,
    sigma,
    *,
    smooth: float = 2.0,
    truncate: float = 4.0,
    edge_k=None,
    curv_k=None,
) -> np.ndarray:
    """Local RMS of the robust per-band z-scores of ``observed - matched``.

    With ``edge_k`` and ``curv_k`` (per band), the residual scale grows with the local
    structure of the reblurred reference:
    ``sigma_c(x)^2 = sigma_c^2 + (edge_k_c |grad m_c(x)|)^2 + (curv_k_c lap m_c(x))^2``.
    The reblur model is exact only up to a fraction of a pixel: a residual mis-registration
    ``d`` leaves ``d |grad m|`` (strong on edges), and the difference between the
    interpolation of a few grid poses and the camera's continuous motion acts like a
    slight change of sharpness, ``~ c lap m`` (strong on fine texture).  Both are nil on
    flat ground; normalising by them stops edges and fine texture from being flagged while
    keeping flat-area sensitivity (:func:`fit_model_error` measures both from the data).

    Parameters
    ----------
    observed, matched : (h, w) or (h, w, C) ndarray
        Observation and photometrically matched reblurred reference (same shape).
    known : (h, w) bool ndarray
        Pixels where both are defined.
    sigma : float or (C,) array_like
        Residual scale of each band (:attr:`Photometry.sigma`).
    smooth, truncate : float
        Gaussian window (standard deviation in pixels, radius in standard deviations).

    Returns
    -------
    S : (h, w) float32 ndarray
        ``sqrt(sum_w G * mean_c z_c^2 / sum_w G)`` over known pixels; 0 where unknown.

    Notes
    -----
    The value at a pixel depends only on pixels within ``int(truncate * smooth + 0.5)``,
    so a tile with at least that halo gives the whole-image values on its core.
    """
    o = _channels(_float(observed))
    m = _channels(_float(matched))
    if o.shape != m.shape:
        raise ValueError(f"observed has shape {o.shape} but matched has shape {m.shape}")
    known = np.asarray(known, dtype=bool)
    if known.shape != o.shape[:2]:
        raise ValueError(f"known has shape {known.shape}, expected {o.shape[:2]}")
    s = np.broadcast_to(np.asarray(sigma, dtype=np.float64).reshape(-1), (o.shape[2],))
    C = o.shape[2]
    ks = np.zeros(C) if edge_k is None else np.broadcast_to(
        np.asarray(edge_k, dtype=np.float64).reshape(-1), (C,))
    kc = np.zeros(C) if curv_k is None else np.broadcast_to(
        np.asarray(curv_k, dtype=np.float64).reshape(-1), (C,))
    all_known = bool(known.all())
    h, w = known.shape
    # every per-pixel step runs over bands of rows that stay in cache, operation for
    # operation as ``where(known, (o - m)^2 / var, 0)`` with
    # ``var = s^2 + ks^2 grad2 + kc^2 lap2`` on whole arrays (the same roundings), in
    # single precision like the images (a statistic compared with a threshold fitted to
    # its own quantiles needs no more; the Gaussian window runs twice as fast)
    bands = [slice(y, min(y + max(1, _STAT_BAND // w), h))
             for y in range(0, h, max(1, _STAT_BAND // w))]
    f32 = np.float32
    e = np.zeros((h, w), f32) if C > 1 else np.empty((h, w), f32)
    for c in range(C):
        mc = m[:, :, c]
        g32 = _grad2_f32(mc) if ks[c] > 0 else None
        l32 = _laplacian_f32(mc) if kc[c] > 0 else None
        s2 = f32(s[c] * s[c])
        for sl in bands:
            t = o[sl, :, c].astype(f32)
            t -= mc[sl]
            t *= t
            var: Any = None
            if g32 is not None:
                var = g32[sl] * f32(ks[c] * ks[c])
                var += s2
            if l32 is not None:
                lap = l32[sl] * l32[sl]
                lap *= f32(kc[c] * kc[c])
                if var is None:
                    var = lap
                    var += s2
                else:
                    var += lap
            t /= s2 if var is None else var
            if not all_known:
                t[~known[sl]] = 0.0
            if C == 1:
                e[sl] = t
            else:
                e[sl] += t
    if C > 1:
        e /= f32(C)
    if smooth > 0:
        num = gaussian_zero(e, smooth, truncate)
        den, positive = (_gaussian_ones(known.shape, smooth, truncate) if all_known
                         else (gaussian_zero(known.astype(f32), smooth, truncate), False))
        if positive:  # den > 1e-6 everywhere: the where() below would change nothing
            for sl in bands:
                np.divide(num[sl], den[sl], out=num[sl])
            e = num
        else:
            e = np.where(den > 1e-6, num / np.maximum(den, f32(1e-6)), f32(0.0))
    S = np.empty((h, w), np.float32)
    for sl in bands:
        v = e[sl]
        np.maximum(v, 0.0, out=v)
        np.sqrt(v, out=S[sl])
    if not all_known:
        S[~known] = 0.0
    return S


#: Elements of one band of rows of the statistic's per-pixel steps (256 KB of float32).
_STAT_BAND = 1 << 16


#: Cache of :func:`_gaussian_ones`, least recently used first (a handful of tile shapes
#: recur over a tiled pass: interior, edge and corner tiles, and their re-runs).
_ONES_CACHE: dict[tuple[int, int, float, float], tuple[np.ndarray, bool]] = {}
_ONES_LOCK = threading.Lock()
_ONES_MAX = 6


def _gaussian_ones(shape: tuple[int, int], sigma: float,
                   truncate: float) -> tuple[np.ndarray, bool]:
    """``gaussian_zero(ones(shape, float32))`` (read-only, cached by shape) and whether it
    exceeds 1e-6 everywhere.  The cached array holds the very bits a new call would
    return."""
    key = (int(shape[0]), int(shape[1]), float(sigma), float(truncate))
    with _ONES_LOCK:
        hit = _ONES_CACHE.pop(key, None)
        if hit is not None:
            _ONES_CACHE[key] = hit  # most recently used: last
    if hit is None:
        g = gaussian_zero(np.ones(key[:2], np.float32), sigma, truncate)
        g.flags.writeable = False
        hit = (g, bool(g.min() > 1e-6))
        with _ONES_LOCK:
            _ONES_CACHE[key] = hit
            while len(_ONES_CACHE) > _ONES_MAX:
                _ONES_CACHE.pop(next(iter(_ONES_CACHE)))
    return hit


def gaussian_zero(a: np.ndarray, sigma: float, truncate: float = 4.0) -> np.ndarray:
    """Gaussian filter with zeros outside ``a`` (float32 stays float32, else float64).

    The kernel and border of ``scipy.ndimage.gaussian_filter(a, sigma, mode="constant",
    truncate=truncate)`` (radius ``int(truncate * sigma + 0.5)``), run by OpenCV: about
    three times faster, and it releases the GIL, so tile threads run it in parallel.
    """
    r = int(truncate * sigma + 0.5)
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    k /= k.sum()
    if np.asarray(a).dtype == np.float32:
        a = np.ascontiguousarray(a)
        k = k.astype(np.float32)
        return cv2.sepFilter2D(a, cv2.CV_32F, k, k, borderType=cv2.BORDER_CONSTANT)
    a = np.ascontiguousarray(a, dtype=np.float64)
    return cv2.sepFilter2D(a, cv2.CV_64F, k, k, borderType=cv2.BORDER_CONSTANT)


def _grad2_f32(a: np.ndarray) -> np.ndarray:
    """Squared gradient magnitude in float32 (central 3x3 Sobel scaled to unit spacing)."""
    a = np.ascontiguousarray(a, dtype=np.float32)
    gx = cv2.Sobel(a, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT)
    gy = cv2.Sobel(a, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT)
    gx /= 8.0
    gy /= 8.0
    gx *= gx
    gy *= gy
    gx += gy
    return gx


def _laplacian_f32(a: np.ndarray) -> np.ndarray:
    """Laplacian in float32 (4-neighbour 3x3 stencil)."""
    a = np.ascontiguousarray(a, dtype=np.float32)
    return cv2.Laplacian(a, cv2.CV_32F, ksize=1, borderType=cv2.BORDER_REFLECT)


def fit_model_error(observed, matched, known, sigma, *, bins: int = 8,
                    max_samples: int = 400_000, k_max: float = 0.5, c_max: float = 0.5,
                    rng=0) -> tuple[np.ndarray, np.ndarray]:
    """Model error of the reblur: the ``edge_k`` and ``curv_k`` of :func:`change_statistic`.

    The residual is modelled as ``N(0, sigma^2 + a |grad m|^2 + b (lap m)^2)`` per band.
    Known pixels (a random sample of at most ``max_samples``) are binned by the quantiles
    of ``|grad m|^2`` and of ``(lap m)^2`` (``bins x bins`` cells); in each cell the excess
    variance is the median of ``r^2`` over 0.455 (the median of a chi-square with one
    degree of freedom) minus ``sigma^2`` -- robust to changes, a minority in every cell --
    and ``a, b >= 0`` are fitted to the cells by non-negative least squares weighted by
    the cell counts.  ``edge_k = sqrt(a)`` (pixels) and ``curv_k = sqrt(b)`` are capped at
    ``k_max`` and ``c_max``: a larger model error would hide real changes on structure.

    Parameters
    ----------
    observed, matched : ndarray or sequence of ndarray
        Observation and photometrically matched reblurred reference (tiles allowed).
    known : bool ndarray or sequence of them
    sigma : (C,) array_like
        Flat-area residual scale per band (:attr:`Photometry.sigma`).
    bins : int
        Quantile bins per predictor.
    max_samples : int
        Pixels sampled per band.
    k_max, c_max : float
        Caps of ``edge_k`` and ``curv_k``.
    rng : int or numpy.random.Generator
        Seed of the sampling.

    Returns
    -------
    edge_k, curv_k : (C,) ndarray
    """
    from scipy.optimize import nnls

    if isinstance(observed, np.ndarray):
        observed, matched, known = [observed], [matched], [known]
    rng = np.random.default_rng(rng)
    s = np.asarray(sigma, dtype=np.float64).reshape(-1)
    C = s.size
    # per band: observed, matched, |grad m|^2 and lap m at the usable pixels, in their own
    # (single) precision; the float64 products are formed on the sample only (the same
    # values, element by element, as on whole tiles: a float32 -> float64 cast is exact)
    acc: list[list[list[np.ndarray]]] = [[[], [], [], []] for _ in range(C)]
    for o, m, k in zip(observed, matched, known, strict=True):
        o, m = _channels(_float(o)), _channels(_float(m))
        # pixels whose 3x3 stencil is known: the values at unknown pixels are arbitrary
        k = np.asarray(k, bool)
        if k.all():  # the erosion (border value 1) keeps every pixel: no masked copies
            k = None
        else:
            k = ndi.binary_erosion(k, np.ones((3, 3), bool), border_value=1)
        for c in range(C):
            for j, v in enumerate((o[:, :, c], m[:, :, c], _grad2_f32(m[:, :, c]),
                                   _laplacian_f32(m[:, :, c]))):
                acc[c][j].append(v.ravel() if k is None else v[k])
    ek, ck = np.zeros(C), np.zeros(C)
    for c in range(C):
        n = sum(a.size for a in acc[c][0])
        if n < 20 * bins * bins:
            continue
        if n > max_samples:
            # the sample drawn from the (never built) concatenation of the tiles
            pick = rng.choice(n, max_samples, replace=False)
            ov, mv, g2, lp = _take_concatenated(acc[c], pick)
        else:
            ov, mv, g2, lp = (np.concatenate(a) for a in acc[c])
        r2 = (ov.astype(np.float64) - mv) ** 2
        g2 = g2.astype(np.float64)
        l2 = lp.astype(np.float64)
        l2 *= l2
        qg = np.searchsorted(np.quantile(g2, np.linspace(0, 1, bins + 1)[1:-1]), g2, "right")
        ql = np.searchsorted(np.quantile(l2, np.linspace(0, 1, bins + 1)[1:-1]), l2, "right")
        cell = qg * bins + ql
        rows, rhs, wts = [], [], []
        # the cells' pixels in their sample order (a stable sort groups them: the same
        # elements in the same order as a boolean mask per cell, one pass instead of one
        # per cell)
        by_cell = np.argsort(cell, kind="stable")
        starts = np.flatnonzero(np.diff(cell[by_cell], prepend=-1))
        for s0, s1 in zip(starts, np.append(starts[1:], cell.size), strict=True):
            sel = by_cell[s0:s1]
            n = int(s1 - s0)
            if n < 20:
                continue
            rows.append([g2[sel].mean(), l2[sel].mean()])
            rhs.append(float(np.median(r2[sel])) / 0.455 - s[c] ** 2)
            wts.append(np.sqrt(n))
        if len(rows) < 2:
            continue
        A = np.asarray(rows) * np.asarray(wts)[:, None]
        scale = np.maximum(A.max(axis=0), 1e-300)  # conditioning: columns to unit range
        coef, _ = nnls(A / scale, np.asarray(rhs) * np.asarray(wts))
        a, b = coef / scale
        ek[c] = min(np.sqrt(max(a, 0.0)), k_max)
        ck[c] = min(np.sqrt(max(b, 0.0)), c_max)
    return ek, ck


def _take_concatenated(lists: list[list[np.ndarray]], idx: np.ndarray) -> list[np.ndarray]:
    """``np.concatenate(pieces)[idx]`` for each list of pieces (all of the same sizes),
    without building the concatenations: ``idx`` is sorted once, so each piece serves a
    contiguous run of it, written back to the positions it came from."""
    offsets = np.cumsum([0] + [a.size for a in lists[0]])
    order = np.argsort(idx, kind="stable")
    sidx = idx[order]
    bounds = np.searchsorted(sidx, offsets)
    outs = []
    for pieces in lists:
        out = np.empty(idx.size, np.result_type(*pieces))
        for t, a in enumerate(pieces):
            s0, s1 = bounds[t], bounds[t + 1]
            out[order[s0:s1]] = a[sidx[s0:s1] - offsets[t]]
        outs.append(out)
    return outs


def estimate_threshold(
    stat_samples, *, method: str = "auto", k: float = 4.0, bins: int = 512,
    broad: float = 0.4,
) -> tuple[float, dict[str, Any]]:
    """Decision threshold of the change statistic from a sample of its values.

    Parameters
    ----------
    stat_samples : array_like or sequence of array_like
        Values of :func:`change_statistic` at known pixels (any shape; e.g. the known
        pixels of a few tiles).  Non-finite values are ignored.
    method : {"auto", "otsu", "mad"}
        ``"otsu"``: Otsu's threshold of the histogram on ``[0, q99.9]`` (values above are
        counted in the last bin, so a few extreme values do not squeeze the histogram).
        ``"mad"``: ``median + k * 1.4826 * MAD``, a robust z-test against the bulk of the
        statistic.  ``"auto"`` (default): the MAD bound, or Otsu when it is lower and the
        bulk is broad (``MAD >= broad * median``).  When changed and unchanged pixels
        overlap (real pairs years apart: a continuum of appearance changes, the bulk 0.5-0.9
        median wide on the LEVIR / WHU pairs of ``benchmarks/quality.py``) Otsu is the lower
        one and splits the two classes.  A bulk as narrow as noise leaves it (0.07-0.10
        median wide on the Fig. 6 set-up there) is the unchanged class itself:
        Otsu would cut through it, most visibly when the sample holds no change at all.
        When the changes are well separated from the noise Otsu falls midway between the
        classes and would drop faint changes: the z-bound again.
    k : float
        Multiplier of the MAD bound.
    bins : int
        Histogram bins of Otsu's method.
    broad : float
        Relative width ``MAD / median`` from which the bulk counts as broad (``"auto"``).

    Returns
    -------
    threshold : float
    info : dict
        ``method``, ``n``, ``median``, ``mad`` (scaled to a standard deviation), ``q99``,
        ``otsu``, ``mad_bound``, ``broad`` (the bulk is broad) and ``chosen`` (``"otsu"``
        or ``"mad"``).

    Raises
    ------
    ValueError
        With no finite sample or an unknown method.
    """
    if isinstance(stat_samples, (list, tuple)):
        x = np.concatenate([np.asarray(a).ravel() for a in stat_samples], dtype=np.float64)
    else:
        x = np.asarray(stat_samples, dtype=np.float64).ravel()
    finite = np.isfinite(x)
    if not finite.all():
        x = x[finite]
    if x.size == 0:
        raise ValueError("estimate_threshold needs at least one finite statistic value")
    if method not in ("auto", "otsu", "mad"):
        raise ValueError(f"method must be 'auto', 'otsu' or 'mad', got {method!r}")
    if not broad >= 0:
        raise ValueError(f"broad must be >= 0, got {broad}")
    med = float(np.median(x))
    dev = x - med  # robust.mad(x), its median computed once
    np.abs(dev, out=dev)
    spread = float(MAD_TO_SIGMA * np.median(dev, overwrite_input=True))
    del dev
    bound = med + float(k) * spread
    info: dict[str, Any] = {
        "method": method, "n": int(x.size), "median": med, "mad": spread, "k": float(k),
        "mad_bound": bound, "q99": float(np.quantile(x, 0.99)),
    }
    lo, hi = float(x.min()), float(np.quantile(x, 0.999))
    if hi <= lo:
        hi = float(x.max())
    if hi <= lo:  # constant statistic: nothing stands out
        info["otsu"] = lo
        info["note"] = "constant statistic"
        return float(np.nextafter(hi, np.inf)), info
    counts, edges = np.histogram(np.minimum(x, hi), bins=int(bins), range=(lo, hi))
    centers = 0.5 * (edges[:-1] + edges[1:])
    otsu = float(threshold_otsu(hist=(counts, centers)))
    info["otsu"] = otsu
    is_broad = spread >= float(broad) * med
    info["broad"] = bool(is_broad)
    if method == "auto":
        chosen = "otsu" if is_broad and otsu < bound else "mad"
    else:
        chosen = method
    info["chosen"] = chosen
    return float(otsu if chosen == "otsu" else bound), info


# --------------------------------------------------------------------------- regions
def _disc(r: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def _shape_ok(sub: np.ndarray, area: int, p: DecisionParams) -> bool:
    # the hull lies inside the bounding box: area / box >= min_solidity settles the
    # solidity test without the (slow) hull
    if p.min_solidity > 0 and area < p.min_solidity * sub.size:
        hull = int(np.count_nonzero(convex_hull_image(sub)))
        if hull and area / hull < p.min_solidity:
            return False
    r_in = float(ndi.distance_transform_edt(np.pad(sub, 1)).max())
    return area / (4.0 * r_in * r_in) <= p.max_aspect


class _Components(NamedTuple):
    """Connected components of a mask (:func:`_components`).

    Attributes
    ----------
    lab : (h, w) int32 ndarray
        0 for the background, 1..n for the components.
    n : int
        Number of components.
    area : (n + 1,) int ndarray
        Pixel count per label (``area[0]``: 0).
    ys, xs, lv : (k,) int ndarray
        Row, column and label of every foreground pixel, in raster order.
    """

    lab: np.ndarray
    n: int
    area: np.ndarray
    ys: np.ndarray
    xs: np.ndarray
    lv: np.ndarray


def _components(mask: np.ndarray, connectivity: int = 8, pixels: bool = True) -> _Components:
    """Connected components of a 2-D mask, labelled by OpenCV (which releases the GIL).

    The same partition as ``scipy.ndimage.label`` with the full 3 x 3 (``connectivity=8``)
    or the cross (``4``) structure; the numbering may differ, so callers never rely on it.
    Areas (and boxes, :func:`_boxes`) come from the foreground pixels only
    (``cv2.findNonZero``; the components are a small part of a tile): OpenCV's own
    statistics pass is several times slower than the labelling.

    Parameters
    ----------
    mask : (h, w) bool or uint8 ndarray
        Foreground: non-zero pixels.
    connectivity : {8, 4}
    pixels : bool
        Also list the foreground pixels (``ys``, ``xs``, ``lv``); False for a dense
        foreground (e.g. the background of a mask), whose areas come from a count over the
        whole label image instead.

    Returns
    -------
    _Components
    """
    m = np.ascontiguousarray(mask)
    if m.dtype == bool:
        m = m.view(np.uint8)
    n, lab = cv2.connectedComponents(m, connectivity=connectivity, ltype=cv2.CV_32S)
    n = int(n) - 1
    if not pixels:
        e = np.zeros(0, np.int32)
        area = np.bincount(lab.ravel(), minlength=n + 1)
        area[0] = 0
        return _Components(lab, n, area, e, e, e)
    pts = cv2.findNonZero(m) if n else None
    if pts is None:
        e = np.zeros(0, np.int32)
        return _Components(lab, n, np.zeros(n + 1, np.intp), e, e, e)
    pts = pts.reshape(-1, 2)
    xs, ys = pts[:, 0], pts[:, 1]
    lv = lab[ys, xs]
    area = np.bincount(lv, minlength=n + 1)
    area[0] = 0
    return _Components(lab, n, area, ys, xs, lv)


def _boxes(cc: _Components, labels) -> dict[int, tuple[slice, slice]]:
    """Tight bounding boxes (as slices) of some labels of ``cc``, from their pixels only."""
    labels = np.asarray(labels, np.intp).reshape(-1)
    if labels.size == 0:
        return {}
    sel = np.zeros(cc.n + 1, bool)
    sel[labels] = True
    pick = sel[cc.lv]
    lv, ys, xs = cc.lv[pick], cc.ys[pick], cc.xs[pick]
    big = np.iinfo(np.int32).max
    y0 = np.full(cc.n + 1, big, np.int32)
    x0 = np.full(cc.n + 1, big, np.int32)
    y1 = np.zeros(cc.n + 1, np.int32)
    x1 = np.zeros(cc.n + 1, np.int32)
    np.minimum.at(y0, lv, ys)
    np.minimum.at(x0, lv, xs)
    np.maximum.at(y1, lv, ys)
    np.maximum.at(x1, lv, xs)
    return {int(k): (slice(int(y0[k]), int(y1[k]) + 1), slice(int(x0[k]), int(x1[k]) + 1))
            for k in labels}


def _union_box(
    boxes: list[tuple[int, int, int, int]], margin: int, shape: tuple[int, ...]
) -> tuple[slice, slice]:
    """Union of ``(y0, x0, y1, x1)`` boxes grown by ``margin``, clipped to ``shape``."""
    y0 = max(min(b[0] for b in boxes) - margin, 0)
    x0 = max(min(b[1] for b in boxes) - margin, 0)
    y1 = min(max(b[2] for b in boxes) + margin, shape[0])
    x1 = min(max(b[3] for b in boxes) + margin, shape[1])
    return slice(y0, y1), slice(x0, x1)


def _labelled(
    S: np.ndarray, lab: np.ndarray, comps: _Components | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Labels and values of the labelled pixels only (candidates are a small fraction)."""
    if comps is not None:
        return comps.lv, S[comps.ys, comps.xs].astype(np.float64)
    sel = lab > 0
    return lab[sel], S[sel].astype(np.float64)


def _label_max(
    S: np.ndarray, lab: np.ndarray, n: int, comps: _Components | None = None
) -> np.ndarray:
    """``ndimage.maximum(S, lab, 1..n)`` over the labelled pixels only (``comps``: their
    positions and labels, from :func:`_components` of ``lab``)."""
    lv, v = _labelled(S, lab, comps)
    out = np.full(n + 1, -np.inf)
    np.maximum.at(out, lv, v)
    return out[1:]


def _label_median(
    S: np.ndarray, lab: np.ndarray, n: int, comps: _Components | None = None
) -> np.ndarray:
    """``ndimage.median(S, lab, 1..n)`` (mean of the two middle values for an even count)
    over the labelled pixels only: one sort of the candidates, not of the whole tile."""
    lv, v = _labelled(S, lab, comps)
    order = np.lexsort((v, lv))
    v = v[order]
    counts = np.bincount(lv, minlength=n + 1)[1:]
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    lo = start + (counts - 1) // 2
    hi = start + counts // 2
    return (v[lo] + v[hi]) / 2.0


def _decide_core(
    S: np.ndarray, known: np.ndarray, threshold: float, p: DecisionParams,
    stop: Callable[[_Components], bool] | None = None,
) -> tuple[np.ndarray | None, np.ndarray, dict[str, int]]:
    """Region decision on an array; returns (mask, level-0 candidate mask, counts).

    ``stop``, called with the components of the level-0 candidates, may end the decision
    there: the mask is then None (and the counts cover nothing).

    Level 0 looks at the whole array; every later level only at the window holding the
    regions passed on to it (grown by the opening's reach, so the opening, which never
    adds pixels, gives the same result there as on the whole array), and the boundary cut
    and the hole filling only at the window of the accepted regions.  Connected components
    come from OpenCV with their areas and boxes (no pass over the whole array per label).
    """
    strong = p.strong_factor * threshold
    shape = S.shape
    accepted = np.zeros(shape, bool)
    counts = {"accepted": 0, "small": 0, "weak": 0, "not_object": 0}
    levels = p.levels if p.region_tests else (1.0,)
    candidates = None
    kernel = _disc(p.open_radius) if p.open_radius > 0 else None
    pending = known
    win: tuple[slice, slice] = (slice(0, shape[0]), slice(0, shape[1]))
    kept: list[tuple[int, int, int, int]] = []  # boxes of the accepted regions
    for li, level in enumerate(levels):
        Sw = S[win]
        m = (Sw > threshold * level) & pending[win]
        if kernel is not None:
            m = cv2.morphologyEx(m.view(np.uint8), cv2.MORPH_OPEN, kernel)
        if candidates is None:  # level 0: the window is the whole array
            candidates = m.view(bool)
        cc = _components(m)
        if li == 0 and stop is not None and stop(cc):
            return None, candidates, counts
        lab, n = cc.lab, cc.n
        if n == 0:
            break
        area = cc.area[1:]
        smax = _label_max(Sw, lab, n, cc)
        small = area < p.min_area
        weak = ~small & (smax < strong)
        counts["small"] += int(np.count_nonzero(small))
        counts["weak"] += int(np.count_nonzero(weak))
        last = li == len(levels) - 1
        oy, ox = win[0].start, win[1].start
        nxt = None
        passed: list[tuple[int, int, int, int]] = []
        tested = np.flatnonzero(~(small | weak))
        boxes = _boxes(cc, tested + 1)
        for i in tested:
            lbl = int(i) + 1
            sl = boxes[lbl]
            sub = lab[sl] == lbl
            full = (slice(sl[0].start + oy, sl[0].stop + oy),
                    slice(sl[1].start + ox, sl[1].stop + ox))
            box = (full[0].start, full[1].start, full[0].stop, full[1].stop)
            if not p.region_tests or _shape_ok(sub, int(area[i]), p):
                accepted[full] |= sub
                kept.append(box)
                counts["accepted"] += 1
            elif last:
                counts["not_object"] += 1
            else:
                if nxt is None:
                    nxt = np.zeros(shape, bool)
                nxt[full] |= sub
                passed.append(box)
        if nxt is None:
            break
        pending = nxt
        win = _union_box(passed, int(p.open_radius) + 1, shape)
    if candidates is None:
        candidates = np.zeros(shape, bool)
    if not kept:
        return accepted, candidates, counts
    # from here on every accepted pixel lies in the window of the accepted regions
    win = _union_box(kept, 0, shape)
    if p.boundary_fraction > 0:
        # object boundary at a fixed fraction of the region's own level: the absolute
        # threshold sits far down the flank of a strong change and would bleed outwards
        acc = accepted[win]
        Sw = S[win]
        cc = _components(acc)
        lab, n = cc.lab, cc.n
        level = _label_median(Sw, lab, n, cc)
        cut = np.concatenate([[np.inf], np.maximum(p.boundary_fraction * level, threshold)])
        acc &= Sw >= cut[lab]
        cc = _components(acc)
        big = cc.area >= p.min_area
        big[0] = False
        acc[...] = big[cc.lab]
        if not big.any():
            return accepted, candidates, counts
        win = _union_box([(b[0].start + win[0].start, b[1].start + win[1].start,
                           b[0].stop + win[0].start, b[1].stop + win[1].start)
                          for b in _boxes(cc, np.flatnonzero(big)).values()], 0, shape)
    if p.close_radius > 0:
        _close_regions(accepted, win, p.close_radius)
    if p.max_hole_area > 0:
        # a hole (a background component clear of the array's border) lies inside the
        # box of the accepted pixels; one pixel of margin keeps the outside connected
        win = _union_box([(win[0].start, win[1].start, win[0].stop, win[1].stop)], 1, shape)
        acc = accepted[win]
        cc = _components(~acc, connectivity=4, pixels=False)
        bg = cc.lab
        fill = cc.area <= p.max_hole_area
        fill[0] = False
        fill[np.concatenate([bg[0], bg[-1], bg[:, 0], bg[:, -1]])] = False
        acc |= fill[bg]
    accepted[win] &= known[win]
    return accepted, candidates, counts


def _close_regions(mask: np.ndarray, win: tuple[slice, slice], radius: int) -> None:
    """Close every connected region of ``mask[win]`` on its own with a disc of ``radius``,
    in place.

    A closing by a convex element stays inside the region's convex hull, hence inside its
    bounding box: each region is closed in its box (padded so that the array's border does
    not act as foreground), and regions never merge, however close.
    """
    sub = mask[win]
    cc = _components(sub)
    if cc.n == 0:
        return
    kernel = _disc(radius)
    pad = radius + 1
    for lbl, sl in _boxes(cc, np.arange(1, cc.n + 1)).items():
        reg = np.pad((cc.lab[sl] == lbl).view(np.uint8), pad)
        closed = cv2.morphologyEx(reg, cv2.MORPH_CLOSE, kernel)[pad:-pad, pad:-pad]
        sub[sl] |= closed.view(bool)


def _region_records(
    mask: np.ndarray, S: np.ndarray, y0: int, x0: int, core=None
) -> list[dict[str, Any]]:
    """Connected regions of ``mask`` (8-conn), full-image coordinates.

    Regions are listed in the raster order of their first pixel (as ``ndimage.label``
    numbers them).  With ``core=(cy0, cx0, ch, cw)`` (array coordinates) only regions whose
    first pixel in raster order lies in the core are listed, so tiles list each region once.
    """
    cc = _components(mask)
    lab = cc.lab
    # first pixel of every label in raster order (the foreground pixels are in raster order)
    lbls, first = np.unique(cc.lv, return_index=True)
    order = np.argsort(first, kind="stable")
    boxes = _boxes(cc, lbls)
    out = []
    for lbl, k in zip(lbls[order].tolist(), first[order].tolist(), strict=True):
        ay, ax = int(cc.ys[k]), int(cc.xs[k])
        if core is not None:
            cy0, cx0, ch, cw = core
            if not (cy0 <= ay < cy0 + ch and cx0 <= ax < cx0 + cw):
                continue
        sl = boxes[lbl]
        sub = lab[sl] == lbl
        area = int(cc.area[lbl])
        # centroid as the mean of the pixel indices: exact integer sums over the box
        sy = int(np.arange(sub.shape[0]) @ np.count_nonzero(sub, axis=1))
        sx = int(np.arange(sub.shape[1]) @ np.count_nonzero(sub, axis=0))
        vals = S[sl][sub]
        out.append(
            {
                "area": area,
                "bbox": [sl[0].start + y0, sl[1].start + x0, sl[0].stop + y0, sl[1].stop + x0],
                "centroid": [
                    float(np.float64(sy) / area + sl[0].start + y0),
                    float(np.float64(sx) / area + sl[1].start + x0),
                ],
                "mean_stat": float(vals.mean()),
                "max_stat": float(vals.max()),
            }
        )
    for k, r in enumerate(out, 1):
        r["label"] = k
    return out


def _clear_of(
    mask: np.ndarray | None, band: list[tuple[slice, slice]], core: tuple[slice, slice],
    cc: _Components | None = None,
) -> bool:
    """No 8-connected component of ``mask`` has pixels both in ``core`` and in ``band``.

    Parameters
    ----------
    mask : (h, w) bool ndarray or None
        None when its components ``cc`` are given.
    band : list of (slice, slice)
        Strips of the array (the tile edges that are not image borders).
    core : (slice, slice)
        The tile's core.
    cc : _Components, optional
        The 8-connected components of ``mask``, if already known.
    """
    return not _reaching(mask, band, core, cc)


def _reaching(
    mask: np.ndarray | None, band: list[tuple[slice, slice]], core: tuple[slice, slice],
    cc: _Components | None = None,
) -> list[int]:
    """Indices of the strips of ``band`` that an 8-connected component of ``mask`` joins
    to ``core`` (empty: the core is clear of the band; see :func:`_clear_of`)."""
    if not band:
        return []
    if cc is None:
        cc = _components(mask)
    lab, n = cc.lab, cc.n
    if n == 0:
        return []
    touch = np.zeros((len(band), n + 1), bool)
    for i, sl in enumerate(band):
        touch[i, lab[sl].ravel()] = True
    touch[:, 0] = False
    any_touch = touch.any(axis=0)
    cy, cx = core
    joined = np.zeros(n + 1, bool)
    for lbl, (ys, xs) in _boxes(cc, np.flatnonzero(any_touch)).items():
        ya, yb = max(ys.start, cy.start), min(ys.stop, cy.stop)
        xa, xb = max(xs.start, cx.start), min(xs.stop, cx.stop)
        if ya < yb and xa < xb and np.any(lab[ya:yb, xa:xb] == lbl):
            joined[lbl] = True
    return [i for i in range(len(band)) if np.any(touch[i] & joined)]


def _prepare(observed, reblurred, unknown):
    o = _float(observed)
    r = _float(reblurred)
    if o.ndim not in (2, 3):
        raise ValueError(f"observed must be (h, w) or (h, w, C), got shape {o.shape}")
    if o.shape != r.shape:
        raise ValueError(f"observed has shape {o.shape} but reblurred has shape {r.shape}")
    known = np.all(np.isfinite(_channels(o)), axis=2) & np.all(np.isfinite(_channels(r)), axis=2)
    if unknown is not None:
        u = np.asarray(unknown, dtype=bool)
        if u.shape != o.shape[:2]:
            raise ValueError(f"unknown has shape {u.shape}, expected {o.shape[:2]}")
        known &= ~u
    if not known.all():  # keep NaN out of every filter
        kk = known[:, :, None] if o.ndim == 3 else known
        o = np.where(kk, o, 0).astype(o.dtype, copy=False)
        r = np.where(kk, r, 0).astype(r.dtype, copy=False)
    return o, r, known


# --------------------------------------------------------------------------- tiles
def tile_boxes(
    image_shape: tuple[int, int], tile_size: int | tuple[int, int], halo: int
) -> Iterator[tuple[tuple[int, int, int, int], tuple[int, int, int, int]]]:
    """Tiles of an image: ``(padded_box, core_box)`` pairs, boxes as ``(y0, x0, h, w)``.

    Cores cover the image without overlap; padded boxes add ``halo`` pixels on every side,
    clipped to the image.
    """
    H, W = (int(v) for v in image_shape)
    th, tw = (tile_size, tile_size) if np.isscalar(tile_size) else tile_size
    if th < 1 or tw < 1 or halo < 0:
        raise ValueError("tile_size must be positive and halo non-negative")
    for y in range(0, H, th):
        for x in range(0, W, tw):
            ch, cw = min(th, H - y), min(tw, W - x)
            py0, px0 = max(y - halo, 0), max(x - halo, 0)
            py1, px1 = min(y + ch + halo, H), min(x + cw + halo, W)
            yield (py0, px0, py1 - py0, px1 - px0), (y, x, ch, cw)


def _tile_statistic(o, matched, known, photometry: Photometry, p: DecisionParams,
                    box: tuple[int, int, int, int], image_shape, previous) -> np.ndarray:
    """:func:`change_statistic` over a padded tile, reusing ``previous = (S, box)`` (an
    earlier tile inside this one, same inputs) where its values are exact.

    A value depends on the inputs within ``smooth_radius + 1`` pixels (the Gaussian window
    and the 3x3 stencils of the model error), so the earlier values are exact except
    within that reach of its edges that are not image borders; the rest of the tile is
    computed in (at most four) strips, each from its window grown by the reach, cropped.
    """

    def compute(y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        sl = (slice(y0, y1), slice(x0, x1))
        return change_statistic(o[sl], matched[sl], known[sl], photometry.sigma,
                                smooth=p.smooth, truncate=p.truncate,
                                edge_k=photometry.edge_k, curv_k=photometry.curv_k)

    by0, bx0, bh, bw = box
    if previous is None:
        return compute(0, bh, 0, bw)
    S0, (py0, px0, ph, pw) = previous
    H, W = image_shape if image_shape is not None else (None, None)
    r = p.smooth_radius + 1
    # the exact part of the earlier statistic, in this tile's coordinates
    ey0 = py0 - by0 + (r if py0 > 0 else 0)
    ex0 = px0 - bx0 + (r if px0 > 0 else 0)
    ey1 = py0 + ph - by0 - (0 if H is not None and py0 + ph >= H else r)
    ex1 = px0 + pw - bx0 - (0 if W is not None and px0 + pw >= W else r)
    inside = py0 >= by0 and px0 >= bx0 and py0 + ph <= by0 + bh and px0 + pw <= bx0 + bw
    if not inside or S0.shape != (ph, pw) or ey0 >= ey1 or ex0 >= ex1:
        return compute(0, bh, 0, bw)
    S = np.empty((bh, bw), np.float32)
    oy, ox = by0 - py0, bx0 - px0
    S[ey0:ey1, ex0:ex1] = S0[ey0 + oy : ey1 + oy, ex0 + ox : ex1 + ox]
    strips = [(0, ey0, 0, bw), (ey1, bh, 0, bw), (ey0, ey1, 0, ex0), (ey0, ey1, ex1, bw)]
    for y0, y1, x0, x1 in strips:
        if y0 >= y1 or x0 >= x1:
            continue
        gy0, gy1 = max(y0 - r, 0), min(y1 + r, bh)
        gx0, gx1 = max(x0 - r, 0), min(x1 + r, bw)
        S[y0:y1, x0:x1] = compute(gy0, gy1, gx0, gx1)[y0 - gy0 : y1 - gy0, x0 - gx0 : x1 - gx0]
    return S


def decide_tile(
    observed_tile: np.ndarray,
    reblurred_tile: np.ndarray,
    unknown_tile: np.ndarray | None = None,
    *,
    threshold: float,
    photometry: Photometry,
    box,
    core=None,
    params: DecisionParams | None = None,
    image_shape: tuple[int, int] | None = None,
    stop_incomplete: bool = False,
    statistic: tuple[np.ndarray, Any] | None = None,
    keep_statistic: bool = False,
) -> tuple[np.ndarray | None, dict[str, Any]]:
    """Decide change on one padded tile and return its core.

    Parameters
    ----------
    observed_tile, reblurred_tile : (h, w) or (h, w, C) ndarray
        Observation and reblurred reference (NOT photometrically matched: ``photometry``
        is applied here) over the padded tile ``box``.
    unknown_tile : (h, w) bool ndarray, optional
        Pixels the reference does not cover; never change.
    threshold : float
        Global threshold of the statistic (:func:`estimate_threshold` on a sample).
    photometry : Photometry
        Global photometric model (:func:`fit_photometry`).
    box : (y0, x0, h, w) or Box
        Full-image position of the padded tile.
    core : (y0, x0, h, w) or Box, optional
        Full-image box of the part to return, inside ``box``; default the whole tile.
    params : DecisionParams, optional
        Must be the same for every tile.
    image_shape : (int, int), optional
        Full image size (default ``photometry.image_shape``): tile edges on the image
        border need no halo.
    stop_incomplete : bool
        Give up as soon as the tile is known to be incomplete (a level-0 candidate region
        joins the core to the edge band), for a caller that re-runs such tiles with a
        larger halo anyway: ``mask`` is then None and ``info`` holds ``complete`` (False),
        ``reach`` (of the level-0 candidates), ``threshold``, ``strong_threshold`` and
        ``n_unknown`` only.
    statistic : (S, box), optional
        The statistic of an earlier call on a window ``box`` inside this tile, with the
        same inputs there (``info["statistic"]`` of that call): a re-run with a larger
        halo computes the statistic only on the ring it adds, plus the statistic's reach
        (the values are those of a computation over the whole tile).
    keep_statistic : bool
        Return ``(S, box)`` as ``info["statistic"]``, for ``statistic=`` of a re-run.

    Returns
    -------
    mask : (core h, core w) bool ndarray or None
    info : dict
        ``complete`` (True when the result is guaranteed equal to the whole-image call:
        no candidate region reaching the core comes within ``params.local_radius`` of a
        tile edge that is not an image border; otherwise re-run with a larger halo),
        ``reach`` (the edges, of ``"top"``, ``"bottom"``, ``"left"``, ``"right"``, that
        such a region comes within that distance of: where the halo must grow; empty when
        complete),
        ``regions`` (regions whose first pixel in raster order lies in the core, full-image
        coordinates: each region is listed by one tile), ``counts`` (candidates accepted /
        dropped, over the padded tile), ``threshold``, ``strong_threshold``, ``n_unknown``.

    Notes
    -----
    Halo requirement: ``halo >= params.local_radius + R`` with ``R`` the distance a change
    region reaches out of the core (see the module notes and :meth:`DecisionParams.halo`).
    """
    p = params if params is not None else DecisionParams()
    o, r, known = _prepare(observed_tile, reblurred_tile, unknown_tile)
    by0, bx0, bh, bw = _box(box)
    if o.shape[:2] != (bh, bw):
        raise ValueError(f"tile shape {o.shape[:2]} does not match box size {(bh, bw)}")
    cy0, cx0, ch, cw = (by0, bx0, bh, bw) if core is None else _box(core)
    if cy0 < by0 or cx0 < bx0 or cy0 + ch > by0 + bh or cx0 + cw > bx0 + bw:
        raise ValueError(f"core {(cy0, cx0, ch, cw)} is not inside box {(by0, bx0, bh, bw)}")
    shape = image_shape if image_shape is not None else photometry.image_shape
    matched = photometry.apply(r, (by0, bx0, bh, bw))
    S = _tile_statistic(o, matched, known, photometry, p, (by0, bx0, bh, bw), shape, statistic)
    ly, lx = cy0 - by0, cx0 - bx0
    # completeness: regions reaching the core must stay clear of non-border tile edges
    m = p.local_radius
    band, names = [], []
    if not by0 <= 0:
        band.append((slice(0, m), slice(None)))
        names.append("top")
    if not (shape is not None and by0 + bh >= shape[0]):
        band.append((slice(bh - m, None), slice(None)))
        names.append("bottom")
    if not bx0 <= 0:
        band.append((slice(None), slice(0, m)))
        names.append("left")
    if not (shape is not None and bx0 + bw >= shape[1]):
        band.append((slice(None), slice(bw - m, None)))
        names.append("right")
    core_sl = (slice(ly, ly + ch), slice(lx, lx + cw))
    n_unknown = int(np.count_nonzero(~known[core_sl]))

    cand_reach: list[list[int]] = [[]]

    def level0(cc: _Components) -> bool:
        # the test on the level-0 candidates, from their components: a candidate region
        # joining the core to the band makes the tile incomplete (mask | cand, tested
        # below, is a superset of the candidates)
        cand_reach[0] = _reaching(None, band, core_sl, cc)
        return stop_incomplete and bool(cand_reach[0])

    mask, cand, counts = _decide_core(S, known, float(threshold), p, stop=level0)
    kept = {"statistic": (S, (by0, bx0, bh, bw))} if keep_statistic else {}
    if mask is None:
        return None, {"complete": False, "reach": [names[i] for i in cand_reach[0]],
                      "threshold": float(threshold),
                      "strong_threshold": float(p.strong_factor * threshold),
                      "n_unknown": n_unknown, **kept}
    if np.any(mask & ~cand):  # filled holes: mask | cand has components of its own
        reach = _reaching(mask | cand, band, core_sl)
    else:  # mask | cand == cand: the test is the one on the candidates
        reach = cand_reach[0]
    complete = not reach
    info = {
        "complete": complete,
        "reach": [names[i] for i in reach],
        "threshold": float(threshold),
        "strong_threshold": float(p.strong_factor * threshold),
        "counts": counts,
        "regions": _region_records(mask, S, by0, bx0, core=(ly, lx, ch, cw)),
        "n_unknown": n_unknown,
        **kept,
    }
    return mask[ly : ly + ch, lx : lx + cw].copy(), info


def decide(
    observed: np.ndarray,
    reblurred: np.ndarray,
    unknown: np.ndarray | None = None,
    *,
    threshold: float | None = None,
    photometry: Photometry | None = None,
    params: DecisionParams | None = None,
    field_block: int | None = None,
    threshold_method: str = "auto",
    edge_error: bool = True,
    rng=None,
    **overrides,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Whole-image change decision.

    Parameters
    ----------
    observed, reblurred : (h, w) or (h, w, C) ndarray
        Observation and aligned reblurred reference (not photometrically matched).
    unknown : (h, w) bool ndarray, optional
        Pixels the reference does not cover: excluded from every fit and never change.
        Non-finite pixels are treated as unknown too.
    threshold : float, optional
        Threshold of the statistic; default estimated from the data
        (:func:`estimate_threshold` with ``threshold_method``).
    photometry : Photometry, optional
        Photometric model; default fitted here (:func:`fit_photometry`).
    params : DecisionParams, optional
        Decision parameters; keyword ``overrides`` replace single fields
        (e.g. ``min_area=50``).
    field_block : int, optional
        Smooth photometric field block size when fitting here (default: none).
    threshold_method : {"auto", "otsu", "mad"}
        How to estimate the threshold when it is not given.
    rng : int or numpy.random.Generator, optional
        Seed of the photometric subsampling.

    Returns
    -------
    change : (h, w) bool ndarray
        Change mask, False wherever ``unknown``.
    info : dict
        ``threshold``, ``threshold_info``, ``strong_threshold``, ``photometry`` (dict),
        ``params`` (dict), ``counts``, ``regions``, ``statistic`` (description),
        ``n_unknown``.

    Raises
    ------
    ValueError
        On mismatched shapes or no known pixel.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> ref = rng.random((128, 128)).astype(np.float32)
    >>> obs = 0.9 * ref + 0.05 + 0.01 * rng.standard_normal(ref.shape).astype(np.float32)
    >>> obs[40:80, 40:80] += 0.4
    >>> change, info = decide(obs, ref)
    >>> bool(change[60, 60]), bool(change[10, 10])
    (True, False)
    """
    p = _params(params, overrides)
    o, r, known = _prepare(observed, reblurred, unknown)
    if not known.any():
        raise ValueError("no known pixel: every pixel is unknown or non-finite")
    if photometry is None:
        photometry = fit_photometry(o, r, known, field_block=field_block, rng=rng,
                                    edge_error=edge_error)
    matched = photometry.apply(r)
    S = change_statistic(o, matched, known, photometry.sigma, smooth=p.smooth, truncate=p.truncate,
                         edge_k=photometry.edge_k, curv_k=photometry.curv_k)
    if threshold is None:
        threshold, tinfo = estimate_threshold(S[known], method=threshold_method)
    else:
        threshold = float(threshold)
        tinfo = {"method": "given"}
    mask, _, counts = _decide_core(S, known, threshold, p)
    info = {
        "threshold": threshold,
        "threshold_info": tinfo,
        "strong_threshold": float(p.strong_factor * threshold),
        "statistic": "local RMS of robust per-band z-scores, Gaussian window sigma="
        f"{p.smooth:g} px",
        "photometry": photometry.to_dict(),
        "params": p.to_dict(),
        "counts": counts,
        "regions": _region_records(mask, S, 0, 0),
        "n_unknown": int(np.count_nonzero(~known)),
    }
    return mask, info
