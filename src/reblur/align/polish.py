"""Blur-aware polish: local blur-kernel centroids move the estimate to the mean camera pose.

A correlation optimum between a sharp and a motion-blurred image lies near a *mode* of
the blur; the centroid of a non-negative kernel fitted between the warped reference and
the observation is the mean camera displacement (:func:`kernel_polish`).

Every region records why its kernel was not used (:data:`REASONS`): a polish whose regions
mostly fail because the blur model explains too little of their texture (``misfit``,
``faint``) meets content that differs between the images, which no larger shake extent
repairs (:func:`content_misfit`); a blur larger than the kernel spreads it (``spread``).
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.linalg import solve_triangular
from scipy.optimize import nnls
from threadpoolctl import threadpool_limits

from .._memory import thread_map
from .overviews import Level, to_full, to_level
from .params import AlignParams
from .result import AlignmentError
from .verify import check_regions, max_corner_shift

log = logging.getLogger(__name__)

#: Side, in pixels of the working level, of the kernel-polish regions.
REGION_PX = 32

#: What a polish region's kernel fit gave: ``fit`` (its centroid is used); ``invalid``
#: (too few pixels hold data in both images); ``flat`` (no texture in the observation);
#: ``faint`` (no non-negative kernel correlates: the best is zero); ``misfit`` (the kernel
#: explains less than ``min_r2`` of the variance); ``spread`` (it fits but spreads beyond
#: the shake extent: a blur larger than the kernel, or no camera shake).
REASONS = ("fit", "invalid", "flat", "faint", "misfit", "spread")

#: Regions run on threads from this many regions on (fewer: the pool costs more than it saves).
_MIN_THREADED = 8


def content_misfit(reasons: dict[str, int]) -> bool:
    """True when the polish regions' failures say the CONTENT differs, not the blur extent.

    ``reasons`` counts the regions by outcome (:data:`REASONS`).  The content misfits
    (``misfit`` and ``faint``: the blur model explains little of the texture whatever the
    kernel's shape) must be at least a quarter of the textured regions (neither
    ``invalid`` nor ``flat``) and at least as many as the ``spread`` kernels, the signature
    of a blur larger than the shake extent (a fitted kernel pushed to its border).

    Examples
    --------
    >>> content_misfit({"fit": 12, "misfit": 30, "spread": 20, "faint": 2})
    True
    >>> content_misfit({"fit": 8, "misfit": 1, "spread": 55})
    False
    """
    bad = reasons.get("misfit", 0) + reasons.get("faint", 0)
    textured = _textured(reasons)
    return bad > 0 and 4 * bad >= textured and bad >= reasons.get("spread", 0)


def blur_exceeds(reasons: dict[str, int]) -> bool:
    """True when the polish regions' failures say the BLUR is larger than the shake extent.

    ``reasons`` counts the regions by outcome (:data:`REASONS`).  At least three quarters
    of the textured regions (neither ``invalid`` nor ``flat``) fitted a kernel that
    explains their texture but spreads beyond the extent (``spread``).  That is a property
    of the blur, not of the estimate polished: a region's kernel is fitted around the
    estimate's local displacement, and a misplaced estimate moves the kernel (or, beyond
    its radius, makes it a ``misfit``) without widening it.  So another estimate polished
    with the same extent on the same level is refused for the same reason.

    Examples
    --------
    >>> blur_exceeds({"spread": 64})
    True
    >>> blur_exceeds({"fit": 30, "spread": 20, "flat": 14})
    False
    >>> blur_exceeds({"fit": 1, "misfit": 2, "spread": 40, "invalid": 21})
    True
    """
    spread = reasons.get("spread", 0)
    return spread > 0 and 4 * spread >= 3 * _textured(reasons)


def _textured(reasons: dict[str, int]) -> int:
    """The regions whose kernel was fitted (neither ``invalid`` nor ``flat``)."""
    return sum(n for k, n in reasons.items() if k not in ("invalid", "flat"))


@dataclass
class Polished:
    """A polished and verified estimate: ``H`` (full resolution), the regions that agree
    with it, those where the blur model fits, and all regions."""

    H: np.ndarray
    n_agree: int
    n_fit: int
    n_total: int
    #: the regions of the first pass (the largest kernel) by outcome (:data:`REASONS`)
    reasons: dict[str, int] = field(default_factory=dict)


class PolishError(AlignmentError):
    """The polish could not verify the estimate; ``reasons`` counts the regions of its
    first pass by outcome (:data:`REASONS`)."""

    def __init__(self, message: str, reasons: dict[str, int]):
        super().__init__(message)
        self.reasons = dict(reasons)


def region_grid(level: Level, shake_px: float) -> tuple[int, int]:
    """``(ny, nx)`` polish regions on ``level``: about :data:`REGION_PX` level pixels, and
    at least 6 pixels per kernel tap for a shake of ``shake_px`` full-resolution pixels."""
    shake = int(math.ceil(shake_px * level.scale))
    region_px = max(REGION_PX, math.sqrt(6.0) * (2 * max(shake + 2, 2) + 1))
    ny, nx = (int(np.clip(round(n / region_px), 3, 8)) for n in level.obs.shape)
    return ny, nx


@threadpool_limits.wrap(limits=1, user_api="blas")
def polish_and_verify(
    level: Level,
    H: np.ndarray,
    shake_px: float,
    ref_shape: tuple[int, int],
    params: AlignParams,
    plausible: Callable[[np.ndarray], object],
    *,
    workers: int = 1,
) -> Polished:
    """Kernel polish of ``H`` on the working ``level``, verified by its regions.

    The polish runs with kernels of radius ``shake + 2``, then ``shake + 1`` level pixels
    (``shake`` the extent ``shake_px`` on the level); a polish that moves the corners by
    more than twice the radius or that ``plausible`` refuses is not used.  Raises
    :class:`PolishError` (an AlignmentError) unless enough regions agree with the result
    (:func:`~reblur.align.verify.check_regions`); it and the result count the regions of
    the first pass by outcome (``reasons``).  ``workers`` threads fit the regions (the
    result is the one-thread result, bit for bit).

    BLAS runs on one thread: the kernels' Gram matrices (a few hundred columns) are too
    small to share, and on a busy host threads waiting for each other took 50x the time.
    """
    shake = int(math.ceil(shake_px * level.scale))
    n_regions = region_grid(level, shake_px)
    n_agree, n_fit, spread, accepted = 0, 0, 0.0, None
    reasons: dict[str, int] | None = None
    for R in (shake + 2, shake + 1):
        R = max(R, 2)
        Hp, n_agree, n_fit, spread, why = kernel_polish(
            level, H, R, n_regions=n_regions, min_r2=params.min_r2, max_pixels=8192,
            max_sd=max(1.0, shake_px * level.scale), workers=workers,
        )
        reasons = why if reasons is None else reasons
        if n_agree < 8:
            break
        jump = max_corner_shift(Hp, H, ref_shape) * level.scale
        if jump > 2 * R:
            log.debug("kernel polish rejected: corners moved by %.1f level px", jump)
            n_agree = 0
            break
        try:
            plausible(Hp)
        except AlignmentError as err:
            log.debug("kernel polish rejected: %s", err)
            n_agree = 0
            break
        H, accepted = Hp, (n_agree, n_fit, spread)
    if accepted is not None:
        n_agree, n_fit, spread = accepted
    log.debug("polish: %d regions agree, %d fit, spread %.2f", n_agree, n_fit, spread)
    n_total = n_regions[0] * n_regions[1]
    reasons = reasons or {}
    try:
        check_regions(n_agree, n_fit, spread, n_total, params, shake_px)
    except AlignmentError as err:
        raise PolishError(str(err), reasons) from None
    return Polished(H, n_agree, n_fit, n_total, reasons)


def kernel_polish(
    level: Level,
    H: np.ndarray,
    R: int,
    *,
    n_regions: tuple[int, int],
    min_r2: float,
    max_sd: float,
    max_pixels: int,
    workers: int = 1,
) -> tuple[np.ndarray, int, int, float, dict[str, int]]:
    """Blur-aware correction of ``H`` (full resolution) from local blur-kernel centroids.

    The reference is warped by ``H`` into the observation frame and, in each of
    ``n_regions = (ny, nx)`` regions, a non-negative ``(2R+1)^2`` kernel ``k`` is fitted so
    that ``warped * k ~ observation`` (zero-mean patches, so gain and offset do not matter).
    The centroid of ``k`` is the mean camera displacement there -- unlike the optimum of a
    correlation, it is not pulled by an asymmetric blur.  A homography fitted robustly to the
    region centres moved by their centroids corrects ``H``.  Returns
    ``(H, n_agree, n_fit, spread, reasons)``: the regions that agree with the corrected
    homography, the regions whose kernel fits, the area of the convex hull of the
    agreeing region centres relative to the region grid (``n_agree = 0`` and ``H``
    unchanged when no homography could be fitted), and the regions counted by outcome
    (:data:`REASONS`; all ``invalid`` when the level is too small for the grid).

    The regions are independent: ``workers > 1`` fits them on that many threads (the
    Gram products and the NNLS release the GIL), in the serial order, so the result is
    the one-thread result bit for bit.
    """
    Hs = to_level(H, level.scale)
    h, w = level.obs.shape
    ny, nx = n_regions
    if h < 2 * R + 8 * ny or w < 2 * R + 8 * nx:
        return H, 0, 0, 0.0, {"invalid": ny * nx}
    ref, valid = _warped(level, Hs, R)
    ys = np.linspace(R, h - R, ny + 1).astype(int)
    xs = np.linspace(R, w - R, nx + 1).astype(int)
    boxes = [(ys[i], ys[i + 1], xs[j], xs[j + 1]) for i in range(ny) for j in range(nx)]

    def fit(box: tuple[int, int, int, int]) -> tuple[tuple[float, float] | None, str]:
        return _kernel_centroid(level.obs, ref, valid, box, R, min_r2=min_r2, max_sd=max_sd,
                                max_pixels=max_pixels)

    fits = thread_map(fit, boxes, workers if len(boxes) >= _MIN_THREADED else 1)
    reasons = dict(Counter(why for _, why in fits))
    src, dst = [], []
    for (y0, y1, x0, x1), (d, _) in zip(boxes, fits, strict=True):
        if d is None:
            continue
        p = np.array([(x0 + x1 - 1) / 2.0, (y0 + y1 - 1) / 2.0])
        src.append(p)
        dst.append(p + d)
    if len(src) < 8:
        return H, 0, len(src), 0.0, reasons
    # correction C maps the warped-reference frame to the observation: H' = C @ H
    C, mask = cv2.findHomography(np.float64(src), np.float64(dst), cv2.RANSAC, 1.0)
    if C is None or mask is None or int(mask.sum()) < 8:
        return H, 0, len(src), 0.0, reasons
    Hn = to_full(C @ Hs, level.scale)
    inl = np.float32(src)[mask.ravel().astype(bool)]
    spread = cv2.contourArea(cv2.convexHull(inl)) / float((xs[-1] - xs[0]) * (ys[-1] - ys[0]))
    return Hn, int(mask.sum()), len(src), float(spread), reasons


def _warped(level: Level, Hs: np.ndarray, R: int) -> tuple[np.ndarray, np.ndarray]:
    """The reference warped by the level homography ``Hs`` into the observation frame, and
    the pixels where a ``(2R+1)^2`` kernel's whole footprint holds data in both images."""
    ref, cover = level.warped_reference(Hs)
    valid = (cover & level.obs_mask.astype(bool)).astype(np.uint8)
    # a core pixel is usable when the kernel's whole footprint is valid
    valid = cv2.erode(valid, np.ones((2 * R + 1, 2 * R + 1), np.uint8), borderValue=0)
    return ref, valid


