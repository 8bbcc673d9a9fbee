"""The command line: simulate, validate, run."""

from __future__ import annotations

import duckdb
import polars as pl
from typer.testing import CliRunner

from tertiary.cli import app

runner = CliRunner()


def test_simulate_validate_run(tmp_path):
    out = tmp_path / "ds"
    res = runner.invoke(app, ["simulate", "terminal-area", "--out", str(out), "--aircraft", "12", "--radars", "3",
                              "--duration", "300", "--seed", "5"])
    assert res.exit_code == 0, res.output
    for name in ("radars.parquet", "reports.parquet", "truth.parquet", "scenario.toml"):
        assert (out / name).exists()
    assert pl.read_parquet(out / "radars.parquet").height == 3
    assert pl.read_parquet(out / "truth.parquet")["truth_id"].n_unique() == 12

    res = runner.invoke(app, ["validate", str(out)])
    assert res.exit_code == 0 and "nothing rejected" in res.output

    # corrupt some rows: validation names them, the run keeps every row accounted for
    rep = pl.read_parquet(out / "reports.parquet")
    bad = rep.with_columns(pl.when(pl.int_range(pl.len()) < 3).then(-5.0).otherwise(pl.col("range_m")).alias("range_m"))
    bad.write_parquet(out / "reports.parquet")
    res = runner.invoke(app, ["validate", str(out)])
    assert res.exit_code == 0 and "range_m: negative value -5.0" in res.output
    res = runner.invoke(app, ["validate", str(out), "--strict"])
    assert res.exit_code == 1 and "range_m" in res.output

    run_dir = tmp_path / "run"
    res = runner.invoke(app, ["run", str(out), "--out", str(run_dir)])
    assert res.exit_code == 0, res.output
    con = duckdb.connect(str(run_dir / "results.duckdb"), read_only=True)
    n_valid = con.execute("SELECT count(*) FROM reports").fetchone()[0]
    n_bad = con.execute("SELECT count(*) FROM rejects WHERE stage = 'ingest'").fetchone()[0]
    assert (n_valid, n_bad) == (rep.height - 3, 3)
    # row accounting: every input report is aligned or rejected, exactly once
    n_aligned = con.execute("SELECT count(DISTINCT report_id) FROM aligned").fetchone()[0]
    n_rej = con.execute("SELECT count(*) FROM rejects WHERE input_table = 'reports'").fetchone()[0]
    both = con.execute("SELECT count(*) FROM rejects r JOIN (SELECT DISTINCT report_id FROM aligned) a "
                       "USING (report_id)").fetchone()[0]
    assert n_aligned + n_rej == rep.height and both == 0
    tables = {r[0] for r in con.execute("SHOW TABLES").fetchall()}
    assert {"aligned", "associations", "fused", "clusters", "rejects", "metrics", "run"} <= tables
    con.close()


def test_run_simulates_scenario(tmp_path):
    res = runner.invoke(app, ["run", "--scenario", "big-box", "--runs", "2", "--out", str(tmp_path / "bb")])
    assert res.exit_code == 0, res.output
    con = duckdb.connect(str(tmp_path / "bb" / "results.duckdb"), read_only=True)
    assert con.execute("SELECT count(DISTINCT run) FROM reports").fetchone()[0] == 2
    keys = {r[0] for r in con.execute("SELECT key FROM run").fetchall()}
    assert {"scenario", "versions", "fingerprints", "rows", "timings"} <= keys
    con.close()


def test_adsb_requires_truth(tmp_path):
    res = runner.invoke(app, ["simulate", "adsb", "--out", str(tmp_path / "x")])
    assert res.exit_code != 0 and "--truth" in res.output


def test_unknown_scenario(tmp_path):
    res = runner.invoke(app, ["simulate", "nowhere", "--out", str(tmp_path / "x")])
    assert res.exit_code != 0
