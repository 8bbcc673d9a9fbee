"""Flight data: the controller's cleared levels, correlated with the surveillance by Mode 3/A code.

An STCA that sees an aircraft climbing cannot tell, from the track alone, where it will level
off. A Mode S aircraft downlinks the level its crew selected (BDS 4,0, ``selected_alt_m``); for a
Mode C-only aircraft, or one that does not downlink it, real systems take the cleared flight
level (CFL) the controller entered in the flight data processing system. The FDPS correlates it
with the surveillance by the Mode 3/A code the flight was assigned.

Input: the optional dataset table ``flight_plans`` (:data:`FLIGHT_PLANS_SCHEMA`), one row per
flight and cleared level:

* ``mode_3a`` — the code assigned to the flight (four octal digits);
* ``valid_from`` / ``valid_to`` — when the code is the flight's and the level is in force;
* ``cleared_alt_m`` — the cleared level (m, the pressure-altitude reference of ``altitude_m``);
* ``run`` (optional; absent: every run of a Monte-Carlo dataset), ``callsign`` (optional);
* ``departure_lat_deg``, ``departure_lon_deg``, ``departure_time`` (optional, all three or none):
  a departing flight's aerodrome reference point (ADEP, as the FDPS's aerodrome data resolve
  it) and its actual time of departure (ATD, from the tower's departure message, which gives
  it to the minute: ICAO DEP field 13, HHMM).

A row with a missing or malformed code, a level outside the altitude band, a missing or
reversed validity interval, a departure given in part, off the globe or after ``valid_to`` goes
to ``rejects`` (input table ``flight_plans``) with its reason (:func:`check_flight_plans`).

Correlation (:func:`correlate`): a report gets the cleared level of the one flight plan that
holds the code it replied with at its time. None, or more than one (a code assigned to two
flights at once), gives null: an ambiguous correlation is no correlation. A report without a
code gets null. The level then travels reports → aligned → fused (the target's newest) →
tracks (``cleared_alt_m``, :data:`tertiary.contract.CLEARED_ALT_COLUMN`), where conflict
prediction stops a climb or descent at it when no selected level is known
(:mod:`safety.conflicts`, "Selected level").

Departure correlation (:func:`departure_step`). A crew that squawks the wrong code (another
flight's, or a mistyped one) is not correlated by code, so a Mode C-only departure climbs in the
picture with no level to stop at, and STCA extrapolates it through whatever holds above. Real
SDPS/FDPS pairs such a track with its plan by where and when it appears: a track that starts
near the aerodrome a departing plan names, low, soon after that plan's ATD, while no track has
replied the plan's code, is that departure (ARTS-style "departure auto-acquisition"). Here,
per radar local track (``run``, ``radar_id``, ``local_track_id``; a gap longer than
:attr:`DepartureConfig.max_gap_s` starts a new track, so a reused track number is never
inherited):

* the track's *first report with a code and a Mode C altitude* decides, once (plots without a
  local track number never do): it must have no code correlation, lie
  within ``radius_m`` of the plan's aerodrome and below ``max_alt_m``, at a time in
  [ATD, ATD + ``window_s``] (the ATD is floored to the minute and the first plots come a scan
  or two after lift-off);
* the plan must not have been replied by code by any report before that time (a correctly
  squawking departure takes its own plan), nor taken by an earlier track of the same radar;
* exactly one plan must qualify: none or several give no correlation, as for codes;
* the track's reports from then on get the plan's level where the code gave none
  (``cleared_alt_m`` is filled, never overwritten), until the track ends or the plan expires.

The decision reads only reports up to the track's first coded report, so it is the same
whatever the processing window (the step carries :class:`DepartureState` across windows). The
Dask engine's time slices rebuild state in their warm-up only: a departure whose first plots lie
before a slice's warm-up is not paired in that slice.
"""

from __future__ import annotations

import polars as pl

from dataclasses import dataclass, field

import numpy as np

from tertiary.contract import CLEARED_ALT_COLUMN, Limits, TIME, rejects_table
from tertiary.core.errors import DataError

__all__ = ["FLIGHT_PLANS_SCHEMA", "DepartureConfig", "DepartureState", "check_flight_plans", "correlate",
           "departure_step", "empty_flight_plans", "init_departure_state"]

