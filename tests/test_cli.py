"""The command line: help for every command, the error boundary, simulate → validate → run with the
same rejects, runs that never overwrite, and the end-of-run summary."""

from __future__ import annotations

import re
from pathlib import Path

import duckdb
import polars as pl
import pytest
from typer.testing import CliRunner

from tertiary.cli.commands import app
from tertiary.cli.common import cell
from tertiary.pipeline.workflows import choose_run_dir

runner = CliRunner()


def _commands() -> list[list[str]]:
    import typer.main
    group = typer.main.get_command(app)
    return [[]] + [[name] for name in group.commands]


@pytest.mark.parametrize("cmd", _commands(), ids=lambda c: " ".join(c) or "tertiary")
def test_help_works_and_shows_every_option_with_its_default(cmd):
    res = runner.invoke(app, [*cmd, "--help"])
    assert res.exit_code == 0, res.output
    assert "Traceback" not in res.output and "Usage:" in res.output
    assert "…" not in res.output          # nothing cut off
    import typer.main
    command = typer.main.get_command(app)
    if cmd:
        command = command.commands[cmd[0]]
    flat = " ".join(res.output.split())
    for param in command.params:
        for opt in param.opts:
            if opt.startswith("-"):
                assert opt in res.output, f"{opt} missing from `{' '.join(cmd)} --help`"
        if param.param_type_name == "option" and param.help is not None:
            assert param.help.split()[0] in flat, f"no help text for {param.opts}"


def test_run_help_shows_full_defaults():
    flat = "".join(runner.invoke(app, ["run", "--help"]).output.split())
    assert "arithmetic,apriori,aposteriori_seed,aposteriori,information,covariance_intersection" in flat
    assert "[default:singer,imm_sym]" in flat


def test_validate_help_is_not_markup():
    # the help text that once crashed (`[/truth]` read as rich markup)
    res = runner.invoke(app, ["validate", "--help"])
    assert res.exit_code == 0 and "truth.parquet" in res.output


def test_readme_options_exist_where_it_says():
    """Every `tertiary ...` line of the README's and docs/cli.md's command blocks parses (options exist)."""
    from pathlib import Path
    root = Path(__file__).resolve().parents[1]
    blocks = [b for f in (root / "README.md", root / "docs" / "cli.md")
              for b in f.read_text().split("```bash")[1:]]
    lines = [ln.split("#")[0].strip() for b in blocks for ln in b.split("```", 1)[0].splitlines()
             if ln.strip().startswith("tertiary ")]
    assert len(lines) >= 8
    import typer.main
    group = typer.main.get_command(app)
    for line in lines:
        words = line.split()[1:]
        if words[0] == "--debug":
            words = words[1:]
        command = group.commands[words[0]]
        known = {o for p in command.params for o in (*p.opts, *p.secondary_opts)}
        for w in words[1:]:
            if w.startswith("--"):
                assert w.split("=")[0] in known, f"README: {line!r}: {w} is not an option of {words[0]}"


def test_bad_option_is_one_line_exit_2(tmp_path):
    res = runner.invoke(app, ["simulate", "big-box", "--out", str(tmp_path / "x"), "--dropout", "R1:abc"])
    assert res.exit_code == 2
    assert "--dropout" in res.output and "Traceback" not in res.output
    res = runner.invoke(app, ["run", "--methods", "nope", "--out", str(tmp_path / "r")])
    assert res.exit_code == 2 and "--methods" in res.output and "nope" in res.output


def test_run_refuses_simulation_options_with_a_dataset(tmp_path):
    res = runner.invoke(app, ["run", str(tmp_path), "--noise-factor", "3"])
    assert res.exit_code == 2 and "--noise-factor" in res.output


def test_missing_dataset_is_a_data_error(tmp_path):
    res = runner.invoke(app, ["validate", str(tmp_path / "nowhere")])
    assert res.exit_code == 3, res.output
    assert "nowhere" in res.output and "Traceback" not in res.output


def test_debug_shows_the_traceback(tmp_path):
    res = runner.invoke(app, ["--debug", "validate", str(tmp_path / "nowhere")])
    assert res.exit_code != 0 and res.exception is not None and not isinstance(res.exception, SystemExit)


def test_ids_print_plain_counts_with_separators():
    assert cell(1025, "target_id") == "1025" and cell(1025, "run") == "1025"
    assert cell(123456, "n") == "123,456"


