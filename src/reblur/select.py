"""Choosing where to estimate the motion: Algorithm 1 of the paper, and its multi-window form.

All pixels see the same camera motion, so the weights can be estimated from a window, as long
as the window is large enough for the blur to vary inside it (a small one looks
space-invariant and gives the wrong weights).  The *kernel-similarity measure* ``m`` of a
window tells: estimate a translation-only blur kernel (eq. 3) on ``gamma`` scattered patches,
take for every pair the maximum of their normalised cross-correlation (eq. 7-8) and average.
``m`` near 1 means the blur looks the same everywhere in the window.

Constants (the paper's defaults, each a parameter of :class:`SelectParams`): ``beta = 6``
initial 100 x 100 crops at good regions, ``gamma = 4`` patches, ``T_m = 0.6 m_1``, sizes
``S = 2 .. 9`` (x 100 px), ``alpha = 5`` locations per size, reject a window more than 2/3
occluded.  Patch side: 41 px as in the paper: with the grid's translation range (25 x 25
kernel) a 41 x 41 patch gives 1681 equations for 625 non-negative unknowns of which only a
few tens are non-zero, enough for a stable estimate, and four of them fit in the initial
100 x 100 crop (quadrant centres) without overlapping.

"Good regions to deblur" (Hu and Yang, ECCV 2012) are rich in strong edges of several
orientations.  The score of a region here is the geometric mean, over four orientation bins,
of the energy of its strong gradients: it is high only when every orientation is present
(a region of parallel edges constrains the blur along one direction only).
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass, field
from numbers import Integral, Real

import cv2
import numpy as np
import scipy.fft as sfft
from threadpoolctl import threadpool_limits

from .estimate import MAX_ACTIVE, check_bands, estimate_motion
from .grid import PoseGrid, map_points
from .result import CropChoice, MotionEstimate
from .warp import Box

__all__ = ["SelectParams", "kernel_similarity", "region_scores", "select_windows", "spread_side"]


@dataclass(frozen=True)
class SelectParams:
    """Constants of sub-image selection (paper's defaults)."""

    beta: int = 6  #: initial crops of size S = 1
    gamma: int = 4  #: patches per crop for the kernel-similarity measure
    patch: int = 41  #: patch side (pixels)
    unit: int = 100  #: the size unit (S = 1 is unit x unit pixels)
    s_start: int = 2  #: first size tried after the initial crops
    s_max: int = 9  #: largest size before declaring the blur space-invariant
    alpha: int = 5  #: locations tried per size
    ratio: float = 0.6  #: T_m = ratio * m_1
    invariant_ratio: float = 0.9  #: no window passed T_m: space-invariant only if m >= this * m_1
    max_occluded: float = 2.0 / 3.0  #: reject a window with more occluded pixels than this
    #: estimates tried at most (the first one and the replacements of rejected windows);
    #: when none fits, the best one is finished and used (``info["selection"]``)
    max_tries: int = 3
    #: outer iterations per level, and the solves' ``rtol``, when finishing an estimate
    #: whose windows do not fit: its weights model change as much as blur, and more
    #: iterations only spread them over more poses
    unfit_outer: int = 10
    unfit_rtol: float = 1e-3
    windows: int = 1  #: windows estimated jointly (1 = the paper's Algorithm 1)
    spread_size: int = 5  #: largest window side (units) when ``windows >= 2``
    #: pixels of all spread windows together: the side is at most ``sqrt(spread_pixels /
    #: windows)`` (in whole units), so more windows spread the same estimation cost wider
    #: (2 or 3 windows: 500 px, 4 or 5: 400 px; :func:`spread_side`)
    spread_pixels: int = 800_000
    #: spread windows scoring at least this fraction of the best window count as fully
    #: textured: their distance apart, not their texture, then decides (roll observability)
    texture_floor: float = 0.2
    lam: float = 0.1
    #: remove the photometric offset on the final windows after the motion
    #: (``estimate_motion(refit_photometry=True)``)
    refit_photometry: bool = True
    #: what the weights are solved on for images of several bands: ``"mean"``, their
    #: band mean (a third of the solver's cost for RGB; the change term and the fit's
    #: figures stay per band), or ``"all"`` (``estimate_motion(bands=)``)
    bands: str = "mean"
    #: how far the estimate may widen the pose grid's translations when its weights pile
    #: on their edge (a factor of the grid's; ``estimate_motion(t_grow=)``; 1: never)
    t_grow: int = 4
    #: poses each of the estimate's solves may hold (``estimate_motion(max_active=)``): a
    #: camera shake's path holds a few hundred at most, a dense blur (defocus) thousands,
    #: at a cost growing as their square and cube
    max_active: int = MAX_ACTIVE
    overview_side: int = 1024  #: resolution of the region-score map
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("beta", "gamma", "patch", "unit", "s_start", "s_max", "alpha",
                     "max_tries", "unfit_outer", "windows", "spread_size", "spread_pixels",
                     "overview_side", "t_grow", "max_active"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, Integral) or v < 1:
                raise ValueError(f"SelectParams.{name} must be an integer >= 1, got {v!r}")
        for name in ("ratio", "invariant_ratio", "max_occluded", "texture_floor"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, Real) or not 0 <= v <= 1:
                raise ValueError(f"SelectParams.{name} must lie in [0, 1], got {v!r}")
        if isinstance(self.lam, bool) or not (isinstance(self.lam, Real)
                                              and 0 < self.lam < float("inf")):
            raise ValueError(f"SelectParams.lam must be a finite number > 0, got {self.lam!r}")
        if isinstance(self.unfit_rtol, bool) or not (isinstance(self.unfit_rtol, Real)
                                                     and 0 <= self.unfit_rtol < 1):
            raise ValueError(f"SelectParams.unfit_rtol must lie in [0, 1), got "
                             f"{self.unfit_rtol!r}")
        check_bands(self.bands, "SelectParams.bands")
        if self.s_start > self.s_max:
            raise ValueError(f"SelectParams.s_start ({self.s_start}) must be at most s_max "
                             f"({self.s_max})")


# ---------------------------------------------------------------------------- scores
def _gray_overview(image, max_side: int) -> tuple[np.ndarray, float]:
    from .align import overview

    return overview(image, max_side)


def region_scores(gray: np.ndarray, cell: int) -> np.ndarray:
    """Good-region score of every ``cell x cell`` block of a grayscale image.

    Returns an array of shape ``(H // cell, W // cell)``: the geometric mean over four
    orientation bins (0, 45, 90, 135 degrees) of the energy of the strong gradients (above
    the image's 75th percentile of gradient magnitude) in the block.
    """
    g = gray.astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    mag = np.hypot(gx, gy)
    strong = mag > np.percentile(mag, 75)
    ang = (np.rad2deg(np.arctan2(gy, gx)) + 180.0) % 180.0
    bins = ((ang + 22.5) // 45).astype(int) % 4
    ny, nx = g.shape[0] // cell, g.shape[1] // cell
    if ny == 0 or nx == 0:
        return np.zeros((max(ny, 0), max(nx, 0)))
    e = np.zeros((4, ny, nx))
    m2 = (mag * mag * strong)[: ny * cell, : nx * cell]
    b = bins[: ny * cell, : nx * cell]
    for k in range(4):
        e[k] = (m2 * (b == k)).reshape(ny, cell, nx, cell).sum(axis=(1, 3))
    return np.exp(np.log(e + 1e-12).mean(axis=0))


def _lattice_scores(gray: np.ndarray, s: float, lat: _Lattice,
                    shape: tuple[int, int]) -> np.ndarray:
    """:func:`region_scores` of ``lat``'s cells in an observation of ``shape``, from its
    overview ``gray`` (``s`` overview pixels per observation pixel); 0 where the overview
    has no whole cell."""
    cell_small = max(int(round(lat.unit * s)), 2)
    y0, x0 = int(round(lat.oy * s)), int(round(lat.ox * s))
    small = region_scores(gray[y0:, x0:], cell_small)
    cells = np.zeros(lat.shape(*shape))
    cy, cx = min(cells.shape[0], small.shape[0]), min(cells.shape[1], small.shape[1])
    cells[:cy, :cx] = small[:cy, :cx]
    return cells


def _window_scores(cells: np.ndarray, n: int) -> np.ndarray:
    """Mean cell score of every ``n x n`` block of cells (summed-area table)."""
    ny, nx = cells.shape
    if n > ny or n > nx:
        return np.zeros((0, 0))
    sat = np.zeros((ny + 1, nx + 1))
    sat[1:, 1:] = cells.cumsum(0).cumsum(1)
    return (sat[n:, n:] - sat[:-n, n:] - sat[n:, :-n] + sat[:-n, :-n]) / (n * n)


# ---------------------------------------------------------------------------- measure
def _ncc_max(a: np.ndarray, b: np.ndarray, sigma: float = 1.0) -> float:
    """Largest normalised cross-correlation of two kernels over every lag."""
    if sigma > 0:  # kernels from small patches are spiky: compare them at 1-px tolerance
        a = cv2.GaussianBlur(a, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
        b = cv2.GaussianBlur(b, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return 0.0
    # every lag of the full linear correlation: a circular one on the zero-padded size
    # (scipy.fft; scipy.signal would cost a quarter of a second of import per run)
    size = (a.shape[0] + b.shape[0] - 1, a.shape[1] + b.shape[1] - 1)
    corr = sfft.irfft2(sfft.rfft2(a, size) * np.conj(sfft.rfft2(b, size)), size)
    return float(corr.max() / (na * nb))


def _patch_boxes(box: Box, gamma: int, patch: int) -> list[Box]:
    """``gamma`` scattered patches: centres spread over the window (quadrant centres for 4)."""
    if gamma == 4:
        fr = [(0.25, 0.25), (0.25, 0.75), (0.75, 0.25), (0.75, 0.75)]
    else:
        ang = np.linspace(0, 2 * np.pi, gamma, endpoint=False)
        fr = [(0.5 + 0.3 * np.sin(a), 0.5 + 0.3 * np.cos(a)) for a in ang]
    out = []
    for fy, fx in fr:
        cy = box.y0 + fy * box.h
        cx = box.x0 + fx * box.w
        y0 = int(np.clip(round(cy - patch / 2), box.y0, box.y1 - patch))
        x0 = int(np.clip(round(cx - patch / 2), box.x0, box.x1 - patch))
        out.append(Box(y0, x0, patch, patch))
    return out


def kernel_similarity(
    reference, observed, box, grid: PoseGrid, *, base=None, gamma: int = 4, patch: int = 41,
    lam: float = 0.1, bands: str = "all",
) -> tuple[float, list[np.ndarray]]:
    """Kernel-similarity measure ``m`` of a window (eq. 7-8).

    Translation-only kernels (the grid's translations, no rotation) are estimated by eq. 3
    on ``gamma`` scattered ``patch x patch`` patches (on every band or on their mean:
    :func:`reblur.estimate.estimate_motion`'s ``bands``); ``m`` is the mean over pairs of
    the maximum normalised cross-correlation of their kernels (1 = identical kernels).

    Returns
    -------
    m : float
    kernels : list of (len(ty), len(tx)) arrays
    """
    from .warp import as_box

    box = as_box(box)
    tgrid = PoseGrid(grid.image_shape, tx=grid.tx, ty=grid.ty, center=grid.center)
    kernels = []
    for pb in _patch_boxes(box, gamma, min(patch, box.h, box.w)):
        est = estimate_motion(
            reference, observed, tgrid, boxes=[pb.as_tuple()], base=base, lam=lam,
            occlusion=False, max_outer=20, bands=bands,
        )
        kernels.append(est.weights[0])
    pairs = list(itertools.combinations(range(len(kernels)), 2))
    m = float(np.mean([_ncc_max(kernels[i], kernels[j]) for i, j in pairs])) if pairs else 1.0
    return m, kernels


# ---------------------------------------------------------------------------- selection
#: Largest share of a cell that may disagree (a large change) for it to hold a window: the
#: windows keep off large changes (the l1 fit of eq. 5 prefers zero weights once about half
#: of its windows' pixels are a new surface darker than the reference there); a smaller
#: change inside a window is left out of its data term instead (``ScaledView.exclude``), and
#: the window stays where the texture is (at 1/3 the demo's windows moved off its right
#: half and its JC fell 0.789 -> 0.661, ``reblur demo``).
MAX_DISAGREEING = 0.5


@dataclass(frozen=True)
class _Lattice:
    """Cells of ``unit`` x ``unit`` observation pixels, the first one's corner at ``(oy,
    ox)``: the positions the windows are chosen from."""

    unit: int
    oy: int = 0
    ox: int = 0

    def shape(self, H: int, W: int) -> tuple[int, int]:
        """Cells in an ``H x W`` observation."""
        return max((H - self.oy) // self.unit, 0), max((W - self.ox) // self.unit, 0)

    def box(self, iy, ix, n: int) -> Box:
        """The ``n x n``-cell window whose first cell is ``(iy, ix)``."""
        u = self.unit
        return Box(self.oy + int(iy) * u, self.ox + int(ix) * u, n * u, n * u)

    def centres(self, shape: tuple[int, int], n: int) -> tuple[np.ndarray, np.ndarray]:
        """Centres (y, x; pixels) of the ``n x n``-cell windows starting at each of
        ``shape`` cells."""
        ys, xs = np.mgrid[0 : shape[0], 0 : shape[1]]
        return self.oy + (ys + n / 2) * self.unit, self.ox + (xs + n / 2) * self.unit

    def cell(self, y: int, x: int) -> tuple[int, int]:
        """The cell holding pixel ``(y, x)``."""
        return (y - self.oy) // self.unit, (x - self.ox) // self.unit


def centred_lattice(H: int, W: int, unit: int) -> _Lattice:
    """The lattice one cell shorter along each axis that has two or more, centred.

    The edge-aligned lattice's outer cells reach the image's edges, where the pose grid's
    translation margin leaves no pixel for every pose; when the image is one or two cells
    across (a strip), no cell of it is covered (:func:`_coverage_cells`), while a centred
    cell keeps half the spare pixels on each side.
    """
    def origin(n: int) -> int:
        k = n // unit
        return (n - max(k - 1, 1) * unit) // 2 if k >= 1 else 0

    return _Lattice(unit, origin(H), origin(W))


def agreeing_cells(agreement: np.ndarray, factor: int, shape: tuple[int, int],
                   unit: int, origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Cells of ``unit`` pixels (``shape`` of them, the first at ``origin``) where at most
    :data:`MAX_DISAGREEING` of the low-resolution ``agreement`` map (``factor`` observation
    pixels per map pixel; NaN: no data, counted as disagreeing) says the images disagree."""
    a = np.nan_to_num(np.asarray(agreement, np.float64), nan=0.0)
    ny, nx = shape
    ii = np.zeros((a.shape[0] + 1, a.shape[1] + 1))
    ii[1:, 1:] = a.cumsum(0).cumsum(1)
    oy, ox = origin
    ys = np.clip(np.round((oy + np.arange(ny + 1) * unit) / factor).astype(int), 0,
                 a.shape[0])
    xs = np.clip(np.round((ox + np.arange(nx + 1) * unit) / factor).astype(int), 0,
                 a.shape[1])
    s = ii[ys[1:, None], xs[None, 1:]] - ii[ys[:-1, None], xs[None, 1:]] \
        - ii[ys[1:, None], xs[None, :-1]] + ii[ys[:-1, None], xs[None, :-1]]
    n = (ys[1:] - ys[:-1])[:, None] * (xs[1:] - xs[:-1])[None, :]
    frac = np.where(n > 0, s / np.maximum(n, 1), 0.0)
    return frac >= 1.0 - MAX_DISAGREEING


def _candidates(cells: np.ndarray, cover: np.ndarray, n: int, k: int,
                lat: _Lattice) -> list[Box]:
    """Up to ``k`` best ``n x n``-cell windows, fully covered, not overlapping each other."""
    sc = _window_scores(cells, n)
    cv = _window_scores(cover.astype(float), n)
    if sc.size == 0:
        return []
    sc = np.where(cv >= 1.0 - 1e-9, sc, -np.inf)
    taken = np.zeros(sc.shape, bool)
    out: list[Box] = []
    order = np.argsort(sc, axis=None)[::-1]
    for flat in order:
        iy, ix = np.unravel_index(flat, sc.shape)
        if not np.isfinite(sc[iy, ix]) or taken[iy, ix]:
            continue
        out.append(lat.box(iy, ix, n))
        taken[max(iy - n + 1, 0) : iy + n, max(ix - n + 1, 0) : ix + n] = True
        if len(out) >= k:
            break
    return out


def _coverage_cells(ref_shape, obs_shape, base, grid: PoseGrid, unit: int,
                    origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Cells of the observation that every base pose maps inside the reference.

    The reference must also hold the translation margin (the largest |t| plus 2 px), so that
    a window made of covered cells has a valid pixel for every pose.

    A fine grid has thousands of base poses (a gigapixel's roll step moves its corners by
    one pixel), and neighbouring ones map every point within a few pixels of each other.
    So every ``m``-th base is mapped first: a cell that these bases map inside the
    reference shrunk by ``delta`` (the largest distance between where a base and its
    nearest mapped base send the corners, edge midpoints and centre of the observation,
    the farthest points of a near-affine displacement, grown by a quarter and a pixel) is
    covered, a cell that one of them maps outside is not, and only the cells left in
    between, a band along the limit, are mapped by every base.  The result is the
    definition's, without mapping every cell by each of the thousands of angles.  The
    cells are ``unit`` pixels, the first one's corner at ``origin`` (y, x).
    """
    oy, ox = origin
    ny, nx = _Lattice(unit, oy, ox).shape(*obs_shape[:2])
    Hr, Wr = ref_shape[:2]
    B0 = np.eye(3) if base is None else np.asarray(base, float)
    margin = max(max(abs(v) for v in grid.tx), max(abs(v) for v in grid.ty)) + 2
    inv = [np.linalg.inv(grid.base_homography(b) @ B0) for b in range(grid.n_bases)]
    ys, xs = np.mgrid[0:ny, 0:nx]
    corners = [np.stack([ox + xs.ravel() * unit + dx, oy + ys.ravel() * unit + dy],
                        axis=1).astype(float)
               for dy, dx in itertools.product((0, unit - 1), (0, unit - 1))]

    def inside(bases, cells: np.ndarray, lim: float) -> np.ndarray:
        ok = np.ones(cells.size, bool)
        for b in bases:
            for pts in corners:
                q = map_points(inv[b], pts[cells])
                ok &= ((q[:, 0] >= lim) & (q[:, 0] <= Wr - 1 - lim)
                       & (q[:, 1] >= lim) & (q[:, 1] <= Hr - 1 - lim))
        return ok

    n = len(inv)
    every = np.arange(ny * nx)
    h1, w1 = obs_shape[0] - 1.0, obs_shape[1] - 1.0
    probe = np.array([[x, y] for y in (0.0, h1 / 2, h1) for x in (0.0, w1 / 2, w1)])
    mapped = np.stack([map_points(Hi, probe) for Hi in inv])  # (n_bases, 9, 2)

    def gap(c: np.ndarray) -> np.ndarray:
        # per base: the farthest probe from where mapped base c sends it
        return np.hypot(*(mapped - mapped[c]).transpose(2, 0, 1)).max(axis=1)

    step, delta = 1, 0.0
    for m in (64, 32, 16, 8, 4):
        if 2 * m > n:
            continue
        sub = np.unique(np.r_[np.arange(0, n, m), n - 1])
        j = np.searchsorted(sub, np.arange(n))
        # one mapped base must cover every point of a base: the nearer of its two
        # neighbours by their farthest probe (not the nearer one probe by probe)
        d = np.minimum(gap(sub[np.minimum(j, sub.size - 1)]), gap(sub[np.maximum(j - 1, 0)]))
        bound = 1.25 * float(d.max()) + 1.0
        if bound <= unit:
            step, delta = m, bound
            break
    if step == 1:
        return inside(range(n), every, margin).reshape(ny, nx)
    sub = np.unique(np.r_[np.arange(0, n, step), n - 1])
    sure = inside(sub, every, margin + delta)
    # not sure, and no mapped base sends it out: decided by every base
    band = np.flatnonzero(inside(sub, every, margin) & ~sure)
    cover = sure.copy()
    if band.size:
        cover[band] = inside(range(n), band, margin)
    return cover.reshape(ny, nx)


def select_windows(
    reference,
    observed,
    grid: PoseGrid,
    *,
    base: np.ndarray | None = None,
    params: SelectParams | None = None,
    progress=None,
    agreement: tuple[np.ndarray | None, int] | None = None,
    blur_reach: float = 0.0,
) -> tuple[CropChoice, MotionEstimate]:
    """Algorithm 1: choose the estimation window(s) and estimate the motion on them.

    Parameters
    ----------
    reference, observed : array-like
        Full images (numpy or lazy arrays); the observation in [0, 1]-scaled or integer units.
    grid : PoseGrid
        Pose grid on the observation geometry.
    base : (3, 3) ndarray, optional
        Coarse alignment (reference -> observation).
    params : SelectParams
        The algorithm's constants.
    progress : callable, optional
        Called with a short text after each window tried.
    agreement : (ndarray, int), optional
        A low-resolution map over the observation, 1 where the aligned images agree and 0
        where they do not (a large change), and the observation pixels per map pixel
        (:func:`reblur.pipeline.photometric_prefit`): windows keep to the cells where the
        images agree (:func:`agreeing_cells`), when there are any.
    blur_reach : float
        A radius (px) the blur is known to reach beyond (:func:`reblur.pipeline.blur_reach`):
        the estimates start on translations at least that wide (``estimate_motion``'s
        ``blur_reach``, within ``params.t_grow``).  0 (default): from ``grid``'s.

    Returns
    -------
    CropChoice
        Accepted window(s), ``m_1``, ``T_m``, every window tried with its measure.
    MotionEstimate
        Weights estimated on the accepted window(s) by eq. 5.

    Raises
    ------
    ValueError
        When no window of the observation is covered by the reference for every pose, or
        the images are textureless (the motion cannot be estimated).
    """
    p = params or SelectParams()
    H, W = observed.shape[:2]
    unit = p.unit
    if min(H, W) < unit:
        raise ValueError(f"the observation ({H}x{W}) is smaller than one {unit}-px crop")
    gray, s = _gray_overview(observed, p.overview_side)
    lat = _Lattice(unit)
    cells = _lattice_scores(gray, s, lat, (H, W))
    if not np.any(cells > 1e-9):
        raise ValueError("motion cannot be estimated: the observation is textureless")
    cover = _coverage_cells(reference.shape, (H, W), base, grid, unit)
    centred = centred_lattice(H, W, unit)
    if not cover.any() and centred != lat:
        # a strip one or two cells across: the margin leaves no edge-aligned cell
        lat = centred
        cells = _lattice_scores(gray, s, lat, (H, W))
        cover = _coverage_cells(reference.shape, (H, W), base, grid, unit, (lat.oy, lat.ox))
    # a strip: at least twice as long as it is across, and the pose grid's margin leaves
    # at most one line of covered cells across it
    strip = (max(cover.shape) >= 2 * min(cover.shape)
             and min(cover.any(axis=1).sum(), cover.any(axis=0).sum()) <= 1)
    extra: dict = {}
    if strip:
        roll = max(abs(r) for r in grid.rz)
        grid, cover = _strip_roll(reference.shape, (H, W), base, grid, lat, cover)
        if max(abs(r) for r in grid.rz) < roll:
            extra["strip_roll_deg"] = [roll, max(abs(r) for r in grid.rz)]
    if agreement is not None and agreement[0] is not None:
        agreeing = agreeing_cells(agreement[0], agreement[1], cover.shape, unit,
                                  (lat.oy, lat.ox))
        if (cover & agreeing).any():
            cover = cover & agreeing
    if not cover.any():
        raise ValueError(
            "motion cannot be estimated: no part of the observation is covered by the "
            "reference for every pose of the grid (align first or shrink the grid)"
        )
    tried: list[dict] = []
    if p.windows >= 2:
        return _select_spread(reference, observed, grid, base, p, cells, cover, (H, W),
                              progress, blur_reach, lat, strip, extra)

    runs = _Runs(reference, observed, grid, base, p, blur_reach, extra)

    def measure(b: Box) -> float:
        m, _ = kernel_similarity(
            reference, observed, b.as_tuple(), grid, base=base, gamma=p.gamma, patch=p.patch,
            lam=p.lam, bands=p.bands,
        )
        return m

    with threadpool_limits(1, user_api="blas"):
        init = _candidates(cells, cover, 1, p.beta, lat)
        if not init:
            raise ValueError("motion cannot be estimated: no textured, covered region found")
        m_init = []
        for b in init:
            m = measure(b)
            m_init.append(m)
            tried.append(dict(box=b.as_tuple(), size=1, m=m, accepted=False, reason="initial"))
        m1 = float(np.mean(m_init))
        thr = p.ratio * m1
        if progress:
            progress(f"m_1 = {m1:.3f}, T_m = {thr:.3f}")
        for S in range(p.s_start, p.s_max + 1):
            if S > min(cells.shape) or len(runs) >= max(1, p.max_tries):
                break
            boxes = _candidates(cells, cover, S, p.alpha, lat)
            for b in boxes:
                m = measure(b)
                rec = dict(box=b.as_tuple(), size=S, m=m, accepted=False, reason="")
                tried.append(rec)
                if progress:
                    progress(f"S = {S}: m = {m:.3f}")
                if m >= thr:
                    rec["reason"] = "m >= T_m (looks space-invariant)"
                    continue
                chosen = [b] + _spread_partners(cells, cover, S, lat, b, p.windows - 1, (H, W),
                                               p.texture_floor)
                est = runs.estimate(chosen)
                occ = _occluded_fraction(est)
                rec["occluded"] = occ
                if occ > p.max_occluded:
                    rec["reason"] = f"{occ:.0%} occluded"
                    if len(runs) >= max(1, p.max_tries):
                        break
                    continue
                rec["accepted"] = True
                rec["reason"] = "m < T_m"
                crop = CropChoice(
                    boxes=[c.as_tuple() for c in chosen], size=S * unit, m1=m1, threshold=thr,
                    tried=tried,
                )
                return crop, runs.finish(est, fits=True)
        if runs:
            # every window estimated was rejected: decide from the least occluded one
            chosen, est = runs.runs[runs.best_index()]
            for r in tried:
                r["accepted"] = r["box"] == chosen[0].as_tuple() and "occluded" in r
            crop = CropChoice(boxes=[c.as_tuple() for c in chosen], size=chosen[0].h, m1=m1,
                              threshold=thr, tried=tried)
            return crop, runs.finish(est, fits=False)
        # No window passed T_m.  The paper then declares the blur space-invariant and uses
        # one kernel.  Here the full grid is solved on the largest window tried instead: if
        # the blur is space-invariant the weights land on the zero-rotation base anyway, and
        # if the window was simply too small to reach T_m (images of a few hundred pixels,
        # or 1000 px images whose far kernels leave the translation support) the rotation
        # is kept.  ``space_invariant`` still records the paper's verdict (m stayed above
        # invariant_ratio * m_1 at every size).
        grown = [r for r in tried if r["size"] >= p.s_start] or tried
        largest = max(r["size"] for r in grown)
        rec = min((r for r in grown if r["size"] == largest), key=lambda r: r["m"])
        invariant = all(r["m"] >= p.invariant_ratio * m1 for r in grown)
        b = Box(*rec["box"])
        chosen = [b] + _spread_partners(cells, cover, rec["size"], lat, b, p.windows - 1,
                                       (H, W), p.texture_floor)
        est = runs.estimate(chosen, stop=False)
        rec["accepted"] = True
        rec["reason"] = "largest window tried (none reached T_m)"
        crop = CropChoice(boxes=[c.as_tuple() for c in chosen], size=rec["size"] * unit, m1=m1,
                          threshold=thr, tried=tried, space_invariant=invariant)
        return crop, runs.finish(est, fits=_occluded_fraction(est) <= p.max_occluded)


def spread_side(p: SelectParams) -> int:
    """Side (units) of the spread windows: ``spread_size``, or less so that the
    ``windows`` windows hold at most ``spread_pixels`` pixels together (at least 1 unit).

    The estimate's cost grows with its pixels (Gram products of the active poses, the
    spectra of the warped stacks), and four or five windows of 500 px made it the largest
    fixed cost of the pipeline; the roll is observable from where the windows are, not
    from their size (``python -m benchmarks.large_motion``).
    """
    per = np.sqrt(p.spread_pixels / max(p.windows, 1))
    return int(max(1, min(p.spread_size, per // p.unit)))


def _select_spread(reference, observed, grid, base, p: SelectParams, cells, cover, shape,
                   progress, blur_reach: float = 0.0, lat: _Lattice | None = None,
                   strip: bool = False,
                   extra: dict | None = None) -> tuple[CropChoice, MotionEstimate]:
    """``p.windows`` windows of :func:`spread_side` units, good regions spread far apart.

    Seen from one window, a small roll about a distant principal point is nearly a pure
    translation, so the roll is observable only from windows far apart.  The first window
    maximises (texture x distance from the principal point), each next one (texture x
    distance to the nearest chosen window); all are estimated jointly (eq. 5 stacked, one
    set of weights).  A window more than ``max_occluded`` occluded is replaced by the next
    best one.  On a ``strip`` (one line of covered cells across), windows of one cell are
    lengthened along it (:func:`_elongate`); elsewhere a window is as large as the covered,
    agreeing cells around it allow, and square.
    """
    unit = p.unit
    lat = lat or _Lattice(unit)
    pcx, pcy = grid.center
    tried: list[dict] = []
    target = spread_side(p)

    def place(S: int, excluded: np.ndarray | None) -> list[Box]:
        """Greedy placement of up to ``p.windows`` non-overlapping S x S windows."""
        sc = _window_scores(cells, S)
        cv = _window_scores(cover.astype(float), S)
        ok = (cv >= 1.0 - 1e-9) & (sc > 0)
        if excluded is not None and excluded.shape == ok.shape:
            ok &= ~excluded
        if not ok.any():
            return []
        cyy, cxx = lat.centres(sc.shape, S)
        smax = sc[ok].max()
        chosen: list[Box] = []
        for _ in range(p.windows):
            if chosen:
                d = np.min([np.hypot(cyy - (c.y0 + c.h / 2), cxx - (c.x0 + c.w / 2))
                            for c in chosen], axis=0)
                allowed = ok & (d >= S * unit)
            else:
                d = np.hypot(cyy - pcy, cxx - pcx) + unit
                allowed = ok
            if not allowed.any():
                break
            obj = np.where(allowed, _texture_term(sc, smax, p.texture_floor) * d, -np.inf)
            iy, ix = np.unravel_index(int(np.argmax(obj)), obj.shape)
            chosen.append(lat.box(iy, ix, S))
        if strip and S == 1 < target:
            chosen = _elongate(chosen, cover, lat, target * target)
        return chosen

    # the largest side up to spread_size at which all the windows fit
    best: tuple[int, list[Box]] = (0, [])
    for S in range(int(min(target, cells.shape[0], cells.shape[1])), 0, -1):
        chosen = place(S, None)
        if len(chosen) > len(best[1]):
            best = (S, chosen)
        if len(chosen) >= p.windows:
            break
    S, chosen = best
    if not chosen:
        raise ValueError("motion cannot be estimated: no textured, covered window found")
    runs = _Runs(reference, observed, grid, base, p, blur_reach, extra)
    excluded = np.zeros(_window_scores(cells, S).shape, bool)
    run_recs: list[list[dict]] = []
    while True:
        if progress:
            progress(f"{len(chosen)} spread windows of {S * unit} px")
        est = runs.estimate(chosen)
        occ = est.info["occluded"]
        bad = [i for i, o in enumerate(occ) if o > p.max_occluded]
        recs = [dict(box=c.as_tuple(), size=S, m=float("nan"), accepted=not bad,
                     occluded=occ[i],
                     reason=f"{occ[i]:.0%} occluded" if i in bad else "spread window")
                for i, c in enumerate(chosen)]
        tried += recs
        run_recs.append(recs)
        if not bad:
            break
        if len(bad) == len(chosen) or len(runs) >= max(1, p.max_tries):
            # every window is mostly change (the pair itself does not fit the model:
            # unrelated, or years apart), or the tries are spent
            break
        for i in bad:
            excluded |= _overlapping(excluded.shape, chosen[i], S, lat)
        nxt = place(S, excluded)
        if len(nxt) < len(chosen) or {c.as_tuple() for c in nxt} == {
                c.as_tuple() for c in chosen}:
            break
        chosen = nxt
    if bad:  # no estimate fits: decide from the best one
        k = runs.best_index()
        chosen, est = runs.runs[k]
        for r in run_recs[k]:
            r["accepted"] = True
    crop = CropChoice(boxes=[c.as_tuple() for c in chosen],
                      size=max(max(c.h, c.w) for c in chosen), tried=tried)
    return crop, runs.finish(est, fits=not bad)


def _strip_roll(ref_shape, obs_shape, base, grid: PoseGrid, lat: _Lattice,
                cover: np.ndarray) -> tuple[PoseGrid, np.ndarray]:
    """On a strip, ``grid`` with its roll range halved while the covered cells span less
    than half the strip's length, and the cells it covers.

    A roll about the strip's centre moves its ends across it: the paper's 3 degrees move
    the ends of a 1024 px strip by 27 px, more than a strip 150 px across leaves beside a
    row of cells, so only its central cells are covered for every pose.  From one window
    there the roll is not observable, and the false alarms gather at the ends (4.3 % of a
    150 x 1024 test-bed strip, ``python -m benchmarks.strips``).  Windows far apart along
    the strip observe it; the roll range the strip can hold is the model, and
    ``info["selection"]["strip_roll_deg"]`` records it (the report notes it).
    """
    along = 1 if cover.shape[1] >= cover.shape[0] else 0

    def span(c: np.ndarray) -> int:
        idx = np.flatnonzero(c.any(axis=1 - along))
        return 0 if idx.size == 0 else int(idx[-1] - idx[0] + 1)

    while 2 * span(cover) < cover.shape[along]:
        lim = max(abs(r) for r in grid.rz) / 2.0
        rz = tuple(r for r in grid.rz if abs(r) <= lim + 1e-12)
        if len(rz) == len(grid.rz) or not rz:
            break
        grid = dataclasses.replace(grid, rz=rz)
        cover = _coverage_cells(ref_shape, obs_shape, base, grid, lat.unit, (lat.oy, lat.ox))
    return grid, cover


def _elongate(chosen: list[Box], cover: np.ndarray, lat: _Lattice, cells: int) -> list[Box]:
    """``chosen`` windows grown a covered row or column of cells at a time, up to ``cells``
    cells each.

    Where the covered cells leave room for windows of one cell only (a strip one or two
    cells across), the estimate would rest on a fraction of the pixels the spread windows
    are meant to hold: from two 100 px windows the roll and the kernels' change across the
    image are poorly constrained.  The windows take turns, each
    adding one line of cells on the next of its four sides that is covered and not another
    window's, so a strip's windows grow along it and none takes the room of another.
    """
    spans = []  # per window: [y0, y1, x0, x1) in cells
    for b in chosen:
        y0, x0 = lat.cell(b.y0, b.x0)
        y1, x1 = lat.cell(b.y0 + b.h - 1, b.x0 + b.w - 1)
        spans.append([y0, y1 + 1, x0, x1 + 1])

    def grown(sp: list[int], side: int) -> list[int] | None:
        """``sp`` with one more line on ``side`` (0 right, 1 left, 2 down, 3 up), if free."""
        y0, y1, x0, x1 = sp
        new = [[y0, y1, x0, x1 + 1], [y0, y1, x0 - 1, x1],
               [y0, y1 + 1, x0, x1], [y0 - 1, y1, x0, x1]][side]
        if new[0] < 0 or new[2] < 0 or new[1] > cover.shape[0] or new[3] > cover.shape[1]:
            return None
        if not cover[new[0]:new[1], new[2]:new[3]].all():
            return None
        for other in spans:
            if other is not sp and (new[0] < other[1] and other[0] < new[1]
                                    and new[2] < other[3] and other[2] < new[3]):
                return None
        return new

    turn, grew = 0, True
    while grew:
        grew = False
        for sp in spans:
            if (sp[1] - sp[0]) * (sp[3] - sp[2]) >= cells:
                continue
            for k in range(4):
                new = grown(sp, (turn + k) % 4)
                if new is not None:
                    sp[:] = new
                    grew = True
                    break
        turn += 1
    u = lat.unit
    return [Box(lat.oy + y0 * u, lat.ox + x0 * u, (y1 - y0) * u, (x1 - x0) * u)
            for y0, y1, x0, x1 in spans]


def _overlapping(shape: tuple[int, int], box: Box, S: int, lat: _Lattice) -> np.ndarray:
    """Positions (cells of ``lat``) of the ``S x S``-cell windows that overlap ``box``."""
    out = np.zeros(shape, bool)
    y0, x0 = lat.cell(box.y0, box.x0)
    y1, x1 = lat.cell(box.y0 + box.h - 1, box.x0 + box.w - 1)
    out[max(y0 - S + 1, 0) : y1 + 1, max(x0 - S + 1, 0) : x1 + 1] = True
    return out


class _Runs:
    """The estimates of one selection: bounded in number, each stopped after its first
    coarse level when a window is more than ``max_occluded`` change (the paper's
    rejection, at a fraction of a full estimate's cost), the best one finished.

    ``info["selection"]`` of the returned estimate holds ``estimates`` (how many were
    run), ``n_outer`` (the outer solver iterations of all of them together: the cost
    bound a pathological pair cannot exceed), ``fits`` and ``occluded`` (per window), and
    ``extra`` (``strip_roll_deg``: the roll range narrowed to a strip, from and to).
    """

    def __init__(self, reference, observed, grid, base, p: SelectParams,
                 blur_reach: float = 0.0, extra: dict | None = None):
        self.args = (reference, observed, grid)
        self.base, self.p, self.blur_reach = base, p, blur_reach
        self.extra = dict(extra or {})
        self.runs: list[tuple[list[Box], MotionEstimate]] = []
        self.n_outer = 0

    def __len__(self) -> int:
        return len(self.runs)

    def estimate(self, chosen: list[Box], stop: bool = True, **kw) -> MotionEstimate:
        p = self.p
        est = estimate_motion(*self.args, boxes=[c.as_tuple() for c in chosen],
                              base=self.base, lam=p.lam, refit_photometry=p.refit_photometry,
                              stop_occluded=p.max_occluded if stop else None, bands=p.bands,
                              t_grow=p.t_grow, blur_reach=self.blur_reach,
                              max_active=p.max_active, **kw)
        self.n_outer += int(est.info["n_outer"])
        self.runs.append((list(chosen), est))
        return est

    def best_index(self) -> int:
        """The run whose windows fit best: fewest rejected windows, then least change."""
        mo = self.p.max_occluded

        def key(k: int):
            occ = self.runs[k][1].info["occluded"]
            return (sum(o > mo for o in occ), float(np.mean(occ)))

        return min(range(len(self.runs)), key=key)

    def finish(self, est: MotionEstimate, fits: bool) -> MotionEstimate:
        """``est`` completed if it stopped early (from where it stopped, within
        ``unfit_outer`` iterations per level), with ``info["selection"]``."""
        p = self.p
        if est.info.get("stopped_early"):
            boxes = [Box(*b) for b in est.info["windows"]]
            # on the grid it stopped on (its first level may have widened the translations)
            reference, observed, _ = self.args
            first = est.info
            est = estimate_motion(reference, observed, est.grid,
                                  boxes=[b.as_tuple() for b in boxes],
                                  base=self.base, lam=p.lam,
                                  refit_photometry=p.refit_photometry,
                                  resume=est.info["resume"], max_outer=p.unfit_outer,
                                  rtol=p.unfit_rtol, bands=p.bands, max_active=p.max_active)
            self.n_outer += int(est.info["n_outer"])
            est.info["translations"] = dict(first["translations"],
                                            edge_share=est.info["translations"]["edge_share"])
            est.info["capped"] = int(first.get("capped", 0)) + int(est.info.get("capped", 0))
        est.info.pop("resume", None)
        est.info["selection"] = dict(estimates=len(self.runs), n_outer=self.n_outer,
                                     fits=bool(fits), occluded=list(est.info["occluded"]),
                                     max_occluded=p.max_occluded, **self.extra)
        return est


def _occluded_fraction_one(chi: np.ndarray) -> float:
    nz = chi != 0
    return float((nz.any(axis=2) if nz.ndim == 3 else nz).mean())


def _occluded_fraction(est: MotionEstimate) -> float:
    n = sum(c.shape[0] * c.shape[1] for c in est.chi)
    occ = 0
    for c in est.chi:
        nz = c != 0
        occ += int((nz.any(axis=2) if nz.ndim == 3 else nz).sum())
    return occ / max(n, 1)


def _texture_term(sc: np.ndarray, smax: float, floor: float) -> np.ndarray:
    """Texture factor of the spread placement: 1 at or above ``floor * smax``, then
    ``sqrt`` of the relative score (a weak window must be much farther to be chosen)."""
    ref = max(float(floor) * float(smax), 1e-300)
    return np.sqrt(np.clip(sc / ref, 0.0, 1.0))


def _spread_partners(cells, cover, S, lat: _Lattice, first: Box, k: int, shape,
                     floor: float = 0.2) -> list[Box]:
    """``k`` more windows of the same size, far from ``first`` and from each other.

    Rotation about the principal point is only observable from windows far apart, so each
    next window maximises (texture factor, :func:`_texture_term`) x (distance to the nearest
    chosen window).
    """
    if k <= 0:
        return []
    sc = _window_scores(cells, S)
    cv = _window_scores(cover.astype(float), S)
    if sc.size == 0:
        return []
    valid = (cv >= 1.0 - 1e-9) & (sc > 0)
    chosen = [first]
    out = []
    diag = float(np.hypot(*shape))
    cyy, cxx = lat.centres(sc.shape, S)
    smax = sc[valid].max() if valid.any() else 1.0
    for _ in range(k):
        dmin = np.full(sc.shape, np.inf)
        for c in chosen:
            d = np.hypot(cyy - (c.y0 + c.h / 2), cxx - (c.x0 + c.w / 2))
            dmin = np.minimum(dmin, d)
        # windows may not overlap the chosen ones
        ok = valid & (dmin >= S * lat.unit * 1.0)
        if not ok.any():
            break
        obj = np.where(ok, _texture_term(sc, smax, floor) * (dmin / diag), -np.inf)
        iy, ix = np.unravel_index(int(np.argmax(obj)), obj.shape)
        b = lat.box(iy, ix, S)
        chosen.append(b)
        out.append(b)
    return out