#: the departure columns (optional, all three or none)
DEPARTURE_COLUMNS = ("departure_lat_deg", "departure_lon_deg", "departure_time")

#: the ``flight_plans`` input table (``run``, ``callsign`` and the departure columns optional)
FLIGHT_PLANS_SCHEMA: dict[str, pl.DataType] = {
    "run": pl.UInt32(), "mode_3a": pl.String(), "callsign": pl.String(), "valid_from": TIME, "valid_to": TIME,
    CLEARED_ALT_COLUMN: pl.Float64(), "departure_lat_deg": pl.Float64(), "departure_lon_deg": pl.Float64(),
    "departure_time": TIME,
}
_REQUIRED = ("mode_3a", "valid_from", "valid_to", CLEARED_ALT_COLUMN)


def empty_flight_plans() -> pl.DataFrame:
    return pl.DataFrame(schema=FLIGHT_PLANS_SCHEMA)


def _reason(limits: Limits) -> pl.Expr:
    lo, hi = limits.altitude_m
    code = pl.col("mode_3a").cast(pl.String)
    alt = pl.col(CLEARED_ALT_COLUMN)
    return (pl.when(code.is_null()).then(pl.lit("mode_3a: missing"))
            .when(~code.str.contains(r"^[0-7]{4}$")).then(pl.lit("mode_3a: not four octal digits"))
            .when(pl.col("valid_from").is_null() | pl.col("valid_to").is_null())
            .then(pl.lit("valid_from/valid_to: missing"))
            .when(pl.col("valid_to") < pl.col("valid_from")).then(pl.lit("valid_to: before valid_from"))
            .when(alt.is_null() | alt.is_nan() | alt.is_infinite()).then(pl.lit(f"{CLEARED_ALT_COLUMN}: not finite"))
            .when((alt < lo) | (alt > hi)).then(pl.lit(f"{CLEARED_ALT_COLUMN}: outside [{lo:g}, {hi:g}] m"))
            .when(pl.sum_horizontal(pl.col(c).is_null() for c in DEPARTURE_COLUMNS).is_between(1, 2))
            .then(pl.lit("departure_lat_deg/departure_lon_deg/departure_time: give all three or none"))
            .when(~pl.col("departure_lat_deg").is_between(-90.0, 90.0)
                  | ~pl.col("departure_lon_deg").is_between(-180.0, 180.0))
            .then(pl.lit("departure_lat_deg/departure_lon_deg: not a position on the globe"))
            .when(pl.col("departure_time") > pl.col("valid_to")).then(pl.lit("departure_time: after valid_to"))
            .otherwise(pl.lit(None, pl.String)))


