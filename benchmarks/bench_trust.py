"""Verdicts on traffic nothing was tuned on: the national peak, the default hour, real ADS-B
traffic, and trajectories made here in the OpenSky format (circling aircraft, en-route traffic at
high level with long turns).

Each dataset is simulated and run with the CLI, each command in a fresh process, and the run's
database is read for every figure a verdict rests on:

* safety, per picture (the truth picture included): alert episodes genuine / nuisance / false /
  undetermined (the truth ends before their outcome),
  how many of them (and of the missed losses) are picture-induced or predictor-induced, Torres &
  McKay's valid alerts, losses of separation alerted and missed (and the missed ones under way
  when their aircraft were first observed, which no alert can precede), median warning;
* system targets and tracks per aircraft, and why an aircraft has more than one confirmed
  system target (:func:`target_splits`);
* horizontal RMSE of every tracker against its fused input, overall and per flight phase;
* the posterior Cramér–Rao bound of every picture, its gap, and the pictures below it;
* the false- and duplicate-track rates and the completeness of every picture (the centralised
  reference against the best fused picture);
* on the national datasets, what the undetermined alerts turn out to be against the same
  scenario's truth simulated 10 minutes longer;
* the cause of each picture-induced alert of the production picture, and for each false alert
  that the picture's uncertainty alone raises, how far the tracks' σ would have to shrink to
  avoid it against how large their actual error is in σ: whether a consistent covariance would
  avoid it.

    python benchmarks/bench_trust.py [--only national15,national15-evening,default,adsb-paris,made] [--work DIR]

Results: ``benchmarks/results/bench_trust.json`` (one entry per dataset; ``--only`` keeps the
entries of the datasets it does not run).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _util import RESULTS, each_dataset  # noqa: E402
from bench_memory import _CHILD, CONFIGS  # noqa: E402

#: every dataset: how it is made, and the run's arguments
DATASETS = ("national15", "national15-evening", "default", "adsb-paris", "made")
#: start (s after midnight) of the national scenario's 15 minutes: the peak every check reads,
#: and an evening slice that no change was checked on before it was made
NATIONAL15_START_S = {"national15": 28800.0, "national15-evening": 64800.0}
#: how much longer the national scenario is simulated to see what its undetermined alerts were
LATER_S = 600.0
SAFETY = ("alert_episodes", "genuine_alerts", "nuisance_alerts", "false_alerts", "undetermined_alerts",
          "alerts_picture_induced", "alerts_predictor_induced", "false_alerts_picture_induced",
          "false_alerts_predictor_induced", "undetermined_alerts_picture_induced",
          "nuisance_alerts_picture_induced", "missed_los_picture_induced", "missed_los_predictor_induced",
          "missed_los_under_way", "valid_alerts", "los_episodes", "alerted_los", "missed_los", "warning_median_s",
          "alerts_per_hour")
#: the trackers run on the made trajectories: production's and the turn-rate-estimating one
MADE_FILTERS = "imm_sym,imm_ct"
PHASES = ("all", "phase:level", "phase:turn", "phase:climb-descent")
FT, KT, FPM = 0.3048, 1852.0 / 3600.0, 0.3048 / 60.0
EARTH_R = 6_371_000.0
#: WGS-84 semi-major axis (m) and first eccentricity squared: the made fixes lie on the ellipsoid
WGS84_A, WGS84_E2 = 6_378_137.0, 6.69437999014e-3


def _child(args: list[str]) -> tuple[float, str]:
    """(wall s, stdout) of one CLI command in a fresh interpreter."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", _CHILD, *args], capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"tertiary {' '.join(args)} failed ({proc.returncode}): {proc.stderr.strip()[-600:]}")
    return time.perf_counter() - t0, proc.stdout


# --------------------------------------------------------------------------- OpenSky-format trajectories


def _flight(icao: str, lat0: float, lon0: float, t0: float, legs: list[tuple[float, float, float]],
            speed_mps: float, alt_ft: float, climb: list[tuple[float, float, float]] = ()) -> dict[str, np.ndarray]:
    """One aircraft at 1 s: ``legs`` (duration s, turn rate °/s, initial heading ° for the first
    leg only) flown one after another from (lat0, lon0); ``climb`` (start s, end s, rate ft/min)."""
    rates = np.concatenate([np.full(int(d), w) for d, w, _ in legs])
    t = np.arange(len(rates), dtype=float)
    heading = legs[0][2] + np.concatenate([[0.0], np.cumsum(rates[:-1])])
    vs = np.zeros_like(t)
    for a, b, r in climb:
        vs[(t >= a) & (t < b)] = r
    alt = alt_ft + np.concatenate([[0.0], np.cumsum(vs[:-1] / 60.0)])
    # each 1 s step flown at its mid-step heading from the sample before, on the WGS-84 ellipsoid
    # (meridian and prime-vertical radii at the current latitude): the positions integrate the
    # reported ground speed and track, as a real aircraft's fixes and velocity messages do
    h = np.radians(heading + 0.5 * rates)
    step_n, step_e = speed_mps * np.cos(h), speed_mps * np.sin(h)
    lat = lat0 + np.degrees(np.concatenate([[0.0], np.cumsum(step_n[:-1])]) / EARTH_R)
    for _ in range(2):                     # the meridian radius at the latitude reached
        s2 = np.sin(np.radians(lat)) ** 2
        m = WGS84_A * (1 - WGS84_E2) / (1 - WGS84_E2 * s2) ** 1.5
        lat = lat0 + np.degrees(np.concatenate([[0.0], np.cumsum(step_n[:-1] / m[:-1])]))
    s2 = np.sin(np.radians(lat)) ** 2
    n_rad = WGS84_A / np.sqrt(1 - WGS84_E2 * s2)
    lon = lon0 + np.degrees(np.concatenate([[0.0], np.cumsum(step_e[:-1] / (n_rad[:-1] * np.cos(np.radians(lat[:-1]))))]))
    return {"timestamp": t0 + t, "icao24": np.full(len(t), icao), "latitude": lat, "longitude": lon,
            "altitude": alt, "groundspeed": np.full(len(t), speed_mps / KT), "track": heading % 360.0,
            "vertical_rate": vs, "onground": np.zeros(len(t), bool), "callsign": np.full(len(t), f"T{icao[-4:]}")}


