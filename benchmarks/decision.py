"""Change-decision benchmark on the real development pairs (METHOD.md sec. 6).

``python -m benchmarks.decision`` (from the repo root) builds, for each of the six
LEVIR-CD / WHU-CD pairs (1024 x 1024 RGB, building-change labels):

* a smooth camera path of 32 poses (translations up to 6 px, roll up to 0.5 degree about
  the image centre; seeded per pair),
* the observation: the "after" image blurred along the path (mean of the 32 warps, through
  :func:`reblur.warp.warp_window` and :func:`reblur.grid.pose_homography`),
* the reblurred reference: the "before" image blurred along the TRUE path, so that only the
  decision varies,
* the truth: the label blurred the same way, thresholded at 0.5; unknown pixels (not covered
  by every warp) are excluded from the scores,

then scores the METHOD baseline (per-band least-squares gain/offset + Otsu on the norm of
the difference + 5x5 opening) and :func:`reblur.decide.decide` (plus two variants: the
pixel-level part alone, and with the smooth photometric field), and writes a markdown
report (default ``docs/results/decision.md``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np
from skimage.filters import threshold_otsu

from benchmarks.common import data_dir
from reblur.decide import decide
from reblur.grid import pose_homography
from reblur.metrics import change_metrics
from reblur.warp import warp_window

REPO = Path(__file__).resolve().parents[1]
DATA = data_dir() / "levir_whu_1024"
OUT = REPO / "docs" / "results" / "decision.md"

#: (name, before, after, label) relative to the data directory
PAIRS = [
    (f"LEVIR {n}", f"samples_LEVIR/A/{n}.png", f"samples_LEVIR/B/{n}.png",
     f"samples_LEVIR/label/{n}.png")
    for n in ("test_7", "test_12", "test_102")
] + [
    (f"WHU {n}", f"samples_WHU-CD/prev/{n}.png", f"samples_WHU-CD/curr/{n}.png",
     f"samples_WHU-CD/label/{n}.png")
    for n in ("000121", "000213", "000241")
]

N_POSES = 32
T_MAX = 6.0  # px
RZ_MAX = 0.5  # degrees

METHODS = {
    "baseline": "METHOD baseline: per-band LS gain/offset, Otsu on |difference|, 5x5 opening",
    "pixel": "reblur.decide, region tests off (statistic + threshold + hysteresis + area)",
    "decide": "reblur.decide, defaults (component tree with object tests)",
    "field256": "reblur.decide with the smooth photometric field, field_block=256",
}
SCORES = [("JC", "jaccard"), ("YC", "yule"), ("PCC %", "pcc"), ("precision", "precision"),
          ("recall", "recall"), ("FPR %", "fpr")]


def camera_path(rng: np.random.Generator, n: int = N_POSES) -> np.ndarray:
    """Smooth random path ``(n, 3)`` of ``(tx, ty, rz)``: a smoothed random walk, centred,
    each axis scaled to reach ``T_MAX`` px / ``RZ_MAX`` degrees."""
    walk = np.cumsum(rng.standard_normal((n, 3)), axis=0)
    k = np.hanning(9)
    k /= k.sum()
    walk = np.stack([np.convolve(np.pad(walk[:, i], 4, mode="edge"), k, "valid")
                     for i in range(3)], axis=1)
    walk -= walk.mean(axis=0)
    walk /= np.abs(walk).max(axis=0)
    return walk * np.array([T_MAX, T_MAX, RZ_MAX])


def blur_along(img: np.ndarray, path: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean of the warps of ``img`` along ``path``; valid where every warp is defined."""
    h, w = img.shape[:2]
    centre = ((w - 1) / 2.0, (h - 1) / 2.0)
    acc = np.zeros((h, w, 1 if img.ndim == 2 else img.shape[2]), np.float64)
    valid = np.ones((h, w), bool)
    for tx, ty, rz in path:
        H = pose_homography(tx, ty, rz=rz, center=centre)
        out, v = warp_window(img, H, (0, 0, h, w))
        acc += out
        valid &= v
    acc /= len(path)
    return acc[:, :, 0] if img.ndim == 2 else acc, valid


def load_pair(data: Path, k: int):
    name, before, after, label = PAIRS[k]
    read = lambda p: cv2.imread(str(data / p), cv2.IMREAD_COLOR)[:, :, ::-1]  # noqa: E731
    a = read(before).astype(np.float32) / 255.0
    b = read(after).astype(np.float32) / 255.0
    lab = (cv2.imread(str(data / label), cv2.IMREAD_GRAYSCALE) > 127).astype(np.float32)
    path = camera_path(np.random.default_rng(1000 + k))
    obs, v1 = blur_along(b, path)
    reb, v2 = blur_along(a, path)
    truth, _ = blur_along(lab, path)
    return name, obs.astype(np.float32), reb.astype(np.float32), truth >= 0.5, ~(v1 & v2)


def baseline(obs: np.ndarray, reb: np.ndarray, unknown: np.ndarray) -> np.ndarray:
    """METHOD sec. 6 baseline: per-band gain/offset (least squares), Otsu on the norm of the
    difference over bands, 5x5 opening."""
    known = ~unknown
    diff = np.empty_like(obs)
    for c in range(obs.shape[2]):
        A = np.stack([reb[..., c][known], np.ones(int(known.sum()), np.float32)], axis=1)
        g, o = np.linalg.lstsq(A, obs[..., c][known], rcond=None)[0]
        diff[..., c] = obs[..., c] - (g * reb[..., c] + o)
    d = np.sqrt((diff**2).sum(axis=2))
    mask = (d > threshold_otsu(d[known])) & known
    mask = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, np.ones((5, 5), np.uint8))
    return mask.astype(bool) & known


