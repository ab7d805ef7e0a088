"""Tree segmentation and DBH: synthetic stands with known trees, real lidR and TreeLS scans."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.spatial import cKDTree

from standgrid.enrichment.ground import classify_ground
from standgrid.enrichment.rasters import dtm_from_ground, height_above_ground
from standgrid.enrichment.trees import segment_trees, tree_id_from_xy, xy_from_tree_id
from standgrid.errors import EnrichError
from standgrid.features.circles import fit_circle, fit_circles, kasa_circle, link_clusters
from standgrid.features.stems import find_stems
from standgrid.rastergrid import RasterGrid
from tests.conftest import real_file

X0, Y0 = 500_000.0, 5_200_000.0  # projected coordinates: ids and rasters must cope


def synthetic_stand(
    seed: int, *, n_side: int = 6, spacing: float = 9.0, stems: bool = False
) -> tuple[np.ndarray, np.ndarray, pd.DataFrame]:
    """A sloped stand of well-separated conifer cones and broadleaf ellipsoids.

    Returns points, their true heights above ground and the truth (x, y, height, dbh).
    With ``stems`` every tree also gets a cylindrical stem seen from 2-3 sides.
    """
    rng = np.random.default_rng(seed)
    slope = (0.25, 0.1)  # ~15 deg
    parts, truth = [], []
    for i in range(n_side):
        for j in range(n_side):
            x = X0 + i * spacing + rng.uniform(-1.5, 1.5) + 5
            y = Y0 + j * spacing + rng.uniform(-1.5, 1.5) + 5
            height = rng.uniform(6, 30)
            dbh = 0.08 + 0.012 * height + rng.uniform(-0.03, 0.03)
            conifer = rng.random() < 0.5
            crown_r = min(1.2 + 0.1 * height, 3.6) if conifer else min(1.5 + 0.12 * height, 4.0)
            crown_len = 0.5 * height
            n = int(40 * np.pi * crown_r**2)
            a = rng.uniform(0, 2 * np.pi, n)
            u = np.sqrt(rng.uniform(0, 1, n))
            if conifer:
                depth = rng.uniform(0, 1, n) ** 0.7
                radius, hz = depth * crown_r * u, height - depth * crown_len
            else:
                radius = crown_r * u
                cap = np.sqrt(np.clip(1 - u**2, 0, 1)) * rng.choice([1.0, 0.6], n)
                hz = height - crown_len / 2 + crown_len / 2 * cap
            crown = np.column_stack([x + radius * np.cos(a), y + radius * np.sin(a), hz])
            crown[0] = (x, y, height)  # the apex is sampled
            parts.append(crown)
            if stems:
                m = 1500
                visible = rng.uniform(0, 2 * np.pi) + rng.choice([0.0, 2.2, 4.1], m)
                ang = visible + rng.uniform(-0.9, 0.9, m)
                hz = rng.uniform(0.2, height - crown_len, m)
                r = dbh / 2 + rng.normal(0, 0.004, m)
                parts.append(np.column_stack([x + r * np.cos(ang), y + r * np.sin(ang), hz]))
            truth.append((x, y, height, dbh))
    span = n_side * spacing + 10
    ng = int(span * span * 4)
    parts.append(
        np.column_stack(
            [X0 + rng.uniform(0, span, ng), Y0 + rng.uniform(0, span, ng), rng.normal(0, 0.02, ng)]
        )
    )
    xyz_h = np.concatenate(parts)
    ground = 1000.0 + slope[0] * (xyz_h[:, 0] - X0) + slope[1] * (xyz_h[:, 1] - Y0)
    xyz = np.column_stack([xyz_h[:, :2], ground + xyz_h[:, 2]])
    return xyz, xyz_h[:, 2], pd.DataFrame(truth, columns=["x", "y", "height", "dbh"])


def match(
    detected: pd.DataFrame, truth: pd.DataFrame, radius: float = 1.5
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one nearest matches (truth index, detected index) within ``radius``."""
    dist, nearest = cKDTree(detected[["x", "y"]].to_numpy()).query(truth[["x", "y"]].to_numpy())
    pairs, used = [], set()
    for t in np.argsort(dist):
        if dist[t] <= radius and nearest[t] not in used:
            used.add(nearest[t])
            pairs.append((t, nearest[t]))
    arr = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    return arr[:, 0], arr[:, 1]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_detection_f1_and_height_on_synthetic_crowns(seed: int) -> None:
    xyz, h, truth = synthetic_stand(seed)
    seg = segment_trees(xyz, h, stems=False)
    table = seg.table
    tall_truth = truth[truth["height"] > 10].reset_index(drop=True)
    tall_detected = table[table["height_m"] > 10].reset_index(drop=True)
    ti, di = match(tall_detected, tall_truth)
    tp = len(ti)
    fp, fn = len(tall_detected) - tp, len(tall_truth) - tp
    f1 = 2 * tp / (2 * tp + fp + fn)
    assert f1 >= 0.9, (tp, fp, fn)
    err = tall_detected["height_m"].to_numpy()[di] - tall_truth["height"].to_numpy()[ti]
    assert np.sqrt(np.mean(err**2)) <= 0.5
    # ground of the top = the true terrain under it (the slope is known)
    expected_ground = 1000.0 + 0.25 * (tall_detected["x"] - X0) + 0.1 * (tall_detected["y"] - Y0)
    assert np.allclose(tall_detected["z_ground"], expected_ground, atol=1e-6)
    # per-point labels: canopy points of a matched tree carry that tree's label
    labelled = seg.labels[h > 2] > 0
    assert labelled.mean() > 0.9
    assert seg.labels.dtype == np.uint32 and seg.labels.max() == len(table)
    # crowns: valid polygons whose area equals the pixel area, containing the top
    for row in table.itertuples():
        assert row.crown.is_valid and abs(row.crown.area - row.crown_area_m2) < 1e-6
    assert (table["n_points"] > 0).all()
    assert table["dbh_reason"].notna().all() and table["dbh_m"].isna().all()


