"""Time and memory of the GIS outputs (:mod:`reblur.gis`) on a large synthetic result.

``python -m benchmarks.gis_outputs [--megapixels 25]`` builds, in a temporary directory,
the full-size outputs of a georeferenced detection as the CLI holds them above 64 MP: the
change and unknown masks as zarr arrays and the reblurred reference (RGB, uint8) in a
:class:`reblur.gis.ReblurredStore`, all written tile by tile.  The change mask holds a few
thousand discs and bars, many across tile borders.  It then writes, one at a time,
``changes.tif`` and ``unknown.tif`` (COG, max overviews), ``reblurred.tif`` (COG, averaged
overviews), ``changes.geojson`` (polygons traced tile by tile, merged and simplified) and,
with the ``geo`` extra, ``changes.gpkg``, and prints a markdown table: seconds, the
largest growth of the resident memory over the stage (sampled every 10 ms by a thread:
what the stage held beyond what was there before it) and the file size.
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
from pathlib import Path

import numpy as np


class _Peak:
    """The largest resident memory (MB) of this process while the block runs, sampled."""

    def __init__(self, every: float = 0.01):
        import psutil

        self.proc, self.every = psutil.Process(), every

    def __enter__(self):
        self.base = self.proc.memory_info().rss
        self.top = self.base
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()
        self.t0 = time.perf_counter()
        return self

    def _run(self):
        while not self.stop.is_set():
            self.top = max(self.top, self.proc.memory_info().rss)
            time.sleep(self.every)

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self.t0
        self.stop.set()
        self.thread.join()
        self.top = max(self.top, self.proc.memory_info().rss)
        self.growth_mb = (self.top - self.base) / 2**20


def build(d: Path, side: int, tile: int = 1024, seed: int = 0):
    """The masks (zarr) and the reblurred store of a ``side`` x ``side`` result."""
    import cv2

    from reblur.gis import ReblurredStore
    from reblur.io import iter_windows, zarr_masks

    rng = np.random.default_rng(seed)
    n = side * side // 10_000
    discs = np.column_stack([rng.integers(0, side, n), rng.integers(0, side, n),
                             rng.integers(3, 40, n)])
    change, unknown = zarr_masks(d, (side, side), tile)
    rb = ReblurredStore(d / "reblurred", (side, side, 3), np.uint8, tile)
    for ys, xs in iter_windows((side, side), tile):
        h, w = ys.stop - ys.start, xs.stop - xs.start
        m = np.zeros((h, w), np.uint8)
        near = discs[(np.abs(discs[:, 0] - (ys.start + h / 2)) < h / 2 + 40)
                     & (np.abs(discs[:, 1] - (xs.start + w / 2)) < w / 2 + 40)]
        for y, x, r in near.tolist():
            cv2.circle(m, (x - xs.start, y - ys.start), r, 1, -1)
            cv2.rectangle(m, (x - xs.start, y - ys.start - 1), (x - xs.start + 3 * r,
                          y - ys.start + 1), 1, -1)
        u = np.zeros((h, w), bool)
        u[:, : max(0, 200 - xs.start)] = True
        change[ys, xs] = m.astype(bool) & ~u
        unknown[ys, xs] = u
        yy, xx = np.mgrid[ys, xs]
        base = (0.5 + 0.25 * np.sin(yy / 97.0) * np.cos(xx / 131.0)).astype(np.float32)
        noise = rng.normal(0, 0.02, (h, w, 3)).astype(np.float32)
        rb[ys, xs] = np.clip(base[:, :, None] + noise, 0, 1)
    return change, unknown, rb


def main(megapixels: float = 25.0, gdal_cache: int | None = None) -> str:
    from affine import Affine
    from rasterio.crs import CRS

    import reblur.gis

    if gdal_cache is not None:  # GDAL's block cache while a COG is assembled, bytes
        reblur.gis._GDAL_CACHE_BYTES = int(gdal_cache)
    from reblur.gis import (
        geopackage_available,
        region_features,
        write_cog,
        write_geojson,
        write_geopackage,
    )
    from reblur.report import _cog_source, _MaskView, _to_dtype

    side = int(round(np.sqrt(megapixels * 1e6)))
    geo = dict(crs=CRS.from_epsg(32631), transform=Affine(0.5, 0, 4e5, 0, -0.5, 5e6))
    rows = []
    with tempfile.TemporaryDirectory(prefix="reblur-gis-bench-") as tmp:
        d = Path(tmp)
        t = time.perf_counter()
        change, unknown, rb = build(d / "work", side)
        t_build = time.perf_counter() - t
        out = d / "out"
        out.mkdir()
        source, convert = _cog_source(rb, np.dtype(np.uint8))
        stages = [
            ("changes.tif", lambda: write_cog(out / "changes.tif", _MaskView(change, unknown),
                                              geo, overviews="max")),
            ("unknown.tif", lambda: write_cog(out / "unknown.tif", _MaskView(unknown), geo,
                                              overviews="max")),
            # as the report writes it (the store's own pixels), and through floats as
            # before 0a7cf1a: the same file
            ("reblurred.tif", lambda: write_cog(out / "reblurred.tif", source, geo,
                                                convert=convert)),
            ("reblurred.tif through floats",
             lambda: write_cog(out / "reblurred.tif through floats", rb, geo,
                               convert=_to_dtype(np.uint8))),
        ]
        feats = []

        def polygons():
            feats.extend(region_features(_MaskView(change, unknown), geo))
            write_geojson(out / "changes.geojson", feats, geo)

        stages.append(("changes.geojson", polygons))
        if geopackage_available():
            stages.append(("changes.gpkg",
                           lambda: write_geopackage(out / "changes.gpkg", feats, geo)))
        for name, fn in stages:
            with _Peak() as p:
                fn()
            rows.append((name, p.seconds, p.growth_mb, (out / name).stat().st_size / 2**20))
        n_feat = len(feats)
    lines = [
        f"## GIS outputs at {side * side / 1e6:.1f} MP (`python -m benchmarks.gis_outputs "
        f"--megapixels {megapixels:g}"
        + ("" if gdal_cache is None else f" --gdal-cache {gdal_cache}") + "`)",
        "",
        f"{side} x {side} px, georeferenced; inputs built tile by tile on disk in "
        f"{t_build:.1f} s; {n_feat} change regions.  Memory: the largest growth of the "
        "resident set over the stage (sampled every 10 ms).",
        "",
        "| output | seconds | memory growth (MB) | file (MB) |",
        "|---|---|---|---|",
    ]
    lines += [f"| {n} | {s:.1f} | {m:.0f} | {f:.1f} |" for n, s, m, f in rows]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--megapixels", type=float, default=25.0)
    ap.add_argument("--gdal-cache", type=int, default=None,
                    help="GDAL's block cache while a COG is assembled, bytes (default: "
                    "reblur.gis's)")
    a = ap.parse_args()
    print(main(a.megapixels, a.gdal_cache))
