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
    ref, obs, poses = _distorted_pair(corner_px, side=512, seed=3)
    assert poses.n_poses == 1  # the identity pose alone
    est = estimate_field(ref, obs, poses, params=FieldParams(probe_px=64))
    if corner_px == 0:
        assert est.field is None and not est.info["applied"]
        return
    assert est.field is not None and est.info["applied"]
    assert est.info["rms_after_px"] < 0.5 * est.info["rms_before_px"]
    q = np.random.default_rng(4).uniform(32, 480, (200, 2))
    err = np.hypot(*(est.field.displacement(q) - _radial(q, shape, corner_px)).T)
    assert np.sqrt(np.mean(err**2)) < 0.1


def test_reach_map_marks_a_step_and_not_a_smooth_field():
    """A field with a 4 px step between two halves: the reach is >= 3 px within a tie-point
    spacing of the step and 0 far from it; a smooth (affine) field has reach 0."""
    d = np.zeros((9, 17, 2), np.float32)
    d[:, 9:, 0] = 4.0  # a step between node columns 8 and 9 (x = 256 .. 288)
    fld = DisplacementField(0.0, 0.0, 32.0, d)
    r = fld.reach_map(Box(0, 0, 256, 512))
    assert fld.max_reach() == 4
    assert r[:, 250:300].min() >= 3
    assert r[:, :150].max() == 0 and r[:, 420:].max() == 0
    smooth, _ = _affine_field((256, 512), step=32.0)
    assert smooth.max_reach() == 0 and not smooth.reach_map(Box(0, 0, 256, 512)).any()


def test_tolerance_reach_is_the_extremes_over_the_disc():
    """The interval widened by a per-pixel reach equals the min / max of the reference
    over a disc of that radius, computed by brute force."""
    from reblur.decide.tolerance import ModelTolerance, tolerance_interval

    rng = np.random.default_rng(5)
    m = rng.random((40, 50)).astype(np.float32)
    reach = np.zeros((40, 50), np.uint8)
    reach[10:30, 5:25] = 2
    reach[5:15, 30:45] = 3
    lo, hi = tolerance_interval(m, ModelTolerance(), reach)
    for y, x in [(0, 0), (12, 6), (20, 20), (8, 40), (14, 44), (35, 48)]:
        r = int(reach[y, x])
        vals = [m[min(max(y + dy, 0), 39), min(max(x + dx, 0), 49)]
                for dy in range(-r, r + 1) for dx in range(-r, r + 1) if dy * dy + dx * dx <= r * r]
        assert lo[y, x] == pytest.approx(min(vals)) and hi[y, x] == pytest.approx(max(vals))


@pytest.mark.parametrize("case", ["lens3", "parallax"])
def test_detect_changes_meets_the_bounds_on_test_bed_geometry(case):
    """Test-bed pairs (independent renderer) with 3 px of lens distortion at the corners or
    a roof 4 px of parallax from the ground, no change: the geometry (homography, poses and
    field) is within 0.5 px RMS of the truth away from occlusion edges, and at most 0.3 %
    of the known pixels is flagged."""
    import reblur
    from reblur.testbed import failure_pair

    pair = failure_pair(case)
    res = reblur.detect_changes(pair.reference, pair.observed)
    assert res.field is not None
    h, w = pair.valid.shape
    ys, xs = np.mgrid[16:h:32, 16:w:32]
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    ok = pair.valid[ys.ravel(), xs.ravel()] & ~res.unknown[ys.ravel(), xs.ravel()]
    if pair.occlusion.any():
        band = pair.geometry.occlusion_window((0, h, 0, w), band_px=3)
        ok &= ~band[ys.ravel(), xs.ravel()]
    pts = pts[ok]
    src = res.motion.source_points(pts + res.field.displacement(pts), res.alignment)
    err = np.hypot(*(src - pair.geometry.centroid(pts)).T)
    assert np.sqrt(np.mean(err**2)) <= 0.5
    known = pair.valid & ~res.unknown
    assert np.count_nonzero(res.change & known) <= 0.003 * np.count_nonzero(known)


