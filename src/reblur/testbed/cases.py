"""The decision's failure modes as test-bed pairs (issue #27's table), one name each.

Every case is a real scene (LEVIR / WHU) seen through the test bed's own camera shake, view
change and sensor, edited by :mod:`reblur.testbed.edits`:

==================  =========================================================================
``hole25``          a 256 x 256 black hole in a 512 x 512 observation (25 % of the view)
``hole50``          the left half of a 512 x 512 observation black
``occluder25``      one dark textured occluder over 25 % of a 512 x 512 view
``occluder45``      the same over 45 %
``occluder60``      the same over 60 % (the high-breakdown limit asked for)
``plain``           8 pasted changes, nothing else (the recall the two below must keep)
``ramp``            an illumination ramp 0.65 -> 1.0 across a 1024 x 1024 observation, 8 pasted
                    changes (false alarms and recall)
``vignette``        radial vignetting (35 % at the corners), 8 pasted changes
``ramp_strong``     an illumination ramp 0.45 -> 1.0 (the light of a low sun across the
                    frame), 8 pasted changes
``saturated``       ``plain`` exposed 1.3x brighter: the sensor saturates ~8 % of the
                    observation (bright roofs), no other change
``fill55``          ``plain`` with the observation's left 55 % set to exactly 0 after the
                    sensor (a mosaic's fill without a nodata tag); the fill is change
``thin``            four thin long changes (10-14 px wide, 250-400 px long, straight and L)
``identical``       observation = reference, byte for byte
``lens3``           barrel lens distortion of the observation camera moving the corners by
                    3 px (:mod:`reblur.testbed.geometry`), no change
``pincushion3``     the same with pincushion distortion (corners 3 px inwards)
``lens3_changes``   ``lens3`` with 8 pasted changes
``parallax``        a second scene plane (a "roof" over 12-20 % of the scene) 4 px of
                    viewpoint parallax from the ground, no change
``parallax_changes`` ``parallax`` with 8 pasted changes
==================  =========================================================================

Nodata (a reference GeoTIFF with ``nodata=0`` and a missing wedge) is a file-format case:
:func:`wedge_mask` gives the wedge; the caller writes the file.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from .camera import shake_for
from .edits import Occluder, Ramp, Vignette, thin_changes
from .pairs import RealismPair, make_pair, plan_pair
from .scenes import CroppedScene, levir_image, whu_image

__all__ = ["CASES", "GEOMETRY_CASES", "failure_pair", "wedge_mask"]

#: Case names, in the order of the issue's table.
CASES = ("hole25", "hole50", "occluder25", "occluder45", "occluder60", "plain", "ramp",
         "vignette", "ramp_strong", "saturated", "fill55", "thin", "identical", "lens3",
         "pincushion3", "lens3_changes", "parallax", "parallax_changes")

#: The geometry cases: ``plan_pair`` keywords and number of pasted changes.
GEOMETRY_CASES = {
    "lens3": ({"lens": {"corner_px": 3.0}}, 0),
    "pincushion3": ({"lens": {"corner_px": -3.0}}, 0),
    "lens3_changes": ({"lens": {"corner_px": 3.0}}, 8),
    "parallax": ({"parallax": {"parallax_px": 4.0}}, 0),
    "parallax_changes": ({"parallax": {"parallax_px": 4.0}}, 8),
}


def _scene(name: str) -> np.ndarray:
    return levir_image(name) if name.startswith("test") else whu_image(name)


def _crop(scene: np.ndarray, side: int) -> Any:
    h, w = scene.shape[:2]
    y0, x0 = (h - side) // 2, (w - side) // 2
    return CroppedScene(scene, (y0, y0 + side, x0, x0 + side))


def _square_occluder(side: int, frac: float, level: float, amplitude: float,
                     seed: int) -> Occluder:
    half = np.sqrt(frac) * side / 2.0
    return Occluder(cx=(side - 1) / 2.0, cy=(side - 1) / 2.0, a=half, b=half, level=level,
                    amplitude=amplitude, seed=seed)


def failure_pair(name: str, *, scene: str = "test_7", seed: int = 0, bits: int = 8,
                 noise_dn: float = 1.0) -> RealismPair:
    """The pair of one failure case (see the module's table).

    Parameters
    ----------
    name : str
        One of :data:`CASES`.
    scene : str
        LEVIR (``test_*``) or WHU (``000*``) scene name.
    seed : int
        Seed of the camera path, the view change, the pasted changes and the noise.
    bits, noise_dn : int, float
        Sensor bit depth and read noise (DN).

    Returns
    -------
    RealismPair
        For ``identical``, the observation is the reference and the truth is empty.  The
        geometry cases carry their ``geometry`` (the truth of where each observation pixel
        comes from) and ``occlusion`` (the second plane's occlusion edges).
    """
    if name not in CASES:
        raise ValueError(f"unknown case {name!r}; choose from {', '.join(CASES)}")
    base = _scene(scene)
    common = dict(bits=bits, noise_dn=noise_dn, seed=seed, viewpoint={"shift_px": 20.0})
    if name.startswith(("hole", "occluder")):
        side = 512
        sc = _crop(base, side)
        frac = {"hole25": 0.25, "occluder25": 0.25, "occluder45": 0.45,
                "occluder60": 0.60}.get(name)
        if name == "hole50":
            occ = Occluder(cx=side / 4.0 - 0.5, cy=(side - 1) / 2.0, a=side / 4.0,
                           b=side / 2.0 + 40, level=0.0, amplitude=0.0)
        elif name.startswith("hole"):
            occ = _square_occluder(side, frac, 0.0, 0.0, seed)
        else:
            occ = _square_occluder(side, frac, 0.12, 0.08, seed)
        return make_pair(sc, n_changes=0, motion=shake_for(sc.shape), objects=(occ,),
                         **common)
    if name in ("plain", "ramp", "vignette", "ramp_strong", "saturated"):
        shape = base.shape[:2]
        light = {"plain": None, "ramp": Ramp(shape, 0.65, 1.0),
                 "vignette": Vignette(shape, 0.35), "ramp_strong": Ramp(shape, 0.45, 1.0),
                 "saturated": Ramp(shape, 1.3, 1.3)}[name]
        return make_pair(base, n_changes=8, motion=shake_for(base.shape), illumination=light,
                         **common)
    if name == "fill55":
        pair = failure_pair("plain", scene=scene, seed=seed, bits=bits, noise_dn=noise_dn)
        cut = int(0.55 * pair.observed.shape[1])
        observed, truth = pair.observed.copy(), pair.truth.copy()
        observed[:, :cut] = 0
        truth[:, :cut] = True
        return dataclasses.replace(pair, observed=observed, truth=truth,
                                   info={**pair.info, "case": name, "fill_columns": cut})
    if name in GEOMETRY_CASES:
        extra, n = GEOMETRY_CASES[name]
        return make_pair(base, n_changes=n, motion=shake_for(base.shape), **extra, **common)
    if name == "thin":
        objs = thin_changes(base, np.random.default_rng([seed, 27]), n=4)
        return make_pair(base, n_changes=0, motion=shake_for(base.shape), objects=objs,
                         **common)
    # identical: the reference twice
    plan = plan_pair(base, n_changes=0, motion=shake_for(base.shape), **common)
    ref = plan.reference_tile((0, base.shape[0], 0, base.shape[1]))
    h, w = ref.shape[:2]
    return RealismPair(ref, ref.copy(), np.zeros((h, w), bool), np.ones((h, w), bool),
                       np.repeat(np.eye(3)[None], 1, axis=0), np.eye(3),
                       {**plan.info, "case": "identical"})


def wedge_mask(shape: tuple[int, int], *, corner: str = "top-left", angle_deg: float = 30.0,
               depth: float = 0.6) -> np.ndarray:
    """A triangular wedge of missing data from one image corner.

    The triangle with one vertex at ``corner``, one ``depth * W`` along the horizontal edge
    from it and one ``depth * tan(angle_deg) * W`` (at most ``H``) along the vertical edge.

    Returns
    -------
    numpy.ndarray
        Boolean ``shape``, True in the wedge.
    """
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    if "right" in corner:
        xs = w - 1 - xs
    if "bottom" in corner:
        ys = h - 1 - ys
    a = depth * w
    b = min(depth * np.tan(np.radians(angle_deg)) * w, h)
    return xs / a + ys / b <= 1.0
