"""Peak memory of reading large PNG and JPEG inputs (issue 30: the decompression-bomb guard).

``python -m benchmarks.big_inputs [--cases zeros png jpeg] [--zeros-side 30000]
[--side 20000] [--src OTHER/src]``

The inputs are generated at run time into a temporary directory (removed at the end, never
committed), row by row, without ever holding an image whole:

* ``zeros`` -- a pair of all-zero 8-bit gray PNGs, ``--zeros-side`` pixels square, through
  ``reblur detect`` (which stops with "textureless");
* ``png`` -- one textured 8-bit RGB PNG, ``--side`` square: :func:`reblur.io.open_image`, then
  every 1024 x 1024 window read once (a checksum), as the tiled pass reads them;
* ``jpeg`` -- the same picture as a baseline JPEG (quality 90, GDAL's encoder);
* ``progressive`` -- a 14000^2 RGB progressive JPEG (its coefficients take 588 MB, over
  the 500 MB GDAL lets libjpeg use by default);
* ``formats`` -- what the formats decoded whole cost: a 2000^2 RGB picture (gray for GIF)
  as WebP, JPEG XL, JPEG 2000, AVIF, BMP and GIF, each decoded by imagecodecs in a fresh
  process: the peak RSS above the process's size before, over the decoded bytes
  :func:`reblur.io._other_layout` counts from the header (``reblur.io._DECODE_PEAK``).

Each case runs in a fresh process (``--src`` puts another checkout's ``src`` first on its
path: the "before" rows).  A thread samples ``/proc/self/status`` every 20 ms: ``VmHWM``
(the kernel's peak resident set), and the peaks of ``RssAnon`` (memory the process owns)
and ``RssFile`` (file pages mapped into it, which the kernel may write back and drop).
Prints one markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import struct
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from pathlib import Path

import numpy as np

from benchmarks.common import REPO, commit

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------------------- inputs
def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def write_png_rows(path: Path, height: int, width: int, bands: int, rows) -> Path:
    """A non-interlaced 8-bit PNG written strip by strip: ``rows(y0, n)`` gives the
    ``(n, width[, bands])`` uint8 rows from ``y0`` (filter type 0, zlib level 1)."""
    colour = {1: 0, 2: 4, 3: 2, 4: 6}[bands]
    comp = zlib.compressobj(1)
    with open(path, "wb") as f:
        f.write(_PNG_MAGIC + _chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, colour,
                                                         0, 0, 0)))
        for y0 in range(0, height, 256):
            n = min(256, height - y0)
            raw = np.zeros((n, 1 + width * bands), np.uint8)
            raw[:, 1:] = np.asarray(rows(y0, n), np.uint8).reshape(n, -1)
            data = comp.compress(raw.tobytes())
            if data:
                f.write(_chunk(b"IDAT", data))
        f.write(_chunk(b"IDAT", comp.flush()) + _chunk(b"IEND", b""))
    return path


def textured_rows(side: int, bands: int = 3, seed: int = 0):
    """``rows(y0, n)`` of a textured picture: a 1024-px tile of smoothed noise, shifted by a
    different amount on every tile row (no two neighbouring tiles alike)."""
    import cv2

    rng = np.random.default_rng(seed)
    tile = cv2.GaussianBlur(rng.random((1024, 1024, bands)).astype(np.float32), (0, 0), 3)
    tile = cv2.normalize(tile, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    if bands == 1:
        tile = tile.reshape(1024, 1024)

    def rows(y0: int, n: int) -> np.ndarray:
        y = np.arange(y0, y0 + n)
        x = np.arange(side)
        out = tile[(y % 1024)[:, None], ((x[None, :] + 389 * (y // 1024)[:, None]) % 1024)]
        return out

    return rows


def make_inputs(d: Path, cases: list[str], zeros_side: int, side: int) -> dict[str, Path]:
    paths: dict[str, Path] = {}
    if "zeros" in cases:
        for name in ("zeros_a.png", "zeros_b.png"):
            paths[name] = write_png_rows(
                d / name, zeros_side, zeros_side, 1,
                lambda y0, n: np.zeros((n, zeros_side), np.uint8))
    if "png" in cases or "jpeg" in cases:
        paths["tex.png"] = write_png_rows(d / "tex.png", side, side, 3, textured_rows(side))
    if "formats" in cases:
        make_formats(d)
    if "progressive" in cases:
        import rasterio
        import rasterio.shutil

        write_png_rows(d / "prog.png", 14000, 14000, 3, textured_rows(14000, seed=1))
        with rasterio.Env(GDAL_CACHEMAX=64, CPL_LOG="/dev/null"):
            rasterio.shutil.copy(d / "prog.png", d / "prog.jpg", driver="JPEG", QUALITY=90,
                                 PROGRESSIVE="ON")
        (d / "prog.png").unlink()
    if "jpeg" in cases:
        import rasterio
        import rasterio.shutil

        with rasterio.Env(GDAL_CACHEMAX=64, CPL_LOG="/dev/null"):
            rasterio.shutil.copy(paths["tex.png"], d / "tex.jpg", driver="JPEG", QUALITY=90)
        paths["tex.jpg"] = d / "tex.jpg"
    return paths


FORMATS = ("webp", "jxl", "jp2", "avif", "bmp", "gif")


def make_formats(d: Path, side: int = 2000) -> None:
    import imagecodecs

    a = textured_rows(side)(0, side)
    enc = {"webp": lambda: imagecodecs.webp_encode(a, level=80),
           "jxl": lambda: imagecodecs.jpegxl_encode(a, level=80),
           "jp2": lambda: imagecodecs.jpeg2k_encode(a, level=40),
           "avif": lambda: imagecodecs.avif_encode(a, level=60, speed=10),
           "bmp": lambda: imagecodecs.bmp_encode(a),
           "gif": lambda: imagecodecs.gif_encode(a[..., 0])}
    for ext in FORMATS:
        (d / f"fmt.{ext}").write_bytes(enc[ext]())


def decode_peak(path: Path) -> dict:
    """Peak RSS of imagecodecs decoding ``path``, over what reblur counts from its header."""
    import mmap

    import imagecodecs

    from reblur.io import _other_layout

    data = path.read_bytes()
    with open(path, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as m:
        lay = _other_layout(path, m)
    before = _rss_mb()
    with _Sampler() as s:
        a = imagecodecs.imread(data)
    peak = max(_hwm_mb(), s.peak["RssAnon"] + s.peak["RssFile"])
    return dict(case=path.suffix[1:], decoded_mb=a.nbytes / 2**20,
                counted_mb=lay.nbytes / 2**20, peak_mb=peak - before,
                ratio=(peak - before) / (lay.nbytes / 2**20))


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


# ---------------------------------------------------------------------------- one case
class _Sampler:
    """Peaks of RssAnon and RssFile (MB) of this process, sampled every 20 ms."""

    def __init__(self) -> None:
        self.peak = {"RssAnon": 0.0, "RssFile": 0.0}
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def sample(self) -> None:
        with open("/proc/self/status") as f:
            for line in f:
                key = line.split(":")[0]
                if key in self.peak:
                    self.peak[key] = max(self.peak[key], int(line.split()[1]) / 1024.0)

    def _run(self) -> None:
        while not self._stop.wait(0.02):
            self.sample()

    def __enter__(self) -> _Sampler:
        self._t.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._t.join()
        self.sample()


def _hwm_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _detect(a: Path, b: Path, out: Path) -> tuple[int, str]:
    """``reblur detect a b --out out -q`` in this process: exit code and last stderr line."""
    import contextlib
    import io

    from reblur.cli import main

    err = io.StringIO()
    code = 0
    with contextlib.redirect_stderr(err):
        try:
            main(["detect", str(a), str(b), "--out", str(out), "-q"])
        except SystemExit as exc:
            code = int(exc.code or 0)
    lines = [ln for ln in err.getvalue().splitlines() if ln.strip()]
    return code, (lines[-1] if lines else "")


def _read_windows(path: Path) -> tuple[int, str, dict]:
    """Open ``path`` and read every 1024 x 1024 window once."""
    from reblur.io import InputError, open_image

    try:
        img = open_image(path)
    except InputError as exc:
        return 1, str(exc).replace(str(path.parent) + "/", ""), {}
    h, w = img.shape[:2]
    total = 0
    for y in range(0, h, 1024):
        for x in range(0, w, 1024):
            total += int(np.asarray(img.array[y : y + 1024, x : x + 1024], np.int64)[::97, ::97]
                         .sum())
    info = dict(lazy=img.lazy, shape=list(img.shape), checksum=total)
    img.close()
    return 0, "", info


def run_one(case: str, d: Path) -> dict:
    import reblur

    if case.startswith("fmt."):
        return decode_peak(d / case)
    t = time.perf_counter()
    with _Sampler() as s:
        if case == "zeros":
            code, line = _detect(d / "zeros_a.png", d / "zeros_b.png", d / "out")
            info: dict = {}
        else:
            name = {"png": "tex.png", "jpeg": "tex.jpg", "progressive": "prog.jpg"}[case]
            code, line, info = _read_windows(d / name)
    return dict(case=case, exit=code, message=line, time_s=time.perf_counter() - t,
                vmhwm_mb=_hwm_mb(), anon_mb=s.peak["RssAnon"], file_mb=s.peak["RssFile"],
                reblur=str(Path(reblur.__file__).parent), **info)


# ---------------------------------------------------------------------------- driver
def run_case(case: str, d: Path, src: Path | None) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(src or REPO / "src"), str(REPO)] + [p for p in [env.get("PYTHONPATH")] if p])
    out = subprocess.run([sys.executable, "-m", "benchmarks.big_inputs", "--one", case,
                          "--dir", str(d)], capture_output=True, text=True, cwd=REPO, env=env,
                         timeout=3600, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"case {case} failed:\n{out.stderr[-3000:]}")
    shutil.rmtree(d / "out", ignore_errors=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def formats_table(rows: list[dict]) -> str:
    lines = ["", "Formats decoded whole (2000^2 RGB; GIF gray), MB:", "",
             "| format | decoded | counted from the header | peak RSS above start | "
             "peak / counted |", "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['case']} | {r['decoded_mb']:.1f} | {r['counted_mb']:.1f} | "
                     f"{r['peak_mb']:.1f} | {r['ratio']:.2f} |")
    return "\n".join(lines)


def table(rows: list[dict], label: str, sizes: dict[str, str]) -> str:
    lines = [f"Inputs read by reblur at {label}; peaks in MB.", "",
             "| case | input | exit | VmHWM | RssAnon peak | RssFile peak | time (s) | result |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        result = r["message"] or ("lazy" if r.get("lazy") else "in memory")
        lines.append(f"| {r['case']} | {sizes[r['case']]} | {r['exit']} | {r['vmhwm_mb']:.0f} "
                     f"| {r['anon_mb']:.0f} | {r['file_mb']:.0f} | {r['time_s']:.1f} "
                     f"| {result} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["zeros", "png", "jpeg"],
                    choices=["zeros", "png", "jpeg", "progressive", "formats"])
    ap.add_argument("--zeros-side", type=int, default=30000)
    ap.add_argument("--side", type=int, default=20000)
    ap.add_argument("--src", type=Path, default=None,
                    help="another checkout's src directory to measure (e.g. an older commit)")
    ap.add_argument("--label", default=None, help="name of --src in the table")
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--dir", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        print(json.dumps(run_one(args.one, args.dir)))
        return ""
    sizes = {"zeros": f"2 x {args.zeros_side}^2 gray PNG", "png": f"{args.side}^2 RGB PNG",
             "jpeg": f"{args.side}^2 RGB JPEG", "progressive": "14000^2 RGB progressive JPEG"}
    with tempfile.TemporaryDirectory(prefix="reblur-big-inputs-") as tmp:
        d = Path(tmp)
        make_inputs(d, args.cases, args.zeros_side, args.side)
        rows = [run_case(c, d, args.src) for c in args.cases if c != "formats"]
        fmts = ([run_case(f"fmt.{ext}", d, args.src) for ext in FORMATS]
                if "formats" in args.cases else [])
    label = args.label or (str(args.src) if args.src else commit())
    text = (table(rows, label, sizes) if rows else "") + (formats_table(fmts) if fmts else "")
    print(text)
    return text


if __name__ == "__main__":
    main()
