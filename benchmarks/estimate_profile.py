"""Where the time of a large-image estimate goes, level by level.

``python -m benchmarks.estimate_profile`` prints a markdown section; ``--case SIDE`` runs one
geometry of :func:`benchmarks.large_motion.run_timing` in this process and prints JSON.
Wrappers around the estimate's steps record, for every coarse-to-fine level:

* the operators' build (warps, spectra and the first touch of their memory): wall time,
  the process's kernel time and minor page faults during it;
* the solve: wall time, and inside it every growth of the cached Gram products
  (``solve._gram_add``: the active and the new columns, wall time), the Huber Newton
  steps (``solve._huber_newton``), and the rest (the adjoints over the whole grid, the
  candidates, the bookkeeping).

Kernel time is the process's (every thread's), so it also covers the benchmark scene's
synthesis where that runs inside a build (the first levels read the reference windows).
The wrappers only observe: the estimate is the one ``benchmarks.large_motion`` times (the
same unseen windows, printed for checking).
"""

from __future__ import annotations

import argparse
import resource
import time

from benchmarks.common import run_case


def _usage() -> tuple[float, float, int]:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return time.perf_counter(), r.ru_stime, r.ru_minflt


def profile_case(side: int) -> dict:
    """Run the timing geometry ``side`` of ``benchmarks.large_motion`` with the wrappers."""
    import reblur.estimate as E
    import reblur.solve as S
    from benchmarks.large_motion import run_timing

    levels: list[dict] = []
    orig = dict(build=E._build_operators, solve=E.active_set, gram=S._gram_add,
                newton=S._huber_newton)

    def build(*a, **k):
        t0, s0, f0 = _usage()
        try:
            return orig["build"](*a, **k)
        finally:
            t1, s1, f1 = _usage()
            levels.append(dict(build_s=t1 - t0, build_kernel_s=s1 - s0, build_faults=f1 - f0,
                               gram=[], newton_s=0.0, newton_steps=0))

    def solve(*a, **k):
        t0 = time.perf_counter()
        try:
            return orig["solve"](*a, **k)
        finally:
            levels[-1]["solve_s"] = time.perf_counter() - t0

    def gram(ws, active, new, *a):
        t0 = time.perf_counter()
        try:
            return orig["gram"](ws, active, new, *a)
        finally:
            if new:
                levels[-1]["gram"].append((len(active), len(new), time.perf_counter() - t0))

    def newton(*a, **k):
        t0 = time.perf_counter()
        out = orig["newton"](*a, **k)
        levels[-1]["newton_s"] += time.perf_counter() - t0
        levels[-1]["newton_steps"] += int(out[2])
        return out

    E._build_operators, E.active_set, S._gram_add, S._huber_newton = (
        build, solve, gram, newton)
    try:
        t0, s0, _ = _usage()
        (H, W), grid, dt, est, unseen, synth = run_timing(side)
        _, s1, _ = _usage()
    finally:
        E._build_operators, E.active_set, S._gram_add, S._huber_newton = (
            orig["build"], orig["solve"], orig["gram"], orig["newton"])
    if len(levels) != len(est.info["levels"]):
        raise RuntimeError(f"{len(levels)} builds for {len(est.info['levels'])} levels: the "
                           "profile needs the coarse-to-fine estimate (a grid sized to the image)")
    for lv, info in zip(levels, est.info["levels"], strict=True):
        lv.update({k: info[k] for k in ("stride", "side", "n_angles", "n_t", "n_outer",
                                        "n_active")})
    return dict(H=H, W=W, time_s=dt, synthesis_s=synth, kernel_s=s1 - s0,
                unseen=[float(u) for u in unseen], levels=levels)


def main(side: int = 32000) -> str:
    """One fresh process at ``side`` (default the 1 Gpx geometry), as a markdown table."""
    r = run_case("benchmarks.estimate_profile", "--case", str(side), timeout=1800,
                 blas_threads=None)
    lines = [
        "## Where the estimate's time goes (`python -m benchmarks.estimate_profile`)",
        "",
        f"The {r['H']} x {r['W']} ({r['H'] * r['W'] / 1e6:.0f} MP) timing geometry of "
        "`benchmarks.large_motion` (four 400 px windows, grid sized to the image), one fresh "
        f"process: {r['time_s']:.2f} s in all, {r['synthesis_s']:.2f} s of it synthesising "
        f"the scene's windows, {r['kernel_s']:.2f} s of kernel time (every thread); unseen "
        "windows " + " / ".join(f"{u:.1f}" for u in r["unseen"]) + " dB. Per level: the "
        "operators' build (kernel time and minor faults: mostly the first touch of the "
        "stacks and spectra, and in the first levels the synthesis); the solve, of which "
        "the Gram growths (active + new columns: seconds) and the Newton steps; the rest "
        "of the solve is the adjoints over the whole grid and the bookkeeping. This VM's "
        "host backs fresh pages at a speed that varies within minutes "
        "(`python -m benchmarks.first_touch`), so the kernel times vary from run to run.",
        "",
        "| stride | side (px) | angles x translations | build (s) | build kernel (s) "
        "| faults | solve (s) | outer its. | Gram (s) | Gram growths: active + new (s) "
        "| Newton (s, steps) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for lv in r["levels"]:
        g = lv["gram"]
        lines.append(
            f"| {lv['stride']} | {lv['side']} | {lv['n_angles']} x {lv['n_t']} "
            f"| {lv['build_s']:.2f} | {lv['build_kernel_s']:.2f} | {lv['build_faults']} "
            f"| {lv['solve_s']:.2f} | {lv['n_outer']} | {sum(x[2] for x in g):.2f} | "
            + ", ".join(f"{a}+{n} ({t:.2f})" for a, n, t in g)
            + f" | {lv['newton_s']:.2f} ({lv['newton_steps']}) |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--case", type=int, help="one geometry at this side, in this process (JSON)")
    a = ap.parse_args()
    if a.case:
        import json

        print(json.dumps(profile_case(a.case)))
    else:
        print(main())
