"""GridParams (the 3-D / 6-D grid from ranges), EXIF focal lengths, and ``reblur detect
--grid 6d --focal ... --tz-max ... --tilt-max ...``."""

import json
import math
import subprocess
import sys

import cv2
import numpy as np
import pytest
from PIL import Image as PILImage

from reblur.grid import GridParams, PoseGrid, map_points, pose_homography
from reblur.io import exif_focal_px


def _farthest(shape):
    h, w = shape
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    return c, np.array([[0.0, 0.0]]), float(np.hypot(*c))


def test_3d_is_the_pipelines_default_grid():
    got = GridParams().build((300, 400))
    want = PoseGrid.from_ranges((300, 400), t_max=12, rz_max=3.0, corner_px=1.0)
    assert got == want
    assert GridParams(rz_step=0.5).build((300, 400)) == PoseGrid.from_ranges(
        (300, 400), t_max=12, rz_max=3.0, rz_step=0.5)


def test_6d_steps_move_the_farthest_pixel_by_one_pixel():
    shape = (300, 400)
    g = GridParams(kind="6d", focal=500.0, tz_max=0.01, tilt_max=0.5, t_max=3).build(shape)
    c, corner, R = _farthest(shape)
    assert g.focal == 500.0 and g.tx == tuple(range(-3, 4))
    tz_step, tilt_step = g.tz[1] - g.tz[0], g.rx[1] - g.rx[0]
    H = pose_homography(tz=tz_step, center=tuple(c))
    assert np.linalg.norm(map_points(H, corner) - corner) == pytest.approx(1.0, rel=1e-9)
    # a tilt or pan: what it moves a pixel beyond the shift it gives the centre, at most
    # ~1 px at the corners (|y| R / f of a step in rad), exactly 1 px to first order at
    # distance R along the axis it turns about's normal (R^2 / f)
    for axis in ("rx", "ry"):
        H = pose_homography(center=tuple(c), focal=500.0, **{axis: tilt_step})
        shift = map_points(H, c[None]) - c[None]
        corners = np.array([[0, 0], [399, 0], [0, 299], [399, 299]], float)
        extra = np.linalg.norm(map_points(H, corners) - corners - shift, axis=1)
        assert 0.5 < extra.max() <= 1.0 + 1e-2
        far = c + (np.array([0.0, R]) if axis == "rx" else np.array([R, 0.0]))
        moved = map_points(H, far[None])[0] - far - shift[0]
        assert np.linalg.norm(moved) == pytest.approx(1.0, rel=0.05)
    # ranges: nearest whole number of steps either side, symmetric about 0
    assert len(g.tz) == 2 * round(0.01 / tz_step) + 1 and g.tz[len(g.tz) // 2] == 0.0
    assert g.rx == g.ry and len(g.rx) == 2 * round(0.5 / tilt_step) + 1
    assert max(g.rz) == pytest.approx(1.0, abs=np.rad2deg(1 / R))  # the 6-D roll default


def test_6d_default_focal_and_refusals():
    assert GridParams(kind="6d").build((200, 250)).focal == pytest.approx(1.2 * 250)
    with pytest.raises(ValueError, match="'3d' or '6d'"):
        GridParams(kind="4d")
    with pytest.raises(ValueError, match="kind='6d'"):
        GridParams(focal=300.0)
    with pytest.raises(ValueError, match="focal must be"):
        GridParams(kind="6d", focal=-1.0)
    with pytest.raises(ValueError, match="base poses .* narrow"):
        GridParams(kind="6d", tilt_max=5.0).build((1000, 1000))


def _jpeg_with_focal(path, img, f35):
    im = PILImage.fromarray(img)
    exif = PILImage.Exif()
    exif.get_ifd(0x8769)[0xA405] = f35
    im.save(path, exif=exif, quality=95)


def test_exif_focal_in_pixels(tmp_path):
    img = np.full((60, 80), 128, np.uint8)
    _jpeg_with_focal(tmp_path / "a.jpg", img, 28)
    assert exif_focal_px(tmp_path / "a.jpg") == pytest.approx(28 * 100 / 43.27)
    PILImage.fromarray(img).save(tmp_path / "b.png")
    assert exif_focal_px(tmp_path / "b.png") is None
    _jpeg_with_focal(tmp_path / "c.jpg", img, 0)  # EXIF's "unknown"
    assert exif_focal_px(tmp_path / "c.jpg") is None
    assert exif_focal_px(tmp_path) is None


# ---------------------------------------------------------------------------- CLI
def _run(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "reblur", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """A 320 px pair (the window selection works on 100 px cells): the observation a
    3-pose blur (translations and a small tilt) of the reference; the observation also as
    a JPEG with a 35 mm-equivalent focal length."""
    d = tmp_path_factory.mktemp("grid6d")
    rng = np.random.default_rng(3)
    ref = cv2.GaussianBlur(rng.random((320, 320)), (0, 0), 1.5)
    ref = (ref - ref.min()) / np.ptp(ref)
    c = (159.5, 159.5)
    obs = np.zeros_like(ref)
    for tx, rx in ((-1, 0.0), (0, 0.2), (1, 0.0)):
        H = pose_homography(tx=tx, rx=rx, center=c, focal=384.0)
        obs += cv2.warpPerspective(ref, H, (320, 320), flags=cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_REFLECT) / 3
    u8 = [np.round(255 * np.clip(a, 0, 1)).astype(np.uint8) for a in (ref, obs)]
    cv2.imwrite(str(d / "ref.png"), u8[0])
    cv2.imwrite(str(d / "obs.png"), u8[1])
    _jpeg_with_focal(d / "obs.jpg", u8[1], 50)
    return d


def _report(out):
    return json.loads((out / "report.json").read_text())


def test_cli_6d_grid_with_focal_and_ranges(tmp_path, pair):
    out = tmp_path / "o"
    res = _run("detect", pair / "ref.png", pair / "obs.png", "-o", out, "--grid", "6d",
               "--focal", 384, "--t-max", 3, "--rz-max", 0.3, "--tz-max", 0.006,
               "--tilt-max", 0.4, "--tilt-step", 0.2, "-q")
    assert res.returncode == 0, res.stderr
    rep = _report(out)
    assert rep["options"]["grid"] == "6d" and rep["options"]["focal_source"] == "--focal"
    g = rep["motion"]["grid"]
    assert g["focal"] == 384.0
    np.testing.assert_allclose(g["rx"], [-0.4, -0.2, 0.0, 0.2, 0.4])
    assert g["ry"] == g["rx"] and g["tx"] == list(range(-3, 4))
    R = math.hypot(159.5, 159.5)
    assert len(g["tz"]) == 2 * round(0.006 * R) + 1  # the default step, 1 / R
    assert max(g["rz"]) <= 0.3 + np.rad2deg(1 / R)


def test_cli_6d_focal_from_exif(tmp_path, pair):
    out = tmp_path / "o"
    res = _run("detect", pair / "ref.png", pair / "obs.jpg", "-o", out, "--grid", "6d",
               "--t-max", 3, "--rz-max", 0.2, "--tilt-max", 0.2, "-q")
    assert res.returncode == 0, res.stderr
    rep = _report(out)
    assert rep["options"]["focal_source"] == "EXIF FocalLengthIn35mmFilm"
    assert rep["motion"]["grid"]["focal"] == pytest.approx(50 * math.hypot(320, 320) / 43.27)


@pytest.mark.parametrize("args, words", [
    (("--focal", 300), "--grid 6d"),
    (("--tilt-max", 0.2, "--tz-step", 0.001), "--tz-step, --tilt-max"),
    (("--grid", "5d"), "--grid"),
    (("--grid", "6d", "--focal", 0), "--focal"),
    (("--grid", "6d", "--tilt-max", 8, "--tilt-step", 0.01), "narrow"),
])
def test_cli_grid_flags_refuse_bad_values(tmp_path, pair, args, words):
    out = tmp_path / "o"
    res = _run("detect", pair / "ref.png", pair / "obs.png", "-o", out, *args)
    assert res.returncode != 0 and "Traceback" not in res.stderr
    assert words in res.stderr, res.stderr
    assert len(res.stderr.strip().splitlines()) <= 3
    assert not out.exists()
