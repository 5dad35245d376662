"""One reference against many observations: one run against separate runs.

``python -m benchmarks.many [--frames N] [--reference C] [--k K]``

The reference is GoPro frame ``C`` (``reblur.testbed.gopro_frame``; sequence GOPR0477_11_00
of the shared data, 1280 x 720, real hand-held shake, moving people); the observations are
``N`` frames spread evenly over the 24 of the sequence (``K > 1``: the mean of ``K``
consecutive frames around each, ``gopro_pair``, real blur), the reference's own frame left
out.  All are written as PNG files, then compared with the reference

* by ``N`` separate ``reblur detect REF OBS --out DIR -q`` processes, and
* by one ``reblur detect REF OBS1 ... OBSN --out DIR -q`` process (the reference's
  overviews, pyramid and features computed once: ``reblur.ReferenceCache``),

each timed from the outside: wall-clock seconds and the CPU seconds (user + system) of the
child processes.  The change masks of both are compared byte for byte.  Target (issue
#31): the many-observation run's time per frame at most half the separate runs'.

The figures depend on the machine's load; both are measured in turn on the same machine.
"""

from __future__ import annotations

import argparse
import csv
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import REPO, commit, machine


def _observations(n: int, reference: int, k: int) -> list[int]:
    """``n`` centre frames spread evenly over the valid ones (the reference's left out
    for ``k = 1``)."""
    from reblur.testbed.gopro import N_FRAMES

    lo, hi = 1 + k // 2, N_FRAMES - (k - 1) // 2
    valid = [c for c in range(lo, hi + 1) if not (k == 1 and c == reference)]
    if n > len(valid):
        raise SystemExit(f"benchmarks.many: error: {n} frames asked, {len(valid)} available "
                         f"for k={k}")
    idx = np.unique(np.round(np.linspace(0, len(valid) - 1, n)).astype(int))
    return [valid[i] for i in idx]


def _write_inputs(folder: Path, reference: int, centres: list[int], k: int) -> list[Path]:
    from reblur.io import write_png
    from reblur.testbed import gopro_frame, gopro_pair

    write_png(folder / "ref.png", gopro_frame(reference))
    paths = []
    for c in centres:
        obs = gopro_frame(c) if k == 1 else gopro_pair(c, k)[1]
        p = folder / f"obs{c:02d}.png"
        write_png(p, obs)
        paths.append(p)
    return paths


def _timed(args: list[str]) -> tuple[float, float, subprocess.CompletedProcess]:
    """Run ``python -m reblur ARGS``: (wall s, CPU s of the child, the process)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "reblur", *args], capture_output=True,
                          text=True, cwd=REPO, check=False)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, proc


#: Stages of report.json's ``timings_s`` shown per frame.
STAGES = ("open", "align", "photometry", "estimate", "refine", "field", "reblur_decide",
          "report")


def _stage_means(folders: list[Path]) -> dict[str, float]:
    """Mean seconds per stage over the runs' report.json files (those that exist)."""
    got: dict[str, list[float]] = {}
    for f in folders:
        if (f / "report.json").exists():
            t = json.loads((f / "report.json").read_text())["timings_s"]
            for k in STAGES:
                got.setdefault(k, []).append(float(t.get(k) or 0.0))
    return {k: round(float(np.mean(v)), 2) for k, v in got.items()}