def test_choose_run_dir_never_overwrites(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    first, note = choose_run_dir(None, "terminal-area", force=False)
    assert first.as_posix() == "runs/terminal-area" and note is None
    first.mkdir(parents=True)
    (first / "results.duckdb").write_bytes(b"")
    second, note = choose_run_dir(None, "terminal-area", force=False)
    assert second.as_posix() == "runs/terminal-area-2" and "runs/terminal-area-2" in note
    from tertiary.core.errors import OptionError
    with pytest.raises(OptionError, match="--force"):
        choose_run_dir(first, "x", force=False)
    assert choose_run_dir(first, "x", force=True) == (first, None)
    with pytest.raises(OptionError, match="run directory"):
        choose_run_dir(None, "../../x", force=False)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "ds"
    res = runner.invoke(app, ["simulate", "terminal-area", "--out", str(out), "--aircraft", "12", "--radars", "3",
                              "--duration", "300", "--seed", "5"])
    assert res.exit_code == 0, res.output
    return out


def test_simulate_writes_a_dataset_and_refuses_to_overwrite_it(dataset):
    for name in ("radars.parquet", "reports.parquet", "truth.parquet", "scenario.toml"):
        assert (dataset / name).exists()
    assert pl.read_parquet(dataset / "radars.parquet").height == 3
    assert pl.read_parquet(dataset / "truth.parquet")["truth_id"].n_unique() == 12
    res = runner.invoke(app, ["simulate", "terminal-area", "--out", str(dataset), "--aircraft", "3"])
    assert res.exit_code == 2 and "--force" in res.output


def test_simulate_summary_counts_what_it_wrote(tmp_path):
    """The summary counts the radars written (an ADS-B scenario places them from the traffic) and
    says how many designed pairs a short terminal area holds."""
    truth = Path(__file__).resolve().parents[1] / "datasets" / "adsb_paris_2021-10-07.parquet"
    res = runner.invoke(app, ["simulate", "adsb", "--truth", str(truth), "--out", str(tmp_path / "adsb")],
                        terminal_width=300)
    assert res.exit_code == 0, res.output
    n = pl.read_parquet(tmp_path / "adsb" / "radars.parquet").height
    assert n > 0 and f" {n} radars" in res.output, res.output
    res = runner.invoke(app, ["simulate", "terminal-area", "--out", str(tmp_path / "ta"), "--aircraft", "30",
                              "--duration", "600"], terminal_width=300)
    assert res.exit_code == 0, res.output
    assert "designed pairs: 10 losses of separation and 2 near misses per run" in res.output
    roles = pl.read_parquet(tmp_path / "ta" / "truth.parquet").group_by("truth_id").agg(pl.col("role").first())
    assert roles.filter(pl.col("role").str.starts_with("conflict-")).height == 20


def _counts(output: str) -> dict[tuple[str, str], int]:
    """(stage, reason) → rows from validate's table (the reason column may fold over lines)."""
    out: dict[tuple[str, str], int] = {}
    for line in output.splitlines():
        m = re.match(r"│\s*(ingest|align)\s*│\s*reports\s*│(.*)│\s*([\d,]+)\s*│", line)
        if m:
            out[(m.group(1), " ".join(m.group(2).split()))] = int(m.group(3).replace(",", ""))
    return out


def test_validate_predicts_what_run_rejects(dataset, tmp_path):
    """validate and run apply the same rules: the same stages, reasons and counts."""
    bad_dir = tmp_path / "bad"
    bad_dir.mkdir()
    for f in dataset.iterdir():
        (bad_dir / f.name).write_bytes(f.read_bytes())
    rep = pl.read_parquet(dataset / "reports.parquet")
    row = pl.int_range(pl.len())
    bad = rep.with_columns(pl.when(row < 3).then(-5.0).otherwise(pl.col("range_m")).alias("range_m"))
    bad.write_parquet(bad_dir / "reports.parquet")
    res = runner.invoke(app, ["validate", str(bad_dir)], terminal_width=400)
    assert res.exit_code == 0, res.output
    assert "range_m" in res.output
    res_strict = runner.invoke(app, ["validate", str(bad_dir), "--strict"])
    assert res_strict.exit_code == 3 and "range_m" in res_strict.output

    run_dir = tmp_path / "run"
    res_run = runner.invoke(app, ["run", str(bad_dir), "--out", str(run_dir), "--no-report", "--filters", "singer",
                                  "--methods", "arithmetic"])
    assert res_run.exit_code == 0, res_run.output
    con = duckdb.connect(str(run_dir / "results.duckdb"), read_only=True)
    run_rejects = con.execute("SELECT stage, reason, count(*) FROM rejects WHERE input_table = 'reports' "
                              "GROUP BY ALL").fetchall()
    n_aligned = con.execute("SELECT count(DISTINCT report_id) FROM aligned").fetchone()[0]
    con.close()
    assert n_aligned + sum(n for _, _, n in run_rejects) == rep.height     # row accounting
    predicted = _counts(res.output)
    assert predicted == {(s, " ".join(r.split())): n for s, r, n in run_rejects}
    assert any(stage == "ingest" for stage, _ in predicted) and sum(predicted.values()) >= 3


def test_run_twice_never_overwrites_and_prints_a_summary(dataset, tmp_path):
    run_dir = tmp_path / "r"
    args = ["run", str(dataset), "--out", str(run_dir), "--no-report", "--filters", "singer", "--methods",
            "arithmetic,information"]
    first = runner.invoke(app, args)
    assert first.exit_code == 0, first.output
    # a batch log: plain lines, no spinner glyphs, and a result at the end
    assert not re.search("[⠋⠙⠹⠸⠼⠴⠦⠧⠇⠏]", first.output)
    assert "reports in" in first.output and "rejected" in first.output and "wall time" in first.output
    assert "horizontal" in first.output and "vertical" in first.output and "for 12 aircraft" in first.output
    assert f"results: {run_dir}" in first.output
    stamp = (run_dir / "results.duckdb").stat().st_mtime_ns
    second = runner.invoke(app, args)
    assert second.exit_code == 2 and "--force" in second.output
    assert (run_dir / "results.duckdb").stat().st_mtime_ns == stamp
    third = runner.invoke(app, [*args, "--force"])
    assert third.exit_code == 0, third.output


def test_batch_progress_as_json_lines_or_nothing(dataset, tmp_path):
    import json
    args = ["run", str(dataset), "--no-report", "--filters", "", "--methods", "arithmetic", "--no-centralized"]
    res = runner.invoke(app, [*args, "--out", str(tmp_path / "j"), "--log-format", "json"])
    assert res.exit_code == 0, res.output
    lines = [json.loads(line) for line in res.output.splitlines() if line.startswith("{")]
    steps = [d["step"] for d in lines if d["task"] == "pipeline"]
    # a dataset with truth: validated before the first window, every picture matched in the windows
    assert steps[:4] == ["validate", "validate_truth", "align", "associate"] and "store" in steps
    assert "match_pictures" in steps
    assert all(d["peak_rss_mib"] > 0 and d["t_s"] >= 0 for d in lines)
    assert "wall time" in res.output                         # the summary is still printed
    quiet = runner.invoke(app, [*args, "--out", str(tmp_path / "q"), "--quiet"])
    assert quiet.exit_code == 0 and "pipeline:" not in quiet.output and "wall time" in quiet.output
    text = runner.invoke(app, [*args, "--out", str(tmp_path / "t")])
    assert re.search(r"\] pipeline: align \(peak [\d,]+ MiB\)", text.output)
    bad = runner.invoke(app, [*args, "--out", str(tmp_path / "b"), "--log-format", "xml"])
    assert bad.exit_code == 2 and "--log-format" in bad.output


def test_one_wall_time_everywhere(dataset, tmp_path):
    run_dir = tmp_path / "w"
    res = runner.invoke(app, ["run", str(dataset), "--out", str(run_dir), "--filters", "", "--methods", "arithmetic"])
    assert res.exit_code == 0, res.output
    shown = re.findall(r"wall time ([\d.,]+) s", res.output)
    assert len(shown) == 1 and "done in" not in res.output      # one duration, shown once
    html = (run_dir / "report.html").read_text(encoding="utf-8")
    assert re.findall(r"wall time ([\d.,]+) s", html) == shown


def test_no_safety_stores_the_picture_without_predicting_conflicts(dataset, tmp_path):
    """``--no-safety``: the fused picture and its accuracy, no conflict prediction, no alert scored."""
    import duckdb
    run_dir = tmp_path / "p"
    res = runner.invoke(app, ["run", str(dataset), "--out", str(run_dir), "--filters", "", "--methods", "arithmetic",
                              "--no-centralized", "--no-safety", "--no-report"])
    assert res.exit_code == 0, res.output
    assert "fusion   arithmetic" in res.output and "safety (alert" not in res.output
    con = duckdb.connect(str(run_dir / "results.duckdb"), read_only=True)
    stages = {s for (s,) in con.sql("SELECT DISTINCT stage FROM metrics").fetchall()}
    assert "fusion" in stages and not stages & {"safety", "alerts", "stca"}
    assert con.sql("SELECT count(*) FROM conflicts").fetchall() == [(0,)]
    assert con.sql("SELECT count(*) FROM fused").fetchall()[0][0] > 0


def test_run_simulates_scenario(tmp_path):
    res = runner.invoke(app, ["run", "--scenario", "big-box", "--runs", "2", "--duration", "120",
                              "--out", str(tmp_path / "bb"), "--no-report", "--filters", "singer"])
    assert res.exit_code == 0, res.output
    con = duckdb.connect(str(tmp_path / "bb" / "results.duckdb"), read_only=True)
    assert con.execute("SELECT count(DISTINCT run) FROM reports").fetchone()[0] == 2
    keys = {r[0] for r in con.execute("SELECT key FROM run").fetchall()}
    assert {"scenario", "versions", "fingerprints", "rows", "timings"} <= keys
    con.close()


def test_adsb_requires_truth(tmp_path):
    res = runner.invoke(app, ["simulate", "adsb", "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "--truth" in res.output


def test_unknown_scenario(tmp_path):
    res = runner.invoke(app, ["simulate", "nowhere", "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "nowhere" in res.output and "Traceback" not in res.output


def test_one_malloc_arena_is_set_on_glibc():
    """The CLI limits glibc to one malloc arena (threads would each keep one): set on glibc,
    a no-op elsewhere."""
    import platform
    from tertiary.core.memory import one_malloc_arena
    assert one_malloc_arena() is (platform.libc_ver()[0] == "glibc")


def test_freed_heap_pages_go_back_to_the_kernel_between_windows():
    """Memory freed below a block still in use stays resident until it is released: a window's
    small arrays freed while one survives it are handed back (glibc; elsewhere nothing is)."""
    import platform

    import numpy as np
    import psutil

    from tertiary.core.memory import release_freed_memory
    if platform.libc_ver()[0] != "glibc":
        assert release_freed_memory() is False
        return
    release_freed_memory()
    proc = psutil.Process()
    blocks = [np.ones(4_000) for _ in range(20_000)]   # 32 kB each: glibc's heap, not mmap; 640 MB
    keep = np.ones(4_000)                               # allocated last, above them
    rss_full = proc.memory_info().rss
    del blocks
    rss_freed = proc.memory_info().rss
    assert release_freed_memory() is True
    rss_released = proc.memory_info().rss
    assert rss_freed - rss_released > 0.8 * 20_000 * 32_000 and keep.sum() == 4_000
    assert rss_full - rss_freed < 0.2 * 20_000 * 32_000     # freeing alone returns next to nothing


def test_counted_steps_drive_the_progress_bar():
    from tertiary.cli.common import counted_step

    assert counted_step("window 3/12 done, 12:00 – 12:05: 9,000 reports so far, 4,321 reports/s") == (
        3, 12, "4,321 reports/s")
    assert counted_step("radar scans window 3/12") == (2, 12, "")          # running: two done
    assert counted_step("align") is None


def test_a_terminal_shows_a_bar_with_rate_and_eta(monkeypatch):
    """In a terminal, windows done of the total, reports/s and the remaining time; a batch log
    (not a terminal) keeps its one line per window."""
    import io

    from rich.console import Console

    from tertiary.cli import common

    out = io.StringIO()
    monkeypatch.setattr(common, "console", Console(file=out, force_terminal=True, width=150))
    common.set_log(False, "text")
    with common.Steps("pipeline") as say:
        say("pipeline: validate")
        say("window 2/8 done, 12:00 – 12:05: 2,000 reports so far, 5,000 reports/s, RSS 1 MiB")
        task = say._prog.tasks[0]
        assert (task.completed, task.total, task.fields["rate"]) == (2, 8, "5,000 reports/s")
        say._prog.refresh()
    screen = out.getvalue()
    assert "2/8" in screen and "5,000 reports/s" in screen and "ETA" in screen
    log = io.StringIO()
    monkeypatch.setattr(common, "console", Console(file=log, force_terminal=False, width=150))
    with common.Steps("pipeline") as say:
        say("window 2/8 done, 12:00 – 12:05: 2,000 reports so far, 5,000 reports/s, RSS 1 MiB")
    assert "pipeline: window 2/8 done" in log.getvalue() and "━" not in log.getvalue()
