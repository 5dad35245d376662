"""Stage 1 of the change decision, photometry (:func:`fit_photometry`; global, fitted once
from a sample of tiles or a downsampled image).  Per band, ``g ~ a * m + b`` by Huber IRLS
(convex, so unique and stable even for weakly correlated captures; a minority of changed
pixels has a bounded influence).  Optionally a smooth field: gain and offset on a grid of
``field_block``-pixel blocks, bilinearly interpolated between block centres (linearly
extrapolated to the edges), fitted *jointly* in that same interpolated form by Huber IRLS
with a small second-difference penalty (linear trends such as illumination ramps are free).
The residual scale ``sigma`` of each band (MAD of the inliers) is the unit of the statistic.
The smooth photometric field is off by default: on real pairs years apart
(``benchmarks/decision.py``) the differences are real appearance changes, not illumination,
and a 256-px field absorbs area-wide changes (mean Jaccard 0.30 -> 0.21); turn it on
(``field_block``, several times the largest change object) for illumination, haze or
vignetting differences.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from threadpoolctl import threadpool_limits

from .._bands import all_bands
from ..robust import huber_line, inlier_scale, mad, median, robust_line
from ._common import FIT_BLAS_THREADS, _box, _channels, _float, _robust_scale, band_map
from .params import DecisionParams
from .statistic import fit_model_error
from .tolerance import ModelTolerance


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


def _grid_sample(grid: np.ndarray, ys: np.ndarray, xs: np.ndarray, block: int) -> np.ndarray:
    """The bilinear interpolation of block-centre values (:func:`_grid_coords`) at
    scattered full-image points ``(ys, xs)``; on a window: :func:`_field_gain_offset`."""
    ny, nx = grid.shape
    iy, iy1, wy = _grid_coords((ys + 0.5) / block - 0.5, ny)
    ix, ix1, wx = _grid_coords((xs + 0.5) / block - 0.5, nx)
    return (1 - wy) * ((1 - wx) * grid[iy, ix] + wx * grid[iy, ix1]) + wy * (
        (1 - wx) * grid[iy1, ix] + wx * grid[iy1, ix1]
    )


#: Rows of a tile mapped at once by :func:`_gain_offset`.
_GAIN_ROWS = 32


def _gain_offset(x: np.ndarray, gain: np.ndarray, offset: np.ndarray, out: np.ndarray) -> None:
    """``out[..., c] = gain[c] * x[..., c] + offset[c]`` for ``(h, w, C)`` arrays, in the
    type of that expression (float64 for a float32 tile and float64 coefficients), then
    stored in ``out``'s type: the per-band expression's values exactly.

    Done :data:`_GAIN_ROWS` rows at a time in one reused buffer, the bands interleaved as
    stored (the coefficients repeated along a row): per band over the whole tile, each band
    was a strided pass and each intermediate a full-size float64 array.
    """
    h, w, C = x.shape
    if C == 1:
        src, dst, g, o = x[:, :, 0], out[:, :, 0], gain.reshape(-1)[0], offset.reshape(-1)[0]
    else:
        src, dst = np.ascontiguousarray(x).reshape(h, w * C), out.reshape(h, w * C)
        g, o = np.tile(gain.reshape(-1), w), np.tile(offset.reshape(-1), w)
    buf = np.empty((min(_GAIN_ROWS, h), src.shape[1]), np.result_type(x, gain, offset))
    for y in range(0, h, _GAIN_ROWS):
        t = buf[: min(_GAIN_ROWS, h - y)]
        np.multiply(src[y : y + len(t)], g, out=t)
        t += o
        dst[y : y + len(t)] = t


def _field_gain_offset(x: np.ndarray, field_gain: np.ndarray, field_offset: np.ndarray,
                       origin: tuple[int, int], block: int, out: np.ndarray) -> None:
    """``out[..., c] = g_c * x[..., c] + o_c`` for an ``(h, w, C)`` tile at ``origin``,
    ``g_c`` and ``o_c`` the bilinear interpolations of the block-centre values
    ``field_gain[c]`` and ``field_offset[c]`` (``(C, ny, nx)``; :func:`_grid_coords`:
    linear between the centres, extrapolated to the image edge), in float64, then stored
    in ``out``'s type.

    Per pixel ``(1 - wy) * rows[iy] + wy * rows[iy1]`` with ``rows`` the fields
    interpolated along x once per grid row: the same floating-point operations as
    ``(1 - wy) * ((1 - wx) * g00 + wx * g01) + wy * ((1 - wx) * g10 + wx * g11)``, at a
    fraction of the passes.  Done :data:`_GAIN_ROWS` rows at a time in reused buffers:
    over the whole tile each field was a full-size float64 array built in five passes.
    """
    h, w, C = x.shape
    iy, iy1, wy = _grid_coords((np.arange(origin[0], origin[0] + h) + 0.5) / block - 0.5,
                               field_gain.shape[1])
    ix, ix1, wx = _grid_coords((np.arange(origin[1], origin[1] + w) + 0.5) / block - 0.5,
                               field_gain.shape[2])
    n = min(_GAIN_ROWS, h)
    g, o, t = (np.empty((n, w)) for _ in range(3))
    for c in range(C):
        # the fields along x at every grid row
        rows = [(1 - wx)[None, :] * f[c][:, ix] + wx[None, :] * f[c][:, ix1]
                for f in (field_gain, field_offset)]
        for y in range(0, h, _GAIN_ROWS):
            k = min(_GAIN_ROWS, h - y)
            a = wy[y : y + k, None]
            b = 1 - a
            for buf, r in zip((g, o), rows, strict=True):
                # (1 - wy) * rows[iy] + wy * rows[iy1]
                np.multiply(b, r[iy[y : y + k]], out=buf[:k])
                np.multiply(a, r[iy1[y : y + k]], out=t[:k])
                buf[:k] += t[:k]
            g[:k] *= x[y : y + k, :, c]
            g[:k] += o[:k]
            out[y : y + k, :, c] = g[:k]


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
    clip : (C, 2) ndarray or None
        The observation's clipping levels ``[low, high]`` per band (:func:`clip_levels`;
        -inf / inf where a band has none): the sensor reports no value beyond them, so the
        model's prediction is clipped to them (None: no band has one).
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
    clip: np.ndarray | None = None
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
        if self.has_field:
            _field_gain_offset(rc, self.field_gain, self.field_offset, (y0, x0),
                               self.field_block, out)
        else:
            _gain_offset(rc, np.asarray(self.gain), np.asarray(self.offset), out)
        if self.clip is not None:
            for c, (lo, hi) in enumerate(np.asarray(self.clip, np.float64)):
                if np.isfinite(lo) or np.isfinite(hi):
                    np.clip(out[:, :, c], lo, hi, out=out[:, :, c])
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
        ok = all_bands(np.isfinite(o)) & all_bands(np.isfinite(m))
        if valid is not None:
            ok &= np.asarray(valid, dtype=bool)
        return np.array([_robust_scale((o[:, :, c] - m[:, :, c])[ok]) for c in range(o.shape[2])])

    def inliers(self, observed: np.ndarray, reblurred: np.ndarray, box=None,
                k: float = 3.5) -> np.ndarray:
        """Pixels the model explains: ``|observed - apply(reblurred, box)| < k sigma`` in
        every band (non-finite pixels are not inliers)."""
        o = _channels(_float(observed))
        m = _channels(self.apply(reblurred, box))
        with np.errstate(invalid="ignore"):
            z = np.abs(o - m) / self.sigma.reshape(1, 1, -1)
        return all_bands(z < k)

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
            "clip": None if self.clip is None else [
                [None if not np.isfinite(v) else float(v) for v in lh] for lh in self.clip],
        }
        if self.has_field:
            d["field_gain"] = np.asarray(self.field_gain).tolist()
            d["field_offset"] = np.asarray(self.field_offset).tolist()
        d["info"] = dict(self.info)
        return d


#: Share of the fit's samples one extreme value of a band must hold exactly to be the
#: sensor's clipping level (:func:`clip_levels`).
CLIP_SHARE = 0.002


def clip_levels(obs: np.ndarray) -> np.ndarray:
    """``(C, 2)`` clipping levels ``[low, high]`` of the observation samples ``obs`` (n, C):
    a band's highest value when at least :data:`CLIP_SHARE` of the samples hold it exactly
    (saturation), else inf; the low level is -inf.

    Where the sensor saturated, the observation says only "at least this bright": the
    photometric line does not hold there (the failure mode ``saturated``, ``plain``
    exposed 1.3x brighter, ~8 % at 255: 5.9 % of the unchanged pixels flagged at dae86f8;
    ``python -m benchmarks.failure_modes``), so such samples stay out of the fit and the
    model's prediction is clipped to the level (:meth:`Photometry.apply`).  Ordinary data
    reaches its maximum at a few samples.  A level held at the low end is more often a
    black hole or fill, which is change: left out of the fit as well, it cost the failure
    modes' ``fill55`` recall 0.846 -> 0.789 and ``hole50`` 0.890 -> 0.882, so the low end
    is not clipped."""
    obs = np.asarray(obs, np.float64)
    out = np.tile(np.array([-np.inf, np.inf]), (obs.shape[1], 1))
    need = max(CLIP_SHARE * obs.shape[0], 2)
    for c in range(obs.shape[1]):
        v = obs[:, c][np.isfinite(obs[:, c])]
        if v.size and v.min() < v.max():
            hi = held_levels(v, need)[1]
            out[c, 1] = np.inf if hi is None else hi
    return out


def held_levels(values: np.ndarray, need: float) -> tuple[float | None, float | None]:
    """The lowest and the highest of ``values`` (1-D, finite), each only if at least
    ``need`` of them hold it exactly, else None: a clipped level (saturation, a fill)."""
    lo, hi = values.min(), values.max()
    return (lo if np.count_nonzero(values == lo) >= need else None,
            hi if np.count_nonzero(values == hi) >= need else None)


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
        ok = all_bands(np.isfinite(o)) & all_bands(np.isfinite(r))
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
    :func:`_field_gain_offset`.  Huber IRLS; the penalty ``smoothness * (n / N)`` times the
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


#: Nodes per side at most of the grid a smooth (polynomial) illumination field is stored on.
_POLY_NODES = 32
#: The field wins under ``illumination="auto"`` when it lowers the inliers' residual scale
#: to at most this fraction of the global model's (and by more than the noise of that
#: comparison): a ramp of 0.65 -> 1.0 brings it to ~0.2-0.5, no illumination leaves it at
#: ~0.97-1.0.
FIELD_GAIN = 0.85
#: Under ``illumination="auto"`` a field is light only if its gain stays above this
#: everywhere in the image (intensities in full-scale units, the floor the pre-fit's global
#: line keeps): a field falling to it fits a region whose observation does not follow the
#: reference -- a black or saturated fill, a new surface -- so well that it wins the
#: criterion (the failure mode ``fill55``, the left 55 % of the view at 0: the field took
#: the fill and the changes as light, nothing was flagged; ``python -m
#: benchmarks.failure_modes``).
MIN_FIELD_GAIN = 0.05
ILLUMINATIONS = ("auto", "global", "field")
#: Added to both residual scales of the illumination criterion (a 16-bit quantum).
_SCALE_FLOOR = 1.0 / 65535.0
#: Samples :func:`fit_photometry` draws (seeded) by default.  An offset from ``n`` samples
#: of residual scale ``sigma`` is off by about ``sigma / sqrt(n)`` (the gain by that over
#: the spread of the intensities), the scale itself by ``1 / sqrt(2 n)`` of it: 0.3 % and
#: 0.2 % of ``sigma`` at 10^5, far below what moves a decision.  The robust fits' cost grows
#: linearly in ``n`` above a fixed part (GoPro 0374: 0.73 s at 2 x 10^5 against 0.46 s at
#: 10^5 and 0.39 s at 5 x 10^4, the gains within 6e-4 of each other).
FIT_SAMPLES = 100_000


def _normalised(ys, xs, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Image coordinates normalised to ``[-1, 1]``: ``u`` across the columns, ``v`` down
    the rows."""
    u = 2.0 * (np.asarray(xs, np.float64) + 0.5) / shape[1] - 1.0
    v = 2.0 * (np.asarray(ys, np.float64) + 0.5) / shape[0] - 1.0
    return u, v


