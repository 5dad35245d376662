"""Coarse, low-resolution alignment of a sharp reference to a blurred observation, and its
refinement after the motion estimate.

The pose grid of the blur model (``tx, ty`` in +-12 px, ``rz`` in +-3 degrees) only absorbs
small viewpoint differences.  Larger ones are removed first by a global homography estimated
at low resolution, where the camera-shake blur is small (a 25 px blur is 3 px at 1/8 scale):

1. :func:`overview` reads both images in horizontal strips and block-averages them to a
   grey overview whose longest side is at most ``max_side`` (the same integer factor for both
   images), then a pyramid of halvings down to ``min_side`` (:mod:`.overviews`).  Through
   an :class:`OverviewCache` (as the pipeline reads them), an image whose file carries its
   own reduced-resolution levels (pyramidal TIFF, COG overviews, zarr multiscales) gives
   its overview from one of them, without reading the full image; the result's
   ``overviews`` says which.
2. SIFT features on an overview level, a ratio test and a robust homography (MAGSAC /
   RANSAC; a 4-dof similarity when matches are few) (:mod:`.features`).  If that fails,
   phase correlation gives a translation to start from (:mod:`.ecc`).
3. ECC refinement (:func:`cv2.findTransformECC`), coarse to fine, on Gaussian pre-blurred
   levels, up to the *working level*: the finest one on which the camera shake spans at
   most 4 pixels (:mod:`.ecc`).
4. Blur-aware polish on the working level: in a grid of regions, a non-negative blur kernel
   between the warped reference and the observation; its centroid is the mean camera
   displacement there (a correlation optimum sits near a mode of the blur instead, several
   pixels off).  A robust homography through the region centres moved by their centroids
   corrects the estimate, and the share of regions that agree with it verifies it
   (:mod:`.polish`).
5. Sanity checks: orientation, zoom, anisotropy, overlap, inliers, region agreement and
   correlation.  Anything implausible raises :class:`AlignmentError` -- never silent
   garbage (:mod:`.verify`).

Between captures years apart (other season, sun, sensor; buildings changed) local features
and the polish's blur model both fail, so the default ``method="auto"`` decides with
*gradient blocks* first (:mod:`.blocks`): signed-gradient fields of the reference warped by
the current estimate and of the observation are correlated block by block (96 px blocks,
+-8 pixels), and a robust similarity through the blocks whose correlation peak is confident
corrects the estimate.  Enough confident blocks -- a clear majority of them -- spread over
the image must agree; unrelated images give almost no confident block.  The initial
estimate is the SIFT one when it holds, else the best of a few in-plane rotation
hypotheses searched with larger blocks on a coarse level -- or, given a rough ``hint``
homography (from georeferencing, or by hand), the rotation hypotheses about it, which
reaches large rotations and pairs the features miss.  The polish then runs as well and is
kept where its blur model fits (a same-scene pair).  A refusal names each stage tried, its
evidence and what would let the user go on.  The options are one validated
:class:`AlignParams`.

:func:`coarse_align_shakes` tries several shake extents on one pair: the overviews, the
pyramid, and the stages that read the extent only through the working level (features,
their ECC refinement, gradient blocks) are computed once and shared (:mod:`.coarse`).

After the motion estimate, :func:`refine_alignment` measures the residual misregistration
of the reblurred reference on probe windows over the whole image and corrects the base
homography (:mod:`.refine`).  What no homography removes -- parallax, lens distortion that
differs between the captures -- is then measured on a lattice of tie points between the
reblurred reference and the observation and fitted by a smooth displacement field, applied
in the reblur when it predicts held-out tie points clearly better (:mod:`.field`).  Two
georeferenced inputs seed the alignment with the homography their CRSs and transforms imply
(:mod:`.georef`).

Coordinates follow :mod:`reblur.grid`: ``(x, y)`` = (column, row) with pixel centres on
integers, and ``H`` maps a reference pixel to the observation pixel.
"""

from .coarse import coarse_align, coarse_align_shakes
from .field import DisplacementField, FieldParams, estimate_field
from .georef import GeoPrior, geo_homography, image_prior
from .overviews import OverviewCache, block_means, overview, overview_matrix
from .params import AlignParams
from .refine import (
    ProbeShift,
    Refinement,
    RefineParams,
    measure_shifts,
    probe_boxes,
    refine_alignment,
)
from .result import Alignment, AlignmentError

__all__ = [
    "AlignParams", "Alignment", "AlignmentError", "DisplacementField", "FieldParams", "GeoPrior",
    "OverviewCache", "ProbeShift", "RefineParams", "Refinement", "block_means", "coarse_align",
    "coarse_align_shakes", "estimate_field", "geo_homography", "image_prior", "measure_shifts",
    "overview", "overview_matrix", "probe_boxes", "refine_alignment",
]
