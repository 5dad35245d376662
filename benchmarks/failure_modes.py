"""The decision's failure modes (issue #27), before and after.

Run: ``python -m benchmarks.failure_modes``.

Every row is a pair of the independent test bed (:mod:`reblur.testbed.cases`): a real LEVIR
scene (``test_7``) through the test bed's own 6-D camera shake, perspective view change
and sensor (8 bit, 1 DN), edited by a black hole, a dark textured occluder, an illumination
ramp or vignetting, long thin changes, or nothing (the observation is the reference); and a
reference GeoTIFF with ``nodata=0`` and a missing wedge.  Each pair is written to files and
run with ``reblur detect`` as a user runs it; with ``--src OLD/src --label COMMIT`` an
earlier checkout's reblur runs instead, and its rows are saved as the "before" figures.
The baseline is register (SIFT + RANSAC, ECC fallback) + difference + Otsu
(:func:`reblur.baselines.register_then_difference`).

Scores (known pixels, the test bed's truth): ``FAR`` the flagged share of unchanged pixels
more than 3 px from a change, ``recall`` and ``JC`` of the changes; for the nodata row the
share of the wedge reported unknown and the share flagged as change.
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

from benchmarks.common import REPO

CASES = ("hole25", "hole50", "occluder25", "occluder45", "occluder60", "plain", "ramp",
         "vignette", "ramp_strong", "saturated", "fill55", "thin", "identical", "nodata")
RUNS = REPO / "docs" / "failure_modes_runs.json"
BEFORE = REPO / "docs" / "failure_modes_before.json"
BOUNDARY = 3


def _write(case: str, d: Path) -> dict:
    """Write a case's pair (GeoTIFFs, 1 m pixels) and truth into ``d``; returns the truth
    arrays (``truth``, ``valid``, and for ``nodata`` the wedge in the observation)."""
    import rasterio
    from rasterio.transform import from_origin

    from reblur import testbed as tb

    pair = tb.failure_pair("plain" if case == "nodata" else case)
    ref = pair.reference.copy()
    extra = {}
    nodata = None
    if case == "nodata":
        wedge = tb.wedge_mask(ref.shape[:2])
        ref[wedge] = 0
        nodata = 0
        extra["wedge"] = _wedge_in_observation(wedge, pair.homographies)
    H, W = ref.shape[:2]
    prof = dict(driver="GTiff", height=H, width=W, count=1, dtype=str(ref.dtype),
                crs="EPSG:32633", transform=from_origin(500000, 4000000, 1.0, 1.0))
    with rasterio.open(d / "reference.tif", "w", nodata=nodata, **prof) as dst:
        dst.write(ref, 1)
    with rasterio.open(d / "observed.tif", "w", **prof) as dst:
        dst.write(pair.observed, 1)
    return dict(truth=pair.truth, valid=pair.valid, reference=ref, observed=pair.observed,
                **extra)


def _wedge_in_observation(wedge: np.ndarray, hs: np.ndarray) -> np.ndarray:
    """Observation pixels some sub-pose reads inside the wedge, eroded by 2 px."""
    import scipy.ndimage as ndi

    H, W = wedge.shape
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    hit = np.zeros(H * W, bool)
    for h in hs[:: max(1, len(hs) // 16)]:
        p = np.linalg.inv(h) @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
        u, v = p[0] / p[2], p[1] / p[2]
        ok = (u >= 0) & (v >= 0) & (u <= W - 1) & (v <= H - 1)
        hit[ok] |= wedge[np.round(v[ok]).astype(int), np.round(u[ok]).astype(int)]
    return ndi.binary_erosion(hit.reshape(H, W), iterations=2)


def _scores(change: np.ndarray, unknown: np.ndarray, t: dict) -> dict:
    import cv2

    known = t["valid"] & ~unknown
    truth = t["truth"]
    k = 2 * BOUNDARY + 1
    near = cv2.dilate(truth.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    neg, pos = known & ~near, known & truth
    res = dict(far=float(np.count_nonzero(change & neg) / max(np.count_nonzero(neg), 1)),
               flagged=float(np.count_nonzero(change & known) / max(np.count_nonzero(known),
                                                                     1)))
    if pos.any():
        res["recall"] = float(np.count_nonzero(change & pos) / np.count_nonzero(pos))
        res["jc"] = float(np.count_nonzero(change & truth & known)
                          / max(np.count_nonzero((change | truth) & known), 1))
    if "wedge" in t:
        w = t["wedge"]
        res["wedge_unknown"] = float(unknown[w].mean())
        res["wedge_change"] = float(change[w].mean())
    return res


def run_reblur(d: Path, t: dict, src: Path | None) -> dict:
    import cv2

    out = d / "out"
    cmd = [sys.executable, "-m", "reblur", "detect", str(d / "reference.tif"),
           str(d / "observed.tif"), "--out", str(out), "--overwrite", "-q"]
    env = dict(os.environ, PYTHONPATH=str(src)) if src is not None else None
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    seconds = time.perf_counter() - t0
    if r.returncode:
        return {"error": (r.stderr.strip().splitlines() or ["?"])[-1][:160],
                "seconds": seconds}
    change = cv2.imread(str(out / "changes.png"), 0) > 0
    unknown = cv2.imread(str(out / "unknown.png"), 0) > 0
    res = _scores(change, unknown, t)
    res["seconds"] = seconds
    rep = json.loads((out / "report.json").read_text())
    il = rep["decision"]["photometry"]["info"].get("illumination")
    if il:
        res["illumination"] = il["model"]
    pre = rep["decision"].get("prefit_illumination")
    if pre:  # the pre-fit's choice for the estimate, and its residual ratio per band
        res["prefit"] = {"model": pre["model"], "ratio": pre["ratio"]}
    return res


def run_baseline(t: dict) -> dict:
    from reblur.baselines import register_then_difference

    ref = t["reference"].astype(np.float32) / 255
    obs = t["observed"].astype(np.float32) / 255
    try:
        change, info = register_then_difference(ref, obs)
    except Exception as exc:  # noqa: BLE001 - the baseline's failure is a row's figure
        return {"error": str(exc).splitlines()[0][:160]}
    return _scores(change, np.asarray(info["unknown"], bool), t)


def rows(src: Path | None = None, cases=CASES, baseline: bool = True) -> list[dict]:
    out = []
    for case in cases:
        with tempfile.TemporaryDirectory(prefix=f"reblur-fm-{case}-") as tmp:
            d = Path(tmp)
            t = _write(case, d)
            row = {"case": case, "reblur": run_reblur(d, t, src)}
            if baseline:
                row["baseline"] = run_baseline(t)
        print(json.dumps(row), flush=True)
        out.append(row)
    return out


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.3f} %"


def _num(v) -> str:
    return "-" if v is None else f"{v:.3f}"


def _cell(r: dict) -> str:
    if "error" in r:
        return f"refused: {r['error'].removeprefix('reblur: error: ')[:70]}"
    if "wedge_unknown" in r:
        return (f"wedge {100 * r['wedge_unknown']:.1f} % unknown, "
                f"{100 * r['wedge_change']:.1f} % change")
    parts = [f"FAR {_pct(r.get('far'))}"]
    if "recall" in r:
        parts += [f"recall {_num(r['recall'])}", f"JC {_num(r['jc'])}"]
    else:
        parts += [f"flagged {_pct(r.get('flagged'))}"]
    return ", ".join(parts)


def table(after: list[dict], before: list[dict] | None) -> str:
    old = {r["case"]: r for r in (before or [])}
    lines = ["| case | reblur before | reblur after | register + difference + Otsu |",
             "|---|---|---|---|"]
    for r in after:
        b = old.get(r["case"], {}).get("reblur")
        lines.append(f"| {r['case']} | {_cell(b) if b else '-'} | {_cell(r['reblur'])} | "
                     f"{_cell(r['baseline']) if 'baseline' in r else '-'} |")
    return "\n".join(lines)


def section(after: list[dict]) -> str:
    before = json.loads(BEFORE.read_text()) if BEFORE.exists() else None
    label = before["label"] if before else "-"
    return (
        "## Failure modes of the decision (issue #27)\n\n"
        "`python -m benchmarks.failure_modes` (pairs of the independent test bed, "
        "`reblur.testbed.cases`, run with `reblur detect`; \"before\" is reblur at "
        f"{label} on the same files, `--src OLD/src --label COMMIT`).  FAR: flagged share of "
        "unchanged known pixels more than 3 px from a change; recall and JC of the changes; "
        "`plain` is the 8 pasted changes of `ramp`, `vignette` and `ramp_strong` without the "
        "illumination; `fill55` is `plain` with the observation's left 55 % set to 0 (a "
        "fill without a nodata tag; the fill counts as change); `saturated` is `plain` "
        "exposed 1.3x brighter (the test bed's sensor saturates ~8 % of the observation); "
        "`ramp_strong`, `saturated` and `fill55` have no \"before\" row (added later)."
        "\n\n" + table(after, before["rows"] if before else None))


def main(src: Path | None = None, label: str | None = None) -> str:
    if src is not None:
        rs = rows(src, baseline=False)
        BEFORE.write_text(json.dumps({"label": label or str(src), "rows": rs}, indent=1))
        return section(json.loads(RUNS.read_text())) if RUNS.exists() else ""
    rs = rows()
    RUNS.write_text(json.dumps(rs, indent=1))
    return section(rs)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--src", type=Path, default=None, help="another checkout's src folder")
    ap.add_argument("--label", default=None, help="name of that checkout (a commit)")
    ap.add_argument("--saved", action="store_true",
                    help="write the section from the saved rows only")
    a = ap.parse_args()
    if a.saved:
        body = section(json.loads(RUNS.read_text()))
    else:
        body = main(a.src, a.label)
    if body:
        from benchmarks.run import write_section

        write_section("failure_modes", body)
        print(body)
