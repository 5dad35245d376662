"""The coarse alignment: :func:`coarse_align` and :func:`coarse_align_shakes` run the stages.

The stages live in their own modules (:mod:`.features`, :mod:`.ecc`, :mod:`.blocks`,
:mod:`.polish`, :mod:`.verify`); this module prepares the pyramid of a pair once
(:class:`Prepared`, which also memoises the stages that do not depend on the shake
extent) and decides between their results, for one shake extent at a time
(:func:`_align`):

1. ``auto``: the SIFT estimate (refined by ECC), if it holds, seeds the gradient blocks
   (:func:`_features_seed`); ``auto`` and ``gradient``: the gradient blocks, from that
   seed or from rotation hypotheses -- or from the caller's hint instead of both --
   decide and verify (:func:`_gradient_blocks`), and the kernel polish is kept where its
   blur model fits (:func:`_polish_and_keep`).
2. ``features`` (or ``auto`` when the blocks failed): the SIFT estimate, polished and
   verified by its regions (:func:`_features_fallback`); with a hint it must lie near it.
3. ``ecc`` (or ``auto`` when both failed): phase correlation (or the hint), ECC coarse to
   fine, the polish and a correlation check (:func:`_phase_fallback`).
4. The checks and diagnostics of the result (:func:`_result`).
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable, Hashable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .._memory import available_cpus
from ..grid import map_points
from .blocks import Blocks, gradient_align, rotation_hypotheses
from .ecc import ecc_refine, phase_init
from .features import Features, match_features
from .overviews import Level, block_factor, image_shape, overview_k, overview_source, pyramid
from .params import AlignParams
from .polish import (
    REGION_PX,
    Polished,
    PolishError,
    blur_exceeds,
    content_misfit,
    polish_and_verify,
)
from .result import Alignment, AlignmentError
from .verify import (
    check_near_hint,
    check_plausible,
    check_textured,
    correlation,
    max_corner_shift,
    refusal,
)

log = logging.getLogger(__name__)

#: Largest corner shift (px, on the working level) between two estimates of one shake
#: extent for the polish of the later one to be the earlier's: the regions' kernels are
#: fitted on the level's pixel grid, and their agreement is judged to a fraction of a pixel,
#: not to a twentieth of one (:meth:`_Shake.polish`).
SAME_ESTIMATE_PX = 0.05

#: Threads fitting the kernel-polish regions (:func:`~reblur.align.polish.kernel_polish`:
#: independent regions, the one-thread result bit for bit).
POLISH_WORKERS = min(2, available_cpus())


# ---------------------------------------------------------------------- entry points
def coarse_align(
    reference,
    observed,
    params: AlignParams | None = None,
    *,
    shake_px: float = 16.0,
    hint: np.ndarray | None = None,
) -> Alignment:
    """Estimate the global reference -> observation homography at low resolution.

    Parameters
    ----------
    reference, observed : array-like, (H, W) or (H, W, C)
        Sharp reference and blurred observation (numpy, zarr, ... any dtype; sizes and band
        counts may differ).  Each is read once, strip by strip, into an overview (an
        :class:`OverviewCache` of a file with reduced-resolution levels reads one of
        those instead).
    params : AlignParams, optional
        The options (default ``AlignParams()``): method, pyramid sizes, thresholds of the
        features, blocks, polish and checks.
    shake_px : float
        Largest camera-shake displacement expected during the exposure, in full-resolution
        pixels, anywhere in the image (an in-plane roll moves the corners by radius x
        angle: 1 degree is 17 px per 1000 px of radius).  It picks the working level of the
        refinement (the finest level where it spans at most 4 pixels) and the kernel size of
        the polish; a blur much larger than this fails verification.
    hint : (3, 3) array-like, optional
        A rough reference -> observation homography in full-resolution pixels (a few
        degrees and tens of pixels off is fine), e.g. from georeferencing or picked by
        hand.  It replaces the SIFT seed and the rotation hypotheses of the gradient blocks
        and the phase-correlation start of the fallback, so it reaches pairs neither
        finds (large rotations, captures years apart); every estimate must then stay
        within ``params.hint_reach`` of it.  The result's ``method`` starts with ``hint``.

    Returns
    -------
    Alignment
        ``H`` (reference -> observation, full-resolution pixels) plus diagnostics.

    Raises
    ------
    AlignmentError
        Textureless images; too few or inconsistent feature matches together with a failed
        fallback (ECC divergence, too low a correlation); a result the kernel polish cannot
        verify; or an implausible homography (folded, extreme zoom or stretch, too little
        overlap).  The message gives the reason on one line.
    ValueError
        Bad arguments (shapes, dtypes, ``shake_px``, a hint that is not an invertible 3x3
        homography or is implausible for these images).

    See Also
    --------
    coarse_align_shakes : the same for several shake extents, sharing the overviews and
        the stages that do not depend on the extent.

    Notes
    -----
    A correlation optimum between a sharp and a motion-blurred image lies near a *mode* of
    the blur, not at its mean: with 8 px of shake the corners of ECC and feature estimates
    are typically 4-16 px off the mean camera pose.  The polish fits, in a grid of regions,
    a non-negative blur kernel between the warped reference and the observation; the
    kernel's centroid is the mean displacement there, and a homography through the moved
    region centres brings the corners to within about a pixel of the mean pose, which is
    the pose the fine pose grid is centred on.  The same fit verifies the result: enough
    regions, spread over the image, must agree.  It assumes the observation is the blurred
    one (``observation = reference * kernel``); with ``polish=False`` only the feature
    checks guard against a wrong answer.

    Examples
    --------
    >>> import numpy as np
    >>> from reblur.grid import map_points, pose_homography
    >>> from reblur.warp import warp_window
    >>> rng = np.random.default_rng(0)
    >>> import cv2
    >>> ref = cv2.GaussianBlur(rng.random((400, 400)).astype(np.float32), (0, 0), 2)
    >>> H = pose_homography(12, -7, rz=2.0, center=(199.5, 199.5))
    >>> obs, _ = warp_window(ref, H, (0, 0, 400, 400))
    >>> a = coarse_align(ref, obs[..., 0], AlignParams(min_side=64))
    >>> corners = np.array([[0, 0], [399, 0], [399, 399], [0, 399]])
    >>> err = np.abs(map_points(a.H, corners) - map_points(H, corners)).max()
    >>> bool(err < 1.0), a.method.split("+")[0]
    (True, 'features')
    """
    params = _checked(params, (shake_px,))
    prep = _prepare(reference, observed, params, hint)
    return _align(prep, params, shake_px)


def coarse_align_shakes(
    reference,
    observed,
    shakes: Sequence[float] = (8.0, 16.0, 32.0, 64.0),
    params: AlignParams | None = None,
    *,
    hint: np.ndarray | None = None,
) -> Iterator[tuple[float, Alignment | AlignmentError]]:
    """:func:`coarse_align` for several camera-shake extents, sharing what does not depend
    on the extent.

    The overviews and the pyramid are built once, and the SIFT matches, their ECC
    refinement, the gradient blocks and the phase-correlation start are computed once for
    each set of inputs they read (the shake extent only picks the working level, which
    these stages may share); the kernel polish and the checks run for each extent, but
    for an estimate whose polish a smaller extent refused on the same level for a content
    misfit (see ``_Shake.polish``), which is refused again without running.  Otherwise
    each result is exactly the one a separate ``coarse_align(reference, observed, params,
    shake_px=s, hint=hint)`` gives.

    Parameters
    ----------
    reference, observed : array-like, (H, W) or (H, W, C)
        As for :func:`coarse_align`; each is read once.
    shakes : sequence of float
        Shake extents (``shake_px`` of :func:`coarse_align`), tried in this order.
    params : AlignParams, optional
        The options, as for :func:`coarse_align`.
    hint : (3, 3) array-like, optional
        A rough reference -> observation homography, as for :func:`coarse_align`.

    Yields
    ------
    shake_px : float
        The extent tried.
    result : Alignment or AlignmentError
        Its alignment, or the error :func:`coarse_align` would raise.  Results are computed
        lazily: stopping the iteration skips the remaining extents.

    Raises
    ------
    ValueError
        Bad arguments, as :func:`coarse_align` (raised on the first ``next``).

    Examples
    --------
    >>> import numpy as np, cv2
    >>> from reblur.grid import pose_homography
    >>> from reblur.warp import warp_window
    >>> rng = np.random.default_rng(0)
    >>> ref = cv2.GaussianBlur(rng.random((400, 400)).astype(np.float32), (0, 0), 2)
    >>> H = pose_homography(12, -7, rz=2.0, center=(199.5, 199.5))
    >>> obs, _ = warp_window(ref, H, (0, 0, 400, 400))
    >>> for s, a in coarse_align_shakes(ref, obs[..., 0], (8.0, 16.0), AlignParams(min_side=64)):
    ...     print(s, a.method.split("+")[0])
    8.0 features
    16.0 features
    """
    shakes = tuple(shakes)
    params = _checked(params, shakes)
    try:
        prep = _prepare(reference, observed, params, hint)
    except AlignmentError as err:
        for sp in shakes:
            yield sp, AlignmentError(str(err))
        return
    for sp in shakes:
        try:
            yield sp, _align(prep, params, sp)
        except AlignmentError as err:
            yield sp, err


def _checked(params: AlignParams | None, shakes: tuple[float, ...]) -> AlignParams:
    """``params`` (default ``AlignParams()``); ValueError on a bad shake extent."""
    if params is None:
        params = AlignParams()
    elif not isinstance(params, AlignParams):
        raise TypeError(f"params must be an AlignParams, got {type(params).__name__}")
    for shake_px in shakes:
        if not (isinstance(shake_px, (int, float, np.number)) and 0 <= shake_px < math.inf):
            raise ValueError(f"shake_px must be a finite number >= 0, got {shake_px!r}")
    return params


# ---------------------------------------------------------------------- the prepared pair
@dataclass
class Prepared:
    """The overviews' pyramid of one pair and the memo of the stages that do not depend
    on the shake extent (see :func:`_align`)."""

    ref_shape: tuple[int, int]
    obs_shape: tuple[int, int]
    scale0: float
    levels: list[Level]
    hint: np.ndarray | None = None
    memo: dict = field(default_factory=dict)
    #: where the overviews came from (:func:`~reblur.align.overviews.overview_source`)
    sources: dict | None = None
    #: polishes refused on a content misfit: (working level, estimate, options) -> the
    #: shake extent and the regions by outcome (see :meth:`_Shake.polish`)
    misfits: dict = field(default_factory=dict)

    def cached(self, key: Hashable, compute: Callable[[], Any]) -> Any:
        """``compute()`` once per ``key``; an AlignmentError it raises is re-raised (a new
        one with the same message) on every later call."""
        if key not in self.memo:
            try:
                self.memo[key] = (True, compute())
            except AlignmentError as err:
                self.memo[key] = (False, str(err))
        ok, got = self.memo[key]
        if not ok:
            raise AlignmentError(got)
        return got


def _prepare(reference, observed, params: AlignParams, hint) -> Prepared:
    """Overviews of both images (each read once), their pyramid, and the checked hint.

    A reference that belongs to a :class:`~reblur.refcache.ReferenceCache` run (it has a
    ``reference_run``) takes its pyramid levels and their features from the cache.

    Raises ValueError when they are too small or the hint is bad, AlignmentError when one
    is textureless."""
    ref_shape, obs_shape = image_shape(reference), image_shape(observed)
    hint = None if hint is None else _checked_hint(hint, ref_shape, obs_shape, params)
    k = block_factor(max(ref_shape + obs_shape), params.max_side)
    scale0 = 1.0 / k
    ref0, obs0 = overview_k(reference, k), overview_k(observed, k)
    if min(ref0.shape + obs0.shape) < 16:
        raise ValueError(
            f"images {ref_shape} and {obs_shape} are too small or elongated to align at "
            f"max_side={params.max_side}; raise max_side, or use --no-align (align=False) "
            "if the images are already registered"
        )
    try:
        check_textured("reference", ref0)
        check_textured("observation", obs0)
    except AlignmentError as err:
        raise AlignmentError(f"alignment (overviews): {err}: nothing to align or compare; "
                             "check the input (blank, saturated or all nodata?)") from None
    run = getattr(reference, "reference_run", None)  # a ReferenceCache's run: reuse
    token = None if run is None else run.token(ref0)
    ref_memo = None
    if token is not None:
        def ref_memo(i, make):
            return run.memo("pyramid levels", (token, params.nodata, i), make)
    levels = pyramid(ref0, obs0, scale0, params.min_side, params.nodata, ref_memo=ref_memo)
    if token is not None:
        for lv in levels:
            level_token = run.token(lv.ref)
            if level_token is not None:
                lv.ref_memo = functools.partial(_reference_product, run, level_token)
    sources = {"reference": overview_source(reference, k),
               "observation": overview_source(observed, k)}
    return Prepared(ref_shape, obs_shape, scale0, levels, hint, sources=sources)


def _reference_product(run, level_token, key, compute):
    """A product of one reference level (its SIFT features) from the run's
    :class:`~reblur.refcache.ReferenceCache`."""
    return run.memo("reference features", (level_token, key), compute)


def _checked_hint(hint, ref_shape: tuple[int, int], obs_shape: tuple[int, int],
                  params: AlignParams) -> np.ndarray:
    """``hint`` as a normalised float64 homography; ValueError saying what is wrong."""
    how = "give the reference -> observation homography in full-resolution pixels"
    try:
        H = np.array(hint, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"alignment hint is not a 3x3 array of numbers; {how}") from None
    if H.shape != (3, 3) or not np.all(np.isfinite(H)):
        raise ValueError(f"alignment hint must be 3x3 finite numbers, got shape {H.shape}; "
                         f"{how}")
    if H[2, 2] == 0 or abs(np.linalg.det(H / H[2, 2])) < 1e-12:
        raise ValueError(f"alignment hint is singular (not invertible); {how}")
    H = H / H[2, 2]
    try:
        check_plausible(H, ref_shape, obs_shape, max_zoom=params.max_zoom,
                        max_anisotropy=params.max_anisotropy, min_overlap=params.min_overlap)
    except AlignmentError as err:
        why = str(err).split(": ", 1)[-1]
        raise ValueError(f"alignment hint is implausible for these images ({why}); {how}, "
                         "or relax AlignParams' max_zoom, max_anisotropy, min_overlap") from None
    return H


# ---------------------------------------------------------------------- one shake extent
@dataclass
class _Shake:
    """One shake extent on a prepared pair: what every stage reads.

    ``work`` is the working level of ECC and the polish: the finest where the shake spans
    at most 4 pixels, but large enough for a grid of polish regions.  ``errors`` collects
    the stages that failed and why, for the refusal; ``polishes`` every kernel polish run
    (:meth:`polish`): the estimate it polished, its regions by outcome, and what became of
    it; ``too_blurred`` the regions of a polish whose kernels spread beyond the extent
    (:func:`~reblur.align.polish.blur_exceeds`), after which no other polish runs."""

    prep: Prepared
    params: AlignParams
    shake_px: float
    work: int = 0
    errors: list[tuple[str, str]] = field(default_factory=list)
    polishes: list[dict] = field(default_factory=list)
    too_blurred: dict[str, int] | None = None
    #: the estimates whose polish this extent refused, with the refusal
    refusals: list[tuple[np.ndarray, str, PolishError]] = field(default_factory=list)

    def __post_init__(self) -> None:
        levels, top = self.prep.levels, len(self.prep.levels) - 1
        work = next((i for i, lv in enumerate(levels)
                     if math.ceil(self.shake_px * lv.scale) <= 4), top)
        while work > 0 and max(levels[work].obs.shape) < 5 * REGION_PX:
            work -= 1
        self.work = work

    @property
    def levels(self) -> list[Level]:
        return self.prep.levels

    @property
    def top(self) -> int:
        return len(self.prep.levels) - 1

    @property
    def hint(self) -> np.ndarray | None:
        return self.prep.hint

    @property
    def key(self) -> Hashable:
        """What every memoised stage reads besides its level indices and seed."""
        return self.params, None if self.hint is None else self.hint.tobytes()

    def first_at_most(self, side: int) -> int:
        """The finest level whose longest side is at most ``side`` (else the coarsest)."""
        return next((i for i, lv in enumerate(self.levels) if lv.side <= side), self.top)

    def feature_levels(self) -> list[int]:
        i = self.first_at_most(self.params.feature_side)
        return list(dict.fromkeys((i, min(i + 1, self.top))))

    def plausible(self, H: np.ndarray) -> float:
        """Raise AlignmentError unless ``H`` is plausible; return the overlap."""
        p = self.params
        overlap = check_plausible(H, self.prep.ref_shape, self.prep.obs_shape,
                                  max_zoom=p.max_zoom, max_anisotropy=p.max_anisotropy,
                                  min_overlap=p.min_overlap)
        if self.hint is not None:
            check_near_hint(H, self.hint, self.prep.ref_shape, p.hint_reach)
        return overlap

    def polish(self, H: np.ndarray, of: str) -> tuple[Polished, dict]:
        """:func:`~reblur.align.polish.polish_and_verify` of ``H`` (the estimate ``of``) on
        the working level, and its record in :attr:`polishes` (``outcome`` ``verified``, for
        the caller to update, or the refusal); raises its AlignmentError.

        An estimate whose polish a smaller extent refused on the same level for a content
        misfit (:func:`~reblur.align.polish.content_misfit`) is refused again without
        running: a larger kernel cannot make the blur model explain content that differs
        (the rule :func:`reblur.pipeline.align_coarse` stops on).  The stages before the
        polish are memoised per level, so the extents that share a level polish the very
        same estimates: on a years-apart 100 MP pair, 6 polishes (0.8 s) of the 10.

        Once a polish of this extent found the blur larger than the extent
        (:func:`~reblur.align.polish.blur_exceeds`), every later polish of it is refused
        without running (:meth:`blur_refusal`): the kernels' spread does not depend on the
        estimate polished.  So is an estimate within :data:`SAME_ESTIMATE_PX` of one
        whose polish this extent refused (:meth:`same_refusal`): the fallbacks often
        converge to the estimate they replace (ECC from phase correlation to the features'
        one; on a 1 MP pair with parallax, 6 of the 12 polishes, 2.3 of its 6.7 s)."""
        rec: dict[str, Any] = {"of": of}
        self.polishes.append(rec)
        key = (self.work, H.tobytes(), self.key)
        refused = self.blur_refusal() or self.same_refusal(H)
        if refused is None and key in self.prep.misfits:
            shake, reasons = self.prep.misfits[key]
            msg = (f"could not be verified: at shake_px={shake:g} on the same level its "
                   "regions' blur kernels explained little of their texture (the content "
                   "differs); a larger extent cannot change that")
            refused = PolishError(msg, reasons)
        if refused is not None:
            rec.update(regions=dict(refused.reasons), outcome=f"refused: {refused}")
            raise refused
        try:
            p = polish_and_verify(self.levels[self.work], H, self.shake_px,
                                  self.prep.ref_shape, self.params, self.plausible,
                                  workers=POLISH_WORKERS)
        except PolishError as err:
            rec.update(regions=err.reasons, outcome=f"refused: {err}")
            self.refusals.append((np.array(H, float), of, err))
            if content_misfit(err.reasons):
                self.prep.misfits[key] = (self.shake_px, dict(err.reasons))
            elif blur_exceeds(err.reasons):
                self.too_blurred = dict(err.reasons)
            raise
        except AlignmentError as err:
            rec.update(outcome=f"refused: {err}")
            raise
        rec.update(regions=p.reasons, outcome="verified")
        return p, rec

    def blur_refusal(self) -> PolishError | None:
        """The refusal of any further polish of this extent once one found the blur larger
        than the extent (:attr:`too_blurred`), else None."""
        if self.too_blurred is None:
            return None
        n = self.too_blurred.get("spread", 0)
        return PolishError(
            f"could not be verified: {n} of the regions' blur kernels of an earlier "
            f"estimate spread beyond shake_px={self.shake_px:g} (the blur is larger); "
            "another estimate cannot change that", self.too_blurred)

    def same_refusal(self, H: np.ndarray) -> PolishError | None:
        """The refusal of an estimate within :data:`SAME_ESTIMATE_PX` (on the working
        level) of one whose polish this extent refused, else None."""
        scale = self.levels[self.work].scale
        for H0, of, err in self.refusals:
            shift = max_corner_shift(H, H0, self.prep.ref_shape) * scale
            if shift <= SAME_ESTIMATE_PX:
                return PolishError(f"{err} (as the estimate '{of}', {shift:.3f} px from "
                                   "it on the working level)", err.reasons)
        return None

    def blurred_out(self) -> bool:
        """Whether a polish of this extent found the blur larger than the extent, so that no
        other estimate of it can verify; the refusal is then recorded (``kernel polish``)."""
        if not self.params.polish or self.too_blurred is None:
            return False
        self.failed("kernel polish", self.blur_refusal())
        return True

    def failed(self, stage: str, err: Exception) -> None:
        """Record why ``stage`` failed."""
        self.errors.append((stage, str(err)))

    def refused(self) -> AlignmentError:
        """The refusal: every stage's reason and what would let the user go on."""
        return refusal(self.errors, self.shake_px, hinted=self.hint is not None)


