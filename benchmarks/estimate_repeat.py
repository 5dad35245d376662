"""CPU of the window estimate of one ``reblur detect`` run, repeated in process, and its
weights against a saved run (``python -m benchmarks.estimate_repeat REF OBS``).

The run is the CLI's (``reblur.cli.main``); every :func:`reblur.estimate.estimate_motion`
call that :func:`reblur.select.select_windows` makes is recorded with its arguments and
result, then run again ``--repeat`` times, each timed by CPU (``time.process_time``, every
thread: other jobs on a shared host do not count) and wall time.  Prints one line per call:
its windows, the solver's outer iterations, CPU and wall (the best of the repeats), the
coarse-to-fine levels of the last repeat (stride, window side, poses, outer iterations,
wall seconds), and
with ``--compare FILE.npz`` the largest absolute difference of the weights, of the change
terms and of the occluded shares from those saved there by ``--save FILE.npz`` (e.g. by
another checkout: ``PYTHONPATH=OLD/src``).  ``--profile`` adds a cProfile of the first
repeat (threads other than the caller's are not profiled).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _record(calls: list) -> None:
    """Wrap ``reblur.select.estimate_motion`` so that its calls land in ``calls``."""
    import reblur.select as sel

    orig = sel.estimate_motion

    def wrapper(*args, **kwargs):
        est = orig(*args, **kwargs)
        calls.append((args, kwargs, est))
        return est

    sel.estimate_motion = wrapper


def _arrays(est) -> dict[str, np.ndarray]:
    out = {"weights": np.asarray(est.weights),
           "occluded": np.asarray(est.info["occluded"], float)}
    for i, c in enumerate(est.chi):
        out[f"chi{i}"] = np.asarray(c)
    return out


def main(argv: list[str] | None = None) -> list[dict]:
    """Run the pair, repeat its estimates; return one dict per estimate (also printed)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reference", type=Path)
    ap.add_argument("observed", type=Path)
    ap.add_argument("--repeat", type=int, default=3, help="runs of each estimate")
    ap.add_argument("--save", type=Path, default=None, help="save the results (.npz)")
    ap.add_argument("--compare", type=Path, default=None, help="compare with saved results")
    ap.add_argument("--profile", action="store_true", help="profile the first repeat")
    ap.add_argument("--top", type=int, default=30, help="entries of the profile printed")
    a = ap.parse_args(argv)
    import reblur.cli
    from reblur.estimate import estimate_motion

    calls: list = []
    _record(calls)
    with tempfile.TemporaryDirectory() as tmp:
        reblur.cli.main(["detect", str(a.reference), str(a.observed), "--out",
                         str(Path(tmp) / "out"), "-q", "--overwrite"], standalone_mode=False)
    saved = dict(np.load(a.compare)) if a.compare else None
    rows, keep = [], {}
    # CPU time of the profiled thread (set OPENBLAS_NUM_THREADS=1 for the estimate in one)
    prof = cProfile.Profile(time.process_time) if a.profile else None
    for i, (args, kwargs, _) in enumerate(calls):
        best = (np.inf, np.inf)
        est = None
        for rep in range(max(1, a.repeat)):
            if prof is not None and rep == 0:
                prof.enable()
            w0, c0 = time.perf_counter(), time.process_time()
            est = estimate_motion(*args, **kwargs)
            c1, w1 = time.process_time(), time.perf_counter()
            if prof is not None and rep == 0:
                prof.disable()
            best = (min(best[0], c1 - c0), min(best[1], w1 - w0))
        row = dict(call=i, boxes=est.info["windows"], n_outer=int(est.info["n_outer"]),
                   cpu_s=best[0], wall_s=best[1], occluded=list(est.info["occluded"]),
                   levels=[(lv["stride"], lv["side"], lv["n_angles"] * lv["n_t"],
                            lv["n_outer"], round(lv["time_s"], 3))
                           for lv in est.info.get("levels", [])])
        arrays = _arrays(est)
        keep.update({f"{i}_{k}": v for k, v in arrays.items()})
        if saved is not None:
            for k, v in arrays.items():
                ref = saved.get(f"{i}_{k}")
                row[f"max|d {k}|"] = (float(np.max(np.abs(v - ref)))
                                      if ref is not None and ref.shape == v.shape else None)
        rows.append(row)
        print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                       for k, v in row.items()))
    if a.save:
        np.savez_compressed(a.save, **keep)
    if prof is not None:
        for key in ("tottime", "cumulative"):
            pstats.Stats(prof).sort_stats(key).print_stats(a.top)
    return rows


if __name__ == "__main__":
    main(sys.argv[1:])
