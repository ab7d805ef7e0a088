"""FVS export: stands run through the real FVS (pyfvs) and its year-0 summary matches
standgrid's stand table in FVS units; DG/HTG from the second campaign reach FVS."""

from __future__ import annotations

import os
import sqlite3
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from standgrid.growth.fvs import (
    BA_M2HA_TO_FT2AC,
    CM_PER_IN,
    M2_PER_ACRE,
    M_PER_FT,
    export_fvs,
    keyword_file,
)
from tests.conftest import BUNDLED_MISSIONS
from tests.pipeline_fixtures import MISSIONS, copy_catalog, enriched_pair


@pytest.fixture(scope="module")
def pyfvs_fvs(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """pyfvs, imported from a scratch folder: on import it opens ./pyfvs.log for logging."""
    here = os.getcwd()
    os.chdir(tmp_path_factory.mktemp("pyfvs"))
    try:
        return pytest.importorskip("pyfvs.fvs")
    finally:
        os.chdir(here)


@pytest.fixture(scope="module")
def catalog(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return enriched_pair(tmp_path_factory).path


@pytest.fixture(scope="module")
def exported(catalog: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("fvs") / "stands.db"
    report = export_fvs(catalog, out, species="DF")
    return out, report.to_dict()


def _tables(db: Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    with sqlite3.connect(db) as conn:
        stands = pd.read_sql("SELECT * FROM FVS_StandInit", conn)
        trees = pd.read_sql("SELECT * FROM FVS_TreeInit", conn)
    conn.close()
    return stands, trees


def _run_fvs(pyfvs_fvs: Any, db: Path, stand_id: str, workdir: Path) -> tuple[pd.DataFrame, str]:
    """Run one stand for two 10-year cycles; FVS's own summary table and main output."""
    out_db = workdir / f"{stand_id}_out.db"
    key = workdir / f"{stand_id}.key"
    key.write_text(keyword_file(db, [stand_id], cycles=2, output_database=out_db))
    fvs = pyfvs_fvs.FVS("PN", workspace=str(workdir), cleanup=False)
    fvs.init_projection(str(key))
    fvs.grow(0)
    fvs.end_projection()
    with sqlite3.connect(out_db) as conn:
        summary = pd.read_sql("SELECT * FROM FVS_Summary ORDER BY Year", conn)
    conn.close()
    return summary, key.with_suffix(".out").read_text(errors="replace")


def test_year0_summary_matches_stand_table(
    pyfvs_fvs: Any,
    catalog: Path,
    exported: tuple[Path, dict],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.chdir(tmp_path)  # pyfvs logs to ./pyfvs.log
    db, report = exported
    stands, trees = _tables(db)
    assert report["stands"] == len(stands) >= 2 and report["trees"] == len(trees)
    metrics = pd.read_parquet(catalog / "tables" / "stand_metrics.parquet")
    metrics["epoch"] = metrics["epoch"].astype(str)
    for stand in stands.itertuples():
        row = metrics[
            (metrics["cell_id"] == stand.SG_Cell_ID)
            & (metrics["epoch"] == stand.SG_Epoch)
            & (metrics["level"] == 1)
        ].iloc[0]
        acres = row["observed_m2"] / M2_PER_ACRE
        assert stand.Inv_Plot_Size == pytest.approx(1.0 / acres, rel=1e-12)
        expected = row  # every counted tree has a DBH: the catalog's own stand row
        assert stand.SG_Trees_Without_DBH == 0
        summary, _ = _run_fvs(pyfvs_fvs, db, stand.Stand_ID, tmp_path)
        year0 = summary.iloc[0]
        assert int(year0["Year"]) == stand.Inv_Year
        tpa = expected["stems_ha"] * M2_PER_ACRE / 10_000.0
        ba = expected["basal_area_m2_ha"] * BA_M2HA_TO_FT2AC
        qmd = expected["qmd_cm"] / CM_PER_IN
        top = expected["dominant_height_m"] / M_PER_FT
        print(
            f"{stand.Stand_ID}: TPA {year0['Tpa']} vs {tpa:.2f}, BA {year0['BA']} vs "
            f"{ba:.2f} ft2/ac, QMD {year0['QMD']:.3f} vs {qmd:.3f} in, "
            f"TopHt {year0['TopHt']} vs {top:.2f} ft"
        )
        # FVS prints TPA, BA and top height as whole numbers: equal within rounding.
        assert abs(year0["Tpa"] - tpa) <= 0.5 + 1e-6
        assert abs(year0["BA"] - ba) <= 0.5 + 1e-6
        assert year0["QMD"] == pytest.approx(qmd, abs=0.005)  # FVS keeps DBH in float32
        # FVS: the 40 largest trees per acre; standgrid: the 100 largest per ha (40.5/acre),
        # each tree here standing for 1/acres TPA: the same trees but for the last one.
        assert abs(year0["TopHt"] - top) <= 1.0
        # The projection ran: two more cycles, trees still there, basal area grew.
        assert list(summary["Year"]) == [stand.Inv_Year, stand.Inv_Year + 10, stand.Inv_Year + 20]
        assert (summary["Tpa"] > 0).all() and summary["BA"].iloc[1] > summary["BA"].iloc[0]


def test_second_campaign_increments_calibrate_fvs(
    pyfvs_fvs: Any,
    catalog: Path,
    exported: tuple[Path, dict],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.chdir(tmp_path)
    db, _ = exported
    stands, trees = _tables(db)
    later = stands[stands["DG_Trans"].notna()]
    assert len(later) >= 1 and (stands["SG_Epoch"] == "2024").any()
    assert stands.loc[stands["SG_Epoch"] == "2024", "DG_Measure"].isna().all()
    stand = later.iloc[0]
    assert stand["DG_Measure"] == pytest.approx(
        (pd.Timestamp("2028-05-20") - pd.Timestamp("2024-05-14")).days / 365.25
    )
    mine = trees[(trees["Stand_ID"] == stand["Stand_ID"]) & trees["DG"].notna()]
    # DG is the past (2024) DBH in inches: the compare table's matched trees.
    changes = pd.read_parquet(catalog / "compare" / "2024__2028" / "tree_changes.parquet")
    by_id = changes.set_index(changes["tree_id_to"].astype(str))
    past = by_id.loc[mine["SG_Tree_ID"], "dbh_m_from"].to_numpy() * 100 / CM_PER_IN
    np.testing.assert_allclose(mine["DG"], past, rtol=1e-12)
    htg = by_id.loc[mine["SG_Tree_ID"], "height_m_delta"].to_numpy() / M_PER_FT
    np.testing.assert_allclose(mine["HTG"], htg, rtol=1e-12)
    _, main_output = _run_fvs(pyfvs_fvs, db, str(stand["Stand_ID"]), tmp_path)
    used = int(main_output.split("THE DIAMETER INCREMENT MODEL")[1].split()[0])
    assert used == len(mine) > 0  # FVS read every DG record for calibration


def test_only_measured_stands_and_measured_growth_reach_fvs(
    catalog: Path, exported: tuple[Path, dict]
) -> None:
    """Stands short of coverage are not exported (the report says why); imputed DBHs are
    exported as such and never calibrate growth (DG only where both epochs measured it)."""
    db, report = exported
    stands, trees = _tables(db)
    metrics = pd.read_parquet(catalog / "tables" / "stand_metrics.parquet")
    short = metrics[(metrics["level"] == 1) & metrics["stems_ha"].isna()]
    assert len(short) >= 1
    for row in short.itertuples():
        assert report["stands_skipped"][f"{row.cell_id}_{row.epoch}"] == row.null_reason
    imputed = trees[trees["SG_DBH_Source"] == "imputed"]
    assert len(imputed) > 20 and imputed["DG"].isna().all()
    for stand in stands.itertuples():
        row = metrics[
            (metrics["cell_id"] == stand.SG_Cell_ID)
            & (metrics["epoch"].astype(str) == stand.SG_Epoch)
            & (metrics["level"] == 1)
        ].iloc[0]
        assert (trees["Stand_ID"] == stand.Stand_ID).sum() == row["n_trees"]


def test_slope_aspect_of_a_stand_reaching_past_the_dtm(tmp_path: Path) -> None:
    """A stand whose window starts west of / north of the DTM is read where it overlaps,
    each pixel at its own place (checked against rasterio.mask on a known plane)."""
    import rasterio
    import rasterio.mask
    import shapely

    from standgrid.geotiff import write_cog
    from standgrid.growth.fvs import slope_aspect
    from standgrid.rastergrid import RasterGrid

    grid = RasterGrid(1000.0, 2000.0, 1.0, 60, 60, crs="EPSG:32630")
    cx, cy = grid.centers()
    plane = 100.0 + 0.10 * (cx - 1000.0) - 0.05 * (cy - 2000.0)  # rises east, falls north
    dtm = tmp_path / "dtm.tif"
    write_cog(dtm, plane.astype(np.float32), grid)
    triangle = shapely.Polygon([(980, 2030), (1030, 2075), (1030, 2030)])  # past W and N edges
    slope, aspect, elevation = slope_aspect(dtm, triangle)
    with rasterio.open(dtm) as src:
        inside, _ = rasterio.mask.mask(src, [triangle], crop=True, filled=False)
    assert elevation == pytest.approx(float(inside.mean()), abs=1e-3)
    assert slope == pytest.approx(100 * np.hypot(0.10, 0.05), rel=1e-4)
    # downslope points west-north-west... the plane falls to the west and to the north
    assert aspect == pytest.approx((np.degrees(np.arctan2(-0.10, 0.05)) + 360) % 360, abs=0.01)


def test_epochs_never_compared_export_without_increments(catalog: Path, tmp_path: Path) -> None:
    """No comparison of the two epochs: FVS gets no DG/HTG, and the report says why."""
    import shutil

    copy = copy_catalog(catalog, tmp_path / "catalog")
    shutil.rmtree(copy / "compare")
    report = export_fvs(copy, tmp_path / "s.db", species="DF")
    _, trees = _tables(tmp_path / "s.db")
    assert trees["DG"].isna().all() and trees["HTG"].isna().all()
    assert any("not compared" in note for note in report.notes)


def _dtm_means(catalog: Path, stands: pd.DataFrame) -> np.ndarray:
    """Mean DTM height (m, ellipsoidal) inside each exported stand, read with rasterio.mask."""
    import pyogrio
    import rasterio
    import rasterio.mask

    polygons = pyogrio.read_dataframe(catalog / "index.gpkg", layer="stand_metrics")
    polygons["epoch"] = polygons["epoch"].astype(str)
    means = []
    for stand in stands.itertuples():
        row = polygons[
            (polygons["cell_id"] == stand.SG_Cell_ID) & (polygons["epoch"] == stand.SG_Epoch)
        ]
        with rasterio.open(catalog / "rasters" / stand.SG_Epoch / "dtm.tif") as src:
            inside, _ = rasterio.mask.mask(src, [row.geometry.iloc[0]], crop=True, filled=False)
        means.append(float(inside.astype(np.float64).mean()))
    return np.array(means)


def test_elev_ft_is_the_dtm_height_above_the_geoid(catalog: Path, tmp_path: Path) -> None:
    """ElevFt = (mean DTM ellipsoidal height - geoid undulation) / 0.3048, the undulation
    read from the grid file itself (GDAL, bilinear by hand) at the stand's lat/lon."""
    from tests.test_georef_geoid import _debian_grid, _grid_bilinear

    grid = _debian_grid()
    db = tmp_path / "s.db"
    report = export_fvs(catalog, db, species="DF", geoid_dirs=[grid.parent])
    assert report.elev_ft_null_reason == {} and report.elev_ft_null_stands == {}
    assert set(report.elevation_reference) == {"2024", "2028"}  # both GNSS-fitted
    assert all(r.endswith(f"with the grid {grid}") for r in report.elevation_reference.values())
    stands, _ = _tables(db)
    assert len(stands) >= 2 and stands["ElevFt"].notna().all()
    undulation = np.array(
        [_grid_bilinear(grid, s.Longitude, s.Latitude) for s in stands.itertuples()]
    )
    assert (undulation > 40).all()  # Wytham Woods, UK: about +48 m
    expected_ft = (_dtm_means(catalog, stands) - undulation) / M_PER_FT
    np.testing.assert_allclose(stands["ElevFt"], expected_ft, atol=0.01)


def test_without_a_geoid_grid_elev_ft_is_null_and_said(catalog: Path, tmp_path: Path) -> None:
    """No grid in the folders searched: ElevFt NULL (FVS's variant default), the report and
    the CLI (stderr) say why, naming the folder."""
    import json

    from click.testing import CliRunner

    from standgrid.cli import cli

    empty = tmp_path / "no_grids"
    empty.mkdir()
    report = export_fvs(catalog, tmp_path / "s.db", species="DF", geoid_dirs=[empty])
    stands, _ = _tables(tmp_path / "s.db")
    assert len(stands) >= 2 and stands["ElevFt"].isna().all()
    assert stands["Slope"].notna().all()  # the DTM was there: only the datum is missing
    reasons = report.elev_ft_null_reason
    assert set(reasons) == {"2024", "2028"}
    for reason in reasons.values():
        assert "no geoid model found" in reason and str(empty) in reason
    assert report.elevation_reference == {}

    out = tmp_path / "cli.db"
    result = CliRunner(env={"STANDGRID_GEOID_PATH": str(empty)}).invoke(
        cli, ["export", "fvs", str(catalog), "-o", str(out), "--species", "DF", "--json"]
    )
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["elev_ft_null_reason"] == reasons
    for epoch, reason in reasons.items():
        assert f"warning: epoch {epoch}: {reason}" in result.stderr
    assert _tables(out)[0]["ElevFt"].isna().all()


# --- missions whose clouds are already projected -----------------------------------------


def _projected_copy(source: Path, target: Path, geoid: Any) -> Path:
    """``source`` (a GNSS-fitted mission) as survey LAS already in EPSG:32630, with heights
    above sea level (ellipsoidal - N through ``geoid``), as national surveys deliver them."""
    import shutil

    import pyproj

    from standgrid.clouds import write_cloud
    from standgrid.georeference import MapProjector, georeference_mission
    from standgrid.mission.opening import open_mission
    from standgrid.pointcloud import PointCloud

    (target / "payload_clouds").mkdir(parents=True)
    for name in ("metadata.yaml", "slam_pose_graph.g2o"):
        shutil.copy(source / name, target / name)
    mission = open_mission(source)
    projector = MapProjector(georeference_mission(mission), "EPSG:32630")
    to_lonlat = pyproj.Transformer.from_crs("EPSG:32630", "EPSG:4326", always_xy=True)
    for payload in mission.payloads:
        if payload.kind != "point_cloud":
            continue
        cloud = mission.load_payload(payload, "map")
        xyz = projector.exact(cloud.xyz)
        lon, lat = to_lonlat.transform(xyz[:, 0], xyz[:, 1])
        xyz[:, 2] = geoid.orthometric_height(lon, lat, xyz[:, 2])
        name = payload.stamp.filename("cloud", "las")
        write_cloud(
            PointCloud(xyz, {"intensity_raw": cloud.fields["intensity"]}),
            target / "payload_clouds" / name,
            crs="EPSG:32630",
        )
    return target


@pytest.fixture(scope="module")
def projected_catalogs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """``projected``: the 2024 mission as projected survey LAS (heights above sea level);
    ``mixed``: one epoch of that and the GNSS-fitted original. Tiled like the shared pair."""
    import shutil

    from standgrid.georeference.geoid import find_geoid
    from standgrid.pipeline.run import run_pipeline
    from standgrid.tiling.options import TileOptions
    from tests.pipeline_fixtures import BUFFER_M, MISSIONS
    from tests.test_georef_geoid import _debian_grid

    grid = _debian_grid()
    geoid = find_geoid([grid.parent])
    root = tmp_path_factory.mktemp("projected")
    source = BUNDLED_MISSIONS / MISSIONS["2024"]
    projected = _projected_copy(source, root / "p" / source.name, geoid)
    run_pipeline([projected], root / "projected", TileOptions(buffer=BUFFER_M))
    survey = _projected_copy(source, root / "m" / "2024-05-14-wytham-anymal-survey", geoid)
    original = shutil.copytree(source, root / "m" / source.name)
    run_pipeline([original, survey], root / "mixed", TileOptions(buffer=BUFFER_M))
    return {"projected": root / "projected", "mixed": root / "mixed", "grid": grid}


def test_projected_clouds_elev_ft_is_null_unless_the_user_says_above_sea_level(
    projected_catalogs: dict[str, Path], catalog: Path, tmp_path: Path
) -> None:
    """Clouds already projected keep their source's heights: no geoid is subtracted. ElevFt
    is NULL with the reason (report, stderr, --json) unless --heights-above-sea-level, then
    the DTM height itself, which equals the GNSS-fitted catalog's ElevFt of the same cells."""
    import json

    from click.testing import CliRunner

    from standgrid.cli import cli

    projected, grid = projected_catalogs["projected"], projected_catalogs["grid"]
    db = tmp_path / "null.db"
    report = export_fvs(projected, db, level=0, species="DF", geoid_dirs=[grid.parent])
    stands, _ = _tables(db)
    assert len(stands) >= 5 and stands["ElevFt"].isna().all() and stands["Slope"].notna().all()
    (reason,) = report.elev_ft_null_reason.values()
    assert "heights of already-projected clouds: vertical datum unknown" in reason
    assert "--heights-above-sea-level" in reason and report.elevation_reference == {}

    db = tmp_path / "asl.db"
    report = export_fvs(
        projected, db, level=0, species="DF", geoid_dirs=[grid.parent], heights_above_sea_level=True
    )
    assert report.elev_ft_null_reason == {} and report.elev_ft_null_stands == {}
    assert "--heights-above-sea-level" in report.elevation_reference["2024"]
    stands, _ = _tables(db)
    assert stands["ElevFt"].notna().all()
    np.testing.assert_allclose(
        stands["ElevFt"], _dtm_means(projected, stands) / M_PER_FT, atol=0.01
    )
    # the same ground, GNSS-fitted (ellipsoidal heights - N): the same elevation
    export_fvs(
        catalog,
        tmp_path / "gnss.db",
        level=0,
        epochs=["2024"],
        species="DF",
        geoid_dirs=[grid.parent],
    )
    gnss = _tables(tmp_path / "gnss.db")[0][["Stand_ID", "ElevFt"]]
    both = stands.merge(gnss, on="Stand_ID", suffixes=("", "_gnss"))
    assert len(both) >= 0.9 * len(stands)
    # the GNSS-fitted catalog aligned the mission with the 2028 one: its heights moved by
    # the alignment's dz (the projected copy was made from the GNSS fit alone)
    record = json.loads((catalog / "catalog.json").read_text())["missions"][MISSIONS["2024"]]
    dz = (record["georeference"].get("alignment") or {}).get("dz_m", 0.0)
    difference = both["ElevFt"] - both["ElevFt_gnss"] + dz / M_PER_FT
    print("projected - GNSS ElevFt (ft):", difference.describe().to_dict(), "dz", dz)
    assert difference.abs().max() < 0.01  # 3 mm: N at the centroid vs at each point

    runner = CliRunner(env={"STANDGRID_GEOID_PATH": str(grid.parent)})
    args = ["export", "fvs", str(projected), "--species", "DF", "--json"]
    result = runner.invoke(cli, [*args, "-o", str(tmp_path / "cli_null.db")])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["elev_ft_null_reason"] == {"2024": reason}
    assert f"warning: epoch 2024: {reason}" in result.stderr
    result = runner.invoke(
        cli, [*args, "-o", str(tmp_path / "cli_asl.db"), "--heights-above-sea-level"]
    )
    assert result.exit_code == 0, result.output
    out = json.loads(result.stdout)
    assert out["elev_ft_null_reason"] == {} and "2024" in out["elevation_reference"]
    assert _tables(tmp_path / "cli_asl.db")[0]["ElevFt"].notna().all()


def test_an_epoch_mixing_gnss_and_projected_missions_has_null_elev_ft(
    projected_catalogs: dict[str, Path], tmp_path: Path
) -> None:
    """GNSS-fitted and already-projected missions in one epoch: one DTM, two vertical
    references; ElevFt is NULL, the reason naming both missions, even with the flag."""
    mixed, grid = projected_catalogs["mixed"], projected_catalogs["grid"]
    for flag in (False, True):
        db = tmp_path / f"{flag}.db"
        report = export_fvs(
            mixed, db, level=0, species="DF", geoid_dirs=[grid.parent], heights_above_sea_level=flag
        )
        stands, _ = _tables(db)
        assert len(stands) >= 5 and stands["ElevFt"].isna().all()
        (reason,) = report.elev_ft_null_reason.values()
        assert "mixes" in reason and "2024-05-14-wytham-anymal-coyote" in reason
        assert "2024-05-14-wytham-anymal-survey" in reason
        assert flag == any("changed nothing" in note for note in report.notes)


def test_a_stand_outside_the_geoid_grid_has_null_elev_ft_with_a_reason(
    catalog: Path, tmp_path: Path
) -> None:
    """A regional grid (part of EGM96) not covering the stands: N is NaN there, and the
    stand's ElevFt is NULL with the reason, not a number."""
    from standgrid.catalog import Catalog
    from standgrid.georeference.geoid import GeoidModel
    from standgrid.growth.fvs import _export_fvs
    from tests.test_georef_geoid import _debian_grid

    grid = _debian_grid()
    if grid.suffix != ".gtx":
        pytest.skip("the regional grid is cut from the GTX grid")
    data = grid.read_bytes()
    lat0, lon0, dlat, dlon, rows, cols = struct.unpack(">4d2i", data[:40])
    values = np.frombuffer(data, ">f4", offset=40).reshape(rows, cols)
    row0, col0 = int((0 - lat0) / dlat), int((0 - lon0) / dlon)  # 0..10 N, 0..10 E
    part = values[row0 : row0 + 41, col0 : col0 + 41]
    regional = tmp_path / "regional.gtx"
    header = struct.pack(">4d2i", 0.0, 0.0, dlat, dlon, *part.shape)
    regional.write_bytes(header + part.astype(">f4").tobytes())
    model = GeoidModel("EGM96", regional, "EPSG:10084", "EPSG:5773", 1.0)
    assert model.undulation(5.0, 5.0) == pytest.approx(float(values[row0 + 20, col0 + 20]))
    with Catalog.reading(catalog) as cat:
        report = _export_fvs(
            cat,
            tmp_path / "s.db",
            level=1,
            epochs=None,
            variant="PN",
            species="DF",
            species_by_stand=None,
            increments=False,
            overwrite=False,
            geoid=model,
        )
    stands, _ = _tables(tmp_path / "s.db")
    assert len(stands) >= 2 and stands["ElevFt"].isna().all()
    assert set(report.elev_ft_null_stands) == set(stands["Stand_ID"])
    assert all(
        f"the geoid grid {regional} has no undulation" in r
        for r in report.elev_ft_null_stands.values()
    )


def _undated_mission(source: Path, target: Path) -> Path:
    """A bundled mission without its date: no metadata.yaml, no GNSS, a plain folder name."""
    import shutil

    shutil.copytree(source, target)
    (target / "metadata.yaml").unlink()
    shutil.rmtree(target / "gnss")
    return target


def test_an_epoch_without_a_date_exports_with_its_label_year_or_is_refused_by_name(
    tmp_path: Path,
) -> None:
    """``tile --anchor ... --epoch 2020`` of undated missions makes an epoch without a date:
    FVS's Inv_Year is then the label when it is a year; an epoch whose label is not a year
    is refused with a typed error naming it (no traceback, nothing written)."""
    from click.testing import CliRunner

    from standgrid.cli import cli

    source = BUNDLED_MISSIONS / "2024-05-14-wytham-anymal-coyote"
    catalog = tmp_path / "cat"
    runner = CliRunner()
    for name, epoch in (("plot_a", "2020"), ("plot_b", "plotB")):
        mission = _undated_mission(source, tmp_path / name)
        anchor = ["--anchor", "47.0", "8.0", "500", "0"]
        result = runner.invoke(
            cli, ["tile", str(mission), "-o", str(catalog), *anchor, "--epoch", epoch]
        )
        assert result.exit_code == 0, result.output
        assert f"epoch {epoch} (no date):" in result.output
    assert runner.invoke(cli, ["enrich", str(catalog)]).exit_code == 0

    out = tmp_path / "stands.db"
    refused = runner.invoke(cli, ["export", "fvs", str(catalog), "-o", str(out)])
    assert refused.exit_code == 1
    assert isinstance(refused.exception, SystemExit)  # a clean message, not a crash
    assert "EpochDateError" in refused.output and "'plotB'" in refused.output
    assert "Traceback" not in refused.output and not out.exists()

    result = runner.invoke(
        cli, ["export", "fvs", str(catalog), "-o", str(out), "--epoch", "2020", "--json"]
    )
    assert result.exit_code == 0, result.output
    stands, trees = _tables(out)
    assert len(stands) > 0 and len(trees) > 0
    assert set(stands["Inv_Year"]) == {2020}
    assert set(stands["SG_Epoch"]) == {"2020"}
    assert "2020: no date; Inv_Year 2020 is its label" in result.stdout


def test_an_existing_keyword_file_is_refused_before_anything_is_written(
    catalog: Path, tmp_path: Path
) -> None:
    from click.testing import CliRunner

    from standgrid.cli import cli

    keywords = tmp_path / "stands.key"
    keywords.write_text("mine\n")
    out = tmp_path / "stands.db"
    args = ["export", "fvs", str(catalog), "-o", str(out), "--keywords", str(keywords)]
    result = CliRunner().invoke(cli, [*args, "--species", "DF"])
    assert result.exit_code == 1 and "--overwrite replaces it" in result.output
    assert keywords.read_text() == "mine\n" and not out.exists()  # the .db was written first
    result = CliRunner().invoke(cli, [*args, "--species", "DF", "--overwrite"])
    assert result.exit_code == 0, result.output
    assert out.is_file() and "DSNIN" in keywords.read_text()  # the new keyword file
