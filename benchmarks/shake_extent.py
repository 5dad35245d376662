"""Camera shake larger than the pose grid (issue #28): time and accuracy against the shake's
extent (``python -m benchmarks.shake_extent``).

The paper's grid holds translations of at most 12 px.  Real hand-held shake goes further:
GoPro 0374 (the sharp middle frame against the mean of eight 240 fps frames) puts 62 % of
its weight on that grid's edge.  A blur the grid cannot hold is a misfit: the l1 fit
spreads the weights over hundreds of poses, each solve runs long, and the reblurred
reference misses the blur.  The estimate widens the translations when that pays
(:func:`reblur.estimate_motion`'s ``t_grow``); this benchmark measures what it buys and
costs.

Cases, each through ``python -m reblur detect REF OBS -q`` in a fresh process (the
defaults; ``--truth`` where there is one):

* the test bed's 1 MP gray pairs of LEVIR test_7 (:func:`reblur.testbed.make_pair`, 8
  pasted changes, a 20 px viewpoint shift, 8-bit sensor) shaken along paths of peak
  translation 6 px (the test bed's default), 12, 20 and 35 px, and one whose out-of-plane
  tilt reaches 1.5 degrees (about 32 px, with perspective);
* the three GoPro pairs of :data:`benchmarks.cost.REAL_PAIRS` (no truth: the moving
  people are real changes).

Per run: wall time, the estimate's time, peak RSS, the estimation windows' fit (PSNR of
the reblurred reference against the observation over each window's unchanged pixels), the
largest translation of the grid used, the share flagged and, with a truth, JC, false-alarm
rate (all of them, those more than 10 px from a true change, and those in flagged regions
that touch no change's reach: the truth is the changes' half-maximum footprint, while a
change blurred over tens of pixels alters the observation as far as its blur reaches, and
a small one under a long blur may have no half-maximum footprint at all) and recall.  ``--src
OLD/src --label COMMIT`` runs another checkout; rows of every label are kept in
``docs/shake_runs.json`` and written into ``docs/benchmarks.md``.
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

import numpy as np
import tifffile

from benchmarks.common import REPO, load_runs, save_runs

RUNS = REPO / "docs" / "shake_runs.json"
CACHE = Path(tempfile.gettempdir()) / "reblur-shake"
#: name -> (seed, camera-path keywords of the test bed)
SHAKES = {
    "6 px": (2, {}),
    "12 px": (2, {"max_shift_px": 12.0, "max_roll_deg": 1.5}),
    "20 px": (2, {"max_shift_px": 20.0, "max_roll_deg": 1.5}),
    "35 px": (3, {"max_shift_px": 35.0, "max_roll_deg": 0.5}),
    # out-of-plane tilt of 1.5 degrees: about 32 px at the test bed's focal length, with
    # perspective the 3-D grid does not hold
    "tilt 1.5 deg": (8, {"max_tilt_deg": 1.5}),
}


def make_case(name: str, cache: Path = CACHE) -> Path:
    """The test-bed pair of ``name`` (:data:`SHAKES`) as ``ref.tif``, ``obs.tif`` and
    ``truth.tif`` in a folder of ``cache`` (made once), with ``reach.tif``: the changes'
    whole reach (every pixel some sub-pose maps into a change object,
    :func:`reblur.testbed.truth_window` with ``share=1e-9``)."""
    from reblur.testbed import levir_image, make_pair, plan_pair, truth_window

    folder = cache / name.replace(" ", "").replace(".", "_")
    seed, motion = SHAKES[name]
    if not (folder / "truth.tif").exists():
        pair = make_pair(levir_image("test_7"), seed=seed, motion=motion or None)
        folder.mkdir(parents=True, exist_ok=True)
        tifffile.imwrite(folder / "ref.tif", pair.reference)
        tifffile.imwrite(folder / "obs.tif", pair.observed)
        tifffile.imwrite(folder / "truth.tif", pair.truth.astype(np.uint8) * 255)
    if not (folder / "reach.tif").exists():
        plan = plan_pair(levir_image("test_7"), seed=seed, motion=motion or None)
        h, w = plan.shape[:2]
        reach = truth_window(plan.changed, plan.homographies, (0, h, 0, w), plan.boxes,
                             share=1e-9)
        tifffile.imwrite(folder / "reach.tif", reach.astype(np.uint8) * 255)
    return folder


def run(ref: Path, obs: Path, truth: Path | None, src: Path | None) -> dict:
    """``reblur detect`` on one pair in a fresh process; the row's figures."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        cmd = [sys.executable, "-m", "reblur", "detect", str(ref), str(obs), "--out",
               str(out), "-q"] + ([] if truth is None else ["--truth", str(truth)])
        env = dict(os.environ)
        if src is not None:
            env["PYTHONPATH"] = str(src)
        t = time.perf_counter()
        r = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False,
                           cwd=REPO)
        seconds = time.perf_counter() - t
        if r.returncode:
            return {"seconds": seconds,
                    "refused": (r.stderr.strip().splitlines() or ["?"])[-1][:300]}
        rep = json.loads((out / "report.json").read_text())
        far = None if truth is None else _far_false_alarms(out / "changes.png", truth)
        lone = None if truth is None else _lone_false_alarms(
            out / "changes.png", truth, truth.with_name("reach.tif"))
    info = rep["motion"]["info"]
    row = {"seconds": seconds, "estimate_s": rep["timings_s"]["estimate"],
           "peak_rss_mb": rep["memory"]["peak_rss_mb"],
           "fit_db": [float(v) for v in info.get("psnr_inliers") or info["psnr"]],
           "t_max": max(abs(v) for v in rep["motion"]["grid"]["tx"]),
           "flagged": rep["changes"]["changed_fraction"]}
    m = rep.get("metrics") or {}
    if m:
        row.update(jc=m["jaccard"], fpr=m["fpr"], recall=m["recall"], far_fpr=far,
                   lone_fpr=lone)
    return row


