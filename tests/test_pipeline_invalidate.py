"""No stale results, through the real pipeline on the bundled pair: re-tiling an enriched and
compared epoch removes exactly that epoch's enrichment and its comparisons (files, tables,
GeoPackage layers read back with pyogrio and sqlite3, catalog.json), ``status`` says so, and
``enrich`` refreshes it."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path
from typing import Any

import httpx
import laspy
import numpy as np
import pandas as pd
import pyogrio
import pytest
from click.testing import CliRunner

from standgrid.catalog.invalidate import enrichment_note, without_enrichment
from standgrid.catalog.records import EpochRecord
from standgrid.cli import cli
from standgrid.comparison.options import CompareOptions
from standgrid.engine import CallbackProgress, Execution
from standgrid.enrichment.options import EnrichOptions
from standgrid.errors import EnrichError
from standgrid.pipeline.compare import compare_epochs
from standgrid.pipeline.enrich import enrich_catalog
from standgrid.pipeline.status import catalog_status
from standgrid.pipeline.tile import tile_missions
from standgrid.serve import create_app
from standgrid.serve.server import running
from tests.conftest import BUNDLED_MISSIONS
from tests.pipeline_fixtures import (
    MISSIONS,
    EnrichedPair,
    copy_catalog,
    enriched_pair,
    tiled_grid25,
)

PAIR = "2024__2028"


@pytest.fixture(scope="session")
def pair(tmp_path_factory: pytest.TempPathFactory) -> EnrichedPair:
    return enriched_pair(tmp_path_factory)


def _files(root: Path, folder: str) -> set[str]:
    base = root / folder
    return {p.relative_to(root).as_posix() for p in base.rglob("*") if p.is_file()}


def _layer_epochs(gpkg: Path, layer: str, column: str = "epoch") -> pd.Series:
    return pyogrio.read_dataframe(gpkg, layer=layer, read_geometry=False)[column].astype(str)


def _sql_count(gpkg: Path, layer: str, where: str = "1") -> int:
    with sqlite3.connect(gpkg) as db:
        return int(db.execute(f'SELECT COUNT(*) FROM "{layer}" WHERE {where}').fetchone()[0])


def _snapshot(root: Path) -> dict[str, Any]:
    """Everything of epoch 2024 a re-tile of 2028 must leave exactly as it was."""
    gpkg = root / "index.gpkg"
    metrics = pd.read_parquet(root / "tables/stand_metrics.parquet")
    return {
        "rasters": {rel: (root / rel).read_bytes() for rel in _files(root, "rasters/2024")},
        "trees": (root / "tables/tree_list_2024.parquet").read_bytes(),
        "metrics": metrics[metrics["epoch"].astype(str) == "2024"].reset_index(drop=True),
        "metric_layer": int((_layer_epochs(gpkg, "stand_metrics") == "2024").sum()),
        "tree_layer": int((_layer_epochs(gpkg, "trees") == "2024").sum()),
        "entry": json.loads((root / "catalog.json").read_text())["epochs"]["2024"],
    }


@pytest.fixture(scope="module")
def retiled(pair: EnrichedPair, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A copy of the enriched, compared pair whose 2028 mission is ingested again."""
    root = copy_catalog(pair.path, tmp_path_factory.mktemp("retile") / "catalog")
    before = _snapshot(root)
    gpkg = root / "index.gpkg"
    counts = {
        "metrics_2028": int((_layer_epochs(gpkg, "stand_metrics") == "2028").sum()),
        "stand_changes": _sql_count(gpkg, "stand_changes"),
        "tree_changes": _sql_count(gpkg, "tree_changes"),
    }
    assert counts["metrics_2028"] > 0 and counts["stand_changes"] > 0  # something to remove
    assert _files(root, f"compare/{PAIR}") and _files(root, "rasters/2028")
    messages: list[str] = []
    report = tile_missions(
        [BUNDLED_MISSIONS / MISSIONS["2028"]],
        root,
        execution=Execution(progress=CallbackProgress(on_status=messages.append)),
    )
    return {
        "root": root,
        "before": before,
        "counts": counts,
        "report": report.to_dict(),
        "messages": messages,
    }


