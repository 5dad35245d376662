"""Cost over content (issue #28): time per stage and peak RSS of ``reblur detect`` on pairs
of 1, 25 and 100 MP whose content ranges from unchanged to unrelated
(``python -m benchmarks.cost``).

Every pair is rendered by the independent test bed (:mod:`reblur.testbed`: a 64-sub-pose
6-D shake, bicubic interpolation, a 20 px viewpoint shift, 8-bit sensor with 0.5 DN of
read noise), tile by tile into tiled TIFFs, from gray scenes upsampled from the 1024 px
development images (``../shared/data``).  Contents, same camera path per size:

* ``unchanged``: LEVIR test_7 against itself;
* ``5%``: 16 blocks of unrelated content (WHU 000213) on a lattice, 5 % of the area;
* ``45%``: one central block of unrelated content, 45 % of the area (an occluder);
* ``years-whu`` / ``years-levir``: the datasets' own years-apart pairs (WHU 000213
  prev -> curr, LEVIR test_7 A -> B), shaken;
* ``unrelated``: LEVIR test_7 against WHU 000213 (to be refused quickly);
* ``5% rgb16``: the ``5%`` pair written as three 16-bit bands (the 8-bit values x 257,
  a darker copy, their negative): what bands and bit depth cost, the content the same.
* ``defocus``: the ``unchanged`` scene, blurred by a lens out of focus instead of a
  shake (:func:`reblur.testbed.defocus_path`: a pillbox of :data:`DEFOCUS_PX`, 256
  sub-poses filling the disk): a dense blur, whose weights fill an area of the pose grid
  where a shake's follow a path.

Each case runs ``python -m reblur detect REF OBS --out DIR -q`` in a fresh process, as a
user does (the package's bytecode written first, as an install leaves it); stage times
come from its ``report.json`` (``estimate`` includes the window selection; ``report`` is
the writing of the outputs), peak RSS from the same report (``ru_maxrss`` of that
process).  The I/O floor (read both inputs whole, write a uint8
mask: :func:`benchmarks.scale.io_floor`) is measured in the same run.

Targets (reported, not tested): any pair of at most 1 MP within 5 s end to end; 100 MP
within 5x the floor; fixed cost (the intercept of time against MP) at most 3 s and the
per-pixel stage's log-log slope 0.9-1.1: the decision's tile pass
(``decision.seconds.tiles`` of the report, plus ``preload``: the tiles a small image loads
once ahead, inside the fit; ``reblur_decide`` also holds the decision's fit on a sample of
windows, work that does not grow with the image).

``--real`` adds the real pairs of at most 1 MP of the shared data, in colour at their own
size (:data:`REAL_PAIRS`: LEVIR and WHU years apart, GoPro's real camera shake; and
:data:`GOPRO_AVERAGES`, longer hand-held shakes made of GoPro frames): the test bed's gray
pairs are not all a user's 1 MP pairs cost (``--sizes "" --real``: those alone).

``--shakes`` adds the test bed's shakes of growing extent (6 to 35 px, and a 1.5 degree
out-of-plane tilt; :data:`benchmarks.shake_extent.SHAKES`) at 1 MP: the scene the same,
what the blur's extent costs.  Their rows, the GoPro rows and ``defocus`` are the 1 MP
target's worst cases; the targets list each kind of pair apart.

``--src OLD/src --label COMMIT`` runs another checkout (the "before" figures, saved in
``docs/cost_before.json``); ``--sizes 1,25`` when time is short.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import tifffile

from benchmarks.common import REPO, compile_package

SIZES = {1: 1, 25: 5, 100: 10}  # MP -> upsampling factor of the 1024 px scenes
CONTENTS = ["unchanged", "5%", "45%", "years-whu", "years-levir", "unrelated", "5% rgb16",
            "defocus"]
#: Radius (px) of the ``defocus`` content's pillbox blur.
DEFOCUS_PX = 10.0
#: Suffix of a content written as three 16-bit bands (:func:`_rgb16`).
RGB16 = " rgb16"
RUNS = REPO / "docs" / "cost_runs.json"
BEFORE = REPO / "docs" / "cost_before.json"
#: Runs of the ``unchanged`` pairs, the median kept: they give the fixed cost (the intercept
#: of their times against MP, a 3 s target), and one run on this shared host moves by
#: 0.3 s (1 MP: 3.2 and 3.5 s an hour apart).
UNCHANGED_RUNS = 3
#: Default folder of the generated pairs (shared with :mod:`benchmarks.align_cost`).
CACHE = Path(tempfile.gettempdir()) / "reblur-cost"
STAGES = ["open", "align", "photometry", "estimate", "refine", "field", "reblur_decide",
          "report"]
#: Column of a run's time outside its stages (see :func:`_outside`).
OUTSIDE = "start-up, imports, exit"


class _Blocks:
    """``base`` with ``other``'s pixels inside ``boxes`` ((y0, y1, x0, x1)), read lazily."""

    def __init__(self, base, other, boxes):
        self.base, self.other, self.boxes = base, other, boxes
        self.shape, self.dtype = base.shape, np.float64

    def __getitem__(self, key):
        ys, xs = key[0], key[1]
        out = np.array(self.base[ys, xs], dtype=np.float64)
        y0, x0 = ys.start or 0, xs.start or 0
        for by0, by1, bx0, bx1 in self.boxes:
            a0, a1 = max(by0, y0), min(by1, y0 + out.shape[0])
            b0, b1 = max(bx0, x0), min(bx1, x0 + out.shape[1])
            if a0 < a1 and b0 < b1:
                out[a0 - y0 : a1 - y0, b0 - x0 : b1 - x0] = self.other[a0:a1, b0:b1]
        return out


