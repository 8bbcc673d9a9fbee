"""The report's safety figures: STCA trade-off curves (covariance against fixed thresholds),
conflict probability against traffic and capacity against accuracy (seed figs. 5.2, 5.3), drawn
with :mod:`safety.alerts` and :mod:`safety.capacity`."""

from __future__ import annotations

import numpy as np
import plotly.graph_objects as go
import polars as pl
from plotly.subplots import make_subplots

from safety.alerts import compare_at_equal_nuisance
from safety.capacity import CAPACITY_V_ZO_M3, V_BC_M3, V_ZO_M3, capacity_curve, nmax_seed, nmax_sound, ppob_curves
from tertiary.report.common import COLORS, Ctx, Section, f32, style, visible

STCA_WARNING_S = 30.0   # the warning requirement the curves are drawn for (≥ 30 s)


def sec_stca(ctx: Ctx) -> Section:
    """Trade-off curves: losses alerted with ≥ 30 s warning against nuisance + false alerts per
    hour, covariance thresholds (by confidence) beside fixed thresholds, per look-ahead."""
    sec = Section("stca", "STCA performance curves")
    curve = ctx.q("stca_tradeoff", warning_s=STCA_WARNING_S)
    if curve.height == 0:
        sec.note = ("Not computed in this run: the curves need truth and a safety stage with look-aheads "
                    "(PipelineConfig.stca_lookaheads_s).")
        return sec
    looks = sorted(curve["t_thr_s"].unique().to_list())
    methods = curve["method"].unique(maintain_order=True).to_list()
    main = ctx.best.best_of(methods) or methods[0]
    fig = make_subplots(rows=1, cols=len(looks), shared_yaxes=True,
                        subplot_titles=[f"look-ahead T = {t:g} s" for t in looks])
    for c, t in enumerate(looks, start=1):
        for i, m in enumerate(methods):
            color = "black" if m == main else COLORS[i % len(COLORS)]
            for mode, dash in (("covariance", "solid"), ("fixed", "dash")):
                part = curve.filter((pl.col("method") == m) & (pl.col("t_thr_s") == t)
                                    & (pl.col("threshold_mode") == mode)).sort("nuisance_false_per_hour")
                label = f"{m} — {mode}" + (" (best picture)" if m == main else "")
                fig.add_trace(go.Scatter(
                    x=f32(part["nuisance_false_per_hour"]), y=f32(part["alerted_fraction"] * 100.0),
                    mode="lines+markers", name=label, legendgroup=label, showlegend=c == 1,
                    visible=visible(m, {main}), line=dict(color=color, dash=dash, width=1.4),
                    text=[f"{'confidence' if mode == 'covariance' else 'fixed term'} {v:g}" for v in part["parameter"]],
                    hovertemplate="%{text}: %{x:.0f} /h, %{y:.0f} %<extra></extra>"), row=1, col=c)
    style(fig, f"Losses of separation alerted with ≥ {STCA_WARNING_S:g} s warning against nuisance + false "
                 "alerts", "", "", height=480)
    for c in range(1, len(looks) + 1):
        fig.update_xaxes(title_text="nuisance + false alerts per hour (1/h)", row=1, col=c)
    fig.update_yaxes(title_text="losses alerted in time (%)", row=1, col=1)
    par = {m: curve.filter(pl.col("threshold_mode") == m)["parameter"] for m in ("covariance", "fixed")}
    span = {m: f"{p.min():g} … {p.max():g}" if p.len() else "none" for m, p in par.items()}
    sec.figures.append((fig, "Each point is one setting of the whole safety stage on the picture (sql/stca_tradeoff.sql,"
                             f" metrics stage safety_tradeoff): solid — thresholds from the track covariance at "
                             f"confidence {span['covariance']}; dashed — fixed thresholds with an estimation term of "
                             f"{span['fixed']} m (vertical scaled alike). Up and to the left is better. Drawn by "
                             "default: the best picture; the others are in the legend."))
    t_cmp = 105.0 if 105.0 in looks else looks[-1]
    cmp = compare_at_equal_nuisance(curve.with_columns(pl.col("warning_s").cast(pl.Float64)),
                                    warning_s=STCA_WARNING_S, t_thr_s=t_cmp)
    wide = cmp.pivot(on="threshold_mode", index=["method", "nuisance_false_per_hour"], values="alerted_fraction")
    # the other reading of the same curves: the lowest alert rate at which a family still alerts
    # ≥ 95 % of the losses in time (a family that never does is null)
    need = (curve.filter((pl.col("t_thr_s") == t_cmp) & (pl.col("alerted_fraction") >= 0.95))
            .group_by("method", "threshold_mode").agg(pl.col("nuisance_false_per_hour").min())
            .pivot(on="threshold_mode", index="method", values="nuisance_false_per_hour"))
    wide = wide.with_columns(*(pl.lit(None, pl.Float64).alias(c) for c in ("covariance", "fixed") if c not in wide.columns))
    need = need.with_columns(*(pl.lit(None, pl.Float64).alias(c) for c in ("covariance", "fixed") if c not in need.columns))
    table = wide.join(need, on="method", how="left", suffix="_rate").select(
        pl.col("method").alias("picture"),
        pl.col("nuisance_false_per_hour").alias("rate compared (1/h): covariance at 0.95"),
        pl.col("covariance").alias("alerted in time at that rate, covariance (fraction)"),
        pl.col("fixed").alias("alerted in time at that rate, fixed (fraction)"),
        pl.col("covariance_rate").alias("lowest rate with ≥ 95 % alerted in time, covariance (1/h)"),
        pl.col("fixed_rate").alias("lowest rate with ≥ 95 % alerted in time, fixed (1/h)"))
    sec.tables.append((f"Covariance against fixed thresholds (T = {t_cmp:g} s, warning ≥ {STCA_WARNING_S:g} s): "
                       "alerted fraction at equal nuisance + false rate (empty where a family does not reach that "
                       "rate: no extrapolation), and the alert rate each family needs to alert 95 % in time",
                       table))
    return sec