def test_retile_removes_the_epochs_files_and_comparison(retiled: dict[str, Any]) -> None:
    root = retiled["root"]
    assert _files(root, "rasters/2028") == set()
    assert not (root / "tables/tree_list_2028.parquet").exists()
    assert not (root / "tables/tree_list_2028.csv").exists()
    assert _files(root, f"compare/{PAIR}") == set()
    assert not (root / ".staging").exists()  # committed
    # the tiles themselves are back (re-tiling is not deleting), without old heights or trees
    tiles = sorted(_files(root, "tiles/2028"))
    assert tiles
    with laspy.open(root / tiles[0]) as reader:
        points = reader.read()
    assert np.isnan(np.asarray(points["height_above_ground"])).all()
    assert (np.asarray(points["tree_id"]) == 0).all()


def test_retile_rewrites_the_qgis_project(retiled: dict[str, Any]) -> None:
    """catalog.qgz names no removed file: 2028 keeps its tiled layers only, no change group."""
    from tests.test_export_qgis_project import read_project, split_source, tree_groups

    root = retiled["root"]
    project = read_project(root)
    for layer in project.findall("projectlayers/maplayer"):
        path, options = split_source(layer.findtext("datasource", ""))
        assert (root / path).is_file(), path
        if "subset" in options:
            rows = pyogrio.read_dataframe(
                root / path,
                layer=options["layername"],
                where=options["subset"],
                read_geometry=False,
            )
            assert len(rows) > 0, layer.findtext("layername")
    groups = tree_groups(project)
    assert list(groups) == ["2028", "2024"]
    names = [n.get("name") for n in groups["2028"].findall("layer-tree-layer")]
    assert names == [
        "Trajectories",
        "GNSS fixes",
        "Payload footprints",
        "Tiles (20 m cells, points)",
    ]
    tiles = groups["2028"].find("layer-tree-layer[@name='Tiles (20 m cells, points)']")
    assert tiles is not None and tiles.get("checked") == "Qt::Checked"  # not enriched: on
    assert len(groups["2024"].findall("layer-tree-layer")) == 11


def test_kept_points_lose_their_enrichment() -> None:
    fields = {
        "height_above_ground": np.array([1.5, 20.0], dtype=np.float32),
        "tree_id": np.array([7, 0], dtype=np.int64),
        "classification": np.array([2, 1], dtype=np.uint8),
        "intensity": np.array([10, 20], dtype=np.uint16),
    }
    out = without_enrichment(fields)
    assert np.isnan(out["height_above_ground"]).all()
    assert out["height_above_ground"].dtype == np.float32
    assert (out["tree_id"] == 0).all() and out["tree_id"].dtype == np.int64
    assert out["classification"] is fields["classification"]  # source classes are kept
    assert out["intensity"] is fields["intensity"]


def test_retile_removes_the_epochs_rows_from_tables_and_layers(retiled: dict[str, Any]) -> None:
    root, gpkg = retiled["root"], retiled["root"] / "index.gpkg"
    for table in (
        pd.read_parquet(root / "tables/stand_metrics.parquet"),
        pd.read_csv(root / "tables/stand_metrics.csv", dtype={"epoch": str}),
    ):
        assert set(table["epoch"].astype(str)) == {"2024"}
    assert set(_layer_epochs(gpkg, "stand_metrics")) == {"2024"}
    assert set(_layer_epochs(gpkg, "trees")) == {"2024"}
    assert _sql_count(gpkg, "stand_metrics", "CAST(epoch AS TEXT) = '2028'") == 0
    assert _sql_count(gpkg, "stand_changes") == 0 and _sql_count(gpkg, "tree_changes") == 0
    # GDAL's own count and spatial index agree with the rows (triggers ran)
    info = pyogrio.read_info(gpkg, layer="stand_metrics")
    assert info["features"] == _sql_count(gpkg, "stand_metrics")
    with sqlite3.connect(gpkg) as db:
        rtree = db.execute("SELECT COUNT(*) FROM rtree_stand_metrics_geom").fetchone()[0]
        styled = db.execute(
            "SELECT COUNT(*) FROM layer_styles WHERE f_table_name = 'stand_metrics'"
        ).fetchone()[0]
    assert rtree == _sql_count(gpkg, "stand_metrics")
    assert styled >= 1  # the layer keeps its QGIS style


