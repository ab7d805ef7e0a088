"""Issue 20's acceptance on simulated missions under a canopy (tests/align_scenarios.py):
GNSS biased by a metre, walking 2 m over minutes and stating 0.5 m; two robots on one day
and a re-survey four years later. Slow: CI runs them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tests.align_scenarios import placements, simulate

pytestmark = pytest.mark.slow
SEED = 7


@pytest.fixture(scope="module")
def campaigns(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("canopy_gnss")
    simulate(root, SEED)
    return root


def _missions(root: Path) -> list[Path]:
    return sorted((root / "missions").iterdir())


def test_overlapping_missions_agree_within_5_cm_and_state_a_true_sigma(
    campaigns: Path, tmp_path: Path
) -> None:
    import pyogrio

    from standgrid.pipeline.tile import tile_missions
    from standgrid.tiling.options import TileOptions

    gnss = tile_missions(_missions(campaigns), tmp_path / "gnss", TileOptions(align=False))
    assert gnss.alignment is None
    before = placements(campaigns, tmp_path / "gnss")
    report = tile_missions(_missions(campaigns), tmp_path / "aligned", TileOptions())
    after = placements(campaigns, tmp_path / "aligned")
    print("\nGNSS only:\n" + before.report() + "\naligned:\n" + after.report())
    assert report.alignment is not None and not report.alignment["warnings"]
    assert all(r["accepted"] for r in report.alignment["registrations"])
    assert len(after.apart) == 3
    for pair, apart in after.apart.items():
        assert np.median(apart) <= 0.05, pair
        assert np.median(before.apart[pair]) >= 0.3, pair  # the hard case it is
    for name in after.error:
        # the true error within the stated 2-sigma (DRMS) for >= 90 % of the nodes
        assert after.coverage(name) >= 0.9, name
        assert np.median(after.error[name]) <= np.median(before.error[name]) + 0.2
    layer = pyogrio.read_dataframe(tmp_path / "aligned" / "index.gpkg", layer="missions")
    by_name = layer.set_index("mission")
    for name, sigma in after.sigma_h.items():
        assert by_name.loc[name, "aligned"]
        assert by_name.loc[name, "sigma_h_m"] == pytest.approx(sigma)
        assert 0 < by_name.loc[name, "sigma_rel_m"] < 0.1


def _stems_ha(catalog: Path, epoch: str) -> pd.Series:
    metrics = pd.read_parquet(catalog / "tables/stand_metrics.parquet")
    rows = metrics[(metrics["epoch"].astype(str) == epoch) & (metrics["level"] == 1)]
    return rows.set_index("cell_id")["stems_ha"].dropna()


def test_two_robots_on_one_day_count_each_tree_once(campaigns: Path, tmp_path: Path) -> None:
    """Both robots' missions of one day tiled into one epoch: no tree counted twice. The
    1 ha stand's stems/ha stays at or below the truth over its observed ground (GNSS alone
    puts the same trees twice: far above it), precision (against the truth moved by the
    map's absolute placement error) stays that of one robot, and the second robot's other
    path finds trees the first missed (more than one robot's count: the issue's "within
    5 % of one robot" does not hold for that reason, reported)."""
    from standgrid.pipeline.run import run_pipeline
    from standgrid.simulate import load_truth
    from standgrid.tiling.options import TileOptions
    from tests.tree_truth import inset_of, scores, truth_table
    from tests.under_canopy_scenarios import _cell_bounds, stand_truth

    a, b = (m for m in _missions(campaigns) if m.name.startswith("2024"))
    truth = load_truth(campaigns / "truth" / a.name)
    assert truth.trees is not None
    table = truth_table(truth.trees)
    inside = inset_of(truth.bounds, 5.0)
    got = {}
    for label, missions, align in (
        ("one", [a], True),
        ("both", [a, b], True),
        ("both_gnss", [a, b], False),
    ):
        catalog = tmp_path / label
        run_pipeline(missions, catalog, TileOptions(align=align))
        stems = _stems_ha(catalog, "2024")
        assert len(stems) >= 1
        cell = str(stems.index[0])
        _, true_ha, _ = stand_truth(
            table, catalog / "rasters/2024/observed.tif", _cell_bounds(cell)
        )
        found = pd.read_parquet(catalog / "tables/tree_list_2024.parquet")
        # the truth where this map put robot A's ground (its absolute placement error)
        where = placements(campaigns, catalog)
        stem_xy = where.placed(a.name, table[["x", "y"]].to_numpy())
        crown_xy = where.placed(a.name, table[["cx", "cy"]].to_numpy())
        placed = table.assign(
            x=stem_xy[:, 0], y=stem_xy[:, 1], cx=crown_xy[:, 0], cy=crown_xy[:, 1]
        )
        got[label] = (float(stems.iloc[0]) / true_ha, scores(found, placed, inside))
    print(
        "\nstems/ha / truth, precision: "
        + ", ".join(f"{k} {r:.3f}, {s.precision:.3f}" for k, (r, s) in got.items())
    )
    one, both, gnss = got["one"], got["both"], got["both_gnss"]
    assert both[0] <= 1.05 and gnss[0] > 1.15  # the same trees twice without alignment
    assert both[1].precision >= one[1].precision - 0.02
    assert both[0] >= one[0] - 0.02


def test_a_resurvey_is_as_repeatable_as_with_exact_placement(tmp_path: Path) -> None:
    """The same ground four years later, no harvest: compare calls no more trees removed or
    new than with exact placement (the true georeference), and the trees it pairs stand
    at most 10 cm apart (median)."""
    from standgrid.pipeline.run import run_pipeline
    from standgrid.tiling.options import TileOptions

    counts, distance = {}, {}
    for how in ("exact", "aligned", "gnss"):
        root = tmp_path / how
        simulate(root, 5, exact=how == "exact", epochs=(1, 2))
        catalog = root / "catalog"
        # exact: the pose graphs' true georeference, as it is
        run_pipeline([root / "missions"], catalog, TileOptions(align=how == "aligned"))
        changes = pd.read_parquet(next(catalog.glob("compare/*/tree_changes.parquet")))
        status = changes["status"].value_counts()
        counts[how] = int(status.get("removed", 0) + status.get("new", 0))
        paired = changes[changes["status"] == "grown"]
        distance[how] = float(paired["distance_m"].median())
    print(f"\nremoved + new: {counts}; paired trees apart (median, m): {distance}")
    assert counts["aligned"] <= counts["exact"] + 2
    assert distance["aligned"] <= 0.10


def test_a_mission_without_gnss_is_placed_by_the_catalog(campaigns: Path, tmp_path: Path) -> None:
    """Robot B's mission with its GNSS removed (no fixes, no anchor), tiled into a catalog
    of robot A's and the 2028 mission: the global stem search places it, within 10 cm of
    both (co-located nodes), with the catalog's own absolute uncertainty."""
    import shutil

    from standgrid.pipeline.tile import tile_missions
    from standgrid.tiling.options import TileOptions

    root = tmp_path / "nognss"
    (root / "missions").mkdir(parents=True)
    shutil.copytree(campaigns / "truth", root / "truth")
    for mission in _missions(campaigns):
        shutil.copytree(mission, root / "missions" / mission.name)
    lost = next(m for m in (root / "missions").iterdir() if "spot" in m.name)
    shutil.rmtree(lost / "gnss")
    shutil.rmtree(lost / "payloads" / "gnss", ignore_errors=True)
    others = [m for m in sorted((root / "missions").iterdir()) if m != lost]
    catalog = root / "catalog"
    tile_missions(others, catalog, TileOptions())
    report = tile_missions([lost], catalog, TileOptions())
    assert report.alignment is not None
    mine = report.alignment["missions"][lost.name]
    assert mine["aligned"] and mine["sigma_prior_m"] is None
    assert sorted(mine["registered_with"]) == sorted(m.name for m in others)
    got = placements(root, catalog)
    print("\n" + got.report())
    for pair, apart in got.apart.items():
        if lost.name in pair:
            assert np.median(apart) <= 0.10, pair
    assert got.coverage(lost.name) >= 0.9
    # without alignment there is no placing it: a clear error, not a guess
    from standgrid.errors import NotGeoreferencedError

    with pytest.raises(NotGeoreferencedError, match="anchor"):
        tile_missions([lost], root / "alone", TileOptions(align=False))
