"""reblur.report and the ``reblur`` command line (driven as a real subprocess)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import textwrap
from html.parser import HTMLParser
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from reblur.align.field import DisplacementField
from reblur.grid import PoseGrid
from reblur.io import Image, open_image, write_geotiff, write_png
from reblur.report import (
    _FIELD_AT,
    _FIELD_SIDE,
    _KERNELS_AT,
    _PANEL_PX,
    _POSES_AT,
    OUTPUT_NAMES,
    blur_kernels,
    field_figure,
    motion_figure,
    overlay_image,
    write_report,
)
from reblur.result import ChangeResult, CropChoice, MotionEstimate

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
LEVIR256 = DATA / "levir_256" / "samples" / "A"


# ---------------------------------------------------------------------------- helpers
def run(*args, timeout: float = 120) -> subprocess.CompletedProcess:
    """Run ``python -m reblur ARGS`` and capture its output."""
    return subprocess.run([sys.executable, "-m", "reblur", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


def assert_one_line_error(res: subprocess.CompletedProcess, *patterns: str) -> str:
    assert res.returncode != 0, res.stdout
    assert "Traceback" not in res.stderr, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("reblur: error: "), lines[0]
    for p in patterns:
        assert re.search(p, lines[0]), (p, lines[0])
    assert res.stdout == ""
    return lines[0]


def read_png(path: Path) -> np.ndarray:
    a = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert a is not None, path
    return a[..., ::-1] if a.ndim == 3 else a


class _Refs(HTMLParser):
    def __init__(self):
        super().__init__()
        self.refs: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.refs += [v for k, v in attrs if k in ("src", "href") and v]


def html_refs(path: Path) -> list[str]:
    p = _Refs()
    p.feed(path.read_text())
    return p.refs


def assert_html_refs_exist(page: Path) -> list[str]:
    refs = html_refs(page)
    assert refs
    for r in refs:
        if r.startswith("data:image/png;base64,"):
            continue
        assert "://" not in r and not r.startswith("/"), r
        assert (page.parent / r).is_file(), r
    return refs


def textured(rng, h=64, w=64, bands=3) -> np.ndarray:
    a = cv2.GaussianBlur(rng.random((h, w, bands)).astype(np.float32), (0, 0), 1.5)
    a = (a - a.min()) / np.ptp(a)
    return (a * 255).astype(np.uint8)


def hand_built(H=120, W=160, *, with_reblurred=True, seed=0):
    """A ChangeResult made by hand: two change blobs (one half in the unknown strip)."""
    rng = np.random.default_rng(seed)
    obs = textured(rng, H, W)
    change = np.zeros((H, W), bool)
    change[20:40, 30:60] = True            # 600 px
    change[90:100, 0:20] = True            # overlaps the unknown strip
    unknown = np.zeros((H, W), bool)
    unknown[:, :8] = True
    grid = PoseGrid.from_ranges((H, W), t_max=3, rz_max=1.0, rz_step=0.5)
    w = np.zeros(grid.shape)
    w[2, 3, 3] = 0.6     # rz = 0, no shift
    w[3, 3, 5] = 0.4     # rz = 0.5, tx = 2
    motion = MotionEstimate(w, grid, boxes=[(10, 10, 100, 100)], info=dict(n_outer=3))
    rb = (obs.astype(np.float32) / 255.0) if with_reblurred else None
    res = ChangeResult(
        change=change, unknown=unknown, reblurred=rb, motion=motion,
        alignment=np.array([[1.0, 0, 2.5], [0, 1, -1.0], [0, 0, 1]]),
        crop=CropChoice(boxes=[(10, 10, 100, 100)], size=100, m1=0.8, threshold=0.48),
        threshold=3.5, decision=dict(statistic="z"), timings=dict(estimate=1.0, total=2.0),
    )
    return res, obs


# ---------------------------------------------------------------------------- report
def test_report_files_and_contents(tmp_path):
    res, obs = hand_built()
    truth = res.change.copy()
    truth[20:40, 30:40] = False
    files, summary = write_report(
        res, tmp_path / "out", reference=Image.from_array(obs, "ref.png"),
        observed=Image.from_array(obs, "obs.png"), truth=truth, options=dict(lam=0.1),
        timings=dict(open=0.01),
    )
    out = tmp_path / "out"
    expect = {"changes.png", "unknown.png", "reblurred.tif", "overlay.png", "motion.png",
              "report.json", "report.html", "viewer"}
    assert set(files) == expect
    assert {p.name for p in out.iterdir()} == expect  # no temp files left behind

    known_change = res.change & ~res.unknown
    ch = read_png(out / "changes.png")
    assert ch.shape == (120, 160) and ch.dtype == np.uint8
    assert set(np.unique(ch)) == {0, 255}
    np.testing.assert_array_equal(ch == 255, known_change)  # unknown -> 0
    assert not ch[90:100, :8].any()
    np.testing.assert_array_equal(read_png(out / "unknown.png") == 255, res.unknown)

    rb = tifffile.imread(out / "reblurred.tif")
    assert rb.dtype == np.uint8 and rb.shape == obs.shape
    # float [0, 1] back to the observation's dtype; no data (0, masked) where unknown
    np.testing.assert_array_equal(rb, np.where(res.unknown[:, :, None], 0, obs))

    ov = read_png(out / "overlay.png")
    assert ov.shape == (120, 160, 3)
    r, g, b = ov[30, 45].astype(int)
    assert r > g and r > b  # filled red where changed
    assert ov[60:80, :8].mean() < ov[60:80, 100:140].mean()  # unknown shaded darker
    assert read_png(out / "motion.png").shape[2] in (3, 4)

    d = json.loads((out / "report.json").read_text())
    for key in ("reblur_version", "inputs", "alignment", "crop", "motion", "threshold",
                "changes", "metrics", "timings_s", "memory", "options", "files", "notes"):
        assert key in d, key
    assert d["inputs"]["observed"]["shape"] == [120, 160, 3]
    assert d["inputs"]["observed"]["dtype"] == "uint8"
    assert d["alignment"]["H"][0][2] == 2.5
    assert d["crop"]["boxes"] == [[10, 10, 100, 100]] and d["crop"]["m1"] == 0.8
    poses = d["motion"]["nonzero_poses"]
    assert [p["weight"] for p in poses] == [0.6, 0.4]
    assert poses[1]["tx"] == 2.0 and poses[1]["rz"] == 0.5
    assert d["threshold"] == 3.5
    c = d["changes"]
    assert c["changed_px"] == int(known_change.sum())
    assert c["changed_fraction"] == pytest.approx(known_change.mean())
    assert c["unknown_px"] == 120 * 8
    assert c["n_regions"] == 2
    assert c["regions"][0]["bbox"] == [20, 30, 40, 60] and c["regions"][0]["area"] == 600
    m = d["metrics"]
    assert m["recall"] == 1.0 and m["precision"] == pytest.approx(
        (known_change & truth).sum() / known_change.sum())
    assert {"pcc", "jaccard", "yule", "f1"} <= set(m)
    assert d["timings_s"]["open"] == 0.01 and d["timings_s"]["estimate"] == 1.0
    assert "report" in d["timings_s"]
    assert d["memory"]["peak_rss_mb"] > 10
    assert d["options"] == {"lam": 0.1}
    assert d["files"]["changes.png"] == "changes.png"

    refs = assert_html_refs_exist(out / "report.html")
    assert sum(r.startswith("data:") for r in refs) == 2  # overlay and motion embedded
    assert {"changes.png", "report.json"} <= set(refs)
    page = (out / "report.html").read_text()
    assert f"{c['changed_px']:,} px" in page


def test_report_deterministic_masks(tmp_path):
    res, obs = hand_built()
    for name in ("a", "b"):
        write_report(res, tmp_path / name, observed=Image.from_array(obs, "obs.png"))
    for f in ("changes.png", "unknown.png", "overlay.png"):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f


def test_report_big_mask_tiff_and_missing_reblurred(tmp_path, monkeypatch):
    import reblur.report as rep

    monkeypatch.setattr(rep, "BIG_MASK_PIXELS", 1000)
    res, obs = hand_built(with_reblurred=False)
    files, summary = write_report(res, tmp_path, observed=Image.from_array(obs, "o.png"))
    assert "reblurred.tif" not in files and not (tmp_path / "reblurred.tif").exists()
    assert any("reblurred.tif not written" in n for n in summary["notes"])
    with tifffile.TiffFile(tmp_path / "changes.tif") as tif:
        assert tif.pages[0].is_tiled
        np.testing.assert_array_equal(tif.asarray(), read_png(tmp_path / "changes.png"))
    assert_html_refs_exist(tmp_path / "report.html")


def test_report_geotiff_outputs(tmp_path):
    rasterio = pytest.importorskip("rasterio")
    from rasterio.transform import from_origin

    res, obs = hand_built()
    geo = dict(crs=rasterio.crs.CRS.from_epsg(32631), transform=from_origin(1000.0, 2000.0, 2, 2))
    write_geotiff(tmp_path / "obs.tif", obs, geo)
    observed = open_image(tmp_path / "obs.tif")
    out = tmp_path / "out"
    files, _ = write_report(res, out, observed=observed)
    assert {"changes.tif", "changes.geojson"} <= set(files)
    with rasterio.open(out / "changes.tif") as src:
        assert src.crs.to_epsg() == 32631 and src.transform == geo["transform"]
        np.testing.assert_array_equal(src.read(1) == 255, res.change & ~res.unknown)
    with rasterio.open(out / "reblurred.tif") as src:
        assert src.crs.to_epsg() == 32631 and src.count == 3 and src.dtypes[0] == "uint8"
    gj = json.loads((out / "changes.geojson").read_text())
    assert gj["crs"]["properties"]["name"] == "urn:ogc:def:crs:EPSG::32631"
    assert len(gj["features"]) == 2
    from shapely.geometry import shape

    polys = sorted((shape(f["geometry"]) for f in gj["features"]), key=lambda p: -p.area)
    # rows 20:40, cols 30:60 -> x 1060..1120, y 2000-80..2000-40
    assert polys[0].bounds == (1060.0, 1920.0, 1120.0, 1960.0)
    assert polys[0].area == 600 * 4
    assert sum(f["properties"]["area_px"] for f in gj["features"]) == int(
        (res.change & ~res.unknown).sum())


def test_overlay_downscales_and_keeps_small_changes():
    H, W = 500, 3000
    obs = np.full((H, W), 30000, np.uint16)
    obs[:, ::7] = 40000
    change = np.zeros((H, W), bool)
    change[251, 1801] = True  # a single pixel must stay visible
    ov = overlay_image(obs, change, np.zeros((H, W), bool), max_side=256)
    s = -(-W // 256)
    assert ov.shape == (-(-H // s), -(-W // s), 3) and max(ov.shape) <= 256
    r, g, b = ov[251 // s, 1801 // s].astype(int)
    assert r > b + 50  # red fill or yellow outline, not the gray background
    assert ov[10, 10, 0] == ov[10, 10, 2]  # background stays gray


def _overlay_whole(obs, change, unknown, s):
    """The overlay drawn over the whole image at once, as written out (the reference for
    the banded drawing): block means, a 1-99 % stretch (uint8: / 255), gray to RGB, the
    unknown darkened, the changes tinted red, without the outlines."""
    h, w = -(-obs.shape[0] // s), -(-obs.shape[1] // s)
    a = np.zeros((h, w) + obs.shape[2:])
    for i in range(h):
        for j in range(w):
            a[i, j] = obs[i * s:(i + 1) * s, j * s:(j + 1) * s].astype(np.float64).mean(
                axis=(0, 1))
    a = a.astype(np.float32)
    if a.ndim == 2:
        a = a[:, :, None]
    a = a[:, :, :1] if a.shape[2] == 2 else a[:, :, :3]
    if obs.dtype == np.uint8:
        a = a / 255.0
    else:
        lo, hi = np.percentile(a, [1.0, 99.0])
        a = (a - lo) / (hi - lo)
    a = np.repeat(np.clip(a, 0.0, 1.0), 3 // a.shape[2], axis=2)
    unk = np.array([[unknown[i * s:(i + 1) * s, j * s:(j + 1) * s].mean() > 0.5
                     for j in range(w)] for i in range(h)])
    chg = np.array([[change[i * s:(i + 1) * s, j * s:(j + 1) * s].any()
                     for j in range(w)] for i in range(h)])
    a[unk] = 0.3 * a[unk] + 0.7 * np.array([0.15, 0.15, 0.25], np.float32)
    a[chg] = 0.55 * a[chg] + 0.45 * np.array([1.0, 0.0, 0.0], np.float32)
    return np.clip(np.rint(a * 255.0), 0, 255).astype(np.uint8), chg


@pytest.mark.parametrize("dtype,bands", [(np.uint16, 1), (np.uint8, 3), (np.float32, 4)])
def test_overlay_in_bands_is_the_whole_image_overlay(dtype, bands, monkeypatch):
    """The overlay is drawn a few rows at a time (``OVERLAY_BAND_ROWS``) with one stretch
    for the whole image: every pixel off the outlines equals the whole-image drawing, and
    the bands' seams do not show.  Its float temporaries stay those of a band: the traced
    peak of a 2048 px 16-bit overlay is under one whole float64 RGB copy (57 MB here; 411
    MB drawn whole, the stretch promoting the image to float64)."""
    import tracemalloc

    from reblur import report

    monkeypatch.setattr(report, "OVERLAY_BAND_ROWS", 16)
    rng = np.random.default_rng(11)
    H, W = 203, 157
    shape = (H, W) if bands == 1 else (H, W, bands)
    top = 255 if dtype == np.uint8 else 60000
    obs = (rng.random(shape) * top).astype(dtype)
    obs[:, :40] = obs[:, :40] // 3  # a dark side: the stretch is the whole image's
    change = rng.random((H, W)) < 0.002
    change[60:90, 70:120] = True
    unknown = np.zeros((H, W), bool)
    unknown[150:, :] = True
    got = overlay_image(obs, change, unknown, max_side=120)
    want, chg = _overlay_whole(obs, change, unknown, 2)
    assert got.shape == want.shape
    # the outlines are drawn (yellow) around the changes only
    near = cv2.dilate(chg.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    np.testing.assert_array_equal(got[~near], want[~near])
    assert (got[near] != want[near]).any()

    monkeypatch.setattr(report, "OVERLAY_BAND_ROWS", 128)
    big = np.full((2048, 2048), 1000, np.uint16)
    big[:, ::5] = 50000
    m = np.zeros((2048, 2048), bool)
    m[500:700, 500:900] = True
    tracemalloc.start()
    try:
        overlay_image(big, m, m)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2048 * 2048 * 3 * 8


@pytest.mark.parametrize("shape", [(23, 31), (20, 30), (23, 31, 3), (3, 7), (9, 2, 4)])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32, np.int32])
def test_block_reduce_against_a_loop_over_blocks(shape, dtype, monkeypatch):
    """The overlay's and the outlines' block reduction: the mean (float32) and the maximum
    (same dtype) of every s x s block, the partial ones at the bottom and right over their
    own pixels, checked block by block; with a working buffer of one row of blocks too."""
    from reblur import report

    rng = np.random.default_rng(7)
    a = (rng.random(shape) * 60000 - (20000 if dtype in (np.float32, np.int32) else 0))
    a = a.astype(dtype)
    for s, buffer in ((1, None), (2, None), (5, None), (2, 1), (5, 1)):
        if buffer is not None:
            monkeypatch.setattr(report, "_REDUCE_BUFFER", buffer)
        _block_reduce = report._block_reduce
        for how, fn in (("mean", np.mean), ("max", np.max)):
            got = _block_reduce(a, s, how)
            ny, nx = -(-shape[0] // s), -(-shape[1] // s)
            assert got.shape == (ny, nx) + shape[2:]
            assert got.dtype == (np.float32 if how == "mean" else a.dtype)
            for i in range(ny):
                for j in range(nx):
                    blk = a[i * s:(i + 1) * s, j * s:(j + 1) * s].astype(np.float64)
                    want = fn(blk, axis=(0, 1))
                    np.testing.assert_allclose(got[i, j], want, rtol=1e-6, atol=1e-6 * 6e4)


def test_blur_kernels_translation_and_rotation():
    grid = PoseGrid.from_ranges((201, 301), t_max=4, rz_max=2.0, rz_step=2.0)
    w = np.zeros(grid.shape)
    w[1, 4 - 1, 4 + 2] = 1.0  # rz = 0, tx = +2, ty = -1
    k, r = blur_kernels(MotionEstimate(w, grid), np.array([[10.0, 10.0], [150.0, 100.0]]))
    for ki in k:
        assert ki.sum() == pytest.approx(1.0)
        assert np.unravel_index(ki.argmax(), ki.shape) == (r - 1, r + 2)
    w[:] = 0
    w[2, 4, 4] = 0.7  # rz = +2 degrees about the centre
    w[1, 4, 4] = 0.3
    pts = np.array([[150.0, 100.0], [0.0, 0.0]])
    k, r = blur_kernels(MotionEstimate(w, grid), pts)
    assert k[0][r, r] == pytest.approx(1.0)  # the centre does not move
    assert k[1].sum() == pytest.approx(1.0) and k[1][r, r] == pytest.approx(0.3)
    # a corner moves by about radius x angle
    rad = np.hypot(150, 100) * np.deg2rad(2)
    ys, xs = np.nonzero(k[1] > 0.05)
    assert np.max(np.hypot(ys - r, xs - r)) == pytest.approx(rad, abs=1.5)


def test_motion_figure_shows_the_pose_and_its_kernel(tmp_path):
    grid = PoseGrid.from_ranges((201, 301), t_max=4, rz_max=2.0, rz_step=2.0)
    w = np.zeros(grid.shape)
    w[1, 4 - 1, 4 + 2] = 1.0  # rz = 0, tx = +2, ty = -1: one pose panel, one bright cell
    png = read_png(motion_figure(MotionEstimate(w, grid), tmp_path / "m.png")).astype(int)
    cell = _PANEL_PX / 9  # 9 x 9 translations

    def at(origin, iy, ix, size):
        return png[int(origin[1] + (iy + 0.5) * size), int(origin[0] + (ix + 0.5) * size)]

    assert at(_POSES_AT, 3, 6, cell).sum() > 3 * 180  # magma's top: near white
    assert at(_POSES_AT, 4, 4, cell).sum() < 3 * 40  # no weight: near black
    _, r = blur_kernels(MotionEstimate(w, grid), np.zeros((1, 2)))
    tap = _PANEL_PX / (2 * r + 1)
    assert at(_KERNELS_AT, r - 1, r + 2, tap).max() < 40  # the displacement (+2, -1): black
    assert at(_KERNELS_AT, r, r, tap).min() > 215  # no displacement: white


def test_field_figure_draws_the_magnitude_and_the_arrows_downwards(tmp_path):
    # 3 x 3 nodes over a 400 x 400 observation, d = (0, +1) at the centre node only:
    # observed(p) ~ reblurred(p + (0, 1)), the content is found one pixel lower: its arrow
    # points down (the other nodes do not move: no arrow)
    d = np.zeros((3, 3, 2), np.float32)
    d[1, 1, 1] = 1.0
    png = read_png(field_figure(DisplacementField(0.0, 0.0, 200.0, d), (400, 400),
                                tmp_path / "f.png")).astype(int)
    s = _FIELD_SIDE / 400
    x, y = (int(c + 200.5 * s) for c in _FIELD_AT)  # the centre node on the canvas
    white = (png.min(axis=2) > 230)
    assert white[y + 10:y + 120, x - 3:x + 4].sum() > 50  # the arrow, below its node
    assert white[y - 120:y - 10, x - 3:x + 4].sum() == 0
    x0, y0 = _FIELD_AT
    r, g, b = png[y0 + 2, x0 + 2]  # node (0, 0): magnitude 0, viridis' dark purple
    assert b > g and r < 100
    r, g, b = png[y - 6, x + 6]  # next to the centre node, magnitude ~1: viridis' yellow
    assert r > 200 and g > 200 and b < 100


# ---------------------------------------------------------------------------- CLI: errors
@pytest.fixture
def good_pair(tmp_path):
    rng = np.random.default_rng(3)
    write_png(tmp_path / "ref.png", textured(rng))
    write_png(tmp_path / "obs.png", textured(rng))
    return tmp_path / "ref.png", tmp_path / "obs.png"


def _bad_inputs(tmp_path: Path, kind: str) -> tuple[Path, list[str]]:
    """Write a bad reference of ``kind``; return it and the error patterns to expect."""
    rng = np.random.default_rng(1)
    p = tmp_path / f"bad_{kind}.png"
    if kind == "missing":
        return tmp_path / "missing.png", [r"missing\.png: no such file"]
    if kind == "not_image":
        p.write_text("this is not an image\n" * 20)
        return p, ["not an image"]
    if kind == "truncated":
        data = cv2.imencode(".png", textured(rng))[1].tobytes()
        p.write_bytes(data[: len(data) // 2])
        return p, ["truncated"]
    if kind == "one_pixel":
        write_png(p, np.zeros((1, 1), np.uint8))
        return p, [r"1x1 pixels; at least 32x32"]
    if kind == "zero_size":
        p = p.with_suffix(".tif")
        with pytest.warns(UserWarning):
            tifffile.imwrite(p, np.zeros((0, 0), np.uint8))
        return p, ["image is empty"]
    if kind == "bands":
        p = p.with_suffix(".tif")
        tifffile.imwrite(p, (rng.random((64, 64, 5)) * 200).astype(np.uint8),
                         photometric="minisblack", planarconfig="contig")
        return p, [r"5 bands .* 3: band counts cannot be reconciled"]
    if kind == "nan":
        p = p.with_suffix(".tif")
        f = rng.random((64, 64)).astype(np.float32)
        f[40, 12] = np.nan
        tifffile.imwrite(p, f)
        return p, [r"NaN pixels \(first at row 40, column 12\)"]
    if kind == "inf":
        p = p.with_suffix(".tif")
        f = rng.random((64, 64, 3)).astype(np.float32)
        f[3, 5, 1] = -np.inf
        tifffile.imwrite(p, f, photometric="rgb")
        return p, [r"Inf pixels"]
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["missing", "not_image", "truncated", "one_pixel",
                                  "zero_size", "bands", "nan", "inf"])
def test_detect_bad_reference(tmp_path, good_pair, kind):
    bad, patterns = _bad_inputs(tmp_path, kind)
    out = tmp_path / "res"
    res = run("detect", bad, good_pair[1], "--out", out)
    line = assert_one_line_error(res, *patterns)
    assert bad.name in line
    assert not out.exists()


def test_detect_bad_observed_and_truth(tmp_path, good_pair):
    bad, _ = _bad_inputs(tmp_path, "truncated")
    out = tmp_path / "res"
    assert_one_line_error(run("detect", good_pair[0], bad, "--out", out), "truncated")
    write_png(tmp_path / "truth.png", np.zeros((50, 64), np.uint8))
    assert_one_line_error(
        run("detect", *good_pair, "--truth", tmp_path / "truth.png", "--out", out),
        r"truth mask is 64x50 pixels",
    )
    assert not out.exists()


def test_detect_max_pixels(tmp_path, good_pair):
    out = tmp_path / "res"
    res = run("detect", *good_pair, "--out", out, "--max-pixels", 4000)
    assert_one_line_error(res, r"ref\.png: image has 4,096 pixels .* limit of 4,000")
    assert not out.exists()


def test_detect_textureless(tmp_path):
    write_png(tmp_path / "a.png", np.full((64, 64), 128, np.uint8))
    write_png(tmp_path / "b.png", np.full((64, 64), 128, np.uint8))
    out = tmp_path / "res"
    res = run("detect", tmp_path / "a.png", tmp_path / "b.png", "--out", out, "-q")
    assert_one_line_error(res, r"textureless|cannot be estimated|constant")
    assert not out.exists()


def test_output_dir_not_writable(tmp_path, good_pair):
    (tmp_path / "afile").write_text("x")
    res = run("detect", *good_pair, "--out", tmp_path / "afile" / "sub")
    assert_one_line_error(res, "cannot create the output directory")
    res = run("detect", *good_pair, "--out", tmp_path / "afile")
    assert_one_line_error(res, "exists and is not a directory")
    assert (tmp_path / "afile").read_text() == "x"
    # /proc refuses new directories even to root
    res = run("detect", *good_pair, "--out", "/proc/reblur-test-out")
    assert_one_line_error(res, "cannot create the output directory")


def test_output_dir_clashes_with_inputs(tmp_path, good_pair):
    ref, obs = good_pair
    res = run("detect", ref, obs, "--out", ref)
    assert_one_line_error(res, r"is \(inside\) the input")
    d = tmp_path / "res"
    d.mkdir()
    write_png(d / "changes.png", textured(np.random.default_rng(0)))
    before = (d / "changes.png").read_bytes()
    for extra in ([], ["--overwrite"]):
        res = run("detect", d / "changes.png", obs, "--out", d, *extra)
        assert_one_line_error(res, "would overwrite the input")
    assert (d / "changes.png").read_bytes() == before
    assert [p.name for p in d.iterdir()] == ["changes.png"]


def test_output_dir_refuses_inputs_inside_its_output_folders(tmp_path, good_pair):
    """An input inside OUT/viewer/ (detect), or inside an output of an observation's
    sub-folder (detect REF OBS OBS ...), would be deleted by --overwrite."""
    ref, obs = good_pair
    d = tmp_path / "res"
    (d / "viewer").mkdir(parents=True)
    (d / "a" / "viewer").mkdir(parents=True)
    inside = d / "viewer" / "obs.png"
    deeper = d / "a" / "viewer" / "obs.png"
    for p in (inside, deeper):
        p.write_bytes(obs.read_bytes())
    for extra in ([], ["--overwrite"]):
        res = run("detect", ref, inside, "--out", d, *extra)
        assert_one_line_error(res, "would overwrite the input")
        res = run("detect", ref, obs, deeper, "--out", d, *extra)
        assert_one_line_error(res, "would overwrite the input")
    assert inside.read_bytes() == deeper.read_bytes() == obs.read_bytes()
    assert sorted(p.relative_to(d).as_posix() for p in d.rglob("*")) == [
        "a", "a/viewer", "a/viewer/obs.png", "viewer", "viewer/obs.png"]


def test_output_dir_holds_results(tmp_path, good_pair):
    d = tmp_path / "res"
    d.mkdir()
    (d / "report.json").write_text("{}")
    res = run("detect", *good_pair, "--out", d)
    assert_one_line_error(res, r"already holds results \(report\.json\); use --overwrite")
    assert (d / "report.json").read_text() == "{}"
    assert [p.name for p in d.iterdir()] == ["report.json"]


def test_usage_error_and_verbose_traceback(tmp_path, good_pair):
    res = run("detect", good_pair[0], "--out", tmp_path / "x")
    assert res.returncode == 2
    assert_one_line_error(res, "Missing argument 'OBSERVED")
    res = run("detect", tmp_path / "nope.png", good_pair[1], "--out", tmp_path / "x", "-v")
    assert res.returncode == 1
    assert "Traceback" in res.stderr
    assert res.stderr.strip().splitlines()[-1].startswith("reblur: error: ")


# ---------------------------------------------------------------------------- CLI: alignment
def _invoke(*args):
    from click.testing import CliRunner

    from reblur.cli import main

    return CliRunner().invoke(main, [str(a) for a in args], prog_name="reblur")


class _Called(Exception):
    """Raised by a stand-in for detect_changes: the CLI got that far."""


def _spy_detect(monkeypatch) -> dict:
    """Replace reblur.detect_changes by a spy that records its keywords and stops."""
    import reblur

    seen: dict = {}

    def spy(*a, **k):
        seen.update(k)
        raise _Called

    monkeypatch.setattr(reblur, "detect_changes", spy)
    return seen


def test_detect_no_align_no_refine(tmp_path, good_pair, monkeypatch):
    """--no-align, --no-refine and --no-field reach the library as align=False,
    refine=False, local_field=False."""
    seen = _spy_detect(monkeypatch)
    res = _invoke("detect", *good_pair, "--out", tmp_path / "res", "-q")
    assert res.exit_code == 1 and "_Called" in res.output, res.output
    assert seen["align"] is True and seen["refine"] is True and seen["align_hint"] is None
    assert seen["local_field"] is True
    res = _invoke("detect", *good_pair, "--out", tmp_path / "res", "--no-align", "--no-refine",
                  "--no-field", "-q")
    assert res.exit_code == 1 and "_Called" in res.output, res.output
    assert seen["align"] is False and seen["refine"] is False and seen["align_hint"] is None
    assert seen["local_field"] is False


def test_detect_workers_default_to_the_usable_cpus(tmp_path, good_pair, monkeypatch):
    """Without --workers the tiles run on the CPUs this process may use (its affinity
    mask), at most 4; --workers N is passed on as given."""
    seen = _spy_detect(monkeypatch)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2}, raising=False)
    res = _invoke("detect", *good_pair, "--out", tmp_path / "res", "-q")
    assert res.exit_code == 1 and "_Called" in res.output, res.output
    assert seen["workers"] == 3
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(64)), raising=False)
    res = _invoke("detect", *good_pair, "--out", tmp_path / "res", "-q")
    assert seen["workers"] == 4
    res = _invoke("detect", *good_pair, "--out", tmp_path / "res", "--workers", "7", "-q")
    assert res.exit_code == 1 and "_Called" in res.output, res.output
    assert seen["workers"] == 7


@pytest.mark.parametrize("text", [
    "1 0 12.5\n0 1 -3\n0 0 1\n",
    "# a rough guess\n2, 0, 25,  0, 2, -6,  0, 0, 2  # row by row\n",
    json.dumps({"H": [[1, 0, 12.5], [0, 1, -3], [0, 0, 1]]}),
    json.dumps([1, 0, 12.5, 0, 1, -3, 0, 0, 1]),
])
def test_align_hint_file_reaches_the_library(tmp_path, good_pair, monkeypatch, text):
    """Text or JSON, nested or flat, any scale: the normalised homography."""
    seen = _spy_detect(monkeypatch)
    hint = tmp_path / "hint.txt"
    hint.write_text(text)
    res = _invoke("detect", *good_pair, "--out", tmp_path / "res", "--align-hint", hint, "-q")
    assert res.exit_code == 1 and "_Called" in res.output, res.output
    assert seen["align"] is True
    np.testing.assert_array_equal(seen["align_hint"], [[1, 0, 12.5], [0, 1, -3], [0, 0, 1]])


@pytest.mark.parametrize(("content", "pattern"), [
    (None, r"hint\.txt: no such file"),
    (b"\xff\xfe\x00\x01binary", r"hint\.txt: not a text file"),
    ("1 0 0\n0 1 0\n", r"hint\.txt: 6 numbers, expected 9 \(a 3x3 reference -> observation"),
    ("1 0 0 0 1 0 0 0 1 5", r"10 numbers, expected 9"),
    ("one two three", r"not a list of numbers"),
    ('{"H": [[1, 0], [0, 1, 0], [0, 0, 1]]}', r"not a list of numbers"),
    ("1 0 nan 0 1 0 0 0 1", r"non-finite"),
    ("[[1, 2, 0], [2, 4, 0], [0, 0, 1]]", r"singular \(not invertible\)"),
    ("1 0 0 0 1 0 0 0 0", r"singular"),
])
def test_align_hint_file_is_checked(tmp_path, content, pattern):
    """A bad --align-hint file is refused while the options are read (the inputs do not
    even exist): usage error 2, one line naming the file and what it must hold."""
    hint = tmp_path / "hint.txt"
    if isinstance(content, bytes):
        hint.write_bytes(content)
    elif content is not None:
        hint.write_text(content)
    res = _invoke("detect", tmp_path / "nope.png", tmp_path / "nope2.png", "--out",
                  tmp_path / "res", "--align-hint", hint)
    assert res.exit_code == 2, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1, res.output
    assert lines[0].startswith("reblur: error: Invalid value for '--align-hint': "), lines[0]
    assert re.search(pattern, lines[0]), lines[0]
    assert not (tmp_path / "res").exists()


def test_no_align_with_align_hint_is_a_usage_error(tmp_path, good_pair):
    hint = tmp_path / "hint.txt"
    hint.write_text("1 0 0 0 1 0 0 0 1")
    res = _invoke("detect", *good_pair, "--out", tmp_path / "res", "--no-align",
                  "--align-hint", hint)
    assert res.exit_code == 2, res.output
    assert re.fullmatch(r"reblur: error: --align-hint seeds the alignment that --no-align "
                        r"skips: give one of them \(see 'reblur detect --help'\)\n",
                        res.output), res.output
    assert not (tmp_path / "res").exists()


def test_help_lists_commands():
    from click.testing import CliRunner

    from reblur.cli import main

    runner = CliRunner()
    res = runner.invoke(main, ["--help"])
    assert res.exit_code == 0
    for cmd in ("detect", "demo", "simulate", "evaluate"):
        assert cmd in res.output
    res = runner.invoke(main, ["detect", "--help"])
    assert res.exit_code == 0
    for opt in ("--t-max", "--rz-max", "--rz-step", "--lam", "--tile-size", "--threshold",
                "--truth", "--max-pixels", "--workers", "--overwrite", "--quiet", "--verbose",
                "--no-align", "--no-refine", "--align-hint", "--no-field"):
        assert opt in res.output
    assert runner.invoke(main, ["--version"]).output.startswith("reblur, version")
    res = runner.invoke(main, ["evaluate", "a.png"])
    assert res.exit_code == 2 and "reblur: error: Missing argument 'TRUTH'" in res.output


# ---------------------------------------------------------------------------- CLI: evaluate
def test_evaluate(tmp_path):
    t = np.zeros((40, 50), np.uint8)
    p = np.zeros((40, 50), np.uint8)
    t[0:10, 0:10] = 255          # 100 true
    p[5:10, 0:20] = 255          # 100 predicted, 50 of them right
    u = np.zeros((40, 50), np.uint8)
    u[39, :] = 255               # ignored row (50 px)
    for name, a in (("t.png", t), ("p.png", p), ("u.png", u)):
        write_png(tmp_path / name, a)
    res = run("evaluate", tmp_path / "p.png", tmp_path / "t.png", "--unknown", tmp_path / "u.png")
    assert res.returncode == 0, res.stderr
    d = json.loads(res.stdout)
    tp, fp, fn = 50, 50, 50
    tn = 40 * 50 - 50 - tp - fp - fn
    assert d["pcc"] == pytest.approx((tp + tn) / (tp + tn + fp + fn))
    assert d["jaccard"] == pytest.approx(tp / (tp + fp + fn))
    assert d["yule"] == pytest.approx(abs(tp / (tp + fp) + tn / (tn + fn) - 1))
    assert d["precision"] == pytest.approx(0.5) and d["recall"] == pytest.approx(0.5)
    assert d["f1"] == pytest.approx(0.5)
    write_png(tmp_path / "small.png", np.zeros((40, 40), np.uint8))
    assert_one_line_error(run("evaluate", tmp_path / "p.png", tmp_path / "small.png"),
                          r"truth mask is 40x40 pixels, the image it describes is 50x40")


# ---------------------------------------------------------------------------- CLI: end to end
@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """A 256x256 pair from a real LEVIR image, made by ``reblur simulate``."""
    src = sorted(LEVIR256.glob("*.png"))
    if not src:
        pytest.skip(f"real test imagery missing: {LEVIR256}")
    d = tmp_path_factory.mktemp("sim")
    res = run("simulate", src[0], "--out", d / "pair", "--seed", 1, "--t-max", 3,
              "--rz-max", 0.5, "--changes", 3)
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith("simulated 256x256 pair")
    return d, src[0]


def test_simulate_outputs(sim, tmp_path):
    d, src = sim
    pair = d / "pair"
    assert sorted(p.name for p in pair.iterdir()) == sorted(
        ["reference.tif", "observed.tif", "truth.png", "unknown.png", "path.json"])
    ref, obs = tifffile.imread(pair / "reference.tif"), tifffile.imread(pair / "observed.tif")
    assert ref.dtype == obs.dtype == np.float32 and ref.shape == obs.shape == (256, 256, 3)
    assert 0 <= obs.min() and obs.max() <= 1
    src_img = read_png(src)
    np.testing.assert_allclose(ref, src_img / 255.0, atol=1e-6)  # reference not quantised
    truth = read_png(pair / "truth.png")
    assert truth.shape == (256, 256) and set(np.unique(truth)) <= {0, 255} and truth.any()
    meta = json.loads((pair / "path.json").read_text())
    assert meta["options"]["seed"] == 1 and np.shape(meta["viewpoint"]) == (3, 3)
    assert "poses" in meta["path"]
    # same seed -> same pair; existing results refused without --overwrite
    res = run("simulate", src, "--out", pair, "--seed", 1)
    assert_one_line_error(res, "already holds results")
    res = run("simulate", src, "--out", tmp_path / "again", "--seed", 1, "--t-max", 3,
              "--rz-max", 0.5, "--changes", 3)
    assert res.returncode == 0, res.stderr
    np.testing.assert_array_equal(tifffile.imread(tmp_path / "again" / "observed.tif"), obs)


@pytest.fixture(scope="module")
def detected(sim):
    """Detect on the simulated pair: reference as uint8 PNG, observation as uint8 GeoTIFF."""
    rasterio = pytest.importorskip("rasterio")
    from rasterio.transform import from_origin

    d, _ = sim
    ref = np.rint(tifffile.imread(d / "pair" / "reference.tif") * 255).astype(np.uint8)
    obs = np.rint(tifffile.imread(d / "pair" / "observed.tif") * 255).astype(np.uint8)
    write_png(d / "ref.png", ref)
    geo = dict(crs=rasterio.crs.CRS.from_epsg(32650), transform=from_origin(4e5, 3e6, 0.5, 0.5))
    write_geotiff(d / "obs.tif", obs, geo)
    out = d / "run1"
    args = ["detect", d / "ref.png", d / "obs.tif", "--truth", d / "pair" / "truth.png",
            "--t-max", 5, "--rz-max", 1, "--rz-step", 0.5]
    res = run(*args, "--out", out)
    assert res.returncode == 0, res.stderr
    return d, out, args, res, obs


def test_report_peak_memory_is_the_runs_own_not_its_parents(detected, tmp_path):
    """``report.json``'s ``peak_rss_mb`` is the run's own high-water mark.  Started from a
    process holding more than twice that (touched pages), it reported the parent's size:
    ``ru_maxrss`` survives ``exec``."""
    d, out, args, _, _ = detected
    own = json.loads((out / "report.json").read_text())["memory"]["peak_rss_mb"]
    held = int(2 * own + 200)  # MB
    code = (f"import subprocess, sys, numpy as np; a = np.ones({held * 2**20 // 8}); "
            "r = subprocess.run([sys.executable, '-m', 'reblur', *sys.argv[1:]]); "
            "sys.exit(r.returncode)")
    big = tmp_path / "from_a_large_parent"
    res = subprocess.run([sys.executable, "-c", code, *map(str, args), "--out", str(big), "-q"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    got = json.loads((big / "report.json").read_text())["memory"]["peak_rss_mb"]
    assert got < held
    assert got == pytest.approx(own, rel=0.3)


def test_detect_end_to_end(detected):
    d, out, _, res, obs = detected
    line = res.stdout.strip()
    assert len(res.stdout.strip().splitlines()) == 1
    m = re.fullmatch(r"changes: ([\d.]+) % of 0\.1 MP in (\d+) regions? \(JC [\d.]+, YC [\d.]+\) "
                     r"-> (.+)", line)
    assert m, line
    assert Path(m.group(3)) == out / "overlay.png"
    names = {p.name for p in out.iterdir()}
    from reblur.gis import geopackage_available

    assert names == {"changes.png", "changes.tif", "changes.geojson", "unknown.png",
                     "unknown.tif", "reblurred.tif", "overlay.png", "motion.png",
                     "report.json", "report.html", "viewer"} | (
                         {"changes.gpkg"} if geopackage_available() else set())
    ch = read_png(out / "changes.png")
    assert ch.shape == (256, 256) and set(np.unique(ch)) <= {0, 255}
    unk = read_png(out / "unknown.png")
    assert not (ch.astype(bool) & unk.astype(bool)).any()
    rep = json.loads((out / "report.json").read_text())
    assert rep["changes"]["changed_px"] == int((ch == 255).sum())
    assert float(m.group(1)) == pytest.approx(100 * rep["changes"]["changed_fraction"], abs=0.01)
    assert rep["changes"]["n_regions"] == int(m.group(2))
    assert rep["inputs"]["observed"]["geo"]["crs"] == "EPSG:32650"
    assert rep["options"]["t_max"] == 5 and rep["motion"]["grid"]["tx"][-1] == 5
    assert rep["motion"]["nonzero_poses"] and rep["metrics"]["jaccard"] is not None
    assert rep["metrics"]["recall"] > 0.3  # the pasted objects are found
    assert {"align", "estimate", "open", "report"} <= set(rep["timings_s"])
    rb = tifffile.imread(out / "reblurred.tif")
    assert rb.dtype == np.uint8 and rb.shape == obs.shape
    known = ~unk.astype(bool) & ~ch.astype(bool)
    err = np.abs(rb.astype(float) - obs.astype(float))[known].mean()
    assert err < 10, err  # reblurred reference matches the observation where unchanged
    gj = json.loads((out / "changes.geojson").read_text())
    assert gj["crs"]["properties"]["name"].endswith("32650")
    if gj["features"]:
        x0, y0, x1, y1 = gj["features"][0]["geometry"]["coordinates"][0][0] * 2
        assert 4e5 <= x0 <= 4e5 + 128 and 3e6 - 128 <= y0 <= 3e6
    assert_html_refs_exist(out / "report.html")


#: Runs ``reblur detect`` with a finder first on ``sys.meta_path`` that records every module
#: imported off the main thread, the masks held back 1 s so that the report's picture and
#: viewer threads start their work first.
_OFF_MAIN_IMPORTS = textwrap.dedent("""
    import sys, threading, time
    seen = []
    class Recorder:
        def find_spec(self, name, path=None, target=None):
            if threading.current_thread() is not threading.main_thread():
                seen.append(name)
            return None
    sys.meta_path.insert(0, Recorder())
    import reblur.report as report
    from reblur.cli import main
    masks = report._write_masks
    def later(*args, **kwargs):
        time.sleep(1.0)
        return masks(*args, **kwargs)
    report._write_masks = later
    main(sys.argv[1:], standalone_mode=False)
    print("imported off the main thread:", sorted(set(seen)))
    print("matplotlib imported:", "matplotlib" in sys.modules)
