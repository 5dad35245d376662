"""Change decision on synthetic pairs with known truth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import scipy.ndimage as ndi

from reblur.decide import (
    DecisionParams,
    Photometry,
    change_statistic,
    decide,
    decide_tile,
    estimate_threshold,
    fit_model_error,
    fit_photometry,
    tile_boxes,
)
from reblur.metrics import change_metrics

SHAPE = (384, 384)
# (top-left, size, change): bright, dark, low contrast (6 noise sigmas), one band only
SQUARES = [((60, 60), 40, +0.25), ((60, 250), 40, -0.25), ((250, 60), 40, +0.06),
           ((250, 250), 40, "band0")]
GAIN = np.array([1.1, 0.9, 1.05], np.float32)
OFFSET = np.array([0.05, -0.02, 0.0], np.float32)


def _texture(shape, bands, rng):
    h, w = shape
    tex = np.zeros((h, w, bands))
    for s in (1.5, 4.0, 12.0):
        tex += ndi.gaussian_filter(rng.standard_normal((h, w, bands)), (s, s, 0)) * s
    return np.clip(0.5 + 0.15 * tex / tex.std(), 0, 1).astype(np.float32)


def make_pair(bands=3, seed=0, ramp=True, squares=SQUARES):
    """Reblurred reference, observation (gain/offset, illumination ramp, noise 0.01, pasted
    squares), truth of the squares, unknown mask (garbage values there)."""
    rng = np.random.default_rng(seed)
    h, w = SHAPE
    reb = _texture(SHAPE, bands, rng)
    obs = reb.copy()
    truth = np.zeros(SHAPE, bool)
    for (y, x), s, d in squares:
        sl = (slice(y, y + s), slice(x, x + s))
        if d == "band0":
            obs[sl + (slice(0, 1),)] += 0.2
        else:
            obs[sl] += d
        truth[sl] = True
    obs = obs * GAIN[:bands] + OFFSET[:bands]
    if ramp:  # multiplicative illumination ramp across, additive haze down
        yy, xx = np.mgrid[0:h, 0:w]
        obs = obs * (0.85 + 0.3 * xx / w)[..., None] + (0.04 * yy / h)[..., None]
    obs = obs + 0.01 * rng.standard_normal(obs.shape)
    unknown = np.zeros(SHAPE, bool)
    unknown[:, :8] = True
    unknown[150:190, 300:340] = True
    obs[unknown] = rng.random((int(unknown.sum()), bands))
    obs = obs.astype(np.float32)
    if bands == 1:
        obs, reb = obs[..., 0], reb[..., 0]
    return obs, reb, truth, unknown


@pytest.fixture(scope="module")
def colour():
    return make_pair(bands=3)


@pytest.fixture(scope="module")
def colour_result(colour):
    obs, reb, truth, unknown = colour
    return decide(obs, reb, unknown, field_block=96)


# --------------------------------------------------------------------------- whole image
def _check_detection(change, truth, unknown):
    m = change_metrics(truth, change, ignore=unknown)
    assert m["jaccard"] >= 0.9, m
    # no false alarm away from the squares: the ramp and the texture raise nothing
    near = ndi.binary_dilation(truth, iterations=4)
    assert not np.any(change & ~near), int(np.count_nonzero(change & ~near))
    # every square found, including the faint one and the one-band change
    for (y, x), s, _ in SQUARES:
        assert change[y : y + s, x : x + s].mean() >= 0.9, (y, x)


def test_colour_squares_with_ramp(colour, colour_result):
    obs, reb, truth, unknown = colour
    change, info = colour_result
    _check_detection(change, truth, unknown)
    assert len(info["regions"]) == len(SQUARES)
    assert info["threshold_info"]["method"] == "auto"


def test_grayscale_squares_with_ramp():
    obs, reb, truth, unknown = make_pair(bands=1)
    change, info = decide(obs, reb, unknown, field_block=96)
    assert change.shape == SHAPE
    _check_detection(change, truth, unknown)


def test_ramp_needs_the_field(colour):
    # without a smooth field the ramp is left in the residual (the field does the work)
    obs, reb, truth, unknown = colour
    change, _ = decide(obs, reb, unknown, illumination="global")
    assert change_metrics(truth, change, ignore=unknown)["jaccard"] < 0.9
    # illumination="auto" (the default) sees that a field explains the data far better
    change, info = decide(obs, reb, unknown)
    chosen = info["photometry"]["info"]["illumination"]
    assert chosen["model"] == "field" and max(chosen["ratio"]) < 0.85, chosen
    assert change_metrics(truth, change, ignore=unknown)["jaccard"] >= 0.9


def test_auto_illumination_keeps_the_global_model_without_a_field():
    obs, reb, truth, unknown = make_pair(bands=3, seed=4, ramp=False)
    change, info = decide(obs, reb, unknown)
    chosen = info["photometry"]["info"]["illumination"]
    assert chosen["model"] == "global" and min(chosen["ratio"]) > 0.95, chosen
    assert info["photometry"]["field_block"] is None
    _check_detection(change, truth, unknown)


def test_auto_illumination_refuses_a_field_that_fits_a_black_fill():
    """The left 55 % of the view is exactly 0 (a fill without a nodata tag): a quadratic
    field fits it perfectly with a gain through 0, and beats the global model's residual
    scale by far.  It is no light: the global model stays, the record says why, and the
    fill (where the reference is not itself near black) is change; the lit part is not."""
    from reblur.decide.photometry import MIN_FIELD_GAIN

    obs, reb, truth, unknown = make_pair(bands=1, seed=4, ramp=False, squares=())
    h, w = SHAPE
    fill = np.zeros(SHAPE, bool)
    fill[:, : int(0.55 * w)] = True
    obs = obs.copy()
    obs[fill] = 0.0
    change, info = decide(obs, reb, unknown)
    chosen = info["photometry"]["info"]["illumination"]
    assert chosen["model"] == "global" and min(chosen["ratio"]) <= 0.85, chosen
    assert "rejected" in chosen and str(MIN_FIELD_GAIN) in chosen["rejected"]
    visible = fill & ~unknown & (reb > 0.15)
    assert change[visible].mean() > 0.9
    assert change[~fill & ~unknown].mean() < 0.01


def test_clip_levels_are_maxima_held_by_a_share_of_the_samples():
    """Against an explicit count: a band's maximum held by >= CLIP_SHARE of the samples is
    its saturation level, one held by a few is not; the low end is never clipped."""
    from reblur.decide.photometry import CLIP_SHARE, clip_levels

    rng = np.random.default_rng(9)
    obs = rng.uniform(0.1, 0.9, (5000, 3))
    obs[:40, 0] = 1.0  # 0.8 % saturated in band 0
    obs[:3, 1] = 0.95  # a maximum at 3 samples in band 1
    obs[:2000, 2] = 0.0  # a black fill over 40 % of band 2
    got = clip_levels(obs)
    for c in range(3):
        v = obs[:, c].max()
        held = np.count_nonzero(obs[:, c] == v) >= CLIP_SHARE * obs.shape[0]
        assert got[c, 1] == (v if held else np.inf), c
    assert np.isneginf(got[:, 0]).all()
    assert got[0, 1] == 1.0 and np.isinf(got[1:, 1]).all()


def test_a_saturated_observation_is_no_change_and_a_new_bright_object_is():
    """A brighter exposure (gain 1.3) saturates the observation at 1.0 over part of the
    view; the reblurred reference does not.  Predicted above the level, 24 % of the
    saturated pixels were flagged at 2ad958e.  The saturated samples now stay out of the
    fit, the model's prediction is clipped at the level, and nothing but the pasted
    squares is flagged, a bright square that saturates included (the model predicts it
    far below the level)."""
    rng = np.random.default_rng(10)
    reb = _texture(SHAPE, 1, rng)[:, :, 0]
    obs = 1.3 * reb - 0.05
    truth = np.zeros(SHAPE, bool)
    for (y, x), size, d in (((40, 40), 40, +0.3), ((300, 300), 40, -0.3)):
        obs[y : y + size, x : x + size] += d
        truth[y : y + size, x : x + size] = True
    obs[40:80, 40:80] = np.maximum(obs[40:80, 40:80], 1.2)  # the bright square saturates
    truth[40:80, 40:80] = True
    obs = np.clip(obs + 0.01 * rng.standard_normal(SHAPE), 0.0, 1.0).astype(np.float32)
    saturated = obs >= 1.0
    assert 0.02 < saturated.mean() < 0.3
    change, info = decide(obs, reb, illumination="global")
    away = ~ndi.binary_dilation(truth, iterations=4)
    assert change[saturated & away].mean() < 0.002
    assert change[away].mean() < 0.002
    assert change[40:80, 40:80].mean() > 0.9 and change[300:340, 300:340].mean() > 0.9
    ph = info["photometry"]
    assert abs(ph["gain"][0] - 1.3) < 0.01, ph["gain"]
    assert ph["info"]["clip"]["levels"][0][1] == 1.0


def test_unknown_never_change(colour, colour_result):
    obs, reb, truth, unknown = colour
    change, info = colour_result
    assert not np.any(change & unknown)
    assert info["n_unknown"] == int(unknown.sum())
    # a square half covered by unknown pixels: only its known half may be flagged
    unk = unknown.copy()
    unk[60:100, 60:80] = True
    change2, _ = decide(obs, reb, unk, field_block=96)
    assert not np.any(change2 & unk)
    assert change2[60:100, 80:100].mean() > 0.8
    # NaN pixels count as unknown
    obs_nan = obs.copy()
    obs_nan[300:320, 150:170] = np.nan
    change3, info3 = decide(obs_nan, reb, unknown, field_block=96)
    assert not change3[300:320, 150:170].any()
    assert info3["n_unknown"] == int(unknown.sum()) + 400


def test_no_change_no_alarm():
    obs, reb, truth, unknown = make_pair(bands=3, seed=1, ramp=False, squares=[])
    change, info = decide(obs, reb, unknown)
    assert not change.any()
    assert info["photometry"]["gain"] == pytest.approx(list(GAIN), abs=0.01)


def test_threshold_override(colour, colour_result):
    obs, reb, truth, unknown = colour
    _, info = colour_result
    ph = fit_photometry(obs, reb, ~unknown, field_block=96)
    huge, info_h = decide(obs, reb, unknown, photometry=ph, threshold=1e6)
    assert not huge.any()
    assert info_h["threshold"] == 1e6 and info_h["threshold_info"]["method"] == "given"
    # the estimated threshold, given explicitly, reproduces the default call
    same, _ = decide(obs, reb, unknown, photometry=ph, threshold=info["threshold"])
    assert np.array_equal(same, colour_result[0])
    # a threshold between the faint square's level and the strong ones drops the faint one
    S = change_statistic(obs, ph.apply(reb), ~unknown, ph.sigma,
                         tolerance=DecisionParams().tolerance)
    faint = float(np.median(S[255:285, 65:95]))
    mid, _ = decide(obs, reb, unknown, photometry=ph, threshold=1.2 * faint)
    assert not mid[250:290, 60:100].any()
    assert mid[60:100, 60:100].mean() > 0.9


def test_hysteresis_needs_strong_evidence(colour):
    obs, reb, truth, unknown = colour
    ph = fit_photometry(obs, reb, ~unknown, field_block=96)
    S = change_statistic(obs, ph.apply(reb), ~unknown, ph.sigma,
                         tolerance=DecisionParams().tolerance)
    faint = float(np.median(S[255:285, 65:95]))
    t = 0.6 * faint  # the faint square is above the threshold but nowhere at 2 t
    weak, info = decide(obs, reb, unknown, photometry=ph, threshold=t)
    assert not weak[250:290, 60:100].any()
    assert info["counts"]["weak"] >= 1
    kept, _ = decide(obs, reb, unknown, photometry=ph, threshold=t, strong_factor=1.2)
    assert kept[250:290, 60:100].mean() > 0.8


def test_thin_changes_kept_by_their_evidence_networks_dropped_without_it():
    """A road-like cross and a 10 x 240 strip of real contrast (0.2) persist under the loose
    tolerance of the edge test (1 px, 8 % of the local range): kept, as thin changes, next to
    a compact square.  With the test off (``edge_test_fraction=0``, the shape tests alone)
    they are dropped as not object-like."""
    obs, reb, _, unknown = make_pair(bands=3, seed=2, ramp=False, squares=[((300, 300), 36, 0.2)])
    obs = obs.copy()
    obs[40:52, 20:360] += 0.2 * GAIN  # horizontal bar of the cross
    obs[20:240, 150:162] += 0.2 * GAIN  # vertical bar
    obs[300:310, 20:260] += 0.2 * GAIN  # a 10 x 240 strip
    kept, info = decide(obs, reb, unknown)
    assert kept[300:336, 300:336].mean() > 0.9
    assert kept[42:50, 30:140].mean() > 0.9 and kept[302:308, 30:250].mean() > 0.9
    assert info["counts"]["thin"] >= 2
    shape_only, info = decide(obs, reb, unknown, edge_test_fraction=0.0)
    assert shape_only[300:336, 300:336].mean() > 0.9
    assert not shape_only[:260, :].any() and not shape_only[290:320, 20:260].any()
    assert info["counts"]["not_object"] >= 2 and info["counts"]["thin"] == 0
    pixel_only, _ = decide(obs, reb, unknown, region_tests=False)
    assert pixel_only[40:52, 30:140].mean() > 0.9 and pixel_only[300:310, 30:250].mean() > 0.9


def test_edge_artefacts_of_a_subpixel_shift_vanish_under_the_edge_test():
    """Long straight soft edges seen 0.9 px off (beyond the statistic's 0.25 px tolerance,
    within the edge test's 1 px): strips of evidence along every edge, crossed by a real
    strip (contrast 0.2).  The pixel-level decision keeps the whole lattice; the edge test
    keeps the real strip and none of the artefacts, even those joined to it."""
    rng = np.random.default_rng(5)
    h, w = 320, 400
    xx = np.arange(w, dtype=np.float64)

    def steps(x):  # soft steps every 50 px
        return 0.1 + 0.8 * sum(1.0 / (1.0 + np.exp(-(x - c) / 3.0)) * (-1) ** k
                               for k, c in enumerate(range(25, w, 50)))

    reb = np.repeat(steps(xx)[None, :], h, axis=0).astype(np.float32)
    obs = np.repeat(steps(xx + 0.9)[None, :], h, axis=0)
    obs[150:162, 30:370] += 0.2  # a real strip across the edges
    obs = (obs + 0.005 * rng.standard_normal(obs.shape)).astype(np.float32)
    ph = fit_photometry(obs, reb, edge_error=False, illumination="global")
    strip = np.zeros((h, w), bool)
    strip[144:168, 22:378] = True
    pixels, _ = decide(obs, reb, photometry=ph, threshold=2.0, region_tests=False)
    assert np.count_nonzero(pixels & ~strip) > 2000  # the artefacts are there
    mask, info = decide(obs, reb, photometry=ph, threshold=2.0)
    assert mask[152:160, 40:360].mean() > 0.9  # the real strip is kept
    assert not mask[~strip].any(), np.argwhere(mask & ~strip)[:5]  # no edge artefact
    assert info["counts"]["thin"] >= 1, info["counts"]
    shape_only, _ = decide(obs, reb, photometry=ph, threshold=2.0, edge_test_fraction=0.0)
    assert not shape_only.any()  # the shape tests alone drop the strip with the lattice


def test_regions_closed_one_by_one():
    """A bay cut into an object (open to the outside, so no hole) is filled by the
    closing; two objects 6 px apart stay apart (a closing of their union would bridge
    them); nothing is added outside the objects."""
    from reblur.decide import _decide_core

    h, w = 200, 300
    yy, xx = np.mgrid[0:h, 0:w]
    disc = (yy - 100) ** 2 + (xx - 80) ** 2 <= 40**2
    bay = disc & (np.abs(yy - 100) <= 5) & (xx >= 80)  # 11 px wide, open to the right
    left = np.zeros((h, w), bool)
    left[85:115, 160:190] = True
    right = np.zeros((h, w), bool)
    right[85:115, 196:226] = True
    S = np.where((disc & ~bay) | left | right, 5.0, 0.0).astype(np.float32)
    known = np.ones((h, w), bool)
    plain, _, _ = _decide_core(S, known, 1.0, DecisionParams(close_radius=0))
    closed, _, _ = _decide_core(S, known, 1.0, DecisionParams(close_radius=8))
    assert not plain[bay].any()  # not a hole: hole filling leaves it
    # all but the mouth, where a 17 px disc from the outside still enters the bay
    assert closed[bay & (xx <= 110)].all() and closed[bay].mean() > 0.8
    assert not closed[:, 190:196].any()
    assert not (closed & ~(disc | left | right)).any()
    assert not (plain & ~closed).any()  # a closing only adds


# --------------------------------------------------------------------------- tiles
def _tiled(obs, reb, unknown, ph, threshold, params, tile, halo):
    out = np.zeros(unknown.shape, bool)
    infos = []
    for pbox, cbox in tile_boxes(unknown.shape, tile, halo):
        y0, x0, h, w = pbox
        sl = (slice(y0, y0 + h), slice(x0, x0 + w))
        m, info = decide_tile(obs[sl], reb[sl], unknown[sl], threshold=threshold,
                              photometry=ph, box=pbox, core=cbox, params=params)
        cy, cx, ch, cw = cbox
        out[cy : cy + ch, cx : cx + cw] = m
        infos.append((cbox, info))
    return out, infos


def test_tiled_equals_whole(colour, colour_result):
    obs, reb, truth, unknown = colour
    whole, info = colour_result
    ph = fit_photometry(obs, reb, ~unknown, field_block=96)
    p = DecisionParams()
    halo = p.halo(max_region_extent=60)  # the squares are 40 px (plus their bleed)
    tiled, infos = _tiled(obs, reb, unknown, ph, info["threshold"], p, 100, halo)
    assert all(i["complete"] for _, i in infos)
    assert np.array_equal(tiled, whole)
    # each region is reported by exactly one tile, at the same place
    regions = sorted(r["bbox"] for _, i in infos for r in i["regions"])
    assert regions == sorted(r["bbox"] for r in info["regions"])


def test_small_halo_is_flagged(colour, colour_result):
    obs, reb, truth, unknown = colour
    whole, info = colour_result
    ph = fit_photometry(obs, reb, ~unknown, field_block=96)
    p = DecisionParams()
    tiled, infos = _tiled(obs, reb, unknown, ph, info["threshold"], p, 100, p.local_radius + 2)
    assert not all(i["complete"] for _, i in infos)
    for (cy, cx, ch, cw), i in infos:  # tiles claiming completeness are exact
        if i["complete"]:
            assert np.array_equal(tiled[cy : cy + ch, cx : cx + cw],
                                  whole[cy : cy + ch, cx : cx + cw])


def test_decide_tile_checks_boxes(colour):
    obs, reb, _, unknown = colour
    ph = fit_photometry(obs, reb, ~unknown)
    with pytest.raises(ValueError, match="box size"):
        decide_tile(obs[:50, :50], reb[:50, :50], threshold=2.0, photometry=ph, box=(0, 0, 60, 50))
    with pytest.raises(ValueError, match="not inside"):
        decide_tile(obs[:50, :50], reb[:50, :50], threshold=2.0, photometry=ph,
                    box=(0, 0, 50, 50), core=(40, 40, 20, 20))


# --------------------------------------------------------------------------- photometry
def test_photometry_robust_global_fit():
    rng = np.random.default_rng(5)
    reb = _texture((200, 200), 3, rng)
    obs = reb * GAIN + OFFSET + 0.01 * rng.standard_normal(reb.shape).astype(np.float32)
    obs[:, :40] += 0.3  # 20 % of the pixels changed
    ph = fit_photometry(obs, reb)
    assert ph.gain == pytest.approx(GAIN, abs=0.02)
    assert ph.offset == pytest.approx(OFFSET, abs=0.02)
    assert ph.sigma == pytest.approx([0.01] * 3, rel=0.3)
    d = ph.to_dict()
    assert d["field_block"] is None and len(d["gain"]) == 3


def test_photometry_apply_is_the_per_band_formula_exactly():
    # gain * x + offset per band, in float64 for a float32 tile, then stored as float32:
    # the explicit loop, bit for bit, for 1 and 3 bands, odd shapes, strided input
    rng = np.random.default_rng(21)
    for shape, bands in (((37, 53, 3), 3), ((70, 41), 1), ((33, 65, 1), 1)):
        gain = 1.0 + rng.normal(0, 0.01, bands)
        offset = rng.normal(0, 0.01, bands)
        ph = Photometry(gain=gain, offset=offset, sigma=np.ones(bands))
        big = rng.random((shape[0] * 2,) + shape[1:], dtype=np.float32)
        for x in (big[: shape[0]], big[::2], big[:, ::-1]):
            x3 = x if x.ndim == 3 else x[:, :, None]
            want = np.stack([(x3[:, :, c].astype(np.float64) * gain[c] + offset[c])
                             .astype(np.float32) for c in range(bands)], axis=2)
            got = ph.apply(x)
            assert got.shape == x.shape and got.dtype == np.float32
            np.testing.assert_array_equal(got if got.ndim == 3 else got[:, :, None], want)
    x64 = rng.random((20, 30, 3))
    ph = Photometry(gain=np.array([1.1, 0.9, 1.0]), offset=np.array([0.01, 0.0, -0.02]),
                    sigma=np.ones(3))
    np.testing.assert_array_equal(ph.apply(x64), x64 * ph.gain + ph.offset)


def test_photometry_sample_is_as_precise_as_every_pixel():
    """The default sample (``FIT_SAMPLES``, 10^5 of a 1 MP image) gives the fit of every
    pixel to within its sampling error: gain ``~ sigma / (sqrt(n) std(x))`` (2e-4 here),
    offset ``~ sigma / sqrt(n)`` (3e-5, times ~2.5 for the mean), scale ``1 / sqrt(2 n)``
    (0.2 %); the bounds are 3-5 of those.  A sample of 10^3 misses them."""
    from reblur.decide.photometry import FIT_SAMPLES

    rng = np.random.default_rng(11)
    reb = _texture((1000, 1000), 1, rng)[:, :, 0]
    obs = reb * 1.1 + 0.05 + 0.01 * rng.standard_normal(reb.shape).astype(np.float32)
    obs[:, :200] += 0.3  # 20 % of the pixels changed
    every = fit_photometry(obs, reb, max_samples=obs.size, edge_error=False)
    assert FIT_SAMPLES < obs.size / 5

    def close(ph) -> bool:
        return (abs(ph.gain[0] - every.gain[0]) < 6e-4
                and abs(ph.offset[0] - every.offset[0]) < 4e-4
                and abs(ph.sigma[0] / every.sigma[0] - 1) < 0.01)

    assert close(fit_photometry(obs, reb, edge_error=False))
    assert not all(close(fit_photometry(obs, reb, max_samples=1000, edge_error=False, rng=s))
                   for s in range(4))
    # (Huber's bounded influence: the changed fifth pulls the offset by ~0.005)
    assert every.gain[0] == pytest.approx(1.1, abs=2e-3)
    assert every.offset[0] == pytest.approx(0.05, abs=0.01)


@pytest.mark.parametrize("illumination", ["global", "field"])
def test_photometry_bands_fitted_side_by_side_equal_each_band_alone(illumination):
    """The bands of a colour pair are fitted on threads side by side: each band's gain,
    offset, scale, robust fit and illumination field equal those of fitting that band
    alone, bit for bit (Huber's fit in two bands, the high-breakdown one in the third,
    where half of the pixels changed)."""
    rng = np.random.default_rng(6)
    reb = _texture((200, 220), 3, rng)
    yy, xx = np.mgrid[:200, :220] / 200.0
    ramp = (1 + 0.2 * xx * yy)[:, :, None]
    obs = reb * GAIN * ramp + OFFSET + 0.01 * rng.standard_normal(reb.shape)
    obs = obs.astype(np.float32)
    obs[:, :30, 0] += 0.3
    obs[:, :110, 2] = 0.9 - obs[:, :110, 2]  # half the third band: another scene
    both = fit_photometry(obs, reb, illumination=illumination, edge_error=False)
    methods = set()
    for c in range(3):
        one = fit_photometry(obs[:, :, c], reb[:, :, c], illumination=illumination,
                             edge_error=False)
        assert (both.gain[c], both.offset[c], both.sigma[c]) == (
            one.gain[0], one.offset[0], one.sigma[0])
        assert both.info["huber"][c] == one.info["huber"][0]
        if illumination == "field":
            ill = both.info["illumination"]
            assert ill["sigma_field"][c] == one.info["illumination"]["sigma_field"][0]
            assert ill["sigma_global"][c] == one.info["illumination"]["sigma_global"][0]
        methods.add(one.info["method"].split()[0])
    assert methods == {"Huber", "high-breakdown"}


def test_prefit_bands_side_by_side_equal_each_band_alone():
    """The low-resolution photometric prefit of a colour pair (its bands on threads): each
    band's gain and offset equal prefitting that band alone, bit for bit, and the agreement
    map is where every band alone agrees (a change in one band only shows in it)."""
    from reblur.pipeline import photometric_prefit

    rng = np.random.default_rng(7)
    ref = (255 * np.clip(_texture((300, 340), 3, rng), 0, 1)).astype(np.uint8)
    obs = np.clip(ref * GAIN + 255 * OFFSET + rng.normal(0, 2, ref.shape), 0, 255)
    obs = obs.astype(np.uint8)
    obs[60:140, 80:200, 1] = 250  # a change in the second band only
    H0 = np.eye(3)
    both = photometric_prefit(ref, obs, H0, 255.0, 255.0)
    alone = [photometric_prefit(ref[:, :, c], obs[:, :, c], H0, 255.0, 255.0)
             for c in range(3)]
    for c, one in enumerate(alone):
        assert (both.gain[c], both.offset[c]) == (one.gain[0], one.offset[0])
    agree = np.logical_and.reduce([one.agreement == 1 for one in alone])
    np.testing.assert_array_equal(both.agreement == 1, agree)
    np.testing.assert_array_equal(np.isnan(both.agreement), np.isnan(alone[0].agreement))
    assert (alone[0].agreement == 1).sum() > (both.agreement == 1).sum() > 0


def test_prefit_on_a_sample_agrees_with_the_fit_on_every_pixel():
    """A prefit map larger than ``FIT_SAMPLES`` fits its line on a seeded sample: the gain
    and offset stay within a fraction of a grey level of the same robust fit on every
    pixel of the map (computed here), and of the truth, with a quarter of the view changed;
    the agreement map is judged on every pixel (the change is a disagreement)."""
    import cv2

    from reblur.decide.photometry import FIT_SAMPLES
    from reblur.pipeline import photometric_prefit
    from reblur.robust import robust_line

    rng = np.random.default_rng(11)
    ref = (255 * np.clip(_texture((512, 512), 1, rng)[:, :, 0], 0, 1)).astype(np.uint8)
    obs = np.clip(ref * 1.1 + 255 * 0.04 + rng.normal(0, 2, ref.shape), 0, 255)
    obs[:256, :256] = 255 - obs[:256, :256]  # a quarter of the view changed
    obs = obs.astype(np.uint8)
    pre = photometric_prefit(ref, obs, np.eye(3), 255.0, 255.0)
    # every pixel of the prefit's map (one per pixel here), low-passed as it does
    assert pre.factor == 1
    r, o = (cv2.GaussianBlur(a.astype(np.float32) / 255.0, (0, 0), 6.0) for a in (ref, obs))
    inner = (slice(8, -8), slice(8, -8))
    assert r[inner].size > FIT_SAMPLES
    g_all, b_all, _ = robust_line(r[inner].astype(float).ravel(), o[inner].astype(float).ravel())
    assert abs(pre.gain[0] - g_all) < 2e-3 and abs(pre.offset[0] - b_all) < 1e-3
    assert abs(pre.gain[0] - 1.1) < 0.01 and abs(pre.offset[0] - 0.04) < 0.005
    assert np.mean(pre.agreement[30:226, 30:226] == 0) > 0.95
    assert np.mean(pre.agreement[300:480, 300:480] == 1) > 0.95


def test_prefit_takes_an_illumination_ramp_into_a_field_and_keeps_the_line_without_one():
    """An observation whose light ramps across it (gain 0.55 -> 1.0, offset -0.05 ->
    +0.05): the prefit chooses its quadratic field, whose gain and offset at every pixel
    are within 0.01 of the ramp's (computed here), and the agreement map holds the whole
    view (the ramp is no change).  The same pair without the ramp keeps the global line,
    and its record says why (ratios above PREFIT_FIELD_GAIN)."""
    from reblur.pipeline import PREFIT_FIELD_GAIN, photometric_prefit

    rng = np.random.default_rng(5)
    H, W = 480, 640
    ref = (255 * np.clip(_texture((H, W), 1, rng)[:, :, 0], 0, 1)).astype(np.uint8)
    xx = np.broadcast_to(np.arange(W, dtype=float), (H, W))
    gain = 0.55 + 0.45 * xx / (W - 1)
    offset = -0.05 + 0.1 * xx / (W - 1)
    noise = rng.normal(0, 1.0, ref.shape)
    lit = np.clip(ref * gain + 255 * offset + noise, 0, 255).astype(np.uint8)
    pre = photometric_prefit(ref, lit, np.eye(3), 255.0, 255.0)
    assert pre.illumination is not None
    assert pre.illumination_info["model"] == "field"
    assert min(pre.illumination_info["ratio"]) <= PREFIT_FIELD_GAIN
    G, Z = pre.illumination.at(np.arange(20, H - 20, 10), np.arange(20, W - 20, 10))
    assert np.abs(G[:, :, 0] - gain[20:H - 20:10, 20:W - 20:10]).max() < 0.01
    assert np.abs(Z[:, :, 0] - offset[20:H - 20:10, 20:W - 20:10]).max() < 0.01
    assert np.mean(pre.agreement[5:-5, 5:-5] == 1) > 0.99
    flat = np.clip(ref * 0.8 + 255 * 0.02 + noise, 0, 255).astype(np.uint8)
    plain = photometric_prefit(ref, flat, np.eye(3), 255.0, 255.0)
    assert plain.illumination is None and plain.illumination_info["model"] == "global"
    assert min(plain.illumination_info["ratio"]) > PREFIT_FIELD_GAIN


def _half_black_pair():
    """LEVIR test_7 (8 bit) and its observation under a 19 px line blur at 30 degrees with
    2 DN of noise, the left 600 of 1024 columns then set to 0 (a fill without a nodata
    tag)."""
    from reblur.testbed.scenes import levir_image

    ref = np.clip(np.rint(levir_image("test_7") * 255), 0, 255).astype(np.uint8)
    k = np.zeros((19, 19), np.float32)
    for t in np.linspace(-9, 9, 37):
        k[int(round(9 + t * np.sin(np.pi / 6))), int(round(9 + t * np.cos(np.pi / 6)))] += 1
    blurred = cv2.filter2D(ref.astype(np.float32), -1, k / k.sum(),
                           borderType=cv2.BORDER_REFLECT)
    noise = np.random.default_rng(7).normal(0, 2, ref.shape)
    obs = np.clip(np.rint(blurred + noise), 0, 255).astype(np.uint8)
    obs[:, :600] = 0
    return ref, obs


def _agreement_by_side(pre):
    a, k = pre.agreement, pre.factor
    return (float(np.nanmean(a[5:-5, int(np.ceil(620 / k)) : -5])),
            float(np.nanmean(a[5:-5, 5 : int(580 / k)])))


def test_prefit_fits_no_line_or_field_through_a_black_fill():
    """A quadratic field fitted through the fill has its gain pass through 0 and leaves a
    residual scale 0.0013 of the line's, so the pre-fit took it and its agreement map --
    which steers the estimation windows -- held the fill and not the lit part (0.0 / 1.0
    at 2ad958e).  The fill, one clipped level over half the map, now stays out of the
    fits: the line is kept, the lit part agrees and the fill does not."""
    import reblur.pipeline as pl

    ref, obs = _half_black_pair()
    pre = pl.photometric_prefit(ref, obs, np.eye(3), 255.0, 255.0)
    assert pre.illumination is None and pre.illumination_info["model"] == "global"
    assert abs(pre.gain[0] - 1.0) < 0.1
    lit, black = _agreement_by_side(pre)
    assert lit > 0.95 and black < 0.05, (lit, black)


def test_prefit_refuses_a_field_whose_gain_falls_to_zero(monkeypatch):
    """The same pair with the clipped level left in the fits (CLIPPED_SHARE above 1): the
    field wins on its residual scale, and is refused because its gain is not above
    MIN_FIELD_GAIN everywhere; the record says so, and the agreement is the line's."""
    import reblur.pipeline as pl

    monkeypatch.setattr(pl, "CLIPPED_SHARE", 2.0)
    ref, obs = _half_black_pair()
    pre = pl.photometric_prefit(ref, obs, np.eye(3), 255.0, 255.0)
    info = pre.illumination_info
    assert min(info["ratio"]) <= pl.PREFIT_FIELD_GAIN
    assert pre.illumination is None and info["model"] == "global" and "rejected" in info
    lit, black = _agreement_by_side(pre)
    assert lit > 0.95 and black < 0.05, (lit, black)


def test_clipped_marks_a_level_held_by_a_share_of_the_map():
    """Exact extremes held by >= CLIPPED_SHARE of the covered map are marked; an extreme at
    a few pixels is not (an explicit count)."""
    from reblur.pipeline import CLIPPED_SHARE, _clipped

    rng = np.random.default_rng(8)
    cover = np.ones((100, 100), bool)
    o = rng.random((100, 100)).astype(np.float32) * 0.8 + 0.1
    o[:3, :3] = 0.95  # a new maximum at 9 pixels (< 1 %)
    o[50:, :] = 0.0  # a fill over half the map
    got = _clipped(o, cover)
    want = np.zeros_like(cover)
    for v in (o.min(), o.max()):
        if (o == v).sum() >= CLIPPED_SHARE * cover.sum():
            want |= o == v
    assert np.array_equal(got, want)
    assert got[50:].all() and not got[:50].any()
    assert not _clipped(o, cover & (np.arange(100) < 50)[:, None]).any()  # fill uncovered


def test_scaled_view_flattens_by_the_illumination_field():
    """ScaledView with an illumination field: every window read, with or without a band
    index, is ``(a / scale - O) / G`` of the field's quadratic polynomials evaluated here
    pixel by pixel; its block means are those of the flattened image within the field's
    variation over a block."""
    from reblur.decide.photometry import IlluminationField
    from reblur.pipeline import ScaledView

    rng = np.random.default_rng(3)
    a = rng.integers(0, 256, (60, 80, 2)).astype(np.uint8)
    g = np.array([[0.9, 0.1, -0.05, 0.02, 0.01, -0.03], [1.1, -0.1, 0.04, 0.0, 0.02, 0.01]])
    o = np.array([[0.01, 0.02, 0.0, -0.01, 0.0, 0.005], [-0.02, 0.0, 0.03, 0.0, 0.0, 0.0]])
    view = ScaledView(a, 255.0, illumination=IlluminationField(g, o, (60, 80)))

    def explicit(r, c, b):
        u, v = 2 * (c + 0.5) / 80 - 1, 2 * (r + 0.5) / 60 - 1
        t = np.array([1, u, v, u * u, u * v, v * v])
        return (a[r, c, b] / 255.0 - t @ o[b]) / (t @ g[b])

    win = view[10:25, 30:52]
    assert win.shape == (15, 22, 2) and win.dtype == np.float32
    for r, c, b in [(10, 30, 0), (24, 51, 1), (17, 40, 0), (12, 45, 1)]:
        assert win[r - 10, c - 30, b] == pytest.approx(explicit(r, c, b), rel=1e-5)
    one = view[5:9, 70:80, 1]
    assert one.shape == (4, 10)
    assert one[2, 3] == pytest.approx(explicit(7, 73, 1), rel=1e-5)
    _, means = view.block_means(4)
    full = view[:, :]
    blocks = full.reshape(15, 4, 20, 4, 2).mean(axis=(1, 3))
    assert np.abs(means - blocks).max() < 2e-3


def test_photometry_from_tiles_and_downsampled(colour):
    obs, reb, _, unknown = colour
    whole = fit_photometry(obs, reb, ~unknown, field_block=96)
    boxes = [(0, 0, 192, 192), (0, 192, 192, 192), (192, 0, 192, 192), (192, 192, 192, 192)]
    sl = [(slice(y, y + h), slice(x, x + w)) for y, x, h, w in boxes]
    tiles = fit_photometry([obs[s] for s in sl], [reb[s] for s in sl],
                           [~unknown[s] for s in sl], boxes=boxes, field_block=96)
    assert tiles.image_shape == SHAPE
    small = [(a.reshape(192, 2, 192, 2, 3).mean((1, 3))) for a in (obs, reb)]
    valid_small = ~unknown.reshape(192, 2, 192, 2).any((1, 3))
    down = fit_photometry(small[0], small[1], valid_small, scale=2, field_block=96)
    assert down.image_shape == SHAPE
    ref = whole.apply(reb)
    for ph in (tiles, down):
        assert np.abs(ph.apply(reb) - ref)[~unknown].max() < 0.01
    # applying per tile equals applying to the whole image
    y, x, h, w = 100, 37, 80, 150
    part = whole.apply(reb[y : y + h, x : x + w], (y, x, h, w))
    assert np.array_equal(part, ref[y : y + h, x : x + w])
    assert isinstance(whole.with_sigma([0.02] * 3), Photometry)
    # the downsampled fit's residual scale is that of averaged pixels; re-measure at full res
    y, x, h, w = boxes[3]
    full = down.residual_sigma(obs[y:, x:], reb[y:, x:], ~unknown[y:, x:], boxes[3])
    assert np.all(down.sigma < 0.8 * full) and full == pytest.approx(whole.sigma, rel=0.1)
    with pytest.raises(ValueError, match="boxes"):
        fit_photometry([obs], [reb])


# --------------------------------------------------------------------------- threshold
def test_estimate_threshold():
    rng = np.random.default_rng(0)
    noise = 1.0 + 0.1 * rng.standard_normal(50_000)
    t, info = estimate_threshold(noise, method="mad")
    assert t == pytest.approx(info["median"] + 4 * info["mad"])
    assert t == pytest.approx(1.4, abs=0.02)
    # overlapping classes: Otsu (lower) is used; well separated: the MAD bound
    overlap = np.concatenate([rng.gamma(2.0, 0.5, 50_000), 3 + rng.gamma(2.0, 1.0, 20_000)])
    t_o, info_o = estimate_threshold(overlap)
    assert t_o == info_o["otsu"] < info_o["mad_bound"] and info_o["broad"]
    separated = np.concatenate([noise, 20 + rng.standard_normal(2_000)])
    t_s, info_s = estimate_threshold([separated[:10_000], separated[10_000:]])
    assert t_s == info_s["mad_bound"] < info_s["otsu"] < 20
    # a bulk as narrow as noise and nothing else (a large image whose sample holds no
    # change): Otsu splits the noise itself, the z-bound is kept
    chi = np.sqrt(rng.chisquare(20, 200_000) / 20)
    t_n, info_n = estimate_threshold(chi)
    med = np.median(chi)
    bound = med + 4 * 1.4826 * np.median(np.abs(chi - med))
    assert info_n["otsu"] < bound and not info_n["broad"]
    assert t_n == pytest.approx(bound, rel=1e-9) and info_n["chosen"] == "mad"
    assert np.mean(chi > t_n) < 0.01 < np.mean(chi > info_n["otsu"])
    t_c, info_c = estimate_threshold(np.full(10, 2.0))
    assert t_c > 2.0 and "note" in info_c
    with pytest.raises(ValueError, match="finite"):
        estimate_threshold(np.array([np.nan]))
    with pytest.raises(ValueError, match="method"):
        estimate_threshold(noise, method="kmeans")


# --------------------------------------------------------------------------- validation
def test_input_validation(colour):
    obs, reb, _, unknown = colour
    with pytest.raises(ValueError, match="shape"):
        decide(obs, reb[:-1])
    with pytest.raises(ValueError, match="unknown"):
        decide(obs, reb, unknown[:-1])
    with pytest.raises(ValueError, match="no known pixel"):
        decide(obs, reb, np.ones(SHAPE, bool))
    with pytest.raises(TypeError, match="unknown decision parameter"):
        decide(obs, reb, min_aera=3)
    with pytest.raises(ValueError, match="levels"):
        DecisionParams(levels=(1.5, 2.0))
    with pytest.raises(ValueError, match="boundary_fraction"):
        DecisionParams(boundary_fraction=1.0)
    p = DecisionParams()
    # window radius + per-pixel reach (the 3 x 3 stencils, the widest tolerance of the
    # ladder: a disc of contrast_radius) + opening + 1
    assert p.local_radius == 8 + max(1, p.contrast_radius) + 2 * 3 + 1
    assert p.halo(100) == p.local_radius + 100


# --------------------------------------------------------------------------- model error
def _structured(seed=0, shape=(512, 512)):
    """A smooth random image with edges and fine texture, and its gradient / Laplacian."""
    rng = np.random.default_rng(seed)
    m = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 1.2)
    m = (m - m.min()) / np.ptp(m)
    m = m + 0.5 * (cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 8) > 0.5)
    m = m.astype(np.float32)
    gx = cv2.Sobel(m, cv2.CV_64F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT) / 8.0
    gy = cv2.Sobel(m, cv2.CV_64F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT) / 8.0
    lap = cv2.Laplacian(m.astype(np.float64), cv2.CV_64F, ksize=1, borderType=cv2.BORDER_REFLECT)
    return rng, m, gx * gx + gy * gy, lap * lap