@dataclass
class _Estimate:
    """An estimate and how it was made: ``stages`` (joined into :attr:`Alignment.method`),
    the feature matches it came from, the polish regions and gradient blocks that agree."""

    H: np.ndarray
    stages: list[str]
    feats: Features | None = None
    n_regions: int = 0
    n_blocks: int = 0
    blocks_side: int = 0  # the level the blocks verified on (its longest side)
    #: the polish regions by outcome, when a polish of this estimate ran and was not kept
    unkept: dict[str, int] | None = None


def _align(prep: Prepared, params: AlignParams, shake_px: float) -> Alignment:
    """:func:`coarse_align` with the shake extent ``shake_px`` on a prepared pair.

    The stages that read the shake extent only through the working level are memoised in
    ``prep`` under the level indices and initial homography they read, and under the
    options (so a memo entry is reused only where a fresh computation would give the same
    result).  Results handed out are copies: a caller that edits an :attr:`Alignment.H`
    in place cannot reach the memo.
    """
    ctx = _Shake(prep, params, shake_px)
    est = None
    if params.method in ("auto", "gradient"):
        seed = _features_seed(ctx) if params.method == "auto" and ctx.hint is None else None
        est = _gradient_blocks(ctx, seed)
        if est is None and params.method == "gradient":
            raise _refused(ctx)
        if est is not None and params.polish:
            _polish_and_keep(ctx, est)
    if est is None and params.method in ("auto", "features"):
        est = _features_fallback(ctx)
    if est is None and params.method in ("auto", "ecc"):
        est = _phase_fallback(ctx)
    if est is None:
        raise _refused(ctx)
    try:
        return _result(ctx, est)
    except AlignmentError as err:
        ctx.failed("checks", err)
        raise _refused(ctx) from None


