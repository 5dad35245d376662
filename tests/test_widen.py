"""Pose grids whose translations widen where the blur reaches beyond them (issue #28).

The paper's grid holds translations of at most 12 px; real hand-held shake goes further
(GoPro 0374 puts 62 % of its weight on that grid's edge).  The pairs here are blurred by
integer shifts of a larger texture, so the true weights are known exactly: two poses of
0.5, beyond the grid given to the estimate.
"""

import dataclasses

import cv2
import numpy as np
import pytest

from reblur import PoseGrid, estimate_motion
from reblur.estimate import MIN_WIDEN_GAIN, T_EDGE_SHARE
from reblur.grid import edge_share, widen_translations

M = 20  # margin of the texture around the reference
TRUE = {(5.0, 0.0): 0.5, (-4.0, 3.0): 0.5}  # (tx, ty) -> weight


@pytest.fixture(scope="module")
def pair():
    rng = np.random.default_rng(3)
    big = cv2.GaussianBlur(rng.random((300, 300)).astype(np.float32), (0, 0), 1.5)
    big = ((big - big.min()) / (big.max() - big.min())).astype(np.float64)
    ref = big[M:-M, M:-M]
    H, W = ref.shape

    def shifted(tx, ty):  # a pose (tx, ty) maps reference pixel x to x + t
        return big[M - ty : M - ty + H, M - tx : M - tx + W]

    obs = sum(w * shifted(int(tx), int(ty)) for (tx, ty), w in TRUE.items())
    return ref, obs


def _by_translation(est) -> dict:
    """Weights summed over the bases, per (tx, ty) carrying more than 1 %."""
    w = est.weights.sum(axis=0)
    return {(est.grid.tx[j], est.grid.ty[i]): float(w[i, j])
            for i, j in np.argwhere(w > 0.01)}


def test_edge_share_against_a_loop_over_the_poses():
    g = PoseGrid((50, 50), tx=[-2, -1, 0, 1, 2], ty=[-1, 0, 1], rz=[-0.5, 0.0, 0.5])
    w = np.random.default_rng(0).random(g.shape)
    on_edge = sum(w[b, i, j] for b in range(3) for i in range(3) for j in range(5)
                  if abs(g.tx[j]) == 2 or abs(g.ty[i]) == 1)
    assert edge_share(w, g) == pytest.approx(on_edge / w.sum(), rel=1e-12)
    assert edge_share(np.zeros(g.shape), g) == 0.0
    # an axis of one value has no edge
    one = PoseGrid((50, 50), tx=[-1, 0, 1], ty=[0])
    w1 = np.array([[[0.0, 1.0, 0.0]]])
    assert edge_share(w1, one) == 0.0
    w1[0, 0, 2] = 1.0
    assert edge_share(w1, one) == 0.5


def test_widen_translations_keeps_the_step_and_the_other_axes():
    g = PoseGrid((50, 50), tx=[-1.5, 0.0, 1.5], ty=[-2, -1, 0, 1, 2], rz=[0.0, 0.3])
    w = widen_translations(g, 3)
    assert w.tx == (-4.5, -3.0, -1.5, 0.0, 1.5, 3.0, 4.5)
    assert w.ty == tuple(float(v) for v in range(-6, 7))
    assert (w.rz, w.center, w.image_shape) == (g.rz, g.center, g.image_shape)
    # an axis that is not a symmetric run of equal steps stays; none left: None
    odd = PoseGrid((50, 50), tx=[0, 1, 2], ty=[-1, 0, 1])
    assert widen_translations(odd).tx == (0.0, 1.0, 2.0)
    assert widen_translations(odd).ty == (-2.0, -1.0, 0.0, 1.0, 2.0)
    assert widen_translations(PoseGrid((50, 50), tx=[0, 1, 2], ty=[0])) is None
    with pytest.raises(ValueError, match="factor"):
        widen_translations(g, 1)


