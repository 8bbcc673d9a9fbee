"""Fuzz suite: a small hypothesis budget over every entry point, and one
regression test per distinct crash class the campaign found.

Every case runs in a memory-limited worker process (``fuzzing.Worker``) with a per-case timeout,
so an unbounded allocation or a hang fails its test instead of taking the machine. A case passes
when it ends in a clear error (exit 2/3/4, one line on stderr, no traceback; in Python a
``TertiaryError``) or in success with row accounting intact and every impossible row in
``rejects``. Failures print their reproducer: ``python tests/fuzzing.py replay '<case>'``.
The long campaign is ``benchmarks/fuzz_campaign.py``.
"""

from __future__ import annotations

import pytest

import fuzzing
from fuzzing import NAN, INF, dataset

# CI budget (cases per entry point); the whole file runs in under 3 minutes on 2 cores
BUDGET = {"validate": 40, "run": 36, "simulate": 20, "sql": 30, "api": 80}


@pytest.fixture(scope="module")
def worker(tmp_path_factory):
    bases = fuzzing.build_bases(tmp_path_factory.mktemp("fuzz-bases"))
    w = fuzzing.Worker(bases, tmp_path_factory.mktemp("fuzz-scratch"))
    yield w
    w.stop()


def _explain(outcomes: list[fuzzing.Outcome]) -> str:
    bad = [o for o in outcomes if not o.ok]
    seen: dict[str, fuzzing.Outcome] = {}
    for o in bad:
        seen.setdefault(o.signature, o)
    lines = [f"{len(bad)} of {len(outcomes)} cases broke the contract ({len(seen)} distinct):"]
    for sig, o in seen.items():
        lines += [f"- {sig}: {o.exc or '; '.join(o.problems)}"[:400], f"  {o.reproducer()[:600]}"]
        if o.tb_tail:
            lines.append("  " + o.tb_tail.strip().splitlines()[-1][:300])
    return "\n".join(lines)


def _check(worker: fuzzing.Worker, *cases: dict) -> list[fuzzing.Outcome]:
    outcomes = [worker.run(c) for c in cases]
    assert all(o.ok for o in outcomes), _explain(outcomes)
    return outcomes


# ---------------------------------------------------------------------------
# the CI budget of the hypothesis harness
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("entry", list(BUDGET))
def test_fuzz_budget(worker, entry):
    """Derandomised hypothesis cases of one entry point: no traceback, no silent acceptance, no hang."""
    outcomes = [worker.run(c) for c in fuzzing.draw_cases(entry, BUDGET[entry])]
    assert {o.cls for o in outcomes} <= set(fuzzing.CLASSES)
    assert all(o.ok for o in outcomes), _explain(outcomes)


# ---------------------------------------------------------------------------
# regression tests, one per distinct crash class (the listed ones and the campaign's findings)
# ---------------------------------------------------------------------------


def test_capacity_p_ge_1_does_not_fail_the_run(worker):
    """`--filters quasi_optimal` on an unmodified dataset: capacity p >= 1 is NaN, not a crash."""
    _check(worker, dataset("run", [], filters="quasi_optimal", methods="arithmetic,information", centralized=True),
           dataset("run", [], base="bb", filters="quasi_optimal"))


@pytest.mark.parametrize("col", ["radar_id", "time", "range_m", "azimuth_deg", "local_track_id"])
def test_run_missing_required_column_is_clear_error(worker, col):
    """`run` turns a SchemaError (dropped required column) into exit 3, as `validate` does."""
    op = [{"op": "drop_col", "table": "reports", "col": col}]
    out = _check(worker, dataset("run", op), dataset("validate", op))
    assert all(o.cls == "clear_error" and o.exit_code == 3 for o in out), [(o.cls, o.exit_code) for o in out]


@pytest.mark.parametrize("to", ["int", "float", "date", "duration"])
def test_time_dtype_changes_do_not_crash(worker, to):
    op = [{"op": "cast", "table": "reports", "col": "time", "to": to}]
    _check(worker, dataset("run", op), dataset("validate", op))