def _refused(ctx: _Shake) -> AlignmentError:
    """The refusal of ``ctx``, with its polishes' records (``polishes``)."""
    err = ctx.refused()
    err.polishes = [dict(r) for r in ctx.polishes]
    return err


# ---------------------------------------------------------------------- the stages
def _features_estimate(ctx: _Shake, i: int) -> _Estimate:
    """SIFT estimate on level ``i``, refined by ECC when that stays with the matches;
    raises its AlignmentError.  Both are memoised: they read the shake extent only
    through the working level."""
    f = ctx.prep.cached(("features", i, ctx.key), functools.partial(_matched_features, ctx, i))
    est = _Estimate(f.H.copy(), ["features"], feats=f)
    if not ctx.params.refine:
        return est
    try:
        He, res_f, res_e = ctx.prep.cached(("features-ecc", i, ctx.work, ctx.key),
                                           functools.partial(_feature_ecc, ctx, f))
        # ECC must not leave the feature matches: smoothing can wash out fine texture and
        # let it drift
        log.debug("feature residual %.2f px, after ECC %.2f px", res_f, res_e)
        if res_e > max(2.0 * res_f, 0.25 * ctx.shake_px, 1.0 / ctx.levels[i].scale):
            raise AlignmentError(
                f"ECC moved away from the feature matches ({res_e:.1f} px vs {res_f:.1f} px)"
            )
        est.H = He.copy()
        est.stages.append("ecc")
    except AlignmentError as err:
        log.debug("ECC refinement rejected (%s); keeping the feature estimate", err)
    return est


