"""Large PNG and JPEG inputs, decoded once into a temporary zarr array read window by window.

PNG and JPEG cannot be read window by window: a decoder starts at the first row.  Decoded
whole, a 30000^2 gray pair takes 1.8 GB before the first window is looked at.  Here a large
one is decoded once, top to bottom, into a zarr array of 512 x 512 tiles (LZ4) in a
temporary directory, and the image is then read from it like a large tiled TIFF:

* PNG (8 or 16 bits, gray, gray + alpha, RGB, RGBA; not interlaced, no palette, no
  ``tRNS``): GDAL's PNG driver (libpng, line by line) gives strips of 512 rows, each
  written to the store and dropped; the decode holds one strip and libpng's state (GDAL's
  block cache limited to 64 MB).  libpng stops checking chunk CRCs once it has the last
  row, so every chunk's CRC is checked first (:func:`check_png_chunks`), by a plain read of
  the file.  These PNGs read the same through libpng in GDAL as through imagecodecs, pixel
  for pixel.
* JPEG (8 bits, 1 or 3 components): libjpeg-turbo (imagecodecs, the decoder used for a small
  JPEG: the same pixels) writes into a memory-mapped file, copied strip by strip into the
  store and deleted.  The decoded pixels are file pages the kernel can write back and drop,
  not memory the process owns; only a progressive JPEG's coefficients (2 bytes per sample)
  are.  GDAL's libjpeg, which streams, upsamples chroma differently (up to 21 levels apart
  from libjpeg-turbo on a 4:2:0 picture).

The directory ``reblur-decoded-PID-*`` lives in the temporary directory (``TMPDIR``) and is
removed when the image is closed or garbage-collected, or at exit; one left by a killed
process is removed by the next decode.  Its size is at most the decoded bytes, which the
byte limit of :func:`reblur.io.open_image` bounds from the header before anything is decoded.
"""

from __future__ import annotations

import contextlib
import errno
import mmap
import os
import re
import shutil
import tempfile
import weakref
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .io import InputError, _Sized, scratch_compressors

#: Prefix of the temporary directories holding decoded images.
PREFIX = "reblur-decoded-"

#: Rows decoded and written at a time (one row of the store's 512 x 512 tiles).
STRIP_ROWS = 512

#: GDAL's block cache while decoding, MB (its default, 5 % of the RAM, would keep the
#: decoded lines: 1.2 GB for a 20000^2 RGB PNG).
GDAL_CACHE_MB = 64

Fail = Callable[[Path, str], InputError]


class DecodedImage(_Sized):
    """Window reader of an image decoded into a temporary zarr array.

    Slicing returns numpy arrays.  ``temporary`` tells :func:`reblur.dask_backend.portable`
    to copy it where remote workers can see it.  Pickling keeps the store's path: processes
    on this machine read the same directory.

    Parameters
    ----------
    array : zarr.Array
        The decoded pixels, ``(H, W)`` or ``(H, W, C)``.
    root : Path
        Temporary directory holding ``array`` (removed by :meth:`close`).
    source : Path
        The file it was decoded from (named in error messages).
    """

    temporary = True
    #: For an image with an alpha band: whether every pixel is opaque (found while decoding).
    opaque: bool | None = None

    def __init__(self, array, root: Path, source: Path):
        self.array = array
        self.root = Path(root)
        self.source = Path(source)
        self.shape = tuple(int(s) for s in array.shape)
        self.dtype = np.dtype(array.dtype)
        self.ndim = len(self.shape)
        self.chunks = tuple(int(c) for c in array.chunks)

    def __repr__(self) -> str:
        return f"DecodedImage({self.source}, shape={self.shape}, dtype={self.dtype})"

    def __getitem__(self, key) -> np.ndarray:
        return np.asarray(self.array[key])

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        a = self[...]
        return a if dtype is None else a.astype(dtype, copy=False)

    def close(self) -> None:
        """Remove the temporary directory (the image cannot be read afterwards)."""
        shutil.rmtree(self.root, ignore_errors=True)


# ---------------------------------------------------------------------------- the store
def _pid_alive(pid: int) -> bool:
    from .outdir import _pid_alive as alive

    return alive(pid)


