"""Result records returned by the library (plain dataclasses, JSON-ready via ``to_dict``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .grid import PoseGrid, mean_source_points

__all__ = ["MotionEstimate", "CropChoice", "ChangeResult"]


@dataclass
class MotionEstimate:
    """Camera motion estimated by eq. 5 (or eq. 3 without occlusion).

    Attributes
    ----------
    weights : ndarray, shape ``grid.shape``
        Non-negative pose weights.
    grid : PoseGrid
        The grid the weights live on.
    chi : list of ndarray
        The change (occlusion) term of each estimation window, either sign, same shape as the
        window of the observation (``(h, w)`` or ``(h, w, C)``).
    boxes : list of tuple
        The estimation windows ``(y0, x0, h, w)`` in observation coordinates.
    info : dict
        Convergence information: ``objective`` history, ``n_outer``, ``converged``,
        ``time_s``, ``n_active``, ``psnr`` of the fit on the windows, ...
    excluded : list of ndarray
        Per window, the ``(h, w)`` pixels left out of the fit as a known change (the
        observation's ``exclude``); empty when none were.
    """

    weights: np.ndarray
    grid: PoseGrid
    chi: list[np.ndarray] = field(default_factory=list)
    boxes: list[tuple[int, int, int, int]] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)
    excluded: list[np.ndarray] = field(default_factory=list)

    def nonzero_poses(self, rtol: float = 0.0) -> list[dict[str, float]]:
        """Poses carrying weight, heaviest first: dicts with tx, ty, tz, rx, ry, rz, weight."""
        out = []
        for b, iy, ix, w in self.grid.nonzero(self.weights, rtol):
            tz, rx, ry, rz = self.grid.bases[b]
            out.append(
                dict(tx=self.grid.tx[ix], ty=self.grid.ty[iy], tz=tz, rx=rx, ry=ry, rz=rz, weight=w)
            )
        return sorted(out, key=lambda d: -d["weight"])

    def source_points(self, xy: np.ndarray, base: np.ndarray | None = None) -> np.ndarray:
        """Where the model says observation points come from in the reference.

        The weighted mean over the poses of ``(H_pose @ base)^-1 xy``: the centroid of the
        blur kernel at each point, with the weights normalised to sum to 1 (a gain the
        weights carry does not move it).  Compared with the true kernel centroid (e.g.
        :func:`reblur.testbed.true_centroid`) it measures the geometry's residual.

        Parameters
        ----------
        xy : (n, 2) array_like
            Observation points ``(x, y)``.
        base : (3, 3) ndarray, optional
            The alignment composed before every pose (:attr:`ChangeResult.alignment`).

        Returns
        -------
        (n, 2) ndarray
            Reference points ``(x, y)``.
        """
        base = np.eye(3) if base is None else np.asarray(base, float)
        poses = self.grid.nonzero(self.weights)
        return mean_source_points([self.grid.homography((b, iy, ix)) @ base
                                   for b, iy, ix, _ in poses], [w for *_, w in poses], xy)


@dataclass
class CropChoice:
    """The estimation window(s) chosen by sub-image selection (Algorithm 1 and its extension).

    Attributes
    ----------
    boxes : list of (y0, x0, h, w)
        Accepted windows, observation coordinates.
    size : int
        Side ``S`` of the accepted window(s) in pixels.
    m1 : float
        Mean kernel-similarity measure of the initial ``beta`` crops.
    threshold : float
        ``T_m = ratio * m1``.
    tried : list of dict
        Every crop tried: ``box``, ``size``, ``m`` (measure), ``accepted``, ``reason``.
    space_invariant : bool
        True when no crop up to ``S_max`` passed and one kernel was used.
    """

    boxes: list[tuple[int, int, int, int]]
    size: int
    m1: float = float("nan")
    threshold: float = float("nan")
    tried: list[dict[str, Any]] = field(default_factory=list)
    space_invariant: bool = False


@dataclass
class ChangeResult:
    """Everything :func:`reblur.detect_changes` found.

    Attributes
    ----------
    change : (H, W) bool ndarray
        Change mask in the observation frame (never True where ``unknown``).
    unknown : (H, W) bool ndarray
        Observation pixels the (aligned) reference does not cover.
    reblurred : ndarray
        The aligned, reblurred reference in the observation frame, float32, same band
        count as the observation, photometrically matched to it.
    motion : MotionEstimate
        Pose weights with their grid (relative to ``alignment``).
    alignment : (3, 3) ndarray
        Coarse reference -> observation homography; the pose grid acts after it.
    crop : CropChoice
        The chosen estimation window(s) and the measures that chose them.
    threshold : float
        Decision threshold used (in the units of the decision statistic, see ``decision``).
    decision : dict
        Details of the decision (statistic, noise estimate, photometric model, clean-up).
    timings : dict
        Seconds per stage.
    regions : list of dict
        Connected change regions: ``label``, ``area``, ``bbox`` (y0, x0, y1, x1), ``centroid``.
    field : reblur.align.field.DisplacementField or None
        Local residual displacement applied after ``alignment`` and the poses (parallax,
        lens distortion): the model of observation pixel ``p`` is the reblurred reference
        at ``p + field(p)``; None when the homography alone fits.
    """

    change: np.ndarray
    unknown: np.ndarray
    reblurred: np.ndarray | None
    motion: MotionEstimate
    alignment: np.ndarray
    crop: CropChoice
    threshold: float
    decision: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    regions: list[dict[str, Any]] = field(default_factory=list)
    field: Any = None
