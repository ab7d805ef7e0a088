"""Mission names, rosbag names and metadata.yaml."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pytest
import yaml

from standgrid.errors import MissionNameError
from standgrid.mission.metadata import (
    MissionMetadata,
    metadata_from_folder_name,
    read_metadata,
    write_metadata,
)
from standgrid.mission.mission_name import (
    KNOWN_ROBOTS,
    MissionName,
    parse_mission_name,
    parse_rosbag_name,
    register_robot,
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


# --- every name form of docs/MISSION_FORMAT.md, and lenient metadata of other tools ----------


@pytest.mark.parametrize(
    "name, date, time, place, robot, unit, tag",
    [
        # VILENS logger (ROS 1): date and time only
        ("2023-05-01-14-01-05", "2023-05-01", "14:01:05", None, None, None, None),
        # ROS 2 VILENS / Frontier: date_time_recNNN_site
        ("2024-03-26_13-47-27_rec004_site", "2024-03-26", "13:47:27", "site", None, None, "rec004"),
        (
            "2024-03-26_13-47-27_rec012_stein_am_rhein",
            "2024-03-26",
            "13:47:27",
            "stein-am-rhein",
            None,
            None,
            "rec012",
        ),
        ("2024-03-26_13-47-27_site", "2024-03-26", "13:47:27", "site", None, None, None),
        # the convention YYYY-MM-DD-<place>-<robot>[-<unit>]
        ("2023-01-13-wytham-anymal-coyote", "2023-01-13", None, "wytham", "anymal", "coyote", None),
        ("2024-06-01-bcts-anymal-coyote", "2024-06-01", None, "bcts", "anymal", "coyote", None),
        (
            "2023-04-21-stein-am-rhein-frontier-v15",
            "2023-04-21",
            None,
            "stein-am-rhein",
            "frontier",
            "v15",
            None,
        ),
        # a folder named like its rosbag: RobotID-Date-Time-AdditionalTag
        (
            "coyote-2023-01-13-10-33-05-lidar",
            "2023-01-13",
            "10:33:05",
            None,
            "coyote",
            None,
            "lidar",
        ),
    ],
)
def test_every_documented_name_form_parses(
    name: str,
    date: str,
    time: str | None,
    place: str | None,
    robot: str | None,
    unit: str | None,
    tag: str | None,
) -> None:
    parsed = parse_mission_name(name)
    assert parsed.date == dt.date.fromisoformat(date)
    assert parsed.time == (None if time is None else dt.time.fromisoformat(time))
    assert (parsed.place, parsed.robot, parsed.unit, parsed.tag) == (place, robot, unit, tag)


def _mission_yaml(tmp_path: Path, folder: str, text: str) -> Path:
    path = tmp_path / folder / "metadata.yaml"
    path.parent.mkdir(parents=True)
    path.write_text(text)
    return path


def test_another_tools_metadata_is_read_and_completed_from_the_folder_name(
    tmp_path: Path,
) -> None:
    path = _mission_yaml(
        tmp_path,
        "2024-06-01-bcts-anymal-coyote",
        "mission_id: 7f3a-22\n"
        "robot_id: coyote\n"
        "platform: anymal\n"
        "start_time: 2024-06-01T10:33:05Z\n"
        "sensors:\n  lidar: hesai-xt32\n  gnss: septentrio-mosaic\n  imu: {model: xsens-mti}\n"
        "operator: jb\n",
    )
    meta = read_metadata(path)
    assert meta.date == dt.date(2024, 6, 1) and meta.time == dt.time(10, 33, 5)
    assert meta.robot == "coyote" and meta.place == "bcts" and meta.unit == "coyote"
    assert meta.sensors == ["hesai-xt32", "septentrio-mosaic", "xsens-mti"]
    # unknown keys and the unused robot synonym are kept
    assert meta.extra == {"mission_id": "7f3a-22", "platform": "anymal", "operator": "jb"}
    assert meta.name == "2024-06-01-bcts-anymal-coyote"
    assert meta.sources == {
        "date": "start_time",
        "robot": "robot_id",
        "sensors": "sensors",
        "place": "folder name",
        "unit": "folder name",
        "name": "folder name",
    }
    # written back in our own layout, it reads back the same
    write_metadata(meta, tmp_path / "again.yaml")
    again = read_metadata(tmp_path / "again.yaml")
    assert again == meta


@pytest.mark.parametrize(
    "text, date, time",
    [
        ("timestamp: 1717238000123456789\n", "2024-06-01", "10:33:20.123457"),  # UNIX ns
        ("timestamp: 1717238000.5\n", "2024-06-01", "10:33:20.500000"),  # UNIX s
        ("datetime: '2024-06-01 10:33:05'\n", "2024-06-01", "10:33:05"),
        ("date: 20240601\n", "2024-06-01", None),
        ("recording_date: 01.06.2024\ntime: '10:33:05'\n", "2024-06-01", "10:33:05"),
        ("start_time: {sec: 1717238000, nsec: 0}\n", "2024-06-01", "10:33:20"),
    ],
)
def test_date_synonyms_and_forms(tmp_path: Path, text: str, date: str, time: str | None) -> None:
    meta = read_metadata(_mission_yaml(tmp_path, "plot-7", text + "site: bcts\nrobot: spot\n"))
    assert meta.date == dt.date.fromisoformat(date)
    assert meta.time == (None if time is None else dt.time.fromisoformat(time))
    assert (meta.place, meta.robot) == ("bcts", "spot")


def test_sensor_lists_of_mappings_and_location_as_position(tmp_path: Path) -> None:
    meta = read_metadata(
        _mission_yaml(
            tmp_path,
            "2023-05-01-14-01-05",
            "location: {lat: 49.1, lon: -123.2, alt: 100.5}\n"
            "sensors:\n"
            "  - {name: front, model: ouster-os0, type: lidar}\n"
            "  - {name: cam_left, type: camera}\n"
            "  - gnss\n"
            "tags: spring, leaf-off\n",
        )
    )
    assert meta.gnss == (49.1, -123.2, 100.5) and meta.place is None and meta.robot is None
    assert meta.sensors == ["ouster-os0", "cam_left", "gnss"]
    assert meta.tags == ["spring", "leaf-off"]
    assert meta.date == dt.date(2023, 5, 1) and meta.sources["date"] == "folder name"


def test_only_an_underivable_date_is_an_error(tmp_path: Path) -> None:
    from standgrid.errors import MetadataError

    path = _mission_yaml(tmp_path, "plot-7", "robot_id: coyote\nsite: bcts\n")
    with pytest.raises(MetadataError, match="missing key 'date'") as info:
        read_metadata(path)
    assert info.value.key == "date" and info.value.path == path and "plot-7" in str(info.value)
    assert isinstance(info.value, ValueError)
    # the same file beside a conventional name is complete
    meta = read_metadata(path, folder_name="2024-06-01-bcts-anymal-coyote")
    assert meta.date == dt.date(2024, 6, 1) and meta.robot == "coyote"


def test_a_present_but_wrong_value_names_its_key_and_line(tmp_path: Path) -> None:
    from standgrid.errors import MetadataError

    path = _mission_yaml(tmp_path, "2024-06-01-bcts-anymal", "robot: spot\nstart_time: soon\n")
    with pytest.raises(MetadataError, match="start_time: not a date") as info:
        read_metadata(path)
    assert info.value.key == "start_time" and info.value.line == 2
