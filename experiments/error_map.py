"""Reblur error map of a large image: one central window (paper) vs spread windows.

The set-up of ``tests/test_large_motion.py`` / ``benchmarks/large_motion.py`` (whose scene,
observation and window layouts are imported from there): a 6450 x 6450 (41.6 MP)
:class:`reblur.simulate.MosaicScene` of the six real LEVIR/WHU images (gray, each upsampled
to 2150 px, 3 x 3 cells, seed 0), observed blurred along a smooth camera path (seed 5, 0.3 deg
of roll and 9 px of translation about the FULL image centre, no noise), both computed window
by window (the full image is never in memory).  Pose weights are estimated from 500 x 500
windows with two configurations:

* A (paper): the 8125-pose grid (``|t| <= 12`` px, ``|rz| <= 3`` deg in 0.5 deg steps) and
  one central window;
* B (reblur's default for large images): the grid sized to the image (one roll step moves
  the farthest pixel by 1 px, solved coarse to fine) and four windows near the corners.

The reference is then reblurred with each estimate on a lattice of ``n x n`` windows of
``side x side`` px (centred on a regular lattice over the whole image) and compared with the
true blurred window (PSNR over the pixels both know).

``python -m experiments.error_map`` writes ``docs/results/error_map.png`` and
``docs/results/error_map.md``; ``--quick`` uses a 4 x 4 lattice.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from benchmarks.large_motion import S, _scene, layouts
from experiments.common import (
    OUT,
    code_version,
    fmt,
    machine,
    md_table,
    pyplot,
    save_figure,
    write_text,
)

CELL, ROWS, COLS = 2150, 3, 3  #: the scene of ``benchmarks/large_motion.py`` (41.6 MP)
PATH_SEED, T_MAX, RZ_MAX = 5, 9.0, 0.3  #: its camera path
SCENE_SEED = 0  #: the seed ``benchmarks.large_motion._scene`` gives ``MosaicScene``
MIN_VALID = 0.5  #: a lattice window is scored when at least this share of it is valid

Box = tuple[int, int, int, int]


def lattice(shape: tuple[int, int], n: int, side: int) -> list[Box]:
    """Windows ``(y0, x0, side, side)`` centred on a regular ``n x n`` lattice over ``shape``.

    Window ``(i, j)`` (row-major in the returned list) is centred on
    ``((i + 1/2) H / n, (j + 1/2) W / n)``, rounded, i.e. in the middle of the ``i, j`` cell
    of an ``n x n`` partition of the image.

    Parameters
    ----------
    shape : (int, int)
        Image size ``(H, W)``.
    n : int
        Windows per row and per column.
    side : int
        Window side in pixels.

    Returns
    -------
    list of (y0, x0, h, w)

    Raises
    ------
    ValueError
        When the windows would overlap (``n * side > min(H, W)``), which would also put some
        outside the image.
    """
    H, W = shape
    if n < 1 or side < 1 or n * side > min(H, W):
        raise ValueError(f"{n} x {n} windows of {side} px do not fit in {H} x {W} disjointly")
    cy = np.rint((np.arange(n) + 0.5) * H / n).astype(int)
    cx = np.rint((np.arange(n) + 0.5) * W / n).astype(int)
    return [(int(y) - side // 2, int(x) - side // 2, side, side) for y in cy for x in cx]


def configurations(shape: tuple[int, int]) -> dict[str, dict]:
    """The two estimation set-ups: ``{key: dict(label, grid, boxes)}``."""
    from reblur import PoseGrid

    H, W = shape
    lay = layouts(H, W)
    return {
        "A": dict(label="paper: 0.5 deg roll step, one central window",
                  grid=PoseGrid.from_ranges(shape, t_max=12, rz_max=3.0, rz_step=0.5),
                  boxes=lay["one central window (paper)"]),
        "B": dict(label="reblur default: grid sized to the image, four spread windows",
                  grid=PoseGrid.from_ranges(shape, corner_px=1.0),
                  boxes=lay["four corners"]),
    }


def window_error(poses, scene, obs, box: Box, truth=None):
    """Reblur one window with ``poses`` and compare it with the true blurred window.

    Parameters
    ----------
    poses : reblur.tiled.SparsePoses
        The estimated weights.
    scene, obs
        Reference (``MosaicScene``) and blurred observation (window by window).
    box : (y0, x0, h, w)
    truth : (ndarray, ndarray), optional
        ``obs.window(box)`` if already computed (shared between estimates).

    Returns
    -------
    psnr : float
        dB over the pixels valid in both (peak 1); NaN when fewer than ``MIN_VALID`` of them.
    valid_share : float
    residual : (h, w) ndarray
        ``|reblurred - truth|``, NaN where not valid.
    """
    from reblur.tiled import reblur_tile

    gt, v = obs.window(box) if truth is None else truth
    img, ok = reblur_tile(poses, scene, box)
    m = ok & v
    res = np.abs(img[:, :, 0].astype(np.float64) - gt)
    res[~m] = np.nan
    share = float(m.mean())
    p = float(10 * np.log10(1.0 / np.mean(res[m] ** 2))) if share >= MIN_VALID else np.nan
    return p, share, res


def run(n: int, side: int, log=print) -> dict:
    """Build the scene, estimate with A and B, and score every lattice window."""
    from reblur import estimate_motion
    from reblur.simulate import PathBlurredScene, random_camera_path
    from reblur.tiled import SparsePoses

    scene = _scene(ROWS, COLS, CELL)
    H, W = scene.shape
    path = random_camera_path(PATH_SEED, center=((W - 1) / 2, (H - 1) / 2), t_max=T_MAX,
                              rz_max=RZ_MAX)
    obs = PathBlurredScene(scene, path)
    cfgs = configurations((H, W))
    for k, c in cfgs.items():
        t0 = time.perf_counter()
        est = estimate_motion(scene, obs, c["grid"], boxes=c["boxes"])
        c["seconds"] = time.perf_counter() - t0
        c["fit"] = [float(x) for x in est.info["psnr"]]
        c["poses"] = SparsePoses(est.weights, est.grid)
        log(f"estimate {k}: {c['seconds']:.1f} s, fit {c['fit']} dB, "
            f"{c['poses'].n_poses} non-zero poses")
    boxes = lattice((H, W), n, side)
    t0 = time.perf_counter()
    for c in cfgs.values():
        c["psnr"], c["share"] = np.full(len(boxes), np.nan), np.zeros(len(boxes))
    for i, b in enumerate(boxes):
        truth = obs.window(b)
        for c in cfgs.values():
            c["psnr"][i], c["share"][i], _ = window_error(c["poses"], scene, obs, b, truth)
        if (i + 1) % n == 0:
            log(f"lattice row {(i + 1) // n}/{n}: {time.perf_counter() - t0:.0f} s")
    map_seconds = time.perf_counter() - t0
    worst = int(np.nanargmin(cfgs["A"]["psnr"]))
    truth = obs.window(boxes[worst])
    for c in cfgs.values():
        c["residual"] = window_error(c["poses"], scene, obs, boxes[worst], truth)[2]
    return dict(shape=(H, W), path=path, n=n, side=side, boxes=boxes, cfgs=cfgs, worst=worst,
                map_seconds=map_seconds)


def summary(psnr: np.ndarray) -> dict[str, float]:
    """Median, 10th percentile and worst (min) of the scored windows' PSNR."""
    p = psnr[np.isfinite(psnr)]
    return dict(median=float(np.median(p)), p10=float(np.percentile(p, 10)),
                worst=float(p.min()), scored=int(p.size))


