"""The job's configuration: :class:`PipelineConfig` (every stage's own frozen dataclass), its
check (:func:`check_config`) and the airspace adaptation taken from a dataset's scenario
(:func:`adapt_to_scenario`). :func:`config_dict` (the configuration as the run record stores
it) is :func:`tertiary.runtime.windows.config_dict`, re-exported here."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

from safety import conflicts as safety_conflicts
from tertiary import contract
from tertiary.core.errors import DataError, OptionError
from tertiary.core.units import FT
from tertiary.evaluation.evaluate import EvaluationConfig
from tertiary.io.dataset import Dataset
from tertiary.runtime.windows import config_dict
from tertiary.sensors.collection import CollectionConfig
from tertiary.simulate.traffic import aerodromes, final_approaches
from tertiary.stages.align import AlignConfig
from tertiary.stages.association.associate import AssociationConfig
from tertiary.stages.clustering import ClusteringConfig
from tertiary.stages.flight_data import DepartureConfig
from tertiary.stages.fusion import ALL_METHODS, METHODS, FusionConfig
from tertiary.stages.fusion.centralized import CentralizedConfig
from tertiary.filters import REGISTRY
from tertiary.stages.tracking.tracker import TrackerConfig
from tertiary.stages.tracking.downlinks import downlink_noise, with_noise

__all__ = ["PipelineConfig", "adapt_to_scenario", "check_config", "config_dict", "default_conflict_config"]

# `safety` is imported as modules, not names: `import safety` first imports `tertiary` (whose
# package imports this one) while `safety` is half initialised, and only a module binding
# survives that


def default_conflict_config() -> safety_conflicts.ConflictConfig:
    """The seed's rule with a controller's alert confirmation (m of n picture epochs)."""
    m, n = safety_conflicts.STCA_CONFIRMATION
    return safety_conflicts.ConflictConfig(confirm_m=m, confirm_n=n)


@dataclass(frozen=True)
class PipelineConfig:
    """Configuration of every stage (each stage's own frozen dataclass)."""

    methods: tuple[str, ...] = METHODS
    filters: tuple[str, ...] = ("singer", "imm_sym")
    centralized: bool = True
    strict: bool = False
    limits: contract.Limits = field(default_factory=contract.Limits)
    align: AlignConfig = field(default_factory=AlignConfig)
    association: AssociationConfig = field(default_factory=AssociationConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    centralized_cfg: CentralizedConfig = field(default_factory=CentralizedConfig)
    clustering: ClusteringConfig = field(default_factory=ClusteringConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    safety: bool = True
    #: the picture conflict prediction runs on: "tracks" — the secondary tracker's confirmed tracks,
    #: one picture per fusion method × filter (what a controller sees); "fused" — the fused plot
    #: sets. Without filters, "tracks" falls back to "fused" (with a note).
    safety_picture: Literal["tracks", "fused"] = "tracks"
    conflicts: safety_conflicts.ConflictConfig = field(default_factory=default_conflict_config)
    #: departure correlation by aerodrome and time (tertiary.stages.flight_data, "Departure correlation"):
    #: a departing track whose code correlates with no plan gets its plan's cleared level
    departures: DepartureConfig = field(default_factory=DepartureConfig)
    #: STCA final-approach volumes (safety.conflicts.ApproachVolume) from the scenario's runways
    #: (terminal-area, national) when ``conflicts`` configures none: the pairs established on
    #: one final are decided with the reduced in-trail minimum and a shorter look-ahead
    stca_approach_volumes: bool = True
    #: STCA and loss-of-separation scoring with the en-route minima above the scenario's en-route
    #: floor (safety.conflicts "En-route airspace"; national: FL150)
    stca_enroute_floor: bool = True
    #: STCA inhibited, and no loss of separation scored, between two aircraft both in one of the
    #: scenario's aerodrome zones (safety.conflicts "Aerodrome zones"; national: its airports)
    stca_aerodrome_zones: bool = True
    #: STCA trade-off curves (metrics stage "safety_tradeoff"): losses alerted with ≥ X s warning
    #: against nuisance + false alerts per hour as the threshold confidence (covariance
    #: thresholds), the fixed estimation term (m) and the look-ahead (s) vary; each point is one
    #: conflict prediction + scoring of every picture, so the default
    #: is the configured look-ahead only; () skips the curves. Needs truth.
    stca_lookaheads_s: tuple[float, ...] = (105.0,)
    stca_confidences: tuple[float, ...] = (0.5, 0.8, 0.95, 0.99)
    stca_fixed_m: tuple[float, ...] = (0.0, 300.0, 600.0, 1200.0)
    #: the one evaluation stage (tertiary.evaluation.evaluate) scores every picture — each fusion method's
    #: confirmed targets and the centralised reference (seed stage "fusion"), each tracker picture
    #: (seed stage "tracker") — when there is a reference. ``evaluation`` adds the surveillance
    #: metrics (stage "evaluation") and the ``requirements`` table judged against
    #: ``requirements_file`` (None: the shipped example, datasets/requirements/example.toml)
    evaluation: bool = True
    requirements_file: str | None = None
    scoring: EvaluationConfig = field(default_factory=EvaluationConfig)
    #: radar registration before alignment (:func:`tertiary.stages.align.apply_registration`): with
    #: ``register``, rows (radar_id, range_bias_m, azimuth_bias_deg, time_offset_s, range_gain) of
    #: ``registration``, or when empty estimated from the reports radar to radar
    #: (:func:`tertiary.sensors.registration.estimate`, method "multi"; the truth is never used)
    register: bool = False
    registration: tuple[tuple[float, float, float, float, float], ...] = ()
    #: §1.7/§5.1/§2.2–2.3 indicators of every tracker picture (tertiary.evaluation.indicators; metrics stage
    #: "indicators"); needs truth. Off by default (one more matching per picture).
    indicators: bool = False
    #: per-radar health from the range innovations (tertiary.sensors.radar_health; metrics stage
    #: "radar_health"): windowed-NIS divergence alarm, adaptive-R estimates. Off by default.
    radar_health: bool = False
    #: report collection ahead of alignment (:mod:`tertiary.sensors.collection`, §1.4): the queue
    #: discipline and processing-time model; lost reports go to ``rejects`` (stage "collection")
    collection: CollectionConfig | None = None


def adapt_to_scenario(cfg: PipelineConfig, ds: Dataset) -> PipelineConfig:
    """``cfg`` with the airspace adaptation an STCA is installed with, taken from the dataset's
    scenario unless ``cfg.conflicts`` already has it: the final-approach volumes of its runways
    (:func:`tertiary.simulate.traffic.final_approaches`; off with ``stca_approach_volumes``) and
    the floor of its en-route airspace (``national.enroute_floor_fl``; off with
    ``stca_enroute_floor``) and its aerodrome zones (:func:`tertiary.simulate.traffic.aerodromes`;
    off with ``stca_aerodrome_zones``); and, unless ``cfg.tracker.calibrate_downlinks`` is off,
    the noise of the downlinked registers measured from its replies
    (:func:`tertiary.stages.tracking.downlinks.downlink_noise`), once: the configuration returned
    carries the σ measured, so a slice of the run adapted again keeps the whole run's."""
    if cfg.tracker.calibrate_downlinks:
        cfg = with_noise(cfg, downlink_noise(ds.reports))
    scen = getattr(ds, "scenario", None)
    if scen is None:
        return cfg
    conflicts = cfg.conflicts
    try:
        frame = ds.origin
    except DataError:
        frame = None
    if cfg.stca_approach_volumes and not conflicts.approach_volumes:
        vols = tuple(safety_conflicts.ApproachVolume(x, y, course, length_m=length, name=f"final {course:05.1f}")
                     for x, y, course, length in final_approaches(scen, frame))
        if vols:
            conflicts = dataclasses.replace(conflicts, approach_volumes=vols)
    floor_fl = getattr(getattr(scen, "national", None), "enroute_floor_fl", 0.0)
    if cfg.stca_enroute_floor and conflicts.enroute_above_m is None and floor_fl > 0:
        # half a level below it: an aircraft level at the floor is in it, whatever its altitude noise
        conflicts = dataclasses.replace(conflicts, enroute_above_m=(float(floor_fl) * 100.0 - 500.0) * FT)
    if cfg.stca_aerodrome_zones and not conflicts.aerodrome_zones:
        zones = tuple(safety_conflicts.AerodromeZone(x, y, name=name) for name, x, y in aerodromes(scen, frame))
        if zones:
            conflicts = dataclasses.replace(conflicts, aerodrome_zones=zones)
    return cfg if conflicts is cfg.conflicts else dataclasses.replace(cfg, conflicts=conflicts)


def check_config(cfg: PipelineConfig | None) -> PipelineConfig:
    """``cfg`` (None = the defaults) after checking its names and numbers (:class:`OptionError`)."""
    cfg = cfg or PipelineConfig()
    unknown = sorted(set(cfg.methods) - set(ALL_METHODS))   # the optional methods too (not in the default)
    if unknown:
        raise OptionError(f"unknown fusion method(s) {', '.join(unknown)}; choose from {', '.join(ALL_METHODS)}",
                          option="methods")
    bad = sorted(set(cfg.filters) - set(REGISTRY))
    if bad:
        raise OptionError(f"unknown filter(s) {', '.join(bad)}; choose from {', '.join(sorted(REGISTRY))}",
                          option="filters")
    a = cfg.align
    if a.period_s is not None and not (isinstance(a.period_s, (int, float)) and 0 < a.period_s < float("inf")):
        raise OptionError(f"must be finite and > 0, got {a.period_s}", option="align.period_s")
    if cfg.safety_picture not in ("tracks", "fused"):
        raise OptionError(f"choose tracks or fused, got {cfg.safety_picture!r}", option="safety_picture")
    if (cfg.association.mode_3a != "off" or cfg.association.callsign != "off") and not cfg.align.identity:
        cfg = dataclasses.replace(cfg, align=dataclasses.replace(cfg.align, identity=True))  # fine identification
    return cfg


