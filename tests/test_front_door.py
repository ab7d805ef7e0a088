"""The front door: ``import standgrid`` is light, and a script uses nothing but its names."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import BUNDLED_MISSIONS, REPO_ROOT
from tests.pipeline_fixtures import BUFFER_M, CRS, MISSIONS, EnrichedPair, enriched_pair

HEAVY = ("numpy", "scipy", "pandas", "geopandas", "pyogrio", "laspy", "rasterio", "pyproj")


def test_import_standgrid_imports_no_heavy_library() -> None:
    code = (
        "import sys, standgrid\n"
        "assert callable(standgrid.__getattr__)\n"
        f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.strip()
    assert out == ""


def test_every_front_door_name_resolves() -> None:
    import inspect
    import types

    import standgrid
    from standgrid import api
    from standgrid.engine.execution import Execution

    for name in standgrid.__all__:
        assert getattr(standgrid, name) is not None, name
    import standgrid.alignment.graph
    import standgrid.comparison.trees
    import standgrid.enrichment.ground  # stage packages are nouns: no verb is rebound

    for verb in api.__all__:  # the typed verbs, every one verb(input, options, *, execution)
        found = getattr(standgrid, verb)
        assert not isinstance(found, types.ModuleType), verb
        assert found is getattr(api, verb), verb
        parameters = inspect.signature(getattr(api, verb)).parameters
        assert parameters["execution"].kind is inspect.Parameter.KEYWORD_ONLY, verb
    assert standgrid.Execution is Execution
    with pytest.raises(AttributeError, match="no attribute 'tile_missions'"):
        _ = standgrid.tile_missions  # type: ignore[attr-defined]


def test_options_and_execution_validate_themselves() -> None:
    """A value out of range is refused when the options are made, naming the field (the
    library's name: the CLI alone says its flag)."""
    import standgrid

    for make, option in (
        (lambda: standgrid.Execution(workers=0), "workers"),
        (lambda: standgrid.Execution(workers=2, scheduler="tcp://h:8786"), "scheduler"),
        (lambda: standgrid.Execution(scheduler="not an address"), "scheduler"),
        (lambda: standgrid.Execution(memory_mb=8), "memory_mb"),
        (lambda: standgrid.Execution(lock_timeout=-1.0), "lock_timeout"),
        (lambda: standgrid.Execution(lock_timeout=True), "lock_timeout"),  # not 1 s
        (lambda: standgrid.TileOptions(buffer=-1.0), "buffer"),
        (lambda: standgrid.TileOptions(anchor=(91.0, 0.0, 0.0, 0.0)), "anchor"),
        (lambda: standgrid.TileOptions(epoch="a/b"), "epoch"),
        (lambda: standgrid.EnrichOptions(pixel_size=0.0), "pixel_size"),
        (lambda: standgrid.EnrichOptions(min_observed_fraction=1.5), "min_observed_fraction"),
        (lambda: standgrid.CompareOptions(max_distance=-2.0), "max_distance"),
    ):
        with pytest.raises(standgrid.OptionError) as refused:
            make()
        assert refused.value.option == option
        assert str(refused.value).startswith(f"option {option}: ") and "--" not in str(
            refused.value
        )
    assert standgrid.Execution(scheduler="tcp://127.0.0.1:8786").scheduler is not None


def test_mission_does_not_import_georeference() -> None:
    root = Path(__file__).resolve().parents[1] / "standgrid" / "mission"
    offenders = [
        f"{path.name}:{number}"
        for path in sorted(root.glob("*.py"))
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if "import" in line and "standgrid.georeference" in line
    ]
    assert offenders == []


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> EnrichedPair:
    """The same missions through the pipeline modules (shared with the acceptance tests)."""
    return enriched_pair(tmp_path_factory)


@pytest.mark.slow
def test_a_script_through_the_front_door(tmp_path: Path, pair: EnrichedPair) -> None:
    """open_mission -> tile (opened missions) -> enrich -> compare -> open_catalog, and the
    three retrievals, give the reports the pipeline modules give for the same missions."""
    import pyogrio
    from pyproj import Transformer

    import standgrid

    missions = [standgrid.open_mission(BUNDLED_MISSIONS / name) for name in MISSIONS.values()]
    out = tmp_path / "catalog"
    tiled = standgrid.tile(missions, out, standgrid.TileOptions(buffer=BUFFER_M))
    enriched = standgrid.enrich(out, standgrid.EnrichOptions(), execution=standgrid.Execution())
    compared = standgrid.compare(out)

    # the reports: conserved points, the same numbers as the pipeline modules' run
    ref = pair.report
    assert tiled.points_in == tiled.points_out == ref["tile"]["points_in"] > 0
    assert tiled.crs == CRS and tiled.grid_fingerprint == ref["tile"]["grid_fingerprint"]
    for epoch, summary in ref["tile"]["epochs"].items():
        assert tiled.epochs[epoch]["points_out"] == summary["points_out"]
    assert sorted(enriched.epochs) == sorted(MISSIONS)
    for epoch, summary in ref["enrich"]["epochs"].items():
        assert enriched.epochs[epoch]["trees"] == summary["trees"] > 150
        assert enriched.epochs[epoch]["cells"] == summary["cells"]
    assert (compared.epoch_from, compared.epoch_to) == ("2024", "2028")
    assert compared.trees == ref["compare"]["trees"]
    assert compared.trees["removed"] >= 25  # the simulated harvest: 27 trees, 90 % found
    assert (out / compared.outputs["chm_difference"]).is_file()

    # the catalog, opened for reading, as typed records
    catalog = standgrid.open_catalog(out)
    assert isinstance(catalog, standgrid.Catalog)
    epochs = catalog.epoch_records
    assert sorted(epochs) == sorted(MISSIONS)
    assert all(record.enriched and record.state == "enriched" for record in epochs.values())
    records = catalog.mission_records
    for epoch, name in MISSIONS.items():
        assert records[name].epoch == epoch
        assert records[name].point_count == tiled.missions[name]["points"]
        assert set(records[name].tiles) <= set(catalog.tiles(epoch))
    grid = standgrid.StandGrid.from_dict(catalog.grid_definition)
    assert grid.cell_size == 20.0

    # retrieval: by type, by pose, and by GNSS from a payload's position in the catalog
    mission = missions[0]
    clouds = standgrid.retrieve_payload_by_type(mission, "point_cloud")
    assert len(clouds) == tiled.missions[mission.name]["payloads"]
    payloads = pyogrio.read_dataframe(out / "index.gpkg", layer="payloads")
    rows = payloads[payloads["mission"] == mission.name].sort_values("stamp_sec")
    to_lla = Transformer.from_crs(CRS, "EPSG:4326", always_xy=True)
    for _, row in rows.iloc[:: max(1, len(rows) // 4)].iterrows():
        lon, lat = to_lla.transform(row["x"], row["y"])
        (hit,) = standgrid.retrieve_payload_by_gnss(mission, (lat, lon))
        assert (hit.stamp.sec, hit.stamp.nsec) == (row["stamp_sec"], row["stamp_nsec"])
        (same,) = standgrid.retrieve_payload_by_pose(mission, mission.pose_of(hit)[:3, 3])
        assert same.stamp == hit.stamp
    assert np.isfinite(rows[["x", "y"]].to_numpy()).all()


@pytest.mark.slow  # a whole CLI run or a cluster in a subprocess (CI runs it)
def test_the_readme_python_snippet_runs_as_a_script(tmp_path: Path) -> None:
    """README's front-door example (it starts dask workers, which Python spawns: they import
    the script again) run verbatim as a script from a folder holding the bundled data."""
    import os
    import re

    readme = (REPO_ROOT / "README.md").read_text(encoding="utf-8")
    snippet = re.search(r"```python\n(.*?)```", readme, re.S)
    assert snippet is not None and "workers=" in snippet.group(1)
    script = tmp_path / "front_door.py"
    script.write_text(snippet.group(1), encoding="utf-8")
    (tmp_path / "data").symlink_to(REPO_ROOT / "data")  # the paths it names, not a copy
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    done = subprocess.run(
        [sys.executable, str(script)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert "2024 2024-05-14 enriched" in done.stdout and "tiles" in done.stdout
    assert (tmp_path / "catalog" / "tables" / "tree_list_2024.parquet").is_file()
