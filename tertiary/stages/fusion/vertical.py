"""The vertical channel of every fused target (:mod:`tertiary.stages.tracking.altitude`):
``alt_m``, ``alt_rate_mps``, ``alt_var_m2``, ``alt_rate_var_m2ps2``, ``alt_cov_m2ps``.

When the rows carry the reports' barometric ``altitude_m`` (with ``time``), a two-state (h, ḣ)
filter runs per (run, radar, local track) over its reports' replies (quantum 25 ft with
``mode_s``, 100 ft without, R = q²/12, garble gate; each report's downlinked vertical rate,
from the measured plots, restarts it at a level-off or a climb's onset and updates its rate),
is extrapolated from the report time to the
epoch ((A1)–(A2)) and, among the target's sources with an estimate that the source with the
latest reply does not contradict (:func:`tertiary.stages.tracking.altitude.superseded`: an older
source still extrapolating a climb after a newer reply shows the level-off), the one with the
smallest height variance is kept (all radars decode the same reply, so their errors are not
independent: :func:`tertiary.stages.tracking.altitude.combine_min_variance`). This channel does
not depend on the method. A target without any Mode C source falls back to the geodetic height of the
method's fused state, its variance from the covariance along the local vertical
(:func:`tertiary.stages.tracking.altitude.geodetic_channel`; ``origin=None``: spherical Earth,
≤ 9 m at 150 km) — never the ENU z.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl

from tertiary.core import geo
from tertiary.stages.fusion.base import TRACK, B, F, Layout, track_keys
from tertiary.stages.tracking.altitude import (ALT_COLUMNS, QUANTUM_MODE_C_M, QUANTUM_MODE_S_M, AltitudeConfig, AltState,
                                               FilterCarry, combine_min_variance, filter_tracks_carry, geodetic_channel,
                                               predict_combined, quantisation_variance, superseded)

__all__ = ["AltCarry", "vertical_channel"]


@dataclass(frozen=True)
class AltCarry:
    """Carried Mode C filters of the vertical channel: per (run, radar, local track) the
    :class:`~tertiary.stages.tracking.altitude.FilterCarry` columns after its last report (``report_id``), whose
    output serves the track's rows that still hold that report in a later window; ``ref_us``:
    the time base (µs) of the filters' ``t_last`` — the first report time ever filtered, so the
    seconds are the same floats as in one whole-run call."""

    tracks: pl.DataFrame | None = None
    ref_us: int | None = None


def _alt_lookup(carry: pl.DataFrame) -> pl.DataFrame:
    """(run, report_id) → the :data:`ALT_COLUMNS` and ``__has`` of each carried track's last report."""
    names = dict(zip(("h", "r", "phh", "phr", "prr"),
                     ("alt_m", "alt_rate_mps", "alt_var_m2", "alt_cov_m2ps", "alt_rate_var_m2ps2")))
    mu = sorted(c for c in carry.columns if c.startswith("af_mu"))
    return carry.select(pl.col("run").cast(pl.UInt32), pl.col("report_id").cast(pl.UInt64),
                        *(pl.col(f"af_post_{f}").alias(c) for f, c in names.items()),
                        pl.col("af_has").alias("__has"), pl.col(mu[-1]).cast(pl.Float64).alias("__mu"))


