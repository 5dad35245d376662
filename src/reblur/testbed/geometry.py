"""Geometry one homography per pose cannot represent: lens distortion and two-plane parallax.

Two departures from the planar pinhole world of :mod:`reblur.testbed.camera`, rendered by
the test bed's own code (:func:`reblur.testbed.render.render_window` takes a
:class:`SceneGeometry` wherever it takes homographies):

* **Lens distortion** of the observation camera, Brown's radial model about the principal
  point: the observation pixel ``p`` sees the ideal (undistorted) image point
  ``u(p) = c + (p - c) (1 + k1 rho^2 + k2 rho^4)``, ``rho = |p - c| / f``, which then goes
  through the sub-pose homographies as before: it samples the reference at
  ``H_k^{-1} u(p)``.  :meth:`Lens.from_corner_px` solves ``k1`` for a stated displacement
  at the image corners: ``corner_px > 0`` is barrel distortion (a corner pixel sees the
  scene ``corner_px`` farther from the centre than an ideal lens would: the content is
  squeezed towards the centre), ``corner_px < 0`` pincushion.
* **A second scene plane** (a "roof", or with ``s < 1`` a "pit") over a polygon of the
  reference, parallel to the ground plane at ``1 / s`` of its distance.  Under the camera's
  translation it moves differently from the ground: each plane has its own plane-induced
  homography ``K (R + s t n^T) K^-1`` per sub-pose (:func:`region_homographies`, from the
  viewpoint's parts and the shake poses of :mod:`reblur.testbed.camera`).  Occlusion rule:
  the observation pixel sees the NEARER plane where the nearer plane's mapping of it lands
  inside the nearer plane's region (the polygon for a roof, its complement for a pit), and
  the farther plane otherwise; decided per sub-pose, so an occlusion edge moving during
  the exposure blurs as it should.

Truth (:meth:`SceneGeometry.centroid`): the exposure-averaged reference position an
observation point samples; :func:`best_homography` and :func:`homography_residual` give the
part of it no single homography explains; :meth:`SceneGeometry.occlusion_window` the
observation pixels at the parallax's occlusion edges (where the sub-poses disagree on the
plane, or a plane is seen that the reference hides).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares

from .camera import CameraPath, compose, intrinsics, translation
from .render import (
    COORD_STEPS,
    Box,
    _apply,
    _check_box,
    _check_homographies,
    _inverses,
    _quantised_maps,
    _scaled_positions,
    source_extent,
)

__all__ = [
    "Lens",
    "Region",
    "SceneGeometry",
    "best_homography",
    "homography_residual",
    "region_homographies",
    "roof_polygon",
]


@dataclass(frozen=True)
class Lens:
    """Radial (Brown) distortion of the observation camera about its principal point.

    Attributes
    ----------
    k1, k2 : float
        Coefficients of ``rho^2`` and ``rho^4``, ``rho`` the distance from the principal
        point in focal lengths.
    centre : tuple of float
        Principal point ``(cx, cy)`` in observation pixels.
    focal : float
        Focal length in pixels.
    """

    k1: float
    k2: float
    centre: tuple[float, float]
    focal: float

    @classmethod
    def from_corner_px(cls, shape: tuple[int, ...], corner_px: float, k2: float = 0.0,
                       focal: float | None = None) -> Lens:
        """The lens that moves the image corners by ``corner_px`` pixels.

        The principal point and focal length are :func:`~reblur.testbed.camera.intrinsics`'
        for ``shape``; the corner is the pixel centre ``(0, 0)`` (all four are equally far
        from the centre).  ``k1`` is solved with ``k2`` held.

        Parameters
        ----------
        shape : tuple of int
            Observation shape ``(H, W[, C])``.
        corner_px : float
            Displacement of the corners, pixels: > 0 barrel (the corner sees the scene
            farther out), < 0 pincushion, 0 no distortion.
        k2 : float
            Fourth-order coefficient.
        focal : float, optional
            Focal length in pixels; default :func:`~reblur.testbed.camera.default_focal`.

        Returns
        -------
        Lens
        """
        k = intrinsics(shape, focal)
        if not np.isfinite(corner_px) or not np.isfinite(k2):
            raise ValueError(f"corner_px and k2 must be finite, got {corner_px!r}, {k2!r}")
        f, cx, cy = float(k[0, 0]), float(k[0, 2]), float(k[1, 2])
        r = float(np.hypot(cx, cy))
        rho2 = (r / f) ** 2
        k1 = (float(corner_px) / r - float(k2) * rho2 ** 2) / rho2
        lens = cls(k1=float(k1), k2=float(k2), centre=(cx, cy), focal=f)
        lens.check(r)
        return lens

    def check(self, radius: float) -> None:
        """Refuse a lens whose radial map folds over within ``radius`` pixels of the centre
        (``d/dr [r (1 + k1 rho^2 + k2 rho^4)] <= 0`` somewhere): it is not a lens."""
        rho2 = (np.linspace(0.0, radius, 2049) / self.focal) ** 2
        if np.any(1 + 3 * self.k1 * rho2 + 5 * self.k2 * rho2 ** 2 <= 0):
            raise ValueError(f"k1={self.k1:.4g}, k2={self.k2:.4g} fold the image over within "
                             f"{radius:.0f} px of the centre: ask for a smaller corner_px")

    def undistort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The ideal image point ``u(p)`` an observation pixel ``p = (x, y)`` sees."""
        cx, cy = self.centre
        dx, dy = x - cx, y - cy
        rho2 = (dx * dx + dy * dy) / (self.focal * self.focal)
        gain = 1.0 + rho2 * (self.k1 + self.k2 * rho2)
        return cx + dx * gain, cy + dy * gain

    def max_shift(self) -> float:
        """Largest ``|u(p) - p|`` over the image (whose corners are as far from the centre
        as the principal point is from the pixel ``(0, 0)``), pixels."""
        r = np.linspace(0.0, float(np.hypot(*self.centre)), 4097)
        rho2 = (r / self.focal) ** 2
        return float(np.max(np.abs(r * rho2 * (self.k1 + self.k2 * rho2))))

    def to_dict(self) -> dict:
        """JSON-able description."""
        return {"k1": self.k1, "k2": self.k2, "centre": list(self.centre), "focal": self.focal}


