"""One reference against many observations: the reference cache, the observation sources
(files, folders, globs, videos) and ``reblur detect REF OBS [OBS ...]``."""

from __future__ import annotations

import csv
import json
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

import reblur
from reblur.align.overviews import OverviewCache, read_block_means
from reblur.data import demo_pair
from reblur.io import InputError, write_png
from reblur.many import (
    detect_changes_many,
    iter_observations,
    observation_sources,
    parse_frames,
    read_video_frames,
)
from reblur.refcache import ReferenceCache
from reblur.simulate import make_pair

#: Fast options for the command line: registered pair, no refinement, a small grid.
FAST = ("--no-align", "--no-refine", "--no-field", "--t-max", "2", "--rz-max", "0",
        "--illumination", "global")


def _reference() -> np.ndarray:
    """A 256 x 320 gray crop of the demo reference (a real photograph)."""
    ref, _, _ = demo_pair()
    return np.ascontiguousarray(cv2.cvtColor(ref, cv2.COLOR_RGB2GRAY)[50:306, 100:420])


def _observation(ref: np.ndarray, seed: int) -> np.ndarray:
    """A shaken, re-viewpointed, changed uint8 observation of ``ref``."""
    p = make_pair(ref, rng=seed, shake=dict(t_max=3, rz_max=0.3), n_changes=2, moving=False)
    return (np.clip(p.observed, 0, 1) * 255).round().astype(np.uint8)


def _registered(ref: np.ndarray, seed: int) -> np.ndarray:
    """A blurred, changed uint8 observation in the reference's frame (for --no-align)."""
    p = make_pair(ref, rng=seed, shake=dict(t_max=1.5, rz_max=0.0), viewpoint=None,
                  n_changes=2, moving=False)
    return (np.clip(p.observed, 0, 1) * 255).round().astype(np.uint8)


@pytest.fixture(scope="module")
def pair_set():
    """The reference and two observations, the second of another size (so that the
    overviews a fresh run reads differ from the first run's)."""
    ref = _reference()
    return ref, [_observation(ref, 1), _observation(ref, 2)[:240, :300]]


# ---------------------------------------------------------------------------- the cache
def test_reuse_gives_the_results_of_separate_runs(pair_set):
    """detect_changes_many (one cache, the reference's work reused) gives, for every
    observation, the masks, reblurred image, alignment and weights of a separate call."""
    ref, observations = pair_set
    opts = dict(t_max=6, rz_max=1, illumination="global", refine=False, local_field=False)
    many = list(detect_changes_many(ref, [(f"o{i}", o) for i, o in enumerate(observations)],
                                    **opts))
    assert [m.error for m in many] == [None, None]
    for m, obs in zip(many, observations, strict=True):
        alone = reblur.detect_changes(ref, obs, **opts)
        a = m.result
        assert np.array_equal(a.change, alone.change)
        assert np.array_equal(a.unknown, alone.unknown)
        assert np.array_equal(a.reblurred, alone.reblurred)
        assert np.array_equal(a.alignment, alone.alignment)
        assert np.array_equal(a.motion.weights, alone.motion.weights)
        assert a.threshold == alone.threshold
        assert "reference_cache" not in alone.decision
        # where the overviews came from, recorded for a reused overview too
        src = a.decision["alignment"]["overviews"]
        assert src == alone.decision["alignment"]["overviews"]
        assert src["reference"]["source"] == "block means of the full image"
    first, second = (m.result.decision["reference_cache"] for m in many)
    kinds = {"overviews", "pyramid levels", "reference features"}
    # the first run computes what the second reuses, and the second computes nothing new
    assert first["reused"] == {} and set(first["computed"]) == kinds
    assert set(second["reused"]) == kinds and second["computed"] == {}


