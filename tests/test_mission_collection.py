"""MissionCollection: find missions under a root, read metadata, search, report bad metadata."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pytest
from mission_factory import make_mission

from standgrid.errors import MetadataError, MissionNotFoundError
from standgrid.mission.collection import MissionCollection
from standgrid.mission.metadata import MissionMetadata, write_metadata


def build_root(root: Path) -> None:
    make_mission(root, "2023-01-13-wytham-anymal-coyote", n_nodes=2, gnss=True)
    make_mission(root, "2023-04-21-stein-am-rhein-frontier-v15", n_nodes=2, cameras=("cam_front",))
    other = make_mission(root / "2024", "run-7", n_nodes=2, imu=True)  # nested, metadata.yaml
    write_metadata(
        MissionMetadata(
            name="run-7",
            date=dt.date(2024, 6, 2),
            place="Evo",
            robot="ANYmal",
            sensors=["lidar", "imu", "gnss"],
        ),
        other.path / "metadata.yaml",
    )
    make_mission(root / "truth", "2023-01-13-wytham-anymal-coyote", n_nodes=2)  # never a mission
    (root / "notes").mkdir()
    (root / "notes" / "readme.txt").write_text("not a mission")


def test_finds_and_reads(tmp_path: Path) -> None:
    build_root(tmp_path)
    c = MissionCollection(tmp_path)
    assert [r.name for r in c.records] == [
        "2023-01-13-wytham-anymal-coyote",
        "2023-04-21-stein-am-rhein-frontier-v15",
        "run-7",
    ]
    assert c.problems == []
    wytham, stein, evo = c.records
    assert wytham.metadata_source == "folder name" and evo.metadata_source == "metadata.yaml"
    assert (wytham.site, wytham.robot, wytham.date) == ("wytham", "anymal", dt.date(2023, 1, 13))
    assert stein.site == "stein-am-rhein" and stein.robot == "frontier"
    assert "gnss" in wytham.sensors and "lidar" in wytham.sensors
    assert evo.path == tmp_path / "2024" / "run-7"


def test_search(tmp_path: Path) -> None:
    build_root(tmp_path)
    c = MissionCollection(tmp_path)

    def names(found: list) -> list[str]:  # type: ignore[type-arg]
        return [r.name for r in found]

    assert names(c.search(site="Wytham")) == ["2023-01-13-wytham-anymal-coyote"]
    assert names(c.search(robot="anymal")) == ["2023-01-13-wytham-anymal-coyote", "run-7"]
    assert names(c.search(date_from="2023-02-01", date_to=dt.date(2024, 6, 2))) == [
        "2023-04-21-stein-am-rhein-frontier-v15",
        "run-7",
    ]
    assert names(c.search(date_to="2023-01-13")) == ["2023-01-13-wytham-anymal-coyote"]
    assert names(c.search(sensors=["imu", "gnss"])) == ["run-7"]
    assert names(c.search(robot="anymal", site="evo", sensors=["lidar"])) == ["run-7"]
    assert c.search(site="nowhere") == []
    assert len(c.search()) == 3


def test_unreadable_metadata_reported_or_raised(tmp_path: Path) -> None:
    build_root(tmp_path)
    bad = tmp_path / "2023-01-13-wytham-anymal-coyote" / "metadata.yaml"
    bad.write_text("date: [not a date\nrobot: x\n")
    c = MissionCollection(tmp_path)
    assert len(c) == 3  # kept, not skipped
    record = next(r for r in c if r.name == "2023-01-13-wytham-anymal-coyote")
    assert record.metadata is None
    assert len(c.problems) == 1 and str(bad) in c.problems[0]
    assert "2023-01-13-wytham-anymal-coyote" not in [r.name for r in c.search(site="wytham")]
    with pytest.raises(MetadataError) as info:
        MissionCollection(tmp_path, strict=True)
    assert info.value.path == bad


def test_unconventional_name_without_metadata(tmp_path: Path) -> None:
    make_mission(tmp_path, "forest-walk-b", n_nodes=2)
    c = MissionCollection(tmp_path)
    assert len(c) == 1
    assert c.records[0].metadata is None and c.records[0].date is None
    assert len(c.problems) == 1 and "no metadata.yaml" in c.problems[0]
    assert MissionCollection(tmp_path, strict=True).records[0].metadata is None
    assert c.search(site="wytham") == [] and len(c.search()) == 1


def test_vilens_date_time_name_gives_date_only(tmp_path: Path) -> None:
    make_mission(tmp_path, "2023-05-01-14-01-05", n_nodes=2)
    c = MissionCollection(tmp_path)
    assert c.problems == []
    assert c.records[0].date == dt.date(2023, 5, 1) and c.records[0].site is None
    assert len(c.search(date_from="2023-05-01", date_to="2023-05-01")) == 1
    assert c.search(site="wytham") == [] and c.search(robot="anymal") == []
    with pytest.raises(MissionNotFoundError):
        MissionCollection(tmp_path / "absent")


def test_sensor_search_matches_kinds_makes_and_models(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from standgrid.cli import cli

    models = {
        "2023-01-13-wytham-anymal-coyote": ["velodyne-vlp16", "septentrio-mosaic"],
        "2023-02-13-wytham-anymal-coyote": ["hesai-xt32", "xsens-mti"],
        "2023-03-13-wytham-frontier-v15": ["Ouster_OS0-128", "zed-f9p", "cam_front"],
        "2023-04-13-wytham-spot": ["zed2i", "imu"],
    }
    for name, sensors in models.items():
        folder = tmp_path / name
        folder.mkdir()
        (folder / "metadata.yaml").write_text("sensors: [" + ", ".join(sensors) + "]\n")
    c = MissionCollection(tmp_path)
    assert c.problems == []

    def dates(*wanted: str) -> list[int]:
        return [r.date.month for r in c.search(sensors=wanted) if r.date is not None]

    assert dates("lidar") == [1, 2, 3]
    assert dates("LiDAR", "gnss") == [1, 3]  # zed-f9p is a GNSS receiver ...
    assert dates("camera") == [3, 4]  # ... zed2i a camera
    assert dates("imu") == [2, 4]
    assert dates("velodyne") == [1] and dates("hesai-xt32") == [2] and dates("ouster") == [3]
    assert dates("radar") == []
    result = CliRunner().invoke(cli, ["missions", str(tmp_path), "--sensor", "lidar", "--json"])
    assert result.exit_code == 0, result.output
    import json

    assert len(json.loads(result.stdout)["missions"]) == 3
