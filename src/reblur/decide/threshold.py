"""Stage 3 of the change decision, the threshold (:func:`estimate_threshold`; global, from
a sample of ``S`` values).  The robust bound ``median + 4 MAD`` of the bulk of ``S``, or
Otsu's split of its histogram when that is lower AND the bulk is broad
(``MAD >= 0.4 median``): on pairs taken years apart the "unchanged" class is a continuum of
real appearance changes, far wider than noise, and Otsu is the lower, adaptive split.
Where the bulk is as narrow as noise makes it (``S`` averages ~``4 pi smooth^2`` squared
z-scores: a relative spread of ~0.1) it is the unchanged class, and Otsu would cut through
it: with no change in the sample (a gigapixel image sampled on 1.7 % of its area) it fell
just above the median, and 2.9 % of an unchanged image came out as change despite the
hysteresis of the regions.  When the changes are well separated, Otsu lands midway between
the classes and the robust bound keeps faint changes.  ``threshold=`` overrides it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from skimage.filters import threshold_otsu

from ..robust import MAD_TO_SIGMA, median


def estimate_threshold(
    stat_samples, *, method: str = "auto", k: float = 4.0, bins: int = 512,
    broad: float = 0.4, minimum: float = 0.0,
) -> tuple[float, dict[str, Any]]:
    """Decision threshold of the change statistic from a sample of its values.

    Parameters
    ----------
    stat_samples : array_like or sequence of array_like
        Values of :func:`change_statistic` at known pixels (any shape; e.g. the known
        pixels of a few tiles).  Non-finite values are ignored.
    method : {"auto", "otsu", "mad"}
        ``"otsu"``: Otsu's threshold of the histogram on ``[0, q99.9]`` (values above are
        counted in the last bin, so a few extreme values do not squeeze the histogram).
        ``"mad"``: ``median + k * 1.4826 * MAD``, a robust z-test against the bulk of the
        statistic.  ``"auto"`` (default): the MAD bound, or Otsu when it is lower and the
        bulk is broad (``MAD >= broad * median``).  When changed and unchanged pixels
        overlap (real pairs years apart: a continuum of appearance changes, the bulk 0.5-0.9
        median wide on the LEVIR / WHU pairs of ``benchmarks/quality.py``) Otsu is the lower
        one and splits the two classes.  A bulk as narrow as noise leaves it (0.07-0.10
        median wide on the Fig. 6 set-up there) is the unchanged class itself:
        Otsu would cut through it, most visibly when the sample holds no change at all.
        When the changes are well separated from the noise Otsu falls midway between the
        classes and would drop faint changes: the z-bound again.
    k : float
        Multiplier of the MAD bound.
    bins : int
        Histogram bins of Otsu's method.
    broad : float
        Relative width ``MAD / median`` from which the bulk counts as broad (``"auto"``).
    minimum : float
        Lower bound of the result (``DecisionParams.min_threshold``); ``info["floored"]``
        says whether it applied.

    Returns
    -------
    threshold : float
    info : dict
        ``method``, ``n``, ``median``, ``mad`` (scaled to a standard deviation), ``q99``,
        ``otsu``, ``mad_bound``, ``broad`` (the bulk is broad) and ``chosen`` (``"otsu"``
        or ``"mad"``).

    Raises
    ------
    ValueError
        With no finite sample or an unknown method.
    """
    if isinstance(stat_samples, (list, tuple)):
        x = np.concatenate([np.asarray(a).ravel() for a in stat_samples], dtype=np.float64)
    else:
        x = np.asarray(stat_samples, dtype=np.float64).ravel()
    finite = np.isfinite(x)
    if not finite.all():
        x = x[finite]
    if x.size == 0:
        raise ValueError("estimate_threshold needs at least one finite statistic value")
    if method not in ("auto", "otsu", "mad"):
        raise ValueError(f"method must be 'auto', 'otsu' or 'mad', got {method!r}")
    if not broad >= 0:
        raise ValueError(f"broad must be >= 0, got {broad}")
    med = median(x)  # np.median's values (reblur.robust.median)
    dev = x - med  # robust.mad(x), its median computed once
    np.abs(dev, out=dev)
    spread = float(MAD_TO_SIGMA * dev.dtype.type(median(dev)))  # in x's precision
    del dev
    bound = med + float(k) * spread
    info: dict[str, Any] = {
        "method": method, "n": int(x.size), "median": med, "mad": spread, "k": float(k),
        "mad_bound": bound, "q99": float(np.quantile(x, 0.99)),
    }
    lo, hi = float(x.min()), float(np.quantile(x, 0.999))
    if hi <= lo:
        hi = float(x.max())
    if hi <= lo:  # constant statistic: nothing stands out
        info["otsu"] = lo
        info["note"] = "constant statistic"
        info["floored"] = bool(minimum > hi)
        return max(float(np.nextafter(hi, np.inf)), float(minimum)), info
    counts, edges = np.histogram(np.minimum(x, hi), bins=int(bins), range=(lo, hi))
    centers = 0.5 * (edges[:-1] + edges[1:])
    otsu = float(threshold_otsu(hist=(counts, centers)))
    info["otsu"] = otsu
    is_broad = spread >= float(broad) * med
    info["broad"] = bool(is_broad)
    if method == "auto":
        chosen = "otsu" if is_broad and otsu < bound else "mad"
    else:
        chosen = method
    info["chosen"] = chosen
    t = float(otsu if chosen == "otsu" else bound)
    info["floored"] = bool(minimum > t)
    return max(t, float(minimum)), info

