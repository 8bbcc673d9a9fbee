"""Alert episodes you can open (tertiary.report.episodes, `tertiary episodes`): the most severe
episodes of the best picture first, each figure drawing the episode's own tracks and truths, the
closest approach its alert predicted, the minima at their size, the classification and warning
in the title; missed losses found again from the truth; the command's errors one line.

The small runs here are shared with tests/test_compare.py and tests/test_views_browser.py
(:func:`small_run`)."""

from __future__ import annotations

import dataclasses
import math
import re
import shutil
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from typer.testing import CliRunner

from tertiary import pipeline
from tertiary.cli.commands import app
from tertiary.core.errors import OptionError
from tertiary.core.units import FT
from tertiary.report import episodes as ev
from tertiary.report.common import Ctx
from tertiary.simulate import load_scenario, simulate
from tertiary.store.run_store import RunStore

runner = CliRunner()

#: run name → methods of its configuration (both on the same dataset)
RUNS = {"base": ("information", "arithmetic"), "fewer": ("information",)}
_DONE: dict[str, Path] = {}


def small_run(factory: pytest.TempPathFactory, name: str = "base") -> Path:
    """A small terminal-area run (20 aircraft, 300 s, 3 conflict pairs, one tracker filter, no
    STCA curves), built once per process and shared by the view tests."""
    if name not in _DONE:
        if "dataset" not in _DONE:
            cfg = load_scenario("terminal-area")
            cfg = dataclasses.replace(cfg, duration_s=300.0, traffic=dataclasses.replace(cfg.traffic, aircraft=20,
                                                                                          conflict_pairs=3))
            _DONE["dataset"] = simulate(cfg)          # type: ignore[assignment]
        out = factory.mktemp(f"view_run_{name}")
        # no STCA trade-off curves: half the run's time, and no view reads them
        pipeline.run(_DONE["dataset"], out, pipeline.PipelineConfig(methods=RUNS[name], filters=("imm_sym",),
                                                                    stca_lookaheads_s=()))
        _DONE[name] = out
    return _DONE[name]


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    return small_run(tmp_path_factory)


def _store(run_dir: Path) -> RunStore:
    return RunStore.open(run_dir, read_only=True)


def test_most_severe_episodes_of_the_best_picture_first(run):
    with _store(run) as store:
        best = ev.best_alert_picture(store)
        alerts = store.sql("SELECT * FROM alerts WHERE method = $p", {"p": best})
        conf = store.sql("SELECT run, id_a, id_b, epoch, severity FROM conflicts WHERE alert AND method = $p",
                         {"p": best})
        listed = ev.list_episodes(store, best)
    assert best is not None and "+" in best and alerts.height >= 3
    # peak severity of each episode, computed here from the conflicts rows inside it
    peak = (alerts.join(conf, on=["run", "id_a", "id_b"]).filter(pl.col("epoch").is_between("t_start", "t_end"))
            .group_by("run", "id_a", "id_b", "t_start").agg(pl.col("severity").max()))
    expected = peak.sort("severity", descending=True)["severity"].to_list()
    assert listed["severity"].to_list() == pytest.approx(expected)
    picture, figs, note = ev.episode_figures(run, n=2)
    assert picture == best and len(figs) == 2 and "2 of" in note
    first = figs[0][0].layout.title.text
    assert first.startswith("#1 ") and best in first
    assert re.search(r"(genuine|nuisance|false)", first)


def _trace(fig, prefix: str):
    return next(t for t in fig.data if (t.name or "").startswith(prefix))


