"""Reading and writing images, masks and reports, small or gigapixel.

Reading
-------
:func:`open_image` returns an :class:`Image`: a handle holding the pixel ``array``
(``(H, W)`` or ``(H, W, C)``, channel last), its file ``path``, ``format`` and, for a
GeoTIFF, its georeferencing ``geo``.  Small images are read into a numpy array; large TIFF
(striped or tiled, classic or BigTIFF) and zarr images stay on disk and ``array`` is a lazy
array-like (a ``zarr.Array`` or a :class:`LazyBands` view of one) that reads only the
windows sliced from it: ``image.array[y0:y1, x0:x1]`` returns a numpy array.

Supported: PNG, JPEG, TIFF/BigTIFF/GeoTIFF, zarr arrays (a directory, or a group holding an
array ``"0"`` or a single array); other formats imagecodecs can decode (BMP, WebP, ...) are
read into memory.  A large PNG or JPEG (more than :data:`LAZY_BYTES` decoded) is decoded once,
in strips, into a temporary zarr store and read from it window by window like a large TIFF
(:mod:`reblur._decoded`).  Pixel types uint8, uint16 (never reduced to 8 bits), other
integers and float32/float64; gray, gray+alpha, RGB, RGBA (alpha is dropped) and multi-band
images.

Every problem with an input raises :class:`InputError` (a ``ValueError``) whose message is
one line naming the file and the problem: missing file, unreadable, truncated or not an
image, data the format would silently read as zeros or grey (a zarr chunk never written, a
TIFF tile or strip with offset or byte count 0, a JPEG whose data ends early), smaller
than :data:`MIN_SIDE` pixels on a side, more than ``max_pixels`` pixels, more decoded bytes
than ``max_pixels`` x :data:`BYTES_PER_PIXEL`, a format decoded whole whose decoder would
need more than :data:`IN_MEMORY_MAX_BYTES`, or a lazily read image whose chunks exceed
:data:`CHUNK_MAX_BYTES` (decompression-bomb guards checked from the header -- size, bands and
sample type -- before any pixel is decoded; a format whose header cannot be read is refused,
and so is an animation), NaN or Inf pixels (refused: a float image is scanned window by
window, never loaded whole).  A TIFF compression no installed codec decodes is refused when
the file is opened, and the first chunk of a lazily read image is decoded then; any later
window that fails to decode (a corrupt tile met by the estimate, a tile thread or a Dask
worker) raises the same one-line
:class:`InputError`, naming the file and the window.  tifffile's own log lines are kept off
the terminal while reading and folded into that message.

Writing
-------
Every writer is atomic: it writes a temporary file in the destination directory and renames
it into place (:func:`atomic_path`), so a reader never sees a half-written file and an
interrupted run leaves no partial output.  :func:`write_tiff` and :func:`write_geotiff`
accept a numpy array or an iterator of tiles, so a gigapixel mask is written without ever
existing whole in memory in its output type.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import json
import logging
import math
import os
import struct
import tempfile
import threading
import warnings
import zlib
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ._bands import all_bands, any_bands
from ._memory import available_cpus
from .levels import FileLevels, combine, tiff_has_levels, tiff_levels, zarr_levels, zarr_multiscales

__all__ = [
    "InputError",
    "Image",
    "LazyBands",
    "ChunkCache",
    "chunk_cached",
    "sweep_rows",
    "tile_chunks",
    "DEFAULT_MAX_PIXELS",
    "BYTES_PER_PIXEL",
    "decoded_bytes_limit",
    "convert_command",
    "MIN_SIDE",
    "open_image",
    "read_mask",
    "reconcile_bands",
    "check_sizes",
    "display_path",
    "MAX_SIZE_RATIO",
    "check_finite",
    "iter_windows",
    "atomic_path",
    "write_png",
    "encode_png",
    "write_tiff",
    "write_geotiff",
    "write_json",
    "to_jsonable",
]

#: Default limit on ``height * width`` (4 gigapixels).  It guards against decompression bombs
#: and typos; raise it with ``max_pixels=`` (``--max-pixels``) for larger images.
DEFAULT_MAX_PIXELS = 4_000_000_000

#: The decoded bytes an image may take are ``max_pixels`` times this: an allowed pixel is
#: 4 bytes (RGBA at 8 bits, gray + alpha at 16, one float32 band), so images of deeper
#: pixels count for more (an RGBA 16-bit image for twice its pixels).  Checked from the
#: header (size, bands, sample type) before anything is decoded, for every format; 16 GB
#: under the default limit.
BYTES_PER_PIXEL = 4

#: Minimum image side in pixels: smaller images cannot carry a blur estimate.
MIN_SIDE = 32

#: Images whose pixel data exceeds this many bytes stay on disk: TIFF and zarr read window
#: by window, PNG and JPEG decoded once, in strips, into a temporary store read the same way.
LAZY_BYTES = 512 * 2**20

#: A chunk (tile or strip) of a lazily read TIFF or zarr image may not decode to more: every
#: window read decodes each chunk it touches whole (a single-strip TIFF: the whole image).
CHUNK_MAX_BYTES = 512 * 2**20

#: A format that cannot be decoded in strips (WebP, JPEG 2000, JPEG XL, AVIF, an interlaced
#: or palette PNG, a 12-bit JPEG, ...) is decoded whole in memory: refuse it when the
#: decoder's peak (the decoded bytes times a measured factor per format, from the header)
#: would exceed this; the message gives the command converting it to a tiled TIFF.
IN_MEMORY_MAX_BYTES = 2**32

#: Rec. 709 luminance weights (as ``skimage.color.rgb2gray``).
LUMINANCE = (0.2125, 0.7154, 0.0721)

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


class InputError(ValueError):
    """An input file cannot be used; the message is one line naming the file and problem."""


# ---------------------------------------------------------------------------- lazy arrays
class _Sized:
    """``size``, ``nbytes`` and ``len()`` of an array-like window reader from its ``shape``
    and ``dtype``."""

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    @property
    def nbytes(self) -> int:
        return self.size * self.dtype.itemsize

    def __len__(self) -> int:
        return self.shape[0]


class LazyBands(_Sized):
    """Lazy channel-last view of an on-disk array, with band selection or luminance.

    Slicing returns numpy arrays and reads only the window asked for.

    Parameters
    ----------
    source : array-like
        ``(H, W)``, ``(H, W, C)`` or, with ``channel_first``, ``(C, H, W)``.
    channel_first : bool
        The source stores bands first (planar TIFF); the view is channel last.
    bands : sequence of int, optional
        Bands of the source to keep (e.g. ``(0, 1, 2)`` drops an alpha band).
    luminance : bool
        Convert the (selected) three bands to one gray band with :data:`LUMINANCE`,
        keeping the dtype (integers are rounded).
    """

    def __init__(
        self,
        source,
        *,
        channel_first: bool = False,
        bands: Sequence[int] | None = None,
        luminance: bool = False,
    ):
        self.source = source
        self.channel_first = bool(channel_first)
        self.bands = None if bands is None else tuple(int(b) for b in bands)
        self.luminance = bool(luminance)
        shape = tuple(int(s) for s in source.shape)
        if len(shape) == 2:
            h, w, c = shape[0], shape[1], 1
            self._src_bands = 0
        elif channel_first:
            c, h, w = shape
            self._src_bands = c
        else:
            h, w, c = shape
            self._src_bands = c
        n = len(self.bands) if self.bands is not None else c
        if self.luminance:
            if n != 3:
                raise ValueError("luminance needs exactly three bands")
            n = 1
        self._shape = (h, w) if n == 1 else (h, w, n)
        self.dtype = np.dtype(source.dtype)

    @property
    def shape(self) -> tuple[int, ...]:
        return self._shape

    @property
    def ndim(self) -> int:
        return len(self._shape)

    @property
    def chunks(self) -> tuple[int, ...] | None:
        ch = getattr(self.source, "chunks", None)
        if ch is None:
            return None
        ch = tuple(int(c) for c in ch)
        return ch[1:3] if self.channel_first else ch[:2]

    def __repr__(self) -> str:
        return f"LazyBands(shape={self._shape}, dtype={self.dtype}, source={type(self.source)})"

    @property
    def file_levels(self) -> FileLevels | None:
        """The source file's reduced-resolution levels, seen through this view."""
        fl = getattr(self.source, "file_levels", None)
        return None if fl is None else fl.map(functools.partial(
            LazyBands, channel_first=self.channel_first, bands=self.bands,
            luminance=self.luminance))

    def __getitem__(self, key) -> np.ndarray:
        if not isinstance(key, tuple):
            key = (key,)
        if any(k is Ellipsis for k in key):
            i = key.index(Ellipsis)
            fill = self.ndim - (len(key) - 1)
            key = key[:i] + (slice(None),) * fill + key[i + 1 :]
        if len(key) > self.ndim:
            raise IndexError(f"too many indices for a {self.ndim}-D image")
        key = key + (slice(None),) * (self.ndim - len(key))
        ky, kx = key[0], key[1]
        spatial = []
        for k, n in ((ky, self._shape[0]), (kx, self._shape[1])):
            if isinstance(k, slice):
                spatial.append(k)
            elif isinstance(k, (int, np.integer)):
                i = int(k) + n if int(k) < 0 else int(k)
                if not 0 <= i < n:
                    raise IndexError(f"index {int(k)} out of range for size {n}")
                spatial.append(slice(i, i + 1))
            else:
                raise IndexError("LazyBands takes integer or slice indices on rows and columns")
        sy, sx = spatial
        if self._src_bands == 0:
            a = np.asarray(self.source[sy, sx])[..., None]
        elif self.channel_first:
            sel = slice(None) if self.bands is None else list(self.bands)
            a = np.moveaxis(np.asarray(self.source[sel, sy, sx]), 0, -1)
        else:
            a = np.asarray(self.source[sy, sx])
            if self.bands is not None:
                a = a[..., list(self.bands)]
        if self.luminance:
            a = _luminance(a)[..., None]
        a = a[..., 0] if len(self._shape) == 2 else a[..., key[2]]
        if not isinstance(kx, slice):
            a = a[:, 0]
        if not isinstance(ky, slice):
            a = a[0]
        return a

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        a = self[...]
        return a if dtype is None else a.astype(dtype, copy=False)


def _spatial_key(key, ndim: int) -> tuple:
    """The row and column parts of an index of a 2-D or 3-D image (Ellipsis expanded)."""
    if not isinstance(key, tuple):
        key = (key,)
    if any(k is Ellipsis for k in key):
        i = key.index(Ellipsis)
        key = key[:i] + (slice(None),) * (ndim - (len(key) - 1)) + key[i + 1 :]
    key = key + (slice(None),) * (2 - len(key))
    return key[:2]


def _fmt_value(v: float) -> str:
    return "nan" if np.isnan(v) else f"{v:g}"


class NodataMask:
    """Lazy ``(H, W)`` validity of an image from a no-data value.

    A pixel holds no data when every band equals ``value`` (GDAL's per-dataset reading of
    a nodata value shared by the bands: a dark red pixel with one band at 0 is data); with
    ``value`` NaN, when any band is not finite.
    """

    def __init__(self, array, value: float):
        self.array = array
        self.value = float(value)
        self.shape = tuple(int(s) for s in array.shape[:2])
        self.dtype = np.dtype(bool)
        self.ndim = 2

    @property
    def file_levels(self) -> FileLevels | None:
        """The validity of the image file's reduced-resolution levels (the same value)."""
        fl = getattr(self.array, "file_levels", None)
        return None if fl is None else fl.map(functools.partial(NodataMask, value=self.value))

    def __getitem__(self, key) -> np.ndarray:
        a = np.asarray(self.array[_spatial_key(key, len(self.array.shape))])
        if np.isnan(self.value):
            bad = ~np.isfinite(a)
            return ~any_bands(bad)
        bad = a == self.value
        return ~all_bands(bad)


class AlphaMask:
    """Lazy ``(H, W)`` validity from an alpha band (``alpha > 0``: data)."""

    def __init__(self, alpha):
        self.alpha = alpha
        self.shape = tuple(int(s) for s in alpha.shape[:2])
        self.dtype = np.dtype(bool)
        self.ndim = 2

    @property
    def file_levels(self) -> FileLevels | None:
        """The validity of the image file's reduced-resolution levels (their alpha band)."""
        fl = getattr(self.alpha, "file_levels", None)
        return None if fl is None else fl.map(AlphaMask)

    def __getitem__(self, key) -> np.ndarray:
        return np.asarray(self.alpha[_spatial_key(key, 2)]) > 0


