"""The report's figures of the air picture: scenario map, radar kinematics and residuals,
accuracy over time and by picture, a-posteriori weights, quality tables, conflicts and the
evaluation stage's picture comparison (seed figs. 4.4–4.11)."""

from __future__ import annotations

import math

import numpy as np
import plotly.graph_objects as go
import polars as pl
from plotly.subplots import make_subplots

from tertiary.core.geo import LocalFrame
from tertiary.report.common import (CENTRALIZED, COLORS, CONFLICT_ROWS, DASHES, KINEMATICS_AIRCRAFT, MIN_SAMPLE_FRAC,
                                    Ctx, Section, f32, radar_names, step_changes, style, thin, visible)

def sec_map(ctx: Ctx) -> Section:
    sec = Section("map", "Scenario map (seed fig. 4.4)")
    n_aircraft = ctx.store.sql("SELECT count(DISTINCT truth_id) AS n FROM truth").item() if "truth" in ctx.tables else 0
    duration = float(ctx.scenario.get("duration_s") or 0.0)
    # about 60 000 map points in all: the thinning step grows with traffic and duration
    step = max(1, math.ceil(n_aircraft * max(duration, 1.0) / 60_000)) if n_aircraft else 10
    traj = ctx.q("trajectories", step_s=step)
    sites = ctx.q("radar_sites")
    fig = go.Figure()
    if traj.height:
        # one trace, aircraft separated by NaN gaps
        gap = traj.select("truth_id").with_columns(pl.col("truth_id").shift(-1).ne(pl.col("truth_id")).fill_null(False)
                                                   .alias("end"))
        xs, ys = traj["x_m"].to_numpy() / 1000.0, traj["y_m"].to_numpy() / 1000.0
        ends = np.flatnonzero(gap["end"].to_numpy()) + 1
        x = np.insert(xs, ends, np.nan)
        y = np.insert(ys, ends, np.nan)
        fig.add_trace(go.Scatter(x=f32(x), y=f32(y), mode="lines", line=dict(width=1, color="#7f9fbf"),
                                 name=f"trajectories ({traj['truth_id'].n_unique()} aircraft)", hoverinfo="skip"))
        starts = traj.group_by("truth_id", maintain_order=True).first()
        fig.add_trace(go.Scatter(x=f32(starts["x_m"] / 1000.0), y=f32(starts["y_m"] / 1000.0), mode="markers",
                                 marker=dict(size=4, color="#1f4e79"), name="start of track",
                                 text=[f"aircraft {i}" for i in starts["truth_id"]], hoverinfo="text"))
    enu = _site_enu(ctx, sites)
    if enu is not None:
        fig.add_trace(go.Scatter(x=f32(enu[0] / 1000.0), y=f32(enu[1] / 1000.0), mode="markers+text",
                                 marker=dict(symbol="triangle-up", size=14, color="#d62728"),
                                 text=sites["name"].to_list(), textposition="top center", name="radar sites"))
    else:
        sec.note = "Radar sites not drawn: the run record has no processing-centre origin."
    style(fig, "Truth trajectories and radar sites (system frame)", "east x (km)", "north y (km)", height=620)
    fig.update_yaxes(scaleanchor="x", scaleratio=1)
    sec.figures.append((fig, f"Truth positions thinned to one point per aircraft every {step} s "
                             "(sql/trajectories.sql); radar sites from sql/radar_sites.sql converted to the "
                             "system ENU frame."))
    sec.tables.append(("Radar sites", sites))
    return sec


def _site_enu(ctx: Ctx, sites: pl.DataFrame) -> tuple[np.ndarray, np.ndarray] | None:
    origin = ctx.scenario.get("origin")
    if not origin or len(origin) < 2 or sites.height == 0:
        return None
    frame = LocalFrame(float(origin[0]), float(origin[1]), float(origin[2]) if len(origin) > 2 else 0.0)
    e, n, _u = frame.from_geodetic(sites["lat_deg"].to_numpy(), sites["lon_deg"].to_numpy(), sites["alt_m"].to_numpy())
    return np.asarray(e), np.asarray(n)