#: Distance (px) from a true change beyond which a flagged pixel is a false alarm away from
#: the changes (:func:`_far_false_alarms`).
NEAR_PX = 10


def _far_false_alarms(changes: Path, truth: Path) -> float:
    """Flagged pixels farther than :data:`NEAR_PX` from every true change, as a share of
    the unchanged pixels: a change blurred over tens of pixels spreads beyond the truth's
    half-maximum footprint, and those flags border it."""
    import cv2

    flagged = cv2.imread(str(changes), cv2.IMREAD_UNCHANGED) > 0
    true = tifffile.imread(truth) > 0
    dist = cv2.distanceTransform((~true).astype(np.uint8), cv2.DIST_L2, 5)
    return float(np.count_nonzero(flagged & (dist > NEAR_PX))) / max(
        int(np.count_nonzero(~true)), 1)


def _lone_false_alarms(changes: Path, truth: Path, reach: Path) -> float:
    """Flagged pixels of the regions (8-connected) that touch no change's reach (``reach``:
    every pixel some sub-pose maps into a change object), as a share of the unchanged
    pixels: the false regions themselves.  A change blurred over tens of pixels alters the
    observation as far as its blur reaches, and a small one under a long blur may have no
    half-maximum footprint (``truth``) at all: the regions flagged there are counted as
    false alarms by the truth's rates, not here."""
    import cv2

    flagged = (cv2.imread(str(changes), cv2.IMREAD_UNCHANGED) > 0).astype(np.uint8)
    true = tifffile.imread(truth) > 0
    near = tifffile.imread(reach) > 0
    n, labels = cv2.connectedComponents(flagged, connectivity=8)
    touch = np.zeros(n, bool)
    touch[np.unique(labels[(flagged > 0) & near])] = True
    lone = (labels > 0) & ~touch[labels]
    return float(np.count_nonzero(lone)) / max(int(np.count_nonzero(~true)), 1)


