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
from tertiary.cli.commands import app
from tertiary.report.common import CENTRALIZED, Best, breakable as _breakable, fmt_cell as _fmt_cell, thin as _thin
from tertiary.report.html import (MAX_POINTS, MIN_SAMPLE_FRAC, REPORT_FILENAME, build_report, build_sections, figure_count)
from tertiary.io.dataset import write_dataset
from tertiary.simulate import load_scenario, simulate
from tertiary.store.run_store import RunStore

runner = CliRunner()

#: figures of a complete run: map, range, range rate, acceleration, residuals, RMSE over time,
#: a-posteriori vs a-priori, accuracy bars, conflict timeline, P_pob, capacity
N_FIGURES = 13


def n_figures(page: str) -> int:
    """The figures a complete run's report holds: the fixed ones and one per alert episode drawn."""
    return N_FIGURES + len(re.findall(r'id="fig-episodes-\d+"', page))
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


def test_a_narrow_batch_log_never_breaks_the_report_path(run_dir):
    """In a batch log narrower than the line, the path of the written report stays whole (a
    path broken across lines cannot be copied): fails when the line is wrapped at COLUMNS."""
    res = runner.invoke(app, ["report", str(run_dir)], env={"COLUMNS": "40"})
    assert res.exit_code == 0, res.output
    assert str(run_dir / REPORT_FILENAME) in res.output.splitlines()[-1]


@pytest.fixture(scope="module")
def page(run_dir) -> str:
    return (run_dir / REPORT_FILENAME).read_text(encoding="utf-8")


def test_one_self_contained_file(run_dir, page):
    # no temp files; the manifest marks the run complete (tertiary.runtime.windows)
    assert sorted(p.name for p in run_dir.iterdir()) == ["manifest.json", REPORT_FILENAME, "results.duckdb"]
    assert page.startswith("<!DOCTYPE html>") and page.rstrip().endswith("</html>")
    # plotly.js inline exactly once, nothing loaded from a CDN or any other URL
    assert len(re.findall(r"plotly\.js v\d+\.\d+\.\d+", page)) == 1
    assert not re.search(r"<script[^>]*\bsrc=", page)
    assert not re.search(r"<link[^>]*\bhref=\"?https?:", page)


def test_every_figure_is_embedded(page):
    n = n_figures(page)
    assert n > N_FIGURES                                             # alert episodes are drawn
    assert figure_count(page) == n
    assert page.count('class="plotly-graph-div"') == n
    assert page.count("window.__reportDone(") == n                  # each marks itself rendered
    assert page.count("Plotly.newPlot(") == n
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
    assert size <= 6e6           # plotly.js (≈ 4.8 MB) plus about a megabyte of thinned data


def test_thin():
    frame = pl.DataFrame({"i": range(10_001)})
    thin = _thin(frame)
    assert thin.height <= MAX_POINTS + 1
    assert thin["i"][0] == 0 and thin["i"][-1] == 10_000
    assert _thin(frame.head(5)).height == 5


@pytest.fixture(scope="module")
def built(run_dir):
    return build_sections(run_dir)


def _figures(built, key: str) -> list:
    sec = next(s for s in built.sections if s.key == key)
    assert sec.figures, (key, sec.note)
    return [fig for fig, _caption in sec.figures]


def _captions(built, key: str) -> str:
    return " ".join(c for s in built.sections if s.key == key for _f, c in s.figures)


def _shown(fig) -> set[str]:
    """Legend groups (or names) of the traces drawn by default."""
    return {t.legendgroup or t.name for t in fig.data if t.visible in (None, True)}


def _section(page: str, key: str) -> str:
    start = page.index(f'<section id="{key}"')
    return page[start:page.index("</section>", start)].replace("<wbr>", "")


