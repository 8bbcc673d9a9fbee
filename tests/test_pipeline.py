"""End to end: dataset → aligned → associations → fused → clusters → metrics → results.duckdb."""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pytest

from tertiary import pipeline
from tertiary.pipeline import scoring
from tertiary import contract as schema
from tertiary.stages.clustering import ClusteringConfig
from tertiary.stages.fusion import METHODS
from tertiary.store.run_store import RunStore


@pytest.fixture(scope="module")
def results(small_terminal):
    # a wide grouping (15 km, 200 m/s): 30 aircraft over 10 minutes rarely come within the
    # default 5 km, and the reference's clutter-only targets are tentative (never clustered)
    cfg = pipeline.PipelineConfig(clustering=ClusteringConfig(always=True, eps_m=15_000.0, dv_mps=200.0))
    return pipeline.process(small_terminal, cfg)


def test_row_accounting(small_terminal, results):
    aligned_ids = set(results.aligned["report_id"].unique().to_list())
    rejected = results.rejects.filter(pl.col("input_table") == "reports")["report_id"].to_list()
    assert aligned_ids.isdisjoint(rejected)
    assert len(aligned_ids) + len(rejected) == small_terminal.reports.height
    assert set(aligned_ids) | set(rejected) == set(small_terminal.reports["report_id"].to_list())


def test_tables_follow_the_contract(results):
    for name in ("aligned", "associations", "fused", "clusters", "tracks", "conflicts", "metrics"):
        schema.validate(getattr(results, name), name, strict=True)


def test_trackers_run_on_every_fusion_picture(results):
    methods = set(results.tracks["method"].unique().to_list())
    assert methods == set(METHODS)                          # not on the centralised reference
    assert set(results.tracks["filter"].unique().to_list()) == {"singer", "imm_sym"}
    m = results.metrics.filter((pl.col("stage") == "tracker") & (pl.col("segment") == "all"))
    names = set(m["method"].unique().to_list())
    assert {f"{meth}+{f}" for meth in METHODS for f in ("singer", "imm_sym")} == names
    comp = m.filter(pl.col("metric") == "completeness")["value"]
    assert comp.min() > 0.9


def test_safety_runs_on_the_confirmed_tracks_of_every_picture(results):
    """Conflict prediction runs on the tracker's pictures (method+filter), every alert names its
    picture, and every picture is scored against the same losses of separation in truth."""
    assert results.conflicts.height > 0 and results.conflicts["alert"].any()
    pictures = {f"{meth}+{f}" for meth in METHODS for f in ("singer", "imm_sym")}
    assert set(results.conflicts["method"].unique().to_list()) <= pictures
    m = results.metrics.filter(pl.col("stage") == "safety")
    from safety.alerts import ALERT_METRICS
    los = set()
    for pic in pictures:
        got = dict(zip(*m.filter(pl.col("method") == pic).select("metric", "value").to_dict().values()))
        assert set(ALERT_METRICS) <= set(got), pic
        los.add(got["los_episodes"])
    assert len(los) == 1 and los.pop() > 0          # one truth: the same losses for every picture
    alerts = results.alerts.filter(pl.col("method") != "truth")
    assert alerts.height > 0 and set(alerts["method"].unique().to_list()) <= pictures
    assert set(alerts["classification"].unique().to_list()) <= {"genuine", "nuisance", "undetermined", "false"}
    genuine = alerts.filter(pl.col("classification") == "genuine")
    assert genuine.height > 0 and genuine["los_start"].null_count() == 0
    schema.validate(alerts, "alerts", strict=True)


