"""Geometric refinement after the motion estimate: probe shifts and the base correction."""

import cv2
import numpy as np
import pytest
from conftest import levir_before

from reblur.align import measure_shifts, probe_boxes, refine_alignment
from reblur.align.refine import _largest_rectangle, covered_box, tie_shift
from reblur.grid import PoseGrid, map_points, pose_homography
from reblur.tiled import SparsePoses, reblur_tile, valid_polygon
from reblur.warp import Box, warp_window

H, W = 900, 1300
C = ((W - 1) / 2, (H - 1) / 2)


@pytest.fixture(scope="module")
def reference():
    """Real imagery: two LEVIR tiles side by side, cropped to 900 x 1300 (grayscale)."""
    a = np.concatenate([levir_before(0), levir_before(1)], axis=1)[:H, :W]
    return np.ascontiguousarray(a.mean(axis=2), dtype=np.float32)


def _grid_and_weights():
    grid = PoseGrid.from_ranges((H, W), t_max=2, rz_max=0.5, rz_step=0.5)
    w = np.zeros(grid.shape)
    b0 = int(np.argmin(np.abs(np.asarray(grid.rz))))
    w[b0, 2, 2] = 0.5  # tx = ty = 0
    w[b0, 2, 3] = 0.5  # tx = 1: a two-pixel horizontal blur
    return grid, w


def _observe(reference, err):
    """The observation the weights describe, through a base homography ``err``."""
    grid, w = _grid_and_weights()
    obs = np.zeros(reference.shape, np.float32)
    for tx in (0.0, 1.0):
        o, _ = warp_window(reference, pose_homography(tx, 0.0, center=C) @ err, (0, 0, H, W),
                           dtype=np.float32)
        obs += 0.5 * o.reshape(obs.shape)
    return obs, grid, w


def test_probe_boxes_cover_the_image():
    boxes = probe_boxes((H, W), size=256, n=5)
    assert len(boxes) == 3 * 5  # 900 px: three 256 px windows fit without overlap
    assert min(b.y0 for b in boxes) == 0 and max(b.y1 for b in boxes) == H
    assert min(b.x0 for b in boxes) == 0 and max(b.x1 for b in boxes) == W
    assert probe_boxes((100, 80), size=256) == [probe_boxes((100, 80), size=80)[0]]


def test_probe_boxes_span_a_box_within_the_image():
    within = Box(30, 30, 640, 1210)  # GoPro's 1280 x 720 less a 30 px margin
    boxes = probe_boxes((720, 1280), size=240, n=5, within=within)
    assert len(boxes) == len(probe_boxes((720, 1280), size=240, n=5)) == 3 * 5
    assert min(b.y0 for b in boxes) == 30 and max(b.y1 for b in boxes) == 670
    assert min(b.x0 for b in boxes) == 30 and max(b.x1 for b in boxes) == 1240
    # a narrow box: no two windows closer than 3/4 of their side
    narrow = probe_boxes((H, W), size=256, within=Box(0, 0, H, 565))
    xs = sorted({b.x0 for b in narrow})
    assert xs == [0, 565 - 256] and len(narrow) == 3 * 2
    # a box smaller than a window: the image's lattice
    assert probe_boxes((H, W), size=256, within=Box(0, 0, 200, W)) == probe_boxes((H, W))


def _largest_rectangle_slow(mask: np.ndarray) -> int:
    """Area of the largest all-true rectangle, by brute force: every pair of rows, the
    longest run of columns true on all the rows between them."""
    best = 0
    for top in range(mask.shape[0]):
        cols = np.ones(mask.shape[1], bool)
        for bottom in range(top, mask.shape[0]):
            cols &= mask[bottom]
            run = longest = 0
            for c in cols:
                run = run + 1 if c else 0
                longest = max(longest, run)
            best = max(best, longest * (bottom - top + 1))
    return best


