"""Calibration of the model's tolerance on the estimation windows (between stages 1 and 2:
:func:`calibrate_tolerance`).

How accurate the blur model is depends on the pair: the camera's real motion (6-D, or
with parts the pose grid cannot hold), the interpolators, the scene's sharpness.  It can
be seen where the motion was estimated: the estimation windows were fitted by eq. 5, and
the estimate marked what it took for change there (``chi``).  Away from those marks, every
pixel of a window is unchanged, and what the statistic finds there is the model's own
error.  The tolerance (:mod:`.tolerance`: a shift and a contrast) is therefore the first
rung of a ladder, from tight to loose, at which the statistic of those unchanged pixels
stays at or under the decision's floor (``DecisionParams.min_threshold``) but for a
fraction ``target`` of them: where the model fits well the decision keeps its full
sensitivity on texture, where it does not it gives away only what it must.  The top of
the ladder bounds what is given away: a change whose contrast is more than twice the
contrast tolerance, relative to the local range, keeps the larger part of its
amplitude.  Where even the top does not meet the target, the floor itself rises to the
level the unchanged pixels reach but for that fraction: the threshold then rests on the
model's measured error rather than on the noise.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np

from .statistic import change_statistic
from .tolerance import ModelTolerance

__all__ = ["calibrate_tolerance", "marked_pixels", "unchanged_pixels"]


def marked_pixels(chi: np.ndarray | None) -> np.ndarray | None:
    """Pixels the estimate's change term marks (non-zero in any band), or None."""
    if chi is None:
        return None
    c = np.asarray(chi)
    return (np.abs(c) > 0).any(axis=2) if c.ndim == 3 else np.abs(c) > 0


