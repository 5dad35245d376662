"""Alignment where one homography is not enough: real GoPro frame averages and test-bed pairs
with lens distortion or two-plane parallax (issue #29), before and after.

``python -m benchmarks.alignment [--gopro quick|all|none] [--cases lens3,...]`` runs
:func:`reblur.detect_changes` with its defaults (in a fresh process per pair, importing
reblur from this checkout or from ``--src OTHER/src``), prints two markdown tables and
records the rows in ``docs/alignment_runs.json`` under ``--label`` (rows of other labels are
kept, so a run with ``--src OLD/src --label OLD`` and one of this checkout give before and
after side by side).

**GoPro k-frame averages.**  Reference = sharp frame ``c`` of ``GOPR0477_11_00``, observation
= mean of the ``k`` frames around it (:func:`reblur.testbed.gopro_pair`), for every ``c``
the window fits and ``k = 4..16`` (``--gopro all``, 195 pairs), or the two pairs of issue
#29 (:data:`QUICK`, frames 9-16 and 17-24 against frame 12; ``--gopro quick``, the
default).  Per pair: ran / refused (an
``AlignmentError``, the library's refusal) / crashed (any other exception: the run died),
with the one-line reason; the flagged share; and the flagged share OUTSIDE the moving
people.  There is no ground truth for them, so the moving area is derived from the raw
frames alone (:func:`moving_area`):

1. every frame of the window is registered to frame ``c`` (:func:`_register`: a trimmed
   brute-force shift search, then OpenCV's ECC with the worst-explained pixels masked).
   The model is a translation: the court's texture is too weak for a homography (ECC
   homographies on these frames moved the image centre by up to 8 px between 1/4 and 1/2
   size, and an unmasked one followed the player), and a shift leaves the floor's
   residual at the level of its faint texture, which step 2 tolerates;
2. the per-pixel temporal standard deviation of the registered frames and frame ``c``
   (gray, [0, 1]), on the pixels every frame covers, is thresholded at
   ``0.04 + 1.0 x |grad I_c|`` (the gradient term allows 1 px of residual
   misregistration: rolling shutter, the court's relief);
3. components under 400 px are dropped, the rest closed with a 31 px disc, holes filled,
   dilated by 9 px;
4. the mask (in frame ``c``) is carried into every frame of the window and frame ``c``
   by its registration and the union taken: the moving people's footprint in the average
   and the reference, smeared by the camera's own motion as the blur smears them.

"Outside" is the known pixels (not reblur's unknown) more than 3 px from that area
(:func:`benchmarks.failure_modes._scores`' false-alarm rate with the area as the truth).

**Test-bed geometry** (:data:`reblur.testbed.GEOMETRY_CASES`, LEVIR ``test_7``, 1 MP, 8 bit,
1 DN): ``lens3`` (barrel, corners 3 px), ``pincushion3``, ``lens3_changes``, ``parallax``
(a roof 4 px of viewpoint parallax from the ground) and ``parallax_changes``.  Per pair: the
alignment method; the geometry residual, RMS and max over a 16 px lattice of known points
off the occlusion edges, of where reblur says an observation pixel comes from (its final
base homography composed with its poses, :meth:`MotionEstimate.source_points`; when the
result has a ``field`` with ``displacement(xy) -> (m, 2)``, the pixel ``p`` is modelled by
the reblurred reference at ``p + d(p)``, so the poses act on ``p + d(p)``) against the
test bed's truth (:meth:`reblur.testbed.SceneGeometry.centroid`); the floor, what the
best single homography leaves on the same points (:func:`reblur.testbed.best_homography`);
the residual on the occlusion edges apart; the false-alarm rate outside the changes and the
occlusion edges (each grown by 3 px); recall and JC of pasted changes; the time.
``--cases quick`` (the default) runs the two with pasted changes, ``--cases all`` the five.

``--coarse [--cross]`` prints the former table instead: the pipeline's coarse alignment on
the six LEVIR-CD / WHU-CD development pairs against the true homography (``--cross``: the
30 unrelated pairs, which must all be refused).
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import REPO, commit, load_runs, save_runs

RUNS = REPO / "docs" / "alignment_runs.json"
#: ``(reference, first frame, k)`` of ``--gopro quick``: the two pairs issue #29 reports
#: failing, frames 9-16 against frame 12 (a crash) and 17-24 against 12 (an
#: AlignmentError; not a centred window).  Each takes one to two minutes on the shared
#: 2-core machine: ``--gopro all`` is the sweep.
QUICK = ((12, 9, 8), (12, 17, 8))
K_RANGE = range(4, 17)
CASES = ("lens3", "pincushion3", "lens3_changes", "parallax", "parallax_changes")
QUICK_CASES = ("lens3_changes", "parallax_changes")
LATTICE = 16  # px between the geometry's scoring points
BOUNDARY = 3  # px around a change or an occlusion edge counted neither way
WORKER_TIMEOUT = 1800


# ---------------------------------------------------------------- worker (any checkout)


def _worker(inp: Path, out: Path) -> None:
    """Run ``reblur.detect_changes`` with its defaults on the pair in ``inp`` (npz:
    ``reference``, ``observed``, ``points``) and write what the scores need to ``out``.

    Runs in its own process with whatever ``reblur`` is on the path (this checkout's or
    ``--src``'s), so it imports nothing else from the project."""
    import reblur

    data = np.load(inp)
    pts = data["points"]
    t = time.perf_counter()
    res: dict = {}
    try:
        r = reblur.detect_changes(data["reference"], data["observed"])
    except Exception as exc:  # noqa: BLE001 - a refusal or a crash is this row's figure
        kind = "refused" if type(exc).__name__ == "AlignmentError" else "crashed"
        line = (str(exc).strip().splitlines() or [""])[0]
        res = dict(status=kind, reason=f"{type(exc).__name__}: {line}"[:300])
        np.savez(out, meta=json.dumps(res | {"seconds": time.perf_counter() - t}))
        return
    seconds = time.perf_counter() - t
    field = getattr(r, "field", None)
    modelled = pts
    if field is not None and hasattr(field, "displacement") and len(pts):
        modelled = pts + np.asarray(field.displacement(pts), dtype=np.float64)
    source = (r.motion.source_points(modelled, r.alignment) if len(pts)
              else np.zeros((0, 2)))
    align = r.decision.get("alignment", {})
    res = dict(status="ran", seconds=seconds, method=align.get("method", "?"),
               refined=bool(align.get("refinement", {}).get("applied", False)),
               field=field is not None)
    np.savez_compressed(out, meta=json.dumps(res), change=r.change, unknown=r.unknown,
                        source=source, alignment=np.asarray(r.alignment, dtype=np.float64))


def run_reblur(reference: np.ndarray, observed: np.ndarray, points: np.ndarray,
               src: Path | None) -> dict:
    """:func:`_worker` in a fresh process (reblur from ``src`` when given); the row's
    ``status``, ``reason`` / ``seconds`` / ``method`` and the arrays of a run."""
    with tempfile.TemporaryDirectory(prefix="reblur-align-") as tmp:
        inp, out = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(inp, reference=reference, observed=observed, points=points)
        env = dict(os.environ, PYTHONPATH=str(src)) if src is not None else None
        cmd = [sys.executable, "-m", "benchmarks.alignment", "--worker", str(inp), str(out)]
        try:
            p = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, env=env,
                               timeout=WORKER_TIMEOUT)
        except subprocess.TimeoutExpired:
            return {"status": "crashed", "reason": f"no result in {WORKER_TIMEOUT} s"}
        if p.returncode or not out.exists():
            last = (p.stderr.strip().splitlines() or [f"exit {p.returncode}"])[-1]
            return {"status": "crashed", "reason": f"worker died: {last}"[:300]}
        with np.load(out) as z:
            res = json.loads(str(z["meta"]))
            res.update({k: z[k] for k in z.files if k != "meta"})
    return res


