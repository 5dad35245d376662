"""Rolling-shutter pairs: false alarms and recall with the global and the rolling model
(``python -m benchmarks.rolling``).

Pairs from the test bed's rolling-shutter mode (:mod:`reblur.testbed.rolling`): one
smooth 6-D path over two exposures, row ``y`` integrating ``[r y / H, r y / H + 1]`` of it
(64 sub-poses per exposure, bicubic warps), a perspective viewpoint change, an 8-bit
sensor with 1 DN read noise; LEVIR ``test_7`` (grey), a centred crop.  Readout fractions
0 (a global shutter), 0.25, 0.5 and 1.0 share the path, the viewpoint and the noise
streams; each is made without change and with pasted changes (10-40 % contrast).

Per pair, :func:`reblur.detect_changes` runs with ``shutter="global"`` (before) and with
``"auto"`` (and ``"rolling"`` with ``--all``): ``FAR`` is the flagged share of the
unchanged known pixels farther than 3 px from a change, ``recall`` the flagged share of
the changed known pixels; ``model`` is what auto kept, ``r est`` the estimated readout,
``s`` the run's wall seconds and ``cpu s`` its process CPU seconds (the machine is shared:
compare the two models' times within one run).  Rows go to ``docs/rolling_runs.json``.

``--gopro C:K,...`` runs real pairs instead: the GoPro HERO's CMOS sensor reads its rows
out one after another, so the k-frame averages of
:func:`reblur.testbed.gopro_pair` (sharp frame ``C`` against the mean of the ``K`` frames
around it) carry a real rolling shutter.  There is no truth: per pair and model, the
flagged share, the flagged share outside the moving people
(:func:`benchmarks.alignment.moving_area`, derived from the raw frames), what auto kept
and its estimated readout.  Rows go to ``docs/rolling_gopro_runs.json``.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from benchmarks.common import REPO

BOUNDARY = 3
RUNS = REPO / "docs" / "rolling_runs.json"
GOPRO_RUNS = REPO / "docs" / "rolling_gopro_runs.json"


def make(readout: float, changes: bool, size: int, seed: int = 0):
    """One rolling-shutter pair of the benchmark (a :class:`~reblur.testbed.RealismPair`)."""
    from reblur.testbed import levir_image
    from reblur.testbed.rolling import make_rolling_pair

    scene = levir_image("test_7", gray=True)
    return make_rolling_pair(scene, readout=readout, size=(size, size), bits=8, noise_dn=1.0,
                             n_changes=8 if changes else 0, seed=seed,
                             viewpoint={"shift_px": 20.0})


def scores(change: np.ndarray, truth: np.ndarray, known: np.ndarray) -> dict:
    """FAR (unchanged pixels beyond ``BOUNDARY`` px of a change) and recall."""
    import cv2

    k = 2 * BOUNDARY + 1
    near = cv2.dilate(truth.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    neg, pos = known & ~near, known & truth
    return {"far": float(np.count_nonzero(change & neg) / max(np.count_nonzero(neg), 1)),
            "recall": (float(np.count_nonzero(change & pos) / np.count_nonzero(pos))
                       if pos.any() else None)}


def run(pair, shutter: str, bands: int | None = None, columns: int | None = None) -> dict:
    """``detect_changes`` with a shutter model (``bands`` row bands and ``columns``
    estimation windows per band; None: :class:`~reblur.rolling.RollingParams`'), scored."""
    import reblur
    from reblur.rolling import RollingParams

    given = {"n_bands": bands, "columns": columns}
    params = RollingParams(**{k: v for k, v in given.items() if v is not None})
    t, c = time.perf_counter(), time.process_time()
    res = reblur.detect_changes(pair.reference, pair.observed, shutter=shutter,
                                rolling=params)
    seconds, cpu = time.perf_counter() - t, time.process_time() - c
    known = pair.valid & ~np.asarray(res.unknown, bool)
    out = scores(np.asarray(res.change, bool), pair.truth, known)
    sh = res.decision.get("shutter", {})
    out.update(seconds=seconds, cpu_seconds=cpu,
               shutter_seconds=res.timings.get("shutter", 0.0),
               model=sh.get("model", "global"), readout=sh.get("readout"),
               readout_quartiles=sh.get("readout_quartiles"),
               drop=sh.get("criterion", {}).get("drop"))
    return out


def matrix(size: int, readouts, shutters, bands: int | None = None,
           changes=(False, True), columns: int | None = None) -> list[dict]:
    rows = []
    for ch in changes:
        for r in readouts:
            pair = make(r, ch, size)
            row = {"size": size, "readout": r, "changes": ch, "bands": bands,
                   "columns": columns}
            for sh in shutters:
                row[sh] = run(pair, sh, bands, columns)
            print(json.dumps(row), flush=True)
            rows.append(row)
    return rows


def gopro_rows(pairs: list[tuple[int, int]], shutters) -> list[dict]:
    """Real GoPro k-frame averages (``(centre, k)``), every model, scored against the
    moving area."""
    from benchmarks.alignment import moving_area
    from benchmarks.failure_modes import _scores
    from reblur.testbed import gopro_frame_indices, gopro_pair

    rows = []
    for c, k in pairs:
        ref, obs = gopro_pair(c, k)
        moving = moving_area(c, list(gopro_frame_indices(c, k)))
        row = {"centre": c, "k": k, "moving_share": float(moving.mean())}
        for sh in shutters:
            import reblur

            t, cpu = time.perf_counter(), time.process_time()
            res = reblur.detect_changes(ref, obs, shutter=sh)
            s = _scores(np.asarray(res.change, bool), np.asarray(res.unknown, bool),
                        {"truth": moving, "valid": np.ones_like(moving)})
            info = res.decision.get("shutter", {})
            row[sh] = dict(flagged=s["flagged"], outside=s["far"],
                           model=info.get("model", "global"), readout=info.get("readout"),
                           readout_quartiles=info.get("readout_quartiles"),
                           drop=info.get("criterion", {}).get("drop"),
                           seconds=time.perf_counter() - t,
                           cpu_seconds=time.process_time() - cpu)
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def gopro_table(rows: list[dict], shutters) -> str:
    head = "| centre | k | moving area | " + " | ".join(
        f"{s} flagged | outside moving | model | r est (quartiles) | RSS drop | s (cpu s)"
        for s in shutters) + " |"
    lines = [head, "|" + "---|" * (3 + 6 * len(shutters))]
    for row in rows:
        cells = [str(row["centre"]), str(row["k"]), f"{100 * row['moving_share']:.1f} %"]
        for sh in shutters:
            d = row[sh]
            r = "-" if d.get("readout") is None else f"{d['readout']:.2f}"
            if d.get("readout_quartiles"):
                r += " ({:.2f}-{:.2f})".format(*d["readout_quartiles"])
            drop = "-" if d.get("drop") is None else f"{100 * d['drop']:.0f} %"
            cells += [f"{100 * d['flagged']:.2f} %", f"{100 * d['outside']:.2f} %",
                      d["model"], r, drop,
                      f"{d['seconds']:.0f} ({d['cpu_seconds']:.0f})"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _cell(d: dict) -> list[str]:
    rec = "-" if d["recall"] is None else f"{d['recall']:.3f}"
    r = "-" if d.get("readout") is None else f"{d['readout']:.2f}"
    if d.get("readout_quartiles"):
        r += " ({:.2f}-{:.2f})".format(*d["readout_quartiles"])
    return [f"{100 * d['far']:.3f} %", rec, d["model"], r,
            f"{d['seconds']:.0f} ({d.get('cpu_seconds', float('nan')):.0f})"]


def table(rows: list[dict], shutters) -> str:
    head = "| readout | changes | " + " | ".join(
        f"{s} FAR | recall | model | r est (quartiles) | s (cpu s)" for s in shutters) + " |"
    lines = [head, "|" + "---|" * (2 + 5 * len(shutters))]
    for row in rows:
        cells = [f"{row['readout']:g}", "yes" if row["changes"] else "no"]
        for s in shutters:
            cells += _cell(row[s])
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=768, help="side of the pairs (px)")
    ap.add_argument("--readouts", default="0,0.25,0.5,1", help="comma-separated fractions")
    ap.add_argument("--all", action="store_true", help="also shutter='rolling'")
    ap.add_argument("--bands", type=int, default=None,
                    help="row bands of the rolling model (default RollingParams')")
    ap.add_argument("--columns", type=int, default=None,
                    help="estimation windows per band across the width (default "
                         "RollingParams'; 2: the edges only, the layout before b4fd12f)")
    ap.add_argument("--no-change-only", action="store_true", help="only the pairs without "
                    "changes")
    ap.add_argument("--no-save", action="store_true", help=f"do not write {RUNS.name}")
    ap.add_argument("--gopro", default=None, metavar="C:K,...",
                    help="real GoPro k-frame averages (centre:k) instead of the test bed")
    a = ap.parse_args()
    shutters = ["global", "auto"] + (["rolling"] if a.all else [])
    if a.gopro:
        pairs = [tuple(int(v) for v in p.split(":")) for p in a.gopro.split(",")]
        rows = gopro_rows(pairs, shutters)
        if not a.no_save:
            GOPRO_RUNS.write_text(json.dumps(rows, indent=1))
        print(gopro_table(rows, shutters))
        raise SystemExit(0)
    rows = matrix(a.size, [float(v) for v in a.readouts.split(",")], shutters, a.bands,
                  (False,) if a.no_change_only else (False, True), a.columns)
    if not a.no_save:
        RUNS.write_text(json.dumps(rows, indent=1))
    print(table(rows, shutters))
