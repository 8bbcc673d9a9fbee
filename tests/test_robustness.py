"""Bad input never crashes: one regression test per crash or silent acceptance found
by the fuzz campaign in the data contract, the dataset reader, scenario options, the pipeline,
alignment and the capacity model. Each ends in a clear TertiaryError or in rejects with a reason."""

from __future__ import annotations

import dataclasses
import json
import math
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import polars as pl
import polars.selectors as cs
import pytest

import tertiary
from tertiary import pipeline
from tertiary.pipeline import tables
from tertiary import contract as schema
from tertiary.stages.align import AlignConfig
from tertiary.core.errors import DataError, OptionError, ResourceError, TertiaryError
from tertiary.io.dataset import Dataset, read_dataset, write_dataset
from tertiary.simulate import simulate
from tertiary.simulate.config import Anomalies, check_scenario, load_scenario, with_radar_count
from tertiary.store.run_store import RunStore

CFG = pipeline.PipelineConfig(methods=("arithmetic",), filters=(), centralized=False, safety=False)
US = 1_000_000


@pytest.fixture(scope="module")
def small() -> Dataset:
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=120.0, traffic=dataclasses.replace(cfg.traffic, aircraft=6))
    return simulate(with_radar_count(cfg, 2))


@pytest.fixture(scope="module")
def small_dir(small: Dataset, tmp_path_factory) -> Path:
    return write_dataset(small, tmp_path_factory.mktemp("ds") / "ta")


def _copy(src: Path, dst: Path) -> Path:
    dst.mkdir(parents=True)
    for f in src.iterdir():
        (dst / f.name).write_bytes(f.read_bytes())
    return dst


def _set_row(frame: pl.DataFrame, col: str, i: int, value, dtype=None) -> pl.DataFrame:
    dtype = dtype or frame.schema[col]
    return frame.with_columns(pl.when(pl.int_range(pl.len()) == i).then(pl.lit(value, dtype))
                              .otherwise(pl.col(col)).alias(col))


def _reasons(ing: pipeline.Ingested, table: str = "reports") -> list[str]:
    return ing.rejects.filter(pl.col("input_table") == table)["reason"].to_list()


def _record(run_dir: Path) -> dict[str, str]:
    with RunStore.open(run_dir) as st:
        return dict(st.read("run").iter_rows())


# --------------------------------------------------------------------------- data contract


def test_schema_error_is_a_data_error() -> None:
    with pytest.raises(DataError) as err:
        schema.validate(pl.DataFrame({"radar_id": [1]}), "reports")
    assert isinstance(err.value, schema.SchemaError) and err.value.table == "reports"
    assert err.value.column == "time" and err.value.problem == "missing column"


@pytest.mark.parametrize("bad", [None, np.zeros((3, 3)), 42, "reports.parquet", [1, 2]])
def test_validate_of_non_frame_is_a_clear_error(bad) -> None:
    with pytest.raises(OptionError, match="expected a polars DataFrame or LazyFrame, a pyarrow Table or a dict"):
        tertiary.validate(bad, "reports")


def test_validate_accepts_lazyframe_pyarrow_and_dict(small: Dataset) -> None:
    frame = small.reports.head(20)
    expect = schema.validate(frame, "reports")
    for given in (frame.lazy(), frame.to_arrow(), frame.to_dict(as_series=False)):
        assert schema.validate(given, "reports").equals(expect)
    with pytest.raises(DataError, match="cannot make a table of the dict"):
        schema.validate({"radar_id": [1, 2], "time": [1]}, "reports")


def test_unknown_table_kind_is_an_option_error() -> None:
    with pytest.raises(OptionError, match="unknown table kind 'report'"):
        schema.validate(pl.DataFrame(), "report")


def test_binary_column_rejects_writer_does_not_panic(small: Dataset) -> None:
    frame = small.reports.head(3).with_columns(
        pl.Series("blob", [b"\x00\xff", None, b"ab"], dtype=pl.Binary),
        pl.Series("nested", [{"b": b"x"}, None, None]),
        pl.Series("dur", [1, 2, 3]).cast(pl.Duration("us")),
    )
    frame = _set_row(frame, "range_m", 0, -5.0)
    _, rej = schema.validate(frame, "reports", strict=False)
    packed = schema.rejects_table(rej, "reports", "ingest")
    detail = json.loads(packed["detail"][0])
    assert detail["blob"] == "00ff" and detail["range_m"] == -5.0