def _at(lat: float, lon: float, heading: float, speed: float, before_s: float) -> tuple[float, float]:
    """The point ``before_s`` seconds of straight flight before (lat, lon) on ``heading``."""
    h = math.radians(heading)
    d = speed * before_s
    return (lat - math.degrees(d * math.cos(h) / EARTH_R),
            lon - math.degrees(d * math.sin(h) / (EARTH_R * math.cos(math.radians(lat)))))


def _encounters(t0: float) -> list[dict[str, np.ndarray]]:
    """Designed en-route encounters at FL350 (speeds 230 m/s), each meeting point 1 200 s in:
    a 90° crossing that misses by 1 NM (a loss of separation), one that misses by 8 NM (none), an
    in-trail pair 8 NM apart, a crossing 1 000 ft apart, and a head-on pair that misses by 3 NM
    because one turns away 150 s before the closest approach (a loss avoided by a manoeuvre)."""
    nm, v, meet, out = 1852.0, 230.0, 1200.0, []
    spots = [(49.6, 1.2), (49.6, 3.6), (48.0, 1.2), (48.0, 3.6), (48.8, 4.2)]
    dlat = lambda m: math.degrees(m / EARTH_R)                    # noqa: E731
    for k, (miss, dz_ft, trail) in enumerate(((1.0, 0, False), (8.0, 0, False), (8.0, 0, True), (0.0, 1000, False))):
        lat, lon = spots[k]
        h2 = 90.0 if trail else 0.0
        la, lo = _at(lat, lon, 90.0, v, meet)
        out.append(_flight(f"c{k}0000", la, lo, t0, [(2400, 0.0, 90.0)], v, 35000.0))
        lb, lob = _at(lat + (0.0 if trail else dlat(miss * nm)), lon - (math.degrees(miss * nm / (EARTH_R * math.cos(
            math.radians(lat)))) if trail else 0.0), h2, v, meet)
        out.append(_flight(f"c{k}0001", lb, lob, t0, [(2400, 0.0, h2)], v, 35000.0 + dz_ft))
    lat, lon = spots[4]
    la, lo = _at(lat, lon, 90.0, v, meet)
    out.append(_flight("c40000", la, lo, t0, [(2400, 0.0, 90.0)], v, 35000.0))
    lb, lob = _at(lat + dlat(0.5 * nm), lon, 270.0, v, meet)
    out.append(_flight("c40001", lb, lob, t0, [(int(meet - 150), 0.0, 270.0), (10, -3.0, 0.0), (1500, 0.0, 0.0)],
                       v, 35000.0))
    return out


def made_trajectories(path: Path, seed: int = 11) -> Path:
    """An hour of made traffic around 48.8° N 2.4° E in the OpenSky schema: a flight-inspection
    aircraft flying wide circles (0.2°/s) and one flying standard-rate orbits (3°/s, both ways),
    24 en-route aircraft at FL300–FL390 on long legs with long gentle turns (0.3–1.5°/s) and a few
    level changes, and the designed encounters of :func:`_encounters`."""
    import polars as pl
    rng = np.random.default_rng(seed)
    t0 = datetime(2021, 10, 7, 9, 0, tzinfo=timezone.utc).timestamp()
    flights = [
        _flight("f10001", 48.70, 2.20, t0, [(300, 0.0, 90.0)] + [(1800, 0.2, 0.0), (600, 0.0, 0.0), (600, -0.2, 0.0)],
                70.0, 6000.0),
        _flight("f10002", 48.95, 2.60, t0, [(240, 0.0, 200.0)] + [(240, 1.5, 0.0), (120, 0.0, 0.0), (120, 3.0, 0.0),
                                                                 (300, 0.0, 0.0), (120, -3.0, 0.0), (240, -1.5, 0.0),
                                                                 (600, 0.0, 0.0)] * 2, 110.0, 8000.0),
    ]
    flights += _encounters(t0)
    for k in range(24):
        legs, total = [], 0
        heading = float(rng.uniform(0, 360))
        while total < 3600:
            straight = int(rng.uniform(300, 900))
            turn_deg = float(rng.uniform(20, 90)) * rng.choice([-1, 1])
            rate = float(rng.uniform(0.3, 1.5)) * np.sign(turn_deg)
            legs += [(straight, 0.0, heading), (int(abs(turn_deg / rate)), rate, heading)]
            total += straight + int(abs(turn_deg / rate))
        alt = float(rng.choice(np.arange(30000, 39001, 1000)))
        climb = [(float(rng.uniform(600, 2400)), 0.0, float(rng.choice([-1500, 1500])))] if k % 3 == 0 else []
        climb = [(a, a + 2000 * FT / (abs(r) * FPM) / 1.0, r) for a, _, r in climb]   # a 2 000 ft change
        lat0, lon0 = 48.8 + float(rng.uniform(-1.2, 1.2)), 2.4 + float(rng.uniform(-1.6, 1.6))
        flights.append(_flight(f"e{20000 + k:05d}", lat0, lon0, t0 + float(rng.uniform(0, 600)), legs,
                               float(rng.uniform(210, 250)), alt, climb))
    cols = {c: np.concatenate([f[c] for f in flights]) for c in flights[0]}
    df = pl.DataFrame(cols).with_columns(pl.from_epoch(pl.col("timestamp"), time_unit="s").dt.replace_time_zone("UTC"))
    df = df.filter(pl.col("timestamp") < pl.lit(datetime.fromtimestamp(t0 + 3600, timezone.utc)))
    df.write_parquet(path)
    return path