def measure(src: Path | None = None, cache: Path = CACHE) -> list[dict]:
    """Every case of the benchmark (GoPro pairs whose files are missing are skipped)."""
    from benchmarks.cost import real_pairs

    rows = []
    for name in SHAKES:
        case = make_case(name, cache)
        rows.append({"case": f"test bed, shake {name}",
                     **run(case / "ref.tif", case / "obs.tif", case / "truth.tif", src)})
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    for name, ref_p, obs_p in real_pairs("GoPro"):
        rows.append({"case": name, **run(ref_p, obs_p, None, src)})
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    return rows


def table(runs: list[dict]) -> str:
    """Markdown: one row per case and label, the labels in the order they were run."""
    out = ["| case | code | time (s) | estimate (s) | peak RSS (MB) | window fit (dB) | "
           "grid t_max (px) | flagged % | JC | false alarms % (> 10 px from a change / in "
           "regions touching no change's reach) | "
           "recall |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    cases = list(dict.fromkeys(r["case"] for run in runs for r in run["rows"]))
    for case in cases:
        for run_ in runs:
            for r in (r for r in run_["rows"] if r["case"] == case):
                if "refused" in r:
                    out.append(f"| {case} | {run_['label']} | {r['seconds']:.1f} | "
                               f"refused: {r['refused']} | | | | | | | |")
                    continue
                fit = " / ".join(f"{v:.1f}" for v in r["fit_db"])
                lone = ("-" if r.get("lone_fpr") is None
                        else f"{100 * r['lone_fpr']:.3f}")
                tail = (f"{r['jc']:.3f} | {100 * r['fpr']:.3f} ({100 * r['far_fpr']:.3f} / "
                        f"{lone}) | "
                        f"{r['recall']:.3f}" if "jc" in r else "- | - | -")
                out.append(f"| {case} | {run_['label']} | {r['seconds']:.1f} | "
                           f"{r['estimate_s']:.1f} | {r['peak_rss_mb']:.0f} | {fit} | "
                           f"{r['t_max']:g} | {100 * r['flagged']:.2f} | {tail} |")
    return "\n".join(out)


def main(src: Path | None = None, label: str | None = None, cache: Path = CACHE) -> str:
    """Run the cases with this checkout (or ``src``), keep the rows under ``label``
    (default: the commit) in ``docs/shake_runs.json`` and return the section's markdown."""
    from benchmarks.common import commit

    label = label or commit()
    rows = measure(src, cache)
    runs = [r for r in load_runs(RUNS) if r["label"] != label]
    runs.append({"label": label, "rows": rows})
    save_runs(RUNS, runs)
    return section(runs)


def section(runs: list[dict]) -> str:
    """The section's markdown from the saved runs."""
    return ("Test-bed pairs of LEVIR test_7 at 1 MP shaken further and further, and the "
            "GoPro pairs (`python -m benchmarks.shake_extent`; `--src OLD/src --label "
            "COMMIT` for another checkout).  Each case is `reblur detect` in a fresh "
            "process with the defaults; the window fit is each estimation window's PSNR "
            "over its unchanged pixels.\n\n" + table(runs))


if __name__ == "__main__":
    from benchmarks.run import write_section

    ap = argparse.ArgumentParser(prog="python -m benchmarks.shake_extent")
    ap.add_argument("--src", type=Path, default=None, help="another checkout's src folder")
    ap.add_argument("--label", default=None, help="name of the rows (default: the commit)")
    ap.add_argument("--cache", type=Path, default=CACHE, help="folder of the pairs")
    ap.add_argument("--saved", action="store_true",
                    help="only rewrite the section from docs/shake_runs.json")
    a = ap.parse_args()
    body = section(load_runs(RUNS)) if a.saved else main(a.src, a.label, a.cache)
    write_section("shake_extent", body)
    print(body)
