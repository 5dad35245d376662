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


# ---------------------------------------------------------------------------- estimate
from reblur.estimate import estimate_motion  # noqa: E402
from reblur.rolling import (  # noqa: E402
    RollingMotion,
    RollingParams,
    RollingPoses,
    choose_shutter,
    readout_fraction,
    reblur_rolling,
    reblur_rolling_tile,
    rolling_windows,
)
from reblur.testbed.rolling import render_rolling_tiled  # noqa: E402
from reblur.tiled import SparsePoses, reblur_tile  # noqa: E402


def test_readout_of_a_constant_velocity_path():
    """Band b's kernel: 8 one-pixel steps starting at tx = b (a path of 8 px per exposure,
    band centres a quarter frame apart, drift 1 px): r = 1 / (1/4 * sqrt(63)) = 0.504."""
    grid = PoseGrid((400, 400), tx=np.arange(0, 12), ty=[0])
    W = np.zeros((4, *grid.shape))
    for b in range(4):
        W[b, 0, 0, b:b + 8] = 1 / 8
    motion = RollingMotion(W, grid, RowBands(400, 4), boxes=[(0, 0, 400, 400)])
    r, info = readout_fraction(motion)
    assert r == pytest.approx(1 / (0.25 * np.sqrt(63)), rel=1e-9)
    still = RollingMotion(np.broadcast_to(W[:1], W.shape), grid, RowBands(400, 4),
                          boxes=[(0, 0, 400, 400)])
    assert readout_fraction(still)[0] == 0.0


def _translation_path(shape, n_exposure, readout, v=(7.0, 2.0)):
    """Homographies of a camera moving at a constant velocity ``v`` px per exposure."""
    n_total = n_exposure + int(np.ceil(readout * n_exposure))
    t = (np.arange(n_total) + 0.5) / n_exposure - (1 + readout) / 2
    return np.stack([np.array([[1, 0, v[0] * s], [0, 1, v[1] * s], [0, 0, 1.0]]) for s in t])


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(11)
    img = cv2.GaussianBlur(rng.random((256, 256)), (0, 0), 1.5)
    return (img - img.min()) / np.ptp(img)


@pytest.mark.parametrize("readout", [0.0, 0.25, 0.5, 1.0])
def test_choice_keeps_the_shutter_that_made_the_pair(scene, readout):
    """The test bed's rolling renderer (bicubic, 64 sub-poses per exposure), a constant
    velocity of (7, 2) px per exposure: auto keeps rolling for r = 0.25, 0.5, 1 and
    estimates r within 0.05 (6 bands), every window and band pair agreeing (quartiles
    within 0.1 of each other); it keeps global for r = 0."""
    hs = _translation_path(scene.shape, 64, readout)
    obs, _ = render_rolling_tiled(scene, hs, readout=readout, n_exposure=64)
    grid = PoseGrid(scene.shape, tx=np.arange(-8, 9), ty=np.arange(-4, 5))
    p = RollingParams(n_bands=6, side=64)
    boxes = rolling_windows(scene.shape, p.n_bands, p.side, p.columns)
    w = estimate_motion(scene, obs, grid, boxes=boxes, lam=1e-3, occlusion=False).weights
    choice = choose_shutter(scene, obs, grid, w_start=w, lam=1e-3, occlusion=False, params=p)
    assert choice.model == ("rolling" if readout else "global"), choice.criterion
    if readout:
        assert abs(choice.rolling.info["readout"] - readout) <= 0.05, choice.rolling.info
        q25, q75 = choice.rolling.info["readout_fit"]["quartiles"]
        assert q25 <= choice.rolling.info["readout"] <= q75
        assert q75 - q25 <= 0.1, choice.rolling.info["readout_fit"]


