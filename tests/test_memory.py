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
    thread count, including more threads than items."""
    from reblur._memory import split_sum

    items = list(range(11))
    seen: list[list[int]] = []

    def fn(part):
        seen.append(list(part))
        out = np.zeros(11)
        out[list(part)] += 1.0
        return out

    np.testing.assert_array_equal(split_sum(fn, items, threads), np.ones(11))
    assert sorted(i for p in seen for i in p) == items
    assert all(p == list(range(p[0], p[-1] + 1)) for p in seen)
    assert len(seen) == min(threads, len(items))


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
