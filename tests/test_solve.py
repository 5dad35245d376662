"""Solver for eq. 3 / eq. 5 on real imagery with known camera paths (ground truth known)."""

import warnings

import numpy as np
import pytest

from reblur import PoseGrid, estimate_motion
from reblur.estimate import soft_threshold
from reblur.operator import BlurOperator
from reblur.simulate import blur_along_path, blur_weights, grid_path, random_camera_path
from reblur.solve import active_set, fista, huber_objective, joint_objective

BOX = (120, 380, 512, 512)  # a 512 x 512 crop away from the image centre


def psnr(a, b, mask=None):
    d = (a - b) if mask is None else (a - b)[mask]
    return 10 * np.log10(1.0 / np.mean(d**2))


def mass_near_truth(w, w_true):
    """Fraction of the estimated weight within one grid step (any axis) of a true pose."""
    true_idx = np.argwhere(w_true > 0)
    near = 0.0
    for idx in np.argwhere(w > 0):
        if np.any(np.abs(true_idx - idx).max(axis=1) <= 1):
            near += w[tuple(idx)]
    return near / w.sum()


@pytest.fixture(scope="module")
def paper_grid():
    return PoseGrid.paper((1024, 1024))


@pytest.mark.parametrize("colour", [False, True])
def test_on_grid_path_recovered(levir_rgb, paper_grid, colour):
    img = levir_rgb if colour else levir_rgb.mean(axis=2)
    w_true = grid_path(paper_grid, rng=3, n_poses=20)
    g, valid = blur_weights(img, paper_grid, w_true, BOX, dtype=np.float32)
    assert valid.all()
    est = estimate_motion(img, _embed(g, img.shape), paper_grid, boxes=[BOX], lam=0.1)
    fit = BlurOperator(img, paper_grid, BOX).matvec(est.weights).reshape(g.shape)
    assert psnr(fit, g) >= 40.0
    assert mass_near_truth(est.weights, w_true) >= 0.9
    assert est.info["converged"]


def _embed(window, shape):
    """Put an observation window at BOX inside a full-size canvas (rest is never read)."""
    out = np.zeros(shape)
    y0, x0, h, w = BOX
    out[y0 : y0 + h, x0 : x0 + w] = window
    return out


def test_noise(levir_gray, paper_grid):
    w_true = grid_path(paper_grid, rng=11, n_poses=25)
    clean, _ = blur_weights(levir_gray, paper_grid, w_true, BOX, dtype=np.float32)
    noisy = clean + np.random.default_rng(0).normal(0, 1 / 255, clean.shape)
    est = estimate_motion(levir_gray, _embed(noisy, levir_gray.shape), paper_grid, boxes=[BOX])
    fit = BlurOperator(levir_gray, paper_grid, BOX).matvec(est.weights)[:, :, 0]
    assert psnr(fit, clean) >= 35.0


def test_occluders_both_polarities(levir_gray, paper_grid):
    """chi recovers bright, dark and low-contrast changes; the weights stay accurate."""
    w_true = grid_path(paper_grid, rng=5, n_poses=15)
    clean, _ = blur_weights(levir_gray, paper_grid, w_true, BOX, dtype=np.float32)
    g = clean.copy()
    truth = np.zeros(g.shape, bool)
    yy, xx = np.mgrid[: g.shape[0], : g.shape[1]]
    bright = (np.abs(yy - 100) < 35) & (np.abs(xx - 120) < 45)
    dark = (yy - 350) ** 2 + (xx - 380) ** 2 < 40**2
    faint = (np.abs(yy - 400) < 30) & (np.abs(xx - 110) < 30)
    g[bright] = 0.97
    g[dark] = 0.03
    g[faint] += 0.12  # close to the background: a faint brightening (shadow / haze patch)
    truth |= bright | dark | faint
    # pixels where the pasted value happens to equal the background are no change at all
    truth &= np.abs(g - clean) > 0.05
    est = estimate_motion(levir_gray, _embed(g, levir_gray.shape), paper_grid, boxes=[BOX])
    fit = BlurOperator(levir_gray, paper_grid, BOX).matvec(est.weights)[:, :, 0]
    assert psnr(fit, clean) >= 40.0
    support = est.chi[0] != 0
    jc = (support & truth).sum() / (support | truth).sum()
    assert jc >= 0.9, jc
    assert (support & faint).sum() >= 0.9 * faint.sum()
    assert mass_near_truth(est.weights, w_true) >= 0.9


def test_off_grid_path_and_finer_grid(levir_gray):
    H, W = levir_gray.shape
    path = random_camera_path(7, center=((W - 1) / 2, (H - 1) / 2), t_max=6.0, rz_max=1.2)
    g, valid = blur_along_path(levir_gray, path, BOX, dtype=np.float32)
    g = g.reshape(g.shape[:2])
    obs = _embed(g, levir_gray.shape)
    scores = []
    for step in (0.5, 0.25, 0.1):
        grid = PoseGrid.from_ranges((H, W), t_max=10, rz_max=2.0, rz_step=step)
        est = estimate_motion(levir_gray, obs, grid, boxes=[BOX])
        fit = BlurOperator(levir_gray, grid, BOX).matvec(est.weights)[:, :, 0]
        scores.append(psnr(fit, g, valid))
    assert scores[0] >= 30.0, scores
    assert scores[2] > scores[0] + 1.0, scores


def test_huber_elimination_equals_joint_problem():
    """eq. 5 with chi eliminated (Huber) has the optimum of the joint (w, chi) problem."""
    rng = np.random.default_rng(2)
    f = rng.random((90, 90))
    import cv2

    f = cv2.GaussianBlur(f, (0, 0), 1.2)
    grid = PoseGrid((90, 90), tx=np.arange(-2, 3), ty=np.arange(-2, 3), rz=[-1.0, 0.0, 1.0])
    box = (12, 10, 64, 64)
    op = BlurOperator(f, grid, box)
    w_true = np.zeros(grid.shape)
    w_true[1, 2, 2], w_true[2, 2, 3], w_true[0, 1, 2] = 0.5, 0.3, 0.2
    g = op.matvec(w_true)
    g[5:20, 30:50] += 0.4  # a change
    g += rng.normal(0, 0.01, g.shape)
    lam = 0.05
    # (1) closed form: for any w, chi = soft(r, lam/2) minimises the joint objective
    w_any = rng.random(grid.shape) * 0.02
    r = g - op.matvec(w_any)
    chi = soft_threshold(r, lam / 2)
    j_star = joint_objective(op, g, w_any, chi, lam)
    assert j_star == pytest.approx(huber_objective([op], [g], w_any, lam), rel=1e-12)
    for _ in range(5):
        assert joint_objective(op, g, w_any, chi + rng.normal(0, 1e-3, chi.shape), lam) > j_star
    # (2) both solvers reach the same optimum
    w_as, info = active_set([op], [g], lam=lam)
    f_as = huber_objective([op], [g], w_as, lam)
    w_fi, chi_fi, finfo = fista(op, g, lam=lam, n_iter=4000)
    f_fi = finfo["objective"][-1]
    assert f_as <= f_fi * (1 + 1e-9)
    assert f_fi <= f_as * (1 + 1e-3), (f_fi, f_as)
    np.testing.assert_allclose(w_fi, w_as, atol=0.02)


def test_estimate_motion_validation(levir_gray):
    grid = PoseGrid.paper((1024, 1024))
    with pytest.raises(ValueError, match="bands"):
        estimate_motion(levir_gray, np.zeros((1024, 1024, 3)), grid)
    with pytest.raises(ValueError, match="geometry"):
        estimate_motion(levir_gray, np.zeros((1000, 1024)), grid)
    with pytest.raises(ValueError, match="covered"):
        estimate_motion(levir_gray, levir_gray, grid, boxes=[(0, 0, 8, 8)])
    with pytest.raises(ValueError, match="refit_photometry"):
        estimate_motion(levir_gray, levir_gray, grid, solver="fista", refit_photometry=True)
    with pytest.raises(ValueError, match="threads"):
        estimate_motion(levir_gray, levir_gray, grid, threads=0)
    for name, bad in (("rtol", -1e-4), ("fine_rtol", 1.0), ("fine_rtol", True)):
        with pytest.raises(ValueError, match=name):
            estimate_motion(levir_gray, levir_gray, grid, **{name: bad})