# --------------------------------------------------------------------------- figures from a run


def _rows(db: Path, sql: str) -> list[tuple]:
    import duckdb
    con = duckdb.connect(str(db), read_only=True)
    try:
        return con.execute(sql).fetchall()
    finally:
        con.close()


def _clean(v):
    return None if v is None or (isinstance(v, float) and not math.isfinite(v)) else round(float(v), 3)


def figures(db: Path) -> dict:
    """Every figure of the verdicts from one run database."""
    m: dict[tuple[str, str, str, str], float] = {
        (s, meth, k, seg): v for s, meth, k, seg, v in _rows(db, "select stage, method, metric, segment, value "
                                                                "from metrics")}
    run = dict(_rows(db, "select key, value from run"))
    rows = json.loads(run.get("rows", "{}"))
    pictures = sorted({meth for (s, meth, k, _) in m if s == "safety" and k == "alert_episodes"})
    safety = {p: {k: _clean(m.get(("safety", p, k, "all"))) for k in SAFETY} for p in pictures}
    for p, v in safety.items():
        if v["los_episodes"]:
            v["alerted_fraction"] = _clean(v["alerted_los"] / v["los_episodes"])
            # of the losses an alert could precede: those under way when first observed left out
            v["alerted_fraction_alertable"] = _clean(v["alerted_los"] / max(v["los_episodes"]
                                                                           - (v["missed_los_under_way"] or 0.0), 1.0))
    fused = sorted({meth for (s, meth, k, _) in m if s == "fusion" and k == "rmse_horizontal_m"})
    tracked = sorted({meth for (s, meth, k, _) in m if s == "tracker" and k == "rmse_horizontal_m"})
    accuracy = {}
    for p in fused + tracked:
        # the evaluation stage's own accuracy (per flight phase too); the fusion / tracker
        # stage's figure where a run has no evaluation stage
        own = ("tracker" if p in tracked else "fusion", p, "rmse_horizontal_m", "all")
        accuracy[p] = {seg: _clean(m.get(("evaluation", p, "rmse_horizontal_m", seg),
                                         m.get(own) if seg == "all" else None)) for seg in PHASES}
    tracker_vs_input = {}
    for p in tracked:
        src = p.split("+")[0]
        tracker_vs_input[p] = {seg: (None if accuracy[p][seg] is None or accuracy.get(src, {}).get(seg) is None
                                     else round(accuracy[p][seg] - accuracy[src][seg], 2)) for seg in PHASES}
    bound = {}
    for (s, meth, k, seg), v in m.items():
        if s == "bound" and k in ("pcrb_horizontal_m", "gap_horizontal_m", "pcrb_pos_m", "gap_pos_m",
                                  "pcrb_vel_mps", "gap_vel_mps"):
            bound.setdefault(meth, {}).setdefault(seg, {})[k] = _clean(v)
    below = sorted({meth for meth, segs in bound.items() for seg, g in segs.items()
                    if any((g.get(k) or 0.0) < 0.0 for k in ("gap_horizontal_m", "gap_pos_m", "gap_vel_mps"))})
    false_tracks, duplicate_tracks, unassessed, completeness = ({meth: _clean(v) for (meth, v) in _rows(
        db, f"select method, value from metrics where stage in {stages} and metric = '{k}' and segment = 'all'")}
        for k, stages in (("false_tracks_per_hour", "('evaluation')"), ("duplicate_tracks_per_hour", "('evaluation')"),
                          ("unassessed_tracks", "('evaluation')"), ("completeness", "('fusion', 'tracker')")))
    tracks_per_aircraft = {p: _clean(m.get(("tracker", p, "tracks", "all"), float("nan")) / rows["aircraft"])
                           for p in tracked if rows.get("aircraft")}
    return {"safety": safety, "accuracy_horizontal_m": accuracy, "tracker_minus_input_m": tracker_vs_input,
            "bound": bound, "pictures_below_bound": below, "false_tracks_per_hour": false_tracks,
            "duplicate_tracks_per_hour": duplicate_tracks, "unassessed_tracks": unassessed,
            "completeness": completeness,
            "targets_per_aircraft": _clean(rows.get("confirmed_targets", 0) / rows["aircraft"])
            if rows.get("aircraft") else None,
            "tracks_per_aircraft": tracks_per_aircraft, "aircraft": rows.get("aircraft"),
            "notes": json.loads(run.get("notes", "[]"))}