def test_tiled_reblur_equals_the_operator(scene):
    rng = np.random.default_rng(12)
    grid = PoseGrid(scene.shape, tx=np.arange(-3, 4), ty=np.arange(-2, 3), rz=[-0.5, 0.0, 0.5])
    W = np.zeros((5, *grid.shape))
    for b in range(5):
        W[b].flat[rng.choice(grid.size, 5, replace=False)] = rng.random(5)
    motion = RollingMotion(W, grid, RowBands(256, 5))
    box = (40, 30, 150, 120)
    op = RollingOperator(scene, grid, box, motion.bands)
    got, ok = reblur_rolling_tile(RollingPoses(motion), scene, box)
    m = ok & op.valid
    assert m.mean() > 0.8
    # both warp in float32 onto different windows (OpenCV's coordinates differ by ~1e-6 px)
    np.testing.assert_allclose(got[m], op.matvec(W)[m], atol=1e-5)
    whole, valid = reblur_rolling(scene, motion, tile_size=64)
    np.testing.assert_allclose(whole[40:190, 30:150][m], got[m][:, 0], atol=1e-5)
    same = RollingMotion(np.broadcast_to(W[2], W.shape), grid, RowBands(256, 5))
    a, _ = reblur_rolling_tile(RollingPoses(same), scene, box)
    b, _ = reblur_tile(SparsePoses(W[2], grid), scene, box)
    np.testing.assert_allclose(a, b, atol=1e-6)
    # a local displacement field: the rolling model applies it like the global one
    from reblur.align.field import DisplacementField

    yy, xx = np.mgrid[0:9, 0:9] * 32.0
    fld = DisplacementField(0.0, 0.0, 32.0, np.stack([0.8 + xx / 300, -0.5 + yy / 400], -1))
    a, ok_a = RollingPoses(same, field=fld).reblur_tile(scene, box)
    b, ok_b = reblur_tile(SparsePoses(W[2], grid, field=fld), scene, box)
    np.testing.assert_array_equal(ok_a, ok_b)
    np.testing.assert_allclose(a, b, atol=1e-5)
    plain, _ = reblur_tile(SparsePoses(W[2], grid), scene, box)
    assert np.abs(a - plain)[ok_a].max() > 1e-3  # the field moved it