def _small_multiples(n: int, titles: list[str], cols: int = 2):
    """A grid of ``n`` panels (``cols`` wide) sharing the x axis, one title per panel."""
    cols = max(1, min(cols, n))
    rows = max(1, math.ceil(n / cols))
    fig = make_subplots(rows=rows, cols=cols, shared_xaxes=True, subplot_titles=titles,
                        vertical_spacing=min(0.12, 0.35 / rows), horizontal_spacing=0.08)
    return fig, rows, cols


def sec_kinematics(ctx: Ctx) -> Section:
    sec = Section("kinematics", "Range, range rate and acceleration per radar (seed figs. 4.5–4.7)")
    kin = ctx.q("radar_kinematics", max_aircraft=KINEMATICS_AIRCRAFT)
    names = radar_names(kin) if kin.height else {}
    radars = sorted(names)
    aircraft = sorted(kin["truth_id"].unique().to_list()) if kin.height else []
    specs = [("est_range_m", "Range D(k) (fig. 4.5)", "range D (km)", 1e-3),
             ("est_range_rate_mps", "Range rate V(k) (fig. 4.6)", "range rate V (m/s)", 1.0),
             ("accel_mps2", "Line-of-sight acceleration a(k) = ΔV/Δt (fig. 4.7)", "acceleration a (m/s²)", 1.0)]
    titles = [f"radar {names[r]}" for r in radars] or ["no radar reports"]
    for col, title, ytitle, scale in specs:
        fig, nrows, ncols = _small_multiples(len(titles), titles)
        for i, rid in enumerate(radars):
            row, cc = i // ncols + 1, i % ncols + 1
            for j, ac in enumerate(aircraft):
                part = kin.filter((pl.col("radar_id") == rid) & (pl.col("truth_id") == ac))
                if part.height == 0:
                    continue
                # NaN gaps between local tracks of the same aircraft
                part = thin(part.sort("local_track_id", "time"))
                brk = np.flatnonzero(np.diff(part["local_track_id"].to_numpy()) != 0) + 1
                x = np.insert(part["t_s"].to_numpy(), brk, np.nan)
                y = np.insert(part[col].cast(pl.Float64).fill_null(float("nan")).to_numpy() * scale, brk, np.nan)
                fig.add_trace(go.Scatter(x=f32(x), y=f32(y), mode="lines", name=f"aircraft {ac}",
                                         legendgroup=f"ac{ac}", showlegend=i == 0,
                                         line=dict(color=COLORS[j % len(COLORS)], width=1.3)), row=row, col=cc)
        style(fig, title + ", one panel per radar", "", "", height=max(300, 250 * nrows + 80))
        fig.update_xaxes(title_text="time t (s)", row=nrows)
        fig.update_yaxes(title_text=ytitle, col=1)
        if col == "accel_mps2" and kin.height:
            # the first seconds of a track (filter transient) would swamp the scale
            lo, hi = kin.select(pl.col(col).quantile(0.005).alias("lo"), pl.col(col).quantile(0.995).alias("hi")).row(0)
            if lo is not None and hi is not None and hi > lo:
                pad = 0.25 * (hi - lo)
                fig.update_yaxes(range=[lo - pad, hi + pad])
        sec.figures.append((fig, ""))
    sec.text = (f"Each radar's own track estimates (est_range_m, est_range_rate_mps) for the first Monte-Carlo "
                f"run and the {len(aircraft)} aircraft seen by the most radars (sql/radar_kinematics.sql, "
                f"{kin.height:,} reports), one panel per radar with the same aircraft colours; the acceleration is "
                "the difference of consecutive range-rate estimates over their time step (axis clipped to the "
                "0.5–99.5 % quantiles, so that track-start transients do not swamp it).")
    return sec


def _bin_s(ctx: Ctx) -> float:
    duration = float(ctx.scenario.get("duration_s") or 0.0)
    sites = ctx.q("radar_sites")
    scan = sites["scan_period_s"].max() if sites.height else 1.0
    return float(max(1.0, round(max(scan or 1.0, duration / 300.0))))