#: what keeps a concurrent second target apart from its aircraft's first, tested in this order
#: on their reports' aligned rows at the second's first epoch (the gate's terms)
SPLIT_CAUSES = ("one radar, two local tracks", "Mode C codes differ (> 300 m)", "a local track jumped (> 3 km)",
                "velocity differs (> 60 m/s)", "the first target has no report then", "other")


def target_splits(db: Path, method: str = "information") -> dict:
    """Every confirmed system target of ``method`` beyond an aircraft's first (targets by the
    majority truth of their reports, ordered by their first confirmed epoch), by cause: ``after
    the first ended`` (a coverage gap the target did not bridge), or, beside it, the first of
    :data:`SPLIT_CAUSES` that holds between its reports and the previous target's at its first
    epoch. Needs the full tables (associations, aligned, fused)."""
    import duckdb
    con = duckdb.connect(str(db), read_only=True)
    try:
        con.execute(f"""create temp table ct as
            with tv as (select a.run, a.target_id, r.truth_id, count(*) n from associations a
                        join reports r using (report_id) where r.truth_id is not null group by all),
                 maj as (select run, target_id, arg_max(truth_id, n) truth_id from tv group by all),
                 conf as (select run, target_id, min(epoch) c0, max(epoch) c1 from fused
                          where method = '{method}' and not tentative group by all)
            select m.*, c.c0, c.c1, lag(c.c1) over w prev_c1, lag(m.target_id) over w prev_id
            from maj m join conf c using (run, target_id)
            window w as (partition by m.run, m.truth_id order by c.c0)""")
        rows = con.execute("""
            with x as (select * from ct where prev_id is not null),
                 g as (select x.target_id xt, a.target_id = x.target_id mine, al.radar_id, al.x_m, al.y_m,
                              al.vx_mps, al.vy_mps, al.altitude_m, x.c0 < x.prev_c1 beside
                       from x join associations a on a.run = x.run and a.epoch = x.c0
                                                  and a.target_id in (x.target_id, x.prev_id)
                       join aligned al on al.report_id = a.report_id and al.epoch = a.epoch and al.run = a.run)
            select s.xt, bool_or(s.beside) beside, count(o.xt) others,
                   bool_or(s.radar_id = o.radar_id) same_radar,
                   min(abs(s.altitude_m - o.altitude_m)) dalt,
                   min(sqrt((s.x_m - o.x_m) ^ 2 + (s.y_m - o.y_m) ^ 2)) dh,
                   min(greatest(abs(s.vx_mps - o.vx_mps), abs(s.vy_mps - o.vy_mps))) dv
            from g s left join g o on o.xt = s.xt and not o.mine where s.mine group by s.xt""").fetchall()
        aircraft = con.execute("select count(distinct (run, truth_id)) from ct").fetchall()[0][0]
    finally:
        con.close()
    counts = dict.fromkeys(("after the first ended", *SPLIT_CAUSES), 0)
    for _, beside, others, same_radar, dalt, dh, dv in rows:
        tests = (bool(same_radar), (dalt or 0.0) > 300.0, (dh or 0.0) > 3000.0, (dv or 0.0) > 60.0, others == 0, True)
        cause = SPLIT_CAUSES[tests.index(True)] if beside else "after the first ended"
        counts[cause] += 1
    return {"method": method, "aircraft_with_a_target": aircraft, "extra_targets": len(rows), "causes": counts}


def _truth_of(data: Path):
    import polars as pl
    files = sorted(p for p in [*data.glob("truth.parquet"), *data.glob("truth/*.parquet")])
    return pl.read_parquet(files)


