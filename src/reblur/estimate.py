"""Estimate the camera motion (pose weights) and the change term from observation windows."""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
from threadpoolctl import threadpool_limits

from .grid import PoseGrid
from .operator import BlurOperator
from .result import MotionEstimate
from .solve import active_set, fista
from .warp import as_box, read_window

__all__ = ["estimate_motion", "intensity_scale", "soft_threshold"]


def intensity_scale(dtype) -> float:
    """Full-scale value of a dtype: 255 for uint8, 65535 for uint16, 1 for floats."""
    dt = np.dtype(dtype)
    if dt.kind in "ui":
        return float(np.iinfo(dt).max)
    return 1.0


def soft_threshold(x: np.ndarray, t: float) -> np.ndarray:
    """``sign(x) * max(|x| - t, 0)``."""
    return np.sign(x) * np.maximum(np.abs(x) - t, 0.0)


def _check_pair(reference, observed) -> tuple[int, int]:
    for name, a in (("reference", reference), ("observed", observed)):
        if len(a.shape) not in (2, 3):
            raise ValueError(f"{name} must be (H, W) or (H, W, C), got shape {a.shape}")
        if min(a.shape[:2]) < 2:
            raise ValueError(f"{name} is too small: {a.shape}")
    cr = reference.shape[2] if len(reference.shape) == 3 else 1
    co = observed.shape[2] if len(observed.shape) == 3 else 1
    if cr != co:
        raise ValueError(f"reference has {cr} bands and observed {co}: reconcile them first")
    return cr, co


def estimate_motion(
    reference,
    observed,
    grid: PoseGrid | None = None,
    *,
    lam: float = 0.1,
    occlusion: bool = True,
    boxes: Sequence | None = None,
    base: np.ndarray | None = None,
    engine: str = "auto",
    solver: str = "active-set",
    scale: float | None = None,
    max_outer: int = 60,
    time_limit: float | None = None,
    fista_iter: int = 500,
) -> MotionEstimate:
    """Estimate pose weights ``w >= 0`` and the change term ``chi`` (eq. 5, or eq. 3).

    Parameters
    ----------
    reference : array-like, (H, W) or (H, W, C)
        Sharp reference (numpy or any sliceable array such as zarr); only the windows the
        estimation needs are read.
    observed : array-like, (H', W') or (H', W', C)
        Blurred observation, same band count.
    grid : PoseGrid, optional
        Pose grid on the observation's full geometry.  Default: the paper's 8125-pose grid.
    lam : float
        Eq. 5's ``lambda`` for intensities scaled to [0, 1]; the change term is
        ``chi = soft(g - F w, lam / 2)``.
    occlusion : bool
        Solve eq. 5 (changes present) or eq. 3 (no change term).
    boxes : sequence of (y0, x0, h, w), optional
        Estimation windows in observation coordinates, sharing one set of weights.
        Default: the whole observation.
    base : (3, 3) ndarray, optional
        Coarse alignment (reference -> observation) composed before every pose.
    engine : {"auto", "fast", "exact"}
        Operator engine (see :class:`reblur.operator.BlurOperator`).
    solver : {"active-set", "fista"}
        ``fista`` is the slow cross-check (single window only).
    scale : float, optional
        Intensity full scale; default from the dtype (255 for uint8, 65535 for uint16, 1 for
        floats).
    max_outer, time_limit, fista_iter
        Solver limits.

    Returns
    -------
    MotionEstimate
        ``weights`` (``grid.shape``), ``chi`` per window (observation units scaled to [0, 1]),
        ``boxes`` and ``info`` (objective history, ``psnr`` of the fit per window, timing).

    Examples
    --------
    >>> import numpy as np
    >>> from reblur import PoseGrid, estimate_motion
    >>> rng = np.random.default_rng(0)
    >>> f = rng.random((96, 96))
    >>> grid = PoseGrid((96, 96), tx=range(-2, 3), ty=range(-2, 3))
    >>> g = (f + np.roll(f, 1, axis=1)) / 2          # blur: half at tx=0, half at tx=1
    >>> est = estimate_motion(f, g, grid, boxes=[(8, 8, 80, 80)], occlusion=False, lam=1e-4)
    >>> np.round(est.weights[0, 2, 2:4], 2)
    array([0.5, 0.5])
    """
    t0 = time.perf_counter()
    _check_pair(reference, observed)
    if grid is None:
        grid = PoseGrid.paper(observed.shape[:2])
    if tuple(grid.image_shape) != tuple(observed.shape[:2]):
        raise ValueError(
            f"grid geometry {grid.image_shape} does not match the observation {observed.shape[:2]}"
        )
    if not lam > 0:
        raise ValueError(f"lam must be positive, got {lam}")
    if boxes is None:
        boxes = [(0, 0, observed.shape[0], observed.shape[1])]
    boxes = [as_box(b) for b in boxes]
    s_ref = intensity_scale(reference.dtype) if scale is None else scale
    s_obs = intensity_scale(observed.dtype) if scale is None else scale
    two_d = len(observed.shape) == 2
    with threadpool_limits(1, user_api="blas"):
        ops, gs = [], []
        for b in boxes:
            ops.append(BlurOperator(reference, grid, b, base=base, engine=engine, scale=s_ref))
            gs.append(read_window(observed, b, np.float64) / s_obs)
        if not any(op.valid.any() for op in ops):
            raise ValueError(
                "no estimation window is covered by the reference for every pose: "
                "align the images first or use a smaller pose grid"
            )
        if solver == "active-set":
            w, info = active_set(
                ops, gs, lam=lam, occlusion=occlusion, max_outer=max_outer,
                time_limit=time_limit,
            )
        elif solver == "fista":
            if len(ops) != 1:
                raise ValueError("the FISTA cross-check takes a single window")
            w, _, info = fista(ops[0], gs[0], lam=lam, n_iter=fista_iter)
        else:
            raise ValueError(f"solver must be 'active-set' or 'fista', got {solver!r}")
        chis, psnrs = [], []
        for op, g in zip(ops, gs, strict=True):
            fit = op.matvec(w)
            r = g - fit
            m = op.valid
            chi = soft_threshold(r, lam / 2.0) if occlusion else np.zeros_like(r)
            chi[~m] = 0.0
            chis.append(chi[:, :, 0] if two_d else chi)
            mse = float(np.mean(r[m] ** 2)) if m.any() else np.nan
            psnrs.append(10 * np.log10(1.0 / mse) if mse > 0 else np.inf)
    info = dict(info)
    info.update(
        psnr=psnrs, lam=lam, occlusion=occlusion, engine=ops[0].engine,
        time_total_s=time.perf_counter() - t0,
        valid_fraction=[float(op.valid.mean()) for op in ops],
    )
    return MotionEstimate(
        weights=w, grid=grid, chi=chis, boxes=[b.as_tuple() for b in boxes], info=info
    )
