"""Where the rolling-shutter readout estimate goes wrong, and what the choice costs
(``python -m benchmarks.rolling_readout [--size 512] [--readouts 0.25,0.5,1] [--grid 6d]
[--against-global]``).

For each test-bed pair of :func:`benchmarks.rolling.make` (no change):

1. the global pipeline runs (``detect_changes(shutter="global")``, its CPU seconds);
2. :func:`reblur.rolling.choose_shutter` runs on the observation with the global weights
   and alignment (CPU seconds of each of its two window fits, their outer iterations);
3. :func:`reblur.rolling.readout_fraction`'s formula is applied to the test bed's TRUE
   band kernels (each band centre row's share of the path's sub-poses,
   :func:`reblur.testbed.rolling.row_slice_weights`) and to the fitted band weights, at the
   same window centres; and the centroid drift between neighbouring bands, true and
   fitted, is printed per window;
4. where the kernels were fitted: at every window's centre, the centroid of the true
   kernel of its row against that of the band model's kernel of the row
   (:meth:`~reblur.rolling.RollingMotion.row_weights`, composed with the alignment), and
   the change of both between consecutive windows on the same side of the image (rows
   a band apart: time drift and the geometry's change across the rows together);
5. that change split in two, true against fitted: the GEOMETRIC part (band ``b``'s kernel
   carried from its window's centre to the next window's, one band lower: the fit's
   alignment composed with its poses, the truth's homographies over the same time
   window) and the TIME part (band ``b + 1`` against band ``b`` at the lower window's
   centre), medians over the windows of each component along the true time drift;
6. the shape of the kernels at their own rows: the covariance of the fitted row kernel
   against the true one at every window centre (the trace, px^2), band by band;
7. with ``--against-global``: the readout-0 pair of the same path and viewpoint runs too,
   and down the rows (at the window centres) the alignment's displacement relative to
   that pair's is set against the true row-kernel centroid's relative to that pair's:
   the least-squares slope of each (px per 100 rows, x and y), i.e. the share of the
   rows' time drift that the alignment (a homography) took as a shear.

The observation is read at its own scale (no photometric gain or offset: the pipeline's
choice runs on its photometrically corrected view, so its figures differ slightly).
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def _true_moments(pair, bands, pt):
    """Mean and covariance of the true source displacement at ``pt`` for every band."""
    from reblur.grid import map_points
    from reblur.testbed.rolling import row_slice_weights

    hs, info = pair.homographies, pair.info
    src = np.array([map_points(np.linalg.inv(h), pt[None])[0] for h in hs]) - pt
    out = []
    for c in bands.centres:
        a = row_slice_weights(np.array([c]), bands.height, info["readout"],
                              info["n_exposure"], len(hs))[0]
        a = a / a.sum()
        mu = a @ src
        d = src - mu
        out.append((mu, d.T @ (d * a[:, None])))
    return out


def _readout(moments, centres) -> list[float]:
    """:func:`reblur.rolling.readout_fraction`'s formula on per-band moments."""
    rs = []
    for b in range(len(moments) - 1):
        (m0, s0), (m1, s1) = moments[b], moments[b + 1]
        dm = m1 - m0
        norm = float(np.linalg.norm(dm))
        if norm == 0:
            rs.append(0.0)
            continue
        u = dm / norm
        var = 0.5 * float(u @ s0 @ u + u @ s1 @ u)
        rs.append(norm / ((centres[b + 1] - centres[b]) * np.sqrt(12 * var)))
    return rs


def _own_rows(pair, m, base) -> None:
    """Item 4 of the module docstring: true and fitted centroids at each window's own row
    and centre (total displacement: pose composed with the alignment ``base``)."""
    from reblur.grid import map_points
    from reblur.testbed.rolling import row_slice_weights

    hs, info = pair.homographies, pair.info
    rows = []
    for y0, x0, h, w in m.boxes:
        pt = np.array([x0 + (w - 1) / 2.0, y0 + (h - 1) / 2.0])
        a = row_slice_weights(pt[1:], m.bands.height, info["readout"], info["n_exposure"],
                              len(hs))[0]
        src = np.array([map_points(np.linalg.inv(hm), pt[None])[0] for hm in hs]) - pt
        k = m.row_weights(pt[1])
        poses = m.grid.nonzero(k)
        d = np.array([map_points(np.linalg.inv(m.grid.homography((b, i, j)) @ base),
                                 pt[None])[0] - pt for b, i, j, _ in poses])
        v = np.array([q[3] for q in poses])
        rows.append((pt, a @ src / a.sum(), v @ d / v.sum()))
    err = [float(np.linalg.norm(t - f)) for _, t, f in rows]
    print(f"  at the windows' own rows: |fitted - true| centroid median {np.median(err):.2f} "
          f"px (max {max(err):.2f})")
    for side in (0, 1):
        pairs = list(zip(rows[side::2][:-1], rows[side::2][1:], strict=True))
        steps = ", ".join(f"{np.linalg.norm(b[1] - a[1]):.2f} / "
                          f"{np.linalg.norm(b[2] - a[2]):.2f}" for a, b in pairs)
        print(f"  change between consecutive windows, x = {rows[side][0][0]:.0f} "
              f"(true / fitted px): {steps}")


