"""Geoid undulations through PROJ equal the grid file read independently (GDAL via rasterio,
bilinear interpolation by hand); no grid -> a typed "no geoid model" that says where."""

from __future__ import annotations

import math
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest

from standgrid.georeference.geoid import (
    CANDIDATES,
    DEBIAN_PROJ_DATA,
    GeoidModel,
    NoGeoidModel,
    find_geoid,
)

#: lon, lat: the bundled Wytham Woods missions (UK), Oregon (FVS's PN variant), Kansas,
#: the Gulf of Guinea, and a point on a grid node
POINTS = [
    (-1.33694, 51.77374),
    (-122.6765, 45.5231),
    (-98.4842, 39.0119),
    (0.0, 0.0),
    (10.25, 47.5),
]


def _debian_grid() -> Path:
    for candidate in CANDIDATES:
        for name in candidate.files:
            if (DEBIAN_PROJ_DATA / name).is_file():
                return DEBIAN_PROJ_DATA / name
    pytest.skip(f"no geoid grid in {DEBIAN_PROJ_DATA} (apt-get install proj-data)")


def _grid_bilinear(path: Path, lon: float, lat: float) -> float:
    """The grid's value at lon/lat, interpolated by hand between its 4 surrounding nodes
    (node i, j at the centre of GDAL's pixel i, j)."""
    import rasterio

    with rasterio.open(path) as src:
        values = src.read(1).astype(np.float64)
        inverse = ~src.transform
        west_node = src.transform.c + src.transform.a / 2
    lon = west_node + (lon - west_node) % 360.0
    col, row = inverse @ (lon, lat)
    col, row = col - 0.5, row - 0.5  # node coordinates
    c0, r0 = math.floor(col), math.floor(row)
    fc, fr = col - c0, row - r0
    c1 = (c0 + 1) % values.shape[1]
    return float(
        (1 - fr) * ((1 - fc) * values[r0, c0] + fc * values[r0, c1])
        + fr * ((1 - fc) * values[r0 + 1, c0] + fc * values[r0 + 1, c1])
    )


def test_undulation_equals_the_grid_read_by_gdal(tmp_path: Path) -> None:
    grid = _debian_grid()
    folder = tmp_path / "grids"
    folder.mkdir()
    shutil.copy(grid, folder / grid.name)  # only this grid: the model found is this one
    model = find_geoid([folder])
    assert isinstance(model, GeoidModel), model
    assert model.file == folder / grid.name
    assert model.name in grid.name.upper().replace("08", "2008")
    lon, lat = np.array(POINTS).T
    undulation = model.undulation(lon, lat)
    expected = [_grid_bilinear(grid, x, y) for x, y in POINTS]
    print(dict(zip(POINTS, undulation.round(3).tolist(), strict=True)))
    np.testing.assert_allclose(undulation, expected, atol=1e-3)
    assert 40 < undulation[0] < 60 and -40 < undulation[1] < -10  # UK +, North America -
    heights = np.array([100.0, 0.0, 250.0, -5.0, 1000.0])
    np.testing.assert_allclose(
        model.orthometric_height(lon, lat, heights), heights - np.array(expected), atol=1e-3
    )
    assert model.describe().endswith(str(folder / grid.name))


def test_default_search_finds_the_debian_grid(monkeypatch: pytest.MonkeyPatch) -> None:
    grid = _debian_grid()
    monkeypatch.delenv("STANDGRID_GEOID_PATH", raising=False)
    model = find_geoid()
    assert isinstance(model, GeoidModel)
    assert model.file.is_file()  # this grid, or a better / earlier one
    lon, lat = POINTS[0]
    if model.file == grid:
        assert model.undulation(lon, lat) == pytest.approx(_grid_bilinear(grid, lon, lat), abs=1e-3)