def _distorted_pair(corner_px: float, side: int = 1024, seed: int = 5):
    """A textured reference and the observation resampled at p + d(p) for the radial d of
    ``corner_px`` at the corners (the identity pose: no blur)."""
    shape = (side, side)
    ref = _texture(shape, seed)
    y, x = np.mgrid[0:side, 0:side].astype(np.float64)
    d = _radial(np.stack([x.ravel(), y.ravel()], axis=1), shape, corner_px).reshape(side, side, 2)
    obs = cv2.remap(ref, (x + d[..., 0]).astype(np.float32), (y + d[..., 1]).astype(np.float32),
                    cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    grid = PoseGrid.from_ranges(shape, t_max=0, rz_max=0.0, rz_step=1.0)
    return ref, obs, SparsePoses(np.ones(grid.shape), grid)


def _counting(monkeypatch):
    """Count the tie-point windows ``estimate_field`` measures."""
    import reblur.align.refine as refine

    seen = []
    real = refine.measure_shifts

    def measure(reference, observed, poses, boxes, **kw):
        seen.extend(boxes)
        return real(reference, observed, poses, boxes, **kw)

    monkeypatch.setattr(refine, "measure_shifts", measure)
    return seen


@pytest.mark.parametrize("corner_px", [0.0, 2.5])
def test_first_pass_settles_only_what_the_whole_lattice_would(monkeypatch, corner_px):
    """A 16 x 16 lattice: on an undistorted pair the first pass (every other tie point of
    every other row, 64) settles that no field is needed, as the whole lattice does; on a
    distorted one every tie point is measured and the field is the one-pass field, node
    for node."""
    import reblur.align.field as field_mod

    ref, obs, poses = _distorted_pair(corner_px)
    p = FieldParams(probe_px=64)
    seen = _counting(monkeypatch)
    est = estimate_field(ref, obs, poses, params=p)
    n_first = len(seen)
    seen.clear()
    monkeypatch.setattr(field_mod, "_FIRST_PASS_MIN", 10**9)  # the one-pass reference
    one = estimate_field(ref, obs, poses, params=p)
    assert one.info["probes"] == est.info["probes"] == 256
    if corner_px == 0:
        assert est.field is None and one.field is None
        assert est.info["first_pass"] == n_first == 64 and len(seen) == 256
        assert est.info["rms_before_px"] < 0.075 and one.info["rms_before_px"] < 0.15
        return
    assert "first_pass" not in est.info and est.info["applied"] and one.info["applied"]
    np.testing.assert_array_equal(est.field.d, one.field.d)
    assert est.info["rms_after_px"] == one.info["rms_after_px"]


def test_settled_needs_enough_quiet_inliers_or_no_correlation():
    """``_settled`` on a 10 x 10 lattice of synthetic tie points: none correlating, or at
    least ``min_points`` inliers under half of ``min_rms_px``, settle it; a residual at
    or above half the threshold, or too few points, do not."""
    from reblur.align.field import _settled
    from reblur.align.refine import ProbeShift

    p = FieldParams()
    rng = np.random.default_rng(8)
    cy, cx = np.mgrid[0:10, 0:10] * 100.0

    def lattice(sigma, cc=0.99, n=100):
        d = rng.normal(0, sigma, (n, 2))
        return [ProbeShift(float(x), float(y), float(a), float(b), cc)
                for x, y, (a, b) in zip(cx.ravel()[:n], cy.ravel()[:n], d, strict=True)]

    none = _settled(lattice(0.01, cc=0.5), 100.0, p)
    assert none is not None and none["measured"] == 0 and "none of 100" in none["reason"]
    quiet = _settled(lattice(0.02), 100.0, p)
    assert quiet is not None and quiet["rms_before_px"] < 0.5 * p.min_rms_px
    assert quiet["inliers"] >= p.min_points
    assert _settled(lattice(0.1), 100.0, p) is None  # RMS ~0.14 px: the whole lattice decides
    assert _settled(lattice(0.02, n=12), 100.0, p) is None  # fewer than min_points


def _blurred_distorted_pair():
    """A distorted 1 MP pair whose observation is also blurred by three translations: the
    reference, the observation, those poses and their weights."""
    ref, obs, _ = _distorted_pair(2.5)
    grid = PoseGrid((1024, 1024), tx=[-1, 0, 1], ty=[0, 1], rz=[0.0])
    w = np.zeros(grid.shape)
    w[0, 0, 1], w[0, 1, 2], w[0, 0, 0] = 0.5, 0.3, 0.2
    poses = SparsePoses(w, grid)
    return ref, reblur_tile(poses, obs, (0, 0, 1024, 1024))[0][:, :, 0], poses, w


def _counted_reblurs(monkeypatch) -> list:
    """The boxes every reblur (``tiled._reblur_poses``) is asked for from now on."""
    import reblur.tiled as tiled

    boxes: list = []
    real = tiled._reblur_poses

    def counted(ps, reference, box, dtype):
        boxes.append(box)
        return real(ps, reference, box, dtype)

    monkeypatch.setattr(tiled, "_reblur_poses", counted)
    return boxes


def test_the_later_passes_reblur_the_image_once(monkeypatch):
    """A distorted 1 MP pair: after the first pass, the rest of the lattice and the check
    with the field cut their rows from one reblur of the image (its strips are the only
    reblurs left), and the field is the one measured without it, within the rounding of
    the warp coordinates; where the image cannot be reblurred whole, exactly that one."""
    import reblur.align.refine as refine_mod
    import reblur.tiled as tiled

    ref, obs, poses, _ = _blurred_distorted_pair()
    p = FieldParams(probe_px=64)
    boxes = _counted_reblurs(monkeypatch)
    est = estimate_field(ref, obs, poses, params=p)
    assert est.info["applied"] and "first_pass" not in est.info
    first = [b for b in boxes if b.h == 64]  # the first pass: 8 rows of tie points
    strips = [b for b in boxes if b.h != 64]
    assert len(first) == 8 and len(boxes) == 8 + len(strips)
    assert sum(b.h for b in strips) == 1024 + 2 * refine_mod._WHOLE_MARGIN
    monkeypatch.setattr(refine_mod, "_WHOLE_SPAN", 2.0)  # never: every pass reblurs its rows
    boxes.clear()
    alone = estimate_field(ref, obs, poses, params=p)
    assert len(boxes) > 8 + 16
    assert alone.info["inliers"] == est.info["inliers"]
    np.testing.assert_allclose(est.field.d, alone.field.d, rtol=0, atol=1e-4)
    assert abs(est.info["rms_after_px"] - alone.info["rms_after_px"]) <= 1e-4
    # an image that cannot be reblurred whole (a pose beyond the horizon there): the rows
    # are reblurred on their own, as without it
    monkeypatch.setattr(refine_mod, "_WHOLE_SPAN", 0.75)

    def beyond(*args, **kwargs):
        raise ValueError("a pose maps the window beyond the horizon")

    monkeypatch.setattr(tiled, "reblur_whole", beyond)
    fallback = estimate_field(ref, obs, poses, params=p)
    np.testing.assert_array_equal(fallback.field.d, alone.field.d)


def test_a_whole_reblur_given_serves_every_tie_point(monkeypatch):
    """The refinement's whole-image reblur (``estimate_field(whole=)``, the same poses
    object) serves the first pass, the rest and the check: the field reblurs nothing
    itself, and it is the one it measures alone within the rounding of the warp
    coordinates.  A reblur of other poses (equal weights, another object) is not used."""
    import reblur.align.refine as refine_mod
    import reblur.tiled as tiled

    ref, obs, poses, w = _blurred_distorted_pair()
    p = FieldParams(probe_px=64)
    alone = estimate_field(ref, obs, poses, params=p)
    whole = tiled.reblur_whole(poses, ref, (1024, 1024), margin=refine_mod._WHOLE_MARGIN)
    boxes = _counted_reblurs(monkeypatch)
    given = estimate_field(ref, obs, poses, params=p, whole=whole)
    assert boxes == []
    assert given.info["applied"] and given.info["inliers"] == alone.info["inliers"]
    np.testing.assert_allclose(given.field.d, alone.field.d, rtol=0, atol=1e-4)
    assert abs(given.info["rms_after_px"] - alone.info["rms_after_px"]) <= 1e-4
    other = estimate_field(ref, obs, SparsePoses(w, poses.grid), params=p, whole=whole)
    assert len(boxes) > 8  # its own first pass and whole reblur
    np.testing.assert_array_equal(other.field.d, alone.field.d)


def test_which_lattices_reblur_the_image_whole(monkeypatch):
    """The later passes reblur the image whole only where a pass would reblur most of it
    anyway: a 1 MP lattice's rows (strips spanning the image), not a 4 MP one's (half of
    it), nor a wide strip image's (its rows' sparse windows are reblurred alone, whatever
    their span), nor an image above the pixel cap."""
    import reblur.align.refine as refine_mod
    import reblur.tiled as tiled
    from reblur.align.field import lattice_boxes
    from reblur.align.refine import _whole_reblur

    made = []
    monkeypatch.setattr(tiled, "reblur_whole", lambda *a, **k: made.append(a[2]) or "whole")
    grid = PoseGrid((8, 8), tx=[0], ty=[0])
    poses = SparsePoses(np.ones(grid.shape), grid)
    p = FieldParams(probe_px=64)

    def later(shape):  # the lattice less the first pass (every other one of every other row)
        boxes = lattice_boxes(shape, p)
        xs, ys = sorted({b.x0 for b in boxes}), sorted({b.y0 for b in boxes})
        first = {(ys[r], xs[c]) for r in range(0, len(ys), 2) for c in range(0, len(xs), 2)}
        return [b for b in boxes if (b.y0, b.x0) not in first]

    ref = np.zeros((4, 4), np.float32)  # never read: reblur_whole is replaced
    assert _whole_reblur(ref, poses, (1024, 1024), later((1024, 1024))) == "whole"
    assert _whole_reblur(ref, poses, (2048, 2048), later((2048, 2048))) is None
    assert _whole_reblur(ref, poses, (1024, 16000), later((1024, 16000))) is None  # < cap
    monkeypatch.setattr(refine_mod, "_WHOLE_PIXELS", 1024 * 1024 - 1)
    assert _whole_reblur(ref, poses, (1024, 1024), later((1024, 1024))) is None
    assert made == [(1024, 1024)]
