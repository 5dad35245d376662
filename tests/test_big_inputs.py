"""Large and forged PNG / JPEG / other inputs (issue 30, item 4): decoded bytes checked from
the header before any decode, against a limit that scales with ``max_pixels``; large PNGs and
JPEGs decoded once, in strips, into a temporary store that gives exactly the pixels of the
whole decode."""

from __future__ import annotations

import gc
import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import cv2
import imagecodecs
import numpy as np
import pytest
import tifffile
from test_cli import assert_one_line_error, run

import reblur.io as rio
from reblur import _decoded
from reblur.io import InputError, open_image, write_png


# ---------------------------------------------------------------------------- forged headers
def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def png_bomb(w: int, h: int, depth: int = 16, colour: int = 6) -> bytes:
    """A PNG header and an end chunk, with no pixel data at all."""
    ihdr = struct.pack(">IIBBBBB", w, h, depth, colour, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IEND", b"")


def jpeg_bomb(w: int, h: int, precision: int = 8, comps: int = 3) -> bytes:
    """SOI, a baseline frame header, a scan header with no data, EOI."""
    sof = struct.pack(">BHHB", precision, h, w, comps) + b"".join(
        bytes((i + 1, 0x11, 0)) for i in range(comps))
    sos = bytes((comps,)) + b"".join(bytes((i + 1, 0)) for i in range(comps)) + b"\x00\x3f\x00"
    return (b"\xff\xd8" + b"\xff\xc0" + struct.pack(">H", 2 + len(sof)) + sof
            + b"\xff\xda" + struct.pack(">H", 2 + len(sos)) + sos + b"\xff\xd9")


def jxl_bomb(side: int) -> bytes:
    """A bare JPEG XL codestream whose SizeHeader says side x side (nothing else)."""
    bits = 0 | (3 << 1) | ((side - 1) << 3) | (1 << 33)  # not small, 30-bit height, 1:1
    return b"\xff\x0a" + bits.to_bytes(10, "little")


def webp_bomb(side: int) -> bytes:
    """A 46-byte lossless WebP of one colour whose header is then made to say side x side:
    a valid stream of any size (one Huffman symbol: no bits per pixel)."""
    a = np.zeros((64, 64, 4), np.uint8)
    a[:] = (1, 2, 3, 255)
    data = bytearray(imagecodecs.webp_encode(a, lossless=True))
    i = data.find(b"VP8L") + 8  # the signature byte, then 14-bit width - 1, height - 1
    bits = struct.unpack("<I", data[i + 1 : i + 5])[0] & ~(2**28 - 1)
    data[i + 1 : i + 5] = struct.pack("<I", bits | (side - 1) | (side - 1) << 14)
    return bytes(data)


def tiff_bomb(path: Path, w: int, h: int) -> Path:
    """A small RGBA 16-bit TIFF whose width and length tags are then made to say w x h."""
    tifffile.imwrite(path, np.zeros((64, 64, 4), np.uint16), photometric="rgb",
                     extrasamples=[2], compression="deflate")
    with tifffile.TiffFile(path, mode="r+") as tif:
        tif.pages[0].tags["ImageWidth"].overwrite(w)
        tif.pages[0].tags["ImageLength"].overwrite(h)
    return path


def zarr_bomb(path: Path, side: int) -> Path:
    """A zarr array declared side x side x 4 uint16, with no chunk written."""
    import zarr

    zarr.create_array(str(path), shape=(side, side, 4), chunks=(4096, 4096, 4), dtype="u2",
                      fill_value=0)
    return path


@pytest.fixture
def no_decoding(monkeypatch):
    """Every decoder reblur calls fails the test if it is called."""
    import rasterio
    import zarr

    def called(*args, **kwargs):
        raise AssertionError("a decoder was called")

    for name in ("png_decode", "jpeg8_decode", "imread", "webp_decode", "jpegxl_decode"):
        monkeypatch.setattr(imagecodecs, name, called)
    monkeypatch.setattr(rasterio, "open", called)
    monkeypatch.setattr(_decoded, "png_to_disk", called)
    monkeypatch.setattr(_decoded, "jpeg_to_disk", called)
    monkeypatch.setattr(tifffile.TiffPage, "asarray", called)
    monkeypatch.setattr(zarr.Array, "__getitem__", called)


def _bombs(d: Path) -> dict[str, Path]:
    """100000^2 RGBA 16-bit where the format allows it (JPEG: 65535^2 RGB of 12 bits;
    WebP: 16384^2 RGB, its largest)."""
    files = {"png": png_bomb(100_000, 100_000), "jpg": jpeg_bomb(65_535, 65_535, 12),
             "jxl": jxl_bomb(100_000), "webp": webp_bomb(16_384)}
    out = {}
    for ext, data in files.items():
        (d / f"bomb.{ext}").write_bytes(data)
        out[ext] = d / f"bomb.{ext}"
    out["tif"] = tiff_bomb(d / "bomb.tif", 100_000, 100_000)
    out["zarr"] = zarr_bomb(d / "bomb.zarr", 100_000)
    return out


#: (pixels, bands x bytes per sample) each forged header declares.
DECLARED = {"png": (100_000**2, 8), "jpg": (65_535**2, 6), "jxl": (100_000**2, 16),
            "tif": (100_000**2, 8), "zarr": (100_000**2, 8)}


@pytest.mark.parametrize("ext", sorted(DECLARED))
def test_forged_headers_refused_before_decoding(tmp_path, ext, no_decoding):
    """The header's pixels are allowed (``max_pixels`` = exactly that many), the bytes they
    decode to are not: refused with the limit's arithmetic, no decoder called, no memory
    taken."""
    import tracemalloc

    path = _bombs(tmp_path)[ext]
    pixels, per_pixel = DECLARED[ext]
    nbytes = pixels * per_pixel
    tracemalloc.start()
    try:
        with pytest.raises(InputError) as err:
            open_image(path, max_pixels=pixels)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    msg = str(err.value)
    upto = "up to " if ext == "jxl" else ""
    assert f"would decode to {upto}{nbytes:,} bytes" in msg, msg
    assert f"more than the limit of {4 * pixels:,} (--max-pixels {pixels:,} x 4 bytes)" in msg
    assert f"raise --max-pixels to at least {-(-nbytes // 4):,}" in msg
    assert msg.startswith(str(path)) and "\n" not in msg
    assert peak < 16 * 2**20, peak
    # the default limit counts pixels first where there are more than 4e9
    if pixels > rio.DEFAULT_MAX_PIXELS:
        with pytest.raises(InputError, match=r"more than the limit of 4,000,000,000; raise"):
            open_image(path)


def test_forged_webp_refused_by_the_in_memory_limit(tmp_path, monkeypatch, no_decoding):
    """WebP never decodes to more than 4 bytes a pixel, so its largest (16384^2 RGB, 46
    bytes here) passes the byte limit; its decoder's peak (3 x 805 MB) is what is bounded,
    from the header, before it runs."""
    path = _bombs(tmp_path)["webp"]
    monkeypatch.setattr(rio, "IN_MEMORY_MAX_BYTES", 2**31)
    with pytest.raises(InputError, match=r"bomb\.webp: image of 16384x16384 pixels would need "
                                         r"about 2,415,919,104 bytes of memory to decode whole"):
        open_image(path)


def test_byte_limit_scales_with_max_pixels(tmp_path):
    """A 64 x 64 RGBA 16-bit PNG decodes to 32768 bytes: allowed from max_pixels = 8192 up
    (4 bytes each), refused below, whatever its 4096 pixels."""
    a = (np.random.default_rng(1).random((64, 64, 4)) * 65535).astype(np.uint16)
    a[..., 3] = 65535
    (tmp_path / "a.png").write_bytes(imagecodecs.png_encode(a))
    assert open_image(tmp_path / "a.png", max_pixels=8192).shape == (64, 64, 3)
    with pytest.raises(InputError, match=r"would decode to 32,768 bytes, more than the limit "
                                         r"of 32,764 \(--max-pixels 8,191 x 4 bytes\)"):
        open_image(tmp_path / "a.png", max_pixels=8191)
    assert rio.decoded_bytes_limit(8191) == 32_764 and rio.decoded_bytes_limit(None) is None


def test_cli_refuses_a_forged_png_in_one_line(tmp_path):
    paths = _bombs(tmp_path)
    good = tmp_path / "good.png"
    write_png(good, (np.random.default_rng(2).random((64, 64)) * 255).astype(np.uint8))
    res = run("detect", paths["png"], good, "--out", tmp_path / "res", "--max-pixels",
              10_000_000_000, "-q")
    assert_one_line_error(res, r"bomb\.png: PNG image of 100000x100000 pixels, 4 bands of 16 "
                               r"bits, would decode to 80,000,000,000 bytes, more than the "
                               r"limit of 40,000,000,000")
    assert not (tmp_path / "res").exists()


# ---------------------------------------------------------------------------- decoded whole
def test_whole_decode_bounded_with_the_conversion_command(tmp_path, monkeypatch):
    """A format that cannot be decoded in strips is refused when its decoder's peak would
    pass the in-memory limit, naming the command that converts it; the tifffile command
    (for a format GDAL does not read) works as printed."""
    a = (np.random.default_rng(3).random((48, 80, 3)) * 255).astype(np.uint8)
    (tmp_path / "a.webp").write_bytes(imagecodecs.webp_encode(a, lossless=True))
    (tmp_path / "a.jxl").write_bytes(imagecodecs.jpegxl_encode(a, lossless=True))
    monkeypatch.setattr(rio, "IN_MEMORY_MAX_BYTES", 20_000)
    # WebP: 48 x 80 x 3 bytes x 3 (its decoder's peak factor) = 34560
    with pytest.raises(InputError, match=r"about 34,560 bytes of memory to decode whole, more "
                                         r"than the limit of 20,000, and it cannot be decoded "
                                         r"in strips; convert it to a tiled TIFF first: "
                                         r"gdal_translate -co TILED=YES .* \S+a\.webp \S+a\.tif$"):
        open_image(tmp_path / "a.webp")
    with pytest.raises(InputError) as err:
        open_image(tmp_path / "a.jxl")
    cmd = str(err.value).split("convert it to a tiled TIFF first: ", 1)[1]
    assert cmd.startswith("python -c ")
    # run as printed, by the Python reblur runs in
    subprocess.run(cmd.replace("python", sys.executable, 1), shell=True, check=True)
    monkeypatch.setattr(rio, "IN_MEMORY_MAX_BYTES", 2**32)
    np.testing.assert_array_equal(open_image(tmp_path / "a.tif").read(), a)


def test_animations_refused(tmp_path):
    from PIL import Image as PILImage

    rng = np.random.default_rng(4)
    frames = [PILImage.fromarray((rng.random((64, 64, 3)) * 255).astype(np.uint8))
              for _ in range(3)]
    frames[0].save(tmp_path / "a.gif", save_all=True, append_images=frames[1:])
    with pytest.raises(InputError, match=r"a\.gif: GIF file holds several frames"):
        open_image(tmp_path / "a.gif")


def test_large_single_strip_tiff_refused(tmp_path, monkeypatch):
    """Every window of a lazily read TIFF decodes each strip it touches whole: a strip over
    the limit (CHUNK_MAX_BYTES, lowered here) is refused; the same pixels in tiles are read
    (the large-image path forced by LAZY_BYTES = 0)."""
    a = (np.random.default_rng(5).random((200, 300)) * 255).astype(np.uint8)
    tifffile.imwrite(tmp_path / "one.tif", a, rowsperstrip=200, compression="deflate")
    tifffile.imwrite(tmp_path / "tiled.tif", a, tile=(64, 64), compression="deflate")
    monkeypatch.setattr(rio, "CHUNK_MAX_BYTES", 20_000)
    monkeypatch.setattr(rio, "LAZY_BYTES", 0)
    with pytest.raises(InputError, match=r"one\.tif: TIFF image stored in strips of 60,000 "
                                         r"bytes each, .* rewrite it in tiles first: "
                                         r"gdal_translate .*one\.tiled\.tif$"):
        open_image(tmp_path / "one.tif")
    tiled = open_image(tmp_path / "tiled.tif")
    assert tiled.lazy
    np.testing.assert_array_equal(tiled.read(), a)


# ---------------------------------------------------------------------------- strips
def _picture(h: int, w: int, bands: int, dtype, seed: int = 6) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = cv2.GaussianBlur(rng.random((h, w, bands)).astype(np.float32), (0, 0), 2)
    a = cv2.normalize(a, None, 0, 1, cv2.NORM_MINMAX).reshape(h, w, bands)
    a = (a * np.iinfo(dtype).max).astype(dtype)
    return a[..., 0] if bands == 1 else a


@pytest.mark.parametrize("bands, dtype", [(1, np.uint8), (1, np.uint16), (2, np.uint8),
                                          (2, np.uint16), (3, np.uint8), (3, np.uint16),
                                          (4, np.uint8), (4, np.uint16)])
def test_png_strips_give_the_whole_decode(tmp_path, bands, dtype):
    """3000 x 2000 PNGs of every layout the strip path takes: the strips give the pixels
    and the no-data mask of the whole decode (alpha 0 in one corner: unknown there)."""
    a = _picture(2000, 3000, bands, dtype)
    if bands in (2, 4):
        a[..., -1] = np.iinfo(dtype).max
        a[:100, :150, -1] = 0
    (tmp_path / "a.png").write_bytes(imagecodecs.png_encode(a, level=1))
    whole = open_image(tmp_path / "a.png", lazy=False)
    strips = open_image(tmp_path / "a.png", lazy=True)
    assert isinstance(whole.array, np.ndarray) and strips.lazy
    np.testing.assert_array_equal(strips.read(), whole.read())
    colour = a if bands == 1 else a[..., : bands - (bands in (2, 4))]
    np.testing.assert_array_equal(strips.read(), colour.reshape(whole.shape))
    if bands in (2, 4):
        np.testing.assert_array_equal(np.asarray(strips.valid[...]), a[..., -1] > 0)
        assert whole.nodata_source == strips.nodata_source == "alpha band"
    strips.close()


def test_opaque_alpha_dropped_in_strips(tmp_path):
    a = _picture(300, 200, 4, np.uint8)
    a[..., 3] = 255
    (tmp_path / "a.png").write_bytes(imagecodecs.png_encode(a))
    img = open_image(tmp_path / "a.png", lazy=True)
    assert img.lazy and img.valid is None and img.shape == (300, 200, 3)
    assert "alpha band dropped (all opaque)" in img.notes


@pytest.mark.parametrize("kind", ["gray", "420", "444", "progressive"])
def test_jpeg_strips_give_the_whole_decode(tmp_path, kind):
    a = _picture(2000, 3000, 1 if kind == "gray" else 3, np.uint8)
    params = {"gray": [], "420": [],
              "444": [cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444],
              "progressive": [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]}[kind]
    cv2.imwrite(str(tmp_path / "a.jpg"), a if a.ndim == 2 else a[..., ::-1],
                [cv2.IMWRITE_JPEG_QUALITY, 85, *params])
    whole = open_image(tmp_path / "a.jpg", lazy=False)
    strips = open_image(tmp_path / "a.jpg", lazy=True)
    assert strips.lazy and strips.shape == a.shape
    np.testing.assert_array_equal(strips.read(), whole.read())
    # and both are what libjpeg-turbo gives through OpenCV
    ref = cv2.imread(str(tmp_path / "a.jpg"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(whole.read(), ref if ref.ndim == 2 else ref[..., ::-1])


@pytest.mark.parametrize("what", ["palette", "interlaced", "trns"])
def test_pngs_the_strips_cannot_take_are_decoded_whole(tmp_path, what):
    from PIL import Image as PILImage

    a = _picture(120, 100, 3, np.uint8)
    p = tmp_path / "a.png"
    if what == "palette":
        PILImage.fromarray(a).convert("P").save(p)
    elif what == "interlaced":
        p.write_bytes(_adam7(a))
        np.testing.assert_array_equal(imagecodecs.png_decode(p.read_bytes()), a)
    else:
        PILImage.fromarray(a).save(p, transparency=(1, 2, 3))
    img = open_image(p, lazy=True)
    assert not img.lazy
    np.testing.assert_array_equal(img.read(), open_image(p, lazy=False).read())


def _adam7(a: np.ndarray) -> bytes:
    """An interlaced (Adam7) 8-bit RGB PNG of ``a``, filter type 0 in every pass."""
    h, w = a.shape[:2]
    passes = [(0, 0, 8, 8), (0, 4, 8, 8), (4, 0, 8, 4), (0, 2, 4, 4), (2, 0, 4, 2),
              (0, 1, 2, 2), (1, 0, 2, 1)]
    raw = b""
    for y0, x0, dy, dx in passes:
        sub = a[y0::dy, x0::dx]
        if sub.size:
            raw += b"".join(b"\x00" + row.tobytes() for row in sub)
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 1)
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(raw))
            + _chunk(b"IEND", b""))


