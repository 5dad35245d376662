"""Blur operator: fast engine == exact engine, adjoint test, single pose == plain warp."""

import cv2
import numpy as np
import pytest

from reblur import operator as operator_module
from reblur.grid import PoseGrid
from reblur.operator import BlurOperator, dottest

SHAPE = (300, 400)


def _grid(**kw):
    return PoseGrid(SHAPE, tx=np.arange(-3, 4), ty=np.arange(-2, 5), rz=[-2.0, -0.5, 0.0, 1.5],
                    **kw)


@pytest.mark.parametrize("blocks", ["one", "per-base"])
@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("box", [(10, 12, 50, 70), (230, 320, 60, 70), (120, 40, 64, 64)])
def test_fast_equals_exact(channels, box, blocks, monkeypatch):
    """Also with the spectral products done one base at a time (the blocks of a large
    operator, see ``operator._BLOCK_BYTES``)."""
    if blocks == "per-base":
        monkeypatch.setattr(operator_module, "_BLOCK_BYTES", 1)
    rng = np.random.default_rng(sum(box) + channels)
    img = rng.random(SHAPE + ((channels,) if channels > 1 else ()))
    img = cv2.GaussianBlur(img, (0, 0), 1.0)  # smooth enough that warps are well defined
    g = _grid()
    fast = BlurOperator(img, g, box, engine="fast")
    exact = BlurOperator(img, g, box, engine="exact")
    np.testing.assert_array_equal(fast.valid, exact.valid)
    w = rng.random(g.shape)
    a, b = fast.matvec(w), exact.matvec(w)
    m = fast.valid
    assert np.linalg.norm((a - b)[m]) <= 1e-5 * np.linalg.norm(b[m])
    r = rng.standard_normal(fast.dimsd)
    r[~m] = 0
    a, b = fast.rmatvec(r), exact.rmatvec(r)
    assert np.linalg.norm(a - b) <= 1e-5 * np.linalg.norm(b)
    # the sparse (slice-add) forward path equals the FFT path
    w_sparse = np.zeros(g.shape)
    w_sparse.flat[rng.choice(g.size, 70, replace=False)] = rng.random(70)
    np.testing.assert_allclose(fast.matvec(w_sparse), exact.matvec(w_sparse), rtol=1e-5)


def test_single_precision_spectra():
    """Spectra stored as complex64 (the default) against complex128: the products agree
    to the rounding of the spectra, far inside the solver's KKT tolerance."""
    rng = np.random.default_rng(5)
    img = cv2.GaussianBlur(rng.random(SHAPE + (3,)), (0, 0), 1.0)
    g = _grid()
    one = BlurOperator(img, g, (120, 40, 64, 64))
    two = BlurOperator(img, g, (120, 40, 64, 64), spectra_precision="double")
    assert one.spec.dtype == np.complex64 and two.spec.dtype == np.complex128
    w = rng.random(g.shape)
    r = rng.standard_normal(one.dimsd)
    a, b = one.matvec(w), two.matvec(w)
    assert a.dtype == np.float64 and np.linalg.norm(a - b) <= 1e-6 * np.linalg.norm(b)
    a, b = one.rmatvec(r), two.rmatvec(r)
    assert np.linalg.norm(a - b) <= 1e-6 * np.linalg.norm(b)
    with pytest.raises(ValueError, match="spectra_precision"):
        BlurOperator(img, g, (120, 40, 64, 64), spectra_precision="half")


@pytest.mark.parametrize("engine", ["fast", "exact"])
def test_gather_many_reads_the_columns(engine):
    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur(rng.random(SHAPE + (3,)), (0, 0), 1.0)
    g = _grid()
    op = BlurOperator(img, g, (40, 250, 48, 56), engine=engine)
    ks = rng.choice(g.size, 9, replace=False)
    rows, cols = rng.integers(0, 48, 50), rng.integers(0, 56, 50)
    chans = rng.integers(0, 3, 50)
    got = op.gather_many(ks, rows, cols, chans)
    want = np.stack([op.column(int(k))[rows, cols, chans] for k in ks], axis=1)
    np.testing.assert_array_equal(got, want)
    assert op.gather_many([], rows, cols, chans).shape == (50, 0)


