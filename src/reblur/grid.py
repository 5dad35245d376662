"""Camera-pose grids and their homographies.

Conventions (used everywhere in reblur)
---------------------------------------
* Pixel coordinates are ``(x, y)`` = (column, row) with pixel centres on integers.
* A homography ``H`` maps a *reference* pixel to the *observation* pixel it lands on:
  ``x_obs ~ H @ [x_ref, y_ref, 1]``.  Warping the reference by ``H`` gives the image
  ``warp(f, H)(x) = f(H^-1 x)`` (what ``cv2.warpPerspective(f, H, ...)`` computes).
* The pose ``p = (tx, ty, tz, rx, ry, rz)`` gives
  ``H(p) = T(tx, ty) @ T(c) @ diag(1 + tz, 1 + tz, 1) @ T(-c) @ K R K^-1`` where ``c`` is
  the principal point of the FULL image, ``K = [[f, 0, cx], [0, f, cy], [0, 0, 1]]``,
  ``R = Rz(rz) @ Ry(ry) @ Rx(rx)`` (angles in degrees).  For ``rx = ry = 0``, ``K R K^-1``
  is the in-plane rotation by ``rz`` about ``c`` and does not depend on ``f``.
  ``Rz(a) = [[cos a, -sin a, 0], [sin a, cos a, 0], [0, 0, 1]]`` in ``(x, y)`` coordinates
  (image rows grow downwards, so a positive ``rz`` turns the picture clockwise on screen).
* Translations are applied last, in the image plane, so every pose is a *base* pose
  ``(tz, rx, ry, rz)`` followed by an image translation: with integer translations, the
  column of ``F`` for pose ``(b, t)`` is the base-warped reference shifted by ``t``.
* Weights are stored as an array of shape ``grid.shape = (n_bases, len(ty), len(tx))``.
* A crop keeps full-image geometry: a window whose top-left pixel is ``(x0, y0)`` uses
  ``T(-x0, -y0) @ H @ T(x0', y0')`` (see :func:`local_homography`), never a re-centred grid.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from numbers import Integral

import numpy as np

__all__ = [
    "PoseGrid",
    "pose_homography",
    "translation",
    "local_homography",
    "map_points",
    "mean_source_points",
    "carry_weights",
    "edge_share",
    "widen_translations",
    "MAX_POSES",
    "MAX_BASES_6D",
    "GridParams",
    "grid_size_for",
]

#: Pose budget of :meth:`PoseGrid.from_ranges`: a grid of more poses is refused before any
#: of it is built (a weight vector of this many poses takes 256 MiB in float64, and the
#: estimate correlates every window with every pose).  The default grid of a 4-gigapixel
#: image (``t_max=12``, ``rz_max=3``, one-pixel rotation step) holds 2.9 million poses.
MAX_POSES = 2**25

_AXES = ("tx", "ty", "tz", "rx", "ry", "rz")

#: Base poses (``tz x rx x ry x rz``) a 6-D :class:`GridParams` grid may hold: the estimate
#: warps and transforms every window once per base (no coarse-to-fine on the 6-D axes),
#: about 0.3 MB of float32 per base for a 250 px window.
MAX_BASES_6D = 2048

#: Focal length of a 6-D grid when none is given: this many times the long side (a normal
#: lens, about 45 degrees across the long side; the test bed's camera).
DEFAULT_FOCAL_FACTOR = 1.2


def translation(tx: float, ty: float) -> np.ndarray:
    """Return the 3x3 homography of an image translation by ``(tx, ty)`` pixels."""
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])


def _rot(axis: str, deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=float)
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=float)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=float)


def pose_homography(
    tx: float = 0.0,
    ty: float = 0.0,
    tz: float = 0.0,
    rx: float = 0.0,
    ry: float = 0.0,
    rz: float = 0.0,
    *,
    center: tuple[float, float],
    focal: float | None = None,
) -> np.ndarray:
    """Homography (reference -> observation) of one camera pose, full-image coordinates.

    Parameters
    ----------
    tx, ty : float
        In-plane translation in pixels (applied last).
    tz : float
        Relative scale change (``0.01`` enlarges by 1 %) about the principal point.
    rx, ry, rz : float
        Rotations in degrees; ``rz`` is the in-plane roll about the principal point.
    center : (float, float)
        Principal point ``(cx, cy)`` of the FULL image, in pixels.
    focal : float, optional
        Focal length in pixels; required when ``rx`` or ``ry`` is non-zero.

    Returns
    -------
    H : (3, 3) ndarray
        Normalised so that ``H[2, 2] == 1``.
    """
    cx, cy = center
    if (rx or ry) and not focal:
        raise ValueError("focal length (pixels) is required for out-of-plane rotations rx, ry")
    f = float(focal) if focal else 1.0
    K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    Kinv = np.array([[1.0 / f, 0.0, -cx / f], [0.0, 1.0 / f, -cy / f], [0.0, 0.0, 1.0]])
    R = _rot("z", rz) @ _rot("y", ry) @ _rot("x", rx)
    s = 1.0 + tz
    S = translation(cx, cy) @ np.diag([s, s, 1.0]) @ translation(-cx, -cy)
    H = translation(tx, ty) @ S @ K @ R @ Kinv
    return H / H[2, 2]


def local_homography(
    H: np.ndarray, src_offset: tuple[int, int], dst_offset: tuple[int, int]
) -> np.ndarray:
    """Express a full-image homography in window-local coordinates.

    Parameters
    ----------
    H : (3, 3) ndarray
        Reference -> observation homography in full-image pixel coordinates.
    src_offset : (int, int)
        ``(x0, y0)`` of the reference window's top-left pixel.
    dst_offset : (int, int)
        ``(x0, y0)`` of the output window's top-left pixel.

    Returns
    -------
    (3, 3) ndarray
        ``T(-dst) @ H @ T(src)``: maps window-local source pixels to window-local output
        pixels.  Building warps this way keeps coordinates small, which matters for
        OpenCV's single-precision warps on images tens of thousands of pixels wide.
    """
    M = translation(-dst_offset[0], -dst_offset[1]) @ H @ translation(*src_offset)
    return M / M[2, 2]


def map_points(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a homography to an ``(n, 2)`` array of ``(x, y)`` points."""
    pts = np.asarray(pts, dtype=float)
    q = pts @ H[:, :2].T + H[:, 2]
    return q[:, :2] / q[:, 2:3]