""")


def test_no_module_is_first_imported_on_a_worker_thread(detected, tmp_path):
    """Two threads importing one package at once can meet it half initialised (a CI run:
    "cannot import name 'BaseGeometry' from partially initialized module
    'shapely.geometry.base'", the viewer's outlines and the GeoJSON polygons importing
    shapely together).  No thread of a run but the main one imports a module: every
    module the tile threads and the report's writer threads use is loaded before they
    start, here with the writer threads given a second's head start on the georeferenced
    pair (GeoJSON polygons and the viewer's outlines both written).  Nor is matplotlib
    (0.3 s) imported by a run that draws no ``rolling.png``."""
    d, _, args, _, _ = detected
    res = subprocess.run(
        [sys.executable, "-c", _OFF_MAIN_IMPORTS, *map(str, args), "--out",
         str(tmp_path / "out"), "-q"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "imported off the main thread: []" in res.stdout, res.stdout
    assert (tmp_path / "out" / "changes.geojson").exists()
    assert not (tmp_path / "out" / "rolling.png").exists()
    assert "matplotlib imported: False" in res.stdout, res.stdout


def test_detect_rerun_is_byte_identical_and_overwrite(detected):
    d, out, args, _, _ = detected
    first = (out / "changes.png").read_bytes()
    res = run(*args, "--out", out)
    assert_one_line_error(res, "already holds results")
    # an older run's set: its report lists a rolling.png this (global shutter) run does
    # not write
    (out / "rolling.png").write_text("stale result of an older, rolling-shutter run")
    rep = json.loads((out / "report.json").read_text())
    rep["files"]["rolling.png"] = "rolling.png"
    (out / "report.json").write_text(json.dumps(rep))
    res = run(*args, "--out", out, "--overwrite", "-q")
    assert res.returncode == 0, res.stderr
    assert (out / "changes.png").read_bytes() == first
    assert not (out / "rolling.png").exists()  # stale output removed
    assert not [p for p in out.iterdir() if p.name not in OUTPUT_NAMES]


@pytest.mark.slow
def test_demo(tmp_path):
    from reblur.data import demo_paths

    if not demo_paths()["reference"].exists():
        pytest.skip("demo data not shipped yet")
    out = tmp_path / "demo"
    res = run("demo", "--out", out, "-q", timeout=300)
    assert res.returncode == 0, res.stderr
    assert f"-> {out / 'overlay.png'}" in res.stdout
    assert (out / "overlay.png").is_file()
    rep = json.loads((out / "report.json").read_text())
    assert rep["metrics"] is not None and rep["options"]["command"] == "demo"


def test_only_the_command_exits_without_collecting():
    """At the exit of a process that ran ``reblur.cli.run`` (the console script), every
    object is frozen out of the collector, so the interpreter's last collections skip them;
    after ``main`` in a host's process nothing is.  Seen at the very end, by an exit
    handler registered first (exit handlers run last-registered first); the outputs of a
    real run are complete before it (the demo, by the command)."""
    code = textwrap.dedent("""
        import atexit, gc, sys
        atexit.register(lambda: print("frozen", gc.get_freeze_count() > 0))
        from reblur import cli
        try:
            getattr(cli, sys.argv[1])(sys.argv[2:])
        except SystemExit:
            pass
        print("before exit", gc.get_freeze_count() > 0)
    """)
    for how, want in (("run", True), ("main", False)):
        r = subprocess.run([sys.executable, "-c", code, how, "--version"],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        assert r.stdout.splitlines()[-2:] == ["before exit False", f"frozen {want}"]


def test_only_the_command_entry_point_changes_the_allocator(monkeypatch):
    """``reblur.cli.run`` (the console script, ``python -m reblur``) keeps freed memory in
    its own process; ``main`` called inside a host's process (CliRunner here, a test, a
    notebook) leaves the host's allocator alone."""
    from click.testing import CliRunner

    from reblur import cli

    calls = []
    monkeypatch.setattr(cli, "retain_freed_memory", lambda: calls.append(1) or True)
    r = CliRunner().invoke(cli.main, ["--version"])
    assert r.exit_code == 0 and calls == []
    with pytest.raises(SystemExit) as exc:
        cli.run(["--version"])
    assert exc.value.code == 0 and calls == [1]
