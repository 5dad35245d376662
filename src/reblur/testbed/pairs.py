"""Reference / observation pairs with ground truth, in memory or written tile by tile.

A pair is made from a real scene: random change objects are pasted into it, the changed scene
is seen from a perspective viewpoint change while the camera shakes along a continuous 6-D
path (bicubic warps averaged over ``n_sub`` sub-poses), and both images go through the sensor
model.  The reference is the UNCHANGED scene with its own independent sensor noise.  Every
image is produced a tile at a time (512 px tiles, per-tile noise streams seeded from
``(seed, image, tile origin)``), so :func:`make_pair` (in memory) and :func:`write_pair`
(tiled BigTIFF on disk, any size) give identical pixels for the same arguments.  Nothing
here comes from reblur's own simulator or pose model.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tifffile

from .camera import CameraPath, compose, random_camera_path, view_from_parts, viewpoint_parts
from .geometry import Lens, Region, SceneGeometry, region_homographies, roof_polygon
from .render import Box, iter_tiles, render_window, valid_window
from .scenes import ChangedScene, CroppedScene, change_boxes, paste_changes, truth_window
from .sensor import apply_sensor, output_dtype

__all__ = ["PairPlan", "RealismPair", "make_pair", "plan_pair", "write_pair"]

TILE = 512
MAX_IN_MEMORY_PX = 16_000_000


@dataclass(frozen=True)
class RealismPair:
    """An in-memory pair.

    Attributes
    ----------
    reference : numpy.ndarray
        Unchanged scene after the sensor model (uint8 or uint16).
    observed : numpy.ndarray
        Blurred, re-viewpointed, changed scene after the sensor model (same dtype).
    truth : numpy.ndarray
        Boolean change mask in the observation frame (half-maximum footprint).
    valid : numpy.ndarray
        Boolean mask of observation pixels whose every sub-pose samples inside the reference.
    homographies : numpy.ndarray
        ``(n_sub, 3, 3)`` reference -> observation mappings ``H_k @ H_view`` (of the
        ground plane, without the lens, when there is a ``geometry``).
    view : numpy.ndarray
        ``3 x 3`` viewpoint homography.
    info : dict
        JSON-able description (seed, bit depth, noise, sizes, poses, change objects).
    occlusion : numpy.ndarray, optional
        Boolean mask of the observation pixels at a second plane's occlusion edges
        (:meth:`~reblur.testbed.geometry.SceneGeometry.occlusion_window`; all False
        without one).
    geometry : SceneGeometry, optional
        The truth of a pair with lens distortion or a second plane: its
        :meth:`~reblur.testbed.geometry.SceneGeometry.centroid` is where an observation
        pixel comes from; None when ``homographies`` say it all.
    """

    reference: np.ndarray
    observed: np.ndarray
    truth: np.ndarray
    valid: np.ndarray
    homographies: np.ndarray
    view: np.ndarray
    info: dict = field(default_factory=dict)
    occlusion: np.ndarray | None = None
    geometry: Any = None


@dataclass(frozen=True)
class PairPlan:
    """Everything needed to produce any tile of a pair (see :func:`plan_pair`).

    Attributes
    ----------
    scene : array-like
        The unchanged scene (the reference before the sensor model).
    changed : ChangedScene
        The scene with the change objects (what the observation is rendered from).
    path : CameraPath
        The camera-shake path.
    view : numpy.ndarray
        ``3 x 3`` viewpoint homography.
    homographies : numpy.ndarray
        ``(n_sub, 3, 3)`` total mappings ``H_k @ H_view``.
    sensor : dict
        Keywords of :func:`~reblur.testbed.sensor.apply_sensor`.
    seed : int
        Seed of the per-tile noise streams.
    info : dict
        JSON-able description.
    boxes : list of Box
        :func:`~reblur.testbed.scenes.change_boxes` of ``changed`` and ``homographies``.
    illumination : callable, optional
        ``illumination(box) -> gain`` multiplied into the rendered observation in its own
        frame (:class:`~reblur.testbed.edits.Ramp`, :class:`~reblur.testbed.edits.Vignette`).
    geometry : SceneGeometry, optional
        Lens distortion and / or a second scene plane; the observation, its truth and
        validity then follow it instead of ``homographies``.
    """

    scene: Any
    changed: ChangedScene
    path: CameraPath
    view: np.ndarray
    homographies: np.ndarray
    sensor: dict
    seed: int
    info: dict
    boxes: list[Box]
    illumination: Any = None
    geometry: SceneGeometry | None = None

    @property
    def mapping(self) -> Any:
        """What the renderer follows: the geometry, or else the homographies."""
        return self.homographies if self.geometry is None else self.geometry

    @property
    def shape(self) -> tuple[int, ...]:
        """Shape of both images ``(H, W[, C])``."""
        return tuple(self.scene.shape)

    def _sensor(self, image: np.ndarray, stream: int, box: Box) -> np.ndarray:
        rng = np.random.default_rng([self.seed, stream, box[0], box[2]])
        return apply_sensor(image, rng, **self.sensor)

    def reference_tile(self, box: Box) -> np.ndarray:
        """Reference pixels of a box: the unchanged scene through the sensor model."""
        return self._sensor(np.asarray(self.scene[box[0]:box[1], box[2]:box[3]]), 1, box)

    def observed_tile(self, box: Box) -> np.ndarray:
        """Observed pixels of a box: the rendered changed scene through the sensor model."""
        return self.sense_observed(self.render_tile(box), box)

    def render_tile(self, box: Box) -> np.ndarray:
        """The noise-free rendered observation of a box (float64 in [0, 1]), before the
        sensor: plans that differ only in their sensor share it."""
        image, _ = render_window(self.changed, self.mapping, box)
        if self.illumination is not None:
            g = self.illumination(box)
            image = np.clip(image * (g[:, :, None] if image.ndim == 3 else g), 0.0, 1.0)
        return image

    def sense_observed(self, image: np.ndarray, box: Box) -> np.ndarray:
        """The sensor model applied to a rendered box (:meth:`render_tile`), with this
        plan's noise stream: ``sense_observed(render_tile(b), b) == observed_tile(b)``."""
        return self._sensor(image, 2, box)

    def truth_tile(self, box: Box) -> np.ndarray:
        """Change mask of a box (boolean)."""
        if self.geometry is not None:
            return self.geometry.truth_window(self.changed.objects, box, self.boxes)
        return truth_window(self.changed, self.homographies, box, self.boxes)

    def valid_tile(self, box: Box) -> np.ndarray:
        """Validity mask of a box (boolean)."""
        if self.geometry is not None:
            return self.geometry.valid_window(box, self.shape)
        return valid_window(self.homographies, box, self.shape)

    def occlusion_tile(self, box: Box, band_px: float = 0.0) -> np.ndarray:
        """Occlusion edges of a second plane in a box, grown by ``band_px`` (boolean; all
        False without one)."""
        if self.geometry is None:
            return np.zeros((box[1] - box[0], box[3] - box[2]), dtype=bool)
        return self.geometry.occlusion_window(box, band_px)