def alert_causes(db: Path, data: Path, picture: str = "information+imm_sym") -> dict:
    """The cause of each picture-induced alert episode of ``picture`` at its first epoch, the first
    rule that fires: ``one aircraft or unmatched`` (the episode has no two distinct aircraft),
    ``a track coasting after its aircraft left`` (an aircraft's truth ended before the alert),
    ``the picture's uncertainty`` (the truth's own states, given the two tracks' covariances,
    raise the same alert: :func:`_uncertainty_alerts`; no error of the picture's states is
    needed), ``coasting track`` (a track held without a plot), ``track far from its aircraft`` (> 2 km),
    ``height error`` (> 150 m), ``a vertical manoeuvre after the last update`` (a rate more
    than 2 m/s off that is within 2 m/s of the aircraft's true rate at the track's previous
    epoch: the aircraft levelled off or began a climb or descent since, which no picture fed by
    scans can know yet; :func:`_rate_an_update_ago`), ``vertical rate error`` (> 2 m/s: a climb
    or descent the aircraft does not fly, or the reverse), ``en-route/terminal boundary`` (one
    track above the en-route floor, one below), ``wide horizontal threshold`` (the
    covariance-based widening of the horizontal threshold above 1 km: an uncertain or
    inconsistent velocity), else ``other``. Counts per
    classification and cause; the medians of the estimation term and of the tracks' velocity
    standard deviation against their real velocity error."""
    import duckdb
    import polars as pl
    from tertiary.evaluation.reference import interpolate_reference
    con = duckdb.connect(str(db), read_only=True)
    q = lambda sql: pl.from_arrow(con.sql(sql).to_arrow_table())    # noqa: E731
    al = q(f"select * from alerts where method = '{picture}' and induced = 'picture'")
    if not al.height:
        return {}
    method, flt = picture.split("+")
    conf = q(f"select run, epoch, id_a, id_b, r_thr_m from conflicts where method = '{picture}'")
    tr = q(f"select run, epoch, track_id, x_m, y_m, vx_mps, vy_mps, alt_m, alt_rate_mps, alt_rate_var_m2ps2, cov_diag, "
           f"status from tracks "
           f"where method = '{method}' and filter = '{flt}'")
    run = dict(con.sql("select key, value from run").fetchall())
    con.close()
    cc = json.loads(run["config"])["conflicts"]
    truth = _truth_of(data)
    a = al.with_row_index("k").join(conf, left_on=["run", "t_start", "id_a", "id_b"],
                                     right_on=["run", "epoch", "id_a", "id_b"], how="left")
    for side in ("a", "b"):
        t = a.select("k", "run", "t_start", pl.col(f"id_{side}").alias("track_id"), "truth_a", "truth_b").join(
            tr, left_on=["run", "t_start", "track_id"], right_on=["run", "epoch", "track_id"], how="left")
        near = []
        for which in ("truth_a", "truth_b"):           # the track's own aircraft: the nearer of the pair
            r = interpolate_reference(truth, t.with_columns(pl.col("t_start").alias("time"),
                                                            pl.col(which).fill_null(-1).alias("truth_id")))
            near.append(r.with_columns((((pl.col("x_m") - pl.col("true_x_m")) ** 2
                                         + (pl.col("y_m") - pl.col("true_y_m")) ** 2).sqrt()).fill_null(1e12)
                                       .alias("__d")).with_row_index("__i"))
        r = pl.concat(near).sort("__i", "__d").unique("__i", keep="first", maintain_order=True)
        a = a.join(r.select("k", pl.col("__d").alias(f"perr_{side}"), pl.col("truth_id").alias(f"own_{side}"),
                            (pl.col("alt_m") - pl.col("true_alt_m")).abs().alias(f"herr_{side}"),
                            (pl.col("alt_rate_mps") - pl.col("true_alt_rate_mps")).abs().alias(f"rerr_{side}"),
                            pl.col("alt_m").alias(f"alt_{side}"), (pl.col("status") == "coasting").alias(f"coast_{side}"),
                            pl.max_horizontal(pl.col("cov_diag").arr.get(3), pl.col("cov_diag").arr.get(4)).sqrt()
                            .alias(f"sv_{side}"), pl.col("alt_rate_var_m2ps2").sqrt().alias(f"sr_{side}"),
                            (((pl.col("vx_mps") - pl.col("true_vx_mps")) ** 2 + (pl.col("vy_mps") - pl.col("true_vy_mps"))
                              ** 2).sqrt()).alias(f"verr_{side}")), on="k", how="left")
    floor = cc.get("enroute_above_m")
    hi = pl.max_horizontal("alt_a", "alt_b")
    sep = (pl.when(hi >= floor).then(cc["enroute_h_m"]).otherwise(3 * 1852.0) if floor is not None
           else pl.lit(cc["dr_h_m"] or 3 * 1852.0))
    a = a.with_columns((pl.col("r_thr_m") - sep - cc["pilot_h_m"]).alias("est_h_m"))
    a = a.join(_uncertainty_alerts(db, data, a, picture, truth), on="k", how="left")
    a = a.join(_rate_an_update_ago(a, tr, truth), on="k", how="left")
    last = truth.group_by("truth_id").agg(pl.col("time").max().cast(pl.Datetime("us", "UTC")).alias("__last"))
    for side in ("a", "b"):
        a = a.join(last.rename({"truth_id": f"truth_{side}", "__last": f"last_{side}"}), on=f"truth_{side}",
                   how="left")
    gone = pl.min_horizontal("last_a", "last_b") < pl.col("t_start").cast(pl.Datetime("us", "UTC"))
    cause = (pl.when(pl.col("truth_a").is_null()).then(pl.lit("one aircraft or unmatched"))
             .when(gone).then(pl.lit("a track coasting after its aircraft left"))
             .when(pl.col("uncertainty")).then(pl.lit("the picture's uncertainty"))
             .when(pl.col("coast_a") | pl.col("coast_b")).then(pl.lit("coasting track"))
             .when(pl.max_horizontal("perr_a", "perr_b") > 2000).then(pl.lit("track far from its aircraft"))
             .when(pl.max_horizontal("herr_a", "herr_b") > 150).then(pl.lit("height error"))
             .when((pl.max_horizontal("rerr_a", "rerr_b") > 2.0) & pl.col("stale_rate").fill_null(False))
             .then(pl.lit("a vertical manoeuvre after the last update"))
             .when(pl.max_horizontal("rerr_a", "rerr_b") > 2.0).then(pl.lit("vertical rate error"))
             .when(pl.lit(floor is not None) & (hi >= (floor or 0.0))
                   & (pl.min_horizontal("alt_a", "alt_b") < (floor or 0.0))).then(pl.lit("en-route/terminal boundary"))
             .when(pl.col("est_h_m") > 1000).then(pl.lit("wide horizontal threshold"))
             .otherwise(pl.lit("other")))
    a = a.with_columns(cause.alias("cause"))
    counts = {f"{c}: {k}": n for c, k, n in a.group_by("classification", "cause").len().sort("classification", "cause")
              .iter_rows()}
    med = a.filter(pl.col("classification") == "false").select(
        pl.col("est_h_m").median(), pl.max_horizontal("sv_a", "sv_b").median().alias("velocity_sigma_mps"),
        pl.max_horizontal("verr_a", "verr_b").median().alias("velocity_error_mps"))
    return {"picture": picture, "counts": counts,
            "false_medians": {k: _clean(v) for k, v in med.row(0, named=True).items()} if med.height else {},
            "uncertainty_false_alerts": _uncertainty_margins(a, cc["enroute_v_m"])}


