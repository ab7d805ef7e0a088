"""``standgrid run``, ``enrich`` and ``compare`` through click's CliRunner: one full run of the
bundled pair, JSON sections, re-enriching an existing catalog (idempotent), and one-line
typed errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner, Result

from standgrid.cli import cli
from tests.conftest import BUNDLED_MISSIONS
from tests.pipeline_fixtures import (
    MISSIONS,
    EnrichedPair,
    copy_catalog,
    enriched_pair,
    tiled_grid25,
)


@pytest.fixture(scope="session")
def pair(tmp_path_factory: pytest.TempPathFactory) -> EnrichedPair:
    return enriched_pair(tmp_path_factory)


@pytest.fixture(scope="module")
def reenriched(pair: EnrichedPair, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Result]:
    """A copy of the shared catalog enriched again with ``standgrid enrich --json``."""
    catalog = copy_catalog(pair.path, tmp_path_factory.mktemp("reenrich") / "catalog")
    result = CliRunner().invoke(cli, ["enrich", str(catalog), "--json", "-q"])
    return catalog, result


def _error_lines(output: str) -> list[str]:
    return [line for line in output.splitlines() if line.startswith("Error:")]


def test_run_the_bundled_pair_and_print_the_qgis_guide(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    out.mkdir()  # an empty folder becomes the catalog
    result = CliRunner().invoke(
        cli, ["run", str(BUNDLED_MISSIONS), "-o", str(out), "--overwrite", "-q"]
    )
    assert result.exit_code == 0, result.output
    text = result.output
    assert "Open it in QGIS" in text
    assert str(out / "index.gpkg") in text
    assert str(out / "catalog.qgz") in text and (out / "catalog.qgz").is_file()
    for epoch in MISSIONS:
        assert str(out / f"tiles_{epoch}.vpc") in text
        assert (out / f"tiles_{epoch}.vpc").is_file()
    assert "2024 -> 2028 (4.02 years)" in text
    assert str(out / "compare/2024__2028/chm_diff.tif") in text
    metrics = pd.read_parquet(out / "tables/stand_metrics.parquet")
    assert sorted(metrics["epoch"].unique()) == ["2024", "2028"]
    assert (out / "compare/2024__2028/stand_changes.parquet").is_file()


def test_run_json_has_tile_enrich_and_compare_sections(tmp_path: Path) -> None:
    """One mission (one epoch, a few seconds): compare is null, not missing."""
    mission = BUNDLED_MISSIONS / MISSIONS["2028"]
    result = CliRunner().invoke(
        cli, ["run", str(mission), "-o", str(tmp_path / "one"), "--json", "-q"]
    )
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert set(report) == {"tile", "enrich", "compare"}
    assert report["tile"]["conserved"] is True
    assert list(report["tile"]["epochs"]) == ["2028"]
    assert report["enrich"]["epochs"]["2028"]["trees"] > 150
    assert report["compare"] is None


def test_run_refuses_a_folder_with_files_without_overwrite(tmp_path: Path) -> None:
    out = tmp_path / "taken"
    out.mkdir()
    (out / "notes.txt").write_text("not a catalog")
    result = CliRunner().invoke(cli, ["run", str(BUNDLED_MISSIONS), "-o", str(out)])
    assert result.exit_code == 1
    lines = _error_lines(result.output)
    assert len(lines) == 1 and lines[0].startswith("Error: OutputExistsError: ")
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_overwrite_never_replaces_a_folder_that_is_not_a_catalog(tmp_path: Path) -> None:
    """``--overwrite`` replaces a catalog only: a folder of missions given as the output by
    mistake is left as it is (it used to be swapped for the new catalog and deleted)."""
    import shutil

    out = tmp_path / "missions"
    shutil.copytree(BUNDLED_MISSIONS, out)
    before = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
    mission = next(p for p in sorted(BUNDLED_MISSIONS.iterdir()) if p.is_dir())
    for command in (["tile", str(mission)], ["run", str(mission)]):
        result = CliRunner().invoke(cli, [*command, "-o", str(out), "--overwrite"])
        assert result.exit_code == 1, result.output
        lines = _error_lines(result.output)
        assert len(lines) == 1 and "is a folder with files that is not a catalog" in lines[0]
        assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == before


def test_enrich_json_on_an_existing_catalog(
    pair: EnrichedPair, reenriched: tuple[Path, Result]
) -> None:
    catalog, result = reenriched
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert report["catalog"] == str(catalog)
    assert list(report["epochs"]) == ["2024", "2028"]
    for epoch, summary in report["epochs"].items():
        trees = pd.read_parquet(catalog / f"tables/tree_list_{epoch}.parquet")
        assert summary["trees"] == len(trees) > 150
        assert summary["trees_dbh_measured"] == int((trees["dbh_source"] == "measured").sum())
        assert summary["trees_dbh_imputed"] == int((trees["dbh_source"] == "imputed").sum())
        assert trees["dbh_m"].notna().all()  # every tree gets a DBH, measured or imputed
        assert summary["cells"] == pair.report["enrich"]["epochs"][epoch]["cells"]
        assert summary["cells_without_ground"] == 0


def test_enrich_again_is_idempotent(pair: EnrichedPair, reenriched: tuple[Path, Result]) -> None:
    catalog, result = reenriched
    assert result.exit_code == 0, result.output
    first = pd.read_parquet(pair.path / "tables/stand_metrics.parquet")
    again = pd.read_parquet(catalog / "tables/stand_metrics.parquet")
    pd.testing.assert_frame_equal(first, again)
    for epoch in MISSIONS:
        a = pd.read_parquet(pair.path / f"tables/tree_list_{epoch}.parquet")
        b = pd.read_parquet(catalog / f"tables/tree_list_{epoch}.parquet")
        pd.testing.assert_frame_equal(a, b)
    import pyogrio

    layers = {name for name, _ in pyogrio.list_layers(catalog / "index.gpkg")}
    assert {"stand_metrics", "trees"} <= layers
    assert len(pyogrio.read_dataframe(catalog / "index.gpkg", layer="stand_metrics")) == len(first)


def test_compare_json_on_an_existing_catalog(
    pair: EnrichedPair, reenriched: tuple[Path, Result]
) -> None:
    catalog, _ = reenriched
    result = CliRunner().invoke(
        cli, ["compare", str(catalog), "--from", "2024", "--to", "2028", "--json", "-q"]
    )
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert report["epoch_from"] == "2024" and report["epoch_to"] == "2028"
    assert round(report["years"], 2) == 4.02
    statuses = pd.read_parquet(catalog / report["outputs"]["tree_parquet"])["status"]
    counts = statuses.value_counts().reindex(report["trees"], fill_value=0).to_dict()
    assert report["trees"] == counts
    assert report["trees"]["removed"] >= 25  # the simulated harvest: 27 trees, 90 % found
    assert report["stands"] == {"in_both": 28, "from_only": 0, "to_only": 0}
    changes = pd.read_parquet(catalog / report["outputs"]["stand_parquet"])
    measured = changes["null_reason"].isna()
    assert measured.sum() >= 20  # the stands both epochs observed well enough
    assert np.isfinite(changes.loc[measured, "zq95_per_year"]).all()
    assert changes.loc[~measured, "null_reason"].str.contains("insufficient_coverage").all()


def test_compare_before_enrich_is_a_one_line_error(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    catalog = tiled_grid25(tmp_path_factory)
    result = CliRunner().invoke(cli, ["compare", str(catalog)])
    assert result.exit_code == 1
    lines = _error_lines(result.output)
    assert len(lines) == 1 and lines[0].startswith("Error: EnrichError: ")
    assert "standgrid enrich" in lines[0]


def test_unknown_epoch_is_a_one_line_error(pair: EnrichedPair) -> None:
    for args in (
        ["enrich", str(pair.path), "--epoch", "1999"],
        ["compare", str(pair.path), "--from", "1999"],
    ):
        result = CliRunner().invoke(cli, args)
        assert result.exit_code == 1
        lines = _error_lines(result.output)
        assert len(lines) == 1 and lines[0].startswith("Error: EpochNotFoundError: "), args


def test_compare_other_grid_is_a_one_line_error(
    pair: EnrichedPair, tmp_path_factory: pytest.TempPathFactory
) -> None:
    other = tiled_grid25(tmp_path_factory)
    result = CliRunner().invoke(cli, ["compare", str(pair.path), "--other", str(other)])
    assert result.exit_code == 1
    lines = _error_lines(result.output)
    assert len(lines) == 1 and lines[0].startswith("Error: GridMismatchError: ")


@pytest.mark.parametrize("command", ["run", "enrich", "compare"])
def test_help_has_an_example(command: str) -> None:
    result = CliRunner().invoke(cli, [command, "--help"])
    assert result.exit_code == 0
    assert "Example:" in result.output


@pytest.mark.slow  # a whole CLI run or a cluster in a subprocess (CI runs it)
def test_compare_help_example_with_another_catalog_runs_verbatim(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``standgrid compare catalog-2024 --other catalog-2028 --json`` from ``compare --help``,
    on two catalogs of one epoch each: the epochs are the only ones of each catalog."""
    import shlex

    help_text = CliRunner().invoke(cli, ["compare", "--help"]).output
    example = next(
        line.strip()
        for line in help_text.splitlines()
        if "--other" in line and line.strip().startswith("standgrid compare")
    )
    words = shlex.split(example)[1:]
    runner = CliRunner()
    monkeypatch.chdir(tmp_path)
    for epoch, name in MISSIONS.items():
        catalog = f"catalog-{epoch}"
        tiled = runner.invoke(cli, ["tile", str(BUNDLED_MISSIONS / name), "-o", catalog, "-q"])
        assert tiled.exit_code == 0, tiled.output
        assert runner.invoke(cli, ["enrich", catalog, "-q"]).exit_code == 0
    result = runner.invoke(cli, words)
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert (report["epoch_from"], report["epoch_to"]) == ("2024", "2028")
    assert round(report["years"], 2) == 4.02  # the missions' dates, 2024-05-14 to 2028-05-20
    assert (tmp_path / "catalog-2024" / report["outputs"]["tree_parquet"]).is_file()
    # giving either epoch alone works too; one catalog of one epoch still needs two
    for given in (["--to", "2028"], ["--from", "2024"]):
        again = runner.invoke(cli, [*words, *given])
        assert again.exit_code == 0, (given, again.output)
        assert json.loads(again.stdout)["epoch_to"] == "2028"
    alone = runner.invoke(cli, ["compare", "catalog-2024"])
    assert alone.exit_code == 1
    assert "needs two epochs (or --other" in alone.output