def sec_residuals(ctx: Ctx) -> Section:
    sec = Section("residuals", "Range residuals per radar (seed fig. 4.9)")
    bin_s = _bin_s(ctx)
    res = ctx.q("radar_residuals_over_time", bin_s=bin_s)
    fig = go.Figure()
    for i, (rid, name) in enumerate(sorted(radar_names(res).items()) if res.height else []):
        part = thin(res.filter(pl.col("radar_id") == rid))
        color = COLORS[i % len(COLORS)]
        fig.add_trace(go.Scatter(x=f32(part["t_s"]), y=f32(part["mean_abs_res_m"]), mode="lines",
                                 name=f"{name} mean |ΔD|", line=dict(color=color, width=1.5)))
        fig.add_trace(go.Scatter(x=f32(part["t_s"]), y=f32(part["pred_sd_m"]), mode="lines",
                                 name=f"{name} predicted SD", line=dict(color=color, width=1, dash="dot"),
                                 visible="legendonly"))
    style(fig, f"Mean |range innovation| per radar, {bin_s:g} s bins", "time t (s)", "|range innovation ΔD| (m)")
    sec.figures.append((fig, "Each radar's own range innovation |res_range_m| averaged over aircraft and runs in "
                             f"{bin_s:g} s bins (sql/radar_residuals_over_time.sql); dotted: mean predicted "
                             "innovation SD (click the legend)."))
    sec.tables.append(("Residual statistics per radar (sql/radar_residuals.sql)", ctx.q("radar_residuals")))
    return sec


def _edge_rule(frac: float = MIN_SAMPLE_FRAC) -> str:
    return (f"Edge-of-coverage rule: an epoch is drawn only if its number of scored samples N_k is at least "
            f"{frac:.0%} of the median N_k of its curve (min_sample_frac = {frac:g} in the SQL report); thinner "
            "epochs, at the start and end of coverage, rest on a handful of aircraft and are not drawn")


def sec_rmse_time(ctx: Ctx) -> Section:
    sec = Section("rmse_time", "Real RMS horizontal and vertical error over time (seed fig. 4.10)")
    b = ctx.best
    radar = ctx.q("radar_accuracy_over_time", min_sample_frac=MIN_SAMPLE_FRAC)
    n_radar_all = ctx.q("radar_accuracy_over_time").height
    panels = (("rmse_horizontal_m", "horizontal"), ("rmse_height_m", "vertical (height)"))
    tert = {m: ctx.q("accuracy_over_time", metric=m, min_sample_frac=MIN_SAMPLE_FRAC) for m, _ in panels}
    n_tert_all = ctx.q("accuracy_over_time", metric=panels[0][0]).height
    fig = make_subplots(rows=2, cols=1, shared_xaxes=True, vertical_spacing=0.1,
                        subplot_titles=[f"{label.capitalize()} RMS error" for _m, label in panels])
    shown = {b.radar, b.fused, CENTRALIZED} - {None}
    for row, (metric, _label) in enumerate(panels, start=1):
        for i, (rid, name) in enumerate(sorted(radar_names(radar).items()) if radar.height else []):
            part = thin(radar.filter(pl.col("radar_id") == rid))
            fig.add_trace(go.Scatter(x=f32(part["t_s"]), y=f32(part[metric]), mode="lines",
                                     name=f"radar {name}" + (" (best radar)" if name == b.radar else ""),
                                     legendgroup=f"radar {name}", showlegend=row == 1,
                                     visible=visible(name, shown),
                                     line=dict(color=COLORS[i % len(COLORS)], width=1.2, dash="dot")), row=row, col=1)
        frame = tert[metric]
        methods = frame["method"].unique(maintain_order=True).to_list() if frame.height else []
        for k, m in enumerate(methods):
            part = thin(frame.filter(pl.col("method") == m))
            main = m == b.fused
            label = m + (" (best picture)" if m == b.picture else " (best fused picture)" if main else
                         " (centralised reference)" if m == CENTRALIZED else "")
            fig.add_trace(go.Scatter(x=f32(part["t_s"]), y=f32(part["value"]), mode="lines", name=label,
                                     legendgroup=m, showlegend=row == 1, visible=visible(m, shown),
                                     line=dict(color="black" if main else "#6a3d9a" if m == CENTRALIZED else None,
                                               width=2.2 if main else 1.4,
                                               dash="solid" if main or m == CENTRALIZED else DASHES[k % len(DASHES)])),
                          row=row, col=1)
    style(fig, "σ(k) of each picture and of each radar's own tracks", "", "", height=720)
    fig.update_yaxes(title_text="horizontal RMSE (m)", row=1, col=1)
    fig.update_yaxes(title_text="vertical RMSE (m)", row=2, col=1)
    fig.update_xaxes(title_text="time t (s)", row=2, col=1)
    left_out = f"{n_tert_all - tert[panels[0][0]].height:,} of {n_tert_all:,} picture epochs and " \
               f"{n_radar_all - radar.height:,} of {n_radar_all:,} radar epochs left out"
    best_note = "" if b.picture == b.fused or b.picture is None else (
        f" The best picture overall, {b.picture}, is a tracker picture without per-epoch accuracy; its fusion "
        f"input's best, {b.fused}, is drawn instead.")
    sec.figures.append((fig, "Drawn by default: the best fused picture (black), the centralised reference (purple) "
                             "and the best radar (dotted); every other picture and radar is in the legend (click to "
                             "show). Per-radar curves: each radar's own track estimates aligned to the common epochs "
                             "(sql/radar_accuracy_over_time.sql); picture curves: accuracy_by_epoch "
                             "(sql/accuracy_over_time.sql); N − 1 denominator over the aircraft and runs at each "
                             f"epoch, first 20 s of each track left out. {_edge_rule()} ({left_out})."
                        + best_note))
    return sec