def _matched_features(ctx: _Shake, i: int) -> Features:
    """SIFT estimate on level ``i``; AlignmentError when it fails or is implausible."""
    f = match_features(ctx.levels[i], ctx.params)
    ctx.plausible(f.H)
    return f


def _feature_ecc(ctx: _Shake, f: Features, level: int | None = None
                 ) -> tuple[np.ndarray, float, float]:
    """ECC refinement of ``f.H`` on ``level`` (default the working level), its residual
    to the matches before and after; AlignmentError when it fails, is implausible or
    correlates too little."""
    i = ctx.work if level is None else level
    He, rho, _ = ecc_refine(ctx.levels, f.H, min(i + 1, ctx.top), i,
                            ctx.prep.ref_shape, ctx.params, max_jump=0.05, tolerant=True)
    ctx.plausible(He)
    if rho < ctx.params.min_ecc:
        raise AlignmentError(f"ECC correlation {rho:.2f} < {ctx.params.min_ecc:g}")
    res_f = float(np.median(np.hypot(*(map_points(f.H, f.src) - f.dst).T)))
    res_e = float(np.median(np.hypot(*(map_points(He, f.src) - f.dst).T)))
    return He, res_f, res_e


def _features_seed(ctx: _Shake) -> _Estimate | None:
    """The first feature level's estimate that holds, to seed the gradient blocks."""
    for i in ctx.feature_levels():
        try:
            return _features_estimate(ctx, i)
        except AlignmentError as err:
            log.debug("feature alignment failed at level %d: %s", i, err)
            ctx.failed("features", err)
    return None