def test_every_alert_is_attributed_to_the_picture_or_the_predictor(results):
    """The truth picture is predicted like the others; every system picture's alert episode is
    picture- or predictor-induced, and the counts split the picture's own."""
    alerts = results.alerts
    truth = alerts.filter(pl.col("method") == "truth")
    system = alerts.filter(pl.col("method") != "truth")
    assert truth.height > 0 and truth["induced"].null_count() == truth.height
    assert system.height > 0 and set(system["induced"].unique().to_list()) <= {"picture", "predictor"}
    assert truth["classification"].eq("genuine").any()          # the perfect picture alerts a real loss
    m = results.metrics.filter(pl.col("stage") == "safety")
    for pic in system["method"].unique().to_list():
        got = dict(m.filter(pl.col("method") == pic).select("metric", "value").iter_rows())
        assert got["alerts_picture_induced"] + got["alerts_predictor_induced"] == got["alert_episodes"], pic
        assert (got["false_alerts_picture_induced"] + got["false_alerts_predictor_induced"]
                == got["false_alerts"]), pic
        assert (got["undetermined_alerts_picture_induced"] + got["undetermined_alerts_predictor_induced"]
                == got["undetermined_alerts"]), pic
        assert (got["genuine_alerts"] + got["nuisance_alerts"] + got["false_alerts"] + got["undetermined_alerts"]
                == got["alert_episodes"]), pic
        assert (got["missed_los_picture_induced"] + got["missed_los_predictor_induced"] + got["missed_los_under_way"]
                <= got["missed_los"]), pic
        unresolved = got["nuisance_alerts"] + got["false_alerts"] + got["undetermined_alerts"]
        assert 0 <= got["valid_alerts"] <= unresolved, pic


def test_every_method_and_the_centralised_reference_are_fused(results):
    methods = set(results.fused["method"].unique().to_list())
    assert methods == set(METHODS) | {"centralized"}
    per = results.fused.filter(pl.col("method") != "centralized")
    sums = per["weights"].list.sum().to_numpy()
    np.testing.assert_allclose(sums, 1.0, atol=1e-9)
    assert (per["n_sources"] == per["radar_ids"].list.len()).all()


def test_association_quality(results):
    m = results.metrics.filter(pl.col("stage") == "association")
    value = dict(zip(m["metric"], m["value"]))
    assert value["assoc_correct_frac"] >= 0.99


def test_accuracy_metrics_long_form(results):
    m = results.metrics.filter(pl.col("stage") == "fusion")
    assert m.columns == ["stage", "method", "metric", "segment", "value", "n_runs"]
    assert {"rmse_pos_m", "rmse_range_m", "rmse_vel_mps"} <= set(m["metric"].to_list())
    assert set(m["segment"].unique().to_list()) <= {"all", "straight", "turn"}
    pos = m.filter((pl.col("metric") == "rmse_pos_m") & (pl.col("segment") == "all"))
    by = dict(zip(pos["method"], pos["value"]))
    assert set(by) == set(METHODS) | {"centralized"}
    # the information filter is near the centralised reference, the plain mean is not better than it
    assert by["information"] <= by["arithmetic"]


def _all(m: pl.DataFrame, stage: str, metric: str) -> dict[str, float]:
    rows = m.filter((pl.col("stage") == stage) & (pl.col("metric") == metric) & (pl.col("segment") == "all"))
    return dict(zip(rows["method"], rows["value"]))


def test_every_picture_has_its_bound_and_a_signed_gap(results):
    """Every fused and tracker picture gets pcrb_pos_m (stage bound) and gap = RMSE − PCRB.
    The bound is that of the motion the truth flies (docs/metrics.md): no picture is below
    it, and none is an order of magnitude above it (a unit, frame or timing error in the
    bound moves it by far more)."""
    m = results.metrics
    rmse = {**_all(m, "fusion", "rmse_pos_m"), **_all(m, "tracker", "rmse_pos_m")}
    pcrb, gap = _all(m, "bound", "pcrb_pos_m"), _all(m, "bound", "gap_pos_m")
    assert set(pcrb) == set(rmse) == set(gap)
    for pic, b in pcrb.items():
        assert gap[pic] == pytest.approx(rmse[pic] - b)
        assert b <= rmse[pic] <= 10 * b, (pic, rmse[pic], b)


