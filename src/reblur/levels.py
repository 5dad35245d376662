"""The reduced-resolution levels an image file carries: pyramidal TIFF, COG / GeoTIFF
overviews, zarr multiscales.

A lazily opened image (:func:`reblur.io.open_image`) whose file holds such levels
carries a :class:`FileLevels` as its ``file_levels`` attribute; the views reblur puts over
an image (band selection, luminance, rescaling, no-data as NaN) carry the same levels seen
through the same view.  :class:`reblur.align.OverviewCache` builds the alignment's
overviews from them instead of reading the full-resolution image.

Geometry
--------
A level of shape ``(h, w)`` of a base image ``(H, W)`` has the per-axis factors
``(H / h, W / w)``, from the shapes, or the factors its metadata states (zarr
multiscales' ``scale``), and its pixel ``i`` stands for the base interval
``[origin + i f, origin + (i + 1) f)`` (pixel edges; base pixel ``r`` is ``[r, r + 1)``),
``origin = 0`` unless the metadata states a translation.  Its centre in base pixel-centre
coordinates is therefore ``origin + (i + 0.5) f - 0.5``: for a 2x block mean, base
pixel ``x`` sits at ``(x + 0.5) / 2 - 0.5`` of the level.  This is GDAL's convention (its
overviews' geotransform is the base's scaled by ``W / w``, and its ``average``
resampling follows it: measured on GDAL 3.10 files, ceil-sized ``gdaladdo`` and
floor-sized COG levels alike) and OpenSlide's.  A level must be consistent with one
downsampling of the base -- a common factor ``f`` with ``|H / f - h| < 1`` and
``|W / f - w| < 1`` -- and smaller than it; otherwise it is ignored, with the reason
logged and recorded.  A zarr multiscales translation that differs from the base's is
read as the position of the level's first pixel centre (OME-NGFF); without one, the
level is taken to cover the base from its corner, as above (the writers that state no
translation -- most -- average blocks from the corner).

A level made by decimation (``a[::2, ::2]``, GDAL's ``nearest``) is read as if it were
the average it stands for: that costs aliasing, and its samples sit off the centres of
the intervals they stand for (``a[::n]`` by ``(n - 1) / 2`` base pixels, GDAL's
``nearest`` by about half a pixel), a shift of the overview that the full-resolution
refinement after the coarse alignment absorbs; the file does not say how a level was
made, so nothing here guesses.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["FileLevel", "FileLevels", "check_level", "tiff_levels", "zarr_levels"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FileLevel:
    """One reduced-resolution level of an image.

    Attributes
    ----------
    array : array-like
        ``(h, w)`` or ``(h, w, C)`` reader of the level, with the bands, dtype and pixel
        values of the base image's view (slicing returns numpy arrays).
    factor : (float, float)
        Base pixels per level pixel along rows and columns.
    origin : (float, float)
        Base position (pixel edges) of the level's top-left corner.
    name : str
        Where it comes from, e.g. ``"TIFF level 2"``.
    """

    array: Any
    factor: tuple[float, float]
    origin: tuple[float, float] = (0.0, 0.0)
    name: str = ""

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.array.shape[0]), int(self.array.shape[1])

    def describe(self) -> dict[str, Any]:
        """JSON-ready description: name, shape, factors (and origin when not 0)."""
        d: dict[str, Any] = dict(name=self.name, shape=list(self.shape),
                                 factor=[round(float(f), 6) for f in self.factor])
        if any(self.origin):
            d["origin"] = [round(float(o), 6) for o in self.origin]
        return d


#: What an opener returns: the levels (in the base's layout), the reasons some were
#: ignored, and a function that releases the file.
Opened = tuple[list[FileLevel], list[str], Callable[[], None]]


class _Compose:
    """``outer(inner(a))``; picklable when both are."""

    def __init__(self, outer: Callable, inner: Callable):
        self.outer, self.inner = outer, inner

    def __call__(self, a):
        return self.outer(self.inner(a))


def _identity(a):
    return a


class FileLevels:
    """The reduced-resolution levels of an image file, opened by path when asked.

    It holds no open file: :meth:`open` opens the file, checks its levels
    (:func:`check_level`) and releases it at the end of the ``with`` block, so it pickles
    (the opener is a picklable callable) and costs nothing until used.

    Parameters
    ----------
    opener : callable
        ``opener() -> (levels, ignored, close)``: the levels in the layout of the image
        opened from the same file, the reasons levels were ignored, a release function.
    source : str
        What holds them, e.g. ``"pyramidal TIFF"`` or ``"zarr multiscales"``.
    key : str
        The file (two level sets with one key come from one file).
    transform : callable, optional
        Applied to each level's array: the view the image is read through.
    """

    def __init__(self, opener: Callable[[], Opened], source: str, key: str,
                 transform: Callable = _identity):
        self.opener, self.source, self.key, self.transform = opener, source, key, transform

    def __repr__(self) -> str:
        return f"FileLevels({self.source}, {self.key})"

    def map(self, fn: Callable) -> FileLevels:
        """The same levels seen through the view ``fn`` (``fn(level_array) -> view``,
        the view an image wrapper puts over its source)."""
        return FileLevels(self.opener, self.source, self.key, _Compose(fn, self.transform))

    @contextlib.contextmanager
    def open(self) -> Iterator[tuple[list[FileLevel], list[str]]]:
        """Yield the usable levels (finest first, through :attr:`transform`) and the
        reasons the others were ignored; the file is released afterwards."""
        levels, ignored, close = self.opener()
        try:
            out = [FileLevel(self.transform(lv.array), lv.factor, lv.origin, lv.name)
                   for lv in levels]
            yield sorted(out, key=lambda lv: min(lv.factor)), ignored
        finally:
            close()


def combine(a: FileLevels | None, b: FileLevels | None, fn: Callable) -> FileLevels | None:
    """Levels of a view reading two views of one file (``fn(view_a, view_b)``): None
    unless both have levels from the same file."""
    if a is None or b is None or a.key != b.key:
        return None
    return FileLevels(a.opener, a.source, a.key, _Pair(fn, a.transform, b.transform))


class _Pair:
    def __init__(self, fn: Callable, ta: Callable, tb: Callable):
        self.fn, self.ta, self.tb = fn, ta, tb

    def __call__(self, a):
        return self.fn(self.ta(a), self.tb(a))


# ---------------------------------------------------------------------------- geometry
def check_level(base: tuple[int, int], level: tuple[int, int],
                stated: tuple[float, float] | None = None) -> tuple[float, float] | str:
    """The per-axis factors of a level, or why it cannot be one.

    Parameters
    ----------
    base, level : (int, int)
        ``(H, W)`` of the base image and ``(h, w)`` of the level.
    stated : (float, float), optional
        Factors the file's metadata states (rows, columns).

    Returns
    -------
    (float, float) or str
        ``stated`` or ``(H / h, W / w)`` when the level is smaller than the base on both
        axes and one factor ``f`` explains both sides to within a pixel
        (``|H / f - h| < 1``, ``|W / f - w| < 1``); otherwise the reason, one line.
    """
    (H, W), (h, w) = base, level
    if h < 1 or w < 1:
        return f"{h}x{w} is empty"
    if not (h < H and w < W):
        return f"{w}x{h} is not smaller than the base {W}x{H}"
    if stated is not None:
        sy, sx = (float(v) for v in stated)
        if not (math.isfinite(sy) and math.isfinite(sx) and sy > 1 and sx > 1):
            return f"its stated scale {sy:g} x {sx:g} is not a reduction"
        if abs(H / sy - h) >= 1 or abs(W / sx - w) >= 1:
            return (f"its stated scale {sy:g} x {sx:g} does not give its size {w}x{h} from "
                    f"the base {W}x{H}")
        return sy, sx
    # one factor within a pixel on both sides: the intervals of f overlap
    lo = max(H / (h + 1), W / (w + 1))
    hi = min(H / (h - 1) if h > 1 else math.inf, W / (w - 1) if w > 1 else math.inf)
    if not lo < hi:
        return (f"{w}x{h} is not one downsampling of the base {W}x{H} (factors "
                f"{W / w:.4g} across, {H / h:.4g} down: another aspect)")
    return H / h, W / w


def _checked(base: tuple[int, int], found: list[tuple[Any, str, tuple | None, tuple]]
             ) -> tuple[list[FileLevel], list[str]]:
    """``found``: (array, name, stated factors or None, origin) -> the levels that pass
    :func:`check_level` and the reasons of the others."""
    levels, ignored = [], []
    for arr, name, stated, origin in found:
        got = check_level(base, (int(arr.shape[0]), int(arr.shape[1])), stated)
        if isinstance(got, str):
            ignored.append(f"{name}: {got}")
        else:
            levels.append(FileLevel(arr, got, origin, name))
    return levels, ignored


# ---------------------------------------------------------------------------- TIFF
def tiff_levels(path: str | Path) -> FileLevels:
    """The levels of the first image series of a TIFF (SubIFDs of a pyramidal OME-TIFF,
    reduced-resolution pages of a COG or GeoTIFF with overviews), as tifffile lists them
    in ``series[0].levels``."""
    p = str(Path(path))
    return FileLevels(functools.partial(_open_tiff_levels, p), "pyramidal TIFF", p)


def tiff_has_levels(series) -> bool:
    """Whether a tifffile series lists reduced-resolution levels."""
    return len(getattr(series, "levels", ()) or ()) > 1


def _open_tiff_levels(path: str) -> Opened:
    import tifffile

    from .io import _tiff_layout, _tiff_view, _tifffile_quiet

    try:
        with _tifffile_quiet():  # its log lines (e.g. on GDAL's appended overviews) kept
            tif = tifffile.TiffFile(path)
            series = tif.series[0]
    except Exception as exc:  # noqa: BLE001 - an unreadable file has no usable levels
        return [], [f"cannot reopen the file ({exc})"], lambda: None
    try:
        axes, shape = series.axes, tuple(int(s) for s in series.shape)
        base = (shape[axes.index("Y")], shape[axes.index("X")])
        found, ignored = [], []
        for i, lv in enumerate(series.levels[1:], start=1):
            name = f"TIFF level {i}"
            why = _tiff_level_problem(path, series, lv)
            if why:
                ignored.append(f"{name}: {why}")
                continue
            layout = _tiff_layout(lv.axes, tuple(int(s) for s in lv.shape))
            if layout is None:
                ignored.append(f"{name}: unsupported layout (axes {lv.axes})")
                continue
            view, chunks = _tiff_view(series, layout, Path(path), level=i)
            why = _chunk_problem(chunks, lv.dtype)
            if why:
                ignored.append(f"{name}: {why}")
                continue
            found.append((view, name, None, (0.0, 0.0)))
        levels, bad = _checked(base, found)
        return levels, ignored + bad, tif.close
    except Exception as exc:  # noqa: BLE001 - a level tifffile cannot describe is unusable
        tif.close()
        return [], [f"cannot read the file's levels ({exc})"], lambda: None


def _chunk_problem(chunks, dtype) -> str | None:
    """Why a level's chunks are too large to decode (as :data:`reblur.io.CHUNK_MAX_BYTES`
    guards the image's own), or None."""
    from .io import CHUNK_MAX_BYTES

    n = int(np.prod([int(c) for c in chunks], dtype=np.int64)) * np.dtype(dtype).itemsize
    if n > CHUNK_MAX_BYTES:
        return f"its chunks decode to {n / 2**20:.0f} MB each (at most " \
               f"{CHUNK_MAX_BYTES / 2**20:.0f} MB)"
    return None


