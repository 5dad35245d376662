"""What fresh memory costs on this machine (first-touch page faults).

``python -m benchmarks.first_touch`` prints a markdown section.  A process that grows (keeps
what it allocates) pays the kernel's page faults on every new page; one that frees and
allocates again at once reuses pages the kernel still holds.  On some virtual machines the
first is far slower than writing memory: the host backs guest memory lazily and takes it
back when the guest frees it.  This is why the estimate keeps its fresh memory small
(``solve.Scratch``, single-precision spectra; docs/NOTES.md, "Memory of the estimate") and
takes it in small pages (``_memory.small_pages``: a transparent huge page needs a whole free
2 MB block, probably the kind of memory the host takes back first).

Each case runs in a fresh process: it allocates ``n`` arrays of ``mb`` MB, writes each once
(``fill``: the first touch) and then again (the second write: memory bandwidth), and
either keeps them all (``grow``) or frees each before the next (``reuse``).
"""

from __future__ import annotations

import argparse
import json
import resource
import time

import numpy as np

from benchmarks.common import run_case

#: (mode, MB per array, arrays, seconds idle before the case).  The second case starts
#: right after the first freed its 2 GB: pages the kernel still holds.  ``grow-threads``
#: is ``grow`` with each first write made by :func:`reblur._memory.zeros` (the available
#: CPUs at once), as the estimate's stacks and spectra are; ``grow-small`` is ``grow``
#: with the arrays allocated inside :func:`reblur._memory.small_pages` (small pages, as
#: the estimate's are).
CASES = (("grow", 256, 8, 5.0), ("grow", 256, 8, 0.0), ("reuse", 256, 8, 5.0),
         ("grow-threads", 256, 8, 5.0), ("grow-small", 256, 8, 5.0))


def case(mode: str, mb: int, n: int) -> dict:
    """Time the first and the second write of ``n`` arrays of ``mb`` MB."""
    from reblur._memory import small_pages, zeros

    first = second = 0.0
    keep = []
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    for _ in range(n):
        t = time.perf_counter()
        if mode == "grow-threads":
            a = zeros(mb * 2**20 // 8, np.float64)
        elif mode == "grow-small":
            with small_pages():
                a = np.empty(mb * 2**20 // 8)
            a.fill(1.0)
        else:
            a = np.empty(mb * 2**20 // 8)
            a.fill(1.0)
        t1 = time.perf_counter()
        a.fill(2.0)
        t2 = time.perf_counter()
        first += t1 - t
        second += t2 - t1
        if mode.startswith("grow"):
            keep.append(a)
        del a
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    total = mb * n
    return dict(mode=mode, mb=total, first_s=first, second_s=second,
                first_ms_per_mb=1e3 * first / total, second_ms_per_mb=1e3 * second / total,
                sys_s=r1.ru_stime - r0.ru_stime, minflt=r1.ru_minflt - r0.ru_minflt)


def main(repeats: int = 3) -> str:
    lines = [
        "## Fresh memory (`python -m benchmarks.first_touch`)",
        "",
        "Time to write memory the first time (page faults included) and a second time, "
        "per MB, each case in a fresh process, repeated; `grow` keeps every array "
        "(new pages all the way), `reuse` frees each before the next.  The idle column is "
        "the pause before the case (0: right after the previous case freed its memory).  "
        "The idle-0 row is what a page fault costs when the host still backs the page. "
        "`grow-threads` makes each first write with `reblur._memory.zeros`: the "
        "available CPUs fault the pages in at once. `grow-small` allocates inside "
        "`reblur._memory.small_pages` (small pages instead of numpy's transparent huge "
        "pages, as the motion estimate does).",
        "",
        "| case | idle before (s) | MB written | first write (ms/MB), per run "
        "| second write (ms/MB) | kernel time (s), per run |",
        "|---|---|---|---|---|---|",
    ]
    for mode, mb, n, idle in CASES:
        rs = []
        for _ in range(repeats):
            if idle:
                time.sleep(idle)
            rs.append(run_case("benchmarks.first_touch", "--case", mode, str(mb), str(n)))
            if not idle:
                break  # only the first run follows the previous case at once
        lines.append(
            f"| {mode} | {idle:g} | {mb * n} | "
            + " / ".join(f"{r['first_ms_per_mb']:.2f}" for r in rs) + " | "
            + f"{np.median([r['second_ms_per_mb'] for r in rs]):.2f} | "
            + " / ".join(f"{r['sys_s']:.2f}" for r in rs) + " |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--case", nargs=3, metavar=("MODE", "MB", "N"))
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    if a.case:
        print(json.dumps(case(a.case[0], int(a.case[1]), int(a.case[2]))))
    else:
        print(main(a.repeats))
