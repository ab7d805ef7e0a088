"""Hostile LAS/LAZ headers end in a typed error, in bounded time, before laspy reads them."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time
from pathlib import Path

import laspy
import numpy as np
import pytest

from standgrid.clouds import iter_cloud_chunks, read_cloud, read_cloud_header
from standgrid.clouds.las_header import MAX_VLRS, check_las_header
from standgrid.errors import PointCloudFormatError

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real"


def _ten_points(path: Path, version: str = "1.4", fmt: int = 6) -> bytes:
    las = laspy.create(point_format=fmt, file_version=version)
    las.x = np.arange(10.0)
    las.y = np.arange(10.0)
    las.z = np.arange(10.0)
    las.write(path)
    return path.read_bytes()


def _refused_quickly(path: Path, match: str) -> None:
    for read in (read_cloud, read_cloud_header, lambda p: list(iter_cloud_chunks(p, 4))):
        start = time.perf_counter()
        with pytest.raises(PointCloudFormatError, match=match) as info:
            read(path)
        assert time.perf_counter() - start < 1.0
        assert str(path) in str(info.value)


def test_vlr_count_of_four_billion_is_refused_at_once(tmp_path: Path) -> None:
    """The 675-byte payload that hung the service's writer (number_of_vlrs = 0xFFFFFFFF)."""
    data = bytearray(_ten_points(tmp_path / "ok.las"))
    assert len(data) == 675
    data[100:104] = b"\xff\xff\xff\xff"
    bad = tmp_path / "vlrs.las"
    bad.write_bytes(bytes(data))
    _refused_quickly(bad, "4294967295 VLRs announced")


def test_version_9_9_is_a_typed_error(tmp_path: Path) -> None:
    data = bytearray(_ten_points(tmp_path / "ok.las"))
    data[24:26] = bytes([9, 9])
    bad = tmp_path / "v99.las"
    bad.write_bytes(bytes(data))
    _refused_quickly(bad, r"version 9\.9")


def test_more_vlrs_than_any_scanner_writes_is_refused(tmp_path: Path) -> None:
    """10,001 real (empty) VLRs: laspy would parse them for seconds; the bound refuses."""
    ok = tmp_path / "ok.las"
    _ten_points(ok)
    src = laspy.read(ok)
    src.header.vlrs.extend(
        laspy.VLR(user_id="x", record_id=i, record_data=b"") for i in range(MAX_VLRS + 1)
    )
    many = tmp_path / "many.las"
    src.write(many)
    _refused_quickly(many, "VLRs announced")


def test_point_count_beyond_the_file_is_refused(tmp_path: Path) -> None:
    data = bytearray(_ten_points(tmp_path / "ok.las"))
    data[247:255] = (10**12).to_bytes(8, "little")
    bad = tmp_path / "count.las"
    bad.write_bytes(bytes(data))
    for read in (read_cloud, lambda p: list(iter_cloud_chunks(p, 4))):
        with pytest.raises(PointCloudFormatError, match="header says 1000000000000 points"):
            read(bad)
    # the header reader reports it (standgrid info lists truncated files, uncounted)
    assert "truncated" in (read_cloud_header(bad).size_problem() or "")


def test_random_bytes_after_lasf_end_in_a_typed_error_in_bounded_time(tmp_path: Path) -> None:
    """``LASF`` + 400 random bytes (version forced to 1.0-1.4 so the walk is exercised), 200
    seeds, each read in a child process that must finish within the time limit."""
    script = textwrap.dedent(
        f"""
        import numpy as np, sys
        from pathlib import Path
        from standgrid.errors import PointCloudFormatError
        from standgrid.clouds import read_cloud
        path = Path({str(tmp_path / "r.las")!r})
        typed = 0
        for seed in range(200):
            rng = np.random.default_rng(seed)
            data = bytearray(b"LASF" + rng.bytes(400))
            data[24:26] = bytes([1, seed % 5])
            path.write_bytes(bytes(data))
            try:
                read_cloud(path)
            except PointCloudFormatError:
                typed += 1
        print(typed)
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert int(done.stdout.strip()) == 200


@pytest.mark.parametrize(
    "name",
    ["las_chablais3.laz", "lidR/MixedConifer.laz", "pyfor/test.laz", "TreeLS/pine_plot.laz"],
)
def test_real_files_pass_the_check(name: str) -> None:
    path = REAL / "als" / name
    if not path.is_file():
        pytest.skip(f"{path} absent")
    facts = check_las_header(path)
    with laspy.open(path) as reader:
        assert facts.point_count == reader.header.point_count
        assert facts.vlrs == len(reader.header.vlrs)
        assert facts.compressed == reader.header.are_points_compressed