def sec_post_prior(ctx: Ctx) -> Section:
    sec = Section("post_prior", "A-posteriori versus a-priori weights (seed fig. 4.11)")
    pp = ctx.q("aposteriori_vs_apriori", min_sample_frac=MIN_SAMPLE_FRAC)
    fig = make_subplots(rows=2, cols=1, shared_xaxes=True, vertical_spacing=0.08, row_heights=[0.6, 0.4])
    colors = {"aposteriori": "#d62728", "aposteriori_seed": "#ff7f0e", "apriori": "#1f77b4", "arithmetic": "#2ca02c"}
    drawn = set()
    for (post, prior), part in (pp.group_by("posterior", "prior", maintain_order=True) if pp.height else []):
        part = thin(part.sort("epoch"))
        for m, col in ((post, "sigma_post"), (prior, "sigma_prior")):
            if m in drawn:
                continue
            drawn.add(m)
            fig.add_trace(go.Scatter(x=f32(part["t_s"]), y=f32(part[col]), mode="lines", name=f"σ {m}",
                                     line=dict(color=colors.get(m), width=1.4)), row=1, col=1)
        fig.add_trace(go.Scatter(x=f32(part["t_s"]), y=f32(part["gain"] * 100.0), mode="lines",
                                 name=f"gain {post} vs {prior}",
                                 line=dict(color=colors.get(post), dash="solid" if prior == "apriori" else "dot",
                                           width=1.1)), row=2, col=1)
    style(fig, "Tertiary RMS range error with a-posteriori and a-priori weights, and the gain", "", "", height=620)
    fig.update_yaxes(title_text="σ range (m)", row=1, col=1)
    fig.update_yaxes(title_text="1 − σ_post/σ_prior (%)", row=2, col=1)
    fig.update_xaxes(title_text="time t (s)", row=2, col=1)
    sec.figures.append((fig, "From accuracy_by_epoch (sql/aposteriori_vs_apriori.sql); gain > 0 where the "
                             "a-posteriori weights beat the reference (solid: a-priori weights, dotted: "
                             f"arithmetic 0.5/0.5). {_edge_rule()}."))
    sec.tables.append((f"Gain summary, same edge rule (sql/aposteriori_gain.sql, min_sample_frac = {MIN_SAMPLE_FRAC:g})",
                       ctx.q("aposteriori_gain", min_sample_frac=MIN_SAMPLE_FRAC)))
    return sec


