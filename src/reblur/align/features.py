"""SIFT features on one overview level, a ratio test and a robust homography."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..grid import map_points
from .overviews import Level, overview_matrix, to_full
from .params import AlignParams
from .result import AlignmentError


def _to_u8(a: np.ndarray) -> np.ndarray:
    lo, hi = np.percentile(a, [0.5, 99.5])
    if hi <= lo:
        hi = lo + 1e-12
    return np.clip((a - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)


@dataclass
class Features:
    H: np.ndarray  # full resolution
    src: np.ndarray  # inlier reference points, full resolution
    dst: np.ndarray  # inlier observation points, full resolution
    n_matches: int
    n_inliers: int


def match_features(level: Level, params: AlignParams) -> Features:
    """SIFT + ratio test + robust homography on one level; raise AlignmentError on failure.

    Reads ``n_features``, ``ratio``, ``ransac_px``, ``min_inliers`` and
    ``min_inlier_ratio`` of ``params``."""
    src, dst = _matches(level, params)
    n, min_inliers = len(src), params.min_inliers
    Hs, inl = _robust_fit(src, dst, params)
    ni = int(inl.sum())
    if ni < min_inliers:
        raise AlignmentError(
            f"too few feature inliers ({ni} < {min_inliers} of {n} matches) between reference "
            "and observation"
        )
    if ni < params.min_inlier_ratio * n:
        raise AlignmentError(
            f"feature matches are inconsistent: {ni} inliers of {n} matches "
            f"(< {100 * params.min_inlier_ratio:.0f} %)"
        )
    A = overview_matrix(level.scale)
    return Features(
        H=to_full(np.asarray(Hs, float), level.scale),
        src=map_points(A, src[inl]),
        dst=map_points(A, dst[inl]),
        n_matches=n,
        n_inliers=ni,
    )


def _matches(level: Level, params: AlignParams) -> tuple[np.ndarray, np.ndarray]:
    """SIFT matches (level pixels) that pass the ratio test, one per observation point (the
    closest); AlignmentError when there are fewer than ``params.min_inliers``."""
    min_inliers = params.min_inliers
    sift = cv2.SIFT_create(nfeatures=params.n_features)

    def reference_features():
        return cv2.SIFT_create(nfeatures=params.n_features).detectAndCompute(
            _to_u8(level.ref), None)

    # the reference's keypoints and descriptors depend on its level alone: a cache of the
    # reference's products (one reference, many observations) computes them once
    kr, dr = (reference_features() if level.ref_memo is None
              else level.ref_memo(("sift", params.n_features), reference_features))
    ko, do = sift.detectAndCompute(_to_u8(level.obs), None)
    nk = min(len(kr), len(ko))
    if dr is None or do is None or nk < min_inliers:
        raise AlignmentError(
            f"images are textureless: only {nk} feature points found (< {min_inliers})"
        )
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(dr, do, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < params.ratio * p[1].distance]
    best: dict[int, cv2.DMatch] = {}
    for mt in good:
        if mt.trainIdx not in best or mt.distance < best[mt.trainIdx].distance:
            best[mt.trainIdx] = mt
    good = list(best.values())
    if len(good) < min_inliers:
        raise AlignmentError(
            f"too few feature matches ({len(good)} < {min_inliers}) between reference and "
            "observation"
        )
    src = np.float64([kr[mt.queryIdx].pt for mt in good])
    dst = np.float64([ko[mt.trainIdx].pt for mt in good])
    return src, dst


def _robust_fit(src: np.ndarray, dst: np.ndarray,
                params: AlignParams) -> tuple[np.ndarray, np.ndarray]:
    """Robust homography (MAGSAC, with at least three times ``min_inliers`` matches) or,
    failing that, a 4-dof similarity (RANSAC): ``(Hs, inlier mask)`` in level pixels."""
    n, min_inliers, ransac_px = len(src), params.min_inliers, params.ransac_px
    Hs, mask = None, None
    if n >= 3 * min_inliers:
        Hs, mask = cv2.findHomography(
            src, dst, cv2.USAC_MAGSAC, ransac_px, maxIters=20000, confidence=0.9999
        )
    if Hs is None or mask is None or int(mask.sum()) < min_inliers:
        A, mask = cv2.estimateAffinePartial2D(
            src, dst, method=cv2.RANSAC, ransacReprojThreshold=ransac_px, maxIters=20000,
            confidence=0.9999,
        )
        Hs = None if A is None else np.vstack([A, [0.0, 0.0, 1.0]])
    if Hs is None or mask is None:
        raise AlignmentError(
            f"no consistent transform among {n} feature matches between reference and observation"
        )
    return Hs, mask.ravel().astype(bool)
