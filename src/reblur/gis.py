"""GIS-ready outputs, written from tiles: Cloud-Optimised GeoTIFFs and change polygons.

:func:`write_cog`
    An image (numpy or lazy, read window by window) as a Cloud-Optimised GeoTIFF (GDAL's
    COG driver): tiled, compressed, with internal overviews, IFDs first and the smallest
    overview's tiles before the larger ones, georeferenced when ``georef`` is given.  The
    full-size image goes through a temporary tiled GeoTIFF written window by window, and
    each overview level is made from the one above, window by window (2 x 2 means, or
    maxima for masks: a change of one pixel stays visible at every zoom), so nothing
    full-size is ever in memory; the COG driver only assembles the levels.
:func:`region_shapes`
    The 8-connected regions of a mask as pixel-edge polygons, traced tile by tile
    (:func:`rasterio.features.shapes`) and merged across tile borders (:mod:`shapely`): only
    the outlines of the regions that cross a border are held until the end, never a
    full-size mask.
:func:`region_features`
    Those regions simplified (topology-preserving, at most half a pixel), in the
    observation's CRS, with the attributes of the decision's region records;
    :func:`write_geojson` writes them as GeoJSON (:func:`change_features`: the same as a
    dict), :func:`write_geopackage` as a GeoPackage when the optional ``geo`` extra
    (``pip install reblur[geo]``, :mod:`pyogrio`) is installed.
:class:`ReblurredStore`
    A full-size image on disk (zarr, in the observation's dtype) that the tiled pass writes
    the reblurred reference into, tile by tile, at any size.
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import shutil
import tempfile
import threading
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ._bands import any_bands
from ._memory import available_cpus
from .io import atomic_path, iter_windows, scratch_compressors

__all__ = [
    "COG_BLOCK",
    "FEATURE_KEYS",
    "POLYGON_TILE",
    "SIMPLIFY_PX",
    "ReblurredStore",
    "Feature",
    "RegionShape",
    "change_features",
    "geopackage_available",
    "quantize",
    "region_features",
    "region_shapes",
    "write_cog",
    "write_geojson",
    "write_geopackage",
]

#: Tile side (px) of the COGs: blocks and the size below which no further overview is made.
COG_BLOCK = 512

#: Side (px) of the mask windows polygons are traced in.
POLYGON_TILE = 2048

#: Largest distance (px) the simplified outlines move from the pixel edges.
SIMPLIFY_PX = 0.5

#: GDAL's block cache while a COG is assembled, in bytes (``rasterio.Env`` hands an integer
#: GDAL_CACHEMAX to ``GDALSetCacheMax64``; the environment variable's small values are
#: megabytes).  Less than a block: each block goes to the file as soon as it is complete,
#: and the copy holds no cache.  It was ``256``, meant as MB and taken as bytes; a real
#: 256 MB cache holds memory for no time gained (``python -m benchmarks.gis_outputs
#: --megapixels 100 --gdal-cache BYTES``: ``reblurred.tif`` 9.3 s and 15 MB of memory
#: growth with 256 bytes, 9.3 s and 179 MB with 256 MB, 7.9 s and 18 MB with 16 MB, within
#: this VM's noise).
_GDAL_CACHE_BYTES = 256

#: One COG written at a time in a process.  GDAL's block cache is shared by every thread and
#: a thread that fills it writes out other threads' dirty blocks, while rasterio's
#: ``Env`` options are per thread: two masked COGs written side by side failed with
#: "_tiffWriteProc: No such file or directory" (every time at 5000^2 px,
#: ``tests/test_gis.py::test_cogs_written_from_two_threads_are_whole``).
_COG_LOCK = threading.Lock()

_OVERVIEWS = ("average", "max", "none")

_GDAL_TYPES = {"uint8": "Byte", "int8": "Int8", "uint16": "UInt16", "int16": "Int16",
               "uint32": "UInt32", "int32": "Int32", "float32": "Float32",
               "float64": "Float64"}


# ---------------------------------------------------------------------------- rasters
def quantize(block: np.ndarray, dtype) -> np.ndarray:
    """Float intensities in [0, 1] of full scale -> ``dtype`` (integers: rounded and clipped
    to the dtype's range, NaN to 0; floats: cast).  A trailing band axis of 1 is dropped."""
    dtype = np.dtype(dtype)
    b = np.asarray(block)
    if b.ndim == 3 and b.shape[2] == 1:
        b = b[:, :, 0]
    if dtype.kind not in "ui":
        return b.astype(dtype, copy=False)
    info = np.iinfo(dtype)
    b = np.asarray(b, np.float32) * np.float32(info.max)  # a new array: changed in place
    np.rint(b, out=b)
    np.clip(b, info.min, info.max, out=b)  # infinities clip, NaN stays
    np.copyto(b, np.float32(0.0), where=np.isnan(b))
    return b.astype(dtype)


def _colour_names(count: int, alpha: bool) -> list[str]:
    """GDAL colour interpretation of ``count`` bands: gray, RGB, then undefined (the last
    band ``alpha`` when it is one)."""
    names = ["Gray"] if count <= 2 else ["Red", "Green", "Blue"]
    names += ["Undefined"] * (count - len(names))
    if alpha and count in (2, 4):
        names[-1] = "Alpha"
    return names[:count]


def _step(shape: tuple[int, ...], block: int, chunks) -> int:
    """Side of the windows read from a source: the block, or its chunk rounded up to whole
    blocks (so a chunked store decodes each chunk once)."""
    ch = int(chunks[0]) if chunks and isinstance(chunks[0], (int, np.integer)) else block
    return block * max(1, -(-ch // block))


def _gdal_threads() -> int:
    """Threads GDAL compresses a file's tiles with (its ``NUM_THREADS``): the CPUs this
    process may use.  Each tile is compressed alone, so the file's bytes are those of one
    thread.  ``python -m benchmarks.gis_outputs --megapixels 25``: ``reblurred.tif`` (RGB,
    uint8) 2.3 -> 1.7 s on two threads, the same bytes."""
    return available_cpus()


def _write_level0(path: Path, data, shape: tuple[int, ...], dtype: np.dtype,
                  georef: dict[str, Any] | None, block: int,
                  convert: Callable | None, alpha: bool = False,
                  nodata_mask=None, level1: tuple[Path, tuple[int, int], str] | None = None
                  ) -> None:
    """The full-size image as a tiled GeoTIFF, window by window (the COG's source); where
    ``nodata_mask`` is True or the source is NaN: NaN (float output) or 0 and an internal
    mask (integer output).

    ``level1 = (path, shape, how)``: the first overview level is written in the same pass,
    each window reduced as it is written -- the pixels (and mask) :func:`_write_level`
    makes from the written file, without reading it back.  That read (decompressing the
    full-size level, its bands interleaved) took most of the overviews' time: 3/4 of their
    pixels are this level's."""
    import rasterio
    from rasterio.enums import ColorInterp
    from rasterio.windows import Window

    h, w = shape[:2]
    count = 1 if len(shape) == 2 else shape[2]
    geo = georef or {}
    # the temporaries are not compressed: each is written once and read once by the COG's
    # copy, mostly from the page cache, and zstd level 1 cost more CPU than its smaller
    # files saved (``python -m benchmarks.gis_outputs --megapixels 25``: reblurred.tif
    # 1.3 -> 1.0 s).  They need the pixels' raw size on the output's disk, and a third more
    # for the overviews: a failed write reports the disk as full when it lacks the raw size
    profile = dict(driver="GTiff", height=h, width=w, count=count, dtype=dtype.name,
                   tiled=True, blockxsize=block, blockysize=block, compress="none",
                   num_threads=_gdal_threads(), BIGTIFF="IF_SAFER",
                   crs=geo.get("crs"), transform=geo.get("transform"))
    if dtype.kind == "f":
        profile["nodata"] = np.nan
    if count in (3, 4):
        profile["photometric"] = "RGB"
        if count == 4:
            profile["alpha"] = "UNASSOCIATED" if alpha else "NO"
    step = _step(shape, block, getattr(data, "chunks", None))
    if level1 is not None:  # whole blocks of the level too: windows of whole block pairs
        step = 2 * block * max(1, -(-step // (2 * block)))
    with contextlib.ExitStack() as files:
        dst = files.enter_context(rasterio.open(path, "w", **profile))
        dst.colorinterp = [ColorInterp[n.lower()] for n in _colour_names(count, alpha)]
        low = None
        if level1 is not None:
            low_path, low_shape, how = level1
            low = files.enter_context(rasterio.open(
                low_path, "w", **dict(profile, height=low_shape[0], width=low_shape[1],
                                      transform=None, crs=None)))
        for ys, xs in iter_windows(shape, step):
            b = np.asarray(data[ys, xs])
            bad = None if nodata_mask is None else _no_data(nodata_mask, b, ys, xs)
            if convert is not None:
                b = convert(b)
            win = Window(xs.start, ys.start, xs.stop - xs.start, ys.stop - ys.start)
            if bad is not None:
                b = np.where(bad if b.ndim == 2 else bad[:, :, None],
                             np.nan if dtype.kind == "f" else 0, b).astype(dtype)
                if dtype.kind != "f":
                    dst.write_mask(np.where(bad, 0, 255).astype(np.uint8), window=win)
            if b.ndim == 2:
                dst.write(b, 1, window=win)
            else:
                dst.write(np.moveaxis(b, -1, 0), window=win)
            if low is not None:
                a = np.asarray(b, dtype)
                # band-first and contiguous: reduced faster than through strided band views
                a = a[None] if a.ndim == 2 else np.ascontiguousarray(np.moveaxis(a, -1, 0))
                valid = None if bad is None or dtype.kind == "f" else ~bad
                _write_reduced(low, a, valid, ys.start // 2, xs.start // 2, how)


def _write_reduced(dst, a: np.ndarray, valid: np.ndarray | None, y: int, x: int,
                   how: str) -> None:
    """The 2 x 2 reduction of a level's window ``a`` ((C, h, w), even corner) at ``(y, x)``
    of the next level ``dst``: :func:`_reduce2`, or over the ``valid`` pixels with the next
    level's mask (:func:`_reduce2_valid`)."""
    from rasterio.windows import Window

    if valid is not None:
        r, ok = _reduce2_valid(a, valid, how)
        dst.write_mask(np.where(ok, 255, 0).astype(np.uint8),
                       window=Window(x, y, r.shape[2], r.shape[1]))
    else:
        r = _reduce2(a, how)
    dst.write(r, window=Window(x, y, r.shape[2], r.shape[1]))


def _no_data(nodata_mask, b: np.ndarray, ys: slice, xs: slice) -> np.ndarray:
    """Window ``ys, xs`` of ``nodata_mask``, or'ed with the NaN pixels of the source
    window ``b``."""
    bad = np.array(nodata_mask[ys, xs], dtype=bool)
    if b.dtype.kind == "f":
        nan = np.isnan(b)
        bad |= any_bands(nan)
    return bad


def _level_shapes(h: int, w: int, block: int) -> list[tuple[int, int]]:
    """Sizes of the overview levels (factor 2 each, GDAL's rounding up) until one fits in a
    block."""
    out = []
    while max(h, w) > block:
        h, w = -(-h // 2), -(-w // 2)
        out.append((h, w))
    return out


def _reduce2(a: np.ndarray, how: str) -> np.ndarray:
    """2 x 2 block maximum or mean (band axis first).  An odd last row / column is a block
    of its own pixels (GDAL's overview sizes round up): it is repeated, which leaves the
    maximum and the mean of its pixels as they are.  Means skip NaN and are rounded for
    integer types."""
    c, h, w = a.shape
    if h % 2 or w % 2:
        a = np.pad(a, ((0, 0), (0, h % 2), (0, w % 2)), mode="edge")
    q = (a[:, 0::2, 0::2], a[:, 0::2, 1::2], a[:, 1::2, 0::2], a[:, 1::2, 1::2])
    if how == "max":  # NaN skipped
        return np.fmax(np.fmax(q[0], q[1]), np.fmax(q[2], q[3]))
    ft = np.float64 if a.dtype.itemsize > 2 else np.float32
    if a.dtype.kind in "ui":
        m = (q[0].astype(ft) + q[1]) + (q[2].astype(ft) + q[3])
        m *= 0.25
        info = np.iinfo(a.dtype)
        return np.clip(np.rint(m), info.min, info.max).astype(a.dtype)
    ok = [~np.isnan(v) for v in q]
    total = sum(np.where(k, v, 0).astype(ft) for k, v in zip(ok, q, strict=True))
    n = sum(k.astype(np.uint8) for k in ok)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (total / n).astype(a.dtype)  # NaN where a block holds no value


def _reduce2_valid(a: np.ndarray, valid: np.ndarray, how: str) -> tuple[np.ndarray,
                                                                        np.ndarray]:
    """:func:`_reduce2` of integer pixels over the ``valid`` ones only: the reduced pixels
    (0 where a block holds no valid pixel) and their validity.

    Unsigned pixels of at most 32 bits are reduced in integer arithmetic
    (:func:`_reduce2_valid_uint`, the same pixels); others through a float copy with NaN
    at the invalid pixels."""
    if a.dtype.kind == "u" and a.dtype.itemsize <= 4:
        return _reduce2_valid_uint(a, valid, how)
    ft = np.float64 if a.dtype.itemsize > 2 else np.float32
    r = _reduce2(np.where(valid[None], a.astype(ft), np.nan), how)
    ok = ~np.isnan(r[0])
    info = np.iinfo(a.dtype)
    with np.errstate(invalid="ignore"):
        out = np.where(ok[None], np.clip(np.rint(r), info.min, info.max), 0).astype(a.dtype)
    return out, ok


def _reduce2_valid_uint(a: np.ndarray, valid: np.ndarray, how: str) -> tuple[np.ndarray,
                                                                             np.ndarray]:
    """:func:`_reduce2_valid` of unsigned pixels (at most 32 bits) without a float copy of
    the window: a block's maximum is that of its valid pixels with the others as 0 (the
    pixels are non-negative), its mean the integer sum of its valid pixels (exact in
    ``uint32`` / ``uint64``) over their count, divided and rounded in the float type of
    the NaN path (``float32`` up to 16 bits, ``float64`` above: the sum is exact there too,
    so the quotient and its rounding are the same): no float copy of the window, no NaN
    tests, fewer passes over it."""
    c, h, w = a.shape
    if h % 2 or w % 2:  # repeated edge pixels, with their validity (as _reduce2 pads)
        a = np.pad(a, ((0, 0), (0, h % 2), (0, w % 2)), mode="edge")
        valid = np.pad(valid, ((0, h % 2), (0, w % 2)), mode="edge")
    q = (a[:, 0::2, 0::2], a[:, 0::2, 1::2], a[:, 1::2, 0::2], a[:, 1::2, 1::2])
    v = (valid[0::2, 0::2], valid[0::2, 1::2], valid[1::2, 0::2], valid[1::2, 1::2])
    n = v[0].astype(np.uint8) + v[1] + v[2] + v[3]
    ok = n > 0
    if how == "max":
        out = np.where(v[0], q[0], 0).astype(a.dtype)
        for qi, vi in zip(q[1:], v[1:], strict=True):
            np.maximum(out, np.where(vi, qi, 0), out=out, casting="unsafe")
        return out, ok
    total = np.where(v[0], q[0], 0).astype(np.uint32 if a.dtype.itemsize <= 2 else np.uint64)
    for qi, vi in zip(q[1:], v[1:], strict=True):
        total += np.where(vi, qi, 0)
    ft = np.float64 if a.dtype.itemsize > 2 else np.float32
    with np.errstate(invalid="ignore", divide="ignore"):
        m = total.astype(ft) / n.astype(ft)  # NaN where a block holds no valid pixel
    m = np.rint(m, out=m)
    return np.where(ok, m, 0).astype(a.dtype), ok


def _write_level(src: Path, dst: Path, shape: tuple[int, int], block: int, how: str) -> None:
    """Overview level ``shape`` of ``src`` (the previous level) by 2 x 2 block reduction."""
    import rasterio
    from rasterio.enums import MaskFlags
    from rasterio.windows import Window

    with rasterio.open(src) as s:
        profile = s.profile
        profile.update(height=shape[0], width=shape[1], transform=None, crs=None)
        whole = Window(0, 0, s.width, s.height)
        masked = s.mask_flag_enums[0] == [MaskFlags.per_dataset]
        with rasterio.open(dst, "w", **profile) as d:
            for ys, xs in iter_windows(shape, block):
                h, w = ys.stop - ys.start, xs.stop - xs.start
                # the window above, clipped to the level: its reduction is exactly h x w
                win = Window(2 * xs.start, 2 * ys.start, 2 * w, 2 * h).intersection(whole)
                valid = s.read_masks(1, window=win) > 0 if masked else None  # valid only
                _write_reduced(d, s.read(window=win), valid, ys.start, xs.start, how)


def _vrt(path: Path, levels: list[Path], shape: tuple[int, ...], dtype: np.dtype,
         georef: dict[str, Any] | None, alpha: bool = False, masked: bool = False) -> None:
    """A VRT of the full-size file whose overviews are the files of ``levels`` (and their
    masks when ``masked``; float pixels: NaN is no data)."""
    h, w = shape[:2]
    count = 1 if len(shape) == 2 else shape[2]
    root = ET.Element("VRTDataset", rasterXSize=str(w), rasterYSize=str(h))
    geo = georef or {}
    if geo.get("crs") is not None:
        ET.SubElement(root, "SRS").text = geo["crs"].to_wkt()
    if geo.get("transform") is not None:
        ET.SubElement(root, "GeoTransform").text = ", ".join(
            repr(float(v)) for v in geo["transform"].to_gdal())
    for band, colour in enumerate(_colour_names(count, alpha), 1):
        b = ET.SubElement(root, "VRTRasterBand", dataType=_GDAL_TYPES[dtype.name],
                          band=str(band))
        ET.SubElement(b, "ColorInterp").text = colour
        if dtype.kind == "f":
            ET.SubElement(b, "NoDataValue").text = "nan"
        _vrt_sources(b, levels, str(band))
    if masked:
        m = ET.SubElement(ET.SubElement(root, "MaskBand"), "VRTRasterBand", dataType="Byte")
        _vrt_sources(m, levels, "mask,1")
    ET.ElementTree(root).write(path, encoding="utf-8")


def _vrt_sources(band: ET.Element, levels: list[Path], source: str) -> None:
    """Band ``source`` of ``levels``: the first the band's pixels, the others overviews."""
    for k, p in enumerate(levels):
        el = ET.SubElement(band, "SimpleSource" if k == 0 else "Overview")
        ET.SubElement(el, "SourceFilename", relativeToVRT="1").text = p.name
        ET.SubElement(el, "SourceBand").text = source


def write_cog(
    path: str | os.PathLike,
    data,
    georef: dict[str, Any] | None = None,
    *,
    block: int = COG_BLOCK,
    overviews: str = "average",
    convert: Callable[[np.ndarray], np.ndarray] | None = None,
    compression: str = "deflate",
    level: int | None = 1,
    alpha: bool = False,
    nodata_mask=None,
) -> Path:
    """Write an image as a Cloud-Optimised GeoTIFF, atomically, window by window.

    Parameters
    ----------
    path : str or path-like
        Destination.
    data : array-like, (H, W) or (H, W, C)
        Numpy, zarr or any lazy array read window by window (a chunked store in whole
        chunks).
    georef : dict, optional
        ``crs`` (``rasterio.crs.CRS`` or None) and ``transform`` (``affine.Affine`` or None),
        as :attr:`reblur.io.Image.geo`.  Without it the file has no georeferencing.
    block : int
        Tile side, a multiple of 16.  Overviews halve the size until one fits in a block.
    overviews : {"average", "max", "none"}
        Overview pixels are the mean (NaN skipped, integers rounded) or the maximum (for
        masks: a single pixel stays visible) of the 2 x 2 pixels of the level above.
    convert : callable, optional
        Applied to each window read from ``data`` (e.g. :func:`quantize`).
    compression : str
        GDAL compression of the COG (``"deflate"`` is readable everywhere).
    level : int or None
        The level of deflate or zstd (GDAL's ``LEVEL``; None: GDAL's default, 6 for
        deflate).
        Level 1 writes a 100 MP reblurred image about 6x faster than level 6 (0.75 s
        against 4.5 s) for about 17 % more bytes.
    alpha : bool
        The last of 2 or 4 bands is alpha.  The bands' colour interpretation is gray for
        1 or 2 bands, red, green, blue for 3 or more, any further band undefined (or alpha).
    nodata_mask : array-like, (H, W) bool, optional
        True where the image holds no data (read window by window); the source's NaN pixels
        are no data too.  Integer outputs get an internal mask (GDAL's per-dataset mask, 0
        there; the pixels are 0), float outputs NaN.  Overviews are made of the valid pixels
        only.  Float outputs always declare NaN as their nodata value.

    Returns
    -------
    Path
    """
    path = Path(path)
    if overviews not in _OVERVIEWS:
        raise ValueError(f"overviews must be one of {', '.join(_OVERVIEWS)}, got {overviews!r}")
    if block < 16 or block % 16:
        raise ValueError(f"block must be a positive multiple of 16, got {block}")
    shape = tuple(int(s) for s in data.shape)
    probe = np.asarray(data[:1, :1])
    dtype = np.dtype((convert(probe) if convert is not None else probe).dtype)
    if dtype.name not in _GDAL_TYPES:
        raise ValueError(f"write_cog writes {', '.join(_GDAL_TYPES)} pixels, got {dtype} "
                         "(convert bool masks to uint8 first)")
    if nodata_mask is not None and tuple(nodata_mask.shape) != shape[:2]:
        raise ValueError(f"nodata_mask is {tuple(nodata_mask.shape)}, the image "
                         f"{shape[:2]}: give one (H, W) mask of the image's size")
    masked = nodata_mask is not None and dtype.kind != "f"
    opts = dict(BLOCKSIZE=block, COMPRESS=compression.upper(), BIGTIFF="IF_SAFER",
                NUM_THREADS=_gdal_threads(), OVERVIEWS="NONE")
    if compression.lower() in ("deflate", "zstd", "lzw"):
        opts["PREDICTOR"] = "YES"
    if level is not None and compression.lower() in ("deflate", "zstd"):
        opts["LEVEL"] = int(level)
    # temporaries next to the output, named like the output set's, so that a run killed
    # here leaves nothing the next run into the directory does not remove
    with _COG_LOCK:
        _write_cog_locked(path, data, georef, shape, dtype, block, overviews, convert, alpha,
                          nodata_mask, masked, opts)
    return path


def _write_cog_locked(path: Path, data, georef, shape, dtype, block, overviews, convert,
                      alpha, nodata_mask, masked, opts) -> None:
    """The GDAL part of :func:`write_cog` (under ``_COG_LOCK``)."""
    import rasterio
    import rasterio.shutil
    from rasterio.errors import NotGeoreferencedWarning

    work = Path(tempfile.mkdtemp(prefix=f".reblur-tmp-{os.getpid()}-cog-", dir=path.parent))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.Env(GDAL_CACHEMAX=_GDAL_CACHE_BYTES, CPL_LOG="/dev/null",
                              GDAL_TIFF_INTERNAL_MASK=True):
                src = work / "level0.tif"
                shapes = _level_shapes(*shape[:2], block) if overviews != "none" else []
                # the first overview level beside the full size, the others each from the
                # one above, window by window
                levels = [src] + [work / f"level{k}.tif" for k in range(1, len(shapes) + 1)]
                _write_level0(src, data, shape, dtype, georef, block, convert, alpha,
                              nodata_mask,
                              level1=(levels[1], shapes[0], overviews) if shapes else None)
                if shapes:
                    for k in range(2, len(levels)):
                        _write_level(levels[k - 1], levels[k], shapes[k - 1], block,
                                     overviews)
                    src = work / "pyramid.vrt"
                    _vrt(src, levels, shape, dtype, georef, alpha, masked)
                    opts["OVERVIEWS"] = "FORCE_USE_EXISTING"
                with atomic_path(path) as tmp:
                    rasterio.shutil.copy(src, tmp, driver="COG", **opts)
    except Exception as exc:
        # GDAL reports a write that filled the disk as its own error (rasterio's CPLE_*
        # classes; the OS's errno is gone): say so when the disk cannot hold the image's
        # pixels (the temporaries are still there)
        raw = math.prod(shape) * dtype.itemsize
        if (type(exc).__module__.startswith("rasterio")
                and shutil.disk_usage(path.parent).free < raw):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path)) from exc
        raise
    finally:
        shutil.rmtree(work, ignore_errors=True)


class ReblurredStore:
    """A full-size image that tiles are written into: the reblurred reference at any size,
    on disk or in memory.

    Written with float intensities in [0, 1] of full scale (what the tiled pass makes),
    stored in ``dtype`` (:func:`quantize`: the observation's, so the store is no larger than
    the observation), read back as float32 in [0, 1].  On disk, a zarr array chunked like
    the tiles, so each tile writes whole chunks; picklable (Dask workers reopen it by
    path).  In memory (``directory`` None), a numpy array of ``dtype``: a quarter of the
    float32 image for 8-bit data (a 25 MP 3-band 16-bit image: 157 MB, not 315).

    Parameters
    ----------
    directory : path or None
        The zarr array's directory (created; an existing one is replaced); None: memory.
    shape : (H, W) or (H, W, C)
    dtype : numpy dtype
        Storage type (the observation's).
    chunk : int
        Chunk side (the tile side of the pass).
    """

    def __init__(self, directory: str | os.PathLike | None, shape: tuple[int, ...], dtype,
                 chunk: int = 1024):
        shape = tuple(int(v) for v in shape)
        if len(shape) not in (2, 3):
            raise ValueError(f"ReblurredStore holds (H, W) or (H, W, C) images, got {shape}")
        self._chunks = (int(chunk), int(chunk)) + shape[2:]
        if directory is None:
            self.stored = np.zeros(shape, np.dtype(dtype))
        else:
            import zarr

            self.stored = zarr.create_array(
                str(directory), shape=shape, chunks=self._chunks, dtype=np.dtype(dtype),
                fill_value=0, overwrite=True, compressors=scratch_compressors(dtype))
        self.shape = shape
        self.dtype = np.dtype(np.float32)
        self.ndim = len(shape)

    @property
    def chunks(self) -> tuple[int, ...]:
        return self._chunks

    @property
    def stored_dtype(self) -> np.dtype:
        return np.dtype(self.stored.dtype)

    def __len__(self) -> int:
        return self.shape[0]

    def __setitem__(self, key, value) -> None:
        self.stored[key] = quantize(value, self.stored_dtype)

    def __getitem__(self, key) -> np.ndarray:
        a = np.asarray(self.stored[key])
        if self.stored_dtype.kind in "ui":
            return a.astype(np.float32) / np.float32(np.iinfo(self.stored_dtype).max)
        return a.astype(np.float32, copy=False)


# ---------------------------------------------------------------------------- polygons
@dataclass
class RegionShape:
    """One 8-connected region of a mask.

    Attributes
    ----------
    geometry : shapely Polygon or MultiPolygon
        The union of its pixels' squares, in pixel coordinates (x = column, y = row, pixel
        ``(r, c)`` covering ``[c, c + 1] x [r, r + 1]``); a MultiPolygon where parts meet
        only at a corner.
    area : int
        Pixels.
    bbox : tuple of int
        ``(y0, x0, y1, x1)``, end exclusive.
    """

    geometry: Any
    area: int
    bbox: tuple[int, int, int, int]


def _tile_regions(m: np.ndarray, y0: int, x0: int, shape: tuple[int, int]
                  ) -> Iterator[tuple[RegionShape, bool]]:
    """The regions of one mask window, each with whether it may go on in a neighbouring
    window (it touches a window edge inside the image)."""
    import cv2
    import shapely
    from affine import Affine
    from rasterio import features
    from shapely.geometry import shape as to_shape

    n, lab, stats, _ = cv2.connectedComponentsWithStats(m.view(np.uint8), connectivity=8,
                                                        ltype=cv2.CV_32S)
    if n == 1:
        return
    pieces: dict[int, list] = {}
    # 4-connected pieces are simple polygons; the pieces of one 8-connected region meet at
    # corners and are joined below
    for geom, v in features.shapes(lab, mask=m, connectivity=4,
                                   transform=Affine.translation(x0, y0)):
        pieces.setdefault(int(v), []).append(to_shape(geom))
    h, w = m.shape
    H, W = shape
    for i in range(1, n):
        x, y, bw, bh, area = (int(v) for v in stats[i])
        parts = pieces[i]
        g = parts[0] if len(parts) == 1 else shapely.union_all(parts)
        if not g.is_valid:  # a ring touching itself at a corner
            g = shapely.make_valid(g)
        open_ = ((y == 0 and y0 > 0) or (x == 0 and x0 > 0) or (y + bh == h and y0 + h < H)
                 or (x + bw == w and x0 + w < W))
        yield RegionShape(g, area, (y0 + y, x0 + x, y0 + y + bh, x0 + x + bw)), open_


def _merge(pieces: list[RegionShape]) -> list[RegionShape]:
    """Join the pieces of regions cut by window borders: pieces of different windows whose
    squares touch (along an edge or at a corner) are 8-connected."""
    import shapely
    from shapely import STRtree

    if not pieces:
        return []
    geoms = [p.geometry for p in pieces]
    a, b = STRtree(geoms).query(geoms, predicate="intersects")
    parent = list(range(len(pieces)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in zip(a.tolist(), b.tolist(), strict=True):
        ri, rj = root(i), root(j)
        if ri != rj:
            parent[max(ri, rj)] = min(ri, rj)
    groups: dict[int, list[int]] = {}
    for i in range(len(pieces)):
        groups.setdefault(root(i), []).append(i)
    out = []
    for idx in groups.values():
        ps = [pieces[i] for i in idx]
        g = ps[0].geometry if len(ps) == 1 else shapely.union_all([p.geometry for p in ps])
        bbox = (min(p.bbox[0] for p in ps), min(p.bbox[1] for p in ps),
                max(p.bbox[2] for p in ps), max(p.bbox[3] for p in ps))
        out.append(RegionShape(g, sum(p.area for p in ps), bbox))
    return out


def region_shapes(mask, *, tile: int = POLYGON_TILE) -> list[RegionShape]:
    """The 8-connected regions of a mask as exact pixel-edge polygons, traced tile by tile.

    Each ``tile`` x ``tile`` window is read, labelled and traced
    (:func:`rasterio.features.shapes`); a region inside a window is final, the pieces of
    regions that reach a window border are joined across borders at the end (union of the
    pieces whose squares touch).  Only those outlines are held, never the full-size mask.

    Parameters
    ----------
    mask : (H, W) array-like
        Non-zero = region (numpy, zarr or a lazy view).
    tile : int
        Window side.

    Returns
    -------
    list of RegionShape
        In the raster order of their bounding boxes' top-left corners.
    """
    if tile < 1:
        raise ValueError(f"tile must be positive, got {tile}")
    shape = tuple(int(v) for v in mask.shape[:2])
    done: list[RegionShape] = []
    pending: list[RegionShape] = []
    for ys, xs in iter_windows(shape, tile):
        m = np.asarray(mask[ys, xs]) != 0
        if not m.any():
            continue
        for r, open_ in _tile_regions(m, ys.start, xs.start, shape):
            (pending if open_ else done).append(r)
    done += _merge(pending)
    done.sort(key=lambda r: (r.bbox[0], r.bbox[1], r.bbox[2], r.bbox[3]))
    return done


#: Region properties copied into the features.
FEATURE_KEYS = ("rank", "score", "polarity", "mean_contrast", "contrast", "area_m2",
                "mean_stat", "max_stat")


@dataclass
class Feature:
    """One change region for the vector outputs.

    Attributes
    ----------
    properties : dict
        ``id``, ``area``, ``area_px`` and the region record's :data:`FEATURE_KEYS`.
    geometry : shapely Polygon or MultiPolygon
        The simplified outline, in the CRS (or pixel coordinates).
    """

    properties: dict[str, Any]
    geometry: Any


def region_features(
    mask,
    georef: dict[str, Any] | None = None,
    regions: list[dict[str, Any]] | None = None,
    *,
    tile: int = POLYGON_TILE,
    tolerance: float = SIMPLIFY_PX,
) -> list[Feature]:
    """The change regions of a mask as simplified, attributed outlines, built tile by tile.

    One feature per 8-connected region (:func:`region_shapes`), its outline simplified
    (Douglas-Peucker, topology-preserving: no ring crosses another; every vertex dropped
    lies within ``tolerance`` pixels of the simplified outline, which lies within
    ``tolerance`` of the pixel edges), then mapped by the ``transform`` of ``georef``
    (pixel coordinates without it).

    Properties: ``id`` (1, 2, ... in the listed order: a region's ``rank`` when all have
    one, and its id in the viewer's ``regions.json``), ``area`` (in CRS units squared, or
    pixels), ``area_px`` and, for the region's record in ``regions`` (matched by bounding
    box and pixel count: :func:`reblur.report.triage` records), its :data:`FEATURE_KEYS`.
    Features are listed by rank (then by area).
    """
    from affine import Affine
    from shapely import affinity

    if tolerance < 0 or not math.isfinite(tolerance):
        raise ValueError(f"tolerance must be a finite number of pixels >= 0, got {tolerance}")
    transform = (georef or {}).get("transform") or Affine.identity()
    px_area = abs(transform.a * transform.e - transform.b * transform.d) or 1.0
    by_key = {}
    for r in regions or []:
        if "bbox" in r and "area" in r:
            by_key[(tuple(int(v) for v in r["bbox"]), int(r["area"]))] = r
    coeffs = [transform.a, transform.b, transform.d, transform.e, transform.c, transform.f]
    feats = []
    for s in region_shapes(mask, tile=tile):
        g = s.geometry.simplify(tolerance, preserve_topology=True) if tolerance else s.geometry
        props: dict[str, Any] = dict(area=s.area * px_area, area_px=s.area)
        rec = by_key.get((s.bbox, s.area))
        if rec is not None:
            props.update({k: rec[k] for k in FEATURE_KEYS if k in rec})
        feats.append(Feature(props, affinity.affine_transform(g, coeffs)))
    feats.sort(key=lambda f: (f.properties.get("rank", np.inf), -f.properties["area"]))
    for i, f in enumerate(feats, 1):  # 1-based: the rank, and the viewer's region id
        f.properties = {"id": i, **f.properties}
    return feats


def _crs_member(georef: dict[str, Any] | None) -> dict[str, Any] | None:
    """GeoJSON 2008's ``crs`` member naming the CRS of ``georef`` (None without one)."""
    crs = (georef or {}).get("crs")
    if crs is None:
        return None
    epsg = crs.to_epsg()
    name = f"urn:ogc:def:crs:EPSG::{epsg}" if epsg else crs.to_wkt()
    return dict(type="name", properties=dict(name=name))


def change_features(
    mask,
    georef: dict[str, Any] | None = None,
    regions: list[dict[str, Any]] | None = None,
    *,
    tile: int = POLYGON_TILE,
    tolerance: float = SIMPLIFY_PX,
) -> dict[str, Any]:
    """:func:`region_features` as a GeoJSON FeatureCollection (a dict).

    The CRS is named in a ``crs`` member (GeoJSON 2008 style; RFC 7946 readers assume
    WGS 84 without it).  :func:`write_geojson` writes the same text without building it.
    """
    from shapely.geometry import mapping

    feats = region_features(mask, georef, regions, tile=tile, tolerance=tolerance)
    fc: dict[str, Any] = dict(type="FeatureCollection", features=[
        dict(type="Feature", properties=f.properties, geometry=mapping(f.geometry))
        for f in feats])
    crs = _crs_member(georef)
    if crs is not None:
        fc["crs"] = crs
    return fc


def write_geojson(path: str | os.PathLike, features: list[Feature],
                  georef: dict[str, Any] | None = None) -> Path:
    """Write features (:func:`region_features`) as a GeoJSON FeatureCollection, atomically,
    one feature per line (the geometry's text made by GEOS, feature by feature)."""
    import json

    import shapely

    from .io import to_jsonable

    path = Path(path)
    crs = _crs_member(georef)
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as f:
        f.write('{"type": "FeatureCollection", ')
        if crs is not None:
            f.write(f'"crs": {json.dumps(crs)}, ')
        f.write('"features": [\n')
        for k, feat in enumerate(features):
            props = json.dumps(to_jsonable(feat.properties), allow_nan=False)
            f.write(f'{"," if k else ""}{{"type": "Feature", "properties": {props}, '
                    f'"geometry": {shapely.to_geojson(feat.geometry)}}}\n')
        f.write("]}\n")
    return path


def geopackage_available() -> bool:
    """Whether :func:`write_geopackage` can write (the ``geo`` extra, :mod:`pyogrio`)."""
    try:
        import pyogrio  # noqa: F401
    except ImportError:
        return False
    return True


def _field(values: list) -> tuple[np.ndarray, np.ndarray | None]:
    """A column for pyogrio (int64, float64 or str) and its null mask (None: no nulls)."""
    present = [v for v in values if v is not None]
    null = np.array([v is None for v in values])
    if present and all(isinstance(v, (bool, np.bool_)) for v in present):
        kind: type = bool
    elif present and all(isinstance(v, (int, np.integer)) for v in present):
        kind = int
    elif present and all(isinstance(v, (int, float, np.number)) for v in present):
        kind = float
    else:
        kind = str
    if kind is str:
        col = np.array(["" if v is None else str(v) for v in values], dtype=object)
    else:
        fill = {bool: False, int: 0, float: np.nan}[kind]
        dt = {bool: np.bool_, int: np.int64, float: np.float64}[kind]
        col = np.array([fill if v is None else v for v in values], dtype=dt)
    return col, (null if null.any() else None)


def write_geopackage(path: str | os.PathLike, features: list[Feature],
                     georef: dict[str, Any] | None = None, *, layer: str = "changes") -> Path:
    """Write features (:func:`region_features`) as a GeoPackage layer, atomically.

    Every geometry is written as a MultiPolygon (one geometry type per layer), with the
    CRS of ``georef``.  Needs the ``geo`` extra (:mod:`pyogrio`).

    Raises
    ------
    ImportError
        :mod:`pyogrio` is not installed (``pip install reblur[geo]``).
    """
    try:
        from pyogrio.raw import write
    except ImportError as exc:
        raise ImportError("writing a GeoPackage needs pyogrio: pip install 'reblur[geo]'"
                          ) from exc
    import shapely
    from shapely.geometry import MultiPolygon

    geoms = [MultiPolygon([f.geometry]) if f.geometry.geom_type == "Polygon" else f.geometry
             for f in features]
    keys: list[str] = []
    for f in features:
        keys += [k for k in f.properties if k not in keys]
    cols, masks = [], []
    for k in keys:
        col, null = _field([f.properties.get(k) for f in features])
        cols.append(col)
        masks.append(null)
    crs = (georef or {}).get("crs")
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.unlink()  # the driver creates the file
        try:
            write(str(tmp), np.array(shapely.to_wkb(geoms), dtype=object), cols, keys,
                  field_mask=masks if any(m is not None for m in masks) else None,
                  layer=layer, driver="GPKG", geometry_type="MultiPolygon",
                  crs=crs.to_wkt() if crs is not None else None)
        finally:
            for extra in ("-wal", "-shm", "-journal"):
                with contextlib.suppress(OSError):
                    Path(str(tmp) + extra).unlink()
    return path
