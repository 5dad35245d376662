"""Estimate the camera motion (pose weights) and the change term from observation windows."""

from __future__ import annotations

import os
import time
from collections.abc import Sequence

import numpy as np
from threadpoolctl import threadpool_limits

from ._bands import BandMean
from ._memory import available_cpus, small_pages, thread_map
from .grid import PoseGrid, carry_weights, edge_share, widen_translations
from .io import ChunkCache, tile_chunks
from .operator import BlurOperator
from .result import MotionEstimate
from .robust import huber_line, mad
from .solve import Scratch, active_set, check_max_active, fista
from .tiled import SparsePoses, reblur_tile
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


#: Default ``rtol`` of :func:`estimate_motion`'s solves.  On pairs the model fits (the
#: demo, the test bed's shaken LEVIR pair) the outer iterations that lower the objective
#: by less than this are the last one or two before the KKT test ends the solve anyway;
#: on a years-apart WHU pair the solves ran 10-16 outer iterations of 300-400 poses
#: below it (1.5e-4 down to 1e-8 each).
RTOL = 1e-4

#: ``rtol`` of the coarse-to-fine schedule's last level, at least: the full windows,
#: started from the central parts' weights (see :data:`_FINE_ON_CENTRES`).  On long real
#: shakes that level is most of the estimate: it keeps few of the central parts' poses
#: (GoPro GOPR0477 frame 13 against the mean of 16 frames, at ``RTOL``: 16 of its final
#: 157), and its tail of outer iterations each lowers the objective by 1e-4 to 1e-3 while
#: the active set grows by 3-8 of the 24 poses each adds.  Against ``RTOL`` (``reblur
#: detect``, the two alternated, ``motion.info.levels`` of ``report.json``), the mean of
#: 8 / 12 / 16 frames: estimate 4.4 / 6.2 / 6.9-7.0 -> 3.1-3.2 / 3.6 / 4.3-4.4 s, the
#: windows' reblur within 0.05 dB; GoPro 0374 2.9 -> 2.6-2.8 s; 1 Gpx unchanged (its last
#: level ends on the KKT test: ``python -m benchmarks.large_motion --case 32000``).
FINE_RTOL = 1e-3

