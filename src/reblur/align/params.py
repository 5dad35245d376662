"""Options of the coarse alignment (:class:`AlignParams`), validated once."""

from __future__ import annotations

import math
from dataclasses import dataclass
from numbers import Integral, Real

import cv2

METHODS = ("auto", "features", "gradient", "ecc")
MOTIONS = {"homography": cv2.MOTION_HOMOGRAPHY, "affine": cv2.MOTION_AFFINE}

#: Options that are integers of at least the given value.
_INTS = {"max_side": 16, "min_side": 16, "feature_side": 1, "n_features": 1,
         "min_inliers": 4, "ecc_iterations": 1, "gradient_side": 1, "min_blocks": 1}
#: Options that are fractions in [0, 1].
_FRACTIONS = ("ratio", "min_inlier_ratio", "min_r2", "min_regions", "min_agree", "min_spread",
              "min_ecc", "min_overlap", "block_ncc", "hint_reach")
#: Options that are finite numbers of at least (strictly above, with True) the given value.
_NUMBERS = {"ransac_px": (0.0, True), "blur_px": (0.0, False), "max_zoom": (1.0, False),
            "max_anisotropy": (1.0, False)}


@dataclass(frozen=True)
class AlignParams:
    """Options of :func:`~reblur.align.coarse_align` (all but the images, the shake extent
    and the hint), validated once on construction.

    Attributes
    ----------
    max_side : int
        Longest side of the finest overview (both images share one integer block factor).
    min_side : int
        Longest side of the coarsest pyramid level (16 <= ``min_side`` <= ``max_side``).
    method : {"auto", "features", "gradient", "ecc"}
        ``"auto"``: gradient blocks (see :func:`~reblur.align.coarse_align`) seeded by the
        hint or the SIFT estimate when there is one, else by rotation hypotheses; they
        decide and verify, and the kernel polish is kept only where its blur model fits
        most regions.  If the blocks cannot verify, the SIFT estimate with ECC and the
        polish, then phase correlation (or the hint) with ECC and the polish.
        ``"gradient"``: gradient blocks from the hint or rotation hypotheses only.
        ``"features"``: SIFT, ECC and the polish only; ``"ecc"``: phase correlation (or the
        hint), ECC and the polish only.
    nodata : float or None
        Overview pixels equal to this value (whole blocks of it, after normalisation) are
        missing data, e.g. the empty corners of a reprojected scene; ECC and the polish
        ignore them.  None: every pixel holds data.
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
        Fewest feature matches (and inliers) accepted (at least 4).
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
        Apply the blur-aware kernel polish, which also verifies the result.
    min_r2 : float
        Smallest fraction of a region's variance the local blur kernel must explain for the
        region to take part in the polish.
    min_regions : float
        Smallest fraction of the polish regions (and at least 8) that must agree with the
        final homography; fewer raises :class:`~reblur.align.AlignmentError`.
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
        Largest accepted scale change (either way) between the images (at least 1).
    max_anisotropy : float
        Largest accepted ratio of the local stretches of ``H`` (at least 1).
    min_overlap : float
        Smallest accepted fraction of the observation covered by the mapped reference.
    gradient_side : int
        The gradient blocks are refined down to the finest level whose longest side is at
        most this (or the working level, if finer).
    rotations : tuple of float
        In-plane rotations (degrees) tried as hypotheses when neither a hint nor a feature
        estimate seeds the gradient blocks.
    block_ncc : float
        Correlation peak a gradient block must reach to count as confident (the peak
        between unrelated 96 px blocks stays near 0.1).
    min_blocks : int
        Fewest confident gradient blocks that must agree with the result; at least
        ``min_agree`` of the confident blocks and ``min_spread`` of the image are also
        required.
    hint_reach : float
        With a hint: how far the result may move the reference's corners from where the
        hint puts them, as a fraction of the reference's diagonal (a feature estimate
        farther away is not used).

    Examples
    --------
    >>> AlignParams(method="gradient").min_blocks
    12
    >>> AlignParams(min_agree=1.5)
    Traceback (most recent call last):
    ...
    ValueError: AlignParams.min_agree must lie in [0, 1], got 1.5
    """

    max_side: int = 1024
    min_side: int = 128
    method: str = "auto"
    nodata: float | None = 0.0
    feature_side: int = 512
    n_features: int = 5000
    ratio: float = 0.8
    ransac_px: float = 2.0
    min_inliers: int = 12
    min_inlier_ratio: float = 0.1
    refine: bool = True
    motion: str = "homography"
    blur_px: float = 8.0
    ecc_iterations: int = 100
    polish: bool = True
    min_r2: float = 0.3
    min_regions: float = 0.15
    min_agree: float = 0.6
    min_spread: float = 0.3
    min_ecc: float = 0.4
    max_zoom: float = 2.0
    max_anisotropy: float = 2.0
    min_overlap: float = 0.2
    gradient_side: int = 512
    rotations: tuple[float, ...] = (-12.0, -8.0, -4.0, 0.0, 4.0, 8.0, 12.0)
    block_ncc: float = 0.25
    min_blocks: int = 12
    hint_reach: float = 0.1

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"AlignParams.method must be one of {METHODS}, got {self.method!r}")
        if self.motion not in MOTIONS:
            raise ValueError(f"AlignParams.motion must be one of {tuple(MOTIONS)}, got "
                             f"{self.motion!r}")
        for name, low in _INTS.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, Integral) or v < low:
                raise ValueError(f"AlignParams.{name} must be an integer >= {low}, got {v!r}")
        if self.max_side < self.min_side:
            raise ValueError(f"AlignParams needs 16 <= min_side <= max_side, got min_side="
                             f"{self.min_side}, max_side={self.max_side}: lower min_side or "
                             "raise max_side")
        for name in _FRACTIONS:
            v = getattr(self, name)
            if not _real(v) or not 0.0 <= v <= 1.0:
                raise ValueError(f"AlignParams.{name} must lie in [0, 1], got {v!r}")
        for name, (low, strict) in _NUMBERS.items():
            v = getattr(self, name)
            if not _real(v) or not math.isfinite(v) or v < low or (strict and v == low):
                raise ValueError(f"AlignParams.{name} must be a finite number "
                                 f"{'>' if strict else '>='} {low:g}, got {v!r}")
        for name in ("refine", "polish"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"AlignParams.{name} must be True or False, got "
                                 f"{getattr(self, name)!r}")
        if self.nodata is not None and (not _real(self.nodata) or not math.isfinite(self.nodata)):
            raise ValueError(f"AlignParams.nodata must be a finite number or None, got "
                             f"{self.nodata!r} (overviews hold no NaN: they count as 0)")
        try:
            rotations = tuple(float(r) for r in self.rotations)
        except (TypeError, ValueError):
            rotations = ()
        if not rotations or not all(math.isfinite(r) for r in rotations):
            raise ValueError(f"AlignParams.rotations must be a non-empty sequence of finite "
                             f"angles (degrees), got {self.rotations!r}")
        object.__setattr__(self, "rotations", rotations)


def _real(v: object) -> bool:
    return isinstance(v, Real) and not isinstance(v, bool)