def run_method(method: str, obs, reb, unknown) -> np.ndarray:
    if method == "baseline":
        return baseline(obs, reb, unknown)
    if method == "pixel":
        return decide(obs, reb, unknown, region_tests=False)[0]
    if method == "decide":
        return decide(obs, reb, unknown)[0]
    if method == "field256":
        return decide(obs, reb, unknown, field_block=256)[0]
    raise ValueError(method)


def _fmt(key: str, v: float) -> str:
    if np.isnan(v):
        return "nan"
    return f"{100 * v:.1f}" if key in ("pcc", "fpr") else f"{v:.3f}"


def report(rows: dict, times: dict, elapsed: float) -> str:
    names = [p[0] for p in PAIRS]
    head = "| pair | method | " + " | ".join(s for s, _ in SCORES) + " |"
    sep = "|" + "---|" * (len(SCORES) + 2)
    lines = [
        "# Change decision on the development pairs",
        "",
        "Generated by `python -m benchmarks.decision` (do not edit by hand).",
        "",
        f"Six 1024 x 1024 RGB pairs (LEVIR-CD, WHU-CD; building-change labels).  Observation:"
        f" the later image blurred along a smooth camera path of {N_POSES} poses (translations"
        f" up to {T_MAX:g} px, roll up to {RZ_MAX:g} degree about the image centre, seed"
        " 1000 + pair index); reblurred reference: the earlier image blurred along the TRUE"
        " path, so only the decision varies.  Truth: the label blurred the same way,"
        " thresholded at 0.5.  Pixels not covered by every warp are unknown and not scored."
        "  PCC and FPR (unchanged pixels flagged) in %.",
        "",
        "Methods:",
        "",
    ]
    lines += [f"- `{m}`: {d}" for m, d in METHODS.items()]
    lines += ["", "## Mean over the six pairs", "", "| method | " +
              " | ".join(s for s, _ in SCORES) + " | s / pair |", "|" + "---|" * (len(SCORES) + 2)]
    for m in METHODS:
        vals = [_fmt(k, float(np.nanmean([rows[n][m][k] for n in names]))) for _, k in SCORES]
        lines.append(f"| {m} | " + " | ".join(vals) + f" | {np.mean(times[m]):.1f} |")
    lines += ["", "## Per pair", "", head, sep]
    for n in names:
        for m in METHODS:
            lines.append(f"| {n} | {m} | " + " | ".join(_fmt(k, rows[n][m][k]) for _, k in SCORES)
                         + " |")
    lines += [
        "",
        "## Reading",
        "",
        "- The labels mark buildings only, while everything that changed in appearance over"
        " the years (new roads, gardens, vegetation, parking lots, parallax along tall"
        " edges) differs too.  On LEVIR test_7 / test_12 the labelled roofs differ *less*"
        " from the earlier image than their unlabelled surroundings (JC < 0.05 for every"
        " method), and on WHU 000241 (a suburb built on a field) roofs, gardens and roads"
        " all changed: object tests there drop roof clusters merged with gardens, and"
        " recall falls.",
        "- The mean Jaccard gain comes mostly from WHU 000213; the false-positive rate falls"
        " on every pair but LEVIR test_102, where it is already ~0.",
        "- Region-level reasoning is what cuts the false alarms: the component tree keeps"
        " compact, object-like regions (solidity >= 0.65, aspect <= 8) and re-examines"
        " networks at stricter levels; compare `pixel` and `decide`.",
        "- The smooth photometric field (`field256`) absorbs real changes as large as its"
        " blocks (WHU 000213: warehouses of 300-400 px built on a field, JC 0.65 -> 0.21);"
        " it is off by default and meant for illumination / haze differences, with blocks"
        " several times the largest change (see tests/test_decide.py).",
        "",
        f"Total run time {elapsed:.0f} s.",
        "",
    ]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA, help="levir_whu_1024 directory")
    ap.add_argument("--out", type=Path, default=OUT, help="markdown report to write")
    args = ap.parse_args(argv)
    if not args.data.is_dir():
        raise SystemExit(f"data directory not found: {args.data} (use --data)")
    t0 = time.perf_counter()
    rows: dict = {}
    times: dict = {m: [] for m in METHODS}
    for k in range(len(PAIRS)):
        name, obs, reb, truth, unknown = load_pair(args.data, k)
        rows[name] = {}
        for m in METHODS:
            t = time.perf_counter()
            mask = run_method(m, obs, reb, unknown)
            times[m].append(time.perf_counter() - t)
            assert not np.any(mask & unknown)
            rows[name][m] = change_metrics(truth, mask, ignore=unknown)
        print(f"{name}: " + ", ".join(f"{m} JC {rows[name][m]['jaccard']:.3f} "
                                      f"FPR {100 * rows[name][m]['fpr']:.1f}%" for m in METHODS),
              flush=True)
    text = report(rows, times, time.perf_counter() - t0)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
