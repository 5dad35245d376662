"""The Dask backend computes exactly what the local path computes.

The reference result is the default local path (a thread pool pulling tiles), computed
independently of Dask; the Dask runs (threads, processes, a two-worker LocalCluster) must
reproduce its masks, reblurred image, regions and threshold bit for bit on a multi-tile
image, with inputs in memory and as tiled TIFF files.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import time

import numpy as np
import pytest
import tifffile
import zarr

import reblur
from reblur.dask_backend import TiffSource, portable, scheduler_kind, tile_bands
from reblur.simulate import make_pair

TILE = 256


@pytest.fixture(scope="module")
def pair(levir_gray):
    # 640 x 896 -> 3 x 4 tiles of 256 px; changes and a viewpoint change inside the grid
    img = levir_gray[:640, :896]
    p = make_pair(img, rng=11, shake=dict(t_max=4.0, rz_max=0.5), viewpoint=None,
                  n_changes=4, moving=False, low_contrast=False)
    ref = np.clip(np.round(p.reference * 255), 0, 255).astype(np.uint8)
    obs = np.clip(np.round(p.observed * 255), 0, 255).astype(np.uint8)
    return ref, obs, p.truth


@pytest.fixture(scope="module")
def local(pair):
    ref, obs, truth = pair
    res = reblur.detect_changes(ref, obs, align=False, t_max=5, rz_max=1.0, tile_size=TILE)
    # the fixture is meaningful: it finds the pasted changes and is multi-tile
    assert res.decision["n_tiles"] == 12
    assert reblur.metrics.jaccard(truth, res.change) > 0.5
    return res


def _same(a, b) -> None:
    np.testing.assert_array_equal(np.asarray(a.change[...]), np.asarray(b.change[...]))
    np.testing.assert_array_equal(np.asarray(a.unknown[...]), np.asarray(b.unknown[...]))
    np.testing.assert_array_equal(a.motion.weights, b.motion.weights)
    assert a.threshold == b.threshold
    assert a.regions == b.regions
    if a.reblurred is not None and b.reblurred is not None:
        np.testing.assert_array_equal(np.asarray(a.reblurred), np.asarray(b.reblurred))


@pytest.mark.parametrize("scheduler", ["threads", "processes"])
def test_local_dask_schedulers_match_local_path(pair, local, scheduler):
    ref, obs, _ = pair
    res = reblur.detect_changes(ref, obs, align=False, t_max=5, rz_max=1.0, tile_size=TILE,
                                scheduler=scheduler, workers=2)
    assert res.decision["backend"]["kind"] == scheduler
    _same(local, res)


def _tiffs(tmp_path, ref, obs):
    paths = []
    for name, a in (("ref", ref), ("obs", obs)):
        p = tmp_path / f"{name}.tif"
        tifffile.imwrite(p, a, tile=(128, 128), compression="zstd")
        paths.append(p)
    return paths


def test_local_cluster_two_workers_matches_local_path(pair, local, tmp_path):
    distributed = pytest.importorskip("distributed")
    ref, obs, _ = pair
    ref_p, obs_p = _tiffs(tmp_path, ref, obs)
    # the files are read lazily, as the CLI does, and reopened by path in each worker
    ref_z = zarr.open(tifffile.imread(ref_p, aszarr=True), mode="r")
    obs_z = zarr.open(tifffile.imread(obs_p, aszarr=True), mode="r")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        with distributed.Client(cluster) as client, distributed.get_task_stream(client) as ts:
            res = reblur.detect_changes(ref_z, obs_z, align=False, t_max=5, rz_max=1.0,
                                        tile_size=TILE, scheduler=cluster.scheduler_address,
                                        work_dir=tmp_path / "work")
    # every tile ran as a task, on both workers; the estimate ran once, on one worker
    tiles = [t for t in ts.data if "reblur-tile" in str(t["key"])]
    assert len(tiles) == 12
    assert len({t["worker"] for t in tiles}) == 2
    assert sum("_estimate_stage" in str(t["key"]) for t in ts.data) == 1
    assert res.decision["backend"]["kind"] == "distributed"
    _same(local, res)
    # small image: masks came back as numpy and the work store was removed
    assert isinstance(res.change, np.ndarray)
    assert not (tmp_path / "work").exists() or not any((tmp_path / "work").iterdir())


@pytest.mark.parametrize("ny,n", [(1, 1), (1, 4), (3, 2), (10, 3), (7, 7), (100, 6)])
def test_tile_bands_partition_the_rows_into_contiguous_near_equal_bands(ny, n):
    bands = tile_bands(ny, n)
    assert len(bands) == min(ny, n)
    assert [r for b in bands for r in b] == list(range(ny))  # contiguous, in order, all
    sizes = [len(b) for b in bands]
    assert max(sizes) - min(sizes) <= 1 and min(sizes) >= 1
    with pytest.raises(ValueError, match="worker"):
        tile_bands(ny, 0)


class _RecordingClient:
    """A client that records what it is asked to compute, and where."""

    def __init__(self, workers):
        self.workers = workers
        self.calls = []

    def scheduler_info(self):
        return {"workers": {w: {} for w in self.workers}}

    def compute(self, blocks, workers=None, allow_other_workers=False):
        self.calls.append((list(blocks), workers, allow_other_workers))
        return list(blocks)


def test_tiles_go_to_workers_in_bands_of_rows_with_a_loose_preference():
    from reblur.dask_backend import _submit_in_bands

    blocks = np.empty((5, 4), object)
    for i in range(5):
        for j in range(4):
            blocks[i, j] = (i, j)
    client = _RecordingClient(["tcp://b:2", "tcp://a:1", "tcp://c:3"])
    futures = _submit_in_bands(client, blocks)
    assert sorted(futures) == sorted(blocks.ravel().tolist())  # every tile, once
    rows = [sorted({i for i, _ in c[0]}) for c in client.calls]
    assert rows == [[0, 1], [2], [3, 4]]  # contiguous bands, near equal
    assert [c[1] for c in client.calls] == [["tcp://a:1"], ["tcp://b:2"], ["tcp://c:3"]]
    assert all(c[2] for c in client.calls)  # idle workers may still take tiles
    # one worker (or none yet): no preference
    client = _RecordingClient(["tcp://a:1"])
    _submit_in_bands(client, blocks)
    assert [(len(c[0]), c[1]) for c in client.calls] == [(20, None)]


def test_large_outputs_stay_in_zarr(pair, local, tmp_path, monkeypatch):
    import reblur.dask_backend as db

    ref, obs, _ = pair
    monkeypatch.setattr(db, "NUMPY_MAX_PIXELS", 1000)  # pretend the image is huge
    res = reblur.detect_changes(ref, obs, align=False, t_max=5, rz_max=1.0, tile_size=TILE,
                                scheduler="processes", workers=2, work_dir=tmp_path / "w",
                                keep_reblurred=False)
    assert isinstance(res.change, zarr.Array)
    assert res.change.chunks == (TILE, TILE)
    assert res.decision["backend"]["store"] == str(tmp_path / "w")
    np.testing.assert_array_equal(res.change[...], local.change)
    np.testing.assert_array_equal(res.unknown[...], local.unknown)


def test_tiff_source_reads_windows_and_pickles(tmp_path):
    rng = np.random.default_rng(0)
    a = rng.integers(0, 65535, (300, 200, 3), dtype=np.uint16)
    p = tmp_path / "a.tif"
    tifffile.imwrite(p, a, tile=(64, 64))
    src = TiffSource(p)
    assert src.shape == a.shape and src.dtype == a.dtype
    np.testing.assert_array_equal(src[17:140, 5:199], a[17:140, 5:199])
    back = pickle.loads(pickle.dumps(src))
    np.testing.assert_array_equal(back[250:, :30], a[250:, :30])
    # a zarr array over tifffile's store is not picklable; portable() reopens it by path
    z = zarr.open(tifffile.imread(p, aszarr=True), mode="r")
    with pytest.raises(TypeError):
        pickle.dumps(z)
    pz = pickle.loads(pickle.dumps(portable(z)))
    np.testing.assert_array_equal(pz[100:120, 60:70], a[100:120, 60:70])


def test_scheduler_names():
    assert scheduler_kind("threads") == "threads"
    assert scheduler_kind("processes") == "processes"
    assert scheduler_kind("tcp://127.0.0.1:8786") == "distributed"
    with pytest.raises(ValueError, match="unknown scheduler"):
        scheduler_kind("gpu")


def test_cli_scheduler_flag_same_mask(pair, tmp_path):
    ref, obs, _ = pair
    ref_p, obs_p = _tiffs(tmp_path, ref, obs)
    outs = {}
    for name, extra in (("plain", []), ("dask", ["--scheduler", "threads", "--workers", "2"])):
        out = tmp_path / name
        r = subprocess.run(
            [sys.executable, "-m", "reblur", "detect", str(ref_p), str(obs_p), "--out", str(out),
             "--t-max", "5", "--rz-max", "1", "--tile-size", str(TILE), "--quiet", *extra],
            capture_output=True, text=True, timeout=600,
        )
        assert r.returncode == 0, r.stderr
        outs[name] = tifffile.imread(out / "reblurred.tif"), _png(out / "changes.png")
    np.testing.assert_array_equal(outs["plain"][1], outs["dask"][1])
    np.testing.assert_array_equal(outs["plain"][0], outs["dask"][0])
    assert not list((tmp_path / "dask").glob(".reblur-work-*"))  # the work store is gone
    bad = subprocess.run(
        [sys.executable, "-m", "reblur", "detect", str(ref_p), str(obs_p), "--out",
         str(tmp_path / "bad"), "--scheduler", "gpu"], capture_output=True, text=True,
        timeout=120,
    )
    assert bad.returncode != 0
    assert "Traceback" not in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
    assert "scheduler" in bad.stderr
    assert not (tmp_path / "bad").exists() or not any((tmp_path / "bad").iterdir())


def _png(path):
    import cv2

    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


def test_cli_large_inputs_keep_masks_on_disk(pair, tmp_path, monkeypatch):
    """Above LARGE_MASK_PIXELS the CLI has the masks written into a zarr store in the output
    directory (not memory): same outputs, store removed afterwards."""
    from click.testing import CliRunner

    import reblur.cli as cli

    ref, obs, _ = pair
    ref_p, obs_p = _tiffs(tmp_path, ref, obs)
    seen = {}
    real = reblur.detect_changes

    def spy(*a, **k):
        seen.update(k)
        return real(*a, **k)

    def run(out):
        r = CliRunner().invoke(cli.main, [
            "detect", str(ref_p), str(obs_p), "--out", str(out), "--t-max", "5", "--rz-max",
            "1", "--tile-size", str(TILE), "--quiet"])
        assert r.exit_code == 0, r.output
        return _png(out / "changes.png"), _png(out / "unknown.png")

    plain = run(tmp_path / "plain")
    monkeypatch.setattr(cli, "LARGE_MASK_PIXELS", 1000)
    monkeypatch.setattr(reblur, "detect_changes", spy)
    out = tmp_path / "large"
    large = run(out)
    assert isinstance(seen["change_out"], zarr.Array)
    np.testing.assert_array_equal(plain[0], large[0])
    np.testing.assert_array_equal(plain[1], large[1])
    assert (plain[0] > 0).any()
    assert not list(out.glob(".reblur-work-*"))


_MALLOC_PROBE = """
import ctypes, resource, sys
import numpy as np
# numpy asks for transparent huge pages for large arrays: one fault would then map 2 MB
np._core.multiarray._set_madvise_hugepage(False)
from reblur.tilejob import tune_worker_malloc

