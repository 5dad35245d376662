"""Continuous 6-D camera paths and perspective viewpoint changes, from the pinhole model.

A camera looking at a distant, fronto-parallel planar scene moves during the exposure along a
smooth random path of translation (tx, ty, tz) and rotation (rx, ry, rz).  The path is
sampled at ``n_sub`` instants (the midpoints of equal slices of the exposure), and each
sub-pose gives the plane-induced homography ``H = K (R + t e3^T) K^-1`` that maps a
reference pixel to an observation pixel.  Unlike reblur's own simulator, nothing here is tied
to a pose grid: translations are continuous (sub-pixel, off any integer lattice),
out-of-plane rotations and depth are first-class, and the homographies are built directly
from the intrinsics, not from reblur's pose code.

Conventions
-----------
* A pixel is ``(x, y)`` = (column, row), pixel centres at integer coordinates, ``y`` down.
* ``K = [[f, 0, cx], [0, f, cy], [0, 0, 1]]`` with ``(cx, cy) = ((W - 1) / 2, (H - 1) / 2)``,
  the centre of the (observation) image, and ``f`` in pixels (default ``1.2 * max(H, W)``).
* A pose is ``(tx, ty, tz, rx, ry, rz)``: ``tx, ty`` in pixels (image-plane shift of the
  scene plane), ``tz`` the fractional increase of the scene depth (0.01 = 1 % farther, so
  the image shrinks by ``1 / 1.01``), ``rx, ry, rz`` in degrees about the camera's x, y and
  optical axis, ``R = Rz(rz) @ Ry(ry) @ Rx(rx)``.  With ``y`` down, positive ``rz`` turns
  the image clockwise on screen (``x -> y`` direction).
* All homographies map reference pixels to observation pixels (homogeneous column vectors).
  The observation of sub-pose ``k`` seen from a changed viewpoint is
  ``H_total_k = H_k @ H_view``: the reference is first mapped to the nominal observation
  frame by the viewpoint change, then the shake of sub-pose ``k`` moves the observation
  camera about ITS principal point (see :func:`compose`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "CameraPath",
    "compose",
    "default_focal",
    "defocus_path",
    "intrinsics",
    "pose_homography",
    "random_camera_path",
    "rotation_matrix",
    "shake_for",
    "translation",
    "view_from_parts",
    "viewpoint_homography",
    "viewpoint_parts",
]


def shake_for(shape: tuple[int, ...]) -> dict:
    """Keywords of :func:`random_camera_path` for the shake of a hand-held or airborne
    exposure scaled to the image: ~5 px of translation, a roll that moves the corners by
    ~8 px and a tilt that shifts the image by ~3 px (with the default focal length)."""
    side = float(max(_check_shape(shape)))
    return {"max_shift_px": 5.0, "max_roll_deg": float(np.degrees(8.0 / (0.7 * side))),
            "max_tilt_deg": float(np.degrees(3.0 / (1.2 * side)))}


def _check_n_sub(n_sub: int) -> None:
    if int(n_sub) < 64:
        raise ValueError(f"n_sub must be >= 64 for a continuous-looking blur, got {n_sub}")


def _check_shape(shape: tuple[int, ...]) -> tuple[int, int]:
    if len(shape) < 2 or int(shape[0]) < 2 or int(shape[1]) < 2:
        raise ValueError(f"shape must be (rows, cols[, ...]) with both >= 2, got {shape!r}")
    return int(shape[0]), int(shape[1])


def default_focal(shape: tuple[int, ...]) -> float:
    """Default focal length in pixels: ``1.2 * max(H, W)`` (a normal, ~45 degree lens).

    Parameters
    ----------
    shape : tuple of int
        Image shape ``(H, W[, C])``.

    Returns
    -------
    float
        Focal length in pixels.
    """
    h, w = _check_shape(shape)
    return 1.2 * max(h, w)


def intrinsics(shape: tuple[int, ...], focal: float | None = None) -> np.ndarray:
    """Camera matrix ``K`` with the principal point at the image centre.

    Parameters
    ----------
    shape : tuple of int
        Image shape ``(H, W[, C])``.
    focal : float, optional
        Focal length in pixels; default :func:`default_focal`.

    Returns
    -------
    numpy.ndarray
        ``3 x 3`` float64 matrix.
    """
    h, w = _check_shape(shape)
    f = default_focal(shape) if focal is None else float(focal)
    if not np.isfinite(f) or f <= 0:
        raise ValueError(f"focal must be a positive number of pixels, got {focal!r}")
    return np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])


def rotation_matrix(rx: float, ry: float, rz: float) -> np.ndarray:
    """Rotation ``Rz(rz) @ Ry(ry) @ Rx(rx)``, angles in degrees.

    Parameters
    ----------
    rx, ry, rz : float
        Rotations about the camera x axis (tilt), y axis (pan) and optical axis (roll).

    Returns
    -------
    numpy.ndarray
        ``3 x 3`` orthonormal float64 matrix.
    """
    a, b, c = np.deg2rad([rx, ry, rz])
    rot_x = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    rot_y = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rot_z = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return rot_z @ rot_y @ rot_x


def pose_homography(
    shape: tuple[int, ...], pose: np.ndarray | tuple[float, ...], focal: float | None = None
) -> np.ndarray:
    """Plane-induced homography ``K (R + t e3^T) K^-1`` of one 6-D pose.

    A scene point on the plane at depth ``d`` seen at reference pixel ``x`` is
    ``X = d K^-1 x``; after the motion it is at ``R X + T`` and images at
    ``K (R K^-1 x + T / d)``.  Writing ``t = T / d = (tx / f, ty / f, tz)`` gives the
    homography; ``tx, ty`` are then the image shifts in pixels.

    Parameters
    ----------
    shape : tuple of int
        Image shape ``(H, W[, C])``; fixes the principal point.
    pose : array_like
        ``(tx, ty, tz, rx, ry, rz)`` (pixels, pixels, fraction, degrees x 3).
    focal : float, optional
        Focal length in pixels; default :func:`default_focal`.

    Returns
    -------
    numpy.ndarray
        ``3 x 3`` float64 homography mapping reference to observation pixels, normalised so
        that ``H[2, 2] == 1``.
    """
    p = np.asarray(pose, dtype=np.float64)
    if p.shape != (6,) or not np.all(np.isfinite(p)):
        raise ValueError(f"pose must be 6 finite numbers (tx, ty, tz, rx, ry, rz), got {pose!r}")
    k = intrinsics(shape, focal)
    f = k[0, 0]
    t = np.array([p[0] / f, p[1] / f, p[2]])
    m = rotation_matrix(p[3], p[4], p[5]) + np.outer(t, [0.0, 0.0, 1.0])
    h = k @ m @ np.linalg.inv(k)
    return h / h[2, 2]


def compose(view: np.ndarray, homographies: np.ndarray) -> np.ndarray:
    """Total sub-pose mappings ``H_total_k = H_k @ H_view``.

    Parameters
    ----------
    view : numpy.ndarray
        ``3 x 3`` viewpoint homography (reference pixel -> nominal observation pixel).
    homographies : numpy.ndarray
        ``(n, 3, 3)`` shake homographies (nominal observation pixel -> observed pixel at
        sub-pose ``k``), built about the observation's principal point.

    Returns
    -------
    numpy.ndarray
        ``(n, 3, 3)`` reference -> observation mappings, each normalised to ``H[2, 2] == 1``.
    """
    v = np.asarray(view, dtype=np.float64)
    hs = np.asarray(homographies, dtype=np.float64)
    if v.shape != (3, 3) or hs.ndim != 3 or hs.shape[1:] != (3, 3):
        raise ValueError("view must be 3 x 3 and homographies (n, 3, 3)")
    total = hs @ v
    return total / total[:, 2:3, 2:3]


@dataclass(frozen=True)
class CameraPath:
    """A camera path sampled at equal time slices of the exposure.

    Attributes
    ----------
    poses : numpy.ndarray
        ``(n_sub, 6)`` sub-poses ``(tx, ty, tz, rx, ry, rz)``; every sub-pose carries the
        same exposure weight ``1 / n_sub``.
    shape : tuple of int
        Observation shape ``(H, W)`` (fixes the principal point).
    focal : float
        Focal length in pixels.
    """

    poses: np.ndarray
    shape: tuple[int, int]
    focal: float

    def homographies(self) -> np.ndarray:
        """Per-sub-pose homographies, ``(n_sub, 3, 3)``, reference -> observation."""
        return np.stack([pose_homography(self.shape, p, self.focal) for p in self.poses])


def _smooth_component(rng: np.random.Generator, t: np.ndarray, n_modes: int) -> np.ndarray:
    """A random smooth curve on ``t`` in [0, 1], scaled so that ``max |c| == 1``."""
    freqs = rng.uniform(0.15, 1.5, size=n_modes)
    phases = rng.uniform(0.0, 2.0 * np.pi, size=n_modes)
    amps = rng.uniform(0.3, 1.0, size=n_modes) / np.arange(1, n_modes + 1)
    c = (amps[:, None] * np.sin(2 * np.pi * freqs[:, None] * t[None] + phases[:, None])).sum(0)
    c = c - c.mean() + rng.uniform(-0.3, 0.3) * np.ptp(c)
    peak = np.max(np.abs(c))
    return c / peak if peak > 0 else c


def random_camera_path(
    shape: tuple[int, ...],
    rng: np.random.Generator,
    *,
    n_sub: int = 64,
    max_shift_px: float = 6.0,
    max_tilt_deg: float = 0.3,
    max_roll_deg: float = 0.5,
    max_depth: float = 0.0,
    n_modes: int = 3,
    focal: float | None = None,
) -> CameraPath:
    """Smooth random 6-D camera-shake path: a sum of a few low-frequency sinusoids per axis.

    Each axis is ``sum_j a_j sin(2 pi nu_j t + phi_j)`` on the exposure ``t`` in [0, 1] with
    ``nu_j`` in 0.15..1.5 cycles per exposure and a random offset, rescaled so that its peak
    magnitude is a random 50..100 % of the axis' maximum.  Values are continuous: nothing
    is snapped to a grid.

    Parameters
    ----------
    shape : tuple of int
        Observation shape ``(H, W[, C])``.
    rng : numpy.random.Generator
        Seeded generator.
    n_sub : int
        Number of sub-poses (equal exposure slices); at least 64 for a realistic blur.
    max_shift_px : float
        Largest ``|tx|``, ``|ty|`` in pixels.
    max_tilt_deg : float
        Largest ``|rx|``, ``|ry|`` in degrees.
    max_roll_deg : float
        Largest ``|rz|`` in degrees.
    max_depth : float
        Largest ``|tz|`` (fractional depth change); 0 disables depth motion.
    n_modes : int
        Number of sinusoids per axis.
    focal : float, optional
        Focal length in pixels; default :func:`default_focal`.

    Returns
    -------
    CameraPath
    """
    h, w = _check_shape(shape)
    _check_n_sub(n_sub)
    limits = np.array([max_shift_px, max_shift_px, max_depth, max_tilt_deg, max_tilt_deg,
                       max_roll_deg], dtype=np.float64)
    if np.any(limits < 0) or not np.all(np.isfinite(limits)):
        raise ValueError("motion limits must be finite and >= 0")
    if int(n_modes) < 1:
        raise ValueError(f"n_modes must be >= 1, got {n_modes}")
    t = (np.arange(int(n_sub)) + 0.5) / int(n_sub)
    poses = np.stack([
        lim * rng.uniform(0.5, 1.0) * _smooth_component(rng, t, int(n_modes)) for lim in limits
    ], axis=1)
    f = default_focal((h, w)) if focal is None else float(focal)
    return CameraPath(poses=poses, shape=(h, w), focal=f)


def defocus_path(shape: tuple[int, ...], radius_px: float, *, n_sub: int = 256,
                 focal: float | None = None) -> CameraPath:
    """A defocus blur as a :class:`CameraPath`: equal-weight sub-poses whose translations
    fill a disk of ``radius_px`` (a pillbox kernel), with no rotation or depth.

    The translations lie on a sunflower (Fibonacci) spiral, ``r_k = R sqrt((k + 1/2) /
    n)`` at the golden angle: equal areas of the disk per sub-pose, off any pixel lattice.
    An out-of-focus lens blurs a fronto-parallel plane with this kernel everywhere; a
    camera shake's sub-poses trace a path instead.

    Parameters
    ----------
    shape : tuple of int
        Observation shape ``(H, W[, C])``.
    radius_px : float
        Radius of the disk (pixels), > 0.
    n_sub : int
        Number of sub-poses, at least 64.
    focal : float, optional
        Focal length in pixels (the path's record: translations do not depend on it);
        default :func:`default_focal`.

    Returns
    -------
    CameraPath
    """
    h, w = _check_shape(shape)
    if not (np.isfinite(radius_px) and radius_px > 0):
        raise ValueError(f"radius_px must be a finite number > 0, got {radius_px!r}")
    _check_n_sub(n_sub)
    k = np.arange(int(n_sub)) + 0.5
    r = float(radius_px) * np.sqrt(k / int(n_sub))
    theta = k * np.pi * (3.0 - np.sqrt(5.0))  # the golden angle
    poses = np.zeros((int(n_sub), 6))
    poses[:, 0], poses[:, 1] = r * np.cos(theta), r * np.sin(theta)
    f = default_focal((h, w)) if focal is None else float(focal)
    return CameraPath(poses=poses, shape=(h, w), focal=f)


def translation(tx: float, ty: float) -> np.ndarray:
    """The image translation ``x -> x + (tx, ty)`` as a ``3 x 3`` homography."""
    return np.array([[1.0, 0.0, float(tx)], [0.0, 1.0, float(ty)], [0.0, 0.0, 1.0]])


def viewpoint_parts(
    shape: tuple[int, ...],
    rng: np.random.Generator,
    shift_px: float = 20.0,
    angle_deg: float = 1.0,
    perspective: float = 2.0,
    focal: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The two parts of :func:`viewpoint_homography`: the turn ``K R K^-1`` and the shift.

    The view is ``translation(*shift) @ turn``.  Physically, the camera turns by ``R`` and
    translates by ``T`` with ``T / d = (shift / f, 0)`` (in the observation camera), ``d``
    the distance of the scene plane, whose normal in the reference camera is ``R^T e3``:
    ``translation(*shift) @ K R K^-1 = K (R + (T / d) (R^T e3)^T) K^-1``, the
    plane-induced homography.  A plane parallel to it at distance ``d / s`` is therefore
    seen through ``translation(*(s * shift)) @ turn``
    (:func:`reblur.testbed.geometry.region_homographies`).  Parameters and random draws
    are those of :func:`viewpoint_homography`.

    Returns
    -------
    turn : numpy.ndarray
        ``3 x 3`` rotation homography about the camera centre, ``H[2, 2] == 1``.
    shift : numpy.ndarray
        ``(2,)`` image shift in pixels: the centre's own ``(tx, ty)`` plus the undoing of
        the shift the turn gives the centre.
    """
    h, w = _check_shape(shape)
    lims = np.array([shift_px, angle_deg, perspective], dtype=np.float64)
    if np.any(lims < 0) or not np.all(np.isfinite(lims)):
        raise ValueError("shift_px, angle_deg and perspective must be finite and >= 0")
    tx, ty = rng.uniform(-shift_px, shift_px, size=2)
    rx, ry = rng.uniform(-perspective, perspective, size=2)
    rz = rng.uniform(-angle_deg, angle_deg)
    turn = pose_homography(shape, (0.0, 0.0, 0.0, rx, ry, rz), focal)
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])
    moved = turn @ c
    return turn, c[:2] - moved[:2] / moved[2] + [tx, ty]


