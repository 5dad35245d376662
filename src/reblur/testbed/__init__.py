"""Independent realism test bed for reblur: pairs made from the physics, not from reblur's model.

The observation is a time average of BICUBIC perspective warps over a continuous 6-D camera
path (sub-pixel translations, out-of-plane tilts, roll and depth, 64+ sub-poses) after a
perspective viewpoint change, of real aerial imagery with pasted changes, through a
Poisson-Gaussian sensor with 8/12/16-bit quantisation and optional JPEG; or real blur from
consecutive high-speed GoPro frames.  This package imports nothing from reblur's model code
(``reblur.grid``, ``reblur.warp``, ``reblur.operator``, ``reblur.simulate``, ``reblur.tiled``),
so reblur can be measured on data that does not share its assumptions.
"""

from __future__ import annotations

from .camera import (
    CameraPath,
    compose,
    default_focal,
    intrinsics,
    pose_homography,
    random_camera_path,
    rotation_matrix,
    shake_for,
    viewpoint_homography,
)
from .cases import CASES, failure_pair, wedge_mask
from .edits import Occluder, Ramp, Vignette, thin_changes
from .gopro import N_FRAMES, gopro_frame, gopro_frame_indices, gopro_pair
from .pairs import PairPlan, RealismPair, make_pair, plan_pair, write_pair
from .render import (
    Box,
    iter_tiles,
    render_tiled,
    render_window,
    source_box,
    true_centroid,
    valid_window,
)
from .scenes import (
    ChangedScene,
    ChangeObject,
    CroppedScene,
    UpsampledScene,
    change_boxes,
    levir_image,
    load_image,
    paste_changes,
    scene_names,
    shared_data_dir,
    truth_window,
    upsampled,
    whu_image,
)
from .sensor import apply_sensor, full_scale, jpeg, output_dtype, quantise

__all__ = [
    "CASES",
    "N_FRAMES",
    "Box",
    "CameraPath",
    "ChangeObject",
    "ChangedScene",
    "CroppedScene",
    "Occluder",
    "PairPlan",
    "Ramp",
    "RealismPair",
    "UpsampledScene",
    "Vignette",
    "apply_sensor",
    "change_boxes",
    "compose",
    "default_focal",
    "failure_pair",
    "full_scale",
    "gopro_frame",
    "gopro_frame_indices",
    "gopro_pair",
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
    "random_camera_path",
    "render_tiled",
    "render_window",
    "rotation_matrix",
    "scene_names",
    "shake_for",
    "shared_data_dir",
    "source_box",
    "thin_changes",
    "true_centroid",
    "truth_window",
    "upsampled",
    "valid_window",
    "viewpoint_homography",
    "wedge_mask",
    "whu_image",
    "write_pair",
]