def _gradient_blocks(ctx: _Shake, seed: _Estimate | None) -> _Estimate | None:
    """Gradient blocks from ``seed`` (if any, and if that fails) from the rotation
    hypotheses, or from the hint alone; None when none verifies (the reasons go to
    ``ctx.errors``)."""
    fine = min(ctx.first_at_most(ctx.params.gradient_side), ctx.work)
    hypotheses = None
    if ctx.hint is not None:  # the rotation hypotheses about the hint instead of the identity
        hypotheses = [ctx.hint @ R for R in rotation_hypotheses(ctx.prep.ref_shape,
                                                                 ctx.params.rotations)]
    first = ["gradient"] if ctx.hint is None else ["hint", "gradient"]
    for s in ([seed, None] if seed is not None else [None]):
        H0 = None if s is None else s.H
        coarser = None if s is None or s.feats is None else functools.partial(
            _features_on, ctx, s.feats)
        try:
            # memoised: reads the shake extent only through ``fine`` and the seed
            blocks: Blocks = ctx.prep.cached(
                ("gradient", fine, None if H0 is None else H0.tobytes(), ctx.key),
                functools.partial(gradient_align, ctx.levels, ctx.prep.ref_shape, fine,
                                  ctx.params, ctx.plausible, seed=H0, hypotheses=hypotheses,
                                  coarser_seed=coarser),
            )
        except AlignmentError as err:
            log.debug("gradient alignment failed (seed %s): %s", s is not None, err)
            ctx.failed("gradient blocks", err)
            continue
        blocks = replace(blocks, H=blocks.H.copy())
        if s is None:
            return _Estimate(blocks.H, first, n_blocks=blocks.n_agree,
                             blocks_side=blocks.side)
        stages = s.stages
        if coarser is not None and blocks.side != ctx.levels[fine].side:
            # verified on a coarser level, from the features refined there
            i = next(j for j, lv in enumerate(ctx.levels) if lv.side == blocks.side)
            refined = not np.array_equal(coarser(i), s.feats.H)
            stages = ["features", "ecc"] if refined else ["features"]
        return _Estimate(blocks.H, stages + ["gradient"], feats=s.feats,
                         n_blocks=blocks.n_agree, blocks_side=blocks.side)
    return None


