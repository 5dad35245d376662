"""Coarse alignment on the six real LEVIR-CD / WHU-CD development pairs.

``python -m benchmarks.alignment [--cross]`` builds each pair as
:func:`benchmarks.quality.levir_table` does (reference = "before"; observation = "after"
warped by a random viewpoint change of up to 3 % / 3 degrees and blurred along a random
camera path of up to 6 px / 0.8 degree, noise 1/255, seed ``100 + index``) and runs the
pipeline's coarse alignment (:func:`reblur.pipeline.align_coarse`).  It prints a markdown
table: accepted or refused (with the reason), the method, the largest corner error
against the TRUE homography (mean camera pose composed with the viewpoint change; it
does not know the dataset's own before / after misregistration) and the time.

``--cross`` also pairs every reference with the other five observations (30 unrelated
pairs), which must all be refused.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from benchmarks.quality import _rgb
from experiments.common import dev_pairs


def _pairs():
    from reblur.grid import pose_homography
    from reblur.simulate import make_pair

    out = []
    for i, (name, before, after, _) in enumerate(dev_pairs()):
        p = make_pair(_rgb(before), _rgb(after), rng=100 + i, n_changes=0, moving=False,
                      shake=dict(t_max=6.0, rz_max=0.8),
                      viewpoint=dict(max_shift_frac=0.03, max_rot_deg=3.0), noise_sigma=1 / 255)
        H = pose_homography(*p.path.poses.mean(axis=0), center=p.path.center) @ p.viewpoint
        out.append((name, p.reference, p.observed, H / H[2, 2]))
    return out


def _corner_error(H: np.ndarray, H_true: np.ndarray, shape) -> float:
    from reblur.grid import map_points

    h, w = shape[:2]
    c = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)
    return float(np.hypot(*(map_points(H, c) - map_points(H_true, c)).T).max())


def alignment_table(cross: bool = False) -> list[str]:
    from reblur.align import AlignmentError
    from reblur.pipeline import align_coarse

    pairs = _pairs()
    lines = ["| pair | result | method | corner error (px) | gradient blocks | time (s) |",
             "|---|---|---|---|---|---|"]
    for name, ref, obs, H_true in pairs:
        t = time.perf_counter()
        try:
            a = align_coarse(ref, obs)
        except AlignmentError as e:
            parts = str(e).split("; fallback: ")
            reason = next((r for r in parts if "gradient" in r), parts[0])
            lines.append(f"| {name} | refused: {reason} | | | | {time.perf_counter() - t:.1f} |")
            continue
        lines.append(f"| {name} | aligned | {a.method} | "
                     f"{_corner_error(a.H, H_true, ref.shape):.2f} | {a.n_blocks} | "
                     f"{time.perf_counter() - t:.1f} |")
    if cross:
        accepted = []
        for i, (name, ref, _, _) in enumerate(pairs):
            for j, (other, _, obs, _) in enumerate(pairs):
                if i != j:
                    try:
                        a = align_coarse(ref, obs)
                        accepted.append(f"{name} x {other} ({a.method})")
                    except AlignmentError:
                        pass
        n = len(pairs) * (len(pairs) - 1)
        lines += ["", f"Unrelated pairs (each reference with another pair's observation): "
                      f"{n - len(accepted)} of {n} refused"
                      + (f"; accepted: {', '.join(accepted)}" if accepted else ".")]
    return lines


if __name__ == "__main__":
    print("\n".join(alignment_table(cross="--cross" in sys.argv[1:])))