@pytest.mark.parametrize("value", [True, False])
def test_boolean_range_is_a_type_error_not_0_1(small: Dataset, value: bool) -> None:
    frame = small.reports.head(5).with_columns(pl.lit(value).alias("range_m"))
    with pytest.raises(DataError, match="'range_m' has dtype Boolean which cannot be cast to Float64"):
        schema.validate(frame, "reports", strict=False)


@pytest.mark.parametrize("dtype", [pl.Int64, pl.Float64, pl.Date, pl.Duration("us")])
def test_time_of_wrong_type_is_a_data_error_in_run(small: Dataset, tmp_path: Path, dtype) -> None:
    col = small.reports["time"]
    bad = col.dt.epoch("us") if dtype in (pl.Int64, pl.Float64) else (
        col.dt.date() if dtype == pl.Date else col - col.min())
    ds = dataclasses.replace(small, reports=small.reports.with_columns(bad.cast(dtype).alias("time")))
    with pytest.raises(DataError, match="reports: column 'time' has dtype"):
        pipeline.run(ds, tmp_path / "run", CFG)
    assert _record(tmp_path / "run")["status"] == "failed"


def test_run_catches_missing_column_and_string_cov(small: Dataset, tmp_path: Path) -> None:
    for i, reports in enumerate((small.reports.drop("azimuth_deg"),
                                 small.reports.with_columns(pl.lit("[1, 2]").alias("est_cov")))):
        with pytest.raises(DataError, match="azimuth_deg|est_cov"):
            pipeline.run(dataclasses.replace(small, reports=reports), tmp_path / f"r{i}", CFG)


def test_impossible_values_are_rejected_with_reasons(small: Dataset) -> None:
    """The silent acceptances of the campaign: each row goes to rejects with its rule's reason."""
    rep = small.reports
    year = lambda y: datetime(y, 6, 1, tzinfo=timezone.utc)  # noqa: E731
    cov = rep["est_cov"].to_numpy().copy()
    asym, neg = cov[5].copy(), cov[6].copy()
    asym[1] += 1e3 * abs(asym[0])
    neg[0] = -abs(neg[0])
    cov[5], cov[6], cov[7] = asym, neg, np.full(36, 1e300)
    cases = {
        0: ("range_m", 1e300, "range_m: beyond max_range_m x 1.2"),
        1: ("elevation_deg", 95.0, "elevation_deg: outside [-90, 90]"),
        2: ("est_range_var_m2", math.inf, "est_range_var_m2: outside (0, 1e+14]"),
        3: ("est_range_var_m2", -4.0, "est_range_var_m2: outside (0, 1e+14]"),
        4: ("x_m", -1e300, "x_m: outside [-1e+07, 1e+07]"),
        8: ("time", year(1970), "time: outside [1990-01-01, 2100-01-01)"),
        9: ("time", year(9999), "time: outside [1990-01-01, 2100-01-01)"),
        10: ("time", year(1995), "time: more than 84 h from the table's median time"),
    }
    for i, (col, value, _) in cases.items():
        rep = _set_row(rep, col, i, value)
    rep = rep.with_columns(pl.Series("est_cov", cov, dtype=pl.Array(pl.Float64, 36)))
    cases |= {5: (None, None, "est_cov: not symmetric"), 6: (None, None, "est_cov: not positive semi-definite"),
              7: (None, None, "est_cov: variance larger than")}
    ing = pipeline.ingest(dataclasses.replace(small, reports=rep))
    got = dict(ing.rejects.filter(pl.col("stage") == "ingest").select("row_index", "reason").iter_rows())
    for i, (_, _, reason) in cases.items():
        assert reason in got.get(i, ""), (i, got.get(i))


