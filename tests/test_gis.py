"""GIS-ready outputs: Cloud-Optimised GeoTIFFs, change polygons, GeoPackage, and the
reblurred reference streamed to disk above the in-memory limit.

Every check is independent of the code under test: the COG layout is read from the TIFF's
own IFD and tile offsets (tifffile), overviews are compared with block maxima / means
computed here with numpy, polygons are rasterised back by GDAL and compared with the mask,
and each region's outline is compared with the union of its pixels' squares built here with
shapely from ``scipy.ndimage.label``.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
import tifffile
from rasterio import features
from rasterio.transform import from_origin
from scipy import ndimage
from shapely import box, union_all
from shapely.geometry import shape

import reblur
from reblur.gis import (
    ReblurredStore,
    change_features,
    quantize,
    region_features,
    region_shapes,
    write_cog,
    write_geojson,
    write_geopackage,
)
from reblur.io import write_geotiff
from reblur.report import find_regions, write_report
from reblur.result import ChangeResult, CropChoice, MotionEstimate

GEO = dict(crs=rasterio.crs.CRS.from_epsg(32631), transform=from_origin(1000.0, 2000.0, 2, 2))
EIGHT = np.ones((3, 3), bool)
CROSS = ndimage.generate_binary_structure(2, 1)


def _blobs(shape, seed: int, level: float = 0.6) -> np.ndarray:
    """A mask of smooth random blobs (holes, bays, diagonal contacts) plus single pixels."""
    import cv2

    rng = np.random.default_rng(seed)
    m = cv2.GaussianBlur(rng.random(shape), (0, 0), 4)
    m = m > np.quantile(m, level)
    ys, xs = rng.integers(0, shape[0], 40), rng.integers(0, shape[1], 40)
    m[ys, xs] = True
    return m


def _cog_layout(path) -> None:
    """The TIFF is laid out as a COG: tiled pages, every IFD before every tile, and the
    tiles of smaller overviews before those of larger ones (read from the file itself)."""
    with tifffile.TiffFile(path) as tif:
        pages = [p for p in tif.pages if not p.is_mask]
        assert all(p.is_tiled for p in pages)
        ifds = [p.offset for p in tif.pages]
        starts = [min(o for o in p.dataoffsets if o) for p in pages]
        assert max(ifds) < min(starts)
        sizes = [p.shape[0] * p.shape[1] for p in pages]
        assert sizes == sorted(sizes, reverse=True)  # full size, then each overview
        assert starts == sorted(starts, reverse=True)  # smallest overview's tiles first


def _block(a: np.ndarray, f: int, how) -> np.ndarray:
    """``f`` x ``f`` block reduction of a 2-D array (edge blocks partial), reference."""
    h, w = a.shape
    out = np.zeros((-(-h // f), -(-w // f)), np.float64)
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            out[i, j] = how(a[i * f:(i + 1) * f, j * f:(j + 1) * f])
    return out


# ---------------------------------------------------------------------------- COG
def test_cog_layout_overviews_georef_and_pixels(tmp_path):
    rng = np.random.default_rng(0)
    img = rng.integers(0, 65535, (300, 420, 3), dtype=np.uint16)
    img[:150, :200] = 1000  # a flat area: its averaged overview is exactly the value
    p = write_cog(tmp_path / "img.tif", img, GEO, block=64)
    _cog_layout(p)
    with rasterio.open(p) as src:
        assert src.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        assert src.block_shapes == [(64, 64)] * 3
        assert src.crs == GEO["crs"] and src.transform == GEO["transform"]
        ov = src.overviews(1)
        assert ov and ov[0] == 2 and all(b == 2 * a for a, b in zip(ov, ov[1:], strict=False))
        assert max(-(-300 // ov[-1]), -(-420 // ov[-1])) <= 64  # the last fits in a block
        np.testing.assert_array_equal(np.moveaxis(src.read(), 0, -1), img)
        half = src.read(1, out_shape=(150, 210))
    ref = _block(img[:, :, 0].astype(float), 2, np.mean)
    assert np.abs(half - ref).max() <= 1  # averaged 2 x 2
    assert (half[:75, :100] == 1000).all()


@pytest.mark.parametrize("overviews", ["average", "none"])
def test_cog_colour_interpretation(tmp_path, overviews):
    from rasterio.enums import ColorInterp as C

    rng = np.random.default_rng(7)
    cases = [((90, 70, 3), np.uint8, {}, (C.red, C.green, C.blue)),
             ((90, 70, 3), np.uint16, {}, (C.red, C.green, C.blue)),
             ((90, 70), np.uint8, {}, (C.gray,)),
             ((90, 70, 4), np.uint8, {"alpha": True}, (C.red, C.green, C.blue, C.alpha)),
             ((90, 70, 4), np.uint16, {}, (C.red, C.green, C.blue, C.undefined))]
    for k, (size, dtype, kw, expect) in enumerate(cases):
        img = rng.integers(0, 200, size).astype(dtype)
        p = write_cog(tmp_path / f"c{k}.tif", img, None, block=32, overviews=overviews, **kw)
        with rasterio.open(p) as src:
            assert src.colorinterp == expect, (size, dtype, kw)
            np.testing.assert_array_equal(src.read(), img.reshape(90, 70, -1).transpose(2, 0, 1))


def test_cog_masks_no_data_and_its_overviews_ignore_it(tmp_path):
    """Integer output: an internal mask (0 where ``nodata_mask`` or the source is NaN), and
    overview pixels the mean of the valid pixels only; float output: NaN, nodata NaN."""
    h, w = 96, 80
    src = np.full((h, w), 0.8, np.float32)  # 204 once quantized
    src[:, :41] = 0.0  # dark, where there is no data: must not darken the overviews
    nodata = np.zeros((h, w), bool)
    nodata[:, :41] = True
    src[5, 60] = np.nan  # NaN in the source: no data too
    valid = ~nodata & ~np.isnan(src)
    p = write_cog(tmp_path / "i.tif", src, None, block=16, nodata_mask=nodata,
                  convert=lambda b: quantize(b, np.uint8))
    _cog_layout(p)
    with rasterio.open(p) as f:
        assert f.mask_flag_enums[0] == [rasterio.enums.MaskFlags.per_dataset]
        np.testing.assert_array_equal(f.read_masks(1), valid.astype(np.uint8) * 255)
        np.testing.assert_array_equal(f.read(1)[valid], 204)
        assert f.overviews(1) == [2, 4, 8]
        for k in f.overviews(1):
            ov = f.read(1, out_shape=(-(-h // k), -(-w // k)))
            ovm = f.read_masks(1, out_shape=ov.shape)
            cover = _block(valid.astype(float), k, np.max) > 0
            np.testing.assert_array_equal(ovm > 0, cover, err_msg=str(k))
            # 41 is odd: column 20 at level 2 averages a no-data and a valid column
            np.testing.assert_array_equal(ov[cover], 204, err_msg=str(k))
    p = write_cog(tmp_path / "f.tif", src, None, block=16, nodata_mask=nodata)
    with rasterio.open(p) as f:
        assert np.isnan(f.nodata)
        a = f.read(1)
        np.testing.assert_array_equal(np.isnan(a), ~valid)
        ov = f.read(1, out_shape=(h // 2, w // 2))
        np.testing.assert_allclose(ov[~np.isnan(ov)], 0.8, rtol=1e-6)


@pytest.mark.parametrize("case", ["rgb16", "gray8-nodata", "float-nan", "mask-max"])
def test_first_overview_made_beside_the_full_size_equals_it_made_from_the_file(tmp_path,
                                                                              case):
    """The first overview level is reduced from each window as the full size is written;
    the reference is the level :func:`reblur.gis._write_level` makes by reading the written
    full-size file back (pixels and mask).  Odd sides, a chunked (zarr) source whose
    chunks are not a whole number of block pairs, several levels."""
    import zarr

    from reblur import gis

    rng = np.random.default_rng(17)
    h, w, block, how = 333, 457, 32, "average"
    mask = None
    if case == "rgb16":
        img = rng.integers(0, 65536, (h, w, 3)).astype(np.uint16)
    elif case == "gray8-nodata":
        img = rng.integers(0, 256, (h, w)).astype(np.uint8)
        mask = np.zeros((h, w), bool)
        mask[:101, :77] = True
        mask[200:, 300:] = True
    elif case == "float-nan":
        img = rng.random((h, w)).astype(np.float32)
        img[50:90, 10:333] = np.nan
    else:
        img = (rng.random((h, w)) < 0.02).astype(np.uint8) * 255
        how = "max"
    z = zarr.create_array(str(tmp_path / "z"), shape=img.shape, chunks=(48, 48) + img.shape[2:],
                          dtype=img.dtype, fill_value=0)
    z[...] = img
    shapes = gis._level_shapes(h, w, block)
    assert len(shapes) >= 3
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True):
        gis._write_level0(tmp_path / "l0.tif", z, img.shape, img.dtype, None, block, None,
                          nodata_mask=mask, level1=(tmp_path / "fused.tif", shapes[0], how))
        gis._write_level(tmp_path / "l0.tif", tmp_path / "read.tif", shapes[0], block, how)
        with rasterio.open(tmp_path / "fused.tif") as a, \
                rasterio.open(tmp_path / "read.tif") as b:
            assert (a.height, a.width) == (b.height, b.width) == shapes[0]
            np.testing.assert_array_equal(a.read(), b.read())
            np.testing.assert_array_equal(a.read_masks(), b.read_masks())
            if mask is not None:  # the mask is the valid pixels' cover, not all set
                assert not a.read_masks(1).all() and a.read_masks(1).any()


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.uint32])
@pytest.mark.parametrize("how", ["mean", "max"])
def test_overview_blocks_of_valid_pixels_equal_an_explicit_reduction(dtype, how):
    """An overview pixel of integer output (:func:`reblur.gis._reduce2_valid`) is the mean
    (rounded half to even) or the maximum of the valid pixels of its 2 x 2 block (an odd
    last row / column: a block of its own pixels), 0 and invalid where none is valid:
    block by block in exact rational arithmetic, extreme values included."""
    from fractions import Fraction

    from reblur.gis import _reduce2_valid

    rng = np.random.default_rng(58)
    top = int(np.iinfo(dtype).max)
    a = rng.integers(0, top, (2, 9, 7), dtype=dtype, endpoint=True)
    a[:, :4] = rng.choice([0, 1, top - 1, top], (2, 4, 7)).astype(dtype)
    valid = rng.random((9, 7)) > 0.35
    valid[:2, :2] = False  # a block without a valid pixel
    out, ok = _reduce2_valid(a, valid, how)
    assert out.dtype == a.dtype and out.shape == (2, 5, 4) and ok.shape == (5, 4)
    for i in range(5):
        for j in range(4):
            ys, xs = slice(2 * i, 2 * i + 2), slice(2 * j, 2 * j + 2)
            vals = [[int(v) for v in a[b, ys, xs][valid[ys, xs]]] for b in range(2)]
            assert ok[i, j] == bool(vals[0])
            for b in range(2):
                if not vals[b]:
                    want = 0
                elif how == "max":
                    want = max(vals[b])
                else:
                    want = round(Fraction(sum(vals[b]), len(vals[b])))  # half to even
                assert int(out[b, i, j]) == want, (b, i, j)


def test_cogs_written_from_two_threads_are_whole(tmp_path):
    """``write_report`` writes the masks' and the reblurred image's COGs from two threads:
    a masked uint8 COG and a max-overview mask COG written side by side must each read back
    as their source (without the lock, GDAL failed with "_tiffWriteProc: No such file or
    directory" every time at this size)."""
    from concurrent.futures import ThreadPoolExecutor

    n = 5000
    rng = np.random.default_rng(5)
    mask = rng.random((n, n)) > 0.99
    img = rng.integers(0, 256, (n, n), dtype=np.uint8)

    def masks():
        for name in ("m.tif", "u.tif"):
            write_cog(tmp_path / name, mask.astype(np.uint8), None, block=512,
                      overviews="max")

    def image():
        write_cog(tmp_path / "r.tif", img.astype(np.float32) / 255, None, block=512,
                  overviews="average", nodata_mask=mask,
                  convert=lambda b: quantize(b, np.uint8))

    with ThreadPoolExecutor(2) as ex:
        for fut in [ex.submit(masks), ex.submit(image)]:
            fut.result()
    for name in ("m.tif", "u.tif"):
        with rasterio.open(tmp_path / name) as f:
            np.testing.assert_array_equal(f.read(1), mask)
    with rasterio.open(tmp_path / "r.tif") as f:
        np.testing.assert_array_equal(f.read_masks(1) == 0, mask)
        np.testing.assert_array_equal(f.read(1)[~mask], img[~mask])


def test_cog_compressed_on_several_threads_is_the_same_file(tmp_path, monkeypatch):
    """GDAL compresses the tiles on the CPUs available (``NUM_THREADS``): each tile alone,
    so a masked 3-band 16-bit COG with overviews is byte for byte the one-thread file, and
    reads back as its source."""
    from reblur import gis

    rng = np.random.default_rng(9)
    h, w = 1500, 1300
    img = (rng.random((h, w, 3)) * 60000).astype(np.uint16)
    img[200:900, 300:1000] = 7  # a flat, highly compressible part beside the noise
    nodata = np.zeros((h, w), bool)
    nodata[:, :123] = True
    files = []
    for threads in (1, 2):
        monkeypatch.setattr(gis, "_gdal_threads", lambda t=threads: t)
        files.append(write_cog(tmp_path / f"t{threads}.tif", img, None, block=256,
                               overviews="average", nodata_mask=nodata))
    assert files[0].read_bytes() == files[1].read_bytes()
    with rasterio.open(files[1]) as f:
        assert f.overviews(1) == [2, 4, 8]
        a = np.moveaxis(f.read(), 0, -1)
        np.testing.assert_array_equal(a[~nodata], img[~nodata])
        np.testing.assert_array_equal(f.read_masks(1) == 0, nodata)


def test_cog_max_overviews_keep_every_change_pixel(tmp_path):
    m = np.zeros((500, 333), np.uint8)
    rng = np.random.default_rng(1)
    m[rng.integers(0, 500, 25), rng.integers(0, 333, 25)] = 255
    p = write_cog(tmp_path / "m.tif", m, None, block=32, overviews="max")
    _cog_layout(p)
    with rasterio.open(p) as src:
        assert src.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        assert src.crs is None
        np.testing.assert_array_equal(src.read(1), m)
        factors = src.overviews(1)
        assert factors == [2, 4, 8, 16]
        for f in factors:
            got = src.read(1, out_shape=(-(-500 // f), -(-333 // f)))
            np.testing.assert_array_equal(got, _block(m, f, np.max))


class _Recorder:
    """A lazy image that records the size of every window read from it."""

    def __init__(self, a):
        self.a, self.shape, self.dtype, self.reads = a, a.shape, a.dtype, []

    def __getitem__(self, key):
        out = self.a[key]
        self.reads.append(out.shape[0] * out.shape[1])
        return out


def test_cog_and_polygons_read_windows_never_the_whole_image(tmp_path):
    m = (_blobs((400, 300), 2) * 255).astype(np.uint8)
    src = _Recorder(m)
    write_cog(tmp_path / "m.tif", src, GEO, block=64, overviews="max")
    # windows of two blocks a side: the first overview's blocks are written whole beside
    # the full size's
    assert max(src.reads) <= (2 * 64) ** 2 < m.size
    src.reads.clear()
    fc = change_features(src, GEO, tile=100)
    assert max(src.reads) <= 100 * 100
    n = ndimage.label(m > 0, EIGHT)[1]
    assert len(fc["features"]) == n


def test_cog_refuses_bad_options(tmp_path):
    with pytest.raises(ValueError, match="multiple of 16"):
        write_cog(tmp_path / "a.tif", np.zeros((8, 8), np.uint8), block=100)
    with pytest.raises(ValueError, match="overviews must be one of"):
        write_cog(tmp_path / "a.tif", np.zeros((8, 8), np.uint8), overviews="cubic-ish")
    with pytest.raises(ValueError, match="convert bool masks"):
        write_cog(tmp_path / "a.tif", np.zeros((8, 8), bool))
    assert not list(tmp_path.iterdir())  # nothing left behind


# ---------------------------------------------------------------------------- polygons
def _exact_regions(mask: np.ndarray) -> list:
    """Each 8-connected region as the union of its pixels' squares (reference)."""
    lab, n = ndimage.label(mask, EIGHT)
    out = []
    for i in range(1, n + 1):
        ys, xs = np.nonzero(lab == i)
        out.append(union_all([box(x, y, x + 1, y + 1) for y, x in zip(ys, xs, strict=True)]))
    return out


def test_polygons_cover_the_mask_within_half_a_pixel(tmp_path):
    mask = _blobs((220, 260), 3)
    fc = change_features(mask, GEO, tile=48)  # many regions cross window borders
    geoms = [shape(f["geometry"]) for f in fc["features"]]
    assert fc["crs"]["properties"]["name"] == "urn:ogc:def:crs:EPSG::32631"
    assert all(g.is_valid for g in geoms)
    # one feature per 8-connected region, with its pixel count
    lab, n = ndimage.label(mask, EIGHT)
    assert len(geoms) == n > 20
    sizes = np.bincount(lab.ravel())[1:]
    assert sorted(f["properties"]["area_px"] for f in fc["features"]) == sorted(sizes.tolist())
    # rasterised back (pixel centres): differs from the mask only on pixels whose edge is
    # a region edge (centres 0.5 px from it); corner pixels (0.71 px) never differ
    back = features.rasterize([(g, 1) for g in geoms], out_shape=mask.shape,
                              transform=GEO["transform"]).astype(bool)
    edge = (mask & ~ndimage.binary_erosion(mask, CROSS, border_value=1)) | (
        ~mask & ndimage.binary_dilation(mask, CROSS))
    diff = back ^ mask
    assert not (diff & ~edge).any()
    assert diff.sum() <= 0.1 * edge.sum()
    # every outline within half a pixel of its region's pixel edges (CRS units: 2 m pixels)
    from shapely import affinity

    inv = ~GEO["transform"]
    ref = _exact_regions(mask)
    for g in geoms:
        px = affinity.affine_transform(g, [inv.a, inv.b, inv.d, inv.e, inv.c, inv.f])
        match = [r for r in ref if r.intersects(px)]
        assert len(match) == 1
        assert px.hausdorff_distance(match[0]) <= 0.5 + 1e-9
        assert px.symmetric_difference(match[0]).area <= 0.5 * match[0].length


def test_polygons_crossing_tile_borders_are_one_feature():
    mask = np.zeros((96, 128), bool)
    mask[20:44, 20:44] = True      # a ring around the corner of 4 windows of 32 px
    mask[26:38, 26:38] = False
    mask[30:32, 30:34] = True      # an island in the hole, crossing a border too
    mask[5, 60:128] = True         # a bar across three windows
    mask[60:80, 10] = True         # a U whose arms meet only in the next window
    mask[60:80, 14] = True
    mask[80:90, 10:15] = True
    mask[62, 62] = mask[63, 63] = mask[64, 64] = True  # diagonal across a window corner
    mask[65:67, 65:69] = True                            # ... touching a block at a corner
    whole = region_shapes(mask, tile=4096)
    tiled = region_shapes(mask, tile=32)
    assert len(whole) == len(tiled) == ndimage.label(mask, EIGHT)[1] == 5
    for a, b in zip(whole, tiled, strict=True):
        assert a.bbox == b.bbox and a.area == b.area
        assert a.geometry.equals(b.geometry) and b.geometry.is_valid
    ring = next(r for r in tiled if r.bbox == (20, 20, 44, 44))
    assert ring.area == 24 * 24 - 12 * 12 and len(ring.geometry.interiors) == 1
    assert ring.geometry.area == ring.area
    chain = next(r for r in tiled if r.bbox == (62, 62, 67, 69))
    assert chain.geometry.geom_type == "MultiPolygon" and chain.area == 3 + 8
    fc = change_features(mask, tile=32)
    assert len(fc["features"]) == 5 and "crs" not in fc


def test_polygons_carry_the_region_records():
    mask = np.zeros((64, 64), bool)
    mask[10:20, 10:30] = True
    mask[40:50, 40:45] = True
    regions = [
        dict(bbox=[40, 40, 50, 45], area=50, rank=1, score=3.5, polarity="darker",
             mean_contrast=40.0, contrast=0.16, mean_stat=9.0, max_stat=12.0, label=7),
        dict(bbox=[10, 10, 20, 30], area=200, rank=2, score=1.2, polarity="brighter"),
        dict(bbox=[0, 0, 1, 1], area=1, rank=3, score=9.9),  # matches no region
    ]
    fc = change_features(mask, dict(crs=None, transform=from_origin(0, 64, 0.5, 0.5)),
                         regions, tile=32)
    p = [f["properties"] for f in fc["features"]]
    assert [q["id"] for q in p] == [1, 2] and [q["rank"] for q in p] == [1, 2]
    assert p[0] == dict(id=1, area=12.5, area_px=50, rank=1, score=3.5, polarity="darker",
                        mean_contrast=40.0, contrast=0.16, mean_stat=9.0, max_stat=12.0)
    assert p[1]["polarity"] == "brighter" and p[1]["area"] == 50.0
    g = shape(fc["features"][1]["geometry"])
    assert g.bounds == (5.0, 54.0, 15.0, 59.0)  # cols 10:30, rows 10:20 at 0.5 m


def test_geojson_file_holds_the_feature_collection(tmp_path):
    mask = _blobs((90, 120), 8)
    regions = [dict(bbox=list(r.bbox), area=r.area, rank=1, score=float("nan"))
               for r in region_shapes(mask)[:1]]
    p = write_geojson(tmp_path / "c.geojson", region_features(mask, GEO, regions), GEO)
    got = json.loads(p.read_text())
    want = change_features(mask, GEO, regions)
    assert got["crs"] == want["crs"] and len(got["features"]) == len(want["features"]) > 5
    assert got["features"][0]["properties"]["score"] is None  # NaN is no JSON number
    for a, b in zip(got["features"], want["features"], strict=True):
        assert a["properties"].keys() == b["properties"].keys()
        assert shape(a["geometry"]).equals_exact(shape(b["geometry"]), 1e-6)
    assert [q.name for q in tmp_path.iterdir()] == ["c.geojson"]


# ---------------------------------------------------------------------------- GeoPackage
def test_geopackage_holds_the_features(tmp_path):
    pyogrio = pytest.importorskip("pyogrio", reason="the geo extra is not installed")
    mask = _blobs((120, 100), 4)
    regions = [dict(bbox=list(r.bbox), area=r.area, rank=k + 1, score=2.0 - k / 100,
                    polarity="darker") for k, r in enumerate(region_shapes(mask))][:-3]
    fc = change_features(mask, GEO, regions)
    p = write_geopackage(tmp_path / "c.gpkg", region_features(mask, GEO, regions), GEO)
    assert [q.name for q in tmp_path.iterdir()] == ["c.gpkg"]
    info = pyogrio.read_info(p)
    assert info["features"] == len(fc["features"])
    assert info["geometry_type"] == "MultiPolygon" and info["crs"] == "EPSG:32631"
    meta, _, geoms, cols = pyogrio.raw.read(p)
    names = list(meta["fields"])
    rank = cols[names.index("rank")]
    assert [f["properties"].get("rank") for f in fc["features"]][-3:] == [None] * 3
    assert rank.tolist()[:-3] == list(range(1, len(rank) - 2))
    area = cols[names.index("area_px")]
    assert area.tolist() == [f["properties"]["area_px"] for f in fc["features"]]
    import shapely

    for g, f in zip(shapely.from_wkb(geoms), fc["features"], strict=True):
        assert g.equals(shape(f["geometry"]))


# ---------------------------------------------------------------------------- report
def _result(h: int, w: int, reblurred) -> tuple[ChangeResult, np.ndarray]:
    from reblur.grid import PoseGrid

    change = _blobs((h, w), 5, 0.9)
    unknown = np.zeros((h, w), bool)
    unknown[:, :20] = True
    change &= ~unknown
    grid = PoseGrid.from_ranges((h, w), t_max=1, rz_max=0.0, rz_step=1.0)
    weights = np.zeros(grid.shape)
    weights[0, 1, 1] = 1.0
    res = ChangeResult(
        change=change, unknown=unknown, reblurred=reblurred,
        motion=MotionEstimate(weights, grid, boxes=[(0, 0, 64, 64)]), alignment=np.eye(3),
        crop=CropChoice(boxes=[(0, 0, 64, 64)], size=64), threshold=3.0,
    )
    return res, change


def test_report_writes_georeferenced_cogs_and_polygons(tmp_path, monkeypatch):
    import reblur.report as rep

    monkeypatch.setattr(rep, "COG_BLOCK", 64)
    rng = np.random.default_rng(6)
    obs = rng.integers(0, 255, (260, 300), dtype=np.uint8)
    write_geotiff(tmp_path / "obs.tif", obs, GEO)
    observed = reblur.io.open_image(tmp_path / "obs.tif")
    res, change = _result(260, 300, obs.astype(np.float32) / 255)
    out = tmp_path / "out"
    files, summary = write_report(res, out, observed=observed)
    assert {"changes.tif", "unknown.tif", "reblurred.tif", "changes.geojson"} <= set(files)
    # no temporaries left
    assert {p.name for p in out.iterdir()} == {v.split("/")[0] for v in files.values()}
    expect = {"changes.tif": change, "unknown.tif": res.unknown,
              "reblurred.tif": np.where(res.unknown, 0, obs)}
    for name, want in expect.items():
        _cog_layout(out / name)
        with rasterio.open(out / name) as src:
            assert src.overviews(1) == [2, 4, 8], name
            assert src.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
            assert src.crs == observed.geo["crs"] and src.transform == observed.geo["transform"]
            got = src.read(1)
            if name == "reblurred.tif":  # the pixels the reference does not cover: masked
                assert res.unknown.any() and not res.unknown.all()
                np.testing.assert_array_equal(src.read_masks(1) == 0, res.unknown)
        np.testing.assert_array_equal(got, want.astype(np.uint8) * (255 if want.dtype == bool
                                                                    else 1))
    gj = json.loads((out / "changes.geojson").read_text())
    assert len(gj["features"]) == ndimage.label(change, EIGHT)[1]
    if "changes.gpkg" not in files:
        assert any("changes.gpkg not written" in n for n in summary["notes"])


def test_region_ids_agree_in_the_geojson_and_the_viewer(tmp_path):
    obs = np.random.default_rng(8).integers(0, 255, (120, 150), dtype=np.uint8)
    write_geotiff(tmp_path / "obs.tif", obs, GEO)
    res, change = _result(120, 150, obs.astype(np.float32) / 255)
    res.regions = find_regions(change)  # as detect_changes lists them
    out = tmp_path / "out"
    write_report(res, out, observed=reblur.io.open_image(tmp_path / "obs.tif"))
    feats = json.loads((out / "changes.geojson").read_text())["features"]
    shown = json.loads((out / "viewer" / "regions.json").read_text())["regions"]
    n = ndimage.label(change, EIGHT)[1]
    assert len(feats) == n and len(shown) == min(n, 500) and n > 3
    ids = sorted(f["properties"]["id"] for f in feats)
    assert ids == list(range(1, n + 1))  # 1-based, like the ranks
    by_id = {f["properties"]["id"]: f for f in feats}
    for r in shown:  # the same region (same pixel count and rank) under the same id
        p = by_id[r["id"]]["properties"]
        assert p["rank"] == r["rank"] == r["id"] and p["area_px"] == r["area"]


def test_report_without_the_geo_extra_skips_the_geopackage(tmp_path, monkeypatch):
    import reblur.report as rep

    monkeypatch.setattr(rep, "geopackage_available", lambda: False)
    obs = np.zeros((96, 128), np.uint8)
    write_geotiff(tmp_path / "obs.tif", obs, GEO)
    res, _ = _result(96, 128, None)
    files, summary = write_report(res, tmp_path / "out",
                                  observed=reblur.io.open_image(tmp_path / "obs.tif"))
    assert "changes.gpkg" not in files and not (tmp_path / "out" / "changes.gpkg").exists()
    assert "changes.geojson" in files
    assert any("pip install 'reblur[geo]'" in n for n in summary["notes"])


def test_reblurred_store_round_trip(tmp_path):
    rng = np.random.default_rng(7)
    v = rng.random((70, 90, 3)).astype(np.float32)
    v[0, 0] = [-0.2, 1.3, np.nan]
    v[1, 0] = [np.inf, -np.inf, 0.5]
    s = ReblurredStore(tmp_path / "rb", v.shape, np.uint16, chunk=32)
    assert s.chunks == (32, 32, 3) and s.dtype == np.float32
    s[0:32, 0:64] = v[0:32, 0:64]
    s[32:70, 0:90] = v[32:70]
    s[0:32, 64:90] = v[0:32, 64:90]
    with np.errstate(over="ignore"):  # +inf, as float32's largest, times 65535: inf, clipped
        q = np.clip(np.rint(np.nan_to_num(v) * 65535), 0, 65535).astype(np.uint16)
    np.testing.assert_array_equal(np.asarray(s.stored[...]), q)
    np.testing.assert_array_equal(s[...], q.astype(np.float32) / 65535)
    np.testing.assert_array_equal(quantize(s[...], np.uint16), q)  # stable when re-written


# ------------------------------------------------------------ reblurred above the limit
@pytest.fixture(scope="module")
def geo_pair(levir_gray, tmp_path_factory):
    from reblur.simulate import make_pair

    d = tmp_path_factory.mktemp("pair")
    p = make_pair(levir_gray[:320, :384], rng=3, shake=dict(t_max=3.0, rz_max=0.3),
                  viewpoint=None, n_changes=3, moving=False, low_contrast=False)
    ref = np.clip(np.round(p.reference * 255), 0, 255).astype(np.uint8)
    obs = np.clip(np.round(p.observed * 255), 0, 255).astype(np.uint8)
    tifffile.imwrite(d / "ref.tif", ref, tile=(128, 128))
    write_geotiff(d / "obs.tif", obs, GEO)
    return d


def test_cli_streams_reblurred_to_disk_above_the_memory_limit(geo_pair, tmp_path,
                                                              monkeypatch):
    """The CLI keeps the reblurred reference in the observation's dtype: in memory (a
    numpy array of that dtype, not float32), or, with the in-memory limits lowered below
    the image (as for a > 64 MP input), written tile by tile into a store on disk.
    reblurred.tif is the same file either way, and the same as a run that kept the float32
    image (the library's default)."""
    from click.testing import CliRunner

    import reblur.cli as cli
    import reblur.gis as gis
    import reblur.pipeline as pl

    seen = {}
    real = reblur.detect_changes

    def spy(*a, **k):
        res = real(*a, **k)
        seen.update(k, result=res)
        return res

    def run(out):
        r = CliRunner().invoke(cli.main, [
            "detect", str(geo_pair / "ref.tif"), str(geo_pair / "obs.tif"), "--out", str(out),
            "--no-align", "--t-max", "4", "--rz-max", "0.5", "--tile-size", "128", "--quiet"])
        assert r.exit_code == 0, r.output
        return json.loads((out / "report.json").read_text())

    monkeypatch.setattr(reblur, "detect_changes", spy)
    plain = run(tmp_path / "plain")
    kept = seen["result"].reblurred
    assert isinstance(kept, ReblurredStore) and isinstance(kept.stored, np.ndarray)
    with rasterio.open(geo_pair / "obs.tif") as f:
        assert kept.stored.dtype == np.dtype(f.dtypes[0])
    # without the in-memory store: the float32 image detect_changes keeps by default
    store = gis.ReblurredStore
    with monkeypatch.context() as m:
        m.setattr(gis, "ReblurredStore",
                  lambda d, *a, **k: None if d is None else store(d, *a, **k))
        seen.clear()
        run(tmp_path / "float")
        assert isinstance(seen["result"].reblurred, np.ndarray)
        assert seen["result"].reblurred.dtype == np.float32
    monkeypatch.setattr(cli, "LARGE_MASK_PIXELS", 1000)
    monkeypatch.setattr(pl, "KEEP_REBLURRED_PIXELS", 1000)
    seen.clear()
    out = tmp_path / "streamed"
    streamed = run(out)
    assert isinstance(seen["reblurred_out"], ReblurredStore)
    assert not isinstance(seen["reblurred_out"].stored, np.ndarray)  # on disk
    assert seen["result"].reblurred is seen["reblurred_out"]  # never a numpy copy
    assert "reblurred.tif" in streamed["files"]
    assert not any("not written" in n and "reblurred" in n for n in streamed["notes"])
    assert not list(out.glob(".reblur-*"))  # the work store is gone
    with rasterio.open(tmp_path / "plain" / "reblurred.tif") as a, \
            rasterio.open(out / "reblurred.tif") as b, \
            rasterio.open(tmp_path / "float" / "reblurred.tif") as c:
        assert b.crs == GEO["crs"] and b.transform == GEO["transform"]
        assert b.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        np.testing.assert_array_equal(a.read(), b.read())
        np.testing.assert_array_equal(c.read(), b.read())
        np.testing.assert_array_equal(c.read_masks(), b.read_masks())
    assert plain["changes"]["changed_px"] == streamed["changes"]["changed_px"] > 0
