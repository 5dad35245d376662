"""Realism matrix: reblur and the register-and-difference baseline on pairs that reblur did
not make (``python -m benchmarks.realism``).

The pairs come from :mod:`reblur.testbed`, which shares no code with reblur's model: a
continuous 6-D camera path over 64 sub-poses, OpenCV's bicubic interpolation, a
perspective viewpoint change, a Poisson-Gaussian sensor with 8- or 16-bit quantisation, and
pasted changes whose contrast is 10-40 % of their surroundings' range.  The scene is a real
aerial image (LEVIR ``test_7``) at its native 1 MP, and upsampled (smooth content) to
25 MP and 100 MP, made tile by tile.

Rows: noise {0, 0.5, 2} DN x {8, 16} bit at each size.  Per row, for reblur (the
``reblur detect`` command, as a user runs it) and the baseline
(:func:`reblur.baselines.register_then_difference`):

* ``FAR``: flagged share of the unchanged pixels (known pixels farther than 3 px from a
  change: the boundary of a blurred change is not counted either way);
* ``recall`` and ``JC`` of the pasted changes (known pixels);
* geometry (reblur only): where reblur says an observation pixel comes from in the
  reference (the weighted mean over its poses of the pose homography composed with the
  final alignment) against where it really comes from (the mean over the 64 sub-poses:
  the blur kernel's centroid), RMS and max over a 17 x 17 lattice of known points.

Each size's camera path, viewpoint and changes are drawn once (seed 0), so the rows of a
size differ only in the sensor.  Large pairs are written once into ``--cache`` and reused.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import tifffile

from benchmarks.common import REPO

SIZES = {1: 1, 4: 2, 25: 5, 100: 10}  # MP -> upsampling factor of the 1024 px scene
ROWS = [(bits, noise) for bits in (8, 16) for noise in (0.0, 0.5, 2.0)]
BOUNDARY = 3  # px around a change counted neither as a false alarm nor as a miss


#: The hard geometry (``--hard``), as the external evaluation's pairs: a 0.3 degree roll
#: whatever the size (the corners of a 25 MP image move by ~25 px), a 60 px / 0.5 degree
#: perspective viewpoint change.
HARD_ROLL_DEG, HARD_VIEW = 0.3, {"shift_px": 60.0, "angle_deg": 0.5}
HARD_ROWS = [(bits, noise) for bits in (8, 16) for noise in (0.0, 2.0)]


def _plan(mp: int, bits: int, noise: float, hard: bool = False):
    from reblur.testbed import levir_image, plan_pair, shake_for, upsampled

    scene = levir_image("test_7", gray=True)
    if SIZES[mp] > 1:
        scene = upsampled(scene, SIZES[mp])
    motion, view = shake_for(scene.shape), {"shift_px": 20.0}
    if hard:
        motion, view = dict(motion, max_roll_deg=HARD_ROLL_DEG), HARD_VIEW
    return plan_pair(scene, bits=bits, noise_dn=noise, n_changes=8 * SIZES[mp] ** 2 // 4 + 8,
                     seed=0 if not hard else 3, motion=motion, viewpoint=view)


def _tiles(shape: tuple[int, ...], tile: int = 512):
    for y in range(0, shape[0], tile):
        for x in range(0, shape[1], tile):
            yield (y, min(y + tile, shape[0]), x, min(x + tile, shape[1]))


def _write(path: Path, shape, dtype, tile_fn) -> None:
    """A tiled (512 px) BigTIFF written tile by tile, through a temporary name."""
    tmp = path.with_suffix(".part.tif")
    tifffile.imwrite(tmp, (tile_fn(b) for b in _tiles(shape)), shape=shape, dtype=dtype,
                     tile=(512, 512), bigtiff=True, compression="zlib")
    os.replace(tmp, path)


def make_case(mp: int, bits: int, noise: float, cache: Path, hard: bool = False) -> Path:
    """Write (or reuse) the pair of one row: reference.tif, observed.tif, truth.tif,
    valid.tif, pair.json."""
    tag = f"{mp}mp" + ("_hard" if hard else "")
    d = cache / f"{tag}_{bits}bit_{noise:g}dn"
    if (d / "pair.json").exists():
        return d
    d.mkdir(parents=True, exist_ok=True)
    plan = _plan(mp, bits, noise, hard)
    shape = plan.shape
    dt = np.uint8 if bits == 8 else np.uint16
    _write(d / "reference.tif", shape, dt, plan.reference_tile)
    render = _rendered(plan, tag, cache)
    _write(d / "observed.tif", shape, dt,
           lambda b: plan.sense_observed(render[b[0]:b[1], b[2]:b[3]], b))
    _write(d / "truth.tif", shape[:2], np.uint8, lambda b: plan.truth_tile(b).astype(np.uint8))
    _write(d / "valid.tif", shape[:2], np.uint8, lambda b: plan.valid_tile(b).astype(np.uint8))
    info = dict(plan.info, homographies=np.asarray(plan.homographies).tolist())
    (d / "pair.json").write_text(json.dumps(info, default=float))
    return d


def _rendered(plan, tag: str, cache: Path):
    """The size's noise-free rendered observation (float32 tiled TIFF in ``cache``, made
    once: the rows of a size differ only in their sensor), opened lazily."""
    import zarr

    path = cache / f"{tag}_render.tif"
    if not path.exists():
        _write(path, plan.shape, np.float32, lambda b: plan.render_tile(b).astype(np.float32))
    return zarr.open(tifffile.imread(path, aszarr=True), mode="r")


def _scores(change: np.ndarray, truth: np.ndarray, known: np.ndarray) -> dict:
    import cv2

    k = 2 * BOUNDARY + 1
    near = cv2.dilate(truth.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    neg = known & ~near
    pos = known & truth
    tp = int(np.count_nonzero(change & pos))
    union = int(np.count_nonzero((change | truth) & known))
    return {"far": float(np.count_nonzero(change & neg) / max(np.count_nonzero(neg), 1)),
            "recall": tp / max(int(np.count_nonzero(pos)), 1),
            "jc": tp / max(union, 1)}


def _geometry(report: dict, homographies: np.ndarray, known: np.ndarray) -> dict:
    """Residual of reblur's reference location of a 17 x 17 lattice of known points."""
    from reblur.grid import mean_source_points, pose_homography
    from reblur.testbed import true_centroid

    H, W = known.shape
    ys, xs = np.meshgrid(np.linspace(0.03 * H, 0.97 * H, 17), np.linspace(0.03 * W, 0.97 * W, 17),
                         indexing="ij")
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1)
    pts = pts[known[pts[:, 1].astype(int), pts[:, 0].astype(int)]]
    if len(pts) == 0:
        return {"rms_px": float("nan"), "max_px": float("nan")}
    base = np.asarray(report["alignment"]["H"], float)
    g = report["motion"]["grid"]
    poses = report["motion"]["nonzero_poses"]
    est = mean_source_points(
        [pose_homography(p["tx"], p["ty"], p["tz"], p["rx"], p["ry"], p["rz"],
                         center=tuple(g["center"]), focal=g["focal"]) @ base for p in poses],
        [p["weight"] for p in poses], pts)
    err = np.hypot(*(est - true_centroid(homographies, pts)).T)
    return {"rms_px": float(np.sqrt(np.mean(err ** 2))), "max_px": float(err.max())}


