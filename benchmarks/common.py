"""Helpers shared by the benchmarks: subprocess runs with peak RSS, machine description.

The shared data folder is ``$REBLUR_DATA`` (``python -m benchmarks.run --data DIR`` sets
it), else ``../shared/data`` beside the repository; ``DATA`` and ``LEVIR_A`` are read from
the environment when first used (:func:`data_dir`).
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

from reblur.testbed.scenes import DataMissing, require_data, shared_data_dir

REPO = Path(__file__).resolve().parents[1]


def data_dir() -> Path:
    """The shared data folder: ``$REBLUR_DATA``, else ``../shared/data`` beside the repo
    (not checked: :func:`require_data` checks what a benchmark reads)."""
    return shared_data_dir(check=False)


def __getattr__(name: str):
    # DATA and LEVIR_A follow REBLUR_DATA as it is when they are first imported
    if name == "DATA":
        return data_dir()
    if name == "LEVIR_A":
        return data_dir() / "levir_whu_1024" / "samples_LEVIR" / "A"
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["DataMissing", "REPO", "data_dir", "require_data"]


def dgemm_rate(n: int = 512, repeat: int = 7) -> float:
    """This host's single-thread DGEMM speed now, GMAC/s: the best of ``repeat`` products
    of two ``n x n`` float64 matrices (``n^3`` multiply-adds each).

    The machine line carries it because the hosts these benchmarks ran on differed in speed
    while reporting the same cores and memory: stops 70-71's host ran the estimate's Gram
    products at 18.3 GMAC/s, stop 72-73's at 11.2 (``benchmarks.gram_work``), and every
    timing moved with it.
    """
    import time

    from threadpoolctl import threadpool_limits

    a = np.random.default_rng(0).random((n, n))
    best = np.inf
    with threadpool_limits(1, user_api="blas"):
        a @ a  # first call: BLAS warm-up
        for _ in range(repeat):
            t0 = time.perf_counter()
            a @ a
            best = min(best, time.perf_counter() - t0)
    return n**3 / best / 1e9


def machine() -> str:
    """One line describing this machine, with its single-thread DGEMM speed now
    (:func:`dgemm_rate`)."""
    try:
        import psutil

        mem = f"{psutil.virtual_memory().total / 2**30:.0f} GiB RAM"
    except Exception:  # pragma: no cover
        mem = "unknown RAM"
    cpu = platform.processor() or platform.machine()
    return (
        f"{os.cpu_count()} cores ({cpu}, single-thread DGEMM {dgemm_rate():.1f} GMAC/s), "
        f"{mem}, Python {platform.python_version()}, numpy {np.__version__}, "
        f"OpenCV {cv2.__version__}"
    )


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MB (``VmHWM``: ``ru_maxrss``
    survives ``exec``, so a case started by a large parent, e.g. ``benchmarks.run`` after
    in-process benchmarks, would report the parent's size)."""
    from reblur._memory import peak_rss_mb as own

    return own()


def run_case(module: str, *args: str, timeout: float = 1800,
             blas_threads: int | None = 1) -> dict:
    """Run ``python -m module args`` in a fresh process; it prints one JSON line last.

    ``blas_threads``: ``OPENBLAS_NUM_THREADS`` of the case (None: the environment's, as a
    user's run has it; the estimate then uses the available cores).
    """
    env = dict(os.environ)
    if blas_threads is not None:
        env["OPENBLAS_NUM_THREADS"] = str(int(blas_threads))
    out = subprocess.run(
        [sys.executable, "-m", module, *args], capture_output=True, text=True, cwd=REPO,
        timeout=timeout, env=env, check=False,
    )
    if out.returncode != 0:
        raise RuntimeError(f"{module} {args} failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def release(client, cluster, work: Path) -> None:
    """Close a Dask client and cluster (either may be None) and remove a work folder."""
    import shutil

    if client is not None:
        client.close()
    if cluster is not None:
        cluster.close()
    shutil.rmtree(work, ignore_errors=True)


def compile_package(src: Path | None = None) -> None:
    """Write the bytecode of the reblur package that ``PYTHONPATH=src`` (None: this
    checkout's) imports, as ``pip install`` does: under ``PYTHONDONTWRITEBYTECODE`` (or in
    a read-only checkout) every fresh process would compile its modules again, about 0.15 s
    of each run, and a checkout compiled against one that is not would gain that much."""
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = str(src)
    code = ("import compileall, pathlib, reblur; "
            "compileall.compile_dir(pathlib.Path(reblur.__file__).parent, quiet=1)")
    subprocess.run([sys.executable, "-c", code], env=env, check=True)


def commit() -> str:
    """Short hash of ``HEAD``, with ``+dirty`` when ``src`` has uncommitted changes."""

    def git(*a):
        return subprocess.run(["git", *a], cwd=REPO, capture_output=True, text=True).stdout

    head = git("rev-parse", "--short", "HEAD").strip() or "unknown"
    dirty = bool(git("status", "--porcelain", "--untracked-files=no", "src").strip())
    return head + ("+dirty" if dirty else "")


def load_runs(path: Path) -> list[dict]:
    """The runs recorded in the JSON file ``path`` (empty if there is none)."""
    return json.loads(path.read_text()) if path.exists() else []


def save_runs(path: Path, runs: list[dict] | dict) -> None:
    """Write ``runs`` to ``path`` through a temporary file (never half-written)."""
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(runs, indent=1))
    os.replace(tmp, path)


def levir_gray(i: int = 0) -> np.ndarray:
    files = sorted(require_data(data_dir() / "levir_whu_1024" / "samples_LEVIR" / "A")
                   .glob("*.png"))
    img = cv2.imread(str(files[i]))[:, :, ::-1]
    return img.astype(np.float64).mean(axis=2) / 255.0


def psnr(a: np.ndarray, b: np.ndarray, mask=None) -> float:
    d = (a - b) if mask is None else (a - b)[mask]
    return float(10 * np.log10(1.0 / np.mean(d * d)))
