"""Pose grid: sizes, homographies against analytic values, crop geometry."""

import cv2
import numpy as np
import pytest

from reblur.grid import PoseGrid, local_homography, map_points, pose_homography, rotation_step_for
from reblur.warp import warp_window


def test_paper_grid():
    g = PoseGrid.paper((1000, 2000))
    assert g.size == 25 * 25 * 13 == 8125
    assert g.shape == (13, 25, 25)
    assert g.center == (999.5, 499.5)
    np.testing.assert_allclose(g.rz, np.arange(-3, 3.01, 0.5))
    assert g.integer_translations
    assert "8125 poses" in repr(g)


def test_rotation_about_principal_point_analytic():
    c = (40.0, 30.0)
    H = pose_homography(rz=90.0, center=c)
    # the principal point is fixed; (c + (10, 0)) goes to (c + (0, 10)) for the (x, y) convention
    np.testing.assert_allclose(map_points(H, np.array([c])), [c], atol=1e-12)
    np.testing.assert_allclose(map_points(H, np.array([[50.0, 30.0]])), [[40.0, 40.0]], atol=1e-12)
    H = pose_homography(tx=3, ty=-2, rz=90.0, center=c)
    np.testing.assert_allclose(map_points(H, np.array([[50.0, 30.0]])), [[43.0, 38.0]], atol=1e-12)


def test_out_of_plane_homography_is_KRKinv():
    f, c = 800.0, (320.0, 240.0)
    H = pose_homography(rx=1.0, ry=-0.5, rz=0.3, tz=0.01, center=c, focal=f)
    # a point on the optical axis direction d = K^-1 x, rotated, scaled, reprojected
    a, b, g = np.deg2rad([1.0, -0.5, 0.3])
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    Rz = np.array([[np.cos(g), -np.sin(g), 0], [np.sin(g), np.cos(g), 0], [0, 0, 1]])
    x = np.array([100.0, 50.0])
    d = np.array([(x[0] - c[0]) / f, (x[1] - c[1]) / f, 1.0])
    e = Rz @ Ry @ Rx @ d
    y = np.array([f * e[0] / e[2], f * e[1] / e[2]]) * 1.01 + np.array(c)
    np.testing.assert_allclose(map_points(H, x[None])[0], y, atol=1e-9)
    with pytest.raises(ValueError, match="focal"):
        pose_homography(rx=1.0, center=c)


def test_grid_validation():
    with pytest.raises(ValueError, match="repeated"):
        PoseGrid((10, 10), tx=[0, 0], ty=[0])
    with pytest.raises(ValueError, match="focal"):
        PoseGrid((10, 10), tx=[0], ty=[0], rx=[0, 1])
    g = PoseGrid((10, 10), tx=[0, 1], ty=[0])
    with pytest.raises(ValueError, match="poses"):
        g.check_weights(np.ones(3))
    with pytest.raises(ValueError, match="non-negative"):
        g.check_weights(-np.ones(2))


def test_rotation_step_moves_corner_one_pixel():
    shape = (6680, 6680)
    step = rotation_step_for(shape, 1.0)
    g = PoseGrid.from_ranges(shape, t_max=0, rz_max=0.3, corner_px=1.0)
    H = g.base_homography(g.n_bases // 2 + 1)  # one step from zero
    corner = np.array([[0.0, 0.0]])
    moved = np.hypot(*(map_points(H, corner) - corner)[0])
    assert abs(moved - 1.0) < 1e-3
    assert g.rz[1] - g.rz[0] == pytest.approx(step)


def test_crop_keeps_full_image_geometry(levir_gray):
    """A crop warped with its offset equals the crop of the full-image warp; re-centring differs."""
    img = levir_gray.astype(np.float32)
    g = PoseGrid((1024, 1024), tx=[3], ty=[-2], rz=[2.0])
    H = g.homography(0)
    full = cv2.warpPerspective(img, H, (1024, 1024), flags=cv2.INTER_LINEAR)
    y0, x0, h, w = 100, 650, 200, 240
    crop, valid = warp_window(img, H, (y0, x0, h, w))
    ref = full[y0 : y0 + h, x0 : x0 + w]
    assert valid.all()
    assert np.max(np.abs(crop[:, :, 0] - ref)) < 2e-3  # OpenCV's 1/32-px coordinate quantisation
    # re-centring the grid on the crop (wrong) gives a visibly different warp
    wrong = PoseGrid((h, w), tx=[3], ty=[-2], rz=[2.0]).homography(0)
    M = local_homography(wrong, (0, 0), (0, 0))
    bad = cv2.warpPerspective(np.ascontiguousarray(img[y0 : y0 + h, x0 : x0 + w]), M, (w, h))
    assert np.mean(np.abs(bad[20:-20, 20:-20] - ref[20:-20, 20:-20])) > 0.02


def test_mean_source_points_is_the_weighted_mean_of_the_inverse_maps():
    from reblur.grid import mean_source_points, translation

    pts = np.array([[10.0, 20.0], [300.0, 5.5]])
    # two translations by (+2, 0) and (-1, +3) with weights 2 : 1 (a gain of 3 in all):
    # the sources are pts - t, weighted -> pts - (2*(2, 0) + 1*(-1, 3)) / 3
    Hs = [translation(2.0, 0.0), translation(-1.0, 3.0)]
    got = mean_source_points(Hs, [2.0, 1.0], pts)
    np.testing.assert_allclose(got, pts - np.array([1.0, 1.0]), atol=1e-12)
    with pytest.raises(ValueError, match="no pose"):
        mean_source_points(Hs, [0.0, 0.0], pts)


def test_carry_weights_matches_a_pose_by_pose_copy():
    """Weights carried between grids that share some poses (a tz x rz grid and a part of
    it with a translation range of its own), both ways, against a pose-by-pose copy by
    values (slow reference): shared poses keep their weight, the others get 0."""
    from reblur.grid import carry_weights

    full = PoseGrid((300, 400), tx=np.arange(-3, 4), ty=np.arange(-2, 3),
                    rz=[-1.0, -0.5, 0.0, 0.5, 1.0], tz=[-0.01, 0.0, 0.01])
    part = PoseGrid((300, 400), tx=np.arange(-1, 6), ty=[0, 1, 2, 3],
                    rz=[-0.5, 1.0, 2.0], tz=[0.0, 0.01])
    rng = np.random.default_rng(4)

    def slow(w, src, dst):
        out = np.zeros(dst.shape)
        for b, base in enumerate(dst.bases):
            for i, ty in enumerate(dst.ty):
                for j, tx in enumerate(dst.tx):
                    if base in src.bases and ty in src.ty and tx in src.tx:
                        out[b, i, j] = w[src.bases.index(base), src.ty.index(ty),
                                         src.tx.index(tx)]
        return out

    for src, dst in ((full, part), (part, full)):
        w = rng.random(src.shape)
        got = carry_weights(w, src, dst)
        np.testing.assert_array_equal(got, slow(w, src, dst))
        assert 0 < np.count_nonzero(got) < got.size