def test_implausible_radar_parameters_reject_the_radar_and_its_reports(small: Dataset) -> None:
    radars = _set_row(small.radars, "scan_period_s", 0, 1e-9)
    radars = _set_row(radars, "sigma_range_m", 1, 1e300)
    ing = pipeline.ingest(dataclasses.replace(small, radars=radars))
    assert sorted(_reasons(ing, "radars")) == ["scan_period_s: outside [0.1, 60], got 1e-9",
                                               "sigma_range_m: outside (0, 10000], got 1e+300"]
    assert ing.reports.height == 0
    reasons = set(_reasons(ing))
    assert reasons == {"radar_id: radar 1 was rejected (see the radars rejects)",
                       "radar_id: radar 2 was rejected (see the radars rejects)"}


def test_truth_dated_1970_or_2100_is_rejected_not_allocated(small: Dataset) -> None:
    """Two truth rows decades apart sized a 12 GiB alert grid; the contract rejects them."""
    t = small.truth
    far = pl.concat([t.head(1).with_columns(pl.lit(datetime(1970, 1, 1, tzinfo=timezone.utc)).alias("time")),
                     t.head(1).with_columns(pl.lit(datetime(2099, 12, 1, tzinfo=timezone.utc)).alias("time"))])
    ing = pipeline.ingest(dataclasses.replace(small, truth=pl.concat([t, far.with_columns(pl.col("time")
                                                                                 .cast(t.schema["time"]))])))
    reasons = _reasons(ing, "truth")
    assert len(reasons) == 2 and ing.truth.height == t.height
    assert "outside [1990-01-01, 2100-01-01)" in reasons[0]
    assert "outside the reports' span +- 3600 s" in reasons[1]
    span = (ing.truth["time"].max() - ing.truth["time"].min()).total_seconds()
    assert span < 2 * 3600 + 200


# --------------------------------------------------------------------------- files


@pytest.mark.parametrize("how", ["truncate", "garbage", "csv", "empty", "ipc"])
@pytest.mark.parametrize("name", ["radars.parquet", "reports.parquet", "truth.parquet"])
def test_unreadable_parquet_is_a_data_error_naming_the_file(small_dir: Path, tmp_path: Path, how: str,
                                                            name: str) -> None:
    d = _copy(small_dir, tmp_path / "d")
    f = d / name
    frame = pl.read_parquet(f)
    if how == "truncate":
        f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
    elif how == "garbage":
        f.write_bytes(b"\x13\x37" * 500)
    elif how == "csv":
        f.write_text(frame.head(5).select(cs.numeric()).write_csv())
    elif how == "empty":
        f.write_bytes(b"")
    else:
        frame.head(5).select(cs.numeric()).write_ipc(f)
    with pytest.raises(DataError, match=f"{name}: " + ("empty file" if how == "empty" else "not a readable Parquet")):
        read_dataset(d)


@pytest.mark.parametrize("name", ["radars.parquet", "reports.parquet"])
def test_missing_table_is_a_data_error(small_dir: Path, tmp_path: Path, name: str) -> None:
    d = _copy(small_dir, tmp_path / "d")
    (d / name).unlink()
    with pytest.raises(DataError, match=f"{name}: missing"):
        read_dataset(d)
    with pytest.raises(DataError, match="no such dataset directory"):
        read_dataset(tmp_path / "nope")


@pytest.mark.parametrize("content, match", [
    (b"\x00\x01garbage [[[", "not UTF-8 text|not valid TOML"),
    ('name = "x"\nkind = "terminal-area"\norigin = [48.0, 2.0, 0.0]\n'.encode("utf-16"), r"not UTF-8 text \(UTF-16\?\)"),
    (b'name = "x"\nkind = "terminal-area"\ncolour = 3\n', r"unknown key\(s\) colour"),
    (b'name = "x"\nkind = "terminal-area"\n', "origin: missing"),
    (b'name = "x"\nkind = "terminal-area"\norigin = "abc"\n', "origin: expected an array, got str 'abc'"),
    (b'name = "x"\nkind = "terminal-area"\norigin = [nan, 2.0, 0.0]\n', r"origin.lat_deg: must be finite"),
    (b'name = "x"\nkind = "terminal-area"\norigin = [48.0, 2.0, 0.0]\nruns = "two"\n', "runs: expected an integer"),
    (b'name = "../../../x"\nkind = "terminal-area"\norigin = [48.0, 2.0, 0.0]\n', "name: must be an identifier"),
])
def test_malformed_scenario_toml_is_a_data_error(small_dir: Path, tmp_path: Path, content: bytes, match: str) -> None:
    d = _copy(small_dir, tmp_path / "d")
    (d / "scenario.toml").write_bytes(content)
    with pytest.raises(DataError, match=r"scenario.toml: .*" + match):
        read_dataset(d)


