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
