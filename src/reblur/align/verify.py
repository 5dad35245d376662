"""Checks of an alignment: plausibility of a homography, correlation under it, texture.

An estimate that folds or mirrors the reference, zooms or stretches it beyond the limits,
or leaves too little overlap raises :class:`~reblur.align.AlignmentError` -- never silent
garbage.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from ..grid import map_points
from .overviews import Level, to_level
from .params import AlignParams
from .result import AlignmentError


def _quad_area(q: np.ndarray) -> float:
    x, y = q[:, 0], q[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def corners(shape: tuple[int, int]) -> np.ndarray:
    h, w = shape
    return np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], dtype=float)


def check_plausible(
    H: np.ndarray,
    ref_shape: tuple[int, int],
    obs_shape: tuple[int, int],
    *,
    max_zoom: float,
    max_anisotropy: float,
    min_overlap: float,
) -> float:
    """Raise AlignmentError unless ``H`` is a plausible viewpoint change; return the overlap."""
    if not np.all(np.isfinite(H)) or abs(np.linalg.det(H)) < 1e-12:
        raise AlignmentError("degenerate estimate: singular or non-finite homography")
    rc = corners(ref_shape)
    wz = rc @ H[2, :2] + H[2, 2]
    if np.any(wz <= 1e-6 * np.abs(H[2, 2])):
        raise AlignmentError(
            "degenerate estimate: the reference crosses the horizon of the homography"
        )
    q = map_points(H, rc)
    # every turn of the mapped quadrilateral must keep the reference's orientation
    e = np.roll(q, -1, axis=0) - q
    turns = e[:, 0] * np.roll(e, -1, axis=0)[:, 1] - e[:, 1] * np.roll(e, -1, axis=0)[:, 0]
    if np.any(turns <= 0):
        raise AlignmentError("degenerate estimate: the mapped reference is folded or mirrored")
    zoom = math.sqrt(_quad_area(q) / _quad_area(rc))
    if not 1.0 / max_zoom <= zoom <= max_zoom:
        raise AlignmentError(
            f"implausible estimate: zoom {zoom:.4g} outside [{1.0 / max_zoom:.4g}, "
            f"{max_zoom:g}] ([align] max_zoom in a --config file)"
        )
    # local anisotropy at the four corners and the centre (Jacobian singular values)
    pts = np.vstack([rc, rc.mean(axis=0)])
    for x, y in pts:
        wv = H[2, 0] * x + H[2, 1] * y + H[2, 2]
        u = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / wv
        v = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / wv
        J = (H[:2, :2] - np.outer([u, v], H[2, :2])) / wv
        s = np.linalg.svd(J, compute_uv=False)
        if s[1] <= 0 or s[0] / s[1] > max_anisotropy:
            raise AlignmentError(
                f"implausible estimate: local stretch ratio {s[0] / max(s[1], 1e-12):.3g} "
                f"exceeds {max_anisotropy:g}"
            )
    oc = corners(obs_shape)
    inter, _ = cv2.intersectConvexConvex(q.astype(np.float32), oc.astype(np.float32))
    overlap = float(inter) / _quad_area(oc) if _quad_area(oc) > 0 else 0.0
    if overlap < min_overlap:
        raise AlignmentError(
            f"implausible estimate: the mapped reference covers {100 * overlap:.1f} % of the "
            f"observation (< {100 * min_overlap:.0f} %)"
        )
    return overlap


def intensity_spread(a: np.ndarray) -> float:
    lo, hi = np.percentile(a, [1.0, 99.0])
    return float(hi - lo)



def max_corner_shift(H1: np.ndarray, H2: np.ndarray, shape: tuple[int, int]) -> float:
    c = corners(shape)
    return float(np.max(np.hypot(*(map_points(H1, c) - map_points(H2, c)).T)))



def correlation(level: Level, H: np.ndarray, sigma: float) -> float:
    """Correlation of the smoothed reference and observation under ``H`` on one level."""
    Hs = to_level(H, level.scale)
    h, w = level.ref.shape
    ref = cv2.GaussianBlur(level.ref, (0, 0), sigma)
    obs = cv2.GaussianBlur(level.obs, (0, 0), sigma)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    back = cv2.warpPerspective(obs, Hs, (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT)
    cover = cv2.warpPerspective(
        level.obs_mask.astype(np.float32), Hs, (w, h), flags=flags,
        borderMode=cv2.BORDER_CONSTANT,
    )
    r = int(math.ceil(3 * sigma)) + 1
    m = ((cover > 0.999) & level.ref_mask.astype(bool)).astype(np.uint8)
    m = cv2.erode(m, np.ones((2 * r + 1, 2 * r + 1), np.uint8)).astype(bool)
    if m.sum() < 64:
        return float("nan")
    a = ref[m].astype(np.float64)
    b = back[m].astype(np.float64)
    a -= a.mean()
    b -= b.mean()
    den = math.sqrt(float(a @ a) * float(b @ b))
    return float(a @ b) / den if den > 0 else float("nan")



def check_textured(name: str, a: np.ndarray) -> None:
    """Raise AlignmentError when the overview ``a`` of the image ``name`` is (nearly)
    constant."""
    tol = 1e-4 * max(1.0, float(np.max(np.abs(a))))
    if intensity_spread(a) <= tol:
        raise AlignmentError(f"images are textureless: the {name} is (nearly) constant")


def check_regions(n_agree: int, n_fit: int, spread: float, n_total: int, params: AlignParams,
                  shake_px: float) -> None:
    """Raise AlignmentError unless enough kernel-polish regions agree with the estimate:
    at least 8, ``params.min_regions`` of the ``n_total`` regions and ``params.min_agree``
    of the ``n_fit`` where the blur model fits, spread over ``params.min_spread`` of the
    region grid."""
    need = max(8, math.ceil(params.min_regions * n_total), math.ceil(params.min_agree * n_fit))
    if n_agree >= need and spread < params.min_spread:
        raise AlignmentError(
            f"could not be verified: the {n_agree} regions that agree with it "
            f"span {100 * spread:.0f} % of the image (< {100 * params.min_spread:.0f} %)"
        )
    if n_agree < need:
        raise AlignmentError(
            f"could not be verified: {n_agree} regions agree with it, of "
            f"{n_fit} where the blur model fits and {n_total} in all (need {need}): images "
            f"unrelated, changed too much or blurred by more than shake_px={shake_px:g}"
        )


def check_blocks(n_agree: int, n_confident: int, n_blocks: int, spread: float,
                 params: AlignParams) -> None:
    """Raise AlignmentError unless enough confident gradient blocks agree with the
    estimate: at least ``params.min_blocks`` and ``params.min_agree`` of the
    ``n_confident``, spread over ``params.min_spread`` of the block grid."""
    need = max(params.min_blocks, math.ceil(params.min_agree * n_confident))
    if n_agree < need:
        raise AlignmentError(
            f"could not be verified: {n_agree} gradient blocks agree with it, "
            f"of {n_confident} confident and {n_blocks} in all (need {need}): "
            "images unrelated, changed too much or not one plane (parallax)"
        )
    if spread < params.min_spread:
        raise AlignmentError(
            f"could not be verified: the {n_agree} gradient blocks that agree "
            f"with it span {100 * spread:.0f} % of the image (< {100 * params.min_spread:.0f} %)"
        )


def check_near_hint(H: np.ndarray, hint: np.ndarray, ref_shape: tuple[int, int],
                    reach: float) -> None:
    """Raise AlignmentError when ``H`` moves a reference corner farther than ``reach``
    times the reference's diagonal from where ``hint`` puts it."""
    limit = reach * math.hypot(*ref_shape)
    moved = max_corner_shift(H, hint, ref_shape)
    if not moved <= limit:
        raise AlignmentError(
            f"the estimate puts the reference corners {moved:.0f} px from the hint's "
            f"(> {limit:.0f} px, hint_reach={reach:g})"
        )


