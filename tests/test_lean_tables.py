"""Lean run tables: ``--tables database`` (the default) stores of the per-epoch tables only the
columns the HTML report and the named SQL read (``LEAN_COLUMNS``), ``--tables full`` every column;
both in the lean layout, whose narrowed columns keep what their readers resolve: absolute positions
within 0.1 mm at any range (float32 plus its remainder), velocities and the detail columns to
float32 round-off, and a reader that casts to FLOAT (the report's figures) the float32 of the value."""

from __future__ import annotations

import dataclasses
import importlib.util
import re
import sys
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

from tertiary.core.errors import OptionError
from tertiary.io.dataset import write_dataset
from tertiary.pipeline.tables import LEAN_COLUMNS, TABLE_MODES, check_tables, lean_columns
from tertiary.simulate import load_scenario, simulate
from tertiary.store import sql_reports
from tertiary.store.layout import RESIDUAL_SUFFIX
from tertiary.store.run_store import LEAN_PREFIX, RunStore

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_store.py"
sys.path.insert(0, str(_PATH.parent))
_spec = importlib.util.spec_from_file_location("bench_store", _PATH)
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)

F32 = 2.0 ** -24          # float32's relative round-off (round to nearest)


# ----------------------------------------------------------------------------- precision of each narrowed column


def _states(n: int = 20_000, seed: int = 3) -> pl.DataFrame:
    """Track states out to 2 000 km (a national system's range and beyond), with the detail columns."""
    rng = np.random.default_rng(seed)
    r, az = rng.uniform(0.0, 2.0e6, n), rng.uniform(0.0, 2 * np.pi, n)
    t0 = pl.datetime(2024, 1, 1, time_zone="UTC")
    return pl.DataFrame({
        "run": pl.Series([0] * n, dtype=pl.UInt32), "track_id": pl.Series(np.arange(n), dtype=pl.UInt64),
        "method": ["information"] * n, "filter": ["imm_sym"] * n,
        "x_m": r * np.sin(az), "y_m": r * np.cos(az),
        # ENU height falls below the tangent plane with range (-78 km at 1 000 km)
        "z_m": rng.uniform(-3.2e5, 1.5e4, n), "alt_m": rng.uniform(0.0, 15_000.0, n),
        "vx_mps": rng.uniform(-320.0, 320.0, n), "vy_mps": rng.uniform(-320.0, 320.0, n),
        "vz_mps": rng.normal(0.0, 10.0, n), "alt_rate_mps": rng.normal(0.0, 10.0, n),
        "nis": rng.chisquare(3, n),
        "innovation": pl.Series(rng.normal(0.0, 80.0, (n, 3)), dtype=pl.Array(pl.Float64, 3)),
        "model_probs": pl.Series(rng.dirichlet([1.0, 1.0], n), dtype=pl.Array(pl.Float64, 2)),
    }).with_columns((t0 + pl.duration(seconds=pl.col("track_id"))).alias("epoch"))


@pytest.fixture(scope="module")
def states(tmp_path_factory):
    given = _states()
    root = tmp_path_factory.mktemp("states")
    with RunStore.create(root) as st:
        st.write("tracks", given)
    with RunStore.open(root) as st:
        back = st.read("tracks")
        phys = dict(st.sql(f"DESCRIBE {LEAN_PREFIX}tracks").select("column_name", "column_type").iter_rows())
        f32 = st.sql("SELECT x_m::FLOAT AS x, y_m::FLOAT AS y, z_m::FLOAT AS z, alt_m::FLOAT AS h, "
                     "vx_mps::FLOAT AS vx FROM tracks")
    return given, back, phys, f32


