"""A deterministic forest-mission simulator with known ground truth."""

from standgrid.simulate.canopy import generate_mixed_forest
from standgrid.simulate.from_scan import ScanMission, mission_from_scan
from standgrid.simulate.mission import (
    SimulatedMission,
    SimulationConfig,
    run_simulation,
    simulate_mission,
    simulate_pair,
)
from standgrid.simulate.raycast import RAYCAST_SCANNERS, RaycastScanner, raycast_scan
from standgrid.simulate.truth import Truth, load_truth

__all__ = [
    "RAYCAST_SCANNERS",
    "RaycastScanner",
    "ScanMission",
    "SimulatedMission",
    "SimulationConfig",
    "Truth",
    "generate_mixed_forest",
    "load_truth",
    "mission_from_scan",
    "raycast_scan",
    "run_simulation",
    "simulate_mission",
    "simulate_pair",
]
