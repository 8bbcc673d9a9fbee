"""Runs side by side (tertiary.report.compare, `tertiary compare`): deltas against the first run
with better / worse by the quantity's direction, changes of verdict, what differs said before
the comparison, the same table for scripts, and a missing or incomplete run refused in one line."""

from __future__ import annotations

import io
import json
from pathlib import Path

import polars as pl
import pytest
from test_episodes_view import small_run
from typer.testing import CliRunner

from tertiary.cli.commands import app
from tertiary.core.errors import DataError, OptionError
from tertiary.report import compare as cmp

runner = CliRunner()


def _facts(label: str, rows: list[tuple], record: dict | None = None, best: str | None = "p1") -> cmp.RunFacts:
    figures = pl.DataFrame(rows, schema=dict(cmp._LONG), orient="row")
    return cmp.RunFacts(label, Path(label), record or {}, figures, best)


A = _facts("A", [("accuracy", "p1", "horizontal RMSE (m)", 50.0, None),
                 ("safety", "p1", "losses missed", 2.0, None),
                 ("safety", "p1", "losses of separation", 10.0, None),
                 ("requirements", "p1", "H-RMS: rmse_horizontal_m <= 60", 50.0, "pass"),
                 ("requirements", "p1", "V-RMS: rmse_height_m <= 30", 20.0, "pass")],
           {"fingerprints": json.dumps({"reports": "aaa", "truth": "ttt"}),
            "config": json.dumps({"methods": ["information"], "conflicts": {"t_man_s": 60.0}})})
B = _facts("B", [("accuracy", "p1", "horizontal RMSE (m)", 65.0, None),
                 ("safety", "p1", "losses missed", 1.0, None),
                 ("safety", "p1", "losses of separation", 12.0, None),
                 ("requirements", "p1", "H-RMS: rmse_horizontal_m <= 60", 65.0, "fail"),
                 ("requirements", "p1", "V-RMS: rmse_height_m <= 30", 20.0, "pass")],
           {"fingerprints": json.dumps({"reports": "bbb", "truth": "ttt"}),
            "config": json.dumps({"methods": ["information"], "conflicts": {"t_man_s": 90.0}})})


def test_deltas_are_against_the_first_run_and_verdict_changes_are_found():
    table = cmp.compare_table([A, B])
    row = table.filter(pl.col("quantity") == "horizontal RMSE (m)").row(0, named=True)
    assert (row["A"], row["B"], row["Δ B"]) == (50.0, 65.0, 15.0)
    assert row["changed"]
    flips = cmp.verdict_changes(table, ["A", "B"])
    assert flips["quantity"].to_list() == ["H-RMS: rmse_horizontal_m <= 60"]
    same = table.filter(pl.col("quantity").str.starts_with("V-RMS")).row(0, named=True)
    assert not same["changed"] and same["Δ B"] == 0.0


def test_better_and_worse_follow_the_quantitys_direction():
    html = cmp.table_html(cmp.compare_table([A, B]), ["A", "B"])
    cells = {q: html.split(f">{q}<", 1)[1].split("</tr>", 1)[0] for q in
             ("horizontal RMSE (m)", "losses missed", "losses of separation")}
    assert 'class="num worse">15' in cells["horizontal RMSE (m)"]           # higher RMSE is worse
    assert 'class="num better">-1' in cells["losses missed"]                # fewer missed is better
    assert 'class="num changed">2' in cells["losses of separation"]         # no direction: only changed
    assert "verdict-fail verdict-change" in html


def test_what_differs_names_dataset_and_configuration_items():
    diff = cmp.differences([A, B])
    items = dict(zip(diff["item"], diff["what"]))
    assert items == {"reports": "dataset", "conflicts.t_man_s": "configuration"}
    lines = cmp.summary_lines(diff)
    assert lines[0] == "dataset differs: reports" and lines[-1] == "configuration differs: conflicts.t_man_s"
    assert cmp.summary_lines(cmp.differences([A, A])) == ["the runs share their dataset, scenario and configuration"]