def mean_source_points(homographies, weights, pts: np.ndarray) -> np.ndarray:
    """Weighted mean over poses of where observation points come from in the reference.

    ``sum_p w_p H_p^-1 pts / sum_p w_p`` for reference -> observation homographies
    ``H_p``: the centroid of the blur kernel at each point (a gain the weights carry does
    not move it).

    Raises
    ------
    ValueError
        When no weight is positive.
    """
    pts = np.asarray(pts, dtype=float).reshape(-1, 2)
    acc = np.zeros_like(pts)
    total = 0.0
    for H, w in zip(homographies, weights, strict=True):
        acc += w * map_points(np.linalg.inv(H), pts)
        total += w
    if total <= 0:
        raise ValueError("the motion has no pose with weight")
    return acc / total


def _as_values(name: str, v) -> tuple[float, ...]:
    arr = np.atleast_1d(np.asarray(v, dtype=float)).ravel()
    if arr.size == 0:
        raise ValueError(f"PoseGrid.{name} must hold at least one value")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"PoseGrid.{name} must be finite")
    if np.unique(arr).size != arr.size:
        raise ValueError(f"PoseGrid.{name} has repeated values")
    return tuple(float(x) for x in np.sort(arr))


def arange_inclusive(lo: float, hi: float, step: float) -> np.ndarray:
    """``[lo:step:hi]`` as MATLAB writes it, robust to floating-point steps."""
    if step <= 0:
        raise ValueError("step must be positive")
    n = int(np.floor((hi - lo) / step + 1e-9)) + 1
    return lo + step * np.arange(max(n, 1))


