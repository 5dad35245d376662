"""Cost of the zoomable viewer (:func:`reblur.viewer.write_viewer`) at growing sizes.

``python -m benchmarks.viewer [--sizes 4,25] [--tile PX]`` (default: the viewer's own tile size)

Each size (megapixels, square) runs in a fresh process: a textured RGB uint8 observation and
the change and unknown masks are written chunk by chunk into zarr stores in a temporary
directory (removed at the end), the result holds them lazily (no reblurred image: that
layer is left out, as when neither the result nor ``reblurred.tif`` has one), with one
change rectangle per 512 x 512 block and a region record for each.  Measured: the time of
``write_viewer``, the tiles and bytes written, the largest window read from any source
(recorded by a wrapper around each store), and the peak resident memory above the
process's size before the call (``VmHWM``, kept by the kernel, reset just before).  Prints
one markdown table.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import commit, peak_rss_mb, run_case


class _Recorded:
    """A zarr array that records the largest window read from it."""

    largest = 0

    def __init__(self, z):
        self.z, self.shape, self.dtype, self.ndim = z, z.shape, z.dtype, z.ndim

    def __getitem__(self, key):
        a = np.asarray(self.z[key])
        _Recorded.largest = max(_Recorded.largest, int(a.shape[0]) * int(a.shape[1]))
        return a


def _inputs(d: Path, side: int):
    import zarr

    chunk = 1024
    obs = zarr.open(str(d / "obs.zarr"), mode="w", shape=(side, side, 3), chunks=(chunk, chunk, 3),
                    dtype=np.uint8)
    chg = zarr.open(str(d / "chg.zarr"), mode="w", shape=(side, side), chunks=(chunk, chunk),
                    dtype=bool)
    unk = zarr.open(str(d / "unk.zarr"), mode="w", shape=(side, side), chunks=(chunk, chunk),
                    dtype=bool)
    rng = np.random.default_rng(0)
    for y in range(0, side, chunk):
        for x in range(0, side, chunk):
            h, w = min(chunk, side - y), min(chunk, side - x)
            yy, xx = np.mgrid[y:y + h, x:x + w]
            base = 128 + 60 * np.sin(xx / 37.0) * np.cos(yy / 53.0)
            noise = rng.normal(0, 20, (h, w, 3))
            obs[y:y + h, x:x + w] = np.clip(base[..., None] + noise, 0, 255).astype(np.uint8)
            u = np.zeros((h, w), bool)
            u[:, : max(0, 64 - x)] = True
            unk[y:y + h, x:x + w] = u
            chg[y:y + h, x:x + w] = False
    regions = []
    for y in range(100, side - 200, 512):
        for x in range(100, side - 200, 512):
            h, w = int(rng.integers(10, 120)), int(rng.integers(10, 120))
            chg[y:y + h, x:x + w] = True
            regions.append(dict(bbox=[y, x, y + h, x + w], area=h * w,
                                score=float(rng.uniform(1, 30)),
                                polarity=str(rng.choice(["brighter", "darker", "mixed"]))))
    regions.sort(key=lambda r: -r["score"])
    return obs, chg, unk, regions


def _reset_peak() -> float:
    """Reset the kernel's peak-RSS mark (``VmHWM``) to the current size; return it (MB)."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    with open("/proc/self/status") as f:
        return next(float(ln.split()[1]) / 1024 for ln in f if ln.startswith("VmRSS:"))


def case(mp: float, tile: int | None) -> dict:
    """One size, in this process."""
    from reblur.grid import PoseGrid
    from reblur.io import Image
    from reblur.result import ChangeResult, CropChoice, MotionEstimate
    from reblur.viewer import ViewerOptions, write_viewer

    side = int(round(np.sqrt(mp * 1e6)))
    d = Path(tempfile.mkdtemp(prefix="reblur-viewer-bench-"))
    try:
        obs, chg, unk, regions = _inputs(d, side)
        grid = PoseGrid.from_ranges((side, side), t_max=1, rz_max=0.0)
        res = ChangeResult(
            change=_Recorded(chg), unknown=_Recorded(unk), reblurred=None,
            motion=MotionEstimate(np.zeros(grid.shape), grid, boxes=[(0, 0, 512, 512)]),
            alignment=np.eye(3), crop=CropChoice(boxes=[(0, 0, 512, 512)], size=512),
            threshold=1.0)
        before = _reset_peak()
        t0 = time.perf_counter()
        info = write_viewer(d / "viewer", res, observed=Image.from_array(_Recorded(obs), "obs"),
                            regions=regions,
                            options=ViewerOptions() if tile is None
                            else ViewerOptions(tile_size=tile))
        dt = time.perf_counter() - t0
        files = [p for p in (d / "viewer" / "tiles").rglob("*") if p.is_file()]
        return dict(mp=side * side / 1e6, side=side, seconds=dt,
                    tiles=sum(p.suffix in (".jpg", ".png") for p in files),
                    mb=sum(p.stat().st_size for p in files) / 2**20,
                    largest_read=_Recorded.largest, regions=len(regions), shown=info.shown,
                    peak_mb_above=peak_rss_mb() - before, levels=info.layout.max_level + 1)
    finally:
        shutil.rmtree(d, ignore_errors=True)


def main(sizes: str = "4,25", tile: int | None = None) -> str:
    """Run every size in a fresh process; return (and print) the markdown table."""
    from reblur.viewer import ViewerOptions

    tile = ViewerOptions().tile_size if tile is None else int(tile)
    rows = [run_case("benchmarks.viewer", "--case", str(float(s)), "--tile", str(tile))
            for s in sizes.split(",")]
    lines = [f"Viewer pyramids (observation, unknown, changes; {tile} px tiles), commit "
             f"{commit()}: `python -m benchmarks.viewer --sizes {sizes}`", "",
             "| size | levels | tiles | on disk | time | largest window read | "
             "peak memory above start | regions (outlined) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['side']}^2 ({r['mp']:.0f} MP) | {r['levels']} | {r['tiles']} | "
                     f"{r['mb']:.0f} MB | {r['seconds']:.1f} s | "
                     f"{r['largest_read'] / 1e6:.2f} MP | {r['peak_mb_above']:.0f} MB | "
                     f"{r['regions']} ({r['shown']}) |")
    text = "\n".join(lines)
    print(text)
    return text


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="4,25", help="megapixels, comma-separated")
    ap.add_argument("--tile", type=int, default=None, help="tile side (default: the viewer's)")
    ap.add_argument("--case", type=float, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.case is not None:
        print(json.dumps(case(a.case, a.tile)))
    else:
        main(a.sizes, a.tile)
