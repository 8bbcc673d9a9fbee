"""Validation's outputs, row for row and reason for reason, on frames holding every kind of bad value.

The expected clean rows, rejects (row indices, order, reason texts), strict-mode messages and
packed rejects are written out in full below: a faster validation must give exactly these, so
any change to which rows are rejected, in which order, or to a single character of a reason fails
here. The truth is also validated in parts (:func:`validate_truth` with tiny parts) and must give
the one-call result.
"""

from __future__ import annotations

import math
import warnings
from datetime import datetime, timedelta, timezone
from types import SimpleNamespace

import numpy as np
import polars as pl
import pytest

from tertiary.contract import SchemaError, UnsortedTimeWarning, validate
from tertiary.contract.rejects import rejects_table
from tertiary.pipeline import ingestion
from tertiary.pipeline.config import PipelineConfig

UTC = timezone.utc
T0 = datetime(2024, 5, 1, 12, 0, 0, tzinfo=UTC)
NAN, INF = math.nan, math.inf


def _cov(kind: str = "ok") -> list[float] | None:
    """A 6×6 covariance, row-major, good or broken in one way."""
    if kind == "null":
        return None
    p = np.diag([100.0, 120.0, 90.0, 4.0, 5.0, 3.0])
    p[0, 1] = p[1, 0] = 10.0
    if kind == "inf":
        p[2, 3] = INF
    elif kind == "big":
        p[0, 0] = 1e15
    elif kind == "asym":
        p[0, 1] = 50.0
    elif kind == "not_psd":
        p[0, 1] = p[1, 0] = 500.0
    elif kind == "nan":
        p[4, 4] = NAN
    elif kind == "tiny_neg":          # an eigenvalue just below 0, within the tolerance
        p = np.diag([100.0, 100.0, 1.0, 1.0, 1.0, 1e-12 - 1e-9])
    return p.ravel().tolist()


def radars() -> pl.DataFrame:
    return pl.DataFrame({
        "radar_id": [1, 2, 4],
        "name": ["R1", "M2", "R4"],
        "lat_deg": [48.0, 48.1, 48.2], "lon_deg": [2.0, 2.1, 2.2], "alt_m": [100.0, 50.0, 80.0],
        "scan_period_s": [4.0, 1.0, 8.0], "sigma_range_m": [30.0, 20.0, 50.0],
        "sigma_azimuth_deg": [0.05, 0.1, 0.08], "sigma_elevation_deg": [0.1, 0.1, 0.1],
        "max_range_m": [200_000.0, 100_000.0, 250_000.0],
        "kind": ["radar", "mlat", None],
    })


# (changes to a good row) per row: every check of the reports table, some rows breaking several
_REPORT_ROWS: list[dict] = [
    {},                                                            # 0 good
    {"local_track_id": 11},                                        # 1 good
    {"range_m": None},                                             # 2
    {"range_m": NAN},                                              # 3
    {"range_m": INF},                                              # 4
    {"range_m": -5.0},                                             # 5
    {"range_m": 300_000.0},                                        # 6 beyond radar 1's range x 1.2
    {"azimuth_deg": 360.0},                                        # 7
    {"elevation_deg": 95.0, "altitude_m": 30_000.0},               # 8 two problems
    {"est_range_var_m2": 0.0},                                     # 9
    {"est_range_var_m2": -INF},                                    # 10
    {"x_m": 2e7},                                                  # 11
    {"vx_mps": -2e4, "est_range_rate_mps": 1e5},                   # 12
    {"radar_id": 7},                                               # 13 unknown radar
    {"radar_id": 3},                                               # 14 rejected radar
    {"radar_id": None},                                            # 15
    {"local_track_id": None},                                      # 16
    {"time": None},                                                # 17
    {"time": datetime(1970, 1, 1, tzinfo=UTC)},                    # 18
    {"time": T0 + timedelta(days=30)},                             # 19 far from the median
    {"est_cov": _cov("inf")},                                      # 20
    {"est_cov": _cov("big")},                                      # 21
    {"est_cov": _cov("asym")},                                     # 22
    {"est_cov": _cov("not_psd")},                                  # 23
    {"est_cov": _cov("nan"), "local_track_id": 24},                # 24 good: NaN left to align
    {"est_cov": _cov("null"), "local_track_id": 25},               # 25 good
    {"est_cov": _cov("tiny_neg"), "local_track_id": 26},           # 26 good: within tolerance
    {"radar_id": 2, "plot_x_m": None, "local_track_id": 27},       # 27 mlat without its plot
    {"radar_id": 2, "plot_sigma_xy_m": 40.0, "local_track_id": 28},  # 28 |xy| above sqrt(sx sy)
    {"radar_id": 2, "local_track_id": 29, "range_m": 110_000.0},   # 29 good (within 1.2 x 100 km)
    {},                                                            # 30 key of row 0
    {"report_id": 1001, "local_track_id": 31},                     # 31 report_id of row 1
    {"range_m": 5000.0},                                           # 32 key of row 3 (bad): good
    {"report_id": 1001, "local_track_id": 11},                     # 33 report_id and key of row 1
    {"adsb_nacp": 12, "adsb_sil": 4},                              # 34
    {"run": None, "local_track_id": 35},                           # 35 good, run 0
    {"radar_id": 7, "azimuth_deg": NAN, "x_m": INF, "mode_s": "abc"},  # 36 several
    {"local_track_id": 37, "time": T0 - timedelta(seconds=30)},    # 37 good, before row 38
    {"local_track_id": 37, "time": T0 - timedelta(seconds=40)},    # 38 good, time decreases
    {"plot_sigma_x_m": 0.0, "plot_sigma_y_m": -1.0, "plot_lat_deg": 91.0},  # 39
    {"range_m": 250_000.0, "radar_id": 4, "local_track_id": 40},   # 40 good (radar 4 reaches 300 km)
]