# ---------------------------------------------------------------- GoPro


def _gray(rgb: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0


def _shrunk(image: np.ndarray, scale: float) -> np.ndarray:
    import cv2

    return cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)


def _trimmed(d: np.ndarray, keep: float = 0.6) -> float:
    """Mean of the smallest ``keep`` share of ``d`` (blind to a moving person's pixels)."""
    d = d.ravel()
    n = max(int(keep * d.size), 1)
    return float(np.partition(d, n - 1)[:n].mean())


def _shift_search(a: np.ndarray, b: np.ndarray, reach: int) -> tuple[int, int]:
    """Integer ``(dx, dy)`` with ``b(x + d) ~ a(x)``: the trimmed mean absolute difference,
    brute force over ``|dx|, |dy| <= reach``."""
    h, w = a.shape
    best = (np.inf, 0, 0)
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            y0, y1, x0, x1 = max(0, -dy), min(h, h - dy), max(0, -dx), min(w, w - dx)
            e = _trimmed(np.abs(a[y0:y1, x0:x1] - b[y0 + dy:y1 + dy, x0 + dx:x1 + dx]))
            best = min(best, (e, dx, dy))
    return best[1], best[2]


def _register(template: np.ndarray, image: np.ndarray) -> np.ndarray:
    """Homography ``W`` with ``image(W x) ~ template(x)`` (full-size pixels), robust to the
    moving people: a brute-force trimmed search of the shift at 1/8 size (up to 96 px),
    then ECC (OpenCV, translation) at 1/4 size, twice, each time masking the 40 % of
    pixels that the previous estimate explains worst."""
    import cv2

    dx, dy = _shift_search(_shrunk(template, 0.125), _shrunk(image, 0.125), 12)
    s = 0.25
    a, b = _shrunk(template, s), _shrunk(image, s)
    w = np.array([[1, 0, 2 * dx], [0, 1, 2 * dy]], np.float32)  # 1/8 -> 1/4 size
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 60, 1e-5)
    for _ in range(2):
        moved = cv2.warpAffine(b, w, a.shape[::-1], flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        res = cv2.GaussianBlur(np.abs(moved - a), (0, 0), 3)
        mask = (res < np.percentile(res, 60)).astype(np.uint8)
        try:
            _, w = cv2.findTransformECC(a, b, w, cv2.MOTION_TRANSLATION, crit, mask, 5)
        except cv2.error:  # no convergence: keep the last estimate
            break
    return np.array([[1, 0, w[0, 2] / s], [0, 1, w[1, 2] / s], [0, 0, 1.0]])


_REGISTERED: dict[tuple[int, int], np.ndarray] = {}


def _registration(centre: int, frame: int) -> np.ndarray:
    """Frame ``frame``'s homography to frame ``centre`` (cached for the sweep)."""
    from reblur.testbed import gopro_frame

    key = (centre, frame)
    if key not in _REGISTERED:
        _REGISTERED[key] = np.eye(3) if frame == centre else _register(
            _gray(gopro_frame(centre)), _gray(gopro_frame(frame)))
    return _REGISTERED[key]


def moving_area(centre: int, frames: list[int]) -> np.ndarray:
    """The moving people's footprint in the average of ``frames`` against frame ``centre``
    (see the module's docstring for the rule); boolean ``(720, 1280)``."""
    import cv2
    import scipy.ndimage as ndi

    from reblur.testbed import gopro_frame

    ref = _gray(gopro_frame(centre))
    h, w = ref.shape
    stack, covered = [], np.ones((h, w), bool)
    seen = sorted(set(frames) | {centre})  # the reference's own people are a change too
    for i in seen:
        wi = _registration(centre, i).astype(np.float32)
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        stack.append(cv2.warpPerspective(_gray(gopro_frame(i)), wi, (w, h), flags=flags))
        cov = cv2.warpPerspective(np.ones((h, w), np.uint8), wi, (w, h), flags=flags)
        covered &= cv2.erode(cov, np.ones((5, 5), np.uint8)) > 0
    spread = np.std(np.stack(stack), axis=0)
    gx, gy = (cv2.Sobel(ref, cv2.CV_32F, dx, dy, ksize=3) / 8 for dx, dy in ((1, 0), (0, 1)))
    grad = cv2.GaussianBlur(np.hypot(gx, gy), (0, 0), 1.0)
    mask = covered & (spread > 0.04 + 1.0 * grad)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = np.zeros(n, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= 400
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (31, 31))
    mask = cv2.morphologyEx(keep[lab].astype(np.uint8), cv2.MORPH_CLOSE, disc)
    mask = ndi.binary_fill_holes(mask).astype(np.uint8)
    mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (19, 19)))
    union = np.zeros((h, w), bool)
    for i in seen:  # carried into each frame's own pixels: the footprint in the average
        union |= cv2.warpPerspective(mask, _registration(centre, i).astype(np.float32),
                                     (w, h), flags=cv2.INTER_NEAREST) > 0
    return union


