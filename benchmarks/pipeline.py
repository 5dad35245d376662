"""End-to-end ``detect_changes`` on the demo pair and a 100 MP tiled-TIFF pair.

``python -m benchmarks.pipeline`` — each case in a fresh process (peak RSS is its own).  The
100 MP pair is generated tile by tile (never whole in memory) as tiled TIFFs: a mosaic of the
real LEVIR/WHU images (gray) and its blur along a smooth camera path, with pasted changes.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import peak_rss_mb, run_case


def demo_case() -> dict:
    import reblur
    from reblur.data import demo_pair
    from reblur.metrics import change_metrics

    ref, obs, truth = demo_pair()
    t = time.perf_counter()
    res = reblur.detect_changes(ref, obs)
    dt = time.perf_counter() - t
    m = change_metrics(truth, res.change, ignore=res.unknown)
    return dict(case="demo", mp=obs.shape[0] * obs.shape[1] / 1e6, time_s=dt,
                peak_rss_mb=peak_rss_mb(), jaccard=m["jaccard"], yule=m["yule"], pcc=m["pcc"],
                fpr=m["fpr"], timings=res.timings)


def big_changes(H: int, W: int) -> list[tuple[int, int, int]]:
    """The 40 pasted squares ``(y0, x0, side)`` of :func:`make_big` (seeded)."""
    rng = np.random.default_rng(0)
    return [(int(rng.integers(0, H - 200)), int(rng.integers(0, W - 200)),
             int(rng.integers(40, 160))) for _ in range(40)]


def make_big(dirpath: Path, side: int, tile: int = 512) -> tuple[Path, Path]:
    """Write a side x side gray uint8 pair as tiled TIFFs, tile by tile."""
    import cv2
    import tifffile

    from benchmarks.common import DATA
    from reblur.simulate import MosaicScene, blur_along_path, random_camera_path

    files = [f for f in sorted((DATA / "levir_whu_1024").glob("samples_*/*/*.png"))
             if f.parent.name in ("A", "prev")]
    ims = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
    n = int(np.ceil(side / 2048))
    scene = MosaicScene(ims, 2048, n, n, rng=1)
    H = W = side
    path = random_camera_path(3, center=((W - 1) / 2, (H - 1) / 2), t_max=5.0, rz_max=0.05)
    changes = big_changes(H, W)

    def tiles(kind):
        for y in range(0, H, tile):
            for x in range(0, W, tile):
                h, w = min(tile, H - y), min(tile, W - x)
                if kind == "ref":
                    a = scene[y : y + h, x : x + w]
                else:
                    a = blur_along_path(scene, path, (y, x, h, w))[0].reshape(h, w)
                    for cy, cx, s in changes:
                        ya, yb = max(cy, y), min(cy + s, y + h)
                        xa, xb = max(cx, x), min(cx + s, x + w)
                        if ya < yb and xa < xb:
                            a[ya - y : yb - y, xa - x : xa - x + (xb - xa)] = 0.95
                yield np.clip(np.round(a * 255), 0, 255).astype(np.uint8)

    out = []
    for kind in ("ref", "obs"):
        p = dirpath / f"{kind}.tif"
        tifffile.imwrite(p, tiles(kind), shape=(H, W), dtype=np.uint8, tile=(tile, tile),
                         compression="zstd", bigtiff=True)
        out.append(p)
    return out[0], out[1]


def big_case(side: int) -> dict:
    import tifffile
    import zarr

    import reblur

    with tempfile.TemporaryDirectory(dir="/tmp") as d:
        t = time.perf_counter()
        ref_p, obs_p = make_big(Path(d), side)
        gen = time.perf_counter() - t
        ref = zarr.open(tifffile.imread(ref_p, aszarr=True), mode="r")
        obs = zarr.open(tifffile.imread(obs_p, aszarr=True), mode="r")
        base = peak_rss_mb()
        t = time.perf_counter()
        res = reblur.detect_changes(ref, obs, workers=2)
        dt = time.perf_counter() - t
        return dict(case=f"{side}x{side}", mp=side * side / 1e6, time_s=dt, gen_s=gen,
                    peak_rss_mb=peak_rss_mb(), rss_before_mb=base,
                    flagged=float(res.change.mean()), timings=res.timings,
                    windows=len(res.crop.boxes), grid_poses=res.motion.grid.size)


def main() -> str:
    demo = run_case("benchmarks.pipeline", "--case", "demo", blas_threads=None)
    big = run_case("benchmarks.pipeline", "--case", "10000", timeout=3600, blas_threads=None)
    lines = [
        "## detect_changes end to end",
        "",
        "`python -m benchmarks.pipeline` (each case in a fresh process).",
        "",
        "| case | size | time (s) | peak RSS (MB) | notes |",
        "|---|---|---|---|---|",
        f"| demo pair (`reblur demo`) | {demo['mp']:.2f} MP RGB | {demo['time_s']:.1f} | "
        f"{demo['peak_rss_mb']:.0f} | JC {demo['jaccard']:.3f}, YC {demo['yule']:.3f}, "
        f"PCC {100 * demo['pcc']:.2f} %, FPR {100 * demo['fpr']:.2f} % |",
        f"| tiled TIFF pair, uint8 gray, generated tile by tile | {big['mp']:.0f} MP | "
        f"{big['time_s']:.1f} | {big['peak_rss_mb']:.0f} | stages: "
        + ", ".join(f"{k} {v:.1f} s" for k, v in big["timings"].items())
        + f"; {big['windows']} windows, {big['grid_poses']} poses; flagged "
        f"{100 * big['flagged']:.2f} % |",
        "",
        "Target (pipeline issue): 100 MP with peak RSS <= 2 GB.",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--case")
    a = ap.parse_args()
    if a.case == "demo":
        print(json.dumps(demo_case()))
    elif a.case:
        print(json.dumps(big_case(int(a.case))))
    else:
        print(main())
