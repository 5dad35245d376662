"""Deep Zoom (DZI) tile pyramids written from windows, never from a full-size image.

A Deep Zoom image of ``W x H`` pixels has levels ``0 .. L`` with ``L = ceil(log2(max(W, H)))``:
level ``l`` is the image shrunk by ``2 ** (L - l)`` (``ceil`` of each side), so level ``L`` is
the full size and level 0 a single pixel.  Each level is cut into tiles of ``tile_size``
pixels (no overlap), stored as ``NAME_files/LEVEL/COL_ROW.FORMAT`` next to ``NAME.dzi``.

:func:`build_pyramids` walks the pyramid as a quadtree, every layer at once.  A node whose
footprint at full size fits in a ``block`` is a leaf: its full-size window is read from each
layer's source (one read per layer), cut into the full-size tiles, and halved level by level
up to the node, every tile written on the way.  Above the leaves each tile is made from its
(up to four) children's tiles, halved: the coarser levels come from the finer level's tiles.
Memory holds one block per layer plus four tiles per level of the path being walked.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._memory import available_cpus, thread_map
from ..io import encode_png

__all__ = ["Layer", "DziLayout", "build_pyramids", "halve", "dzi_xml"]

#: Deep Zoom's XML namespace (OpenSeadragon recognises a DZI by it).
DZI_NS = "http://schemas.microsoft.com/deepzoom/2008"


@dataclass(frozen=True)
class DziLayout:
    """The geometry of a Deep Zoom pyramid.

    Attributes
    ----------
    width, height : int
        Full size in pixels.
    tile_size : int
        Side of a tile (the last row and column of tiles may be smaller).
    """

    width: int
    height: int
    tile_size: int

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1:
            raise ValueError(f"a pyramid needs a non-empty image, got {self.width}x{self.height}")
        if self.tile_size < 1:
            raise ValueError(f"tile_size must be positive, got {self.tile_size}")

    @property
    def max_level(self) -> int:
        """The full-size level ``L = ceil(log2(max(W, H)))``."""
        return math.ceil(math.log2(max(self.width, self.height))) if max(
            self.width, self.height) > 1 else 0

    def scale(self, level: int) -> int:
        """Full-size pixels per pixel of ``level`` along each axis."""
        return 2 ** (self.max_level - level)

    def size(self, level: int) -> tuple[int, int]:
        """``(height, width)`` of ``level``."""
        s = self.scale(level)
        return -(-self.height // s), -(-self.width // s)

    def grid(self, level: int) -> tuple[int, int]:
        """``(rows, cols)`` of tiles at ``level``."""
        h, w = self.size(level)
        return -(-h // self.tile_size), -(-w // self.tile_size)

    def n_tiles(self) -> int:
        """Tiles in the whole pyramid (one layer)."""
        return sum(r * c for r, c in (self.grid(lv) for lv in range(self.max_level + 1)))

    def footprint(self, level: int, row: int, col: int) -> tuple[slice, slice]:
        """The full-size window a tile of ``level`` covers."""
        span = self.tile_size * self.scale(level)
        return (slice(row * span, min((row + 1) * span, self.height)),
                slice(col * span, min((col + 1) * span, self.width)))


@dataclass(frozen=True)
class Layer:
    """One pyramid: where its pixels come from and how its tiles are stored.

    Attributes
    ----------
    name : str
        File stem: ``NAME.dzi`` and ``NAME_files/``.
    read : callable
        ``read(rows, cols) -> (h, w, C)`` display values in [0, 255] of a full-size window
        (``rows``, ``cols`` are slices): float32, or uint8 where they are whole (an 8-bit
        image, a mask), which the full-size tiles are encoded from without a float copy.
    encode : callable
        ``encode(tile) -> uint8 (h, w), (h, w, 3) RGB or (h, w, 4) RGBA``: a tile of
        ``read``'s values as the image to store; ``read``'s own type at full size, float32
        (halved) on the coarser levels, the same image for the same values.
    fmt : {"jpg", "png"}
        Tile format.
    reduce : {"mean", "max"}
        How four pixels become one on the next coarser level: their mean, or their maximum
        (masks: a single changed pixel stays visible at every zoom).
    quality : int
        JPEG quality.
    flat : bool
        PNG tiles of few flat colours (masks): written in run-length mode
        (:func:`reblur.io.encode_png` with ``flat``), several times faster and as small.
    """

    name: str
    read: Callable[[slice, slice], np.ndarray]
    encode: Callable[[np.ndarray], np.ndarray]
    fmt: str = "png"
    reduce: str = "mean"
    quality: int = 90
    flat: bool = False

    def __post_init__(self) -> None:
        if self.fmt not in ("jpg", "png"):
            raise ValueError(f"layer {self.name}: tile format must be 'jpg' or 'png', "
                             f"got {self.fmt!r}")
        if self.reduce not in ("mean", "max"):
            raise ValueError(f"layer {self.name}: reduce must be 'mean' or 'max', "
                             f"got {self.reduce!r}")


def halve(a: np.ndarray, how: str = "mean") -> np.ndarray:
    """Shrink ``(h, w, C)`` by 2 on each axis to ``(ceil(h/2), ceil(w/2), C)``, float32.

    Each output pixel is the mean (or maximum) of the full-size pixels of its 2x2 block that
    exist (the last row or column of an odd side has only one or two).  Integer input
    gives the values of its float32 copy's.
    """
    h, w = a.shape[:2]
    if (h, w) == (1, 1):
        return a.astype(np.float32, copy=False)
    odd_h, odd_w = h % 2, w % 2
    if odd_h or odd_w:  # repeat the last row / column: the mean then needs no recount
        a = np.pad(a, ((0, odd_h), (0, odd_w), (0, 0)), mode="edge")
    q = (a[0::2, 0::2], a[1::2, 0::2], a[0::2, 1::2], a[1::2, 1::2])
    if how == "max":
        return np.maximum(np.maximum(q[0], q[1]), np.maximum(q[2], q[3])).astype(
            np.float32, copy=False)
    out = q[0].astype(np.float32)
    out += q[1]
    out += q[2]
    out += q[3]
    out *= np.float32(0.25)
    return out


def dzi_xml(layout: DziLayout, fmt: str) -> str:
    """The ``.dzi`` descriptor of a pyramid."""
    return (f'<?xml version="1.0" encoding="UTF-8"?>\n'
            f'<Image xmlns="{DZI_NS}" Format="{fmt}" Overlap="0" '
            f'TileSize="{layout.tile_size}">\n'
            f'  <Size Width="{layout.width}" Height="{layout.height}"/>\n</Image>\n')


class _Writer:
    """Encodes and stores the tiles of the layers; counts them."""

    def __init__(self, root: Path, layers: Sequence[Layer], layout: DziLayout):
        import cv2

        self.cv2 = cv2
        self.root, self.layers, self.layout = root, list(layers), layout
        self.written = 0
        self._blank: dict[tuple, bytes] = {}
        self._made: set[Path] = set()
        self._lock = threading.Lock()
        self.workers = 1
        for layer in self.layers:
            (root / f"{layer.name}.dzi").write_text(dzi_xml(layout, layer.fmt), encoding="utf-8")

    def _bytes(self, layer: Layer, img: np.ndarray) -> bytes:
        if layer.fmt == "png":
            try:
                return encode_png(img, flat=layer.flat)
            except OSError as exc:
                raise OSError(f"encoding a png tile of layer {layer.name} failed") from exc
        cv2 = self.cv2
        if img.ndim == 3 and img.shape[2] == 3:
            # OpenCV's channel order by its own swap: numpy's copy of a reversed-stride
            # view is many times slower
            img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2BGR)
        # no chroma subsampling: colours stay on their pixel when zoomed in
        ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(img),
                               [cv2.IMWRITE_JPEG_QUALITY, int(layer.quality),
                                cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                                cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444])
        if not ok:
            raise OSError(f"encoding a jpg tile of layer {layer.name} failed")
        return buf.tobytes()

    def write(self, k: int, level: int, row: int, col: int, tile: np.ndarray) -> None:
        layer = self.layers[k]
        d = self.root / f"{layer.name}_files" / str(level)
        if d not in self._made:
            d.mkdir(parents=True, exist_ok=True)
            with self._lock:
                self._made.add(d)
        if not tile.any():  # a blank mask tile: encoded once per shape
            key = (k, tile.shape)
            if key not in self._blank:
                self._blank[key] = self._bytes(layer, layer.encode(tile))
            data = self._blank[key]
        else:
            data = self._bytes(layer, layer.encode(tile))
        (d / f"{col}_{row}.{layer.fmt}").write_bytes(data)
        with self._lock:
            self.written += 1


def _leaf(w: _Writer, level: int, row: int, col: int) -> list[np.ndarray]:
    """Read a leaf's full-size window from every layer; write its tiles from full size up to
    ``level``; return its tile at ``level`` per layer (float32 once halved; a uint8 window
    stays uint8 at full size, a quarter of the bytes to encode and halve)."""
    lay = w.layout
    ys, xs = lay.footprint(level, row, col)
    out = []
    for k, layer in enumerate(w.layers):
        a = np.asarray(layer.read(ys, xs))
        if a.dtype != np.uint8:
            a = a.astype(np.float32, copy=False)
        if a.ndim == 2:
            a = a[:, :, None]
        if a.shape[:2] != (ys.stop - ys.start, xs.stop - xs.start):
            raise ValueError(f"layer {layer.name}: read({ys}, {xs}) gave shape {a.shape}")
        T = lay.tile_size
        for lv in range(lay.max_level, level - 1, -1):
            f = 2 ** (lv - level)  # tiles of lv per tile of level, per axis
            for i in range(0, a.shape[0], T):
                for j in range(0, a.shape[1], T):
                    w.write(k, lv, row * f + i // T, col * f + j // T, a[i:i + T, j:j + T])
            if lv > level:
                a = halve(a, layer.reduce)
        out.append(a)
    return out


def _is_leaf(lay: DziLayout, level: int, block: int) -> bool:
    """Whether a tile of ``level`` is built from one window read (at most ``block`` px)."""
    return lay.tile_size * lay.scale(level) <= block or level == lay.max_level


def _node(w: _Writer, level: int, row: int, col: int, block: int) -> list[np.ndarray]:
    """Write the tile ``(level, row, col)`` and every finer tile below it; return it."""
    lay = w.layout
    if _is_leaf(lay, level, block):
        return _leaf(w, level, row, col)
    rows, cols = lay.grid(level + 1)
    at = [(dr, dc) for dr in (0, 1) for dc in (0, 1)
          if 2 * row + dr < rows and 2 * col + dc < cols]
    # leaves (a window read, its tiles encoded and written) run side by side: reading,
    # encoding and writing release the GIL; at most four windows are held at once
    workers = w.workers if _is_leaf(lay, level + 1, block) else 1
    got = thread_map(lambda rc: _node(w, level + 1, 2 * row + rc[0], 2 * col + rc[1], block),
                     at, workers)
    kids = dict(zip(at, got, strict=True))
    out = []
    T = lay.tile_size
    for k, layer in enumerate(w.layers):
        top = kids[0, 0][k]
        h = top.shape[0] + (kids[1, 0][k].shape[0] if (1, 0) in kids else 0)
        wd = top.shape[1] + (kids[0, 1][k].shape[1] if (0, 1) in kids else 0)
        a = np.zeros((h, wd, top.shape[2]), np.float32)
        for (dr, dc), tiles in kids.items():
            t = tiles[k]
            a[dr * T:dr * T + t.shape[0], dc * T:dc * T + t.shape[1]] = t
        a = halve(a, layer.reduce)
        w.write(k, level, row, col, a)
        out.append(a)
    return out


def build_pyramids(root: str | Path, layers: Sequence[Layer], shape: tuple[int, int], *,
                   tile_size: int = 256, block: int = 1024,
                   workers: int | None = None) -> DziLayout:
    """Write one Deep Zoom pyramid per layer into ``root``, reading windows of at most
    ``block`` x ``block`` full-size pixels.

    Parameters
    ----------
    root : path
        Directory (created) for ``NAME.dzi`` and ``NAME_files/`` of every layer.
    layers : sequence of Layer
        The pyramids to write, all of the same image size.
    shape : (int, int)
        Full size ``(height, width)``.
    tile_size : int
        Side of the tiles.
    block : int
        Side of the largest window read from a source (a multiple of ``tile_size`` is best).
    workers : int, optional
        Threads building the windows of the same parent tile side by side (OpenCV
        single-threaded in each); default the CPUs available to the process.  The
        pyramids do not depend on it.

    Returns
    -------
    DziLayout
    """
    if block < tile_size:
        raise ValueError(f"block ({block}) must be at least tile_size ({tile_size})")
    n_workers = available_cpus() if workers is None else int(workers)
    if n_workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if len({layer.name for layer in layers}) != len(layers):
        raise ValueError("every layer needs its own name")
    layout = DziLayout(int(shape[1]), int(shape[0]), int(tile_size))
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    w = _Writer(root, layers, layout)
    w.workers = n_workers
    _node(w, 0, 0, 0, int(block))
    if w.written != layout.n_tiles() * len(layers):  # pragma: no cover - a bug if it happens
        raise RuntimeError(f"wrote {w.written} tiles, the layout has "
                           f"{layout.n_tiles() * len(layers)}")
    return layout
