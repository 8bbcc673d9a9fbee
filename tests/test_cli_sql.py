"""`tertiary sql` says no clearly: unknown parameter values list what the run holds, read-only
refusals and SQL errors are one line with exit 2, a runaway query hits its timeout (exit 4),
informational queries that used to be refused work, and exports never land in the run directory."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from tertiary.cli.commands import app

runner = CliRunner()


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    base = tmp_path_factory.mktemp("sqlcli")
    res = runner.invoke(app, ["simulate", "terminal-area", "--out", str(base / "ds"), "--aircraft", "6",
                              "--radars", "2", "--duration", "240", "--seed", "2"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["run", str(base / "ds"), "--out", str(base / "run"), "--no-report",
                              "--filters", "singer", "--methods", "arithmetic,information"])
    assert res.exit_code == 0, res.output
    return base / "run"


def sql(run_dir, *args, **kw):
    return runner.invoke(app, ["sql", str(run_dir), *args], terminal_width=200, **kw)


def test_unknown_parameter_value_lists_the_allowed_ones(run_dir):
    res = sql(run_dir, "accuracy_by_method", "-p", "segment=bogus")
    assert res.exit_code == 2
    assert "segment='bogus'" in res.output and "allowed: all" in res.output
    res = sql(run_dir, "accuracy_by_method", "-p", "method=nope")
    assert res.exit_code == 2 and "arithmetic" in res.output and "information" in res.output
    res = sql(run_dir, "accuracy_by_method", "-p", "method=information", "--format", "csv")
    assert res.exit_code == 0 and "information" in res.output


def test_unknown_parameter_name_and_report(run_dir):
    res = sql(run_dir, "accuracy_by_method", "-p", "colour=red")
    assert res.exit_code == 2 and "colour" in res.output and "segment" in res.output
    res = sql(run_dir, "no_such_report")
    assert res.exit_code == 2 and "accuracy_by_method" in res.output


def test_numeric_parameter_must_be_a_number(run_dir):
    res = sql(run_dir, "conflict_timeline", "-p", "bin_s=abc")
    assert res.exit_code == 2 and "bin_s" in res.output


def test_ids_are_plain_integers(run_dir):
    res = sql(run_dir, "--query", "SELECT 1025 AS target_id, 1025 AS n")
    assert res.exit_code == 0
    row = next(line for line in res.output.splitlines() if "1025" in line or "1,025" in line)
    assert [c.strip() for c in row.split("│")[1:3]] == ["1025", "1,025"]


def test_markup_in_results_is_text(run_dir):
    res = sql(run_dir, "--query", "SELECT '[/truth] [bold]x' AS t")
    assert res.exit_code == 0 and "[/truth] [bold]x" in res.output


@pytest.mark.parametrize("q", ["PIVOT metrics ON stage USING count(*)",
                               "SELECT name FROM pragma_table_info('metrics')",
                               "PRAGMA table_info('metrics')",
                               "SELECT INTERVAL 3 DAY AS i"])
def test_read_only_queries_that_were_refused_work(run_dir, q):
    res = sql(run_dir, "--query", q)
    assert res.exit_code == 0, res.output


@pytest.mark.parametrize("q", ["DELETE FROM metrics", "COPY metrics TO 'x.csv'", "ATTACH 'y.db'", "INSTALL httpfs",
                               "SELECT * FROM read_csv('/etc/passwd')", "PRAGMA enable_profiling",
                               "SET threads = 1"])
def test_writes_and_file_reads_are_refused_in_one_line(run_dir, q):
    res = sql(run_dir, "--query", q)
    assert res.exit_code == 2, res.output
    assert len(res.output.strip().splitlines()) == 1 and "Traceback" not in res.output


def test_sql_error_is_one_line(run_dir):
    res = sql(run_dir, "--query", "SELEC 1")
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1


def test_runaway_query_hits_the_timeout(run_dir):
    res = sql(run_dir, "--query", "SELECT count(*) FROM range(1000000000) a, range(1000000000) b", "--timeout", "1")
    assert res.exit_code == 4 and "timeout" in res.output


def test_export_never_inside_the_run_dir_nor_onto_a_directory(run_dir, tmp_path):
    res = sql(run_dir, "accuracy_by_method", "--out", str(run_dir / "x.csv"))
    assert res.exit_code == 2 and "inside the run directory" in res.output
    res = sql(run_dir, "accuracy_by_method", "--format", "csv", "--out", str(tmp_path))
    assert res.exit_code == 2 and "directory" in res.output
    res = sql(run_dir, "accuracy_by_method", "--out", str(tmp_path / "a.csv"))
    assert res.exit_code == 0 and (tmp_path / "a.csv").read_text().startswith("stage,")


def test_list_reads_as_a_table_of_questions(run_dir):
    res = sql(run_dir, "--list")
    assert res.exit_code == 0 and "what it answers" in res.output and "accuracy_by_method" in res.output