@pytest.mark.parametrize("rolls", [1, 21], ids=["translations", "coarse-to-fine"])
def test_a_blur_beyond_the_grid_widens_it_until_it_fits(pair, rolls):
    ref, obs = pair
    grid = PoseGrid(ref.shape, tx=range(-2, 3), ty=range(-2, 3),
                    rz=np.linspace(-0.5, 0.5, rolls) if rolls > 1 else [0.0])
    kw = dict(boxes=[(30, 30, 200, 200)], occlusion=False, lam=1e-4)
    narrow = estimate_motion(ref, obs, grid, **kw)
    assert narrow.grid is grid
    assert narrow.info["translations"]["edge_share"] >= T_EDGE_SHARE
    wide = estimate_motion(ref, obs, grid, t_grow=4, **kw)
    tr = wide.info["translations"]
    # 2 -> 4 (5 px still beyond) -> 8 px, then nothing on the edge
    assert (tr["t_max_start"], tr["t_max"]) == (2.0, 8.0)
    checks = tr["checks"]
    assert [c["outcome"] for c in checks] == ["widened", "widened", "clear"]
    assert [c["t_max"] for c in checks] == [2.0, 4.0, 8.0]
    assert checks[0]["edge_share"] == 1.0 and checks[-1]["edge_share"] < T_EDGE_SHARE
    assert all(c["gain"] >= MIN_WIDEN_GAIN for c in checks[:2])
    assert wide.grid.tx == tuple(float(v) for v in range(-8, 9))
    assert wide.grid.rz == grid.rz
    got = _by_translation(wide)
    assert got.keys() == TRUE.keys()
    for t, v in TRUE.items():
        assert got[t] == pytest.approx(v, abs=1e-3)
    assert wide.info["psnr"][0] > narrow.info["psnr"][0] + 40


def test_the_widening_stops_at_t_grow_and_at_a_quarter_of_the_window(pair):
    ref, obs = pair
    grid = PoseGrid(ref.shape, tx=range(-2, 3), ty=range(-2, 3))
    kw = dict(occlusion=False, lam=1e-4)
    est = estimate_motion(ref, obs, grid, boxes=[(30, 30, 200, 200)], t_grow=2, **kw)
    tr = est.info["translations"]
    assert tr["t_max"] == 4.0  # 8 would exceed 2x the grid's 2
    assert tr["checks"][-1]["outcome"] == "limit"
    assert tr["edge_share"] >= T_EDGE_SHARE  # still beyond
    # a 24 px window: a quarter is 6 px, so 4 but not 8
    est = estimate_motion(ref, obs, grid, boxes=[(100, 100, 24, 24)], t_grow=8, **kw)
    assert est.info["translations"]["t_max"] == 4.0
    assert est.info["translations"]["checks"][-1]["outcome"] == "limit"


def test_weight_on_the_edge_that_belongs_there_keeps_the_grid():
    """A blur whose poses lie on the grid's edge: the wider grid fits no better (the
    check's gain is the loss per valid pixel), so the grid is kept."""
    rng = np.random.default_rng(4)
    big = cv2.GaussianBlur(rng.random((300, 300)).astype(np.float32), (0, 0), 1.5)
    big = ((big - big.min()) / (big.max() - big.min())).astype(np.float64)
    ref = big[M:-M, M:-M]
    H, W = ref.shape
    obs = 0.5 * big[M : M + H, M - 2 : M - 2 + W] + 0.5 * big[M : M + H, M + 1 : M + 1 + W]
    grid = PoseGrid(ref.shape, tx=range(-2, 3), ty=range(-2, 3))
    est = estimate_motion(ref, obs, grid, boxes=[(30, 30, 200, 200)], occlusion=False,
                          lam=1e-4, t_grow=4)
    assert est.grid is grid
    (check,) = est.info["translations"]["checks"]
    assert check["edge_share"] == pytest.approx(0.5, abs=1e-3)
    assert check["outcome"] == "no gain" and check["gain"] < MIN_WIDEN_GAIN
    got = _by_translation(est)
    assert got.keys() == {(2.0, 0.0), (-1.0, 0.0)}
    assert all(v == pytest.approx(0.5, abs=1e-3) for v in got.values())


def test_a_blur_inside_the_grid_leaves_it_as_it_is(pair):
    ref, obs = pair
    grid = PoseGrid(ref.shape, tx=range(-6, 7), ty=range(-6, 7))
    kw = dict(boxes=[(30, 30, 200, 200)], occlusion=False, lam=1e-4)
    est = estimate_motion(ref, obs, grid, t_grow=4, **kw)
    assert est.grid is grid
    assert est.info["translations"]["checks"] == [
        dict(t_max=6.0, edge_share=0.0, outcome="clear")]
    np.testing.assert_array_equal(est.weights, estimate_motion(ref, obs, grid, **kw).weights)