def plot(r: dict, path: Path) -> Path:
    """Two heat maps (A, B) on one dB scale with the estimation windows, and the residual
    of A's worst lattice window beside the same window with B."""
    plt = pyplot()
    from matplotlib.patches import Rectangle

    H, W = r["shape"]
    n, cfgs, worst = r["n"], r["cfgs"], r["worst"]
    allp = np.concatenate([c["psnr"] for c in cfgs.values()])
    vmin, vmax = np.floor(np.nanmin(allp)), np.ceil(np.nanmax(allp))
    fig = plt.figure(figsize=(14.5, 5.6))
    gs = fig.add_gridspec(2, 4, width_ratios=[1, 1, 0.05, 0.55], hspace=0.35, wspace=0.22)
    wy, wx, wh, ww = r["boxes"][worst]
    im = None
    for col, (k, c) in enumerate(cfgs.items()):
        ax = fig.add_subplot(gs[:, col])
        im = ax.imshow(c["psnr"].reshape(n, n), extent=(0, W, H, 0), cmap="viridis",
                       vmin=vmin, vmax=vmax, interpolation="nearest")
        if n <= 16:
            for i, v in enumerate(c["psnr"]):
                y, x = (i // n + 0.5) * H / n, (i % n + 0.5) * W / n
                light = np.isfinite(v) and v > vmin + 0.6 * (vmax - vmin)
                ax.text(x, y, "-" if not np.isfinite(v) else f"{v:.0f}", ha="center",
                        va="center", fontsize=6 if n > 8 else 8, color="k" if light else "w")
        for y0, x0, h, w in c["boxes"]:
            ax.add_patch(Rectangle((x0, y0), w, h, fill=False, edgecolor="red", lw=1.8))
        ax.add_patch(Rectangle((wx, wy), ww, wh, fill=False, edgecolor="orange", lw=1.2,
                               ls="--"))
        s = summary(c["psnr"])
        ax.set_title(f"{k}: {c['label']}\nmedian {s['median']:.1f} dB, worst "
                     f"{s['worst']:.1f} dB", fontsize=9)
        ax.set_xlabel("x (px)")
        if col == 0:
            ax.set_ylabel("y (px)")
    cb = fig.colorbar(im, cax=fig.add_subplot(gs[:, 2]))
    cb.set_label(f"reblur PSNR of each {r['side']} x {r['side']} window (dB)")
    res = [c["residual"] for c in cfgs.values()]
    rmax = float(np.nanpercentile(res[0], 99.5))
    for row, (k, c) in enumerate(cfgs.items()):
        ax = fig.add_subplot(gs[row, 3])
        rim = ax.imshow(np.ma.masked_invalid(c["residual"]), cmap="magma", vmin=0, vmax=rmax)
        ax.set_title(f"|residual|, {k}: {c['psnr'][worst]:.1f} dB, max "
                     f"{np.nanmax(c['residual']):.3f}", fontsize=8)
        ax.set_axis_off()
        fig.colorbar(rim, ax=ax, fraction=0.046, pad=0.03).ax.tick_params(labelsize=6)
    fig.suptitle(f"{H} x {W} image: red = estimation windows, dashed orange = A's worst "
                 f"window (residuals at right, same scale)", fontsize=9)
    return save_figure(fig, path)


def _distance_split(r: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distance of each lattice window's centre from the image centre, and the masks of the
    inner windows (within H / 6 of the centre, about the central cell, or the nearest ones
    if none is) and of the outskirts (>= 3/4 of the largest distance)."""
    H, W = r["shape"]
    c = np.array([(y + h / 2, x + w / 2) for y, x, h, w in r["boxes"]])
    d = np.hypot(c[:, 0] - H / 2, c[:, 1] - W / 2)
    return d, d <= max(min(H, W) / 6, d.min()), d >= 0.75 * d.max()


def _overlap(p: Box, q: Box) -> bool:
    """Whether two ``(y0, x0, h, w)`` boxes share a pixel."""
    return (p[0] < q[0] + q[2] and q[0] < p[0] + p[2] and p[1] < q[1] + q[3]
            and q[1] < p[1] + p[3])


def findings(r: dict) -> str:
    """The paragraph of the report, built from the numbers (claims only what they show)."""
    cfgs = r["cfgs"]
    a, b = cfgs["A"]["psnr"], cfgs["B"]["psnr"]
    _, inner, outer = _distance_split(r)
    ain, aout = np.nanmedian(a[inner]), np.nanmedian(a[outer])
    bin_, bout = np.nanmedian(b[inner]), np.nanmedian(b[outer])
    both = np.isfinite(a) & np.isfinite(b)
    better = int((b[both] > a[both]).sum())
    sa, sb = summary(a), summary(b)
    own = [i for i, bx in enumerate(r["boxes"])
           if any(_overlap(bx, e) for e in cfgs["A"]["boxes"])]
    def trend(name: str, centre: float, out: float) -> str:
        drop = centre - out
        if drop > 3.0:
            return f"{name} falls off by {drop:.1f} dB toward the outskirts"
        if drop < -3.0:
            return f"{name} is {-drop:.1f} dB better on the outskirts than near the centre"
        return f"{name} stays within 3 dB between the centre and the outskirts ({drop:+.1f} dB)"

    text = (
        f"Near the image centre ({int(inner.sum())} lattice windows within H/6 of it, around "
        f"A's estimation window) the median PSNR is {ain:.1f} dB with A and {bin_:.1f} dB with "
        f"B; on the outskirts ({int(outer.sum())} windows at >= 3/4 of the largest distance "
        f"from the centre) it is {aout:.1f} dB with A and {bout:.1f} dB with B: "
        f"{trend('A', ain, aout)}; {trend('B', bin_, bout)}. "
        f"B's worst window is {sb['worst']:.1f} dB against A's {sa['worst']:.1f} dB, its 10th "
        f"percentile {sb['p10']:.1f} dB against {sa['p10']:.1f} dB, and B is above A on "
        f"{better} of the {int(both.sum())} windows both score. "
        + (f"On the {len(own)} lattice windows that overlap A's estimation window A reaches "
           + ", ".join(f"{a[i]:.1f}" for i in own) + " dB (B: "
           + ", ".join(f"{b[i]:.1f}" for i in own) + " dB). " if own else "")
        + f"A fits its own window at "
        f"{min(cfgs['A']['fit']):.1f} dB, B its four at {min(cfgs['B']['fit']):.1f} dB or more. "
        f"B's estimation took {cfgs['B']['seconds']:.1f} s against "
        f"{cfgs['A']['seconds']:.1f} s for A."
    )
    return text


def report(r: dict, command: str, seconds: float) -> str:
    """The markdown report."""
    H, W = r["shape"]
    n, side, cfgs = r["n"], r["side"], r["cfgs"]
    ext = r["path"].extent()
    lines = [
        "# Reblur error map of a large image: one central window vs spread windows",
        "",
        f"Generated by `{command}` (do not edit by hand); {seconds / 60:.1f} min on "
        f"{machine()}; {code_version()}.",
        "",
        "## What ran",
        "",
        f"- Scene: `reblur.simulate.MosaicScene` of the six LEVIR/WHU development images "
        f"(gray, each upsampled to {CELL} px), {ROWS} x {COLS} cells, seed {SCENE_SEED}: "
        f"{H} x {W} ({H * W / 1e6:.1f} MP), computed window by window "
        "(`benchmarks.large_motion._scene`), never whole.",
        f"- Observation: blur along `random_camera_path({PATH_SEED}, center=image centre, "
        f"t_max={T_MAX}, rz_max={RZ_MAX})` (extent: roll {ext['rz']:.2f} deg, translation "
        f"{max(ext['tx'], ext['ty']):.1f} px), no noise, also window by window "
        "(`blur_along_path`).",
        f"- Estimation: `reblur.estimate_motion` (defaults) on {S} x {S} windows "
        "(`benchmarks.large_motion.layouts`).",
        "- Map: the reference reblurred with each estimate (`reblur.tiled.reblur_tile`) on "
        f"{n} x {n} windows of {side} x {side} px centred on a regular lattice (window "
        f"(i, j) centred on ((i + 1/2) H / {n}, (j + 1/2) W / {n})), PSNR (peak 1) against "
        "the true blurred window over the pixels valid in both; a heat-map cell shows the "
        f"window centred in it. Windows with less than {MIN_VALID:.0%} valid pixels are not "
        "scored. No random generator other than the two seeds above.",
        "",
    ]
    rows = []
    for k, c in cfgs.items():
        g = c["grid"]
        step = g.rz[1] - g.rz[0] if len(g.rz) > 1 else 0.0
        s = summary(c["psnr"])
        rows.append([f"{k}: {c['label']}", f"{g.size} poses, roll step {step:.4f} deg",
                     "; ".join(str(tuple(b)) for b in c["boxes"]), f"{c['seconds']:.1f}",
                     ", ".join(f"{x:.1f}" for x in c["fit"]), f"{s['median']:.1f}",
                     f"{s['p10']:.1f}", f"{s['worst']:.1f}",
                     f"{s['scored']} / {n * n} (min valid {fmt(float(c['share'].min()), 2)})"])
    lines += md_table(["configuration", "grid", "estimation windows (y0, x0, h, w)",
                       "estimation time (s)", "fit on own windows (dB)", "median (dB)",
                       "10th pct (dB)", "worst (dB)", "windows scored"], rows)
    wy, wx, _, _ = r["boxes"][r["worst"]]
    lines += [
        "",
        f"Reblurring and scoring the {n * n} lattice windows for both estimates took "
        f"{r['map_seconds']:.0f} s. Times are wall times under `nice` on a 2-core machine "
        "shared with other work; they are indicative only.",
        "",
        "![error map](error_map.png)",
        "",
        f"Left: A; middle: B (same colour scale, dB; red: estimation windows). Right: "
        f"|reblurred - true| on A's worst lattice window (dashed orange, top-left corner "
        f"({wy}, {wx})) with A (top) and B (bottom), same scale.",
        "",
        "## What it shows",
        "",
        findings(r),
        "",
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Command line entry point."""
    ap = argparse.ArgumentParser(prog="python -m experiments.error_map", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="a 4 x 4 lattice")
    ap.add_argument("--n", type=int, default=None, help="windows per lattice row (12)")
    ap.add_argument("--side", type=int, default=256, help="lattice window side (px)")
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args(argv)
    n = a.n if a.n is not None else (4 if a.quick else 12)
    cmd = "python -m experiments.error_map" + (" " + " ".join(argv) if argv else "")
    t = time.perf_counter()
    r = run(n, a.side, log=lambda s: print(s, file=sys.stderr, flush=True))
    plot(r, a.out / "error_map.png")
    write_text(a.out / "error_map.md", report(r, cmd, time.perf_counter() - t))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