def test_largest_rectangle_is_the_brute_force_one():
    rng = np.random.default_rng(5)
    for _ in range(40):
        shape = tuple(int(v) for v in rng.integers(1, 14, size=2))
        m = rng.random(shape) < rng.uniform(0.3, 0.95)
        i, j, h, w = _largest_rectangle(m)
        assert h * w == _largest_rectangle_slow(m)
        assert m[i : i + h, j : j + w].all()
    assert _largest_rectangle(np.zeros((3, 4), bool)) == (0, 0, 0, 0)
    assert _largest_rectangle(np.ones((3, 4), bool)) == (0, 0, 3, 4)


def _viewpoint_poses():
    """A viewpoint 25 px and 0.4 degree away, a slight perspective, and a blur over two
    rolls and translations up to 3 px."""
    base = pose_homography(25.0, -18.0, 0.01, 0.0, 0.0, 0.4, center=C)
    base = base @ np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [2e-5, -1e-5, 1.0]])
    grid = PoseGrid.from_ranges((H, W), t_max=3, rz_max=0.5, rz_step=0.5)
    w = np.zeros(grid.shape)
    w[1, 3, 3] = 0.4  # rz = 0, t = 0
    w[1, 0, 6] = 0.2  # tx = 3, ty = -3
    w[2, 5, 1] = 0.2  # rz = 0.5 degree, tx = -2, ty = 2
    w[2, 6, 4] = 0.2
    return SparsePoses(w, grid, base)