def check_flight_plans(plans: pl.DataFrame, limits: Limits = Limits()) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(valid rows in :data:`FLIGHT_PLANS_SCHEMA`, ``rejects`` rows of the others with their
    reason). A missing required column or a value of the wrong type is a :class:`DataError` naming it."""
    missing = [c for c in _REQUIRED if c not in plans.columns]
    if missing:
        raise DataError(f"flight_plans: required column {missing[0]!r} is missing "
                        f"(have: {', '.join(plans.columns) or 'none'})")
    cols = []
    for c, t in FLIGHT_PLANS_SCHEMA.items():
        if c not in plans.columns:
            continue
        src = plans.schema[c]
        # text is never a time or a number here, nor a boolean a code: a wrong type is the table's error
        ok = (src == t or src == pl.Null or (t == pl.String() and src.is_integer())
              or (isinstance(t, pl.Datetime) and isinstance(src, pl.Datetime))
              or (t.is_numeric() and src.is_numeric()))
        if not ok:
            raise DataError(f"flight_plans: column {c!r} is {src}, expected {t}")
        try:
            cols.append(plans[c].cast(t))
        except (pl.exceptions.InvalidOperationError, pl.exceptions.ComputeError) as exc:
            raise DataError(f"flight_plans: column {c!r} does not fit {t} ({str(exc).splitlines()[0]})") from exc
    frame = pl.DataFrame(cols)
    frame = frame.with_columns(pl.lit(None, t).alias(c) for c, t in FLIGHT_PLANS_SCHEMA.items() if c not in frame.columns)
    frame = frame.with_row_index("row_index").with_columns(_reason(limits).alias("reason"))
    bad = frame.filter(pl.col("reason").is_not_null())
    good = frame.filter(pl.col("reason").is_null()).drop("row_index", "reason")
    given = [c for c in FLIGHT_PLANS_SCHEMA if c in plans.columns]
    return good.select(list(FLIGHT_PLANS_SCHEMA)), rejects_table(bad.select("row_index", *given, "reason"),
                                                                 "flight_plans", "validate")


def correlate(reports: pl.DataFrame, plans: pl.DataFrame) -> pl.DataFrame:
    """``reports`` with ``cleared_alt_m``: the level of the one flight plan holding the report's
    ``mode_3a`` at its ``time`` (and its ``run``, where the plan names one), null when none or
    several do, or the report has no code (module docstring). Rows and their order are kept."""
    if plans.height == 0 or "mode_3a" not in reports.columns or reports.height == 0:
        return reports.with_columns(pl.lit(None, pl.Float64).alias(CLEARED_ALT_COLUMN))
    run = pl.col("run").cast(pl.UInt32) if "run" in reports.columns else pl.lit(0, pl.UInt32)
    keys = (reports.select(run.alias("__run"), pl.col("mode_3a").cast(pl.String), pl.col("time"))
            .with_row_index("__i").drop_nulls("mode_3a"))
    hits = (keys.join(plans, on="mode_3a", how="inner")
            .filter((pl.col("time") >= pl.col("valid_from")) & (pl.col("time") <= pl.col("valid_to"))
                    & (pl.col("run").is_null() | (pl.col("run") == pl.col("__run"))))
            .group_by("__i").agg(pl.len().alias("__n"), pl.col(CLEARED_ALT_COLUMN).first())
            .filter(pl.col("__n") == 1).select("__i", CLEARED_ALT_COLUMN))
    out = (reports.drop(CLEARED_ALT_COLUMN, strict=False).with_row_index("__i")
           .join(hits, on="__i", how="left", maintain_order="left").drop("__i"))
    return out


@dataclass(frozen=True)
class DepartureConfig:
    """Departure correlation by aerodrome and time (module docstring; :func:`departure_step`).

    * ``radius_m``: the first coded plot lies within this horizontal distance of the aerodrome;
    * ``max_alt_m``: … below this pressure altitude (5 000 ft: a departure in its first minutes);
    * ``window_s``: … at most this long after the plan's ATD (the ATD is to the minute, the
      first plots follow lift-off by a scan or two);
    * ``max_gap_s``: a radar local track silent longer than this has ended (its number may be
      reused);
    * ``enabled``: False correlates by code only.
    """

    radius_m: float = 15_000.0
    max_alt_m: float = 1_524.0
    window_s: float = 180.0
    max_gap_s: float = 60.0
    enabled: bool = True

    def __post_init__(self) -> None:
        for name in ("radius_m", "max_alt_m", "window_s", "max_gap_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise ValueError(f"DepartureConfig.{name} must be a finite number > 0, got {v!r}")


_KEY = ["run", "radar_id", "local_track_id"]
_NEVER = np.iinfo(np.int64).max
_TRACKS = {"run": pl.UInt32, "radar_id": pl.UInt32, "local_track_id": pl.UInt32, "__last": pl.Int64,
           "__decided": pl.Boolean, "__plan": pl.Int64}


@dataclass(frozen=True)
class DepartureState:
    """What departure correlation carries across windows: per departure plan (its row in the
    valid ``flight_plans``) the first time its code was replied (µs; never: int64 max), the
    radar local tracks still alive (last report time, decided yet, plan taken) and which plans
    each radar's tracks have taken."""

    replied_us: dict = field(default_factory=dict)
    tracks: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema=_TRACKS))
    taken: frozenset = frozenset()


def init_departure_state() -> DepartureState:
    return DepartureState()