def sec_accuracy(ctx: Ctx) -> Section:
    sec = Section("accuracy", "Accuracy by picture, filter and segment")
    acc = ctx.q("accuracy_by_method")
    b = ctx.best
    pic = (pl.when(pl.col("filter").is_null()).then(pl.col("method"))
           .otherwise(pl.col("method") + "+" + pl.col("filter")).alias("picture"))
    rows = acc.with_columns(pic) if acc.height else acc
    # one x position per picture, ordered by horizontal RMSE (segment all): best first
    # only pictures with a horizontal or vertical figure get a slot (tracker rows may lack them)
    drawn = b.pictures.filter(pl.col("horizontal_m").is_not_null() | pl.col("height_m").is_not_null())
    order = drawn.sort(["horizontal_m", "pos_m"], nulls_last=True)["picture"].to_list()
    missing = b.pictures.filter(~pl.col("picture").is_in(order))["picture"].to_list()
    if rows.height:
        rows = rows.filter(pl.col("picture").is_in(order))
    fig = make_subplots(rows=1, cols=2, shared_yaxes=False, horizontal_spacing=0.08,
                        subplot_titles=["Horizontal RMS error", "Vertical (height) RMS error"])
    for i, seg in enumerate(["all", "straight", "turn"]):
        part = rows.filter(pl.col("segment") == seg) if rows.height else rows
        if part.height == 0:
            continue
        for col, (metric, _title) in enumerate((("rmse_horizontal_m", ""), ("rmse_height_m", "")), start=1):
            fig.add_trace(go.Bar(x=part["picture"].to_list(), y=f32(part[metric]), name=f"segment {seg}",
                                 legendgroup=seg, showlegend=col == 1, marker_color=COLORS[i],
                                 visible=True if seg == "all" else "legendonly"), row=1, col=col)
    style(fig, "Real RMS error of every picture (fusion methods, and trackers as method+filter)", "", "",
            height=560, barmode="group")
    fig.update_xaxes(categoryorder="array", categoryarray=order, tickangle=-40)
    fig.update_yaxes(title_text="horizontal RMSE (m)", row=1, col=1)
    fig.update_yaxes(title_text="vertical RMSE (m)", row=1, col=2)
    best = f"best picture: {b.picture}; " if b.picture else ""
    sec.figures.append((fig, f"From the metrics table (sql/accuracy_by_method.sql), pictures ordered by horizontal "
                             f"RMSE, segment all ({best}the centralised measurement-level filter, {CENTRALIZED}, is a "
                             "reference, not a bound); straight and turn segments are in the legend."
                             + (f" Not drawn ({len(missing)} pictures without horizontal and vertical rows in this "
                                f"run): {', '.join(missing)}." if missing else "")))
    sec.tables.append(("RMSE by picture, filter and segment, in metres (sql/accuracy_by_method.sql)", acc))
    return sec


def sec_quality(ctx: Ctx) -> Section:
    sec = Section("quality", "Association, track and cluster quality")
    sec.tables.append(("Association quality (sql/association_quality.sql)", ctx.q("association_quality")))
    sec.tables.append(("Track quality (sql/track_quality.sql)", ctx.q("track_quality")))
    sec.tables.append(("Cluster statistics (sql/cluster_statistics.sql)", ctx.q("cluster_statistics")))
    return sec