def _crop(scene: Any, size: tuple[int, int] | None) -> Any:
    if scene is None or not hasattr(scene, "shape") or len(scene.shape) not in (2, 3):
        raise ValueError("scene must be an (H, W) or (H, W, C) array or scene reader")
    if size is None:
        return scene
    h, w = (int(v) for v in size)
    if not (64 <= h <= scene.shape[0] and 64 <= w <= scene.shape[1]):
        raise ValueError(f"size {size!r} must be >= 64 and fit in the scene {scene.shape[:2]}")
    y0, x0 = (scene.shape[0] - h) // 2, (scene.shape[1] - w) // 2
    return CroppedScene(scene, (y0, y0 + h, x0, x0 + w))


def _object_info(changed: ChangedScene) -> list[dict]:
    keys = ("kind", "cx", "cy", "angle", "a", "b", "a2", "delta", "local_range", "level",
            "amplitude", "seed")
    return [{k: getattr(o, k) for k in keys if hasattr(o, k)}
            | {"harmonics": [list(p) for p in getattr(o, "harmonics", ())]}
            for o in changed.objects]


def plan_pair(
    scene: Any,
    *,
    size: tuple[int, int] | None = None,
    bits: int = 8,
    noise_dn: float = 1.0,
    full_well: float = 0.0,
    jpeg_quality: int | None = None,
    n_changes: int = 8,
    seed: int = 0,
    motion: dict | None = None,
    viewpoint: dict | None = None,
    changes: dict | None = None,
    objects: Sequence[Any] = (),
    illumination: Any = None,
    lens: dict | None = None,
    parallax: dict | None = None,
) -> PairPlan:
    """Draw a pair's changes, camera path and viewpoint (no pixels are computed).

    Parameters
    ----------
    scene : array-like
        Scene in [0, 1] (array or reader, gray or RGB).
    size : tuple of int, optional
        ``(H, W)`` of the pair, a centred crop of the scene; default the whole scene.
    bits : int
        Output bit depth, 8, 12 or 16.
    noise_dn : float
        Read-noise standard deviation in DN of ``bits``.
    full_well : float
        Photo-electrons at full scale (shot noise); 0 disables shot noise.
    jpeg_quality : int, optional
        JPEG quality for 8-bit output, per 512 px tile.
    n_changes : int
        Number of change objects.
    seed : int
        Seed of every random draw (geometry, changes and per-tile noise).
    motion, viewpoint, changes : dict, optional
        Extra keyword arguments of :func:`~reblur.testbed.camera.random_camera_path`,
        :func:`~reblur.testbed.camera.viewpoint_homography` and
        :func:`~reblur.testbed.scenes.paste_changes`.
    objects : sequence, optional
        Further change objects, added after the pasted ones (occluders, thin changes: see
        :mod:`reblur.testbed.edits`); the pasted ones avoid nothing, so use ``n_changes=0``
        or place these away from them.
    illumination : callable, optional
        ``illumination(box) -> gain`` of the observation (see :class:`PairPlan`).
    lens : dict, optional
        Lens distortion of the observation camera: keywords of
        :meth:`~reblur.testbed.geometry.Lens.from_corner_px` (``corner_px``, ``k2``), e.g.
        ``{"corner_px": 3.0}`` for corners moved 3 px outwards (barrel).
    parallax : dict, optional
        A second scene plane: ``parallax_px`` (the displacement between the planes the
        viewpoint change gives, > 0 a nearer roof, < 0 a farther pit), optionally
        ``polygon`` (its ``(n, 2)`` outline in reference pixels; default a random
        rectangle of 12-20 % of the image, :func:`~reblur.testbed.geometry.roof_polygon`,
        drawn from its own stream so the rest of the pair is the same as without it).

    Returns
    -------
    PairPlan
    """
    if int(seed) < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed}")
    sensor = dict(bits=bits, read_noise_dn=float(noise_dn), full_well=float(full_well),
                  jpeg_quality=jpeg_quality)
    apply_sensor(np.zeros((8, 8)), np.random.default_rng(0), **sensor)  # validates early
    base = _crop(scene, size)
    rng = np.random.default_rng(int(seed))
    changed = paste_changes(base, rng, n_changes=n_changes, **(changes or {}))
    if objects:
        changed = ChangedScene(base, changed.objects + tuple(objects))
    path = random_camera_path(base.shape, rng, **(motion or {}))
    turn, shift = viewpoint_parts(base.shape, rng, focal=path.focal, **(viewpoint or {}))
    view = view_from_parts(turn, shift)
    total = compose(view, path.homographies())
    geometry = _geometry(base.shape, int(seed), path, turn, shift, total, lens, parallax)
    info = {"seed": int(seed), "bits": bits, "noise_dn": float(noise_dn),
            "full_well": float(full_well), "jpeg_quality": jpeg_quality,
            "shape": list(base.shape), "tile": TILE, "focal": path.focal,
            "n_sub": len(path.poses), "poses": path.poses.tolist(), "view": view.tolist(),
            "homographies": total.tolist(), "objects": _object_info(changed),
            "convention": "homographies map reference (x, y) to observation; H_k @ H_view",
            "view_shift": shift.tolist()}
    if geometry is not None:
        info["geometry"] = geometry.to_dict()
    if illumination is not None:
        info["illumination"] = (illumination.to_dict() if hasattr(illumination, "to_dict")
                                else repr(illumination))
    boxes = (change_boxes(changed, total) if geometry is None
             else geometry.change_boxes(changed.objects))
    return PairPlan(base, changed, path, view, total, sensor, int(seed), info, boxes,
                    illumination, geometry)