def test_an_estimate_stopped_early_resumes_on_its_widened_grid(pair):
    """The paper's rejection stops after the first level (here forced: any change term
    at all); the selection then finishes the estimate on the grid it stopped on."""
    ref, obs = pair
    grid = PoseGrid(ref.shape, tx=range(-2, 3), ty=range(-2, 3), rz=np.linspace(-0.5, 0.5, 21))
    kw = dict(boxes=[(30, 30, 200, 200)], lam=1e-4)
    first = estimate_motion(ref, obs, grid, t_grow=4, stop_occluded=-1.0, **kw)
    assert first.info["stopped_early"]
    assert first.grid.tx == tuple(float(v) for v in range(-8, 9))
    done = estimate_motion(ref, obs, first.grid, resume=first.info["resume"], **kw)
    assert done.grid is first.grid
    got = _by_translation(done)
    assert got.keys() == TRUE.keys()
    for t, v in TRUE.items():
        assert got[t] == pytest.approx(v, abs=1e-3)


def test_t_grow_is_validated(pair):
    ref, obs = pair
    grid = PoseGrid(ref.shape, tx=range(-2, 3), ty=range(-2, 3))
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="t_grow"):
            estimate_motion(ref, obs, grid, boxes=[(30, 30, 200, 200)], t_grow=bad)
    from reblur.select import SelectParams

    with pytest.raises(ValueError, match="t_grow"):
        dataclasses.replace(SelectParams(), t_grow=0)


def test_the_pipeline_widens_its_default_grid_but_not_a_given_one(pair):
    """``detect_changes`` builds its grid from ``t_max`` and lets the estimate widen it
    (``SelectParams.t_grow``); a grid the caller gives stays as it is, and the report says
    the blur reaches beyond it."""
    from reblur import detect_changes
    from reblur.report import model_notes

    ref, obs = pair
    kw = dict(align=False, refine=False, local_field=False, rz_max=0.5)
    wide = detect_changes(ref, obs, t_max=2, **kw)
    assert wide.motion.info["translations"]["t_max"] == 8.0
    assert max(wide.motion.grid.tx) == 8.0
    got = _by_translation(wide.motion)
    assert got.keys() == TRUE.keys()
    for t, v in TRUE.items():
        # 0.506 / 0.494 and 8.4 % flagged while a photometric refit's warm start, every
        # pixel an outlier, stalled (solve._unbounded)
        assert got[t] == pytest.approx(v, abs=2e-3)
    assert not wide.change.any()  # nothing changed
    assert not any("beyond the pose grid" in n for n in model_notes(wide))
    given = PoseGrid(ref.shape, tx=range(-2, 3), ty=range(-2, 3))
    kept = detect_changes(ref, obs, grid=given, **kw)
    assert kept.motion.grid == given
    assert kept.motion.info["translations"]["edge_share"] >= T_EDGE_SHARE
    assert any("beyond the pose grid's translations (+-2 px)" in n for n in model_notes(kept))


@pytest.mark.parametrize("outcome, noted", [("limit", True), (None, True), ("reach", True),
                                            ("no gain", False), ("clear", False)])
def test_the_report_notes_a_blur_beyond_the_grid_only_when_it_could_not_widen(outcome,
                                                                              noted):
    from types import SimpleNamespace

    from reblur.report import model_notes

    checks = [] if outcome is None else [dict(t_max=24.0, edge_share=0.3, outcome=outcome)]
    tr = dict(t_max_start=12.0, t_max=24.0 if checks else 12.0, checks=checks,
              edge_share=0.3)
    result = SimpleNamespace(motion=SimpleNamespace(info=dict(translations=tr)), decision={})
    notes = [n for n in model_notes(result) if "beyond the pose grid" in n]
    assert bool(notes) == noted
    if noted and checks:
        assert "(+-24 px, widened from 12 px): 30% of the weight" in notes[0]


@pytest.mark.parametrize("method, sigma", [("features+ecc+kernel", 16.0),
                                           ("features+ecc+gradient", 3.0)])