def remove_stale(where: str | os.PathLike | None = None) -> list[Path]:
    """Remove ``reblur-decoded-PID-*`` directories of processes no longer alive."""
    where = Path(where or tempfile.gettempdir())
    pat = re.compile(rf"{re.escape(PREFIX)}(\d+)-")
    removed = []
    try:
        entries = list(where.iterdir())
    except OSError:
        return removed
    for p in entries:
        m = pat.match(p.name)
        if m is None or _pid_alive(int(m.group(1))) or not p.is_dir() or p.is_symlink():
            continue
        shutil.rmtree(p, ignore_errors=True)
        if not p.exists():
            removed.append(p)
    return removed


def _new_root() -> Path:
    remove_stale()
    return Path(tempfile.mkdtemp(prefix=f"{PREFIX}{os.getpid()}-"))


def _create(root: Path, shape: tuple[int, ...], dtype: np.dtype):
    """The store: 512 x 512 tiles, LZ4 (Blosc, level 1: writes 192 MB in about half the
    time zstd level 1 takes, for 15 % more bytes on a noisy picture;
    :func:`reblur.io.scratch_compressors`)."""
    import zarr

    chunks = (STRIP_ROWS, STRIP_ROWS) + tuple(shape[2:])
    return zarr.create_array(str(root / "0"), shape=shape, chunks=chunks, dtype=dtype,
                             fill_value=0, compressors=scratch_compressors(dtype))


class _Writer:
    """Writes strips into the store in a thread, one at a time, while the next strip is
    decoded (at most two strips in memory)."""

    def __init__(self, z):
        from concurrent.futures import ThreadPoolExecutor

        self.z = z
        self.pool = ThreadPoolExecutor(max_workers=1)
        self.pending = None

    def __call__(self, y: int, block: np.ndarray) -> None:
        self.wait()
        self.pending = self.pool.submit(self.z.__setitem__, slice(y, y + len(block)), block)

    def wait(self) -> None:
        if self.pending is not None:
            pending, self.pending = self.pending, None
            pending.result()

    def __enter__(self) -> _Writer:
        return self

    def __exit__(self, *exc) -> None:
        try:
            if exc[0] is None:
                self.wait()
        finally:
            self.pool.shutdown(wait=True, cancel_futures=True)


def _space_hint(root: Path, nbytes: int, convert: str) -> str:
    return (f"not enough free space in {root.parent} for the decoded image (up to {nbytes:,} "
            f"bytes); set TMPDIR to a larger disk, or convert the file to a tiled TIFF first: "
            f"{convert}")


def _decode(path: Path, shape: tuple[int, ...], dtype: np.dtype, fill, fail: Fail,
            convert: str) -> DecodedImage:
    """A store of ``shape`` filled by ``fill(array)``; the directory is removed on failure
    (a full disk is one line naming the temporary directory), else when the returned image
    is garbage-collected or at exit."""
    root = _new_root()
    nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
    try:
        z = _create(root, shape, dtype)
        fill(z, root)
    except BaseException as exc:
        shutil.rmtree(root, ignore_errors=True)
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise fail(path, _space_hint(root, nbytes, convert)) from exc
        raise
    img = DecodedImage(z, root, path)
    weakref.finalize(img, shutil.rmtree, str(root), True)
    return img


# ---------------------------------------------------------------------------- PNG
def check_png_chunks(path: Path, fail: Fail, piece: int = 16 * 2**20) -> None:
    """Walk the chunks of a PNG file, checking each one's CRC; refuse a file that ends
    early or holds anything after ``IEND``.  Reads the file once, ``piece`` bytes at a
    time."""
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        f.seek(8)
        pos = 8
        while True:
            head = f.read(8)
            if len(head) < 8:
                raise fail(path, "PNG file is truncated (it ends inside a chunk, before IEND)")
            n, kind = int.from_bytes(head[:4], "big"), head[4:]
            if pos + 12 + n > size:
                raise fail(path, f"PNG file is truncated (chunk {kind!r} at byte {pos:,} runs "
                                 "past the end of the file)")
            crc = zlib.crc32(kind)
            left = n
            while left:
                block = f.read(min(piece, left))
                crc = zlib.crc32(block, crc)
                left -= len(block)
            if int.from_bytes(f.read(4), "big") != crc:
                name = kind.decode("latin-1")
                raise fail(path, f"PNG file is corrupt (CRC error in its {name} chunk at byte "
                                 f"{pos:,})")
            pos += 12 + n
            if kind == b"IEND":
                return