def test_no_grid_is_a_reason_naming_the_folders(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    (tmp_path / "fake").mkdir()
    (tmp_path / "fake" / "egm96_15.gtx").write_bytes(b"not a grid")
    found = find_geoid([empty, tmp_path / "fake"])
    assert isinstance(found, NoGeoidModel)
    assert found.reason.startswith("no geoid model found")
    assert str(empty) in found.reason and "egm96_15.gtx" in found.reason
    # the unreadable file is named, with what is wrong with it, and not used
    assert f"{tmp_path / 'fake' / 'egm96_15.gtx'}: 10 bytes: shorter than a GTX header" in (
        found.reason
    )


def test_environment_variable_replaces_the_search_path(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("STANDGRID_GEOID_PATH", str(tmp_path))
    found = find_geoid()
    assert isinstance(found, NoGeoidModel) and found.searched == (tmp_path,)


def _damaged_copies(tmp_path: Path) -> dict[str, Path]:
    """Folders each holding one damaged copy of the EGM96 grid (under its own name)."""
    grid = DEBIAN_PROJ_DATA / "egm96_15.gtx"
    if not grid.is_file():
        pytest.skip(f"no {grid} (apt-get install proj-data)")
    data = grid.read_bytes()
    rows, cols = struct.unpack(">2i", data[32:40])
    values = np.frombuffer(data, ">f4", offset=40).reshape(rows, cols)
    zeroed = values.copy()
    zeroed[rows // 2 + 100 : rows // 2 + 160] = 0.0  # a band at 25..40 N, no anchor in it
    damaged = {
        "truncated 77 %": data[: int(len(data) * 0.77)],
        "truncated 90 %": data[: int(len(data) * 0.90)],
        "zeroed band": data[:40] + zeroed.astype(">f4").tobytes(),
        "negated": data[:40] + (-values).astype(">f4").tobytes(),
        "header only": data[:40],
    }
    folders = {}
    for label, content in damaged.items():
        folder = tmp_path / label.replace(" ", "_").replace("%", "pct")
        folder.mkdir()
        (folder / grid.name).write_bytes(content)
        folders[label] = folder
    return folders


def test_a_damaged_grid_is_refused_naming_the_file(tmp_path: Path) -> None:
    """Truncated, zero-filled or sign-flipped copies of the EGM96 grid are each refused,
    the reason naming the file; the intact grid in the same search passes."""
    for label, folder in _damaged_copies(tmp_path).items():
        found = find_geoid([folder])
        assert isinstance(found, NoGeoidModel), f"{label}: accepted"
        (problem,) = found.problems
        print(label, problem)
        assert problem.startswith(f"{folder / 'egm96_15.gtx'}: "), problem
        assert str(folder / "egm96_15.gtx") in found.reason
        # the intact grid, searched after the damaged one, is the one used
        model = find_geoid([folder, DEBIAN_PROJ_DATA])
        assert isinstance(model, GeoidModel) and model.file != folder / "egm96_15.gtx"


def test_a_sign_flipped_grid_is_refused_by_its_anchors(tmp_path: Path) -> None:
    """A grid whose values are all in the undulation range, but negated (a band of it kept
    in range): refused because PROJ's undulation at the anchor points is not EGM96's."""
    folders = _damaged_copies(tmp_path)
    data = (folders["negated"] / "egm96_15.gtx").read_bytes()
    values = np.frombuffer(data, ">f4", offset=40).clip(-85.0, 85.0)  # in range everywhere
    (folders["negated"] / "egm96_15.gtx").write_bytes(data[:40] + values.astype(">f4").tobytes())
    found = find_geoid([folders["negated"]])
    assert isinstance(found, NoGeoidModel)
    assert "N(-1.337, 51.773) = -47.89 m, not 47.89" in found.reason, found.reason


def test_the_verdict_is_cached_per_file_version(tmp_path: Path) -> None:
    """A grid damaged after it was checked (new size / mtime) is checked again."""
    grid = DEBIAN_PROJ_DATA / "egm96_15.gtx"
    if not grid.is_file():
        pytest.skip(f"no {grid} (apt-get install proj-data)")
    folder = tmp_path / "grids"
    folder.mkdir()
    shutil.copy(grid, folder / grid.name)
    assert isinstance(find_geoid([folder]), GeoidModel)
    data = (folder / grid.name).read_bytes()
    (folder / grid.name).write_bytes(data[: len(data) - 4 * 1440])
    assert isinstance(find_geoid([folder]), NoGeoidModel)
