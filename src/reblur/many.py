"""One reference against many observations: the frames of a video, repeated flights.

:func:`detect_changes_many` compares a reference with each observation in turn, sharing
what depends on the reference alone (:class:`~reblur.refcache.ReferenceCache`); an
observation that fails (refused alignment, unreadable) gets its one-line reason and the
run goes on.  :func:`observation_sources` and :func:`iter_observations` turn the
command line's observations (files, folders, glob patterns, video files read frame by frame
through OpenCV) into named observations; :func:`summary_row`, :func:`write_summary_csv`
and :func:`write_index_html` write the list of results (``summary.csv``,
``index.html``) of ``reblur detect REF OBS [OBS ...]``.
"""

from __future__ import annotations

import csv
import glob
import html
import inspect
import logging
import math
import os
import re
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np

from .io import InputError, atomic_path, display_path, printable
from .refcache import ReferenceCache
from .result import ChangeResult

__all__ = [
    "IMAGE_SUFFIXES",
    "SUMMARY_COLUMNS",
    "VIDEO_SUFFIXES",
    "Observation",
    "ObservationResult",
    "Source",
    "detect_changes_many",
    "iter_observations",
    "observation_sources",
    "parse_frames",
    "read_video_frames",
    "summary_row",
    "write_index_html",
    "write_summary_csv",
]

log = logging.getLogger(__name__)

#: File name suffixes taken as images in a folder of observations.
IMAGE_SUFFIXES = frozenset({
    ".png", ".jpg", ".jpeg", ".jpe", ".tif", ".tiff", ".webp", ".bmp", ".jp2", ".j2k",
    ".jxl", ".avif", ".gif", ".pgm", ".ppm", ".pnm",
})
#: File name suffixes read as videos, frame by frame (OpenCV's ``VideoCapture``).
VIDEO_SUFFIXES = frozenset({
    ".avi", ".mp4", ".m4v", ".mov", ".mkv", ".webm", ".mpg", ".mpeg", ".wmv", ".flv",
    ".ts", ".mts", ".m2ts", ".3gp", ".ogv",
})
#: Names an observation's folder may not take (the files of the run's own listing).
RESERVED_NAMES = frozenset({"index.html", "summary.csv"})
#: Keywords of :func:`reblur.detect_changes` that cannot be shared by several observations.
#: (each holds one result's arrays or files: shared, the last observation would overwrite
#: the others')
_NOT_SHARED = ("reference_cache", "change_out", "unknown_out", "reblurred_out", "work_dir")


# ---------------------------------------------------------------------------- library
@dataclass
class ObservationResult:
    """The outcome of one observation of :func:`detect_changes_many`.

    Attributes
    ----------
    name : str
        The observation's name.
    result : ChangeResult or None
        The detection, or None when it failed.
    error : str or None
        Why it failed, on one line (None when it did not).
    seconds : float
        Wall-clock time spent on it (loading included).
    """

    name: str
    result: ChangeResult | None
    error: str | None
    seconds: float

    @property
    def ok(self) -> bool:
        """Whether the detection succeeded."""
        return self.error is None


