"""The same pairs on one core and on all of them (``python -m benchmarks.cores [--src
OLD/src --label COMMIT] [--saved]``): does the result depend on the machine's cores?

``reblur detect`` runs in a fresh process per pair and per affinity (its thread pools are
sized from the affinity), on the 1 MP pairs of :func:`benchmarks.gram_work.pairs` (the test
bed's 6 / 12 / 20 px shakes and 1.5 degree tilt, the cost benchmark's unchanged and defocus
pairs, the GoPro pairs and the GoPro 0477 averages).  Per pair: the share flagged on each,
whether the masks and the reblurred image are the same bytes, and the pixels whose flag
differs.  The runs are kept in ``docs/cores_runs.json``: this checkout's, and the "before"
runs of other checkouts (``--src``).  ``tests/test_cores.py`` checks one of these pairs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2

from benchmarks.common import REPO, commit, save_runs


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


#: The runs: ``{"now": RUN, "before": [RUN, ...]}``, a RUN ``{"label", "cpus", "rows"}``
#: (``main`` saves "now"; ``--src`` adds or replaces a "before" of its label).
RUNS = REPO / "docs" / "cores_runs.json"


def measure(src: Path | None, cpus: list[int]) -> list[dict]:
    """Per pair: the share flagged on one core and on ``cpus``, whether the masks and the
    reblurred image are the same bytes, and the pixels whose flag differs."""
    from benchmarks.gram_work import pairs

    rows = []
    for name, ref, obs in pairs():
        with tempfile.TemporaryDirectory() as tmp:
            one = detect(ref, obs, Path(tmp) / "one", cpus[:1], src)
            all_ = detect(ref, obs, Path(tmp) / "all", cpus, src)
            m1 = cv2.imread(str(Path(tmp) / "one" / "changes.png"), cv2.IMREAD_GRAYSCALE) > 0
            m2 = cv2.imread(str(Path(tmp) / "all" / "changes.png"), cv2.IMREAD_GRAYSCALE) > 0
        rows.append({"pair": name, "flagged_one": float(m1.mean()),
                     "flagged_all": float(m2.mean()),
                     "masks_same": one["changes.png"] == all_["changes.png"]
                     and one["unknown.png"] == all_["unknown.png"],
                     "reblurred_same": one["reblurred.tif"] == all_["reblurred.tif"],
                     "differing": int((m1 ^ m2).sum())})
        print(_row(rows[-1]), flush=True)
    return rows


def _row(r: dict) -> str:
    return (f"| {r['pair']} | {100 * r['flagged_one']:.3f} % | {100 * r['flagged_all']:.3f} % "
            f"| {'same' if r['masks_same'] else 'differ'} | "
            f"{'same' if r['reblurred_same'] else 'differ'} | {r['differing']} |")


def _table(run: dict) -> list[str]:
    return ["| pair | flagged, 1 core | flagged, all | masks | reblurred | pixels differing |",
            "|---|---|---|---|---|---|", *(_row(r) for r in run["rows"])]


def section(runs: dict) -> str:
    """The markdown of the saved runs: now, then each before."""
    now = runs.get("now")
    lines = []
    if now is not None:
        lines += [f"## One core against {len(now['cpus'])} (`python -m benchmarks.cores`, "
                  f"{now['label']})", "", *_table(now)]
    for run in runs.get("before", []):
        lines += ["", f"Before (`python -m benchmarks.cores --src` a checkout of "
                      f"{run['label']}):", "", *_table(run)]
    return "\n".join(lines)


def main(src: Path | None = None, label: str | None = None) -> str:
    """Run the pairs on one core and on all (with ``src``: that checkout's, saved as a
    "before" run named ``label``); return the section of every saved run."""
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        return "## One core against all (`python -m benchmarks.cores`)\n\nNeeds two cores."
    runs = json.loads(RUNS.read_text()) if RUNS.exists() else {}
    run = {"label": commit() if src is None else (label or str(src)), "cpus": cpus,
           "rows": measure(src, cpus)}
    if src is None:
        runs["now"] = run
    else:
        runs["before"] = [r for r in runs.get("before", []) if r["label"] != run["label"]]
        runs["before"].append(run)
    save_runs(RUNS, runs)
    return section(runs)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(prog="python -m benchmarks.cores")
    ap.add_argument("--src", type=Path, default=None, help="another checkout's src folder")
    ap.add_argument("--label", default=None, help="name of that checkout (a commit)")
    ap.add_argument("--saved", action="store_true",
                    help="write the section from docs/cores_runs.json only")
    args = ap.parse_args()
    body = (section(json.loads(RUNS.read_text())) if args.saved
            else main(args.src, args.label))
    from benchmarks.run import write_section

    write_section("cores", body)
    print(body)