def test_default_threads_follow_the_environment(monkeypatch):
    import os

    from reblur.estimate import MAX_BLAS_THREADS, _default_threads

    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    cpus = len(os.sched_getaffinity(0))
    assert _default_threads() == min(cpus, MAX_BLAS_THREADS)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert _default_threads() == 1
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "junk")  # not a count: the next one counts
    assert _default_threads() == 1
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "64")
    assert _default_threads() == min(cpus, MAX_BLAS_THREADS)


def test_uint8_input_is_scaled(levir_gray, paper_grid):
    w_true = grid_path(paper_grid, rng=4, n_poses=10)
    g, _ = blur_weights(levir_gray, paper_grid, w_true, BOX, dtype=np.float32)
    ref8 = np.round(levir_gray * 255).astype(np.uint8)
    obs = np.round(_embed(g, levir_gray.shape) * 255).astype(np.uint8)
    est = estimate_motion(ref8, obs, paper_grid, boxes=[BOX])
    assert 0.9 < est.weights.sum() < 1.1
    assert mass_near_truth(est.weights, w_true) >= 0.9


def _two_windows_rolled(ref):
    """Two 240 px windows of ``ref`` blurred along a camera path with 1 deg of roll (the
    rest of the observation zero), and a grid of 81 roll angles for them."""
    H, W = ref.shape
    path = random_camera_path(4, center=((W - 1) / 2, (H - 1) / 2), t_max=6.0, rz_max=1.0)
    boxes = [(150, 150, 240, 240), (634, 634, 240, 240)]
    obs = np.zeros((H, W))
    for b in boxes:
        g, _ = blur_along_path(ref, path, b, dtype=np.float32)
        obs[b[0] : b[0] + b[2], b[1] : b[1] + b[3]] = g.reshape(b[2], b[3])
    grid = PoseGrid.from_ranges((H, W), t_max=10, rz_max=2.0, rz_step=0.05)  # 81 angles
    return obs, grid, boxes


def test_coarse_to_fine_matches_the_direct_solve(levir_gray):
    """Coarse to fine over the roll angles (and, on coarse levels, every 2nd/4th translation)
    must reach the optimum of the direct solve over the whole fine grid."""
    obs, grid, boxes = _two_windows_rolled(levir_gray)
    direct = estimate_motion(levir_gray, obs, grid, boxes=boxes, coarse_to_fine=False)
    c2f = estimate_motion(levir_gray, obs, grid, boxes=boxes, coarse_to_fine=True, max_bases=6)
    assert len(c2f.info["levels"]) >= 3
    assert c2f.info["levels"][0]["t_stride"] > 1
    ops = [BlurOperator(levir_gray, grid, b) for b in boxes]
    gs = [obs[b[0] : b[0] + b[2], b[1] : b[1] + b[3], None] for b in boxes]
    f_direct = huber_objective(ops, gs, direct.weights, 0.1)
    f_c2f = huber_objective(ops, gs, c2f.weights, 0.1)
    data_direct = f_direct - 0.1 * direct.weights.sum()  # the data term of eq. 5
    assert f_c2f - f_direct <= 0.02 * data_direct, (f_c2f, f_direct, data_direct)
    assert min(c2f.info["psnr"]) >= min(direct.info["psnr"]) - 0.5


def test_coarse_to_fine_keeps_a_long_path():
    """A roll path spread over many angles (each < 1 % of the weight, as a 0.3 deg path
    at 1 Gpx) keeps all of them, with their neighbours on the next lattice; a stray angle
    far below the heaviest one is dropped."""
    from reblur.estimate import _next_angles

    n, stride = 1600, 8
    mass = np.zeros(n)
    path = np.arange(200, 200 + 150 * stride, stride)  # 150 angles, 0.67 % each
    mass[path] = 1.0 + 0.2 * np.sin(np.arange(path.size))
    mass[40] = 1e-4  # stray
    idx, new_stride = _next_angles(mass, stride)
    assert new_stride == 2
    want = {a + k * 2 for a in path for k in range(-4, 5)}
    assert set(idx) == want  # every path angle within one old stride, none near the stray
    one = np.zeros(n)
    one[500] = 1.0
    assert _next_angles(one, 10) == (list(range(490, 511, 2)), 2)  # 10 // 4: symmetric
    assert _next_angles(one, 3) == (list(range(497, 504)), 1)
    # not from stride 6 straight to the (costly) last level: one more level at stride 2
    assert _next_angles(one, 6) == (list(range(494, 507, 2)), 2)


@pytest.mark.parametrize("one_sided", [False, True])
@pytest.mark.parametrize("changed", [0.1, 0.6])
def test_huber_optimum_with_many_outliers(changed, one_sided):
    """KKT certificate, from the explicit matrix, of the active-set optimum when a large
    part of the window changed (most residuals in the linear part of the Huber loss), and
    no worse than a bound-constrained quasi-Newton solve of the same objective; the same
    from warm starts too strong and far too weak (every pixel an outlier)."""
    import cv2
    from scipy.optimize import minimize

    rng = np.random.default_rng(12)
    f = cv2.GaussianBlur(rng.random((100, 100)), (0, 0), 1.5)
    grid = PoseGrid((100, 100), tx=np.arange(-2, 3), ty=np.arange(-2, 3), rz=[-1.0, 0.0, 1.0])
    box = (14, 14, 72, 72)
    op = BlurOperator(f, grid, box)
    w_true = np.zeros(grid.shape)
    w_true[1, 2, 2], w_true[2, 1, 3], w_true[0, 3, 1] = 0.5, 0.3, 0.2
    g = op.matvec(w_true)[:, :, 0]
    yy, xx = np.mgrid[:72, :72]
    patch = yy < changed * 72  # a band of changed rows, both polarities
    g[patch] += np.where(xx[patch] < 36, 0.3, -0.25)
    g += rng.normal(0, 0.01, g.shape)
    lam = 0.05
    delta = lam / 2
    # one-sided: the change term may only brighten (ICIP 2013's sign rule, all +1)
    s = np.ones(g.shape) if one_sided else None
    w_as, info = active_set([op], [g[:, :, None]], lam=lam,
                            signs=None if s is None else [s[:, :, None]])
    assert info["converged"]
    A = np.stack([op.column(k)[:, :, 0].ravel() for k in range(grid.size)], axis=1)
    m = op.valid.ravel()
    A, gv = A[m], g.ravel()[m]
    sv = None if s is None else s.ravel()[m]

    def psi(rr):
        if sv is None:
            return 2 * np.clip(rr, -delta, delta)
        return np.where(sv * rr > delta, 2 * delta * sv, 2 * rr)

    def loss(rr):
        out = np.abs(rr) > delta if sv is None else sv * rr > delta
        return np.where(out, 2 * delta * np.abs(rr) - delta * delta, rr * rr).sum()

    r = gv - A @ w_as.ravel()
    assert np.mean(np.abs(r) > delta) >= 0.4 * changed  # the outliers are really there
    grad = lam - A.T @ psi(r)
    on = w_as.ravel() > 0
    scale = np.abs(A.T @ psi(gv)).max()
    assert np.all(np.abs(grad[on]) <= 1e-6 * scale)
    assert np.all(grad[~on] >= -1e-6 * scale)

    def fun(w):
        rr = gv - A @ w
        return loss(rr) + lam * w.sum(), lam - A.T @ psi(rr)

    ref = minimize(fun, np.full(grid.size, 1.0 / grid.size), jac=True, method="L-BFGS-B",
                   bounds=[(0, None)] * grid.size, options=dict(maxiter=20000, gtol=1e-12))
    f_as = fun(w_as.ravel())[0]
    assert f_as <= ref.fun * (1 + 1e-9), (f_as, ref.fun)

    # a warm start whose inactive poses already pass the KKT test (weights 1.5x too large:
    # every inactive gradient is positive) must still be optimised, not returned as is
    w0 = 1.5 * w_as
    assert np.all(fun(w0.ravel())[1][~on] >= 0)
    w_ws, _ = active_set([op], [g[:, :, None]], lam=lam, w0=w0,
                         signs=None if s is None else [s[:, :, None]])
    f_ws, grad_ws = fun(w_ws.ravel())
    on_ws = w_ws.ravel() > 0
    assert np.all(np.abs(grad_ws[on_ws]) <= 1e-6 * scale)
    assert np.all(grad_ws[~on_ws] >= -1e-6 * scale)
    assert f_ws <= ref.fun * (1 + 1e-9), (f_ws, ref.fun)

    # a warm start 100x too weak leaves every pixel an outlier: no weight has curvature in
    # its partition's quadratic model, which has no minimiser; the solve must still reach
    # the optimum (it stalled at the start, its Newton steps NaN)
    w_far = 0.01 * w_true
    r_far = gv - A @ w_far.ravel()
    assert np.all((np.abs(r_far) if sv is None else sv * r_far) > delta)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        w_fs, info_fs = active_set([op], [g[:, :, None]], lam=lam, w0=w_far,
                                   signs=None if s is None else [s[:, :, None]])
    assert info_fs["converged"]
    f_fs = fun(w_fs.ravel())[0]
    assert f_fs <= ref.fun * (1 + 1e-9), (f_fs, ref.fun)


