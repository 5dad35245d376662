"""One tile of the reblur-and-decide pass: the unit of work of every scheduler.

:func:`reblur.pipeline.reblur_and_decide` (local thread pool) and
:func:`reblur.dask_backend.decide_tiles` (Dask) both run :func:`run_tile` on every output
tile, so the two paths compute exactly the same thing.  A :class:`TileJob` holds what every
tile shares: the sparse pose weights, the photometric model, the threshold, the decision
parameters and the output arrays.  It is small (no image data), so a distributed scheduler
ships it once per worker.
"""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ._bands import all_bands
from ._memory import M_MMAP_THRESHOLD, M_TRIM_THRESHOLD, MMAP_THRESHOLD_MAX, glibc_mallopt
from .decide import DecisionParams, Photometry, decide_tile
from .tiled import SparsePoses, reblur_tile
from .warp import as_box, read_window

__all__ = ["LoadedTiles", "TileJob", "grow_tile", "load_tile", "max_region_extent",
           "preload_tiles", "run_tile", "pad_box", "tile_work", "tune_worker_malloc"]

#: Tries per tile: the first halo; twice, then four times it where a region reaches the
#: edge; eight times it (the largest halo) on every edge a region has reached; and, if a
#: region then reaches another edge, the largest halo on every edge.
_ATTEMPTS = 5

#: The largest halo is the first one ``<< _LARGEST`` (8x).
_LARGEST = 3


def max_region_extent(halo: int, local_radius: int) -> int:
    """Largest region (bounding-box side, px) the re-runs of :func:`run_tile` decide exactly
    with a first-try ``halo``: the largest halo, ``halo << 3``, less the reach of the
    pixel-local steps.  A region seen larger than this in a padded tile is decided there,
    without growing the halo (``decide_tile``'s ``max_extent``)."""
    return max((int(halo) << _LARGEST) - int(local_radius), 0)


def tile_work(results: Sequence[dict[str, Any]]) -> dict[str, int]:
    """The work of a tile pass from :func:`run_tile`'s results: decisions (``attempts``, and
    the most any tile took) and padded pixels decided, summed over the tiles."""
    return {"attempts": sum(int(r["attempts"]) for r in results),
            "max_attempts": max((int(r["attempts"]) for r in results), default=0),
            "pixels": sum(int(r["pixels"]) for r in results)}


#: Serialises in-process writes into outputs whose chunks straddle tiles.
_WRITE_LOCK = threading.Lock()

_MALLOC_TUNED: list[bool] = []


def tune_worker_malloc() -> bool:
    """Let glibc reuse heap memory for array temporaries in a Dask worker (once per process).

    A ``distributed`` nanny starts its workers with ``MALLOC_TRIM_THRESHOLD_=65536`` (to
    return freed memory to the system).  Setting any such variable also freezes glibc's
    mmap threshold at 128 KB, so every numpy temporary above it is a fresh ``mmap`` whose
    pages fault in on first touch: the estimate's and the tiles' element-wise steps ran
    several times slower on a ``LocalCluster`` worker than in the client (the cost curve's
    ``LocalCluster`` row, ``python -m benchmarks.scale``).  This sets the mmap threshold
    back to 32 MB (the ceiling of glibc's own dynamic threshold) and raises the trim
    threshold to twice that (what glibc's dynamic rule sets with it): with the nanny's
    64 KB, every tile's temporaries freed at the top of the heap went back to the system
    and faulted in again on the next tile: a two-worker ``LocalCluster``'s tile pass took
    1.8x the CPU of the local path's at 100 MP (``python -m benchmarks.dask_cluster``).  A
    worker keeps at most 64 MB more per malloc arena.  Nothing happens outside Linux, without
    ``MALLOC_TRIM_THRESHOLD_`` in the environment, or when the user chose
    ``MALLOC_MMAP_THRESHOLD_`` already; a trim threshold above 64 MB is left as it is.

    Returns
    -------
    bool
        True if the thresholds were set by this call.
    """
    if _MALLOC_TUNED:
        return False
    _MALLOC_TUNED.append(True)
    env = os.environ
    if (not sys.platform.startswith("linux") or "MALLOC_TRIM_THRESHOLD_" not in env
            or "MALLOC_MMAP_THRESHOLD_" in env):
        return False
    mallopt = glibc_mallopt()
    if mallopt is None:  # not glibc
        return False
    # the largest block glibc then serves from the heap: its own dynamic threshold's ceiling
    trim = _trim_threshold(env["MALLOC_TRIM_THRESHOLD_"])
    if trim < 2 * MMAP_THRESHOLD_MAX and not mallopt(M_TRIM_THRESHOLD, 2 * MMAP_THRESHOLD_MAX):
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX))


