"""Stage 5 — fusion of the reports associated to one system target, one time window at a time.

Input: one row per (run, epoch, report) already associated to a target (the ``aligned`` state
and covariance joined with ``associations``, plus ``fresh`` and ``nominal_var``; see
:data:`INPUT_COLUMNS`). Output: the ``fused`` table, one row per (run, epoch, target_id,
method), with the vertical channel (:mod:`~tertiary.stages.fusion.vertical`), the tracker's
measurement (:mod:`~tertiary.stages.fusion.measurement`) and ``tentative``
(:mod:`~tertiary.stages.fusion.confirm`). :func:`fuse_step` carries every recursion across
windows in a :class:`FuseState`; :func:`fuse` is the whole run as one window.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.contract import CLEARED_ALT_COLUMN, FUSED_EXTRA, SELECTED_ALT_COLUMN, TABLES, TURN_RATE_COLUMN, is_sorted_by
from tertiary.core import geo
from tertiary.core.units import STATE
from tertiary.stages.fusion.base import CHAIN, GROUP, F, layout, sym
from tertiary.stages.fusion.config import FusionConfig
from tertiary.stages.fusion.confirm import ConfirmState, confirm_targets_step
from tertiary.stages.fusion.gate import apply_gate
from tertiary.stages.fusion.measurement import measurements
from tertiary.stages.fusion.methods import METHODS
from tertiary.stages.fusion.methods.aposteriori import first_innovation_var, los_innovation, seed_fixed_variance
from tertiary.stages.fusion.methods.nis import empty_nis_carry, nis_inflation_step
from tertiary.stages.fusion.registry import REGISTRY, RunInputs, check_methods, run_methods
from tertiary.stages.fusion.vertical import AltCarry, vertical_channel
from tertiary.stages.tracking.altitude import ALT_COLUMNS

__all__ = ["INPUT_COLUMNS", "FuseState", "fuse", "fuse_step", "init_fuse_state"]

INPUT_COLUMNS = [
    *GROUP, "radar_id", "local_track_id", "report_id", *STATE, "cov",
    "res_range_m", "res_range_var_m2", "fresh", "nominal_var",
]


def check_columns(rows: pl.DataFrame) -> None:
    missing = [c for c in INPUT_COLUMNS if c not in rows.columns]
    if missing:
        raise ValueError(f"fusion input lacks column(s): {', '.join(missing)}")


def input_arrays(rows: pl.DataFrame) -> dict[str, NDArray]:
    n = rows.height
    col = lambda c: rows[c].cast(pl.Float64).fill_null(np.nan).to_numpy()  # noqa: E731
    return {
        "x": rows.select(STATE).to_numpy().astype(float),
        "cov": sym(rows["cov"].to_numpy().astype(float).reshape(n, 6, 6)),
        "res": col("res_range_m"),
        "res_var": col("res_range_var_m2"),
        "fresh": rows["fresh"].fill_null(False).to_numpy().astype(bool),
        "nominal_var": rows["nominal_var"].to_numpy().astype(float).reshape(n, 3),
    }


def _radar_sites(rows: pl.DataFrame, radars: pl.DataFrame, origin: geo.LocalFrame) -> tuple[F, F]:
    """Each row's radar site in the system frame (n, 3) and σ²_range (n,)."""
    unknown = set(rows["radar_id"].unique().to_list()) - set(radars["radar_id"].to_list())
    if unknown:
        raise ValueError(f"radar_id(s) {sorted(unknown)} missing from radars")
    e, n_, u = origin.from_geodetic(radars["lat_deg"].to_numpy(), radars["lon_deg"].to_numpy(),
                                    radars["alt_m"].to_numpy())
    table = radars.select(pl.col("radar_id").cast(pl.UInt32), pl.col("sigma_range_m").cast(pl.Float64)
                          ).with_columns(pl.Series("__e", e), pl.Series("__n", n_), pl.Series("__u", u))
    j = rows.select(pl.col("radar_id").cast(pl.UInt32)).join(table, on="radar_id", how="left", maintain_order="left")
    return j.select("__e", "__n", "__u").to_numpy(), j["sigma_range_m"].to_numpy() ** 2


def line_of_sight_inputs(methods: list[str], rows: pl.DataFrame, radars: pl.DataFrame,
                         origin: geo.LocalFrame | None, a: dict[str, NDArray]) -> None:
    """The per-row inputs of the ``line_of_sight`` methods, added to ``a``: the line of sight and
    the 3-D innovation terms ``u``, ``a_pred``, ``dvar`` (:func:`los_innovation`)."""
    los = [m for m in methods if REGISTRY[m].line_of_sight]
    if los:
        if origin is None:
            raise ValueError(f"{', '.join(los)}: needs the system frame origin (fuse(..., origin=...)) "
                             "for each radar's line of sight")
        site, sig2 = _radar_sites(rows, radars, origin)
        a["u"], a["a_pred"], a["dvar"] = los_innovation(a["x"], site, a["res_var"], sig2, a["nominal_var"])


