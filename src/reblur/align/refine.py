"""Geometric check and refinement of the coarse alignment, after the motion estimate.

The pose grid holds in-plane rotations and translations only, and the motion is estimated
on a few windows; a residual error of the coarse alignment that the grid cannot represent
(a scale, shear or perspective error of 1e-4 is 0.2 px at 2000 px from the centre) or that
the windows cannot see shows up far from them as edges that do not line up -- false alarms
on every strong edge of the unseen part of the image.

This module measures that error where it matters, on the data: probe windows spread over
the part of the observation the reference covers under every pose (:func:`covered_box`)
are reblurred with the estimated weights and registered to the observation by a
sub-pixel translation (ECC, :func:`cv2.findTransformECC`, invariant to gain and offset;
the displacement field's tie points use :func:`tie_shift`).  The probe
displacements ``p_i`` at the probe centres ``c_i`` are fitted by a homography
``G: c -> c + p`` (affine with fewer than 12 reliable probes), robustly (RANSAC, then
least squares on the inliers), and the base homography becomes ``G^-1 @ base``: the
reblurred image moves onto the observation everywhere.  Composing the correction before
the poses instead of after them differs by the commutator of two near-identity transforms
(second order: ~0.005 px for a 0.2 px correction and a 3 degree roll over 2000 px).  The
residual displacement before and after is reported; a correction that does not reduce it
is not applied.

Nothing here stops the run: a probe that cannot be measured (its window maps beyond the
horizon of a pose, ECC fails, values are not finite) is skipped with the reason, and a
correction that is degenerate (singular, folding the image) or implausible (moving the
corners by more than a few probe sizes) is rejected with the reason
(``Refinement.info["rejected"]``), the base left as it was.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from .._bands import BandMean
from .._memory import available_cpus, thread_map
from ..grid import PoseGrid, map_points
from ..tiled import SparsePoses, WholeReblur, reblur_tile, reblur_windows, valid_polygon
from ..warp import Box, read_window
from .result import AlignmentError
from .verify import check_plausible, max_corner_shift

__all__ = ["ProbeShift", "RefineParams", "Refinement", "covered_box", "measure_shifts",
           "probe_boxes", "refine_alignment", "tie_shift"]


@dataclass(frozen=True)
class ProbeShift:
    """Residual displacement measured on one probe window.

    ``observed(x) ~ reblurred(x + (dx, dy))`` around the probe centre ``(cx, cy)``
    (observation pixels); ``cc`` is ECC's correlation coefficient.  A probe that could
    not be measured has NaN ``dx``, ``dy`` and ``cc`` and says why in ``reason``.
    """

    cx: float
    cy: float
    dx: float
    dy: float
    cc: float
    reason: str = ""

    @property
    def measured(self) -> bool:
        return not self.reason

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (NaN as None)."""
        def num(v: float) -> float | None:
            return round(float(v), 4) if np.isfinite(v) else None

        d: dict[str, Any] = {"cx": num(self.cx), "cy": num(self.cy), "dx": num(self.dx),
                             "dy": num(self.dy), "cc": num(self.cc)}
        if self.reason:
            d["reason"] = self.reason
        return d


@dataclass
class Refinement:
    """Result of :func:`refine_alignment`.

    Attributes
    ----------
    base : (3, 3) ndarray
        Refined base homography (reference -> observation), or the input when unchanged.
    applied : bool
        Whether a correction was applied.
    model : str
        ``"homography"``, ``"affine"`` or ``"none"``.
    before, after : list of ProbeShift
        Probe displacements with the input and the refined base.
    info : dict
        Summary numbers (RMS / max displacement over reliable probes before and after).
    poses : SparsePoses or None
        The weights with :attr:`base`, as the probes measured them.
    whole : WholeReblur or None
        The image reblurred whole with :attr:`poses`, when the probes covered it
        (:func:`_whole_reblur`): the displacement field's tie points are
        cut from it (:func:`reblur.align.field.estimate_field`'s ``whole``).
    """

    base: np.ndarray
    applied: bool
    model: str
    before: list[ProbeShift] = field(default_factory=list)
    after: list[ProbeShift] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)
    poses: SparsePoses | None = None
    whole: WholeReblur | None = None


