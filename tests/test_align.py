"""Alignment of missions (standgrid.alignment): stem registration, the mission graph (GTSAM),
GNSS priors that admit correlated errors, and the simulator's canopy GNSS."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from standgrid.alignment.graph import Prior, correlation_time, solve
from standgrid.alignment.register import RegisterOptions, register
from standgrid.alignment.stage import PlacedLandmarks


def _stems(rng: np.random.Generator, n: int = 120, side: float = 60.0) -> np.ndarray:
    xy = rng.uniform(0, side, (n, 2)) + np.array([500_000.0, 5_700_000.0])
    z = rng.uniform(100.0, 102.0, n)
    return np.column_stack([xy, z, rng.uniform(0.08, 0.5, n)])


def _moved(stems: np.ndarray, yaw: float, t: tuple[float, float], pivot: np.ndarray) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    out = stems.copy()
    q = stems[:, :2] - pivot
    out[:, 0] = c * q[:, 0] - s * q[:, 1] + pivot[0] + t[0]
    out[:, 1] = s * q[:, 0] + c * q[:, 1] + pivot[1] + t[1]
    return out


def _placed(name: str, stems: np.ndarray) -> PlacedLandmarks:
    return PlacedLandmarks(name, stems, np.zeros((0, 3)), stems[:, :3])


def test_stems_register_a_known_offset_and_turn() -> None:
    """A mission placed 1.9 m and 1.7 deg off, 70 % of its stems shared with the other (the
    rest its own), each stem seen with 1 cm noise: the registration undoes the offset."""
    rng = np.random.default_rng(3)
    world = _stems(rng, 160)
    fixed = world[:130]
    shared = world[30:]  # 100 shared stems + 30 of its own
    seen = shared + np.column_stack(
        [rng.normal(0, 0.01, (len(shared), 2)), np.zeros((len(shared), 2))]
    )
    pivot = seen[:, :2].mean(axis=0)
    yaw, t = math.radians(1.7), (1.5, -1.2)
    moving = _moved(seen, -yaw, (0.0, 0.0), pivot)
    moving[:, :2] -= t
    reg = register(_placed("m", moving), _placed("f", fixed), RegisterOptions(gicp=False))
    assert reg.accepted, reg.reason
    back = (
        (moving[:, :2] - reg.pivot)
        @ np.array(
            [[math.cos(reg.yaw), -math.sin(reg.yaw)], [math.sin(reg.yaw), math.cos(reg.yaw)]]
        ).T
        + reg.pivot
        + reg.t
    )
    err = np.hypot(*(back - shared[:, :2]).T)
    assert np.median(err) < 0.02 and err.max() < 0.06
    assert 95 <= reg.stems_matched <= 100
    assert abs(math.degrees(reg.yaw) - 1.7) < 0.05
    # the stated covariance is not absurdly tight or loose for 1 cm stems
    sigma = math.sqrt(reg.covariance[0][0] + reg.covariance[1][1])
    assert 0.01 <= sigma <= 0.1


def test_a_regular_plantation_is_ambiguous() -> None:
    """Stems on an exact 3 m lattice: every 3 m shift matches as well; refused, not guessed."""
    g = np.arange(0.0, 60.0, 3.0)
    xx, yy = np.meshgrid(g, g)
    stems = np.column_stack(
        [
            xx.ravel() + 500_000,
            yy.ravel() + 5_700_000,
            np.full(xx.size, 100.0),
            np.full(xx.size, 0.3),
        ]
    )
    moving = stems.copy()
    moving[:, :2] += (1.2, 0.4)
    reg = register(_placed("m", moving), _placed("f", stems), RegisterOptions(gicp=False))
    assert not reg.accepted and reg.reason.startswith("ambiguous")


def test_missions_that_do_not_overlap_are_not_registered() -> None:
    rng = np.random.default_rng(1)
    a = _stems(rng)
    b = a.copy()
    b[:, 0] += 500.0
    reg = register(_placed("m", b), _placed("f", a))
    assert not reg.accepted and "overlap" in reg.reason
    few = register(_placed("m", a[:4]), _placed("f", a))
    assert not few.accepted and few.reason.startswith("too few stems")


def test_the_graph_splits_an_offset_by_the_priors_and_keeps_the_registration() -> None:
    """Two missions 2 m apart by GNSS, a registration that says where one stands from the
    other: the solution honours it exactly, and each moves in inverse proportion to its
    prior's weight."""
    rng = np.random.default_rng(5)
    stems = _stems(rng)
    pivot = stems[:, :2].mean(axis=0)
    moving = stems.copy()
    moving[:, :2] += (2.0, 0.0)
    reg = register(_placed("b", moving), _placed("a", stems), RegisterOptions(gicp=False))
    assert reg.accepted
    centre = (float(pivot[0]), float(pivot[1]))
    priors = {
        "a": Prior(centre, 1.0, math.radians(1.0), 1.0, "test"),
        "b": Prior(centre, 2.0, math.radians(1.0), 1.0, "test"),
    }
    sol = solve(["a", "b"], priors, [reg])
    ca, cb = sol.corrections["a"], sol.corrections["b"]
    probe = np.column_stack([stems[:, :2], np.zeros(len(stems))])
    # the same ground: a's point and b's point of one stem land together
    apart = ca.apply(probe)[:, :2] - cb.apply(probe + np.array([2.0, 0.0, 0.0]))[:, :2]
    assert np.abs(apart).max() < 1e-3
    # weights 1 : 1/4 -> a moves 2 * (1/4) / (1 + 1/4) = 0.4 m, b the other 1.6 m
    assert ca.g[0] == pytest.approx(0.4, abs=0.02)
    assert cb.apply(probe + np.array([2.0, 0.0, 0.0]))[0, 0] - (probe[0, 0] + 2.0) == pytest.approx(
        -1.6, abs=0.02
    )
    # the absolute 1-sigma: both priors combined (per axis 1/sqrt(1 + 1/4)), as a DRMS
    assert ca.sigma_at(pivot[None])[0] == pytest.approx(math.sqrt(2 / 1.25), rel=0.05)
    assert sol.sigma_rel["a"] < 0.1