def test_verdict_opens_the_report(page, run_dir):
    first = re.search(r'<section id="([^"]+)"', page)
    assert first and first.group(1) == "verdict"
    verdict = _section(page, "verdict")
    assert page.index('<section id="verdict"') < page.index("<nav>")         # before the table of contents
    # three lines: the best picture against the best radar and the reference, the bound, the alerts
    with RunStore.open(run_dir) as store:
        m = store.read("metrics")
    fus = m.filter((pl.col("stage") == "fusion") & (pl.col("segment") == "all")
                   & (pl.col("metric") == "rmse_horizontal_m") & (pl.col("method") != CENTRALIZED)).sort("value", "method")
    best = fus["method"][0]
    assert f"<b>Best picture {best}</b>: horizontal RMSE <b>{fus['value'][0]:,.1f} m</b>" in verdict
    assert "the best radar alone" in verdict and "centralised reference" in verdict
    assert "the posterior Cramér–Rao bound" in verdict and "no picture is below the bound" in verdict
    assert "losses of separation alerted</b>" in verdict and "picture-induced" in verdict
    # the predictor's share is what the truth picture also raises, of every class
    pred = re.search(r"([\d,]+) predictor-induced", verdict)
    assert pred and float(pred.group(1).replace(",", "")) in set(
        m.filter(pl.col("metric") == "alerts_predictor_induced")["value"].to_list())
    # the pipeline judges its pictures against the shipped example requirements: the matrix
    assert 'id="verdict-matrix"' in verdict and ("Failing: " in verdict or "No requirement fails" in verdict)
    # the long tables are below the table of contents: in detail and in the appendix
    detail = _section(page, "verdict-detail")
    assert "Best radar alone" in detail and "horizontal RMSE (m)" in detail and "vertical RMSE (m)" in detail
    assert "Safety performance" in detail and "false alerts" in detail and "losses alerted" in detail
    appendix = _section(page, "requirements")
    assert page.index("<nav>") < page.index('<section id="verdict-detail"') < page.index('<section id="requirements"')
    assert re.search(r"\d+ pass, \d+ fail, \d+ insufficient samples", appendix)


def test_verdict_matrix_has_one_cell_per_requirement_and_picture(page, run_dir):
    """Rows are the requirements, columns the pictures (most accurate first), each cell coloured
    by its verdict with the value on hover, and the failing cells are named above the matrix."""
    with RunStore.open(run_dir) as store:
        req = store.read("requirements")
    verdict = _section(page, "verdict")
    matrix = verdict[verdict.index('id="verdict-matrix"'):]
    pictures = re.findall(r'<th class="vm-pic"><span>([^<]+)</span></th>', matrix)
    assert sorted(pictures) == sorted(req["method"].unique()) and pictures[-1] == CENTRALIZED
    rows = re.findall(r'<th class="vm-req"[^>]*>([^<]+)</th>', matrix)
    assert rows == req["requirement"].unique(maintain_order=True).to_list()
    cells = re.findall(r'<td class="vm verdict-(\w+)" title="([^"]+)">', matrix)
    assert len(cells) == req.height
    for r in req.iter_rows(named=True):
        cell = [c for c in cells if c[1].startswith(f"{r['requirement']} on {r['method']}:")]
        assert len(cell) == 1 and cell[0][0] == r["verdict"]
        value = "n/a" if r["value"] is None else f"{r['value']:,.4g}"
        assert cell[0][1].endswith(f": {r['verdict']}") and f"= {value}," in cell[0][1]
    sentence = verdict[verdict.index('<p class="vm-sentence">'):verdict.index('id="verdict-matrix"')]
    for name in req.filter(pl.col("verdict") == "fail")["requirement"].unique():
        assert f"<b>{name}</b> on " in sentence
    for name in set(req["requirement"]) - set(req.filter(pl.col("verdict") == "fail")["requirement"]):
        assert f"<b>{name}</b>" not in sentence


def test_failing_pictures_are_named_by_family():
    from tertiary.report.verdict import _name_pictures

    pics = ["information+imm_sym", "apriori+imm_sym", "information", "apriori", "information+singer",
            "apriori+singer", CENTRALIZED]
    assert _name_pictures(["apriori+imm_sym", "information+singer", "apriori+singer", CENTRALIZED], pics) == (
        "apriori+imm_sym, every +singer picture and centralized")
    assert _name_pictures(["information", "apriori"], pics) == "every fused picture"
    assert _name_pictures(pics, pics) == "every picture"


def _metric(m: pl.DataFrame, stage: str, method: str, metric: str) -> float:
    return m.filter((pl.col("stage") == stage) & (pl.col("method") == method) & (pl.col("metric") == metric)
                    & (pl.col("segment") == "all"))["value"].item()


