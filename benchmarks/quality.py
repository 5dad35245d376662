"""Change-detection quality end to end (the pipeline issue's acceptance figures).

``python -m benchmarks.quality`` runs :func:`reblur.detect_changes` (all defaults) on

* the six LEVIR-CD / WHU-CD development pairs: reference = "before"; observation = "after"
  warped by a random viewpoint change and blurred along a random camera path of the
  package's simulator (rotation + translation, not on the grid), plus noise 1/255; truth =
  the building-change label carried the same way (thresholded at 0.5).  Scored against the
  plain register-then-difference baseline (:func:`reblur.baselines.register_then_difference`)
  on the same pairs.  The labels cover buildings only, so absolute JC is modest on pairs
  years apart; the gain over the baseline is what counts.
* the Fig. 6 set-up of the paper (``tests/test_pipeline.py``): a 2188 x 1315 scene of real
  imagery, viewpoint change, five pasted changes (one low-contrast) and one moving object,
  over several seeds: the spread of JC / YC / PCC, not one lucky draw.
* the GoPro frames: real hand-held blur (mean of 8 frames at 240 fps) against the 4th
  frame, no pasted change: the fraction of pixels flagged.

Prints markdown (``make bench`` writes it into ``docs/benchmarks.md``).
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from benchmarks.common import DATA
from experiments.common import dev_pairs as _pairs


def _rgb(path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_COLOR)[:, :, ::-1].astype(np.float32) / 255.0


def _row(name, m, t) -> str:
    return (f"| {name} | {m['jaccard']:.3f} | {m['yule']:.3f} | {100 * m['pcc']:.2f} | "
            f"{100 * m['fpr']:.2f} | {m['recall']:.3f} | {t:.1f} |")


def _rule(res) -> str:
    """The threshold's rule and the sampled statistic's bulk width (MAD / median)."""
    ti = res.decision.get("threshold_info", {})
    if "median" not in ti:
        return ti.get("method", "?")
    return f"{ti.get('chosen', ti.get('method'))} ({ti['mad'] / ti['median']:.2f})"


def _rules_line(rules: list[str]) -> list[str]:
    return ["", "Threshold rule (MAD / median of the sampled statistic; Otsu only from 0.4, "
            "`reblur.decide.estimate_threshold`): " + ", ".join(rules) + "."] if rules else []


def levir_table(shift_frac: float = 0.03, rot_deg: float = 3.0, align: bool = True) -> list[str]:
    import reblur
    from reblur.baselines import register_then_difference
    from reblur.metrics import change_metrics
    from reblur.simulate import blur_along_path, make_pair

    lines = ["| pair | method | JC | YC | PCC % | FPR % | recall | time (s) |",
             "|---|---|---|---|---|---|---|---|"]
    sums: dict[str, list] = {"reblur": [], "register-then-difference": []}
    rules: list[str] = []
    for i, (name, before, after, label) in enumerate(_pairs()):
        ref, aft = _rgb(before), _rgb(after)
        lab = cv2.imread(str(label), cv2.IMREAD_GRAYSCALE) > 127
        p = make_pair(ref, aft, rng=100 + i, n_changes=0, moving=False,
                      shake=dict(t_max=6.0, rz_max=0.8),
                      viewpoint=dict(max_shift_frac=shift_frac, max_rot_deg=rot_deg),
                      noise_sigma=1 / 255)
        carried, _ = blur_along_path(lab.astype(np.float32), p.path, base=p.viewpoint)
        truth = (carried.reshape(p.unknown.shape) >= 0.5) & ~p.unknown
        t = time.perf_counter()
        try:
            res = reblur.detect_changes(p.reference, p.observed, align=align)
            ours, ign = res.change, p.unknown | res.unknown
            rules.append(f"{name} {_rule(res)}")
        except ValueError as e:  # a refusal is reported, not hidden
            lines.append(f"| {name} | reblur | refused: {e} | | | | | |")
            ours = None
        t_ours = time.perf_counter() - t
        t = time.perf_counter()
        base, info = register_then_difference(p.reference, p.observed)
        t_base = time.perf_counter() - t
        if ours is not None:
            m = change_metrics(truth, ours, ignore=ign)
            sums["reblur"].append(m)
            lines.append(_row(f"{name} | reblur", m, t_ours))
        mb = change_metrics(truth, base, ignore=p.unknown | info["unknown"])
        sums["register-then-difference"].append(mb)
        lines.append(_row(f"{name} | register-then-difference", mb, t_base))
    lines.append("")
    lines.append("| mean over pairs | JC | YC | PCC % | FPR % | recall |")
    lines.append("|---|---|---|---|---|---|")
    for k, ms in sums.items():
        if ms:
            avg = {q: float(np.mean([m[q] for m in ms])) for q in ("jaccard", "yule", "pcc",
                                                                  "fpr", "recall")}
            lines.append(f"| {k} ({len(ms)} pairs) | {avg['jaccard']:.3f} | {avg['yule']:.3f} "
                         f"| {100 * avg['pcc']:.2f} | {100 * avg['fpr']:.2f} | "
                         f"{avg['recall']:.3f} |")
    return lines + _rules_line(rules)


def fig6_pair(seed: int):
    """The paper's Fig. 6 set-up for one seed (as ``tests/test_pipeline.py``): LEVIR
    "before" #1 beside pair #4's at 2188 x 1315, viewpoint change, shake, 5 pasted changes
    and a moving object, noise 1/255."""
    from reblur.simulate import make_pair

    pairs = _pairs()
    a, b = _rgb(pairs[1][1]), _rgb(pairs[4][1])
    scene = np.concatenate([a, b], axis=1)
    scene = cv2.resize(scene, (2188, 1315), interpolation=cv2.INTER_CUBIC).clip(0, 1)
    return make_pair(scene, rng=seed, shake=dict(t_max=6.0, rz_max=0.8),
                     viewpoint=dict(max_shift_frac=0.02, max_rot_deg=2.0), n_changes=5,
                     moving=True, noise_sigma=1 / 255)


def fig6_table(seeds=(6, 7, 8, 9)) -> list[str]:
    import reblur
    from reblur.metrics import change_metrics

    lines = ["| seed | JC | YC | PCC % | FP px | FN px | truth px | time (s) |",
             "|---|---|---|---|---|---|---|---|"]
    jcs = []
    rules: list[str] = []
    for s in seeds:
        p = fig6_pair(s)
        t = time.perf_counter()
        res = reblur.detect_changes(p.reference, p.observed)
        dt = time.perf_counter() - t
        m = change_metrics(p.truth, res.change, ignore=p.unknown | res.unknown)
        jcs.append(m["jaccard"])
        rules.append(f"seed {s} {_rule(res)}")
        lines.append(f"| {s} | {m['jaccard']:.3f} | {m['yule']:.3f} | {100 * m['pcc']:.2f} | "
                     f"{m['fp']} | {m['fn']} | {m['tp'] + m['fn']} | {dt:.1f} |")
    lines.append("")
    lines.append(f"JC over seeds: mean {np.mean(jcs):.3f}, min {np.min(jcs):.3f}, "
                 f"max {np.max(jcs):.3f} (the paper's Table I, synthetic: JC 0.851, YC 0.944, "
                 "PCC 99.79 %; the issue's target JC >= 0.9).")
    return lines + _rules_line(rules)


def gopro_line() -> list[str]:
    import reblur

    out = []
    for d in sorted((DATA / "gopro").glob("frames_*")):
        frames = sorted(d.glob("*.png"))[:8]
        if len(frames) < 8:
            continue
        stack = np.stack([_rgb(f) for f in frames])
        t = time.perf_counter()
        res = reblur.detect_changes(stack[3], stack.mean(axis=0).astype(np.float32))
        dt = time.perf_counter() - t
        flagged = float(res.change[~res.unknown].mean())
        out.append(f"| {d.name} | {stack.shape[2]}x{stack.shape[1]} | {100 * flagged:.2f} | "
                   f"{len(res.regions)} | {_rule(res)} | {dt:.1f} |")
    if not out:
        return []
    return ["| sequence | size | flagged % | regions | threshold rule (MAD / median) | "
            "time (s) |", "|---|---|---|---|---|---|", *out]


def main() -> str:
    parts = [
        "## Change detection quality",
        "",
        "`python -m benchmarks.quality` — `reblur.detect_changes` with all defaults.",
        "",
        "### LEVIR-CD / WHU-CD pairs: simulated viewpoint change + camera shake, real changes",
        "",
        "Viewpoint change up to 3 % of the side and 3 degrees (beyond the pose grid: the "
        "coarse alignment is needed); camera shake up to 6 px and 0.8 degree; noise 1/255. "
        "A refusal is the alignment's verification failing (an error, not a wrong mask). "
        "The baseline's registration has no verification: where it fails its mask is scored "
        "on whatever overlaps.",
        "",
        *levir_table(0.03, 3.0, align=True),
        "",
        "The same pairs with a viewpoint change within the pose grid's range (1 %, 1 degree), "
        "the coarse alignment switched off (`align=False`): what the estimate and the decision "
        "achieve when the alignment is not the bottleneck.",
        "",
        *levir_table(0.01, 1.0, align=False),
        "",
        "### Paper's Fig. 6 set-up (2188 x 1315, viewpoint, 5 pasted changes, 1 moving object)",
        "",
        *fig6_table(),
        "",
        "### GoPro: real hand-held blur, no pasted change (moving people are real changes)",
        "",
        *gopro_line(),
    ]
    return "\n".join(parts)


if __name__ == "__main__":
    print(main())
