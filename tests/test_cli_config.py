"""``reblur detect --config FILE.toml`` and the detection options on the command line;
``REBLUR_DATA`` / ``--data`` for the experiments and benchmarks; the LICENSE file."""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest

from reblur.align import AlignParams
from reblur.config import ConfigError, load_config
from reblur.data import demo_pair
from reblur.decide import DecisionParams
from reblur.io import write_png
from reblur.rolling import RollingParams
from reblur.select import SelectParams
from reblur.simulate import make_pair

REPO = Path(__file__).resolve().parents[1]
FAST = ("--no-align", "--no-refine", "--no-field", "--t-max", "2", "--rz-max", "0", "-q")


def _run(*args, module: str = "reblur", env: dict | None = None,
         timeout: float = 600) -> subprocess.CompletedProcess:
    import os

    return subprocess.run([sys.executable, "-m", module, *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout,
                          env=None if env is None else {**os.environ, **env})


@pytest.fixture(scope="module")
def pair(tmp_path_factory) -> tuple[Path, Path]:
    """A registered 256 x 320 pair (blurred, two pasted changes) as PNG files."""
    d = tmp_path_factory.mktemp("pair")
    ref, _, _ = demo_pair()
    ref = np.ascontiguousarray(cv2.cvtColor(ref, cv2.COLOR_RGB2GRAY)[50:306, 100:420])
    p = make_pair(ref, rng=1, shake=dict(t_max=1.5, rz_max=0.0), viewpoint=None,
                  n_changes=2, moving=False)
    write_png(d / "ref.png", ref)
    write_png(d / "obs.png", (np.clip(p.observed, 0, 1) * 255).round().astype(np.uint8))
    return d / "ref.png", d / "obs.png"


# ---------------------------------------------------------------------------- bad files
@pytest.mark.parametrize("text, words", [
    ("[decision]\nmin_aera = 50\n", "[decision] unknown key 'min_aera' (did you mean min_area"),
    ("[decisions]\nmin_area = 50\n", "unknown table 'decisions'"),
    ("min_area = 50\n", "unknown key outside a table 'min_area'"),
    ("[decision]\nmin_area = \"big\"\n", "[decision] min_area must be an integer, got 'big'"),
    ("[decision]\nregion_tests = 1\n", "[decision] region_tests must be true or false"),
    ("[align]\nmin_agree = 1.5\n", "AlignParams.min_agree must lie in [0, 1], got 1.5"),
    ("[select]\nwindows = 0\n", "SelectParams.windows must be an integer >= 1, got 0"),
    ("[rolling]\nn_bands = 0\n", "RollingParams.n_bands must be >= 1"),
    ("[select]\nextra = 1\n", "[select] unknown key 'extra'"),
    ("[select]\nbands = \"red\"\n", "SelectParams.bands must be 'mean' or 'all', got 'red'"),
    ("[decision\nmin_area = 50\n", "not valid TOML"),
    # TOML's nan and inf are numbers, never settings (nan passed `smooth < 0` silently)
    ("[decision]\nsmooth = nan\n", "[decision] smooth must be a finite number, got nan"),
    ("[decision]\nmin_threshold = inf\n", "[decision] min_threshold must be a finite number"),
    ("[rolling]\nmin_readout = -inf\n", "[rolling] min_readout must be a finite number"),
])
def test_bad_config_is_one_line_and_exit_2(tmp_path, pair, text, words):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(text)
    out = tmp_path / "res"
    res = _run("detect", *pair, "--out", out, "--config", cfg)
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("reblur: error: Invalid value for '--config'"), lines[0]
    assert str(cfg) in lines[0] and words in lines[0], lines[0]
    assert not out.exists()


def test_missing_config_file(tmp_path, pair):
    res = _run("detect", *pair, "--out", tmp_path / "res", "--config", tmp_path / "no.toml")
    assert res.returncode == 2 and "no.toml: no such file" in res.stderr


def test_config_values_reach_the_dataclasses(tmp_path):
    """Each table fills its dataclass; the file's values, not the defaults, end up there;
    lists become tuples; "none" is None where the field allows it."""
    cfg = tmp_path / "c.toml"
    cfg.write_text('[decision]\nmin_area = 50\nlevels = [1, 1.5, 3]\n'
                   'tolerance_ladder = [[0.25, 0.0], [1.0, 0.05]]\n'
                   '[select]\nmax_tries = 2\nlam = 0.2\n'
                   '[align]\nmethod = "features"\nnodata = "none"\nrotations = [-5, 0, 5]\n'
                   '[rolling]\nn_bands = 8\n')
    c = load_config(cfg)
    assert c.decision == DecisionParams(min_area=50, levels=(1.0, 1.5, 3.0),
                                        tolerance_ladder=((0.25, 0.0), (1.0, 0.05)))
    assert c.select == SelectParams(max_tries=2, lam=0.2)
    assert c.align == AlignParams(method="features", nodata=None, rotations=(-5.0, 0.0, 5.0))
    assert c.rolling == RollingParams(n_bands=8)
    assert c.sets("select", "lam") and not c.sets("select", "windows")
    # the documented example of reblur.config is a valid file
    import reblur.config

    doc = reblur.config.__doc__
    example = "\n".join(line[4:] for line in doc.split("::", 1)[1].splitlines()
                        if line.startswith("    "))
    assert set(tomllib.loads(example)) == {"decision", "select", "align", "rolling"}
    with pytest.raises(ConfigError):
        load_config(tmp_path / "missing.toml")


@pytest.mark.parametrize("explicit_lam", [False, True])
def test_config_and_flags_in_a_run(tmp_path, pair, explicit_lam):
    """A run uses the file's decision options and [select] lam, unless --lam is given;
    --box sets the estimation window; report.json records all of it."""
    cfg = tmp_path / "c.toml"
    cfg.write_text("[decision]\nmin_area = 50\nillumination = \"global\"\n"
                   "[select]\nlam = 0.2\n")
    out = tmp_path / "res"
    extra = ("--lam", 0.15) if explicit_lam else ()
    res = _run("detect", *pair, "--out", out, "--config", cfg, "--box", "20,30,200,250",
               *FAST, *extra)
    assert res.returncode == 0, res.stderr
    rep = json.loads((out / "report.json").read_text())
    assert rep["decision"]["params"]["min_area"] == 50
    assert rep["decision"]["params"]["illumination"] == "global"
    assert rep["options"]["lam"] == (0.15 if explicit_lam else 0.2)
    assert rep["options"]["decision"]["min_area"] == 50
    assert rep["options"]["config"] == str(cfg)
    assert rep["motion"]["boxes"] == [[20, 30, 200, 250]]


def test_colour_motion_on_the_band_mean_or_every_band(tmp_path):
    """The demo pair (RGB): by default the motion is solved on the band mean, with
    ``[select] bands = "all"`` on every band; report.json says which, the change term of
    the windows stays per band, and both masks score alike against the pair's truth."""
    from reblur.data import demo_paths

    paths = demo_paths()
    truth = cv2.imread(str(paths["truth"]), cv2.IMREAD_GRAYSCALE) > 127
    cfg = tmp_path / "all.toml"
    cfg.write_text('[select]\nbands = "all"\n')
    jc = {}
    for bands, extra in (("mean", ()), ("all", ("--config", cfg))):
        out = tmp_path / bands
        res = _run("detect", paths["reference"], paths["observed"], "--out", out, "-q",
                   *extra)
        assert res.returncode == 0, res.stderr
        info = json.loads((out / "report.json").read_text())["motion"]["info"]
        assert info["bands"] == bands
        assert len(info["photometry"]["offset"]) == 3
        changes = cv2.imread(str(out / "changes.png"), cv2.IMREAD_UNCHANGED) > 0
        jc[bands] = (changes & truth).sum() / (changes | truth).sum()
    assert min(jc.values()) >= 0.75 and abs(jc["mean"] - jc["all"]) <= 0.01, jc


@pytest.mark.parametrize("value", ["1,2,3", "0,0,4,4", "a,b,c,d", "-1,0,100,100"])
def test_bad_box_is_refused(tmp_path, pair, value):
    res = _run("detect", *pair, "--out", tmp_path / "res", "--box", value)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "--box" in lines[0] and "Y0,X0,H,W" in lines[0], lines


# ---------------------------------------------------------------------------- data, license
def test_experiments_without_the_data_say_so_in_one_line(tmp_path):
    """``python -m experiments.run`` with no shared data: one line naming what is missing
    and how to point at it, exit 2 (it used to die of a ZeroDivisionError)."""
    res = _run("--data", tmp_path / "nothing", module="experiments.run")
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("experiments: error: shared data not "
                                                   "found"), lines
    assert "REBLUR_DATA" in lines[0] and "--data" in lines[0]
    res = _run("operator", "--data", tmp_path / "nothing", module="benchmarks.run")
    assert res.returncode == 2 and res.stderr.startswith("benchmarks: error: shared data "
                                                         "not found"), res.stderr


def test_reblur_data_points_the_helpers_at_the_data(tmp_path, monkeypatch):
    from experiments import common as ex_common
    from reblur.testbed import DataMissing, gopro_frame, shared_data_dir

    monkeypatch.setenv("REBLUR_DATA", str(tmp_path))
    assert shared_data_dir() == tmp_path
    with pytest.raises(DataMissing, match="REBLUR_DATA"):
        ex_common.test_image(0, 1000)
    with pytest.raises(DataMissing, match="gopro"):
        gopro_frame(1)
    monkeypatch.setenv("REBLUR_DATA", str(tmp_path / "absent"))
    with pytest.raises(DataMissing, match="absent"):
        shared_data_dir()


def test_license_file_matches_the_declared_license():
    declared = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["license"]
    text = (REPO / "LICENSE").read_text()
    assert declared == "BSD-3-Clause"
    assert text.startswith("BSD 3-Clause License")
    assert "the reblur developers" in text
    assert "Neither the name of the copyright holder" in text  # the third clause
