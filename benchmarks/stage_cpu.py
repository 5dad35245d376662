"""CPU and wall time per stage of one ``reblur detect`` run, in process
(``python -m benchmarks.stage_cpu REF OBS [--out DIR]``).

On a shared host the wall times of ``report.json`` hold the other jobs' share of the
cores; the CPU time (``time.process_time``: every thread of the process) of a stage does
not.  The run is the CLI's (``reblur.cli.run``), with timers wrapped around the functions
of :data:`STAGES` (a stage called several times adds up; nested stages count in both).
Prints one line per stage, slowest first, then the import of ``reblur.cli`` and the whole
run, with the minor page faults of the process meanwhile (fresh pages touched, 4 KB each:
on a VM that backs memory lazily they are kernel time); ``--profile module:function``
adds a cProfile of that function (threads other than the caller's are not profiled: their
work shows as waits).  The tile pass's chunk caches (:func:`reblur.io.chunk_cached`, inputs
chunked in tiles on disk) are listed last: their bound, and the chunks they served from
memory (hits) and read from the store (reads).  Cases of
``python -m benchmarks.cost`` are in its cache folder
(``$TMPDIR/reblur-cost/1mp_unchanged/ref.tif`` ...).
"""

from __future__ import annotations

import argparse
import cProfile
import functools
import importlib
import pstats
import resource
import sys
import tempfile
import time
from pathlib import Path

#: ``module:function`` timed by default: the stages of ``detect_changes`` and the writing.
STAGES = (
    "reblur.pipeline:align_coarse",
    "reblur.align.coarse:match_features",
    "reblur.align.coarse:gradient_align",
    "reblur.align.coarse:ecc_refine",
    "reblur.align.coarse:polish_and_verify",
    "reblur.pipeline:photometric_prefit",
    "reblur.pipeline:select_windows",
    "reblur.pipeline:refine_alignment",
    "reblur.pipeline:estimate_field",
    "reblur.pipeline:reblur_and_decide",
    "reblur.pipeline:fit_photometry",
    "reblur.pipeline:run_tiles",
    "reblur.report:write_report",
    "reblur.report:motion_figure",
    "reblur.report:field_figure",
    "reblur.report:_write_viewer",
)


def _timed(spec: str, acc: dict[str, list[float]]) -> None:
    """Replace ``module:function`` by a wrapper adding its wall and CPU time to ``acc``."""
    mod_name, name = spec.split(":")
    mod = importlib.import_module(mod_name)
    f = getattr(mod, name)

    @functools.wraps(f)
    def wrapper(*args, **kwargs):
        w, c, m = time.perf_counter(), time.process_time(), _minflt()
        try:
            return f(*args, **kwargs)
        finally:
            row = acc.setdefault(spec, [0, 0.0, 0.0, 0])
            row[0] += 1
            row[1] += time.perf_counter() - w
            row[2] += time.process_time() - c
            row[3] += _minflt() - m

    setattr(mod, name, wrapper)


def main(argv: list[str] | None = None) -> dict[str, list[float]]:
    """Run ``reblur detect REF OBS --out OUT -q`` in process; return ``{stage: [calls,
    wall, cpu]}`` (also printed)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reference", type=Path)
    ap.add_argument("observed", type=Path)
    ap.add_argument("--out", type=Path, default=None,
                    help="output folder (default: a temporary one, removed)")
    ap.add_argument("--stages", default=",".join(STAGES),
                    help="comma-separated module:function to time")
    ap.add_argument("--profile", default=None, metavar="MODULE:FUNCTION",
                    help="also profile this function (cProfile) and print its top entries")
    ap.add_argument("--top", type=int, default=30, help="entries of the profile printed")
    ap.add_argument("--workers", type=int, default=None,
                    help="reblur detect's --workers (1: every tile in the profiled thread)")
    a = ap.parse_args(argv)
    w0, c0, m0 = time.perf_counter(), time.process_time(), _minflt()
    import reblur.cli

    acc: dict[str, list[float]] = {"import reblur.cli": [1, time.perf_counter() - w0,
                                                         time.process_time() - c0,
                                                         _minflt() - m0]}
    for spec in a.stages.split(","):
        _timed(spec, acc)
    prof = _profiled(a.profile) if a.profile else None
    caches = _caches_kept()
    with tempfile.TemporaryDirectory() as tmp:
        out = a.out or Path(tmp) / "out"
        args = ["detect", str(a.reference), str(a.observed), "--out", str(out), "-q",
                "--overwrite"]
        if a.workers is not None:
            args += ["--workers", str(a.workers)]
        try:
            reblur.cli.run(args, standalone_mode=False)
        finally:
            acc["whole run"] = [1, time.perf_counter() - w0, time.process_time() - c0,
                                _minflt() - m0]
    print(f"{'stage':45s} {'calls':>5s} {'wall s':>7s} {'CPU s':>7s} {'faults':>8s}")
    for spec, (n, wall, cpu, flt) in sorted(acc.items(), key=lambda kv: -kv[1][2]):
        print(f"{spec:45s} {n:5d} {wall:7.2f} {cpu:7.2f} {flt:8d}")
    for c in caches:
        print(f"chunk cache: {c.max_bytes / 2**20:.0f} MB bound, {c.hits} hits, "
              f"{c.misses} reads")
    if prof is not None:
        print(f"\nprofile of {a.profile} (internal time, then cumulative):")
        try:
            stats = pstats.Stats(prof)
        except TypeError:  # nothing was recorded
            print(f"{a.profile} was not called through that name: name the module that "
                  "calls it (e.g. reblur.select:estimate_motion)")
        else:
            for key in ("tottime", "cumulative"):
                stats.sort_stats(key).print_stats(a.top)
    return acc


def _caches_kept() -> list:
    """The :class:`reblur.io.ChunkCache` readers :func:`reblur.pipeline.reblur_and_decide`
    creates from now on (through ``chunk_cached``), for their counts after the run."""
    import reblur.pipeline as pipeline
    from reblur.io import ChunkCache

    made: list = []
    make = pipeline.chunk_cached

    @functools.wraps(make)
    def wrapper(*args, **kwargs):
        c = make(*args, **kwargs)
        if isinstance(c, ChunkCache):
            made.append(c)
        return c

    pipeline.chunk_cached = wrapper
    return made


def _minflt() -> int:
    """Minor page faults of this process so far (every thread)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def _profiled(spec: str) -> cProfile.Profile:
    """Replace ``module:function`` by a wrapper that runs it under one shared profiler
    (its callers' references to it included: it is looked up at call time)."""
    mod_name, name = spec.split(":")
    mod = importlib.import_module(mod_name)
    f = getattr(mod, name)
    prof = cProfile.Profile()

    @functools.wraps(f)
    def wrapper(*args, **kwargs):
        prof.enable()
        try:
            return f(*args, **kwargs)
        finally:
            prof.disable()

    setattr(mod, name, wrapper)
    return prof


if __name__ == "__main__":
    main(sys.argv[1:])