def test_positions_within_a_tenth_of_a_millimetre_at_2000_km(states):
    """float32 alone keeps 62 mm at 2 000 km; stored with its remainder a position is within 0.1 mm."""
    given, back, phys, _ = states
    for c in ("x_m", "y_m", "z_m", "alt_m"):
        assert phys[c] == "FLOAT" and phys[c + RESIDUAL_SUFFIX] == "BIGINT", c
        err = np.abs(back[c].to_numpy() - given[c].to_numpy())
        assert err.max() <= 1.0e-4 + 1e-9, (c, err.max())
        # never further from the value than its float32
        f32_err = np.abs(given[c].cast(pl.Float32).cast(pl.Float64).to_numpy() - given[c].to_numpy())
        assert np.all(err <= f32_err + 1e-12), c
    # the claim is not vacuous: float32 alone misses a centimetre out there
    x = given["x_m"].to_numpy()
    assert np.abs(x.astype(np.float32).astype(np.float64) - x).max() > 0.01


def test_a_reader_casting_to_float32_gets_the_float32_of_the_value(states):
    """The report's episode figures read the states as FLOAT: they get exactly what they would
    from the table stored as given."""
    given, _, _, f32 = states
    for c, g in (("x", "x_m"), ("y", "y_m"), ("z", "z_m"), ("h", "alt_m"), ("vx", "vx_mps")):
        assert f32[c].equals(given[g].cast(pl.Float32)), c


def test_float32_columns_to_float32_round_off(states):
    """Velocities (2e-5 m/s at 320 m/s), NIS, innovations and model probabilities: float32
    round-off, far below what any reader resolves (the figures draw float32, no named SQL reads them)."""
    given, back, phys, _ = states
    assert phys["vx_mps"] == "FLOAT" and phys["nis"] == "FLOAT"
    for c in ("vx_mps", "vy_mps", "vz_mps", "alt_rate_mps", "nis"):
        g, b = given[c].to_numpy(), back[c].to_numpy()
        assert np.all(np.abs(b - g) <= F32 * np.abs(g)), c
    assert np.abs(back["vx_mps"].to_numpy() - given["vx_mps"].to_numpy()).max() <= 2.0e-5
    for c in ("innovation", "model_probs"):
        g, b = (np.stack(f[c].to_numpy()) for f in (given, back))
        assert np.all(np.abs(b - g) <= F32 * np.abs(g)), c


def test_a_position_that_is_not_finite_or_null_comes_back_as_it_was(tmp_path):
    f = _states(6).with_columns(pl.Series("x_m", [np.nan, np.inf, -np.inf, None, 1.0e40, 123456.789]))
    with RunStore.create(tmp_path) as st:
        st.write("tracks", f)
    with RunStore.open(tmp_path) as st:
        x = st.read("tracks")["x_m"].to_list()
    assert np.isnan(x[0]) and x[1] == np.inf and x[2] == -np.inf and x[3] is None
    assert x[4] == np.inf and abs(x[5] - 123456.789) <= 1e-4      # beyond float32's range: its float32


# ----------------------------------------------------------------------------- a small run stored lean and full


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """One small job (two fusion methods + centralised, one tracker, conflicts, truth), its tables
    stored as given (every column, no lean layout), ``--tables full`` and ``--tables database``."""
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=240.0, traffic=dataclasses.replace(cfg.traffic, aircraft=20,
                                                                                 conflict_pairs=3))
    root = tmp_path_factory.mktemp("lean_tables")
    write_dataset(simulate(cfg), root / "ds")
    from tertiary.pipeline import PipelineConfig
    tables, info = bench.process(root / "ds", PipelineConfig(methods=("arithmetic", "information"),
                                                             filters=("imm_sym",)))
    dbs = {"given": bench.store(tables, info, root / "given", lean=False, mode="full"),
           "full": bench.store(tables, info, root / "full", lean=True, mode="full"),
           "database": bench.store(tables, info, root / "database", lean=True, mode="database")}
    return dbs, dict(tables)


def test_named_sql_same_on_lean_and_full(runs):
    """Every named SQL report gives the same answer (to 1e-9) on the default store as on the
    tables stored as given and on ``--tables full``."""
    dbs, _ = runs
    for ref in ("given", "full"):
        diffs = bench.compare_sql(dbs[ref], dbs["database"])
        assert not diffs, (ref, diffs)
    with RunStore.open(dbs["database"]) as st:      # not vacuous: the reports over the slimmed tables answer
        for name in ("radar_accuracy_over_time", "radar_residuals", "radar_kinematics", "reports_by_radar",
                     "conflicts", "conflict_timeline", "row_accounting", "association_quality"):
            assert sql_reports.run_report(st, name).height > 0, name


