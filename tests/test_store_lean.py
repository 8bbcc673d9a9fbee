"""The lean run database: the run's large tables stored in a lean physical layout
behind views with the old names give every SQL report and every table read-back the same answer
as the tables stored as given (to float32 round-off where a column is narrowed)."""

from __future__ import annotations

import dataclasses
import importlib.util
import re
import sys
from pathlib import Path

import duckdb
import numpy as np
import polars as pl
import pytest

from tertiary import pipeline
from tertiary.store import sql_reports
from tertiary.io.dataset import write_dataset
from tertiary.simulate import load_scenario, simulate
from tertiary.store.run_store import LEAN_PREFIX, RunStore

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_store.py"
sys.path.insert(0, str(_PATH.parent))
_spec = importlib.util.spec_from_file_location("bench_store", _PATH)
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """One small job (2 fusion methods + centralised, one tracker, conflicts, truth) stored twice."""
    cfg = load_scenario("terminal-area")
    # 10 min: large enough that the tables span several of DuckDB's 256 kB blocks (the size test
    # compares files, whose growth is counted in blocks)
    cfg = dataclasses.replace(cfg, duration_s=600.0, traffic=dataclasses.replace(cfg.traffic, aircraft=30,
                                                                                 conflict_pairs=3))
    root = tmp_path_factory.mktemp("lean")
    write_dataset(simulate(cfg), root / "ds")
    pcfg = pipeline.PipelineConfig(methods=("arithmetic", "information"), filters=("singer",))
    tables, info = bench.process(root / "ds", pcfg)
    before = bench.store(tables, info, root / "before", lean=False)
    after = bench.store(tables, info, root / "after", lean=True)
    return {"before": before, "after": after, "tables": dict(tables), "dataset": root / "ds"}


def test_every_sql_report_same_before_and_after(runs):
    diffs = bench.compare(runs["before"], runs["after"])
    assert not diffs, diffs
    # not vacuous: the reports that read the lean tables return rows
    with RunStore.open(runs["after"]) as st:
        for name in ("radar_accuracy_over_time", "conflicts", "conflict_timeline", "row_accounting",
                     "association_quality", "alert_episodes"):
            assert sql_reports.run_report(st, name).height > 0, name


def test_lean_tables_are_views_over_smaller_parts(runs):
    with RunStore.open(runs["after"]) as st:
        kinds = dict(st.sql("SELECT table_name, table_type FROM information_schema.tables").iter_rows())
        for t in ("aligned", "fused", "tracks", "reports"):
            assert kinds[t] == "VIEW" and kinds[LEAN_PREFIX + t] == "BASE TABLE", t
        assert kinds[LEAN_PREFIX + "fused__shared"] == "BASE TABLE"
        assert kinds["conflicts"] == kinds["truth"] == kinds["metrics"] == "BASE TABLE"
        assert not any(t.startswith(LEAN_PREFIX) for t in st.tables())
        phys = lambda t: set(st.sql(f'SELECT * FROM "{LEAN_PREFIX}{t}" LIMIT 0').columns)  # noqa: E731
        # aligned keeps only what is not the report's own; age_s is recomputed
        assert phys("aligned").isdisjoint({"run", "radar_id", "local_track_id", "time", "res_range_m", "mode_s",
                                           "truth_id", "altitude_m", "age_s"})
        assert "cov_diag" not in phys("tracks") and "cov_ut" not in phys("tracks") and "cov_ut__20" in phys("tracks")
        types = dict(st.sql(f"DESCRIBE {LEAN_PREFIX}tracks").select("column_name", "column_type").iter_rows())
        assert types["x_m"] == "FLOAT" and types["cov_ut__0"] == "FLOAT"
        # the views give the old types
        types = dict(st.sql("DESCRIBE tracks").select("column_name", "column_type").iter_rows())
        assert types["x_m"] == "DOUBLE" and types["cov_ut"] == "FLOAT[21]" and types["cov_diag"] == "DOUBLE[6]"
    assert runs["after"].stat().st_size < 0.9 * runs["before"].stat().st_size