@pytest.mark.parametrize("n_new", [5, 120])
def test_solver_gram_skips_only_zero_columns(n_new):
    """The solver's Gram products on the band model (blocks cut at the band rows, columns
    that do not reach a block left out) equal the dense products of the explicit columns,
    with an inlier mask and outlier signs, for few and many new columns."""
    from reblur.solve import _gram_add, _Window

    rng = np.random.default_rng(7)
    img, grid = _image(6, channels=2), _grid()
    op = RollingOperator(img, grid, (40, 15, 50, 60), RowBands(SHAPE[0], 6))
    assert len(op.row_breaks) > 2 and op.touch == [1, 2, 3, 4]  # bands 0, 5 out of reach
    g = rng.random(op.dimsd)
    win = _Window(op, g, op.valid, delta=0.05)
    win.inl = op.valid[:, :, None] & (rng.random(op.dimsd) > 0.2)
    win.sgn = np.where(~win.inl & op.valid[:, :, None], rng.choice([-1, 1], op.dimsd),
                       0).astype(np.int8)
    cols = [int(k) for k in rng.choice(op.grid.size, 30 + n_new, replace=False)]
    A = np.stack([np.asarray(op.column(k), float)[op.valid].ravel() for k in cols], axis=1)
    D = win.inl[op.valid].ravel().astype(float)
    s = win.sgn[op.valid].ravel().astype(float)
    gv = g[op.valid].ravel()

    class _One:  # the single-window interface _gram_add drives
        wins = [win]

        def map(self, fn, *seqs):
            return [fn(win, *[q[0] for q in seqs])]

    G, b, d = _gram_add(_One(), cols[:30], cols[30:], A[:, :30].T @ (D[:, None] * A[:, :30]),
                        A[:, :30].T @ (D * gv), A[:, :30].T @ s)
    np.testing.assert_allclose(G, A.T @ (D[:, None] * A), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(b, A.T @ (D * gv), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(d, A.T @ s, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("readout", [0.0, 0.5])
def test_choice_decides_on_central_parts_and_refits_only_a_kept_band_model(scene, readout,
                                                                           monkeypatch):
    """The choice's work, counted in window fits and their pixels: with ``coarse`` both
    models are fitted on the windows' central parts (a fraction of the pixels, the same
    centres); a global-shutter pair (r = 0) then costs no full-window fit at all, a
    rolling one (r = 0.5) one band fit on the full windows instead of the two fits of
    ``coarse=False``.  Both settings keep the same model, and the kept band model reads
    the known readout (within 0.05) either way."""
    import reblur.rolling as R

    hs = _translation_path(scene.shape, 64, readout)
    obs, _ = render_rolling_tiled(scene, hs, readout=readout, n_exposure=64)
    grid = PoseGrid(scene.shape, tx=np.arange(-8, 9), ty=np.arange(-4, 5))
    boxes = rolling_windows(scene.shape, 6, 128, RollingParams().columns)
    full_px = sum(h * w for _, _, h, w in boxes)
    w = estimate_motion(scene, obs, grid, boxes=boxes, lam=1e-3, occlusion=False).weights
    fit = R._fit
    runs = {}
    for coarse in (False, True):
        fits = []

        def counted(ops, gs, bands, *args, fits=fits):
            out = fit(ops, gs, bands, *args)
            fits.append((bands.n_bands, sum(op.box.h * op.box.w for op in ops),
                         [op.box.as_tuple() for op in ops], out[1]["n_outer"]))
            return out

        monkeypatch.setattr(R, "_fit", counted)
        p = RollingParams(n_bands=6, side=128, coarse=coarse)
        runs[coarse] = (choose_shutter(scene, obs, grid, w_start=w, lam=1e-3,
                                       occlusion=False, params=p), fits)
    (full, fits_full), (coarse, fits_coarse) = runs[False], runs[True]
    assert full.model == coarse.model == ("rolling" if readout else "global")
    assert [(b, px) for b, px, _, _ in fits_full] == [(1, full_px), (6, full_px)]
    on_parts = fits_coarse[:2]
    assert [b for b, _, _, _ in on_parts] == [1, 6]
    for _, px, parts, _ in on_parts:
        assert px <= full_px / 2
        centres = [(y + h / 2, x + w / 2) for y, x, h, w in parts]
        np.testing.assert_allclose(centres, [(y + h / 2, x + w / 2) for y, x, h, w in boxes],
                                   atol=1.0)
    if readout:
        assert [(b, px) for b, px, _, _ in fits_coarse[2:]] == [(6, full_px)]
        for choice in (full, coarse):
            assert abs(choice.rolling.info["readout"] - readout) <= 0.05
        assert [f["n_outer"] for f in coarse.criterion["fits"]] == [f[3] for f in fits_coarse]
    else:
        assert len(fits_coarse) == 2


def test_field_measured_through_the_band_model(scene):
    """A pair rendered with a band model whose bands drift 2 px apart (top to bottom):
    measured through the global model of the mean weights, the tie points see the rows'
    shear (and a field is fitted to it); measured through the band model itself
    (``reblur.tiled.reblur_tile`` of :class:`RollingPoses`, as the pipeline does when it
    keeps the band model), they see nothing to correct."""
    from reblur.align.field import estimate_field

    grid = PoseGrid(scene.shape, tx=np.arange(-4, 5), ty=[0])
    W = np.zeros((4, *grid.shape))
    for b in range(4):  # a 3 px box whose start moves 2/3 px per band (2 px in all)
        W[b, 0, 0, 2:5] = 1 / 3 * (1 - b / 3)
        W[b, 0, 0, 4:7] += 1 / 3 * (b / 3)
    motion = RollingMotion(W, grid, RowBands(256, 4))
    obs, _ = reblur_rolling(scene, motion)
    poses = RollingPoses(motion)
    box = (30, 40, 100, 90)
    np.testing.assert_array_equal(reblur_tile(poses, scene, box)[0],
                                  reblur_rolling_tile(poses, scene, box)[0])
    through_bands = estimate_field(scene, obs, poses).info
    through_mean = estimate_field(scene, obs, SparsePoses(W.mean(axis=0), grid)).info
    assert through_bands["rms_before_px"] < 0.05, through_bands
    assert not through_bands["applied"]
    assert through_mean["rms_before_px"] > 0.3, through_mean
    assert through_mean["applied"]


def test_windows_spread_across_the_width():
    """Three columns: left edge, centre, right edge per band; two: the edges only (the
    first layout, written out here); one: centred; invalid counts raise."""
    H, W, side = 300, 640, 100
    bands = RowBands(H, 3)
    rows = [int(np.clip(round(c - side / 2), 0, H - side)) for c in bands.centres]
    three = rolling_windows((H, W), 3, side, 3)
    assert three == [(y, x, side, side) for y in rows for x in (20, 270, 520)]
    assert rolling_windows((H, W), 3, side) == three
    assert rolling_windows((H, W), 3, side, 2) == [(y, x, side, side) for y in rows
                                                 for x in (20, 520)]
    assert rolling_windows((H, W), 3, side, 1) == [(y, 270, side, side) for y in rows]
    five = rolling_windows((H, W), 3, side, 5)
    assert sorted({x for _, x, _, _ in five}) == [20, 145, 270, 395, 520]
    # narrower than two windows: the three overlap (150 // 32 = 4 px from the edges)
    assert sorted({x for _, x, _, _ in rolling_windows((H, 150), 3, 100, 3)}) == [4, 25, 46]
    # narrower than one window: one full-width window per band, kept once
    assert rolling_windows((H, 90), 3, 100, 3) == [(y, 0, 100, 90) for y in rows]
    with pytest.raises(ValueError, match="columns"):
        rolling_windows((H, W), 3, side, 0)
    with pytest.raises(ValueError, match="columns"):
        RollingParams(columns=0)


def _roll_pair(readout, deg, noise, seed=0, shape=(128, 512)):
    """A rolling-shutter pair of a roll about the image centre at ``deg`` degrees per
    exposure (64 sub-poses each), rendered by the test bed, with Gaussian noise."""
    from reblur.grid import pose_homography

    H, W = shape
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random((H, W)), (0, 0), 1.5)
    scene = (img - img.min()) / np.ptp(img)
    n = 64
    t = (np.arange(n + int(np.ceil(readout * n))) + 0.5) / n - (1 + readout) / 2
    centre = ((W - 1) / 2, (H - 1) / 2)
    hs = np.stack([pose_homography(0.0, 0.0, 0.0, 0.0, 0.0, deg * s, center=centre)
                   for s in t])
    clean, ok = render_rolling_tiled(scene, hs, readout=readout, n_exposure=n)
    obs = clean + np.random.default_rng(seed + 1).normal(0.0, noise, clean.shape)
    return scene, obs, ok


@pytest.mark.parametrize("readout", [0.5, 1.0])
def test_band_kernels_right_across_the_width_under_a_strong_roll(readout):
    """A roll of 6 degrees per exposure about the centre of a 128 x 512 frame: under a
    rolling shutter the bands' kernels are arcs whose vertical extent grows with the
    distance from the centre column.  Seen at the two edge windows only, a band's weight
    over (ty, rz) is known through two projections (``ty +- rz dx``), which leave the
    centre's (``ty`` alone) free.  Fitted on three columns, the reblurred reference
    explains the centre strip between the edge windows down to the noise ``sigma``
    (RMS residual <= 1.25 sigma, i.e. a model error <= 0.75 sigma: 1.06 / 1.13 sigma at
    r = 0.5 / 1); on the edges alone it does not (1.33 / 1.61 sigma, model errors of
    0.9 / 1.3 sigma)."""
    sigma = 0.01
    scene, obs, ok = _roll_pair(readout, 6.0, sigma)
    H, W = scene.shape
    side = 64
    grid = PoseGrid(scene.shape, tx=np.arange(-3, 4), ty=np.arange(-3, 4),
                    rz=np.round(np.arange(-6.0, 6.01, 0.25), 3))
    w = estimate_motion(scene, obs, grid, boxes=rolling_windows(scene.shape, 6, side),
                        lam=1e-3, occlusion=False).weights
    strip = np.zeros((H, W), bool)  # between the edge windows: x in [W/32 + side, ...)
    strip[:, W // 32 + side:W - side - W // 32] = True
    rms = {}
    for columns in (3, 2):
        p = RollingParams(n_bands=6, side=side, columns=columns)
        choice = choose_shutter(scene, obs, grid, w_start=w, lam=1e-3, occlusion=False,
                                params=p)
        assert choice.model == "rolling", choice.criterion
        assert len({x for _, x, _, _ in choice.rolling.boxes}) == columns
        reblurred, valid = reblur_rolling(scene, choice.rolling)
        m = strip & valid & ok
        assert m.sum() > 0.8 * strip.sum()
        rms[columns] = float(np.sqrt(np.mean((reblurred - obs)[m] ** 2)))
    assert rms[3] <= 1.25 * sigma, rms
    assert rms[2] > 1.25 * sigma, rms  # the edges alone: the bound can fail


def test_band_model_dropped_when_the_full_window_refit_reads_no_readout(scene, monkeypatch):
    """The parts keep the band model (r = 0.5), and the full-window refit reads a readout
    below ``min_readout`` (forced here through readout_fraction on the full windows): the
    choice falls back to the global model and records it."""
    import reblur.rolling as R

    hs = _translation_path(scene.shape, 64, 0.5)
    obs, _ = render_rolling_tiled(scene, hs, readout=0.5, n_exposure=64)
    grid = PoseGrid(scene.shape, tx=np.arange(-8, 9), ty=np.arange(-4, 5))
    p = RollingParams(n_bands=6, side=128)
    boxes = rolling_windows(scene.shape, p.n_bands, p.side, p.columns)
    w = estimate_motion(scene, obs, grid, boxes=boxes, lam=1e-3, occlusion=False).weights
    kept = choose_shutter(scene, obs, grid, w_start=w, lam=1e-3, occlusion=False, params=p)
    assert kept.model == "rolling" and not kept.criterion["refit_rejected"]
    assert kept.criterion["readout_final"] >= p.min_readout
    fraction = R.readout_fraction

    def none_on_full_windows(motion):
        r, info = fraction(motion)
        full = all(h == p.side for _, _, h, _ in motion.boxes)
        return (0.5 * p.min_readout if full else r), info

    monkeypatch.setattr(R, "readout_fraction", none_on_full_windows)
    dropped = choose_shutter(scene, obs, grid, w_start=w, lam=1e-3, occlusion=False,
                             params=p)
    assert dropped.model == "global", dropped.criterion
    assert dropped.criterion["refit_rejected"]
    assert dropped.criterion["readout"] >= p.min_readout  # the parts kept it
    assert dropped.criterion["readout_final"] == 0.5 * p.min_readout
    assert "refit" in dropped.criterion["rule"]
    assert dropped.motion is dropped.global_


def test_refit_on_the_band_mean_keeps_the_choice_and_reports_per_band(scene):
    """An RGB rolling pair (r = 0.5, three differently textured bands): with
    ``bands="mean"`` the full-window band refit is solved on the band mean (its operators
    one band), the choice and the readout are those of the refit on every band (within
    0.05 of the truth), and its change term and fit are per band: each window's PSNR is
    that of the colour residual of the weights found, computed here with fresh RGB band
    operators."""
    import reblur.rolling as R

    rgb = np.stack([scene, np.rot90(scene), scene[::-1]], axis=2)
    hs = _translation_path(scene.shape, 64, 0.5)
    obs, _ = render_rolling_tiled(rgb, hs, readout=0.5, n_exposure=64)
    grid = PoseGrid(scene.shape, tx=np.arange(-8, 9), ty=np.arange(-4, 5))
    p = RollingParams(n_bands=6, side=128)  # the choice on 64 px parts, then the refit
    boxes = rolling_windows(scene.shape, p.n_bands, p.side, p.columns)
    w = estimate_motion(rgb, obs, grid, boxes=boxes, lam=1e-3, occlusion=False,
                        bands="mean").weights
    fit = R._fit
    seen = []

    def recorded(ops, gs, bands, *args):
        seen.append((bands.n_bands, ops[0].dimsd[2]))
        return fit(ops, gs, bands, *args)

    choices = {}
    for bands in ("all", "mean"):
        seen.clear()
        R._fit = recorded
        try:
            choices[bands] = choose_shutter(rgb, obs, grid, w_start=w, lam=1e-3,
                                            occlusion=False, params=p, bands=bands)
        finally:
            R._fit = fit
        # the choice on the parts in RGB either way; the refit on the bands or their mean
        assert seen == [(1, 3), (6, 3), (6, 3 if bands == "all" else 1)]
    for choice in choices.values():
        assert choice.model == "rolling"
        assert abs(choice.rolling.info["readout"] - 0.5) <= 0.05, choice.rolling.info
    roll = choices["mean"].rolling
    assert roll.info["bands"] == "mean" and choices["all"].rolling.info["bands"] == "all"
    many = RowBands(scene.shape[0], p.n_bands)
    for box, chi, got in zip(roll.boxes, roll.chi, roll.info["psnr"], strict=True):
        op = RollingOperator(rgb, roll.grid, box, many)
        y, x, h, wd = box
        r = obs[y : y + h, x : x + wd] - op.matvec(roll.weights)
        assert chi.shape == (h, wd, 3)
        assert got == pytest.approx(10 * np.log10(1 / np.mean(r[op.valid] ** 2)), abs=1e-6)