def test_figure_draws_the_episodes_tracks_cpa_and_minima(run):
    with _store(run) as store:
        best = ev.best_alert_picture(store)
        row = ev.list_episodes(store, best).row(0, named=True)
        ep = ev._alert_episode(row, best)
        fig, caption = ev.episode_figure(store, ep, 1)
        method, _, filt = best.partition("+")
        states = store.sql("SELECT track_id, epoch, x_m, y_m, coalesce(alt_m, z_m) AS h, vx_mps, vy_mps, "
                           "coalesce(alt_rate_mps, vz_mps) AS vh FROM tracks WHERE method = $m AND filter = $f "
                           "AND epoch = $t AND track_id IN ($a, $b) ORDER BY track_id",
                           {"m": method, "f": filt, "t": row["cpa_epoch"], "a": row["id_a"], "b": row["id_b"]})
        cc = ev.conflict_config(ev.run_config(store))
    track_a = _trace(fig, f"A: track {row['id_a']}")
    assert len(track_a.x) >= 3 and f"B: track {row['id_b']}" in [t.name for t in fig.data]
    assert any((t.name or "").startswith(f"A: truth of aircraft {row['truth_a']}") for t in fig.data)
    # the predicted CPA: each track's state at the closest alert row moved on straight for T_min
    t_min = max(row["cpa_t_min_s"], 0.0) if math.isfinite(row["cpa_t_min_s"]) else 0.0
    a = states.filter(pl.col("track_id") == row["id_a"]).row(0, named=True)
    # the figure draws the float32 values of the lean store (positions to a few mm at 40 km)
    a = {k: float(np.float32(v)) if isinstance(v, float) else v for k, v in a.items()}
    pred = np.array([a["x_m"] + a["vx_mps"] * t_min, a["y_m"] + a["vy_mps"] * t_min]) / 1e3
    cpa = _trace(fig, "predicted CPA")
    assert [cpa.x[0], cpa.y[0]] == pytest.approx(pred, abs=1e-9)
    # the horizontal minimum at its size around A's predicted position (km on the plan view)
    circle = _trace(fig, "horizontal minimum")
    r = np.hypot(np.asarray(circle.x) - pred[0], np.asarray(circle.y) - pred[1])
    assert r == pytest.approx(cc.sep_h_m / 1e3, rel=1e-6)
    # the vertical minimum: a band of ± Δr_v (in ft) around A's predicted altitude
    band = next(s for s in fig.layout.shapes if s.type == "rect" and s.y0 is not None and s.y1 - s.y0 > 0)
    h = a["h"] + (a["vh"] or 0.0) * t_min
    assert [band.y0, band.y1] == pytest.approx([(h - cc.sep_v_m) / FT, (h + cc.sep_v_m) / FT], rel=1e-6)
    title = fig.layout.title.text
    assert row["classification"] in title and f"warning {row['warning_s']:.0f} s" in title
    assert f"{row['induced']}-induced" in title
    assert "altitude (ft" in fig.layout.xaxis2.title.text + fig.layout.yaxis2.title.text
    assert "east x (km)" == fig.layout.xaxis.title.text and "T_min" in caption


def _miss_one(run: Path, copy: Path, stored: bool) -> tuple[str, dict]:
    """A copy of the run where the best picture missed its first genuine loss: its alerts of that
    pair deleted and, with ``stored``, the stored loss marked missed (else the losses table dropped)."""
    copy.mkdir()
    shutil.copy(run / "results.duckdb", copy / "results.duckdb")
    with RunStore.open(copy, read_only=False) as store:
        best = ev.best_alert_picture(store)
        gone = store.sql("SELECT run, truth_a, truth_b, los_start FROM alerts WHERE method = $p AND "
                         "classification = 'genuine' ORDER BY t_start LIMIT 1", {"p": best}).row(0, named=True)
        store.sql("DELETE FROM alerts WHERE method = $p AND truth_a = $a AND truth_b = $b",
                  {"p": best, "a": gone["truth_a"], "b": gone["truth_b"]})
        store.sql("UPDATE metrics SET value = 1 WHERE stage = 'safety' AND metric = 'missed_los' AND method = $p",
                  {"p": best})
        if stored:
            store.sql("UPDATE losses SET alerted = false WHERE method = $p AND truth_a = $a AND truth_b = $b "
                      "AND t_start = $t", {"p": best, "a": gone["truth_a"], "b": gone["truth_b"],
                                           "t": gone["los_start"]})
        else:
            store.sql("DROP TABLE losses")
    return best, gone


def test_a_stored_missed_loss_is_drawn(run, tmp_path):
    """The run's scoring stores every loss per picture (table losses): its missed ones are drawn,
    exactly those, picture-induced when the truth picture alerted them."""
    best, gone = _miss_one(run, tmp_path / "run", stored=True)
    with _store(tmp_path / "run") as store:
        missed, note = ev.missed_losses(store, best)
        fig, _caption = ev.episode_figure(store, missed[0])
    assert [(m.truth_a, m.truth_b, m.t_start) for m in missed] == [(gone["truth_a"], gone["truth_b"],
                                                                     gone["los_start"])]
    assert missed[0].induced == "picture" and "table losses" in note
    assert "missed loss of separation (picture-induced)" in fig.layout.title.text