def sec_ppob(ctx: Ctx) -> Section:
    sec = Section("ppob", "Conflict probability against traffic (seed fig. 5.2)")
    sigmas = (50.0, 100.0, 200.0)
    cur = ppob_curves(n=tuple(range(2, 201)), sigmas=sigmas)
    fig = go.Figure()
    dashes = {"seed": "solid", "sound_one": "dash", "sound_any": "dot"}
    for i, s in enumerate(sigmas):
        for model in ("seed", "sound_one", "sound_any"):
            part = cur.filter((pl.col("sigma_m") == s) & (pl.col("model") == model))
            p = part.select(pl.when(pl.col("valid") & (pl.col("p") > 0)).then(pl.col("p"))).to_series()
            fig.add_trace(go.Scatter(x=f32(part["n"]), y=f32(p), mode="lines", name=f"σ = {s:g} m, {model}",
                                     line=dict(color=COLORS[i], dash=dashes[model], width=1.5)))
    style(fig, "P_pob against the number of aircraft n", "number of aircraft n (aircraft)",
            "probability of a conflict P_pob (dimensionless)")
    fig.update_yaxes(type="log", exponentformat="power")
    sec.figures.append((fig, f"safety.capacity.ppob_curves with V_zo = {V_ZO_M3:.0e} m³ and V_BC = {V_BC_M3:g} m³: "
                             "seed = (5.21) as printed, drawn only where valid ((n − 1)V_ob < V_zo/2; it has a "
                             "pole beyond); sound_one / sound_any = the sounder model (conflict radius 12σ), one "
                             "given aircraft / any pair."))
    return sec


def sec_capacity(ctx: Ctx) -> Section:
    sec = Section("capacity", "Capacity against accuracy (seed fig. 5.3)")
    cap = ctx.q("capacity_by_method")
    p_run = float(cap["p_star"].drop_nulls()[0]) if cap.height and cap["p_star"].drop_nulls().len() else 1e-3
    settings = [(p_run, CAPACITY_V_ZO_M3), (1e-6, V_ZO_M3)]
    sigmas = np.arange(10.0, 201.0, 2.0)
    fig = go.Figure()
    measured = cap.filter(pl.col("sigma_m").is_not_null() & (pl.col("stage") == "fusion")) if cap.height else cap
    for i, (p_star, v_zo) in enumerate(settings):
        curve = capacity_curve(sigmas, p_star=p_star, v_zo=v_zo)
        for model, dash in (("seed", "solid"), ("sound", "dash")):
            part = curve.filter(pl.col("model") == model)
            fig.add_trace(go.Scatter(x=f32(part["sigma_m"]), y=f32(part["n_max"]), mode="lines",
                                     name=f"{model}: P* = {p_star:g}, V_zo = {v_zo:.0e} m³",
                                     line=dict(color=COLORS[i], dash=dash, width=1.6)))
            if measured.height:
                s = measured["sigma_m"].to_numpy()
                if i == 0:   # the run's own capacity rows (metrics table)
                    n = measured["n_max_seed" if model == "seed" else "n_max_sound"].to_numpy()
                else:
                    n = nmax_seed(s, p_star, v_zo=v_zo) if model == "seed" else nmax_sound(s, p_star, v_zo=v_zo)
                fig.add_trace(go.Scatter(x=f32(s), y=f32(n), mode="markers",
                                         name=f"measured ({model}, P* = {p_star:g})",
                                         marker=dict(color=COLORS[i], symbol="circle" if model == "seed" else "diamond",
                                                     size=9, line=dict(color="black", width=0.5)),
                                         text=measured["method"].to_list(),
                                         hovertemplate="%{text}: σ = %{x:.1f} m, n_max = %{y}<extra></extra>"))
    style(fig, "Largest number of aircraft n_max against the RMS error σ", "RMS error σ (m)",
            "largest number of aircraft n_max (aircraft)")
    fig.update_xaxes(type="log")
    fig.update_yaxes(type="log")
    sec.figures.append((fig, f"safety.capacity.capacity_curve for the run's P* = {p_run:g} with V_zo = "
                             f"{CAPACITY_V_ZO_M3:.0e} m³ (a 100 km × 100 km × 10 km zone, as in the metrics table; "
                             "n_max ∝ σ⁻³) and for the printed P* = 1e-6, V_zo = 1e12 m³, which admits a single "
                             "aircraft at every realistic σ, as the digest notes. The seed model (5.18)–(5.21) is "
                             "drawn as printed and is illustrative (odds-shaped); the sounder model beside it. "
                             "Markers: each fusion method's measured RMSE σ (rmse_range_m, segment all) and its "
                             "n_max; the table adds P(n) with a fixed number of aircraft, which varies continuously "
                             "with σ (sql/capacity_by_method.sql)."))
    sec.tables.append(("Capacity by method (sql/capacity_by_method.sql)", cap))
    return sec