class RasterMask:
    """Lazy ``(H, W)`` validity from a raster's internal (per-dataset) mask, read window by
    window with rasterio (GDAL's ``GetMaskBand``: 0 = no data)."""

    def __init__(self, path: Path, shape: tuple[int, int]):
        self.path = Path(path)
        self.shape = tuple(int(s) for s in shape)
        self.dtype = np.dtype(bool)
        self.ndim = 2

    def __getitem__(self, key) -> np.ndarray:
        import rasterio
        from rasterio.windows import Window

        ky, kx = _spatial_key(key, 2)
        y0, y1, _ = ky.indices(self.shape[0])
        x0, x1, _ = kx.indices(self.shape[1])
        with rasterio.Env(CPL_LOG="/dev/null"), rasterio.open(self.path) as src:
            m = src.read_masks(1, window=Window(x0, y0, max(x1 - x0, 0), max(y1 - y0, 0)))
        return m > 0


class MaskedView:
    """An image as :func:`reblur.detect_changes` reads it when some pixels hold no data:
    float32, integers divided by their type's maximum (the scale reblur gives them anyway),
    NaN where ``valid`` is False.  NaN is unknown everywhere downstream: the reblurred
    reference is NaN wherever its blur touches a no-data pixel, and unknown pixels are
    never change.

    Parameters
    ----------
    array : array-like
        ``(H, W)`` or ``(H, W, C)`` image (numpy or lazy).
    valid : array-like
        ``(H, W)`` bool reader (or array), True where there is data.
    """

    def __init__(self, array, valid):
        self.array = array
        self.valid = valid
        self.shape = tuple(int(s) for s in array.shape)
        if tuple(valid.shape[:2]) != self.shape[:2]:
            raise ValueError(f"validity mask {tuple(valid.shape)} does not match the image "
                             f"{self.shape}")
        self.dtype = np.dtype(np.float32)
        self.ndim = len(self.shape)
        dt = np.dtype(array.dtype)
        self._scale = np.float32(1.0 / np.iinfo(dt).max) if dt.kind in "ui" else None

    @property
    def chunks(self):
        return getattr(self.array, "chunks", None)

    @property
    def file_levels(self) -> FileLevels | None:
        """The image file's reduced-resolution levels seen through the same view (when the
        validity is a no-data value or alpha band of the same file: it has them too)."""
        return combine(getattr(self.array, "file_levels", None),
                       getattr(self.valid, "file_levels", None), MaskedView)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key) -> np.ndarray:
        a = np.array(self.array[key], dtype=np.float32)
        if self._scale is not None:
            a *= self._scale
        bad = ~np.asarray(self.valid[_spatial_key(key, self.ndim)], bool)
        if bad.any():
            if a.ndim == bad.ndim + 1:
                a[bad, :] = np.nan
            elif a.shape == bad.shape:
                a[bad] = np.nan
            else:  # a single band picked by the index
                a[bad.reshape(a.shape)] = np.nan
        return a

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        a = self[...]
        return a if dtype is None else a.astype(dtype, copy=False)