def sec_conflicts(ctx: Ctx) -> Section:
    sec = Section("conflicts", "Conflicts")
    tl = ctx.q("conflict_timeline")
    b = ctx.best
    methods = tl["method"].unique(maintain_order=True).to_list() if tl.height else []
    main = b.best_of(methods)
    shown = {main, CENTRALIZED}
    fig = make_subplots(rows=2, cols=1, shared_xaxes=True, vertical_spacing=0.1,
                        subplot_titles=["Aircraft pairs in alert at each epoch", "New alerts per minute"])
    for i, m in enumerate(methods):
        part = tl.filter(pl.col("method") == m)
        minute = (part.with_columns((pl.col("t_s") // 60.0 * 60.0).alias("t0"))
                  .group_by("t0").agg(pl.col("new_alerts").sum()).sort("t0"))
        color = "black" if m == main else COLORS[i % len(COLORS)]
        label = m + (" (best picture)" if m == main else " (centralised reference)" if m == CENTRALIZED else "")
        part = thin(step_changes(part.sort("t_s"), "alerts"))
        fig.add_trace(go.Scatter(x=f32(part["t_s"]), y=f32(part["alerts"]), mode="lines", name=label,
                                 legendgroup=m, visible=visible(m, shown),
                                 line=dict(color=color, width=1.2, shape="hv")), row=1, col=1)
        # per whole minute of the run: the rate is the count in that minute (alerts/min)
        fig.add_trace(go.Scatter(x=f32(minute["t0"] + 30.0), y=f32(minute["new_alerts"]), mode="lines+markers",
                                 name=label, legendgroup=m, showlegend=False, visible=visible(m, shown),
                                 marker=dict(size=4), line=dict(color=color, width=1.2)), row=2, col=1)
    style(fig, "Conflict alerts over time, per picture", "", "", height=620)
    fig.update_yaxes(title_text="pairs in alert (pairs)", row=1, col=1)
    fig.update_yaxes(title_text="new alerts per minute (1/min)", row=2, col=1)
    fig.update_xaxes(title_text="time t (s)", row=2, col=1)
    sec.figures.append((fig, "Conflict prediction (5.10)–(5.17) on every picture (sql/conflict_timeline.sql). Top: "
                             "pairs in alert at each epoch; bottom: alerts that start (pair not in alert at its "
                             "previous epoch) counted per minute of the run, drawn at the middle of the minute. Drawn "
                             "by default: the best picture and the centralised reference; the others are in the "
                             "legend." if methods else "No aircraft pairs were evaluated (single-aircraft scenario?)."))
    sec.tables.append(("Alert scores against truth (sql/alert_scores.sql)", ctx.q("alert_scores")))
    conflicts = ctx.q("conflicts")
    sec.tables.append((f"Most severe conflicts (sql/conflicts.sql; {conflicts.height:,} alerted pairs)",
                       conflicts.head(CONFLICT_ROWS)))
    return sec


EVAL_BAR_METRICS = (("rmse_horizontal_m", "horizontal RMS"), ("p95_horizontal_m", "horizontal p95"),
                    ("along_track_rms_m", "along-track RMS"), ("across_track_rms_m", "across-track RMS"),
                    ("rmse_height_m", "height RMS"))


def sec_evaluation(ctx: Ctx) -> Section:
    """The evaluation stage (tertiary.evaluation.evaluate): pictures side by side, and the horizontal RMS
    by altitude band, range ring and flight phase."""
    sec = Section("evaluation", "Pictures against the reference (evaluation stage)")
    cmp = ctx.q("picture_comparison")
    if cmp.height == 0:
        sec.note = "Not computed in this run: no picture was scored by the evaluation stage."
        return sec
    fig = go.Figure()
    for i, (metric, label) in enumerate(EVAL_BAR_METRICS):
        if metric in cmp.columns:
            fig.add_trace(go.Bar(x=cmp["method"].to_list(), y=f32(cmp[metric]), name=label,
                                 marker_color=COLORS[i % len(COLORS)]))
    style(fig, "Position errors per picture", "", "error (m)", barmode="group")
    sec.figures.append((fig, "tertiary.evaluation.evaluate: every picture matched once to the reference (tertiary.evaluation.matching:"
                             " interpolated reference, 1 NM horizontal / 300 m vertical gate, one-to-one per epoch), errors split into "
                             "horizontal, along-track, across-track and height (sql/picture_comparison.sql)."))
    sec.tables.append(("Pictures compared (sql/picture_comparison.sql)", cmp))
    multi = ctx.q("multitarget_metrics")
    if multi.height:
        sec.tables.append(("Multi-target metrics beside RMSE: OSPA, GOSPA (and its parts), SIAP "
                           "(sql/multitarget_metrics.sql)", multi))
    by = ctx.store.sql("SELECT method, segment, value FROM metrics WHERE stage = 'evaluation' "
                       "AND metric = 'rmse_horizontal_m' ORDER BY segment")
    if by.height:
        wide = by.pivot(on="method", index="segment", values="value", aggregate_function="first")
        sec.tables.append(("Horizontal RMS (m) by altitude band, range ring from the nearest radar and flight "
                           "phase", wide))
    return sec
