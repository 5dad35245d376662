"""Thin strips: the estimation windows and the decision on images 130-400 px across
(``python -m benchmarks.strips [--src OTHER/src --label COMMIT]``).

The estimation windows are chosen from cells of 100 px.  On a strip one or two cells
across, the edge-aligned cells reach the edges the pose grid's translation margin
excludes, and the windows, when there are any, are one cell.  Each case is a LEVIR test_7
strip (1024 px long, the rows centred) through the independent test bed's shake
(``shake_for``), a 6 px view change, its sensor and three pasted changes, written as TIFF
and run through ``reblur detect`` in a fresh process.  Scores: FAR, the share flagged of
the valid pixels farther than 3 px from a change; recall of the changes' half-maximum
footprint; the windows the run chose.  ``--src`` runs another checkout on the same pairs
and shows both tables.
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
import numpy as np
import tifffile

#: Strip heights (px); every strip is 1024 px long.
HEIGHTS = (130, 140, 150, 200, 240, 300, 400)
RUNS = Path(__file__).resolve().parents[1] / "docs" / "strips_runs.json"


def make_case(height: int, d: Path) -> dict:
    """Write the strip pair of ``height`` into ``d``; returns its truth and valid masks."""
    from reblur.testbed.camera import shake_for
    from reblur.testbed.pairs import make_pair
    from reblur.testbed.scenes import levir_image

    scene = levir_image("test_7")
    y0 = (scene.shape[0] - height) // 2
    scene = scene[y0 : y0 + height]
    pair = make_pair(scene, n_changes=3, motion=shake_for(scene.shape),
                     viewpoint={"shift_px": 6.0}, seed=3)
    tifffile.imwrite(d / "reference.tif", pair.reference)
    tifffile.imwrite(d / "observed.tif", pair.observed)
    return {"truth": pair.truth, "valid": pair.valid}


def run(d: Path, truth: dict, src: Path | None) -> dict:
    """``reblur detect`` on the pair in ``d`` (``src`` on ``PYTHONPATH`` if given)."""
    out = d / "out"
    cmd = [sys.executable, "-m", "reblur", "detect", str(d / "reference.tif"),
           str(d / "observed.tif"), "--out", str(out), "--overwrite", "-q"]
    env = dict(os.environ, PYTHONPATH=str(src)) if src is not None else None
    r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if r.returncode:
        return {"error": (r.stderr.strip().splitlines() or ["?"])[-1][:120]}
    change = cv2.imread(str(out / "changes.png"), 0) > 0
    near = cv2.dilate(truth["truth"].astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    quiet = truth["valid"] & ~near
    rep = json.loads((out / "report.json").read_text())
    return {"far": float((change & quiet).sum() / max(quiet.sum(), 1)),
            "recall": float((change & truth["truth"]).sum() / max(truth["truth"].sum(), 1)),
            "windows": rep["motion"]["info"]["windows"],
            "seconds": float(rep["timings_s"]["total"])}


def rows(src: Path | None = None) -> list[dict]:
    out = []
    for h in HEIGHTS:
        with tempfile.TemporaryDirectory(prefix=f"reblur-strip-{h}-") as tmp:
            d = Path(tmp)
            row = {"height": h, **run(d, make_case(h, d), src)}
        print(json.dumps(row), flush=True)
        out.append(row)
    return out


def table(rs: list[dict]) -> str:
    lines = ["| strip (px) | FAR | recall | windows (y0, x0, h, w) | s |", "|---|---|---|---|---|"]
    for r in rs:
        if "error" in r:
            lines.append(f"| {r['height']} x 1024 | refused: {r['error']} | | | |")
            continue
        wins = ", ".join("(" + ", ".join(str(v) for v in w) + ")" for w in r["windows"])
        lines.append(f"| {r['height']} x 1024 | {100 * r['far']:.3f} % | {r['recall']:.3f} | "
                     f"{wins} | {r['seconds']:.1f} |")
    return "\n".join(lines)


def section(saved: dict) -> str:
    body = ["## Thin strips (`python -m benchmarks.strips`)", "",
            (__doc__ or "").split("\n\n")[1].replace("\n", " "), "", table(saved["rows"])]
    if saved.get("before"):
        body += ["", f"Before (reblur at {saved['before']['label']}, same pairs; "
                 "`python -m benchmarks.strips --src OLD_CHECKOUT/src --label COMMIT`):", "",
                 table(saved["before"]["rows"])]
    return "\n".join(body)


def main(src: Path | None = None, label: str | None = None) -> str:
    """Run the strips (with ``src``: another checkout's, kept as "before"); the section."""
    saved = json.loads(RUNS.read_text()) if RUNS.exists() else {}
    if src is not None:
        saved["before"] = {"label": label or str(src), "rows": rows(src)}
    else:
        saved["rows"] = rows()
    RUNS.write_text(json.dumps(saved, indent=1))
    return section(saved) if "rows" in saved else ""


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--src", type=Path, default=None, help="another checkout's src folder")
    ap.add_argument("--label", default=None, help="name of that checkout (a commit)")
    a = ap.parse_args()
    text = main(a.src, a.label)
    if text:
        from benchmarks.run import write_section

        write_section("strips", text)
        print(text)
