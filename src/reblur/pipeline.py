"""``detect_changes``: the whole method on a pair of (possibly huge) images.

Data flows one way: validate -> coarse alignment (:mod:`reblur.align`) -> photometric
pre-match -> window selection and motion estimate (:mod:`reblur.select`,
:mod:`reblur.estimate`) -> tiled reblur (:mod:`reblur.tiled`) and decision
(:mod:`reblur.decide`) -> :class:`~reblur.result.ChangeResult`.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy import ndimage
from threadpoolctl import threadpool_limits

from ._bands import mean_bands
from .align import AlignParams, OverviewCache, block_means, overview_matrix, refine_alignment
from .align.field import estimate_field
from .decide import (
    DecisionParams,
    change_statistic,
    estimate_threshold,
    fit_photometry,
    tile_boxes,
)
from .decide._common import FIT_BLAS_THREADS, band_map
from .decide.calibrate import calibrate_tolerance, marked_pixels, unchanged_pixels
from .decide.photometry import (
    _SCALE_FLOOR,
    FIT_SAMPLES,
    MIN_FIELD_GAIN,
    IlluminationField,
    fit_poly_field,
    held_levels,
    with_model_error,
)
from .estimate import estimate_motion, intensity_scale
from .grid import GridParams, PoseGrid
from .io import chunk_cached
from .refcache import ReferenceCache, ReferenceRun
from .result import ChangeResult, CropChoice
from .robust import inlier_scale, robust_line
from .rolling import RollingParams, RollingPoses, choose_shutter
from .select import SelectParams, select_windows
from .tiled import SparsePoses, run_tiles
from .tilejob import TileJob, load_tile, pad_box, preload_tiles, run_tile, tile_work

__all__ = ["detect_changes", "ScaledView"]


class ScaledView:
    """Lazy per-band affine view ``(a / scale - offset) / gain`` of an array-like (float32).

    Lets the estimation read observation windows on the reference's photometric scale
    without a full-size copy of a (possibly on-disk) image.  ``exclude(box)`` (optional)
    gives the window's pixels the estimate leaves out (:meth:`Prefit.exclusion`).  With an
    ``illumination`` field (:class:`~reblur.decide.photometry.IlluminationField`, from
    :func:`photometric_prefit`) its gain and offset at each pixel replace ``gain`` and
    ``offset``: ``(a / scale - O(r, c)) / G(r, c)``.
    """

    def __init__(self, array, scale: float, gain=None, offset=None, exclude=None,
                 illumination: IlluminationField | None = None):
        self.array = array
        self.illumination = illumination
        #: pixels the estimate leaves out of its data term (see :func:`estimate_motion`)
        self.exclude = exclude
        self.shape = tuple(array.shape)
        self.dtype = np.dtype(np.float32)
        self.scale = float(scale)
        C = self.shape[2] if len(self.shape) == 3 else 1
        self.gain = np.ones(C, np.float32) if gain is None else np.asarray(gain, np.float32)
        self.offset = np.zeros(C, np.float32) if offset is None else np.asarray(offset, np.float32)

    def __getitem__(self, key):
        a = np.asarray(self.array[key], dtype=np.float32) / self.scale
        if self.illumination is not None:
            return self._flattened(a, key)
        if a.ndim == 3:
            return (a - self.offset) / self.gain
        return (a - self.offset[0]) / self.gain[0]

    def _flattened(self, a: np.ndarray, key) -> np.ndarray:
        """``(a - O) / G`` of the illumination field at the pixels ``key`` selected."""
        k = key if isinstance(key, tuple) else (key,)
        rows = np.arange(self.shape[0])[k[0] if k else slice(None)]
        cols = np.arange(self.shape[1])[k[1] if len(k) > 1 else slice(None)]
        G, Z = self.illumination.at(np.atleast_1d(rows), np.atleast_1d(cols))
        if len(k) > 2:  # a band index too: the field's bands alike
            G, Z = G[:, :, k[2]], Z[:, :, k[2]]
        if G.size != a.size:
            raise ValueError(f"ScaledView cannot index the illumination field by {key!r}")
        return (a - Z.reshape(a.shape)) / G.reshape(a.shape)

    def block_means(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """:func:`reblur.align.block_means` of the view, from those of the array (the
        affine map commutes with block means, so an :class:`~reblur.align.OverviewCache`
        underneath answers without a read)."""
        _, bands = block_means(self.array, k)
        # block_means divides integers by the dtype's maximum, which is ``scale`` here
        raw = intensity_scale(np.dtype(self.array.dtype)) / self.scale
        if self.illumination is not None:
            # the field at the blocks' centres: smooth over a block, so the block means of
            # the flattened image within a fraction of its curvature over a block
            rows = (np.arange(bands.shape[0]) + 0.5) * k - 0.5
            cols = (np.arange(bands.shape[1]) + 0.5) * k - 0.5
            G, Z = self.illumination.at(rows, cols)
            v = (bands * np.float32(raw) - Z) / G
        else:
            v = (bands * np.float32(raw) - self.offset) / self.gain
        grey = v[:, :, 0] if v.shape[2] == 1 else mean_bands(v)
        return grey, v


def _check_inputs(reference, observed) -> None:
    for name, a in (("reference", reference), ("observed", observed)):
        shp = tuple(a.shape)
        if len(shp) not in (2, 3):
            raise ValueError(f"{name} must be (H, W) or (H, W, C), got shape {shp}")
        if min(shp[:2]) < 32:
            raise ValueError(f"{name} is too small ({shp[0]}x{shp[1]}); at least 32x32 is needed")
        dt = np.dtype(a.dtype)
        if dt.kind not in "uif":
            raise ValueError(f"{name} has unsupported dtype {dt}")
        if dt.kind == "f" and isinstance(a, np.ndarray) and not np.isfinite(a).all():
            raise ValueError(f"{name} contains NaN or Inf pixels")
    cr = reference.shape[2] if len(reference.shape) == 3 else 1
    co = observed.shape[2] if len(observed.shape) == 3 else 1
    if cr != co:
        raise ValueError(
            f"reference has {cr} band(s) and observed {co}: convert them to the same bands"
        )


#: Smallest low-resolution difference (a fraction of the reference's 2-98 % range) that
#: counts as a disagreement of the pre-fit (:func:`photometric_prefit`).
_MIN_DISAGREEMENT = 0.05
#: The pre-fit's illumination field wins when it lowers the inliers' residual scale of the
#: low-resolution images to at most this fraction of the global lines' in some band.
#: There the residual is the scene's (the blur's remnant, motion in the scene, changes)
#: more than the sensor's, and a quadratic field takes up part of it whatever the light:
#: pairs without an illumination change measured 0.64-1.1 (``report.json``'s
#: ``decision.prefit_illumination``: the failure modes' black hole, occluders and nodata
#: wedge 0.64-0.69, GoPro and LEVIR pairs 0.74-1.1), the test bed's ramps and vignetting
#: 0.03-0.09 (``python -m benchmarks.failure_modes``).  A field weak enough to stay above
#: the bound is one the global line and the estimate's offset absorb.
PREFIT_FIELD_GAIN = 0.4
#: Samples of the low-resolution maps the pre-fit's field is fitted on: the maps are
#: low-passed far beyond their noise, so twelve coefficients are as well determined by
#: 12 500 of them as by the decision's 50 000, at a quarter of the cost of a choice that
#: every run makes.
PREFIT_FIELD_SAMPLES = 12_500


@dataclass
class Prefit:
    """Output of :func:`photometric_prefit`.

    Attributes
    ----------
    gain, offset : (C,) ndarray
        ``observed ~ gain * reference + offset`` per band.
    agreement : 2-D float ndarray or None
        Low-resolution map over the observation: 1 where the aligned, low-passed images
        agree under that model (within 3.5 inlier scales in every band), 0 where they do
        not (a change, or no reference there), NaN where the reference does not cover.
        Each of its pixels stands for ``factor`` x ``factor`` observation pixels.
    factor : int
        Observation pixels per map pixel (per side).
    info : dict
        The fit of each band (:func:`reblur.robust.robust_line`).
    illumination : IlluminationField or None
        A smooth gain and offset over the image, where it explains the low-resolution
        images markedly better than ``gain`` and ``offset`` (a ramp, vignetting, haze):
        the estimate then reads the observation flattened by it (:class:`ScaledView`).
    illumination_info : dict
        The choice between the field and the global model (residual scales, ratio).
    """

    gain: np.ndarray
    offset: np.ndarray
    agreement: np.ndarray | None = None
    factor: int = 1
    info: list[dict] = field(default_factory=list)
    illumination: IlluminationField | None = None
    illumination_info: dict = field(default_factory=dict)

    def exclusion(self, margin: float) -> Callable[[Any], np.ndarray] | None:
        """``exclude(box) -> (h, w) bool``: the observation pixels of a window inside a large
        disagreement (a change of at least 3 x 3 map pixels, grown by ``margin``
        observation pixels), or None when there is none.  The motion estimate leaves them
        out of its data term: its l1 fit gives up on a window about half covered by a new
        surface, and the pixels around a large change carry no blur the reference can
        explain."""
        if self.agreement is None:
            return None
        dis = self.agreement == 0  # NaN (no reference) is the operator's own business
        dis = ndimage.binary_opening(dis, structure=np.ones((3, 3), bool))
        if not dis.any():
            return None
        grow = int(np.ceil(margin / self.factor)) + 1
        dis = ndimage.binary_dilation(dis, structure=np.ones((3, 3), bool), iterations=grow)
        k = self.factor

        def exclude(box) -> np.ndarray:
            y0, x0, h, w = (int(v) for v in (box.as_tuple() if hasattr(box, "as_tuple")
                                               else box))
            ys = np.clip((np.arange(y0, y0 + h) // k), 0, dis.shape[0] - 1)
            xs = np.clip((np.arange(x0, x0 + w) // k), 0, dis.shape[1] - 1)
            return dis[np.ix_(ys, xs)]

        return exclude


@threadpool_limits.wrap(limits=FIT_BLAS_THREADS, user_api="blas")
def photometric_prefit(
    reference, observed, H0: np.ndarray, s_ref: float, s_obs: float, max_side: int = 512,
    sigma_px: float = 6.0,
) -> Prefit:
    """Per-band gain and offset with ``observed ~ gain * reference + offset`` (robust), and
    where the two images agree under it.

    Fitted at low resolution (block means, :func:`reblur.align.block_means`, the long side
    at most ``max_side``, or the nearest overview an :class:`~reblur.align.OverviewCache`
    already holds) on the aligned, low-pass images (blur matters little there), by
    :func:`reblur.robust.robust_line`: Huber's fit, or a high-breakdown one where a large
    change (a quarter of the view or more, a black hole) drags Huber's away.  The line is
    fitted on a seeded sample of at most :data:`~reblur.decide.photometry.FIT_SAMPLES`
    pixels, as the decision's own photometry is (the low-passed pixels are far from
    independent: a 512 px map holds 262144 of them), and the agreement is judged on all
    of them.  ``s_ref`` and ``s_obs`` are the images' full-scale values
    (:func:`reblur.estimate.intensity_scale`).
    The agreement map lets the window selection keep away from large changes and the
    estimate leave them out (the l1 fit of the motion gives up on a window about half
    covered by a new object).  Both images are low-passed beyond the shake's reach
    (``sigma_px`` observation pixels), so the blur is not a disagreement.
    """
    def low(image, s):
        k = max(1, int(np.ceil(max(image.shape[:2]) / max_side)))
        factor = getattr(image, "factor", None)
        if factor is not None:
            k = factor(k)
        k = min(k, *image.shape[:2])  # a block must fit in the image
        _, b = block_means(image, k)
        # block means of integers come divided by the dtype's maximum; scale by ``s``
        b = b * np.float32(intensity_scale(np.dtype(image.dtype)) / s)
        return b, k

    ref, kr = low(reference, s_ref)
    obs, ko = low(observed, s_obs)
    Hs = np.linalg.inv(overview_matrix(1.0 / ko)) @ H0 @ overview_matrix(1.0 / kr)
    h, w = obs.shape[:2]
    ones = np.ones(ref.shape[:2], np.float32)
    cover = cv2.warpPerspective(ones, Hs, (w, h), flags=cv2.INTER_LINEAR) > 0.999
    cover = ndimage.binary_erosion(cover, iterations=3)
    C = obs.shape[2]
    gain = np.ones(C)
    offset = np.zeros(C)
    if cover.sum() < 100:
        return Prefit(gain, offset)
    sigma = max(2.0, float(sigma_px) / ko)

    # the images in this thread (OpenCV), the fits on the bands' threads (numpy only)
    low_passed = []
    for c in range(C):
        r = cv2.warpPerspective(np.ascontiguousarray(ref[:, :, c]), Hs, (w, h),
                                flags=cv2.INTER_LINEAR)
        low_passed.append((cv2.GaussianBlur(r, (0, 0), sigma),
                           cv2.GaussianBlur(np.ascontiguousarray(obs[:, :, c]), (0, 0), sigma)))

    # the map pixels each band's line is fitted on (flat indices): a seeded sample of the
    # covered ones, without a clipped level of the band
    def sample(c: int) -> np.ndarray:
        pix = np.flatnonzero(cover & ~_clipped(low_passed[c][1], cover))
        if pix.size > FIT_SAMPLES:
            pick = np.random.default_rng(0).choice(pix.size, FIT_SAMPLES, replace=False)
            pix = pix[np.sort(pick)]
        return pix

    fit_pix = [sample(c) for c in range(C)]

    def fit_band(c: int) -> tuple[float, float, dict, np.ndarray | None, float]:
        r, o = low_passed[c]
        pix = fit_pix[c]
        g, b, fit = robust_line(r.ravel()[pix].astype(float), o.ravel()[pix].astype(float))
        if not g > 0.05:  # not a sane gain: keep the identity
            g, b = 1.0, 0.0
        scale = fit.get("scale")
        if scale is None or not scale > 0:
            return g, b, fit, None, np.nan
        res = o.astype(np.float64) - (np.float64(g) * r + np.float64(b))
        centre, scale, _ = inlier_scale(res[cover], scale)
        return g, b, fit, _agrees(res, centre, scale, r, g), scale

    def _agrees(res, centre, scale, r, g) -> np.ndarray:
        # a disagreement is also a visible one: at least 5 % of the scene's range (on
        # noise-free data the inliers' scale is the blur's residual, near zero)
        lo, hi = np.percentile(r[cover], [2, 98])
        band = max(3.5 * scale, _MIN_DISAGREEMENT * float(hi - lo) * abs(g))
        return np.abs(res - centre) < band

    fits = band_map(fit_band, C)
    for c, (g, b, _, _, _) in enumerate(fits):
        gain[c], offset[c] = g, b
    illum, illum_info, field_ok = _prefit_illumination(
        low_passed, cover, fit_pix, fits, int(ko), tuple(observed.shape[:2]), _agrees)
    agree = cover.copy()
    for ok in (field_ok if illum is not None else [f[3] for f in fits]):
        if ok is not None:
            agree &= ok
    agreement = np.where(cover, agree.astype(np.float32), np.float32(np.nan))
    return Prefit(gain, offset, agreement, int(ko), [f[2] for f in fits], illum, illum_info)


#: Share of the covered low-resolution map one extreme level of the observation must hold
#: to count as clipped (:func:`_clipped`).
CLIPPED_SHARE = 0.01


def _clipped(o: np.ndarray, cover: np.ndarray) -> np.ndarray:
    """Map pixels where a band ``o`` of the low-passed observation sits exactly at its
    lowest or highest covered value, when that level holds at least :data:`CLIPPED_SHARE`
    of the covered map: a fill (0 where a mosaic has no data and no nodata tag),
    saturation, a flat new surface.  Their value does not follow the reference, and a
    field fitted through them has a gain of 0 there and a residual near 0: a LEVIR scene
    with its left 600 of 1024 columns at 0 took that field (0.0013 of the line's residual
    scale), whose agreement map held the fill and not the lit part, where the windows
    belong (``tests/test_decide.py``).  Low-passed, an ordinary image reaches its
    extremes at a pixel or two: nothing is left out."""
    out = np.zeros(cover.shape, bool)
    for v in held_levels(o[cover], CLIPPED_SHARE * max(int(cover.sum()), 1)):
        if v is not None:
            out |= o == v
    return out


def _prefit_illumination(low_passed, cover, fit_pix, fits, k: int, shape, agrees):
    """The smooth illumination field of :func:`photometric_prefit` and the choice between
    it and the global lines ``fits`` (the decision's photometry fits the same field,
    :func:`~reblur.decide.photometry.fit_poly_field`): the field when it lowers the inliers'
    residual scale of the low-resolution images to at most :data:`PREFIT_FIELD_GAIN` of the
    lines' in some band.  ``low_passed`` holds each band's (reference, observation) maps of
    ``k`` observation pixels per map pixel, ``fit_pix`` each band's flat indices of the
    sample its line was fitted on.  The field must also keep its gain above
    :data:`~reblur.decide.photometry.MIN_FIELD_GAIN` everywhere.  Returns the field (None:
    the global lines stay), its record, and each band's agreement under it (``agrees(res,
    centre, scale, r, g)``)."""
    C = len(low_passed)
    h, w = low_passed[0][1].shape
    rows, cols = (np.arange(h) + 0.5) * k - 0.5, (np.arange(w) + 0.5) * k - 0.5
    coef_g, coef_o = np.zeros((C, 6)), np.zeros((C, 6))
    s_global, s_field = np.full(C, np.nan), np.full(C, np.nan)
    g_min = np.full(C, np.inf)
    residuals: list = [None] * C

    def fit_band(c: int) -> None:  # each band writes its own rows (numpy only: band_map)
        g, b, _, _, scale = fits[c]
        coef_g[c, 0], coef_o[c, 0] = g, b
        if not scale > 0:
            return
        r, o = low_passed[c]
        pix = fit_pix[c]
        iy, ix = np.divmod(pix, w)
        ys, xs = (iy + 0.5) * k - 0.5, (ix + 0.5) * k - 0.5  # observation pixels
        a, bb = fit_poly_field(ys, xs, r.ravel()[pix].astype(float),
                               o.ravel()[pix].astype(float), shape, (g, b), scale,
                               max_samples=PREFIT_FIELD_SAMPLES)
        coef_g[c], coef_o[c] = a, bb
        G, Z = IlluminationField(a[None], bb[None], shape).at(rows, cols)
        g_min[c] = float(G.min())
        res = o.astype(np.float64) - (G[:, :, 0] * r.astype(np.float64) + Z[:, :, 0])
        centre, s_f, _ = inlier_scale(res[cover], scale)
        s_global[c], s_field[c] = scale, s_f
        residuals[c] = (res, centre, s_f, r, g)

    band_map(fit_band, C)
    ratio = (s_field + _SCALE_FLOOR) / (s_global + _SCALE_FLOOR)
    wins = bool(np.any(ratio <= PREFIT_FIELD_GAIN))
    use = wins and bool(np.min(g_min) > MIN_FIELD_GAIN)
    info = {"model": "field" if use else "global",
            "criterion": f"field if its inlier residual scale is <= {PREFIT_FIELD_GAIN} of "
                         f"the global line's in some band and its gain above "
                         f"{MIN_FIELD_GAIN} everywhere (low-resolution images)",
            "sigma_global": [float(v) for v in s_global],
            "sigma_field": [float(v) for v in s_field],
            "ratio": [round(float(v), 4) for v in ratio]}
    if wins and not use:
        info["rejected"] = (f"its gain falls to {float(np.min(g_min)):.3g}: not light but a "
                            "region the observation does not follow")
    if not use:
        return None, info, None
    field_ = IlluminationField(coef_g, coef_o, tuple(int(v) for v in shape))
    info["field"] = field_.to_dict()
    return field_, info, [None if rr is None else agrees(*rr) for rr in residuals]


@dataclass
class Decided:
    """Output of :func:`reblur_and_decide`."""

    change: Any
    unknown: Any
    reblurred: Any
    threshold: float
    info: dict[str, Any] = field(default_factory=dict)
    regions: list[dict[str, Any]] = field(default_factory=list)


#: Up to this many observation pixels :func:`detect_changes` keeps the reblurred reference
#: in memory by default (above: none, unless ``reblurred_out`` is given).
KEEP_REBLURRED_PIXELS = 64_000_000

#: Long side (px) above which the default spread windows add one near the centre.
CENTRE_WINDOW_SIDE = 16384

def default_windows(shape: tuple[int, int], large_side: int = 2500) -> int:
    """Estimation windows :func:`detect_changes` uses by default for an observation of
    ``shape``: 2 up to ``large_side`` px a side, 4 above, 5 above
    :data:`CENTRE_WINDOW_SIDE`."""
    side = max(int(v) for v in shape[:2])
    if side <= large_side:
        return 2
    return 5 if side > CENTRE_WINDOW_SIDE else 4


#: Side (px) of pass 1's sample windows.  The sample's job is to see the whole image (its
#: windows are spread on a lattice); 256 px windows do that with a quarter of the pixels
#: of 512 px ones: pass 1 at 100 MP 4.1-4.7 -> 1.1 s (``python -m benchmarks.scale --case
#: DIR --mode local``); images up to ~4 MP are sampled whole either way.
_SAMPLE_SIDE = 256


def sample_windows(shape: tuple[int, int], n: int, side: int) -> list[tuple[int, int, int, int]]:
    """Up to ``n`` windows of the ``side``-px tiling of an image, on a lattice over it.

    Rows and columns of the tiling are picked evenly (as many of each as the image's aspect
    asks for), so the sample covers the whole image in both directions.  The threshold,
    the residual scale and the model error are fitted on it: a sample along one line (the
    evenly spaced indices of a row-major list of tiles: the diagonal of a 31 x 31 tiling at
    1 Gpx) misses how they vary over the image.  The same pixel budget in more, smaller
    windows sees more of the image.

    Returns
    -------
    list of (y0, x0, h, w)
    """
    if n < 1 or side < 1:
        raise ValueError(f"need at least one sample window of at least 1 px, got {n}, {side}")
    H, W = (int(v) for v in shape)
    ny, nx = -(-H // side), -(-W // side)
    r = int(np.clip(round(np.sqrt(n * ny / nx)), 1, ny))
    c = int(np.clip(n // r, 1, nx))
    rows = np.unique(np.round(np.linspace(0, ny - 1, r)).astype(int))
    cols = np.unique(np.round(np.linspace(0, nx - 1, c)).astype(int))
    return [(int(i * side), int(j * side), min(side, H - i * side), min(side, W - j * side))
            for i in rows for j in cols]


def reblur_and_decide(
    reference,
    observed,
    poses: SparsePoses,
    *,
    s_ref: float,
    s_obs: float,
    gain: np.ndarray,
    offset: np.ndarray,
    tile_size: int = 1024,
    threshold: float | None = None,
    params: DecisionParams | None = None,
    workers: int = 1,
    keep_reblurred: bool = True,
    change_out=None,
    unknown_out=None,
    reblurred_out=None,
    max_region: int | None = None,
    n_sample_tiles: int = 64,
    edge_error: bool = True,
    scheduler=None,
    work_dir=None,
    progress: Callable[[float], None] | None = None,
    calibration: Sequence[tuple[Sequence[int], np.ndarray | None, np.ndarray | None]]
    | None = None,
) -> Decided:
    """Reblur the reference and decide change, streaming over tiles.

    Two passes.  (1) A sample of up to ``n_sample_tiles`` windows (:func:`sample_windows`,
    at most 256 px a side) spread over the image fits the global photometric model
    (:func:`reblur.decide.fit_photometry`) and the threshold of the change statistic
    (:func:`reblur.decide.estimate_threshold`).  (2) Every tile, padded with a halo of
    ``params.halo(max_region)`` pixels, is reblurred (each padded tile reads only the
    reference window its poses touch), decided (:func:`reblur.decide.decide_tile`) and its
    core written out; a tile whose regions reach the halo's edge is re-run with a larger
    halo on the edges they reach, up to eight times the first, at most four times
    (:func:`reblur.tilejob.run_tile`).  A small image's padded tiles are loaded once
    before pass 1 (:func:`reblur.tilejob.preload_tiles`, at most
    :data:`~reblur.tilejob.PRELOAD_BYTES`): pass 1 cuts its windows from them, and the
    local tile pass starts each tile from its load (a Dask worker loads it again: the same
    arrays).
    On-disk images are read through a chunk cache (:func:`reblur.io.chunk_cached`):
    neighbouring windows share chunks.  Nothing full-size is held but the output masks (and
    the reblurred image if ``keep_reblurred``); outputs given as arrays on disk
    (``change_out``, ``unknown_out``, ``reblurred_out``: zarr arrays,
    :class:`reblur.gis.ReblurredStore`) are written tile by tile, at any size (a given
    ``reblurred_out`` is written whatever ``keep_reblurred`` says).

    With ``calibration`` (the estimation windows ``(y0, x0, h, w)``, the estimate's
    change term on each and the pixels it left out as a known change, or None), the
    tolerance of the statistic is measured on the
    windows' unchanged pixels (:func:`reblur.decide.calibrate.calibrate_tolerance`)
    between the photometric fit and the model-error fit.

    Pass 2 runs on a local thread pool of ``workers`` threads, or with ``scheduler`` as a
    Dask graph (:func:`reblur.dask_backend.decide_tiles`; ``work_dir`` holds its zarr
    outputs): both run the same tile function, so the results are identical.
    """
    p = params or DecisionParams()
    H, W = observed.shape[:2]
    C = observed.shape[2] if len(observed.shape) == 3 else 1
    two_d = len(observed.shape) == 2
    gain = np.asarray(gain, np.float32)
    offset = np.asarray(offset, np.float32)
    if max_region is None:
        # first-try halo for regions reaching 64 px out of a tile: changes are sparse, so
        # few tiles need the re-run with a larger halo, and the halo costs every tile
        # (1024 px tiles: 1.35x the core's pixels, against 2.35x for 256 px)
        max_region = max(32, min(64, tile_size // 4))

    # windows of neighbouring tiles overlap: read on-disk images through a chunk cache
    ref_r = chunk_cached(reference, tile_size, p.halo(max_region))
    obs_r = chunk_cached(observed, tile_size, p.halo(max_region))

    def load(box):
        return load_tile(poses, ref_r, obs_r, box, s_ref=s_ref, s_obs=s_obs,
                         gain=gain, offset=offset)

    # pass 1: photometry and threshold from a sample of windows spread over the image
    # in a function of its own: its windows (and the views of them its fits took) are
    # freed before the tile pass, which they used to outlive
    t_pass1 = time.perf_counter()
    # a small image's padded tiles are loaded once, for both passes (LoadedTiles)
    halo = p.halo(max_region)
    t_load = time.perf_counter()
    held = preload_tiles(load, [t for t, _ in tile_boxes((H, W), tile_size, halo)], C)
    t_load = time.perf_counter() - t_load

    def load_sample(box):
        got = None if held is None else held.window(box)
        return load(box) if got is None else got

    p, photometry, threshold, tinfo, cinfo = _fit_decision(
        load_sample, p, (H, W), n_sample_tiles=n_sample_tiles, tile_size=tile_size,
        workers=workers, calibration=calibration, edge_error=edge_error, threshold=threshold)
    t_pass1 = time.perf_counter() - t_pass1
    t_pass2 = time.perf_counter()

    # pass 2: every tile with its halo (were the calibrated parameters to change the halo,
    # the held tiles would no longer be these tiles: each would load its own)
    if scheduler is not None or p.halo(max_region) != halo:
        held = None
    halo = p.halo(max_region)
    if scheduler is not None:
        from .dask_backend import decide_tiles

        out = decide_tiles(
            reference, observed, poses, scheduler=scheduler, s_ref=s_ref, s_obs=s_obs,
            gain=gain, offset=offset, threshold=threshold, photometry=photometry, params=p,
            halo=halo, tile_size=tile_size, workers=workers,
            keep_reblurred=keep_reblurred or reblurred_out is not None,
            change_out=change_out, unknown_out=unknown_out, reblurred_out=reblurred_out,
            store=work_dir,
            progress=progress,
        )
        change, unknown, reblurred = out.change, out.unknown, out.reblurred
        regions, incomplete = out.regions, out.incomplete
        backend = out.info
    else:
        change = np.zeros((H, W), bool) if change_out is None else change_out
        unknown = np.zeros((H, W), bool) if unknown_out is None else unknown_out
        reblurred = reblurred_out
        if keep_reblurred and reblurred is None:
            reblurred = np.zeros((H, W) if two_d else (H, W, C), np.float32)
        job = TileJob(
            poses=poses, s_ref=float(s_ref), s_obs=float(s_obs), gain=gain, offset=offset,
            threshold=threshold, photometry=photometry, params=p, halo=halo,
            image_shape=(H, W), two_d=two_d, change_out=change, unknown_out=unknown,
            reblurred_out=reblurred, lock_writes=True, client_pid=os.getpid(),
        )
        tiles = list(tile_boxes((H, W), tile_size, halo))
        results: list[dict[str, Any]] = []
        lock = threading.Lock()

        def run(pair) -> None:
            first = None if held is None else held.take(pair[0])
            res = run_tile(job, ref_r, obs_r, *pair, loaded=first)
            with lock:
                results.append(res)
                n_done = len(results)
            if progress is not None:
                progress(n_done / len(tiles))

        run_tiles(run, tiles, workers)
        regions = [r for res in results for r in res["regions"]]
        incomplete = sum(0 if res["complete"] else 1 for res in results)
        backend = {"scheduler": None, "kind": "local threads", "workers": int(workers),
                   "work": tile_work(results)}
    regions.sort(key=lambda r: (r["bbox"][0], r["bbox"][1]) if "bbox" in r else (0, 0))
    info = dict(
        threshold_info=tinfo,
        photometry=photometry.to_dict(),
        params=p.to_dict(),
        statistic="local RMS of robust per-band z-scores of observed - matched reblurred, "
        "outside the model's tolerance interval",
        tolerance=p.tolerance.to_dict(),
        calibration=cinfo,
        n_tiles=-(-H // tile_size) * -(-W // tile_size),
        incomplete_tiles=incomplete,
        halo=halo,
        backend=backend,
        # "fit" holds "preload": the padded tiles a small image loads once, ahead, for both
        # passes (the tile pass's reading and reblurring of them)
        seconds={"fit": round(t_pass1, 3), "tiles": round(time.perf_counter() - t_pass2, 3),
                 "preload": round(t_load if held is not None else 0.0, 3)},
    )
    return Decided(change, unknown, reblurred, threshold, info, regions)


def _fit_decision(load, p: DecisionParams, shape: tuple[int, int], *, n_sample_tiles: int,
                  tile_size: int, workers: int, calibration, edge_error: bool,
                  threshold: float | None):
    """Pass 1 of :func:`reblur_and_decide`: the photometric model, the calibrated
    parameters and the threshold, from a sample of windows spread over the image (loaded by
    ``load(box)``).  Returns ``(params, photometry, threshold, threshold_info,
    calibration_info)``; the windows are dropped on return."""
    H, W = shape
    picked = sample_windows((H, W), n_sample_tiles, min(tile_size, _SAMPLE_SIDE))
    # each window is loaded with the statistic's reach around it, so that its statistic
    # is the one the tile pass computes there (not truncated at the window's edges)
    grown = [pad_box(b, p.local_radius, (H, W)) for b in picked]
    cores = [(slice(b[0] - g[0], b[0] - g[0] + b[2]), slice(b[1] - g[1], b[1] - g[1] + b[3]))
             for b, g in zip(picked, grown, strict=True)]
    loaded: list = [None] * len(picked)

    def load_sample(k: int) -> None:
        loaded[k] = load(grown[k])

    run_tiles(load_sample, list(range(len(picked))), workers)
    known = [~u for _, _, u in loaded]
    if not any(k[c].any() for k, c in zip(known, cores, strict=True)):
        raise ValueError("the reference covers no pixel of the observation")
    # the photometric model is fitted on the windows themselves
    sample = ([o[c] for (o, _, _), c in zip(loaded, cores, strict=True)],
              [r[c] for (_, r, _), c in zip(loaded, cores, strict=True)],
              [k[c] for k, c in zip(known, cores, strict=True)])
    photometry = fit_photometry(*sample, boxes=picked, image_shape=(H, W), rng=0,
                                edge_error=False, illumination=p.illumination)
    cinfo: dict[str, Any] = {"calibrated": False, "shift": p.shift_tolerance,
                             "contrast": p.contrast_tolerance}
    if calibration and p.tolerance_ladder:
        p, cinfo = _calibrate_tolerance(p, calibration, load, photometry, (H, W))
        field_auto = (p.illumination == "auto"
                      and photometry.info.get("illumination", {}).get("model") == "field")
        if "marked" in cinfo and (field_auto
                                  or photometry.info.get("method", "").startswith("high-")):
            # the estimate fits none of its windows (a pair years apart): the tightest band
            # of the scatter is no unchanged class, and a smooth field would absorb
            # area-wide appearance changes; Huber's global fit of it all is the model
            # (WHU 000213 with align=False: JC 0.47 -> 0.14 with the field)
            photometry = fit_photometry(
                *sample, boxes=picked, image_shape=(H, W), rng=0, edge_error=False,
                illumination="global" if p.illumination == "auto" else p.illumination,
                high_breakdown=False)
            cinfo["photometry"] = ("Huber, global: the estimate fits none of its windows")
    if p.edge_test_fraction > 0 and not cinfo.get("calibrated"):
        # the edge-artefact test trusts the model's measured error: where the windows did
        # not calibrate it (a pair years apart, changed everywhere), a strip is as likely
        # a seasonal edge as a new road, and only object-like regions are kept
        p = dataclasses.replace(p, edge_test_fraction=0.0)
        cinfo["edge_test"] = "off: the tolerance is not calibrated"
    if edge_error:
        photometry = with_model_error(photometry, *sample, boxes=picked, tolerance=p.tolerance)
    if threshold is None:
        stats: list = [None] * len(picked)

        def sample_statistic(i: int) -> None:
            o, r, _ = loaded[i]
            k = known[i]
            S = change_statistic(o, photometry.apply(r, grown[i]), k, photometry.sigma,
                                 smooth=p.smooth, truncate=p.truncate,
                                 edge_k=photometry.edge_k, curv_k=photometry.curv_k,
                                 tolerance=p.tolerance)
            sel = k[cores[i]]
            if null_from_inliers:
                # most of the view may be change: the statistic's null from the pixels
                # the photometric model explains (within 3.5 scales in every band)
                sel = sel & photometry.inliers(o, r, grown[i])[cores[i]]
            stats[i] = S[cores[i]][sel]

        null_from_inliers = photometry.info.get("method", "").startswith("high-breakdown")
        run_tiles(sample_statistic, list(range(len(picked))), workers)
        threshold, tinfo = estimate_threshold(stats, minimum=p.min_threshold)
        tinfo["null"] = ("photometric inliers (high-breakdown fit)" if null_from_inliers
                         else "all known pixels")
    else:
        tinfo = {"method": "given"}
    threshold = float(threshold)
    return p, photometry, threshold, tinfo, cinfo


#: Largest fraction of the windows' known pixels the estimate may mark as change for the
#: residual scale to count as noise (beyond: the pair differs everywhere).
_MAX_MARKED = 0.5


#: Fewest unchanged window pixels the tolerance is calibrated on (its target fraction,
#: 2e-4, is then at least a dozen pixels).
_MIN_CALIBRATION_PIXELS = 50_000


def _calibrate_tolerance(p: DecisionParams, windows, load, photometry, shape):
    """``p`` with its tolerance measured on the estimation ``windows``.

    Where the estimate marked most of its windows as change (a pair years apart, a view
    mostly changed), the residual scale ``sigma`` measures appearance change, not noise: the
    statistic's floor (``min_threshold``, in noise units) does not apply, and the threshold
    is the data's own split (:func:`reblur.decide.estimate_threshold`)."""
    margin = p.smooth_radius + p.pixel_reach + 2
    obs, mat, kn, ev = [], [], [], []
    marked = total = 0
    for window in windows:  # (box, chi) or (box, chi, excluded)
        box, chi, excluded = (*window, None)[:3]
        box = tuple(int(v) for v in box)
        g = pad_box(box, p.local_radius, shape)
        o, r, u = load(g)
        core = (slice(box[0] - g[0], box[0] - g[0] + box[2]),
                slice(box[1] - g[1], box[1] - g[1] + box[3]))
        k = ~u
        ev_w = np.zeros_like(k)
        c = None if chi is None or np.shape(chi)[:2] != k[core].shape else chi
        ev_w[core] = unchanged_pixels(k[core], c, margin)
        # what the fit saw: the pixels it left out (a large change known beforehand) say
        # nothing about how well the model fits
        fitted = k[core]
        if excluded is not None and np.shape(excluded) == fitted.shape:
            fitted = fitted & ~np.asarray(excluded, bool)
            ev_w[core] &= ~np.asarray(excluded, bool)
        total += int(np.count_nonzero(fitted))
        mk = marked_pixels(c)
        marked += 0 if mk is None else int(np.count_nonzero(mk & fitted))
        obs.append(o)
        mat.append(photometry.apply(r, g))
        kn.append(k)
        ev.append(ev_w)
    n = sum(int(np.count_nonzero(e)) for e in ev)
    if marked > _MAX_MARKED * max(total, 1):
        return dataclasses.replace(p, min_threshold=0.0), {
            "calibrated": False, "shift": p.shift_tolerance, "contrast": p.contrast_tolerance,
            "floor": 0.0, "marked": marked / max(total, 1),
            "reason": f"the estimate marked {100 * marked / max(total, 1):.0f} % of its "
                      "windows as change: the residual scale is not noise, no floor"}
    if n < _MIN_CALIBRATION_PIXELS:
        return p, {"calibrated": False, "shift": p.shift_tolerance,
                   "contrast": p.contrast_tolerance,
                   "reason": f"{n} unchanged pixels in the estimation windows (fewer than "
                   f"{_MIN_CALIBRATION_PIXELS}): the tolerance is the default"}
    tol, info = calibrate_tolerance(
        obs, mat, kn, ev, photometry.sigma, ladder=p.ladder, threshold=p.min_threshold,
        target=p.calibration_target, margin=p.calibration_margin, smooth=p.smooth,
        truncate=p.truncate)
    info.update(calibrated=True, shift=tol.shift, contrast=tol.contrast, windows=len(obs))
    floor = max(p.min_threshold, info["floor"])
    return dataclasses.replace(p, shift_tolerance=tol.shift, contrast_tolerance=tol.contrast,
                               min_threshold=floor), info