@dataclass(frozen=True)
class RefineParams:
    """Options of :func:`refine_alignment`, validated once.

    Attributes
    ----------
    probe_size : int, optional
        Probe side; default a third of the short side, within [128, 256] px (large enough
        for a sub-pixel ECC estimate, small enough for several probes per side).
    n_probes : int
        Probes per side (at most).
    min_cc : float
        Smallest ECC correlation of a probe used in the fit (changes, occlusions and
        photometric differences lower it).
    ransac_px : float
        RANSAC inlier distance of the fit.
    min_gain_px : float
        The correction is applied only when it lowers the RMS probe displacement by at
        least this much.
    max_correction : float
        Largest corner displacement of an accepted correction, in probe sizes: the probes
        measure shifts of a fraction of their size, so a correction moving the image's
        corners farther extrapolates noise.
    """

    probe_size: int | None = None
    n_probes: int = 5
    min_cc: float = 0.9
    ransac_px: float = 0.3
    min_gain_px: float = 0.02
    max_correction: float = 2.0

    def __post_init__(self) -> None:
        if self.probe_size is not None and not (
                isinstance(self.probe_size, int) and self.probe_size >= 16):
            raise ValueError(f"RefineParams.probe_size must be None or an integer >= 16, got "
                             f"{self.probe_size!r}")
        if not (isinstance(self.n_probes, int) and self.n_probes >= 1):
            raise ValueError(f"RefineParams.n_probes must be an integer >= 1, got "
                             f"{self.n_probes!r}")
        if not 0.0 <= self.min_cc <= 1.0:
            raise ValueError(f"RefineParams.min_cc must lie in [0, 1], got {self.min_cc!r}")
        for name in ("ransac_px", "max_correction"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"RefineParams.{name} must be a finite number > 0, got {v!r}")
        if not (math.isfinite(self.min_gain_px) and self.min_gain_px >= 0):
            raise ValueError(f"RefineParams.min_gain_px must be a finite number >= 0, got "
                             f"{self.min_gain_px!r}")