def _poly_terms(ys: np.ndarray, xs: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The six quadratic monomials of normalised image coordinates (``[-1, 1]``)."""
    u, v = _normalised(ys, xs, shape)
    return np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=-1)


#: Samples the illumination field's IRLS fits its 12 coefficients on (every k-th of those
#: near the global model's band): their standard error is then a few 1e-3 of the noise,
#: and the fit a quarter of the time on 200 000 samples.  The choice between the field and
#: the global model still measures both on every sample.
FIELD_FIT_SAMPLES = 50_000


def fit_poly_field(ys, xs, x, y, shape, start, scale, n_iter: int = 15,
                   max_samples: int = FIELD_FIT_SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """Huber IRLS of ``y ~ (T a) x + (T b)`` with ``T`` the quadratic terms: a smooth gain
    and offset over the image (ramps, vignetting, haze and cloud-shadow gradients).  Samples
    farther than 8 inlier ``scale`` s from the ``start`` model's band get no say, then the
    Huber weights use the residuals' MAD; at most ``max_samples`` of the others, evenly
    spaced, are fitted.  Returns the coefficients ``a``, ``b``."""
    p = np.zeros(12)
    p[0], p[6] = start
    # the start model's residuals (its design row is x, 0, .., 0, 1, 0, ..: the product
    # with p is x p0 + p6), then the design of the samples kept only: built for all of
    # them it was 12 float64 columns of every sample (1 MP: 96 MB, twice)
    r = y - (x * p[0] + p[6])
    use = np.abs(r - median(r)) < 8.0 * scale if scale > 0 else np.ones(r.size, bool)
    if np.count_nonzero(use) < 100:
        use = np.ones(r.size, bool)
    idx = np.flatnonzero(use)
    if idx.size > max_samples:  # an even subset (the samples are in image order)
        idx = idx[::-(-idx.size // max_samples)]
    T = _poly_terms(np.asarray(ys)[idx], np.asarray(xs)[idx], shape)
    A = np.concatenate([T * x[idx, None], T], axis=1)
    yy = y[idx]
    for _ in range(n_iter):
        r = yy - A @ p
        s = mad(r)
        if not s > 0:
            break
        w = np.minimum(1.0, 1.345 * s / np.maximum(np.abs(r), 1e-12))
        p_new = _weighted_lstsq(A, yy, w)
        done = np.max(np.abs(p_new - p)) < 1e-7
        p = p_new
        if done:
            break
    return p[:6], p[6:]


@dataclass(frozen=True)
class IlluminationField:
    """A smooth illumination field over an image: ``y ~ G(r, c) x + O(r, c)`` per band,
    ``G`` and ``O`` quadratic in the normalised image coordinates (the six monomials of
    :func:`_poly_terms`), as :func:`fit_poly_field` fits them.

    Attributes
    ----------
    gain, offset : (C, 6) ndarray
        The coefficients of ``G`` and ``O`` per band.
    shape : (int, int)
        The image's ``(height, width)`` the coordinates are normalised by.
    """

    gain: np.ndarray
    offset: np.ndarray
    shape: tuple[int, int]

    def at(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``G`` and ``O`` at every pixel of the rows ``rows`` and columns ``cols`` (image
        pixel indices): two ``(len(rows), len(cols), C)`` float32 arrays."""
        # the monomials of _poly_terms, broadcast: u along a row, v down a column
        u, v = _normalised(np.asarray(rows, np.float64)[:, None],
                           np.asarray(cols, np.float64)[None, :], self.shape)
        uu, uv, vv = u * u, u * v, v * v

        def field(coef: np.ndarray) -> np.ndarray:
            out = np.empty((uv.shape[0], uv.shape[1], coef.shape[0]), np.float32)
            for c, k in enumerate(np.asarray(coef, np.float64)):
                out[:, :, c] = k[0] + k[1] * u + k[2] * v + k[3] * uu + k[4] * uv + k[5] * vv
            return out

        return field(self.gain), field(self.offset)

    def to_dict(self) -> dict[str, Any]:
        return {"gain": np.asarray(self.gain).tolist(),
                "offset": np.asarray(self.offset).tolist(),
                "shape": [int(v) for v in self.shape],
                "terms": "1, u, v, u^2, uv, v^2 of u, v in [-1, 1] across the columns, rows"}


def _weighted_lstsq(A: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``argmin_p sum w (y - A p)^2`` by the normal equations (a few columns, many rows:
    ~6x faster than a least-squares solver on the rows), ``np.linalg.lstsq`` when they are
    ill-conditioned (a nearly constant ``x`` makes the gain and offset terms collinear)."""
    Aw = A * w[:, None]
    M = Aw.T @ A
    if np.linalg.cond(M) < 1e10:
        return np.linalg.solve(M, Aw.T @ y)
    sw = np.sqrt(w)
    return np.linalg.lstsq(A * sw[:, None], y * sw, rcond=None)[0]


def _poly_grid(coef: np.ndarray, shape: tuple[int, int], block: int) -> np.ndarray:
    """A polynomial field at the centres of ``block``-pixel blocks (``_field_gain_offset`` form)."""
    ny, nx = -(-shape[0] // block), -(-shape[1] // block)
    cy = (np.arange(ny) + 0.5) * block - 0.5
    cx = (np.arange(nx) + 0.5) * block - 0.5
    yy, xx = np.meshgrid(cy, cx, indexing="ij")
    return _poly_terms(yy, xx, shape) @ coef


def _illumination(ys, xs, obs, reb, shape, gain, offset, sigma, fits, mode):
    """The smooth illumination field of :func:`fit_photometry` and the choice between it
    and the global model.  Returns ``(block, field_gain, field_offset, record)`` with the
    field None when the global model is kept."""
    C = obs.shape[1]
    block = max(8, -(-max(shape) // _POLY_NODES))
    fg = np.empty((C, -(-shape[0] // block), -(-shape[1] // block)))
    fo = np.empty_like(fg)
    s_field = np.empty(C)
    s_global = np.empty(C)

    def fit_band(c: int) -> None:  # each band writes its own rows
        r0 = obs[:, c] - gain[c] * reb[:, c] - offset[c]
        s_global[c] = inlier_scale(r0, sigma[c], median(r0))[1]
        a, b = fit_poly_field(ys, xs, reb[:, c], obs[:, c], shape, (gain[c], offset[c]),
                               float(fits[c].get("scale", sigma[c])))
        fg[c] = _poly_grid(a, shape, block)
        fo[c] = _poly_grid(b, shape, block)
        r = obs[:, c] - _grid_sample(fg[c], ys, xs, block) * reb[:, c] \
            - _grid_sample(fo[c], ys, xs, block)
        s_field[c] = inlier_scale(r, sigma[c], median(r))[1]

    band_map(fit_band, C)
    # the same estimator of the inliers' scale for both models; a floor of a 16-bit
    # quantum keeps noise-free data (both scales near 0) from a meaningless ratio
    ratio = (s_field + _SCALE_FLOOR) / (s_global + _SCALE_FLOOR)
    floor = float(fg.min())
    use = mode == "field" or bool(np.min(ratio) <= FIELD_GAIN and floor > MIN_FIELD_GAIN)
    record = {
        "model": "field" if use else "global",
        "mode": mode,
        "criterion": f"field if its inlier residual scale is <= {FIELD_GAIN} of the global "
                     "model's in some band" if mode == "auto" else "requested",
        "sigma_global": [float(v) for v in s_global],
        "sigma_field": [float(v) for v in s_field],
        "ratio": [round(float(v), 4) for v in ratio],
        "field": "gain and offset quadratic in the image coordinates",
    }
    if mode == "auto" and np.min(ratio) <= FIELD_GAIN and not use:
        record["rejected"] = (f"its gain falls to {floor:.3g} (<= {MIN_FIELD_GAIN}): not "
                              "light but a region the observation does not follow")
    if not use:
        return None, None, None, record
    record["gain_range"] = [float(fg.min()), float(fg.max())]
    return block, fg, fo, record


@threadpool_limits.wrap(limits=FIT_BLAS_THREADS, user_api="blas")
def fit_photometry(
    observed,
    reblurred,
    valid=None,
    *,
    boxes=None,
    image_shape: tuple[int, int] | None = None,
    scale: float = 1.0,
    field_block: int | None = None,
    max_samples: int = FIT_SAMPLES,
    smoothness: float = 0.01,
    edge_error: bool = True,
    rng=None,
    tolerance: ModelTolerance | None = None,
    illumination: str = "global",
    high_breakdown: bool = True,
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
        Samples drawn (seeded) for the fit (default :data:`FIT_SAMPLES`); with a field at
        least ``2048`` per block.
    smoothness : float
        Weight of the field's second-difference penalty, relative to the samples per block
        (see ``_fit_field``); linear trends are not penalised.
    rng : int or numpy.random.Generator, optional
        Seed of the subsampling (default 0: reproducible).

    edge_error : bool
        Also fit the model error ``edge_k`` and ``curv_k`` (:func:`fit_model_error`) on
        full-resolution input (not when ``scale != 1``).
    tolerance : ModelTolerance, optional
        The model's tolerance the statistic will use (:mod:`reblur.decide.tolerance`): the
        model error is fitted on what it leaves.  Default: ``DecisionParams().tolerance``
        (``ModelTolerance()`` for none).
    illumination : {"global", "field", "auto"}
        ``"global"``: one gain and offset per band (or the block field of ``field_block``).
        ``"field"``: a smooth illumination field, gain and offset quadratic in the image
        coordinates (a ramp, vignetting, a haze or cloud-shadow gradient; too smooth to
        absorb a change), fitted by Huber IRLS around the global fit and stored on a grid
        of at most 32 x 32 nodes.  ``"auto"``: the field when it brings the inliers'
        residual scale to at most :data:`FIELD_GAIN` (0.85) of the global model's in some
        band, else the global model.  ``info["illumination"]`` records the choice, the
        criterion and both scales.  Not with ``field_block``.

    Returns
    -------
    Photometry

    Raises
    ------
    ValueError
        On mismatched shapes, a missing box, or too few valid pixels (< 10).
    """
    rng = np.random.default_rng(0 if rng is None else rng)
    if illumination not in ILLUMINATIONS:
        raise ValueError(f"illumination must be one of {ILLUMINATIONS}, got {illumination!r}")
    if illumination != "global" and field_block is not None:
        raise ValueError("field_block is a field of its own: use it with illumination='global'")
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
    clip = clip_levels(obs)
    clipped = np.any((obs <= clip[:, 0]) | (obs >= clip[:, 1]), axis=1)
    n_clipped = int(np.count_nonzero(clipped))
    if n_clipped and obs.shape[0] - n_clipped >= 10:
        # clipped samples follow no line: the fit is on the others
        ys, xs, obs, reb = ys[~clipped], xs[~clipped], obs[~clipped], reb[~clipped]
    C = obs.shape[1]
    gain = np.empty(C)
    offset = np.empty(C)
    sigma = np.empty(C)
    fits = []

    def fit_band(c: int) -> tuple[float, float, dict, float]:
        if high_breakdown:
            g, o, fit = robust_line(reb[:, c], obs[:, c])
        else:
            g, o = huber_line(reb[:, c], obs[:, c])
            fit = {"method": "Huber", "huber": [g, o]}
        r = obs[:, c] - np.float64(g) * reb[:, c] - np.float64(o)
        if fit["method"] == "high-breakdown":
            # most pixels may be change: the inliers' scale, not a MAD of everything
            return g, o, fit, inlier_scale(r, fit["scale"])[1]
        return g, o, fit, _robust_scale(r)

    for c, (g, o, fit, s) in enumerate(band_map(fit_band, C)):
        gain[c], offset[c], sigma[c] = g, o, s
        fits.append(fit)
    methods = sorted({f["method"] for f in fits})
    info: dict[str, Any] = {
        "n_samples": int(obs.shape[0]),
        "method": "Huber IRLS" if methods == ["Huber"] else "high-breakdown (LQS start, "
        "Huber on the inliers): Huber's fit left far fewer pixels within 3.5 inlier scales",
        "inliers": [round(float(f.get("inliers", 1.0)), 4) for f in fits],
        "huber": [f["huber"] for f in fits],
    }
    if np.isfinite(clip).any():
        info["clip"] = {"levels": [[None if not np.isfinite(v) else float(v) for v in lh]
                                   for lh in clip],
                        "samples_left_out": n_clipped}
    fg = fo = None
    if illumination != "global":
        field_block, fg, fo, chosen = _illumination(
            ys, xs, obs, reb, image_shape, gain, offset, sigma, fits, illumination)
        info["illumination"] = chosen
        if fg is not None:
            sigma = np.asarray(chosen["sigma_field"], np.float64)
    elif field_block is not None:
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
        field_block=field_block, field_gain=fg, field_offset=fo,
        clip=clip if np.isfinite(clip).any() else None, info=info,
    )
    if edge_error and scale == 1.0:
        ph = with_model_error(ph, observed, reblurred, valid, boxes=boxes, tolerance=tolerance)
    return ph


def with_model_error(ph: Photometry, observed, reblurred, valid=None, *, boxes=None,
                     tolerance: ModelTolerance | None = None) -> Photometry:
    """``ph`` with its model error (``edge_k``, ``curv_k``) fitted by
    :func:`fit_model_error` on full-resolution data (one array, or tiles with their
    ``boxes``, as for :func:`fit_photometry`), outside the model's ``tolerance`` (default:
    ``DecisionParams().tolerance``)."""
    if tolerance is None:
        tolerance = DecisionParams().tolerance
    # gradients need full-resolution data: tiles or the whole image
    if isinstance(observed, np.ndarray) or not isinstance(observed, Sequence):
        tiles = [(observed, reblurred, valid, None)]
    else:
        vs = valid if valid is not None else [None] * len(observed)
        bs = boxes if boxes is not None else [None] * len(observed)
        tiles = list(zip(observed, reblurred, vs, bs, strict=True))
    os_, ms_, ks_ = [], [], []
    for o, r, v, b in tiles:
        o = _channels(_float(o))
        k = all_bands(np.isfinite(o))
        if v is not None:
            k &= np.asarray(v, bool)
        os_.append(o)
        ms_.append(_channels(ph.apply(r, b)))
        ks_.append(k)
    ek, ck = fit_model_error(os_, ms_, ks_, ph.sigma, tolerance=tolerance)
    return dataclasses.replace(ph, edge_k=ek, curv_k=ck)

