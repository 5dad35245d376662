"""Real scenes for the test bed: shared aerial imagery, window-wise upsampling, pasted changes.

Scenes are real photographs (LEVIR-CD and WHU building-change images from the project's
shared data folder), not synthetic textures.  Large scenes are *readers*: objects with
``.shape``, ``.dtype`` and 2-D slicing that compute only the requested window, so a 100 MP
scene is never held in memory.  Change objects (rectangles, star-shaped blobs, thin bars and
L shapes) are defined analytically and pasted into the scene before the observation is
rendered, so they are blurred like everything else; their ground truth in the observation
frame is their footprint pushed through the same sub-pose homographies (half maximum).
reblur's simulator pastes its changes on an already rendered frame with its own code; none
of that is used here.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .render import Box, _apply, _check_homographies, _inverses

__all__ = [
    "DATA_ENV",
    "ChangeObject",
    "ChangedScene",
    "DataMissing",
    "CroppedScene",
    "UpsampledScene",
    "change_boxes",
    "levir_image",
    "load_image",
    "paste_changes",
    "scene_names",
    "shared_data_dir",
    "truth_window",
    "upsampled",
    "whu_image",
]

_KINDS = ("rect", "blob", "thin", "L")
_KIND_P = (0.35, 0.35, 0.15, 0.15)


#: Environment variable naming the shared data folder (default ``<repo>/../shared/data``).
DATA_ENV = "REBLUR_DATA"


class DataMissing(FileNotFoundError):
    """The shared data (or a part of it) is not where it is looked for; one-line message."""


def shared_data_dir(check: bool = True) -> Path:
    """The project's shared data folder: ``$REBLUR_DATA``, else ``<repo>/../shared/data``.

    Parameters
    ----------
    check : bool
        Raise :class:`DataMissing` when the folder does not exist.

    Returns
    -------
    pathlib.Path

    Raises
    ------
    DataMissing
        With ``check``, if the folder does not exist.
    """
    env = os.environ.get(DATA_ENV, "").strip()
    if env:
        data = Path(env).expanduser()
    else:
        data = Path(__file__).resolve().parents[3].parent / "shared" / "data"
    if check and not data.is_dir():
        raise DataMissing(missing_data_message(data))
    return data


def missing_data_message(path: Path) -> str:
    """One line saying that ``path`` (a part of the shared data) is missing and how to
    point reblur at the data."""
    how = (f"set {DATA_ENV} to the shared data folder (see its README.md)" if
           not os.environ.get(DATA_ENV, "").strip() else f"check {DATA_ENV}")
    return f"shared data not found: {path} does not exist; {how}, or pass --data DIR"


def require_data(path: Path) -> Path:
    """``path`` (inside the shared data), or :class:`DataMissing` when it does not exist."""
    if not Path(path).exists():
        raise DataMissing(missing_data_message(Path(path)))
    return Path(path)


def load_image(path: str | Path, gray: bool = True) -> np.ndarray:
    """Read an 8- or 16-bit image as float64 in [0, 1], gray (luma) or RGB.

    Parameters
    ----------
    path : str or pathlib.Path
        Image file.
    gray : bool
        Convert to gray with OpenCV's luma weights.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` or ``(H, W, 3)`` float64.
    """
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FileNotFoundError(f"cannot read image {path}")
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY if gray else cv2.COLOR_BGR2RGB)
    elif not gray:
        img = np.repeat(img[..., None], 3, axis=2)
    return img.astype(np.float64) / scale


def _dataset_dir(dataset: str) -> Path:
    sub = {"levir": "samples_LEVIR", "whu": "samples_WHU-CD"}
    if dataset not in sub:
        raise ValueError(f"dataset must be 'levir' or 'whu', got {dataset!r}")
    return require_data(shared_data_dir() / "levir_whu_1024" / sub[dataset])


def scene_names(dataset: str = "levir") -> list[str]:
    """Names (file stems) of the 1024 x 1024 scenes of a dataset ('levir' or 'whu')."""
    folder = "A" if dataset == "levir" else "prev"
    return sorted(p.stem for p in (_dataset_dir(dataset) / folder).glob("*.png"))


def _named(dataset: str, name: str, which: str, allowed: tuple[str, ...], gray: bool):
    if which not in allowed:
        raise ValueError(f"which must be one of {allowed}, got {which!r}")
    path = _dataset_dir(dataset) / which / f"{name}.png"
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found; available: {scene_names(dataset)}")
    return load_image(path, gray)


def levir_image(name: str = "test_7", which: str = "A", gray: bool = True) -> np.ndarray:
    """A LEVIR-CD 1024 x 1024 image (``which`` = 'A' before, 'B' after, 'label')."""
    return _named("levir", name, which, ("A", "B", "label"), gray)


def whu_image(name: str = "000121", which: str = "prev", gray: bool = True) -> np.ndarray:
    """A WHU-CD 1024 x 1024 image (``which`` = 'prev', 'curr' or 'label')."""
    return _named("whu", name, which, ("prev", "curr", "label"), gray)


def _window(key: Any, shape: tuple[int, ...]) -> Box:
    """Turn a 2-D slice key into a clipped box (steps other than 1 are refused)."""
    if not isinstance(key, tuple) or len(key) != 2 or not all(isinstance(k, slice) for k in key):
        raise ValueError("scene readers take 2-D slices, e.g. scene[y0:y1, x0:x1]")
    (r0, r1, rs), (c0, c1, cs) = (k.indices(int(n)) for k, n in zip(key, shape[:2], strict=True))
    if rs != 1 or cs != 1:
        raise ValueError("scene readers take contiguous slices (step 1)")
    return r0, max(r1, r0), c0, max(c1, c0)


class UpsampledScene:
    """Bicubic upsampling of an in-memory image, computed window by window.

    Output pixel ``(x, y)`` samples the source at ``((x + 0.5) / f - 0.5, (y + 0.5) / f -
    0.5)`` (pixel-area aligned), with OpenCV's bicubic and a reflected border, clipped to
    [0, 1].  Windows are independent: any window equals the same part of the whole.

    Parameters
    ----------
    image : numpy.ndarray
        Source, float in [0, 1], ``(H, W)`` or ``(H, W, C)``.
    factor : float
        Upsampling factor, > 0.
    """

    def __init__(self, image: np.ndarray, factor: float) -> None:
        img = np.asarray(image, dtype=np.float32)
        if img.ndim not in (2, 3) or min(img.shape[:2]) < 2:
            raise ValueError(f"image must be (H, W) or (H, W, C), got shape {img.shape}")
        if not np.isfinite(factor) or factor <= 0:
            raise ValueError(f"factor must be a positive number, got {factor!r}")
        self.image, self.factor = img, float(factor)
        size = (round(img.shape[0] * factor), round(img.shape[1] * factor))
        self.shape: tuple[int, ...] = size + img.shape[2:]
        self.dtype = np.dtype(np.float32)

    def __getitem__(self, key: Any) -> np.ndarray:
        y0, y1, x0, x1 = _window(key, self.shape)
        if y1 == y0 or x1 == x0:
            return np.zeros((y1 - y0, x1 - x0) + self.shape[2:], dtype=np.float32)
        u = ((np.arange(x0, x1) + 0.5) / self.factor - 0.5).astype(np.float32)
        v = ((np.arange(y0, y1) + 0.5) / self.factor - 0.5).astype(np.float32)
        mx, my = np.meshgrid(u, v)
        out = cv2.remap(self.image, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT_101)
        return np.clip(out, 0.0, 1.0)


def upsampled(image: np.ndarray, factor: float) -> UpsampledScene:
    """Window-by-window bicubic upsampled scene (see :class:`UpsampledScene`)."""
    return UpsampledScene(image, factor)


class CroppedScene:
    """A rectangular part ``box = (y0, y1, x0, x1)`` of another scene, read lazily."""

    def __init__(self, base: Any, box: Box) -> None:
        y0, y1, x0, x1 = (int(v) for v in box)
        if not (0 <= y0 < y1 <= base.shape[0] and 0 <= x0 < x1 <= base.shape[1]):
            raise ValueError(f"crop {box!r} must lie inside the scene of shape {base.shape}")
        self.base, self.box = base, (y0, y1, x0, x1)
        self.shape: tuple[int, ...] = (y1 - y0, x1 - x0) + tuple(base.shape[2:])
        self.dtype = np.dtype(getattr(base, "dtype", np.float64))

    def __getitem__(self, key: Any) -> np.ndarray:
        r0, r1, c0, c1 = _window(key, self.shape)
        y0, _, x0, _ = self.box
        return np.asarray(self.base[y0 + r0:y0 + r1, x0 + c0:x0 + c1])


def disc_box(cx: float, cy: float, r: float) -> Box:
    """Integer box ``(y0, y1, x0, x1)`` holding the disc of radius ``r`` about ``(cx, cy)``."""
    return (int(np.floor(cy - r)), int(np.ceil(cy + r)) + 1,
            int(np.floor(cx - r)), int(np.ceil(cx + r)) + 1)


def object_frame(x: np.ndarray, y: np.ndarray, cx: float, cy: float, angle: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(x, y)`` in an object's frame: centred on ``(cx, cy)``, rotated by ``-angle``."""
    c, s = np.cos(angle), np.sin(angle)
    return (x - cx) * c + (y - cy) * s, -(x - cx) * s + (y - cy) * c