def _nnls_gram(A: np.ndarray, b: np.ndarray, bb: float) -> tuple[np.ndarray, float]:
    """``argmin ||A k - b||^2`` over ``k >= 0`` and that residual sum of squares
    (``bb = b @ b``), solved on the Cholesky factor of the Gram matrix (``A^T A = L L^T``,
    ``||A k - b||^2 = ||L^T k - d||^2 + bb - d @ d`` with ``L d = A^T b``): a square
    problem of the kernel's taps instead of one row per pixel, twice as fast for the same
    solution.  The pixel rows themselves when the Gram matrix is singular (a flat region)."""
    try:
        L = np.linalg.cholesky(A.T @ A)
    except np.linalg.LinAlgError:
        k, rnorm = nnls(A, b, maxiter=50 * A.shape[1])
        return k, rnorm**2
    d = solve_triangular(L, A.T @ b, lower=True)
    k, rnorm = nnls(L.T, d, maxiter=50 * A.shape[1])
    return k, max(0.0, rnorm**2 + bb - float(d @ d))


def _kernel_centroid(
    obs: np.ndarray,
    ref: np.ndarray,
    valid: np.ndarray,
    region: tuple[int, int, int, int],
    R: int,
    *,
    min_r2: float,
    max_sd: float,
    max_pixels: int,
) -> tuple[tuple[float, float] | None, str]:
    """Centroid ``(dx, dy)`` of the non-negative ``(2R+1)^2`` kernel that blurs the warped
    reference ``ref`` into ``obs`` on ``region = (y0, y1, x0, x1)`` (at most ``max_pixels``
    of its ``valid`` pixels) and the outcome (:data:`REASONS`): None and why when too
    little is valid, the observation is flat, no kernel correlates, the kernel explains
    less than ``min_r2`` of the variance, or it spreads beyond ``max_sd``."""
    y0, y1, x0, x1 = region
    core = valid[y0:y1, x0:x1].astype(bool)
    n = int(core.sum())
    if n < 0.5 * core.size or n < 4 * (2 * R + 1) ** 2:
        return None, "invalid"
    step = max(1, int(math.ceil(math.sqrt(n / max_pixels))))
    sel = np.zeros_like(core)
    sel[::step, ::step] = core[::step, ::step]
    b = obs[y0:y1, x0:x1][sel].astype(np.float64)
    ext = ref[y0 - R : y1 + R, x0 - R : x1 + R]
    win = np.lib.stride_tricks.sliding_window_view(ext, (y1 - y0, x1 - x0))
    # column (a, c) holds the reference shifted by (R - c, R - a)
    A = win[:, :, sel].reshape((2 * R + 1) ** 2, -1).T.astype(np.float64)
    A -= A.mean(axis=0)
    b -= b.mean()
    bb = float(b @ b)
    if bb <= 1e-12 * b.size:
        return None, "flat"
    k, rss = _nnls_gram(A, b, bb)
    mass = float(k.sum())
    if mass <= 0:
        return None, "faint"
    if 1.0 - rss / bb < min_r2:
        return None, "misfit"
    K = k.reshape(2 * R + 1, 2 * R + 1) / mass
    taps = np.arange(-R, R + 1, dtype=float)
    dy = -float(K.sum(axis=1) @ taps)  # g(x) = sum_d k_d ref(x - d), d = (R - c, R - a)
    dx = -float(K.sum(axis=0) @ taps)
    # a camera-shake kernel is compact; one fitted where the scene changed spreads
    sd = math.sqrt(
        float(K.sum(axis=1) @ (taps + dy) ** 2) + float(K.sum(axis=0) @ (taps + dx) ** 2)
    )
    if sd > max_sd:
        return None, "spread"
    return (dx, dy), "fit"
