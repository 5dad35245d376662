"""What ``overlay.png`` costs to draw (issue #28): time, page faults and traced memory.

``python -m benchmarks.pictures`` prints a markdown section.  Each case runs in a fresh
process, as a ``reblur detect`` run draws the overlay once: an observation of the given
size, dtype and bands (seeded noise over stripes), a block of changes and a band of
unknown pixels, drawn by :func:`reblur.report.overlay_image` at its default size (long side
2048).  The first call is timed (page faults included: on this VM fresh memory above the C
library's 32 MB mmap threshold costs 1-2.4 ms per MB, ``python -m benchmarks.first_touch``);
a second call in the same process measures the traced peak (``tracemalloc``).

``--src OLD/src --label COMMIT`` draws with another checkout (the "before" rows).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time

import numpy as np

from benchmarks.common import REPO, run_case

#: (side, dtype, bands): the overlay of a 16-bit or float image is stretched to its 1-99 %
#: range, that of a uint8 one shown as is
CASES = ((2048, "uint16", 1), (2048, "uint16", 3), (2048, "float32", 1), (2048, "uint8", 3),
         (4096, "uint16", 1))


def case(side: int, dtype: str, bands: int) -> dict:
    """Draw one overlay in this process; the timings of its first call, its traced peak."""
    import tracemalloc

    from reblur.report import overlay_image

    rng = np.random.default_rng(3)
    shape = (side, side) if bands == 1 else (side, side, bands)
    top = 255 if dtype == "uint8" else 60000
    obs = (rng.random(shape, dtype=np.float32) * top).astype(dtype)
    obs[:, ::9] //= 3
    change = np.zeros((side, side), bool)
    change[side // 4 : side // 3, side // 5 : side // 2] = True
    unknown = np.zeros((side, side), bool)
    unknown[:, : side // 10] = True
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    t = time.perf_counter()
    overlay_image(obs, change, unknown)
    seconds = time.perf_counter() - t
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    tracemalloc.start()
    overlay_image(obs, change, unknown)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return dict(seconds=seconds, minflt=r1.ru_minflt - r0.ru_minflt, peak_mb=peak / 2**20)


def _rows(src: str | None, repeats: int) -> list[str]:
    """One table row per case, each run ``repeats`` times in fresh processes importing
    reblur from ``src`` (None: this checkout)."""
    saved = os.environ.get("PYTHONPATH")
    if src:  # the cases' processes import reblur from there
        os.environ["PYTHONPATH"] = os.path.abspath(src)
    try:
        runs = [[run_case("benchmarks.pictures", "--case", str(side), dtype, str(bands))
                 for _ in range(repeats)] for side, dtype, bands in CASES]
    finally:
        if src:
            if saved is None:
                del os.environ["PYTHONPATH"]
            else:
                os.environ["PYTHONPATH"] = saved
    return [f"| {side}^2 {dtype} x{bands} | "
            + " / ".join(f"{r['seconds']:.2f}" for r in rs) + " | "
            + f"{int(np.median([r['minflt'] for r in rs]))} | {rs[0]['peak_mb']:.0f} |"
            for (side, dtype, bands), rs in zip(CASES, runs, strict=True)]


#: The "before" rows of the last ``--src`` run: ``{"label", "rows"}`` (markdown rows).
BEFORE = REPO / "docs" / "pictures_before.json"


def main(src: str | None = None, label: str | None = None, repeats: int = 2) -> str:
    """The section: this checkout's rows, and first those of ``src`` (named ``label``),
    saved, or of the last such run."""
    head = ["| image | first call (s) | page faults | traced peak (MB) |", "|---|---|---|---|"]
    lines = [
        "## The overlay picture (`python -m benchmarks.pictures`)",
        "",
        "`reblur.report.overlay_image` at its default long side (2048) in a fresh process: "
        "the first call's time (runs separated by /: a run right after another finds "
        "freed pages the host still backs) and minor page faults, the traced peak of a "
        "second call.",
        "",
    ]
    if src:  # kept for the runs without --src (``make bench``)
        BEFORE.write_text(json.dumps({"label": label or str(src),
                                      "rows": _rows(src, repeats)}, indent=1))
    if BEFORE.exists():
        before = json.loads(BEFORE.read_text())
        lines += [f"Before (`{before['label']}`, `--src`):", "", *head, *before["rows"],
                  "", "Now:", ""]
    lines += [*head, *_rows(None, repeats)]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", nargs=3, metavar=("SIDE", "DTYPE", "BANDS"))
    ap.add_argument("--src", default=None,
                    help="also draw with another checkout's src folder (before rows)")
    ap.add_argument("--label", default=None, help="name of that checkout (e.g. its commit)")
    ap.add_argument("--repeats", type=int, default=2)
    a = ap.parse_args()
    if a.case:
        print(json.dumps(case(int(a.case[0]), a.case[1], int(a.case[2]))))
    else:
        print(main(a.src, a.label, a.repeats))
