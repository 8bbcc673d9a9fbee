"""The HTML report: one self-contained file, every figure from the sql/ reports, bounded size,
robust to missing tables, and the `tertiary report` / `tertiary run` commands."""

from __future__ import annotations

import dataclasses
import re
import shutil

import polars as pl
import pytest
from typer.testing import CliRunner

from tertiary import pipeline
from tertiary.cli import app
from tertiary.report import MAX_POINTS, REPORT_FILENAME, _thin, build_report, figure_count
from tertiary.simulate import load_scenario, simulate, write_dataset
from tertiary.store import RunStore

runner = CliRunner()

#: figures of a complete run: map, range, range rate, acceleration, residuals, RMSE over time,
#: a-posteriori vs a-priori, accuracy bars, conflict timeline, P_pob, capacity
N_FIGURES = 11
SEED_FIGURES = ["4.4", "4.5", "4.6", "4.7", "4.9", "4.10", "4.11", "5.2", "5.3"]


def small_dataset():
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=300.0, traffic=dataclasses.replace(cfg.traffic, aircraft=20,
                                                                                  conflict_pairs=3))
    return simulate(cfg)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("report_run")
    pipeline.run(small_dataset(), out, pipeline.PipelineConfig(filters=("singer",)))
    res = runner.invoke(app, ["report", str(out)])
    assert res.exit_code == 0, res.output
    assert "wrote" in res.output and REPORT_FILENAME in res.output
    return out


@pytest.fixture(scope="module")
def page(run_dir) -> str:
    return (run_dir / REPORT_FILENAME).read_text(encoding="utf-8")


def test_one_self_contained_file(run_dir, page):
    assert sorted(p.name for p in run_dir.iterdir()) == [REPORT_FILENAME, "results.duckdb"]   # no temp files
    assert page.startswith("<!DOCTYPE html>") and page.rstrip().endswith("</html>")
    # plotly.js inline exactly once, nothing loaded from a CDN or any other URL
    assert len(re.findall(r"plotly\.js v\d+\.\d+\.\d+", page)) == 1
    assert not re.search(r"<script[^>]*\bsrc=", page)
    assert not re.search(r"<link[^>]*\bhref=\"?https?:", page)


def test_every_figure_is_embedded(page):
    assert figure_count(page) == N_FIGURES
    assert page.count('class="plotly-graph-div"') == N_FIGURES
    assert page.count("window.__reportDone(") == N_FIGURES          # each marks itself rendered
    assert page.count("Plotly.newPlot(") == N_FIGURES
    assert '<pre id="js-errors"' in page
    for fig in SEED_FIGURES:
        assert f"fig. {fig})" in page or f"fig. {fig}," in page or f"figs. {fig}" in page, fig
    assert "Not available" not in page


def test_figures_and_tables_come_from_sql_reports(page):
    for name in ("trajectories", "radar_sites", "radar_kinematics", "radar_residuals_over_time", "radar_residuals",
                 "radar_accuracy_over_time", "accuracy_over_time", "aposteriori_vs_apriori", "aposteriori_gain",
                 "accuracy_by_method", "association_quality", "track_quality", "cluster_statistics",
                 "conflict_timeline", "alert_scores", "conflicts", "capacity_by_method", "stage_timings",
                 "row_accounting", "rejects_by_reason", "reports_by_radar"):
        assert f"sql/{name}.sql" in page, name
    # run metadata: configuration, versions, fingerprints, timings, row accounting
    for text in ("Pipeline configuration", "Versions", "Input fingerprints", "Stage timings", "Row accounting",
                 "reports_in", "duckdb", "polars"):
        assert text in page, text


def test_size_is_bounded(run_dir):
    size = (run_dir / REPORT_FILENAME).stat().st_size
    assert size < 20e6
    assert size < 8e6            # plotly.js (≈ 4.7 MB) plus a few hundred kB of thinned data


def test_thin():
    frame = pl.DataFrame({"i": range(10_001)})
    thin = _thin(frame)
    assert thin.height <= MAX_POINTS + 1
    assert thin["i"][0] == 0 and thin["i"][-1] == 10_000
    assert _thin(frame.head(5)).height == 5


def test_report_survives_missing_tables(run_dir, tmp_path):
    shutil.copy(run_dir / "results.duckdb", tmp_path / "results.duckdb")
    with RunStore.update(tmp_path) as store:
        for table in ("conflicts", "accuracy_by_epoch", "truth"):
            store.con.execute(f"DROP TABLE {table}")
    out = build_report(tmp_path, tmp_path / "r.html")
    page = out.read_text()
    assert "Not available for this run" in page
    assert 0 < figure_count(page) < N_FIGURES
    assert page.count('class="plotly-graph-div"') == figure_count(page)


def test_report_command_errors(tmp_path):
    res = runner.invoke(app, ["report", str(tmp_path)])
    assert res.exit_code == 1 and "no run database" in res.output


def test_run_writes_database_and_report(tmp_path):
    ds_dir = tmp_path / "ds"
    write_dataset(small_dataset(), ds_dir)
    res = runner.invoke(app, ["run", str(ds_dir), "--out", str(tmp_path / "a"), "--filters", "singer",
                              "--methods", "arithmetic,apriori,aposteriori_seed,aposteriori", "--no-report"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "a" / "results.duckdb").is_file() and not (tmp_path / "a" / REPORT_FILENAME).exists()
    res = runner.invoke(app, ["run", str(ds_dir), "--out", str(tmp_path / "b"), "--filters", "singer",
                              "--methods", "arithmetic,apriori,aposteriori_seed,aposteriori"])
    assert res.exit_code == 0, res.output
    html_path = tmp_path / "b" / REPORT_FILENAME
    assert html_path.is_file()
    flat = " ".join(res.output.split())
    assert "results.duckdb" in flat and REPORT_FILENAME in flat and "done in" in flat
    assert figure_count(html_path.read_text()) == N_FIGURES
