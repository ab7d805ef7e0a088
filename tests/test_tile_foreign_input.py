"""Missions as other tools and robots write them, tiled with no change to their files:
another tool's metadata.yaml and held-out folder names, clouds already in a projected CRS
(PCD in payload_clouds_in_utm/, LAS with a CRS), and a mission without GNSS placed by an
explicit anchor. Every tiled point is matched to its source point by (payload stamp,
intensity) and compared with where the GNSS-fitted tiling (or the simulator's truth) puts it."""

from __future__ import annotations

import hashlib
import json
import math
import shutil
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pyogrio
import pytest
from click.testing import CliRunner

from standgrid.cli import cli
from standgrid.clouds import write_cloud
from standgrid.errors import CRSError, GeoreferenceError
from standgrid.geometry import yaw_of
from standgrid.georeference import MapProjector, georeference_mission
from standgrid.mission.opening import open_mission
from standgrid.pipeline.tile import tile_missions
from standgrid.pointcloud import PointCloud
from standgrid.simulate import simulate_mission
from standgrid.stamps import Stamp
from standgrid.tiling.options import TileOptions
from tests.conftest import BUNDLED_MISSIONS

CRS = "EPSG:32630"
Points = dict[tuple[Stamp, float], np.ndarray]


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Any:
    root = tmp_path_factory.mktemp("foreign")
    made = simulate_mission(root, seed=7, area=60.0, points_per_payload=2000)
    made_root = root
    return made, made_root


@pytest.fixture(scope="module")
def reference(sim: Any) -> dict[str, Points]:
    """The simulator's own mission tiled with its GNSS fit: the placement to reproduce."""
    made, root = sim
    catalog = root / "reference"
    tile_missions([made.mission_dir], catalog, TileOptions(crs=CRS, laz=False))
    return tiled_points(catalog)


def tiled_points(catalog: Path, only: str | None = None) -> dict[str, Points]:
    """mission -> {(payload stamp, intensity): xyz} of every point in the catalog's tiles
    (``only``: of that mission)."""
    payloads = pyogrio.read_dataframe(catalog / "index.gpkg", layer="payloads")
    key = {
        int(r.payload_id): (r.mission, Stamp(int(r.stamp_sec), int(r.stamp_nsec)))
        for r in payloads.itertuples()
    }
    out: dict[str, Points] = {}
    for path in sorted(catalog.glob("tiles/*/*.la[sz]")):
        las = laspy.read(path)
        xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
        for pid, value, p in zip(las.payload_id, las.intensity_raw, xyz, strict=True):
            mission, stamp = key[int(pid)]
            if only is not None and mission != only:
                continue
            points = out.setdefault(mission, {})
            assert (stamp, float(value)) not in points, "intensity must identify a point"
            points[(stamp, float(value))] = p
    return out


def max_distance(got: Points, want: Points) -> tuple[float, float]:
    """(largest horizontal, largest vertical) distance of matched points; same point sets."""
    assert got.keys() == want.keys()
    keys = list(want)
    diff = np.array([got[k] for k in keys]) - np.array([want[k] for k in keys])
    return float(np.hypot(diff[:, 0], diff[:, 1]).max()), float(np.abs(diff[:, 2]).max())


def digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


# --- another tool's metadata and held-out names ------------------------------------------------

OTHER_TOOL_YAML = {
    # robot_id instead of robot, no place, extra keys, sensors as a mapping of models
    "2024-05-14-bcts-anymal-coyote": (
        "mission_id: 7f3a-22\nrobot_id: coyote\nplatform: anymal\n"
        "start_time: 2024-05-14T09:35:23Z\n"
        "sensors:\n  lidar: velodyne-vlp16\n  gnss: septentrio-mosaic\n"
    ),
    # the ROS 2 VILENS / Frontier name; no date in the file at all
    "2024-05-14_09-35-23_rec004_site": "robot_name: anymal\nsensors: [hesai-xt32, imu]\n",
    # the VILENS logger's name, and no metadata.yaml
    "2024-05-14-09-35-23": None,
}