def _read(path: Path) -> np.ndarray:
    return tifffile.imread(path)


def run_reblur(case: Path, out: Path, src: Path | None = None,
               config: Path | None = None) -> dict:
    """``reblur detect`` on a case, as a user runs it; scores against the truth.  ``src``:
    another checkout's ``src`` folder to run instead (e.g. an earlier commit's, for the
    figures before a change); ``config``: a parameter file (``reblur detect --config``)."""
    t = time.perf_counter()
    cmd = [sys.executable, "-m", "reblur", "detect", str(case / "reference.tif"),
           str(case / "observed.tif"), "--out", str(out), "--overwrite"]
    if config is not None:
        cmd += ["--config", str(config)]
    env = dict(os.environ, PYTHONPATH=str(src)) if src is not None else None
    r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    seconds = time.perf_counter() - t
    if r.returncode:
        return {"error": (r.stderr.strip().splitlines() or ["?"])[-1], "seconds": seconds}
    report = json.loads((out / "report.json").read_text())
    tif = out / "changes.tif"
    change = (_read(tif) if tif.exists() else _png(out / "changes.png")) > 0
    unknown = _png(out / "unknown.png") > 0 if (out / "unknown.png").exists() else \
        _read(out / "unknown.tif") > 0
    truth = _read(case / "truth.tif") > 0
    known = (_read(case / "valid.tif") > 0) & ~unknown
    info = json.loads((case / "pair.json").read_text())
    res = _scores(change, truth, known)
    res["geometry"] = _geometry(report, np.asarray(info["homographies"]), known)
    res["seconds"] = seconds
    res["threshold"] = report.get("threshold")
    ref = report.get("alignment", {}).get("details", {}).get("refinement", {})
    shifts = ref.get("probe_shifts")
    if shifts is not None:  # probes the refinement measured and used, of all
        res["probes"] = [sum(1 for d in shifts if "reason" not in d), len(shifts)]
    return res