def test_a_missed_loss_is_found_again_and_drawn(run, tmp_path, monkeypatch):
    """Without a stored losses table (an older run), an alerted loss whose alerts are deleted must
    come back as a missed loss of that pair, found again from the truth."""
    best, gone = _miss_one(run, tmp_path / "run", stored=False)
    copy = tmp_path / "run"
    with _store(copy) as store:
        missed, note = ev.missed_losses(store, best)
        fig, caption = ev.episode_figure(store, missed[0])
        of_pair, _ = ev.missed_losses(store, best, (gone["truth_a"], gone["truth_b"]))   # that pair's truth only
    assert [m.t_start for m in of_pair] == [m.t_start for m in missed]
    assert [(m.truth_a, m.truth_b) for m in missed] == [(gone["truth_a"], gone["truth_b"])]
    assert abs((missed[0].t_start - gone["los_start"]).total_seconds()) < 1.0
    assert missed[0].induced == "picture"        # the truth picture alerted it
    assert "missed_los metric counts 1" in note
    title = fig.layout.title.text
    assert "missed loss of separation (picture-induced)" in title
    assert any((t.name or "").startswith("A: track ") for t in fig.data), "the picture's nearest tracks drawn"
    _p, figs, _n = ev.episode_figures(copy, n=1)
    assert "missed loss" in figs[-1][0].layout.title.text     # the section draws every missed loss
    monkeypatch.setattr(ev, "MAX_TRUTH_ROWS", 10)
    with _store(copy) as store:
        none, too_big = ev.missed_losses(store, best)
    assert none == [] and "--pair" in too_big


def test_section_fragment_counts_its_figures(run):
    html = ev.episodes_section(run, n=2)
    assert html.startswith('<div class="episodes" data-figures="2">')
    assert html.count('class="plotly-graph-div"') == 2 and "window.__reportDone" in html
    assert "<script src=" not in html and "</script><" in html        # no plotly.js, no network
    with _store(run) as store:
        sec = ev.sec_episodes(Ctx(store, lambda _m: None))               # the report's section form
    assert sec.key == "episodes" and len(sec.figures) == min(ev.DEFAULT_EPISODES, _alerts_of_best(run))


def _alerts_of_best(run: Path) -> int:
    with _store(run) as store:
        return store.sql("SELECT count(*) FROM alerts WHERE method = $p", {"p": ev.best_alert_picture(store)}).item()


def test_pair_parsing():
    assert ev.parse_pair("15, 5") == (5, 15)
    with pytest.raises(OptionError, match="--pair"):
        ev.parse_pair("5")


def test_cli_episodes_of_a_pair_on_any_picture(run, tmp_path):
    with _store(run) as store:
        pair = store.sql("SELECT truth_a, truth_b, count(*) AS n FROM alerts WHERE method = 'truth' "
                         "GROUP BY ALL ORDER BY n DESC, truth_a LIMIT 1").row(0)
    out = tmp_path / "pair.html"
    res = runner.invoke(app, ["episodes", str(run), "--picture", "truth", "--pair", f"{pair[1]},{pair[0]}",
                              "--out", str(out)])
    assert res.exit_code == 0, res.output
    page = out.read_text()
    assert f'data-figures="{pair[2]}"' in page and f"aircraft {pair[0]} &amp; {pair[1]}" in page
    assert "wrote" in res.output and str(pair[2]) in res.output


def test_cli_episodes_errors_are_one_line(run, tmp_path):
    res = runner.invoke(app, ["episodes", str(run), "--picture", "nope"])
    assert res.exit_code == 2 and "--picture" in res.output and "information+imm_sym" in res.output
    assert len(res.output.strip().splitlines()) == 1
    res = runner.invoke(app, ["episodes", str(run), "--pair", "1"])
    assert res.exit_code == 2 and "--pair" in res.output
    res = runner.invoke(app, ["episodes", str(tmp_path / "nowhere")])
    assert res.exit_code == 3 and "Traceback" not in res.output
    half = tmp_path / "half"
    half.mkdir()
    (half / "manifest.json").write_text('{"status": "running", "windows_done": 2, "window_s": 300, '
                                        '"dataset": "ta"}')
    res = runner.invoke(app, ["episodes", str(half)])
    assert res.exit_code == 3 and "--resume" in res.output and len(res.output.strip().splitlines()) == 1