def _features_on(ctx: _Shake, f: Features, i: int) -> np.ndarray:
    """The features' estimate ``f`` refined by ECC on level ``i`` (as on the working
    level, :func:`_features_estimate`), or as it is when that fails or leaves the
    matches by more than a pixel of level ``i``: the seed of the gradient blocks on a
    level coarser than the working level's (:func:`~reblur.align.blocks.gradient_align`)."""
    try:
        He, res_f, res_e = ctx.prep.cached(("features-ecc-on", f.H.tobytes(), i, ctx.key),
                                           functools.partial(_feature_ecc, ctx, f, i))
    except AlignmentError as err:
        log.debug("ECC of the features at level %d rejected (%s)", i, err)
        return f.H.copy()
    if res_e > max(2.0 * res_f, 1.0 / ctx.levels[i].scale):
        return f.H.copy()
    return He.copy()


def _polish_and_keep(ctx: _Shake, est: _Estimate) -> None:
    """The kernel polish of a gradient-block estimate, kept (``est`` updated) only when it
    verifies, its blur model fits at least half the regions, and it stays within the
    blur's reach of the blocks' estimate.

    The polish reaches the mean camera pose on a same-scene pair, where a correlation
    optimum sits near a mode of the blur; between captures years apart its blur model
    does not hold and it can wander."""
    try:
        p, rec = ctx.polish(est.H, "+".join(est.stages))
    except AlignmentError as err:
        log.debug("kernel polish not kept: %s", err)
        est.unkept = getattr(err, "reasons", None)
        return
    fine = min(ctx.first_at_most(ctx.params.gradient_side), ctx.work)
    reach = max(2.0 / ctx.levels[fine].scale, ctx.shake_px)
    moved = max_corner_shift(p.H, est.H, ctx.prep.ref_shape)
    if p.n_fit < 0.5 * p.n_total:
        why = f"the blur model fits in {p.n_fit} of {p.n_total} regions only"
    elif moved > reach:
        why = f"it moved the estimate by {moved:.1f} px (> {reach:.1f})"
    else:
        est.H, est.n_regions = p.H, p.n_agree
        est.stages.append("kernel")
        rec["outcome"] = "kept"
        return
    log.debug("kernel polish not kept: %s", why)
    rec["outcome"] = f"verified, not kept: {why}"
    est.unkept = p.reasons