def viewpoint_homography(
    shape: tuple[int, ...],
    rng: np.random.Generator,
    shift_px: float = 20.0,
    angle_deg: float = 1.0,
    perspective: float = 2.0,
    focal: float | None = None,
) -> np.ndarray:
    """A random perspective viewpoint change, reference pixel -> nominal observation pixel.

    The camera turns by a random tilt/pan (``|rx|, |ry| <= perspective``) and roll
    (``|rz| <= angle_deg``) about its centre, ``K R K^-1``; the image shift this turn gives
    the image centre (``f tan(angle)``, hundreds of pixels on large images) is then replaced
    by a random shift ``|tx|, |ty| <= shift_px``.  So the image centre moves by exactly
    ``(tx, ty)``, while the corners move differently (rotation and keystone).  The parts
    are :func:`viewpoint_parts`.

    Parameters
    ----------
    shape : tuple of int
        Image shape ``(H, W[, C])``.
    rng : numpy.random.Generator
        Seeded generator.
    shift_px : float
        Largest image shift ``|tx|``, ``|ty|`` in pixels.
    angle_deg : float
        Largest in-plane rotation about the image centre, degrees.
    perspective : float
        Largest out-of-plane rotation ``|rx|``, ``|ry|`` in degrees (a true perspective
        change: the four corners move differently); 0 gives a similarity.
    focal : float, optional
        Focal length in pixels; default :func:`default_focal`.

    Returns
    -------
    numpy.ndarray
        ``3 x 3`` float64 homography.
    """
    turn, shift = viewpoint_parts(shape, rng, shift_px, angle_deg, perspective, focal)
    return view_from_parts(turn, shift)


def view_from_parts(turn: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """``translation(*shift) @ turn``, normalised to ``H[2, 2] == 1``."""
    view = translation(*shift) @ turn
    return view / view[2, 2]