def _kernel_verified(align_info: dict) -> bool:
    """Whether the coarse alignment's kernel polish verified the blur (its method has a
    ``kernel`` stage): only then does its shake extent say anything of the blur."""
    return "kernel" in str(align_info.get("method", "")).split("+")


def blur_reach(align_info: dict) -> float:
    """A radius (px) the blur reaches beyond, from the coarse alignment's record
    (:meth:`reblur.align.Alignment.to_dict` of :func:`align_coarse`): the largest shake
    extent tried below the one at which its kernel polish verified the blur.

    Kernels of that radius were fitted region by region and did not verify (a blur larger
    than the extent fails verification) where those of the next extent did.  0 when the
    smallest extent verified, when no kernel verified the result (an extent reached by
    content that fits no blur says nothing of the blur) or without the record.

    Examples
    --------
    >>> blur_reach({"method": "features+ecc+kernel", "shake_px": 32.0,
    ...             "extents": [{"shake_px": 8.0}, {"shake_px": 16.0}, {"shake_px": 32.0}]})
    16.0
    >>> blur_reach({"method": "features+ecc+gradient", "shake_px": 32.0,
    ...             "extents": [{"shake_px": 8.0}, {"shake_px": 16.0}, {"shake_px": 32.0}]})
    0.0
    """
    if not _kernel_verified(align_info):
        return 0.0
    verified = float(align_info.get("shake_px") or 0.0)
    below = [float(e["shake_px"]) for e in align_info.get("extents") or ()
             if e.get("shake_px") is not None and float(e["shake_px"]) < verified]
    return max(below, default=0.0)


