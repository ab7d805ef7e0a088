"""Seed retrieval API: by type, by map pose (cKDTree / footprint), by GNSS."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mission_factory import make_mission

from standgrid.errors import NotGeoreferencedError, PayloadNotFoundError
from standgrid.geometry import pose_matrix, transform_points
from standgrid.georeference.retrieval import retrieve_payload_by_gnss
from standgrid.mission.opening import open_mission
from standgrid.mission.retrieval import (
    footprint,
    retrieve_payload_by_pose,
    retrieve_payload_by_type,
)
from standgrid.mission.sensors import GnssFixes, write_gnss


@pytest.fixture
def mission(tmp_path: Path):  # type: ignore[no-untyped-def]
    return make_mission(
        tmp_path, n_nodes=6, spacing=10.0, gnss=True, imu=True, cameras=("front", "rear")
    )


def test_by_type(mission) -> None:  # type: ignore[no-untyped-def]
    clouds = retrieve_payload_by_type(mission.path, "point_cloud")
    assert [p.stamp for p in clouds] == mission.stamps
    assert all(p.kind == "point_cloud" and p.node_id is not None for p in clouds)
    images = retrieve_payload_by_type(mission.path, "camera")
    assert len(images) == 4 and {p.sensor for p in images} == {"front", "rear"}
    assert all(p.kind == "image" and p.path.suffix == ".png" for p in images)
    assert images[0].node_id == 0  # images share the node stamps
    imu = retrieve_payload_by_type(mission.path, "imu")
    assert len(imu) == 2 and all(p.path.parent.name == "imu" for p in imu)
    gnss = retrieve_payload_by_type(mission.path, "GNSS")
    assert [p.path.name for p in gnss] == ["fixes.txt"]
    assert retrieve_payload_by_type(mission.path, "scan") == []
    with pytest.raises(PayloadNotFoundError, match="unknown data type"):
        retrieve_payload_by_type(mission.path, "radar")


def test_by_pose_nearest_and_radius(mission) -> None:  # type: ignore[no-untyped-def]
    positions = mission.poses[:, :3, 3]
    query = positions[3] + np.array([1.0, -0.5, 0.2])
    (hit,) = retrieve_payload_by_pose(mission.path, query)
    assert hit.stamp == mission.stamps[3]
    two = retrieve_payload_by_pose(mission.path, query, k=2)
    expected = np.argsort(np.linalg.norm(positions - query, axis=1))[:2]
    assert [p.stamp for p in two] == [mission.stamps[i] for i in expected]
    pose = np.eye(4)
    pose[:3, 3] = positions[0]
    assert retrieve_payload_by_pose(mission.path, pose)[0].stamp == mission.stamps[0]
    within = retrieve_payload_by_pose(mission.path, positions[2], radius=10.5)
    assert within[0].stamp == mission.stamps[2]
    assert {p.stamp for p in within} == {mission.stamps[i] for i in (1, 2, 3)}
    with pytest.raises(PayloadNotFoundError):
        retrieve_payload_by_pose(mission.path, positions[0] + 1000.0, radius=5.0)


def test_by_pose_covering_uses_map_footprint(mission) -> None:  # type: ignore[no-untyped-def]
    m = open_mission(mission.path)
    box = footprint(m, m.payloads[0])
    cloud = m.load_payload(m.payloads[0], "map").xyz
    assert np.all(box[0] <= cloud.min(axis=0) + 1e-9) and np.all(cloud.max(axis=0) <= box[1] + 1e-9)
    # a point inside payload 0's cloud but nearer to no other node than it is covered by 0
    inside = cloud[np.argmin(np.linalg.norm(cloud - cloud.mean(axis=0), axis=1))]
    hits = retrieve_payload_by_pose(m, inside, covering=True)
    assert mission.stamps[0] in {p.stamp for p in hits}
    far = mission.poses[-1, :3, 3] + np.array([500.0, 0, 0])
    with pytest.raises(PayloadNotFoundError):
        retrieve_payload_by_pose(m, far, covering=True)
    with pytest.raises(ValueError):
        retrieve_payload_by_pose(m, [1.0, 2.0, 3.0, 4.0])


def test_by_gnss_without_gnss_is_not_georeferenced(tmp_path: Path) -> None:
    syn = make_mission(tmp_path, n_nodes=4)
    with pytest.raises(NotGeoreferencedError, match="GNSS"):
        retrieve_payload_by_gnss(syn.path, (51.77, -1.33))


def test_by_gnss_with_consistent_fixes(tmp_path: Path) -> None:
    from standgrid.georeference import enu_to_lla

    syn = make_mission(tmp_path, n_nodes=14, spacing=8.0)
    lla_ref = (51.77, -1.33, 120.0)
    yaw = 0.7
    T_enu_map = pose_matrix([30.0, -12.0, 4.0], [0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])
    enu = transform_points(T_enu_map, syn.poses[:, :3, 3])
    lat, lon, alt = enu_to_lla(enu[:, 0], enu[:, 1], enu[:, 2], lla_ref)
    k = len(syn.stamps)
    fixes = GnssFixes(
        np.array([s.ns for s in syn.stamps], dtype=np.int64),
        lat,
        lon,
        alt,
        np.full(k, 4, np.int8),
        np.full(k, 0.02),
        np.full(k, 0.05),
    )
    (syn.path / "gnss").mkdir()
    write_gnss(fixes, syn.path / "gnss" / "fixes.txt")
    (hit,) = retrieve_payload_by_gnss(syn.path, (float(lat[5]), float(lon[5]), float(alt[5])))
    assert hit.stamp == syn.stamps[5]
    two = retrieve_payload_by_gnss(syn.path, (float(lat[9]), float(lon[9])), k=2)
    assert two[0].stamp == syn.stamps[9] and two[1].stamp in {syn.stamps[8], syn.stamps[10]}


def test_by_pose_xy_query_is_horizontal(mission) -> None:  # type: ignore[no-untyped-def]
    """An (x, y) query ignores height: nodes sit ~3 m up, a 1 m radius still finds them."""
    positions = mission.poses[:, :3, 3]
    assert np.all(positions[:, 2] > 2.0)  # the nodes are well above z = 0
    xy = positions[2, :2] + np.array([0.3, -0.2])
    within = retrieve_payload_by_pose(mission.path, xy, radius=1.0)
    assert [p.stamp for p in within] == [mission.stamps[2]]
    three = retrieve_payload_by_pose(mission.path, xy, k=3)
    order = np.argsort(np.linalg.norm(positions[:, :2] - xy, axis=1), kind="stable")[:3]
    assert [p.stamp for p in three] == [mission.stamps[i] for i in order]
    # a 3-D query still measures height
    with pytest.raises(PayloadNotFoundError):
        retrieve_payload_by_pose(mission.path, np.append(xy, 0.0), radius=1.0)


def test_cli_by_pose_without_z_reports_horizontal_distance(mission) -> None:  # type: ignore[no-untyped-def]
    import json

    from click.testing import CliRunner

    from standgrid.cli import cli

    x, y, z = mission.poses[4, :3, 3]
    args = ["retrieve", "by-pose", str(mission.path), str(x + 0.6), str(y - 0.8)]
    result = CliRunner().invoke(cli, [*args, "--radius", "2", "--json"])
    assert result.exit_code == 0, result.output
    (row,) = json.loads(result.output)
    assert row["stamp"] == str(mission.stamps[4])
    assert row["distance_m"] == pytest.approx(1.0, abs=1e-6)
    full = CliRunner().invoke(cli, [*args, str(z), "--json"])
    assert json.loads(full.output)[0]["distance_m"] == pytest.approx(1.0, abs=1e-6)


def _fixed_mission(tmp_path: Path):  # type: ignore[no-untyped-def]
    """A mission whose GNSS fixes are its nodes placed exactly (known georeference)."""
    from standgrid.georeference import enu_to_lla

    syn = make_mission(tmp_path, n_nodes=14, spacing=8.0)
    lla_ref = (51.77, -1.33, 120.0)
    yaw = 0.7
    T_enu_map = pose_matrix([30.0, -12.0, 4.0], [0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])
    enu = transform_points(T_enu_map, syn.poses[:, :3, 3])
    k = len(syn.stamps)
    lat, lon, alt = enu_to_lla(enu[:, 0], enu[:, 1], enu[:, 2], lla_ref)
    fixes = GnssFixes(
        np.array([s.ns for s in syn.stamps], dtype=np.int64),
        lat,
        lon,
        alt,
        np.full(k, 4, np.int8),
        np.full(k, 0.02),
        np.full(k, 0.05),
    )
    (syn.path / "gnss").mkdir()
    write_gnss(fixes, syn.path / "gnss" / "fixes.txt")
    return syn, enu, lla_ref


def test_by_gnss_gives_each_payloads_distance(tmp_path: Path) -> None:
    """1 m (0.6 east, 0.8 north) from node 5 at its height: the distance is 1 m, in Python,
    in the CLI's --json and its human lines."""
    import json

    from click.testing import CliRunner

    from standgrid.cli import cli
    from standgrid.georeference import enu_to_lla
    from standgrid.georeference.retrieval import locate_by_gnss

    syn, enu, lla_ref = _fixed_mission(tmp_path)
    e, n, u = enu[5] + np.array([0.6, 0.8, 0.0])
    lat, lon, alt = (float(v) for v in enu_to_lla(e, n, u, lla_ref))
    found = locate_by_gnss(syn.path, (lat, lon, alt), k=2)
    assert found.payloads[0].stamp == syn.stamps[5]
    assert found.distances_m[0] == pytest.approx(1.0, abs=1e-3)
    assert found.distances_m[0] < found.distances_m[1]
    args = ["retrieve", "by-gnss", str(syn.path), repr(lat), repr(lon), repr(alt)]
    result = CliRunner().invoke(cli, [*args, "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.output)[0]["distance_m"] == pytest.approx(1.0, abs=1e-3)
    human = CliRunner().invoke(cli, args)
    assert human.exit_code == 0 and "  1.00 m  " in human.output, human.output
    # beyond --max-distance: refused
    far = CliRunner().invoke(cli, [*args, "--max-distance", "0.5"])
    assert far.exit_code == 1 and "PayloadTooFarError" in far.output


def test_by_gnss_with_latitude_and_longitude_swapped_is_refused(tmp_path: Path) -> None:
    """The bundled Wytham mission asked for (lon, lat): the nearest payload is thousands of
    km away; refused with that distance (WGS 84 geodesic) and the hint that swapped, the
    coordinate lies by a payload. ``max_distance=None`` lifts the limit."""
    import re

    from pyproj import Geod

    from standgrid.errors import PayloadTooFarError
    from tests.conftest import BUNDLED_MISSIONS

    folder = BUNDLED_MISSIONS / "2024-05-14-wytham-anymal-coyote"
    lat, lon = 51.77320, -1.33739
    assert len(retrieve_payload_by_gnss(folder, (lat, lon))) == 1  # the right order: found
    with pytest.raises(PayloadTooFarError) as caught:
        retrieve_payload_by_gnss(folder, (lon, lat))
    assert isinstance(caught.value, LookupError)
    message = str(caught.value)
    km = float(re.search(r"is ([\d,.]+) km away", message).group(1).replace(",", ""))  # type: ignore[union-attr]
    _, _, truth = Geod(ellps="WGS84").inv(lat, lon, lon, lat)  # (lon, lat) given -> (lat, lon)
    assert km == pytest.approx(truth / 1000, abs=1.0), message
    assert "swapped" in message and "latitude first" in message
    assert len(retrieve_payload_by_gnss(folder, (lon, lat), max_distance=None, k=2)) == 2
