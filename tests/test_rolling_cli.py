"""``reblur detect --shutter``: the flag reaches the pipeline and the report records it."""

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from reblur.testbed.rolling import render_rolling_tiled


def _run(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "reblur", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def rolling_pair(tmp_path_factory):
    """A 256 px pair: a camera at (7, 2) px per exposure, readout 0.5 (test bed renderer)."""
    d = tmp_path_factory.mktemp("rs")
    rng = np.random.default_rng(21)
    ref = cv2.GaussianBlur(rng.random((256, 256)), (0, 0), 1.5)
    ref = (ref - ref.min()) / np.ptp(ref)
    n, r = 64, 0.5
    t = (np.arange(n + n // 2) + 0.5) / n - (1 + r) / 2
    hs = np.stack([np.array([[1, 0, 7 * s], [0, 1, 2 * s], [0, 0, 1.0]]) for s in t])
    obs, _ = render_rolling_tiled(ref, hs, readout=r, n_exposure=n)
    for name, img in (("ref.png", ref), ("obs.png", obs)):
        cv2.imwrite(str(d / name), np.round(255 * np.clip(img, 0, 1)).astype(np.uint8))
    return d / "ref.png", d / "obs.png"


def test_shutter_rolling_is_used_and_reported(tmp_path, rolling_pair):
    """A constant velocity under a rolling shutter is a shear plus one blur: the
    alignment absorbs the shear, so the bands come out alike and the estimated readout
    small; what is checked is that the model ran and its record reached the report."""
    res = _run("detect", *rolling_pair, "--out", tmp_path / "out", "--shutter", "rolling",
               "-q")
    assert res.returncode == 0, res.stderr
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    sh = report["decision"]["shutter"]
    assert sh["asked"] == "rolling" and sh["model"] == "rolling"
    assert 0.0 <= sh["readout"] <= 1.0
    assert "alignment" in sh["readout_meaning"]  # says what the figure is, and its bias
    bands = sh["rolling"]["bands"]
    assert len(bands) == 6 and all(abs(b["weight_sum"] - 1) < 0.1 for b in bands)
    assert sh["criterion"]["rule"].startswith("rolling when BIC")
    assert report["files"]["rolling.png"] == "rolling.png"
    assert (tmp_path / "out" / "rolling.png").stat().st_size > 0


def test_shutter_flag_refuses_other_values(tmp_path, rolling_pair):
    res = _run("detect", *rolling_pair, "--out", tmp_path / "out", "--shutter", "sideways")
    assert res.returncode != 0 and "Traceback" not in res.stderr
    assert "--shutter" in res.stderr
    assert not (tmp_path / "out").exists()


def test_rolling_figure_lists_the_bands(tmp_path):
    """rolling.png is drawn from the record of the band model, one point per band."""
    from matplotlib.image import imread

    from reblur.report import rolling_figure

    bands = [dict(centre_row=c, weight_sum=1.0, n_poses=5,
                  mean_pose=dict(tx=0.5 * i, ty=-0.2 * i, tz=0.0, rx=0.0, ry=0.0, rz=0.1))
             for i, c in enumerate((31.5, 95.5, 159.5, 223.5))]
    rec = dict(model="rolling", readout=0.4, criterion=dict(drop=0.6),
               rolling=dict(n_bands=4, bands=bands))
    path = rolling_figure(rec, tmp_path / "rolling.png")
    img = imread(path)
    assert img.shape[0] > 100 and img.shape[1] > 300 and img.std() > 0
