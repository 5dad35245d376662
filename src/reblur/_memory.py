"""Fresh memory, faulted in by several threads; the CPUs available, and work split across them.

The first write to a page of fresh memory costs a page fault.  Where the host still backs
the page that is about 0.1 ms per MB; on the virtual machine the benchmarks run on it is
2-7 ms per MB (varying with the host), because the host backs guest memory only when it is
first touched (``python -m benchmarks.first_touch``).  The faults of different threads are
served in parallel (its ``grow-threads`` row: 0.9-1.7 ms per MB on 2 CPUs, against 2.1-2.8
for one thread in the same run), so a large array that is about to be filled is first
zeroed by all CPUs at once.

On that machine a process's first memory also costs less in small pages than in the
transparent huge pages numpy asks for on every allocation of 4 MB or more: the motion
estimate at 1 Gpx (``python -m benchmarks.large_motion --case 32000``, each run started
after 10 s of idle, alternated) took 4.95-5.22 s with 1.0 s of kernel time in small pages,
against 5.92-6.18 s with 2.9 s in huge pages (docs/NOTES.md, "Eleventh stop").  Probably
because a huge page needs a whole free 2 MB block, and whole free blocks are what the host
takes back, while small pages also come from partly used blocks it still backs.  (The
``grow-small`` row of ``python -m benchmarks.first_touch``, 2 GB kept, gains less and
varies with the host.)  :func:`small_pages` turns numpy's request off while a piece of
work that allocates much short-lived memory runs.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import cv2
import numpy as np

__all__ = ["available_cpus", "glibc_mallopt", "parts", "retain_freed_memory", "small_pages",
           "opencv_single", "split_sum", "thread_map", "zeros"]

#: Arrays below this size are zeroed by the calling thread alone.
_PARALLEL_BYTES = 32 * 2**20


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


#: glibc's ``mallopt`` parameters (malloc.h)
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
#: glibc's largest mmap threshold on 64-bit (``DEFAULT_MMAP_THRESHOLD_MAX``)
MMAP_THRESHOLD_MAX = 32 * 2**20


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MB.

    Linux's ``VmHWM``, the high-water mark of this program's own memory.  ``ru_maxrss``
    survives ``exec``: a run started from a large process (a notebook, an orchestration
    script holding 800 MB) reported that parent's size as its own.  ``ru_maxrss`` where
    ``/proc`` is missing.
    """
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource
    import sys

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024.0


def retain_freed_memory(trim_bytes: int = 256 * 2**20) -> bool:
    """Keep freed memory of blocks up to 32 MB in the process for the next allocations
    (glibc only; the command line calls it once, at its start: a library must not change
    its host process's allocator).

    By default glibc maps every block above a threshold afresh (128 kB at first, raised
    up to 32 MB as such blocks are freed) and returns the top of its heap to the system
    once more than twice that is free.  Every stage then touches fresh pages, and a page
    fault costs 1-7 ms per MB on the VM the benchmarks run on (``python -m
    benchmarks.first_touch``).  With blocks up to 32 MB taken from the heap and up to
    ``trim_bytes`` of free heap kept, a stage reuses the pages its predecessor freed
    (``reblur detect`` on the cost pairs of ``python -m benchmarks.cost``, alternated with
    and without): 1 MP 2.73-2.86 s against 3.09-3.14 s end to end, half the page faults,
    50 MB more peak memory; 25 MP 6.1-6.2 s against 7.0-7.1 s; 100 MP (45 % changed)
    27.6-28.4 s against 26.6-27.2 s and 40-110 MB more peak, within that size's noise.
    Larger blocks (whole images, full-size masks) are still mapped and returned.

    Returns whether the allocator took the settings (False elsewhere than glibc, or where
    the environment sets them itself).
    """
    if "MALLOC_MMAP_THRESHOLD_" in os.environ or "MALLOC_TRIM_THRESHOLD_" in os.environ:
        return False  # the user's own settings stand
    mallopt = glibc_mallopt()
    if mallopt is None:  # pragma: no cover - not glibc
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX)
                and mallopt(M_TRIM_THRESHOLD, int(trim_bytes)))


def glibc_mallopt() -> Callable[[int, int], int] | None:
    """glibc's ``mallopt(param, value)``, or None where the C library is not glibc (musl,
    macOS, Windows)."""
    try:
        import ctypes

        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version  # noqa: B018 - glibc, not musl or macOS
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # pragma: no cover - not glibc
        return None
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    return mallopt


def _hugepage_switch():
    """numpy's switch of its huge-page request (``_set_madvise_hugepage``: takes the new
    setting, returns the previous one), or None where this numpy has none."""
    try:
        from numpy._core import multiarray
    except ImportError:  # pragma: no cover (numpy < 2)
        from numpy.core import multiarray
    return getattr(multiarray, "_set_madvise_hugepage", None)