def test_dataset_without_scenario_toml_runs(small_dir: Path, tmp_path: Path) -> None:
    """No scenario.toml crashed with a TypeError; now the origin is the argument or the sites."""
    d = _copy(small_dir, tmp_path / "my data")
    (d / "scenario.toml").unlink()
    ds = read_dataset(d)
    sites = pl.read_parquet(d / "radars.parquet")
    assert ds.scenario.origin == pytest.approx((sites["lat_deg"].mean(), sites["lon_deg"].mean(), 0.0))
    assert ds.scenario.name == "my_data" and any("mean radar site" in n for n in ds.notes)
    # truth in an unnamed frame is not scored in a guessed one (km "errors"); --origin names it
    assert ds.truth.height == 0 and any("truth.parquet: not used" in n for n in ds.notes)
    named = read_dataset(d, origin=(48.0, 2.0))
    assert named.scenario.origin == (48.0, 2.0, 0.0) and named.truth.height > 0
    with pytest.raises(OptionError, match="origin"):
        read_dataset(d, origin=(95.0, 2.0))
    db = pipeline.run(ds, tmp_path / "run", CFG)
    assert json.loads(_record(db.parent)["notes"])[1].startswith("system origin = mean radar site")
    pl.DataFrame({"radar_id": [1]}).write_parquet(d / "radars.parquet")
    with pytest.raises(DataError, match="no scenario.toml and no radar site"):
        read_dataset(d)


# --------------------------------------------------------------------------- options


@pytest.mark.parametrize("change, match", [
    (dict(runs=-1), r"runs \(--runs\): must be finite and in \[1"),
    (dict(runs=0), r"runs \(--runs\)"),
    (dict(seed=-1), r"seed \(--seed\)"),
    (dict(duration_s=0.0), r"duration_s \(--duration\)"),
    (dict(duration_s=math.nan), r"duration_s \(--duration\)"),
    (dict(duration_s=math.inf), r"duration_s \(--duration\)"),
    (dict(duration_s=-10.0), r"duration_s \(--duration\)"),
    (dict(name="../../x"), "name: must be an identifier"),
    (dict(anomalies=Anomalies(noise_factor=-1.0)), r"anomalies.noise_factor \(--noise-factor\)"),
    (dict(anomalies=Anomalies(noise_factor=math.inf)), r"anomalies.noise_factor"),
    (dict(anomalies=Anomalies(outlier_fraction=1.5)), r"anomalies.outlier_fraction \(--outliers\)"),
    (dict(anomalies=Anomalies(noise_window_s=(300.0, 100.0))), "start must be before end"),
    (dict(anomalies=Anomalies(dropout_radar="NOPE", dropout_window_s=(0.0, 10.0))), "unknown radar 'NOPE'"),
    (dict(anomalies=Anomalies(bias_step_time_s=math.nan)), "anomalies.bias_step_time_s"),
])
def test_bad_scenario_option_is_an_option_error_before_work(change: dict, match: str) -> None:
    cfg = dataclasses.replace(load_scenario("terminal-area"), **change)
    with pytest.raises(OptionError, match=match):
        check_scenario(cfg)
    with pytest.raises(OptionError, match=match):
        simulate(cfg)


def test_bad_counts_are_option_errors() -> None:
    cfg = load_scenario("terminal-area")
    with pytest.raises(OptionError, match=r"traffic.aircraft"):
        check_scenario(dataclasses.replace(cfg, traffic=dataclasses.replace(cfg.traffic, aircraft=-3)))
    with pytest.raises(OptionError, match=r"radars \(--radars\): need at least one radar"):
        with_radar_count(cfg, 0)
    with pytest.raises(OptionError, match="unknown scenario 'nope'.*built-in: .*terminal-area"):
        load_scenario("nope")
    with pytest.raises(ResourceError, match="rows estimated"):
        check_scenario(dataclasses.replace(cfg, duration_s=3e7, runs=50))


