"""Coarse, low-resolution alignment of a sharp reference to a blurred observation.

The pose grid of the blur model (``tx, ty`` in +-12 px, ``rz`` in +-3 degrees) only absorbs
small viewpoint differences.  Larger ones are removed first by a global homography estimated
at low resolution, where the camera-shake blur is small (a 25 px blur is 3 px at 1/8 scale):

1. :func:`overview` reads both images in horizontal strips and block-averages them to a
   grey overview whose longest side is at most ``max_side`` (the same integer factor for both
   images), then a pyramid of halvings down to ``min_side``.
2. SIFT features on an overview level, a ratio test and a robust homography (MAGSAC /
   RANSAC; a 4-dof similarity when matches are few).  If that fails, phase correlation gives
   a translation to start from.
3. ECC refinement (:func:`cv2.findTransformECC`), coarse to fine, on Gaussian pre-blurred
   levels, up to the *working level*: the finest one on which the camera shake spans at
   most 4 pixels.
4. Blur-aware polish on the working level: in a grid of regions, a non-negative blur kernel
   between the warped reference and the observation; its centroid is the mean camera
   displacement there (a correlation optimum sits near a mode of the blur instead, several
   pixels off).  A robust homography through the region centres moved by their centroids
   corrects the estimate, and the share of regions that agree with it verifies it.
5. Sanity checks: orientation, zoom, anisotropy, overlap, inliers, region agreement and
   correlation.  Anything implausible raises :class:`AlignmentError` -- never silent garbage.

Between captures years apart (other season, sun, sensor; buildings changed) local features
and the polish's blur model both fail, so the default ``method="auto"`` decides with
*gradient blocks* first: signed-gradient fields of the reference warped by the current
estimate and of the observation are correlated block by block (``_BLOCK_PX`` blocks, +-8
pixels), and a robust similarity through the blocks whose correlation peak is confident
corrects the estimate.  Enough confident blocks -- a clear majority of them -- spread over
the image must agree; unrelated images give almost no confident block.  The initial
estimate is the SIFT one when it holds, else the best of a few in-plane rotation
hypotheses searched with larger blocks on a coarse level.  The polish then runs as
well and is kept where its blur model fits (a same-scene pair).

:func:`coarse_align_shakes` tries several shake extents on one pair: the overviews, the
pyramid, and the stages that read the extent only through the working level (features,
their ECC refinement, gradient blocks) are computed once and shared.

Coordinates follow :mod:`reblur.grid`: ``(x, y)`` = (column, row) with pixel centres on
integers, and ``H`` maps a reference pixel to the observation pixel.  An overview made with
the integer block factor ``k`` (``scale = 1 / k``) has pixel ``x_s`` centred on the full
resolution position ``x = k * x_s + (k - 1) / 2`` (i.e. ``(x_s + 0.5) / scale - 0.5``).
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable, Hashable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
from scipy.optimize import nnls

from .grid import map_points, translation

__all__ = [
    "Alignment", "AlignmentError", "OverviewCache", "block_means", "coarse_align",
    "coarse_align_shakes", "overview", "overview_matrix",
]

log = logging.getLogger(__name__)

#: Read at most this many bytes (as float32) per strip when building overviews.
_STRIP_BYTES = 64 * 2**20

#: Side, in pixels of the working level, of the kernel-polish regions.
_REGION_PX = 32

_METHODS = ("auto", "features", "gradient", "ecc")
_MOTIONS = {"homography": cv2.MOTION_HOMOGRAPHY, "affine": cv2.MOTION_AFFINE}


class AlignmentError(ValueError):
    """The reference and the observation could not be aligned (reason in the message)."""


@dataclass(frozen=True)
class Alignment:
    """Result of :func:`coarse_align`.

    Attributes
    ----------
    H : (3, 3) ndarray of float64
        Reference -> observation homography in FULL-resolution pixel coordinates,
        normalised so that ``H[2, 2] == 1``.
    method : str
        The stages that produced ``H``, joined by ``+``: ``features`` or ``phase`` (the
        initial estimate), ``ecc`` (refinement) and ``kernel`` (blur-aware polish), e.g.
        ``"features+ecc+kernel"``.
    n_matches : int
        Feature matches that passed the ratio test (0 when features were not used).
    n_inliers : int
        Matches consistent with the robust feature estimate.
    scale : float
        Working downscale of the finest overview (``1 / k`` for a block factor ``k``).
    residual_px : float or None
        Median distance, in full-resolution pixels, between the inlier matches of the
        observation and the reference matches mapped by ``H`` (None without features).
    ecc : float or None
        Correlation coefficient of the pre-blurred reference and observation under ``H`` on
        the working level (None when too little overlaps to compute it).
    overlap : float
        Fraction of the observation covered by the mapped reference.
    n_regions : int
        Regions of the kernel polish that agree with ``H`` (0 when the polish did not run
        or was rejected).
    n_blocks : int
        Gradient blocks whose correlation is confident and that agree with ``H`` (0 when
        the gradient blocks were not used).
    """

    H: np.ndarray
    method: str
    n_matches: int
    n_inliers: int
    scale: float
    residual_px: float | None
    ecc: float | None
    overlap: float
    n_regions: int = 0
    n_blocks: int = 0

    def to_dict(self) -> dict:
        """JSON-ready description of the alignment."""
        return {
            "H": [[float(v) for v in row] for row in np.asarray(self.H)],
            "method": self.method,
            "n_matches": int(self.n_matches),
            "n_inliers": int(self.n_inliers),
            "scale": float(self.scale),
            "residual_px": None if self.residual_px is None else float(self.residual_px),
            "ecc": None if self.ecc is None else float(self.ecc),
            "overlap": float(self.overlap),
            "n_regions": int(self.n_regions),
            "n_blocks": int(self.n_blocks),
        }


# ---------------------------------------------------------------------- overviews
def _shape2(image) -> tuple[int, int]:
    shape = tuple(int(s) for s in image.shape)
    if len(shape) not in (2, 3):
        raise ValueError(f"image must be (H, W) or (H, W, C), got shape {shape}")
    if min(shape[:2]) < 1 or (len(shape) == 3 and shape[2] < 1):
        raise ValueError(f"image is empty: shape {shape}")
    return shape[0], shape[1]


def _dtype_norm(dtype) -> float:
    dtype = np.dtype(dtype)
    if dtype == np.bool_:
        return 1.0
    if np.issubdtype(dtype, np.integer):
        return 1.0 / float(np.iinfo(dtype).max)
    if np.issubdtype(dtype, np.floating):
        return 1.0
    raise ValueError(f"unsupported image dtype {dtype}")


def _block_factor(max_len: int, max_side: int) -> int:
    if max_side < 1:
        raise ValueError(f"max_side must be positive, got {max_side}")
    return max(1, math.ceil(max_len / max_side))


def _overview_k(image, k: int) -> np.ndarray:
    """Grey block mean of ``image`` over ``k x k`` blocks (partial edge blocks dropped)."""
    return block_means(image, k)[0]


def block_means(image, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Grey and per-band means of ``image`` over ``k x k`` blocks, in one read.

    Integer images are divided by their dtype's maximum (floats kept, NaN and Inf -> 0);
    partial edge blocks are dropped.  An image that keeps its overviews (an
    :class:`OverviewCache`, or anything with a ``block_means(k)`` method) answers
    without a read when it can.

    Returns
    -------
    grey : (H // k, W // k) float32 ndarray
        Block means of the band average (of the image itself for one band).
    bands : (H // k, W // k, C) float32 ndarray
        Block means of every band (a view of ``grey`` for one band).
    """
    fn = getattr(image, "block_means", None)
    if fn is not None:
        return fn(int(k))
    return _read_block_means(image, int(k))


