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
    blocks_side : int
        Longest side, in pixels, of the overview level the gradient blocks verified ``H``
        on (0 when they were not used): coarser than the working level's when the finer
        level's blocks did not agree (:func:`reblur.align.blocks.gradient_align`).
    overviews : dict or None
        Where each image's overviews came from: ``{"reference": ..., "observation":
        ...}``, each ``{"source": "file levels", "file": ..., "level": ...}`` (the
        file's own reduced-resolution levels) or ``{"source": "block means of the full
        image"}`` (see :meth:`~reblur.align.OverviewCache.overview_source`).
    shake_px : float or None
        The shake extent of this result (:func:`coarse_align`'s ``shake_px``).
    polishes : tuple of dict
        Every kernel polish run for this result, in order: ``of`` (the estimate it
        polished, e.g. ``"features+gradient"``), ``regions`` (its regions counted by
        outcome: ``fit``, ``invalid``, ``flat``, ``faint``, ``misfit``, ``spread``; see
        :data:`reblur.align.polish.REASONS`) and ``outcome`` (``kept``, ``verified, not
        kept: ...`` or ``refused: ...``).
    content_misfit : bool
        True when ``H`` has no ``kernel`` stage because the polish's blur model did not fit
        the CONTENT (:func:`reblur.align.polish.content_misfit`: most failing regions
        explain little of their texture, rather than a blur larger than ``shake_px``): a
        larger shake extent would not help, and :func:`reblur.pipeline.align_coarse`
        tries none.
    extents : tuple of dict or None
        Set by :func:`reblur.pipeline.align_coarse`: the shake extents it tried, in order,
        each ``{"shake_px", "method"}`` (or ``"refused"``: the reason), ``"polishes"`` and
        ``"content_misfit"`` (None from :func:`coarse_align` itself).
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
    blocks_side: int = 0
    overviews: dict | None = None
    shake_px: float | None = None
    polishes: tuple[dict, ...] = ()
    content_misfit: bool = False
    extents: tuple[dict, ...] | None = None

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
            "blocks_side": int(self.blocks_side),
            **({} if self.overviews is None else {"overviews": self.overviews}),
            "shake_px": None if self.shake_px is None else float(self.shake_px),
            "polishes": [dict(p) for p in self.polishes],
            "content_misfit": bool(self.content_misfit),
            **({} if self.extents is None else {"extents": [dict(e) for e in self.extents]}),
        }