@dataclass(frozen=True)
class FuseState:
    """Everything :func:`fuse_step` carries from one window to the next (natural keys only):

    * ``chains``: per (run, target_id, radar_id) of each target's last fused group, the weights
      b(k−1) of the a-posteriori recursions (``w_<method>``; ``w_aposteriori_coord_{0,1,2}``
      per axis) — the radar set of that group is its rows;
    * ``seed_first``: per (run, radar_id, local_track_id) the first finite ``res_range_var_m2``
      (D_n of ``aposteriori_seed``, (4.75)–(4.76));
    * ``nis``: per local track the last ``nis_window`` NIS values and moving mean (``invcov_nis``);
    * ``alt``: the Mode C filters of the vertical channel (:class:`AltCarry`);
    * ``confirm``: target confirmation (:class:`ConfirmState`);
    * ``reached_us``: the end of the last window stepped (µs since the Unix epoch), None before.

    The frames keep one row per target / local track ever seen (a few numbers each), since a
    target or track may resume after any silence."""

    chains: pl.DataFrame
    seed_first: pl.DataFrame
    nis: pl.DataFrame
    alt: AltCarry
    confirm: ConfirmState
    reached_us: int | None = None


def init_fuse_state() -> FuseState:
    """The state before the first window."""
    return FuseState(pl.DataFrame(schema={"run": pl.UInt32, "target_id": pl.UInt64, "radar_id": pl.UInt32}),
                     pl.DataFrame(schema={"run": pl.UInt32, "radar_id": pl.UInt32, "local_track_id": pl.UInt32,
                                          "first_var": pl.Float64}),
                     empty_nis_carry(), AltCarry(), ConfirmState.empty(), None)


def _weight_columns(method: str) -> list[str]:
    """The ``chains`` columns of a recursive method's carried weights (one per axis when per-axis)."""
    return [f"w_{method}_{c}" for c in range(3)] if REGISTRY[method].per_axis else [f"w_{method}"]


def _carried_weights(rows: pl.DataFrame, chains: pl.DataFrame, methods: list[str]) -> dict[str, F]:
    """Per recursive method, b(k−1) of each row from ``chains``: for the rows of each target's
    first group in ``rows`` when its radar set equals the carried one (else the recursion
    restarts at 1/N, as within a call); NaN elsewhere."""
    rec = [m for m in methods if REGISTRY[m].recursive]
    if not rec or chains.is_empty():
        return {}
    keys = rows.select(pl.col("run").cast(pl.UInt32), "epoch", pl.col("target_id").cast(pl.UInt64),
                       pl.col("radar_id").cast(pl.UInt32))
    first = (keys.group_by(GROUP, maintain_order=True).agg(pl.col("radar_id").alias("__set"))
             .group_by(CHAIN, maintain_order=True).first())
    sets = chains.group_by(CHAIN).agg(pl.col("radar_id").sort().alias("__old"))
    cont = first.join(sets, on=CHAIN, how="inner").filter(pl.col("__set") == pl.col("__old")).select(GROUP)
    cols = [c for m in rec for c in _weight_columns(m) if c in chains.columns]
    j = (keys.join(cont.with_columns(pl.lit(True).alias("__c")), on=GROUP, how="left", maintain_order="left")
         .join(chains.select(*CHAIN, "radar_id", *cols), on=[*CHAIN, "radar_id"], how="left", maintain_order="left"))
    ok = j["__c"].fill_null(False).to_numpy()
    col = lambda c: np.where(ok, j[c].cast(pl.Float64).fill_null(np.nan).to_numpy(), np.nan) if c in j.columns \
        else np.full(len(ok), np.nan)  # noqa: E731
    return {m: (np.stack([col(c) for c in _weight_columns(m)], axis=1) if REGISTRY[m].per_axis
                else col(_weight_columns(m)[0])) for m in rec}


def _new_chains(rows: pl.DataFrame, chains: pl.DataFrame, methods: list[str], ws: F, w3: dict[str, F]
                ) -> pl.DataFrame:
    """``chains`` with every target of ``rows`` replaced by its last group and that group's weights."""
    rec = [m for m in methods if REGISTRY[m].recursive]
    cols = []
    for i, m in enumerate(methods):
        if REGISTRY[m].per_axis:
            cols += [pl.Series(c, w3[m][:, a]) for a, c in enumerate(_weight_columns(m))]
        elif m in rec:
            cols.append(pl.Series(_weight_columns(m)[0], ws[i]))
    k = rows.select(pl.col("run").cast(pl.UInt32), "epoch", pl.col("target_id").cast(pl.UInt64),
                    pl.col("radar_id").cast(pl.UInt32)).with_columns(cols)
    last = k.filter(pl.col("epoch") == pl.col("epoch").max().over(CHAIN)).drop("epoch")
    return pl.concat([chains.join(last, on=CHAIN, how="anti"), last], how="diagonal_relaxed")


