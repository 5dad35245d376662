"""The alignment's overviews from a file's own reduced-resolution levels (pyramidal TIFF,
GDAL / COG overviews, zarr multiscales), and the full-image block-mean read without them.

Truths: a known homography applied to a real LEVIR image (the alignment tests), linear
ramps whose block means are their values at the block centres (the geometry of the level
conventions), and block means computed by numpy reshapes (the banded, threaded read).
"""

from __future__ import annotations

import logging
import pickle
import warnings

import cv2
import numpy as np
import pytest
import tifffile
import zarr
from conftest import LEVIR

from reblur.align import AlignParams, OverviewCache, block_means, coarse_align
from reblur.align import overviews as ov
from reblur.grid import map_points, pose_homography
from reblur.io import open_image, reconcile_bands
from reblur.levels import FileLevel, FileLevels, check_level
from reblur.warp import Box, warp_window

SIDE = 1024
TRUE_H = pose_homography(14.3, -9.6, rz=2.0, center=((SIDE - 1) / 2, (SIDE - 1) / 2))


# ---------------------------------------------------------------------------- helpers
def _block_mean(a: np.ndarray, n: int) -> np.ndarray:
    """Mean of ``n x n`` blocks (sides divisible by ``n``), float64."""
    h, w = a.shape[0] // n, a.shape[1] // n
    return a[: h * n, : w * n].astype(np.float64).reshape(h, n, w, n, *a.shape[2:]).mean(
        axis=(1, 3))


def _write_tiff(path, a: np.ndarray, factors=(), *, tile=128, level_fn=None,
                ome=None) -> None:
    """``a`` as a tiled TIFF with reduced-resolution levels in SubIFDs, one per factor
    (exact block means rounded to the dtype by default, or ``level_fn(a, n)``)."""
    photometric = "rgb" if a.ndim == 3 and a.shape[2] in (3, 4) else "minisblack"
    extra = {"extrasamples": [2]} if a.ndim == 3 and a.shape[2] == 4 else {}
    with tifffile.TiffWriter(path, ome=ome) as tw:
        tw.write(a, tile=(tile, tile), subifds=len(factors), photometric=photometric, **extra)
        for n in factors:
            lv = level_fn(a, n) if level_fn else _block_mean(a, n)
            if a.dtype.kind in "ui":
                lv = np.clip(np.rint(lv), 0, np.iinfo(a.dtype).max)
            tw.write(lv.astype(a.dtype), tile=(tile, tile), subfiletype=1,
                     photometric=photometric, **extra)


class _Counted:
    """Array-like forwarding to ``a`` that counts its reads."""

    def __init__(self, a):
        self.a, self.reads = a, 0
        self.shape, self.dtype = a.shape, a.dtype
        self.chunks = getattr(a, "chunks", None)

    def __getitem__(self, key):
        self.reads += 1
        return self.a[key]


def _corner_gap(Ha: np.ndarray, Hb: np.ndarray, shape=(SIDE, SIDE)) -> float:
    h, w = shape
    c = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)
    return float(np.hypot(*(map_points(Ha, c) - map_points(Hb, c)).T).max())


@pytest.fixture(scope="module")
def pair_files(tmp_path_factory):
    """A real 1024 px image and its view under :data:`TRUE_H`, uint8, as TIFFs with and
    without 2x / 4x / 8x block-mean levels."""
    ref = cv2.imread(str(LEVIR / "A" / "test_7.png"), cv2.IMREAD_GRAYSCALE)
    assert ref is not None and ref.shape == (SIDE, SIDE)
    obs, _ = warp_window(ref.astype(np.float32) / 255, TRUE_H, Box(0, 0, SIDE, SIDE))
    obs = np.clip(np.rint(obs[..., 0] * 255), 0, 255).astype(np.uint8)
    d = tmp_path_factory.mktemp("pyramid")
    for name, a in (("ref", ref), ("obs", obs)):
        _write_tiff(d / f"{name}.tif", a)
        _write_tiff(d / f"{name}_levels.tif", a, (2, 4, 8))
    return d


