"""A georeferenced prior for the alignment: the homography two GeoTIFFs' metadata imply.

When both the reference and the observation carry a coordinate reference system (CRS) and an
affine geotransform, the mapping from reference pixels to observation pixels is known before
looking at a single pixel value.  :func:`geo_homography` turns it into a homography in
reblur's convention (:mod:`reblur.grid`: full-resolution pixel coordinates ``(x, y)`` =
(column, row) with pixel centres on integers, ``x_obs ~ H @ [x_ref, y_ref, 1]``).

A rasterio geotransform maps pixel CORNER coordinates ``(col, row)`` to map coordinates, so
the centre of pixel ``(c, r)`` lies at ``transform * (c + 0.5, r + 0.5)``.  With
``S = T(0.5, 0.5)`` the pixel-centre mapping is

* same CRS: ``H = S^-1 @ A_obs^-1 @ A_ref @ S`` exactly (an affine map);
* different CRSs: reference pixel centres on an ``n x n`` grid over the part of the reference
  that the observation covers -> map coordinates (reference transform) -> observation CRS
  (``rasterio.warp.transform``, i.e. PROJ) -> observation pixels (inverse observation
  transform) -> a least-squares homography (normalised DLT, ``cv2.findHomography`` method 0).
  A change of map projection is not exactly a homography; the fit residual (max and RMS over
  the grid, in observation pixels) says by how much, and is the prior's stated uncertainty.

The prior is a SEED for the image-based alignment, never a replacement for it: metadata can
be wrong (a shifted orthophoto, a datum error, a mislabelled CRS), and the images themselves
decide the final homography.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

__all__ = ["GeoPrior", "geo_homography", "image_prior"]

#: Points per edge of the densified footprint outlines used for the overlap.
_OUTLINE_PTS = 64


@dataclass(frozen=True, eq=False)
class GeoPrior:
    """Reference -> observation homography implied by two images' georeferencing.

    Attributes
    ----------
    H : (3, 3) ndarray of float64
        Reference -> observation homography in full-resolution pixel coordinates (pixel
        centres on integers), normalised so that ``H[2, 2] == 1``.  Read-only.
    residual_max : float
        Largest distance, in observation pixels, between ``H`` and the exact reprojection
        over the fit grid (0 when both images share one CRS: the map is then exactly affine).
    residual_rms : float
        Root mean square of the same distances.
    overlap : float
        Fraction of the observation's area covered by the reference's footprint.
    method : str
        ``"affine"`` (same CRS, exact) or ``"fit"`` (least squares over reprojected points).
    ref_crs, obs_crs : str
        The two CRSs, as ``CRS.to_string()``.
    n_points : int
        Points in the fit (0 for ``"affine"``).
    """

    H: np.ndarray
    residual_max: float
    residual_rms: float
    overlap: float
    method: str
    ref_crs: str
    obs_crs: str
    n_points: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description for the run report."""
        return dict(
            H=[[float(v) for v in row] for row in self.H],
            residual_max_px=float(self.residual_max),
            residual_rms_px=float(self.residual_rms),
            overlap=float(self.overlap),
            method=self.method,
            ref_crs=self.ref_crs,
            obs_crs=self.obs_crs,
            n_points=int(self.n_points),
        )