def test_shared_overviews_are_those_a_fresh_run_makes():
    """An overview one run derived from a finer one is not handed to a run that would
    have read it directly: each gets what its own fresh OverviewCache gives."""
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (96, 128, 3), dtype=np.uint8)
    direct = read_block_means(img, 4)[1]
    fresh = OverviewCache(img)
    fresh.block_means(2)
    derived = fresh.block_means(4)[1]
    assert not np.array_equal(derived, direct)  # else this test could not fail
    cache = ReferenceCache(img)
    a = cache.begin().overviews
    a.block_means(2)
    assert np.array_equal(a.block_means(4)[1], derived)
    b = cache.begin().overviews
    assert np.array_equal(b.block_means(4)[1], direct)
    c = cache.begin().overviews
    assert c.block_means(4)[1] is b.block_means(4)[1]  # reused, not recomputed
    assert cache.totals()["reused"] == {"overviews": 1}


def test_cache_of_another_reference_is_refused(pair_set):
    ref, observations = pair_set
    with pytest.raises(ValueError, match="another reference"):
        reblur.detect_changes(ref, observations[0], reference_cache=ReferenceCache(ref.copy()))


@pytest.mark.parametrize("option", ["reblurred_out", "change_out", "work_dir"])
def test_per_result_outputs_cannot_be_shared(pair_set, option, tmp_path):
    """One buffer or folder for every observation would leave each result holding the
    last one's arrays."""
    ref, observations = pair_set
    with pytest.raises(ValueError, match=f"{option} cannot be shared"):
        next(detect_changes_many(ref, observations, **{option: tmp_path}))


def test_cache_arrays_are_read_only(pair_set):
    """Every later run shares what the cache holds: no run may change it in place."""
    ref, observations = pair_set
    cache = ReferenceCache(ref)
    reblur.detect_changes(ref, observations[0], reference_cache=cache)
    held = [a for a, _ in cache._held.values()]
    assert held and not any(a.flags.writeable for a in held)


def test_many_records_failures_and_goes_on():
    """A loader that raises and a too small observation fail on their own, with one-line
    reasons; bad options are refused before any observation."""
    ref = _reference()

    def unreadable():
        raise OSError("frame 7: read error")

    got = list(detect_changes_many(ref, [("a", unreadable), ("b", np.zeros((8, 8)))]))
    assert [(g.name, g.ok) for g in got] == [("a", False), ("b", False)]
    assert got[0].error == "frame 7: read error"
    assert "too small" in got[1].error and "\n" not in got[1].error
    with pytest.raises(TypeError, match="tile_sise"):
        detect_changes_many(ref, [], tile_sise=64)
    with pytest.raises(ValueError, match="change_out"):
        detect_changes_many(ref, [], change_out=np.zeros((8, 8), bool))


# ---------------------------------------------------------------------------- sources
def _video(path: Path, frames: list[np.ndarray], fps: float = 10.0) -> Path:
    h, w = frames[0].shape[:2]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert vw.isOpened(), "OpenCV cannot write MJPG/AVI here"
    for f in frames:
        vw.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR) if f.ndim == 2 else f[:, :, ::-1])
    vw.release()
    return path


def test_video_read_frame_by_frame_with_every_and_frames(tmp_path):
    """Frames 1..5 every 2nd: 1, 3, 5, each the frame written at that position (frames
    are the reference rolled by 24 px times their number, told apart after JPEG)."""
    ref = _reference()
    written = [np.roll(ref, 24 * i, axis=1) for i in range(8)]
    video = _video(tmp_path / "clip.avi", written)
    got = list(read_video_frames(video, every=2, frames=(1, 6)))
    assert [i for i, _ in got] == [1, 3, 5]
    for i, frame in got:
        assert frame.shape == (*ref.shape, 3) and frame.dtype == np.uint8
        err = [np.abs(frame[:, :, 1].astype(int) - w).mean() for w in written]
        assert int(np.argmin(err)) == i and err[i] < 4, err
    assert [i for i, _ in read_video_frames(video, frames=(6, None))] == [6, 7]
    with pytest.raises(InputError, match="cannot open the video"):
        list(read_video_frames(tmp_path / "missing.avi"))


@pytest.mark.parametrize("text, expected", [
    (None, (0, None)), ("2:5", (2, 5)), ("10:", (10, None)), (":7", (0, 7)), (" 3 : 4 ", (3, 4)),
])
def test_parse_frames(text, expected):
    assert parse_frames(text) == expected


