"""The embedded demo pair (regenerate with ``scripts/make_demo_data.py``)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

__all__ = ["demo_pair", "demo_paths"]

_HERE = Path(__file__).resolve().parent


def demo_paths() -> dict[str, Path]:
    """Paths of the shipped demo files: reference, observed, truth, unknown, meta."""
    return {
        k: _HERE / f"demo_{k}.{'json' if k == 'meta' else 'png'}"
        for k in ("reference", "observed", "truth", "unknown", "meta")
    }


def demo_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The demo pair as arrays.

    Returns
    -------
    reference : (H, W, 3) uint8
        A real photograph (public domain).
    observed : (H, W, 3) uint8
        The same scene, re-viewpointed, shaken, with changes.
    truth : (H, W) bool
        Where the scene changed, in the observation's frame.
    """
    p = demo_paths()
    ref = cv2.cvtColor(cv2.imread(str(p["reference"])), cv2.COLOR_BGR2RGB)
    obs = cv2.cvtColor(cv2.imread(str(p["observed"])), cv2.COLOR_BGR2RGB)
    truth = cv2.imread(str(p["truth"]), cv2.IMREAD_GRAYSCALE) > 127
    return ref, obs, truth


def demo_meta() -> dict:
    """How the demo pair was made (source, camera path, viewpoint)."""
    return json.loads(demo_paths()["meta"].read_text())
