"""Low-resolution overviews of (possibly huge, on-disk) images and the alignment pyramid.

Both images are read once, in bands of whole chunk rows (in threads), and block-averaged
to a grey overview (:func:`overview`, :func:`block_means`; an :class:`OverviewCache`
keeps them for the other low-resolution views of a pipeline).  When the file carries
its own reduced-resolution levels (:mod:`reblur.levels`), an :class:`OverviewCache`
reads the overview from one of them instead (:func:`level_block_means`) and the
full-resolution image is not read.  :func:`pyramid` halves the overviews of a pair into
:class:`Level` s.

An overview made with the integer block factor ``k`` (``scale = 1 / k``) has pixel ``x_s``
centred on the full-resolution position ``x = k * x_s + (k - 1) / 2`` (i.e.
``(x_s + 0.5) / scale - 0.5``); :func:`to_level` and :func:`to_full` move a homography
between the two frames.
"""

from __future__ import annotations

import itertools
import logging
import math
import os
from collections import deque
from collections.abc import Callable, Hashable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import scipy.sparse as sp

from .._bands import mean_bands
from .._memory import opencv_single

log = logging.getLogger(__name__)

#: Read about this many bytes (as float32) per band when building overviews (more when
#: one row of the image's chunks is larger).  Small enough for a band's temporaries (its
#: sums in integers, then float64) to stay few and reused: with 32 MB, the block means of a
#: 1 MP RGB image at full resolution (one band) took 84-356 ms on first call against 25-38
#: ms (fresh memory faulting in, ``python -m benchmarks.first_touch``; measured with
#: ``python -c "import time, cv2, reblur.align.overviews as o; a = cv2.imread(PNG);
#: o._STRIP_BYTES = MB << 20; t = time.perf_counter(); o.read_block_means(a, 1);
#: print(time.perf_counter() - t)"`` on LEVIR test_12, a fresh process per figure).
_STRIP_BYTES = 4 * 2**20

#: Bands of an image read and averaged at once when building overviews.
_THREADS = max(1, min(4, os.cpu_count() or 1))

