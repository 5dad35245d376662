"""The solver's NNLS by exchange against scipy's NNLS on every Newton step of a run
(``python -m benchmarks.nnls_exchange [--only PREFIX]``; issue #28).

The active set's finite Newton method (:func:`reblur.solve._huber_newton`) solves an NNLS on
the cached Gram at every step: :func:`reblur.solve._nnls_gram`, first by block principal
pivoting from a guessed non-zero set (:func:`reblur.solve._nnls_exchange`), then scipy's
NNLS (Lawson-Hanson) when :data:`reblur.solve._EXCHANGES` sets do not settle.  This
benchmark runs ``reblur detect`` on each pair in a fresh process; a wrapper computes every
solve both ways, the run going on with the exchange's answer as a plain run does, and
counts:

* the solves, their sizes, and how many the exchange answered;
* the sets the exchange tried (``scipy.linalg.cho_factor`` calls, one per set);
* the time of each way (the exchange's including its fallback where it gave up);
* the largest difference of the two answers relative to the largest weight, and the
  solves whose non-zero sets differ.

Pairs (:func:`benchmarks.gram_work.pairs`, the largest active sets by default): the test
bed's 1.5 degree tilt, the cost benchmark's defocus pair, GoPro 0477 / 16 frames.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import run_case

#: The pairs run by default (name prefixes of :func:`benchmarks.gram_work.pairs`).
DEFAULT = ("test bed, shake tilt", "cost pair, defocus", "GoPro 0477 frame 13, 16")


def one(ref: Path, obs: Path) -> dict:
    """``reblur detect ref obs`` in this process, every NNLS solved both ways."""
    import scipy.linalg

    import reblur.solve as S
    from reblur.cli import run

    rows: list[tuple] = []
    sets = [0]
    answered = [False]
    factor = scipy.linalg.cho_factor
    solve, exchange = S._nnls_gram, S._nnls_exchange

    def counted_factor(*args, **kwargs):
        sets[0] += 1
        return factor(*args, **kwargs)

    def recorded_exchange(*args):
        w = exchange(*args)
        answered[0] = w is not None
        return w

    def both(G, b, support=None):
        t = time.perf_counter()
        ref_w = solve(G, b)
        t_nnls = time.perf_counter() - t
        sets[0], answered[0] = 0, False
        t = time.perf_counter()
        w = solve(G, b, support)
        t_exchange = time.perf_counter() - t
        scale = max(float(np.max(ref_w)), 1e-300)
        rows.append((G.shape[0], answered[0], sets[0], t_nnls, t_exchange,
                     float(np.max(np.abs(w - ref_w))) / scale,
                     bool(np.any((w > 0) != (ref_w > 0)))))
        return w

    scipy.linalg.cho_factor = counted_factor
    S._nnls_gram, S._nnls_exchange = both, recorded_exchange
    try:
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "out"
            sys.argv = ["reblur", "detect", str(ref), str(obs), "--out", str(out), "-q"]
            try:
                run()
            except SystemExit as e:
                if e.code:
                    raise
    finally:
        scipy.linalg.cho_factor = factor
        S._nnls_gram, S._nnls_exchange = solve, exchange
    a = np.array(rows, dtype=float).reshape(-1, 7)
    return {"solves": len(rows), "size_min": int(a[:, 0].min()), "size_max": int(a[:, 0].max()),
            "answered": int(a[:, 1].sum()), "sets_max": int(a[:, 2].max()),
            "sets_median": float(np.median(a[:, 2])), "nnls_s": float(a[:, 3].sum()),
            "exchange_s": float(a[:, 4].sum()), "max_rel_diff": float(a[:, 5].max()),
            "support_differs": int(a[:, 6].sum())}


def main(only: tuple[str, ...] = DEFAULT) -> str:
    """Run the pairs whose names start with one of ``only``; the markdown section."""
    from benchmarks.gram_work import pairs

    rows = []
    for name, ref, obs in pairs():
        if not name.startswith(only):
            continue
        r = run_case("benchmarks.nnls_exchange", "--one", str(ref), str(obs),
                     blas_threads=None)
        r["name"] = name
        print(json.dumps(r), flush=True)
        rows.append(r)
    lines = [
        "## The solver's NNLS: exchange against scipy's (`python -m benchmarks.nnls_exchange`)",
        "",
        "Each pair through `reblur detect` in a fresh process; every Newton step's NNLS "
        "solved by scipy's NNLS (Lawson-Hanson) and by `solve._nnls_gram` from the step's "
        "guessed non-zero set (block principal pivoting, scipy's NNLS after "
        "`solve._EXCHANGES` sets), the run going on with the latter. Sets: Cholesky "
        "factorisations of the exchange (one per set tried). Times: every solve's, summed "
        "(the exchange's with its fallback). Difference: the largest of the two answers' "
        "over the largest weight.",
        "",
        "| pair | solves | poses | answered by the exchange | sets (median / max) "
        "| scipy NNLS (s) | exchange (s) | largest difference | non-zero sets differ |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['name']} | {r['solves']} | {r['size_min']}-{r['size_max']} "
            f"| {r['answered']} | {r['sets_median']:.0f} / {r['sets_max']} "
            f"| {r['nnls_s']:.2f} | {r['exchange_s']:.2f} | {r['max_rel_diff']:.1e} "
            f"| {r['support_differs']} |")
    return "\n".join(lines)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--one", nargs=2, type=Path, metavar=("REF", "OBS"),
                    help="one pair in this process (prints JSON)")
    ap.add_argument("--only", action="append", default=None,
                    help="pairs whose names start with this (repeatable; default: "
                         + "; ".join(DEFAULT) + ")")
    a = ap.parse_args()
    if a.one:
        print(json.dumps(one(*a.one)))
    else:
        from benchmarks.run import write_section

        body = main(tuple(a.only) if a.only else DEFAULT)
        write_section("nnls_exchange", body)
        print(body)
