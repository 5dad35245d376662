"""Phase-correlation start and ECC refinement (:func:`cv2.findTransformECC`), coarse to fine.

ECC runs on Gaussian pre-blurred levels, so that the camera-shake blur of the
observation matters little; nodata pixels (level masks) are left out.
"""

from __future__ import annotations

import logging
import math

import cv2
import numpy as np

from ..grid import translation
from .overviews import Level, to_full, to_level
from .params import MOTIONS, AlignParams
from .result import AlignmentError
from .verify import max_corner_shift

log = logging.getLogger(__name__)

#: Iterations of ECC at a level that starts from a coarser level's converged estimate.
#: That start is within about a level pixel of the optimum, where ECC meets its criterion
#: (a correlation gain below ``1e-6``) in 2-3 iterations on pairs that correlate.  Between
#: images that differ it creeps by about 1e-5 per iteration, 40 ms each on a 1024 px
#: level, and would run all ``AlignParams.ecc_iterations``: 0.7 s per level, three times
#: per alignment of a years-apart 100 MP pair.  ``python -m benchmarks.align_cost``
#: (5c87de2 against this): the corner errors against the test bed's truth of the same-scene
#: pairs, 1 to 100 MP, change by at most 0.03 px; those of the years-apart pairs, which no
#: homography fits to better than 14-35 px, by at most 1 px.
REFINE_ITERATIONS = 5


def phase_init(level: Level) -> np.ndarray:
    """Translation (full resolution homography) from phase correlation on one level."""
    h = max(level.ref.shape[0], level.obs.shape[0])
    w = max(level.ref.shape[1], level.obs.shape[1])

    def pad(a: np.ndarray) -> np.ndarray:
        out = np.zeros((h, w), np.float64)
        out[: a.shape[0], : a.shape[1]] = a - a.mean()
        return out

    win = cv2.createHanningWindow((w, h), cv2.CV_64F)
    (dx, dy), _ = cv2.phaseCorrelate(pad(level.ref), pad(level.obs), win)
    return to_full(translation(dx, dy), level.scale)


def _ecc_level(
    level: Level, H: np.ndarray, motion: int, sigma: float, iterations: int, eps: float
) -> tuple[np.ndarray, float]:
    """One ECC run on a level; ``H`` in and out at full resolution.  Raises cv2.error."""
    Hs = to_level(H, level.scale)
    ref = cv2.GaussianBlur(level.ref, (0, 0), sigma) if sigma > 0 else level.ref
    obs = cv2.GaussianBlur(level.obs, (0, 0), sigma) if sigma > 0 else level.obs
    if motion == cv2.MOTION_HOMOGRAPHY:
        warp = Hs.astype(np.float32)
    else:
        warp = (Hs[:2] / Hs[2, 2]).astype(np.float32)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, eps)
    # leave out pixels near missing data (nodata borders), which the pre-blur smears
    r = int(math.ceil(3 * sigma)) + 1
    kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    rmask = cv2.erode(level.ref_mask, kernel, borderType=cv2.BORDER_REPLICATE)
    omask = cv2.erode(level.obs_mask, kernel, borderType=cv2.BORDER_REPLICATE)
    if rmask.sum() < 64 or omask.sum() < 64:
        raise AlignmentError("images hold too little valid data for ECC")
    rho, warp = cv2.findTransformECCWithMask(ref, obs, rmask, omask, warp, motion, crit, 1)
    M = np.asarray(warp, np.float64)
    if M.shape == (2, 3):
        M = np.vstack([M, [0.0, 0.0, 1.0]])
    return to_full(M / M[2, 2], level.scale), float(rho)


def ecc_refine(
    levels: list[Level],
    H: np.ndarray,
    start: int,
    stop: int,
    ref_shape: tuple[int, int],
    params: AlignParams,
    *,
    max_jump: float,
    tolerant: bool = False,
) -> tuple[np.ndarray, float, float]:
    """Coarse-to-fine ECC from level ``start`` down to level ``stop`` (inclusive).

    The motion model, pre-blur and iterations are ``params.motion``, ``params.blur_px``
    (at least one level pixel) and ``params.ecc_iterations`` (at most
    :data:`REFINE_ITERATIONS` once a coarser level has converged).

    Returns ``(H, rho, scale)`` of the finest level that converged.  Raises AlignmentError
    when no level converges or the estimate jumps by more than ``max_jump`` of a level's
    size (at the first level) -- later levels that fail keep the coarser estimate.  With
    ``tolerant`` (a trusted initial ``H``), levels that fail before any converged are
    skipped instead, and the levels after the first then run :data:`REFINE_ITERATIONS`
    at most: the first level spent the whole budget from that start and diverged (or
    failed), so a finer one may still confirm an optimum near it, as a refinement does,
    but not climb ``ecc_iterations`` towards a far one that the jump test refuses.  On a
    years-apart pair (the shared data's LEVIR test_12, 1 MP) the second level's 100
    iterations took 0.75 s for an estimate 102 px away, refused.
    """
    motion, blur_px, sigma_min = MOTIONS[params.motion], params.blur_px, 1.0
    iterations = params.ecc_iterations
    rho_out, scale_out, done = float("nan"), float("nan"), False
    for i in range(start, stop - 1, -1):
        lv = levels[i]
        size = f"{lv.ref.shape[1]}x{lv.ref.shape[0]} px"
        try:
            sigma = max(sigma_min, blur_px * lv.scale)
            # the refinement's budget once a level has converged, and at a level after
            # one that failed from the same trusted start (see the docstring)
            its = (min(iterations, REFINE_ITERATIONS) if done or (tolerant and i < start)
                   else iterations)
            Hn, rho = _ecc_level(lv, H, motion, sigma, its, 1e-6)
            jump = max_corner_shift(Hn, H, ref_shape) * lv.scale
            if not np.all(np.isfinite(Hn)) or jump > max_jump * lv.side:
                raise AlignmentError(f"ECC did not converge: the estimate moved by {jump:.0f} px")
        except (cv2.error, AlignmentError) as err:
            if done:
                log.debug("ECC failed at level %d (%s), keeping the coarser estimate", i, err)
                break
            if tolerant and i > stop:
                log.debug("ECC failed at level %d (%s), trying a finer level", i, err)
                continue
            if isinstance(err, AlignmentError):
                raise AlignmentError(f"{err} at {size}") from None
            raise AlignmentError(
                f"ECC did not converge at {size}: images may be unrelated or too different"
            ) from err
        H, rho_out, scale_out, done = Hn, rho, lv.scale, True
    return H, rho_out, scale_out

