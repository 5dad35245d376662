"""Gradient blocks: alignment of captures years apart, independent of local features.

Signed-gradient fields of the reference warped by the current estimate and of the
observation are correlated block by block; a robust similarity through the blocks whose
correlation peak is confident corrects the estimate (:func:`gradient_align`).  Unrelated
images give almost no confident block.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from .._memory import available_cpus, parts, thread_map
from ..grid import map_points, translation
from .overviews import Level, to_full, to_level
from .params import AlignParams
from .result import AlignmentError
from .verify import check_blocks, max_corner_shift

log = logging.getLogger(__name__)

#: Side, in pixels of the level, of the blocks matched by :func:`_block_match`.
_BLOCK_PX = 96
#: Side of the blocks of the coarse (rotation hypothesis) search.
_COARSE_BLOCK_PX = 64
#: Threads matching the blocks of one level (each with OpenCV single-threaded).
MATCH_WORKERS = min(2, available_cpus())


def _grad_field(a: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """``(h, w, 2)`` signed gradient of ``a`` smoothed by ``sigma``, zero near missing data.

    Gradients drop the brightness offset between captures and emphasise the edges (roads,
    roof outlines, field borders) that survive years between them; zeroing them near
    missing data keeps the edge of a nodata border from matching itself.
    """
    b = cv2.GaussianBlur(a, (0, 0), sigma)
    gx = cv2.Sobel(b, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(b, cv2.CV_32F, 0, 1, ksize=3)
    r = int(math.ceil(2 * sigma)) + 2
    m = cv2.erode(
        mask.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8),
        borderType=cv2.BORDER_CONSTANT, borderValue=0,
    )
    return np.dstack([gx * m, gy * m])


def _parabola(a: float, b: float, c: float) -> float:
    d = a - 2.0 * b + c
    return 0.0 if d >= 0 else float(np.clip(0.5 * (a - c) / d, -0.5, 0.5))


def _block_match(
    level: Level, H: np.ndarray, *, block: int, search: int, step: int, sigma: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Displacements of gradient blocks between the reference warped by ``H`` and the
    observation, on one level.

    The reference is warped into the observation frame by ``H`` (full resolution); for
    every ``block x block`` block of the observation (centres ``step`` apart) the
    normalised correlation of the two gradient fields is searched over ``+-search`` pixels.
    Returns ``(src, dst, ncc)``: ``src`` the matched points of the warped reference,
    ``dst`` the block centres of the observation (level pixels), and the correlation peak.
    The blocks are matched on :data:`MATCH_WORKERS` threads, in a fixed order.
    """
    h, w = level.obs.shape
    warped, cover = level.warped_reference(to_level(H, level.scale))
    fr = _grad_field(warped, cover, sigma)
    fo = _grad_field(level.obs, level.obs_mask, sigma)
    half, S = block // 2, search
    cys = np.arange(half + S, h - half - S + 1, step)
    cxs = np.arange(half + S, w - half - S + 1, step)
    # blocks of the observation with gradient almost everywhere, whose search window in
    # the warped reference has it mostly (counts from integral images)
    side = 2 * half  # the template's side (``block`` rounded down to even)
    n_o = _box_counts(np.any(fo != 0, axis=2), cys - half, cxs - half, side)
    n_r = _box_counts(np.any(fr != 0, axis=2), cys - half - S, cxs - half - S, side + 2 * S)
    ok = (n_o / side**2 >= 0.9) & (n_r / (side + 2 * S) ** 2 >= 0.8)
    centres = [(int(cys[i]), int(cxs[j])) for i, j in zip(*np.nonzero(ok), strict=True)]

    def match(part: list[tuple[int, int]]) -> list[tuple[float, float, int, int, float]]:
        out = []
        for cy, cx in part:
            t = fo[cy - half : cy + half, cx - half : cx + half]
            sr = fr[cy - half - S : cy + half + S, cx - half - S : cx + half + S]
            if float(np.ptp(t)) <= 0 or float(np.ptp(sr)) <= 0:
                continue
            r = cv2.matchTemplate(
                np.ascontiguousarray(sr), np.ascontiguousarray(t), cv2.TM_CCOEFF_NORMED
            )
            _, peak, _, (px, py) = cv2.minMaxLoc(r)
            if not np.isfinite(peak):
                continue
            dx = px - S + (_parabola(*r[py, px - 1 : px + 2]) if 0 < px < 2 * S else 0.0)
            dy = py - S + (_parabola(*r[py - 1 : py + 2, px]) if 0 < py < 2 * S else 0.0)
            # observation block at c matches the warped reference at c + d
            out.append((cx + dx, cy + dy, cx, cy, peak))
        return out

    found = [m for got in thread_map(match, parts(centres, MATCH_WORKERS), MATCH_WORKERS)
             for m in got]
    a = np.float64(found).reshape(-1, 5)
    return a[:, 0:2].copy(), a[:, 2:4].copy(), a[:, 4].copy()