@pytest.mark.parametrize("text", ["5", "a:b", "5:5", "6:2", "-1:3"])
def test_parse_frames_refuses(text):
    with pytest.raises(ValueError, match="frames"):
        parse_frames(text)


def test_sources_files_folders_globs_and_names(tmp_path):
    """A folder gives its images sorted (not other files), a glob its matches, a video
    file its frames; names are unique, safe, and never index.html / summary.csv."""
    img = np.full((40, 40), 7, np.uint8)
    (tmp_path / "shots").mkdir()
    for n in ("b.png", "a.jpg", "notes.txt"):
        (tmp_path / "shots" / n).write_bytes(b"x")
    (tmp_path / "other").mkdir()
    write_png(tmp_path / "other" / "a.png", img)
    write_png(tmp_path / "other" / "index.html.png", img)
    write_png(tmp_path / "other" / "we ird#name.png", img)
    video = _video(tmp_path / "clip.avi", [img, img + 50, img + 100])
    srcs = observation_sources([tmp_path / "shots", str(tmp_path / "other" / "*.png"),
                                video])
    assert [(s.path.name, s.kind) for s in srcs] == [
        ("a.jpg", "image"), ("b.png", "image"), ("a.png", "image"),
        ("index.html.png", "image"), ("we ird#name.png", "image"), ("clip.avi", "video")]
    names = [o.name for o in iter_observations(srcs, every=2)]
    assert names == ["a", "b", "a-2", "index.html-2", "we_ird_name", "clip-f000000",
                     "clip-f000002"]
    with pytest.raises(InputError, match="no file matches"):
        observation_sources([str(tmp_path / "nothing*.png")])
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="holds no image"):
        observation_sources([tmp_path / "empty"])


