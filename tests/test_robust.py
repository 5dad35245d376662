"""Robust line fit (``reblur.robust.huber_line``) against an explicit IRLS."""

import numpy as np
import pytest

from reblur.robust import MAD_TO_SIGMA, huber_line, inlier_scale, mad, median


def _irls_lstsq(x, y, n_iter=20):
    """The same Huber IRLS with ``np.linalg.lstsq`` on the square-root-weighted design."""
    A = np.stack([x, np.ones_like(x)], axis=1)
    p = np.linalg.lstsq(A, y, rcond=None)[0]
    for _ in range(n_iter):
        r = y - A @ p
        s = mad(r)
        sw = np.sqrt(np.minimum(1.0, 1.345 * s / np.maximum(np.abs(r), 1e-12)))
        p_new = np.linalg.lstsq(A * sw[:, None], y * sw, rcond=None)[0]
        done = np.allclose(p_new, p, rtol=0, atol=1e-6)
        p = p_new
        if done:
            break
    return p


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_huber_line_equals_the_lstsq_irls_and_resists_outliers(seed):
    rng = np.random.default_rng(seed)
    x = rng.random(200_000)
    y = 0.8 * x + 0.05 + rng.normal(0, 0.01, x.size)
    out = rng.random(x.size) < 0.2  # a fifth of the points changed
    y[out] += rng.uniform(0.2, 0.6, out.sum())
    gain, offset = huber_line(x, y)
    want = _irls_lstsq(x, y)
    np.testing.assert_allclose([gain, offset], want, rtol=0, atol=1e-9)
    assert abs(gain - 0.8) < 0.02 and abs(offset - 0.05) < 0.02  # the outliers barely bias it
    ls = np.polyfit(x, y, 1)  # plain least squares is pulled up by them
    assert ls[1] - 0.05 > 2 * abs(offset - 0.05)


def test_huber_line_degenerate_inputs():
    y = np.arange(10.0)
    assert huber_line(np.full(10, 0.3), y) == (1.0, float(np.median(y - 0.3)))
    assert huber_line(np.array([1.0]), np.array([2.0])) == (1.0, 1.0)
    x = np.linspace(0, 1, 101)
    assert np.allclose(huber_line(x, 2 * x - 1), (2.0, -1.0))  # exact line: MAD 0 stops


@pytest.mark.parametrize("n", [1000, 8191, 8192, 8193, 20_000, 65_536, 65_537, 300_001])
@pytest.mark.parametrize("kind", ["normal", "ties", "sorted", "half-constant", "nan", "float32"])
def test_median_equals_numpy(n, kind):
    """The bracketed selection returns exactly ``np.median``'s value: odd and even counts,
    many ties, sorted data (a strided sample sees its order), a constant half, NaN."""
    rng = np.random.default_rng(n)
    x = rng.standard_normal(n)
    if kind == "ties":
        x = np.round(x, 1)
    elif kind == "sorted":
        x = np.sort(x)
    elif kind == "half-constant":
        x[: n // 2] = 0.25
    elif kind == "nan":
        x[n // 3] = np.nan
    elif kind == "float32":
        x = rng.standard_cauchy(n).astype(np.float32)
    got, want = median(x), float(np.median(x))
    assert got == want or (np.isnan(got) and np.isnan(want)), (got, want)


def _inlier_scale_numpy(r, start, centre=0.0, k=3.5, n_iter=20):
    """``inlier_scale`` as it was written with ``np.median`` (the reference)."""
    c, s = float(centre), float(start)
    for _ in range(n_iter):
        keep = np.abs(r - c) < k * s
        if np.count_nonzero(keep) < 3:
            break
        c_new = float(np.median(r[keep]))
        s_new = MAD_TO_SIGMA * float(np.median(np.abs(r[keep] - c_new)))
        if not s_new > 0:
            break
        done = abs(s_new - s) <= 1e-6 * s and abs(c_new - c) <= 1e-6 * s
        c, s = c_new, s_new
        if done:
            break
    return c, s, np.abs(r - c) < k * s


@pytest.mark.parametrize("n", [5_000, 200_001, 400_000])
def test_inlier_scale_equals_the_numpy_median_one(n):
    """``inlier_scale`` on :func:`median` gives exactly what it gave on ``np.median``
    (centre, scale and inliers), on large residuals with 30 % gross outliers and ties."""
    rng = np.random.default_rng(n)
    r = 0.5 + 0.02 * rng.standard_normal(n)
    bad = rng.random(n) < 0.3
    r[bad] = rng.uniform(-5.0, 5.0, int(bad.sum()))
    r[: n // 10] = np.round(r[: n // 10], 2)
    c, s, keep = inlier_scale(r, 0.1, 0.4)
    c0, s0, keep0 = _inlier_scale_numpy(r, 0.1, 0.4)
    assert (c, s) == (c0, s0) and np.array_equal(keep, keep0)
    assert abs(c - 0.5) < 1e-3 and abs(s - 0.02) < 2e-3


@pytest.mark.parametrize("seed", range(40))
def test_inlier_scale_equals_the_direct_iteration_on_hostile_residuals(seed):
    """The sorted-run iteration gives exactly the direct one's centre, scale and inliers
    (odd and even counts, heavy ties, NaN and infinities, a handful of values, starts
    that leave fewer than three inliers or a zero scale)."""
    rng = np.random.default_rng(seed)
    n = int(rng.choice([3, 4, 7, 10, 51, 500, 2_000, 8_193, 30_000]))
    r = rng.normal(rng.uniform(-1, 1), rng.uniform(1e-3, 1.0), n)
    if seed % 4 == 1:
        r = np.round(r, 1)  # a few values repeated many times
    if seed % 4 == 2:
        r[rng.random(n) < 0.2] = rng.choice([np.nan, np.inf, -np.inf])
    if seed % 4 == 3:
        r[rng.random(n) < 0.5] = 0.3  # half of them one value: a zero MAD
    bad = rng.random(n) < 0.3
    r[bad] = rng.uniform(-50, 50, int(bad.sum()))
    start = float(rng.choice([1e-4, 0.05, 0.5, 5.0]))
    centre = float(rng.choice([0.0, float(np.nanmedian(r[np.isfinite(r)]))
                               if np.isfinite(r).any() else 0.0, 3.0]))
    got = inlier_scale(r, start, centre)
    want = _inlier_scale_numpy(r, start, centre)
    assert got[:2] == want[:2], (got[:2], want[:2])
    assert np.array_equal(got[2], want[2])


def test_inlier_scale_of_a_nan_centre_or_no_scale():
    r = np.linspace(-1, 1, 101)
    c, s, keep = inlier_scale(r, 0.1, float("nan"))
    assert np.isnan(c) and s == 0.1 and not keep.any()  # nothing within reach of NaN
    c, s, keep = inlier_scale(r, 0.0, 0.2)
    assert (c, s) == (0.2, 0.0) and keep.all()  # no scale: all finite values, unchanged


@pytest.mark.parametrize("n_iter", [1, 2, 20])
def test_inlier_scale_excludes_values_exactly_at_the_bound(n_iter):
    """``|r - c| < k s`` is strict: integers at exactly 3.5 x 2 = 7 from the centre are out
    of the first step, as in the direct iteration (a ``<=`` bound fails this)."""
    r = np.repeat(np.arange(-10.0, 11.0), [1 + (i % 3) for i in range(21)])
    got = inlier_scale(r, 2.0, 0.0, n_iter=n_iter)
    want = _inlier_scale_numpy(r, 2.0, 0.0, n_iter=n_iter)
    assert got[:2] == want[:2] and np.array_equal(got[2], want[2])