def reports() -> pl.DataFrame:
    rows = []
    for i, change in enumerate(_REPORT_ROWS):
        row = {
            "report_id": 1000 + i, "run": 0, "radar_id": 1, "time": T0 + timedelta(seconds=i),
            "local_track_id": 10 + (i % 3 == 1), "range_m": 50_000.0 + i, "azimuth_deg": 10.0 + i,
            "elevation_deg": 2.0, "altitude_m": 3000.0, "mode_s": "3C6586", "est_range_var_m2": 900.0,
            "est_range_rate_mps": -120.0, "x_m": 1000.0 * i, "y_m": -500.0, "z_m": 3000.0, "vx_mps": 150.0,
            "vy_mps": 0.0, "vz_mps": 0.0, "est_cov": _cov(), "plot_x_m": 100.0, "plot_y_m": 200.0,
            "plot_lat_deg": 48.0, "plot_sigma_x_m": 10.0, "plot_sigma_y_m": 20.0, "plot_sigma_xy_m": 5.0,
            "adsb_nacp": 9, "adsb_sil": 3, "extra": f"e{i}",
        }
        if i in (30,):
            row.update(local_track_id=10, time=T0)                   # row 0's key
        if i in (32,):
            row.update(local_track_id=10, time=T0 + timedelta(seconds=3))   # row 3's key
        if i in (33,):
            row.update(time=T0 + timedelta(seconds=1))              # row 1's key
        row.update(change)
        rows.append(row)
    schema = {"report_id": pl.UInt64, "run": pl.UInt32, "radar_id": pl.UInt32, "time": pl.Datetime("us", "UTC"),
              "local_track_id": pl.UInt32, "est_cov": pl.Array(pl.Float64, 36), "adsb_nacp": pl.UInt8,
              "adsb_sil": pl.UInt8}
    return pl.DataFrame(rows, schema_overrides=schema)