class Info(ctypes.Structure):  # glibc's struct mallinfo2
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks",
                "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]

libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = Info

def mmapped_by_an_8mb_array():
    a = np.ones(1 << 20)  # freed at once: lets glibc's dynamic threshold adapt, if it may
    del a
    before = libc.mallinfo2().hblks
    a = np.ones(1 << 20)  # 8 MiB: more than the free lists of a fresh process hold
    return libc.mallinfo2().hblks - before

def faults_of_reallocations(n=4):
    a = np.ones(1 << 20)  # 8 MiB, written: every page touched
    del a
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(n):
        a = np.ones(1 << 20)
        del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

first = mmapped_by_an_8mb_array()
faults = faults_of_reallocations()
tuned = tune_worker_malloc()
print(first, tuned, tune_worker_malloc(), mmapped_by_an_8mb_array(), faults,
      faults_of_reallocations())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")
def test_worker_malloc_tuning_keeps_array_temporaries_on_the_heap():
    """A distributed nanny's MALLOC_TRIM_THRESHOLD_ freezes glibc's mmap threshold at
    128 KB: an 8 MiB array is mmapped (counted by mallinfo2's hblks) even after one was
    freed, where glibc's default would have raised the threshold.  After
    tune_worker_malloc it comes from the heap; without the variable, or with a chosen
    MALLOC_MMAP_THRESHOLD_, nothing is changed.

    Page faults: re-allocating a freed 8 MiB array four times faults in its 2048 pages
    every time when the memory went back to the system in between (an mmap, or the
    nanny's 64 KB trim threshold trimming the heap's top); once tuned, a freed array's
    pages are reused, as with glibc's default (fewer faults than one array has pages)."""
    import resource

    pages = (8 << 20) // resource.getpagesize()
    try:  # with transparent huge pages always on, one fault maps 2 MB: no page counts
        with open("/sys/kernel/mm/transparent_hugepage/enabled") as f:
            counts = "[always]" not in f.read()
    except OSError:
        counts = True

    def probe(env):
        out = subprocess.run([sys.executable, "-c", _MALLOC_PROBE], env=env, check=True,
                             capture_output=True, text=True).stdout.split()
        return out[:4], int(out[4]), int(out[5])

    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    nanny = dict(env, MALLOC_TRIM_THRESHOLD_="65536")
    flags, before, after = probe(nanny)
    assert flags == ["1", "True", "False", "0"]
    assert not counts or (before > 3 * pages and after < pages), (before, after)
    flags, before, after = probe(env)
    assert flags == ["0", "False", "False", "0"]  # glibc's default adapts by itself
    assert not counts or after < pages, (before, after)
    chosen = dict(nanny, MALLOC_MMAP_THRESHOLD_="131072")
    flags, before, after = probe(chosen)
    assert flags == ["1", "False", "False", "1"]
    assert not counts or (before > 3 * pages and after > 3 * pages), (before, after)


