"""Synthetic test data: camera-shake blur, viewpoint changes, pasted changes, noise.

The blur model is the paper's (eq. 1-2): the observation is the time average, over the
exposure, of the reference warped by the camera pose at each instant,
``g = sum_k w_k warp(f, H(p_k))``.  Every warp goes through
:func:`reblur.warp.warp_window`, so blurring works window by window on images of any size
(including on-disk zarr arrays), with the full image's geometry: rotations are about the
principal point of the FULL observation, never about a window's centre.

Two kinds of camera motion are provided:

* :class:`CameraPath` / :func:`random_camera_path` -- a smooth *continuous* trajectory,
  sampled at equal slices of the exposure time, not snapped to any pose grid (the realistic
  case: the solver can only approximate it on its grid);
* :func:`grid_path` -- a sparse, connected set of poses *on* a :class:`~reblur.grid.PoseGrid`
  with known weights (the solver can recover it exactly).

Conventions follow :mod:`reblur.grid`: pixel ``(x, y)`` = (column, row), homographies map
reference pixels to observation pixels, poses are ``(tx, ty, tz, rx, ry, rz)`` with angles
in degrees.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import cv2
import numpy as np
from scipy import ndimage

from .grid import PoseGrid, pose_homography, translation
from .warp import Box, as_box, read_window, source_box, warp_window

__all__ = [
    "DEFAULT_SHAKE",
    "DEFAULT_VIEWPOINT",
    "CameraPath",
    "MosaicScene",
    "PathBlurredScene",
    "SimulatedPair",
    "add_noise",
    "blur_along_path",
    "blur_along_path_tiled",
    "blur_weights",
    "grid_path",
    "make_pair",
    "moving_object",
    "paste_changes",
    "random_camera_path",
    "to_float",
    "viewpoint_homography",
]

_AXES = ("tx", "ty", "tz", "rx", "ry", "rz")

#: Default camera shake of :func:`make_pair` (keyword arguments of :func:`random_camera_path`).
DEFAULT_SHAKE: Mapping = MappingProxyType({"t_max": 6.0, "rz_max": 1.0})
#: Default viewpoint change of :func:`make_pair` (keywords of :func:`viewpoint_homography`).
DEFAULT_VIEWPOINT: Mapping = MappingProxyType({"max_shift_frac": 0.02, "max_rot_deg": 2.0})


def _rng(rng) -> np.random.Generator:
    """Accept a Generator (used as is) or anything ``np.random.default_rng`` takes."""
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


# ---------------------------------------------------------------------------- images
def to_float(image) -> tuple[np.ndarray, float]:
    """Convert an image to float32 in ``[0, 1]``.

    Parameters
    ----------
    image : array-like
        ``uint8`` (divided by 255), ``uint16`` (divided by 65535), any other unsigned
        integer type (divided by its maximum), ``bool``, or floating point (unchanged
        values, cast to float32).

    Returns
    -------
    image : ndarray of float32
    scale : float
        The divisor used (1.0 for floating-point and boolean input); multiply by it to get
        back to the original range.
    """
    a = np.asarray(image)
    if a.dtype == bool:
        return a.astype(np.float32), 1.0
    if np.issubdtype(a.dtype, np.floating):
        return a.astype(np.float32, copy=False), 1.0
    if np.issubdtype(a.dtype, np.unsignedinteger):
        scale = float(np.iinfo(a.dtype).max)
        return (a.astype(np.float32) / np.float32(scale)).astype(np.float32), scale
    raise TypeError(f"cannot convert images of dtype {a.dtype} to [0, 1] floats")


def _float_image(image, name: str = "image") -> np.ndarray:
    a = np.asarray(image)
    if not np.issubdtype(a.dtype, np.floating):
        raise TypeError(f"{name} must be a float image in [0, 1] (see to_float), got {a.dtype}")
    if a.ndim not in (2, 3):
        raise ValueError(f"{name} must be (h, w) or (h, w, C), got shape {a.shape}")
    return a


def add_noise(image, sigma: float, rng, *, clip: bool = True) -> np.ndarray:
    """Add white Gaussian noise of standard deviation ``sigma``.

    Parameters
    ----------
    image : ndarray
        Float image (values in ``[0, 1]``).
    sigma : float
        Noise standard deviation, in the image's units (``1/255`` is one 8-bit level).
    rng : numpy.random.Generator or int
        Random generator or seed.
    clip : bool
        Clip the result to ``[0, 1]`` (default).

    Returns
    -------
    ndarray
        Noisy image, same shape and dtype as ``image`` (float32 for non-float input).
    """
    a = np.asarray(image)
    dtype = a.dtype if np.issubdtype(a.dtype, np.floating) else np.float32
    out = a.astype(dtype, copy=True)
    if sigma > 0:
        out += (float(sigma) * _rng(rng).standard_normal(a.shape)).astype(dtype)
    if clip:
        np.clip(out, 0.0, 1.0, out=out)
    return out


# ---------------------------------------------------------------------------- camera paths
@dataclass
class CameraPath:
    """A continuous camera trajectory during the exposure.

    Parameters
    ----------
    poses : (n, 6) ndarray
        Poses ``(tx, ty, tz, rx, ry, rz)`` (pixels, relative scale, degrees), one sample
        per equal slice of the exposure time: every sample has weight ``1 / n``.
    center : (float, float)
        Principal point ``(cx, cy)`` of the FULL observation image (the centre of the
        rotations).
    focal : float, optional
        Focal length in pixels (needed when ``rx``/``ry`` are non-zero).
    """

    poses: np.ndarray
    center: tuple[float, float]
    focal: float | None = None

    def __post_init__(self):
        p = np.array(self.poses, dtype=float, copy=True)
        if p.ndim == 1 and p.size == 6:
            p = p[None, :]
        if p.ndim != 2 or p.shape[1] != 6 or p.shape[0] < 1:
            raise ValueError(f"poses must be an (n, 6) array with n >= 1, got shape {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ValueError("poses must be finite")
        self.poses = p
        self.center = (float(self.center[0]), float(self.center[1]))
        self.focal = None if self.focal is None else float(self.focal)
        if np.any(p[:, 3:5] != 0) and not (self.focal and self.focal > 0):
            raise ValueError("a positive focal length is needed for out-of-plane rotations")

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    @classmethod
    def static(cls, center: tuple[float, float]) -> CameraPath:
        """A camera that does not move (one identity pose)."""
        return cls(np.zeros((1, 6)), center)

    def homographies(self) -> list[np.ndarray]:
        """Reference -> observation homography of every sample (full-image coordinates)."""
        return [pose_homography(*p, center=self.center, focal=self.focal) for p in self.poses]

    def extent(self) -> dict[str, float]:
        """Largest absolute value of each pose axis: ``{"tx": max|tx|, ..., "rz": max|rz|}``."""
        return {a: float(np.abs(self.poses[:, i]).max()) for i, a in enumerate(_AXES)}

    def to_dict(self) -> dict:
        """JSON-ready description (inverse of :meth:`from_dict`)."""
        return {
            "axes": list(_AXES),
            "poses": [[float(v) for v in p] for p in self.poses],
            "center": [self.center[0], self.center[1]],
            "focal": self.focal,
        }

    @classmethod
    def from_dict(cls, d: Mapping) -> CameraPath:
        """Rebuild a path written by :meth:`to_dict`."""
        axes = tuple(d.get("axes", _AXES))
        if axes != _AXES:
            raise ValueError(f"unsupported pose axes {axes}, expected {_AXES}")
        return cls(np.asarray(d["poses"], dtype=float), tuple(d["center"]), d.get("focal"))


def random_camera_path(
    rng,
    *,
    center: tuple[float, float],
    n_samples: int = 64,
    t_max: float = 8.0,
    rz_max: float = 1.0,
    rxy_max: float = 0.0,
    tz_max: float = 0.0,
    focal: float | None = None,
) -> CameraPath:
    """A smooth random camera-shake trajectory.

    Each pose axis is the double integral of smoothed random accelerations (plus a random
    initial velocity), starting at the identity pose.  The values are continuous: sub-pixel
    translations and rotations between any grid's angles.  Each axis is then scaled so
    that its largest absolute value equals the requested maximum, with a random sign.

    Parameters
    ----------
    rng : numpy.random.Generator or int
        Random generator or seed.
    center : (float, float)
        Principal point ``(cx, cy)`` of the FULL observation image.
    n_samples : int
        Number of equally spaced time samples.
    t_max : float
        Largest ``|tx|`` and largest ``|ty|``, pixels.
    rz_max : float
        Largest in-plane rotation ``|rz|``, degrees.
    rxy_max : float
        Largest ``|rx|`` and ``|ry|``, degrees (needs ``focal``).
    tz_max : float
        Largest relative scale change ``|tz|``.
    focal : float, optional
        Focal length in pixels.

    Returns
    -------
    CameraPath
        ``n_samples`` poses; an axis whose maximum is 0 stays 0.
    """
    rng = _rng(rng)
    n = int(n_samples)
    if n < 1:
        raise ValueError("n_samples must be >= 1")
    if rxy_max and not focal:
        raise ValueError("rxy_max > 0 needs a focal length (pixels)")
    maxima = np.array([t_max, t_max, tz_max, rxy_max, rxy_max, rz_max], dtype=float)
    if np.any(maxima < 0):
        raise ValueError("maxima must be non-negative")
    poses = np.zeros((n, 6))
    if n > 1:
        acc = ndimage.gaussian_filter1d(
            rng.standard_normal((n, 6)), sigma=max(n / 16.0, 1.0), axis=0, mode="nearest"
        )
        acc /= acc.std(axis=0, keepdims=True) + 1e-12
        vel = np.cumsum(acc, axis=0) + rng.normal(0.0, 0.5 * np.sqrt(n), size=(1, 6))
        pos = np.concatenate([np.zeros((1, 6)), np.cumsum(vel[:-1], axis=0)])
        peak = np.abs(pos).max(axis=0)
        sign = rng.choice([-1.0, 1.0], size=6)
        scale = np.where(peak > 0, maxima / np.where(peak > 0, peak, 1.0), 0.0)
        poses = pos * (scale * sign)[None, :]
    return CameraPath(poses, center, focal)


def grid_path(
    grid: PoseGrid, rng, n_poses: int = 20, *, return_indices: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """A known sparse camera path ON a pose grid: a connected walk with random dwell times.

    The walk starts near the grid centre and each step moves one index (``+-1``) along one
    of the weight axes ``(base, ty, tx)``, never leaving the grid nor revisiting a pose
    (depth-first search with backtracking, so it also works on small grids).

    Parameters
    ----------
    grid : PoseGrid
        The pose grid.
    rng : numpy.random.Generator or int
        Random generator or seed.
    n_poses : int
        Number of distinct poses on the path (at most ``grid.size``).
    return_indices : bool
        Also return the visited ``(b, iy, ix)`` indices in walk order.

    Returns
    -------
    weights : ndarray, shape ``grid.shape``
        Positive on the path (random dwell times), zero elsewhere, summing to 1.
    indices : (n_poses, 3) int ndarray
        Only with ``return_indices``.
    """
    rng = _rng(rng)
    shape = grid.shape
    n = int(n_poses)
    if not 1 <= n <= grid.size:
        raise ValueError(f"n_poses must be in [1, {grid.size}], got {n_poses}")
    moves = [
        np.array(m) for m in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))
    ]
    move_pref = np.array([1.0, 1.0, 2.0, 2.0, 2.0, 2.0])
    dims = np.array(shape)

    def start_index(jitter: int) -> tuple[int, ...]:
        c = dims // 2 + rng.integers(-jitter, jitter + 1, size=3)
        return tuple(int(v) for v in np.clip(c, 0, dims - 1))

    def candidates(cur, prev_move, visited):
        # random order, base (rotation) steps drawn less often than translation steps
        keys = rng.random(len(moves)) ** (1.0 / move_pref)
        order = [int(i) for i in np.argsort(-keys)]
        if prev_move is not None and rng.random() < 0.5:  # some momentum: path-like walks
            order.remove(prev_move)
            order.insert(0, prev_move)
        out = []
        for m in order:
            nxt = tuple(int(v) for v in np.asarray(cur) + moves[m])
            if all(0 <= v < d for v, d in zip(nxt, shape, strict=True)) and nxt not in visited:
                out.append((m, nxt))
        return out

    walk: list[tuple[int, ...]] | None = None
    for attempt in range(50):
        budget = 200 * n
        start = start_index(min(1 + attempt // 5, max(shape)))
        walk_try, visited = [start], {start}
        stack = [candidates(start, None, visited)]
        while len(walk_try) < n and stack and budget > 0:
            budget -= 1
            if not stack[-1]:  # dead end: backtrack
                stack.pop()
                visited.discard(walk_try.pop())
                continue
            m, nxt = stack[-1].pop(0)
            if nxt in visited:
                continue
            walk_try.append(nxt)
            visited.add(nxt)
            stack.append(candidates(nxt, m, visited))
        if len(walk_try) == n:
            walk = walk_try
            break
    if walk is None:
        raise RuntimeError(f"could not find a connected path of {n} poses on {grid!r}")
    idx = np.array(walk, dtype=int).reshape(n, 3)
    dwell = rng.uniform(0.3, 1.0, size=n)
    weights = np.zeros(shape)
    weights[idx[:, 0], idx[:, 1], idx[:, 2]] = dwell / dwell.sum()
    return (weights, idx) if return_indices else weights


def viewpoint_homography(
    rng,
    shape: tuple[int, ...],
    *,
    max_shift_frac: float = 0.05,
    max_rot_deg: float = 5.0,
    max_scale: float = 0.02,
    max_persp: float = 0.0,
) -> np.ndarray:
    """A random viewpoint change (reference -> observation) about the image centre.

    ``H = T(c + s) @ R(theta) @ diag(k, k, 1) @ P @ T(-c)`` with ``c`` the image centre,
    shift ``|s_x| <= max_shift_frac * w``, ``|s_y| <= max_shift_frac * h``,
    ``|theta| <= max_rot_deg``, ``|k - 1| <= max_scale``, and ``P`` a perspective term
    whose projective denominator stays within ``1 +- max_persp`` over the whole image
    (relative to its value at the centre).  The centre maps to ``c + s``.

    Parameters
    ----------
    rng : numpy.random.Generator or int
        Random generator or seed.
    shape : (h, w) or (h, w, C)
        Image shape.
    max_shift_frac, max_rot_deg, max_scale, max_persp : float
        Bounds, see above.

    Returns
    -------
    (3, 3) ndarray
        Normalised so that ``H[2, 2] == 1``.
    """
    rng = _rng(rng)
    h, w = int(shape[0]), int(shape[1])
    c = ((w - 1) / 2.0, (h - 1) / 2.0)
    sx, sy = rng.uniform(-1.0, 1.0, size=2) * max_shift_frac * np.array([w, h])
    theta = rng.uniform(-1.0, 1.0) * max_rot_deg
    k = 1.0 + rng.uniform(-1.0, 1.0) * max_scale
    H = pose_homography(sx, sy, k - 1.0, 0.0, 0.0, theta, center=c)
    if max_persp > 0:
        u = rng.uniform(-1.0, 1.0, size=2)
        u *= rng.uniform(0.0, 1.0) * max_persp / max(np.abs(u).sum(), 1e-12)
        hw, hh = max(w / 2.0, 0.5), max(h / 2.0, 0.5)
        P = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [u[0] / hw, u[1] / hh, 1.0]])
        H = H @ translation(*c) @ P @ translation(-c[0], -c[1])
    return H / H[2, 2]


# ---------------------------------------------------------------------------- blurring
def _path_homographies(path, base) -> list[np.ndarray]:
    if isinstance(path, CameraPath):
        hs = path.homographies()
    else:
        arr = np.asarray(path, dtype=float)
        if arr.ndim == 2 and arr.shape == (3, 3):
            arr = arr[None]
        if arr.ndim != 3 or arr.shape[1:] != (3, 3) or arr.shape[0] < 1:
            raise TypeError("path must be a CameraPath or a sequence of 3x3 homographies")
        hs = list(arr)
    if base is None:
        return [np.asarray(H, dtype=float) for H in hs]
    B = np.asarray(base, dtype=float)
    if B.shape != (3, 3):
        raise ValueError(f"base must be a 3x3 homography, got shape {B.shape}")
    return [np.asarray(H, dtype=float) @ B for H in hs]


def _channels(reference) -> int:
    return int(reference.shape[2]) if len(reference.shape) == 3 else 1


def _blur_box(reference, hs: Sequence[np.ndarray], box: Box, dtype) -> tuple[np.ndarray, ...]:
    """Mean of the warps ``hs`` of ``reference`` into ``box``: ``(h, w, C)`` and valid mask.

    The reference window every warp needs is read once (the union of their source boxes,
    clipped to the image) and shared by all warps.
    """
    Href, Wref = reference.shape[:2]
    C = _channels(reference)
    boxes = [source_box(H, box) for H in hs]
    y0 = max(min(b.y0 for b in boxes), 0)
    x0 = max(min(b.x0 for b in boxes), 0)
    y1 = min(max(b.y1 for b in boxes), Href)
    x1 = min(max(b.x1 for b in boxes), Wref)
    acc = np.zeros((box.h, box.w, C), dtype)
    if y0 >= y1 or x0 >= x1:
        return acc, np.zeros((box.h, box.w), bool)
    sbox = Box(y0, x0, y1 - y0, x1 - x0)
    src = read_window(reference, sbox, dtype)
    valid = np.ones((box.h, box.w), bool)
    for H in hs:
        out, ok = warp_window(reference, H, box, dtype=dtype, source=(src, sbox))
        acc += out
        valid &= ok
    acc /= dtype(len(hs))
    return acc, valid


def _full_box(reference, box) -> Box:
    if box is None:
        return Box(0, 0, int(reference.shape[0]), int(reference.shape[1]))
    return as_box(box)


def _like_reference(out: np.ndarray, reference) -> np.ndarray:
    return out[:, :, 0] if len(reference.shape) == 2 else out


def blur_along_path(
    reference, path, box=None, *, base: np.ndarray | None = None, dtype=np.float32
) -> tuple[np.ndarray, np.ndarray]:
    """Blur an image along a camera path: the mean of its warps by every path sample.

    ``g = mean_k warp(reference, H_k @ base)`` evaluated in the observation window ``box``.

    Parameters
    ----------
    reference : array-like, (H, W) or (H, W, C)
        Sharp image (numpy, zarr, ...); only the window the box needs is read.
    path : CameraPath or sequence of (3, 3) ndarray
        The camera motion (equal weight per sample).
    box : Box or (y0, x0, h, w), optional
        Observation window (full-image coordinates); default the whole reference frame.
    base : (3, 3) ndarray, optional
        Viewpoint homography applied before the camera shake (default identity).
    dtype : numpy dtype
        Working and output precision.  With OpenCV 5, float32 warps are the more accurate
        ones (single-precision coordinates, window-local); float64 warps snap coordinates
        to 1/32 pixel.

    Returns
    -------
    image : ndarray, (h, w) or (h, w, C) like ``reference``
        Blurred window (partial sums near unknown regions, 0 where nothing is known).
    valid : (h, w) bool ndarray
        True where every sample's warp is inside the reference.
    """
    hs = _path_homographies(path, base)
    box = _full_box(reference, box)
    dtype = np.dtype(dtype).type
    out, valid = _blur_box(reference, hs, box, dtype)
    return _like_reference(out, reference), valid


def blur_weights(
    reference,
    grid: PoseGrid,
    weights: np.ndarray,
    box=None,
    *,
    base: np.ndarray | None = None,
    dtype=np.float32,
) -> tuple[np.ndarray, np.ndarray]:
    """Blur an image by pose weights on a grid, one explicit warp per pose (``F @ w``).

    This is the slow, obviously correct reference implementation of the blur operator:
    ``sum_k w_k warp(reference, H(p_k) @ base)`` over the poses with non-zero weight, each
    warp a :func:`~reblur.warp.warp_window` of the whole ``box`` in precision ``dtype``,
    accumulated in float64.  Weights are used as given (not normalised).

    Note that OpenCV 5 warps float32 images with single-precision coordinates but float64
    images on a 1/32-pixel coordinate table, so the two precisions differ by up to
    ~1/64 px times the image gradient; compare against an operator of the same ``dtype``.

    Parameters
    ----------
    reference : array-like, (H, W) or (H, W, C)
        Sharp image.
    grid : PoseGrid
        The pose grid.
    weights : ndarray
        ``grid.size`` non-negative weights (any shape that reshapes to ``grid.shape``).
    box : Box or (y0, x0, h, w), optional
        Observation window; default the whole reference frame.
    base : (3, 3) ndarray, optional
        Viewpoint homography applied before the pose (default identity).
    dtype : numpy dtype
        Warp and output precision.

    Returns
    -------
    image : ndarray, (h, w) or (h, w, C) like ``reference``
    valid : (h, w) bool ndarray
        True where every pose with non-zero weight warps from inside the reference.
    """
    w = grid.check_weights(weights)
    box = _full_box(reference, box)
    B = np.eye(3) if base is None else np.asarray(base, dtype=float)
    acc = np.zeros((box.h, box.w, _channels(reference)), np.float64)
    valid = np.ones((box.h, box.w), bool)
    for b, iy, ix, wk in grid.nonzero(w):
        out, ok = warp_window(reference, grid.homography((b, iy, ix)) @ B, box, dtype=dtype)
        acc += wk * out
        valid &= ok
    return _like_reference(acc.astype(dtype), reference), valid


def blur_along_path_tiled(
    reference,
    path,
    out,
    *,
    base: np.ndarray | None = None,
    tile: int = 1024,
    valid_out=None,
):
    """Blur along a camera path tile by tile, writing into an array-like output.

    Same values as :func:`blur_along_path` over the whole frame (up to ~1e-5: OpenCV
    computes float32 warp coordinates in single precision, and tile-local coordinates
    are smaller than whole-frame ones), but the working set is one
    ``tile x tile`` output window plus the reference window it reads (the tile grown by the
    blur's extent), so ``reference`` and ``out`` may be larger than memory (zarr arrays,
    memory maps, ...).

    Parameters
    ----------
    reference : array-like, (H, W) or (H, W, C)
        Sharp image.
    path : CameraPath or sequence of (3, 3) ndarray
        The camera motion.
    out : array-like, (Ho, Wo) or (Ho, Wo, C)
        Output, observation frame (any size; the path's centre should be its centre).
        Written with ``out[y0:y1, x0:x1] = ...``; a floating dtype is expected, the
        float32 result is cast to it.
    base : (3, 3) ndarray, optional
        Viewpoint homography applied before the shake.
    tile : int
        Tile side in pixels (align it with ``out``'s chunks for zarr).
    valid_out : array-like of bool, (Ho, Wo), optional
        Receives the valid mask.

    Returns
    -------
    out
        The output array, for convenience.
    """
    hs = _path_homographies(path, base)
    Ho, Wo = out.shape[:2]
    C = _channels(reference)
    if (
        len(out.shape) not in (2, 3)
        or (len(out.shape) == 3 and out.shape[2] != C)
        or (len(out.shape) == 2 and C != 1)
    ):
        raise ValueError(f"out shape {out.shape} does not match the reference's channels ({C})")
    if valid_out is not None and tuple(valid_out.shape[:2]) != (Ho, Wo):
        raise ValueError("valid_out must have the output's height and width")
    tile = int(tile)
    if tile < 1:
        raise ValueError("tile must be positive")
    for y0 in range(0, Ho, tile):
        for x0 in range(0, Wo, tile):
            box = Box(y0, x0, min(tile, Ho - y0), min(tile, Wo - x0))
            img, valid = _blur_box(reference, hs, box, np.float32)
            out[box.slices] = img[:, :, 0] if len(out.shape) == 2 else img
            if valid_out is not None:
                valid_out[box.slices] = valid
    return out


# ---------------------------------------------------------------------------- changes
def _object_mask(rng: np.random.Generator, size: float) -> np.ndarray:
    """A filled rotated rectangle or ellipse of longest side ``size`` pixels (cropped)."""
    a = max(size / 2.0, 1.5)
    b = max(a * rng.uniform(0.45, 1.0), 1.5)
    ang = rng.uniform(0.0, np.pi)
    r = int(np.ceil(np.hypot(a, b))) + 1
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1].astype(float)
    u = xx * np.cos(ang) + yy * np.sin(ang)
    v = -xx * np.sin(ang) + yy * np.cos(ang)
    if rng.random() < 0.5:
        m = (np.abs(u) <= a) & (np.abs(v) <= b)
    else:
        m = (u / a) ** 2 + (v / b) ** 2 <= 1.0
    rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
    return m[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]


def _texture(rng: np.random.Generator, shape: tuple[int, int], mask: np.ndarray) -> np.ndarray:
    """Smooth random texture, zero mean and unit standard deviation over ``mask``."""
    s = max(1.0, min(shape) / 8.0)
    t = ndimage.gaussian_filter(rng.standard_normal(shape), s)
    t -= t[mask].mean()
    sd = t[mask].std()
    return t / sd if sd > 0 else t


def _object_values(
    rng: np.random.Generator,
    mask: np.ndarray,
    local: np.ndarray,
    sign: float,
    low: bool,
    strength: tuple[float, float] = (0.2, 0.45),
) -> np.ndarray:
    """Pixel values ``(ph, pw, C)`` of a textured object over a background of mean ``local``.

    ``low``: mean offset within ~0.06 of ``local`` (but with texture and an outline);
    otherwise a clear offset in ``strength`` of polarity ``sign`` (flipped when ``[0, 1]``
    leaves less room than ``strength[0]`` that way and more the other way).
    """
    C = local.size
    ph, pw = mask.shape
    tex = _texture(rng, (ph, pw), mask)
    ring = mask & ~ndimage.binary_erosion(mask)
    if low:
        delta = sign * rng.uniform(0.03, 0.06) * np.ones(C)
        amp, edge = 0.025, 0.04
    else:
        up, down = float((1.0 - local).min()), float(local.min())
        room, other = (up, down) if sign > 0 else (down, up)
        if room < strength[0] and other > room:
            sign = -sign
        delta = sign * rng.uniform(*strength) * rng.uniform(0.8, 1.2, size=C)
        amp, edge = rng.uniform(0.03, 0.07), 0.06
    val = local[None, None, :] + delta[None, None, :] + amp * tex[:, :, None]
    val += np.where(ring, -np.sign(delta.mean()) * edge, 0.0)[:, :, None]  # an outline
    return np.clip(val, 0.0, 1.0)


def _local_mean(img: np.ndarray, y0: int, x0: int, mask: np.ndarray) -> np.ndarray:
    ph, pw = mask.shape
    win = img[y0 : y0 + ph, x0 : x0 + pw]
    win = win[:, :, None] if win.ndim == 2 else win
    return win[mask].astype(float).mean(axis=0)


def paste_changes(
    image,
    rng,
    n: int = 4,
    *,
    size_range: tuple[float, float] = (0.03, 0.12),
    low_contrast: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Paste ``n`` textured objects (rotated rectangles and ellipses) into an image.

    Polarities alternate (brighter / darker than the local background, i.e. the mean of the
    pixels the object covers; the first one is random).  With ``low_contrast`` the last
    object's mean is within ~0.06 of the local background, with a faint texture and outline,
    so only its structure gives it away.  Objects are placed without overlap when possible.

    Parameters
    ----------
    image : ndarray, (h, w) or (h, w, C), float in [0, 1]
        Scene to change (not modified).
    rng : numpy.random.Generator or int
        Random generator or seed.
    n : int
        Number of objects.
    size_range : (float, float)
        Longest side of an object as a fraction of ``min(h, w)``.
    low_contrast : bool
        Make one object (the last) low-contrast.

    Returns
    -------
    changed : ndarray
        Copy of ``image`` with the objects, same shape and dtype.
    truth : (h, w) bool ndarray
        Object footprints; exactly the pixels that may differ from ``image``.
    """
    rng = _rng(rng)
    img = _float_image(image)
    h, w = img.shape[:2]
    out = img.copy()
    out3 = out[:, :, None] if out.ndim == 2 else out
    truth = np.zeros((h, w), bool)
    keepout = np.zeros((h, w), bool)
    first = rng.choice([-1.0, 1.0])
    lo, hi = size_range
    for i in range(int(n)):
        size = min(rng.uniform(lo, hi) * min(h, w), min(h, w) - 2)
        mask = _object_mask(rng, max(size, 3.0))
        ph, pw = mask.shape
        if ph > h or pw > w:
            continue
        for _ in range(100):  # avoid overlapping earlier objects when there is room
            y0 = int(rng.integers(0, h - ph + 1))
            x0 = int(rng.integers(0, w - pw + 1))
            if not np.any(keepout[y0 : y0 + ph, x0 : x0 + pw] & mask):
                break
        low = low_contrast and i == n - 1
        sign = first * (1.0 if i % 2 == 0 else -1.0)
        local = _local_mean(img, y0, x0, mask)
        vals = _object_values(rng, mask, local, sign, low).astype(out.dtype)
        win = out3[y0 : y0 + ph, x0 : x0 + pw]
        win[mask] = vals[mask]
        truth[y0 : y0 + ph, x0 : x0 + pw] |= mask
        keepout[max(y0 - 3, 0) : y0 + ph + 3, max(x0 - 3, 0) : x0 + pw + 3] = True
    return out, truth


def moving_object(
    image,
    rng,
    *,
    size_range: tuple[float, float] = (0.03, 0.08),
    travel_range: tuple[float, float] = (0.04, 0.12),
    n_steps: int = 32,
    sign: float | None = None,
    truth: str = "swept",
) -> tuple[np.ndarray, np.ndarray]:
    """Paste an object that moves on its own during the exposure (a cyclist, a car).

    The object travels along a straight segment; the result is the time average of the
    scene with the object at ``n_steps`` equally spaced (sub-pixel) positions, i.e. the
    object blurred by its own linear motion.  The camera's shake is applied on top of this
    by :func:`blur_along_path`.

    Parameters
    ----------
    image : ndarray, (h, w) or (h, w, C), float in [0, 1]
        Scene (not modified).
    rng : numpy.random.Generator or int
        Random generator or seed.
    size_range : (float, float)
        Longest side of the object, fraction of ``min(h, w)``.
    travel_range : (float, float)
        Length of its path during the exposure, fraction of ``min(h, w)``.
    n_steps : int
        Time samples.
    sign : float, optional
        ``+1`` brighter / ``-1`` darker than the background (random by default; flipped
        when the background leaves no room for a strong contrast that way).
    truth : {"swept", "half_max", "occupancy"}
        Which footprint to return (``"occupancy"``: the float fraction itself).
        ``"swept"``: every pixel the object covered at some instant, i.e. exactly the
        pixels that may differ from ``image`` (including the faint ends of the smear,
        covered for a small fraction of the exposure).
        ``"half_max"``: pixels whose occupancy (fraction of the exposure the object covers
        them) is at least half the largest occupancy -- the full width at half maximum of
        the smear, the same rule as the ``>= 0.5`` footprint of a static change carried
        through the camera blur (:func:`make_pair`).

    Returns
    -------
    changed : ndarray
        Copy of ``image`` with the moving object, same shape and dtype.
    truth : (h, w) ndarray
        The footprint chosen by ``truth`` (bool; float32 for ``"occupancy"``).
    """
    if truth not in ("swept", "half_max", "occupancy"):
        raise ValueError(f"truth must be 'swept', 'half_max' or 'occupancy', got {truth!r}")
    rng = _rng(rng)
    img = _float_image(image)
    h, w = img.shape[:2]
    m = min(h, w)
    size = max(rng.uniform(*size_range) * m, 3.0)
    mask = _object_mask(rng, size)
    ph, pw = mask.shape
    ang = rng.uniform(0.0, 2 * np.pi)
    travel = rng.uniform(*travel_range) * m
    # shrink the travel until the swept box fits in the image (1 px margin for sub-pixels)
    for _ in range(60):
        dx, dy = travel * np.cos(ang), travel * np.sin(ang)
        bw, bh = pw + int(np.ceil(abs(dx))) + 2, ph + int(np.ceil(abs(dy))) + 2
        if bw <= w and bh <= h:
            break
        travel *= 0.8
    else:
        raise ValueError(f"image {h}x{w} is too small for a moving object")
    by0 = int(rng.integers(0, h - bh + 1))
    bx0 = int(rng.integers(0, w - bw + 1))
    # start position (patch top-left) inside the swept box, in box coordinates
    sx = 1.0 + (abs(dx) if dx < 0 else 0.0)
    sy = 1.0 + (abs(dy) if dy < 0 else 0.0)
    bg = img[by0 : by0 + bh, bx0 : bx0 + bw]
    bg3 = (bg[:, :, None] if bg.ndim == 2 else bg).astype(np.float32)
    local = _local_mean(img, by0 + int(round(sy)), bx0 + int(round(sx)), mask)
    s = rng.choice([-1.0, 1.0]) if sign is None else float(np.sign(sign) or 1.0)
    vals = _object_values(rng, mask, local, s, False, (0.4, 0.7)).astype(np.float32)
    alpha0 = mask.astype(np.float32)
    premult0 = vals * alpha0[:, :, None]
    C = bg3.shape[2]
    acc = np.zeros_like(bg3)
    swept = np.zeros((bh, bw), np.float32)
    for t in np.linspace(0.0, 1.0, max(int(n_steps), 1)):
        M = np.array([[1.0, 0.0, sx + t * dx], [0.0, 1.0, sy + t * dy]])
        a = cv2.warpAffine(
            alpha0,
            M,
            (bw, bh),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        p = np.empty_like(bg3)
        for c in range(C):
            p[:, :, c] = cv2.warpAffine(
                np.ascontiguousarray(premult0[:, :, c]),
                M,
                (bw, bh),
                flags=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=0,
            )
        acc += bg3 * (1.0 - a)[:, :, None] + p
        swept += a
    acc /= np.float32(max(int(n_steps), 1))
    foot = swept > 0
    if truth == "occupancy":
        keep = swept / np.float32(max(int(n_steps), 1))
    else:
        keep = foot if truth == "swept" else swept >= 0.5 * swept.max()
    out = img.copy()
    out3 = out[:, :, None] if out.ndim == 2 else out
    win = out3[by0 : by0 + bh, bx0 : bx0 + bw]
    win[foot] = np.clip(acc[foot], 0.0, 1.0).astype(out.dtype)
    mask = np.zeros((h, w), keep.dtype)
    mask[by0 : by0 + bh, bx0 : bx0 + bw] = keep
    return out, mask


# ---------------------------------------------------------------------------- pairs
@dataclass
class SimulatedPair:
    """A synthetic (reference, blurred observation) pair with its ground truth.

    Attributes
    ----------
    reference : ndarray
        Sharp reference image, float32 in [0, 1].
    observed : ndarray
        Blurred, re-viewpointed, noisy observation of the changed scene (same shape).
    truth : (h, w) bool ndarray
        Changes in the observation frame (only where known: ``truth & unknown`` is empty).
    unknown : (h, w) bool ndarray
        Observation pixels the reference does not cover (under some camera pose).
    path : CameraPath
        The camera shake (centre = observation centre).
    viewpoint : (3, 3) ndarray
        Reference -> observation viewpoint homography, applied before the shake.
    scene : ndarray, optional
        The sharp changed scene in the reference frame (before viewpoint and blur).
    scene_truth : ndarray, optional
        The changes in the reference frame (the moving object by its half-maximum
        footprint).
    scene_changed : ndarray, optional
        Every scene pixel that may differ from the reference (the moving object by its
        whole swept footprint).
    """

    reference: np.ndarray
    observed: np.ndarray
    truth: np.ndarray
    unknown: np.ndarray
    path: CameraPath
    viewpoint: np.ndarray
    scene: np.ndarray | None = None
    scene_truth: np.ndarray | None = None
    scene_changed: np.ndarray | None = None

    def meta(self) -> dict:
        """JSON-ready record of the motion: ``{"path": ..., "viewpoint": ...}``."""
        return {
            "path": self.path.to_dict(),
            "viewpoint": [[float(v) for v in row] for row in self.viewpoint],
        }


def make_pair(
    image_before,
    image_after=None,
    *,
    rng,
    shake: Mapping | None = DEFAULT_SHAKE,
    viewpoint: Mapping | None = DEFAULT_VIEWPOINT,
    n_changes: int = 4,
    moving: bool | Mapping = True,
    low_contrast: bool = True,
    noise_sigma: float = 1.0 / 255.0,
) -> SimulatedPair:
    """Simulate a change-detection pair: sharp reference, blurred changed observation.

    The "after" scene (``image_after``, or a copy of ``image_before``) gets
    ``n_changes`` pasted objects (:func:`paste_changes`) and, with ``moving``, one object
    moving during the exposure (:func:`moving_object`).  It is then warped by a random
    viewpoint homography, blurred along a random camera path (rotations about the
    observation's centre), noised and clipped to [0, 1].  The truth is the float change
    mask carried the same way (same path and viewpoint) and thresholded at 0.5; the moving
    object enters it by its half-maximum smear footprint (``truth="half_max"`` of
    :func:`moving_object`), not by the faint ends it covers for an instant.

    Parameters
    ----------
    image_before : ndarray, (h, w) or (h, w, C)
        The reference (uint8, uint16 or float in [0, 1]).
    image_after : ndarray, optional
        A real later image of the scene, aligned with ``image_before`` (same shape).
    rng : numpy.random.Generator or int
        Random generator or seed.
    shake : mapping, optional
        Keywords of :func:`random_camera_path` (``center`` is set here); ``None`` for a
        still camera.  Default :data:`DEFAULT_SHAKE` (``t_max=6, rz_max=1``).
    viewpoint : mapping, optional
        Keywords of :func:`viewpoint_homography`; ``None`` for the same viewpoint.
        Default :data:`DEFAULT_VIEWPOINT` (``max_shift_frac=0.02, max_rot_deg=2``).
    n_changes : int
        Number of pasted static objects.
    moving : bool or mapping
        Add one object moving during the exposure; a mapping is passed on to
        :func:`moving_object` (e.g. ``{"travel_range": (0.02, 0.04)}``).
    low_contrast : bool
        Make the last pasted object a low-contrast one (see :func:`paste_changes`).
    noise_sigma : float
        Standard deviation of the added Gaussian noise.

    Returns
    -------
    SimulatedPair
    """
    rng = _rng(rng)
    reference = to_float(image_before)[0]
    _float_image(reference, "image_before")
    if image_after is None:
        scene = reference.copy()
    else:
        scene = to_float(image_after)[0].copy()
        if scene.shape != reference.shape:
            raise ValueError(
                f"image_after {scene.shape} must have the shape of image_before {reference.shape}"
            )
    h, w = reference.shape[:2]
    mask = np.zeros((h, w), bool)
    if n_changes > 0:
        scene, mask = paste_changes(scene, rng, n_changes, low_contrast=low_contrast)
    changed = mask.copy()
    if moving:
        opts = dict(moving) if isinstance(moving, Mapping) else {}
        opts.pop("truth", None)
        scene, occ = moving_object(scene, rng, truth="occupancy", **opts)
        mask |= occ >= 0.5 * occ.max()
        changed |= occ > 0
    center = ((w - 1) / 2.0, (h - 1) / 2.0)  # observation frame = reference frame's size
    V = np.eye(3) if viewpoint is None else viewpoint_homography(rng, (h, w), **viewpoint)
    if shake is None:
        path = CameraPath.static(center)
    else:
        path = random_camera_path(rng, center=center, **dict(shake))
    blurred, valid = blur_along_path(scene, path, base=V)
    observed = add_noise(blurred, noise_sigma, rng, clip=True)
    carried, _ = blur_along_path(mask.astype(np.float32), path, base=V)
    truth = (carried >= 0.5) & valid
    return SimulatedPair(
        reference=reference,
        observed=observed,
        truth=truth,
        unknown=~valid,
        path=path,
        viewpoint=V,
        scene=scene,
        scene_truth=mask,
        scene_changed=changed,
    )


class MosaicScene:
    """A huge virtual image made of real images, computed window by window on demand.

    The image is a ``rows x cols`` mosaic of cells of ``cell x cell`` pixels; each cell is
    one of ``images`` (cycled), flipped/transposed at random, and resampled to the cell size
    by bicubic interpolation.  Every pixel is computed from the same formula whichever
    window asks for it, so any window equals the same window of the whole mosaic; nothing
    full-size is ever held.  Supports ``scene[y0:y1, x0:x1]`` (steps allowed), ``shape`` and
    ``dtype`` like an array, so it can stand in for a gigapixel reference anywhere reblur
    reads windows.

    Parameters
    ----------
    images : sequence of (h, w) ndarray
        Grayscale source images (float in [0, 1] or uint8/uint16).
    cell : int
        Cell side in pixels (e.g. ``2 * 1024`` to upsample 1024 px images x 2).
    rows, cols : int
        Mosaic size in cells; ``shape = (rows * cell, cols * cell)``.
    rng : numpy.random.Generator or int
        Seed of the per-cell image choice and orientation.
    """

    def __init__(self, images, cell: int, rows: int, cols: int, rng=0):
        gen = _rng(rng)
        self.images = [to_float(np.asarray(im))[0] for im in images]
        if any(im.ndim != 2 for im in self.images):
            raise ValueError("MosaicScene takes grayscale images")
        self.cell = int(cell)
        self.shape = (int(rows) * self.cell, int(cols) * self.cell)
        self.dtype = np.dtype(np.float32)
        self.ndim = 2
        n = len(self.images)
        self._pick = [
            [(int(gen.integers(n)), int(gen.integers(8))) for _ in range(cols)]
            for _ in range(rows)
        ]

    def __getitem__(self, key):
        ys, xs = key
        y0, y1, sy = ys.indices(self.shape[0])
        x0, x1, sx = xs.indices(self.shape[1])
        yy = np.arange(y0, y1, sy)
        xx = np.arange(x0, x1, sx)
        out = np.zeros((yy.size, xx.size), np.float32)
        c = self.cell
        for ci in np.unique(yy // c):
            ry = np.flatnonzero(yy // c == ci)
            for cj in np.unique(xx // c):
                rx = np.flatnonzero(xx // c == cj)
                k, o = self._pick[ci][cj]
                img = self.images[k]
                ly = (yy[ry] - ci * c).astype(np.float32)
                lx = (xx[rx] - cj * c).astype(np.float32)
                if o & 1:
                    ly = c - 1 - ly
                if o & 2:
                    lx = c - 1 - lx
                if o & 4:  # transpose the cell
                    ly, lx = lx, ly
                    gy, gx = np.meshgrid(ly, lx, indexing="xy")
                else:
                    gx, gy = np.meshgrid(lx, ly, indexing="xy")
                h, w = img.shape
                mx = ((gx + 0.5) * (w / c) - 0.5).astype(np.float32)
                my = ((gy + 0.5) * (h / c) - 0.5).astype(np.float32)
                part = cv2.remap(img, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
                out[np.ix_(ry, rx)] = np.clip(part, 0.0, 1.0)
        return out

    def __array__(self, dtype=None, copy=None):
        a = self[:, :]
        return a if dtype is None else a.astype(dtype)


class PathBlurredScene:
    """The blur of an image along a camera path, computed window by window on demand.

    Stands in for a huge blurred observation (e.g. of a :class:`MosaicScene`) wherever
    reblur reads windows: ``blurred[y0:y1, x0:x1]`` is :func:`blur_along_path` on that
    window (float32, gray images), so nothing full-size is held.

    Parameters
    ----------
    scene : array-like, (H, W)
        Sharp image (numpy, :class:`MosaicScene`, ...).
    path : CameraPath
        Camera motion, in the scene's full-image coordinates.

    Examples
    --------
    >>> import numpy as np
    >>> scene = np.random.default_rng(0).random((64, 64))
    >>> obs = PathBlurredScene(scene, CameraPath.static((31.5, 31.5)))
    >>> bool(np.allclose(obs[8:40, 8:40], scene[8:40, 8:40], atol=1e-6))
    True
    """

    def __init__(self, scene, path: CameraPath):
        if len(scene.shape) != 2:
            raise ValueError(f"PathBlurredScene takes a gray (H, W) scene, got {scene.shape}")
        self.scene, self.path = scene, path
        self.shape, self.dtype = tuple(scene.shape), np.dtype(np.float32)

    def window(self, box) -> tuple[np.ndarray, np.ndarray]:
        """Blurred window ``(y0, x0, h, w)`` and its validity (every sample inside)."""
        y0, x0, h, w = (int(v) for v in box)
        g, v = blur_along_path(self.scene, self.path, (y0, x0, h, w), dtype=np.float32)
        return g.reshape(h, w), v

    def __getitem__(self, key):
        ys, xs = key
        if not (isinstance(ys, slice) and isinstance(xs, slice)) or (ys.step or 1) != 1 or (
            xs.step or 1
        ) != 1:
            raise IndexError("PathBlurredScene takes two unit-step slices")
        y0, y1, _ = ys.indices(self.shape[0])
        x0, x1, _ = xs.indices(self.shape[1])
        return self.window((y0, x0, y1 - y0, x1 - x0))[0]
