"""Hostile inputs and interrupted or concurrent runs (issue 30).

Corrupt containers are refused rather than read as zeros; the output set of a run appears
all at once or not at all; two runs into one output directory cannot mix their files.
"""

from __future__ import annotations

import csv
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from urllib.parse import quote

import cv2
import numpy as np
import pytest
import tifffile
import zarr

# ---------------------------------------------------------------------------- helpers
# the CLI tests' runner and one-line-error check (tests/ is on sys.path under pytest)
from test_cli import assert_one_line_error, run  # noqa: E402

from reblur.io import InputError, open_image, write_png


def textured(rng, h=64, w=64, bands=3) -> np.ndarray:
    """Smoothed noise: enough texture for an alignment, uint8."""
    a = rng.random((h, w, bands) if bands > 1 else (h, w)) * 255
    return cv2.GaussianBlur(a, (0, 0), 1.5).astype(np.uint8)


@pytest.fixture
def good_pair(tmp_path):
    rng = np.random.default_rng(3)
    write_png(tmp_path / "ref.png", textured(rng))
    write_png(tmp_path / "obs.png", textured(rng))
    return tmp_path / "ref.png", tmp_path / "obs.png"


def assert_refused(bad: Path, obs: Path, out: Path, *patterns: str) -> None:
    """The CLI refuses ``bad`` as the reference in one line, leaving no output directory."""
    before = sorted(p.name for p in out.parent.iterdir())
    line = assert_one_line_error(run("detect", bad, obs, "--out", out, "-q"), *patterns)
    assert bad.name in line
    assert not out.exists()
    assert sorted(p.name for p in out.parent.iterdir()) == before  # no lock or temporary left


# ---------------------------------------------------------------------------- corrupt inputs
@pytest.mark.parametrize("zarr_format", [2, 3])
def test_zarr_with_a_missing_chunk_is_refused(tmp_path, good_pair, zarr_format):
    rng = np.random.default_rng(11)
    a = textured(rng, 96, 64, bands=1)
    store = tmp_path / "ref.zarr"
    z = zarr.create_array(str(store), shape=a.shape, chunks=(32, 32), dtype="u1",
                          zarr_format=zarr_format, fill_value=0)
    z[...] = a
    np.testing.assert_array_equal(open_image(store).read(), a)  # intact: read as written
    chunk = store / ("1.1" if zarr_format == 2 else "c/1/1")
    assert chunk.is_file()
    chunk.unlink()
    # what the bare reader gives: the deleted chunk is zeros, as if it were image content
    assert (np.asarray(zarr.open(str(store), mode="r")[32:64, 32:64]) == 0).all()
    with pytest.raises(InputError, match=r"lacks 1 of its 6 chunks"):
        open_image(store)
    assert_refused(store, good_pair[1], tmp_path / "res", r"zarr store lacks 1 of its 6 chunks")


def _zero_tiff_segment(path: Path, index: int) -> None:
    """Set the offset and byte count of tile/strip ``index`` to 0 (in place)."""
    with tifffile.TiffFile(path, mode="r+b") as tif:
        page = tif.pages[0]
        tags = page.tags
        names = (("TileOffsets", "TileByteCounts") if "TileOffsets" in tags
                 else ("StripOffsets", "StripByteCounts"))
        for name in names:
            values = list(tags[name].value)
            values[index] = 0
            tags[name].overwrite(values)


@pytest.mark.parametrize("layout", [dict(tile=(32, 32)), dict(rowsperstrip=16)])
def test_tiff_tile_without_data_is_refused(tmp_path, good_pair, layout):
    rng = np.random.default_rng(12)
    a = textured(rng, 96, 64, bands=1) | 1  # no zero pixel anywhere
    p = tmp_path / "ref.tif"
    tifffile.imwrite(p, a, compression="deflate", **layout)
    np.testing.assert_array_equal(open_image(p).read(), a)
    _zero_tiff_segment(p, 2)
    # what tifffile makes of it: a block of zeros where the segment was
    assert (tifffile.imread(p) == 0).sum() >= 16 * 32
    with pytest.raises(InputError, match=r"lacks data for 1 of its \d+ tiles or strips"):
        open_image(p)
    with pytest.raises(InputError, match=r"lacks data"):
        open_image(p, lazy=True)
    assert_refused(p, good_pair[1], tmp_path / "res", r"TIFF image lacks data")


