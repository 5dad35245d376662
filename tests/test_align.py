"""Tests for reblur.align: coarse alignment of a blurred observation from another viewpoint.

Observations are made from real 1024x1024 LEVIR / WHU-CD images: the reference is warped by a
known viewpoint homography (translation up to 5 % of the width, roll up to 5 degrees, a little
perspective, about the image centre) and blurred by camera shake (the mean of 30 warps along
a smooth random path of up to +-8 px and +-1 degree about the centre).  The blurred image is
centred on the mean pose of the path, so the truth is the mean pose's homography composed
with the viewpoint warp.
"""

from __future__ import annotations

import json
import re

import cv2
import numpy as np
import pytest
import zarr
from conftest import LEVIR, WHU

from reblur import align as align_mod
from reblur.align import (
    Alignment,
    AlignmentError,
    AlignParams,
    coarse_align,
    overview,
    overview_matrix,
)
from reblur.align import coarse as coarse_mod
from reblur.align import overviews as overviews_mod
from reblur.align.verify import check_plausible
from reblur.grid import map_points, pose_homography, translation
from reblur.warp import Box, warp_window

SIZE = 1024
CENTER = ((SIZE - 1) / 2.0, (SIZE - 1) / 2.0)


def _read(path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, f"real test imagery missing: {path}"
    return (cv2.cvtColor(img, cv2.COLOR_BGR2RGB) / 255.0).astype(np.float32)


def _smooth_walk(rng: np.random.Generator, n: int) -> np.ndarray:
    """A smooth random walk of ``n`` samples scaled to [-1, 1]."""
    v = np.cumsum(rng.normal(size=n + 6))
    v = np.convolve(v, np.ones(7) / 7.0, mode="valid")[:n]
    v -= (v.max() + v.min()) / 2.0
    return v / np.abs(v).max()


def _viewpoint(rng: np.random.Generator, t_frac=0.05, rot=5.0, persp=1e-5) -> np.ndarray:
    tx, ty = rng.uniform(-t_frac, t_frac, 2) * SIZE
    Hv = pose_homography(tx, ty, rz=rng.uniform(-rot, rot), center=CENTER)
    P = np.eye(3)
    P[2, :2] = rng.uniform(-persp, persp, 2)
    Hv = Hv @ translation(*CENTER) @ P @ translation(-CENTER[0], -CENTER[1])
    return Hv / Hv[2, 2]


def _observe(source, Hv, rng, *, n=30, shake=8.0, roll=1.0):
    """Blur ``source`` warped by ``Hv`` along a random shake path; return (obs, H_true)."""
    px, py, pr = shake * _smooth_walk(rng, n), shake * _smooth_walk(rng, n), roll * _smooth_walk(
        rng, n
    )
    acc = np.zeros(source.shape[:2] + (source.shape[2],), np.float32)
    for a, b, r in zip(px, py, pr, strict=True):
        out, _ = warp_window(source, pose_homography(a, b, rz=r, center=CENTER) @ Hv,
                             Box(0, 0, SIZE, SIZE))
        acc += out
    H_true = pose_homography(px.mean(), py.mean(), rz=pr.mean(), center=CENTER) @ Hv
    return acc / n, H_true / H_true[2, 2]


def _corners(shape) -> np.ndarray:
    h, w = shape[:2]
    return np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)


def _ref_corner_error(H, H_true, ref_shape) -> float:
    """Largest distance between where ``H`` and ``H_true`` send the reference corners."""
    c = _corners(ref_shape)
    return float(np.hypot(*(map_points(H, c) - map_points(H_true, c)).T).max())


def _obs_corner_error(H, H_true, obs_shape) -> float:
    """Largest misalignment, in observation pixels, at the observation's corners."""
    c = _corners(obs_shape)
    return float(np.hypot(*(map_points(H @ np.linalg.inv(H_true), c) - c).T).max())


IMAGES = {
    "levir_test_7": LEVIR / "A" / "test_7.png",
    "levir_test_102": LEVIR / "A" / "test_102.png",
    "whu_000121": WHU / "prev" / "000121.png",
}


@pytest.fixture(scope="module")
def scenes():
    """name -> (reference, blurred observation, true homography), made once."""
    out = {}
    for i, (name, path) in enumerate(IMAGES.items()):
        rng = np.random.default_rng(100 + i)
        ref = _read(path)
        obs, H_true = _observe(ref, _viewpoint(rng), rng)
        out[name] = (ref, obs, H_true)
    return out


@pytest.fixture(scope="module")
def scene(scenes):
    return scenes["levir_test_7"]


@pytest.fixture(scope="module")
def aligned(scene) -> Alignment:
    ref, obs, _ = scene
    return coarse_align(ref, obs)


# ---------------------------------------------------------------------------- overview
class _Recorder:
    """Array-like that records the row ranges read."""

    def __init__(self, a):
        self.a, self.reads = a, []
        self.shape, self.dtype = a.shape, a.dtype

    def __getitem__(self, key):
        self.reads.append(key[0])
        return self.a[key]