# ---------------------------------------------------------------------------- command line
def _run(*args, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "reblur", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


def test_cli_many_observations(tmp_path):
    """An image, two frames of a video and an unreadable file: three folders with the
    usual outputs, a failed row with its reason, index.html and summary.csv listing all
    four, exit code 1; the image's folder holds what a single run writes."""
    ref = _reference()
    obs = _registered(ref, 1)
    write_png(tmp_path / "ref.png", ref)
    write_png(tmp_path / "obs.png", obs)
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")
    frames = [np.clip(obs.astype(int) + 3 * i, 0, 255).astype(np.uint8) for i in range(5)]
    _video(tmp_path / "clip.avi", frames)
    out = tmp_path / "res"
    res = _run("detect", tmp_path / "ref.png", tmp_path / "obs.png", tmp_path / "clip.avi",
               tmp_path / "broken.png", "--every", 2, "--frames", "1:4", "--out", out, *FAST,
               "-q")
    assert res.returncode == 1, res.stderr
    assert res.stderr.strip().splitlines() == [
        f"reblur: error: 1 of 4 observations failed (reasons in {out / 'summary.csv'})"]
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [(r["name"], r["status"]) for r in rows] == [
        ("obs", "ok"), ("clip-f000001", "ok"), ("clip-f000003", "ok"), ("broken", "failed")]
    assert "broken.png" in rows[3]["reason"] and rows[3]["changed_percent"] == ""
    for r in rows[:3]:
        folder = out / r["name"]
        assert {"changes.png", "report.json", "report.html", "overlay.png"} <= {
            p.name for p in folder.iterdir()}
        rep = json.loads((folder / "report.json").read_text())
        changed = cv2.imread(str(folder / "changes.png"), cv2.IMREAD_GRAYSCALE) == 255
        # the row's flagged share is the share of changes.png's pixels
        assert float(r["changed_percent"]) == pytest.approx(100 * changed.mean(), rel=1e-3)
        assert int(r["regions"]) == rep["changes"]["n_regions"]
    assert rows[1]["source"].endswith("clip.avi#1")
    # the second and third reused the reference's overviews
    assert rows[0]["reused"] == "" and "overviews" in rows[1]["reused"]
    index = (out / "index.html").read_text()
    for r in rows[:3]:
        assert f'href="{r["name"]}/report.html"' in index
        viewer = f'{r["name"]}/viewer/index.html'
        assert f'href="{viewer}"' in index and (out / viewer).is_file()
    assert "failed: " in index and "broken" in index
    # the single run of the same pair writes the same change mask
    alone = tmp_path / "alone"
    res = _run("detect", tmp_path / "ref.png", tmp_path / "obs.png", "--out", alone, *FAST,
               "-q")
    assert res.returncode == 0, res.stderr
    assert (alone / "changes.png").read_bytes() == (out / "obs" / "changes.png").read_bytes()
    assert not (alone / "summary.csv").exists()


def test_cli_many_refuses_bad_combinations(tmp_path):
    ref = _reference()
    write_png(tmp_path / "ref.png", ref)
    write_png(tmp_path / "a.png", ref)
    cases = [
        (("a.png", "--every", 2), "--every and --frames pick the frames of a video; OBSERVED "
                                  "is one image"),
        (("a.png", "a.png", "--truth", "a.png"), "--truth scores one observation"),
        (("a.png", "a.png", "--frames", "1:3"), "OBSERVED names none"),
        (("a.png", "--frames", "3:1"), "select no frame"),
    ]
    for args, words in cases:
        args = [tmp_path / a if str(a).endswith(".png") else a for a in args]
        res = _run("detect", tmp_path / "ref.png", *args, "--out", tmp_path / "o")
        assert res.returncode == 2, res.stderr
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and words in lines[0], lines
        assert not (tmp_path / "o").exists()


def test_cli_many_refuses_an_earlier_runs_folders_up_front(tmp_path):
    """An earlier run stopped before its index.html left observation folders: without
    --overwrite the run is refused at once, before any work (it used to detect every
    other observation and fail those one by one)."""
    ref = _reference()
    write_png(tmp_path / "ref.png", ref)
    write_png(tmp_path / "a.png", ref)
    write_png(tmp_path / "b.png", ref)
    (tmp_path / "o" / "a").mkdir(parents=True)
    (tmp_path / "o" / "a" / "report.json").write_text("{}")
    res = _run("detect", tmp_path / "ref.png", tmp_path / "a.png", tmp_path / "b.png",
               "--out", tmp_path / "o")
    assert res.returncode == 1, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "already holds results (a/)" in lines[0], lines
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["a"]


def test_cli_progress_lines_when_stderr_is_not_a_terminal(tmp_path):
    """Without a terminal, progress is log lines: every stage from 0 % to 100 % in steps
    of 10 %, the report's writing included, no bar control characters."""
    ref = _reference()
    write_png(tmp_path / "ref.png", ref)
    write_png(tmp_path / "obs.png", _registered(ref, 1))
    res = _run("detect", tmp_path / "ref.png", tmp_path / "obs.png", "--out",
               tmp_path / "res", *FAST)
    assert res.returncode == 0, res.stderr
    assert "\r" not in res.stderr and "\x1b" not in res.stderr
    seen: dict[str, list[int]] = {}
    for line in res.stderr.strip().splitlines():
        m = re.fullmatch(r"reblur: ([a-z +]+): (\d+) % \((\d+\.\d) s\)", line)
        assert m is not None, line
        seen.setdefault(m.group(1), []).append(int(m.group(2)))
    assert list(seen)[:2] == ["align", "estimate"] and list(seen)[-1] == "report"
    assert "reblur + decide" in seen
    for stage, levels in seen.items():
        assert levels == sorted(set(levels)), (stage, levels)
        assert levels[0] == 0 and levels[-1] == 100, (stage, levels)
        assert all(v % 10 == 0 for v in levels), (stage, levels)
    assert res.stdout.startswith("changes: ")


def test_benchmark_frames_are_spread_and_skip_the_reference():
    from benchmarks.many import _observations

    assert _observations(6, 12, 1) == [1, 5, 10, 15, 20, 24]
    assert len(_observations(23, 12, 1)) == 23 and 12 not in _observations(23, 12, 1)
    # 4-frame means: centres 3..23 (gopro_frame_indices), the reference's centre allowed
    assert _observations(3, 12, 4) == [3, 13, 23]
    with pytest.raises(SystemExit):
        _observations(24, 12, 1)
