"""Run every experiment in turn: ``python -m experiments.run`` (``make experiments``).

Each writes its report and plots into ``docs/results/``; the quick defaults of each
module apply (see their docstrings and the reports for exactly what ran).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path


def main(argv: Sequence[str] | None = None) -> int:
    """Run Fig. 3, Fig. 5, Fig. 6, Table I (with the baselines) and the error map, in turn.

    The shared data folder is ``--data DIR``, else ``$REBLUR_DATA``, else
    ``../shared/data`` beside the repository; without it, one line on stderr and exit 2.
    """
    ap = argparse.ArgumentParser(prog="python -m experiments.run",
                                 description="Run every experiment in turn.")
    ap.add_argument("--data", type=Path, default=None,
                    help="the shared data folder (default: $REBLUR_DATA, else "
                         "../shared/data beside the repository)")
    args = ap.parse_args(list(argv) if argv is not None else None)
    if args.data is not None:
        os.environ["REBLUR_DATA"] = str(args.data)
    # imported once the data folder is known (the modules read it on import)
    from experiments import error_map, fig3, fig5, fig6, table1
    from experiments.common import DataMissing, data_dir, dev_pairs

    try:
        dev_pairs()
        for mod in (fig3, fig5, fig6, table1, error_map):
            t = time.perf_counter()
            mod.main([])
            print(f"{mod.__name__}: {time.perf_counter() - t:.0f} s", flush=True)
    except DataMissing as exc:
        print(f"experiments: error: {exc} (data folder: {data_dir()})", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
