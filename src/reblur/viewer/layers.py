"""The viewer's raster layers: the observation, the reblurred reference and the masks, as
:class:`~reblur.viewer.pyramid.Layer` objects that read their sources window by window.

Images are shown with one display stretch, taken from the observation: uint8 as it is,
other types from the 1st to the 99th percentile of a sample of windows spread over the
image (never the whole image), so the reblurred reference and the observation compare
pixel for pixel.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .pyramid import Layer

__all__ = ["Stretch", "sample_stretch", "image_layer", "mask_layer", "reblurred_source",
           "CHANGE_RGB", "UNKNOWN_RGB"]

#: Colour of the change fill (translucent, drawn over the observation).
CHANGE_RGB = (255, 40, 40)
#: Colour of unknown pixels (the reference does not cover them).
UNKNOWN_RGB = (30, 30, 70)


@dataclass(frozen=True)
class Stretch:
    """Linear display stretch: ``lo`` maps to 0, ``hi`` to 255 (clipped); NaN (no data) to
    0."""

    lo: float
    hi: float

    def apply(self, a: np.ndarray) -> np.ndarray:
        """``a`` stretched, float32 in [0, 255]: NaN becomes 0, infinities 0 or 255."""
        a = np.asarray(a, dtype=np.float32)
        if self.hi <= self.lo:
            return np.zeros_like(a)
        out = np.subtract(a, np.float32(self.lo))
        out *= np.float32(255.0 / (self.hi - self.lo))
        # fmax takes the number where the other operand is NaN: the clip and the NaN
        # replacement in two passes in place, not a clip and np.nan_to_num's four
        np.fmax(out, np.float32(0.0), out=out)
        return np.fmin(out, np.float32(255.0), out=out)


def _display_bands(a: np.ndarray) -> np.ndarray:
    """``(h, w, 1)`` gray or ``(h, w, 3)`` RGB: a second band alone is dropped (gray +
    alpha), more than three keep the first three."""
    if a.ndim == 2:
        return a[:, :, None]
    if a.shape[2] == 2:
        return a[:, :, :1]
    if a.shape[2] > 3:
        return a[:, :, :3]
    return a


def sample_stretch(array: Any, dtype: np.dtype, *, n: int = 8, side: int = 128) -> Stretch:
    """The display stretch of an image (numpy or lazy), from at most ``n x n`` windows of
    ``side`` pixels spread evenly over it: ``[0, 255]`` for uint8, else its 1st and 99th
    percentiles.

    Integer samples stay in their type (``np.percentile`` interpolates them in float64,
    the same values as a float64 copy): a 16-bit RGB sample is a quarter of the bytes, and
    its float64 copy's first-touch page faults were most of the stretch's time (1 MP
    ``5% rgb16``, ``benchmarks.cost``: the viewer 0.32-0.45 -> 0.26-0.34 s).
    """
    if np.dtype(dtype) == np.uint8:
        return Stretch(0.0, 255.0)
    H, W = (int(v) for v in array.shape[:2])
    parts = []
    for y in np.unique(np.linspace(0, max(0, H - side), n).astype(int)):
        for x in np.unique(np.linspace(0, max(0, W - side), n).astype(int)):
            win = _display_bands(np.asarray(array[y:y + side, x:x + side]))
            exact = win.dtype.kind in "iu" and win.dtype.itemsize <= 4  # exact in float64
            parts.append(win.ravel() if exact else win.astype(np.float64).ravel())
    v = np.concatenate(parts)
    if v.dtype.kind == "f":
        v = v[np.isfinite(v)]
    if v.size == 0:
        return Stretch(0.0, 1.0)
    lo, hi = np.percentile(v, [1.0, 99.0])
    if hi <= lo:
        lo, hi = float(v.min()), float(v.max())
    return Stretch(float(lo), float(hi) if hi > lo else float(lo) + 1.0)


def _encode_image(tile: np.ndarray) -> np.ndarray:
    u8 = tile if tile.dtype == np.uint8 else np.rint(tile).astype(np.uint8)
    return u8[:, :, 0] if u8.shape[2] == 1 else u8


def image_layer(name: str, array: Any, stretch: Stretch, *, scale: float = 1.0,
                fmt: str = "jpg", quality: int = 90) -> Layer:
    """A layer showing an image (numpy or lazy ``(H, W)`` / ``(H, W, C)``), read by windows.

    ``scale`` multiplies the values before ``stretch`` (the reblurred reference is in
    fractions of full scale: ``scale`` = the observation's full-scale value).
    """
    as_is = scale == 1.0 and stretch == Stretch(0.0, 255.0) and np.dtype(array.dtype) == np.uint8

    def read(ys: slice, xs: slice) -> np.ndarray:
        a = _display_bands(np.asarray(array[ys, xs]))
        if as_is:  # display values already: uint8, encoded as they are
            return a
        a = a.astype(np.float32) * np.float32(scale) if scale != 1.0 else a
        return stretch.apply(a)  # no data (NaN): black

    return Layer(name, read, _encode_image, fmt=fmt, reduce="mean", quality=quality)


def mask_layer(name: str, mask: Any, rgb: tuple[int, int, int], *, alpha: float,
               reduce: str, exclude: Any = None) -> Layer:
    """A layer drawing a bool mask (numpy or lazy ``(H, W)``) as colour ``rgb`` with opacity
    ``alpha`` (RGBA PNG tiles, transparent elsewhere); ``exclude`` masks pixels out.

    With ``reduce="mean"`` a coarse pixel's opacity is the share of masked pixels under it;
    with ``"max"`` any masked pixel makes it fully drawn.
    """
    colour = np.asarray(rgb, np.uint8)

    full = np.uint8(np.rint(np.float32(255.0) * np.float32(alpha)))  # a masked pixel's

    def read(ys: slice, xs: slice) -> np.ndarray:
        m = np.asarray(mask[ys, xs], dtype=bool)
        if exclude is not None:
            m = m & ~np.asarray(exclude[ys, xs], dtype=bool)
        return m[:, :, None].view(np.uint8) * np.uint8(255)  # 0 or 255, uint8

    def encode(tile: np.ndarray) -> np.ndarray:
        out = np.empty(tile.shape[:2] + (4,), np.uint8)
        out[:, :, :3] = colour
        if tile.dtype == np.uint8:  # full size: 0 or 255
            np.multiply(tile[:, :, 0] != 0, full, out=out[:, :, 3])
        else:
            out[:, :, 3] = np.rint(tile[:, :, 0] * np.float32(alpha)).astype(np.uint8)
        return out

    return Layer(name, read, encode, fmt="png", reduce=reduce, flat=True)


def reblurred_source(result: Any, observed: Any, reblurred_path: Path | None
                     ) -> tuple[Any, float, str | None]:
    """Where the reblurred reference's pixels come from.

    Returns ``(image, scale, note)``: the result's own reblurred image (fractions of full
    scale: ``scale`` = the observation's full-scale value; a
    :class:`~reblur.gis.ReblurredStore` of the observation's dtype: its stored pixels, in
    the observation's units, ``scale`` 1), else ``reblurred.tif`` opened
    lazily (an :class:`reblur.io.Image` read window by window, in the observation's units:
    ``scale`` 1; the caller closes it), else ``None`` with a note saying why the layer is
    missing.
    """
    if result.reblurred is not None:
        dt = np.dtype(observed.dtype) if observed is not None else np.dtype(np.float32)
        if getattr(result.reblurred, "stored_dtype", None) == dt:
            # a reblur.gis.ReblurredStore holding the observation's dtype: its pixels as
            # stored (those of reblurred.tif), no float copy of each window
            return result.reblurred.stored, 1.0, None
        return result.reblurred, float(np.iinfo(dt).max) if dt.kind in "ui" else 1.0, None
    if reblurred_path is not None and Path(reblurred_path).exists():
        from ..io import open_image

        img = open_image(reblurred_path, max_pixels=None, lazy=True, check_values=False,
                         rescale=False)
        return img, 1.0, None
    return None, 1.0, ("the reblurred reference is not shown: the result holds no reblurred "
                       "image and no reblurred.tif was written")