def _rate_an_update_ago(a, tracks, truth, tol_mps: float = 2.0):
    """(k, stale_rate) per alert of ``a`` (its tracks ``id_a``/``id_b`` and their own aircraft
    ``own_a``/``own_b`` at ``t_start``): True where a track whose vertical rate is more than
    ``tol_mps`` off its aircraft's at the alert's first epoch is within ``tol_mps`` of the
    aircraft's true rate at the track's previous epoch (one update earlier)."""
    import polars as pl
    from tertiary.evaluation.reference import interpolate_reference
    stale = []
    for side in ("a", "b"):
        rows = a.select("k", "run", "t_start", pl.col(f"id_{side}").alias("track_id"), pl.col(f"own_{side}")
                        .alias("truth_id"), pl.col(f"rerr_{side}").alias("rerr"))
        prev = (tracks.select("run", "track_id", "epoch").join(rows, on=["run", "track_id"])
                .filter(pl.col("epoch") < pl.col("t_start")).group_by("k").agg(pl.col("epoch").max().alias("time")))
        rows = (rows.join(prev, on="k", how="left")
                .filter(pl.col("time").is_not_null() & pl.col("truth_id").is_not_null()))
        got = interpolate_reference(truth, rows)
        rate = tracks.select("run", "track_id", pl.col("epoch").alias("t_start"), "alt_rate_mps")
        got = got.join(rate, on=["run", "track_id", "t_start"], how="left")
        stale.append(got.select("k", ((pl.col("rerr") > tol_mps)
                                      & ((pl.col("alt_rate_mps") - pl.col("true_alt_rate_mps")).abs() <= tol_mps))
                                .fill_null(False).alias("s")))
    both = pl.concat(stale).group_by("k").agg(pl.col("s").any().alias("stale_rate"))
    return a.select("k").join(both, on="k", how="left").with_columns(pl.col("stale_rate").fill_null(False))


def _uncertainty_margins(a, sep_v_m: float) -> list[dict]:
    """Each false alert the picture's uncertainty alone raises: the channel that decides it
    (vertical when the predicted vertical miss exceeds the vertical minimum, so only the widened
    vertical threshold catches it), ``avoid_scale`` (:func:`_uncertainty_alerts`) and the two
    tracks' actual error in that channel in units of their σ at the alert's first epoch (RMS over
    the pair; horizontal: velocity error / (√2 σ_v), vertical: rate error / σ_rate). An alert
    a consistent covariance would avoid has error_to_sigma below avoid_scale; one epoch's ratio is
    a single draw (|N(0, 1)| when consistent), so it says which side an alert is on, not a rate."""
    import polars as pl
    rows = a.filter((pl.col("classification") == "false") & pl.col("uncertainty").fill_null(False))
    vertical = pl.col("dz_min_pred_m") > sep_v_m
    h = ((pl.col("verr_a") / (2 ** 0.5 * pl.col("sv_a"))) ** 2 + (pl.col("verr_b") / (2 ** 0.5 * pl.col("sv_b"))) ** 2)
    v = (pl.col("rerr_a") / pl.col("sr_a")) ** 2 + (pl.col("rerr_b") / pl.col("sr_b")) ** 2
    rows = rows.select(pl.col("t_start").cast(pl.String), "id_a", "id_b",
                       pl.when(vertical).then(pl.lit("vertical")).otherwise(pl.lit("horizontal")).alias("channel"),
                       "avoid_scale", (pl.when(vertical).then(v).otherwise(h) / 2).sqrt().round(2).alias("error_to_sigma"))
    return rows.to_dicts()


