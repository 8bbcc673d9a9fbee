"""tertiary — tertiary processing of multi-radar air-traffic surveillance data.

Public API (the CLI is a thin layer over these):

* data contract: :func:`validate`, :data:`TABLES`, :class:`SchemaError`
* geodesy: :mod:`tertiary.core.geo` (WGS-84, ENU frames, radar polar, covariance propagation)
* simulation: :func:`simulate`, :func:`load_scenario`, :func:`write_dataset`, :func:`read_dataset`
* the radar's own secondary processing: :func:`track_reports`
* storage: :class:`RunStore`, :func:`export_parquet`
* stages: :func:`tertiary.stages.align.align`, :func:`candidate_pairs`, :func:`tertiary.stages.association.associate.associate`,
  :func:`fuse`, :func:`cluster`; the one evaluation stage :func:`evaluate_pictures` (matching by
  :func:`match_to_reference`, seed metrics in :mod:`tertiary.evaluation.accuracy`), the centralised reference in
  :mod:`tertiary.stages.fusion.centralized`, the posterior Cramér–Rao bound in :mod:`tertiary.evaluation.bound`
* radars that err: :class:`RadarTrackerConfig`, :class:`TransponderConfig` (the simulated radars'
  own association, :mod:`tertiary.simulate.radar_tracker`)
* the batch job: :func:`run` (writes the run database window by window, resumable), :func:`process`
  (in memory), :func:`ingest`; the windowed engine (:mod:`tertiary.runtime.windows`): :func:`stream` (the
  streamed stages, each a step function ``<stage>_step(state, window) -> (outputs, state)``) and
  :func:`finalize` (the whole-run stages)
* results: :func:`run_report` / :func:`list_reports` (the named SQL reports of ``sql/``, read-only,
  bound parameters), :func:`build_report` (the self-contained HTML report of a run)
"""

import os as _os
import sys as _sys

#: polars' allocator (jemalloc, prefix ``_rjem_``) purges a freed page after 0.5 s (dirty
#: decay, polars' own setting) but then only advises the kernel it may take it (muzzy decay,
#: 1 s): such pages stay in the resident set, so a stage stood on the last ones' pages. Muzzy
#: decay 0 hands them back when purged (12 h terminal-area production run: peak 1 240 -> 1 185
#: MiB, 112 -> 104 s wall; dirty decay 0 too: 1 093 MiB but 158 s). polars appends this variable
#: to its own setting when it loads, and jemalloc reads the result once: set before any import
#: of polars, unless the environment sets it.
if "polars" not in _sys.modules:
    _os.environ.setdefault("_RJEM_MALLOC_CONF", "muzzy_decay_ms:0")

from tertiary.evaluation import accuracy, bound
from tertiary.stages import align
from tertiary.stages.tracking import altitude
from tertiary.stages.association import associate
from tertiary.stages.fusion import centralized
from tertiary.core import geo  # noqa: E402
from tertiary.stages.align import AlignConfig
from tertiary.stages.association.associate import AssociationConfig
from tertiary.sensors.local_tracks import LocalTrackerConfig, track_reports
from tertiary.stages.clustering import ClusteringConfig, cluster
from tertiary.stages.fusion.fuse import (METHODS, ConfirmState, FusionConfig, confirm_step, fuse, fuse_bar_shalom_campo, measured_plots)
from tertiary.stages.association.gating import GatingConfig, candidate_pairs
from tertiary.core.errors import DataError, OptionError, ResourceError, TertiaryError
from tertiary.stages.align import AlignState, align_step, init_align_state
from tertiary.stages.association.associate import (AssociateState, AssociationStats, associate_step, init_associate_state)
from tertiary.stages.clustering import ClusterState, cluster_step, init_cluster_state
from tertiary.stages.fusion.fuse import FuseState, fuse_step, init_fuse_state
from tertiary.stages.fusion.centralized import CentralizedState, centralized_step, init_centralized_state
from tertiary.stages.tracking.tracker import TrackState, init_track_state, track_step
from tertiary.runtime.windows import PartStore, ReportSource, Window, windows
from tertiary.pipeline.job import PipelineConfig, StageError, finalize, ingest, process, run, screen, stream
from tertiary.contract.schema import (RULES, TABLES, Limits, SchemaError, UnsortedTimeWarning, contract_rules, validate)
from tertiary.simulate import Dataset, check_scenario, load_scenario, read_dataset, simulate, write_dataset
from tertiary.simulate.radar_tracker import RadarTrackerConfig
from tertiary.simulate.config import TransponderConfig
from tertiary.report.html import build_report
from tertiary.store.sql_reports import list_reports, run_report
from tertiary.store.run_store import RunStore, export_parquet