@pytest.mark.parametrize("progressive", [0, 1])
def test_truncated_jpeg_with_end_marker_is_refused(tmp_path, good_pair, progressive):
    rng = np.random.default_rng(13)
    a = textured(rng, 128, 128)
    data = cv2.imencode(".jpg", a, [cv2.IMWRITE_JPEG_PROGRESSIVE, progressive])[1].tobytes()
    full = tmp_path / "full.jpg"
    full.write_bytes(data)
    expect = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    assert np.abs(open_image(full).read().astype(int) - expect).max() <= 1
    p = tmp_path / "ref.jpg"
    p.write_bytes(data[: len(data) // 2] + b"\xff\xd9")
    # the decoders used elsewhere accept it: the lost half comes back as a flat area
    assert cv2.imdecode(np.frombuffer(p.read_bytes(), np.uint8), cv2.IMREAD_COLOR) is not None
    with pytest.raises(InputError, match=r"JPEG data is truncated or corrupt \(.*premature end"):
        open_image(p)
    assert_refused(p, good_pair[1], tmp_path / "res", r"JPEG data is truncated or corrupt")


# ---------------------------------------------------------------------------- output sets
#: ``python -c`` driver: runs the CLI with one report writer patched (argv[1] says how).
DRIVER = """
import errno, os, signal, sys, time
import reblur.report as R

# a shell starts background jobs with SIGINT ignored, and Python then keeps it ignored: the
# Ctrl-C tests ask for the disposition a terminal gives (CI may run in the background)
signal.signal(signal.SIGINT, signal.default_int_handler)

mode, marker = sys.argv[1], sys.argv[2]
if mode == "enospc":
    def fail(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    R.write_json = fail
elif mode == "slow":
    def slow(f):
        def wrapped(*args, **kwargs):
            open(marker, "a").close()
            time.sleep(0.4)
            return f(*args, **kwargs)
        return wrapped
    R.write_png, R.write_cog, R.write_json = map(slow, (R.write_png, R.write_cog, R.write_json))
elif mode == "codec-warns":  # imagecodecs logs a warning before its decoder fails
    import logging
    import imagecodecs
    decode = imagecodecs.png_decode
    def noisy(*args, **kwargs):
        logging.getLogger("imagecodecs").warning("PNG warning: IDAT: incorrect data check")
        return decode(*args, **kwargs)
    imagecodecs.png_decode = noisy
elif mode == "lazy":  # every TIFF and zarr input read window by window, as large ones are
    import reblur.io
    reblur.io.LAZY_BYTES = 0
elif mode == "compute":
    # the masks go to a work store on disk (as for inputs over 64 MP); the marker appears
    # when the computation starts
    import reblur
    import reblur.cli as C
    C.LARGE_MASK_PIXELS = 0
    detect = reblur.detect_changes
    def marked(*args, **kwargs):
        open(marker, "a").close()
        return detect(*args, **kwargs)
    reblur.detect_changes = marked
from reblur.cli import main
sys.argv = ["reblur", *sys.argv[3:]]
main()
"""


def scene(rng, side=256) -> tuple[np.ndarray, np.ndarray]:
    """A reference of flat shapes and an observation shifted by (2, 1) px, blurred along x,
    with one painted change: a pair reblur detects in a few seconds."""
    img = np.full((side, side, 3), 90.0)
    for _ in range(160):
        x, y = (int(v) for v in rng.integers(0, side, 2))
        s = int(rng.integers(4, 18))
        col = [float(c) for c in rng.integers(0, 255, 3)]
        if rng.random() < 0.5:
            cv2.rectangle(img, (x, y), (x + s, y + int(s * 0.7)), col, -1)
        else:
            cv2.circle(img, (x, y), s // 2, col, -1)
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    obs = cv2.blur(np.roll(img, (2, 1), (0, 1)), (3, 1))
    obs[60:80, 60:90] = (250, 20, 20)
    return img.astype(np.uint8), obs.astype(np.uint8)


@pytest.fixture
def pair(tmp_path):
    ref, obs = scene(np.random.default_rng(21))
    d = tmp_path / "in"
    d.mkdir()
    write_png(d / "ref.png", ref)
    write_png(d / "obs.png", obs)
    return d / "ref.png", d / "obs.png"


FAST = ("--t-max", 3, "--rz-max", 0, "-q")


def detect_args(pair, out, *extra) -> list:
    return ["detect", *pair, "--out", out, *FAST, *extra]


def drive(mode: str, marker: Path, *args) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", DRIVER, mode, str(marker), *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def assert_complete(out: Path) -> dict:
    """``out`` holds exactly the files its report.json lists, each readable."""
    import json

    rep = json.loads((out / "report.json").read_text())
    names = sorted({n.split("/")[0] for n in rep["files"].values()})  # viewer/index.html
    assert sorted(p.name for p in out.iterdir()) == names
    for n in names:
        assert (out / n).stat().st_size > 0
    assert cv2.imread(str(out / "changes.png"), cv2.IMREAD_UNCHANGED).shape == (256, 256)
    return rep


def test_disk_full_mid_write_leaves_no_output(tmp_path, pair):
    out = tmp_path / "res"
    proc = drive("enospc", tmp_path / "m", *detect_args(pair, out))
    stdout, stderr = proc.communicate(timeout=120)
    res = subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)
    assert_one_line_error(res, r"res: cannot write the results \(No space left on device\); "
                               r"nothing was written")
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]  # no temporary, no lock
    # with --overwrite, earlier results stay exactly as they were
    out.mkdir()
    (out / "report.json").write_text('{"earlier": true}')
    (out / "changes.png").write_bytes(b"earlier")
    proc = drive("enospc", tmp_path / "m", *detect_args(pair, out, "--overwrite"))
    stdout, stderr = proc.communicate(timeout=120)
    res = subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)
    assert_one_line_error(res, r"No space left on device")
    assert {p.name: p.read_bytes() for p in out.iterdir()} == {
        "report.json": b'{"earlier": true}', "changes.png": b"earlier"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in", "res"]


def _kill_during_write(tmp_path: Path, args: list, delay: float) -> int:
    """Start a run whose writers are slowed, SIGKILL it ``delay`` s into the write phase."""
    import signal
    import time

    marker = tmp_path / f"writing-{delay}"
    proc = drive("slow", marker, *args)
    t_end = time.monotonic() + 120
    while not marker.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < t_end
        time.sleep(0.02)
    time.sleep(delay)
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    return proc.pid


def test_killed_runs_leave_no_or_complete_results_and_are_cleaned(tmp_path, pair):
    out = tmp_path / "res"
    for delay in (0.1, 1.0):  # during the first file, and a few files later
        pid = _kill_during_write(tmp_path, detect_args(pair, out), delay)
        assert not out.exists()
        # the killed run's temporary is left; the one before it was removed by this run
        left = [p.name for p in tmp_path.iterdir() if p.name.startswith(".res.reblur-tmp-")]
        assert [n.split("-")[2] for n in left] == [str(pid)]
    # a temporary of a live process is not touched (this test's own pid)
    live = tmp_path / f".res.reblur-tmp-{os.getpid()}-keep"
    live.mkdir()
    res = run(*detect_args(pair, out))
    assert res.returncode == 0, res.stderr
    assert_complete(out)
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith("writing-")) == [
        live.name, "in", "res"]
    # killed while overwriting: the earlier complete set stays, byte for byte
    def files(d: Path) -> dict[str, bytes]:  # the viewer/ folder too
        return {str(p.relative_to(d)): p.read_bytes() for p in d.rglob("*") if p.is_file()}

    before = files(out)
    _kill_during_write(tmp_path, detect_args(pair, out, "--overwrite"), 0.5)
    assert files(out) == before