def test_narrowed_columns_keep_float32_precision_and_the_rest_is_exact(runs):
    with RunStore.open(runs["after"]) as st:
        tracks, aligned = st.read("tracks"), st.read("aligned")
    given = runs["tables"]["tracks"]
    x, y = tracks["x_m"].to_numpy(), given["x_m"].to_numpy()
    rel = np.abs(x - y) / np.maximum(np.abs(y), 1e-30)
    assert 0 < rel.max() <= 2.0 ** -24          # narrowed: float32 round-off, no more
    assert tracks["track_id"].equals(given["track_id"]) and tracks["epoch"].equals(given["epoch"])
    src = runs["tables"]["aligned"]
    for c in ("report_id", "run", "radar_id", "local_track_id", "time", "mode_s", "truth_id", "res_range_m"):
        assert aligned[c].equals(src[c], check_dtypes=True, null_equal=True), c   # joined back exactly
    assert np.allclose(aligned["age_s"].to_numpy(), src["age_s"].to_numpy(), rtol=0, atol=1e-9)
    # the covariance comes back as the full symmetric Float64 matrix (float32 values)
    cov = tracks["cov"].to_numpy().reshape(-1, 6, 6)
    assert np.array_equal(cov, cov.transpose(0, 2, 1))


def _normalised_html(run_dir: Path) -> str:
    """The report's HTML without what differs between two renderings of one run (its build time,
    the database's path)."""
    from tertiary.report.html import render_report
    page, _n = render_report(run_dir)
    page = re.sub(r"Report built\s+\S+ \S+ UTC in [0-9.]+ s", "Report built", page)
    return page.replace("<wbr>", "").replace(str(run_dir), "RUN")


def test_html_report_same_before_and_after(runs):
    before, after = _normalised_html(runs["before"].parent), _normalised_html(runs["after"].parent)
    assert len(before) > 10_000
    assert before == after


# ----------------------------------------------------------------------------- the checks behind each rule


def _aligned_case(n: int = 6) -> tuple[pl.DataFrame, pl.DataFrame]:
    t0 = pl.datetime(2024, 1, 1, time_zone="UTC")
    reports = pl.DataFrame({"report_id": pl.Series(range(n), dtype=pl.UInt64), "run": pl.Series([0] * n, dtype=pl.UInt32),
                            "radar_id": pl.Series([1] * n, dtype=pl.UInt32), "mode_s": ["a", None, "b", "c", "d", "e"][:n]})
    reports = reports.with_columns((t0 + pl.duration(seconds=pl.int_range(n))).alias("time"))
    aligned = reports.with_columns((pl.col("time") + pl.duration(seconds=1)).alias("epoch"),
                                   pl.lit(1.0).alias("age_s"), pl.Series("x_m", np.linspace(1e4, 2e5, n)))
    return reports, aligned


def test_aligned_keeps_a_column_that_differs_from_its_report(tmp_path):
    reports, aligned = _aligned_case()
    aligned = aligned.with_columns(pl.when(pl.col("report_id") == 2).then(pl.lit("zz")).otherwise("mode_s")
                                   .alias("mode_s"))
    with RunStore.create(tmp_path) as st:
        st.write("reports", reports)
        st.write("aligned", aligned)
    with RunStore.open(tmp_path) as st:
        back = st.read("aligned")
        phys = st.sql(f"SELECT * FROM {LEAN_PREFIX}aligned LIMIT 0").columns
    assert "mode_s" in phys and "radar_id" not in phys and "age_s" not in phys
    assert back.select(pl.exclude("x_m")).equals(aligned.select(pl.exclude("x_m")), null_equal=True)
    assert back.columns == aligned.columns


