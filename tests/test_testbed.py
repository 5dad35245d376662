"""Tests of the independent realism test bed (reblur.testbed).

Every expected value is computed independently of the code under test: analytic results
(rigid motions, linear ramps, Poisson-Gaussian variance) or explicit slow references
(per-pixel loops, OpenCV renders of an indicator, frames averaged by hand).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from reblur import testbed as tb

PKG = Path(tb.__file__).resolve().parent
SRC = PKG.parents[1]
FORBIDDEN = ("reblur.grid", "reblur.warp", "reblur.operator", "reblur.simulate", "reblur.tiled")


def _data_or_skip() -> Path:
    try:
        return tb.shared_data_dir()
    except FileNotFoundError:
        pytest.skip("shared data absent")


def _translation(tx: float, ty: float) -> np.ndarray:
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])


def _keys_position(u: np.ndarray, a: float = -0.75) -> np.ndarray:
    """Where Keys' cubic convolution (OpenCV's a = -0.75) puts a linear ramp sampled at u.

    Interpolating ``f(x) = x`` gives ``sum_k w(u - k) k`` over the 4 taps around ``u``: equal
    to ``u`` only for a = -0.5; for a = -0.75 it carries a small first-order phase error.
    """

    def w(s):
        s = np.abs(s)
        near = (a + 2) * s**3 - (a + 3) * s**2 + 1
        far = a * s**3 - 5 * a * s**2 + 8 * a * s - 4 * a
        return np.where(s <= 1, near, np.where(s < 2, far, 0.0))

    base = np.floor(u)
    return sum(w(u - (base + j)) * (base + j) for j in (-1, 0, 1, 2))


def _shaken(shape, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    path = tb.random_camera_path(shape, rng, max_shift_px=4.0)
    view = tb.viewpoint_homography(shape, rng, shift_px=6.0, angle_deg=0.5, perspective=1.0)
    return tb.compose(view, path.homographies())


# ---------------------------------------------------------------- independence


def test_sources_import_nothing_from_reblur():
    for path in PKG.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                assert not any(a.name.startswith("reblur") for a in node.names), path
            elif isinstance(node, ast.ImportFrom):
                assert node.level in (0, 1), (path, node.module)
                assert not (node.module or "").startswith("reblur"), (path, node.module)


def test_importing_testbed_loads_no_reblur_model_module():
    code = (
        "import sys, types\n"
        f"pkg = types.ModuleType('reblur'); pkg.__path__ = [{str(SRC / 'reblur')!r}]\n"
        "sys.modules['reblur'] = pkg\n"
        "import reblur.testbed\n"
        "print(sorted(m for m in sys.modules if m.startswith('reblur')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    loaded = [m for m in eval(out) if m != "reblur" and not m.startswith("reblur.testbed")]
    assert loaded == []
    assert not any(m in out for m in FORBIDDEN)


# ---------------------------------------------------------------- camera


def test_roll_fixes_centre_and_moves_corner_by_chord():
    shape, angle = (301, 401), 0.5
    h = tb.pose_homography(shape, (0, 0, 0, 0, 0, angle))
    cx, cy = 200.0, 150.0
    centre = h @ [cx, cy, 1.0]
    np.testing.assert_allclose(centre[:2] / centre[2], [cx, cy], atol=1e-9)
    corner = h @ [0.0, 0.0, 1.0]
    r = np.hypot(cx, cy)
    moved = np.hypot(*(corner[:2] / corner[2] - [0.0, 0.0]))
    np.testing.assert_allclose(moved, 2 * r * np.sin(np.deg2rad(angle) / 2), rtol=1e-9)
    right = h @ [cx + 100.0, cy, 1.0]  # clockwise on screen: +x turns towards +y
    np.testing.assert_allclose(right[:2] / right[2], [cx + 100 * np.cos(np.deg2rad(angle)),
                                                      cy + 100 * np.sin(np.deg2rad(angle))])


def test_translation_and_depth_poses():
    shape = (200, 300)
    h = tb.pose_homography(shape, (2.37, -1.61, 0, 0, 0, 0))
    np.testing.assert_allclose(h, _translation(2.37, -1.61), atol=1e-12)
    s = tb.pose_homography(shape, (0, 0, 0.01, 0, 0, 0))
    p = s @ [10.0, 20.0, 1.0]
    c = np.array([149.5, 99.5])
    np.testing.assert_allclose(p[:2] / p[2], c + (np.array([10.0, 20.0]) - c) / 1.01)


def test_tilt_is_a_true_perspective_and_view_moves_corners_differently():
    shape = (400, 600)
    h = tb.pose_homography(shape, (0, 0, 0, 0.3, 0, 0))
    assert abs(h[2, 1]) > 1e-7 and abs(h[2, 0]) < 1e-12
    view = tb.viewpoint_homography(shape, np.random.default_rng(1), 10.0, 1.0, 2.0)
    corners = np.array([[0, 0, 1], [599, 0, 1], [0, 399, 1], [599, 399, 1]], float).T
    moved = view @ corners
    disp = moved[:2] / moved[2] - corners[:2]
    assert np.ptp(disp[0]) > 1.0 and np.ptp(disp[1]) > 1.0
    centre = view @ [299.5, 199.5, 1.0]
    assert np.all(np.abs(centre[:2] / centre[2] - [299.5, 199.5]) <= 10.0 + 1e-9)
    flat = tb.viewpoint_homography(shape, np.random.default_rng(1), 10.0, 0.0, 0.0)
    assert np.allclose(flat[:2, :2], np.eye(2)) and np.allclose(flat[2], [0, 0, 1])


def test_random_path_is_continuous_bounded_and_seeded():
    shape = (300, 300)
    path = tb.random_camera_path(shape, np.random.default_rng(5), max_shift_px=3.0,
                                 max_roll_deg=0.5, max_tilt_deg=0.3, max_depth=0.002)
    again = tb.random_camera_path(shape, np.random.default_rng(5), max_shift_px=3.0,
                                  max_roll_deg=0.5, max_tilt_deg=0.3, max_depth=0.002)
    assert path.poses.shape == (64, 6)
    np.testing.assert_array_equal(path.poses, again.poses)
    limits = np.array([3.0, 3.0, 0.002, 0.3, 0.3, 0.5])
    assert np.all(np.abs(path.poses) <= limits + 1e-12)
    assert np.all(np.ptp(path.poses, axis=0) > 0)
    assert np.all(np.abs(path.poses[:, :2] - np.rint(path.poses[:, :2])) > 1e-6)
    curvature = np.abs(np.diff(path.poses, n=2, axis=0)).max(axis=0)
    assert np.all(curvature < 0.05 * np.ptp(path.poses, axis=0))  # smooth, not jittery
    with pytest.raises(ValueError, match="n_sub"):
        tb.random_camera_path(shape, np.random.default_rng(0), n_sub=16)


# ---------------------------------------------------------------- render


def test_zero_motion_renders_reference_exactly():
    ref = np.random.default_rng(0).random((70, 90))
    out, valid = tb.render_window(ref, np.stack([np.eye(3)] * 3), (0, 70, 0, 90))
    np.testing.assert_allclose(out, ref.astype(np.float32), atol=1e-6)
    assert valid[2:-2, 2:-2].all() and not valid[:2].any() and not valid[:, -2:].any()


def test_integer_translation_is_a_roll():
    ref = np.random.default_rng(1).random((60, 80))
    h = tb.pose_homography(ref.shape, (3, -2, 0, 0, 0, 0))
    out, _ = tb.render_window(ref, h[None], (0, 60, 0, 80))
    rolled = np.roll(ref, (-2, 3), axis=(0, 1))
    np.testing.assert_allclose(out[5:-5, 5:-5], rolled[5:-5, 5:-5], atol=1e-6)


def test_constant_image_stays_constant():
    ref = np.full((120, 150), 0.37)
    hs = _shaken(ref.shape, 2)
    out, valid = tb.render_window(ref, hs, (0, 120, 0, 150))
    np.testing.assert_allclose(out, 0.37, atol=1e-6)
    assert valid.mean() > 0.5


def test_keys_kernel_phase_error_is_small():
    u = np.linspace(0, 1, 101)
    err = _keys_position(u) - u
    assert np.abs(err).max() < 0.05 and np.abs(_keys_position(u, -0.5) - u).max() < 1e-12


def test_linear_ramp_is_reproduced_by_the_cubic():
    ys, xs = np.mgrid[0:120, 0:160].astype(np.float64)
    ref = 0.1 + 0.004 * xs + 0.002 * ys
    hs = _shaken(ref.shape, 3)
    out, valid = tb.render_window(ref, hs, (0, 120, 0, 160))
    expected = np.zeros_like(ref)
    for h in hs:  # explicit per-pose mapping of every pixel
        hi = np.linalg.inv(h)
        den = hi[2, 0] * xs + hi[2, 1] * ys + hi[2, 2]
        u = (hi[0, 0] * xs + hi[0, 1] * ys + hi[0, 2]) / den
        v = (hi[1, 0] * xs + hi[1, 1] * ys + hi[1, 2]) / den
        expected += (0.1 + 0.004 * _keys_position(u) + 0.002 * _keys_position(v)) / len(hs)
    assert valid.mean() > 0.6
    np.testing.assert_allclose(out[valid], expected[valid], atol=3e-5)


def test_true_centroid_of_two_translations_is_the_midpoint():
    hs = np.stack([_translation(2.5, 1.0), _translation(-0.5, 3.0)])
    pts = np.array([[10.0, 20.0], [33.3, 4.4]])
    np.testing.assert_allclose(tb.true_centroid(hs, pts), pts - [1.0, 2.0], atol=1e-12)


def test_tiled_render_equals_whole_render():
    ref = np.random.default_rng(4).random((150, 170))
    hs = _shaken(ref.shape, 4)
    whole, whole_valid = tb.render_window(ref, hs, (0, 150, 0, 170))
    tiled, tiled_valid = tb.render_tiled(ref, hs, tile=48)
    np.testing.assert_array_equal(tiled, whole)
    np.testing.assert_array_equal(tiled_valid, whole_valid)


class _Recorder:
    """A source that records the windows read from it."""

    def __init__(self, array: np.ndarray) -> None:
        self.array, self.shape, self.reads = array, array.shape, []

    def __getitem__(self, key):
        self.reads.append(key)
        return self.array[key]


def test_window_reads_only_the_region_it_needs():
    tx, ty = 5.3, -2.2
    ref = np.full((400, 400), np.nan)
    box = (100, 140, 200, 260)
    # hand-computed cubic support of obs pixels x - t: floor(u) - 1 .. floor(u) + 2
    r0, r1 = int(np.floor(100 - ty)) - 1, int(np.floor(139 - ty)) + 3
    c0, c1 = int(np.floor(200 - tx)) - 1, int(np.floor(259 - tx)) + 3
    ref[r0:r1, c0:c1] = np.random.default_rng(5).random((r1 - r0, c1 - c0))
    src = _Recorder(ref)
    out, valid = tb.render_window(src, _translation(tx, ty)[None], box)
    assert np.isfinite(out).all() and valid.all()
    (rows, cols), = src.reads
    assert rows.start >= r0 - 3 and rows.stop <= r1 + 3
    assert cols.start >= c0 - 3 and cols.stop <= c1 + 3


def test_valid_mask_of_a_translation_is_the_shifted_shrunk_frame():
    shape, tx, ty = (50, 70), 4.5, -3.25
    valid = tb.valid_window(_translation(tx, ty)[None], (0, 50, 0, 70), shape)
    expected = np.zeros(shape, dtype=bool)
    for y in range(50):
        for x in range(70):
            u, v = x - tx, y - ty
            expected[y, x] = 2 <= u <= 67 and 2 <= v <= 47
    np.testing.assert_array_equal(valid, expected)
    inner = tb.valid_window(_translation(tx, ty)[None], (10, 20, 10, 20), shape)
    assert inner.all()


def test_render_rejects_bad_arguments():
    with pytest.raises(ValueError, match="y1 > y0"):
        tb.render_window(np.zeros((10, 10)), np.eye(3)[None], (5, 5, 0, 10))
    with pytest.raises(ValueError, match=r"\(n, 3, 3\)"):
        tb.render_window(np.zeros((10, 10)), np.eye(2)[None], (0, 5, 0, 10))


# ---------------------------------------------------------------- sensor


def test_poisson_gaussian_variance_on_a_flat_image():
    x, full_well, read, bits = 0.4, 2000.0, 20.0, 16
    img = np.full((500, 400), x)
    dn = tb.apply_sensor(img, np.random.default_rng(6), bits=bits, read_noise_dn=read,
                         full_well=full_well).astype(np.float64)
    m = 65535.0
    expected_var = x * m**2 / full_well + read**2 + 1 / 12
    n = dn.size
    assert abs(dn.var() / expected_var - 1) < 5 * np.sqrt(2 / n)
    assert abs(dn.mean() - x * m) < 5 * np.sqrt(expected_var / n)


def test_read_noise_only_variance_8bit():
    dn = tb.apply_sensor(np.full((400, 400), 0.5), np.random.default_rng(7), bits=8,
                         read_noise_dn=3.0).astype(np.float64)
    assert abs(dn.var() / (9.0 + 1 / 12) - 1) < 5 * np.sqrt(2 / dn.size)


def test_quantisation_ranges_and_dtypes():
    ramp = np.linspace(-0.1, 1.1, 1001)
    for bits, top, dtype in ((8, 255, np.uint8), (12, 4095, np.uint16), (16, 65535, np.uint16)):
        q = tb.quantise(ramp, bits)
        assert q.dtype == dtype and q.min() == 0 and q.max() == top
        assert tb.quantise(np.array([0.25]), bits)[0] == round(0.25 * top)
    noiseless = tb.apply_sensor(np.full((4, 4), 1.0), np.random.default_rng(0), bits=12)
    assert noiseless.dtype == np.uint16 and (noiseless == 4095).all()
    with pytest.raises(ValueError, match="bits"):
        tb.quantise(ramp, 10)
    with pytest.raises(ValueError, match="8-bit"):
        tb.apply_sensor(np.zeros((8, 8)), np.random.default_rng(0), bits=16, jpeg_quality=90)


def test_jpeg_is_close_and_seeded_noise_repeats():
    img = np.random.default_rng(8).random((64, 64)) * 0.2 + 0.4
    a = tb.apply_sensor(img, np.random.default_rng(9), bits=8, read_noise_dn=1.0,
                        jpeg_quality=90)
    b = tb.apply_sensor(img, np.random.default_rng(9), bits=8, read_noise_dn=1.0,
                        jpeg_quality=90)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a.astype(float) - np.rint(img * 255)).mean() < 4


# ---------------------------------------------------------------- scenes


def test_shared_data_dir_and_scene_loaders():
    data = _data_or_skip()
    assert (data / "README.md").is_file()
    img = tb.levir_image("test_7", "A")
    rgb = tb.whu_image(tb.scene_names("whu")[0], "curr", gray=False)
    assert img.shape == (1024, 1024) and rgb.shape == (1024, 1024, 3)
    assert 0 <= img.min() and img.max() <= 1 and img.std() > 0.05
    with pytest.raises(ValueError, match="which"):
        tb.levir_image("test_7", "C")


def test_upsampled_reader_windows_and_linear_content():
    ys, xs = np.mgrid[0:40, 0:50].astype(np.float64)
    src = 0.2 + 0.01 * xs + 0.005 * ys
    up = tb.upsampled(src, 2.5)
    assert up.shape == (100, 125)
    whole = up[:, :]
    np.testing.assert_array_equal(up[30:70, 40:90], whole[30:70, 40:90])
    oy, ox = np.mgrid[0:100, 0:125].astype(np.float64)
    u, v = _keys_position((ox + 0.5) / 2.5 - 0.5), _keys_position((oy + 0.5) / 2.5 - 0.5)
    expected = 0.2 + 0.01 * u + 0.005 * v
    np.testing.assert_allclose(whole[8:-8, 8:-8], expected[8:-8, 8:-8], atol=1e-5)


def test_pasted_changes_have_the_stated_contrast():
    _data_or_skip()
    base = tb.levir_image("test_7", "B")[:512, :512]
    scene = tb.paste_changes(base, np.random.default_rng(10), n_changes=8, contrast=(0.1, 0.4))
    changed = scene[:, :]
    kinds = set()
    for obj in scene.objects:
        kinds.add(obj.kind)
        y0, y1, x0, x1 = obj.bbox
        pad = int(np.ceil(obj.radius))
        around = base[max(y0 - pad, 0):y1 + pad, max(x0 - pad, 0):x1 + pad]
        p2, p98 = np.percentile(around, [2, 98])
        yy, xx = np.mgrid[y0:y1, x0:x1]
        inside = np.zeros((y1 - y0, x1 - x0), dtype=bool)
        for j, (y, x) in enumerate(zip(yy.ravel(), xx.ravel(), strict=True)):
            inside.flat[j] = obj.contains(np.float64(x), np.float64(y))  # pixel by pixel
        diff = np.abs(changed[y0:y1, x0:x1] - base[y0:y1, x0:x1])[inside]
        unclipped = diff[(changed[y0:y1, x0:x1][inside] > 0) & (changed[y0:y1, x0:x1][inside] < 1)]
        assert inside.sum() >= 4
        assert np.all(unclipped >= 0.1 * (p98 - p2) - 1e-9)
        assert unclipped.size >= 0.9 * diff.size
        assert np.all(np.abs(changed - base)[y0:y1, x0:x1][~inside] == 0)
    assert len(scene.objects) == 8 and len(kinds) >= 2


def test_truth_is_the_half_maximum_footprint():
    _data_or_skip()
    scene = tb.levir_image("test_12", "B")
    pair = tb.make_pair(scene, size=(300, 340), n_changes=5, seed=11,
                        motion={"max_shift_px": 5.0})
    objects = tuple(tb.ChangeObject(**(o | {"harmonics": tuple(map(tuple, o["harmonics"]))}))
                    for o in pair.info["objects"])
    ys, xs = np.mgrid[0:300, 0:340].astype(np.float64)
    indicator = np.logical_or.reduce([o.contains(xs, ys) for o in objects]).astype(np.float32)
    mean = np.zeros((300, 340))
    for h in pair.homographies:  # direct OpenCV render of the indicator, one pose at a time
        mean += cv2.warpPerspective(indicator, h, (340, 300), flags=cv2.INTER_LINEAR)
    mean /= len(pair.homographies)
    direct = mean >= 0.5
    assert pair.truth.sum() > 100
    agree = direct == pair.truth
    assert agree.mean() > 0.995
    assert np.all(np.abs(mean[~agree] - 0.5) < 0.2)


# ---------------------------------------------------------------- pairs


def test_make_pair_is_seeded_and_consistent():
    _data_or_skip()
    scene = tb.levir_image("test_7", "B")
    kw = dict(size=(200, 220), bits=12, noise_dn=2.0, n_changes=3, seed=12,
              changes={"size_px": (10.0, 30.0), "margin": 20.0})
    a, b = tb.make_pair(scene, **kw), tb.make_pair(scene, **kw)
    np.testing.assert_array_equal(a.observed, b.observed)
    assert a.reference.dtype == np.uint16 and a.reference.max() <= 4095
    assert a.homographies.shape == (64, 3, 3) and a.valid.mean() > 0.5
    with pytest.raises(ValueError, match="size"):
        tb.make_pair(scene, size=(2000, 200))


def test_write_pair_round_trips_and_equals_make_pair(tmp_path):
    _data_or_skip()
    scene = tb.upsampled(tb.levir_image("test_102", "B"), 1.2)
    kwargs = dict(size=(1100, 700), bits=16, noise_dn=3.0, n_changes=4, seed=13,
                  full_well=5000.0)
    mem = tb.make_pair(scene, **kwargs)
    info = tb.write_pair(tmp_path, scene, **kwargs)
    with tifffile.TiffFile(tmp_path / "observed.tif") as tif:
        page = tif.pages[0]
        assert tif.is_bigtiff and page.is_tiled and page.tilewidth == 512
        observed = page.asarray()
    np.testing.assert_array_equal(observed, mem.observed)
    np.testing.assert_array_equal(tifffile.imread(tmp_path / "reference.tif"), mem.reference)
    np.testing.assert_array_equal(tifffile.imread(tmp_path / "truth.tif") > 0, mem.truth)
    np.testing.assert_array_equal(tifffile.imread(tmp_path / "valid.tif") > 0, mem.valid)
    saved = json.loads((tmp_path / "pair.json").read_text())
    assert saved["seed"] == 13 and saved["bits"] == 16 and saved["shape"] == [1100, 700]
    np.testing.assert_array_equal(np.array(saved["homographies"]), mem.homographies)
    assert info["noise_dn"] == 3.0


# ---------------------------------------------------------------- gopro


def test_gopro_pair_is_the_mean_of_the_frames():
    data = _data_or_skip()
    folder = data / "gopro" / "frames_GOPR0477_11_00"
    if not folder.is_dir():
        pytest.skip("GoPro frames absent")
    ref, obs = tb.gopro_pair(12, 5)
    frames = [cv2.imread(str(folder / f"{i:06d}.png"))[..., ::-1].astype(np.float64)
              for i in (10, 11, 12, 13, 14)]
    np.testing.assert_array_equal(obs, np.rint(sum(frames) / 5).astype(np.uint8))
    np.testing.assert_array_equal(ref, frames[2].astype(np.uint8))
    assert tb.gopro_frame_indices(12, 4) == [10, 11, 12, 13]
    with pytest.raises(ValueError, match="centre in"):
        tb.gopro_pair(2, 7)
    with pytest.raises(ValueError, match="k must be"):
        tb.gopro_pair(12, 0)


def test_rgb_jpeg_pair_written_equals_in_memory(tmp_path):
    _data_or_skip()
    img = tb.levir_image("test_7", "B", gray=False)
    kwargs = dict(size=(300, 280), bits=8, noise_dn=1.0, n_changes=2, seed=14, jpeg_quality=85,
                  changes={"size_px": (10.0, 30.0)})
    mem = tb.make_pair(img, **kwargs)
    tb.write_pair(tmp_path, img, **kwargs)
    assert mem.observed.shape == (300, 280, 3) and mem.observed.dtype == np.uint8
    np.testing.assert_array_equal(tifffile.imread(tmp_path / "observed.tif"), mem.observed)


def test_make_pair_refuses_huge_in_memory_pairs():
    _data_or_skip()
    big = tb.upsampled(tb.levir_image("test_7", "B"), 4.1)
    with pytest.raises(ValueError, match="write_pair"):
        tb.make_pair(big, n_changes=1)


def test_truth_window_share_gives_the_half_maximum_footprint_and_the_whole_reach():
    """Four sub-poses shifting a 10 x 6 px rectangle by 0, 2, 4 and 6 px: the default
    truth is the pixels at least two of them cover, ``share=1e-9`` every pixel one covers,
    ``share=1`` those all four do (an explicit loop over the poses)."""
    from reblur.testbed.scenes import ChangedScene, ChangeObject, truth_window

    obj = ChangeObject(kind="rect", cx=30.0, cy=20.0, angle=0.0, a=5.0, b=3.0, a2=0.0,
                       harmonics=(), delta=0.3, local_range=1.0)
    scene = ChangedScene(np.zeros((40, 60)), (obj,))
    shifts = (0.0, 2.0, 4.0, 6.0)
    hs = np.array([[[1.0, 0.0, t], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]] for t in shifts])
    ys, xs = np.mgrid[0:40, 0:60].astype(float)
    count = sum(obj.contains(xs - t, ys).astype(int) for t in shifts)
    box = (0, 40, 0, 60)
    np.testing.assert_array_equal(truth_window(scene, hs, box), count >= 2)
    reach = truth_window(scene, hs, box, share=1e-9)
    np.testing.assert_array_equal(reach, count >= 1)
    np.testing.assert_array_equal(truth_window(scene, hs, box, share=1.0), count == 4)
    assert reach.sum() > truth_window(scene, hs, box).sum() > 0
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="share"):
            truth_window(scene, hs, box, share=bad)


def test_defocus_path_fills_the_disk_evenly():
    """A pillbox: every sub-pose within the radius, translation only, centred, with the
    uniform disk's moments (E r^2 = R^2 / 2, half the sub-poses inside R / sqrt(2)); bad
    radii and too few sub-poses refused."""
    from reblur.testbed import defocus_path

    R = 10.0
    p = defocus_path((600, 800), R, n_sub=400).poses
    assert p.shape == (400, 6) and not p[:, 2:].any()
    r2 = p[:, 0] ** 2 + p[:, 1] ** 2
    assert r2.max() <= R * R
    assert np.mean(r2) == pytest.approx(R * R / 2, rel=0.01)
    assert np.count_nonzero(r2 < R * R / 2) == 200
    assert np.abs(p[:, :2].mean(axis=0)).max() < 0.05 * R
    for bad in (0.0, -1.0, np.inf, np.nan):
        with pytest.raises(ValueError, match="radius_px"):
            defocus_path((64, 64), bad)
    with pytest.raises(ValueError, match="n_sub"):
        defocus_path((64, 64), 3.0, n_sub=32)
