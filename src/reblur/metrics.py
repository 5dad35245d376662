"""Scores of a change mask against a reference mask, and PSNR.

Pixels are counted in a confusion matrix (Radke et al. 2005; Rosin and Ioannidis 2003)::

    TP: change in truth, predicted     FP: no change in truth, predicted
    FN: change in truth, not predicted TN: no change in truth, not predicted

and the paper's scores are computed from it (METHOD.md, sec. 5):

* ``PCC = (TP + TN) / N`` (in ``[0, 1]``; print it as a percentage),
* ``JC = TP / (TP + FP + FN)`` (Jaccard coefficient),
* ``YC = |TP / (TP + FP) + TN / (TN + FN) - 1|`` (Yule coefficient),

plus precision, recall, F1 and the false-positive rate ``FP / (FP + TN)``.

Degenerate cases (a ratio whose denominator is zero)
----------------------------------------------------
* Every score is NaN when no pixel is counted (everything ignored).
* ``jaccard`` and ``f1``: **1.0** when truth and prediction are both empty
  (``TP + FP + FN == 0``): nothing to find and nothing reported is a perfect answer, and
  ``F1 = 2 JC / (1 + JC)`` keeps that identity.  Any false alarm then gives 0.
* ``precision``: NaN when nothing is predicted (``TP + FP == 0``).
* ``recall``: NaN when the truth has no change (``TP + FN == 0``).
* ``false_positive_rate``: NaN when the truth has no unchanged pixel (``FP + TN == 0``).
* ``yule``: NaN when either of its ratios is undefined (nothing predicted, or everything
  predicted): a constant answer has no predictive value to measure.
* ``psnr``: ``inf`` when the images agree exactly, NaN when the mask selects no pixel.

NaN (not 0) marks an undefined score so that a mean over images can skip it
(``numpy.nanmean``) instead of being biased by an arbitrary convention.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "confusion",
    "pcc",
    "jaccard",
    "yule",
    "precision",
    "recall",
    "f1",
    "false_positive_rate",
    "psnr",
    "change_metrics",
]


def _as_mask(a, name: str) -> np.ndarray:
    a = np.asarray(a)
    if a.dtype == bool:
        return a
    if np.issubdtype(a.dtype, np.integer):
        if a.size and (a.min() < 0 or a.max() > 1):
            raise ValueError(
                f"{name} must be boolean or hold only 0 and 1, got values in "
                f"[{a.min()}, {a.max()}]; threshold it first (e.g. `{name} > 0`)"
            )
        return a.astype(bool)
    raise ValueError(
        f"{name} must be a boolean (or 0/1 integer) mask, got dtype {a.dtype}; "
        f"threshold it first (e.g. `{name} >= 0.5`)"
    )


def _check_masks(mask_true, mask_pred, ignore) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    t = _as_mask(mask_true, "mask_true")
    p = _as_mask(mask_pred, "mask_pred")
    if t.shape != p.shape:
        raise ValueError(f"mask_true has shape {t.shape} but mask_pred has shape {p.shape}")
    ig = None
    if ignore is not None:
        ig = _as_mask(ignore, "ignore")
        if ig.shape != t.shape:
            raise ValueError(f"ignore has shape {ig.shape}, the masks have shape {t.shape}")
    return t, p, ig


def _ratio(num: float, den: float) -> float:
    return float(num) / float(den) if den else float("nan")


def confusion(mask_true, mask_pred, ignore=None) -> dict[str, int]:
    """Count the confusion matrix of a predicted change mask.

    Parameters
    ----------
    mask_true, mask_pred : array_like of bool, same shape
        Reference and predicted change masks (True = change).  0/1 integers are accepted.
    ignore : array_like of bool, optional
        Pixels left out of every count (e.g. pixels the reference does not cover).

    Returns
    -------
    dict
        ``tp``, ``fp``, ``tn``, ``fn`` as Python ints.

    Raises
    ------
    ValueError
        If the shapes differ or a mask is not boolean (or 0/1).

    Examples
    --------
    >>> confusion([[1, 1], [0, 0]], [[1, 0], [1, 0]])
    {'tp': 1, 'fp': 1, 'tn': 1, 'fn': 1}
    """
    t, p, ig = _check_masks(mask_true, mask_pred, ignore)
    if ig is not None:
        keep = ~ig
        t, p = t[keep], p[keep]
    tp = int(np.count_nonzero(t & p))
    fp = int(np.count_nonzero(~t & p))
    fn = int(np.count_nonzero(t & ~p))
    tn = int(t.size - tp - fp - fn)
    return {"tp": tp, "fp": fp, "tn": tn, "fn": fn}


def _from_counts(c: dict[str, int]) -> dict[str, float]:
    tp, fp, tn, fn = c["tp"], c["fp"], c["tn"], c["fn"]
    n = tp + fp + tn + fn
    if n == 0:
        nan = float("nan")
        return dict.fromkeys(("pcc", "jaccard", "yule", "precision", "recall", "f1", "fpr"), nan)
    prec = _ratio(tp, tp + fp)
    npv = _ratio(tn, tn + fn)
    return {
        "pcc": _ratio(tp + tn, n),
        "jaccard": 1.0 if tp + fp + fn == 0 else tp / (tp + fp + fn),
        "yule": abs(prec + npv - 1.0),  # NaN propagates
        "precision": prec,
        "recall": _ratio(tp, tp + fn),
        "f1": 1.0 if tp + fp + fn == 0 else 2 * tp / (2 * tp + fp + fn),
        "fpr": _ratio(fp, fp + tn),
    }


def pcc(mask_true, mask_pred, ignore=None) -> float:
    """Percentage of correct classification as a fraction: ``(TP + TN) / N``.

    NaN when no pixel is counted.  See :func:`confusion` for the parameters.
    """
    return _from_counts(confusion(mask_true, mask_pred, ignore))["pcc"]


def jaccard(mask_true, mask_pred, ignore=None) -> float:
    """Jaccard coefficient ``TP / (TP + FP + FN)``; 1.0 when truth and prediction are empty.

    (NaN when no pixel is counted.)

    See :func:`confusion` for the parameters.
    """
    return _from_counts(confusion(mask_true, mask_pred, ignore))["jaccard"]


def yule(mask_true, mask_pred, ignore=None) -> float:
    """Yule coefficient ``|TP / (TP + FP) + TN / (TN + FN) - 1|``.

    NaN when nothing or everything is predicted.  See :func:`confusion` for the parameters.
    """
    return _from_counts(confusion(mask_true, mask_pred, ignore))["yule"]


def precision(mask_true, mask_pred, ignore=None) -> float:
    """Precision ``TP / (TP + FP)``; NaN when nothing is predicted."""
    return _from_counts(confusion(mask_true, mask_pred, ignore))["precision"]


def recall(mask_true, mask_pred, ignore=None) -> float:
    """Recall ``TP / (TP + FN)``; NaN when the truth holds no change."""
    return _from_counts(confusion(mask_true, mask_pred, ignore))["recall"]


def f1(mask_true, mask_pred, ignore=None) -> float:
    """F1 score ``2 TP / (2 TP + FP + FN)``; 1.0 when truth and prediction are empty."""
    return _from_counts(confusion(mask_true, mask_pred, ignore))["f1"]


def false_positive_rate(mask_true, mask_pred, ignore=None) -> float:
    """Fraction of unchanged pixels flagged, ``FP / (FP + TN)``; NaN if none is unchanged."""
    return _from_counts(confusion(mask_true, mask_pred, ignore))["fpr"]


def change_metrics(mask_true, mask_pred, ignore=None) -> dict[str, float | int]:
    """All change scores at once.

    Parameters
    ----------
    mask_true, mask_pred : array_like of bool, same shape
        Reference and predicted change masks.
    ignore : array_like of bool, optional
        Pixels left out of every count.

    Returns
    -------
    dict
        ``tp``, ``fp``, ``tn``, ``fn``, ``n`` (ints) and ``pcc``, ``jaccard``, ``yule``,
        ``precision``, ``recall``, ``f1``, ``fpr`` (floats; see the module notes for the
        degenerate cases).  ``pcc`` is a fraction in ``[0, 1]``.
    """
    c = confusion(mask_true, mask_pred, ignore)
    out: dict[str, float | int] = dict(c)
    out["n"] = c["tp"] + c["fp"] + c["tn"] + c["fn"]
    out.update(_from_counts(c))
    return out


def psnr(reference, image, data_range: float = 1.0, mask=None) -> float:
    """Peak signal-to-noise ratio ``10 log10(data_range^2 / MSE)`` in dB.

    Parameters
    ----------
    reference, image : array_like, same shape
        ``(h, w)`` or ``(h, w, C)`` images.
    data_range : float
        Peak-to-peak range of the data (1.0 for images in ``[0, 1]``, 255 for 8-bit).
    mask : array_like of bool, optional
        ``(h, w)`` (or full-shape) mask of the pixels to compare; all bands of a selected
        pixel count.

    Returns
    -------
    float
        PSNR in dB; ``inf`` for identical images, NaN if the mask selects nothing.

    Raises
    ------
    ValueError
        On a shape mismatch or a non-positive ``data_range``.
    """
    a = np.asarray(reference, dtype=np.float64)
    b = np.asarray(image, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"reference has shape {a.shape} but image has shape {b.shape}")
    if not data_range > 0:
        raise ValueError(f"data_range must be positive, got {data_range}")
    d2 = (a - b) ** 2
    if mask is not None:
        m = _as_mask(mask, "mask")
        if m.shape == a.shape[:2] and d2.ndim == 3:
            d2 = d2[m]
        elif m.shape == a.shape:
            d2 = d2[m]
        else:
            raise ValueError(f"mask has shape {m.shape}, expected {a.shape[:2]} or {a.shape}")
    if d2.size == 0:
        return float("nan")
    mse = float(np.mean(d2))
    if mse == 0:
        return float("inf")
    return float(10.0 * np.log10(data_range**2 / mse))
