"""Scenario simulation, the input side of the pipeline beside the readers of :mod:`tertiary.io`:
truth trajectories (:mod:`.traffic`, :mod:`.trajectory`) observed by simulated radars
(:mod:`.radar`, :mod:`.radar_tracker`), MLAT / WAM systems (:mod:`.mlat`, :mod:`.mlat_observe`) and
ADS-B ground stations (:mod:`.adsb_station`)
with their own secondary processing, producing a dataset's
``radars``, ``reports`` and ``truth`` tables (:mod:`.simulator`), configured by a scenario
(:mod:`.config`). :class:`Dataset`, :func:`read_dataset` and :func:`write_dataset` live in
:mod:`tertiary.io.dataset` and are re-exported here.
"""

from __future__ import annotations

import importlib
from typing import Any

from tertiary.simulate.adsb_station import AdsbStationConfig
from tertiary.simulate.mlat import MlatConfig
from tertiary.simulate.config import (AdsbConfig, Anomalies, RadarConfig, RadarTrackerConfig, ScenarioConfig, TrackerParams, TrafficConfig, TransponderConfig, builtin_scenarios, check_scenario, load_scenario, read_scenario_toml, resolve_data_path)
from tertiary.simulate.traffic import TerminalTraffic, big_box, terminal_area, terminal_traffic
from tertiary.simulate.trajectory import Trajectories

__all__ = ["Dataset", "simulate", "write_dataset", "read_dataset", "simulate_windows", "write_stream", "SimWindow", "load_scenario", "builtin_scenarios",
           "ScenarioConfig", "RadarConfig", "Anomalies", "TrafficConfig", "TrackerParams", "AdsbConfig",
           "TransponderConfig", "RadarTrackerConfig", "MlatConfig", "AdsbStationConfig",
           "Trajectories", "big_box", "terminal_area", "resolve_data_path", "check_scenario",
           "read_scenario_toml", "block_s", "terminal_traffic", "TerminalTraffic", "NATIONAL_EPOCH"]

#: names looked up in their module on first use. ``tertiary.io.dataset`` imports this package's
#: scenario config; importing the simulator (which imports ``tertiary.io.dataset``) here would
#: make ``import tertiary.io.dataset`` re-enter that module half-made.
_LATER = {"Dataset": "tertiary.io.dataset", "read_dataset": "tertiary.io.dataset", "write_dataset": "tertiary.io.dataset",
          **dict.fromkeys(("simulate", "simulate_windows", "write_stream", "SimWindow", "block_s", "NATIONAL_EPOCH",
                           "STREAMED", "radars_frame", "flight_plans"), "tertiary.simulate.simulator")}


def __getattr__(name: str) -> Any:
    if name in _LATER:
        return getattr(importlib.import_module(_LATER[name]), name)
    raise AttributeError(f"module 'tertiary.simulate' has no attribute {name!r}")