def unchanged_pixels(known: np.ndarray, chi: np.ndarray | None, margin: int) -> np.ndarray:
    """Known pixels farther than ``margin`` pixels from any change the estimate marked.

    Parameters
    ----------
    known : (h, w) bool ndarray
    chi : (h, w) or (h, w, C) ndarray, optional
        The estimate's change term on the same window (non-zero: change).
    margin : int
        Distance kept from a marked change (the statistic's window reaches that far).

    Returns
    -------
    (h, w) bool ndarray
    """
    known = np.asarray(known, bool)
    marked = marked_pixels(chi)
    if marked is None:
        return known.copy()
    if marked.shape != known.shape:
        raise ValueError(f"chi has shape {marked.shape}, the window {known.shape}")
    if margin > 0 and marked.any():
        k = 2 * int(margin) + 1
        marked = cv2.dilate(marked.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    return known & ~marked


def calibrate_tolerance(
    observed: Sequence[np.ndarray],
    matched: Sequence[np.ndarray],
    known: Sequence[np.ndarray],
    evaluate: Sequence[np.ndarray],
    sigma,
    *,
    ladder: Sequence[ModelTolerance],
    threshold: float,
    target: float,
    margin: int = 0,
    smooth: float = 2.0,
    truncate: float = 4.0,
) -> tuple[ModelTolerance, dict[str, Any]]:
    """First tolerance of ``ladder`` under which the unchanged pixels of the estimation
    windows stay below ``threshold`` but for a fraction ``target``.

    Parameters
    ----------
    observed, matched : sequence of (h, w) or (h, w, C) ndarray
        Each window's observation and photometrically matched reblurred reference.
    known : sequence of (h, w) bool ndarray
        Pixels where both are defined (enter the statistic).
    evaluate : sequence of (h, w) bool ndarray
        Unchanged pixels on which the false-alarm fraction is counted
        (:func:`unchanged_pixels`).
    sigma : (C,) array_like
        Residual scale per band (:attr:`Photometry.sigma`).
    ladder : sequence of ModelTolerance
        Tolerances from tight to loose.  A nested ladder (each rung's shift and contrast
        at least the previous one's, as the default) is searched by bisection after its
        first and last rungs, any other scanned in order (:func:`_first_meeting`): the
        same rung either way.
    threshold : float
        The statistic's floor (``DecisionParams.min_threshold``).
    target : float
        Largest fraction of unchanged pixels allowed above ``threshold``.
    margin : int
        Rungs added beyond the first that meets the target (bounded by the ladder): the
        windows are a few, chosen where the texture fits best, and the rest of the image
        may hold more model error than they show.
    smooth, truncate : float
        The statistic's window.

    Returns
    -------
    tolerance : ModelTolerance
        The chosen tolerance: ``margin`` rungs after the first that meets the target (the
        ladder's last one when none does).
    info : dict
        ``n`` (pixels evaluated), ``tried`` (shift, contrast, fraction above the threshold
        of each rung evaluated, in ladder order),
        ``met`` (whether the chosen value meets the target), ``floor``: ``threshold``,
        or where even the last tolerance does not meet the target, the ``1 - target``
        quantile of the unchanged pixels' statistic under it (the decision's threshold
        should not lie below it).

    Raises
    ------
    ValueError
        With an empty ladder, or no pixel to evaluate.
    """
    lad = list(ladder)
    if not lad:
        raise ValueError("the tolerance ladder is empty")
    n = int(sum(int(np.count_nonzero(e)) for e in evaluate))
    if n == 0:
        raise ValueError("no unchanged pixel to calibrate the tolerance on")
    tried: dict[int, list[float]] = {}
    last = len(lad) - 1
    values: list[np.ndarray] = []  # the last rung's, for the floor

    def meets(i: int) -> bool:
        """Whether rung ``i`` meets the target (its statistic computed once)."""
        tol = lad[i]
        got = [change_statistic(o, m, k, sigma, smooth=smooth, truncate=truncate,
                                tolerance=tol)[e]
               for o, m, k, e in zip(observed, matched, known, evaluate, strict=True)]
        if i == last:
            values[:] = got
        above = sum(int(np.count_nonzero(v > threshold)) for v in got)
        tried[i] = [tol.shift, tol.contrast, above / n]
        return above <= target * n

    first = _first_meeting(len(lad), meets, nested=_nested(lad))
    record = [tried[i] for i in sorted(tried)]
    if first is not None:
        pick = lad[min(first + int(margin), len(lad) - 1)]
        return pick, {"n": n, "tried": record, "met": True, "target": float(target),
                      "floor": float(threshold), "margin": int(margin),
                      "first_met": [lad[first].shift, lad[first].contrast]}
    # the model's error exceeds even the largest tolerance: the statistic's floor rises
    # to what the unchanged pixels reach but for the target fraction
    floor = float(np.quantile(np.concatenate(values), 1.0 - target))
    return lad[-1], {"n": n, "tried": record, "met": False, "target": float(target),
                     "floor": max(floor, float(threshold))}


def _nested(ladder: Sequence[ModelTolerance]) -> bool:
    """Whether every rung's tolerance contains the previous one's (shift and contrast both
    non-decreasing): then the interval of :func:`~reblur.decide.tolerance.tolerance_interval`
    only widens up the ladder (a square of shifts contains the smaller ones, a wider
    contrast band the narrower), every pixel's distance from it only shrinks, and so does
    the fraction of pixels above the threshold."""
    return all(b.shift >= a.shift and b.contrast >= a.contrast
               for a, b in zip(ladder[:-1], ladder[1:], strict=True))


def _first_meeting(n: int, meets, *, nested: bool) -> int | None:
    """Index of the first of ``n`` rungs for which ``meets(i)`` holds, or None.

    A ladder that is not nested is scanned in order.  On a nested one ``meets`` is
    monotone (once a rung meets the target every looser one does), so after the first rung
    the last is tried (a model error beyond the ladder, the GoPro pairs': two statistics
    instead of six), then the first meeting rung is bisected between them: the rung a scan
    in order finds, in at most ``2 + log2(n)`` evaluations.
    """
    if not nested:
        return next((i for i in range(n) if meets(i)), None)
    if meets(0):
        return 0
    if n == 1 or not meets(n - 1):
        return None
    lo, hi = 0, n - 1  # lo fails, hi meets
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if meets(mid):
            hi = mid
        else:
            lo = mid
    return hi