def _uncertainty_alerts(db: Path, data: Path, alerts, picture: str, truth, before_s: float = 40.0):
    """(k, uncertainty) per alert of ``alerts`` (k, run, t_start, id_a, id_b, truth_a, truth_b):
    whether the same conflict prediction (the run's configuration and confirmation) on the
    truth's states of the two aircraft, each given its track's covariance and height-channel
    variances at every epoch (the epochs from ``before_s`` before the alert's first to it),
    raises the alert (confirmed) at the alert's first epoch. True: the picture's uncertainty alone
    alerts (a perfect state with that covariance would too); False: the picture's states differ
    from the truth enough to alert where their truth would not.

    For an alert the uncertainty alone raises, ``avoid_scale``: the largest factor s (to 1 %) by
    which every σ of the two tracks (covariance × s²) could shrink and that prediction still
    alert; below it the alert is gone. A consistent covariance avoids the alert only if the
    tracks' errors are smaller than s times their σ (:func:`alert_causes` sets the two side by
    side)."""
    import duckdb
    import polars as pl
    from datetime import timedelta
    from safety import alerts as sa, conflicts as sc
    from tertiary.evaluation.truth_picture import truth_picture
    from tertiary.io.dataset import read_dataset
    from tertiary.pipeline.config import PipelineConfig, adapt_to_scenario, check_config
    from tertiary.store.layout import expand_covariances
    ds = read_dataset(data)
    cc = adapt_to_scenario(check_config(PipelineConfig()), ds).conflicts
    method, flt = picture.split("+")
    con = duckdb.connect(str(db), read_only=True)
    var = ["alt_var_m2", "alt_rate_var_m2ps2", "alt_cov_m2ps"]
    out = []
    for r in alerts.filter(pl.col("truth_a").is_not_null() & pl.col("truth_b").is_not_null()).iter_rows(named=True):
        t0 = r["t_start"] - timedelta(seconds=before_s)
        cov = pl.from_arrow(con.sql(
            f"select epoch, track_id, cov_ut, {', '.join(var)} from tracks where method = '{method}' "
            f"and filter = '{flt}' and run = {int(r['run'])} and track_id in ({int(r['id_a'])}, {int(r['id_b'])}) "
            f"and epoch between '{t0.isoformat()}' and '{r['t_start'].isoformat()}'").to_arrow_table())
        ids = {r["id_a"]: r["truth_a"], r["id_b"]: r["truth_b"]}
        cov = cov.with_columns(pl.col("track_id").replace_strict(ids, return_dtype=pl.UInt64),
                               pl.col("epoch").cast(pl.Datetime("us", "UTC")))
        cov = expand_covariances(cov)                     # cov_ut → the 6×6 the thresholds read
        pair = truth.filter(pl.col("truth_id").is_in([r["truth_a"], r["truth_b"]]))
        spans = pair.group_by("truth_id").agg(pl.col("time").min().alias("first"), pl.col("time").max().alias("last"))
        epochs = cov.select(pl.lit(r["run"], pl.UInt32).alias("run"), "epoch").unique().sort("epoch")
        pic = truth_picture(pair, spans.with_columns(pl.lit(r["run"], pl.UInt32).alias("run")), epochs, picture)
        pic = pic.drop("cov_diag", *var, strict=False).join(cov, on=["epoch", "track_id"], how="inner")
        us = epochs["epoch"].dt.epoch("us")
        at = int(pl.Series([r["t_start"]]).dt.epoch("us")[0])

        def alerts_at(scale: float) -> bool:
            scaled = pic.with_columns(pl.col("cov").arr.eval(pl.element() * scale ** 2),
                                      *(pl.col(c) * scale ** 2 for c in var))
            rows, _ = sc.conflicts_step(sc.init_conflict_state(), scaled, cc, "track_id", ds.origin, int(us.min()),
                                        int(us.max()) + 1, slim=False)
            return rows.filter((pl.col("epoch").dt.epoch("us") == at) & pl.col("alert")).height > 0

        hit, avoid = alerts_at(1.0), None
        if hit:                         # bisection: alerts at hi, not at lo (s = 0 is the truth picture)
            lo, hi = 0.0, 1.0
            while hi - lo > 0.01:
                mid = 0.5 * (lo + hi)
                lo, hi = (lo, mid) if alerts_at(mid) else (mid, hi)
            avoid = round(hi, 2)
        out.append({"k": r["k"], "uncertainty": hit, "avoid_scale": avoid})
    con.close()
    return pl.DataFrame(out, schema={"k": pl.UInt32, "uncertainty": pl.Boolean, "avoid_scale": pl.Float64})


def undetermined_outcomes(db: Path, data: Path, longer: Path) -> dict:
    """What the undetermined alerts (the truth ends before their link window closes) turn out to
    be against the same scenario's truth simulated ``LATER_S`` longer (``longer``; the simulation
    is deterministic: its truth equals the run's where both exist, checked here). Per picture
    (production and the truth picture) counts by (picture-induced?, outcome): genuine or nuisance
    when a loss or proximity of the pair overlaps the window, undetermined when the longer truth
    still ends first (an aircraft left the scenario), else false. The window's end is
    max(t_end + T^пор, t_start + the first alert epoch's predicted time to the closest approach,
    ≤ 2 T^пор): the scoring's, with the first epoch's prediction standing for every epoch's."""
    import duckdb
    import polars as pl
    from safety import alerts as sa
    from tertiary.core.units import US
    from tertiary.io.dataset import read_dataset
    from tertiary.pipeline.config import PipelineConfig, adapt_to_scenario, check_config
    ds = read_dataset(data)
    acfg = sa.AlertConfig(conflict=adapt_to_scenario(check_config(PipelineConfig()), ds).conflicts)
    short, long_ = _truth_of(data), _truth_of(longer)
    same = short.join(long_, on=["truth_id", "time"], how="left", suffix="_l")
    equal = bool(same["x_m_l"].is_not_null().all() and (same["x_m"] - same["x_m_l"]).abs().max() == 0.0
                 and (same["alt_m"] - same["alt_m_l"]).abs().max() == 0.0)
    con = duckdb.connect(str(db), read_only=True)
    al = pl.from_arrow(con.sql("select * from alerts where classification = 'undetermined'").to_arrow_table())
    con.close()
    if not al.height:
        return {"truth_equal_on_shared_span": equal, "counts": {}}
    los, prox = sa.truth_intervals(long_, acfg, ds.origin)
    tca = (pl.col("t_min_first_s").fill_nan(None).fill_null(0.0).clip(0.0, acfg.cpa_reach) * US).cast(pl.Int64)
    al = al.with_row_index("__k").with_columns(
        pl.col("t_start").dt.epoch("us").alias("t0"),
        pl.max_horizontal(pl.col("t_end").dt.epoch("us") + int(acfg.link * US),
                          pl.col("t_start").dt.epoch("us") + tca).alias("reach"))

    def linked(iv):
        return (al.join(iv.drop("run", strict=False), on=["truth_a", "truth_b"], how="inner")
                .filter((pl.col("t_start_us") <= pl.col("reach")) & (pl.col("t_end_us") >= pl.col("t0")))["__k"])
    obs = sa.observed_until(long_, acfg, ds.origin).drop("run", strict=False)
    for side in ("a", "b"):
        al = al.join(obs.rename({"truth_id": f"truth_{side}", "__obs_us": f"__o{side}"}), on=f"truth_{side}",
                     how="left")
    seen = pl.min_horizontal("__oa", "__ob") >= pl.col("reach")
    out = (pl.when(pl.col("__k").is_in(linked(los).implode())).then(pl.lit("genuine"))
           .when(pl.col("__k").is_in(linked(prox).implode())).then(pl.lit("nuisance"))
           .when(seen).then(pl.lit("false")).otherwise(pl.lit("undetermined")))
    al = al.with_columns(out.alias("outcome"))
    counts = {}
    for m, ind, o, n in al.group_by("method", "induced", "outcome").len().sort("method", "induced", "outcome").rows():
        counts.setdefault(m, {})[f"{ind or 'truth picture'} -> {o}"] = n
    keep = ("information+imm_sym", sa.TRUTH_PICTURE)
    return {"truth_equal_on_shared_span": equal, "later_s": LATER_S,
            "counts": {m: c for m, c in counts.items() if m in keep}}


