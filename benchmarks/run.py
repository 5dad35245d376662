"""``make bench``: run the benchmarks and write their figures into ``docs/benchmarks.md``.

Each benchmark owns one section of the file, delimited by ``<!-- NAME:begin -->`` and
``<!-- NAME:end -->``; a run replaces only the sections it produced, so a long benchmark
(e.g. the gigapixel cost curve, ``python -m benchmarks.scale``) can be run on its own.
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import os
import re
import sys
import time
from pathlib import Path

from benchmarks.common import REPO, DataMissing, data_dir, machine, require_data

DOC = REPO / "docs" / "benchmarks.md"
#: name -> (module, callable returning markdown)
BENCHES = {
    "operator": ("benchmarks.operator", "main"),
    "large_motion": ("benchmarks.large_motion", "main"),
    "pipeline": ("benchmarks.pipeline", "main"),
    "quality": ("benchmarks.quality", "main"),
    "outskirts": ("benchmarks.outskirts", "main"),
    "scale": ("benchmarks.scale", "main"),
    "first_touch": ("benchmarks.first_touch", "main"),
    "estimate_profile": ("benchmarks.estimate_profile", "main"),
    # 1 and 25 MP; the 100 MP rows: python -m benchmarks.realism --sizes 1,25,100
    "realism": ("benchmarks.realism", "main"),
    # cost over content at 1 and 25 MP; 100 MP: python -m benchmarks.cost --sizes 1,25,100
    "cost": ("benchmarks.cost", "main"),
    # the decision's failure modes (issue #27); before: --src OLD/src --label COMMIT
    "failure_modes": ("benchmarks.failure_modes", "main"),
    # the zoomable viewer's pyramids at 4 and 25 MP (issue #31)
    "viewer": ("benchmarks.viewer", "main"),
    # the coarse alignment alone on the cost pairs, 1-100 MP (issue #28)
    "align_cost": ("benchmarks.align_cost", "bench"),
    # the mask PNGs' encodings: viewer tiles and a 100 MP change mask (issues #28, #31)
    "png_masks": ("benchmarks.png_masks", "main"),
    # the estimation windows' side: time against blur-model fidelity on real shake (#28)
    "window_side": ("benchmarks.window_side", "main"),
    # the tile pass against one whole-image decision, 25 MP cost pairs (#28)
    "tiled_whole": ("benchmarks.tiled_whole", "main"),
    # the overlay picture's drawing: time, page faults, traced memory (#28)
    "pictures": ("benchmarks.pictures", "main"),
    # camera shake beyond the pose grid: time and accuracy against its extent (#28)
    "shake_extent": ("benchmarks.shake_extent", "main"),
    # the estimate's first level at half resolution, on and off (#28)
    "half_start": ("benchmarks.half_start", "main"),
    # the estimate's Gram products at 1 MP: work, rate, share of the estimate (#28)
    "gram_work": ("benchmarks.gram_work", "main"),
    # the 1 MP pairs on one core and on all: the same bytes out (#28)
    "cores": ("benchmarks.cores", "main"),
    # thin strips: the estimation windows and the decision, 130-400 px across
    "strips": ("benchmarks.strips", "main"),
    # the solver's NNLS by exchange against scipy's on every Newton step (#28)
    "nnls_exchange": ("benchmarks.nnls_exchange", "main"),
}


def write_section(name: str, body: str, path: Path = DOC) -> None:
    """Replace (or append) the section ``name`` of ``docs/benchmarks.md``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    text = path.read_text() if path.exists() else "# Benchmarks\n\nFigures from `make bench`.\n"
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    stamp = f"_Run {datetime.date.today().isoformat()} on {machine()}._\n\n"
    block = f"{begin}\n{stamp}{body.strip()}\n{end}"
    pat = re.compile(re.escape(begin) + ".*?" + re.escape(end), re.S)
    if pat.search(text):
        text = pat.sub(lambda _m: block, text)
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    tmp = path.with_suffix(".md.tmp")
    tmp.write_text(text)
    tmp.replace(path)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmarks named (default: all); one line on stderr and exit 2 when the
    shared data they read is missing (``--data DIR``, else ``$REBLUR_DATA``, else
    ``../shared/data`` beside the repository)."""
    ap = argparse.ArgumentParser(prog="python -m benchmarks.run")
    ap.add_argument("names", nargs="*", default=list(BENCHES), metavar="NAME",
                    help=f"benchmarks to run: {', '.join(BENCHES)}")
    ap.add_argument("--data", type=Path, default=None,
                    help="the shared data folder (default: $REBLUR_DATA, else "
                         "../shared/data beside the repository)")
    a = ap.parse_args(argv)
    unknown = [n for n in a.names if n not in BENCHES]
    if unknown:
        ap.error(f"unknown benchmark(s) {', '.join(unknown)}; choose from {', '.join(BENCHES)}")
    if a.data is not None:
        os.environ["REBLUR_DATA"] = str(a.data)  # read by the benchmarks and their cases
    try:
        require_data(data_dir())
        for name in a.names:
            mod, fn = BENCHES[name]
            t = time.perf_counter()
            print(f"[bench] {name} ...", flush=True)
            body = getattr(importlib.import_module(mod), fn)()
            write_section(name, body)
            print(f"[bench] {name} done in {time.perf_counter() - t:.0f} s", flush=True)
    except DataMissing as exc:
        print(f"benchmarks: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
