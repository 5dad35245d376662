"""The tiled reblur-and-decide pass as a Dask graph, and readers Dask workers can use.

The graph is a :func:`dask.array.map_blocks` over the grid of output tiles: block ``(i, j)``
is one task that reads its own padded observation window and the reference window its
poses touch (the halo comes from the poses and the tile's position -- a rotation about a
distant principal point moves far pixels by radius x angle -- not from a fixed overlap
depth, so ``map_overlap`` would be wrong here), reblurs and decides it with
:func:`reblur.tilejob.run_tile` (the very function of the local path), and writes its core
into the outputs (chunked zarr arrays) before it returns.  Only the tile's bookkeeping
(regions, completeness) travels back to the client: nothing full-size is ever gathered in
one process.  What every task shares -- :class:`reblur.tilejob.TileJob` (sparse pose
weights, photometric model, threshold, decision parameters) and the two image readers --
enters the graph once.

Schedulers
----------
``"threads"`` (or ``"sync"``)
    Dask's local thread pool in this process; inputs and outputs are used as they are
    (numpy outputs are allowed).
``"processes"``
    Dask's local process pool.  Inputs are read by path inside the tasks: zarr arrays on a
    local or shared store, file paths, TIFF-backed zarr arrays (:func:`portable` reopens
    them by path in each worker), and numpy arrays, which :func:`portable` writes once to
    a zarr store (``work_dir``) that the tasks read (an image pickled into the tasks was
    copied into every one: 100 MP took 184 s and 4.1 GB against 42 s and 1.0 GB locally,
    issue #28).  Outputs are zarr arrays.
``"tcp://host:port"`` (or a :class:`distributed.Client`, or ``"distributed"`` for the
current default client)
    A Dask distributed cluster.  Inputs travel as readers (each worker opens the files
    itself: a cluster on several machines must see the same paths); numpy inputs are
    written to a zarr store first, as for ``"processes"``.  Outputs are zarr arrays every
    worker can write (``work_dir`` / the output arrays on shared storage for a cluster on
    several machines).

Outputs written by several processes must have chunks that divide the tile size, so that
no two tasks write the same chunk.  When no output array is given, masks go to a zarr store
in a temporary directory (or ``store``) and are loaded into numpy when the image has at
most :data:`NUMPY_MAX_PIXELS` pixels (the store is then deleted); larger images come back
as zarr arrays in that store (``info["store"]``; the caller deletes it).
"""

from __future__ import annotations

import atexit
import copy
import os
import pickle
import shutil
import tempfile
import threading
import uuid
import weakref
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np

from .decide import DecisionParams, Photometry
from .io import chunk_cached, scratch_compressors
from .tiled import SparsePoses
from .tilejob import TileJob, pad_box, run_tile, tile_work, tune_worker_malloc

__all__ = [
    "NUMPY_MAX_PIXELS",
    "TiffSource",
    "TilesOutput",
    "decide_tiles",
    "open_source",
    "portable",
    "run_once",
    "scheduler_kind",
    "tile_bands",
    "tile_graph",
]

#: Masks of images up to this many pixels are returned as numpy arrays (as the local path).
NUMPY_MAX_PIXELS = 64_000_000

_LOCAL = ("threads", "threading", "sync", "synchronous", "single-threaded")


# ---------------------------------------------------------------------------- sources
class TiffSource:
    """A picklable, lazily opened window reader of one TIFF image (series and level).

    Slicing returns numpy arrays and reads only the tiles or strips it needs (through
    tifffile's zarr store).  The file is opened on first use in each process and kept open;
    pickling drops the handle, so a worker reopens the file by path.

    Parameters
    ----------
    path : str or path-like
        TIFF file (classic or BigTIFF, tiled or striped).
    series, level : int
        Image series and pyramid level.
    squeeze : bool, optional
        tifffile's ``squeeze`` (drop length-1 axes); default tifffile's.
    """

    def __init__(self, path, series: int = 0, level: int = 0, squeeze: bool | None = None):
        self.path = str(path)
        self.series = int(series)
        self.level = int(level)
        self.squeeze = squeeze
        self._lock = threading.Lock()
        self._tif = None
        self._z = None
        z = self._array()
        self.shape = tuple(int(s) for s in z.shape)
        self.dtype = np.dtype(z.dtype)
        self.ndim = len(self.shape)
        self.chunks = tuple(z.chunks)

    def _array(self):
        if self._z is None:
            with self._lock:
                if self._z is None:
                    import tifffile
                    import zarr

                    tif = tifffile.TiffFile(self.path)
                    kw = {} if self.squeeze is None else {"squeeze": self.squeeze}
                    store = tif.series[self.series].aszarr(level=self.level, **kw)
                    self._z = zarr.open(store, mode="r")
                    self._tif = tif
        return self._z

    def __getitem__(self, key) -> np.ndarray:
        return np.asarray(self._array()[key])

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state.update(_tif=None, _z=None, _lock=None)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()

    def close(self) -> None:
        """Close the file (it is reopened on the next read)."""
        with self._lock:
            if self._tif is not None:
                self._tif.close()
            self._tif = self._z = None

    def __repr__(self) -> str:
        return f"TiffSource({self.path!r}, series={self.series}, level={self.level}, {self.shape})"


