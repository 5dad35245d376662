"""What the coarse alignment returns (:class:`Alignment`) or raises (:class:`AlignmentError`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class AlignmentError(ValueError):
    """The reference and the observation could not be aligned (reason in the message)."""


@dataclass(frozen=True)
class Alignment:
    """Result of :func:`coarse_align`.

    Attributes
    ----------
    H : (3, 3) ndarray of float64
        Reference -> observation homography in FULL-resolution pixel coordinates,
        normalised so that ``H[2, 2] == 1``.
    method : str
        The stages that produced ``H``, joined by ``+``: ``features`` or ``phase`` (the
        initial estimate), ``ecc`` (refinement) and ``kernel`` (blur-aware polish), e.g.
        ``"features+ecc+kernel"``.
    n_matches : int
        Feature matches that passed the ratio test (0 when features were not used).
    n_inliers : int
        Matches consistent with the robust feature estimate.
    scale : float
        Working downscale of the finest overview (``1 / k`` for a block factor ``k``).
    residual_px : float or None
        Median distance, in full-resolution pixels, between the inlier matches of the
        observation and the reference matches mapped by ``H`` (None without features).
    ecc : float or None
        Correlation coefficient of the pre-blurred reference and observation under ``H`` on
        the working level (None when too little overlaps to compute it).
    overlap : float
        Fraction of the observation covered by the mapped reference.
    n_regions : int
        Regions of the kernel polish that agree with ``H`` (0 when the polish did not run
        or was rejected).
    n_blocks : int
        Gradient blocks whose correlation is confident and that agree with ``H`` (0 when
        the gradient blocks were not used).
    overviews : dict or None
        Where each image's overviews came from: ``{"reference": ..., "observation":
        ...}``, each ``{"source": "file levels", "file": ..., "level": ...}`` (the
        file's own reduced-resolution levels) or ``{"source": "block means of the full
        image"}`` (see :meth:`~reblur.align.OverviewCache.overview_source`).
    """

    H: np.ndarray
    method: str
    n_matches: int
    n_inliers: int
    scale: float
    residual_px: float | None
    ecc: float | None
    overlap: float
    n_regions: int = 0
    n_blocks: int = 0
    overviews: dict | None = None

    def to_dict(self) -> dict:
        """JSON-ready description of the alignment."""
        return {
            "H": [[float(v) for v in row] for row in np.asarray(self.H)],
            "method": self.method,
            "n_matches": int(self.n_matches),
            "n_inliers": int(self.n_inliers),
            "scale": float(self.scale),
            "residual_px": None if self.residual_px is None else float(self.residual_px),
            "ecc": None if self.ecc is None else float(self.ecc),
            "overlap": float(self.overlap),
            "n_regions": int(self.n_regions),
            "n_blocks": int(self.n_blocks),
            **({} if self.overviews is None else {"overviews": self.overviews}),
        }