def _opened(path, count: bool = False):
    """The view of ``path`` detection reads; with ``count``, its full-resolution reader
    replaced by a :class:`_Counted` one (returned too)."""
    arr = open_image(path, lazy=True).for_detection()
    if not count:
        return arr, None
    arr.source = counted = _Counted(arr.source)
    reader = getattr(arr, "chunk_reader", None)
    if reader is not None:  # a pass over the file's chunks is a full read too

        def chunks(workers: int = 1, func=None):
            counted.reads += 1
            return reader(workers, func)

        arr.chunk_reader = chunks
    return arr, counted


# ---------------------------------------------------------------------------- alignment
@pytest.mark.parametrize("max_side, level", [(256, "TIFF level 2"), (200, "TIFF level 1")])
@pytest.mark.parametrize("sides", ["both", "reference"])
def test_alignment_from_levels_matches_the_full_read(pair_files, max_side, level, sides):
    """k = 4 from the 4x level and k = 6 from the 2x level (a 4x level would cut blocks),
    levels in both files or in the reference only (where a wrong pixel-centre convention
    would show: both overviews would no longer move together): the homography's corners
    lie within 0.1 px of the full read's, both near the applied homography; the
    full-resolution images with levels are never read."""
    p = AlignParams(max_side=max_side, min_side=64)
    plain = coarse_align(OverviewCache(_opened(pair_files / "ref.tif")[0]),
                         OverviewCache(_opened(pair_files / "obs.tif")[0]), p, shake_px=4.0)
    ref, ref_n = _opened(pair_files / "ref_levels.tif", count=True)
    obs_name = "obs_levels.tif" if sides == "both" else "obs.tif"
    obs, obs_n = _opened(pair_files / obs_name, count=True)
    rc, oc = OverviewCache(ref), OverviewCache(obs)
    a = coarse_align(rc, oc, p, shake_px=4.0)
    assert _corner_gap(a.H, plain.H) < 0.1
    assert _corner_gap(a.H, TRUE_H) < 1.5 and _corner_gap(plain.H, TRUE_H) < 1.5
    assert ref_n.reads == 0 and rc.reads == 0 and rc.level_reads == 1
    src = a.to_dict()["overviews"]
    assert src["reference"]["source"] == "file levels"
    assert src["reference"]["level"]["name"] == level
    if sides == "both":
        assert obs_n.reads == 0 and src["observation"]["source"] == "file levels"
    else:
        assert obs_n.reads > 0 and src["observation"]["source"] == ov.FROM_FULL
    assert plain.to_dict()["overviews"]["reference"] == {"source": ov.FROM_FULL}


def test_coarser_views_derive_from_the_level_overview(pair_files):
    """The pipeline's later low-resolution views (a multiple of the factor) come from the
    overview read from the level: no further read of the file."""
    ref, counted = _opened(pair_files / "ref_levels.tif", count=True)
    cache = OverviewCache(ref)
    g4, _ = block_means(cache, 4)
    g8, _ = block_means(cache, 8)
    assert cache.level_reads == 1 and cache.reads == 0 and counted.reads == 0
    want = _block_mean(_block_mean(np.asarray(ref[...]), 4), 2) / 255
    np.testing.assert_allclose(g8, want, atol=0.6 / 255)
    assert cache.overview_source(8)["source"] == "file levels"
    # file_levels=False: always the full image
    off = OverviewCache(ref, file_levels=False)
    block_means(off, 4)
    assert off.reads == 1 and counted.reads > 0 and off.overview_source(4) == {
        "source": ov.FROM_FULL}
    np.testing.assert_allclose(g4, off.block_means(4)[0], atol=0.6 / 255)


# ---------------------------------------------------------------------------- geometry
def test_check_level_shapes():
    assert check_level((1000, 1500), (500, 750)) == (2.0, 2.0)
    assert check_level((1001, 1503), (501, 752)) == pytest.approx((1001 / 501, 1503 / 752))
    assert check_level((1001, 1503), (500, 751)) == pytest.approx((1001 / 500, 1503 / 751))
    assert "another aspect" in check_level((1024, 1024), (512, 300))
    assert "not smaller" in check_level((1024, 1024), (1024, 1024))
    assert "not smaller" in check_level((1024, 1024), (512, 1100))
    assert check_level((1024, 1024), (512, 512), stated=(2.0, 2.0)) == (2.0, 2.0)
    assert "does not give its size" in check_level((1024, 1024), (512, 512), stated=(4, 4))
    assert "not a reduction" in check_level((1024, 1024), (512, 512), stated=(0.5, 2))


