"""Write the results of :func:`reblur.detect_changes` into an output directory.

:func:`write_report` writes, each file atomically (:func:`reblur.io.atomic_path`):

``changes.png``
    The change mask, uint8 255 (change) / 0, in the observation's frame and size; unknown
    pixels are 0.  Byte-identical for identical masks.  Skipped above
    :data:`PNG_MAX_PIXELS` (``changes.tif`` holds the mask then).
``changes.tif``, ``unknown.tif``
    The same masks as Cloud-Optimised GeoTIFFs (:func:`reblur.gis.write_cog`: tiled,
    internal overviews whose pixels are the maximum of those they cover, so a change of one
    pixel shows at every zoom), written tile by tile, when the image has more than
    :data:`BIG_MASK_PIXELS` pixels or the observation is georeferenced (then with its CRS
    and transform).
``unknown.png``
    Observation pixels the aligned reference does not cover, 255 / 0.
``reblurred.tif``
    The reblurred reference in the observation's frame and dtype, a Cloud-Optimised
    GeoTIFF with averaged overviews (georeferenced like the observation); the unknown
    pixels hold no data (an internal mask, or NaN in a float image), written tile by
    tile from the result's array -- in memory, or on disk at any size
    (:class:`reblur.gis.ReblurredStore`); skipped, with a note in ``report.json``, when the
    result holds none.
``overlay.png``
    The observation, downscaled to at most :data:`OVERLAY_MAX_SIDE` pixels on its long
    side, with changes filled in translucent red and outlined in yellow, unknown shaded.
``motion.png``
    The pose weights (a tx-ty image per rotation carrying weight) and the blur kernels they
    make at a 3x3 grid of image positions.
``field.png``
    When a local displacement field was applied (:mod:`reblur.align.field`): its magnitude over
    the observation, with arrows, in pixels.
``rolling.png``
    When the rolling-shutter model was used (:mod:`reblur.rolling`): every row band's mean
    pose against its centre row, and the estimated readout fraction.
``report.json``, ``report.html``
    Inputs, alignment, chosen windows, non-zero poses, threshold, changed area, regions,
    timings, peak memory, options, version and (given a truth mask) scores; the HTML page
    embeds the two pictures and links the other files.
``changes.geojson``, ``changes.gpkg``
    With a georeferenced observation: one polygon per change region in its CRS, traced tile
    by tile and merged across tile borders, simplified by at most half a pixel, with the
    region's triage attributes (:func:`reblur.gis.change_features`); the GeoPackage when
    the ``geo`` extra is installed (``pip install reblur[geo]``), else a note says so.
``viewer/``
    A zoomable, offline viewer (``viewer/index.html``; :mod:`reblur.viewer`): tile pyramids
    of the observation, the reblurred reference and the masks, the strongest regions'
    outlines and the estimation windows.
"""

from __future__ import annotations

import base64
import html
import importlib
import importlib.metadata
import os
import shutil
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from ._memory import peak_rss_mb
from .estimate import T_EDGE_SHARE
from .gis import (
    FEATURE_KEYS,
    ReblurredStore,
    change_features,
    geopackage_available,
    quantize,
    region_features,
    write_cog,
    write_geojson,
    write_geopackage,
)
from .io import (
    Image,
    iter_windows,
    printable,
    to_jsonable,
    write_json,
    write_png,
    write_png_bands,
)
from .result import ChangeResult, MotionEstimate
from .viewer import ViewerOptions
from .viewer.layers import _display_bands

__all__ = [
    "OUTPUT_NAMES",
    "BIG_MASK_PIXELS",
    "OVERLAY_MAX_SIDE",
    "write_report",
    "existing_outputs",
    "remove_outputs",
    "downscale",
    "overlay_image",
    "blur_kernels",
    "motion_figure",
    "field_figure",
    "change_polygons",
    "summarize",
    "summary_line",
]

#: Every file name :func:`write_report` may write.
OUTPUT_NAMES = (
    "changes.png",
    "changes.tif",
    "unknown.png",
    "unknown.tif",
    "reblurred.tif",
    "overlay.png",
    "motion.png",
    "field.png",
    "rolling.png",
    "report.json",
    "report.html",
    "changes.geojson",
    "changes.gpkg",
    "viewer",
)

#: Above this many pixels the change mask is also written as a tiled TIFF.
BIG_MASK_PIXELS = 50_000_000

#: Above this many pixels no PNG mask is written (OpenCV's codec limit), only TIFF.
PNG_MAX_PIXELS = 2**30

#: Long side of ``overlay.png``.
OVERLAY_MAX_SIDE = 2048

#: Tile side (px) of the GeoTIFFs written (:func:`reblur.gis.write_cog`).
COG_BLOCK = 512

#: At most this many regions are listed in ``report.json`` (strongest first, :func:`triage`).
MAX_LISTED_REGIONS = 1000


# ---------------------------------------------------------------------------- helpers
class _MaskView:
    """Lazy uint8 255/0 view of ``change & ~unknown`` (read tile by tile by the writers)."""

    def __init__(self, change, unknown=None):
        self.change, self.unknown = change, unknown
        self.shape = tuple(int(s) for s in change.shape[:2])
        self.dtype = np.dtype(np.uint8)
        #: the masks' chunks (zarr on disk): the writers read whole chunks
        self.chunks = getattr(change, "chunks", None)

    def __getitem__(self, key) -> np.ndarray:
        m = np.asarray(self.change[key], dtype=bool)
        if self.unknown is not None:
            m = m & ~np.asarray(self.unknown[key], dtype=bool)
        return m.astype(np.uint8) * np.uint8(255)


def _mask_bands(change, unknown=None) -> Iterator[np.ndarray]:
    """``change & ~unknown`` as uint8 255/0, band by band of rows (the masks' chunks, or
    about 16 MB): what the PNG masks are written from, never the whole image at once (a
    1 Gpx ``changes.png`` from one array held 1 GB more than the detection's peak)."""
    view = _MaskView(change, unknown)
    H, W = view.shape
    step = int(view.chunks[0]) if view.chunks else _row_step((H, W), 3, 1, 16 * 2**20)
    for y0 in range(0, H, step):
        yield view[y0:min(H, y0 + step)]


