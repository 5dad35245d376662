"""Issue: motion that stays right across a large image (grid sized to it, spread windows).

A >= 40 MP scene made of real imagery (six LEVIR/WHU images, upsampled x2.1, mosaicked) is
computed window by window, never whole; the observation is its blur along a smooth camera
path with 0.3 deg of roll about the FULL image centre (not on any grid), also window by window.
"""

import numpy as np
import pytest
from conftest import levir_pairs, load_rgb

from reblur import PoseGrid, estimate_motion
from reblur.simulate import MosaicScene, PathBlurredScene, random_camera_path
from reblur.tiled import SparsePoses, reblur_tile

S, MARGIN = 500, 300


@pytest.fixture(scope="module")
def big_pair():
    ims = [load_rgb(a).mean(axis=2) for a, _, _ in levir_pairs()]
    scene = MosaicScene(ims, 2150, 3, 3, rng=0)
    H, W = scene.shape
    assert H * W >= 40e6
    path = random_camera_path(5, center=((W - 1) / 2, (H - 1) / 2), t_max=9.0, rz_max=0.3)
    assert abs(path.extent()["rz"] - 0.3) < 1e-9
    return scene, PathBlurredScene(scene, path)


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
    """Four windows of the size the pipeline picks for four (400 px), centred where the
    issue's 500 px corner windows are, against the paper's single central 500 px window."""
    from reblur.select import SelectParams, spread_side

    scene, obs = big_pair
    H, W = scene.shape
    p = SelectParams(windows=4)
    s = spread_side(p) * p.unit
    assert 4 * s * s <= p.spread_pixels
    lo, hy, hx = MARGIN, H - MARGIN - S, W - MARGIN - S
    d = (S - s) // 2
    four = [(y + d, x + d, s, s) for y, x in ((lo, lo), (hy, hx), (lo, hx), (hy, lo))]
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



def test_outskirts_flagged_no_more_than_twice_the_centre(big_pair, tmp_path):
    """End to end on the 41.6 MP pair with 48 pasted changes and sensor noise (1/255), files
    read lazily, defaults: unchanged pixels are flagged in the outer quarter of the image at
    most twice as often as in the central quarter, and the changes are found everywhere.
    The paper's set-up (0.5 deg roll step, one window) fails the same criterion on the
    same data.  (Without noise the default fails it too: ``python -m benchmarks.outskirts``,
    docs/NOTES.md.)"""
    import sys

    from conftest import REPO

    if str(REPO) not in sys.path:  # the benchmarks live beside src/, not in the package
        sys.path.insert(0, str(REPO))
    from benchmarks.outskirts import paste_squares, run, write_pair

    scene, obs = big_pair
    H, W = scene.shape
    squares = paste_squares(H, W)
    ref_p, obs_p = write_pair(tmp_path, scene, lambda b: obs.window(b)[0], squares, 1.0 / 255)

    r = run(ref_p, obs_p, squares)
    assert r["fa_outer"] <= 2 * r["fa_centre"] + 1e-4, r
    assert min(r["found_centre"], r["found_outer"]) > 0.8, r
    # the paper's grid and single window: far more false alarms in the outskirts
    p = run(ref_p, obs_p, squares, rz_step=0.5, windows=1)
    assert p["fa_outer"] > 2 * p["fa_centre"] + 1e-4, p
    assert p["fa_outer"] > 10 * max(r["fa_outer"], 1e-4), (p, r)