def _lattice(shape, frac: float, k: int) -> list[tuple[int, int, int, int]]:
    """``k x k`` blocks on a lattice (``k = 1``: one central block), ``frac`` of the area."""
    H, W = shape[:2]
    side_y, side_x = int(H * np.sqrt(frac) / k), int(W * np.sqrt(frac) / k)
    out = []
    for i in range(k):
        for j in range(k):
            cy, cx = int((i + 0.5) * H / k), int((j + 0.5) * W / k)
            out.append((cy - side_y // 2, cy - side_y // 2 + side_y,
                        cx - side_x // 2, cx - side_x // 2 + side_x))
    return out


def _scenes(mp: int, content: str):
    """(reference scene, observed scene) of a case, gray in [0, 1], lazily upsampled."""
    from reblur.testbed import levir_image, upsampled, whu_image

    f = SIZES[mp]

    def up(img):
        return upsampled(img, f) if f > 1 else img

    levir_a = up(levir_image("test_7", gray=True))
    whu_curr = up(whu_image("000213", "curr", gray=True))
    if content in ("unchanged", "defocus"):
        return levir_a, levir_a
    if content == "5%":
        return levir_a, _Blocks(levir_a, whu_curr, _lattice(levir_a.shape, 0.05, 4))
    if content == "45%":
        return levir_a, _Blocks(levir_a, whu_curr, _lattice(levir_a.shape, 0.45, 1))
    if content == "years-whu":
        return up(whu_image("000213", "prev", gray=True)), whu_curr
    if content == "years-levir":
        return levir_a, up(levir_image("test_7", "B", gray=True))
    if content == "unrelated":
        return levir_a, whu_curr
    raise ValueError(f"unknown content {content!r}")


def _tiles(shape, tile: int = 512):
    for y in range(0, shape[0], tile):
        for x in range(0, shape[1], tile):
            yield (y, min(y + tile, shape[0]), x, min(x + tile, shape[1]))


def _rgb16(tile: np.ndarray) -> np.ndarray:
    """Three 16-bit bands of an 8-bit gray tile: the values x 257, a darker copy
    (0.9 x + 12.8, x 257) and their negative (65535 - 257 x)."""
    v = tile.astype(np.uint32) * 257
    dark = (v * 9 + 32896) // 10
    return np.stack([v, dark, 65535 - v], axis=-1).astype(np.uint16)


def _write(path: Path, shape, tile_fn, rgb16: bool = False) -> None:
    tmp = path.with_suffix(".part.tif")
    tiles = (tile_fn(b) for b in _tiles(shape))
    if rgb16:
        tiles, shape, dtype = (_rgb16(t) for t in tiles), (*shape, 3), np.uint16
    else:
        dtype = np.uint8
    tifffile.imwrite(tmp, tiles, shape=shape, dtype=dtype, tile=(512, 512), bigtiff=True,
                     compression="zlib")
    os.replace(tmp, path)


def make_case(mp: int, content: str, cache: Path) -> Path:
    """Write (or reuse) ``ref.tif`` and ``obs.tif`` of a case."""
    from reblur.testbed import ChangedScene, compose, defocus_path, plan_pair, shake_for

    d = cache / f"{mp}mp_{content.replace('%', 'pc').replace(' ', '_')}"
    if (d / "obs.tif").exists():
        return d
    d.mkdir(parents=True, exist_ok=True)
    rgb16 = content.endswith(RGB16)
    ref_scene, obs_scene = _scenes(mp, content.removesuffix(RGB16))
    plan = plan_pair(ref_scene, bits=8, noise_dn=0.5, n_changes=0, seed=0,
                     motion=shake_for(ref_scene.shape), viewpoint={"shift_px": 20.0})
    plan = dataclasses.replace(plan, changed=ChangedScene(obs_scene, ()))
    if content == "defocus":
        path = defocus_path(plan.shape, DEFOCUS_PX, focal=plan.path.focal)
        plan = dataclasses.replace(plan, path=path,
                                   homographies=compose(plan.view, path.homographies()))
    _write(d / "ref.tif", plan.shape, plan.reference_tile, rgb16)
    _write(d / "obs.tif", plan.shape, plan.observed_tile, rgb16)
    return d


def _children_cpu() -> float:
    """User + system CPU seconds of the finished child processes so far."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def file_create_ms(root: Path | None = None, n: int = 300) -> float:
    """Milliseconds to create, write (3 KB) and close one file in a new folder under
    ``root`` (default: the temporary folder), the median of ``n``.  The viewer writes one
    file per tile (2300 at 100 MP): where creating a file is slow, that shows in the
    writing's time.  (On the development VM it varied from 0.03 to 1 ms within minutes,
    in any folder of its disk.)"""
    with tempfile.TemporaryDirectory(dir=root) as tmp:
        times = []
        for i in range(n):
            t = time.perf_counter()
            with open(Path(tmp) / f"{i}.png", "wb") as f:
                f.write(b"\0" * 3000)
            times.append(time.perf_counter() - t)
    return 1000.0 * float(np.median(times))


#: Real pairs of at most 1 MP from the shared data (``--real``), as a user runs them: the
#: reference first, the later (or blurred) image second.  LEVIR and WHU: 1024 px RGB
#: aerial pairs years apart (WHU's are refused: too few of their features agree); GoPro:
#: the sharp middle frame against the mean of eight hand-held 240 fps frames, 1280 x 720
#: RGB, real camera shake.
REAL_PAIRS = {
    **{f"LEVIR {n}": (f"levir_whu_1024/samples_LEVIR/A/{n}.png",
                      f"levir_whu_1024/samples_LEVIR/B/{n}.png")
       for n in ("test_7", "test_12", "test_102")},
    **{f"WHU {n}": (f"levir_whu_1024/samples_WHU-CD/prev/{n}.png",
                    f"levir_whu_1024/samples_WHU-CD/curr/{n}.png")
       for n in ("000121", "000213", "000241")},
    **{f"GoPro {n[:8]}": (f"gopro/pairs/{n}_gt.png", f"gopro/pairs/{n}.png")
       for n in ("GOPR0374_11_00_st_frame-614_n_avg-8", "GOPR0384_11_00_st_frame-203_n_avg-8",
                 "GOPR0410_11_00_st_frame-326_n_avg-8")},
}


def real_pairs(prefix: str = ""):
    """``(name, reference path, observation path)`` of the :data:`REAL_PAIRS` whose name
    starts with ``prefix``; a pair whose files are missing is skipped with a line on
    stderr."""
    from benchmarks.common import DATA

    for name, (ref, obs) in REAL_PAIRS.items():
        if not name.startswith(prefix):
            continue
        ref_p, obs_p = Path(DATA) / ref, Path(DATA) / obs
        if not (ref_p.exists() and obs_p.exists()):
            print(f"skipped {name}: {ref_p} or {obs_p} missing", file=sys.stderr)
            continue
        yield name, ref_p, obs_p


#: GoPro GOPR0477 frame averages (``--real``): the sharp frame 13 against the mean of the
#: ``k`` consecutive 240 fps hand-held frames around it (:func:`reblur.testbed.gopro_pair`,
#: 1280 x 720 RGB), as ``(centre, k)``.  The longer the average, the further the shake
#: reaches: from about k = 11 on, the alignment verifies the blur at 16 px, and the
#: estimate's weights reach the +-12 px grid's edge without a wider grid fitting better.
GOPRO_AVERAGES = ((13, 8), (13, 12), (13, 16))


def _average_name(centre: int, k: int) -> str:
    """The name of a :data:`GOPRO_AVERAGES` pair."""
    return f"GoPro 0477 frame {centre}, {k} frames"


def gopro_averages(cache: Path):
    """``(name, reference path, observation path)`` of :data:`GOPRO_AVERAGES`, written as
    PNG under ``cache`` (or reused); skipped with a line on stderr when the shared data's
    frames are missing."""
    import cv2

    from reblur.testbed import gopro_pair

    for centre, k in GOPRO_AVERAGES:
        name = _average_name(centre, k)
        d = cache / f"gopro0477_{centre}_{k}"
        ref_p, obs_p = d / "ref.png", d / "obs.png"
        if not obs_p.exists():
            try:
                ref, obs = gopro_pair(centre, k)
            except (FileNotFoundError, OSError) as err:
                print(f"skipped {name}: {err}", file=sys.stderr)
                continue
            d.mkdir(parents=True, exist_ok=True)
            for path, img in ((ref_p, ref), (obs_p, obs)):
                tmp = path.with_suffix(".tmp.png")
                cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
                os.replace(tmp, path)
        yield name, ref_p, obs_p


def measure_real(src: Path | None = None, out_root: Path | None = None,
                 cache: Path | None = None) -> list[dict]:
    """:data:`REAL_PAIRS` and :data:`GOPRO_AVERAGES` (written under ``cache``, default the
    cases' folder) through ``reblur detect`` (rows of size 1 MP, content ``real: NAME``); a
    pair whose files are missing is skipped with a line on stderr."""
    compile_package(src)
    return _pair_rows([*real_pairs(), *gopro_averages(cache or CACHE)], "real: ", src,
                      out_root)


def _pair_rows(pairs, prefix: str, src: Path | None, out_root: Path | None) -> list[dict]:
    """Rows of size 1 MP, content ``prefix + NAME``, of ``(NAME, reference, observation)``
    pairs through :func:`run_pair` (each printed as it ends)."""
    rows = []
    for name, ref_p, obs_p in pairs:
        row = {"mp": 1, "content": prefix + name, "file_create_ms": file_create_ms(out_root),
               **run_pair(ref_p, obs_p, src, out_root)}
        print(json.dumps(row, default=float), flush=True)
        rows.append(row)
    return rows


#: Test-bed shakes of growing extent at 1 MP (``--shakes``; the pairs of
#: :data:`benchmarks.shake_extent.SHAKES`): what the blur's extent costs, the scene the
#: same.
SHAKE_PREFIX = "shake: "


def measure_shakes(src: Path | None = None, out_root: Path | None = None) -> list[dict]:
    """The test bed's shake pairs (:data:`benchmarks.shake_extent.SHAKES`, made once in
    that benchmark's cache) through ``reblur detect``: rows of size 1 MP, content
    ``shake: NAME``."""
    from benchmarks.shake_extent import SHAKES
    from benchmarks.shake_extent import make_case as shake_case

    compile_package(src)
    pairs = [(name, d / "ref.tif", d / "obs.tif") for name, d in
             ((name, shake_case(name)) for name in SHAKES)]
    return _pair_rows(pairs, SHAKE_PREFIX, src, out_root)


def run_case(case: Path, src: Path | None = None, out_root: Path | None = None) -> dict:
    """:func:`run_pair` on a generated case's ``ref.tif`` and ``obs.tif``."""
    return run_pair(case / "ref.tif", case / "obs.tif", src, out_root)


def run_pair(ref: Path, obs: Path, src: Path | None = None,
             out_root: Path | None = None) -> dict:
    """``reblur detect REF OBS`` in a fresh process, its outputs in a new folder under
    ``out_root`` (default: the temporary folder); stage times and peak RSS."""
    with tempfile.TemporaryDirectory(dir=out_root) as tmp:
        out = Path(tmp) / "out"
        cmd = [sys.executable, "-m", "reblur", "detect", str(ref), str(obs), "--out",
               str(out), "-q"]
        env = dict(os.environ)
        if src is not None:
            env["PYTHONPATH"] = str(src)
        t = time.perf_counter()
        cpu = _children_cpu()
        r = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
        seconds = time.perf_counter() - t
        # CPU time of the run (user + system, all its threads): on a shared host the wall
        # time holds the other jobs' share of the cores too
        res: dict = {"seconds": seconds, "cpu_s": _children_cpu() - cpu,
                     "load": os.getloadavg()[0]}
        if r.returncode:
            res["refused"] = (r.stderr.strip().splitlines() or ["?"])[-1][:300]
            return res
        rep = json.loads((out / "report.json").read_text())
    res["stages"] = {k: float(v) for k, v in rep.get("timings_s", {}).items()}
    res["peak_rss_mb"] = rep.get("memory", {}).get("peak_rss_mb")
    mi = rep.get("motion", {}).get("info", {})
    sel = mi.get("selection")
    if sel:
        res["selection"] = {k: sel[k] for k in ("estimates", "n_outer", "fits") if k in sel}
    res["n_outer"] = mi.get("n_outer")
    res["n_active"] = mi.get("n_active")  # poses with weight in the last solve
    ch = rep.get("changes", {})
    res["flagged"] = ch.get("changed_fraction")
    res["n_regions"] = ch.get("n_regions")
    res["notes"] = len(rep.get("notes", []))
    dec = rep.get("decision", {})
    # the decision's sampled fit (fixed work) and its tile pass (the per-pixel stage)
    res["decide_seconds"] = dec.get("seconds")
    # the tile pass's work: decisions, padded pixels decided, tiles left incomplete
    res["tile_work"] = {**dec.get("backend", {}).get("work", {}),
                        "tiles": dec.get("n_tiles"), "incomplete": dec.get("incomplete_tiles")}
    details = rep.get("alignment", {}).get("details") or {}
    res["align_method"] = details.get("method")
    # the shake extents the alignment tried (absent before the report recorded them)
    extents = details.get("extents")
    res["align_extents"] = None if extents is None else [e["shake_px"] for e in extents]
    res["align_content_misfit"] = details.get("content_misfit")
    return res


def measure(sizes: list[int], contents: list[str], cache: Path,
            src: Path | None = None, out_root: Path | None = None) -> list[dict]:
    from benchmarks.scale import io_floor

    compile_package(src)
    rows = []
    for mp in sizes:
        for content in contents:
            t = time.perf_counter()
            case = make_case(mp, content, cache)
            made = time.perf_counter() - t
            runs = [run_case(case, src, out_root)
                    for _ in range(UNCHANGED_RUNS if content == "unchanged" else 1)]
            # the run of the median time (an odd count), the others' times kept beside it
            runs.sort(key=lambda r: r["seconds"])
            row = {"mp": mp, "content": content, "make_s": made,
                   "file_create_ms": file_create_ms(out_root), **runs[len(runs) // 2]}
            if len(runs) > 1:
                row["seconds_runs"] = [r["seconds"] for r in runs]
            if content == contents[0]:
                row["io_floor_s"] = io_floor(case)["time_s"]
            print(json.dumps(row, default=float), flush=True)
            rows.append(row)
    return rows


def _slope(xs, ys) -> float:
    return float(np.polyfit(np.log(xs), np.log(ys), 1)[0]) if len(xs) >= 2 else float("nan")


def _tiles_seconds(row: dict) -> float | None:
    """The decision's tile pass (``decision.seconds.tiles`` of the row's report), if known,
    with the tiles' loading a small image does ahead of it, inside the fit
    (``decision.seconds.preload``: its padded tiles read and reblurred once for both
    passes; without it, a 1 MP tile pass reads nothing and the slope over sizes rises
    from ~1.0 to ~1.3)."""
    sec = row.get("decide_seconds") or {}
    tiles = sec.get("tiles")
    return float(tiles) + float(sec.get("preload") or 0.0) if tiles else None


def _outside(row: dict) -> float | None:
    """Seconds of a run outside :data:`STAGES`: Python's start-up, the imports, reading
    the options, and the process's exit (its memory handed back); None when the row has no
    ``total`` (the pipeline's stages from the alignment to the decision)."""
    st = row["stages"]
    if "total" not in st:
        return None
    return float(row["seconds"]) - st["total"] - st.get("open", 0.0) - st.get("report", 0.0)


def _cell(row: dict, stage: str) -> str:
    """A stage's seconds; ``reblur_decide`` with its tile pass in brackets when known."""
    st = row["stages"]
    if stage not in st:
        return "-"
    tiles = _tiles_seconds(row)
    if stage == "reblur_decide" and tiles:
        return f"{st[stage]:.2f} ({float(tiles):.2f})"
    return f"{st[stage]:.2f}"


def table(rows: list[dict]) -> str:
    lines = ["| size | content | total (s) | " + " | ".join(STAGES) + f" | {OUTSIDE} | "
             "peak RSS (MB) | estimates / outer iterations | notes |",
             "|---" * (len(STAGES) + 7) + "|"]
    for r in rows:
        if "refused" in r:
            cells = [f"{r['seconds']:.1f} (refused: {r['refused'][:90]})"] + [""] * len(STAGES) \
                + ["", "", "", ""]
        else:
            sel = r.get("selection") or {}
            est = (f"{sel['estimates']} / {sel['n_outer']}" + ("" if sel.get("fits", True)
                                                              else " (no fit)")) if sel else (
                f"? / {r['n_outer']} (last estimate)" if r.get("n_outer") else "-")
            if r.get("n_active"):
                est += f", {r['n_active']} poses"
            out = _outside(r)
            cells = ([f"{r['seconds']:.1f}"] + [_cell(r, k) for k in STAGES]
                     + ["-" if out is None else f"{out:.2f}"]
                     + [f"{r['peak_rss_mb']:.0f}" if r.get("peak_rss_mb") else "-", est,
                        str(r.get("notes", ""))])
        lines.append(f"| {r['mp']} MP | {r['content']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _tile_pass(row: dict) -> float:
    """Seconds of the per-pixel stage of a row: the decision's tile pass
    (``decision.seconds.tiles`` of its report), else the whole reblur-and-decide stage,
    which also holds the decision's fit on a sample of windows (fixed work)."""
    tiles = _tiles_seconds(row)
    return tiles if tiles else float(row["stages"].get("reblur_decide", np.nan))


def _decided(ok: list[tuple[int, dict]]) -> tuple[np.ndarray, np.ndarray] | None:
    """Pixels the tile pass decided per row of ``ok`` (``(mp, row)`` pairs) and their
    ratio to the image's pixels (the halos' and re-runs' overhead), if every row has them."""
    px = [(r.get("tile_work") or {}).get("pixels") for _, r in ok]
    if not all(px):
        return None
    px = np.array(px, float)
    image = np.array([(1024 * SIZES[m]) ** 2 if m in SIZES else np.nan for m, _ in ok])
    return px, px / image


def _kinds(rows: list[dict]) -> list[tuple[str, list[dict]]]:
    """``rows`` by kind of pair: the issue's contents (test-bed scene changes under one
    shake, the real aerial pairs years apart), real camera shake (GoPro), and the test
    bed's larger blurs (its shakes of growing extent, the defocus); empty kinds left out."""
    def kind(r: dict) -> str:
        c = r["content"]
        if c.startswith("real: GoPro"):
            return "real camera shake (GoPro, colour)"
        if c.startswith(SHAKE_PREFIX) or c == "defocus":
            return "the test bed's larger blurs (shakes of 6-35 px, a 1.5 degree tilt, defocus)"
        return "the issue's contents (one 6 px shake; aerial pairs years apart)"
    out: dict[str, list[dict]] = {}
    for r in rows:
        out.setdefault(kind(r), []).append(r)
    return list(out.items())


def targets(rows: list[dict]) -> str:
    """The issue's targets, met or not, on ``rows`` (and the host's load while they ran)."""
    loads = [r["load"] for r in rows if "load" in r]
    out = [f"- host load average while the rows ran: {min(loads):.1f}-{max(loads):.1f} on "
           f"{os.cpu_count()} cores"] if loads else []
    made = [r["file_create_ms"] for r in rows if "file_create_ms" in r]
    if made:
        out.append(f"- creating a file in the output folder took {min(made):.2f}-"
                   f"{max(made):.2f} ms (`--out-root`; the viewer writes one per tile)")
    small = [r for r in rows if r["mp"] <= 1]
    if small:
        worst = max(small, key=lambda r: r["seconds"])
        out.append(f"- any pair <= 1 MP <= 5 s: worst {worst['seconds']:.1f} s "
                   f"({worst['content']}): {'met' if worst['seconds'] <= 5 else 'NOT met'}")
        for kind, some in _kinds(small):
            w = max(some, key=lambda r: r["seconds"])
            out.append(f"  - {kind}: {len(some)} pairs, {min(r['seconds'] for r in some):.1f}"
                       f"-{w['seconds']:.1f} s (worst: {w['content']})")
    floors = {r["mp"]: r["io_floor_s"] for r in rows if "io_floor_s" in r}
    if 100 in floors:
        big = [r for r in rows if r["mp"] == 100]
        worst = max(big, key=lambda r: r["seconds"])
        x = worst["seconds"] / floors[100]
        out.append(f"- 100 MP <= 5x the I/O floor ({floors[100]:.1f} s): worst "
                   f"{worst['seconds']:.1f} s = {x:.1f}x ({worst['content']}): "
                   f"{'met' if x <= 5 else 'NOT met'}")
    ok = sorted((r["mp"], r) for r in rows if r["content"] == "unchanged" and "stages" in r)
    if len(ok) >= 2:
        mp = np.array([m for m, _ in ok], float)
        tot = np.array([r["seconds"] for _, r in ok])
        per = np.array([_tile_pass(r) for _, r in ok])
        b, a = np.polyfit(mp, tot, 1)
        fixed = float(np.mean([r["seconds"] - _tile_pass(r) - r["stages"].get("report", 0.0)
                               for _, r in ok]))
        s = _slope(mp, per)
        spread = [r["seconds_runs"] for _, r in ok if r.get("seconds_runs")]
        runs = (f"; each the median of {len(spread[0])} runs: "
                + ", ".join(f"{min(x):.1f}-{max(x):.1f} s" for x in spread)
                if len(spread) == len(ok) else "")
        out.append(f"- fixed cost <= 3 s (unchanged content{runs}): intercept of total time "
                   f"against MP {a:.1f} s ({1000 * b:.0f} ms per MP); mean time outside the "
                   f"tiles and the writing {fixed:.1f} s: "
                   f"{'met' if max(a, fixed) <= 3 else 'NOT met'}")
        what = "the tile pass" if all(_tiles_seconds(r) for _, r in ok) else "reblur + decide"
        out.append(f"- per-pixel stage ({what}) log-log slope 0.9-1.1: {s:.2f} "
                   f"over {', '.join(f'{m:g}' for m in mp)} MP: "
                   f"{'met' if 0.9 <= s <= 1.1 else 'NOT met'}")
        decided = _decided(ok)
        if decided is not None:
            px, halo = decided
            out.append(f"  - against the pixels the tile pass decides (halos and re-runs "
                       f"included; `decision.backend.work.pixels`): slope "
                       f"{_slope(px, per):.2f}; decided / image pixels "
                       f"{' / '.join(f'{h:.2f}' for h in halo)}: a single tile has no halo, "
                       f"so the slope against MP holds that step")
    return "\n".join(out)


def section(rows: list[dict]) -> str:
    before = ""
    if BEFORE.exists():
        old = json.loads(BEFORE.read_text())
        before = (f"\n\nBefore (reblur at {old['label']}, same pairs; "
                  "`python -m benchmarks.cost --src OLD_CHECKOUT/src --label COMMIT`):\n\n"
                  + table(old["rows"]) + "\n\n" + targets(old["rows"]))
    return ("## Cost over content (`python -m benchmarks.cost`)\n\n"
            "`reblur detect` in a fresh process per case, as a user runs it, on test-bed pairs "
            "(LEVIR test_7 / WHU 000213 scenes, gray, upsampled; 64-sub-pose shake, 20 px "
            "viewpoint, 8-bit; `5% rgb16`: the `5%` pair written as three 16-bit bands); "
            "rows `real: ...` are the shared data's real pairs of at most "
            "1 MP, colour, at their own size (`--real`); rows `shake: ...` the test bed's "
            "shakes of growing extent (`--shakes`). Stage times (s) from `report.json` "
            "(`estimate` includes the "
            "window selection, `field` the local displacement field's tie points, "
            "`reblur_decide` its tile pass in brackets, `report` writes "
            f"the outputs and the viewer; `{OUTSIDE}`: the rest of the process's time); "
            "peak RSS of the process; the estimate's outer iterations and the poses "
            "with weight in its last solve. The host "
            "is shared with other jobs: timings are noisy. Rows in `docs/cost_runs.json`.\n\n"
            + table(rows) + "\n\nTargets:\n\n" + targets(rows) + before)


def main(sizes: list[int] | None = None, contents: list[str] | None = None,
         cache: Path | None = None, src: Path | None = None, label: str | None = None,
         out_root: Path | None = None, real: bool = False, shakes: bool = False) -> str:
    """Run the cases (with ``real`` also the real pairs, with ``shakes`` the test bed's
    shakes of growing extent); return the markdown section (with ``src``: save the
    "before" rows)."""
    sizes = [1, 25] if sizes is None else sizes
    contents = CONTENTS if contents is None else contents
    cache = cache or CACHE
    if out_root is not None:
        Path(out_root).mkdir(parents=True, exist_ok=True)
    rows = measure(sizes, contents, cache, src, out_root) if sizes and contents else []
    if real:
        rows += measure_real(src, out_root, cache)
    if shakes:
        rows += measure_shakes(src, out_root)
    if src is not None:
        old = json.loads(BEFORE.read_text())["rows"] if BEFORE.exists() else []
        rows = _merged(old, rows)
        BEFORE.write_text(json.dumps({"label": label or str(src), "rows": rows}, indent=1,
                                     default=float))
        return table(rows) + "\n\n" + targets(rows)
    rows = _merged(json.loads(RUNS.read_text()) if RUNS.exists() else [], rows)
    RUNS.write_text(json.dumps(rows, indent=1, default=float))
    return section(rows)


def _merged(old: list[dict], new: list[dict]) -> list[dict]:
    """``old`` rows with those of the same size and content replaced by ``new``'s, sorted
    by size then content (a run at some sizes keeps the saved rows of the others)."""
    keys = {(r["mp"], r["content"]) for r in new}
    rows = [r for r in old if (r["mp"], r["content"]) not in keys] + new
    from benchmarks.shake_extent import SHAKES

    real = [*REAL_PAIRS, *(_average_name(c, k) for c, k in GOPRO_AVERAGES)]
    order = {c: i for i, c in enumerate(CONTENTS + [f"real: {n}" for n in real]
                                        + [SHAKE_PREFIX + n for n in SHAKES])}
    return sorted(rows, key=lambda r: (r["mp"], order.get(r["content"], 99)))


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1,25", help="comma-separated MP sizes among 1, 25, 100")
    ap.add_argument("--quick", action="store_true", help="1 MP only")
    ap.add_argument("--contents", default=",".join(CONTENTS))
    ap.add_argument("--cache", type=Path, default=None, help="folder of the generated pairs")
    ap.add_argument("--src", type=Path, default=None,
                    help="run reblur from another checkout's src folder: the 'before' rows")
    ap.add_argument("--label", default=None, help="name of that checkout (e.g. its commit)")
    ap.add_argument("--out-root", type=Path, default=None,
                    help="folder under which each run writes its outputs (default: the "
                    "temporary folder)")
    ap.add_argument("--real", action="store_true",
                    help="also the real pairs of at most 1 MP of the shared data (REAL_PAIRS)")
    ap.add_argument("--shakes", action="store_true",
                    help="also the test bed's shakes of growing extent at 1 MP "
                    "(benchmarks.shake_extent.SHAKES)")
    ap.add_argument("--saved", action="store_true",
                    help="only rewrite the section from docs/cost_runs.json")
    a = ap.parse_args()
    from benchmarks.run import write_section

    if a.saved:
        body = section(json.loads(RUNS.read_text()))
    else:
        sizes = [1] if a.quick else [int(s) for s in a.sizes.split(",") if s]
        body = main(sizes, [c for c in a.contents.split(",") if c], a.cache, a.src, a.label,
                    a.out_root, a.real, a.shakes)
    if a.src is None:
        write_section("cost", body)
    print(body)