def test_tree_ids_are_stable_across_overlapping_blocks() -> None:
    xyz, h, _ = synthetic_stand(3)
    whole = segment_trees(xyz, h, stems=False).table
    xmid = X0 + 30.0
    halo = 6.0
    owned_parts = []
    for xmin, xmax in ((X0 - 10, xmid), (xmid, X0 + 80)):
        sel = (xyz[:, 0] >= xmin - halo) & (xyz[:, 0] < xmax + halo)
        seg = segment_trees(
            xyz[sel], h[sel], stems=False, keep_bounds=(xmin, Y0 - 10, xmax, Y0 + 80)
        )
        owned = seg.owned()
        assert ((owned["x"] >= xmin) & (owned["x"] < xmax)).all()
        assert not seg.table["owned"].all()  # the halo holds trees of the neighbour block
        owned_parts.append(owned)
    blocks = pd.concat(owned_parts)
    assert blocks["tree_id"].is_unique
    assert set(blocks["tree_id"]) == set(whole["tree_id"])
    merged = whole.set_index("tree_id").loc[blocks["tree_id"]]
    assert np.allclose(merged["height_m"].to_numpy(), blocks["height_m"].to_numpy())


def test_tree_id_round_trip() -> None:
    x = np.array([X0 + 0.04, 123_456.78, -50.0])
    y = np.array([Y0 + 0.26, 6_543_210.12, -20.0])
    ids = tree_id_from_xy(x, y)
    assert ids.dtype == np.int64 and len(set(ids)) == 3 and (ids > 0).all()
    bx, by = xy_from_tree_id(ids)
    assert np.allclose(bx, np.round(x, 1)) and np.allclose(by, np.round(y, 1))
    assert tree_id_from_xy(np.array([X0 + 0.0401]), np.array([Y0 + 0.2601]))[0] == ids[0]
    with pytest.raises(EnrichError):
        tree_id_from_xy(np.array([2e8]), np.array([0.0]))


def test_empty_and_bad_input() -> None:
    xyz = np.column_stack([np.arange(10.0), np.zeros(10), np.zeros(10)])
    seg = segment_trees(xyz, np.zeros(10))
    assert seg.table.empty and (seg.labels == 0).all() and seg.table.columns[0] == "tree_id"
    with pytest.raises(EnrichError):
        segment_trees(xyz, np.zeros(9))


def arc_points(
    rng: np.random.Generator, cx: float, cy: float, r: float, arc_deg: float, n: int, noise: float
) -> np.ndarray:
    start = rng.uniform(0, 2 * np.pi)
    ang = start + np.radians(rng.uniform(0, arc_deg, n))
    rr = r + rng.normal(0, noise, n)
    return np.column_stack([cx + rr * np.cos(ang), cy + rr * np.sin(ang)])