def align_coarse(reference, observed, shakes=(8.0, 16.0, 32.0, 64.0), hint=None,
                 params: AlignParams | None = None):
    """Coarse alignment, trying camera-shake extents from small to large.

    ``hint`` is an optional rough reference -> observation homography in full-resolution
    pixels (:func:`reblur.align.coarse_align`), passed to every extent; ``params`` the
    alignment's options (default ``AlignParams()``).

    :func:`reblur.align.coarse_align` refines at the finest pyramid level where the shake
    spans a few pixels and verifies the result with blur kernels fitted region by region;
    a blur larger than ``shake_px`` fails verification.  The smallest extent that verifies
    works at the finest level, hence the most accurate alignment (on the demo pair: 0.3 px
    worst error at ``shake_px=8`` against 5.4 px at 16).

    A result verified by the gradient blocks alone (no ``kernel`` stage: the polish's blur
    model did not fit) is kept in reserve while larger extents are tried: on a same-scene
    pair the polish then fits and removes the blur bias of the correlation optimum (on the
    Fig. 6 set-up, seed 8 of ``benchmarks/quality.py``: a 10 px corner error left at
    ``shake_px=8``); between captures years apart it never fits, and the reserve is used.
    When the polish of such a result failed on the content (:attr:`Alignment.content_misfit`:
    its regions' kernels explain little of their texture, where a blur larger than the
    extent spreads them instead), no larger extent is tried: the blur model cannot fit
    content that differs, whatever its extent (a years-apart 1 MP pair: one polish
    instead of four).

    The result's :attr:`~reblur.align.Alignment.extents` records every extent tried: its
    method or refusal, its polishes (regions by outcome) and whether it found a content
    misfit.

    The extents share one pyramid of overviews (:func:`reblur.align.coarse_align_shakes`):
    the images are read once, and the features, their ECC refinement and the gradient
    blocks are computed once for each working level they read; the result is the one
    separate :func:`~reblur.align.coarse_align` calls give.
    """
    from .align import coarse_align_shakes

    err: Exception | None = None
    reserve = None
    tried: list[dict[str, Any]] = []
    for s, a in coarse_align_shakes(reference, observed, shakes, params, hint=hint):
        if isinstance(a, Exception):
            err = a
            tried.append(dict(shake_px=float(s), refused=str(a),
                              polishes=[dict(p) for p in getattr(a, "polishes", ())],
                              content_misfit=False))
            continue
        tried.append(dict(shake_px=float(s), method=a.method,
                          polishes=[dict(p) for p in a.polishes],
                          content_misfit=a.content_misfit))
        if "kernel" in a.method.split("+"):
            return dataclasses.replace(a, extents=tuple(tried))
        reserve = reserve or a
        if a.content_misfit:  # a larger extent cannot make the blur model fit the content
            break
    if reserve is not None:
        return dataclasses.replace(reserve, extents=tuple(tried))
    assert err is not None
    raise err


