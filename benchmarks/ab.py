"""Two checkouts on the same 1 MP pairs, run alternately (``python -m benchmarks.ab --src
OLD/src [--label COMMIT] [--repeat 2]``; issue #28).

This host's speed drifts by up to 1.6x between phases (docs/NOTES.md), so a speed-up
measured by two benchmark runs an hour apart is partly the host's. This benchmark runs
``reblur detect`` in a fresh process on every pair of :func:`benchmarks.gram_work.pairs`
(the test bed's 6 / 12 / 20 px shakes and 1.5 degree tilt, the cost benchmark's unchanged
and defocus pairs, the GoPro pairs and the GoPro 0477 averages) with the other checkout's
sources (``--src``, on ``PYTHONPATH``) and with this checkout's, alternately, ``--repeat``
times each (both packages byte-compiled first, as an install leaves them), and reports per
pair the mean total, estimate and reblur_decide times of both (stages from ``report.json``),
the share flagged and the fidelity of each blur model: the PSNR of ``reblurred.tif``
against the observation over the pixels every run of the pair left known and unflagged (the
same pixels for both; :mod:`benchmarks.window_side` scores its sides so); for the test-bed pairs,
recall and false alarms against their truth.
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

from benchmarks.common import REPO, commit, compile_package, psnr


def _image(path: Path) -> np.ndarray:
    """An image file as float in [0, 1], ``(H, W, C)``."""
    a = tifffile.imread(path) if path.suffix in (".tif", ".tiff") else \
        cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if a.ndim == 3 and path.suffix not in (".tif", ".tiff"):
        a = a[:, :, ::-1]  # OpenCV's BGR
    scale = 65535.0 if a.dtype == np.uint16 else 255.0
    a = a.astype(np.float64) / scale
    return a[:, :, None] if a.ndim == 2 else a


def detect(ref: Path, obs: Path, out: Path, src: Path | None) -> dict:
    """``reblur detect ref obs`` in a fresh process (``src`` first on ``PYTHONPATH``); its
    wall time, report and masks."""
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = str(src)
    cmd = [sys.executable, "-m", "reblur", "detect", str(ref), str(obs), "--out", str(out),
           "-q", "--overwrite"]
    t = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO, check=False)
    seconds = time.perf_counter() - t
    if r.returncode:
        raise RuntimeError(f"reblur detect {ref} {obs} failed: {r.stderr.strip()[-300:]}")
    rep = json.loads((out / "report.json").read_text())
    return {"seconds": seconds, "estimate_s": rep["timings_s"]["estimate"],
            "decide_s": rep["timings_s"]["reblur_decide"],
            "flagged": rep["changes"]["changed_fraction"],
            "changes": cv2.imread(str(out / "changes.png"), cv2.IMREAD_GRAYSCALE) > 0,
            "unknown": cv2.imread(str(out / "unknown.png"), cv2.IMREAD_GRAYSCALE) > 0,
            "reblurred": _image(out / "reblurred.tif")}


def score(runs: list[dict], obs: np.ndarray, truth: np.ndarray | None) -> list[dict]:
    """Per run: the PSNR of its reblurred reference against ``obs`` over the pixels that
    every run of ``runs`` left known and unflagged, and (given ``truth``) recall and the
    share of unchanged pixels flagged.  The runs' masks and images are dropped."""
    keep = np.ones(obs.shape[:2], bool)
    for r in runs:
        keep &= ~r["changes"] & ~r["unknown"]
    out = []
    for r in runs:
        reb = r["reblurred"]
        g = obs if obs.shape[2] == reb.shape[2] else obs.mean(axis=2, keepdims=True)
        row = {k: v for k, v in r.items() if k not in ("changes", "unknown", "reblurred")}
        row["psnr_db"] = psnr(reb, g, keep)
        row["scored"] = float(keep.mean())
        if truth is not None:
            row["recall"] = float(np.count_nonzero(r["changes"] & truth)) / max(
                int(np.count_nonzero(truth)), 1)
            row["false_alarms"] = float(np.count_nonzero(r["changes"] & ~truth)) / max(
                int(np.count_nonzero(~truth)), 1)
        out.append(row)
    return out