def refusal(reasons: Sequence[tuple[str, str]], shake_px: float, *,
            hinted: bool) -> AlignmentError:
    """The one-line refusal of an alignment: each stage that failed with its measured
    evidence (``reasons``: ``(stage, reason)`` in the order tried, repeats dropped), then
    the options that would let the user go on.  A failed kernel polish (the blur model did
    not fit) also suggests a larger shake extent than ``shake_px``; a refusal despite a
    hint (``hinted``) asks for a closer one."""
    parts = [f"({stage}): {reason}" for stage, reason in dict.fromkeys(reasons)]
    if hinted:
        hint = ("a closer --align-hint FILE (hint=; within a few degrees and tens of pixels "
                "of the reference -> observation homography)")
    else:
        hint = ("--align-hint FILE (hint=: a rough reference -> observation homography in "
                "full-resolution pixels)")
    go_on = (f"to go on: {hint}, georeferenced inputs, or --no-align (align=False) if the "
             "images are already registered")
    if any(stage == "kernel polish" for stage, _ in reasons):
        go_on += (f"; if the blur spans more than {shake_px:g} px, a larger shake extent "
                  f"(shake_px={max(8.0, 2.0 * shake_px):g})")
    return AlignmentError(f"alignment {'; fallback '.join(parts)} -- {go_on}")