def gopro_set(which: str) -> list[tuple[int, int, int]]:
    """``(reference, first frame, k)`` of ``--gopro``: ``quick``, ``all`` (every centred
    window, :func:`reblur.testbed.gopro_frame_indices`), ``sample`` (k = 4, 8, 12, 16 and
    every fourth centre: 18 of them, about 10 minutes here) or ``none``."""
    from reblur.testbed import N_FRAMES

    if which == "none":
        return []
    if which == "quick":
        return list(QUICK)
    if which in ("all", "sample"):
        ks, step = (K_RANGE, 1) if which == "all" else ((4, 8, 12, 16), 4)
        return [(c, c - k // 2, k) for k in ks
                for c in range(1 + k // 2, N_FRAMES - (k - 1) // 2 + 1, step)]
    raise ValueError(f"--gopro must be quick, sample, all or none, got {which!r}")


def gopro_images(centre: int, first: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The reference frame and the mean of frames ``first .. first + k - 1``
    (:func:`reblur.testbed.gopro_pair` for a centred window; the same mean otherwise)."""
    from reblur.testbed import gopro_frame, gopro_frame_indices, gopro_pair

    if gopro_frame_indices(centre, k)[0] == first:
        return gopro_pair(centre, k)
    acc = sum(gopro_frame(i).astype(np.float64) for i in range(first, first + k))
    return gopro_frame(centre), np.rint(acc / k).astype(np.uint8)


def gopro_row(centre: int, first: int, k: int, src: Path | None) -> dict:
    """One GoPro pair: status, flagged share, flagged share outside the moving area."""
    from benchmarks.failure_modes import _scores

    ref, obs = gopro_images(centre, first, k)
    frames = list(range(first, first + k))
    row = {"kind": "gopro", "centre": centre, "k": k, "frames": [frames[0], frames[-1]]}
    res = run_reblur(ref, obs, np.zeros((0, 2)), src)
    row.update({key: res[key] for key in ("status", "reason", "seconds", "method")
                if key in res})
    moving = moving_area(centre, frames)
    row["moving_share"] = float(moving.mean())
    if res["status"] == "ran":
        s = _scores(res["change"], res["unknown"],
                    {"truth": moving, "valid": np.ones_like(moving)})
        row.update(flagged=s["flagged"], flagged_outside=s["far"],
                   moving_flagged=s.get("recall"))
    return row


# ---------------------------------------------------------------- test-bed geometry


def _testbed_fingerprint() -> str:
    """Hash of the test bed's sources: a cached pair is reused only while they hold."""
    import reblur.testbed as tb

    h = hashlib.sha1()
    for p in sorted(Path(tb.__file__).parent.glob("*.py")):
        h.update(p.read_bytes())
    return h.hexdigest()[:12]


def case_truth(case: str, cache: Path) -> dict:
    """A geometry case's pair and truth (made once, kept in ``cache``): images, change
    truth, validity, the occlusion edges grown by 3 px, the scoring lattice (valid points)
    with its true centroids, and the best single homography's residual there."""
    import reblur.testbed as tb

    path = cache / f"{case}_{_testbed_fingerprint()}.npz"
    if path.exists():
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    pair = tb.failure_pair(case)
    h, w = pair.valid.shape
    occ = pair.occlusion
    band = pair.geometry.occlusion_window((0, h, 0, w), band_px=BOUNDARY) if occ.any() else occ
    ys, xs = np.mgrid[LATTICE // 2:h:LATTICE, LATTICE // 2:w:LATTICE]
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    pts = pts[pair.valid[ys.ravel(), xs.ravel()]]
    edge = band[pts[:, 1].astype(int), pts[:, 0].astype(int)]
    floor = tb.homography_residual(pair.geometry, pts[~edge],
                                   tb.best_homography(pair.geometry, pts[~edge]))
    t = dict(reference=pair.reference, observed=pair.observed, truth=pair.truth,
             valid=pair.valid, band=band, points=pts, centroid=pair.geometry.centroid(pts),
             edge=edge, floor=np.hypot(*floor.T))
    cache.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **t)
    return t


def _rms(e: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(e ** 2))) if e.size else None


def testbed_row(case: str, src: Path | None, cache: Path) -> dict:
    """One geometry case: method, residual against the truth, false alarms, recall, time."""
    from benchmarks.failure_modes import _scores

    t = case_truth(case, cache)
    row = {"kind": "testbed", "case": case, "floor_rms_px": _rms(t["floor"]),
           "floor_max_px": float(t["floor"].max())}
    res = run_reblur(t["reference"], t["observed"], t["points"], src)
    row.update({key: res[key] for key in ("status", "reason", "seconds", "method", "refined",
                                          "field") if key in res})
    if res["status"] != "ran":
        return row
    pts = t["points"].astype(int)
    known = ~res["unknown"][pts[:, 1], pts[:, 0]]
    err = np.hypot(*(res["source"] - t["centroid"]).T)
    on, off = known & t["edge"], known & ~t["edge"]
    row.update(residual_rms_px=_rms(err[off]), residual_max_px=float(err[off].max()),
               edge_rms_px=_rms(err[on]), points=int(off.sum()))
    s = _scores(res["change"], res["unknown"],
                {"truth": t["truth"], "valid": t["valid"] & ~t["band"]})
    row.update(far=s["far"], flagged=s["flagged"], recall=s.get("recall"), jc=s.get("jc"))
    return row


# ---------------------------------------------------------------- tables and the record


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.2f} %"


def _px(v) -> str:
    return "-" if v is None else f"{v:.2f}"


def _status(r: dict) -> str:
    if r.get("status") == "ran":
        return "ran"
    return f"{r.get('status', '?')}: {r.get('reason', '')[:90]}"


def gopro_table(rows: list[dict]) -> str:
    lines = ["| label | c | k | frames | result | flagged | flagged outside moving area "
             "| moving area | s |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['label']} | {r['centre']} | {r['k']} | {r['frames'][0]}-"
                     f"{r['frames'][1]} | {_status(r)} | {_pct(r.get('flagged'))} | "
                     f"{_pct(r.get('flagged_outside'))} | {_pct(r['moving_share'])} | "
                     f"{r.get('seconds', 0):.0f} |")
    ran = [r for r in rows if r.get("status") == "ran"]
    for label in dict.fromkeys(r["label"] for r in rows):
        mine = [r for r in rows if r["label"] == label]
        ok = [r for r in ran if r["label"] == label]
        worst = max((r["flagged_outside"] for r in ok), default=None)
        lines.append(f"\n{label}: {len(ok)} of {len(mine)} ran, "
                     f"{sum(r['status'] == 'refused' for r in mine)} refused, "
                     f"{sum(r['status'] == 'crashed' for r in mine)} crashed; flagged outside "
                     f"the moving area at most {_pct(worst)}.")
    return "\n".join(lines)


def _median(v: list[float]) -> float | None:
    return float(np.median(v)) if v else None


def gopro_summary(rows: list[dict]) -> str:
    """Per label and ``k``: pairs, ran / refused / crashed, and the flagged share and the
    flagged share outside the moving area (median and worst, with the worst pair)."""
    lines = ["| label | k | pairs | ran | refused | crashed | flagged median / max "
             "| outside moving area median / max | worst pair (c) | s median |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for label in dict.fromkeys(r["label"] for r in rows):
        for k in sorted({r["k"] for r in rows if r["label"] == label}):
            mine = [r for r in rows if r["label"] == label and r["k"] == k]
            ok = [r for r in mine if r.get("status") == "ran"]
            flagged = [r["flagged"] for r in ok]
            outside = [r["flagged_outside"] for r in ok]
            worst = max(ok, key=lambda r: r["flagged_outside"]) if ok else None
            lines.append(
                f"| {label} | {k} | {len(mine)} | {len(ok)} | "
                f"{sum(r['status'] == 'refused' for r in mine)} | "
                f"{sum(r['status'] == 'crashed' for r in mine)} | {_pct(_median(flagged))} / "
                f"{_pct(max(flagged, default=None))} | {_pct(_median(outside))} / "
                f"{_pct(max(outside, default=None))} | "
                f"{worst['centre'] if worst else '-'} | "
                f"{_median([r.get('seconds', 0.0) for r in mine]) or 0:.0f} |")
    return "\n".join(lines)


def testbed_table(rows: list[dict]) -> str:
    lines = ["| label | case | result | method | residual RMS / max (px) | one-homography "
             "floor RMS / max | occlusion edges RMS | FAR | recall | JC | s |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        method = r.get("method", "-") + (" + field" if r.get("field") else "")
        lines.append(
            f"| {r['label']} | {r['case']} | {_status(r)} | {method} | "
            f"{_px(r.get('residual_rms_px'))} / {_px(r.get('residual_max_px'))} | "
            f"{_px(r['floor_rms_px'])} / {_px(r['floor_max_px'])} | {_px(r.get('edge_rms_px'))}"
            f" | {_pct(r.get('far'))} | {_px(r.get('recall'))} | {_px(r.get('jc'))} | "
            f"{r.get('seconds', 0):.0f} |")
    return "\n".join(lines)


def _key(r: dict) -> tuple:
    return (r["label"], r["kind"], r.get("case"), r.get("centre"), tuple(r.get("frames", ())))


def record(rows: list[dict], path: Path = RUNS) -> list[dict]:
    """Merge ``rows`` into the saved runs (a row replaces the saved one of the same label,
    kind and pair); return them all."""
    new = {_key(r): r for r in rows}
    kept = [r for r in load_runs(path) if _key(r) not in new]
    runs = kept + rows
    save_runs(path, runs)
    return runs


def _gopro_rows(pairs: list[tuple[int, int, int]], src: Path | None, stamp: dict,
                jobs: int, save: bool) -> list[dict]:
    """The GoPro rows of ``pairs``, ``jobs`` workers at a time; each row is printed and
    (with ``save``) recorded as soon as it is done, so a sweep that is stopped keeps what it
    measured and ``--resume`` goes on from there."""
    from concurrent.futures import ThreadPoolExecutor, as_completed

    rows = []
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        futures = [pool.submit(gopro_row, c, first, k, src) for c, first, k in pairs]
        for f in as_completed(futures):
            rows.append(f.result() | stamp)
            print(json.dumps(rows[-1]), flush=True)
            if save:
                record([rows[-1]])
    return rows


def main(gopro: str = "quick", cases: tuple[str, ...] = QUICK_CASES, src: Path | None = None,
         label: str | None = None, cache: Path | None = None, save: bool = True,
         jobs: int = 1, resume: bool = False) -> str:
    """Run the selected rows; record them; return the two tables (all saved labels).

    ``jobs`` GoPro pairs run at once (each in its own process); with ``resume`` the GoPro
    pairs already recorded under ``label`` are not run again."""
    cache = cache or Path(tempfile.gettempdir()) / "reblur-alignment-cases"
    label = label or (str(src) if src is not None else commit())
    stamp = dict(label=label, date=datetime.date.today().isoformat())
    rows = []
    for name in cases:
        rows.append(testbed_row(name, src, cache) | stamp)
        print(json.dumps(rows[-1]), flush=True)
    pairs = gopro_set(gopro)
    done = {(r["centre"], r["frames"][0], r["k"]) for r in load_runs(RUNS)
            if resume and r["kind"] == "gopro" and r["label"] == label}
    gopro_rows = _gopro_rows([p for p in pairs if p not in done], src, stamp, jobs, save)
    runs = record(rows) if save and rows else (load_runs(RUNS) if save else rows + gopro_rows)
    shown_pairs = set(pairs)
    shown = [r for r in runs if (r["kind"] == "testbed" and r["case"] in cases) or (
        r["kind"] == "gopro" and (r["centre"], r["frames"][0], r["k"]) in shown_pairs
        and (r["label"] == label or not resume))]
    return ("### Test-bed geometry\n\n" + testbed_table(
        sorted([r for r in shown if r["kind"] == "testbed"], key=lambda r: (r["case"],)))
            + "\n\n### GoPro k-frame averages\n\n" + (gopro_summary if len(pairs) > 40
                                                         else gopro_table)(
        sorted([r for r in shown if r["kind"] == "gopro"],
               key=lambda r: (r["k"], r["centre"], r["frames"][0]))))


# ---------------------------------------------------------------- the coarse table


def _pairs():
    from benchmarks.quality import _rgb
    from experiments.common import dev_pairs
    from reblur.grid import pose_homography
    from reblur.simulate import make_pair

    out = []
    for i, (name, before, after, _) in enumerate(dev_pairs()):
        p = make_pair(_rgb(before), _rgb(after), rng=100 + i, n_changes=0, moving=False,
                      shake=dict(t_max=6.0, rz_max=0.8),
                      viewpoint=dict(max_shift_frac=0.03, max_rot_deg=3.0), noise_sigma=1 / 255)
        H = pose_homography(*p.path.poses.mean(axis=0), center=p.path.center) @ p.viewpoint
        out.append((name, p.reference, p.observed, H / H[2, 2]))
    return out


def _corner_error(H: np.ndarray, H_true: np.ndarray, shape) -> float:
    from reblur.grid import map_points

    h, w = shape[:2]
    c = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)
    return float(np.hypot(*(map_points(H, c) - map_points(H_true, c)).T).max())


def alignment_table(cross: bool = False) -> list[str]:
    """The coarse alignment on the six development pairs (``--coarse``): accepted or
    refused, method, largest corner error against the true homography, time."""
    from reblur.align import AlignmentError
    from reblur.pipeline import align_coarse

    pairs = _pairs()
    lines = ["| pair | result | method | corner error (px) | gradient blocks | time (s) |",
             "|---|---|---|---|---|---|"]
    for name, ref, obs, H_true in pairs:
        t = time.perf_counter()
        try:
            a = align_coarse(ref, obs)
        except AlignmentError as e:
            parts = str(e).split("; fallback: ")
            reason = next((r for r in parts if "gradient" in r), parts[0])
            lines.append(f"| {name} | refused: {reason} | | | | {time.perf_counter() - t:.1f} |")
            continue
        lines.append(f"| {name} | aligned | {a.method} | "
                     f"{_corner_error(a.H, H_true, ref.shape):.2f} | {a.n_blocks} | "
                     f"{time.perf_counter() - t:.1f} |")
    if cross:
        accepted = []
        for i, (name, ref, _, _) in enumerate(pairs):
            for j, (other, _, obs, _) in enumerate(pairs):
                if i != j:
                    try:
                        a = align_coarse(ref, obs)
                        accepted.append(f"{name} x {other} ({a.method})")
                    except AlignmentError:
                        pass
        n = len(pairs) * (len(pairs) - 1)
        lines += ["", f"Unrelated pairs (each reference with another pair's observation): "
                      f"{n - len(accepted)} of {n} refused"
                      + (f"; accepted: {', '.join(accepted)}" if accepted else ".")]
    return lines


def _cases(text: str) -> tuple[str, ...]:
    names = tuple(s for s in text.split(",") if s) if text not in ("all", "quick") else (
        CASES if text == "all" else QUICK_CASES)
    bad = [n for n in names if n not in CASES]
    if bad:
        raise argparse.ArgumentTypeError(f"unknown case(s) {bad}; choose from {CASES}")
    return names


if __name__ == "__main__":
    if sys.argv[1:2] == ["--worker"]:
        _worker(Path(sys.argv[2]), Path(sys.argv[3]))
        sys.exit(0)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gopro", default="quick", choices=("quick", "sample", "all", "none"),
                    help="GoPro pairs: issue #29's two, k = 4 / 8 / 12 / 16 at every fourth "
                         "centre, every centred window with k = 4..16, or none")
    ap.add_argument("--cases", type=_cases, default=QUICK_CASES,
                    help=f"test-bed cases, comma-separated, 'quick' or 'all' ({','.join(CASES)})")
    ap.add_argument("--src", type=Path, default=None, help="another checkout's src folder")
    ap.add_argument("--label", default=None, help="name of the rows (default: the commit)")
    ap.add_argument("--cache", type=Path, default=None, help="folder of the made pairs")
    ap.add_argument("--no-save", action="store_true", help="do not record the rows")
    ap.add_argument("--jobs", type=int, default=1, help="GoPro pairs run at once")
    ap.add_argument("--resume", action="store_true",
                    help="skip the GoPro pairs already recorded under --label")
    ap.add_argument("--coarse", action="store_true",
                    help="the coarse alignment on the development pairs instead")
    ap.add_argument("--cross", action="store_true", help="with --coarse: unrelated pairs too")
    a = ap.parse_args()
    if a.coarse:
        print("\n".join(alignment_table(cross=a.cross)))
    else:
        print(main(a.gopro, a.cases, a.src, a.label, a.cache, not a.no_save, a.jobs, a.resume))
