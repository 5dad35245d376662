"""Scene edits beyond pasted additive changes: the failure modes of a change decision.

* :class:`Occluder`: a region whose content is *replaced* (a dark textured object, a black
  hole, a new roof), from a quarter to most of the view; it is a change object like the
  others (its ground truth is its half-maximum footprint in the observation frame).
* :func:`thin_changes`: long thin changes, straight or L-shaped (new roads, walls), added
  with a contrast relative to their surroundings like :func:`~reblur.testbed.paste_changes`.
* :class:`Ramp` and :class:`Vignette`: illumination fields multiplied into the rendered
  observation in its own frame (a sun/haze gradient, a lens's radial fall-off), so an
  unchanged scene looks different without any change.

Everything is analytic and seeded; nothing comes from reblur.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .render import Box
from .scenes import ChangeObject, _gray, disc_box, object_frame, signed_delta

__all__ = ["Occluder", "Ramp", "Vignette", "thin_changes"]


@dataclass(frozen=True)
class Occluder:
    """A rotated rectangle whose scene content is replaced by a seeded texture.

    The texture is ``level + amplitude * t(x, y)`` with ``t`` a sum of six plane waves of
    random directions, periods in ``period`` (pixels) and phases, scaled to [-1, 1]: a
    textured surface the reference never saw.  ``amplitude = 0`` paints a flat value (a
    black hole with ``level = 0``).

    Attributes
    ----------
    cx, cy : float
        Centre, scene pixels.
    a, b : float
        Half width and half height before rotation, pixels.
    angle : float
        Rotation in radians.
    level, amplitude : float
        Mean value and texture amplitude, in [0, 1] units.
    period : tuple of float
        Range of the plane waves' periods, pixels.
    seed : int
        Seed of the texture's directions, periods and phases.
    """

    cx: float
    cy: float
    a: float
    b: float
    angle: float = 0.0
    level: float = 0.15
    amplitude: float = 0.1
    period: tuple[float, float] = (6.0, 40.0)
    seed: int = 0
    kind: str = "occluder"

    def __post_init__(self) -> None:
        if not (self.a > 0 and self.b > 0):
            raise ValueError(f"an occluder needs positive half sizes, got {self.a}, {self.b}")
        if not (0 <= self.level <= 1 and 0 <= self.amplitude <= 1):
            raise ValueError("level and amplitude must lie in [0, 1]")

    @property
    def radius(self) -> float:
        """Radius of a disc holding the object."""
        return float(np.hypot(self.a, self.b)) + 1.0

    @property
    def bbox(self) -> Box:
        """Integer box ``(y0, y1, x0, x1)`` holding the object."""
        return disc_box(self.cx, self.cy, self.radius)

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Whether points ``(x, y)`` lie inside the rectangle."""
        u, v = object_frame(x, y, self.cx, self.cy, self.angle)
        return (np.abs(u) <= self.a) & (np.abs(v) <= self.b)

    def paint(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Texture values at points ``(x, y)`` (scene pixels), in [0, 1]."""
        if self.amplitude == 0:
            return np.full(np.shape(x), float(self.level))
        rng = np.random.default_rng([int(self.seed), 7])
        t = np.zeros(np.shape(x))
        for _ in range(6):
            th = rng.uniform(0, np.pi)
            k = 2 * np.pi / rng.uniform(*self.period)
            t += np.cos(k * (x * np.cos(th) + y * np.sin(th)) + rng.uniform(0, 2 * np.pi))
        return np.clip(self.level + self.amplitude * t / 6.0 * 2.0, 0.0, 1.0)

    @property
    def delta(self) -> float:
        """Not additive: kept for the pair's JSON description (0)."""
        return 0.0

    @property
    def local_range(self) -> float:
        return 0.0


def thin_changes(
    scene: Any,
    rng: np.random.Generator,
    *,
    n: int = 4,
    width_px: tuple[float, float] = (10.0, 14.0),
    length_px: tuple[float, float] = (250.0, 400.0),
    contrast: tuple[float, float] = (0.2, 0.4),
    l_fraction: float = 0.5,
    margin: float = 30.0,
    max_tries: int = 500,
) -> tuple[ChangeObject, ...]:
    """Long thin changes (straight bars and L shapes) that do not overlap.

    Each adds ``+-c * (p98 - p2)`` of its surroundings, ``c`` uniform in ``contrast``, the
    sign chosen to stay in [0, 1] as in :func:`~reblur.testbed.paste_changes`.

    Parameters
    ----------
    scene : array-like
        Scene in [0, 1].
    rng : numpy.random.Generator
        Seeded generator.
    n : int
        Number of objects.
    width_px, length_px : tuple of float
        Ranges of the full width and of the (first arm's) full length, pixels.
    contrast : tuple of float
        Range of the contrast fraction.
    l_fraction : float
        Share of L shapes (the rest are straight).
    margin : float
        Distance kept from the scene's edges.
    max_tries : int
        Placement attempts per object.

    Returns
    -------
    tuple of ChangeObject
    """
    h, w = scene.shape[:2]
    objs: list[ChangeObject] = []
    for i in range(int(n)):
        for _ in range(int(max_tries)):
            kind = "L" if rng.random() < l_fraction else "rect"
            a = rng.uniform(*length_px) / 2.0
            b = rng.uniform(*width_px) / 2.0
            a2 = a * rng.uniform(0.5, 1.0)
            probe = ChangeObject(kind=kind, cx=0.0, cy=0.0, angle=float(rng.uniform(0, np.pi)),
                                 a=float(a), b=float(b), a2=float(a2), harmonics=(),
                                 delta=0.0, local_range=0.0)
            lo = margin + ((a + a2 + b) if kind == "L" else (a + b))
            if w <= 2 * lo or h <= 2 * lo:
                continue
            cx, cy = rng.uniform(lo, w - lo), rng.uniform(lo, h - lo)
            o = ChangeObject(**{**probe.__dict__, "cx": float(cx), "cy": float(cy)})
            y0, y1, x0, x1 = o.bbox
            if y0 < margin or x0 < margin or y1 > h - margin or x1 > w - margin:
                continue
            ys, xs = np.mgrid[y0:y1, x0:x1].astype(np.float64)
            # apart from the others by 3 widths (the grown object holds the object itself)
            grown = ChangeObject(**{**o.__dict__, "b": o.b + 3 * width_px[1]})
            if any(np.any(grown.contains(xs, ys) & p.contains(xs, ys)) for p in objs):
                continue
            region = _gray(np.asarray(scene[y0:y1, x0:x1], np.float64))
            p2, p98 = np.percentile(region, [2, 98])
            if p98 - p2 < 0.05:
                continue
            delta = signed_delta(rng, region[o.contains(xs, ys)], p98 - p2, contrast)
            objs.append(ChangeObject(**{**o.__dict__, "delta": delta,
                                        "local_range": float(p98 - p2)}))
            break
        else:
            raise ValueError(f"could not place thin change {i + 1} of {n} in {scene.shape[:2]}")
    return tuple(objs)


def _centres(box: Box) -> tuple[np.ndarray, np.ndarray]:
    y0, y1, x0, x1 = box
    return np.mgrid[y0:y1, x0:x1].astype(np.float64)


@dataclass(frozen=True)
class Ramp:
    """Linear illumination ramp from ``lo`` to ``hi`` across the image along ``angle``.

    ``angle = 0`` ramps left to right.  The gain at a pixel is linear in its projection on
    the direction, ``lo`` at the image's first corner along it and ``hi`` at the last.
    """

    shape: tuple[int, int]
    lo: float = 0.65
    hi: float = 1.0
    angle: float = 0.0

    def __call__(self, box: Box) -> np.ndarray:
        ys, xs = _centres(box)
        h, w = self.shape[:2]
        c, s = np.cos(self.angle), np.sin(self.angle)
        corners = np.array([0.0, (w - 1) * c, (h - 1) * s, (w - 1) * c + (h - 1) * s])
        t = (xs * c + ys * s - corners.min()) / max(np.ptp(corners), 1e-9)
        return self.lo + (self.hi - self.lo) * t

    def to_dict(self) -> dict:
        return {"kind": "ramp", "lo": self.lo, "hi": self.hi, "angle": self.angle}


@dataclass(frozen=True)
class Vignette:
    """Radial fall-off ``1 - strength * (r / r_corner)^2`` about the image centre (cos^4-like
    for moderate angles): ``strength`` is the loss at the corners."""

    shape: tuple[int, int]
    strength: float = 0.35

    def __call__(self, box: Box) -> np.ndarray:
        ys, xs = _centres(box)
        h, w = self.shape[:2]
        cy, cx = (h - 1) / 2.0, (w - 1) / 2.0
        r2 = ((xs - cx) ** 2 + (ys - cy) ** 2) / (cx * cx + cy * cy)
        return 1.0 - self.strength * r2

    def to_dict(self) -> dict:
        return {"kind": "vignette", "strength": self.strength}