def test_cli_on_a_real_cluster_without_a_default_client(pair, tmp_path):
    """The README's recipe: `dask scheduler`, two `dask worker` processes, then
    `reblur detect ... --scheduler tcp://...` in a process that has no default client.
    The masks equal the local path's."""
    ref, obs, _ = pair
    ref_p, obs_p = _tiffs(tmp_path, ref, obs)
    dask_cli = os.path.join(os.path.dirname(sys.executable), "dask")
    sched_file = tmp_path / "scheduler.json"
    env = dict(os.environ, DASK_DISTRIBUTED__WORKER__DAEMON="False")
    procs = [subprocess.Popen([dask_cli, "scheduler", "--host", "127.0.0.1", "--port", "0",
                               "--no-dashboard", "--scheduler-file", str(sched_file)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)]
    try:
        for _ in range(600):  # the scheduler writes its address when it is up
            if sched_file.exists() and sched_file.stat().st_size > 0:
                break
            procs[0].wait(timeout=0.05) if procs[0].poll() is not None else time.sleep(0.05)
        import json

        address = json.loads(sched_file.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        for _ in range(2):
            procs.append(subprocess.Popen(
                [dask_cli, "worker", address, "--nthreads", "1", "--no-dashboard",
                 "--host", "127.0.0.1"],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env))
        outs = {}
        for name, extra in (("local", []), ("cluster", ["--scheduler", address])):
            out = tmp_path / name
            r = subprocess.run(
                [sys.executable, "-m", "reblur", "detect", str(ref_p), str(obs_p), "--out",
                 str(out), "--t-max", "5", "--rz-max", "1", "--tile-size", str(TILE),
                 "--quiet", *extra], capture_output=True, text=True, timeout=600)
            assert r.returncode == 0, r.stderr
            outs[name] = _png(out / "changes.png")
        np.testing.assert_array_equal(outs["local"], outs["cluster"])
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()


def test_process_task_graphs_carry_paths_not_images(pair, local, monkeypatch, tmp_path):
    # numpy inputs are written once to zarr and the tasks read them by path: the pickled
    # graph is a few kB, not the images (at cb9c21e it held both, 2 x 573 kB here; 100 MP
    # pairs were copied into every task: 184 s and 4.1 GB against 42 s and 1.0 GB)
    import reblur.dask_backend as db

    ref, obs, _ = pair
    seen = []
    compute = db._compute

    def spy(graph, *args, **kwargs):
        graph_dict = dict(graph.__dask_graph__())
        seen.append((len(pickle.dumps(graph_dict)),
                     [type(v).__name__ for v in graph_dict.values()
                      if isinstance(v, np.ndarray) and v.size > 1]))
        return compute(graph, *args, **kwargs)

    monkeypatch.setattr(db, "_compute", spy)
    res = reblur.detect_changes(ref, obs, align=False, t_max=5, rz_max=1.0, tile_size=TILE,
                                scheduler="processes", workers=2, work_dir=tmp_path)
    _same(local, res)
    (size, arrays), = seen
    assert not arrays
    assert size < ref.nbytes // 4, size
    # the readers in the graph are zarr copies under work_dir, equal to the inputs
    z = portable(ref, "reference", tmp_path)
    assert str(tmp_path) in str(z.store)
    np.testing.assert_array_equal(np.asarray(z[...]), ref)
    assert len(pickle.dumps(z)) < 10_000
    assert portable(ref, "reference", tmp_path) is z  # written once per array


def test_masked_views_travel_by_path(tmp_path):
    """An image with no-data pixels (``io.MaskedView`` over a numpy array, its validity a
    ``NodataMask`` of the same array) goes to worker processes as paths, not pixels, and reads
    the same NaN there."""
    import pickle

    from reblur.dask_backend import portable
    from reblur.io import MaskedView, NodataMask

    a = (np.random.default_rng(0).random((600, 600)) * 255).astype(np.uint8)
    a[100:200, 100:300] = 0
    v = MaskedView(a, NodataMask(a, 0))
    p = portable(v, "ref", tmp_path)
    assert len(pickle.dumps(p)) < a.nbytes // 20
    got, want = pickle.loads(pickle.dumps(p))[50:250, 50:350], v[50:250, 50:350]
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    assert np.isnan(want).sum() >= 100 * 200
    np.testing.assert_array_equal(np.nan_to_num(got), np.nan_to_num(want))


def test_tile_tasks_carry_keys_not_the_job(tmp_path):
    """Each tile task of the graph names the shared job and readers by key: its pickled size
    stays under 2 kB whatever the image or the job weighs, and the job's bytes enter the
    graph once (a job of 1 MB, 16 and 256 tiles: the graph is 1 MB plus a constant per
    tile, not 16 or 256 MB)."""
    import types

    from reblur.dask_backend import tile_graph

    blob = np.ones(1 << 17)  # 1 MiB standing for the pose weights and models
    for side in (1000, 4000):
        job = types.SimpleNamespace(image_shape=(side, side), blob=blob)
        z = zarr.create_array(str(tmp_path / f"img{side}"), shape=(side, side),
                              chunks=(256, 256), dtype=np.uint8)
        graph = dict(tile_graph(job, z, z, 256).__dask_graph__())
        n_tiles = (-(-side // 256)) ** 2
        tiles = [v for k, v in graph.items() if isinstance(k, tuple)]
        assert len(tiles) == n_tiles and len(graph) == n_tiles + 3
        assert max(len(pickle.dumps(t)) for t in tiles) < 2000
        assert len(pickle.dumps(graph)) < blob.nbytes + 2000 * (n_tiles + 3)
