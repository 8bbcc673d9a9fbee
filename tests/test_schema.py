"""Tests of the data contract in ``tertiary.contract``."""

from __future__ import annotations

import json
import math
import warnings
from datetime import datetime, timedelta, timezone

import polars as pl
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tertiary.contract import (TABLES, Limits, SchemaError, TableSchema, UnsortedTimeWarning, empty_frame, rejects_table, validate)

T0 = datetime(2024, 3, 1, 12, 0, 0, tzinfo=timezone.utc)
UTC_US = pl.Datetime("us", "UTC")


def reports(n: int = 4, **overrides: list) -> pl.DataFrame:
    """A valid reports frame: one track per radar, 4 s scans."""
    data = {
        "radar_id": [1 + i % 2 for i in range(n)],
        "time": [T0 + timedelta(seconds=4 * (i // 2)) for i in range(n)],
        "local_track_id": [10 + i % 2 for i in range(n)],
        "range_m": [50_000.0 + 100 * i for i in range(n)],
        "azimuth_deg": [45.0 + i for i in range(n)],
    }
    data.update(overrides)
    return pl.DataFrame(data)


def radars(**overrides: list) -> pl.DataFrame:
    data = {
        "radar_id": [1, 2],
        "name": ["north", "south"],
        "lat_deg": [50.0, 49.0],
        "lon_deg": [4.0, 5.0],
        "alt_m": [100.0, 200.0],
        "scan_period_s": [4.0, 5.0],
        "sigma_range_m": [50.0, 60.0],
        "sigma_azimuth_deg": [0.05, 0.06],
        "sigma_elevation_deg": [0.1, 0.1],
        "max_range_m": [250_000.0, 250_000.0],
    }
    data.update(overrides)
    return pl.DataFrame(data)


def truth(**overrides: list) -> pl.DataFrame:
    data = {
        "truth_id": [1, 1, 2],
        "time": [T0, T0 + timedelta(seconds=1), T0],
        **{c: [0.0, 1.0, 2.0] for c in ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")},
    }
    data.update(overrides)
    return pl.DataFrame(data)


def lenient(frame: pl.DataFrame, kind: str = "reports", **kw) -> tuple[pl.DataFrame, pl.DataFrame]:
    out = validate(frame, kind, strict=False, **kw)
    assert isinstance(out, tuple)
    return out


def reasons(rejects: pl.DataFrame) -> list[str]:
    return rejects["reason"].to_list()


# --------------------------------------------------------------------------- schemas


def test_tables_cover_all_kinds() -> None:
    expected = {
        "radars", "reports", "truth", "aligned", "associations", "fused",
        "clusters", "tracks", "conflicts", "alerts", "rejects", "metrics", "run",
    }
    assert set(TABLES) == expected
    for name, schema in TABLES.items():
        assert isinstance(schema, TableSchema) and schema.name == name
        assert not set(schema.required) & set(schema.optional)
        assert set(schema.key) <= set(schema.required) | {"run"}


def test_schema_is_frozen() -> None:
    with pytest.raises(AttributeError):
        TABLES["reports"].name = "other"  # type: ignore[misc]


def test_key_dtypes() -> None:
    rep = TABLES["reports"]
    assert rep.required["time"] == UTC_US
    assert rep.optional["est_cov"] == pl.Array(pl.Float64, 36)
    assert TABLES["fused"].required["radar_ids"] == pl.List(pl.UInt32)
    assert TABLES["tracks"].required["cov_diag"] == pl.Array(pl.Float64, 6)
    assert TABLES["conflicts"].required["alert"] == pl.Boolean


@pytest.mark.parametrize("kind", sorted(TABLES))
def test_empty_frame(kind: str) -> None:
    schema = TABLES[kind]
    full = empty_frame(kind)
    assert full.height == 0 and dict(full.schema) == schema.columns
    assert list(empty_frame(kind, optional=False).columns) == list(schema.required)
    clean, rejects = lenient(full, kind)
    assert clean.height == 0 and rejects.height == 0


def test_unknown_kind() -> None:
    with pytest.raises(ValueError, match="unknown table kind 'bogus'"):
        validate(reports(), "bogus")


# --------------------------------------------------------------------------- good input


def test_good_frame_passes_unchanged() -> None:
    frame = reports(6).with_columns(
        pl.col("radar_id").cast(pl.UInt32),
        pl.col("local_track_id").cast(pl.UInt32),
        report_id=pl.int_range(6, dtype=pl.UInt64),
        run=pl.lit(0, pl.UInt32),
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        clean = validate(frame, "reports", radars=radars())
    assert clean.equals(frame)
    assert dict(clean.schema) == dict(frame.schema)


def test_good_frame_is_cast_to_schema() -> None:
    clean, rejects = lenient(reports(6))
    assert rejects.height == 0 and clean.height == 6
    schema = TABLES["reports"].columns
    assert all(clean.schema[c] == schema[c] for c in clean.columns)


def test_report_id_assigned_from_row_position() -> None:
    clean = validate(reports(5), "reports")
    assert clean["report_id"].dtype == pl.UInt64
    assert clean["report_id"].to_list() == [0, 1, 2, 3, 4]
    assert clean["run"].to_list() == [0] * 5


def test_given_report_id_is_kept_and_must_be_unique() -> None:
    clean, rejects = lenient(reports(3, report_id=[7, 7, 9]))
    assert clean["report_id"].to_list() == [7, 9]
    assert reasons(rejects) == ["report_id: duplicate value 7"]
    assert rejects["row_index"].to_list() == [1]


def test_null_given_report_id_rejected() -> None:
    clean, rejects = lenient(reports(2, report_id=[5, None]))
    assert clean["report_id"].to_list() == [5]
    assert reasons(rejects) == ["report_id: null"]


def test_null_run_means_run_0() -> None:
    clean = validate(reports(2, run=[None, 1]), "reports")
    assert clean["run"].to_list() == [0, 1]


def test_column_order_and_extra_columns() -> None:
    frame = reports(2, note=["a", "b"], altitude_m=[1000.0, 2000.0]).select(
        "note", "altitude_m", "azimuth_deg", "range_m", "local_track_id", "time", "radar_id"
    )
    clean = validate(frame, "reports")
    assert clean.columns == [
        "radar_id", "time", "local_track_id", "range_m", "azimuth_deg",
        "report_id", "run", "altitude_m", "note",
    ]


def test_numeric_strings_cast() -> None:
    clean = validate(reports(2, range_m=["123.4", " 5e3 "], radar_id=["1", "2"]), "reports")
    assert clean["range_m"].to_list() == [123.4, 5000.0]
    assert clean["radar_id"].dtype == pl.UInt32


def test_time_accepts_iso_strings_and_any_datetime() -> None:
    strings = ["2024-03-01T12:00:00Z", "2024-03-01 12:00:04", "2024-03-01T14:00:08+02:00",
               "2024-03-01T12:00:12.500"]
    clean = validate(reports(4, radar_id=[1] * 4, local_track_id=[1] * 4, time=strings), "reports")
    assert clean["time"].dtype == UTC_US
    assert clean["time"].to_list() == [T0 + timedelta(seconds=s) for s in (0, 4, 8, 12.5)]
    ns_paris = reports(2).with_columns(
        pl.col("time").dt.convert_time_zone("Europe/Paris").dt.cast_time_unit("ns")
    )
    naive = reports(2).with_columns(pl.col("time").dt.replace_time_zone(None))
    for frame in (ns_paris, naive):
        out = validate(frame, "reports")
        assert out["time"].dtype == UTC_US
        assert out["time"].to_list() == reports(2)["time"].to_list()


def test_nan_allowed_in_optional_estimates() -> None:
    frame = reports(2, est_range_m=[math.nan, 1.0], elevation_deg=[math.nan, None])
    clean, rejects = lenient(frame)
    assert rejects.height == 0 and clean.height == 2


def test_est_cov_list_cast_to_array() -> None:
    frame = reports(2, est_cov=[[0.0] * 36, [1.0] * 35])
    clean, rejects = lenient(frame)
    assert clean["est_cov"].dtype == pl.Array(pl.Float64, 36)
    assert clean.height == 1
    (reason,) = reasons(rejects)
    assert reason.startswith("est_cov: cannot cast [1.0, 1.0")
    assert reason.endswith("to Array(Float64, 36)")


# --------------------------------------------------------------------------- table-level errors


@pytest.mark.parametrize("strict", [True, False])
def test_missing_required_column(strict: bool) -> None:
    with pytest.raises(SchemaError, match=r"reports: required column 'range_m' is missing \(have: radar_id, time") as err:
        validate(reports().drop("range_m"), "reports", strict=strict)
    assert err.value.table == "reports" and err.value.column == "range_m"
    assert err.value.problem == "missing column"


def test_missing_several_columns() -> None:
    with pytest.raises(SchemaError, match="required columns 'range_m', 'azimuth_deg' are missing"):
        validate(reports().drop("range_m", "azimuth_deg"), "reports", strict=False)


@pytest.mark.parametrize("strict", [True, False])
def test_uncastable_dtype_column(strict: bool) -> None:
    frame = reports(2, range_m=[[1.0], [2.0]])
    with pytest.raises(SchemaError, match=r"column 'range_m' has dtype List\(Float64\) which cannot be cast to Float64") as err:
        validate(frame, "reports", strict=strict)
    assert err.value.column == "range_m" and err.value.problem == "uncastable dtype"


@pytest.mark.parametrize("strict", [True, False])
def test_integer_time_rejected_with_hint(strict: bool) -> None:
    frame = reports(2, time=[1_700_000_000, 1_700_000_004])
    with pytest.raises(SchemaError, match=r"'time' has dtype Int64; expected Datetime or ISO-8601 strings \(hint: .*pl.from_epoch"):
        validate(frame, "reports", strict=strict)


def test_datetime_into_float_column_is_uncastable() -> None:
    with pytest.raises(SchemaError, match="'range_m' has dtype Datetime"):
        validate(reports(2, range_m=[T0, T0]), "reports")


# --------------------------------------------------------------------------- row-level problems


def test_partially_uncastable_strings_lenient() -> None:
    frame = reports(4, range_m=["123.4", "1000", "abc", "12 km"])
    clean, rejects = lenient(frame)
    assert clean["range_m"].to_list() == [123.4, 1000.0]
    assert reasons(rejects) == [
        "range_m: cannot cast 'abc' to Float64",
        "range_m: cannot cast '12 km' to Float64",
    ]
    assert rejects["row_index"].to_list() == [2, 3]
    assert rejects["report_id"].to_list() == [2, 3]
    assert rejects["range_m"].to_list() == ["abc", "12 km"]  # original values


def test_partially_uncastable_strings_strict() -> None:
    frame = reports(4, range_m=["123.4", "1000", "abc", "12 km"])
    with pytest.raises(SchemaError) as err:
        validate(frame, "reports")
    msg = str(err.value)
    assert "reports: column 'range_m': cannot cast to Float64 in 2 row(s)" in msg
    assert "row 2: range_m='abc'" in msg and "row 3: range_m='12 km'" in msg
    assert err.value.rows == [2, 3] and err.value.column == "range_m"


def test_strict_prints_at_most_five_examples() -> None:
    frame = reports(8, range_m=[-1.0] * 8)
    with pytest.raises(SchemaError) as err:
        validate(frame, "reports")
    assert str(err.value).count("row ") == 5
    assert err.value.rows == list(range(8))


def test_fractional_id_is_a_cast_failure() -> None:
    clean, rejects = lenient(reports(2, radar_id=[1.0, 1.5]))
    assert clean["radar_id"].to_list() == [1]
    assert reasons(rejects) == ["radar_id: cannot cast 1.5 to UInt32"]


def test_bad_time_string() -> None:
    clean, rejects = lenient(reports(2, time=["2024-03-01T12:00:00Z", "yesterday"]))
    assert reasons(rejects) == ["time: cannot cast 'yesterday' to Datetime[us, UTC]"]


def test_null_required() -> None:
    frame = reports(3, range_m=[1.0, None, 3.0])
    clean, rejects = lenient(frame)
    assert reasons(rejects) == ["range_m: null"] and clean.height == 2
    with pytest.raises(SchemaError, match=r"column 'range_m': null in 1 row\(s\); e.g. row 1: range_m=None"):
        validate(frame, "reports")


def test_nan_required() -> None:
    frame = reports(3, azimuth_deg=[1.0, math.nan, 3.0])
    _, rejects = lenient(frame)
    assert reasons(rejects) == ["azimuth_deg: NaN"]
    with pytest.raises(SchemaError, match=r"column 'azimuth_deg': NaN in 1 row\(s\); e.g. row 1: azimuth_deg=nan"):
        validate(frame, "reports")


def test_nan_string_required() -> None:
    _, rejects = lenient(reports(2, range_m=["NaN", "1"]))
    assert reasons(rejects) == ["range_m: NaN"]


def test_inf_required() -> None:
    frame = reports(3, range_m=[1.0, math.inf, -math.inf])
    _, rejects = lenient(frame)
    assert reasons(rejects) == [
        "range_m: infinite value inf",
        "range_m: infinite value -inf",
    ]
    with pytest.raises(SchemaError, match="column 'range_m': infinite value in 2 row"):
        validate(frame, "reports")


def test_non_positive_range() -> None:
    """A range of zero is a decoding error too: the contract is (0, max_range x margin]."""
    frame = reports(3, range_m=[1.0, -12.0, 0.0])
    clean, rejects = lenient(frame)
    assert reasons(rejects) == ["range_m: non-positive value -12.0", "range_m: non-positive value 0.0"]
    assert clean["range_m"].to_list() == [1.0]
    with pytest.raises(SchemaError, match=r"column 'range_m': non-positive value in 2 row\(s\); e.g. row 1: range_m=-12.0"):
        validate(frame, "reports")


def test_range_limit_configurable() -> None:
    _, rejects = lenient(reports(2, range_m=[1.0, 600_000.0]), limits=Limits(range_m=(0.0, 500_000.0)))
    assert reasons(rejects) == ["range_m: outside (0, 500000], got 600000.0"]


@pytest.mark.parametrize("azimuth", [360.0, -1.0, 720.5])
def test_azimuth_outside(azimuth: float) -> None:
    frame = reports(2, azimuth_deg=[359.999, azimuth])
    clean, rejects = lenient(frame)
    assert clean["azimuth_deg"].to_list() == [359.999]
    assert reasons(rejects) == [f"azimuth_deg: outside [0, 360), got {azimuth}"]
    with pytest.raises(SchemaError, match=r"column 'azimuth_deg': outside \[0, 360\) in 1 row"):
        validate(frame, "reports")


def test_elevation_outside() -> None:
    _, rejects = lenient(reports(2, elevation_deg=[1.0, 95.0]))
    assert reasons(rejects) == ["elevation_deg: outside [-90, 90], got 95.0"]


def test_altitude_glitch() -> None:
    frame = reports(3, altitude_m=[10_000.0, 37_520.0, None])  # 123 100 ft
    clean, rejects = lenient(frame)
    assert reasons(rejects) == ["altitude_m: outside [-500, 20000], got 37520.0"]
    assert clean["altitude_m"].to_list() == [10_000.0, None]
    with pytest.raises(SchemaError, match="altitude_m=37520.0"):
        validate(frame, "reports")
    wide = validate(frame, "reports", limits=Limits(altitude_m=(-500.0, 40_000.0)))
    assert wide.height == 3


def test_unknown_radar() -> None:
    frame = reports(3, radar_id=[1, 9, 2])
    clean, rejects = lenient(frame, radars=radars())
    assert reasons(rejects) == ["radar_id: unknown radar 9"]
    assert clean["radar_id"].to_list() == [1, 2]
    with pytest.raises(SchemaError, match=r"column 'radar_id': unknown radar in 1 row\(s\); e.g. row 1: radar_id=9"):
        validate(frame, "reports", radars=radars())
    assert validate(frame, "reports").height == 3  # no radars frame, no check


def test_several_problems_joined() -> None:
    frame = reports(2, range_m=[1.0, -5.0], azimuth_deg=[1.0, 400.0])
    _, rejects = lenient(frame)
    assert reasons(rejects) == [
        "range_m: non-positive value -5.0; azimuth_deg: outside [0, 360), got 400.0"
    ]


def test_duplicates_keep_first() -> None:
    frame = pl.concat([reports(3), reports(3).slice(0, 1)])
    clean, rejects = lenient(frame)
    assert clean["report_id"].to_list() == [0, 1, 2]
    assert reasons(rejects) == [
        "duplicate of report_id 0 (run, radar_id, local_track_id, time)"
    ]
    assert rejects["row_index"].to_list() == [3]
    with pytest.raises(SchemaError, match=r"column 'run, radar_id, local_track_id, time': duplicate .* in 1 row") as err:
        validate(frame, "reports")
    assert err.value.rows == [3]


def test_duplicates_in_other_runs_are_not_duplicates() -> None:
    frame = pl.concat([reports(2), reports(2)]).with_columns(run=pl.Series([0, 0, 1, 1]))
    assert validate(frame, "reports").height == 4


def test_good_row_not_rejected_as_copy_of_bad_row() -> None:
    bad_first = reports(2, range_m=[-1.0, 5.0], time=[T0, T0], radar_id=[1, 1], local_track_id=[1, 1])
    clean, rejects = lenient(bad_first)
    assert clean["range_m"].to_list() == [5.0]
    assert reasons(rejects) == ["range_m: non-positive value -1.0"]


# --------------------------------------------------------------------------- ordering


def test_unsorted_times_are_sorted_with_warning() -> None:
    frame = reports(6).reverse()
    with pytest.warns(UnsortedTimeWarning, match=r"reports: time out of order in 2 of 2 tracks; sorted by \(run, radar_id, local_track_id, time\)"):
        clean, rejects = lenient(frame)
    assert rejects.height == 0 and clean.height == 6
    assert clean.equals(clean.sort("run", "radar_id", "local_track_id", "time"))


def test_sorted_tracks_keep_input_order() -> None:
    frame = reports(6)  # interleaved tracks, each in time order
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        clean = validate(frame, "reports")
    assert clean["report_id"].to_list() == list(range(6))


# --------------------------------------------------------------------------- radars and truth


def test_radars_good() -> None:
    clean = validate(radars(), "radars")
    assert clean["radar_id"].dtype == pl.UInt32 and clean.height == 2


def test_latitude_91() -> None:
    frame = radars(lat_deg=[91.0, 49.0])
    clean, rejects = lenient(frame, "radars")
    assert reasons(rejects) == ["lat_deg: outside [-90, 90], got 91.0"]
    assert "report_id" not in rejects.columns and rejects["row_index"].to_list() == [0]
    with pytest.raises(SchemaError, match=r"radars: column 'lat_deg': outside \[-90, 90\] in 1 row\(s\); e.g. row 0: lat_deg=91.0"):
        validate(frame, "radars")


def test_radar_checks() -> None:
    frame = radars(
        radar_id=[1, 1],
        scan_period_s=[0.0, 4.0],
        sigma_range_m=[50.0, -1.0],
        lon_deg=[4.0, 181.0],
        timing=["rotating", "phased"],
    )
    _, rejects = lenient(frame, "radars")
    assert reasons(rejects) == [
        "scan_period_s: outside [0.1, 60], got 0.0",
        "lon_deg: outside [-180, 180], got 181.0; sigma_range_m: outside (0, 10000], got -1.0; "
        "timing: invalid value 'phased', expected one of rotating, synchronous",
    ]


def test_duplicate_radar_id() -> None:
    _, rejects = lenient(radars(radar_id=[3, 3]), "radars")
    assert reasons(rejects) == ["duplicate of row_index 0 (radar_id)"]


def test_truth_duplicates_and_order() -> None:
    frame = pl.concat([truth(), truth().slice(1, 1)])
    clean, rejects = lenient(frame, "truth")
    assert reasons(rejects) == ["duplicate of row_index 1 (truth_id, time)"]
    with pytest.warns(UnsortedTimeWarning, match="truth: time out of order in 1 of 2"):
        sorted_ = validate(truth().reverse(), "truth")
    assert sorted_["truth_id"].to_list() == [1, 1, 2]


# --------------------------------------------------------------------------- rejects table


def test_rejects_table_canonical_schema() -> None:
    frame = reports(3, range_m=["1", "-12", "x"], azimuth_deg=[1.0, math.nan, 2.0])
    _, rejects = lenient(frame)
    packed = rejects_table(rejects, "reports", "ingest")
    assert dict(packed.schema) == TABLES["rejects"].columns
    assert packed["input_table"].to_list() == ["reports", "reports"]
    assert packed["stage"].to_list() == ["ingest", "ingest"]
    assert packed["report_id"].to_list() == [1, 2]
    assert packed["row_index"].to_list() == [1, 2]
    assert packed["reason"].to_list() == reasons(rejects)
    detail = json.loads(packed["detail"][0])
    assert detail["range_m"] == "-12" and detail["azimuth_deg"] == "NaN"
    assert detail["time"].startswith("2024-03-01T12:00:00")
    assert validate(packed, "rejects").height == 2


def test_rejects_table_without_report_id() -> None:
    _, rejects = lenient(radars(lat_deg=[91.0, 1.0]), "radars")
    packed = rejects_table(rejects, "radars", "ingest")
    assert packed["report_id"].to_list() == [None]
    assert json.loads(packed["detail"][0])["lat_deg"] == 91.0


def test_rejects_table_empty() -> None:
    _, rejects = lenient(reports())
    packed = rejects_table(rejects, "reports", "ingest")
    assert packed.height == 0 and dict(packed.schema) == TABLES["rejects"].columns


# --------------------------------------------------------------------------- row accounting

BAD_KINDS = (
    "neg_range", "nan_range", "inf_range", "null_range", "text_range",
    "az_360", "az_neg", "alt_glitch", "unknown_radar", "dup",
)


def _bad_row(kind: str, good: dict) -> dict:
    row = dict(good)
    patch = {
        "neg_range": {"range_m": "-12.0"},
        "nan_range": {"range_m": "NaN"},
        "inf_range": {"range_m": "inf"},
        "null_range": {"range_m": None},
        "text_range": {"range_m": "12 km"},
        "az_360": {"azimuth_deg": 360.0},
        "az_neg": {"azimuth_deg": -1.0},
        "alt_glitch": {"altitude_m": 37_520.0},
        "unknown_radar": {"radar_id": 9},
        "dup": {},
    }[kind]
    row.update(patch)
    return row


@st.composite
def frames_with_bad_rows(draw: st.DrawFn) -> tuple[pl.DataFrame, set[int], int]:
    n_good = draw(st.integers(1, 30))
    good = [
        {
            "radar_id": draw(st.sampled_from([1, 2])),
            "time": T0 + timedelta(seconds=i),
            "local_track_id": draw(st.integers(0, 3)),
            "range_m": str(draw(st.floats(1.0, 2.5e5))),
            "azimuth_deg": draw(st.floats(0.0, 360.0, exclude_max=True)),
            "altitude_m": draw(st.one_of(st.none(), st.floats(-500.0, 20_000.0))),
        }
        for i in range(n_good)
    ]
    injected = draw(st.lists(st.tuples(st.sampled_from(BAD_KINDS), st.integers(0, n_good - 1)), max_size=15))
    rows = [(row, False) for row in good]
    for kind, source in injected:
        position = draw(st.integers(0, len(rows)))
        rows.insert(position, (_bad_row(kind, good[source]), kind != "dup"))
    frame = pl.DataFrame([row for row, _ in rows], schema_overrides={"range_m": pl.String})
    bad_positions = {i for i, (_, bad) in enumerate(rows) if bad}
    n_dups = sum(kind == "dup" for kind, _ in injected)
    return frame, bad_positions, n_dups


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(frames_with_bad_rows())
def test_row_accounting(case: tuple[pl.DataFrame, set[int], int]) -> None:
    frame, bad_positions, n_dups = case
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnsortedTimeWarning)
        clean, rejects = lenient(frame, radars=radars())
    n = frame.height
    assert clean.height + rejects.height == n
    kept, dropped = set(clean["report_id"].to_list()), set(rejects["report_id"].to_list())
    assert not kept & dropped
    assert kept | dropped == set(range(n))
    assert set(rejects["row_index"].to_list()) == dropped
    assert bad_positions <= dropped
    assert rejects.height == len(bad_positions) + n_dups
    assert rejects["reason"].null_count() == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = validate(clean, "reports", radars=radars())
    assert again.equals(clean)


# --------------------------------------------------------------------------- is_sorted_by

from hypothesis import given, settings
from hypothesis import strategies as st

from tertiary.contract import is_sorted_by


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 3), st.integers(0, 3), st.one_of(st.none(), st.integers(0, 3))),
                max_size=30))
def test_is_sorted_by_agrees_with_polars_sort(rows):
    """True exactly when the frame has no nulls in the keys and sorting would not move a row."""
    frame = pl.DataFrame(rows, schema={"a": pl.Int64, "b": pl.UInt32, "c": pl.Int64}, orient="row")
    expected = frame.height < 2 or (frame["c"].null_count() == 0 and frame.sort("a", "b", "c").equals(frame))
    assert is_sorted_by(frame, ["a", "b", "c"]) == expected
    srt = frame.drop_nulls().sort("a", "b", "c")
    assert is_sorted_by(srt, ["a", "b", "c"])