def _trim_threshold(value: str) -> int:
    """``MALLOC_TRIM_THRESHOLD_`` as glibc reads it (a number; anything else is 0)."""
    try:
        return int(value.strip(), 0)
    except ValueError:
        return 0


@dataclass
class TileJob:
    """Everything a tile task needs besides the two images.

    Attributes
    ----------
    poses : SparsePoses
        Non-zero pose weights (with the coarse alignment composed).
    s_ref, s_obs : float
        Intensity scales of the reference and the observation (to [0, 1] units).
    gain, offset : (C,) ndarray
        Photometric pre-match of the reblurred reference to the observation.
    threshold : float
        Global threshold of the change statistic.
    photometry : Photometry
        Global photometric model.
    params : DecisionParams
        Decision parameters (the same for every tile).
    halo : int
        First-try halo of the padded tiles (grown, up to eight times, on the edges a
        tile's regions reach; :func:`run_tile`).
    image_shape : (int, int)
        Observation size.
    two_d : bool
        The observation is 2-D (the reblurred output is then 2-D).
    change_out, unknown_out : array-like
        Full-size ``(H, W)`` bool outputs (numpy in this process, zarr for other processes).
    reblurred_out : array-like or None
        Full-size float32 output of the matched reblurred reference, or None.
    lock_writes : bool
        Serialise writes (in-process outputs whose chunks straddle tiles).
    client_pid : int
        Process that built the job; a task running in another process sets OpenCV to one
        thread (one task per worker thread: no nested thread pools).
    """

    poses: SparsePoses
    s_ref: float
    s_obs: float
    gain: np.ndarray
    offset: np.ndarray
    threshold: float
    photometry: Photometry
    params: DecisionParams
    halo: int
    image_shape: tuple[int, int]
    two_d: bool
    change_out: Any
    unknown_out: Any
    reblurred_out: Any = None
    lock_writes: bool = True
    client_pid: int = 0