@pytest.mark.parametrize("col,to", [("est_cov", "string"), ("range_m", "string"), ("callsign", "binary")])
def test_column_dtype_changes_do_not_crash(worker, col, to):
    """est_cov as a string; a Binary text column (a Rust panic when writing rejects)."""
    op = [{"op": "cast", "table": "reports", "col": col, "to": to}]
    _check(worker, dataset("run", op), dataset("validate", op))


@pytest.mark.parametrize("file", ["radars.parquet", "reports.parquet"])
@pytest.mark.parametrize("how", fuzzing.FILE_OPS)
def test_unreadable_parquet_is_clear_error(worker, file, how):
    """Truncated, garbage, CSV-renamed, empty, Arrow IPC or missing Parquet files: exit 3."""
    op = [{"op": "file", "file": file, "how": how}]
    out = _check(worker, dataset("validate", op), dataset("run", op))
    assert all(o.cls == "clear_error" and o.exit_code == 3 for o in out), [(o.cls, o.exit_code, o.exc) for o in out]


@pytest.mark.parametrize("how", fuzzing.TOML_OPS)
def test_scenario_toml_malformed_does_not_crash(worker, how):
    """Garbage, UTF-16, unknown key, no origin, origin "abc"/NaN/off the globe, a path as name."""
    op = [{"op": "toml", "how": how}]
    _check(worker, dataset("run", op, default_out=how == "name_path"), dataset("validate", op))


@pytest.mark.parametrize("ops", [
    [{"op": "set_all", "table": "reports", "col": "range_m", "value": -1.0}],
    [{"op": "head", "table": "reports", "n": 0}],
    [{"op": "head", "table": "radars", "n": 0}],
    [{"op": "set_all", "table": "radars", "col": "scan_period_s", "value": -1.0}],
    [{"op": "head", "table": "reports", "n": 1}],
    [{"op": "head", "table": "truth", "n": 0}],
], ids=["all-reports-invalid", "zero-reports", "zero-radars", "every-radar-rejected", "one-report", "zero-truth"])
def test_no_valid_report_left_is_not_a_crash(worker, ops):
    """Degenerate inputs (align.epoch_grid TypeError): a clear message or an accounted success."""
    _check(worker, dataset("run", ops), dataset("validate", ops))


def test_truth_dated_1970_and_2100_bounded_allocation(worker):
    """Two truth rows dated 1970 and 2100 asked for 12.2 GiB in safety/alerts.py."""
    op = [{"op": "set", "table": "truth", "col": "time", "value": "year:1970", "impossible": True, "rows": [0.1]},
          {"op": "set", "table": "truth", "col": "time", "value": "year:2100", "impossible": True, "rows": [0.9]}]
    _check(worker, dataset("run", op), dataset("run", op, base="bb"))


@pytest.mark.parametrize("value", [1e-9, 1e300])
def test_scan_period_extremes_bounded(worker, value):
    """scan_period_s = 1e-9 asked for 3.78 TiB in align.py; 1e300 overflowed int64 silently."""
    op = [{"op": "set", "table": "radars", "col": "scan_period_s", "value": value, "impossible": True,
           "rows": [0.0]}]
    _check(worker, dataset("run", op), dataset("validate", op))


@pytest.mark.parametrize("col,value", [("range_m", 1e300), ("range_m", -1e300), ("x_m", 1e300), ("x_m", -1e300),
                                       ("vx_mps", 1e300), ("est_cov", "big"), ("est_range_var_m2", 1e300)])
def test_values_1e300_do_not_overflow(worker, col, value):
    """±1e300 overflowed the KD-tree and the conflict code; est_cov 1e300 made a singular matrix."""
    op = [{"op": "set", "table": "reports", "col": col, "value": value, "impossible": col == "range_m",
           "rows": [0.2, 0.5]}]
    _check(worker, dataset("run", op), dataset("run", op, base="bb", filters="imm_sym"))


@pytest.mark.parametrize("table,col", [("reports", "callsign"), ("radars", "name"), ("radars", "timing"),
                                       ("truth", "callsign")])
