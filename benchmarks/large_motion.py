"""Motion across very large images: pose grid sized to the image, windows spread over it.

``python -m benchmarks.large_motion`` prints a markdown section.  The scene is a
:class:`reblur.simulate.MosaicScene` of the six real LEVIR/WHU images (grayscale, each cell
upsampled to ``cell`` px), computed window by window: the full image is never in memory, so
gigapixel geometries cost only what the estimation windows cost.  The observation is blurred
along a smooth camera path (roll ``rz`` about the FULL image centre, translation), no noise,
and is also generated window by window.  Weights are estimated on 500 x 500 windows (the
timing rows: the size the pipeline picks for four windows), then windows the estimate never
saw are reblurred and compared with their true blur.
"""

from __future__ import annotations

import argparse
import json
import resource
import time

import numpy as np

from benchmarks.common import DATA, REPO, commit, load_runs, peak_rss_mb, psnr, run_case, save_runs

S = 500
MARGIN = 300
#: Every timing run (each fresh process of every series of ``main``), with its commit and
#: start time: this VM's speed drifts (its host backs fresh memory at a speed that varies
#: within minutes), so the table's series is one sample; the earlier ones stay in view.
RUNS = REPO / "docs" / "large_motion_runs.json"
#: The fields of a timing run kept in :data:`RUNS`.
_KEEP = ("H", "W", "time_s", "synthesis_s", "sys_s", "user_s", "peak_rss_mb", "unseen")


def _scene(rows: int, cols: int, cell: int):
    import cv2

    from reblur.simulate import MosaicScene

    files = sorted((DATA / "levir_whu_1024").glob("samples_*/*/*.png"))
    files = [f for f in files if f.parent.name in ("A", "prev")]
    ims = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
    return MosaicScene(ims, cell, rows, cols, rng=0)