def test_correlation_time_of_a_gauss_markov_walk() -> None:
    from standgrid.simulate.gnss import _gauss_markov

    rng = np.random.default_rng(0)
    t = np.arange(0.0, 3600.0, 0.5)
    walk = _gauss_markov(rng, t, 1.0, 120.0)
    tau = correlation_time((t * 1e9).astype(np.int64), walk)
    assert 60.0 <= tau <= 240.0
    white = rng.normal(0, 1, (len(t), 2))
    assert correlation_time((t * 1e9).astype(np.int64), white) <= 20.0


def test_canopy_gnss_is_biased_correlated_and_states_too_little() -> None:
    """The simulator's canopy GNSS: a bias per recording, a walk correlated over minutes, and
    receivers stating 0.5 m; the default model draws none of these (the demo unchanged)."""
    from standgrid.simulate.gnss import GnssModel, gnss_model
    from standgrid.simulate.mission import SimulationConfig, run_simulation

    config = SimulationConfig(area=60.0, gnss=gnss_model("canopy"))
    sim = run_simulation(4, 1, config)
    fixes, true = sim.gnss.fixes, sim.gnss.true_xyz
    ok = ~sim.gnss.outlier
    # errors in the CRS, horizontal, of the fixes that are not multipath outliers
    from standgrid.simulate.chain import FrameChain
    from standgrid.simulate.mission import SITE_CRS

    chain = FrameChain(SITE_CRS, sim.chain.lla_ref, np.eye(4))
    lla = np.column_stack([fixes.lat, fixes.lon, fixes.alt])
    err = chain.lla_to_crs(lla)[:, :2] - true[:, :2]
    err = err[ok]
    rms = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
    assert rms > 1.0  # metres, while every fix states 0.5 m
    assert np.all(fixes.h_std == 0.5)
    assert set(np.unique(fixes.quality)) <= {1, 2, 5}
    stamps = fixes.stamps_ns[ok]
    assert correlation_time(stamps, err) > 30.0
    assert GnssModel() == gnss_model("demo") and GnssModel().walk_h_m == 0.0


