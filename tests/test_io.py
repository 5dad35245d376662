"""reblur.io: reading every supported layout, refusing bad inputs, atomic writers."""

from __future__ import annotations

import json
import os
import struct
import zlib

import cv2
import imagecodecs
import numpy as np
import pytest
import tifffile

from reblur.io import (
    LUMINANCE,
    Image,
    InputError,
    LazyBands,
    atomic_path,
    check_finite,
    encode_png,
    open_image,
    read_mask,
    reconcile_bands,
    write_geotiff,
    write_json,
    write_png,
    write_tiff,
)


@pytest.fixture
def rng():
    return np.random.default_rng(0)


def _rgb16(rng, h=300, w=400):
    return (rng.random((h, w, 3)) * 65535).astype(np.uint16)


# ---------------------------------------------------------------------------- reading
def test_png_uint8_gray_rgb_rgba(tmp_path, rng):
    rgba = (rng.random((64, 80, 4)) * 255).astype(np.uint8)
    for arr, name in ((rgba[..., 0], "g.png"), (rgba[..., :3], "c.png"), (rgba, "a.png")):
        (tmp_path / name).write_bytes(imagecodecs.png_encode(np.ascontiguousarray(arr)))
    g = open_image(tmp_path / "g.png")
    assert g.shape == (64, 80) and g.bands == 1 and g.dtype == np.uint8
    np.testing.assert_array_equal(g.array, rgba[..., 0])
    c = open_image(tmp_path / "c.png")
    np.testing.assert_array_equal(c.array, rgba[..., :3])  # RGB order, not OpenCV's BGR
    a = open_image(tmp_path / "a.png")
    assert a.shape == (64, 80, 3) and a.nodata_source == "alpha band"
    np.testing.assert_array_equal(a.array, rgba[..., :3])
    # the alpha band is the validity: transparent (0) pixels hold no data
    np.testing.assert_array_equal(np.asarray(a.valid), rgba[..., 3] > 0)
    assert not a.lazy and a.format == "png"
    opaque = rgba.copy()
    opaque[..., 3] = 255
    (tmp_path / "o.png").write_bytes(imagecodecs.png_encode(opaque))
    o = open_image(tmp_path / "o.png")
    assert o.valid is None and any("all opaque" in n for n in o.notes)


def test_masked_view_is_nan_where_there_is_no_data(tmp_path):
    from reblur.io import MaskedView, NodataMask

    a = np.arange(60, dtype=np.uint16).reshape(3, 4, 5) * 1000
    a[1, 2] = 7  # every band at the nodata value: no data
    a[2, 3, 0] = 7  # one band only: data
    v = MaskedView(a, NodataMask(a, 7))
    out = v[...]
    assert out.dtype == np.float32 and np.isnan(out[1, 2]).all()
    assert np.isfinite(np.delete(out.reshape(12, 5), 6, axis=0)).all()
    np.testing.assert_allclose(out[0, 1], a[0, 1] / 65535, rtol=1e-6)
    np.testing.assert_allclose(v[1:3, 2:4][0, 0], np.nan)  # windows keep the mask aligned


def test_png16_is_not_clipped(tmp_path, rng):
    a = _rgb16(rng, 40, 50)
    write_png(tmp_path / "x.png", a)
    img = open_image(tmp_path / "x.png")
    assert img.dtype == np.uint16 and img.array.max() > 255
    np.testing.assert_array_equal(img.array, a)


def test_jpeg(tmp_path, rng):
    yy, xx = np.mgrid[:48, :64]
    a = np.stack([yy * 5, xx * 4, 255 - xx * 3], axis=-1).astype(np.uint8)  # smooth
    (tmp_path / "x.jpg").write_bytes(imagecodecs.jpeg8_encode(a, level=95))
    img = open_image(tmp_path / "x.jpg")
    assert img.format == "jpeg" and img.shape == (48, 64, 3) and img.dtype == np.uint8
    assert np.abs(img.array.astype(int) - a).mean() < 3