def _selected_alt_inputs(rows: pl.DataFrame) -> list[pl.Expr]:
    """``__sel`` (the row's selected altitude, null without) and ``__t`` (its report's age order:
    the report time, else −age_s, else none) for :func:`fuse_step`'s per-target latest."""
    def opt(c: str) -> pl.Expr:
        return pl.col(c).cast(pl.Float64).fill_nan(None) if c in rows.columns else pl.lit(None, pl.Float64)
    t = (pl.col("time").dt.epoch("us").cast(pl.Float64) if "time" in rows.columns
         else -pl.col("age_s").cast(pl.Float64) if "age_s" in rows.columns else pl.lit(0.0))
    # with the selected altitude, the BDS 5,0 track-angle rate (``__turn``) and the cleared level
    # from flight data (``__clr``) the same way
    return [opt(SELECTED_ALT_COLUMN).alias("__sel"), t.alias("__t"), opt(TURN_RATE_COLUMN).alias("__turn"),
            opt(CLEARED_ALT_COLUMN).alias("__clr")]


def fuse(rows: pl.DataFrame, radars: pl.DataFrame, methods: Sequence[str] = METHODS,
         cfg: FusionConfig = FusionConfig(), origin: geo.LocalFrame | None = None,
         plots: pl.DataFrame | None = None) -> pl.DataFrame:
    """Fuse the associated reports of every (run, epoch, target_id) with each method.

    ``rows`` holds :data:`INPUT_COLUMNS` (sorted here by (run, epoch, target_id, radar_id));
    null innovations count as NaN and a null ``fresh`` as False. ``radars`` (``radar_id``,
    ``sigma_range_m``) is read only by ``aposteriori_seed``, and with the sites (``lat_deg``,
    ``lon_deg``, ``alt_m``) and ``origin`` by ``aposteriori_coord`` / ``aposteriori_mv``. ``plots`` (:func:`measured_plots`)
    or the rows' own :data:`PLOT_COLUMNS` (with ``age_s``) give the tracker's measurement
    columns; without them those are null. Returns the ``fused`` table: the
    blocks of the methods in the order given, each sorted by (run, epoch, target_id).
    Raises ValueError for an unknown method, a missing column, or a radar reporting twice
    for one target at one epoch. The whole run as one window of :func:`fuse_step`."""
    return fuse_step(init_fuse_state(), rows, radars, methods, cfg, origin, plots)[0]


