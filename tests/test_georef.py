"""The georeferenced prior (reblur.align.georef) on real GeoTIFF pairs made by GDAL.

Expected values come from outside the code under test: the analytic affine map of two
north-up transforms, PROJ's own reprojection of individual pixel centres (rasterio.warp), and
GDAL's warper, whose output is warped back with OpenCV and compared with the original image.

The residual figures of every CRS pair tested are printed by
    pytest -s -k residual_figures tests/test_georef.py
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import rasterio
from affine import Affine
from rasterio.crs import CRS
from rasterio.warp import calculate_default_transform
from rasterio.warp import transform as proj_transform

from reblur.align.georef import geo_homography
from reblur.io import open_image
from reblur.testbed.geo import DEFAULT_ORIGIN, geo_pair
from reblur.testbed.scenes import levir_image

E0, N0 = DEFAULT_ORIGIN
UTM33 = CRS.from_epsg(32633)

#: (observation CRS, its pixel size in its own units): about 0.7 m on the ground at 45 N for
#: Web Mercator (1 / cos 45), a neighbouring UTM zone, and 0.55 m x 0.78 m in degrees
CRS_PAIRS = [("EPSG:3857", 1.0), ("EPSG:32634", 0.7), ("EPSG:4326", 7e-6)]


def _geo(crs, transform) -> dict:
    return dict(crs=CRS.from_user_input(crs), transform=transform)


def _utm_geo(pixel: float = 0.5, e: float = E0, n: float = N0) -> dict:
    return _geo(UTM33, Affine(pixel, 0.0, e, 0.0, -pixel, n))


def _reprojected_geo(ref_geo: dict, ref_hw: tuple[int, int], crs: str, res):
    """Observation grid GDAL picks for the reference's footprint in ``crs``."""
    h, w = ref_hw
    t = ref_geo["transform"]
    bounds = (t.c, t.f + t.e * h, t.c + t.a * w, t.f)
    tr, ow, oh = calculate_default_transform(ref_geo["crs"], crs, w, h, *bounds, resolution=res)
    return _geo(crs, tr), (oh, ow)


def _proj_pixels(ref_geo, obs_geo, xy: np.ndarray) -> np.ndarray:
    """Reference pixel centres -> observation pixel centres, one point at a time through
    affine and PROJ (pixel (c, r)'s centre is at transform * (c + 0.5, r + 0.5))."""
    out = []
    for x, y in xy:
        mx, my = ref_geo["transform"] @ (x + 0.5, y + 0.5)
        (ox,), (oy,) = proj_transform(ref_geo["crs"], obs_geo["crs"], [mx], [my])
        c, r = ~obs_geo["transform"] @ (ox, oy)
        out.append((c - 0.5, r - 0.5))
    return np.array(out)


def _apply(H, xy):
    q = np.c_[xy, np.ones(len(xy))] @ H.T
    return q[:, :2] / q[:, 2:]


# --- (a) same CRS: the exact affine map ----------------------------------------------------


def test_same_crs_scaled_offset_is_the_analytic_affine():
    ref, obs = _utm_geo(0.5), _utm_geo(0.7, E0 + 30.0, N0 - 20.0)
    prior = geo_homography(ref, (400, 600), obs, (500, 500, 3))
    # column: E0 + 0.5 (x + 0.5) = E0 + 30 + 0.7 (x_obs + 0.5); rows likewise with northings
    expected = np.array([
        [0.5 / 0.7, 0.0, (0.25 - 30.0) / 0.7 - 0.5],
        [0.0, 0.5 / 0.7, (0.25 - 20.0) / 0.7 - 0.5],
        [0.0, 0.0, 1.0],
    ])
    np.testing.assert_allclose(prior.H, expected, rtol=0, atol=1e-9)
    assert prior.method == "affine" and prior.residual_max == 0.0
    # footprints: x in [E0, E0 + 300] vs [E0 + 30, E0 + 380]; y in [N0 - 200, N0] vs
    # [N0 - 370, N0 - 20]: 270 m x 180 m of the observation's 350 m x 350 m
    assert prior.overlap == pytest.approx(270 * 180 / 350**2, abs=1e-9)


def test_same_crs_rotated_transform_maps_pixel_centres():
    ref = _geo(UTM33, Affine.translation(E0, N0) @ Affine.rotation(25.0) @ Affine.scale(0.5, -0.5))
    obs = _utm_geo(0.8, E0 - 200.0, N0 + 100.0)
    prior = geo_homography(ref, (300, 400), obs, (600, 600))
    xy = np.random.default_rng(0).uniform(0, 299, size=(20, 2))
    expected = [np.array(~obs["transform"] @ (ref["transform"] @ (x + 0.5, y + 0.5))) - 0.5
                for x, y in xy]
    np.testing.assert_allclose(_apply(prior.H, xy), expected, rtol=0, atol=1e-9)


# --- (b) different CRSs: PROJ's reprojection of pixel centres ------------------------------


