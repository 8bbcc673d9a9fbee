"""The named SQL reports in sql/: shipped in the wheel and correct on a small run database."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import polars as pl
import pytest

import tertiary
from tertiary import pipeline
from tertiary.simulate import load_scenario, simulate
from tertiary.store.run_store import RunStore

SQL_DIR = Path(__file__).resolve().parents[1] / "sql"


def _query(name: str) -> str:
    return (SQL_DIR / f"{name}.sql").read_text()


def test_every_sql_file_has_a_header_comment():
    files = sorted(SQL_DIR.glob("*.sql"))
    assert files
    for f in files:
        assert f.read_text().startswith("-- "), f.name


def test_sql_and_scenarios_shipped_with_installed_package():
    pkg = Path(tertiary.__file__).resolve().parent
    if "site-packages" not in str(pkg):
        pytest.skip("running from a source checkout; the wheel check runs on the installed package")
    shipped = {p.name for p in (pkg / "sql").glob("*.sql")}
    assert shipped == {p.name for p in SQL_DIR.glob("*.sql")}
    from tertiary.simulate.config import builtin_dir, builtin_scenarios
    assert builtin_dir() == pkg / "datasets"
    assert {"big-box", "terminal-area", "adsb-paris", "adsb"} <= set(builtin_scenarios())
    from tertiary.evaluation.requirements import example_path, load_requirements
    assert example_path().is_file() and pkg in example_path().parents   # the example requirements ship
    assert load_requirements(example_path()).items


@pytest.fixture(scope="module")
def run_db(tmp_path_factory):
    cfg = load_scenario("big-box").replace(runs=2)
    ds = simulate(cfg)
    reports = ds.reports.with_columns(
        pl.when(pl.col("report_id") < 4).then(-1.0).otherwise(pl.col("range_m")).alias("range_m"))
    ds = dataclasses.replace(ds, reports=reports)
    out = tmp_path_factory.mktemp("run")
    pipeline.run(ds, out)
    return ds, out


def test_rejects_by_reason(run_db):
    _, out = run_db
    with RunStore.open(out) as store:
        df = store.sql(_query("rejects_by_reason"))
    assert df.columns == ["input_table", "stage", "reason", "rows", "example_row_index"]
    assert df.row(0)[:4] == ("reports", "ingest", "range_m: non-positive value -1.0", 4)


def test_reports_by_radar(run_db):
    ds, out = run_db
    with RunStore.open(out) as store:
        df = store.sql(_query("reports_by_radar"))
    assert df["radar_id"].to_list() == [1, 2]
    valid = ds.reports.filter(pl.col("range_m") >= 0)
    for rid in (1, 2):
        mine = valid.filter(pl.col("radar_id") == rid)
        row = df.filter(pl.col("radar_id") == rid)
        assert row["reports"].item() == mine.height
        # the radars run their own trackers (tracks may break): count from the reports themselves
        assert row["local_tracks"].item() == mine.select("run", "local_track_id").n_unique() >= 2
        res = mine["res_range_m"].to_numpy()
        res = res[~np.isnan(res)]
        assert row["res_range_sd_m"].item() == pytest.approx(np.std(res, ddof=1), rel=1e-9)


def test_run_summary(run_db):
    _, out = run_db
    with RunStore.open(out) as store:
        df = store.sql(_query("run_summary"))
    rows = dict(zip(df["key"], df["value"]))
    counts = json.loads(rows["rows"])
    assert counts["reports_in"] == 3408 and counts["reports_rejected"] == 4
    assert counts["reports_aligned"] + counts["reports_rejected"] == counts["reports_in"]