def test_verdict_ranks_against_truth_and_bound_and_gives_the_reference_its_own_row(page, run_dir):
    """The verdict ranks the pictures by their error against the truth, each with its gap to the
    PCRB, and never measures them against the centralised reference; the reference's own
    figures (RMSE, gap, false and duplicate tracks per hour) are a row of their own, unranked."""
    verdict = _section(page, "verdict-detail")
    assert "the reference's" not in verdict and "against the centralised reference" not in verdict
    with RunStore.open(run_dir) as store:
        m = store.read("metrics")
    best = re.search(r"Best picture: ([^<]+)</b>", verdict).group(1)
    gap, pcrb = _metric(m, "bound", best, "gap_horizontal_m"), _metric(m, "bound", best, "pcrb_horizontal_m")
    side = "above" if gap >= 0 else "below"
    assert (f"{abs(gap):,.1f} m {side} the posterior Cramér–Rao bound (PCRB {pcrb:,.1f} m on the same samples)"
            in verdict)
    accuracy = verdict[:verdict.index("<h3>Safety")]
    rows = [c for c in (re.findall(r"<td[^>]*>([^<]*)</td>", r) for r in re.findall(r"<tr>(.*?)</tr>", accuracy)) if c]
    ref = [r for r in rows if r[1] == CENTRALIZED]
    assert len(ref) == 1 and ref[0][0] == "" and ref[0][2] == "centralised reference (not ranked)"
    for stage, metric in (("fusion", "rmse_horizontal_m"), ("bound", "gap_horizontal_m"),
                          ("evaluation", "false_tracks_per_hour"), ("evaluation", "duplicate_tracks_per_hour")):
        assert _fmt_cell(_metric(m, stage, CENTRALIZED, metric)) in ref[0], metric
    ranks = [r[0] for r in rows if r[0]]
    assert ranks == [str(k) for k in range(1, len(ranks) + 1)] and rows[0][:3] == ["1", best, "best picture"]


def test_verdict_of_an_evaluation_never_ranks_the_reference_first(run_dir, tmp_path):
    """Even when the centralised reference has the smallest error, the most accurate picture
    named is a picture; the reference is named as itself, with its false and duplicate tracks
    per hour."""
    shutil.copy(run_dir / "results.duckdb", tmp_path / "results.duckdb")
    with RunStore.update(tmp_path) as store:
        store.con.execute("UPDATE metrics SET value = 0.5 WHERE method = 'centralized' AND stage = 'evaluation' "
                          "AND metric = 'rmse_horizontal_m'")
        store.con.execute("DELETE FROM run WHERE key = 'kind'")
        store.con.execute("INSERT INTO run VALUES ('kind', 'evaluation')")
    page = build_report(tmp_path, tmp_path / "r.html").read_text()
    verdict, detail = _section(page, "verdict"), _section(page, "verdict-detail")
    assert "<b>Most accurate picture " in verdict and f"Most accurate picture {CENTRALIZED}" not in verdict
    assert "Most accurate picture: " in detail and f"Most accurate picture: {CENTRALIZED}" not in detail
    assert f"Centralised reference ({CENTRALIZED}, not ranked): horizontal RMS 0.5 m" in detail
    assert re.search(r"[\d.,na/]+ false and [\d.,na/]+ duplicate tracks per hour", detail)


