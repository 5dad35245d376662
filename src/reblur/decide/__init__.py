"""The change decision: observed vs reblurred reference, tile by tile.

The reblurred reference ``m`` should match the observation ``g`` except where the scene
changed.  The decision runs in four stages, built so that a gigapixel image can be processed
as a stream of tiles, one module each:

1. **Photometry** (:mod:`.photometry`, :func:`fit_photometry`; global): per band
   ``g ~ a * m + b`` by Huber IRLS, optionally as a smooth field; the residual scale
   ``sigma`` is the unit of the statistic.
2. **Statistic** (:mod:`.statistic`, :func:`change_statistic`; local): the RMS of the
   per-band z-scores over a Gaussian window, of the residual left outside the model's
   tolerance interval (:mod:`.tolerance`: a fraction of a pixel of misregistration, a few
   percent of the local range of blur-shape error), the residual scale grown on edges
   and fine texture (:func:`fit_model_error`).
3. **Threshold** (:mod:`.threshold`, :func:`estimate_threshold`; global, from a sample of
   the statistic, never below ``DecisionParams.min_threshold``).
4. **Regions** (:mod:`.regions`; local up to the extent of a change region): a component
   tree with hysteresis and object-shape tests, then trimming, closing and hole filling.

:mod:`.tile` runs them on a padded tile (:func:`decide_tile`, :func:`tile_boxes`; its
docstring states the halo a tile needs for exact results) or on a whole image
(:func:`decide`); :mod:`.params` holds :class:`DecisionParams` and the reasons for its
defaults.  Each module's docstring describes its stage in full.
"""

from __future__ import annotations

# the public names (``__all__``) and, as redundant aliases, the private ones the tests and
# other modules import from ``reblur.decide``
from .calibrate import calibrate_tolerance, marked_pixels, unchanged_pixels
from .params import DecisionParams
from .photometry import Photometry, fit_photometry
from .regions import _boxes as _boxes
from .regions import _clear_of as _clear_of
from .regions import _components as _components
from .regions import _decide_core as _decide_core
from .regions import _label_median as _label_median
from .regions import _label_reaches as _label_reaches
from .regions import _region_records as _region_records
from .statistic import change_statistic, fit_model_error
from .statistic import gaussian_zero as gaussian_zero
from .threshold import estimate_threshold
from .tile import _tile_statistic as _tile_statistic
from .tile import decide, decide_tile, tile_boxes
from .tolerance import ModelTolerance, tolerance_interval, tolerant_reference

__all__ = [
    "Photometry",
    "fit_photometry",
    "DecisionParams",
    "change_statistic",
    "estimate_threshold",
    "fit_model_error",
    "decide_tile",
    "decide",
    "tile_boxes",
    "ModelTolerance",
    "calibrate_tolerance",
    "marked_pixels",
    "unchanged_pixels",
    "tolerance_interval",
    "tolerant_reference",
]
