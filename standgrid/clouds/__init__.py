"""Point-cloud files: one module per format, one registry, one LAS encoder.

``open_cloud(path)`` gives a :class:`CloudReader` (``.header``, ``.read()``,
``.chunks(n)``) for PCD (pypcd4), PLY (plyfile), LAS/LAZ and COPC (laspy); ``read_cloud``,
``read_cloud_header``, ``iter_cloud_chunks`` and ``write_cloud`` are thin functions over the
format table in :mod:`standgrid.clouds.registry`. Every LAS/LAZ file standgrid writes,
payload or tile, comes from :mod:`standgrid.clouds.las_write`.
"""

from standgrid.clouds.base import CloudHeader, CloudReader, check_cloud_file
from standgrid.clouds.registry import (
    CLOUD_EXTENSIONS,
    FORMATS,
    CloudFormat,
    iter_cloud_chunks,
    open_cloud,
    read_cloud,
    read_cloud_header,
    write_cloud,
)

__all__ = [
    "CLOUD_EXTENSIONS",
    "FORMATS",
    "CloudFormat",
    "CloudHeader",
    "CloudReader",
    "check_cloud_file",
    "iter_cloud_chunks",
    "open_cloud",
    "read_cloud",
    "read_cloud_header",
    "write_cloud",
]
