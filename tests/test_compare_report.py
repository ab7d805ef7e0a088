"""Change outputs: CSV + Parquet tables and styled GeoPackage layers, read back twice."""

from __future__ import annotations

import csv
import datetime as dt
import sqlite3
import xml.etree.ElementTree as ET

import geopandas as gpd
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pyogrio
import pytest
import shapely

from standgrid.comparison import compare_stands, match_trees, write_change_outputs
from standgrid.comparison.trees import ChangeInputError

CRS = "EPSG:32633"
X0, Y0, SIZE = 600_000.0, 5_000_000.0, 50.0
DATE_FROM, DATE_TO = dt.date(2020, 6, 1), dt.date(2024, 6, 1)  # 4 years


def _cells() -> gpd.GeoDataFrame:
    names = ["A", "B", "C"]
    boxes = [shapely.box(X0 + i * SIZE, Y0, X0 + (i + 1) * SIZE, Y0 + SIZE) for i in range(3)]
    return gpd.GeoDataFrame({"cell_id": names}, geometry=boxes, crs=CRS)


def _inputs():
    metrics_from = pd.DataFrame(
        {
            "cell_id": ["A", "B", "C"],
            "height_p95_m": [20.0, 18.0, np.nan],
            "null_reason": ["", "", "no points"],
        }
    )
    metrics_to = pd.DataFrame(
        {"cell_id": ["A", "B", "C"], "height_p95_m": [22.0, 10.0, 5.0], "null_reason": ["", "", ""]}
    )
    before = pd.DataFrame(
        {
            "tree_id": [1, 2, 3],
            "x": [X0 + 10, X0 + 30, X0 + 60],
            "y": [Y0 + 10, Y0 + 10, Y0 + 20],
            "height_m": [20.0, 18.0, 15.0],
        }
    )
    after = pd.DataFrame(
        {
            "tree_id": [7, 8, 9],
            "x": [X0 + 10.3, X0 + 60.2, X0 + 80],
            "y": [Y0 + 10, Y0 + 20, Y0 + 20],
            "height_m": [22.0, 17.0, 3.0],
        }
    )
    matches = match_trees(before, after, date_from=DATE_FROM, date_to=DATE_TO)
    changes = compare_stands(
        metrics_from,
        metrics_to,
        date_from=DATE_FROM,
        date_to=DATE_TO,
        epoch_from="2020",
        epoch_to="2024",
        tree_matches=matches,
        cells=_cells(),
    )
    return changes, matches


def _existing_index(path):
    frame = gpd.GeoDataFrame(
        {"cell_id": ["A"], "point_count": [5]},
        geometry=[shapely.box(X0, Y0, X0 + SIZE, Y0 + SIZE)],
        crs=CRS,
    )
    pyogrio.write_dataframe(frame, path, layer="cells", driver="GPKG")