def test_a_mission_placed_nowhere_near_is_found_by_the_global_stem_search() -> None:
    """Without GNSS the map frame is anywhere: turned 123 deg and 40 m off, the stem pairs
    of like length and DBH find it, and the fine registration finishes it."""
    from standgrid.alignment.register import register_global

    rng = np.random.default_rng(11)
    world = _stems(rng, 400, side=100.0)  # more stems than the search's 150 stoutest
    fixed = world[:300]
    shared = world[100:]
    seen = shared + np.column_stack(
        [rng.normal(0, 0.01, (len(shared), 2)), np.zeros((len(shared), 2))]
    )
    pivot = seen[:, :2].mean(axis=0)
    moving = _moved(seen, math.radians(123.0), (40.0, -25.0), pivot)
    reg = register_global(_placed("m", moving), _placed("f", fixed), RegisterOptions(gicp=False))
    assert reg.accepted, reg.reason
    rot = np.array(
        [[math.cos(reg.yaw), -math.sin(reg.yaw)], [math.sin(reg.yaw), math.cos(reg.yaw)]]
    )
    back = (moving[:, :2] - reg.pivot) @ rot.T + reg.pivot + reg.t
    err = np.hypot(*(back - shared[:, :2]).T)
    assert np.median(err) < 0.02 and err.max() < 0.06
    assert reg.stems_matched >= 190
    # the covariance moved to the new pivot still says centimetres
    assert math.sqrt(reg.covariance[0][0] + reg.covariance[1][1]) < 0.1
    # a stand of other stems: nothing alike enough, refused
    other = _stems(np.random.default_rng(99), 150, side=70.0)
    miss = register_global(_placed("m", other), _placed("f", fixed), RegisterOptions(gicp=False))
    assert not miss.accepted


def test_standgrid_align_realigns_a_catalog_tiled_by_gnss_alone(tmp_path: Path) -> None:
    """The bundled pair tiled with --no-align, then ``standgrid align``: both missions
    registered on their stems, re-tiled in their own epochs, the alignment recorded in the
    catalog and the missions layer; aligning again changes nothing."""
    import json
    import shutil

    import pyogrio
    from click.testing import CliRunner

    from standgrid.cli import cli
    from tests.conftest import BUNDLED_MISSIONS

    catalog = tmp_path / "catalog"
    for source in BUNDLED_MISSIONS.iterdir():
        shutil.copytree(source, tmp_path / "missions" / source.name)
    missions = [str(m) for m in sorted((tmp_path / "missions").iterdir())]
    runner = CliRunner()
    done = runner.invoke(cli, ["tile", *missions, "-o", str(catalog), "--no-align", "-q"])
    assert done.exit_code == 0, done.output
    state = json.loads((catalog / "catalog.json").read_text())
    assert all("alignment" not in m["georeference"] for m in state["missions"].values())
    done = runner.invoke(cli, ["align", str(catalog), "--json", "-q"])
    assert done.exit_code == 0, done.output
    report = json.loads(done.output)
    (registration,) = report["alignment"]["registrations"]
    assert registration["accepted"] and registration["stems_matched"] >= 20
    assert registration["rms_m"] < 0.05
    state = json.loads((catalog / "catalog.json").read_text())
    epochs = {name: m["epoch"] for name, m in state["missions"].items()}
    assert sorted(epochs.values()) == ["2024", "2028"]
    transforms = {}
    for name, m in state["missions"].items():
        aligned = m["georeference"]["alignment"]
        assert aligned["aligned"] and aligned["sigma_rel_m"] < 0.1
        assert m["georeference"]["method"] == "aligned"
        transforms[name] = m["georeference"]["T_enu_map"]
    layer = pyogrio.read_dataframe(catalog / "index.gpkg", layer="missions")
    assert layer["aligned"].all() and layer["sigma_h_m"].notna().all()
    again = runner.invoke(cli, ["align", str(catalog), "-q"])
    assert again.exit_code == 0, again.output
    state = json.loads((catalog / "catalog.json").read_text())
    for name, m in state["missions"].items():
        assert m["georeference"]["T_enu_map"] == transforms[name]
    # a mission's folder gone: refused by name, the catalog untouched
    before = (catalog / "catalog.json").read_bytes()
    gone = Path(missions[0])
    gone.rename(gone.with_name("moved"))
    refused = runner.invoke(cli, ["align", str(catalog), "-q"])
    assert refused.exit_code != 0 and gone.name in refused.output
    assert "Traceback" not in refused.output
    assert (catalog / "catalog.json").read_bytes() == before