# the outputs expected (every value written out)
REPORT_REJECTS = [(2, 1002, 'range_m: null'), (3, 1003, 'range_m: NaN'), (4, 1004, 'range_m: infinite value inf'),
 (5, 1005, 'range_m: non-positive value -5.0'),
 (6, 1006, 'range_m: beyond max_range_m x 1.2 = 240000.0 of radar 1, got 300000.0'),
 (7, 1007, 'azimuth_deg: outside [0, 360), got 360.0'),
 (8, 1008, 'elevation_deg: outside [-90, 90], got 95.0; altitude_m: outside [-500, 20000], got 30000.0'),
 (9, 1009, 'est_range_var_m2: outside (0, 1e+14], got 0.0'),
 (10, 1010, 'est_range_var_m2: outside (0, 1e+14], got -inf'),
 (11, 1011, 'x_m: outside [-1e+07, 1e+07], got 20000000.0'),
 (12, 1012,
  'est_range_rate_mps: outside [-10000, 10000], got 100000.0; vx_mps: outside [-10000, 10000], got '
  '-20000.0'),
 (13, 1013, 'radar_id: unknown radar 7'),
 (14, 1014, 'radar_id: radar 3 was rejected (see the radars rejects)'), (15, 1015, 'radar_id: null'),
 (16, 1016, 'local_track_id: null'), (17, 1017, 'time: null'),
 (18, 1018, 'time: outside [1990-01-01, 2100-01-01) UTC, got 1970-01-01T00:00:00Z'),
 (19, 1019,
  "time: more than 84 h from the table's median time 2024-05-01T12:00:14Z, got 2024-05-31T12:00:00Z"),
 (20, 1020, 'est_cov: infinite value'), (21, 1021, 'est_cov: variance larger than 1e+14'),
 (22, 1022, 'est_cov: not symmetric (|P - P^T| > 1e-06 x largest diagonal)'),
 (23, 1023, 'est_cov: not positive semi-definite (eigenvalue < -1e-06 x largest diagonal)'),
 (27, 1027, 'plot_x_m: radar 2 is of kind mlat or adsb; its report has no plot_x_m, plot_y_m'),
 (28, 1028,
  'plot_sigma_xy_m: |40.0| above sqrt(plot_sigma_x_m x plot_sigma_y_m) = sqrt(10.0 x 20.0): not a '
  'covariance'),
 (30, 1030, 'duplicate of report_id 1000 (run, radar_id, local_track_id, time)'),
 (31, 1001, 'report_id: duplicate value 1001'),
 (33, 1001,
  'report_id: duplicate value 1001; duplicate of report_id 1001 (run, radar_id, local_track_id, time)'),
 (34, 1034, 'adsb_nacp: outside [0, 11], got 12; adsb_sil: outside [0, 3], got 4'),
 (36, 1036, 'azimuth_deg: NaN; x_m: outside [-1e+07, 1e+07], got inf; radar_id: unknown radar 7'),
 (39, 1039,
  'plot_lat_deg: outside [-90, 90], got 91.0; plot_sigma_x_m: outside (0, 1e+07], got 0.0; plot_sigma_y_m: '
  'outside (0, 1e+07], got -1.0; plot_sigma_xy_m: |5.0| above sqrt(plot_sigma_x_m x plot_sigma_y_m) = '
  'sqrt(0.0 x -1.0): not a covariance')]

REPORT_CLEAN_IDS = [1000, 1032, 1001, 1024, 1025, 1026, 1035, 1038, 1037, 1029, 1040]

REPORT_NOTES = ['reports: time out of order in 1 of 9 tracks; sorted by (run, radar_id, local_track_id, time)']

REPORT_CLEAN_SCHEMA = [('radar_id', 'UInt32'), ('time', "Datetime(time_unit='us', time_zone='UTC')"),
 ('local_track_id', 'UInt32'), ('range_m', 'Float64'), ('azimuth_deg', 'Float64'), ('report_id', 'UInt64'),
 ('run', 'UInt32'), ('elevation_deg', 'Float64'), ('altitude_m', 'Float64'), ('mode_s', 'String'),
 ('est_range_rate_mps', 'Float64'), ('est_range_var_m2', 'Float64'), ('x_m', 'Float64'), ('y_m', 'Float64'),
 ('z_m', 'Float64'), ('vx_mps', 'Float64'), ('vy_mps', 'Float64'), ('vz_mps', 'Float64'),
 ('est_cov', 'Array(Float64, shape=(36,))'), ('plot_x_m', 'Float64'), ('plot_y_m', 'Float64'),
 ('plot_lat_deg', 'Float64'), ('plot_sigma_x_m', 'Float64'), ('plot_sigma_y_m', 'Float64'),
 ('plot_sigma_xy_m', 'Float64'), ('adsb_nacp', 'UInt8'), ('adsb_sil', 'UInt8'), ('extra', 'String')]

REPORT_REJECT_COLUMNS = ['row_index', 'report_id', 'reason', 'run', 'radar_id', 'time', 'local_track_id', 'range_m', 'azimuth_deg',
 'elevation_deg', 'altitude_m', 'mode_s', 'est_range_var_m2', 'est_range_rate_mps', 'x_m', 'y_m', 'z_m',
 'vx_mps', 'vy_mps', 'vz_mps', 'est_cov', 'plot_x_m', 'plot_y_m', 'plot_lat_deg', 'plot_sigma_x_m',
 'plot_sigma_y_m', 'plot_sigma_xy_m', 'adsb_nacp', 'adsb_sil', 'extra']