@pytest.mark.parametrize(("crs", "res"), CRS_PAIRS)
def test_fit_matches_proj_within_its_residual(crs, res):
    ref = _utm_geo(0.5)
    ref_hw = (2000, 2000)  # a 1 km scene
    obs, obs_hw = _reprojected_geo(ref, ref_hw, crs, res)
    prior = geo_homography(ref, ref_hw, obs, obs_hw)
    assert prior.method == "fit" and prior.obs_crs == crs
    assert 0 < prior.residual_rms <= prior.residual_max < 0.1
    xy = np.random.default_rng(1).uniform(0, 1999, size=(50, 2))
    err = np.hypot(*(_apply(prior.H, xy) - _proj_pixels(ref, obs, xy)).T)
    # the random points lie between the grid points: allow a tenth more than the grid's max
    assert err.max() <= 1.1 * prior.residual_max
    json.dumps(prior.to_dict())


def test_fit_covers_only_the_overlap_of_a_large_reference():
    """A 1 km observation inside a 20 km reference: the fit is over the overlap, where it is
    as good as for a 1 km reference (a fit over the whole reference would be metres off)."""
    ref, ref_hw = _utm_geo(0.5), (40000, 40000)
    sub = _utm_geo(0.5, E0 + 9000.0, N0 - 9000.0)  # the 1 km around the reference's centre
    obs, obs_hw = _reprojected_geo(sub, (2000, 2000), "EPSG:3857", 1.0)
    prior = geo_homography(ref, ref_hw, obs, obs_hw)
    assert prior.overlap > 0.9  # GDAL's grid is the footprint's bounding box
    assert prior.residual_max < 0.1
    xy = np.random.default_rng(2).uniform(18000, 19999, size=(50, 2))
    err = np.hypot(*(_apply(prior.H, xy) - _proj_pixels(ref, obs, xy)).T)
    assert err.max() <= 1.1 * prior.residual_max


def test_points_beyond_the_projections_horizon_are_skipped():
    """A lon/lat reference reaching past the limb of an orthographic observation: PROJ cannot
    map part of it (GDAL fails the whole call then); the prior comes from the rest, with its
    (large) residual stated, and agrees with PROJ where the observation sees the reference."""
    ref = _geo("EPSG:4326", Affine(0.1, 0.0, 80.0, 0.0, -0.1, 10.0))  # 80..100 E, 10 S..10 N
    ortho = CRS.from_proj4("+proj=ortho +lat_0=0 +lon_0=0 +R=6371000")
    obs = _geo(ortho, Affine(1000.0, 0.0, 6.2e6, 0.0, -1000.0, 1.0e6))  # x to 6.5e6 > R
    prior = geo_homography(ref, (200, 200), obs, (2000, 300))
    assert 0 < prior.overlap < 0.2 and prior.residual_max > 1.0
    rng = np.random.default_rng(3)
    xy = np.c_[rng.uniform(0, 99, 30), rng.uniform(0, 199, 30)]  # 80..90 E: on the near side
    err = np.hypot(*(_apply(prior.H, xy) - _proj_pixels(ref, obs, xy)).T)
    assert err.max() <= 1.1 * prior.residual_max


# --- (c) GDAL-reprojected pixels warped back with H^-1 -------------------------------------


@pytest.fixture(scope="module")
def scene() -> np.ndarray:
    """A real, non-square LEVIR-CD crop (a swapped x/y would show)."""
    return levir_image("test_102")[128:640, 64:832]


def _shift(a: np.ndarray, b: np.ndarray) -> float:
    (dx, dy), _ = cv2.phaseCorrelate(a.astype(np.float64), b.astype(np.float64))
    return float(np.hypot(dx, dy))


@pytest.mark.parametrize(("crs", "res"), [("EPSG:32633", 0.7), *CRS_PAIRS])
def test_reprojected_image_warps_back_onto_the_original(scene, tmp_path, crs, res):
    pair = geo_pair(scene, tmp_path, obs_crs=crs, obs_resolution=res)
    ref, obs = open_image(pair.reference), open_image(pair.observation)
    with rasterio.open(pair.observation) as src:  # reblur.io reads the georeferencing
        assert obs.geo["crs"] == src.crs == CRS.from_user_input(crs)
        assert obs.geo["transform"] == src.transform
    prior = geo_homography(ref.geo, ref.shape, obs.geo, obs.shape)
    o = np.asarray(obs.array, dtype=np.float32)
    r = np.asarray(ref.array, dtype=np.float32)
    h, w = r.shape
    inner = np.s_[24:-24, 24:-24]

    def back(H):
        return cv2.warpPerspective(o, np.linalg.inv(H), (w, h), flags=cv2.INTER_LINEAR)[inner]

    assert np.corrcoef(back(prior.H).ravel(), r[inner].ravel())[0, 1] > 0.98
    assert _shift(r[inner], back(prior.H)) < 0.05
    # the check can fail: treating the transform as mapping pixel centres (not corners)
    # leaves the warped-back image off by a fraction of a pixel wherever the sizes differ
    s = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    assert _shift(r[inner], back(s @ prior.H @ np.linalg.inv(s))) > 0.1
    # the overlap is the share of the observation GDAL filled with data
    assert prior.overlap == pytest.approx(np.mean(o > 0), abs=0.005)


