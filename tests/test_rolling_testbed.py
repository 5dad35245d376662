"""Rolling-shutter mode of the test bed (reblur.testbed.rolling)."""

import numpy as np
import pytest

from reblur import testbed as tb
from reblur.testbed import rolling as tr


def _path(shape, n_total, seed=0):
    rng = np.random.default_rng(seed)
    path = tb.random_camera_path(shape, rng, n_sub=n_total, max_shift_px=4.0,
                                 max_roll_deg=1.0, max_tilt_deg=0.3)
    return path.homographies()


def _scene(shape, seed=1):
    import cv2

    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.random(shape), (0, 0), 1.5)


def test_no_readout_is_the_global_renderer_bit_for_bit():
    shape = (96, 120)
    src, hs = _scene(shape), _path(shape, 128)
    box = (10, 70, 20, 101)
    got, ok = tr.render_rolling_window(src, hs, box, readout=0.0, n_exposure=64)
    want, ok_want = tb.render_window(src, hs[:64], box)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(ok, ok_want)


def test_tiled_render_equals_a_per_row_brute_force():
    """Each row: the exact overlap of every slice [j, j+1]/n with the row's window
    [r y / H, r y / H + 1] (exposure units), times the one-pose render of that row."""
    shape, n, r = (40, 48), 64, 0.5
    src, hs = _scene(shape, 2), _path(shape, 96, seed=3)
    got, _ = tr.render_rolling_tiled(src, hs, readout=r, n_exposure=n, tile=16)
    want = np.zeros(shape)
    for y in range(shape[0]):
        t0 = r * y / shape[0]
        for j in range(len(hs)):
            share = max(0.0, min((j + 1) / n, t0 + 1.0) - max(j / n, t0))
            if share > 0:
                row, _ = tb.render_window(src, hs[j:j + 1], (y, y + 1, 0, shape[1]))
                want[y] += share * row[0]
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-13)
    glob, _ = tb.render_tiled(src, hs[:n], tile=16)
    assert np.abs(got - glob)[-10:].max() > 1e-3  # the late rows see another motion


def test_weights_sum_to_an_exposure_and_slide_with_the_rows():
    a = tr.row_slice_weights(np.arange(100), 100, 1.0, 8, 16)
    np.testing.assert_allclose(a.sum(axis=1), 8.0)
    first = [int(np.flatnonzero(row)[0]) for row in a]
    assert first[0] == 0 and first[-1] == 7 and np.all(np.diff(first) >= 0)
    with pytest.raises(ValueError, match="readout"):
        tr.row_slice_weights(np.arange(3), 3, 1.5, 8, 16)
    with pytest.raises(ValueError, match="longer path"):
        tr.row_slice_weights(np.arange(3), 3, 1.0, 8, 12)


def test_pair_without_readout_is_a_global_pair_of_the_path_start():
    scene = _scene((160, 160), 4)
    kw = dict(size=(128, 128), n_changes=2, seed=5,
              changes=dict(size_px=(10.0, 20.0), margin=20.0))
    plan = tr.plan_rolling_pair(scene, readout=0.0, n_exposure=64, **kw)
    assert len(plan.homographies) == 128 and plan.info["readout"] == 0.0
    box = (0, 64, 64, 128)
    want, _ = tb.render_window(plan.changed, plan.homographies[:64], box)
    np.testing.assert_array_equal(plan.render_tile(box), want)
    np.testing.assert_array_equal(
        plan.truth_tile(box), tb.truth_window(plan.changed, plan.homographies[:64], box))
    np.testing.assert_array_equal(
        plan.valid_tile(box), tb.valid_window(plan.homographies[:64], box, plan.shape))
    pair = tr.make_rolling_pair(scene, readout=0.5, **kw)
    assert pair.observed.dtype == np.uint8 and pair.truth.any()
    assert pair.info["readout"] == 0.5


def test_auto_leaves_a_global_shutter_pair_unchanged():
    """A realism test-bed pair with no readout (6-D shake path, perspective viewpoint
    change, 8-bit sensor with read noise, LEVIR test_7): auto keeps the global model, and
    the change mask is then the global run's, pixel for pixel."""
    import reblur

    scene = tb.levir_image("test_7")
    pair = tr.make_rolling_pair(scene, readout=0.0, size=(320, 320), bits=8, noise_dn=1.0,
                                n_changes=0, seed=3, viewpoint={"shift_px": 10.0})
    glob = reblur.detect_changes(pair.reference, pair.observed)
    auto = reblur.detect_changes(pair.reference, pair.observed, shutter="auto")
    sh = auto.decision["shutter"]
    assert sh["asked"] == "auto" and sh["model"] == "global", sh["criterion"]
    np.testing.assert_array_equal(auto.change, glob.change)
    np.testing.assert_array_equal(auto.unknown, glob.unknown)
