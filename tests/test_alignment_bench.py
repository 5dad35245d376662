"""The alignment benchmark's own machinery (``benchmarks/alignment.py``): the GoPro sweep's
pairs, the moving-area registration, the record of runs, and how a run is scored (refused /
crashed, a result's displacement field) against independent values."""

from __future__ import annotations

import json
import sys
import types

import cv2
import numpy as np
import pytest
from conftest import REPO

if str(REPO) not in sys.path:  # the benchmarks live beside src/, not in the package
    sys.path.insert(0, str(REPO))
from benchmarks import alignment as bench  # noqa: E402


def test_gopro_sweep_holds_every_window_that_fits():
    pairs = bench.gopro_set("all")
    assert len(pairs) == sum(24 - k + 1 for k in range(4, 17)) == 195
    for c, first, k in pairs:  # even k: one more frame before the centre
        assert first == c - k // 2 and 1 <= first and first + k - 1 <= 24 and 4 <= k <= 16
    assert len(set(pairs)) == len(pairs)
    assert bench.gopro_set("quick") == [(12, 9, 8), (12, 17, 8)]  # the two
    assert bench.gopro_set("none") == []
    sample = bench.gopro_set("sample")  # k = 4, 8, 12, 16 at every fourth centre
    assert set(sample) <= set(pairs) and {k for *_, k in sample} == {4, 8, 12, 16}
    assert len(sample) == sum(len(range(1 + k // 2, 24 - (k - 1) // 2 + 1, 4))
                              for k in (4, 8, 12, 16)) == 18
    with pytest.raises(ValueError, match="quick, sample, all or none"):
        bench.gopro_set("some")


def _texture(shape, seed):
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 2.0)


def test_registration_finds_the_camera_shift_despite_a_moving_object():
    base = _texture((400, 640), 1)
    dx, dy = 13.4, -7.8  # frame(x + d) = template(x): frame(x) = template(x - d)
    m = np.float32([[1, 0, -dx], [0, 1, -dy]])
    frame = cv2.warpAffine(base, m, (640, 400), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_REFLECT)
    frame[120:300, 380:560] = _texture((180, 180), 2)  # something moved by itself
    w = bench._register(base, frame)
    np.testing.assert_allclose(w[:2, 2], [dx, dy], atol=0.25)
    np.testing.assert_allclose(w[:2, :2], np.eye(2))


def test_record_replaces_only_the_same_label_and_pair(tmp_path):
    path = tmp_path / "runs.json"
    old = [{"label": "a", "kind": "gopro", "centre": 12, "k": 8, "flagged": 0.1},
           {"label": "b", "kind": "gopro", "centre": 12, "k": 8, "flagged": 0.2},
           {"label": "a", "kind": "testbed", "case": "lens3", "far": 0.0}]
    bench.record(old, path)
    runs = bench.record([{"label": "a", "kind": "gopro", "centre": 12, "k": 8,
                          "flagged": 0.3}], path)
    assert json.loads(path.read_text()) == runs
    assert sorted((r["label"], r["kind"], r.get("flagged")) for r in runs) == [
        ("a", "gopro", 0.3), ("a", "testbed", None), ("b", "gopro", 0.2)]


class _Motion:
    def __init__(self):
        self.asked = None

    def source_points(self, xy, base):
        self.asked = np.asarray(xy)
        return np.asarray(xy) + base[:2, 2]


def _fake_reblur(monkeypatch, outcome):
    module = types.ModuleType("reblur")

    def detect_changes(reference, observed):
        if isinstance(outcome, Exception):
            raise outcome
        return outcome

    module.detect_changes = detect_changes
    monkeypatch.setitem(sys.modules, "reblur", module)


def _run_worker(tmp_path, points):
    inp, out = tmp_path / "in.npz", tmp_path / "out.npz"
    np.savez(inp, reference=np.zeros((4, 4)), observed=np.zeros((4, 4)), points=points)
    bench._worker(inp, out)
    with np.load(out) as z:
        return json.loads(str(z["meta"])), {k: z[k] for k in z.files if k != "meta"}


@pytest.mark.parametrize("exc, status", [
    (type("AlignmentError", (ValueError,), {})("no homography verified\nmore"), "refused"),
    (ValueError("degenerate homography: part of the window maps beyond the horizon"),
     "crashed"),
    (ZeroDivisionError("x"), "crashed")])
def test_worker_tells_a_refusal_from_a_crash(monkeypatch, tmp_path, exc, status):
    _fake_reblur(monkeypatch, exc)
    meta, _ = _run_worker(tmp_path, np.zeros((0, 2)))
    assert meta["status"] == status
    assert meta["reason"].startswith(type(exc).__name__ + ": ") and "\n" not in meta["reason"]


def test_worker_models_a_pixel_at_p_plus_the_field(monkeypatch, tmp_path):
    pts = np.array([[10.0, 20.0], [30.5, 4.0]])
    motion = _Motion()

    class Field:
        def displacement(self, xy):
            return np.tile([0.5, -1.5], (len(xy), 1))

    result = types.SimpleNamespace(
        change=np.zeros((4, 4), bool), unknown=np.zeros((4, 4), bool), motion=motion,
        alignment=np.array([[1.0, 0, 2.0], [0, 1, 3.0], [0, 0, 1]]), field=Field(),
        decision={"alignment": {"method": "features", "refinement": {"applied": True}}})
    _fake_reblur(monkeypatch, result)
    meta, arrays = _run_worker(tmp_path, pts)
    np.testing.assert_allclose(motion.asked, pts + [0.5, -1.5])
    np.testing.assert_allclose(arrays["source"], pts + [2.5, 1.5])
    assert meta["field"] and meta["refined"] and meta["method"] == "features"
    del result.field  # a result without a field: the homography alone
    meta, arrays = _run_worker(tmp_path, pts)
    np.testing.assert_allclose(arrays["source"], pts + [2.0, 3.0])
    assert not meta["field"]
