"""Core value types: errors, stamps, poses, point clouds, atomic outputs."""

from __future__ import annotations

from datetime import UTC
from pathlib import Path

import numpy as np
import pytest

from standgrid import _atomic, errors
from standgrid._atomic import atomic_output
from standgrid.geometry import (
    invert_pose,
    pose_matrix,
    relative_pose,
    transform_points,
    translation_quat,
    yaw_of,
)
from standgrid.pointcloud import PointCloud
from standgrid.stamps import Stamp, stamp_from_filename, unix_ns_to_adjusted_gps_time


def test_every_error_has_one_root_and_names_file_and_line() -> None:
    classes = [getattr(errors, n) for n in errors.__all__]
    assert all(issubclass(c, errors.StandgridError) for c in classes)
    err = errors.PoseGraphFormatError("bad token", path="g.slam", line=7)
    assert str(err) == "g.slam:7: bad token"
    assert isinstance(err, ValueError)
    missing = errors.MissionNotFoundError("no such mission", path="/x")
    assert isinstance(missing, FileNotFoundError) and str(missing) == "/x: no such mission"


def test_stamps_compare_as_integers_and_round_trip_file_names() -> None:
    name = "cloud_1583840261_039995392.pcd"
    prefix, stamp, ext = stamp_from_filename(name)  # type: ignore[misc]
    assert (prefix, ext) == ("cloud", "pcd")
    assert stamp == Stamp.parse("1583840261", "39995392")  # unpadded, as in graphs
    assert stamp.filename("cloud", "pcd") == name
    assert Stamp.from_ns(stamp.ns) == stamp
    assert stamp_from_filename("cloud_1.pcd") is None
    with pytest.raises(ValueError):
        Stamp.parse(1, 1_000_000_000)


def test_adjusted_gps_time() -> None:
    # 2017-01-01T00:00:00Z = UNIX 1483228800; GPS seconds = UNIX - 315964800 + 18.
    gps = unix_ns_to_adjusted_gps_time(1483228800 * 10**9 + 500_000_000)
    assert gps == pytest.approx(1483228800 - 315964800 + 18 - 1e9 + 0.5, abs=1e-6)


def test_poses_compose_invert_and_split() -> None:
    rng = np.random.default_rng(0)
    q = rng.normal(size=(5, 4))
    t = rng.normal(size=(5, 3)) * 1e5
    poses = pose_matrix(t, q)
    assert np.allclose(invert_pose(poses) @ poses, np.eye(4), atol=1e-9)
    t2, q2 = translation_quat(poses)
    assert np.allclose(t2, t)
    assert np.allclose(pose_matrix(t2, q2), poses, atol=1e-12)
    edge = relative_pose(poses[0], poses[1])
    assert np.allclose(poses[0] @ edge, poses[1])
    yaw = pose_matrix([0, 0, 0], [0, 0, np.sin(0.4), np.cos(0.4)])
    assert yaw_of(yaw) == pytest.approx(0.8)
    pts = rng.normal(size=(10, 3))
    assert np.allclose(transform_points(yaw, pts), (yaw[:3, :3] @ pts.T).T)


def test_pointcloud_keeps_float64_and_checks_fields() -> None:
    cloud = PointCloud(np.ones((3, 3), dtype=np.float32), {"intensity": np.arange(3)})
    assert cloud.xyz.dtype == np.float64 and len(cloud) == 3
    with pytest.raises(ValueError, match="field 'i'"):
        PointCloud(np.ones((3, 3)), {"i": np.arange(2)})
    both = PointCloud.concat([cloud, cloud.select([0])])
    assert len(both) == 4 and list(both.fields["intensity"]) == [0, 1, 2, 0]
    with pytest.raises(ValueError, match="cannot concatenate"):
        PointCloud.concat([cloud, PointCloud(np.ones((1, 3)))])


def test_atomic_output_leaves_nothing_half_written(tmp_path) -> None:
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_output(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("crash")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]
    with pytest.raises(errors.OutputExistsError), atomic_output(target, overwrite=False):
        pass
    with atomic_output(target) as tmp:
        tmp.write_text("new")
    assert target.read_text() == "new"


