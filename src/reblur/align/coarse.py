"""The coarse alignment: :func:`coarse_align` and :func:`coarse_align_shakes` run the stages.

The stages live in their own modules (:mod:`.features`, :mod:`.ecc`, :mod:`.blocks`,
:mod:`.polish`, :mod:`.verify`); this module prepares the pyramid of a pair once
(:class:`Prepared`, which also memoises the stages that do not depend on the shake
extent) and decides between their results.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable, Hashable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from ..grid import map_points
from .blocks import gradient_align
from .ecc import ecc_refine, phase_init
from .features import Features, match_features
from .overviews import Level, block_factor, image_shape, overview_k, pyramid
from .polish import REGION_PX, kernel_polish
from .result import Alignment, AlignmentError
from .verify import check_plausible, correlation, intensity_spread, max_corner_shift

log = logging.getLogger(__name__)

_METHODS = ("auto", "features", "gradient", "ecc")
_MOTIONS = {"homography": cv2.MOTION_HOMOGRAPHY, "affine": cv2.MOTION_AFFINE}


def coarse_align(
    reference,
    observed,
    *,
    max_side: int = 1024,
    min_side: int = 128,
    method: str = "auto",
    shake_px: float = 16.0,
    nodata: float | None = 0.0,
    feature_side: int = 512,
    n_features: int = 5000,
    ratio: float = 0.8,
    ransac_px: float = 2.0,
    min_inliers: int = 12,
    min_inlier_ratio: float = 0.1,
    refine: bool = True,
    motion: str = "homography",
    blur_px: float = 8.0,
    ecc_iterations: int = 100,
    polish: bool = True,
    min_r2: float = 0.3,
    min_regions: float = 0.15,
    min_agree: float = 0.6,
    min_spread: float = 0.3,
    min_ecc: float = 0.4,
    max_zoom: float = 2.0,
    max_anisotropy: float = 2.0,
    min_overlap: float = 0.2,
    gradient_side: int = 512,
    rotations: tuple[float, ...] = (-12.0, -8.0, -4.0, 0.0, 4.0, 8.0, 12.0),
    block_ncc: float = 0.25,
    min_blocks: int = 12,
) -> Alignment:
    """Estimate the global reference -> observation homography at low resolution.

    Parameters
    ----------
    reference, observed : array-like, (H, W) or (H, W, C)
        Sharp reference and blurred observation (numpy, zarr, ... any dtype; sizes and band
        counts may differ).  Each is read once, strip by strip, into an overview.
    max_side : int
        Longest side of the finest overview (both images share one integer block factor).
    min_side : int
        Longest side of the coarsest pyramid level.
    method : {"auto", "features", "gradient", "ecc"}
        ``"auto"``: gradient blocks (see Notes) seeded by the SIFT estimate when there is
        one, else by rotation hypotheses; they decide and verify, and the kernel polish is
        kept only where its blur model fits most regions.  If the blocks cannot verify, the
        SIFT estimate with ECC and the polish, then phase correlation with ECC and the
        polish.  ``"gradient"``: gradient blocks from rotation hypotheses only.
        ``"features"``: SIFT, ECC and the polish only; ``"ecc"``: phase correlation, ECC
        and the polish only.
    shake_px : float
        Largest camera-shake displacement expected during the exposure, in full-resolution
        pixels, anywhere in the image (an in-plane roll moves the corners by radius x
        angle: 1 degree is 17 px per 1000 px of radius).  It picks the working level of the
        refinement (the finest level where it spans at most 4 pixels) and the kernel size of
        the polish; a blur much larger than this fails verification.
    nodata : float or None
        Overview pixels equal to this value (whole blocks of it, after normalisation) are
        missing data, e.g. the empty corners of a reprojected scene; ECC and the polish ignore
        them.  None: every pixel holds data.
    feature_side : int
        SIFT runs on the finest level whose longest side is at most this (and on the next
        coarser level if that fails).
    n_features : int
        SIFT features per image.
    ratio : float
        Lowe's ratio-test threshold.
    ransac_px : float
        Robust-fit inlier threshold, in pixels of the level the features are matched on.
    min_inliers : int
        Fewest feature matches (and inliers) accepted.
    min_inlier_ratio : float
        Smallest accepted fraction of inliers among the matches.
    refine : bool
        Refine the feature estimate with ECC (the phase-correlation path always uses ECC).
    motion : {"homography", "affine"}
        Motion model of the ECC refinement.
    blur_px : float
        Gaussian pre-blur applied to both images before ECC, as a standard deviation in
        full-resolution pixels (at least 1 pixel of the level).
    ecc_iterations : int
        ECC iterations per level.
    polish : bool
        Apply the blur-aware kernel polish (see Notes), which also verifies the result.
    min_r2 : float
        Smallest fraction of a region's variance the local blur kernel must explain for the
        region to take part in the polish.
    min_regions : float
        Smallest fraction of the polish regions (and at least 8) that must agree with the
        final homography; fewer raises :class:`AlignmentError`.
    min_agree : float
        Smallest fraction of the regions where a kernel fits that must agree with the final
        homography (a kernel fitted where the scene changed is spread out, its centroid
        near the current estimate, so agreement must be a clear majority).
    min_spread : float
        Smallest area of the convex hull of the agreeing region centres, as a fraction of
        the region grid: a homography supported by one corner of the image only is not
        trusted elsewhere.
    min_ecc : float
        Smallest accepted ECC correlation: a feature estimate keeps its own value when ECC
        ends below it; a phase-correlation estimate raises.
    max_zoom : float
        Largest accepted scale change (either way) between the images.
    max_anisotropy : float
        Largest accepted ratio of the local stretches of ``H``.
    min_overlap : float
        Smallest accepted fraction of the observation covered by the mapped reference.
    gradient_side : int
        The gradient blocks are refined down to the finest level whose longest side is at
        most this (or the working level, if finer).
    rotations : tuple of float
        In-plane rotations (degrees) tried as hypotheses when no feature estimate seeds the
        gradient blocks.
    block_ncc : float
        Correlation peak a gradient block must reach to count as confident (the peak
        between unrelated 96 px blocks stays near 0.1).
    min_blocks : int
        Fewest confident gradient blocks that must agree with the result; at least
        ``min_agree`` of the confident blocks and ``min_spread`` of the image are also
        required.

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
        Bad arguments (shapes, dtypes, options).

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
    >>> a = coarse_align(ref, obs[..., 0], min_side=64)
    >>> corners = np.array([[0, 0], [399, 0], [399, 399], [0, 399]])
    >>> err = np.abs(map_points(a.H, corners) - map_points(H, corners)).max()
    >>> bool(err < 1.0), a.method.split("+")[0]
    (True, 'features')
    """
    params = dict(locals())  # every keyword argument, as given
    del params["reference"], params["observed"], params["shake_px"]
    _check_args(method=method, motion=motion, min_side=min_side, max_side=max_side,
                shakes=(shake_px,))
    prep = _prepare(reference, observed, max_side=max_side, min_side=min_side, nodata=nodata)
    return _align(prep, shake_px=shake_px, **params)


def coarse_align_shakes(
    reference,
    observed,
    shakes: Sequence[float] = (8.0, 16.0, 32.0, 64.0),
    **kwargs: Any,
) -> Iterator[tuple[float, Alignment | AlignmentError]]:
    """:func:`coarse_align` for several camera-shake extents, sharing what does not depend
    on the extent.

    The overviews and the pyramid are built once, and the SIFT matches, their ECC
    refinement, the gradient blocks and the phase-correlation start are computed once for
    each set of inputs they read (the shake extent only picks the working level, which
    these stages may share); the kernel polish and the checks run for each extent.  Each
    result is exactly the one a separate ``coarse_align(reference, observed,
    shake_px=s, **kwargs)`` gives.

    Parameters
    ----------
    reference, observed : array-like, (H, W) or (H, W, C)
        As for :func:`coarse_align`; each is read once.
    shakes : sequence of float
        Shake extents (``shake_px`` of :func:`coarse_align`), tried in this order.
    **kwargs
        Any other keyword argument of :func:`coarse_align` (not ``shake_px``).

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
    TypeError
        An unknown keyword argument, or ``shake_px``.

    Examples
    --------
    >>> import numpy as np, cv2
    >>> from reblur.grid import pose_homography
    >>> from reblur.warp import warp_window
    >>> rng = np.random.default_rng(0)
    >>> ref = cv2.GaussianBlur(rng.random((400, 400)).astype(np.float32), (0, 0), 2)
    >>> H = pose_homography(12, -7, rz=2.0, center=(199.5, 199.5))
    >>> obs, _ = warp_window(ref, H, (0, 0, 400, 400))
    >>> for s, a in coarse_align_shakes(ref, obs[..., 0], (8.0, 16.0), min_side=64):
    ...     print(s, a.method.split("+")[0])
    8.0 features
    16.0 features
    """
    defaults = dict(coarse_align.__kwdefaults__)
    del defaults["shake_px"]
    unknown = sorted(set(kwargs) - set(defaults))
    if unknown:
        raise TypeError(f"coarse_align_shakes() got unexpected keyword arguments {unknown}")
    params = {**defaults, **kwargs}
    shakes = tuple(shakes)
    _check_args(method=params["method"], motion=params["motion"],
                min_side=params["min_side"], max_side=params["max_side"], shakes=shakes)
    try:
        prep = _prepare(reference, observed, max_side=params["max_side"],
                        min_side=params["min_side"], nodata=params["nodata"])
    except AlignmentError as err:
        for sp in shakes:
            yield sp, AlignmentError(str(err))
        return
    for sp in shakes:
        try:
            yield sp, _align(prep, shake_px=sp, **params)
        except AlignmentError as err:
            yield sp, err


def _check_args(
    *, method: str, motion: str, min_side: int, max_side: int, shakes: tuple[float, ...]
) -> None:
    """Raise ValueError on bad arguments of :func:`coarse_align`."""
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
    if motion not in _MOTIONS:
        raise ValueError(f"motion must be one of {tuple(_MOTIONS)}, got {motion!r}")
    if min_side < 16 or max_side < min_side:
        raise ValueError(f"need 16 <= min_side <= max_side, got {min_side}, {max_side}")
    for shake_px in shakes:
        if not shake_px >= 0:
            raise ValueError(f"shake_px must be >= 0, got {shake_px}")


@dataclass
class Prepared:
    """The overviews' pyramid of one pair and the memo of the stages that do not depend
    on the shake extent (see :func:`_align`)."""

    ref_shape: tuple[int, int]
    obs_shape: tuple[int, int]
    scale0: float
    levels: list[Level]
    memo: dict = field(default_factory=dict)

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


def _prepare(reference, observed, *, max_side: int, min_side: int,
             nodata: float | None) -> Prepared:
    """Overviews of both images (each read once) and their pyramid.

    Raises ValueError when they are too small, AlignmentError when one is textureless."""
    ref_shape, obs_shape = image_shape(reference), image_shape(observed)
    k = block_factor(max(ref_shape + obs_shape), max_side)
    scale0 = 1.0 / k
    ref0, obs0 = overview_k(reference, k), overview_k(observed, k)
    if min(ref0.shape + obs0.shape) < 16:
        raise ValueError(
            f"images {ref_shape} and {obs_shape} are too small or elongated to align at "
            f"max_side={max_side}; raise max_side"
        )
    for name, a in (("reference", ref0), ("observation", obs0)):
        tol = 1e-4 * max(1.0, float(np.max(np.abs(a))))
        if intensity_spread(a) <= tol:
            raise AlignmentError(f"images are textureless: the {name} is (nearly) constant")
    levels = pyramid(ref0, obs0, scale0, min_side, nodata)
    return Prepared(ref_shape, obs_shape, scale0, levels)


def _align(
    prep: Prepared,
    *,
    shake_px: float,
    max_side: int,
    min_side: int,
    method: str,
    nodata: float | None,
    feature_side: int,
    n_features: int,
    ratio: float,
    ransac_px: float,
    min_inliers: int,
    min_inlier_ratio: float,
    refine: bool,
    motion: str,
    blur_px: float,
    ecc_iterations: int,
    polish: bool,
    min_r2: float,
    min_regions: float,
    min_agree: float,
    min_spread: float,
    min_ecc: float,
    max_zoom: float,
    max_anisotropy: float,
    min_overlap: float,
    gradient_side: int,
    rotations: tuple[float, ...],
    block_ncc: float,
    min_blocks: int,
) -> Alignment:
    """:func:`coarse_align` with the shake extent ``shake_px`` on a prepared pair.

    The stages that read the shake extent only through the working level are memoised in
    ``prep`` under the level indices and initial homography they read, and under every
    other argument (so a memo entry is reused only where a fresh computation would give
    the same result).  Results handed out are copies: a caller that edits an
    :attr:`Alignment.H` in place cannot reach the memo.
    """
    # every argument but the shake extent: part of each memo key
    fixed = repr(sorted((k, v) for k, v in locals().items() if k not in ("prep", "shake_px")))
    ref_shape, obs_shape, scale0, levels = prep.ref_shape, prep.obs_shape, prep.scale0, prep.levels
    top = len(levels) - 1
    checks = dict(max_zoom=max_zoom, max_anisotropy=max_anisotropy, min_overlap=min_overlap)
    mot = _MOTIONS[motion]

    def first_at_most(side: int) -> int:
        return next((i for i, lv in enumerate(levels) if lv.side <= side), top)

    def shake_at(i: int) -> int:
        return int(math.ceil(shake_px * levels[i].scale))

    # working level of ECC and the polish: the finest where the shake spans <= 4 pixels,
    # but large enough for a grid of polish regions
    work = next((i for i in range(len(levels)) if shake_at(i) <= 4), top)
    while work > 0 and max(levels[work].obs.shape) < 5 * REGION_PX:
        work -= 1

    ecc_kw = dict(motion=mot, blur_px=blur_px, sigma_min=1.0, iterations=ecc_iterations)
    lv = levels[work]
    # polish regions hold >= 6 pixels per kernel tap
    region_px = max(REGION_PX, math.sqrt(6.0) * (2 * max(shake_at(work) + 2, 2) + 1))
    n_regions = tuple(int(np.clip(round(n / region_px), 3, 8)) for n in lv.obs.shape)
    n_total = n_regions[0] * n_regions[1]

    def polish_and_verify(H: np.ndarray, stages: list[str]) -> tuple[np.ndarray, int, int]:
        """Kernel polish of ``H``; raise AlignmentError unless enough regions agree.

        Returns the polished ``H``, the regions that agree and the regions that fit."""
        n_agree, n_fit, spread, accepted = 0, 0, 0.0, None
        for R in (shake_at(work) + 2, shake_at(work) + 1):
            R = max(R, 2)
            Hp, n_agree, n_fit, spread = kernel_polish(
                lv, H, R, n_regions=n_regions, min_r2=min_r2, max_pixels=8192,
                max_sd=max(1.0, shake_px * lv.scale),
            )
            if n_agree < 8:
                break
            jump = max_corner_shift(Hp, H, ref_shape) * lv.scale
            if jump > 2 * R:
                log.debug("kernel polish rejected: corners moved by %.1f level px", jump)
                n_agree = 0
                break
            try:
                check_plausible(Hp, ref_shape, obs_shape, **checks)
            except AlignmentError as err:
                log.debug("kernel polish rejected: %s", err)
                n_agree = 0
                break
            H, accepted = Hp, (n_agree, n_fit, spread)
            if stages[-1] != "kernel":
                stages.append("kernel")
        if accepted is not None:
            n_agree, n_fit, spread = accepted
        log.debug("polish: %d regions agree, %d fit, spread %.2f", n_agree, n_fit, spread)
        need = max(8, math.ceil(min_regions * n_total), math.ceil(min_agree * n_fit))
        if n_agree >= need and spread < min_spread:
            raise AlignmentError(
                f"alignment could not be verified: the {n_agree} regions that agree with it "
                f"span {100 * spread:.0f} % of the image (< {100 * min_spread:.0f} %)"
            )
        if n_agree < need:
            raise AlignmentError(
                f"alignment could not be verified: {n_agree} regions agree with it, of "
                f"{n_fit} where the blur model fits and {n_total} in all (need {need}): images "
                f"unrelated, changed too much or blurred by more than shake_px={shake_px:g}"
            )
        return H, n_agree, n_fit

    errors: list[str] = []

    def matched_features(i: int) -> Features:
        """SIFT estimate on level ``i``; AlignmentError when it fails or is implausible."""
        f = match_features(
            levels[i], n_features=n_features, ratio=ratio, ransac_px=ransac_px,
            min_inliers=min_inliers, min_inlier_ratio=min_inlier_ratio,
        )
        check_plausible(f.H, ref_shape, obs_shape, **checks)
        return f

    def feature_ecc(f: Features) -> tuple[np.ndarray, float, float]:
        """ECC refinement of ``f.H`` on the working level, its residual to the matches
        before and after; AlignmentError when it fails, is implausible or correlates too
        little."""
        He, rho, _ = ecc_refine(
            levels, f.H, min(work + 1, top), work, ref_shape, max_jump=0.05,
            tolerant=True, **ecc_kw,
        )
        check_plausible(He, ref_shape, obs_shape, **checks)
        if rho < min_ecc:
            raise AlignmentError(f"ECC correlation {rho:.2f} < {min_ecc:g}")
        res_f = float(np.median(np.hypot(*(map_points(f.H, f.src) - f.dst).T)))
        res_e = float(np.median(np.hypot(*(map_points(He, f.src) - f.dst).T)))
        return He, res_f, res_e

    def features_estimate(i: int) -> tuple[Features, np.ndarray, list[str]]:
        """SIFT estimate on level ``i``, refined by ECC when that stays with the matches;
        raises its AlignmentError.  Both are memoised: they read the shake extent only
        through the working level."""
        f = prep.cached(("features", i, fixed), functools.partial(matched_features, i))
        H, stages = f.H.copy(), ["features"]
        if refine:
            try:
                He, res_f, res_e = prep.cached(
                    ("features-ecc", i, work, fixed), functools.partial(feature_ecc, f)
                )
                # ECC must not leave the feature matches: smoothing can wash out fine
                # texture and let it drift
                log.debug("feature residual %.2f px, after ECC %.2f px", res_f, res_e)
                if res_e > max(2.0 * res_f, 0.25 * shake_px, 1.0 / levels[i].scale):
                    raise AlignmentError(
                        f"ECC moved away from the feature matches ({res_e:.1f} px vs "
                        f"{res_f:.1f} px)"
                    )
                H = He.copy()
                stages.append("ecc")
            except AlignmentError as err:
                log.debug("ECC refinement rejected (%s); keeping the feature estimate", err)
        return f, H, stages

    feature_levels = list(dict.fromkeys((first_at_most(feature_side),
                                         min(first_at_most(feature_side) + 1, top))))
    feats: Features | None = None
    n_agree, n_blocks = 0, 0
    if method in ("auto", "gradient"):
        # features (when they hold) only seed the gradient blocks, which decide
        init: tuple[Features, np.ndarray, list[str]] | None = None
        if method == "auto":
            for i in feature_levels:
                try:
                    init = features_estimate(i)
                    break
                except AlignmentError as err:
                    log.debug("feature alignment failed at level %d: %s", i, err)
                    errors.append(str(err))
        fine = min(first_at_most(gradient_side), work)
        grad_kw = dict(
            rotations=rotations, min_ncc=block_ncc, min_blocks=min_blocks,
            min_agree=min_agree, min_spread=min_spread,
            plausible=lambda M: check_plausible(M, ref_shape, obs_shape, **checks),
        )
        blocks, stages = None, ["gradient"]
        for seed in ([init, None] if init is not None else [None]):
            H0 = None if seed is None else seed[1]
            try:
                # memoised: reads the shake extent only through ``fine`` and the seed
                blocks = prep.cached(
                    ("gradient", fine, None if H0 is None else H0.tobytes(), fixed),
                    functools.partial(gradient_align, levels, H0, ref_shape, fine, **grad_kw),
                )
                blocks = replace(blocks, H=blocks.H.copy())
            except AlignmentError as err:
                log.debug("gradient alignment failed (seed %s): %s", seed is not None, err)
                errors.append(str(err))
                continue
            if seed is not None:
                feats, stages = seed[0], seed[2] + ["gradient"]
            break
        if blocks is not None:
            H, n_blocks = blocks.H, blocks.n_agree
            if polish:
                # the blur-aware polish reaches the mean camera pose on a same-scene pair,
                # where a correlation optimum sits near a mode of the blur; between captures
                # years apart its blur model does not hold and it can wander: keep it only
                # when it verifies and stays within the blur's reach of the blocks' estimate
                try:
                    Hp, n_p, n_fit = polish_and_verify(H, ["gradient"])
                    reach = max(2.0 / levels[fine].scale, shake_px)
                    moved = max_corner_shift(Hp, H, ref_shape)
                    if n_fit < 0.5 * n_total:
                        log.debug("kernel polish not kept: the blur model fits in %d of %d "
                                  "regions only", n_fit, n_total)
                    elif moved > reach:
                        log.debug("kernel polish moved %.1f px (> %.1f): not kept", moved, reach)
                    else:
                        H, n_agree = Hp, n_p
                        stages.append("kernel")
                except AlignmentError as err:
                    log.debug("kernel polish not kept: %s", err)
        elif method == "gradient":
            raise AlignmentError(errors[-1])

    if method == "features" or (method == "auto" and n_blocks == 0):
        for i in feature_levels:
            try:
                f, H, stages = features_estimate(i)
            except AlignmentError as err:
                if method == "features":
                    errors.append(str(err))
                continue
            n_agree = 0
            if polish:
                try:
                    H, n_agree, _ = polish_and_verify(H, stages)
                except AlignmentError as err:
                    log.debug("feature estimate at level %d rejected: %s", i, err)
                    errors.append(str(err))
                    continue
            feats = f
            break

    if n_blocks == 0 and feats is None and method in ("auto", "ecc"):
        # fallback: phase correlation for the translation, then ECC coarse to fine
        def phase_ecc() -> np.ndarray:
            H = phase_init(levels[top])
            check_plausible(H, ref_shape, obs_shape, **checks)
            H, _, _ = ecc_refine(levels, H, top, work, ref_shape, max_jump=0.25, **ecc_kw)
            check_plausible(H, ref_shape, obs_shape, **checks)
            return H

        try:
            # memoised: reads the shake extent only through the working level
            H = prep.cached(("phase-ecc", work, fixed), phase_ecc).copy()
            stages, n_agree = ["phase", "ecc"], 0
            if polish:
                H, n_agree, _ = polish_and_verify(H, stages)
            rho = correlation(lv, H, max(1.0, blur_px * lv.scale))
            if not rho >= min_ecc:
                raise AlignmentError(
                    f"correlation {rho:.2f} < {min_ecc:g} after alignment: images look unrelated"
                )
        except AlignmentError as err:
            raise AlignmentError(
                "; fallback: ".join(dict.fromkeys(errors + [str(err)]))
            ) from None
    elif n_blocks == 0 and feats is None:
        raise AlignmentError("; fallback: ".join(dict.fromkeys(errors)))

    overlap = check_plausible(H, ref_shape, obs_shape, **checks)
    rho = correlation(lv, H, max(1.0, blur_px * lv.scale))
    residual = None
    if feats is not None:
        residual = float(np.median(np.hypot(*(map_points(H, feats.src) - feats.dst).T)))
    return Alignment(
        H=H, method="+".join(stages),
        n_matches=feats.n_matches if feats else 0, n_inliers=feats.n_inliers if feats else 0,
        scale=scale0, residual_px=residual, ecc=rho if np.isfinite(rho) else None,
        overlap=overlap, n_regions=n_agree, n_blocks=n_blocks,
    )
