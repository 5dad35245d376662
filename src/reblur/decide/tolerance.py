"""The model's tolerance: how far the reblurred reference may miss the observation without
that being change (used by stage 2, :mod:`.statistic`).

Reblur is exact only up to what its model cannot represent: a residual misregistration of
a fraction of a pixel (the alignment's and refinement's error, interpolation phase), and a
blur shape that differs slightly from the camera's continuous motion (a discrete pose
grid, 3-D poses for a 6-D shake, a different interpolator).  Both leave residuals that
grow with the local structure of the scene, on every edge, and neither is noise: a
statistic in units of the noise floods the edges of clean, 16-bit or upsampled imagery
(docs/NOTES.md, realism section).

So the observation is compared not with one value of the matched reblurred reference
``m`` but with the interval of values ``m`` could take under the model's error:

* **shift**: the values of the bilinear interpolant of ``m`` over every shift within
  ``+-shift`` pixels in x and y.  The interpolant is bilinear on each quarter cell, so its
  extremes over the square lie on the nine sample points ``(x + i shift, y + j shift)``,
  ``i, j in {-1, 0, 1}``: the interval is exact, not sampled.  With ``shift = 1`` it is
  the minimum and maximum of the 3 x 3 neighbourhood.
* **contrast**: the interval widened on both sides by ``contrast`` times the local range
  of ``m`` (max - min over a disc of ``radius`` pixels).  A blur kernel that differs
  from the true one by a total-variation distance ``d`` changes a value by at most ``d``
  times the range of the scene under the kernel; ``contrast`` is that ``d``, the
  relative accuracy of the blur model.

* **geometry** (optional, per pixel): where the local displacement field of the alignment
  (:mod:`reblur.align.field`) varies by ``r`` pixels within a tie-point spacing, its smooth
  fit may miss a sharp step (a roof's edge under parallax) by up to that much: the interval
  is widened to the minimum and maximum of ``m`` over a disc of ``r`` pixels there
  (``reach``, an integer map; 0 elsewhere, where nothing changes).

The residual that enters the statistic is the distance of the observation from this
interval (:func:`tolerant_reference` returns the interval's point nearest to it).  A
change whose contrast exceeds ``contrast`` times the local range (and the shift's reach)
keeps the rest of its amplitude; on flat ground the interval is a point and nothing is
lost.  The tolerance reaches :meth:`ModelTolerance.reach` pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

__all__ = ["ModelTolerance", "tolerance_interval", "tolerant_reference"]


@dataclass(frozen=True)
class ModelTolerance:
    """How far the model may miss, see the module docstring.

    Attributes
    ----------
    shift : float
        Misregistration tolerated, in pixels, ``0 <= shift <= 1`` (0: none).
    contrast : float
        Relative accuracy of the blur model: the interval is widened by ``contrast`` times
        the local range of the reference (0: none), ``0 <= contrast < 0.5``.
    radius : int
        Radius (pixels) of the disc over which the local range is taken (>= 1).
    """

    shift: float = 0.0
    contrast: float = 0.0
    radius: int = 3

    def __post_init__(self):
        if not 0.0 <= self.shift <= 1.0:
            raise ValueError(f"shift tolerance must lie in [0, 1] px, got {self.shift}")
        if not 0.0 <= self.contrast < 0.5:
            raise ValueError(f"contrast tolerance must lie in [0, 0.5), got {self.contrast}")
        if int(self.radius) < 1:
            raise ValueError(f"contrast radius must be at least 1 px, got {self.radius}")

    @property
    def active(self) -> bool:
        """Whether the tolerance changes anything."""
        return self.shift > 0 or self.contrast > 0

    @property
    def reach(self) -> int:
        """How far (pixels) the interval at a pixel looks."""
        r = 1 if self.shift > 0 else 0
        return max(r, int(self.radius)) if self.contrast > 0 else r

    def to_dict(self) -> dict[str, Any]:
        return {"shift": float(self.shift), "contrast": float(self.contrast),
                "radius": int(self.radius)}


def _padded(m: np.ndarray, r: int) -> np.ndarray:
    return cv2.copyMakeBorder(m, r, r, r, r, cv2.BORDER_REPLICATE)


def _disc(r: int) -> np.ndarray:
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    return ((yy * yy + xx * xx) <= r * r).astype(np.uint8)


def _widen_by_reach(m: np.ndarray, lo: np.ndarray, hi: np.ndarray, reach: np.ndarray) -> None:
    """Widen ``[lo, hi]`` in place to the extremes of ``m`` over a disc of ``reach`` px."""
    for r in np.unique(reach):
        if r <= 0:
            continue
        where = reach == r
        k = _disc(int(r))
        np.minimum(lo, cv2.erode(m, k, borderType=cv2.BORDER_REPLICATE), out=lo, where=where)
        np.maximum(hi, cv2.dilate(m, k, borderType=cv2.BORDER_REPLICATE), out=hi, where=where)


def tolerance_interval(matched: np.ndarray, tol: ModelTolerance,
                       reach: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bound of the values ``matched`` may take under the tolerance.

    Parameters
    ----------
    matched : (h, w) ndarray
        One band of the photometrically matched reblurred reference.
    tol : ModelTolerance
    reach : (h, w) integer ndarray, optional
        Per-pixel geometric reach (pixels; see the module docstring).

    Returns
    -------
    lo, hi : (h, w) float32 ndarray
        The interval at every pixel (border pixels replicate the edge).
    """
    m = np.ascontiguousarray(matched, dtype=np.float32)
    h, w = m.shape
    f32 = np.float32
    if tol.shift >= 1.0:
        k3 = np.ones((3, 3), np.uint8)
        lo = cv2.erode(m, k3, borderType=cv2.BORDER_REPLICATE)
        hi = cv2.dilate(m, k3, borderType=cv2.BORDER_REPLICATE)
    elif tol.shift > 0.0:
        # OpenCV's blends and extremes (with the contrast step below: the 100 MP unchanged
        # tile pass 8.8 -> 7.6 s CPU, ``python -m benchmarks.stage_cpu REF OBS --stages
        # reblur.pipeline:run_tiles``); its float32 blend may round the last bit
        # differently from numpy's two products
        a, b = float(tol.shift), float(1.0 - tol.shift)
        p = _padded(m, 1)
        lo = m.copy()
        hi = m.copy()
        for dy in (-1, 0, 1):
            row = (p[1:h + 1] if dy == 0
                   else cv2.addWeighted(p[1:h + 1], b, p[1 + dy:h + 1 + dy], a, 0.0))
            for dx in (-1, 0, 1):
                if dx == 0 and dy == 0:
                    continue
                mid = row[:, 1:w + 1]
                v = mid if dx == 0 else cv2.addWeighted(mid, b, row[:, 1 + dx:w + 1 + dx],
                                                        a, 0.0)
                cv2.min(lo, v, dst=lo)
                cv2.max(hi, v, dst=hi)
    else:
        lo = m.copy()
        hi = m.copy()
    if tol.contrast > 0.0:
        r = int(tol.radius)
        disc = _disc(r)
        rng = cv2.dilate(m, disc, borderType=cv2.BORDER_REPLICATE)
        cv2.subtract(rng, cv2.erode(m, disc, borderType=cv2.BORDER_REPLICATE), dst=rng)
        rng *= f32(tol.contrast)
        cv2.subtract(lo, rng, dst=lo)  # float32 sums, rounded once: numpy's values
        cv2.add(hi, rng, dst=hi)
    if reach is not None:
        _widen_by_reach(m, lo, hi, reach)
    return lo, hi