def test_tables_and_layers_written_and_read_back(tmp_path):
    changes, matches = _inputs()
    gpkg = tmp_path / "index.gpkg"
    _existing_index(gpkg)
    out_dir = tmp_path / "compare" / "2020__2024"
    result = write_change_outputs(
        out_dir, gpkg, changes, matches, epoch_from="2020", epoch_to="2024", cells=_cells()
    )

    # flat table: pandas and the csv module agree; keyed by cell_id + epochs
    table = pd.read_csv(result.stand_csv)
    assert list(table.columns[:3]) == ["cell_id", "epoch_from", "epoch_to"]
    assert "geometry" not in table.columns
    with result.stand_csv.open(newline="") as handle:
        rows = {row["cell_id"]: row for row in csv.DictReader(handle)}
    assert float(rows["A"]["height_p95_m_per_year"]) == pytest.approx(0.5)
    assert float(rows["A"]["tree_height_growth_m_per_year"]) == pytest.approx(0.5)
    assert rows["C"]["height_p95_m_delta"] == ""  # null stays null, not 0
    assert rows["C"]["null_reason"] == "from: no points"
    assert rows["A"]["trees_removed"] == "1" and rows["B"]["trees_new"] == "1"
    parquet = pq.read_table(result.stand_parquet).to_pandas()
    assert parquet["height_p95_m_delta"].tolist()[:2] == pytest.approx([2.0, -8.0])
    assert np.isnan(parquet["height_p95_m_delta"].iloc[2])
    assert parquet["trees_removed"].tolist() == [1, 0, 0]

    trees = pq.read_table(result.tree_parquet).to_pandas()
    assert sorted(trees["status"]) == ["grown", "grown", "new", "removed"]
    assert set(trees["epoch_from"]) == {"2020"}
    assert len(pd.read_csv(result.tree_csv)) == 4

    # GeoPackage: layers with geometry, the old layer kept
    assert {name for name, _ in pyogrio.list_layers(gpkg)} >= {
        "cells",
        "stand_changes",
        "tree_changes",
    }
    stands = gpd.read_file(gpkg, layer="stand_changes")
    assert stands.crs.to_epsg() == 32633
    a = stands.set_index("cell_id").loc["A"]
    assert a.geometry.area == pytest.approx(SIZE * SIZE)
    assert a["height_p95_m_per_year"] == pytest.approx(0.5)
    assert pd.isna(stands.set_index("cell_id").loc["C", "height_p95_m_delta"])
    points = gpd.read_file(gpkg, layer="tree_changes")
    assert points.geom_type.unique().tolist() == ["Point"]
    removed = points[points["status"] == "removed"].iloc[0]
    assert (removed.geometry.x, removed.geometry.y) == pytest.approx((X0 + 30, Y0 + 10))

    # default QGIS styles, read with sqlite3 (a second reader of the GeoPackage)
    with sqlite3.connect(gpkg) as db:
        styles = dict(
            db.execute(
                "SELECT f_table_name, styleQML FROM layer_styles WHERE useAsDefault = 1"
            ).fetchall()
        )
    assert result.style_field == "tree_height_growth_m_per_year"
    stand_qml = ET.fromstring(styles["stand_changes"].split("\n", 1)[1])
    renderer = stand_qml.find("renderer-v2")
    assert renderer.get("type") == "graduatedSymbol"
    assert renderer.get("attr") == "tree_height_growth_m_per_year"
    lower, upper = result.style_range
    assert lower == -upper and upper > 0  # centred on zero: diverging
    tree_qml = ET.fromstring(styles["tree_changes"].split("\n", 1)[1])
    categories = {c.get("value") for c in tree_qml.iter("category")}
    assert categories == {"grown", "new", "removed", "missed"}


def test_chosen_style_field_and_geodataframe_input(tmp_path):
    changes, _ = _inputs()
    frame = changes.merge(_cells(), on="cell_id")
    geo = gpd.GeoDataFrame(frame, geometry="geometry", crs=CRS)
    gpkg = tmp_path / "out.gpkg"
    result = write_change_outputs(
        tmp_path / "c",
        gpkg,
        geo,
        epoch_from="2020",
        epoch_to="2024",
        style_field="height_p95_m_delta",
    )
    assert result.tree_csv is None
    assert result.style_range == pytest.approx((-8.0 * 0.98 - 2.0 * 0.02, 8.0 * 0.98 + 0.04))
    assert [name for name, _ in pyogrio.list_layers(gpkg)].count("tree_changes") == 0
    with sqlite3.connect(gpkg) as db:
        (qml,) = db.execute(
            "SELECT styleQML FROM layer_styles WHERE f_table_name = 'stand_changes'"
        ).fetchone()
    assert 'attr="height_p95_m_delta"' in qml


def test_missing_polygons_and_unknown_style_field_are_refused(tmp_path):
    changes, _ = _inputs()
    with pytest.raises(ChangeInputError, match="no cell polygon: C"):
        write_change_outputs(
            tmp_path / "c",
            tmp_path / "x.gpkg",
            changes,
            epoch_from="2020",
            epoch_to="2024",
            cells=_cells().iloc[:2],
        )
    with pytest.raises(ChangeInputError, match="not_a_column"):
        write_change_outputs(
            tmp_path / "c",
            tmp_path / "x.gpkg",
            changes,
            epoch_from="2020",
            epoch_to="2024",
            cells=_cells(),
            style_field="not_a_column",
        )
    assert not (tmp_path / "x.gpkg").exists()
    assert not (tmp_path / "c").exists()  # refused before anything was written
