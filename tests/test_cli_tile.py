"""``standgrid tile`` through click's CliRunner: JSON and human output, errors, help."""

from __future__ import annotations

import json
from pathlib import Path

import laspy
import numpy as np
import pytest
from click.testing import CliRunner

from standgrid.cli import cli
from tests.conftest import BUNDLED_MISSIONS
from tests.mission_factory import make_mission

M1 = BUNDLED_MISSIONS / "2024-05-14-wytham-anymal-coyote"
M2 = BUNDLED_MISSIONS / "2028-05-20-wytham-frontier-v15"


@pytest.fixture
def runner() -> CliRunner:
    return CliRunner()


def _error_lines(output: str) -> list[str]:
    return [line for line in output.splitlines() if line.startswith("Error:")]


def test_json_output_is_conserved(runner: CliRunner, tmp_path: Path) -> None:
    catalog = tmp_path / "catalog"
    result = runner.invoke(
        cli,
        ["tile", str(M1), str(M2), "-o", str(catalog), "--las", "--buffer", "1", "--json", "-q"],
    )
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["conserved"] is True
    assert report["points_in"] == report["points_out"] > 0
    assert sorted(report["epochs"]) == ["2024", "2028"]
    tiles = sorted(catalog.glob("tiles/*/*.las"))
    assert sum(e["cells"] for e in report["epochs"].values()) == len(tiles)
    written = 0
    for path in tiles:
        las = laspy.read(path)
        written += int((~np.asarray(las.withheld, dtype=bool)).sum())
    assert written == report["points_out"]
    state = json.loads((catalog / "catalog.json").read_text())
    assert state["tiling"] == {"buffer": 1.0, "laz": False, "copc": False}


def test_human_output_names_the_catalog(runner: CliRunner, tmp_path: Path) -> None:
    catalog = tmp_path / "catalog"
    result = runner.invoke(cli, ["tile", str(M1), "-o", str(catalog), "--grid", "40", "-q"])
    assert result.exit_code == 0, result.output
    assert str(catalog) in result.stdout
    assert "conserved" in result.stdout
    assert str(catalog / "index.gpkg") in result.stdout
    tiles = list(catalog.glob("tiles/2024/*"))
    assert tiles and all(p.suffix == ".laz" and p.stem.startswith("40m_") for p in tiles)


def test_missing_georeference_is_a_one_line_error(runner: CliRunner, tmp_path: Path) -> None:
    mission = make_mission(tmp_path / "m").path
    result = runner.invoke(cli, ["tile", str(mission), "-o", str(tmp_path / "catalog")])
    assert result.exit_code == 1
    lines = _error_lines(result.output)
    assert len(lines) == 1
    assert lines[0].startswith("Error: NotGeoreferencedError: ")
    assert str(mission) in lines[0]
    assert "Traceback" not in result.output
    assert not (tmp_path / "catalog").exists()


def test_grid_mismatch_is_a_one_line_error(runner: CliRunner, tmp_path: Path) -> None:
    catalog = tmp_path / "catalog"
    assert runner.invoke(cli, ["tile", str(M1), "-o", str(catalog), "-q"]).exit_code == 0
    before = (catalog / "catalog.json").read_bytes()
    result = runner.invoke(cli, ["tile", str(M2), "-o", str(catalog), "--grid", "50", "-q"])
    assert result.exit_code == 1
    lines = _error_lines(result.output)
    assert len(lines) == 1 and lines[0].startswith("Error: GridMismatchError: ")
    assert "Traceback" not in result.output
    assert (catalog / "catalog.json").read_bytes() == before


def test_unknown_crs_is_a_one_line_error(runner: CliRunner, tmp_path: Path) -> None:
    result = runner.invoke(
        cli, ["tile", str(M1), "-o", str(tmp_path / "catalog"), "--crs", "EPSG:999999"]
    )
    assert result.exit_code == 1
    assert _error_lines(result.output)[0].startswith("Error: CRSError: ")


def test_existing_folder_needs_overwrite(runner: CliRunner, tmp_path: Path) -> None:
    folder = tmp_path / "out"
    folder.mkdir()
    (folder / "keep.txt").write_text("x")
    result = runner.invoke(cli, ["tile", str(M1), "-o", str(folder), "-q"])
    assert result.exit_code == 1
    assert _error_lines(result.output)[0].startswith("Error: OutputExistsError: ")
    # --overwrite replaces a catalog only: a folder of other files is never deleted
    result = runner.invoke(cli, ["tile", str(M1), "-o", str(folder), "-q", "--overwrite"])
    assert result.exit_code == 1
    assert "is a folder with files that is not a catalog" in _error_lines(result.output)[0]
    assert sorted(p.name for p in folder.iterdir()) == ["keep.txt"]


def test_help_has_an_example(runner: CliRunner) -> None:
    result = runner.invoke(cli, ["tile", "--help"])
    assert result.exit_code == 0
    assert "Example:" in result.output
    assert "standgrid tile" in result.output


def test_levels_and_voronoi_options(runner: CliRunner, tmp_path: Path) -> None:
    grid = tmp_path / "grid"
    result = runner.invoke(cli, ["tile", str(M1), "-o", str(grid), "--levels", "20,60", "-q"])
    assert result.exit_code == 0, result.output
    assert json.loads((grid / "catalog.json").read_text())["grid"]["levels"] == [20.0, 60.0]
    cells = tmp_path / "voronoi"
    result = runner.invoke(cli, ["tile", str(M1), "-o", str(cells), "--voronoi", "--json", "-q"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["scheme"] == "voronoi"
    tiles = list(cells.glob("tiles/2024/*.laz"))
    assert tiles and all(p.stem.startswith(f"V_{M1.name}_") for p in tiles)