@dataclass
class Estimated:
    """Output of the estimation stage of :func:`detect_changes` (small: it may travel
    from a Dask worker)."""

    base: np.ndarray
    gain: np.ndarray
    offset: np.ndarray
    grid: PoseGrid
    motion: Any
    crop: CropChoice
    align_info: dict[str, Any]
    refine_info: dict[str, Any]
    timings: dict[str, float]
    field: Any = None
    field_info: dict[str, Any] = dataclasses.field(default_factory=dict)
    #: the observation's illumination field when the pre-fit chose one (``gain`` and
    #: ``offset`` then hold its global line; :func:`photometric_prefit`), composed with the
    #: estimate's gain and offset as they are, and the record of that choice
    illumination: IlluminationField | None = None
    illumination_info: dict[str, Any] = dataclasses.field(default_factory=dict)


def _estimate_stage(
    reference,
    observed,
    *,
    grid: PoseGrid | GridParams | None,
    t_max: int,
    rz_max: float,
    rz_step: float | None,
    lam: float,
    align: bool,
    refine: bool,
    local_field: bool,
    windows: int | None,
    large_side: int,
    select: SelectParams | None,
    boxes: list | None,
    align_hint: np.ndarray | None = None,
    align_params: AlignParams | None = None,
    progress: Callable[[str, float], None] | None = None,
    reference_run: ReferenceRun | None = None,
) -> Estimated:
    """Coarse alignment, photometric pre-match, window selection, motion estimate and
    whole-image geometric refinement (steps 1-3 of :func:`detect_changes`).

    With ``reference_run`` (a :class:`~reblur.refcache.ReferenceCache`'s view), the
    reference's overviews, pyramid levels and features come from the cache."""
    timings: dict[str, float] = {}

    def report(stage: str, frac: float) -> None:
        if progress is not None:
            progress(stage, frac)

    Ho, Wo = observed.shape[:2]
    s_ref = intensity_scale(reference.dtype)
    s_obs = intensity_scale(observed.dtype)
    # the low-resolution views of steps 1-3 (alignment, photometric pre-fit, window
    # selection) come from one read of each image (of the reference: one per cache)
    reference = (OverviewCache(reference) if reference_run is None
                 else reference_run.overviews)
    observed = OverviewCache(observed)

    # 1. coarse alignment
    t = time.perf_counter()
    report("align", 0.0)
    if align:
        alignment = align_coarse(reference, observed, hint=align_hint, params=align_params)
        H0 = alignment.H
        align_info = alignment.to_dict()
    else:
        H0 = np.eye(3)
        align_info = dict(method="none")
    timings["align"] = time.perf_counter() - t
    report("align", 1.0)

    # 2. photometric pre-match for the estimation, the images low-passed beyond the blur's
    # reach: the grid's, or the shake extent at which the alignment's kernel polish
    # verified the blur when that is larger (an extent reached without it, by content
    # that fits no blur, says nothing of the blur: a years-apart 25 MP pair's 32 px)
    t = time.perf_counter()
    verified = _kernel_verified(align_info)
    reach = max(float(t_max), float(align_info.get("shake_px") or 0.0) if verified else 0.0)
    prefit = photometric_prefit(reference, observed, H0, s_ref, s_obs, sigma_px=reach / 2.0)
    gain, offset = prefit.gain, prefit.offset
    obs_view = ScaledView(observed, s_obs, gain / 1.0, offset,
                          exclude=prefit.exclusion(margin=reach / 2.0),
                          illumination=prefit.illumination)
    # the reference is read in its own units, scaled by s_ref inside the operator
    timings["photometry"] = time.perf_counter() - t

    # 3. grid, window selection and the motion estimate
    t = time.perf_counter()
    if windows is None:
        windows = default_windows((Ho, Wo), large_side)
    # a grid the caller gave is kept as it is; the default one may widen its translations
    # where the blur reaches beyond them (SelectParams.t_grow)
    given = grid is not None
    if isinstance(grid, GridParams):
        grid = grid.build((Ho, Wo))
    if grid is None:
        if rz_step is None:
            grid = PoseGrid.from_ranges((Ho, Wo), t_max=t_max, rz_max=rz_max, corner_px=1.0)
        else:
            grid = PoseGrid.from_ranges((Ho, Wo), t_max=t_max, rz_max=rz_max,
                                        rz_step=0.5 if rz_step is None else rz_step)
    elif tuple(grid.image_shape) != (Ho, Wo):
        raise ValueError(f"grid geometry {grid.image_shape} does not match the observation")
    report("estimate", 0.0)
    sp = select or SelectParams(lam=lam, windows=windows)
    if given:
        sp = dataclasses.replace(sp, t_grow=1)
    if boxes is not None:
        motion = estimate_motion(reference, obs_view, grid, boxes=boxes, base=H0, lam=lam,
                                 scale=None, refit_photometry=sp.refit_photometry,
                                 bands=sp.bands, t_grow=sp.t_grow,
                                 blur_reach=blur_reach(align_info), max_active=sp.max_active)
        crop = CropChoice(boxes=[tuple(b) for b in motion.boxes], size=int(boxes[0][2]))
    else:
        crop, motion = select_windows(
            reference, obs_view, grid, base=H0, params=sp,
            agreement=(prefit.agreement, prefit.factor), blur_reach=blur_reach(align_info),
            progress=(lambda msg: report("estimate", 0.5)) if progress else None,
        )
    if not np.any(motion.weights > 0):
        raise ValueError("motion cannot be estimated: every pose weight came out zero")
    grid = motion.grid  # its translations widened where the blur reached beyond them
    photo = motion.info.get("photometry")
    b_fit = np.zeros(len(gain)) if photo is None else np.asarray(photo["offset"], float)
    # the estimate found view ~ F w + b on its windows, with view = (obs - offset) / gain
    offset = offset + gain * b_fit
    # one home for the photometric gain: the weights are the fractions of the exposure
    # spent in each pose (sum 1); what they sum to beyond that is a gain of the observation
    weight_sum = float(motion.weights.sum())
    motion.weights = motion.weights / weight_sum
    gain = gain * weight_sum
    motion.info["weight_sum"] = weight_sum
    illum = prefit.illumination
    if illum is not None:  # the same composition with the field: obs ~ G S F w + O + G b
        illum = IlluminationField(illum.gain * weight_sum,
                                  illum.offset + illum.gain * b_fit[:, None], illum.shape)
    timings["estimate"] = time.perf_counter() - t
    report("estimate", 1.0)

    # 3b. geometric check over the whole image, correcting the base homography
    refine_info: dict[str, Any] = {"applied": False, "model": "off"}
    ref_res = None
    if refine:
        t = time.perf_counter()
        report("refine", 0.0)
        ref_res = refine_alignment(reference, observed, motion.weights, grid, H0,
                                   ref_scale=s_ref, obs_scale=s_obs)
        refine_info = ref_res.info
        H0 = ref_res.base
        timings["refine"] = time.perf_counter() - t
        report("refine", 1.0)

    # 3c. local residual displacement (parallax, lens distortion) on a lattice of tie points
    fld, field_info = None, {"applied": False, "reason": "off"}
    if local_field:
        t = time.perf_counter()
        report("field", 0.0)
        # the refinement's poses and whole-image reblur, where it made one (1 MP)
        poses = None if ref_res is None else ref_res.poses
        fe = estimate_field(reference, observed,
                            SparsePoses(motion.weights, grid, H0) if poses is None else poses,
                            ref_scale=s_ref, obs_scale=s_obs,
                            whole=None if ref_res is None else ref_res.whole)
        fld, field_info = fe.field, fe.info
        timings["field"] = time.perf_counter() - t
        report("field", 1.0)

    return Estimated(base=H0, gain=gain, offset=offset, grid=grid, motion=motion, crop=crop,
                     align_info=align_info, refine_info=refine_info, timings=timings,
                     field=fld, field_info=field_info, illumination=illum,
                     illumination_info=prefit.illumination_info)


