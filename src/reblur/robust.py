"""Robust statistics shared by the estimation and the decision stages."""

from __future__ import annotations

import numpy as np

__all__ = ["MAD_TO_SIGMA", "mad", "huber_line"]

#: MAD -> standard deviation for a Gaussian.
MAD_TO_SIGMA = 1.4826


def mad(x: np.ndarray) -> float:
    """Median absolute deviation scaled to a Gaussian's standard deviation (NaN if empty)."""
    return float(MAD_TO_SIGMA * np.median(np.abs(x - np.median(x)))) if x.size else float("nan")


def huber_line(
    x: np.ndarray, y: np.ndarray, start: tuple[float, float] | None = None, n_iter: int = 20
) -> tuple[float, float]:
    """Huber IRLS fit ``y ~ gain * x + offset`` (scale re-estimated by MAD each step).

    Huber's loss is convex, so the fit is unique and stable even when ``x`` and ``y`` are
    weakly correlated, and its bounded influence keeps a minority of outliers (changed
    pixels) from biasing it.  (A redescending Tukey fit was tried for the decision's
    photometry: on the development pairs it locks onto the dominant unchanged class and
    flags more of the neighbouring, unlabelled changes.)

    Parameters
    ----------
    x, y : (n,) ndarray
        Paired samples.
    start : (gain, offset), optional
        Starting point (default: the least-squares fit).
    n_iter : int
        Reweighting steps at most (stops when the parameters move by less than 1e-6).

    Returns
    -------
    gain, offset : float
        ``(1, median(y - x))`` when ``x`` is constant or has fewer than two samples.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.size < 2 or np.ptp(x) == 0:
        return 1.0, float(np.median(y - x)) if y.size else 0.0
    A = np.stack([x, np.ones_like(x)], axis=1)
    if start is None:
        p = np.linalg.lstsq(A, y, rcond=None)[0]
    else:
        p = np.asarray(start, dtype=np.float64)
    for _ in range(n_iter):
        r = y - A @ p
        s = mad(r)
        if not s > 0:
            break
        sw = np.sqrt(np.minimum(1.0, 1.345 * s / np.maximum(np.abs(r), 1e-12)))
        p_new = np.linalg.lstsq(A * sw[:, None], y * sw, rcond=None)[0]
        done = np.allclose(p_new, p, rtol=0, atol=1e-6)
        p = p_new
        if done:
            break
    return float(p[0]), float(p[1])
