"""Bounds of the realism issue on small pairs of the independent test bed (reblur.testbed):
blur reblur did not make (a continuous 6-D camera path over 64 sub-poses, bicubic
interpolation, a perspective viewpoint change, a Poisson-Gaussian sensor).

Each bound is checked against the test bed's own ground truth: its change objects'
half-maximum footprint and, for the geometry, the true blur-kernel centroid
(:func:`reblur.testbed.true_centroid`).  ``benchmarks/realism.py`` runs the full matrix
(up to 100 MP) with the register-and-difference baseline beside it.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage as ndi

import reblur
from reblur import testbed as tb

pytestmark = pytest.mark.slow

#: the bounds of the issue
MAX_FAR = 0.001  # false alarms on unchanged pixels
MIN_RECALL = 0.9  # pasted changes of 10-40 % of their surroundings' range
MAX_GEOMETRY_RMS, MAX_GEOMETRY_MAX = 0.3, 0.6  # px


def _scene(name):
    try:
        return tb.levir_image(name) if name.startswith("test") else tb.whu_image(name)
    except FileNotFoundError:
        pytest.skip("../shared/data is absent")


def _run(name, bits, noise, n_changes, seed):
    scene = _scene(name)
    pair = tb.make_pair(scene, bits=bits, noise_dn=noise, n_changes=n_changes, seed=seed,
                        motion=tb.shake_for(scene.shape), viewpoint={"shift_px": 20.0})
    res = reblur.detect_changes(pair.reference, pair.observed)
    return pair, res


def _scores(pair, res):
    known = pair.valid & ~res.unknown
    near = ndi.binary_dilation(pair.truth, iterations=3)  # a blurred change's boundary
    neg = known & ~near
    pos = known & pair.truth
    far = np.count_nonzero(res.change & neg) / np.count_nonzero(neg)
    recall = np.count_nonzero(res.change & pos) / max(np.count_nonzero(pos), 1)
    return far, recall


def _geometry(pair, res):
    H, W = pair.valid.shape
    ys, xs = np.meshgrid(np.linspace(0.05 * H, 0.95 * H, 9), np.linspace(0.05 * W, 0.95 * W, 9),
                         indexing="ij")
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1)
    known = pair.valid & ~res.unknown
    pts = pts[known[pts[:, 1].astype(int), pts[:, 0].astype(int)]]
    err = np.hypot(*(res.motion.source_points(pts, res.alignment)
                     - tb.true_centroid(pair.homographies, pts)).T)
    return float(np.sqrt(np.mean(err ** 2))), float(err.max())


# (scene, bits, noise DN, pasted changes, seed): clean 16-bit without change on a rural
# and an urban scene (the flood cases), noisy 8-bit and clean 16-bit with changes
CASES = [("test_7", 16, 0.0, 0, 0), ("000121", 16, 0.0, 0, 0), ("test_7", 8, 2.0, 8, 0),
         ("000121", 16, 0.5, 8, 1)]


@pytest.fixture(scope="module", params=CASES, ids=lambda c: f"{c[0]}-{c[1]}bit-{c[2]}dn-{c[3]}")
def case(request):
    return request.param, *_run(*request.param)


def test_false_alarms_at_most_a_tenth_of_a_percent(case):
    _, pair, res = case
    far, _ = _scores(pair, res)
    assert far <= MAX_FAR, far


def test_pasted_changes_are_found(case):
    (name, bits, noise, n, seed), pair, res = case
    if n == 0:
        assert not pair.truth.any()
        return
    _, recall = _scores(pair, res)
    assert recall >= MIN_RECALL, recall


def test_geometry_to_a_fraction_of_a_pixel(case):
    _, pair, res = case
    rms, worst = _geometry(pair, res)
    assert rms <= MAX_GEOMETRY_RMS and worst <= MAX_GEOMETRY_MAX, (rms, worst)


def test_weights_are_fractions_of_the_exposure(case):
    """The photometric gain has one home: the weights sum to 1, the gain they carried is
    recorded."""
    _, _, res = case
    assert res.motion.weights.sum() == pytest.approx(1.0, abs=1e-9)
    assert res.motion.info["weight_sum"] > 0


def test_the_tolerance_is_measured_and_reported(case):
    _, _, res = case
    cal = res.decision["calibration"]
    assert cal["calibrated"] and cal["n"] >= 50_000
    # the chosen rung is the first of the ladder that meets the target (or the last): the
    # rungs evaluated, in ladder order, meet it from that one on, and the one before it was
    # evaluated and failed
    ladder = [list(r) for r in reblur.decide.DecisionParams().tolerance_ladder]
    idx = [ladder.index(t[:2]) for t in cal["tried"]]
    assert idx == sorted(set(idx))
    meets = {i: t[2] <= cal["target"] for i, t in zip(idx, cal["tried"], strict=True)}
    if cal["met"]:  # the margin's rungs beyond the first that meets the target
        first = ladder.index(cal["first_met"])
        assert first == 0 or meets[first - 1] is False
        assert all(m == (i >= first) for i, m in meets.items())
        want = ladder[min(first + cal["margin"], len(ladder) - 1)]
    else:
        assert not any(meets.values()) and len(ladder) - 1 in meets
        want = ladder[-1]
    assert [cal["shift"], cal["contrast"]] == want


def test_identical_inputs_flag_nothing():
    """Observation = reference, byte for byte: no change, nothing unknown."""
    scene = _scene("test_7")
    a = np.round(scene * 255).astype(np.uint8)
    res = reblur.detect_changes(a, a.copy())
    assert not res.change.any(), res.change.mean()
    assert not res.unknown.any()
