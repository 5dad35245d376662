"""Regenerate the embedded demo pair in ``src/reblur/data`` (deterministic).

Source: scikit-image's ``rocket`` image (SpaceX launch photo of DSCOVR, released into the
public domain).  The observation is the same scene seen from a slightly different
viewpoint, shaken by a smooth camera path (rotation about the image centre + translation),
with pasted changes (both polarities, one faint) and a moving object, plus noise.

Run: ``.venv/bin/python scripts/make_demo_data.py``
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import skimage.data

from reblur.simulate import make_pair

OUT = Path(__file__).resolve().parents[1] / "src" / "reblur" / "data"


def main() -> None:
    img = skimage.data.rocket().astype(np.float64) / 255.0
    pair = make_pair(
        img,
        rng=2024,
        shake=dict(t_max=5.0, rz_max=1.0),
        viewpoint=dict(max_shift_frac=0.03, max_rot_deg=3.0),
        n_changes=4,
        moving=True,
        noise_sigma=1.0 / 255.0,
    )
    OUT.mkdir(parents=True, exist_ok=True)

    def save(name, a):
        a = np.clip(np.round(np.asarray(a, np.float64) * 255), 0, 255).astype(np.uint8)
        if a.ndim == 3:
            a = cv2.cvtColor(a, cv2.COLOR_RGB2BGR)
        cv2.imwrite(str(OUT / name), a, [cv2.IMWRITE_PNG_COMPRESSION, 9])

    save("demo_reference.png", pair.reference)
    save("demo_observed.png", pair.observed)
    save("demo_truth.png", pair.truth.astype(float))
    save("demo_unknown.png", pair.unknown.astype(float))
    meta = dict(
        source="scikit-image data.rocket(): SpaceX launch photo of DSCOVR, public domain",
        path=pair.path.to_dict(),
        viewpoint=np.asarray(pair.viewpoint).tolist(),
        generator="scripts/make_demo_data.py",
    )
    (OUT / "demo_meta.json").write_text(json.dumps(meta, indent=1))
    print("wrote", sorted(p.name for p in OUT.glob("demo_*")))


if __name__ == "__main__":
    main()
