"""Encoding of the mask PNGs (``python -m benchmarks.png_masks [--side 10240]``).

Two masks, drawn with a seeded generator:

* a blank 512 px RGBA viewer tile (one colour, transparent), as ``viewer.layers.mask_layer``
  encodes an empty tile;
* a ``side x side`` gray change mask (0 / 255, a few hundred discs).

Each is encoded with OpenCV's defaults (filters chosen per row, default strategy),
``io.encode_png(flat=True)`` (run-length mode; colour rows with the Sub filter), the
run-length mode without any row filter (what ``flat`` did to colour tiles from 6d45758 to
19b5c65), and, for the gray mask, ``io.write_png_bands`` (band by band, zlib levels 1 and
6).  Prints a markdown table: bytes and the median time of the repeats.  Every encoding
is decoded and checked against the mask.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np


def _median_time(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times)), out


def _masks(side: int) -> tuple[np.ndarray, np.ndarray]:
    tile = np.empty((512, 512, 4), np.uint8)
    tile[:] = (40, 40, 255, 0)
    rng = np.random.default_rng(0)
    gray = np.zeros((side, side), np.uint8)
    for _ in range(300):
        y, x = rng.integers(0, side, 2)
        cv2.circle(gray, (int(x), int(y)), int(rng.integers(5, side // 50)), 255, -1)
    return tile, gray


def _opencv(a: np.ndarray, params: list[int]) -> bytes:
    if a.ndim == 3:
        a = a[:, :, [2, 1, 0, 3]]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(a), params)
    assert ok
    return buf.tobytes()


def main(side: int = 10240) -> str:
    from reblur.io import encode_png, write_png_bands

    tile, gray = _masks(side)
    rle_unfiltered = [cv2.IMWRITE_PNG_COMPRESSION, 6,
                      cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE,
                      cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE]
    rows = []
    for name, mask, reps in (("512 px RGBA tile, blank", tile, 50),
                             (f"{side}^2 gray mask", gray, 3)):
        cases = [
            ("OpenCV default", lambda m=mask: _opencv(m, [cv2.IMWRITE_PNG_COMPRESSION, 6])),
            ("encode_png(flat=True)", lambda m=mask: encode_png(m, flat=True)),
            ("run-length, no row filter", lambda m=mask: _opencv(m, rle_unfiltered)),
        ]
        for how, fn in cases:
            sec, data = _median_time(fn, reps)
            back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
            if back.ndim == 3:
                back = back[:, :, [2, 1, 0, 3]]
            assert np.array_equal(back, mask), how
            rows.append((name, how, len(data), sec))
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "m.png"
        band = 1024
        for level in (1, 6):
            def bands():
                return (gray[y:y + band] for y in range(0, side, band))

            sec, _ = _median_time(lambda lv=level: write_png_bands(p, gray.shape, bands(),
                                                                   compression=lv), 3)
            assert np.array_equal(cv2.imread(str(p), cv2.IMREAD_UNCHANGED), gray)
            rows.append((f"{side}^2 gray mask", f"write_png_bands, level {level} (file)",
                         p.stat().st_size, sec))
    lines = [f"## Mask PNGs (`python -m benchmarks.png_masks --side {side}`)", "",
             "| mask | encoding | bytes | time (ms) |", "|---|---|---|---|"]
    lines += [f"| {m} | {h} | {n:,} | {1000 * s:.2f} |" for m, h, n, s in rows]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=10240, help="side of the gray mask (px)")
    print(main(ap.parse_args().side))