@dataclass(frozen=True)
class PoseGrid:
    """A discrete set of camera poses: base poses x in-plane translations.

    The grid is the Cartesian product of ``tz x rx x ry x rz`` (the *bases*, in that order,
    ``rz`` fastest) with ``ty x tx``.  Weights on the grid have shape ``self.shape``.

    Parameters
    ----------
    image_shape : (int, int)
        ``(height, width)`` of the FULL observation image: sets the default principal
        point, the centre of every rotation.
    tx, ty : sequence of float
        Translations in pixels.  Integer values enable the fast FFT engine.
    rz : sequence of float
        In-plane rotations, degrees.
    tz, rx, ry : sequence of float
        Scale changes and out-of-plane rotations (degrees); default ``(0,)``.
    focal : float, optional
        Focal length in pixels (needed when ``rx``/``ry`` hold non-zero values).
    center : (float, float), optional
        Principal point ``(cx, cy)``; default the full image centre
        ``((width - 1) / 2, (height - 1) / 2)``.

    Examples
    --------
    >>> g = PoseGrid.paper((1000, 1000))
    >>> g.size, g.shape
    (8125, (13, 25, 25))
    """

    image_shape: tuple[int, int]
    tx: tuple[float, ...]
    ty: tuple[float, ...]
    rz: tuple[float, ...] = (0.0,)
    tz: tuple[float, ...] = (0.0,)
    rx: tuple[float, ...] = (0.0,)
    ry: tuple[float, ...] = (0.0,)
    focal: float | None = None
    center: tuple[float, float] | None = None
    _bases: tuple = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        shape = tuple(int(s) for s in self.image_shape)
        if len(shape) != 2 or min(shape) < 1:
            raise ValueError(f"image_shape must be (height, width) > 0, got {self.image_shape}")
        object.__setattr__(self, "image_shape", shape)
        for name in _AXES:
            object.__setattr__(self, name, _as_values(name, getattr(self, name)))
        if self.center is None:
            object.__setattr__(self, "center", ((shape[1] - 1) / 2.0, (shape[0] - 1) / 2.0))
        else:
            object.__setattr__(self, "center", (float(self.center[0]), float(self.center[1])))
        if any(v != 0 for v in self.rx + self.ry):
            if self.focal is None or not self.focal > 0:
                raise ValueError("PoseGrid needs a positive focal length (pixels) when rx/ry vary")
        bases = tuple(itertools.product(self.tz, self.rx, self.ry, self.rz))
        object.__setattr__(self, "_bases", bases)

    # ------------------------------------------------------------------ builders
    @classmethod
    def paper(
        cls, image_shape: tuple[int, int], *, center: tuple[float, float] | None = None
    ) -> PoseGrid:
        """The paper's grid: tx, ty in [-12:1:12] px, rz in [-3:0.5:3] degrees (8125 poses)."""
        t = np.arange(-12, 13)
        return cls(image_shape, tx=t, ty=t, rz=arange_inclusive(-3, 3, 0.5), center=center)

    @classmethod
    def from_ranges(
        cls,
        image_shape: tuple[int, int],
        *,
        t_max: int = 12,
        rz_max: float = 3.0,
        rz_step: float | None = 0.5,
        corner_px: float | None = None,
        center: tuple[float, float] | None = None,
    ) -> PoseGrid:
        """Symmetric grid: integer ``|tx|, |ty| <= t_max`` and ``|rz| <= rz_max`` degrees.

        ``corner_px`` (if given) overrides ``rz_step`` so that one rotation step moves the
        pixel farthest from the principal point by at most ``corner_px`` pixels.
        """
        shape = tuple(int(s) for s in image_shape)
        n_t, n_rz, rz_step = _range_counts(shape, t_max, rz_max, rz_step, corner_px, center)
        t = np.arange(-int(t_max), int(t_max) + 1)
        n = (n_rz - 1) // 2
        rz = rz_step * np.arange(-n, n + 1) if n else np.array([0.0])
        return cls(shape, tx=t, ty=t, rz=rz, center=center)

    def with_translations(self, tx, ty) -> PoseGrid:
        """Copy of this grid with other translation values."""
        return self._replace(tx=tx, ty=ty)

    def with_bases(self, rz, tz=None, rx=None, ry=None) -> PoseGrid:
        """Copy of this grid with other base-pose values."""
        return self._replace(
            rz=rz, tz=self.tz if tz is None else tz, rx=self.rx if rx is None else rx,
            ry=self.ry if ry is None else ry,
        )

    def _replace(self, **kw) -> PoseGrid:
        args = {n: getattr(self, n) for n in _AXES}
        args.update(kw)
        return PoseGrid(self.image_shape, focal=self.focal, center=self.center, **args)

    # ------------------------------------------------------------------ properties
    @property
    def bases(self) -> tuple[tuple[float, float, float, float], ...]:
        """Base poses ``(tz, rx, ry, rz)`` in weight order."""
        return self._bases

    @property
    def n_bases(self) -> int:
        return len(self._bases)

    @property
    def shape(self) -> tuple[int, int, int]:
        """Shape of a weight array: ``(n_bases, len(ty), len(tx))``."""
        return (len(self._bases), len(self.ty), len(self.tx))

    @property
    def size(self) -> int:
        """Number of poses."""
        return int(np.prod(self.shape))

    @property
    def integer_translations(self) -> bool:
        """True when every translation is a whole number of pixels (fast engine applies)."""
        return all(float(v).is_integer() for v in self.tx + self.ty)

    @property
    def ndim_active(self) -> int:
        """How many of the six pose axes take more than one value."""
        return sum(len(getattr(self, n)) > 1 for n in _AXES)

    @property
    def radius(self) -> float:
        """Distance from the principal point to the farthest image corner, in pixels."""
        h, w = self.image_shape
        cx, cy = self.center
        return float(max(np.hypot(x - cx, y - cy) for x in (0, w - 1) for y in (0, h - 1)))

    def poses(self) -> np.ndarray:
        """All poses as an ``(size, 6)`` array of ``(tx, ty, tz, rx, ry, rz)`` in weight order."""
        out = np.empty((self.size, 6))
        k = 0
        for tz, rx, ry, rz in self._bases:
            for ty in self.ty:
                for tx in self.tx:
                    out[k] = (tx, ty, tz, rx, ry, rz)
                    k += 1
        return out

    def base_homography(self, b: int) -> np.ndarray:
        """Homography of base pose ``b`` (no translation), full-image coordinates."""
        tz, rx, ry, rz = self._bases[b]
        return pose_homography(0.0, 0.0, tz, rx, ry, rz, center=self.center, focal=self.focal)

    def homography(self, index) -> np.ndarray:
        """Homography of one pose, given by flat index or ``(b, iy, ix)``."""
        b, iy, ix = np.unravel_index(index, self.shape) if np.isscalar(index) else index
        return translation(self.tx[ix], self.ty[iy]) @ self.base_homography(int(b))

    def nonzero(self, weights: np.ndarray, rtol: float = 0.0) -> list[tuple[int, int, int, float]]:
        """Poses carrying weight: list of ``(b, iy, ix, w)`` with ``w > rtol * max(w)``."""
        w = self.check_weights(weights)
        thr = rtol * float(w.max()) if w.size and w.max() > 0 else 0.0
        idx = np.argwhere(w > thr)
        return [(int(b), int(i), int(j), float(w[b, i, j])) for b, i, j in idx]

    def check_weights(self, weights: np.ndarray) -> np.ndarray:
        """Return ``weights`` reshaped to ``self.shape``; raise ValueError if it does not fit."""
        w = np.asarray(weights, dtype=float)
        if w.size != self.size:
            raise ValueError(f"weights have {w.size} values, the grid has {self.size} poses")
        w = w.reshape(self.shape)
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise ValueError("pose weights must be finite and non-negative")
        return w

    def to_dict(self) -> dict:
        """JSON-ready description of the grid."""
        d = {n: list(getattr(self, n)) for n in _AXES}
        d.update(image_shape=list(self.image_shape), center=list(self.center), focal=self.focal)
        return d

    def __repr__(self) -> str:
        def rng(v: Sequence[float]) -> str:
            if len(v) == 1:
                return f"{v[0]:g}"
            step = (v[-1] - v[0]) / (len(v) - 1)
            return f"[{v[0]:g}:{step:g}:{v[-1]:g}]"

        parts = [f"{n}={rng(getattr(self, n))}" for n in _AXES if getattr(self, n) != (0.0,)]
        return (
            f"PoseGrid({self.size} poses, image {self.image_shape[0]}x{self.image_shape[1]}, "
            f"center=({self.center[0]:g}, {self.center[1]:g}), " + ", ".join(parts) + ")"
        )