def _decision_params(decision: DecisionParams | None, illumination: str | None,
                     fld: Any) -> DecisionParams:
    """The decision's options with the ``illumination`` override and the geometric reach of
    the local displacement field (0 without one)."""
    p = decision or DecisionParams()
    if illumination is not None:
        p = dataclasses.replace(p, illumination=illumination)
    if fld is not None:
        p = dataclasses.replace(p, geometry_reach=max(int(p.geometry_reach), fld.max_reach()))
    return p


def _windows_of(motion) -> list[tuple[tuple[int, ...], np.ndarray | None, np.ndarray | None]]:
    """The estimation windows, the estimate's change term on each and the pixels it left
    out as a known change (None where missing)."""
    n = len(motion.boxes)
    chis = list(motion.chi) + [None] * (n - len(motion.chi))
    excl = list(getattr(motion, "excluded", []) or []) + [None] * n
    return [(tuple(int(v) for v in box), chi, ex)
            for box, chi, ex in zip(motion.boxes, chis, excl[:n], strict=True)]


#: What the reported readout fraction measures (``report.json`` ``shutter.readout_meaning``).
READOUT_MEANING = (
    "the drift between the row bands' kernels that the alignment leaves: a constant camera "
    "drift under a rolling shutter is a global blur plus a shear of the rows, which the "
    "alignment's homography takes up, so the sensor's true readout can be larger "
    "(reblur.rolling.readout_fraction)")