def _geometry(shape: tuple[int, ...], seed: int, path: CameraPath, turn: np.ndarray,
              shift: np.ndarray, total: np.ndarray, lens: dict | None,
              parallax: dict | None) -> SceneGeometry | None:
    """The pair's :class:`~reblur.testbed.geometry.SceneGeometry` (None without a lens or a
    second plane)."""
    if lens is None and parallax is None:
        return None
    lens_model = None
    if lens is not None:
        if set(lens) - {"corner_px", "k2"}:
            raise ValueError(f"lens takes corner_px and k2, got {sorted(lens)}")
        lens_model = Lens.from_corner_px(shape, focal=path.focal, **lens)
    if parallax is None:
        return SceneGeometry(total, lens=lens_model)
    if set(parallax) - {"parallax_px", "polygon"} or "parallax_px" not in parallax:
        raise ValueError(f"parallax takes parallax_px and optionally polygon, got "
                         f"{sorted(parallax)}")
    reach = float(np.hypot(*shift))
    px = float(parallax["parallax_px"])
    if reach < 1e-6 and px != 0:
        raise ValueError("the viewpoint change has no translation, so nothing shows "
                         "parallax: give viewpoint shift_px > 0")
    scale = 1.0 + (px / reach if px else 0.0)
    if scale <= 0:
        raise ValueError(f"parallax_px {px} puts the plane behind the camera: keep it above "
                         f"-{reach:.1f} px for this viewpoint")
    poly = parallax.get("polygon")
    if poly is None:
        poly = roof_polygon(shape, np.random.default_rng([seed, 29]))
    region = Region(polygon=np.asarray(poly, dtype=np.float64), scale=scale, parallax_px=px)
    return SceneGeometry(total, lens=lens_model, region=region,
                         region_homographies=region_homographies(path, turn, shift, scale))


