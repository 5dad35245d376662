"""Rolling-shutter band model (reblur.rolling): operator, estimate, reblur, model choice."""

import cv2
import numpy as np
import pytest

from reblur.grid import PoseGrid, local_homography
from reblur.operator import BlurOperator
from reblur.rolling import RollingOperator, RowBands

SHAPE = (120, 150)


def _grid():
    return PoseGrid(SHAPE, tx=np.arange(-2, 3), ty=np.arange(-1, 2), rz=[-1.0, 0.0, 1.5])


def _image(seed=0, channels=1):
    rng = np.random.default_rng(seed)
    img = rng.random(SHAPE + ((channels,) if channels > 1 else ()))
    return cv2.GaussianBlur(img, (0, 0), 1.2)


def _phi(bands, rows):
    """Independent hat functions: np.interp of the identity rows at the band centres."""
    c = (np.arange(bands.n_bands) + 0.5) * bands.height / bands.n_bands - 0.5
    return np.stack([np.interp(rows, c, np.eye(bands.n_bands)[b]) for b in range(len(c))])


def test_bands_are_a_partition_of_unity_interpolating_between_centres():
    bands = RowBands(100, 4)
    rows = np.arange(100)
    phi = bands.weights(rows)
    np.testing.assert_allclose(phi.sum(axis=0), 1.0)
    np.testing.assert_allclose(phi, _phi(bands, rows), atol=1e-12)
    assert np.all((phi > 0).sum(axis=0) <= 2)
    for b in range(4):
        y0, y1 = bands.row_span(b)
        pos = np.flatnonzero(phi[b] > 0)
        assert (pos[0], pos[-1] + 1) == (y0, y1)
    np.testing.assert_array_equal(RowBands(100, 1).weights(rows), 1.0)
    with pytest.raises(ValueError, match="n_bands"):
        RowBands(10, 0)


@pytest.mark.parametrize("engine", ["fast", "exact"])
def test_dot_test_in_float64(engine):
    """Dense weights (more than 64 per band: the fast engine's float64 spectral path)."""
    rng = np.random.default_rng(1)
    img = _image(1, channels=2)
    grid = PoseGrid(SHAPE, tx=np.arange(-4, 5), ty=np.arange(-2, 3), rz=[-1.0, 0.0, 1.5])
    op = RollingOperator(img, grid, (20, 30, 70, 60), RowBands(SHAPE[0], 4), engine=engine,
                         spectra_precision="double")
    u = rng.random(op.grid.shape)
    v = rng.standard_normal(op.dimsd)
    lhs, rhs = float(np.vdot(op.matvec(u), v)), float(np.vdot(u, op.rmatvec(v)))
    assert abs(lhs - rhs) <= 1e-10 * abs(lhs), (lhs, rhs)


def _per_row_reference(img, grid, box, bands, W):
    """Loops over rows and poses with plain cv2.warpPerspective of the whole reference."""
    y0, x0, h, w = box
    phi = _phi(bands, np.arange(y0, y0 + h))
    out = np.zeros((h, w))
    warped = {}
    for i in range(h):
        kernel = np.tensordot(phi[:, i], W, axes=1)
        for k in np.flatnonzero(kernel.ravel()):
            if k not in warped:
                M = local_homography(grid.homography(int(k)), (0, 0), (x0, y0))
                warped[k] = cv2.warpPerspective(img.astype(np.float32), M, (w, h),
                                                flags=cv2.INTER_LINEAR)
            out[i] += kernel.ravel()[k] * warped[k][i]
    return out


@pytest.mark.parametrize("n_bands", [1, 3, 5])
def test_equals_a_per_row_reference(n_bands):
    rng = np.random.default_rng(n_bands)
    img, grid = _image(2), _grid()
    box = (25, 35, 60, 70)
    bands = RowBands(SHAPE[0], n_bands)
    W = np.zeros((n_bands, *grid.shape))
    for b in range(n_bands):  # each band its own sparse kernel
        W[b].flat[rng.choice(grid.size, 6, replace=False)] = rng.random(6)
    op = RollingOperator(img, grid, box, bands)
    got = op.matvec(W)[:, :, 0]
    want = _per_row_reference(img, grid, box, bands, W)
    m = op.valid
    assert m.mean() > 0.9
    assert np.max(np.abs(got - want)[m]) < 1e-4 * np.max(np.abs(want))


def test_identical_bands_are_the_global_operator():
    rng = np.random.default_rng(4)
    img, grid = _image(3, channels=3), _grid()
    box = (0, 10, 120, 90)
    glob = BlurOperator(img, grid, box, spectra_precision="double")
    op = RollingOperator(img, grid, box, RowBands(SHAPE[0], 6), spectra_precision="double")
    w = rng.random(grid.shape)
    np.testing.assert_allclose(op.matvec(np.broadcast_to(w, op.grid.shape)), glob.matvec(w),
                               rtol=1e-12, atol=1e-12)
    r = rng.standard_normal(op.dimsd)
    np.testing.assert_allclose(op.rmatvec(r).sum(axis=0), glob.rmatvec(r), rtol=1e-9,
                               atol=1e-9)


def test_columns_gather_and_combine_agree():
    rng = np.random.default_rng(5)
    img, grid = _image(4, channels=2), _grid()
    op = RollingOperator(img, grid, (30, 20, 50, 40), RowBands(SHAPE[0], 4))
    ks = rng.choice(op.grid.size, 7, replace=False)
    vals = rng.random(7)
    cols = [np.asarray(op.column(int(k))) for k in ks]
    want = sum(v * c for v, c in zip(vals, cols, strict=True))
    np.testing.assert_allclose(op.combine(ks, vals), want, rtol=1e-6, atol=1e-7)
    rows, cc, ch = rng.integers(0, 50, 30), rng.integers(0, 40, 30), rng.integers(0, 2, 30)
    np.testing.assert_allclose(op.gather_many(ks, rows, cc, ch),
                               np.stack([c[rows, cc, ch] for c in cols], axis=1), rtol=1e-6)
    np.testing.assert_allclose(op.column(int(ks[0]))[5:9], cols[0][5:9])
    W = np.zeros(op.grid.size)
    W[ks] = vals
    np.testing.assert_allclose(op.matvec(W), op.combine(ks, vals), rtol=1e-5, atol=1e-6)