#: Poses a solve's active set may hold (``estimate_motion(max_active=)``).  A camera
#: shake's weights lie along a path through the pose grid: at most 294 poses in a level
#: for the test bed's 35 px shake (``python -m benchmarks.shake_extent``), 122 for GoPro
#: 0477 against 16 frames, 456 for the out-of-plane tilt pair (a blur the grid cannot
#: follow; ``motion.info.levels`` of ``report.json``).  A dense blur fills an area
#: instead: ``benchmarks.cost``'s ``defocus`` pair (a 10 px pillbox, 1 MP) held 449-815,
#: and its Gram products (square of the poses) and NNLS (cube) took its estimate to
#: 17.6-17.8 s, 9.0-9.9 s under this bound, the fits 0.03-0.05 dB lower.
MAX_ACTIVE = 640


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
    rtol: float = RTOL,
    fine_rtol: float = FINE_RTOL,
    time_limit: float | None = None,
    fista_iter: int = 500,
    coarse_to_fine: bool | str = "auto",
    max_bases: int = 16,
    refit_photometry: bool = False,
    threads: int | None = None,
    stop_occluded: float | None = None,
    resume: dict | None = None,
    bands: str = "all",
    t_grow: int = 1,
    blur_reach: float = 0.0,
    max_active: int | None = MAX_ACTIVE,
) -> MotionEstimate:
    """Estimate pose weights ``w >= 0`` and the change term ``chi`` (eq. 5, or eq. 3).

    Parameters
    ----------
    reference : array-like, (H, W) or (H, W, C)
        Sharp reference (numpy or any sliceable array such as zarr); only the windows the
        estimation needs are read.
    observed : array-like, (H', W') or (H', W', C)
        Blurred observation, same band count.  When it has an ``exclude`` attribute (a
        callable ``exclude(box) -> (h, w) bool``, e.g. a large change seen at low
        resolution), those pixels are left out of the data term and reported as change
        (``chi`` is the whole residual there).
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
        Solver limits (``max_outer``: outer iterations per solve, i.e. per
        coarse-to-fine level and per photometric round).
    rtol : float
        Each solve stops when an outer iteration lowered its objective by less than this
        fraction (:func:`reblur.solve.active_set`'s ``rtol``): on windows the model does
        not fit, the active set otherwise grows for tens of iterations of hundreds of
        poses for gains of 1e-4 to 1e-6.  0: the KKT test alone.
    fine_rtol : float
        ``rtol`` of the coarse-to-fine schedule's last level (the full windows, from the
        central parts' weights), at least ``rtol``: :data:`FINE_RTOL` by default.
    coarse_to_fine : bool or "auto"
        Solve on a subset of the roll angles first (at most ``max_bases``, evenly spread),
        then refine, level by level with a quarter of the angle stride, only around the
        angles that carry at least 1 % of the heaviest angle's weight (within one old
        stride of them), warm-starting each level; the result lives on the full ``grid``.
        A level whose angle stride moves the far windows by ``s`` pixels also keeps only
        every ``ts``-th translation (``ts`` the largest power of two <= ``s / 4``, at most a
        quarter of the translation range): finer shifts cannot be told apart there.
        Levels before the last solve on the windows' central :func:`coarse_side` pixels;
        at the finest stride those are solved first and the full windows then start from
        their solution (:data:`_FINE_ON_CENTRES`).  Where the first level's translations
        reach :data:`HALF_MIN_T` px and its parts are at least twice
        :data:`HALF_MIN_SIDE`, it is solved at half resolution (:data:`HALF_START`).
        ``info["levels"]`` lists the levels (with the solver's ``warm_start`` record where
        a level starts from weights, and ``resolution`` 0.5 on a half-resolution one,
        whose ``t_max`` is in full-resolution pixels and ``side`` in its own).
        ``"auto"``: when the grid varies only ``rz`` and has more than ``max_bases`` angles.
        This keeps fine rotation grids (a step that moves the farthest pixel of a huge
        image by one pixel) affordable.
    max_bases : int
        Angles per coarse-to-fine level.
    refit_photometry : bool
        After the solve, remove the per-band offset between the observation and the
        reblurred reference that the weights cannot represent (they carry a gain in their
        sum, not an offset): secant rounds on the intercept of a Huber line over the
        windows' inliers, each solving again from the weights found, until it is below
        1e-4.  A photometric pre-match made before the motion is known (low resolution,
        sharp against blurred, changes included) leaves an offset of a few thousandths;
        the weights then bend to absorb it and reproduce the blur wrong far from the
        windows (``benchmarks/outskirts.py``, noise-free: corner windows 50-54 dB without,
        61-65 dB with).  ``info["photometry"]`` holds the ``offset`` removed (per band,
        ``g ~ F w + offset``) and the ``rounds``; ``chi`` is then in the corrected units.
    threads : int, optional
        Threads of the estimate; default the CPUs available to the process, at most
        :data:`MAX_BLAS_THREADS` and at most ``OPENBLAS_NUM_THREADS`` or
        ``OMP_NUM_THREADS`` when set.  With several windows they split the windows: each
        thread builds its share of the operators and runs the solver's per-window steps
        for them (``active_set(workers=)``), BLAS, OpenCV and the operators' products
        single-threaded inside.  With one window they go to its products instead: FFTs
        and the sums of columns (:meth:`BlurOperator.combine`); the solver's BLAS stays
        on one thread (its threaded sums would round with the number of cores).  The
        estimate runs while nothing else does (the tiles wait for its weights), so it may
        use the cores (docs/NOTES.md, "Eighth stop", for the gain on 2 cores).
    stop_occluded : float, optional
        With coarse-to-fine: after the first level, if a window's part came out more than
        this fraction change (the paper's rejection rule, 2/3), stop there.  The result
        then holds that level's weights, ``boxes`` and ``chi`` of the parts solved,
        ``info["stopped_early"] = True`` and ``info["resume"]`` to finish it later.  The
        first level predicts the final fraction closely (on a years-apart WHU pair 0.40 /
        0.74 after it, 0.41 / 0.74 at the end), for a fraction of the cost.
    resume : dict, optional
        ``info["resume"]`` of an estimate stopped early on the same ``boxes`` (same grid,
        base and scales): the levels continue from its weights instead of starting over.
    bands : {"all", "mean"}
        What the weights are solved on for images of several bands.  ``"all"``: every
        band, eq. 5 summed over them.  ``"mean"``: the band mean of the reference and of
        the observation (one band: the solver's products, the costliest part of the
        estimate, cost a third for RGB).  The blur is the same in every band and linear,
        so the band mean of the observation is the blur of the reference's band mean;
        what is lost is texture that only colour shows (an edge between two colours of
        equal mean).  The change term, the fit's figures (``psnr``, ``occluded``) and the
        photometric ``offset`` are then computed per band with the weights found, so the
        result has the same form as with ``"all"``; ``info["bands"]`` says which was used.
    t_grow : int
        How far the translations may widen, a factor of the grid's (1, default: the grid
        as given).  When the first solve (the first coarse-to-fine level) puts at least
        :data:`T_EDGE_SHARE` of the weight on the grid's outermost translations, the blur
        may reach beyond them: the grid's symmetric translation axes are made twice as
        wide (:func:`reblur.grid.widen_translations`) and that solve runs again from its
        weights; the wider grid is kept when it lowers the loss per valid pixel by at
        least :data:`MIN_WIDEN_GAIN` (a pose on the edge that belongs there, or the
        spread of a pair whose content changed, gains nothing), and tried wider again
        while the widest translation stays within ``t_grow`` times the grid's and a
        quarter of the smallest window's side, and the grid within
        :data:`MAX_WIDENED_POSES` (:func:`_widen_first`).  The result then lives on the
        wider grid (``MotionEstimate.grid``).  ``info["translations"]`` holds the range
        started from and ended on, each check (``t_max``, ``edge_share``, ``gain``,
        ``outcome``) and the edge share of the final weights (and ``blur_reach``, when
        given).
    blur_reach : float
        A radius (px) the blur is known to reach beyond: the kernel polish of the coarse
        alignment failed at the shake extent below the one it verified
        (:func:`reblur.pipeline.blur_reach`).  With ``t_grow > 1``, the translations start
        doubled while narrower than it, within the limits of the checks above (which go on
        from there, within the growth left): a first solve on a grid the blur is known to
        exceed is a misfit whose hundreds of poses cost more than the wider solve, and
        the optimum the later levels reach is the same (test-bed shakes of 20 and 35 px,
        32 px for their alignment: estimate 9.4 -> 8.0 and 8.3 -> 6.3 s, the same
        masks; ``python -m benchmarks.shake_extent``).  Each doubling is a check of
        outcome ``"reach"``.  0 (default): start from the grid given.  Not with
        ``resume``.
    max_active : int, optional
        Poses each solve's active set may hold (:func:`reblur.solve.active_set`'s
        ``max_active``; default :data:`MAX_ACTIVE`; None: no bound).  A solve that fills
        it stops there; ``info["capped"]`` counts such solves (each level's record says
        whether it was one).

    Returns
    -------
    MotionEstimate
        ``weights`` (``grid.shape``), ``chi`` per window (observation units scaled to [0, 1]),
        ``boxes`` and ``info`` (objective history, ``psnr`` of the fit per window,
        ``occluded``: the share of each window's valid pixels with a non-zero change
        term, ``n_outer``: the outer iterations of every solve together, ``windows``: the
        windows asked for, timing).

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
    only_rz = len(grid.tz) == len(grid.rx) == len(grid.ry) == 1
    if coarse_to_fine == "auto":
        coarse_to_fine = only_rz and grid.n_bases > max_bases and solver == "active-set"
    if refit_photometry and solver != "active-set":
        raise ValueError("refit_photometry needs solver='active-set'")
    if coarse_to_fine and not only_rz:
        raise ValueError("coarse_to_fine refines the roll axis only: use a grid varying rz alone")
    if resume is not None and not coarse_to_fine:
        raise ValueError("resume continues a coarse-to-fine estimate: coarse_to_fine is off")
    check_bands(bands)
    reference = _cached_reads(reference)
    on_mean = bands == "mean" and not two_d and int(observed.shape[2]) > 1
    ref_bands, obs_bands = reference, observed
    if on_mean:
        reference, observed = BandMean(reference), BandMean(observed)
    levels = []
    scratch = Scratch()  # the solver's work memory, shared by every solve below
    if threads is None:
        threads = _default_threads()
    if int(threads) < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    for name, v in (("rtol", rtol), ("fine_rtol", fine_rtol)):
        if isinstance(v, bool) or not (isinstance(v, (int, float, np.number)) and 0 <= v < 1):
            raise ValueError(f"{name} must lie in [0, 1), got {v!r}")
    if isinstance(t_grow, bool) or not isinstance(t_grow, (int, np.integer)) or t_grow < 1:
        raise ValueError(f"t_grow must be an integer >= 1, got {t_grow!r}")
    if isinstance(blur_reach, bool) or not (
            isinstance(blur_reach, (int, float, np.number)) and 0 <= blur_reach < np.inf):
        raise ValueError(f"blur_reach must be a finite number >= 0, got {blur_reach!r}")
    check_max_active(max_active)
    start, log = grid, []
    if t_grow > 1 and blur_reach > 0 and solver == "active-set" and resume is None:
        grid, t_grow = _widen_to_reach(grid, boxes, int(t_grow), float(blur_reach), log)
    with threadpool_limits(int(threads), user_api="blas"), small_pages():
        if coarse_to_fine:
            w, info, ops, gs, grid_used, grid = _rz_coarse_to_fine(
                reference, observed, grid, boxes, base, engine, s_ref, s_obs, lam, occlusion,
                max_outer, time_limit, max_bases, levels, scratch, threads=int(threads),
                rtol=rtol, fine_rtol=max(rtol, fine_rtol), stop_occluded=stop_occluded,
                resume=resume, t_grow=int(t_grow), log=log, max_active=max_active,
            )
        else:
            def solve(sub, w0):
                out = _solve(reference, observed, sub, boxes, base, engine, s_ref, s_obs,
                             lam, occlusion, solver, max_outer, time_limit, fista_iter, w0,
                             scratch=scratch, threads=int(threads), rtol=rtol,
                             max_active=max_active)
                if solver == "active-set":  # the history over every solve (FISTA: one)
                    spent["objective"] += list(out[1]["objective"])
                    spent["n_outer"] += int(out[1]["n_outer"])
                    spent["time_s"] += float(out[1]["time_s"])
                    spent["capped"] += int(bool(out[1].get("capped")))
                return out

            spent = dict(objective=[], n_outer=0, time_s=0.0, capped=0)
            w, info, ops, gs = solve(grid, None)
            if t_grow > 1 and solver == "active-set":
                grid, (_, w, info, ops, gs) = _widen_first(
                    grid, 1, (grid, w, info, ops, gs), solve,
                    _t_limit(grid, boxes, int(t_grow)), log)
                info = {**info, **spent}
            grid_used = grid
        stopped = bool(info.get("stopped_early", False))
        if refit_photometry and not stopped:
            w, info, gs = _refit_photometry(ops, gs, w, info, lam, occlusion, max_outer,
                                            time_limit, scratch=scratch, rtol=rtol,
                                            max_active=max_active)
        if on_mean:
            resid = _band_residuals(ref_bands, obs_bands, ops, w, grid_used, base, s_ref,
                                    s_obs, info, threads=int(threads))
        else:
            resid = [g - op.matvec(w) for op, g in zip(ops, gs, strict=True)]
        chis, psnrs, psnr_in, occluded = [], [], [], []
        for op, r in zip(ops, resid, strict=True):
            m = op.valid
            chi = soft_threshold(r, lam / 2.0) if occlusion else np.zeros_like(r)
            chi[~m] = 0.0
            ex = getattr(op, "excluded", None)
            if ex is not None and ex.any():  # left out as a known change: all of it is
                chi[ex] = r[ex]
            chis.append(chi[:, :, 0] if two_d else chi)
            psnrs.append(_psnr(r[m]))
            inl = m[:, :, None] & (chi == 0)
            psnr_in.append(_psnr(r[inl]))
            occluded.append(_occluded_share(chi, m))
        windows = [b.as_tuple() for b in boxes]
        if stopped:  # the parts the first level solved
            boxes = [op.box for op in ops]
        if grid_used is not grid:
            w = carry_weights(w, grid_used, grid)
    info = dict(info)
    info["capped"] = int(info.get("capped", 0))  # solves stopped by max_active
    info["max_active"] = max_active
    info["translations"] = _widening_info(start, grid, log, w)
    if blur_reach > 0:
        info["translations"]["blur_reach"] = float(blur_reach)
    info.update(
        psnr=psnrs, psnr_inliers=psnr_in, lam=lam, occlusion=occlusion, engine=ops[0].engine,
        time_total_s=time.perf_counter() - t0,
        valid_fraction=[float(op.valid.mean()) for op in ops], levels=levels,
        occluded=occluded, stopped_early=stopped, windows=windows,
        bands="mean" if on_mean else "all",
    )
    excluded = [op.excluded for op in ops if getattr(op, "excluded", None) is not None]
    if excluded:
        info["excluded_fraction"] = [float(e.mean()) for e in excluded]
    return MotionEstimate(
        weights=w, grid=grid, chi=chis, boxes=[b.as_tuple() for b in boxes], info=info,
        excluded=excluded if any(e.any() for e in excluded) else [],
    )


def check_bands(bands, name: str = "bands") -> None:
    """ValueError unless ``bands`` is ``"mean"`` or ``"all"`` (:func:`estimate_motion`'s
    ``bands``; ``name`` is the option's name in the message)."""
    if bands not in ("all", "mean"):
        raise ValueError(f"{name} must be 'mean' or 'all', got {bands!r}")


def _band_residuals(reference, observed, ops, w, grid, base, s_ref, s_obs, info, threads):
    """Per band, the residual ``g - offset - F w`` on the window of each operator of
    ``ops`` (solved on the band mean), from ``reference`` and ``observed`` with their
    bands; ``info["photometry"]["offset"]`` (the band mean's) becomes one per band.

    ``F w`` is the reblur of the window with the poses that carry weight
    (:func:`reblur.tiled.reblur_tile`): one warp per base pose with weight, its
    translations added in place, nothing held per pose (an operator of the poses' span
    held a float32 stack of every base: 112 MB for a 500 px RGB window of 34 angles, on
    GoPro 0374).  Pixels the solve left out (``op.valid`` False) keep their residual (the
    known changes are reported whole); non-finite values of either image read as 0
    there, as in the solve.
    """
    poses = SparsePoses(w, grid, base)
    C = int(observed.shape[2])
    photo = info.get("photometry")
    offset = 0.0
    if photo is not None:
        offset = float(np.asarray(photo["offset"], float).ravel()[0])
        photo["offset"] = [offset] * C

    def residual(op):
        fit, _ = reblur_tile(poses, reference, op.box, dtype=np.float32)
        fit = np.where(np.isfinite(fit), fit, np.float32(0.0)).astype(np.float64)
        if s_ref != 1.0:
            fit /= s_ref
        g = read_window(observed, op.box, np.float64) / s_obs
        g = np.where(np.isfinite(g), g, 0.0)
        return g - offset - fit

    return thread_map(residual, ops, threads)


def _occluded_share(chi: np.ndarray, valid: np.ndarray) -> float:
    """Share of the ``valid`` pixels whose change term ``chi`` (h, w, C) is non-zero in
    some band."""
    n = int(valid.sum())
    if n == 0:
        return 1.0
    return float(((chi != 0).any(axis=2) & valid).sum() / n)


#: Bytes of reference chunks an estimate keeps (:func:`_cached_reads`).
_READ_CACHE_BYTES = 256 * 2**20
#: Chunk size (px) of the reads of a lazy reference that has no tile-like chunks.
_READ_CHUNK = 256


def _cached_reads(reference):
    """A lazily read ``reference`` behind a :class:`~reblur.io.ChunkCache` for the estimate.

    The coarse-to-fine levels read overlapping regions around each window (the first two
    levels the reach of the whole roll range, ~1.7k px square for a 128 px part at 1 Gpx;
    the last level the reach of its angles around the full window): through the cache,
    each chunk of the reference is read and decoded once.  The chunks are the array's own
    when they are tiles, else :data:`_READ_CHUNK` px squares.  numpy arrays (and readers
    already cached) are returned as they are: slicing them is free.
    """
    if isinstance(reference, (np.ndarray, ChunkCache)):
        return reference
    chunks = tile_chunks(reference) or (_READ_CHUNK, _READ_CHUNK)
    return ChunkCache(reference, max_bytes=_READ_CACHE_BYTES, chunks=chunks)


#: Default cap on the solver's BLAS threads (:func:`estimate_motion`): its products are
#: blocks of 32768 pixels times a few hundred columns, small enough that many threads
#: mostly wait (measured on 2 cores only).
MAX_BLAS_THREADS = 4


def _default_threads() -> int:
    """The CPUs available to the process, capped by :data:`MAX_BLAS_THREADS` and by the
    usual environment limits (the first of ``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS``
    that holds a positive integer)."""
    n = min(available_cpus(), MAX_BLAS_THREADS)
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
        v = os.environ.get(var, "").strip()
        if v.isdigit() and int(v) > 0:
            return min(n, int(v))
    return n


def _psnr(r: np.ndarray) -> float:
    if r.size == 0:
        return float("nan")
    mse = float(np.mean(r * r))
    return 10 * np.log10(1.0 / mse) if mse > 0 else float("inf")


#: Share of the weight on the pose grid's outermost translations
#: (:func:`reblur.grid.edge_share`) from which an estimate's first solve tries them twice
#: as wide (``t_grow``).  A blur the grid holds leaves none there (the cost pairs of
#: ``benchmarks.cost``, LEVIR test_12); real hand-held shake put 10 % (GoPro 0384) and
#: 62 % (0374) on the paper's 12 px, a test-bed shake of 20 px 65 %; a years-apart pair's
#: misfit 2-8 %.
T_EDGE_SHARE = 0.05
#: Least relative drop of the first solve's loss per valid pixel for which the wider
#: translations are kept (:func:`_widen_first`): a blur beyond the grid fits far better
#: on the wider one (GoPro 0374 55 %, the test bed's 20 px shake 83 %), while a pose
#: on the edge that belongs there (0384: 0.001 %) or a misfit of changed content that
#: merely spreads (LEVIR test_102, years-apart LEVIR: 0.07-0.14 %) gains nothing.
MIN_WIDEN_GAIN = 0.05
#: Poses a widened grid may hold (a float64 weight array of 64 MiB): the coarse-to-fine
#: levels hold whole-grid weight arrays, and a gigapixel image's roll step is fine.
MAX_WIDENED_POSES = 2**23


def _t_max(grid: PoseGrid) -> float:
    return float(max(abs(v) for v in grid.tx + grid.ty))


def _t_limit(grid: PoseGrid, boxes, t_grow: int) -> float:
    """The widest translation (px) an estimate on ``boxes`` may widen ``grid`` to:
    ``t_grow`` times the grid's, and a quarter of the smallest window's side (a wider
    shift leaves little of a window that every pose covers)."""
    return min(_t_max(grid) * t_grow, min(min(b.h, b.w) for b in boxes) / 4.0)


def _mean_loss(info: dict, ops) -> float:
    """A solve's final objective per valid pixel of its windows (the wider translations
    cover fewer pixels of a window near the image's border)."""
    n = sum(int(np.count_nonzero(op.valid)) for op in ops)
    return float(info["objective"][-1]) / max(n, 1)


def _widened(grid: PoseGrid, t_limit: float) -> PoseGrid | None:
    """``grid`` with translations twice as wide, or None beyond ``t_limit`` px or
    :data:`MAX_WIDENED_POSES` poses (or when no axis can widen)."""
    wider = widen_translations(grid)
    if wider is None or wider.size > MAX_WIDENED_POSES or _t_max(wider) > t_limit:
        return None
    return wider


def _widen_to_reach(grid: PoseGrid, boxes, t_grow: int, reach: float,
                    log: list) -> tuple[PoseGrid, int]:
    """``grid``'s translations doubled while narrower than ``reach`` px (within the
    limits of :func:`_widen_first` for ``t_grow``), one ``"reach"`` record in ``log`` per
    doubling.  Returns the grid and the growth factor left to the checks: the widest
    translation they may reach stays ``t_grow`` times ``grid``'s."""
    t_limit = _t_limit(grid, boxes, t_grow)
    while t_grow >= 2 and _t_max(grid) < reach:
        wider = _widened(grid, t_limit)
        if wider is None:
            break
        log.append(dict(t_max=_t_max(grid), outcome="reach"))
        grid, t_grow = wider, t_grow // 2
    return grid, t_grow


def _widen_first(grid: PoseGrid, ts: int, first: tuple, solve, t_limit: float,
                 log: list) -> tuple:
    """The first solve of an estimate on translations twice as wide, as long as it pays.

    ``first`` is ``(sub, w, info, ops, gs)``: that solve's grid (``grid``'s bases and
    every ``ts``-th of its translations), its weights, info, operators and windows.
    While the weights put at least :data:`T_EDGE_SHARE` on ``sub``'s outermost
    translations, ``grid`` is widened (:func:`reblur.grid.widen_translations`, within
    ``t_limit`` px and :data:`MAX_WIDENED_POSES` poses) and ``solve(sub, w0)`` solves the
    same windows on its translations from the weights found; the wider grid is kept when
    it lowers the loss per valid pixel by at least :data:`MIN_WIDEN_GAIN`.  ``log`` gets
    one record per check (``t_max``, ``edge_share``, ``outcome``: ``"clear"``,
    ``"limit"``, ``"no gain"`` or ``"widened"``, and the ``gain`` of a wider solve).
    Returns the grid kept and the ``first`` tuple of its solve.
    """
    while True:
        sub, w, info, ops, _ = first
        share = edge_share(w, sub)
        rec = dict(t_max=_t_max(sub), edge_share=round(share, 4))
        log.append(rec)
        if share < T_EDGE_SHARE:
            rec["outcome"] = "clear"
            return grid, first
        wider = _widened(grid, t_limit)
        if wider is None:
            rec["outcome"] = "limit"
            return grid, first
        x0 = wider.tx.index(min(wider.tx, key=abs))
        y0 = wider.ty.index(min(wider.ty, key=abs))
        part = PoseGrid(wider.image_shape, rz=sub.rz, center=wider.center,
                        tx=[v for i, v in enumerate(wider.tx) if (i - x0) % ts == 0],
                        ty=[v for i, v in enumerate(wider.ty) if (i - y0) % ts == 0])
        w2, info2, ops2, gs2 = solve(part, carry_weights(w, sub, part))
        gain = 1.0 - _mean_loss(info2, ops2) / max(_mean_loss(info, ops), 1e-300)
        rec["gain"] = round(gain, 4)
        if not gain >= MIN_WIDEN_GAIN:
            rec["outcome"] = "no gain"
            return grid, first
        rec["outcome"] = "widened"
        grid, first = wider, (part, w2, info2, ops2, gs2)


def _widening_info(start: PoseGrid, grid: PoseGrid, log: list, w: np.ndarray) -> dict:
    """``info["translations"]``: the range the estimate started from and ended on, the
    checks of :func:`_widen_first`, and the edge share of the final weights."""
    return dict(t_max_start=_t_max(start), t_max=_t_max(grid), checks=log,
                edge_share=round(edge_share(w, grid), 4))


#: The solver fits every ``k``-th row of the windows (``active_set(row_step=k)``), ``k``
#: the largest up to :data:`MAX_ROW_STEP` that leaves every window at least
#: :data:`ROW_SAMPLE_PIXELS` of its pixels and half that many of its valid ones
#: (:func:`row_step`): 2 on the coarse levels' 256 px central parts, 4 on 500 px windows.
#: The solver's products (the Gram blocks, the forward sums, the line searches) scale with
#: the pixels fitted, while a few hundred weights are as well determined by a quarter of a
#: 500 px window's rows as by all of them: the rows keep the window's extent, whose spread
#: is what makes the weights observable (a smaller window loses it:
#: ``benchmarks.window_side``).  1 MP pairs (``python -m benchmarks.gram_work``, against
#: every row, with the row views' phase adjoint): estimate 1.2-1.9x faster; GoPro reblur
#: PSNR, the realism matrix at 1 / 4 / 25 MP, Fig. 6 and the failure modes within 0.05 dB
#: / 0.001 JC (docs/NOTES.md).
MAX_ROW_STEP = 4
#: See :data:`MAX_ROW_STEP`: a 181 px square window's pixels.
ROW_SAMPLE_PIXELS = 2**15


def row_step(ops) -> int:
    """The row step of a solve on the windows of the operators ``ops`` (see
    :data:`MAX_ROW_STEP`); 1 where a window holds few valid pixels (the data left after
    exclusions and no data are all that is fitted there) and for operators that cannot be
    restricted to rows (no ``rows`` method)."""
    if not all(hasattr(op, "rows") for op in ops):
        return 1
    k = MAX_ROW_STEP
    for op in ops:
        k = min(k, op.box.h * op.box.w // ROW_SAMPLE_PIXELS,
                int(np.count_nonzero(op.valid)) // (ROW_SAMPLE_PIXELS // 2))
    return int(max(1, k))


def _solve(reference, observed, grid, boxes, base, engine, s_ref, s_obs, lam, occlusion,
           solver, max_outer, time_limit, fista_iter, w0, gs=None, scratch=None, threads=None,
           rtol=0.0, max_active=None, pixel_weight=1.0):
    ops = _build_operators(reference, grid, boxes, base, engine, s_ref, threads)
    if gs is None:
        gs = [read_window(observed, b, np.float64) / s_obs for b in boxes]
    gs = _exclude(ops, boxes, getattr(observed, "exclude", None), gs)
    if not any(op.valid.any() for op in ops):
        raise ValueError(
            "no estimation window is covered by the reference for every pose: "
            "align the images first or use a smaller pose grid"
        )
    if solver == "active-set":
        w, info = active_set(
            ops, gs, lam=lam, occlusion=occlusion, max_outer=max_outer, time_limit=time_limit,
            w0=w0, scratch=scratch, workers=1 if threads is None else threads, rtol=rtol,
            row_step=row_step(ops), max_active=max_active, pixel_weight=pixel_weight,
        )
    elif solver == "fista":
        if len(ops) != 1:
            raise ValueError("the FISTA cross-check takes a single window")
        w, _, info = fista(ops[0], gs[0], lam=lam, n_iter=fista_iter)
    else:
        raise ValueError(f"solver must be 'active-set' or 'fista', got {solver!r}")
    return w, info, ops, gs


#: Pixels (all windows together) :func:`_exclude` must leave for the exclusion to apply.
_MIN_KEPT = 256


def _exclude(ops, boxes, exclude, gs) -> list[np.ndarray]:
    """Leave the pixels ``exclude(box)`` out of each window's data term (``op.valid``);
    ``op.excluded`` keeps them (the estimate reports them as change).  Where the exclusion
    would leave fewer than :data:`_MIN_KEPT` pixels in all the windows together (a patch
    inside the known change), it does not apply: they are fitted as they are and the
    window selection judges them.  No-data (non-finite) pixels of the observation windows
    ``gs`` are left out too; returns the windows with them set to 0 (copies: the caller's
    arrays keep their NaN for the next level)."""
    exs = [np.zeros_like(op.valid) if exclude is None else np.asarray(exclude(b), bool)
           for op, b in zip(ops, boxes, strict=True)]
    if sum(int(np.count_nonzero(op.valid & ~ex)) for op, ex in zip(ops, exs, strict=True)) \
            < _MIN_KEPT:
        exs = [np.zeros_like(op.valid) for op in ops]
    out = []
    for op, ex, g in zip(ops, exs, gs, strict=True):
        op.excluded = ex & op.valid
        op.valid = op.valid & ~ex
        fin = np.isfinite(g)
        if not fin.all():
            g = np.where(fin, g, 0.0)
            op.valid &= fin.all(axis=2) if fin.ndim == 3 else fin
        out.append(g)
    return out


def _build_operators(reference, grid, boxes, base, engine, scale, threads):
    """One operator per window, the windows built in parallel on ``threads`` threads
    (each single-threaded inside: its warps, transforms and fresh pages), then every
    operator given ``threads`` for its products."""
    n = 1 if threads is None else int(threads)
    parallel = n > 1 and len(boxes) > 1

    def build(box):
        return BlurOperator(reference, grid, box, base=base, engine=engine, scale=scale,
                            threads=1 if parallel else threads)

    ops = thread_map(build, boxes, n)
    if parallel:
        for op in ops:
            op.threads = n
    return ops


def _fit_gain_offset(ops, gs, w, lam, occlusion):
    """Per-band Huber fit ``g ~ a * F w + b`` over the windows' inliers (valid pixels whose
    residual the change term leaves alone, ``|r| <= lam / 2``).

    Returns ``a, b`` and the residual scale (MAD) of the fit, per band, and the number of
    inlier pixels.
    """
    C = gs[0].shape[2]
    fws = [op.matvec(w) for op in ops]
    a, b, scale = np.ones(C), np.zeros(C), np.full(C, np.inf)
    n_used = 0
    for c in range(C):
        xs, ys = [], []
        for op, g, fw in zip(ops, gs, fws, strict=True):
            m = op.valid
            if occlusion:
                m = m & (np.abs(g[:, :, c] - fw[:, :, c]) <= lam / 2.0)
            xs.append(fw[:, :, c][m])
            ys.append(g[:, :, c][m])
        x, y = np.concatenate(xs), np.concatenate(ys)
        n_used = max(n_used, x.size)
        if x.size >= 100:
            ac, bc = huber_line(x, y)
            if ac > 0.05:  # a sane gain; otherwise keep the identity
                a[c], b[c] = ac, bc
                scale[c] = mad(y - ac * x - bc)
    return a, b, scale, n_used


#: ``rtol`` of the photometric rounds' solves (:func:`_refit_photometry`), at least: each
#: starts from the weights found, whose support barely moves, and its outer iterations that
#: lower the objective by less than this add poses that take up what is left of the
#: offset (GoPro 0374: 5 outer iterations -> 3, reblur PSNR 34.22 dB either way,
#: ``python -m benchmarks.window_side --sides ""``).
REFIT_RTOL = 1e-3


def _refit_photometry(ops, gs, w, info, lam, occlusion, max_outer, time_limit,
                      max_rounds: int = 4, tol: float = 1e-4, scratch=None, rtol=0.0,
                      max_active=None):
    """Find the offset ``B`` (per band) with which eq. 5 on ``g - B`` leaves no offset.

    The weights represent a gain (their sum) but not an offset, so a solve against an
    observation with an offset bends them to absorb part of it.  The intercept ``b`` of
    the Huber line ``g - B ~ a * F w + b`` over the inliers is the part they could not
    absorb.  ``b(B)`` falls nearly linearly as ``B`` approaches the true offset, so the
    rounds propose secant steps on it (the first a plain ``B += b``), each solving eq. 5
    from the weights found (warm start, cheap: the support barely moves).  The rounds run
    only while the intercept is significant against the inliers' residual scale (``|b| >=
    scale / 2``: the biased pre-match of a well-modelled pair, not the misfit of a pair
    where much changed) and above ``tol`` (intensity units); a round is kept only if it
    lowers eq. 5's objective in ``(w, B)`` and they stop when a kept round left more than
    0.8 of the intercept (the model does not explain it).  The gain stays in the weights
    (it is not identifiable apart from their sum).  Returns the weights, the merged solver
    info (with ``photometry``) and the corrected observation windows.
    """
    C = gs[0].shape[2]
    g0 = gs
    info = dict(info)
    best_obj = float(info["objective"][-1]) if info.get("objective") else np.inf
    best = (w, np.zeros(C), gs)
    rounds = kept = 0
    n_used = 0
    prev = None  # (B, b) of the previous kept round
    b = np.zeros(C)
    for rounds in range(1, max_rounds + 1):  # noqa: B007 (reported below)
        w, B, gs = best
        _, b, scale, n_used = _fit_gain_offset(ops, gs, w, lam, occlusion)
        if np.all((np.abs(b) < tol) | (np.abs(b) < 0.5 * scale)):
            break
        if prev is not None and np.max(np.abs(b)) > 0.8 * np.max(np.abs(prev[1])):
            break
        step = b.copy()
        if prev is not None:
            dB, db = B - prev[0], b - prev[1]
            with np.errstate(divide="ignore", invalid="ignore"):
                slope = np.where(np.abs(dB) > 1e-12, db / dB, np.nan)
            # a sane secant slope: b falls as B grows, by no more than the plain step
            ok = np.isfinite(slope) & (slope < -0.05) & (slope > -1.5)
            step = np.where(ok, -b / np.where(ok, slope, 1.0), b)
        B_new = B + step
        gs_new = [g - B_new for g in g0]
        w_new, more = active_set(ops, gs_new, lam=lam, occlusion=occlusion,
                                 max_outer=max_outer, time_limit=time_limit, w0=w,
                                 scratch=scratch, workers=ops[0].threads,
                                 rtol=max(rtol, REFIT_RTOL),
                                 row_step=row_step(ops), max_active=max_active)
        info["n_outer"] = int(info.get("n_outer", 0)) + int(more["n_outer"])
        info["capped"] = int(info.get("capped", 0)) + int(bool(more.get("capped")))
        info["time_s"] = float(info.get("time_s", 0.0)) + float(more["time_s"])
        obj = float(more["objective"][-1])
        if not obj < best_obj:
            break
        info["objective"] = list(info.get("objective", [])) + list(more["objective"])
        info.update({k: v for k, v in more.items()
                     if k not in ("objective", "n_outer", "time_s", "capped")})
        prev = (B, b)
        best, best_obj = (w_new, B_new, gs_new), obj
        kept += 1
    w, B, gs = best
    info["photometry"] = dict(offset=B.tolist(), n_pixels=int(n_used), rounds=rounds,
                              kept=kept, last_intercept=np.abs(b).tolist())
    return w, info, gs


def _shrink(box, side: int):
    """The central ``side x side`` part of a window (the window itself if smaller)."""
    y0, x0, h, w = box.as_tuple()
    hh, ww = min(h, side), min(w, side)
    return as_box((y0 + (h - hh) // 2, x0 + (w - ww) // 2, hh, ww))


#: Angle stride ratio between coarse-to-fine levels: quartering needs half the levels of
#: halving (each level re-solves a few hundred active poses from its warm start) at the
#: same accuracy (``python -m benchmarks.large_motion``: every row within 0.1 dB).
_C2F_FACTOR = 4


def _next_angles(mass: np.ndarray, stride: int, centre: int | None = None
                 ) -> tuple[list[int], int]:
    """Angles of the next coarse-to-fine level, and its stride.

    ``mass`` holds the weight of every angle of the full grid after a level of stride
    ``stride``.  The angles that carry weight are those above 1 % of the heaviest angle:
    a share of the total (1 % before) dropped whole stretches of a long roll path at
    1 Gpx, where a 0.3 deg path spreads over ~120 angles of <= 1 % each (unseen windows
    48-55 dB instead of 63-69 dB, ``python -m benchmarks.large_motion``).  Around each,
    the next level takes the angles within one old stride, every ``new_stride``-th (a
    lattice through the angle itself, so the warm start carries over).  When no angle
    carries weight (the windows' fit put everything in the change term: a window covered
    by a new object), the search goes on around the ``centre`` angle.
    """
    n = mass.size
    active = np.flatnonzero(mass > 0.01 * max(float(mass.max()), 1e-300))
    if active.size == 0:
        active = np.array([n // 2 if centre is None else int(centre)])
    new_stride = max(1, stride // _C2F_FACTOR)
    if new_stride == 1 and stride > _C2F_FACTOR:
        # not straight to the last level (full windows, the costly one) from a stride
        # whose candidates would span many angles: one more cheap level at stride 2
        new_stride = 2
    reach = (stride // new_stride) * new_stride
    cand: set[int] = set()
    for a in active:
        cand.update(j for j in range(a - reach, a + reach + 1, new_stride) if 0 <= j < n)
    return sorted(cand), new_stride


#: Pixels of all windows together on a coarse-to-fine level before the last, for three
#: windows or more: the central ``sqrt(_COARSE_PIXELS / K)`` px of each of the ``K``
#: windows (128 px for four, 114 for five: the pipeline's defaults above 2500 px).  One or
#: two windows keep 256 px each.  A coarse level only finds where the weight lies, and its
#: cost (Gram products, spectra) grows with its pixels.  Windows spread around the image
#: pin the roll down jointly: 128 px each gave the same weights as 181 px at 38 MP, 105 MP
#: and 1 Gpx (``python -m benchmarks.large_motion``: unseen windows to 0.01 dB; the 1 Gpx
#: estimate 1.8 s shorter) and the same flags on the outskirts pair
#: (``python -m benchmarks.outskirts``, defaults).  Two windows of a small image carry the
#: roll alone: at 181 px each, ``python -m benchmarks.quality`` moved (Fig. 6 seed 8 JC
#: 0.834 -> 0.807, the ``align=False`` WHU pairs 0.264 -> 0.284 in the mean), so they
#: keep 256 px.
_COARSE_PIXELS = 2**16

#: Solve the finest roll stride on the windows' central parts before the full windows
#: (when those parts hold at most half of the pixels).  The full-window level is the
#: costly one (every angle's stack and spectra at full size, Gram products over all its
#: pixels); started from the stride-2 solution it spent most of its outer iterations
#: finding the odd angles' weights, which the central parts find for a tenth of the
#: pixels.  From their solution it only adjusts the weights (1 Gpx: 4 outer iterations
#: there instead of 6; ``python -m benchmarks.large_motion --case 32000`` prints the
#: levels).  The result is the same optimum (the same poses, another warm start).
_FINE_ON_CENTRES = True


def coarse_side(n_windows: int) -> int:
    """Side (px) of each window's central part on the coarse levels (64 to 256 px)."""
    n = max(int(n_windows), 1)
    if n <= 2:
        return 256
    return max(64, min(256, int(np.sqrt(_COARSE_PIXELS / n))))


def _rz_coarse_to_fine(reference, observed, grid, boxes, base, engine, s_ref, s_obs, lam,
                       occlusion, max_outer, time_limit, max_bases, levels, scratch=None,
                       t_margin: int = 3, threads=None, rtol=0.0, fine_rtol=None,
                       stop_occluded=None, resume=None, t_grow: int = 1,
                       log: list | None = None, max_active=None):
    """Coarse-to-fine over the roll angles of ``grid`` (see :func:`estimate_motion`).

    Coarse levels solve on the central :func:`coarse_side` pixels of each window (the
    windows stay far apart, so roll stays observable) and, after the first level, only over the
    translations that carry weight plus ``t_margin`` pixels (every ``ts``-th of them on
    coarse levels, nested from level to level so that warm starts carry over).  At the
    finest stride the central parts are solved first when they hold at most half of the
    windows' pixels; the last level then uses the full windows, the same poses, and the
    warm start of that solve (see :data:`_FINE_ON_CENTRES`), and stops at ``fine_rtol``
    (default ``rtol``; the levels before it at ``rtol``; each level's record holds its
    own).  The result is embedded in the full grid.  The observation windows are read once:
    the central parts are views of them.

    With ``stop_occluded``, a first level that leaves a window's part more than that share
    change ends the schedule there (``info["stopped_early"]``, ``info["resume"]``: the
    state the next level starts from); ``resume`` starts from such a state.

    With ``t_grow > 1`` the first level is tried on translations twice as wide while its
    weights pile on the grid's edge (:func:`_widen_first`, records appended to ``log``).
    Returns the weights on the last level's grid, the merged info, its operators and
    windows, that grid and the (possibly widened) full grid.
    """
    n = grid.n_bases
    stride = int(np.ceil((n - 1) / max(max_bases - 1, 1)))
    centre = int(np.argmin(np.abs(np.asarray(grid.rz))))
    idx = sorted(set(range(centre % stride, n, stride)) | {centre})
    tx, ty = list(grid.tx), list(grid.ty)
    # coarse levels also use every ``ts``-th translation: with a roll step that moves the
    # far windows by ``stride`` pixels, finer translations cannot be told apart there
    x0 = int(np.argmin(np.abs(np.asarray(grid.tx))))
    y0 = int(np.argmin(np.abs(np.asarray(grid.ty))))
    t_cap = max(1, min(len(grid.tx), len(grid.ty)) // 4)

    def t_stride(s: int) -> int:
        ts = 1
        while ts * 2 <= min(s / 4.0, t_cap):
            ts *= 2
        return ts

    def every(vals: list, full: list, i0: int, ts: int) -> list:
        return [v for v in vals if (full.index(v) - i0) % ts == 0]

    def advance(w_full: np.ndarray, stride: int, ts: int):
        """Angles, stride and translations of the level after one of ``stride``."""
        idx, new_stride = _next_angles(w_full.sum(axis=(1, 2)), stride, centre)
        tx, ty = list(grid.tx), list(grid.ty)
        # translations: those carrying weight, plus a margin, within the grid
        nz = np.argwhere(w_full > 0)
        if nz.size:
            mg = max(t_margin, ts)
            ylo, yhi = nz[:, 1].min() - mg, nz[:, 1].max() + mg
            xlo, xhi = nz[:, 2].min() - mg, nz[:, 2].max() + mg
            ty = list(grid.ty[max(ylo, 0) : yhi + 1])
            tx = list(grid.tx[max(xlo, 0) : xhi + 1])
        return idx, new_stride, tx, ty

    t_limit = _t_limit(grid, boxes, t_grow)
    log = [] if log is None else log
    fine_rtol = rtol if fine_rtol is None else fine_rtol
    small = [_shrink(b, coarse_side(len(boxes))) for b in boxes]
    g_full = [read_window(observed, b, np.float64) / s_obs for b in boxes]
    g_small = [g[s.y0 - b.y0 : s.y1 - b.y0, s.x0 - b.x0 : s.x1 - b.x0]
               for g, s, b in zip(g_full, small, boxes, strict=True)]
    centres_first = _FINE_ON_CENTRES and (
        2 * sum(b.h * b.w for b in small) <= sum(b.h * b.w for b in boxes))
    w_prev = None
    total = dict(objective=[], n_outer=0, time_s=0.0, capped=0)
    on_centres = True  # the level about to run solves on the central parts
    if resume is not None:
        w_prev = np.asarray(resume["weights"], float)
        if w_prev.shape != grid.shape:
            raise ValueError(f"resume weights of shape {w_prev.shape} do not fit the grid "
                             f"{grid.shape}")
        if int(resume["stride"]) == 1:  # it stopped on the central parts at stride 1
            idx, tx, ty = list(resume["angles"]), list(resume["tx"]), list(resume["ty"])
            stride, on_centres = 1, False
        else:
            idx, stride, tx, ty = advance(w_prev, int(resume["stride"]), int(resume["t_stride"]))
    first = resume is None

    def run(part, w0, bx, gs, *, stride, ts, lv_rtol=None, views=None, scale=1):
        """One level's solve on ``part`` (at ``lv_rtol``, default ``rtol``) and its record;
        ``views`` (reference, observation, base) replace the full-resolution ones on a level
        ``scale`` times coarser."""
        lv_rtol = rtol if lv_rtol is None else lv_rtol
        ref_v, obs_v, base_v = (reference, observed, base) if views is None else views
        out = _solve(ref_v, obs_v, part, bx, base_v, engine, s_ref, s_obs, lam, occlusion,
                     "active-set", max_outer, time_limit, 0, w0, gs=gs, scratch=scratch,
                     threads=threads, rtol=lv_rtol, max_active=max_active,
                     pixel_weight=scale * scale)
        info = out[1]
        rec = dict(stride=stride, t_stride=ts, n_angles=len(part.rz),
                   n_t=len(part.tx) * len(part.ty), side=int(max(bx[0].h, bx[0].w)),
                   t_max=scale * _t_max(part), n_outer=info["n_outer"], time_s=info["time_s"],
                   n_active=info["n_active"], rtol=lv_rtol,
                   row_step=int(info.get("row_step", 1)), capped=bool(info["capped"]))
        if scale != 1:
            rec["resolution"] = 1.0 / scale
        if "warm_start" in info:
            rec["warm_start"] = info["warm_start"]
        levels.append(rec)
        total["objective"] += info["objective"]
        total["n_outer"] += info["n_outer"]
        total["time_s"] += info["time_s"]
        total["capped"] += int(bool(info["capped"]))
        return out

    if first and _half_start_applies(grid, small):
        # the full-resolution levels go on from its weights (and grid, if it widened)
        w_prev, grid, info = _half_first_level(
            reference, observed, base, grid, small, idx, stride, s_obs, t_grow, t_limit, log,
            run, stop_occluded if occlusion else None, lam)
        if info.get("stopped_early"):  # a part came out changed: stop there
            sub = PoseGrid(grid.image_shape, tx=grid.tx, ty=grid.ty,
                           rz=[grid.rz[i] for i in idx], center=grid.center)
            ops = _build_operators(reference, sub, small, base, engine, s_ref, threads)
            gs = _exclude(ops, small, getattr(observed, "exclude", None), g_small)
            total.update({k: v for k, v in info.items() if k not in total})
            total["resume"] = dict(weights=w_prev, stride=stride, t_stride=1,
                                   angles=list(idx), tx=list(grid.tx), ty=list(grid.ty))
            return carry_weights(w_prev, grid, sub), total, ops, gs, sub, grid
        x0 = int(np.argmin(np.abs(np.asarray(grid.tx))))
        y0 = int(np.argmin(np.abs(np.asarray(grid.ty))))
        t_cap = max(1, min(len(grid.tx), len(grid.ty)) // 4)
        idx, stride, tx, ty = advance(w_prev, stride, t_stride(stride))
        first = False
    while True:
        last = stride == 1 and not (on_centres and centres_first)
        ts = t_stride(stride)
        sub = PoseGrid(grid.image_shape, tx=every(tx, list(grid.tx), x0, ts),
                       ty=every(ty, list(grid.ty), y0, ts), rz=[grid.rz[i] for i in idx],
                       center=grid.center)
        w0 = None if w_prev is None else w_prev[np.ix_(
            idx, [grid.ty.index(v) for v in sub.ty], [grid.tx.index(v) for v in sub.tx])]
        bx, gs = (boxes, g_full) if last else (small, g_small)
        ops = None  # the previous level's stacks and spectra go before the next's come

        def solve(part, w0, bx=bx, gs=gs, stride=stride, ts=ts, last=last):
            return run(part, w0, bx, gs, stride=stride, ts=ts,
                       lv_rtol=fine_rtol if last else rtol)

        w, info, ops, gs = solve(sub, w0)
        if first and t_grow > 1:
            wide, (sub, w, info, ops, gs) = _widen_first(grid, ts, (sub, w, info, ops, gs),
                                                         solve, t_limit, log)
            if wide is not grid:  # the blur reached beyond: the levels go on from there
                grid, tx, ty = wide, list(wide.tx), list(wide.ty)
                x0 = int(np.argmin(np.abs(np.asarray(grid.tx))))
                y0 = int(np.argmin(np.abs(np.asarray(grid.ty))))
                t_cap = max(1, min(len(grid.tx), len(grid.ty)) // 4)
        if last:
            total.update({k: v for k, v in info.items() if k not in total})
            return w, total, ops, gs, sub, grid
        w_full = carry_weights(w, sub, grid)
        w_prev = w_full
        if first and stop_occluded is not None and occlusion:
            first = False
            shares = [_occluded_share(soft_threshold(g - op.matvec(w), lam / 2.0), op.valid)
                      for op, g in zip(ops, gs, strict=True)]
            if max(shares) > stop_occluded:
                total.update({k: v for k, v in info.items() if k not in total})
                total.update(stopped_early=True,
                             resume=dict(weights=w_full, stride=stride, t_stride=ts,
                                         angles=list(idx), tx=list(tx), ty=list(ty)))
                return w, total, ops, gs, sub, grid
        first = False
        if stride == 1:  # the central parts at the finest stride: same poses, full windows
            on_centres = False
            continue
        idx, stride, tx, ty = advance(w_full, stride, ts)


# ---------------------------------------------------- the first level at half resolution
#: Solve the first coarse-to-fine level at half resolution (METHOD.md: "consider a
#: coarse-to-fine start (half resolution, coarser grid)").  The first level is the
#: costliest of a wide blur: at full resolution a 35 px shake's first level solved 2401
#: translations per angle, widened to 9409, 27 outer iterations with ~290 poses.  At half
#: resolution the same blur spans half as many pixels each way: a quarter of the
#: translations, of the pixels and of the poses carrying weight.  Each block mean stands
#: for four pixels (``active_set(pixel_weight=4)``), so the l1 term and the widening's
#: gains weigh as at full resolution.  Its weights, each carried to twice its translation
#: (:func:`_full_weights`), start the next level, which keeps the translations that carry
#: weight (plus a margin) at full resolution; the levels after it are as before.
#: ``python -m benchmarks.half_start`` (estimate medians, off -> on): the test bed's 20 /
#: 35 px shakes 5.28 -> 4.78, 5.68 -> 3.65 s, the 1.5 degree tilt 18.2 -> 12.0 s, with
#: the same masks and fits; GoPro 0374, which starts at 24 px, 3.73 -> 2.72 s with the
#: same mask (``python -m benchmarks.shake_extent``).
HALF_START = True
#: The least translation half-range (px, full resolution) of the first level's grid for
#: which it runs at half resolution: the grids the alignment found the blur wide for.
#: On the default +-12 px too (``T >= 6`` in ``python -m benchmarks.half_start``) the 6 /
#: 12 px shakes and the defocus pair gained 0.5-1.2 s with the same masks, but real
#: shake moved (GoPro 0477 / 16 152 px fewer flagged, 0374 0.06 % more) and content that
#: differs paid: at half resolution a misfit gains from wider translations (four times
#: fewer pixels for the same poses): unrelated windows (LEVIR test_7 against WHU 000213)
#: widened twice, and the years-apart WHU 000213 pair of ``tests/test_cost.py`` took 45
#: outer iterations where that test bounds them at 40.
HALF_MIN_T = 16.0
#: The least side (px) of a half-resolution central part (a full-resolution part of
#: twice that): two windows' 256 px parts qualify, four windows' 128 px (25 MP and up)
#: do not; the benchmarks have no wide blur above 1 MP to measure them on.
HALF_MIN_SIDE = 96


class _Halved:
    """2 x 2 block means of an array-like image (``(H, W)`` or ``(H, W, C)``), read window
    by window as float32 (``read_window`` slices it with whole-pixel bounds).

    Half-resolution pixel ``(i, j)`` is the mean of full pixels ``2i .. 2i + 1``, ``2j ..
    2j + 1``; an odd last row or column repeats its pixel.  A non-finite pixel (no data)
    makes its block's mean non-finite.  An ``exclude`` of the array (see
    :func:`estimate_motion`'s ``observed``) is halved too: a half-resolution pixel is
    excluded where any of its four pixels is.
    """

    def __init__(self, array) -> None:
        self.array = array
        self._hw = (int(array.shape[0]), int(array.shape[1]))
        H, W = self._hw
        self.shape = ((H + 1) // 2, (W + 1) // 2, *(int(v) for v in array.shape[2:]))
        self.dtype = np.dtype(np.float32)
        ex = getattr(array, "exclude", None)
        if ex is not None:
            def exclude(box):
                b = as_box(box)
                m = np.asarray(ex(as_box((2 * b.y0, 2 * b.x0, 2 * b.h, 2 * b.w))), bool)
                return m[0::2, 0::2] | m[1::2, 0::2] | m[0::2, 1::2] | m[1::2, 1::2]
            self.exclude = exclude

    def __getitem__(self, key) -> np.ndarray:
        ys, xs = key[:2]
        H, W = self._hw
        y0, y1 = 2 * ys.start, min(2 * ys.stop, H)
        x0, x1 = 2 * xs.start, min(2 * xs.stop, W)
        a = np.asarray(self.array[y0:y1, x0:x1], np.float32)
        if a.shape[0] % 2:
            a = np.concatenate([a, a[-1:]], axis=0)
        if a.shape[1] % 2:
            a = np.concatenate([a, a[:, -1:]], axis=1)
        return 0.25 * ((a[0::2, 0::2] + a[1::2, 0::2]) + (a[0::2, 1::2] + a[1::2, 1::2]))


#: Full-resolution pixel coordinates -> :class:`_Halved` ones (pixel centres at whole
#: numbers: half-resolution pixel 0 is the mean of full pixels 0 and 1, centred at 0.5).
_HALF = np.array([[0.5, 0.0, -0.25], [0.0, 0.5, -0.25], [0.0, 0.0, 1.0]])


def _half_grid(grid: PoseGrid, idx: Sequence[int]) -> PoseGrid:
    """The half-resolution counterpart of ``grid``'s angles ``idx``: the same rolls about
    ``grid``'s centre mapped by :data:`_HALF`, and the whole-pixel translations ``t`` with
    ``2 t`` in ``grid``'s range.  Its pose ``(rz, t)`` is ``_HALF @ H @ inv(_HALF)`` for
    ``grid``'s pose ``(rz, 2 t)``."""
    def half(vals) -> list[float]:
        lo, hi = int(np.ceil(min(vals) / 2.0)), int(np.floor(max(vals) / 2.0))
        return [float(v) for v in range(lo, hi + 1)]
    cx, cy = grid.center
    H, W = grid.image_shape
    return PoseGrid(((H + 1) // 2, (W + 1) // 2), tx=half(grid.tx), ty=half(grid.ty),
                    rz=[grid.rz[i] for i in idx], center=(cx / 2.0 - 0.25, cy / 2.0 - 0.25))


def _full_weights(w_h: np.ndarray, sub_h: PoseGrid, grid: PoseGrid,
                  idx: Sequence[int]) -> np.ndarray:
    """Weights on ``sub_h`` (:func:`_half_grid` of ``grid``'s angles ``idx``) carried to
    ``grid``: each pose's weight to ``grid``'s pose of the same angle at twice its
    translation (the nearest ``grid`` holds)."""
    out = np.zeros(grid.shape)
    tyf, txf = np.asarray(grid.ty, float), np.asarray(grid.tx, float)
    iy = np.abs(tyf[None, :] - 2.0 * np.asarray(sub_h.ty, float)[:, None]).argmin(axis=1)
    ix = np.abs(txf[None, :] - 2.0 * np.asarray(sub_h.tx, float)[:, None]).argmin(axis=1)
    w_h = sub_h.check_weights(w_h)
    for a, b in enumerate(idx):
        np.add.at(out[b], (iy[:, None], ix[None, :]), w_h[a])
    return out


def _half_start_applies(grid: PoseGrid, small: Sequence) -> bool:
    """Whether the first level runs at half resolution (:data:`HALF_START`)."""
    return (HALF_START and _t_max(grid) >= HALF_MIN_T
            and min(min(b.h, b.w) for b in small) >= 2 * HALF_MIN_SIDE)


def _half_first_level(reference, observed, base, grid: PoseGrid, small: Sequence,
                      idx: Sequence[int], stride: int, s_obs: float, t_grow: int,
                      t_limit: float, log: list, run, stop_occluded: float | None,
                      lam: float) -> tuple[np.ndarray, PoseGrid, dict]:
    """The first level of :func:`_rz_coarse_to_fine` (angles ``idx``, ``stride``) on the
    central parts ``small`` at half resolution (:data:`HALF_START`), widened as
    :func:`_widen_first` does (``t_limit`` in full-resolution px; ``log``'s records in
    them too); ``run`` is the schedule's solve.  Returns its weights carried to ``grid``,
    widened as far, that grid and its last solve's info, with ``stopped_early`` where a
    part comes out more than ``stop_occluded`` change (the paper's rejection, decided at
    half resolution as it is on the full-resolution first level)."""
    views = (_Halved(reference), _Halved(observed),
             _HALF @ (np.eye(3) if base is None else np.asarray(base, float))
             @ np.linalg.inv(_HALF))
    bh = [as_box((-(-b.y0 // 2), -(-b.x0 // 2), b.h // 2, b.w // 2)) for b in small]
    gh = [read_window(views[1], b, np.float64) / s_obs for b in bh]

    def solve(part, w0):
        return run(part, w0, bh, gh, stride=stride, ts=1, views=views, scale=2)

    sub = _half_grid(grid, idx)
    first = (sub, *solve(sub, None))
    if t_grow > 1:
        n_log = len(log)
        wide, first = _widen_first(_half_grid(grid, range(grid.n_bases)), 1, first, solve,
                                   t_limit / 2.0, log)
        for rec in log[n_log:]:
            rec["t_max"] *= 2
            rec["resolution"] = 0.5
        while _t_max(grid) < 2.0 * _t_max(wide) - 1.0:
            wider = widen_translations(grid)
            if wider is None or wider.size > MAX_WIDENED_POSES:
                break
            grid = wider
    sub, w, info, ops, gs = first
    info = dict(info)
    if stop_occluded is not None:
        shares = [_occluded_share(soft_threshold(g - op.matvec(w), lam / 2.0), op.valid)
                  for op, g in zip(ops, gs, strict=True)]
        info["stopped_early"] = max(shares) > stop_occluded
    return _full_weights(w, sub, grid, idx), grid, info
