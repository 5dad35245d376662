"""Outlines of the strongest change regions, traced from the mask inside each region's box.

A region's 8-connected component lies inside its bounding box, so labelling the box alone
finds it whole: the component whose box is the whole window and whose pixel count is the
region's area.  Boxes larger than ``max_side`` on a side are shrunk by an integer factor
first (block maximum, read in bands of rows), and the outline is then that of the largest
component at that scale (marked ``approximate``).  Outlines follow pixel edges, simplified
(topology-preserving) by half a pixel of the scale traced at, more when a region would need
more than ``max_vertices`` vertices.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["region_outline", "region_records", "REGION_KEYS"]

#: Region attributes the viewer shows (those a record has).
REGION_KEYS = ("rank", "label", "score", "polarity", "area", "area_m2", "mean_contrast",
               "contrast", "difference", "mean_stat", "max_stat", "bbox", "centroid")


class _Window:
    """``mask[y0:y1, x0:x1]`` as an array-like (``reblur.report.downscale`` reads it)."""

    def __init__(self, mask: Any, bbox: tuple[int, int, int, int]):
        self.mask = mask
        self.y0, self.x0, y1, x1 = bbox
        self.shape = (y1 - self.y0, x1 - self.x0)
        self.dtype = np.dtype(np.uint8)

    def __getitem__(self, key) -> np.ndarray:
        ys, xs = key if isinstance(key, tuple) else (key, slice(None))
        ys = slice(*ys.indices(self.shape[0])) if isinstance(ys, slice) else ys
        xs = slice(*xs.indices(self.shape[1])) if isinstance(xs, slice) else xs
        win = self.mask[self.y0 + ys.start:self.y0 + ys.stop, self.x0 + xs.start:self.x0 + xs.stop]
        return np.asarray(win, dtype=bool).astype(np.uint8)


def _component(m: np.ndarray, area: int | None) -> tuple[np.ndarray, bool]:
    """The region's component of the box ``m`` (exact), else the largest one."""
    import cv2

    n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8, ltype=cv2.CV_32S)
    if n < 2:
        return np.zeros_like(m, dtype=bool), False
    h, w = m.shape
    for i in range(1, n):
        x, y, cw, ch, a = (int(v) for v in stats[i])
        if (x, y, cw, ch) == (0, 0, w, h) and (area is None or a == area):
            return lab == i, True
    return lab == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA])), False


def region_outline(mask: Any, bbox: tuple[int, int, int, int], area: int | None = None, *,
                   max_side: int = 2048, max_vertices: int = 200
                   ) -> tuple[list[list[list[float]]], bool]:
    """The outline of one region as rings of ``[x, y]`` image coordinates (pixel edges).

    Parameters
    ----------
    mask : (H, W) bool array-like
        The change mask (numpy or lazy; read only inside ``bbox``).
    bbox : (y0, x0, y1, x1)
        The region's bounding box.
    area : int, optional
        Its pixel count (picks its component when the box holds pieces of others).
    max_side : int
        Boxes longer than this are traced at a coarser scale.
    max_vertices : int
        Most vertices of an outline (the simplification grows until it fits).

    Returns
    -------
    rings : list
        Exterior and hole rings of its polygon(s), each a list of ``[x, y]``.
    exact : bool
        False when the box was shrunk or the component not found by box and area.
    """
    from affine import Affine
    from rasterio import features
    from shapely.geometry import shape

    from ..report import downscale

    y0, x0, y1, x1 = (int(v) for v in bbox)
    view = _Window(mask, (y0, x0, y1, x1))
    s = max(1, -(-max(view.shape) // max_side))
    m = np.ascontiguousarray(downscale(view, max_side, "max")) if s > 1 else view[:, :]
    comp, exact = _component(m.astype(np.uint8), area if s == 1 else None)
    if not comp.any():
        return [], False
    tr = Affine(s, 0, x0, 0, s, y0)
    polys = [shape(g) for g, _ in features.shapes(comp.astype(np.uint8), mask=comp,
                                                   connectivity=8, transform=tr)]
    rings = []
    for poly in polys:
        tol = 0.5 * s
        simple = poly.simplify(tol, preserve_topology=True)
        while _n_vertices(simple) > max_vertices and tol < max(view.shape):
            tol *= 2
            simple = poly.simplify(tol, preserve_topology=True)
        for ring in [simple.exterior, *simple.interiors]:
            rings.append([[round(float(x), 2), round(float(y), 2)] for x, y in ring.coords])
    return rings, exact and s == 1


def _n_vertices(poly) -> int:
    return len(poly.exterior.coords) + sum(len(r.coords) for r in poly.interiors)


def region_records(mask: Any, regions: list[dict[str, Any]], *, max_regions: int,
                   max_side: int = 2048, max_vertices: int = 200) -> list[dict[str, Any]]:
    """The first ``max_regions`` regions (the report's triage order) with their outlines.

    Each record holds ``id`` (1 = first: the region's ``rank``, and its ``id`` in
    ``changes.geojson``), the attributes of :data:`REGION_KEYS` it has,
    ``outline`` (rings, :func:`region_outline`) and ``exact``.
    """
    out = []
    for k, r in enumerate(regions[:max_regions], 1):
        rec: dict[str, Any] = {"id": k}
        rec.update({key: r[key] for key in REGION_KEYS if key in r})
        if "bbox" in r:
            rec["outline"], rec["exact"] = region_outline(
                mask, r["bbox"], r.get("area"), max_side=max_side, max_vertices=max_vertices)
        else:
            rec["outline"], rec["exact"] = [], False
        out.append(rec)
    return out