def _mode_c_per_row(rows: pl.DataFrame, cfg: AltitudeConfig, carry: AltCarry = AltCarry(),
                    plots: pl.DataFrame | None = None) -> tuple[AltState, B, AltCarry]:
    """Each row's Mode C estimate (h, ḣ, P) at its epoch and whether it has one: the filter of
    its (run, radar, local track) after the row's report, extrapolated by epoch − time. The
    filters continue from ``carry`` (earlier windows) and the new carry is returned. Each
    report's downlinked vertical rate is the ``plots``' ``plot_vrate_mps``
    (:func:`~tertiary.stages.fusion.measurement.measured_plots`, joined on run and report_id)."""
    n = rows.height
    none = AltState.full(n), np.zeros(n, bool), carry
    if "altitude_m" not in rows.columns or "time" not in rows.columns:
        return none
    fresh = pl.col("fresh").fill_null(False)
    has_s = "mode_s" in rows.columns
    # the Mode S address as an integer identity: a radar track whose address changes has swapped
    # aircraft, and its altitude filter restarts (tertiary.stages.tracking.altitude.filter_tracks, ident)
    ident = (pl.col("mode_s").cast(pl.String).str.to_integer(base=16, strict=False).fill_null(-1)
             if has_s else pl.lit(-1, pl.Int64))
    rep = track_keys(rows.filter(fresh).select(*TRACK, pl.col("report_id").cast(pl.UInt64), "time", "altitude_m",
                                                (pl.col("mode_s").is_not_null() if has_s else pl.lit(True)).alias("__s"),
                                                ident.cast(pl.Int64).alias("__ident"))
                      .unique(subset=["run", "report_id"], keep="first", maintain_order=True)
                      .sort([*TRACK, "time"]))
    if plots is not None and "plot_vrate_mps" in plots.columns and rep.height:
        reg = plots.select(pl.col("run").cast(rep.schema["run"]), pl.col("report_id").cast(pl.UInt64),
                           pl.col("plot_vrate_mps").cast(pl.Float64).alias("__vrate")).unique(["run", "report_id"])
        rep = rep.join(reg, on=["run", "report_id"], how="left", maintain_order="left")
    else:
        rep = rep.with_columns(pl.lit(None, pl.Float64).alias("__vrate"))
    old = carry.tracks
    lookups = [] if old is None else [_alt_lookup(old)]
    ref_us, tracks = carry.ref_us, old
    if rep.height:
        keys = rep.select(TRACK).to_numpy()
        new = np.r_[True, np.any(keys[1:] != keys[:-1], axis=1)]
        starts = np.flatnonzero(new)
        lengths = np.diff(np.append(starts, len(keys)))
        t_us = rep["time"].dt.epoch("us").to_numpy()
        ref_us = int(t_us.min()) if ref_us is None else ref_us
        t = (t_us - ref_us) * 1e-6
        z = rep["altitude_m"].cast(pl.Float64).fill_null(np.nan).to_numpy()
        var = quantisation_variance(np.where(rep["__s"].to_numpy(), QUANTUM_MODE_S_M, QUANTUM_MODE_C_M))
        init = _alt_init(rep[starts].select(TRACK), old, cfg)
        post, has, _, final, mu = filter_tracks_carry(t, z, var, starts, lengths, cfg,
                                                      ident=rep["__ident"].to_numpy(), init=init, with_mu=True,
                                                      vrate=rep["__vrate"].fill_null(np.nan).to_numpy())
        cols = post.columns()
        lookups.insert(0, rep.select("run", "report_id").with_columns(
            *(pl.Series(c, cols[c]) for c in ALT_COLUMNS), pl.Series("__has", has), pl.Series("__mu", mu)))
        now = rep[starts + lengths - 1].select(*TRACK, "report_id").with_columns(
            pl.Series(c, v) for c, v in final.columns().items())
        tracks = now if old is None else pl.concat([old.join(now, on=TRACK, how="anti"), now])
    if not lookups:
        return AltState.full(n), np.zeros(n, bool), carry
    table = pl.concat(lookups, how="diagonal_relaxed").unique(subset=["run", "report_id"], keep="first",
                                                              maintain_order=True)
    j = rows.select(pl.col("run").cast(pl.UInt32), pl.col("report_id").cast(pl.UInt64), "epoch", "time").join(
        table, on=["run", "report_id"], how="left", maintain_order="left")
    at = AltState(*(j[c].fill_null(np.nan).to_numpy() for c in
                    ("alt_m", "alt_rate_mps", "alt_var_m2", "alt_cov_m2ps", "alt_rate_var_m2ps2")))
    age = (j["epoch"].dt.epoch("us").to_numpy() - j["time"].dt.epoch("us").to_numpy()) * 1e-6
    # extrapolated as the IMM predicts its combined estimate (the mode-weighted q), not with the
    # manoeuvre model's q: a level aircraft's rate stays known to cm/s between its replies
    mu = j["__mu"].cast(pl.Float64).fill_null(np.nan).to_numpy()
    return (predict_combined(at, np.maximum(age, 0.0), mu, cfg), j["__has"].fill_null(False).to_numpy(),
            AltCarry(tracks, ref_us))


def _alt_init(keys: pl.DataFrame, old: pl.DataFrame | None, cfg: AltitudeConfig) -> FilterCarry:
    """The filters' starting state for the tracks ``keys`` (in order): carried where ``old`` has
    the track, else a filter that has seen nothing."""
    k = keys.height
    if old is None or old.is_empty():
        return FilterCarry.fresh(k, cfg)
    j = keys.join(old, on=TRACK, how="left", maintain_order="left")
    default = FilterCarry.fresh(1, cfg).columns()
    return FilterCarry.from_columns({c: j[c].fill_null(v[0]).to_numpy() for c, v in default.items()}, cfg)


def vertical_channel(rows: pl.DataFrame, lay: Layout, xs: F, covs: F, origin: geo.LocalFrame | None,
                     cfg: AltitudeConfig, carry: AltCarry = AltCarry(), plots: pl.DataFrame | None = None
                     ) -> tuple[dict[str, F], AltCarry]:
    """The :data:`~tertiary.stages.tracking.altitude.ALT_COLUMNS` of every (method, group), shape (M, G) each,
    stacked in method order: Mode C where a source has it, else the geodetic height of the
    method's fused state (see the module docstring); and the Mode C filters' new carry.
    ``plots``: the reports' measured plots, for their downlinked vertical rates."""
    n_groups = len(lay.starts)
    per_row, has, carry = _mode_c_per_row(rows, cfg, carry, plots)
    if has.any():
        has = has & ~superseded(per_row, has, lay.group, rows["time"].dt.epoch("us").to_numpy(), cfg)
    mode_c, got = combine_min_variance(per_row, has, lay.group, n_groups)
    mc = mode_c.columns()
    out = {c: np.repeat(mc[c][None], len(xs), axis=0) for c in ALT_COLUMNS}
    rest = np.flatnonzero(~got)                      # the fallback only where no Mode C
    for i in range(len(xs)):
        fb = geodetic_channel(xs[i, rest], covs[i, rest], origin).columns()
        for c in ALT_COLUMNS:
            out[c][i, rest] = fb[c]
    return out, carry