@pytest.mark.parametrize("engine", ["fast", "exact"])
def test_adjoint(engine):
    rng = np.random.default_rng(7)
    img = rng.random(SHAPE + (2,))
    op = BlurOperator(img, _grid(), (40, 250, 48, 56), engine=engine)
    lhs, rhs = dottest(op, rng)
    assert abs(lhs - rhs) <= 1e-6 * max(abs(lhs), abs(rhs)), (lhs, rhs)


def test_single_pose_is_plain_warp(levir_gray):
    img = levir_gray.astype(np.float64)
    H, W = img.shape
    g = PoseGrid((H, W), tx=[5], ty=[-3], rz=[1.5])
    y0, x0, h, w = 700, 100, 128, 160
    op = BlurOperator(img, g, (y0, x0, h, w))
    out = op.matvec(np.ones(1))[:, :, 0]
    # independent: OpenCV's rotation matrix about the centre, then the translation
    M = cv2.getRotationMatrix2D(((W - 1) / 2, (H - 1) / 2), -1.5, 1.0)  # cv2 angle is CCW
    M[:, 2] += (5, -3)
    ref = cv2.warpAffine(img, M, (W, H), flags=cv2.INTER_LINEAR)[y0 : y0 + h, x0 : x0 + w]
    assert np.max(np.abs(out - ref)) < 0.02  # two warps quantise coordinates differently
    assert np.mean(np.abs(out - ref)) < 2e-3


def test_valid_marks_pixels_outside_reference():
    img = np.ones((100, 120))
    g = PoseGrid((100, 120), tx=np.arange(-4, 5), ty=[0])
    op = BlurOperator(img, g, (10, 0, 20, 30))
    # columns 0..3 need reference pixels at x < 0 for tx = +4 .. +1; column 4 needs x >= 0
    assert not op.valid[:, :4].any()
    assert op.valid[:, 4:].all()
    np.testing.assert_allclose(op.matvec(np.full(g.shape, 1 / 9))[:, 4:], 1.0)


def test_warp_window_into_a_given_array():
    """``warp_window(out=)`` writes the same values as a fresh warp into the array given
    (3 and 6 bands: one OpenCV call, or several), and refuses a wrong shape."""
    from reblur.warp import warp_window

    rng = np.random.default_rng(8)
    H = np.array([[0.999, 0.02, 3.3], [-0.02, 0.999, -2.1], [0.0, 0.0, 1.0]])
    for bands in (3, 6):
        img = rng.random((80, 90, bands)).astype(np.float32)
        want, ok_want = warp_window(img, H, (10, 12, 50, 60))
        out = np.full((50, 60, bands), np.nan, np.float32)
        got, ok = warp_window(img, H, (10, 12, 50, 60), out=out)
        assert got is out
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(ok, ok_want)
    with pytest.raises(ValueError, match="out must be"):
        warp_window(img, H, (10, 12, 50, 60), out=np.zeros((50, 61, 6), np.float32))


def _single_run_bound(op, ks, vals) -> np.ndarray:
    """Rounding bound of :meth:`BlurOperator.combine` on the fast engine, per pixel: runs
    of ``_SINGLE_RUN`` float32 products summed in float32 (each product and each partial
    sum rounded once: at most ``(_SINGLE_RUN + 1)`` unit roundoffs of the terms' sum of
    magnitudes), then added into float64."""
    from reblur import operator as operator_module

    mag = sum(abs(float(v)) * np.abs(op.column(int(k)).astype(float))
              for k, v in zip(ks, vals, strict=True))
    u = np.finfo(np.float32).eps / 2
    return (operator_module._SINGLE_RUN + 1) * u * mag + 1e-300