class ChunkCache:
    """Window reader of a chunked, on-disk image that keeps recently decoded chunks.

    The windows of a tiled pass overlap -- each padded tile reads its halo and the reach
    of its poses -- so reading them straight from a compressed store decodes most chunks
    several times (about four times each, for 1024-px tiles over 512-px chunks).  Through
    this reader every chunk is read whole, once while it stays among the most recently
    used ones (the chunks a window lacks in one request), and windows are assembled from
    the kept chunks.  Slicing returns numpy arrays, exactly ``np.asarray(array[key])``.

    Parameters
    ----------
    array : array-like
        ``(H, W)`` or ``(H, W, C)`` with a ``chunks`` attribute (zarr, tifffile's zarr
        store, :class:`reblur.dask_backend.TiffSource`, :class:`LazyBands` over one).
    max_bytes : int, optional
        Bound on the bytes of the kept chunks (least recently used go first).  Default:
        four rows of chunks across the image (a row of 1024-px tiles and the one before
        it), at least 64 MB and at most 1 GB.
    chunks : (int, int), optional
        Chunk size to use; default ``array.chunks``.

    Notes
    -----
    Thread-safe: tile threads share one reader (two threads may decode the same chunk at
    the same moment; both copies are equal).  Pickling drops the kept chunks.
    """

    def __init__(self, array, max_bytes: int | None = None, chunks=None):
        self.array = array
        self.shape = tuple(int(v) for v in array.shape)
        if len(self.shape) not in (2, 3):
            raise ValueError(f"ChunkCache needs an (H, W) or (H, W, C) array, got {self.shape}")
        self.dtype = np.dtype(array.dtype)
        self.ndim = len(self.shape)
        ch = chunks if chunks is not None else getattr(array, "chunks", None)
        if ch is None:
            raise ValueError("ChunkCache needs a chunked array (or chunks=)")
        self.chunks = (max(1, int(ch[0])), max(1, int(ch[1])))
        px = int(np.prod(self.shape[2:], dtype=np.int64)) * self.dtype.itemsize
        if max_bytes is None:
            rows = 4 * self.chunks[0] * self.shape[1] * px
            max_bytes = min(max(rows, 64 * 2**20), 2**30)
        self.max_bytes = int(max_bytes)
        self.hits = self.misses = 0
        self._init_cache()

    def _init_cache(self) -> None:
        import collections
        import threading

        self._kept: collections.OrderedDict = collections.OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        for k in ("_kept", "_bytes", "_lock"):
            state.pop(k, None)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._init_cache()

    def _fetch(self, keys: list[tuple[int, int]]) -> dict[tuple[int, int], np.ndarray]:
        """The chunks ``keys``: kept ones from memory, the others read in one request
        (the rectangle of chunks that holds them: one call, decoded concurrently by the
        store, costs less than a call per chunk)."""
        got: dict[tuple[int, int], np.ndarray] = {}
        with self._lock:
            for key in keys:
                a = self._kept.get(key)
                if a is not None:
                    self._kept.move_to_end(key)
                    got[key] = a
            self.hits += len(got)
            self.misses += len(keys) - len(got)
        missing = [k for k in keys if k not in got]
        if not missing:
            return got
        hy, hx = self.chunks
        cy0, cy1 = min(k[0] for k in missing), max(k[0] for k in missing) + 1
        cx0, cx1 = min(k[1] for k in missing), max(k[1] for k in missing) + 1
        y0, x0 = cy0 * hy, cx0 * hx
        block = np.asarray(self.array[y0 : min(cy1 * hy, self.shape[0]),
                                      x0 : min(cx1 * hx, self.shape[1])])
        fresh = {}
        for cy in range(cy0, cy1):
            for cx in range(cx0, cx1):
                # a copy: a kept chunk must not hold the whole block alive
                fresh[(cy, cx)] = block[cy * hy - y0 : (cy + 1) * hy - y0,
                                        cx * hx - x0 : (cx + 1) * hx - x0].copy()
        with self._lock:
            for key, a in fresh.items():
                if key in self._kept:
                    self._kept.move_to_end(key)
                    continue
                self._kept[key] = a
                self._bytes += a.nbytes
            while self._bytes > self.max_bytes and len(self._kept) > 1:
                _, old = self._kept.popitem(last=False)
                self._bytes -= old.nbytes
        for key in missing:
            got[key] = fresh[key]
        return got

    def __getitem__(self, key):
        if not isinstance(key, tuple):
            key = (key,)
        ys = key[0] if len(key) > 0 else slice(None)
        xs = key[1] if len(key) > 1 else slice(None)
        if not (isinstance(ys, slice) and isinstance(xs, slice)
                and ys.step in (None, 1) and xs.step in (None, 1)):
            return np.asarray(self.array[key])
        y0, y1, _ = ys.indices(self.shape[0])
        x0, x1, _ = xs.indices(self.shape[1])
        y1, x1 = max(y0, y1), max(x0, x1)
        out = np.empty((y1 - y0, x1 - x0, *self.shape[2:]), self.dtype)
        hy, hx = self.chunks
        keys = [(cy, cx) for cy in range(y0 // hy, -(-y1 // hy))
                for cx in range(x0 // hx, -(-x1 // hx))]
        chunks = self._fetch(keys)
        for (cy, cx), c in chunks.items():
            ya, yb = max(y0, cy * hy), min(y1, (cy + 1) * hy)
            xa, xb = max(x0, cx * hx), min(x1, (cx + 1) * hx)
            out[ya - y0 : yb - y0, xa - x0 : xb - x0] = c[ya - cy * hy : yb - cy * hy,
                                                          xa - cx * hx : xb - cx * hx]
        return out[(slice(None), slice(None), *key[2:])] if len(key) > 2 else out


def tile_chunks(image) -> tuple[int, int] | None:
    """The ``(rows, cols)`` chunk size of ``image`` when its chunks are tiles (at least
    64 px on each side, at most 2**24 px): what a :class:`ChunkCache` can keep whole.
    None for numpy arrays, row strips and arrays without chunks."""
    chunks = getattr(image, "chunks", None)
    if isinstance(image, np.ndarray) or not chunks or len(chunks) < 2:
        return None
    ch, cw = int(chunks[0]), int(chunks[1])
    if min(ch, cw) < 64 or ch * cw > 2**24:
        return None
    return ch, cw


def sweep_rows(tile_size: int, halo: int, chunk_rows: int) -> int:
    """Image rows a :class:`ChunkCache` keeps for a raster sweep of ``tile_size`` tiles
    padded by ``halo``: one padded tile row and a chunk row of slack on each side.

    In raster order, least-recently-used eviction then reads every chunk once: the chunks
    a tile row shares with the next one are still kept when the next row starts (without
    the slack, some are read twice).  Two tile rows, the budget before, kept 1.5x the
    chunks for 17 % fewer reads and no faster tile pass (the 100 MP ``5% rgb16`` pair of
    ``python -m benchmarks.cost``: 199 -> 130 MB per cache and 581-601 -> 697-719 chunk
    reads, ``python -m benchmarks.stage_cpu REF OBS``; tile pass 34.8-35.4 -> 33.2-34.5 s,
    alternating ``reblur detect`` runs).  The extra reads come from the windows that are
    no plain raster sweep (re-runs with larger halos, pass 1's samples, two threads at a
    row's end).
    """
    return int(tile_size) + 2 * int(halo) + 2 * int(chunk_rows)


def chunk_cached(image, tile_size: int, halo: int):
    """``image`` read through a :class:`ChunkCache` sized for a tiled pass, when it is a
    chunked on-disk array whose chunks are tiles (not single rows); anything else (numpy
    arrays, a reader already cached) is returned as it is.

    The cache keeps :func:`sweep_rows` rows across the image, within 64 MB to 256 MB.
    """
    tiles = None if isinstance(image, ChunkCache) else tile_chunks(image)
    if tiles is None:
        return image
    ch, cw = tiles
    px = int(np.prod(image.shape[2:], dtype=np.int64)) * np.dtype(image.dtype).itemsize
    rows = sweep_rows(tile_size, halo, ch)
    budget = min(max(rows * int(image.shape[1]) * px, 64 * 2**20), 256 * 2**20)
    return ChunkCache(image, max_bytes=budget, chunks=(ch, cw))


class _Guarded(_Sized):
    """Window reader of a lazily read file whose read and decode failures become one
    :class:`InputError` naming the file and the window.

    The windows of a large image are decoded long after :func:`open_image` returned (in the
    estimate, the tile threads or Dask workers): a corrupt tile or chunk found there must
    still say which file is broken, not surface as a codec's bare exception.  Slicing
    returns numpy arrays; ``source`` is the wrapped reader (:func:`reblur.dask_backend.portable`
    makes it picklable).
    """

    #: The file's reduced-resolution levels (:mod:`reblur.levels`), None without any.
    file_levels: FileLevels | None = None
    #: Every chunk of the image, decoded, for whole-image passes (:class:`_TiffChunks`),
    #: None when the file offers no such reader.
    chunk_reader: _TiffChunks | None = None

    def __init__(self, source, path: Path):
        self.source = source
        self.path = path

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(int(s) for s in self.source.shape)

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(self.source.dtype)

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def chunks(self):
        return getattr(self.source, "chunks", None)

    def __repr__(self) -> str:
        return f"_Guarded({self.path}, shape={self.shape}, dtype={self.dtype})"

    def __getitem__(self, key) -> np.ndarray:
        try:
            with _tifffile_quiet():
                return np.asarray(self.source[key])
        except (InputError, MemoryError):
            raise
        except Exception as exc:  # noqa: BLE001 - every read failure means a corrupt file
            raise _undecodable(self.path, _where(key, self.shape), exc) from exc

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        a = self[...]
        return a if dtype is None else a.astype(dtype, copy=False)


def _undecodable(path: Path, where: str, exc: BaseException) -> InputError:
    """The one-line error of image data that fails to decode (``where``: :func:`_where`'s
    place of it, or empty)."""
    return _fail(path, f"cannot decode the image data{where} ({_first_line(exc)}): the "
                       "file is corrupt or truncated")


def _where(key, shape: tuple[int, ...]) -> str:
    """`` at rows a-b, columns c-d`` for a window ``key`` of an array of ``shape`` (empty
    when it is not a window of slices)."""
    if not isinstance(key, tuple):
        key = (key,)
    key = key + (slice(None),) * max(0, 2 - len(key))
    parts = []
    for name, k, n in zip(("rows", "columns"), key[:2], shape[:2], strict=False):
        if not isinstance(k, slice) or k.step not in (None, 1):
            return ""
        a, b, _ = k.indices(n)
        parts.append(f"{name} {a}-{b - 1}")
    return f" at {', '.join(parts)}"


def _first_line(exc: BaseException) -> str:
    msg = str(exc).strip()
    return msg.splitlines()[0] if msg else type(exc).__name__


class _TifffileLog(logging.Filter):
    """Keeps tifffile's own log lines off the terminal while reblur reads a file: what it
    logs (a missing tag, a corrupt structure) is kept here and reported in reblur's one
    error line instead.  Other records pass."""

    def __init__(self) -> None:
        super().__init__()
        self.depth = 0
        self.kept: list[str] = []
        self.lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        if self.depth <= 0:
            return True
        with self.lock:
            if len(self.kept) < 16:
                self.kept.append(record.getMessage())
        return False


_TIFF_LOG = _TifffileLog()
logging.getLogger("tifffile").addFilter(_TIFF_LOG)


@contextlib.contextmanager
def _tifffile_quiet() -> Iterator[Callable[[], list[str]]]:
    """Silence tifffile's logger within the block; yield a function that returns the
    messages it logged so far (those of any thread while the block runs)."""
    with _TIFF_LOG.lock:
        _TIFF_LOG.depth += 1
        start = len(_TIFF_LOG.kept)

    def logged() -> list[str]:
        with _TIFF_LOG.lock:
            return list(_TIFF_LOG.kept[start:])

    try:
        yield logged
    finally:
        with _TIFF_LOG.lock:
            _TIFF_LOG.depth -= 1
            if _TIFF_LOG.depth == 0:
                _TIFF_LOG.kept.clear()


def _check_first_window(path: Path, array) -> None:
    """Decode the first chunk of a lazily read image now, at open time: an undecodable
    codec or corrupt data is refused before the work starts (the other chunks are checked
    as they are read)."""
    ch = getattr(array, "chunks", None)
    h, w = (int(v) for v in array.shape[:2])
    ry = int(ch[0]) if ch else min(h, 256)
    rx = int(ch[1]) if ch and len(ch) > 1 else min(w, 256)
    array[0 : min(h, max(1, ry)), 0 : min(w, max(1, rx))]


def _luminance(a: np.ndarray) -> np.ndarray:
    """``(..., 3)`` -> ``(...)`` luminance in the input dtype (integers rounded)."""
    g = np.tensordot(a.astype(np.float32, copy=False), np.asarray(LUMINANCE, np.float32),
                     axes=([-1], [0]))
    if np.issubdtype(a.dtype, np.integer):
        info = np.iinfo(a.dtype)
        return np.clip(np.rint(g), info.min, info.max).astype(a.dtype)
    return g.astype(a.dtype, copy=False)


# ---------------------------------------------------------------------------- the handle
@dataclass
class Image:
    """An opened image.

    Attributes
    ----------
    array : ndarray or array-like
        Pixels, ``(H, W)`` or ``(H, W, C)``, channel last.  A numpy array for images read
        into memory, otherwise a lazy array-like (``zarr.Array`` or :class:`LazyBands`).
    path : Path or None
        The file it came from (``None`` for :meth:`from_array`).
    format : str
        ``"png"``, ``"jpeg"``, ``"tiff"``, ``"zarr"``, ``"array"`` or the codec name.
    geo : dict or None
        For georeferenced TIFFs: ``crs`` (``rasterio.crs.CRS``), ``transform``
        (``affine.Affine``) and ``nodata``; ``None`` otherwise.
    notes : list of str
        What was done on reading (alpha dropped, converted to gray, ...).
    valid : array-like or None
        ``(H, W)`` bool reader, False where the file says there is no data (its nodata
        value, internal mask or alpha band, or ``--nodata``): those pixels are unknown,
        never change.  None: every pixel holds data.
    nodata_source : str or None
        Where ``valid`` comes from ("nodata 0", "alpha band", "internal mask", ...).
    """

    array: Any
    path: Path | None = None
    format: str = "array"
    geo: dict[str, Any] | None = None
    notes: list[str] = field(default_factory=list)
    _closer: Callable[[], None] | None = field(default=None, repr=False, compare=False)
    valid: Any = None
    nodata_source: str | None = None

    @classmethod
    def from_array(cls, array, name: str | None = None) -> Image:
        """Wrap an in-memory (or lazy) array after the same validation as :func:`open_image`."""
        arr = array if hasattr(array, "shape") and hasattr(array, "dtype") else np.asarray(array)
        label = name or "<array>"
        _check_shape(label, tuple(arr.shape), None)
        _check_dtype(label, np.dtype(arr.dtype))
        img = cls(arr, Path(name) if name else None, "array")
        check_finite(img)
        return img

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(int(s) for s in self.array.shape)

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(self.array.dtype)

    @property
    def bands(self) -> int:
        return 1 if len(self.shape) == 2 else self.shape[2]

    @property
    def height(self) -> int:
        return self.shape[0]

    @property
    def width(self) -> int:
        return self.shape[1]

    @property
    def n_pixels(self) -> int:
        return self.shape[0] * self.shape[1]

    @property
    def lazy(self) -> bool:
        """True when the pixels stay on disk."""
        return not isinstance(self.array, np.ndarray)

    @property
    def name(self) -> str:
        return str(self.path) if self.path is not None else "<array>"

    def info(self) -> dict[str, Any]:
        """JSON-ready description: path, format, shape, dtype, bands, lazy, geo, notes."""
        d: dict[str, Any] = dict(
            path=str(self.path) if self.path is not None else None,
            format=self.format,
            shape=list(self.shape),
            dtype=str(self.dtype),
            bands=self.bands,
            megapixels=round(self.n_pixels / 1e6, 3),
            lazy=self.lazy,
        )
        if self.geo:
            d["geo"] = dict(
                crs=self.geo["crs"].to_string() if self.geo.get("crs") else None,
                transform=list(self.geo["transform"])[:6],
            )
        if self.notes:
            d["notes"] = list(self.notes)
        if self.nodata_source:
            d["nodata"] = self.nodata_source
        return d

    def with_nodata(self, value: float) -> Image:
        """This image with the pixels whose every band equals ``value`` (NaN: any band not
        finite) marked as no data; replaces what the file said."""
        v = float(value)
        return replace(self, valid=NodataMask(self.array, v),
                       nodata_source=f"nodata {_fmt_value(v)} (given)")

    def for_detection(self) -> Any:
        """What :func:`reblur.detect_changes` reads: the array itself, or with no-data pixels
        as NaN (:class:`MaskedView`)."""
        return self.array if self.valid is None else MaskedView(self.array, self.valid)

    def read(self) -> np.ndarray:
        """The whole image as a numpy array (loads a lazy image into memory)."""
        return np.asarray(self.array[...]) if self.lazy else self.array

    def close(self) -> None:
        """Release the file handle of a lazy image (the array cannot be read afterwards)."""
        if self._closer is not None:
            self._closer()
            self._closer = None

    def __enter__(self) -> Image:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ---------------------------------------------------------------------------- validation
_ESCAPES = {"\n": "\\n", "\r": "\\r", "\t": "\\t"}


def display_path(path: Any) -> str:
    """``path`` as text safe to print on a terminal: every non-printable character escaped.

    A file name may hold anything but ``/`` and NUL: a newline (which would split a one-line
    message, or read as a space once lines are joined), a terminal escape sequence (which
    the terminal would act on) or bytes that are not UTF-8 (which cannot even be printed).
    These are written as Python writes them in a ``repr`` -- ``\\n``, ``\\x1b``,
    ``\\u200b`` -- and undecodable bytes as ``\\xNN``; printable names are unchanged.

    Examples
    --------
    >>> display_path("a\\nb\\x1b[31m.png")
    'a\\\\nb\\\\x1b[31m.png'
    >>> display_path("café.png")
    'café.png'
    """
    s = os.fspath(path) if isinstance(path, os.PathLike) else str(path)
    if isinstance(s, bytes):
        s = os.fsdecode(s)
    if s.isprintable():
        return s
    out = []
    for ch in s:
        o = ord(ch)
        if ch.isprintable():
            out.append(ch)
        elif ch in _ESCAPES:
            out.append(_ESCAPES[ch])
        elif 0xDC80 <= o <= 0xDCFF:  # a byte that is not UTF-8 (os.fsdecode's surrogate)
            out.append(f"\\x{o - 0xDC00:02x}")
        elif o < 0x100:
            out.append(f"\\x{o:02x}")
        elif o < 0x10000:
            out.append(f"\\u{o:04x}")
        else:
            out.append(f"\\U{o:08x}")
    return "".join(out)


def _fail(path, problem: str) -> InputError:
    return InputError(f"{display_path(path)}: {problem}")


def _check_shape(path, shape: tuple[int, ...], max_pixels: int) -> None:
    if len(shape) not in (2, 3):
        raise _fail(path, f"expected a 2-D image (H, W) or (H, W, bands), got shape {shape}")
    h, w = shape[:2]
    if h == 0 or w == 0 or (len(shape) == 3 and shape[2] == 0):
        raise _fail(path, f"image is empty (shape {shape})")
    if h < MIN_SIDE or w < MIN_SIDE:
        raise _fail(path, f"image is {w}x{h} pixels; at least {MIN_SIDE}x{MIN_SIDE} is needed")
    if max_pixels is not None and h * w > max_pixels:
        raise _fail(
            path,
            f"image has {h * w:,} pixels ({w}x{h}), more than the limit of {int(max_pixels):,}; "
            "raise --max-pixels (max_pixels=) if this is intended",
        )


def _check_dtype(path, dtype: np.dtype) -> None:
    if dtype.kind not in "uif" and dtype != np.bool_:
        raise _fail(path, f"unsupported pixel type {dtype}")


def iter_windows(
    shape: tuple[int, ...], tile: int | tuple[int, int] = 1024
) -> Iterator[tuple[slice, slice]]:
    """Row-major ``(rows, cols)`` slices covering an image of ``shape`` with tiles of ``tile``."""
    th, tw = (tile, tile) if np.isscalar(tile) else tile
    h, w = shape[:2]
    for y in range(0, h, th):
        for x in range(0, w, tw):
            yield slice(y, min(y + th, h)), slice(x, min(x + tw, w))


def _row_bands(array, target_bytes: int = 64 * 2**20) -> Iterator[slice]:
    """Row slices of about ``target_bytes`` each, aligned to the array's chunk rows."""
    shape = tuple(array.shape)
    h = shape[0]
    row_bytes = max(1, int(np.prod(shape[1:])) * np.dtype(array.dtype).itemsize)
    step = max(1, target_bytes // row_bytes)
    chunks = getattr(array, "chunks", None)
    if chunks:
        ch = int(chunks[0])
        step = max(ch, (step // ch) * ch)
    for y in range(0, h, step):
        yield slice(y, min(y + step, h))


def _nan_nodata(img: Image) -> bool:
    return isinstance(img.valid, NodataMask) and np.isnan(img.valid.value)


def check_finite(image: Image | Any, name: str | None = None, *,
                 nan_is_nodata: bool = False) -> None:
    """Raise :class:`InputError` if a float image holds NaN or Inf pixels (only Inf with
    ``nan_is_nodata``: the file declares NaN as its no-data value).

    Lazy images are scanned in bands of rows (about 64 MB each), never loaded whole.
    """
    arr = image.array if isinstance(image, Image) else image
    label = name or (image.name if isinstance(image, Image) else "<array>")
    if np.dtype(arr.dtype).kind != "f":
        return
    for rows in _row_bands(arr):
        block = np.asarray(arr[rows])
        if nan_is_nodata:
            block = np.where(np.isnan(block), 0, block)
        if not np.isfinite(block).all():
            bad = ~np.isfinite(block)
            while bad.ndim > 2:
                bad = bad.any(axis=-1)
            y, x = np.argwhere(bad)[0]
            n_nan = int(np.isnan(block).sum())
            kind = "NaN" if n_nan else "Inf"
            raise _fail(
                label,
                f"image has {kind} pixels (first at row {rows.start + int(y)}, column {int(x)}); "
                "fill or mask them before change detection",
            )


# ---------------------------------------------------------------------------- limits
def decoded_bytes_limit(max_pixels: int | None) -> int | None:
    """The decoded bytes an image may take under ``max_pixels``: :data:`BYTES_PER_PIXEL`
    per allowed pixel (None: no limit)."""
    return None if max_pixels is None else int(max_pixels) * BYTES_PER_PIXEL


@dataclass(frozen=True)
class _Layout:
    """What an image file decodes to, read from its header before any pixel is decoded.

    ``itemsize`` is bytes per sample (an upper bound where the header does not say:
    ``exact`` False); ``streamable``: :mod:`reblur._decoded` can decode it in strips into a
    temporary store; ``peak``: the decoder's peak memory over the decoded bytes when it
    decodes the image whole (``python -m benchmarks.big_inputs --cases formats``);
    ``gdal``: GDAL reads the format (for the conversion command in messages).
    """

    height: int
    width: int
    bands: int
    itemsize: int
    exact: bool = True
    streamable: bool = False
    peak: float = 1.0
    gdal: bool = True

    @property
    def nbytes(self) -> int:
        return self.height * self.width * self.bands * self.itemsize


def convert_command(path: Path, gdal: bool = True) -> str:
    """A shell command converting ``path`` to a tiled, compressed (Big)TIFF beside it, which
    reblur reads window by window: GDAL's ``gdal_translate`` (which reads PNG and baseline
    JPEG line by line), or tifffile for a format GDAL does not read."""
    import shlex

    path = Path(path)
    dst = (path.with_name(f"{path.stem}.tiled.tif") if path.suffix.lower() in (".tif", ".tiff")
           else path.with_suffix(".tif"))
    src, dst_q = shlex.quote(display_path(path)), shlex.quote(display_path(dst))
    if gdal:
        return (f"gdal_translate -co TILED=YES -co COMPRESS=ZSTD -co BIGTIFF=IF_SAFER {src} "
                f"{dst_q}")
    return ("python -c 'import sys, imagecodecs, tifffile; tifffile.imwrite(sys.argv[2], "
            "imagecodecs.imread(sys.argv[1]), tile=(512, 512), compression=\"zstd\", "
            f"bigtiff=True)' {src} {dst_q}")


def _check_bytes(path, what: str, lay: _Layout, max_pixels: int | None) -> int:
    """The decoded bytes of ``lay``; raise when they exceed what ``max_pixels`` allows."""
    n, cap = lay.nbytes, decoded_bytes_limit(max_pixels)
    if cap is not None and n > cap:
        s = "s" * (lay.bands != 1)
        upto = "" if lay.exact else "up to "
        raise _fail(
            path,
            f"{what} of {lay.width}x{lay.height} pixels, {lay.bands} band{s} of "
            f"{8 * lay.itemsize} bits, would decode to {upto}{n:,} bytes, more than the limit "
            f"of {cap:,} (--max-pixels {int(max_pixels):,} x {BYTES_PER_PIXEL} bytes); raise "
            f"--max-pixels to at least {-(-n // BYTES_PER_PIXEL):,} if this is intended",
        )
    return n


def _check_in_memory(path, what: str, lay: _Layout) -> None:
    """Refuse an image whose whole decode would need more than :data:`IN_MEMORY_MAX_BYTES`."""
    need = int(lay.nbytes * lay.peak)
    if need > IN_MEMORY_MAX_BYTES:
        raise _fail(
            path,
            f"{what} of {lay.width}x{lay.height} pixels would need about {need:,} bytes of "
            f"memory to decode whole, more than the limit of {IN_MEMORY_MAX_BYTES:,}, and it "
            "cannot be decoded in strips; convert it to a tiled TIFF first: "
            f"{convert_command(path, lay.gdal)}",
        )


def _check_chunk_bytes(path, chunks, dtype, what: str, hint: str) -> None:
    """Refuse a lazily read image whose chunks (tiles or strips) are too large to decode one
    at a time: every window read decodes each chunk it touches whole."""
    n = int(np.prod([int(c) for c in chunks], dtype=np.int64)) * np.dtype(dtype).itemsize
    if n > CHUNK_MAX_BYTES:
        raise _fail(path, f"{what} of {n:,} bytes each, and every window read decodes each one "
                          f"it touches whole (limit {CHUNK_MAX_BYTES:,} bytes); {hint}")


# ---------------------------------------------------------------------------- headers
def _png_layout(path: Path, data) -> _Layout:
    """The layout of a PNG from its IHDR and the chunks before its image data (a ``tRNS``
    chunk adds an alpha band; a palette decodes to RGB)."""
    if len(data) < 33 or data[12:16] != b"IHDR":
        raise _fail(path, "not a valid PNG file (no IHDR header)")
    w, h = struct.unpack(">II", data[16:24])
    depth, colour, interlace = data[24], data[25], data[28]
    trns, i = False, 8
    while i + 8 <= len(data):
        kind = bytes(data[i + 4 : i + 8])
        if kind in (b"IDAT", b"IEND"):
            break
        trns = trns or kind == b"tRNS"
        i += 12 + int.from_bytes(data[i : i + 4], "big")
    bands = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}.get(colour, 4) + (trns and colour in (0, 2, 3))
    plain = depth in (8, 16) and colour in (0, 2, 4, 6) and not trns and interlace == 0
    return _Layout(h, w, bands, 2 if depth == 16 else 1, streamable=plain)


def _jpeg_layout(path: Path, data) -> _Layout:
    """The layout of a JPEG from its first frame header; check the image is complete (an
    end-of-image marker after the last scan), reading only the head and the tail of the
    file.  Baseline, extended and progressive Huffman JPEGs of 8 bits and 1 or 3 components
    decode in strips; a progressive one also needs its coefficients, 2 bytes per sample."""
    i, n = 2, len(data)
    size = sos = None
    while i + 4 <= n:
        if data[i] != 0xFF:
            raise _fail(path, "not a valid JPEG file (corrupt marker structure)")
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0x01,) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        (seg_len,) = struct.unpack(">H", data[i + 2 : i + 4])
        if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE,
                      0xCF):
            if i + 9 > n:
                break
            h, w = struct.unpack(">HH", data[i + 5 : i + 9])
            comps = data[i + 9] if i + 10 <= n else 4
            size = (h, w, comps, 2 if data[i + 4] > 8 else 1, marker)
        if marker == 0xDA:  # start of scan: entropy-coded data follows
            sos = i
            break
        i += 2 + seg_len
    if size is None:
        raise _fail(path, "not a valid JPEG file (no frame header) or truncated")
    eoi = data.rfind(b"\xff\xd9")
    if sos is None or eoi < sos or data.find(b"\xff\xda", eoi) >= 0:
        raise _fail(path, "JPEG file is truncated (no end-of-image marker after the last scan)")
    h, w, comps, itemsize, marker = size
    progressive = marker in (0xC2, 0xC6, 0xCA, 0xCE)
    return _Layout(h, w, comps, itemsize, peak=3.0 if progressive else 1.0,
                   streamable=marker in (0xC0, 0xC1, 0xC2) and itemsize == 1
                   and comps in (1, 3))


def _check_jpeg_data(path: Path) -> None:
    """Refuse a JPEG whose compressed data ends early or is corrupt.

    libjpeg only *warns* when the entropy-coded data stops before the last block ("premature
    end of data segment": a truncated file with an end marker appended) and decodes the rest
    as flat grey; imagecodecs, OpenCV and Pillow all accept the result.  GDAL's JPEG driver
    turns these warnings into errors (``GDAL_ERROR_ON_LIBJPEG_WARNING``), so the file is
    decoded once through it, in strips of rows, as a check: with GDAL's block cache limited
    to 64 MB (its default, 5 % of the RAM, would keep the decoded rows) and without GDAL's
    500 MB cap on libjpeg's memory, which refuses a valid progressive JPEG above 170 MP
    ("Backing store not supported"; :func:`_check_in_memory` has bounded it already).
    """
    import rasterio
    from rasterio.windows import Window

    # set when the dataset is opened: GDAL sizes libjpeg's memory then
    # GDAL_CACHEMAX in bytes: rasterio.Env hands an integer to GDALSetCacheMax64
    env = dict(GDAL_ERROR_ON_LIBJPEG_WARNING=True, CPL_LOG="/dev/null",
               GDAL_CACHEMAX=64 * 2**20,
               JPEGMEM=f"{IN_MEMORY_MAX_BYTES // 2**20}M")
    with warnings.catch_warnings(), rasterio.Env(**env):
        warnings.simplefilter("ignore")
        try:
            src = rasterio.open(path, driver="JPEG")
        except Exception:  # noqa: BLE001 - not for GDAL to say: the decoder below decides
            return
        with src:
            rows = max(1, (64 * 2**20) // max(1, src.width * src.count))
            try:
                for y in range(0, src.height, rows):
                    src.read(window=Window(0, y, src.width, min(rows, src.height - y)))
            except MemoryError:
                raise
            except Exception as exc:  # noqa: BLE001 - any libjpeg complaint: corrupt data
                cause = exc.__cause__ or exc
                msg = str(cause).splitlines()[0] if str(cause) else type(cause).__name__
                why = msg.split("libjpeg:", 1)[1].strip() if "libjpeg:" in msg else msg
                raise _fail(path, f"JPEG data is truncated or corrupt ({why})") from exc


#: Bands and bytes per sample of what imagecodecs decodes a Pillow mode to (a palette to
#: RGBA, at most).
_PIL_LAYOUT = {"1": (1, 1), "L": (1, 1), "P": (4, 1), "PA": (4, 1), "LA": (2, 1),
               "La": (2, 1), "RGB": (3, 1), "YCbCr": (3, 1), "LAB": (3, 1), "HSV": (3, 1),
               "RGBA": (4, 1), "RGBa": (4, 1), "RGBX": (4, 1), "CMYK": (4, 1), "I": (1, 4),
               "F": (1, 4), "I;16": (1, 2), "I;16L": (1, 2), "I;16B": (1, 2), "I;16N": (1, 2)}

#: Peak memory of imagecodecs' decoder over the decoded bytes (as :func:`_other_layout`
#: counts them), rounded up from ``python -m benchmarks.big_inputs --cases formats``
#: (2000^2 RGB pictures: WebP 2.94, JPEG 2000 2.76 -- 32-bit planes first --, AVIF 1.22,
#: JPEG XL 0.51 of its 16-byte bound, BMP 1.18, GIF 1.16 of its RGBA bound).  Others: 2.
_DECODE_PEAK = {"JPEG2000": 3.0, "WEBP": 3.0, "AVIF": 1.5, "JXL": 1.0}

#: Formats GDAL reads here (the conversion command uses gdal_translate for them).
_GDAL_FORMATS = {"PNG", "JPEG", "WEBP", "JPEG2000", "BMP", "GIF"}

def _jxl_size(data: bytes) -> tuple[int, int] | None:
    """``(height, width)`` from a JPEG XL SizeHeader (bare codestream or ISOBMFF container)."""
    if data.startswith(b"\x00\x00\x00\x0cJXL \r\n\x87\n"):
        i, code = 12, None
        while i + 8 <= len(data) and code is None:
            size, kind = struct.unpack(">I4s", data[i : i + 8])
            head = 8
            if size == 1 and i + 16 <= len(data):
                size, head = struct.unpack(">Q", data[i + 8 : i + 16])[0], 16
            elif size == 0:
                size = len(data) - i
            if kind == b"jxlc":
                code = data[i + head : i + size]
            elif kind == b"jxlp":
                code = data[i + head + 4 : i + size]
            if size < head:
                return None
            i += size
        data = code or b""
    if not data.startswith(b"\xff\x0a") or len(data) < 12:
        return None
    bits = int.from_bytes(data[2:12], "little")
    pos = 0

    def u(n: int) -> int:
        nonlocal pos
        v = (bits >> pos) & ((1 << n) - 1)
        pos += n
        return v

    def u32() -> int:
        return 1 + u((9, 13, 18, 30)[u(2)])

    small = u(1)
    h = 8 * (1 + u(5)) if small else u32()
    ratio = u(3)
    if ratio:
        num, den = ((1, 1), (12, 10), (4, 3), (3, 2), (16, 9), (5, 4), (2, 1))[ratio - 1]
        w = h * num // den
    else:
        w = 8 * (1 + u(5)) if small else u32()
    return h, w


def _other_layout(path: Path, data) -> _Layout:
    """The layout of a WebP, JPEG 2000, AVIF, BMP, GIF, JPEG XL... image, read from its
    header without decoding it (an upper bound on the bytes where the header does not say:
    JPEG 2000 and AVIF samples may be 16-bit, JPEG XL may decode to four float32 bands).

    Raises
    ------
    InputError
        When no header reader knows the format (its size cannot be checked before decoding),
        or the file is an animation (imagecodecs would decode every frame).
    """
    from PIL import Image as PILImage

    old = PILImage.MAX_IMAGE_PIXELS
    PILImage.MAX_IMAGE_PIXELS = None  # the size is checked here, against our own limits
    found = None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with PILImage.open(path) as im:
                w, h = im.size
                found = (im.format, im.mode, bool(getattr(im, "is_animated", False)))
    except Exception:  # noqa: BLE001 - not a format Pillow knows: try the others
        pass
    finally:
        PILImage.MAX_IMAGE_PIXELS = old
    if found is not None:
        name, mode, animated = found
        if animated:
            raise _fail(path, f"{name} file holds several frames (an animation); reblur "
                              "compares single images: save the frame to compare as PNG or TIFF")
        bands, itemsize = (4, 1) if name == "GIF" else _PIL_LAYOUT.get(mode, (4, 4))
        loose = name in ("JPEG2000", "AVIF", "GIF") or mode not in _PIL_LAYOUT
        wide = name in ("JPEG2000", "AVIF") or mode not in _PIL_LAYOUT  # 16-bit samples?
        return _Layout(h, w, bands, max(itemsize, 2) if wide else itemsize, exact=not loose,
                       peak=_DECODE_PEAK.get(name, 2.0), gdal=name in _GDAL_FORMATS)
    size = _jxl_size(bytes(data))
    if size is not None:
        return _Layout(size[0], size[1], 4, 4, exact=False, peak=_DECODE_PEAK["JXL"],
                       gdal=False)
    raise _fail(path, "not an image file (unrecognised format), or a format whose size "
                      "cannot be checked before decoding; convert it to PNG or TIFF")


# ---------------------------------------------------------------------------- readers
def _read_codec(path: Path, fmt: str, max_pixels: int | None, lazy: bool | None) -> Image:
    """Read a PNG, JPEG or other single image: the header's size and decoded bytes checked
    first; a large PNG or JPEG decoded in strips into a temporary store (read window by
    window, :mod:`reblur._decoded`), anything else decoded whole in memory."""
    import mmap

    with open(path, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as data:
        lay = {"png": _png_layout, "jpeg": _jpeg_layout}.get(fmt, _other_layout)(path, data)
        what = f"{fmt.upper()} image" if fmt != "other" else "image"
        _check_shape(path, (lay.height, lay.width), max_pixels)
        nbytes = _check_bytes(path, what, lay, max_pixels)
        if fmt == "png" and b"IEND" not in data[-16:]:
            raise _fail(path, "PNG file is truncated (no IEND chunk at the end)")
        to_disk = lay.streamable and (nbytes > LAZY_BYTES if lazy is None else bool(lazy))
        if not to_disk:
            _check_in_memory(path, what, lay)
        if fmt == "jpeg":
            _check_jpeg_data(path)
        if to_disk:
            return _read_to_disk(path, fmt, lay)
        arr = _decode_whole(path, fmt, data)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    _check_shape(path, arr.shape, max_pixels)
    img = Image(arr, path, fmt)
    return _drop_alpha(img, alpha=arr.ndim == 3 and arr.shape[2] in (2, 4))


def _decode_whole(path: Path, fmt: str, data) -> np.ndarray:
    import imagecodecs

    try:
        if fmt == "png":
            return np.asarray(imagecodecs.png_decode(data))
        if fmt == "jpeg":
            return np.asarray(imagecodecs.jpeg8_decode(data))
        return np.asarray(imagecodecs.imread(bytes(data)))
    except MemoryError:
        raise
    except Exception as exc:  # noqa: BLE001 - every codec failure means the same thing here
        if fmt == "other":
            raise _fail(path, "not an image file (unrecognised format)") from exc
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise _fail(path, f"cannot decode {fmt.upper()} image ({msg})") from exc


def _read_to_disk(path: Path, fmt: str, lay: _Layout) -> Image:
    """A PNG or JPEG decoded once into a temporary zarr store, read window by window."""
    from . import _decoded

    shape = (lay.height, lay.width) + ((lay.bands,) if lay.bands > 1 else ())
    dtype = np.dtype(np.uint16 if lay.itemsize == 2 else np.uint8)
    decode = _decoded.png_to_disk if fmt == "png" else _decoded.jpeg_to_disk
    arr = decode(path, shape, dtype, _fail, convert_command(path))
    img = Image(arr, path, fmt, notes=["decoded once, in strips, into a temporary store"],
                _closer=arr.close)
    return _drop_alpha(img, alpha=lay.bands in (2, 4), opaque=arr.opaque)


def _drop_alpha(img: Image, alpha: bool, opaque: bool | None = None) -> Image:
    """The colour bands of an image with an alpha band; the alpha band becomes its
    validity (transparent pixels hold no data) when it is not all opaque (``opaque``: known
    already, for an image on disk)."""
    if not alpha:
        return img
    keep = img.bands - 1
    if opaque and not isinstance(img.array, np.ndarray):
        arr = LazyBands(img.array, bands=range(keep))
        return replace(img, array=arr, notes=img.notes + ["alpha band dropped (all opaque)"])
    if isinstance(img.array, np.ndarray):
        a = np.ascontiguousarray(img.array[:, :, keep])
        arr = img.array[:, :, :keep]
        arr = arr[:, :, 0] if keep == 1 else arr
        arr = np.ascontiguousarray(arr)
        valid = None if bool((a > 0).all()) else a > 0
    else:
        arr = LazyBands(img.array, bands=range(keep))
        valid = AlphaMask(LazyBands(img.array, bands=(keep,)))
    if valid is None:
        return replace(img, array=arr, notes=img.notes + ["alpha band dropped (all opaque)"])
    return replace(img, array=arr, valid=valid, nodata_source="alpha band",
                   notes=img.notes + ["alpha band: transparent pixels hold no data"])


def _read_geo(path: Path) -> tuple[dict[str, Any] | None, float | None, bool]:
    """Georeferencing (None when there is none), the nodata value and whether the raster
    has an internal (per-dataset) mask, from GDAL through rasterio."""
    import rasterio
    from rasterio.enums import MaskFlags
    from rasterio.errors import NotGeoreferencedWarning

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.Env(CPL_LOG="/dev/null"), rasterio.open(path) as src:
                flags = src.mask_flag_enums[0] if src.count else ()
                internal = (MaskFlags.per_dataset in flags and MaskFlags.alpha not in flags
                            and MaskFlags.nodata not in flags)
                geo = None
                if not (src.crs is None and src.transform.is_identity):
                    geo = dict(crs=src.crs, transform=src.transform, nodata=src.nodata)
                return geo, src.nodata, bool(internal)
    except Exception:  # noqa: BLE001 - no usable georeferencing is not an error
        return None, None, False


def _with_file_mask(img: Image, nodata: float | None, internal: bool) -> Image:
    """``img`` with the validity its file declares (alpha first, then nodata, then an
    internal mask)."""
    if img.valid is not None:
        return img
    if nodata is not None:
        return replace(img, valid=NodataMask(img.array, nodata),
                       nodata_source=f"nodata {_fmt_value(float(nodata))} (file)")
    if internal and img.path is not None:
        return replace(img, valid=RasterMask(img.path, img.shape[:2]),
                       nodata_source="internal mask (file)")
    return img


def _read_tiff(path: Path, max_pixels: int, lazy: bool | None) -> Image:
    """Open a TIFF (:func:`_open_tiff`), tifffile's own log lines kept off the terminal: what
    it logged goes into the error message when the file is refused."""
    with _tifffile_quiet() as logged:
        try:
            return _open_tiff(path, max_pixels, lazy, logged)
        except InputError as exc:
            said = logged()
            if not said or "tifffile:" in str(exc):
                raise
            raise InputError(f"{exc} (tifffile: {_one(said[0])})") from exc.__cause__


def _one(text: str) -> str:
    return " ".join(str(text).split())


def _check_tiff_codec(path: Path, page) -> None:
    """Refuse a TIFF whose compression this installation cannot decode (an unknown code, or
    a codec imagecodecs lacks), at open time rather than when the first tile is read."""
    import tifffile

    comp = page.compression
    if int(comp) == 1:
        return
    name = getattr(comp, "name", str(int(comp)))
    try:
        tifffile.TIFF.DECOMPRESSORS[comp]
    except Exception as exc:  # noqa: BLE001 - unknown code or missing codec
        why = _first_line(exc).strip("'\"")
        raise _fail(path, f"TIFF compression {name} cannot be decoded ({why})") from exc


def _open_tiff(path: Path, max_pixels: int, lazy: bool | None,
               logged: Callable[[], list[str]]) -> Image:
    import tifffile

    try:
        tif = tifffile.TiffFile(path)
    except Exception as exc:  # noqa: BLE001
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise _fail(path, f"not a readable TIFF file ({msg})") from exc
    try:
        if not tif.series:
            raise _fail(path, "TIFF file holds no image")
        series = tif.series[0]
        axes = series.axes
        shape = tuple(int(s) for s in series.shape)
        page = series.pages[0] if series.pages else tif.pages[0]
        if page is None:
            raise _fail(path, "TIFF file holds no image")
        layout = _tiff_layout(axes, shape)
        if layout is None:
            raise _fail(path, f"unsupported TIFF layout (axes {axes}, shape {shape})")
        ax, channel_first, bands = layout
        squeezed = [(a, n) for a, n in zip(axes, shape, strict=True) if n > 1 or a in "YX"]
        hw = (shape[axes.index("Y")], shape[axes.index("X")])
        _check_shape(path, hw + ((bands,) if bands > 1 else ()), max_pixels)
        dtype = np.dtype(series.dtype)
        _check_dtype(path, dtype)
        lay = _Layout(hw[0], hw[1], bands, dtype.itemsize)
        nbytes = _check_bytes(path, "TIFF image", lay, max_pixels)
        if int(page.photometric) == 3:  # palette
            raise _fail(path, "palette (indexed colour) TIFF images are not supported")
        _check_tiff_codec(path, page)
        said = [m for m in logged() if "ByteCounts" in m or "data offset" in m]
        if said:
            raise _fail(path, "TIFF header is corrupt: the image's tile or strip table is "
                              f"missing or invalid (tifffile: {_one(said[0])})")
        # truncated file: every segment of the image must lie inside the file
        size = os.path.getsize(path)
        for p in series.pages:
            offs = np.asarray(getattr(p, "dataoffsets", ()) or (), dtype=np.int64)
            cnts = np.asarray(getattr(p, "databytecounts", ()) or (), dtype=np.int64)
            if offs.size and (offs + cnts).max() > size:
                raise _fail(path, "TIFF file is truncated (image data runs past the end of file)")
            if offs.size != cnts.size or (cnts.size and (cnts <= 0).any()):
                # libtiff and tifffile read such a tile or strip as zeros
                n = int((cnts <= 0).sum())
                raise _fail(path, f"TIFF image lacks data for {n:,} of its {cnts.size:,} tiles "
                                  "or strips (offset or byte count 0): missing data would read "
                                  "as zeros")
        extrasamples = tuple(getattr(page, "extrasamples", ()) or ())
        alpha = bands in (2, 4) and bool(extrasamples) and extrasamples[-1] in (1, 2)
        if lazy is None:
            lazy = nbytes > LAZY_BYTES
        if not lazy:
            _check_in_memory(path, "TIFF image", lay)
            try:
                # every CPU decodes tiles or strips (tifffile's default: half of them, one
                # on two cores); the same pixels. `python -m benchmarks.cost`: opening the
                # 100 MP pairs 0.73-1.02 -> 0.44-0.54 s
                arr = series.asarray(maxworkers=available_cpus())
            except Exception as exc:  # noqa: BLE001
                msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise _fail(path, f"cannot decode TIFF image data ({msg})") from exc
            arr = arr.reshape([n for _, n in squeezed])
            if channel_first:
                arr = np.ascontiguousarray(np.moveaxis(arr, 0, -1))
            tif.close()
            img = Image(arr, path, "tiff")
        else:
            arr, chunks = _tiff_view(series, layout, path)
            kind = "tiles" if page.is_tiled else "strips"
            _check_chunk_bytes(path, chunks, dtype, f"TIFF image stored in {kind}",
                               f"rewrite it in tiles first: {convert_command(path)}")
            if tiff_has_levels(series):
                arr.file_levels = tiff_levels(path)
            if not channel_first and _TiffChunks.supports(series):
                arr.chunk_reader = _TiffChunks(path, series, 0)  # whole-image passes
            _check_first_window(path, arr)
            img = Image(arr, path, "tiff", _closer=tif.close)
    except InputError:
        tif.close()
        raise
    except Exception as exc:  # noqa: BLE001
        tif.close()
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise _fail(path, f"cannot read TIFF file ({msg})") from exc
    img.geo, nodata, internal = _read_geo(path)
    return _with_file_mask(_drop_alpha(img, alpha), nodata, internal)


def _tiff_layout(axes: str, shape: tuple[int, ...]) -> tuple[str, bool, int] | None:
    """The canonical layout of a TIFF series -- YX, YXS (chunky), SYX / CYX / IYX / QYX
    (planar or page stack) once length-1 axes are dropped -- as (those axes, channel
    first, bands), or None for another layout."""
    squeezed = [(a, n) for a, n in zip(axes, shape, strict=True) if n > 1 or a in "YX"]
    ax = "".join(a for a, _ in squeezed)
    if ax == "YX":
        return ax, False, 1
    if len(ax) == 3 and ax[:2] == "YX":
        return ax, False, squeezed[2][1]
    if len(ax) == 3 and ax[1:] == "YX":
        return ax, True, squeezed[0][1]
    return None


def _tiff_view(series, layout: tuple[str, bool, int], path: Path,
               level: int = 0) -> tuple[_Guarded, tuple[int, ...]]:
    """A lazy channel-last reader of a tifffile series' ``level`` (0: the image itself)
    of the ``layout`` :func:`_tiff_layout` found, its failures one-line
    :class:`InputError` s; and the file's chunks (tiles or strips, all axes)."""
    import zarr

    lv = series.levels[level] if level else series
    axes, shape = lv.axes, tuple(int(s) for s in lv.shape)
    ax, channel_first, _ = layout
    z = zarr.open(series.aszarr(level=level), mode="r")
    chunks = tuple(int(c) for c in z.chunks)
    if len(z.shape) != len(ax):
        z = _Squeezed(z, axes, shape)
    return _Guarded(LazyBands(z, channel_first=True) if channel_first else z, path), chunks


class _TiffChunks:
    """Every chunk (tile or strip) of a TIFF image, decoded, with its place: what a pass
    over the whole image (:func:`reblur.align.overviews.read_block_means`) reads, in any
    order, without a window reader's copies.

    Through the zarr view of a lazy TIFF, each chunk is decoded then copied into a fresh
    window buffer (first-touch pages): the overviews of the 100 MP 16-bit RGB cost pair
    took 0.8-1.4 s per image that way, the decoding of its 400 tiles 0.2 s, the block
    sums from the chunks 0.45-0.6 s (``python -m benchmarks.align_cost``'s ``5% rgb16``:
    its alignment 3.43-3.53 -> 2.32-2.36 s).  Only for a single page of one image plane
    (chunky samples), the image's own level.

    Parameters
    ----------
    path : Path
        The TIFF file (opened again by each pass, so passes never share a file handle).
    series : tifffile.TiffPageSeries
        Its image series, as opened (:meth:`supports` it).
    index : int
        The series' index in the file.
    """

    def __init__(self, path: Path, series, index: int = 0):
        self.path = path
        self.index = index
        page = series.pages[0]
        #: ``(H, W, C, dtype)`` of the page when opened (a pass checks the file still has it)
        self.layout = (int(page.imagelength), int(page.imagewidth),
                       int(page.samplesperpixel), np.dtype(page.dtype))

    @staticmethod
    def supports(series) -> bool:
        """Whether the chunks of ``series`` (a tifffile series) are whole pixels of one
        page: one page, one plane (chunky samples or one sample), no depth, integer
        samples of 8, 16 or 32 bits (the chunks' values are then the window reader's)."""
        pages = series.pages
        if len(pages) != 1 or pages[0] is None:
            return False
        page = pages[0]
        dt = np.dtype(page.dtype)
        return (int(getattr(page, "imagedepth", 1)) == 1
                and (int(page.samplesperpixel) == 1 or int(page.planarconfig) == 1)
                and dt.kind in "ui" and int(page.bitspersample) == 8 * dt.itemsize)

    def __call__(self, workers: int, func: Callable[[int, int, np.ndarray], Any]
                 ) -> Iterator[Any]:
        """``func(y0, x0, chunk)`` for every chunk, computed in the ``workers`` threads
        that decode; ``chunk`` is ``(h, w, C)``, cropped to the
        image (edge tiles are padded in the file).  A chunk that fails to decode raises one
        :class:`InputError` naming the file and the chunk's rows and columns."""
        import tifffile

        H, W, C, _ = self.layout

        def place(result) -> Any:
            seg, index, shape = result
            if seg is None:  # a chunk without data would read as zeros
                raise ValueError("a tile or strip has no data")
            y0, x0 = int(index[2]), int(index[3])
            a = seg.reshape(int(shape[1]), int(shape[2]), C)[: H - y0, : W - x0]
            return func(y0, x0, a)

        try:
            with _tifffile_quiet(), tifffile.TiffFile(self.path) as tif:
                page = self._page(tif)
                yield from page.segments(maxworkers=max(1, int(workers)), func=place)
        except (InputError, MemoryError):
            raise
        except Exception as exc:  # noqa: BLE001 - every read failure means a corrupt file
            raise _undecodable(self.path, self._broken(), exc) from exc

    def _page(self, tif):
        """The image's page in the open file ``tif``, which must still be the one opened."""
        page = tif.series[self.index].pages[0]
        got = (int(page.imagelength), int(page.imagewidth), int(page.samplesperpixel),
               np.dtype(page.dtype))
        if got != self.layout:
            raise ValueError(f"the file changed since it was opened: {got[0]}x{got[1]}x"
                             f"{got[2]} {got[3]}, was {self.layout[0]}x{self.layout[1]}x"
                             f"{self.layout[2]} {self.layout[3]}")
        return page

    def _broken(self) -> str:
        """`` at rows a-b, columns c-d`` of the first chunk that fails to decode, found by
        decoding them one by one (after a pass failed); empty when none fails."""
        import tifffile

        H, W = self.layout[:2]
        try:
            with _tifffile_quiet(), tifffile.TiffFile(self.path) as tif:
                page = self._page(tif)
                rows, cols = ((int(page.tilelength), int(page.tilewidth)) if page.is_tiled
                              else (int(page.rowsperstrip), W))
                across = -(-W // cols)
                chunks = page.segments(maxworkers=1)  # in the chunks' order
                i = 0
                while True:
                    try:
                        ok = next(chunks)[0] is not None
                    except StopIteration:
                        return ""
                    except Exception:  # noqa: BLE001 - the broken chunk
                        ok = False
                    if not ok:
                        y0, x0 = (i // across) * rows, (i % across) * cols
                        return _where((slice(y0, min(y0 + rows, H)),
                                       slice(x0, min(x0 + cols, W))), (H, W))
                    i += 1
        except Exception:  # noqa: BLE001 - the file itself is unreadable now
            return ""


class _Squeezed:
    """Drop length-1 non-spatial axes of a lazy array (e.g. a ``(1, H, W)`` page stack)."""

    def __init__(self, source, axes: str, shape: tuple[int, ...]):
        self.source = source
        self._keep = [i for i, (a, n) in enumerate(zip(axes, shape, strict=True))
                      if n > 1 or a in "YX"]
        self.shape = tuple(shape[i] for i in self._keep)
        self.dtype = source.dtype
        self.ndim = len(self.shape)
        self.chunks = tuple(source.chunks[i] for i in self._keep)

    def __getitem__(self, key):
        if not isinstance(key, tuple):
            key = (key,)
        key = key + (slice(None),) * (self.ndim - len(key))
        full: list[Any] = [0] * len(self.source.shape)
        for i, k in zip(self._keep, key, strict=True):
            full[i] = k
        return np.asarray(self.source[tuple(full)])


def _read_zarr(path: Path, max_pixels: int, lazy: bool | None) -> Image:
    import zarr

    try:
        node = zarr.open(str(path), mode="r")
    except Exception as exc:  # noqa: BLE001
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise _fail(path, f"not a readable zarr store ({msg})") from exc
    levels = None
    if not hasattr(node, "shape"):
        names = sorted(k for k, v in node.members() if hasattr(v, "shape"))
        if "0" in names:
            base = "0"
        elif len(names) == 1:
            base = names[0]
        else:
            raise _fail(path, f"zarr group holds {len(names)} arrays; expected one (or '0')")
        datasets = zarr_multiscales(node)
        if datasets and datasets[0]["path"] == base:
            levels = zarr_levels(path, base)
        node = node[base]
    stored = node
    shape = tuple(int(s) for s in node.shape)
    if len(shape) == 3 and shape[2] == 1:
        node = LazyBands(node, bands=(0,))
        shape = shape[:2]
    _check_shape(path, shape, max_pixels)
    dtype = np.dtype(node.dtype)
    _check_dtype(path, dtype)
    lay = _Layout(shape[0], shape[1], int(np.prod(shape[2:], dtype=np.int64)), dtype.itemsize)
    nbytes = _check_bytes(path, "zarr array", lay, max_pixels)
    _check_zarr_chunks(path, stored)
    if lazy is None:
        lazy = nbytes > LAZY_BYTES
    nodata = _zarr_nodata(node)
    if lazy:
        _check_chunk_bytes(path, node.chunks, dtype, "zarr array stored in chunks",
                           "rechunk it to tiles of at most 4096 x 4096 pixels")
        arr = _Guarded(node, path)
        arr.file_levels = levels
        _check_first_window(path, arr)
        return _with_file_mask(Image(arr, path, "zarr"), nodata, False)
    _check_in_memory(path, "zarr array", lay)
    try:
        arr = np.asarray(node[...])
    except MemoryError:
        raise
    except Exception as exc:  # noqa: BLE001 - any codec or store failure means corrupt data
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise _fail(path, f"cannot decode zarr chunk data ({msg})") from exc
    return _with_file_mask(Image(arr, path, "zarr"), nodata, False)


def _zarr_nodata(node) -> float | None:
    """The no-data value a zarr array declares in its attributes (``nodata``, or the CF /
    xarray ``_FillValue``), or None.  zarr's own ``fill_value`` is not one: it is what an
    unwritten chunk reads as (refused by :func:`_check_zarr_chunks`), and 0 by default."""
    attrs = getattr(node, "attrs", {}) or {}
    for key in ("nodata", "_FillValue"):
        if key in attrs and attrs[key] is not None:
            try:
                return float(attrs[key])
            except (TypeError, ValueError):
                return None
    return None


def _check_zarr_chunks(path: Path, node) -> None:
    """Refuse a zarr array some of whose chunks were never written (or were deleted).

    zarr reads a missing chunk as the array's fill value, which would pass for image content
    (a flat area hiding real changes), so every chunk must be present in the store.
    """
    try:
        total, written = int(node.nchunks), int(node.nchunks_initialized)
    except Exception as exc:  # noqa: BLE001 - an unlistable store is an unreadable one
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise _fail(path, f"cannot list the chunks of the zarr store ({msg})") from exc
    if written < total:
        raise _fail(
            path,
            f"zarr store lacks {total - written:,} of its {total:,} chunks (missing or never "
            f"written; they would read as the fill value {node.fill_value}, not as image "
            "data); write every chunk (zarr: write_empty_chunks=True)",
        )


def _sniff(path: Path) -> str:
    if path.is_dir():
        return "zarr"
    with open(path, "rb") as fh:
        head = fh.read(16)
    if head.startswith(_PNG_MAGIC):
        return "png"
    if head.startswith(b"\xff\xd8"):
        return "jpeg"
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return "tiff"
    return "other"


def open_image(
    path: str | os.PathLike,
    *,
    max_pixels: int | None = DEFAULT_MAX_PIXELS,
    lazy: bool | None = None,
    check_values: bool = True,
    rescale: bool = True,
    nodata: float | None = None,
) -> Image:
    """Open an image file or zarr store for change detection.

    Parameters
    ----------
    path : str or path-like
        PNG, JPEG, TIFF/BigTIFF/GeoTIFF (striped or tiled), a zarr array directory, or
        any other format imagecodecs decodes.  The format is recognised from the content.
    max_pixels : int or None
        Refuse images with more than this many pixels (``height * width``), or more than
        :data:`BYTES_PER_PIXEL` times as many decoded bytes; checked from the header before
        decoding.  Default :data:`DEFAULT_MAX_PIXELS`; ``None`` = no limit.
    lazy : bool, optional
        Keep the pixels on disk: TIFF and zarr read window by window; PNG (8/16-bit, not
        interlaced, no palette or ``tRNS``) and JPEG (8-bit, 1 or 3 components) decoded
        once, in strips, into a temporary zarr store (removed by :meth:`Image.close`, when
        the image is garbage-collected or at exit; ``TMPDIR`` says where).  Default: when
        the pixels take more than :data:`LAZY_BYTES`.  Other formats are decoded into
        memory.
    check_values : bool
        Scan float images for NaN/Inf (streamed for lazy images).
    rescale : bool
        Give 32- and 64-bit integer images as float32 in [0, 1], mapped from the range of
        values they hold (not their type's; see :func:`_rescale_wide`).  8- and 16-bit
        images keep their dtype.
    nodata : float, optional
        Pixels whose every band equals this value (NaN: any band not finite) hold no data
        (:meth:`Image.with_nodata`), replacing what the file declares.  Otherwise the file
        says: a GeoTIFF's nodata value or internal mask, an alpha band, a zarr array's
        ``nodata`` / ``_FillValue`` attribute.  :attr:`Image.valid` holds the result.

    Returns
    -------
    Image
        ``array`` is ``(H, W)`` or ``(H, W, C)``, channel last, alpha dropped, in the
        file's own dtype (16-bit data stays 16-bit).

    Raises
    ------
    InputError
        One-line message naming the file and the problem: missing, unreadable, truncated,
        not an image, too small (< :data:`MIN_SIDE` px on a side), more than ``max_pixels``
        pixels or their decoded bytes, too large to decode whole or in its chunks,
        unsupported layout or pixel type, NaN/Inf pixels, no space left for a temporary
        store.
    """
    p = Path(path)
    try:
        os.stat(p)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise _fail(p, "symlink loop: the path cannot be resolved") from None
        if exc.errno == errno.ENAMETOOLONG:
            raise _fail(p, "file name too long") from None
    if not p.exists():
        raise _fail(p, "no such file")
    if p.is_dir() and not (
        (p / "zarr.json").exists() or (p / ".zarray").exists() or (p / ".zgroup").exists()
    ):
        raise _fail(p, "is a directory, not an image (or a zarr store)")
    if not p.is_dir() and p.stat().st_size == 0:
        raise _fail(p, "file is empty")
    if not os.access(p, os.R_OK):
        raise _fail(p, "file is not readable (permission denied)")
    limit = max_pixels if max_pixels is not None else None
    try:
        fmt = _sniff(p)
        if fmt == "tiff":
            img = _read_tiff(p, limit, lazy)
        elif fmt == "zarr":
            img = _read_zarr(p, limit, lazy)
        elif fmt in ("png", "jpeg"):
            img = _read_codec(p, fmt, limit, lazy)
        else:
            if p.stat().st_size > 256 * 2**20:
                raise _fail(p, "unrecognised image format")
            img = _read_codec(p, "other", limit, lazy)
    except InputError:
        raise
    except MemoryError as exc:
        raise _fail(p, "not enough memory to read the image") from exc
    except OSError as exc:
        raise _fail(p, f"cannot read file ({exc.strerror or exc})") from exc
    _check_dtype(p, img.dtype)
    if img.dtype == np.bool_:
        img.array = img.array.astype(np.uint8) if not img.lazy else img.array
    if nodata is not None:
        img = img.with_nodata(nodata)
    if check_values:
        check_finite(img, nan_is_nodata=_nan_nodata(img))
    if rescale and img.dtype.kind in "iu" and img.dtype.itemsize >= 4:
        img = _rescale_wide(img)
    return img


class _Rescaled:
    """Lazy float32 view ``(source - lo) / (hi - lo)`` of an on-disk integer image."""

    def __init__(self, source, lo: float, hi: float):
        self.source = source
        self.lo, self.hi = float(lo), float(hi)
        self.shape = tuple(int(v) for v in source.shape)
        self.ndim = len(self.shape)
        self.dtype = np.dtype(np.float32)
        self.chunks = getattr(source, "chunks", None)
        self.size = int(np.prod(self.shape))
        self.nbytes = 4 * self.size

    def __len__(self) -> int:
        return self.shape[0]

    @property
    def file_levels(self) -> FileLevels | None:
        """The source file's reduced-resolution levels, rescaled the same way."""
        fl = getattr(self.source, "file_levels", None)
        return None if fl is None else fl.map(functools.partial(_Rescaled, lo=self.lo,
                                                                hi=self.hi))

    def __getitem__(self, key) -> np.ndarray:
        a = np.asarray(self.source[key], dtype=np.float64)
        return ((a - self.lo) / (self.hi - self.lo)).astype(np.float32)

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        a = self[...]
        return a if dtype is None else a.astype(dtype, copy=False)


def _rescale_wide(img: Image) -> Image:
    """A 32- or 64-bit integer image as float32 in [0, 1], from the range its data use.

    Intensities are otherwise taken relative to the dtype's full range (255 for uint8,
    65535 for uint16), which is right for the 8- and 16-bit types cameras write; data stored
    as int32 / int64 / uint32 / uint64 hardly ever spans its type (a 0-255 image as int64
    would be 28 nano-units of the range, and every later test -- texture, noise, the l1
    weight -- would find it flat).  A constant image is left as it is.
    """
    arr = img.array
    lo, hi = np.inf, -np.inf
    for rows in _row_bands(arr):
        block = np.asarray(arr[rows])
        if img.valid is not None:  # the range of the data, not of the no-data value
            block = block[np.asarray(img.valid[rows, :], bool)]
        if block.size:
            lo, hi = min(lo, float(block.min())), max(hi, float(block.max()))
    if not hi > lo:
        return img
    if isinstance(arr, np.ndarray):
        out = ((arr.astype(np.float64) - lo) / (hi - lo)).astype(np.float32)
    else:
        out = _Rescaled(arr, lo, hi)
    note = (f"{img.dtype} data rescaled from the range they use, [{lo:.15g}, {hi:.15g}], "
            "to float32 in [0, 1]")
    return replace(img, array=out, notes=img.notes + [note])


def read_mask(
    path: str | os.PathLike,
    shape: tuple[int, int] | None = None,
    *,
    max_pixels: int | None = DEFAULT_MAX_PIXELS,
    what: str = "mask",
) -> np.ndarray:
    """Read a binary mask: True where any band is non-zero.

    Parameters
    ----------
    path : str or path-like
        Any image :func:`open_image` reads (0/255 PNG, 0/1 TIFF, ...).
    shape : (int, int), optional
        Required ``(H, W)``; an :class:`InputError` is raised when it differs.
    what : str
        Word for the mask in error messages (``"truth mask"``, ...).
    """
    img = open_image(path, max_pixels=max_pixels, rescale=False)
    if shape is not None and tuple(img.shape[:2]) != tuple(shape[:2]):
        raise _fail(
            img.path,
            f"{what} is {img.width}x{img.height} pixels, the image it describes is "
            f"{shape[1]}x{shape[0]}",
        )
    out = np.zeros(img.shape[:2], dtype=bool)
    for rows in _row_bands(img.array):
        block = np.asarray(img.array[rows]) != 0
        out[rows] = any_bands(block)
    img.close()
    return out


#: :func:`check_sizes` refuses a pair whose sides differ by this factor or more: alignment
#: finds views within a factor 2 of each other's scale (the benchmark's 4000 px reference
#: and its 2000 px reduction align and flag nothing) and none at a factor 4 (its features
#: and gradient blocks no longer match), where it used to report "textureless".
MAX_SIZE_RATIO = 4.0


def check_sizes(reference: Image, observed: Image) -> None:
    """Refuse a pair whose sizes are too far apart for one to be a view of the other.

    reblur compares two views of one scene at about the same scale and extent: the
    observation is aligned to the reference (a similarity) and blurred poses are sought
    around that.  A side ratio of :data:`MAX_SIZE_RATIO` or more (a 100x100 observation of a
    4000x4000 reference: a thumbnail, or a small crop) cannot be aligned; saying so beats
    the alignment's "textureless" or "too few features".

    Raises
    ------
    InputError
        Naming both files, their sizes and the factor.
    """
    (hr, wr), (ho, wo) = reference.shape[:2], observed.shape[:2]
    ratio = max(hr / ho, ho / hr, wr / wo, wo / wr)
    if ratio >= MAX_SIZE_RATIO:
        raise InputError(
            f"the sizes of {display_path(observed.name)} ({wo}x{ho}) and "
            f"{display_path(reference.name)} ({wr}x{hr}) disagree by a factor of "
            f"{ratio:.3g}: the observation is not a view of the reference at a compatible "
            f"scale and extent (reblur compares views within a factor {MAX_SIZE_RATIO:g} of "
            "each other's size); resample or crop one to match the other"
        )


def reconcile_bands(reference: Image, observed: Image) -> tuple[Image, Image]:
    """Bring the reference and the observation to the same band count.

    Same count: unchanged.  One RGB (3 bands) and one gray: the RGB image is converted to
    gray luminance (Rec. 709 weights :data:`LUMINANCE`, dtype kept).  Alpha bands were
    already dropped by :func:`open_image`.

    Raises
    ------
    InputError
        Any other combination (e.g. 4-band multispectral against RGB), naming both files.
    """
    a, b = reference.bands, observed.bands
    if a == b:
        return reference, observed
    if {a, b} == {1, 3}:
        if a == 3:
            return _to_gray(reference), observed
        return reference, _to_gray(observed)
    raise InputError(
        f"{display_path(reference.name)} has {a} band{'s' * (a != 1)} and "
        f"{display_path(observed.name)} has {b}: "
        "band counts cannot be reconciled (only RGB vs gray is converted; alpha is dropped)"
    )


def _to_gray(img: Image) -> Image:
    if isinstance(img.array, np.ndarray):
        arr = _luminance(img.array)
    else:
        arr = LazyBands(img.array, luminance=True)
    return replace(img, array=arr, notes=img.notes + ["converted RGB to gray luminance"])


# ---------------------------------------------------------------------------- writers
@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success rename it onto ``path``.

    The temporary name keeps the suffix (writers that infer the format from it still work)
    and lives in the same directory, so the final ``os.replace`` is atomic.  On error the
    temporary file is removed and ``path`` is left untouched.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> with atomic_path(d / "a.txt") as tmp:
    ...     _ = tmp.write_text("done")
    >>> (d / "a.txt").read_text()
    'done'
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}",
                               dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def scratch_compressors(dtype) -> list[Any]:
    """The codec of reblur's temporary zarr stores (decoded inputs, the reblurred reference
    and the masks of a large run, arrays spilled for Dask workers): LZ4 through Blosc at
    level 1, byte-shuffled for multi-byte types.

    zarr's default (zstd, level 3) packs a 16-bit RGB reblurred reference a few per cent
    tighter for several times the CPU, writing and reading; these stores live for one run
    and are read several times (100 MP ``5% rgb16``, ``python -m benchmarks.cost``
    alternated with ``--src``: CPU 108-111 -> 102-103 s with the in-place steps of the
    same commit).  Lossless: the values read back are those written.
    """
    from zarr.codecs import BloscCodec

    shuffle = "shuffle" if np.dtype(dtype).itemsize > 1 else "noshuffle"
    return [BloscCodec(cname="lz4", clevel=1, shuffle=shuffle)]


def zarr_masks(
    directory: str | os.PathLike, shape: tuple[int, int], chunk: int,
    names: Sequence[str] = ("change", "unknown"),
) -> list[Any]:
    """New full-size bool zarr arrays on disk (one per name), chunked ``chunk`` x ``chunk``.

    For masks too large to hold in memory: tile writers (thread or Dask workers) fill them
    chunk by chunk and the report writers read them back tile by tile.
    """
    import zarr

    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    return [
        zarr.create_array(str(d / n), shape=tuple(int(v) for v in shape), chunks=(chunk, chunk),
                          dtype=bool, fill_value=False, overwrite=True,
                          compressors=scratch_compressors(bool))
        for n in names
    ]


def encode_png(array: np.ndarray, *, compression: int = 6, flat: bool = False) -> bytes:
    """A uint8/uint16 (or bool, as 0/255) gray, RGB or RGBA image as the bytes of a PNG.

    Parameters
    ----------
    array : ndarray
        ``(H, W)``, ``(H, W, 1)``, ``(H, W, 3)`` RGB or ``(H, W, 4)`` RGBA.
    compression : int
        zlib level, 0-9.
    flat : bool
        The image is made of few flat colours (a mask): deflate in run-length mode, which
        codes runs of a repeated byte.  A gray image goes unfiltered (its pixels are the
        bytes); a colour one with the Sub filter of every row, which turns a pixel equal to
        its left neighbour into zero bytes (unfiltered, a flat RGBA colour repeats with a
        4-byte period that run-length mode cannot code: a blank 512 px tile takes 100
        times the bytes).  Masks encode 2-5 times faster than with the default filters
        and strategy, about as small (``python -m benchmarks.png_masks``); a
        photograph would compress badly.  Either way the PNG holds the same pixels in the
        same type.

    Returns
    -------
    bytes
        The encoding is deterministic: the same array and options always give the same
        bytes.
    """
    import cv2

    a = np.asarray(array)
    if a.dtype == np.bool_:
        a = a.astype(np.uint8) * 255
    if a.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"PNG holds uint8 or uint16 pixels, got {a.dtype}")
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim == 3:  # OpenCV's channel order, by its own swap (numpy's copies are slower)
        if a.shape[2] == 3:
            a = cv2.cvtColor(np.ascontiguousarray(a), cv2.COLOR_RGB2BGR)
        elif a.shape[2] == 4:
            a = cv2.cvtColor(np.ascontiguousarray(a), cv2.COLOR_RGBA2BGRA)
        else:
            raise ValueError(f"PNG holds 1, 3 or 4 bands, got {a.shape[2]}")
    params = [cv2.IMWRITE_PNG_COMPRESSION, int(compression)]
    if flat:  # after the level, which resets the strategy
        row_filter = cv2.IMWRITE_PNG_FILTER_NONE if a.ndim == 2 else cv2.IMWRITE_PNG_FILTER_SUB
        params += [cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE,
                   cv2.IMWRITE_PNG_FILTER, row_filter]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(a), params)
    if not ok:
        raise OSError("PNG encoding failed")
    return buf.tobytes()


def write_png(path: str | os.PathLike, array: np.ndarray, *, compression: int = 6,
              flat: bool = False) -> Path:
    """Write a uint8/uint16 (or bool, as 0/255) gray, RGB or RGBA image as PNG, atomically
    (:func:`encode_png`; ``flat`` for masks).

    The encoding is deterministic: the same array always gives the same bytes.
    """
    try:
        data = encode_png(array, compression=compression, flat=flat)
    except OSError as exc:
        raise OSError(f"{path}: {exc}") from exc
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


#: Bytes of deflate output gathered into one IDAT chunk by :func:`write_png_bands`.
_IDAT_BYTES = 2**20


def write_png_bands(path: str | os.PathLike, shape: tuple[int, int],
                    bands: Iterable[np.ndarray], *, compression: int = 1) -> Path:
    """Write an 8-bit gray mask as PNG band by band, atomically: memory for one band, not
    the image (OpenCV encodes whole arrays only: a 1 Gpx ``changes.png`` held 1 GB).

    Parameters
    ----------
    path : path-like
    shape : (H, W)
    bands : iterable of uint8 (h, W) arrays
        The rows from top to bottom; their heights add up to ``H``.
    compression : int
        zlib level, 0-9 (in run-length mode levels 1 and 6 gave a 100 MP mask the same
        size in about the same time: ``python -m benchmarks.png_masks``).

    Returns
    -------
    Path

    Notes
    -----
    The PNG holds the rows :func:`encode_png` makes of the same mask with ``flat``: rows
    without filter, deflate in run-length mode (a mask's runs of 0 and 255), in IDAT chunks
    of about a megabyte.  Deterministic: the same bands give the same bytes.
    """
    H, W = (int(v) for v in shape)
    if not (0 < H < 2**31 and 0 < W < 2**31):
        raise ValueError(f"a PNG is 1 to 2^31 - 1 pixels a side, got {W}x{H}")

    def chunk(f, kind: bytes, data: bytes) -> None:
        f.write(struct.pack(">I", len(data)) + kind + data)
        f.write(struct.pack(">I", zlib.crc32(data, zlib.crc32(kind)) & 0xFFFFFFFF))

    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n")
        chunk(f, b"IHDR", struct.pack(">IIBBBBB", W, H, 8, 0, 0, 0, 0))
        z = zlib.compressobj(int(compression), zlib.DEFLATED, 15, 9, zlib.Z_RLE)
        out, rows = bytearray(), 0
        raw = np.zeros((0, W + 1), np.uint8)  # per row: filter type 0, then the pixels
        for band in bands:
            b = np.asarray(band)
            if b.dtype != np.uint8 or b.ndim != 2 or b.shape[1] != W or rows + len(b) > H:
                raise ValueError(f"band of {b.dtype} {b.shape} at row {rows} does not fit a "
                                 f"{W}x{H} 8-bit gray PNG")
            if len(raw) < len(b):
                raw = np.zeros((len(b), W + 1), np.uint8)
            raw[: len(b), 1:] = b
            out += z.compress(raw[: len(b)])
            rows += b.shape[0]
            if len(out) >= _IDAT_BYTES:
                chunk(f, b"IDAT", bytes(out))
                out.clear()
        if rows != H:
            raise ValueError(f"the bands hold {rows} rows, the PNG {H}")
        out += z.flush()
        chunk(f, b"IDAT", bytes(out))
        chunk(f, b"IEND", b"")
    return path


def _tiles_of(array, tile: tuple[int, int], convert: Callable | None) -> Iterator[np.ndarray]:
    """Full-size (edge-padded with zeros) tiles of an array-like, row-major."""
    th, tw = tile
    for ys, xs in iter_windows(array.shape, tile):
        block = np.asarray(array[ys, xs])
        if convert is not None:
            block = convert(block)
        if block.shape[:2] != (th, tw):
            pad = np.zeros((th, tw) + block.shape[2:], dtype=block.dtype)
            pad[: block.shape[0], : block.shape[1]] = block
            block = pad
        yield block


def write_tiff(
    path: str | os.PathLike,
    data,
    *,
    shape: tuple[int, ...] | None = None,
    dtype=None,
    tiled: bool = True,
    tile: int = 512,
    compression: str | None = "deflate",
    bigtiff: bool | None = None,
    georef: dict[str, Any] | None = None,
    convert: Callable[[np.ndarray], np.ndarray] | None = None,
) -> Path:
    """Write an image as a (tiled) TIFF, atomically, without holding it whole in memory.

    Parameters
    ----------
    path : str or path-like
        Destination.
    data : ndarray, array-like, or iterable of tiles
        An array ``(H, W)`` / ``(H, W, C)`` (numpy or lazy: read tile by tile), or an
        iterator yielding ``tile x tile`` blocks in row-major order (edge tiles padded to
        full size); then ``shape`` and ``dtype`` are required and ``tiled`` must be True.
    shape, dtype
        Image shape and pixel type when ``data`` is an iterator.
    tiled : bool
        Tiled layout (default) or strips.
    tile : int
        Tile side (multiple of 16).
    compression : str or None
        ``"deflate"`` (default, readable everywhere), ``"zstd"`` (faster, GDAL >= 2.3,
        tifffile) or ``None``.
    bigtiff : bool, optional
        Default: BigTIFF when the uncompressed data exceeds 3.5 GB.
    georef : dict, optional
        ``crs`` and ``transform`` (as :attr:`Image.geo`): write a GeoTIFF via
        :func:`write_geotiff`.
    convert : callable, optional
        Applied to each block read from an array ``data`` (e.g. ``bool -> 0/255``).
    """
    path = Path(path)
    if georef is not None:
        return write_geotiff(path, data, georef, shape=shape, dtype=dtype, tile=tile,
                             compression=compression or "none", convert=convert)
    import tifffile

    is_array = hasattr(data, "shape") and hasattr(data, "dtype")
    if is_array:
        shape = tuple(int(s) for s in data.shape)
        if convert is None:
            dtype = np.dtype(data.dtype)
        else:
            dtype = np.dtype(convert(np.asarray(data[:1, :1])).dtype)
    elif shape is None or dtype is None:
        raise ValueError("write_tiff needs shape= and dtype= when data is a tile iterator")
    dtype = np.dtype(dtype)
    if dtype == np.bool_:
        raise ValueError("write_tiff: convert bool masks to uint8 first (convert=)")
    shape = tuple(int(s) for s in shape)
    nbytes = int(np.prod(shape)) * dtype.itemsize
    if bigtiff is None:
        bigtiff = nbytes > 3.5e9
    bands = 1 if len(shape) == 2 else shape[2]
    photometric = "rgb" if bands == 3 and dtype == np.uint8 else "minisblack"
    kw: dict[str, Any] = dict(
        shape=shape, dtype=dtype, bigtiff=bigtiff, photometric=photometric, metadata=None,
        compression=compression,
    )
    if bands > 1:
        kw["planarconfig"] = "contig"
    if compression and dtype.kind in "iu":
        kw["predictor"] = True
    if tiled:
        kw["tile"] = (tile, tile)
        if is_array:
            payload = (_tiles_of(data, (tile, tile), convert) if convert is not None
                       or not isinstance(data, np.ndarray) else np.asarray(data))
        else:
            payload = data
    else:
        if not is_array:
            raise ValueError("write_tiff: a tile iterator needs tiled=True")
        arr = np.asarray(data[...])
        payload = convert(arr) if convert is not None else arr
        kw["rowsperstrip"] = max(1, (2**20) // max(1, shape[1] * bands * dtype.itemsize))
    if isinstance(payload, np.ndarray):
        kw.pop("shape")
        kw.pop("dtype")
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, payload, **kw)
    return path


def write_geotiff(
    path: str | os.PathLike,
    data,
    georef: dict[str, Any],
    *,
    shape: tuple[int, ...] | None = None,
    dtype=None,
    tile: int = 512,
    compression: str = "deflate",
    nodata: float | None = None,
    convert: Callable[[np.ndarray], np.ndarray] | None = None,
) -> Path:
    """Write a GeoTIFF with the given georeferencing (``crs``, ``transform``) via rasterio.

    ``data`` is an array (numpy or lazy) or an iterator of ``tile x tile`` blocks in
    row-major order (then ``shape`` and ``dtype`` are required).  The file is tiled,
    compressed, BigTIFF when needed, and written atomically.
    """
    import rasterio
    from rasterio.windows import Window

    path = Path(path)
    is_array = hasattr(data, "shape") and hasattr(data, "dtype")
    if is_array:
        shape = tuple(int(s) for s in data.shape)
        dtype = (np.dtype(data.dtype) if convert is None
                 else np.dtype(convert(np.asarray(data[:1, :1])).dtype))
        tiles: Iterable[np.ndarray] = _tiles_of(data, (tile, tile), convert)
    else:
        if shape is None or dtype is None:
            raise ValueError("write_geotiff needs shape= and dtype= when data is a tile iterator")
        tiles = data
    dtype = np.dtype(dtype)
    h, w = shape[:2]
    count = 1 if len(shape) == 2 else shape[2]
    profile = dict(
        driver="GTiff", height=h, width=w, count=count, dtype=dtype.name,
        crs=georef.get("crs"), transform=georef.get("transform"), tiled=True,
        blockxsize=tile, blockysize=tile, compress=compression, BIGTIFF="IF_SAFER",
    )
    if nodata is not None:
        profile["nodata"] = nodata
    with atomic_path(path) as tmp:
        with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(tmp, "w", **profile) as dst:
            windows = iter_windows(shape, tile)
            for (ys, xs), block in zip(windows, tiles, strict=False):
                block = np.asarray(block)[: ys.stop - ys.start, : xs.stop - xs.start]
                win = Window(xs.start, ys.start, xs.stop - xs.start, ys.stop - ys.start)
                if block.ndim == 2:
                    dst.write(block, 1, window=win)
                else:
                    dst.write(np.moveaxis(block, -1, 0), window=win)
    return path


def printable(text: str) -> str:
    r"""``text`` as any UTF-8 file can hold it: the bytes of a file name that is not UTF-8
    (which Python decodes to lone surrogates, ``surrogateescape``) become ``\xNN``
    escapes (the four characters), e.g. ``ref\xff.tif`` for a Latin-1 file name whose
    fourth byte is 0xff.

    Examples
    --------
    >>> import os
    >>> printable(os.fsdecode(b"caf\xe9.tif"))
    'caf\\xe9.tif'
    >>> printable("café.tif")
    'café.tif'
    """
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        pass
    try:
        raw = text.encode("utf-8", "surrogateescape")
    except UnicodeEncodeError:  # a lone surrogate that stands for no byte
        return text.encode("utf-8", "backslashreplace").decode("utf-8")
    return raw.decode("utf-8", "backslashreplace")


def to_jsonable(obj: Any) -> Any:
    """Convert numpy scalars/arrays, paths, tuples and non-finite floats (-> None) for JSON;
    text as UTF-8 can hold it (:func:`printable`)."""
    if isinstance(obj, dict):
        return {printable(str(k)): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer, int)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, os.PathLike):
        return printable(str(obj))
    if isinstance(obj, str):
        return printable(obj)
    if obj is None:
        return obj
    if hasattr(obj, "to_dict"):
        return to_jsonable(obj.to_dict())
    return printable(str(obj))


def write_json(path: str | os.PathLike, obj: Any, *, indent: int = 2) -> Path:
    """Write ``obj`` as JSON (numpy values converted, NaN -> null), atomically."""
    path = Path(path)
    text = json.dumps(to_jsonable(obj), indent=indent, allow_nan=False) + "\n"
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


#: Diagonal of the 36 x 24 mm frame that 35 mm-equivalent focal lengths refer to (mm).
FRAME_35MM_DIAGONAL = 43.27


def exif_focal_px(path: str | os.PathLike) -> float | None:
    """Focal length in pixels from a file's EXIF ``FocalLengthIn35mmFilm`` (tag 0xA405).

    ``f_px = f35 * diagonal_px / 43.27`` (the 36 x 24 mm frame's diagonal), with the
    diagonal of the image as stored.  None when the file has no such tag (or 0, EXIF's
    "unknown"), or Pillow cannot read its header (zarr stores, unusual TIFFs).
    """
    from PIL import Image as PILImage
    from PIL import UnidentifiedImageError

    p = Path(path)
    if p.is_dir():
        return None
    old = PILImage.MAX_IMAGE_PIXELS
    PILImage.MAX_IMAGE_PIXELS = None  # only the header is read
    try:
        with PILImage.open(p) as im:
            exif = im.getexif()
            f35 = exif.get_ifd(0x8769).get(0xA405) or exif.get(0xA405)
            w, h = im.size
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError):
        return None
    finally:
        PILImage.MAX_IMAGE_PIXELS = old
    try:
        f35 = float(f35)
    except (TypeError, ValueError):
        return None
    if not (math.isfinite(f35) and f35 > 0):
        return None
    return f35 * math.hypot(w, h) / FRAME_35MM_DIAGONAL