def pad_box(core: Sequence[int], halo: int | Sequence[int],
            shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """``core`` grown by ``halo`` pixels on every side (or by ``(top, bottom, left,
    right)``), clipped to an image of ``shape``."""
    y, x, h, w = (int(v) for v in core)
    t, b, lf, r = (int(halo),) * 4 if np.isscalar(halo) else (int(v) for v in halo)
    y0, x0 = max(y - t, 0), max(x - lf, 0)
    y1, x1 = min(y + h + b, shape[0]), min(x + w + r, shape[1])
    return (y0, x0, y1 - y0, x1 - x0)


def load_tile(poses: SparsePoses, reference, observed, box, *, s_ref: float, s_obs: float,
              gain: np.ndarray, offset: np.ndarray) -> tuple[np.ndarray, ...]:
    """Observation window, reblurred reference pre-matched to it, and the unknown mask.

    Returns
    -------
    obs, reb : (h, w, C) float32 ndarray
        ``observed / s_obs`` and ``reblurred / s_ref * gain + offset`` on ``box``.
    unknown : (h, w) bool ndarray
        Pixels some non-zero pose reads outside the reference or on a no-data (NaN) pixel
        of it, and no-data pixels of the observation.
    """
    box = as_box(box)
    # a model with its own tile reblur (row-dependent weights: reblur.rolling.RollingPoses)
    own = getattr(poses, "reblur_tile", None)
    reb, valid = own(reference, box) if own is not None else reblur_tile(poses, reference, box)
    # in place: the same float32 operations as ``reb / s_ref * gain + offset``
    reb /= np.float32(s_ref)
    reb *= np.asarray(gain, np.float32)
    reb += np.asarray(offset, np.float32)
    obs = read_window(observed, box, np.float32)
    obs /= np.float32(s_obs)
    unknown = ~valid
    # no data (NaN: :class:`reblur.io.MaskedView`) in the observation, or in the reference
    # under the blur of a pixel, is unknown too
    for a in (reb, obs):
        fin = np.isfinite(a)
        if not fin.all():
            unknown |= ~all_bands(fin)
    return obs, reb, unknown


#: Most bytes :func:`preload_tiles` holds (the observation and the reblurred reference in
#: float32, and the unknown mask, over the padded tiles): a colour image of about 2.5 MP,
#: a gray one of about 7 MP.
PRELOAD_BYTES = 64 << 20


class LoadedTiles:
    """The first try's :func:`load_tile` of every padded tile of a small image, made once
    for the decision's two passes (:func:`preload_tiles`).

    Pass 1's windows are cut or pieced from them (:meth:`window`) and the local tile pass
    starts each tile from its own load (:meth:`take`).  The tile pass then decides on the
    arrays a Dask worker's own :func:`load_tile` of the padded tile gives, bit for bit;
    pass 1 runs on the client for every backend, so it is the same for all of them too.  A
    window cut from a padded tile equals the window's own load up to the rounding of
    OpenCV's warp coordinates (see :func:`reblur.tiled.reblur_windows`).  The arrays are
    read-only.
    """

    def __init__(self, loads: dict[tuple[int, int, int, int], tuple[np.ndarray, ...]]):
        self._loads = dict(loads)
        self._lock = threading.Lock()
        for arrays in self._loads.values():
            for a in arrays:
                a.flags.writeable = False

    def __len__(self) -> int:
        return len(self._loads)

    def window(self, box) -> tuple[np.ndarray, ...] | None:
        """``(obs, reb, unknown)`` on ``box``: views into a held padded tile that contains
        it, else copies pieced together from the held tiles that cover it (a pixel's values
        do not depend on the tile it was loaded in, but for the warps' rounding); None when
        they do not cover it."""
        y, x, h, w = (int(v) for v in box)
        with self._lock:
            items = list(self._loads.items())
        for (ty, tx, th, tw), arrays in items:
            if ty <= y and tx <= x and y + h <= ty + th and x + w <= tx + tw:
                sl = (slice(y - ty, y - ty + h), slice(x - tx, x - tx + w))
                return tuple(a[sl] for a in arrays)
        done = np.zeros((h, w), bool)
        out: list[np.ndarray] | None = None
        for (ty, tx, th, tw), arrays in items:
            y0, x0 = max(y, ty), max(x, tx)
            y1, x1 = min(y + h, ty + th), min(x + w, tx + tw)
            if y0 >= y1 or x0 >= x1:
                continue
            if out is None:
                out = [np.empty((h, w, *a.shape[2:]), a.dtype) for a in arrays]
            mine = (slice(y0 - y, y1 - y), slice(x0 - x, x1 - x))
            theirs = (slice(y0 - ty, y1 - ty), slice(x0 - tx, x1 - tx))
            for o, a in zip(out, arrays, strict=True):
                o[mine] = a[theirs]
            done[mine] = True
        if out is None or not done.all():
            return None
        return tuple(out)

    def take(self, padded) -> tuple[np.ndarray, ...] | None:
        """The load of the padded tile ``padded``, no longer held (None if not held)."""
        with self._lock:
            return self._loads.pop(tuple(int(v) for v in padded), None)


def preload_tiles(load, padded: Sequence[Sequence[int]], n_bands: int,
                  max_bytes: int | None = None) -> LoadedTiles | None:
    """``load(box)`` (:func:`load_tile` with the decision's poses and photometric
    pre-match) of every box of ``padded``, as a :class:`LoadedTiles`; None when they would
    take more than ``max_bytes`` (default :data:`PRELOAD_BYTES`).

    On a small image the decision's pass 1 samples every tile anyway (its 256 px windows
    grown by the statistic's reach, then the estimation windows: 1.8 times the pixels of a
    1 MP image), and the tile pass reblurred all of it once more.  The tiles are loaded one
    after the other, each warp on OpenCV's threads: a small image has a tile or two, of
    unequal sizes (1280 x 720 px: 0.8 and 0.24 MP), which one thread per tile would
    leave to one core.
    """
    boxes = [tuple(int(v) for v in b) for b in padded]
    pixels = sum(b[2] * b[3] for b in boxes)
    cap = PRELOAD_BYTES if max_bytes is None else int(max_bytes)
    if not boxes or pixels * (8 * int(n_bands) + 1) > cap:
        return None
    return LoadedTiles({b: load(b) for b in boxes})


def grow_tile(poses: SparsePoses, reference, observed, box, loaded, larger, *, s_ref: float,
              s_obs: float, gain: np.ndarray, offset: np.ndarray) -> tuple[np.ndarray, ...]:
    """:func:`load_tile` on ``larger``, reusing what was loaded on ``box`` inside it.

    Only the ring ``larger - box`` is read and reblurred (as four strips).  The observation
    and the unknown mask are exactly those of a direct call; the reblurred reference too,
    up to the rounding of OpenCV's single-precision warp coordinates, which depend on the
    window a warp is built for (~1e-6 of the intensity; see :mod:`reblur.tiled`).

    Parameters
    ----------
    box, larger : (y0, x0, h, w)
        The loaded window and a window containing it.
    loaded : (obs, reb, unknown)
        :func:`load_tile` on ``box``.
    """
    y0, x0, h, w = (int(v) for v in box)
    Y0, X0, Hh, Ww = (int(v) for v in larger)
    if y0 < Y0 or x0 < X0 or y0 + h > Y0 + Hh or x0 + w > X0 + Ww:
        raise ValueError(f"{tuple(larger)} does not contain {tuple(box)}")
    obs, reb, unk = loaded
    C = obs.shape[2]
    out = (np.empty((Hh, Ww, C), obs.dtype), np.empty((Hh, Ww, C), reb.dtype),
           np.empty((Hh, Ww), bool))
    ly, lx = y0 - Y0, x0 - X0
    for big, small in zip(out, loaded, strict=True):
        big[ly : ly + h, lx : lx + w] = small
    strips = [(Y0, X0, ly, Ww), (y0 + h, X0, Y0 + Hh - y0 - h, Ww),
              (y0, X0, h, lx), (y0, x0 + w, h, X0 + Ww - x0 - w)]
    for sy, sx, sh, sw in strips:
        if sh <= 0 or sw <= 0:
            continue
        part = load_tile(poses, reference, observed, (sy, sx, sh, sw), s_ref=s_ref, s_obs=s_obs,
                         gain=gain, offset=offset)
        for big, small in zip(out, part, strict=True):
            big[sy - Y0 : sy - Y0 + sh, sx - X0 : sx - X0 + sw] = small
    return out


def run_tile(
    job: TileJob, reference, observed, padded: Sequence[int], core: Sequence[int], *,
    loaded: tuple[np.ndarray, ...] | None = None,
) -> dict[str, Any]:
    """Reblur, decide and write one tile.

    The padded tile is reblurred (reading only the reference window its poses touch),
    pre-matched, decided by :func:`reblur.decide.decide_tile`, re-run when a region reaches
    the halo's edge -- with a twice, then four times larger halo on the edges it reaches,
    then eight times the first halo on every edge a region has reached, and last, if a
    region then reaches another edge, eight times on every edge -- reading, reblurring and
    computing the statistic only on what the halo adds (:func:`grow_tile`), and its core
    written into the job's outputs.  Only regions that the largest halo can hold
    (:func:`max_region_extent`) ask for a re-run: a region already larger than that in the
    padded tile (an area-wide change, a large false region) is decided on the tile as it
    is and counted in ``oversize``.  The work per tile is at most five attempts, none
    larger than the core grown by eight times the first halo on every edge, however many
    regions it holds; growing only the edges regions reach spares most tiles that largest
    window (under half its pixels for one edge of a 1024 px tile and the default halo).

    Parameters
    ----------
    job : TileJob
    reference, observed : array-like
        Full-size images (numpy, zarr or any window reader).
    padded, core : (y0, x0, h, w)
        The tile with its halo and the part it owns.
    loaded : (obs, reb, unknown), optional
        :func:`load_tile` of ``padded`` with the job's poses and pre-match, when the caller
        already has it (:class:`LoadedTiles`; read-only arrays are fine): the first try
        then reads and reblurs nothing.

    Returns
    -------
    dict
        ``core`` (box), ``regions`` (list of dict, full-image coordinates), ``complete``
        (bool: the result equals the whole-image decision), ``oversize`` (regions reaching
        the last attempt's edge that no halo of the schedule holds), ``attempts`` (number of
        :func:`~reblur.decide.decide_tile` calls), ``pixels`` (padded pixels decided, over
        the attempts).
    """
    if os.getpid() != job.client_pid:
        if cv2.getNumThreads() != 1:
            cv2.setNumThreads(1)
        tune_worker_malloc()
    H, W = job.image_shape
    gain = np.asarray(job.gain, np.float32)
    offset = np.asarray(job.offset, np.float32)
    padded = tuple(int(v) for v in padded)
    core = tuple(int(v) for v in core)
    sides = ("top", "bottom", "left", "right")
    halo = dict.fromkeys(sides, int(job.halo))
    prev, stat = padded, None
    max_extent = max_region_extent(job.halo, job.params.local_radius)
    pixels = 0
    big = int(job.halo) << _LARGEST
    largest = pad_box(core, big, (H, W))  # no try reads more than this
    for attempt in range(_ATTEMPTS):
        last = attempt == _ATTEMPTS - 1 or padded == largest
        if attempt == 0:
            if loaded is None:
                loaded = load_tile(job.poses, reference, observed, padded, s_ref=job.s_ref,
                                   s_obs=job.s_obs, gain=gain, offset=offset)
        else:  # a re-run reads and reblurs only the ring the larger halo adds
            loaded = grow_tile(job.poses, reference, observed, prev, loaded, padded,
                               s_ref=job.s_ref, s_obs=job.s_obs, gain=gain, offset=offset)
        obs, reb, unk = loaded
        prev = padded
        # where the local displacement field is uncertain, the tolerance reaches farther
        fld = getattr(job.poses, "field", None)
        reach = (fld.reach_map(padded, job.params.geometry_reach)
                 if fld is not None and job.params.geometry_reach > 0 else None)
        # an attempt that will be re-run stops as soon as it is known to be incomplete
        mask, info = decide_tile(
            obs, reb, unk, threshold=job.threshold, photometry=job.photometry, box=padded,
            core=core, params=job.params, image_shape=(H, W), stop_incomplete=not last,
            statistic=stat, keep_statistic=not last, reach=reach, max_extent=max_extent,
        )
        pixels += padded[2] * padded[3]
        stat = info.pop("statistic", None)
        if not info["reach"] or last:  # complete, or only oversize regions reach the edge
            break
        if attempt + 1 < _LARGEST:  # twice the halo where a region came too close to the edge
            for side in info["reach"]:
                halo[side] *= 2
        elif attempt + 1 == _LARGEST:  # the largest halo on every edge a region has reached
            for side in sides:
                if halo[side] > job.halo or side in info["reach"]:
                    halo[side] = big
        else:  # a region reached another edge: the largest halo on every edge
            halo = dict.fromkeys(sides, big)
        padded = pad_box(core, [halo[side] for side in sides], (H, W))
    ly, lx = core[0] - padded[0], core[1] - padded[1]
    sl = (slice(ly, ly + core[2]), slice(lx, lx + core[3]))
    cs = (slice(core[0], core[0] + core[2]), slice(core[1], core[1] + core[3]))
    m = None
    if job.reblurred_out is not None:
        m = job.photometry.apply(reb[sl], core)
        m = m[:, :, 0] if job.two_d else m
    if job.lock_writes:
        _WRITE_LOCK.acquire()
    try:
        job.change_out[cs] = mask
        job.unknown_out[cs] = unk[sl]
        if m is not None:
            job.reblurred_out[cs] = m
    finally:
        if job.lock_writes:
            _WRITE_LOCK.release()
    return {"core": core, "regions": info["regions"], "complete": bool(info["complete"]),
            "oversize": int(info["oversize"]), "attempts": attempt + 1, "pixels": pixels}