def _tiff_level_problem(path: str, series, lv) -> str | None:
    """Why a tifffile level cannot stand for the series' base (None: it can)."""
    import os

    import tifffile

    if lv.axes != series.axes:
        return f"axes {lv.axes} differ from the base's {series.axes}"
    base = dict(zip(series.axes, series.shape, strict=True))
    for a, n in zip(lv.axes, lv.shape, strict=True):
        if a not in "YX" and n != base[a]:
            return f"{n} along {a}, the base has {base[a]} (another band layout)"
    if np.dtype(lv.dtype) != np.dtype(series.dtype):
        return f"dtype {lv.dtype} differs from the base's {series.dtype}"
    page = lv.keyframe
    if int(page.compression) != 1:
        try:
            tifffile.TIFF.DECOMPRESSORS[page.compression]
        except Exception:  # noqa: BLE001 - unknown code or missing codec
            return f"its compression {page.compression!r} cannot be decoded"
    size = os.path.getsize(path)
    for pg in lv.pages:
        if pg is None:
            return "a page is missing"
        offs = np.asarray(getattr(pg, "dataoffsets", ()) or (), dtype=np.int64)
        cnts = np.asarray(getattr(pg, "databytecounts", ()) or (), dtype=np.int64)
        if offs.size and ((offs + cnts).max() > size or (cnts <= 0).any()):
            return "its data is truncated or missing"
    return None