def test_truth_file_missing_or_malformed_is_a_data_error(tmp_path: Path) -> None:
    cfg = load_scenario("adsb")
    missing = dataclasses.replace(cfg, adsb=dataclasses.replace(cfg.adsb, truth_file=str(tmp_path / "no.parquet")))
    with pytest.raises(DataError, match="no.parquet: file not found"):
        simulate(missing)
    bad = tmp_path / "bad.csv"
    bad.write_text("a,b\n1,2\n")
    with pytest.raises(DataError, match="bad.csv: not a readable ADS-B trajectory table"):
        simulate(dataclasses.replace(cfg, adsb=dataclasses.replace(cfg.adsb, truth_file=str(bad))))


def test_truth_file_on_a_scenario_without_adsb_is_an_option_error() -> None:
    cfg = load_scenario("terminal-area")
    with pytest.raises(OptionError, match=r"adsb.truth_file \(--truth\): .* adsb scenarios only"):
        check_scenario(dataclasses.replace(cfg, adsb=dataclasses.replace(cfg.adsb, truth_file="x.parquet")))


def test_write_dataset_on_a_file_is_a_data_error(small: Dataset, tmp_path: Path) -> None:
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(DataError, match="exists and is not a directory"):
        write_dataset(small, f)


# --------------------------------------------------------------------------- one validation path


def _bad_dataset(small: Dataset) -> Dataset:
    """Bad rows of every kind the stages reject, in a shuffled input order."""
    rep = small.reports
    rep = _set_row(rep, "range_m", 0, -1.0)                               # ingest: value rule
    rep = _set_row(rep, "azimuth_deg", 1, None)                           # ingest: null
    rep = pl.concat([rep, rep.slice(2, 1)])                               # ingest: duplicate key
    rep = _set_row(rep, "radar_id", 3, 9)                                 # ingest: unknown radar
    rep = _set_row(rep, "x_m", 4, math.nan)                               # align: no usable estimate
    rep = _set_row(rep, "vx_mps", 5, 2000.0)                              # align: implausible speed
    later = rep.slice(6, 1).with_columns(pl.col("time") + pl.duration(microseconds=1000),
                                         pl.col("report_id") + 10 ** 9)
    rep = pl.concat([rep, later])                                          # align: superseded
    rep = rep.sample(fraction=1.0, shuffle=True, seed=3)
    return dataclasses.replace(small, reports=rep)


def test_screen_predicts_the_runs_rejects_exactly(small: Dataset, tmp_path: Path) -> None:
    ds = _bad_dataset(small)
    screened = pipeline.screen(ds, CFG)
    pipeline.run(ds, tmp_path / "run", CFG)
    with RunStore.open(tmp_path / "run") as st:
        stored = st.read("rejects")
    key = ["input_table", "stage", "row_index", "reason"]
    assert screened.rejects.select(key).sort(key).equals(stored.select(key).sort(key))
    stages = set(stored["stage"])
    assert stages == {"ingest", "align"}
    reasons = " | ".join(stored["reason"])
    for text in ("non-positive", "null", "duplicate of report_id", "unknown radar 9", "no usable track estimate",
                 "implausible track speed", "superseded"):
        assert text in reasons


def test_rejects_row_index_is_the_input_row_for_every_stage(small: Dataset) -> None:
    ds = _bad_dataset(small)
    rej = pipeline.screen(ds, CFG).rejects.filter(pl.col("input_table") == "reports")
    ids = ds.reports["report_id"].to_list()
    for row in rej.filter(pl.col("report_id").is_not_null()).iter_rows(named=True):
        assert ids[row["row_index"]] == row["report_id"], row


# --------------------------------------------------------------------------- degenerate inputs


