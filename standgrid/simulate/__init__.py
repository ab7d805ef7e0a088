"""A deterministic forest-mission simulator with known ground truth."""

from standgrid.simulate.from_scan import ScanMission, mission_from_scan
from standgrid.simulate.mission import (
    SimulatedMission,
    SimulationConfig,
    run_simulation,
    simulate_mission,
    simulate_pair,
)
from standgrid.simulate.truth import Truth, load_truth

__all__ = [
    "ScanMission",
    "SimulatedMission",
    "SimulationConfig",
    "Truth",
    "load_truth",
    "mission_from_scan",
    "run_simulation",
    "simulate_mission",
    "simulate_pair",
]
