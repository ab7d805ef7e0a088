"""Stand numbers against the simulator's truth when two campaigns cover different ground.

Builds the scenario of ``tests/test_coverage_acceptance.py`` at full size (default: a
200 x 200 m stand, 30 k points per payload, 45 % of one 1 ha stand harvested between the
campaigns), then prints, per epoch and grid level, how many stands are reported and the
error of stems/ha and basal area/ha against the truth over the same observed ground, and
the basal-area change of every co-observed 1 ha stand against the true change.

Not a test (minutes):

    python benchmarks/coverage_accuracy.py                 # 200 m, harvest
    python benchmarks/coverage_accuracy.py --area 160 --no-harvest
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from standgrid.comparison.coverage import CoObserved  # noqa: E402
from standgrid.partition import StandGrid  # noqa: E402
from tests.coverage_scenarios import (  # noqa: E402
    observed_mask,
    run_scenario,
    truth_per_stand,
    truth_trees,
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--area", type=float, default=200.0, help="stand side (m)")
    parser.add_argument("--points", type=int, default=30_000, help="points per payload")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--no-harvest", action="store_true")
    opts = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="standgrid-coverage-") as work:
        started = time.monotonic()
        scenario = run_scenario(
            Path(work),
            seed=opts.seed,
            area=opts.area,
            points_per_payload=opts.points,
            harvest=not opts.no_harvest,
        )
        print(
            f"built in {time.monotonic() - started:.0f} s; harvested stand: "
            f"{scenario.harvest_stand}"
        )
        catalog = scenario.catalog
        state = json.loads((catalog / "catalog.json").read_text())
        grid = StandGrid.from_dict(state["grid"])
        epochs = sorted(state["epochs"])
        metrics = pd.read_parquet(catalog / "tables/stand_metrics.parquet")
        for epoch, truth in zip(epochs, scenario.truth, strict=True):
            mask, raster = observed_mask(catalog, epoch)
            rows = truth_per_stand(
                metrics[metrics["epoch"] == epoch], truth_trees(truth), mask, raster, grid
            )
            for level, name in ((0, "20 m cells"), (1, "1 ha stands")):
                at = rows[rows["level"] == level]
                ok = at[at["stems_ha"].notna()]
                stems = (ok["stems_ha"] / ok["truth_stems_ha"] - 1).abs()
                ba = (ok["basal_area_m2_ha"] / ok["truth_basal_area_m2_ha"] - 1).abs()
                off = ((ok["stems_ha"] - ok["truth_stems_ha"]) * ok["observed_m2"] / 1e4).round()
                short = int((at["observed_fraction"] < 0.25).sum())
                print(
                    f"{epoch} {name}: {len(ok)} of {len(at)} reported ({short} short of "
                    f"coverage, none with a value: {bool(at.loc[at['observed_fraction'] < 0.25, 'stems_ha'].isna().all())}); "  # noqa: E501
                    f"stems/ha error median {stems.median():.1%} max {stems.max():.1%} "
                    f"(trees off: max {int(off.abs().max())}); basal area error median "
                    f"{ba.median():.1%} max {ba.max():.1%}"
                )
            trees = pd.read_parquet(catalog / f"tables/tree_list_{epoch}.parquet")
            print(f"  DBH: {trees['dbh_source'].value_counts().to_dict()}")
        _change(catalog, epochs, scenario.truth, grid)


def _change(catalog: Path, epochs: list[str], truths: list[Path], grid: StandGrid) -> None:
    """Basal-area change per co-observed 1 ha stand against the truth's."""
    e1, e2 = epochs
    changes = pd.read_parquet(catalog / f"compare/{e1}__{e2}/stand_changes.parquet")
    stands = changes[(changes["level"] == 1) & changes["basal_area_m2_ha_delta"].notna()]
    co = CoObserved.read(
        catalog / f"rasters/{e1}/observed.tif", catalog / f"rasters/{e2}/observed.tif"
    )
    sides = []
    for truth in truths:
        trees = truth_trees(truth)
        trees = trees[co.at(trees["x"].to_numpy(), trees["y"].to_numpy())]
        stand = [str(grid.cell(x, y, level=1)) for x, y in zip(trees["x"], trees["y"], strict=True)]
        sides.append(pd.Series(np.pi * (trees["dbh_m"].to_numpy() / 2) ** 2).groupby(stand).sum())
    for row in stands.itertuples():
        ha = row.co_observed_m2 / 1e4
        true_delta = (sides[1].get(row.cell_id, 0.0) - sides[0].get(row.cell_id, 0.0)) / ha
        print(
            f"{row.cell_id}: co-observed {row.co_observed_fraction:.0%}; basal area "
            f"{row.basal_area_m2_ha_from:.1f} -> {row.basal_area_m2_ha_to:.1f} m2/ha, change "
            f"{row.basal_area_m2_ha_delta:+.2f} vs true {true_delta:+.2f} "
            f"({abs(row.basal_area_m2_ha_delta - true_delta) / abs(true_delta):.1%} of it); "
            f"{row.trees_removed} removed"
        )


if __name__ == "__main__":
    main()
