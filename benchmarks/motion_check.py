"""Is the motion right across a cost-curve pair?  Reblur accuracy on windows of the image.

``python -m benchmarks.motion_check [--side 31623] [--dir DIR] [--windows K]``

Generates the pair of :func:`benchmarks.pipeline.make_big` (the cost curve's synthetic
mosaic, as tiled TIFFs; kept in ``--dir`` if given, so a second run skips the generation),
runs the estimation stages of ``detect_changes`` on the files (coarse alignment,
photometric pre-match, spread windows, motion estimate, refinement) and prints the PSNR of
the reblurred reference (with the pipeline's pre-match applied) against the TRUE blur,
before the pasted changes, on 400 x 400 windows at the centre, the corners, the middle
of the edges and next to cell seams.  A diagnostic, not part of ``make bench``: it tells
whether false alarms of a cost-curve run come from the motion or from the decision.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

S = 400  #: window side
CELL = 2048  #: mosaic cell of make_big


def windows(side: int) -> dict[str, tuple[int, int, int, int]]:
    """Named ``(y, x, S, S)`` windows spread over a ``side`` x ``side`` image."""
    far, mid = side - 1000, side // 2
    seam = CELL * max(1, side // CELL // 2)
    return {
        "centre": (mid, mid, S, S), "quarter": (side // 4, side // 4, S, S),
        "top-left": (600, 600, S, S), "top-right": (600, far, S, S),
        "bottom-left": (far, 600, S, S), "bottom-right": (far, far, S, S),
        "left edge": (mid, 600, S, S), "top edge": (600, mid, S, S),
        "across a row seam": (seam - S // 2, mid + 300, S, S),
        "across a column seam": (mid + 300, seam - S // 2, S, S),
    }


def check(d: Path, side: int, n_windows: int | None = None) -> list[str]:
    import cv2
    import tifffile
    import zarr

    from benchmarks.common import DATA, psnr
    from benchmarks.pipeline import make_big
    from reblur.pipeline import _estimate_stage
    from reblur.simulate import MosaicScene, PathBlurredScene, random_camera_path
    from reblur.tiled import SparsePoses, reblur_tile

    if not (d / "obs.tif").exists():
        make_big(d, side)
    # the generator's scene and path (same seeds as make_big)
    files = [f for f in sorted((DATA / "levir_whu_1024").glob("samples_*/*/*.png"))
             if f.parent.name in ("A", "prev")]
    ims = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
    n = int(np.ceil(side / CELL))
    scene = MosaicScene(ims, CELL, n, n, rng=1)
    path = random_camera_path(3, center=((side - 1) / 2, (side - 1) / 2), t_max=5.0,
                              rz_max=0.05)
    truth = PathBlurredScene(scene, path)
    ref = zarr.open(tifffile.imread(d / "ref.tif", aszarr=True), mode="r")
    obs = zarr.open(tifffile.imread(d / "obs.tif", aszarr=True), mode="r")
    t = time.perf_counter()
    e = _estimate_stage(ref, obs, grid=None, t_max=12, rz_max=3.0, rz_step=None, lam=0.1,
                        align=True, refine=True, windows=n_windows, large_side=2500, select=None,
                        boxes=None)
    dt = time.perf_counter() - t
    poses = SparsePoses(e.motion.weights, e.grid, e.base)
    lines = [f"{side} x {side}: estimation stages {dt:.1f} s, windows {e.crop.boxes}, "
             f"{poses.n_poses} poses", "", "| window | box | PSNR against the true blur (dB) |",
             "|---|---|---|"]
    for name, b in windows(side).items():
        gt, valid = truth.window(b)
        img, ok = reblur_tile(poses, ref, b)
        m = img[:, :, 0] / 255.0 * float(e.gain[0]) + float(e.offset[0])
        lines.append(f"| {name} | {b} | {psnr(m, gt, ok & valid):.1f} |")
    q = np.round(gt * 255) / 255
    lines.append(f"\nuint8 quantisation of the last window alone: {psnr(q, gt, valid):.1f} dB")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=31623)
    ap.add_argument("--dir", type=Path, default=None)
    ap.add_argument("--windows", type=int, default=None,
                    help="estimation windows (default: the pipeline's default for the size)")
    a = ap.parse_args()
    if a.dir is not None:
        a.dir.mkdir(parents=True, exist_ok=True)
        print("\n".join(check(a.dir, a.side, a.windows)))
        return
    with tempfile.TemporaryDirectory(dir="/tmp", prefix="reblur-motion-") as dd:
        print("\n".join(check(Path(dd), a.side, a.windows)))


if __name__ == "__main__":
    main()
