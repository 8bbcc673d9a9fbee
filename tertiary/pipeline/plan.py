"""The streamed stages as :class:`~tertiary.core.stage.Stage` values, in pipeline order.

Each class is a thin adapter: it binds a stage's configuration and the run's fixed context
(radars, system frame, fusion methods, tracker filters…) when it is built and calls the stage's
step function, so it produces exactly what that function produces. Inputs and outputs are
named tables holding the window's rows (what :func:`tertiary.pipeline.streaming.pipeline_step` passes
and receives); an adapter refuses a bad window or rows outside it with
:func:`~tertiary.core.stage.check_window`.

Three kinds of outputs are not a window's rows: :attr:`totals` are one-row counts that add up
over windows (the association statistics), :attr:`sums` are keyed counts whose rows of one key
add up over windows (the evaluation's percentile sketch counts) and :attr:`snapshots` describe
the state after the window (the association's live targets, which the centralised reference of
the same window reads).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace
from typing import Any, ClassVar

import numpy as np
import polars as pl

from safety.confirmation import ConfirmState, confirm_step
from safety.alerts.episodes import scored_conflicts
from safety.alerts.tradeoff import CURVE_THREADS, curve_settings
from safety.conflicts import ConflictConfig, ConflictState, conflicts_step, conflicts_steps, init_conflict_state
from tertiary import contract as schema
from tertiary.core import geo
from tertiary.core.stage import Stage, Window, check_window
from tertiary.evaluation import sketch
from tertiary.evaluation.evaluate import EvaluationConfig, Reference, radar_sites
from tertiary.evaluation.streamed import PICTURE_VALUES, MatchState, match_window
from tertiary.pipeline.pictures import as_picture, confirmed_only, safety_id_column
from tertiary.pipeline.tables import NOT_SCORED
from tertiary.stages import align as align_stage
from tertiary.stages.association.associate import AssociationConfig, associate_step, init_associate_state
from tertiary.stages.clustering import ClusteringConfig, cluster_step, init_cluster_state
from tertiary.stages.flight_data import DepartureConfig, departure_step, init_departure_state
from tertiary.stages.fusion.centralized import CentralizedConfig, centralized_step, init_centralized_state
from tertiary.stages.fusion import FusionConfig, fuse_step, init_fuse_state
from tertiary.stages.tracking.tracker import TrackerConfig, init_track_state, track_step

#: the streamed stages the pipeline runs, in pipeline order (one window goes through them in this
#: order; :func:`tertiary.pipeline.streaming.pipeline_step` steps each through its adapter)
STAGES: tuple[str, ...] = ("align", "departures", "associate", "fuse", "centralized", "cluster", "track",
                           "conflicts", "stca_curves", "evaluation")
#: stages with the same contract that a run does not step on their own: conflict prediction
#: confirms its alerts itself; the m-of-n confirmation is a stage for pictures scored alone
EXTRA_STAGES: tuple[str, ...] = ("alert_confirmation",)


class _Adapter:
    """What every adapter shares: its name and the outputs that are not rows of the window."""

    name: ClassVar[str]
    #: one-row outputs whose columns add up over windows
    totals: ClassVar[tuple[str, ...]] = ()
    #: outputs that describe the state after the window (not appended)
    snapshots: ClassVar[tuple[str, ...]] = ()
    #: keyed outputs → their columns that add up over windows (the other columns are the key)
    sums: ClassVar[Mapping[str, tuple[str, ...]]] = {}


@dataclass(frozen=True)
class AlignStage(_Adapter):
    """Reports onto the epoch grid (:func:`tertiary.stages.align.align_step`).

    Input ``reports`` (time in the window); outputs ``aligned`` and ``rejects``. The grid origin
    is the run's (``grid_origin_us``), or, for a run that is one window, the window's own."""

    radars: pl.DataFrame
    origin: geo.LocalFrame
    cfg: align_stage.AlignConfig
    grid_origin_us: int | None = None
    name: ClassVar[str] = "align"

    def init(self) -> align_stage.AlignState:
        return align_stage.init_align_state()

    def step(self, state: align_stage.AlignState, inputs: Mapping[str, pl.DataFrame], window: Window
             ) -> tuple[dict[str, pl.DataFrame], align_stage.AlignState]:
        reports = inputs["reports"]
        check_window(reports, window, column="time", table="reports")
        g0 = self.grid_origin_us
        if g0 is None:
            g0 = align_stage.epoch_grid(reports, self.radars, self.cfg)[0] if reports.height else 0
        (aligned, rejects), new = align_stage.align_step(
            state, reports, self.radars, self.origin, None if window.open_start else window.t0_us,
            None if window.open_end else window.t1_us, g0, self.cfg)
        return {"aligned": aligned, "rejects": rejects}, new


@dataclass(frozen=True)
class DeparturesStage(_Adapter):
    """Departure correlation by aerodrome and time (:func:`tertiary.stages.flight_data.departure_step`).

    Inputs ``aligned`` (epoch in the window), ``reports`` (the window's new reports) and
    ``codes`` (run, report_id, mode_3a of every report ``aligned`` refers to); output ``aligned``
    with the cleared levels filled."""

    plans: pl.DataFrame
    cfg: DepartureConfig
    name: ClassVar[str] = "departures"

    def init(self) -> Any:
        return init_departure_state()

    def step(self, state: Any, inputs: Mapping[str, pl.DataFrame], window: Window
             ) -> tuple[dict[str, pl.DataFrame], Any]:
        aligned = inputs["aligned"]
        check_window(aligned, window, table="aligned")
        codes = inputs.get("codes")
        if codes is None or self.plans.height == 0:
            return {"aligned": aligned}, state
        aligned, new = departure_step(state, aligned, inputs["reports"], codes, self.plans, self.cfg)
        return {"aligned": aligned}, new


@dataclass(frozen=True)
class AssociateStage(_Adapter):
    """Which aligned reports are the same aircraft (:func:`~tertiary.stages.association.associate.associate_step`).

    Input ``aligned``; outputs ``associations``, ``stats`` (one row of
    :class:`~tertiary.stages.association.associate.AssociationStats`) and ``live_targets`` (the
    target ids that may still be associated after the window)."""

    cfg: AssociationConfig
    name: ClassVar[str] = "associate"
    totals: ClassVar[tuple[str, ...]] = ("stats",)
    snapshots: ClassVar[tuple[str, ...]] = ("live_targets",)

    def init(self) -> Any:
        return init_associate_state()

    def step(self, state: Any, inputs: Mapping[str, pl.DataFrame], window: Window
             ) -> tuple[dict[str, pl.DataFrame], Any]:
        aligned = inputs["aligned"]
        check_window(aligned, window, after_us=state.t_us, table="aligned")
        (associations, stats), new = associate_step(state, aligned, window.t0_us, window.t1_us, self.cfg)
        return {"associations": associations, "stats": pl.DataFrame([asdict(stats)]),
                "live_targets": new.live_targets()}, new


@dataclass(frozen=True)
class FuseStage(_Adapter):
    """Multi-radar fusion by every configured method (:func:`~tertiary.stages.fusion.fuse_step`).

    Inputs ``rows`` (aligned rows with their ``target_id``, epoch in the window, sorted by run,
    epoch, target_id, radar_id) and ``plots`` (measured plots of the reports up to the window's
    end); output ``fused``."""

    radars: pl.DataFrame
    methods: tuple[str, ...]
    cfg: FusionConfig
    origin: geo.LocalFrame
    name: ClassVar[str] = "fuse"

    def init(self) -> Any:
        return init_fuse_state()

    def step(self, state: Any, inputs: Mapping[str, pl.DataFrame], window: Window
             ) -> tuple[dict[str, pl.DataFrame], Any]:
        rows = inputs["rows"]
        check_window(rows, window, table="rows")
        fused, new = fuse_step(state, rows, self.radars, self.methods, self.cfg, self.origin, inputs.get("plots"),
                               window.t0_us, window.t1_us)
        return {"fused": fused}, new


@dataclass(frozen=True)
class CentralizedStage(_Adapter):
    """The centralised reference (:func:`~tertiary.stages.fusion.centralized.centralized_step`).

    Inputs ``reports`` (validated reports up to the window's end), ``associations``, ``keys``
    (run, epoch, target_id to estimate, epoch in the window) and ``live`` (the association's
    ``live_targets`` after the window; optional); output ``centralized`` (fused rows of method
    "centralized")."""

    radars: pl.DataFrame
    origin: geo.LocalFrame
    cfg: CentralizedConfig
    name: ClassVar[str] = "centralized"

    def init(self) -> Any:
        return init_centralized_state()

    def step(self, state: Any, inputs: Mapping[str, pl.DataFrame], window: Window
             ) -> tuple[dict[str, pl.DataFrame], Any]:
        keys = inputs["keys"]
        check_window(keys, window, table="keys")
        out, new = centralized_step(state, inputs["reports"], self.radars, inputs["associations"], keys, self.origin,
                                    self.cfg, window.t0_us, window.t1_us, live=inputs.get("live"))
        return {"centralized": out}, new


@dataclass(frozen=True)
class ClusterStage(_Adapter):
    """Clustering of fused targets (:func:`~tertiary.stages.clustering.cluster_step`): input
    ``fused``, output ``clusters``."""

    cfg: ClusteringConfig
    name: ClassVar[str] = "cluster"

    def init(self) -> Any:
        return init_cluster_state()

    def step(self, state: Any, inputs: Mapping[str, pl.DataFrame], window: Window
             ) -> tuple[dict[str, pl.DataFrame], Any]:
        fused = inputs["fused"]
        check_window(fused, window, after_us=state.t_us, table="fused")
        clusters, new = cluster_step(state, fused, window.t0_us, window.t1_us, self.cfg)
        return {"clusters": clusters}, new


@dataclass(frozen=True)
class TrackStage(_Adapter):
    """The secondary trackers (:func:`~tertiary.stages.tracking.tracker.track_step`): input
    ``fused`` (every fusion method's picture, no centralised reference), output ``tracks``.
    Without filters no track is made."""

    filters: Any                      # names, or name → filter (tracker ``Filters``)
    cfg: TrackerConfig
    names: Sequence[str] | None = None   # the filters' names the state is made for (default: ``filters``)
    name: ClassVar[str] = "track"

    def init(self) -> Any:
        return init_track_state(self.filters if self.names is None else self.names)

    def step(self, state: Any, inputs: Mapping[str, pl.DataFrame], window: Window
             ) -> tuple[dict[str, pl.DataFrame], Any]:
        fused = inputs["fused"]
        check_window(fused, window, table="fused")
        if not self.filters:
            return {"tracks": schema.empty_frame("tracks", False)}, state
        tracks, new = track_step(state, fused, self.filters, self.cfg, window.t0_us, window.t1_us)
        return {"tracks": tracks}, new


@dataclass(frozen=True)
class ConflictsStage(_Adapter):
    """Conflict prediction (:func:`safety.conflicts.conflicts_step`): input ``picture`` (its ids
    in ``id_col``, every picture named in ``method``), output ``conflicts``."""

    cfg: ConflictConfig
    id_col: str
    origin: geo.LocalFrame
    name: ClassVar[str] = "conflicts"

    def init(self) -> Any:
        return init_conflict_state()

    def step(self, state: Any, inputs: Mapping[str, pl.DataFrame], window: Window
             ) -> tuple[dict[str, pl.DataFrame], Any]:
        picture = inputs["picture"]
        check_window(picture, window, table="picture")
        conflicts, new = conflicts_step(state, picture, self.cfg, self.id_col, self.origin, window.t0_us,
                                        window.t1_us)
        return {"conflicts": conflicts}, new


@dataclass(frozen=True)
class StcaCurvesStage(_Adapter):
    """Conflict prediction under every point of the STCA trade-off curves
    (:func:`safety.alerts.tradeoff.curve_settings`), one carried state per setting: input
    ``picture`` (as :class:`ConflictsStage`), output ``curve_rows`` — each setting's
    :func:`~safety.alerts.episodes.scored_conflicts` with its index in ``setting``. The whole-run
    stage then only scores them."""

    settings: tuple[ConflictConfig, ...]
    id_col: str
    origin: geo.LocalFrame
    name: ClassVar[str] = "stca_curves"

    def init(self) -> tuple[ConflictState, ...]:
        return tuple(init_conflict_state() for _ in self.settings)

    def step(self, state: tuple[ConflictState, ...], inputs: Mapping[str, pl.DataFrame], window: Window
             ) -> tuple[dict[str, pl.DataFrame], tuple[ConflictState, ...]]:
        picture = inputs["picture"]
        check_window(picture, window, table="picture")
        if not self.settings:
            return {"curve_rows": empty_curve_rows()}, state
        # each setting's work is mostly numpy, polars and the KD-tree, outside the GIL
        with ThreadPoolExecutor(CURVE_THREADS) as pool:
            steps = conflicts_steps(list(state), picture, list(self.settings), self.id_col, self.origin,
                                    window.t0_us, window.t1_us, slim=False, map_=pool.map, scored_only=True)
            rows = list(pool.map(scored_conflicts, [out for out, _ in steps]))
        out = pl.concat([r.with_columns(pl.lit(k, pl.UInt16).alias("setting")) for k, r in enumerate(rows)],
                        how="vertical_relaxed")
        return {"curve_rows": out.select(list(CURVE_ROWS)).cast(CURVE_ROWS)}, tuple(s for _, s in steps)


@dataclass(frozen=True)
class EvaluationStage(_Adapter):
    """The evaluation's matching and seed metrics (:func:`tertiary.evaluation.streamed.match_window`)
    against the run's validated truth (``reference``): inputs ``fused`` and ``tracks`` (the
    window's rows) and, optional, ``aligned`` (its reports' aircraft: what continuity expects
    covered); outputs ``matched.<group>`` and ``expected.<group>``, one pair per picture schema
    (a picture's rows told by ``method``), for each picture the window has — each fusion
    method's confirmed targets (``target_id``) and each tracker picture "<method>+<filter>"
    (``track_id``) — and, with ``aligned``, every picture's ``scored`` rows and per-epoch seed
    sums, and with ``multitarget`` the percentile sketch counts (:attr:`sums`). The whole-run stage
    then finishes the metrics."""

    sums: ClassVar[Mapping[str, tuple[str, ...]]] = {PICTURE_VALUES: (sketch.COUNT,)}
    reference: Reference
    cfg: EvaluationConfig
    multitarget: bool
    #: the radar sites in the system frame (the range breakdown); None: no range breakdown
    radar_xy: np.ndarray | None = None
    name: ClassVar[str] = "evaluation"

    def init(self) -> MatchState:
        return MatchState()

    def step(self, state: MatchState, inputs: Mapping[str, pl.DataFrame], window: Window
             ) -> tuple[dict[str, pl.DataFrame], MatchState]:
        fused, tracks = inputs["fused"], inputs["tracks"]
        check_window(fused, window, table="fused")
        check_window(tracks, window, table="tracks")
        pictures = []
        # the columns the whole-run stage would not read of a stored picture, dropped as it does
        for frame, id_col in ((confirmed_only(fused), "target_id"), (as_picture(tracks) if tracks.height else tracks,
                                                                      "track_id")):
            if frame.height:
                pictures += [(name, id_col, part.drop(NOT_SCORED, strict=False)) for (name,), part in
                             frame.partition_by("method", as_dict=True, maintain_order=True).items()]
        return match_window(state, pictures, self.reference, self.cfg, self.multitarget,
                            window_aircraft(inputs.get("aligned"), window), self.radar_xy)


def window_aircraft(aligned: pl.DataFrame | None, window: Window) -> pl.DataFrame | None:
    """(run, epoch, truth_id) of a window's aligned rows; None without them or their aircraft."""
    if aligned is None:
        return None
    check_window(aligned, window, table="aligned")
    if "truth_id" in aligned.columns:
        return aligned.select("run", "epoch", "truth_id")
    if aligned.height == 0:         # a window without reports: nobody to expect covered
        return pl.DataFrame(schema={"run": pl.UInt32, "epoch": schema.TIME, "truth_id": pl.Int64})
    return None


#: the columns of the ``curve_rows`` a run's windows make (:class:`StcaCurvesStage`)
CURVE_ROWS: dict[str, pl.DataType] = {
    "setting": pl.UInt16, "run": pl.UInt32, "method": pl.String, "epoch": schema.TIME, "id_a": pl.UInt64,
    "id_b": pl.UInt64, "alert": pl.Boolean, "r_min_m": pl.Float64, "dz_min_m": pl.Float64, "t_min_s": pl.Float64}


def empty_curve_rows() -> pl.DataFrame:
    return pl.DataFrame(schema=CURVE_ROWS)


def stca_settings(cfg: Any) -> tuple[ConflictConfig, ...]:
    """The conflict configuration of every point of a run's STCA curves (none without safety or
    without a look-ahead), in :func:`safety.alerts.tradeoff.curve_settings` order."""
    if not (cfg.safety and cfg.stca_lookaheads_s):
        return ()
    return tuple(cc for _, _, cc in curve_settings(cfg.conflicts, cfg.stca_confidences, cfg.stca_fixed_m,
                                                   cfg.stca_lookaheads_s))


@dataclass(frozen=True)
class AlertConfirmationStage(_Adapter):
    """m-of-n alert confirmation (:func:`safety.confirmation.confirm_step`), one picture epoch
    at a time.

    Inputs ``conflicts`` (run, epoch, method, id_a, id_b and the unconfirmed condition
    ``raw_alert``, or ``alert`` when there is no ``raw_alert``) and ``epochs`` (optional: the
    picture's epochs in the window, column ``epoch``; an epoch without a conflict row still
    counts as one without the condition). The pictures share their epochs. Output ``conflicts``
    with ``raw_alert`` and the confirmed ``alert``."""

    m: int
    n: int
    name: ClassVar[str] = "alert_confirmation"

    def init(self) -> ConfirmState:
        return ConfirmState()

    def step(self, state: ConfirmState, inputs: Mapping[str, pl.DataFrame], window: Window
             ) -> tuple[dict[str, pl.DataFrame], ConfirmState]:
        rows = inputs["conflicts"]
        check_window(rows, window, table="conflicts")
        if "raw_alert" not in rows.columns:
            rows = rows.with_columns(pl.col("alert").alias("raw_alert"))
        epochs = rows["epoch"]
        if inputs.get("epochs") is not None:
            check_window(inputs["epochs"], window, table="epochs")
            epochs = pl.concat([epochs, inputs["epochs"]["epoch"].cast(epochs.dtype)])
        out = []
        for epoch in epochs.unique().sort():
            part = rows.filter(pl.col("epoch") == epoch)
            state, flags = confirm_step(state, part, self.m, self.n)
            out.append(part.with_columns(flags))
        return {"conflicts": pl.concat(out) if out else rows.with_columns(pl.col("raw_alert").alias("alert"))}, state


#: the adapter of each name of :data:`STAGES`
CLASSES: dict[str, type] = {c.name: c for c in (AlignStage, DeparturesStage, AssociateStage, FuseStage,
                                                  CentralizedStage, ClusterStage, TrackStage, ConflictsStage,
                                                  StcaCurvesStage, EvaluationStage, AlertConfirmationStage)}


def reference_config(cfg: Any) -> CentralizedConfig:
    """The centralised reference's configuration of a ``PipelineConfig``: its own, with the fused
    pictures' ``min_plots`` and ``min_plots_primary`` and the secondary tracker's initiation
    parameters, so that it confirms its targets as the pictures it is compared with do."""
    t = cfg.tracker
    return replace(cfg.centralized_cfg, min_plots=cfg.fusion.min_plots,
                   min_plots_primary=cfg.fusion.min_plots_primary, v_min_mps=t.v_min_mps,
                   v_max_mps=t.v_max_mps, confirm_gate_m=t.confirm_gate_m)


def build_stage(name: str, cfg: Any, context: Any) -> Stage:
    """The stage ``name`` of :data:`STAGES` for a ``PipelineConfig`` and a run context (its
    ``radars``, ``origin``, ``grid_origin_us``, ``filters`` and ``departure_plans``)."""
    radars, origin = context.radars, context.origin
    builders = {
        "align": lambda: AlignStage(radars, origin, cfg.align, context.grid_origin_us),
        "departures": lambda: DeparturesStage(getattr(context, "departure_plans", pl.DataFrame()), cfg.departures),
        "associate": lambda: AssociateStage(cfg.association),
        "fuse": lambda: FuseStage(radars, tuple(cfg.methods), cfg.fusion, origin),
        # the reference confirms its targets with the pictures' count and the tracker's initiation test
        "centralized": lambda: CentralizedStage(radars, origin, reference_config(cfg)),
        "cluster": lambda: ClusterStage(cfg.clustering),
        "track": lambda: TrackStage(context.filters, cfg.tracker, tuple(cfg.filters)),
        "conflicts": lambda: ConflictsStage(cfg.conflicts, safety_id_column(cfg), origin),
        "stca_curves": lambda: StcaCurvesStage(stca_settings(cfg), safety_id_column(cfg), origin),
        "evaluation": lambda: EvaluationStage(getattr(context, "reference", None), cfg.scoring, cfg.evaluation,
                                              radar_sites(radars, origin)),
        "alert_confirmation": lambda: AlertConfirmationStage(cfg.conflicts.confirm_m, cfg.conflicts.confirm_n),
    }
    if name not in builders:
        raise KeyError(f"no stage {name!r}; the stages are {', '.join((*STAGES, *EXTRA_STAGES))}")
    return builders[name]()


def build_stages(cfg: Any, context: Any, names: Sequence[str] = STAGES) -> dict[str, Stage]:
    """The stages ``names`` (default: every one of :data:`STAGES`, in pipeline order) built for
    ``cfg`` (a ``PipelineConfig``) and ``context`` (a ``RunContext``). Which of them a run
    uses is the configuration's: ``centralized``, ``filters``, ``safety``, departure plans."""
    return {n: build_stage(n, cfg, context) for n in names}