def geo_homography(
    ref_geo: dict[str, Any] | None,
    ref_shape: tuple[int, ...],
    obs_geo: dict[str, Any] | None,
    obs_shape: tuple[int, ...],
    *,
    n: int = 21,
) -> GeoPrior:
    """Homography from reference to observation pixels implied by their georeferencing.

    Parameters
    ----------
    ref_geo, obs_geo : dict
        Georeferencing as :attr:`reblur.io.Image.geo`: ``crs`` (``rasterio.crs.CRS`` or
        anything ``CRS.from_user_input`` accepts) and ``transform`` (``affine.Affine``,
        pixel corner -> map coordinates).
    ref_shape, obs_shape : tuple of int
        Image shapes ``(rows, cols[, bands])`` at full resolution.
    n : int
        Fit grid points per side (``n * n`` points; at least 3) when the CRSs differ.

    Returns
    -------
    GeoPrior

    Raises
    ------
    ValueError
        If a side lacks a CRS or a transform, a transform is singular or not finite, the
        footprints do not overlap (the message gives both bounds in the observation's CRS),
        or the reprojection over the overlap is not a usable homography (more than a tenth of
        the fit points outside the projection's domain, or a fit that folds the overlap over
        the horizon).  Fewer unmappable points are skipped.

    Notes
    -----
    Rotated and sheared geotransforms are supported: they remain affine maps.  Only a
    singular transform (zero area per pixel) makes the mapping degenerate.
    """
    if int(n) < 3:
        raise ValueError(f"n must be at least 3 (fit grid points per side), got {n}")
    ref_crs, ref_a = _parse_geo(ref_geo, "reference")
    obs_crs, obs_a = _parse_geo(obs_geo, "observation")
    ref_hw, obs_hw = _shape_hw(ref_shape, "ref_shape"), _shape_hw(obs_shape, "obs_shape")
    names = (ref_crs.to_string(), obs_crs.to_string())
    if ref_crs == obs_crs:
        S = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
        H = np.linalg.inv(S) @ np.linalg.inv(obs_a) @ ref_a @ S
        overlap = _overlap(_apply(H, _rect_outline(ref_hw)), _rect_polygon(obs_hw))
        if overlap <= 0.0:
            raise _disjoint(ref_crs, ref_a, ref_hw, obs_crs, obs_a, obs_hw)
        return _prior(H / H[2, 2], 0.0, 0.0, overlap, "affine", names, 0)
    overlap = _overlap(_pixels_to_pixels(_rect_outline(ref_hw), ref_a, ref_crs, obs_a, obs_crs),
                       _rect_polygon(obs_hw))
    if overlap <= 0.0:
        raise _disjoint(ref_crs, ref_a, ref_hw, obs_crs, obs_a, obs_hw)
    back = _pixels_to_pixels(_rect_outline(obs_hw), obs_a, obs_crs, ref_a, ref_crs)
    src = _fit_grid(back, ref_hw, int(n))
    dst = _pixels_to_pixels(src, ref_a, ref_crs, obs_a, obs_crs)
    H, rmax, rrms, n_used = _fit(src, dst, names)
    return _prior(H, rmax, rrms, overlap, "fit", names, n_used)


def _fit(src: np.ndarray, dst: np.ndarray, names: tuple[str, str]):
    """``(H, max, RMS residual, points used)`` of the least-squares fit ``src -> dst``,
    skipping points PROJ could not map (refused when they are more than a tenth)."""
    ok = np.isfinite(dst).all(axis=1)
    if ok.sum() < 0.9 * len(src):
        raise ValueError(
            f"cannot reproject the overlap from {names[0]} to {names[1]}: "
            f"{len(src) - int(ok.sum())} of {len(src)} points fall outside the projection's "
            "domain; reproject one image into the other's CRS first (e.g. gdalwarp)"
        )
    src, dst = src[ok], dst[ok]
    H = _fit_homography(src, dst)
    _check_not_folded(H, src, names)
    err = np.hypot(*(_apply(H, src) - dst).T)
    return H, float(err.max()), float(np.sqrt(np.mean(err**2))), len(src)


def _prior(H, rmax, rrms, overlap, method, names, n_points) -> GeoPrior:
    H = np.array(H, dtype=np.float64)
    H.setflags(write=False)
    return GeoPrior(H=H, residual_max=rmax, residual_rms=rrms, overlap=float(overlap),
                    method=method, ref_crs=names[0], obs_crs=names[1], n_points=int(n_points))


def _parse_geo(geo: dict[str, Any] | None, side: str) -> tuple[Any, np.ndarray]:
    """``(CRS, 3x3 transform matrix)`` of one side, or a ValueError naming what is missing."""
    from rasterio.crs import CRS

    hint = ("write it as a GeoTIFF with a CRS and a geotransform, or align from pixels "
            "alone (no georeferenced prior)")
    if not geo:
        raise ValueError(f"the {side} is not georeferenced; {hint}")
    if geo.get("crs") is None:
        raise ValueError(f"the {side} has a geotransform but no CRS; {hint}")
    if geo.get("transform") is None:
        raise ValueError(f"the {side} has a CRS but no geotransform; {hint}")
    crs = CRS.from_user_input(geo["crs"])
    t = geo["transform"]
    A = np.array([[t.a, t.b, t.c], [t.d, t.e, t.f], [0.0, 0.0, 1.0]], dtype=np.float64)
    det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
    scale = float(np.sum(A[:2, :2] ** 2))
    if not np.isfinite(A).all() or scale == 0.0 or abs(det) <= 1e-12 * scale:
        raise ValueError(
            f"the {side}'s geotransform {tuple(float(v) for v in A[:2].ravel())} is "
            "degenerate (its rows are collinear: a pixel covers no area); fix the file's "
            "georeferencing"
        )
    return crs, A