def probe_boxes(shape: tuple[int, int], *, size: int = 256, n: int = 5,
                within: Box | None = None) -> list[Box]:
    """Up to ``n x n`` probe windows of ``size`` px on a regular lattice over the image.

    The lattice spans the whole image (first and last windows touch the borders); on an
    image smaller than ``n`` windows per side there are as many as fit without overlap
    (at least one, shrunk to the image).  With ``within`` (a box of the image at least
    ``size`` on each side) the windows span that box instead: as many per side as on the
    image, fewer where they would overlap by more than a quarter of their side.
    """
    H, W = int(shape[0]), int(shape[1])
    s = int(min(size, H, W))
    ny = max(1, min(int(n), H // s))
    nx = max(1, min(int(n), W // s))
    y0, x0, h, w = 0, 0, H, W
    if within is not None and min(within.h, within.w) >= s:
        y0, x0, h, w = within.y0, within.x0, within.h, within.w
        # windows spaced at least 3/4 of their side apart
        ny = min(ny, 1 + int((h - s) // (0.75 * s)))
        nx = min(nx, 1 + int((w - s) // (0.75 * s)))
    ys = np.linspace(y0, y0 + h - s, ny).round().astype(int) if ny > 1 else [y0 + (h - s) // 2]
    xs = np.linspace(x0, x0 + w - s, nx).round().astype(int) if nx > 1 else [x0 + (w - s) // 2]
    return [Box(int(y), int(x), s, s) for y in ys for x in xs]


#: Most cells per side of the coverage mask :func:`covered_box` searches.
_COVER_CELLS = 128


def covered_box(poses: SparsePoses, ref_shape: tuple[int, ...],
                shape: tuple[int, int]) -> Box | None:
    """The largest axis-aligned box of the observation ``shape`` where every pose of
    ``poses`` reads reference pixels (:func:`reblur.tiled.valid_polygon`), on cells of
    at most :data:`_COVER_CELLS` per side whose four corners lie inside the polygon; None
    when no cell does.

    The probes' lattice is laid over it: a probe reaching beyond it is refused for its
    coverage, and with the lattice over the whole image those were the border probes
    wherever the viewpoint or the blur's reach leaves a margin (GoPro 0477 / 16: 11 of 15
    refused, an affine fitted through 3 probes).
    """
    import shapely  # as align.georef: on first use

    poly = valid_polygon(poses, ref_shape)
    if poly is None:
        return None
    H, W = int(shape[0]), int(shape[1])
    u = max(1, -(-max(H, W) // _COVER_CELLS))
    ny, nx = -(-H // u), -(-W // u)
    # corner points of the cells (the last ones clipped to the image's last pixel)
    gy = np.minimum(np.arange(ny + 1) * u, H) - np.r_[np.zeros(ny), 1.0]
    gx = np.minimum(np.arange(nx + 1) * u, W) - np.r_[np.zeros(nx), 1.0]
    # a corner on the polygon's edge counts as inside
    inside = shapely.intersects_xy(shapely.Polygon(poly), *np.meshgrid(gx, gy))
    cells = inside[:-1, :-1] & inside[1:, :-1] & inside[:-1, 1:] & inside[1:, 1:]
    i0, j0, hc, wc = _largest_rectangle(cells)
    if hc == 0:
        return None
    y0, x0 = i0 * u, j0 * u
    return Box(y0, x0, min((i0 + hc) * u, H) - y0, min((j0 + wc) * u, W) - x0)


def _largest_rectangle(mask: np.ndarray) -> tuple[int, int, int, int]:
    """``(row, col, height, width)`` of the largest all-true rectangle of ``mask`` (the
    histogram method: each row's run heights, a stack of increasing heights); zeros when
    ``mask`` holds no true cell."""
    ny, nx = mask.shape
    heights = np.zeros(nx, int)
    best, best_area = (0, 0, 0, 0), 0
    for i in range(ny):
        heights = np.where(mask[i], heights + 1, 0)
        stack: list[tuple[int, int]] = []  # (first column, height), heights increasing
        for j in range(nx + 1):
            h = int(heights[j]) if j < nx else 0
            start = j
            while stack and stack[-1][1] >= h:
                s, sh = stack.pop()
                if sh * (j - s) > best_area:
                    best_area, best = sh * (j - s), (i - sh + 1, s, sh, j - s)
                start = s
            stack.append((start, h))
    return best


def _gray(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a.mean(axis=2) if a.ndim == 3 else a, dtype=np.float32)


def measure_shifts(
    reference,
    observed,
    poses: SparsePoses,
    boxes: list[Box],
    *,
    ref_scale: float = 1.0,
    obs_scale: float = 1.0,
    min_valid: float = 0.95,
    min_texture: float = 1e-4,
    workers: int | None = None,
    search: bool = False,
    whole: WholeReblur | None = None,
) -> list[ProbeShift]:
    """Sub-pixel displacement between the reblurred reference and the observation per window.

    Parameters
    ----------
    reference, observed : array-like
        Images (numpy, zarr, ...); only the windows are read.
    poses : SparsePoses
        Estimated weights with the base homography to check.
    boxes : list of Box
        Probe windows in observation pixels.
    ref_scale, obs_scale : float
        Intensity scales dividing the reference and the observation.
    min_valid : float
        Fraction of the window the reference must cover (else the probe is skipped).
    min_texture : float
        Smallest standard deviation of the Laplacian-of-Gaussian of the window
        (intensities in [0, 1]): flat windows cannot be registered and are skipped.  It
        is low enough for smooth (upsampled, clean 16-bit) imagery: ECC's convergence
        and the correlation gate of the fit judge the rest.
    workers : int, optional
        Threads measuring probes side by side (OpenCV single-threaded in each); default
        the CPUs available to the process.  Each probe is measured alone, so the result
        does not depend on it.  The 576 probes of a 100 MP field lattice took 5.0 s CPU
        on one thread (reblur 2.8 s, ECC 1.3 s).
    search : bool
        Locate the window's centre within an eighth of the window first and register it on
        that fixed support (:func:`tie_shift`: the displacement field's many small tie
        points, whose outliers the median test removes).  Default: ECC of the whole window
        against the whole window from zero shift, which reaches the nearest optimum only
        (the refinement's few large probes: with a search, GoPro GOPR0477's probes on
        walking people correlated at 0.95 with their motion, and the refined geometry cost
        0.4-0.5 dB of reblur PSNR).  The whole-window measurement can drift
        (:func:`tie_shift`): on GOPR0374's 240 px probes none moved under the change that
        moved a third of its 64 px tie points, but one over GOPR0477's people (16-frame
        average) ends 0.6 or 4.2 px off with the last digits of its input.
    whole : WholeReblur, optional
        The whole image already reblurred with these poses (:func:`reblur.tiled.reblur_whole`
        of :func:`measured_reference`): the rows of probes are cut from it.

    Returns
    -------
    list of ProbeShift
        One per probe, in the order of ``boxes``; those that could not be measured
        carry the reason (:attr:`ProbeShift.reason`).

    Notes
    -----
    Probes of one row (same top and height) that cover at least :data:`_STRIP_COVER` of
    the span from the first to the last are reblurred together, as one strip, and
    measured on its slices: a probe's reblur costs about as much per rotation group of
    the poses as per pixel, and a dense lattice (a 1 MP image's field) covers whole rows.
    The reblurred values are those of a probe's own window, up to the rounding of OpenCV's
    warp coordinates (:func:`reblur.tiled.reblur_windows`).

    Both images are measured on their band mean (:func:`_gray`), so a reference of
    several bands is reblurred as its band mean (:class:`reblur._bands.BandMean`): one
    float32 band instead of every band in 16-bit fixed point, the same values up to
    rounding (the blur is linear).  On GoPro 0477 frame 13 against 16 frames (0.9 MP,
    colour) the refinement and the field took 0.42 + 0.45 s, now 0.30 + 0.33 s.
    """
    n = available_cpus() if workers is None else int(workers)
    if n < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    reference = measured_reference(reference)

    def measure(b: Box, reblurred=None) -> ProbeShift:
        return _measure_one(reference, observed, poses, b, ref_scale, obs_scale, min_valid,
                            min_texture, search, reblurred)

    def run(idx: list[int]) -> list[ProbeShift]:
        if len(idx) > 1:
            try:
                got = reblur_windows(poses, reference, [boxes[i] for i in idx], whole=whole)
            except (ValueError, np.linalg.LinAlgError, cv2.error):
                got = None  # each probe says why on its own
            if got is not None:
                return [measure(boxes[i], r) for i, r in zip(idx, got, strict=True)]
        return [measure(boxes[i]) for i in idx]

    jobs = _strip_jobs(boxes)
    shifts: list[ProbeShift | None] = [None] * len(boxes)
    for idx, part in zip(jobs, thread_map(run, jobs, n), strict=True):
        for i, s in zip(idx, part, strict=True):
            shifts[i] = s
    return shifts  # type: ignore[return-value]


def measured_reference(reference):
    """What :func:`measure_shifts` reblurs of ``reference``: its band mean
    (:class:`~reblur._bands.BandMean`) when it has several bands (the measurement compares
    band means), else the reference itself."""
    if len(reference.shape) == 3 and reference.shape[2] > 1:
        return BandMean(reference)
    return reference


#: Share of a row's span (first probe's left edge to last probe's right edge) that its
#: probes must cover for :func:`measure_shifts` to reblur the span once.  Field lattices
#: cover 100 % of each row at 1 MP, 61 % at 25 MP and 31 % at 100 MP (every other probe of
#: a row: half that).
_STRIP_COVER = 0.5


def _strip_jobs(boxes: list[Box]) -> list[list[int]]:
    """The work of :func:`measure_shifts`, as lists of indices into ``boxes``: the probes
    of a row (same top and height) covering at least :data:`_STRIP_COVER` of their span,
    reblurred together; every other probe alone."""
    rows: dict[tuple[int, int], list[int]] = {}
    for i, b in enumerate(boxes):
        rows.setdefault((b.y0, b.h), []).append(i)
    jobs: list[list[int]] = []
    for idx in rows.values():
        x0 = min(boxes[i].x0 for i in idx)
        x1 = max(boxes[i].x0 + boxes[i].w for i in idx)
        if len(idx) > 1 and sum(boxes[i].w for i in idx) >= _STRIP_COVER * (x1 - x0):
            jobs.append(idx)
        else:
            jobs.extend([i] for i in idx)
    return jobs


def _measure_one(reference, observed, poses: SparsePoses, b: Box, ref_scale: float,
                 obs_scale: float, min_valid: float, min_texture: float, search: bool,
                 reblurred: tuple[np.ndarray, np.ndarray] | None = None) -> ProbeShift:
    """One probe of :func:`measure_shifts` (``reblurred``: its reblurred reference and
    validity, when already computed)."""
    cx, cy = b.x0 + (b.w - 1) / 2.0, b.y0 + (b.h - 1) / 2.0

    def failed(reason: str) -> ProbeShift:
        return ProbeShift(cx=cx, cy=cy, dx=np.nan, dy=np.nan, cc=np.nan, reason=reason)

    if reblurred is not None:
        reb, valid = reblurred
    else:
        try:
            reb, valid = reblur_tile(poses, reference, b)
        except (ValueError, np.linalg.LinAlgError, cv2.error) as e:
            # a pose maps part of the window beyond the horizon, or is singular
            return failed(f"cannot be reblurred: {' '.join(str(e).split())}")
    cover = float(valid.mean())
    if cover < min_valid:
        return failed(f"the reference covers {100 * cover:.0f} % of it "
                      f"(< {100 * min_valid:.0f} %)")
    obs = _gray(read_window(observed, b, np.float32)) / np.float32(obs_scale)
    rb = _gray(reb) / np.float32(ref_scale)
    if not (np.isfinite(obs).all() and np.isfinite(rb).all()):
        return failed("non-finite values")
    log = cv2.Laplacian(cv2.GaussianBlur(obs, (0, 0), 1.5), cv2.CV_32F)
    texture = float(np.sqrt(log.var()))
    if texture < min_texture:
        return failed(f"flat: texture {texture:.2g} < {min_texture:.2g}")
    got = (tie_shift(obs, rb, valid, min_valid=min_valid) if search
           else _whole_window_shift(obs, rb, valid))
    if isinstance(got, str):
        return failed(got)
    dx, dy, cc = got
    return ProbeShift(cx=cx, cy=cy, dx=dx, dy=dy, cc=cc)


#: Pre-smoothing of both measurements (the 5 x 5 Gaussian ECC applies by default).
_PRESMOOTH = 5
#: ECC's stopping rule in both: 100 iterations, or a change of the correlation below 1e-5.
_ECC_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-5)


def _whole_window_shift(observed: np.ndarray, reblurred: np.ndarray, valid: np.ndarray
                        ) -> tuple[float, float, float] | str:
    """:func:`tie_shift`'s result by ECC of the whole window from zero shift (see
    :func:`measure_shifts`' ``search``)."""
    warp = np.eye(2, 3, dtype=np.float32)
    try:
        cc, warp = cv2.findTransformECC(observed, reblurred, warp, cv2.MOTION_TRANSLATION,
                                        _ECC_CRITERIA, valid.astype(np.uint8), _PRESMOOTH)
    except cv2.error:
        return "ECC did not converge"
    dx, dy = float(warp[0, 2]), float(warp[1, 2])
    if not (np.isfinite(dx) and np.isfinite(dy)) or max(abs(dx), abs(dy)) > observed.shape[1] / 4:
        return f"implausible shift ({dx:.3g}, {dy:.3g}) px"
    return dx, dy, float(cc)


def tie_shift(observed: np.ndarray, reblurred: np.ndarray, valid: np.ndarray, *,
              min_valid: float = 0.5) -> tuple[float, float, float] | str:
    """Sub-pixel translation ``(dx, dy)`` with ``observed(x) ~ reblurred(x + (dx, dy))``.

    The central part of ``reblurred`` (a margin of an eighth of the window on each side
    is the search range) is located in ``observed``: first the best whole-pixel shift by
    normalised cross-correlation (:func:`cv2.matchTemplate`, gain and offset invariant),
    then ECC (:func:`cv2.findTransformECCWithMask`, translation) from there.  The support
    is the same at every shift tried.  ECC on the whole window against the whole window
    (:func:`measure_shifts` without ``search``) loses the part of the window shifted out
    of it, so a smaller overlap can correlate better: on real camera shake (GoPro
    GOPR0374, 64 px tie points of the displacement field, horizontal blur of ~15 px) it
    wandered along the blur to the far end of a flat correlation ridge, by up to 20 px,
    and a change of the input in its sixth digit moved a third of the tie points by
    0.2-7 px; whether the field was applied then depended on the number of threads (5.6 %
    against 4.5 % flagged).

    Parameters
    ----------
    observed, reblurred : (h, w) ndarray
        The observation's window and the reblurred reference's, intensities on one scale
        (computed in single precision).
    valid : (h, w) ndarray of bool
        Where ``reblurred`` is defined.
    min_valid : float
        Fewest defined pixels in the searched central part (a fraction).

    Returns
    -------
    (dx, dy, cc) or str
        The shift and ECC's correlation coefficient, or why there is none: too little of
        the central part defined, the best whole-pixel shift at the edge of the search
        range (the displacement may lie beyond it), ECC failing, or ECC leaving the
        whole-pixel neighbourhood of that shift -- the correlation is flat over more than
        a pixel along some direction (blur along it, or a straight edge), so the shift is
        not determined there.
    """
    observed = np.ascontiguousarray(observed, dtype=np.float32)
    reblurred = np.ascontiguousarray(reblurred, dtype=np.float32)
    h, w = observed.shape
    if reblurred.shape != (h, w) or np.shape(valid) != (h, w):
        raise ValueError(f"tie_shift needs windows of one shape, got {observed.shape}, "
                         f"{reblurred.shape} and {np.shape(valid)}")
    mx, my = max(2, w // 8), max(2, h // 8)
    k = (_PRESMOOTH, _PRESMOOTH)
    obs = cv2.GaussianBlur(observed, k, 0)
    reb = cv2.GaussianBlur(reblurred, k, 0)
    # leave out the pixels the pre-smoothing mixed with undefined ones
    vm = cv2.erode(valid.astype(np.uint8), np.ones(k, np.uint8),
                   borderType=cv2.BORDER_REPLICATE)
    tmpl = np.ascontiguousarray(reb[my:h - my, mx:w - mx])
    tmask = np.ascontiguousarray(vm[my:h - my, mx:w - mx])
    if tmask.mean() < min_valid:
        return (f"the reference covers {100 * tmask.mean():.0f} % of its centre "
                f"(< {100 * min_valid:.0f} %)")
    score = cv2.matchTemplate(obs, tmpl, cv2.TM_CCOEFF_NORMED, mask=tmask)
    score[~np.isfinite(score)] = -np.inf
    iy, ix = np.unravel_index(int(np.argmax(score)), score.shape)
    if not (0 < ix < 2 * mx and 0 < iy < 2 * my):
        return (f"the best whole-pixel shift ({mx - ix}, {my - iy}) px lies on the edge of "
                f"the +-{mx} px search")
    warp = np.array([[1, 0, ix], [0, 1, iy]], np.float32)
    try:
        cc, warp = cv2.findTransformECCWithMask(tmpl, obs, tmask, np.ones_like(obs, np.uint8),
                                                warp, cv2.MOTION_TRANSLATION, _ECC_CRITERIA,
                                                1)
    except cv2.error:
        return "ECC did not converge"
    tx, ty = float(warp[0, 2]), float(warp[1, 2])
    if not (np.isfinite(tx) and np.isfinite(ty)):
        return "ECC did not converge"
    if max(abs(tx - ix), abs(ty - iy)) > 1.0:
        return (f"flat correlation: ECC moved ({tx - ix:.2g}, {ty - iy:.2g}) px from the best "
                f"whole-pixel shift")
    # obs(u + t) ~ reb(u + m)  =>  obs(x) ~ reb(x + m - t)
    return mx - tx, my - ty, float(cc)


def _stats(shifts: list[ProbeShift], min_cc: float) -> dict[str, float]:
    good = [s for s in shifts if s.measured and s.cc >= min_cc]
    if not good:
        return {"n": 0, "rms_px": None, "max_px": None}  # JSON-ready: no NaN
    d = np.hypot([s.dx for s in good], [s.dy for s in good])
    return {"n": len(good), "rms_px": float(np.sqrt(np.mean(d * d))), "max_px": float(d.max())}


def _records(shifts: list[ProbeShift], min_cc: float) -> list[dict[str, Any]]:
    """Per-probe records for the report: shift, correlation, and why a probe is not used."""
    out = []
    for s in shifts:
        d = s.to_dict()
        if s.measured and s.cc < min_cc:
            d["reason"] = f"correlation {s.cc:.3f} < {min_cc} (changes or occlusion)"
        out.append(d)
    return out


def _fit(shifts: list[ProbeShift], ransac_px: float) -> tuple[np.ndarray | None, str, int]:
    src = np.array([[s.cx, s.cy] for s in shifts], np.float64)
    dst = src + np.array([[s.dx, s.dy] for s in shifts], np.float64)
    n = len(shifts)
    if n >= 12:  # 8 parameters: enough redundancy not to extrapolate noise to the corners
        G, inl = cv2.findHomography(src, dst, cv2.RANSAC, ransac_px)
        if G is not None and inl is not None and int(inl.sum()) >= 12:
            keep = inl.ravel().astype(bool)
            G, _ = cv2.findHomography(src[keep], dst[keep], 0)  # least squares on inliers
            if G is not None:
                return G / G[2, 2], "homography", int(keep.sum())
    if n >= 3:
        A, inl = cv2.estimateAffine2D(src, dst, method=cv2.RANSAC,
                                      ransacReprojThreshold=ransac_px, refineIters=20)
        if A is not None and inl is not None and int(inl.sum()) >= 3:
            return np.vstack([A, [0.0, 0.0, 1.0]]), "affine", int(inl.sum())
    return None, "none", 0


#: Share of the image that what :func:`measure_shifts` would reblur of some windows must
#: span for the image to be reblurred once for them (:func:`_whole_reblur`): the
#: displacement field's second pass and its check reblur their rows' spans, so that is
#: at least 1.5 times the rows' share of the image in reblurs, against one.  At 1 MP the
#: field's rows and the refinement's probes span it all; at 4 MP (the same 64 px tie
#: points on a 16 x 16 lattice) half.
_WHOLE_SPAN = 0.75

#: Most pixels of an image that :func:`_whole_reblur` reblurs whole (64 MB in float32):
#: beyond, the rows reblur on their own whatever they span.
_WHOLE_PIXELS = 1 << 24

#: Margin around the image of that reblur: the displacement field's check grows each
#: window by the field's reach and the bicubic footprint (a window reaching beyond is
#: reblurred on its own).
_WHOLE_MARGIN = 8


def _whole_reblur(reference, poses, shape: tuple[int, int], boxes: list[Box]):
    """:func:`reblur.tiled.reblur_whole` of ``reference`` (as :func:`measure_shifts`
    measures it) for the windows ``boxes`` (the refinement's probes, the displacement
    field's tie points left after its first pass), or None when what
    :func:`measure_shifts` reblurs of them (its strips and single windows) is less than
    :data:`_WHOLE_SPAN` of the image, the image holds more than :data:`_WHOLE_PIXELS`,
    the poses reblur tiles their own way, or the image cannot be reblurred whole."""
    from .. import tiled
    H, W = shape
    if hasattr(poses, "reblur_tile") or not boxes or H * W > _WHOLE_PIXELS:
        return None
    # what a pass reblurs: the span of each row reblurred as one strip, the other windows
    # alone (the sparse rows of a wide image's lattice, whose span is no measure of it)
    span = 0
    for idx in _strip_jobs(boxes):
        bs = [boxes[i] for i in idx]
        span += bs[0].h * (max(b.x1 for b in bs) - min(b.x0 for b in bs))
    if span < _WHOLE_SPAN * H * W:
        return None
    try:
        return tiled.reblur_whole(poses, measured_reference(reference), shape,
                                  margin=_WHOLE_MARGIN, workers=available_cpus())
    except (ValueError, np.linalg.LinAlgError, cv2.error):
        # a pose maps part of the image beyond the horizon, or is singular: the rows are
        # reblurred on their own, and each window that cannot be says why
        return None


def refine_alignment(
    reference,
    observed,
    weights: np.ndarray,
    grid: PoseGrid,
    base: np.ndarray,
    *,
    ref_scale: float = 1.0,
    obs_scale: float = 1.0,
    probes: list[Box] | None = None,
    params: RefineParams | None = None,
) -> Refinement:
    """Check the geometry of the estimate over the whole image and correct the base homography.

    Parameters
    ----------
    reference, observed : array-like
        Reference and observation (numpy, zarr, ...), read window by window.
    weights : ndarray, ``grid.shape``
        Estimated pose weights.
    grid : PoseGrid
        Their grid (observation geometry).
    base : (3, 3) ndarray
        Base homography (reference -> observation) the weights were estimated with.
    ref_scale, obs_scale : float
        Intensity scales of the reference and the observation.
    probes : list of Box, optional
        Probe windows (default :func:`probe_boxes` with ``params.probe_size`` and
        ``params.n_probes``).
    params : RefineParams, optional
        The options (default ``RefineParams()``).

    Returns
    -------
    Refinement
        Never raises on what it measures: probes that cannot be measured carry their
        reason, and a correction that is rejected leaves the base unchanged with
        ``info["rejected"]`` saying why.
    """
    p = RefineParams() if params is None else params
    base = np.asarray(base, np.float64)
    size = p.probe_size
    if size is None:
        size = int(np.clip(min(grid.image_shape[:2]) // 3, 128, 256))
    kw = dict(ref_scale=ref_scale, obs_scale=obs_scale)
    shape = tuple(int(s) for s in grid.image_shape[:2])
    poses0 = SparsePoses(weights, grid, base)
    within = None
    if probes is None:  # the lattice where the reference covers the observation
        within = covered_box(poses0, reference.shape, shape)
        if within is not None and min(within.h, within.w) < min(size, *shape):
            within = None  # narrower than a probe: probe_boxes lays it over the image
    boxes = probes if probes is not None else probe_boxes(shape, size=size, n=p.n_probes,
                                                          within=within)
    before = measure_shifts(reference, observed, poses0, boxes, **kw)
    s0 = _stats(before, p.min_cc)
    good = [s for s in before if s.measured and s.cc >= p.min_cc]
    G, model, n_in = _fit(good, p.ransac_px)
    info: dict[str, Any] = {"probes": len(boxes), "before": s0, "model": model,
                            "inliers": n_in, "probe_shifts": _records(before, p.min_cc)}
    if probes is None:
        info["lattice"] = ("the image" if within is None else
                           [int(within.y0), int(within.x0), int(within.h), int(within.w)])
    if G is None:
        return Refinement(base, False, "none", before, before, info, poses0)
    new, why = _corrected(G, base, shape, tuple(int(s) for s in reference.shape[:2]),
                          p.max_correction * max(max(b.h, b.w) for b in boxes))
    if new is None:
        info["rejected"], info["applied"] = why, False
        return Refinement(base, False, model, before, before, info, poses0)
    # where the probes cover the image (1 MP), it is reblurred whole for them with the
    # corrected base, and that reblur serves the displacement field's tie points next
    # (Refinement.whole) when the correction is applied
    poses1 = SparsePoses(weights, grid, new)
    whole1 = _whole_reblur(reference, poses1, shape, boxes)
    after = measure_shifts(reference, observed, poses1, boxes, whole=whole1, **kw)
    s1 = _stats(after, p.min_cc)
    info["after"] = s1
    info["probe_shifts_after"] = _records(after, p.min_cc)
    corners = np.array([[0.0, 0.0], [shape[1] - 1.0, 0.0], [shape[1] - 1.0, shape[0] - 1.0],
                        [0.0, shape[0] - 1.0]])
    info["correction_at_corners_px"] = float(np.abs(map_points(G, corners) - corners).max())
    ok = s0["n"] > 0 and s1["n"] > 0 and s1["rms_px"] <= s0["rms_px"] - p.min_gain_px
    info["applied"] = bool(ok)
    if not ok:
        return Refinement(base, False, model, before, after, info, poses0)
    return Refinement(new, True, model, before, after, info, poses1, whole1)


def _corrected(G: np.ndarray, base: np.ndarray, obs_shape: tuple[int, int],
               ref_shape: tuple[int, int], max_px: float) -> tuple[np.ndarray | None, str]:
    """The corrected base ``G^-1 @ base``, or None and why the correction ``G`` (observation
    frame) is rejected: singular or not finite, folding the observation or the corrected
    reference, or moving the observation's corners by more than ``max_px``."""
    if not np.all(np.isfinite(G)) or abs(np.linalg.det(G)) < 1e-12 or G[2, 2] == 0:
        return None, "degenerate correction: singular or non-finite"
    G = G / G[2, 2]
    # a correction is near the identity: the loosest plausible viewpoint change is far more
    # than any correction the probes can support; what it catches is folding and horizons
    limits = dict(max_zoom=2.0, max_anisotropy=2.0, min_overlap=0.2)
    try:
        check_plausible(G, obs_shape, obs_shape, **limits)
    except AlignmentError as err:
        return None, f"degenerate correction: {str(err).split(': ', 1)[-1]}"
    moved = max_corner_shift(G, np.eye(3), obs_shape)
    if not moved <= max_px:
        return None, (f"implausible correction: it moves the image corners by {moved:.0f} px "
                      f"(> {max_px:.0f} px, max_correction probe sizes)")
    new = np.linalg.inv(G) @ base
    if not np.all(np.isfinite(new)) or abs(new[2, 2]) < 1e-12:
        return None, "degenerate corrected base: non-finite or at infinity"
    new = new / new[2, 2]
    try:
        check_plausible(new, ref_shape, obs_shape, **limits)
    except AlignmentError as err:
        return None, f"degenerate corrected base: {str(err).split(': ', 1)[-1]}"
    return new, ""