def test_retile_leaves_the_other_epoch_untouched(retiled: dict[str, Any]) -> None:
    after = _snapshot(retiled["root"])
    before = retiled["before"]
    assert after["rasters"] == before["rasters"] and len(before["rasters"]) >= 6
    assert after["trees"] == before["trees"]
    pd.testing.assert_frame_equal(after["metrics"], before["metrics"])
    assert after["metric_layer"] == before["metric_layer"] > 0
    assert after["tree_layer"] == before["tree_layer"] > 0
    assert after["entry"] == before["entry"] and after["entry"]["enriched"] is True


def test_retile_marks_the_epoch_stale_in_the_catalog(retiled: dict[str, Any]) -> None:
    state = json.loads((retiled["root"] / "catalog.json").read_text())
    entry = state["epochs"]["2028"]
    assert entry["enriched"] is False and "enrichment" not in entry
    stale = entry["invalidated"]
    assert stale["reason"] == f"re-tiled: missions {MISSIONS['2028']}"
    assert stale["comparisons"] == [PAIR] and stale["at"].endswith("Z")
    assert PAIR not in state.get("comparisons", {})
    assert "invalidated" not in state["epochs"]["2024"]
    # the tiler's report and its progress lines say what went
    removed = retiled["report"]["epochs"]["2028"]["invalidated"]
    assert removed["comparisons"] == [PAIR]
    assert "rasters/2028/chm.tif" in removed["files"]
    assert f"compare/{PAIR}/chm_diff.tif" in removed["files"]
    assert removed["rows"]["stand_metrics"] == retiled["counts"]["metrics_2028"]
    assert removed["rows"]["stand_changes"] == retiled["counts"]["stand_changes"]
    assert any("epoch 2028 re-tiled" in m and PAIR in m for m in retiled["messages"])


