"""Window-by-window rendering of a blurred observation as a time average of bicubic warps.

The observation is ``obs(x) = mean_k ref(H_k^{-1} x)`` over the sub-pose homographies of a
continuous camera path (reference -> observation, see :mod:`reblur.testbed.camera`).  Each
term is a BICUBIC perspective warp (OpenCV's cubic convolution kernel, a = -0.75, through
``cv2.remap`` on sample positions computed here in float64; reblur's own model uses bilinear
warps on a pose grid), accumulated in float64.  Note that the a = -0.75 kernel reproduces
constants exactly but linear ramps only up to a sub-pixel phase error (at most ~0.04 px,
odd about half-pixel positions); it is part of this generator's "optics", not of the scene.
Any window of the observation is rendered from only the reference region it needs (the
window corners mapped through every inverse homography, plus a margin for the cubic's
support), so observations of any size are made a tile at a time; a pixel of a tile equals
the same pixel of a whole-image render, bit for bit.

Windows are ``box = (y0, y1, x0, x1)``, half-open, in observation pixels.  A ``source`` is
anything with ``.shape`` and 2-D slicing (a numpy array, a memory map, a zarr array or a
reader from :mod:`reblur.testbed.scenes`).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import cv2
import numpy as np

__all__ = [
    "Box",
    "as_mapping",
    "iter_tiles",
    "render_tiled",
    "render_window",
    "source_box",
    "true_centroid",
    "valid_window",
]

Box = tuple[int, int, int, int]
CUBIC_MARGIN = 3
COORD_STEPS = 256  # sample positions are rounded to 1/256 px (exact in float32 below 32768 px)
MAX_WINDOW = 32767  # OpenCV's remap limit on a source window's side


def _check_homographies(homographies: np.ndarray) -> np.ndarray:
    hs = np.asarray(homographies, dtype=np.float64)
    if hs.ndim == 2:
        hs = hs[None]
    if hs.ndim != 3 or hs.shape[1:] != (3, 3) or len(hs) == 0:
        raise ValueError(f"homographies must be (n, 3, 3) with n >= 1, got {hs.shape}")
    if not np.all(np.isfinite(hs)):
        raise ValueError("homographies must be finite")
    return hs


def _check_box(box: Box, shape: tuple[int, ...] | None = None) -> Box:
    y0, y1, x0, x1 = (int(v) for v in box)
    if y1 <= y0 or x1 <= x0:
        raise ValueError(f"box must be (y0, y1, x0, x1) with y1 > y0 and x1 > x0, got {box!r}")
    if shape is not None and (y0 < 0 or x0 < 0 or y1 > shape[0] or x1 > shape[1]):
        raise ValueError(f"box {box!r} must lie inside the image of shape {tuple(shape[:2])}")
    return y0, y1, x0, x1


def _apply(h: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map pixel coordinates through a homography (float64)."""
    den = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    return (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / den, (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / den


def _inverses(hs: np.ndarray) -> np.ndarray:
    inv = np.linalg.inv(hs)
    return inv / inv[:, 2:3, 2:3]


def iter_tiles(shape: tuple[int, ...], tile: int = 512) -> Iterator[Box]:
    """Row-major tile boxes covering an image (edge tiles are smaller).

    Parameters
    ----------
    shape : tuple of int
        Image shape ``(H, W[, C])``.
    tile : int
        Tile side in pixels.

    Yields
    ------
    Box
        ``(y0, y1, x0, x1)``.
    """
    if int(tile) < 1:
        raise ValueError(f"tile must be a positive number of pixels, got {tile}")
    h, w = int(shape[0]), int(shape[1])
    for y0 in range(0, h, tile):
        for x0 in range(0, w, tile):
            yield y0, min(y0 + tile, h), x0, min(x0 + tile, w)


def source_box(
    homographies: np.ndarray, box: Box, ref_shape: tuple[int, ...], margin: int = CUBIC_MARGIN
) -> Box | None:
    """Reference region a window of the observation samples, clipped to the reference.

    The window's four corner pixel centres are mapped through every inverse homography;
    a homography maps the window (a convex quadrilateral) onto a convex quadrilateral, so
    the bounding box of the mapped corners, grown by ``margin`` pixels for the cubic's
    4 x 4 support, holds every sample.

    Parameters
    ----------
    homographies : numpy.ndarray
        ``(n, 3, 3)`` reference -> observation homographies.
    box : Box
        Observation window ``(y0, y1, x0, x1)``.
    ref_shape : tuple of int
        Reference shape.
    margin : int
        Extra pixels on every side.

    Returns
    -------
    Box or None
        Reference box, or None when the window samples nothing inside the reference.
    """
    hs = _check_homographies(homographies)
    y0, y1, x0, x1 = _check_box(box)
    cx = np.array([x0, x1 - 1, x0, x1 - 1], dtype=np.float64)
    cy = np.array([y0, y0, y1 - 1, y1 - 1], dtype=np.float64)
    xs, ys = zip(*(_apply(h, cx, cy) for h in _inverses(hs)), strict=True)
    return source_extent(np.concatenate(xs), np.concatenate(ys), margin, ref_shape)


def source_extent(xs: np.ndarray, ys: np.ndarray, margin: int,
                  ref_shape: tuple[int, ...]) -> Box | None:
    """The reference window ``(y0, y1, x0, x1)`` holding the points ``(xs, ys)`` grown by
    ``margin`` pixels, clipped to the reference; None when it is empty."""
    sx0 = max(int(np.floor(xs.min())) - margin, 0)
    sx1 = min(int(np.ceil(xs.max())) + margin + 1, int(ref_shape[1]))
    sy0 = max(int(np.floor(ys.min())) - margin, 0)
    sy1 = min(int(np.ceil(ys.max())) + margin + 1, int(ref_shape[0]))
    if sx1 <= sx0 or sy1 <= sy0:
        return None
    return sy0, sy1, sx0, sx1


def _pixel_valid(
    inv: np.ndarray, box: Box, ref_shape: tuple[int, ...], shrink: float
) -> np.ndarray:
    y0, y1, x0, x1 = box
    ys, xs = np.mgrid[y0:y1, x0:x1].astype(np.float64)
    ok = np.ones(ys.shape, dtype=bool)
    hi_x, hi_y = ref_shape[1] - 1 - shrink, ref_shape[0] - 1 - shrink
    for h in inv:
        u, v = _apply(h, xs, ys)
        ok &= (u >= shrink) & (u <= hi_x) & (v >= shrink) & (v <= hi_y)
    return ok


def valid_window(
    homographies: np.ndarray, box: Box, ref_shape: tuple[int, ...], shrink: float = 2.0
) -> np.ndarray:
    """Pixels of a window whose every sub-pose samples inside the reference.

    A pixel is valid when, for every ``k``, ``H_k^{-1} x`` lies in the reference shrunk by
    ``shrink`` pixels (2 covers the bicubic's support).  The valid set of one homography is
    convex, so a window whose four corners are valid is valid throughout (fast path).

    Parameters
    ----------
    homographies : numpy.ndarray
        ``(n, 3, 3)`` reference -> observation homographies.
    box : Box
        Observation window ``(y0, y1, x0, x1)``.
    ref_shape : tuple of int
        Reference shape.
    shrink : float
        Border of the reference, in pixels, treated as outside.

    Returns
    -------
    numpy.ndarray
        Boolean ``(y1 - y0, x1 - x0)`` mask.
    """
    inv = _inverses(_check_homographies(homographies))
    y0, y1, x0, x1 = _check_box(box)
    corners = (y0, y0 + 1, x0, x0 + 1), (y0, y0 + 1, x1 - 1, x1), (y1 - 1, y1, x0, x0 + 1), (
        y1 - 1, y1, x1 - 1, x1)
    if all(_pixel_valid(inv, c, ref_shape, shrink)[0, 0] for c in corners):
        return np.ones((y1 - y0, x1 - x0), dtype=bool)
    return _pixel_valid(inv, (y0, y1, x0, x1), ref_shape, shrink)


def _scaled_positions(inv: np.ndarray, xs: np.ndarray, ys: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """``H^{-1} (x, y)`` times ``COORD_STEPS`` in float64 (``xs``, ``ys`` broadcast)."""
    scale = COORD_STEPS / (inv[2, 0] * xs + (inv[2, 1] * ys + inv[2, 2]))
    qx = (inv[0, 0] * xs + (inv[0, 1] * ys + inv[0, 2])) * scale
    qy = (inv[1, 0] * xs + (inv[1, 1] * ys + inv[1, 2])) * scale
    return qx, qy


def _quantised_maps(qx: np.ndarray, qy: np.ndarray, sbox: Box) -> tuple[np.ndarray, np.ndarray]:
    """Remap maps from positions scaled by ``COORD_STEPS`` (:func:`_scaled_positions`),
    rounded to ``1 / COORD_STEPS`` px and made relative to the source box's origin."""
    maps = []
    for q, origin in ((qx, sbox[2]), (qy, sbox[0])):
        q = np.rint(q)
        q -= origin * COORD_STEPS
        m = q.astype(np.float32)
        m *= np.float32(1.0 / COORD_STEPS)
        maps.append(m)
    return maps[0], maps[1]


def _sample_maps(inv: np.ndarray, box: Box, sbox: Box) -> tuple[np.ndarray, np.ndarray]:
    """Sampling maps of one sub-pose, relative to the source box, exact across windows.

    ``H^{-1} x`` is computed in float64 from ABSOLUTE pixel coordinates and rounded to
    ``1 / COORD_STEPS`` px; relative to the (integer) source origin such values are exact in
    float32, so a pixel gets the same sample whichever window it is rendered in.
    """
    y0, y1, x0, x1 = box
    xs = np.arange(x0, x1, dtype=np.float64)[None, :]
    ys = np.arange(y0, y1, dtype=np.float64)[:, None]
    return _quantised_maps(*_scaled_positions(inv, xs, ys), sbox)


class _Homographies:
    """The sub-pose mappings of plain homographies, in the interface of
    :class:`reblur.testbed.geometry.SceneGeometry` (``n``, ``source_box``, ``valid_window``,
    ``sample_maps``)."""

    def __init__(self, homographies: np.ndarray) -> None:
        self.homographies = _check_homographies(homographies)
        self.inv = _inverses(self.homographies)
        self.n = len(self.homographies)

    def source_box(self, box: Box, ref_shape: tuple[int, ...]) -> Box | None:
        return source_box(self.homographies, box, ref_shape)

    def valid_window(self, box: Box, ref_shape: tuple[int, ...], shrink: float) -> np.ndarray:
        return valid_window(self.homographies, box, ref_shape, shrink)

    def sample_maps(self, k: int, box: Box, sbox: Box) -> tuple[np.ndarray, np.ndarray]:
        return _sample_maps(self.inv[k], box, sbox)


def as_mapping(mapping: Any) -> Any:
    """``mapping`` as an object with ``n``, ``source_box``, ``valid_window`` and
    ``sample_maps``: a geometry (:class:`reblur.testbed.geometry.SceneGeometry`) as it is,
    an ``(n, 3, 3)`` stack of homographies wrapped."""
    if hasattr(mapping, "sample_maps"):
        return mapping
    return _Homographies(mapping)


def _read(source: Any, sbox: Box) -> np.ndarray:
    sy0, sy1, sx0, sx1 = sbox
    return np.ascontiguousarray(source[sy0:sy1, sx0:sx1], dtype=np.float32)


def render_window(
    source: Any, homographies: Any, box: Box, *, shrink: float = 2.0
) -> tuple[np.ndarray, np.ndarray]:
    """Render one window of the blurred observation and its validity mask.

    ``obs(x) = mean_k ref(H_k^{-1} x)``: per sub-pose, the sample positions ``H_k^{-1} x``
    are computed in float64 (rounded to 1/256 px so that they do not depend on the window)
    and OpenCV's bicubic (``cv2.remap`` with ``INTER_CUBIC``, the kernel
    ``cv2.warpPerspective`` uses) interpolates the reference region the window needs; the
    terms are accumulated in float64.  Samples outside the reference use a replicated
    border; such pixels are flagged invalid.  With a
    :class:`~reblur.testbed.geometry.SceneGeometry` instead of homographies, the sample
    positions are the geometry's (lens distortion, a second scene plane), the rest is the
    same.

    Parameters
    ----------
    source : array-like
        Reference, ``(H, W)`` or ``(H, W, C)``, float values; read only inside the window's
        :func:`source_box`.
    homographies : numpy.ndarray or SceneGeometry
        ``(n, 3, 3)`` reference -> observation homographies (equal exposure weights), or a
        geometry giving each sub-pose's sample positions.
    box : Box
        Observation window ``(y0, y1, x0, x1)``.
    shrink : float
        Border of the reference, in pixels, treated as outside for the mask.

    Returns
    -------
    image : numpy.ndarray
        float64 ``(y1 - y0, x1 - x0[, C])``.
    valid : numpy.ndarray
        Boolean ``(y1 - y0, x1 - x0)`` (see :func:`valid_window`).
    """
    mapping = as_mapping(homographies)
    y0, y1, x0, x1 = _check_box(box)
    ref_shape = tuple(source.shape)
    out_shape = (y1 - y0, x1 - x0) + ref_shape[2:]
    valid = mapping.valid_window(box, ref_shape, shrink)
    sbox = mapping.source_box(box, ref_shape)
    if sbox is None:
        return np.zeros(out_shape), valid
    if max(sbox[1] - sbox[0], sbox[3] - sbox[2], y1 - y0, x1 - x0) > MAX_WINDOW:
        raise ValueError(f"window {box!r} is too large for one remap: render it in tiles")
    src = _read(source, sbox)
    acc = np.zeros(out_shape, dtype=np.float64)
    for k in range(mapping.n):
        map_x, map_y = mapping.sample_maps(k, box, sbox)
        acc += cv2.remap(src, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    return acc / mapping.n, valid


def render_tiled(
    source: Any, homographies: Any, out_shape: tuple[int, int] | None = None,
    tile: int = 512,
) -> tuple[np.ndarray, np.ndarray]:
    """Render a whole (in-memory) observation tile by tile.

    Parameters
    ----------
    source : array-like
        Reference.
    homographies : numpy.ndarray or SceneGeometry
        ``(n, 3, 3)`` reference -> observation homographies, or a geometry.
    out_shape : tuple of int, optional
        Observation ``(H, W)``; default the reference's.
    tile : int
        Tile side.

    Returns
    -------
    image, valid : numpy.ndarray
        As :func:`render_window` for the full frame.
    """
    shape = tuple(out_shape) if out_shape is not None else tuple(source.shape[:2])
    image = np.zeros(shape[:2] + tuple(source.shape[2:]))
    valid = np.zeros(shape[:2], dtype=bool)
    for b in iter_tiles(shape, tile):
        image[b[0]:b[1], b[2]:b[3]], valid[b[0]:b[1], b[2]:b[3]] = render_window(
            source, homographies, b)
    return image, valid


def true_centroid(homographies: np.ndarray, xy_obs: np.ndarray) -> np.ndarray:
    """Centroid of the blur kernel: the mean reference location an observation point samples.

    Parameters
    ----------
    homographies : numpy.ndarray
        ``(n, 3, 3)`` reference -> observation homographies.
    xy_obs : numpy.ndarray
        ``(m, 2)`` observation points ``(x, y)``.

    Returns
    -------
    numpy.ndarray
        ``(m, 2)`` reference points ``mean_k H_k^{-1} xy_obs``.
    """
    pts = np.asarray(xy_obs, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"xy_obs must be (m, 2) points (x, y), got shape {pts.shape}")
    inv = _inverses(_check_homographies(homographies))
    mapped = [np.stack(_apply(h, pts[:, 0], pts[:, 1]), axis=1) for h in inv]
    return np.mean(mapped, axis=0)
