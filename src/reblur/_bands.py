"""Per-pixel reductions over the bands of an image: ``np.all`` / ``np.any`` / ``np.mean``
over its last axis.

numpy reduces a short last axis pixel by pixel: on a 1300 px 3-band tile ``np.all(b,
axis=2)`` took 22 ms, the and of the three planes 3.3 ms (``python -m timeit -s "import
numpy as np; from reblur._bands import all_bands; b = np.ones((1300, 1300, 3), bool)"
"all_bands(b)"``, and ``"np.all(b, axis=2)"``); a 1024 px 3-band float32 band mean 15.2
against 2.4 ms (the same command with ``b = np.ones((1024, 1024, 3), np.float32)``,
``"b.mean(axis=2, dtype=np.float32)"`` and ``"mean_bands(b)"``).  These combine the
bands' planes one by one instead (the same booleans; the same float32 sums, band after
band).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["BandMean", "all_bands", "any_bands", "mean_bands"]


def _planes(b: np.ndarray, op: np.ufunc) -> np.ndarray:
    """``op`` of the bands' planes of an (h, w, C) bool array, one by one; a 2-D one as
    it is."""
    b = np.asarray(b)
    if b.ndim == 2:
        return b
    out = b[:, :, 0].copy()
    for c in range(1, b.shape[2]):
        op(out, b[:, :, c], out=out)
    return out


def all_bands(b: np.ndarray) -> np.ndarray:
    """``np.all(b, axis=2)`` of an (h, w, C) bool array; a 2-D one is returned as it is.

    Parameters
    ----------
    b : (h, w) or (h, w, C) bool ndarray

    Returns
    -------
    (h, w) bool ndarray
        A new array for a 3-D ``b``.
    """
    return _planes(b, np.logical_and)


def any_bands(b: np.ndarray) -> np.ndarray:
    """``np.any(b, axis=2)`` of an (h, w, C) bool array (parameters and result as
    :func:`all_bands`)."""
    return _planes(b, np.logical_or)


def mean_bands(a: np.ndarray, dtype=np.float32) -> np.ndarray:
    """``np.mean(a, axis=2, dtype=dtype)`` of an (h, w, C) array: its planes cast to
    ``dtype`` and added band after band, then divided by ``C`` (numpy's order for a short
    last axis: the same values, ``tests/test_decide_fast.py``).

    Parameters
    ----------
    a : (h, w, C) ndarray
        Any real dtype.
    dtype : numpy dtype
        Floating type of the sums and the result.

    Returns
    -------
    (h, w) ndarray of ``dtype``
        A new array.
    """
    a = np.asarray(a)
    if a.ndim != 3:
        raise ValueError(f"mean_bands needs an (h, w, C) array, got shape {a.shape}")
    out = a[:, :, 0].astype(dtype)
    for c in range(1, a.shape[2]):
        np.add(out, a[:, :, c], out=out, dtype=dtype)
    out /= a.shape[2]
    return out


class BandMean:
    """Lazy band mean of an ``(H, W, C)`` array-like: slices of it are ``(h, w)`` float32.

    What :func:`reblur.estimate.estimate_motion` solves on with ``bands="mean"``, and
    what :func:`reblur.align.refine.measure_shifts` reblurs (the blur is linear: the
    band mean of the reblurred bands is the reblurred band mean).  An ``exclude`` of the
    array (see :func:`~reblur.estimate.estimate_motion`'s ``observed``) is kept.  Values
    stay in the array's units (its intensity scale applies).

    Parameters
    ----------
    array : array-like
        ``(H, W, C)``: numpy, zarr, or a view with ``shape``, ``dtype`` and slicing.
    """

    def __init__(self, array: Any) -> None:
        self.array = array
        self.shape = tuple(int(v) for v in array.shape[:2])
        self.dtype = np.dtype(np.float32)
        self.exclude = getattr(array, "exclude", None)

    def __getitem__(self, key: Any) -> np.ndarray:
        if isinstance(key, tuple) and len(key) > 2:
            raise IndexError("a band mean has two axes")
        a = np.asarray(self.array[key])
        return mean_bands(a) if a.ndim == 3 else a.mean(axis=-1, dtype=np.float32)