@pytest.mark.parametrize("text", ["[/truth]", "[/]"])
def test_markup_text_in_data_is_not_interpreted(worker, table, col, text):
    """Text like "[/]" in data and in reject reasons raised rich MarkupError."""
    op = [{"op": "text", "table": table, "col": col, "value": text, "rows": [0.0, 0.6]}]
    _check(worker, dataset("run", op, report=True), dataset("validate", op))


@pytest.mark.parametrize("query,expect", [
    ("SELECT INTERVAL 1 DAY AS i", "ok"), ("SELECT '[/]' AS x, '[/truth]' AS y", "ok"),
    ("PIVOT (SELECT radar_id, run FROM aligned) ON run USING count(*)", "ok"),
    ("SELECT * FROM pragma_table_info('aligned')", "ok"),
    ("SELECT '\udcff'", "error"), ("\udcff\udcfe", "error"),
    ("ATTACH '{tmp}/x.duckdb' AS x", "error"), ("INSTALL httpfs", "error"), ("COPY aligned TO '{tmp}/x.csv'", "error"),
    ("SELECT * FROM read_csv('/etc/passwd')", "error"), ("DROP TABLE aligned", "error"),
])
def test_sql_query_hostile_and_odd_results(worker, query, expect):
    """INTERVAL results, markup in results, invalid UTF-8; PIVOT/pragma_table_info work; writes refused."""
    out = _check(worker, {"entry": "sql", "args": [], "expect": expect, "query": query})
    assert out[0].cls == ("success" if expect == "ok" else "clear_error"), out[0]


@pytest.mark.parametrize("fmt", [[], ["--format", "csv"], ["--out", "{tmp}/o.csv"], ["--out", "{tmp}/o.parquet"]],
                         ids=["table", "csv", "out-csv", "out-parquet"])
@pytest.mark.parametrize("query", ["SELECT 'x'::BLOB AS b", "SELECT MAP {'k': 1} AS m",
                                   "SELECT 'infinity'::TIMESTAMP AS ts", "SELECT 'infinity'::DATE AS d"],
                         ids=["blob", "map", "infinite-timestamp", "infinite-date"])
def test_sql_odd_result_types_print_and_export(worker, query, fmt):
    """Found by the campaign: BLOB/MAP results to CSV raised polars ComputeError (sql_reports.frame_to_csv);
    infinite TIMESTAMP/DATE results raised a Rust PanicException when printed or written as CSV."""
    _check(worker, {"entry": "sql", "args": fmt, "expect": "any", "query": query})


@pytest.mark.parametrize("args", [["--out", "{tmp}"], ["--out", "{run}/results.duckdb"], ["--out", "{run}"]])
def test_sql_out_directory_or_run_file_refused(worker, args):
    """`--out` naming a directory, or a file inside the run directory, is a clear error."""
    _check(worker, {"entry": "sql", "args": args, "expect": "error", "query": "SELECT 1 AS x"})


def test_sql_cross_join_hits_statement_timeout(worker):
    """A cross join ran until killed: with --timeout it must end in a clear error, not a hang."""
    case = {"entry": "sql", "args": ["--timeout", "2"], "expect": "error", "subprocess": True, "timeout": 40.0,
            "query": fuzzing.CROSS_JOIN}
    out = _check(worker, case)
    assert out[0].cls == "clear_error", out[0]


@pytest.mark.parametrize("obj", ["none", "dict", "numpy", "lazy", "arrow", "list", "str", "columns_dict"])
@pytest.mark.parametrize("strict", [True, False])
def test_api_validate_odd_objects(worker, obj, strict):
    """tertiary.validate(None | dict | numpy | LazyFrame | pyarrow.Table, ...) raised AttributeError."""
    _check(worker, {"entry": "api", "obj": obj, "kind": "reports", "table": "reports", "ops": [], "strict": strict,
                    "with_radars": False, "base": "ta"})


def test_api_validate_unknown_kind(worker):
    _check(worker, {"entry": "api", "obj": "frame", "kind": "nope", "table": "reports", "ops": [], "strict": False,
                    "with_radars": False, "base": "ta"})


