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
* ``run`` (optional; absent: every run of a Monte-Carlo dataset), ``callsign`` (optional).

A row with a missing or malformed code, a level outside the altitude band, a missing or
reversed validity interval goes to ``rejects`` (input table ``flight_plans``) with its reason
(:func:`check_flight_plans`).

Correlation (:func:`correlate`): a report gets the cleared level of the one flight plan that
holds the code it replied with at its time. None, or more than one (a code assigned to two
flights at once), gives null: an ambiguous correlation is no correlation. A report without a
code gets null. The level then travels reports → aligned → fused (the target's newest) →
tracks (``cleared_alt_m``, :data:`tertiary.schema.CLEARED_ALT_COLUMN`), where conflict
prediction stops a climb or descent at it when no selected level is known
(:mod:`safety.conflicts`, "Selected level").
"""

from __future__ import annotations

import polars as pl

from tertiary.schema import CLEARED_ALT_COLUMN, Limits, TIME, rejects_table

__all__ = ["FLIGHT_PLANS_SCHEMA", "check_flight_plans", "correlate", "empty_flight_plans"]

#: the ``flight_plans`` input table (``run`` and ``callsign`` optional)
FLIGHT_PLANS_SCHEMA: dict[str, pl.DataType] = {
    "run": pl.UInt32(), "mode_3a": pl.String(), "callsign": pl.String(), "valid_from": TIME, "valid_to": TIME,
    CLEARED_ALT_COLUMN: pl.Float64(),
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
            .otherwise(pl.lit(None, pl.String)))


def check_flight_plans(plans: pl.DataFrame, limits: Limits = Limits()) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(valid rows in :data:`FLIGHT_PLANS_SCHEMA`, ``rejects`` rows of the others with their
    reason). A missing required column or a value of the wrong type is a :class:`DataError` naming it."""
    from tertiary.errors import DataError
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
    frame = frame.with_row_index("row_index").with_columns(_reason(limits).alias("reason"))
    bad = frame.filter(pl.col("reason").is_not_null())
    good = frame.filter(pl.col("reason").is_null()).drop("row_index", "reason")
    good = good.with_columns(pl.lit(None, t).alias(c) for c, t in FLIGHT_PLANS_SCHEMA.items() if c not in good.columns)
    return good.select(list(FLIGHT_PLANS_SCHEMA)), rejects_table(bad, "flight_plans", "validate")


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
