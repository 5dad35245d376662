"""Helpers shared by the experiments: data, camera paths, atomic output, time and memory."""

from __future__ import annotations

import argparse
import os
import platform
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from reblur.testbed.scenes import DataMissing, require_data, shared_data_dir

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "docs" / "results"


def data_dir() -> Path:
    """The shared data folder: ``$REBLUR_DATA`` (``python -m experiments.run --data DIR``
    sets it), else ``../shared/data`` beside the repository (not checked here)."""
    return shared_data_dir(check=False)


def __getattr__(name: str):
    # DATA, LEVIR and WHU follow REBLUR_DATA as it is when they are first imported
    subs = {"DATA": (), "LEVIR": ("levir_whu_1024", "samples_LEVIR"),
            "WHU": ("levir_whu_1024", "samples_WHU-CD")}
    if name in subs:
        return data_dir().joinpath(*subs[name])
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["DataMissing", "OUT", "REPO", "data_dir", "require_data"]


# ---------------------------------------------------------------------------- data
def load_rgb(path: Path) -> np.ndarray:
    """Read an 8-bit image as float32 RGB in [0, 1].

    Raises
    ------
    FileNotFoundError
        When the file cannot be read (the data sit in ``../shared/data`` beside the repo).
    """
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise FileNotFoundError(f"cannot read {path} (../shared/data must sit beside the repo)")
    return img[:, :, ::-1].astype(np.float32) / 255.0


def dev_pairs() -> list[tuple[str, Path, Path, Path]]:
    """``(name, before, after, label)`` of the six LEVIR-CD / WHU-CD development pairs.

    Same order as ``benchmarks/quality.py`` (so the seeds ``100 + index`` match it).
    """
    levir = require_data(data_dir() / "levir_whu_1024" / "samples_LEVIR")
    whu = require_data(data_dir() / "levir_whu_1024" / "samples_WHU-CD")
    out = []
    for a in sorted((levir / "A").glob("*.png")):
        out.append((f"LEVIR {a.stem}", a, levir / "B" / a.name, levir / "label" / a.name))
    for a in sorted((whu / "prev").glob("*.png")):
        out.append((f"WHU {a.stem}", a, whu / "curr" / a.name, whu / "label" / a.name))
    if not out:
        raise DataMissing(f"no development pair found in {levir} or {whu}: the shared data "
                          "is incomplete")
    return out


def gray_images() -> list[tuple[str, np.ndarray]]:
    """The six "before" images of the development pairs, grayscale float32, 1024 x 1024."""
    return [(name, np.ascontiguousarray(load_rgb(b).mean(axis=2), dtype=np.float32))
            for name, b, _, _ in dev_pairs()]


def test_image(index: int, side: int) -> tuple[str, np.ndarray]:
    """A real grayscale test image of ``side x side`` pixels (1000 or 2000).

    ``side <= 1024``: the central crop of development image ``index``.  ``side = 2000``: a
    2 x 2 mosaic of the central 1000 x 1000 crops of images ``index .. index + 3`` (cycled):
    real pixels throughout, no resampling.
    """
    imgs = gray_images()
    n = len(imgs)

    def crop(i: int, s: int) -> np.ndarray:
        a = imgs[i % n][1]
        y0, x0 = (a.shape[0] - s) // 2, (a.shape[1] - s) // 2
        return a[y0 : y0 + s, x0 : x0 + s]

    if side <= 1024:
        return imgs[index % n][0], np.ascontiguousarray(crop(index, side))
    if side != 2000:
        raise ValueError(f"side must be <= 1024 or 2000, got {side}")
    t = [crop(index + k, 1000) for k in range(4)]
    mosaic = np.block([[t[0], t[1]], [t[2], t[3]]])
    names = "+".join(imgs[(index + k) % n][0].split()[-1] for k in range(4))
    return f"mosaic {names}", np.ascontiguousarray(mosaic, dtype=np.float32)