def test_default_store_keeps_the_read_columns_and_every_row(runs):
    dbs, tables = runs
    with RunStore.open(dbs["database"]) as lean, RunStore.open(dbs["full"]) as full:
        assert lean.tables() == full.tables()
        for name in lean.tables():
            n = f'SELECT count(*) FROM "{name}"'
            assert lean.sql(n).item() == full.sql(n).item(), name
            cols, given = lean.sql(f'SELECT * FROM "{name}" LIMIT 0').columns, tables.get(name)
            if name in LEAN_COLUMNS:
                assert cols == [c for c in given.columns if c in LEAN_COLUMNS[name]], name
                assert len(cols) < len(given.columns), name
            elif given is not None:
                assert cols == given.columns, name
    # a small run: most of each file is DuckDB's 256 kB blocks holding little
    assert dbs["database"].stat().st_size < 0.75 * dbs["full"].stat().st_size


def test_the_report_reads_the_same_states_from_the_default_store(runs):
    """What the report's alert episodes read of tracks, fused and truth (the only readers of their
    states) is the same on the default store as on the tables stored as given."""
    from tertiary.report import episodes
    dbs, _ = runs
    got = {}
    for k in ("given", "database"):
        with RunStore.open(dbs[k]) as st:
            pictures = episodes._pictures(st)
            assert len(pictures) > 2
            got[k] = []
            for picture in pictures:
                for row in episodes.list_episodes(st, picture).head(2).iter_rows(named=True):
                    d = episodes._episode_data(st, episodes._alert_episode(row, picture))
                    got[k].append((d.tracks, d.truth))
    assert len(got["given"]) == len(got["database"]) > 4
    for (t1, r1), (t2, r2) in zip(got["given"], got["database"]):
        assert t1.height > 0 and t1.equals(t2) and r1.equals(r2)


def test_tables_modes():
    assert TABLE_MODES == ("database", "full", "parquet")
    assert lean_columns("database") is LEAN_COLUMNS and lean_columns("parquet") is LEAN_COLUMNS
    assert lean_columns("full") == {}
    check_tables("full", Path.cwd())
    with pytest.raises(OptionError, match=re.escape("full")):
        check_tables("lean", Path.cwd())


def test_parquet_tables_filter_nan_residuals_as_the_database_does(tmp_path):
    """``--tables parquet`` registers copies of the read columns: a named SQL that leaves NaN
    residuals out (``NOT isnan(res_range_m)``) counts the same rows as on the database copy (a
    Parquet file with float min/max statistics makes DuckDB keep the NaN rows)."""
    from tertiary.pipeline.tables import StreamedTable, store_sink
    n = 1000
    res = np.where(np.arange(n) % 7 == 0, np.nan, np.linspace(-50.0, 50.0, n))
    reports = pl.DataFrame({"run": pl.Series([0] * n, dtype=pl.UInt32),
                            "report_id": pl.Series(np.arange(n), dtype=pl.UInt64),
                            "radar_id": pl.Series([1] * n, dtype=pl.UInt32), "res_range_m": res,
                            "azimuth_deg": np.linspace(0.0, 359.0, n)})
    part = tmp_path / "w=000000.parquet"
    reports.write_parquet(part, compression="lz4")              # a window's part, with statistics
    counts = {}
    for mode in ("database", "parquet"):
        with RunStore.create(tmp_path / mode) as st:
            store_sink(st, [], mode)("reports", StreamedTable(lambda: iter([reports]), parts_files=(part,)))
        with RunStore.open(tmp_path / mode) as st:
            counts[mode] = st.sql("SELECT count(*) FROM reports WHERE NOT isnan(res_range_m)").item()
            assert st.sql("SELECT * FROM reports LIMIT 0").columns == ["run", "report_id", "radar_id", "res_range_m"]
    assert counts == {"database": n - (n + 6) // 7, "parquet": n - (n + 6) // 7}


# ----------------------------------------------------------------------------- the windows' parts


@pytest.fixture(scope="module")
def windowed(tmp_path_factory):
    """One small windowed job run with ``--tables database`` and ``--tables full``; each run's
    window parts' columns, read before the completed run removes them."""
    from tertiary.pipeline import PipelineConfig, run
    from tertiary.runtime import windows
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=240.0, traffic=dataclasses.replace(cfg.traffic, aircraft=20,
                                                                                 conflict_pairs=3))
    root = tmp_path_factory.mktemp("lean_parts")
    ds = simulate(cfg)
    seen: dict[str, dict[str, set[str]]] = {}
    finish = windows.PartStore.finish

    def keep_schemas(self, status, **info):
        if status == "complete":
            seen[self.dir.name] = {d.name: set().union(*(pl.read_parquet_schema(f) for f in d.glob("w=*.parquet")))
                                   for d in (self.dir / windows.PARTS).iterdir() if not d.name.startswith("_")}
        return finish(self, status, **info)
    windows.PartStore.finish = keep_schemas
    try:
        pcfg = PipelineConfig(methods=("information",), filters=("imm_sym",))
        dbs = {mode: run(ds, root / mode, pcfg, window_s=60.0, tables=mode) for mode in ("database", "full")}
    finally:
        windows.PartStore.finish = finish
    return dbs, seen