def one_line_reason(exc: BaseException) -> str:
    """Why ``exc`` stopped an observation, on one line (no traceback)."""
    text = " ".join(str(exc).split())
    if isinstance(exc, (ValueError, OSError)) and text:
        return text
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def detect_changes_many(
    reference,
    observations: Iterable[Any],
    *,
    reference_cache: ReferenceCache | None = None,
    **options: Any,
) -> Iterator[ObservationResult]:
    """Compare one reference with many observations, its own work done once.

    Each observation is compared with ``reference`` by :func:`reblur.detect_changes` with
    the same ``options``, sharing one :class:`~reblur.refcache.ReferenceCache`: the
    reference's overviews, alignment pyramid and features are computed for the first
    observation and reused for the others.  Each result is the one a separate call gives.
    An observation that fails (its loader raises, the alignment refuses it, ...) yields a
    result with the reason and the run goes on.

    Parameters
    ----------
    reference : array-like, (H, W) or (H, W, C)
        The sharp reference.
    observations : iterable
        Array-likes, ``(name, array-like)`` pairs, or ``(name, loader)`` pairs where
        ``loader()`` returns the array-like (it is called inside the observation's
        error handling: a file that cannot be read fails that observation alone).  Read
        lazily: a generator holds one observation at a time.  Unnamed observations are
        called ``observation-0001``, ``observation-0002``, ...
    reference_cache : ReferenceCache, optional
        A cache of ``reference`` to fill or reuse (default: a new one).
    **options
        Keywords of :func:`reblur.detect_changes` (all but ``reference_cache``,
        ``change_out`` and ``unknown_out``).

    Returns
    -------
    iterator of ObservationResult
        One per observation, in order, each yielded as soon as it is done (so that only
        one result need be held; ``list(...)`` keeps them all).
        ``result.decision["reference_cache"]`` says what each reused.

    Raises
    ------
    TypeError
        An unknown keyword in ``options``.
    ValueError
        A keyword that cannot be shared by several observations, or a cache of another
        reference.

    Examples
    --------
    >>> import numpy as np, cv2
    >>> from reblur.many import detect_changes_many
    >>> rng = np.random.default_rng(0)
    >>> ref = cv2.GaussianBlur(rng.random((256, 256)), (0, 0), 2)
    >>> ref = (ref - ref.min()) / np.ptp(ref)
    >>> bad = np.zeros((8, 8))
    >>> blurred = cv2.GaussianBlur(ref, (0, 0), 1.0)
    >>> for r in detect_changes_many(ref, [("blurred", blurred), ("tiny", bad)],
    ...                              align=False, t_max=2, rz_max=0):
    ...     print(r.name, r.ok, r.error or "-")
    blurred True -
    tiny False observed is too small (8x8); at least 32x32 is needed
    """
    from .pipeline import detect_changes

    known = set(inspect.signature(detect_changes).parameters) - {"reference", "observed"}
    unknown = sorted(set(options) - known)
    if unknown:
        raise TypeError(f"detect_changes_many got unknown option(s) {unknown}; they must be "
                        "keywords of reblur.detect_changes")
    shared = sorted(set(options) & set(_NOT_SHARED))
    if shared:
        raise ValueError(f"{', '.join(shared)} cannot be shared by several observations: "
                         "call reblur.detect_changes for each observation instead")
    cache = ReferenceCache(reference) if reference_cache is None else reference_cache
    if cache.reference is not reference:
        raise ValueError("reference_cache was made for another reference: pass "
                         "reference_cache.reference as the reference")
    return _run_many(detect_changes, reference, observations, cache, options)


def _run_many(detect_changes: Callable[..., ChangeResult], reference, observations,
              cache: ReferenceCache, options: dict[str, Any]) -> Iterator[ObservationResult]:
    for i, item in enumerate(observations, 1):
        name, source = _named(item, i)
        t0 = time.perf_counter()
        try:
            observed = source() if callable(source) else source
            result = detect_changes(reference, observed, reference_cache=cache, **options)
        except Exception as exc:  # noqa: BLE001 - one observation fails, the run goes on
            log.info("%s: failed: %s", name, one_line_reason(exc))
            yield ObservationResult(name, None, one_line_reason(exc), time.perf_counter() - t0)
            continue
        yield ObservationResult(name, result, None, time.perf_counter() - t0)


def _named(item: Any, i: int) -> tuple[str, Any]:
    if isinstance(item, tuple) and len(item) == 2 and isinstance(item[0], str):
        return item[0], item[1]
    return f"observation-{i:04d}", item


# ---------------------------------------------------------------------------- sources
@dataclass(frozen=True)
class Source:
    """One observation argument, resolved: an image file (or zarr store) or a video."""

    path: Path
    kind: str  # "image" or "video"