def layouts(H: int, W: int, margin: int = MARGIN,
            side: int = S) -> dict[str, list[tuple[int, int, int, int]]]:
    """Estimation windows of ``side`` px, centred where the ``S``-px windows of the issue's
    table are."""
    lo, hy, hx = margin, H - margin - S, W - margin - S
    d = (S - side) // 2
    out = {
        "one central window (paper)": [(H // 2 - S // 2, W // 2 - S // 2, S, S)],
        "two opposite corners": [(lo, lo, S, S), (hy, hx, S, S)],
        "four corners": [(lo, lo, S, S), (hy, hx, S, S), (lo, hx, S, S), (hy, lo, S, S)],
    }
    return {k: [(y + d, x + d, side, side) for y, x, _, _ in v] for k, v in out.items()}


def pipeline_side(windows: int) -> int:
    """Side (px) of the spread windows the pipeline picks for ``windows`` windows."""
    from reblur.select import SelectParams, spread_side

    p = SelectParams(windows=windows)
    return spread_side(p) * p.unit


def unseen_windows(H: int, W: int, margin: int = MARGIN):
    return [(H - margin - S, W // 2 - S // 2, S, S), (margin, W // 2 - S // 2, S, S),
            (H // 2 - S // 2, margin, S, S)]


def pose_margin(H: int, W: int, rz_max: float = 3.0, t_max: int = 12) -> int:
    """Distance from the border a window needs so that every pose of the grid reads real
    pixels: a roll of ``rz_max`` about the centre moves a corner by ``radius x angle``."""
    return int(np.ceil(np.hypot(H, W) / 2 * np.deg2rad(rz_max))) + t_max + 20


def evaluate(scene, obs, est, boxes, base=None) -> list[float]:
    """PSNR of the reblurred reference on windows (tile-local reblur, as the pipeline does);
    ``base``: the homography the pose grid acts after (a pipeline result's alignment)."""
    from reblur.tiled import SparsePoses, reblur_tile

    poses = SparsePoses(est.weights, est.grid, base=base)
    out = []
    for b in boxes:
        gt, v = obs.window(b)
        img, ok = reblur_tile(poses, scene, b)
        out.append(psnr(img[:, :, 0], gt, ok & v))
    return out


def run_accuracy(rows: int, cols: int, cell: int, rz: float, t: float, seed: int = 5):
    from reblur import PoseGrid, estimate_motion
    from reblur.simulate import PathBlurredScene, random_camera_path

    scene = _scene(rows, cols, cell)
    H, W = scene.shape
    path = random_camera_path(seed, center=((W - 1) / 2, (H - 1) / 2), t_max=t, rz_max=rz)
    obs = PathBlurredScene(scene, path)
    grids = {
        "paper (0.5 deg step)": PoseGrid.paper((H, W)),
        "sized to image (1 px at the corner)": PoseGrid.from_ranges((H, W), corner_px=1.0),
    }
    rows_out = []
    for gname, grid in grids.items():
        cases = list(layouts(H, W).items())
        side = pipeline_side(4)
        if gname.startswith("sized") and side != S:
            cases.append((f"four corners, {side} px (the pipeline's size for four)",
                          layouts(H, W, side=side)["four corners"]))
        for lname, boxes in cases:
            t0 = time.perf_counter()
            est = estimate_motion(scene, obs, grid, boxes=boxes)
            dt = time.perf_counter() - t0
            unseen = evaluate(scene, obs, est, unseen_windows(H, W))
            rows_out.append((gname, lname, dt, float(np.min(est.info["psnr"])), unseen))
    return (H, W), rows_out


class _Timed:
    """An array-like that counts the seconds spent synthesising what is read from it (the
    benchmark's scenes compute every window on demand; a user's file would be read)."""

    def __init__(self, arr, clock: list[float]):
        self.arr, self.clock = arr, clock
        self.shape, self.dtype = arr.shape, arr.dtype

    def __getitem__(self, key):
        t0 = time.perf_counter()
        try:
            return np.asarray(self.arr[key])
        finally:
            self.clock[0] += time.perf_counter() - t0


def run_timing(side: int, windows: int = 4, rz: float = 0.3, t: float = 9.0,
               **kw):
    from reblur import PoseGrid, estimate_motion
    from reblur.simulate import PathBlurredScene, random_camera_path

    # cells of the images' own 1024 px below 8192 px (so 5000 gives 5120 px, 26 MP, the
    # issue's 25 MP row), 2048 px above (10240 px, 105 MP; 32768 px, 1.07 Gpx)
    cell = 1024 if side < 8192 else 2048
    n = int(np.ceil(side / cell))
    scene = _scene(n, n, cell)
    H, W = scene.shape
    path = random_camera_path(5, center=((W - 1) / 2, (H - 1) / 2), t_max=t, rz_max=rz)
    obs = PathBlurredScene(scene, path)
    grid = PoseGrid.from_ranges((H, W), corner_px=1.0)
    m = max(MARGIN, pose_margin(H, W))
    boxes = list(layouts(H, W, m, pipeline_side(windows)).values())[2 if windows == 4 else 1]
    clock = [0.0]
    t0 = time.perf_counter()
    est = estimate_motion(_Timed(scene, clock), _Timed(obs, clock), grid, boxes=boxes, **kw)
    dt = time.perf_counter() - t0
    unseen = evaluate(scene, obs, est, unseen_windows(H, W, m))
    return (H, W), grid, dt, est, unseen, clock[0]


def timing_case(side: int, threads: int | None = None) -> dict:
    """One timing row in this process (run it in a fresh one: peak RSS and kernel time);
    ``threads``: the estimate's BLAS threads (default: the estimate's own default)."""
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    kw = {} if threads is None else {"threads": threads}
    (H, W), grid, dt, est, unseen, synth = run_timing(side, **kw)
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    return dict(H=H, W=W, poses=int(grid.size), step=float(grid.rz[1] - grid.rz[0]),
                time_s=dt, synthesis_s=synth, unseen=[float(u) for u in unseen],
                peak_rss_mb=peak_rss_mb(),
                levels=[{k: v.get(k) for k in ("stride", "side", "n_angles", "n_t", "n_outer",
                                           "n_active")} | {"time_s": round(v["time_s"], 2)}
                        for v in est.info["levels"]],
                sys_s=r1.ru_stime - r0.ru_stime, user_s=r1.ru_utime - r0.ru_utime)


#: Seconds of idle before each timing run: a user's estimate starts cold, and on this VM a
#: process started right after another maps pages the host still backs (the first run of
#: a back-to-back series was the slow one: docs/NOTES.md, "Eleventh stop"), while 5 s of
#: idle suffice for the host to take them back (``python -m benchmarks.first_touch``).
IDLE_S = 10.0


def main(timing_sides=(5000, 10000, 32000), repeats: int = 5, idle: float = IDLE_S) -> str:
    """The accuracy table, then the timing rows: each size in ``repeats`` fresh processes,
    each after ``idle`` seconds without work, reported as the median run with the range of
    the times (this VM's speed drifts by +-15 % within the hour: one sample says little)."""
    lines = [
        "## Motion across very large images (grid sized to the image, spread windows)",
        "",
        "`python -m benchmarks.large_motion` — mosaic of the 6 real LEVIR/WHU images (gray, "
        "each upsampled to 2150 px), 6450 x 6450 (41.6 MP), camera path with 0.3 deg of roll "
        "and 9 px of translation about the image centre, not on any grid, no noise. Weights "
        "from 500 x 500 windows (unless the row says otherwise); PSNR of three 500 x 500 "
        "windows the estimate never saw (bottom centre, top centre, left centre).",
        "",
        "| grid | estimation windows | time (s) | fit on own windows (dB, worst) "
        "| unseen windows (dB) |",
        "|---|---|---|---|---|",
    ]
    (H, W), rows = run_accuracy(3, 3, 2150, 0.3, 9.0)
    for gname, lname, dt, fit, unseen in rows:
        lines.append(
            f"| {gname} | {lname} | {dt:.1f} | {fit:.1f} | "
            + ", ".join(f"{u:.1f}" for u in unseen) + " |"
        )
    lines += [
        "",
        f"Estimation time at large geometries (four {pipeline_side(4)} x {pipeline_side(4)} "
        "windows near the corners, the size the pipeline picks for four windows, as far "
        "out as every pose of the +-3 deg grid allows; grid sized to the image, coarse-to-fine "
        "over the roll angles; the image itself is never loaded). Target (issue: large "
        "images): <= 5 s at 1 Gpx.  Each row in a fresh process (BLAS threads: the "
        "default, the available cores); peak RSS and kernel time are the process's: they "
        "also cover the scene's synthesis (window by window as the estimate reads it, inside "
        "its time as file reads would be) and the unseen windows' evaluation after it; "
        "kernel time is mostly page faults of fresh memory "
        "(`python -m benchmarks.first_touch`). The synthesis column is the part of the "
        "time spent computing the scene's windows as the estimate reads them (a file "
        f"read in a real run). Each size runs {repeats} times, each in a fresh process "
        f"started after {idle:.0f} s of idle (a cold start: on this VM the host takes back "
        "freed memory within seconds, and a process started right after another runs "
        "faster); the row is the median run, with the range of the times. Every run is "
        "kept in "
        "`docs/large_motion_runs.json` with its commit and the start of its series; the "
        "line under the table lists the earlier series of the largest size.",
        "",
        "| image | poses in the grid | roll step (deg) | time (s): median (range) "
        "| of which synthesis (s) | unseen windows (dB) | peak RSS (MB) | kernel time (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    import datetime

    history = load_runs(RUNS)
    series = dict(commit=commit(), started=datetime.datetime.now().isoformat(timespec="minutes"),
                  idle_s=idle)
    for side in timing_sides:
        runs = []
        for _ in range(repeats):
            time.sleep(idle)
            runs.append(run_case("benchmarks.large_motion", "--case", str(side),
                                 timeout=3600, blas_threads=None))
        if any(q["unseen"] != runs[0]["unseen"] for q in runs):
            raise RuntimeError(f"the runs at {side} px disagree: {[q['unseen'] for q in runs]}")
        history += [{k: q[k] for k in _KEEP} | series | dict(side=side) for q in runs]
        save_runs(RUNS, history)
        times = sorted(q["time_s"] for q in runs)
        r = sorted(runs, key=lambda q: q["time_s"])[len(runs) // 2]  # the median run
        H, W = r["H"], r["W"]
        lines.append(
            f"| {H} x {W} ({H * W / 1e6:.0f} MP) | {r['poses']} | {r['step']:.4f} | "
            f"{r['time_s']:.1f} ({times[0]:.1f}-{times[-1]:.1f}) | {r['synthesis_s']:.1f} | "
            + ", ".join(f"{u:.1f}" for u in r["unseen"])
            + f" | {r['peak_rss_mb']:.0f} | {r['sys_s']:.1f} |"
        )
    lines += _earlier(history, series["started"], max(timing_sides))
    return "\n".join(lines) + "\n"


def _earlier(history: list[dict], current: str, side: int, n: int = 6) -> list[str]:
    """One line on the ``n`` latest earlier series of the ``side`` px row: when, commit,
    median time (range) and the median run's kernel time."""
    by: dict[str, list[dict]] = {}
    for r in history:
        if r["side"] == side and r["started"] != current:
            by.setdefault(r["started"], []).append(r)
    cells = []
    for started in sorted(by, reverse=True)[:n]:
        rs = sorted(by[started], key=lambda q: q["time_s"])
        med = rs[len(rs) // 2]
        idle = med.get("idle_s", 0.0)
        cells.append(f"{started.replace('T', ' ')} at {med['commit']}"
                     + (f", {idle:.0f} s idle before each run" if idle else ", back to back")
                     + f": {med['time_s']:.1f} s ({rs[0]['time_s']:.1f}-"
                     f"{rs[-1]['time_s']:.1f}), kernel {med['sys_s']:.1f} s")
    if not cells:
        return []
    H, W = by[next(iter(by))][0]["H"], by[next(iter(by))][0]["W"]
    return ["", f"Earlier series of the {H} x {W} row (`docs/large_motion_runs.json`; median "
            "(range), kernel time of the median run): " + "; ".join(cells) + "."]


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="timing at 25 MP only")
    ap.add_argument("--case", type=int, help="one timing row at this side (JSON)")
    ap.add_argument("--threads", type=int, default=None, help="with --case: BLAS threads")
    a = ap.parse_args()
    if a.case:
        print(json.dumps(timing_case(a.case, a.threads)))
    else:
        print(main((5000,) if a.quick else (5000, 10000, 32000)))