def test_overwrite_into_a_folder_with_other_files(tmp_path, pair):
    """A folder that also holds files of the user's (here: the inputs, and a changes.tif no
    earlier report lists) is filled file by file; those files stay, with a warning for the
    one that has a result's name, and the new set is complete."""
    import json

    ref, obs = pair
    out = ref.parent
    (out / "changes.tif").write_bytes(b"a user's own file, not a reblur result")
    res = run(*detect_args(pair, out))
    assert_one_line_error(res, r"already holds results \(changes\.tif\)")
    res = run(*detect_args(pair, out, "--overwrite"))
    assert res.returncode == 0, res.stderr
    assert res.stderr == (f"reblur: WARNING: left {out / 'changes.tif'} in place: this run does "
                          "not write it and the earlier report does not list it (it is not "
                          "part of the new result set)\n")
    assert (out / "changes.tif").read_bytes() == b"a user's own file, not a reblur result"
    inputs = {ref.name: ref.read_bytes(), obs.name: obs.read_bytes()}
    for p in (ref, obs, out / "changes.tif"):
        p.rename(tmp_path / p.name)
    assert_complete(out)
    assert "changes.tif" not in json.loads((out / "report.json").read_text())["files"]
    assert {n: (tmp_path / n).read_bytes() for n in inputs} == inputs
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["in", "changes.tif", *inputs])


@pytest.mark.parametrize("other", [False, True], ids=["swapped", "file-by-file"])
def test_overwrite_removes_only_the_earlier_sets_files(tmp_path, other):
    """--overwrite removes the files the earlier report.json lists (its changes.tif of a
    larger input, which this run does not write) and leaves a file of a result's name it
    does not list; whether the folder is swapped whole or filled file by file."""
    import json

    import reblur.outdir as od

    names = ("changes.png", "changes.tif", "changes.geojson", "unknown.tif", "report.json")
    out = tmp_path / "res"
    out.mkdir()
    earlier = {"changes.png": "changes.png", "changes.tif": "changes.tif",
               "changes.geojson": "changes.geojson", "report.json": "report.json"}
    for n in earlier:
        (out / n).write_text("earlier")
    (out / "report.json").write_text(json.dumps({"files": earlier}))
    (out / "unknown.tif").write_text("not listed: someone else's")
    if other:
        (out / "notes.txt").write_text("mine")
    with od.output_set(out, names, overwrite=True, last=("report.json",),
                       manifest="report.json") as stage:
        (stage / "changes.png").write_text("new")
        (stage / "report.json").write_text(json.dumps({"files": {"changes.png": "changes.png",
                                                                 "report.json": "report.json"}}))
    got = {p.name: p.read_text() for p in out.iterdir()}
    assert got.pop("changes.png") == "new"
    assert json.loads(got.pop("report.json"))["files"] == {"changes.png": "changes.png",
                                                           "report.json": "report.json"}
    assert got == {"unknown.tif": "not listed: someone else's",
                   **({"notes.txt": "mine"} if other else {})}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]
    # without a manifest (reblur simulate's set), every file of the names is a result
    (out / "changes.tif").write_text("earlier")
    with od.output_set(out, names, overwrite=True) as stage:
        (stage / "changes.png").write_text("newer")
    assert sorted(p.name for p in out.iterdir()) == ["changes.png"] + (
        ["notes.txt"] if other else [])


def test_second_run_into_a_locked_folder_is_refused(tmp_path, pair):
    import fcntl

    from reblur.outdir import lock_path

    out = tmp_path / "res"
    lock = lock_path(out)
    assert lock == tmp_path / ".res.reblur-lock"
    with open(lock, "w") as fh:
        fh.write("4242\n")
        fh.flush()
        fcntl.flock(fh, fcntl.LOCK_EX)
        res = run(*detect_args(pair, out))
        assert_one_line_error(res, r"res: another reblur run \(pid 4242\) is writing into this "
                                   r"output directory")
        assert not out.exists()
        assert lock.read_text() == "4242\n"
    lock.unlink()


