"""Independent realism test bed for reblur: pairs made from the physics, not from reblur's model.

The observation is a time average of BICUBIC perspective warps over a continuous 6-D camera
path (sub-pixel translations, out-of-plane tilts, roll and depth, 64+ sub-poses) after a
perspective viewpoint change, of real aerial imagery with pasted changes, through a
Poisson-Gaussian sensor with 8/12/16-bit quantisation and optional JPEG; or real blur from
consecutive high-speed GoPro frames.  Optionally the observation camera's lens distorts and a
second scene plane shows parallax (:mod:`reblur.testbed.geometry`): geometry no single
homography per pose represents.  This package imports nothing from reblur's model code
(``reblur.grid``, ``reblur.warp``, ``reblur.operator``, ``reblur.simulate``, ``reblur.tiled``),
so reblur can be measured on data that does not share its assumptions.
"""

from __future__ import annotations

from .camera import (
    CameraPath,
    compose,
    default_focal,
    defocus_path,
    intrinsics,
    pose_homography,
    random_camera_path,
    rotation_matrix,
    shake_for,
    translation,
    view_from_parts,
    viewpoint_homography,
    viewpoint_parts,
)
from .cases import CASES, GEOMETRY_CASES, failure_pair, wedge_mask
from .edits import Occluder, Ramp, Vignette, thin_changes
from .geometry import (
    Lens,
    Region,
    SceneGeometry,
    best_homography,
    homography_residual,
    region_homographies,
    roof_polygon,
)
from .gopro import N_FRAMES, gopro_frame, gopro_frame_indices, gopro_pair
from .pairs import PairPlan, RealismPair, make_pair, plan_pair, write_pair
from .render import (
    Box,
    as_mapping,
    iter_tiles,
    render_tiled,
    render_window,
    source_box,
    true_centroid,
    valid_window,
)
from .scenes import (
    DATA_ENV,
    ChangedScene,
    ChangeObject,
    CroppedScene,
    DataMissing,
    UpsampledScene,
    change_boxes,
    levir_image,
    load_image,
    paste_changes,
    require_data,
    scene_names,
    shared_data_dir,
    truth_window,
    upsampled,
    whu_image,
)
from .sensor import apply_sensor, full_scale, jpeg, output_dtype, quantise

__all__ = [
    "CASES",
    "GEOMETRY_CASES",
    "N_FRAMES",
    "Box",
    "CameraPath",
    "ChangeObject",
    "ChangedScene",
    "CroppedScene",
    "Lens",
    "Occluder",
    "PairPlan",
    "Ramp",
    "RealismPair",
    "Region",
    "SceneGeometry",
    "UpsampledScene",
    "Vignette",
    "apply_sensor",
    "as_mapping",
    "best_homography",
    "change_boxes",
    "compose",
    "default_focal",
    "failure_pair",
    "full_scale",
    "gopro_frame",
    "gopro_frame_indices",
    "gopro_pair",
    "homography_residual",
    "intrinsics",
    "iter_tiles",
    "jpeg",
    "levir_image",
    "load_image",
    "make_pair",
    "output_dtype",
    "paste_changes",
    "plan_pair",
    "pose_homography",
    "quantise",
    "defocus_path",
    "random_camera_path",
    "region_homographies",
    "render_tiled",
    "render_window",
    "roof_polygon",
    "rotation_matrix",
    "scene_names",
    "shake_for",
    "shared_data_dir",
    "require_data",
    "DataMissing",
    "DATA_ENV",
    "source_box",
    "thin_changes",
    "translation",
    "true_centroid",
    "truth_window",
    "upsampled",
    "valid_window",
    "view_from_parts",
    "viewpoint_homography",
    "viewpoint_parts",
    "wedge_mask",
    "whu_image",
    "write_pair",
]