def _box_counts(a: np.ndarray, y0: np.ndarray, x0: np.ndarray, side: int) -> np.ndarray:
    """Number of true pixels of ``a`` in the ``side x side`` boxes whose top-left corners
    are the rows ``y0`` times the columns ``x0`` (all inside ``a``)."""
    s = cv2.integral(a.astype(np.uint8), sdepth=cv2.CV_32S).astype(np.int64)
    y1, x1 = y0 + side, x0 + side
    return (s[y1][:, x1] - s[y0][:, x1] - s[y1][:, x0] + s[y0][:, x0])


def _similarity_lsq(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares similarity (rotation, uniform scale, translation) ``src -> dst``."""
    n = len(src)
    A = np.zeros((2 * n, 4))
    A[0::2] = np.c_[src[:, 0], -src[:, 1], np.ones(n), np.zeros(n)]
    A[1::2] = np.c_[src[:, 1], src[:, 0], np.zeros(n), np.ones(n)]
    a, b, tx, ty = np.linalg.lstsq(A, dst.reshape(-1), rcond=None)[0]
    return np.array([[a, -b, tx], [b, a, ty], [0.0, 0.0, 1.0]])


def _robust_similarity(
    src: np.ndarray, dst: np.ndarray, tol: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """RANSAC similarity then least squares on its inliers (re-selected three times).

    Returns ``(M, inliers)`` or None when fewer than 4 points agree.
    """
    if len(src) < 4:
        return None
    M, mask = cv2.estimateAffinePartial2D(
        src, dst, method=cv2.RANSAC, ransacReprojThreshold=tol, maxIters=5000,
        confidence=0.999, refineIters=0,
    )
    if M is None or mask is None:
        return None
    inl = mask.ravel().astype(bool)
    M = np.vstack([M, [0.0, 0.0, 1.0]])
    for _ in range(3):
        if inl.sum() < 4:
            return None
        M = _similarity_lsq(src[inl], dst[inl])
        inl = np.hypot(*(map_points(M, src) - dst).T) < tol
    if inl.sum() < 4:
        return None
    return M, inl


@dataclass
class Blocks:
    H: np.ndarray  # full resolution
    n_agree: int  # confident blocks that agree with H
    n_confident: int  # blocks whose correlation peak reaches the confidence level
    n_blocks: int  # blocks matched
    spread: float  # convex hull of the agreeing blocks / area of the block grid
    residual_px: float  # median misfit of the agreeing blocks, full-resolution pixels
    side: int = 0  # longest side of the level the blocks were matched on


def _gradient_estimate(
    level: Level,
    H: np.ndarray,
    ref_shape: tuple[int, int],
    *,
    block: int,
    search: int,
    sigma: float,
    min_ncc: float,
    tol: float,
    iterations: int = 3,
) -> Blocks | None:
    """Correct ``H`` (full resolution) by a similarity fitted to the confident gradient
    blocks of one level that agree within ``tol`` level pixels; repeat up to
    ``iterations`` times while the corners still move.  None when fewer than 4 agree."""
    best: Blocks | None = None
    for _ in range(iterations):
        src, dst, score = _block_match(
            level, H, block=block, search=search, step=max(4, block // 3), sigma=sigma
        )
        conf = score >= min_ncc
        fit = _robust_similarity(src[conf], dst[conf], tol)
        if fit is None:
            return best
        M, inl = fit
        # C maps the warped-reference frame to the observation: H' = C @ H
        Hn = to_full(M @ to_level(H, level.scale), level.scale)
        pts = dst[conf][inl]
        grid = float((np.ptp(dst[:, 0]) + block) * (np.ptp(dst[:, 1]) + block))
        spread = cv2.contourArea(cv2.convexHull(np.float32(pts))) / max(grid, 1.0)
        res = float(np.median(np.hypot(*(map_points(M, src[conf][inl]) - pts).T)))
        moved = max_corner_shift(Hn, H, ref_shape) * level.scale
        H = Hn
        best = Blocks(H, int(inl.sum()), int(conf.sum()), len(score), float(spread),
                       res / level.scale, level.side)
        if moved < 0.1:
            break
    return best


def gradient_align(
    levels: list[Level],
    ref_shape: tuple[int, int],
    fine: int,
    params: AlignParams,
    plausible: Callable[[np.ndarray], object],
    *,
    seed: np.ndarray | None = None,
    hypotheses: Sequence[np.ndarray] | None = None,
    coarser_seed: Callable[[int], np.ndarray] | None = None,
) -> Blocks:
    """Alignment by gradient-block correlation (independent of local features).

    Without a ``seed``: on the finest level whose longest side is at most 256, every
    homography of ``hypotheses`` (default: the in-plane rotations ``params.rotations``
    about the reference centre, :func:`rotation_hypotheses`) is tried and blocks searched
    over +-10 % of the side; the hypothesis with most confident agreeing blocks wins.
    Then, on each level down to ``fine``, the estimate is refined with a +-8 pixel search.
    ``plausible`` raises AlignmentError on an implausible estimate.  Raises
    AlignmentError unless at least ``params.min_blocks`` confident blocks, and at least
    ``params.min_agree`` of all the confident ones, agree, spread over
    ``params.min_spread`` of the block grid.

    A ``seed`` is refined on level ``fine``; when that does not verify, it is refined
    afresh on the next coarser level (from ``coarser_seed(i)`` on level ``i`` when given),
    and so on down to the level the search from the hypotheses starts refining on
    (:attr:`Blocks.side` says which verified).  Where the finer level's blocks disagree
    and a coarser level's agree, the finer detail is what differs, not the registration:
    captures years apart seen finer than their changes (the cost benchmark's 100 MP
    upsampled LEVIR pair: a third of the confident blocks agree at 1024 px, all but a few
    at 512 px).  Without this, the alignment ran every fallback on the finer level and
    then larger shake extents until one worked on the coarser level: the same estimate,
    in twice the time (``python -m benchmarks.align_cost``).
    """
    if seed is not None:
        return _seeded(levels, ref_shape, fine, params, plausible, seed, coarser_seed)
    if hypotheses is None:
        hypotheses = rotation_hypotheses(ref_shape, params.rotations)
    H0, start = _best_hypothesis(levels, hypotheses, ref_shape, fine, params.block_ncc)
    plausible(H0)
    H, out = H0, None
    for i in range(max(start, fine), fine - 1, -1):
        out = _level_estimate(levels[i], H, ref_shape, params, plausible)
        H = out.H
    assert out is not None
    _verified(out, params)
    return out


def _seeded(levels: list[Level], ref_shape: tuple[int, int], fine: int, params: AlignParams,
            plausible: Callable[[np.ndarray], object], seed: np.ndarray,
            coarser_seed: Callable[[int], np.ndarray] | None) -> Blocks:
    """:func:`gradient_align` from a seed: the finest level from ``fine`` down to the
    hypotheses' first refinement level whose blocks verify the seed refined on it."""
    plausible(seed)
    last = max(fine, _hypothesis_level(levels, fine) - 1)

    def on(i: int) -> Blocks:  # the seed refined on level i, verified
        start = seed if i == fine or coarser_seed is None else coarser_seed(i)
        out = _level_estimate(levels[i], start, ref_shape, params, plausible)
        _verified(out, params)
        return out

    for i in range(fine, last):
        try:
            return on(i)
        except AlignmentError:
            log.debug("gradient blocks from the seed do not verify at %d px; trying %d px",
                      levels[i].side, levels[i + 1].side)
    return on(last)


def _level_estimate(lv: Level, H: np.ndarray, ref_shape: tuple[int, int], params: AlignParams,
                    plausible: Callable[[np.ndarray], object]) -> Blocks:
    """:func:`_gradient_estimate` of ``H`` on the level ``lv`` (+-8 px search), checked
    plausible; AlignmentError when fewer than 4 blocks agree."""
    b = _gradient_estimate(
        lv, H, ref_shape, block=min(_BLOCK_PX, max(lv.obs.shape) // 4), search=8,
        sigma=1.0, min_ncc=params.block_ncc, tol=1.0,
    )
    if b is None:
        raise AlignmentError(
            f"gradient blocks are inconsistent at {lv.ref.shape[1]}x{lv.ref.shape[0]} px: "
            "images unrelated or changed too much"
        )
    plausible(b.H)
    return b


def _verified(out: Blocks, params: AlignParams) -> None:
    """:func:`~reblur.align.verify.check_blocks` of a level's blocks (logged)."""
    log.debug("gradient blocks at %d px: %d agree of %d confident, %d in all; spread %.2f",
              out.side, out.n_agree, out.n_confident, out.n_blocks, out.spread)
    check_blocks(out.n_agree, out.n_confident, out.n_blocks, out.spread, params)


def rotation_hypotheses(ref_shape: tuple[int, int], rotations: Sequence[float]) -> list[np.ndarray]:
    """In-plane rotations (degrees) about the centre of the reference, as homographies."""
    h, w = ref_shape
    return [translation((w - 1) / 2.0, (h - 1) / 2.0) @ rotation(rz) @ translation(
        -(w - 1) / 2.0, -(h - 1) / 2.0) for rz in rotations]


def _best_hypothesis(
    levels: list[Level],
    hypotheses: Sequence[np.ndarray],
    ref_shape: tuple[int, int],
    fine: int,
    min_ncc: float,
) -> tuple[np.ndarray, int]:
    """The hypothesis with the most confident agreeing blocks on a coarse level (the
    finest whose longest side is at most 256, not finer than ``fine``), corrected by them,
    and the level to refine from next.  AlignmentError when fewer than 4 blocks agree."""
    ic = _hypothesis_level(levels, fine)
    lv = levels[ic]
    search = max(8, round(0.1 * lv.side))
    best: Blocks | None = None
    for k, Hr in enumerate(hypotheses):
        b = _gradient_estimate(
            lv, Hr, ref_shape, block=_COARSE_BLOCK_PX, search=search, sigma=1.0,
            min_ncc=min_ncc, tol=1.5, iterations=1,
        )
        log.debug("gradient hypothesis %d: %s", k, None if b is None else b.n_agree)
        if b is not None and (best is None or b.n_agree > best.n_agree):
            best = b
    if best is None or best.n_agree < 4:
        n = 0 if best is None else best.n_agree
        raise AlignmentError(
            f"no consistent gradient structure: {n} confident blocks agree at "
            f"{lv.ref.shape[1]}x{lv.ref.shape[0]} px"
        )
    return best.H, ic - 1


def _hypothesis_level(levels: list[Level], fine: int) -> int:
    """The level of the rotation hypotheses' search: the finest whose longest side is at
    most 256, not finer than ``fine``."""
    ic = next((i for i, lv in enumerate(levels) if lv.side <= 256), len(levels) - 1)
    return max(ic, fine)


def rotation(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

