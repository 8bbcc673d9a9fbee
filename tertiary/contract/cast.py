"""Casting an input column to its contract dtype: the values that cannot be cast become null and
are flagged (the caller turns them into rejects), a column that cannot be cast at all raises."""

from __future__ import annotations

import polars as pl

from tertiary.contract.errors import SchemaError
from tertiary.contract.tables import TIME

__all__ = ["cast_column", "dtype_label"]

_ISO_FORMATS = (
    "%Y-%m-%dT%H:%M:%S%.f%#z",
    "%Y-%m-%dT%H:%M:%S%.f",
    "%Y-%m-%dT%H:%M%#z",
    "%Y-%m-%dT%H:%M",
    "%Y-%m-%d",
)


def dtype_label(dtype: pl.DataType) -> str:
    """A dtype as reasons name it (time zone and array size spelled out)."""
    if isinstance(dtype, pl.Datetime):
        tz = f", {dtype.time_zone}" if dtype.time_zone else ""
        return f"Datetime[{dtype.time_unit}{tz}]"
    if isinstance(dtype, pl.Array):
        return f"Array({dtype_label(dtype.inner)}, {dtype.size})"
    return str(dtype)


def _parse_iso(s: pl.Series) -> pl.Series:
    """Parse ISO-8601 strings to UTC datetimes; naive strings are UTC."""
    text = s.str.strip_chars().str.replace(" ", "T", literal=True)
    parsed = [
        text.str.to_datetime(fmt, time_unit="us", time_zone="UTC", strict=False)
        for fmt in _ISO_FORMATS
    ]
    return pl.select(pl.coalesce(parsed)).to_series().alias(s.name)


def _to_time(s: pl.Series, table: str) -> pl.Series:
    if isinstance(s.dtype, pl.Datetime):
        if s.dtype.time_zone is None:
            s = s.dt.replace_time_zone("UTC")
        return s.dt.convert_time_zone("UTC").dt.cast_time_unit("us")
    if s.dtype == pl.String:
        return _parse_iso(s)
    if s.dtype == pl.Null:
        return s.cast(TIME)
    hint = (
        f" (hint: epoch seconds can be converted with "
        f"pl.from_epoch('{s.name}', time_unit='s'))"
        if s.dtype.is_numeric()
        else ""
    )
    raise SchemaError(
        f"{table}: column '{s.name}' has dtype {s.dtype}; expected Datetime "
        f"or ISO-8601 strings{hint}",
        table=table,
        column=s.name,
        problem="uncastable dtype",
    )


def _to_array(s: pl.Series, dtype: pl.Array) -> pl.Series:
    """Cast list/array values; rows of the wrong width or with null items become null."""
    if s.dtype == pl.Null:
        return s.cast(dtype)
    items = s.cast(pl.List(dtype.inner), strict=False)
    wrong = items.list.drop_nulls().list.len() != dtype.size
    return pl.select(pl.when(wrong).then(None).otherwise(items)).to_series().cast(dtype)


def _castable(src: pl.DataType, dtype: pl.DataType) -> bool:
    """Source dtypes accepted for a target dtype (polars would cast more, silently: a Boolean
    to 0/1, a Date to days, a Struct to a Struct of numbers)."""
    if src == pl.Null or src == dtype:
        return True
    if dtype.is_numeric():
        return (src.is_numeric() and src != pl.Boolean) or src == pl.String
    if dtype == pl.String:
        return src.is_numeric() or isinstance(src, (pl.Categorical, pl.Enum))
    if dtype == pl.Boolean:
        return src == pl.String
    if isinstance(dtype, (pl.List, pl.Array)):
        return isinstance(src, (pl.List, pl.Array)) and _castable(src.inner, dtype.inner)
    return True


def _cast_values(s: pl.Series, dtype: pl.DataType, table: str) -> pl.Series:
    if isinstance(dtype, pl.Datetime):
        return _to_time(s, table)
    if not _castable(s.dtype, dtype):
        raise pl.exceptions.InvalidOperationError(f"{s.dtype} to {dtype}")
    if isinstance(dtype, pl.Array):
        return _to_array(s, dtype)
    if s.dtype == pl.String and dtype != pl.String:
        s = s.str.strip_chars()
    return s.cast(dtype, strict=False)


def cast_column(s: pl.Series, dtype: pl.DataType, table: str) -> tuple[pl.Series, pl.Series]:
    """Cast ``s`` to ``dtype``; also return a mask of values the cast lost."""
    if s.dtype == dtype:
        return s, pl.repeat(False, len(s), eager=True)
    try:
        out = _cast_values(s, dtype, table)
    except pl.exceptions.PolarsError as exc:
        raise SchemaError(
            f"{table}: column '{s.name}' has dtype {s.dtype} which cannot be "
            f"cast to {dtype_label(dtype)}",
            table=table,
            column=s.name,
            problem="uncastable dtype",
        ) from exc
    lost = s.is_not_null() & out.is_null()
    if dtype.is_integer() and s.dtype.is_float():
        lost = lost | (s.is_not_null() & (s != s.floor()).fill_null(False))
    return out.alias(s.name), lost.fill_null(False)