def test_shared_scratch_gives_the_same_solve():
    """The Gram copies of all windows (and of later calls) share one scratch buffer: a
    buffer left large and full of garbage by an earlier use changes nothing."""
    import cv2

    from reblur.solve import Scratch

    rng = np.random.default_rng(4)
    f = cv2.GaussianBlur(rng.random((160, 160)), (0, 0), 1.5)
    grid = PoseGrid((160, 160), tx=np.arange(-2, 3), ty=np.arange(-2, 3), rz=[-1.0, 0.0, 1.0])
    ops = [BlurOperator(f, grid, b) for b in ((10, 10, 60, 70), (90, 80, 60, 70))]
    w_true = np.zeros(grid.shape)
    w_true[0, 2, 2], w_true[2, 1, 3] = 0.6, 0.4
    gs = [op.matvec(w_true) + rng.normal(0, 0.01, op.dimsd) for op in ops]
    gs[1][:20, :30] += 0.3  # a change in the second window
    fresh, _ = active_set(ops, gs, lam=0.05)
    scratch = Scratch()
    scratch.take(4 * 10**6)[:] = np.nan  # a larger, dirty buffer from an earlier call
    shared, _ = active_set(ops, gs, lam=0.05, scratch=scratch)
    np.testing.assert_array_equal(shared, fresh)
    assert scratch.nbytes == 8 * 4 * 10**6  # reused, not reallocated
    assert mass_near_truth(shared, w_true) > 0.9


def _kkt_of_rows(ops, gs, masks, w, lam, step):
    """The KKT test of the row-sampled Huber problem on its explicit matrix (see
    test_row_step_solves_the_sampled_rows_with_the_l1_term_scaled)."""
    delta = lam / 2
    A = np.concatenate([np.stack([op.column(k)[::step][m[::step]].ravel()
                                  for k in range(ops[0].grid.size)], axis=1)
                        for op, m in zip(ops, masks, strict=True)])
    gv = np.concatenate([g[::step][m[::step]].ravel() for g, m in zip(gs, masks, strict=True)])
    r = gv - A @ w.ravel()
    psi = np.where(np.abs(r) > delta, 2 * delta * np.sign(r), 2 * r)
    grad = lam / step - A.T @ psi
    on = w.ravel() > 0
    scale = np.abs(A.T @ np.where(np.abs(gv) > delta, 2 * delta * np.sign(gv), 2 * gv)).max()
    return np.all(np.abs(grad[on]) <= 1e-6 * scale) and np.all(grad[~on] >= -1e-6 * scale)


def _partition_moves(ops, g_before, g_after, masks, w, lam, step):
    """Share of the sampled valid pixels whose Huber partition at ``w`` differs between
    the two observations (explicit sums of the columns)."""
    moved = total = 0
    for op, a, b, m in zip(ops, g_before, g_after, masks, strict=True):
        fw = sum(w.ravel()[k] * op.column(k) for k in np.flatnonzero(w.ravel()))
        sa = np.sign(a - fw) * (np.abs(a - fw) > lam / 2)
        sb = np.sign(b - fw) * (np.abs(b - fw) > lam / 2)
        mm = m[::step]
        moved += int(np.count_nonzero((sa != sb)[::step][mm]))
        total += int(mm.sum())
    return moved / total


@pytest.mark.parametrize("offset", [0.004, 0.3])
def test_a_solve_on_the_same_operators_starts_from_the_carried_gram(offset):
    """A photometric round's solve (the same operators, the observation less an offset,
    warm-started from the weights found) starts from the inlier Gram the last solve left in
    the shared scratch, updated over the pixels whose partition moved, and recomputes
    ``A^T D g`` and ``A^T s``: it reaches the optimum of its own problem (the KKT test on
    the explicit matrix; a stale ``A^T D g`` or a missed update fails it) and the fresh
    solve's weights.  Where most pixels moved (an offset beyond the Huber threshold) the
    Gram is computed afresh; other operators, or other masks, never take it."""
    import cv2

    from reblur.solve import Scratch

    rng = np.random.default_rng(33)
    f = cv2.GaussianBlur(rng.random((160, 160)), (0, 0), 1.5)
    grid = PoseGrid((160, 160), tx=np.arange(-2, 3), ty=np.arange(-2, 3), rz=[-1.0, 0.0, 1.0])
    boxes = ((10, 10, 61, 70), (90, 80, 60, 70))
    ops = [BlurOperator(f, grid, b) for b in boxes]
    w_true = np.zeros(grid.shape)
    w_true[0, 2, 2], w_true[2, 1, 3], w_true[1, 3, 1] = 0.5, 0.3, 0.2
    gs = [op.matvec(w_true) + rng.normal(0, 0.01, op.dimsd) for op in ops]
    gs[1][:25, :30] += 0.3  # a change in the second window
    masks = [op.valid.copy() for op in ops]
    lam, step = 0.05, 2
    scratch = Scratch()
    w1, _ = active_set(ops, gs, lam=lam, row_step=step, scratch=scratch)
    gs2 = [g - offset for g in gs]
    moved = _partition_moves(ops, gs, gs2, masks, w1, lam, step)
    w2, info = active_set(ops, gs2, lam=lam, row_step=step, scratch=scratch, w0=w1)
    fresh, _ = active_set(ops, gs2, lam=lam, row_step=step, w0=w1)
    assert info["converged"] and _kkt_of_rows(ops, gs2, masks, w2, lam, step)
    np.testing.assert_allclose(w2, fresh, atol=1e-9)
    if offset < 0.01:  # some pixels moved across the threshold, far fewer than half
        assert 0.001 < moved < 0.2
        assert scratch.carry.used == 1 and info["warm_start"]["carried"]
    else:
        assert moved > 0.5 and scratch.carry.used == 0 and "carried" not in info["warm_start"]
    # other operators on the same windows, or other masks: never the held matrix
    used = scratch.carry.used
    others = [BlurOperator(f, grid, b) for b in boxes]
    active_set(others, gs2, lam=lam, row_step=step, scratch=scratch, w0=w2)
    fewer = [m.copy() for m in masks]
    fewer[0][40:44] = False
    active_set(others, gs2, lam=lam, row_step=step, scratch=scratch, w0=w2, masks=fewer)
    assert scratch.carry.used == used


def test_photometric_refit_recovers_the_offset(levir_gray, paper_grid):
    """An observation with another gain and offset than the reference: the refit finds
    the offset (synthetic truth), the weights carry the gain in their sum, and they fit
    the blur as well as without the photometric change."""
    w_true = grid_path(paper_grid, rng=11, n_poses=25)
    clean, _ = blur_weights(levir_gray, paper_grid, w_true, BOX, dtype=np.float32)
    a_true, b_true = 0.93, 0.035
    obs = _embed(a_true * clean + b_true, levir_gray.shape)
    op = BlurOperator(levir_gray, paper_grid, BOX)
    plain = estimate_motion(levir_gray, obs, paper_grid, boxes=[BOX])
    refit = estimate_motion(levir_gray, obs, paper_grid, boxes=[BOX], refit_photometry=True)
    ph = refit.info["photometry"]
    assert abs(ph["offset"][0] - b_true) <= 5e-4, ph
    assert abs(refit.weights.sum() - a_true * w_true.sum()) <= 5e-3
    fit_refit = op.matvec(refit.weights)[:, :, 0]
    fit_plain = op.matvec(plain.weights)[:, :, 0]
    truth = a_true * clean + b_true
    assert psnr(fit_refit + b_true, truth) >= 40.0
    assert psnr(fit_refit + b_true, truth) > psnr(fit_plain, truth) + 3.0
    assert mass_near_truth(refit.weights, w_true) >= 0.9
    # without a photometric difference the refit is (almost) the identity
    same = estimate_motion(levir_gray, _embed(clean, levir_gray.shape), paper_grid,
                           boxes=[BOX], refit_photometry=True)
    assert abs(same.info["photometry"]["offset"][0]) <= 5e-4


