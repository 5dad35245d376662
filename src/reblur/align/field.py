"""Local residual displacement field after the global homography.

One homography maps a planar scene between two views.  Parallax (buildings, statues, street
scenes) and lens distortion that differs between the captures leave a residual that no
homography removes: edges that do not line up, hence false alarms.  As local
co-registration does for sharp imagery (AROSICS: a grid of tie points, a smooth
displacement field), this module measures the residual on a lattice of tie points and
fits a smooth field to it -- but measured between the REBLURRED reference and the
observation (:func:`reblur.align.refine.measure_shifts`), so the camera-shake blur, which moves
a correlation peak towards a mode of the blur, does not bias the tie points.

1. Tie points: probe windows on a regular lattice over the observation; each one's
   sub-pixel translation between the reblurred reference (estimated weights, refined base
   homography) and the observation (:func:`reblur.align.refine.tie_shift`: normalised
   cross-correlation, then ECC on a fixed support; invariant to gain and offset).  A probe
   on a change or an occlusion correlates poorly and is left out (``min_cc``); one whose
   correlation is flat over more than a pixel (along a blur streak) is not located.
2. Outliers: the normalised median test of particle-image velocimetry (Westerweel and
   Scarano 2005): a tie point whose vector differs from the median of its lattice
   neighbours by more than ``median_test`` times their own median deviation (plus
   ``noise_px``) is rejected.
3. A smooth field: a thin-plate spline with an affine part
   (:class:`scipy.interpolate.RBFInterpolator`), its smoothing chosen by k-fold
   cross-validation of the held-out tie points.  The field is kept only when its held-out
   error beats the zero field (the homography alone) clearly: planar scenes keep their
   homography, unchanged.
4. The field is stored on a coarse node grid and applied in the reblur
   (:func:`reblur.tiled.reblur_tile`): ``observed(p) ~ reblurred(p + d(p))``, so the
   reblurred tile is resampled at ``p + d(p)`` (bicubic).  The blur kernel varies slowly
   with position, so resampling after blurring equals blurring the displaced reference up
   to the kernel's change over ``|d|`` pixels.  The tie points are measured again through
   that path; a field that does not lower their residual is not applied.

References
----------
.. [1] J. Westerweel and F. Scarano, "Universal outlier detection for PIV data",
   Experiments in Fluids 39 (2005) 1096-1100. :doi:`10.1007/s00348-005-0016-6`
.. [2] D. Scheffler et al., "AROSICS: An automated and robust open-source image
   co-registration software for multi-sensor satellite data", Remote Sensing 9 (2017)
   676. :doi:`10.3390/rs9070676`
"""

from __future__ import annotations

import copy
import functools
import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.interpolate import RBFInterpolator
from scipy.spatial import cKDTree

from ..tiled import WholeReblur
from ..warp import Box, as_box

#: Largest geometric reach (pixels) the decision's tolerance takes from a field.
MAX_REACH = 4

__all__ = [
    "DisplacementField", "FieldEstimate", "FieldParams", "estimate_field", "fit_field",
    "lattice_boxes", "reject_outliers",
]


