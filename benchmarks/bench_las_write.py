"""write_tile throughput against a plain laspy write of the same points, same run.

Usage: python benchmarks/bench_las_write.py [n_points]   (default 1,000,000)
Prints points/s for both and the ratio write_tile / laspy (1.0 = no overhead).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import laspy
import numpy as np
import pyproj

from standgrid.export.las import write_tile
from standgrid.pointcloud import PointCloud


def make_cloud(n: int) -> PointCloud:
    rng = np.random.default_rng(0)
    xyz = rng.uniform([500_000.0, 6_000_000.0, 100.0], [500_050.0, 6_000_050.0, 140.0], (n, 3))
    return PointCloud(
        xyz,
        {
            "intensity": rng.integers(0, 65535, n).astype(np.uint16),
            "gps_time": rng.uniform(4e8, 4.1e8, n),
            "point_source_id": np.full(n, 7, np.uint16),
            "payload_id": rng.integers(0, 5000, n).astype(np.uint32),
        },
    )


def plain_laspy(path: Path, cloud: PointCloud, laz: bool) -> None:
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.offsets = np.floor(cloud.xyz.min(axis=0))
    header.scales = np.full(3, 0.001)
    header.add_crs(pyproj.CRS("EPSG:32632"))
    header.add_extra_dim(laspy.ExtraBytesParams(name="payload_id", type="u4"))
    las = laspy.LasData(header)
    las.x, las.y, las.z = cloud.xyz[:, 0], cloud.xyz[:, 1], cloud.xyz[:, 2]
    for name in ("intensity", "gps_time", "point_source_id", "payload_id"):
        las[name] = cloud.fields[name]
    with open(path, "wb") as stream:
        las.write(
            stream, do_compress=laz, laz_backend=laspy.LazBackend.LazrsParallel if laz else None
        )


def best_of(fn, repeat: int = 3) -> float:  # type: ignore[no-untyped-def]
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000
    cloud = make_cloud(n)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for suffix in (".las", ".laz"):
            laz = suffix == ".laz"
            t_plain = best_of(
                lambda laz=laz, s=suffix: plain_laspy(folder / f"plain{s}", cloud, laz)
            )
            t_ours = best_of(
                lambda s=suffix: write_tile(folder / f"tile{s}", cloud, crs="EPSG:32632")
            )
            print(
                f"{suffix[1:].upper()} n={n:,}: laspy {n / t_plain / 1e6:.2f} Mpts/s, "
                f"write_tile {n / t_ours / 1e6:.2f} Mpts/s, ratio write_tile/laspy time "
                f"{t_ours / t_plain:.2f}"
            )


if __name__ == "__main__":
    main()
