"""The tiled decision's work is bounded per tile, whatever the regions (issue #28).

Counts, never seconds: decisions per tile (:func:`reblur.tilejob.run_tile`'s
``attempts``), pixels decided per tile, and the labelling passes of one decision.  The
masks are checked against an independent reference: the decision of the whole image in one
call (:func:`reblur.decide.decide_tile` over every pixel, no tile edge), which the tiles
must equal wherever no region is larger than the re-runs' largest halo holds.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage as ndi

import reblur.decide.regions as regions
from reblur.decide import DecisionParams, Photometry, decide_tile, tile_boxes
from reblur.grid import PoseGrid
from reblur.tiled import SparsePoses
from reblur.tilejob import (
    _ATTEMPTS,
    TileJob,
    load_tile,
    max_region_extent,
    preload_tiles,
    run_tile,
)

SHAPE = (1024, 1536)
TILE = 256
THRESHOLD = 3.0


def _scene(n_small: int, big: bool, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference, observation and the changed mask: ``n_small`` false regions of 12-17 px on
    a lattice (many across the tile edges), and optionally one 420 x 460 px block."""
    rng = np.random.default_rng(seed)
    ref = ndi.gaussian_filter(rng.standard_normal(SHAPE), 6.0)
    ref = (0.5 + 0.1 * ref / ref.std()).astype(np.float32)
    change = np.zeros(SHAPE, bool)
    gy, gx = np.arange(3, SHAPE[0] - 20, 32), np.arange(3, SHAPE[1] - 20, 32)
    yy, xx = (a.ravel() for a in np.meshgrid(gy, gx, indexing="ij"))
    for k in rng.permutation(yy.size)[:n_small]:
        h, w = rng.integers(12, 18, 2)
        change[yy[k] : yy[k] + h, xx[k] : xx[k] + w] = True
    if big:
        change[300:720, 400:860] = True
    obs = ref + 0.25 * change + 0.01 * rng.standard_normal(SHAPE)
    return ref, obs.astype(np.float32), change


def _job(ref: np.ndarray, halo: int) -> tuple[TileJob, DecisionParams]:
    p = DecisionParams()
    grid = PoseGrid(SHAPE, tx=(0,), ty=(0,))
    poses = SparsePoses(np.ones(grid.shape), grid)
    ph = Photometry(gain=np.ones(1), offset=np.zeros(1), sigma=np.full(1, 0.01),
                    image_shape=SHAPE)
    job = TileJob(poses=poses, s_ref=1.0, s_obs=1.0, gain=np.ones(1, np.float32),
                  offset=np.zeros(1, np.float32), threshold=THRESHOLD, photometry=ph, params=p,
                  halo=halo, image_shape=SHAPE, two_d=True,
                  change_out=np.zeros(SHAPE, bool), unknown_out=np.zeros(SHAPE, bool))
    return job, p


def _tiled(ref, obs, halo):
    job, p = _job(ref, halo)
    results = [run_tile(job, ref, obs, padded, core)
               for padded, core in tile_boxes(SHAPE, TILE, halo)]
    return job.change_out, results, job


def _whole(job: TileJob, ref, obs) -> np.ndarray:
    """The reference: one decision over the whole image (no tile edge, nothing to grow)."""
    box = (0, 0, *SHAPE)
    o, r, u = load_tile(job.poses, ref, obs, box, s_ref=1.0, s_obs=1.0, gain=job.gain,
                        offset=job.offset)
    mask, info = decide_tile(o, r, u, threshold=THRESHOLD, photometry=job.photometry, box=box,
                             params=job.params, image_shape=SHAPE)
    assert info["complete"]
    return mask


@pytest.fixture(scope="module")
def many():
    ref, obs, change = _scene(1500, big=False, seed=1)
    return ref, obs, change


