"""The fast paths of the decision against the previous implementations.

The references below are the previous code: ``scipy.ndimage`` labelling of the whole array
at every step of the region passes, full-size temporaries in the statistic, concatenated
samples in the model-error fit.  The fast versions must give bit-identical masks, counts,
region records, completeness flags, statistics and fits on random seeded inputs.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import scipy.ndimage as ndi
from skimage.morphology import convex_hull_image

from reblur.decide import (
    DecisionParams,
    _boxes,
    _clear_of,
    _components,
    _decide_core,
    _label_median,
    _region_records,
    change_statistic,
    fit_model_error,
    gaussian_zero,
)
from reblur.decide.regions import _hull_pixels

_EIGHT = np.ones((3, 3), bool)
_FOUR = ndi.generate_binary_structure(2, 1)


# --------------------------------------------------------------------------- references
def _ref_shape_ok(sub, area, p):
    if p.min_solidity > 0 and area < p.min_solidity * sub.size:
        hull = int(np.count_nonzero(convex_hull_image(sub)))
        if hull and area / hull < p.min_solidity:
            return False
    r_in = float(ndi.distance_transform_edt(np.pad(sub, 1)).max())
    return area / (4.0 * r_in * r_in) <= p.max_aspect


def _ref_decide_core(S, known, threshold, p):
    strong = p.strong_factor * threshold
    accepted = np.zeros(S.shape, bool)
    pending = known.copy()
    counts = {"accepted": 0, "small": 0, "weak": 0, "not_object": 0, "thin": 0}
    levels = p.levels if p.region_tests else (1.0,)
    candidates = None
    kernel = (cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * p.open_radius + 1,) * 2)
              if p.open_radius > 0 else None)
    for li, level in enumerate(levels):
        m = (S > threshold * level) & pending
        if kernel is not None:
            m = cv2.morphologyEx(m.view(np.uint8), cv2.MORPH_OPEN, kernel).astype(bool)
        if candidates is None:
            candidates = m
        lab, n = ndi.label(m, structure=_EIGHT)
        if n == 0:
            break
        area = np.bincount(lab.ravel(), minlength=n + 1)[1:]
        smax = ndi.maximum(S, lab, np.arange(1, n + 1))
        keep = np.zeros(n + 1, bool)
        nxt = np.zeros(n + 1, bool)
        last = li == len(levels) - 1
        for i, sl in enumerate(ndi.find_objects(lab)):
            lbl = i + 1
            if area[i] < p.min_area:
                counts["small"] += 1
                continue
            if smax[i] < strong:
                counts["weak"] += 1
                continue
            if not p.region_tests or _ref_shape_ok(lab[sl] == lbl, int(area[i]), p):
                keep[lbl] = True
                counts["accepted"] += 1
            elif last:
                counts["not_object"] += 1
            else:
                nxt[lbl] = True
        accepted |= keep[lab]
        pending = nxt[lab]
        if not pending.any():
            break
    if candidates is None:
        candidates = np.zeros(S.shape, bool)
    if p.boundary_fraction > 0 and accepted.any():
        lab, n = ndi.label(accepted, structure=_EIGHT)
        level = np.atleast_1d(ndi.median(S.astype(np.float64), lab, np.arange(1, n + 1)))
        cut = np.concatenate([[np.inf], np.maximum(p.boundary_fraction * level, threshold)])
        accepted &= S >= cut[lab]
        lab, n = ndi.label(accepted, structure=_EIGHT)
        area = np.bincount(lab.ravel(), minlength=n + 1)
        big = area >= p.min_area
        big[0] = False
        accepted = big[lab]
    if p.close_radius > 0 and accepted.any():
        # every region closed on its own, on the whole (padded) array
        r = p.close_radius
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2).astype(bool)
        lab, n = ndi.label(accepted, structure=_EIGHT)
        closed = accepted.copy()
        for lbl in range(1, n + 1):
            reg = np.pad(lab == lbl, r + 1)
            closed |= ndi.binary_closing(reg, structure=disc)[r + 1 : -r - 1, r + 1 : -r - 1]
        accepted = closed
    if p.max_hole_area > 0 and accepted.any():
        bg, nb = ndi.label(~accepted, structure=_FOUR)
        sizes = np.bincount(bg.ravel(), minlength=nb + 1)
        border = np.unique(np.concatenate([bg[0], bg[-1], bg[:, 0], bg[:, -1]]))
        fill = sizes <= p.max_hole_area
        fill[0] = False
        fill[border] = False
        accepted |= fill[bg]
    accepted &= known
    return accepted, candidates, counts


def _ref_region_records(mask, S, y0, x0, core=None):
    lab, n = ndi.label(mask, structure=_EIGHT)
    out = []
    for i, sl in enumerate(ndi.find_objects(lab)):
        sub = lab[sl] == i + 1
        yy, xx = np.nonzero(sub)
        ay, ax = int(yy[0] + sl[0].start), int(xx[0] + sl[1].start)
        if core is not None:
            cy0, cx0, ch, cw = core
            if not (cy0 <= ay < cy0 + ch and cx0 <= ax < cx0 + cw):
                continue
        vals = S[sl][sub]
        out.append({
            "area": int(sub.sum()),
            "bbox": [sl[0].start + y0, sl[1].start + x0, sl[0].stop + y0, sl[1].stop + x0],
            "centroid": [float(yy.mean() + sl[0].start + y0),
                         float(xx.mean() + sl[1].start + x0)],
            "mean_stat": float(vals.mean()),
            "max_stat": float(vals.max()),
        })
    for k, r in enumerate(out, 1):
        r["label"] = k
    return out


def _ref_complete(cm_list, band, core):
    for cm in cm_list:
        lab, n = ndi.label(cm, structure=_EIGHT)
        if n:
            in_core = np.unique(lab[core])
            in_band = np.unique(lab[band])
            if np.intersect1d(in_core[in_core > 0], in_band[in_band > 0]).size:
                return False
    return True


def _ref_statistic(observed, matched, known, sigma, smooth, truncate, edge_k, curv_k):
    o = observed if observed.ndim == 3 else observed[:, :, None]
    m = matched if matched.ndim == 3 else matched[:, :, None]
    C = o.shape[2]
    s = np.broadcast_to(np.asarray(sigma, np.float64).reshape(-1), (C,))
    ks = np.zeros(C) if edge_k is None else np.broadcast_to(np.asarray(edge_k, float), (C,))
    kc = np.zeros(C) if curv_k is None else np.broadcast_to(np.asarray(curv_k, float), (C,))
    e = np.zeros(o.shape[:2], np.float64)
    for c in range(C):
        r = o[:, :, c].astype(np.float64) - m[:, :, c]
        var = np.full(r.shape, s[c] * s[c])
        a = np.ascontiguousarray(m[:, :, c], dtype=np.float32)
        if ks[c] > 0:
            gx = cv2.Sobel(a, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT) / 8.0
            gy = cv2.Sobel(a, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT) / 8.0
            var = var + ks[c] * ks[c] * (gx * gx + gy * gy).astype(np.float64)
        if kc[c] > 0:
            lap = cv2.Laplacian(a, cv2.CV_32F, ksize=1, borderType=cv2.BORDER_REFLECT)
            var = var + kc[c] * kc[c] * lap.astype(np.float64) ** 2
        e += np.where(known, r * r / var, 0.0)
    e /= C
    if smooth > 0:
        num = gaussian_zero(e, smooth, truncate)
        den = gaussian_zero(known.astype(np.float64), smooth, truncate)
        e = np.where(den > 1e-6, num / np.maximum(den, 1e-6), 0.0)
    S = np.sqrt(np.maximum(e, 0.0)).astype(np.float32)
    S[~known] = 0.0
    return S


def _ref_fit_model_error(observed, matched, known, sigma, bins=8, max_samples=400_000,
                         k_max=0.5, c_max=0.5, rng=0):
    from scipy.optimize import nnls

    rng = np.random.default_rng(rng)
    s = np.asarray(sigma, dtype=np.float64).reshape(-1)
    C = s.size
    acc = [[[], [], []] for _ in range(C)]
    for o, m, k in zip(observed, matched, known, strict=True):
        o = o if o.ndim == 3 else o[:, :, None]
        m = m if m.ndim == 3 else m[:, :, None]
        k = ndi.binary_erosion(np.asarray(k, bool), np.ones((3, 3), bool), border_value=1)
        for c in range(C):
            mc = np.ascontiguousarray(m[:, :, c], dtype=np.float32)
            gx = cv2.Sobel(mc, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT) / 8.0
            gy = cv2.Sobel(mc, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT) / 8.0
            lap = cv2.Laplacian(mc, cv2.CV_32F, ksize=1, borderType=cv2.BORDER_REFLECT)
            acc[c][0].append(((o[:, :, c].astype(np.float64) - m[:, :, c]) ** 2)[k])
            acc[c][1].append((gx * gx + gy * gy).astype(np.float64)[k])
            acc[c][2].append((lap.astype(np.float64) ** 2)[k])
    ek, ck = np.zeros(C), np.zeros(C)
    for c in range(C):
        r2, g2, l2 = (np.concatenate(a) if a else np.zeros(0) for a in acc[c])
        if r2.size < 20 * bins * bins:
            continue
        if r2.size > max_samples:
            pick = rng.choice(r2.size, max_samples, replace=False)
            r2, g2, l2 = r2[pick], g2[pick], l2[pick]
        qg = np.searchsorted(np.quantile(g2, np.linspace(0, 1, bins + 1)[1:-1]), g2, "right")
        ql = np.searchsorted(np.quantile(l2, np.linspace(0, 1, bins + 1)[1:-1]), l2, "right")
        cell = qg * bins + ql
        rows, rhs, wts = [], [], []
        for b in np.unique(cell):
            sel = cell == b
            n = int(sel.sum())
            if n < 20:
                continue
            rows.append([g2[sel].mean(), l2[sel].mean()])
            rhs.append(float(np.median(r2[sel])) / 0.455 - s[c] ** 2)
            wts.append(np.sqrt(n))
        if len(rows) < 2:
            continue
        A = np.asarray(rows) * np.asarray(wts)[:, None]
        scale = np.maximum(A.max(axis=0), 1e-300)
        coef, _ = nnls(A / scale, np.asarray(rhs) * np.asarray(wts))
        a, b = coef / scale
        ek[c] = min(np.sqrt(max(a, 0.0)), k_max)
        ck[c] = min(np.sqrt(max(b, 0.0)), c_max)
    return ek, ck


# --------------------------------------------------------------------------- inputs
def _blobs(rng, shape, density, smooth):
    """Random blobby mask: thresholded smoothed noise."""
    f = ndi.gaussian_filter(rng.standard_normal(shape), smooth)
    return f > np.quantile(f, 1.0 - density)


def _statistic_field(rng, shape):
    """A change statistic: noise, object-like squares and discs, branching strips."""
    S = np.abs(ndi.gaussian_filter(rng.standard_normal(shape), 1.5)) * 2.0
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    for _ in range(rng.integers(3, 9)):
        y, x = rng.integers(0, h), rng.integers(0, w)
        r = rng.integers(5, 25)
        v = rng.uniform(1.0, 6.0)
        if rng.random() < 0.5:
            S[max(y - r, 0) : y + r, max(x - r, 0) : x + r] += v
        else:
            S[(yy - y) ** 2 + (xx - x) ** 2 < r * r] += v
    for _ in range(rng.integers(1, 4)):  # thin strips and crosses (not object-like)
        y, x = rng.integers(0, h), rng.integers(0, w)
        S[max(y - 3, 0) : y + 3, :] += rng.uniform(1.0, 4.0)
        S[:, max(x - 3, 0) : x + 3] += rng.uniform(1.0, 4.0)
    ring_y, ring_x = rng.integers(40, h - 40), rng.integers(40, w - 40)  # a ring: a hole
    d2 = (yy - ring_y) ** 2 + (xx - ring_x) ** 2
    S[(d2 < 30**2) & (d2 > 12**2)] += 5.0
    return S.astype(np.float32)


PARAMS = [
    DecisionParams(),
    DecisionParams(min_area=30, open_radius=1, max_hole_area=200),
    DecisionParams(region_tests=False),
    DecisionParams(boundary_fraction=0.0, max_hole_area=0),
    DecisionParams(close_radius=0),
    DecisionParams(close_radius=3, max_hole_area=0),
    DecisionParams(open_radius=0, levels=(1.0, 1.1, 1.3), min_solidity=0.8, max_aspect=3.0),
]


# --------------------------------------------------------------------------- tests
@pytest.mark.parametrize("connectivity", [8, 4])
def test_components_match_ndimage(connectivity):
    rng = np.random.default_rng(11)
    structure = _EIGHT if connectivity == 8 else _FOUR
    shapes = [(1, 1), (1, 37), (29, 1), (64, 64), (97, 131)]
    n_seen = 0
    for k in range(40):
        shape = shapes[k % len(shapes)]
        if k % 7 == 0:
            m = np.zeros(shape, bool) if k % 2 else np.ones(shape, bool)
        else:
            m = rng.random(shape) < rng.uniform(0.05, 0.7)
        ref, n_ref = ndi.label(m, structure=structure)
        cc = _components(m if k % 3 else m.view(np.uint8), connectivity)
        assert cc.n == n_ref
        assert ((cc.lab > 0) == m).all()
        # the same partition: a one-to-one map between the two numberings
        pairs = np.unique(np.stack([ref[m], cc.lab[m]]), axis=1)
        assert pairs.shape[1] == n_ref
        assert np.unique(pairs[1]).size == n_ref
        # boxes and areas against find_objects / bincount
        area = np.bincount(ref.ravel(), minlength=n_ref + 1)
        boxes = _boxes(cc, np.arange(1, cc.n + 1))
        some = _boxes(cc, np.arange(1, cc.n + 1)[::3])
        assert cc.area[0] == 0
        for i, sl in enumerate(ndi.find_objects(ref)):
            lbl = int(pairs[1][pairs[0] == i + 1][0])
            assert boxes[lbl] == sl
            assert some.get(lbl, sl) == sl
            assert cc.area[lbl] == area[i + 1]
        dense = _components(m, connectivity, pixels=False)  # areas from the label image
        np.testing.assert_array_equal(dense.lab, cc.lab)
        np.testing.assert_array_equal(dense.area, cc.area)
        ys, xs = np.nonzero(m)
        np.testing.assert_array_equal(cc.ys, ys)
        np.testing.assert_array_equal(cc.xs, xs)
        np.testing.assert_array_equal(cc.lv, cc.lab[ys, xs])
        n_seen += n_ref
    assert n_seen > 100


def test_label_statistics_from_components():
    rng = np.random.default_rng(5)
    for _ in range(10):
        S = rng.random((120, 170)).astype(np.float32)
        cc = _components(rng.random((120, 170)) > 0.55)
        np.testing.assert_array_equal(_label_median(S, cc.lab, cc.n, cc),
                                      _label_median(S, cc.lab, cc.n))


def test_label_median_sort_keys_against_numpy_median():
    """The float32 median through 64-bit sort keys against ``np.median`` label by label, on
    values with both signs, signed zeros, ties and one-pixel labels."""
    rng = np.random.default_rng(12)
    for _ in range(8):
        shape = (int(rng.integers(30, 90)), int(rng.integers(30, 90)))
        cc = _components(rng.random(shape) > 0.5)
        S = rng.choice(np.array([-3.5, -1e-30, -0.0, 0.0, 1e-30, 0.25, 2.0, 7e20], np.float32),
                       shape) * rng.integers(1, 4, shape).astype(np.float32)
        noisy = rng.random(shape) < 0.5
        S[noisy] = rng.standard_normal(int(noisy.sum())).astype(np.float32)
        got = _label_median(S, cc.lab, cc.n, cc)
        ref = [np.median(S[cc.lab == k].astype(np.float64)) for k in range(1, cc.n + 1)]
        np.testing.assert_array_equal(got, ref)
        assert (cc.area[1:] == 1).any() and (cc.area[1:] > 20).any()


def test_hull_pixels_match_convex_hull_image():
    """The row-by-row integer count of the hull's pixels against scikit-image's
    ``convex_hull_image`` (point-in-polygon over the whole box), on seeded shapes: noise of
    every density, opened noise (blobs), discs with gaps, thin diagonal strips, single rows
    and columns, single pixels."""
    rng = np.random.default_rng(31)
    shapes = []
    for _ in range(400):
        h, w = (int(v) for v in rng.integers(1, 70, 2))
        m = rng.random((h, w)) < rng.uniform(0.02, 0.9)
        if rng.random() < 0.4:
            m = ndi.binary_opening(m)
        shapes.append(m)
    for r in (3, 17, 40):
        disc = np.zeros((2 * r + 3, 2 * r + 9), np.uint8)
        cv2.ellipse(disc, (r + 4, r + 1), (r + 3, r), 17, 0, 360, 1, -1)
        disc[::5] = 0
        shapes.append(disc.astype(bool))
    for k in (1, 2, 7):
        strip = np.zeros((90, 60), bool)
        for i in range(90):
            strip[i, (i * 2) // 3 : (i * 2) // 3 + k] = True
        shapes.append(strip)
    shapes += [np.ones((1, 9), bool), np.ones((13, 1), bool), np.ones((1, 1), bool)]
    n = 0
    for m in shapes:
        lab, k = ndi.label(m, structure=_EIGHT)
        if k == 0:
            continue
        sl = ndi.find_objects(lab)[0]
        sub = lab[sl] == 1
        assert _hull_pixels(sub) == int(np.count_nonzero(convex_hull_image(sub)))
        n += 1
    assert n > 300


def test_octagon_bounds_the_hull_and_settles_solid_regions():
    """``_octagon_pixels`` (the box cut by the ranges of ``r + c`` and ``c - r``) is never
    below scikit-image's hull, equals it on a rectangle and a diamond, and is what lets
    ``_shape_ok`` skip the hull: it must settle some solid regions."""
    from reblur.decide.regions import _octagon_pixels

    def octagon(sub):
        rows = np.flatnonzero(sub.any(axis=1))
        first = np.argmax(sub[rows], axis=1)
        last = sub.shape[1] - 1 - np.argmax(sub[rows, ::-1], axis=1)
        return _octagon_pixels(sub.shape, rows, first, last)

    rng = np.random.default_rng(33)
    p = DecisionParams()
    settled = n = 0
    for _ in range(300):
        shape = tuple(int(v) for v in rng.integers(2, 80, 2))
        m = _blobs(rng, shape, rng.uniform(0.1, 0.9), rng.uniform(0.5, 8.0))
        lab, k = ndi.label(m, structure=_EIGHT)
        for i, sl in enumerate(ndi.find_objects(lab)):
            sub = lab[sl] == i + 1
            hull = int(np.count_nonzero(convex_hull_image(sub)))
            bound = octagon(sub)
            assert hull <= bound <= sub.size
            area = int(sub.sum())
            settled += area >= p.min_solidity * bound and area < p.min_solidity * sub.size
            n += 1
    assert n > 500 and settled > 10
    yy, xx = np.mgrid[:21, :21]
    for sub in (np.ones((7, 12), bool), np.abs(yy - 10) + np.abs(xx - 10) <= 10):
        assert octagon(sub) == int(np.count_nonzero(convex_hull_image(sub))) == sub.sum()


def test_label_reaches_matches_ndimage_maximum():
    """Which labels hold a pixel at a level, against ``ndimage.maximum``, with the level on
    pixel values and between them."""
    from reblur.decide.regions import _label_reaches

    rng = np.random.default_rng(34)
    for _ in range(10):
        S = rng.random((90, 130)).astype(np.float32)
        lab, n = ndi.label(_blobs(rng, S.shape, 0.4, 2.0), structure=_EIGHT)
        top = ndi.maximum(S, lab, np.arange(1, n + 1))
        for level in (np.float32(np.median(top)), np.float32(top.min()), np.float32(0.9)):
            np.testing.assert_array_equal(_label_reaches(S, lab, n, level), top >= level)


@pytest.mark.parametrize("connectivity", [8, 4])
def test_components_with_boxes_on_sparse_and_dense_masks(connectivity):
    """``_components(boxes=True)`` -- OpenCV's statistics pass on masks more than a
    quarter foreground, pixel lists and ``find_objects`` below -- against ``ndimage``:
    the same partition, areas and bounding boxes."""
    from reblur.decide.regions import _STATS_SHARE

    rng = np.random.default_rng(35)
    struct = _EIGHT if connectivity == 8 else _FOUR
    paths = set()
    for density in (0.03, 0.15, 0.4, 0.75):
        for _ in range(3):
            m = _blobs(rng, (150, 210), density, rng.uniform(0.7, 3.0))
            cc = _components(m, connectivity=connectivity, pixels=False, boxes=True)
            paths.add(cc.box is not None)
            assert (cc.box is not None) == (m.mean() > _STATS_SHARE)
            lab, n = ndi.label(m, structure=struct)
            assert cc.n == n
            pairs = np.unique(np.stack([lab[m], cc.lab[m]]), axis=1)  # the same partition
            assert pairs.shape[1] == n == np.unique(pairs[1]).size
            got = _boxes(cc, np.arange(1, n + 1))
            for a, b in pairs.T:
                assert got[int(b)] == ndi.find_objects((lab == a).astype(np.int32))[0]
                assert cc.area[b] == np.count_nonzero(lab == a)
            assert cc.area[0] == 0 and (cc.lab[~m] == 0).all()
    assert paths == {True, False}


def test_fill_holes_matches_background_labelling():
    """Holes filled by flooding the outside away against the labelling of the whole
    background (4-connected, clear of the border, at most ``max_area`` pixels)."""
    from reblur.decide.regions import _fill_holes

    rng = np.random.default_rng(36)
    filled = kept = 0
    for _ in range(40):
        shape = tuple(int(v) for v in rng.integers(20, 160, 2))
        m = _blobs(rng, shape, rng.uniform(0.3, 0.8), rng.uniform(0.7, 4.0))
        max_area = int(rng.integers(1, 60))
        lab, n = ndi.label(~m, structure=_FOUR)
        area = np.bincount(lab.ravel(), minlength=n + 1)
        border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
        fill = area <= max_area
        fill[0] = False
        fill[border] = False
        want = m | fill[lab]
        hole = np.ones(n + 1, bool)
        hole[0] = False
        hole[border] = False
        filled += int(np.count_nonzero(fill))
        kept += int(np.count_nonzero(hole & ~fill))
        got = m.copy()
        _fill_holes(got, max_area)
        np.testing.assert_array_equal(got, want)
    assert filled > 20 and kept > 5  # holes filled and holes too large to fill


def test_inradius_matches_scipy():
    """``_inradius`` (OpenCV's float32 transform, squared and rounded) gives scipy's float64
    value to the bit: blobs of every scale, single pixels, one-pixel lines, and a 2400 px
    disc beyond OpenCV's range (scipy's own transform)."""
    from reblur.decide.regions import _CV_INRADIUS_MAX, _inradius

    rng = np.random.default_rng(41)
    masks = [np.ones((1, 1), bool), np.ones((1, 57), bool), np.ones((9, 9), bool)]
    for _ in range(150):
        shape = tuple(int(v) for v in rng.integers(3, 400, 2))
        masks.append(_blobs(rng, shape, rng.uniform(0.2, 0.9), rng.uniform(0.5, 25.0)))
    yy, xx = np.mgrid[:2401, :2401]
    masks.append((yy - 1200) ** 2 + (xx - 1200) ** 2 <= 1200**2)
    radii = []
    for m in masks:
        want = float(ndi.distance_transform_edt(np.pad(m, 1)).max())
        assert _inradius(m) == want
        radii.append(want)
    assert max(radii) > _CV_INRADIUS_MAX and sorted(radii)[-2] > 50  # both paths


def test_shape_test_matches_reference():
    """``_shape_ok`` (rows' spans before the hull) against the hull-first reference on the
    components of seeded masks, with both outcomes of the solidity test present."""
    from reblur.decide.regions import _shape_ok

    rng = np.random.default_rng(32)
    p = DecisionParams()
    outcomes = set()
    for _ in range(40):
        m = ndi.binary_opening(rng.random((120, 160)) < rng.uniform(0.3, 0.8))
        lab, n = ndi.label(m, structure=_EIGHT)
        for i, sl in enumerate(ndi.find_objects(lab)):
            sub = lab[sl] == i + 1
            area = int(sub.sum())
            want = _ref_shape_ok(sub, area, p)
            assert _shape_ok(sub, area, p) == want
            outcomes.add(want)
    assert outcomes == {True, False}


@pytest.mark.parametrize("pi", range(len(PARAMS)))
def test_decide_core_matches_reference(pi):
    p = PARAMS[pi]
    rng = np.random.default_rng(100 + pi)
    n_accepted = n_passed = 0
    for k in range(6):
        shape = (int(rng.integers(150, 260)), int(rng.integers(150, 260)))
        S = _statistic_field(rng, shape)
        known = np.ones(shape, bool)
        if k % 2:
            known &= ~_blobs(rng, shape, 0.1, 6.0)
            known[:, : rng.integers(1, 20)] = False
        threshold = float(rng.uniform(0.8, 1.6))
        mask, cand, counts = _decide_core(S, known, threshold, p)
        rmask, rcand, rcounts = _ref_decide_core(S, known, threshold, p)
        np.testing.assert_array_equal(mask, rmask)
        np.testing.assert_array_equal(cand, rcand)
        assert counts == rcounts
        n_accepted += counts["accepted"]
        n_passed += counts["not_object"]
    assert n_accepted > 5  # the inputs exercise the region tests


def test_region_records_match_reference():
    rng = np.random.default_rng(7)
    n_regions = 0
    for k in range(25):
        shape = (int(rng.integers(20, 200)), int(rng.integers(20, 200)))
        mask = _blobs(rng, shape, rng.uniform(0.02, 0.4), rng.uniform(0.7, 4.0))
        S = rng.random(shape).astype(np.float32) * 5
        y0, x0 = int(rng.integers(0, 5000)), int(rng.integers(0, 5000))
        core = None
        if k % 2:
            cy, cx = int(rng.integers(0, shape[0] // 2)), int(rng.integers(0, shape[1] // 2))
            core = (cy, cx, int(rng.integers(1, shape[0] - cy + 1)),
                    int(rng.integers(1, shape[1] - cx + 1)))
        got = _region_records(mask, S, y0, x0, core=core)
        ref = _ref_region_records(mask, S, y0, x0, core=core)
        assert got == ref
        n_regions += len(ref)
    assert _region_records(np.zeros((5, 7), bool), np.zeros((5, 7), np.float32), 0, 0) == []
    assert n_regions > 50


def test_completeness_matches_reference():
    rng = np.random.default_rng(3)
    outcomes = set()
    for _ in range(60):
        shape = (int(rng.integers(60, 160)), int(rng.integers(60, 160)))
        cand = _blobs(rng, shape, rng.uniform(0.05, 0.5), rng.uniform(1.0, 5.0))
        mask = _blobs(rng, shape, 0.05, 3.0) & ~cand
        m = int(rng.integers(0, 12))
        h, w = shape
        sides = rng.random(4) < 0.7
        band = np.zeros(shape, bool)
        strips = []
        for on, sl in zip(sides, [(slice(0, m), slice(None)), (slice(h - m, None), slice(None)),
                                  (slice(None), slice(0, m)), (slice(None), slice(w - m, None))],
                          strict=True):
            if on:
                band[sl] = True
                strips.append(sl)
        halo = m + int(rng.integers(0, 20))
        core = (slice(halo, max(h - halo, halo + 1)), slice(halo, max(w - halo, halo + 1)))
        got = _clear_of(mask | cand, strips, core)
        assert got == _ref_complete((cand, mask | cand), band, core)
        outcomes.add(got)
    assert outcomes == {True, False}


@pytest.mark.parametrize("band_elements", [1 << 16, 1000])  # one band; 8-row bands
@pytest.mark.parametrize("bands", [1, 3])
def test_change_statistic_matches_reference(bands, band_elements, monkeypatch):
    import reblur.decide.statistic

    # change_statistic reads the band size from its own module
    monkeypatch.setattr(reblur.decide.statistic, "_STAT_BAND", band_elements)
    rng = np.random.default_rng(21 + bands)
    shape = (90, 117)
    for k in range(6):
        m = rng.random(shape + (bands,)).astype(np.float32)
        o = (m + 0.05 * rng.standard_normal(m.shape)).astype(np.float32)
        known = np.ones(shape, bool) if k % 2 == 0 else ~_blobs(rng, shape, 0.2, 3.0)
        sigma = rng.uniform(0.01, 0.1, bands)
        edge_k = [None, rng.uniform(0.1, 0.5, bands), np.zeros(bands)][k % 3]
        curv_k = [None, rng.uniform(0.1, 0.5, bands)][k % 2]
        smooth = [2.0, 0.0, 1.3][k % 3]
        oo, mm = (o[:, :, 0], m[:, :, 0]) if bands == 1 and k % 2 else (o, m)
        got = change_statistic(oo, mm, known, sigma, smooth=smooth, truncate=4.0,
                               edge_k=edge_k, curv_k=curv_k)
        ref = _ref_statistic(oo, mm, known, sigma, smooth, 4.0, edge_k, curv_k)
        # the statistic runs in single precision, the reference in double
        assert got.dtype == np.float32
        np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-6)
        np.testing.assert_array_equal(got[~known], 0.0)
        # twice: the second all-known call reads the cached window weights
        again = change_statistic(oo, mm, known, sigma, smooth=smooth, truncate=4.0,
                                 edge_k=edge_k, curv_k=curv_k)
        np.testing.assert_array_equal(again, got)


@pytest.mark.parametrize("bands", [1, 3])
def test_fit_model_error_matches_reference(bands):
    rng = np.random.default_rng(40 + bands)
    tiles = []
    for k in range(5):
        shape = (int(rng.integers(40, 120)), int(rng.integers(40, 120)))
        m = ndi.gaussian_filter(rng.random(shape + (bands,)), (1.0, 1.0, 0)).astype(np.float32)
        gx = np.gradient(m, axis=1)
        o = (m + 0.3 * gx + 0.01 * rng.standard_normal(m.shape)).astype(np.float32)
        known = np.ones(shape, bool) if k % 2 else ~_blobs(rng, shape, 0.15, 3.0)
        tiles.append((o, m, known))
    o, m, kn = (list(t) for t in zip(*tiles, strict=True))
    sigma = np.full(bands, 0.01)
    n = sum(int(k.sum()) for k in kn)
    fits = set()
    for max_samples in (n * 2, n // 3, 5000):  # all pixels; a sample across the tiles
        got = fit_model_error(o, m, kn, sigma, max_samples=max_samples, rng=9)
        ref = _ref_fit_model_error(o, m, kn, sigma, max_samples=max_samples, rng=9)
        np.testing.assert_array_equal(got[0], ref[0])
        np.testing.assert_array_equal(got[1], ref[1])
        fits.add(tuple(np.concatenate(got)))
    assert len(fits) == 3 and all(f[0] > 0 for f in fits)


def test_sample_order_equals_the_stable_argsort():
    """The order that sorts a sample of indices (``_take_concatenated``): that of numpy's
    stable argsort, for a sample without replacement (the marking shortcut) and for one
    with repeats (the fallback)."""
    from reblur.decide.statistic import _sorting_order

    rng = np.random.default_rng(12)
    for n, k, repeats in ((10_000, 4_000, False), (10_000, 4_000, True), (3, 3, False),
                          (50, 0, False)):
        idx = rng.choice(n, k, replace=repeats)
        assert repeats == (np.unique(idx).size < k)
        np.testing.assert_array_equal(_sorting_order(idx, n), np.argsort(idx, kind="stable"))


def test_tile_completeness_and_stop_incomplete():
    from reblur.decide import Photometry, decide_tile

    ph = Photometry(gain=np.ones(1), offset=np.zeros(1), sigma=np.ones(1),
                    image_shape=(2000, 2000))
    rng = np.random.default_rng(8)
    outcomes = []
    holes = set()
    for _ in range(16):
        shape = (int(rng.integers(150, 230)), int(rng.integers(150, 230)))
        obs = (np.abs(ndi.gaussian_filter(rng.standard_normal(shape), 1.5)) * 2.0)
        for _ in range(3):  # squares, some across the tile's edge band
            y, x = rng.integers(0, shape[0] - 20), rng.integers(0, shape[1] - 20)
            r = int(rng.integers(8, 20))
            obs[y : y + 2 * r, x : x + 2 * r] += rng.uniform(2.0, 6.0)
        if rng.random() < 0.6:  # a square ring: its hole is filled, outside the candidates
            y, x = rng.integers(0, shape[0] - 60), rng.integers(0, shape[1] - 60)
            obs[y : y + 56, x : x + 56] += 5.0
            obs[y + 12 : y + 44, x + 12 : x + 44] -= 5.0
        obs = obs.astype(np.float32)
        reb = np.zeros_like(obs)
        unknown = _blobs(rng, shape, 0.05, 4.0) if rng.random() < 0.5 else None
        box = (500, 600, *shape)
        halo = int(rng.integers(20, 45))
        core = (500 + halo, 600 + halo, shape[0] - 2 * halo, shape[1] - 2 * halo)
        kw = dict(threshold=float(rng.uniform(0.9, 1.5)), photometry=ph, box=box, core=core)
        mask, info = decide_tile(obs, reb, unknown, **kw)
        smask, sinfo = decide_tile(obs, reb, unknown, stop_incomplete=True, **kw)
        # completeness against the reference: two labellings, candidates and mask | cand
        known = np.ones(shape, bool) if unknown is None else ~unknown
        p = DecisionParams()
        S = change_statistic(obs, reb, known, [1.0])
        rmask, rcand, _ = _ref_decide_core(S, known, kw["threshold"], p)
        band = np.zeros(shape, bool)
        m = p.local_radius
        band[:m] = band[-m:] = band[:, :m] = band[:, -m:] = True
        core_sl = (slice(halo, shape[0] - halo), slice(halo, shape[1] - halo))
        assert info["complete"] == _ref_complete((rcand, rmask | rcand), band, core_sl)
        holes.add(bool(np.any(rmask & ~rcand)))
        if info["complete"]:
            np.testing.assert_array_equal(smask, mask)
            assert sinfo == info
        elif smask is not None:  # only the final mask | candidates test found it
            np.testing.assert_array_equal(smask, mask)
            assert sinfo == info
        else:
            assert sinfo["complete"] is False
            assert sinfo["n_unknown"] == info["n_unknown"]
        outcomes.append((info["complete"], smask is None))
    assert (True, False) in outcomes and (False, True) in outcomes
    assert holes == {True, False}  # both ways of the final test


@pytest.mark.parametrize("name", ["smooth", "min_threshold", "max_aspect", "strong_factor"])
@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_decision_params_refuse_non_finite_settings(name, value):
    """NaN passes every ``<`` check: ``smooth=nan`` ran and flagged 0.70 % against 1.08 %."""
    with pytest.raises(ValueError, match=f"DecisionParams.{name} must be a finite number"):
        DecisionParams(**{name: value})


def _ref_grid_interp(grid, y0, x0, h, w, block):
    # the bilinear field on a window by four gathers over the whole window
    from reblur.decide.photometry import _grid_coords

    ny, nx = grid.shape
    iy, iy1, wy = _grid_coords((np.arange(y0, y0 + h) + 0.5) / block - 0.5, ny)
    ix, ix1, wx = _grid_coords((np.arange(x0, x0 + w) + 0.5) / block - 0.5, nx)
    wy, wx = wy[:, None], wx[None, :]
    g00, g01 = grid[iy][:, ix], grid[iy][:, ix1]
    g10, g11 = grid[iy1][:, ix], grid[iy1][:, ix1]
    return (1 - wy) * ((1 - wx) * g00 + wx * g01) + wy * ((1 - wx) * g10 + wx * g11)


@pytest.mark.parametrize("bands", [1, 3])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_field_apply_matches_reference(bands, dtype):
    """A tile mapped through a smooth photometric field, 32 rows at a time, is the
    whole-window expression ``g * r + o`` of the four-gather bilinear fields, stored in the
    tile's type, bit for bit (tiles shorter than a chunk and ending mid-chunk, grids of one
    row or column included)."""
    from reblur.decide.photometry import Photometry

    rng = np.random.default_rng(47)
    cases = [((9, 13), (7, 11, 0, 0)), ((9, 13), (32, 50, 13, 5)),
             ((9, 13), (101, 77, 200, 300)), ((9, 13), (360, 520, 0, 0)),
             ((1, 1), (40, 40, 0, 0)), ((1, 7), (33, 90, 2, 100)), ((6, 1), (75, 40, 90, 0))]
    block = 40
    for (ny, nx), (h, w, y0, x0) in cases:
        fg = 1.0 + 0.05 * rng.standard_normal((bands, ny, nx))
        fo = 0.02 * rng.standard_normal((bands, ny, nx))
        ph = Photometry(gain=np.ones(bands), offset=np.zeros(bands), sigma=np.ones(bands),
                        image_shape=(ny * block, nx * block), field_block=block,
                        field_gain=fg, field_offset=fo)
        r = rng.random((h, w, bands)).astype(dtype)
        got = ph.apply(r if bands > 1 else r[:, :, 0], (y0, x0, h, w))
        want = np.stack([(_ref_grid_interp(fg[c], y0, x0, h, w, block) * r[:, :, c]
                          + _ref_grid_interp(fo[c], y0, x0, h, w, block)).astype(dtype)
                         for c in range(bands)], axis=2)
        assert got.dtype == dtype
        np.testing.assert_array_equal(got if bands > 1 else got[:, :, None], want)


@pytest.mark.parametrize("shape", [(37, 29), (37, 29, 1), (37, 29, 3), (37, 29, 4)])
def test_band_tests_match_numpy(shape):
    """The per-pixel band tests (a tile's known pixels, the photometric inliers, the COG
    writer's no-data) are ``np.all`` / ``np.any`` over the bands, with NaN in some
    bands of some pixels only."""
    from reblur._bands import all_bands, any_bands

    rng = np.random.default_rng(5)
    a = rng.random(shape).astype(np.float32)
    a[rng.random(shape) < 0.2] = np.nan
    for got_fn, fn, b in ((all_bands, np.all, np.isfinite(a)), (any_bands, np.any, np.isnan(a))):
        want = b if b.ndim == 2 else fn(b, axis=2)
        got = got_fn(b)
        assert got.shape == shape[:2] and got.dtype == bool
        np.testing.assert_array_equal(got, want)
        if b.ndim == 3:
            assert 0 < got.sum() < got.size
            assert not np.shares_memory(got, b)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32, np.float64])
@pytest.mark.parametrize("bands", [1, 3, 4])
def test_band_mean_matches_numpy(dtype, bands):
    """The band mean by planes (the overviews' gray, the estimate's band-mean windows) is
    numpy's ``mean(axis=2, dtype=float32)`` value for value, for integer and float
    images whose sums round (values spread over six orders of magnitude), and equals an
    explicit float32 loop over the bands of one pixel."""
    from reblur._bands import mean_bands

    rng = np.random.default_rng(7)
    shape = (67, 131, bands)
    if np.dtype(dtype).kind == "u":
        a = rng.integers(0, np.iinfo(dtype).max, shape, endpoint=True).astype(dtype)
    else:
        a = (rng.random(shape) * 10.0 ** rng.integers(-3, 3, shape)).astype(dtype)
    got = mean_bands(a)
    assert got.dtype == np.float32 and got.shape == shape[:2]
    np.testing.assert_array_equal(got, a.mean(axis=2, dtype=np.float32))
    acc = np.float32(0.0)
    for c in range(bands):
        acc = np.float32(acc + np.float32(a[5, 9, c]))
    assert got[5, 9] == np.float32(acc / np.float32(bands))
    with pytest.raises(ValueError, match="h, w, C"):
        mean_bands(a[:, :, 0])
