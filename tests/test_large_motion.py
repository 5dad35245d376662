"""Issue: motion that stays right across a large image (grid sized to it, spread windows).

A >= 40 MP scene made of real imagery (six LEVIR/WHU images, upsampled x2.1, mosaicked) is
computed window by window, never whole; the observation is its blur along a smooth camera
path with 0.3 deg of roll about the FULL image centre (not on any grid), also window by window.
"""

import numpy as np
import pytest
from conftest import levir_pairs, load_rgb

from reblur import PoseGrid, estimate_motion
from reblur.simulate import MosaicScene, blur_along_path, random_camera_path
from reblur.tiled import SparsePoses, reblur_tile

S, MARGIN = 500, 300


class Observed:
    def __init__(self, scene, path):
        self.scene, self.path = scene, path
        self.shape, self.dtype = scene.shape, np.dtype(np.float32)

    def window(self, box):
        g, v = blur_along_path(self.scene, self.path, box, dtype=np.float32)
        return g.reshape(box[2], box[3]), v

    def __getitem__(self, key):
        ys, xs = key
        return self.window((ys.start, xs.start, ys.stop - ys.start, xs.stop - xs.start))[0]


@pytest.fixture(scope="module")
def big_pair():
    ims = [load_rgb(a).mean(axis=2) for a, _, _ in levir_pairs()]
    scene = MosaicScene(ims, 2150, 3, 3, rng=0)
    H, W = scene.shape
    assert H * W >= 40e6
    path = random_camera_path(5, center=((W - 1) / 2, (H - 1) / 2), t_max=9.0, rz_max=0.3)
    assert abs(path.extent()["rz"] - 0.3) < 1e-9
    return scene, Observed(scene, path)


def _unseen_psnr(scene, obs, est):
    H, W = scene.shape
    boxes = [(H - MARGIN - S, W // 2 - S // 2, S, S), (MARGIN, W // 2 - S // 2, S, S),
             (H // 2 - S // 2, MARGIN, S, S)]
    poses = SparsePoses(est.weights, est.grid)
    out = []
    for b in boxes:
        gt, v = obs.window(b)
        img, ok = reblur_tile(poses, scene, b)
        d = (img[:, :, 0] - gt)[ok & v]
        out.append(10 * np.log10(1.0 / np.mean(d * d)))
    return np.array(out)


def test_spread_windows_and_sized_grid_beat_the_paper_setup(big_pair):
    scene, obs = big_pair
    H, W = scene.shape
    lo, hy, hx = MARGIN, H - MARGIN - S, W - MARGIN - S
    four = [(lo, lo, S, S), (hy, hx, S, S), (lo, hx, S, S), (hy, lo, S, S)]
    fine = PoseGrid.from_ranges((H, W), corner_px=1.0)
    # one roll step moves the farthest pixel by one pixel
    assert np.deg2rad(fine.rz[1] - fine.rz[0]) * fine.radius == pytest.approx(1.0, rel=1e-6)
    est = estimate_motion(scene, obs, fine, boxes=four)
    good = _unseen_psnr(scene, obs, est)
    assert good.min() >= 50.0, good
    central = [(H // 2 - S // 2, W // 2 - S // 2, S, S)]
    paper = estimate_motion(scene, obs, PoseGrid.paper((H, W)), boxes=central)
    bad = _unseen_psnr(scene, obs, paper)
    # the paper's single central window fits its own window well but not the far ones
    assert paper.info["psnr"][0] > 45.0
    assert bad.max() < good.min() - 10.0, (bad, good)


def _write_tiles(path, shape, tile_fn, tile=1024):
    import tifffile

    H, W = shape

    def tiles():
        for y in range(0, H, tile):
            for x in range(0, W, tile):
                a = tile_fn((y, x, min(tile, H - y), min(tile, W - x)))
                yield np.clip(np.round(a * 255), 0, 255).astype(np.uint8)

    tifffile.imwrite(path, tiles(), shape=(H, W), dtype=np.uint8, tile=(tile, tile),
                     compression="zstd", bigtiff=True)


def test_outskirts_flagged_no_more_than_twice_the_centre(big_pair, tmp_path):
    """End to end on the 41.6 MP pair with 48 pasted changes and sensor noise (1/255), files
    read lazily, defaults: unchanged pixels are flagged in the outer quarter of the image at
    most twice as often as in the central quarter, and the changes are found everywhere.
    The paper's set-up (0.5 deg roll step, one window) fails the same criterion on the
    same data.  (Without noise the default fails it too: see docs/NOTES.md.)"""
    import tifffile
    import zarr

    import reblur

    scene, obs = big_pair
    H, W = scene.shape
    rng = np.random.default_rng(3)
    squares = [(int(rng.integers(100, H - 300)), int(rng.integers(100, W - 300)),
                int(rng.integers(80, 200)), 0.92 if k % 2 else 0.06) for k in range(48)]

    def observed(box):
        y, x, h, w = box
        a = obs.window(box)[0]
        a = a + np.random.default_rng([7, y, x]).normal(0.0, 1.0 / 255, a.shape)
        for sy, sx, s, v in squares:
            ya, yb, xa, xb = max(sy, y), min(sy + s, y + h), max(sx, x), min(sx + s, x + w)
            if ya < yb and xa < xb:
                a[ya - y : yb - y, xa - x : xb - x] = v
        return a

    _write_tiles(tmp_path / "ref.tif", (H, W), lambda b: scene[b[0] : b[0] + b[2],
                                                              b[1] : b[1] + b[3]])
    _write_tiles(tmp_path / "obs.tif", (H, W), observed)
    ref = zarr.open(tifffile.imread(tmp_path / "ref.tif", aszarr=True), mode="r")
    ob = zarr.open(tifffile.imread(tmp_path / "obs.tif", aszarr=True), mode="r")

    pasted = np.zeros((H, W), bool)  # the squares, grown by the blur's reach
    core = np.zeros((H, W), bool)  # their interiors
    for sy, sx, s, _ in squares:
        pasted[max(sy - 40, 0) : sy + s + 40, max(sx - 40, 0) : sx + s + 40] = True
        core[sy + 8 : sy + s - 8, sx + 8 : sx + s - 8] = True
    yy, xx = np.ogrid[:H, :W]
    dy, dx = np.abs(yy - (H - 1) / 2) / H, np.abs(xx - (W - 1) / 2) / W
    centre = (dy < 0.25) & (dx < 0.25)  # central box, a quarter of the area
    side = np.sqrt(0.75) / 2
    outer = (dy >= side) | (dx >= side)  # outside a box of 3/4 of the area

    def rates(**kw):
        res = reblur.detect_changes(ref, ob, workers=2, keep_reblurred=False, **kw)
        unknown = np.asarray(res.unknown, bool)
        change = np.asarray(res.change, bool) & ~unknown
        still = ~pasted & ~unknown
        found = [change[core & region].mean() for region in (centre, outer)]
        return change[centre & still].mean(), change[outer & still].mean(), found

    fa_centre, fa_outer, found = rates()
    assert fa_outer <= 2 * fa_centre + 1e-4, (fa_outer, fa_centre)
    assert min(found) > 0.8, found
    # the paper's grid and single window: far more false alarms in the outskirts
    p_centre, p_outer, _ = rates(rz_step=0.5, windows=1)
    assert p_outer > 2 * p_centre + 1e-4, (p_outer, p_centre)
    assert p_outer > 10 * max(fa_outer, 1e-4)