def _features_fallback(ctx: _Shake) -> _Estimate | None:
    """The first feature level's estimate that the polish verifies (any, without the
    polish); None when there is none."""
    for i in ctx.feature_levels():
        if ctx.blurred_out():  # its polish would be refused
            break
        try:
            est = _features_estimate(ctx, i)
        except AlignmentError as err:
            if ctx.params.method == "features" or ctx.hint is not None:
                # (``auto`` without a hint recorded it as a seed)
                ctx.failed("features", err)
            continue
        if ctx.params.polish:
            try:
                _polish_verified(ctx, est)
            except AlignmentError as err:
                log.debug("feature estimate at level %d rejected: %s", i, err)
                ctx.failed("kernel polish", err)
                continue
        return est
    return None


def _polish_verified(ctx: _Shake, est: _Estimate) -> None:
    """Polish ``est`` in place; raise AlignmentError unless its regions verify it."""
    p, rec = ctx.polish(est.H, "+".join(est.stages))
    rec["outcome"] = "kept"
    est.H, est.n_regions = p.H, p.n_agree
    if est.stages[-1] != "kernel":
        est.stages.append("kernel")


def _phase_fallback(ctx: _Shake) -> _Estimate:
    """Phase correlation for the translation (or the hint), ECC coarse to fine, the
    polish, and a correlation check; raises the refusal with every stage's reason when it
    fails."""
    start = "phase" if ctx.hint is None else "hint"
    stage = f"{start} + ECC"
    if ctx.blurred_out():  # its polish would be refused: not worth the ECC
        raise _refused(ctx)
    try:
        # memoised: reads the shake extent only through the working level
        H = ctx.prep.cached(("phase-ecc", ctx.work, ctx.key),
                            functools.partial(_phase_ecc, ctx)).copy()
        est = _Estimate(H, [start, "ecc"])
        if ctx.params.polish:
            stage = "kernel polish"
            _polish_verified(ctx, est)
        stage = "correlation"
        lv = ctx.levels[ctx.work]
        rho = correlation(lv, est.H, max(1.0, ctx.params.blur_px * lv.scale))
        if not rho >= ctx.params.min_ecc:
            raise AlignmentError(
                f"{rho:.2f} < {ctx.params.min_ecc:g} after alignment: images look unrelated"
            )
    except AlignmentError as err:
        ctx.failed(stage, err)
        raise _refused(ctx) from None
    return est