def _ramps(h: int, w: int) -> np.ndarray:
    """Two float32 bands: the column and the row of each pixel centre."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    return np.stack([x, y], axis=2)


def _centre_errors(bands: np.ndarray, k: int, skip: int = 0) -> tuple[float, float]:
    """Mean and largest distance (px) between the block means of the :func:`_ramps`
    and the block centres, where each block mean of a ramp should be (the first ``skip``
    rows and columns of blocks left out)."""
    h, w = bands.shape[:2]
    cy, cx = np.mgrid[0:h, 0:w] * float(k) + (k - 1) / 2.0
    err = np.stack([bands[..., 0] - cx, bands[..., 1] - cy])[:, skip:, skip:]
    return float(np.abs(err.mean(axis=(1, 2))).max()), float(np.abs(err).max())


@pytest.mark.parametrize("driver", ["GTiff", "COG"])
def test_gdal_overviews_follow_the_shape_ratio_convention(tmp_path, driver):
    """GDAL's average overviews (``gdaladdo``: ceil-sized; the COG driver: floor-sized) of
    two ramps: the overviews read from them put every block mean within 0.25 px of its
    block's centre and on average within 0.02 px (a half-pixel convention error would
    show as 0.5 px on average)."""
    rasterio = pytest.importorskip("rasterio")
    from rasterio.enums import Resampling

    a = _ramps(1001, 1503)
    path = tmp_path / "ramps.tif"
    prof = dict(driver=driver, width=1503, height=1001, count=2, dtype="float32")
    if driver == "GTiff":
        prof.update(tiled=True, blockxsize=256, blockysize=256)
    else:
        prof.update(overview_resampling="average", blocksize=256)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # not georeferenced
        with rasterio.open(path, "w", **prof) as dst:
            dst.write(np.moveaxis(a, 2, 0))
            if driver == "GTiff":
                dst.build_overviews([2, 4, 8], Resampling.average)
    view = open_image(path, lazy=True).for_detection()
    assert view.file_levels is not None
    for k in (2, 4, 6, 8, 13, 16):
        cache = OverviewCache(view)
        _, bands = block_means(cache, k)
        src = cache.overview_source(k)
        assert src["source"] == ("file levels" if k >= 4 else ov.FROM_FULL), (k, src)
        mean_err, max_err = _centre_errors(bands, k)
        assert mean_err < 0.02 and max_err < 0.25, (k, src, mean_err, max_err)


def test_level_block_means_exact_and_cut_blocks():
    """From an exact 2x block mean (float), factors that are multiples of 2 give the
    image's block means; others, from a 4x level, the ramps' centres within 0.05 of a
    level pixel (``k / f >= 2``) and on average within 0.01 px."""
    a = _ramps(512, 768)
    for k in (2, 4, 10):
        lv = FileLevel(_block_mean(a, 2).astype(np.float32), (2.0, 2.0))
        got = ov.level_block_means(lv, k, a.shape[:2])
        np.testing.assert_allclose(got[1], _block_mean(a, k), atol=1e-3)
    lv4 = FileLevel(_block_mean(a, 4).astype(np.float32), (4.0, 4.0))
    for k in (9, 10, 14):
        _, bands = ov.level_block_means(lv4, k, a.shape[:2])
        mean_err, max_err = _centre_errors(bands, k)
        assert mean_err < 0.01 and max_err <= 0.05 * 4 + 1e-3, (k, mean_err, max_err)


def test_choose_level():
    def lv(f, n=500):
        return FileLevel(np.zeros((n, n), np.uint8), (f, f), name=str(f))

    levels = [lv(2.0), lv(4.0), lv(8.0), lv(16.0)]
    pick = {k: getattr(ov.choose_level(levels, k), "name", None) for k in (1, 2, 3, 4, 6, 7,
                                                                              8, 10, 12, 31)}
    # exact divisors, else at most half the factor
    assert pick == {1: None, 2: "2.0", 3: None, 4: "4.0", 6: "2.0", 7: "2.0", 8: "8.0",
                    10: "4.0", 12: "4.0", 31: "8.0"}
    # a floor-sized COG level (f slightly above 4) still serves k = 8 and 10
    cog = [lv(2.002), lv(4.004)]
    assert ov.choose_level(cog, 8).name == "4.004"
    assert ov.choose_level(cog, 4).name == "2.002"


# ---------------------------------------------------------------------------- zarr
def _ngff(path, arrays: dict, scales: dict, translations: dict | None = None,
          chunks=(128, 128)) -> None:
    """A zarr group of ``arrays`` ((y, x[, c]) each) with multiscales metadata stating
    ``scales`` and ``translations`` (y, x) per array."""
    g = zarr.open_group(str(path), mode="w")
    datasets = []
    bands = [] if next(iter(arrays.values())).ndim == 2 else [1.0]
    for name, a in arrays.items():
        z = g.create_array(name, shape=a.shape, chunks=chunks + a.shape[2:], dtype=a.dtype)
        z[...] = a
        tr = [{"type": "scale", "scale": list(scales[name]) + bands}]
        if translations and name in translations:
            tr.append({"type": "translation",
                       "translation": list(translations[name]) + [0.0] * len(bands)})
        datasets.append({"path": name, "coordinateTransformations": tr})
    axes = [{"name": "y", "type": "space"}, {"name": "x", "type": "space"}]
    axes += [{"name": "c", "type": "channel"}] * len(bands)
    g.attrs["multiscales"] = [{"version": "0.4", "axes": axes, "datasets": datasets}]


def test_zarr_multiscales_alignment(pair_files, tmp_path):
    """An OME-Zarr-style multiscales group: the alignment reads its levels, never the
    full-resolution array, and agrees with the full read within 0.1 px."""
    views = {}
    for name in ("ref", "obs"):
        a = np.asarray(open_image(pair_files / f"{name}.tif").array)
        lv = {str(i): np.clip(np.rint(_block_mean(a, 2 ** i)), 0, 255).astype(np.uint8)
              if i else a for i in range(3)}
        _ngff(tmp_path / f"{name}.zarr", lv, {str(i): (2.0 ** i, 2.0 ** i) for i in range(3)})
        views[name] = open_image(tmp_path / f"{name}.zarr", lazy=True).for_detection()
        assert views[name].file_levels is not None
    p = AlignParams(max_side=256, min_side=64)
    plain = coarse_align(np.asarray(views["ref"][...]), np.asarray(views["obs"][...]), p,
                         shake_px=4.0)
    counted = {n: _Counted(v.source) for n, v in views.items()}
    for n, v in views.items():
        v.source = counted[n]
    a = coarse_align(OverviewCache(views["ref"]), OverviewCache(views["obs"]), p, shake_px=4.0)
    assert counted["ref"].reads == counted["obs"].reads == 0
    assert a.overviews["reference"]["file"] == "zarr multiscales"
    assert a.overviews["reference"]["level"]["name"] == "zarr dataset '2'"
    assert _corner_gap(a.H, plain.H) < 0.1 and _corner_gap(a.H, TRUE_H) < 1.5


def test_zarr_stated_scale_and_translation(tmp_path):
    """Levels made by decimation, ``a[1::2]`` (centres on base pixels 1, 3, ...), stating
    scale 2 and translation 1: read where they say they are (a ramp's block means at the
    block centres); a level whose stated scale contradicts its shape, and one with chunks
    never written, are ignored."""
    a = _ramps(600, 800)
    arrays = {"0": a, "1": np.ascontiguousarray(a[1::2, 1::2]), "2": a[::4, ::4].copy(),
              "3": np.zeros((75, 100, 2), np.float32)}
    _ngff(tmp_path / "r.zarr", arrays, {"0": (1, 1), "1": (2, 2), "2": (2, 2), "3": (8, 8)},
          {"0": (0, 0), "1": (1, 1)}, chunks=(64, 64))  # zarr skips "3"'s chunks: fill value
    view = open_image(tmp_path / "r.zarr", lazy=True).for_detection()
    cache = OverviewCache(view)
    _, bands = block_means(cache, 8)
    src = cache.overview_source(8)
    assert src["level"]["name"] == "zarr dataset '1'" and src["level"]["origin"] == [0.5, 0.5]
    assert any("stated scale" in s for s in src["ignored_levels"])
    assert any("'3': 4 of its 4 chunks were never written" in s for s in src["ignored_levels"])
    # (the first block lacks the half pixel before the level's first sample)
    mean_err, max_err = _centre_errors(bands, 8, skip=1)
    assert mean_err < 1e-3 and max_err < 1e-3


# ---------------------------------------------------------------------------- views, errors
def test_levels_seen_through_the_views(tmp_path):
    """RGBA (alpha -> no data as NaN), RGB as luminance against a gray image, and uint32
    (rescaled to its range): the overviews from the levels equal the full read's within
    the levels' rounding."""
    rng = np.random.default_rng(3)
    base = cv2.GaussianBlur(rng.random((512, 640, 3)).astype(np.float32), (0, 0), 3)
    rgb = np.clip(base * 255 * 3 - 255, 0, 255).astype(np.uint8)
    alpha = np.full((512, 640, 1), 255, np.uint8)
    alpha[128:256, 64:192] = 0  # whole 4x4 blocks of transparency
    _write_tiff(tmp_path / "rgba.tif", np.concatenate([rgb, alpha], axis=2), (2, 4))
    _write_tiff(tmp_path / "rgb.tif", rgb, (2, 4))
    _write_tiff(tmp_path / "gray.tif", rgb[..., 0], (2, 4))
    wide = (rgb[..., 1].astype(np.uint32) * 1000 + 7).astype(np.uint32)
    _write_tiff(tmp_path / "wide.tif", wide, (2, 4))
    rgba = open_image(tmp_path / "rgba.tif", lazy=True)
    lum, _ = reconcile_bands(open_image(tmp_path / "rgb.tif", lazy=True),
                             open_image(tmp_path / "gray.tif", lazy=True))
    views = {"alpha": (rgba.for_detection(), 1 / 255),
             "luminance": (lum.for_detection(), 1 / 255),
             "rescaled": (open_image(tmp_path / "wide.tif", lazy=True).for_detection(),
                          1 / 255)}
    for name, (view, tol) in views.items():
        assert view.file_levels is not None, name
        cache = OverviewCache(view)
        g, b = block_means(cache, 4)
        assert cache.overview_source(4)["source"] == "file levels", name
        g0, b0 = ov.read_block_means(view, 4)
        np.testing.assert_allclose(b, b0, atol=tol, err_msg=name)
    # the transparent blocks read as 0 both ways
    assert np.all(block_means(OverviewCache(views["alpha"][0]), 4)[0][32:64, 16:48] == 0)