_pages_lock = threading.Lock()
_pages_users = 0  # small_pages contexts open in this process (any thread)
_pages_saved: object = True  # numpy's setting before the first of them


@contextmanager
def small_pages() -> Iterator[None]:
    """Allocate numpy's large arrays in small pages while the block runs.

    numpy asks the kernel for transparent huge pages (``madvise``) on every allocation of
    4 MB or more.  Where fresh memory is expensive to back (a virtual machine whose host
    takes freed memory back), huge pages made the first touch of the estimate's ~1 GB of
    short-lived stacks and spectra cost three times the kernel time of small pages (module
    notes).

    The setting is numpy's and process-wide: it is switched off when the first of
    overlapping blocks (in any thread) starts and restored when the last ends; arrays
    allocated meanwhile by other threads also get small pages (a performance hint only).
    A no-op where numpy has no such switch.
    """
    global _pages_users, _pages_saved
    switch = _hugepage_switch()
    if switch is None:  # pragma: no cover
        yield
        return
    with _pages_lock:
        if _pages_users == 0:
            _pages_saved = switch(False)
        _pages_users += 1
    try:
        yield
    finally:
        with _pages_lock:
            _pages_users -= 1
            if _pages_users == 0:
                switch(_pages_saved)


def zeros(shape, dtype, threads: int | None = None) -> np.ndarray:
    """``np.zeros(shape, dtype)`` whose pages are written (faulted in) by ``threads``
    threads at once (default: the available CPUs), not lazily by whoever writes first."""
    a = np.empty(shape, dtype)
    n = available_cpus() if threads is None else max(1, int(threads))
    flat = a.reshape(-1).view(np.uint8)
    if n == 1 or flat.size < _PARALLEL_BYTES:
        flat.fill(0)
        return a
    with ThreadPoolExecutor(n) as ex:  # np.copyto releases the GIL on large arrays
        list(ex.map(lambda p: np.copyto(p, 0), parts(flat, n)))
    return a


def parts(items, n: int) -> list:
    """``items`` cut into ``n`` contiguous parts of near-equal length."""
    bounds = np.linspace(0, len(items), n + 1).astype(np.int64)
    return [items[b0:b1] for b0, b1 in zip(bounds[:-1], bounds[1:], strict=True)]


def split_sum(fn, items, threads: int, n_parts: int) -> np.ndarray:
    """``sum(fn(part) for part in parts)``, ``items`` cut into ``n_parts`` contiguous
    parts, run on at most ``threads`` threads (``fn`` must release the GIL for most of its
    work, as numpy's large-array arithmetic does) and summed in their order.  The parts and
    the order of their sum depend only on ``len(items)`` and ``n_parts``, never on
    ``threads``: the result is the same on any machine."""
    n = max(1, min(int(n_parts), len(items)))
    if n == 1:
        return fn(items)
    cut = parts(items, n)
    workers = max(1, min(int(threads), n))
    if workers == 1:
        results = [fn(p) for p in cut]
    else:
        with ThreadPoolExecutor(workers) as ex:
            results = list(ex.map(fn, cut))
    out = results[0]
    for r in results[1:]:
        out += r
    return out


#: OpenCV's thread count is one setting of the process: :func:`thread_map` calls running at
#: once (the viewer's beside the report's other writers) count themselves here; the first
#: sets it to 1, the last puts back what the first found.
_CV_LOCK = threading.Lock()
_cv_users = 0
_cv_saved = 1


def _cv_single(enter: bool) -> None:
    global _cv_users, _cv_saved
    with _CV_LOCK:
        if enter:
            if _cv_users == 0:
                _cv_saved = cv2.getNumThreads()
                cv2.setNumThreads(1)
            _cv_users += 1
        else:
            _cv_users -= 1
            if _cv_users == 0:
                cv2.setNumThreads(_cv_saved)


@contextmanager
def opencv_single():
    """OpenCV single-threaded for the time of the block (nests, and with
    :func:`thread_map`; OpenCV's own threads come back when the last user ends).  Its
    bilinear warps then give the same pixels whatever the machine's cores: threaded, they
    differ by a unit roundoff at a few pixels with the number of threads
    (``tests/test_operator.py``)."""
    _cv_single(True)
    try:
        yield
    finally:
        _cv_single(False)


def thread_map(fn, items, workers: int) -> list:
    """``[fn(x) for x in items]`` on ``workers`` threads, OpenCV single-threaded inside
    each (so the threads do not oversubscribe the cores); in order.  Calls may run at once
    and nest: OpenCV's own threads come back when the last one ends."""
    items = list(items)
    if workers <= 1 or len(items) <= 1:
        return [fn(x) for x in items]
    with opencv_single(), ThreadPoolExecutor(min(int(workers), len(items))) as ex:
        return list(ex.map(fn, items))