NO_RADARS_REJECTS = [(2, 'range_m: null'), (3, 'range_m: NaN'), (4, 'range_m: infinite value inf'),
 (5, 'range_m: non-positive value -5.0'), (7, 'azimuth_deg: outside [0, 360), got 360.0'),
 (8, 'elevation_deg: outside [-90, 90], got 95.0; altitude_m: outside [-500, 20000], got 30000.0'),
 (9, 'est_range_var_m2: outside (0, 1e+14], got 0.0'),
 (10, 'est_range_var_m2: outside (0, 1e+14], got -inf'),
 (11, 'x_m: outside [-1e+07, 1e+07], got 20000000.0'),
 (12,
  'est_range_rate_mps: outside [-10000, 10000], got 100000.0; vx_mps: outside [-10000, 10000], got '
  '-20000.0'),
 (15, 'radar_id: null'), (16, 'local_track_id: null'), (17, 'time: null'),
 (18, 'time: outside [1990-01-01, 2100-01-01) UTC, got 1970-01-01T00:00:00Z'),
 (19, "time: more than 84 h from the table's median time 2024-05-01T12:00:14Z, got 2024-05-31T12:00:00Z"),
 (20, 'est_cov: infinite value'), (21, 'est_cov: variance larger than 1e+14'),
 (22, 'est_cov: not symmetric (|P - P^T| > 1e-06 x largest diagonal)'),
 (23, 'est_cov: not positive semi-definite (eigenvalue < -1e-06 x largest diagonal)'),
 (28,
  'plot_sigma_xy_m: |40.0| above sqrt(plot_sigma_x_m x plot_sigma_y_m) = sqrt(10.0 x 20.0): not a '
  'covariance'),
 (30, 'duplicate of report_id 0 (run, radar_id, local_track_id, time)'),
 (33, 'duplicate of report_id 1 (run, radar_id, local_track_id, time)'),
 (34, 'adsb_nacp: outside [0, 11], got 12; adsb_sil: outside [0, 3], got 4'),
 (36, 'azimuth_deg: NaN; x_m: outside [-1e+07, 1e+07], got inf'),
 (39,
  'plot_lat_deg: outside [-90, 90], got 91.0; plot_sigma_x_m: outside (0, 1e+07], got 0.0; plot_sigma_y_m: '
  'outside (0, 1e+07], got -1.0; plot_sigma_xy_m: |5.0| above sqrt(plot_sigma_x_m x plot_sigma_y_m) = '
  'sqrt(0.0 x -1.0): not a covariance')]

STRICT_MESSAGE = ("reports: column 'radar_id': null in 1 row(s); e.g. row 15: radar_id=None (27 row(s) fail checks in all; "
 'validate with strict=False to get the rejects)')

STRICT_ROWS = [15]

STRICT_DUP_MESSAGE = ("reports: column 'report_id': duplicate value in 2 row(s); e.g. row 3: report_id=1001, row 4: "
 'report_id=1001 (3 row(s) fail checks in all; validate with strict=False to get the rejects)')

CAST_REJECTS = [(1,
  "radar_id: cannot cast 1.5 to UInt32; time: cannot cast 'yesterday' to Datetime[us, UTC]; est_cov: "
  'cannot cast [100.0, 10.0, 0.0, 0.0, 0.0, 0.0, 10.0, 120.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 90.0, 0.0, '
  '0.0, 0.0, 0.0, 0.0, 0.0, 4.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 5.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0] to '
  'Array(Float64, 36)'),
 (2, "local_track_id: cannot cast 'x' to UInt32"),
 (3,
  "range_m: cannot cast 'abc' to Float64; est_cov: cannot cast [100.0, 10.0, 0.0, 0.0, 0.0, 0.0, 10.0, "
  '120.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 90.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 4.0, 0.0, 0.0, 0.0, 0.0, 0.0, '
  '0.0, 5.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0] to Array(Float64, 36)'),
 (4, 'range_m: NaN'),
 (5, 'time: null; range_m: infinite value inf; azimuth_deg: outside [0, 360), got 400.0')]

CAST_CLEAN_ROWS = [(1, datetime(2024, 5, 1, 12, 0, tzinfo=UTC), 5, 1000.0, 1.0, 0, 0, '1',
  [100.0, 10.0, 0.0, 0.0, 0.0, 0.0, 10.0, 120.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 90.0, 0.0, 0.0, 0.0, 0.0,
   0.0, 0.0, 4.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 5.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 3.0])]