def carry_weights(weights: np.ndarray, src: PoseGrid, dst: PoseGrid) -> np.ndarray:
    """Weights on ``src`` carried over to ``dst``: each pose of ``dst`` takes the weight of
    the same pose of ``src`` (the same base and translation values), 0 where ``src`` has
    no such pose; weight on poses of ``src`` that ``dst`` lacks is dropped.  Either grid
    may be a part of the other (a coarse-to-fine level, a support grid).

    Examples
    --------
    >>> full = PoseGrid((100, 100), tx=[-1, 0, 1], ty=[0], rz=[-0.5, 0.0, 0.5])
    >>> part = PoseGrid((100, 100), tx=[0, 1], ty=[0], rz=[0.0])
    >>> w = np.arange(9.0).reshape(full.shape)
    >>> carry_weights(w, full, part)
    array([[[4., 5.]]])
    >>> carry_weights(carry_weights(w, full, part), part, full)[:, 0]
    array([[0., 0., 0.],
           [0., 4., 5.],
           [0., 0., 0.]])
    """
    w = src.check_weights(weights)
    out = np.zeros(dst.shape)

    def pairs(a: Sequence, b: Sequence) -> tuple[list[int], list[int]]:
        at = {v: i for i, v in enumerate(a)}
        got = [(j, at[v]) for j, v in enumerate(b) if v in at]
        return [j for j, _ in got], [i for _, i in got]

    db, sb = pairs(src.bases, dst.bases)
    dy, sy = pairs(src.ty, dst.ty)
    dx, sx = pairs(src.tx, dst.tx)
    if db and dy and dx:
        out[np.ix_(db, dy, dx)] = w[np.ix_(sb, sy, sx)]
    return out


