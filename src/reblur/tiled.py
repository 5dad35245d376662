"""Reblur a (huge) reference with estimated pose weights, tile by tile.

Each output tile reads only the reference window its non-zero poses touch: the halo comes
from the poses and the tile's position (a rotation about a distant principal point moves a
pixel by radius x angle), never from a fixed margin.  Per tile there is one warp per distinct
non-zero base pose (rotation / scale / tilt), built in tile-local coordinates; whole-pixel
translations are then slices added in place with their weight.  Grids with fractional
translations fall back to one warp per non-zero pose.
"""

from __future__ import annotations

import threading
from collections import defaultdict
from collections.abc import Callable, Iterator

import cv2
import numpy as np

from ._memory import thread_map
from .grid import PoseGrid, map_points, translation
from .warp import Box, as_box, read_window, source_box, warp_source

__all__ = ["reblur", "reblur_tile", "reblur_windows", "reblur_whole", "iter_tiles",
           "SparsePoses", "WholeReblur", "valid_polygon"]


class SparsePoses:
    """The non-zero poses of a weight array, grouped by base pose.

    Parameters
    ----------
    weights : ndarray, ``grid.shape``
    grid : PoseGrid
    base : (3, 3) ndarray, optional
        Coarse alignment composed before every pose.
    rtol : float
        Weights below ``rtol * max(w)`` are dropped (0 keeps every non-zero pose).
    field : reblur.align.field.DisplacementField, optional
        Local residual displacement applied after the poses: the reblurred image is
        resampled at ``p + field(p)`` (parallax, lens distortion).
    """

    def __init__(self, weights, grid: PoseGrid, base=None, rtol: float = 0.0, field=None):
        self.grid = grid
        self.field = field
        self.base = np.eye(3) if base is None else np.asarray(base, float)
        w = grid.check_weights(weights)
        groups: dict[int, list[tuple[float, float, float]]] = defaultdict(list)
        for b, iy, ix, v in grid.nonzero(w, rtol):
            groups[b].append((grid.tx[ix], grid.ty[iy], v))
        self.groups = {b: np.array(v) for b, v in sorted(groups.items())}
        self.base_h = {b: grid.base_homography(b) @ self.base for b in self.groups}
        self.integer = grid.integer_translations

    @property
    def n_poses(self) -> int:
        return sum(len(v) for v in self.groups.values())


def valid_polygon(poses: SparsePoses, ref_shape: tuple[int, ...], *,
                  margin: float = 1.0) -> np.ndarray | None:
    """Where every pose of ``poses`` reads reference pixels: the convex polygon of the
    observation inside which :func:`reblur_tile`'s validity is True (its poses only, not
    their displacement field), shrunk by ``margin`` pixels of the reference.

    A pose ``translation(t) @ B`` reads the reference at ``B^-1 (p - t)``, so it is valid
    on the quadrilateral ``B(R) + t`` (``R`` the reference's pixel centres less the
    margin: the bilinear footprint lies inside).  For one base ``B`` the translations'
    intersection is that of their convex hull's vertices (the quadrilateral is convex), and
    the polygon is the intersection over the bases.  Returns the ``(k, 2)`` vertices
    ``(x, y)``, or None when there are no poses, a base maps the reference beyond the
    horizon (no convex image) or the intersection is empty.
    """
    if not poses.groups:
        return None
    Hr, Wr = (float(v) for v in ref_shape[:2])
    m = float(margin)
    corners = np.array([[m, m], [Wr - 1 - m, m], [Wr - 1 - m, Hr - 1 - m], [m, Hr - 1 - m]])
    if corners[1, 0] < corners[0, 0] or corners[2, 1] < corners[0, 1]:
        return None
    poly = None
    for b, tw in poses.groups.items():
        Hb = poses.base_h[b]
        w = corners @ Hb[2, :2] + Hb[2, 2]
        if not np.all(w > 0):  # the reference's image crosses the horizon
            return None
        quad = map_points(Hb, corners)
        ts = tw[:, :2].astype(np.float32)
        hull = cv2.convexHull(ts).reshape(-1, 2) if len(ts) > 2 else ts
        for t in hull.astype(np.float64):
            q = np.float32(quad + t)
            if poly is None:
                poly = q
                continue
            area, got = cv2.intersectConvexConvex(poly, q)
            if got is None or area <= 0:
                return None
            poly = got.reshape(-1, 2)
    return None if poly is None else np.asarray(poly, np.float64)