def test_matvec_sums_columns_or_uses_spectra_with_the_same_result():
    """``matvec`` sums columns for a few poses per weighted angle (float32 runs within
    their rounding bound) and takes the spectral product for many (to the rounding of the
    single-precision spectra): both give the explicit sum of the weighted columns."""
    from reblur import operator as operator_module

    rng = np.random.default_rng(31)
    img = cv2.GaussianBlur(rng.random(SHAPE), (0, 0), 1.0)
    g = PoseGrid(SHAPE, tx=np.arange(-3, 4), ty=np.arange(-2, 5), rz=np.linspace(-2, 2, 12))
    op = BlurOperator(img, g, (40, 250, 48, 56))
    few = np.zeros(g.shape)  # 72 poses, 6 on every base: more than 64, few per base
    few[:, 0, :6] = rng.random((12, 6))
    assert few.astype(bool).sum() > 64 and 6 <= operator_module._COLUMNS_PER_BASE
    dense = rng.random(g.shape)  # 49 per base
    assert dense[0].size > operator_module._COLUMNS_PER_BASE
    for w, rtol in ((few, None), (dense, 1e-5)):
        want = sum(float(w.flat[k]) * op.column(k).astype(float) for k in range(g.size))
        nz = np.flatnonzero(w)
        bound = _single_run_bound(op, nz, w.ravel()[nz])
        if rtol is None:  # summed columns
            assert np.all(np.abs(op.matvec(w) - want) <= bound)
        else:
            np.testing.assert_allclose(op.matvec(w), want, rtol=rtol, atol=rtol * 1e-3)
        assert np.all(np.abs(op.combine(nz[::-1], w.ravel()[nz][::-1]) - want) <= bound)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_combine_in_threads_equals_the_explicit_sum(monkeypatch, threads):
    """Sums split across threads (forced on a small window) give the explicit weighted
    sum of the columns, in any order of the poses given."""
    from reblur import operator as operator_module

    monkeypatch.setattr(operator_module, "_PARALLEL_SUM", 0)
    rng = np.random.default_rng(32)
    img = cv2.GaussianBlur(rng.random(SHAPE + (2,)), (0, 0), 1.0)
    g = _grid()
    op = BlurOperator(img, g, (40, 250, 48, 56), threads=threads)
    assert op.threads == threads
    ks = rng.choice(g.size, 40, replace=False)
    vals = rng.standard_normal(40)
    vals[::7] = 0.0
    want = sum(float(v) * op.column(int(k)).astype(float) for k, v in zip(ks, vals, strict=True))
    got = op.combine(ks, vals)
    assert got.dtype == np.float64
    assert np.all(np.abs(got - want) <= _single_run_bound(op, ks, vals))


def test_stack_and_sums_do_not_depend_on_the_threads(monkeypatch):
    """The pose stack and the sums of columns are the same numbers whatever the number of
    threads, the operator's or OpenCV's: OpenCV's threaded bilinear warps round a few
    pixels differently with its thread count, and a sum cut into one part per thread
    rounds with that count; the solver then amplifies either (one core against two
    flagged 2.22 against 2.02 % of GoPro 0477 / 16 frames)."""
    monkeypatch.setattr(operator_module, "_PARALLEL_SUM", 0)  # every sum split
    rng = np.random.default_rng(33)
    img = cv2.GaussianBlur(rng.random((700, 900)), (0, 0), 1.0)
    g = PoseGrid((700, 900), tx=np.arange(-3, 4), ty=np.arange(-2, 3),
                 rz=[-1.5, -0.7, 0.0, 0.4, 1.1])
    box = (20, 30, 640, 820)  # a large window: OpenCV cuts its warps into stripes
    saved = cv2.getNumThreads()
    ops = []
    try:
        for cv_threads, threads in ((1, 1), (2, 2), (3, 3), (2, 1)):
            cv2.setNumThreads(cv_threads)
            ops.append(BlurOperator(img, g, box, threads=threads))
    finally:
        cv2.setNumThreads(saved)
    ks = rng.choice(g.size, 60, replace=False)
    vals = rng.random(60)
    sums = [op.combine(ks, vals) for op in ops]
    for op, total in zip(ops[1:], sums[1:], strict=True):
        np.testing.assert_array_equal(op.stack, ops[0].stack)
        np.testing.assert_array_equal(op.valid, ops[0].valid)
        np.testing.assert_array_equal(total, sums[0])


