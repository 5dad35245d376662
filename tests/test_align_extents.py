"""The shake extents :func:`reblur.pipeline.align_coarse` tries (issue #28).

A polish whose regions fail because the CONTENT differs (the blur model explains little
of their texture) stops the search for a larger extent; a polish whose kernels spread
(a blur larger than the extent) does not.  The counts are of extents and polishes run,
never of seconds.  Real imagery: LEVIR-CD test_102 "before" / "after" (years apart), test_7 and
WHU-CD 000121, shaken as in ``tests/test_align.py``.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from conftest import DATA, LEVIR, WHU, load_rgb
from test_align import _observe, _read

from reblur.align import AlignParams, coarse_align_shakes
from reblur.align import coarse as coarse_mod
from reblur.align import polish as polish_mod
from reblur.align.overviews import pyramid
from reblur.align.polish import blur_exceeds, content_misfit, kernel_polish, polish_and_verify
from reblur.grid import map_points, pose_homography
from reblur.pipeline import align_coarse

SIZE = 1024
CENTER = ((SIZE - 1) / 2.0, (SIZE - 1) / 2.0)
SHAKES = (8.0, 16.0, 32.0, 64.0)


def _shaken(scene: np.ndarray, seed: int, shake: float, n: int = 30):
    """``scene`` seen from another viewpoint (up to 3 % and 3 degrees) and blurred along a
    smooth path of up to +-``shake`` px and +-1 degree; returns ``(observation, true
    homography of the mean pose)``."""
    rng = np.random.default_rng(seed)
    tx, ty = rng.uniform(-0.03, 0.03, 2) * SIZE
    Hv = pose_homography(tx, ty, rz=rng.uniform(-3, 3), center=CENTER)
    return _observe(scene, Hv, rng, n=n, shake=shake, roll=1.0)


def _corner_error(H, H_true) -> float:
    c = np.array([[0, 0], [SIZE - 1, 0], [SIZE - 1, SIZE - 1], [0, SIZE - 1]], float)
    return float(np.hypot(*(map_points(H @ np.linalg.inv(H_true), c) - c).T).max())


def _every_extent(ref, obs):
    """What align_coarse returned before the early stop: every extent tried, the first
    with the ``kernel`` stage, else the first alignment (the reserve)."""
    results = [a for _, a in coarse_align_shakes(ref, obs, SHAKES)
               if not isinstance(a, Exception)]
    kept = [a for a in results if "kernel" in a.method.split("+")]
    return (kept or results)[0]


class _Counting:
    """Counts the polishes run, by shake extent."""

    def __init__(self, monkeypatch):
        self.extents: list[float] = []
        original = coarse_mod.polish_and_verify

        def counted(level, H, shake_px, *args, **kwargs):
            self.extents.append(shake_px)
            return original(level, H, shake_px, *args, **kwargs)

        monkeypatch.setattr(coarse_mod, "polish_and_verify", counted)


@pytest.fixture(scope="module")
def years_apart():
    """LEVIR test_102 "before" (grassland) against its "after" (warehouses), seen from
    another viewpoint (3 % / 3 degrees) and shaken (6 px, 0.8 degree) by the package's
    simulator, as in ``tests/test_align.py``: the gradient blocks align it, the polish's
    blur model does not fit."""
    from reblur.simulate import make_pair

    p = make_pair(_read(LEVIR / "A" / "test_102.png"), _read(LEVIR / "B" / "test_102.png"),
                  rng=100, n_changes=0, moving=False, shake=dict(t_max=6.0, rz_max=0.8),
                  viewpoint=dict(max_shift_frac=0.03, max_rot_deg=3.0), noise_sigma=1 / 255)
    H = pose_homography(*p.path.poses.mean(axis=0), center=p.path.center) @ p.viewpoint
    return p.reference, p.observed, H / H[2, 2]


@pytest.fixture(scope="module")
def occluded():
    """LEVIR test_7 against itself with its central 45 % replaced by WHU 000121, shaken by
    8 px (the cost benchmark's ``45%`` content)."""
    ref = _read(LEVIR / "A" / "test_7.png")
    scene = ref.copy()
    side = int(SIZE * np.sqrt(0.45))
    y0 = (SIZE - side) // 2
    scene[y0:y0 + side, y0:y0 + side] = _read(WHU / "prev" / "000121.png")[:side, :side]
    obs, H = _shaken(scene, 8, 8.0)
    return ref, obs, H


@pytest.mark.parametrize("case", ["years_apart", "occluded"])
def test_content_misfit_stops_the_larger_extents(case, request, monkeypatch):
    """Content that differs: one extent and one polish instead of four of each, and the
    very homography trying every extent gives (bit for bit), recorded in the details."""
    ref, obs, H_true = request.getfixturevalue(case)
    want = _every_extent(ref, obs)
    assert "kernel" not in want.method  # the case this is about: the reserve is returned
    count = _Counting(monkeypatch)
    got = align_coarse(ref, obs)
    assert count.extents == [8.0]  # before: [8.0, 16.0, 32.0, 64.0]
    assert got.H.tobytes() == want.H.tobytes() and got.method == want.method
    # within the blur's reach of the truth (8 px of shake, 1 degree of roll: 21 px at the
    # corners), as the gradient blocks alone place it
    assert got.content_misfit and _corner_error(got.H, H_true) < 21.0
    details = got.to_dict()
    assert [e["shake_px"] for e in details["extents"]] == [8.0]
    (extent,) = details["extents"]
    assert extent["content_misfit"] and extent["method"] == got.method
    (polish,) = extent["polishes"]
    regions = polish["regions"]
    assert set(regions) <= set(polish_mod.REASONS)
    assert regions.get("misfit", 0) + regions.get("faint", 0) >= regions.get("spread", 0)
    assert polish["outcome"].startswith(("verified, not kept", "refused"))


def test_large_blur_still_reaches_the_extent_it_needs(monkeypatch):
    """The same scene shaken by 24 px: at 8 px the kernels spread (a blur larger than the
    extent, not a content misfit), so the search goes on and the polish fits at 16 px."""
    ref = _read(LEVIR / "A" / "test_7.png")
    obs, H_true = _shaken(ref, 100, 24.0)
    count = _Counting(monkeypatch)
    got = align_coarse(ref, obs)
    assert got.method.endswith("kernel") and got.shake_px > 8.0
    assert _corner_error(got.H, H_true) < 2.0
    tried = got.to_dict()["extents"]
    assert [e["shake_px"] for e in tried][0] == 8.0 and len(tried) >= 2
    first = tried[0]
    assert not first["content_misfit"]
    regions = first["polishes"][0]["regions"]
    assert regions.get("spread", 0) > 4 * (regions.get("misfit", 0) + regions.get("faint", 0))
    assert count.extents[0] == 8.0 and got.shake_px in count.extents


def test_a_blur_larger_than_the_extent_stops_its_other_estimates(monkeypatch):
    """Real camera shake larger than 8 px (GoPro 0374, an average of 8 frames): at 8 px the
    gradient blocks do not verify and the first feature estimate's kernels all spread, so
    neither the next feature level nor the phase correlation is polished at 8 px (three
    polishes before); the extent that fits gives the very homography it gives alone."""
    pairs = DATA / "gopro" / "pairs"
    ref = load_rgb(pairs / "GOPR0374_11_00_st_frame-614_n_avg-8_gt.png").astype(np.float32)
    obs = load_rgb(pairs / "GOPR0374_11_00_st_frame-614_n_avg-8.png").astype(np.float32)
    count = _Counting(monkeypatch)
    got = align_coarse(ref, obs)
    assert got.shake_px == 16.0 and got.method.endswith("kernel")
    assert count.extents == [8.0, 16.0]
    first = got.to_dict()["extents"][0]
    assert first["shake_px"] == 8.0 and "refused" in first
    (polish,) = first["polishes"]
    assert blur_exceeds(polish["regions"]) and not content_misfit(polish["regions"])
    assert "spread beyond shake_px=8" in first["refused"]
    (_, alone), = coarse_align_shakes(ref, obs, (16.0,))
    assert alone.H.tobytes() == got.H.tobytes() and alone.method == got.method


def test_blur_exceeds_rule():
    """The rule on counts: spread kernels must be three quarters of the textured regions."""
    assert blur_exceeds({"spread": 64})
    assert blur_exceeds({"spread": 45, "fit": 10, "misfit": 5, "flat": 30, "invalid": 9})
    assert not blur_exceeds({"spread": 44, "fit": 11, "misfit": 5})  # 44 < 45 of 60
    assert blur_exceeds({"spread": 51, "fit": 12, "misfit": 1})  # 24 px of shake at 8 px
    assert not blur_exceeds({"invalid": 9, "flat": 3})  # nothing to judge
    assert not blur_exceeds({})


def test_content_misfit_rule():
    """The rule on counts: content failures must be a quarter of the textured regions and
    outnumber the spread kernels."""
    assert content_misfit({"fit": 28, "spread": 7, "misfit": 27, "faint": 2})
    assert content_misfit({"misfit": 5, "invalid": 50})  # invalid regions do not count
    assert not content_misfit({"fit": 57, "spread": 3, "misfit": 4})  # a few changes
    assert not content_misfit({"fit": 1, "spread": 60, "misfit": 10})  # a larger blur
    assert not content_misfit({"invalid": 9})  # nothing to judge
    assert not content_misfit({})


def test_region_reasons(years_apart):
    """Each region's outcome: a flat observation gives ``flat``; an observation without
    data ``invalid``; unrelated noise ``misfit`` or ``faint``; the reference itself
    ``fit``."""
    ref, _, _ = years_apart
    gray = cv2.resize(ref.mean(axis=2), (256, 256), interpolation=cv2.INTER_AREA)
    rng = np.random.default_rng(3)
    cases = {
        "fit": gray,
        "flat": np.full_like(gray, 0.5),
        "noise": rng.random(gray.shape).astype(np.float32),
    }
    for name, obs in cases.items():
        (level, *_) = pyramid(gray, obs, 1.0, 256, None)
        *_, why = kernel_polish(level, np.eye(3), 3, n_regions=(4, 4), min_r2=0.3,
                                max_sd=3.0, max_pixels=8192)
        assert sum(why.values()) == 16, (name, why)
        if name == "noise":
            assert why.get("misfit", 0) + why.get("faint", 0) == 16, why
        else:
            assert why == {name: 16}, why
    (level, *_) = pyramid(gray, gray, 1.0, 256, None)
    level.obs_mask[:] = 0
    *_, why = kernel_polish(level, np.eye(3), 3, n_regions=(4, 4), min_r2=0.3, max_sd=3.0,
                            max_pixels=8192)
    assert why == {"invalid": 16}


@pytest.mark.parametrize("shake_px", [8.0, 16.0])
def test_threaded_polish_equals_the_serial_one(years_apart, shake_px):
    """The regions fitted on threads give the one-thread polish bit for bit: homography,
    counts, and the refusal (message and reasons) when it does not verify."""
    ref, obs, H_true = years_apart
    params = AlignParams()
    prep = coarse_mod._prepare(ref, obs, params, None)
    ctx = coarse_mod._Shake(prep, params, shake_px)
    level = prep.levels[ctx.work]
    H0 = H_true @ pose_homography(3.0, -2.0, rz=0.2, center=CENTER)

    def run(workers):
        try:
            p = polish_and_verify(level, H0, shake_px, prep.ref_shape, params, ctx.plausible,
                                  workers=workers)
            return "ok", p.H.tobytes(), p.n_agree, p.n_fit, p.n_total, p.reasons
        except polish_mod.PolishError as err:
            return "refused", str(err), err.reasons

    serial = run(1)
    assert run(4) == serial and run(2) == serial
    for R in (3, 6):
        one = kernel_polish(level, H0, R, n_regions=(8, 8), min_r2=0.3, max_sd=4.0,
                            max_pixels=8192)
        many = kernel_polish(level, H0, R, n_regions=(8, 8), min_r2=0.3, max_sd=4.0,
                             max_pixels=8192, workers=3)
        assert one[0].tobytes() == many[0].tobytes() and one[1:] == many[1:]
        assert sum(one[4].values()) == 64


def test_an_estimate_a_polish_refused_is_not_polished_again(monkeypatch):
    """WHU-CD 000121 (parallax, refused at every extent): the fallbacks of an extent
    converge to the estimate whose polish it just refused (ECC from the phase correlation
    to the features' one, within 0.01 px), and are refused without running: 6 polishes of
    12.  The reference is the slow path: run, each skipped polish is refused too, and every
    extent's refusal is the same."""
    ref = load_rgb(WHU / "prev" / "000121.png").astype(np.float32)
    obs = load_rgb(WHU / "curr" / "000121.png").astype(np.float32)
    count = _Counting(monkeypatch)
    got = [(s, a) for s, a in coarse_align_shakes(ref, obs, SHAKES)]
    assert all(isinstance(a, Exception) for _, a in got)
    skipped = [p for _, a in got for p in a.polishes if "as the estimate" in p["outcome"]]
    assert len(count.extents) == 6 and len(skipped) == 6  # before: 12 run
    count.extents.clear()
    monkeypatch.setattr(coarse_mod, "SAME_ESTIMATE_PX", -1.0)  # every estimate polished
    slow = [(s, a) for s, a in coarse_align_shakes(ref, obs, SHAKES)]
    assert len(count.extents) == 12
    for (s, a), (s2, b) in zip(got, slow, strict=True):
        assert s == s2 and isinstance(b, Exception)
        assert [p["of"] for p in a.polishes] == [p["of"] for p in b.polishes]
        for p, q in zip(a.polishes, b.polishes, strict=True):
            assert q["outcome"].startswith("refused") and p["regions"] == q["regions"]
        # the refusal names the same stages, each for the same reason up to the skip's note
        assert str(a).split(";")[0] == str(b).split(";")[0]
