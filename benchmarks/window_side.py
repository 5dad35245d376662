"""What the estimation windows' side costs and buys on real camera shake
(``python -m benchmarks.window_side [--sides 400,320,256]``).

Issue #28 asks for any pair of at most 1 MP in at most 5 s end to end.  On real hand-held
shake (the GoPro pairs of :data:`benchmarks.cost.REAL_PAIRS`) the estimate is most of the
time, and most of the estimate is its last level: the full windows (two of 500 px on an
image under 2500 px) with every pose of the path, whose Gram products grow with the
windows' pixels times the active poses.  This benchmark measures the trade the target
asks for: each pair through ``reblur detect`` in a fresh process with its defaults, then
again with the central ``S x S`` part of each window the default run chose (``--box``),
for every side ``S`` of ``--sides``, and with each configuration file of ``--configs``
(``reblur detect --config``; by default ``benchmarks/configs/bands_all.toml``, the
weights solved on every band instead of their mean).  ``--shutter auto`` runs them all
with the rolling-shutter choice (its stage's time and model in the table).

Per run: the estimate's and the whole run's time (``report.json``), its outer iterations,
the share flagged, and the fidelity of the blur model away from the windows: the PSNR of
``reblurred.tif`` against the observation over the pixels that every run of the pair
left known and unflagged (the same pixels for all sides; GoPro pairs hold moving people,
no pasted change, so the flagged share is not a score).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import tifffile

from benchmarks.common import psnr
from benchmarks.cost import real_pairs
from benchmarks.quality import _rgb

#: Window sides (px) tried besides the default.
SIDES = (400, 320, 256)
#: Configurations tried besides the default: the motion solved on every band.
CONFIGS = (str(Path(__file__).parent / "configs" / "bands_all.toml"),)


def _detect(ref: Path, obs: Path, out: Path, boxes: list[str], config: str | None = None,
            shutter: str = "global") -> dict:
    """``reblur detect`` in a fresh process; its report, with the wall time."""
    cmd = [sys.executable, "-m", "reblur", "detect", str(ref), str(obs), "--out", str(out),
           "-q", "--shutter", shutter]
    for b in boxes:
        cmd += ["--box", b]
    if config is not None:
        cmd += ["--config", config]
    t = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if r.returncode:
        raise RuntimeError(f"reblur detect failed: {r.stderr.strip()[-300:]}")
    rep = json.loads((out / "report.json").read_text())
    rep["_seconds"] = time.perf_counter() - t
    return rep


def _centred(windows: list[list[int]], side: int) -> list[str]:
    """``--box`` values of the central ``side x side`` part of each window."""
    return [f"{y + (h - side) // 2},{x + (w - side) // 2},{side},{side}"
            for y, x, h, w in windows if min(h, w) >= side]


def measure_pair(name: str, ref: Path, obs: Path, sides=SIDES, configs=(),
                 shutter: str = "global") -> list[dict]:
    """Rows of one pair: the default run, then one per side and one per configuration,
    all with ``reblur detect --shutter shutter``."""
    g = _rgb(obs).astype(np.float64)
    rows, images = [], []
    keep = np.ones(g.shape[:2], bool)
    with tempfile.TemporaryDirectory() as tmp:
        runs = [("default", [], None)]
        rep = _detect(ref, obs, Path(tmp) / "default", [], shutter=shutter)
        windows = rep["motion"]["info"]["windows"]
        runs += [(str(s), _centred(windows, s), None) for s in sides]
        runs += [(Path(c).stem, [], c) for c in configs]
        for i, (label, boxes, config) in enumerate(runs):
            out = Path(tmp) / (label if i == 0 else f"{i}")
            if i > 0:
                rep = _detect(ref, obs, out, boxes, config, shutter)
            reb = tifffile.imread(out / "reblurred.tif").astype(np.float64) / 255.0
            keep &= cv2.imread(str(out / "changes.png"), cv2.IMREAD_GRAYSCALE) == 0
            keep &= cv2.imread(str(out / "unknown.png"), cv2.IMREAD_GRAYSCALE) == 0
            images.append(reb)
            mi = rep["motion"]["info"]
            rows.append({
                "pair": name, "windows": label,
                "side": int(max(max(w[2], w[3]) for w in mi["windows"])),
                "estimate_s": rep["timings_s"]["estimate"], "total_s": rep["_seconds"],
                "n_outer": mi["n_outer"], "flagged": rep["changes"]["changed_fraction"],
                "shutter": rep["decision"].get("shutter", {}).get("model", "global"),
                "shutter_s": rep["timings_s"].get("shutter", 0.0),
            })
    for row, reb in zip(rows, images, strict=True):
        row["psnr_db"] = psnr(reb, g, keep)
        row["pixels_scored"] = float(keep.mean())
    return rows


def table(rows: list[dict]) -> str:
    out = ["| pair | windows | side (px) | estimate (s) | shutter (s) | total (s) | "
           "outer iterations | flagged | reblur PSNR (dB) | pixels scored |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        sh = "-" if r["shutter"] == "global" and not r["shutter_s"] else \
            f"{r['shutter']} {r['shutter_s']:.2f}"
        out.append(f"| {r['pair']} | {r['windows']} | {r['side']} | {r['estimate_s']:.2f} | "
                   f"{sh} | {r['total_s']:.2f} | {r['n_outer']} | "
                   f"{100 * r['flagged']:.2f} % | {r['psnr_db']:.2f} | "
                   f"{100 * r['pixels_scored']:.1f} % |")
    return "\n".join(out)


def main(sides=SIDES, configs=CONFIGS, shutter: str = "global") -> str:
    """Run the GoPro pairs; return the markdown section."""
    rows = []
    for name, ref_p, obs_p in real_pairs("GoPro"):
        for r in measure_pair(name, ref_p, obs_p, sides, configs, shutter):
            print(json.dumps(r), flush=True)
            rows.append(r)
    load = os.getloadavg()[0]
    return ("## Estimation window side on real shake (`python -m benchmarks.window_side`)\n\n"
            "Each GoPro pair with its default windows, then with the central part of each "
            "(`--box`), then with each `--configs` file. PSNR of `reblurred.tif` against "
            "the observation over the pixels every run of the pair left known and "
            "unflagged.\n\n"
            f"{table(rows)}\n\n- host load average at the end: {load:.1f} on 2 cores\n")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(prog="python -m benchmarks.window_side")
    ap.add_argument("--sides", default=",".join(map(str, SIDES)),
                    help="window sides (px) to try besides the default, comma-separated")
    ap.add_argument("--configs", default=",".join(CONFIGS),
                    help="reblur detect --config files to run besides the default, "
                         "comma-separated")
    ap.add_argument("--shutter", default="global", choices=("global", "auto", "rolling"),
                    help="reblur detect --shutter of every run")
    a = ap.parse_args()
    print(main(tuple(int(s) for s in a.sides.split(",") if s),
               tuple(c for c in a.configs.split(",") if c), a.shutter))