def test_verdict_renders_requirements_and_losses_when_present(run_dir, tmp_path):
    shutil.copy(run_dir / "results.duckdb", tmp_path / "results.duckdb")
    req = pl.DataFrame({"requirement": ["horizontal RMS terminal", "probability of update"],
                        "metric": ["rmse_horizontal_m", "prob_update"], "breakdown": ["all", "all"],
                        "threshold": [150.0, 0.97], "value": [48.0, 0.9], "n_samples": [1000, 12],
                        "verdict": ["pass", "insufficient"], "method": "information"})
    los = pl.DataFrame({"stage": "safety", "method": "information",
                        "metric": ["los_episodes", "alerted_los", "missed_los", "genuine_alerts", "nuisance_alerts",
                                   "alerts_per_hour", "warning_median_s", "warning_p05_s"],
                        "segment": "all", "value": [4.0, 3.0, 1.0, 3.0, 2.0, 6.5, 41.0, 12.0],
                        "n_runs": 1}).with_columns(pl.col("n_runs").cast(pl.UInt32))
    with RunStore.update(tmp_path) as store:
        store.write("requirements", req)
        store.con.execute("DELETE FROM metrics WHERE stage = 'safety' AND metric IN (SELECT metric FROM los)")
        store.con.execute("INSERT INTO metrics SELECT * FROM los")
    page = build_report(tmp_path, tmp_path / "r.html").read_text()
    verdict, detail, appendix = (_section(page, k) for k in ("verdict", "verdict-detail", "requirements"))
    assert "1 pass, 0 fail, 1 insufficient samples</b> (of 2 requirement × picture cells" in appendix
    assert 'class="verdict-pass"' in appendix and 'class="verdict-insufficient"' in appendix
    assert "No requirement fails on any picture. 1 cell(s) have too few samples" in verdict
    assert 'class="vm verdict-pass"' in verdict and 'class="vm verdict-insufficient"' in verdict
    assert "<b>3 of 4 losses of separation alerted</b>, median warning 41 s" in verdict
    assert "5th-percentile warning (s)" in detail and "median warning (s)" in detail
    assert "4 losses of separation in truth, <b>3 alerted</b>, <b>1 missed</b>" in detail
    assert "(6.5 alerts per hour); median warning 41 s, 5th percentile 12 s" in detail


def test_verdict_without_loss_of_separation_scores_says_so(run_dir, tmp_path):
    shutil.copy(run_dir / "results.duckdb", tmp_path / "results.duckdb")
    with RunStore.update(tmp_path) as store:
        store.con.execute("DELETE FROM metrics WHERE metric IN ('los_episodes', 'alerted_los', 'missed_los')")
    page = build_report(tmp_path, tmp_path / "r.html").read_text()
    verdict, detail = _section(page, "verdict"), _section(page, "verdict-detail")
    assert "<b>Alerts</b>" not in verdict and "No losses of separation were scored" in detail


def test_default_visible_traces_are_best_picture_reference_and_best_radar(built, run_dir):
    with RunStore.open(run_dir) as store:
        m = store.read("metrics")
    horiz = m.filter((pl.col("stage") == "fusion") & (pl.col("segment") == "all")
                     & (pl.col("metric") == "rmse_horizontal_m") & (pl.col("method") != CENTRALIZED)).sort("value", "method")
    best = horiz["method"][0]
    fig = _figures(built, "rmse_time")[0]
    radar_groups = {t.legendgroup for t in fig.data if t.legendgroup.startswith("radar ")}
    assert len(radar_groups) >= 2
    shown = _shown(fig)
    best_radar = [g for g in shown if g.startswith("radar ")]
    assert len(best_radar) == 1
    assert shown == {best, CENTRALIZED, best_radar[0]}
    assert len(fig.data) > 2 * len(shown)            # every other trace is there, legend-only
    assert {t.visible for t in fig.data} == {True, "legendonly"}
    # the best radar is the one with the lowest pooled horizontal RMSE (its own tracks)
    best_name = best_radar[0].removeprefix("radar ")
    with RunStore.open(run_dir) as store:
        from tertiary.store.sql_reports import run_report
        ra = run_report(store, "radar_accuracy_over_time", {})
    pooled = ra.group_by("name").agg((pl.col("rmse_horizontal_m") ** 2).mean().sqrt().alias("h")).sort("h", "name")
    assert pooled["name"][0] == best_name
    # conflicts (predicted on the tracker's pictures): the best picture overall by default
    anyp = m.filter(pl.col("stage").is_in(["fusion", "tracker"]) & (pl.col("segment") == "all")
                    & (pl.col("metric") == "rmse_horizontal_m") & (pl.col("method") != CENTRALIZED)).sort("value", "method")
    conf = _figures(built, "conflicts")[0]
    pictures = {t.legendgroup for t in conf.data}
    expected = next(p for p in anyp["method"].to_list() if p in pictures)
    assert _shown(conf) - {CENTRALIZED} == {expected}