def test_covered_box_holds_what_every_pose_reads(reference):
    """The polygon and the box against the warps' own validity (:func:`reblur_tile`)."""
    poses = _viewpoint_poses()
    _, valid = reblur_tile(poses, reference, (0, 0, H, W))
    assert 0.8 < valid.mean() < 0.98  # the viewpoint leaves a margin
    # the polygon is the validity up to a pixel along its edges
    poly = valid_polygon(poses, reference.shape)
    # the polygon rasterised on its own (OpenCV, 1/256 px vertices) at every pixel
    inside = np.zeros((H, W), np.uint8)
    cv2.fillConvexPoly(inside, np.round(poly * 256).astype(np.int32), 1, shift=8)
    inside = inside.astype(bool)
    near = cv2.dilate((inside != cv2.erode(inside.astype(np.uint8), np.ones((5, 5)))
                       ).astype(np.uint8), np.ones((5, 5))).astype(bool)
    assert not (inside & ~valid & ~near).any()  # inside: valid (margin of 1 px)
    assert not (valid & ~inside & ~near).any()  # valid: inside, but within 2 px of an edge
    box = covered_box(poses, reference.shape, (H, W))
    assert valid[box.y0 : box.y1, box.x0 : box.x1].all()
    # nearly the largest: the brute-force largest rectangle of the validity's 20 px cells
    cells = valid[: H // 20 * 20, : W // 20 * 20].reshape(H // 20, 20, W // 20, 20)
    slow = 400 * _largest_rectangle_slow(cells.all(axis=(1, 3)))
    assert slow <= box.h * box.w < valid.sum()


def test_the_probes_lie_where_the_reference_covers(reference):
    """On a viewpoint that leaves a margin, the lattice over the image loses its border
    probes to their coverage; laid over the covered box, every probe is measured."""
    poses = _viewpoint_poses()
    obs, _ = reblur_tile(poses, reference, (0, 0, H, W))
    obs = obs[:, :, 0]
    w, grid = np.zeros(poses.grid.shape), poses.grid
    for b, tw in poses.groups.items():
        for tx, ty, v in tw:
            w[b, grid.ty.index(ty), grid.tx.index(tx)] = v
    whole = refine_alignment(reference, obs, w, grid, poses.base, probes=probe_boxes((H, W)))
    lost = [s for s in whole.before if not s.measured]
    assert len(lost) >= 6 and all("the reference covers" in s.reason for s in lost)
    r = refine_alignment(reference, obs, w, grid, poses.base)
    box = Box(*r.info["lattice"])
    assert r.info["probes"] == len(probe_boxes((H, W))) == 15
    assert all(s.measured and np.hypot(s.dx, s.dy) < 0.02 for s in r.before)
    assert all(box.y0 <= s.cy - 127.5 and s.cy + 128.5 <= box.y1 for s in r.before)
    assert all(box.x0 <= s.cx - 127.5 and s.cx + 128.5 <= box.x1 for s in r.before)
    assert not r.applied  # the base is the true one


@pytest.mark.parametrize("search", [False, True])
def test_shifts_match_the_analytic_displacement(reference, search):
    # observation seen through a small scale + roll error the weights do not know about
    err = pose_homography(0.0, 0.0, 3e-4, 0.0, 0.0, 0.02, center=C)
    obs, grid, w = _observe(reference, err)
    boxes = probe_boxes((H, W))
    every = measure_shifts(reference, obs, SparsePoses(w, grid), boxes, search=search)
    assert len(every) == len(boxes)
    shifts = [s for s in every if s.measured]
    assert len(shifts) >= 12
    errs = []
    for s in shifts:
        # observed(x) = reblurred(err^-1 x): the displacement is err^-1 (c) - c at the
        # centre; it varies by ~0.08 px across a 256 px probe, and ECC returns a
        # texture-weighted mean of it, hence the tolerance
        want = map_points(np.linalg.inv(err), np.array([[s.cx, s.cy]]))[0] - (s.cx, s.cy)
        errs.append(np.hypot(s.dx - want[0], s.dy - want[1]))
    assert max(errs) < 0.05 and np.median(errs) < 0.02, errs


def test_colour_probes_are_measured_on_the_reblurred_band_mean(monkeypatch):
    # a colour pair through a known scale + roll error: its shifts are those of the gray
    # pair made of the band means (float64 means, computed here), to rounding, and the
    # reference is reblurred as one band, not three
    import reblur.tiled

    rgb = np.concatenate([levir_before(0), levir_before(1)], axis=1)[:H, :W]
    gray = np.ascontiguousarray(rgb.astype(np.float64).mean(axis=2), dtype=np.float32)
    err = pose_homography(0.0, 0.0, 3e-4, 0.0, 0.0, 0.02, center=C)
    obs_gray, grid, w = _observe(gray, err)
    obs = np.repeat(obs_gray[:, :, None], 3, axis=2)
    boxes = probe_boxes((H, W))
    bands = []
    warp = reblur.tiled.warp_source

    def counted(source, *a, **k):
        bands.append(source[0].shape[2] if source[0].ndim == 3 else 1)
        return warp(source, *a, **k)

    monkeypatch.setattr(reblur.tiled, "warp_source", counted)
    colour = measure_shifts(rgb, obs, SparsePoses(w, grid), boxes)
    assert bands and set(bands) == {1}
    want = measure_shifts(gray, obs_gray, SparsePoses(w, grid), boxes)
    assert [s.measured for s in colour] == [s.measured for s in want]
    assert sum(s.measured for s in colour) >= 12
    for s, t in zip(colour, want, strict=True):
        if s.measured:
            assert abs(s.dx - t.dx) < 1e-3 and abs(s.dy - t.dy) < 1e-3, (s, t)


def _streaked_windows(n_scenes: int, seed: int):
    """64 px windows of smooth scenes under a 31 px horizontal motion blur, the
    observation's and the reblurred reference's (exact model, shifted by a known
    sub-pixel translation, 1 % noise): correlation ridges several pixels flat along x."""
    rng = np.random.default_rng(seed)
    kernel = np.full((1, 31), 1 / 31, np.float32)
    for _ in range(n_scenes):
        s = cv2.GaussianBlur(rng.random((400, 400)).astype(np.float32), (0, 0), 8)
        s = cv2.filter2D((s - s.min()) / np.ptp(s), -1, kernel)
        d = rng.uniform(-2, 2, 2)
        # reblurred(x) = s(x - d), so observed(x) = s(x) = reblurred(x + d)
        reb = cv2.warpAffine(s, np.float32([[1, 0, d[0]], [0, 1, d[1]]]), s.shape[::-1],
                             flags=cv2.INTER_CUBIC)
        obs = s + rng.normal(0, 0.01, s.shape).astype(np.float32)
        for y0 in range(100, 300, 64):
            for x0 in range(100, 300, 64):
                yield (obs[y0:y0 + 64, x0:x0 + 64].copy(), reb[y0:y0 + 64, x0:x0 + 64].copy(),
                       d)


def test_tie_shift_is_stable_and_accurate_along_a_blur_ridge():
    # ECC over the whole window against the whole window (measure_shifts without search)
    # loses the part shifted out of the window, so it drifts along such ridges: put in
    # tie_shift's place, it fails the sixth-digit stability check below (GoPro GOPR0374:
    # a third of the field's tie points moved, by 0.2-7 px)
    valid = np.ones((64, 64), bool)
    errs, refused = [], 0
    for obs, reb, d in _streaked_windows(12, seed=8):
        a = tie_shift(obs, reb, valid)
        b = tie_shift(obs, reb * np.float32(1 + 1e-6), valid)
        if isinstance(a, str):
            refused += 1
            assert isinstance(b, str), (a, b)
            continue
        assert not isinstance(b, str), (a, b)
        assert max(abs(a[0] - b[0]), abs(a[1] - b[1])) < 0.01, (a, b)
        errs.append(np.hypot(a[0] - d[0], a[1] - d[1]))
    assert refused <= 4 and len(errs) >= 188
    assert np.sqrt(np.mean(np.square(errs))) < 0.15 and max(errs) < 0.5


def test_tie_shift_refuses_what_it_cannot_locate():
    rng = np.random.default_rng(2)
    s = cv2.GaussianBlur(rng.random((64, 64)).astype(np.float32), (0, 0), 2)
    valid = np.ones((64, 64), bool)
    # a shift beyond the search range (an eighth of the window, 8 px)
    far = np.roll(s, 12, axis=1)
    assert "edge of the +-8 px search" in tie_shift(s, far, valid)
    # the reference defined on too little of the searched centre
    part = valid.copy()
    part[:, :40] = False
    assert "covers" in tie_shift(s, s, part, min_valid=0.5)
    # horizontal stripes, constant along x: nothing locates the shift along x
    stripes = np.tile(np.sin(np.arange(64) / 3.0).astype(np.float32)[:, None], (1, 64))
    got = tie_shift(stripes, stripes, valid)
    assert isinstance(got, str) and ("flat" in got or "edge" in got), got
    # double-precision windows are measured as single-precision ones; shapes must agree
    assert tie_shift(s.astype(np.float64), np.roll(s, 3, axis=1), valid) == tie_shift(
        s, np.roll(s, 3, axis=1), valid)
    with pytest.raises(ValueError, match="one shape"):
        tie_shift(s, s[:60], valid)


@pytest.mark.parametrize("search", [False, True])
def test_threaded_shifts_equal_the_serial_ones(reference, search):
    # the probes are measured side by side; each is computed alone, so the threads'
    # result is the one-thread result, bit for bit (the serial loop is the reference)
    err = pose_homography(0.3, -0.2, 3e-4, 0.0, 0.0, 0.02, center=C)
    obs, grid, w = _observe(reference, err)
    boxes = probe_boxes((H, W), size=128, n=8)
    poses = SparsePoses(w, grid)
    serial = measure_shifts(reference, obs, poses, boxes, workers=1, search=search)
    assert sum(s.measured for s in serial) >= 20
    assert measure_shifts(reference, obs, poses, boxes, workers=3, search=search) == serial
    with pytest.raises(ValueError, match="workers"):
        measure_shifts(reference, obs, poses, boxes, workers=0)


def test_rows_of_probes_are_reblurred_as_strips(reference, monkeypatch):
    """Dense rows of probes are reblurred once (one job per row); the shifts are those of
    each probe reblurred alone (the per-probe path, forced by an unreachable cover) within
    the reblur's window-dependent rounding; a sparse row and a lone probe go alone."""
    from reblur.align import refine
    from reblur.warp import Box

    err = pose_homography(0.3, -0.2, 3e-4, 0.0, 0.0, 0.02, center=C)
    obs, grid, w = _observe(reference, err)
    boxes = probe_boxes((H, W), size=128, n=8)  # 7 rows of 8: 79 % of each row's span
    jobs = refine._strip_jobs(boxes)
    assert [len(j) for j in jobs] == [8] * 7
    assert sorted(i for j in jobs for i in j) == list(range(len(boxes)))
    sparse = [Box(0, 0, 64, 64), Box(0, 200, 64, 64), Box(100, 0, 64, 64)]  # 128 of 264 px
    assert refine._strip_jobs(sparse) == [[0], [1], [2]]
    assert refine._strip_jobs([Box(0, 0, 64, 64), Box(0, 64, 64, 64)]) == [[0, 1]]
    poses = SparsePoses(w, grid)
    strips = measure_shifts(reference, obs, poses, boxes)
    monkeypatch.setattr(refine, "_STRIP_COVER", np.inf)
    assert all(len(j) == 1 for j in refine._strip_jobs(boxes))
    alone = measure_shifts(reference, obs, poses, boxes)
    assert sum(s.measured for s in alone) >= 40
    for a, b in zip(strips, alone, strict=True):
        assert a.measured == b.measured and (a.cx, a.cy) == (b.cx, b.cy)
        if a.measured:
            assert abs(a.dx - b.dx) < 1e-3 and abs(a.dy - b.dy) < 1e-3
            assert abs(a.cc - b.cc) < 1e-5


def test_refinement_removes_a_residual_scale_error(reference):
    err = pose_homography(0.4, -0.3, 2e-4, 0.0, 0.0, 0.015, center=C)
    obs, grid, w = _observe(reference, err)
    r = refine_alignment(reference, obs, w, grid, np.eye(3))
    assert r.applied and r.model == "homography"
    assert r.info["before"]["max_px"] > 0.3
    assert r.info["after"]["max_px"] < 0.03
    corners = np.array([[0.0, 0.0], [W - 1, 0.0], [W - 1, H - 1], [0.0, H - 1]])
    # the refined base maps the reference where the true one does, to a few hundredths
    assert np.abs(map_points(r.base, corners) - map_points(err, corners)).max() < 0.05
    # the probes covered the image: it was reblurred whole with the refined base, for the
    # displacement field next; its values are those of an independent reblur
    np.testing.assert_array_equal(r.poses.base, r.base)
    assert r.whole is not None and r.whole.serves(r.poses, Box(0, 0, H, W))
    own, ok = reblur_tile(SparsePoses(w, grid, r.base), reference, (0, 0, H, W))
    cut, valid = r.whole.cut(Box(0, 0, H, W))
    np.testing.assert_array_equal(valid, ok)
    np.testing.assert_allclose(cut[ok], own[ok], rtol=0, atol=1e-3)


def test_refinement_leaves_a_correct_base_alone(reference):
    obs, grid, w = _observe(reference, np.eye(3))
    r = refine_alignment(reference, obs, w, grid, np.eye(3))
    assert not r.applied
    np.testing.assert_array_equal(r.base, np.eye(3))
    assert r.info["before"]["max_px"] < 0.02
    # no corrected base: no whole-image reblur for the field (it reblurs its own)
    assert r.whole is None
    np.testing.assert_array_equal(r.poses.base, np.eye(3))


def test_no_reliable_probe_no_correction():
    flat = np.full((300, 300), 0.5, np.float32)
    grid = PoseGrid.from_ranges((300, 300), t_max=1, rz_max=0.5, rz_step=0.5)
    w = np.zeros(grid.shape)
    w[1, 1, 1] = 1.0
    r = refine_alignment(flat, flat, w, grid, np.eye(3))
    assert not r.applied and r.model == "none"
    # every probe is reported, with its reason, in the result and in the report's records
    assert len(r.before) == r.info["probes"] >= 1
    assert all(not s.measured and s.reason.startswith("flat") for s in r.before)
    assert [d["reason"] for d in r.info["probe_shifts"]] == [s.reason for s in r.before]
    assert all(d["dx"] is None for d in r.info["probe_shifts"])


def test_probes_beyond_the_horizon_are_skipped(reference):
    """A strong perspective base: observation columns x >= 1000 map beyond the horizon of
    the reference (the base's inverse divides by 1 - x / 1000), columns in between to
    points past the reference's right edge.  Those probes are skipped with their reason;
    the ones on the left are measured, and the refinement returns."""
    base = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1e-3, 0.0, 1.0]])
    grid, w = _grid_and_weights()
    obs = np.zeros(reference.shape, np.float32)  # nothing right of the horizon
    for tx in (0.0, 1.0):
        o, _ = warp_window(reference, pose_homography(tx, 0.0, center=C) @ base,
                           (0, 0, H, 990), dtype=np.float32)
        obs[:, :990] += 0.5 * o.reshape(H, 990)
    # the lattice over the whole image (by default it lies where the reference covers)
    boxes = probe_boxes((H, W), size=256)
    r = refine_alignment(reference, obs, w, grid, base, probes=boxes)
    assert len(r.before) == len(boxes)
    inv = np.linalg.inv(base)
    reasons = set()
    for b, s in zip(boxes, r.before, strict=True):
        corners = np.array([[b.x0, b.y0], [b.x1 - 1, b.y0], [b.x0, b.y1 - 1],
                            [b.x1 - 1, b.y1 - 1]], float)
        src = map_points(inv, corners)
        if b.x0 < 1000 < b.x1 - 1:  # the window straddles the horizon
            assert not s.measured and "beyond the horizon" in s.reason, (b, s)
        elif b.x0 >= 1000 or src[:, 0].max() > W - 3 or src[:, 1].max() > H - 3:
            # all of it beyond, or reading past the reference's edges
            assert not s.measured and "the reference covers" in s.reason, (b, s)
        else:
            assert s.measured and np.hypot(s.dx, s.dy) < 0.05, (b, s)
        reasons.add(s.reason.split(":")[0])
    assert {"", "cannot be reblurred"} < reasons  # both kinds occur
    assert not r.applied or r.info["after"]["n"] > 0