def test_circle_fit_dbh_rmse_on_partial_arcs() -> None:
    rng = np.random.default_rng(7)
    errors = []
    for _ in range(40):
        r = rng.uniform(0.05, 0.3)
        arc = rng.uniform(120, 360)
        pts = arc_points(rng, X0 + 3.0, Y0 + 4.0, r, arc, 80, 0.005)
        branch = np.column_stack(
            [X0 + 3.0 + rng.uniform(r, r + 0.3, 8), Y0 + 4.0 + rng.normal(0, 0.02, 8)]
        )
        fit = fit_circle(np.concatenate([pts, branch]))
        assert fit is not None
        errors.append(2 * fit.radius - 2 * r)
        assert fit.arc_deg >= 0.7 * arc
    assert np.sqrt(np.mean(np.square(errors))) <= 0.02
    # the algebraic fit is exact on exact points
    cx, cy, r = kasa_circle(arc_points(rng, 1.0, 2.0, 0.2, 360, 50, 0.0))
    assert np.allclose([cx, cy, r], [1.0, 2.0, 0.2], atol=1e-9)


def test_segment_trees_attaches_dbh_to_the_right_trees() -> None:
    xyz, h, truth = synthetic_stand(4, stems=True)
    table = segment_trees(xyz, h).table
    ti, di = match(table, truth)
    assert len(ti) >= 0.9 * len(truth)
    dbh = table["dbh_m"].to_numpy()[di]
    have = np.isfinite(dbh)
    assert have.mean() >= 0.9
    err = dbh[have] - truth["dbh"].to_numpy()[ti][have]
    assert np.sqrt(np.mean(err**2)) <= 0.02
    assert table.loc[table["dbh_m"].isna(), "dbh_reason"].notna().all()
    assert table.loc[table["dbh_m"].notna(), "dbh_reason"].isna().all()
    stem_offset = np.hypot(table["stem_x"] - table["x"], table["stem_y"] - table["y"])
    assert (stem_offset[table["dbh_m"].notna()] < 0.2).all()


def test_find_stems_rejects_blobs_and_a_shrub_is_no_tree() -> None:
    rng = np.random.default_rng(1)
    blob = np.column_stack(
        [rng.normal(5, 0.3, 600), rng.normal(5, 0.3, 600), rng.uniform(0.5, 1.95, 600)]
    )
    stem = np.column_stack(
        [*arc_points(rng, 9.0, 9.0, 0.15, 360, 1200, 0.003).T, rng.uniform(0.5, 6.0, 1200)]
    )
    # a shrub: stem-like cross-sections from 1.0 to 1.8 m, nothing above
    shrub = np.column_stack(
        [*arc_points(rng, 2.0, 9.0, 0.2, 360, 300, 0.003).T, rng.uniform(1.0, 1.8, 300)]
    )
    # a cone of twigs: round, but narrowing by 30 cm per m
    z = rng.uniform(0.5, 1.95, 600)
    cone = np.column_stack([*arc_points(rng, 6.0, 2.0, 1.0, 360, 600, 0.003).T, z])
    cone[:, :2] = (cone[:, :2] - (6.0, 2.0)) * (0.6 - 0.15 * z)[:, None] + (6.0, 2.0)
    xyz = np.concatenate([blob, stem, shrub, cone])
    found = find_stems(xyz, xyz[:, 2]).table
    assert len(found) == 2, found
    tree = found[np.hypot(found["stem_x"] - 9.0, found["stem_y"] - 9.0) < 0.05]
    assert len(tree) == 1 and abs(tree["dbh_m"].iloc[0] - 0.30) < 0.01
    assert tree["lean_deg"].iloc[0] < 1.0 and tree["stem_high_m"].iloc[0] >= 3.4
    # the shrub's short "stem" is found, but a tree must reach 2 m: it is none
    trees = segment_trees(xyz, xyz[:, 2]).table
    assert len(trees) == 1 and trees["detected_by"].iloc[0] == "both"  # its top: its own
    assert np.hypot(trees["x"].iloc[0] - 9.0, trees["y"].iloc[0] - 9.0) < 0.05


