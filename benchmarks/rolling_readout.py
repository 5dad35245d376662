"""Where the rolling-shutter readout estimate goes wrong, and what the choice costs
(``python -m benchmarks.rolling_readout [--size 512] [--readouts 0.25,0.5,1] [--grid 6d]``).

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
   a band apart: time drift and the geometry's change across the rows together).

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


def run(readout: float, size: int, grid: str = "3d") -> None:
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


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--readouts", default="0.25,0.5,1")
    ap.add_argument("--grid", default="3d", choices=("3d", "6d"),
                    help="the pose grid (6d: also scale change and tilt)")
    a = ap.parse_args()
    for r in a.readouts.split(","):
        run(float(r), a.size, a.grid)