@pytest.mark.parametrize("which", ["all_rejected", "zero_rows", "every_radar_rejected", "no_radars"])
def test_nothing_valid_left_is_a_clear_error_with_a_run_record(small: Dataset, tmp_path: Path, which: str) -> None:
    """align.epoch_grid raised a TypeError; now a DataError after rejects and the run record."""
    ds = {"all_rejected": dataclasses.replace(small, reports=small.reports.with_columns(pl.lit(-1.0).alias("range_m"))),
          "zero_rows": dataclasses.replace(small, reports=small.reports.clear()),
          "every_radar_rejected": dataclasses.replace(small, radars=small.radars.with_columns(
              pl.lit(500.0).alias("scan_period_s"))),
          "no_radars": dataclasses.replace(small, radars=small.radars.clear())}[which]
    with pytest.raises(DataError, match="no valid report left|the table has no rows"):
        pipeline.run(ds, tmp_path / "run", CFG)
    rec = _record(tmp_path / "run")
    assert rec["status"] == "failed" and rec["failed_stage"] == "validate"
    if which == "zero_rows":       # validate refuses it the same way
        with pytest.raises(DataError, match="reports: the table has no rows"):
            pipeline.screen(ds, CFG)
        return
    with RunStore.open(tmp_path / "run") as st:
        assert st.read("rejects").height == ds.reports.height + (ds.radars.height if "radar" in which else 0)
    assert pipeline.screen(ds, CFG).valid_reports == 0


def test_one_report_runs(small: Dataset, tmp_path: Path) -> None:
    db = pipeline.run(dataclasses.replace(small, reports=small.reports.head(1)), tmp_path / "run",
                      pipeline.PipelineConfig(methods=("arithmetic",), filters=("singer",)))
    assert _record(db.parent)["status"] == "completed"


# --------------------------------------------------------------------------- bounded resources


def test_tiny_epoch_period_is_refused_before_allocating(small: Dataset) -> None:
    """scan_period_s = 1e-9 asked align for 3.78 TiB; the row estimate refuses first."""
    cfg = dataclasses.replace(CFG, align=AlignConfig(period_s=1e-6))
    with pytest.raises(ResourceError, match=r"align: .* aligned rows .* exceed the limit"):
        pipeline.screen(small, cfg)
    with pytest.raises(OptionError, match="align.period_s"):
        pipeline.screen(small, dataclasses.replace(CFG, align=AlignConfig(period_s=-1.0)))


# --------------------------------------------------------------------------- late failures


def test_capacity_p_at_least_1_is_nan_with_a_note() -> None:
    """quasi_optimal's km-level RMSE made _p_pair raise at the very end of the run."""
    from safety.capacity import capacity_from_metrics
    metrics = pl.DataFrame({"stage": ["tracker", "fusion"], "method": ["bad", "good"], "metric": "rmse_pos_m",
                            "segment": "all", "value": [5e4, 60.0], "n_runs": 1},
                           schema_overrides={"n_runs": pl.UInt32})
    notes: list[str] = []
    cap = capacity_from_metrics(metrics, notes=notes)
    sound = dict(cap.filter(pl.col("metric").str.starts_with("capacity_n_") & pl.col("metric").str.ends_with("_sound"))
                 .select("method", "value").iter_rows())
    assert math.isnan(sound["bad"]) and sound["good"] >= 1
    assert len(notes) == 1 and "bad is NaN" in notes[0] and "p = " in notes[0]


def test_a_late_stage_failure_keeps_the_completed_stages(small: Dataset, tmp_path: Path, monkeypatch) -> None:
    """Clustering fails in the third window (of 30 s): the two completed windows' tables are stored (and
    nothing of the failing window), with a run record naming the stage."""
    from tertiary.pipeline import plan       # the cluster stage's adapter looks the step function up there
    real, calls = plan.cluster_step, []

    def boom(*a, **k):
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("cluster exploded")
        return real(*a, **k)
    monkeypatch.setattr(plan, "cluster_step", boom)
    with pytest.raises(pipeline.StageError, match="stage 'cluster' failed .*cluster exploded") as err:
        pipeline.run(small, tmp_path / "run", CFG, window_s=30.0)
    assert isinstance(err.value, TertiaryError)
    rec = _record(tmp_path / "run")
    assert rec["failed_stage"] == "cluster" and "cluster exploded" in rec["error"]
    with RunStore.open(tmp_path / "run") as st:
        assert {"radars", "reports", "rejects", "aligned", "associations", "fused"} <= set(st.tables())
        last = st.sql("SELECT max(epoch) AS t FROM fused")["t"][0]
        first = st.sql("SELECT min(time) AS t FROM reports")["t"][0]
    assert (last - first).total_seconds() < 60.0         # two windows of 30 s, not the failing third