CAST_PACKED = [('reports', 'ingest', 1, 1,
  "radar_id: cannot cast 1.5 to UInt32; time: cannot cast 'yesterday' to Datetime[us, UTC]; est_cov: "
  'cannot cast [100.0, 10.0, 0.0, 0.0, 0.0, 0.0, 10.0, 120.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 90.0, 0.0, '
  '0.0, 0.0, 0.0, 0.0, 0.0, 4.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 5.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0] to '
  'Array(Float64, 36)',
  '{"report_id":1,"radar_id":1.5,"time":"yesterday","local_track_id":"5","range_m":"1000.5","azimuth_deg":2,"mode_s":2,"est_cov":[100.0,10.0,0.0,0.0,0.0,0.0,10.0,120.0,0.0,0.0,0.0,0.0,0.0,0.0,90.0,0.0,0.0,0.0,0.0,0.0,0.0,4.0,0.0,0.0,0.0,0.0,0.0,0.0,5.0,0.0,0.0,0.0,0.0,0.0,0.0],"run":1}'),
 ('reports', 'ingest', 2, 2, "local_track_id: cannot cast 'x' to UInt32",
  '{"report_id":2,"radar_id":1.0,"time":"2024-05-01 '
  '12:00:02","local_track_id":"x","range_m":"2000","azimuth_deg":3,"mode_s":3,"est_cov":[100.0,10.0,0.0,0.0,0.0,0.0,10.0,120.0,0.0,0.0,0.0,0.0,0.0,0.0,90.0,0.0,0.0,0.0,0.0,0.0,0.0,4.0,0.0,0.0,0.0,0.0,0.0,0.0,5.0,0.0,0.0,0.0,0.0,0.0,0.0,3.0],"run":1}'),
 ('reports', 'ingest', 3, 3,
  "range_m: cannot cast 'abc' to Float64; est_cov: cannot cast [100.0, 10.0, 0.0, 0.0, 0.0, 0.0, 10.0, "
  '120.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 90.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 4.0, 0.0, 0.0, 0.0, 0.0, 0.0, '
  '0.0, 5.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0] to Array(Float64, 36)',
  '{"report_id":3,"radar_id":1.0,"time":"2024-05-01T12:00:03+02:00","local_track_id":" 5 '
  '","range_m":"abc","azimuth_deg":4,"mode_s":4,"est_cov":[100.0,10.0,0.0,0.0,0.0,0.0,10.0,120.0,0.0,0.0,0.0,0.0,0.0,0.0,90.0,0.0,0.0,0.0,0.0,0.0,0.0,4.0,0.0,0.0,0.0,0.0,0.0,0.0,5.0,0.0,0.0,0.0,0.0,0.0,0.0,null],"run":2}'),
 ('reports', 'ingest', 4, 4, 'range_m: NaN',
  '{"report_id":4,"radar_id":1.0,"time":"2024-05-01","local_track_id":"5","range_m":"NaN","azimuth_deg":5,"mode_s":5,"est_cov":null,"run":null}'),
 ('reports', 'ingest', 5, 5,
  'time: null; range_m: infinite value inf; azimuth_deg: outside [0, 360), got 400.0',
  '{"report_id":5,"radar_id":1.0,"time":null,"local_track_id":"6","range_m":"inf","azimuth_deg":400,"mode_s":6,"est_cov":[100.0,10.0,0.0,0.0,0.0,0.0,10.0,120.0,0.0,0.0,0.0,0.0,0.0,0.0,90.0,0.0,0.0,0.0,0.0,0.0,0.0,4.0,0.0,0.0,0.0,0.0,0.0,0.0,5.0,0.0,0.0,0.0,0.0,0.0,0.0,3.0],"run":0}')]

TRUTH_REJECTS = [(1, 'x_m: NaN'), (2, 'vx_mps: infinite value inf'),
 (4, 'ax_mps2: outside [-1000, 1000], got 2000.0; alt_m: outside [-500, 20000], got 25000.0'),
 (5, 'time: outside [1990-01-01, 2100-01-01) UTC, got 2150-01-01T00:00:00Z'),
 (7,
  "time: outside the reports' span +- 3600 s [2024-05-01T11:59:55Z, 2024-05-01T14:00:00Z], got "
  '2024-05-01T17:00:00Z'),
 (8, 'duplicate of row_index 6 (truth_id, time)'), (9, 'truth_id: null'),
 (11, 'duplicate of row_index 10 (truth_id, time)')]

TRUTH_CLEAN_ROWS = [(1, datetime(2024, 5, 1, 12, 0, tzinfo=UTC), 0.0, 0.0, 3000.0, 100.0,
  0.0, 0.0, 0.0, 'cruise', 3000.0),
 (2, datetime(2024, 5, 1, 12, 0, 3, tzinfo=UTC), 3.0, 0.0, 3000.0, 100.0,
  0.0, 0.0, 0.0, 'cruise', 3000.0),
 (3, datetime(2024, 5, 1, 12, 0, 6, tzinfo=UTC), 6.0, 0.0, 3000.0, 100.0,
  0.0, 0.0, 0.0, 'cruise', 3000.0),
 (4, datetime(2024, 5, 1, 12, 0, 10, tzinfo=UTC), 10.0, 0.0, 3000.0,
  100.0, 0.0, 0.0, 0.0, 'cruise', 3000.0),
 (5, datetime(2024, 5, 1, 12, 0, 1, tzinfo=UTC), 13.0, 0.0, 3000.0, 100.0,
  0.0, 0.0, 0.0, 'cruise', 3000.0),
 (5, datetime(2024, 5, 1, 12, 0, 12, tzinfo=UTC), 12.0, 0.0, 3000.0,
  100.0, 0.0, 0.0, 0.0, 'cruise', 3000.0)]

