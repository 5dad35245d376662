"""Tests of the test bed's lens distortion and two-plane parallax (reblur.testbed.geometry).

Expected values are computed independently of the code under test: the Brown model's
closed form, plane-induced homographies built here from rotations (scipy) and
translations, a per-pixel loop with matplotlib's point-in-polygon and ``np.linalg.solve``
for the occlusion rule, linear ramps rendered through OpenCV (which read back the sampled
position), and the least-squares scaling of a radial field.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile
from matplotlib.path import Path as PolygonPath
from scipy.spatial.transform import Rotation

from reblur import testbed as tb
from reblur.testbed.scenes import ChangeObject


def _k(shape, f):
    h, w = shape
    return np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])


def _translation(tx: float, ty: float) -> np.ndarray:
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])


def _ramps(shape):
    ys, xs = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    return xs, ys


# ---------------------------------------------------------------- lens


@pytest.mark.parametrize("corner_px, k2", [(3.0, 0.0), (-3.0, 0.0), (3.0, 0.05), (1.5, -0.02)])
def test_lens_moves_the_corners_by_corner_px(corner_px, k2):
    shape = (120, 160)
    f = 1.2 * 160
    r = np.hypot(79.5, 59.5)
    k1 = (corner_px / r - k2 * (r / f) ** 4) / (r / f) ** 2  # Brown's model solved by hand
    lens = tb.Lens.from_corner_px(shape, corner_px, k2=k2)
    assert lens.k1 == pytest.approx(k1, rel=1e-12)
    # render ramps through the lens from a reference 20 px larger: the observation of
    # ramp x (y) is the x (y) each corner pixel samples, whatever the model's code says
    margin = 10.0
    xs, ys = _ramps((shape[0] + 20, shape[1] + 20))
    hs = _translation(-margin, -margin)[None]
    geom = tb.SceneGeometry(hs, lens=lens)
    for ramp, axis in ((xs, 0), (ys, 1)):
        out, _ = tb.render_window(ramp, geom, (0, shape[0], 0, shape[1]))
        for (x, y) in ((0, 0), (159, 0), (0, 119), (159, 119)):
            moved = out[y, x] - margin - (x, y)[axis]
            radial = ((x, y)[axis] - (79.5, 59.5)[axis]) / r
            assert moved == pytest.approx(corner_px * radial, abs=0.05)  # Keys' phase error


def test_barrel_corner_sees_farther_out_and_pincushion_nearer():
    shape = (100, 100)
    for sign in (1.0, -1.0):
        lens = tb.Lens.from_corner_px(shape, 3.0 * sign)
        ux, uy = lens.undistort(np.array([0.0]), np.array([0.0]))
        d_before, d_after = np.hypot(49.5, 49.5), np.hypot(ux[0] - 49.5, uy[0] - 49.5)
        assert d_after - d_before == pytest.approx(3.0 * sign, abs=1e-9)
        assert lens.max_shift() == pytest.approx(3.0, rel=1e-6)


def test_lens_that_folds_the_image_is_refused():
    with pytest.raises(ValueError, match="fold"):
        tb.Lens.from_corner_px((100, 100), -40.0)
    with pytest.raises(ValueError, match="finite"):
        tb.Lens.from_corner_px((100, 100), float("nan"))


# ---------------------------------------------------------------- identity of the zero case


def _shaken_parts(shape, seed):
    rng = np.random.default_rng(seed)
    path = tb.random_camera_path(shape, rng, max_shift_px=4.0)
    turn, shift = tb.viewpoint_parts(shape, rng, shift_px=6.0, angle_deg=0.5, perspective=1.0)
    return path, turn, shift, tb.compose(tb.view_from_parts(turn, shift), path.homographies())


def test_zero_distortion_and_zero_parallax_render_as_the_plain_renderer():
    ref = np.random.default_rng(0).random((150, 170))
    path, turn, shift, hs = _shaken_parts(ref.shape, 1)
    square = [[40.0, 30.0], [120.0, 30.0], [120.0, 110.0], [40.0, 110.0]]
    geom = tb.SceneGeometry(hs, lens=tb.Lens.from_corner_px(ref.shape, 0.0),
                            region=tb.Region(square, 1.0),
                            region_homographies=tb.region_homographies(path, turn, shift, 1.0))
    plain, plain_valid = tb.render_window(ref, hs, (0, 150, 0, 170))
    out, valid = tb.render_window(ref, geom, (0, 150, 0, 170))
    np.testing.assert_array_equal(out, plain)
    np.testing.assert_array_equal(valid, plain_valid)
    assert not geom.occlusion_window((0, 150, 0, 170), band_px=2.0).any()
    np.testing.assert_allclose(geom.centroid(np.array([[10.0, 20.0], [85.0, 70.0]])),
                               tb.true_centroid(hs, np.array([[10.0, 20.0], [85.0, 70.0]])),
                               atol=1e-9)


def test_pair_with_zero_geometry_equals_the_plain_pair():
    scene = np.random.default_rng(2).random((200, 220))
    kw = dict(bits=16, noise_dn=1.0, n_changes=2, seed=5, changes={"size_px": (10.0, 20.0)})
    plain = tb.make_pair(scene, **kw)
    zero = tb.make_pair(scene, lens={"corner_px": 0.0}, parallax={"parallax_px": 0.0}, **kw)
    for name in ("reference", "observed", "truth", "valid"):
        np.testing.assert_array_equal(getattr(zero, name), getattr(plain, name))
    assert not zero.occlusion.any() and plain.geometry is None


# ---------------------------------------------------------------- parallax


def _plane_homography(k, rot, t, n, d):
    h = k @ (rot + np.outer(t, n) / d) @ np.linalg.inv(k)
    return h / h[2, 2]


def test_second_plane_follows_its_own_plane_induced_homography():
    shape, f = (200, 240), 300.0
    k = _k(shape, f)
    rot = Rotation.from_euler("xyz", [0.8, -0.6, 0.4], degrees=True).as_matrix()  # Rz Ry Rx
    t = np.array([0.05, -0.03, 0.0])  # T / d, the view's translation over the ground depth
    n = rot.T @ [0.0, 0.0, 1.0]  # ground normal in the reference camera
    s = 1.25  # the roof at 1 / 1.25 of the ground's distance
    poses = np.array([[1.5, -0.7, 0.004, 0.05, -0.03, 0.1], [-0.8, 1.1, -0.002, -0.02, 0.04, -0.2]])
    poses = np.repeat(poses, 32, axis=0)
    path = tb.CameraPath(poses=poses, shape=shape, focal=f)
    turn = k @ rot @ np.linalg.inv(k)
    turn /= turn[2, 2]
    shift = f * t[:2]
    ground = tb.compose(tb.view_from_parts(turn, shift), path.homographies())
    roof = tb.region_homographies(path, turn, shift, s)
    for j in (0, 40):
        px, py, pz, a, b, c = poses[j]
        rk = Rotation.from_euler("xyz", [a, b, c], degrees=True).as_matrix()
        tk = np.array([px / f, py / f, pz])
        e3 = np.array([0.0, 0.0, 1.0])
        want_g = _plane_homography(k, rk, tk, e3, 1.0) @ _plane_homography(k, rot, t, n, 1.0)
        want_r = _plane_homography(k, rk, tk, e3, 1 / s) @ _plane_homography(k, rot, t, n, 1 / s)
        np.testing.assert_allclose(ground[j], want_g / want_g[2, 2], atol=1e-10)
        np.testing.assert_allclose(roof[j], want_r / want_r[2, 2], atol=1e-10)
    # the truth inside the roof is that plane's centroid, outside the ground's
    poly = np.array([[60.0, 50.0], [180.0, 50.0], [180.0, 150.0], [60.0, 150.0]])
    geom = tb.SceneGeometry(ground, region=tb.Region(poly, s), region_homographies=roof)
    inside, outside = np.array([[120.0, 100.0]]), np.array([[15.0, 180.0]])
    np.testing.assert_allclose(geom.centroid(inside), tb.true_centroid(roof, inside), atol=1e-9)
    np.testing.assert_allclose(geom.centroid(outside), tb.true_centroid(ground, outside),
                               atol=1e-9)


def test_parallax_px_is_the_displacement_between_the_planes():
    scene = np.random.default_rng(3).random((256, 256))
    plan = tb.plan_pair(scene, n_changes=0, seed=4, parallax={"parallax_px": 4.0})
    region = plan.geometry.region
    shift = np.array(plan.info["view_shift"])
    still = tb.CameraPath(poses=np.zeros((64, 6)), shape=(256, 256), focal=plan.path.focal)
    turn = np.linalg.inv(tb.translation(*shift)) @ plan.view  # the view's own turn
    ground = tb.view_from_parts(turn, shift)
    roof = tb.region_homographies(still, turn, shift, region.scale)[0]
    pts = np.array([[10.0, 10.0, 1.0], [128.0, 77.0, 1.0], [250.0, 200.0, 1.0]]).T
    g, r = ground @ pts, roof @ pts
    moved = r[:2] / r[2] - g[:2] / g[2]
    np.testing.assert_allclose(np.hypot(*moved), 4.0, atol=1e-9)
    np.testing.assert_allclose(moved / 4.0, (shift / np.hypot(*shift))[:, None] @ np.ones((1, 3)),
                               atol=1e-9)  # along the view's translation: a roof comes nearer
    assert region.scale > 1 and region.parallax_px == 4.0
    pit = tb.plan_pair(scene, n_changes=0, seed=4, parallax={"parallax_px": -4.0})
    assert pit.geometry.region.scale == pytest.approx(2 - region.scale)


def _brute_force_sources(geom, lens, ground, roof, poly, scale, x, y):
    """Per sub-pose sources of one observation pixel by the rule, written out: the nearer
    plane is seen where its own mapping lands in its region."""
    inside = PolygonPath(poly).contains_point
    dx, dy = x - lens.centre[0], y - lens.centre[1]
    rho2 = (dx * dx + dy * dy) / lens.focal ** 2
    g = 1 + lens.k1 * rho2 + lens.k2 * rho2 ** 2
    u = np.array([lens.centre[0] + dx * g, lens.centre[1] + dy * g, 1.0])
    out, seen_any, seen_all, hidden = [], False, True, False
    for hg, hr in zip(ground, roof, strict=True):
        a, b = np.linalg.solve(hg, u), np.linalg.solve(hr, u)
        a, b = a[:2] / a[2], b[:2] / b[2]
        if scale > 1:
            seen = inside(b)
            hidden |= (not seen) and inside(a)
        else:
            seen = inside(a)
            hidden |= seen and not inside(b)
        out.append(b if seen else a)
        seen_any, seen_all = seen_any or seen, seen_all and seen
    return np.array(out), (seen_any and not seen_all) or hidden


@pytest.mark.parametrize("scale", [1.3, 0.75])
def test_truth_occlusion_and_render_match_a_brute_force_of_the_rule(scale):
    shape = (48, 64)
    rng = np.random.default_rng(7)
    path = tb.random_camera_path(shape, rng, max_shift_px=3.0, n_sub=64)
    path = tb.CameraPath(poses=path.poses[::8], shape=shape, focal=path.focal)  # 8 sub-poses
    turn, shift = tb.viewpoint_parts(shape, rng, shift_px=12.0, angle_deg=0.5, perspective=1.0)
    ground = tb.compose(tb.view_from_parts(turn, shift), path.homographies())
    roof = tb.region_homographies(path, turn, shift, scale)
    poly = np.array([[20.0, 14.0], [46.0, 18.0], [40.0, 36.0], [30.0, 30.0], [18.0, 34.0]])
    lens = tb.Lens.from_corner_px(shape, 2.0)
    geom = tb.SceneGeometry(ground, lens=lens, region=tb.Region(poly, scale),
                            region_homographies=roof)
    ys, xs = np.mgrid[0:48, 0:64]
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    want, want_occ = zip(*(_brute_force_sources(geom, lens, ground, roof, poly, scale, x, y)
                           for x, y in pts), strict=True)
    want = np.stack(want, axis=1)  # (n_sub, m, 2)
    np.testing.assert_allclose(geom.sources(pts), want, atol=1e-2 / 256 + 1e-9)
    np.testing.assert_allclose(geom.centroid(pts), want.mean(axis=0), atol=1e-2)
    occ = geom.occlusion_window((0, 48, 0, 64))
    assert np.mean(occ.ravel() != np.array(want_occ)) < 0.003  # ties at 1/256 px rounding
    assert occ.any()
    # the renderer samples what the truth says: a ramp reads back the sampled position
    ref_x, ref_y = _ramps((60, 80))
    for ramp, axis in ((ref_x, 0), (ref_y, 1)):
        out, valid = tb.render_window(ramp, geom, (0, 48, 0, 64))
        err = out.ravel() - want[:, :, axis].mean(axis=0)
        assert valid.mean() > 0.6 and np.abs(err[valid.ravel()]).max() < 0.05
    # the change truth is the half-maximum of the sources inside an object
    obj = ChangeObject("rect", 30.0, 24.0, 0.3, 9.0, 6.0, 0.0, (), 0.2, 0.5)
    boxes = geom.change_boxes((obj,))
    truth = geom.truth_window((obj,), (0, 48, 0, 64), boxes)
    inside = obj.contains(want[..., 0], want[..., 1]).mean(axis=0) >= 0.5
    np.testing.assert_array_equal(truth.ravel(), inside)


# ---------------------------------------------------------------- the one-homography floor


def test_best_homography_is_exact_on_a_homography_and_leaves_the_lens_radial_field():
    shape = (101, 101)
    hs = tb.pose_homography(shape, (2.0, -1.0, 0.003, 0.1, -0.2, 0.3))[None]
    ys, xs = np.mgrid[0:101:10, 0:101:10]
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    plain = tb.SceneGeometry(hs)
    h = tb.best_homography(plain, pts)
    assert np.abs(tb.homography_residual(plain, pts, h)).max() < 1e-6
    lens = tb.Lens.from_corner_px(shape, 3.0)
    geom = tb.SceneGeometry(np.eye(3)[None], lens=lens)
    res = tb.homography_residual(geom, pts, tb.best_homography(geom, pts))
    # least squares of u(p) = c + (1 + kappa) d over a symmetric square lattice: a scaling
    # about the centre by 1 + sum(kappa |d|^2) / sum(|d|^2); the rest is the residual
    d = pts - 50.0
    kappa = lens.k1 * (d ** 2).sum(axis=1) / lens.focal ** 2
    sigma = (kappa * (d ** 2).sum(axis=1)).sum() / (d ** 2).sum()
    np.testing.assert_allclose(res, (kappa - sigma)[:, None] * d, atol=1e-6)
    assert np.hypot(*res.T).max() > 1.0


# ---------------------------------------------------------------- pairs and cases


def test_geometry_pair_writes_its_occlusion_and_truth(tmp_path):
    scene = np.random.default_rng(8).random((300, 280))
    kw = dict(bits=8, noise_dn=1.0, n_changes=3, seed=9, changes={"size_px": (10.0, 24.0)},
              lens={"corner_px": -2.0}, parallax={"parallax_px": 3.0})
    mem = tb.make_pair(scene, **kw)
    info = tb.write_pair(tmp_path, scene, **kw)
    assert "occlusion.tif" in info["files"]
    np.testing.assert_array_equal(tifffile.imread(tmp_path / "occlusion.tif") > 0, mem.occlusion)
    np.testing.assert_array_equal(tifffile.imread(tmp_path / "observed.tif"), mem.observed)
    saved = json.loads((tmp_path / "pair.json").read_text())
    assert saved["geometry"]["lens"]["k1"] == mem.geometry.lens.k1 < 0
    assert saved["geometry"]["region"]["parallax_px"] == 3.0
    assert mem.truth.any() and mem.occlusion.any() and mem.occlusion.mean() < 0.1
    # the occlusion edge lies on the roof's outline as the observation sees it
    poly = np.array(saved["geometry"]["region"]["polygon"])
    ys, xs = np.nonzero(mem.occlusion)
    near = mem.geometry.centroid(np.stack([xs, ys], axis=1).astype(float))
    outline = _outline(poly)
    dist = np.hypot(*(near[::7, None] - outline[None]).transpose(2, 0, 1)).min(axis=1)
    assert np.median(dist) < 3.0


def _outline(poly, step=0.5):
    pts = []
    for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        n = int(np.ceil(np.hypot(*(b - a)) / step))
        pts.append(a + (b - a) * np.linspace(0, 1, n, endpoint=False)[:, None])
    return np.concatenate(pts)


def test_geometry_options_are_validated():
    scene = np.random.default_rng(0).random((128, 128))
    with pytest.raises(ValueError, match="lens takes"):
        tb.plan_pair(scene, n_changes=0, lens={"k1": 0.1})
    with pytest.raises(ValueError, match="parallax takes"):
        tb.plan_pair(scene, n_changes=0, parallax={"depth": 2.0})
    with pytest.raises(ValueError, match="no translation"):
        tb.plan_pair(scene, n_changes=0, parallax={"parallax_px": 2.0},
                     viewpoint={"shift_px": 0.0, "angle_deg": 0.0, "perspective": 0.0})
    with pytest.raises(ValueError, match="polygon"):
        tb.Region(np.zeros((2, 2)), 1.2)


def test_geometry_cases_are_named_and_planned():
    assert set(tb.GEOMETRY_CASES) <= set(tb.CASES)
    assert tb.GEOMETRY_CASES["lens3"][0] == {"lens": {"corner_px": 3.0}}
    assert tb.GEOMETRY_CASES["parallax"][0] == {"parallax": {"parallax_px": 4.0}}
    assert tb.GEOMETRY_CASES["parallax_changes"][1] > 0 == tb.GEOMETRY_CASES["parallax"][1]