__version__ = "0.1.0"

__all__ = ["geo", "validate", "TABLES", "Limits", "SchemaError", "UnsortedTimeWarning", "simulate",
           "load_scenario", "write_dataset", "read_dataset", "Dataset", "track_reports", "LocalTrackerConfig",
           "RunStore", "export_parquet", "run", "ingest", "process", "PipelineConfig", "align", "AlignConfig",
           "associate", "AssociationConfig", "accuracy", "centralized", "candidate_pairs", "GatingConfig", "fuse", "FusionConfig", "METHODS",
           "cluster", "ClusteringConfig", "build_report", "list_reports", "run_report", "__version__",
           "screen", "StageError", "check_scenario", "RULES", "contract_rules", "TertiaryError", "OptionError",
           "DataError", "ResourceError", "altitude", "bound", "RadarTrackerConfig", "TransponderConfig",
           "measured_plots", "fuse_bar_shalom_campo", "confirm_step", "ConfirmState", "evaluate_pictures",
           "match_to_reference", "MatchConfig", "load_requirements", "check_requirements", "ALL_METHODS",
           "CollectionConfig", "collect", "IndicatorConfig", "bayes_threshold",
           "conversion_valid", "make_range_channel", "check_flight_plans", "correlate_flight_plans",
           "DepartureConfig", "correlate_departures",
           "adapt_to_scenario",
           # the windowed engine: every streamed stage is a step (state, window) -> (outputs, state)
           "AlignState", "align_step", "init_align_state", "AssociateState", "AssociationStats", "associate_step",
           "init_associate_state", "ClusterState", "cluster_step", "init_cluster_state", "FuseState", "fuse_step",
           "init_fuse_state", "CentralizedState", "centralized_step", "init_centralized_state", "TrackState",
           "init_track_state", "track_step", "PartStore", "ReportSource", "Window", "windows", "stream", "finalize"]
from tertiary.evaluation.evaluate import evaluate_pictures  # noqa: E402  (after the stages it builds on)
from tertiary.evaluation.matching import MatchConfig, match_to_reference  # noqa: E402
from tertiary.evaluation.requirements import check_requirements, load_requirements  # noqa: E402
from tertiary.stages.fusion.fuse import ALL_METHODS  # noqa: E402
from tertiary.sensors.collection import CollectionConfig, collect  # noqa: E402
from tertiary.evaluation.indicators import IndicatorConfig  # noqa: E402  (indicators(): tertiary.indicators)
from tertiary.stages.association.gating import bayes_threshold  # noqa: E402
from tertiary.stages.align import conversion_valid  # noqa: E402
from tertiary.stages.tracking.filters import make_range_channel  # noqa: E402
from tertiary.stages.flight_data import check_flight_plans  # noqa: E402
from tertiary.stages.flight_data import correlate as correlate_flight_plans  # noqa: E402
from tertiary.stages.flight_data import DepartureConfig  # noqa: E402
from tertiary.stages.flight_data import departure_step as correlate_departures  # noqa: E402
from tertiary.pipeline.job import adapt_to_scenario  # noqa: E402