def test_rules_table_is_documented() -> None:
    text = schema.rules_markdown()
    assert "| reports | range_m | (0, max_range_m x 1.2] of its radar (without a radars table: (0, 2400000] m) |" in text
    assert len(schema.RULES) >= 20


def test_scenario_toml_origin_off_the_globe_is_refused_even_with_origin_option(tmp_path):
    """Found by the fuzz campaign: --origin overrode a scenario.toml origin of latitude 148.85 and
    the bad field was never checked; the file is validated whole."""
    from tertiary.core.errors import DataError
    from tertiary.io.dataset import read_dataset, write_dataset
    from tertiary.simulate import load_scenario, simulate
    ds = simulate(load_scenario("big-box").replace(runs=1, duration_s=60.0))
    out = write_dataset(ds, tmp_path / "ds")
    toml = out / "scenario.toml"
    text = toml.read_text()
    toml.write_text(text.replace("origin = [50.45,", "origin = [148.85,"))
    assert "148.85" in toml.read_text()
    with pytest.raises(DataError, match="origin"):
        read_dataset(out, origin=(-33.9, 151.2))
    toml.write_text(text)
    assert read_dataset(out, origin=(-33.9, 151.2)).scenario.origin[:2] == (-33.9, 151.2)


def test_a_table_write_failure_in_finalize_names_write_tables(small: Dataset, tmp_path: Path,
                                                               monkeypatch) -> None:
    """The finalize's tables are written on a thread beside the whole-run stages: a write that
    fails (here the ``fused`` table) is raised as ``write_tables``'s failure, not as the stage
    that happened to run then, the tables after it are not written, and the run record and the
    tables written before it are kept."""
    from tertiary.store.run_store import RunStore as Store
    real, written = Store.write_parts, []

    def boom(self, name, parts):
        if name == "fused":
            raise OSError("disk full while writing fused")
        written.append(name)
        return real(self, name, parts)
    monkeypatch.setattr(Store, "write_parts", boom)
    with pytest.raises(pipeline.StageError, match="stage 'write_tables' failed .*disk full") as err:
        pipeline.run(small, tmp_path / "run", CFG, window_s=30.0)
    assert "while writing table 'fused'" in "".join(getattr(err.value.__cause__, "__notes__", []))
    rec = _record(tmp_path / "run")
    assert rec["status"] == "failed" and rec["failed_stage"] == "write_tables"
    # written before ``fused`` in the finalize's order, and nothing after it (the failed run's
    # tables are then written whole from the windows' parts, not part by part)
    assert {"reports", "aligned"} <= set(written) and "tracks" not in written
    with RunStore.open(tmp_path / "run") as st:
        assert {"reports", "aligned"} <= set(st.tables())


def test_the_finalize_tables_are_written_in_order_and_whole(small: Dataset, monkeypatch) -> None:
    """The sink receives every table once, in the order the finalize gives them, each complete,
    from the writer thread: the same (table, rows) sequence as a sink called in the stages' own
    thread."""
    import threading

    def run(threads: set) -> list[tuple[str, int]]:
        got: list[tuple[str, int]] = []

        def sink(name, frame):
            threads.add(threading.current_thread().name)
            rows = (sum(f.height for f in frame.parts()) if isinstance(frame, pipeline.StreamedTable)
                    else frame.height)
            got.append((name, rows))
        pipeline.process(small, CFG, sink=sink, window_s=30.0)
        return got
    threaded, inline = set(), set()
    got = run(threaded)
    # the same finalize with each table handed over at once, in the stages' thread
    monkeypatch.setattr(tables.SinkThread, "__call__", lambda self, name, frame: self.sink(name, frame))
    want = run(inline)
    assert got == want and len(got) == len({n for n, _ in got}) > 8
    assert [n for n, _ in got][-2:] == ["metrics", "accuracy_by_epoch"]
    assert threaded == {"finalize-sink_0"} and inline == {threading.main_thread().name}