def test_tiles_equal_the_whole_image_with_thousands_of_regions(many):
    """Regions of 12-17 px, ~1500 of them, hundreds across tile edges: every tile completes
    (after at most one re-run) and the tiled mask is the whole-image one, pixel for pixel."""
    ref, obs, change = many
    p = DecisionParams()
    halo = p.halo(16)
    tiled, results, job = _tiled(ref, obs, halo)
    whole = _whole(job, ref, obs)
    n_regions = ndi.label(whole, structure=np.ones((3, 3)))[1]
    assert n_regions > 1000  # the false regions are there, not merged
    assert all(r["complete"] and r["oversize"] == 0 for r in results)
    assert max(r["attempts"] for r in results) == 2  # some regions do cross tile edges
    np.testing.assert_array_equal(tiled, whole)


def test_tiles_started_from_held_loads_equal_their_own(many):
    """:func:`preload_tiles`' loads (read-only) start the tiles: the mask, the re-runs and
    the pixels decided are those of tiles that load themselves (re-runs grow from the held
    arrays), each held tile is handed out once, and a window has the values of its own load
    (the identity pose: exact), as a view inside a held tile or pieced from two; none is
    served once the tiles are taken."""
    ref, obs, _ = many
    halo = DecisionParams().halo(16)
    tiled, results, _ = _tiled(ref, obs, halo)
    job, _ = _job(ref, halo)
    tiles = list(tile_boxes(SHAPE, TILE, halo))

    def load(box):
        return load_tile(job.poses, ref, obs, box, s_ref=1.0, s_obs=1.0, gain=job.gain,
                         offset=job.offset)

    assert preload_tiles(load, [t for t, _ in tiles], 1, max_bytes=2**20) is None
    held = preload_tiles(load, [t for t, _ in tiles], 1)
    assert len(held) == len(tiles)
    inside = (TILE + 10, 20, 100, 120)
    across = (100, TILE - halo - 10, 50, 2 * halo + 20)  # wider than two tiles' overlap
    cut, own = held.window(inside), load(inside)
    assert not cut[0].flags.writeable
    for a, b in zip(cut, own, strict=True):
        np.testing.assert_array_equal(a, b)
    pieced, own = held.window(across), load(across)
    assert pieced[0].flags.writeable  # a copy, pieced from two tiles
    for a, b in zip(pieced, own, strict=True):
        np.testing.assert_array_equal(a, b)
    started = [run_tile(job, ref, obs, padded, core, loaded=held.take(padded))
               for padded, core in tiles]
    assert len(held) == 0 and held.take(tiles[0][0]) is None and held.window(inside) is None
    np.testing.assert_array_equal(job.change_out, tiled)
    assert [(r["attempts"], r["pixels"]) for r in started] == \
        [(r["attempts"], r["pixels"]) for r in results]
    assert max(r["attempts"] for r in started) == 2  # re-runs grew from held arrays


def test_work_per_tile_does_not_grow_with_the_regions(many, monkeypatch):
    """Labelling passes and the pixels they cover, per decision: the same bound with a few
    and ~250 regions in the tile (no per-region pass over the tile)."""
    calls: list[int] = []
    real = regions._components

    def counted(mask, *a, **k):
        calls.append(int(np.asarray(mask).size))
        return real(mask, *a, **k)

    monkeypatch.setattr(regions, "_components", counted)
    p = DecisionParams()
    ph = Photometry(gain=np.ones(1), offset=np.zeros(1), sigma=np.full(1, 0.01),
                    image_shape=SHAPE)
    box = (0, 0, 512, 512)
    work = {}
    for n in (15, 1500):
        ref, obs, _ = _scene(n, big=False, seed=2) if n != 1500 else many
        calls.clear()
        mask, info = decide_tile(obs[:512, :512], ref[:512, :512], None, threshold=THRESHOLD,
                                 photometry=ph, box=box, params=p, image_shape=SHAPE)
        work[n] = (len(calls), sum(calls), info["counts"]["accepted"])
    (c_few, px_few, acc_few), (c_many, px_many, acc_many) = work[15], work[1500]
    assert acc_few <= 5 and acc_many >= 200
    bound = len(p.levels) + 6  # one labelling per level, the trim (2), closing, holes, records
    assert c_few <= bound and c_many <= bound
    assert max(px_few, px_many) <= bound * 512 * 512