def test_a_lean_run_writes_only_what_is_read_back_to_its_parts(windowed):
    """A run that stores lean tables writes lean window parts: no covariance of a report or an
    aligned plot, none of the fusion's inputs or the tracker's diagnostics (a day's parts would
    otherwise be several times its input); ``--tables full`` writes every column."""
    from tertiary.pipeline.tables import ALIGNED_COLUMNS, NOT_SCORED, REPORT_COLUMNS
    _, seen = windowed
    lean, full = seen["database"], seen["full"]
    assert lean["aligned"] <= {*LEAN_COLUMNS["aligned"], *ALIGNED_COLUMNS}
    assert lean["reports"] <= {*LEAN_COLUMNS["reports"], *REPORT_COLUMNS}
    assert {"cov", "nominal_var"} <= full["aligned"] and "est_cov" in full["reports"]
    for name in ("fused", "tracks"):
        gone = full[name] & set(NOT_SCORED) - set(LEAN_COLUMNS[name])
        assert gone and not lean[name] & gone, name
        assert "cov" in lean[name], name          # the evaluation's consistency reads it


def test_lean_parts_give_the_tables_and_metrics_of_whole_parts(windowed):
    """Every stored table and metric of the lean-parts run equals the whole-parts run's (its
    stored columns), to 1e-9: nothing a whole-run stage reads was trimmed."""
    dbs, _ = windowed
    with RunStore.open(dbs["database"]) as lean, RunStore.open(dbs["full"]) as full:
        assert lean.tables() == full.tables()
        for name in lean.tables():
            if name == "run":
                continue
            a = lean.sql(f'SELECT * FROM "{name}"')
            b = full.sql(f'SELECT {", ".join(chr(34) + c + chr(34) for c in a.columns)} FROM "{name}"')
            assert a.height == b.height > 0 or name in ("clusters", "rejects", "alerts", "losses"), name
            key = [c for c in a.columns if a.schema[c] not in (pl.Float32, pl.Float64) and not
                   isinstance(a.schema[c], (pl.List, pl.Array, pl.Struct))]
            assert_frame_equal(a.sort(key, nulls_last=True), b.sort(key, nulls_last=True),
                                          check_exact=False, rel_tol=1e-9, abs_tol=1e-9)


def test_a_run_resumes_only_with_the_parts_it_wrote(windowed, tmp_path):
    """``--resume`` with another ``--tables`` mode would mix lean and whole parts: refused."""
    from tertiary.runtime.windows import PartStore
    header = {"dataset": "d", "window_s": 60.0, "config_hash": "h", "parts": "lean"}
    store = PartStore.start(tmp_path, header)
    store.manifest["windows_done"] = 0
    store._commit()
    with pytest.raises(OptionError, match="--tables"):
        PartStore.resume(tmp_path, {**header, "parts": "full"})
    PartStore.resume(tmp_path, header)