def test_aligned_keeps_its_columns_when_its_reports_ids_repeat(tmp_path):
    """The report columns are joined back by report_id only where that join is one to one: a
    reports table in which an id of the aligned rows names two reports keeps aligned whole; ids
    that repeat among reports no aligned row names do not matter (the check reads the reports
    the part names only)."""
    reports, aligned = _aligned_case()
    dup = pl.concat([reports, reports.filter(pl.col("report_id") == 3).with_columns(pl.lit("q").alias("mode_s"))])
    far = reports.filter(pl.col("report_id") == 0).with_columns(pl.lit(99, pl.UInt64).alias("report_id"))
    for name, rep, dropped in (("dup", dup, False), ("far", pl.concat([reports, far, far]), True)):
        with RunStore.create(tmp_path / name) as st:
            st.write("reports", rep)
            st.write("aligned", aligned)
        with RunStore.open(tmp_path / name) as st:
            back = st.read("aligned")
            names = st.sql("SELECT table_name FROM information_schema.tables")["table_name"].to_list()
            phys = st.sql(f"SELECT * FROM {LEAN_PREFIX + 'aligned' if LEAN_PREFIX + 'aligned' in names else 'aligned'}"
                          " LIMIT 0").columns
        assert ("mode_s" not in phys) == dropped, name
        assert back.select(pl.exclude("x_m")).equals(aligned.select(pl.exclude("x_m")), null_equal=True)


def test_aligned_parts_whose_report_ids_interleave_are_checked_against_their_own_reports(tmp_path):
    """A window's reports need not have contiguous ids (the national scenario's span nearly the
    whole table): each part is checked against the reports it names, so two parts with
    interleaved ids both drop the report columns, and a mismatch in one row of the second part
    keeps that column for the whole table (its parts then no longer share one layout)."""
    reports, aligned = _aligned_case()
    evens, odds = (aligned.filter(pl.col("report_id") % 2 == k) for k in (0, 1))
    bad_odds = odds.with_columns(pl.when(pl.col("report_id") == 3).then(pl.lit("zz")).otherwise("mode_s")
                                 .alias("mode_s"))
    for name, second, dropped in (("same", odds, True), ("differs", bad_odds, False)):
        with RunStore.create(tmp_path / name) as st:
            st.write("reports", reports)
            st.write_parts("aligned", lambda second=second: iter([evens, second]))
        with RunStore.open(tmp_path / name) as st:
            back = st.read("aligned").sort("report_id")
            phys = st.sql(f"SELECT * FROM {LEAN_PREFIX}aligned LIMIT 0").columns
        assert ("mode_s" not in phys) == dropped and "radar_id" not in phys, name
        want = pl.concat([evens, second]).sort("report_id")
        assert back.select(pl.exclude("x_m")).equals(want.select(pl.exclude("x_m")), null_equal=True), name


def test_aligned_without_reports_is_stored_whole(tmp_path):
    _, aligned = _aligned_case()
    with RunStore.create(tmp_path) as st:
        st.write("aligned", aligned)
    with RunStore.open(tmp_path) as st:     # nothing to join the report columns from: a plain table
        kinds = dict(st.sql("SELECT table_name, table_type FROM information_schema.tables").iter_rows())
        assert kinds == {"aligned": "BASE TABLE"}
        assert st.read("aligned").equals(aligned)


def _fused_case() -> pl.DataFrame:
    t0 = pl.datetime(2024, 1, 1, time_zone="UTC")
    rows = []
    for m in ("arithmetic", "information", "centralized"):
        for k in range(4):
            rows.append({"run": 0, "epoch": k // 2, "target_id": k % 2, "method": m, "x_m": 1e4 + k,
                         "alt_m": 100.0 * k + (7.0 if m == "centralized" else 0.0),
                         "mode_s": None if m == "centralized" else f"m{k % 2}"})
    f = pl.DataFrame(rows).with_columns(pl.col("run").cast(pl.UInt32), pl.col("target_id").cast(pl.UInt64),
                                        (t0 + pl.duration(seconds=pl.col("epoch"))).alias("epoch"))
    return f


def test_fused_method_independent_columns_stored_once_per_target(tmp_path):
    fused = _fused_case()
    with RunStore.create(tmp_path) as st:
        st.write("fused", fused)
    with RunStore.open(tmp_path) as st:
        shared = st.sql(f"SELECT * FROM {LEAN_PREFIX}fused__shared")
        back = st.read("fused")
    assert shared.height == 4 and {"alt_m", "mode_s"} <= set(shared.columns)
    assert back.select(pl.exclude("x_m", "alt_m")).equals(fused.select(pl.exclude("x_m", "alt_m")), null_equal=True)
    assert np.array_equal(back["alt_m"].to_numpy(), fused["alt_m"].to_numpy())   # exact in float32


