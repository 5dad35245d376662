"""Baselines and ablations to compare reblur against.

Every baseline takes the inputs of :func:`reblur.detect_changes` (a sharp ``reference`` and a
blurred, re-viewpointed ``observed`` image, ``(H, W)`` or ``(H, W, C)``, uint8/uint16 or float
in [0, 1]) and returns ``(change, info)``: a boolean change mask in the observation's frame
and a dict with at least ``timings`` (seconds per stage) and ``unknown`` (observation pixels
the registered reference does not cover; never reported as change).

* :func:`register_then_difference` -- the common practice that ignores blur: SIFT features
  (ECC fallback), RANSAC homography, absolute difference, Otsu threshold, 5x5 opening.
* :func:`deblur_then_difference` -- the pipeline the paper argues against: one
  space-invariant kernel (eq. 3/5 with a translation-only pose grid on a central window),
  non-blind deconvolution of the observation (Richardson-Lucy or Wiener, scikit-image), then
  registration, difference, Otsu, opening.
* :func:`sign_flip_occlusion` -- Punnappurath et al., ICIP 2013, as the paper describes it:
  the same reblur model, but non-negativity on the WHOLE vector ``[w; chi]``, the
  polarity of each identity column fixed in advance from the minimum and maximum of the
  corresponding row of ``F``.  An occluder whose intensity lies inside that range (close
  to the background) gets the wrong polarity on part of its pixels (paper, Fig. 1).
* :func:`whole_image_solve` -- the method without sub-image selection: eq. 5 on the whole
  observation (:func:`reblur.detect_changes` with one window covering the image).
"""

from __future__ import annotations

import time
from typing import Any

import cv2
import numpy as np
from scipy import ndimage
from skimage.filters import threshold_otsu

from .estimate import estimate_motion, soft_threshold
from .grid import PoseGrid
from .operator import BlurOperator
from .simulate import to_float
from .solve import active_set
from .tiled import reblur as reblur_image
from .warp import as_box, read_window

__all__ = [
    "register_homography",
    "difference_mask",
    "register_then_difference",
    "deblur_then_difference",
    "sign_flip_signs",
    "solve_signed",
    "sign_flip_occlusion",
    "whole_image_solve",
]


# ---------------------------------------------------------------------------- helpers
def _as_float(image) -> np.ndarray:
    """Float32 copy in [0, 1] (uint8 / uint16 scaled), ``(H, W, C)``."""
    a = to_float(np.asarray(image))[0]
    return a[:, :, None] if a.ndim == 2 else a


def _gray(a: np.ndarray) -> np.ndarray:
    return a.mean(axis=2) if a.ndim == 3 else a


def _u8(gray: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(gray * 255.0), 0, 255).astype(np.uint8)


def _check_pair(reference, observed) -> tuple[np.ndarray, np.ndarray]:
    ref, obs = _as_float(reference), _as_float(observed)
    if ref.shape[2] != obs.shape[2]:
        raise ValueError(
            f"reference has {ref.shape[2]} band(s) and observed {obs.shape[2]}: "
            "convert them to the same bands"
        )
    if min(ref.shape[:2] + obs.shape[:2]) < 32:
        raise ValueError("images must be at least 32x32 pixels")
    return ref, obs


