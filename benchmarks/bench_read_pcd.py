"""Time read_cloud on a 1,000,000-point binary PCD against baselines measured in the same run.

Baselines: raw ``np.fromfile`` of the same bytes with the structured dtype (the floor), and
pypcd4's own ``PointCloud.from_path`` (what read_cloud wraps). Target: read_cloud well under 1 s.

    python benchmarks/bench_read_pcd.py [--points 1000000] [--repeat 5]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from pypcd4 import PointCloud as PcdCloud

from standgrid.clouds import read_cloud, write_cloud
from standgrid.pointcloud import PointCloud


def best_of(repeat: int, fn: Callable[[], object]) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()

    rng = np.random.default_rng(0)
    n = args.points
    cloud = PointCloud(
        rng.uniform(-50, 50, (n, 3)).astype(np.float32),
        {"intensity": rng.uniform(0, 255, n).astype(np.float32)},
    )
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.pcd"
        write_cloud(cloud, path, encoding="binary")
        raw = path.read_bytes()
        data_offset = raw.index(b"DATA binary\n") + len(b"DATA binary\n")
        dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])

        def raw_fromfile() -> np.ndarray:
            with path.open("rb") as fp:
                fp.seek(data_offset)
                return np.fromfile(fp, dtype=dtype, count=n)

        check = read_cloud(path)
        assert len(check) == n and np.array_equal(check.xyz, cloud.xyz)

        t_raw = best_of(args.repeat, raw_fromfile)
        t_pypcd4 = best_of(args.repeat, lambda: PcdCloud.from_path(path))
        t_read = best_of(args.repeat, lambda: read_cloud(path))

    print(f"points: {n:,}  file: {len(raw) / 1e6:.1f} MB  best of {args.repeat}")
    print(f"np.fromfile (floor)    {t_raw:8.4f} s")
    print(f"pypcd4 from_path       {t_pypcd4:8.4f} s")
    print(f"standgrid read_cloud   {t_read:8.4f} s")
    print(f"ratio read_cloud / np.fromfile: {t_read / t_raw:6.2f}")
    print(f"ratio read_cloud / pypcd4:      {t_read / t_pypcd4:6.2f}")
    print(f"target (< 1 s): {'met' if t_read < 1.0 else 'NOT met'}")


if __name__ == "__main__":
    main()
