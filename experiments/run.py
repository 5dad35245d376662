"""Run every experiment in turn: ``python -m experiments.run`` (``make experiments``).

Each writes its report and plots into ``docs/results/``; the quick defaults of each
module apply (see their docstrings and the reports for exactly what ran).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence

from experiments import error_map, fig3, fig5, fig6, table1


def main(argv: Sequence[str] | None = None) -> int:
    """Run Fig. 3, Fig. 5, Fig. 6, Table I (with the baselines) and the error map, in turn."""
    for mod in (fig3, fig5, fig6, table1, error_map):
        t = time.perf_counter()
        mod.main([])
        print(f"{mod.__name__}: {time.perf_counter() - t:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