def open_source(path) -> Any:
    """Open an image file lazily for the workers: a :class:`TiffSource` or a zarr array.

    Parameters
    ----------
    path : str or path-like
        A TIFF file, or a zarr array directory (a group holding an array ``"0"`` works
        too).

    Returns
    -------
    array-like
        Picklable, sliceable reader (``shape``, ``dtype``, ``a[y0:y1, x0:x1]``).
    """
    p = Path(path)
    if p.is_dir():
        import zarr

        node = zarr.open(str(p), mode="r")
        if not hasattr(node, "shape"):
            node = node["0"]
        return node
    with open(p, "rb") as fh:
        head = fh.read(4)
    if head in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return TiffSource(p)
    raise ValueError(f"{p}: only TIFF files and zarr arrays can be read by Dask workers")


def _tiff_source_of(z) -> TiffSource | None:
    """The :class:`TiffSource` equivalent of a zarr array over tifffile's store, if any."""
    store = getattr(z, "store", None)
    if type(store).__name__ != "ZarrTiffStore":
        return None
    data = getattr(store, "_data", None)
    if not isinstance(data, list) or len(data) != 1:
        return None
    ser = data[0]
    parent = getattr(ser, "parent", None)
    path = getattr(getattr(parent, "filehandle", None), "path", None)
    if not path:
        return None
    for i, s in enumerate(parent.series):
        for lv, level in enumerate(s.levels):
            if level is ser:
                src = TiffSource(path, i, lv, squeeze=getattr(store, "_squeeze", None))
                if src.shape == tuple(z.shape) and src.dtype == np.dtype(z.dtype):
                    return src
                src.close()
                return None
    return None


#: Chunk side of the zarr copies of numpy inputs (:func:`portable`).
SPILL_CHUNK = 512
#: zarr copies of numpy inputs, by ``id`` of the array and store: made once per array,
#: store and process, removed when the array is freed (or at exit).
_SPILLED: dict[tuple[int, str], Any] = {}
_SPILL_LOCK = threading.Lock()


def _spill(a: np.ndarray, name: str, store) -> Any:
    """A zarr copy of ``a`` on disk (under ``store``, else a temporary directory), read by
    path in the tasks; one per array, removed with it."""
    import zarr

    with _SPILL_LOCK:
        key = (id(a), str(store))
        z = _SPILLED.get(key)
        if z is not None and tuple(z.shape) == a.shape and np.dtype(z.dtype) == a.dtype:
            return z
        if store is not None:
            Path(store).mkdir(parents=True, exist_ok=True)
        root = Path(tempfile.mkdtemp(prefix=f"reblur-{name}-",
                                     dir=None if store is None else str(store)))
        chunks = (SPILL_CHUNK, SPILL_CHUNK) + tuple(a.shape[2:])
        z = zarr.create_array(str(root / "0"), shape=a.shape, chunks=chunks, dtype=a.dtype,
                              fill_value=0, overwrite=True,
                              compressors=scratch_compressors(a.dtype))
        for y in range(0, a.shape[0], 4 * SPILL_CHUNK):
            z[y : y + 4 * SPILL_CHUNK] = a[y : y + 4 * SPILL_CHUNK]
        z = zarr.open_array(str(root / "0"), mode="r")
        _SPILLED[key] = z

        def drop(key=key, root=root) -> None:
            _SPILLED.pop(key, None)
            shutil.rmtree(root, ignore_errors=True)

        weakref.finalize(a, drop)
        atexit.register(shutil.rmtree, root, True)
        return z