def test_held_out_missions_with_another_tools_metadata_tile_unchanged(
    sim: Any, reference: dict[str, Points], tmp_path: Path
) -> None:
    made, _ = sim
    folders = []
    for name, text in OTHER_TOOL_YAML.items():
        folder = tmp_path / "missions" / name
        shutil.copytree(made.mission_dir, folder)
        (folder / "metadata.yaml").unlink()
        if text is not None:
            (folder / "metadata.yaml").write_text(text)
        folders.append(folder)
    before = {f.name: digest(f) for f in folders}

    result = CliRunner().invoke(
        cli, ["tile", *map(str, folders), "-o", str(tmp_path / "cat"), "--las", "-q", "--json"]
    )
    assert result.exit_code == 0, result.output
    assert {f.name: digest(f) for f in folders} == before  # no file changed

    tiled = tiled_points(tmp_path / "cat")
    want = reference[made.name]
    for folder in folders:
        horizontal, vertical = max_distance(tiled[folder.name], want)
        assert horizontal < 1e-9 and vertical < 1e-9  # the same fit, the same points
    missions = pyogrio.read_dataframe(tmp_path / "cat" / "index.gpkg", layer="missions")
    row = {r.mission: r for r in missions.itertuples()}
    assert (
        row["2024-05-14-bcts-anymal-coyote"].robot,
        row["2024-05-14-bcts-anymal-coyote"].place,
    ) == ("coyote", "bcts")
    assert row["2024-05-14_09-35-23_rec004_site"].place == "site"
    assert {str(r.epoch) for r in missions.itertuples()} == {"2024"}
    # the lidar is found by kind whatever the metadata calls it
    found = CliRunner().invoke(
        cli, ["missions", str(tmp_path / "missions"), "--sensor", "lidar", "--json"]
    )
    assert found.exit_code == 0 and found.stdout.count('"name"') == 3


# --- clouds already in a projected CRS ---------------------------------------------------------


def _projected_copy(made: Any, folder: Path, fmt: str, subfolder: str) -> Path:
    """A mission holding only graph, metadata and the payloads projected (with the GNSS
    fit the reference tiling uses) into the catalog CRS: no GNSS, no base-frame clouds."""
    mission = open_mission(made.mission_dir)
    projector = MapProjector(georeference_mission(mission), CRS)
    folder.mkdir(parents=True)
    for name in ("metadata.yaml", "slam_pose_graph.g2o"):
        shutil.copy(made.mission_dir / name, folder / name)
    (folder / subfolder).mkdir()
    for payload in mission.payloads:
        cloud = mission.load_payload(payload, "map")
        xyz = projector.exact(cloud.xyz)
        out = PointCloud(xyz, dict(cloud.fields))
        path = folder / subfolder / payload.stamp.filename("cloud", fmt)
        if fmt in ("pcd", "ply"):
            write_cloud(out, path)  # float64 x y z (large coordinates)
        else:
            intensity = out.fields.pop("intensity")
            write_cloud(PointCloud(xyz, {"intensity_raw": intensity}), path, crs=CRS)
    return folder


@pytest.mark.parametrize(
    "fmt, subfolder", [("pcd", "payload_clouds_in_utm"), ("las", "payload_clouds")]
)
def test_projected_clouds_tile_where_the_gnss_fit_puts_them(
    sim: Any, reference: dict[str, Points], tmp_path: Path, fmt: str, subfolder: str
) -> None:
    made, _ = sim
    folder = _projected_copy(made, tmp_path / made.name, fmt, subfolder)
    mission = open_mission(folder)
    assert mission.is_projected and mission.gnss is None
    if fmt == "pcd":
        with pytest.raises(CRSError, match="option crs"):
            tile_missions([folder], tmp_path / "no-crs", TileOptions())
        options = TileOptions(crs=CRS, laz=False)
    else:
        assert {p.crs.text for p in mission.payloads if p.crs is not None} == {CRS}
        assert all(p.crs is not None for p in mission.payloads)
        options = TileOptions(laz=False)  # the LAS files name their CRS
    report = tile_missions([folder], tmp_path / "cat", options).to_dict()
    assert report["crs"] == CRS
    assert report["missions"][made.name]["georeference"]["method"] == "projected"
    horizontal, vertical = max_distance(
        tiled_points(tmp_path / "cat")[made.name], reference[made.name]
    )
    print(
        f"\n{fmt}: largest distance to the GNSS-fitted tiling: horizontal "
        f"{horizontal * 1000:.2f} mm, vertical {vertical * 1000:.2f} mm"
    )
    # both sides snap to the tiles' 1 mm lattice; the reference projects through a verified
    # affine (within 1 mm of exact); LAS payloads add their own 1 mm scale
    assert horizontal <= 0.003 and vertical <= 0.003