def _split(pair, m, base) -> None:
    """Item 5 of the module docstring: the change between consecutive windows on one side
    split into its geometric and time parts, true against fitted (components along the
    true time drift's direction, medians over the window pairs)."""
    from reblur.grid import map_points
    from reblur.testbed.rolling import row_slice_weights

    hs, info = pair.homographies, pair.info
    H = m.bands.height
    centres = m.bands.centres

    def fitted(b, pt):
        poses = m.grid.nonzero(m.weights[b])
        d = np.array([map_points(np.linalg.inv(m.grid.homography((q, i, j)) @ base),
                                 pt[None])[0] - pt for q, i, j, _ in poses])
        v = np.array([q[3] for q in poses])
        return v @ d / v.sum()

    def true(b, pt):
        a = row_slice_weights(np.array([centres[b]]), H, info["readout"], info["n_exposure"],
                              len(hs))[0]
        src = np.array([map_points(np.linalg.inv(hm), pt[None])[0] for hm in hs]) - pt
        return a @ src / a.sum()

    pts = np.array([[x0 + (w - 1) / 2.0, y0 + (h - 1) / 2.0] for y0, x0, h, w in m.boxes])
    rows = {k: [] for k in ("geo_true", "geo_fit", "time_true", "time_fit")}
    for side in (0, 1):
        own = pts[side::2]
        for b in range(min(len(own), m.bands.n_bands) - 1):
            p0, p1 = own[b], own[b + 1]
            tt = true(b + 1, p1) - true(b, p1)
            u = tt / max(float(np.linalg.norm(tt)), 1e-12)
            rows["time_true"].append(float(u @ tt))
            rows["time_fit"].append(float(u @ (fitted(b + 1, p1) - fitted(b, p1))))
            rows["geo_true"].append(float(u @ (true(b, p1) - true(b, p0))))
            rows["geo_fit"].append(float(u @ (fitted(b, p1) - fitted(b, p0))))
    med = {k: float(np.median(v)) for k, v in rows.items()}
    print("  split of the change between consecutive windows (px along the true time "
          f"drift, medians): geometric true {med['geo_true']:.2f} / fitted "
          f"{med['geo_fit']:.2f}, time true {med['time_true']:.2f} / fitted "
          f"{med['time_fit']:.2f}, sum true {med['geo_true'] + med['time_true']:.2f} / "
          f"fitted {med['geo_fit'] + med['time_fit']:.2f}")


def _shapes(pair, m, base) -> None:
    """Item 6 of the module docstring: trace of the row kernel's covariance (px^2) at
    every window centre, true / fitted, top to bottom on each side."""
    from reblur.grid import map_points
    from reblur.testbed.rolling import row_slice_weights

    hs, info = pair.homographies, pair.info
    out = {0: [], 1: []}
    for i, (y0, x0, h, w) in enumerate(m.boxes):
        pt = np.array([x0 + (w - 1) / 2.0, y0 + (h - 1) / 2.0])
        a = row_slice_weights(pt[1:], m.bands.height, info["readout"], info["n_exposure"],
                              len(hs))[0]
        src = np.array([map_points(np.linalg.inv(hm), pt[None])[0] for hm in hs]) - pt
        k = m.row_weights(pt[1])
        poses = m.grid.nonzero(k)
        d = np.array([map_points(np.linalg.inv(m.grid.homography((b, i_, j)) @ base),
                                 pt[None])[0] - pt for b, i_, j, _ in poses])
        v = np.array([q[3] for q in poses])
        traces = []
        for dd, ww in ((src, a), (d, v)):
            ww = ww / ww.sum()
            e = dd - ww @ dd
            traces.append(float(np.sum(ww[:, None] * e * e)))
        out[i % 2].append(traces)
    for side, tr in out.items():
        print(f"  kernel covariance trace at own rows, side {side} (true / fitted px^2): "
              + ", ".join(f"{t:.1f} / {f:.1f}" for t, f in tr))