TRUTH_NOTES = ['truth: time out of order in 1 of 5 (truth_id) groups; sorted by (truth_id, time)']

TRUTH_PART_DETAILS = ['{"truth_id":1,"time":"2024-05-01T12:00:01+00:00","x_m":"NaN","y_m":0.0,"z_m":3000.0,"vx_mps":"100.0","vy_mps":0.0,"vz_mps":0.0,"alt_m":3000.0,"ax_mps2":0.0,"segment":"cruise"}',
 '{"truth_id":1,"time":"2024-05-01T12:00:02+00:00","x_m":"2.0","y_m":0.0,"z_m":3000.0,"vx_mps":"inf","vy_mps":0.0,"vz_mps":0.0,"alt_m":3000.0,"ax_mps2":0.0,"segment":"cruise"}',
 '{"truth_id":2,"time":"2024-05-01T12:00:04+00:00","x_m":4.0,"y_m":0.0,"z_m":3000.0,"vx_mps":100.0,"vy_mps":0.0,"vz_mps":0.0,"alt_m":25000.0,"ax_mps2":2000.0,"segment":"cruise"}',
 '{"truth_id":2,"time":"2150-01-01T00:00:00+00:00","x_m":5.0,"y_m":0.0,"z_m":3000.0,"vx_mps":100.0,"vy_mps":0.0,"vz_mps":0.0,"alt_m":3000.0,"ax_mps2":0.0,"segment":"cruise"}',
 '{"truth_id":3,"time":"2024-05-01T17:00:00+00:00","x_m":7.0,"y_m":0.0,"z_m":3000.0,"vx_mps":100.0,"vy_mps":0.0,"vz_mps":0.0,"alt_m":3000.0,"ax_mps2":0.0,"segment":"cruise"}',
 '{"truth_id":3,"time":"2024-05-01T12:00:06+00:00","x_m":8.0,"y_m":0.0,"z_m":3000.0,"vx_mps":100.0,"vy_mps":0.0,"vz_mps":0.0,"alt_m":3000.0,"ax_mps2":0.0,"segment":"cruise"}',
 '{"truth_id":null,"time":"2024-05-01T12:00:09+00:00","x_m":9.0,"y_m":0.0,"z_m":3000.0,"vx_mps":100.0,"vy_mps":0.0,"vz_mps":0.0,"alt_m":3000.0,"ax_mps2":0.0,"segment":"cruise"}',
 '{"truth_id":4,"time":"2024-05-01T12:00:10+00:00","x_m":11.0,"y_m":0.0,"z_m":3000.0,"vx_mps":100.0,"vy_mps":0.0,"vz_mps":0.0,"alt_m":3000.0,"ax_mps2":0.0,"segment":"cruise"}']

RADAR_REJECTS = [(3, 'duplicate of row_index 0 (radar_id)'),
 (4,
  'lat_deg: outside [-90, 90], got 91.0; scan_period_s: null; sigma_range_m: outside (0, 10000], got 0.0; '
  "kind: invalid value 'sonar', expected one of radar, mlat, adsb"),
 (5,
  'lat_deg: NaN; scan_period_s: outside [0.1, 60], got 0.01; sigma_range_m: outside (0, 10000], got '
  '100000.0')]


