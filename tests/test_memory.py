"""Fresh arrays faulted in by several threads (``reblur._memory``)."""

import numpy as np
import pytest

from reblur import _memory


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("shape", [(7, 5), (3, 1234, 2345), (5_000_003,)])
def test_zeros_overwrites_every_byte(monkeypatch, threads, shape):
    """``np.empty`` is made to return garbage: every element must come back zero, also
    across the threads' chunk boundaries (odd sizes) and above the parallel size."""

    def dirty(shape, dtype):
        a = np.ones(shape, dtype)
        a.reshape(-1).view(np.uint8)[:] = 0xAB
        return a

    monkeypatch.setattr(_memory, "_PARALLEL_BYTES", 1024)  # the parallel path on any size
    monkeypatch.setattr(_memory.np, "empty", dirty)
    a = _memory.zeros(shape, np.complex64, threads=threads)
    monkeypatch.undo()
    assert a.shape == shape and a.dtype == np.complex64
    assert np.count_nonzero(a.view(np.uint8)) == 0


@pytest.mark.parametrize("threads", [1, 2, 3, 20])
def test_split_sum_covers_every_item_once(threads):
    """Every item lands in exactly one part (the parts are contiguous), whatever the
    number of parts, including more parts than items (on as many threads)."""
    from reblur._memory import split_sum

    items = list(range(11))
    seen: list[list[int]] = []

    def fn(part):
        seen.append(list(part))
        out = np.zeros(11)
        out[list(part)] += 1.0
        return out

    np.testing.assert_array_equal(split_sum(fn, items, threads, threads), np.ones(11))
    assert sorted(i for p in seen for i in p) == items
    assert all(p == list(range(p[0], p[-1] + 1)) for p in seen)
    assert len(seen) == min(threads, len(items))


def test_split_sum_in_fixed_parts_rounds_alike_on_any_threads():
    """With ``n_parts`` the parts, and so the rounding of their sum, are those of the parts
    alone: the same float32 sums on 1, 2, 3 or 8 threads, equal to the parts summed in
    order here (and not to two parts, which round otherwise)."""
    from reblur._memory import parts, split_sum

    rng = np.random.default_rng(2)
    cols = rng.random((40, 5000)).astype(np.float32) * 1e3

    def fn(idx):
        return cols[list(idx)].sum(axis=0, dtype=np.float32)

    want = sum((fn(p) for p in parts(list(range(40)), 4)), np.zeros(5000, np.float32))
    for threads in (1, 2, 3, 8):
        np.testing.assert_array_equal(split_sum(fn, list(range(40)), threads, 4), want)
    assert not np.array_equal(split_sum(fn, list(range(40)), 2, 2), want)


@pytest.mark.parametrize("workers", [1, 2, 5])
def test_thread_map_keeps_order_and_opencv_threads(workers):
    """Results come back in the items' order; OpenCV runs single-threaded inside the
    threads and gets its thread count back after, also when an item fails."""
    import cv2

    from reblur._memory import thread_map

    before = cv2.getNumThreads()
    seen = []

    def fn(x):
        seen.append(cv2.getNumThreads())
        return x * x

    assert thread_map(fn, range(7), workers) == [x * x for x in range(7)]
    if workers > 1:
        assert set(seen) == {1}
    assert cv2.getNumThreads() == before

    def bad(x):
        if x == 3:
            raise ValueError("item 3")
        return x

    with pytest.raises(ValueError, match="item 3"):
        thread_map(bad, range(6), workers)
    assert cv2.getNumThreads() == before


def test_thread_maps_running_at_once_keep_opencv_single_then_restore_it():
    """Two ``thread_map`` calls overlapping (the viewer's beside another writer's): OpenCV
    stays single-threaded until the later one ends, even when the first one ends first,
    and then gets its own thread count back."""
    import threading

    import cv2

    from reblur._memory import thread_map

    before = cv2.getNumThreads()
    cv2.setNumThreads(max(2, before))
    want = cv2.getNumThreads()
    b_started, a_done = threading.Event(), threading.Event()
    inside_b = []

    def fa(x):
        assert b_started.wait(10)
        return x

    def fb(x):
        b_started.set()
        assert a_done.wait(10)
        inside_b.append(cv2.getNumThreads())
        return x

    try:
        first = threading.Thread(target=lambda: (thread_map(fa, range(2), 2), a_done.set()))
        first.start()
        while cv2.getNumThreads() != 1:  # the first map has set OpenCV single-threaded
            pass
        assert thread_map(fb, range(2), 2) == [0, 1]
        first.join()
        assert inside_b == [1, 1]
        assert cv2.getNumThreads() == want
    finally:
        cv2.setNumThreads(before)


_THP_PROBE = """
import numpy as np
from reblur import _memory


def eligible(a):
    addr = a.ctypes.data + a.nbytes // 2  # numpy advises the 2 MB-aligned part, a mapping
    inside = False
    for line in open("/proc/self/smaps").read().splitlines():
        head = line.split()[0] if line else ""
        if "-" in head and ":" not in head:  # a mapping's first line: "start-end perms ..."
            lo, hi = (int(x, 16) for x in head.split("-"))
            inside = lo <= addr < hi
        elif inside and line.startswith("THPeligible:"):
            return int(line.split()[1])
    return -1


outside = np.empty(64 * 2**20, np.uint8)
with _memory.small_pages():
    inside = np.empty(64 * 2**20, np.uint8)
after = np.empty(64 * 2**20, np.uint8)
print(eligible(outside), eligible(inside), eligible(after))
"""