def make_pair(
    scene: Any,
    *,
    size: tuple[int, int] | None = None,
    bits: int = 8,
    noise_dn: float = 1.0,
    n_changes: int = 8,
    seed: int = 0,
    **options: Any,
) -> RealismPair:
    """Make an in-memory pair (up to 16 MP; use :func:`write_pair` beyond).

    Parameters
    ----------
    scene, size, bits, noise_dn, n_changes, seed
        See :func:`plan_pair`.
    **options
        Further :func:`plan_pair` keywords (``full_well``, ``jpeg_quality``, ``motion``,
        ``viewpoint``, ``changes``).

    Returns
    -------
    RealismPair
    """
    plan = plan_pair(scene, size=size, bits=bits, noise_dn=noise_dn, n_changes=n_changes,
                     seed=seed, **options)
    return pair_from_plan(plan)


def pair_from_plan(plan: PairPlan) -> RealismPair:
    """Render every tile of ``plan`` into an in-memory :class:`RealismPair`.

    Raises
    ------
    ValueError
        When the pair is larger than :data:`MAX_IN_MEMORY_PX` (use :func:`write_pair`).
    """
    h, w = plan.shape[:2]
    if h * w > MAX_IN_MEMORY_PX:
        raise ValueError(f"{h}x{w} is too large to hold in memory: use write_pair")
    dt = output_dtype(plan.sensor["bits"])
    ref = np.zeros(plan.shape, dtype=dt)
    obs = np.zeros(plan.shape, dtype=dt)
    truth = np.zeros((h, w), dtype=bool)
    valid = np.zeros((h, w), dtype=bool)
    occlusion = np.zeros((h, w), dtype=bool)
    for b in iter_tiles(plan.shape, TILE):
        win = np.s_[b[0]:b[1], b[2]:b[3]]
        ref[win], obs[win] = plan.reference_tile(b), plan.observed_tile(b)
        truth[win], valid[win] = plan.truth_tile(b), plan.valid_tile(b)
        occlusion[win] = plan.occlusion_tile(b)
    return RealismPair(ref, obs, truth, valid, plan.homographies, plan.view, plan.info,
                       occlusion, plan.geometry)


def _write_tiff(path: Path, tiles, shape: tuple[int, ...], dtype, compress: bool) -> None:
    photometric = "rgb" if len(shape) == 3 else "minisblack"
    tifffile.imwrite(path, tiles, shape=shape, dtype=dtype, tile=(TILE, TILE), bigtiff=True,
                     photometric=photometric, compression="zlib" if compress else None)


def write_pair(out_dir: str | Path, scene: Any, **kwargs: Any) -> dict:
    """Write a pair of any size tile by tile as tiled BigTIFFs plus ``pair.json``.

    Files: ``reference.tif`` and ``observed.tif`` (uint8/uint16, 512 px tiles),
    ``truth.tif`` and ``valid.tif`` (uint8 0/255, zlib), with a lens or a second plane also
    ``occlusion.tif`` (:meth:`PairPlan.occlusion_tile`), ``pair.json`` (the plan's info).
    Only a few tiles are in memory at any time.  Pixels equal :func:`make_pair`'s with the
    same arguments.

    Parameters
    ----------
    out_dir : str or pathlib.Path
        Output folder (created).
    scene : array-like
        Scene in [0, 1] (array or reader).
    **kwargs
        :func:`plan_pair` keywords.

    Returns
    -------
    dict
        The info written to ``pair.json``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plan = plan_pair(scene, **kwargs)
    shape, dt = plan.shape, output_dtype(plan.sensor["bits"])
    boxes = list(iter_tiles(shape, TILE))
    _write_tiff(out / "reference.tif", (plan.reference_tile(b) for b in boxes), shape, dt, False)
    _write_tiff(out / "observed.tif", (plan.observed_tile(b) for b in boxes), shape, dt, False)
    masks = {"truth": plan.truth_tile, "valid": plan.valid_tile}
    if plan.geometry is not None:
        masks["occlusion"] = plan.occlusion_tile
    for name, fn in masks.items():
        tiles = (fn(b).astype(np.uint8) * 255 for b in boxes)
        _write_tiff(out / f"{name}.tif", tiles, shape[:2], np.uint8, True)
    info = plan.info | {"files": ["reference.tif", "observed.tif"]
                        + [f"{name}.tif" for name in masks]}
    (out / "pair.json").write_text(json.dumps(info, indent=1))
    return info