class _Win:
    """The part of a window that the line search reads: mask, Huber delta, outliers."""

    def __init__(self, m3, delta, signs=None):
        self.m3, self.delta, self.s = m3, delta, signs

    def outliers(self, r):
        if self.delta is None:
            return None
        if self.s is None:
            return self.m3 & (np.abs(r) > self.delta)
        return self.m3 & (self.s * r > self.delta)


def test_line_search_finds_the_minimiser_of_the_huber_objective():
    """The Newton / secant line search returns the step that bisection on the derivative
    of ``phi(t) = lam t sum(dw) + sum huber(r - t D)`` converges to (written out here
    independently), for squared, two-sided and one-sided Huber losses, and 1 when the
    objective still decreases at the full step."""
    from reblur.solve import _line_search, _Windows

    def phi_slope(wins, res, deltas, dw_sum, lam, t):
        s = lam * dw_sum
        for w, r, D in zip(wins, res, deltas, strict=True):
            rt = r - t * D
            if w.delta is None:
                psi = 2.0 * rt
            else:
                out = w.m3 & ((np.abs(rt) if w.s is None else w.s * rt) > w.delta)
                psi = np.where(out, 2.0 * w.delta * np.sign(rt), 2.0 * rt)
            s -= float(np.sum(np.where(w.m3, psi, 0.0) * D))
        return s

    rng = np.random.default_rng(3)
    found_interior = 0
    for trial in range(60):
        kind = trial % 3
        wins, res, deltas = [], [], []
        for _ in range(2):
            m3 = rng.random((30, 20, 1)) > 0.2
            delta = None if kind == 0 else float(rng.uniform(0.05, 0.5))
            signs = np.sign(rng.normal(size=m3.shape)) if kind == 2 else None
            r = np.where(m3, rng.normal(0, 0.4, m3.shape), 0.0)
            D = np.where(m3, rng.normal(0, 0.3, m3.shape) + 0.2 * r, 0.0)
            wins.append(_Win(m3, delta, signs))
            res.append(r)
            deltas.append(D)
        dw_sum, lam = float(rng.normal()), float(rng.uniform(0, 2))
        t = _line_search(_Windows(wins), res, deltas, dw_sum, lam)
        if phi_slope(wins, res, deltas, dw_sum, lam, 1.0) <= 0:
            assert t == 1.0
            continue
        lo, hi = 0.0, 1.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if phi_slope(wins, res, deltas, dw_sum, lam, mid) <= 0:
                lo = mid
            else:
                hi = mid
        assert abs(t - lo) < 1e-9, (trial, t, lo)
        found_interior += 0.0 < lo < 1.0
    assert found_interior >= 20


def test_batch_grows_with_the_active_set():
    """Poses enter ``batch`` at a time, or a quarter of the active set when that is more:
    from a warm start of 40 poses with ``batch=1``, some outer iteration adds 10 or more
    (the counts are observed through the callback); the solve passes the KKT test from
    the explicit matrix, at the scale of the gradient at ``w = 0`` (the solver's, for a
    warm start as for a cold one), and still fits the blur."""
    import cv2

    rng = np.random.default_rng(12)
    f = cv2.GaussianBlur(rng.random((140, 140)), (0, 0), 1.2)
    grid = PoseGrid((140, 140), tx=np.arange(-6, 7), ty=np.arange(-6, 7))
    op = BlurOperator(f, grid, (20, 20, 100, 100))
    w_true = np.zeros(grid.size)
    w_true[rng.choice(grid.size, 60, replace=False)] = rng.random(60) + 0.5
    w_true = (w_true / w_true.sum()).reshape(grid.shape)
    g = op.matvec(w_true)
    w0 = np.zeros(grid.size)
    w0[np.flatnonzero(w_true.ravel())[:40]] = 1.0 / 40
    sizes = []
    w, info = active_set([op], [g], lam=1e-6, occlusion=False, batch=1,
                         w0=w0.reshape(grid.shape),
                         callback=lambda w: sizes.append(int(np.count_nonzero(w))))
    steps = np.diff([40] + sizes)
    assert steps.max() >= 10
    assert info["converged"]
    A = np.stack([op.column(k)[:, :, 0].ravel() for k in range(grid.size)], axis=1)
    m = op.valid.ravel()
    A, gv = A[m].astype(float), g[:, :, 0].ravel()[m]
    grad = 1e-6 - A.T @ (2 * (gv - A @ w.ravel()))  # eq. 3: squared loss, lam = 1e-6
    scale = np.abs(A.T @ (2 * gv)).max()
    on = w.ravel() > 0
    assert np.all(np.abs(grad[on]) <= 1e-6 * scale) and np.all(grad[~on] >= -1e-6 * scale)
    assert np.linalg.norm(op.matvec(w) - g) <= 1e-3 * np.linalg.norm(g)


def test_warm_start_record_counts_the_poses_its_own_optimum_keeps():
    """``info["warm_start"]``: a warm start on 30 poses of positive weight and 20 poses the
    data holds with a small negative weight keeps, once its own weights are optimised, as
    many poses as the non-negative least squares on those 50 columns (``scipy.optimize.nnls``
    on the explicit matrix; lam ~ 0): fewer than it started from."""
    import cv2
    from scipy.optimize import nnls

    rng = np.random.default_rng(5)
    f = cv2.GaussianBlur(rng.random((120, 120)), (0, 0), 1.0)
    grid = PoseGrid((120, 120), tx=np.arange(-5, 6), ty=np.arange(-5, 6))
    op = BlurOperator(f, grid, (20, 20, 80, 80))
    picks = rng.choice(grid.size, 50, replace=False)
    w_true = np.zeros(grid.size)
    w_true[picks[:30]] = rng.random(30) + 0.5
    w_true /= w_true.sum()
    w_true[picks[30:]] = -0.002
    g = op.matvec(w_true.reshape(grid.shape))
    w0 = np.zeros(grid.size)
    w0[picks] = 1.0 / 50
    _, info = active_set([op], [g], lam=1e-9, occlusion=False, w0=w0.reshape(grid.shape))
    m = op.valid.ravel()
    A = np.stack([op.column(k)[:, :, 0].ravel()[m] for k in picks], axis=1).astype(float)
    x, _ = nnls(A, g[:, :, 0].ravel()[m].astype(float))
    assert info["warm_start"] == {"poses": 50, "kept": int(np.count_nonzero(x > 1e-9))}
    assert 0 < info["warm_start"]["kept"] < 50
    _, cold = active_set([op], [g], lam=1e-9, occlusion=False)
    assert "warm_start" not in cold


