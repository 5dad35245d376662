"""The estimate's Gram products on pairs of at most 1 MP: how much work, at what rate
(``python -m benchmarks.gram_work``; issue #28).

The active-set solver (:func:`reblur.solve.active_set`) caches ``A^T D A`` over its active
poses and grows it by each outer iteration's new columns (``solve._Window.block_products``):
per row block of a window it copies the active columns as contiguous rows and multiplies
them with the new ones (one GEMM).  This benchmark counts that work on each pair, in a
fresh ``reblur detect`` process with the defaults:

* the multiply-adds of the products (GMAC) and the column values copied for them;
* the CPU time spent in them (every thread's own CPU time, summed over the windows);
* the CPU time of the adjoint products ``F^T r`` (:meth:`reblur.operator.BlurOperator.rmatvec`,
  one per window per outer iteration: the KKT test's gradient over every pose, with the
  spectra the first one of an operator computes), the estimate's other large share;
* the rate reached, against this machine's single-thread DGEMM rate for the solver's
  typical shape (124 active + new columns against 24 new ones, 16000 pixels per block) and
  for a square-ish one (the BLAS's best);
* the time the same work needs at that typical rate on every core: a floor of the Gram
  products as they are computed now (fewer poses or fewer pixels lower it, a faster
  kernel does not by much).

Pairs: the test bed's 1 MP LEVIR test_7 pairs shaken by 6, 12 and 20 px and tilted by 1.5
degrees (:func:`benchmarks.shake_extent.make_case`), the cost benchmark's unchanged and defocus 1 MP
pairs (the defocus fills the solver's active bound: the largest Gram products), and
the shared data's real camera shake (:data:`benchmarks.cost.REAL_PAIRS` GoPro rows and
:data:`benchmarks.cost.GOPRO_AVERAGES`).  The wrapper only observes: the outputs are those
of a plain run.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from benchmarks.common import run_case

#: The solver's typical Gram growth: (active + new) x pixels against new x pixels.
TYPICAL_SHAPE = (124, 24, 16000)
#: A square-ish product, near the BLAS's best rate.
SQUARE_SHAPE = (100, 100, 16000)


def gemm_rate(shape: tuple[int, int, int], repeat: int = 40) -> float:
    """Single-thread DGEMM rate (GMAC/s) of ``A @ B.T``, ``A`` of ``(n_all, n_pix)`` and
    ``B`` its last ``n_new`` rows (the solver's product), best of three timings."""
    from threadpoolctl import threadpool_limits

    n_all, n_new, n_pix = shape
    a = np.random.default_rng(0).random((n_all, n_pix))
    b = np.ascontiguousarray(a[-n_new:])
    best = np.inf
    with threadpool_limits(1, user_api="blas"):
        a @ b.T
        for _ in range(3):
            t = time.perf_counter()
            for _ in range(repeat):
                a @ b.T
            best = min(best, (time.perf_counter() - t) / repeat)
    return n_all * n_new * n_pix / best / 1e9


#: Gram growths ``(active + new, new)`` over a 16000-pixel block for :func:`split_times`:
#: a warm start, growths near the active bound, a typical small one.
SPLIT_SHAPES = ((572, 572), (640, 126), (200, 96), (164, 24))


def split_times(repeat: int = 5) -> list[tuple[int, int, float, float, float]]:
    """Single-thread seconds (best of ``repeat``) of one Gram growth of each
    :data:`SPLIT_SHAPES` shape computed three ways: one GEMM of every column against the new
    ones (numpy's SYRK where there are no old ones); the old-by-new GEMM and the new-by-new
    SYRK (``solve._Window._block`` from ``solve._SYRK_FROM`` new columns); GEMMs of 48 new
    columns each over the rows up to their group (the upper triangle, as before 5a895c7).
    Rows ``(n_all, n_new, one, split, groups)``."""
    from threadpoolctl import threadpool_limits

    rng = np.random.default_rng(0)
    out = []
    for n_all, n_new in SPLIT_SHAPES:
        buf = rng.random((n_all + 8, 16500))
        at = buf[:n_all, :16000]  # a block of the solver's scratch: rows not contiguous
        n_old = n_all - n_new
        atn = at[n_old:]

        def one(at=at, atn=atn):
            return at @ atn.T

        def split(at=at, atn=atn, n_old=n_old):
            if n_old:
                at[:n_old] @ atn.T
            return atn @ atn.T

        def groups(at=at, atn=atn, n_old=n_old, n_new=n_new):
            for s0 in range(0, n_new, 48):
                s1 = min(s0 + 48, n_new)
                at[: n_old + s1] @ atn[s0:s1].T

        times = []
        with threadpool_limits(1, user_api="blas"):
            for fn in (one, split, groups):
                best = np.inf
                for _ in range(repeat):
                    t = time.perf_counter()
                    fn()
                    best = min(best, time.perf_counter() - t)
                times.append(best)
        out.append((n_all, n_new, *times))
    return out


def copy_and_product(shape: tuple[int, int, int] = TYPICAL_SHAPE, repeat: int = 100
                     ) -> tuple[float, float]:
    """Seconds of one Gram block's column copies and of its product, single thread: the
    ``n_all`` columns of ``n_pix`` pixels (rows of a 500 px window, shifted views of 13
    angle images, as ``_Window._block`` copies them) into one buffer, then the buffer
    against its last ``n_new`` rows."""
    from threadpoolctl import threadpool_limits

    n_all, n_new, n_pix = shape
    rng = np.random.default_rng(0)
    side, rows = 500, n_pix // 500
    images = rng.random((13, side + 30, side + 30, 1))
    views = [images[rng.integers(13), dy:dy + side, dx:dx + side]
             for dy, dx in rng.integers(0, 25, (n_all, 2))]
    buf = np.empty((n_all, rows * side))
    with threadpool_limits(1, user_api="blas"):
        t = time.perf_counter()
        for i in range(repeat):
            r0 = (i % (side // rows)) * rows
            for j, v in enumerate(views):
                np.copyto(buf[j].reshape(rows, side, 1), v[r0:r0 + rows])
        copy = (time.perf_counter() - t) / repeat
        t = time.perf_counter()
        for _ in range(repeat):
            buf @ buf[-n_new:].T
        product = (time.perf_counter() - t) / repeat
    return copy, product


@contextmanager
def counted_blocks():
    """Count the Gram growths of every :func:`reblur.solve.active_set` run inside: yields a
    dict whose ``macs`` (multiply-adds of the products), ``copied`` (column values copied
    for them), ``cpu_s`` (each thread's own CPU time in them, summed) and ``blocks`` grow
    as they run; ``adjoints`` and ``adjoint_cpu_s`` count the operators' adjoint products
    the same way.  The products themselves are left as they are."""
    import reblur.solve as S
    from reblur.operator import BlurOperator

    counts = {"macs": 0.0, "copied": 0.0, "cpu_s": 0.0, "blocks": 0, "adjoints": 0,
              "adjoint_cpu_s": 0.0}
    lock = threading.Lock()
    block = S._Window._block
    rmatvec = BlurOperator.rmatvec

    def counted_adjoint(self, residual):
        c = time.thread_time()
        out = rmatvec(self, residual)
        cpu = time.thread_time() - c
        with lock:
            counts["adjoints"] += 1
            counts["adjoint_cpu_s"] += cpu
        return out

    def counted(self, views, n_new, r0, r1, mk, buf, G, b, d):
        c = time.thread_time()
        block(self, views, n_new, r0, r1, mk, buf, G, b, d)
        cpu = time.thread_time() - c
        w, C = self.op.dimsd[1:]
        dense = mk.mean() >= S._DENSE_BLOCK
        n_pix = (r1 - r0) * w * C if dense else int(mk.sum()) * C
        n_all = len(views)
        n_old = n_all - n_new
        if n_old and n_new < S._SYRK_FROM:  # one GEMM
            macs = n_all * n_new * n_pix
        else:  # old against new (GEMM), new against new (SYRK: its upper triangle)
            macs = (n_old * n_new + n_new * (n_new + 1) // 2) * n_pix
        with lock:
            counts["macs"] += macs
            counts["copied"] += n_all * n_pix
            counts["cpu_s"] += cpu
            counts["blocks"] += 1

    S._Window._block = counted
    BlurOperator.rmatvec = counted_adjoint
    try:
        yield counts
    finally:
        S._Window._block = block
        BlurOperator.rmatvec = rmatvec


def one(ref: Path, obs: Path) -> dict:
    """``reblur detect ref obs`` in this process with its Gram growths counted."""
    from reblur.cli import run

    with counted_blocks() as counts, tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        sys.argv = ["reblur", "detect", str(ref), str(obs), "--out", str(out), "-q"]
        t = time.perf_counter()
        try:
            run()
        except SystemExit as e:
            if e.code:
                raise
        seconds = time.perf_counter() - t
        rep = json.loads((out / "report.json").read_text())
    info = rep["motion"]["info"]
    return {"seconds": seconds, "estimate_s": rep["timings_s"]["estimate"],
            "n_outer": (info.get("selection") or {}).get("n_outer", info.get("n_outer")),
            "n_active": info.get("n_active"), **counts}


def pairs() -> list[tuple[str, Path, Path]]:
    """``(name, reference, observation)`` of the benchmark's pairs (made or reused)."""
    from benchmarks.cost import CACHE, gopro_averages, make_case, real_pairs
    from benchmarks.shake_extent import make_case as shake_case

    out = []
    for name in ("6 px", "12 px", "20 px", "tilt 1.5 deg"):
        d = shake_case(name)
        out.append((f"test bed, shake {name}", d / "ref.tif", d / "obs.tif"))
    for content in ("unchanged", "defocus"):
        d = make_case(1, content, CACHE)
        out.append((f"cost pair, {content}", d / "ref.tif", d / "obs.tif"))
    out += [(n, r, o) for n, r, o in real_pairs("GoPro")]
    out += list(gopro_averages(CACHE))
    return out


def main() -> str:
    """Run every pair in a fresh process; the markdown section."""
    typical, square = gemm_rate(TYPICAL_SHAPE), gemm_rate(SQUARE_SHAPE)
    copy, product = copy_and_product()
    splits = split_times()
    cores = len(os.sched_getaffinity(0))
    rows = []
    for name, ref, obs in pairs():
        r = run_case("benchmarks.gram_work", "--one", str(ref), str(obs), blas_threads=None)
        r["name"] = name
        print(json.dumps(r, default=float), flush=True)
        rows.append(r)
    lines = [
        "## The estimate's Gram products at 1 MP (`python -m benchmarks.gram_work`)",
        "",
        "Each pair through `reblur detect` with the defaults in a fresh process, the "
        "solver's Gram growths (`solve._Window._block`) counted: multiply-adds, column "
        "values copied for them, CPU time (each thread's own, summed). This machine's "
        f"single-thread DGEMM: {typical:.1f} GMAC/s for the solver's typical product "
        f"({TYPICAL_SHAPE[0]} x {TYPICAL_SHAPE[2]} against {TYPICAL_SHAPE[1]} x "
        f"{TYPICAL_SHAPE[2]}), {square:.1f} GMAC/s for a square-ish one "
        f"({SQUARE_SHAPE[0]} x {SQUARE_SHAPE[1]}). One block of the typical shape: its "
        f"columns' copy {1e3 * copy:.2f} ms, its product {1e3 * product:.2f} ms "
        f"({100 * copy / (copy + product):.0f} % copying). Floor: the work at the typical "
        f"rate on {cores} cores.",
        "",
        "| pair | total (s) | estimate (s) | outer its. | active poses | Gram work (GMAC) "
        "| copied (G values) | Gram CPU (s) | rate (GMAC/s per thread) | floor (s) "
        "| adjoints | adjoint CPU (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        rate = r["macs"] / 1e9 / r["cpu_s"] if r["cpu_s"] > 0 else float("nan")
        lines.append(
            f"| {r['name']} | {r['seconds']:.1f} | {r['estimate_s']:.2f} | {r['n_outer']} | "
            f"{r['n_active']} | {r['macs'] / 1e9:.1f} | {r['copied'] / 1e9:.2f} | "
            f"{r['cpu_s']:.2f} | {rate:.1f} | {r['macs'] / 1e9 / typical / cores:.2f} | "
            f"{r['adjoints']} | {r['adjoint_cpu_s']:.2f} |")
    est = np.array([r["estimate_s"] for r in rows])
    work = np.array([r["macs"] / 1e9 for r in rows])
    slope, icpt = np.polyfit(work, est, 1)
    share = np.array([r["cpu_s"] for r in rows]) / cores / est
    adjoint = np.array([r["adjoint_cpu_s"] for r in rows]) / cores / est
    outside = [r["seconds"] - r["estimate_s"] for r in rows]
    lines += [
        "",
        f"- estimate time against the Gram work (least squares over the rows): "
        f"{icpt:.2f} s + {1e3 * slope:.0f} ms per GMAC; the Gram CPU over {cores} cores is "
        f"{100 * share.min():.0f}-{100 * share.max():.0f} % of the estimate's time, the "
        f"adjoints' {100 * adjoint.min():.0f}-{100 * adjoint.max():.0f} %",
        f"- rows' time outside the estimate: {min(outside):.1f}-{max(outside):.1f} s "
        "(in-process: no interpreter start-up)",
        "- one Gram growth over a 16000-pixel block, single thread (`split_times`; "
        "active + new against new): one GEMM / old-by-new GEMM + new-by-new SYRK / GEMMs of "
        "48 new columns (before 5a895c7): "
        + "; ".join(f"{a - n} + {n} against {n}: {1e3 * t1:.1f} / {1e3 * t2:.1f} / "
                    f"{1e3 * t3:.1f} ms" for a, n, t1, t2, t3 in splits),
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--one", nargs=2, type=Path, metavar=("REF", "OBS"),
                    help="one pair in this process (prints JSON)")
    a = ap.parse_args()
    if a.one:
        print(json.dumps(one(*a.one), default=float))
    else:
        from benchmarks.run import write_section

        body = main()
        write_section("gram_work", body)
        print(body)