def _one_key_disagrees() -> pl.DataFrame:
    """:func:`_fused_case` where one (epoch, target) has a height of its own in one method (as a
    primary-only target's height comes from each method's own position)."""
    odd = (pl.col("method") == "information") & (pl.col("alt_m") == 200.0)
    return _fused_case().with_columns(pl.when(odd).then(pl.col("alt_m") + 0.5).otherwise("alt_m").alias("alt_m"))


def test_a_key_whose_methods_disagree_keeps_its_rows_own_values(tmp_path):
    fused = _one_key_disagrees()
    with RunStore.create(tmp_path) as st:
        st.write("fused", fused)
    with RunStore.open(tmp_path) as st:
        shared = st.sql(f"SELECT * FROM {LEAN_PREFIX}fused__shared")
        back = st.read("fused")
    # the three keys that agree are shared, each column of them; the fourth keeps its own
    assert shared.height == 3 and {"alt_m", "mode_s"} <= set(shared.columns)
    assert 200.0 not in shared["alt_m"].to_list()
    assert np.array_equal(back["alt_m"].to_numpy(), fused["alt_m"].to_numpy())
    assert back["mode_s"].equals(fused["mode_s"])


def test_a_part_with_a_disagreeing_key_is_appended_in_the_tables_layout(tmp_path, monkeypatch):
    """The parts of a streamed ``fused`` table keep one layout when a later part holds a key
    whose methods disagree: appended as they come, never concatenated and written whole."""
    whole = _one_key_disagrees().sort("epoch", maintain_order=True)
    parts = whole.partition_by("epoch", maintain_order=True)
    assert parts[1]["alt_m"].to_list().count(200.5) == 1          # the odd key is in the later part
    with RunStore.create(tmp_path / "whole") as st:
        st.write("fused", whole)
    with RunStore.create(tmp_path / "parts") as st:
        monkeypatch.setattr(RunStore, "write", lambda *a: pytest.fail("the parts were written whole"))
        st.write_parts("fused", lambda: iter(parts))
    a, b = _dump(tmp_path / "whole"), _dump(tmp_path / "parts")
    for t in a:
        assert a[t].equals(b[t], null_equal=True), t


def _tracks_case(n: int = 5) -> pl.DataFrame:
    rng = np.random.default_rng(1)
    a = rng.normal(size=(n, 6, 6))
    cov = a @ a.transpose(0, 2, 1) * 100.0
    diag = np.diagonal(cov, axis1=1, axis2=2).copy()
    return pl.DataFrame({"track_id": pl.Series(range(n), dtype=pl.UInt64), "x_m": rng.normal(size=n) * 1e5,
                         "cov": pl.Series(cov.reshape(n, 36), dtype=pl.Array(pl.Float64, 36)),
                         "cov_diag": pl.Series(diag, dtype=pl.Array(pl.Float64, 6))})


def test_tracks_cov_diag_derived_only_when_it_is_the_diagonal(tmp_path):
    good = _tracks_case()
    bad = good.with_columns((pl.col("cov_diag") * 1.01).alias("cov_diag"))
    for name, frame, derived in (("a", good, True), ("b", bad, False)):
        with RunStore.create(tmp_path / name) as st:
            st.write("tracks", frame)
        with RunStore.open(tmp_path / name) as st:
            phys = st.sql(f"SELECT * FROM {LEAN_PREFIX}tracks LIMIT 0").columns
            back = st.read("tracks")
        assert (not any(c.startswith("cov_diag") for c in phys)) == derived
        assert np.allclose(back["cov_diag"].to_numpy(), frame["cov_diag"].to_numpy(), rtol=2 ** -23, atol=0)
        assert np.allclose(back["cov"].to_numpy(), frame["cov"].to_numpy(), rtol=2 ** -23, atol=0)