def test_adjusted_gps_time_uses_the_leap_seconds_of_its_date() -> None:
    from datetime import datetime

    from standgrid.stamps import GPS_EPOCH_UNIX, GPS_LEAP_SECONDS

    def unix(y: int, m: int, d: int) -> int:
        return int(datetime(y, m, d, tzinfo=UTC).timestamp())

    stamps = {unix(2010, 3, 10): 15, unix(2020, 3, 10): 18, unix(1980, 6, 1): 0}
    stamps[unix(2017, 1, 1) - 1] = 17  # the last second before the 18th leap second
    ns = np.array([s * 1_000_000_000 + 250_000_000 for s in stamps], dtype=np.int64)
    gps = unix_ns_to_adjusted_gps_time(ns)
    for got, (sec, leap) in zip(gps, stamps.items(), strict=True):
        assert got == pytest.approx(sec - GPS_EPOCH_UNIX + leap - 1e9 + 0.25, abs=1e-6)
    assert GPS_LEAP_SECONDS == 18
    assert float(unix_ns_to_adjusted_gps_time(ns[1])) == pytest.approx(gps[1])


@pytest.mark.parametrize("kind", ["file", "folder"])
def test_no_overwrite_never_replaces_what_another_writer_made_meanwhile(
    tmp_path: Path, kind: str
) -> None:
    """overwrite=False is checked when the output is put in place, not only at the start:
    a file or folder another process created meanwhile is kept, this writer refused."""
    target = tmp_path / "out"
    with pytest.raises(errors.OutputExistsError), atomic_output(target, overwrite=False) as tmp:
        if kind == "file":
            tmp.write_text("mine")
            target.write_text("theirs")  # the other writer lands first
        else:
            tmp.mkdir()
            (tmp / "a.txt").write_text("mine")
            target.mkdir()
            (target / "a.txt").write_text("theirs")
    kept = target if kind == "file" else target / "a.txt"
    assert kept.read_text() == "theirs"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no temporary left behind
    fresh = tmp_path / "fresh"
    with atomic_output(fresh, overwrite=False) as tmp:
        tmp.write_text("new")
    assert fresh.read_text() == "new"


def test_atomic_folder_replace_rolls_back_when_the_new_folder_cannot_move_in(
    tmp_path, monkeypatch
) -> None:
    import os

    target = tmp_path / "out"
    target.mkdir()
    (target / "a.txt").write_text("old")
    real_replace = os.replace
    calls: list[tuple[object, object]] = []

    def fail_second(src, dst) -> None:  # type: ignore[no-untyped-def]
        calls.append((src, dst))
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", fail_second)
    # the two-rename path of file systems without an atomic exchange (renameat2)
    monkeypatch.setattr(_atomic, "exchange", lambda a, b: False)
    with (
        pytest.raises(errors.OutputNotWritableError, match="into place") as info,
        atomic_output(target, replaces=_is_out_folder, what="an out folder") as tmp,
    ):
        tmp.mkdir()
        (tmp / "a.txt").write_text("new")
    assert info.value.path == target
    assert isinstance(info.value.__cause__, OSError)
    assert (target / "a.txt").read_text() == "old"  # the old output is back in place
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no stranded temporaries
    monkeypatch.setattr(os, "replace", real_replace)
    with atomic_output(target, replaces=_is_out_folder, what="an out folder") as tmp:
        tmp.mkdir()
        (tmp / "a.txt").write_text("new")
    assert (target / "a.txt").read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
    # a folder of other things is never replaced: overwriting replaces only what it makes
    (target / "a.txt").unlink()
    (target / "notes.txt").write_text("mine")
    with (
        pytest.raises(errors.OutputExistsError, match="not an out folder"),
        atomic_output(target, replaces=_is_out_folder, what="an out folder") as tmp,
    ):
        tmp.mkdir()
    with (  # a file output onto a folder
        pytest.raises(errors.OutputExistsError, match="is a folder with files"),
        atomic_output(target) as tmp,
    ):
        tmp.write_text("new")
    assert [p.name for p in target.iterdir()] == ["notes.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
    empty = tmp_path / "empty"
    empty.mkdir()
    with (  # a file output onto an empty folder: a typed error, the folder stays
        pytest.raises(errors.OutputExistsError, match="is a folder"),
        atomic_output(empty) as tmp,
    ):
        tmp.write_text("new")
    assert empty.is_dir() and not any(empty.iterdir())


def _is_out_folder(path: Path) -> bool:
    return (path / "a.txt").is_file()
