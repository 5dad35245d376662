"""Low-resolution overviews of (possibly huge, on-disk) images and the alignment pyramid.

Both images are read once, in horizontal strips, and block-averaged to a grey overview
(:func:`overview`, :func:`block_means`; an :class:`OverviewCache` keeps them for the
other low-resolution views of a pipeline); :func:`pyramid` halves the overviews of a pair
into :class:`Level` s.

An overview made with the integer block factor ``k`` (``scale = 1 / k``) has pixel ``x_s``
centred on the full-resolution position ``x = k * x_s + (k - 1) / 2`` (i.e.
``(x_s + 0.5) / scale - 0.5``); :func:`to_level` and :func:`to_full` move a homography
between the two frames.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

#: Read at most this many bytes (as float32) per strip when building overviews.
_STRIP_BYTES = 64 * 2**20


def image_shape(image) -> tuple[int, int]:
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


def block_factor(max_len: int, max_side: int) -> int:
    if max_side < 1:
        raise ValueError(f"max_side must be positive, got {max_side}")
    return max(1, math.ceil(max_len / max_side))


def overview_k(image, k: int) -> np.ndarray:
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
    return read_block_means(image, int(k))


def read_block_means(image, k: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`block_means` read from the image, in horizontal strips.

    The next strip is read (decoded) in the background while one is averaged.  Integer
    images are summed exactly in integers; floats are averaged by OpenCV's area resize.
    """
    H, W = image_shape(image)
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
                self._memo[k] = read_block_means(self.image, k)
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
    k = block_factor(max(image_shape(image)), max_side)
    return overview_k(image, k), 1.0 / k


def overview_matrix(scale: float) -> np.ndarray:
    """3x3 matrix mapping overview pixel coordinates to full-resolution coordinates.

    ``x = (x_s + 0.5) / scale - 0.5``; a homography ``Hs`` between two overviews of the same
    scale is ``A @ Hs @ inv(A)`` at full resolution.
    """
    k = 1.0 / float(scale)
    return np.array([[k, 0.0, (k - 1.0) / 2.0], [0.0, k, (k - 1.0) / 2.0], [0.0, 0.0, 1.0]])


def to_level(H: np.ndarray, scale: float) -> np.ndarray:
    A = overview_matrix(scale)
    M = np.linalg.inv(A) @ H @ A
    return M / M[2, 2]


def to_full(Hs: np.ndarray, scale: float) -> np.ndarray:
    A = overview_matrix(scale)
    M = A @ Hs @ np.linalg.inv(A)
    return M / M[2, 2]


def _halve(a: np.ndarray) -> np.ndarray:
    h, w = a.shape[0] // 2, a.shape[1] // 2
    return cv2.resize(a[: 2 * h, : 2 * w], (w, h), interpolation=cv2.INTER_AREA)


@dataclass
class Level:
    ref: np.ndarray
    obs: np.ndarray
    scale: float
    ref_mask: np.ndarray  # uint8, 1 where the overview pixel holds data
    obs_mask: np.ndarray
    #: ``ref_memo(key, compute)``: a product of the reference level alone (its SIFT
    #: features), kept for the next observation (:class:`reblur.refcache.ReferenceCache`);
    #: None: computed every time
    ref_memo: Callable[[Hashable, Callable[[], Any]], Any] | None = None

    @property
    def side(self) -> int:
        return max(self.ref.shape + self.obs.shape)

    def warped_reference(self, Hs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The reference warped by the level homography ``Hs`` into the observation frame
        (bilinear, 0 outside), and where its whole footprint holds reference data."""
        h, w = self.obs.shape
        ref = cv2.warpPerspective(self.ref, Hs, (w, h), flags=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_CONSTANT)
        cover = cv2.warpPerspective(self.ref_mask.astype(np.float32), Hs, (w, h),
                                    flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        return ref, cover > 0.999


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


def pyramid(
    ref0: np.ndarray, obs0: np.ndarray, scale0: float, min_side: int, nodata: float | None,
    ref_memo: Callable[[int, Callable[[], Any]], Any] | None = None,
) -> list[Level]:
    """Levels from fine (index 0) to coarse; each halves the previous one.

    ``ref_memo(i, compute)`` (optional) gives the reference half of level ``i`` (its
    overview and data mask) from a cache of the reference's products instead of
    ``compute()`` (:class:`reblur.refcache.ReferenceCache`)."""
    def ref_level(i: int, make: Callable[[], tuple[np.ndarray, np.ndarray]]):
        return make() if ref_memo is None else ref_memo(i, make)

    ref, mask = ref_level(0, lambda: (ref0, _data_mask(ref0, nodata)))
    levels = [Level(ref, obs0, scale0, mask, _data_mask(obs0, nodata))]
    while True:
        last = levels[-1]
        if last.side // 2 < min_side or min(last.ref.shape + last.obs.shape) // 2 < 16:
            break
        ref, mask = ref_level(len(levels), lambda last=last: (_halve(last.ref),
                                                              _halve_mask(last.ref_mask)))
        levels.append(Level(ref, _halve(last.obs), last.scale / 2.0, mask,
                            _halve_mask(last.obs_mask)))
    return levels