@dataclass(frozen=True)
class FieldParams:
    """Options of the local displacement field (:func:`estimate_field`; the pipeline,
    ``detect_changes(local_field=True)``, uses the defaults).

    Attributes
    ----------
    probe_px : int or None
        Side of a tie-point window; default a sixteenth of the short side, within
        [64, 128] px (the smooth field's transition across a roof's edge is about one
        window wide: ``benchmarks/alignment.py``'s parallax rows, 128 px windows at
        main@554729b against 64 px at f18626f).
    max_probes : int
        Most tie points per side of the lattice (the cost grows with its square).
    min_cc : float
        Smallest ECC correlation of a tie point (changes and occlusions lower it).
    min_cover : float
        Smallest fraction of a tie-point window the reference must cover (ECC ignores
        the rest): the corners of a re-viewpointed observation are where lens distortion
        is largest and the reference often covers only part of them.
    min_rms_px : float
        No field below this RMS tie-point residual: a blur kernel that is not exactly the
        true one moves an ECC optimum by about a tenth of a pixel where the geometry is
        right, and fitting that would move the geometry away from the truth (the planar
        pairs of ``benchmarks/realism.py`` keep their geometry residual, 0.04-0.06 px RMS,
        because no field is fitted there).
    median_test : float
        Threshold of the normalised median test.
    noise_px : float
        Measurement noise floor of a tie point, in pixels (the test's epsilon).
    min_points : int
        Fewest tie points passing both tests for a field to be fitted.
    min_gain_px : float
        The field is kept only when its cross-validated RMS error is at least this much
        below the zero field's ...
    max_ratio : float
        ... and at most this fraction of it.
    folds : int
        Folds of the cross-validation.
    smoothings : tuple of float
        Smoothing parameters of the thin-plate spline tried (coordinates scaled to the
        image's long side, displacements in pixels).
    """

    probe_px: int | None = None
    max_probes: int = 24
    min_cc: float = 0.9
    min_cover: float = 0.5
    min_rms_px: float = 0.15
    median_test: float = 2.0
    noise_px: float = 0.1
    min_points: int = 16
    min_gain_px: float = 0.05
    max_ratio: float = 0.8
    folds: int = 5
    smoothings: tuple[float, ...] = (1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1)

    def __post_init__(self) -> None:
        if self.probe_px is not None and not 16 <= self.probe_px <= 4096:
            raise ValueError(f"probe_px must be in [16, 4096] or None, got {self.probe_px}")
        if not 2 <= self.max_probes <= 64:
            raise ValueError(f"max_probes must be in [2, 64], got {self.max_probes}")
        for name in ("min_cc", "min_cover"):
            if not 0.0 < getattr(self, name) < 1.0:
                raise ValueError(f"{name} must be in (0, 1), got {getattr(self, name)}")
        for name in ("median_test", "noise_px", "min_gain_px", "min_rms_px"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v}")
        if not 0.0 < self.max_ratio <= 1.0:
            raise ValueError(f"max_ratio must be in (0, 1], got {self.max_ratio}")
        if self.min_points < 6:
            raise ValueError(f"min_points must be >= 6 (an affine part and some "
                             f"redundancy), got {self.min_points}")
        if not 2 <= self.folds <= 20:
            raise ValueError(f"folds must be in [2, 20], got {self.folds}")
        if not self.smoothings or not all(math.isfinite(s) and s >= 0 for s in self.smoothings):
            raise ValueError(f"smoothings must be non-negative numbers, got {self.smoothings}")