def tolerant_reference(observed: np.ndarray, matched: np.ndarray,
                       tol: ModelTolerance | None,
                       reach: np.ndarray | None = None) -> np.ndarray:
    """The value within the tolerance interval of ``matched`` nearest to ``observed``.

    ``observed - tolerant_reference(observed, matched, tol)`` is the residual the model
    cannot explain: 0 inside the interval, the distance to it outside.

    Parameters
    ----------
    observed, matched : (h, w) ndarray
        One band of the observation and of the matched reblurred reference.
    tol : ModelTolerance or None
        None or an inactive tolerance (and no ``reach``) returns ``matched`` itself.
    reach : (h, w) integer ndarray, optional
        Per-pixel geometric reach (:func:`tolerance_interval`).

    Returns
    -------
    (h, w) ndarray
    """
    if reach is not None and not reach.any():
        reach = None
    if (tol is None or not tol.active) and reach is None:
        return matched
    lo, hi = tolerance_interval(matched, tol or ModelTolerance(), reach)
    o = np.asarray(observed, dtype=np.float32)
    if o.flags.c_contiguous:  # OpenCV's extremes (exact, as numpy's) without a temporary
        cv2.max(lo, cv2.min(o, hi, dst=hi), dst=lo)
    else:
        np.maximum(lo, np.minimum(o, hi), out=lo)
    return lo
