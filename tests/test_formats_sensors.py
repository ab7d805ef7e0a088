"""GNSS and IMU text logs, per-payload GNSS concatenation and lazy image loading."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from standgrid.mission.sensors import (
    FixQuality,
    GnssFixes,
    ImageRef,
    ImuSamples,
    concat_gnss,
    load_image,
    read_gnss,
    read_imu,
    write_gnss,
    write_imu,
)
from standgrid.stamps import Stamp


def _fixes(n: int, start_ns: int, seed: int = 0) -> GnssFixes:
    rng = np.random.default_rng(seed)
    return GnssFixes(
        stamps_ns=start_ns + np.arange(n, dtype=np.int64) * 100_000_000,
        lat=51.77 + rng.normal(0, 1e-4, n),
        lon=-1.33 + rng.normal(0, 1e-4, n),
        alt=120 + rng.normal(0, 1, n),
        quality=rng.choice([1, 2, 4, 5], n).astype(np.int8),
        h_std=rng.uniform(0.01, 2, n),
        v_std=np.where(rng.random(n) < 0.2, np.nan, rng.uniform(0.02, 3, n)),
    )


def test_gnss_round_trip_exact(tmp_path: Path) -> None:
    fixes = _fixes(200, 1_700_000_000 * 10**9 + 7)
    out = tmp_path / "gnss" / "fixes.txt"
    write_gnss(fixes, out)
    assert out.read_text().splitlines()[0] == (
        "# sec, nsec, latitude, longitude, altitude, quality, h_std, v_std"
    )
    back = read_gnss(out)
    np.testing.assert_array_equal(back.stamps_ns, fixes.stamps_ns)
    for name in ("lat", "lon", "alt", "h_std", "v_std", "quality"):
        np.testing.assert_array_equal(getattr(back, name), getattr(fixes, name))
    assert back.quality.dtype == np.int8 and back.source == out


def test_gnss_whitespace_without_std_columns(tmp_path: Path) -> None:
    path = tmp_path / "fixes.txt"
    path.write_text(
        "# a comment line that is not a header\n"
        "1700000000 5 51.5 -1.25 100.5 4\n"
        "1700000001 500000000   51.6  -1.26  101.0  0\n"
    )
    fixes = read_gnss(path)
    assert len(fixes) == 2
    np.testing.assert_array_equal(
        fixes.stamps_ns, [1_700_000_000_000_000_005, 1_700_000_001_500_000_000]
    )
    assert fixes.quality.tolist() == [FixQuality.RTK_FIXED, FixQuality.INVALID]
    assert np.isnan(fixes.h_std).all() and np.isnan(fixes.v_std).all()


def test_gnss_header_order_and_invalid_fix_nan(tmp_path: Path) -> None:
    path = tmp_path / "fixes.csv"
    path.write_text(
        "#sec,nsec,quality,latitude,longitude,altitude\n"
        "10,0,1,45.0,7.0,300\n"
        "11,0,0,nan,nan,nan\n"  # an invalid fix may have no position
    )
    fixes = read_gnss(path)
    assert fixes.quality.tolist() == [1, 0]
    assert fixes.lat[0] == 45.0 and np.isnan(fixes.lat[1])


def test_gnss_header_only_is_empty_log(tmp_path: Path) -> None:
    path = tmp_path / "gnss_1_000000000.txt"
    path.write_text("# sec, nsec, latitude, longitude, altitude, quality, h_std, v_std\n")
    assert len(read_gnss(path)) == 0


def test_concat_gnss_sorts_and_drops_exact_duplicates(tmp_path: Path) -> None:
    a = _fixes(10, 2_000 * 10**9, seed=1)
    b = _fixes(10, 1_000 * 10**9, seed=2)
    overlap = GnssFixes(
        *(
            getattr(a, n)[:3]
            for n in ("stamps_ns", "lat", "lon", "alt", "quality", "h_std", "v_std")
        )
    )
    for k, part in enumerate((a, b, overlap)):
        write_gnss(part, tmp_path / f"gnss_{k}.txt")
    parts = [read_gnss(tmp_path / f"gnss_{k}.txt") for k in range(3)]
    joined = concat_gnss(parts)
    assert len(joined) == 20
    assert np.all(np.diff(joined.stamps_ns) > 0)
    np.testing.assert_array_equal(joined.lat[:10], b.lat)
    np.testing.assert_array_equal(joined.lat[10:], a.lat)
    assert len(concat_gnss(parts, drop_exact_duplicates=False)) == 23
    assert len(concat_gnss([])) == 0


def test_imu_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    n = 500
    samples = ImuSamples(
        stamps_ns=1_600_000_000 * 10**9 + np.arange(n, dtype=np.int64) * 2_500_000,
        accel=rng.normal([0, 0, 9.81], 0.1, (n, 3)),
        gyro=rng.normal(0, 0.01, (n, 3)),
    )
    out = tmp_path / "imu_1600000000_000000000.txt"
    write_imu(samples, out)
    back = read_imu(out)
    np.testing.assert_array_equal(back.stamps_ns, samples.stamps_ns)
    np.testing.assert_array_equal(back.accel, samples.accel)
    np.testing.assert_array_equal(back.gyro, samples.gyro)


def test_imu_without_header_commas(tmp_path: Path) -> None:
    path = tmp_path / "imu.txt"
    path.write_text("5,1,0.1,0.2,9.8,0.01,0.02,0.03\n")
    imu = read_imu(path)
    np.testing.assert_array_equal(imu.gyro, [[0.01, 0.02, 0.03]])


def test_load_image_png(tmp_path: Path) -> None:
    pixels = np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3)
    path = tmp_path / "image_1_000000005.png"
    Image.fromarray(pixels).save(path)
    ref = ImageRef("cam_front", Stamp(1, 5), path)
    np.testing.assert_array_equal(load_image(ref), pixels)


def test_load_image_missing_and_corrupt(tmp_path: Path) -> None:
    from standgrid.errors import FormatError, MissionNotFoundError

    with pytest.raises(MissionNotFoundError):
        load_image(ImageRef("cam", Stamp(1, 0), tmp_path / "none.png"))
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not an image")
    with pytest.raises(FormatError, match=r"bad\.png"):
        load_image(ImageRef("cam", Stamp(1, 0), bad))


def _one_fix(stamp_ns: int, lat: float) -> GnssFixes:
    return GnssFixes(
        np.array([stamp_ns], np.int64),
        np.array([lat]),
        np.array([-1.33]),
        np.array([120.0]),
        np.array([4], np.int8),
        np.array([np.nan]),
        np.array([0.05]),
    )


def test_concat_gnss_drops_duplicates_not_adjacent_after_stamp_sort() -> None:
    """A, B, A' (same stamp, A == A'): the copy of A is dropped though B sits between them."""
    t = 1_700_000_000 * 10**9
    a, b = _one_fix(t, 51.5), _one_fix(t, 51.4)
    joined = concat_gnss([a, b, a, _one_fix(t - 5, 51.6)])
    assert len(joined) == 3
    assert joined.stamps_ns.tolist() == [t - 5, t, t]
    # stable by stamp: the rows keep the order they were first logged in (A before B)
    assert joined.lat.tolist() == [51.6, 51.5, 51.4]
    assert len(concat_gnss([a, b, a], drop_exact_duplicates=False)) == 3


def test_concat_imu_sorts_by_stamp_and_keeps_every_row(tmp_path: Path) -> None:
    from standgrid.mission.sensors import concat_imu

    parts = [
        ImuSamples(np.array([30, 10], np.int64), np.ones((2, 3)), np.zeros((2, 3)), tmp_path / "a"),
        ImuSamples(np.array([20, 10], np.int64), np.full((2, 3), 2.0), np.zeros((2, 3))),
    ]
    joined = concat_imu(parts)
    assert joined.stamps_ns.tolist() == [10, 10, 20, 30]
    assert joined.accel[:, 0].tolist() == [1.0, 2.0, 2.0, 1.0]
    assert joined.source == tmp_path
    assert len(concat_imu([])) == 0


def test_sensor_log_path_that_is_a_folder_is_a_typed_error(tmp_path: Path) -> None:
    from standgrid.errors import MissionNotFoundError, SensorLogFormatError

    folder = tmp_path / "fixes.txt"
    folder.mkdir()
    for reader in (read_gnss, read_imu):
        with pytest.raises(SensorLogFormatError, match="cannot read") as info:
            reader(folder)
        assert info.value.path == folder and isinstance(info.value.__cause__, OSError)
        with pytest.raises(MissionNotFoundError):
            reader(tmp_path / "absent.txt")