def catalog_json_crs(catalog: Path) -> str:
    return str(json.loads((catalog / "catalog.json").read_text())["crs"])


def test_projected_clouds_naming_no_crs_take_the_catalog_crs_they_are_added_to(
    sim: Any, reference: dict[str, Points], tmp_path: Path
) -> None:
    """PLY clouds in payload_clouds_in_utm/ name no CRS: into a new catalog they need --crs,
    added to a catalog (--crs auto) they are in its CRS, and tile where the GNSS fit does."""
    made, _ = sim
    folder = _projected_copy(made, tmp_path / made.name, "ply", "payload_clouds_in_utm")
    catalog = tmp_path / "cat"
    other = BUNDLED_MISSIONS / "2028-05-20-wytham-frontier-v15"
    tile_missions([other], catalog, TileOptions(laz=False))  # its UTM zone: the same CRS
    assert catalog_json_crs(catalog) == CRS
    with pytest.raises(CRSError, match="option crs"):
        tile_missions([folder], tmp_path / "new", TileOptions())
    result = CliRunner().invoke(cli, ["tile", str(folder), "-o", str(catalog), "-q", "--json"])
    assert result.exit_code == 0, result.output
    tiled = tiled_points(catalog, only=made.name)[made.name]
    horizontal, vertical = max_distance(tiled, reference[made.name])
    assert horizontal <= 0.003 and vertical <= 0.003


# --- a mission without GNSS, placed by an anchor -----------------------------------------------


def test_anchor_from_the_true_start_places_a_mission_without_gnss(sim: Any, tmp_path: Path) -> None:
    made, _ = sim
    folder = tmp_path / made.name
    shutil.copytree(made.mission_dir, folder)
    shutil.rmtree(folder / "gnss")
    shutil.rmtree(folder / "payloads" / "gnss")
    with pytest.raises(GeoreferenceError, match="option anchor"):
        tile_missions([folder], tmp_path / "refused", TileOptions(crs=CRS))
    # the truth: where the map origin is, and where its x axis points
    lat, lon, alt = made.chain.map_to_lla(np.zeros((1, 3)))[0]
    yaw = math.degrees(yaw_of(np.linalg.inv(made.chain.T_map_enu)))
    args = ["tile", str(folder), "-o", str(tmp_path / "cat"), "--crs", CRS, "--las", "-q"]
    result = CliRunner().invoke(
        cli, [*args, "--anchor", *(repr(float(v)) for v in (lat, lon, alt, yaw))]
    )
    assert result.exit_code == 0, result.output
    tiled = tiled_points(tmp_path / "cat")[made.name]
    truth: Points = {}
    for k, span in enumerate(made.spans):
        cloud, points = made.payload(k)
        stamp = Stamp.from_ns(int(made.stamps_ns[span.centre]))
        for value, p in zip(cloud.fields["intensity"], points.xyz, strict=True):
            truth[(stamp, float(value))] = p
    horizontal, vertical = max_distance(tiled, truth)
    diff = np.array([tiled[k] - truth[k] for k in truth])
    median_h = float(np.median(np.hypot(diff[:, 0], diff[:, 1])))
    print(
        f"\nanchor: horizontal error median {median_h * 100:.2f} cm, max "
        f"{horizontal * 100:.2f} cm; vertical max {vertical * 100:.2f} cm "
        "(SLAM drift of the simulated graph included)"
    )
    assert median_h < 0.05 and horizontal < 0.15 and vertical < 0.10
    # a heading off by one degree moves points by ~1.7 cm per metre from the origin: seen
    result = CliRunner().invoke(
        cli,
        [
            *args[:3],
            str(tmp_path / "off"),
            *args[4:],
            "--anchor",
            *(repr(float(v)) for v in (lat, lon, alt, yaw + 1.0)),
        ],
    )
    assert result.exit_code == 0, result.output
    off, _ = max_distance(tiled_points(tmp_path / "off")[made.name], truth)
    assert off > 0.5
