"""The generic tree list: every format written, read back with a second reader, and
compared with the catalog's own tree lists."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pandas as pd
import pyogrio
import pytest
from pyproj import Transformer

from standgrid.catalog import Catalog
from standgrid.cli import cli
from standgrid.errors import FormatError
from standgrid.growth.treelist import TREE_COLUMNS, generic_tree_list, write_tree_list
from tests.pipeline_fixtures import enriched_pair


@pytest.fixture(scope="module")
def catalog(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return enriched_pair(tmp_path_factory).path


def _source(catalog: Path) -> pd.DataFrame:
    frames = [
        pd.read_parquet(catalog / "tables" / f"tree_list_{e}.parquet") for e in ("2024", "2028")
    ]
    return pd.concat(frames, ignore_index=True)


def test_columns_match_the_catalog(catalog: Path) -> None:
    cat = Catalog.open(catalog)
    table = generic_tree_list(cat)
    source = _source(catalog)
    assert list(table.columns) == TREE_COLUMNS and len(table) == len(source)
    assert (table["tree_id"].to_numpy() == source["tree_id"].to_numpy()).all()
    np.testing.assert_array_equal(table["dbh_cm"], source["dbh_m"] * 100.0)
    assert (table["dbh_source"].to_numpy() == source["dbh_source"].to_numpy()).all()
    stands = pd.read_parquet(catalog / "tables" / "stand_metrics.parquet")
    stands = stands[stands["level"] == 1].assign(epoch=stands["epoch"].astype(str))
    # summing the expansion factors of the counted trees gives the stand table's values
    counted = table[table["counted"]]
    assert len(counted) > 0
    assert table.loc[~table["counted"], "trees_per_ha"].isna().all()
    sums = (
        counted.assign(ba=counted["basal_area_m2"] * counted["trees_per_ha"])
        .groupby(["epoch", "stand_id"])[["trees_per_ha", "ba"]]
        .sum()
    )
    rows = stands.set_index(["epoch", "cell_id"]).loc[sums.index]
    np.testing.assert_allclose(sums["trees_per_ha"], rows["stems_ha"], rtol=1e-9)
    np.testing.assert_allclose(sums["ba"], rows["basal_area_m2_ha"], rtol=1e-9)
    np.testing.assert_allclose(
        counted["stand_area_m2"],
        rows["observed_m2"]
        .reindex(pd.MultiIndex.from_frame(counted[["epoch", "stand_id"]]))
        .to_numpy(),
    )
    back = Transformer.from_crs("EPSG:4326", cat.crs, always_xy=True)
    x, y = back.transform(table["lon"].to_numpy(), table["lat"].to_numpy())
    px = table["stem_x"].fillna(table["x"]).to_numpy()
    assert np.abs(x - px).max() < 1e-6 and np.isfinite(y).all()


@pytest.mark.parametrize("suffix", [".csv", ".parquet", ".gpkg", ".sqlite"])
def test_every_format_reads_back(catalog: Path, tmp_path: Path, suffix: str) -> None:
    cat = Catalog.open(catalog)
    table = generic_tree_list(cat)
    out = write_tree_list(table, tmp_path / f"trees{suffix}", crs=cat.crs)
    if suffix == ".csv":
        back = pd.read_csv(out)
    elif suffix == ".parquet":
        back = pd.read_parquet(out)
    elif suffix == ".gpkg":
        back = pyogrio.read_dataframe(out, layer="trees")
        px = table["stem_x"].fillna(table["x"]).to_numpy()
        np.testing.assert_array_equal(back.geometry.x.to_numpy(), px)
        assert back.crs.to_epsg() == 32630
    else:
        with sqlite3.connect(out) as conn:
            back = pd.read_sql("SELECT * FROM trees", conn)
        conn.close()
    assert len(back) == len(table)
    assert (back["tree_id"].astype(np.int64).to_numpy() == table["tree_id"].to_numpy()).all()
    np.testing.assert_allclose(back["dbh_cm"].astype(float), table["dbh_cm"], equal_nan=True)
    assert back["dbh_source"].isna().sum() == table["dbh_source"].isna().sum()


def test_cli_and_unknown_suffix(catalog: Path, tmp_path: Path) -> None:
    from click.testing import CliRunner

    result = CliRunner().invoke(
        cli,
        [
            "export",
            "trees",
            str(catalog),
            "-o",
            str(tmp_path / "t.parquet"),
            "--epoch",
            "2028",
            "--json",
        ],
    )
    assert result.exit_code == 0, result.output
    assert len(pd.read_parquet(tmp_path / "t.parquet")) == len(
        pd.read_parquet(catalog / "tables" / "tree_list_2028.parquet")
    )
    again = CliRunner().invoke(
        cli, ["export", "trees", str(catalog), "-o", str(tmp_path / "t.parquet")]
    )
    assert again.exit_code != 0 and "exists" in again.output
    with pytest.raises(FormatError, match="suffix"):
        write_tree_list(generic_tree_list(Catalog.open(catalog)), tmp_path / "t.xlsx", crs="x")
