"""Window-local homography warps of (possibly huge, on-disk) images.

Every warp in reblur goes through :func:`warp_window`: it maps the corners of the output
window back through the homography, reads only the reference window they cover (plus a
small interpolation margin), and warps it with OpenCV in window-local coordinates.  Output
pixels whose source lies outside the reference are *unknown*: ``valid`` is False there and
the value is 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .grid import local_homography, map_points

__all__ = ["Box", "as_channels", "read_window", "source_box", "warp_source", "warp_window"]

#: Extra source pixels read around the mapped window (bilinear needs 1, keep 2).
_PAD = 2


@dataclass(frozen=True)
class Box:
    """A window ``rows y0:y0+h, cols x0:x0+w`` (may extend outside an image)."""

    y0: int
    x0: int
    h: int
    w: int

    @property
    def y1(self) -> int:
        return self.y0 + self.h

    @property
    def x1(self) -> int:
        return self.x0 + self.w

    @property
    def slices(self) -> tuple[slice, slice]:
        return slice(self.y0, self.y1), slice(self.x0, self.x1)

    def grow(self, top: int, bottom: int, left: int, right: int) -> Box:
        return Box(self.y0 - top, self.x0 - left, self.h + top + bottom, self.w + left + right)

    def corners(self) -> np.ndarray:
        """Pixel-centre corners ``(x, y)`` of the window."""
        x0, y0, x1, y1 = self.x0, self.y0, self.x1 - 1, self.y1 - 1
        return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)

    def as_tuple(self) -> tuple[int, int, int, int]:
        return (self.y0, self.x0, self.h, self.w)


def as_box(box) -> Box:
    """Accept a :class:`Box` or a ``(y0, x0, h, w)`` tuple."""
    if isinstance(box, Box):
        return box
    y0, x0, h, w = (int(v) for v in box)
    if h < 1 or w < 1:
        raise ValueError(f"window must have positive size, got {box}")
    return Box(y0, x0, h, w)


def as_channels(a: np.ndarray) -> np.ndarray:
    """View a 2-D image as ``(h, w, 1)``; 3-D images are returned unchanged."""
    a = np.asarray(a)
    return a[:, :, None] if a.ndim == 2 else a


def read_window(image, box: Box, dtype=np.float32) -> np.ndarray:
    """Read ``box`` from an array-like image (numpy, zarr, ...), zero outside the image.

    Returns an ``(h, w, C)`` array of ``dtype``.  Only the part inside the image is read.
    """
    H, W = image.shape[:2]
    C = image.shape[2] if len(image.shape) == 3 else 1
    out = np.zeros((box.h, box.w, C), dtype=dtype)
    ya, yb = max(box.y0, 0), min(box.y1, H)
    xa, xb = max(box.x0, 0), min(box.x1, W)
    if ya < yb and xa < xb:
        out[ya - box.y0 : yb - box.y0, xa - box.x0 : xb - box.x0] = as_channels(
            np.asarray(image[ya:yb, xa:xb])
        )
    return out


def source_box(H: np.ndarray, dst: Box, pad: int = _PAD) -> Box:
    """Bounding box, in reference pixels, of what the output window ``dst`` reads.

    A homography maps a rectangle to a quadrilateral (when the horizon is far outside),
    so the box of the four back-mapped corners bounds every source pixel.
    """
    Hi = np.linalg.inv(H)
    c = np.asarray(dst.corners(), dtype=float)
    w = c @ Hi[2, :2] + Hi[2, 2]
    # the window is convex: it stays on one side of the horizon line iff its corners do
    if not (np.all(np.isfinite(w)) and (np.all(w > 0) or np.all(w < 0))):
        raise ValueError(
            "degenerate homography: part of the window maps beyond the horizon of the "
            "reference (the alignment or the pose grid is far off)"
        )
    src = map_points(Hi, c)
    if not np.all(np.isfinite(src)):
        raise ValueError("degenerate homography: the window maps to non-finite positions")
    x0, y0 = np.floor(src.min(axis=0)).astype(int) - pad
    x1, y1 = np.ceil(src.max(axis=0)).astype(int) + pad
    return Box(int(y0), int(x0), int(y1 - y0 + 1), int(x1 - x0 + 1))


def _warp(src: np.ndarray, M: np.ndarray, dst: Box, interpolation: int,
          out: np.ndarray | None = None) -> np.ndarray:
    C = src.shape[2]
    if out is None:
        out = np.empty((dst.h, dst.w, C), dtype=src.dtype)
    elif out.shape != (dst.h, dst.w, C) or out.dtype != src.dtype:
        raise ValueError(f"out must be {(dst.h, dst.w, C)} {src.dtype}, got {out.shape} "
                         f"{out.dtype}")
    for c0 in range(0, C, 4):  # OpenCV warps at most 4 channels at once
        c1 = min(c0 + 4, C)
        if c1 - c0 == 1:
            part_src, part_dst = src[:, :, c0], out[:, :, c0]
        else:
            part_src, part_dst = src[:, :, c0:c1], out[:, :, c0:c1]
        part_src = np.ascontiguousarray(part_src)
        into = part_dst if C <= 4 else None  # a channel range of more is not contiguous
        got = cv2.warpPerspective(
            part_src, M, (dst.w, dst.h), dst=into, flags=interpolation,
            borderMode=cv2.BORDER_CONSTANT, borderValue=0,
        )
        if into is None or not np.shares_memory(got, out):
            out[:, :, c0:c1] = got.reshape(dst.h, dst.w, c1 - c0)
    return out


def warp_source(
    source: tuple[np.ndarray, Box], H: np.ndarray, dst: Box, need: Box,
    ref_shape: tuple[int, int], interpolation: int = cv2.INTER_LINEAR,
    out: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`warp_window` from a read source window, with its :func:`source_box` known.

    Returns the warped window and its validity mask, or None for the mask when every
    pixel's footprint lies inside the reference (the usual case, which costs nothing).
    ``out``: an ``(h, w, C)`` array of the source's dtype to warp into.
    """
    src, sbox = source
    Href, Wref = ref_shape
    M = local_homography(H, (sbox.x0, sbox.y0), (dst.x0, dst.y0))
    out = _warp(src, M, dst, interpolation, out)
    if need.y0 >= 0 and need.x0 >= 0 and need.y1 <= Href and need.x1 <= Wref:
        return out, None
    # validity: the reference extent expressed in the source window, warped like the data
    inside = np.zeros(src.shape[:2], np.float32)
    ya, yb = max(-sbox.y0, 0), min(Href - sbox.y0, sbox.h)
    xa, xb = max(-sbox.x0, 0), min(Wref - sbox.x0, sbox.w)
    if ya < yb and xa < xb:
        inside[ya:yb, xa:xb] = 1.0
    cover = cv2.warpPerspective(
        inside, M, (dst.w, dst.h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    return out, cover >= 1.0 - 1e-3


def warp_window(
    reference,
    H: np.ndarray,
    dst,
    *,
    dtype=np.float32,
    interpolation: int = cv2.INTER_LINEAR,
    source: tuple[np.ndarray, Box] | None = None,
    out: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Warp the reference by ``H`` into the output window ``dst``.

    Parameters
    ----------
    reference : array-like, (H, W) or (H, W, C)
        The full reference image (numpy, zarr, or anything sliceable).  Only the window
        that ``dst`` maps to is read.
    H : (3, 3) ndarray
        Reference -> observation homography in full-image coordinates.
    dst : Box or (y0, x0, h, w)
        Output window in observation coordinates.
    dtype : numpy dtype
        Working precision (float32 or float64).
    interpolation : int
        OpenCV interpolation flag (bilinear by default).
    source : (array, Box), optional
        An already-read reference window (``(h, w, C)``) and its box, to avoid re-reading
        when several warps share a source.  It must cover :func:`source_box`.
    out : (h, w, C) ndarray, optional
        Array of ``dtype`` to warp into (and return); OpenCV's threads write it, so its
        fresh pages are faulted in in parallel.

    Returns
    -------
    out : (h, w, C) ndarray
        Warped window (0 where unknown).
    valid : (h, w) bool ndarray
        True where the whole bilinear footprint lies inside the reference.
    """
    dst = as_box(dst)
    Href, Wref = reference.shape[:2]
    need = source_box(H, dst)
    if source is None:
        # clip to the image: outside pixels are unknown anyway
        y0, x0 = max(need.y0, 0), max(need.x0, 0)
        y1, x1 = min(need.y1, Href), min(need.x1, Wref)
        if y0 >= y1 or x0 >= x1:
            C = reference.shape[2] if len(reference.shape) == 3 else 1
            if out is None:
                out = np.zeros((dst.h, dst.w, C), dtype)
            else:
                out[...] = 0
            return out, np.zeros((dst.h, dst.w), bool)
        sbox = Box(y0, x0, y1 - y0, x1 - x0)
        src = read_window(reference, sbox, dtype)
    else:
        src, sbox = source
        src = as_channels(src).astype(dtype, copy=False)
    out, valid = warp_source((src, sbox), H, dst, need, (Href, Wref), interpolation, out)
    return out, np.ones((dst.h, dst.w), bool) if valid is None else valid