def reblur_tile(poses: SparsePoses, reference, box, *, dtype=np.float32):
    """Reblurred reference on one observation window.

    Returns
    -------
    out : (h, w, C) ndarray
    valid : (h, w) bool ndarray
        True where every non-zero pose reads real reference pixels.
    """
    box = as_box(box)
    if hasattr(poses, "reblur_tile"):  # the band model (reblur.rolling.RollingPoses)
        return poses.reblur_tile(reference, box, dtype=dtype)
    fld = getattr(poses, "field", None)
    if fld is None:
        return _reblur_poses(poses, reference, box, dtype)
    # the local displacement: reblur a window grown by its reach, resample at p + d(p)
    return fld.displaced(lambda b: _reblur_poses(poses, reference, b, dtype), box)


class WholeReblur:
    """The reblur of a whole image (the poses without their displacement field), computed
    once (:func:`reblur_whole`) for the windows of several :func:`reblur_windows` calls.

    Attributes
    ----------
    image : (h, w, C) ndarray
    valid : (h, w) bool ndarray
    box : Box
        What they cover: the image grown by a margin (reblurred there as anywhere else:
        a pose reading outside the reference leaves its pixels invalid).
    """

    def __init__(self, poses: SparsePoses, image: np.ndarray, valid: np.ndarray, box: Box):
        self._groups, self._base_h = poses.groups, poses.base_h
        self.image, self.valid, self.box = image, valid, box

    def serves(self, poses: SparsePoses, box: Box, dtype=np.float32) -> bool:
        """Whether ``box`` lies inside :attr:`box`, ``poses`` are the poses reblurred (the
        same objects, with or without a field: :func:`copy.copy` shares them) and
        ``dtype`` is the reblur's."""
        b = self.box
        return (poses.groups is self._groups and poses.base_h is self._base_h
                and self.image.dtype == np.dtype(dtype)
                and b.y0 <= box.y0 and b.x0 <= box.x0 and box.y1 <= b.y1 and box.x1 <= b.x1)

    def cut(self, box: Box) -> tuple[np.ndarray, np.ndarray]:
        """Views of the reblur and its validity on ``box`` (read only: shared)."""
        sl = (slice(box.y0 - self.box.y0, box.y1 - self.box.y0),
              slice(box.x0 - self.box.x0, box.x1 - self.box.x0))
        return self.image[sl], self.valid[sl]


#: Rows :func:`reblur_whole` reblurs at once (a strip per thread).
_WHOLE_ROWS = 128


def reblur_whole(poses: SparsePoses, reference, shape: tuple[int, int], *, margin: int = 0,
                 workers: int = 1, dtype=np.float32) -> WholeReblur:
    """The reblur of the whole ``shape`` image grown by ``margin`` pixels on every side,
    without the poses' displacement field, in strips of :data:`_WHOLE_ROWS` rows on
    ``workers`` threads: what many windows covering an image read (a 1 MP image's
    displacement-field lattice, measured in passes) reblurred once.  A window cut from it
    equals its own reblur up to the rounding of OpenCV's warp coordinates
    (:func:`reblur_windows`)."""
    H, W = (int(v) for v in shape)
    m = int(margin)
    box = Box(-m, -m, H + 2 * m, W + 2 * m)
    strips = [Box(y, box.x0, min(_WHOLE_ROWS, box.y1 - y), box.w)
              for y in range(box.y0, box.y1, _WHOLE_ROWS)]
    C = reference.shape[2] if len(reference.shape) == 3 else 1
    image = np.empty((box.h, box.w, C), dtype)
    valid = np.empty((box.h, box.w), bool)

    def one(b: Box) -> None:  # each strip into its rows: no strip outlives its copy
        rows = slice(b.y0 - box.y0, b.y1 - box.y0)
        image[rows], valid[rows] = _reblur_poses(poses, reference, b, dtype)

    thread_map(one, strips, workers)
    image.flags.writeable = False
    valid.flags.writeable = False
    return WholeReblur(poses, image, valid, box)


