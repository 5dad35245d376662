"""The model's tolerance interval (reblur.decide.tolerance) against explicit references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.ndimage as ndi

from reblur.decide import (
    DecisionParams,
    ModelTolerance,
    change_statistic,
    decide,
    estimate_threshold,
    tolerance_interval,
    tolerant_reference,
)


def _smooth_image(shape=(48, 56), seed=0):
    rng = np.random.default_rng(seed)
    return ndi.gaussian_filter(rng.random(shape), 1.2).astype(np.float32)


def _dense_shift_extremes(m: np.ndarray, rho: float, n: int = 21):
    """Min and max over a dense n x n lattice of shifts in [-rho, rho]^2 of the bilinear
    interpolant (scipy, edge replicated): an explicit slow reference."""
    lo = np.full(m.shape, np.inf)
    hi = np.full(m.shape, -np.inf)
    for dy in np.linspace(-rho, rho, n):
        for dx in np.linspace(-rho, rho, n):
            s = ndi.shift(m.astype(np.float64), (dy, dx), order=1, mode="nearest")
            lo = np.minimum(lo, s)
            hi = np.maximum(hi, s)
    return lo, hi


@pytest.mark.parametrize("rho", [0.3, 0.5, 1.0])
def test_shift_interval_is_the_extremes_over_all_shifts(rho):
    m = _smooth_image()
    lo, hi = tolerance_interval(m, ModelTolerance(shift=rho))
    rlo, rhi = _dense_shift_extremes(m, rho)
    # the lattice includes the nine vertices, where the extremes lie: equal up to rounding
    inner = (slice(2, -2), slice(2, -2))
    np.testing.assert_allclose(lo[inner], rlo[inner], atol=2e-6)
    np.testing.assert_allclose(hi[inner], rhi[inner], atol=2e-6)


def test_contrast_widening_is_a_fraction_of_the_local_range():
    m = _smooth_image(seed=1)
    tol = ModelTolerance(shift=0.0, contrast=0.1, radius=2)
    lo, hi = tolerance_interval(m, tol)
    # explicit: range over a disc of radius 2, by brute force
    yy, xx = np.mgrid[-2:3, -2:3]
    disc = (yy ** 2 + xx ** 2) <= 4
    mx = ndi.maximum_filter(m, footprint=disc, mode="nearest")
    mn = ndi.minimum_filter(m, footprint=disc, mode="nearest")
    np.testing.assert_allclose(hi - m, 0.1 * (mx - mn), atol=1e-6)
    np.testing.assert_allclose(m - lo, 0.1 * (mx - mn), atol=1e-6)


def test_tolerant_reference_is_the_nearest_point_of_the_interval():
    rng = np.random.default_rng(2)
    m = _smooth_image(seed=2)
    o = m + rng.normal(0, 0.05, m.shape).astype(np.float32)
    tol = ModelTolerance(shift=0.5, contrast=0.05)
    lo, hi = tolerance_interval(m, tol)
    t = tolerant_reference(o, m, tol)
    inside = (o >= lo) & (o <= hi)
    assert np.array_equal(t[inside], o[inside])
    assert np.array_equal(t[o < lo], lo[o < lo])
    assert np.array_equal(t[o > hi], hi[o > hi])
    # no tolerance: the reference itself
    assert tolerant_reference(o, m, ModelTolerance()) is m
    assert tolerant_reference(o, m, None) is m


def test_a_subpixel_shift_is_not_change_but_a_real_change_is():
    """The observation is the reference moved by 0.4 px (linear interpolation) plus a
    square of 0.3: with the tolerance, only the square remains."""
    m = _smooth_image((96, 96), seed=3) * 0.8
    o = ndi.shift(m.astype(np.float64), (0.4, -0.3), order=1, mode="nearest").astype(np.float32)
    o[40:60, 40:60] += 0.3
    known = np.ones(m.shape, bool)
    sigma = [0.01]
    plain = change_statistic(o, m, known, sigma)
    tol = change_statistic(o, m, known, sigma, tolerance=ModelTolerance(shift=0.5))
    outside = np.ones(m.shape, bool)
    outside[30:70, 30:70] = False  # the square and the window (radius 8) around it
    outside[:3] = outside[-3:] = False
    outside[:, :3] = outside[:, -3:] = False
    assert plain[outside].max() > 2.0  # without it, the shift alone crosses the floor
    assert tol[outside].max() < 1e-6
    assert tol[45:55, 45:55].min() > 20.0  # 0.3 / 0.01, minus nothing on smooth ground


def test_threshold_floor():
    x = np.random.default_rng(4).normal(0.3, 0.05, 10_000)
    t, info = estimate_threshold(x, minimum=2.0)
    assert t == 2.0 and info["floored"]
    t2, info2 = estimate_threshold(x + 5.0, minimum=2.0)
    assert t2 > 5.0 and not info2["floored"]


def test_params_validate_the_tolerance():
    with pytest.raises(ValueError, match="shift tolerance"):
        DecisionParams(shift_tolerance=1.5)
    with pytest.raises(ValueError, match="contrast tolerance"):
        DecisionParams(contrast_tolerance=0.7)
    with pytest.raises(ValueError, match="min_threshold"):
        DecisionParams(min_threshold=-1)
    p = DecisionParams(contrast_radius=5)
    assert p.pixel_reach == 5
    assert p.local_radius == p.smooth_radius + 5 + 2 * p.open_radius + 1


def test_noise_free_misregistered_pair_flags_nothing():
    """A clean (noise-free) pair whose only difference is a 0.3 px shift and a slightly
    different blur: with the default tolerance nothing is change and the square keeps its
    recall.  (The error here is uniform, so the fitted model error alone also copes: this
    guards the tolerance's cost, the test-bed bounds in tests/test_realism.py its gain.)"""
    rng = np.random.default_rng(5)
    ref = ndi.gaussian_filter(rng.random((256, 256)), 2.0)
    ref = (ref - ref.min()) / np.ptp(ref)
    m = ndi.gaussian_filter(ref, 1.0).astype(np.float32)
    o = ndi.gaussian_filter(ndi.shift(ref, (0.3, 0.2), order=3, mode="nearest"), 1.1)
    o = o.astype(np.float32)
    o[100:140, 120:160] += 0.2
    change, _ = decide(o, m)
    truth = np.zeros(m.shape, bool)
    truth[100:140, 120:160] = True
    near = ndi.binary_dilation(truth, iterations=4)
    assert change[~near].mean() == 0.0
    assert change[truth].mean() > 0.9


def test_report_warns_when_the_model_fits_badly():
    from types import SimpleNamespace

    from reblur.report import model_notes

    def result(fits, cal):
        return SimpleNamespace(motion=SimpleNamespace(info={"psnr_inliers": fits}),
                               decision={"calibration": cal})

    good = {"calibrated": True, "met": True, "shift": 0.25, "contrast": 0.0, "floor": 2.0}
    assert model_notes(result([48.0, 51.5], good)) == []
    spread = model_notes(result([39.7, 43.5, 56.0, 56.2], good))
    assert len(spread) == 1 and "39.7 to 56.2 dB" in spread[0]
    bad = dict(good, met=False, shift=1.0, contrast=0.08, floor=4.02)
    raised = model_notes(result([48.0, 49.0], bad))
    assert len(raised) == 1 and "raised to 4.02" in raised[0]


def _windows_pair(seed=7, n=2, side=240):
    """Estimation windows of a clean pair whose observation is the reference moved by
    0.4 px: only model error, no change."""
    rng = np.random.default_rng(seed)
    H = W = 600
    m = ndi.gaussian_filter(rng.random((H, W)), 1.5).astype(np.float32)
    m = (m - m.min()) / np.ptp(m)
    o = ndi.shift(m, (0.4, 0.0), order=3, mode="nearest").astype(np.float32)
    o += rng.normal(0, 0.002, o.shape).astype(np.float32)
    boxes = [(40 + 300 * i, 60, side, side) for i in range(n)]

    def load(g):
        y, x, h, w = g
        sl = (slice(y, y + h), slice(x, x + w))
        return o[sl][..., None], m[sl][..., None], np.zeros((h, w), bool)

    return boxes, load, (H, W)


def test_calibration_picks_the_first_rung_that_explains_the_windows():
    from reblur.decide import Photometry
    from reblur.pipeline import _calibrate_tolerance

    boxes, load, shape = _windows_pair()
    ph = Photometry(gain=np.ones(1), offset=np.zeros(1), sigma=np.array([0.002]),
                    image_shape=shape)
    p = DecisionParams(calibration_margin=0)
    q, info = _calibrate_tolerance(p, [(b, None) for b in boxes], load, ph, shape)
    assert info["calibrated"]
    # a 0.4 px shift: the 0.25 px rung leaves it above the floor, a 0.5 px one explains it
    assert info["tried"][0][:2] == [0.25, 0.0] and info["tried"][0][2] > info["target"]
    assert info["tried"][1][:2] == [0.5, 0.02] and info["tried"][1][2] <= info["target"]
    assert (q.shift_tolerance, q.contrast_tolerance) == (0.5, 0.02) and info["met"]
    assert q.min_threshold == p.min_threshold
    # with a margin, that many rungs further (and no further than the ladder's end)
    q2, _ = _calibrate_tolerance(DecisionParams(calibration_margin=2),
                                 [(b, None) for b in boxes], load, ph, shape)
    assert (q2.shift_tolerance, q2.contrast_tolerance) == p.tolerance_ladder[3]
    q9, _ = _calibrate_tolerance(DecisionParams(calibration_margin=9),
                                 [(b, None) for b in boxes], load, ph, shape)
    assert (q9.shift_tolerance, q9.contrast_tolerance) == p.tolerance_ladder[-1]


def test_first_meeting_rung_of_a_nested_ladder_is_bisected():
    """On a monotone ladder the search finds the rung a scan in order finds, evaluating
    at most 2 + ceil(log2 n) rungs; a ladder that is not nested is scanned in order."""
    from reblur.decide.calibrate import _first_meeting

    for n in range(1, 9):
        for k in range(n + 1):  # rungs k.. meet (k == n: none)
            asked = []

            def meets(i, k=k, asked=asked):
                asked.append(i)
                return i >= k

            got = _first_meeting(n, meets, nested=True)
            assert got == (k if k < n else None)
            assert len(asked) == len(set(asked)) <= 2 + math.ceil(math.log2(n))
    flags = [False, True, False, True]
    asked = []
    assert _first_meeting(4, lambda i: asked.append(i) or flags[i], nested=False) == 1
    assert asked == [0, 1]


def _scan_calibration(obs, mat, kn, ev, sigma, ladder, threshold, target, margin):
    # the calibration as a plain scan of the ladder in order (the reference)
    from reblur.decide.statistic import change_statistic

    n = sum(int(e.sum()) for e in ev)
    for i, tol in enumerate(ladder):
        vals = [change_statistic(o, m, k, sigma, tolerance=tol)[e]
                for o, m, k, e in zip(obs, mat, kn, ev, strict=True)]
        if sum(int((v > threshold).sum()) for v in vals) <= target * n:
            return ladder[min(i + margin, len(ladder) - 1)], float(threshold)
    return ladder[-1], max(float(np.quantile(np.concatenate(vals), 1 - target)), threshold)


@pytest.mark.parametrize("shift", [0.0, 0.4, 0.8, 1.6])
def test_calibration_search_chooses_what_a_scan_chooses(shift):
    """The calibration's rung and floor, on windows of a pair moved by ``shift`` px (met at
    the first, a middle or no rung), equal those of a scan of the ladder in order, for the
    default ladder, a finer nested one and one that is not nested."""
    from reblur.decide.calibrate import calibrate_tolerance

    rng = np.random.default_rng(11)
    m = ndi.gaussian_filter(rng.random((300, 300)), 1.5).astype(np.float32)
    m = (m - m.min()) / np.ptp(m)
    o = ndi.shift(m, (shift, 0.3 * shift), order=3, mode="nearest").astype(np.float32)
    o += rng.normal(0, 0.002, o.shape).astype(np.float32)
    obs, mat = [o[:150, :, None], o[150:, :, None]], [m[:150, :, None], m[150:, :, None]]
    kn = [np.ones((150, 300), bool)] * 2
    ev = [k.copy() for k in kn]
    for e in ev:
        e[:20], e[-20:], e[:, :20], e[:, -20:] = False, False, False, False
    sigma = np.array([0.002])
    ladders = [
        tuple(DecisionParams().ladder),
        tuple(ModelTolerance(s, c) for s, c in [(0.1, 0.0), (0.25, 0.0), (0.25, 0.01),
                                                 (0.5, 0.01), (0.5, 0.02), (0.75, 0.02),
                                                 (1.0, 0.02), (1.0, 0.04), (1.0, 0.08)]),
        tuple(ModelTolerance(s, c) for s, c in [(1.0, 0.0), (0.25, 0.05), (0.5, 0.0)]),
    ]
    for ladder in ladders:
        for margin in (0, 2):
            tol, info = calibrate_tolerance(obs, mat, kn, ev, sigma, ladder=ladder,
                                            threshold=2.0, target=2e-4, margin=margin)
            want, floor = _scan_calibration(obs, mat, kn, ev, sigma, ladder, 2.0, 2e-4,
                                            margin)
            assert (tol, info["floor"]) == (want, floor)


def test_windows_marked_as_change_drop_the_noise_floor():
    """Where the estimate marks most of its windows as change, sigma is no noise unit."""
    from reblur.decide import Photometry
    from reblur.pipeline import _calibrate_tolerance

    boxes, load, shape = _windows_pair()
    ph = Photometry(gain=np.ones(1), offset=np.zeros(1), sigma=np.array([0.002]),
                    image_shape=shape)
    chi = np.ones((boxes[0][2], boxes[0][3]), np.float32)
    chi[:10] = 0  # 4 % unmarked
    q, info = _calibrate_tolerance(DecisionParams(), [(b, chi) for b in boxes], load, ph,
                                   shape)
    assert not info["calibrated"] and info["marked"] > 0.9
    assert q.min_threshold == 0.0


def test_tolerant_reference_takes_any_memory_layout():
    """The contiguous path (OpenCV) and the strided one (numpy) clamp to the same values,
    and both to the explicit ``clip(o, lo, hi)``."""
    rng = np.random.default_rng(7)
    m = _smooth_image((64, 71), seed=7)
    o = m + rng.normal(0, 0.05, m.shape).astype(np.float32)
    tol = ModelTolerance(shift=0.4, contrast=0.05, radius=3)
    lo, hi = tolerance_interval(m, tol)
    want = np.minimum(np.maximum(o, lo), hi)
    np.testing.assert_array_equal(tolerant_reference(o, m, tol), want)
    np.testing.assert_array_equal(tolerant_reference(np.asfortranarray(o), m, tol), want)