@dataclass(frozen=True)
class Region:
    """A second scene plane over a polygon of the reference.

    Attributes
    ----------
    polygon : numpy.ndarray
        ``(n, 2)`` vertices ``(x, y)`` in reference pixels (a simple polygon; even-odd rule).
    scale : float
        ``s``: the ground plane's distance over this plane's (> 1 nearer, a roof; < 1
        farther, a pit; 1 the ground itself).
    parallax_px : float
        The displacement between the planes the viewpoint change gives, pixels (signed as
        ``s - 1``): ``(s - 1) |shift|`` of :func:`~reblur.testbed.camera.viewpoint_parts`.
    """

    polygon: np.ndarray
    scale: float
    parallax_px: float = 0.0

    def __post_init__(self) -> None:
        poly = np.asarray(self.polygon, dtype=np.float64)
        if poly.ndim != 2 or poly.shape[1] != 2 or len(poly) < 3 or not np.isfinite(poly).all():
            raise ValueError("polygon must be (n, 2) finite vertices (x, y) with n >= 3")
        if not np.isfinite(self.scale) or self.scale <= 0:
            raise ValueError(f"scale must be a positive distance ratio, got {self.scale!r}")
        object.__setattr__(self, "polygon", poly)

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Whether reference points ``(x, y)`` lie inside the polygon (even-odd rule)."""
        inside = np.zeros(np.broadcast(x, y).shape, dtype=bool)
        p = self.polygon
        for (x1, y1), (x2, y2) in zip(p, np.roll(p, -1, axis=0), strict=True):
            if y1 == y2:
                continue
            crosses = (y1 > y) != (y2 > y)
            inside ^= crosses & (x < x1 + (y - y1) * (x2 - x1) / (y2 - y1))
        return inside

    def to_dict(self) -> dict:
        """JSON-able description."""
        return {"polygon": self.polygon.tolist(), "scale": self.scale,
                "parallax_px": self.parallax_px}


def roof_polygon(shape: tuple[int, ...], rng: np.random.Generator,
                 area: tuple[float, float] = (0.12, 0.2)) -> np.ndarray:
    """A random "roof": a rotated rectangle of ``area`` (fractions of the image), kept a
    tenth of the image away from the edges (centred on an axis where it cannot be)."""
    h, w = int(shape[0]), int(shape[1])
    frac = rng.uniform(*area)
    aspect = rng.uniform(0.6, 1.6)
    a = np.sqrt(frac * h * w * aspect) / 2.0
    b = np.sqrt(frac * h * w / aspect) / 2.0
    ang = rng.uniform(0.0, np.pi)
    c, s = np.cos(ang), np.sin(ang)
    corners = np.array([[-a, -b], [a, -b], [a, b], [-a, b]]) @ np.array([[c, s], [-s, c]])
    reach = np.abs(corners).max(axis=0)
    lo, hi = reach + 0.1 * np.array([w, h]), np.array([w - 1, h - 1]) - reach - 0.1 * np.array(
        [w, h])
    centre = np.where(hi > lo, rng.uniform(np.minimum(lo, hi), np.maximum(lo, hi)),
                      [(w - 1) / 2, (h - 1) / 2])
    return corners + centre


def region_homographies(path: CameraPath, turn: np.ndarray, shift: np.ndarray,
                        scale: float) -> np.ndarray:
    """Sub-pose homographies of a plane at ``1 / scale`` of the ground plane's distance.

    The ground's are ``compose(translation(*shift) @ turn, path.homographies())``
    (:func:`~reblur.testbed.camera.viewpoint_parts`); the plane-induced homography
    ``K (R + t n^T / d) K^-1`` of a parallel plane at ``d / s`` scales every translation
    ``t`` by ``s``: the view's shift becomes ``s * shift`` and each shake pose
    ``(tx, ty, tz, rx, ry, rz)`` becomes ``(s tx, s ty, s tz, rx, ry, rz)`` (the shake's
    plane is fronto-parallel to the nominal observation camera: the view's plane seen from
    there).  With ``scale == 1`` the result equals the ground's bit for bit.

    Returns
    -------
    numpy.ndarray
        ``(n_sub, 3, 3)`` reference -> observation homographies.
    """
    s = float(scale)
    poses = np.asarray(path.poses, dtype=np.float64) * np.array([s, s, s, 1.0, 1.0, 1.0])
    shakes = CameraPath(poses=poses, shape=path.shape, focal=path.focal).homographies()
    near = np.asarray(shift, dtype=np.float64) * (s - 1.0)
    view = translation(*near) @ (translation(*shift) @ np.asarray(turn, dtype=np.float64))
    return compose(view / view[2, 2], shakes)


class SceneGeometry:
    """Where each sub-pose of the exposure takes an observation pixel in the reference.

    Sub-pose ``k`` maps the observation pixel ``p`` to ``H_k^{-1} u(p)`` on the ground
    plane, or ``G_k^{-1} u(p)`` on the region's plane when the occlusion rule (module
    docstring) says the region's plane is seen; ``u`` is the lens (identity without one).

    Parameters
    ----------
    homographies : numpy.ndarray
        ``(n, 3, 3)`` ground-plane reference -> observation homographies (``H_k @ H_view``).
    lens : Lens, optional
        Distortion of the observation camera.
    region : Region, optional
        The second plane.
    region_homographies : numpy.ndarray, optional
        ``(n, 3, 3)`` its homographies (:func:`region_homographies`); required with
        ``region``.
    """

    def __init__(self, homographies: np.ndarray, *, lens: Lens | None = None,
                 region: Region | None = None,
                 region_homographies: np.ndarray | None = None) -> None:
        self.homographies = _check_homographies(homographies)
        self.n = len(self.homographies)
        self.inv = _inverses(self.homographies)
        self.lens, self.region = lens, region
        self.region_inv = None
        if (region is None) != (region_homographies is None):
            raise ValueError("give region and region_homographies together")
        if region is not None:
            rh = _check_homographies(region_homographies)
            if rh.shape != self.homographies.shape:
                raise ValueError("region_homographies must have one homography per sub-pose")
            self.region_homographies = rh
            self.region_inv = _inverses(rh)
            # ideal-frame box beyond which no sub-pose of either plane reaches the polygon
            px, py = region.polygon[:, 0], region.polygon[:, 1]
            pts = np.concatenate([np.stack(_apply(h, px, py), axis=1)
                                  for h in np.concatenate([self.homographies, rh])])
            self._reach = (*(pts.min(axis=0) - 1.0), *(pts.max(axis=0) + 1.0))

    # ------------------------------------------------------------ sample positions
    def _ideal(self, xs: np.ndarray, ys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (xs, ys) if self.lens is None else self.lens.undistort(xs, ys)

    def _scaled(self, k: int, xs: np.ndarray, ys: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Sub-pose ``k``'s positions of ideal points, times ``COORD_STEPS``; with a region,
        also whether the region's plane is seen and whether a hidden point is seen (both
        decided only near the polygon: elsewhere neither plane's mapping reaches it)."""
        qx, qy = _scaled_positions(self.inv[k], xs, ys)
        if self.region is None:
            return qx, qy, None, None
        xs, ys = np.broadcast_arrays(xs, ys)
        qx, qy = np.broadcast_to(qx, xs.shape).copy(), np.broadcast_to(qy, xs.shape).copy()
        x0, y0, x1, y1 = self._reach
        near = (xs >= x0) & (xs <= x1) & (ys >= y0) & (ys <= y1)
        seen, hidden = np.zeros(qx.shape, dtype=bool), np.zeros(qx.shape, dtype=bool)
        if not near.any():
            return qx, qy, seen, hidden
        rx, ry = _scaled_positions(self.region_inv[k], xs[near], ys[near])
        gx, gy = qx[near], qy[near]
        step = 1.0 / COORD_STEPS
        if self.region.scale >= 1.0:  # the region is nearer: seen where it lands inside
            s = self.region.contains(rx * step, ry * step)
            h = ~s & self.region.contains(gx * step, gy * step)
        else:  # the ground is nearer: seen where it lands outside the polygon
            s = self.region.contains(gx * step, gy * step)
            h = s & ~self.region.contains(rx * step, ry * step)
        seen[near], hidden[near] = s, h
        qx[near], qy[near] = np.where(s, rx, gx), np.where(s, ry, gy)
        return qx, qy, seen, hidden

    def sources(self, xy_obs: np.ndarray) -> np.ndarray:
        """Every sub-pose's reference position of observation points.

        Parameters
        ----------
        xy_obs : numpy.ndarray
            ``(m, 2)`` observation points ``(x, y)`` (any float coordinates).

        Returns
        -------
        numpy.ndarray
            ``(n_sub, m, 2)`` reference points.
        """
        pts = _check_points(xy_obs)
        xs, ys = self._ideal(pts[:, 0], pts[:, 1])
        out = np.empty((self.n, len(pts), 2))
        for k in range(self.n):
            qx, qy, _, _ = self._scaled(k, xs, ys)
            out[k, :, 0], out[k, :, 1] = qx / COORD_STEPS, qy / COORD_STEPS
        return out

    def centroid(self, xy_obs: np.ndarray) -> np.ndarray:
        """The exposure-averaged reference position observation points sample (the blur
        kernel's centroid; :func:`~reblur.testbed.render.true_centroid` generalised).

        Parameters
        ----------
        xy_obs : numpy.ndarray
            ``(m, 2)`` observation points ``(x, y)``.

        Returns
        -------
        numpy.ndarray
            ``(m, 2)`` reference points ``mean_k source_k(p)``.
        """
        return self.sources(xy_obs).mean(axis=0)

    def sample_maps(self, k: int, box: Box, sbox: Box) -> tuple[np.ndarray, np.ndarray]:
        """Sub-pose ``k``'s remap maps of an observation window, relative to ``sbox``,
        rounded as :func:`reblur.testbed.render.render_window` rounds (exact across
        windows)."""
        xs, ys = self._ideal(*_grid(box, broadcast=self.lens is None))
        qx, qy, _, _ = self._scaled(k, xs, ys)
        qx, qy = np.broadcast_arrays(qx, qy)
        return _quantised_maps(qx, qy, sbox)

    # ------------------------------------------------------------ windows and masks
    def _all_inverses(self) -> np.ndarray:
        return self.inv if self.region_inv is None else np.concatenate([self.inv,
                                                                        self.region_inv])

    def source_box(self, box: Box, ref_shape: tuple[int, ...], margin: int = 4) -> Box | None:
        """Reference region a window samples (every border pixel of the window through the
        lens and every sub-pose of both planes, grown by ``margin`` px), clipped; None
        when it samples nothing inside the reference."""
        y0, y1, x0, x1 = _check_box(box)
        bx = np.concatenate([np.arange(x0, x1), np.full(y1 - y0, x1 - 1), np.arange(x0, x1),
                             np.full(y1 - y0, x0)]).astype(np.float64)
        by = np.concatenate([np.full(x1 - x0, y0), np.arange(y0, y1), np.full(x1 - x0, y1 - 1),
                             np.arange(y0, y1)]).astype(np.float64)
        ux, uy = self._ideal(bx, by)
        pts = [np.stack(_apply(h, ux, uy)) for h in self._all_inverses()]
        xs, ys = np.concatenate([p[0] for p in pts]), np.concatenate([p[1] for p in pts])
        return source_extent(xs, ys, margin, ref_shape)

    def _masks(self, box: Box, ref_shape: tuple[int, ...] | None, shrink: float,
               ground: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Per pixel of a window: every sub-pose samples inside the reference shrunk by
        ``shrink`` (when ``ref_shape`` is given; with ``ground``, its ground-plane sample
        does); and the occlusion edge (sub-poses disagree on the plane seen, or one sees a
        point the reference hides)."""
        y0, y1, x0, x1 = _check_box(box)
        xs, ys = self._ideal(*_grid(box, broadcast=False))
        ok = np.ones((y1 - y0, x1 - x0), dtype=bool)
        first = np.zeros_like(ok)
        differs = np.zeros_like(ok)
        hidden = np.zeros_like(ok)
        for k in range(self.n):
            if ground:
                qx, qy = _scaled_positions(self.inv[k], xs, ys)
                seen = hid = None
            else:
                qx, qy, seen, hid = self._scaled(k, xs, ys)
            if ref_shape is not None:
                u, v = qx / COORD_STEPS, qy / COORD_STEPS
                ok &= ((u >= shrink) & (u <= ref_shape[1] - 1 - shrink) & (v >= shrink)
                       & (v <= ref_shape[0] - 1 - shrink))
            if seen is not None:
                if k == 0:
                    first = seen.copy()
                differs |= seen != first
                hidden |= hid
        return ok, differs | hidden

    def valid_window(self, box: Box, ref_shape: tuple[int, ...], shrink: float = 2.0
                     ) -> np.ndarray:
        """Pixels of a window whose every sub-pose samples inside the reference shrunk by
        ``shrink`` pixels (as :func:`~reblur.testbed.render.valid_window`).

        Fast path: each sub-pose's ground-plane valid set is the preimage of a convex set
        under a homography and the (monotone, radial) lens, a topological disc, which
        holds a window whose border it holds.  A pixel whose ground sample is valid is
        valid when the polygon of a second plane lies in the shrunk reference (it samples
        either the ground there or a point of the polygon); so then a window whose border
        has valid ground samples is valid throughout."""
        y0, y1, x0, x1 = _check_box(box)
        inside = True
        if self.region is not None:
            p = self.region.polygon
            inside = bool(np.all((p >= shrink) & (p <= np.array(ref_shape[1::-1][:2]) - 1
                                                  - shrink)))
        if inside and y1 - y0 > 2 and x1 - x0 > 2:
            rims = [(y0, y0 + 1, x0, x1), (y1 - 1, y1, x0, x1), (y0, y1, x0, x0 + 1),
                    (y0, y1, x1 - 1, x1)]
            if all(self._masks(r, ref_shape, shrink, ground=True)[0].all() for r in rims):
                return np.ones((y1 - y0, x1 - x0), dtype=bool)
        ok = self._masks(box, ref_shape, shrink, ground=True)[0]
        if self.region is None or (inside and not self._reaches(box, ~ok)):
            return ok
        return self._masks(box, ref_shape, shrink)[0]

    def _reaches(self, box: Box, pixels: np.ndarray) -> bool:
        """Whether any of the marked pixels of a window can see the region's plane."""
        xs, ys = self._ideal(*_grid(box, broadcast=False))
        x0, y0, x1, y1 = self._reach
        return bool(np.any(pixels & (xs >= x0) & (xs <= x1) & (ys >= y0) & (ys <= y1)))

    def occlusion_window(self, box: Box, band_px: float = 0.0) -> np.ndarray:
        """Observation pixels at the second plane's occlusion edges.

        A pixel is marked when its sub-poses do not all see the same plane, or when one of
        them sees a point of the farther plane that the nearer one hides in the reference
        (it samples the nearer plane's pixels there: the reference never saw it); then the
        mark is grown by ``band_px`` (a disc).  Empty without a region or with ``scale ==
        1`` (the planes coincide).

        Returns
        -------
        numpy.ndarray
            Boolean ``(y1 - y0, x1 - x0)``.
        """
        y0, y1, x0, x1 = _check_box(box)
        if self.region is None or self.region.scale == 1.0:
            return np.zeros((y1 - y0, x1 - x0), dtype=bool)
        if band_px < 0 or not np.isfinite(band_px):
            raise ValueError(f"band_px must be a finite number >= 0, got {band_px!r}")
        g = int(np.ceil(band_px))
        mark = self._masks((y0 - g, y1 + g, x0 - g, x1 + g), None, 0.0)[1]
        if g:
            disc = (np.hypot(*np.mgrid[-g:g + 1, -g:g + 1]) <= band_px).astype(np.uint8)
            mark = cv2.dilate(mark.astype(np.uint8), disc) > 0
        return mark[g:g + y1 - y0, g:g + x1 - x0]

    # ------------------------------------------------------------ change truth
    def change_boxes(self, objects: tuple[Any, ...]) -> list[Box]:
        """Observation boxes holding each change object under every sub-pose of both
        planes, grown by the lens' largest displacement."""
        pad = 0 if self.lens is None else int(np.ceil(self.lens.max_shift())) + 1
        hs = self.homographies if self.region is None else np.concatenate(
            [self.homographies, self.region_homographies])
        out = []
        for o in objects:
            y0, y1, x0, x1 = o.bbox
            cx = np.array([x0, x1, x0, x1], dtype=np.float64)
            cy = np.array([y0, y0, y1, y1], dtype=np.float64)
            pts = np.concatenate([np.stack(_apply(h, cx, cy)) for h in hs], axis=1)
            out.append((int(np.floor(pts[1].min())) - 1 - pad,
                        int(np.ceil(pts[1].max())) + 2 + pad,
                        int(np.floor(pts[0].min())) - 1 - pad,
                        int(np.ceil(pts[0].max())) + 2 + pad))
        return out

    def truth_window(self, objects: tuple[Any, ...], box: Box, boxes: list[Box]
                     ) -> np.ndarray:
        """Change mask of a window: ``mean_k 1[source_k(p) in an object] >= 0.5`` (as
        :func:`~reblur.testbed.scenes.truth_window`, with this geometry's sources)."""
        y0, y1, x0, x1 = _check_box(box)
        out = np.zeros((y1 - y0, x1 - x0), dtype=bool)
        near = [(o, (max(b[0], y0), min(b[1], y1), max(b[2], x0), min(b[3], x1)))
                for o, b in zip(objects, boxes, strict=True)]
        near = [(o, b) for o, b in near if b[1] > b[0] and b[3] > b[2]]
        objs = [o for o, _ in near]
        for _, (r0, r1, c0, c1) in near:
            xs, ys = self._ideal(*_grid((r0, r1, c0, c1), broadcast=False))
            count = np.zeros(xs.shape, dtype=np.int32)
            for k in range(self.n):
                qx, qy, _, _ = self._scaled(k, xs, ys)
                u, v = qx / COORD_STEPS, qy / COORD_STEPS
                count += np.logical_or.reduce([o.contains(u, v) for o in objs])
            out[r0 - y0:r1 - y0, c0 - x0:c1 - x0] |= 2 * count >= self.n
        return out

    def to_dict(self) -> dict:
        """JSON-able description (the ground homographies are the pair's own)."""
        d: dict = {}
        if self.lens is not None:
            d["lens"] = self.lens.to_dict()
        if self.region is not None:
            d["region"] = self.region.to_dict() | {
                "homographies": self.region_homographies.tolist()}
        return d


def _grid(box: Box, broadcast: bool) -> tuple[np.ndarray, np.ndarray]:
    y0, y1, x0, x1 = box
    xs = np.arange(x0, x1, dtype=np.float64)[None, :]
    ys = np.arange(y0, y1, dtype=np.float64)[:, None]
    if broadcast:
        return xs, ys
    return np.broadcast_to(xs, (y1 - y0, x1 - x0)), np.broadcast_to(ys, (y1 - y0, x1 - x0))


def _check_points(xy_obs: np.ndarray) -> np.ndarray:
    pts = np.asarray(xy_obs, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"xy_obs must be (m, 2) points (x, y), got shape {pts.shape}")
    return pts


def best_homography(geometry: SceneGeometry, xy_obs: np.ndarray) -> np.ndarray:
    """The single homography that best explains the geometry at observation points.

    Minimises the RMS distance, in reference pixels, between ``H^{-1} p`` and the true
    centroid :meth:`SceneGeometry.centroid` over the points (a direct linear fit, then
    Levenberg-Marquardt on the geometric error).  Pass the points a score counts (valid,
    off occlusion edges): it is the floor any one-homography method has there.

    Parameters
    ----------
    geometry : SceneGeometry
        The truth.
    xy_obs : numpy.ndarray
        ``(m, 2)`` observation points, m >= 4, not all on a line.

    Returns
    -------
    numpy.ndarray
        ``3 x 3`` reference -> observation homography, ``H[2, 2] == 1``.
    """
    pts = _check_points(xy_obs)
    if len(pts) < 4:
        raise ValueError("best_homography needs at least 4 observation points")
    target = geometry.centroid(pts)
    g0, _ = cv2.findHomography(pts, target, 0)
    if g0 is None:
        raise ValueError("the points do not determine a homography (collinear?)")
    g0 = g0 / g0[2, 2]

    def resid(h: np.ndarray) -> np.ndarray:
        g = np.append(h, 1.0).reshape(3, 3)
        return (np.stack(_apply(g, pts[:, 0], pts[:, 1]), axis=1) - target).ravel()

    fit = least_squares(resid, g0.ravel()[:8], method="lm")
    g = np.append(fit.x, 1.0).reshape(3, 3)
    h = np.linalg.inv(g)
    return h / h[2, 2]


def homography_residual(geometry: SceneGeometry, xy_obs: np.ndarray,
                        homography: np.ndarray) -> np.ndarray:
    """What a homography leaves of the geometry: ``centroid(p) - H^{-1} p``.

    Parameters
    ----------
    geometry : SceneGeometry
        The truth.
    xy_obs : numpy.ndarray
        ``(m, 2)`` observation points.
    homography : numpy.ndarray
        ``3 x 3`` reference -> observation homography (e.g. :func:`best_homography`).

    Returns
    -------
    numpy.ndarray
        ``(m, 2)`` displacement in reference pixels.
    """
    pts = _check_points(xy_obs)
    g = np.linalg.inv(np.asarray(homography, dtype=np.float64))
    return geometry.centroid(pts) - np.stack(_apply(g, pts[:, 0], pts[:, 1]), axis=1)
