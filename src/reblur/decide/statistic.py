"""Stage 2 of the change decision, the statistic (:func:`change_statistic`; local).
``z_c = (g_c - a_c m_c - b_c) / sigma_c`` per band, ``sigma_c`` grown where the reblurred
reference has edges and fine texture (model error: ``sigma_c^2 + (k |grad m|)^2 +
(c lap m)^2``, fitted from the data by :func:`fit_model_error`), and
``S = sqrt(G * mean_c z_c^2 / G * 1)``: the RMS of the z-scores over a Gaussian window of
``smooth`` pixels (:func:`gaussian_zero`), normalised over known pixels only (unknown
pixels neither contribute nor receive a value).  Every band enters the sum, so a change in
any one band counts; the window averages about ``4 pi smooth^2 C`` squared z-scores, which
cuts the variance of the statistic accordingly.  It is a filter of radius
``int(truncate * smooth + 0.5)`` plus the per-pixel reach.  With a ``tolerance``
(:mod:`.tolerance`) the residual ``g - m`` is replaced by the observation's distance from
the interval of values the model allows around ``m``.
"""

from __future__ import annotations

import threading
from typing import Any

import cv2
import numpy as np
import scipy.ndimage as ndi

from ._common import _channels, _float, band_map
from .tolerance import ModelTolerance, tolerant_reference


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
    tolerance: ModelTolerance | None = None,
    reach: np.ndarray | None = None,
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
    edge_k, curv_k : (C,) array_like, optional
        Model-error coefficients (:func:`fit_model_error`).
    tolerance : ModelTolerance, optional
        The residual is taken from the model's tolerance interval around ``matched``
        (:func:`reblur.decide.tolerance.tolerant_reference`) instead of ``matched`` itself.
    reach : (h, w) integer ndarray, optional
        Per-pixel geometric reach widening that interval (the local displacement field's
        uncertainty, :meth:`reblur.align.field.DisplacementField.reach_map`).

    Returns
    -------
    S : (h, w) float32 ndarray
        ``sqrt(sum_w G * mean_c z_c^2 / sum_w G)`` over known pixels; 0 where unknown.

    Notes
    -----
    The value at a pixel depends only on pixels within ``int(truncate * smooth + 0.5)``
    plus the per-pixel reach (1 for the 3 x 3 stencils, ``tolerance.reach`` for the
    interval: ``DecisionParams.pixel_reach``), so a tile with at least that halo gives the
    whole-image values on its core.
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
        mt = tolerant_reference(o[:, :, c], mc, tolerance, reach)
        g32 = _grad2_f32(mc) if ks[c] > 0 else None
        l32 = _laplacian_f32(mc) if kc[c] > 0 else None
        s2 = f32(s[c] * s[c])
        for sl in bands:
            t = o[sl, :, c].astype(f32)
            t -= mt[sl]
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
                    rng=0, tolerance: ModelTolerance | None = None,
                    ) -> tuple[np.ndarray, np.ndarray]:
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
    tolerance : ModelTolerance, optional
        Fit the error left outside the model's tolerance interval (the residual of
        :func:`change_statistic` with the same ``tolerance``).

    Returns
    -------
    edge_k, curv_k : (C,) ndarray
    """
    if isinstance(observed, np.ndarray):
        observed, matched, known = [observed], [matched], [known]
    rng = np.random.default_rng(rng)
    s = np.asarray(sigma, dtype=np.float64).reshape(-1)
    C = s.size
    # per band: observed, matched, |grad m|^2 and lap m at the usable pixels, in their own
    # (single) precision; the float64 products are formed on the sample only (the same
    # values, element by element, as on whole tiles: a float32 -> float64 cast is exact)
    tiles, masks = [], []
    for o, m, k in zip(observed, matched, known, strict=True):
        tiles.append((_channels(_float(o)), _channels(_float(m))))
        # pixels whose 3x3 stencil is known: the values at unknown pixels are arbitrary
        k = np.asarray(k, bool)
        if k.all():  # the erosion (border value 1) keeps every pixel: no masked copies
            masks.append(None)
        else:
            reach = max(1, tolerance.reach if tolerance is not None else 0)
            masks.append(ndi.binary_erosion(k, np.ones((3, 3), bool), iterations=reach,
                                            border_value=1))

    # the predictors in this thread (OpenCV's filters), band after band
    accs: list[list[list[np.ndarray]]] = [[[], [], [], []] for _ in range(C)]
    for (o, m), k in zip(tiles, masks, strict=True):
        for c in range(C):
            mt = tolerant_reference(o[:, :, c], m[:, :, c], tolerance)
            for j, v in enumerate((o[:, :, c], mt, _grad2_f32(m[:, :, c]),
                                   _laplacian_f32(m[:, :, c]))):
                accs[c][j].append(v.ravel() if k is None else v[k])
    # the fits (numpy) side by side, each exactly as alone; the samples drawn first, in
    # band order (one generator for all of them)
    n = sum(a.size for a in accs[0][0]) if C else 0  # the same pixels in every band
    if n < 20 * bins * bins:
        return np.zeros(C), np.zeros(C)
    picks = [rng.choice(n, max_samples, replace=False) if n > max_samples else None
             for _ in range(C)]
    fits = band_map(lambda c: _fit_band_error(accs[c], picks[c], s[c], bins), C)
    ek, ck = np.zeros(C), np.zeros(C)
    for c, ab in enumerate(fits):
        if ab is not None:
            ek[c] = min(np.sqrt(max(ab[0], 0.0)), k_max)
            ck[c] = min(np.sqrt(max(ab[1], 0.0)), c_max)
    return ek, ck


def _fit_band_error(acc: list[list[np.ndarray]], pick: np.ndarray | None, sigma: float,
                    bins: int) -> tuple[float, float] | None:
    """One band's ``(a, b)`` of :func:`fit_model_error` from its predictors' pieces ``acc``
    (observed, tolerant reference, ``|grad m|^2``, ``lap m``) and the sample ``pick`` of
    their concatenation (None: all of it); None when fewer than two cells are filled."""
    from scipy.optimize import nnls

    if pick is not None:
        # the sample drawn from the (never built) concatenation of the tiles
        ov, mv, g2, lp = _take_concatenated(acc, pick)
    else:
        ov, mv, g2, lp = (np.concatenate(a) for a in acc)
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
    # per cell); on 8- or 16-bit keys numpy's stable sort is a radix sort (4 x 10^5 cells
    # of 64, ``python -m timeit``: 2.7 ms against 16 ms as int64)
    small = np.uint8 if bins * bins <= 256 else np.uint16 if bins * bins <= 65536 else None
    by_cell = np.argsort(cell if small is None else cell.astype(small), kind="stable")
    starts = np.flatnonzero(np.diff(cell[by_cell], prepend=-1))
    for s0, s1 in zip(starts, np.append(starts[1:], cell.size), strict=True):
        sel = by_cell[s0:s1]
        n = int(s1 - s0)
        if n < 20:
            continue
        rows.append([g2[sel].mean(), l2[sel].mean()])
        rhs.append(float(np.median(r2[sel])) / 0.455 - sigma ** 2)
        wts.append(np.sqrt(n))
    if len(rows) < 2:
        return None
    A = np.asarray(rows) * np.asarray(wts)[:, None]
    scale = np.maximum(A.max(axis=0), 1e-300)  # conditioning: columns to unit range
    coef, _ = nnls(A / scale, np.asarray(rhs) * np.asarray(wts))
    a, b = coef / scale
    return float(a), float(b)


def _sorting_order(idx: np.ndarray, n: int) -> np.ndarray:
    """``np.argsort(idx, kind="stable")`` for indices into ``range(n)``.  Distinct ones (a
    sample without replacement) are sorted by marking them: one pass over ``n`` flags
    instead of a comparison sort (4 x 10^5 indices, ``python -m timeit``: of 10^6, 3.3 ms
    against 31 ms; of 4.2 x 10^6, the sample windows of a large image, 11 against 32 ms)."""
    mark = np.zeros(n, bool)
    mark[idx] = True
    if int(np.count_nonzero(mark)) != idx.size:  # repeated indices: no shortcut
        return np.argsort(idx, kind="stable")
    pos = np.empty(n, np.int32 if idx.size < 2**31 else np.intp)
    pos[idx] = np.arange(idx.size, dtype=pos.dtype)
    return pos[np.flatnonzero(mark)]


def _take_concatenated(lists: list[list[np.ndarray]], idx: np.ndarray) -> list[np.ndarray]:
    """``np.concatenate(pieces)[idx]`` for each list of pieces (all of the same sizes),
    without building the concatenations: ``idx`` is sorted once, so each piece serves a
    contiguous run of it, written back to the positions it came from."""
    offsets = np.cumsum([0] + [a.size for a in lists[0]])
    order = _sorting_order(idx, int(offsets[-1]))
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

