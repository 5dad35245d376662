"""Where the Fig. 6 errors lie (diagnostic for the pipeline issue's JC >= 0.9).

``python -m benchmarks.fig6_errors [--seeds 6 8] [--halfmax]`` -- the set-up of
``benchmarks.quality``'s Fig. 6 table, run with ``detect_changes`` defaults; for each seed
the false positives by their distance to the truth, the misses by their depth inside it,
and the largest false regions with their distance to the nearest change.

``--halfmax`` also scores a boundary rule that was tried and dropped: inside a band of
``r`` px around each accepted region, keep the pixels whose ``|observed - reblurred|``
reaches half of the region's amplitude (its 90th or 95th percentile) -- the half-maximum
convention of the simulator's truth.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage as ndi

from reblur.metrics import change_metrics


def _jaccard(truth, change, ignore) -> tuple[float, int, int]:
    m = change_metrics(truth, change, ignore=ignore)
    return float(m["jaccard"]), int(m["fp"]), int(m["fn"])


def halfmax_boundary(change, amplitude, r: int, q: float) -> np.ndarray:
    """``change`` with the band of ``r`` px around each region set to
    ``amplitude >= 0.5 * percentile(amplitude in the region, q)``."""
    out = change.copy()
    lab, _ = ndi.label(change, np.ones((3, 3)))
    H, W = change.shape
    for i, sl in enumerate(ndi.find_objects(lab)):
        y0, y1 = max(sl[0].start - r - 1, 0), min(sl[0].stop + r + 1, H)
        x0, x1 = max(sl[1].start - r - 1, 0), min(sl[1].stop + r + 1, W)
        reg = lab[y0:y1, x0:x1] == i + 1
        a = amplitude[y0:y1, x0:x1]
        level = 0.5 * np.percentile(a[reg], q)
        inner = ndi.binary_erosion(reg, np.ones((3, 3)), iterations=r)
        band = ndi.binary_dilation(reg, np.ones((3, 3)), iterations=r) & ~inner
        out[y0:y1, x0:x1][band] = (a >= level)[band]
    return out


def main(seeds=(6, 8), halfmax: bool = False) -> str:
    import reblur
    from benchmarks.quality import fig6_pair

    lines = []
    for s in seeds:
        p = fig6_pair(s)
        res = reblur.detect_changes(p.reference, p.observed)
        ign = p.unknown | res.unknown
        t, c = p.truth & ~ign, res.change & ~ign
        fp, fn = c & ~t, t & ~c
        d_out = ndi.distance_transform_edt(~t)
        d_in = ndi.distance_transform_edt(t)
        jc, nfp, nfn = _jaccard(p.truth, res.change, ign)
        lines.append(f"seed {s}: JC {jc:.3f}, {nfp} false positives, {nfn} misses")
        lines.append("  false positives within 1 / 2 / 4 px of the truth, beyond 8 px: "
                     + " / ".join(str(int((fp & (d_out <= k)).sum())) for k in (1, 2, 4))
                     + f", {int((fp & (d_out > 8)).sum())}")
        lines.append("  misses within 1 / 2 / 4 px of the background, deeper than 8 px: "
                     + " / ".join(str(int((fn & (d_in <= k)).sum())) for k in (1, 2, 4))
                     + f", {int((fn & (d_in > 8)).sum())}")
        lab, _ = ndi.label(fp, np.ones((3, 3)))
        sizes = np.bincount(lab.ravel())[1:]
        big = sorted(((int(n), int(d_out[lab == i + 1].min())) for i, n in enumerate(sizes)
                      if n > 100), reverse=True)[:6]
        lines.append("  largest false regions (px, distance to the nearest change): "
                     + ", ".join(f"{n} at {d}" for n, d in big))
        if halfmax:
            o = np.asarray(p.observed, float)
            m = np.asarray(res.reblurred, float)
            if o.max() > 2.0:
                o = o / 255.0
            amp = np.sqrt(((o - m).reshape(*o.shape[:2], -1) ** 2).sum(axis=2))
            for r in (1, 2, 3):
                for q in (90, 95):
                    jr, fr, nr = _jaccard(p.truth, halfmax_boundary(res.change, amp, r, q), ign)
                    lines.append(f"  half-maximum boundary, band {r} px, q {q}: JC {jr:.3f} "
                                 f"({fr} false positives, {nr} misses)")
    return "\n".join(lines)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[6, 8])
    ap.add_argument("--halfmax", action="store_true")
    a = ap.parse_args()
    print(main(tuple(a.seeds), a.halfmax))
