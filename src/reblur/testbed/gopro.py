"""Real camera-shake blur from consecutive high-speed GoPro frames.

Averaging ``k`` consecutive 240 fps frames of a hand-held camera (GoPro dataset, Nah et al.
2017, sequence GOPR0477_11_00 in the shared data folder) gives a genuinely blurred frame:
real 6-D shake, rolling shutter, lens distortion and moving objects, none of it modelled.
The centre frame is the sharp reference.  Unlike every other source of pairs (reblur's
simulator or this test bed's renderer), no homography model is involved at all.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .scenes import require_data, shared_data_dir

__all__ = ["N_FRAMES", "gopro_frame", "gopro_frame_indices", "gopro_pair"]

N_FRAMES = 24


def _frames_dir() -> Path:
    return require_data(shared_data_dir() / "gopro" / "frames_GOPR0477_11_00")


def gopro_frame_indices(centre: int, k: int) -> list[int]:
    """Frame numbers (1-based) averaged for a centre frame and a count ``k``.

    For odd ``k`` the window is ``centre - (k - 1) / 2 .. centre + (k - 1) / 2``; for even
    ``k`` it is ``centre - k / 2 .. centre + k / 2 - 1`` (one more frame before the centre).

    Parameters
    ----------
    centre : int
        Reference frame, 1..24.
    k : int
        Number of frames averaged, 1..24.

    Returns
    -------
    list of int
    """
    if not 1 <= int(k) <= N_FRAMES:
        raise ValueError(f"k must be in 1..{N_FRAMES} frames, got {k}")
    if not 1 <= int(centre) <= N_FRAMES:
        raise ValueError(f"centre must be a frame number in 1..{N_FRAMES}, got {centre}")
    first = int(centre) - int(k) // 2
    frames = list(range(first, first + int(k)))
    if frames[0] < 1 or frames[-1] > N_FRAMES:
        lo, hi = 1 + int(k) // 2, N_FRAMES - (int(k) - 1) // 2
        raise ValueError(f"frames {frames[0]}..{frames[-1]} fall outside 1..{N_FRAMES}: "
                         f"for k={k} choose centre in {lo}..{hi}")
    return frames


def gopro_frame(index: int) -> np.ndarray:
    """One GoPro frame (1-based index) as uint8 RGB ``(720, 1280, 3)``."""
    if not 1 <= int(index) <= N_FRAMES:
        raise ValueError(f"frame index must be in 1..{N_FRAMES}, got {index}")
    path = _frames_dir() / f"{int(index):06d}.png"
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise FileNotFoundError(f"cannot read {path}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def gopro_pair(centre: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """A real blurred pair: the centre frame and the mean of ``k`` frames around it.

    Parameters
    ----------
    centre : int
        Reference frame, 1..24.
    k : int
        Number of consecutive frames averaged (see :func:`gopro_frame_indices`).

    Returns
    -------
    reference : numpy.ndarray
        uint8 RGB centre frame.
    observation : numpy.ndarray
        uint8 RGB ``rint(mean of the k frames)``.
    """
    frames = gopro_frame_indices(centre, k)
    acc = gopro_frame(frames[0]).astype(np.float64)
    for i in frames[1:]:
        acc += gopro_frame(i)
    observation = np.rint(acc / len(frames)).astype(np.uint8)
    return gopro_frame(int(centre)), observation