def _local_copy(a) -> bool:
    """Whether ``a``, or a view it wraps, reads a temporary store of this machine
    (:class:`reblur._decoded.DecodedImage`)."""
    for _ in range(8):
        if getattr(a, "temporary", False):
            return True
        a = getattr(a, "source", None)
        if a is None:
            return False
    return False


def portable(a, name: str = "image", store=None) -> Any:
    """An equivalent reader of ``a`` that can be pickled to other processes, reading the
    image by path: never the pixels themselves.

    Parameters
    ----------
    a : array-like or str or path-like
        numpy array or a PNG / JPEG decoded into a temporary store (written once to a zarr
        array under ``store``, which is returned; without ``store`` the temporary store is
        read where it is, by processes of this machine),
        file path (:func:`open_source`), zarr array (as is when picklable, reopened by path
        when it wraps a TIFF file), or a lazy view with a ``source`` attribute (such as
        :class:`reblur.io.LazyBands`), converted recursively.
    name : str
        Used in error messages and the name of a numpy array's copy.
    store : path, optional
        Directory of the zarr copies of numpy arrays (workers on other machines must see
        it); default a temporary directory.  The copy is removed when the array is freed.

    Returns
    -------
    array-like

    Raises
    ------
    TypeError
        When ``a`` cannot be made picklable (pass a file path instead).
    """
    if isinstance(a, (str, os.PathLike)):
        return open_source(a)
    if isinstance(a, np.ndarray):
        return _spill(a, name, store)
    from .io import AlphaMask, MaskedView, NodataMask

    if isinstance(a, MaskedView):  # no-data pixels as NaN: the image and its validity
        return MaskedView(portable(a.array, name, store),
                          portable(a.valid, f"{name} validity", store))
    if isinstance(a, NodataMask):
        return NodataMask(portable(a.array, name, store), a.value)
    if isinstance(a, AlphaMask):
        return AlphaMask(portable(a.alpha, f"{name} alpha", store))
    src = _tiff_source_of(a)
    if src is not None:
        return src
    if store is not None and _local_copy(a):
        # a PNG / JPEG decoded into a temporary store: copied where the workers can see it
        if getattr(a, "temporary", False):
            return _spill(a, name, store)
        b = copy.copy(a)
        b.source = portable(a.source, name, store)
        return b
    try:
        pickle.dumps(a)
        return a
    except Exception:  # noqa: BLE001 - any pickling failure: try the wrapped source
        pass
    if hasattr(a, "source"):
        b = copy.copy(a)
        b.source = portable(a.source, name, store)
        return b
    raise TypeError(
        f"{name} ({type(a).__name__}) cannot be sent to Dask worker processes: pass a file "
        "path, a zarr array or a numpy array, or use scheduler='threads'"
    )


# ---------------------------------------------------------------------------- graph
class TilesOutput(NamedTuple):
    """Result of :func:`decide_tiles`."""

    change: Any
    unknown: Any
    reblurred: Any
    regions: list[dict[str, Any]]
    incomplete: int
    info: dict[str, Any]


def scheduler_kind(scheduler) -> str:
    """``"threads"``, ``"processes"`` or ``"distributed"`` for a ``scheduler`` argument.

    Raises
    ------
    ValueError, TypeError
        For an unknown scheduler name or type.
    """
    if hasattr(scheduler, "submit") and hasattr(scheduler, "scatter"):
        return "distributed"
    if not isinstance(scheduler, str):
        raise TypeError(f"scheduler must be a string or a distributed.Client, got {scheduler!r}")
    s = scheduler.strip().lower()
    if s in _LOCAL:
        return "threads"
    if s in ("processes", "multiprocessing"):
        return "processes"
    if s == "distributed" or "://" in s:
        return "distributed"
    raise ValueError(
        f"unknown scheduler {scheduler!r}: use 'threads', 'processes', 'tcp://host:port' "
        "or a distributed.Client"
    )


@contextmanager
def _client(scheduler) -> Iterator[Any]:
    """A distributed client for ``scheduler`` (closed afterwards if opened here)."""
    import distributed

    if hasattr(scheduler, "submit"):
        yield scheduler
    elif scheduler.strip().lower() == "distributed":
        yield distributed.get_client()
    else:
        client = distributed.Client(scheduler, set_as_default=False)
        try:
            yield client
        finally:
            client.close()