@pytest.mark.parametrize("layout", ["tiled", "striped", "planar", "bigtiff"])
@pytest.mark.parametrize("lazy", [False, True])
def test_tiff_layouts_eager_and_lazy(tmp_path, rng, layout, lazy):
    a = _rgb16(rng)
    p = tmp_path / "x.tif"
    if layout == "tiled":
        tifffile.imwrite(p, a, tile=(64, 64), compression="zstd")
    elif layout == "striped":
        tifffile.imwrite(p, a, rowsperstrip=16, compression="deflate")
    elif layout == "planar":
        tifffile.imwrite(p, np.moveaxis(a, -1, 0), photometric="rgb", planarconfig="separate",
                         rowsperstrip=32)
    else:
        tifffile.imwrite(p, a, bigtiff=True, tile=(128, 128))
    img = open_image(p, lazy=lazy)
    assert img.shape == (300, 400, 3) and img.dtype == np.uint16 and img.lazy is lazy
    assert isinstance(img.array, np.ndarray) is (not lazy)
    np.testing.assert_array_equal(np.asarray(img.array[...]), a)
    np.testing.assert_array_equal(img.array[17:99, 250:333], a[17:99, 250:333])
    np.testing.assert_array_equal(img.array[5, 7], a[5, 7])
    np.testing.assert_array_equal(img.array[::50, ::100], a[::50, ::100])
    img.close()


def test_tiff_float32_gray_and_alpha(tmp_path, rng):
    f = rng.random((100, 90)).astype(np.float32)
    tifffile.imwrite(tmp_path / "f.tif", f)
    img = open_image(tmp_path / "f.tif")
    assert img.dtype == np.float32 and img.shape == (100, 90)
    np.testing.assert_array_equal(img.array, f)
    rgba = (rng.random((64, 64, 4)) * 255).astype(np.uint8)
    tifffile.imwrite(tmp_path / "a.tif", rgba, photometric="rgb", extrasamples=["unassalpha"])
    for lazy in (False, True):
        img = open_image(tmp_path / "a.tif", lazy=lazy)
        assert img.shape == (64, 64, 3)
        np.testing.assert_array_equal(np.asarray(img.array[...]), rgba[..., :3])


def test_multiband_tiff_kept(tmp_path, rng):
    a = (rng.random((64, 70, 5)) * 1000).astype(np.uint16)
    tifffile.imwrite(tmp_path / "m.tif", a, photometric="minisblack", planarconfig="contig")
    img = open_image(tmp_path / "m.tif")
    assert img.bands == 5
    np.testing.assert_array_equal(img.array, a)


def test_zarr_store_is_lazy(tmp_path, rng):
    zarr = pytest.importorskip("zarr")
    a = (rng.random((200, 150, 3)) * 255).astype(np.uint8)
    z = zarr.create_array(str(tmp_path / "x.zarr"), shape=a.shape, chunks=(64, 64, 3),
                          dtype=a.dtype)
    z[...] = a
    img = open_image(tmp_path / "x.zarr", lazy=True)
    assert img.lazy and img.format == "zarr" and img.shape == a.shape
    np.testing.assert_array_equal(img.array[10:70, 20:30], a[10:70, 20:30])
    eager = open_image(tmp_path / "x.zarr")
    assert not eager.lazy
    np.testing.assert_array_equal(eager.array, a)


def test_geotiff_roundtrip_keeps_georeferencing(tmp_path, rng):
    rasterio = pytest.importorskip("rasterio")
    from rasterio.transform import from_origin

    a = (rng.random((96, 128)) * 255).astype(np.uint8)
    geo = dict(crs=rasterio.crs.CRS.from_epsg(32633),
               transform=from_origin(500000.0, 4000000.0, 0.5, 0.5))
    write_geotiff(tmp_path / "g.tif", a, geo, tile=64)
    img = open_image(tmp_path / "g.tif")
    np.testing.assert_array_equal(img.array, a)
    assert img.geo["crs"].to_epsg() == 32633
    assert tuple(img.geo["transform"])[:6] == (0.5, 0.0, 500000.0, 0.0, -0.5, 4000000.0)
    info = img.info()
    assert info["geo"]["crs"] == "EPSG:32633"
    plain = tmp_path / "p.tif"
    tifffile.imwrite(plain, a)
    assert open_image(plain).geo is None


# ---------------------------------------------------------------------------- refusing
def _png_header_only(w: int, h: int) -> bytes:
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    chunk = struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    return b"\x89PNG\r\n\x1a\n" + chunk


def test_missing_empty_and_not_an_image(tmp_path):
    with pytest.raises(InputError, match=r"nope\.png: no such file"):
        open_image(tmp_path / "nope.png")
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(InputError, match="empty"):
        open_image(tmp_path / "empty.png")
    (tmp_path / "t.png").write_text("hello, I am text\n" * 10)
    with pytest.raises(InputError, match="not an image"):
        open_image(tmp_path / "t.png")
    (tmp_path / "d").mkdir()
    with pytest.raises(InputError, match="directory"):
        open_image(tmp_path / "d")