# ---------------------------------------------------------------------------- zarr
def zarr_multiscales(group) -> list[dict] | None:
    """The ``datasets`` of a zarr group's first multiscales entry (OME-NGFF 0.4:
    ``attrs["multiscales"]``, 0.5: ``attrs["ome"]["multiscales"]``), or None."""
    attrs = dict(getattr(group, "attrs", {}) or {})
    ms = attrs.get("multiscales")
    if ms is None and isinstance(attrs.get("ome"), dict):
        ms = attrs["ome"].get("multiscales")
    if not isinstance(ms, list) or not ms or not isinstance(ms[0], dict):
        return None
    ds = ms[0].get("datasets")
    if not isinstance(ds, list) or len(ds) < 2:
        return None
    return [d for d in ds if isinstance(d, dict) and isinstance(d.get("path"), str)]


def zarr_levels(path: str | Path, base_name: str) -> FileLevels:
    """The levels of a zarr group's multiscales whose first dataset is ``base_name``."""
    p = str(Path(path))
    return FileLevels(functools.partial(_open_zarr_levels, p, base_name), "zarr multiscales",
                      p)


def _transform(d: dict, kind: str, n: int) -> list[float] | None:
    for t in d.get("coordinateTransformations") or ():
        if isinstance(t, dict) and t.get("type") == kind and isinstance(t.get(kind), list):
            v = t[kind]
            if len(v) == n and all(isinstance(x, (int, float)) for x in v):
                return [float(x) for x in v]
    return None