def test_headline_reads_each_runs_best_picture():
    head = cmp.headline([A, B])
    assert head["horizontal RMSE (m)"].to_list() == [50.0, 65.0]
    assert head["losses missed"].to_list() == [2.0, 1.0]
    assert (head["requirements pass"].to_list(), head["fail"].to_list()) == ([2, 1], [0, 1])


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> tuple[Path, Path]:
    return small_run(tmp_path_factory, "base"), small_run(tmp_path_factory, "fewer")


def test_cli_compare_says_what_differs_first_then_writes_the_page(runs, tmp_path):
    out = tmp_path / "compare.html"
    res = runner.invoke(app, ["compare", str(runs[0]), str(runs[1]), "--out", str(out)])
    assert res.exit_code == 0, res.output
    lines = res.output.strip().splitlines()
    assert lines[0] == "note: configuration differs: methods" and lines[-1].startswith(f"wrote {out}")
    page = out.read_text()
    assert 'data-figures="1"' in page and page.count("<script>") >= 3        # plotly.js inline, offline
    assert page.index("What differs") < page.index("Headline") < page.index("Figures side by side")


def test_cli_compare_table_for_scripts(runs, tmp_path):
    res = runner.invoke(app, ["compare", str(runs[0]), str(runs[1]), "--format", "csv"])
    assert res.exit_code == 0, res.output
    assert "note: configuration differs: methods" in res.stderr     # CSV on stdout stays CSV
    table = pl.read_csv(io.StringIO(res.stdout))
    a, b = cmp._labels(list(runs))
    assert table.columns[:6] == ["section", "picture", "quantity", a, b, f"Δ {b}"]
    arith = table.filter(pl.col("picture") == "arithmetic+imm_sym")
    assert arith.height and arith[b].is_null().all() and arith["changed"].all()    # a picture one run lacks
    same = table.filter((pl.col("picture") == "information+imm_sym") & (pl.col("section") == "accuracy"))
    assert same.height == 3 and (same[f"Δ {b}"].abs() < 1e-9).all()                 # same dataset, same picture
    out = tmp_path / "t.parquet"
    res = runner.invoke(app, ["compare", str(runs[0]), str(runs[1]), "--out", str(out), "--changed"])
    assert res.exit_code == 0, res.output
    assert pl.read_parquet(out)["changed"].all()


def test_cli_compare_refuses_a_missing_or_incomplete_run(runs, tmp_path):
    res = runner.invoke(app, ["compare", str(runs[0])])
    assert res.exit_code == 2 and "at least two" in res.output
    res = runner.invoke(app, ["compare", str(runs[0]), str(tmp_path / "nowhere")])
    assert res.exit_code == 3 and "nowhere" in res.output and len(res.output.strip().splitlines()) == 1
    half = tmp_path / "half"
    half.mkdir()
    (half / "manifest.json").write_text('{"status": "running", "windows_done": 1, "window_s": 300, "dataset": "ta"}')
    res = runner.invoke(app, ["compare", str(runs[0]), str(half)])
    assert res.exit_code == 3 and f"--resume {half}" in res.output and len(res.output.strip().splitlines()) == 1
    with pytest.raises(DataError):
        cmp.load_runs([runs[0], half])
    with pytest.raises(OptionError):
        cmp.load_runs([runs[0]])
    res = runner.invoke(app, ["compare", str(runs[0]), str(runs[1]), "--out", str(tmp_path / "x.txt")])
    assert res.exit_code == 2 and "--out" in res.output


def test_requirements_are_told_apart_by_rule_and_breakdown():
    req = pl.DataFrame({"requirement": ["H-RMS", "H-RMS"], "metric": ["rmse_horizontal_m"] * 2, "op": ["<="] * 2,
                        "threshold": [150.0, 150.0], "breakdown": ["all", "range:0-50km"]})
    names = req.select(cmp._requirement(req.columns).alias("q"))["q"].to_list()
    assert names == ["H-RMS: rmse_horizontal_m <= 150.0", "H-RMS: rmse_horizontal_m <= 150.0 (range:0-50km)"]
