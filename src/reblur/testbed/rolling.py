"""Rolling-shutter observations: every row averaged over its own time window of one path.

A CMOS sensor with a rolling shutter exposes its rows one after the other.  With the
exposure ``e`` as the unit of time and the readout fraction ``r`` (the time the shutter
takes to sweep the frame, as a fraction of the exposure), row ``y`` of an ``H``-row
observation integrates over ``[r y / H, r y / H + 1]``.  One smooth camera path is sampled
at ``n_exposure`` sub-poses per exposure over ``[0, 1 + r_max]``: sub-pose ``j`` stands
for the time slice ``[j, j + 1] / n_exposure``, and row ``y`` averages the reference warped
by the homographies of ITS sub-poses, each weighted by the share of its slice inside the
row's window (the slices cut by the window's ends count in part):

    ``obs(x, y) = sum_j a_j(y) ref(H_j^{-1} (x, y)) / n_exposure``,
    ``a_j(y) = |[j, j + 1] cap [s(y), s(y) + n_exposure]|``, ``s(y) = r n_exposure y / H``.

Each term is the test bed's own bicubic warp (:func:`reblur.testbed.render.render_window`
with one homography), accumulated in float64 in the order of the sub-poses, so with
``r = 0`` a window is bit for bit :func:`~reblur.testbed.render.render_window` of the first
``n_exposure`` homographies.  Like the rest of :mod:`reblur.testbed`, nothing here comes
from reblur's model code.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from .camera import shake_for
from .pairs import TILE, PairPlan, RealismPair, pair_from_plan, plan_pair
from .render import Box, iter_tiles, render_window, valid_window
from .scenes import truth_window

__all__ = [
    "READOUTS",
    "RollingPlan",
    "make_rolling_pair",
    "plan_rolling_pair",
    "render_rolling_tiled",
    "render_rolling_window",
    "row_slice_weights",
]

#: Readout fractions of the benchmark pairs (0: a global shutter).
READOUTS = (0.0, 0.25, 0.5, 1.0)


def _check_readout(readout: float, n_exposure: int, n_total: int) -> tuple[float, int]:
    r = float(readout)
    n = int(n_exposure)
    if not (np.isfinite(r) and 0.0 <= r <= 1.0):
        raise ValueError(f"readout must be a fraction in [0, 1], got {readout!r}")
    if n < 1:
        raise ValueError(f"n_exposure must be a positive number of sub-poses, got {n_exposure}")
    need = n + int(np.ceil(r * n))
    if n_total < need:
        raise ValueError(f"a readout of {r:g} with {n} sub-poses per exposure needs {need} "
                         f"sub-poses, the path has {n_total}: sample a longer path")
    return r, n


def row_slice_weights(rows: np.ndarray, height: int, readout: float, n_exposure: int,
                      n_total: int) -> np.ndarray:
    """Exposed share ``a_j(y)`` of every sub-pose slice in every row's window.

    Parameters
    ----------
    rows : numpy.ndarray
        Observation rows ``y`` (full-image coordinates).
    height : int
        Rows ``H`` of the observation.
    readout : float
        Readout fraction ``r`` in [0, 1].
    n_exposure : int
        Sub-poses per exposure.
    n_total : int
        Sub-poses of the path.

    Returns
    -------
    numpy.ndarray
        ``(len(rows), n_total)`` weights in [0, 1]; each row sums to ``n_exposure``.
    """
    r, n = _check_readout(readout, n_exposure, n_total)
    start = r * n * np.asarray(rows, dtype=np.float64)[:, None] / int(height)
    j = np.arange(n_total, dtype=np.float64)[None, :]
    return np.clip(np.minimum(j + 1.0, start + n) - np.maximum(j, start), 0.0, 1.0)


def render_rolling_window(
    source: Any, homographies: np.ndarray, box: Box, *, readout: float, n_exposure: int,
    height: int | None = None, shrink: float = 2.0,
) -> tuple[np.ndarray, np.ndarray]:
    """One window of a rolling-shutter observation and its validity mask.

    Parameters
    ----------
    source : array-like
        Reference (float values), ``(H, W)`` or ``(H, W, C)``.
    homographies : numpy.ndarray
        ``(n_total, 3, 3)`` reference -> observation homographies of the path's sub-poses,
        ``n_exposure`` per exposure, in time order.
    box : Box
        Observation window ``(y0, y1, x0, x1)``.
    readout : float
        Readout fraction ``r`` in [0, 1].
    n_exposure : int
        Sub-poses per exposure.
    height : int, optional
        Rows of the whole observation (the readout sweeps them); default the source's.
    shrink : float
        As :func:`~reblur.testbed.render.render_window`.

    Returns
    -------
    image : numpy.ndarray
        float64 ``(y1 - y0, x1 - x0[, C])``.
    valid : numpy.ndarray
        Boolean mask: every sub-pose a row integrates samples inside the reference.
    """
    hs = np.asarray(homographies, dtype=np.float64)
    if hs.ndim != 3 or hs.shape[1:] != (3, 3):
        raise ValueError(f"homographies must be (n, 3, 3), got shape {hs.shape}")
    y0, y1, x0, x1 = (int(v) for v in box)
    if y1 <= y0 or x1 <= x0:
        raise ValueError(f"box must be (y0, y1, x0, x1) with y1 > y0 and x1 > x0, got {box!r}")
    H = int(source.shape[0] if height is None else height)
    a = row_slice_weights(np.arange(y0, y1), H, readout, n_exposure, len(hs))
    out_shape = (y1 - y0, x1 - x0) + tuple(source.shape[2:])
    acc = np.zeros(out_shape, dtype=np.float64)
    valid = np.ones(out_shape[:2], dtype=bool)
    for j in np.flatnonzero(a.any(axis=0)):
        img, ok = render_window(source, hs[j:j + 1], (y0, y1, x0, x1), shrink=shrink)
        aj = a[:, j]
        if np.all(aj == 1.0):
            acc += img
        else:
            acc += aj.reshape((-1,) + (1,) * (img.ndim - 1)) * img
        valid &= ok | (aj == 0.0)[:, None]
    return acc / int(n_exposure), valid


def render_rolling_tiled(source: Any, homographies: np.ndarray, *, readout: float,
                         n_exposure: int, tile: int = TILE) -> tuple[np.ndarray, np.ndarray]:
    """A whole (in-memory) rolling-shutter observation, tile by tile (the source's size)."""
    shape = tuple(source.shape[:2])
    image = np.zeros(shape + tuple(source.shape[2:]))
    valid = np.zeros(shape, dtype=bool)
    for b in iter_tiles(shape, tile):
        image[b[0]:b[1], b[2]:b[3]], valid[b[0]:b[1], b[2]:b[3]] = render_rolling_window(
            source, homographies, b, readout=readout, n_exposure=n_exposure)
    return image, valid


@dataclass(frozen=True)
class RollingPlan(PairPlan):
    """A :class:`~reblur.testbed.pairs.PairPlan` whose observation has a rolling shutter.

    ``homographies`` holds the whole path (``n_exposure * (1 + readout_max)`` sub-poses);
    row ``y`` integrates the ones of its window (:func:`row_slice_weights`).  The truth
    is the half-maximum footprint over the row's own sub-poses, weighted like the image.
    """

    readout: float = 0.0
    n_exposure: int = 64

    def _weights(self, box: Box) -> np.ndarray:
        return row_slice_weights(np.arange(box[0], box[1]), self.shape[0], self.readout,
                                 self.n_exposure, len(self.homographies))

    def render_tile(self, box: Box) -> np.ndarray:
        image, _ = render_rolling_window(self.changed, self.homographies, box,
                                         readout=self.readout, n_exposure=self.n_exposure,
                                         height=self.shape[0])
        if self.illumination is not None:
            g = self.illumination(box)
            image = np.clip(image * (g[:, :, None] if image.ndim == 3 else g), 0.0, 1.0)
        return image

    def truth_tile(self, box: Box) -> np.ndarray:
        a = self._weights(box)
        share = np.zeros((box[1] - box[0], box[3] - box[2]))
        for j in np.flatnonzero(a.any(axis=0)):
            hit = truth_window(self.changed, self.homographies[j:j + 1], box)
            share += a[:, j:j + 1] * hit
        return 2.0 * share >= self.n_exposure

    def valid_tile(self, box: Box) -> np.ndarray:
        a = self._weights(box)
        valid = np.ones((box[1] - box[0], box[3] - box[2]), dtype=bool)
        for j in np.flatnonzero(a.any(axis=0)):
            ok = valid_window(self.homographies[j:j + 1], box, self.shape)
            valid &= ok | (a[:, j] == 0.0)[:, None]
        return valid


def plan_rolling_pair(
    scene: Any,
    *,
    readout: float,
    readout_max: float = 1.0,
    n_exposure: int = 64,
    motion: dict | None = None,
    **kwargs: Any,
) -> RollingPlan:
    """Draw a rolling-shutter pair: one path over ``1 + readout_max`` exposures.

    The path, viewpoint and changes are drawn as :func:`~reblur.testbed.pairs.plan_pair`
    draws them (same seed, same draws), with ``n_exposure * (1 + readout_max)`` sub-poses:
    pairs that differ only in ``readout`` share the path, the changes and the noise
    streams (``readout=0``: a global-shutter pair over the path's first exposure).  The
    path's time is ``1 + readout_max`` exposures long, so its shake limits
    (default :func:`~reblur.testbed.camera.shake_for`) are scaled by that factor: an
    exposure then sees about the motion of a global-shutter pair of the same limits.

    Parameters
    ----------
    scene : array-like
        Scene in [0, 1].
    readout : float
        Readout fraction in [0, ``readout_max``].
    readout_max : float
        Longest readout the path serves, in [0, 1].
    n_exposure : int
        Sub-poses per exposure (at least 64, the test bed's rule).
    motion : dict, optional
        :func:`~reblur.testbed.camera.random_camera_path` keywords (limits over the whole
        path); ``n_sub`` is set here.
    **kwargs
        Other :func:`~reblur.testbed.pairs.plan_pair` keywords (``size``, ``bits``,
        ``noise_dn``, ``n_changes``, ``seed``, ``viewpoint``, ``changes``, ...).

    Returns
    -------
    RollingPlan
    """
    if not 0.0 <= float(readout_max) <= 1.0:
        raise ValueError(f"readout_max must be in [0, 1], got {readout_max!r}")
    if not 0.0 <= float(readout) <= float(readout_max):
        raise ValueError(f"readout must be in [0, readout_max={readout_max:g}], got {readout!r}")
    n_total = int(n_exposure) + int(np.ceil(float(readout_max) * int(n_exposure)))
    if motion is None:
        size = kwargs.get("size") or scene.shape[:2]
        motion = {k: v * (1.0 + float(readout_max)) for k, v in shake_for(size).items()}
    plan = plan_pair(scene, motion=dict(motion, n_sub=n_total), **kwargs)
    fields = {f.name: getattr(plan, f.name) for f in dataclasses.fields(PairPlan)}
    info = dict(plan.info, readout=float(readout), readout_max=float(readout_max),
                n_exposure=int(n_exposure),
                rolling="row y integrates [r y / H, r y / H + 1] exposures of the path")
    fields["info"] = info
    return RollingPlan(**fields, readout=float(readout), n_exposure=int(n_exposure))


def make_rolling_pair(scene: Any, *, readout: float, **kwargs: Any) -> RealismPair:
    """An in-memory rolling-shutter pair (see :func:`plan_rolling_pair`), tile by tile.

    Returns
    -------
    RealismPair
        ``homographies`` holds the whole path; ``info["readout"]`` and
        ``info["n_exposure"]`` say which sub-poses each row integrates.
    """
    plan = plan_rolling_pair(scene, readout=readout, **kwargs)
    return pair_from_plan(plan)