def compare(name: str, ref: Path, obs: Path, old: Path, repeat: int = 2) -> list[dict]:
    """Rows of one pair: ``repeat`` runs of the checkout at ``old`` and of this one,
    alternately (old first)."""
    truth_p = ref.parent / "truth.tif"
    truth = tifffile.imread(truth_p) > 0 if truth_p.exists() else None
    runs, sides = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(repeat):
            for side, src in (("old", old), ("new", None)):
                runs.append(detect(ref, obs, Path(tmp) / f"{side}{i}", src))
                sides.append(side)
    rows = score(runs, _image(obs), truth)
    for row, side in zip(rows, sides, strict=True):
        row.update(pair=name, side=side)
    return rows


def table(rows: list[dict], labels: dict[str, str]) -> str:
    """Markdown: per pair and side, the mean of its runs."""
    out = ["| pair | code | total (s) | estimate (s) | reblur_decide (s) | flagged % | "
           "reblur PSNR (dB) | recall | false alarms % |", "|---|---|---|---|---|---|---|---|---|"]
    pairs = list(dict.fromkeys(r["pair"] for r in rows))
    for p in pairs:
        for side in ("old", "new"):
            rs = [r for r in rows if r["pair"] == p and r["side"] == side]
            mean = {k: float(np.mean([r[k] for r in rs])) for k in rs[0]
                    if isinstance(rs[0][k], float)}
            rec = f"{mean['recall']:.4f}" if "recall" in mean else "-"
            fa = f"{100 * mean['false_alarms']:.4f}" if "false_alarms" in mean else "-"
            out.append(f"| {p} | {labels[side]} | {mean['seconds']:.2f} | "
                       f"{mean['estimate_s']:.2f} | {mean['decide_s']:.2f} | "
                       f"{100 * mean['flagged']:.3f} | "
                       f"{mean['psnr_db']:.3f} | {rec} | {fa} |")
    return "\n".join(out)


def main(old: Path, label: str, repeat: int = 2, only: str = "") -> str:
    """Run every pair (names starting with ``only``); the markdown section."""
    from benchmarks.gram_work import pairs

    for src in (old, None):  # both compiled, or the one that is not pays ~0.15 s a run
        compile_package(src)
    rows = []
    for name, ref, obs in pairs():
        if not name.startswith(only):
            continue
        for r in compare(name, ref, obs, old, repeat):
            print(json.dumps(r), flush=True)
            rows.append(r)
    labels = {"old": label, "new": commit()}
    load = os.getloadavg()[0]
    return ("## Two checkouts, alternately, at 1 MP (`python -m benchmarks.ab`)\n\n"
            f"`reblur detect` in a fresh process per run, {labels['old']} and "
            f"{labels['new']} alternately, {repeat} runs each (means)"
            + (f", the pairs whose name starts with `{only}` (`--only`)" if only else "")
            + ". PSNR of "
            "`reblurred.tif` against the observation over the pixels every run of the pair "
            "left known and unflagged; recall and false alarms (flagged unchanged pixels) "
            "against the test bed's truth.\n\n"
            f"{table(rows, labels)}\n\n- host load average at the end: {load:.1f} on "
            f"{os.cpu_count()} cores\n")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(prog="python -m benchmarks.ab")
    ap.add_argument("--src", type=Path, required=True, help="the other checkout's src folder")
    ap.add_argument("--label", default=None, help="its name (default: the folder)")
    ap.add_argument("--repeat", type=int, default=2, help="runs of each checkout per pair")
    ap.add_argument("--only", default="", help="pairs whose name starts with this")
    a = ap.parse_args()
    from benchmarks.run import write_section

    body = main(a.src, a.label or str(a.src), a.repeat, a.only)
    write_section("ab", body)
    print(body)