def _shutter_stage(reference, view, grid, H0, weights, shutter, params, lam, poses,
                   calibration, local_field, bands="all"):
    """The rolling-shutter model (``shutter="rolling"``) or the choice (``"auto"``):
    the poses and calibration windows to decide with, and the record of the choice."""
    choice = choose_shutter(reference, view, grid, w_start=weights, base=H0, lam=lam,
                            params=params, bands=bands)
    model = "rolling" if shutter == "rolling" else choice.model
    info = dict(asked=shutter, model=model, criterion=choice.criterion,
                readout=choice.rolling.info["readout"],
                readout_quartiles=choice.rolling.info["readout_fit"]["quartiles"],
                readout_meaning=READOUT_MEANING, rolling=choice.rolling.to_dict())
    if model == "rolling":
        m = choice.rolling
        poses = RollingPoses(m, H0)
        if local_field:
            # the global model's field was measured through its reblur, whose misfit of a
            # rolling shutter (a shear growing down the rows) it holds: measured again
            # through the band model, which explains that shear itself, and kept only if it
            # lowers the tie points' residual through the band model (estimate_field's test)
            fe = estimate_field(reference, view, poses,
                                ref_scale=intensity_scale(reference.dtype))
            poses.field = fe.field
            info["field"] = fe.info
        calibration = [(tuple(b), c, None) for b, c in zip(m.boxes, m.chi, strict=True)]
    return poses, calibration, info


