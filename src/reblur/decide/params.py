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
from dataclasses import dataclass
from typing import Any


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
        than the statistic's window.
    close_radius : int
        Radius of the disc with which each accepted region is closed (on its own, so
        neighbouring regions never merge) before the hole filling: bays narrower than
        ``2 close_radius`` that open to the outside are filled.  0 for none.
    max_hole_area : int
        Largest enclosed hole filled, in pixels (0: no filling).
    region_tests : bool
        False skips the shape tests and the component tree (one level, area and
        hysteresis only): the pixel-level decision, for comparison.
    """

    smooth: float = 2.0
    truncate: float = 4.0
    open_radius: int = 3
    min_area: int = 100
    strong_factor: float = 2.0
    levels: tuple[float, ...] = (1.0, 1.25, 1.5, 2.0, 2.5, 3.0)
    min_solidity: float = 0.65
    max_aspect: float = 8.0
    boundary_fraction: float = 0.7071
    close_radius: int = 8
    max_hole_area: int = 1024
    region_tests: bool = True

    def __post_init__(self):
        lv = tuple(float(v) for v in self.levels)
        object.__setattr__(self, "levels", lv)
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

    @property
    def smooth_radius(self) -> int:
        """Radius of the statistic's Gaussian window (as scipy.ndimage truncates it)."""
        return int(self.truncate * self.smooth + 0.5) if self.smooth > 0 else 0

    @property
    def local_radius(self) -> int:
        """Reach of the pixel-local steps: statistic window + opening (2 r) + 1."""
        return self.smooth_radius + 2 * int(self.open_radius) + 2  # + 1 for the gradient

    def halo(self, max_region_extent: int = 256) -> int:
        """Tile halo for exact tiled results with regions reaching ``max_region_extent`` px."""
        return self.local_radius + int(max_region_extent)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["levels"] = list(self.levels)
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