def test_consistency_rows_for_every_picture(results):
    m = results.metrics
    pictures = set(_all(m, "fusion", "rmse_pos_m")) | set(_all(m, "tracker", "rmse_pos_m"))
    nees = {**_all(m, "fusion", "nees_mean"), **_all(m, "tracker", "nees_mean")}
    frac = {**_all(m, "fusion", "nees_in_band_frac"), **_all(m, "tracker", "nees_in_band_frac")}
    assert set(nees) == set(frac) == pictures
    assert all(0.0 <= f <= 1.0 for f in frac.values())
    nis = _all(m, "tracker", "nis_in_band_frac")
    assert set(nis) == {p for p in pictures if "+" in p}


def test_one_aircraft_one_run_has_accuracy_for_every_picture(small_terminal):
    """One aircraft in one run: N_k = 1 at every epoch, so (2.15) pools the epochs; every
    fused and tracker picture still has rmse_pos_m, rmse_horizontal_m and rmse_height_m."""
    ds = small_terminal
    one = int(ds.reports.filter(pl.col("truth_id").is_not_null()).group_by("truth_id").len()
              .sort("len", descending=True)["truth_id"][0])
    rep = ds.reports.filter(pl.col("truth_id") == one)
    ds1 = dataclasses.replace(ds, reports=rep, truth=ds.truth.filter(pl.col("truth_id") == one))
    res = pipeline.process(ds1, pipeline.PipelineConfig(filters=("singer",), safety=False))
    m = res.metrics
    pictures = set(METHODS) | {"centralized"} | {f"{meth}+singer" for meth in METHODS}
    for metric in ("rmse_pos_m", "rmse_horizontal_m", "rmse_height_m"):
        got = {**_all(m, "fusion", metric), **_all(m, "tracker", metric)}
        assert set(got) == pictures, metric
        assert all(np.isfinite(v) and v > 0 for v in got.values())
    assert set(_all(m, "bound", "pcrb_pos_m")) == pictures


def test_clusters_reference_fused_targets(results):
    c = results.clusters
    assert c.height > 0 and set(c["method"]) - {"centralized"}
    fused_ids = results.fused.select("run", "epoch", "method", "target_id")
    members = c.explode("members").select("run", "epoch", "method", pl.col("members").alias("target_id"))
    assert members.join(fused_ids, on=["run", "epoch", "method", "target_id"], how="anti").height == 0
    assert (c["count"] == c["members"].list.len()).all()


def test_run_database(small_terminal, tmp_path):
    cfg = pipeline.PipelineConfig(methods=("arithmetic", "aposteriori"), centralized=False)
    db = pipeline.run(small_terminal, tmp_path, cfg)
    with RunStore.open(tmp_path) as store:
        tables = set(store.tables())
        assert {"aligned", "associations", "fused", "clusters", "rejects", "metrics", "run", "reports",
                "radars", "truth", "accuracy_by_epoch"} <= tables
        methods = store.sql("SELECT DISTINCT method FROM fused ORDER BY method")["method"].to_list()
        assert methods == ["aposteriori", "arithmetic"]
    assert db.name == "results.duckdb"


def test_unknown_method_is_a_clear_error(small_terminal):
    with pytest.raises(ValueError, match="unknown fusion method"):
        pipeline.process(small_terminal, pipeline.PipelineConfig(methods=("median",)))


def test_plot_only_input_runs_end_to_end(small_terminal):
    """ASTERIX-CAT048-like plots without the radars' track estimates still run every method."""
    plots = small_terminal.reports.select("report_id", "run", "radar_id", "time", "local_track_id", "range_m",
                                          "azimuth_deg", "elevation_deg", "altitude_m", "mode_s", "truth_id")
    ds = dataclasses.replace(small_terminal, reports=plots)
    res = pipeline.process(ds, pipeline.PipelineConfig(centralized=False))
    assert set(res.fused["method"].unique().to_list()) == set(METHODS)