def test_null_covariance_rows_survive_the_split(tmp_path):
    f = _tracks_case().drop("cov_diag")
    f = f.with_columns(pl.when(pl.col("track_id") == 2).then(None).otherwise(pl.col("cov")).alias("cov"))
    with RunStore.create(tmp_path) as st:
        st.write("tracks", f)
    with RunStore.open(tmp_path) as st:
        back = st.read("tracks")
    assert back["cov"].is_null().to_list() == f["cov"].is_null().to_list()


def test_rewrite_append_and_plain_duckdb_reader(tmp_path):
    f = _tracks_case()
    with RunStore.create(tmp_path) as st:
        st.write("tracks", f)
        st.append("tracks", f)
        assert st.read("tracks").height == 2 * f.height
        st.write("tracks", pl.DataFrame({"a": [1]}))          # a plain table replaces the lean view
        assert st.read("tracks").to_dict(as_series=False) == {"a": [1]}
        st.write("tracks", f)                                 # and back
    con = duckdb.connect(str(tmp_path / "results.duckdb"), read_only=True)
    try:
        assert con.sql("SELECT count(*) FROM tracks").fetchall() == [(f.height,)]
        assert {r[0] for r in con.sql("SHOW TABLES").fetchall()} >= {"tracks", LEAN_PREFIX + "tracks"}
    finally:
        con.close()


def test_lean_false_stores_tables_as_given(tmp_path):
    with RunStore.create(tmp_path, lean=False) as st:
        st.write("tracks", _tracks_case())
    with RunStore.open(tmp_path) as st:
        kinds = dict(st.sql("SELECT table_name, table_type FROM information_schema.tables").iter_rows())
    assert kinds == {"tracks": "BASE TABLE"}


def _dump(path: Path) -> dict[str, pl.DataFrame]:
    with RunStore.open(path) as st:
        return {t: st.sql(f'SELECT * FROM "{t}"') for t in st.sql(
            "SELECT table_name FROM information_schema.tables ORDER BY 1")["table_name"]}


@pytest.mark.parametrize("case", ["fused", "tracks", "aligned"])
def test_write_parts_equals_write_of_the_whole(tmp_path, case):
    """A streamed table written window by window (the database built part by part)
    is the table written whole: same physical tables, same rows in the same order, same view."""
    if case == "fused":
        whole = _fused_case().sort("epoch", maintain_order=True)     # windows are time slices:
        parts = whole.partition_by("epoch", maintain_order=True)   # a (run, epoch, target) never straddles
    elif case == "tracks":
        whole = _tracks_case(9)
        parts = [whole[:2], whole[2:2].clear(), whole[2:7], whole[7:]]
    else:
        reports, whole = _aligned_case()
        parts = [whole[:1], whole[1:]]
    for name, by_parts in (("whole", False), ("parts", True)):
        with RunStore.create(tmp_path / name) as st:
            if case == "aligned":
                st.write("reports", reports)
            if by_parts:
                st.write_parts(case, lambda: iter(parts))
            else:
                st.write(case, whole)
    a, b = _dump(tmp_path / "whole"), _dump(tmp_path / "parts")
    assert set(a) == set(b) and LEAN_PREFIX + case in a
    for t in a:
        assert a[t].equals(b[t], null_equal=True), t


def test_write_parts_falls_back_when_a_part_breaks_a_layout_rule(tmp_path):
    """A later part whose covariance diagonal is not ``cov_diag``: the whole table keeps
    ``cov_diag`` stored, so the parts are written whole (same table as ``write``)."""
    good = _tracks_case(6)
    bad = good.with_columns(pl.when(pl.col("track_id") == 4).then(pl.col("cov_diag") * 1.01)
                            .otherwise(pl.col("cov_diag")).alias("cov_diag"))
    with RunStore.create(tmp_path / "whole") as st:
        st.write("tracks", bad)
    with RunStore.create(tmp_path / "parts") as st:
        st.write_parts("tracks", lambda: iter([bad[:3], bad[3:]]))
    a, b = _dump(tmp_path / "whole"), _dump(tmp_path / "parts")
    assert any(c.startswith("cov_diag") for c in b[LEAN_PREFIX + "tracks"].columns)
    for t in a:
        assert a[t].equals(b[t], null_equal=True), t
