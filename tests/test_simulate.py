"""Tests of the simulator (reblur.simulate) against independent computations."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import zarr
from scipy import ndimage

from reblur.grid import PoseGrid, map_points
from reblur.simulate import (
    CameraPath,
    add_noise,
    blur_along_path,
    blur_along_path_tiled,
    blur_weights,
    grid_path,
    make_pair,
    moving_object,
    paste_changes,
    random_camera_path,
    to_float,
    viewpoint_homography,
)
from reblur.warp import Box

LEVIR_A = Path(__file__).resolve().parents[2] / "shared" / "data" / "levir_whu_1024"
LEVIR_A = LEVIR_A / "samples_LEVIR" / "A"


def _levir(i: int = 0) -> np.ndarray:
    files = sorted(LEVIR_A.glob("*.png"))
    assert files, f"real test imagery missing: {LEVIR_A}"
    img = cv2.imread(str(files[i]))
    assert img is not None
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0


@pytest.fixture(scope="module")
def levir() -> np.ndarray:
    return _levir(0)


def _centre(shape) -> tuple[float, float]:
    return ((shape[1] - 1) / 2.0, (shape[0] - 1) / 2.0)


# --------------------------------------------------------------------------- helpers
def test_to_float():
    a8 = np.array([[0, 128, 255]], np.uint8)
    f, s = to_float(a8)
    assert f.dtype == np.float32 and s == 255.0
    np.testing.assert_allclose(f, [[0.0, 128 / 255, 1.0]], rtol=1e-6)
    a16 = np.array([0, 65535, 32768], np.uint16)
    f, s = to_float(a16)
    assert s == 65535.0
    np.testing.assert_allclose(f, [0.0, 1.0, 32768 / 65535], rtol=1e-6)
    ff = np.array([0.25, 0.5])
    f, s = to_float(ff)
    assert s == 1.0 and f.dtype == np.float32
    np.testing.assert_array_equal(f, [0.25, 0.5])
    with pytest.raises(TypeError):
        to_float(np.array([1, -1], np.int16))


def test_add_noise_statistics():
    img = np.full((200, 200), 0.5, np.float32)
    out = add_noise(img, 0.02, 5)
    assert out.dtype == np.float32 and out.shape == img.shape
    assert abs(float((out - 0.5).std()) - 0.02) < 0.001
    assert abs(float((out - 0.5).mean())) < 0.001
    np.testing.assert_array_equal(out, add_noise(img, 0.02, 5))  # seeded
    assert np.all(img == 0.5)  # input untouched
    clipped = add_noise(np.ones((50, 50)), 0.1, 1)
    assert clipped.max() <= 1.0 and clipped.min() < 1.0


# --------------------------------------------------------------------------- camera paths
def test_random_camera_path_extent_smooth_offgrid():
    c = (255.5, 199.5)
    p = random_camera_path(1, center=c, n_samples=64, t_max=6.0, rz_max=1.5)
    assert p.poses.shape == (64, 6) and p.center == c
    e = p.extent()
    assert e["tx"] == pytest.approx(6.0) and e["ty"] == pytest.approx(6.0)
    assert e["rz"] == pytest.approx(1.5)
    assert e["tz"] == e["rx"] == e["ry"] == 0.0
    np.testing.assert_array_equal(p.poses[0], 0.0)  # starts at the identity
    # smooth: consecutive samples move a small part of the range, and the curvature is small
    d1 = np.abs(np.diff(p.poses[:, [0, 1, 5]], axis=0)).max(axis=0)
    d2 = np.abs(np.diff(p.poses[:, [0, 1, 5]], n=2, axis=0)).max(axis=0)
    assert np.all(d1 < 0.2 * np.array([12.0, 12.0, 3.0]))
    assert np.all(d2 < 0.1 * d1)
    # off-grid: sub-pixel translations, angles not multiples of 0.5 degrees
    frac = np.abs(p.poses[1:, :2] - np.round(p.poses[1:, :2]))
    assert np.mean(frac > 0.01) > 0.9
    assert np.mean(np.abs(p.poses[1:, 5] / 0.5 - np.round(p.poses[1:, 5] / 0.5)) > 0.01) > 0.7
    # seeded and varied
    np.testing.assert_array_equal(
        p.poses, random_camera_path(1, center=c, t_max=6.0, rz_max=1.5).poses
    )
    q = random_camera_path(2, center=c, t_max=6.0, rz_max=1.5)
    assert not np.allclose(p.poses, q.poses)
    # more axes
    r = random_camera_path(
        np.random.default_rng(3), center=c, n_samples=10, tz_max=0.01, rxy_max=0.2, focal=800.0
    )
    assert r.extent()["tz"] == pytest.approx(0.01) and r.extent()["ry"] == pytest.approx(0.2)
    assert len(r.homographies()) == 10
    with pytest.raises(ValueError):
        random_camera_path(0, center=c, rxy_max=0.2)


def test_camera_path_dict_roundtrip():
    p = random_camera_path(
        4, center=(10.0, 20.5), n_samples=7, tz_max=0.01, rxy_max=0.1, focal=500.0
    )
    q = CameraPath.from_dict(json.loads(json.dumps(p.to_dict())))
    np.testing.assert_array_equal(p.poses, q.poses)
    assert q.center == p.center and q.focal == p.focal
    for a, b in zip(p.homographies(), q.homographies(), strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError):
        CameraPath(np.zeros((3, 5)), (0.0, 0.0))


def _neighbours(a, b) -> bool:
    return int(np.abs(np.asarray(a) - np.asarray(b)).sum()) == 1


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_grid_path_connected(seed):
    grid = PoseGrid.paper((300, 300))
    w, idx = grid_path(grid, seed, 20, return_indices=True)
    assert w.shape == grid.shape
    assert np.count_nonzero(w) == 20 and len({tuple(i) for i in idx}) == 20
    assert np.all(w >= 0) and w.sum() == pytest.approx(1.0)
    assert np.all(w[idx[:, 0], idx[:, 1], idx[:, 2]] > 0)
    assert all(_neighbours(idx[k], idx[k + 1]) for k in range(19))
    # independent check: the support is one 6-connected component
    _, ncomp = ndimage.label(w > 0, structure=ndimage.generate_binary_structure(3, 1))
    assert ncomp == 1
    # starts near the centre
    assert np.abs(idx[0] - np.array(grid.shape) // 2).max() <= 1
    np.testing.assert_array_equal(w, grid_path(grid, seed, 20))  # seeded


def test_grid_path_small_grid_and_limits():
    grid = PoseGrid((50, 50), tx=[0, 1, 2], ty=[0, 1, 2])
    w, idx = grid_path(grid, 7, 9, return_indices=True)  # a Hamiltonian path of the 3x3
    assert np.all(w > 0) and w.sum() == pytest.approx(1.0)
    assert all(_neighbours(idx[k], idx[k + 1]) for k in range(8))
    with pytest.raises(ValueError):
        grid_path(grid, 0, 10)


# --------------------------------------------------------------------------- blurring
def test_single_pose_equals_cv2_rigid_warp(levir):
    img = levir[100:340, 200:520]  # 240 x 320
    h, w = img.shape[:2]
    c = _centre(img.shape)
    tx, ty, rz = 3.25, -2.5, 1.5
    path = CameraPath(np.array([[tx, ty, 0, 0, 0, rz]]), c)
    out, valid = blur_along_path(img, path)
    # independent: OpenCV's rotation matrix (positive angle = counter-clockwise on screen,
    # i.e. rz = -angle in reblur's convention) plus the translation
    M = cv2.getRotationMatrix2D(c, -rz, 1.0)
    M[:, 2] += (tx, ty)
    ref = cv2.warpAffine(img, M, (w, h), flags=cv2.INTER_LINEAR)
    inner = (slice(15, h - 15), slice(15, w - 15))
    assert valid[inner].all()
    err = np.abs(out[inner] - ref[inner])
    assert err.mean() < 2e-3 and err.max() < 0.05
    # a wrong sign of the rotation would be far off
    M2 = cv2.getRotationMatrix2D(c, rz, 1.0)
    M2[:, 2] += (tx, ty)
    wrong = cv2.warpAffine(img, M2, (w, h), flags=cv2.INTER_LINEAR)
    assert np.abs(out[inner] - wrong[inner]).mean() > 10 * err.mean()
    # valid: where the back-mapped pixel lies inside the reference (independent geometry;
    # 1/8 px slack for the bilinear footprint's rounding)
    yy, xx = np.mgrid[0:h, 0:w]
    src = map_points(np.linalg.inv(path.homographies()[0]), np.c_[xx.ravel(), yy.ravel()])
    sx, sy = src[:, 0].reshape(h, w), src[:, 1].reshape(h, w)
    e = 0.125
    surely_in = (sx > e) & (sx < w - 1 - e) & (sy > e) & (sy < h - 1 - e)
    surely_out = (sx < -e) | (sx > w - 1 + e) | (sy < -e) | (sy > h - 1 + e)
    assert valid[surely_in].all() and not valid[surely_out].any()
    assert surely_out.sum() > 0.02 * h * w  # the rotated, shifted frame leaves gaps


def test_integer_translation_path_equals_shift_average():
    rng = np.random.default_rng(0)
    img = rng.random((60, 80)).astype(np.float32)
    shifts = [(0, 0), (1, 0), (2, 1), (3, 1), (3, 2), (-2, -1)]  # (tx, ty)
    path = CameraPath(np.array([[tx, ty, 0, 0, 0, 0] for tx, ty in shifts], float), (0, 0))
    out, valid = blur_along_path(img, path)
    assert out.shape == img.shape and out.dtype == np.float32
    # independent: warp(f, T(t))(x) = f(x - t) on a zero-padded copy
    P = 5
    pad = np.pad(img, P)
    inside = np.pad(np.ones_like(img, bool), P)
    expect = np.zeros_like(img, dtype=np.float64)
    expect_valid = np.ones(img.shape, bool)
    for tx, ty in shifts:
        expect += pad[P - ty : P - ty + 60, P - tx : P - tx + 80]
        expect_valid &= inside[P - ty : P - ty + 60, P - tx : P - tx + 80]
    expect /= len(shifts)
    np.testing.assert_array_equal(valid, expect_valid)
    np.testing.assert_allclose(out[valid], expect[valid], atol=1e-6)
    # a sub-window gives the same values (full-image geometry is kept in crops)
    sub, vsub = blur_along_path(img, path, Box(10, 20, 30, 40))
    np.testing.assert_allclose(sub, out[10:40, 20:60], atol=1e-6)
    np.testing.assert_array_equal(vsub, valid[10:40, 20:60])


def test_blur_weights_matches_warps_and_path(levir):
    img = levir[300:460, 500:700]  # 160 x 200, RGB
    grid = PoseGrid.from_ranges(img.shape[:2], t_max=3, rz_max=1.0, rz_step=0.5)
    c = grid.center
    # one-hot: equals an independent cv2 rotation + translation
    w = np.zeros(grid.shape)
    b, iy, ix = 4, 1, 5  # rz = +1.0, ty = -2, tx = +2
    w[b, iy, ix] = 1.0
    out, valid = blur_weights(img, grid, w)
    assert grid.bases[b][3] == 1.0 and grid.ty[iy] == -2 and grid.tx[ix] == 2
    M = cv2.getRotationMatrix2D(c, -1.0, 1.0)
    M[:, 2] += (2.0, -2.0)
    ref = cv2.warpAffine(img, M, (200, 160), flags=cv2.INTER_LINEAR)
    inner = (slice(10, 150), slice(10, 190))
    assert valid[inner].all()
    err = np.abs(out[inner] - ref[inner])
    assert err.mean() < 2e-3 and err.max() < 0.05
    # two poses: linear combination
    w2 = np.zeros(grid.shape)
    w2[b, iy, ix], w2[0, 3, 3] = 0.3, 0.7
    out2, _ = blur_weights(img, grid, w2)
    single, _ = blur_weights(img, grid, (w2 > 0.5).astype(float))
    np.testing.assert_allclose(out2, 0.3 * out + 0.7 * single, atol=1e-5)
    # equal weights on a grid path == blur_along_path through the same poses (other code)
    wp, idx = grid_path(grid, 3, 8, return_indices=True)
    wp = (wp > 0) / 8.0
    poses = np.array([[grid.tx[i], grid.ty[j], 0, 0, 0, grid.bases[k][3]] for k, j, i in idx])
    viaw, vw = blur_weights(img, grid, wp)
    viap, vp = blur_along_path(img, CameraPath(poses, c))
    np.testing.assert_allclose(viaw, viap, atol=1e-5)
    np.testing.assert_array_equal(vw, vp)
    with pytest.raises(ValueError):
        blur_weights(img, grid, np.ones(3))


def test_base_homography_is_applied_first():
    rng = np.random.default_rng(1)
    img = ndimage.gaussian_filter(rng.random((90, 110)), 2).astype(np.float32)
    c = _centre(img.shape)
    V = viewpoint_homography(2, img.shape, max_shift_frac=0.03, max_rot_deg=3.0)
    path = CameraPath(np.array([[2.0, -1.0, 0, 0, 0, 0.7]]), c)
    out, valid = blur_along_path(img, path, base=V)
    H = path.homographies()[0] @ V
    ref = cv2.warpPerspective(img, H, (110, 90), flags=cv2.INTER_LINEAR)
    assert valid.mean() > 0.6
    assert np.abs(out[valid] - ref[valid]).max() < 0.02
    wrong = cv2.warpPerspective(img, V @ path.homographies()[0], (110, 90))
    assert np.abs(out[valid] - wrong[valid]).max() > 0.02


class _CountingArray:
    """Array-like wrapper that records the area of every read."""

    def __init__(self, a):
        self.a, self.shape, self.dtype, self.reads = a, a.shape, a.dtype, []

    def __getitem__(self, key):
        part = self.a[key]
        self.reads.append(part.shape[0] * part.shape[1])
        return part


def test_tiled_equals_whole(levir):
    img = levir[:700, 50:950]  # 700 x 900 RGB
    c = _centre(img.shape)
    path = random_camera_path(5, center=c, n_samples=16, t_max=6.0, rz_max=1.0)
    V = viewpoint_homography(6, img.shape, max_shift_frac=0.02, max_rot_deg=2.0)
    whole, vwhole = blur_along_path(img, path, base=V)
    counted = _CountingArray(img)
    out = np.full(img.shape, -1.0, np.float32)
    vout = np.zeros(img.shape[:2], bool)
    res = blur_along_path_tiled(counted, path, out, base=V, tile=256, valid_out=vout)
    assert res is out
    # OpenCV computes float32 warp coordinates in single precision: the whole-frame warp
    # (coordinates up to ~900) and the tile-local one differ by ~1e-4 px, i.e. ~1e-5 in value
    # (a real bug -- a wrong offset or centre -- is off by ~1e-1)
    d = np.abs(out - whole)
    assert d.max() < 5e-5 and d.mean() < 1e-6
    np.testing.assert_array_equal(vout, vwhole)
    # every read is one tile grown by the blur's reach (6 px, 1 deg at r ~ 570: 10 px,
    # 2 deg of viewpoint at r ~ 570: 20 px, 2 % shift: 18 px), never the whole image
    assert len(counted.reads) == 12  # 3 x 4 tiles, one read each
    assert max(counted.reads) < (256 + 2 * 60) ** 2 < img.shape[0] * img.shape[1] / 3


def test_tiled_zarr_grayscale(levir):
    img = levir[:300, :340].mean(axis=2).astype(np.float32)
    zref = zarr.zeros(shape=img.shape, chunks=(128, 128), dtype="f4")
    zref[:] = img
    zout = zarr.zeros(shape=img.shape, chunks=(100, 100), dtype="f4")
    path = random_camera_path(8, center=_centre(img.shape), n_samples=8, t_max=4, rz_max=0.5)
    blur_along_path_tiled(zref, path, zout, tile=100)
    whole, _ = blur_along_path(img, path)
    np.testing.assert_allclose(zout[:], whole, atol=5e-5)
    # ... and exactly equal to the same tiling done in memory
    mem = blur_along_path_tiled(img, path, np.zeros(img.shape, np.float32), tile=100)
    np.testing.assert_array_equal(zout[:], mem)
    with pytest.raises(ValueError):
        blur_along_path_tiled(zref, path, np.zeros((300, 340, 3), np.float32))


# --------------------------------------------------------------------------- viewpoint
def test_viewpoint_homography_bounds():
    shape = (400, 600)
    c = np.array(_centre(shape))
    corners = np.array([[0, 0], [599, 0], [599, 399], [0, 399]], float)
    angles, shifts = [], []
    for seed in range(40):
        H = viewpoint_homography(seed, shape, max_shift_frac=0.05, max_rot_deg=5.0, max_scale=0.02)
        assert H[2, 2] == pytest.approx(1.0)
        np.testing.assert_allclose(H[2, :2], 0.0, atol=1e-15)  # affine without perspective
        A = H[:2, :2]
        k = np.sqrt(np.linalg.det(A))
        ang = np.degrees(np.arctan2(A[1, 0], A[0, 0]))
        np.testing.assert_allclose(
            A,
            k
            * np.array(
                [
                    [np.cos(np.radians(ang)), -np.sin(np.radians(ang))],
                    [np.sin(np.radians(ang)), np.cos(np.radians(ang))],
                ]
            ),
            atol=1e-12,
        )
        assert abs(k - 1) <= 0.02 and abs(ang) <= 5.0
        s = map_points(H, c[None])[0] - c
        assert abs(s[0]) <= 0.05 * 600 and abs(s[1]) <= 0.05 * 400
        angles.append(ang)
        shifts.append(s)
    # the bounds are used, not just respected
    assert max(np.abs(angles)) > 3.5 and np.abs(shifts).max(axis=0)[0] > 20
    # perspective: the projective denominator stays within 1 +- max_persp of the centre's
    for seed in range(20):
        H = viewpoint_homography(seed, shape, max_persp=0.05)
        den = np.c_[corners, np.ones(4)] @ H[2] / (np.r_[c, 1.0] @ H[2])
        assert np.all(np.abs(den - 1) <= 0.05 + 1e-12)
    assert np.abs(H[2, :2]).max() > 0
    np.testing.assert_array_equal(viewpoint_homography(3, shape), viewpoint_homography(3, shape))


# --------------------------------------------------------------------------- changes
def test_paste_changes_polarity_and_truth(levir):
    img = levir[512:768, 256:512].copy()  # 256 x 256 RGB
    before = img.copy()
    out, truth = paste_changes(img, 3, n=4, size_range=(0.08, 0.15))
    np.testing.assert_array_equal(img, before)  # input untouched
    assert out.shape == img.shape and out.dtype == img.dtype
    changed = np.any(out != img, axis=2)
    assert not np.any(changed & ~truth)  # every changed pixel is in the truth
    assert changed[truth].mean() > 0.9  # and the truth is what changed
    lab, nlab = ndimage.label(truth)
    assert nlab == 4
    areas = ndimage.sum(truth, lab, range(1, nlab + 1))
    assert np.all(areas >= 0.5 * (0.08 * 0.45 * 256) ** 2 * 0.7)
    assert np.all(areas <= (0.15 * 256 * 1.5) ** 2)
    diffs, spread = [], []
    for i in range(1, nlab + 1):
        m = lab == i
        d = out[m].mean(axis=1) - img[m].mean(axis=1)
        diffs.append(d.mean())
        spread.append(np.abs(out[m] - img[m]).max())
    diffs = np.array(diffs)
    assert (diffs > 0.15).any() and (diffs < -0.15).any()  # both polarities
    low = np.abs(diffs) < 0.08
    assert low.any()  # one object close to the local background ...
    assert np.array(spread)[low].max() > 0.03  # ... but with texture / an edge
    assert np.all((out >= 0) & (out <= 1))


def test_paste_changes_gray_and_seeded():
    rng = np.random.default_rng(0)
    img = ndimage.gaussian_filter(rng.random((120, 150)), 3)
    img = (img - img.min()) / np.ptp(img)
    a, ta = paste_changes(img, 9, n=3, low_contrast=False)
    b, tb = paste_changes(img, np.random.default_rng(9), n=3, low_contrast=False)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(ta, tb)
    assert a.ndim == 2 and a.dtype == np.float64
    assert not np.any((a != img) & ~ta)
    assert ta.any()
    with pytest.raises(TypeError):
        paste_changes((img * 255).astype(np.uint8), 0)


def test_moving_object_smear(levir):
    img = levir[0:200, 0:240]
    out, truth = moving_object(img, 4, size_range=(0.06, 0.06), travel_range=(0.25, 0.25))
    changed = np.any(out != img, axis=2)
    assert not np.any(changed & ~truth)
    assert changed[truth].mean() > 0.9
    assert ndimage.label(truth)[1] == 1
    ys, xs = np.nonzero(truth)
    span = max(np.ptp(ys), np.ptp(xs))
    assert span >= 0.25 * 200 - 1  # swept along its path, longer than the object (12 px)
    assert truth.sum() > 3 * (0.06 * 200) ** 2 * 0.4  # much more than one object's area
    # blurred by its motion: along the trail the object is only partly present, so the
    # change is graded (many distinct fractions), not a hard paste
    d = np.abs(out - img).max(axis=2)[truth]
    assert np.unique(np.round(d, 2)).size > 10


# --------------------------------------------------------------------------- pairs
def test_make_pair_consistent(levir):
    img = levir[200:456, 600:856]  # 256 x 256 RGB
    u8 = np.round(img * 255).astype(np.uint8)
    pair = make_pair(u8, rng=11, noise_sigma=0.0)
    h, w = img.shape[:2]
    assert pair.reference.dtype == np.float32 and pair.reference.shape == img.shape
    np.testing.assert_allclose(pair.reference, img, atol=1e-6)
    assert pair.observed.shape == img.shape and pair.observed.dtype == np.float32
    assert pair.truth.shape == pair.unknown.shape == (h, w)
    assert pair.path.center == ((w - 1) / 2, (h - 1) / 2)  # the observation's centre
    assert 0 < pair.unknown.mean() < 0.3 and not pair.unknown[100:156, 100:156].any()
    assert pair.unknown[0].any() or pair.unknown[-1].any() or pair.unknown[:, 0].any()
    assert not np.any(pair.truth & pair.unknown)
    assert 0.005 < pair.truth.mean() < 0.3
    assert np.all((pair.observed >= 0) & (pair.observed <= 1))
    # round trip through JSON: reblurring the reference with the recorded motion gives the
    # observation wherever nothing changed (no noise here)
    meta = json.loads(json.dumps(pair.meta()))
    path = CameraPath.from_dict(meta["path"])
    V = np.array(meta["viewpoint"])
    reblur, valid = blur_along_path(pair.reference, path, base=V)
    np.testing.assert_array_equal(valid, ~pair.unknown)
    carried, _ = blur_along_path(pair.scene_changed.astype(np.float32), path, base=V)
    quiet = valid & (carried == 0)
    assert quiet.mean() > 0.5
    np.testing.assert_allclose(pair.observed[quiet], reblur[quiet], atol=1e-5)
    # and the changes show: inside the truth the observation differs clearly
    diff = np.abs(pair.observed - reblur).max(axis=2)
    assert np.median(diff[pair.truth]) > 0.05
    assert np.median(diff[quiet]) < 1e-5
    # the truth is the change mask carried by the same motion, thresholded at 0.5
    held, _ = blur_along_path(pair.scene_truth.astype(np.float32), path, base=V)
    np.testing.assert_array_equal(pair.truth, (held >= 0.5) & valid)
    # the viewpoint is not the identity and the shake has the requested extent
    assert np.abs(V - np.eye(3)).max() > 1e-3
    assert path.extent()["tx"] == pytest.approx(6.0) and path.extent()["rz"] == pytest.approx(1.0)


def test_make_pair_after_image_noise_and_seed():
    a, b = _levir(1)[:160, :200], _levir(1)[40:200, 30:230]  # "after" differs everywhere
    p1 = make_pair(
        a,
        b,
        rng=np.random.default_rng(2),
        n_changes=2,
        moving=False,
        shake=None,
        viewpoint=None,
        noise_sigma=0.01,
    )
    # still camera, same viewpoint: observation = after scene + noise (clipped)
    assert len(p1.path) == 1 and not p1.unknown.any()
    np.testing.assert_array_equal(p1.viewpoint, np.eye(3))
    r = p1.observed - p1.scene
    inner = (r > -0.5) & (p1.scene > 0.05) & (p1.scene < 0.95)
    assert abs(float(r[inner].std()) - 0.01) < 0.001
    # scene = after image outside the pasted changes
    np.testing.assert_array_equal(p1.scene[~p1.scene_truth], b[~p1.scene_truth])
    np.testing.assert_array_equal(p1.truth, p1.scene_truth)
    np.testing.assert_array_equal(p1.scene_changed, p1.scene_truth)  # nothing moving
    p2 = make_pair(
        a,
        b,
        rng=np.random.default_rng(2),
        n_changes=2,
        moving=False,
        shake=None,
        viewpoint=None,
        noise_sigma=0.01,
    )
    np.testing.assert_array_equal(p1.observed, p2.observed)
    with pytest.raises(ValueError):
        make_pair(a, b[:100], rng=0)


def test_moving_object_half_max_footprint(levir):
    """The half-maximum footprint: the same smear, the pixels covered at least half as long as
    the most covered one (checked against the occupancy recomputed independently)."""
    img = levir[0:200, 0:240]
    kw = dict(size_range=(0.1, 0.1), travel_range=(0.05, 0.05), n_steps=16)
    out_s, swept = moving_object(img, 9, **kw)
    out_h, half = moving_object(img, 9, truth="half_max", **kw)
    np.testing.assert_array_equal(out_s, out_h)  # same scene, only the footprint differs
    assert half.any() and not np.any(half & ~swept) and half.sum() < swept.sum()
    # the ends of the smear, covered for a short part of the exposure, change the image
    # much less than the half-max core
    d = np.abs(out_s - img).max(axis=2)
    assert np.median(d[half]) > 2 * np.median(d[swept & ~half])
    with pytest.raises(ValueError, match="truth"):
        moving_object(img, 9, truth="all")
    # the occupancy: the fraction of the time steps the object covers each pixel
    _, occ = moving_object(img, 9, truth="occupancy", **kw)
    assert occ.dtype == np.float32 and occ.max() <= 1.0 + 1e-6
    np.testing.assert_array_equal(occ > 0, swept)
    np.testing.assert_array_equal(occ >= 0.5 * occ.max(), half)


def test_make_pair_moving_truth(levir):
    """The pair's truth holds the moving object by its half-maximum footprint, carried
    through the camera blur; every pixel it may change is in ``scene_changed``."""
    img = levir[200:456, 600:856]
    pair = make_pair(img, rng=5, n_changes=0, noise_sigma=0.0, viewpoint=None,
                     moving={"travel_range": (0.1, 0.1)})
    assert pair.scene_truth.any() and pair.scene_truth.sum() < pair.scene_changed.sum()
    assert not np.any(pair.scene_truth & ~pair.scene_changed)
    untouched = ~pair.scene_changed
    np.testing.assert_array_equal(pair.scene[untouched], img[untouched])


def test_path_blurred_scene_reads_windows_of_the_blur():
    """Window reads equal the whole-image blur cropped (computed independently, at once)."""
    from reblur.simulate import PathBlurredScene

    rng = np.random.default_rng(21)
    scene = rng.random((120, 150))
    path = random_camera_path(2, center=(74.5, 59.5), t_max=3.0, rz_max=0.5)
    whole, _ = blur_along_path(scene, path, (0, 0, 120, 150), dtype=np.float32)
    whole = whole.reshape(120, 150)
    obs = PathBlurredScene(scene, path)
    assert obs.shape == (120, 150) and obs.dtype == np.float32
    # (OpenCV float32 warp coordinates differ by window: about 1e-6 of the value)
    np.testing.assert_allclose(obs[30:70, 40:110], whole[30:70, 40:110], atol=1e-5)
    np.testing.assert_allclose(obs[:, 100:], whole[:, 100:], atol=1e-5)
    with pytest.raises(IndexError):
        obs[::2, :]
    with pytest.raises(ValueError, match="gray"):
        PathBlurredScene(rng.random((10, 10, 3)), path)
