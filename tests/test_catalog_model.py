"""catalog.paths is the only module spelling catalog paths; catalog.records are frozen views."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest

from standgrid.catalog import EpochRecord, MissionRecord, paths

PACKAGE = Path(__file__).resolve().parents[1] / "standgrid"
PREFIXES = ("rasters/", "tables/", "tiles/", "tiles_", "compare/")
NAMES = ("index.gpkg", "catalog.json")


def test_paths_spell_the_documented_layout() -> None:
    assert (paths.CATALOG_FILE, paths.INDEX) == ("catalog.json", "index.gpkg")
    assert paths.vpc("2024") == "tiles_2024.vpc"
    assert paths.tile("2024", "20m_E1_N2") == "tiles/2024/20m_E1_N2.laz"
    assert paths.tile("2024", "20m_E1_N2", laz=False) == "tiles/2024/20m_E1_N2.las"
    assert paths.raster("2024", "chm") == "rasters/2024/chm.tif"
    assert paths.raster_style("2024", "chm") == "rasters/2024/chm.qml"
    assert paths.stand_metrics("parquet") == "tables/stand_metrics.parquet"
    assert paths.tree_list("2028", "csv") == "tables/tree_list_2028.csv"
    assert paths.comparison("2024", "2028") == "compare/2024__2028"
    assert paths.comparison("2024", "2028", "chm_diff.tif") == "compare/2024__2028/chm_diff.tif"
    assert paths.comparison_folder(paths.comparison_key("a", "b")) == "compare/a__b"


def _docstrings(tree: ast.AST) -> set[int]:
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                found.add(id(body[0].value))
    return found


def test_no_other_module_spells_a_catalog_path() -> None:
    offenders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path == PACKAGE / "catalog" / "paths.py":
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        docs = _docstrings(tree)
        for node in ast.walk(tree):
            if not isinstance(node, ast.Constant) or not isinstance(node.value, str):
                continue
            if id(node) in docs:
                continue
            text = node.value
            if text.startswith("tiles_") and not (text == "tiles_" or text.endswith(".vpc")):
                continue  # a word like "tiles_with_points", not an epoch's VPC
            if text in NAMES or text.startswith(PREFIXES):
                offenders.append(f"{path.relative_to(PACKAGE)}:{node.lineno}: {text!r}")
    assert offenders == []


def test_records_are_frozen_views_of_catalog_json() -> None:
    entry = {
        "date": "2024-05-14",
        "missions": ["m1", "m2"],
        "enriched": False,
        "invalidated": {"at": "2026-01-01T00:00:00Z", "reason": "re-tiled", "comparisons": []},
        "comparisons_invalidated": {"2024__2028": {"at": "t", "reason": "r"}},
    }
    epoch = EpochRecord.from_json("2024", entry)
    assert (epoch.label, epoch.date, epoch.missions) == ("2024", "2024-05-14", ("m1", "m2"))
    assert epoch.state == "stale" and not epoch.enriched
    entry["invalidated"]["reason"] = "changed"  # a view, not an alias of the state
    assert epoch.invalidated is not None and epoch.invalidated["reason"] == "re-tiled"
    assert EpochRecord.from_json("x", {"missions": [], "enriched": True}).state == "enriched"
    assert EpochRecord.from_json("x", {"missions": []}).state == "not enriched"
    with pytest.raises(dataclasses.FrozenInstanceError):
        epoch.enriched = True  # type: ignore[misc]

    mission = MissionRecord.from_json(
        "m1",
        {
            "number": 3,
            "epoch": "2024",
            "date": "2024-05-14",
            "tiles": ["tiles/2024/a.laz"],
            "point_count": 12,
            "payload_count": 2,
            "sensors": ["lidar"],
            "simulator": {"seed": 1},
        },
    )
    assert (mission.number, mission.epoch, mission.point_count) == (3, "2024", 12)
    assert mission.tiles == ("tiles/2024/a.laz",) and mission.sensors == ("lidar",)
    assert mission.extra == {"simulator": {"seed": 1}}
    with pytest.raises(KeyError):
        MissionRecord.from_json("m0", {"epoch": "2024"})  # no number: not a mission entry