def test_model_error_fit_recovers_known_coefficients():
    """Residual drawn from N(0, s^2 + a |grad m|^2 + b (lap m)^2) with known a, b."""
    rng, m, g2, l2 = _structured()
    s, k_edge, k_curv = 0.01, 0.15, 0.08
    sd = np.sqrt(s * s + k_edge**2 * g2 + k_curv**2 * l2)
    obs = m + rng.standard_normal(m.shape) * sd
    known = np.ones(m.shape, bool)
    ek, ck = fit_model_error(obs, m, known, [s])
    assert ek[0] == pytest.approx(k_edge, rel=0.15)
    assert ck[0] == pytest.approx(k_curv, rel=0.2)
    # a change (a strong square, 4 % of the pixels) does not inflate the fit much
    obs2 = obs.copy()
    obs2[100:202, 100:202] += 0.3
    ek2, ck2 = fit_model_error(obs2, m, known, [s])
    assert ek2[0] == pytest.approx(k_edge, rel=0.25) and ck2[0] == pytest.approx(k_curv, rel=0.3)
    # pure noise: no model error
    ek0, ck0 = fit_model_error(m + s * rng.standard_normal(m.shape), m, known, [s])
    assert ek0[0] < 0.03 and ck0[0] < 0.03


def test_statistic_with_model_error_matches_explicit_formula():
    rng, m, g2, l2 = _structured(1, (96, 96))
    obs = (m + 0.02 * rng.standard_normal(m.shape)).astype(np.float32)
    known = np.ones(m.shape, bool)
    known[:5] = False
    S = change_statistic(obs, m, known, [0.01], smooth=0.0, edge_k=[0.2], curv_k=[0.1])
    z2 = (obs.astype(np.float64) - m) ** 2 / (0.01**2 + 0.04 * g2 + 0.01 * l2)
    np.testing.assert_allclose(S[known], np.sqrt(z2[known]), rtol=1e-5)
    assert not S[~known].any()


