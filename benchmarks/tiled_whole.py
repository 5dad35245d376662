"""How far the tile pass lies from one decision over the whole image
(``python -m benchmarks.tiled_whole [--cases 25:years-levir,25:45%] [--cache DIR]``).

The tile pass (:func:`reblur.tilejob.run_tile`) equals the whole-image decision on every
tile it reports complete.  A tile is incomplete when a candidate region reaching its core
is larger than the largest halo of the re-run schedule holds (``oversize``): that region
is decided on the tile's window, not as a whole.  This benchmark measures what that costs
in the mask, on the cost pairs of :mod:`benchmarks.cost` (the test bed's scene, changed
by content): each case runs through :func:`reblur.pipeline.detect_changes` (tiled, its
defaults), then the same job -- the same pose weights, photometry, threshold and
parameters, taken from the pass itself -- decides the whole image in one call
(:func:`reblur.decide.decide_tile` over every pixel, no tile edge), and the two masks are
compared pixel for pixel.  Any change to the tile pass (its halos, its re-runs, regions
decided across tiles) should keep these figures; a whole-image decision holds several GB
at 100 MP, so the default cases are 25 MP.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import tifffile

from benchmarks.cost import CACHE, _lattice, make_case

CASES = ("25:years-levir", "25:45%", "25:5%", "25:unchanged")

#: The pasted blocks of the lattice cases (:func:`benchmarks.cost._scenes`): fraction of
#: the area and blocks per side.
BLOCKS = {"5pc": (0.05, 4), "45pc": (0.45, 1)}

#: Pixels either side of a block's edge left out of the scores (the viewpoint's 20 px shift
#: and the blur move the edges in the observation's frame).
EDGE = 40


def _truth_scores(case: str, masks: dict[str, np.ndarray]) -> dict[str, tuple[float, float]]:
    """Per mask: the share flagged inside the pasted blocks (shrunk by :data:`EDGE`) and
    outside them (grown by it); empty for a case without blocks."""
    content = case.split("_", 1)[1]
    if content not in BLOCKS and content != "unchanged":
        return {}
    shape = next(iter(masks.values())).shape
    inside = np.zeros(shape, bool)
    near = np.zeros(shape, bool)
    for y0, y1, x0, x1 in (_lattice(shape, *BLOCKS[content]) if content in BLOCKS else []):
        inside[y0 + EDGE : y1 - EDGE, x0 + EDGE : x1 - EDGE] = True
        near[max(y0 - EDGE, 0) : y1 + EDGE, max(x0 - EDGE, 0) : x1 + EDGE] = True
    out = {}
    for name, m in masks.items():
        recall = float(m[inside].mean()) if inside.any() else float("nan")
        out[name] = (recall, float(m[~near].mean()))
    return out


def compare(case: Path) -> dict:
    """Tile pass and whole-image decision of one case: shares of the image flagged by
    each, their disagreement and Jaccard, incomplete tiles and the tile pass's work."""
    import reblur.pipeline as pipeline
    import reblur.tilejob as tilejob
    from reblur.decide import decide_tile
    from reblur.tilejob import load_tile

    seen: dict = {}
    real = tilejob.run_tile

    def spy(job, reference, observed, *args, **kwargs):
        seen.update(job=job, reference=reference, observed=observed)
        return real(job, reference, observed, *args, **kwargs)

    ref = tifffile.imread(case / "ref.tif")
    obs = tifffile.imread(case / "obs.tif")
    # the tile pass's own job, seen by its tiles (wherever the pass calls them from)
    spied = [m for m in (tilejob, pipeline) if getattr(m, "run_tile", None) is real]
    for m in spied:
        m.run_tile = spy
    try:
        t = time.perf_counter()
        res = pipeline.detect_changes(ref, obs)
        seconds = time.perf_counter() - t
    finally:
        for m in spied:
            m.run_tile = real
    job = seen["job"]
    tiled = np.asarray(res.change, bool)
    H, W = job.image_shape
    box = (0, 0, H, W)
    o, r, u = load_tile(job.poses, seen["reference"], seen["observed"], box, s_ref=job.s_ref,
                        s_obs=job.s_obs, gain=np.asarray(job.gain, np.float32),
                        offset=np.asarray(job.offset, np.float32))
    fld = getattr(job.poses, "field", None)
    reach = (fld.reach_map(box, job.params.geometry_reach)
             if fld is not None and job.params.geometry_reach > 0 else None)
    whole, _ = decide_tile(o, r, u, threshold=job.threshold, photometry=job.photometry,
                           box=box, params=job.params, image_shape=(H, W), reach=reach)
    del o, r, u
    dec = res.decision
    union = np.count_nonzero(tiled | whole)
    truth = _truth_scores(case.name, {"tiled": tiled, "whole": whole})
    return {
        "truth": truth,
        "case": case.name, "mp": H * W / 1e6, "seconds": seconds,
        "tile_pass": dec.get("seconds", {}).get("tiles"),
        "tiles": dec.get("n_tiles"), "incomplete": dec.get("incomplete_tiles"),
        "work": dec.get("backend", {}).get("work", {}),
        "tiled": float(tiled.mean()), "whole": float(whole.mean()),
        "tiled_only": float((tiled & ~whole).mean()),
        "whole_only": float((whole & ~tiled).mean()),
        "jc": float(np.count_nonzero(tiled & whole) / union) if union else 1.0,
    }