def _warp(image: np.ndarray, H: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, ...]:
    """Warp ``(h, w, C)`` float32 ``image`` by ``H`` into ``shape``; also the covered mask."""
    h, w = shape
    out = np.empty((h, w, image.shape[2]), np.float32)
    for c in range(image.shape[2]):
        out[:, :, c] = cv2.warpPerspective(
            np.ascontiguousarray(image[:, :, c]), H, (w, h), flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT, borderValue=0,
        )
    ones = np.ones(image.shape[:2], np.float32)
    cover = cv2.warpPerspective(ones, H, (w, h), flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out, cover >= 1.0 - 1e-3


def register_homography(
    reference,
    observed,
    *,
    max_side: int = 2048,
    n_features: int = 8000,
    ratio: float = 0.75,
    ransac_px: float = 3.0,
    min_inliers: int = 12,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Reference -> observation homography from SIFT matches and RANSAC (ECC fallback).

    Blur is ignored: this is the registration of the common practice.

    Parameters
    ----------
    reference, observed : ndarray, (H, W) or (H, W, C)
        Images (uint8, uint16 or float in [0, 1]).
    max_side : int
        Features are detected on images downscaled so the longest side is at most this.
    n_features : int
        SIFT features per image.
    ratio : float
        Lowe's ratio test.
    ransac_px : float
        RANSAC inlier threshold, in pixels of the (downscaled) working images.
    min_inliers : int
        Fewer RANSAC inliers switch to the ECC fallback (identity start, homography motion,
        coarse to fine on a pyramid).

    Returns
    -------
    H : (3, 3) ndarray
        Maps reference pixels to observation pixels, full resolution.
    info : dict
        ``method`` (``"sift"`` or ``"ecc"``), ``n_matches``, ``n_inliers``.
    """
    ref, obs = _as_float(reference), _as_float(observed)
    k = max(1.0, max(ref.shape[:2] + obs.shape[:2]) / float(max_side))
    gr, go = _gray(ref), _gray(obs)
    if k > 1.0:
        gr = cv2.resize(gr, None, fx=1 / k, fy=1 / k, interpolation=cv2.INTER_AREA)
        go = cv2.resize(go, None, fx=1 / k, fy=1 / k, interpolation=cv2.INTER_AREA)
    S = np.diag([1.0 / k, 1.0 / k, 1.0])
    Sinv = np.diag([k, k, 1.0])
    sift = cv2.SIFT_create(nfeatures=n_features)
    k1, d1 = sift.detectAndCompute(_u8(gr), None)
    k2, d2 = sift.detectAndCompute(_u8(go), None)
    info: dict[str, Any] = dict(method="sift", n_matches=0, n_inliers=0)
    if d1 is not None and d2 is not None and len(k1) >= 4 and len(k2) >= 4:
        matches = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
        good = [m[0] for m in matches if len(m) == 2 and m[0].distance < ratio * m[1].distance]
        info["n_matches"] = len(good)
        if len(good) >= max(min_inliers, 4):
            src = np.float32([k1[m.queryIdx].pt for m in good])
            dst = np.float32([k2[m.trainIdx].pt for m in good])
            Hs, inl = cv2.findHomography(src, dst, cv2.RANSAC, ransac_px, maxIters=5000)
            n_in = int(inl.sum()) if inl is not None else 0
            info["n_inliers"] = n_in
            if Hs is not None and n_in >= min_inliers:
                H = Sinv @ Hs @ S
                return H / H[2, 2], info
    # fallback: ECC from the identity, coarse to fine
    info["method"] = "ecc"
    levels = [(gr, go)]
    while min(levels[-1][0].shape) > 128:
        a, b = levels[-1]
        levels.append((cv2.pyrDown(a), cv2.pyrDown(b)))
    Hs = np.eye(3, dtype=np.float32)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    for li in range(len(levels) - 1, -1, -1):
        a, b = levels[li]
        f = 2.0**li
        Hl = (np.diag([1 / f, 1 / f, 1.0]) @ Hs @ np.diag([f, f, 1.0])).astype(np.float32)
        # findTransformECC warps the input (observation) onto the template: it returns
        # the observation -> reference map
        Hinv = np.linalg.inv(Hl).astype(np.float32)
        try:
            _, Hinv = cv2.findTransformECC(
                a.astype(np.float32), b.astype(np.float32), Hinv, cv2.MOTION_HOMOGRAPHY, crit,
                None, 5,
            )
        except cv2.error:
            pass
        Hl = np.linalg.inv(Hinv)
        Hs = np.diag([f, f, 1.0]) @ Hl @ np.diag([1 / f, 1 / f, 1.0])
    H = Sinv @ Hs @ S
    return H / H[2, 2], info


def difference_mask(
    observed: np.ndarray,
    prediction: np.ndarray,
    known: np.ndarray,
    *,
    open_size: int = 5,
) -> tuple[np.ndarray, float, np.ndarray]:
    """Otsu threshold of the band-mean absolute difference, then a square opening.

    Parameters
    ----------
    observed, prediction : (H, W, C) float arrays
        The observation and what the reference predicts for it.
    known : (H, W) bool
        Pixels where the prediction exists (the threshold is fitted on them only).
    open_size : int
        Side of the square structuring element of the opening (0 or 1: no opening).

    Returns
    -------
    mask : (H, W) bool
    threshold : float
        Otsu's threshold on the absolute difference (NaN when too few known pixels).
    diff : (H, W) float32
        The absolute difference (band mean), 0 where unknown.
    """
    diff = np.abs(observed.astype(np.float32) - prediction.astype(np.float32)).mean(axis=2)
    diff[~known] = 0.0
    vals = diff[known]
    if vals.size < 16 or np.ptp(vals) <= 0:
        return np.zeros(known.shape, bool), float("nan"), diff
    thr = float(threshold_otsu(vals))
    mask = (diff > thr) & known
    if open_size > 1:
        mask = ndimage.binary_opening(mask, structure=np.ones((open_size, open_size), bool))
    return mask & known, thr, diff


# ---------------------------------------------------------------------------- (a)
def register_then_difference(
    reference,
    observed,
    *,
    open_size: int = 5,
    max_side: int = 2048,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Register ignoring blur, difference, threshold: the common practice.

    SIFT features, ratio test and a RANSAC homography (:func:`register_homography`, ECC
    fallback); the reference is warped into the observation's frame; the change mask is the
    band-mean absolute difference above Otsu's threshold, opened with a
    ``open_size x open_size`` square (:func:`difference_mask`).

    Parameters
    ----------
    reference, observed : ndarray, (H, W) or (H, W, C)
        Sharp reference and (blurred) observation, same band count.
    open_size : int
        Side of the opening's square.
    max_side : int
        Longest side of the images the features are detected on.

    Returns
    -------
    change : (H', W') bool ndarray
        Observation frame.
    info : dict
        ``H``, ``registration`` (method, matches, inliers), ``threshold``, ``unknown``,
        ``timings``.

    Examples
    --------
    >>> import numpy as np, cv2
    >>> rng = np.random.default_rng(0)
    >>> ref = cv2.GaussianBlur(rng.random((256, 256)).astype(np.float32), (0, 0), 2)
    >>> ref = (ref - ref.min()) / np.ptp(ref)
    >>> obs = np.roll(ref, (3, 5), axis=(0, 1)).copy()
    >>> obs[100:140, 100:140] = 1.0
    >>> mask, info = register_then_difference(ref, obs)
    >>> bool(mask[105:135, 105:135].mean() > 0.9), bool(mask[:80].mean() < 0.01)
    (True, True)
    """
    t0 = time.perf_counter()
    ref, obs = _check_pair(reference, observed)
    H, reg = register_homography(ref, obs, max_side=max_side)
    t1 = time.perf_counter()
    warped, known = _warp(ref, H, obs.shape[:2])
    mask, thr, _ = difference_mask(obs, warped, known, open_size=open_size)
    t2 = time.perf_counter()
    info = dict(
        H=H, registration=reg, threshold=thr, unknown=~known,
        timings=dict(register=t1 - t0, difference=t2 - t1, total=t2 - t0),
    )
    return mask, info


# ---------------------------------------------------------------------------- (b)
def _central_box(shape: tuple[int, int], side: int) -> tuple[int, int, int, int]:
    h, w = shape
    s_h, s_w = min(side, h), min(side, w)
    return ((h - s_h) // 2, (w - s_w) // 2, s_h, s_w)


def _deconvolve(image: np.ndarray, psf: np.ndarray, method: str, iterations: int,
                balance: float) -> np.ndarray:
    """Deconvolve every band of ``image`` (reflect-padded by the kernel size)."""
    from skimage import restoration

    pad = max(psf.shape)
    out = np.empty_like(image)
    for c in range(image.shape[2]):
        band = np.pad(image[:, :, c].astype(np.float64), pad, mode="reflect")
        if method == "richardson_lucy":
            rec = restoration.richardson_lucy(band, psf, num_iter=iterations, clip=True)
        elif method == "wiener":
            rec = restoration.wiener(band, psf, balance=balance, clip=True)
        else:
            raise ValueError(f"method must be 'richardson_lucy' or 'wiener', got {method!r}")
        out[:, :, c] = rec[pad:-pad, pad:-pad]
    return np.clip(out, 0.0, 1.0)


def deblur_then_difference(
    reference,
    observed,
    *,
    t_max: int = 12,
    window: int = 512,
    lam: float = 0.1,
    method: str = "richardson_lucy",
    iterations: int = 30,
    balance: float = 0.05,
    open_size: int = 5,
    max_side: int = 2048,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Deblur the observation with one space-invariant kernel, register, difference.

    1. Register the reference to the blurred observation, ignoring blur
       (:func:`register_homography`): ``H0``.
    2. Estimate ONE blur kernel: eq. 5 (:func:`reblur.estimate_motion`, changes allowed) on a
       central ``window x window`` window with a translation-only pose grid
       ``|tx|, |ty| <= t_max`` composed after ``H0``.  The pose weights are the kernel
       (``g = k * warp(f, H0)``), normalised to sum 1.  This is the best space-invariant
       kernel the reference allows, better than a blind estimate.
    3. Non-blind deconvolution of every band of the observation with scikit-image
       (Richardson-Lucy, ``iterations``; or Wiener with ``balance``).
    4. Register the reference to the deblurred observation (:func:`register_homography`,
       falling back to ``H0``), absolute difference, Otsu threshold, opening
       (:func:`difference_mask`).

    A rotating camera blurs differently across the image: one kernel cannot deblur it all,
    and deconvolution adds ringing and amplified noise, which the difference reports as
    change (the paper's argument, Sec. I).

    Parameters
    ----------
    reference, observed : ndarray, (H, W) or (H, W, C)
        Sharp reference and blurred observation, same band count.
    t_max : int
        Kernel half-size (pixels).
    window : int
        Side of the central window the kernel is estimated on.
    lam : float
        Eq. 5's lambda.
    method : {"richardson_lucy", "wiener"}
        Deconvolution.
    iterations : int
        Richardson-Lucy iterations.
    balance : float
        Wiener regularisation.
    open_size : int
        Side of the opening's square.
    max_side : int
        Longest side of the images the features are detected on.

    Returns
    -------
    change : (H', W') bool ndarray
    info : dict
        ``kernel``, ``H0``, ``H``, ``registration``, ``threshold``, ``unknown``,
        ``deblurred`` (float32 image), ``timings``.
    """
    t0 = time.perf_counter()
    ref, obs = _check_pair(reference, observed)
    H0, reg0 = register_homography(ref, obs, max_side=max_side)
    t1 = time.perf_counter()
    shape = obs.shape[:2]
    t = np.arange(-int(t_max), int(t_max) + 1)
    grid = PoseGrid(shape, tx=t, ty=t)
    box = _central_box(shape, window)
    est = estimate_motion(ref, obs, grid, boxes=[box], base=H0, lam=lam, occlusion=True)
    kernel = est.weights[0]
    if kernel.sum() <= 0:
        kernel = np.zeros_like(kernel)
        kernel[t_max, t_max] = 1.0
    kernel = kernel / kernel.sum()
    t2 = time.perf_counter()
    deblurred = _deconvolve(obs, kernel, method, iterations, balance).astype(np.float32)
    t3 = time.perf_counter()
    H, reg = register_homography(ref, deblurred, max_side=max_side)
    if reg["method"] != "sift":  # a failed re-registration: keep the blurred-image estimate
        H, reg = H0, dict(reg0, note="re-registration failed, H0 kept")
    warped, known = _warp(ref, H, shape)
    mask, thr, _ = difference_mask(deblurred, warped, known, open_size=open_size)
    t4 = time.perf_counter()
    info = dict(
        kernel=kernel, H0=H0, H=H, registration=reg, threshold=thr, unknown=~known,
        deblurred=deblurred, kernel_box=box,
        timings=dict(register=(t1 - t0) + (t4 - t3), kernel=t2 - t1, deconvolve=t3 - t2,
                     total=t4 - t0),
    )
    return mask, info


# ---------------------------------------------------------------------------- (c)
def _row_extrema(op: BlurOperator) -> tuple[np.ndarray, np.ndarray]:
    """Minimum and maximum over all poses of every row of ``F`` (window pixel and band).

    Fast engine with contiguous whole-pixel translations: per base pose, a rectangular
    min / max filter of the warped stack (the columns of ``F`` are its shifted slices).
    Otherwise one pass over the explicit columns.
    """
    grid = op.grid
    h, w, C = op.dimsd
    tx, ty = np.asarray(grid.tx), np.asarray(grid.ty)
    contiguous = (
        op.engine == "fast"
        and (tx.size == 1 or np.all(np.diff(tx) == 1))
        and (ty.size == 1 or np.all(np.diff(ty) == 1))
    )
    lo = np.full((h, w, C), np.inf)
    hi = np.full((h, w, C), -np.inf)
    if contiguous:
        kern = np.ones((op.Dy + 1, op.Dx + 1), np.uint8)
        for b in range(grid.n_bases):
            for c in range(C):
                s = np.ascontiguousarray(op.stack[b, :, :, c], dtype=np.float32)
                # anchor (0, 0): dst[y, x] = min / max of s[y:y + Dy + 1, x:x + Dx + 1]
                mn = cv2.erode(s, kern, anchor=(0, 0), borderType=cv2.BORDER_REPLICATE)
                mx = cv2.dilate(s, kern, anchor=(0, 0), borderType=cv2.BORDER_REPLICATE)
                np.minimum(lo[:, :, c], mn[:h, :w], out=lo[:, :, c])
                np.maximum(hi[:, :, c], mx[:h, :w], out=hi[:, :, c])
        return lo, hi
    for k in range(grid.size):
        col = op.column(k)
        np.minimum(lo, col, out=lo)
        np.maximum(hi, col, out=hi)
    return lo, hi


def sign_flip_signs(
    op: BlurOperator, g: np.ndarray, inside: str = "positive"
) -> np.ndarray:
    """Polarity of every identity column, fixed before solving (Punnappurath et al. 2013).

    For pixel (and band) ``i`` let ``lo_i, hi_i`` be the minimum and maximum of row ``i`` of
    ``F`` over ALL poses of the grid (every intensity the blur alone could produce there).

    * ``g_i > hi_i``: only a brighter occluder explains it, polarity ``+1``;
    * ``g_i < lo_i``: polarity ``-1`` (the sign of the identity column is flipped);
    * ``lo_i <= g_i <= hi_i``: the blur alone could explain the value and the rule has no
      evidence.  ``inside`` says what the column gets there: ``"positive"`` (default: the
      identity column keeps its ``+1``, only rows below the minimum are flipped),
      ``"negative"``, ``"nearest"`` (the polarity of the nearer extreme,
      ``sign(g_i - (lo_i + hi_i) / 2)``), or ``"none"`` (``0``: no change term there).

    Parameters
    ----------
    op : BlurOperator
        The window's operator.
    g : (h, w) or (h, w, C) ndarray
        The observation in the window, scaled like the operator's columns.
    inside : {"positive", "negative", "nearest", "none"}
        Rule for values inside the row's range.

    Returns
    -------
    (h, w, C) ndarray of float, values in {-1, 0, +1}
    """
    g3 = np.asarray(g, dtype=float).reshape(op.dimsd)
    lo, hi = _row_extrema(op)
    if inside == "nearest":
        s = np.where(g3 >= 0.5 * (lo + hi), 1.0, -1.0)
    elif inside in _INSIDE:
        s = np.full(g3.shape, _INSIDE[inside])
    else:
        raise ValueError(
            f"inside must be 'positive', 'negative', 'nearest' or 'none', got {inside!r}"
        )
    s = np.where(g3 > hi, 1.0, s)
    s = np.where(g3 < lo, -1.0, s)
    return s


_INSIDE = {"positive": 1.0, "negative": -1.0, "none": 0.0}


def solve_signed(
    op: BlurOperator,
    g: np.ndarray,
    signs: np.ndarray | None,
    *,
    lam: float = 0.1,
    mask: np.ndarray | None = None,
    batch: int = 24,
    max_outer: int = 40,
    max_irls: int = 30,
    tol: float = 1e-7,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Eq. 5 with the change term restricted to fixed polarities (or free: eq. 5 itself).

    Solves ``min ||g - F w - chi||^2 + lam (sum w + sum |chi|)`` subject to ``w >= 0`` and,
    where ``signs`` is non-zero, ``signs * chi >= 0``.  With ``A = [F, diag(signs)]`` this is
    exactly ICIP 2013's non-negative lasso on ``[w; |chi|]``.  Eliminating ``chi`` (for a
    fixed ``w`` the best ``|chi_i|`` is ``max(0, s_i r_i - lam / 2)``, ``r = g - F w``) leaves
    a one-sided Huber loss: ``2 d |r_i| - d^2`` where ``s_i r_i > d = lam / 2`` and ``r_i^2``
    otherwise (``signs=None``: the usual two-sided Huber of eq. 5).  It is solved like
    :func:`reblur.solve.active_set` (with its ``signs``): batched Lawson-Hanson over the
    poses, each active sub-problem solved exactly by a finite Newton method on the
    one-sided Huber partition.

    Parameters
    ----------
    op : BlurOperator
        Operator of the window.
    g : (h, w) or (h, w, C) ndarray
        Observation in the window (scaled like the operator).
    signs : (h, w, C) ndarray or None
        Allowed polarity of ``chi`` per pixel and band: ``+1``, ``-1``, or ``0`` (no change
        term: the pixel stays in the quadratic data term).  None: either polarity
        everywhere (eq. 5).
    lam : float
        Eq. 5's lambda.
    mask : (h, w) bool, optional
        Pixels in the data term (default ``op.valid``).
    batch, max_outer, max_irls, tol
        Solver settings (poses added per outer step, iteration caps, relative objective
        change that stops the outer loop).

    Returns
    -------
    w : ndarray, ``grid.shape``
    chi : (h, w, C) ndarray
        The change term (0 outside ``mask``).
    info : dict
        ``objective`` history, ``n_outer``, ``n_active``, ``time_s``.
    """
    t0 = time.perf_counter()
    m = op.valid if mask is None else np.asarray(mask, bool)
    m3 = np.broadcast_to(m[:, :, None], op.dimsd)
    g3 = np.asarray(g, dtype=float).reshape(op.dimsd)
    s = None if signs is None else np.asarray(signs, float).reshape(op.dimsd)
    d = lam / 2.0
    w, sinfo = active_set([op], [g3], lam=lam, masks=[m], signs=None if s is None else [s],
                          batch=batch, max_outer=max_outer, max_irls=max_irls, tol=tol)
    r = np.where(m3, g3 - op.matvec(w), 0.0)
    chi = soft_threshold(r, d) if s is None else s * np.maximum(s * r - d, 0.0)
    chi[~m3] = 0.0
    info = dict(objective=sinfo["objective"], n_outer=sinfo["n_outer"],
                n_active=sinfo["n_active"], time_s=time.perf_counter() - t0)
    return w, chi, info


def sign_flip_occlusion(
    reference,
    observed,
    *,
    grid: PoseGrid | None = None,
    box=None,
    base: np.ndarray | None = None,
    align: bool = False,
    lam: float = 0.1,
    inside: str = "positive",
    whole_image: bool = True,
    open_size: int = 5,
    tile_size: int = 1024,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Reblur-difference with sign-flipped occlusion columns (Punnappurath et al., ICIP 2013).

    The model is the paper's ``g = F w + chi`` but, as in ICIP 2013, non-negativity holds on
    the whole vector ``[w; |chi|]``, and the polarity of each identity column of
    ``A = [F, I]`` is chosen BEFORE solving from the minimum and maximum of the same row of
    ``F`` (:func:`sign_flip_signs`).  The problem is solved exactly
    (:func:`solve_signed`).  Pixels where the rule picked the wrong polarity cannot be
    explained as change: they stay in the quadratic data term, pull the pose weights, and
    are not detected.  With ``signs=None`` the same solver is eq. 5 (tested against
    :func:`reblur.estimate_motion`), so any difference between the two is the sign rule.

    Detection: the estimated weights reblur the whole reference (``whole_image``, by tiles);
    ``chi`` is recomputed from the residual with the same per-pixel polarities (row extrema
    of the whole image, computed window by window); the change mask is the support of
    ``chi`` (any band), opened with an ``open_size`` square.  ``whole_image=False`` reports
    only the estimation window's ``chi`` (False elsewhere).

    Parameters
    ----------
    reference, observed : ndarray, (H, W) or (H, W, C)
        Sharp reference and blurred observation (float in [0, 1] or integer).
    grid : PoseGrid, optional
        Pose grid on the observation geometry (default: the paper's 8125 poses).
    box : (y0, x0, h, w), optional
        Estimation window (default: the whole observation; ICIP 2013 had no sub-image
        selection).
    base : (3, 3) ndarray, optional
        Reference -> observation alignment composed before every pose.
    align : bool
        Estimate ``base`` with :func:`register_homography` (ignored if ``base`` is given).
    lam : float
        Lambda of the l1 penalty (the change term is ``max(0, s r - lam / 2)``).
    inside : {"positive", "negative", "nearest", "none"}
        Polarity rule for observed values inside the row's range (:func:`sign_flip_signs`).
    whole_image : bool
        Detect on the whole image (True) or the estimation window only.
    open_size : int
        Side of the opening's square (0: none).
    tile_size : int
        Tile side for the whole-image reblur and signs.

    Returns
    -------
    change : (H', W') bool ndarray
    info : dict
        ``weights``, ``grid``, ``box``, ``chi`` and ``signs`` (window), ``base``,
        ``psnr`` (fit on the window, all valid pixels), ``unknown``, ``solver``, ``timings``.
    """
    t0 = time.perf_counter()
    ref, obs = _check_pair(reference, observed)
    shape = obs.shape[:2]
    if grid is None:
        grid = PoseGrid.paper(shape)
    if base is None and align:
        base, _ = register_homography(ref, obs)
    box = as_box((0, 0, shape[0], shape[1]) if box is None else box)
    op = BlurOperator(ref, grid, box, base=base)
    g = read_window(obs, box, np.float64)
    t1 = time.perf_counter()
    signs = sign_flip_signs(op, g, inside)
    t2 = time.perf_counter()
    w, chi, sinfo = solve_signed(op, g, signs, lam=lam)
    t3 = time.perf_counter()
    r = (g - op.matvec(w))[op.valid]
    mse = float(np.mean(r * r)) if r.size else float("nan")
    psnr = 10 * np.log10(1.0 / mse) if mse > 0 else float("inf")
    del op
    change = np.zeros(shape, bool)
    unknown = np.ones(shape, bool)
    d = lam / 2.0
    if whole_image:
        reb, valid = reblur_image(ref, w, grid, base=base, tile_size=tile_size)
        reb = reb.reshape(obs.shape)
        unknown = ~valid
        for y0 in range(0, shape[0], tile_size):
            for x0 in range(0, shape[1], tile_size):
                tb = (y0, x0, min(tile_size, shape[0] - y0), min(tile_size, shape[1] - x0))
                top = BlurOperator(ref, grid, tb, base=base, spectra=False)
                sl = (slice(y0, y0 + tb[2]), slice(x0, x0 + tb[3]))
                s = sign_flip_signs(top, obs[sl], inside)
                res = obs[sl] - reb[sl]
                occ = (s * res > d).any(axis=2) & valid[sl]
                change[sl] = occ
                del top
    else:
        unknown[box.slices] = False
        change[box.slices] = (chi != 0).any(axis=2)
    if open_size > 1:
        change = ndimage.binary_opening(change, structure=np.ones((open_size, open_size), bool))
    change &= ~unknown
    t4 = time.perf_counter()
    info = dict(
        weights=w, grid=grid, box=box.as_tuple(), chi=chi, signs=signs, base=base, psnr=psnr,
        unknown=unknown, solver=sinfo,
        timings=dict(setup=t1 - t0, signs=t2 - t1, solve=t3 - t2, detect=t4 - t3,
                     total=t4 - t0),
    )
    return change, info


# ---------------------------------------------------------------------------- (d)
def whole_image_solve(
    reference,
    observed,
    *,
    grid: PoseGrid | None = None,
    t_max: int = 12,
    rz_max: float = 3.0,
    rz_step: float | None = 0.5,
    lam: float = 0.1,
    align: bool = True,
    tile_size: int = 1024,
    **kwargs,
) -> tuple[np.ndarray, dict[str, Any]]:
    """The method without sub-image selection: eq. 5 on the WHOLE observation.

    :func:`reblur.detect_changes` with one estimation window covering the observation
    (same alignment, photometric pre-match, tiled reblur and decision), so any difference
    from the full method is the window selection.  Time and memory grow with the image: the
    operator holds one warped copy of the (grown) window per base pose plus its spectrum,
    which is what the paper's sub-image selection avoids.

    Parameters
    ----------
    reference, observed : ndarray
        As for :func:`reblur.detect_changes`.
    grid, t_max, rz_max, rz_step, lam, align, tile_size
        Passed to :func:`reblur.detect_changes`.
    **kwargs
        Further keywords of :func:`reblur.detect_changes` (``decision``, ``threshold``, ...).

    Returns
    -------
    change : (H', W') bool ndarray
    info : dict
        ``result`` (the :class:`~reblur.result.ChangeResult`), ``psnr`` (eq. 5 fit on the
        whole image), ``unknown``, ``timings``.
    """
    from .pipeline import detect_changes

    H, W = observed.shape[:2]
    t0 = time.perf_counter()
    res = detect_changes(
        reference, observed, grid=grid, t_max=t_max, rz_max=rz_max, rz_step=rz_step, lam=lam,
        align=align, boxes=[(0, 0, H, W)], tile_size=tile_size, **kwargs,
    )
    timings = dict(res.timings)
    timings["total"] = time.perf_counter() - t0
    info = dict(result=res, psnr=res.motion.info.get("psnr"), unknown=res.unknown,
                timings=timings)
    return np.asarray(res.change, bool), info