def test_status_reports_stale_epoch_and_invalidated_comparison(retiled: dict[str, Any]) -> None:
    root = retiled["root"]
    status = catalog_status(root)
    assert status["epochs"]["2024"]["state"] == "enriched"
    e2028 = status["epochs"]["2028"]
    assert e2028["state"] == "stale" and e2028["missions"] == [MISSIONS["2028"]]
    assert e2028["invalidated"]["reason"].startswith("re-tiled")
    assert e2028["tiles"] == len(_files(root, "tiles/2028"))
    assert e2028["points"] == retiled["report"]["epochs"]["2028"]["points_new"] > 0
    assert status["comparisons"][PAIR]["state"] == "invalidated"

    runner = CliRunner()
    result = runner.invoke(cli, ["status", str(root), "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.output)["epochs"]["2028"]["state"] == "stale"
    human = runner.invoke(cli, ["status", str(root)])
    assert human.exit_code == 0
    assert "stale: re-tiled" in human.output and f"{PAIR}  invalidated" in human.output


def test_compare_refuses_the_stale_epoch(retiled: dict[str, Any]) -> None:
    with pytest.raises(EnrichError, match=r"stale: .*re-run `standgrid enrich"):
        compare_epochs(retiled["root"], CompareOptions("2024", "2028"))


def test_export_says_the_epoch_is_stale(retiled: dict[str, Any], tmp_path: Path) -> None:
    result = CliRunner().invoke(
        cli,
        ["export", "trees", str(retiled["root"]), "-o", str(tmp_path / "t.csv"), "--epoch", "2028"],
    )
    assert result.exit_code != 0
    assert "is stale" in result.output and "re-run `standgrid enrich`" in result.output
    assert "not enriched" not in result.output


@pytest.mark.slow
def test_enrich_refreshes_the_stale_epoch(
    retiled: dict[str, Any], tmp_path_factory: pytest.TempPathFactory
) -> None:
    root = copy_catalog(retiled["root"], tmp_path_factory.mktemp("refresh") / "catalog")
    messages: list[str] = []
    enrich_catalog(
        root,
        EnrichOptions(epochs=("2028",)),
        execution=Execution(progress=CallbackProgress(on_status=messages.append)),
    )
    assert any("2028" in m and "refreshing stale epoch" in m and PAIR in m for m in messages)
    entry = json.loads((root / "catalog.json").read_text())["epochs"]["2028"]
    assert entry["enriched"] is True and "invalidated" not in entry
    assert {"rasters/2028/chm.tif", "rasters/2028/chm.qml"} <= _files(root, "rasters/2028")
    assert set(_layer_epochs(root / "index.gpkg", "stand_metrics")) == {"2024", "2028"}
    status = catalog_status(root)
    assert status["epochs"]["2028"]["state"] == "enriched"
    assert status["comparisons"][PAIR]["state"] == "invalidated"  # until compared again
    compare_epochs(root, CompareOptions("2024", "2028"))
    assert catalog_status(root)["comparisons"][PAIR]["state"] == "present"


def test_enrich_says_what_it_computes() -> None:
    def note(entry: dict[str, Any]) -> str:
        return enrichment_note(EpochRecord.from_json("2024", {"missions": [], **entry}))

    assert note({"enriched": True}) == "recomputing (was enriched)"
    assert note({"enriched": False}) == "computing (not enriched)"
    stale = {"at": "T", "reason": "re-tiled: missions m", "comparisons": ["a__b"]}
    assert note({"enriched": False, "invalidated": stale}) == (
        "refreshing stale epoch (re-tiled: missions m, T); compare again: a__b"
    )


def test_retiling_an_unenriched_epoch_marks_nothing(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    root = copy_catalog(tiled_grid25(tmp_path_factory), tmp_path_factory.mktemp("g25") / "c")
    report = tile_missions([BUNDLED_MISSIONS / MISSIONS["2024"]], root)
    assert "invalidated" not in report.to_dict()["epochs"]["2024"]
    entry = json.loads((root / "catalog.json").read_text())["epochs"]["2024"]
    assert "invalidated" not in entry and entry["enriched"] is False
    assert catalog_status(root)["epochs"]["2024"]["state"] == "not enriched"


def test_re_enriching_an_epoch_removes_its_comparisons(pair: EnrichedPair, tmp_path: Path) -> None:
    """Enrich again (e.g. with another coverage rule): the comparison that read the old
    results is removed (files, change rows, catalog entry) and listed as invalidated."""
    root = copy_catalog(pair.path, tmp_path / "catalog")
    assert _files(root, f"compare/{PAIR}")
    messages: list[str] = []
    enrich_catalog(
        root,
        EnrichOptions(epochs=("2028",), min_observed_fraction=0.5),
        execution=Execution(progress=CallbackProgress(on_status=messages.append)),
    )
    assert not _files(root, f"compare/{PAIR}")
    assert _sql_count(root / "index.gpkg", "stand_changes") == 0
    state = json.loads((root / "catalog.json").read_text())
    assert PAIR not in state.get("comparisons", {})
    assert PAIR in state["epochs"]["2028"]["comparisons_invalidated"]
    assert any(PAIR in m and "compare again" in m for m in messages)
    assert catalog_status(root)["comparisons"][PAIR]["state"] == "invalidated"


def test_an_epoch_whose_dbh_model_pooled_a_re_tiled_epoch_is_invalidated_too(
    tmp_path: Path,
) -> None:
    from standgrid.catalog import Catalog
    from standgrid.catalog.invalidate import POOLED_MODEL, invalidate_epochs

    grid = {"crs": "EPSG:32632", "cell_size": 20.0, "origin": [0.0, 0.0], "levels": 2}
    catalog = Catalog.create(tmp_path / "c", grid, "EPSG:32632")
    with catalog.transaction() as txn:
        for epoch in ("2024", "2028", "2032"):
            txn.record_mission(f"m{epoch}", epoch=epoch, date=f"{epoch}-05-01")
        txn.mark_enriched("2024", {"height_diameter_model": {"source": "epoch 2024"}})
        txn.mark_enriched("2028", {"height_diameter_model": {"source": POOLED_MODEL}})
        txn.mark_enriched("2032", {"height_diameter_model": {"source": "epoch 2032"}})
    catalog = Catalog.open(catalog.root)
    with catalog.transaction() as txn:
        invalidate_epochs(catalog, txn, {"2024": "re-tiled: missions m2024"})
    epochs = Catalog.open(catalog.root).epoch_records
    assert epochs["2024"].state == "stale"
    assert epochs["2028"].state == "stale"  # its imputed DBH used 2024's old trees
    assert epochs["2028"].invalidated is not None
    assert "pooled the trees of re-tiled epochs 2024" in epochs["2028"].invalidated["reason"]
    assert epochs["2032"].state == "enriched"  # its own model: untouched


@pytest.mark.slow  # the default suite keeps to its time; CI runs it with -m slow
def test_a_comparison_against_another_catalog_goes_stale_when_that_epoch_changes(
    pair: EnrichedPair, tmp_path: Path
) -> None:
    """``compare --other``: re-tiling (then re-enriching, then removing) the other catalog's
    epoch leaves this catalog's comparison in place, and ``status`` says it is stale."""
    here = copy_catalog(pair.path, tmp_path / "c24")
    other = copy_catalog(pair.path, tmp_path / "c28")
    compare_epochs(here, CompareOptions("2024", "2028", other_catalog=other))
    entry = json.loads((here / "catalog.json").read_text())["comparisons"][PAIR]
    assert entry["other_catalog"] == str(other.resolve())
    assert entry["other_epoch"]["enrichment"]
    assert catalog_status(here)["comparisons"][PAIR]["state"] == "present"

    tile_missions([BUNDLED_MISSIONS / MISSIONS["2028"]], other)  # re-tiled there, no buffer
    seen = catalog_status(here)["comparisons"][PAIR]
    assert seen["state"] == "stale" and "re-tiled" in seen["reason"], seen
    assert str(other.resolve()) in seen["reason"]
    result = CliRunner().invoke(cli, ["status", str(here)])
    assert result.exit_code == 0, result.output
    assert f"{PAIR}  stale" in result.output and "run `standgrid compare` again" in result.output
    with running(create_app(here)) as server:  # the served change layers say so too
        for layer in ("stand_changes", "tree_changes"):
            body = httpx.get(f"{server.base_url}/ogc/collections/{layer}").json()
            assert [s["comparison"] for s in body["standgrid:stale_comparisons"]] == [PAIR]
            assert "stale" in body["description"]

    enrich_catalog(other, EnrichOptions(epochs=("2028",)))  # enriched, but not what was read
    seen = catalog_status(here)["comparisons"][PAIR]
    assert seen["state"] == "stale" and "enriched again" in seen["reason"], seen

    compare_epochs(here, CompareOptions("2024", "2028", other_catalog=other))
    assert catalog_status(here)["comparisons"][PAIR]["state"] == "present"
    (other / "catalog.json").rename(other / "catalog.json.gone")
    seen = catalog_status(here)["comparisons"][PAIR]
    assert seen["state"] == "stale" and "gone" in seen["reason"], seen
