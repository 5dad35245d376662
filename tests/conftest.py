"""Shared test fixtures: real imagery from ../shared/data (never copied into the repo)."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

# keep BLAS single-threaded: pytest-xdist already runs one process per core
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
LEVIR = DATA / "levir_whu_1024" / "samples_LEVIR"
WHU = DATA / "levir_whu_1024" / "samples_WHU-CD"


def load_rgb(path: Path) -> np.ndarray:
    """Read an image as float64 RGB in [0, 1]."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FileNotFoundError(path)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return img.astype(np.float64) / (65535.0 if img.dtype == np.uint16 else 255.0)


def levir_before(i: int = 0) -> np.ndarray:
    files = sorted((LEVIR / "A").glob("*.png"))
    return load_rgb(files[i])


def levir_pairs():
    """(before, after, label) paths of the six 1024x1024 development pairs."""
    out = []
    for a in sorted((LEVIR / "A").glob("*.png")):
        out.append((a, LEVIR / "B" / a.name, LEVIR / "label" / a.name))
    for a in sorted((WHU / "prev").glob("*.png")):
        out.append((a, WHU / "curr" / a.name, WHU / "label" / a.name))
    return out


@pytest.fixture(scope="session")
def levir_rgb() -> np.ndarray:
    assert LEVIR.exists(), (
        f"real test imagery missing: {LEVIR} (../shared must sit beside the repo)"
    )
    return levir_before(0)


@pytest.fixture(scope="session")
def levir_gray(levir_rgb) -> np.ndarray:
    return levir_rgb.mean(axis=2)


@pytest.fixture
def small_disk(tmp_path):
    """A 160 KB tmpfs, a real full disk for the results or a decoded store (both larger):
    skipped where mounting is not permitted; unmounted afterwards."""
    import shutil
    import subprocess

    where = tmp_path / "disk"
    where.mkdir()
    if shutil.which("mount") is None or os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root and mount(8)")
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=160k", "tmpfs", str(where)],
                         capture_output=True, text=True)
    if res.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {res.stderr.strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)