def test_coarse_to_fine_solves_the_centres_before_the_full_windows(levir_gray):
    """Four windows: the finest roll stride is solved on their central parts first, then
    on the full windows with the same poses, reaching the optimum of the direct solve.
    The observation is read once per window (the central parts are views)."""
    H, W = levir_gray.shape
    path = random_camera_path(6, center=((W - 1) / 2, (H - 1) / 2), t_max=5.0, rz_max=1.0)
    boxes = [(120, 120, 260, 260), (640, 640, 260, 260), (120, 640, 260, 260),
             (640, 120, 260, 260)]
    obs = np.zeros((H, W))
    for b in boxes:
        g, _ = blur_along_path(levir_gray, path, b, dtype=np.float32)
        obs[b[0] : b[0] + b[2], b[1] : b[1] + b[3]] = g.reshape(b[2], b[3])

    class Counted:  # an array that counts its reads
        def __init__(self, a):
            self.a, self.shape, self.dtype, self.reads = a, a.shape, a.dtype, 0

        def __getitem__(self, key):
            self.reads += 1
            return self.a[key]

    grid = PoseGrid.from_ranges((H, W), t_max=8, rz_max=1.5, rz_step=0.05)  # 61 angles
    direct = estimate_motion(levir_gray, obs, grid, boxes=boxes, coarse_to_fine=False)
    counted = Counted(obs)
    c2f = estimate_motion(levir_gray, counted, grid, boxes=boxes, coarse_to_fine=True,
                          max_bases=6)
    assert counted.reads == len(boxes)
    lv = c2f.info["levels"]
    assert [(v["stride"], v["side"]) for v in lv[-2:]] == [(1, 128), (1, 260)]
    assert lv[-2]["n_angles"] == lv[-1]["n_angles"] and lv[-2]["n_t"] == lv[-1]["n_t"]
    assert all(v["side"] == 128 for v in lv[:-1])
    # rows fitted (estimate.row_step): every row of the 128 px central parts (16384 px, under
    # ROW_SAMPLE_PIXELS), every other row of the 260 px windows (67600 px: 2 x 32768 and
    # more, all valid)
    assert [v["row_step"] for v in lv] == [1] * (len(lv) - 1) + [2]
    # the first level starts cold; each later one from all of the poses the level before
    # ended on (its angles a lattice through theirs), and records what it kept of them
    assert "warm_start" not in lv[0]
    for before, v in zip(lv[:-1], lv[1:], strict=True):
        assert v["warm_start"]["poses"] == before["n_active"]
        assert 0 < v["warm_start"]["kept"] <= v["warm_start"]["poses"]
    ops = [BlurOperator(levir_gray, grid, b) for b in boxes]
    gs = [obs[b[0] : b[0] + b[2], b[1] : b[1] + b[3], None] for b in boxes]
    f_direct = huber_objective(ops, gs, direct.weights, 0.1)
    f_c2f = huber_objective(ops, gs, c2f.weights, 0.1)
    data_direct = f_direct - 0.1 * direct.weights.sum()
    assert f_c2f - f_direct <= 0.02 * data_direct, (f_c2f, f_direct, data_direct)
    assert min(c2f.info["psnr"]) >= min(direct.info["psnr"]) - 0.5


