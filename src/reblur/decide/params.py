"""Parameters of the change decision (:class:`DecisionParams`): the statistic's window and
the region-level decision.  Pixel sizes (``smooth=2``, ``open_radius=3``, ``min_area=100``,
``close_radius=8``) suit imagery where the objects of interest are at least ~10 x 10 px;
scale them with the ground resolution (``close_radius=8`` fills bays up to 16 px wide;
docs/NOTES.md, fifth stop, for its effect and the radii tried).  The shape limits are
generic: L- or T-shaped objects have solidity 0.7-0.9, branching networks 0.1-0.5
(``min_solidity=0.65`` lies between, on the flat part of the measured curve: 0.6 and 0.7
give the same Jaccard on the development pairs, 0.75 loses 0.03); ``max_aspect=8`` rejects
strips.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from .tolerance import ModelTolerance


@dataclass(frozen=True)
class DecisionParams:
    """Parameters of the statistic and of the region-level decision.

    Attributes
    ----------
    smooth : float
        Standard deviation (pixels) of the Gaussian window of the local RMS statistic;
        0 for none.
    truncate : float
        Gaussian window radius in units of ``smooth``.
    open_radius : int
        Radius of the disc of the opening at each level (0 for none).
    min_area : int
        Smallest region kept, in pixels.
    strong_factor : float
        A region must contain a pixel with ``S >= strong_factor * threshold``.
    levels : tuple of float
        Threshold multipliers of the component tree, increasing, starting at 1.
    min_solidity : float
        Smallest area / convex-hull area of an accepted region.
    max_aspect : float
        Largest ``area / (2 r_in)^2`` of an accepted region (``r_in``: inscribed radius).
    boundary_fraction : float
        Accepted regions are trimmed to ``S >= boundary_fraction * median(S in region)``
        (0: no trimming).  ``S`` is an RMS, so ``1/sqrt(2)`` is the half-energy contour,
        which lies on the edge of a sharp step; about 0.5 suits edges blurred over more
        than the statistic's window: the observation is blurred, so a change's edge is a
        ramp over the blur's extent and its half-amplitude contour (the truth convention
        of a blurred change) lies at half the inside value.
    close_radius : int
        Radius of the disc with which each accepted region is closed (on its own, so
        neighbouring regions never merge) before the hole filling: bays narrower than
        ``2 close_radius`` that open to the outside are filled.  0 for none.
    max_hole_area : int
        Largest enclosed hole filled, in pixels (0: no filling).
    region_tests : bool
        False skips the shape tests and the component tree (one level, area and
        hysteresis only): the pixel-level decision, for comparison.
    shift_tolerance : float
        Misregistration (pixels, at most 1) the statistic tolerates: the observation is
        compared with every value the reblurred reference takes under such a shift
        (:mod:`reblur.decide.tolerance`).  Used as given where nothing calibrates it
        (:func:`decide`, :func:`decide_tile`, or an empty ``tolerance_ladder``);
        :func:`reblur.detect_changes` measures the tolerance instead.  The default,
        0.25 px, is the geometry's error on the independent test bed.
    contrast_tolerance : float
        Relative accuracy of the blur model: the tolerance interval is widened by this
        fraction of the local range of the reference (over ``contrast_radius``); used
        as given like ``shift_tolerance``.
    contrast_radius : int
        Radius (pixels) of the disc of the local range.
    tolerance_ladder : tuple of (shift, contrast)
        Tolerances tried in order, tight to loose, by the calibration on the estimation
        windows (:mod:`reblur.decide.calibrate`): the first at which their unchanged
        pixels stay under ``min_threshold`` but for ``calibration_target`` of them
        replaces ``shift_tolerance`` and ``contrast_tolerance``.  Its top, (1 px, 0.08),
        keeps a change of 10 % of the local range above the tolerance even where the
        range is that of the change's own surroundings.  Empty: no calibration.
    calibration_target : float
        Fraction of the windows' unchanged pixels allowed above ``min_threshold``.
    calibration_margin : int
        Rungs taken beyond the first that meets the target: the windows show the model's
        error where the texture fits best, and elsewhere it can be larger (a roll and a
        perspective viewpoint grow it towards the corners).  The hard-geometry rows of
        ``benchmarks/realism.py`` are the check: at most 0.02 % false alarms with two.
    geometry_reach : int
        Largest per-pixel geometric reach the tiles pass to the statistic (the local
        displacement field's uncertainty, :mod:`reblur.decide.tolerance`); set by the
        pipeline from the field, 0 without one.  It enters :attr:`pixel_reach`, hence the
        halo.
    edge_test_shift, edge_test_contrast : float
        The loose tolerance of the edge-artefact test: a region that is not object-like
        (a strip, a branching network) is kept when it persists under this tolerance (a
        shift of up to ``edge_test_shift`` px and ``edge_test_contrast`` of the local range,
        or the calibrated tolerance where that is looser): an edge artefact of residual
        misregistration or blur-model error vanishes under a sub-pixel shift of the
        reblurred reference, a thin real change (a new road, a wall) does not.
    edge_test_fraction : float
        Share of a region's pixels that must stay above the threshold under the loose
        tolerance (and one above the strong threshold) for it to persist; 0 turns the test
        off (every region that is not object-like is dropped, as before).
    illumination : {"auto", "global", "field"}
        Photometric model between the reblurred reference and the observation
        (:func:`reblur.decide.fit_photometry`): one gain and offset per band, a smooth
        (quadratic) gain and offset field for ramps, vignetting and shadow gradients, or
        ``"auto"``: the field where it explains the data markedly better (its inlier
        residual scale at most 0.85 of the global model's), recorded in the report.
    min_threshold : float
        Lower bound of the estimated threshold, in units of the statistic (an RMS of
        noise z-scores over ``4 pi smooth^2`` pixels: 1 for pure noise, whose 1e-6 tail
        lies near 1.5).  With the tolerance on, the bulk of the statistic is mostly 0 on
        clean data, and a threshold fitted to its spread alone would fall into the noise.
    """

    smooth: float = 2.0
    truncate: float = 4.0
    open_radius: int = 3
    min_area: int = 100
    strong_factor: float = 2.0
    levels: tuple[float, ...] = (1.0, 1.25, 1.5, 2.0, 2.5, 3.0)
    min_solidity: float = 0.65
    max_aspect: float = 8.0
    boundary_fraction: float = 0.6
    close_radius: int = 8
    max_hole_area: int = 1024
    region_tests: bool = True
    shift_tolerance: float = 0.25
    contrast_tolerance: float = 0.0
    contrast_radius: int = 3
    illumination: str = "auto"
    edge_test_shift: float = 1.0
    edge_test_contrast: float = 0.08
    edge_test_fraction: float = 0.5
    min_threshold: float = 2.0
    tolerance_ladder: tuple[tuple[float, float], ...] = (
        (0.25, 0.0), (0.5, 0.02), (0.5, 0.03), (1.0, 0.03), (1.0, 0.05), (1.0, 0.08))
    calibration_target: float = 2e-4
    calibration_margin: int = 2
    geometry_reach: int = 0

    def __post_init__(self):
        for f in dataclasses.fields(self):  # no NaN / inf setting: NaN passes every `<` test
            v = getattr(self, f.name)
            if isinstance(v, float) and not math.isfinite(v):
                raise ValueError(f"DecisionParams.{f.name} must be a finite number, got {v}")
        lv = tuple(float(v) for v in self.levels)
        object.__setattr__(self, "levels", lv)
        lad = tuple((float(a), float(b)) for a, b in self.tolerance_ladder)
        object.__setattr__(self, "tolerance_ladder", lad)
        for a, b in lad:  # each rung must be a valid tolerance
            ModelTolerance(shift=a, contrast=b, radius=int(self.contrast_radius))
        if int(self.calibration_margin) < 0:
            raise ValueError(f"calibration_margin must be >= 0, got {self.calibration_margin}")
        if not 0.0 <= self.calibration_target < 1.0:
            raise ValueError(f"calibration_target must lie in [0, 1), got "
                             f"{self.calibration_target}")
        if not lv or lv[0] != 1.0 or any(b <= a for a, b in zip(lv, lv[1:], strict=False)):
            raise ValueError(f"levels must increase from 1.0, got {self.levels}")
        if self.smooth < 0 or self.truncate <= 0:
            raise ValueError("smooth must be >= 0 and truncate > 0")
        if min(self.open_radius, self.min_area, self.max_hole_area, self.close_radius) < 0:
            raise ValueError("open_radius, min_area, close_radius and max_hole_area must be >= 0")
        if self.strong_factor < 1.0:
            raise ValueError(f"strong_factor must be >= 1, got {self.strong_factor}")
        if not 0.0 <= self.boundary_fraction < 1.0:
            raise ValueError(f"boundary_fraction must lie in [0, 1), got {self.boundary_fraction}")
        if not 0.0 <= self.min_solidity <= 1.0 or self.max_aspect < 1.0:
            raise ValueError("min_solidity must lie in [0, 1] and max_aspect be >= 1")
        if not self.min_threshold >= 0.0:
            raise ValueError(f"min_threshold must be >= 0, got {self.min_threshold}")
        _ = self.tolerance  # validates shift_tolerance, contrast_tolerance, contrast_radius
        _ = self.loose_tolerance  # validates the edge test's tolerance
        if self.illumination not in ("auto", "global", "field"):
            raise ValueError(f"illumination must be 'auto', 'global' or 'field', got "
                             f"{self.illumination!r}")
        if not 0 <= int(self.geometry_reach) <= 8:
            raise ValueError(f"geometry_reach must lie in [0, 8] px, got {self.geometry_reach}")
        if not 0.0 <= self.edge_test_fraction <= 1.0:
            raise ValueError(f"edge_test_fraction must lie in [0, 1], got "
                             f"{self.edge_test_fraction}")

    @property
    def tolerance(self) -> ModelTolerance:
        """The model's tolerance of the statistic (:mod:`reblur.decide.tolerance`)."""
        return ModelTolerance(shift=float(self.shift_tolerance),
                              contrast=float(self.contrast_tolerance),
                              radius=int(self.contrast_radius))

    @property
    def loose_tolerance(self) -> ModelTolerance:
        """The tolerance of the edge-artefact test: the looser of ``edge_test_*`` and the
        statistic's own, per component."""
        return ModelTolerance(shift=max(float(self.edge_test_shift), float(self.shift_tolerance)),
                              contrast=max(float(self.edge_test_contrast),
                                           float(self.contrast_tolerance)),
                              radius=int(self.contrast_radius))

    @property
    def ladder(self) -> list[ModelTolerance]:
        """The rungs of ``tolerance_ladder`` as tolerances."""
        return [ModelTolerance(shift=a, contrast=b, radius=int(self.contrast_radius))
                for a, b in self.tolerance_ladder]

    @property
    def pixel_reach(self) -> int:
        """How far the per-pixel residual looks: the 3 x 3 stencils of the model error and
        the tolerance interval."""
        return max([1, self.tolerance.reach, self.loose_tolerance.reach]
                   + [t.reach for t in self.ladder]) + int(self.geometry_reach)

    @property
    def smooth_radius(self) -> int:
        """Radius of the statistic's Gaussian window (as scipy.ndimage truncates it)."""
        return int(self.truncate * self.smooth + 0.5) if self.smooth > 0 else 0

    @property
    def local_radius(self) -> int:
        """Reach of the pixel-local steps: statistic window + per-pixel residual + opening
        (2 r) + 1."""
        return self.smooth_radius + self.pixel_reach + 2 * int(self.open_radius) + 1

    def halo(self, max_region_extent: int = 256) -> int:
        """Tile halo for exact tiled results with regions reaching ``max_region_extent`` px."""
        return self.local_radius + int(max_region_extent)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["levels"] = list(self.levels)
        d["tolerance_ladder"] = [list(r) for r in self.tolerance_ladder]
        return d


def _params(params: DecisionParams | None, overrides: dict[str, Any]) -> DecisionParams:
    p = params if params is not None else DecisionParams()
    if overrides:
        names = {f.name for f in dataclasses.fields(DecisionParams)}
        bad = sorted(set(overrides) - names)
        if bad:
            raise TypeError(f"unknown decision parameter(s) {bad}; known: {sorted(names)}")
        p = dataclasses.replace(p, **overrides)
    return p