def _read_block_means(image, k: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`block_means` read from the image, in horizontal strips.

    The next strip is read (decoded) in the background while one is averaged.  Integer
    images are summed exactly in integers; floats are averaged by OpenCV's area resize.
    """
    H, W = _shape2(image)
    C = int(image.shape[2]) if len(image.shape) == 3 else 1
    h, w = H // k, W // k
    if h < 1 or w < 1:
        raise ValueError(f"image {H}x{W} is smaller than one {k}x{k} overview block")
    dtype = np.dtype(image.dtype)
    norm = _dtype_norm(dtype)
    m = max(1, _STRIP_BYTES // (k * k * w * C * 4))  # output rows per strip
    bands = np.empty((h, w, C), np.float32)

    def read(r0: int) -> np.ndarray:
        a = np.asarray(image[r0 * k : min(r0 + m, h) * k, : w * k])
        return a.reshape(a.shape[0], a.shape[1], C)

    with ThreadPoolExecutor(1) as pool:
        ahead = pool.submit(read, 0)
        for r0 in range(0, h, m):
            r1 = min(r0 + m, h)
            a = ahead.result()
            if r1 < h:
                ahead = pool.submit(read, r1)
            bands[r0:r1] = _strip_means(a, k, norm)
    grey = bands[:, :, 0] if C == 1 else bands.mean(axis=2, dtype=np.float32)
    return grey, bands


def _strip_means(a: np.ndarray, k: int, norm: float) -> np.ndarray:
    """``(r k, w k, C)`` -> ``(r, w, C)`` float32 means of ``k x k`` blocks, times ``norm``."""
    rk, wk, C = a.shape
    r, w = rk // k, wk // k
    if a.dtype.kind == "b" or (a.dtype.kind in "ui" and a.dtype.itemsize <= 4):
        top = 1 if a.dtype.kind == "b" else int(np.iinfo(a.dtype).max)
        if a.dtype.kind == "i":
            acc, vert = np.int64, np.int64
        else:
            acc = np.uint32 if k * k * top < 2**32 else np.uint64
            vert = np.uint16 if k * top < 2**16 else acc
        v = np.add.reduce(a.reshape(r, k, wk * C), axis=1, dtype=vert)
        t = np.add.reduce(v.reshape(r, w, k, C), axis=2, dtype=acc)
        out = t.astype(np.float64)
        out *= norm / (k * k)
        return out.astype(np.float32)
    f = a.astype(np.float32, copy=False)
    if a.dtype.kind == "f":
        f = np.nan_to_num(f, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    if k > 1:
        f = np.stack([cv2.resize(np.ascontiguousarray(f[:, :, c]), (w, r),
                                 interpolation=cv2.INTER_AREA) for c in range(C)], axis=2)
    if norm != 1.0:
        f = f * np.float32(norm)
    return f


class OverviewCache:
    """An image that keeps the block-mean overviews read from it.

    It stands in for the image anywhere (``shape``, ``dtype`` and ``__getitem__`` are the
    image's), and :func:`block_means` (hence :func:`overview`) asks it first: a block
    factor already read costs nothing, and a multiple of one is block-averaged from it
    (the mean of means over equal blocks is the mean), so the several low-resolution
    views of a pipeline -- alignment, photometric pre-fit, window selection -- read a
    huge image once.  What it keeps is a few overviews (each ``1 / k^2`` of the image).

    Parameters
    ----------
    image : array-like, (H, W) or (H, W, C)
        numpy, zarr, tifffile store, ...

    Attributes
    ----------
    reads : int
        Passes over the image so far.
    """

    def __init__(self, image):
        self.image = image
        self.shape = tuple(int(s) for s in image.shape)
        self.dtype = np.dtype(image.dtype)
        self.reads = 0
        self._memo: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def __getitem__(self, key):
        return self.image[key]

    def factor(self, k: int) -> int:
        """The smallest block factor ``>= k`` that costs no read, if one is at most
        ``2 k``; otherwise ``k``."""
        got = [k0 * -(-k // k0) for k0 in self._memo]
        got = [g for g in got if g <= 2 * k]
        return min(got) if got else int(k)

    def block_means(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """:func:`block_means` of the image, read at most once per unrelated factor."""
        k = int(k)
        if k not in self._memo:
            divisors = [k0 for k0 in self._memo if k % k0 == 0]
            if divisors:
                k0 = max(divisors)
                _, bands0 = self._memo[k0]
                f = k // k0
                h, w = self.shape[0] // k, self.shape[1] // k
                if h < 1 or w < 1:
                    raise ValueError(f"image {self.shape[0]}x{self.shape[1]} is smaller than "
                                     f"one {k}x{k} overview block")
                C = bands0.shape[2]
                bands = np.empty((h, w, C), np.float32)
                for c in range(C):
                    bands[:, :, c] = cv2.resize(
                        np.ascontiguousarray(bands0[: h * f, : w * f, c]), (w, h),
                        interpolation=cv2.INTER_AREA)
                grey = bands[:, :, 0] if C == 1 else bands.mean(axis=2, dtype=np.float32)
                self._memo[k] = (grey, bands)
            else:
                self._memo[k] = _read_block_means(self.image, k)
                self.reads += 1
        return self._memo[k]


def overview(image, max_side: int = 1024) -> tuple[np.ndarray, float]:
    """Low-resolution grey overview of a (possibly huge, on-disk) image.

    Parameters
    ----------
    image : array-like, (H, W) or (H, W, C)
        numpy array, zarr array, tifffile zarr store, ... of any integer or float dtype.
        It is read in horizontal strips; no full-resolution float copy is made.
    max_side : int
        Longest side allowed for the overview.

    Returns
    -------
    small : (h, w) ndarray of float32
        Mean of ``k x k`` blocks (``k = ceil(max(H, W) / max_side)``) averaged over bands,
        integer inputs divided by their dtype's maximum (floats kept as they are; NaN
        becomes 0).  ``h = H // k``, ``w = W // k``: incomplete edge blocks are dropped.
    scale : float
        ``1 / k``.  Overview pixel ``(x_s, y_s)`` is centred on the full-resolution point
        ``((x_s + 0.5) / scale - 0.5, (y_s + 0.5) / scale - 0.5)``.
    """
    k = _block_factor(max(_shape2(image)), max_side)
    return _overview_k(image, k), 1.0 / k


def overview_matrix(scale: float) -> np.ndarray:
    """3x3 matrix mapping overview pixel coordinates to full-resolution coordinates.

    ``x = (x_s + 0.5) / scale - 0.5``; a homography ``Hs`` between two overviews of the same
    scale is ``A @ Hs @ inv(A)`` at full resolution.
    """
    k = 1.0 / float(scale)
    return np.array([[k, 0.0, (k - 1.0) / 2.0], [0.0, k, (k - 1.0) / 2.0], [0.0, 0.0, 1.0]])


def _to_level(H: np.ndarray, scale: float) -> np.ndarray:
    A = overview_matrix(scale)
    M = np.linalg.inv(A) @ H @ A
    return M / M[2, 2]


def _to_full(Hs: np.ndarray, scale: float) -> np.ndarray:
    A = overview_matrix(scale)
    M = A @ Hs @ np.linalg.inv(A)
    return M / M[2, 2]


def _halve(a: np.ndarray) -> np.ndarray:
    h, w = a.shape[0] // 2, a.shape[1] // 2
    return cv2.resize(a[: 2 * h, : 2 * w], (w, h), interpolation=cv2.INTER_AREA)


@dataclass
class _Level:
    ref: np.ndarray
    obs: np.ndarray
    scale: float
    ref_mask: np.ndarray  # uint8, 1 where the overview pixel holds data
    obs_mask: np.ndarray

    @property
    def side(self) -> int:
        return max(self.ref.shape + self.obs.shape)


def _data_mask(a: np.ndarray, nodata: float | None) -> np.ndarray:
    """1 where ``a`` holds data: ``nodata`` pixels count as missing only in 7x7 patches
    (an opening), so that isolated black pixels of real imagery are kept."""
    if nodata is None:
        return np.ones(a.shape, np.uint8)
    missing = (a == np.float32(nodata)).astype(np.uint8)
    missing = cv2.morphologyEx(missing, cv2.MORPH_OPEN, np.ones((7, 7), np.uint8))
    return 1 - missing


def _halve_mask(m: np.ndarray) -> np.ndarray:
    # a coarse pixel holds data only if its four children do
    return (_halve(m.astype(np.float32)) > 0.999).astype(np.uint8)


def _pyramid(
    ref0: np.ndarray, obs0: np.ndarray, scale0: float, min_side: int, nodata: float | None
) -> list[_Level]:
    """Levels from fine (index 0) to coarse; each halves the previous one."""
    levels = [_Level(ref0, obs0, scale0, _data_mask(ref0, nodata), _data_mask(obs0, nodata))]
    while True:
        last = levels[-1]
        if last.side // 2 < min_side or min(last.ref.shape + last.obs.shape) // 2 < 16:
            break
        levels.append(
            _Level(
                _halve(last.ref), _halve(last.obs), last.scale / 2.0,
                _halve_mask(last.ref_mask), _halve_mask(last.obs_mask),
            )
        )
    return levels


# ---------------------------------------------------------------------- checks
def _quad_area(q: np.ndarray) -> float:
    x, y = q[:, 0], q[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _corners(shape: tuple[int, int]) -> np.ndarray:
    h, w = shape
    return np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], dtype=float)


def _check_plausible(
    H: np.ndarray,
    ref_shape: tuple[int, int],
    obs_shape: tuple[int, int],
    *,
    max_zoom: float,
    max_anisotropy: float,
    min_overlap: float,
) -> float:
    """Raise AlignmentError unless ``H`` is a plausible viewpoint change; return the overlap."""
    if not np.all(np.isfinite(H)) or abs(np.linalg.det(H)) < 1e-12:
        raise AlignmentError("alignment is degenerate: singular or non-finite homography")
    rc = _corners(ref_shape)
    wz = rc @ H[2, :2] + H[2, 2]
    if np.any(wz <= 1e-6 * np.abs(H[2, 2])):
        raise AlignmentError(
            "alignment is degenerate: the reference crosses the horizon of the homography"
        )
    q = map_points(H, rc)
    # every turn of the mapped quadrilateral must keep the reference's orientation
    e = np.roll(q, -1, axis=0) - q
    turns = e[:, 0] * np.roll(e, -1, axis=0)[:, 1] - e[:, 1] * np.roll(e, -1, axis=0)[:, 0]
    if np.any(turns <= 0):
        raise AlignmentError("alignment is degenerate: the mapped reference is folded or mirrored")
    zoom = math.sqrt(_quad_area(q) / _quad_area(rc))
    if not 1.0 / max_zoom <= zoom <= max_zoom:
        raise AlignmentError(
            f"alignment is degenerate: zoom {zoom:.3g} outside [1/{max_zoom:g}, {max_zoom:g}]"
        )
    # local anisotropy at the four corners and the centre (Jacobian singular values)
    pts = np.vstack([rc, rc.mean(axis=0)])
    for x, y in pts:
        wv = H[2, 0] * x + H[2, 1] * y + H[2, 2]
        u = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / wv
        v = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / wv
        J = (H[:2, :2] - np.outer([u, v], H[2, :2])) / wv
        s = np.linalg.svd(J, compute_uv=False)
        if s[1] <= 0 or s[0] / s[1] > max_anisotropy:
            raise AlignmentError(
                f"alignment is degenerate: local stretch ratio {s[0] / max(s[1], 1e-12):.3g} "
                f"exceeds {max_anisotropy:g}"
            )
    oc = _corners(obs_shape)
    inter, _ = cv2.intersectConvexConvex(q.astype(np.float32), oc.astype(np.float32))
    overlap = float(inter) / _quad_area(oc) if _quad_area(oc) > 0 else 0.0
    if overlap < min_overlap:
        raise AlignmentError(
            f"alignment is implausible: the mapped reference covers {100 * overlap:.1f} % of the "
            f"observation (< {100 * min_overlap:.0f} %)"
        )
    return overlap


def _spread(a: np.ndarray) -> float:
    lo, hi = np.percentile(a, [1.0, 99.0])
    return float(hi - lo)


# ---------------------------------------------------------------------- stage 1: features
def _to_u8(a: np.ndarray) -> np.ndarray:
    lo, hi = np.percentile(a, [0.5, 99.5])
    if hi <= lo:
        hi = lo + 1e-12
    return np.clip((a - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)


@dataclass
class _Features:
    H: np.ndarray  # full resolution
    src: np.ndarray  # inlier reference points, full resolution
    dst: np.ndarray  # inlier observation points, full resolution
    n_matches: int
    n_inliers: int


def _match_features(
    level: _Level,
    *,
    n_features: int,
    ratio: float,
    ransac_px: float,
    min_inliers: int,
    min_inlier_ratio: float,
) -> _Features:
    """SIFT + ratio test + robust homography on one level; raise AlignmentError on failure."""
    sift = cv2.SIFT_create(nfeatures=n_features)
    kr, dr = sift.detectAndCompute(_to_u8(level.ref), None)
    ko, do = sift.detectAndCompute(_to_u8(level.obs), None)
    nk = min(len(kr), len(ko))
    if dr is None or do is None or nk < min_inliers:
        raise AlignmentError(
            f"images are textureless: only {nk} feature points found (< {min_inliers})"
        )
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(dr, do, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < ratio * p[1].distance]
    # keep one match per observation point (the closest)
    best: dict[int, cv2.DMatch] = {}
    for mt in good:
        if mt.trainIdx not in best or mt.distance < best[mt.trainIdx].distance:
            best[mt.trainIdx] = mt
    good = list(best.values())
    n = len(good)
    if n < min_inliers:
        raise AlignmentError(
            f"too few feature matches ({n} < {min_inliers}) between reference and observation"
        )
    src = np.float64([kr[mt.queryIdx].pt for mt in good])
    dst = np.float64([ko[mt.trainIdx].pt for mt in good])
    Hs, mask = None, None
    if n >= 3 * min_inliers:
        Hs, mask = cv2.findHomography(
            src, dst, cv2.USAC_MAGSAC, ransac_px, maxIters=20000, confidence=0.9999
        )
    if Hs is None or mask is None or int(mask.sum()) < min_inliers:
        A, mask = cv2.estimateAffinePartial2D(
            src, dst, method=cv2.RANSAC, ransacReprojThreshold=ransac_px, maxIters=20000,
            confidence=0.9999,
        )
        Hs = None if A is None else np.vstack([A, [0.0, 0.0, 1.0]])
    if Hs is None or mask is None:
        raise AlignmentError(
            f"no consistent transform among {n} feature matches between reference and observation"
        )
    inl = mask.ravel().astype(bool)
    ni = int(inl.sum())
    if ni < min_inliers:
        raise AlignmentError(
            f"too few feature inliers ({ni} < {min_inliers} of {n} matches) between reference "
            "and observation"
        )
    if ni < min_inlier_ratio * n:
        raise AlignmentError(
            f"feature matches are inconsistent: {ni} inliers of {n} matches "
            f"(< {100 * min_inlier_ratio:.0f} %)"
        )
    A = overview_matrix(level.scale)
    return _Features(
        H=_to_full(np.asarray(Hs, float), level.scale),
        src=map_points(A, src[inl]),
        dst=map_points(A, dst[inl]),
        n_matches=n,
        n_inliers=ni,
    )


# ---------------------------------------------------------------------- stage 2: ECC
def _phase_init(level: _Level) -> np.ndarray:
    """Translation (full resolution homography) from phase correlation on one level."""
    h = max(level.ref.shape[0], level.obs.shape[0])
    w = max(level.ref.shape[1], level.obs.shape[1])

    def pad(a: np.ndarray) -> np.ndarray:
        out = np.zeros((h, w), np.float64)
        out[: a.shape[0], : a.shape[1]] = a - a.mean()
        return out

    win = cv2.createHanningWindow((w, h), cv2.CV_64F)
    (dx, dy), _ = cv2.phaseCorrelate(pad(level.ref), pad(level.obs), win)
    return _to_full(translation(dx, dy), level.scale)


def _ecc_level(
    level: _Level, H: np.ndarray, motion: int, sigma: float, iterations: int, eps: float
) -> tuple[np.ndarray, float]:
    """One ECC run on a level; ``H`` in and out at full resolution.  Raises cv2.error."""
    Hs = _to_level(H, level.scale)
    ref = cv2.GaussianBlur(level.ref, (0, 0), sigma) if sigma > 0 else level.ref
    obs = cv2.GaussianBlur(level.obs, (0, 0), sigma) if sigma > 0 else level.obs
    if motion == cv2.MOTION_HOMOGRAPHY:
        warp = Hs.astype(np.float32)
    else:
        warp = (Hs[:2] / Hs[2, 2]).astype(np.float32)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, eps)
    # leave out pixels near missing data (nodata borders), which the pre-blur smears
    r = int(math.ceil(3 * sigma)) + 1
    kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    rmask = cv2.erode(level.ref_mask, kernel, borderType=cv2.BORDER_REPLICATE)
    omask = cv2.erode(level.obs_mask, kernel, borderType=cv2.BORDER_REPLICATE)
    if rmask.sum() < 64 or omask.sum() < 64:
        raise AlignmentError("images hold too little valid data for ECC")
    rho, warp = cv2.findTransformECCWithMask(ref, obs, rmask, omask, warp, motion, crit, 1)
    M = np.asarray(warp, np.float64)
    if M.shape == (2, 3):
        M = np.vstack([M, [0.0, 0.0, 1.0]])
    return _to_full(M / M[2, 2], level.scale), float(rho)


def _max_corner_shift(H1: np.ndarray, H2: np.ndarray, shape: tuple[int, int]) -> float:
    c = _corners(shape)
    return float(np.max(np.hypot(*(map_points(H1, c) - map_points(H2, c)).T)))


def _ecc_refine(
    levels: list[_Level],
    H: np.ndarray,
    start: int,
    stop: int,
    ref_shape: tuple[int, int],
    *,
    motion: int,
    blur_px: float,
    sigma_min: float,
    iterations: int,
    max_jump: float,
    tolerant: bool = False,
) -> tuple[np.ndarray, float, float]:
    """Coarse-to-fine ECC from level ``start`` down to level ``stop`` (inclusive).

    Returns ``(H, rho, scale)`` of the finest level that converged.  Raises AlignmentError
    when no level converges or the estimate jumps by more than ``max_jump`` of a level's
    size (at the first level) -- later levels that fail keep the coarser estimate.  With
    ``tolerant`` (a trusted initial ``H``), levels that fail before any converged are
    skipped instead.
    """
    rho_out, scale_out, done = float("nan"), float("nan"), False
    for i in range(start, stop - 1, -1):
        lv = levels[i]
        size = f"{lv.ref.shape[1]}x{lv.ref.shape[0]} px"
        try:
            sigma = max(sigma_min, blur_px * lv.scale)
            Hn, rho = _ecc_level(lv, H, motion, sigma, iterations, 1e-6)
            jump = _max_corner_shift(Hn, H, ref_shape) * lv.scale
            if not np.all(np.isfinite(Hn)) or jump > max_jump * lv.side:
                raise AlignmentError(f"ECC did not converge: the estimate moved by {jump:.0f} px")
        except (cv2.error, AlignmentError) as err:
            if done:
                log.debug("ECC failed at level %d (%s), keeping the coarser estimate", i, err)
                break
            if tolerant and i > stop:
                log.debug("ECC failed at level %d (%s), trying a finer level", i, err)
                continue
            if isinstance(err, AlignmentError):
                raise AlignmentError(f"{err} at {size}") from None
            raise AlignmentError(
                f"ECC did not converge at {size}: images may be unrelated or too different"
            ) from err
        H, rho_out, scale_out, done = Hn, rho, lv.scale, True
    return H, rho_out, scale_out


# ---------------------------------------------------------------------- stage 2b: gradient blocks
#: Side, in pixels of the level, of the blocks matched by :func:`_block_match`.
_BLOCK_PX = 96
#: Side of the blocks of the coarse (rotation hypothesis) search.
_COARSE_BLOCK_PX = 64


def _grad_field(a: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """``(h, w, 2)`` signed gradient of ``a`` smoothed by ``sigma``, zero near missing data.

    Gradients drop the brightness offset between captures and emphasise the edges (roads,
    roof outlines, field borders) that survive years between them; zeroing them near
    missing data keeps the edge of a nodata border from matching itself.
    """
    b = cv2.GaussianBlur(a, (0, 0), sigma)
    gx = cv2.Sobel(b, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(b, cv2.CV_32F, 0, 1, ksize=3)
    r = int(math.ceil(2 * sigma)) + 2
    m = cv2.erode(
        mask.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8),
        borderType=cv2.BORDER_CONSTANT, borderValue=0,
    )
    return np.dstack([gx * m, gy * m])


def _parabola(a: float, b: float, c: float) -> float:
    d = a - 2.0 * b + c
    return 0.0 if d >= 0 else float(np.clip(0.5 * (a - c) / d, -0.5, 0.5))


def _block_match(
    level: _Level, H: np.ndarray, *, block: int, search: int, step: int, sigma: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Displacements of gradient blocks between the reference warped by ``H`` and the
    observation, on one level.

    The reference is warped into the observation frame by ``H`` (full resolution); for
    every ``block x block`` block of the observation (centres ``step`` apart) the
    normalised correlation of the two gradient fields is searched over ``+-search`` pixels.
    Returns ``(src, dst, ncc)``: ``src`` the matched points of the warped reference,
    ``dst`` the block centres of the observation (level pixels), and the correlation peak.
    """
    Hs = _to_level(H, level.scale)
    h, w = level.obs.shape
    warped = cv2.warpPerspective(
        level.ref, Hs, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
    )
    cover = cv2.warpPerspective(
        level.ref_mask.astype(np.float32), Hs, (w, h), flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
    ) > 0.999
    fr = _grad_field(warped, cover, sigma)
    fo = _grad_field(level.obs, level.obs_mask, sigma)
    has_r = np.any(fr != 0, axis=2)
    has_o = np.any(fo != 0, axis=2)
    half, S = block // 2, search
    src, dst, score = [], [], []
    for cy in range(half + S, h - half - S + 1, step):
        for cx in range(half + S, w - half - S + 1, step):
            t = fo[cy - half : cy + half, cx - half : cx + half]
            win = (slice(cy - half - S, cy + half + S), slice(cx - half - S, cx + half + S))
            if has_o[cy - half : cy + half, cx - half : cx + half].mean() < 0.9:
                continue
            if has_r[win].mean() < 0.8:
                continue
            sr = fr[win]
            if float(np.ptp(t)) <= 0 or float(np.ptp(sr)) <= 0:
                continue
            r = cv2.matchTemplate(
                np.ascontiguousarray(sr), np.ascontiguousarray(t), cv2.TM_CCOEFF_NORMED
            )
            _, peak, _, (px, py) = cv2.minMaxLoc(r)
            if not np.isfinite(peak):
                continue
            dx = px - S + (_parabola(*r[py, px - 1 : px + 2]) if 0 < px < 2 * S else 0.0)
            dy = py - S + (_parabola(*r[py - 1 : py + 2, px]) if 0 < py < 2 * S else 0.0)
            # observation block at c matches the warped reference at c + d
            src.append((cx + dx, cy + dy))
            dst.append((cx, cy))
            score.append(peak)
    return (
        np.float64(src).reshape(-1, 2), np.float64(dst).reshape(-1, 2), np.float64(score)
    )


def _similarity_lsq(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares similarity (rotation, uniform scale, translation) ``src -> dst``."""
    n = len(src)
    A = np.zeros((2 * n, 4))
    A[0::2] = np.c_[src[:, 0], -src[:, 1], np.ones(n), np.zeros(n)]
    A[1::2] = np.c_[src[:, 1], src[:, 0], np.zeros(n), np.ones(n)]
    a, b, tx, ty = np.linalg.lstsq(A, dst.reshape(-1), rcond=None)[0]
    return np.array([[a, -b, tx], [b, a, ty], [0.0, 0.0, 1.0]])


def _robust_similarity(
    src: np.ndarray, dst: np.ndarray, tol: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """RANSAC similarity then least squares on its inliers (re-selected three times).

    Returns ``(M, inliers)`` or None when fewer than 4 points agree.
    """
    if len(src) < 4:
        return None
    M, mask = cv2.estimateAffinePartial2D(
        src, dst, method=cv2.RANSAC, ransacReprojThreshold=tol, maxIters=5000,
        confidence=0.999, refineIters=0,
    )
    if M is None or mask is None:
        return None
    inl = mask.ravel().astype(bool)
    M = np.vstack([M, [0.0, 0.0, 1.0]])
    for _ in range(3):
        if inl.sum() < 4:
            return None
        M = _similarity_lsq(src[inl], dst[inl])
        inl = np.hypot(*(map_points(M, src) - dst).T) < tol
    if inl.sum() < 4:
        return None
    return M, inl


@dataclass
class _Blocks:
    H: np.ndarray  # full resolution
    n_agree: int  # confident blocks that agree with H
    n_confident: int  # blocks whose correlation peak reaches the confidence level
    n_blocks: int  # blocks matched
    spread: float  # convex hull of the agreeing blocks / area of the block grid
    residual_px: float  # median misfit of the agreeing blocks, full-resolution pixels


def _gradient_estimate(
    level: _Level,
    H: np.ndarray,
    ref_shape: tuple[int, int],
    *,
    block: int,
    search: int,
    sigma: float,
    min_ncc: float,
    tol: float,
    iterations: int = 3,
) -> _Blocks | None:
    """Correct ``H`` (full resolution) by a similarity fitted to the confident gradient
    blocks of one level that agree within ``tol`` level pixels; repeat up to
    ``iterations`` times while the corners still move.  None when fewer than 4 agree."""
    best: _Blocks | None = None
    for _ in range(iterations):
        src, dst, score = _block_match(
            level, H, block=block, search=search, step=max(4, block // 3), sigma=sigma
        )
        conf = score >= min_ncc
        fit = _robust_similarity(src[conf], dst[conf], tol)
        if fit is None:
            return best
        M, inl = fit
        # C maps the warped-reference frame to the observation: H' = C @ H
        Hn = _to_full(M @ _to_level(H, level.scale), level.scale)
        pts = dst[conf][inl]
        grid = float((np.ptp(dst[:, 0]) + block) * (np.ptp(dst[:, 1]) + block))
        spread = cv2.contourArea(cv2.convexHull(np.float32(pts))) / max(grid, 1.0)
        res = float(np.median(np.hypot(*(map_points(M, src[conf][inl]) - pts).T)))
        moved = _max_corner_shift(Hn, H, ref_shape) * level.scale
        H = Hn
        best = _Blocks(H, int(inl.sum()), int(conf.sum()), len(score), float(spread),
                       res / level.scale)
        if moved < 0.1:
            break
    return best


def _gradient_align(
    levels: list[_Level],
    H0: np.ndarray | None,
    ref_shape: tuple[int, int],
    fine: int,
    *,
    rotations: tuple[float, ...],
    min_ncc: float,
    min_blocks: int,
    min_agree: float,
    min_spread: float,
    plausible,
) -> _Blocks:
    """Alignment by gradient-block correlation (independent of local features).

    Without an initial ``H0``: on the finest level whose longest side is at most 256,
    every in-plane rotation of ``rotations`` (degrees, about the reference centre) is
    tried and blocks searched over +-10 % of the side; the hypothesis with most confident
    agreeing blocks wins.  Then, on each level down to ``fine``, the estimate is refined
    with a +-8 pixel search.  Raises AlignmentError unless at least ``min_blocks``
    confident blocks, and at least ``min_agree`` of all the confident ones, agree, spread
    over ``min_spread`` of the block grid.
    """
    h, w = ref_shape
    if H0 is None:
        ic = next((i for i, lv in enumerate(levels) if lv.side <= 256), len(levels) - 1)
        ic = max(ic, fine)
        lv = levels[ic]
        search = max(8, round(0.1 * lv.side))
        best: _Blocks | None = None
        for rz in rotations:
            Hr = translation((w - 1) / 2.0, (h - 1) / 2.0) @ _rotation(rz) @ translation(
                -(w - 1) / 2.0, -(h - 1) / 2.0
            )
            b = _gradient_estimate(
                lv, Hr, ref_shape, block=_COARSE_BLOCK_PX, search=search, sigma=1.0,
                min_ncc=min_ncc, tol=1.5, iterations=1,
            )
            log.debug("gradient hypothesis rz=%g: %s", rz, None if b is None else b.n_agree)
            if b is not None and (best is None or b.n_agree > best.n_agree):
                best = b
        if best is None or best.n_agree < 4:
            n = 0 if best is None else best.n_agree
            raise AlignmentError(
                f"no consistent gradient structure: {n} confident blocks agree at "
                f"{lv.ref.shape[1]}x{lv.ref.shape[0]} px"
            )
        H0, start = best.H, ic - 1
    else:
        start = fine
    plausible(H0)
    H, out = H0, None
    for i in range(max(start, fine), fine - 1, -1):
        lv = levels[i]
        b = _gradient_estimate(
            lv, H, ref_shape, block=min(_BLOCK_PX, max(lv.obs.shape) // 4), search=8,
            sigma=1.0, min_ncc=min_ncc, tol=1.0,
        )
        if b is None:
            raise AlignmentError(
                f"gradient blocks are inconsistent at {lv.ref.shape[1]}x{lv.ref.shape[0]} px: "
                "images unrelated or changed too much"
            )
        plausible(b.H)
        H, out = b.H, b
    assert out is not None
    log.debug("gradient blocks: %d agree of %d confident, %d in all; spread %.2f",
              out.n_agree, out.n_confident, out.n_blocks, out.spread)
    need = max(min_blocks, math.ceil(min_agree * out.n_confident))
    if out.n_agree < need:
        raise AlignmentError(
            f"alignment could not be verified: {out.n_agree} gradient blocks agree with it, "
            f"of {out.n_confident} confident and {out.n_blocks} in all (need {need}): "
            "images unrelated, changed too much or not one plane (parallax)"
        )
    if out.spread < min_spread:
        raise AlignmentError(
            f"alignment could not be verified: the {out.n_agree} gradient blocks that agree "
            f"with it span {100 * out.spread:.0f} % of the image (< {100 * min_spread:.0f} %)"
        )
    return out


def _rotation(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# ---------------------------------------------------------------------- stage 3: kernels
def _kernel_polish(
    level: _Level,
    H: np.ndarray,
    R: int,
    *,
    n_regions: tuple[int, int],
    min_r2: float,
    max_sd: float,
    max_pixels: int,
) -> tuple[np.ndarray, int, int, float]:
    """Blur-aware correction of ``H`` (full resolution) from local blur-kernel centroids.

    The reference is warped by ``H`` into the observation frame and, in each of
    ``n_regions = (ny, nx)`` regions, a non-negative ``(2R+1)^2`` kernel ``k`` is fitted so
    that ``warped * k ~ observation`` (zero-mean patches, so gain and offset do not matter).
    The centroid of ``k`` is the mean camera displacement there -- unlike the optimum of a
    correlation, it is not pulled by an asymmetric blur.  A homography fitted robustly to the
    region centres moved by their centroids corrects ``H``.  Returns
    ``(H, n_agree, n_fit, spread)``: the regions that agree with the corrected homography,
    the regions whose kernel fits, and the area of the convex hull of the agreeing region
    centres relative to the region grid (``n_agree = 0`` and ``H`` unchanged when no
    homography could be fitted).
    """
    Hs = _to_level(H, level.scale)
    h, w = level.obs.shape
    ny, nx = n_regions
    if h < 2 * R + 8 * ny or w < 2 * R + 8 * nx:
        return H, 0, 0, 0.0
    ref = cv2.warpPerspective(
        level.ref, Hs, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
    )
    cover = cv2.warpPerspective(
        level.ref_mask.astype(np.float32), Hs, (w, h), flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
    )
    valid = ((cover > 0.999) & level.obs_mask.astype(bool)).astype(np.uint8)
    # a core pixel is usable when the kernel's whole footprint is valid
    valid = cv2.erode(valid, np.ones((2 * R + 1, 2 * R + 1), np.uint8), borderValue=0)
    ys = np.linspace(R, h - R, ny + 1).astype(int)
    xs = np.linspace(R, w - R, nx + 1).astype(int)
    taps = np.arange(-R, R + 1, dtype=float)
    src, dst = [], []
    for i in range(ny):
        for j in range(nx):
            y0, y1, x0, x1 = ys[i], ys[i + 1], xs[j], xs[j + 1]
            core = valid[y0:y1, x0:x1].astype(bool)
            n = int(core.sum())
            if n < 0.5 * core.size or n < 4 * (2 * R + 1) ** 2:
                continue
            step = max(1, int(math.ceil(math.sqrt(n / max_pixels))))
            sel = np.zeros_like(core)
            sel[::step, ::step] = core[::step, ::step]
            b = level.obs[y0:y1, x0:x1][sel].astype(np.float64)
            ext = ref[y0 - R : y1 + R, x0 - R : x1 + R]
            win = np.lib.stride_tricks.sliding_window_view(ext, (y1 - y0, x1 - x0))
            # column (a, c) holds the reference shifted by (R - c, R - a)
            A = win[:, :, sel].reshape((2 * R + 1) ** 2, -1).T.astype(np.float64)
            A -= A.mean(axis=0)
            b -= b.mean()
            bb = float(b @ b)
            if bb <= 1e-12 * b.size:
                continue
            k, rnorm = nnls(A, b, maxiter=50 * A.shape[1])
            mass = float(k.sum())
            if mass <= 0 or 1.0 - rnorm**2 / bb < min_r2:
                continue
            K = k.reshape(2 * R + 1, 2 * R + 1) / mass
            dy = -float(K.sum(axis=1) @ taps)  # g(x) = sum_d k_d ref(x - d), d = (R - c, R - a)
            dx = -float(K.sum(axis=0) @ taps)
            # a camera-shake kernel is compact; one fitted where the scene changed spreads
            sd = math.sqrt(
                float(K.sum(axis=1) @ (taps + dy) ** 2) + float(K.sum(axis=0) @ (taps + dx) ** 2)
            )
            if sd > max_sd:
                continue
            p = np.array([(x0 + x1 - 1) / 2.0, (y0 + y1 - 1) / 2.0])
            src.append(p)
            dst.append(p + (dx, dy))
    if len(src) < 8:
        return H, 0, len(src), 0.0
    # correction C maps the warped-reference frame to the observation: H' = C @ H
    C, mask = cv2.findHomography(np.float64(src), np.float64(dst), cv2.RANSAC, 1.0)
    if C is None or mask is None or int(mask.sum()) < 8:
        return H, 0, len(src), 0.0
    Hn = _to_full(C @ Hs, level.scale)
    inl = np.float32(src)[mask.ravel().astype(bool)]
    spread = cv2.contourArea(cv2.convexHull(inl)) / float((xs[-1] - xs[0]) * (ys[-1] - ys[0]))
    return Hn, int(mask.sum()), len(src), float(spread)


def _correlation(level: _Level, H: np.ndarray, sigma: float) -> float:
    """Correlation of the smoothed reference and observation under ``H`` on one level."""
    Hs = _to_level(H, level.scale)
    h, w = level.ref.shape
    ref = cv2.GaussianBlur(level.ref, (0, 0), sigma)
    obs = cv2.GaussianBlur(level.obs, (0, 0), sigma)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    back = cv2.warpPerspective(obs, Hs, (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT)
    cover = cv2.warpPerspective(
        level.obs_mask.astype(np.float32), Hs, (w, h), flags=flags,
        borderMode=cv2.BORDER_CONSTANT,
    )
    r = int(math.ceil(3 * sigma)) + 1
    m = ((cover > 0.999) & level.ref_mask.astype(bool)).astype(np.uint8)
    m = cv2.erode(m, np.ones((2 * r + 1, 2 * r + 1), np.uint8)).astype(bool)
    if m.sum() < 64:
        return float("nan")
    a = ref[m].astype(np.float64)
    b = back[m].astype(np.float64)
    a -= a.mean()
    b -= b.mean()
    den = math.sqrt(float(a @ a) * float(b @ b))
    return float(a @ b) / den if den > 0 else float("nan")


# ---------------------------------------------------------------------- main entry
def coarse_align(
    reference,
    observed,
    *,
    max_side: int = 1024,
    min_side: int = 128,
    method: str = "auto",
    shake_px: float = 16.0,
    nodata: float | None = 0.0,
    feature_side: int = 512,
    n_features: int = 5000,
    ratio: float = 0.8,
    ransac_px: float = 2.0,
    min_inliers: int = 12,
    min_inlier_ratio: float = 0.1,
    refine: bool = True,
    motion: str = "homography",
    blur_px: float = 8.0,
    ecc_iterations: int = 100,
    polish: bool = True,
    min_r2: float = 0.3,
    min_regions: float = 0.15,
    min_agree: float = 0.6,
    min_spread: float = 0.3,
    min_ecc: float = 0.4,
    max_zoom: float = 2.0,
    max_anisotropy: float = 2.0,
    min_overlap: float = 0.2,
    gradient_side: int = 512,
    rotations: tuple[float, ...] = (-12.0, -8.0, -4.0, 0.0, 4.0, 8.0, 12.0),
    block_ncc: float = 0.25,
    min_blocks: int = 12,
) -> Alignment:
    """Estimate the global reference -> observation homography at low resolution.

    Parameters
    ----------
    reference, observed : array-like, (H, W) or (H, W, C)
        Sharp reference and blurred observation (numpy, zarr, ... any dtype; sizes and band
        counts may differ).  Each is read once, strip by strip, into an overview.
    max_side : int
        Longest side of the finest overview (both images share one integer block factor).
    min_side : int
        Longest side of the coarsest pyramid level.
    method : {"auto", "features", "gradient", "ecc"}
        ``"auto"``: gradient blocks (see Notes) seeded by the SIFT estimate when there is
        one, else by rotation hypotheses; they decide and verify, and the kernel polish is
        kept only where its blur model fits most regions.  If the blocks cannot verify, the
        SIFT estimate with ECC and the polish, then phase correlation with ECC and the
        polish.  ``"gradient"``: gradient blocks from rotation hypotheses only.
        ``"features"``: SIFT, ECC and the polish only; ``"ecc"``: phase correlation, ECC
        and the polish only.
    shake_px : float
        Largest camera-shake displacement expected during the exposure, in full-resolution
        pixels, anywhere in the image (an in-plane roll moves the corners by radius x
        angle: 1 degree is 17 px per 1000 px of radius).  It picks the working level of the
        refinement (the finest level where it spans at most 4 pixels) and the kernel size of
        the polish; a blur much larger than this fails verification.
    nodata : float or None
        Overview pixels equal to this value (whole blocks of it, after normalisation) are
        missing data, e.g. the empty corners of a reprojected scene; ECC and the polish ignore
        them.  None: every pixel holds data.
    feature_side : int
        SIFT runs on the finest level whose longest side is at most this (and on the next
        coarser level if that fails).
    n_features : int
        SIFT features per image.
    ratio : float
        Lowe's ratio-test threshold.
    ransac_px : float
        Robust-fit inlier threshold, in pixels of the level the features are matched on.
    min_inliers : int
        Fewest feature matches (and inliers) accepted.
    min_inlier_ratio : float
        Smallest accepted fraction of inliers among the matches.
    refine : bool
        Refine the feature estimate with ECC (the phase-correlation path always uses ECC).
    motion : {"homography", "affine"}
        Motion model of the ECC refinement.
    blur_px : float
        Gaussian pre-blur applied to both images before ECC, as a standard deviation in
        full-resolution pixels (at least 1 pixel of the level).
    ecc_iterations : int
        ECC iterations per level.
    polish : bool
        Apply the blur-aware kernel polish (see Notes), which also verifies the result.
    min_r2 : float
        Smallest fraction of a region's variance the local blur kernel must explain for the
        region to take part in the polish.
    min_regions : float
        Smallest fraction of the polish regions (and at least 8) that must agree with the
        final homography; fewer raises :class:`AlignmentError`.
    min_agree : float
        Smallest fraction of the regions where a kernel fits that must agree with the final
        homography (a kernel fitted where the scene changed is spread out, its centroid
        near the current estimate, so agreement must be a clear majority).
    min_spread : float
        Smallest area of the convex hull of the agreeing region centres, as a fraction of
        the region grid: a homography supported by one corner of the image only is not
        trusted elsewhere.
    min_ecc : float
        Smallest accepted ECC correlation: a feature estimate keeps its own value when ECC
        ends below it; a phase-correlation estimate raises.
    max_zoom : float
        Largest accepted scale change (either way) between the images.
    max_anisotropy : float
        Largest accepted ratio of the local stretches of ``H``.
    min_overlap : float
        Smallest accepted fraction of the observation covered by the mapped reference.
    gradient_side : int
        The gradient blocks are refined down to the finest level whose longest side is at
        most this (or the working level, if finer).
    rotations : tuple of float
        In-plane rotations (degrees) tried as hypotheses when no feature estimate seeds the
        gradient blocks.
    block_ncc : float
        Correlation peak a gradient block must reach to count as confident (the peak
        between unrelated 96 px blocks stays near 0.1).
    min_blocks : int
        Fewest confident gradient blocks that must agree with the result; at least
        ``min_agree`` of the confident blocks and ``min_spread`` of the image are also
        required.

    Returns
    -------
    Alignment
        ``H`` (reference -> observation, full-resolution pixels) plus diagnostics.

    Raises
    ------
    AlignmentError
        Textureless images; too few or inconsistent feature matches together with a failed
        fallback (ECC divergence, too low a correlation); a result the kernel polish cannot
        verify; or an implausible homography (folded, extreme zoom or stretch, too little
        overlap).  The message gives the reason on one line.
    ValueError
        Bad arguments (shapes, dtypes, options).

    See Also
    --------
    coarse_align_shakes : the same for several shake extents, sharing the overviews and
        the stages that do not depend on the extent.

    Notes
    -----
    A correlation optimum between a sharp and a motion-blurred image lies near a *mode* of
    the blur, not at its mean: with 8 px of shake the corners of ECC and feature estimates
    are typically 4-16 px off the mean camera pose.  The polish fits, in a grid of regions,
    a non-negative blur kernel between the warped reference and the observation; the
    kernel's centroid is the mean displacement there, and a homography through the moved
    region centres brings the corners to within about a pixel of the mean pose, which is
    the pose the fine pose grid is centred on.  The same fit verifies the result: enough
    regions, spread over the image, must agree.  It assumes the observation is the blurred
    one (``observation = reference * kernel``); with ``polish=False`` only the feature
    checks guard against a wrong answer.

    Examples
    --------
    >>> import numpy as np
    >>> from reblur.grid import map_points, pose_homography
    >>> from reblur.warp import warp_window
    >>> rng = np.random.default_rng(0)
    >>> import cv2
    >>> ref = cv2.GaussianBlur(rng.random((400, 400)).astype(np.float32), (0, 0), 2)
    >>> H = pose_homography(12, -7, rz=2.0, center=(199.5, 199.5))
    >>> obs, _ = warp_window(ref, H, (0, 0, 400, 400))
    >>> a = coarse_align(ref, obs[..., 0], min_side=64)
    >>> corners = np.array([[0, 0], [399, 0], [399, 399], [0, 399]])
    >>> err = np.abs(map_points(a.H, corners) - map_points(H, corners)).max()
    >>> bool(err < 1.0), a.method.split("+")[0]
    (True, 'features')
    """
    params = dict(locals())  # every keyword argument, as given
    del params["reference"], params["observed"], params["shake_px"]
    _check_args(method=method, motion=motion, min_side=min_side, max_side=max_side,
                shakes=(shake_px,))
    prep = _prepare(reference, observed, max_side=max_side, min_side=min_side, nodata=nodata)
    return _align(prep, shake_px=shake_px, **params)


def coarse_align_shakes(
    reference,
    observed,
    shakes: Sequence[float] = (8.0, 16.0, 32.0, 64.0),
    **kwargs: Any,
) -> Iterator[tuple[float, Alignment | AlignmentError]]:
    """:func:`coarse_align` for several camera-shake extents, sharing what does not depend
    on the extent.

    The overviews and the pyramid are built once, and the SIFT matches, their ECC
    refinement, the gradient blocks and the phase-correlation start are computed once for
    each set of inputs they read (the shake extent only picks the working level, which
    these stages may share); the kernel polish and the checks run for each extent.  Each
    result is exactly the one a separate ``coarse_align(reference, observed,
    shake_px=s, **kwargs)`` gives.

    Parameters
    ----------
    reference, observed : array-like, (H, W) or (H, W, C)
        As for :func:`coarse_align`; each is read once.
    shakes : sequence of float
        Shake extents (``shake_px`` of :func:`coarse_align`), tried in this order.
    **kwargs
        Any other keyword argument of :func:`coarse_align` (not ``shake_px``).

    Yields
    ------
    shake_px : float
        The extent tried.
    result : Alignment or AlignmentError
        Its alignment, or the error :func:`coarse_align` would raise.  Results are computed
        lazily: stopping the iteration skips the remaining extents.

    Raises
    ------
    ValueError
        Bad arguments, as :func:`coarse_align` (raised on the first ``next``).
    TypeError
        An unknown keyword argument, or ``shake_px``.

    Examples
    --------
    >>> import numpy as np, cv2
    >>> from reblur.grid import pose_homography
    >>> from reblur.warp import warp_window
    >>> rng = np.random.default_rng(0)
    >>> ref = cv2.GaussianBlur(rng.random((400, 400)).astype(np.float32), (0, 0), 2)
    >>> H = pose_homography(12, -7, rz=2.0, center=(199.5, 199.5))
    >>> obs, _ = warp_window(ref, H, (0, 0, 400, 400))
    >>> for s, a in coarse_align_shakes(ref, obs[..., 0], (8.0, 16.0), min_side=64):
    ...     print(s, a.method.split("+")[0])
    8.0 features
    16.0 features
    """
    defaults = dict(coarse_align.__kwdefaults__)
    del defaults["shake_px"]
    unknown = sorted(set(kwargs) - set(defaults))
    if unknown:
        raise TypeError(f"coarse_align_shakes() got unexpected keyword arguments {unknown}")
    params = {**defaults, **kwargs}
    shakes = tuple(shakes)
    _check_args(method=params["method"], motion=params["motion"],
                min_side=params["min_side"], max_side=params["max_side"], shakes=shakes)
    try:
        prep = _prepare(reference, observed, max_side=params["max_side"],
                        min_side=params["min_side"], nodata=params["nodata"])
    except AlignmentError as err:
        for sp in shakes:
            yield sp, AlignmentError(str(err))
        return
    for sp in shakes:
        try:
            yield sp, _align(prep, shake_px=sp, **params)
        except AlignmentError as err:
            yield sp, err


def _check_args(
    *, method: str, motion: str, min_side: int, max_side: int, shakes: tuple[float, ...]
) -> None:
    """Raise ValueError on bad arguments of :func:`coarse_align`."""
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
    if motion not in _MOTIONS:
        raise ValueError(f"motion must be one of {tuple(_MOTIONS)}, got {motion!r}")
    if min_side < 16 or max_side < min_side:
        raise ValueError(f"need 16 <= min_side <= max_side, got {min_side}, {max_side}")
    for shake_px in shakes:
        if not shake_px >= 0:
            raise ValueError(f"shake_px must be >= 0, got {shake_px}")


@dataclass
class _Prepared:
    """The overviews' pyramid of one pair and the memo of the stages that do not depend
    on the shake extent (see :func:`_align`)."""

    ref_shape: tuple[int, int]
    obs_shape: tuple[int, int]
    scale0: float
    levels: list[_Level]
    memo: dict = field(default_factory=dict)

    def cached(self, key: Hashable, compute: Callable[[], Any]) -> Any:
        """``compute()`` once per ``key``; an AlignmentError it raises is re-raised (a new
        one with the same message) on every later call."""
        if key not in self.memo:
            try:
                self.memo[key] = (True, compute())
            except AlignmentError as err:
                self.memo[key] = (False, str(err))
        ok, got = self.memo[key]
        if not ok:
            raise AlignmentError(got)
        return got


def _prepare(reference, observed, *, max_side: int, min_side: int,
             nodata: float | None) -> _Prepared:
    """Overviews of both images (each read once) and their pyramid.

    Raises ValueError when they are too small, AlignmentError when one is textureless."""
    ref_shape, obs_shape = _shape2(reference), _shape2(observed)
    k = _block_factor(max(ref_shape + obs_shape), max_side)
    scale0 = 1.0 / k
    ref0, obs0 = _overview_k(reference, k), _overview_k(observed, k)
    if min(ref0.shape + obs0.shape) < 16:
        raise ValueError(
            f"images {ref_shape} and {obs_shape} are too small or elongated to align at "
            f"max_side={max_side}; raise max_side"
        )
    for name, a in (("reference", ref0), ("observation", obs0)):
        tol = 1e-4 * max(1.0, float(np.max(np.abs(a))))
        if _spread(a) <= tol:
            raise AlignmentError(f"images are textureless: the {name} is (nearly) constant")
    levels = _pyramid(ref0, obs0, scale0, min_side, nodata)
    return _Prepared(ref_shape, obs_shape, scale0, levels)


def _align(
    prep: _Prepared,
    *,
    shake_px: float,
    max_side: int,
    min_side: int,
    method: str,
    nodata: float | None,
    feature_side: int,
    n_features: int,
    ratio: float,
    ransac_px: float,
    min_inliers: int,
    min_inlier_ratio: float,
    refine: bool,
    motion: str,
    blur_px: float,
    ecc_iterations: int,
    polish: bool,
    min_r2: float,
    min_regions: float,
    min_agree: float,
    min_spread: float,
    min_ecc: float,
    max_zoom: float,
    max_anisotropy: float,
    min_overlap: float,
    gradient_side: int,
    rotations: tuple[float, ...],
    block_ncc: float,
    min_blocks: int,
) -> Alignment:
    """:func:`coarse_align` with the shake extent ``shake_px`` on a prepared pair.

    The stages that read the shake extent only through the working level are memoised in
    ``prep`` under the level indices and initial homography they read, and under every
    other argument (so a memo entry is reused only where a fresh computation would give
    the same result).  Results handed out are copies: a caller that edits an
    :attr:`Alignment.H` in place cannot reach the memo.
    """
    # every argument but the shake extent: part of each memo key
    fixed = repr(sorted((k, v) for k, v in locals().items() if k not in ("prep", "shake_px")))
    ref_shape, obs_shape, scale0, levels = prep.ref_shape, prep.obs_shape, prep.scale0, prep.levels
    top = len(levels) - 1
    checks = dict(max_zoom=max_zoom, max_anisotropy=max_anisotropy, min_overlap=min_overlap)
    mot = _MOTIONS[motion]

    def first_at_most(side: int) -> int:
        return next((i for i, lv in enumerate(levels) if lv.side <= side), top)

    def shake_at(i: int) -> int:
        return int(math.ceil(shake_px * levels[i].scale))

    # working level of ECC and the polish: the finest where the shake spans <= 4 pixels,
    # but large enough for a grid of polish regions
    work = next((i for i in range(len(levels)) if shake_at(i) <= 4), top)
    while work > 0 and max(levels[work].obs.shape) < 5 * _REGION_PX:
        work -= 1

    ecc_kw = dict(motion=mot, blur_px=blur_px, sigma_min=1.0, iterations=ecc_iterations)
    lv = levels[work]
    # polish regions hold >= 6 pixels per kernel tap
    region_px = max(_REGION_PX, math.sqrt(6.0) * (2 * max(shake_at(work) + 2, 2) + 1))
    n_regions = tuple(int(np.clip(round(n / region_px), 3, 8)) for n in lv.obs.shape)
    n_total = n_regions[0] * n_regions[1]

    def polish_and_verify(H: np.ndarray, stages: list[str]) -> tuple[np.ndarray, int, int]:
        """Kernel polish of ``H``; raise AlignmentError unless enough regions agree.

        Returns the polished ``H``, the regions that agree and the regions that fit."""
        n_agree, n_fit, spread, accepted = 0, 0, 0.0, None
        for R in (shake_at(work) + 2, shake_at(work) + 1):
            R = max(R, 2)
            Hp, n_agree, n_fit, spread = _kernel_polish(
                lv, H, R, n_regions=n_regions, min_r2=min_r2, max_pixels=8192,
                max_sd=max(1.0, shake_px * lv.scale),
            )
            if n_agree < 8:
                break
            jump = _max_corner_shift(Hp, H, ref_shape) * lv.scale
            if jump > 2 * R:
                log.debug("kernel polish rejected: corners moved by %.1f level px", jump)
                n_agree = 0
                break
            try:
                _check_plausible(Hp, ref_shape, obs_shape, **checks)
            except AlignmentError as err:
                log.debug("kernel polish rejected: %s", err)
                n_agree = 0
                break
            H, accepted = Hp, (n_agree, n_fit, spread)
            if stages[-1] != "kernel":
                stages.append("kernel")
        if accepted is not None:
            n_agree, n_fit, spread = accepted
        log.debug("polish: %d regions agree, %d fit, spread %.2f", n_agree, n_fit, spread)
        need = max(8, math.ceil(min_regions * n_total), math.ceil(min_agree * n_fit))
        if n_agree >= need and spread < min_spread:
            raise AlignmentError(
                f"alignment could not be verified: the {n_agree} regions that agree with it "
                f"span {100 * spread:.0f} % of the image (< {100 * min_spread:.0f} %)"
            )
        if n_agree < need:
            raise AlignmentError(
                f"alignment could not be verified: {n_agree} regions agree with it, of "
                f"{n_fit} where the blur model fits and {n_total} in all (need {need}): images "
                f"unrelated, changed too much or blurred by more than shake_px={shake_px:g}"
            )
        return H, n_agree, n_fit

    errors: list[str] = []

    def matched_features(i: int) -> _Features:
        """SIFT estimate on level ``i``; AlignmentError when it fails or is implausible."""
        f = _match_features(
            levels[i], n_features=n_features, ratio=ratio, ransac_px=ransac_px,
            min_inliers=min_inliers, min_inlier_ratio=min_inlier_ratio,
        )
        _check_plausible(f.H, ref_shape, obs_shape, **checks)
        return f

    def feature_ecc(f: _Features) -> tuple[np.ndarray, float, float]:
        """ECC refinement of ``f.H`` on the working level, its residual to the matches
        before and after; AlignmentError when it fails, is implausible or correlates too
        little."""
        He, rho, _ = _ecc_refine(
            levels, f.H, min(work + 1, top), work, ref_shape, max_jump=0.05,
            tolerant=True, **ecc_kw,
        )
        _check_plausible(He, ref_shape, obs_shape, **checks)
        if rho < min_ecc:
            raise AlignmentError(f"ECC correlation {rho:.2f} < {min_ecc:g}")
        res_f = float(np.median(np.hypot(*(map_points(f.H, f.src) - f.dst).T)))
        res_e = float(np.median(np.hypot(*(map_points(He, f.src) - f.dst).T)))
        return He, res_f, res_e

    def features_estimate(i: int) -> tuple[_Features, np.ndarray, list[str]]:
        """SIFT estimate on level ``i``, refined by ECC when that stays with the matches;
        raises its AlignmentError.  Both are memoised: they read the shake extent only
        through the working level."""
        f = prep.cached(("features", i, fixed), functools.partial(matched_features, i))
        H, stages = f.H.copy(), ["features"]
        if refine:
            try:
                He, res_f, res_e = prep.cached(
                    ("features-ecc", i, work, fixed), functools.partial(feature_ecc, f)
                )
                # ECC must not leave the feature matches: smoothing can wash out fine
                # texture and let it drift
                log.debug("feature residual %.2f px, after ECC %.2f px", res_f, res_e)
                if res_e > max(2.0 * res_f, 0.25 * shake_px, 1.0 / levels[i].scale):
                    raise AlignmentError(
                        f"ECC moved away from the feature matches ({res_e:.1f} px vs "
                        f"{res_f:.1f} px)"
                    )
                H = He.copy()
                stages.append("ecc")
            except AlignmentError as err:
                log.debug("ECC refinement rejected (%s); keeping the feature estimate", err)
        return f, H, stages

    feature_levels = list(dict.fromkeys((first_at_most(feature_side),
                                         min(first_at_most(feature_side) + 1, top))))
    feats: _Features | None = None
    n_agree, n_blocks = 0, 0
    if method in ("auto", "gradient"):
        # features (when they hold) only seed the gradient blocks, which decide
        init: tuple[_Features, np.ndarray, list[str]] | None = None
        if method == "auto":
            for i in feature_levels:
                try:
                    init = features_estimate(i)
                    break
                except AlignmentError as err:
                    log.debug("feature alignment failed at level %d: %s", i, err)
                    errors.append(str(err))
        fine = min(first_at_most(gradient_side), work)
        grad_kw = dict(
            rotations=rotations, min_ncc=block_ncc, min_blocks=min_blocks,
            min_agree=min_agree, min_spread=min_spread,
            plausible=lambda M: _check_plausible(M, ref_shape, obs_shape, **checks),
        )
        blocks, stages = None, ["gradient"]
        for seed in ([init, None] if init is not None else [None]):
            H0 = None if seed is None else seed[1]
            try:
                # memoised: reads the shake extent only through ``fine`` and the seed
                blocks = prep.cached(
                    ("gradient", fine, None if H0 is None else H0.tobytes(), fixed),
                    functools.partial(_gradient_align, levels, H0, ref_shape, fine, **grad_kw),
                )
                blocks = replace(blocks, H=blocks.H.copy())
            except AlignmentError as err:
                log.debug("gradient alignment failed (seed %s): %s", seed is not None, err)
                errors.append(str(err))
                continue
            if seed is not None:
                feats, stages = seed[0], seed[2] + ["gradient"]
            break
        if blocks is not None:
            H, n_blocks = blocks.H, blocks.n_agree
            if polish:
                # the blur-aware polish reaches the mean camera pose on a same-scene pair,
                # where a correlation optimum sits near a mode of the blur; between captures
                # years apart its blur model does not hold and it can wander: keep it only
                # when it verifies and stays within the blur's reach of the blocks' estimate
                try:
                    Hp, n_p, n_fit = polish_and_verify(H, ["gradient"])
                    reach = max(2.0 / levels[fine].scale, shake_px)
                    moved = _max_corner_shift(Hp, H, ref_shape)
                    if n_fit < 0.5 * n_total:
                        log.debug("kernel polish not kept: the blur model fits in %d of %d "
                                  "regions only", n_fit, n_total)
                    elif moved > reach:
                        log.debug("kernel polish moved %.1f px (> %.1f): not kept", moved, reach)
                    else:
                        H, n_agree = Hp, n_p
                        stages.append("kernel")
                except AlignmentError as err:
                    log.debug("kernel polish not kept: %s", err)
        elif method == "gradient":
            raise AlignmentError(errors[-1])

    if method == "features" or (method == "auto" and n_blocks == 0):
        for i in feature_levels:
            try:
                f, H, stages = features_estimate(i)
            except AlignmentError as err:
                if method == "features":
                    errors.append(str(err))
                continue
            n_agree = 0
            if polish:
                try:
                    H, n_agree, _ = polish_and_verify(H, stages)
                except AlignmentError as err:
                    log.debug("feature estimate at level %d rejected: %s", i, err)
                    errors.append(str(err))
                    continue
            feats = f
            break

    if n_blocks == 0 and feats is None and method in ("auto", "ecc"):
        # fallback: phase correlation for the translation, then ECC coarse to fine
        def phase_ecc() -> np.ndarray:
            H = _phase_init(levels[top])
            _check_plausible(H, ref_shape, obs_shape, **checks)
            H, _, _ = _ecc_refine(levels, H, top, work, ref_shape, max_jump=0.25, **ecc_kw)
            _check_plausible(H, ref_shape, obs_shape, **checks)
            return H

        try:
            # memoised: reads the shake extent only through the working level
            H = prep.cached(("phase-ecc", work, fixed), phase_ecc).copy()
            stages, n_agree = ["phase", "ecc"], 0
            if polish:
                H, n_agree, _ = polish_and_verify(H, stages)
            rho = _correlation(lv, H, max(1.0, blur_px * lv.scale))
            if not rho >= min_ecc:
                raise AlignmentError(
                    f"correlation {rho:.2f} < {min_ecc:g} after alignment: images look unrelated"
                )
        except AlignmentError as err:
            raise AlignmentError(
                "; fallback: ".join(dict.fromkeys(errors + [str(err)]))
            ) from None
    elif n_blocks == 0 and feats is None:
        raise AlignmentError("; fallback: ".join(dict.fromkeys(errors)))

    overlap = _check_plausible(H, ref_shape, obs_shape, **checks)
    rho = _correlation(lv, H, max(1.0, blur_px * lv.scale))
    residual = None
    if feats is not None:
        residual = float(np.median(np.hypot(*(map_points(H, feats.src) - feats.dst).T)))
    return Alignment(
        H=H, method="+".join(stages),
        n_matches=feats.n_matches if feats else 0, n_inliers=feats.n_inliers if feats else 0,
        scale=scale0, residual_px=residual, ecc=rho if np.isfinite(rho) else None,
        overlap=overlap, n_regions=n_agree, n_blocks=n_blocks,
    )