@dataclass(frozen=True)
class Observation:
    """One observation of a run: its folder name, where it comes from and how to load it.

    Attributes
    ----------
    name : str
        Unique, file-system-safe name (the observation's output folder).
    label : str
        Where it comes from: the file, or ``VIDEO#FRAME``.
    path : Path
        The image or video file.
    frame : int or None
        The video frame (0-based), None for an image file.
    array : ndarray or None
        The decoded video frame (RGB), None for an image file (opened when needed).
    """

    name: str
    label: str
    path: Path
    frame: int | None = None
    array: np.ndarray | None = None


def parse_frames(text: str | None) -> tuple[int, int | None]:
    """``"A:B"`` -> ``(A, B)``: video frames ``A <= i < B`` (0-based; either may be left
    out: ``"10:"``, ``":100"``); None -> ``(0, None)``.

    Raises
    ------
    ValueError
        Not of that form, negative, or ``B <= A``.
    """
    if text is None:
        return 0, None
    m = re.fullmatch(r"\s*(\d*)\s*:\s*(\d*)\s*", str(text))
    if m is None:
        raise ValueError(f"frames must be A:B (0-based frame numbers, B excluded, either "
                         f"may be left out), got {text!r}")
    start = int(m.group(1)) if m.group(1) else 0
    stop = int(m.group(2)) if m.group(2) else None
    if stop is not None and stop <= start:
        raise ValueError(f"frames {text!r} select no frame: B must be larger than A")
    return start, stop


def _is_zarr(p: Path) -> bool:
    return p.is_dir() and any((p / n).exists() for n in ("zarr.json", ".zarray", ".zgroup"))


def observation_sources(args: Sequence[str | os.PathLike]) -> list[Source]:
    """The observations the command line names, in order.

    Each argument is a file (an image, or a video when its suffix is one of
    :data:`VIDEO_SUFFIXES`), a zarr store, a folder (its image files and zarr stores,
    sorted by name; not recursive), or a glob pattern (``*``, ``?``, ``[...]``; its
    matches sorted by name).

    Raises
    ------
    InputError
        A path that does not exist and matches nothing, or a folder without images.
    """
    out: list[Source] = []
    for arg in args:
        p = Path(arg)
        if p.is_dir() and not _is_zarr(p):
            found = sorted(q for q in p.iterdir()
                           if (q.is_file() and q.suffix.lower() in IMAGE_SUFFIXES)
                           or _is_zarr(q))
            if not found:
                raise InputError(f"{display_path(p)}: folder holds no image "
                                 f"({', '.join(sorted(IMAGE_SUFFIXES)[:6])}, ...)")
            out.extend(Source(q, "image") for q in found)
        elif p.exists() or p.is_symlink() or not glob.has_magic(str(arg)):
            out.append(Source(p, "video" if p.suffix.lower() in VIDEO_SUFFIXES else "image"))
        else:
            matches = sorted(Path(m) for m in glob.glob(str(arg)))
            if not matches:
                raise InputError(f"{display_path(arg)}: no file matches this pattern")
            out.extend(Source(m, "video" if m.suffix.lower() in VIDEO_SUFFIXES else "image")
                       for m in matches if not m.is_dir() or _is_zarr(m))
    return out