def centred_box(shape: tuple[int, int], side: int) -> tuple[int, int, int, int]:
    """``(y0, x0, h, w)`` of the ``side x side`` window centred in ``shape``."""
    h, w = shape
    return ((h - side) // 2, (w - side) // 2, side, side)


# ---------------------------------------------------------------------------- output
def sweep_parser(name: str, description: str | None) -> argparse.ArgumentParser:
    """Command line of an images x camera-paths sweep: ``--full``, ``--images``, ``--paths``,
    ``--out``; see :func:`sweep_sizes`."""
    ap = argparse.ArgumentParser(prog=f"python -m experiments.{name}", description=description)
    ap.add_argument("--full", action="store_true", help="the paper's 5 images x 5 paths")
    ap.add_argument("--images", type=int, default=None, help="images (default 3)")
    ap.add_argument("--paths", type=int, default=None, help="camera paths (default 2)")
    ap.add_argument("--out", type=Path, default=OUT)
    return ap


def sweep_sizes(args: argparse.Namespace) -> tuple[int, int]:
    """``(images, paths)`` of a sweep: explicit counts, else 5 x 5 with ``--full``, else 3 x 2."""
    return args.images or (5 if args.full else 3), args.paths or (5 if args.full else 2)


def write_text(path: Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (:func:`reblur.io.atomic_path`)."""
    from reblur.io import atomic_path

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


def save_figure(fig, path: Path) -> Path:
    """Save a matplotlib figure as PNG atomically and close it."""
    import matplotlib.pyplot as plt

    from reblur.io import atomic_path

    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    finally:
        plt.close(fig)
    return path


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def md_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> list[str]:
    """Markdown table lines."""
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(v) for v in r) + " |" for r in rows]
    return out


def machine() -> str:
    """One line describing this machine and the main library versions."""
    import psutil

    return (
        f"{os.cpu_count()} cores ({platform.machine()}), "
        f"{psutil.virtual_memory().total / 2**30:.0f} GiB RAM, Python "
        f"{platform.python_version()}, numpy {np.__version__}, OpenCV {cv2.__version__}; "
        f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}"
    )


def fmt(v: float, digits: int = 3) -> str:
    """A number for a table: fixed digits, ``n/a`` for NaN/None."""
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "n/a"
    return f"{v:.{digits}f}"


# ---------------------------------------------------------------------------- measurement
@dataclass
class Measured:
    """What :func:`measure` returns: the call's value, wall time and memory."""

    value: Any
    seconds: float
    peak_rss_mb: float  #: highest sampled resident set size of this process during the call
    start_rss_mb: float  #: resident set size when the call started


def measure(fn: Callable[[], Any], interval: float = 0.02) -> Measured:
    """Run ``fn()``, timing it and sampling this process's RSS every ``interval`` seconds.

    The peak is sampled (psutil, a background thread), so a spike shorter than
    ``interval`` can be missed; ``start_rss_mb`` shows what was resident before the call
    (the inputs and earlier work), so ``peak - start`` is what the call itself added.
    """
    import psutil

    proc = psutil.Process()
    start = proc.memory_info().rss
    peak = [start]
    stop = threading.Event()

    def sample() -> None:
        while not stop.is_set():
            peak[0] = max(peak[0], proc.memory_info().rss)
            stop.wait(interval)

    th = threading.Thread(target=sample, daemon=True)
    th.start()
    t0 = time.perf_counter()
    try:
        value = fn()
    finally:
        dt = time.perf_counter() - t0
        stop.set()
        th.join()
    peak[0] = max(peak[0], proc.memory_info().rss)
    return Measured(value, dt, peak[0] / 2**20, start / 2**20)


def strong_rotation_path(seed: int, shape: tuple[int, int], *, t_max: float = 5.0,
                         rz_max: float = 2.5):
    """A smooth random camera path with strong roll (about the full image's centre).

    :func:`reblur.simulate.random_camera_path` with 64 time samples, translations up to
    ``t_max`` px and roll up to ``rz_max`` degrees (the paper's grid spans +-12 px and
    +-3 degrees).
    """
    from reblur.simulate import random_camera_path

    h, w = shape
    return random_camera_path(seed, center=((w - 1) / 2.0, (h - 1) / 2.0), t_max=t_max,
                              rz_max=rz_max)


def code_version() -> str:
    """Commit of the working tree, and whether ``src/reblur`` had uncommitted changes."""
    import subprocess

    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, text=True,
                              capture_output=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "src/reblur"], cwd=REPO,
                               text=True, capture_output=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown commit"
    return f"commit {head}" + (" + uncommitted changes in src/reblur" if dirty else "")


def fig6_pair(seed: int = 6):
    """The paper's Fig. 6 set-up, built as ``tests/test_pipeline.py`` builds it.

    A 2188 x 1315 RGB scene (LEVIR "before" #1 beside development pair #4's "before",
    resized), viewpoint change up to 2 % / 2 degrees, camera shake up to 6 px / 0.8 degree,
    five pasted changes (one low-contrast) and one object moving during the exposure, noise
    1/255 (:func:`reblur.simulate.make_pair`).
    """
    from reblur.simulate import make_pair

    pairs = dev_pairs()
    a, b = load_rgb(pairs[1][1]), load_rgb(pairs[4][1])
    scene = np.concatenate([a, b], axis=1)
    scene = cv2.resize(scene, (2188, 1315), interpolation=cv2.INTER_CUBIC).clip(0, 1)
    return make_pair(scene, rng=seed, shake=dict(t_max=6.0, rz_max=0.8),
                     viewpoint=dict(max_shift_frac=0.02, max_rot_deg=2.0), n_changes=5,
                     moving=True, noise_sigma=1 / 255)


def outcome_rgb(truth: np.ndarray, pred: np.ndarray, unknown: np.ndarray) -> np.ndarray:
    """Colour map of a mask's outcome: TP white, FP red, FN blue, TN black, unknown gray."""
    out = np.zeros(truth.shape + (3,), np.float32)
    out[truth & pred] = (1.0, 1.0, 1.0)
    out[~truth & pred] = (1.0, 0.15, 0.15)
    out[truth & ~pred] = (0.2, 0.45, 1.0)
    out[unknown] = (0.35, 0.35, 0.35)
    return out