def measure(n: int, reference: int = 12, k: int = 1, keep: Path | None = None) -> dict:
    """Run both ways on ``n`` observations; the figures as a dict."""
    work = Path(tempfile.mkdtemp(prefix="reblur-many-")) if keep is None else keep
    work.mkdir(parents=True, exist_ok=True)
    try:
        centres = _observations(n, reference, k)
        obs = _write_inputs(work, reference, centres, k)
        ref = work / "ref.png"
        sep_wall, sep_cpu, failed = [], [], {}
        for p in obs:
            w, c, proc = _timed(["detect", str(ref), str(p), "--out", str(work / "sep" / p.stem),
                                 "-q"])
            sep_wall.append(w)
            sep_cpu.append(c)
            if proc.returncode != 0:
                failed[p.stem] = (proc.stderr.strip().splitlines() or ["?"])[-1][:200]
            print(f"separate {p.stem}: {w:.1f} s wall, {c:.1f} s CPU", flush=True)
        m_wall, m_cpu, proc = _timed(["detect", str(ref), *map(str, obs), "--out",
                                      str(work / "many"), "-q"])
        print(f"many ({len(obs)}): {m_wall:.1f} s wall, {m_cpu:.1f} s CPU", flush=True)
        rows = {}
        if (work / "many" / "summary.csv").exists():
            with open(work / "many" / "summary.csv", newline="") as f:
                rows = {r["name"]: r for r in csv.DictReader(f)}
        ran = [i for i, p in enumerate(obs)
               if p.stem not in failed and rows.get(p.stem, {}).get("status") == "ok"]
        same = sum(
            (work / "sep" / p.stem / "changes.png").exists()
            and (work / "sep" / p.stem / "changes.png").read_bytes()
            == (work / "many" / p.stem / "changes.png").read_bytes()
            for p in obs if (work / "many" / p.stem / "changes.png").exists())
        return dict(
            commit=commit(), machine=machine(), frames=centres, k=k, reference=reference,
            separate_wall_s=round(sum(sep_wall), 1), separate_cpu_s=round(sum(sep_cpu), 1),
            many_wall_s=round(m_wall, 1), many_cpu_s=round(m_cpu, 1),
            per_frame_separate_wall_s=round(sum(sep_wall) / len(obs), 2),
            per_frame_many_wall_s=round(m_wall / len(obs), 2),
            per_frame_separate_cpu_s=round(sum(sep_cpu) / len(obs), 2),
            per_frame_many_cpu_s=round(m_cpu / len(obs), 2),
            wall_ratio=round(m_wall / sum(sep_wall), 3),
            cpu_ratio=round(m_cpu / sum(sep_cpu), 3),
            identical_masks=int(same), separate_failed=failed,
            many_returncode=proc.returncode,
            ran_in_both=len(ran),
            # frames that ran both ways: separate runs' wall time (processes included)
            # against the many-observation run's own seconds for each (summary.csv)
            ran_separate_wall_s=round(float(np.mean([sep_wall[i] for i in ran])), 2)
            if ran else None,
            ran_many_seconds=round(float(np.mean([float(rows[obs[i].stem]["seconds"])
                                                  for i in ran])), 2) if ran else None,
            many_failed={n: r["reason"][:200] for n, r in rows.items()
                         if r["status"] != "ok"},
            stages_separate=_stage_means([work / "sep" / p.stem for p in obs]),
            stages_many=_stage_means([work / "many" / p.stem for p in obs]),
        )
    finally:
        if keep is None:
            shutil.rmtree(work, ignore_errors=True)


def markdown(r: dict) -> str:
    """The figures as a markdown table."""
    return "\n".join([
        f"`python -m benchmarks.many --frames {len(r['frames'])} --reference "
        f"{r['reference']} --k {r['k']}` (commit {r['commit']}): GoPro frame "
        f"{r['reference']} against frames {', '.join(map(str, r['frames']))}"
        + (f" ({r['k']}-frame means)" if r["k"] > 1 else "") + ", 1280 x 720.",
        "",
        "| | wall s per frame | CPU s per frame |",
        "|---|---|---|",
        f"| {len(r['frames'])} separate `reblur detect` runs | "
        f"{r['per_frame_separate_wall_s']} | {r['per_frame_separate_cpu_s']} |",
        f"| one `reblur detect REF OBS...` run | {r['per_frame_many_wall_s']} | "
        f"{r['per_frame_many_cpu_s']} |",
        f"| ratio (target <= 0.5) | {r['wall_ratio']} | {r['cpu_ratio']} |",
        "",
        f"Ran both ways: {r['ran_in_both']} of {len(r['frames'])} (refused separately: "
        f"{', '.join(sorted(r['separate_failed'])) or 'none'}; in the many-observation run: "
        f"{', '.join(sorted(r['many_failed'])) or 'none'}); their change masks "
        f"identical: {r['identical_masks']} of {r['ran_in_both']}.  On those frames: "
        f"{r['ran_separate_wall_s']} s wall per separate run, {r['ran_many_seconds']} s per "
        "frame inside the many-observation run (summary.csv `seconds`).",
        "",
        "Mean seconds per frame by stage (report.json `timings_s`; the rest of the wall "
        "time is the process: start, imports, first calls):",
        "",
        "| | " + " | ".join(STAGES) + " |",
        "|---|" + "---|" * len(STAGES),
        *(f"| {label} | " + " | ".join(str(r[key].get(s, "-")) for s in STAGES) + " |"
          for label, key in (("separate", "stages_separate"), ("many", "stages_many"))),
    ])


def main(argv: list[str] | None = None) -> str:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.many",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=23,
                    help="observations (default 23: every frame but the reference)")
    ap.add_argument("--reference", type=int, default=12, help="reference frame, 1..24")
    ap.add_argument("--k", type=int, default=1,
                    help="frames averaged per observation (1: the frames themselves)")
    ap.add_argument("--keep", type=Path, default=None,
                    help="keep inputs and outputs in this folder")
    a = ap.parse_args(argv)
    r = measure(a.frames, a.reference, a.k, a.keep)
    md = markdown(r)
    print(md)
    print(json.dumps(r))
    return md


if __name__ == "__main__":
    main()
