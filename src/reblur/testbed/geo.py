"""Real georeferenced pairs: one image as GeoTIFFs in two CRSs, resampled by GDAL.

A real aerial image is given a projected CRS (UTM zone 33N by default) and a north-up
geotransform, then reprojected with GDAL's warper (``rasterio.warp.reproject``, bilinear) into
another CRS and pixel size: Web Mercator, a neighbouring UTM zone, or longitude/latitude.  The
two files show the same ground in two pixel grids related by a change of map projection, which
is what a user's GeoTIFFs from two providers look like.  The geometry comes from PROJ and GDAL
only; nothing here uses reblur's own georeferencing code (:mod:`reblur.align.georef`), so the pairs
can test it.

Pixel values: the image in ``[0, 1]`` is stored as float32 ``(v * 255 + 1) / 256`` (so in
``[1/256, 1]``) and 0 marks only the no-data corners the reprojection leaves.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["DEFAULT_ORIGIN", "GeoPair", "geo_pair", "reproject_geotiff", "write_georeferenced"]

#: Top-left corner (easting, northing, metres) in UTM zone 33N: about 45.1 N, 17.8 E, 2.8
#: degrees east of the zone's central meridian, so a neighbouring zone (34N) sees the scene
#: turned by about 4 degrees.
DEFAULT_ORIGIN = (720_000.0, 5_000_000.0)


@dataclass(frozen=True)
class GeoPair:
    """Two GeoTIFFs of the same ground.

    Attributes
    ----------
    reference : pathlib.Path
        The image in its original CRS and pixel grid.
    observation : pathlib.Path
        The same image reprojected into another CRS (and pixel size), 0 outside its footprint.
    """

    reference: Path
    observation: Path


def write_georeferenced(
    image: np.ndarray,
    path: str | Path,
    *,
    crs: str = "EPSG:32633",
    pixel: float = 0.5,
    origin: tuple[float, float] = DEFAULT_ORIGIN,
) -> Path:
    """Write a single-band image as a north-up GeoTIFF.

    Parameters
    ----------
    image : numpy.ndarray
        ``(H, W)`` values in ``[0, 1]``.
    path : str or pathlib.Path
        Output file.
    crs : str
        Projected CRS of the image.
    pixel : float
        Pixel size in the CRS's units.
    origin : (float, float)
        Map coordinates of the top-left corner of the top-left pixel.

    Returns
    -------
    pathlib.Path
    """
    import rasterio
    from affine import Affine

    image = np.asarray(image, dtype=np.float64)
    if image.ndim != 2:
        raise ValueError(f"write_georeferenced takes a grey (H, W) image, got {image.shape}")
    data = ((np.clip(image, 0.0, 1.0) * 255.0 + 1.0) / 256.0).astype(np.float32)
    transform = Affine(pixel, 0.0, origin[0], 0.0, -pixel, origin[1])
    path = Path(path)
    with rasterio.open(path, "w", driver="GTiff", height=data.shape[0], width=data.shape[1],
                       count=1, dtype="float32", crs=crs, transform=transform,
                       nodata=0.0) as dst:
        dst.write(data, 1)
    return path


def reproject_geotiff(
    src_path: str | Path,
    dst_path: str | Path,
    crs: str,
    *,
    resolution: float | None = None,
) -> Path:
    """Reproject a single-band GeoTIFF into ``crs`` with GDAL's bilinear warper.

    Parameters
    ----------
    src_path, dst_path : str or pathlib.Path
        Input and output files.
    crs : str
        Target CRS.
    resolution : float, optional
        Square pixel size in the target CRS's units (degrees for EPSG:4326).  Default: GDAL's
        choice, about as many pixels as the input.

    Returns
    -------
    pathlib.Path
    """
    import rasterio
    from rasterio.warp import Resampling, calculate_default_transform, reproject

    with rasterio.open(src_path) as src:
        data = src.read(1)
        transform, width, height = calculate_default_transform(
            src.crs, crs, src.width, src.height, *src.bounds, resolution=resolution)
        out = np.zeros((height, width), dtype=np.float32)
        reproject(data, out, src_transform=src.transform, src_crs=src.crs, src_nodata=0.0,
                  dst_transform=transform, dst_crs=crs, dst_nodata=0.0,
                  resampling=Resampling.bilinear)
    dst_path = Path(dst_path)
    with rasterio.open(dst_path, "w", driver="GTiff", height=height, width=width, count=1,
                       dtype="float32", crs=crs, transform=transform, nodata=0.0) as dst:
        dst.write(out, 1)
    return dst_path


def geo_pair(
    image: np.ndarray,
    out_dir: str | Path,
    *,
    obs_crs: str = "EPSG:3857",
    obs_resolution: float | None = None,
    ref_crs: str = "EPSG:32633",
    pixel: float = 0.5,
    origin: tuple[float, float] = DEFAULT_ORIGIN,
) -> GeoPair:
    """Write ``image`` as a reference GeoTIFF and its reprojection as the observation.

    Parameters
    ----------
    image : numpy.ndarray
        ``(H, W)`` values in ``[0, 1]`` (a real image, e.g. a grey LEVIR-CD tile).
    out_dir : str or pathlib.Path
        Existing folder for ``reference.tif`` and ``observation.tif``.
    obs_crs : str
        CRS of the observation.
    obs_resolution : float, optional
        Pixel size of the observation in ``obs_crs`` units (see :func:`reproject_geotiff`).
    ref_crs, pixel, origin
        Georeferencing of the reference (see :func:`write_georeferenced`).

    Returns
    -------
    GeoPair
    """
    out_dir = Path(out_dir)
    ref = write_georeferenced(image, out_dir / "reference.tif", crs=ref_crs, pixel=pixel,
                              origin=origin)
    obs = reproject_geotiff(ref, out_dir / "observation.tif", obs_crs,
                            resolution=obs_resolution)
    return GeoPair(reference=ref, observation=obs)