def single_linkage(xy: np.ndarray, distance: float) -> tuple[int, np.ndarray]:
    """Reference: components of every pair within ``distance``, numbered by first point."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    pairs = cKDTree(xy).query_pairs(distance, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), (len(xy), len(xy)))
    count, comp = connected_components(graph, directed=False)
    return count, comp


@pytest.mark.parametrize("distance", [0.2, 0.05, 0.5])
def test_link_clusters_is_single_linkage(distance: float) -> None:
    rng = np.random.default_rng(3)
    stems = [
        arc_points(rng, X0 + rng.uniform(0, 8), Y0 + rng.uniform(0, 8), 0.2, 360, 300, 0.01)
        for _ in range(12)
    ]
    scatter = np.column_stack([X0 + rng.uniform(0, 8, 800), Y0 + rng.uniform(0, 8, 800)])
    # a chain of points just within ``distance`` of the next, and one just beyond its end
    step = np.arange(7) * 0.999 * distance
    step[-1] = step[-2] + 1.001 * distance
    chain = np.column_stack([X0 - 3.0 + step, np.full(7, Y0 - 3.0)])
    xy = np.concatenate([*stems, scatter, chain])
    xy = xy[rng.permutation(len(xy))] - np.array([X0 - 4.0, Y0 - 4.0])
    count, comp = link_clusters(xy, distance)
    want_count, want = single_linkage(xy, distance)
    assert count == want_count and np.array_equal(comp, want)
    assert np.array_equal(
        np.unique(comp, return_index=True)[1], np.sort(np.unique(comp, return_index=True)[1])
    )
    assert link_clusters(xy[:0], distance)[0] == 0


def test_fit_circles_fits_each_set_as_fit_circle() -> None:
    rng = np.random.default_rng(5)
    sets = [
        arc_points(
            rng,
            rng.uniform(-5, 5),
            rng.uniform(-5, 5),
            rng.uniform(0.05, 0.4),
            rng.uniform(60, 360),
            int(rng.integers(3, 400)),
            0.005,
        )
        for _ in range(30)
    ]
    sets.insert(3, sets[0][:2])  # too few points: None
    sets.insert(7, np.zeros((5, 2)))  # degenerate: singular normal equations
    together = fit_circles(sets)
    assert together == [fit_circle(xy) for xy in sets]
    assert together[3] is None and together[0] is not None


def test_find_stems_within_bounds_keeps_the_stems_standing_inside() -> None:
    """Stems are chosen by where they stand, from all their points: the same stems as over
    the whole stand, those inside the bounds."""
    xyz, h, _ = synthetic_stand(4, stems=True)
    bounds = (X0 + 10.0, Y0 + 12.0, X0 + 40.0, Y0 + 35.0)
    whole = find_stems(xyz, h).table
    x, y = whole["stem_x"], whole["stem_y"]
    inside = (x >= bounds[0]) & (x < bounds[2]) & (y >= bounds[1]) & (y < bounds[3])
    within = find_stems(xyz, h, within=bounds).table
    assert len(within) >= 3
    pd.testing.assert_frame_equal(within, whole[inside].reset_index(drop=True))


@pytest.mark.realdata
def test_dbh_on_real_terrestrial_pine_plot() -> None:
    import laspy

    las = laspy.read(real_file("als/TreeLS/pine_plot.laz"))
    xyz = np.column_stack([las.x, las.y, las.z])
    ground = classify_ground(xyz, cloth_resolution=0.25, rigidness=2)
    grid = RasterGrid.covering(
        (0.0, 0.0, 10.0, 10.0), origin=(0.0, 0.0), cell_size=10.0, pixel_size=0.5
    )
    h = height_above_ground(xyz, dtm_from_ground(xyz[ground], grid), grid)
    ok = find_stems(xyz, h).table
    assert len(ok) >= 10
    assert ok["dbh_m"].between(0.05, 0.6).all()
    assert 0.12 <= ok["dbh_m"].median() <= 0.35
    assert ok["dbh_rmse_m"].median() < 0.01  # tight circles: these are stems
    assert (ok["stem_circles"] >= 3).all()


@pytest.mark.realdata
def test_real_mixed_conifer_trees_agree_with_lidr_segmentation() -> None:
    import laspy

    las = laspy.read(real_file("als/lidR/MixedConifer.laz"))
    xyz = np.column_stack([las.x, las.y, las.z])  # height-normalised already
    seg = segment_trees(xyz, xyz[:, 2], stems=False)
    tree_id = np.asarray(las.treeID)
    lidr = pd.DataFrame({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "t": tree_id})
    lidr_tops = lidr[lidr["t"] > 0].sort_values("z").groupby("t").tail(1)
    assert abs(len(seg.table) - len(lidr_tops)) <= 0.3 * len(lidr_tops)
    dist, _ = cKDTree(seg.table[["x", "y"]].to_numpy()).query(lidr_tops[["x", "y"]].to_numpy())
    assert (dist < 1.5).mean() >= 0.7
    assert seg.table["tree_id"].is_unique
    assert seg.table["height_m"].max() == pytest.approx(xyz[:, 2].max())


def test_full_chain_on_a_simulated_robot_mission() -> None:
    """CSF -> DTM -> heights -> trees on the simulator's points, against its ground truth."""
    simulate = pytest.importorskip("standgrid.simulate")
    from standgrid.enrichment.allometry import fit_height_diameter, impute_dbh
    from standgrid.enrichment.metrics import cell_index, tree_metrics

    sim = simulate.run_simulation(7, 1, simulate.SimulationConfig(area=60.0))
    xyz = np.concatenate([sim.payload(k)[1].xyz for k in range(len(sim.spans))])
    world = sim.world
    ground = classify_ground(xyz)
    b = world.bounds
    grid = RasterGrid.covering(
        (xyz[:, 0].min(), xyz[:, 1].min(), xyz[:, 0].max(), xyz[:, 1].max()),
        origin=(b[0], b[1]),
        cell_size=20.0,
    )
    dtm = dtm_from_ground(xyz[ground], grid)
    cx, cy = grid.centers()
    inner_px = (cx > b[0] + 5) & (cx < b[2] - 5) & (cy > b[1] + 5) & (cy < b[3] - 5)
    assert np.median(np.abs(dtm - world.terrain.height(cx, cy))[inner_px]) < 0.05
    h = height_above_ground(xyz, dtm, grid)
    table = segment_trees(xyz, h).table

    trees = world.trees.select(world.trees.standing)
    truth = pd.DataFrame({"x": trees.x, "y": trees.y, "height": trees.height, "dbh": trees.dbh})
    ti, di = match(table, truth)

    def inner(x: np.ndarray, y: np.ndarray) -> np.ndarray:  # edge trees are half-seen
        return (x > b[0] + 3) & (x < b[2] - 3) & (y > b[1] + 3) & (y < b[3] - 3)

    tall_truth = (truth["height"].to_numpy() > 10) & inner(
        truth["x"].to_numpy(), truth["y"].to_numpy()
    )
    tall_found = (table["height_m"].to_numpy() > 10) & inner(
        table["x"].to_numpy(), table["y"].to_numpy()
    )
    tp = int(tall_truth[ti].sum())
    fn = int(tall_truth.sum()) - tp
    matched = np.zeros(len(table), dtype=bool)
    matched[di] = True
    fp = int((tall_found & ~matched).sum())
    assert tp > 50
    assert 2 * tp / (2 * tp + fp + fn) >= 0.9, (tp, fp, fn)
    pairs = tall_truth[ti]
    height_err = table["height_m"].to_numpy()[di][pairs] - truth["height"].to_numpy()[ti][pairs]
    assert np.sqrt(np.mean(height_err**2)) <= 0.5
    dbh = table["dbh_m"].to_numpy()[di][pairs]
    true_dbh = truth["dbh"].to_numpy()[ti][pairs]
    assert np.isfinite(dbh).mean() >= 0.8
    ok = np.isfinite(dbh)
    assert np.sqrt(np.mean((dbh[ok] - true_dbh[ok]) ** 2)) <= 0.02
    # tree-based stand metrics over the whole inner area against the truth list
    area = (b[2] - b[0] - 6) * (b[3] - b[1] - 6)
    found = table[inner(table["x"].to_numpy(), table["y"].to_numpy()) & (table["height_m"] > 10)]
    real = truth[tall_truth]
    # every tree gets a DBH: the unmeasured ones from the height-diameter model
    measured = table[np.isfinite(table["dbh_m"])]
    model = fit_height_diameter(measured["height_m"], measured["dbh_m"])
    found = impute_dbh(found, model)
    est = tree_metrics(
        np.zeros(len(found), np.int64),
        found["height_m"],
        found["dbh_m"],
        cell_area_m2=area,
        dbh_measured=(found["dbh_source"] == "measured").to_numpy(),
    )
    ref = tree_metrics(
        np.zeros(len(real), np.int64), real["height"], real["dbh"], cell_area_m2=area
    )
    assert est.loc[0, "stems_ha"] == pytest.approx(ref.loc[0, "stems_ha"], rel=0.1)
    assert est.loc[0, "basal_area_m2_ha"] == pytest.approx(ref.loc[0, "basal_area_m2_ha"], rel=0.15)
    assert est.loc[0, "dominant_height_m"] == pytest.approx(
        ref.loc[0, "dominant_height_m"], abs=1.0
    )
    col, row = cell_index(found["x"], found["y"], origin=(b[0], b[1]), cell_size=20.0)
    per_cell = tree_metrics(row * 10 + col, found["height_m"], found["dbh_m"], cell_area_m2=400.0)
    assert per_cell["n_trees"].sum() == len(found)