def _aligned(out, tile_size: int) -> bool:
    """Every tile core maps to whole chunks of ``out`` (so no two tasks share a chunk)."""
    chunks = getattr(out, "chunks", None)
    if not chunks or not isinstance(chunks[0], (int, np.integer)):
        return False
    return tile_size % int(chunks[0]) == 0 and tile_size % int(chunks[1]) == 0


def _zarr_out(root: Path, name: str, shape, chunks, dtype):
    import zarr

    return zarr.create_array(
        str(root / name), shape=shape, chunks=chunks, dtype=dtype, fill_value=0,
        overwrite=True, compressors=scratch_compressors(dtype),
    )


def decide_tiles(
    reference,
    observed,
    poses: SparsePoses,
    *,
    scheduler,
    s_ref: float,
    s_obs: float,
    gain: np.ndarray,
    offset: np.ndarray,
    threshold: float,
    photometry: Photometry,
    params: DecisionParams,
    halo: int,
    tile_size: int,
    workers: int = 1,
    keep_reblurred: bool = True,
    change_out=None,
    unknown_out=None,
    reblurred_out=None,
    store: str | os.PathLike | None = None,
    progress: Callable[[float], None] | None = None,
) -> TilesOutput:
    """Run pass 2 (every padded tile: reblur, decide, write the core) on Dask.

    Parameters
    ----------
    reference, observed : array-like or path
        The images as given to :func:`reblur.pipeline.reblur_and_decide` (numpy, zarr,
        tifffile-backed zarr, lazy views) or file paths (TIFF or zarr).
    poses : SparsePoses
        Estimated pose weights (small: shipped to every worker once).
    scheduler : str or distributed.Client
        ``"threads"``, ``"processes"``, ``"tcp://host:port"``, ``"distributed"`` (the
        default client) or a client.  See the module notes.
    s_ref, s_obs, gain, offset, threshold, photometry, params, halo
        As computed by pass 1 of :func:`reblur.pipeline.reblur_and_decide`.
    tile_size : int
        Core tile side (zarr outputs created here are chunked by it); the tiles are those
        of :func:`reblur.decide.tile_boxes`.
    workers : int
        Threads / processes of the local schedulers (ignored by a cluster).
    keep_reblurred : bool
        Also write the matched reblurred reference.
    change_out, unknown_out, reblurred_out : array-like, optional
        Where to write (full-size, ``(H, W)`` bool; ``(H, W[, C])`` float32).  Zarr arrays
        with chunks dividing ``tile_size`` for the process-based schedulers.
    store : path, optional
        Directory for the zarr outputs created here (default: a new temporary directory).
    progress : callable, optional
        Called with the fraction of tiles done.

    Returns
    -------
    TilesOutput
        ``change``, ``unknown``, ``reblurred`` (numpy for images up to
        :data:`NUMPY_MAX_PIXELS` pixels when no output was given, else the output arrays),
        ``regions`` (sorted like the local path), ``incomplete`` (tiles still incomplete
        after the last re-run, :func:`reblur.tilejob.run_tile`) and ``info`` (scheduler,
        store).
    """
    kind = scheduler_kind(scheduler)
    H, W = observed.shape[:2]
    C = observed.shape[2] if len(observed.shape) == 3 else 1
    two_d = len(observed.shape) == 2
    in_process = kind == "threads"

    # outputs: given arrays, numpy (in-process only) or zarr in a store every worker sees
    created: dict[str, Any] = {}
    root: Path | None = None

    def make(name: str, shape, dtype):
        nonlocal root
        if in_process:
            return np.zeros(shape, dtype)
        if root is None:
            root = Path(store) if store is not None else Path(
                tempfile.mkdtemp(prefix="reblur-dask-"))
            root.mkdir(parents=True, exist_ok=True)
        chunks = (tile_size, tile_size) + tuple(shape[2:])
        created[name] = _zarr_out(root, name, shape, chunks, dtype)
        return created[name]

    if change_out is None:
        change_out = make("change", (H, W), bool)
    if unknown_out is None:
        unknown_out = make("unknown", (H, W), bool)
    if keep_reblurred and reblurred_out is None:
        reblurred_out = make("reblurred", (H, W) if two_d else (H, W, C), np.float32)
    if not keep_reblurred:
        reblurred_out = None
    outs = [o for o in (change_out, unknown_out, reblurred_out) if o is not None]
    aligned = all(_aligned(o, tile_size) for o in outs)
    if not in_process:
        for o in outs:
            if isinstance(o, np.ndarray):
                raise TypeError(
                    f"scheduler {scheduler!r} runs tasks in other processes: outputs must be "
                    "zarr arrays (or leave them None), not numpy arrays"
                )
        if not aligned:
            raise ValueError(
                f"output chunks must divide tile_size={tile_size} so that no two tasks write "
                "the same chunk"
            )

    job = TileJob(
        poses=poses, s_ref=float(s_ref), s_obs=float(s_obs),
        gain=np.asarray(gain, np.float32), offset=np.asarray(offset, np.float32),
        threshold=float(threshold), photometry=photometry, params=params, halo=int(halo),
        image_shape=(int(H), int(W)), two_d=two_d, change_out=change_out,
        unknown_out=unknown_out, reblurred_out=reblurred_out,
        lock_writes=in_process and not aligned, client_pid=os.getpid(),
    )
    if not in_process:
        reference = portable(reference, "reference", store)
        observed = portable(observed, "observed", store)
    # neighbouring tiles read overlapping windows: a worker keeps the chunks it decoded
    # (the readers enter the graph once, so a worker's tasks share them; a process pool
    # unpickles them per task, which keeps only what a task re-reads)
    reference = chunk_cached(reference, tile_size, halo)
    observed = chunk_cached(observed, tile_size, halo)

    graph = tile_graph(job, reference, observed, tile_size)
    try:
        results = _compute(graph, kind, scheduler, workers, progress)
    except BaseException:
        if root is not None:  # nothing half-written is left behind
            for name in created:
                shutil.rmtree(root / name, ignore_errors=True)
            if store is None:
                shutil.rmtree(root, ignore_errors=True)
        raise

    regions = [r for res in results for r in res["regions"]]
    regions.sort(key=lambda r: (r["bbox"][0], r["bbox"][1]) if "bbox" in r else (0, 0))
    incomplete = sum(0 if res["complete"] else 1 for res in results)
    info: dict[str, Any] = {"scheduler": str(scheduler), "kind": kind,
                            "work": tile_work(results)}
    change, unknown, reblurred = change_out, unknown_out, reblurred_out
    if created and H * W <= NUMPY_MAX_PIXELS:
        change = np.asarray(change[...]) if "change" in created else change
        unknown = np.asarray(unknown[...]) if "unknown" in created else unknown
        if reblurred is not None and "reblurred" in created:
            reblurred = np.asarray(reblurred[...])
        if root is not None:  # loaded: remove what was created here
            for name in created:
                shutil.rmtree(root / name, ignore_errors=True)
            if store is None or not any(root.iterdir()):
                shutil.rmtree(root, ignore_errors=True)
    elif root is not None:
        info["store"] = str(root)
    return TilesOutput(change, unknown, reblurred, regions, incomplete, info)




