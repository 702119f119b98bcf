"""Site and scenario files, ground truth, sensor and jammer emulators, as a pure-Python library.

No Zenoh, no clocks, no I/O beyond reading scenario files: the services in
``services/`` pace and publish what these functions compute, and the Monte Carlo
harness calls them directly. Everything is a deterministic function of
(scenario, process id, run); see ``sensors_sim/README.md``.
"""

from .emulators import SensorEvent, scan_times, sensor_events
from .jammer import JamEffect, JamState, jam_effect, jam_events, jam_state
from .loader import list_scenarios, load_scenario, load_site
from .noise import process_rng
from .spec import (
    SENSOR_KINDS,
    JammerSpec,
    Scenario,
    ScenarioError,
    SensorSpec,
    Site,
    SiteSpec,
    TargetSpec,
)
from .trajectories import Trajectory, TruthSample, truth_events, truth_trajectory

__all__ = [
    "SENSOR_KINDS",
    "JamEffect",
    "JamState",
    "JammerSpec",
    "Scenario",
    "ScenarioError",
    "SensorEvent",
    "SensorSpec",
    "Site",
    "SiteSpec",
    "TargetSpec",
    "Trajectory",
    "TruthSample",
    "jam_effect",
    "jam_events",
    "jam_state",
    "list_scenarios",
    "load_scenario",
    "load_site",
    "process_rng",
    "scan_times",
    "sensor_events",
    "truth_events",
    "truth_trajectory",
]