def _row_step(shape: tuple[int, ...], itemsize: int, multiple: int,
              target: int = 64 * 2**20) -> int:
    row = max(1, int(np.prod(shape[1:])) * itemsize)
    k = max(1, target // (row * multiple))
    return k * multiple


#: dtypes whose block maxima OpenCV's dilation takes (integers: a float NaN keeps numpy's
#: rule, a block holding one is NaN)
_CV_DEPTHS = (np.uint8, np.uint16, np.int16)


#: Bytes of the working buffer of :func:`_block_reduce` (reused band after band: a fresh
#: full-band float copy costs page faults that dwarfed the reduction on this VM).
_REDUCE_BUFFER = 8 * 2**20


#: Bytes of the bands :func:`downscale` reads: under glibc's largest mmap threshold
#: (32 MB), so a freed band's pages serve the next one; 64 MB bands were mapped afresh
#: each time, and their page faults took most of the overlay's time on this VM.
DOWNSCALE_BAND = 16 * 2**20


def _block_reduce(a: np.ndarray, s: int, how: str) -> np.ndarray:
    """Mean (float32) or maximum (same dtype) of every ``s x s`` block of ``a``, partial
    blocks at the bottom and right included (over their own pixels).

    OpenCV does the work, a few rows of blocks at a time in one reused buffer: the maximum
    is a dilation by an ``s x s`` box anchored at its top-left corner, read at the blocks'
    corners; the mean of the whole blocks an area resize by ``1/s`` of their float32
    copy, which for an integer factor is the block mean.  :func:`_block_reduce_np` remains
    for the dtypes and band counts OpenCV does not take and for the partial blocks' strips
    of the mean."""
    import cv2

    r, w = a.shape[:2]
    bands = a.shape[2] if a.ndim == 3 else 1
    if bands > 4 or a.dtype == np.bool_ or (how == "max" and a.dtype.type not in _CV_DEPTHS):
        return _block_reduce_np(a, s, how)
    ny, nx, h, v = -(-r // s), -(-w // s), r // s, w // s
    if how == "max":
        out = np.empty((ny, nx) + a.shape[2:], a.dtype)
        step = max(1, _REDUCE_BUFFER // (s * w * bands * a.dtype.itemsize))  # rows of blocks
        buf = np.empty((min(ny, step) * s, w) + a.shape[2:], a.dtype)
        box = np.ones((s, s), np.uint8)
        for i0 in range(0, ny, step):
            src = np.ascontiguousarray(a[i0 * s:(i0 + step) * s])
            dst = buf[: src.shape[0]]
            cv2.dilate(src, box, dst=dst, anchor=(0, 0))
            out[i0:i0 + step] = dst[::s, ::s]
        return out
    out = np.empty((ny, nx) + a.shape[2:], np.float32)
    if h and v:
        step = max(1, _REDUCE_BUFFER // (s * v * s * bands * 4))
        buf = np.empty((min(h, step) * s, v * s) + a.shape[2:], np.float32)
        for i0 in range(0, h, step):
            i1 = min(h, i0 + step)
            sub = buf[: (i1 - i0) * s]
            np.copyto(sub, a[i0 * s:i1 * s, : v * s], casting="unsafe")
            out[i0:i1, :v] = cv2.resize(sub, (v, i1 - i0), interpolation=cv2.INTER_AREA
                                        ).reshape(out[i0:i1, :v].shape)
    if h < ny:  # the partial bottom row of blocks
        out[h:] = _block_reduce_np(a[h * s:], s, how)
    if v < nx and h:  # the partial right column of blocks, above it
        out[:h, v:] = _block_reduce_np(a[: h * s, v * s:], s, how)
    return out


def _block_reduce_np(a: np.ndarray, s: int, how: str) -> np.ndarray:
    """:func:`_block_reduce` by numpy's reductions of ``a`` padded to whole blocks."""
    r, w = a.shape[:2]
    R, Wp = -(-r // s) * s, -(-w // s) * s
    if (R, Wp) != (r, w):  # padding that takes no part: 0 in a sum, the least value in a max
        low = 0 if how != "max" or a.dtype == np.bool_ else (
            np.iinfo(a.dtype).min if a.dtype.kind in "iu" else -np.inf)
        pad = np.full((R, Wp) + a.shape[2:], low, a.dtype)
        pad[:r, :w] = a
        a = pad
    b = a.reshape((R // s, s, Wp // s, s) + a.shape[2:])
    if how == "max":
        return b.max(axis=(1, 3))
    total = b.sum(axis=(1, 3), dtype=np.float64)
    rows = np.minimum(s, r - s * np.arange(R // s))
    cols = np.minimum(s, w - s * np.arange(Wp // s))
    cnt = np.outer(rows, cols).astype(np.float64)
    if total.ndim == 3:
        cnt = cnt[:, :, None]
    return (total / cnt).astype(np.float32)


def downscale(array, max_side: int = OVERLAY_MAX_SIDE, how: str = "mean") -> np.ndarray:
    """Shrink an image (numpy or lazy) by an integer factor so its long side <= ``max_side``.

    Reads bands of rows (about :data:`DOWNSCALE_BAND` bytes at a time), so it works on
    images larger than memory.  The result is a new array, never a view of ``array``.

    Parameters
    ----------
    array : array-like, (H, W) or (H, W, C)
    max_side : int
    how : {"mean", "max"}
        Block mean (float32) or block maximum (keeps the dtype; for masks, so a one-pixel
        change stays visible).
    """
    shape = tuple(int(v) for v in array.shape)
    s = max(1, -(-max(shape[:2]) // max_side))
    if s == 1:
        a = np.asarray(array[...])
        return a.astype(np.float32) if how == "mean" else a.copy()
    step = _row_step(shape, np.dtype(array.dtype).itemsize, s, DOWNSCALE_BAND)
    parts = []
    for y in range(0, shape[0], step):
        block = np.asarray(array[y : min(y + step, shape[0])])
        parts.append(_block_reduce(block, s, how))
    return np.concatenate(parts, axis=0)


def _display_stretch(small: np.ndarray, dtype: np.dtype) -> tuple[float, float] | None:
    """``(lo, hi)``, the 1-99 % range of a downscaled image that is not uint8 (None for
    uint8, shown as is): one pass over the whole image, so every band of
    :func:`_display_rgb` is stretched alike."""
    if np.dtype(dtype) == np.uint8:
        return None
    lo, hi = np.percentile(_display_bands(np.asarray(small, dtype=np.float32)), [1.0, 99.0])
    return lo, hi


def _display_rgb(small: np.ndarray, dtype: np.dtype,
                 stretch: tuple[float, float] | None = None) -> np.ndarray:
    """Float RGB in [0, 1] for display: uint8 as is, others stretched to the 1-99 % range
    (``stretch``, from :func:`_display_stretch`; computed from ``small`` when not given)."""
    a = _display_bands(np.asarray(small, dtype=np.float32))
    if np.dtype(dtype) == np.uint8:
        a = a / 255.0
    else:
        lo, hi = _display_stretch(a, dtype) if stretch is None else stretch
        a = (a - lo) / (hi - lo) if hi > lo else np.zeros_like(a)
    a = np.clip(a, 0.0, 1.0)
    if a.shape[2] == 1:
        a = np.repeat(a, 3, axis=2)
    return a


#: Rows of the overlay drawn at a time: its float temporaries stay a few MB.  Drawn whole,
#: a 2048 px overlay of a 16-bit image held ~100 MB float64 arrays, each freshly mapped
#: by the C library (above its 32 MB mmap threshold): 1.0-4.0 s on the first call here,
#: almost all of it first-touch page faults (``python -m benchmarks.pictures``).
OVERLAY_BAND_ROWS = 128


def overlay_image(
    observed, change, unknown=None, *, max_side: int = OVERLAY_MAX_SIDE
) -> np.ndarray:
    """The observation with changes (red fill, yellow outline) and unknown (dark) drawn in.

    Parameters
    ----------
    observed : array-like, (H, W) or (H, W, C)
        Observation (numpy or lazy), any dtype.
    change, unknown : (H, W) bool array-like
        Masks in the observation frame.
    max_side : int
        Long side of the result (the image is shrunk by an integer factor).

    Returns
    -------
    (h, w, 3) uint8 RGB
    """
    import cv2

    dtype = np.dtype(observed.dtype)
    small = downscale(observed, max_side, "mean")
    stretch = _display_stretch(small, dtype)
    chg = downscale(_BoolView(change), max_side, "max").astype(bool)
    unk = (None if unknown is None
           else downscale(_BoolView(unknown), max_side, "mean") > 0.5)
    dark = 0.7 * np.array([0.15, 0.15, 0.25], np.float32)
    red = 0.45 * np.array([1.0, 0.0, 0.0], np.float32)
    u8 = np.empty(small.shape[:2] + (3,), np.uint8)
    # band by band, the same arithmetic on every pixel as on the whole image
    for y0 in range(0, u8.shape[0], OVERLAY_BAND_ROWS):
        rows = slice(y0, y0 + OVERLAY_BAND_ROWS)
        out = _display_rgb(small[rows], dtype, stretch)
        if unk is not None:
            u = unk[rows]
            out[u] = 0.3 * out[u] + dark
        c = chg[rows]
        out[c] = 0.55 * out[c] + red
        u8[rows] = np.clip(np.rint(out * 255.0), 0, 255)
    contours, _ = cv2.findContours(chg.astype(np.uint8), cv2.RETR_EXTERNAL,
                                   cv2.CHAIN_APPROX_NONE)
    thickness = 2 if max(u8.shape[:2]) > 1000 else 1
    cv2.drawContours(u8, contours, -1, (255, 230, 0), thickness)
    return u8


class _BoolView:
    """uint8 0/1 view of a bool array-like (``downscale`` reads it in bands)."""

    def __init__(self, mask):
        self.mask = mask
        self.shape = tuple(int(s) for s in mask.shape[:2])
        self.dtype = np.dtype(np.uint8)

    def __getitem__(self, key) -> np.ndarray:
        return np.asarray(self.mask[key], dtype=bool).view(np.uint8)  # 0 / 1, no copy


# ---------------------------------------------------------------------------- motion
def kernel_positions(image_shape: tuple[int, int], fractions=(0.1, 0.5, 0.9)) -> np.ndarray:
    """A 3x3 grid of ``(x, y)`` positions at ``fractions`` of the width and height."""
    h, w = image_shape
    return np.array([(fx * (w - 1), fy * (h - 1)) for fy in fractions for fx in fractions])


def blur_kernels(
    motion: MotionEstimate, points: np.ndarray, *, radius: int | None = None
) -> tuple[np.ndarray, int]:
    """Blur kernels (point-spread functions) of the estimated motion at image positions.

    For each pose ``k`` with weight ``w_k``, the position ``p`` moves to
    ``grid.homography(k) p``; its displacement relative to ``p`` receives ``w_k``
    (bilinear splat).

    Parameters
    ----------
    motion : MotionEstimate
    points : (n, 2) array
        ``(x, y)`` positions in full observation pixels.
    radius : int, optional
        Half-size of the kernels; default covers the largest displacement.

    Returns
    -------
    kernels : (n, 2 r + 1, 2 r + 1) float ndarray
        ``kernels[i][r + dy, r + dx]`` is the weight displaced by ``(dx, dy)``.
    r : int
    """
    from .grid import map_points

    grid = motion.grid
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    nz = grid.nonzero(motion.weights)
    disp = np.zeros((len(nz), len(pts), 2))
    wts = np.array([w for *_, w in nz], dtype=float)
    for k, (b, iy, ix, _) in enumerate(nz):
        disp[k] = map_points(grid.homography((b, iy, ix)), pts) - pts
    if radius is None:
        radius = int(np.ceil(np.abs(disp).max())) + 1 if len(nz) else 3
        radius = max(radius, 3)
    r = int(radius)
    n = 2 * r + 1
    kernels = np.zeros((len(pts), n, n))
    for i in range(len(pts)):
        x = disp[:, i, 0] + r
        y = disp[:, i, 1] + r
        x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
        fx, fy = x - x0, y - y0
        for dy, wy in ((0, 1 - fy), (1, fy)):
            for dx, wx in ((0, 1 - fx), (1, fx)):
                yy, xx = y0 + dy, x0 + dx
                ok = (yy >= 0) & (yy < n) & (xx >= 0) & (xx < n)
                np.add.at(kernels[i], (yy[ok], xx[ok]), (wts * wy * wx)[ok])
    return kernels, r


def _base_label(base: tuple[float, float, float, float]) -> str:
    tz, rx, ry, rz = base
    parts = [f"rz={rz:g}°"]
    if tz:
        parts.append(f"tz={tz:g}")
    if rx:
        parts.append(f"rx={rx:g}°")
    if ry:
        parts.append(f"ry={ry:g}°")
    return " ".join(parts)


#: Side (px) of a panel of ``motion.png``; top left corners of its first pose-weight and
#: first blur-kernel panels.
_PANEL_PX = 150
_POSES_AT = (20, 64)
_KERNELS_AT = (740, 64)
_FONT = 0  # cv2.FONT_HERSHEY_SIMPLEX


def _text(canvas: np.ndarray, text: str, x: int, y: int, size: float = 0.4,
          centre: bool = False) -> None:
    """Draw ASCII ``text`` in black on ``canvas`` with its baseline at ``y`` (left end at
    ``x``, or centred on it)."""
    import cv2

    text = text.replace("\N{DEGREE SIGN}", " deg")
    if centre:
        x -= cv2.getTextSize(text, _FONT, size, 1)[0][0] // 2
    cv2.putText(canvas, text, (int(x), int(y)), _FONT, size, (0, 0, 0), 1, cv2.LINE_AA)


def _panel(values: np.ndarray, vmax: float, cmap: int | None) -> np.ndarray:
    """``values`` in ``[0, vmax]`` as a :data:`_PANEL_PX` square RGB image (nearest
    neighbour) in the OpenCV colour map ``cmap``, or black on white (None), framed."""
    import cv2

    u8 = np.clip(np.asarray(values, float) / (vmax if vmax > 0 else 1.0) * 255, 0, 255)
    u8 = cv2.resize(u8.astype(np.uint8), (_PANEL_PX, _PANEL_PX),
                    interpolation=cv2.INTER_NEAREST)
    rgb = (np.repeat((255 - u8)[:, :, None], 3, axis=2) if cmap is None
           else cv2.applyColorMap(u8, cmap)[:, :, ::-1])
    rgb = np.ascontiguousarray(rgb)
    cv2.rectangle(rgb, (0, 0), (_PANEL_PX - 1, _PANEL_PX - 1), (0, 0, 0), 1)
    return rgb


def _panels(canvas: np.ndarray, images: list[np.ndarray], titles: list[str], cols: int,
            x0: int, y0: int, gap: int = 34) -> None:
    """Paste ``images`` (panels) on ``canvas`` in ``cols`` columns from ``(x0, y0)``, each
    with its title above it."""
    for i, (img, title) in enumerate(zip(images, titles, strict=True)):
        x = x0 + (i % cols) * (_PANEL_PX + gap)
        y = y0 + (i // cols) * (_PANEL_PX + gap)
        canvas[y:y + _PANEL_PX, x:x + _PANEL_PX] = img
        _text(canvas, title, x + _PANEL_PX // 2, y - 6, 0.38, centre=True)


def motion_figure(motion: MotionEstimate, path: str | os.PathLike, *,
                  max_panels: int = 9) -> Path:
    """Draw the pose weights and blur kernels into a PNG (atomically).

    Left: for each base pose (rotation) carrying weight, heaviest ``max_panels`` of them,
    the weights as an image over ``(tx, ty)`` (one colour scale, its bar on the right).
    Right: :func:`blur_kernels` at a 3x3 grid of image positions (10, 50, 90 % of width
    and height), each scaled to its own maximum.  Drawn with OpenCV: a few milliseconds,
    where a plotting library spends a second on the axes.
    """
    import cv2

    grid = motion.grid
    w = grid.check_weights(motion.weights)
    mass = w.sum(axis=(1, 2))
    total = float(mass.sum())
    order = [int(b) for b in np.argsort(-mass, kind="stable") if mass[b] > 0][:max_panels]
    order.sort(key=lambda b: grid.bases[b][::-1])
    step = _PANEL_PX + 34
    canvas = np.full((90 + 3 * step, 1320, 3), 255, np.uint8)
    vmax = float(w.max()) if w.size and w.max() > 0 else 1.0
    cols = max(1, int(np.ceil(np.sqrt(max(1, len(order))))))
    _panels(canvas, [_panel(w[b], vmax, cv2.COLORMAP_MAGMA) for b in order],
            [f"{_base_label(grid.bases[b])}  ({100 * mass[b] / total:.0f} %)" for b in order],
            cols, *_POSES_AT)
    tx, ty = np.asarray(grid.tx), np.asarray(grid.ty)
    _text(canvas, f"pose weights ({sum(1 for _ in grid.nonzero(w))} of {grid.size} poses)",
          300, 22, 0.55, centre=True)
    _text(canvas, f"each panel: tx {tx[0]:g}..{tx[-1]:g} px (right), ty {ty[0]:g}.."
          f"{ty[-1]:g} px (down)", 300, 42, 0.4, centre=True)
    if not order:
        _text(canvas, "no pose carries weight", 300, 200, 0.5, centre=True)
    else:  # the colour bar
        bar = _panel(np.linspace(vmax, 0, 256)[:, None], vmax, cv2.COLORMAP_MAGMA)
        bar = cv2.resize(bar, (14, 3 * step - 34), interpolation=cv2.INTER_NEAREST)
        x = 20 + cols * step
        canvas[64:64 + bar.shape[0], x:x + 14] = bar
        _text(canvas, f"{vmax:.3g}", x + 18, 74)
        _text(canvas, "0", x + 18, 64 + bar.shape[0])
        _text(canvas, "pose weight", x + 18, 64 + bar.shape[0] // 2)
    pts = kernel_positions(grid.image_shape)
    kernels, r = blur_kernels(motion, pts)
    _panels(canvas, [_panel(k, float(k.max()), None) for k in kernels],
            [f"x={x:.0f}, y={y:.0f}" for x, y in pts], 3, *_KERNELS_AT)
    _text(canvas, "blur kernels at image positions", 1010, 22, 0.55, centre=True)
    _text(canvas, f"each panel: displacement -{r}..{r} px (x right, y down)", 1010, 42, 0.4,
          centre=True)
    return write_png(path, canvas)


def _colour_bar(canvas: np.ndarray, x: int, y: int, height: int, vmax: float, cmap: int,
                label: str) -> None:
    """A vertical colour bar of ``cmap`` from 0 (bottom) to ``vmax`` at ``(x, y)``."""
    import cv2

    ramp = np.linspace(255, 0, height).astype(np.uint8)[:, None].repeat(14, axis=1)
    canvas[y:y + height, x:x + 14] = cv2.applyColorMap(ramp, cmap)[:, :, ::-1]
    _text(canvas, f"{vmax:.3g}", x + 18, y + 10)
    _text(canvas, "0", x + 18, y + height)
    _text(canvas, label, x + 18, y + height // 2)


#: Long side (px) of the observation in ``field.png``, and its top left corner there.
_FIELD_SIDE = 560
_FIELD_AT = (50, 50)


def field_figure(fld: Any, shape: tuple[int, int], path: str | os.PathLike) -> Path:
    """Draw a displacement field's magnitude over the observation, with arrows, into a PNG
    (atomically).

    The magnitude is interpolated bilinearly between the field's nodes (constant beyond
    the outer ones, as the field itself); at most ~16 arrows a side show the displacement,
    the longest drawn over 90 % of the arrows' spacing.  Drawn with OpenCV.

    Parameters
    ----------
    fld : reblur.align.field.DisplacementField
    shape : (int, int)
        Observation size (the plot's extent).
    path : path-like
    """
    import cv2

    H, W = int(shape[0]), int(shape[1])
    scale = _FIELD_SIDE / max(H, W, 1)
    h, w = max(1, round(H * scale)), max(1, round(W * scale))
    mag = np.ascontiguousarray(fld.magnitude, np.float32)
    ny, nx = mag.shape
    # canvas pixel -> image position -> fractional node index
    u = ((np.arange(w) + 0.5) / scale - 0.5 - fld.x0) / fld.step
    v = ((np.arange(h) + 0.5) / scale - 0.5 - fld.y0) / fld.step
    mx, my = np.meshgrid(np.clip(u, 0, nx - 1).astype(np.float32),
                         np.clip(v, 0, ny - 1).astype(np.float32))
    vmax = float(mag.max()) if mag.size else 0.0
    img = cv2.remap(mag, mx, my, cv2.INTER_LINEAR) / (vmax if vmax > 0 else 1.0)
    x0, y0 = _FIELD_AT
    canvas = np.full((h + 100, w + 150, 3), 255, np.uint8)
    canvas[y0:y0 + h, x0:x0 + w] = cv2.applyColorMap(
        np.clip(img * 255, 0, 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[:, :, ::-1]
    k = max(1, int(np.ceil(max(ny, nx) / 16)))  # at most ~16 arrows per side
    d = fld.d[::k, ::k].reshape(-1, 2).astype(float)
    longest = float(np.hypot(d[:, 0], d[:, 1]).max()) if d.size else 0.0
    gain = 0.9 * k * fld.step * scale / longest if longest > 0 else 0.0
    gy, gx = np.meshgrid(fld.y0 + fld.step * np.arange(0, ny, k),
                         fld.x0 + fld.step * np.arange(0, nx, k), indexing="ij")
    for (px, py), (dx, dy) in zip(np.c_[gx.ravel(), gy.ravel()], d, strict=True):
        a = (x0 + (px + 0.5) * scale, y0 + (py + 0.5) * scale)
        b = (a[0] + gain * dx, a[1] + gain * dy)
        if np.hypot(b[0] - a[0], b[1] - a[1]) >= 2:
            cv2.arrowedLine(canvas, tuple(int(round(c)) for c in a),
                            tuple(int(round(c)) for c in b), (255, 255, 255), 2, cv2.LINE_AA,
                            tipLength=0.3)
    cv2.rectangle(canvas, (x0 - 1, y0 - 1), (x0 + w, y0 + h), (0, 0, 0), 1)
    _colour_bar(canvas, x0 + w + 20, y0, h, vmax, cv2.COLORMAP_VIRIDIS, "|d| (px)")
    _text(canvas, f"local displacement after the homography: max {vmax:.2f} px",
          x0 + w // 2, 22, 0.5, centre=True)
    _text(canvas, f"observation {W} x {H} px; arrows: the displacement, longest "
          f"{longest:.2f} px", x0 + w // 2, y0 + h + 30, 0.4, centre=True)
    return write_png(path, canvas)


def rolling_figure(shutter: dict[str, Any], path: str | os.PathLike) -> Path:
    """Plot the band model's motion (``result.decision["shutter"]`` when the rolling model
    was used) into a PNG (atomically): each band's mean pose against its centre row --
    the translations (px) and the roll (degrees) -- and the estimated readout fraction.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from .io import atomic_path

    bands = shutter["rolling"]["bands"]
    rows = [b["centre_row"] for b in bands]
    pose = {k: [b["mean_pose"][k] for b in bands] for k in ("tx", "ty", "rz")}
    fig = Figure(figsize=(9.0, 3.6), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    ax_t, ax_r = fig.subplots(1, 2)
    for k, mark in (("tx", "o-"), ("ty", "s-")):
        ax_t.plot(rows, pose[k], mark, label=k)
    ax_t.set_ylabel("mean translation (px)")
    ax_t.legend(fontsize=8)
    ax_r.plot(rows, pose["rz"], "d-", color="C2")
    ax_r.set_ylabel("mean roll rz (deg)")
    for ax in (ax_t, ax_r):
        ax.set_xlabel("band centre row")
        ax.grid(alpha=0.3)
    r = shutter.get("readout")
    q = shutter.get("readout_quartiles")
    crit = shutter.get("criterion", {})
    spread = "" if not q else f" (windows' quartiles {q[0]:.2f}-{q[1]:.2f})"
    fig.suptitle(f"rolling shutter, {len(bands)} bands: readout after the alignment "
                 f"{'-' if r is None else f'{r:.2f}'}{spread} of an exposure; inlier RSS "
                 f"{100 * crit.get('drop', float('nan')):.0f} % below the global model's",
                 fontsize=10)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", metadata={"Software": None})
    return path


# ---------------------------------------------------------------------------- regions
def _full_scale(observed: Image | None) -> float | None:
    """Full-scale value of the observation's own units (255 for uint8, 65535 for uint16,
    1 for floats), None without it."""
    if observed is None:
        return None
    dt = np.dtype(observed.dtype)
    return float(np.iinfo(dt).max) if dt.kind in "ui" else 1.0


def triage(regions: list[dict[str, Any]], observed: Image | None = None
           ) -> list[dict[str, Any]]:
    """The regions as an analyst triages them: most evidence first.

    Each record gains ``rank`` (1 = strongest), ``mean_contrast`` (the mean magnitude of
    the difference from the matched reblurred reference, in the observation's own units:
    DN for integer images) and, with a georeferenced observation, ``area_m2`` (in the
    units of its CRS, squared: m^2 for projected CRSs in metres).  Sorted by ``score`` (the
    region's mean statistic over the decision threshold), then by area; records without a
    score (regions found on a mask alone) by area.
    """
    scale = _full_scale(observed)
    geo = observed.geo if observed is not None else None
    px_area = None
    if geo and geo.get("transform") is not None:
        t = geo["transform"]
        px_area = abs(t.a * t.e - t.b * t.d)
    out = []
    for r in regions:
        r = dict(r)
        if "contrast" in r and scale is not None:
            r["mean_contrast"] = r["contrast"] * scale
        if px_area:
            r["area_m2"] = float(r.get("area", 0)) * px_area
        out.append(r)
    out.sort(key=lambda r: (-float(r.get("score", 0.0)), -int(r.get("area", 0)),
                            list(r.get("bbox", []))))
    for k, r in enumerate(out, 1):
        r["rank"] = k
    return out


def find_regions(change: np.ndarray) -> list[dict[str, Any]]:
    """Connected (8-neighbour) change regions: label, area, bbox (y0, x0, y1, x1), centroid."""
    import cv2

    n, _, stats, cent = cv2.connectedComponentsWithStats(
        np.asarray(change, dtype=np.uint8), connectivity=8
    )
    out = []
    for i in range(1, n):
        x, y, w, h, area = (int(v) for v in stats[i])
        out.append(dict(label=i, area=area, bbox=[y, x, y + h, x + w],
                        centroid=[float(cent[i][1]), float(cent[i][0])]))
    return out


#: Region properties copied into the GeoJSON features.
_FEATURE_KEYS = FEATURE_KEYS


def change_polygons(change, geo: dict[str, Any] | None = None,
                    regions: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """Change regions as a GeoJSON FeatureCollection (:func:`reblur.gis.change_features`).

    One feature per 8-connected region of ``change`` (numpy or lazy: traced tile by tile,
    merged across tile borders), simplified by at most half a pixel, in the observation's
    CRS when ``geo`` (``crs``, ``transform``) is given, else in pixel coordinates.  With
    ``regions`` (:func:`triage` records), each feature carries its region's triage
    properties (rank, score, polarity, mean contrast, area in m^2), matched by the region's
    bounding box and pixel count; features are listed by rank.
    """
    return change_features(change, geo, regions)


# ---------------------------------------------------------------------------- summary
def _version() -> str:
    try:
        return importlib.metadata.version("reblur")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - source checkout
        from . import __version__

        return __version__


def _memory() -> dict[str, float]:
    out = dict(peak_rss_mb=round(peak_rss_mb(), 1))
    try:
        import psutil

        out["rss_mb"] = round(psutil.Process().memory_info().rss / 2**20, 1)
    except Exception:  # noqa: BLE001 - optional
        pass
    return out


def _count(mask) -> int:
    """Non-zero pixels of a mask (numpy or lazy), counted window by window."""
    return sum(int(np.count_nonzero(np.asarray(mask[ys, xs])))
               for ys, xs in iter_windows(mask.shape, 4096))


#: Spread of the estimation windows' fits (dB) from which the report warns.
FIT_SPREAD_DB = 6.0


def model_notes(result) -> list[str]:
    """What an analyst should know about how well the model fits: estimation windows whose
    fits disagree, no window that fits (the estimate decided from the best one), a blur
    spread over more poses than a solve holds (and a shutter model left unfitted for it), a
    roll range narrowed to a thin strip, a blur beyond the pose grid's translations, and a
    model error the decision's tolerance could not absorb."""
    notes = []
    info = result.motion.info
    fits = [f for f in (info.get("psnr_inliers") or info.get("psnr") or [])
            if f is not None and np.isfinite(f)]
    if len(fits) > 1 and max(fits) - min(fits) > FIT_SPREAD_DB:
        notes.append(
            f"the estimation windows fit at {min(fits):.1f} to {max(fits):.1f} dB: the blur "
            "model fits some parts of the image worse than others; the decision's tolerance "
            "is calibrated on all of them, so the worst sets it")
    sel = info.get("selection") or {}
    if sel and not sel.get("fits", True):
        occ = [float(o) for o in sel.get("occluded") or []] or [float("nan")]
        notes.append(
            f"no estimation window fits the blur model: {min(occ):.0%} to {max(occ):.0%} of "
            f"the windows' pixels came out as change (a window above "
            f"{sel.get('max_occluded', 2 / 3):.0%} is rejected) in each of the "
            f"{sel.get('estimates', 1)} estimates tried; the motion comes from the best one, "
            "so the reblurred reference and the changes are less reliable than usual")
    if sel.get("strip_roll_deg"):
        r0, r1 = sel["strip_roll_deg"]
        notes.append(
            f"the observation is a thin strip: the pose grid's roll range was narrowed from "
            f"+-{r0:.2f} to +-{r1:.2f} degrees so that estimation windows far apart along it see "
            "data for every pose (a larger roll would move the strip's ends across it); a "
            "roll beyond that range is not modelled")
    if info.get("capped"):
        notes.append(
            f"the blur spreads over more camera poses than an estimate holds "
            f"({info.get('max_active')} per solve; {info['capped']} solve(s) reached it): "
            "a dense blur such as defocus rather than camera shake; the weights are the "
            "best over the poses held, so the reblurred reference may miss part of the "
            "blur ([select] max_active in a --config file raises the bound, at a cost "
            "growing as its cube)")
    skipped = (result.decision.get("shutter") or {}).get("skipped")
    if skipped:
        notes.append(f"--shutter {result.decision['shutter']['asked']} was not applied: "
                     f"{skipped}")
    tr = info.get("translations") or {}
    checks = tr.get("checks") or [{}]
    # on the edge with no wider grid tried (a grid given, a growth the start used up) or
    # allowed; a wider one that fitted no better says the poses on the edge belong there
    if tr.get("edge_share", 0.0) >= T_EDGE_SHARE and checks[-1].get("outcome") in (
            None, "limit", "reach"):
        grown = (f", widened from {tr['t_max_start']:g} px" if tr["t_max"] > tr["t_max_start"]
                 else "")
        notes.append(
            f"the blur reaches beyond the pose grid's translations (+-{tr['t_max']:g} px"
            f"{grown}): {tr['edge_share']:.0%} of the weight lies on their edge, so the "
            "reblurred reference misses part of the blur (--t-max sets the range the "
            "estimate starts from)")
    cal = result.decision.get("calibration", {})
    if cal.get("calibrated") and not cal.get("met", True):
        notes.append(
            f"the model's error exceeds the loosest tolerance (shift {cal['shift']:g} px, "
            f"contrast {cal['contrast']:g}) on the estimation windows: the threshold was "
            f"raised to {cal['floor']:.2f}, and faint changes on strong structure may be "
            "missed")
    return notes


def summarize(
    result: ChangeResult,
    *,
    reference: Image | None = None,
    observed: Image | None = None,
    truth: np.ndarray | None = None,
    options: dict[str, Any] | None = None,
    timings: dict[str, float] | None = None,
) -> dict[str, Any]:
    """The content of ``report.json`` (without the ``files`` and ``notes`` entries)."""
    H, W = result.change.shape[:2]
    n = H * W
    known_change = _MaskView(result.change, result.unknown)  # what changes.png shows
    changed = _count(known_change)
    unknown = _count(result.unknown)
    regions = list(result.regions) if result.regions else (
        find_regions(known_change[...]) if changed and n <= 2**26 else []
    )
    regions = triage(regions, observed)
    known = n - unknown
    d: dict[str, Any] = dict(
        reblur_version=_version(),
        inputs=dict(
            reference=reference.info() if reference is not None else None,
            observed=observed.info() if observed is not None else None,
        ),
        alignment=dict(H=np.asarray(result.alignment).tolist(),
                       details=result.decision.get("alignment")),
        crop=dict(
            boxes=[list(b) for b in result.crop.boxes], size=result.crop.size,
            m1=result.crop.m1, threshold=result.crop.threshold,
            space_invariant=result.crop.space_invariant, tried=result.crop.tried,
        ),
        motion=dict(
            grid=result.motion.grid.to_dict(), n_poses=result.motion.grid.size,
            nonzero_poses=result.motion.nonzero_poses(),
            boxes=[list(b) for b in result.motion.boxes], info=result.motion.info,
        ),
        threshold=result.threshold,
        decision={k: v for k, v in result.decision.items() if k != "alignment"},
        changes=dict(
            height=H, width=W, pixels=n, changed_px=changed,
            changed_fraction=changed / n if n else float("nan"),
            unknown_px=unknown, unknown_fraction=unknown / n if n else float("nan"),
            changed_fraction_of_known=changed / known if known else float("nan"),
            n_regions=len(regions),
            regions=regions[:MAX_LISTED_REGIONS],
        ),
        metrics=None,
        timings_s={**dict(result.timings), **dict(timings or {})},
        memory=_memory(),
        options=options or {},
    )
    if truth is not None:
        from .metrics import change_metrics

        pred = np.asarray(result.change, dtype=bool) & ~np.asarray(result.unknown, dtype=bool)
        d["metrics"] = change_metrics(truth, pred, ignore=result.unknown)
    return to_jsonable(d)


def summary_line(summary: dict[str, Any], out_dir: str | os.PathLike | None = None) -> str:
    """One line: ``changes: 1.23 % of 4.2 MP in 7 regions -> DIR/overlay.png``."""
    c = summary["changes"]
    frac = c["changed_fraction"] or 0.0
    line = (f"changes: {100 * frac:.2f} % of {c['pixels'] / 1e6:.1f} MP in {c['n_regions']} "
            f"region{'s' * (c['n_regions'] != 1)}")
    m = summary.get("metrics")
    if m:
        line += f" (JC {_fmt(m.get('jaccard'))}, YC {_fmt(m.get('yule'))})"
    if out_dir is not None:
        line += f" -> {Path(out_dir) / 'overlay.png'}"
    return line


def _fmt(v) -> str:
    return "n/a" if v is None else f"{v:.3f}"


# ---------------------------------------------------------------------------- html
def _data_uri(path: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode("ascii")


def _rows(pairs: Iterable[tuple[str, Any]]) -> str:
    return "\n".join(
        f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(str(v))}</td></tr>"
        for k, v in pairs
    )


#: Regions listed in the HTML report's table (the strongest; report.json lists more).
HTML_REGIONS = 100


def _region_table(regions: list[dict[str, Any]], n_regions: int) -> str:
    """The HTML table of the strongest regions, as :func:`triage` ranks them."""
    if not regions:
        return ""
    geo = any("area_m2" in r for r in regions)
    head = ["rank", "score", "polarity", "mean contrast", "area (px)"]
    head += ["area (m\u00b2)"] if geo else []
    head += ["centroid (row, col)", "bbox (y0, x0, y1, x1)"]
    rows = []
    for r in regions[:HTML_REGIONS]:
        cells = [r.get("rank"), _fmt(r.get("score")), r.get("polarity", "-"),
                 _fmt(r.get("mean_contrast")), r.get("area")]
        cells += [_fmt(r.get("area_m2"))] if geo else []
        cells += [", ".join(f"{v:.0f}" for v in r.get("centroid", [])),
                  ", ".join(str(v) for v in r.get("bbox", []))]
        rows.append("<tr>" + "".join(f"<td>{html.escape(str(v))}</td>" for v in cells)
                    + "</tr>")
    shown = min(len(regions), HTML_REGIONS)
    more = (f"<p>The {shown} strongest of {n_regions} regions; report.json lists up to "
            f"{MAX_LISTED_REGIONS}.</p>" if n_regions > shown else "")
    return ("<h2>Change regions</h2><p>Score: the region's mean change statistic over the "
            "decision threshold (1 = at the threshold). Mean contrast: observed minus "
            "the matched reblurred reference, in the observation's units.</p>"
            '<table class="regions"><tr>' + "".join(f"<th>{h}</th>" for h in head)
            + "</tr>\n" + "\n".join(rows) + "</table>" + more)


def write_html(path: str | os.PathLike, summary: dict[str, Any], files: dict[str, str]) -> Path:
    """A single self-contained HTML page: key numbers, embedded pictures, links to files.

    ``files`` maps output names to file names relative to the page's directory; only those
    are linked, and ``overlay.png``/``motion.png`` are embedded as data URIs.
    """
    from .io import atomic_path

    path = Path(path)
    out_dir = path.parent
    c = summary["changes"]
    inp = summary["inputs"]
    obs, ref = inp.get("observed") or {}, inp.get("reference") or {}
    rows = [
        ("reference", f"{ref.get('path')} ({_shape_str(ref)})"),
        ("observed", f"{obs.get('path')} ({_shape_str(obs)})"),
        ("changed area", f"{c['changed_px']:,} px ({100 * (c['changed_fraction'] or 0):.3f} %)"),
        ("change regions", c["n_regions"]),
        ("unknown area", f"{c['unknown_px']:,} px ({100 * (c['unknown_fraction'] or 0):.3f} %)"),
        ("threshold", summary.get("threshold")),
        ("poses with weight", f"{len(summary['motion']['nonzero_poses'])} of "
                              f"{summary['motion']['n_poses']}"),
        ("estimation windows", summary["crop"]["boxes"]),
        ("local displacement field", _field_text(
            ((summary.get("alignment") or {}).get("details") or {}).get("field"))),
        ("total time", f"{summary['timings_s'].get('total', float('nan')):.1f} s"
         if summary["timings_s"].get("total") is not None else "n/a"),
        ("peak memory", f"{summary['memory'].get('peak_rss_mb')} MB"),
        ("reblur version", summary.get("reblur_version")),
    ]
    m = summary.get("metrics")
    if m:
        rows += [(f"truth: {k}", _fmt(m.get(k))) for k in
                 ("pcc", "jaccard", "yule", "precision", "recall", "f1") if k in m]
    figs = []
    for name, caption in (("overlay.png", "Changes (red, outlined) and unknown (dark)"),
                          ("motion.png", "Estimated camera motion"),
                          ("field.png", "Local displacement after the homography "
                                        "(parallax, lens distortion)"),
                          ("rolling.png", "Rolling shutter: the motion of each row band")):
        if name in files and (out_dir / files[name]).exists():
            figs.append(
                f'<figure><img alt="{name}" src="{_data_uri(out_dir / files[name])}">'
                f"<figcaption>{html.escape(caption)}</figcaption></figure>"
            )
    links = "\n".join(
        f'<li><a href="{html.escape(rel)}">{html.escape(name)}</a></li>'
        for name, rel in files.items() if name != "report.html" and (out_dir / rel).exists()
    )
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in summary.get("notes", []))
    table = _region_table(c.get("regions") or [], c["n_regions"])
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<title>reblur change report</title>
<style>
body {{ font-family: sans-serif; margin: 2em; max-width: 1400px; }}
table {{ border-collapse: collapse; }} th, td {{ padding: 2px 10px; text-align: left;
 border-bottom: 1px solid #ddd; }} img {{ max-width: 100%; }}
</style></head><body>
<h1>reblur change report</h1>
<table>
{_rows(rows)}
</table>
{"<h2>Notes</h2><ul>" + notes + "</ul>" if notes else ""}
{"".join(figs)}
{table}
<h2>Files</h2><ul>
{links}
</ul>
</body></html>
"""
    with atomic_path(path) as tmp:
        tmp.write_text(printable(page), encoding="utf-8")
    return path


def _field_text(info: dict[str, Any] | None) -> str:
    """One line on the local displacement field for the HTML page."""
    if not info:
        return "n/a"
    if not info.get("applied"):
        return f"not applied: {info.get('reason') or 'off'}"
    f = info.get("field") or {}
    return (f"max {f.get('max_px')} px, RMS {f.get('rms_px')} px over the image; "
            f"{info.get('inliers')} tie points, residual {info.get('rms_before_px')} -> "
            f"{info.get('rms_after_px')} px RMS")


def _shape_str(info: dict) -> str:
    shp = info.get("shape") or []
    if len(shp) < 2:
        return "?"
    bands = shp[2] if len(shp) > 2 else 1
    return f"{shp[1]}x{shp[0]}, {bands} band{'s' * (bands != 1)}, {info.get('dtype')}"


# ---------------------------------------------------------------------------- main entry
def existing_outputs(out_dir: str | os.PathLike) -> list[Path]:
    """Result files of a previous run present in ``out_dir``."""
    d = Path(out_dir)
    return [d / n for n in OUTPUT_NAMES if (d / n).exists()]


def remove_outputs(out_dir: str | os.PathLike, keep: Iterable[str] = ()) -> list[Path]:
    """Delete result files in ``out_dir`` except ``keep`` (stale files of an older run)."""
    keep = set(keep)
    removed = []
    for p in existing_outputs(out_dir):
        if p.name not in keep:
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()
            removed.append(p)
    return removed


def _to_dtype(dtype: np.dtype):
    """Block converter: float reblurred in [0, 1] units -> the observation's dtype."""
    dtype = np.dtype(dtype)

    def conv(b: np.ndarray) -> np.ndarray:
        return quantize(b, dtype)
    return conv


def _write_viewer(result: ChangeResult, out: Path, observed: Image | None,
                  changes: dict[str, Any], options: ViewerOptions
                  ) -> tuple[dict[str, str], list[str], float]:
    """The zoomable viewer (:func:`reblur.viewer.write_viewer`), regions as in the report
    (``changes``: its ``changes`` entry); returns (files, notes, its time).  It reads the
    result's own reblurred image, not ``reblurred.tif``, so it runs beside the writing of
    the COGs."""
    from .viewer import VIEWER_DIR, write_viewer

    info = write_viewer(out / VIEWER_DIR, result, observed=observed,
                        regions=changes["regions"], n_regions=changes["n_regions"],
                        options=options)
    return ({"viewer": f"{VIEWER_DIR}/index.html"}, [f"viewer: {n}" for n in info.notes],
            info.time_s)


def _write_masks(result: ChangeResult, out: Path, observed: Image | None,
                 geo) -> tuple[dict[str, str], list[str]]:
    """``changes.png`` / ``unknown.png`` (up to the PNG limit), the masks' COGs (large or
    georeferenced images) and the polygons (georeferenced); returns (files, notes)."""
    change, unknown = result.change, result.unknown
    H, W = change.shape[:2]
    files: dict[str, str] = {}
    notes: list[str] = []
    if H * W <= PNG_MAX_PIXELS:
        write_png_bands(out / "changes.png", (H, W), _mask_bands(change, unknown))
        files["changes.png"] = "changes.png"
        write_png_bands(out / "unknown.png", (H, W), _mask_bands(unknown))
        files["unknown.png"] = "unknown.png"
    else:
        notes.append(f"image of {H * W:,} pixels: masks written as TIFF only (PNG limit)")
    if H * W > BIG_MASK_PIXELS or geo is not None or H * W > PNG_MAX_PIXELS:
        for name, view in (("changes.tif", _MaskView(change, unknown)),
                           ("unknown.tif", _MaskView(unknown))):
            write_cog(out / name, view, geo, block=COG_BLOCK, overviews="max")
            files[name] = name
    if geo is not None:
        feats = region_features(_MaskView(change, unknown), geo,
                                triage(list(result.regions), observed))
        write_geojson(out / "changes.geojson", feats, geo)
        files["changes.geojson"] = "changes.geojson"
        if geopackage_available():
            write_geopackage(out / "changes.gpkg", feats, geo)
            files["changes.gpkg"] = "changes.gpkg"
        else:
            notes.append("changes.gpkg not written: GeoPackage output needs the geo extra "
                         "(pip install 'reblur[geo]'); changes.geojson holds the same polygons")
    return files, notes


def _cog_source(reblurred, dtype: np.dtype) -> tuple[Any, Callable | None]:
    """What ``reblurred.tif`` is written from, and the converter of its windows: a
    :class:`~reblur.gis.ReblurredStore` that holds ``dtype`` pixels (the observation's) is
    written as it is stored, anything else quantised from float intensities (the same file;
    ``python -m benchmarks.gis_outputs`` times both)."""
    if isinstance(reblurred, ReblurredStore) and reblurred.stored_dtype == dtype:
        return reblurred.stored, None
    return reblurred, _to_dtype(dtype)


def _write_reblurred(result: ChangeResult, out: Path, observed: Image | None,
                     geo) -> tuple[dict[str, str], list[str]]:
    """``reblurred.tif`` (a COG in the observation's dtype); returns (files, notes)."""
    if result.reblurred is None:
        return {}, ["reblurred.tif not written: the result holds no reblurred image "
                    "(detect_changes keeps it in memory up to 64 MP, and writes it to "
                    "reblurred_out at any size)"]
    dtype = np.dtype(observed.dtype if observed is not None else np.float32)
    data, convert = _cog_source(result.reblurred, dtype)
    # the pixels the reference does not cover hold no data (a mask, or NaN)
    write_cog(out / "reblurred.tif", data, geo, block=COG_BLOCK, overviews="average",
              convert=convert, nodata_mask=result.unknown)
    return {"reblurred.tif": "reblurred.tif"}, []


def _draws_rolling(result: ChangeResult) -> bool:
    """Whether the result has the rolling-shutter model's bands (``rolling.png``)."""
    shutter = result.decision.get("shutter", {})
    return shutter.get("model") == "rolling" and "rolling" in shutter


def _write_pictures(result: ChangeResult, out: Path, observed: Image | None,
                    geo) -> tuple[dict[str, str], list[str]]:
    """``overlay.png``, ``motion.png`` and, where the result has them, ``field.png`` and
    ``rolling.png``; returns (files, notes)."""
    change, unknown = result.change, result.unknown
    obs_arr = observed.array if observed is not None else None
    if obs_arr is None:
        obs_arr = result.reblurred if result.reblurred is not None else _MaskView(change)
    # level 3: a photograph compresses 1 % less than at the default 6, in a third of the time
    write_png(out / "overlay.png", overlay_image(obs_arr, change, unknown), compression=3)
    files = {"overlay.png": "overlay.png"}
    motion_figure(result.motion, out / "motion.png")
    files["motion.png"] = "motion.png"
    if getattr(result, "field", None) is not None:
        field_figure(result.field, result.change.shape[:2], out / "field.png")
        files["field.png"] = "field.png"
    if _draws_rolling(result):
        rolling_figure(result.decision["shutter"], out / "rolling.png")
        files["rolling.png"] = "rolling.png"
    return files, []


#: Modules the writers import on first use.  :func:`write_report` imports them before its
#: threads start: two threads importing one package at once can meet it half initialised
#: (a clean-clone CI run: "cannot import name 'BaseGeometry' from partially initialized
#: module 'shapely.geometry.base'", the viewer's outlines and the GeoJSON polygons both
#: importing shapely).
_WRITER_MODULES = (
    "affine", "shapely", "shapely.affinity", "shapely.geometry", "rasterio",
    "rasterio.enums", "rasterio.errors", "rasterio.features", "rasterio.shutil",
    "rasterio.windows", "reblur.viewer.outlines", "reblur.viewer.layers",
    "reblur.viewer.pyramid",
)
#: Those of :func:`rolling_figure`, imported only for a run that draws it: matplotlib takes
#: 0.3 s to import, a tenth of a 1 MP run.
_ROLLING_MODULES = ("matplotlib.figure", "matplotlib.backends.backend_agg")


def _import_writers(rolling: bool) -> None:
    """Import :data:`_WRITER_MODULES`, and :data:`_ROLLING_MODULES` if ``rolling``, on the
    calling thread (a missing optional one is left to raise where it is used)."""
    for name in _WRITER_MODULES + (_ROLLING_MODULES if rolling else ()):
        try:
            importlib.import_module(name)
        except ImportError:
            pass


def write_report(
    result: ChangeResult,
    out_dir: str | os.PathLike,
    *,
    reference: Image | None = None,
    observed: Image | None = None,
    truth: np.ndarray | None = None,
    options: dict[str, Any] | None = None,
    timings: dict[str, float] | None = None,
    notes: Iterable[str] = (),
    viewer: ViewerOptions | None = ViewerOptions(),  # noqa: B008 - frozen
    progress: Callable[[str, float], None] | None = None,
) -> tuple[dict[str, str], dict[str, Any]]:
    """Write every result file of one detection into ``out_dir`` (created if missing).

    Parameters
    ----------
    result : ChangeResult
        What :func:`reblur.detect_changes` returned.
    out_dir : path
        Output directory.  Existing result files are replaced (atomically); refusing to
        overwrite is the caller's decision (the CLI's ``--overwrite``).
    reference, observed : Image, optional
        The inputs (paths, sizes, dtypes for the report; the observation is drawn in
        ``overlay.png``, its dtype and georeferencing are used for ``reblurred.tif``,
        ``changes.tif`` and ``changes.geojson``).
    truth : (H, W) bool ndarray, optional
        True change mask: scores go into ``report.json`` (unknown pixels ignored).
    options : dict, optional
        Options of the run, recorded verbatim.
    timings : dict, optional
        Extra stage timings (seconds), merged with ``result.timings``.
    notes : iterable of str
        Extra remarks recorded in the report.
    viewer : reblur.viewer.ViewerOptions or None
        How to write the zoomable viewer ``viewer/``; None: no viewer.
    progress : callable, optional
        ``progress("report", fraction)`` as the files are written.

    Returns
    -------
    files : dict
        Output name -> file name (relative to ``out_dir``) of every file written.
    summary : dict
        The content of ``report.json``.
    """
    t0 = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    notes = list(notes) + model_notes(result)
    H, W = result.change.shape[:2]
    if observed is not None and tuple(observed.shape[:2]) != (H, W):
        raise ValueError(
            f"result is {W}x{H} but the observation is {observed.width}x{observed.height}"
        )
    if truth is not None and tuple(np.shape(truth)[:2]) != (H, W):
        raise ValueError(f"truth mask is {np.shape(truth)[1]}x{np.shape(truth)[0]}, the "
                         f"observation {W}x{H}")
    geo = observed.geo if observed is not None else None
    files: dict[str, str] = {}

    def done(fraction: float) -> None:
        if progress is not None:
            progress("report", fraction)

    done(0.0)

    # the regions, as report.json lists them, first: the viewer draws them
    summary = summarize(result, reference=reference, observed=observed, truth=truth,
                        options=options, timings=timings)
    # the pictures (PNGs drawn from the arrays) and the viewer are written on two threads
    # beside the masks and the reblurred image; those two stay on the calling thread, one
    # after the other: GDAL writes one COG at a time in a process anyway
    # (``gis._COG_LOCK``).  Files and notes are merged in this order (the first error
    # raised is the one reported).  On the 100 MP unchanged cost pair the writing took
    # 11.5 s with the viewer after the rest, 9.3 s beside it, 15-16 s of CPU either way
    # (``python -m benchmarks.stage_cpu``).
    _import_writers(_draws_rolling(result))
    with ThreadPoolExecutor(2) as ex:
        pictures = ex.submit(_write_pictures, result, out, observed, geo)
        viewing = (None if viewer is None else
                   ex.submit(_write_viewer, result, out, observed, summary["changes"], viewer))
        for job, fraction in ((_write_masks, 0.3), (_write_reblurred, 0.6)):
            got_files, got_notes = job(result, out, observed, geo)
            files.update(got_files)
            notes.extend(got_notes)
            done(fraction)
        got_files, got_notes = pictures.result()
        files.update(got_files)
        notes.extend(got_notes)
        done(0.8)
        if viewing is not None:
            got_files, got_notes, seconds = viewing.result()
            files.update(got_files)
            notes.extend(got_notes)
            summary["timings_s"]["viewer"] = seconds
        done(0.9)
    # the writing's time and the peak memory include the files
    summary["timings_s"]["report"] = time.perf_counter() - t0
    summary["memory"] = to_jsonable(_memory())
    files["report.json"] = "report.json"
    files["report.html"] = "report.html"
    summary["notes"] = notes
    summary["files"] = dict(files)
    write_json(out / "report.json", summary)
    write_html(out / "report.html", summary, files)
    done(1.0)
    return files, summary