def departure_plans(plans: pl.DataFrame, frame) -> pl.DataFrame:
    """The plans that name a departure, with their row (``__plan``), run, ATD and validity in µs
    and their aerodrome in the system ``frame`` (east, north, m)."""
    if plans.height == 0 or "departure_time" not in plans.columns:
        return pl.DataFrame()
    dep = plans.with_row_index("__plan").with_columns(pl.col("__plan").cast(pl.Int64)).filter(
        pl.col("departure_time").is_not_null())
    if dep.height == 0:
        return pl.DataFrame()
    e, n, _ = frame.from_geodetic(dep["departure_lat_deg"].to_numpy(), dep["departure_lon_deg"].to_numpy(),
                                  np.zeros(dep.height))
    return dep.select("__plan", pl.col("run").alias("__prun"), "mode_3a",
                      pl.col("departure_time").dt.epoch("us").alias("__atd"),
                      pl.col("valid_from").dt.epoch("us").alias("__from"),
                      pl.col("valid_to").dt.epoch("us").alias("__to"),
                      pl.col(CLEARED_ALT_COLUMN).alias("__level"),
                      pl.Series("__ax", e), pl.Series("__ay", n))


def _replied(reports: pl.DataFrame, dep: pl.DataFrame, replied: dict) -> dict:
    """``replied`` updated with the first time each departure plan's code was replied in
    ``reports`` (at a time the plan holds it, in its run)."""
    if reports.height == 0 or "mode_3a" not in reports.columns:
        return replied
    run = pl.col("run").cast(pl.UInt32) if "run" in reports.columns else pl.lit(0, pl.UInt32)
    t = pl.col("time").dt.epoch("us")
    hits = (reports.select(run.alias("__run"), pl.col("mode_3a").cast(pl.String), t.alias("__t"))
            .drop_nulls("mode_3a").join(dep, on="mode_3a", how="inner")
            .filter(pl.col("__t").is_between(pl.col("__from"), pl.col("__to"))
                    & (pl.col("__prun").is_null() | (pl.col("__prun") == pl.col("__run"))))
            .group_by("__plan").agg(pl.col("__t").min()))
    out = dict(replied)
    for plan, t_us in hits.iter_rows():       # one row per departure plan replied in the window
        out[plan] = min(out.get(plan, _NEVER), t_us)
    return out


def departure_step(state: DepartureState, aligned: pl.DataFrame, reports: pl.DataFrame, codes: pl.DataFrame,
                   dep: pl.DataFrame, cfg: DepartureConfig = DepartureConfig()
                   ) -> tuple[pl.DataFrame, DepartureState]:
    """One window of departure correlation (module docstring): ``aligned`` with ``cleared_alt_m``
    filled from the departure plan its radar local track was paired with, and the carried state.

    ``reports``: the window's new reports (their codes mark plans replied); ``codes``: ``run``,
    ``report_id``, ``mode_3a`` of every report ``aligned`` refers to; ``dep``:
    :func:`departure_plans`. Rows and their order are kept."""
    if not cfg.enabled or dep.height == 0 or aligned.height == 0 or "local_track_id" not in aligned.columns:
        return aligned, state
    replied = _replied(reports, dep, state.replied_us)
    rows = (aligned.select(*(pl.col(k).cast(_TRACKS[k]) for k in _KEY), "report_id",
                           pl.col("time").dt.epoch("us").alias("__t"), "epoch", "x_m", "y_m",
                           pl.col("altitude_m") if "altitude_m" in aligned.columns else pl.lit(None, pl.Float64)
                           .alias("altitude_m"), CLEARED_ALT_COLUMN)
            .with_row_index("__i")
            .join(codes.select(pl.col("run").cast(_TRACKS["run"]), "report_id", pl.col("mode_3a").cast(pl.String)),
                  on=["run", "report_id"], how="left")
            .join(state.tracks, on=_KEY, how="left")
            .sort(*_KEY, "__t", "epoch", "__i"))
    prev_t = pl.col("__t").shift(1).over(_KEY)
    gap = pl.col("__t") - pl.coalesce(prev_t, pl.col("__last"))
    rows = rows.with_columns(
        (gap.is_null() | (gap > int(cfg.max_gap_s * 1e6))).alias("__new")).with_columns(
        pl.col("__new").cum_sum().over(_KEY).alias("__seg"))
    # a segment that continues a carried track keeps its decision and plan
    carried = (pl.col("__seg") == 0) & pl.col("__last").is_not_null()
    rows = rows.with_columns(pl.when(carried).then(pl.col("__decided")).otherwise(False).alias("__decided"),
                             pl.when(carried).then(pl.col("__plan")).otherwise(None).alias("__plan"))
    seg = [*_KEY, "__seg"]
    # a plot without a local track number belongs to no track: it never decides
    coded = pl.col("mode_3a").is_not_null() & pl.col("altitude_m").is_not_null() & pl.col("local_track_id").is_not_null()
    first = (rows.filter(~pl.col("__decided") & coded).group_by(seg).agg(pl.all().sort_by("__t", "epoch", "__i")
                                                                            .first()))
    cand = first.filter(pl.col(CLEARED_ALT_COLUMN).is_null())
    chosen, taken = _choose(cand, dep, replied, state.taken, cfg)
    decided = first.select(*seg, pl.col("__t").alias("__t_dec")).join(chosen, on=seg, how="left")
    rows = (rows.join(decided, on=seg, how="left")
            .with_columns(pl.when(pl.col("__t_dec").is_not_null() & (pl.col("__t") >= pl.col("__t_dec")))
                          .then(pl.col("__chosen")).otherwise(pl.col("__plan")).alias("__plan"),
                          (pl.col("__decided") | (pl.col("__t_dec").is_not_null()
                                                  & (pl.col("__t") >= pl.col("__t_dec")))).alias("__decided"))
            .join(dep.select("__plan", "__level", "__to"), on="__plan", how="left")
            .with_columns(pl.when(pl.col("__t") <= pl.col("__to")).then(pl.col("__level")).alias("__level")))
    fill = rows.select("__i", "__level").sort("__i")["__level"]
    out = aligned.with_columns(pl.col(CLEARED_ALT_COLUMN).fill_null(fill))
    last = rows.drop_nulls(_KEY).group_by(_KEY).agg(pl.col("__t").max().alias("__last"),
                                   pl.col("__decided").sort_by("__t", "epoch", "__i").last(),
                                   pl.col("__plan").sort_by("__t", "epoch", "__i").last())
    t_max = int(rows["__t"].max())
    # a track silent for longer than the gap has ended; the margin covers reports held back by alignment
    keep = pl.col("__last") >= t_max - int((cfg.max_gap_s + 600.0) * 1e6)
    tracks = (pl.concat([state.tracks.join(last, on=_KEY, how="anti"), last.select(list(_TRACKS))])
              .filter(keep).cast(_TRACKS))
    return out, DepartureState(replied, tracks, taken)


