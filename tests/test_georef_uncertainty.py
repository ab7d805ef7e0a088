"""The georeference fit's 1-sigma uncertainty against the simulator's known GNSS noise, and
the warning when the GNSS baseline is too short to fix the heading."""

from __future__ import annotations

import math

import numpy as np
import pytest

from standgrid.geometry import invert_pose, yaw_of
from standgrid.georeference import GeoreferenceFit, fit_georeference
from standgrid.georeference.uncertainty import MAX_YAW_SIGMA_DEG
from standgrid.mission.sensors import GnssFixes
from standgrid.simulate import SimulationConfig, run_simulation


def _fit(sim, keep: np.ndarray | None = None) -> GeoreferenceFit:  # type: ignore[no-untyped-def]
    g = sim.gnss.fixes
    k = np.ones(len(g), dtype=bool) if keep is None else keep
    kept = GnssFixes(
        g.stamps_ns[k], g.lat[k], g.lon[k], g.alt[k], g.quality[k], g.h_std[k], g.v_std[k]
    )
    return fit_georeference(kept, sim.graph.stamps_ns, sim.graph.positions)


def _z_scores(sim, fit: GeoreferenceFit) -> np.ndarray:  # type: ignore[no-untyped-def]
    """(fit - truth) / sigma for yaw, t_E, t_N, t_U."""
    truth = invert_pose(sim.chain.T_map_enu)
    dyaw = math.degrees(math.remainder(yaw_of(fit.T_enu_map) - yaw_of(truth), 2 * math.pi))
    dt = fit.T_enu_map[:3, 3] - truth[:3, 3]
    u = fit.uncertainty
    assert u is not None
    return np.array([dyaw / u.sigma_yaw_deg, *(dt / np.array(u.sigma_translation_m))])


def test_sigma_is_the_size_of_the_true_error_across_seeds() -> None:
    """No SLAM drift (drift is an error of the map, not of the tie): the only error is the
    simulated GNSS noise (canopy 0.5-3 m, RTK windows 2-3 cm, 2 % multipath outliers)."""
    config = SimulationConfig(area=80.0, drift_m=0.0)
    z = np.array(
        [
            _z_scores(sim, _fit(sim))
            for sim in map(lambda s: run_simulation(s, 1, config), range(10))
        ]
    )
    print(
        f"\nz = error / sigma (yaw, E, N, U): RMS {np.sqrt((z**2).mean(axis=0)).round(2)}, "
        f"max |z| {np.abs(z).max(axis=0).round(2)}"
    )
    # every true yaw and horizontal translation error within 3 sigma, height within 4 sigma
    assert np.all(np.abs(z[:, :3]) < 3.0) and np.all(np.abs(z[:, 3]) < 4.0)
    # and sigma is not inflated either: the errors' RMS in sigmas is near 1
    rms = np.sqrt((z**2).mean(axis=0))
    assert np.all((rms > 0.5) & (rms < 1.6))


def test_uncertainty_round_trips_and_is_small_with_a_long_baseline() -> None:
    sim = run_simulation(3, 1, SimulationConfig(area=80.0))
    fit = _fit(sim)
    u = fit.uncertainty
    assert u is not None and u.heading_fixed and u.warnings == ()
    assert u.baseline_m > 60.0 and u.sigma_yaw_deg < 0.05
    again = GeoreferenceFit.from_dict(fit.to_dict())
    assert again.uncertainty == u


def test_short_baseline_warns_that_the_heading_is_not_fixed() -> None:
    sim = run_simulation(3, 1, SimulationConfig(area=80.0))
    g = sim.gnss.fixes
    rtk = g.quality == 4
    t = (g.stamps_ns - g.stamps_ns[0]) * 1e-9
    # 25 s of canopy-grade fixes (no RTK): ~15 m of trajectory
    keep = ~rtk & (t < 25.0)
    fit = _fit(sim, keep)
    u = fit.uncertainty
    assert u is not None and not u.heading_fixed
    assert u.sigma_yaw_deg > MAX_YAW_SIGMA_DEG and u.baseline_m < 25.0
    assert len(u.warnings) == 1 and "too short to fix the heading" in u.warnings[0]
    # the heading error really is of the size the warning states (not within 0.1 deg)
    z = _z_scores(sim, fit)
    assert abs(z[0]) < 3.0
    assert "warnings" in fit.to_dict()["uncertainty"]


@pytest.mark.parametrize("method", ["yaw2d", "rigid3d"])
def test_both_methods_report_an_uncertainty(method: str) -> None:
    sim = run_simulation(5, 1, SimulationConfig(area=60.0, drift_m=0.0))
    g = sim.gnss.fixes
    fit = fit_georeference(g, sim.graph.stamps_ns, sim.graph.positions, method=method)
    assert fit.uncertainty is not None
    assert np.all(np.isfinite(fit.uncertainty.sigma_translation_m))
    assert np.all(np.abs(_z_scores(sim, fit)) < 4.0)


def test_georef_command_shows_sigma_and_the_short_baseline_warning(tmp_path) -> None:  # type: ignore[no-untyped-def]
    import json

    from click.testing import CliRunner

    from standgrid.cli import cli
    from standgrid.mission.sensors import read_gnss, write_gnss
    from standgrid.simulate import simulate_mission

    sim = simulate_mission(tmp_path, seed=3, area=60.0, points_per_payload=500)
    assert sim.mission_dir is not None
    log = sim.mission_dir / "gnss" / "fixes.txt"
    runner = CliRunner()
    result = runner.invoke(cli, ["georef", str(sim.mission_dir)])
    assert result.exit_code == 0 and "uncertainty  1-sigma yaw" in result.stdout
    assert "WARNING" not in result.stdout
    # keep 25 s of canopy-grade fixes only (per-payload logs removed: the log is the source)
    g = read_gnss(log)
    keep = (g.quality != 4) & ((g.stamps_ns - g.stamps_ns[0]) < 25_000_000_000)
    import shutil
    from dataclasses import replace

    shutil.rmtree(sim.mission_dir / "payloads" / "gnss")
    short = replace(
        g,
        **{
            k: getattr(g, k)[keep]
            for k in ("stamps_ns", "lat", "lon", "alt", "quality", "h_std", "v_std")
        },
    )
    write_gnss(short, log)
    result = runner.invoke(cli, ["georef", str(sim.mission_dir), "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["uncertainty"]["sigma_yaw_deg"] > MAX_YAW_SIGMA_DEG
    assert len(data["warnings"]) == 1 and "too short to fix the heading" in data["warnings"][0]
    assert "too short to fix the heading" in result.stderr