def fuse_step(state: FuseState, rows_window: pl.DataFrame, radars: pl.DataFrame, methods: Sequence[str] = METHODS,
              cfg: FusionConfig = FusionConfig(), origin: geo.LocalFrame | None = None,
              plots_window: pl.DataFrame | None = None, t0_us: int | None = None, t1_us: int | None = None
              ) -> tuple[pl.DataFrame, FuseState]:
    """:func:`fuse` of one time window, carrying every recursion in ``state`` (:class:`FuseState`).

    ``rows_window``: the fusion rows (aligned + target_id, :data:`INPUT_COLUMNS`, with ``time``,
    ``altitude_m``, ``mode_s``, ``age_s`` as the pipeline has them) with epoch in
    [``t0_us``, ``t1_us``) (µs since the Unix epoch; None = unbounded). ``plots_window``:
    :func:`measured_plots` of (at least) the reports of the window's fresh rows — every report
    whose first epoch lies in the window, i.e. reports with time in
    [t0_us − epoch period − max collection delay, t1_us); extra reports are ignored. No other
    history is needed. Stepping the windows of a run in order and concatenating the outputs
    gives :func:`fuse` of the whole run (same rows; values to round-off), provided ``methods``
    and ``cfg`` are the same in every window. The state passed in is not modified. Raises
    ValueError for rows outside the window (and as :func:`fuse`)."""
    methods = check_methods(methods)
    check_columns(rows_window)
    rows = rows_window
    reached = t1_us if t1_us is not None else state.reached_us
    if rows.height and (t0_us is not None or t1_us is not None):
        e = rows["epoch"].dt.epoch("us")
        if (t0_us is not None and e.min() < t0_us) or (t1_us is not None and e.max() >= t1_us):
            raise ValueError(f"fuse_step: rows_window has epochs outside [{t0_us}, {t1_us}) µs")
    schema = TABLES["fused"].required
    out_schema = {**schema, **TABLES["fused"].optional, **FUSED_EXTRA}
    if rows.height == 0 or not methods:
        return pl.DataFrame(schema=out_schema), replace(state, reached_us=reached)
    if not is_sorted_by(rows, [*GROUP, "radar_id"]):  # the pipeline passes sorted rows: skip the sort
        rows = rows.sort([*GROUP, "radar_id"], maintain_order=True)
    rows, inflate = apply_gate(rows, cfg)
    lay, a = layout(rows), input_arrays(rows)
    if inflate is not None:
        a["cov"] = a["cov"] * inflate[:, None, None]
    nis_carry = state.nis
    if any(REGISTRY[m].nis_inflation for m in methods):
        a["lam"], nis_carry = nis_inflation_step(rows, cfg.nis_window, state.nis)
    line_of_sight_inputs(methods, rows, radars, origin, a)
    seed_first = first_innovation_var(rows, state.seed_first)
    d_fixed = lambda: seed_fixed_variance(rows, radars, state.seed_first)  # noqa: E731
    b0 = _carried_weights(rows, state.chains, methods)
    xs, covs, ws, axis_w = run_methods(methods, RunInputs(a, lay, cfg, d_fixed), b0)
    alt, alt_carry = vertical_channel(rows, lay, xs, covs, origin, cfg.altitude, state.alt, plots_window)
    meas = measurements(rows, methods, a, lay, ws, plots_window, axis_w)
    tentative, confirm = confirm_targets_step(state.confirm, rows, cfg.min_plots, cfg.min_plots_primary)
    new_state = FuseState(_new_chains(rows, state.chains, methods, ws, axis_w), seed_first, nis_carry, alt_carry,
                          confirm, reached)
    mode_s = pl.col("mode_s").cast(pl.String) if "mode_s" in rows.columns else pl.lit(None, pl.String)
    head = rows.select(*GROUP, "radar_id", mode_s.alias("__s"), *_selected_alt_inputs(rows)).with_columns(
        pl.Series(f"__w{i}", ws[i]) for i in range(len(methods))
    ).group_by(GROUP, maintain_order=True).agg(
        pl.col("radar_id").alias("radar_ids"), pl.len().alias("n_sources"),
        # the target's identity: the address most of its reports carry (ties: the smallest)
        pl.col("__s").drop_nulls().mode().sort().first().alias("mode_s"),
        # its selected altitude (BDS 4,0): that of its newest report carrying one
        pl.col("__sel").sort_by("__t", "radar_id").drop_nulls().last().alias(SELECTED_ALT_COLUMN),
        # its track-angle rate (BDS 5,0): likewise the newest report's
        pl.col("__turn").sort_by("__t", "radar_id").drop_nulls().last().alias(TURN_RATE_COLUMN),
        # its cleared level from flight data (tertiary.stages.flight_data): likewise
        pl.col("__clr").sort_by("__t", "radar_id").drop_nulls().last().alias(CLEARED_ALT_COLUMN),
        *(pl.col(f"__w{i}") for i in range(len(methods))))
    head = head.with_columns(tentative["tentative"])
    keys = pl.concat([head.select(*GROUP, pl.lit(m).alias("method"), "radar_ids", "n_sources",
                                  pl.col(f"__w{i}").alias("weights"), "tentative", "mode_s", SELECTED_ALT_COLUMN,
                                  TURN_RATE_COLUMN, CLEARED_ALT_COLUMN)
                      for i, m in enumerate(methods)])
    # states and covariances of all methods in one go (they are stacked in method order)
    xs = xs.reshape(-1, 6)
    mz = meas["meas"].reshape(-1, 3)
    mv = meas["meas_v"].reshape(-1, 3)
    return keys.with_columns(
        *(pl.Series(c, xs[:, j]) for j, c in enumerate(STATE)),
        pl.Series("cov", covs.reshape(-1, 36)),
        *(pl.Series(c, alt[c].reshape(-1)) for c in ALT_COLUMNS),
        pl.Series("n_fresh", meas["n_fresh"].reshape(-1)),
        pl.Series("age_s", meas["age_s"].reshape(-1)).fill_nan(None),
        *(pl.Series(c, mz[:, j]).fill_nan(None) for j, c in enumerate(("meas_x_m", "meas_y_m", "meas_z_m"))),
        pl.Series("meas_cov", meas["meas_cov"].reshape(-1, 9), dtype=pl.Array(pl.Float64, 9)),
        *(pl.Series(c, mv[:, j]).fill_nan(None) for j, c in enumerate(("meas_vx_mps", "meas_vy_mps",
                                                                      "meas_vrate_mps"))),
    ).with_columns(pl.when(pl.col("meas_x_m").is_not_null()).then(pl.col("meas_cov")).alias("meas_cov")
                   ).select(list(out_schema)).cast(out_schema), new_state
