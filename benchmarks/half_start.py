"""The estimate's first level at half resolution (issue #28): what it buys and where
(``python -m benchmarks.half_start``).

:data:`reblur.estimate.HALF_START` solves the first coarse-to-fine level on 2 x 2 block
means of the windows' central parts when the first level's translations reach at least
:data:`reblur.estimate.HALF_MIN_T` px.  This runs ``reblur detect`` in a fresh process on
each pair with three settings, alternated: ``off`` (every level at full resolution),
``T >= 16`` (the default: the grids the alignment found the blur wide for) and ``T >=
6`` (the default +-12 px grid too), and reports per
run the estimate's time, each level's outer iterations (``h`` marks a half-resolution
level), the window fit (PSNR of the reblurred reference over each window's unchanged
pixels) and the pixels flagged.

Pairs: the test bed's shakes of :mod:`benchmarks.shake_extent` (6 to 35 px, the 1.5
degree tilt), the 1 MP ``defocus`` pair of :mod:`benchmarks.cost` and the GoPro 0477
average of 16 frames (:data:`benchmarks.cost.GOPRO_AVERAGES`): a dense blur and a real
one, each on the +-12 px grid with many poses.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.common import REPO

#: setting -> HALF_MIN_T (None: HALF_START off)
SETTINGS = {"off": None, "T >= 16": 16.0, "T >= 6": 6.0}

_RUNNER = ("import runpy, sys, reblur.estimate as e; t = sys.argv.pop(1); "
           "e.HALF_START = t != 'off'; e.HALF_MIN_T = float(t) if t != 'off' else 0.0; "
           "runpy.run_module('reblur', run_name='__main__')")


def pairs(cost_cache: Path, shake_cache: Path) -> list[tuple[str, Path, Path]]:
    """``(name, reference, observation)`` of the benchmark's pairs (made where missing)."""
    from benchmarks import cost, shake_extent

    out = []
    for name in shake_extent.SHAKES:
        folder = shake_extent.make_case(name, shake_cache)
        out.append((f"shake {name}", folder / "ref.tif", folder / "obs.tif"))
    folder = cost.make_case(1, "defocus", cost_cache)
    out.append(("defocus 1 MP", folder / "ref.tif", folder / "obs.tif"))
    for name, ref, obs in cost.gopro_averages(cost_cache):
        if name.endswith("16 frames"):
            out.append((name, ref, obs))
    return out


def run(ref: Path, obs: Path, setting: str) -> dict:
    """``reblur detect`` with ``setting`` in a fresh process; the run's figures."""
    t = SETTINGS[setting]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        cmd = [sys.executable, "-c", _RUNNER, "off" if t is None else str(t), "detect",
               str(ref), str(obs), "--out", str(out), "-q"]
        r = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, check=False,
                           env=dict(os.environ))
        if r.returncode:
            raise RuntimeError(f"reblur detect failed: {r.stderr.strip()[-300:]}")
        rep = json.loads((out / "report.json").read_text())
    info = rep["motion"]["info"]
    return {"estimate_s": rep["timings_s"]["estimate"],
            "levels": " ".join(("h" if "resolution" in lv else "") + str(lv["n_outer"])
                               for lv in info["levels"]),
            "fit_db": [round(float(v), 2) for v in info.get("psnr_inliers") or info["psnr"]],
            "flagged_px": rep["changes"]["changed_px"]}


def measure(repeat: int, cost_cache: Path, shake_cache: Path) -> list[dict]:
    """Every pair, the settings alternated ``repeat`` times; one row per pair and setting
    (the median estimate time, the last run's other figures)."""
    rows = []
    for name, ref, obs in pairs(cost_cache, shake_cache):
        got: dict[str, list[dict]] = {s: [] for s in SETTINGS}
        for _ in range(repeat):
            for s in SETTINGS:
                got[s].append(run(ref, obs, s))
        for s, runs in got.items():
            times = [r["estimate_s"] for r in runs]
            rows.append({"pair": name, "setting": s, **runs[-1],
                         "estimate_s": statistics.median(times),
                         "estimate_range": [min(times), max(times)]})
            print(rows[-1], file=sys.stderr)
    return rows


def table(rows: list[dict]) -> str:
    """The section's table."""
    out = ["| pair | first level at half resolution | estimate (s), median (range) | "
           "outer iterations by level | window fit (dB) | flagged px |",
           "|---|---|---|---|---|---|"]
    for r in rows:
        lo, hi = r["estimate_range"]
        fit = " / ".join(f"{v:.2f}" for v in r["fit_db"])
        out.append(f"| {r['pair']} | {r['setting']} | {r['estimate_s']:.2f} ({lo:.2f}-"
                   f"{hi:.2f}) | {r['levels']} | {fit} | {r['flagged_px']} |")
    return "\n".join(out)


def section(rows: list[dict], repeat: int) -> str:
    return ("`python -m benchmarks.half_start`: `reblur detect` in a fresh process per run, "
            f"the three settings alternated, {repeat} runs each; `off`: every level at full "
            "resolution; `T >= t`: the first level at half resolution where its "
            "translations reach t px (16: the default, `reblur.estimate.HALF_MIN_T`).  "
            "Outer iterations by level: `h` marks the half-resolution level (with its "
            "widening, when it widened).\n\n" + table(rows))


def main(repeat: int = 2, cost_cache: Path | None = None,
         shake_cache: Path | None = None) -> str:
    """Run the pairs (made under the caches of :mod:`benchmarks.cost` and
    :mod:`benchmarks.shake_extent` by default); the section's markdown."""
    from benchmarks.cost import CACHE as COST_CACHE
    from benchmarks.shake_extent import CACHE as SHAKE_CACHE

    rows = measure(repeat, cost_cache or COST_CACHE, shake_cache or SHAKE_CACHE)
    return section(rows, repeat)


if __name__ == "__main__":
    from benchmarks.run import write_section

    ap = argparse.ArgumentParser(prog="python -m benchmarks.half_start")
    ap.add_argument("--repeat", type=int, default=2, help="runs per pair and setting")
    ap.add_argument("--cost-cache", type=Path, default=None)
    ap.add_argument("--shake-cache", type=Path, default=None)
    a = ap.parse_args()
    body = main(a.repeat, a.cost_cache, a.shake_cache)
    write_section("half_start", body)
    print(body)