# --- (d) refusals ----------------------------------------------------------------------------


def test_missing_georeferencing_is_refused():
    ref, obs = _utm_geo(), _utm_geo()
    with pytest.raises(ValueError, match="reference is not georeferenced"):
        geo_homography(None, (10, 10), obs, (10, 10))
    with pytest.raises(ValueError, match="observation has a geotransform but no CRS"):
        geo_homography(ref, (10, 10), dict(crs=None, transform=obs["transform"]), (10, 10))
    with pytest.raises(ValueError, match="reference has a CRS but no geotransform"):
        geo_homography(dict(crs=UTM33), (10, 10), obs, (10, 10))


def test_disjoint_footprints_are_refused_with_both_bounds():
    ref = _utm_geo(0.5)  # 50 m x 50 m
    far = _utm_geo(0.5, E0 + 1000.0)
    with pytest.raises(ValueError, match="do not overlap") as info:
        geo_homography(ref, (100, 100), far, (100, 100))
    msg = str(info.value)
    assert f"({E0:.3f}, {N0 - 50:.3f}, {E0 + 50:.3f}, {N0:.3f})" in msg
    assert f"({E0 + 1000:.3f}, {N0 - 50:.3f}, {E0 + 1050:.3f}, {N0:.3f})" in msg
    # in two CRSs, both bounds are given in the observation's
    obs, obs_hw = _reprojected_geo(far, (100, 100), "EPSG:3857", 1.0)
    with pytest.raises(ValueError, match=r"do not overlap.*in EPSG:3857"):
        geo_homography(ref, (100, 100), obs, obs_hw)


def test_degenerate_transform_is_refused():
    flat = _geo(UTM33, Affine(0.5, 0.5, E0, 0.5, 0.5, N0))  # both axes along one direction
    with pytest.raises(ValueError, match="reference's geotransform .* is degenerate"):
        geo_homography(flat, (10, 10), _utm_geo(), (10, 10))
    with pytest.raises(ValueError, match="n must be at least 3"):
        geo_homography(_utm_geo(), (10, 10), _utm_geo(), (10, 10), n=2)


# --- figures -------------------------------------------------------------------------------


@pytest.mark.parametrize("km", [1, 10])
@pytest.mark.parametrize(("crs", "res"), CRS_PAIRS)
def test_residual_figures(crs, res, km):
    """Print the fit residual of each CRS pair (``pytest -s``) for a 1 km and a 10 km scene at
    0.5 m, UTM 33N near 45.1 N 17.8 E."""
    ref = _utm_geo(0.5)
    side = int(km * 2000)
    obs, obs_hw = _reprojected_geo(ref, (side, side), crs, res)
    prior = geo_homography(ref, (side, side), obs, obs_hw)
    print(f"\nEPSG:32633 0.5 m -> {crs} pixel {res}: {km} km scene, obs {obs_hw}: residual max "
          f"{prior.residual_max:.4f} px, RMS {prior.residual_rms:.4f} px, overlap "
          f"{prior.overlap:.3f}")
    assert prior.residual_max < 0.1 * km**2


# --- end to end: a pair in two CRSs through the command -------------------------------------


def test_a_pair_in_two_crss_aligns_from_its_georeferencing(scene, tmp_path):
    """``reblur detect`` on a UTM 33 reference and its reprojection into UTM 34 at 0.7 m
    (turned by about 4 degrees, scaled by 0.5 / 0.7): the georeferencing seeds the
    alignment (recorded in report.json), the final homography agrees with the one PROJ
    implies, and nothing is flagged (the pair holds no change)."""
    import json

    from click.testing import CliRunner

    from reblur.cli import main

    pair = geo_pair(scene, tmp_path, obs_crs="EPSG:32634", obs_resolution=0.7)
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["detect", str(pair.reference), str(pair.observation),
                                  "--out", str(out), "-q"])
    assert r.exit_code == 0, r.output
    rep = json.loads((out / "report.json").read_text())
    prior = rep["options"]["georef_prior"]
    assert prior is not None and prior["residual_max_px"] < 0.1
    # where PROJ puts the reference's corner pixel centres in the observation (centre of
    # pixel (c, r) at transform * (c + 0.5, r + 0.5)), independently of reblur's prior
    with rasterio.open(pair.reference) as a, rasterio.open(pair.observation) as b:
        h, w = a.height, a.width
        cols = np.array([0, w - 1, w - 1, 0], float) + 0.5
        rows = np.array([0, 0, h - 1, h - 1], float) + 0.5
        xs, ys = a.transform * (cols, rows)
        xo, yo = proj_transform(a.crs, b.crs, list(xs), list(ys))
        co, ro = ~b.transform * (np.asarray(xo), np.asarray(yo))
    truth = np.stack([co - 0.5, ro - 0.5], axis=1)
    H = np.asarray(rep["alignment"]["H"])
    p = H @ np.stack([cols - 0.5, rows - 0.5, np.ones(4)])
    assert np.abs((p[:2] / p[2]).T - truth).max() < 1.0
    assert rep["changes"]["changed_fraction_of_known"] < 0.005
