"""reblur.viewer: Deep Zoom pyramids built from windows, region outlines, and the page in a
headless Chromium."""

from __future__ import annotations

import base64
import contextlib
import fcntl
import functools
import http.server
import json
import os
import re
import select
import shutil
import subprocess
import tempfile
import threading
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy import ndimage
from test_cli import assert_html_refs_exist, hand_built, textured

from reblur.io import Image, write_tiff
from reblur.outdir import output_set
from reblur.report import write_report
from reblur.viewer import ViewerOptions, build_pyramids, write_viewer
from reblur.viewer.layers import Stretch, image_layer, mask_layer, sample_stretch
from reblur.viewer.outlines import region_outline
from reblur.viewer.pyramid import DziLayout

ROOT = Path(__file__).resolve().parents[1]
EIGHT = np.ones((3, 3), bool)  # 8-connectivity for ndimage.label


# ---------------------------------------------------------------------------- helpers
class Recorder:
    """A lazy array-like that records every window read from it."""

    def __init__(self, array: np.ndarray):
        self.array = array
        self.shape, self.dtype, self.ndim = array.shape, array.dtype, array.ndim
        self.reads: list[tuple[int, int]] = []
        self.count = np.zeros(array.shape[:2], np.int32)

    def __getitem__(self, key):
        out = self.array[key]
        ys, xs = key if isinstance(key, tuple) else (key, slice(None))
        ys, xs = slice(*ys.indices(self.shape[0])), slice(*xs.indices(self.shape[1]))
        self.reads.append((ys.stop - ys.start, xs.stop - xs.start))
        self.count[ys, xs] += 1
        return np.array(out)

    def largest(self) -> int:
        return max(h * w for h, w in self.reads)


def read_level(root: Path, name: str, level: int) -> np.ndarray:
    """Assemble one level of a DZI pyramid from its tile files."""
    info = ET.parse(root / f"{name}.dzi").getroot()
    size = info.find("{*}Size")
    lay = DziLayout(int(size.get("Width")), int(size.get("Height")), int(info.get("TileSize")))
    rows, cols = lay.grid(level)
    h, w = lay.size(level)
    T = lay.tile_size
    out = None
    for r in range(rows):
        for c in range(cols):
            p = root / f"{name}_files" / str(level) / f"{c}_{r}.{info.get('Format')}"
            t = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            assert t is not None, p
            t = t[..., ::-1] if t.ndim == 3 and t.shape[2] == 3 else t
            t = t[..., [2, 1, 0, 3]] if t.ndim == 3 and t.shape[2] == 4 else t
            if out is None:
                out = np.zeros((h, w) + t.shape[2:], t.dtype)
            assert t.shape[:2] == (min(T, h - r * T), min(T, w - c * T)), (level, r, c)
            out[r * T:r * T + t.shape[0], c * T:c * T + t.shape[1]] = t
    return out


def block_mean(a: np.ndarray, s: int) -> np.ndarray:
    """Mean over full ``s x s`` blocks (the reference for the coarser levels)."""
    h, w = a.shape[0] // s, a.shape[1] // s
    b = a[:h * s, :w * s].astype(np.float64)
    return b.reshape(h, s, w, s, *a.shape[2:]).mean(axis=(1, 3))


# ---------------------------------------------------------------------------- pyramid
def test_pyramids_built_by_threads_equal_the_serial_build(tmp_path):
    # leaves are built side by side; the files must be those of the one-thread build
    rng = np.random.default_rng(3)
    img = textured(rng, 300, 420)
    m = np.zeros(img.shape[:2], bool)
    m[40:90, 100:260] = True

    def layers():
        return [image_layer("img", img, sample_stretch(img, img.dtype), fmt="jpg"),
                mask_layer("m", m, (255, 0, 0), alpha=0.8, reduce="max")]

    def files(root):
        return {p.relative_to(root): p.read_bytes() for p in root.rglob("*") if p.is_file()}

    one = build_pyramids(tmp_path / "one", layers(), img.shape[:2], tile_size=32, block=64,
                         workers=1)
    many = build_pyramids(tmp_path / "many", layers(), img.shape[:2], tile_size=32, block=64,
                          workers=3)
    assert one == many
    a, b = files(tmp_path / "one"), files(tmp_path / "many")
    assert len(a) == 2 * one.n_tiles() + 2  # every tile of both layers, and two .dzi
    assert a == b
    with pytest.raises(ValueError, match="workers"):
        build_pyramids(tmp_path / "bad", layers(), img.shape[:2], tile_size=32, workers=0)
    assert not (tmp_path / "bad").exists()