def test_label_statistics_match_ndimage():
    # the candidate-only reach / median against scipy's whole-array versions (the reference)
    from scipy import ndimage as ndi

    from reblur.decide import _label_median, _label_reaches

    rng = np.random.default_rng(5)
    for _ in range(10):
        S = rng.random((120, 170)).astype(np.float32)
        lab, n = ndi.label(rng.random((120, 170)) > 0.55)
        idx = np.arange(1, n + 1)
        np.testing.assert_array_equal(_label_reaches(S, lab, n, np.float32(0.9)),
                                      ndi.maximum(S, lab, idx) >= np.float32(0.9))
        np.testing.assert_allclose(_label_median(S, lab, n), ndi.median(S, lab, idx),
                                   rtol=0, atol=1e-7)


def test_gaussian_zero_matches_ndimage():
    from scipy import ndimage as ndi

    from reblur.decide import gaussian_zero

    a = np.random.default_rng(2).random((61, 83))
    for sigma, trunc in ((2.0, 4.0), (1.3, 3.0)):
        ref = ndi.gaussian_filter(a, sigma, mode="constant", cval=0.0, truncate=trunc)
        np.testing.assert_allclose(gaussian_zero(a, sigma, trunc), ref, rtol=0, atol=1e-12)


def test_statistic_reused_on_a_larger_halo_equals_computing_it_whole():
    """A re-run with a larger halo computes the statistic only on the ring (plus its
    reach) and reuses the rest: the values are those of computing it over the whole
    larger tile, on interior tiles and tiles on the image border, with unknown pixels."""
    from reblur.decide import DecisionParams, Photometry, _tile_statistic, change_statistic

    rng = np.random.default_rng(11)
    H, W = 260, 300
    obs = rng.normal(0.5, 0.1, (H, W, 2)).astype(np.float32)
    reb = (obs + rng.normal(0, 0.02, obs.shape)).astype(np.float32)
    known = np.ones((H, W), bool)
    known[100:130, 40:90] = False
    ph = Photometry(gain=np.ones(2), offset=np.zeros(2), sigma=np.array([0.02, 0.03]),
                    image_shape=(H, W), edge_k=np.array([0.3, 0.2]),
                    curv_k=np.array([0.1, 0.0]))
    p = DecisionParams()
    for small, large in (((60, 70, 120, 130), (30, 40, 180, 190)),  # interior
                         ((0, 0, 110, 120), (0, 0, 170, 180)),  # top-left border
                         ((140, 150, 120, 150), (100, 110, 160, 190))):  # bottom-right
        def stat(box):
            y, x, h, w = box
            sl = (slice(y, y + h), slice(x, x + w))
            return _tile_statistic(obs[sl], reb[sl], known[sl], ph, p, box, (H, W), None)

        y, x, h, w = large
        sl = (slice(y, y + h), slice(x, x + w))
        reused = _tile_statistic(obs[sl], reb[sl], known[sl], ph, p, large, (H, W),
                                 (stat(small), small))
        whole = change_statistic(obs[sl], reb[sl], known[sl], ph.sigma, smooth=p.smooth,
                                 truncate=p.truncate, edge_k=ph.edge_k, curv_k=ph.curv_k,
                                 tolerance=p.tolerance)
        np.testing.assert_allclose(reused, whole, rtol=1e-6, atol=1e-7)
        # the earlier values near its inner edges are not exact, so they were recomputed
        sy, sx = small[0] - y, small[1] - x
        if small[0] > 0:
            edge = stat(small)[0, 20:-20]
            assert not np.allclose(edge, whole[sy, sx + 20 : sx + small[3] - 20], rtol=1e-6)