def test_tracks_carry_the_identity_of_their_targets():
    """tracks.mode_s: the address of the fused target each track was last updated with, carried
    while it coasts; scored as identity correctness by the evaluation stage."""
    import dataclasses
    from tertiary.simulate import load_scenario, simulate
    cfg = load_scenario("terminal-area")
    ds = simulate(dataclasses.replace(cfg, duration_s=300.0, traffic=dataclasses.replace(cfg.traffic, aircraft=16)))
    res = pipeline.process(ds, pipeline.PipelineConfig(methods=("information",), filters=("singer",),
                                                       centralized=False, safety=False))
    assert "mode_s" in res.tracks.columns and res.tracks["mode_s"].null_count() < 0.2 * res.tracks.height
    frac = res.metrics.filter((pl.col("stage") == "evaluation") & (pl.col("metric") == "mode_s_correct_frac")
                              & (pl.col("segment") == "all"))
    # every picture is scored: the fused picture and the tracker picture built on it
    assert sorted(frac["method"]) == ["information", "information+singer"] and (frac["value"] > 0.95).all()


@pytest.mark.parametrize("offset", [0, 10**12])
def test_observed_aircraft_joined_in_blocks_equal_the_whole_join(monkeypatch, offset):
    """An on-disk run finds which aircraft had a report aligned at each epoch a block of aligned
    rows at a time (memory), through a table indexed by report id (speed)
    or, with ids too sparse for it (``offset``), a join. With blocks of 3 rows over aligned rows
    that repeat a report (one per radar), cross block edges and include a report without an
    aircraft, one of another run, one whose report is unknown and one of an unknown run, the set
    equals the whole join's. Fails if a block's rows are dropped, an (aircraft, epoch) seen in
    two blocks counts twice, or a report is looked up in another run's or another report's row."""
    monkeypatch.setattr(scoring, "OBSERVED_BLOCK_ROWS", 3)
    from datetime import datetime, timedelta, timezone
    t0 = datetime(2021, 1, 1, tzinfo=timezone.utc)
    aligned = pl.DataFrame({"run": [0, 0, 0, 0, 0, 0, 1, 0, 0, 3],
                            "report_id": [offset + i for i in (1, 2, 3, 3, 4, 5, 5, 6, 99, 2)],
                            "epoch": [t0 + timedelta(seconds=s) for s in (0, 0, 4, 4, 4, 8, 8, 12, 12, 12)]},
                           schema={"run": pl.UInt32, "report_id": pl.UInt64, "epoch": schema.TIME})
    reports = pl.DataFrame({"run": [0] * 6 + [1], "report_id": [offset + i for i in (1, 2, 3, 4, 5, 6, 5)],
                            "truth_id": [10, 11, 10, 11, None, 12, 10]},
                           schema={"run": pl.UInt32, "report_id": pl.UInt64, "truth_id": pl.Int64})
    assert (scoring.report_truth(reports) is None) == (offset > 0)
    want = (aligned.join(reports, on=["run", "report_id"], how="left").select("run", "epoch", "truth_id")
            .drop_nulls().unique())
    got = scoring.observed_aircraft(aligned, reports)
    key = ["run", "epoch", "truth_id"]
    assert got.height == want.height == 6
    assert got.sort(key).equals(want.sort(key))
    assert scoring.observed_aircraft(aligned.clear(), reports).columns == key


def test_a_recording_without_truth_runs_and_stores(small_terminal, tmp_path):
    """A recording with no truth (a radar capture without CAT021: no truth table, no truth_id
    column) runs every stage to the run database; only what needs a reference is left out."""
    ds = dataclasses.replace(small_terminal, reports=small_terminal.reports.drop("truth_id"),
                             truth=small_terminal.truth.clear())
    pipeline.run(ds, tmp_path, pipeline.PipelineConfig(methods=("information",), filters=("singer",),
                                                       centralized=False))
    with RunStore.open(tmp_path) as store:
        assert store.sql("SELECT count(*) FROM tracks").item() > 0
        assert store.sql("SELECT count(*) FROM metrics WHERE stage = 'evaluation'").item() == 0
