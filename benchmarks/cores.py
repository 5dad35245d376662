"""The same pairs on one core and on all of them (``python -m benchmarks.cores [--src
OLD/src]``): does the result depend on the machine's cores?

``reblur detect`` runs in a fresh process per pair and per affinity (its thread pools are
sized from the affinity), on the 1 MP pairs of :func:`benchmarks.gram_work.pairs` (the test
bed's 6 / 12 px shakes, the cost benchmark's unchanged pair, the GoPro pairs and the GoPro
0477 averages).  Per pair: the share flagged on each, whether the masks and the reblurred
image are the same bytes, and the pixels whose flag differs.  ``tests/test_cores.py``
checks one of these pairs.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2

from benchmarks.common import REPO, commit


def detect(ref: Path, obs: Path, out: Path, cpus: list[int], src: Path | None) -> dict:
    """``reblur detect`` on ``cpus``: its masks and reblurred image (bytes)."""
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = str(src)
    # the CPUs set in the child before numpy, BLAS and OpenCV size their thread pools
    code = (f"import os, runpy, sys; os.sched_setaffinity(0, {list(cpus)}); "
            "sys.argv[0] = 'reblur'; runpy.run_module('reblur', run_name='__main__')")
    r = subprocess.run([sys.executable, "-c", code, "detect", str(ref), str(obs), "--out",
                        str(out), "-q"], capture_output=True, text=True, env=env, cwd=REPO,
                       check=False)
    if r.returncode:
        raise RuntimeError(f"reblur detect {ref} {obs} failed: {r.stderr.strip()[-300:]}")
    return {n: (out / n).read_bytes() for n in ("changes.png", "unknown.png", "reblurred.tif")}


def main(src: Path | None = None) -> str:
    from benchmarks.gram_work import pairs

    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        return "## One core against all (`python -m benchmarks.cores`)\n\nNeeds two cores."
    label = commit() if src is None else str(src)
    lines = [f"## One core against {len(cpus)} (`python -m benchmarks.cores`, {label})", "",
             "| pair | flagged, 1 core | flagged, all | masks | reblurred | pixels differing |",
             "|---|---|---|---|---|---|"]
    for name, ref, obs in pairs():
        with tempfile.TemporaryDirectory() as tmp:
            one = detect(ref, obs, Path(tmp) / "one", cpus[:1], src)
            all_ = detect(ref, obs, Path(tmp) / "all", cpus, src)
            m1 = cv2.imread(str(Path(tmp) / "one" / "changes.png"), cv2.IMREAD_GRAYSCALE) > 0
            m2 = cv2.imread(str(Path(tmp) / "all" / "changes.png"), cv2.IMREAD_GRAYSCALE) > 0
        same = one["changes.png"] == all_["changes.png"] and \
            one["unknown.png"] == all_["unknown.png"]
        row = (f"| {name} | {100 * m1.mean():.3f} % | {100 * m2.mean():.3f} % | "
               f"{'same' if same else 'differ'} | "
               f"{'same' if one['reblurred.tif'] == all_['reblurred.tif'] else 'differ'} | "
               f"{int((m1 ^ m2).sum())} |")
        print(row, flush=True)
        lines.append(row)
    return "\n".join(lines)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(prog="python -m benchmarks.cores")
    ap.add_argument("--src", type=Path, default=None, help="another checkout's src folder")
    args = ap.parse_args()
    print(main(args.src))