def test_overview_block_mean_in_strips(monkeypatch):
    rng = np.random.default_rng(0)
    a = rng.integers(0, 65536, size=(37, 53, 3), dtype=np.uint16)
    rec = _Recorder(a)
    monkeypatch.setattr(overviews_mod, "_STRIP_BYTES", 6 * 48 * 3 * 4 * 2)  # two block rows
    small, scale = overview(rec, max_side=10)
    k = 6  # ceil(53 / 10)
    assert scale == pytest.approx(1 / k)
    assert small.shape == (37 // k, 53 // k) and small.dtype == np.float32
    want = (a[:36, :48].astype(np.float64).mean(axis=2) / 65535.0)
    want = want.reshape(6, k, 8, k).mean(axis=(1, 3))
    np.testing.assert_allclose(small, want, atol=1e-6)
    # read strip by strip, never the whole image
    assert len(rec.reads) == 3
    assert all(s.stop - s.start <= 2 * k for s in rec.reads)


def test_overview_float_gray_and_nan():
    a = np.full((40, 40), 0.25, np.float32)
    a[0, 0] = np.nan
    small, scale = overview(a, max_side=20)
    assert scale == 0.5 and small.shape == (20, 20)
    assert np.isfinite(small).all()
    assert small[0, 0] == pytest.approx(0.75 * 0.25)
    assert small[5, 5] == pytest.approx(0.25)
    full, s1 = overview(a[..., None].repeat(3, axis=2), max_side=64)
    assert s1 == 1.0 and full.shape == (40, 40)


def test_overview_matrix_pixel_centres():
    A = overview_matrix(0.25)
    # overview pixel 0 averages full pixels 0..3: its centre is 1.5
    np.testing.assert_allclose(map_points(A, [[0, 0], [2, 1]]), [[1.5, 1.5], [9.5, 5.5]])
    np.testing.assert_allclose(overview_matrix(1.0), np.eye(3))


# ---------------------------------------------------------------------------- accuracy
@pytest.mark.parametrize("name", list(IMAGES))
def test_recovers_viewpoint_under_camera_shake(scenes, name):
    ref, obs, H_true = scenes[name]
    a = coarse_align(ref, obs)
    ref_err = _ref_corner_error(a.H, H_true, ref.shape)
    obs_err = _obs_corner_error(a.H, H_true, obs.shape)
    # the fine pose grid absorbs +-12 px; the blur-aware polish lands within a pixel
    assert ref_err <= 2.0, (ref_err, a)
    assert obs_err <= 2.0, (obs_err, a)
    assert a.H.shape == (3, 3) and a.H.dtype == np.float64 and a.H[2, 2] == 1.0
    assert a.method.endswith("kernel") and a.scale == 1.0
    assert a.n_regions >= 16 and a.overlap > 0.8
    assert a.ecc is not None and a.ecc > 0.8
    d = json.loads(json.dumps(a.to_dict()))
    np.testing.assert_allclose(d["H"], a.H)
    assert d["method"] == a.method and d["n_regions"] == a.n_regions


def test_low_resolution_working_scale(scene):
    """max_side=256 works on a 1/4 overview: the pixel-centre conversion must be exact."""
    ref, obs, H_true = scene
    a = coarse_align(ref, obs, AlignParams(max_side=256))
    assert a.scale == 0.25
    assert _ref_corner_error(a.H, H_true, ref.shape) <= 2.0


def test_without_polish_is_only_coarse(scene):
    """A correlation/feature optimum sits near a mode of the blur, not at its mean."""
    ref, obs, H_true = scene
    a = coarse_align(ref, obs, AlignParams(polish=False))
    assert "kernel" not in a.method and a.n_regions == 0
    assert a.residual_px is not None and np.isfinite(a.residual_px)
    assert _obs_corner_error(a.H, H_true, obs.shape) <= 25.0


def test_phase_correlation_path(scene):
    ref, obs, H_true = scene
    a = coarse_align(ref, obs, AlignParams(method="ecc"))
    assert a.method == "phase+ecc+kernel"
    assert a.n_matches == 0 and a.residual_px is None
    assert _obs_corner_error(a.H, H_true, obs.shape) <= 2.0


def test_ecc_refines_finer_levels_in_few_iterations(scene, monkeypatch):
    """Coarse to fine, the first level runs all ``ecc_iterations`` and the finer ones at
    most ``REFINE_ITERATIONS``; on a shaken same-scene pair that leaves the estimate where
    the uncapped refinement puts it (within 0.05 px of the finest level)."""
    from reblur.align import ecc as ecc_mod

    ref, obs, _ = scene
    params = AlignParams()
    prep = coarse_mod._prepare(ref, obs, params, None)
    top = len(prep.levels) - 1
    H0 = ecc_mod.phase_init(prep.levels[top])
    used = []
    level = ecc_mod._ecc_level

    def counting(lv, H, motion, sigma, iterations, eps):
        used.append(iterations)
        return level(lv, H, motion, sigma, iterations, eps)

    monkeypatch.setattr(ecc_mod, "_ecc_level", counting)
    H, _, _ = ecc_mod.ecc_refine(prep.levels, H0, top, 0, prep.ref_shape, params,
                                 max_jump=0.25)
    assert len(used) == top + 1 and used[0] == params.ecc_iterations
    assert max(used[1:]) == ecc_mod.REFINE_ITERATIONS < params.ecc_iterations
    monkeypatch.setattr(ecc_mod, "REFINE_ITERATIONS", params.ecc_iterations)
    H_full, _, _ = ecc_mod.ecc_refine(prep.levels, H0, top, 0, prep.ref_shape, params,
                                      max_jump=0.25)
    assert _ref_corner_error(H, H_full, prep.ref_shape) * prep.levels[0].scale <= 0.05


def test_tolerant_ecc_gives_the_levels_after_a_failed_one_a_refinements_budget(
        scene, monkeypatch):
    """From a trusted start (``tolerant``), a first level that fails is skipped and the
    finer levels run at most ``REFINE_ITERATIONS`` (the failed one spent the whole budget
    from that start); without ``tolerant`` the failure ends the refinement."""
    from reblur.align import ecc as ecc_mod

    ref, obs, H_true = scene
    params = AlignParams()
    prep = coarse_mod._prepare(ref, obs, params, None)
    top = len(prep.levels) - 1
    assert top >= 2
    used = []
    level = ecc_mod._ecc_level

    def first_fails(lv, H, motion, sigma, iterations, eps):
        used.append(iterations)
        if len(used) == 1:  # the first level, as an ECC that does not converge
            raise cv2.error("no convergence")
        return level(lv, H, motion, sigma, iterations, eps)

    monkeypatch.setattr(ecc_mod, "_ecc_level", first_fails)
    H, rho, scale = ecc_mod.ecc_refine(prep.levels, H_true, top, 0, prep.ref_shape, params,
                                       max_jump=0.05, tolerant=True)
    assert used == [params.ecc_iterations] + [ecc_mod.REFINE_ITERATIONS] * top
    assert ecc_mod.REFINE_ITERATIONS < params.ecc_iterations
    assert scale == prep.levels[0].scale and rho > 0.5
    # on a pair that correlates, where the uncapped levels put it
    monkeypatch.setattr(ecc_mod, "REFINE_ITERATIONS", params.ecc_iterations)
    used.clear()
    H_full, _, _ = ecc_mod.ecc_refine(prep.levels, H_true, top, 0, prep.ref_shape, params,
                                      max_jump=0.05, tolerant=True)
    assert used == [params.ecc_iterations] * (top + 1)
    assert _ref_corner_error(H, H_full, prep.ref_shape) * prep.levels[0].scale <= 0.05
    used.clear()
    with pytest.raises(AlignmentError, match="ECC did not converge"):
        ecc_mod.ecc_refine(prep.levels, H_true, top, 0, prep.ref_shape, params,
                           max_jump=0.05)
    assert used == [params.ecc_iterations]


def _slow_block_match(level, H, *, block, search, step, sigma):
    """The gradient blocks' matching, block by block (the reference for ``_block_match``)."""
    from reblur.align import blocks as blocks_mod
    from reblur.align.overviews import to_level

    h, w = level.obs.shape
    warped, cover = level.warped_reference(to_level(H, level.scale))
    fr = blocks_mod._grad_field(warped, cover, sigma)
    fo = blocks_mod._grad_field(level.obs, level.obs_mask, sigma)
    has_r, has_o = np.any(fr != 0, axis=2), np.any(fo != 0, axis=2)
    half, S = block // 2, search
    out = []
    for cy in range(half + S, h - half - S + 1, step):
        for cx in range(half + S, w - half - S + 1, step):
            t = fo[cy - half:cy + half, cx - half:cx + half]
            win = (slice(cy - half - S, cy + half + S), slice(cx - half - S, cx + half + S))
            if has_o[cy - half:cy + half, cx - half:cx + half].mean() < 0.9:
                continue
            if has_r[win].mean() < 0.8 or np.ptp(t) <= 0 or np.ptp(fr[win]) <= 0:
                continue
            r = cv2.matchTemplate(np.ascontiguousarray(fr[win]), np.ascontiguousarray(t),
                                  cv2.TM_CCOEFF_NORMED)
            _, peak, _, (px, py) = cv2.minMaxLoc(r)
            dx = px - S + (blocks_mod._parabola(*r[py, px - 1:px + 2]) if 0 < px < 2 * S
                           else 0.0)
            dy = py - S + (blocks_mod._parabola(*r[py - 1:py + 2, px]) if 0 < py < 2 * S
                           else 0.0)
            out.append((cx + dx, cy + dy, cx, cy, peak))
    return np.float64(out).reshape(-1, 5)


@pytest.mark.parametrize("block", [96, 75])
def test_gradient_blocks_match_the_block_by_block_reference(scene, block):
    """The threaded matching with coverage from integral images gives, bit for bit, the
    blocks of a plain loop over them, also for an odd block side (a 300 px level)."""
    from reblur.align import blocks as blocks_mod

    ref, obs, H_true = scene
    lv = coarse_mod._prepare(ref, obs, AlignParams(), None).levels[0]
    src, dst, ncc = blocks_mod._block_match(lv, H_true, block=block, search=8,
                                            step=max(4, block // 3), sigma=1.0)
    want = _slow_block_match(lv, H_true, block=block, search=8, step=max(4, block // 3),
                             sigma=1.0)
    assert len(want) > 20
    np.testing.assert_array_equal(np.c_[src, dst, ncc], want)


def _coarse_match_fine_differs(fine_amp: float, seed: int = 3, n: int = 1024,
                               coarse_sigma: float = 6.0, fine_sigma: float = 0.7,
                               shift: tuple[float, float] = (5.0, -3.0)):
    """A pair whose coarse structure (a random field low-passed at ``coarse_sigma`` px) is
    the same, moved by ``shift`` px, and whose fine texture (``fine_sigma`` px,
    ``fine_amp`` times the coarse field's contrast) is drawn afresh in the observation."""
    rng = np.random.default_rng(seed)

    def field(sigma, amp):
        a = cv2.GaussianBlur(rng.standard_normal((n + 64, n + 64)).astype(np.float32),
                             (0, 0), sigma)
        return amp * a / a.std()

    coarse = field(coarse_sigma, 1.0)
    fine_ref, fine_obs = field(fine_sigma, fine_amp), field(fine_sigma, fine_amp)
    moved = cv2.warpAffine(coarse, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]),
                           coarse.shape[::-1], flags=cv2.INTER_CUBIC)

    def unit(a):
        a = a[32:32 + n, 32:32 + n]
        return ((a - a.min()) / np.ptp(a)).astype(np.float32)

    return unit(coarse + fine_ref), unit(moved + fine_obs)


def test_seeded_gradient_blocks_verify_on_the_finest_level_that_agrees():
    """Fine texture that differs between the captures (years apart) defeats the blocks
    at full resolution, not at half of it: a seed 2.8 px off is refined on the 512 px
    level and lands within 0.25 px of the true (5, -3) shift.  The 1024 px level alone
    refuses it; with little fine texture the 1024 px level verifies; an unrelated
    observation is refused on every level."""
    from reblur.align.blocks import gradient_align

    def run(ref, obs, levels=None):
        lv = coarse_mod._prepare(ref, obs, AlignParams(), None).levels
        return gradient_align(lv if levels is None else lv[:levels], ref.shape, 0,
                              AlignParams(), lambda H: None, seed=translation(7.0, -1.0))

    ref, obs = _coarse_match_fine_differs(1.0)
    b = run(ref, obs)
    assert b.side == 512
    np.testing.assert_allclose(b.H[:2, 2], [5.0, -3.0], atol=0.25)
    np.testing.assert_allclose(b.H[:2, :2], np.eye(2), atol=1e-3)
    with pytest.raises(AlignmentError, match="inconsistent|could not be verified"):
        run(ref, obs, levels=1)  # the 1024 px level only

    ref, obs = _coarse_match_fine_differs(0.3)
    b = run(ref, obs)
    assert b.side == 1024
    np.testing.assert_allclose(b.H[:2, 2], [5.0, -3.0], atol=0.25)

    other, _ = _coarse_match_fine_differs(1.0, seed=9)
    with pytest.raises(AlignmentError, match="inconsistent|could not be verified"):
        run(ref, other)


def test_shake_extent_verifies_where_the_blocks_agree_on_a_coarser_level():
    """A 2048 px pair whose 1.5 px texture differs between the captures: at shake_px=8
    the working level (1024 px) shows that texture and its blocks do not agree with the
    features' estimate; on the 512 px level, from the features refined by ECC there, they
    do, and the result is within 1.5 px of the true (10, -6) shift at every corner.  (The
    fallbacks at 1024 px all fail: before the coarser level was tried, this extent was
    refused and a larger one ran.)"""
    n = 2048
    ref, obs = _coarse_match_fine_differs(1.0, n=n, coarse_sigma=12.0, fine_sigma=1.5,
                                          shift=(10.0, -6.0))
    a = coarse_align(ref, obs, shake_px=8)
    assert a.method == "features+ecc+gradient", a.method
    assert a.shake_px == 8.0
    assert a.blocks_side == 512 and a.to_dict()["blocks_side"] == 512
    c = np.array([[0, 0], [n - 1, 0], [n - 1, n - 1], [0, n - 1]], float)
    assert np.abs(map_points(a.H, c) - (c + [10.0, -6.0])).max() <= 1.5


def test_gradient_block_coverage_counts():
    """The coverage of every block and search window, from integral images, is the slow
    count of its pixels."""
    from reblur.align.blocks import _box_counts

    rng = np.random.default_rng(5)
    a = rng.random((70, 90)) < 0.7
    y0, x0 = np.array([0, 7, 33, 40]), np.array([0, 12, 50, 59])
    got = _box_counts(a, y0, x0, 30)
    want = np.array([[a[y:y + 30, x:x + 30].sum() for x in x0] for y in y0])
    np.testing.assert_array_equal(got, want)


def test_identity_and_sharp_warp():
    ref = _read(IMAGES["whu_000121"])
    a = coarse_align(ref, ref)
    assert _ref_corner_error(a.H, np.eye(3), ref.shape) <= 0.1, a.H
    rng = np.random.default_rng(3)
    Hv = _viewpoint(rng)
    obs, _ = warp_window(ref, Hv, Box(0, 0, SIZE, SIZE))
    # the working level is 1/4 for the default 16 px of shake: a fraction of its pixel
    b = coarse_align(ref, obs)
    assert _obs_corner_error(b.H, Hv, obs.shape) <= 1.5
    # no shake expected: the polish runs at full resolution
    c = coarse_align(ref, obs, shake_px=4)
    assert _obs_corner_error(c.H, Hv, obs.shape) <= 0.1


def test_observation_crop_of_other_size(scene):
    """A 900x800 observation cut at (x0, y0) = (70, 50): H includes the crop offset."""
    ref, obs, H_true = scene
    x0, y0 = 70, 50
    crop = obs[y0 : y0 + 900, x0 : x0 + 800]
    a = coarse_align(ref, crop)
    H_crop = translation(-x0, -y0) @ H_true
    assert _obs_corner_error(a.H, H_crop, crop.shape) <= 2.0
    # and a reference smaller than the observation: H starts at the reference crop's offset
    ref_crop = ref[y0 : y0 + 900, x0 : x0 + 800]
    b = coarse_align(ref_crop, obs)
    assert _ref_corner_error(b.H, H_true @ translation(x0, y0), ref_crop.shape) <= 2.0


def test_uint16_and_zarr_inputs(scene, aligned, tmp_path):
    ref, obs, H_true = scene
    ref16 = np.round(ref * 65535).astype(np.uint16)
    obs16 = np.round(np.clip(obs, 0, 1) * 65535).astype(np.uint16)
    a16 = coarse_align(ref16, obs16)
    assert _obs_corner_error(a16.H, aligned.H, obs.shape) <= 0.5
    zarrs = []
    for name, arr in (("ref", ref16), ("obs", obs16)):
        z = zarr.open_array(
            store=str(tmp_path / f"{name}.zarr"), mode="w", shape=arr.shape,
            chunks=(256, 256, 3), dtype=arr.dtype,
        )
        z[:] = arr
        zarrs.append(zarr.open_array(store=str(tmp_path / f"{name}.zarr"), mode="r"))
    az = coarse_align(*zarrs)
    np.testing.assert_allclose(az.H, a16.H, rtol=0, atol=1e-9)
    assert az.method == a16.method


def test_partial_scene_change(scene):
    """A 300x300 patch of the later LEVIR image (a real change) does not derail it."""
    ref = _read(IMAGES["levir_test_7"])
    later = _read(LEVIR / "B" / "test_7.png")
    comp = ref.copy()
    comp[400:700, 150:450] = later[400:700, 150:450]
    rng = np.random.default_rng(7)
    obs, H_true = _observe(comp, _viewpoint(rng), rng)
    a = coarse_align(ref, obs)
    assert _obs_corner_error(a.H, H_true, obs.shape) <= 2.5, a


# ---------------------------------------------------------------------------- refusals
def test_unrelated_images_raise(scene):
    ref, _, _ = scene
    rng = np.random.default_rng(11)
    other = _read(WHU / "prev" / "000213.png")
    obs, _ = _observe(other, _viewpoint(rng), rng, n=10)
    with pytest.raises(AlignmentError):
        coarse_align(ref, obs)
    noise = rng.random((SIZE, SIZE, 3)).astype(np.float32)
    with pytest.raises(AlignmentError) as refused:
        coarse_align(ref, noise)
    # one line: each stage tried with its evidence, then what would let the user go on
    msg = str(refused.value)
    assert "\n" not in msg
    assert re.match(r"alignment \(features\): too few feature matches \(\d+ < 12\)", msg), msg
    assert "; fallback (gradient blocks): no consistent gradient structure: 0 confident " \
           "blocks agree at 256x256 px" in msg, msg
    assert "; fallback (phase + ECC): ECC did not converge" in msg, msg
    go_on = msg.split(" -- to go on: ")[1]
    for option in ("--align-hint FILE", "hint=", "georeferenced inputs", "--no-align",
                   "align=False"):
        assert option in go_on, msg
    assert "shake" not in go_on  # the blur model was never the problem
    with pytest.raises(AlignmentError):
        coarse_align(noise, ref)


def test_constant_image_raises(scene):
    ref, obs, _ = scene
    flat = np.full((600, 700, 3), 0.4, np.float32)
    with pytest.raises(AlignmentError, match="textureless"):
        coarse_align(flat, obs)
    with pytest.raises(AlignmentError, match="textureless"):
        coarse_align(ref, np.zeros((SIZE, SIZE), np.uint8))


def test_bad_arguments(scene):
    ref, obs, _ = scene
    assert issubclass(AlignmentError, ValueError)
    with pytest.raises(ValueError, match="method"):
        coarse_align(ref, obs, AlignParams(method="sift"))
    with pytest.raises(ValueError, match="shape"):
        coarse_align(ref[None], obs)
    with pytest.raises(ValueError, match="min_side"):
        coarse_align(ref, obs, AlignParams(min_side=512, max_side=256))


@pytest.mark.parametrize(
    ("options", "pattern"),
    [
        (dict(method="sift"), r"AlignParams\.method must be one of .*'sift'"),
        (dict(motion="projective"), r"AlignParams\.motion"),
        (dict(min_side=8), r"AlignParams\.min_side must be an integer >= 16"),
        (dict(max_side=100.5), r"AlignParams\.max_side must be an integer"),
        (dict(min_side=512, max_side=256), r"min_side <= max_side.*raise max_side"),
        (dict(min_agree=1.5), r"AlignParams\.min_agree must lie in \[0, 1\], got 1\.5"),
        (dict(min_overlap=-0.1), r"AlignParams\.min_overlap must lie in \[0, 1\]"),
        (dict(ransac_px=0.0), r"AlignParams\.ransac_px must be a finite number > 0"),
        (dict(max_zoom=float("inf")), r"AlignParams\.max_zoom must be a finite number >= 1"),
        (dict(max_anisotropy=0.5), r"AlignParams\.max_anisotropy"),
        (dict(min_inliers=3), r"AlignParams\.min_inliers must be an integer >= 4"),
        (dict(polish="yes"), r"AlignParams\.polish must be True or False"),
        (dict(nodata=float("nan")), r"AlignParams\.nodata must be a finite number or None"),
        (dict(rotations=(0.0, float("nan"))), r"AlignParams\.rotations .* finite"),
        (dict(rotations=()), r"AlignParams\.rotations must be a non-empty"),
    ],
)
def test_align_params_refuse_bad_options(options, pattern):
    with pytest.raises(ValueError, match=pattern):
        AlignParams(**options)


def test_align_params_are_frozen_and_normalised():
    p = AlignParams(rotations=[-5, 0, 5], nodata=None)
    assert p.rotations == (-5.0, 0.0, 5.0) and isinstance(p.rotations, tuple)
    assert hash(p) == hash(AlignParams(rotations=(-5.0, 0.0, 5.0), nodata=None))
    with pytest.raises(AttributeError):
        p.method = "ecc"  # type: ignore[misc]
    with pytest.raises(TypeError, match="unexpected keyword"):
        AlignParams(shake_px=8.0)  # the extent is coarse_align's argument, not an option
    rng = np.random.default_rng(0)
    ref = rng.random((64, 64)).astype(np.float32)
    with pytest.raises(TypeError, match="AlignParams"):
        coarse_align(ref, ref, {"method": "ecc"})
    with pytest.raises(ValueError, match="shake_px must be a finite number"):
        coarse_align(ref, ref, shake_px=float("inf"))


@pytest.mark.parametrize(
    ("H", "reason"),
    [
        (np.diag([-1.0, 1.0, 1.0]) @ translation(-1023, 0), "mirrored"),
        (translation(-1535.5, -1535.5) @ np.diag([3.0, 3.0, 1.0]), "zoom"),
        (np.diag([1.9, 0.6, 1.0]), "stretch"),
        (translation(900, 900), "covers"),
        (np.array([[1.0, 0, 0], [0, 1.0, 0], [-0.002, 0, 1.0]]), "horizon"),
    ],
)
def test_implausible_homographies_are_refused(H, reason):
    with pytest.raises(AlignmentError, match=reason):
        check_plausible(
            H, (SIZE, SIZE), (SIZE, SIZE), max_zoom=2.0, max_anisotropy=2.0, min_overlap=0.2
        )


def test_a_zoom_just_outside_the_range_is_reported_to_four_digits_with_its_option():
    """A view a pixel short of half the size maps the reference's corners to a zoom of
    (S / 2 - 1) / (S - 1), just under 1/2: the message says so (such an estimate read
    "zoom 0.5 outside [1/2, 2]") and names the option that widens the range."""
    zoom = (SIZE / 2 - 1) / (SIZE - 1)
    H = np.diag([zoom, zoom, 1.0])
    with pytest.raises(AlignmentError) as err:
        check_plausible(H, (SIZE, SIZE), (SIZE // 2, SIZE // 2), max_zoom=2.0,
                        max_anisotropy=2.0, min_overlap=0.2)
    assert f"zoom {zoom:.4g} outside [0.5, 2]" in str(err.value)
    assert zoom < 0.5 and f"{zoom:.4g}" != "0.5"
    assert "[align] max_zoom" in str(err.value)


# ---------------------------------------------------------------------------- real before/after
def _later_pair(index: int, after: str):
    """A real "before" image and a later capture (years apart) of the same or another
    scene, the later one seen from another viewpoint (3 % / 3 degrees) and shaken (6 px,
    0.8 degree) as in ``benchmarks/quality.py`` (seed ``100 + index``).  Returns
    ``(reference, observation, true homography of the mean camera pose)``."""
    from reblur.simulate import make_pair

    before = _read(LEVIR / "A" / "test_102.png")
    p = make_pair(before, _read(after), rng=100 + index, n_changes=0, moving=False,
                  shake=dict(t_max=6.0, rz_max=0.8),
                  viewpoint=dict(max_shift_frac=0.03, max_rot_deg=3.0), noise_sigma=1 / 255)
    H = pose_homography(*p.path.poses.mean(axis=0), center=p.path.center) @ p.viewpoint
    return p.reference, p.observed, H / H[2, 2]


def test_real_pair_years_apart_aligns_by_gradient_blocks():
    """LEVIR test_102 (grassland, then warehouses): SIFT finds 3 consistent matches; the
    gradient blocks recover the viewpoint.  The truth ignores the dataset's own before /
    after misregistration (about 1.5 px here), hence a bound of a few pixels; the
    viewpoint change alone is 40 px at the corners."""
    ref, obs, H_true = _later_pair(0, LEVIR / "B" / "test_102.png")
    assert _ref_corner_error(np.eye(3), H_true, ref.shape) > 30
    a = coarse_align(ref, obs, shake_px=8)
    assert a.method.startswith("gradient"), a
    assert a.n_blocks >= 20
    assert a.blocks_side == 512  # the working level of an 8 px shake on a 1024 px pair
    assert _ref_corner_error(a.H, H_true, ref.shape) <= 4.0, a


def test_real_unrelated_later_image_is_refused():
    """The same "before" image against a later capture of ANOTHER scene (WHU 000121)."""
    ref, obs, _ = _later_pair(3, WHU / "curr" / "000121.png")
    for shake in (8.0, 64.0):
        with pytest.raises(AlignmentError, match="could not be verified|too few|inconsistent"):
            coarse_align(ref, obs, shake_px=shake)


# ---------------------------------------------------------------------------- several shakes
SHAKES = (8.0, 16.0, 32.0, 64.0)


#: A kernel polish's reason, in a refusal or a polish record: the shared run does not
#: rerun a polish a smaller extent refused on a content misfit on the same level
_POLISH_REASON = re.compile(r"(kernel polish\): )?could not be verified: [^;]*?"
                            r"(shake_px=[0-9.]+|cannot change that)")


def _outcome(a):
    """Comparable form of an alignment or an AlignmentError, its polishes' reasons left
    out (they are compared by :func:`_check_reused_polishes`)."""
    if isinstance(a, AlignmentError):
        return ("refused", _POLISH_REASON.sub("<polish refused>", str(a)))
    d = a.to_dict()
    d["polishes"] = [{k: v for k, v in r.items() if k == "of"} for r in d["polishes"]]
    del d["content_misfit"]  # read from the polishes
    return ("aligned", a.H.tobytes(), json.dumps(d, sort_keys=True))


def _polish_records(a) -> list[dict]:
    return [dict(r) for r in (a.polishes if not isinstance(a, AlignmentError)
                              else getattr(a, "polishes", ()))]


def _check_reused_polishes(shared: list, separate: list) -> int:
    """Every polish record of the shared run is the separate run's, or (a polish not
    rerun) a refusal naming a smaller extent whose polish of the same estimate was
    refused with the same regions on a content misfit.  Returns how many were reused."""
    from reblur.align.polish import content_misfit

    reused, seen = 0, []  # (extent, record) of the content-misfit refusals so far
    for (s, got), want in zip(shared, separate, strict=True):
        got, want = _polish_records(got), _polish_records(want)
        assert len(got) == len(want), f"shake_px={s}"
        for g, w in zip(got, want, strict=True):
            assert g["of"] == w["of"]
            m = re.search(r"at shake_px=([0-9.]+) on the same level", g["outcome"])
            if m is None:
                assert g == w, f"shake_px={s}"
            else:
                earlier = float(m.group(1))
                assert earlier < s and w["outcome"].startswith("refused")
                assert any(e == earlier and r["of"] == g["of"]
                           and r["regions"] == g["regions"] for e, r in seen)
                reused += 1
            if g.get("regions") and content_misfit(g["regions"]) and m is None:
                seen.append((s, g))
    return reused


@pytest.mark.parametrize("case", ["same_scene", "years_apart", "unrelated"])
def test_shakes_share_work_but_not_results(case, scenes, monkeypatch):
    """``coarse_align_shakes`` (one pyramid; features, ECC and gradient blocks memoised)
    gives, extent by extent, exactly what separate ``coarse_align`` calls give: the same
    homography bit for bit, diagnostics, or refusal message, but for the polishes it does
    not rerun (refused on a content misfit at a smaller extent on the same level).  Covers
    the feature + ECC path (a same-scene pair), the gradient blocks from rotation
    hypotheses (years apart, the polish never fits) and a refusal (another scene); a
    caller editing a yielded ``H`` in place must not change the later extents."""
    if case == "same_scene":
        ref, obs, _ = scenes["levir_test_7"]
    elif case == "years_apart":
        ref, obs, _ = _later_pair(0, LEVIR / "B" / "test_102.png")
    else:
        ref, obs, _ = _later_pair(3, WHU / "curr" / "000121.png")
    separate_raw = []
    for s in SHAKES:
        try:
            separate_raw.append(coarse_align(ref, obs, shake_px=s))
        except AlignmentError as err:
            separate_raw.append(err)
    separate = [_outcome(a) for a in separate_raw]

    calls = {"sift": 0, "overview": 0}
    match, ov = coarse_mod.match_features, coarse_mod.overview_k

    def counting_match(*args, **kwargs):
        calls["sift"] += 1
        return match(*args, **kwargs)

    def counting_overview(*args, **kwargs):
        calls["overview"] += 1
        return ov(*args, **kwargs)

    monkeypatch.setattr(coarse_mod, "match_features", counting_match)
    monkeypatch.setattr(coarse_mod, "overview_k", counting_overview)
    shared, raw = [], []
    for s, a in align_mod.coarse_align_shakes(ref, obs, SHAKES):
        shared.append((s, _outcome(a)))
        raw.append((s, a))
        if not isinstance(a, AlignmentError):
            a.H[:] = np.nan  # must not reach the memo
    assert [s for s, _ in shared] == list(SHAKES)
    for s, (got, want) in zip(SHAKES, zip([o for _, o in shared], separate, strict=True),
                              strict=True):
        assert got == want, f"shake_px={s}"
    reused = _check_reused_polishes(raw, separate_raw)
    if case == "years_apart":  # extents sharing a level: polishes refused on content
        assert reused > 0
    assert calls["overview"] == 2  # each image read once
    assert calls["sift"] <= 2  # at most the two feature levels, once each
    if case != "unrelated":
        assert any(o[0] == "aligned" for o in separate)


def test_shakes_arguments():
    rng = np.random.default_rng(0)
    ref = rng.random((64, 64)).astype(np.float32)
    with pytest.raises(TypeError, match="shake_px"):
        next(align_mod.coarse_align_shakes(ref, ref, (8.0,), shake_px=4.0))
    with pytest.raises(ValueError, match="shake_px"):
        next(align_mod.coarse_align_shakes(ref, ref, (8.0, -1.0)))
    with pytest.raises(TypeError, match="method"):
        next(align_mod.coarse_align_shakes(ref, ref, (8.0,), method="nope"))
    # a textureless image is refused at every extent, with coarse_align's message
    flat = np.zeros((64, 64), np.float32)
    got = list(align_mod.coarse_align_shakes(flat, ref, (8.0, 16.0), AlignParams(min_side=32)))
    assert [s for s, _ in got] == [8.0, 16.0]
    for _, err in got:
        assert isinstance(err, AlignmentError) and "textureless" in str(err)
    with pytest.raises(AlignmentError, match="textureless"):
        coarse_align(flat, ref, AlignParams(min_side=32))


def test_overview_cache_reads_once_and_derives_coarser_factors():
    """An OverviewCache reads the image once for a factor and its multiples; the derived
    block means equal those read directly (means of equal blocks), for one band and
    three; the pipeline's scaled view gives the overview of the scaled pixels."""
    from reblur.align import OverviewCache, block_means
    from reblur.pipeline import ScaledView

    rng = np.random.default_rng(5)
    for shape in ((123, 161), (123, 161, 3)):
        a = rng.integers(0, 255, size=shape, dtype=np.uint8)
        rec = _Recorder(a)
        cache = OverviewCache(rec)
        g3, b3 = block_means(cache, 3)
        n_reads = len(rec.reads)
        g6, b6 = block_means(cache, 6)
        g9, _ = block_means(cache, 9)
        assert len(rec.reads) == n_reads and cache.reads == 1  # no new read
        for k, g, b in ((3, g3, b3), (6, g6, b6)):
            h, w = shape[0] // k, shape[1] // k
            blocks = a[: h * k, : w * k].astype(np.float64).reshape(h, k, w, k, -1) / 255.0
            want = blocks.mean(axis=(1, 3))
            np.testing.assert_allclose(b, want, atol=1e-6)
            np.testing.assert_allclose(g, want.mean(axis=2), atol=1e-6)
        assert g9.shape == (123 // 9, 161 // 9)
        assert cache.factor(5) == 6 and cache.factor(7) == 9 and cache.factor(2) == 3
        # a factor that is no multiple of one read reads again
        block_means(cache, 4)
        assert cache.reads == 2
        with pytest.raises(ValueError, match="overview block"):  # derived, but too coarse
            block_means(cache, 3 * 42)
        # the scaled view's overview, from the cache, against reading the view
        C = shape[2] if len(shape) == 3 else 1
        gain, offset = np.linspace(0.8, 1.2, C), np.linspace(-0.1, 0.1, C)
        view = ScaledView(cache, 255.0, gain, offset)
        plain = ScaledView(a, 255.0, gain, offset)
        direct = overviews_mod.read_block_means(plain, 3)
        for got, want in zip(view.block_means(3), direct, strict=True):
            np.testing.assert_allclose(got, want, atol=1e-5)
        assert cache.reads == 2


# ---------------------------------------------------------------------------- hint
def _rotated_40(image, seed, shake=6.0, roll=0.5):
    """``image`` seen rotated by 40 degrees and shifted by (60, -35) px about the centre,
    shaken (``shake`` px, ``roll`` degrees): beyond the +-12 degrees of the rotation
    hypotheses."""
    rng = np.random.default_rng(seed)
    V = pose_homography(60.0, -35.0, rz=40.0, center=CENTER)
    return _observe(image, V, rng, n=20, shake=shake, roll=roll)


def test_hint_reaches_a_large_rotation(scene):
    """Gradient blocks alone (no features) refuse a 40 degree rotation; a hint 5 degrees
    and 20 px off seeds them instead of the rotation hypotheses, and the polish lands on
    the mean camera pose."""
    ref = scene[0]
    obs, H_true = _rotated_40(ref, 40)
    gradient = AlignParams(method="gradient")
    with pytest.raises(AlignmentError, match="no consistent gradient structure"):
        coarse_align(ref, obs, gradient, shake_px=8)
    for hint in (pose_homography(75.0, -45.0, rz=35.0, center=CENTER),
                 pose_homography(45.0, -25.0, rz=45.0, center=CENTER)):
        assert _ref_corner_error(hint, H_true, ref.shape) > 60  # a rough hint
        a = coarse_align(ref, obs, gradient, shake_px=8, hint=hint)
        assert a.method == "hint+gradient+kernel", a
        assert _ref_corner_error(a.H, H_true, ref.shape) < 1.5, a
        assert _obs_corner_error(a.H, H_true, obs.shape) < 1.5, a
    # the pipeline's coarse alignment passes the hint through
    from reblur.pipeline import align_coarse

    b = align_coarse(ref, obs, (8.0,), hint=hint)
    np.testing.assert_array_equal(b.H, a.H)


def test_hint_reaches_a_pair_years_apart():
    """LEVIR test_102 before and after (years apart: SIFT finds 3 consistent matches),
    the later image rotated by 40 degrees: the default refuses, a rough hint aligns.  The
    truth ignores the dataset's own before / after misregistration, about 2 px here
    (seeds 5-7: 2.2-2.4 px at the centre, 3.1-3.8 px at the corners), hence the bounds;
    the shake is light because the blocks alone (the polish does not fit between captures
    years apart) sit near a mode of the blur, not at its mean."""
    ref = _read(LEVIR / "A" / "test_102.png")
    obs, H_true = _rotated_40(_read(LEVIR / "B" / "test_102.png"), 5, shake=3.0, roll=0.2)
    with pytest.raises(AlignmentError, match="too few feature inliers"):
        coarse_align(ref, obs, shake_px=8)
    hint = pose_homography(75.0, -45.0, rz=35.0, center=CENTER)
    a = coarse_align(ref, obs, shake_px=8, hint=hint)
    assert a.method.startswith("hint+gradient") and a.n_blocks >= 30, a
    assert _ref_corner_error(a.H, H_true, ref.shape) < 5.0, a
    c = map_points(a.H, [CENTER]) - map_points(H_true, [CENTER])
    assert np.hypot(*c[0]) < 3.2, a


def test_bad_hints_are_refused(scene):
    ref, obs, H_true = scene
    with pytest.raises(ValueError, match="3x3 finite"):
        coarse_align(ref, obs, hint=np.eye(2))
    with pytest.raises(ValueError, match="3x3 finite"):
        coarse_align(ref, obs, hint=np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match="singular"):
        coarse_align(ref, obs, hint=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="implausible.*covers"):
        coarse_align(ref, obs, hint=translation(900, 900))
    with pytest.raises(ValueError, match="implausible.*mirrored"):
        next(align_mod.coarse_align_shakes(ref, obs, hint=np.diag([-1.0, 1.0, 1.0])))
    # a hint is normalised; a correct one gives the usual answer
    a = coarse_align(ref, obs, hint=2.0 * H_true)
    assert a.method.startswith("hint") and _obs_corner_error(a.H, H_true, obs.shape) <= 2.0


def test_refusals_say_which_option_helps(scene):
    """A pair shaken by 8 px aligned with a shake extent of 2 px: the polish cannot verify
    it, and the refusal names a larger extent, with which it aligns; a hint that is
    refused asks for a closer one."""
    ref, obs, H_true = scene
    features = AlignParams(max_side=256, method="features")
    with pytest.raises(AlignmentError) as refused:
        coarse_align(ref, obs, features, shake_px=2)
    msg = str(refused.value)
    assert re.search(r"\(kernel polish\): could not be verified: \d+ regions agree", msg), msg
    assert msg.endswith("if the blur spans more than 2 px, a larger shake extent (shake_px=8)")
    a = coarse_align(ref, obs, features, shake_px=8)
    assert a.method.endswith("kernel") and _obs_corner_error(a.H, H_true, obs.shape) < 2.0
    noise = np.random.default_rng(12).random((SIZE, SIZE)).astype(np.float32)
    with pytest.raises(AlignmentError, match=r"^alignment \(gradient blocks\)") as refused:
        coarse_align(ref, noise, hint=translation(5.0, -3.0))
    assert "to go on: a closer --align-hint FILE" in str(refused.value)