def test_the_pre_match_low_passes_over_a_shake_the_kernel_polish_verified(pair, monkeypatch,
                                                                         method, sigma):
    """The photometric pre-match smooths over the larger of ``t_max`` and the alignment's
    shake extent, but only an extent its kernel polish verified: one reached without it
    (content that fits no blur, e.g. years apart) says nothing of the blur."""
    import reblur.pipeline as pl
    from reblur import detect_changes

    class Aligned:  # what align_coarse returns, reduced to what the stage reads
        H = np.eye(3)

        def to_dict(self):
            return {"method": method, "shake_px": 32.0}

    seen = []
    prefit = pl.photometric_prefit

    def spy(*args, sigma_px, **kw):
        seen.append(sigma_px)
        return prefit(*args, sigma_px=sigma_px, **kw)

    monkeypatch.setattr(pl, "align_coarse", lambda *a, **k: Aligned())
    monkeypatch.setattr(pl, "photometric_prefit", spy)
    ref, obs = pair
    detect_changes(ref, obs, refine=False, local_field=False, rz_max=0.5, t_max=6)
    assert seen == [sigma]


def test_the_fista_cross_check_still_runs_through_estimate_motion():
    """``solver="fista"`` (no outer iterations to count, never widened) still estimates:
    half the weight at ``tx = 0`` and half at ``tx = 1``, as the blur was made."""
    rng = np.random.default_rng(0)
    f = rng.random((96, 96))
    g = (f + np.roll(f, 1, axis=1)) / 2
    grid = PoseGrid((96, 96), tx=range(-2, 3), ty=range(-2, 3))
    est = estimate_motion(f, g, grid, boxes=[(8, 8, 80, 80)], solver="fista", occlusion=False,
                          lam=1e-4, fista_iter=2000, t_grow=4)
    assert est.grid is grid and est.info["translations"]["checks"] == []
    np.testing.assert_allclose(est.weights[0, 2, 2:4], [0.5, 0.5], atol=0.02)
    assert est.weights.sum() - est.weights[0, 2, 2:4].sum() < 0.02


def _checks(est) -> list[tuple]:
    return [(c["t_max"], c["outcome"]) for c in est.info["translations"]["checks"]]


@pytest.mark.parametrize("rolls", [1, 21], ids=["translations", "coarse-to-fine"])
def test_a_known_reach_starts_the_translations_wider(pair, rolls):
    """A blur known to reach beyond 3 px (the alignment's kernel polish failed there): the
    +-2 px grid, which would only be a misfit, is not solved; the estimate starts on +-4
    px, where the check finds the 5 px pose on the edge and widens to 8 px as before, with
    the same weights."""
    ref, obs = pair
    grid = PoseGrid(ref.shape, tx=range(-2, 3), ty=range(-2, 3),
                    rz=np.linspace(-0.5, 0.5, rolls) if rolls > 1 else [0.0])
    kw = dict(boxes=[(30, 30, 200, 200)], occlusion=False, lam=1e-4, t_grow=4)
    est = estimate_motion(ref, obs, grid, blur_reach=3.0, **kw)
    assert _checks(est) == [(2.0, "reach"), (4.0, "widened"), (8.0, "clear")]
    tr = est.info["translations"]
    assert (tr["t_max_start"], tr["t_max"], tr["blur_reach"]) == (2.0, 8.0, 3.0)
    assert est.grid.tx == tuple(float(v) for v in range(-8, 9))
    got = _by_translation(est)
    assert got.keys() == TRUE.keys()
    for t, v in TRUE.items():
        assert got[t] == pytest.approx(v, abs=1e-3)
    if rolls > 1:  # every level's solve on +-4 px or wider
        assert min(lv["t_max"] for lv in est.info["levels"]) == 4.0
        plain = estimate_motion(ref, obs, grid, **kw)
        assert min(lv["t_max"] for lv in plain.info["levels"]) == 2.0
        assert len(est.info["levels"]) == len(plain.info["levels"]) - 1