def test_truncated_files(tmp_path, rng):
    a = (rng.random((64, 64, 3)) * 255).astype(np.uint8)
    png = imagecodecs.png_encode(a)
    jpg = imagecodecs.jpeg8_encode(a)
    (tmp_path / "t.png").write_bytes(png[: len(png) // 2])
    (tmp_path / "t.jpg").write_bytes(jpg[: len(jpg) // 2])
    tifffile.imwrite(tmp_path / "full.tif", a, compression="deflate", rowsperstrip=8)
    data = (tmp_path / "full.tif").read_bytes()
    (tmp_path / "t.tif").write_bytes(data[: len(data) // 2])
    for name in ("t.png", "t.jpg", "t.tif"):
        with pytest.raises(InputError, match=r"truncated|cannot|not a"):
            open_image(tmp_path / name)


def test_too_small_and_empty(tmp_path):
    write_png(tmp_path / "one.png", np.zeros((1, 1), np.uint8))
    with pytest.raises(InputError, match=r"1x1 pixels; at least 32x32"):
        open_image(tmp_path / "one.png")
    write_png(tmp_path / "thin.png", np.zeros((500, 8), np.uint8))
    with pytest.raises(InputError, match="at least"):
        open_image(tmp_path / "thin.png")
    with pytest.warns(UserWarning):
        tifffile.imwrite(tmp_path / "zero.tif", np.zeros((0, 0), np.uint8))
    with pytest.raises(InputError, match="zero.tif: image is empty"):
        open_image(tmp_path / "zero.tif")


def test_max_pixels_checked_from_header(tmp_path):
    # a header claiming 100000 x 100000 pixels: refused before any decoding
    (tmp_path / "bomb.png").write_bytes(_png_header_only(100_000, 100_000))
    with pytest.raises(InputError, match=r"10,000,000,000 pixels .* limit of 4,000,000,000"):
        open_image(tmp_path / "bomb.png")
    write_png(tmp_path / "ok.png", np.zeros((64, 64), np.uint8))
    with pytest.raises(InputError, match="--max-pixels"):
        open_image(tmp_path / "ok.png", max_pixels=1000)
    assert open_image(tmp_path / "ok.png", max_pixels=4096).shape == (64, 64)


@pytest.mark.parametrize("lazy", [False, True])
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nonfinite_refused_streaming(tmp_path, rng, lazy, bad):
    f = rng.random((400, 100)).astype(np.float32)
    f[333, 44] = bad
    tifffile.imwrite(tmp_path / "f.tif", f, tile=(64, 64))
    kind = "NaN" if np.isnan(bad) else "Inf"
    with pytest.raises(InputError, match=rf"{kind} pixels \(first at row 333, column 44\)"):
        open_image(tmp_path / "f.tif", lazy=lazy)
    # the lazy check reads bands of rows, never the whole image at once
    reads = []

    class Spy:
        shape, dtype, chunks = f.shape, f.dtype, (64, 64)

        def __getitem__(self, key):
            reads.append(key)
            return f[key]

    import reblur.io as rio

    old = rio._row_bands
    rio._row_bands = lambda a, target_bytes=64 * 2**20: old(a, target_bytes=64 * 100 * 4)
    try:
        with pytest.raises(InputError):
            check_finite(Spy(), "spy")
    finally:
        rio._row_bands = old
    assert len(reads) == 333 // 64 + 1 and all(r.stop - r.start <= 64 for r in reads)


# ---------------------------------------------------------------------------- bands
def test_reconcile_bands(tmp_path, rng):
    rgb = (rng.random((64, 64, 3)) * 255).astype(np.uint8)
    gray = rgb[..., 1].copy()
    write_png(tmp_path / "rgb.png", rgb)
    write_png(tmp_path / "gray.png", gray)
    tifffile.imwrite(tmp_path / "rgb.tif", rgb, tile=(32, 32))
    r, o = reconcile_bands(open_image(tmp_path / "rgb.png"), open_image(tmp_path / "gray.png"))
    assert r.shape == (64, 64) and o.shape == (64, 64) and r.dtype == np.uint8
    expect = np.rint(rgb.astype(np.float32) @ np.asarray(LUMINANCE, np.float32)).astype(np.uint8)
    np.testing.assert_array_equal(r.array, expect)
    assert "converted RGB to gray luminance" in r.notes
    o2, r2 = reconcile_bands(open_image(tmp_path / "gray.png"),
                             open_image(tmp_path / "rgb.tif", lazy=True))
    assert isinstance(r2.array, LazyBands) and r2.shape == (64, 64)
    np.testing.assert_array_equal(r2.array[10:20, 3:40], expect[10:20, 3:40])
    same = open_image(tmp_path / "rgb.png")
    assert reconcile_bands(same, same) == (same, same)
    five = Image.from_array(np.zeros((64, 64, 5), np.uint16), "five.tif")
    with pytest.raises(InputError, match=r"five.tif has 5 bands and .*rgb.png has 3"):
        reconcile_bands(five, same)


def test_lazybands_indexing(rng):
    a = (rng.random((50, 60, 4)) * 255).astype(np.uint8)
    v = LazyBands(a, bands=(0, 1, 2))
    assert v.shape == (50, 60, 3) and v.ndim == 3
    np.testing.assert_array_equal(v[...], a[..., :3])
    np.testing.assert_array_equal(v[-1, -2], a[-1, -2, :3])
    np.testing.assert_array_equal(v[3:9, 10], a[3:9, 10, :3])
    np.testing.assert_array_equal(v[3:9, 10:12, 1], a[3:9, 10:12, 1])
    np.testing.assert_array_equal(np.asarray(v), a[..., :3])
    cf = LazyBands(np.moveaxis(a, -1, 0), channel_first=True)
    np.testing.assert_array_equal(cf[5:7, 8:30], a[5:7, 8:30])
    with pytest.raises(IndexError):
        v[100, 0]


def test_read_mask(tmp_path):
    m = np.zeros((40, 50), np.uint8)
    m[5:9, 7:20] = 255
    write_png(tmp_path / "m.png", m)
    got = read_mask(tmp_path / "m.png", (40, 50))
    assert got.dtype == bool and got.sum() == 4 * 13
    with pytest.raises(InputError, match=r"truth mask is 50x40 pixels, the image .* 60x40"):
        read_mask(tmp_path / "m.png", (40, 60), what="truth mask")


# ---------------------------------------------------------------------------- writing
def test_atomic_path_success_and_failure(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("boom")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]  # no temp left
    with atomic_path(target) as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".txt" and tmp != target
        tmp.write_text("new")
    assert target.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]
    assert oct(target.stat().st_mode & 0o777) != oct(0o600)  # not mkstemp's private mode


def test_write_png_is_deterministic(tmp_path, rng):
    m = rng.random((100, 120)) > 0.7
    write_png(tmp_path / "a.png", m)
    write_png(tmp_path / "b.png", m.copy())
    assert (tmp_path / "a.png").read_bytes() == (tmp_path / "b.png").read_bytes()
    back = open_image(tmp_path / "a.png").array
    np.testing.assert_array_equal(back, m.astype(np.uint8) * 255)
    with pytest.raises(ValueError, match="uint8 or uint16"):
        write_png(tmp_path / "c.png", m.astype(np.float32))


def _png_rows(data: bytes) -> tuple[dict, list[bytes]]:
    """A PNG's header fields and its scanlines (each with its filter-type byte), parsed with
    struct and zlib alone."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, hdr = 8, b"", {}
    while pos < len(data):
        n, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + n]
        if kind == b"IHDR":
            w, h, depth, colour = struct.unpack(">IIBB", body[:10])
            hdr = dict(width=w, height=h, depth=depth, colour=colour)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    raw = zlib.decompress(idat)
    channels = {0: 1, 2: 3, 4: 2, 6: 4}[hdr["colour"]]
    stride = 1 + hdr["width"] * channels * hdr["depth"] // 8
    assert len(raw) == stride * hdr["height"]
    return hdr, [raw[i:i + stride] for i in range(0, len(raw), stride)]


def _unfilter_sub(row: bytes, bpp: int) -> np.ndarray:
    """A PNG scanline under the Sub filter (type 1) decoded by the PNG specification:
    each byte plus the decoded byte ``bpp`` before it, modulo 256."""
    f = np.frombuffer(row[1:], np.uint8).reshape(-1, bpp).astype(np.int64)
    return (np.cumsum(f, axis=0) % 256).astype(np.uint8).ravel()


def test_flat_png_holds_the_same_pixels_compactly(tmp_path, rng):
    """``flat`` (masks) keeps the pixels, type and bands.  A gray mask's rows carry no
    filter (type 0: the bytes are the pixels); a colour mask's rows the Sub filter (type 1),
    without which a flat RGBA colour repeats with a 4-byte period that run-length deflate
    cannot code.  The default encoding filters the same images differently."""
    m = np.zeros((300, 200), bool)
    m[40:120, 30:90] = True
    m[200:260, 150:190] = rng.random((60, 40)) > 0.5
    rgba = np.zeros((64, 80, 4), np.uint8)
    rgba[..., :3] = (255, 40, 40)
    rgba[10:30, 5:60, 3] = 115
    for name, a, want, kind in (("m", m, m.astype(np.uint8) * 255, 0), ("rgba", rgba, rgba, 1)):
        write_png(tmp_path / f"{name}_flat.png", a, flat=True)
        write_png(tmp_path / f"{name}.png", a)
        hdr, rows = _png_rows((tmp_path / f"{name}_flat.png").read_bytes())
        assert (hdr["depth"], hdr["colour"]) == ((8, 0) if name == "m" else (8, 6))
        assert {r[0] for r in rows} == {kind}, name
        assert {r[0] for r in _png_rows((tmp_path / f"{name}.png").read_bytes())[1]} != {kind}
        # the rows, decoded by the specification, are the pixels
        bpp = 1 if name == "m" else 4
        got = np.concatenate([_unfilter_sub(r, bpp) if kind else np.frombuffer(r[1:], np.uint8)
                              for r in rows]).reshape(want.shape)
        np.testing.assert_array_equal(got, want)
    # and a reader decodes the mask as before: 0 / 255 in uint8
    back = open_image(tmp_path / "m_flat.png").array
    assert back.dtype == np.uint8
    np.testing.assert_array_equal(back, m.astype(np.uint8) * 255)
    # a blank 512 px RGBA tile (one colour, transparent: the viewer's empty mask tile) holds
    # 1 MB of pixels; the row filters and deflate make them a few KB, flat or not
    blank = np.empty((512, 512, 4), np.uint8)
    blank[:] = (40, 40, 255, 0)
    for flat in (False, True):
        data = encode_png(blank, flat=flat)
        assert len(data) < 8192, (flat, len(data))
        np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(data, np.uint8),
                                                   cv2.IMREAD_UNCHANGED)[..., [2, 1, 0, 3]], blank)


def test_png_of_colour_images_keeps_the_channel_order():
    # RGB and RGBA, 8 and 16 bits: decoded by OpenCV (BGR / BGRA) and swapped back
    rng = np.random.default_rng(4)
    for dt, top in ((np.uint8, 256), (np.uint16, 65536)):
        for bands, back in ((3, [2, 1, 0]), (4, [2, 1, 0, 3])):
            a = rng.integers(0, top, (37, 53, bands)).astype(dt)
            for view in (a, a[::-1, ::2]):  # strided input too
                data = encode_png(view)
                got = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
                assert got.dtype == dt
                np.testing.assert_array_equal(got[..., back], view)


def test_write_tiff_from_tile_iterator(tmp_path, rng):
    h, w, t = 300, 250, 64
    full = (rng.random((h, w)) > 0.5).astype(np.uint8) * 255

    def tiles():
        for y in range(0, h, t):
            for x in range(0, w, t):
                blk = np.zeros((t, t), np.uint8)
                part = full[y : y + t, x : x + t]
                blk[: part.shape[0], : part.shape[1]] = part
                yield blk

    p = write_tiff(tmp_path / "m.tif", tiles(), shape=(h, w), dtype=np.uint8, tile=t,
                   compression="zstd")
    with tifffile.TiffFile(p) as tif:
        page = tif.pages[0]
        assert page.is_tiled and page.tilelength == t and not tif.is_bigtiff
        assert page.compression == 50000  # zstd
        np.testing.assert_array_equal(tif.asarray(), full)
    write_tiff(tmp_path / "b.tif", full, bigtiff=True, tile=64)
    with tifffile.TiffFile(tmp_path / "b.tif") as tif:
        assert tif.is_bigtiff
        np.testing.assert_array_equal(tif.asarray(), full)
    with pytest.raises(ValueError, match="shape= and dtype="):
        write_tiff(tmp_path / "x.tif", tiles())


def test_write_tiff_lazy_source_with_convert(tmp_path, rng):
    a = rng.random((130, 140, 3)).astype(np.float32)
    src = LazyBands(a)  # not a numpy array: read tile by tile
    write_tiff(tmp_path / "c.tif", src, tile=32,
               convert=lambda b: np.rint(b * 255).astype(np.uint8))
    back = tifffile.imread(tmp_path / "c.tif")
    np.testing.assert_array_equal(back, np.rint(a * 255).astype(np.uint8))
    write_tiff(tmp_path / "s.tif", a, tiled=False)
    with tifffile.TiffFile(tmp_path / "s.tif") as tif:
        assert not tif.pages[0].is_tiled
        np.testing.assert_array_equal(tif.asarray(), a)


def test_write_json(tmp_path):
    write_json(tmp_path / "j.json", dict(a=np.float32(1.5), b=float("nan"), c=np.arange(3),
                                         d=(1, 2), e=tmp_path, f=np.bool_(True)))
    d = json.loads((tmp_path / "j.json").read_text())
    assert d == dict(a=1.5, b=None, c=[0, 1, 2], d=[1, 2], e=str(tmp_path), f=True)
    assert not [p for p in os.listdir(tmp_path) if p != "j.json"]


class _Counting:
    """A chunked array-like that counts the pixels it hands out."""

    def __init__(self, a, chunks):
        self.a, self.chunks, self.read_px = a, chunks, 0
        self.shape, self.dtype = a.shape, a.dtype

    def __getitem__(self, key):
        out = np.asarray(self.a[key])
        self.read_px += out.shape[0] * (out.shape[1] if out.ndim > 1 else 1)
        return out


@pytest.mark.parametrize("bands", [0, 3])
def test_chunk_cache_windows_equal_direct_reads(bands):
    """Every window assembled from kept chunks equals slicing the array itself (inside,
    across chunk edges, at the image's edges, with a band index); overlapping windows
    reuse chunks; the kept bytes never exceed the bound; pickling drops the chunks."""
    import pickle

    from reblur.io import ChunkCache

    rng = np.random.default_rng(7)
    shape = (300, 410) + ((bands,) if bands else ())
    a = rng.integers(0, 65535, size=shape, dtype=np.uint16)
    src = _Counting(a, (64, 96))
    one_chunk = 64 * 96 * a.itemsize * (bands or 1)
    cache = ChunkCache(src, max_bytes=12 * one_chunk)
    assert cache.shape == a.shape and cache.dtype == a.dtype and cache.chunks == (64, 96)
    for _ in range(200):
        y0, x0 = int(rng.integers(0, 300)), int(rng.integers(0, 410))
        y1, x1 = int(rng.integers(y0, 301)), int(rng.integers(x0, 411))
        np.testing.assert_array_equal(cache[y0:y1, x0:x1], a[y0:y1, x0:x1])
        assert cache._bytes <= 12 * one_chunk
    np.testing.assert_array_equal(cache[:, 5:], a[:, 5:])
    np.testing.assert_array_equal(cache[-70:, :-3], a[-70:, :-3])
    if bands:
        np.testing.assert_array_equal(cache[10:90, 20:200, 1], a[10:90, 20:200, 1])
    np.testing.assert_array_equal(cache[3], a[3])  # not a window: read directly
    # two overlapping windows: the second reads only the chunks the first did not cover
    fresh = ChunkCache(_Counting(a, (64, 96)), max_bytes=100 * one_chunk)
    fresh[0:128, 0:192]
    n0 = fresh.array.read_px
    fresh[64:128, 96:288]
    assert n0 == 128 * 192 and fresh.array.read_px - n0 == 64 * 96
    again = pickle.loads(pickle.dumps(fresh))
    assert len(again._kept) == 0 and again.max_bytes == fresh.max_bytes
    np.testing.assert_array_equal(again[50:70, 80:100], a[50:70, 80:100])


def test_chunk_cached_wraps_only_tiled_on_disk_arrays():
    from reblur.io import ChunkCache, chunk_cached

    a = np.zeros((4000, 3000), np.uint8)
    assert chunk_cached(a, 1024, 80) is a  # in memory
    tiled = _Counting(a, (512, 512))
    c = chunk_cached(tiled, 1024, 80)
    assert isinstance(c, ChunkCache) and c.chunks == (512, 512)
    # a padded tile row and two chunk rows across the image, within 64..256 MB
    assert c.max_bytes == 64 * 2**20  # (1024 + 160 + 1024) * 3000 bytes is below the floor
    big = _Counting(np.zeros((10, 200_000), np.uint16), (256, 256))
    assert chunk_cached(big, 1024, 80).max_bytes == 256 * 2**20
    wide = _Counting(np.zeros((10, 20_000, 3), np.uint16), (512, 512))
    assert chunk_cached(wide, 1024, 80).max_bytes == (1024 + 160 + 1024) * 20_000 * 6
    assert chunk_cached(c, 1024, 80) is c  # already cached
    rows = _Counting(a, (16, 3000))  # a striped file: chunks are row strips
    assert chunk_cached(rows, 1024, 80) is rows


@pytest.mark.parametrize(("tile", "halo", "chunk"), [(128, 16, 64), (128, 40, 48), (96, 8, 64)])
def test_sweep_rows_read_every_chunk_once_in_a_raster_tile_pass(tile, halo, chunk):
    """Padded tiles read in raster order through a cache of ``sweep_rows`` image rows
    decode every chunk exactly once (counted pixels handed out by the store); a cache one
    chunk row smaller on each side decodes some twice, so the bound is not loose."""
    from reblur.decide import tile_boxes
    from reblur.io import ChunkCache, sweep_rows

    a = np.random.default_rng(3).integers(0, 255, (700, 960), dtype=np.uint8)
    reads = []
    for rows in (sweep_rows(tile, halo, chunk), tile + 2 * halo):
        src = _Counting(a, (chunk, chunk))
        cache = ChunkCache(src, max_bytes=rows * a.shape[1])
        for (y0, x0, h, w), _ in tile_boxes(a.shape, tile, halo):
            np.testing.assert_array_equal(cache[y0 : y0 + h, x0 : x0 + w],
                                          a[y0 : y0 + h, x0 : x0 + w])
        reads.append(src.read_px)
    assert reads[0] == a.size
    assert reads[1] > a.size


def test_mask_bands_and_their_png_of_zarr_and_numpy_masks(tmp_path, rng):
    """The report's PNG masks (``changes.png``, ``unknown.png``): ``change & ~unknown`` as
    0 / 255 uint8 bands, from zarr masks on disk (bands of their chunks, the last one
    partial) and from in-memory arrays, which stay as they were; written band by band, the
    PNG decodes (OpenCV) to the mask and holds what ``encode_png(flat=True)`` encodes."""
    from reblur.io import write_png_bands, zarr_masks
    from reblur.report import _mask_bands

    shape = (203, 150)
    c = rng.random(shape) > 0.7
    u = rng.random(shape) > 0.8
    zc, zu = zarr_masks(tmp_path / "m", shape, 64)
    zc[...] = c
    zu[...] = u
    want = np.where(c & ~u, 255, 0).astype(np.uint8)
    c0, u0 = c.copy(), u.copy()
    for change, unknown in ((zc, zu), (c, u)):
        bands = list(_mask_bands(change, unknown))
        assert all(b.dtype == np.uint8 for b in bands)
        assert len(bands) == (4 if change is zc else 1)
        np.testing.assert_array_equal(np.concatenate(bands), want)
        np.testing.assert_array_equal(np.concatenate(list(_mask_bands(unknown))),
                                      np.where(u, 255, 0))
        p = write_png_bands(tmp_path / "c.png", shape, _mask_bands(change, unknown))
        np.testing.assert_array_equal(cv2.imread(str(p), cv2.IMREAD_UNCHANGED), want)
        hdr, rows = _png_rows(p.read_bytes())
        assert (hdr["depth"], hdr["colour"]) == (8, 0) and {r[0] for r in rows} == {0}
        assert _png_rows(encode_png(want, flat=True))[1] == rows
    np.testing.assert_array_equal(c, c0)
    np.testing.assert_array_equal(u, u0)


def test_write_png_bands_refuses_bands_that_do_not_fit(tmp_path):
    """Too few rows, a band of another width or type: an error, and no file."""
    from reblur.io import write_png_bands

    band = np.zeros((10, 20), np.uint8)
    for bands in ([band], [band, band, band], [np.zeros((20, 21), np.uint8)],
                  [np.zeros((20, 20), np.float32)]):
        with pytest.raises(ValueError):
            write_png_bands(tmp_path / "m.png", (20, 20), iter(bands))
        assert not list(tmp_path.iterdir())