def test_inconsistent_levels_ignored_with_a_reason(tmp_path, caplog):
    """An OME-TIFF's SubIFDs are its levels whatever their shapes (tifffile checks
    other TIFFs' levels itself): one of another aspect and one larger than the base are
    ignored, each with its reason logged and recorded, and the image read instead."""
    a = np.random.default_rng(1).integers(0, 255, (512, 512), dtype=np.uint8)

    def bad(x, n):  # another aspect, then one not smaller than the base
        return cv2.resize(x, (512 // n, 300 // n)) if n == 2 else np.vstack([x, x])

    _write_tiff(tmp_path / "bad.ome.tif", a, (2, 4), level_fn=bad, ome=True)
    view = open_image(tmp_path / "bad.ome.tif", lazy=True).for_detection()
    cache = OverviewCache(view)
    with caplog.at_level(logging.WARNING, logger="reblur.align.overviews"):
        g, _ = block_means(cache, 4)
    src = cache.overview_source(4)
    assert src["source"] == ov.FROM_FULL and cache.reads == 1
    assert len(src["ignored_levels"]) == 2
    assert "another aspect" in src["ignored_levels"][0]
    assert "not smaller" in src["ignored_levels"][1]
    assert sum("level ignored" in r.getMessage() for r in caplog.records) == 2
    np.testing.assert_allclose(g, _block_mean(a, 4) / 255, atol=1e-6)


def test_unreadable_level_falls_back_to_the_full_image(caplog):
    class Broken:
        shape, dtype = (128, 128), np.dtype(np.uint8)

        def __getitem__(self, key):
            raise ValueError("corrupt tile")

    class WithLevels(np.ndarray):
        pass

    a = np.arange(256 * 256, dtype=np.uint16).reshape(256, 256).view(WithLevels)
    a.file_levels = FileLevels(lambda: ([FileLevel(Broken(), (2.0, 2.0))], [], lambda: None),
                               "test", "broken.tif")
    cache = OverviewCache(a)
    with caplog.at_level(logging.WARNING, logger="reblur.align.overviews"):
        g, _ = block_means(cache, 4)
    assert cache.reads == 1 and "corrupt tile" in cache.overview_source(4)["levels_failed"]
    assert any("could not be read" in r.getMessage() for r in caplog.records)
    np.testing.assert_allclose(g, _block_mean(np.asarray(a), 4) / 65535, atol=1e-6)


def test_file_levels_pickle(pair_files):
    """The levels travel by path: pickled alone, or with the reader Dask workers get."""
    from reblur.dask_backend import portable

    view = open_image(pair_files / "ref_levels.tif", lazy=True).for_detection()
    sent = pickle.loads(pickle.dumps(portable(view, "reference")))
    cache = OverviewCache(sent)
    block_means(cache, 4)
    assert cache.reads == 0 and cache.overview_source(4)["source"] == "file levels"
    again = pickle.loads(pickle.dumps(view.file_levels))
    with again.open() as (levels, ignored):
        assert [lv.shape for lv in levels] == [(512, 512), (256, 256), (128, 128)]
        assert ignored == []
        np.testing.assert_array_equal(np.asarray(levels[1].array[...]),
                                      np.asarray(view.file_levels.opener()[0][1].array[...]))


# ---------------------------------------------------------------------------- full read
class _Chunked(_Counted):
    """A numpy array presented with ``chunks``, recording the row ranges read."""

    def __init__(self, a, chunks):
        super().__init__(a)
        self.chunks, self.rows = chunks, []

    def __getitem__(self, key):
        self.rows.append((key[0].start, key[0].stop))
        return super().__getitem__(key)


@pytest.mark.parametrize("threads", [1, 3])
def test_full_read_in_chunk_rows(monkeypatch, threads):
    """Bands of whole chunk rows (each chunk read once) even where blocks straddle them,
    in threads: the block means equal numpy's, for integers, floats and several bands."""
    monkeypatch.setattr(ov, "_THREADS", threads)
    monkeypatch.setattr(ov, "_STRIP_BYTES", 4096)
    rng = np.random.default_rng(2)
    for a in (rng.integers(0, 65535, (301, 222, 3), dtype=np.uint16),
              rng.random((301, 222)).astype(np.float32)):
        for chunk, k in ((7, 3), (16, 7), (64, 10), (5, 5)):
            c = _Chunked(a, (chunk, 64))
            g, b = ov.read_block_means(c, k)
            h = a.shape[0] // k
            norm = 65535.0 if a.dtype == np.uint16 else 1.0
            want = _block_mean(a, k) / norm
            np.testing.assert_allclose(b if a.ndim == 3 else g, want, rtol=1e-6, atol=1e-6)
            starts = sorted(r[0] for r in c.rows)
            assert all(s % chunk == 0 for s in starts), (chunk, k, c.rows)
            stops = sorted(r[1] for r in c.rows)
            assert all(s % chunk == 0 or s == h * k for s in stops)
            assert sum(r[1] - r[0] for r in c.rows) == h * k  # each row once


# ------------------------------------------------------- whole-image pass over TIFF chunks
def _tiff(path, a, **kw):
    tifffile.imwrite(path, a, compression="zlib", **kw)
    return open_image(path, lazy=True).array


@pytest.mark.parametrize("layout", [dict(tile=(64, 64)), dict(rowsperstrip=16)])
def test_tiff_block_means_from_the_chunks_equal_the_band_read(tmp_path, monkeypatch, layout):
    """A lazy TIFF's block means come from its decoded chunks (no window is read) and equal,
    bit for bit, those read band by band from the same file, and numpy's block mean: 300 x
    410 px (edge tiles padded in the file), blocks cut by the chunks' edges (k = 5, 10
    against 64 px tiles and 16-row strips) or not (k = 8, 16)."""
    from reblur.io import _Guarded  # the lazy file reader: its windows are counted

    rng = np.random.default_rng(5)
    window = _Guarded.__getitem__
    reads = []
    monkeypatch.setattr(_Guarded, "__getitem__",
                        lambda self, key: reads.append(key) or window(self, key))
    for a in (rng.integers(0, 65535, (300, 410, 3), dtype=np.uint16),
              rng.integers(0, 255, (300, 410), dtype=np.uint8),
              rng.integers(-32768, 32767, (300, 410), dtype=np.int16)):
        img = _tiff(tmp_path / "a.tif", a, **layout)
        assert img.chunk_reader is not None
        info = np.iinfo(a.dtype)
        for k in (5, 8, 10, 16):
            reads.clear()
            monkeypatch.setattr(ov, "_THREADS", 1 + k % 2)  # decoded on one thread, on two
            g, b = ov.read_block_means(img, k)
            assert reads == []  # from the chunks alone
            want = _block_mean(a, k) / info.max
            np.testing.assert_allclose(b if a.ndim == 3 else g, want, rtol=1e-6, atol=1e-7)
            reader, img.chunk_reader = img.chunk_reader, None
            g2, b2 = ov.read_block_means(img, k)  # band by band, through the windows
            img.chunk_reader = reader
            assert reads and np.array_equal(b, b2) and np.array_equal(g, g2), (a.dtype, k)


def test_tiff_chunks_corrupt_tile_is_one_input_error(tmp_path):
    """A tile whose compressed data is damaged fails the chunk pass with one InputError
    naming the file, as a window read of it does."""
    from reblur.io import InputError

    rng = np.random.default_rng(6)
    a = rng.integers(0, 255, (256, 256), dtype=np.uint8)
    path = tmp_path / "a.tif"
    tifffile.imwrite(path, a, tile=(64, 64), compression="zlib")
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        off, n = int(page.dataoffsets[5]), int(page.databytecounts[5])
    raw = bytearray(path.read_bytes())
    raw[off: off + n] = bytes(n)  # zeros: not a zlib stream
    path.write_bytes(bytes(raw))
    img = open_image(path, lazy=True).array
    # tile 5 of 4 across: rows 64-127, columns 64-127
    with pytest.raises(InputError, match=r"a\.tif: cannot decode the image data at rows "
                                         r"64-127, columns 64-127 \(.*\): the file is "
                                         r"corrupt or truncated"):
        ov.read_block_means(img, 8)


def test_tiff_chunks_of_a_file_changed_since_it_was_opened(tmp_path):
    """A file replaced by another image after it was opened is refused by the chunk pass,
    not read as the image it was."""
    from reblur.io import InputError

    path = tmp_path / "a.tif"
    tifffile.imwrite(path, np.zeros((256, 256), np.uint8), tile=(64, 64))
    img = open_image(path, lazy=True).array
    tifffile.imwrite(path, np.zeros((128, 256, 3), np.uint8), tile=(64, 64))
    with pytest.raises(InputError, match="changed since it was opened"):
        ov.read_block_means(img, 8)


def test_warped_reference_does_not_depend_on_opencv_threads():
    """A level's warped reference (read by the gradient blocks and the kernel polish) is
    OpenCV's one-thread warp whatever OpenCV's thread count: threaded, its bilinear warp
    rounds a few pixels with the number of threads, and on a host whose warp does that
    the 12 px test-bed shake came out 1e-9 apart in its homography on one core and on
    two (``python -m benchmarks.cores``)."""
    from reblur.align.overviews import Level

    rng = np.random.default_rng(41)
    ref = cv2.GaussianBlur(rng.random((700, 900)).astype(np.float32), (0, 0), 1.2)
    ones = np.ones(ref.shape, np.uint8)
    level = Level(ref, ref.copy(), 1.0, ones, ones)
    Hs = np.array([[1.01, 0.013, 3.7], [-0.008, 0.995, -2.3], [7e-6, -9e-7, 1.0]])
    saved = cv2.getNumThreads()
    try:
        cv2.setNumThreads(1)
        want = cv2.warpPerspective(ref, Hs, (900, 700), flags=cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_CONSTANT)
        for n in (2, 3, 4):
            cv2.setNumThreads(n)
            got, _ = level.warped_reference(Hs)
            np.testing.assert_array_equal(got, want)
            assert cv2.getNumThreads() == n  # put back
    finally:
        cv2.setNumThreads(saved)