def test_pictures_with_equal_accuracy_are_ranked_by_name():
    """Trackers that coincide (a short run) tie: the figure shows the same picture every run,
    whatever order the store returns them in."""
    rows = pl.DataFrame({"picture": ["information+singer", "covariance_intersection+singer", "bar_shalom_campo+singer",
                                     "arithmetic+singer"],
                         "stage": ["tracker"] * 4, "horizontal_m": [61.2, 61.2, 61.2, 70.4],
                         "height_m": [4.0] * 4, "pos_m": [106.0] * 4})
    for order in (rows, rows.reverse(), rows[[1, 0, 2, 3]]):
        best = Best(order, pl.DataFrame())
        assert best.best_of(order["picture"].to_list()) == "bar_shalom_campo+singer"


def test_horizontal_and_vertical_panels(built):
    fig = _figures(built, "rmse_time")[0]
    assert fig.layout.yaxis.title.text == "horizontal RMSE (m)"
    assert fig.layout.yaxis2.title.text == "vertical RMSE (m)"
    ys = {t.yaxis for t in fig.data}
    assert ys == {"y", "y2"}
    # the same trace set in each panel, toggled together by one legend entry
    by_panel = {y: sorted(t.legendgroup for t in fig.data if t.yaxis == y) for y in ys}
    assert by_panel["y"] == by_panel["y2"]
    bars = _figures(built, "accuracy")[0]
    assert bars.layout.yaxis.title.text == "horizontal RMSE (m)"
    assert bars.layout.yaxis2.title.text == "vertical RMSE (m)"
    assert {t.yaxis for t in bars.data} == {"y", "y2"}


def test_kinematics_are_small_multiples(built, run_dir):
    with RunStore.open(run_dir) as store:
        n_radars = store.read("radars").height
    figs = _figures(built, "kinematics")
    assert len(figs) == 3
    for fig in figs:
        assert len(fig.layout.annotations) == n_radars                     # one titled panel per radar
        assert len({t.xaxis for t in fig.data}) == n_radars
        # each panel holds only the few aircraft, not every radar × aircraft
        for ax in {t.xaxis for t in fig.data}:
            assert len({t.name for t in fig.data if t.xaxis == ax}) <= 3
        assert sum(bool(t.showlegend) for t in fig.data) <= 3              # one legend entry per aircraft


UNIT = re.compile(r"\((m|km|s|m/s|m/s²|%|1/min|1/h|pairs|aircraft|dimensionless)\)|\(ft[;)]")


def test_every_axis_has_its_unit(built):
    n_axes = 0
    for sec in built.sections:
        for fig, _c in sec.figures:
            layout = fig.to_plotly_json()["layout"]
            axes = {k: v for k, v in layout.items() if re.fullmatch(r"[xy]axis\d*", k)}
            titled = {k: v["title"]["text"] for k, v in axes.items() if v.get("title", {}).get("text")}
            for k, text in titled.items():
                assert UNIT.search(text), (sec.key, k, text)
            # every figure names its units on both axes (a categorical x axis of pictures excepted)
            assert any(k.startswith("y") for k in titled), (sec.key, titled)
            assert any(k.startswith("x") for k in titled) or sec.key in ("accuracy", "evaluation"), (sec.key, titled)
            n_axes += len(titled)
    assert n_axes >= 20
    conf = next(s for s in built.sections if s.key == "conflicts").figures[0][0]
    assert conf.layout.yaxis2.title.text == "new alerts per minute (1/min)"


def test_edge_rule_is_applied_and_stated(built, run_dir):
    caption = _captions(built, "rmse_time")
    assert f"at least {MIN_SAMPLE_FRAC:.0%} of the median N_k" in caption and "left out" in caption
    assert "Edge-of-coverage rule" in _captions(built, "post_prior")
    # the drawn epochs are exactly those passing the rule, computed here in polars
    with RunStore.open(run_dir) as store:
        by = store.read("accuracy_by_epoch").filter(pl.col("metric") == "rmse_horizontal_m")
    keep = by.filter(pl.col("n") >= MIN_SAMPLE_FRAC * pl.col("n").median().over("method"))
    fig = _figures(built, "rmse_time")[0]
    drawn = sum(len(t.x) for t in fig.data if t.yaxis == "y" and not t.legendgroup.startswith("radar "))
    assert drawn == keep.height < by.height or drawn == keep.height == by.height