def _png(path: Path) -> np.ndarray:
    import cv2

    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


def run_baseline(case: Path) -> dict:
    """Register (SIFT + RANSAC homography), difference, Otsu: the common practice."""
    from reblur.baselines import register_then_difference

    ref = _read(case / "reference.tif").astype(np.float32)
    obs = _read(case / "observed.tif").astype(np.float32)
    scale = float(max(ref.max(), obs.max(), 1.0))
    t = time.perf_counter()
    change, info = register_then_difference(ref / scale, obs / scale)
    seconds = time.perf_counter() - t
    truth = _read(case / "truth.tif") > 0
    known = (_read(case / "valid.tif") > 0) & ~np.asarray(info["unknown"], bool)
    res = _scores(change, truth, known)
    res["seconds"] = seconds
    return res


def matrix(sizes: list[int], cache: Path, baseline: bool = True,
           src: Path | None = None, hard: bool = False,
           config: Path | None = None) -> list[dict]:
    rows = []
    for mp in sizes:
        for bits, noise in (HARD_ROWS if hard else ROWS):
            t = time.perf_counter()
            case = make_case(mp, bits, noise, cache, hard)
            made = time.perf_counter() - t
            with tempfile.TemporaryDirectory() as tmp:
                rb = run_reblur(case, Path(tmp) / "out", src, config)
            row = {"mp": mp, "bits": bits, "noise": noise, "reblur": rb, "make_s": made,
                   "hard": hard}
            if baseline:
                row["baseline"] = run_baseline(case)
            print(json.dumps(row, default=float), flush=True)
            rows.append(row)
    return rows


def _pct(v: float) -> str:
    return f"{100 * v:.3f} %"