# --------------------------------------------------------------------------- datasets


def _national15(work: Path, name: str, extra_s: float = 0.0, suffix: str = "") -> list[str]:
    from tertiary.simulate import load_scenario
    from tertiary.simulate.config import scenario_toml
    base = load_scenario("national")
    start = NATIONAL15_START_S[name]
    cfg = dataclasses.replace(base, duration_s=900.0 + extra_s,
                              national=dataclasses.replace(base.national, start_s=start))
    (work / f"{name}{suffix}.toml").write_text(scenario_toml(cfg))
    return [str(work / f"{name}{suffix}.toml")]


def _later(name: str, work: Path) -> dict:
    """:func:`undetermined_outcomes` of a national dataset's run, its scenario simulated
    ``LATER_S`` longer (kept in ``work``)."""
    longer = work / f"{name}-longer"
    if not (longer / "truth").exists():
        _child(["simulate", *_national15(work, name, LATER_S, "-longer"), "--out", str(longer), "--force", "--quiet"])
    return {"undetermined_outcomes": undetermined_outcomes(work / f"{name}-run" / "results.duckdb", work / name,
                                                           longer)}


def run_dataset(name: str, work: Path, figures_only: bool = False) -> dict:
    data, out = work / name, work / f"{name}-run"
    if figures_only:                    # the figures again from a kept run (no simulation, no run)
        old = json.loads((RESULTS / "bench_trust.json").read_text())["datasets"].get(name, {})
        return {**old, **figures(out / "results.duckdb"),
                "picture_induced_causes": alert_causes(out / "results.duckdb", data),
                "target_splits": target_splits(out / "results.duckdb"),
                **(_later(name, work) if name in NATIONAL15_START_S else {})}
    if name in NATIONAL15_START_S:
        sim, args = _national15(work, name), CONFIGS["production"]
    elif name == "default":
        sim, args = ["terminal-area"], []
    elif name == "adsb-paris":
        sim, args = ["adsb-paris"], CONFIGS["production"]
    else:
        sim = ["adsb", "--truth", str(made_trajectories(work / "made.parquet"))]
        args = ["--methods", "information", "--filters", MADE_FILTERS]
    wall_s, _ = _child(["simulate", *sim, "--out", str(data), "--force", "--quiet"])
    # every table: the causes read each alert's conflict row (its threshold) and the tracks' status
    wall_r, stdout = _child(["run", str(data), "--out", str(out), "--force", "--no-report", "--tables", "full", *args])
    print(stdout, flush=True)
    return {"simulate": sim, "run_args": args, "simulate_s": round(wall_s, 1), "run_s": round(wall_r, 1),
            "summary": [line.strip() for line in stdout.splitlines()
                        if line.strip().startswith(("run ", "system targets", "fusion", "tracker", "safety "))],
            **figures(out / "results.duckdb"), "picture_induced_causes": alert_causes(out / "results.duckdb", data),
            "target_splits": target_splits(out / "results.duckdb"),
            **(_later(name, work) if name in NATIONAL15_START_S else {})}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=",".join(DATASETS), help="comma-separated datasets to run")
    ap.add_argument("--work", type=Path, default=None, help="keep the datasets and runs here (default: a temp dir)")
    ap.add_argument("--figures-only", action="store_true", help="read the figures again from the runs kept in --work")
    args = ap.parse_args()
    if args.figures_only and args.work is None:
        raise SystemExit("--figures-only reads the runs of --work")
    results = each_dataset("bench_trust", args.only, DATASETS, args.work,
                           lambda name, work: run_dataset(name, work, args.figures_only))
    print(json.dumps({k: v["safety"] for k, v in results.items()}, indent=1))


if __name__ == "__main__":
    main()