def test_an_existing_output_names_the_cli_flag_and_the_library_stays_neutral(
    pair: EnrichedPair, tmp_path: Path
) -> None:
    """The CLI says ``--overwrite`` (its flag); the library's message says ``overwrite``
    without a flag's dashes (a script passes ``overwrite=True``)."""
    from standgrid.catalog import Catalog
    from standgrid.errors import OutputExistsError
    from standgrid.growth.treelist import generic_tree_list, write_tree_list

    out = tmp_path / "trees.csv"
    args = ["export", "trees", str(pair.path), "-o", str(out), "-q"]
    assert CliRunner().invoke(cli, args).exit_code == 0
    first = out.read_bytes()
    again = CliRunner().invoke(cli, args)
    assert again.exit_code == 1
    assert _error_lines(again.output) == [
        f"Error: OutputExistsError: {out}: exists (--overwrite replaces it)"
    ]
    assert out.read_bytes() == first
    with Catalog.reading(pair.path) as catalog:
        table = generic_tree_list(catalog, None, level=1)
    with pytest.raises(OutputExistsError) as refused:
        write_tree_list(table, out, crs=catalog.crs, fmt=None, overwrite=False)
    assert str(refused.value).endswith("exists (option overwrite replaces it)")


def test_run_replaces_a_mission_from_another_folder_only_with_replace(tmp_path: Path) -> None:
    """The hint of the refusal names ``--replace``, which ``run`` has as ``tile`` does."""
    import shutil

    mission = next(p for p in sorted(BUNDLED_MISSIONS.iterdir()) if p.is_dir())
    out = tmp_path / "catalog"
    assert CliRunner().invoke(cli, ["tile", str(mission), "-o", str(out), "-q"]).exit_code == 0
    copy = shutil.copytree(mission, tmp_path / "elsewhere" / mission.name)
    refused = CliRunner().invoke(cli, ["run", str(copy), "-o", str(out), "-q"])
    assert refused.exit_code == 1
    assert "MissionFolderConflictError" in refused.output and "--replace" in refused.output
    replaced = CliRunner().invoke(cli, ["run", str(copy), "-o", str(out), "-q", "--replace"])
    assert replaced.exit_code == 0, replaced.output
