"""Scores of change masks, checked against confusion matrices counted by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from reblur.metrics import (
    change_metrics,
    confusion,
    f1,
    false_positive_rate,
    jaccard,
    pcc,
    precision,
    psnr,
    recall,
    yule,
)

# truth             prediction
# 1 1 0             1 0 1
# 0 1 0             0 1 0
# by hand: TP at (0,0), (1,1); FN at (0,1); FP at (0,2); TN at (1,0), (1,2)
TRUTH = np.array([[1, 1, 0], [0, 1, 0]], bool)
PRED = np.array([[1, 0, 1], [0, 1, 0]], bool)


def test_confusion_by_hand():
    assert confusion(TRUTH, PRED) == {"tp": 2, "fp": 1, "tn": 2, "fn": 1}


def test_scores_by_hand():
    # PCC = 4/6, JC = 2/(2+1+1), precision = 2/3, recall = 2/3, NPV = 2/3,
    # YC = |2/3 + 2/3 - 1| = 1/3, F1 = 4/(4+1+1), FPR = 1/3
    assert pcc(TRUTH, PRED) == pytest.approx(4 / 6)
    assert jaccard(TRUTH, PRED) == pytest.approx(0.5)
    assert precision(TRUTH, PRED) == pytest.approx(2 / 3)
    assert recall(TRUTH, PRED) == pytest.approx(2 / 3)
    assert yule(TRUTH, PRED) == pytest.approx(1 / 3)
    assert f1(TRUTH, PRED) == pytest.approx(2 / 3)
    assert false_positive_rate(TRUTH, PRED) == pytest.approx(1 / 3)


def test_ignore_by_hand():
    ignore = np.zeros_like(TRUTH)
    ignore[0, 2] = True  # the only false positive
    # TP 2, FP 0, TN 2, FN 1: JC = 2/3, precision 1, NPV 2/3, YC = |1 + 2/3 - 1| = 2/3
    assert confusion(TRUTH, PRED, ignore) == {"tp": 2, "fp": 0, "tn": 2, "fn": 1}
    m = change_metrics(TRUTH, PRED, ignore)
    assert m["n"] == 5
    assert m["jaccard"] == pytest.approx(2 / 3)
    assert m["precision"] == pytest.approx(1.0)
    assert m["yule"] == pytest.approx(2 / 3)
    assert m["pcc"] == pytest.approx(4 / 5)
    assert m["fpr"] == pytest.approx(0.0)


def test_change_metrics_matches_single_functions():
    rng = np.random.default_rng(3)
    t = rng.random((17, 23)) < 0.3
    p = rng.random((17, 23)) < 0.4
    ig = rng.random((17, 23)) < 0.1
    m = change_metrics(t, p, ig)
    for key, fn in [("pcc", pcc), ("jaccard", jaccard), ("yule", yule), ("precision", precision),
                    ("recall", recall), ("f1", f1), ("fpr", false_positive_rate)]:
        assert m[key] == pytest.approx(fn(t, p, ig)), key
    # brute-force count
    tp = fp = tn = fn_ = 0
    for a, b, i in zip(t.ravel(), p.ravel(), ig.ravel(), strict=True):
        if i:
            continue
        tp += a and b
        fp += (not a) and b
        fn_ += a and not b
        tn += (not a) and not b
    assert (m["tp"], m["fp"], m["tn"], m["fn"]) == (tp, fp, tn, fn_)
    assert m["yule"] == pytest.approx(abs(tp / (tp + fp) + tn / (tn + fn_) - 1))


def test_degenerate_both_empty():
    # no change in truth, nothing predicted: a perfect answer
    z = np.zeros((2, 2), bool)
    m = change_metrics(z, z)
    assert (m["tp"], m["fp"], m["tn"], m["fn"]) == (0, 0, 4, 0)
    assert m["jaccard"] == 1.0 and m["f1"] == 1.0 and m["pcc"] == 1.0
    assert m["fpr"] == 0.0
    assert math.isnan(m["precision"])  # nothing predicted
    assert math.isnan(m["recall"])  # nothing to find
    assert math.isnan(m["yule"])  # TP/(TP+FP) undefined


def test_degenerate_false_alarm_on_empty_truth():
    z = np.zeros((2, 2), bool)
    p = z.copy()
    p[0, 0] = True  # TP 0, FP 1, TN 3, FN 0
    m = change_metrics(z, p)
    assert m["jaccard"] == 0.0 and m["f1"] == 0.0
    assert m["precision"] == 0.0
    assert math.isnan(m["recall"])
    assert m["yule"] == pytest.approx(0.0)  # |0 + 3/3 - 1|
    assert m["fpr"] == pytest.approx(0.25)


def test_degenerate_everything_changed_and_predicted():
    o = np.ones((2, 3), bool)
    m = change_metrics(o, o)  # TP 6
    assert m["jaccard"] == 1.0 and m["precision"] == 1.0 and m["recall"] == 1.0
    assert math.isnan(m["yule"])  # TN/(TN+FN) undefined
    assert math.isnan(m["fpr"])  # no unchanged pixel


def test_all_ignored_gives_nan():
    m = change_metrics(TRUTH, PRED, np.ones_like(TRUTH))
    assert m["n"] == 0
    for key in ("pcc", "jaccard", "yule", "precision", "recall", "f1", "fpr"):
        assert math.isnan(m[key]), key


def test_integer_masks_accepted():
    assert confusion(TRUTH.astype(np.uint8), PRED.astype(int)) == confusion(TRUTH, PRED)


@pytest.mark.parametrize(
    "t, p, ig, match",
    [
        (np.zeros((2, 2), bool), np.zeros((2, 3), bool), None, "shape"),
        (np.zeros((2, 2), bool), np.zeros((2, 2), bool), np.zeros((3, 2), bool), "ignore"),
        (np.full((2, 2), 255, np.uint8), np.zeros((2, 2), bool), None, "threshold it"),
        (np.full((2, 2), 0.7), np.zeros((2, 2), bool), None, "threshold it"),
    ],
)
def test_bad_inputs(t, p, ig, match):
    with pytest.raises(ValueError, match=match):
        confusion(t, p, ig)


def test_psnr_values():
    a = np.zeros((4, 5, 3))
    b = np.full((4, 5, 3), 0.1)  # MSE 0.01 -> 20 dB
    assert psnr(a, b) == pytest.approx(20.0)
    assert psnr(a, b * 255, data_range=255) == pytest.approx(20.0)
    assert psnr(a, a) == math.inf
    mask = np.zeros((4, 5), bool)
    mask[0, 0] = True
    c = b.copy()
    c[1:] = 1.0  # differs only outside the mask
    assert psnr(a, c, mask=mask) == pytest.approx(20.0)
    assert math.isnan(psnr(a, b, mask=np.zeros((4, 5), bool)))


def test_psnr_errors():
    with pytest.raises(ValueError, match="shape"):
        psnr(np.zeros((2, 2)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="data_range"):
        psnr(np.zeros((2, 2)), np.zeros((2, 2)), data_range=0)
    with pytest.raises(ValueError, match="mask"):
        psnr(np.zeros((2, 2)), np.zeros((2, 2)), mask=np.zeros((3, 3), bool))
