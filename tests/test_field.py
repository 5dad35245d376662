"""Tests for reblur.align.field: the local residual displacement field after the homography."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from reblur.align.field import (
    DisplacementField,
    FieldParams,
    estimate_field,
    fit_field,
    lattice_boxes,
    reject_outliers,
)
from reblur.grid import PoseGrid
from reblur.tiled import SparsePoses, reblur_tile
from reblur.warp import Box


def _affine_field(shape=(200, 300), step=20.0, a=(0.3, -0.2), b=(0.004, 0.001),
                  c=(-0.002, 0.003)) -> tuple[DisplacementField, callable]:
    """A field whose node values are affine in (x, y): bilinear interpolation is exact."""
    H, W = shape
    ny, nx = int(np.ceil((H - 1) / step)) + 1, int(np.ceil((W - 1) / step)) + 1
    gy, gx = np.mgrid[0:ny, 0:nx] * step

    def truth(x, y):
        return (a[0] + b[0] * x + c[0] * y, a[1] + b[1] * x + c[1] * y)

    dx, dy = truth(gx, gy)
    return DisplacementField(0.0, 0.0, step, np.stack([dx, dy], axis=-1)), truth


def test_field_is_bilinear_between_nodes_and_constant_beyond():
    fld, truth = _affine_field()
    rng = np.random.default_rng(0)
    xy = rng.uniform([0, 0], [299, 199], size=(50, 2))
    got = fld.displacement(xy)
    want = np.stack(truth(xy[:, 0], xy[:, 1]), axis=1)
    np.testing.assert_allclose(got, want, atol=1e-4)
    dx, dy = fld.maps(Box(10, 20, 30, 40))
    y, x = np.mgrid[10:40, 20:60]
    tx, ty = truth(x, y)
    np.testing.assert_allclose(dx, tx, atol=1e-4)
    np.testing.assert_allclose(dy, ty, atol=1e-4)
    # beyond the last node (x = 300 is past 299 -> node 15 at x = 300 exists; go further)
    far = fld.displacement(np.array([[10_000.0, 50.0]]))
    edge = fld.displacement(np.array([[fld.step * (fld.d.shape[1] - 1), 50.0]]))
    np.testing.assert_allclose(far, edge, atol=1e-5)


def test_field_rejects_bad_nodes():
    with pytest.raises(ValueError, match="finite"):
        DisplacementField(0, 0, 10, np.full((3, 3, 2), np.nan))
    with pytest.raises(ValueError, match="ny, nx, 2"):
        DisplacementField(0, 0, 10, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="min_cc"):
        FieldParams(min_cc=1.5)


def test_reblur_tile_resamples_at_the_displaced_position():
    """Identity pose, a linear ramp reference: the field moves the sample to p + d(p),
    so the output is the ramp at p + d(p) (bicubic interpolation reproduces a ramp)."""
    H, W = 120, 160
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    ref = (0.002 * x + 0.003 * y).astype(np.float32)
    grid = PoseGrid.from_ranges((H, W), t_max=0, rz_max=0.0, rz_step=1.0)
    w = np.ones(grid.shape)
    assert w.size == 1  # the identity pose alone
    fld, truth = _affine_field((H, W), step=16.0, a=(1.5, -0.75))
    box = Box(20, 30, 60, 80)
    out, valid = reblur_tile(SparsePoses(w, grid, field=fld), ref, box)
    yy, xx = np.mgrid[20:80, 30:110].astype(np.float64)
    dx, dy = truth(xx, yy)
    want = 0.002 * (xx + dx) + 0.003 * (yy + dy)
    assert valid.all()
    # OpenCV's remap quantises positions to 1/32 px: 0.005 / 32 on this ramp
    np.testing.assert_allclose(out[..., 0], want, atol=2e-4)
    plain, _ = reblur_tile(SparsePoses(w, grid), ref, box)
    assert np.abs(plain[..., 0] - want).max() > 1e-3  # the field did something


def _radial(pts, shape, corner_px):
    H, W = shape
    c = np.array([(W - 1) / 2.0, (H - 1) / 2.0])
    rmax = float(np.hypot(*c))
    r = np.hypot(*(pts - c).T)
    return (pts - c) * (corner_px * r * r / rmax**3)[:, None]


def test_fit_field_recovers_a_radial_field_and_the_median_test_its_outliers():
    shape = (1024, 1024)
    rng = np.random.default_rng(1)
    s = 1024 / 12
    g = (np.mgrid[0:12, 0:12].reshape(2, -1).T[:, ::-1] + 0.5) * s
    vec = _radial(g, shape, 3.0) + rng.normal(0, 0.03, g.shape)
    bad = rng.choice(len(g), 8, replace=False)
    vec[bad] += rng.choice([-1, 1], (8, 2)) * rng.uniform(2, 4, (8, 2))
    keep = reject_outliers(g, vec, s)
    assert not keep[bad].any()
    assert keep.sum() >= len(g) - 8 - 4  # few good points lost
    fld, info = fit_field(g[keep], vec[keep], shape, s)
    assert fld is not None and info["reason"] == ""
    q = rng.uniform(s / 2, 1024 - s / 2, (200, 2))  # inside the tie points' hull
    err = np.hypot(*(fld.displacement(q) - _radial(q, shape, 3.0)).T)
    assert np.sqrt(np.mean(err**2)) < 0.05
    assert info["cv_rms_px"] < 0.5 * info["cv_rms_zero_px"]


def test_fit_field_keeps_the_homography_when_the_field_explains_nothing():
    rng = np.random.default_rng(2)
    g = (np.mgrid[0:10, 0:10].reshape(2, -1).T + 0.5) * 50.0
    fld, info = fit_field(g, rng.normal(0, 0.05, g.shape), (500, 500), 50.0)
    assert fld is None and "no field needed" in info["reason"]
    # large but unstructured disagreement: no smooth field predicts held-out points
    fld, info = fit_field(g, rng.normal(0, 0.5, g.shape), (500, 500), 50.0)
    assert fld is None and "held-out" in info["reason"]
    fld, info = fit_field(g[:5], np.zeros((5, 2)), (500, 500), 50.0)
    assert fld is None and "reliable tie points" in info["reason"]


def test_lattice_covers_the_image_with_non_overlapping_windows():
    boxes = lattice_boxes((1000, 700), FieldParams(probe_px=100, max_probes=6))
    assert len(boxes) == 6 * 6
    assert min(b.y0 for b in boxes) == 0 and max(b.y1 for b in boxes) == 1000
    assert min(b.x0 for b in boxes) == 0 and max(b.x1 for b in boxes) == 700
    xs = sorted({b.x0 for b in boxes})
    assert min(np.diff(xs)) >= 100


def _texture(shape, seed):
    rng = np.random.default_rng(seed)
    a = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 2.0)
    return (a - a.min()) / (a.max() - a.min())


@pytest.mark.parametrize("corner_px", [0.0, 2.5])
def test_estimate_field_measures_a_known_distortion_through_the_reblur(corner_px):
    """The observation is the reference resampled at p + d(p) for a known radial d (no
    blur, the identity pose): the estimated field matches d inside the lattice, and an
    undistorted pair gets no field."""
    shape = (512, 512)
    ref = _texture(shape, 3)
    y, x = np.mgrid[0:512, 0:512].astype(np.float64)
    pts = np.stack([x.ravel(), y.ravel()], axis=1)
    d = _radial(pts, shape, corner_px).reshape(512, 512, 2)
    obs = cv2.remap(ref, (x + d[..., 0]).astype(np.float32), (y + d[..., 1]).astype(np.float32),
                    cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    grid = PoseGrid.from_ranges(shape, t_max=0, rz_max=0.0, rz_step=1.0)
    w = np.ones(grid.shape)
    assert w.size == 1  # the identity pose alone
    est = estimate_field(ref, obs, SparsePoses(w, grid), params=FieldParams(probe_px=64))
    if corner_px == 0:
        assert est.field is None and not est.info["applied"]
        return
    assert est.field is not None and est.info["applied"]
    assert est.info["rms_after_px"] < 0.5 * est.info["rms_before_px"]
    q = np.random.default_rng(4).uniform(32, 480, (200, 2))
    err = np.hypot(*(est.field.displacement(q) - _radial(q, shape, corner_px)).T)
    assert np.sqrt(np.mean(err**2)) < 0.1