@dataclass(frozen=True)
class DisplacementField:
    """A smooth displacement field over the observation, on a regular node grid.

    ``observed(p) ~ reblurred(p + d(p))`` for an observation pixel ``p = (x, y)``.  Node
    ``(i, j)`` sits at ``(x0 + j * step, y0 + i * step)``; between nodes the field is
    bilinear (in double precision: OpenCV's remap would quantise positions to 1/32 of a
    node step), beyond the outer nodes it is held constant.

    Attributes
    ----------
    x0, y0, step : float
        Node grid origin and spacing, in observation pixels.
    d : (ny, nx, 2) ndarray of float32
        ``(dx, dy)`` at the nodes.
    """

    x0: float
    y0: float
    step: float
    d: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        d = np.asarray(self.d, np.float32)
        if d.ndim != 3 or d.shape[2] != 2 or min(d.shape[:2]) < 1:
            raise ValueError(f"d must be (ny, nx, 2), got {d.shape}")
        if not np.isfinite(d).all():
            raise ValueError("a displacement field must be finite")
        if not self.step > 0:
            raise ValueError(f"step must be positive, got {self.step}")
        object.__setattr__(self, "d", np.ascontiguousarray(d))

    def _weights(self, coord: np.ndarray, origin: float, n: int) -> np.ndarray:
        """``(m, n)`` linear-interpolation weights of positions ``coord`` on ``n`` nodes
        (held constant beyond the outer nodes)."""
        f = np.clip((np.asarray(coord, np.float64) - origin) / self.step, 0.0, n - 1.0)
        i0 = np.minimum(np.floor(f).astype(int), max(n - 2, 0))
        t = f - i0
        w = np.zeros((len(f), n))
        rows = np.arange(len(f))
        w[rows, i0] = 1.0 - t
        if n > 1:
            w[rows, i0 + 1] += t
        return w

    def displacement(self, xy: np.ndarray) -> np.ndarray:
        """``(m, 2)`` displacements ``d(p)`` at ``(m, 2)`` observation points ``(x, y)``."""
        pts = np.asarray(xy, np.float64).reshape(-1, 2)
        ny, nx = self.d.shape[:2]
        wx = self._weights(pts[:, 0], self.x0, nx)
        wy = self._weights(pts[:, 1], self.y0, ny)
        return np.einsum("mi,ijc,mj->mc", wy, self.d.astype(np.float64), wx)

    def maps(self, box) -> tuple[np.ndarray, np.ndarray]:
        """``(dx, dy)``, each ``(h, w)`` float32, at every pixel of an observation window
        (separable: a product of two small interpolation matrices per component)."""
        b = as_box(box)
        ny, nx = self.d.shape[:2]
        y0, y1, ty = self._taps(np.arange(b.y0, b.y1), self.y0, ny)
        x0, x1, tx = self._taps(np.arange(b.x0, b.x1), self.x0, nx)
        d = self.d.astype(np.float64)
        out = []
        for c in (0, 1):
            rows = d[y0, :, c] * (1.0 - ty)[:, None] + d[y1, :, c] * ty[:, None]
            out.append((rows[:, x0] * (1.0 - tx) + rows[:, x1] * tx).astype(np.float32))
        return out[0], out[1]

    def _taps(self, coord: np.ndarray, origin: float, n: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The two nodes and the weight of the second of :meth:`_weights`' rows (the
        interpolation as two taps: a product with the weight matrices would go through
        BLAS, whose threads cost more than the product on a tile)."""
        f = np.clip((np.asarray(coord, np.float64) - origin) / self.step, 0.0, n - 1.0)
        i0 = np.minimum(np.floor(f).astype(int), max(n - 2, 0))
        return i0, np.minimum(i0 + 1, n - 1), f - i0

    def bound(self, box) -> float:
        """Largest ``|dx|`` or ``|dy|`` the field takes on an observation window (the node
        values bound the bilinear field)."""
        b = as_box(box)
        ny, nx = self.d.shape[:2]
        j0 = int(np.clip(math.floor((b.x0 - self.x0) / self.step), 0, nx - 1))
        j1 = int(np.clip(math.ceil((b.x1 - 1 - self.x0) / self.step), 0, nx - 1))
        i0 = int(np.clip(math.floor((b.y0 - self.y0) / self.step), 0, ny - 1))
        i1 = int(np.clip(math.ceil((b.y1 - 1 - self.y0) / self.step), 0, ny - 1))
        return float(np.abs(self.d[i0:i1 + 1, j0:j1 + 1]).max())

    @functools.cached_property
    def _node_variation(self) -> np.ndarray:
        """At each node, the largest change of the field (vector norm) to any node within
        two steps (one tie-point spacing): how far a smooth fit may miss a sharp step.
        Computed once per field (every tile asks)."""
        d = self.d.astype(np.float64)
        ny, nx = d.shape[:2]
        p = np.pad(d, ((2, 2), (2, 2), (0, 0)), mode="edge")
        v = np.zeros((ny, nx))
        for dy in range(-2, 3):
            for dx in range(-2, 3):
                diff = p[2 + dy:2 + dy + ny, 2 + dx:2 + dx + nx] - d
                np.maximum(v, np.hypot(diff[..., 0], diff[..., 1]), out=v)
        return v

    def max_reach(self, cap: int = MAX_REACH) -> int:
        """Largest value :meth:`reach_map` takes anywhere (the decision's halo needs it)."""
        return int(min(cap, np.floor(self._node_variation.max() + 0.5)))

    def reach_map(self, box, cap: int = MAX_REACH) -> np.ndarray:
        """Per-pixel geometric uncertainty (whole pixels) of the field on a window.

        Where the field varies by ``v`` pixels within one tie-point spacing, a smooth fit
        can miss a sharp step (a roof's edge under parallax) by up to about ``v``; the
        decision widens its tolerance by ``round(v)`` pixels there, capped at ``cap``
        (:mod:`reblur.decide.tolerance`).  Each pixel takes the largest value of the
        nodes of its cell and their neighbours; 0 where the field is smooth.

        Returns
        -------
        (h, w) uint8 ndarray
        """
        b = as_box(box)
        ny, nx = self.d.shape[:2]
        r = np.minimum(np.floor(self._node_variation + 0.5), cap).astype(np.uint8)
        r = cv2.dilate(r, np.ones((3, 3), np.uint8))  # the nodes around a cell
        iy = np.clip(np.floor((np.arange(b.y0, b.y1) - self.y0) / self.step).astype(int),
                     0, ny - 1)
        ix = np.clip(np.floor((np.arange(b.x0, b.x1) - self.x0) / self.step).astype(int),
                     0, nx - 1)
        return r[np.ix_(iy, ix)]

    @property
    def magnitude(self) -> np.ndarray:
        """``|d|`` at the nodes, ``(ny, nx)`` float32."""
        return np.hypot(self.d[..., 0], self.d[..., 1])

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (the node grid itself is written as an image)."""
        mag = self.magnitude
        return {"nodes": list(self.d.shape[:2]), "step_px": float(self.step),
                "max_px": round(float(mag.max()), 4),
                "rms_px": round(float(np.sqrt(np.mean(mag * mag))), 4),
                "max_reach_px": self.max_reach()}

    def displaced(self, reblur: Any, box) -> tuple[np.ndarray, np.ndarray]:
        """A tile reblur with the field applied: ``reblur(window) -> (image, valid)`` on
        the window grown by the field's reach, resampled at ``p + d(p)``
        (:meth:`resample`)."""
        b = as_box(box)
        pad = self.pad(b)
        img, ok = reblur(b.grow(pad, pad, pad, pad))
        return self.resample(img, b, ok, pad)

    def pad(self, box) -> int:
        """Pixels by which :meth:`displaced` grows a window before resampling it: the
        field's reach there and the bicubic footprint."""
        return int(np.ceil(self.bound(box))) + 3

    def resample(self, image: np.ndarray, box, valid: np.ndarray, pad: int
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Resample a window reblurred on ``box`` grown by ``pad`` pixels at ``p + d(p)``.

        Parameters
        ----------
        image : (h + 2 pad, w + 2 pad, C) ndarray
            The reblurred window on ``box.grow(pad, pad, pad, pad)``.
        box : Box
            The output window (observation pixels).
        valid : (h + 2 pad, w + 2 pad) bool ndarray
            Its validity.
        pad : int
            At least ``ceil(bound(box)) + 3`` (bicubic interpolation: a bilinear one would
            low-pass the reblurred image by up to a two-tap mean, and the thin lines of the
            observation would then stand out as change).

        Returns
        -------
        out : (h, w, C) ndarray
        valid : (h, w) bool ndarray
            True where the whole bicubic footprint (4 x 4 pixels) is valid.
        """
        b = as_box(box)
        dx, dy = self.maps(b)
        gx = np.arange(b.w, dtype=np.float32)[None, :] + np.float32(pad)
        gy = np.arange(b.h, dtype=np.float32)[:, None] + np.float32(pad)
        mx, my = dx + gx, dy + gy
        C = image.shape[2]
        out = np.empty((b.h, b.w, C), image.dtype)
        for c0 in range(0, C, 4):  # OpenCV remaps at most 4 channels at once
            c1 = min(c0 + 4, C)
            got = cv2.remap(np.ascontiguousarray(image[:, :, c0:c1]), mx, my,
                            cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            out[:, :, c0:c1] = got.reshape(b.h, b.w, c1 - c0)
        # bicubic reads a 4 x 4 neighbourhood: valid where all of it is
        ok = cv2.erode(valid.astype(np.uint8), np.ones((3, 3), np.uint8),
                       borderType=cv2.BORDER_CONSTANT, borderValue=0)
        ok = cv2.remap(ok.astype(np.float32), mx, my, cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return out, ok >= 1.0 - 1e-3


def lattice_boxes(shape: tuple[int, int], params: FieldParams) -> list[Box]:
    """Tie-point windows: a regular lattice of non-overlapping windows over the image, at
    most ``params.max_probes`` per side (spread over the whole image when fewer fit)."""
    H, W = int(shape[0]), int(shape[1])
    s = params.probe_px or int(np.clip(min(H, W) // 16, 64, 128))
    s = int(min(s, H, W))
    ny, nx = (max(1, min(params.max_probes, n // s)) for n in (H, W))
    ys = np.linspace(0, H - s, ny).round().astype(int) if ny > 1 else [(H - s) // 2]
    xs = np.linspace(0, W - s, nx).round().astype(int) if nx > 1 else [(W - s) // 2]
    return [Box(int(y), int(x), s, s) for y in ys for x in xs]


def reject_outliers(centres: np.ndarray, shifts: np.ndarray, spacing: float,
                    params: FieldParams | None = None) -> np.ndarray:
    """Inliers of the normalised median test over lattice neighbours.

    Parameters
    ----------
    centres, shifts : (n, 2) ndarray
        Tie-point positions and displacements.
    spacing : float
        Lattice spacing: neighbours lie within 1.5 spacings (diagonals included).
    params : FieldParams, optional
        ``median_test`` and ``noise_px``.

    Returns
    -------
    (n,) bool ndarray
        A point with fewer than two neighbours cannot be checked and is rejected.
    """
    p = params or FieldParams()
    pts = np.asarray(centres, np.float64).reshape(-1, 2)
    vec = np.asarray(shifts, np.float64).reshape(-1, 2)
    keep = np.zeros(len(pts), bool)
    if len(pts) < 3:
        return keep
    tree = cKDTree(pts)
    for i, nb in enumerate(tree.query_ball_point(pts, r=1.5 * spacing * math.sqrt(2.0))):
        nb = [j for j in nb if j != i]
        if len(nb) < 2:
            continue
        v = vec[nb]
        med = np.median(v, axis=0)
        # residuals of the neighbours to their own median: the local spread
        rm = np.median(np.abs(v - med), axis=0)
        r = np.abs(vec[i] - med) / (rm + p.noise_px)
        keep[i] = bool(np.all(r <= p.median_test))
    return keep


def _cv_rms(pts: np.ndarray, vec: np.ndarray, smoothing: float, folds: np.ndarray) -> float:
    """Held-out RMS error of the thin-plate spline with this smoothing (k-fold)."""
    err = np.empty_like(vec)
    for k in np.unique(folds):
        test = folds == k
        f = RBFInterpolator(pts[~test], vec[~test], kernel="thin_plate_spline",
                            smoothing=smoothing, degree=1)
        err[test] = f(pts[test]) - vec[test]
    return float(np.sqrt(np.mean(np.sum(err * err, axis=1))))


def fit_field(
    centres: np.ndarray,
    shifts: np.ndarray,
    shape: tuple[int, int],
    spacing: float,
    params: FieldParams | None = None,
) -> tuple[DisplacementField | None, dict[str, Any]]:
    """Fit a smooth displacement field to tie points, or decide that none is needed.

    Parameters
    ----------
    centres : (n, 2) ndarray
        Tie-point positions ``(x, y)``, observation pixels (outliers already removed,
        :func:`reject_outliers`).
    shifts : (n, 2) ndarray
        Their displacements ``d`` with ``observed(p) ~ reblurred(p + d)``.
    shape : (int, int)
        Observation size.
    spacing : float
        Lattice spacing, pixels (the node grid's step is half of it, at least 16 px).
    params : FieldParams, optional

    Returns
    -------
    field : DisplacementField or None
        None when there are too few tie points or the field does not beat the zero field
        under cross-validation (the reason is in ``info["reason"]``).
    info : dict
        ``cv_rms_zero_px`` and ``cv_rms_px`` (held-out RMS error of the zero field and of
        the field), ``smoothing``, ``reason`` (empty when a field is returned).
    """
    p = params or FieldParams()
    pts = np.asarray(centres, np.float64).reshape(-1, 2)
    vec = np.asarray(shifts, np.float64).reshape(-1, 2)
    info: dict[str, Any] = {}
    if len(pts) < p.min_points:
        info["reason"] = f"{len(pts)} reliable tie points (< {p.min_points})"
        return None, info
    H, W = int(shape[0]), int(shape[1])
    scale = float(max(H, W))
    u = (pts - np.array([(W - 1) / 2.0, (H - 1) / 2.0])) / scale
    rng = np.random.default_rng(0)  # fold assignment only: deterministic
    folds = rng.permutation(len(u)) % p.folds
    zero = float(np.sqrt(np.mean(np.sum(vec * vec, axis=1))))
    scores = [(_cv_rms(u, vec, s, folds), s) for s in p.smoothings]
    best, s_best = min(scores)
    info.update(cv_rms_zero_px=round(zero, 4), cv_rms_px=round(best, 4), smoothing=s_best)
    if zero < p.min_rms_px:
        info["reason"] = (f"the homography leaves the tie points at {zero:.3f} px RMS "
                          f"(< {p.min_rms_px:g}): no field needed")
        return None, info
    if not (best <= zero - p.min_gain_px and best <= p.max_ratio * zero):
        info["reason"] = (f"the field predicts held-out tie points to {best:.3f} px RMS, "
                          f"the homography alone to {zero:.3f} px: no field needed")
        return None, info
    tps = RBFInterpolator(u, vec, kernel="thin_plate_spline", smoothing=s_best, degree=1)
    step = max(16.0, spacing / 2.0)
    ny, nx = int(math.ceil((H - 1) / step)) + 1, int(math.ceil((W - 1) / step)) + 1
    gy, gx = np.mgrid[0:ny, 0:nx].astype(np.float64) * step
    nodes = np.stack([gx.ravel(), gy.ravel()], axis=1)
    d = tps((nodes - np.array([(W - 1) / 2.0, (H - 1) / 2.0])) / scale)
    info["reason"] = ""
    return DisplacementField(0.0, 0.0, step, d.reshape(ny, nx, 2)), info


@dataclass
class FieldEstimate:
    """Result of :func:`estimate_field`: the field (None when none is applied) and a
    JSON-ready ``info`` (tie points, tests, cross-validation, residual before / after)."""

    field: DisplacementField | None
    info: dict[str, Any]


def _rms(shifts: list, idx: list[int]) -> float:
    d = np.array([[shifts[i].dx, shifts[i].dy] for i in idx], np.float64)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def _tie_points(shifts: list, spacing: float, p: FieldParams):
    """The tie points of ``shifts`` (on a lattice of ``spacing``) correlating at least
    ``min_cc``: their indices, centres and displacements, and which of them pass the
    median test (:func:`reject_outliers`)."""
    good = [i for i, s in enumerate(shifts) if s.measured and s.cc >= p.min_cc]
    centres = np.array([[shifts[i].cx, shifts[i].cy] for i in good]).reshape(-1, 2)
    vec = np.array([[shifts[i].dx, shifts[i].dy] for i in good]).reshape(-1, 2)
    return good, centres, vec, reject_outliers(centres, vec, spacing, p)


#: Fewest tie points in :func:`estimate_field`'s first pass (every other one of every
#: other row); a smaller lattice is measured whole.
_FIRST_PASS_MIN = 36

def _settled(shifts: list, spacing: float, p: FieldParams) -> dict[str, Any] | None:
    """Why no field is needed, judged from the first pass's tie points ``shifts`` (on a
    lattice of ``spacing``), or None when the whole lattice must be measured.

    Two outcomes are settled by a quarter of the lattice: none of its tie points
    correlates (``min_cc``: content changed or unrelated all over; the whole lattice then
    holds too few to fit a field), or the homography leaves at least ``min_points`` of
    its inliers (the median test) below half of ``min_rms_px`` RMS.  A residual a field
    would be fitted for spans several tie points (the median test rejects a lone one),
    so every other tie point sees it; half the threshold keeps a margin for the
    sampling.
    """
    good, _, _, keep = _tie_points(shifts, spacing, p)
    if not good:
        return {"measured": 0, "inliers": 0,
                "reason": f"none of {len(shifts)} tie points (every other one of every other "
                          f"row) correlates at {p.min_cc:g}: no field fitted"}
    n = int(keep.sum())
    if n < p.min_points:
        return None
    zero = _rms(shifts, [i for i, k in zip(good, keep, strict=True) if k])
    if zero >= 0.5 * p.min_rms_px:
        return None
    return {"measured": len(good), "inliers": n, "rms_before_px": round(zero, 4),
            "reason": f"the homography leaves {n} tie points (every other one of every other "
                      f"row) at {zero:.3f} px RMS (< half of {p.min_rms_px:g}): no field "
                      f"needed"}


def estimate_field(
    reference,
    observed,
    poses,
    *,
    params: FieldParams | None = None,
    ref_scale: float = 1.0,
    obs_scale: float = 1.0,
    whole: WholeReblur | None = None,
) -> FieldEstimate:
    """Measure tie points between the reblurred reference and the observation, fit a smooth
    field to them and verify it through the reblur.

    Parameters
    ----------
    reference, observed : array-like
        Reference and observation (numpy, zarr, ...), read window by window.
    poses : reblur.tiled.SparsePoses
        Estimated weights with the (refined) base homography, without a field.
    params : FieldParams, optional
    ref_scale, obs_scale : float
        Intensity scales of the reference and the observation.
    whole : reblur.tiled.WholeReblur, optional
        The image already reblurred with ``poses`` (the same object; the refinement's
        :attr:`~reblur.align.refine.Refinement.whole`): every tie point is cut from it.

    Returns
    -------
    FieldEstimate
        ``info`` holds ``probes`` (tie-point windows), ``measured`` (correlating at least
        ``min_cc``), ``inliers``, the cross-validation numbers of :func:`fit_field`,
        ``rms_before_px`` / ``rms_after_px`` (the inliers' residual without and with the
        field, measured through the reblur), ``applied`` and ``reason``; ``first_pass``
        (tie points measured) when a quarter of the lattice settled that no field is
        needed (:func:`_settled`), the rest unmeasured.  Otherwise every tie point is
        measured and the result is the same as measuring them in one pass.

    Notes
    -----
    Where the rows of tie points left after the first pass span most of the image (a 1 MP
    image's lattice covers it), the image is reblurred once for them and for the check
    with the field (:func:`reblur.align.refine._whole_reblur`), unless ``whole`` is given:
    each pass reblurred its rows, 2.5 times the image in all.  The 12 px test-bed shake
    (164 poses): the field 1.30 -> 1.05 s, its tie points, inliers and residuals the same
    to 4 decimals.
    """
    from .refine import _whole_reblur, measure_shifts

    p = params or FieldParams()
    shape = tuple(int(v) for v in poses.grid.image_shape[:2])
    boxes = lattice_boxes(shape, p)
    kw = dict(ref_scale=ref_scale, obs_scale=obs_scale, min_valid=p.min_cover, search=True)
    if whole is not None and whole.serves(poses, Box(0, 0, *shape)):
        kw["whole"] = whole
    xs = sorted({b.x0 for b in boxes})
    ys = sorted({b.y0 for b in boxes})
    steps = [b - a for v in (xs, ys) for a, b in zip(v, v[1:], strict=False)]
    spacing = float(min(steps) if steps else boxes[0].w)
    info: dict[str, Any] = {"probes": len(boxes), "probe_px": boxes[0].w, "applied": False}
    # every other tie point of every other row first: where the homography leaves them
    # well below the smallest residual a field is fitted for, the rest cannot change that
    first = [r * len(xs) + c for r in range(0, len(ys), 2) for c in range(0, len(xs), 2)]
    if len(first) < _FIRST_PASS_MIN:
        first = []
    before: list = [None] * len(boxes)
    if first:
        part = measure_shifts(reference, observed, poses, [boxes[i] for i in first], **kw)
        for i, s in zip(first, part, strict=True):
            before[i] = s
        settled = _settled(part, 2.0 * spacing, p)
        if settled is not None:
            info.update(settled, first_pass=len(first))
            return FieldEstimate(None, info)
    rest = [i for i, s in enumerate(before) if s is None]
    # the rest of the lattice and the check with the field: from one reblur of the image
    # where their rows cover most of it (each pass would reblur its rows again)
    if kw.get("whole") is None:
        kw["whole"] = _whole_reblur(reference, poses, shape, [boxes[i] for i in rest])
    for i, s in zip(rest, measure_shifts(reference, observed, poses, [boxes[i] for i in rest],
                                         **kw), strict=True):
        before[i] = s
    good, centres, vec, keep = _tie_points(before, spacing, p)
    info["measured"] = len(good)
    info["inliers"] = int(keep.sum())
    fld, fit_info = fit_field(centres[keep], vec[keep], shape, spacing, p)
    info.update(fit_info)
    inl = [i for i, k in zip(good, keep, strict=True) if k]
    if inl:
        info["rms_before_px"] = round(_rms(before, inl), 4)
    if fld is None:
        return FieldEstimate(None, info)
    moved = copy.copy(poses)
    moved.field = fld
    after = measure_shifts(reference, observed, moved, [boxes[i] for i in inl], **kw)
    both = [j for j, s in enumerate(after) if s.measured and s.cc >= p.min_cc]
    rb = _rms(before, [inl[j] for j in both]) if both else float("nan")
    ra = _rms(after, both) if both else float("nan")
    info.update(rms_before_px=round(rb, 4), rms_after_px=round(ra, 4), field=fld.to_dict())
    if not (len(both) >= p.min_points and ra <= rb - p.min_gain_px / 2):
        info["reason"] = (f"the field left the tie points at {ra:.3f} px RMS "
                          f"(without it {rb:.3f} px): not applied")
        return FieldEstimate(None, info)
    info["applied"] = True
    return FieldEstimate(fld, info)