@pytest.mark.parametrize(("G", "reason"), [
    (np.zeros((3, 3)), "degenerate correction: singular"),
    (np.array([[1.0, 0, 0], [0, 1.0, 0], [np.nan, 0, 1.0]]), "singular or non-finite"),
    (np.array([[-1.0, 0, W - 1.0], [0, 1.0, 0], [0, 0, 1.0]]), "folded or mirrored"),
    (np.array([[1.0, 0, 0], [0, 1.0, 0], [-1.5e-3, 0, 1.0]]), "crosses the horizon"),
    (np.array([[1.0, 0, 600.0], [0, 1.0, 0], [0, 0, 1.0]]), r"moves the image corners by 600 px"),
])
def test_degenerate_corrections_are_rejected(reference, monkeypatch, G, reason):
    """A fitted correction that is singular, folds the image or moves it by more than a
    few probe sizes is rejected with the reason, not raised; the base stays."""
    from reblur.align import refine as refine_mod

    obs, grid, w = _observe(reference, np.eye(3))
    monkeypatch.setattr(refine_mod, "_fit", lambda shifts, ransac_px: (G, "homography", 12))
    base = pose_homography(0.5, 0.0, center=C)
    r = refine_alignment(reference, obs, w, grid, base)
    assert not r.applied and reason in r.info["rejected"], r.info
    np.testing.assert_array_equal(r.base, base)
    assert r.after == r.before and r.info["applied"] is False


def test_refine_params_are_checked():
    from reblur.align import RefineParams

    for bad, pattern in ((dict(probe_size=8), "probe_size"), (dict(n_probes=0), "n_probes"),
                         (dict(min_cc=1.5), "min_cc"), (dict(ransac_px=0.0), "ransac_px"),
                         (dict(max_correction=float("inf")), "max_correction"),
                         (dict(min_gain_px=-1.0), "min_gain_px")):
        with pytest.raises(ValueError, match=rf"RefineParams\.{pattern}"):
            RefineParams(**bad)