def test_oversize_region_is_decided_without_growing_the_halo():
    """A 420 x 460 px block, larger than the last halo holds: tiles it covers decide it at
    once (one attempt), no tile exceeds the attempt schedule, the tiles decide at most 3x
    the pixels of their first try in total, and away from the block the mask is the
    whole-image one."""
    ref, obs, change = _scene(300, big=True, seed=3)
    p = DecisionParams()
    halo = p.halo(16)
    assert max_region_extent(halo, p.local_radius) < 420
    tiled, results, job = _tiled(ref, obs, halo)
    whole = _whole(job, ref, obs)
    first = sum(pb[2] * pb[3] for pb, _ in tile_boxes(SHAPE, TILE, halo))
    assert sum(r["pixels"] for r in results) <= 3 * first
    assert max(r["attempts"] for r in results) <= _ATTEMPTS
    centre = [r for r in results if r["core"][:2] == (2 * TILE, 2 * TILE)][0]
    assert centre["attempts"] == 1 and centre["oversize"] == 1 and not centre["complete"]
    # the block is found by the tiles
    block = np.zeros(SHAPE, bool)
    block[300:720, 400:860] = True
    assert np.count_nonzero(tiled & block) >= 0.97 * block.sum()
    # the tiles the block does not reach complete, and equal the whole-image decision
    done = [r["core"] for r in results if r["complete"]]
    assert len(done) >= 3
    for cy, cx, ch, cw in done:
        np.testing.assert_array_equal(tiled[cy : cy + ch, cx : cx + cw],
                                      whole[cy : cy + ch, cx : cx + cw])


def test_halo_grows_on_the_edges_regions_reach():
    """Two regions reaching up out of their tile's core by 212 px (more than four times the
    first halo, less than the largest halo holds): a bar, and an L whose arm turns left
    beyond the left halo only where the largest top halo sees it.  The bar's tile grows
    its top edge alone (h, 2h, 4h, then 8h) and completes there; the L's tile reaches the
    left edge on that try and completes on the largest window.  The padded pixels decided
    are counted from the schedule by hand; both tiles equal the whole-image decision."""
    p = DecisionParams()
    h = p.halo(16)
    # past the 4h halo's edge band, and no larger (530 - 300 px) than the largest halo holds
    assert 4 * h + p.local_radius < 512 - 300
    assert 530 - 300 <= max_region_extent(h, p.local_radius)
    ref, obs, _ = _scene(0, big=False, seed=4)
    shapes = np.zeros(SHAPE, bool)
    shapes[300:530, 600:624] = True  # the bar, in the core (512, 512)
    shapes[300:530, 1112:1136] = True  # the L's stem, in the core (512, 1024) ...
    shapes[300:324, 962:1136] = True  # ... and its arm, left of the core beyond h
    obs = obs + 0.25 * shapes.astype(np.float32)
    tiled, results, job = _tiled(ref, obs, h)
    whole = _whole(job, ref, obs)
    by_core = {r["core"][:2]: r for r in results}
    side = TILE + 2 * h  # every padded tile here is 256 + 2h wide before it grows
    heights = [TILE + 2 * h, TILE + 3 * h, TILE + 5 * h, TILE + 9 * h]  # the top edge grows
    bar = by_core[(512, 512)]
    assert bar["complete"] and bar["attempts"] == 4
    assert bar["pixels"] == side * sum(heights)
    ell = by_core[(512, 1024)]
    assert ell["complete"] and ell["attempts"] == 5
    # the largest window, clipped at the image's bottom and right borders
    largest = ((min(768 + 8 * h, SHAPE[0]) - (512 - 8 * h))
               * (min(1280 + 8 * h, SHAPE[1]) - (1024 - 8 * h)))
    assert ell["pixels"] == side * sum(heights) + largest
    assert all(r["complete"] for r in results)
    np.testing.assert_array_equal(tiled, whole)