def read_video_frames(
    path: str | os.PathLike, *, every: int = 1, frames: tuple[int, int | None] = (0, None)
) -> Iterator[tuple[int, np.ndarray]]:
    """The frames of a video, one at a time, through OpenCV's ``VideoCapture``.

    Parameters
    ----------
    path : path-like
        A video file OpenCV can read.
    every : int
        Take every ``every``-th frame from the first one selected.
    frames : (int, int or None)
        Frames ``start <= i < stop`` (0-based; None: to the end), e.g. from
        :func:`parse_frames`.

    Yields
    ------
    index : int
        The frame's number (0-based).
    frame : (H, W, 3) uint8 ndarray
        The frame, RGB.

    Raises
    ------
    InputError
        OpenCV cannot open the file as a video.
    """
    import cv2

    if int(every) < 1:
        raise ValueError(f"every must be at least 1, got {every}")
    start, stop = frames
    p = Path(path)
    cap = cv2.VideoCapture(str(p))
    try:
        if not cap.isOpened():
            raise InputError(f"{display_path(p)}: cannot open the video (not a file or "
                             "format OpenCV's video reader can read)")
        announced = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        i = 0
        while stop is None or i < stop:
            want = i >= start and (i - start) % int(every) == 0
            if want:
                ok, frame = cap.read()
            else:
                ok, frame = cap.grab(), None
            if not ok:
                if 0 < announced and i < min(announced, stop or announced):
                    log.warning("%s: the video ended at frame %d of the %d it announces",
                                display_path(p), i, announced)
                break
            if want:
                if frame.ndim == 2:
                    frame = cv2.cvtColor(frame, cv2.COLOR_GRAY2RGB)
                yield i, cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
            i += 1
    finally:
        cap.release()


def _safe(text: str) -> str:
    name = re.sub(r"[^A-Za-z0-9._+-]+", "_", text).strip("_") or "observation"
    return "_" + name[1:] if name.startswith(".") else name


def iter_observations(
    sources: Sequence[Source], *, every: int = 1, frames: tuple[int, int | None] = (0, None),
    on_error: Callable[[Source, Exception], None] | None = None,
) -> Iterator[Observation]:
    """The observations of ``sources``, named, in order; video frames decoded one at a time.

    An image's name is its file name without the suffix, a video frame's
    ``STEM-fNNNNNN`` (its 0-based number); characters other than letters, digits and
    ``._+-`` become ``_``, and a name already taken gets ``-2``, ``-3``, ...

    ``on_error(source, exc)`` is called for a video that cannot be opened (and the run
    goes on); without it the error is raised.
    """
    taken: set[str] = set(RESERVED_NAMES)

    def unique(base: str) -> str:
        name, k = base, 1
        while name.lower() in taken:
            k += 1
            name = f"{base}-{k}"
        taken.add(name.lower())
        return name

    for src in sources:
        stem = _safe(src.path.stem if src.path.suffix else src.path.name)
        if src.kind == "image":
            yield Observation(unique(stem), str(src.path), src.path)
            continue
        try:
            for i, frame in read_video_frames(src.path, every=every, frames=frames):
                yield Observation(unique(f"{stem}-f{i:06d}"), f"{src.path}#{i}", src.path, i,
                                  frame)
        except InputError as exc:
            if on_error is None:
                raise
            on_error(src, exc)


# ---------------------------------------------------------------------------- listing
#: Columns of ``summary.csv``.
SUMMARY_COLUMNS = (
    "name", "source", "status", "reason", "changed_percent", "changed_px", "unknown_percent",
    "regions", "top_scores", "threshold", "alignment", "seconds", "detect_s", "report_s",
    "reused", "folder",
)


def _num(v: Any, digits: int = 4) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    return f"{v:.{digits}g}" if isinstance(v, float) else str(v)


def _secs(v: Any) -> str:
    return "" if v is None or not math.isfinite(float(v)) else f"{float(v):.2f}"