def test_two_concurrent_runs_do_not_mix(tmp_path, pair):
    """Two runs started together: one writes, the other is refused (locked, or the folder
    already holds the first one's results)."""
    out = tmp_path / "res"
    procs = [subprocess.Popen([sys.executable, "-m", "reblur", *map(str, detect_args(pair, out))],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    results = [p.communicate(timeout=120) + (p.returncode,) for p in procs]
    codes = sorted(r[2] for r in results)
    assert codes == [0, 1], results
    refused = next(r for r in results if r[2] == 1)
    assert re.fullmatch(r"reblur: error: .*(another reblur run|already holds results).*\n",
                        refused[1]), refused
    assert_complete(out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in", "res"]


def test_output_set_inside_the_folder_when_the_parent_is_not_writable(tmp_path, monkeypatch):
    """Root ignores permissions, so an unwritable parent is simulated: the temporary folder
    and the lock then live inside the output folder and the files are moved in one by one."""
    import reblur.outdir as od

    monkeypatch.setattr(od, "_in_parent", lambda out: False)
    out = tmp_path / "res"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    (out / "old.txt").write_text("earlier result")
    names = ("a.txt", "old.txt", "report.json")
    with pytest.raises(od.OutputDirError, match=r"already holds results \(old\.txt\)"):
        with od.output_set(out, names):
            pass
    with pytest.raises(RuntimeError, match="boom"):
        with od.output_set(out, names, overwrite=True) as stage:
            assert stage.parent == out and (out / ".reblur-lock").is_file()
            (stage / "a.txt").write_text("new")
            raise RuntimeError("boom")
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt", "old.txt"]
    with od.output_set(out, names, overwrite=True, last=("report.json",)) as stage:
        (stage / "a.txt").write_text("new")
        (stage / "report.json").write_text("{}")
    assert {p.name: p.read_text() for p in out.iterdir()} == {
        "notes.txt": "mine", "a.txt": "new", "report.json": "{}"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]


# ---------------------------------------------------------------------------- bombs
# forged headers, the byte limit and strip decoding: tests/test_big_inputs.py
def test_other_formats_sized_from_their_header(tmp_path):
    import imagecodecs

    a = textured(np.random.default_rng(14), 48, 80)
    for name, data in (("a.webp", imagecodecs.webp_encode(a, lossless=True)),
                       ("a.jxl", imagecodecs.jpegxl_encode(a, lossless=True))):
        (tmp_path / name).write_bytes(data)
        np.testing.assert_array_equal(open_image(tmp_path / name).read(), a)
        with pytest.raises(InputError, match=r"3,840 pixels \(80x48\), more than the limit"):
            open_image(tmp_path / name, max_pixels=3000)


# ---------------------------------------------------------------------------- interrupts
def _signal_when_marked(proc: subprocess.Popen, marker: Path, sig: int, delay: float) -> None:
    import time

    t_end = time.monotonic() + 120
    while not marker.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < t_end
        time.sleep(0.02)
    time.sleep(delay)
    proc.send_signal(sig)


@pytest.mark.parametrize("mode, delay", [("compute", 0.5), ("slow", 0.3)],
                         ids=["computing", "writing"])
def test_ctrl_c_exits_130_and_leaves_nothing(tmp_path, pair, mode, delay):
    """SIGINT (Ctrl-C) while computing (with the masks' work store on disk) and while
    writing: exit status 130, one line "interrupted", no temporary left anywhere."""
    import signal

    out = tmp_path / "res"
    marker = tmp_path / "marker"
    proc = drive(mode, marker, *detect_args(pair, out, "--workers", 2))
    _signal_when_marked(proc, marker, signal.SIGINT, delay)
    stdout, stderr = proc.communicate(timeout=60)
    assert (proc.returncode, stdout, stderr) == (130, "", "reblur: error: interrupted\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in", "marker"]


# ---------------------------------------------------------------------------- options
@pytest.mark.parametrize("args, pattern", [
    (("--threshold", "nan"), r"'--threshold': 'nan' is not a finite number"),
    (("--threshold", "inf"), r"'--threshold': 'inf' is not a finite number"),
    (("--threshold", "-1"), r"'--threshold': -1\.0 is not in the range x>0"),
    (("--rz-max", "inf"), r"'--rz-max': 'inf' is not a finite number"),
    (("--rz-max", "90"), r"'--rz-max': 90\.0 is not in the range 0<=x<=45"),
    (("--rz-step", "nan"), r"'--rz-step': 'nan' is not a finite number"),
    (("--lam", "1e308"), r"'--lam': 1e\+308 is not in the range 0<x<=1000"),
    (("--lam", "-inf"), r"'--lam': '-inf' is not a finite number"),
    (("--rz-step", "1e-9"), r"pose grid would hold 3,750,000,000,625 poses \(25x25 "
                            r"translations x 6,000,000,001 rotations\), more than the budget "
                            r"of 33,554,432 poses"),
    (("--t-max", "3000", "--rz-step", "0.5"), r"pose grid would hold 468,156,013 poses"),
], ids=lambda v: " ".join(v) if isinstance(v, tuple) else None)
def test_absurd_option_values_refused_up_front(tmp_path, args, pattern):
    """Refused before any input is opened (the inputs do not even exist): usage error 2."""
    from click.testing import CliRunner

    from reblur.cli import main

    res = CliRunner().invoke(main, ["detect", str(tmp_path / "nope.png"),
                                    str(tmp_path / "nope2.png"), "--out",
                                    str(tmp_path / "res"), *args])
    assert res.exit_code == 2, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("reblur: error: Invalid value for "), lines
    assert re.search(pattern, lines[0]), lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.parametrize("option, value", [("--noise", "nan"), ("--rz-max", "inf"),
                                           ("--shift-frac", "2"), ("--t-max", "-1")])
def test_simulate_refuses_absurd_values(tmp_path, option, value):
    from click.testing import CliRunner

    from reblur.cli import main

    res = CliRunner().invoke(main, ["simulate", str(tmp_path / "nope.png"), "--out",
                                    str(tmp_path / "sim"), option, value])
    assert res.exit_code == 2, res.output
    assert re.fullmatch(rf"reblur: error: Invalid value for '{option}': .*\n", res.output)


def test_pose_budget_in_the_library():
    """The grid's size is computed from its ranges before anything is allocated: a grid of
    6e9 rotations is refused at once, and the count matches the grid actually built."""
    from reblur.grid import MAX_POSES, PoseGrid, grid_size_for

    for kw in (dict(t_max=3, rz_max=1.0, rz_step=0.3), dict(t_max=0, rz_max=0.0, rz_step=None),
               dict(t_max=5, rz_max=2.0, corner_px=1.0, rz_step=None)):
        grid = PoseGrid.from_ranges((300, 400), **kw)
        assert grid_size_for((300, 400), **kw) == grid.size
    assert PoseGrid.from_ranges((300, 400), t_max=3, rz_max=1.0, rz_step=0.3).rz == (
        -1.2, -0.8999999999999999, -0.6, -0.3, 0.0, 0.3, 0.6, 0.8999999999999999, 1.2)
    with pytest.raises(ValueError, match=rf"more than the budget of {MAX_POSES:,} poses"):
        PoseGrid.from_ranges((300, 400), rz_max=3.0, rz_step=1e-9)
    for bad in (dict(rz_max=float("inf")), dict(rz_step=float("nan")), dict(t_max=-1)):
        with pytest.raises(ValueError, match=r"must be a finite number >= 0"):
            PoseGrid.from_ranges((300, 400), **bad)


# ---------------------------------------------------------------------------- windowed reads
def _flip_tiff_segment(path: Path, index: int) -> None:
    """Corrupt the compressed data of tile/strip ``index`` (its first two bytes kept)."""
    with tifffile.TiffFile(path) as tif:
        off = int(tif.pages[0].dataoffsets[index])
        n = int(tif.pages[0].databytecounts[index])
    data = bytearray(path.read_bytes())
    data[off + 2 : off + n] = bytes(b ^ 0x55 for b in data[off + 2 : off + n])
    path.write_bytes(bytes(data))


def _set_tiff_tag(path: Path, code: int, value: int | None) -> None:
    """Set a short tag of the first IFD of a little-endian classic TIFF (``None``: rename the
    tag to an unknown code, as if it were missing)."""
    import struct

    data = bytearray(path.read_bytes())
    ifd = struct.unpack("<I", data[4:8])[0]
    for i in range(struct.unpack("<H", data[ifd : ifd + 2])[0]):
        e = ifd + 2 + 12 * i
        if struct.unpack("<H", data[e : e + 2])[0] == code:
            if value is None:
                data[e : e + 2] = struct.pack("<H", 65000)
            else:
                data[e + 8 : e + 10] = struct.pack("<H", value)
    path.write_bytes(bytes(data))


@pytest.fixture
def tiled_pair(tmp_path, pair):
    """The test pair as tiled TIFFs (64 px tiles, deflate)."""
    d = tmp_path / "tif"
    d.mkdir()
    for p in pair:
        tifffile.imwrite(d / (p.stem + ".tif"), open_image(p).read(), tile=(64, 64),
                         compression="deflate")
    return d / "ref.tif", d / "obs.tif"


def test_corrupt_tile_of_a_lazily_read_tiff_is_named(pair, tiled_pair):
    ref, _ = tiled_pair
    _flip_tiff_segment(ref, 10)  # not the first tile: found while the windows are read
    img = open_image(ref, lazy=True)
    np.testing.assert_array_equal(img.array[0:64, 0:64], open_image(pair[0]).read()[0:64, 0:64])
    with pytest.raises(InputError, match=r"ref\.tif: cannot decode the image data at rows "
                                         r"128-191, columns 128-191 \(.*\): the file is corrupt"):
        img.array[128:192, 128:192]


def test_corrupt_chunk_of_a_lazily_read_zarr_is_named(tmp_path):
    a = textured(np.random.default_rng(15), 128, 128, bands=1)
    store = tmp_path / "ref.zarr"
    zarr.create_array(str(store), shape=a.shape, chunks=(64, 64), dtype="u1",
                      fill_value=0)[...] = a
    chunk = store / "c" / "1" / "1"
    chunk.write_bytes(bytes(b ^ 0x55 for b in chunk.read_bytes()))
    img = open_image(store, lazy=True)
    np.testing.assert_array_equal(img.array[0:64, 0:64], a[0:64, 0:64])
    with pytest.raises(InputError, match=r"ref\.zarr: cannot decode the image data at rows "
                                         r"32-99, columns 0-127"):
        img.array[32:100, :]
    # the first chunk corrupt: refused when opened
    first = store / "c" / "0" / "0"
    first.write_bytes(bytes(b ^ 0x55 for b in first.read_bytes()))
    with pytest.raises(InputError, match=r"ref\.zarr: cannot decode the image data at rows "
                                         r"0-63, columns 0-63"):
        open_image(store, lazy=True)


@pytest.mark.parametrize("lazy", [False, True])
def test_undecodable_tiff_compression_refused_at_open(tiled_pair, lazy):
    ref, _ = tiled_pair
    _set_tiff_tag(ref, 259, 60123)  # Compression: a code no codec knows
    with pytest.raises(InputError, match=r"ref\.tif: TIFF compression 60123 cannot be decoded"):
        open_image(ref, lazy=lazy)
    _set_tiff_tag(ref, 259, 34887)  # LERC: a known codec, but the data is deflate
    with pytest.raises(InputError, match=r"ref\.tif: cannot decode (TIFF|the) image data"):
        open_image(ref, lazy=lazy)


def test_corrupt_large_tiff_in_the_cli_is_one_named_line(tmp_path, tiled_pair):
    """The CLI with every input read window by window (as inputs over 512 MB are): a corrupt
    tile deep in the file gives one line naming it; no internal error, no asyncio noise."""
    ref, obs = tiled_pair
    _flip_tiff_segment(ref, 10)
    out = tmp_path / "res"
    proc = drive("lazy", tmp_path / "m", "detect", ref, obs, "--out", out, *FAST,
                 "--workers", 2)
    stdout, stderr = proc.communicate(timeout=120)
    res = subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)
    assert_one_line_error(res, r"ref\.tif: cannot decode the image data at rows \d+-\d+, "
                               r"columns \d+-\d+ \(.*\): the file is corrupt or truncated")
    assert not out.exists()


def test_tifffile_log_lines_become_part_of_the_one_line(tmp_path, tiled_pair):
    ref, obs = tiled_pair
    _set_tiff_tag(ref, 325, None)  # TileByteCounts missing: tifffile logs two ERROR lines
    res = run("detect", ref, obs, "--out", tmp_path / "res", "-q")
    assert_one_line_error(res, r"ref\.tif: TIFF header is corrupt: the image's tile or strip "
                               r"table is missing or invalid \(tifffile: .*ByteCounts")


# ---------------------------------------------------------------------------- diagnoses
def test_symlink_loops_are_named(tmp_path, pair):
    (tmp_path / "a.png").symlink_to(tmp_path / "b.png")
    (tmp_path / "b.png").symlink_to(tmp_path / "a.png")
    (tmp_path / "o1").symlink_to(tmp_path / "o2")
    (tmp_path / "o2").symlink_to(tmp_path / "o1")
    with pytest.raises(InputError, match=r"a\.png: symlink loop: the path cannot be resolved"):
        open_image(tmp_path / "a.png")
    before = sorted(p.name for p in tmp_path.iterdir())
    for args in ((tmp_path / "a.png", pair[1], "--out", tmp_path / "res"),
                 (*pair, "--out", tmp_path / "o1" / "res")):
        res = run("detect", *args, "-q")
        assert_one_line_error(res, r"(a\.png|o1/res): symlink loop: the path cannot be resolved")
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_sizes_far_apart_are_named_not_textureless(tmp_path):
    """A thumbnail-sized observation of a large reference: the sizes are the problem (it
    was reported as "images are textureless")."""
    from reblur.io import MAX_SIZE_RATIO, Image, check_sizes

    rng = np.random.default_rng(16)
    big = textured(rng, 1024, 1024, bands=1)
    small = cv2.resize(big, (64, 64), interpolation=cv2.INTER_AREA)
    write_png(tmp_path / "big.png", big)
    write_png(tmp_path / "small.png", small)
    res = run("detect", tmp_path / "big.png", tmp_path / "small.png", "--out", tmp_path / "res")
    line = assert_one_line_error(res, r"the sizes of .*small\.png \(64x64\) and .*big\.png "
                                      r"\(1024x1024\) disagree by a factor of 16: the "
                                      r"observation is not a view of the reference at a "
                                      r"compatible scale")
    assert "textureless" not in line
    assert not (tmp_path / "res").exists()
    # the limit: half the size passes, a quarter does not, either way round
    for side, ok in ((512, True), (257, True), (256, False)):
        a = Image.from_array(np.zeros((side, 1024), np.uint8), "a")
        b = Image.from_array(np.zeros((1024, 1024), np.uint8), "b")
        for pair_ in ((a, b), (b, a)):
            if ok:
                check_sizes(*pair_)
            else:
                with pytest.raises(InputError, match=rf"factor of {1024 / side:g}"):
                    check_sizes(*pair_)
    assert MAX_SIZE_RATIO == 4


def test_wide_integer_data_rescaled_from_the_range_it_uses(tmp_path):
    """int64 data holding 8-bit values was "textureless" (values / 2**63): it is read as
    float32 from the range it uses, lazily too; masks keep their values."""
    a = textured(np.random.default_rng(17), 80, 96, bands=1).astype(np.int64) * 3 - 100
    lo, hi = int(a.min()), int(a.max())
    expect = ((a - lo) / (hi - lo)).astype(np.float32)
    for dtype in (np.int64, np.uint32, np.int32):
        b = a - lo if dtype == np.uint32 else a
        tifffile.imwrite(tmp_path / "w.tif", b.astype(dtype), tile=(32, 32))
        for lazy in (False, True):
            img = open_image(tmp_path / "w.tif", lazy=lazy)
            assert img.dtype == np.float32
            np.testing.assert_allclose(img.read(), expect, atol=1e-6)
            assert any("rescaled" in n and f"[{lo - (lo if dtype == np.uint32 else 0)}" in n
                       for n in img.notes), img.notes
    # 8/16-bit data keep their type; a constant wide image is left as it is
    tifffile.imwrite(tmp_path / "c.tif", np.full((40, 40), 7, np.int64))
    assert open_image(tmp_path / "c.tif").dtype == np.int64
    tifffile.imwrite(tmp_path / "u.tif", a.astype(np.uint16) + 100)
    assert open_image(tmp_path / "u.tif").dtype == np.uint16


def test_wide_integer_pair_detects_the_change_and_names_are_escaped(tmp_path, pair):
    """The test pair stored as int64 (it was refused as "textureless") gives the mask of
    the same pair in 8 bits and finds the painted change, written into a folder whose name
    holds a newline and a terminal escape: every printed line keeps them escaped.

    The change covers a shape of the reference whose edges the model-error tolerance
    widens: the statistic dips to 1.4-1.6 times the threshold there, so how much of that
    corner a run keeps moves with the estimate (508 to 600 of the 600 pixels between
    its variants on this noise-free pair; all 600 with 0.5 DN of noise)."""
    ref, obs = (open_image(p).read().astype(np.int64) for p in pair)
    d = tmp_path / "in64"
    d.mkdir()
    tifffile.imwrite(d / "ref.tif", ref, photometric="rgb")
    tifffile.imwrite(d / "obs.tif", obs, photometric="rgb")
    out = tmp_path / "res\n\x1b[31mred"
    res = run("detect", d / "ref.tif", d / "obs.tif", "--out", out, *FAST, "-v")
    assert res.returncode == 0, res.stderr
    assert res.stdout.endswith("-> " + str(tmp_path) + "/res\\n\\x1b[31mred/overlay.png\n")
    assert res.stdout.count("\n") == 1
    for stream in (res.stdout, res.stderr):
        assert "\x1b" not in stream
    assert all(line.startswith("reblur: ") for line in res.stderr.splitlines()), res.stderr
    changes = cv2.imread(str(out / "changes.png"), cv2.IMREAD_UNCHANGED) > 0
    eight = tmp_path / "eight"
    assert run("detect", *pair, "--out", eight, *FAST).returncode == 0
    np.testing.assert_array_equal(
        changes, cv2.imread(str(eight / "changes.png"), cv2.IMREAD_UNCHANGED) > 0)
    truth = np.zeros_like(changes)
    truth[60:80, 60:90] = True  # painted in the observation, whose frame changes.png is in
    near = np.zeros_like(changes)
    near[50:90, 50:100] = True  # the change and a 10 px rim (the closing of the regions)
    assert (changes & truth).sum() >= 0.8 * truth.sum()
    assert not (changes & ~near).any()


@pytest.mark.parametrize("name", ["no\nsuch\x1b]0;owned\x07.png", "bad\udcff\x9b2J.png"],
                         ids=["newline-osc", "not-utf8-csi"])
def test_error_lines_escape_control_characters(tmp_path, pair, name):
    from reblur.io import display_path

    p = os.fsencode(tmp_path / name)
    res = subprocess.run([sys.executable, "-m", "reblur", "detect", p, os.fsencode(pair[1]),
                          "--out", os.fsencode(tmp_path / "res")], capture_output=True)
    assert res.returncode == 1 and res.stdout == b""
    line = res.stderr.decode("utf-8")  # undecodable bytes would fail here
    assert line == f"reblur: error: {display_path(tmp_path / name)}: no such file\n"
    assert line.count("\n") == 1 and "\x1b" not in line and "\x07" not in line
    assert display_path(name) in (r"no\nsuch\x1b]0;owned\x07.png", r"bad\xff\x9b2J.png")


def test_names_that_are_not_utf8_reach_every_text_output_escaped(tmp_path, pair):
    """A reference and observations whose names are Latin-1, not UTF-8 (bytes 0xff, 0xe9):
    the run succeeds, every text output (report.json, report.html, the viewer's data,
    summary.csv, index.html) is UTF-8, and the names appear with those bytes as ``\\xNN``
    (report.html used to fail to write: a UTF-8 file cannot hold the undecodable bytes)."""
    d = os.fsencode(tmp_path)
    ref, obs, obs2 = d + b"/ref\xff.png", d + b"/obs\xe9.png", d + b"/obs2.png"
    for src, dst in ((pair[0], ref), (pair[1], obs), (pair[1], obs2)):
        with open(dst, "wb") as f:
            f.write(Path(src).read_bytes())
    single, many = d + b"/one", d + b"/many"
    for out, observed in ((single, [obs]), (many, [obs, obs2])):
        res = subprocess.run([sys.executable, "-m", "reblur", "detect", ref, *observed,
                              "--out", out, *map(str, FAST)], capture_output=True)
        assert res.returncode == 0, res.stderr.decode("utf-8", "backslashreplace")
    texts = [p for p in Path(os.fsdecode(d)).rglob("*")
             if p.suffix in (".json", ".html", ".js", ".csv")]
    assert len(texts) >= 10
    for p in texts:
        p.read_bytes().decode("utf-8")  # strict: fails on any byte that is not UTF-8
    one = Path(os.fsdecode(single))
    rep = json.loads((one / "report.json").read_text(encoding="utf-8"))
    assert rep["inputs"]["reference"]["path"].endswith("/ref\\xff.png")
    assert rep["inputs"]["observed"]["path"].endswith("/obs\\xe9.png")
    page = (one / "report.html").read_text(encoding="utf-8")
    assert "ref\\xff.png" in page and "obs\\xe9.png" in page
    rows = list(csv.DictReader((Path(os.fsdecode(many)) / "summary.csv").open(encoding="utf-8")))
    assert [r["status"] for r in rows] == ["ok", "ok"]
    assert rows[0]["source"].endswith("obs\\xe9.png")
    index = (Path(os.fsdecode(many)) / "index.html").read_text(encoding="utf-8")
    for r in rows:  # every link leads to the observation's folder
        assert f'href="{quote(os.fsencode(r["name"]), safe="")}/report.html"' in index
        assert (Path(os.fsdecode(many)) / r["name"] / "report.html").is_file()


# ---------------------------------------------------------------------------- work store
def test_large_run_work_store_never_in_the_output_folder(tmp_path, pair):
    """The masks' work store of a large run (forced here on a small pair) lives in the
    temporary sibling: a run killed while computing leaves no output folder, only its
    temporary, which the next run removes even when that run fails."""
    import signal

    out = tmp_path / "res"
    marker = tmp_path / "marker"
    proc = drive("compute", marker, *detect_args(pair, out))
    seen: list[str] = []

    def work_store_exists() -> bool:
        seen[:] = [str(p.relative_to(tmp_path)) for p in tmp_path.glob(".res.reblur-tmp-*/*")]
        return any(".reblur-work-" in s for s in seen)

    import time

    t_end = time.monotonic() + 60
    while not (marker.exists() and work_store_exists()):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < t_end
        time.sleep(0.02)
    assert not out.exists()  # not created before the results are complete
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=30)
    left = sorted(p.name for p in tmp_path.iterdir() if p.name not in ("in", "marker"))
    assert len(left) == 2 and left[0] == ".res.reblur-lock"  # released by the kernel
    assert left[1].startswith(f".res.reblur-tmp-{proc.pid}-")
    # the next run fails (its truth mask has the wrong size) and still cleans up after both
    write_png(tmp_path / "in" / "truth.png", np.zeros((40, 40), bool))
    res = run(*detect_args(pair, out, "--truth", tmp_path / "in" / "truth.png"))
    assert_one_line_error(res, r"truth mask is 40x40 pixels")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in", "marker"]


# ---------------------------------------------------------------------------- a real full disk
def test_real_disk_full_leaves_no_output(small_disk, pair):
    """The disk fills while the results are written (no writer patched): one line, no
    output folder, no temporary or lock left on the disk.  (With --overwrite an earlier set
    stays intact: test_disk_full_mid_write_leaves_no_output.)"""
    out = small_disk / "res"
    res = run(*detect_args(pair, out))
    assert_one_line_error(res, r"res: cannot write the results \(No space left on device\); "
                               r"nothing was written")
    assert list(small_disk.iterdir()) == []


@pytest.mark.parametrize("quiet", [False, True])
def test_a_cog_filling_the_disk_prints_nothing_once_libtiff_is_quiet(small_disk, quiet):
    """A COG that fills the disk in the middle of GDAL's write (the failure the test above
    meets when the disk fills during a COG): GDAL's error comes out as the OS's "no space
    left" either way; libtiff's own lines reach stderr unless the command's
    ``_quiet_libtiff`` ran (the unquiet run shows the check can fail)."""
    code = (
        "import sys, numpy as np\n"
        "from reblur import cli\n"
        "from reblur.gis import write_cog\n"
        f"assert cli._quiet_libtiff() if {quiet} else True\n"
        "a = np.random.default_rng(0).integers(0, 256, (1200, 1200), dtype=np.uint8)\n"
        "import errno\n"
        "try:\n"
        f"    write_cog({str(small_disk / 'x.tif')!r}, a, None, block=256)\n"
        "except OSError as exc:\n"
        "    sys.exit(3 if exc.errno == errno.ENOSPC else 4)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 3, res.stderr
    assert ("_tiff" in res.stderr) is (not quiet), res.stderr


# ---------------------------------------------------------------------------- property-based
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_SAMPLE: dict = {}


def _samples() -> dict[str, tuple[dict[str, bytes], np.ndarray, tuple[int, int]]]:
    """Valid inputs of each format, as ``{name: (files, decoded array, payload span)}``:
    ``files`` maps a relative path to its bytes (a zarr store is a directory), the payload
    span is where the format's integrity check covers the bytes (flips there must be
    caught: PNG's chunk CRCs, the TIFF tiles' deflate checksums, a crc32c zarr codec)."""
    if _SAMPLE:
        return _SAMPLE
    import tempfile

    from zarr.codecs import Crc32cCodec, ZstdCodec

    a = textured(np.random.default_rng(18), 48, 40)
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        write_png(d / "a.png", a)
        png = (d / "a.png").read_bytes()
        _SAMPLE["png"] = ({"a.png": png}, a, (8, len(png)))
        jpg = cv2.imencode(".jpg", a[..., ::-1])[1].tobytes()
        _SAMPLE["jpeg"] = ({"a.jpg": jpg}, open_image_bytes(d, "a.jpg", jpg), (0, 0))
        tifffile.imwrite(d / "a.tif", a, tile=(16, 16), compression="deflate",
                         photometric="rgb")
        with tifffile.TiffFile(d / "a.tif") as tif:
            offs, cnts = tif.pages[0].dataoffsets, tif.pages[0].databytecounts
        _SAMPLE["tiff"] = ({"a.tif": (d / "a.tif").read_bytes()}, a,
                           (int(min(offs)), int(max(np.add(offs, cnts)))))
        z = zarr.create_array(str(d / "a.zarr"), shape=a.shape, chunks=(16, 16, 3),
                              dtype="u1", fill_value=0,
                              compressors=[ZstdCodec(), Crc32cCodec()])
        z[...] = a
        files = {str(p.relative_to(d)): p.read_bytes() for p in (d / "a.zarr").rglob("*")
                 if p.is_file()}
        _SAMPLE["zarr"] = (files, a, (0, 0))
    return _SAMPLE


def open_image_bytes(d: Path, name: str, data: bytes) -> np.ndarray:
    (d / name).write_bytes(data)
    return open_image(d / name).read()


@st.composite
def _mutations(draw):
    """``(format, file to mutate, new bytes, must be caught)``."""
    fmt = draw(st.sampled_from(["png", "jpeg", "tiff", "zarr"]))
    files, _, (p0, p1) = _samples()[fmt]
    if fmt == "zarr":
        name = draw(st.sampled_from(sorted(files)))  # a chunk, or the metadata
    else:
        name = next(iter(files))
    data = bytearray(files[name])
    if draw(st.booleans()):
        cut = draw(st.integers(0, len(data) - 1))
        return fmt, name, bytes(data[:cut]), True  # truncated: refused, whatever the format
    in_payload = draw(st.booleans()) and p1 > p0
    caught = True
    for _ in range(draw(st.integers(1, 3))):
        if in_payload:
            i = draw(st.integers(p0, p1 - 1))
        elif fmt == "zarr" and name.startswith("a.zarr/c/"):
            i = draw(st.integers(0, len(data) - 1))  # a chunk: crc32c covers it all
        else:
            i = draw(st.integers(0, len(data) - 1))
            caught = fmt == "png" and i >= 8  # PNG: every chunk has a CRC
        data[i] ^= draw(st.integers(1, 255))
    return fmt, name, bytes(data), caught


def _write(d: Path, fmt: str, name: str, data: bytes) -> Path:
    files = _samples()[fmt][0]
    for rel, b in files.items():
        (d / rel).parent.mkdir(parents=True, exist_ok=True)
        (d / rel).write_bytes(data if rel == name else b)
    return d / ("a.zarr" if fmt == "zarr" else name)


@settings(max_examples=60, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(mutation=_mutations(), lazy=st.booleans())
def test_readers_never_accept_changed_content(mutation, lazy):
    """Random truncations and byte flips of valid PNG, JPEG, TIFF and zarr inputs, read
    whole or window by window (a PNG or JPEG then decoded in strips): the reader refuses
    them with one line naming the file (any other exception fails the test, with its
    traceback), or gives back exactly the original pixels wherever the format can tell (a
    truncation anywhere; a flip under a checksum).  Without a checksum (JPEG data, TIFF
    tags, zarr metadata) a flip may change what the file says: not caught, never a crash."""
    import tempfile

    fmt, name, data, caught = mutation
    _, original, _ = _samples()[fmt]
    with tempfile.TemporaryDirectory() as d:
        path = _write(Path(d), fmt, name, data)
        try:
            with open_image(path, lazy=lazy) as img:  # PNG, JPEG: decoded in strips
                got = img.read()
        except InputError as exc:
            msg = str(exc)
            assert "\n" not in msg and msg.startswith(f"{path}: "), msg
            return
    if caught and data != _samples()[fmt][0][name]:
        assert got.shape == original.shape and got.dtype == original.dtype
        np.testing.assert_array_equal(got, original)


@settings(max_examples=4, deadline=None, derandomize=True)
@given(fmt=st.sampled_from(["png", "jpeg", "tiff", "zarr"]), frac=st.floats(0.05, 0.95))
def test_truncated_inputs_refused_by_the_cli(fmt, frac):
    """The CLI on a truncated reference (a zarr store: its first chunk): exit 1, one line
    naming it, no output folder."""
    import tempfile

    files, _, _ = _samples()[fmt]
    name = "a.zarr/c/0/0/0" if fmt == "zarr" else next(iter(files))
    data = files[name][: int(frac * len(files[name]))]
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        bad = _write(d, fmt, name, data)
        good = d / "good.png"
        write_png(good, _samples()["png"][1])
        line = assert_one_line_error(run("detect", bad, good, "--out", d / "res", "-q"))
        assert bad.name in line
        assert not (d / "res").exists()


def test_codec_log_lines_stay_off_stderr(tmp_path, pair):
    """imagecodecs logs libpng's warnings ("PNG warning: IDAT: incorrect data check") before
    it raises: only the error line reaches stderr."""
    data = bytearray(pair[0].read_bytes())
    i = data.find(b"IDAT") + 200
    data[i] ^= 0x5A
    bad = tmp_path / "bad.png"
    bad.write_bytes(bytes(data))
    proc = drive("codec-warns", tmp_path / "m", "detect", bad, pair[1], "--out",
                 tmp_path / "res", "-q")
    stdout, stderr = proc.communicate(timeout=60)
    assert_one_line_error(subprocess.CompletedProcess(proc.args, proc.returncode, stdout,
                                                      stderr),
                          r"bad\.png: cannot decode PNG image")
