"""A zoomable, offline viewer of one detection: ``DIR/viewer/index.html``.

:func:`write_viewer` writes, into a ``viewer`` folder:

``tiles/NAME.dzi``, ``tiles/NAME_files/``
    Deep Zoom tile pyramids (:mod:`reblur.viewer.pyramid`), built window by window, of the
    observation, the reblurred reference, the change mask (translucent red; a changed pixel
    stays visible at every zoom) and the unknown pixels.
``regions.json``
    The strongest regions (the report's triage order, at most
    :attr:`ViewerOptions.max_regions`) with their attributes and outlines in image
    pixels, the total count, and the estimation windows.
``data.js``
    The same, with the pyramids' geometry, for the page (a script, so the page also works
    opened straight from the disk, where a browser refuses to fetch files).
``index.html``, ``static/``
    The page and OpenSeadragon (BSD-3-Clause, vendored: its licence is in
    ``static/LICENSE-openseadragon.txt``); nothing is fetched from elsewhere.

The page shows the observation from the whole image down to single pixels, with layers:
change outlines coloured by polarity (brighter / appeared, darker / disappeared, mixed),
the change fill, unknown pixels, the reblurred reference (a swipe against the observation),
and the estimation windows.  A click on a region shows its attributes.  The page writes
its state into ``document.title`` (``regions:N tiles:M failed:K ...``) for tests.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from ..io import to_jsonable
from .layers import (
    CHANGE_RGB,
    UNKNOWN_RGB,
    image_layer,
    mask_layer,
    reblurred_source,
    sample_stretch,
)
from .outlines import region_records
from .pyramid import DziLayout, Layer, build_pyramids

__all__ = ["ViewerOptions", "ViewerInfo", "write_viewer", "build_pyramids", "DziLayout",
           "Layer", "VIEWER_DIR"]

#: The viewer's folder in an output directory.
VIEWER_DIR = "viewer"

#: The page's files in the package (copied into every viewer folder).
_STATIC = ("openseadragon.min.js", "LICENSE-openseadragon.txt", "viewer.js", "viewer.css")


@dataclass(frozen=True)
class ViewerOptions:
    """How the viewer is written.

    Attributes
    ----------
    tile_size : int
        Side of the pyramid tiles (pixels).  512 px tiles make a quarter of the files of
        256 px ones; inside a 100 MP run, whose COGs are written at the same time, the
        writing of a 45 %-changed pair took 10.6 s against 12.1 s (the same for an unchanged
        pair).
    block : int
        Side of the largest window read from an image or mask while building the pyramids
        (2048 px saved 3 % of a 100 MP run's writing but added 140 MB to its peak memory).
    image_format : {"jpg", "png"}
        Tiles of the observation and the reblurred reference (masks are always PNG).
    quality : int
        JPEG quality.
    max_regions : int
        Outlines drawn for at most this many regions, the strongest (the page states how
        many of how many).
    max_vertices : int
        Most vertices of one outline.
    outline_side : int
        Region boxes longer than this are traced at a coarser scale.
    """

    tile_size: int = 512
    block: int = 1024
    image_format: str = "jpg"
    quality: int = 90
    max_regions: int = 500
    max_vertices: int = 200
    outline_side: int = 2048

    def __post_init__(self) -> None:
        if not 16 <= self.tile_size <= 4096:
            raise ValueError(f"tile_size must be 16..4096 pixels, got {self.tile_size}")
        if self.block < self.tile_size:
            raise ValueError(f"block ({self.block}) must be at least tile_size "
                             f"({self.tile_size})")
        if self.image_format not in ("jpg", "png"):
            raise ValueError(f"image_format must be 'jpg' or 'png', got {self.image_format!r}")
        if not 1 <= self.quality <= 100:
            raise ValueError(f"quality must be 1..100, got {self.quality}")
        if self.max_regions < 0 or self.max_vertices < 4 or self.outline_side < 16:
            raise ValueError("max_regions must be >= 0, max_vertices >= 4 and "
                             "outline_side >= 16")


@dataclass
class ViewerInfo:
    """What :func:`write_viewer` wrote.

    Attributes
    ----------
    index : Path
        The page.
    layout : DziLayout
        The pyramids' geometry (all layers alike).
    layers : list of str
        The pyramids written.
    n_regions, shown : int
        Regions in the result, and how many the page outlines.
    notes : list of str
        What the viewer leaves out and why.
    time_s : float
        Seconds spent.
    """

    index: Path
    layout: DziLayout
    layers: list[str]
    n_regions: int
    shown: int
    notes: list[str] = field(default_factory=list)
    time_s: float = 0.0


def _layers(result: Any, observed: Any, reblurred_path: Path | None,
            opts: ViewerOptions) -> tuple[list[Layer], list[dict[str, Any]], list[str], list]:
    """The raster layers, their descriptions for the page, notes, and handles to close."""
    change, unknown = result.change, result.unknown
    notes: list[str] = []
    handles = []
    rb, scale, note = reblurred_source(result, observed, reblurred_path)
    if note:
        notes.append(note)
    if hasattr(rb, "close") and hasattr(rb, "array"):  # reblurred.tif, opened lazily
        handles.append(rb)
        rb = rb.array
    if observed is not None:
        base, dtype = observed.array, np.dtype(observed.dtype)
    elif rb is not None:
        base, dtype = rb, np.dtype(np.float32)
        notes.append("no observation given: the base layer is the reblurred reference")
    else:
        base, dtype = _BoolU8(change), np.dtype(np.uint8)
        notes.append("no observation and no reblurred image: the base layer is the mask")
    stretch = sample_stretch(base, dtype)
    fmt = dict(fmt=opts.image_format, quality=opts.quality)
    layers = [image_layer("observed", base, stretch, **fmt)]
    desc = [dict(name="observed", label="observation", kind="image")]
    if rb is not None and observed is not None:
        layers.append(image_layer("reblurred", rb, stretch, scale=scale, **fmt))
        desc.append(dict(name="reblurred", label="reblurred reference", kind="swipe"))
    layers.append(mask_layer("unknown", unknown, UNKNOWN_RGB, alpha=0.75, reduce="mean"))
    desc.append(dict(name="unknown", label="unknown (not covered)", kind="mask"))
    layers.append(mask_layer("changes", change, CHANGE_RGB, alpha=0.45, reduce="max",
                             exclude=unknown))
    desc.append(dict(name="changes", label="change fill", kind="mask"))
    for d, layer in zip(desc, layers, strict=True):
        d["format"] = layer.fmt
    return layers, desc, notes, handles


class _BoolU8:
    """uint8 0/255 view of a bool array-like."""

    def __init__(self, mask: Any):
        self.mask, self.shape, self.dtype = mask, tuple(mask.shape[:2]), np.dtype(np.uint8)

    def __getitem__(self, key) -> np.ndarray:
        return np.asarray(self.mask[key], dtype=bool).astype(np.uint8) * np.uint8(255)


class _Known:
    """``change & ~unknown`` of two bool array-likes (the mask the regions come from)."""

    def __init__(self, change: Any, unknown: Any):
        self.change, self.unknown = change, unknown
        self.shape, self.dtype = tuple(change.shape[:2]), np.dtype(bool)

    def __getitem__(self, key) -> np.ndarray:
        return np.asarray(self.change[key], dtype=bool) & ~np.asarray(self.unknown[key],
                                                                       dtype=bool)


def _windows(result: Any) -> list[list[int]]:
    """The estimation windows ``[y0, x0, h, w]``."""
    boxes = list(getattr(result.motion, "boxes", None) or []) or list(result.crop.boxes)
    return [[int(v) for v in b] for b in boxes]


def _copy_static(dest: Path) -> None:
    src = resources.files(__name__) / "static"
    (dest / "static" / "images").mkdir(parents=True, exist_ok=True)
    for name in _STATIC:
        (dest / "static" / name).write_bytes((src / name).read_bytes())
    for img in (src / "images").iterdir():
        if img.name.endswith(".png"):
            (dest / "static" / "images" / img.name).write_bytes(img.read_bytes())
    (dest / "index.html").write_bytes((src / "index.html").read_bytes())


_MARKERS = ("index.html", "data.js", "tiles")


def _clear_viewer_folder(out: Path) -> None:
    """Empty ``out`` if it is an earlier viewer; refuse any other non-empty folder."""
    if not out.exists() and not out.is_symlink():
        return
    if not out.is_dir() or out.is_symlink():
        raise ValueError(f"{out} exists and is not a folder: give write_viewer a new or "
                         "empty folder, or an earlier viewer's")
    if not any(out.iterdir()):
        return
    if not all((out / m).exists() for m in _MARKERS):
        raise ValueError(f"{out} is not empty and not an earlier viewer (no index.html, "
                         "data.js and tiles/): give write_viewer a new or empty folder")
    for p in out.iterdir():
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()


def write_viewer(
    out_dir: str | Path,
    result: Any,
    *,
    observed: Any = None,
    regions: list[dict[str, Any]] | None = None,
    n_regions: int | None = None,
    reblurred_path: str | Path | None = None,
    options: ViewerOptions | None = None,
) -> ViewerInfo:
    """Write the zoomable viewer of a detection into ``out_dir`` (the ``viewer`` folder).

    Parameters
    ----------
    out_dir : path
        The viewer's folder: new, empty or an earlier viewer (whose files are replaced);
        any other non-empty folder is refused (ValueError), its files left as they are.
    result : ChangeResult
        What :func:`reblur.detect_changes` returned; its masks and reblurred image may be
        lazy (zarr): every image is read window by window.
    observed : reblur.io.Image, optional
        The observation (the base layer; its dtype sets the display stretch).
    regions : list of dict, optional
        Region records in the report's triage order (``report.json``'s
        ``changes.regions``); default: ``result.regions`` as they are.
    n_regions : int, optional
        How many regions the result has in all (default: ``len(regions)``).
    reblurred_path : path, optional
        ``reblurred.tif``, read back window by window when the result holds no reblurred
        image.
    options : ViewerOptions, optional

    Returns
    -------
    ViewerInfo
    """
    t0 = time.perf_counter()
    opts = options or ViewerOptions()
    out = Path(out_dir)
    H, W = (int(v) for v in result.change.shape[:2])
    if observed is not None and tuple(observed.shape[:2]) != (H, W):
        raise ValueError(f"result is {W}x{H} but the observation is "
                         f"{observed.shape[1]}x{observed.shape[0]}")
    _clear_viewer_folder(out)
    out.mkdir(parents=True, exist_ok=True)
    layers, desc, notes, handles = _layers(
        result, observed, Path(reblurred_path) if reblurred_path else None, opts)
    try:
        layout = build_pyramids(out / "tiles", layers, (H, W), tile_size=opts.tile_size,
                                block=opts.block)
    finally:
        for h in handles:
            h.close()
    regions = list(result.regions if regions is None else regions)
    total = len(regions) if n_regions is None else int(n_regions)
    recs = region_records(_Known(result.change, result.unknown), regions,
                          max_regions=opts.max_regions,
                          max_side=opts.outline_side, max_vertices=opts.max_vertices)
    if total > len(recs):
        notes.append(f"outlines of the {len(recs)} strongest of {total} regions")
    data = dict(width=W, height=H, tile_size=layout.tile_size, max_level=layout.max_level,
                layers=[dict(d, url=f"tiles/{d['name']}_files/", dzi=f"tiles/{d['name']}.dzi")
                        for d in desc],
                n_regions=total, shown=len(recs), regions=recs, windows=_windows(result),
                notes=notes)
    text = json.dumps(to_jsonable(data), separators=(",", ":"), allow_nan=False)
    (out / "regions.json").write_text(text, encoding="utf-8")
    (out / "data.js").write_text(f"window.REBLUR_VIEWER = {text};\n", encoding="utf-8")
    _copy_static(out)
    return ViewerInfo(out / "index.html", layout, [d["name"] for d in desc], total,
                      len(recs), notes, time.perf_counter() - t0)