def _alignment_shear(pair, m, base, size: int, grid: str) -> None:
    """Item 7 of the module docstring."""
    import reblur
    from benchmarks.rolling import make
    from reblur.grid import GridParams, map_points
    from reblur.testbed.rolling import row_slice_weights

    glob = make(0.0, False, size)
    res0 = reblur.detect_changes(glob.reference, glob.observed, shutter="global",
                                 grid=GridParams(kind="6d") if grid == "6d" else None)
    hs, info = pair.homographies, pair.info
    pts = np.array([[x0 + (w - 1) / 2.0, y0 + (h - 1) / 2.0] for y0, x0, h, w in m.boxes])
    src = np.stack([map_points(np.linalg.inv(hm), pts) - pts for hm in hs])  # (n, pts, 2)

    def centroid(readout):
        a = row_slice_weights(pts[:, 1], m.bands.height, readout, info["n_exposure"],
                              len(hs))
        return np.einsum("pn,npi->pi", a / a.sum(1, keepdims=True), src)

    d_base = (map_points(np.linalg.inv(base), pts)
              - map_points(np.linalg.inv(res0.alignment), pts))
    d_true = centroid(info["readout"]) - centroid(0.0)
    X = np.stack([np.ones(len(pts)), pts[:, 0], pts[:, 1]], 1)
    sb = 100 * np.linalg.lstsq(X, d_base, rcond=None)[0][2]
    st = 100 * np.linalg.lstsq(X, d_true, rcond=None)[0][2]
    print(f"  against the readout-0 pair, px per 100 rows (x, y): alignment "
          f"({sb[0]:.2f}, {sb[1]:.2f}), true centroid ({st[0]:.2f}, {st[1]:.2f})")


def run(readout: float, size: int, grid: str = "3d", against: bool = False) -> None:
    import reblur
    import reblur.rolling as R
    from benchmarks.rolling import make
    from reblur.grid import GridParams

    pair = make(readout, False, size)
    c0 = time.process_time()
    res = reblur.detect_changes(pair.reference, pair.observed, shutter="global",
                                grid=GridParams(kind="6d") if grid == "6d" else None)
    cpu_global = time.process_time() - c0
    fits = []
    fit = R._fit

    def timed(*args):
        c = time.process_time()
        out = fit(*args)
        fits.append((args[2].n_bands, time.process_time() - c, out[1]["n_outer"]))
        return out

    R._fit = timed
    try:
        c0 = time.process_time()
        choice = R.choose_shutter(pair.reference, pair.observed, res.motion.grid,
                                  w_start=res.motion.weights, base=res.alignment)
        cpu_choice = time.process_time() - c0
    finally:
        R._fit = fit
    m = choice.rolling
    centres = m.bands.centres / m.bands.height
    pts = np.array([[x0 + (w - 1) / 2.0, y0 + (h - 1) / 2.0] for y0, x0, h, w in m.boxes])
    r_true, r_fit = [], []
    print(f"readout {readout} ({grid} grid {res.motion.grid.shape}): global pipeline "
          f"{cpu_global:.1f} s CPU; choice "
          f"{cpu_choice:.1f} s CPU ("
          + ", ".join(f"{b} band(s) {s:.1f} s, {n} outer" for b, s, n in fits)
          + f"); kept {choice.model}")
    for pt in pts:
        true = _true_moments(pair, m.bands, pt)
        fitted = [R._moments(m.grid, m.weights[b], pt) for b in range(m.bands.n_bands)]
        r_true += _readout(true, centres)
        r_fit += _readout(fitted, centres)
        drift = [np.linalg.norm(np.diff([mu for mu, _ in ms], axis=0), axis=1).round(2)
                 for ms in (true, fitted)]
        print(f"  window centre {pt}: centroid drift per band, true {drift[0]}, "
              f"fitted {drift[1]}")
    print(f"  readout formula: on the true kernels {np.median(r_true):.2f}, on the fitted "
          f"{np.median(r_fit):.2f} (reported {m.info['readout']:.2f}, quartiles "
          + "{:.2f}-{:.2f})".format(*m.info["readout_fit"]["quartiles"]), flush=True)
    _own_rows(pair, m, res.alignment)
    _split(pair, m, res.alignment)
    _shapes(pair, m, res.alignment)
    if against:
        _alignment_shear(pair, m, res.alignment, size, grid)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--readouts", default="0.25,0.5,1")
    ap.add_argument("--grid", default="3d", choices=("3d", "6d"),
                    help="the pose grid (6d: also scale change and tilt)")
    ap.add_argument("--against-global", action="store_true",
                    help="also run the readout-0 pair and compare the alignments (item 7)")
    a = ap.parse_args()
    for r in a.readouts.split(","):
        run(float(r), a.size, a.grid, a.against_global)
