"""Small helpers shared by the stages of the change decision: band and dtype normalisation
(``_channels``, ``_float``), box parsing (``_box``), the robust residual scale
(``_robust_scale``, the MAD of the inliers) and the bands' fits side by side
(:func:`band_map`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .._memory import available_cpus
from ..robust import MAD_TO_SIGMA, median


def _channels(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    return a[:, :, None] if a.ndim == 2 else a


def _float(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    if a.dtype in (np.float32, np.float64):
        return a
    return a.astype(np.float32)


def _box(box) -> tuple[int, int, int, int]:
    if hasattr(box, "as_tuple"):
        box = box.as_tuple()
    y0, x0, h, w = (int(v) for v in box)
    if h < 1 or w < 1:
        raise ValueError(f"box must have positive size, got {(y0, x0, h, w)}")
    return y0, x0, h, w


def _robust_scale(r: np.ndarray, k: float = 3.5, n_iter: int = 5) -> float:
    """Standard deviation of the inliers: MAD, re-estimated on ``|r - med| < k * scale``.

    The plain MAD is inflated by a large fraction of changed pixels (by 30 % with 20 %
    gross outliers); trimming beyond ``k = 3.5`` scales removes them and biases a Gaussian's
    MAD by less than 0.1 %.
    """
    r = r[np.isfinite(r)]
    if r.size == 0:
        return float("nan")
    med = median(r)  # np.median's values (reblur.robust.median)
    d = np.abs(r - med)
    s = MAD_TO_SIGMA * median(d)
    for _ in range(n_iter):
        keep = d < k * s
        if not keep.any():
            break
        s_new = MAD_TO_SIGMA * median(d[keep])
        if s_new == s:
            break
        s = s_new
    return s


#: BLAS threads of the photometric fits: their products are vectors of at most a few
#: hundred thousand samples, where more threads mostly wait (on 2 busy cores a Huber
#: step took 10x the single-threaded time).
FIT_BLAS_THREADS = 1


def band_map(fit, n_bands: int) -> list:
    """``[fit(c) for c in range(n_bands)]``, the bands side by side on the CPUs available.

    Each band's robust fit is computed alone, on its own samples, exactly as in a loop;
    most of its time is numpy's selections and products, which release the GIL: three
    bands of 260 000 samples (:func:`reblur.robust.robust_line`) took 0.27 s on two
    threads against 0.40 s in a loop.  BLAS stays on :data:`FIT_BLAS_THREADS` (the
    callers' limit, which the fits' own limit of one thread leaves as it is), so the
    values are the loop's.  ``fit`` must not call OpenCV: its filters split an image into
    as many stripes as it has threads, and the stripes' sums differ in the last bits (a
    band's prefit gain moved by 1e-11 with OpenCV on one thread); two threads filtering at
    once would get one stripe or several by timing.  Filter first, then fit here.
    """
    n = min(n_bands, available_cpus())
    if n <= 1:
        return [fit(c) for c in range(n_bands)]
    with ThreadPoolExecutor(n) as ex:
        return list(ex.map(fit, range(n_bands)))