def test_uint8_windows_give_the_tiles_of_their_float32_copies(tmp_path):
    """8-bit images and masks are read, encoded and halved in uint8 at full size: every
    tile file equals the one made from float32 copies of the same windows (the reference),
    gray and RGB, masks with partial opacity and both reductions; each side one more than
    a multiple of the block, so the corner leaf is a single pixel."""
    from dataclasses import replace

    rng = np.random.default_rng(11)
    rgb = textured(rng, 193, 321)
    gray = textured(rng, 193, 321)[:, :, 0]
    m = rng.random(gray.shape) < 0.02
    m[50:120, 90:200] = True
    m[-1, -1] = True

    def layers():
        st = Stretch(0.0, 255.0)
        return [image_layer("rgb", rgb, st, fmt="jpg"), image_layer("gray", gray, st, fmt="png"),
                mask_layer("chg", m, (255, 40, 40), alpha=0.45, reduce="max"),
                mask_layer("unk", m, (30, 30, 70), alpha=0.75, reduce="mean")]

    def as_float(layer):
        return replace(layer, read=lambda ys, xs, r=layer.read: np.asarray(
            r(ys, xs), dtype=np.float32))

    native = layers()
    assert all(np.asarray(lay.read(slice(0, 9), slice(0, 9))).dtype == np.uint8 for lay in native)

    def files(root):
        return {p.relative_to(root): p.read_bytes() for p in root.rglob("*") if p.is_file()}

    build_pyramids(tmp_path / "u8", native, gray.shape, tile_size=32, block=64)
    build_pyramids(tmp_path / "f32", [as_float(lay) for lay in layers()], gray.shape,
                   tile_size=32, block=64)
    a, b = files(tmp_path / "u8"), files(tmp_path / "f32")
    assert len(a) > 4 * 20 and a == b