def png_to_disk(path: Path, shape: tuple[int, ...], dtype: np.dtype, fail: Fail,
                convert: str) -> DecodedImage:
    """Decode a PNG into a temporary store, strip by strip (see the module's notes)."""
    import rasterio
    from rasterio.windows import Window

    check_png_chunks(path, fail)
    h, w = shape[:2]
    alpha = len(shape) == 3 and shape[2] in (2, 4)
    opaque = [True]

    def fill(z, root: Path) -> None:
        env = dict(GDAL_CACHEMAX=GDAL_CACHE_MB * 2**20, GDAL_PNG_WHOLE_IMAGE_OPTIM="NO",
                   CPL_LOG="/dev/null")
        with _quiet(), rasterio.Env(**env):
            src = _gdal(lambda: rasterio.open(path, driver="PNG"), path, fail)
            with src, _Writer(z) as write:
                if (src.height, src.width) != (h, w) or src.count != (shape[2:] or (1,))[0]:
                    raise fail(path, "PNG header and image data disagree")
                for y in range(0, h, STRIP_ROWS):
                    n = min(STRIP_ROWS, h - y)
                    block = _gdal(lambda y=y, n=n: src.read(window=Window(0, y, w, n)), path,
                                  fail)
                    write(y, block[0] if len(shape) == 2 else np.moveaxis(block, 0, -1))
                    if alpha and opaque[0]:
                        opaque[0] = bool((block[-1] > 0).all())

    img = _decode(path, shape, dtype, fill, fail, convert)
    img.opaque = opaque[0] if alpha else None
    return img


# ---------------------------------------------------------------------------- JPEG
def jpeg_to_disk(path: Path, shape: tuple[int, ...], dtype: np.dtype, fail: Fail,
                 convert: str) -> DecodedImage:
    """Decode a JPEG into a temporary store through a memory-mapped file (see the module's
    notes)."""
    import imagecodecs

    def fill(z, root: Path) -> None:
        npy = root / "decode.npy"
        try:
            out = np.lib.format.open_memmap(npy, mode="w+", dtype=dtype, shape=shape)
            try:
                with open(path, "rb") as fh, mmap.mmap(fh.fileno(), 0,
                                                       access=mmap.ACCESS_READ) as data:
                    got = imagecodecs.jpeg8_decode(data, out=out)
            except (OSError, MemoryError, KeyboardInterrupt):
                raise
            except Exception as exc:  # noqa: BLE001 - every codec failure: corrupt data
                raise fail(path, f"cannot decode JPEG image ({_why(exc)})") from exc
            if got is not out:
                got = np.asarray(got).reshape(shape)
            for y in range(0, shape[0], STRIP_ROWS):
                z[y : y + STRIP_ROWS] = got[y : y + STRIP_ROWS]
            del got, out
        finally:
            with contextlib.suppress(OSError):
                npy.unlink()

    return _decode(path, shape, dtype, fill, fail, convert)


# ---------------------------------------------------------------------------- helpers
def _gdal(call, path: Path, fail: Fail):
    """``call()``; a GDAL or libpng failure becomes one line naming ``path`` (rasterio's
    errors are OSErrors, which would otherwise read as a failing disk)."""
    from rasterio.errors import RasterioError

    try:
        return call()
    except (MemoryError, KeyboardInterrupt):
        raise
    except (RasterioError, RuntimeError, ValueError) as exc:
        raise fail(path, f"cannot decode PNG image ({_why(exc)})") from exc

def _why(exc: BaseException) -> str:
    """The first line of what went wrong, with GDAL's own cause when it has one."""
    cause = exc.__cause__ or exc
    msg = str(cause).strip().splitlines()[0] if str(cause).strip() else type(cause).__name__
    return msg.split("libpng: ", 1)[-1]


@contextlib.contextmanager
def _quiet():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield
