"""Cost and accuracy of the coarse alignment alone on the cost benchmark's pairs (issue #28:
at most 3 s at 100 MP, whatever the content): ``python -m benchmarks.align_cost``.

For every pair of :mod:`benchmarks.cost` (same cache, same test-bed rendering) this opens
both files and times :func:`reblur.pipeline.align_coarse` on them, as ``reblur detect``
does (each image read once into its overviews), in this process.  Per pair: the time,
the shake extents tried, the method, and the corner error against the test bed's truth,
the mean over the camera path's sub-poses of where each reference corner lands
(the pose the pipeline's fine grid is centred on).  Refused pairs (unrelated content) give
their time only.

The rows are kept in ``docs/align_cost_runs.json`` under ``--label`` (default: this
checkout's commit) and the section shows every label's table, so that another checkout's
figures stand beside these: ``PYTHONPATH=OLD/src python -m benchmarks.align_cost --label
OLD`` (run from this checkout).  ``--refine-iterations N`` sets
:data:`reblur.align.ecc.REFINE_ITERATIONS` and ``--match-workers N``
:data:`reblur.align.blocks.MATCH_WORKERS`.  ``--no-save`` prints the table only.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks.common import REPO
from benchmarks.cost import CACHE, CONTENTS, RGB16, _scenes, make_case


def truth_error(H: np.ndarray, mp: int, content: str) -> float:
    """Largest distance (full-resolution px) between where ``H`` and the test bed's mean
    sub-pose put the reference's corners."""
    from reblur.grid import map_points
    from reblur.testbed import plan_pair, shake_for

    ref, _ = _scenes(mp, content.removesuffix(RGB16))  # (the same scene in 16-bit bands)
    plan = plan_pair(ref, bits=8, noise_dn=0.5, n_changes=0, seed=0,
                     motion=shake_for(ref.shape), viewpoint={"shift_px": 20.0})
    h, w = ref.shape[:2]
    c = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)
    true = np.mean([map_points(Hk, c) for Hk in plan.homographies], axis=0)
    return float(np.abs(map_points(H, c) - true).max())


def run_case(case: Path) -> dict:
    """Time the coarse alignment of one cached pair."""
    from reblur.align import AlignmentError
    from reblur.align.overviews import OverviewCache
    from reblur.io import open_image
    from reblur.pipeline import align_coarse

    ref, obs = open_image(case / "ref.tif"), open_image(case / "obs.tif")
    t = time.perf_counter()
    try:
        a = align_coarse(OverviewCache(ref.for_detection()), OverviewCache(obs.for_detection()))
    except AlignmentError as err:
        return {"seconds": time.perf_counter() - t, "refused": str(err)[:80]}
    return {"seconds": time.perf_counter() - t, "method": a.method, "H": a.H,
            "extents": [e["shake_px"] for e in a.extents]}


def table(rows: list[dict]) -> str:
    out = ["| size | content | align (s) | extents tried | method | corner error (px) |",
           "|---|---|---|---|---|---|"]
    for r in rows:
        if "refused" in r:
            out.append(f"| {r['mp']} MP | {r['content']} | {r['seconds']:.2f} | | refused | |")
            continue
        ext = ", ".join(f"{e:g}" for e in r["extents"])
        out.append(f"| {r['mp']} MP | {r['content']} | {r['seconds']:.2f} | {ext} | "
                   f"{r['method']} | {r['error']:.2f} |")
    return "\n".join(out)


RUNS = REPO / "docs" / "align_cost_runs.json"


def main(sizes: list[int], contents: list[str], cache: Path) -> list[dict]:
    rows = []
    for mp in sizes:
        for content in contents:
            r = {"mp": mp, "content": content, **run_case(make_case(mp, content, cache))}
            if "H" in r:
                r["error"] = truth_error(r.pop("H"), mp, content)
            print(r, flush=True)
            rows.append(r)
    return rows


def section(rows: list[dict], label: str) -> str:
    """Save ``rows`` under ``label`` in :data:`RUNS` and render every label's table."""
    import json

    runs = json.loads(RUNS.read_text()) if RUNS.exists() else {}
    runs.pop(label, None)
    runs = {label: {"date": time.strftime("%Y-%m-%d"), "rows": rows}, **runs}
    RUNS.write_text(json.dumps(runs, indent=1))
    return ("## Coarse alignment over content (`python -m benchmarks.align_cost`)\n\n"
            "The alignment alone (`pipeline.align_coarse`) on the cost benchmark's pairs; "
            "corner error against the test bed's mean pose.  One table per checkout "
            "(`docs/align_cost_runs.json`), newest first.\n\n"
            + "\n\n".join(f"{k} ({v['date']}):\n\n{table(v['rows'])}"
                           for k, v in runs.items()))


def bench(cache: Path | None = None, label: str | None = None) -> str:
    """``make bench``: every size and content, rows saved under this checkout's commit."""
    from benchmarks.common import commit

    cache = cache or CACHE
    return section(main([1, 25, 100], CONTENTS, cache), label or commit())


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1,25,100")
    ap.add_argument("--contents", default=",".join(CONTENTS))
    ap.add_argument("--cache", type=Path, default=CACHE)
    ap.add_argument("--refine-iterations", type=int, default=None)
    ap.add_argument("--match-workers", type=int, default=None)
    ap.add_argument("--no-save", action="store_true")
    ap.add_argument("--label", default=None, help="name of the rows (default: the commit)")
    a = ap.parse_args()
    import reblur.align.blocks as blocks
    import reblur.align.ecc as ecc

    if a.refine_iterations is not None:
        ecc.REFINE_ITERATIONS = a.refine_iterations
    if a.match_workers is not None:
        blocks.MATCH_WORKERS = a.match_workers
    rows = main([int(s) for s in a.sizes.split(",")], a.contents.split(","), a.cache)
    if a.no_save:
        print(table(rows))
    else:
        from benchmarks.common import commit
        from benchmarks.run import write_section

        body = section(rows, a.label or commit())
        write_section("align_cost", body)
        print(body)