def test_pyramid_levels_are_block_means_of_the_full_size(tmp_path):
    rng = np.random.default_rng(0)
    img = textured(rng, 200, 300)  # uint8: displayed as it is
    layer = image_layer("img", img, sample_stretch(img, img.dtype), fmt="png")
    lay = build_pyramids(tmp_path, [layer], img.shape[:2], tile_size=64, block=128)
    assert lay.max_level == 9  # ceil(log2(300))
    levels = sorted(int(p.name) for p in (tmp_path / "img_files").iterdir())
    assert levels == list(range(10))
    np.testing.assert_array_equal(read_level(tmp_path, "img", 9), img)  # base: full size
    top = list((tmp_path / "img_files" / "0").iterdir())
    assert len(top) == 1 and cv2.imread(str(top[0])).shape[:2] == (1, 1)
    for level in (8, 6, 4):
        s = 2 ** (9 - level)
        got = read_level(tmp_path, "img", level).astype(np.float64)
        ref = block_mean(img, s)  # full blocks only (the last row/column may be partial)
        assert got.shape[:2] == (-(-200 // s), -(-300 // s))
        assert np.abs(got[:ref.shape[0], :ref.shape[1]] - ref).max() <= 1.0, level


def test_colour_tiles_keep_their_channel_order(tmp_path):
    # a red-green-blue striped RGB image: its JPEG and PNG tiles decode (read_level: OpenCV's
    # BGR swapped back) to the same stripes; a swapped order would put blue where red is
    img = np.zeros((64, 96, 3), np.uint8)
    img[:, :32, 0] = 250
    img[:, 32:64, 1] = 250
    img[:, 64:, 2] = 250
    for fmt in ("jpg", "png"):
        layer = image_layer(fmt, img, sample_stretch(img, img.dtype), fmt=fmt)
        lay = build_pyramids(tmp_path, [layer], img.shape[:2], tile_size=64, block=128)
        got = read_level(tmp_path, fmt, lay.max_level).astype(int)
        assert np.abs(got - img).max() <= (8 if fmt == "jpg" else 0), fmt


def test_sample_stretch_is_the_percentiles_of_its_windows_whatever_the_type():
    # an image smaller than one window is sampled whole: its 1st and 99th percentiles in
    # float64, computed here directly; integer samples kept in their type must agree
    rng = np.random.default_rng(5)
    rgb16 = rng.integers(0, 65536, (90, 110, 3)).astype(np.uint16)
    gray = rng.integers(-32768, 32768, (100, 70)).astype(np.int16)
    wide = rng.integers(0, 2**32, (60, 50, 3), dtype=np.uint64).astype(np.uint32)
    for img in (rgb16, gray, wide):
        lo, hi = np.percentile(img.astype(np.float64), [1.0, 99.0])
        s = sample_stretch(img, img.dtype)
        assert (s.lo, s.hi) == (lo, hi)
    fl = rng.normal(size=(80, 80)).astype(np.float32)
    fl[::7, ::5] = np.nan  # no data: left out
    s = sample_stretch(fl, fl.dtype)
    lo, hi = np.percentile(fl[np.isfinite(fl)].astype(np.float64), [1.0, 99.0])
    assert (s.lo, s.hi) == (lo, hi)
    # a larger image: 2 x 2 windows of 40 px at its corners
    big = rng.integers(0, 4096, (100, 130)).astype(np.uint16)
    wins = [big[y:y + 40, x:x + 40] for y in (0, 60) for x in (0, 90)]
    lo, hi = np.percentile(np.concatenate([w.ravel() for w in wins]).astype(float), [1, 99])
    s = sample_stretch(big, big.dtype, n=2, side=40)
    assert (s.lo, s.hi) == (lo, hi)


def test_stretch_clips_and_shows_no_data_as_black():
    # the linear map written out in float64, then clipped; NaN (no data) is black and
    # infinities clip like any large value
    rng = np.random.default_rng(11)
    a = rng.normal(500.0, 300.0, (64, 48, 3)).astype(np.float32)
    a[3, :5, 0] = [np.nan, np.inf, -np.inf, 1e30, -1e30]
    before = a.copy()
    lo, hi = 200.0, 900.0
    want = (a.astype(np.float64) - lo) * (255.0 / (hi - lo))
    want = np.where(np.isnan(want), 0.0, np.clip(want, 0.0, 255.0))
    got = Stretch(lo, hi).apply(a)
    assert got.dtype == np.float32 and np.isfinite(got).all()
    assert np.abs(got - want).max() <= 1e-3
    assert list(got[3, :5, 0]) == [0.0, 255.0, 0.0, 255.0, 0.0]
    np.testing.assert_array_equal(a, before)  # the input is left alone
    u16 = rng.integers(0, 65536, (20, 30)).astype(np.uint16)
    np.testing.assert_allclose(Stretch(1000.0, 60000.0).apply(u16),
                               np.clip((u16 - 1000.0) * (255.0 / 59000.0), 0, 255),
                               rtol=0, atol=1e-3)
    assert not Stretch(5.0, 5.0).apply(u16).any()  # a flat stretch shows black


def test_pyramid_of_lazy_inputs_reads_windows_only(tmp_path):
    rng = np.random.default_rng(1)
    H, W = 700, 1000
    obs = Recorder(textured(rng, H, W).astype(np.uint16) * 200)
    chg = np.zeros((H, W), bool)
    chg[100:160, 200:330] = True
    chg[500:520, 900:990] = True
    change, unknown = Recorder(chg), Recorder(np.zeros((H, W), bool))
    res, _ = hand_built(H, W)
    res.change, res.unknown, res.reblurred = change, unknown, None
    opts = ViewerOptions(tile_size=64, block=256)
    regions = [dict(bbox=[100, 200, 160, 330], area=60 * 130),
               dict(bbox=[500, 900, 520, 990], area=20 * 90)]
    info = write_viewer(tmp_path / "viewer", res, observed=Image.from_array(obs, "o.tif"),
                        regions=regions, options=opts)
    # every read is a window of at most block x block pixels: the stretch's sample, the
    # pyramid's blocks, the regions' boxes
    for arr in (obs, change, unknown):
        assert arr.largest() <= 256 * 256 < H * W
    assert obs.count.min() >= 1  # the whole image reached the pyramid
    root = tmp_path / "viewer" / "tiles"
    assert info.layout.max_level == 10
    assert read_level(root, "observed", 10).shape[:2] == (H, W)
    assert len(list((root / "observed_files" / "0").iterdir())) == 1
    assert read_level(root, "changes", 0).shape[:2] == (1, 1)
    # every level has the tiles the layout says, and nothing else
    for name in info.layers:
        n = sum(1 for _ in (root / f"{name}_files").rglob("*.*"))
        assert n == info.layout.n_tiles(), name


def test_mask_layer_keeps_a_single_changed_pixel_visible_at_every_level(tmp_path):
    m = np.zeros((300, 500), bool)
    m[123, 321] = True
    unk = np.zeros_like(m)
    unk[:, :50] = True
    layers = [mask_layer("chg", m, (255, 0, 0), alpha=1.0, reduce="max"),
              mask_layer("unk", unk, (0, 0, 255), alpha=1.0, reduce="mean")]
    lay = build_pyramids(tmp_path, layers, m.shape, tile_size=64, block=128)
    for level in range(lay.max_level + 1):
        s = 2 ** (lay.max_level - level)
        a = read_level(tmp_path, "chg", level)[..., 3]
        assert a.max() == 255 and a[123 // s, 321 // s] == 255 and np.count_nonzero(a) == 1
    # the mean keeps the share: level max-1, the first column of 2x2 blocks is all unknown
    u = read_level(tmp_path, "unk", lay.max_level - 3)[..., 3].astype(float)
    share = block_mean(unk.astype(float), 8)
    np.testing.assert_allclose(u[:share.shape[0], :share.shape[1]], 255 * share, atol=1.0)


# ---------------------------------------------------------------------------- outlines
def rasterise(rings, shape) -> np.ndarray:
    """Pixels whose centre lies inside the rings (even-odd), by shapely."""
    import shapely
    from shapely.geometry import Polygon

    poly = Polygon(rings[0], rings[1:])
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    return shapely.contains_xy(poly, xx.ravel() + 0.5, yy.ravel() + 0.5).reshape(shape)


def test_outline_is_the_region_and_not_its_neighbour_in_the_box():
    m = np.zeros((80, 90), bool)
    m[10:60, 10:20] = True  # an L ...
    m[50:60, 10:70] = True
    m[20:40, 35:55] = True  # ... with another region inside its box
    m[25:30, 40:45] = False  # (which has a hole)
    lab, n = ndimage.label(m, structure=EIGHT)
    assert n == 2
    ell = lab == lab[12, 12]
    ys, xs = np.nonzero(ell)
    bbox = (ys.min(), xs.min(), ys.max() + 1, xs.max() + 1)
    rings, exact = region_outline(m, bbox, int(ell.sum()))
    assert exact and len(rings) == 1
    np.testing.assert_array_equal(rasterise(rings, m.shape), ell)
    sq = lab == lab[21, 36]
    ys, xs = np.nonzero(sq)
    rings, exact = region_outline(m, (ys.min(), xs.min(), ys.max() + 1, xs.max() + 1),
                                  int(sq.sum()))
    assert exact and len(rings) == 2  # exterior and the hole
    np.testing.assert_array_equal(rasterise(rings, m.shape), sq)


def test_outline_of_a_box_larger_than_max_side_is_traced_coarser():
    m = np.zeros((300, 400), bool)
    cv2.circle(m.view(np.uint8), (200, 150), 120, 1, -1)
    ys, xs = np.nonzero(m)
    rings, exact = region_outline(m, (ys.min(), xs.min(), ys.max() + 1, xs.max() + 1),
                                  int(m.sum()), max_side=64, max_vertices=40)
    assert not exact
    assert sum(len(r) for r in rings) <= 40
    inter = rasterise(rings, m.shape)
    iou = np.count_nonzero(inter & m) / np.count_nonzero(inter | m)
    assert iou > 0.9


# ---------------------------------------------------------------------------- sources
def test_reblurred_layer_read_back_from_reblurred_tif(tmp_path):
    res, obs = hand_built(90, 130)
    res.reblurred = None
    rb = textured(np.random.default_rng(5), 90, 130)
    write_tiff(tmp_path / "reblurred.tif", rb)
    info = write_viewer(tmp_path / "viewer", res, observed=Image.from_array(obs, "o.png"),
                        reblurred_path=tmp_path / "reblurred.tif",
                        options=ViewerOptions(image_format="png", tile_size=64))
    assert "reblurred" in info.layers and not info.notes
    root = tmp_path / "viewer" / "tiles"
    np.testing.assert_array_equal(read_level(root, "reblurred", info.layout.max_level), rb)
    np.testing.assert_array_equal(read_level(root, "observed", info.layout.max_level), obs)
    # neither in the result nor on disk: no layer, and a note saying so
    info = write_viewer(tmp_path / "v2", res, observed=Image.from_array(obs, "o.png"))
    assert "reblurred" not in info.layers and "reblurred" in info.notes[0]


def test_reblurred_in_fractions_is_shown_in_the_observations_stretch(tmp_path):
    res, obs8 = hand_built(64, 96)
    obs = obs8.astype(np.uint16) * 100 + 1000  # 1000 .. 26500
    res.reblurred = obs.astype(np.float32) / 65535.0  # the same image, fractions of full scale
    info = write_viewer(tmp_path / "v", res, observed=Image.from_array(obs, "o.tif"),
                        options=ViewerOptions(image_format="png", tile_size=64))
    root = tmp_path / "v" / "tiles"
    a = read_level(root, "observed", info.layout.max_level).astype(int)
    b = read_level(root, "reblurred", info.layout.max_level).astype(int)
    assert np.abs(a - b).max() <= 1 and np.ptp(a) > 200  # stretched, and alike


def test_write_viewer_refuses_a_folder_that_is_not_a_viewer(tmp_path):
    res, obs = hand_built(64, 96)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.txt").write_text("keep me")
    with pytest.raises(ValueError, match="not an earlier viewer"):
        write_viewer(mine, res, observed=Image.from_array(obs, "o.png"))
    assert (mine / "thesis.txt").read_text() == "keep me"
    assert sorted(p.name for p in mine.iterdir()) == ["thesis.txt"]
    # an earlier viewer is replaced; an empty folder is used
    opts = ViewerOptions(image_format="png", tile_size=64)
    for folder in (tmp_path / "v", tmp_path / "v", tmp_path / "empty"):
        folder.mkdir(exist_ok=True)
        info = write_viewer(folder, res, observed=Image.from_array(obs, "o.png"),
                            options=opts)
        (folder / "tiles" / "stale.txt").write_text("old")
        assert info.index == folder / "index.html" and info.index.exists()
    write_viewer(tmp_path / "v", res, observed=Image.from_array(obs, "o.png"), options=opts)
    assert not (tmp_path / "v" / "tiles" / "stale.txt").exists()


def test_bad_options_are_refused():
    with pytest.raises(ValueError, match="image_format"):
        ViewerOptions(image_format="webp")
    with pytest.raises(ValueError, match="block"):
        ViewerOptions(tile_size=512, block=256)


# ---------------------------------------------------------------------------- report
def test_write_report_writes_the_viewer_and_lists_it(tmp_path):
    res, obs = hand_built()
    files, summary = write_report(res, tmp_path / "out", observed=Image.from_array(obs, "o.png"))
    out = tmp_path / "out"
    assert files["viewer"] == "viewer/index.html"
    refs = assert_html_refs_exist(out / "viewer" / "index.html")
    assert "data.js" in refs and "static/openseadragon.min.js" in refs
    data = json.loads((out / "viewer" / "regions.json").read_text())
    known = res.change & ~res.unknown
    _, n = ndimage.label(known, structure=EIGHT)
    assert data["n_regions"] == summary["changes"]["n_regions"] == n
    assert sorted(r["area"] for r in data["regions"]) == sorted(
        np.bincount(ndimage.label(known, structure=EIGHT)[0].ravel())[1:].tolist())
    assert all(r["exact"] and r["outline"] for r in data["regions"])
    assert data["windows"] == [[10, 10, 100, 100]]
    assert (out / "viewer" / "static" / "LICENSE-openseadragon.txt").read_text().startswith(
        "Copyright")
    assert "viewer" in summary["timings_s"]
    # no viewer when asked for none
    files, _ = write_report(res, tmp_path / "none", observed=Image.from_array(obs, "o.png"),
                            viewer=None)
    assert "viewer" not in files and not (tmp_path / "none" / "viewer").exists()


def test_output_set_replaces_the_viewer_folder(tmp_path):
    out = tmp_path / "out"
    names = ("report.json", "viewer")
    for k in range(2):
        with output_set(out, names, overwrite=True, manifest="report.json") as stage:
            (stage / "viewer").mkdir()
            (stage / "viewer" / f"run{k}.txt").write_text("x")
            (stage / "report.json").write_text(json.dumps({"files": {
                "viewer": "viewer/index.html"}}))
        (out / "notes-of-mine.txt").write_text("kept")  # forces the file-by-file move
    assert sorted(p.name for p in (out / "viewer").iterdir()) == ["run1.txt"]
    assert (out / "notes-of-mine.txt").exists()


# ---------------------------------------------------------------------------- the page
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                  "--no-first-run", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--hide-scrollbars",
                  # nothing but the local server answers: the page must be self-contained
                  "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1"]


def chromium() -> str:
    exe = shutil.which("chromium")
    if exe is None:  # a failure, not a skip: .ci/run installs it
        pytest.fail("chromium is not installed: apt-get install -y chromium")
    return exe


class Browser:
    """Headless Chromium driven through the DevTools protocol on a pipe (fds 3 and 4).

    A page is loaded, then polled in real time until it says it is ready: unlike
    ``--virtual-time-budget``, nothing is cut short on a loaded machine.
    """

    def __init__(self, width: int, height: int, timeout: float = 90.0):
        self.profile = tempfile.TemporaryDirectory()
        cmd_r, self.cmd_w = os.pipe()
        self.res_r, res_w = os.pipe()

        def fds():  # the child reads commands on fd 3, writes replies on fd 4
            a, b = (fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in (cmd_r, res_w))
            os.dup2(a, 3)  # (through fds above 4: the pipes may be 3 and 4 themselves)
            os.dup2(b, 4)

        self.proc = subprocess.Popen(
            [chromium(), *CHROMIUM_FLAGS, f"--user-data-dir={self.profile.name}",
             f"--window-size={width},{height}", "--remote-debugging-pipe", "about:blank"],
            preexec_fn=fds, close_fds=False, stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(cmd_r)
        os.close(res_w)
        self.deadline = time.monotonic() + timeout
        self.buf, self.n, self.session = b"", 0, None
        page = next(t for t in self.send("Target.getTargets")["targetInfos"]
                    if t["type"] == "page")
        self.session = self.send("Target.attachToTarget", targetId=page["targetId"],
                                 flatten=True)["sessionId"]
        self.send("Emulation.setDeviceMetricsOverride", width=width, height=height,
                  deviceScaleFactor=1, mobile=False)

    def _message(self) -> dict:
        while b"\0" not in self.buf:
            left = self.deadline - time.monotonic()
            if left <= 0 or not select.select([self.res_r], [], [], left)[0]:
                raise TimeoutError("chromium did not answer in time")
            chunk = os.read(self.res_r, 1 << 20)
            if not chunk:
                raise RuntimeError("chromium closed the DevTools pipe")
            self.buf += chunk
        msg, self.buf = self.buf.split(b"\0", 1)
        return json.loads(msg)

    def send(self, method: str, **params):
        self.n += 1
        msg = dict(id=self.n, method=method, params=params)
        if self.session is not None:
            msg["sessionId"] = self.session
        os.write(self.cmd_w, json.dumps(msg).encode() + b"\0")
        while True:
            m = self._message()
            if m.get("id") == self.n:
                if "error" in m:
                    raise RuntimeError(f"{method}: {m['error']}")
                return m["result"]

    def eval(self, expression: str):
        r = self.send("Runtime.evaluate", expression=expression, returnByValue=True,
                      awaitPromise=True)
        return r["result"].get("value")

    def wait_for(self, expression: str) -> None:
        while not self.eval(expression):
            if time.monotonic() > self.deadline:
                raise TimeoutError(f"never true: {expression}")
            time.sleep(0.1)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.session = None
            self.send("Browser.close")
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        os.close(self.cmd_w)
        os.close(self.res_r)
        self.profile.cleanup()


class _Quiet(http.server.SimpleHTTPRequestHandler):
    log: list[tuple[str, int]]

    def log_request(self, code="-", size="-"):
        self.log.append((self.path, int(code) if str(code).isdigit() else 0))

    def log_message(self, *args):
        pass


@pytest.fixture
def served():
    """Serve a folder on localhost; yields ``(start(folder) -> base url, request log)``."""
    servers = []
    log: list[tuple[str, int]] = []

    def start(folder: Path) -> str:
        handler = type("H", (_Quiet,), {"log": log})
        srv = http.server.ThreadingHTTPServer(
            ("127.0.0.1", 0), functools.partial(handler, directory=str(folder)))
        threading.Thread(target=srv.serve_forever, daemon=True).start()
        servers.append(srv)
        return f"http://127.0.0.1:{srv.server_port}/"

    yield start, log
    for srv in servers:
        srv.shutdown()
        srv.server_close()


def detected_demo():
    import reblur
    from reblur.data import demo_pair

    ref, obs, _ = demo_pair()
    return reblur.detect_changes(ref, obs), ref, obs


@pytest.mark.slow
def test_viewer_in_headless_chromium(tmp_path, served):
    res, ref, obs = detected_demo()
    out = tmp_path / "out"
    write_report(res, out, observed=Image.from_array(obs, "demo observed"),
                 reference=Image.from_array(ref, "demo reference"))
    known = np.asarray(res.change) & ~np.asarray(res.unknown)
    lab, n = ndimage.label(known, structure=EIGHT)
    assert n >= 2  # the demo has changes
    # a click on a pixel of the largest region shows that region's attributes
    areas = np.bincount(lab.ravel())[1:]
    big = 1 + int(np.argmax(areas))
    ys, xs = np.nonzero(lab == big)
    k = int(np.argmin((ys - ys.mean()) ** 2 + (xs - xs.mean()) ** 2))  # a pixel inside
    start, log = served
    url = start(out / "viewer") + f"index.html#swipe=50&click={xs[k] + 0.5},{ys[k] + 0.5}"
    browser = Browser(1000, 700)
    try:
        browser.send("Page.navigate", url=url)
        browser.wait_for("document.title.includes('loaded:1')")
        # two frames more: the last tiles are drawn
        browser.eval("new Promise(r => requestAnimationFrame(() => requestAnimationFrame("
                     "() => r(1))))")
        title = browser.eval("document.title")
        details = browser.eval("document.getElementById('details').innerHTML")
        rect = browser.eval("document.body.dataset.imageRect")
        png = base64.b64decode(browser.send("Page.captureScreenshot", format="png")["data"])
        # a mouse click in a region's box but off every outline (its hole or an empty
        # corner) selects no region: the click tolerance is 6 screen pixels
        x0, y0, w, h = (float(v) for v in rect.split(","))
        s = w / known.shape[1]
        far = ndimage.distance_transform_edt(~known)
        boxed = np.zeros_like(known)
        for sl in ndimage.find_objects(lab):
            boxed[sl] = True
        far[~boxed] = 0
        cy, cx = np.unravel_index(int(np.argmax(far)), far.shape)
        assert far[cy, cx] * s > 6 + 2 * s, (far[cy, cx], s)  # farther than the tolerance
        for kind in ("mousePressed", "mouseReleased"):
            browser.send("Input.dispatchMouseEvent", type=kind, x=x0 + (cx + 0.5) * s,
                         y=y0 + (cy + 0.5) * s, button="left", clickCount=1)
        browser.eval("new Promise(r => requestAnimationFrame(() => r(1)))")
        off = browser.eval("document.getElementById('details').innerHTML")
    finally:
        browser.close()
    assert "No region there" in off, off
    st = dict(kv.split(":") for kv in title.split())
    assert int(st["regions"]) == min(n, ViewerOptions().max_regions), title
    assert int(st["tiles"]) > 0 and st["failed"] == "0" and st["layers"] == "4", title
    assert re.search(rf"<th>area \(px\)</th><td>{areas[big - 1]}</td>", details), details
    # every request was for a file of the folder, and every one was there
    assert log and all(code == 200 for _, code in log), [x for x in log if x[1] != 200]

    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    assert img.shape[:2] == (700, 1000)
    x0, y0, w, h = (int(round(float(v))) for v in rect.split(","))
    assert w > 300 and h > 200 and x0 >= 0 and y0 >= 0  # fitted in the viewer
    seen = img[y0 + 2:y0 + h - 2, x0 + 2:x0 + w - 2].astype(np.float64)
    expect = cv2.resize(obs, (w, h), interpolation=cv2.INTER_AREA)[2:-2, 2:-2].astype(float)
    assert seen.std() > 20  # not blank
    r = np.corrcoef(seen.mean(axis=2).ravel(), expect.mean(axis=2).ravel())[0, 1]
    assert r > 0.8, r  # the tiles drawn are the observation, in its place
    if os.environ.get("REBLUR_UPDATE_README") == "1":
        save_readme_picture(img, ROOT / "docs" / "viewer.png")


def save_readme_picture(rgb: np.ndarray, dest: Path) -> None:
    """The screenshot for the README, in 256 colours (small); left as it is when the view
    has not changed (renderings differ by a few grey levels from run to run).  Written only
    when the environment sets ``REBLUR_UPDATE_README=1`` (the file is tracked: a test run
    leaves it alone)::

        REBLUR_UPDATE_README=1 pytest tests/test_viewer.py -k chromium
    """
    from PIL import Image as PILImage

    from reblur.io import atomic_path

    if dest.exists():
        old = cv2.imread(str(dest))
        if old is not None and old.shape == rgb.shape and np.abs(
                old[..., ::-1].astype(int) - rgb).mean() < 2.0:
            return
    q = PILImage.fromarray(np.ascontiguousarray(rgb)).quantize(
        colors=256, method=PILImage.Quantize.FASTOCTREE, dither=PILImage.Dither.NONE)
    dest.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(dest) as tmp:
        q.save(tmp, format="PNG", optimize=True)


def test_halve_means_the_pixels_that_exist_at_odd_edges():
    from reblur.viewer.pyramid import halve

    rng = np.random.default_rng(3)
    a = rng.random((7, 5, 2)).astype(np.float32)
    ref = np.zeros((4, 3, 2))
    top = np.zeros((4, 3, 2))
    for i in range(4):
        for j in range(3):
            block = a[2 * i:2 * i + 2, 2 * j:2 * j + 2]  # 1, 2 or 4 pixels at the edges
            ref[i, j] = block.mean(axis=(0, 1))
            top[i, j] = block.max(axis=(0, 1))
    np.testing.assert_allclose(halve(a, "mean"), ref, rtol=1e-6)
    np.testing.assert_array_equal(halve(a, "max"), top)
    assert halve(a[:1, :1], "mean").shape == (1, 1, 2)


def test_viewer_opens_from_the_disk(tmp_path):
    """Opened as a file (no server: a browser refuses to fetch files there), the page still
    shows its tiles and regions: its data come in a script, its tiles as images."""
    res, obs = hand_built(200, 300)
    lab, n = ndimage.label(res.change & ~res.unknown, structure=EIGHT)
    regions = [dict(bbox=[sl[0].start, sl[1].start, sl[0].stop, sl[1].stop],
                    area=int((lab[sl] == i).sum()))
               for i, sl in enumerate(ndimage.find_objects(lab), 1)]
    info = write_viewer(tmp_path / "viewer", res, observed=Image.from_array(obs, "o.png"),
                        regions=regions, options=ViewerOptions(tile_size=128))
    browser = Browser(800, 500)
    try:
        browser.send("Page.navigate", url=info.index.as_uri())
        browser.wait_for("document.title.includes('loaded:1')")
        title = browser.eval("document.title")
    finally:
        browser.close()
    st = dict(kv.split(":") for kv in title.split())
    assert int(st["regions"]) == n and int(st["tiles"]) > 0 and st["failed"] == "0", title


def test_package_data_holds_every_static_file():
    """pyproject's package-data patterns cover every file the viewer copies (the wheel)."""
    import fnmatch
    import tomllib

    import reblur

    pats = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"]["reblur"]
    pkg = Path(reblur.__file__).parent
    static = [p.relative_to(pkg).as_posix() for p in (pkg / "viewer" / "static").rglob("*")
              if p.is_file()]
    assert len(static) == 21  # the page, its script and style, OSD, its licence, 16 buttons
    missing = [f for f in static if not any(fnmatch.fnmatchcase(f, p) for p in pats)]
    assert not missing