def _edge(values: Sequence[float]) -> np.ndarray:
    """The outermost values of one translation axis (none for a single value)."""
    v = np.asarray(values, float)
    if v.size < 2:
        return np.zeros(v.size, bool)
    return (v == v.min()) | (v == v.max())


def edge_share(weights: np.ndarray, grid: PoseGrid) -> float:
    """Share of the weight on the grid's outermost translations.

    The poses whose ``tx`` is the grid's least or largest, or whose ``ty`` is (axes of one
    value have no edge).  A blur that reaches beyond the translations piles its outer part
    there: the l1 fit puts each pose it lacks on the nearest one it has.  0 when the
    weights are all zero.

    Examples
    --------
    >>> g = PoseGrid((100, 100), tx=[-1, 0, 1], ty=[-1, 0, 1])
    >>> w = np.zeros(g.shape); w[0, 1, 1] = 0.75; w[0, 1, 2] = 0.25
    >>> edge_share(w, g)
    0.25
    """
    w = grid.check_weights(weights)
    total = float(w.sum())
    if not total > 0:
        return 0.0
    ring = _edge(grid.ty)[:, None] | _edge(grid.tx)[None, :]
    return float(w[:, ring].sum()) / total


def widen_translations(grid: PoseGrid, factor: int = 2) -> PoseGrid | None:
    """``grid`` with its translation ranges ``factor`` times as wide, the same step.

    Each translation axis that is a symmetric run of equal steps about 0 (``tx = step *
    [-n..n]``, as :meth:`PoseGrid.from_ranges` builds it) becomes ``step * [-factor n ..
    factor n]``; other axes stay as they are.  None when no axis can widen.

    Examples
    --------
    >>> g = PoseGrid((100, 100), tx=[-2, -1, 0, 1, 2], ty=[0])
    >>> widen_translations(g).tx
    (-4.0, -3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0, 4.0)
    """
    if isinstance(factor, bool) or not isinstance(factor, Integral) or factor < 2:
        raise ValueError(f"factor must be an integer >= 2, got {factor!r}")

    def wider(values: Sequence[float]) -> tuple[float, ...] | None:
        v = np.asarray(values, float)
        n = v.size // 2
        if v.size < 3 or v.size % 2 == 0:
            return None
        step = float(v[n + 1] - v[n])
        ideal = step * np.arange(-n, n + 1)
        if not (step > 0 and v[n] == 0 and np.allclose(v, ideal, rtol=0, atol=1e-9 * step)):
            return None
        return tuple(float(x) for x in step * np.arange(-factor * n, factor * n + 1))

    tx, ty = wider(grid.tx), wider(grid.ty)
    if tx is None and ty is None:
        return None
    return grid._replace(tx=grid.tx if tx is None else tx, ty=grid.ty if ty is None else ty)


def _symmetric(v_max: float, step: float) -> np.ndarray:
    """``step * [-n..n]`` with ``n`` the nearest whole number of steps to ``v_max``, at
    least one (``[0]`` for ``v_max = 0``): each value multiplies the bases."""
    n = max(1, round(v_max / step)) if v_max > 0 else 0
    return step * np.arange(-n, n + 1) if n else np.array([0.0])