@dataclass(frozen=True)
class ChangeObject:
    """One pasted change, defined analytically in scene pixel coordinates.

    Attributes
    ----------
    kind : str
        'rect', 'blob', 'thin' (a bar 2..4 px wide) or 'L'.
    cx, cy : float
        Centre (for 'L', the corner).
    angle : float
        Orientation in radians.
    a, b, a2 : float
        Half length, half width and (for 'L') the second arm's length, pixels.
    harmonics : tuple
        ``((c_j, psi_j), ...)`` radial harmonics ``j = 2, 3, ...`` of a blob's outline.
    delta : float
        Added intensity (either sign); the contrast is ``|delta| / local_range``.
    local_range : float
        p98 - p2 of the scene around the object.
    """

    kind: str
    cx: float
    cy: float
    angle: float
    a: float
    b: float
    a2: float
    harmonics: tuple[tuple[float, float], ...]
    delta: float
    local_range: float

    @property
    def radius(self) -> float:
        """Radius of a disc holding the object."""
        return 1.5 * float(np.hypot(max(self.a, self.a2), self.b)) + 1.0

    @property
    def bbox(self) -> Box:
        """Integer box ``(y0, y1, x0, x1)`` holding the object."""
        return disc_box(self.cx, self.cy, self.radius)

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Whether points ``(x, y)`` (any float coordinates) lie inside the object."""
        u, v = object_frame(x, y, self.cx, self.cy, self.angle)
        if self.kind in ("rect", "thin"):
            return (np.abs(u) <= self.a) & (np.abs(v) <= self.b)
        if self.kind == "L":
            arm1 = (u >= -self.b) & (u <= self.a) & (np.abs(v) <= self.b)
            return arm1 | ((np.abs(u) <= self.b) & (v >= -self.b) & (v <= self.a2))
        p, q = u / self.a, v / self.b
        phi = np.arctan2(q, p)
        edge = 1.0 + sum(cj * np.cos(j * phi + pj) for j, (cj, pj) in enumerate(self.harmonics, 2))
        return np.hypot(p, q) <= edge


def _mask_in(objects: tuple[Any, ...], box: Box) -> tuple[np.ndarray, np.ndarray, list]:
    """Pixel-centre coordinates ``(ys, xs)`` of a box and per-object indicators on them
    (only intersecting objects)."""
    y0, y1, x0, x1 = box
    ys, xs = np.mgrid[y0:y1, x0:x1].astype(np.float64)
    hits = []
    for o in objects:
        b = o.bbox
        if b[0] < y1 and b[1] > y0 and b[2] < x1 and b[3] > x0:
            hits.append((o, o.contains(xs, ys)))
    return ys, xs, hits


class ChangedScene:
    """A scene with change objects added, read window by window (values clipped to [0, 1]).

    Parameters
    ----------
    base : array-like
        The unchanged scene (array or reader).
    objects : tuple of ChangeObject or Occluder-like objects
        The changes.  An object with a ``paint(xs, ys)`` method (for instance
        :class:`reblur.testbed.edits.Occluder`) *replaces* the scene inside its outline by
        what it paints there; the others add their ``delta``.
    """

    def __init__(self, base: Any, objects: tuple[ChangeObject, ...]) -> None:
        self.base, self.objects = base, tuple(objects)
        self.shape: tuple[int, ...] = tuple(base.shape)
        self.dtype = np.dtype(np.float64)

    def __getitem__(self, key: Any) -> np.ndarray:
        box = _window(key, self.shape)
        out = np.array(self.base[box[0]:box[1], box[2]:box[3]], dtype=np.float64)
        ys, xs, hits = _mask_in(self.objects, box)
        for o, m in hits:
            if hasattr(o, "paint"):
                v = o.paint(xs[m], ys[m])
                out[m] = v[:, None] if out.ndim == 3 else v
            else:
                out[m] += o.delta
        return np.clip(out, 0.0, 1.0)

    def footprint(self, box: Box) -> np.ndarray:
        """Union of the objects' indicators on a window's pixel centres (scene frame)."""
        _, _, hits = _mask_in(self.objects, box)
        mask = np.zeros((box[1] - box[0], box[3] - box[2]), dtype=bool)
        for _, m in hits:
            mask |= m
        return mask


def _gray(a: np.ndarray) -> np.ndarray:
    return a.mean(axis=2) if a.ndim == 3 else a


def _random_shape(rng: np.random.Generator, size_px: tuple[float, float]) -> dict:
    kind = str(rng.choice(_KINDS, p=_KIND_P))
    a = rng.uniform(*size_px) / 2.0
    b = rng.uniform(1.0, 2.0) if kind == "thin" else a * rng.uniform(0.35, 1.0)
    if kind == "L":
        b = rng.uniform(1.5, max(2.0, a / 4.0))
    harm = tuple((float(rng.uniform(0.0, 0.12)), float(rng.uniform(0, 2 * np.pi)))
                 for _ in range(3))
    return dict(kind=kind, angle=float(rng.uniform(0, np.pi)), a=float(a), b=float(b),
                a2=float(a * rng.uniform(0.5, 1.0)), harmonics=harm)


def signed_delta(rng: np.random.Generator, inside: np.ndarray, local_range: float,
                 contrast: tuple[float, float]) -> float:
    """An object's added intensity: ``+-c * local_range`` with ``c`` uniform in ``contrast``
    and a random sign, flipped when the first choice would push the ``inside`` values out of
    [0, 1]."""
    mag = rng.uniform(*contrast) * local_range
    sign = 1.0 if rng.random() < 0.5 else -1.0
    if (sign > 0 and inside.max() + mag > 1) or (sign < 0 and inside.min() - mag < 0):
        sign = -sign
    return float(sign * mag)


def _place(rng, scene, shape: dict, margin: float, taken: list[Box], min_range: float,
           contrast: tuple[float, float]) -> ChangeObject | None:
    h, w = scene.shape[:2]
    probe = ChangeObject(cx=0.0, cy=0.0, delta=0.0, local_range=0.0, **shape)
    r = probe.radius
    lo_y, lo_x = margin + r, margin + r
    if h - lo_y <= lo_y or w - lo_x <= lo_x:
        return None
    cx, cy = rng.uniform(lo_x, w - lo_x), rng.uniform(lo_y, h - lo_y)
    obj = ChangeObject(cx=cx, cy=cy, delta=0.0, local_range=0.0, **shape)
    b = obj.bbox
    if any(b[0] < t[1] and b[1] > t[0] and b[2] < t[3] and b[3] > t[2] for t in taken):
        return None
    pad = int(np.ceil(r))
    around = (max(b[0] - pad, 0), min(b[1] + pad, h), max(b[2] - pad, 0), min(b[3] + pad, w))
    region = _gray(np.asarray(scene[around[0]:around[1], around[2]:around[3]], np.float64))
    p2, p98 = np.percentile(region, [2, 98])
    if p98 - p2 < min_range:
        return None
    inside = _gray(np.asarray(scene[b[0]:b[1], b[2]:b[3]], np.float64))[
        _mask_in((obj,), b)[2][0][1]]
    return ChangeObject(cx=float(cx), cy=float(cy),
                        delta=signed_delta(rng, inside, p98 - p2, contrast),
                        local_range=float(p98 - p2), **shape)


def paste_changes(
    scene: Any,
    rng: np.random.Generator,
    *,
    n_changes: int = 8,
    contrast: tuple[float, float] = (0.1, 0.4),
    size_px: tuple[float, float] = (12.0, 60.0),
    margin: float = 40.0,
    min_range: float = 0.05,
    max_tries: int = 200,
) -> ChangedScene:
    """Paste random change objects into a scene (lazily: returns a reader).

    Each object adds ``delta = +-c * (p98 - p2)`` to the scene inside its outline, with
    ``c`` uniform in ``contrast`` and the percentiles taken over the object's surroundings
    (its box grown by its radius); the sign is flipped when the first choice would push
    the object's pixels out of [0, 1].  Kinds: rectangles and blobs (35 % each), thin
    bars and L shapes (15 % each).  Objects do not overlap and keep ``margin`` pixels from
    the scene's edges; places whose local range is below ``min_range`` are skipped.

    Parameters
    ----------
    scene : array-like
        Unchanged scene in [0, 1] (array or reader).
    rng : numpy.random.Generator
        Seeded generator.
    n_changes : int
        Number of objects (0 allowed).
    contrast : tuple of float
        Range of the contrast fraction ``c``, within (0, 1].
    size_px : tuple of float
        Range of the objects' lengths in pixels.
    margin : float
        Distance kept from the scene's edges, pixels.
    min_range : float
        Smallest acceptable local range (p98 - p2).
    max_tries : int
        Placement attempts per object before giving up.

    Returns
    -------
    ChangedScene
    """
    lo, hi = contrast
    if not 0 < lo <= hi <= 1:
        raise ValueError(f"contrast must be (lo, hi) with 0 < lo <= hi <= 1, got {contrast!r}")
    if not 2 <= size_px[0] <= size_px[1]:
        raise ValueError(f"size_px must be (lo, hi) with 2 <= lo <= hi, got {size_px!r}")
    if int(n_changes) < 0:
        raise ValueError(f"n_changes must be >= 0, got {n_changes}")
    objects: list[ChangeObject] = []
    for _ in range(int(n_changes)):
        for _ in range(int(max_tries)):
            obj = _place(rng, scene, _random_shape(rng, size_px), margin,
                         [o.bbox for o in objects], min_range, (lo, hi))
            if obj is not None:
                objects.append(obj)
                break
        else:
            raise ValueError(f"could not place {n_changes} non-overlapping changes with local "
                             f"range >= {min_range} in a {scene.shape[:2]} scene with margin "
                             f"{margin}: lower n_changes, size_px, margin or min_range")
    return ChangedScene(scene, tuple(objects))


def _object_obs_box(o: ChangeObject, hs: np.ndarray) -> Box:
    y0, y1, x0, x1 = o.bbox
    cx = np.array([x0, x1, x0, x1], dtype=np.float64)
    cy = np.array([y0, y0, y1, y1], dtype=np.float64)
    pts = np.concatenate([np.stack(_apply(h, cx, cy)) for h in hs], axis=1)
    return (int(np.floor(pts[1].min())) - 1, int(np.ceil(pts[1].max())) + 2,
            int(np.floor(pts[0].min())) - 1, int(np.ceil(pts[0].max())) + 2)


def change_boxes(scene: ChangedScene, homographies: np.ndarray) -> list[Box]:
    """Observation-frame boxes holding each change object under every sub-pose homography.

    Parameters
    ----------
    scene : ChangedScene
        The scene with its change objects.
    homographies : numpy.ndarray
        ``(n, 3, 3)`` reference -> observation homographies.

    Returns
    -------
    list of Box
        One ``(y0, y1, x0, x1)`` per object (unclipped).
    """
    hs = _check_homographies(homographies)
    return [_object_obs_box(o, hs) for o in scene.objects]


def truth_window(
    scene: ChangedScene, homographies: np.ndarray, box: Box, boxes: list[Box] | None = None,
    share: float = 0.5,
) -> np.ndarray:
    """Ground truth of a window of the observation: half-maximum footprint of the changes.

    A pixel ``x`` is changed when ``mean_k 1[H_k^{-1} x in an object] >= share`` (0.5: the
    half-maximum footprint), the objects' indicators evaluated exactly at the sampled
    (continuous) reference location.  A small ``share`` (``1 / n`` or less for ``n``
    sub-poses) gives the changes' whole reach: every pixel that some sub-pose maps into an
    object, where a change alters the observation however faintly (a small object under a
    long blur may have no half-maximum footprint at all).

    Parameters
    ----------
    scene : ChangedScene
        The scene with its change objects.
    homographies : numpy.ndarray
        ``(n, 3, 3)`` reference -> observation homographies.
    box : Box
        Observation window ``(y0, y1, x0, x1)``.
    boxes : list of Box, optional
        :func:`change_boxes` of the same scene and homographies (computed when omitted;
        pass it when rendering many windows).
    share : float
        Least share of the sub-poses, in (0, 1].

    Returns
    -------
    numpy.ndarray
        Boolean ``(y1 - y0, x1 - x0)``.
    """
    hs = _check_homographies(homographies)
    if not 0.0 < share <= 1.0:
        raise ValueError(f"share must be in (0, 1], got {share!r}")
    y0, y1, x0, x1 = box
    boxes = change_boxes(scene, hs) if boxes is None else boxes
    if len(boxes) != len(scene.objects):
        raise ValueError("boxes must be change_boxes(scene, homographies), one per object")
    out = np.zeros((y1 - y0, x1 - x0), dtype=bool)
    near = []
    for o, b in zip(scene.objects, boxes, strict=True):
        b = (max(b[0], y0), min(b[1], y1), max(b[2], x0), min(b[3], x1))
        if b[1] > b[0] and b[3] > b[2]:
            near.append((o, b))
    if not near:
        return out
    inv = _inverses(hs)
    objs = [o for o, _ in near]
    for _, (r0, r1, c0, c1) in near:
        ys, xs = np.mgrid[r0:r1, c0:c1].astype(np.float64)
        count = np.zeros(xs.shape, dtype=np.int32)
        for h in inv:
            u, v = _apply(h, xs, ys)
            count += np.logical_or.reduce([o.contains(u, v) for o in objs])
        out[r0 - y0:r1 - y0, c0 - x0:c1 - x0] |= count >= share * len(hs)
    return out