def test_tables_wrap_and_print(page):
    css = page[page.index("<style>"):page.index("</style>")]
    assert "max-height" not in css.split("@media print")[0].split(".tablewrap")[1].split("}")[0]
    assert "overflow-wrap: break-word" in css and "white-space: normal" in css
    assert "@media print" in css and "table-header-group" in css and "break-inside: avoid" in css
    assert _breakable("covariance_intersection+imm_sym") == "covariance_<wbr>intersection_<wbr>imm_<wbr>sym".replace(
        "intersection_<wbr>", "intersection+<wbr>")
    assert "<wbr>" in _breakable("a" * 40) and _breakable("<b>&") == "&lt;b&gt;&amp;"


def test_report_survives_missing_tables(run_dir, tmp_path):
    shutil.copy(run_dir / "results.duckdb", tmp_path / "results.duckdb")
    with RunStore.update(tmp_path) as store:
        for table in ("conflicts", "accuracy_by_epoch", "truth"):
            store.con.execute(f"DROP TABLE {table}")
    out = build_report(tmp_path, tmp_path / "r.html")
    page = out.read_text()
    assert "Not available for this run" in page
    assert 0 < figure_count(page) < n_figures(page)
    assert page.count('class="plotly-graph-div"') == figure_count(page)


def test_report_command_errors(tmp_path):
    res = runner.invoke(app, ["report", str(tmp_path)])
    # a missing run database is a data error (tertiary.core.errors.DataError, exit 3) with a one-line message
    assert res.exit_code == 3 and "no run database" in res.output


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
    assert "results.duckdb" in flat and REPORT_FILENAME in flat          # where the results and report are
    assert figure_count(html_path.read_text()) == n_figures(html_path.read_text())


def test_stca_curves_section_draws_both_threshold_families(built):
    sec = next(s for s in built.sections if s.key == "stca")
    assert not sec.note, sec.note
    names = {t.name for t in sec.figures[0][0].data}
    assert any(n.endswith("— covariance") for n in names) and any(n.endswith("— fixed") for n in names)
    table = sec.tables[0][1]
    assert table.height == len({n.split(" — ")[0] for n in names})          # one row per picture
    # the covariance family's own point at confidence 0.95 is always on its curve
    assert table[:, 1].is_not_null().all() and table[:, 2].is_not_null().all()


def test_named_reports_have_no_empty_column_on_the_main_job(run_dir):
    """Every named SQL report on a main-job run fills each column it prints (a column no stage
    fills is a dead column). The one data-dependent gap: no manoeuvre epoch, no manoeuvre gain."""
    from tertiary.store import sql_reports

    with sql_reports.open_read_only(run_dir) as store:
        for rep in sql_reports.list_reports():
            frame = sql_reports.run_report(store, rep.name, {})
            if rep.name == "cluster_statistics":       # clustering is not a stage of the main job
                assert frame.height == 0
                continue
            assert frame.height > 0, rep.name
            empty = {c for c in frame.columns if frame[c].null_count() == frame.height}
            if rep.name == "aposteriori_gain" and (frame["manoeuvre_epochs"] == 0).all():
                empty.discard("max_gain_manoeuvre")
            assert not empty, f"{rep.name}: columns without a value: {sorted(empty)}"


def test_step_curves_keep_only_their_changes_and_draw_the_same_line():
    """A step curve (shape "hv") thinned to its changes holds, at every original x, the value of
    the last kept point at or before it: the line drawn is the same."""
    import numpy as np

    from tertiary.report.common import step_changes

    rng = np.random.default_rng(3)
    y = np.repeat(rng.integers(0, 4, 60), rng.integers(1, 30, 60))
    frame = pl.DataFrame({"t_s": np.arange(len(y), dtype=float), "alerts": y})
    kept = step_changes(frame, "alerts")
    assert kept.height < frame.height / 4 and kept["t_s"][-1] == frame["t_s"][-1]
    idx = np.searchsorted(kept["t_s"].to_numpy(), frame["t_s"].to_numpy(), side="right") - 1
    assert (kept["alerts"].to_numpy()[idx] == y).all()
