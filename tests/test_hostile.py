"""Hostile inputs and interrupted or concurrent runs (issue 30).

Corrupt containers are refused rather than read as zeros; the output set of a run appears
all at once or not at all; two runs into one output directory cannot mix their files.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
import zarr

from reblur.io import InputError, open_image, write_png


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