def _shape_hw(shape: tuple[int, ...], name: str) -> tuple[int, int]:
    if len(shape) < 2 or int(shape[0]) < 1 or int(shape[1]) < 1:
        raise ValueError(f"{name} must be (rows, cols[, bands]) with positive sizes, got {shape}")
    return int(shape[0]), int(shape[1])


def _rect_outline(hw: tuple[int, int], k: int = _OUTLINE_PTS) -> np.ndarray:
    """Closed outline of an image's area (pixel-centre coordinates, edges at -0.5), ``k``
    points per edge, clockwise on screen from the top-left corner."""
    h, w = hw
    xs, ys = np.linspace(-0.5, w - 0.5, k + 1), np.linspace(-0.5, h - 0.5, k + 1)
    top = np.stack([xs[:-1], np.full(k, -0.5)], axis=1)
    right = np.stack([np.full(k, w - 0.5), ys[:-1]], axis=1)
    bottom = np.stack([xs[::-1][:-1], np.full(k, h - 0.5)], axis=1)
    left = np.stack([np.full(k, -0.5), ys[::-1][:-1]], axis=1)
    return np.concatenate([top, right, bottom, left])


def _rect_polygon(hw: tuple[int, int]):
    import shapely

    h, w = hw
    return shapely.box(-0.5, -0.5, w - 0.5, h - 0.5)


def _valid_polygon(pts: np.ndarray):
    """A valid shapely geometry from a (possibly self-intersecting) outline."""
    import shapely

    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < 3:
        return shapely.Polygon()
    return shapely.make_valid(shapely.Polygon(pts))


def _overlap(outline: np.ndarray, rect) -> float:
    """Fraction of ``rect``'s area inside the polygon ``outline``."""
    return float(_valid_polygon(outline).intersection(rect).area / rect.area)


def _apply(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    q = pts @ H[:, :2].T + H[:, 2]
    return q[:, :2] / q[:, 2:]


def _pixels_to_pixels(pts, src_a, src_crs, dst_a, dst_crs) -> np.ndarray:
    """Pixel centres of one raster -> (fractional) pixel centres of another, through map
    coordinates and, when the CRSs differ, PROJ.  Points PROJ cannot map come back
    non-finite."""
    m = (pts + 0.5) @ src_a[:2, :2].T + src_a[:2, 2]
    if src_crs != dst_crs:
        m = _reproject_points(m, src_crs, dst_crs)
    inv = np.linalg.inv(dst_a)
    with np.errstate(invalid="ignore"):  # unmappable points stay NaN
        return m @ inv[:2, :2].T + inv[:2, 2] - 0.5


def _reproject_points(m: np.ndarray, src_crs, dst_crs) -> np.ndarray:
    """Map coordinates from one CRS to another; NaN where PROJ cannot map a point (GDAL
    fails the whole call then, so the points are retried one at a time)."""
    from rasterio.warp import transform

    def run(pts: np.ndarray) -> np.ndarray:
        xs, ys = transform(src_crs, dst_crs, pts[:, 0], pts[:, 1])
        return np.stack([np.asarray(xs, dtype=np.float64), np.asarray(ys, dtype=np.float64)],
                        axis=1)

    try:
        return run(m)
    except Exception:  # noqa: BLE001 - GDAL's CPLE errors are not public classes
        out = np.full_like(m, np.nan)
        for i in range(len(m)):
            try:
                out[i] = run(m[i : i + 1])[0]
            except Exception:  # noqa: BLE001, S112 - an unmappable point stays NaN
                continue
        return out


def _fit_grid(back_outline: np.ndarray, ref_hw: tuple[int, int], n: int) -> np.ndarray:
    """``n x n`` reference pixel centres spanning the part of the reference the observation
    covers (its bounding box; the whole reference when the outline cannot be mapped)."""
    ref_rect = _rect_polygon(ref_hw)
    inter = _valid_polygon(back_outline).intersection(ref_rect)
    x0, y0, x1, y1 = (inter if inter.area > 0 else ref_rect).bounds
    x0, y0 = max(x0, 0.0), max(y0, 0.0)
    x1, y1 = min(x1, ref_hw[1] - 1.0), min(y1, ref_hw[0] - 1.0)
    if x1 - x0 < 1.0 or y1 - y0 < 1.0:  # a sliver: fit on a pixel-wide patch around it
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        x0, x1, y0, y1 = cx - 0.5, cx + 0.5, cy - 0.5, cy + 0.5
    gx, gy = np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n))
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def _normaliser(pts: np.ndarray) -> np.ndarray:
    """Hartley's similarity: centroid to the origin, mean distance sqrt(2)."""
    c = pts.mean(axis=0)
    d = float(np.mean(np.hypot(*(pts - c).T)))
    s = np.sqrt(2.0) / d if d > 0 else 1.0
    return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])


def _fit_homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares homography ``src -> dst`` on normalised coordinates."""
    Ts, Td = _normaliser(src), _normaliser(dst)
    Hn, _ = cv2.findHomography(_apply(Ts, src), _apply(Td, dst), 0)
    if Hn is None or not np.isfinite(Hn).all():
        raise ValueError("the reprojected points fit no homography (degenerate georeferencing)")
    H = np.linalg.inv(Td) @ Hn @ Ts
    return H / H[2, 2]


def _check_not_folded(H: np.ndarray, src: np.ndarray, names: tuple[str, str]) -> None:
    """The fit must keep every grid point in front of the horizon, with one orientation."""
    w = src @ H[2, :2] + H[2, 2]
    jac = np.linalg.det(H) / w**3
    if not (np.all(w > 0) and (np.all(jac > 0) or np.all(jac < 0))):
        raise ValueError(
            f"the mapping from {names[0]} to {names[1]} over the overlap is not a usable "
            "homography (it folds over the horizon); reproject one image into the other's "
            "CRS first"
        )


def _disjoint(ref_crs, ref_a, ref_hw, obs_crs, obs_a, obs_hw) -> ValueError:
    """The error for footprints that do not overlap, with both bounds in the obs CRS."""
    from rasterio.warp import transform_bounds

    def bounds(a: np.ndarray, hw: tuple[int, int]) -> tuple[float, ...]:
        h, w = hw
        corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], dtype=np.float64)
        m = corners @ a[:2, :2].T + a[:2, 2]
        return (*m.min(axis=0), *m.max(axis=0))

    ref_b = bounds(ref_a, ref_hw)
    if ref_crs != obs_crs:
        ref_b = transform_bounds(ref_crs, obs_crs, *ref_b, densify_pts=21)
    fmt = ", ".join
    return ValueError(
        "the georeferenced footprints do not overlap: reference bounds "
        f"({fmt(f'{v:.3f}' for v in ref_b)}) and observation bounds "
        f"({fmt(f'{v:.3f}' for v in bounds(obs_a, obs_hw))}) as (left, bottom, right, top) in "
        f"{obs_crs.to_string()}; check that both files show the same area and carry the right "
        "CRS, or drop the georeferencing to align from pixels alone"
    )


def image_prior(reference: Any, observed: Any, *, n: int = 21) -> GeoPrior | None:
    """The georeferenced prior of two opened images, or None unless both are georeferenced.

    Parameters
    ----------
    reference, observed : reblur.io.Image
        Opened inputs; their ``geo`` (CRS and transform of a GeoTIFF) and ``shape``.
    n : int
        Fit points per side (:func:`geo_homography`).

    Returns
    -------
    GeoPrior or None
        None when either image has no CRS or no transform (pixels alone decide then).

    Raises
    ------
    ValueError
        Both are georeferenced but their footprints do not overlap, or the mapping is
        degenerate (the message says which, with the bounds).
    """
    geos = [getattr(im, "geo", None) or {} for im in (reference, observed)]
    if not all(g.get("crs") is not None and g.get("transform") is not None for g in geos):
        return None
    return geo_homography(geos[0], tuple(reference.shape), geos[1], tuple(observed.shape), n=n)