def table(rows: list[dict]) -> str:
    lines = [
        "## The tile pass against one whole-image decision (`python -m benchmarks.tiled_whole`)",
        "",
        "Cost pairs of `benchmarks.cost` through `detect_changes` (tiled, defaults), then the "
        "same job deciding the whole image in one call; masks compared pixel for pixel.  "
        "Incomplete tiles hold a region larger than the re-runs' largest halo, decided on "
        "the tile's window.  Lattice cases: the share flagged inside the pasted blocks "
        f"(shrunk by {EDGE} px) and outside them (grown by {EDGE} px).",
        "",
        "| case | MP | tiles (incomplete) | decisions / padded MP | tile pass s | "
        "flagged tiled / whole | "
        "tiled only | whole only | Jaccard | in blocks tiled / whole | outside tiled / whole |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        w = r["work"]
        lines.append(
            f"| {r['case']} | {r['mp']:.0f} | {r['tiles']} ({r['incomplete']}) | "
            f"{w.get('attempts', '?')} / {w.get('pixels', 0) / 1e6:.0f} | "
            f"{r['tile_pass']:.1f} | "
            f"{100 * r['tiled']:.3f} / {100 * r['whole']:.3f} % | "
            f"{100 * r['tiled_only']:.4f} % | {100 * r['whole_only']:.4f} % | {r['jc']:.4f} | "
            + _truth_cells(r.get("truth", {})))
    return "\n".join(lines) + "\n"


def _truth_cells(t: dict) -> str:
    if not t:
        return "- | - |"
    (ri, fo), (rw, fw) = t["tiled"], t["whole"]
    inside = "-" if np.isnan(ri) else f"{100 * ri:.2f} / {100 * rw:.2f} %"
    return f"{inside} | {100 * fo:.3f} / {100 * fw:.3f} % |"


def main(cases: tuple[str, ...] = CASES, cache: Path | None = None) -> str:
    rows = []
    for spec in cases:
        mp, content = spec.split(":", 1)
        rows.append(compare(make_case(int(mp), content, cache or CACHE)))
        print(table(rows[-1:]).splitlines()[-1], flush=True)
    return table(rows)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(prog="python -m benchmarks.tiled_whole")
    ap.add_argument("--cases", default=",".join(CASES),
                    help="MP:content pairs of benchmarks.cost, comma-separated")
    ap.add_argument("--cache", type=Path, default=None,
                    help="folder of the generated pairs (default: benchmarks.cost's)")
    a = ap.parse_args()
    print(main(tuple(c for c in a.cases.split(",") if c), a.cache))