def detect_changes(
    reference,
    observed,
    *,
    grid: PoseGrid | GridParams | None = None,
    t_max: int = 12,
    rz_max: float = 3.0,
    rz_step: float | None = None,
    lam: float = 0.1,
    align: bool = True,
    refine: bool = True,
    local_field: bool = True,
    align_hint: np.ndarray | None = None,
    align_params: AlignParams | None = None,
    windows: int | None = None,
    large_side: int = 2500,
    select: SelectParams | None = None,
    boxes: list | None = None,
    tile_size: int = 1024,
    threshold: float | None = None,
    decision: DecisionParams | None = None,
    illumination: str | None = None,
    workers: int = 1,
    shutter: str = "global",
    rolling: RollingParams | None = None,
    keep_reblurred: bool | None = None,
    change_out=None,
    unknown_out=None,
    reblurred_out=None,
    scheduler=None,
    work_dir=None,
    progress: Callable[[str, float], None] | None = None,
    reference_cache: ReferenceCache | None = None,
) -> ChangeResult:
    """Find what changed between a sharp reference and a blurred, re-viewpointed observation.

    Parameters
    ----------
    reference : array-like, (H, W) or (H, W, C)
        Sharp reference (numpy, zarr, tifffile's zarr store: read window by window).
    observed : array-like, (H', W') or (H', W', C)
        Later, motion-blurred observation with the same bands; may differ in size.
    grid : PoseGrid or GridParams, optional
        Pose grid on the observation geometry, or the ranges to build it from
        (:class:`reblur.grid.GridParams`, e.g. ``GridParams(kind="6d", focal=...)`` for
        the scale change, tilt and pan as well).  Default: integer ``|tx|, |ty| <= t_max``
        and ``|rz| <= rz_max`` in steps of ``rz_step`` degrees (the paper's grid with
        ``rz_step=0.5``), whose translations the estimate widens where the blur reaches
        beyond them (``SelectParams.t_grow``, :func:`reblur.estimate_motion`'s ``t_grow``;
        the result's ``motion.grid`` is the grid used), starting wider where the
        alignment's kernel polish found the blur reaching beyond them (:func:`blur_reach`).
        A grid given here is kept.
    t_max, rz_max, rz_step : int, float, float
        Ranges of the default grid.  ``rz_step=None`` (default): the step that moves the
        farthest pixel of the full image by one pixel (solved coarse to fine), because the
        paper's 0.5 degree step moves a corner pixel by ``radius x 0.0087`` px (41 px on a
        6680 px image, 11 px on a 2500 px one) and cannot represent the motion far from
        the centre; ``rz_step=0.5`` gives the paper's grid.  The photometric pre-match
        low-passes the images over ``t_max``, or over the shake extent at which the
        alignment's kernel polish verified the blur when that is larger.
    lam : float
        Eq. 5's ``lambda`` (intensities in [0, 1]).
    align : bool
        Run the coarse alignment (needed when the viewpoint moved beyond the grid).
        ``False`` when the images are already registered (the base homography is the
        identity).
    refine : bool
        After the motion estimate, measure the residual misregistration of the reblurred
        reference on probe windows spread over the whole image and correct the base
        homography (:func:`reblur.align.refine_alignment`): the grid cannot represent a
        residual scale / shear / perspective error of the coarse alignment, and the
        estimation windows do not see the rest of the image.
    local_field : bool
        After the refinement, measure tie points between the reblurred reference and the
        observation on a lattice over the whole image and fit a smooth displacement field
        to what the homography leaves (parallax, lens distortion;
        :func:`reblur.align.field.estimate_field`), applied in the reblur when it predicts
        held-out tie points clearly better than the homography alone.
    align_hint : (3, 3) array-like, optional
        A rough reference -> observation homography in full-resolution pixels (a few
        degrees and tens of pixels off is fine) that seeds the coarse alignment instead
        of the features and rotation hypotheses (:func:`reblur.align.coarse_align`'s
        ``hint``): it reaches pairs the alignment refuses on its own (large rotations,
        captures years apart).  Needs ``align=True``.
    align_params : AlignParams, optional
        Options of the coarse alignment (:class:`reblur.align.AlignParams`: method,
        pyramid sizes, thresholds of its stages and checks).
    windows : int, optional
        Windows estimated jointly (1 = the paper's Algorithm 1, single growing crop).
        Default: 2 up to ``large_side``, 4 above, 5 above ``CENTRE_WINDOW_SIDE`` (16384
        px), spread around the principal point: a small roll about a distant centre is only
        observable from windows far apart (``benchmarks/large_motion.py``: on 41.6 MP,
        unseen windows reach 23-38 dB from one central window with the paper's grid, 49-63
        dB from two corners and 58-68 dB from four with the sized grid).  The spread
        placement puts four near the corners and the fifth near the centre, whose blur
        (the translations alone) the corners constrain only indirectly at these sizes
        (``benchmarks/motion_check.py``, centre window against the true blur, 5 windows /
        4: 53.9 / 50.9 dB at 400 MP, 57.2 / 52.8 dB at 1 Gpx; at 100 MP four suffice,
        57.2 dB).  The windows share a pixel budget
        (:attr:`reblur.select.SelectParams.spread_pixels`): 500 px for two, 400 px for
        four or five.
    large_side : int
        Long side (pixels) above which the large-image defaults apply.
    select : SelectParams, optional
        Constants of Algorithm 1.
    boxes : list of (y0, x0, h, w), optional
        Skip the selection and estimate on these windows.
    tile_size : int
        Tile side for reblur and decision.
    threshold : float, optional
        Override the data-driven decision threshold (units of the decision statistic).
    decision : DecisionParams, optional
        Decision and clean-up settings.
    illumination : {"auto", "global", "field"}, optional
        The photometric model (:attr:`DecisionParams.illumination`; default ``"auto"``:
        a smooth field where it explains the data markedly better than one gain and
        offset).  Overrides ``decision.illumination``.
    workers : int
        Threads pulling tiles (with a local Dask scheduler: its threads or processes).
    shutter : {"global", "rolling", "auto"}
        The shutter model.  ``"rolling"``: row bands with their own pose weights
        (:mod:`reblur.rolling`), estimated from the global estimate on windows spread over
        the rows; ``"auto"``: fits both on those windows and keeps the rolling model only
        when it explains them clearly better (:func:`reblur.rolling.choose_shutter`).
        ``result.decision["shutter"]`` records the choice, the criterion, the estimated
        readout fraction and the per-band motion.
    rolling : RollingParams, optional
        Settings of the rolling model and of the choice.
    keep_reblurred : bool, optional
        Return the full reblurred reference in memory (default: when the observation has at
        most :data:`KEEP_REBLURRED_PIXELS` pixels).
    change_out, unknown_out : array-like, optional
        Where to write the full-size masks (e.g. zarr arrays); default numpy arrays.
    reblurred_out : array-like, optional
        Where to write the full-size matched reblurred reference, tile by tile, at any size
        (e.g. a :class:`reblur.gis.ReblurredStore` on disk, float32 ``(H, W[, C])``
        values in [0, 1] of full scale); ``result.reblurred`` is then this array, whatever
        ``keep_reblurred`` says.
    scheduler : None or str or distributed.Client
        None (default): the local path, a thread pool pulling tiles.  ``"threads"``,
        ``"processes"``, ``"tcp://host:port"`` (a running Dask scheduler), ``"distributed"``
        (the current client) or a :class:`distributed.Client`: the reblur-and-decide pass
        runs as a Dask graph (:mod:`reblur.dask_backend`) and, on a cluster, the motion
        estimate runs once on one worker.  Same result as the local path.  Inputs for
        other processes must be numpy arrays (small images), zarr arrays or TIFF-backed
        arrays (reopened by path in each worker).
    work_dir : path, optional
        With ``scheduler``: directory of the zarr outputs the workers write (default a
        temporary directory; it must be shared storage for a cluster on several
        machines).  For more than ``reblur.dask_backend.NUMPY_MAX_PIXELS`` pixels the
        masks stay there as zarr arrays (``result.decision["backend"]["store"]``).
    progress : callable, optional
        ``progress(stage, fraction)`` for progress bars.
    reference_cache : ReferenceCache, optional
        What depends on the reference alone (its overviews, alignment pyramid levels and
        features), computed by the first call that uses the cache and reused by the next
        ones: pass one :class:`reblur.refcache.ReferenceCache` of ``reference`` to every
        comparison of this reference (:func:`reblur.many.detect_changes_many` does).  The
        result is the one a call without the cache gives;
        ``result.decision["reference_cache"]`` says what was reused.

    Returns
    -------
    ChangeResult

    Raises
    ------
    ValueError
        Invalid inputs, textureless images (motion cannot be estimated), or
        :class:`reblur.align.AlignmentError` when the images cannot be aligned.

    Examples
    --------
    >>> import numpy as np, reblur
    >>> from reblur.simulate import random_camera_path, blur_along_path
    >>> rng = np.random.default_rng(1)
    >>> import cv2
    >>> ref = cv2.GaussianBlur(rng.random((400, 400)), (0, 0), 2)
    >>> ref = (ref - ref.min()) / np.ptp(ref)
    >>> path = random_camera_path(1, center=(199.5, 199.5), t_max=3, rz_max=0.5)
    >>> obs = blur_along_path(ref, path, dtype=np.float64)[0].reshape(400, 400)
    >>> obs[150:200, 150:200] = 1.0                    # something new appeared
    >>> res = reblur.detect_changes(ref, obs, align=False, t_max=5, rz_max=1)
    >>> bool(res.change[160:190, 160:190].mean() > 0.9), bool(res.change[:100].mean() < 0.01)
    (True, True)
    """
    timings: dict[str, float] = {}
    t_all = time.perf_counter()

    def report(stage: str, frac: float) -> None:
        if progress is not None:
            progress(stage, frac)

    _check_inputs(reference, observed)
    if shutter not in ("global", "rolling", "auto"):
        raise ValueError(f"shutter must be 'global', 'rolling' or 'auto', got {shutter!r}")
    Ho, Wo = observed.shape[:2]
    s_ref = intensity_scale(reference.dtype)
    s_obs = intensity_scale(observed.dtype)
    if align_hint is not None and not align:
        raise ValueError("align_hint needs align=True: the hint seeds the coarse alignment")
    if align_params is not None and not isinstance(align_params, AlignParams):
        raise TypeError(f"align_params must be an AlignParams, got {type(align_params).__name__}")
    if reference_cache is not None and reference_cache.reference is not reference:
        raise ValueError("reference_cache was made for another reference: pass "
                         "reference_cache.reference as the reference, or a new "
                         "ReferenceCache(reference)")
    options = dict(grid=grid, t_max=t_max, rz_max=rz_max, rz_step=rz_step, lam=lam,
                   align=align, refine=refine, local_field=local_field, windows=windows,
                   large_side=large_side, select=select, boxes=boxes,
                   align_hint=align_hint, align_params=align_params)
    cache_info: dict[str, Any] | None = None
    est = None
    if scheduler is not None:
        from .dask_backend import portable, run_once, scheduler_kind

        if scheduler_kind(scheduler) == "distributed":
            # the motion estimate runs once, on one worker; only its result travels back
            report("estimate", 0.0)
            est = run_once(_estimate_stage, portable(reference, "reference", work_dir),
                           portable(observed, "observed", work_dir), scheduler=scheduler,
                           **options)
            report("estimate", 1.0)
            if reference_cache is not None:
                cache_info = {"used": False, "reason": "the estimate ran on a Dask worker"}
            reference_cache = None
    if est is None:
        run = reference_cache.begin() if reference_cache is not None else None
        est = _estimate_stage(reference, observed, progress=progress, reference_run=run,
                              **options)
        if run is not None:
            cache_info = dict(run.to_dict(), used=True)
    timings.update(est.timings)
    H0, gain, offset, grid, motion = est.base, est.gain, est.offset, est.grid, est.motion

    # 4. tiled reblur and decision
    t = time.perf_counter()
    poses = SparsePoses(motion.weights, grid, H0, field=est.field)
    calibration = _windows_of(motion)
    shutter_info: dict[str, Any] = {"asked": shutter, "model": "global"}
    if shutter != "global" and motion.info.get("capped"):
        # the band model holds the global support in each of its bands, from a warm start
        # of them all: a support that filled the estimate's pose bound made it grind
        shutter_info["skipped"] = (
            f"the blur filled the estimate's pose bound ({motion.info.get('max_active')} "
            "poses) in a solve: a dense blur such as defocus, not a rolling shutter's "
            "drift; the band model, which would hold that support in each row band, was "
            "not fitted")
    elif shutter != "global":
        t_sh = time.perf_counter()
        poses, calibration, shutter_info = _shutter_stage(
            reference, ScaledView(observed, s_obs, gain, offset, illumination=est.illumination),
            grid, H0, motion.weights,
            shutter, rolling, lam, poses, calibration, local_field,
            bands=(select or SelectParams()).bands)
        timings["shutter"] = time.perf_counter() - t_sh
        t = time.perf_counter()
    keep = (Ho * Wo <= KEEP_REBLURRED_PIXELS) if keep_reblurred is None else keep_reblurred
    report("reblur + decide", 0.0)
    dec = reblur_and_decide(
        reference, observed, poses, s_ref=s_ref, s_obs=s_obs, gain=gain, offset=offset,
        tile_size=tile_size, threshold=threshold, workers=workers,
        params=_decision_params(decision, illumination, getattr(poses, "field", None)),
        keep_reblurred=keep, change_out=change_out, unknown_out=unknown_out,
        reblurred_out=reblurred_out, scheduler=scheduler, work_dir=work_dir,
        progress=(lambda f: report("reblur + decide", f)) if progress else None,
        calibration=calibration,
    )
    timings["reblur_decide"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_all
    dec.info["prefit_gain"] = gain.tolist()
    dec.info["prefit_offset"] = offset.tolist()
    dec.info["prefit_illumination"] = est.illumination_info
    dec.info["shutter"] = shutter_info
    if cache_info is not None:
        dec.info["reference_cache"] = cache_info
    return ChangeResult(
        change=dec.change,
        unknown=dec.unknown,
        reblurred=dec.reblurred,
        motion=motion,
        alignment=H0,
        crop=est.crop,
        threshold=dec.threshold,
        decision=dict(dec.info, alignment=dict(est.align_info, refinement=est.refine_info,
                                                field=est.field_info)),
        timings=timings,
        regions=dec.regions,
        field=est.field,
    )
