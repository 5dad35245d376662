"""The tiled driver of the change decision (:func:`decide_tile`, :func:`tile_boxes`) and the
whole-image :func:`decide`.  Stages 1 and 3 are global: fit them on a sample of tiles, then
pass ``photometry`` and ``threshold`` to :func:`decide_tile` for every tile.  Stage 2 is a
filter of radius ``int(truncate * smooth + 0.5)``; stage 4 looks at whole connected regions.
:func:`decide_tile` takes a padded tile (core plus halo) and returns the core; its result
equals the whole-image :func:`decide` (same photometry and threshold) exactly when every
candidate region reaching the core stays ``params.local_radius`` pixels clear of every tile
edge that is not an image border.  Hence the halo requirement
``halo >= params.local_radius + R``, with ``R`` how far a candidate region (a connected set
of ``S > threshold`` after the opening) reaches out of the core.  ``R`` depends on the data:
take the largest change object expected (``params.halo(R)``) and check
``info["complete"]``; False means a region came too close to the tile edge, and the tile
should be re-run with a larger halo (``info["reach"]``: on which edges).  A caller whose
halo has a ceiling passes ``max_extent``: a region already larger than that in the tile
(an area-wide change) asks for no larger halo -- none would complete it -- and is decided
on the tile (``info["oversize"]``), so the work per tile stays bounded.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np

from .._bands import all_bands
from ._common import _box, _channels, _float
from .params import DecisionParams, _params
from .photometry import Photometry, fit_photometry
from .regions import (
    _Components,
    _decide_core,
    _edge_regions,
    _region_records,
    persistence_test,
)
from .statistic import change_statistic
from .threshold import estimate_threshold


def _prepare(observed, reblurred, unknown):
    o = _float(observed)
    r = _float(reblurred)
    if o.ndim not in (2, 3):
        raise ValueError(f"observed must be (h, w) or (h, w, C), got shape {o.shape}")
    if o.shape != r.shape:
        raise ValueError(f"observed has shape {o.shape} but reblurred has shape {r.shape}")
    known = all_bands(np.isfinite(_channels(o))) & all_bands(np.isfinite(_channels(r)))
    if unknown is not None:
        u = np.asarray(unknown, dtype=bool)
        if u.shape != o.shape[:2]:
            raise ValueError(f"unknown has shape {u.shape}, expected {o.shape[:2]}")
        known &= ~u
    if not known.all():  # keep NaN out of every filter
        kk = known[:, :, None] if o.ndim == 3 else known
        o = np.where(kk, o, 0).astype(o.dtype, copy=False)
        r = np.where(kk, r, 0).astype(r.dtype, copy=False)
    return o, r, known


def tile_boxes(
    image_shape: tuple[int, int], tile_size: int | tuple[int, int], halo: int
) -> Iterator[tuple[tuple[int, int, int, int], tuple[int, int, int, int]]]:
    """Tiles of an image: ``(padded_box, core_box)`` pairs, boxes as ``(y0, x0, h, w)``.

    Cores cover the image without overlap; padded boxes add ``halo`` pixels on every side,
    clipped to the image.
    """
    H, W = (int(v) for v in image_shape)
    th, tw = (tile_size, tile_size) if np.isscalar(tile_size) else tile_size
    if th < 1 or tw < 1 or halo < 0:
        raise ValueError("tile_size must be positive and halo non-negative")
    for y in range(0, H, th):
        for x in range(0, W, tw):
            ch, cw = min(th, H - y), min(tw, W - x)
            py0, px0 = max(y - halo, 0), max(x - halo, 0)
            py1, px1 = min(y + ch + halo, H), min(x + cw + halo, W)
            yield (py0, px0, py1 - py0, px1 - px0), (y, x, ch, cw)


def _tile_statistic(o, matched, known, photometry: Photometry, p: DecisionParams,
                    box: tuple[int, int, int, int], image_shape, previous,
                    reach: np.ndarray | None = None) -> np.ndarray:
    """:func:`change_statistic` over a padded tile, reusing ``previous = (S, box)`` (an
    earlier tile inside this one, same inputs) where its values are exact.

    A value depends on the inputs within ``smooth_radius + pixel_reach`` pixels (the
    Gaussian window, the 3x3 stencils of the model error and the tolerance interval), so
    the earlier values are exact except within that reach of its edges that are not image
    borders; the rest of the tile is
    computed in (at most four) strips, each from its window grown by the reach, cropped.
    """

    def compute(y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        sl = (slice(y0, y1), slice(x0, x1))
        return change_statistic(o[sl], matched[sl], known[sl], photometry.sigma,
                                smooth=p.smooth, truncate=p.truncate,
                                edge_k=photometry.edge_k, curv_k=photometry.curv_k,
                                tolerance=p.tolerance,
                                reach=None if reach is None else reach[sl])

    by0, bx0, bh, bw = box
    if previous is None:
        return compute(0, bh, 0, bw)
    S0, (py0, px0, ph, pw) = previous
    H, W = image_shape if image_shape is not None else (None, None)
    r = p.smooth_radius + p.pixel_reach
    # the exact part of the earlier statistic, in this tile's coordinates
    ey0 = py0 - by0 + (r if py0 > 0 else 0)
    ex0 = px0 - bx0 + (r if px0 > 0 else 0)
    ey1 = py0 + ph - by0 - (0 if H is not None and py0 + ph >= H else r)
    ex1 = px0 + pw - bx0 - (0 if W is not None and px0 + pw >= W else r)
    inside = py0 >= by0 and px0 >= bx0 and py0 + ph <= by0 + bh and px0 + pw <= bx0 + bw
    if not inside or S0.shape != (ph, pw) or ey0 >= ey1 or ex0 >= ex1:
        return compute(0, bh, 0, bw)
    S = np.empty((bh, bw), np.float32)
    oy, ox = by0 - py0, bx0 - px0
    S[ey0:ey1, ex0:ex1] = S0[ey0 + oy : ey1 + oy, ex0 + ox : ex1 + ox]
    strips = [(0, ey0, 0, bw), (ey1, bh, 0, bw), (ey0, ey1, 0, ex0), (ey0, ey1, ex1, bw)]
    for y0, y1, x0, x1 in strips:
        if y0 >= y1 or x0 >= x1:
            continue
        gy0, gy1 = max(y0 - r, 0), min(y1 + r, bh)
        gx0, gx1 = max(x0 - r, 0), min(x1 + r, bw)
        S[y0:y1, x0:x1] = compute(gy0, gy1, gx0, gx1)[y0 - gy0 : y1 - gy0, x0 - gx0 : x1 - gx0]
    return S


def decide_tile(
    observed_tile: np.ndarray,
    reblurred_tile: np.ndarray,
    unknown_tile: np.ndarray | None = None,
    *,
    threshold: float,
    photometry: Photometry,
    box,
    core=None,
    params: DecisionParams | None = None,
    image_shape: tuple[int, int] | None = None,
    stop_incomplete: bool = False,
    statistic: tuple[np.ndarray, Any] | None = None,
    keep_statistic: bool = False,
    reach: np.ndarray | None = None,
    max_extent: int | None = None,
) -> tuple[np.ndarray | None, dict[str, Any]]:
    """Decide change on one padded tile and return its core.

    Parameters
    ----------
    observed_tile, reblurred_tile : (h, w) or (h, w, C) ndarray
        Observation and reblurred reference (NOT photometrically matched: ``photometry``
        is applied here) over the padded tile ``box``.
    unknown_tile : (h, w) bool ndarray, optional
        Pixels the reference does not cover; never change.
    threshold : float
        Global threshold of the statistic (:func:`estimate_threshold` on a sample).
    photometry : Photometry
        Global photometric model (:func:`fit_photometry`).
    box : (y0, x0, h, w) or Box
        Full-image position of the padded tile.
    core : (y0, x0, h, w) or Box, optional
        Full-image box of the part to return, inside ``box``; default the whole tile.
    params : DecisionParams, optional
        Must be the same for every tile.
    image_shape : (int, int), optional
        Full image size (default ``photometry.image_shape``): tile edges on the image
        border need no halo.
    stop_incomplete : bool
        Give up as soon as the tile is known to be incomplete (a level-0 candidate region
        joins the core to the edge band), for a caller that re-runs such tiles with a
        larger halo anyway: ``mask`` is then None and ``info`` holds ``complete`` (False),
        ``reach`` (of the level-0 candidates), ``threshold``, ``strong_threshold`` and
        ``n_unknown`` only.
    statistic : (S, box), optional
        The statistic of an earlier call on a window ``box`` inside this tile, with the
        same inputs there (``info["statistic"]`` of that call): a re-run with a larger
        halo computes the statistic only on the ring it adds, plus the statistic's reach
        (the values are those of a computation over the whole tile).
    keep_statistic : bool
        Return ``(S, box)`` as ``info["statistic"]``, for ``statistic=`` of a re-run.
    reach : (h, w) integer ndarray, optional
        Per-pixel geometric reach of the statistic's tolerance over the padded tile (the
        local displacement field's uncertainty; at most ``params.geometry_reach``).
    max_extent : int, optional
        Largest region (bounding box side, in pixels) a larger halo is meant to complete:
        a region reaching the edge band whose part in this tile is already taller or wider
        is *oversize* (``info["oversize"]``): it never lands in ``reach``, never stops the
        tile (``stop_incomplete``), and is decided on this tile's window.  Default: every
        region may be completed.

    Returns
    -------
    mask : (core h, core w) bool ndarray or None
    info : dict
        ``complete`` (True when the result is guaranteed equal to the whole-image call:
        no candidate region reaching the core comes within ``params.local_radius`` of a
        tile edge that is not an image border; otherwise re-run with a larger halo),
        ``reach`` (the edges, of ``"top"``, ``"bottom"``, ``"left"``, ``"right"``, that
        such a region comes within that distance of: where the halo must grow; oversize
        regions excluded; empty when complete),
        ``oversize`` (how many regions reaching the band are larger than ``max_extent``;
        the tile is then incomplete but no halo can complete it),
        ``regions`` (regions whose first pixel in raster order lies in the core, full-image
        coordinates: each region is listed by one tile), ``counts`` (candidates accepted /
        dropped, over the padded tile), ``threshold``, ``strong_threshold``, ``n_unknown``.

    Notes
    -----
    Halo requirement: ``halo >= params.local_radius + R`` with ``R`` the distance a change
    region reaches out of the core (see the module notes and :meth:`DecisionParams.halo`).
    """
    p = params if params is not None else DecisionParams()
    o, r, known = _prepare(observed_tile, reblurred_tile, unknown_tile)
    by0, bx0, bh, bw = _box(box)
    if o.shape[:2] != (bh, bw):
        raise ValueError(f"tile shape {o.shape[:2]} does not match box size {(bh, bw)}")
    cy0, cx0, ch, cw = (by0, bx0, bh, bw) if core is None else _box(core)
    if cy0 < by0 or cx0 < bx0 or cy0 + ch > by0 + bh or cx0 + cw > bx0 + bw:
        raise ValueError(f"core {(cy0, cx0, ch, cw)} is not inside box {(by0, bx0, bh, bw)}")
    shape = image_shape if image_shape is not None else photometry.image_shape
    matched = photometry.apply(r, (by0, bx0, bh, bw))
    S = _tile_statistic(o, matched, known, photometry, p, (by0, bx0, bh, bw), shape, statistic,
                        reach)
    ly, lx = cy0 - by0, cx0 - bx0
    # completeness: regions reaching the core must stay clear of non-border tile edges
    m = p.local_radius
    band, names = [], []
    if not by0 <= 0:
        band.append((slice(0, m), slice(None)))
        names.append("top")
    if not (shape is not None and by0 + bh >= shape[0]):
        band.append((slice(bh - m, None), slice(None)))
        names.append("bottom")
    if not bx0 <= 0:
        band.append((slice(None), slice(0, m)))
        names.append("left")
    if not (shape is not None and bx0 + bw >= shape[1]):
        band.append((slice(None), slice(bw - m, None)))
        names.append("right")
    core_sl = (slice(ly, ly + ch), slice(lx, lx + cw))
    n_unknown = int(np.count_nonzero(~known[core_sl]))

    cand_reach: list[tuple[list[int], int]] = [([], 0)]

    def level0(cc: _Components) -> bool:
        # the test on the level-0 candidates, from their components: a candidate region
        # joining the core to the band makes the tile incomplete (mask | cand, tested
        # below, is a superset of the candidates); an oversize one does not stop it
        cand_reach[0] = _edge_regions(None, band, core_sl, cc, max_extent)
        return stop_incomplete and bool(cand_reach[0][0])

    mask, cand, counts = _decide_core(
        S, known, float(threshold), p, stop=level0,
        persists=persistence_test(o, matched, known, photometry, p, float(threshold)))
    kept = {"statistic": (S, (by0, bx0, bh, bw))} if keep_statistic else {}
    if mask is None:
        return None, {"complete": False, "reach": [names[i] for i in cand_reach[0][0]],
                      "oversize": cand_reach[0][1], "threshold": float(threshold),
                      "strong_threshold": float(p.strong_factor * threshold),
                      "n_unknown": n_unknown, **kept}
    if np.any(mask & ~cand):  # filled holes: mask | cand has components of its own
        edge, n_over = _edge_regions(mask | cand, band, core_sl, None, max_extent)
    else:  # mask | cand == cand: the test is the one on the candidates
        edge, n_over = cand_reach[0]
    info = {
        "complete": not edge and not n_over,
        "reach": [names[i] for i in edge],
        "oversize": n_over,
        "threshold": float(threshold),
        "strong_threshold": float(p.strong_factor * threshold),
        "counts": counts,
        "regions": _region_records(mask, S, by0, bx0, core=(ly, lx, ch, cw), observed=o,
                                   matched=matched, threshold=float(threshold)),
        "n_unknown": n_unknown,
        **kept,
    }
    return mask[ly : ly + ch, lx : lx + cw].copy(), info


def decide(
    observed: np.ndarray,
    reblurred: np.ndarray,
    unknown: np.ndarray | None = None,
    *,
    threshold: float | None = None,
    photometry: Photometry | None = None,
    params: DecisionParams | None = None,
    field_block: int | None = None,
    threshold_method: str = "auto",
    edge_error: bool = True,
    rng=None,
    **overrides,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Whole-image change decision.

    Parameters
    ----------
    observed, reblurred : (h, w) or (h, w, C) ndarray
        Observation and aligned reblurred reference (not photometrically matched).
    unknown : (h, w) bool ndarray, optional
        Pixels the reference does not cover: excluded from every fit and never change.
        Non-finite pixels are treated as unknown too.
    threshold : float, optional
        Threshold of the statistic; default estimated from the data
        (:func:`estimate_threshold` with ``threshold_method``).
    photometry : Photometry, optional
        Photometric model; default fitted here (:func:`fit_photometry`).
    params : DecisionParams, optional
        Decision parameters; keyword ``overrides`` replace single fields
        (e.g. ``min_area=50``).
    field_block : int, optional
        Smooth photometric field block size when fitting here (default: none).
    threshold_method : {"auto", "otsu", "mad"}
        How to estimate the threshold when it is not given.
    rng : int or numpy.random.Generator, optional
        Seed of the photometric subsampling.

    Returns
    -------
    change : (h, w) bool ndarray
        Change mask, False wherever ``unknown``.
    info : dict
        ``threshold``, ``threshold_info``, ``strong_threshold``, ``photometry`` (dict),
        ``params`` (dict), ``counts``, ``regions``, ``statistic`` (description),
        ``n_unknown``.

    Raises
    ------
    ValueError
        On mismatched shapes or no known pixel.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> ref = rng.random((128, 128)).astype(np.float32)
    >>> obs = 0.9 * ref + 0.05 + 0.01 * rng.standard_normal(ref.shape).astype(np.float32)
    >>> obs[40:80, 40:80] += 0.4
    >>> change, info = decide(obs, ref)
    >>> bool(change[60, 60]), bool(change[10, 10])
    (True, False)
    """
    p = _params(params, overrides)
    o, r, known = _prepare(observed, reblurred, unknown)
    if not known.any():
        raise ValueError("no known pixel: every pixel is unknown or non-finite")
    if photometry is None:
        photometry = fit_photometry(
            o, r, known, field_block=field_block, rng=rng, edge_error=edge_error,
            tolerance=p.tolerance,
            illumination="global" if field_block is not None else p.illumination)
    matched = photometry.apply(r)
    S = change_statistic(o, matched, known, photometry.sigma, smooth=p.smooth, truncate=p.truncate,
                         edge_k=photometry.edge_k, curv_k=photometry.curv_k,
                         tolerance=p.tolerance)
    if threshold is None:
        threshold, tinfo = estimate_threshold(S[known], method=threshold_method,
                                              minimum=p.min_threshold)
    else:
        threshold = float(threshold)
        tinfo = {"method": "given"}
    mask, _, counts = _decide_core(
        S, known, threshold, p,
        persists=persistence_test(o, matched, known, photometry, p, threshold))
    info = {
        "threshold": threshold,
        "threshold_info": tinfo,
        "strong_threshold": float(p.strong_factor * threshold),
        "statistic": "local RMS of robust per-band z-scores, Gaussian window sigma="
        f"{p.smooth:g} px",
        "photometry": photometry.to_dict(),
        "params": p.to_dict(),
        "counts": counts,
        "regions": _region_records(mask, S, 0, 0, observed=o, matched=matched,
                                   threshold=threshold),
        "n_unknown": int(np.count_nonzero(~known)),
    }
    return mask, info