@pytest.mark.parametrize("extra", [extra for extra, _ in fuzzing.SIM_BAD], ids=lambda a: " ".join(a))
def test_simulate_bad_option_is_clear_error(worker, extra):
    """Counts < 1, non-finite durations and anomaly options, malformed strings: exit 2 before any work."""
    out = _check(worker, {"entry": "simulate", "args": fuzzing.SIM_BASE + extra, "impossible": True, "out": "new"})
    assert out[0].exit_code == 2, out[0]


@pytest.mark.parametrize("case", [
    {"entry": "simulate", "args": ["simulate", "nope", "--duration", "30"], "impossible": True, "out": "new"},
    {"entry": "simulate", "args": fuzzing.SIM_BASE, "impossible": True, "out": "file"},
    *[{"entry": "simulate", "args": ["simulate", "adsb", "--duration", "30"], "truth": t, "impossible": True,
       "out": "new"} for t in ("missing", "garbage", "empty", "csv", "none")],
], ids=["unknown-scenario", "out-is-a-file", "truth-missing", "truth-garbage", "truth-empty", "truth-csv",
        "truth-no-columns"])
def test_simulate_bad_scenario_truth_or_out(worker, case):
    _check(worker, case)


# ---------------------------------------------------------------------------
# silent acceptances listed in the issue: each impossible value is rejected with a reason
# ---------------------------------------------------------------------------

SILENT = [
    ("reports", "range_m", 1e300), ("reports", "range_m", "2max"),
    *[("reports", "time", f"year:{y}") for y in (1, 1970, 2100, 9999)],
    ("reports", "est_range_var_m2", INF), ("reports", "est_range_var_m2", -1.0), ("reports", "est_cov", "asym"),
    ("reports", "est_cov", "negdiag"), ("reports", "elevation_deg", 95.0), ("reports", "elevation_deg", -95.0),
    ("radars", "sigma_range_m", 1e300), ("radars", "sigma_azimuth_deg", 1e300), ("radars", "scan_period_s", 1e300),
    ("reports", "azimuth_deg", NAN),
]


@pytest.mark.parametrize("table,col,value", SILENT, ids=lambda v: str(v))
def test_impossible_value_is_rejected_not_silent(worker, table, col, value):
    op = [{"op": "set", "table": table, "col": col, "value": value, "impossible": True, "rows": [0.3]}]
    out = _check(worker, dataset("run", op), dataset("validate", op))
    assert all(o.cls in ("rejects", "clear_error") for o in out), [(o.cls, o.problems) for o in out]


def test_range_as_boolean_is_not_a_number(worker):
    op = [{"op": "cast", "table": "reports", "col": "range_m", "to": "bool", "impossible": True}]
    _check(worker, dataset("run", op), dataset("validate", op))


def test_traceback_only_with_debug(worker, tmp_path):
    """The same unreadable file: one line without --debug, the exception itself with --debug."""
    import shutil

    from typer.testing import CliRunner

    from tertiary.cli.commands import app

    ds = tmp_path / "ds"
    shutil.copytree(worker.bases / "ta", ds)
    (ds / "reports.parquet").write_bytes(b"garbage")
    plain = CliRunner().invoke(app, ["validate", str(ds)])
    assert plain.exit_code == 3 and "Traceback" not in plain.stderr and len(plain.stderr.strip().splitlines()) == 1
    debug = CliRunner().invoke(app, ["--debug", "validate", str(ds)])
    assert debug.exception is not None and not isinstance(debug.exception, SystemExit), debug.stderr


@pytest.mark.parametrize("value", [1e300, 1e12])
def test_api_range_beyond_any_radar_rejected_without_radars(worker, value):
    """Found by the campaign: tertiary.validate(reports) without a radars table accepts range_m = 1e300
    (the absolute band is (0, inf)); no radar can see beyond max(max_range_m) x margin."""
    op = [{"op": "set", "table": "reports", "col": "range_m", "value": value, "impossible": True, "rows": [0.3]}]
    out = _check(worker, {"entry": "api", "obj": "frame", "kind": "reports", "table": "reports", "ops": op,
                          "strict": False, "with_radars": False, "base": "ta"})
    assert out[0].cls == "rejects", out[0]