@dataclass(frozen=True)
class GridParams:
    """Ranges of the pose grid :func:`reblur.detect_changes` builds on the observation.

    ``kind="3d"``: integer ``|tx|, |ty| <= t_max`` and ``|rz| <= rz_max`` degrees (the
    paper's axes).  ``kind="6d"``: also the scale change ``tz`` (relative) and the tilt
    and pan ``rx``, ``ry`` (degrees) of a camera of focal length ``focal`` pixels, each
    over the whole number of steps nearest to ``tz_max`` / ``tilt_max`` either side (one
    at least).  A step left None moves no pixel by more than about one pixel (``R`` the
    distance from the principal point to the farthest pixel): ``rz`` by ``1 / R`` rad,
    ``tz`` by ``1 / R``, and ``rx``/``ry`` by ``f / R^2`` rad -- a tilt by ``a`` shifts
    the image centre by ``f tan a``, which the translations take, and a pixel ``(x, y)``
    from the centre by about ``a |y| r / f`` beyond it (``|x|`` for a pan, ``r`` its
    distance from the centre), at most ``a R^2 / f``.

    Attributes
    ----------
    kind : {"3d", "6d"}
    t_max : int
        Largest translation (pixels).
    rz_max : float, optional
        Largest roll (degrees); default 3 for "3d", 1 for "6d" (after the coarse alignment
        the roll of a blur is small, and every roll value multiplies the 6-D bases).
    rz_step, tz_step, tilt_step : float, optional
        Steps (degrees, relative scale, degrees); default: one pixel at the farthest pixel.
    tz_max : float
        Largest relative scale change ("6d").
    tilt_max : float
        Largest tilt / pan (degrees, "6d").
    focal : float, optional
        Focal length in pixels ("6d"); default :data:`DEFAULT_FOCAL_FACTOR` x the long side.
    """

    kind: str = "3d"
    t_max: int = 12
    rz_max: float | None = None
    rz_step: float | None = None
    tz_max: float = 0.002
    tz_step: float | None = None
    tilt_max: float = 0.15
    tilt_step: float | None = None
    focal: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("3d", "6d"):
            raise ValueError(f"grid kind must be '3d' or '6d', got {self.kind!r}")
        for name in ("rz_max", "tz_max", "tilt_max"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(float(v)) and float(v) >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
        for name in ("rz_step", "tz_step", "tilt_step", "focal"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(float(v)) and float(v) > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
        if self.kind == "3d":
            moved = [n for n in ("tz_step", "tilt_step", "focal") if getattr(self, n) is not None]
            if moved:
                raise ValueError(f"{', '.join(moved)} apply to the 6-D grid: use kind='6d'")

    @property
    def roll_max(self) -> float:
        """``rz_max``, or its default for the kind."""
        return float(self.rz_max) if self.rz_max is not None else (
            3.0 if self.kind == "3d" else 1.0)

    def focal_for(self, image_shape: tuple[int, int]) -> float:
        """The focal length (pixels) of the 6-D grid on an image of this shape."""
        if self.focal is not None:
            return float(self.focal)
        return DEFAULT_FOCAL_FACTOR * float(max(image_shape[:2]))

    def build(self, image_shape: tuple[int, int]) -> PoseGrid:
        """The grid on an observation of ``image_shape`` (``(height, width)``).

        Raises
        ------
        ValueError
            A range the budget refuses (:data:`MAX_POSES`; for "6d" also
            :data:`MAX_BASES_6D` base poses), with the counts and what to narrow.
        """
        shape = tuple(int(s) for s in image_shape[:2])
        step = dict(rz_step=self.rz_step) if self.rz_step is not None else dict(corner_px=1.0)
        n_t, n_rz, _ = _range_counts(shape, self.t_max, self.roll_max,
                                     self.rz_step if self.rz_step is not None else 0.5,
                                     step.get("corner_px"), None)
        if self.kind == "3d":
            return PoseGrid.from_ranges(shape, t_max=self.t_max, rz_max=self.roll_max, **step)
        f = self.focal_for(shape)
        R = PoseGrid(shape, tx=[0], ty=[0]).radius
        tz = _symmetric(float(self.tz_max), self.tz_step or 1.0 / max(R, 1.0))
        tilt = _symmetric(float(self.tilt_max),
                          self.tilt_step or float(np.rad2deg(f / max(R, 1.0) ** 2)))
        n_bases = n_rz * len(tz) * len(tilt) ** 2
        if n_bases > MAX_BASES_6D or n_bases * n_t * n_t > MAX_POSES:
            raise ValueError(
                f"the 6-D grid would hold {n_bases:,} base poses ({n_rz} rz x {len(tz)} tz x "
                f"{len(tilt)} rx x {len(tilt)} ry) and {n_bases * n_t * n_t:,} poses, more "
                f"than the budget of {MAX_BASES_6D:,} bases / {MAX_POSES:,} poses: narrow "
                "rz_max, tz_max or tilt_max, or coarsen their steps")
        rz = PoseGrid.from_ranges(shape, t_max=0, rz_max=self.roll_max, **step).rz
        t = np.arange(-int(self.t_max), int(self.t_max) + 1)
        return PoseGrid(shape, tx=t, ty=t, rz=rz, tz=tz, rx=tilt, ry=tilt, focal=f)


def _range_counts(
    image_shape: tuple[int, int],
    t_max: int,
    rz_max: float,
    rz_step: float | None,
    corner_px: float | None,
    center: tuple[float, float] | None,
) -> tuple[int, int, float]:
    """``(translations per axis, rotations, rotation step)`` of a :meth:`PoseGrid.from_ranges`
    grid, checked (finite, in range, within :data:`MAX_POSES`) before anything is built."""
    for name, v in (("t_max", t_max), ("rz_max", rz_max), ("rz_step", rz_step),
                    ("corner_px", corner_px)):
        if v is None:
            continue
        try:
            v = float(v)
        except (TypeError, ValueError):
            raise ValueError(f"{name} must be a number, got {v!r}") from None
        if not math.isfinite(v) or v < 0:
            raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
    if int(t_max) != t_max:
        raise ValueError(f"t_max must be a whole number of pixels, got {t_max!r}")
    if corner_px is not None:
        if not corner_px > 0:
            raise ValueError(f"corner_px must be positive, got {corner_px!r}")
        rz_step = rotation_step_for(image_shape, corner_px, center)
    n_t = 2 * int(t_max) + 1
    if rz_max > 0:
        if rz_step is None or not rz_step > 0:
            raise ValueError(f"rz_step must be positive when rz_max > 0, got {rz_step!r}")
        n_half = math.ceil(rz_max / rz_step - 1e-9)  # a Python int: no overflow
    else:
        n_half = 0
    n_rz = 2 * n_half + 1
    total = n_t * n_t * n_rz
    if total > MAX_POSES:
        raise ValueError(
            f"the pose grid would hold {total:,} poses ({n_t}x{n_t} translations x {n_rz:,} "
            f"rotations), more than the budget of {MAX_POSES:,} poses; choose a coarser "
            "rz_step or a smaller rz_max or t_max"
        )
    return n_t, n_rz, float(rz_step) if n_half else 0.0


def grid_size_for(
    image_shape: tuple[int, int],
    *,
    t_max: int = 12,
    rz_max: float = 3.0,
    rz_step: float | None = 0.5,
    corner_px: float | None = None,
    center: tuple[float, float] | None = None,
) -> int:
    """Number of poses :meth:`PoseGrid.from_ranges` would build with these arguments,
    computed without building it.

    Raises
    ------
    ValueError
        A range that is not finite or negative, or a grid over :data:`MAX_POSES` poses.

    Examples
    --------
    >>> grid_size_for((1000, 1000), t_max=12, rz_max=3, rz_step=0.5)
    8125
    """
    n_t, n_rz, _ = _range_counts(tuple(int(s) for s in image_shape), t_max, rz_max, rz_step,
                                 corner_px, center)
    return n_t * n_t * n_rz


def rotation_step_for(
    image_shape: tuple[int, int], corner_px: float = 1.0, center: tuple[float, float] | None = None
) -> float:
    """Rotation step (degrees) that moves the farthest image pixel by ``corner_px`` pixels."""
    h, w = image_shape
    cx, cy = center if center is not None else ((w - 1) / 2.0, (h - 1) / 2.0)
    r = max(np.hypot(x - cx, y - cy) for x in (0, w - 1) for y in (0, h - 1))
    return float(np.rad2deg(corner_px / max(r, 1.0)))