def _lenient(frame, kind, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        clean, rejects = validate(frame, kind, strict=False, **kw)
    return clean, rejects, [str(w.message) for w in caught if issubclass(w.category, UnsortedTimeWarning)]


def test_reports_every_bad_value() -> None:
    frame = reports()
    clean, rejects, notes = _lenient(frame, "reports", radars=radars(), rejected_radars=[3])
    assert list(zip(rejects["row_index"].to_list(), rejects["report_id"].to_list(),
                    rejects["reason"].to_list())) == REPORT_REJECTS
    assert clean["report_id"].to_list() == REPORT_CLEAN_IDS
    assert notes == REPORT_NOTES
    assert [(k, str(v)) for k, v in clean.schema.items()] == REPORT_CLEAN_SCHEMA
    # the clean rows are the input rows (run null -> 0), sorted by track, nothing else touched
    expected = frame.with_columns(pl.col("run").fill_null(0))
    expected = expected.join(clean.select("extra"), on="extra", how="semi", maintain_order="left")
    expected = expected.sort(["run", "radar_id", "local_track_id", "time"], maintain_order=True)
    assert clean.equals(expected.select(clean.columns))
    # the rejects carry every input column with its input value
    assert rejects.columns == REPORT_REJECT_COLUMNS
    orig = frame.with_row_index("row_index").join(rejects.select("row_index"), on="row_index", how="semi",
                                                  maintain_order="left")
    assert rejects.drop("reason").select(orig.columns).equals(orig)


def test_reports_without_radars() -> None:
    frame = reports().drop("report_id")
    clean, rejects, _ = _lenient(frame, "reports")
    assert list(zip(rejects["row_index"].to_list(), rejects["reason"].to_list())) == NO_RADARS_REJECTS
    assert clean.height == frame.height - rejects.height


def test_reports_strict_message() -> None:
    with pytest.raises(SchemaError) as err:
        validate(reports(), "reports", radars=radars(), rejected_radars=[3])
    assert str(err.value) == STRICT_MESSAGE
    assert err.value.rows == STRICT_ROWS
    dups = reports()[[0, 1, 30, 31, 33]]
    with pytest.raises(SchemaError) as err:
        validate(dups, "reports", radars=radars())
    assert str(err.value) == STRICT_DUP_MESSAGE


def cast_frame() -> pl.DataFrame:
    """Columns given in other dtypes, some values that cannot be cast."""
    return pl.DataFrame({
        "radar_id": [1.0, 1.5, 1.0, 1.0, 1.0, 1.0],
        "time": ["2024-05-01T12:00:00Z", "yesterday", "2024-05-01 12:00:02", "2024-05-01T12:00:03+02:00",
                 "2024-05-01", None],
        "local_track_id": ["5", "5", "x", " 5 ", "5", "6"],
        "range_m": ["1000", "1000.5", "2000", "abc", "NaN", "inf"],
        "azimuth_deg": [1, 2, 3, 4, 5, 400],
        "mode_s": [1, 2, 3, 4, 5, 6],
        "est_cov": [_cov(), _cov()[:35], _cov(), [*_cov()[:35], None], None, _cov()],
        "run": [None, 1, 1, 2, None, 0],
    }, strict=False)


def test_cast_failures() -> None:
    clean, rejects, _ = _lenient(cast_frame(), "reports")
    assert list(zip(rejects["row_index"].to_list(), rejects["reason"].to_list())) == CAST_REJECTS
    assert clean.rows() == CAST_CLEAN_ROWS
    packed = rejects_table(rejects, "reports", "ingest")
    assert packed.rows() == CAST_PACKED


def truth() -> pl.DataFrame:
    n = 14
    frame = pl.DataFrame({
        "truth_id": [1, 1, 1, 2, 2, 2, 3, 3, 3, None, 4, 4, 5, 5],
        "time": [T0 + timedelta(seconds=i) for i in range(n)],
        "x_m": [float(i) for i in range(n)], "y_m": [0.0] * n, "z_m": [3000.0] * n,
        "vx_mps": [100.0] * n, "vy_mps": [0.0] * n, "vz_mps": [0.0] * n,
        "alt_m": [3000.0] * n, "ax_mps2": [0.0] * n, "segment": ["cruise"] * n,
    })
    changes = {1: {"x_m": NAN}, 2: {"vx_mps": INF}, 4: {"alt_m": 25_000.0, "ax_mps2": 2000.0},
               5: {"time": datetime(2150, 1, 1, tzinfo=UTC)}, 7: {"time": T0 + timedelta(hours=5)},
               8: {"time": T0 + timedelta(seconds=6)}, 11: {"time": T0 + timedelta(seconds=10)},
               13: {"time": T0 + timedelta(seconds=1)}}
    for i, change in changes.items():
        frame = frame.with_columns(pl.when(pl.int_range(pl.len()) == i).then(pl.lit(v, dtype=frame.schema[c]))
                                   .otherwise(pl.col(c)).alias(c) for c, v in change.items())
    return frame


WINDOW = (T0 - timedelta(seconds=5), T0 + timedelta(hours=2), "the reports' span +- 3600 s")


def test_truth_every_bad_value() -> None:
    clean, rejects, notes = _lenient(truth(), "truth", time_window=WINDOW)
    assert list(zip(rejects["row_index"].to_list(), rejects["reason"].to_list())) == TRUTH_REJECTS
    assert clean.rows() == TRUTH_CLEAN_ROWS
    assert notes == TRUTH_NOTES


@pytest.mark.parametrize("interleaved", [False, True])
def test_truth_in_parts_is_the_whole(monkeypatch: pytest.MonkeyPatch, interleaved: bool) -> None:
    """validate_truth: one call on a short truth; on a long one (above TRUTH_PART_ROWS) one call
    with its rejects packed part by part, or above TRUTH_WHOLE_ROWS part by part (parts of
    consecutive rows and gathered ones; time-major, the aircraft interleaved, put back in input
    order): the same clean table, rejects (details included) and notes."""
    cfg, frame = PipelineConfig(), truth()
    if interleaved:
        frame = frame.sort("time", maintain_order=True, nulls_last=True)

    def run() -> tuple[pl.DataFrame, pl.DataFrame, list[str]]:
        notes: list[str] = []
        clean, rejects = ingestion.validate_truth(SimpleNamespace(truth=frame), cfg, notes, WINDOW)
        return clean, rejects, notes

    one = run()
    monkeypatch.setattr(ingestion, "TRUTH_PART_ROWS", 3)
    packed_by_part = run()
    monkeypatch.setattr(ingestion, "TRUTH_WHOLE_ROWS", 0, raising=False)
    parts = run()
    for got in (packed_by_part, parts):
        assert got[0].equals(one[0]) and got[2] == one[2]
    assert parts[1].equals(packed_by_part[1])
    # a float column holding a NaN anywhere in a part's rejects is written as text in that part's
    # details: the details of a truth packed whole and in parts differ, nothing else
    keys = ["input_table", "stage", "report_id", "row_index", "reason"]
    assert parts[1].select(keys).equals(one[1].select(keys))
    assert parts[1]["detail"].to_list() != one[1]["detail"].to_list()
    if interleaved:
        assert one[0].sort("truth_id", "time").rows() == sorted(TRUTH_CLEAN_ROWS)
        assert one[1].height == len(TRUTH_REJECTS)
    else:
        assert one[0].rows() == TRUTH_CLEAN_ROWS and one[2] == TRUTH_NOTES
        assert [r for _, r in TRUTH_REJECTS] == one[1]["reason"].to_list()
        assert parts[1]["detail"].to_list() == TRUTH_PART_DETAILS


def bad_radars() -> pl.DataFrame:
    frame = radars()
    return pl.concat([frame, frame.with_columns(
        pl.Series("radar_id", [1, 5, 6], dtype=pl.Int64), pl.Series("lat_deg", [48.0, 91.0, NAN]),
        pl.Series("kind", ["radar", "sonar", "adsb"]), pl.Series("sigma_range_m", [30.0, 0.0, 1e5]),
        pl.Series("scan_period_s", [4.0, None, 0.01]))], how="vertical_relaxed")


def test_radars_every_bad_value() -> None:
    clean, rejects, _ = _lenient(bad_radars(), "radars")
    assert list(zip(rejects["row_index"].to_list(), rejects["reason"].to_list())) == RADAR_REJECTS
    assert clean["radar_id"].to_list() == [1, 2, 4]


@pytest.mark.parametrize("seed", range(4))
def test_streamed_median_time_is_the_median_of_the_whole_column(seed):
    """The median time read a batch at a time (count and range, a histogram, the middle
    buckets' values) is exactly the polars median of the whole column: odd and even counts,
    times in one bucket or spread over decades, repeated times, nulls and times outside the
    years left out."""
    from tertiary.contract import streamed_median_time, table_median_time
    rng = np.random.default_rng(seed)
    base = 1_633_000_000_000_000
    for scale in (1, 1_000, 10**6, 10**9, 10**12, 10**14):
        for n in (1, 2, 7, 1_000, 4_001):
            v = base + (rng.integers(0, scale, n) if n % 2 else rng.integers(0, 5, n) * scale)
            odd = [None, datetime(1900, 1, 1, tzinfo=timezone.utc)]
            s = pl.concat([pl.Series(v).cast(pl.Datetime("us", "UTC")), pl.Series(odd, dtype=pl.Datetime("us", "UTC"))])
            k = int(rng.integers(1, 60))

            def batches(s=s, k=k):
                return (s.slice(o, k) for o in range(0, s.len(), k))
            assert streamed_median_time(batches) == table_median_time(pl.DataFrame({"time": s}))
    assert streamed_median_time(lambda: iter([pl.Series([None], dtype=pl.Datetime("us", "UTC"))])) is None