def _phase_ecc(ctx: _Shake) -> np.ndarray:
    """Phase correlation on the coarsest level (or the hint), then ECC down to the working
    level."""
    H = phase_init(ctx.levels[ctx.top]) if ctx.hint is None else ctx.hint
    ctx.plausible(H)
    H, _, _ = ecc_refine(ctx.levels, H, ctx.top, ctx.work, ctx.prep.ref_shape, ctx.params,
                         max_jump=0.25)
    ctx.plausible(H)
    return H


def _result(ctx: _Shake, est: _Estimate) -> Alignment:
    """The final checks and diagnostics of an estimate."""
    overlap = ctx.plausible(est.H)
    lv = ctx.levels[ctx.work]
    rho = correlation(lv, est.H, max(1.0, ctx.params.blur_px * lv.scale))
    f = est.feats
    residual = None
    if f is not None:
        residual = float(np.median(np.hypot(*(map_points(est.H, f.src) - f.dst).T)))
    return Alignment(
        H=est.H, method="+".join(est.stages),
        n_matches=f.n_matches if f else 0, n_inliers=f.n_inliers if f else 0,
        scale=ctx.prep.scale0, residual_px=residual, ecc=rho if np.isfinite(rho) else None,
        overlap=overlap, n_regions=est.n_regions, n_blocks=est.n_blocks,
        blocks_side=est.blocks_side,
        overviews={k: dict(v) for k, v in (ctx.prep.sources or {}).items()},
        shake_px=float(ctx.shake_px), polishes=tuple(dict(r) for r in ctx.polishes),
        content_misfit=est.unkept is not None and content_misfit(est.unkept),
    )