@pytest.mark.parametrize("engine", ["fast", "exact"])
@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("step", [2, 3])
def test_rows_restrict_the_operator_to_every_step_th_row(engine, channels, step):
    """``rows(step)`` is ``S F`` with ``S`` the window's rows ``0, step, ...``: its columns,
    products and validity are the whole operator's at those rows, its adjoint the whole
    adjoint of the residual placed back on them (zero between), and it shares the stack."""
    rng = np.random.default_rng(11 * step + channels)
    img = cv2.GaussianBlur(rng.random(SHAPE + ((channels,) if channels > 1 else ())),
                           (0, 0), 1.0)
    g = _grid()
    box = (40, 250, 49, 56)  # 49 rows: the last sampled row is the window's last or not
    full = BlurOperator(img, g, box, engine=engine)
    sub = full.rows(step)
    assert full.rows(1) is full and full.row_step == 1 and sub.row_step == step
    n = len(range(0, 49, step))
    assert sub.dimsd == (n, 56, channels) and sub.shape == (n * 56 * channels, g.size)
    np.testing.assert_array_equal(sub.valid, full.valid[::step])
    if engine == "fast":
        assert np.shares_memory(sub.column(5), full.stack)
    for k in rng.choice(g.size, 6, replace=False):
        np.testing.assert_array_equal(sub.column(int(k)), full.column(int(k))[::step])
    for nz in (5, g.size):  # few poses: a sum of columns; all of them: the spectral product
        w = np.zeros(g.size)
        w[rng.choice(g.size, nz, replace=False)] = rng.random(nz)
        want = full.matvec(w)[::step]
        assert np.linalg.norm(sub.matvec(w) - want) <= 1e-6 * np.linalg.norm(want)
    r = rng.standard_normal(sub.dimsd)
    placed = np.zeros(full.dimsd)
    placed[::step] = r
    want = full.rmatvec(placed)
    assert np.linalg.norm(sub.rmatvec(r) - want) <= 1e-6 * np.linalg.norm(want)
    lhs, rhs = dottest(sub, rng)
    assert abs(lhs - rhs) <= 1e-6 * max(abs(lhs), abs(rhs))
    ks = rng.choice(g.size, 4, replace=False)
    rows, cols = rng.integers(0, n, 30), rng.integers(0, 56, 30)
    chans = rng.integers(0, channels, 30)
    got = sub.gather_many(ks, rows, cols, chans)
    want = np.stack([full.column(int(k))[rows * step, cols, chans] for k in ks], axis=1)
    np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match="at least 1"):
        full.rows(0)
    with pytest.raises(ValueError, match="already"):
        sub.rows(2)


def test_spectra_are_computed_on_first_use_only():
    """The spectra cost about 25 columns per base: a fresh operator sums the columns of a
    product with up to 24 weighted poses per base of the grid and computes no spectra;
    once they exist (the adjoint needs them), the same product takes them.  A row view's
    adjoint computes its phases' spectra only.  Every path gives the explicit sum."""
    from reblur import operator as operator_module

    rng = np.random.default_rng(33)
    img = cv2.GaussianBlur(rng.random(SHAPE), (0, 0), 1.0)
    g = PoseGrid(SHAPE, tx=np.arange(-3, 4), ty=np.arange(-2, 5), rz=np.linspace(-2, 2, 12))
    op = BlurOperator(img, g, (40, 250, 48, 56))
    w = np.zeros(g.shape)  # 20 poses on every base: beyond 8 per base, within 24
    w[:, :3, :] = rng.random((12, 3, 7))
    w[:, 2, 6] = 0.0
    assert (w > 0).sum() == 20 * 12
    assert 20 > operator_module._COLUMNS_PER_BASE and 20 <= operator_module._COLUMNS_PER_COLD_BASE
    want = sum(float(w.flat[k]) * op.column(k).astype(float) for k in range(g.size))
    sub = op.rows(2)
    r = rng.standard_normal(sub.dimsd)
    placed = np.zeros(op.dimsd)
    placed[::2] = r
    explicit = np.array([np.vdot(op.column(k), placed) for k in range(g.size)])
    got = sub.rmatvec(r).ravel()
    assert np.linalg.norm(got - explicit) <= 1e-6 * np.linalg.norm(explicit)
    assert ("rows", 2) in op._cache and "full" not in op._cache
    nz = np.flatnonzero(w)
    assert np.all(np.abs(op.matvec(w) - want) <= _single_run_bound(op, nz, w.ravel()[nz]))
    assert "full" not in op._cache  # summed columns
    assert op.spec.shape[0] == g.n_bases  # computed now
    np.testing.assert_allclose(op.matvec(w), want, rtol=1e-5, atol=1e-8)