#: Where an overview came from (:meth:`OverviewCache.overview_source`).
FROM_LEVELS = "file levels"
FROM_FULL = "block means of the full image"


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
    """:func:`block_means` read from the image, in horizontal bands.

    Bands are whole rows of the image's chunks (tiles or strips) where it has them, so
    each chunk is decoded once, and at most :data:`_STRIP_BYTES` (as float32) where it
    does not; up to :data:`_THREADS` bands are read (decoded) and averaged at once -- the
    TIFF and zarr decoders and numpy's sums release the GIL -- and at most one more is
    held.  Integer images are summed exactly in integers; floats are averaged by
    OpenCV's area resize.  The result does not depend on the bands: a block split
    between two bands is averaged from its rows of both.
    """
    H, W = image_shape(image)
    C = int(image.shape[2]) if len(image.shape) == 3 else 1
    h, w = H // k, W // k
    if h < 1 or w < 1:
        raise ValueError(f"image {H}x{W} is smaller than one {k}x{k} overview block")
    norm = _dtype_norm(image.dtype)
    reader = getattr(image, "chunk_reader", None)
    if reader is not None and _exact(image.dtype) and h * w * C * 8 <= _SUMS_BYTES:
        return _chunk_block_means(reader, (H, W, C), k, norm)
    bands = np.empty((h, w, C), np.float32)

    def work(y0: int, y1: int, a: np.ndarray):
        # rows [y0, head) end a block begun in the band before, [tail, y1) begin one
        # ending in the band after; the blocks between are averaged here
        head = min(-(-y0 // k) * k, y1)
        tail = max(y1 // k * k, head)
        means = _strip_means(a[head - y0 : tail - y0], k, norm) if tail > head else None
        return head // k, means, a[: head - y0].copy(), a[tail - y0 :].copy()

    edges = _band_edges(0, h * k, _band_rows(image, k, w * k * C * 4), _chunk_rows(image))
    pending = None
    for r0, means, head, tail in _in_bands(image, edges, slice(0, w * k), C, work):
        if head.shape[0]:
            joined = np.concatenate([pending, head]) if pending is not None else head
            bands[r0 - 1] = _strip_means(joined, k, norm)[0]
        if means is not None:
            bands[r0 : r0 + means.shape[0]] = means
        pending = tail if tail.shape[0] else None
    grey = bands[:, :, 0] if C == 1 else mean_bands(bands)
    return grey, bands


#: Largest accumulator (int64 block sums) :func:`read_block_means` builds from a file's
#: decoded chunks; a finer overview of a larger image is read in bands.
_SUMS_BYTES = 256 * 2**20


def _exact(dtype) -> bool:
    """Whether block sums of ``dtype`` are exact in int64 (:func:`_strip_means`' integer
    path: booleans and integers of at most 4 bytes)."""
    dt = np.dtype(dtype)
    return dt.kind == "b" or (dt.kind in "ui" and dt.itemsize <= 4)


def _sum_dtypes(dtype, k: int) -> tuple[type, type]:
    """Accumulators of exact ``k x k`` block sums of an :func:`_exact` ``dtype``: of ``k``
    values down a column, and of the ``k x k`` block (the narrowest that hold them)."""
    dt = np.dtype(dtype)
    if dt.kind == "i":
        return np.int64, np.int64
    top = 1 if dt.kind == "b" else int(np.iinfo(dt).max)
    acc = np.uint32 if k * k * top < 2**32 else np.uint64
    return (np.uint16 if k * top < 2**16 else acc), acc


def _chunk_block_means(reader, shape: tuple[int, int, int], k: int, norm: float
                       ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`read_block_means` of an integer image from its decoded chunks (``reader``, an
    image's ``chunk_reader``: ``func(y0, x0, chunk)`` in the decoding threads, in any
    order), without copying them into windows.  Each chunk's pixels are summed by block
    (its blocks cut at its edges) into exact int64 sums, so the means are those of the
    band-wise read, bit for bit.

    A block cut by a chunk's edge gets its parts from each chunk it spans."""
    H, W, C = shape
    h, w = H // k, W // k
    acc = np.zeros((h, w, C), np.int64)

    def sums(y0: int, x0: int, a: np.ndarray):  # in the decoding threads
        a = a.reshape(a.shape[0], a.shape[1], C)
        y1, x1 = min(y0 + a.shape[0], h * k), min(x0 + a.shape[1], w * k)
        if y1 <= y0 or x1 <= x0:
            return None  # the dropped partial blocks at the image's edge
        return y0 // k, x0 // k, _block_sums(a[: y1 - y0, : x1 - x0], y0, x0, k)

    for got in reader(_THREADS, sums):
        if got is not None:
            r, c, t = got
            acc[r : r + t.shape[0], c : c + t.shape[1]] += t
    out = acc.astype(np.float64)
    out *= norm / (k * k)
    bands = out.astype(np.float32)
    grey = bands[:, :, 0] if C == 1 else mean_bands(bands)
    return grey, bands


def _block_sums(a: np.ndarray, y0: int, x0: int, k: int) -> np.ndarray:
    """Exact sums, as int64, of the ``(h, w, C)`` integer chunk ``a`` (at ``y0, x0`` in the
    image) over the ``k x k`` blocks it touches, those cut at its edges included (their
    parts here); the vertical sums in :func:`_strip_means`' narrow accumulators."""
    vert, _ = _sum_dtypes(a.dtype, k)
    return _axis_sums(_axis_sums(a, 0, y0, k, vert), 1, x0, k, np.int64)


def _axis_sums(a: np.ndarray, axis: int, p0: int, k: int, dtype) -> np.ndarray:
    """Sums of ``a`` along ``axis`` over the ``k``-blocks its entries (from ``p0`` in the
    image) fall in: a partial block at either end summed alone, the whole ones between
    by one reshape."""
    n = a.shape[axis]
    head = min(-p0 % k, n)
    end = head + (n - head) // k * k

    def part(i: int, j: int) -> np.ndarray:
        return a[(slice(None),) * axis + (slice(i, j),)]

    parts = []
    if head:
        parts.append(np.add.reduce(part(0, head), axis=axis, keepdims=True, dtype=dtype))
    if end > head:
        m = part(head, end)
        m = m.reshape(m.shape[:axis] + ((end - head) // k, k) + m.shape[axis + 1:])
        parts.append(np.add.reduce(m, axis=axis + 1, dtype=dtype))
    if end < n:
        parts.append(np.add.reduce(part(end, n), axis=axis, keepdims=True, dtype=dtype))
    return parts[0] if len(parts) == 1 else np.concatenate(parts, axis=axis)


def _chunk_rows(image) -> int | None:
    """Rows of the image's chunks (tiles or strips), None when it has none."""
    ch = getattr(image, "chunks", None)
    try:
        return max(1, int(ch[0])) if ch else None
    except (TypeError, ValueError, IndexError):
        return None


def _band_rows(image, k: int, row_bytes: int) -> int:
    """Rows per band: about :data:`_STRIP_BYTES` of ``row_bytes`` rows, whole chunk rows
    and at least ``k`` rows where the image has chunks, else whole blocks of ``k``."""
    rows = max(1, _STRIP_BYTES // max(1, row_bytes))
    ch = _chunk_rows(image)
    if ch is None:
        return max(1, rows // k) * k
    return ch * -(-max(rows - rows % ch, ch, k) // ch)


def _band_edges(y0: int, y1: int, rows: int, chunk: int | None) -> list[int]:
    """Band edges from ``y0`` to ``y1``: multiples of ``rows`` (which are chunk edges
    when the image has chunks) between them."""
    start = y0 - y0 % rows if chunk else y0
    inner = range(start + rows, y1, rows)
    return [y0, *[e for e in inner if e > y0], y1]


def _in_bands(image, edges: list[int], cols: slice, C: int,
              work: Callable[[int, int, np.ndarray], Any]) -> Iterator[Any]:
    """``work(y0, y1, image[y0:y1, cols])`` (as ``(rows, cols, C)``) for the bands between
    consecutive ``edges``, in order; up to :data:`_THREADS` at once, at most one more
    band read ahead."""

    def task(y0: int, y1: int):
        a = np.asarray(image[y0:y1, cols])
        return work(y0, y1, a.reshape(a.shape[0], a.shape[1], C))

    spans = list(itertools.pairwise(edges))
    if _THREADS == 1 or len(spans) == 1:
        for y0, y1 in spans:
            yield task(y0, y1)
        return
    with ThreadPoolExecutor(_THREADS) as pool:
        ahead: deque = deque()
        for y0, y1 in spans:
            ahead.append(pool.submit(task, y0, y1))
            if len(ahead) > _THREADS:
                yield ahead.popleft().result()
        while ahead:
            yield ahead.popleft().result()


def _strip_means(a: np.ndarray, k: int, norm: float) -> np.ndarray:
    """``(r k, w k, C)`` -> ``(r, w, C)`` float32 means of ``k x k`` blocks, times ``norm``."""
    rk, wk, C = a.shape
    r, w = rk // k, wk // k
    if _exact(a.dtype):
        vert, acc = _sum_dtypes(a.dtype, k)
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

    When the image's file carries reduced-resolution levels (a ``file_levels``
    attribute, :mod:`reblur.levels`: pyramidal TIFF, COG overviews, zarr multiscales), a
    new factor ``k`` is read from the coarsest level at most ``k`` times smaller
    (:func:`level_block_means`) and the full-resolution image is not read at all; only
    without a usable level (none fine enough, or one that fails to decode: logged) is it
    read.  :meth:`overview_source` says which.

    Parameters
    ----------
    image : array-like, (H, W) or (H, W, C)
        numpy, zarr, tifffile store, ...
    file_levels : bool
        Use the file's levels when it has them (False: always read the image).

    Attributes
    ----------
    reads : int
        Passes over the full-resolution image so far.
    level_reads : int
        Overviews read from the file's levels so far.
    """

    def __init__(self, image, *, file_levels: bool = True):
        self.image = image
        self.shape = tuple(int(s) for s in image.shape)
        self.dtype = np.dtype(image.dtype)
        self.reads = 0
        self.level_reads = 0
        self.levels = getattr(image, "file_levels", None) if file_levels else None
        self._memo: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._sources: dict[int, dict[str, Any]] = {}
        self._ignored: list[str] | None = None
        self._failed: str | None = None

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
        """:func:`block_means` of the image: from the file's levels when they serve,
        else read at most once per unrelated factor."""
        k = int(k)
        if k not in self._memo:
            divisors = [k0 for k0 in self._memo if k % k0 == 0]
            if divisors:
                k0 = max(divisors)
                self._memo[k] = _coarser(self._memo[k0][1], k // k0, self.shape, k)
                self._sources[k] = self._sources[k0]
            else:
                got = self._from_levels(k)
                if got is None:
                    self._memo[k] = read_block_means(self.image, k)
                    self.reads += 1
                    self._sources[k] = self._full_source()
                else:
                    self._memo[k], self._sources[k] = got
                    self.level_reads += 1
        return self._memo[k]

    def overview_source(self, k: int) -> dict[str, Any]:
        """Where the overview of factor ``k`` came from: ``{"source": "file levels",
        "file": ..., "level": {...}}`` or ``{"source": "block means of the full
        image"}``, with the reasons the file's levels were ignored or failed, if any."""
        k = int(k)
        if k not in self._sources:
            self.block_means(k)
        return dict(self._sources[k])

    def _full_source(self) -> dict[str, Any]:
        out: dict[str, Any] = {"source": FROM_FULL}
        if self._ignored:
            out["ignored_levels"] = list(self._ignored)
        if self._failed:
            out["levels_failed"] = self._failed
        return out

    def _from_levels(self, k: int) -> tuple[tuple[np.ndarray, np.ndarray], dict] | None:
        """The overview of factor ``k`` from the coarsest file level that serves, and its
        source; None without one (or when reading it failed: logged)."""
        if self.levels is None or k < 2:
            return None
        try:
            with self.levels.open() as (levels, ignored):
                if self._ignored is None:
                    self._ignored = ignored
                    for why in ignored:
                        log.warning("%s: level ignored for the overviews: %s",
                                    self.levels.key, why)
                lv = choose_level(levels, k)
                if lv is None:
                    return None
                got = level_block_means(lv, k, self.shape[:2])
        except MemoryError:
            raise
        except Exception as exc:  # noqa: BLE001 - the full image is the fallback
            self._failed = f"{type(exc).__name__}: {exc}".splitlines()[0]
            log.warning("%s: the file's levels could not be read (%s); reading the full "
                        "image for its overviews", self.levels.key, self._failed)
            self.levels = None
            return None
        if got is None:
            return None
        src: dict[str, Any] = {"source": FROM_LEVELS, "file": self.levels.source,
                               "level": lv.describe()}
        if self._ignored:
            src["ignored_levels"] = list(self._ignored)
        return got, src


def _coarser(bands0: np.ndarray, f: int, shape: tuple[int, ...], k: int
             ) -> tuple[np.ndarray, np.ndarray]:
    """Block means of factor ``k`` from those of factor ``k / f`` (``bands0``) of an
    image of ``shape``."""
    h, w = shape[0] // k, shape[1] // k
    if h < 1 or w < 1:
        raise ValueError(f"image {shape[0]}x{shape[1]} is smaller than one {k}x{k} "
                         "overview block")
    C = bands0.shape[2]
    bands = np.empty((h, w, C), np.float32)
    for c in range(C):
        bands[:, :, c] = cv2.resize(np.ascontiguousarray(bands0[: h * f, : w * f, c]), (w, h),
                                    interpolation=cv2.INTER_AREA)
    grey = bands[:, :, 0] if C == 1 else mean_bands(bands)
    return grey, bands


def overview_source(image, k: int) -> dict[str, Any]:
    """Where :func:`block_means` of ``image`` for the factor ``k`` comes from
    (:meth:`OverviewCache.overview_source`; any other image is read whole)."""
    fn = getattr(image, "overview_source", None)
    return fn(int(k)) if fn is not None else {"source": FROM_FULL}


# ---------------------------------------------------------------------------- file levels
def choose_level(levels: list, k: int):
    """The coarsest of ``levels`` (:class:`reblur.levels.FileLevel`) that gives the block
    means of factor ``k`` well, or None.

    On each axis the level's factor ``f`` must divide ``k`` exactly (the blocks are then
    unions of level pixels), or be at most ``k / 2`` (to within one level pixel across
    the image).  Otherwise a block's edges cut level pixels, which moves the centroid of
    its weights by up to 0.085 of a level pixel, alternately either way (at most 0.05
    for ``k / f >= 2``, falling as ``k / f`` grows), and a ceil- or floor-sized level
    (``f`` near but not at an integer) blurs the overview by a fraction of a level pixel
    that varies across it.  Measured on a 1024 px scene aligned at ``k = 6``: corners of
    the homography 0.16 px from the full read's with the 4x level, 0.003 px with the 2x
    level; on a 1001 x 1023 px one at ``k = 4`` (ceil-sized area levels): 0.20 px with
    the ``f = 3.99`` level, 0.10 px with the ``f = 2.00`` one.
    """
    def fits(f: float, n: int) -> bool:
        exact = f == round(f) and k % round(f) == 0
        return exact or k / f >= 2.0 * (1.0 - 1.0 / max(1, n))

    ok = [lv for lv in levels if all(fits(float(f), min(lv.shape)) for f in lv.factor)]
    return max(ok, key=lambda lv: min(lv.factor)) if ok else None


def level_block_means(level, k: int, shape: tuple[int, int]
                      ) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`block_means` over ``k x k`` blocks of an image of ``shape``, from one of its
    reduced-resolution levels (:class:`reblur.levels.FileLevel`).

    Each block's value is the mean, over the block, of the level's piecewise-constant
    picture of the image (level pixel ``i`` standing for the base interval
    ``[origin + i f, origin + (i + 1) f)``): exact area weights, as ``cv2.INTER_AREA``
    between the two grids.  When ``k`` is a multiple of an integer factor it is the
    level's own block mean, and of a level made by block means, the image's.  Otherwise
    a block's weights spill over the level pixels its edges cut, which smooths by up to
    one level pixel and moves its centroid by up to 0.085 of one (periodically, zero on
    average; :func:`choose_level` keeps that small).  Only the level's rows and columns
    under the blocks are read, in bands of whole chunk rows (threads, as
    :func:`read_block_means`); integers are divided by their dtype's maximum, NaN and
    Inf read as 0.

    Returns
    -------
    grey, bands : float32 ndarrays, or None
        As :func:`block_means`; None when the level does not cover half of some block.
    """
    H, W = int(shape[0]), int(shape[1])
    h, w = H // k, W // k
    if h < 1 or w < 1:
        raise ValueError(f"image {H}x{W} is smaller than one {k}x{k} overview block")
    arr = level.array
    hl, wl = int(arr.shape[0]), int(arr.shape[1])
    C = int(arr.shape[2]) if len(arr.shape) == 3 else 1
    Wy = _area_weights(h, k, hl, float(level.factor[0]), float(level.origin[0]))
    Wx = _area_weights(w, k, wl, float(level.factor[1]), float(level.origin[1]))
    if Wy is None or Wx is None:
        return None
    r0, r1 = int(Wy.indices.min()), int(Wy.indices.max()) + 1
    c0, c1 = int(Wx.indices.min()), int(Wx.indices.max()) + 1
    Wx = Wx[:, c0:c1].tocsr()
    Wy = Wy.tocsc()
    is_float = np.dtype(arr.dtype).kind == "f"
    down = np.zeros((h, (c1 - c0) * C), np.float32)  # the rows' weights applied

    def work(y0: int, y1: int, a: np.ndarray):
        part = Wy[:, y0:y1]
        if not part.nnz:
            return 0, 0, None
        j0, j1 = int(part.indices.min()), int(part.indices.max()) + 1
        f = a.astype(np.float32).reshape(y1 - y0, -1)
        if is_float:
            f = np.nan_to_num(f, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
        return j0, j1, part[j0:j1].tocsr() @ f

    edges = _band_edges(r0, r1, _band_rows(arr, 1, (c1 - c0) * C * 4), _chunk_rows(arr))
    for j0, j1, t in _in_bands(arr, edges, slice(c0, c1), C, work):
        if t is not None:
            down[j0:j1] += t
    down = down.reshape(h, c1 - c0, C)
    bands = np.empty((h, w, C), np.float32)
    norm = _dtype_norm(arr.dtype)
    for c in range(C):  # then the columns' weights
        bands[:, :, c] = (Wx @ np.ascontiguousarray(down[:, :, c].T)).T * norm
    grey = bands[:, :, 0] if C == 1 else mean_bands(bands)
    return grey, bands


def _area_weights(n: int, k: int, n_in: int, f: float, origin: float):
    """``(n, n_in)`` sparse weights: output pixel ``j`` is the mean over the image
    interval ``[j k, (j + 1) k)`` of a level whose pixel ``i`` covers
    ``[origin + i f, origin + (i + 1) f)``; None when the level covers less than half of
    some output pixel's interval (a pixel it covers in part is the mean of that part)."""
    j = np.arange(n, dtype=np.float64)
    a, b = j * k, (j + 1) * k
    m = int(math.ceil(k / f)) + 2
    i = np.floor((a - origin) / f).astype(np.int64)[:, None] + np.arange(m)[None, :]
    lo = np.maximum(a[:, None], origin + i * f)
    hi = np.minimum(b[:, None], origin + (i + 1) * f)
    wgt = np.clip(hi - lo, 0.0, None)
    wgt[(i < 0) | (i >= n_in)] = 0.0
    tot = wgt.sum(axis=1)
    if not (tot >= 0.5 * k).all():
        return None
    wgt /= tot[:, None]
    keep = wgt > 0
    rows = np.broadcast_to(np.arange(n)[:, None], wgt.shape)[keep]
    return sp.csr_matrix((wgt[keep].astype(np.float32), (rows, i[keep])), shape=(n, n_in))


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
        (bilinear, 0 outside), and where its whole footprint holds reference data.

        OpenCV warps on one thread here: threaded, its rows' coordinates round with the
        number of threads, and the gradient blocks and kernel polish that read this warp
        moved the homography by 1e-9 between one core and two (``python -m
        benchmarks.cores``: the 12 and 20 px shakes' ``reblurred.tif``)."""
        h, w = self.obs.shape
        with opencv_single():
            ref = cv2.warpPerspective(self.ref, Hs, (w, h), flags=cv2.INTER_LINEAR,
                                      borderMode=cv2.BORDER_CONSTANT)
            cover = cv2.warpPerspective(self.ref_mask.astype(np.float32), Hs, (w, h),
                                        flags=cv2.INTER_LINEAR,
                                        borderMode=cv2.BORDER_CONSTANT)
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