def test_poly_field_fit_recovers_a_quadratic_gain_and_offset():
    """The illumination field's IRLS on more samples than it fits on (an even subset of
    those near the start model's band): a known quadratic gain and offset over the image,
    10 % of the samples changed by +0.5, comes back to within the noise's reach."""
    from reblur.decide.photometry import FIELD_FIT_SAMPLES, fit_poly_field

    rng = np.random.default_rng(3)
    shape = (400, 500)
    n = shape[0] * shape[1]
    assert n > FIELD_FIT_SAMPLES
    ys, xs = np.divmod(np.arange(n), shape[1])
    u = 2.0 * (xs + 0.5) / shape[1] - 1.0
    v = 2.0 * (ys + 0.5) / shape[0] - 1.0
    a_true = np.array([1.1, 0.1, 0.0, 0.0, 0.0, -0.05])  # 1, u, v, u^2, uv, v^2
    b_true = np.array([0.01, 0.02, 0.0, 0.0, 0.01, 0.0])
    terms = np.stack([np.ones(n), u, v, u * u, u * v, v * v], axis=1)
    x = rng.random(n)
    y = (terms @ a_true) * x + terms @ b_true + 0.005 * rng.standard_normal(n)
    y[rng.random(n) < 0.1] += 0.5
    # the start (a global model) leaves the ramp in its residuals: their inlier scale,
    # 0.03, keeps the whole ramp within its 8-scale band and the changes out of it
    a, b = fit_poly_field(ys, xs, x, y, shape, (1.1, 0.01), 0.03)
    np.testing.assert_allclose(a, a_true, atol=3e-3)
    np.testing.assert_allclose(b, b_true, atol=2e-3)