def _choose(cand: pl.DataFrame, dep: pl.DataFrame, replied: dict, taken: frozenset, cfg: DepartureConfig
            ) -> tuple[pl.DataFrame, frozenset]:
    """The plan each candidate track segment (its first coded plot, uncorrelated by code) takes:
    the one departure plan that qualifies (module docstring), in time order so that an earlier
    track of a radar takes a plan first. Candidates are the rare uncorrelated plots near an
    aerodrome: the loop is over those few, never over reports."""
    seg = [*_KEY, "__seg"]
    empty = pl.DataFrame(schema={**{k: cand.schema[k] for k in seg}, "__chosen": pl.Int64})
    if cand.height == 0:
        return empty, taken
    pairs = (cand.select(*seg, "__t", "x_m", "y_m", "altitude_m").join(dep, how="cross")
             .filter((pl.col("__prun").is_null() | (pl.col("__prun") == pl.col("run")))
                     & (pl.col("__t") >= pl.col("__atd")) & (pl.col("__t") <= pl.col("__atd") + int(cfg.window_s * 1e6))
                     & (pl.col("__t") <= pl.col("__to"))
                     & ((pl.col("x_m") - pl.col("__ax")) ** 2 + (pl.col("y_m") - pl.col("__ay")) ** 2
                        <= cfg.radius_m ** 2)
                     & (pl.col("altitude_m") <= cfg.max_alt_m)))
    if pairs.height == 0:
        return empty, taken
    pairs = pairs.with_columns(pl.col("__plan").replace_strict(replied, default=_NEVER, return_dtype=pl.Int64)
                               .alias("__replied")).filter(pl.col("__replied") >= pl.col("__t"))
    out, now = [], set(taken)
    for key, group in pairs.sort("__t", *seg).group_by(seg, maintain_order=True):
        run, radar = key[0], key[1]
        free = [p for p in group["__plan"].unique().to_list() if (run, radar, p) not in now]
        if len(free) == 1:                   # an ambiguous correlation is no correlation
            now.add((run, radar, free[0]))
            out.append((*key, free[0]))
    return (pl.DataFrame(out, schema=empty.schema, orient="row") if out else empty), frozenset(now)