def test_a_known_reach_keeps_the_limits_of_the_widening(pair):
    """The start counts against ``t_grow``: a reach of 100 px on a +-2 px grid with
    ``t_grow=4`` starts at 8 px and no check widens further; ``t_grow=1`` keeps the grid;
    a resumed estimate stays on the grid it resumes."""
    ref, obs = pair
    grid = PoseGrid(ref.shape, tx=range(-2, 3), ty=range(-2, 3))
    kw = dict(boxes=[(30, 30, 200, 200)], occlusion=False, lam=1e-4)
    far = estimate_motion(ref, obs, grid, t_grow=4, blur_reach=100.0, **kw)
    assert _checks(far) == [(2.0, "reach"), (4.0, "reach")]
    assert far.info["translations"]["t_max"] == 8.0
    # t_grow=2: one doubling, then the checks have nothing left
    two = estimate_motion(ref, obs, grid, t_grow=2, blur_reach=100.0, **kw)
    assert _checks(two) == [(2.0, "reach")] and two.info["translations"]["t_max"] == 4.0
    kept = estimate_motion(ref, obs, grid, t_grow=1, blur_reach=100.0, **kw)
    assert kept.grid is grid and _checks(kept) == []
    # a reach the grid holds changes nothing
    inside = estimate_motion(ref, obs, grid, t_grow=4, blur_reach=2.0, **kw)
    assert _checks(inside)[0] == (2.0, "widened")
    rolled = PoseGrid(ref.shape, tx=range(-2, 3), ty=range(-2, 3), rz=np.linspace(-0.5, 0.5, 21))
    first = estimate_motion(ref, obs, rolled, t_grow=4, blur_reach=3.0, stop_occluded=-1.0,
                            boxes=[(30, 30, 200, 200)], lam=1e-4)
    assert first.info["stopped_early"]
    done = estimate_motion(ref, obs, first.grid, resume=first.info["resume"], t_grow=4,
                           blur_reach=100.0, boxes=[(30, 30, 200, 200)], lam=1e-4)
    assert done.grid is first.grid
    for bad in (-1.0, np.nan, np.inf, "3", True):
        with pytest.raises(ValueError, match="blur_reach"):
            estimate_motion(ref, obs, grid, t_grow=4, blur_reach=bad, **kw)


@pytest.mark.parametrize("info, reach", [
    ({"method": "phase+ecc+kernel", "shake_px": 32.0,
      "extents": [{"shake_px": 8.0, "refused": "..."}, {"shake_px": 16.0, "refused": "..."},
                  {"shake_px": 32.0, "method": "phase+ecc+kernel"}]}, 16.0),
    ({"method": "features+ecc+kernel", "shake_px": 16.0,
      "extents": [{"shake_px": 8.0, "method": "features+ecc+gradient"},
                  {"shake_px": 16.0, "method": "features+ecc+kernel"}]}, 8.0),
    ({"method": "features+ecc+kernel", "shake_px": 8.0,
      "extents": [{"shake_px": 8.0, "method": "features+ecc+kernel"}]}, 0.0),
    # reached by content that fits no blur (a reserve without a kernel stage)
    ({"method": "features+ecc+gradient", "shake_px": 32.0,
      "extents": [{"shake_px": 8.0}, {"shake_px": 16.0}, {"shake_px": 32.0}]}, 0.0),
    ({"method": "features+ecc+kernel", "shake_px": 16.0}, 0.0),  # no ladder recorded
    ({"method": "none"}, 0.0),
])
def test_the_blur_reach_is_the_extent_below_the_one_the_kernel_polish_verified(info, reach):
    from reblur.pipeline import blur_reach

    assert blur_reach(info) == reach


def test_the_pipeline_starts_from_the_reach_the_alignment_found(pair, monkeypatch):
    """``detect_changes`` hands the alignment's :func:`~reblur.pipeline.blur_reach` to the
    estimate: kernels of 3 px did not verify, 6 px ones did, so the +-2 px grid starts at
    4 px."""
    import reblur.pipeline as pl
    from reblur import detect_changes

    class Aligned:  # what align_coarse returns, reduced to what the stage reads
        H = np.eye(3)

        def to_dict(self):
            return {"method": "features+ecc+kernel", "shake_px": 6.0,
                    "extents": [{"shake_px": 3.0, "refused": "..."},
                                {"shake_px": 6.0, "method": "features+ecc+kernel"}]}

    monkeypatch.setattr(pl, "align_coarse", lambda *a, **k: Aligned())
    ref, obs = pair
    res = detect_changes(ref, obs, refine=False, local_field=False, rz_max=0.5, t_max=2)
    checks = res.motion.info["translations"]["checks"]
    assert checks[0] == dict(t_max=2.0, outcome="reach")
    assert res.motion.info["translations"]["t_max"] == 8.0
    got = _by_translation(res.motion)
    assert got.keys() == TRUE.keys()
