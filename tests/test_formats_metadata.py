"""Mission names, rosbag names and metadata.yaml."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pytest
import yaml

from standgrid.errors import MissionNameError
from standgrid.mission.metadata import (
    KNOWN_ROBOTS,
    MissionMetadata,
    MissionName,
    metadata_from_folder_name,
    parse_mission_name,
    parse_rosbag_name,
    read_metadata,
    register_robot,
    write_metadata,
)


@pytest.mark.parametrize(
    "name, place, robot, unit",
    [
        ("2023-01-13-wytham-anymal-coyote", "wytham", "anymal", "coyote"),
        ("2023-04-21-stein-am-rhein-frontier-v15", "stein-am-rhein", "frontier", "v15"),
        ("2023-04-21-stein-am-rhein-frontier", "stein-am-rhein", "frontier", None),
        ("2022-09-01-spot-hill-husky", "spot-hill", "husky", None),  # last known robot wins
        ("2024-06-02-evo-forest-mulebot-frn015", "evo-forest", "mulebot", "frn015"),  # unit rule
        ("2024-06-02-evo-forest-mulebot", "evo-forest", "mulebot", None),  # last-token rule
    ],
)
def test_parse_mission_name(name: str, place: str, robot: str, unit: str | None) -> None:
    parsed = parse_mission_name(name)
    assert (parsed.place, parsed.robot, parsed.unit) == (place, robot, unit)
    assert parsed.date == dt.date.fromisoformat(name[:10])
    assert str(parsed) == name


def test_parse_mission_name_with_time_and_path() -> None:
    parsed = parse_mission_name("/data/missions/2024-03-26_13-47-27-wytham-spot")
    assert parsed == MissionName(dt.date(2024, 3, 26), "wytham", "spot", None, dt.time(13, 47, 27))


def test_register_robot_changes_the_split() -> None:
    name = "2023-05-05-forest-walker-alpha"
    assert parse_mission_name(name).robot == "alpha"
    register_robot("Walker")
    try:
        assert parse_mission_name(name) == MissionName(
            dt.date(2023, 5, 5), "forest", "walker", "alpha"
        )
    finally:
        KNOWN_ROBOTS.discard("walker")


@pytest.mark.parametrize(
    "bad", ["2023-13-01-wytham-anymal", "2023-02-30-a-b", "wytham-anymal", "2023-01-13-anymal"]
)
def test_parse_mission_name_errors(bad: str) -> None:
    with pytest.raises(MissionNameError):
        parse_mission_name(bad)


def test_parse_rosbag_name() -> None:
    bag = parse_rosbag_name("coyote-2023-01-13-10-33-05-lidar.bag")
    assert (bag.robot_id, bag.date, bag.time, bag.tag) == (
        "coyote",
        dt.date(2023, 1, 13),
        dt.time(10, 33, 5),
        "lidar",
    )
    plain = parse_rosbag_name("frn015_2024-03-26_13-47-27.mcap")
    assert plain.robot_id == "frn015" and plain.tag is None and plain.extension == "mcap"
    with pytest.raises(MissionNameError):
        parse_rosbag_name("notabag.txt")


def test_metadata_round_trip_exact(tmp_path: Path) -> None:
    meta = MissionMetadata(
        name="2023-04-21-stein-am-rhein-frontier-v15",
        date=dt.date(2023, 4, 21),
        place="stein-am-rhein",
        robot="frontier",
        unit="v15",
        time=dt.time(10, 33, 5, 250000),
        gnss=(47.6597123456789, 8.8593, 401.25),
        sensors=["lidar", "gnss", "cam_front"],
        tags=["spring", "leaf-off"],
        notes="Plot 3, wet ground.\nSecond line.",
        extra={"operator": "ab", "battery": [0.9, 0.4]},
    )
    out = tmp_path / "metadata.yaml"
    write_metadata(meta, out)
    assert read_metadata(out) == meta
    doc = yaml.safe_load(out.read_text())
    assert doc["date"] == dt.date(2023, 4, 21) and doc["gnss"]["latitude"] == 47.6597123456789


def test_metadata_unknown_keys_kept_and_time_forms(tmp_path: Path) -> None:
    path = tmp_path / "metadata.yaml"
    path.write_text(
        "date: '2023-01-13'\nplace: wytham\nrobot: anymal\ntime: 10:33:05\nweather: rain\n"
    )
    meta = read_metadata(path)
    assert meta.name == "2023-01-13-wytham-anymal"
    assert meta.time == dt.time(10, 33, 5)  # YAML 1.1 base-60 integer understood
    assert meta.extra == {"weather": "rain"} and meta.gnss is None


def test_metadata_from_folder_name_infers_sensors(tmp_path: Path) -> None:
    folder = tmp_path / "2023-01-13-wytham-anymal-coyote"
    for sub in ("payload_clouds", "gnss", "payloads/imu", "payloads/cameras/cam_left"):
        (folder / sub).mkdir(parents=True)
    meta = metadata_from_folder_name(folder)
    assert (meta.place, meta.robot, meta.unit) == ("wytham", "anymal", "coyote")
    assert meta.sensors == ["lidar", "gnss", "imu", "cam_left"]
    assert metadata_from_folder_name(folder.name, sensors=["x"]).sensors == ["x"]


BASE_YAML = "date: '2023-01-13'\nplace: wytham\nrobot: anymal\n"


@pytest.mark.parametrize(
    ("gnss", "message"),
    [
        ("{latitude: 51.7, longitude: -1.3}", "missing 'altitude'"),
        ("{latitude: 51.7, longitude: -1.3, altitude: .nan}", "must be finite"),
        ("{latitude: 51.7, longitude: -1.3, altitude: .inf}", "must be finite"),
        ("[.nan, -1.3, 100.0]", "must be finite"),
        ("[91.0, -1.3, 100.0]", "out of range"),
    ],
)
def test_metadata_gnss_needs_finite_lat_lon_alt(tmp_path: Path, gnss: str, message: str) -> None:
    from standgrid.errors import MetadataError
    from standgrid.mission.metadata import read_metadata

    path = tmp_path / "metadata.yaml"
    path.write_text(BASE_YAML + f"gnss: {gnss}\n")
    with pytest.raises(MetadataError, match=message) as info:
        read_metadata(path)
    assert info.value.path == path and info.value.line == 4


def test_metadata_path_that_is_a_folder_is_a_typed_error(tmp_path: Path) -> None:
    from standgrid.errors import MetadataError
    from standgrid.mission.metadata import read_metadata

    (tmp_path / "metadata.yaml").mkdir()
    with pytest.raises(MetadataError, match="cannot read") as info:
        read_metadata(tmp_path / "metadata.yaml")
    assert isinstance(info.value.__cause__, OSError)