@pytest.mark.parametrize("keep", [0.9, 0.15])
@pytest.mark.parametrize("n_old", [0, 30])
def test_gram_of_many_new_columns_equals_the_explicit_product(n_old, keep):
    """Many columns entering at once (a warm start; their block by SYRK): the
    cached ``A^T D A``, ``A^T D g`` and ``A^T s`` equal those of the explicit matrix, with
    a masked window (mostly valid: its row blocks are copied whole; mostly masked: their
    valid pixels gathered) whose masked pixels hold NaN, and outliers of both signs."""
    import cv2

    from reblur.solve import _gram_add, _Window, _Windows

    rng = np.random.default_rng(21)
    f = cv2.GaussianBlur(rng.random((140, 140)), (0, 0), 1.2)
    grid = PoseGrid((140, 140), tx=np.arange(-3, 4), ty=np.arange(-3, 4),
                    rz=[-1.0, -0.5, 0.0, 0.5, 1.0])  # 245 poses
    op = BlurOperator(f, grid, (30, 25, 70, 90))
    g = rng.random(op.dimsd)
    mask = op.valid & (rng.random(op.valid.shape) < keep)
    g[~mask] = np.nan  # no data there: must not reach the products
    win = _Window(op, g, mask, delta=0.2)
    win.inl, win.sgn = win.partition(g - 0.5)  # a partition with outliers of both signs
    assert 0 < (~win.inl & win.m3).sum() and (win.sgn > 0).any() and (win.sgn < 0).any()
    cols = [int(k) for k in rng.permutation(grid.size)[: n_old + 149]]
    old, new = cols[:n_old], cols[n_old:]
    G0, b0, d0 = np.zeros((0, 0)), np.zeros(0), np.zeros(0)
    if old:
        G0, b0, d0 = _gram_add(_Windows([win]), [], old, G0, b0, d0)
    G, b, d = _gram_add(_Windows([win]), old, new, G0, b0, d0)
    A = np.stack([op.column(k).astype(float).ravel() for k in cols], axis=1)
    m = win.m3.ravel()
    Dv = win.inl.ravel()[m].astype(float)
    A = A[m]
    np.testing.assert_allclose(G, A.T @ (Dv[:, None] * A), rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(b, A.T @ (Dv * g.ravel()[m]), rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(d, A.T @ win.sgn.ravel()[m].astype(float), rtol=1e-10,
                               atol=1e-9)


def test_estimate_threads_reach_the_operators(monkeypatch, levir_gray):
    """``estimate_motion(threads=...)`` sizes the operators' threaded column sums too."""
    from reblur import estimate as estimate_module

    made = []
    real = estimate_module.BlurOperator

    def spy(*args, **kwargs):
        op = real(*args, **kwargs)
        made.append(op.threads)
        return op

    monkeypatch.setattr(estimate_module, "BlurOperator", spy)
    grid = PoseGrid(levir_gray.shape, tx=range(-2, 3), ty=range(-2, 3), rz=[-0.1, 0.0, 0.1])
    f = levir_gray.astype(float)
    estimate_motion(f, f, grid, boxes=[(300, 300, 64, 64)], occlusion=False, threads=1)
    assert made == [1]


def _three_windows(rng):
    """Three windows sharing one blur, one of them partly changed (Huber outliers)."""
    import cv2

    f = cv2.GaussianBlur(rng.random((200, 200)), (0, 0), 1.5)
    grid = PoseGrid((200, 200), tx=np.arange(-2, 3), ty=np.arange(-2, 3), rz=[-1.0, 0.0, 1.0])
    boxes = ((10, 10, 60, 70), (120, 100, 60, 70), (20, 120, 50, 60))
    ops = [BlurOperator(f, grid, b, threads=2) for b in boxes]
    w_true = np.zeros(grid.shape)
    w_true[0, 2, 2], w_true[2, 1, 3], w_true[1, 3, 1] = 0.5, 0.3, 0.2
    gs = [op.matvec(w_true) + rng.normal(0, 0.005, op.dimsd) for op in ops]
    gs[1][:25, :40] += 0.3  # a change in the second window
    return grid, ops, gs, w_true


@pytest.mark.parametrize("workers", [2, 3])
def test_windows_in_threads_reach_the_same_optimum(workers):
    """Per-window steps in threads (three windows: groups of 2 + 1, or one each) give the
    one-after-the-other solve to rounding, and the optimum passes the KKT test computed
    from the explicit columns of all windows; every operator's threads and the BLAS limit
    are as before afterwards."""
    from threadpoolctl import threadpool_info

    rng = np.random.default_rng(31)
    grid, ops, gs, w_true = _three_windows(rng)
    lam = 0.05
    blas_before = [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
    serial, info_s = active_set(ops, gs, lam=lam)
    par, info_p = active_set(ops, gs, lam=lam, workers=workers)
    assert info_p["converged"] and info_s["converged"]
    np.testing.assert_allclose(par, serial, rtol=1e-8, atol=1e-10)
    assert [op.threads for op in ops] == [2, 2, 2]
    assert [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"] \
        == blas_before
    # KKT of eq. 5 (chi eliminated: Huber at lam / 2) from the explicit matrices
    delta = lam / 2
    grad = np.full(grid.size, lam)
    scale = np.zeros(grid.size)
    for op, g in zip(ops, gs, strict=True):
        A = np.stack([op.column(k)[:, :, 0].ravel() for k in range(grid.size)], axis=1)
        m = op.valid.ravel()
        A, gv = A[m].astype(float), g[:, :, 0].ravel()[m]
        grad -= A.T @ (2 * np.clip(gv - A @ par.ravel(), -delta, delta))
        scale += A.T @ (2 * np.clip(gv, -delta, delta))
    on = par.ravel() > 0
    tol = 1e-6 * np.abs(scale - lam).max()
    assert np.all(np.abs(grad[on]) <= tol) and np.all(grad[~on] >= -tol)
    assert mass_near_truth(par, w_true) > 0.9


def test_windows_in_threads_give_the_serial_solve_bit_for_bit():
    """Windows large enough for several row blocks of the Gram products: solved in two
    threads or one after the other, the weights and the objective's history are the same
    numbers (the blocks' rows do not depend on the windows solved at once), so a result
    does not depend on the machine's cores."""
    import cv2

    rng = np.random.default_rng(35)
    f = cv2.GaussianBlur(rng.random((460, 460)), (0, 0), 1.5)
    grid = PoseGrid((460, 460), tx=np.arange(-2, 3), ty=np.arange(-2, 3), rz=[-0.5, 0.0, 0.5])
    boxes = ((10, 10, 200, 210), (240, 230, 200, 210))  # 42000 px each
    ops = [BlurOperator(f, grid, b, threads=2) for b in boxes]
    w_true = np.zeros(grid.shape)
    w_true[1, 2, 2], w_true[2, 1, 3], w_true[0, 3, 1] = 0.5, 0.3, 0.2
    gs = [op.matvec(w_true) + rng.normal(0, 0.005, op.dimsd) for op in ops]
    gs[1][:60, :80] += 0.3  # a change: Huber outliers
    serial, info_s = active_set(ops, gs, lam=0.05)
    par, info_p = active_set(ops, gs, lam=0.05, workers=2)
    np.testing.assert_array_equal(par, serial)
    assert info_p["objective"] == info_s["objective"]
    assert mass_near_truth(par, w_true) > 0.9


def test_a_failing_window_thread_restores_the_threads():
    """An error in one window's thread reaches the caller, and leaves the operators'
    threads as they were."""
    rng = np.random.default_rng(32)
    _, ops, gs, _ = _three_windows(rng)

    def broken(r):
        raise RuntimeError("window 2 failed")

    ops[2].rmatvec = broken
    with pytest.raises(RuntimeError, match="window 2 failed"):
        active_set(ops, gs, lam=0.05, workers=2)
    assert [op.threads for op in ops] == [2, 2, 2]


def test_operators_built_in_threads_equal_the_serial_build(levir_gray):
    """The estimate builds its windows' operators in threads: the same stacks, spectra
    and masks as one at a time, and each operator then has the estimate's threads."""
    from reblur.estimate import _build_operators

    f = levir_gray.astype(np.float32)
    grid = PoseGrid(f.shape, tx=range(-3, 4), ty=range(-2, 3), rz=[-0.2, 0.0, 0.3])
    boxes = [(100, 100, 90, 80), (600, 650, 70, 90), (300, 700, 64, 64)]
    par = _build_operators(f, grid, boxes, None, "auto", 255.0, 2)
    for op, b in zip(par, boxes, strict=True):
        ref = BlurOperator(f, grid, b, scale=255.0, threads=1)
        assert op.threads == 2
        np.testing.assert_array_equal(op.stack, ref.stack)
        np.testing.assert_array_equal(op.spec, ref.spec)
        np.testing.assert_array_equal(op.valid, ref.valid)


class _CountingReads:
    """A lazily read image (no ``chunks``) that counts how often each pixel is read."""

    def __init__(self, a):
        self.a, self.shape, self.dtype, self.ndim = a, a.shape, a.dtype, a.ndim
        self.times = np.zeros(a.shape[:2], np.int32)

    def __getitem__(self, key):
        self.times[key[:2]] += 1
        return np.asarray(self.a[key])


def test_lazy_reference_is_read_once_per_pixel(levir_gray, monkeypatch):
    """A lazily read reference goes through a chunk cache: the coarse-to-fine estimate,
    whose levels read overlapping regions, reads no pixel of it twice, and returns
    exactly what the in-memory reference gives."""
    import reblur.estimate as E

    obs, grid, boxes = _two_windows_rolled(levir_gray)
    kw = dict(boxes=boxes, coarse_to_fine=True, max_bases=6)
    plain = estimate_motion(levir_gray, obs, grid, **kw)
    assert len(plain.info["levels"]) >= 3
    lazy = _CountingReads(levir_gray)
    cached = estimate_motion(lazy, obs, grid, **kw)
    np.testing.assert_array_equal(cached.weights, plain.weights)
    assert lazy.times.max() == 1
    # without the cache the levels read some pixels several times
    direct = _CountingReads(levir_gray)
    monkeypatch.setattr(E, "_cached_reads", lambda r: r)
    estimate_motion(direct, obs, grid, **kw)
    assert direct.times.max() >= 3


@pytest.mark.parametrize("one_sided", [False, True])
def test_kkt_scale_is_the_gradient_at_zero_for_any_start(one_sided):
    """The KKT test's scale is the data term's largest gradient at ``w = 0``, computed
    here from the explicit matrix: the same for a cold start and for a warm start (whose
    own gradient is far smaller: scaled by it, the test was stricter the better the
    start)."""
    import cv2

    rng = np.random.default_rng(44)
    f = cv2.GaussianBlur(rng.random((90, 90)), (0, 0), 1.3)
    grid = PoseGrid((90, 90), tx=np.arange(-3, 4), ty=np.arange(-3, 4), rz=[-1.0, 0.0, 1.0])
    op = BlurOperator(f, grid, (12, 12, 66, 66))
    w_true = np.zeros(grid.shape)
    w_true[1, 3, 3], w_true[2, 2, 4] = 0.6, 0.4
    g = op.matvec(w_true) + rng.normal(0, 0.01, op.dimsd)
    g[:10, :20] += 0.4  # a change: outliers of the Huber loss
    lam, delta = 0.05, 0.025
    s = np.ones(op.dimsd) if one_sided else None
    A = np.stack([op.column(k)[:, :, 0].ravel() for k in range(grid.size)], axis=1)
    m = op.valid.ravel()
    A, gv = A[m].astype(float), g[:, :, 0].ravel()[m]
    if s is None:
        psi0 = 2 * np.clip(gv, -delta, delta)
    else:
        psi0 = np.where(gv > delta, 2 * delta, 2 * gv)
    scale = np.abs(A.T @ psi0).max()
    kw = dict(lam=lam, signs=None if s is None else [s])
    _, cold = active_set([op], [g], **kw)
    warm_w, warm = active_set([op], [g], w0=w_true, **kw)
    assert cold["kkt_scale"] == pytest.approx(scale, rel=1e-5)
    assert warm["kkt_scale"] == pytest.approx(scale, rel=1e-5)
    # the warm start's own gradient scale is far smaller than the problem's
    r0 = gv - A @ w_true.ravel()
    psi_w = 2 * np.clip(r0, -delta, delta) if s is None else np.where(r0 > delta, 2 * delta,
                                                                        2 * r0)
    assert np.abs(A.T @ psi_w).max() < 0.1 * scale


def test_band_mean_estimate_keeps_the_change_term_per_band(levir_rgb, paper_grid):
    """Weights solved on the band mean of an RGB pair (``bands="mean"``): the path is
    found, and the change term, the fit's PSNR and the change share are those of the
    weights' residual in every band, checked against the slow explicit blur
    (``blur_weights``): a change in one band shows in that band only."""
    w_true = grid_path(paper_grid, rng=3, n_poses=20)
    g, _ = blur_weights(levir_rgb, paper_grid, w_true, BOX, dtype=np.float64)
    g[100:160, 200:260, 0] += 0.4  # the red band only
    est = estimate_motion(levir_rgb, _embed(g, levir_rgb.shape), paper_grid, boxes=[BOX],
                          lam=0.1, bands="mean")
    assert est.info["bands"] == "mean"
    assert mass_near_truth(est.weights, w_true) >= 0.9
    fit, valid = blur_weights(levir_rgb, paper_grid, est.weights, BOX, dtype=np.float32)
    assert valid.all()
    r = g - fit
    chi = est.chi[0]
    assert chi.shape == g.shape
    np.testing.assert_allclose(chi, soft_threshold(r, 0.05), atol=1e-5)
    assert (chi[100:160, 200:260, 0] != 0).mean() >= 0.95
    assert not chi[100:160, 200:260, 1:].any()
    assert est.info["psnr"][0] == pytest.approx(psnr(fit, g), abs=1e-4)
    share = float((chi != 0).any(axis=2).mean())
    assert est.info["occluded"][0] == pytest.approx(share, abs=1e-9)
    assert share >= 60 * 60 / 512**2


def test_band_mean_refit_gives_an_offset_per_band(levir_rgb, paper_grid):
    """An offset on every band of an RGB observation (synthetic truth): the refit on the
    band mean reports it once per band, as the solve on every band does."""
    w_true = grid_path(paper_grid, rng=11, n_poses=25)
    clean, _ = blur_weights(levir_rgb, paper_grid, w_true, BOX, dtype=np.float64)
    obs = _embed(0.95 * clean + 0.03, levir_rgb.shape)
    for bands in ("mean", "all"):
        est = estimate_motion(levir_rgb, obs, paper_grid, boxes=[BOX], refit_photometry=True,
                              bands=bands)
        offset = est.info["photometry"]["offset"]
        assert len(offset) == 3
        np.testing.assert_allclose(offset, 0.03, atol=1e-3)
        assert mass_near_truth(est.weights, w_true) >= 0.9


def test_bands_option_is_checked(levir_gray):
    from reblur.select import SelectParams

    with pytest.raises(ValueError, match="bands"):
        SelectParams(bands="red")
    with pytest.raises(ValueError, match="bands"):
        estimate_motion(levir_gray, levir_gray, PoseGrid.paper(levir_gray.shape),
                        bands="luma")


def test_photometric_rounds_stop_at_the_refit_rtol(levir_gray, paper_grid, monkeypatch):
    """The photometric rounds re-solve from the weights found with ``rtol`` at least
    ``REFIT_RTOL`` (the first solve keeps its own), and still recover the offset."""
    import reblur.estimate as E

    w_true = grid_path(paper_grid, rng=11, n_poses=25)
    clean, _ = blur_weights(levir_gray, paper_grid, w_true, BOX, dtype=np.float32)
    obs = _embed(0.93 * clean + 0.035, levir_gray.shape)
    seen = []
    solve = E.active_set

    def recorded(*args, **kw):
        seen.append((kw.get("w0") is not None, kw["rtol"]))
        return solve(*args, **kw)

    monkeypatch.setattr(E, "active_set", recorded)
    est = estimate_motion(levir_gray, obs, paper_grid, boxes=[BOX], refit_photometry=True)
    assert seen[0] == (False, E.RTOL)  # the solve itself
    rounds = [rtol for warm, rtol in seen[1:] if warm]
    assert rounds and all(r == E.REFIT_RTOL > E.RTOL for r in rounds)
    assert abs(est.info["photometry"]["offset"][0] - 0.035) <= 5e-4


def test_full_window_level_stops_at_the_fine_rtol_on_a_long_real_shake():
    """GoPro GOPR0477 frame 13 against the mean of 16 hand-held 240 fps frames (a real
    shake of ~15 px), the pipeline's two 500 px windows, weights on the band mean: the
    coarse-to-fine's last level (the full windows, from the central parts' weights) stops
    at ``FINE_RTOL``, the levels before it at ``RTOL``.  Against the same estimate with the
    last level at ``RTOL`` (a longer solve to a lower objective: the reference), it ends
    in fewer outer iterations, its objective within 1 % and its windows' reblur within
    0.1 dB."""
    import reblur.estimate as E
    from reblur.testbed import gopro_pair

    ref, obs = gopro_pair(13, 16)
    grid = PoseGrid.from_ranges(obs.shape[:2], t_max=12, rz_max=3.0, corner_px=1.0)
    kw = dict(boxes=[(100, 600, 500, 500), (100, 100, 500, 500)], bands="mean")
    fine = estimate_motion(ref, obs, grid, **kw)
    slow = estimate_motion(ref, obs, grid, fine_rtol=E.RTOL, **kw)
    assert E.RTOL < E.FINE_RTOL
    lv = fine.info["levels"]
    assert [v["rtol"] for v in lv] == [E.RTOL] * (len(lv) - 1) + [E.FINE_RTOL]
    assert lv[-1]["side"] == 500 and "warm_start" in lv[-1]
    # the last level's outer iterations: each but the last lowered the objective by at
    # least FINE_RTOL of its value (or it ended on the KKT test)
    obj = np.asarray(fine.info["objective"][-lv[-1]["n_outer"]:])
    drops = (obj[:-1] - obj[1:]) / obj[1:]
    assert np.all(drops[:-1] >= E.FINE_RTOL)
    assert fine.info["converged"] or drops[-1] < E.FINE_RTOL
    assert lv[-1]["n_outer"] < slow.info["levels"][-1]["n_outer"]
    assert fine.info["objective"][-1] <= 1.01 * slow.info["objective"][-1]
    assert min(fine.info["psnr"]) >= min(slow.info["psnr"]) - 0.1


def test_row_step_rule():
    """``estimate.row_step``: the largest step up to ``MAX_ROW_STEP`` leaving every window
    ``ROW_SAMPLE_PIXELS`` of its pixels and half that of its valid ones; 1 with an
    operator that has no row views (the rolling-shutter band model)."""
    from types import SimpleNamespace

    from reblur.estimate import MAX_ROW_STEP, ROW_SAMPLE_PIXELS, row_step
    from reblur.warp import Box

    def op(side, valid_share=1.0):
        valid = np.zeros((side, side), bool)
        valid.flat[: int(round(valid_share * side * side))] = True
        return SimpleNamespace(box=Box(0, 0, side, side), valid=valid, rows=lambda k: None)

    assert (MAX_ROW_STEP, ROW_SAMPLE_PIXELS) == (4, 32768)
    assert row_step([op(500, 0.8), op(500, 0.77)]) == 4  # 7 by the area, 11 by the valid
    assert row_step([op(256, 0.8)]) == 2  # 65536 px: 2; 52429 valid: 3
    assert row_step([op(500), op(256)]) == 2  # one step for all the windows
    assert row_step([op(500, 0.2)]) == 3  # 50000 valid: 3 x 16384 and more
    assert row_step([op(180)]) == 1
    assert row_step([op(500), op(500, 0.0)]) == 1  # a window with no data left
    rolling = SimpleNamespace(box=Box(0, 0, 500, 500), valid=np.ones((500, 500), bool))
    assert row_step([op(500), rolling]) == 1  # an operator without row views


@pytest.mark.parametrize(("one_sided", "step", "weight"),
                         [(False, 3, 1.0), (True, 3, 1.0), (False, 1, 4.0), (True, 3, 4.0)])
def test_row_step_solves_the_sampled_rows_with_the_l1_term_scaled(one_sided, step, weight):
    """``active_set(row_step=s, pixel_weight=p)`` fits the windows' rows ``0, s, 2s, ...``
    with the weights' l1 term divided by ``s p``: its result passes the KKT test of that
    problem on the explicit matrix of those rows (the Huber threshold still ``lam / 2``),
    and the objective it reports is ``s p`` times that problem's, the whole windows' (or
    the full resolution's) units."""
    import cv2

    rng = np.random.default_rng(21)
    f = cv2.GaussianBlur(rng.random((160, 160)), (0, 0), 1.5)
    grid = PoseGrid((160, 160), tx=np.arange(-2, 3), ty=np.arange(-2, 3), rz=[-1.0, 0.0, 1.0])
    ops = [BlurOperator(f, grid, b) for b in ((10, 10, 61, 70), (90, 80, 60, 70))]
    w_true = np.zeros(grid.shape)
    w_true[0, 2, 2], w_true[2, 1, 3], w_true[1, 3, 1] = 0.5, 0.3, 0.2
    gs = [op.matvec(w_true) + rng.normal(0, 0.01, op.dimsd) for op in ops]
    gs[1][:25, :30] += 0.3  # a change in the second window
    masks = [op.valid.copy() for op in ops]
    masks[0][30:34] = False  # pixels left out of the data term
    signs = [np.ones(op.dimsd) for op in ops] if one_sided else None
    lam = 0.05
    delta = lam / 2
    w, info = active_set(ops, gs, lam=lam, masks=masks, signs=signs, row_step=step,
                         pixel_weight=weight)
    assert info["converged"] and info.get("row_step", 1) == step
    A = np.concatenate([np.stack([op.column(k)[::step][m[::step]].ravel()
                                  for k in range(grid.size)], axis=1)
                        for op, m in zip(ops, masks, strict=True)])
    gv = np.concatenate([g[::step][m[::step]].ravel() for g, m in zip(gs, masks, strict=True)])
    sv = None if signs is None else np.ones_like(gv)
    r = gv - A @ w.ravel()
    out = np.abs(r) > delta if sv is None else sv * r > delta
    assert out.sum() > 100  # the change is in the linear part of the loss
    psi = np.where(out, 2 * delta * np.sign(r), 2 * r)
    grad = lam / (step * weight) - A.T @ psi
    on = w.ravel() > 0
    scale = np.abs(A.T @ np.where(np.abs(gv) > delta, 2 * delta * np.sign(gv), 2 * gv)).max()
    assert np.all(np.abs(grad[on]) <= 1e-6 * scale)
    assert np.all(grad[~on] >= -1e-6 * scale)
    loss = np.where(out, 2 * delta * np.abs(r) - delta * delta, r * r).sum()
    assert info["objective"][-1] == pytest.approx(step * weight * loss + lam * w.sum(),
                                                  rel=1e-6)
    assert mass_near_truth(w, w_true) > 0.9
    with pytest.raises(ValueError, match="row_step"):
        active_set(ops, gs, lam=lam, row_step=0)
    for bad in (0.5, True, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="pixel_weight"):
            active_set(ops, gs, lam=lam, pixel_weight=bad)


def _dense_blur_problem():
    """A window blurred by a dense kernel: every one of the 13 x 13 translations carries
    weight (a disk-like blob), as a defocus blur does, instead of a shake's path."""
    import cv2

    rng = np.random.default_rng(21)
    f = cv2.GaussianBlur(rng.random((150, 150)), (0, 0), 1.0)
    grid = PoseGrid((150, 150), tx=np.arange(-6, 7), ty=np.arange(-6, 7))
    op = BlurOperator(f, grid, (20, 20, 110, 110))
    yy, xx = np.mgrid[-6:7, -6:7]
    w_true = np.exp(-(xx**2 + yy**2) / (2 * 3.0**2))[None]
    w_true /= w_true.sum()
    g = op.matvec(w_true) + rng.normal(0, 1e-3, op.dimsd)
    return op, grid, g


def test_max_active_bounds_the_active_set_and_stops_at_the_optimum_over_it(monkeypatch):
    """A solve bounded by ``max_active`` holds at most that many poses, stops once it has
    filled them (at the next outer iteration, where the unbounded solve goes on growing),
    and its weights are the optimum over the poses it holds: the KKT conditions of eq. 3
    restricted to them, from the explicit matrix (fails if the bound leaves the last
    Newton step out, or stops before optimising the poses it added)."""
    import reblur.solve as solve_mod

    op, grid, g = _dense_blur_problem()
    lam = 1e-6
    w_free, free = active_set([op], [g], lam=lam, occlusion=False, batch=8)
    assert free["n_active"] > 60 and not free["capped"]
    growths = []  # (poses held, poses added) of each outer iteration's Gram growth
    gram_add = solve_mod._gram_add

    def spy(ws, active, new, G, b, d):
        growths.append((len(active), len(new)))
        return gram_add(ws, active, new, G, b, d)

    monkeypatch.setattr(solve_mod, "_gram_add", spy)
    w, info = active_set([op], [g], lam=lam, occlusion=False, batch=16, max_active=30)
    assert info["capped"] and not info["converged"]
    held = [k + n for k, n in growths]
    assert held[-1] == 30 and max(held[:-1]) < 30  # the last growth filled the bound
    # its Newton steps dropped some poses again, yet the next outer iteration stopped:
    # a solve that kept refilling the room would run on at the bound's cost
    assert info["n_active"] < 30
    assert info["n_outer"] == len(growths) + 1 < free["n_outer"]
    A = np.stack([op.column(k)[:, :, 0].ravel() for k in range(grid.size)], axis=1)
    m = op.valid.ravel()
    A, gv = A[m].astype(float), g[:, :, 0].ravel()[m]
    grad = lam - A.T @ (2 * (gv - A @ w.ravel()))
    scale = np.abs(A.T @ (2 * gv)).max()
    on = w.ravel() > 0
    assert np.all(np.abs(grad[on]) <= 1e-6 * scale)
    # the poses left out would still lower it (the solver converges at -1e-6 of the scale)
    assert grad[~on].min() < -1e-5 * scale
    # the bounded fit is worse than the free one, but a fair approximation of the blob
    res = np.linalg.norm(op.matvec(w) - g) / np.linalg.norm(g)
    res_free = np.linalg.norm(op.matvec(w_free) - g) / np.linalg.norm(g)
    assert res_free < res < 0.05


def test_max_active_above_the_active_set_changes_nothing():
    """A bound the solve never reaches gives the unbounded solve bit for bit; a warm start
    holding more poses than the bound keeps them and adds none."""
    op, grid, g = _dense_blur_problem()
    w_free, free = active_set([op], [g], lam=1e-6, occlusion=False, batch=8)
    w_big, big = active_set([op], [g], lam=1e-6, occlusion=False, batch=8,
                            max_active=free["n_active"] + 50)
    assert np.array_equal(w_free, w_big) and not big["capped"]
    w0 = np.where(w_free > 0, w_free, 0.0)
    n0 = int(np.count_nonzero(w0))
    w_ws, ws = active_set([op], [g], lam=1e-6, occlusion=False, w0=w0, max_active=n0 // 2)
    assert ws["n_active"] <= n0 and ws["warm_start"]["poses"] == n0
    assert set(np.flatnonzero(w_ws)) <= set(np.flatnonzero(w0))


@pytest.mark.parametrize("bad", [0, -3, 2.5, True, "10"])
def test_max_active_is_checked(bad):
    op, _, g = _dense_blur_problem()
    with pytest.raises(ValueError, match="max_active"):
        active_set([op], [g], lam=1e-6, occlusion=False, max_active=bad)


def _nnls_problem(seed: int, n: int = 60, m: int = 400):
    """A least-squares problem whose columns are shifted copies of one smooth signal (the
    pose columns' kind: strongly correlated), its Gram form and scipy's NNLS of it."""
    from scipy.ndimage import gaussian_filter1d
    from scipy.optimize import nnls

    rng = np.random.default_rng(seed)
    f = gaussian_filter1d(rng.standard_normal(m + n), 2.0)
    A = np.stack([f[k : k + m] for k in range(n)], axis=1) + 0.05 * rng.standard_normal((m, n))
    w_true = np.where(rng.random(n) < 0.3, rng.random(n), 0.0)
    y = A @ w_true + 0.05 * rng.standard_normal(m)
    w_ref, _ = nnls(A, y, maxiter=50 * n)
    return A.T @ A, A.T @ y, w_ref


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_nnls_by_exchange_from_any_start_equals_scipys_nnls_of_the_pixels(seed):
    """``solve._nnls_gram`` from a guessed non-zero set (every column, none, a random one,
    the solution's own) returns scipy's NNLS of the least-squares problem itself (pixel
    rows, not the Gram form), as it does without a guess; when the exchange answers, its
    point meets the KKT conditions."""
    from reblur.solve import _nnls_exchange, _nnls_gram

    G, b, w_ref = _nnls_problem(seed)
    n = G.shape[0]
    assert 0 < np.count_nonzero(w_ref) < n
    rng = np.random.default_rng(seed + 10)
    starts = [None, np.ones(n, bool), np.zeros(n, bool), rng.random(n) < 0.5, w_ref > 0]
    scale = np.max(w_ref)
    for start in starts:
        w = _nnls_gram(G, b, start)
        np.testing.assert_allclose(w, w_ref, atol=1e-7 * scale)
    w = _nnls_exchange(G, b, 0.0, np.ones(n, bool))
    assert w is not None
    grad = G @ w - b
    P = w > 0
    assert np.all(np.abs(grad[P]) <= 1e-8 * np.abs(b).max())
    assert np.all(grad[~P] >= 0.0)
    # from the solution's own set: one Cholesky, the same point
    np.testing.assert_allclose(_nnls_exchange(G, b, 0.0, w_ref > 0), w_ref, atol=1e-7 * scale)


def test_nnls_exchange_gives_up_after_its_bound_and_the_nnls_answers(monkeypatch):
    """With one set allowed, a wrong guess (every column, where the solution has zeros) is
    not answered by the exchange; ``_nnls_gram`` then returns scipy's NNLS all the same."""
    import reblur.solve as S

    G, b, w_ref = _nnls_problem(3)
    n = G.shape[0]
    monkeypatch.setattr(S, "_EXCHANGES", 1)
    assert S._nnls_exchange(G, b, 0.0, np.ones(n, bool)) is None
    np.testing.assert_allclose(S._nnls_gram(G, b, np.ones(n, bool)), w_ref,
                               atol=1e-7 * np.max(w_ref))
