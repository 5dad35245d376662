"""Sensor model: Poisson-Gaussian noise, quantisation to 8/12/16 bit, optional JPEG.

An image in [0, 1] (the irradiance, scaled so that 1 is full scale) becomes a photo-electron
count ``Poisson(x * full_well)``, read out with Gaussian read noise and quantised:
``DN = round(clip(e / full_well + N(0, read_noise_dn / M), 0, 1) * M)`` with
``M = 2**bits - 1``.  The noise variance in DN is therefore
``x * M**2 / full_well + read_noise_dn**2`` (shot + read).  8-bit output may then be JPEG
compressed with OpenCV.  reblur's simulator adds plain Gaussian noise; this model's noise
depends on the signal, as a real sensor's does.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["apply_sensor", "full_scale", "jpeg", "output_dtype", "quantise"]

_BITS = (8, 12, 16)


def full_scale(bits: int) -> int:
    """Largest digital number of a bit depth: 255, 4095 or 65535.

    Parameters
    ----------
    bits : int
        8, 12 or 16.

    Returns
    -------
    int
    """
    if bits not in _BITS:
        raise ValueError(f"bits must be one of {_BITS}, got {bits!r}")
    return 2**bits - 1


def output_dtype(bits: int) -> np.dtype:
    """Storage dtype of a bit depth: uint8 for 8, uint16 for 12 and 16."""
    full_scale(bits)
    return np.dtype(np.uint8 if bits == 8 else np.uint16)


def quantise(image: np.ndarray, bits: int) -> np.ndarray:
    """Round an image in [0, 1] to integers ``0..2**bits - 1`` (values outside are clipped).

    Parameters
    ----------
    image : numpy.ndarray
        Float image, nominally in [0, 1].
    bits : int
        8, 12 or 16 (12-bit is stored in uint16 with maximum 4095).

    Returns
    -------
    numpy.ndarray
        uint8 or uint16.
    """
    m = full_scale(bits)
    dn = np.rint(np.clip(np.asarray(image, dtype=np.float64), 0.0, 1.0) * m)
    return dn.astype(output_dtype(bits))


def jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    """JPEG-compress and decode an 8-bit gray or RGB image with OpenCV.

    Parameters
    ----------
    image : numpy.ndarray
        uint8 ``(H, W)`` or ``(H, W, 3)`` (RGB order).
    quality : int
        JPEG quality 1..100.

    Returns
    -------
    numpy.ndarray
        uint8 of the same shape.
    """
    if image.dtype != np.uint8:
        raise ValueError("JPEG is 8-bit only: use bits=8 or jpeg_quality=None")
    if not 1 <= int(quality) <= 100:
        raise ValueError(f"jpeg quality must be in 1..100, got {quality}")
    rgb = image.ndim == 3
    bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if rgb else image
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError(f"OpenCV could not JPEG-encode an image of shape {image.shape}")
    if not rgb:
        return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def apply_sensor(
    image: np.ndarray,
    rng: np.random.Generator,
    *,
    bits: int = 8,
    read_noise_dn: float = 0.0,
    full_well: float = 0.0,
    jpeg_quality: int | None = None,
) -> np.ndarray:
    """Add Poisson-Gaussian noise, quantise and optionally JPEG-compress.

    Parameters
    ----------
    image : numpy.ndarray
        Float image in [0, 1], gray or RGB.
    rng : numpy.random.Generator
        Seeded generator.
    bits : int
        Output bit depth: 8, 12 or 16.
    read_noise_dn : float
        Read-noise standard deviation in DN of the output bit depth; 0 disables it.
    full_well : float
        Photo-electrons at full scale (the gain): shot-noise variance in [0, 1] units is
        ``x / full_well``; 0 disables shot noise.
    jpeg_quality : int, optional
        JPEG quality (8-bit only); None for no compression.

    Returns
    -------
    numpy.ndarray
        uint8 (8-bit) or uint16 (12- and 16-bit) image.
    """
    m = full_scale(bits)
    if read_noise_dn < 0 or full_well < 0:
        raise ValueError("read_noise_dn and full_well must be >= 0 (0 disables that noise)")
    if jpeg_quality is not None and bits != 8:
        raise ValueError("JPEG is 8-bit only: use bits=8 or jpeg_quality=None")
    x = np.clip(np.asarray(image, dtype=np.float64), 0.0, 1.0)
    if full_well > 0:
        x = rng.poisson(x * full_well) / full_well
    if read_noise_dn > 0:
        x = x + rng.normal(0.0, read_noise_dn / m, size=x.shape)
    out = quantise(x, bits)
    return out if jpeg_quality is None else jpeg(out, jpeg_quality)
