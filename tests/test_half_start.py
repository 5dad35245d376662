"""The first coarse-to-fine level at half resolution (``estimate.HALF_START``, issue #28).

A wide blur's first level is solved on 2 x 2 block means of the windows' central parts,
with half the translations each way; its weights start the full-resolution levels.  The
checks here: the block means against an explicit loop, the half-resolution poses against
the full-resolution ones conjugated by the pixel map, the half-resolution model against
an explicitly warped and block-averaged blur, the carrying of the weights, and an
estimate that ends on the same weights as one started at full resolution.
"""

import cv2
import numpy as np
import pytest

from reblur import PoseGrid, estimate_motion
from reblur import estimate as est_mod
from reblur.estimate import _HALF, _full_weights, _half_grid, _Halved
from reblur.operator import BlurOperator
from reblur.warp import Box, read_window


def _block_means(a: np.ndarray) -> np.ndarray:
    """2 x 2 block means by an explicit loop, an odd last row / column repeated."""
    H, W = a.shape[:2]
    out = np.zeros(((H + 1) // 2, (W + 1) // 2, *a.shape[2:]))
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            ys = [min(2 * i, H - 1), min(2 * i + 1, H - 1)]
            xs = [min(2 * j, W - 1), min(2 * j + 1, W - 1)]
            out[i, j] = sum(a[y, x] for y in ys for x in xs) / 4.0
    return out


@pytest.mark.parametrize("shape", [(8, 10), (7, 9), (7, 9, 3)])
def test_halved_windows_are_the_block_means(shape):
    rng = np.random.default_rng(0)
    a = rng.random(shape).astype(np.float32)
    h = _Halved(a)
    want = _block_means(a.astype(np.float64))
    assert h.shape == want.shape
    for box in [Box(0, 0, *want.shape[:2]), Box(1, 2, 2, 3), Box(-2, -1, 4, 9)]:
        got = read_window(h, box, np.float64)
        exp = read_window(want, box, np.float64)
        np.testing.assert_allclose(got, exp, rtol=0, atol=1e-6)
    # no data stays no data
    a[3, 4] = np.nan
    assert np.isnan(_Halved(a)[1:2, 2:3]).all()


def test_halved_exclude_is_any_of_the_four_pixels():
    a = np.zeros((9, 9), np.float32)
    mask = np.zeros((20, 20), bool)
    mask[3, 6] = True  # full pixel (3, 6): half pixel (1, 3)

    class WithExclude:
        shape, dtype = a.shape, a.dtype

        def __getitem__(self, key):
            return a[key]

        def exclude(self, box):
            return mask[box.y0:box.y1, box.x0:box.x1]

    ex = _Halved(WithExclude()).exclude(Box(0, 1, 4, 4))
    want = np.zeros((4, 4), bool)
    want[1, 2] = True  # half column 3 is column 2 of a box starting at 1
    np.testing.assert_array_equal(ex, want)


def test_half_grid_poses_are_the_full_ones_in_half_pixels():
    grid = PoseGrid((301, 400), tx=range(-17, 18), ty=range(-12, 13), rz=[-1.5, 0.0, 0.75])
    half = _half_grid(grid, [0, 2])
    assert half.tx == tuple(float(v) for v in range(-8, 9))
    assert half.ty == tuple(float(v) for v in range(-6, 7))
    assert half.rz == (-1.5, 0.75)
    assert half.image_shape == (151, 200)
    S = _HALF
    for b_half, b in enumerate([0, 2]):
        for iy, ty in enumerate(half.ty):
            for ix, tx in enumerate(half.tx):
                full = grid.homography((b, grid.ty.index(2 * ty), grid.tx.index(2 * tx)))
                np.testing.assert_allclose(half.homography((b_half, iy, ix)),
                                           S @ full @ np.linalg.inv(S), atol=1e-9)


def _explicit_blur(ref, grid, base, w):
    """sum_k w_k warp(ref, H_k base), pose by pose (OpenCV bilinear, float64)."""
    H, W = ref.shape
    out = np.zeros((H, W))
    for b, iy, ix, wk in grid.nonzero(w):
        M = grid.homography((b, iy, ix)) @ base
        out += wk * cv2.warpPerspective(ref, M, (W, H), flags=cv2.INTER_LINEAR)
    return out


def test_the_half_resolution_model_predicts_the_block_means_of_the_blur():
    rng = np.random.default_rng(1)
    ref = cv2.GaussianBlur(rng.random((420, 460)), (0, 0), 3.0)
    ref = (ref - ref.min()) / (ref.max() - ref.min())
    grid = PoseGrid(ref.shape, tx=range(-10, 11), ty=range(-10, 11), rz=[-0.6, 0.0, 0.6])
    base = np.array([[1.002, 0.001, 3.3], [-0.002, 0.999, -2.1], [0.0, 0.0, 1.0]])
    w = np.zeros(grid.shape)  # poses at even translations: the half grid holds them
    for (b, ty, tx), wk in {(0, -8, 6): 0.3, (1, 0, 0): 0.2, (1, 2, -4): 0.25,
                            (2, 10, 8): 0.25}.items():
        w[b, grid.ty.index(ty), grid.tx.index(tx)] = wk
    obs_half = _block_means(_explicit_blur(ref, grid, base, w))
    box = Box(40, 50, 120, 130)

    half = _half_grid(grid, range(grid.n_bases))
    op = BlurOperator(_Halved(ref), half, box, base=_HALF @ base @ np.linalg.inv(_HALF),
                      engine="fast")
    pred = op.matvec(_full_to_half(w, grid, half))[:, :, 0]
    want = obs_half[box.y0:box.y1, box.x0:box.x1]
    m = op.valid
    err = np.sqrt(np.mean((pred - want)[m] ** 2))
    # against the data's own scale: the blur one half-resolution pixel off
    off = obs_half[box.y0 + 1:box.y1 + 1, box.x0:box.x1]
    assert err < 0.004  # the texture's standard deviation is 0.11
    assert err < 0.15 * np.sqrt(np.mean((pred - off)[m] ** 2))


def _full_to_half(w, grid, half):
    """The half grid's weights of full-grid weights at even translations."""
    out = np.zeros(half.shape)
    for b, iy, ix, wk in grid.nonzero(w):
        out[b, half.ty.index(grid.ty[iy] / 2), half.tx.index(grid.tx[ix] / 2)] = wk
    return out


def test_full_weights_go_to_twice_the_translation_or_the_nearest():
    grid = PoseGrid((100, 100), tx=range(-5, 6), ty=range(-3, 4), rz=[-1.0, 0.0, 1.0])
    half = PoseGrid((50, 50), tx=range(-3, 4), ty=range(-2, 3), rz=[-1.0, 1.0])
    w_h = np.zeros(half.shape)
    w_h[0, half.ty.index(1), half.tx.index(-2)] = 0.5  # -> (ty 2, tx -4) at angle 0
    w_h[1, half.ty.index(-2), half.tx.index(3)] = 0.3  # -> (-4, 6): nearest (-3, 5)
    w_h[1, half.ty.index(2), half.tx.index(3)] = 0.2   # -> (4, 6): nearest (3, 5)
    out = _full_weights(w_h, half, grid, [0, 2])
    want = np.zeros(grid.shape)
    want[0, grid.ty.index(2), grid.tx.index(-4)] = 0.5
    want[2, grid.ty.index(-3), grid.tx.index(5)] = 0.3
    want[2, grid.ty.index(3), grid.tx.index(5)] = 0.2
    np.testing.assert_array_equal(out, want)


M = 40  # margin of the texture around the reference
TRUE = {(18.0, 0.0): 0.5, (-14.0, 10.0): 0.3, (-3.0, -7.0): 0.2}  # (tx, ty) -> weight


@pytest.fixture(scope="module")
def wide_pair():
    """Integer shifts of a texture: the true weights are known exactly."""
    rng = np.random.default_rng(3)
    big = cv2.GaussianBlur(rng.random((560, 560)).astype(np.float32), (0, 0), 1.5)
    big = ((big - big.min()) / (big.max() - big.min())).astype(np.float64)
    ref = big[M:-M, M:-M]
    H, W = ref.shape

    def shifted(tx, ty):  # a pose (tx, ty) maps reference pixel x to x + t
        return big[M - int(ty): M - int(ty) + H, M - int(tx): M - int(tx) + W]

    return ref, sum(w * shifted(tx, ty) for (tx, ty), w in TRUE.items())


def _by_translation(est) -> dict:
    w = est.weights.sum(axis=0)
    return {(est.grid.tx[j], est.grid.ty[i]): float(w[i, j]) for i, j in np.argwhere(w > 0.01)}


def _estimate(pair, monkeypatch, on: bool, t: int = 24, **kw):
    ref, obs = pair
    monkeypatch.setattr(est_mod, "HALF_START", on)
    grid = PoseGrid(ref.shape, tx=range(-t, t + 1), ty=range(-t, t + 1),
                    rz=np.linspace(-0.5, 0.5, 21))
    kw = {"occlusion": False, "lam": 1e-4, **kw}
    return estimate_motion(ref, obs, grid, boxes=[(60, 60, 360, 360)], **kw)


def test_a_half_resolution_start_ends_on_the_full_resolution_weights(wide_pair, monkeypatch):
    on = _estimate(wide_pair, monkeypatch, True)
    off = _estimate(wide_pair, monkeypatch, False)
    first = on.info["levels"][0]
    assert first["resolution"] == 0.5 and first["t_max"] == 24.0 and first["side"] == 128
    assert all("resolution" not in lv for lv in on.info["levels"][1:])
    assert all("resolution" not in lv for lv in off.info["levels"])
    for est in (on, off):
        got = _by_translation(est)
        assert set(got) == set(TRUE)
        for t, wk in TRUE.items():
            assert got[t] == pytest.approx(wk, abs=0.02)
    assert on.info["psnr"][0] == pytest.approx(off.info["psnr"][0], abs=0.5)
    assert on.info["psnr"][0] > 50


def test_a_half_resolution_start_widens_in_full_resolution_pixels(wide_pair, monkeypatch):
    on = _estimate(wide_pair, monkeypatch, True, t=16, t_grow=2)
    checks = on.info["translations"]["checks"]
    assert [c["t_max"] for c in checks] == [16.0, 32.0]
    assert [c["outcome"] for c in checks] == ["widened", "clear"]
    assert all(c["resolution"] == 0.5 for c in checks)
    assert on.grid.tx[-1] == 32.0
    got = _by_translation(on)
    assert got[(18.0, 0.0)] == pytest.approx(0.5, abs=0.02)


def test_a_narrow_grid_starts_at_full_resolution(wide_pair, monkeypatch):
    """Below HALF_MIN_T the estimate is the one without the half-resolution start."""
    on = _estimate(wide_pair, monkeypatch, True, t=4)
    off = _estimate(wide_pair, monkeypatch, False, t=4)
    assert est_mod.HALF_MIN_T > 4
    assert all("resolution" not in lv for lv in on.info["levels"])
    np.testing.assert_array_equal(on.weights, off.weights)


def test_a_changed_half_resolution_level_stops_and_resumes(wide_pair, monkeypatch):
    """A half-resolution first level past stop_occluded stops the estimate there (the
    paper's rejection), with the full-resolution parts as its windows; resumed, it ends
    where an estimate that never stopped does, in as many outer iterations."""
    ref, _ = wide_pair
    other = np.random.default_rng(9).random(ref.shape)
    kw = dict(occlusion=True, lam=0.1, max_outer=8)
    stopped = _estimate((ref, other), monkeypatch, True, stop_occluded=0.5, **kw)
    assert stopped.info["stopped_early"]
    assert [lv.get("resolution") for lv in stopped.info["levels"]] == [0.5]
    assert stopped.boxes == [(112, 112, 256, 256)]
    assert stopped.chi[0].shape == (256, 256)
    assert stopped.info["occluded"][0] > 0.5
    resumed = _estimate((ref, other), monkeypatch, True, resume=stopped.info["resume"], **kw)
    whole = _estimate((ref, other), monkeypatch, True, **kw)
    np.testing.assert_allclose(resumed.weights, whole.weights, rtol=1e-9, atol=1e-12)
    assert stopped.info["n_outer"] + resumed.info["n_outer"] == whole.info["n_outer"]


def test_a_half_resolution_level_weighs_its_pixels_as_four(wide_pair, monkeypatch):
    """Each block mean stands for four pixels (``active_set(pixel_weight=4)``): the l1 term
    keeps its full-resolution weight against the data term.  On a dim pair (intensities
    within 0.01, where that term matters) the half-resolution level widens the grid as the
    full-resolution one does; weighted as one pixel each, its gain was 0.025 (< 5 %), the
    grid stayed at +-16 px and the fit lost 15 dB."""
    ref, obs = wide_pair
    kw = dict(occlusion=True, lam=0.1, t_grow=2, scale=1.0)
    on = _estimate((0.01 * ref, 0.01 * obs), monkeypatch, True, t=16, **kw)
    off = _estimate((0.01 * ref, 0.01 * obs), monkeypatch, False, t=16, **kw)
    for est in (on, off):
        assert [c["outcome"] for c in est.info["translations"]["checks"]] == ["widened",
                                                                              "clear"]
    assert on.info["levels"][0]["resolution"] == 0.5
    gains = [est.info["translations"]["checks"][0]["gain"] for est in (on, off)]
    assert gains[0] == pytest.approx(gains[1], rel=0.3)
    assert on.info["psnr"][0] == pytest.approx(off.info["psnr"][0], abs=0.5)