def table(rows: list[dict]) -> str:
    lines = [
        "| size | bits | noise (DN) | reblur FAR | recall | JC | geometry RMS / max (px) "
        "| probes | s | baseline FAR | recall | JC |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        rb, bl = r["reblur"], r.get("baseline", {})
        if "error" in rb:
            cells = [f"failed: {rb['error']}", "", "", "", "", f"{rb['seconds']:.0f}"]
        else:
            g = rb["geometry"]
            probes = "{} / {}".format(*rb["probes"]) if "probes" in rb else "-"
            cells = [_pct(rb["far"]), f"{rb['recall']:.3f}", f"{rb['jc']:.3f}",
                     f"{g['rms_px']:.2f} / {g['max_px']:.2f}", probes, f"{rb['seconds']:.0f}"]
        base = ([_pct(bl["far"]), f"{bl['recall']:.3f}", f"{bl['jc']:.3f}"] if bl
                else ["-", "-", "-"])
        size = f"{r['mp']} MP" + (" hard" if r.get("hard") else "")
        lines.append(f"| {size} | {r['bits']} | {r['noise']:g} | " + " | ".join(cells + base)
                     + " |")
    return "\n".join(lines)


BEFORE = REPO / "docs" / "realism_before.json"


def main(sizes: list[int] | None = None, cache: Path | None = None,
         src: Path | None = None, label: str | None = None,
         hard_sizes: list[int] | None = None, config: Path | None = None) -> str:
    """Run the matrix (and its hard-geometry rows at ``hard_sizes``); return the markdown
    section of ``docs/benchmarks.md``.

    With ``src`` (another checkout's ``src``), the rows are saved as the "before" figures
    (``docs/realism_before.json``, under ``label``) and only printed.  With ``config`` (a
    ``reblur detect --config`` file: a variant of the defaults) they are only printed."""
    sizes = [1, 25] if sizes is None else sizes
    hard_sizes = [4] if hard_sizes is None else hard_sizes
    cache = cache or Path(tempfile.gettempdir()) / "reblur-realism"
    rows = (matrix(sizes, cache, src=src, config=config)
            + matrix(hard_sizes, cache, src=src, hard=True, config=config))
    if config is not None:
        return table(rows)
    if src is not None:
        BEFORE.write_text(json.dumps({"label": label or str(src), "rows": rows}, indent=1,
                                     default=float))
        return table(rows)
    _save(rows)
    return section(rows)


def section(rows: list[dict]) -> str:
    """The markdown section of the matrix, with the saved "before" rows under it."""
    before = ""
    if BEFORE.exists():
        old = json.loads(BEFORE.read_text())
        before = (f"\n\nBefore (reblur at {old['label']}, same pairs; "
                  "`python -m benchmarks.realism --src OLD_CHECKOUT/src --label COMMIT`):\n\n"
                  + table(old["rows"]))
    return (
        "## Realism matrix (`python -m benchmarks.realism`)\n\n"
        "Pairs from the independent test bed (`reblur.testbed`: 64-sub-pose 6-D shake, bicubic "
        "interpolation, perspective viewpoint, Poisson-Gaussian sensor), LEVIR test_7 at 1 MP "
        "and upsampled; 10-40 % contrast changes. FAR: flagged share of unchanged known "
        f"pixels farther than {BOUNDARY} px from a change. Geometry: reblur's reference "
        "location of a 17 x 17 lattice against the true blur centroid. Probes: the "
        "refinement's probes measured and used, of all. Baseline: "
        "register (SIFT + RANSAC) + difference + Otsu. Rows in `docs/realism_runs.json`. "
        f"Rows marked hard: a {HARD_ROLL_DEG} degree roll at any size and a "
        f"{HARD_VIEW['shift_px']:g} px / {HARD_VIEW['angle_deg']:g} degree perspective "
        "viewpoint, like the external evaluation's pairs.\n\n"
        + table(rows) + before
    )


def _save(rows: list[dict]) -> None:
    runs = REPO / "docs" / "realism_runs.json"
    runs.write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1,25", help="comma-separated MP sizes among 1, 25, 100")
    ap.add_argument("--hard-sizes", default="4",
                    help="sizes of the hard-geometry rows (empty for none)")
    ap.add_argument("--cache", type=Path, default=None, help="folder of the generated pairs")
    ap.add_argument("--src", type=Path, default=None,
                    help="run reblur from another checkout's src folder: the 'before' rows")
    ap.add_argument("--label", default=None, help="name of that checkout (e.g. its commit)")
    ap.add_argument("--config", type=Path, default=None,
                    help="a reblur detect --config file (a variant of the defaults): the rows "
                         "are printed, not saved")
    ap.add_argument("--saved", action="store_true",
                    help="only rewrite the section from docs/realism_runs.json")
    a = ap.parse_args()
    from benchmarks.run import write_section

    if a.saved:
        body = section(json.loads((REPO / "docs" / "realism_runs.json").read_text()))
    else:
        body = main([int(s) for s in a.sizes.split(",") if s],
                    a.cache, a.src, a.label, [int(s) for s in a.hard_sizes.split(",") if s],
                    a.config)
    if a.src is None and a.config is None:
        write_section("realism", body)
    print(body)