def _numpy_setting() -> bool:
    switch = _memory._hugepage_switch()
    before = switch(True)
    switch(before)
    return bool(before)


def test_small_pages_takes_large_arrays_out_of_huge_pages():
    """Inside ``small_pages`` a large fresh array is not eligible for transparent huge
    pages, where before and after the block it is: the kernel's own account of the
    mappings (``/proc/self/smaps``), in a fresh process (in a long-lived one an array can
    land where an earlier, advised one was)."""
    import os
    import subprocess
    import sys

    if not os.path.exists("/proc/self/smaps"):
        pytest.skip("no /proc/self/smaps on this system")
    out = subprocess.run([sys.executable, "-c", _THP_PROBE], capture_output=True, text=True,
                         check=True, env={**os.environ, "NUMPY_MADVISE_HUGEPAGE": "1"})
    outside, inside, after = (int(v) for v in out.stdout.split())
    if outside != 1:
        pytest.skip("numpy's large arrays are not in huge pages on this system")
    assert inside == 0
    assert after == 1


def test_small_pages_restores_numpy_after_overlapping_blocks():
    """Overlapping blocks in several threads: numpy's setting is off while any runs and
    back to what it was when the last ends, whatever the order they end in."""
    import threading

    before = _numpy_setting()
    entered, release = threading.Barrier(3), [threading.Event() for _ in range(2)]
    seen = []

    def worker(i):
        with _memory.small_pages():
            entered.wait(10)
            release[i].wait(10)
            seen.append(_numpy_setting())

    threads = [threading.Thread(target=worker, args=(i,), daemon=True) for i in range(2)]
    for t in threads:
        t.start()
    try:
        entered.wait(10)
        assert _numpy_setting() is False
        release[0].set()  # the first to enter ends first
        threads[0].join(10)
        assert _numpy_setting() is False  # the other block still runs
        release[1].set()
        threads[1].join(10)
        assert seen == [False, False]
        assert _numpy_setting() is before
    finally:
        for ev in release:
            ev.set()
        _memory._hugepage_switch()(before)


def test_estimate_runs_in_small_pages(monkeypatch):
    """``estimate_motion`` switches numpy's huge pages off for its work and back after,
    also when it fails."""
    from reblur import PoseGrid, estimate_motion

    calls = []

    def switch(value):
        calls.append(value)
        return "previous"

    monkeypatch.setattr(_memory, "_hugepage_switch", lambda: switch)
    rng = np.random.default_rng(3)
    f = rng.random((64, 64))
    grid = PoseGrid((64, 64), tx=range(-1, 2), ty=range(-1, 2))
    estimate_motion(f, f, grid, boxes=[(8, 8, 48, 48)])
    assert calls == [False, "previous"]
    calls.clear()

    def fail(*a, **k):
        raise RuntimeError("solver failed")

    monkeypatch.setattr("reblur.estimate._solve", fail)
    with pytest.raises(RuntimeError, match="solver failed"):
        estimate_motion(f, f, grid, boxes=[(8, 8, 48, 48)])
    assert calls == [False, "previous"]


_HEAP_PROBE = """
import ctypes, sys
import numpy as np
from reblur import _memory


class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks",
                                                 "hblkhd", "usmblks", "fsmblks", "uordblks",
                                                 "fordblks", "keepcost")]


libc = ctypes.CDLL(None)
libc.mallinfo2.restype = MallInfo2
took = _memory.retain_freed_memory() if sys.argv[1] == "on" else None
a = np.ones(16 * 2**20, np.uint8)
alive = libc.mallinfo2()
del a
freed = libc.mallinfo2()
print(took, alive.hblkhd, freed.fordblks)
"""


def test_retain_freed_memory_keeps_a_freed_block_in_the_heap():
    """glibc's own accounting (mallinfo2), in fresh processes: by default a 16 MB block is
    mapped apart (``hblkhd``) and given back when freed; after ``retain_freed_memory`` it
    comes from the heap, and once freed stays there as free heap (``fordblks``) for the
    next allocation.  A user's MALLOC_* variables stand."""
    import ctypes
    import os
    import subprocess
    import sys

    try:
        ctypes.CDLL(None).mallinfo2  # noqa: B018 - glibc >= 2.33
    except AttributeError:
        pytest.skip("not glibc (>= 2.33)")
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}

    def probe(mode, extra=None):
        out = subprocess.run([sys.executable, "-c", _HEAP_PROBE, mode], check=True,
                             capture_output=True, text=True, env={**env, **(extra or {})})
        took, mapped, free = out.stdout.split()
        return took, int(mapped), int(free)

    block = 16 * 2**20
    took, mapped, free = probe("off")
    assert mapped >= block and free < block
    took, mapped, free = probe("on")
    assert took == "True" and mapped < block and free >= block
    took, mapped, _ = probe("on", {"MALLOC_MMAP_THRESHOLD_": "131072"})
    assert took == "False" and mapped >= block