# ---------------------------------------------------------------------------- corrupt data
def _idats(data: bytes) -> list[tuple[int, int]]:
    out, i = [], 8
    while i < len(data):
        n = struct.unpack(">I", data[i : i + 4])[0]
        if data[i + 4 : i + 8] == b"IDAT":
            out.append((i, n))
        i += 12 + n
    return out


def test_flip_in_the_last_rows_refused_by_the_strips(tmp_path):
    """A flipped byte near the end of the last IDAT chunk changes only the last rows, which
    libpng decodes without looking at that chunk's CRC: the chunk walk catches it."""
    a = _picture(600, 400, 3, np.uint8)
    data = bytearray(imagecodecs.png_encode(a, level=1))
    i, n = _idats(bytes(data))[-1]
    data[i + 8 + n - 8] ^= 0x01
    (tmp_path / "a.png").write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"a\.png: PNG file is corrupt \(CRC error in its "
                                         r"IDAT chunk at byte [\d,]+\)"):
        open_image(tmp_path / "a.png", lazy=True)
    with pytest.raises(InputError, match=r"a\.png: cannot decode PNG image"):
        open_image(tmp_path / "a.png", lazy=False)


def test_truncated_png_with_an_end_chunk_refused_by_the_strips(tmp_path, monkeypatch):
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    a = _picture(600, 400, 3, np.uint8)
    data = imagecodecs.png_encode(a, level=1)
    cut = data[: len(data) // 2] + _chunk(b"IEND", b"")
    (tmp_path / "a.png").write_bytes(cut)
    with pytest.raises(InputError, match=r"a\.png: PNG file is (truncated|corrupt)"):
        open_image(tmp_path / "a.png", lazy=True)
    i, n = _idats(data)[len(_idats(data)) // 2]  # cut at a chunk boundary: CRCs all right
    (tmp_path / "b.png").write_bytes(data[:i] + _chunk(b"IEND", b""))
    with pytest.raises(InputError, match=r"b\.png: cannot decode PNG image \(.*Not enough "
                                         r"image data"):
        open_image(tmp_path / "b.png", lazy=True)
    assert not list(tmp_path.glob(f"{_decoded.PREFIX}*"))  # no store left behind


# ---------------------------------------------------------------------------- the store
def test_store_removed_on_close_on_collection_and_after_a_killed_run(tmp_path, monkeypatch):
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    (tmp_path / "a.png").write_bytes(imagecodecs.png_encode(_picture(100, 80, 3, np.uint8)))
    img = open_image(tmp_path / "a.png", lazy=True)
    root = img.array.root
    assert root.parent == tmp_path and root.name.startswith(f"reblur-decoded-{os.getpid()}-")
    img.close()
    assert not root.exists()
    img = open_image(tmp_path / "a.png", lazy=True)
    root = img.array.root
    del img
    gc.collect()
    assert not root.exists()
    # a store left by a process that no longer runs: removed by the next decode
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True).stdout.strip()
    stale = tmp_path / f"reblur-decoded-{dead}-abc"
    (stale / "0").mkdir(parents=True)
    img = open_image(tmp_path / "a.png", lazy=True)
    assert not stale.exists() and img.array.root.exists()


def test_no_space_for_the_store_is_one_line(tmp_path, monkeypatch, small_disk):
    """The store fills its disk: one line naming where, what to do; nothing left there."""
    import tempfile

    where = small_disk
    monkeypatch.setattr(tempfile, "tempdir", str(where))
    noise = (np.random.default_rng(7).random((600, 600, 3)) * 255).astype(np.uint8)
    (tmp_path / "n.png").write_bytes(imagecodecs.png_encode(noise, level=1))
    with pytest.raises(InputError, match=r"n\.png: not enough free space in .*disk for the "
                                         r"decoded image \(up to 1,080,000 bytes\); set TMPDIR"):
        open_image(tmp_path / "n.png", lazy=True)
    assert list(where.iterdir()) == []


def test_dask_workers_get_a_copy_where_they_can_see_it(tmp_path):
    from reblur.dask_backend import portable

    a = _picture(300, 200, 4, np.uint8)
    a[:10, :10, 3] = 0
    (tmp_path / "a.png").write_bytes(imagecodecs.png_encode(a))
    img = open_image(tmp_path / "a.png", lazy=True)
    view = img.for_detection()
    store = tmp_path / "work"
    moved = portable(view, "reference", store)
    here = portable(view, "reference")  # same machine: read where it is
    np.testing.assert_array_equal(np.asarray(moved[...]), np.asarray(view[...]))
    assert str(store) in str(moved.array.source.store_path)
    assert moved.array.source is not img.array.source
    assert here.array.source is img.array.source


# ---------------------------------------------------------------------------- the CLI
def test_cli_on_a_pair_decoded_in_strips(tmp_path):
    """The CLI with every PNG decoded in strips (LAZY_BYTES = 0) finds what it finds with
    the pair in memory."""
    from test_hostile import detect_args, drive, scene

    ref, obs = scene(np.random.default_rng(21))
    d = tmp_path / "in"
    d.mkdir()
    write_png(d / "ref.png", ref)
    write_png(d / "obs.png", obs)
    res = run(*detect_args((d / "ref.png", d / "obs.png"), tmp_path / "mem"))
    assert res.returncode == 0, res.stderr
    proc = drive("lazy", tmp_path / "m", *detect_args((d / "ref.png", d / "obs.png"),
                                                      tmp_path / "strips"))
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    mem = cv2.imread(str(tmp_path / "mem" / "changes.png"), cv2.IMREAD_UNCHANGED)
    strips = cv2.imread(str(tmp_path / "strips" / "changes.png"), cv2.IMREAD_UNCHANGED)
    assert mem.any()
    np.testing.assert_array_equal(strips, mem)


@pytest.mark.slow
def test_progressive_jpeg_over_gdals_libjpeg_cap_is_read(tmp_path):
    """A valid progressive JPEG whose coefficients (2 bytes a sample: 545 MB here) pass the
    500 MiB GDAL lets libjpeg use by default was refused as "truncated or corrupt (Backing
    store not supported)" by the data check."""
    a = np.zeros((16_500, 16_500), np.uint8)
    a[::64] = 200
    assert cv2.imwrite(str(tmp_path / "p.jpg"), a, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])
    del a
    img = open_image(tmp_path / "p.jpg")
    assert img.shape == (16_500, 16_500)
    np.testing.assert_array_equal(img.array[:130, :3], cv2.imread(
        str(tmp_path / "p.jpg"), cv2.IMREAD_GRAYSCALE)[:130, :3])