def _spatial_axes(group, ndim: int) -> tuple[int, int]:
    """Indices of the row and column axes: named ``y``, ``x`` in the multiscales' axes,
    else the first two (reblur's (H, W[, C]) layout)."""
    attrs = dict(getattr(group, "attrs", {}) or {})
    ms = attrs.get("multiscales") or (attrs.get("ome") or {}).get("multiscales") or [{}]
    names = [a.get("name") if isinstance(a, dict) else a for a in ms[0].get("axes") or ()]
    if len(names) == ndim and "y" in names and "x" in names:
        return names.index("y"), names.index("x")
    return 0, 1


def _unwritten(arr) -> str | None:
    """Why a zarr level cannot be trusted: chunks never written (they would read as the
    fill value, as :func:`reblur.io.open_image` refuses for the image itself)."""
    try:
        total, written = int(arr.nchunks), int(arr.nchunks_initialized)
    except Exception as exc:  # noqa: BLE001 - an unlistable store is an unusable level
        return f"its chunks cannot be listed ({exc})"
    if written < total:
        return f"{total - written} of its {total} chunks were never written"
    return None


def _open_zarr_levels(path: str, base_name: str) -> Opened:
    import zarr

    from .io import _Guarded

    try:
        group = zarr.open(path, mode="r")
        datasets = zarr_multiscales(group) or []
    except Exception as exc:  # noqa: BLE001 - an unreadable store has no usable levels
        return [], [f"cannot reopen the store ({exc})"], lambda: None
    if not datasets or datasets[0]["path"] != base_name:
        return [], ["the multiscales' first dataset is not the array read"], lambda: None
    base = group[base_name]
    ndim = len(base.shape)
    iy, ix = _spatial_axes(group, ndim)
    if (iy, ix) != (0, 1):
        return [], [f"spatial axes at {iy}, {ix}: reblur reads (y, x[, c]) arrays"], \
            lambda: None
    s0 = _transform(datasets[0], "scale", ndim)
    t0 = _transform(datasets[0], "translation", ndim) or [0.0] * ndim
    found, ignored = [], []
    for d in datasets[1:]:
        name = f"zarr dataset {d['path']!r}"
        try:
            arr = group[d["path"]]
        except Exception as exc:  # noqa: BLE001 - a listed dataset that is not there
            ignored.append(f"{name}: cannot be opened ({exc})")
            continue
        if len(arr.shape) != ndim or tuple(arr.shape[2:]) != tuple(base.shape[2:]):
            ignored.append(f"{name}: shape {tuple(arr.shape)} has another band layout than "
                           f"the base's {tuple(base.shape)}")
            continue
        if np.dtype(arr.dtype) != np.dtype(base.dtype):
            ignored.append(f"{name}: dtype {arr.dtype} differs from the base's {base.dtype}")
            continue
        why = _chunk_problem(arr.chunks, arr.dtype) or _unwritten(arr)
        if why:
            ignored.append(f"{name}: {why}")
            continue
        s = _transform(d, "scale", ndim)
        stated = None
        if s is not None and s0 is not None and s0[0] > 0 and s0[1] > 0:
            stated = (s[0] / s0[0], s[1] / s0[1])
        origin = (0.0, 0.0)
        t = _transform(d, "translation", ndim)
        if t is not None and stated is not None and (t[0] != t0[0] or t[1] != t0[1]):
            # a stated translation puts the level's pixel centre 0 at base (t - t0) / s0
            origin = tuple(((t[i] - t0[i]) / s0[i]) + 0.5 - 0.5 * stated[i] for i in (0, 1))
        view = arr if ndim == 2 or base.shape[2] != 1 else None
        if view is None:  # (H, W, 1) is read as (H, W)
            from .io import LazyBands

            view = LazyBands(arr, bands=(0,))
        found.append((_Guarded(view, Path(path)), name, stated, origin))
    levels, bad = _checked((int(base.shape[0]), int(base.shape[1])), found)
    return levels, ignored + bad, lambda: None