def reblur_windows(poses: SparsePoses, reference, boxes, *, dtype=np.float32,
                   whole: WholeReblur | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """:func:`reblur_tile` on several windows, reblurred together on the box spanning them.

    A window's reblur costs about as much per rotation group of the poses as per pixel,
    so many small windows close together (a row of tie points) cost several times one
    reblur of their span.  Each result is a view of that span's reblur, then resampled
    on its own by a displacement field if the poses have one (the field's bicubic
    resampling rounds its coordinates differently on a larger window): it equals
    :func:`reblur_tile` on the window up to the rounding of OpenCV's warp coordinates,
    which depend on the window a warp is built for (a sample moved by one 1/32 px step
    here and there; the GoPro pairs' tie points came out bit for bit the same).  Pose
    models with their own tile reblur (:class:`reblur.rolling.RollingPoses`) reblur each
    window alone.  With ``whole`` (:func:`reblur_whole` of these poses) the span is cut
    from it when it lies inside; the results are then read-only views.

    Returns
    -------
    list of (out, valid)
        As :func:`reblur_tile`, one per window, in the order of ``boxes``.
    """
    boxes = [as_box(b) for b in boxes]
    if len(boxes) < 2 or hasattr(poses, "reblur_tile"):
        return [reblur_tile(poses, reference, b, dtype=dtype) for b in boxes]
    fld = getattr(poses, "field", None)
    pads = [0] * len(boxes) if fld is None else [fld.pad(b) for b in boxes]
    grown = [b.grow(p, p, p, p) for b, p in zip(boxes, pads, strict=True)]
    y0, x0 = min(g.y0 for g in grown), min(g.x0 for g in grown)
    span = Box(y0, x0, max(g.y1 for g in grown) - y0, max(g.x1 for g in grown) - x0)
    if whole is not None and whole.serves(poses, span, dtype):
        img, ok = whole.cut(span)
    else:
        img, ok = _reblur_poses(poses, reference, span, dtype)

    def cut(g: Box) -> tuple[np.ndarray, np.ndarray]:  # a window's part of the span
        sl = (slice(g.y0 - y0, g.y1 - y0), slice(g.x0 - x0, g.x1 - x0))
        return img[sl], ok[sl]

    if fld is None:
        return [cut(b) for b in boxes]
    return [fld.displaced(cut, b) for b in boxes]  # each grown by its own pad, as alone


def _reblur_poses(poses: SparsePoses, reference, box: Box, dtype) -> tuple[np.ndarray,
                                                                          np.ndarray]:
    """:func:`reblur_tile` without the displacement field."""
    C = reference.shape[2] if len(reference.shape) == 3 else 1
    out = np.zeros((box.h, box.w, C), dtype)
    valid = np.ones((box.h, box.w), bool)
    if not poses.groups:
        return out, np.zeros_like(valid)
    # every warp of the tile reads from one reference window, read once
    warps = []
    for b, tw in poses.groups.items():
        Hb = poses.base_h[b]
        if not poses.integer:
            warps += [(translation(tx, ty) @ Hb, box, v) for tx, ty, v in tw]
            continue
        tx = tw[:, 0].astype(int)
        ty = tw[:, 1].astype(int)
        ext = box.grow(int(ty.max()), int(-ty.min()), int(tx.max()),
                       int(-tx.min()))
        warps.append((Hb, ext, (tx, ty, tw[:, 2])))
    needs = [source_box(H, dst) for H, dst, _ in warps]
    fixed = _fixed_point(reference, dtype)
    source = _shared_source(reference, needs, np.uint16 if fixed else dtype)
    if fixed and source is not None:
        source[0][...] <<= 8
    shape = tuple(reference.shape[:2])
    acc = out[:, :, 0] if C == 1 else out  # OpenCV sees one multi-band image

    def view(a: np.ndarray) -> np.ndarray:
        return a[:, :, 0] if C == 1 else a

    def add(img: np.ndarray, weight: float) -> None:
        """``acc += weight * img`` (a fixed-point ``img`` scaled back by 2^-8)."""
        if fixed:
            cv2.addWeighted(img, weight / 256.0, acc, 1.0, 0.0, dst=acc, dtype=cv2.CV_32F)
        else:
            cv2.scaleAdd(img, float(np.asarray(weight, dtype)), acc, dst=acc)

    for (H, dst, what), need in zip(warps, needs, strict=True):
        if source is None:  # the window reads nothing of the reference
            img, ok = np.zeros((dst.h, dst.w, C), dtype), np.zeros((dst.h, dst.w), bool)
        else:
            img, ok = warp_source(source, H, dst, need, shape)
        if not poses.integer:
            add(view(img), float(what))
            if ok is not None:
                valid &= ok
            continue
        # whole-pixel translations: the shifted copies, weighted, added in place
        tx, ty, wv = what
        tymax, txmax = int(ty.max()), int(tx.max())
        src = view(img)
        for sx, sy, v in zip(tx, ty, wv, strict=True):
            oy, ox = tymax - int(sy), txmax - int(sx)
            add(src[oy : oy + box.h, ox : ox + box.w], float(v))
            if ok is not None:
                valid &= ok[oy : oy + box.h, ox : ox + box.w]
    return out, valid


def _fixed_point(reference, dtype) -> bool:
    """Whether the warps of an 8-bit reference run in 16-bit fixed point (the 8-bit values
    times 256) rather than in ``dtype``.

    OpenCV's bilinear warp resamples at the same 1/32 px positions with either type; the
    16-bit one rounds its result to a 256th of an 8-bit level (an error of at most 0.002
    level, 10^-5 of the range), and takes 55 % of the float32 warp's time (1188 px
    windows, one thread).  The weighted sum is taken in ``dtype`` (float32) as before.
    """
    return np.dtype(reference.dtype) == np.uint8 and np.dtype(dtype) == np.float32


def _shared_source(reference, boxes: list[Box], dtype) -> tuple[np.ndarray, Box] | None:
    """One reference window (clipped to the image) covering every box of ``boxes`` (the
    :func:`reblur.warp.source_box` of each warp)."""
    Href, Wref = reference.shape[:2]
    y0 = max(min(b.y0 for b in boxes), 0)
    x0 = max(min(b.x0 for b in boxes), 0)
    y1 = min(max(b.y1 for b in boxes), Href)
    x1 = min(max(b.x1 for b in boxes), Wref)
    if y0 >= y1 or x0 >= x1:
        return None
    sbox = Box(y0, x0, y1 - y0, x1 - x0)
    return read_window(reference, sbox, dtype), sbox


def iter_tiles(shape: tuple[int, int], tile_size: int) -> Iterator[Box]:
    """Row-major tiles covering an image of ``shape`` (last row/column may be smaller)."""
    H, W = shape
    if tile_size < 1:
        raise ValueError("tile_size must be positive")
    for y0 in range(0, H, tile_size):
        for x0 in range(0, W, tile_size):
            yield Box(y0, x0, min(tile_size, H - y0), min(tile_size, W - x0))


def reblur(
    reference,
    weights: np.ndarray,
    grid: PoseGrid,
    *,
    base: np.ndarray | None = None,
    out_shape: tuple[int, int] | None = None,
    tile_size: int = 1024,
    workers: int = 1,
    out=None,
    valid_out=None,
    dtype=np.float32,
    progress: Callable[[int], None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Reblur the whole reference with pose weights, in the observation's frame, by tiles.

    Parameters
    ----------
    reference : array-like, (H, W) or (H, W, C)
        Reference image (numpy, zarr, ...), in its own units (no rescaling is applied).
    weights : ndarray, ``grid.shape``
        Non-negative pose weights.
    grid : PoseGrid
        The grid of ``weights`` (its ``image_shape`` is the observation's).
    base : (3, 3) ndarray, optional
        Coarse alignment (reference -> observation) composed before every pose.
    out_shape : (int, int), optional
        Output size; default ``grid.image_shape``.
    tile_size : int
        Side of the output tiles.
    workers : int
        Threads pulling tiles (OpenCV runs single-threaded inside each).
    out, valid_out : array-like, optional
        Where to write (e.g. zarr or memmap arrays of shape ``(H, W, C)`` and ``(H, W)``);
        default new numpy arrays.
    dtype : numpy dtype
        Working and output precision.
    progress : callable, optional
        Called with the number of pixels of each finished tile.

    Returns
    -------
    image : (H, W) or (H, W, C) array-like
        The reblurred reference (``out`` if given); 2-D when the reference is 2-D.
    valid : (H, W) bool array-like
        False where some non-zero pose reads outside the reference ("unknown").
    """
    poses = SparsePoses(weights, grid, base)
    H, W = out_shape if out_shape is not None else grid.image_shape
    C = reference.shape[2] if len(reference.shape) == 3 else 1
    two_d = len(reference.shape) == 2
    if out is None:
        out = np.zeros((H, W) if two_d else (H, W, C), dtype)
    if valid_out is None:
        valid_out = np.zeros((H, W), bool)
    lock = threading.Lock()

    def run(box: Box) -> None:
        img, ok = reblur_tile(poses, reference, box, dtype=dtype)
        with lock:
            out[box.slices] = img[:, :, 0] if two_d else img
            valid_out[box.slices] = ok
        if progress is not None:
            progress(box.h * box.w)

    run_tiles(run, list(iter_tiles((H, W), tile_size)), workers)
    return out, valid_out


def run_tiles(fn: Callable, tiles: list, workers: int = 1) -> None:
    """Call ``fn(tile)`` for every tile, on ``workers`` threads (OpenCV single-threaded
    inside each, so the threads do not oversubscribe the cores)."""
    thread_map(fn, tiles, workers)
