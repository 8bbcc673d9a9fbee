"""The ``rejects`` table: rows that broke the contract, packed with their reason and the rejected
row as JSON."""

from __future__ import annotations

import polars as pl

from tertiary.contract.errors import SchemaError
from tertiary.contract.tables import REASON, ROW_INDEX, TABLES

__all__ = ["has_dtype", "rejects_table"]


def has_dtype(dtype: pl.DataType, kinds: tuple[type, ...]) -> bool:
    """Whether ``dtype`` is, or nests (list, array, struct field), one of the dtype classes ``kinds``."""
    if isinstance(dtype, kinds):
        return True
    if isinstance(dtype, (pl.List, pl.Array)):
        return has_dtype(dtype.inner, kinds)
    if isinstance(dtype, pl.Struct):
        return any(has_dtype(f.dtype, kinds) for f in dtype.fields)
    return False


def _json_expr(col: pl.Expr, dtype: pl.DataType, finite: bool) -> pl.Expr:
    """``col`` in a dtype the JSON writer handles: it panics on Binary and cannot write Object
    values, and JSON has no NaN (temporal, decimal and the rest it writes natively)."""
    if dtype.is_float():
        return col if finite else col.cast(pl.String)
    if dtype == pl.Binary:
        return col.bin.encode("hex")
    if isinstance(dtype, (pl.List, pl.Array)) and dtype.inner.is_float() and not finite:
        return col.cast(pl.List(dtype.inner)).list.eval(pl.element().cast(pl.String))
    if has_dtype(dtype, (pl.Binary, pl.Object)):
        return pl.lit(f"<{dtype}>")
    return col


def _all_finite(series: pl.Series) -> bool:
    """No NaN/inf anywhere in a float (or list/array of float) column."""
    dtype = series.dtype
    if isinstance(dtype, (pl.List, pl.Array)) and dtype.inner.is_float():
        series = series.cast(pl.List(dtype.inner)).explode()
    elif not dtype.is_float():
        return True
    return bool(series.drop_nulls().is_finite().all())


def _json_safe(frame: pl.DataFrame) -> list[pl.Expr]:
    """Columns for JSON: every dtype made writable (binary as hex, durations as µs, temporal and
    decimal as text); floats holding NaN/inf become strings (JSON has no NaN)."""
    return [
        _json_expr(pl.col(name), dtype, _all_finite(frame[name])).alias(name)
        for name, dtype in frame.schema.items()
    ]


def rejects_table(rejects: pl.DataFrame, table: str, stage: str) -> pl.DataFrame:
    """Pack ``validate()`` rejects into the canonical ``rejects`` schema.

    ``detail`` is the rejected row (all its columns except ``row_index`` and
    ``reason``) as a JSON object; NaN/inf floats are written as strings.
    """
    missing = [c for c in (ROW_INDEX, REASON) if c not in rejects.columns]
    if missing:
        raise SchemaError(
            f"rejects: required column '{missing[0]}' is missing "
            f"(have: {', '.join(rejects.columns)})",
            table="rejects",
            column=missing[0],
            problem="missing column",
        )
    body = rejects.drop(ROW_INDEX, REASON)
    detail = (
        pl.struct(_json_safe(body)).struct.json_encode() if body.width else pl.lit("{}")
    )
    report_id = pl.col("report_id") if "report_id" in rejects.columns else pl.lit(None)
    out = rejects.select(
        pl.lit(table).alias("input_table"),
        pl.lit(stage).alias("stage"),
        report_id.cast(pl.UInt64).alias("report_id"),
        pl.col(ROW_INDEX).cast(pl.UInt64),
        pl.col(REASON).cast(pl.String),
        detail.alias("detail"),
    )
    return out.cast(TABLES["rejects"].required)
