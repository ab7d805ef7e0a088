"""CLI: standgrid info / missions / retrieve / payloads build, human and --json output."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner
from mission_factory import make_mission

from standgrid.cli import cli


def run(*args: str) -> str:
    result = CliRunner().invoke(cli, [str(a) for a in args])
    assert result.exit_code == 0, result.output + repr(result.exception)
    return result.stdout


@pytest.mark.parametrize(
    "command",
    [
        ["info"],
        ["missions"],
        ["retrieve"],
        ["retrieve", "by-type"],
        ["retrieve", "by-pose"],
        ["retrieve", "by-gnss"],
        ["payloads"],
        ["payloads", "build"],
    ],
)
def test_help_has_example(command: list[str]) -> None:
    out = run(*command, "--help")
    assert "Example:" in out


def test_info(tmp_path: Path) -> None:
    syn = make_mission(tmp_path, gnss=True, cameras=("front",))
    data = json.loads(run("info", syn.path, "--json"))
    assert data["nodes"] == 5 and data["payloads"] == 5 and data["points"] == 1000
    assert data["gnss_fixes"] == 15 and data["images"] == 2
    assert data["metadata"]["robot"] == "anymal"
    human = run("info", syn.path)
    assert "5 nodes" in human and "1,000 points" in human and "15 GNSS fixes" in human


def test_info_reports_orphans_and_fails_strict(tmp_path: Path) -> None:
    syn = make_mission(tmp_path)
    src = syn.path / "payload_clouds" / syn.stamps[0].filename("cloud", "pcd")
    orphan = syn.path / "payload_clouds" / "cloud_1900000000_000000000.pcd"
    orphan.write_bytes(src.read_bytes())
    assert orphan.name in run("info", syn.path)
    result = CliRunner().invoke(cli, ["info", str(syn.path), "--strict"])
    assert result.exit_code != 0 and "OrphanPayloadError" in result.output


def test_info_reports_a_truncated_cloud_and_does_not_count_it(tmp_path: Path) -> None:
    syn = make_mission(tmp_path)  # 5 payloads of 200 points, binary PCD
    cut = syn.path / "payload_clouds" / syn.stamps[2].filename("cloud", "pcd")
    cut.write_bytes(cut.read_bytes()[:-100])
    data = json.loads(run("info", syn.path, "--json"))
    assert data["payloads"] == 5 and data["payloads_truncated"] == 1
    assert data["points"] == 800  # the truncated payload's 200 points are not counted
    assert any(cut.name in p and "truncated" in p for p in data["problems"])
    assert "1 truncated, not counted" in run("info", syn.path)
    result = CliRunner().invoke(cli, ["info", str(syn.path), "--strict"])
    assert result.exit_code != 0 and "truncated" in result.output


@pytest.mark.parametrize(
    "name, encoding",
    [
        ("c.pcd", "binary"),
        ("c.pcd", "binary_compressed"),
        ("c.ply", "binary"),
        ("c.las", "binary"),
    ],
)
def test_cloud_headers_know_the_size_their_data_needs(
    tmp_path: Path, name: str, encoding: str
) -> None:
    import numpy as np

    from standgrid.clouds import read_cloud, read_cloud_header, write_cloud
    from standgrid.errors import PointCloudFormatError
    from standgrid.pointcloud import PointCloud

    rng = np.random.default_rng(4)
    cloud = PointCloud(
        rng.uniform(-5, 5, (500, 3)), {"intensity": rng.integers(0, 9, 500).astype(np.uint16)}
    )
    path = tmp_path / name
    write_cloud(cloud, path, encoding=encoding)  # type: ignore[arg-type]
    header = read_cloud_header(path)
    assert header.size_problem() is None and header.data_bytes is not None
    assert header.data_offset + header.data_bytes <= path.stat().st_size
    path.write_bytes(path.read_bytes()[:-7])
    problem = read_cloud_header(path).size_problem()
    assert problem is not None and "truncated" in problem and "500 points" in problem
    with pytest.raises(PointCloudFormatError):
        read_cloud(path)  # the second reader agrees: the file is short


def test_missions(tmp_path: Path) -> None:
    make_mission(tmp_path, "2023-01-13-wytham-anymal-coyote", n_nodes=2, gnss=True)
    make_mission(tmp_path, "2024-04-21-stein-am-rhein-frontier-v15", n_nodes=2)
    data = json.loads(run("missions", tmp_path, "--from", "2024-01-01", "--json"))
    assert data["total"] == 2
    assert [m["name"] for m in data["missions"]] == ["2024-04-21-stein-am-rhein-frontier-v15"]
    data = json.loads(run("missions", tmp_path, "--sensor", "gnss", "--sensor", "lidar", "--json"))
    assert [m["site"] for m in data["missions"]] == ["wytham"]
    human = run("missions", tmp_path, "--robot", "frontier")
    assert "stein-am-rhein" in human and "1 of 2 missions" in human


def test_retrieve(tmp_path: Path) -> None:
    syn = make_mission(tmp_path, n_nodes=4, spacing=10.0, cameras=("front",))
    rows = json.loads(run("retrieve", "by-type", syn.path, "image", "--json"))
    assert [r["sensor"] for r in rows] == ["front", "front"]
    x, y, z = syn.poses[2, :3, 3]
    rows = json.loads(run("retrieve", "by-pose", syn.path, x + 0.5, y, z, "--json"))
    assert len(rows) == 1 and rows[0]["stamp_ns"] == syn.stamps[2].ns
    assert rows[0]["distance_m"] == pytest.approx(0.5)
    human = run("retrieve", "by-pose", syn.path, x, y, z, "-k", "2")
    assert len(human.strip().splitlines()) == 2 and str(syn.stamps[2]) in human
    result = CliRunner().invoke(cli, ["retrieve", "by-gnss", str(syn.path), "51.7", "-1.3"])
    assert result.exit_code != 0 and "NotGeoreferencedError" in result.output


def test_payloads_build(tmp_path: Path) -> None:
    syn = make_mission(tmp_path / "in", n_nodes=8, spacing=2.0, cloud_folder="individual_clouds")
    out = tmp_path / "out"
    data = json.loads(run("payloads", "build", syn.path, "-o", out, "--distance", "5", "--json"))
    assert data["payloads"] >= 2 and data["points"] == 8 * 200
    assert (out / "payload_clouds").is_dir()
    result = CliRunner().invoke(cli, ["payloads", "build", str(syn.path), "-o", str(out)])
    assert result.exit_code != 0 and "OutputExistsError" in result.output
    human = run("payloads", "build", syn.path, "-o", out, "--area", "100", "--overwrite")
    assert human.startswith("1 payloads, 1,600 points")


@pytest.mark.parametrize("keep", ["all but the last 100 bytes", "half"])
def test_info_lists_a_truncated_laz_and_an_empty_pcd_as_problems(tmp_path: Path, keep: str) -> None:
    """A bundled mission with one payload as a LAZ cut short (its chunk table lost) and one
    empty PCD: info lists both as problems, counts neither, and goes on."""
    import shutil

    import laspy

    from standgrid.clouds import read_cloud, read_cloud_header, write_cloud
    from standgrid.pointcloud import PointCloud
    from tests.conftest import BUNDLED_MISSIONS

    mission = tmp_path / "2024-05-14-wytham-anymal-coyote"
    shutil.copytree(BUNDLED_MISSIONS / mission.name, mission)
    clouds = sorted((mission / "payload_clouds").glob("*.pcd"))
    total = sum(read_cloud_header(p).points for p in clouds)
    laz = clouds[0].with_suffix(".laz")
    write_cloud(PointCloud(read_cloud(clouds[0]).xyz, {}), laz)
    clouds[0].unlink()
    with laspy.open(laz) as reader:  # a second reader: a real, compressed LAZ
        assert reader.header.are_points_compressed
        cut_points = int(reader.header.point_count)
    data = laz.read_bytes()
    laz.write_bytes(data[: len(data) - 100] if keep.startswith("all") else data[: len(data) // 2])
    empty_points = read_cloud_header(clouds[1]).points
    clouds[1].write_bytes(b"")

    report = json.loads(run("info", mission, "--json"))
    assert report["payloads"] == len(clouds) and report["payloads_truncated"] == 2
    assert report["points"] == total - cut_points - empty_points
    problems = {Path(p.split(": ", 1)[0]).name: p for p in report["problems"]}
    assert "truncated: the file ends before its LAZ chunk table" in problems[laz.name]
    assert "empty file" in problems[clouds[1].name]
    human = run("info", mission)
    assert f"problem   {laz}: truncated" in human
    strict = CliRunner().invoke(cli, ["info", str(mission), "--strict"])
    assert strict.exit_code == 1 and "PointCloudFormatError" in strict.output
