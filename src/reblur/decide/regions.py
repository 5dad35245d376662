"""Stage 4 of the change decision, regions (:func:`_decide_core`; local up to the extent of
a change region).  A component tree over the levels ``threshold * levels``: at each level
``S > level`` is opened with a disc of ``open_radius`` (removes the thin bands that
parallax and residual mis-registration leave along edges) and labelled (8-connectivity).
A component is dropped if smaller than ``min_area`` or if it holds no *strong* pixel
(``S >= strong_factor * threshold``: hysteresis, a region needs strong evidence somewhere
and then keeps its weaker surroundings down to the threshold); **accepted** if it looks
like an object: solidity (area / convex-hull area) ``>= min_solidity`` and aspect
``area / (2 r_in)^2 <= max_aspect`` (``r_in``: radius of the largest inscribed disc; an
``a x b`` rectangle has aspect ``a / b``); otherwise (a branching network of roads or
vegetation edges, or several objects merged through weak bridges) passed to the next,
stricter level, where it may split into object-like parts.  What is still not object-like
at the last level is dropped.  Accepted regions are trimmed to their half-energy contour
(``S >= boundary_fraction * median(S in region)``: an absolute threshold lies far down the
flank of a strong change and would bleed outwards), pieces below ``min_area`` go, each
region is closed on its own with a disc of ``close_radius`` (an object whose inside partly
matches the background -- a low-contrast object, a roof like the ground -- is found with
bays cut into it; the closing fills those narrower than the disc), enclosed holes up to
``max_hole_area`` are filled, and unknown pixels are never change.  Also here: the
connected components, the region records and the tile-edge reach tests of the tiled driver.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import cv2
import numpy as np
import scipy.ndimage as ndi

from .params import DecisionParams


def _disc(r: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def _hull_pixels(sub: np.ndarray) -> int:
    """Pixels of ``skimage.morphology.convex_hull_image(sub)`` (default options), counted
    row by row in integer arithmetic.

    scikit-image's hull is the polygon around the pixels' edge midpoints (``(r +- 1/2, c)``,
    ``(r, c +- 1/2)``), and a pixel belongs to it when its centre lies inside or on it.
    Doubled, those midpoints are integer points: the hull's vertices come from OpenCV's
    integer convex hull of the row and column end pixels (every hull vertex is one), and on
    each row the polygon spans ``[min, max]`` of its edges' crossings, rationals whose ceiling
    and floor (over 2) are exact integer divisions.  The work is rows x hull edges, where
    ``grid_points_in_poly`` tests every pixel of the box against every edge (most of the
    decision's time on a pair with thousands of false regions).
    """
    h, w = sub.shape
    rows = np.flatnonzero(sub.any(axis=1))
    cols = np.flatnonzero(sub.any(axis=0))
    if rows.size == 0:
        return 0
    r_first = np.argmax(sub[rows], axis=1)
    r_last = w - 1 - np.argmax(sub[rows, ::-1], axis=1)
    c_first = np.argmax(sub[:, cols], axis=0)
    c_last = h - 1 - np.argmax(sub[::-1, cols], axis=0)
    ys = np.concatenate([rows, rows, c_first, c_last]).astype(np.int64)
    xs = np.concatenate([r_first, r_last, cols, cols]).astype(np.int64)
    # doubled edge midpoints of those pixels, as (x, y)
    pts = np.concatenate([np.stack([2 * xs + dx, 2 * ys + dy], axis=1)
                          for dx, dy in ((-1, 0), (1, 0), (0, -1), (0, 1))])
    hull = cv2.convexHull(pts.astype(np.int32).reshape(-1, 1, 2)).reshape(-1, 2)
    hull = hull.astype(np.int64)
    x1, y1 = hull[:, 0], hull[:, 1]
    x2, y2 = np.roll(x1, -1), np.roll(y1, -1)
    keep = y1 != y2  # a horizontal edge's ends are ends of its neighbours too
    x1, y1, x2, y2 = x1[keep], y1[keep], x2[keep], y2[keep]
    up = y1 > y2  # orient every edge downwards (y1 < y2)
    x1, x2 = np.where(up, x2, x1), np.where(up, x1, x2)
    y1, y2 = np.where(up, y2, y1), np.where(up, y1, y2)
    Y = 2 * np.arange(h, dtype=np.int64)[None, :]  # the doubled row centres
    dy = (y2 - y1)[:, None]
    num = x1[:, None] * dy + (Y - y1[:, None]) * (x2 - x1)[:, None]  # crossing x = num / dy
    on = (Y >= y1[:, None]) & (Y <= y2[:, None])
    big = np.iinfo(np.int64).max
    lo = np.where(on, -((-num) // (2 * dy)), big).min(axis=0)  # ceil(x / 2)
    hi = np.where(on, num // (2 * dy), -big).max(axis=0)  # floor(x / 2)
    lo, hi = np.maximum(lo, 0), np.minimum(hi, w - 1)
    return int(np.maximum(hi - lo + 1, 0)[(lo <= hi)].sum())


def _octagon_pixels(shape: tuple[int, int], rows: np.ndarray, first: np.ndarray,
                    last: np.ndarray) -> int:
    """Pixels of a box of ``shape`` whose row ``r`` and column ``c`` keep ``r + c`` and
    ``c - r`` within their ranges over a region (``rows``: its non-empty rows, ``first``,
    ``last``: its first and last column on each): an upper bound of
    :func:`_hull_pixels`.

    The hull's vertices are the region's edge midpoints ``(r +- 1/2, c)``,
    ``(r, c +- 1/2)``, whose ``r + c`` lies within half a unit of the region's range, and
    so does every point of the hull; a pixel centre, with integer ``r + c``, lies inside
    only within the range itself.  The same holds for ``c - r``, the rows and the columns.
    """
    s_lo, s_hi = int((rows + first).min()), int((rows + last).max())
    d_lo, d_hi = int((first - rows).min()), int((last - rows).max())
    r = np.arange(shape[0])
    lo = np.maximum(np.maximum(s_lo - r, r + d_lo), 0)
    hi = np.minimum(np.minimum(s_hi - r, r + d_hi), shape[1] - 1)
    return int(np.maximum(hi - lo + 1, 0).sum())


def _shape_ok(sub: np.ndarray, area: int, p: DecisionParams) -> bool:
    # the hull lies inside the bounding box: area / box >= min_solidity settles the
    # solidity test without the hull
    if p.min_solidity > 0 and area < p.min_solidity * sub.size:
        # the hull holds every pixel between the first and the last of a row (their centres
        # lie on a segment between two of the region's): a region whose rows' spans
        # already hold too many pixels fails without the hull
        rows = np.flatnonzero(sub.any(axis=1))
        first = np.argmax(sub[rows], axis=1)
        last = sub.shape[1] - 1 - np.argmax(sub[rows, ::-1], axis=1)
        if area < p.min_solidity * int(np.sum(last - first + 1)):
            return False
        # ... and it lies inside the region's octagon: a region filling enough of that
        # passes without the hull (43 % of the hulls of 25 MP years-levir's regions)
        if area < p.min_solidity * _octagon_pixels(sub.shape, rows, first, last):
            hull = _hull_pixels(sub)
            if hull and area / hull < p.min_solidity:
                return False
    r_in = _inradius(sub)
    return area / (4.0 * r_in * r_in) <= p.max_aspect


#: Largest inscribed radius (px) :func:`_inradius` takes from OpenCV: float32 holds the
#: squared distances exactly, and its root to well within half a unit of their spacing.
_CV_INRADIUS_MAX = 1000.0


def _inradius(sub: np.ndarray) -> float:
    """Radius of the largest disc inscribed in a region:
    ``scipy.ndimage.distance_transform_edt(np.pad(sub, 1)).max()``, the same float.

    OpenCV's exact Euclidean transform (``DIST_MASK_PRECISE``) is 5x faster but returns
    float32: its maximum, squared and rounded, is the integer squared distance, and
    scipy's value is that integer's float64 root.  Beyond :data:`_CV_INRADIUS_MAX` scipy
    computes it.
    """
    padded = np.pad(sub, 1)
    d = float(cv2.distanceTransform(padded.view(np.uint8), cv2.DIST_L2,
                                    cv2.DIST_MASK_PRECISE).max())
    if d > _CV_INRADIUS_MAX:
        return float(ndi.distance_transform_edt(padded).max())
    return float(np.sqrt(np.float64(round(d * d))))


class _Components(NamedTuple):
    """Connected components of a mask (:func:`_components`).

    Attributes
    ----------
    lab : (h, w) int32 ndarray
        0 for the background, 1..n for the components.
    n : int
        Number of components.
    area : (n + 1,) int ndarray
        Pixel count per label (``area[0]``: 0).
    ys, xs, lv : (k,) int ndarray
        Row, column and label of every foreground pixel, in raster order (empty unless
        listed: ``pixels`` of :func:`_components`).
    box : (n + 1, 4) int ndarray or None
        Tight bounding box ``(y0, x0, y1, x1)`` per label (row 0: the background's), when
        asked for (``boxes`` of :func:`_components`); :func:`_boxes` uses it.
    """

    lab: np.ndarray
    n: int
    area: np.ndarray
    ys: np.ndarray
    xs: np.ndarray
    lv: np.ndarray
    box: np.ndarray | None = None


#: Share of foreground above which :func:`_components` takes areas and boxes from OpenCV's
#: statistics pass: on the candidate masks of the 25 MP years-levir and 45 % pairs of
#: ``benchmarks.cost`` (levels of ``_decide_core``) it cost 1.7-1.9x the pixel list and
#: ``find_objects`` below 10 % foreground, the same at 20-30 %, 0.4-0.7x above.
_STATS_SHARE = 0.25


def _components(mask: np.ndarray, connectivity: int = 8, pixels: bool = True,
                boxes: bool = False) -> _Components:
    """Connected components of a 2-D mask, labelled by OpenCV (which releases the GIL).

    The same partition as ``scipy.ndimage.label`` with the full 3 x 3 (``connectivity=8``)
    or the cross (``4``) structure; the numbering may differ, so callers never rely on it.

    Parameters
    ----------
    mask : (h, w) bool or uint8 ndarray
        Foreground: non-zero pixels.
    connectivity : {8, 4}
    pixels : bool
        Also list the foreground pixels (``ys``, ``xs``, ``lv``), and count the areas from
        them (``cv2.findNonZero``: cheap when the components are a small part of the
        array); False for a dense foreground (e.g. the background of a mask), whose areas
        come from a count over the whole label image instead.
    boxes : bool
        The caller will ask for bounding boxes (:func:`_boxes`).  With ``pixels`` False
        and more than :data:`_STATS_SHARE` of the mask foreground, areas and boxes come
        from OpenCV's statistics pass (``connectedComponentsWithStats``, one thread) and
        travel in ``box``: there it costs less than listing the pixels and scanning the
        label image for the boxes.  On sparser masks it costs more: the pixels are listed
        (the areas counted from them) and :func:`_boxes` scans the label image
        (``ndimage.find_objects``).

    Returns
    -------
    _Components
    """
    m = np.ascontiguousarray(mask)
    if m.dtype == bool:
        m = m.view(np.uint8)
    e = np.zeros(0, np.int32)
    if boxes and not pixels and cv2.countNonZero(m) > _STATS_SHARE * m.size:
        n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=connectivity,
                                                            ltype=cv2.CV_32S)
        area = stats[:, cv2.CC_STAT_AREA].astype(np.intp)
        area[0] = 0
        y0, x0 = stats[:, cv2.CC_STAT_TOP], stats[:, cv2.CC_STAT_LEFT]
        box = np.stack([y0, x0, y0 + stats[:, cv2.CC_STAT_HEIGHT],
                        x0 + stats[:, cv2.CC_STAT_WIDTH]], axis=1)
        return _Components(lab, int(n) - 1, area, e, e, e, box)
    if boxes:  # sparse, or the pixels wanted too
        pixels = True
    n, lab = cv2.connectedComponents(m, connectivity=connectivity, ltype=cv2.CV_32S)
    n = int(n) - 1
    if not pixels:
        area = np.bincount(lab.ravel(), minlength=n + 1)
        area[0] = 0
        return _Components(lab, n, area, e, e, e)
    return _with_pixels(_Components(lab, n, np.zeros(n + 1, np.intp), e, e, e), m)


def _with_pixels(cc: _Components, m: np.ndarray) -> _Components:
    """``cc`` with the foreground pixels of ``m`` listed and the areas counted from them."""
    pts = cv2.findNonZero(m) if cc.n else None
    if pts is None:
        return cc
    pts = pts.reshape(-1, 2)
    xs, ys = pts[:, 0], pts[:, 1]
    # a 1-D take at the flat positions: a third faster than the 2-D fancy index
    lv = np.take(cc.lab, ys.astype(np.intp) * cc.lab.shape[1] + xs)
    area = np.bincount(lv, minlength=cc.n + 1)
    area[0] = 0
    return cc._replace(area=area, ys=ys, xs=xs, lv=lv)


def _boxes(cc: _Components, labels) -> dict[int, tuple[slice, slice]]:
    """Tight bounding boxes (as slices) of some labels of ``cc``.

    From ``cc.box`` when the components carry their boxes; else one pass of
    ``scipy.ndimage.find_objects`` over the label image, whatever the number and size of
    the components (an unbuffered ``np.minimum.at`` over the foreground pixels cost ~40 ms
    per megapixel of components, four times per call).
    """
    labels = np.asarray(labels, np.intp).reshape(-1)
    if labels.size == 0:
        return {}
    if cc.box is not None:
        b = cc.box[labels].tolist()
        return {int(k): (slice(y0, y1), slice(x0, x1))
                for k, (y0, x0, y1, x1) in zip(labels.tolist(), b, strict=True)}
    found = ndi.find_objects(cc.lab, max_label=int(labels.max()))
    return {int(k): found[k - 1] for k in labels}


def _union_box(
    boxes: list[tuple[int, int, int, int]], margin: int, shape: tuple[int, ...]
) -> tuple[slice, slice]:
    """Union of ``(y0, x0, y1, x1)`` boxes grown by ``margin``, clipped to ``shape``."""
    y0 = max(min(b[0] for b in boxes) - margin, 0)
    x0 = max(min(b[1] for b in boxes) - margin, 0)
    y1 = min(max(b[2] for b in boxes) + margin, shape[0])
    x1 = min(max(b[3] for b in boxes) + margin, shape[1])
    return slice(y0, y1), slice(x0, x1)


def _labelled(
    S: np.ndarray, lab: np.ndarray, comps: _Components | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Labels and values of the labelled pixels only (candidates are a small fraction)."""
    if comps is not None:
        return comps.lv, S[comps.ys, comps.xs].astype(np.float64)
    sel = lab > 0
    return lab[sel], S[sel].astype(np.float64)


def _label_reaches(S: np.ndarray, lab: np.ndarray, n: int, level: float) -> np.ndarray:
    """``ndimage.maximum(S, lab, 1..n) >= level`` for labels whose pixels have no NaN in
    ``S`` (the candidates of a threshold on ``S``): which labels hold a pixel at ``level``
    or above.

    One comparison over the array and a gather of the labels where it holds: no reduction
    over every labelled pixel (``np.maximum.at`` over the candidates of a densely changed
    tile took a quarter of its region decision).
    """
    hit = np.zeros(n + 1, bool)
    hit[lab[S >= level]] = True
    return hit[1:]


def _sort_keys(v: np.ndarray) -> np.ndarray:
    """Unsigned integer keys ordered as the float32 values ``v`` (finite; ``-0.0`` sorts
    just before ``0.0``): the IEEE bits with the sign bit set for non-negative values and
    every bit flipped for negative ones."""
    u = np.ascontiguousarray(v, np.float32).view(np.uint32).astype(np.uint64)
    neg = u >= np.uint64(1 << 31)
    return np.where(neg, np.uint64(0xFFFFFFFF) - u, u | np.uint64(1 << 31))


def _from_keys(k: np.ndarray) -> np.ndarray:
    """The float32 values of :func:`_sort_keys` (inverse)."""
    k = k & np.uint64(0xFFFFFFFF)
    pos = k >= np.uint64(1 << 31)
    u = np.where(pos, k - np.uint64(1 << 31), np.uint64(0xFFFFFFFF) - k)
    return u.astype(np.uint32).view(np.float32)


def _label_median(
    S: np.ndarray, lab: np.ndarray, n: int, comps: _Components | None = None
) -> np.ndarray:
    """``ndimage.median(S, lab, 1..n)`` (mean of the two middle values for an even count)
    over the labelled pixels only.

    For a float32 ``S`` (the statistic), one sort of 64-bit keys ``label << 32 |
    order-preserving bits of the value`` (a plain sort, several times faster than the
    two-key ``lexsort`` of an index): the values come out grouped by label and ascending
    within each.
    """
    if S.dtype == np.float32:
        if comps is not None:
            lv, v32 = comps.lv, S[comps.ys, comps.xs]
        else:
            sel = lab > 0
            lv, v32 = lab[sel], S[sel]
        keys = (lv.astype(np.uint64) << np.uint64(32)) | _sort_keys(v32)
        keys.sort()
        vals = _from_keys(keys).astype(np.float64)
    else:
        lv, v = _labelled(S, lab, comps)
        vals = v[np.lexsort((v, lv))]
    counts = np.bincount(lv, minlength=n + 1)[1:]
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    lo = start + (counts - 1) // 2
    hi = start + counts // 2
    return (vals[lo] + vals[hi]) / 2.0


def _decide_core(
    S: np.ndarray, known: np.ndarray, threshold: float, p: DecisionParams,
    stop: Callable[[_Components], bool] | None = None,
    persists: Callable[[np.ndarray, tuple[slice, slice]], np.ndarray | None] | None = None,
) -> tuple[np.ndarray | None, np.ndarray, dict[str, int]]:
    """Region decision on an array; returns (mask, level-0 candidate mask, counts).

    ``stop``, called with the components of the level-0 candidates, may end the decision
    there: the mask is then None (and the counts cover nothing).  ``persists(sub, window)``
    (the region's mask on its bounding ``window`` of the array) is asked about every region
    that is not object-like: a mask (its pixels that persist) accepts them as a thin change
    (``counts["thin"]``), None passes the region on; the evidence test of
    :func:`persistence_test`.

    Level 0 looks at the whole array; every later level only at the window holding the
    regions passed on to it (grown by the opening's reach, so the opening, which never
    adds pixels, gives the same result there as on the whole array), and the boundary cut
    and the hole filling only at the window of the accepted regions.  Connected components
    come from OpenCV with their areas and boxes (no pass over the whole array per label).
    """
    strong = p.strong_factor * threshold
    shape = S.shape
    accepted = np.zeros(shape, bool)
    counts = {"accepted": 0, "small": 0, "weak": 0, "not_object": 0, "thin": 0}
    levels = p.levels if p.region_tests else (1.0,)
    candidates = None
    kernel = _disc(p.open_radius) if p.open_radius > 0 else None
    pending = known
    win: tuple[slice, slice] = (slice(0, shape[0]), slice(0, shape[1]))
    kept: list[tuple[int, int, int, int]] = []  # boxes of the accepted regions
    for li, level in enumerate(levels):
        Sw = S[win]
        m = (Sw > threshold * level) & pending[win]
        if kernel is not None:
            m = cv2.morphologyEx(m.view(np.uint8), cv2.MORPH_OPEN, kernel)
        if candidates is None:  # level 0: the window is the whole array
            candidates = m.view(bool)
        cc = _components(m, pixels=False, boxes=True)
        if li == 0 and stop is not None and stop(cc):
            return None, candidates, counts
        lab, n = cc.lab, cc.n
        if n == 0:
            break
        area = cc.area[1:]
        small = area < p.min_area
        weak = ~small & ~_label_reaches(Sw, lab, n, strong)
        counts["small"] += int(np.count_nonzero(small))
        counts["weak"] += int(np.count_nonzero(weak))
        last = li == len(levels) - 1
        oy, ox = win[0].start, win[1].start
        nxt = None
        passed: list[tuple[int, int, int, int]] = []
        tested = np.flatnonzero(~(small | weak))
        boxes = _boxes(cc, tested + 1)
        for i in tested:
            lbl = int(i) + 1
            sl = boxes[lbl]
            sub = lab[sl] == lbl
            full = (slice(sl[0].start + oy, sl[0].stop + oy),
                    slice(sl[1].start + ox, sl[1].stop + ox))
            box = (full[0].start, full[1].start, full[0].stop, full[1].stop)
            if not p.region_tests or _shape_ok(sub, int(area[i]), p):
                accepted[full] |= sub
                kept.append(box)
                counts["accepted"] += 1
            elif persists is not None and (part := persists(sub, full)) is not None:
                accepted[full] |= part
                kept.append(box)
                counts["thin"] += 1
            elif last:
                counts["not_object"] += 1
            else:
                if nxt is None:
                    nxt = np.zeros(shape, bool)
                nxt[full] |= sub
                passed.append(box)
        if nxt is None:
            break
        pending = nxt
        win = _union_box(passed, int(p.open_radius) + 1, shape)
    if candidates is None:
        candidates = np.zeros(shape, bool)
    if not kept:
        return accepted, candidates, counts
    # from here on every accepted pixel lies in the window of the accepted regions
    win = _union_box(kept, 0, shape)
    if p.boundary_fraction > 0:
        # object boundary at a fixed fraction of the region's own level: the absolute
        # threshold sits far down the flank of a strong change and would bleed outwards
        acc = accepted[win]
        Sw = S[win]
        cc = _components(acc)
        level = _label_median(Sw, cc.lab, cc.n, cc)
        cut = np.maximum(p.boundary_fraction * level, threshold)
        # acc &= Sw >= cut[label], on the accepted pixels only
        drop = ~(Sw[cc.ys, cc.xs] >= cut[cc.lv - 1])
        acc[cc.ys[drop], cc.xs[drop]] = False
        # then pieces below min_area go
        cc = _components(acc)
        if not cc.n:
            return accepted, candidates, counts
        small = (cc.area < p.min_area)[cc.lv]
        acc[cc.ys[small], cc.xs[small]] = False
        if small.all():
            return accepted, candidates, counts
        # the window of what is left: the box of its pixels (listed in raster order)
        ys, xs = cc.ys[~small], cc.xs[~small]
        oy, ox = win[0].start, win[1].start
        win = (slice(oy + int(ys[0]), oy + int(ys[-1]) + 1),
               slice(ox + int(xs.min()), ox + int(xs.max()) + 1))
    if p.close_radius > 0:
        _close_regions(accepted, win, p.close_radius)
    if p.max_hole_area > 0:
        # a hole (a background component clear of the array's border) lies inside the
        # box of the accepted pixels; one pixel of margin keeps the outside connected
        win = _union_box([(win[0].start, win[1].start, win[0].stop, win[1].stop)], 1, shape)
        _fill_holes(accepted[win], p.max_hole_area)
    accepted[win] &= known[win]
    return accepted, candidates, counts


def _fill_holes(mask: np.ndarray, max_area: int) -> None:
    """Fill, in place, the holes of ``mask`` of at most ``max_area`` pixels: the
    4-connected components of its background that do not touch the array's border.

    The outside (the background connected to the border) is flood-filled away on a copy
    bordered by one background pixel, so that only the holes remain; they are labelled and
    measured alone.  Labelling the whole background and counting its labels gives the same
    holes at 4-6x the cost (the background is most of the window of a changed tile).
    """
    inv = np.pad((~mask).view(np.uint8), 1, constant_values=1)
    cv2.floodFill(inv, None, (0, 0), 0, flags=4)
    holes = inv[1:-1, 1:-1]
    if not cv2.countNonZero(holes):
        return
    cc = _components(holes, connectivity=4)
    fill = (cc.area <= max_area)[cc.lv]
    mask[cc.ys[fill], cc.xs[fill]] = True


def persistence_test(
    observed: np.ndarray, matched: np.ndarray, known: np.ndarray, photometry: Any,
    p: DecisionParams, threshold: float,
) -> Callable[[np.ndarray, tuple[slice, slice]], np.ndarray | None] | None:
    """The edge-artefact test of a region that is not object-like (see ``persists`` of
    :func:`_decide_core`), on one array (a padded tile or the whole image).

    The statistic is recomputed (once for the array, when a region first asks) under the
    loose tolerance :attr:`DecisionParams.loose_tolerance` (a shift of up to 1 px, 8 % of
    the local range): the artefacts that residual misregistration and blur-model error
    leave along edges vanish under it, a real thin change (a road, a wall, 10 % of the local
    range or more) does not.  The region persists when at least ``edge_test_fraction`` of
    its pixels stay above ``threshold`` and one above the strong threshold; what is kept of
    it are those pixels, opened like the candidates and in pieces of at least ``min_area``
    (artefact strips joined to a real change go).  None when the test is off
    (``edge_test_fraction == 0`` or no region tests).
    """
    if not p.region_tests or p.edge_test_fraction <= 0:
        return None
    from .statistic import change_statistic

    loose = p.loose_tolerance
    strong = p.strong_factor * threshold
    kernel = _disc(p.open_radius) if p.open_radius > 0 else None
    cache: list[np.ndarray] = []

    def persists(sub: np.ndarray, window: tuple[slice, slice]) -> np.ndarray | None:
        if not cache:  # once per array, when the first region asks (the cost of stage 2)
            cache.append(change_statistic(
                observed, matched, known, photometry.sigma, smooth=p.smooth,
                truncate=p.truncate, edge_k=photometry.edge_k, curv_k=photometry.curv_k,
                tolerance=loose))
        L = cache[0][window]
        v = L[sub]
        if not (v.size and np.mean(v > threshold) >= p.edge_test_fraction
                and v.max() >= strong):
            return None
        part = sub & (L > threshold)
        if kernel is not None:
            part = cv2.morphologyEx(np.pad(part, 1).view(np.uint8), cv2.MORPH_OPEN,
                                    kernel)[1:-1, 1:-1].view(bool)
        cc = _components(part)
        keep = np.zeros(cc.n + 1, bool)
        if cc.n:
            keep[1:] = (cc.area[1:] >= p.min_area) & _label_reaches(L, cc.lab, cc.n, strong)
        part = keep[cc.lab]
        return part if part.any() else None

    return persists


def _close_regions(mask: np.ndarray, win: tuple[slice, slice], radius: int) -> None:
    """Close every connected region of ``mask[win]`` on its own with a disc of ``radius``,
    in place.

    A closing by a convex element stays inside the region's convex hull, hence inside its
    bounding box: each region is closed in its box (padded so that the array's border does
    not act as foreground), and regions never merge, however close.
    """
    sub = mask[win]
    cc = _components(sub, pixels=False, boxes=True)
    if cc.n == 0:
        return
    kernel = _disc(radius)
    pad = radius + 1
    for lbl, sl in _boxes(cc, np.arange(1, cc.n + 1)).items():
        reg = np.pad((cc.lab[sl] == lbl).view(np.uint8), pad)
        closed = cv2.morphologyEx(reg, cv2.MORPH_CLOSE, kernel)[pad:-pad, pad:-pad]
        sub[sl] |= closed.view(bool)


#: A region is "brighter" (or "darker") when at least this share of its pixels is.
POLARITY_SHARE = 0.8


def _region_records(
    mask: np.ndarray, S: np.ndarray, y0: int, x0: int, core=None, *,
    observed: np.ndarray | None = None, matched: np.ndarray | None = None,
    threshold: float | None = None,
) -> list[dict[str, Any]]:
    """Connected regions of ``mask`` (8-conn), full-image coordinates.

    Regions are listed in the raster order of their first pixel (as ``ndimage.label``
    numbers them).  With ``core=(cy0, cx0, ch, cw)`` (array coordinates) only regions whose
    first pixel in raster order lies in the core are listed, so tiles list each region once.

    With ``observed`` and ``matched`` (the photometrically matched reblurred reference,
    ``(h, w, C)``, intensities in [0, 1] of full scale) each record has what an analyst
    triages by: ``difference`` (per band, the mean of observed - matched), ``contrast``
    (the mean of its band-averaged magnitude, a fraction of full scale), ``polarity``
    ("brighter" or "darker" when at least :data:`POLARITY_SHARE` of the pixels are, else
    "mixed"); with ``threshold``, ``score`` = mean statistic / threshold: the region's
    evidence in units of the decision threshold (1 at the threshold; the statistic is the
    RMS of noise z-scores beyond the model's tolerance).
    """
    cc = _components(mask)
    lab = cc.lab
    # first pixel of every label in raster order (the foreground pixels are in raster order)
    lbls, first = np.unique(cc.lv, return_index=True)
    order = np.argsort(first, kind="stable")
    boxes = _boxes(cc, lbls)
    out = []
    for lbl, k in zip(lbls[order].tolist(), first[order].tolist(), strict=True):
        ay, ax = int(cc.ys[k]), int(cc.xs[k])
        if core is not None:
            cy0, cx0, ch, cw = core
            if not (cy0 <= ay < cy0 + ch and cx0 <= ax < cx0 + cw):
                continue
        sl = boxes[lbl]
        sub = lab[sl] == lbl
        area = int(cc.area[lbl])
        # centroid as the mean of the pixel indices: exact integer sums over the box
        sy = int(np.arange(sub.shape[0]) @ np.count_nonzero(sub, axis=1))
        sx = int(np.arange(sub.shape[1]) @ np.count_nonzero(sub, axis=0))
        vals = S[sl][sub]
        rec = {
            "area": area,
            "bbox": [sl[0].start + y0, sl[1].start + x0, sl[0].stop + y0, sl[1].stop + x0],
            "centroid": [
                float(np.float64(sy) / area + sl[0].start + y0),
                float(np.float64(sx) / area + sl[1].start + x0),
            ],
            "mean_stat": float(vals.mean()),
            "max_stat": float(vals.max()),
        }
        if observed is not None and matched is not None:
            d = np.asarray(observed[sl], np.float64) - np.asarray(matched[sl], np.float64)
            d = (d[:, :, None] if d.ndim == 2 else d)[sub]  # (area, C)
            band_mean = d.mean(axis=1)
            pos = float(np.mean(band_mean > 0))
            rec["difference"] = [float(v) for v in d.mean(axis=0)]
            rec["contrast"] = float(np.abs(band_mean).mean())
            rec["polarity"] = ("brighter" if pos >= POLARITY_SHARE else
                               "darker" if pos <= 1 - POLARITY_SHARE else "mixed")
        if threshold is not None and threshold > 0:
            rec["score"] = float(vals.mean()) / float(threshold)
        out.append(rec)
    for k, r in enumerate(out, 1):
        r["label"] = k
    return out


def _clear_of(
    mask: np.ndarray | None, band: list[tuple[slice, slice]], core: tuple[slice, slice],
    cc: _Components | None = None,
) -> bool:
    """No 8-connected component of ``mask`` has pixels both in ``core`` and in ``band``.

    Parameters
    ----------
    mask : (h, w) bool ndarray or None
        None when its components ``cc`` are given.
    band : list of (slice, slice)
        Strips of the array (the tile edges that are not image borders).
    core : (slice, slice)
        The tile's core.
    cc : _Components, optional
        The 8-connected components of ``mask``, if already known.
    """
    return not _reaching(mask, band, core, cc)


def _reaching(
    mask: np.ndarray | None, band: list[tuple[slice, slice]], core: tuple[slice, slice],
    cc: _Components | None = None,
) -> list[int]:
    """Indices of the strips of ``band`` that an 8-connected component of ``mask`` joins
    to ``core`` (empty: the core is clear of the band; see :func:`_clear_of`)."""
    return _edge_regions(mask, band, core, cc)[0]


def _edge_regions(
    mask: np.ndarray | None, band: list[tuple[slice, slice]], core: tuple[slice, slice],
    cc: _Components | None = None, max_extent: int | None = None,
) -> tuple[list[int], int]:
    """The components of ``mask`` that join ``core`` to ``band``, split by size.

    Parameters
    ----------
    mask, band, core, cc
        As for :func:`_clear_of`.
    max_extent : int, optional
        A joining component whose bounding box (within the array) is taller or wider than
        this is *oversize*: it does not count in the strips returned.

    Returns
    -------
    strips : list of int
        Indices of the strips of ``band`` that a joining component no larger than
        ``max_extent`` reaches (every joining component without ``max_extent``).
    n_oversize : int
        Number of joining components larger than ``max_extent``.
    """
    if not band:
        return [], 0
    if cc is None:
        cc = _components(mask, pixels=False, boxes=True)
    lab, n = cc.lab, cc.n
    if n == 0:
        return [], 0
    touch = np.zeros((len(band), n + 1), bool)
    for i, sl in enumerate(band):
        touch[i, lab[sl].ravel()] = True
    touch[:, 0] = False
    any_touch = touch.any(axis=0)
    cy, cx = core
    joined = np.zeros(n + 1, bool)
    n_oversize = 0
    for lbl, (ys, xs) in _boxes(cc, np.flatnonzero(any_touch)).items():
        ya, yb = max(ys.start, cy.start), min(ys.stop, cy.stop)
        xa, xb = max(xs.start, cx.start), min(xs.stop, cx.stop)
        if ya < yb and xa < xb and np.any(lab[ya:yb, xa:xb] == lbl):
            if max_extent is not None and max(ys.stop - ys.start,
                                              xs.stop - xs.start) > max_extent:
                n_oversize += 1
            else:
                joined[lbl] = True
    return [i for i in range(len(band)) if np.any(touch[i] & joined)], n_oversize