def summary_row(name: str, source: str, summary: dict[str, Any] | None = None, *,
                reason: str | None = None, seconds: float | None = None) -> dict[str, str]:
    """One row of ``summary.csv``: from the observation's ``report.json`` content, or the
    one-line ``reason`` it failed.

    Flagged share (``changed_percent``: % of the observation's pixels), regions, the three
    strongest region scores (a region's mean statistic over the threshold), the threshold,
    the alignment's method, timings (``seconds``: the observation's total, loading and
    writing included; ``detect_s``: the detection; ``report_s``: writing its outputs) and
    what the detection took from the reference cache (``reused``).
    """
    row = {k: "" for k in SUMMARY_COLUMNS}
    row.update(name=name, source=source, seconds=_secs(seconds))
    if summary is None:
        row.update(status="failed", reason=" ".join(str(reason or "failed").split()))
        return row
    c = summary.get("changes", {})
    t = summary.get("timings_s", {})
    scores = [r["score"] for r in c.get("regions", [])[:3] if r.get("score") is not None]
    cache = summary.get("decision", {}).get("reference_cache") or {}
    details = (summary.get("alignment") or {}).get("details") or {}
    row.update(
        status="ok", changed_percent=_num(100 * (c.get("changed_fraction") or 0.0)),
        changed_px=_num(c.get("changed_px")),
        unknown_percent=_num(100 * (c.get("unknown_fraction") or 0.0)),
        regions=_num(c.get("n_regions")), top_scores=" ".join(f"{s:.3g}" for s in scores),
        threshold=_num(summary.get("threshold")), alignment=str(details.get("method", "")),
        detect_s=_secs(t.get("total")), report_s=_secs(t.get("report")),
        reused=" ".join(f"{k}:{v}" for k, v in sorted((cache.get("reused") or {}).items())),
        folder=name,
    )
    return row


def write_summary_csv(path: str | os.PathLike, rows: Iterable[dict[str, str]]) -> Path:
    """``summary.csv``: one row per observation (:data:`SUMMARY_COLUMNS`), written
    atomically."""
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=list(SUMMARY_COLUMNS))
        w.writeheader()
        for r in rows:
            w.writerow({k: printable(str(r.get(k, ""))) for k in SUMMARY_COLUMNS})
    return Path(path)


_INDEX_CSS = """body{font-family:sans-serif;margin:2em;color:#222}
table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:4px 8px;text-align:left;
vertical-align:top}tr.failed td{background:#fdd}img{max-width:200px;max-height:120px}"""


def write_index_html(path: str | os.PathLike, rows: Sequence[dict[str, str]], *,
                     reference: str, totals: dict[str, Any] | None = None) -> Path:
    """``index.html``: every observation with its overlay, key numbers and links to its
    report and its zoomable viewer; a failed one with its reason.  Links are relative
    (the folder can move)."""
    head = ["observation", "overlay", "status", "flagged %", "regions", "top scores",
            "seconds", "source"]
    body = []
    for r in rows:
        name = html.escape(r["name"])
        # the folder's name as a URL path segment: its bytes percent-encoded ('#', '?', '%'
        # or a name that is not UTF-8 would otherwise break the link)
        href = quote(os.fsencode(r["name"]), safe="")
        if r["status"] == "ok":
            link = (f'<a href="{href}/report.html">{name}</a> '
                    f'(<a href="{href}/viewer/index.html">viewer</a>)')
            pic = f'<a href="{href}/report.html"><img src="{href}/overlay.png" alt=""></a>'
            status = "ok"
        else:
            link, pic = name, ""
            status = "failed: " + html.escape(r["reason"])
        cells = [link, pic, status, html.escape(r["changed_percent"]),
                 html.escape(r["regions"]), html.escape(r["top_scores"]),
                 html.escape(r["seconds"]), html.escape(r["source"])]
        cls = "" if r["status"] == "ok" else ' class="failed"'
        body.append(f"<tr{cls}>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    n_ok = sum(r["status"] == "ok" for r in rows)
    extra = ""
    if totals:
        reused = ", ".join(f"{k} {v}x" for k, v in sorted(totals.get("reused", {}).items()))
        extra = (f"<p>Reference work reused: {html.escape(reused or 'nothing')} "
                 "(see each report.json, decision.reference_cache).</p>")
    page = (
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>reblur: "
        f"{len(rows)} observations</title><style>{_INDEX_CSS}</style></head><body>"
        f"<h1>{len(rows)} observations of {html.escape(reference)}</h1>"
        f"<p>{n_ok} ok, {len(rows) - n_ok} failed. summary.csv holds the same list.</p>"
        f"{extra}<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>\n"
        + "\n".join(body) + "</table></body></html>\n"
    )
    with atomic_path(path) as tmp:
        Path(tmp).write_text(printable(page), encoding="utf-8")
    return Path(path)