def _tile_block(job: TileJob, reference, observed, tile_size: int, block_id=None) -> np.ndarray:
    """Block ``block_id`` of :func:`tile_graph`: run one tile, return its bookkeeping."""
    i, j = block_id
    H, W = job.image_shape
    y, x = i * tile_size, j * tile_size
    core = (y, x, min(tile_size, H - y), min(tile_size, W - x))
    out = np.empty((1, 1), object)
    out[0, 0] = run_tile(job, reference, observed, pad_box(core, job.halo, (H, W)), core)
    return out


def tile_graph(job: TileJob, reference, observed, tile_size: int):
    """The reblur-and-decide pass as a lazy ``(ny, nx)`` object dask array, one block a tile.

    Block ``(i, j)`` runs :func:`reblur.tilejob.run_tile` on the output tile whose core
    starts at ``(i * tile_size, j * tile_size)``; computing it writes the tile into the
    job's outputs and yields a dict (``core``, ``regions``, ``complete``).  The job and the
    two readers enter the graph once, by name (never hashed, never copied per task).

    Parameters
    ----------
    job : TileJob
    reference, observed : array-like
        Window readers of the two images (see :func:`portable` for other processes).
    tile_size : int
        Core tile side.

    Returns
    -------
    dask.array.Array
        dtype object, chunks of one block per tile.
    """
    import dask
    import dask.array as da

    H, W = job.image_shape
    ny, nx = -(-H // tile_size), -(-W // tile_size)
    tag = uuid.uuid4().hex
    shared = {
        k: dask.delayed(v, name=f"reblur-{k}-{tag}", traverse=False)
        for k, v in (("job", job), ("reference", reference), ("observed", observed))
    }
    return da.map_blocks(
        _tile_block, shared["job"], shared["reference"], shared["observed"], tile_size,
        chunks=((1,) * ny, (1,) * nx), dtype=object, meta=np.empty((0, 0), object),
        name=f"reblur-tile-{tag}",
    )


def tile_bands(ny: int, n_workers: int) -> list[range]:
    """Contiguous bands of tile rows, one per worker (as equal as the rows allow; empty
    bands dropped).

    A tile reads its core and a halo around it, so neighbouring tiles decode the same
    chunks of the inputs; a worker keeps the chunks it decoded (:class:`reblur.io.ChunkCache`),
    so giving it a band of rows decodes most chunks once on the cluster, where tiles handed
    out in turn would have every worker decode nearly every chunk.
    """
    if ny < 1 or n_workers < 1:
        raise ValueError(f"need at least one tile row and one worker, got {ny} and {n_workers}")
    edges = np.linspace(0, ny, min(ny, n_workers) + 1).round().astype(int)
    return [range(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]


def _submit_in_bands(client, blocks: np.ndarray) -> list:
    """Futures of the ``(ny, nx)`` delayed ``blocks``, a band of tile rows preferred on each
    of the cluster's workers (:func:`tile_bands`); the preference is loose, so an idle worker
    still takes (steals) tiles from a busy one.  Without workers yet, no preference."""
    workers = sorted(client.scheduler_info().get("workers", {}))
    if len(workers) < 2:
        return client.compute(blocks.ravel().tolist())
    futures = []
    for addr, rows in zip(workers, tile_bands(blocks.shape[0], len(workers)), strict=False):
        futures += client.compute(blocks[rows.start:rows.stop].ravel().tolist(),
                                  workers=[addr], allow_other_workers=True)
    return futures


def _compute(graph, kind: str, scheduler, workers: int,
             progress: Callable[[float], None] | None) -> list[dict[str, Any]]:
    """Compute the blocks of :func:`tile_graph` on ``scheduler``, reporting progress."""
    import dask

    n = int(np.prod(graph.numblocks))
    if kind == "distributed":
        import distributed

        results: list[dict[str, Any]] = []
        with _client(scheduler) as client:
            futures = _submit_in_bands(client, graph.to_delayed())
            # the client's own loop: as_completed would otherwise look for a default
            # client, and the one opened here is not made the default
            for k, fut in enumerate(distributed.as_completed(futures, loop=client.loop), 1):
                results.append(fut.result()[0, 0])
                fut.release()
                if progress is not None:
                    progress(k / n)
            del futures
        return results

    from dask.callbacks import Callback

    name = graph.name
    done = [0]

    class _Progress(Callback):
        def _posttask(self, key, result, dsk, state, id):  # noqa: A002 - dask's signature
            if isinstance(key, tuple) and key and key[0] == name:
                done[0] += 1
                progress(min(done[0] / n, 1.0))

    num = max(1, int(workers))
    sched = "threads" if kind == "threads" else "processes"
    n_cv = cv2.getNumThreads()
    if kind == "threads":
        cv2.setNumThreads(1)  # one tile per thread: no nested OpenCV thread pools
    try:
        if progress is not None:
            with _Progress():
                (out,) = dask.compute(graph, scheduler=sched, num_workers=num)
        else:
            (out,) = dask.compute(graph, scheduler=sched, num_workers=num)
    finally:
        cv2.setNumThreads(n_cv)
    return [r for r in out.ravel()]


def _on_worker(fn: Callable, *args, **kwargs):
    """``fn(*args, **kwargs)`` on a worker, after :func:`reblur.tilejob.tune_worker_malloc`."""
    tune_worker_malloc()
    return fn(*args, **kwargs)


def run_once(fn: Callable, *args, scheduler=None, **kwargs):
    """Run ``fn(*args, **kwargs)`` once: on one worker of a distributed cluster, else here.

    Used for the motion estimate, so that on a cluster only its small result (the pose
    weights and the alignment) travels back; array arguments must then be picklable
    readers (:func:`portable`).
    """
    if scheduler is None or scheduler_kind(scheduler) != "distributed":
        return fn(*args, **kwargs)
    with _client(scheduler) as client:
        # the task keeps fn's name (dashboards, task streams), not the wrapper's
        key = f"{getattr(fn, '__name__', 'run_once')}-{uuid.uuid4().hex}"
        fut = client.submit(_on_worker, fn, *args, key=key, pure=False, **kwargs)
        try:
            return fut.result()
        finally:
            fut.release()
