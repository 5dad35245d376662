"""reblur: change detection between a sharp reference and a motion-blurred observation.

The blur is a weighted average of homography warps of the reference over a grid of camera
poses; the weights (and the changes, as a sparse additive term) are estimated by an l1 problem
on well-chosen windows, the whole reference is reblurred with them, and what differs is the
change.  See ``METHOD.md`` in the project's shared notes and the README.
"""

from __future__ import annotations

from .estimate import estimate_motion
from .grid import GridParams, PoseGrid
from .result import ChangeResult, CropChoice, MotionEstimate
from .tiled import reblur

__version__ = "0.1.0"

__all__ = [
    "ChangeResult",
    "CropChoice",
    "GridParams",
    "MotionEstimate",
    "PoseGrid",
    "ReferenceCache",
    "__version__",
    "detect_changes",
    "detect_changes_many",
    "estimate_motion",
    "metrics",
    "reblur",
]


def __getattr__(name):
    # detect_changes pulls in the whole pipeline (alignment, selection, decision): import lazily
    if name == "detect_changes":
        from .pipeline import detect_changes

        return detect_changes
    if name == "detect_changes_many":
        from .many import detect_changes_many

        return detect_changes_many
    if name == "ReferenceCache":
        from .refcache import ReferenceCache

        return ReferenceCache
    if name == "metrics":
        import importlib

        return importlib.import_module(".metrics", __name__)
    raise AttributeError(f"module 'reblur' has no attribute {name!r}")
