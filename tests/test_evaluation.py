"""The one evaluation stage (tertiary.evaluation.evaluate) and `tertiary evaluate` on a picture file the
pipeline did not write."""

from __future__ import annotations

import shutil
from pathlib import Path

import duckdb
import numpy as np
import polars as pl
import pytest
from typer.testing import CliRunner

from tertiary import pipeline
from tertiary.pipeline import scoring
from tertiary.cli.commands import app
from polars.testing import assert_frame_equal

from tertiary.core.errors import DataError
from tertiary.evaluation.evaluate import (EvaluationConfig, comparison, evaluate_each, evaluate_pictures, read_picture)
from tertiary.evaluation.matching import MatchConfig
from tertiary.evaluation.requirements import example_path, load_requirements
from tertiary.io.dataset import write_dataset
from tertiary.simulate import load_scenario, simulate

from apart import Apart

runner = CliRunner()


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A terminal-area dataset and the tracks of two pictures written as stand-alone files with
    no tertiary column names beyond the tracks schema (as another system would export them)."""
    root = tmp_path_factory.mktemp("eval")
    cfg = load_scenario("terminal-area")
    import dataclasses
    cfg = dataclasses.replace(cfg, duration_s=420.0, seed=11)
    ds = simulate(dataclasses.replace(cfg, traffic=dataclasses.replace(cfg.traffic, aircraft=24)))
    write_dataset(ds, root / "ds")
    res = pipeline.process(ds, pipeline.PipelineConfig(methods=("information", "arithmetic"), filters=("singer",),
                                                       centralized=False, safety=False))
    files = []
    for m in ("information", "arithmetic"):
        part = res.tracks.filter(pl.col("method") == m).drop("method", "filter")
        path = root / f"system_{m[:4]}.parquet"             # renamed: the file is "another system's"
        part.write_parquet(path)
        files.append(path)
    return root, ds, files


def test_the_stage_scores_every_picture_and_judges_requirements(small):
    root, ds, files = small
    tracks = pl.concat([read_picture(f) for f in files], how="diagonal_relaxed")
    ev = evaluate_pictures(tracks, ds.truth, radars=ds.radars, frame=ds.origin,
                           requirements=load_requirements(example_path()))
    assert sorted(ev.metrics["method"].unique()) == ["system_arit", "system_info"]
    cmp = comparison(ev.metrics)
    info = cmp.filter(pl.col("method") == "system_info").row(0, named=True)
    arit = cmp.filter(pl.col("method") == "system_arit").row(0, named=True)
    assert 5.0 < info["rmse_horizontal_m"] < arit["rmse_horizontal_m"] < 500.0   # information beats arithmetic
    assert 0.8 < info["prob_update"] <= 1.0
    segs = set(ev.metrics.filter(pl.col("metric") == "rmse_horizontal_m")["segment"])
    assert "all" in segs and any(s.startswith("range:") for s in segs) and any(s.startswith("alt:") for s in segs)
    assert set(ev.requirements["verdict"]) <= {"pass", "fail", "insufficient"} and ev.requirements.height >= 10
    # the matcher agrees with the labels the pipeline knows (its own tracks): nearly every match right
    m = ev.matched.filter(pl.col("truth_id").is_not_null())
    assert m.height > 0.8 * ev.matched.height


def test_evaluate_command_on_renamed_files_writes_a_run(small, tmp_path):
    root, _ds, files = small
    out = tmp_path / "ev"
    res = runner.invoke(app, ["evaluate", *map(str, files), "--dataset", str(root / "ds"), "--out", str(out),
                              "--requirements", str(example_path())], terminal_width=250)
    assert res.exit_code == 0, res.output
    assert "Pictures compared" in res.output and "Requirements" in res.output and "system_info" in res.output
    con = duckdb.connect(str(out / "results.duckdb"), read_only=True)
    tables = {r[0] for r in con.sql("SHOW TABLES").fetchall()}
    assert {"tracks", "truth", "metrics", "requirements", "run", "evaluation_matched"} <= tables
    verdicts = {r[0] for r in con.sql("SELECT DISTINCT verdict FROM requirements").fetchall()}
    assert verdicts <= {"pass", "fail", "insufficient"}
    page = (out / "report.html").read_text()
    assert 'id="verdict-matrix"' in page and "Pictures against the reference" in page and "Not available" not in page
    again = runner.invoke(app, ["evaluate", str(files[0]), "--dataset", str(root / "ds"), "--out", str(out)])
    assert again.exit_code == 2 and "--force" in again.output


def test_evaluate_refuses_bad_input_with_one_line(small, tmp_path):
    root, _ds, files = small
    bad = tmp_path / "bad.parquet"
    pl.DataFrame({"epoch": [1], "x_m": [0.0]}).write_parquet(bad)
    res = runner.invoke(app, ["evaluate", str(bad), "--dataset", str(root / "ds"), "--out", str(tmp_path / "o")])
    assert res.exit_code == 3 and "missing column" in res.output
    res = runner.invoke(app, ["evaluate", str(files[0]), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "--truth" in res.output
    dup = tmp_path / "copy"
    dup.mkdir()
    shutil.copy(files[0], dup / files[0].name)
    res = runner.invoke(app, ["evaluate", str(files[0]), str(dup / files[0].name), "--dataset", str(root / "ds"),
                              "--out", str(tmp_path / "o")])
    assert res.exit_code == 3 and "same picture" in res.output


def test_an_imported_cat062_picture_is_evaluated_like_our_own(tmp_path):
    """CAT062 → external picture → scored by the same stage as the pipeline's pictures."""
    def cli(*args):
        res = runner.invoke(app, [*map(str, args)], terminal_width=250)
        assert res.exit_code == 0, res.output
        return res.output
    ta, run_dir, pic = tmp_path / "ta", tmp_path / "run", tmp_path / "picture.ast"
    cli("simulate", "terminal-area", "--out", ta, "--aircraft", 12, "--duration", 240, "--runs", 1,
        "--format", "asterix")
    cli("run", ta, "--out", run_dir, "--filters", "singer", "--methods", "information", "--no-report")
    cli("export", "asterix", run_dir, "--picture", "singer/information", "--out", pic)
    cli("import", "asterix", pic, ta / "recording.ast", "--sites", ta / "sites.toml", "--date", "2021-10-07",
        "--out", tmp_path / "ds")
    out = cli("evaluate", tmp_path / "ds" / "external_tracks.parquet", "--dataset", tmp_path / "ds",
              "--out", tmp_path / "ev", "--no-report")
    con = duckdb.connect(str(tmp_path / "ev" / "results.duckdb"), read_only=True)
    got = dict(con.sql("SELECT metric, value FROM metrics WHERE stage = 'evaluation' AND segment = 'all'").fetchall())
    ours = dict(duckdb.connect(str(run_dir / "results.duckdb"), read_only=True).sql(
        "SELECT metric, value FROM metrics WHERE stage = 'evaluation' AND segment = 'all'").fetchall())
    # the picture that went through CAT062 scores as it did in the run (ASTERIX resolution aside)
    assert got["rmse_horizontal_m"] == pytest.approx(ours["rmse_horizontal_m"], rel=0.15), out
    assert got["prob_update"] == pytest.approx(ours["prob_update"], abs=0.02)


def test_reconstructed_reference_is_scored_against_truth_and_radars_are_evaluated(small, tmp_path):
    root, _ds, files = small
    out = tmp_path / "rec"
    res = runner.invoke(app, ["evaluate", str(files[0]), "--dataset", str(root / "ds"), "--out", str(out),
                              "--reference", "reconstruct", "--no-report"], terminal_width=250)
    assert res.exit_code == 0, res.output
    con = duckdb.connect(str(out / "results.duckdb"), read_only=True)
    m = {(s, me, k): v for s, me, k, v in con.sql(
        "SELECT stage, method, metric, value FROM metrics WHERE segment = 'all'").fetchall()}
    rec = m[("evaluation", "reference(reconstructed)", "rmse_horizontal_m")]
    online = m[("evaluation", "system_info", "rmse_horizontal_m")]
    assert rec < 0.75 * online                 # it sees the future: clearly better than the online picture
    radars = {me for s, me, _k in m if s == "radar"}
    assert len(radars) >= 2 and all(("radar", r, "range_bias_m") in m and ("radar", r, "pd") in m for r in radars)
    bad = runner.invoke(app, ["evaluate", str(files[0]), "--truth", str(root / "ds" / "truth.parquet"), "--out",
                              str(tmp_path / "x"), "--reference", "reconstruct"])
    assert bad.exit_code == 2 and "--dataset" in bad.output


def test_an_adsb_recording_is_a_reference_with_its_own_error_stated(tmp_path):
    """ADS-B points filtered by quality, only short gaps interpolated, and the
    reference's σ beside the accuracy; a picture 30 m east of the ADS-B flights scores 30 m."""
    from tertiary.core import geo
    from tertiary.evaluation.evaluate import adsb_reference_table, reference_error_metrics
    from tertiary.evaluation.matching import MatchConfig
    from tertiary.simulate.config import builtin_dir
    raw = pl.read_parquet(builtin_dir() / "adsb_paris_2021-10-07.parquet")
    raw = raw.filter(pl.col("icao24").is_in(raw["icao24"].unique().sort().head(6).to_list()))
    frame = geo.LocalFrame(48.85, 2.35, 0.0)
    ref, removed = adsb_reference_table(raw, frame)
    assert ref.height > 100 and removed.height > 0 and "reason" in removed.columns
    pic = ref.filter(pl.col("alt_m") > 1000).select(
        pl.lit(0, pl.UInt32).alias("run"), pl.col("time").alias("epoch"), pl.col("truth_id").cast(pl.UInt64)
        .alias("track_id"), (pl.col("x_m") + 30.0).alias("x_m"), "y_m", "z_m", pl.col("vx_mps").fill_null(0.0),
        pl.col("vy_mps").fill_null(0.0), "vz_mps", "alt_m", pl.lit("shifted").alias("method"))
    from tertiary.evaluation.evaluate import EvaluationConfig
    ev = evaluate_pictures(pic, ref, cfg=EvaluationConfig(match=MatchConfig(max_gap_s=10.0)))
    got = dict(ev.metrics.filter((pl.col("segment") == "all") & (pl.col("stage") == "evaluation")).select("metric", "value").iter_rows())
    assert got["rmse_horizontal_m"] == pytest.approx(30.0, abs=0.5)
    sig = reference_error_metrics(ev.metrics, ref)
    assert sig["metric"].to_list() == ["reference_sigma_h_m"] and 5.0 < sig["value"][0] < 100.0


def test_an_adsb_reference_says_its_quality_filter_and_keeps_what_it_dropped(small, tmp_path):
    """``evaluate --reference adsb``: points declaring NACp below 8 are in the evaluation's
    ``rejects`` with the reason, and the printed and recorded notes name the filter and the count."""
    import json
    from tertiary.simulate.config import builtin_dir
    from tertiary.store.run_store import RunStore
    root, _ds, files = small
    raw = pl.read_parquet(builtin_dir() / "adsb_paris_2021-10-07.parquet")
    raw = raw.filter(pl.col("icao24").is_in(raw["icao24"].unique().sort().head(6).to_list()))
    raw = raw.with_columns(pl.when(pl.int_range(pl.len()) % 10 == 3).then(6).otherwise(9).alias("nacp"))
    raw.write_parquet(tmp_path / "adsb.parquet")
    res = runner.invoke(app, ["evaluate", str(files[0]), "--dataset", str(root / "ds"), "--out", str(tmp_path / "e"),
                              "--reference", "adsb", "--adsb", str(tmp_path / "adsb.parquet")])
    assert res.exit_code == 0, res.output
    with RunStore.open(tmp_path / "e") as store:
        low = store.sql("SELECT count(*) AS n FROM rejects WHERE reason = "
                        "'declared quality below the reference bound (NACP 6 < 8)'")["n"][0]
        notes = json.loads(dict(store.sql("SELECT key, value FROM run").iter_rows())["notes"])
    assert low > 0.5 * (raw["nacp"] == 6).sum()          # the rest fail the cleaning first (on ground, ...)
    assert f"NACp >= 8 (else NUCp >= 7) and NIC >= 0; {low:,} point(s) below that quality" in notes[0]
    assert "NACp >= 8" in " ".join(res.output.split())


def test_reference_options_are_checked(small, tmp_path):
    root, _ds, files = small
    res = runner.invoke(app, ["evaluate", str(files[0]), "--dataset", str(root / "ds"), "--out", str(tmp_path / "a"),
                              "--reference", "adsb"])
    assert res.exit_code == 2 and "--adsb" in res.output
    res = runner.invoke(app, ["evaluate", str(files[0]), "--dataset", str(root / "ds"), "--out", str(tmp_path / "b"),
                              "--reference", "nope"])
    assert res.exit_code == 2 and "truth, reconstruct or adsb" in res.output


def test_a_reference_that_is_not_a_truth_table_is_one_line(small, tmp_path):
    _root, _ds, files = small
    res = runner.invoke(app, ["evaluate", str(files[0]), "--truth", str(files[0]), "--out", str(tmp_path / "o")])
    assert res.exit_code == 3 and "reference: missing column(s) truth_id, time" in res.output
    res = runner.invoke(app, ["evaluate", str(files[0]), "--truth", str(tmp_path / "none.parquet"),
                              "--out", str(tmp_path / "o")])
    assert res.exit_code == 3 and "file not found" in res.output


def _sorted(frame: pl.DataFrame) -> pl.DataFrame:
    keys = [c for c, t in frame.schema.items() if t == pl.String or t.is_integer() or isinstance(t, pl.Datetime)]
    return frame.sort(keys, nulls_last=True)


def test_a_picture_scored_in_time_blocks_equals_the_whole_picture(small):
    """The pipeline scores an on-disk picture a block of windows at a time, each block against its
    time slice of the reference (memory). On a sparse reference (a sample every 23 s,
    so most epochs interpolate across a block edge) with a gap longer than ``max_gap_s``,
    aircraft appearing and leaving inside blocks and blocks cut between reference samples, every
    output equals one call on the whole picture. Fails if a slice loses the samples just outside
    its block, if the identity items come from the slice instead of the whole reference, or if the
    scoring transient is cut per block."""
    root, ds, files = small
    picture = read_picture(files[0]).with_columns(pl.lit("system").alias("method"))
    truth = ds.truth.with_columns(pl.col("time").rank("ordinal").over("truth_id").alias("__k"))
    first = truth["truth_id"].min()
    gap = pl.col("time").is_between(truth["time"].min() + pl.duration(seconds=150),
                                     truth["time"].min() + pl.duration(seconds=260))
    truth = truth.filter((pl.col("__k") % 23 == 1) & ~(gap & (pl.col("truth_id") == first))).drop("__k")
    # the reference's Mode S addresses change part-way: identity items are each aircraft's first
    late = pl.col("time") > truth["time"].min() + pl.duration(seconds=200)
    truth = truth.with_columns(pl.when(late).then(pl.lit("ffffff")).otherwise(pl.col("icao24")).alias("icao24"))
    cfg = EvaluationConfig(match=MatchConfig(max_gap_s=60.0))
    kw = dict(radars=ds.radars, frame=ds.origin, cfg=cfg, requirements=load_requirements(example_path()))
    whole = evaluate_each([picture], truth, **kw)
    edges = picture["epoch"].unique().sort().gather_every(13)
    cut = picture.join(pl.DataFrame({"epoch": edges, "__b": range(len(edges))}), on="epoch", how="left").sort("epoch")
    cut = cut.with_columns(pl.col("__b").forward_fill().fill_null(0))
    parts = [p.drop("__b") for p in cut.partition_by("__b", maintain_order=True)]
    assert len(parts) >= 5
    got = evaluate_each([iter(parts)], truth, **kw)
    assert whole.metrics.height > 100 and whole.matched.height == picture.height
    for name in ("metrics", "requirements", "by_epoch", "samples", "id_map", "matched"):
        a, b = getattr(got, name), getattr(whole, name)
        assert a.columns == b.columns, name
        assert_frame_equal(_sorted(a), _sorted(b), check_dtypes=False, rel_tol=1e-9, abs_tol=1e-9)
    with pytest.raises(DataError, match="time order"):
        evaluate_each([iter([parts[1], parts[0]])], truth, **kw)


def test_a_reference_file_scores_as_the_reference_in_memory(small, tmp_path, monkeypatch):
    """An on-disk run hands the evaluation its truth as a reference file and releases the frame
    (memory): each block's time slice is read from the file. With row groups of 16
    samples (a slice spans and skips many), a sparse reference whose samples straddle the
    blocks' edges and identity items that change part-way, every output of the file equals the
    frame's, for the picture in blocks and whole; the file reads back as the truth. Fails if
    the file's slice is not the frame's (another row group's samples, another order) or the
    identity items come from another sample than each aircraft's first."""
    from tertiary.evaluation import evaluate as evaluation
    from tertiary.evaluation.evaluate import read_reference, write_reference
    root, ds, files = small
    monkeypatch.setattr(evaluation, "REFERENCE_GROUP_ROWS", 16)
    picture = read_picture(files[0]).with_columns(pl.lit("system").alias("method"))
    truth = ds.truth.with_columns(pl.col("time").rank("ordinal").over("truth_id").alias("__k"))
    truth = truth.filter(pl.col("__k") % 17 == 1).drop("__k")
    late = pl.col("time") > truth["time"].min() + pl.duration(seconds=200)
    truth = truth.with_columns(pl.when(late).then(pl.lit("ffffff")).otherwise(pl.col("icao24")).alias("icao24"))
    path = write_reference(truth, tmp_path / "reference.parquet")
    assert_frame_equal(read_reference(path), truth)
    kw = dict(radars=ds.radars, frame=ds.origin, cfg=EvaluationConfig(match=MatchConfig(max_gap_s=60.0)),
              requirements=load_requirements(example_path()))
    edges = picture["epoch"].unique().sort().gather_every(11)
    cut = picture.join(pl.DataFrame({"epoch": edges, "__b": range(len(edges))}), on="epoch", how="left").sort("epoch")
    parts = [p.drop("__b") for p in cut.with_columns(pl.col("__b").forward_fill().fill_null(0))
             .partition_by("__b", maintain_order=True)]
    assert len(parts) >= 5 and truth.height > 10 * 16
    for pictures in (lambda: [iter(parts)], lambda: [picture]):
        mem, disk = evaluate_each(pictures(), truth, **kw), evaluate_each(pictures(), path, **kw)
        assert mem.metrics.height > 100
        for name in ("metrics", "requirements", "by_epoch", "samples", "id_map", "matched"):
            a, b = getattr(disk, name), getattr(mem, name)
            assert a.columns == b.columns, name
            if name != "matched":           # the matched rows in the same order, the rest as sets
                a, b = _sorted(a), _sorted(b)
            # round-off: a small match cost differs by 2.6e-9 of itself
            assert_frame_equal(a, b, check_dtypes=False, rel_tol=1e-9, abs_tol=1e-9)


def test_a_reference_in_pieces_has_each_aircrafts_identity_from_its_first_sample(small, tmp_path):
    """A reference written in pieces (the streamed truth) is read for its identity items a piece
    at a time: each aircraft's items are those of its first sample even when later pieces
    carry others, and an aircraft first seen in a later piece comes after the earlier ones."""
    from tertiary.evaluation.evaluate import Reference, write_reference_pieces
    from tertiary.evaluation.matching import neighbour_times, reference_identity
    _, ds, _ = small
    truth = ds.truth.sort("time")
    late = pl.col("time") > truth["time"].min() + pl.duration(seconds=150)
    truth = truth.with_columns(pl.when(late).then(pl.lit("ffffff")).otherwise(pl.col("icao24")).alias("icao24"),
                               pl.when(late).then(pl.lit("LATE1")).otherwise(pl.col("callsign")).alias("callsign"))
    times = neighbour_times(truth)
    whole = truth.with_columns(times["__prev"], times["__next"])
    pieces = [whole.slice(k, 997) for k in range(0, whole.height, 997)]
    ref = Reference(write_reference_pieces(pieces, tmp_path / "reference"))
    assert len(ref.files) >= 4 and truth["truth_id"].n_unique() >= 3
    want = reference_identity(truth)
    assert want["icao24"].ne("ffffff").any()
    assert_frame_equal(ref.identity, want)


def test_a_picture_scored_without_its_matched_rows_has_the_same_metrics(small):
    """The pipeline asks for no matched rows back (``keep_matched=False``), and the evaluation
    then keeps of each matched block only the columns its metrics read (memory). On a
    tracker picture carrying its diagnostics (``nis``, covariances, Mode S, altitude channel) every
    output equals the full path's. Fails if the slim path drops a column a metric reads: the
    consistency rows of ``nis``, an identity item, or the id map's ``gated_truth_id``."""
    root, ds, files = small
    picture = read_picture(files[0]).with_columns(pl.lit("system").alias("method"))
    assert {"nis", "mode_s", "alt_m"} <= set(picture.columns)
    kw = dict(radars=ds.radars, frame=ds.origin, requirements=load_requirements(example_path()))
    edges = picture["epoch"].unique().sort().gather_every(17)
    cut = picture.join(pl.DataFrame({"epoch": edges, "__b": range(len(edges))}), on="epoch", how="left").sort("epoch")
    parts = [p.drop("__b") for p in cut.with_columns(pl.col("__b").forward_fill().fill_null(0))
             .partition_by("__b", maintain_order=True)]
    full = evaluate_each([iter(parts)], ds.truth, **kw)
    slim = evaluate_each([iter(parts)], ds.truth, keep_matched=False, **kw)
    assert slim.matched.height == 0 and full.matched.height == picture.height
    assert full.metrics.filter(pl.col("metric").str.starts_with("nis_")).height
    assert full.metrics.filter(pl.col("metric") == "mode_s_correct_frac").height
    for name in ("metrics", "requirements", "by_epoch", "samples", "id_map"):
        a, b = getattr(slim, name), getattr(full, name)
        assert a.columns == b.columns, name
        assert_frame_equal(_sorted(a), _sorted(b), check_dtypes=False, rel_tol=1e-12, abs_tol=1e-12)


def test_a_picture_spilled_to_disk_and_scored_in_buckets_has_the_same_metrics(small, tmp_path, monkeypatch):
    """A long picture is matched to Parquet files block by block and its metrics computed in
    buckets of aircraft or tracks (``spill``: the stage's memory bounded by a
    bucket). On a tracker picture in blocks, with buckets of 150, 400 and 10 000 rows, every
    output equals the in-memory path's and the spill directory is left empty. Fails if the
    spilled blocks lose or repeat rows, or if the buckets are not combined exactly; and if the
    accuracy's filed rows are still on disk when the metrics file theirs."""
    from tertiary.evaluation import evaluate as evaluation
    root, ds, files = small
    picture = read_picture(files[0]).with_columns(pl.lit("system").alias("method"))
    kw = dict(radars=ds.radars, frame=ds.origin, requirements=load_requirements(example_path()),
              keep_matched=False)
    edges = picture["epoch"].unique().sort().gather_every(13)
    cut = picture.join(pl.DataFrame({"epoch": edges, "__b": range(len(edges))}), on="epoch", how="left").sort("epoch")
    parts = [p.drop("__b") for p in cut.with_columns(pl.col("__b").forward_fill().fill_null(0))
             .partition_by("__b", maintain_order=True)]
    want = evaluate_each([iter(parts)], ds.truth, **kw)
    calls, left = [], []
    real = evaluation.picture_accuracy_buckets
    monkeypatch.setattr(evaluation, "picture_accuracy_buckets",
                        lambda *a, **k: calls.append(k["buckets"]) or real(*a, **k))
    real_metrics = evaluation.picture_metrics_buckets

    def metrics(*a, **k):
        # the accuracy's filed rows are gone before the metrics file theirs (disk peak)
        left.extend(k["scratch"].parent.glob("accuracy/*"))
        return real_metrics(*a, **k)
    monkeypatch.setattr(evaluation, "picture_metrics_buckets", metrics)
    for rows in (150, 400, 10_000):
        got = evaluate_each([iter(parts)], ds.truth, spill=tmp_path / "spill", bucket_rows=rows, **kw)
        for name in ("metrics", "requirements", "by_epoch", "samples", "id_map"):
            a, b = getattr(got, name), getattr(want, name)
            assert a.columns == b.columns, name
            assert_frame_equal(_sorted(a), _sorted(b), check_dtypes=False, rel_tol=1e-9, abs_tol=1e-9)
        assert not list((tmp_path / "spill").glob("*/*"))
    assert calls == [-(-picture.height // 150), -(-picture.height // 400), 1] and calls[0] > 3
    assert not left


def _as_is(frame: pl.DataFrame) -> pl.DataFrame:
    return frame


def test_a_picture_on_disk_matched_apart_a_stretch_a_piece_has_the_same_metrics(small, tmp_path, monkeypatch):
    """A distributed run's end matches a picture on disk a stretch of its windows at a time,
    each stretch a piece of its cluster (arguments shipped, pieces in any order), joins their
    OSPA, GOSPA and SIAP states, and computes the metrics a bucket of tracks or aircraft a
    piece: every output equals the picture matched and scored in memory here.
    Fails if a stretch's rows, a filed slice's or a bucket's sums are lost, or if the stretches'
    multi-target states are not joined."""
    from tertiary.evaluation import buckets, matched_apart
    from tertiary.evaluation.evaluate import write_reference
    root, ds, files = small
    picture = read_picture(files[0]).with_columns(pl.lit("system").alias("method"))
    ref = write_reference(ds.truth, tmp_path / "ref.parquet")
    kw = dict(radars=ds.radars, frame=ds.origin, requirements=load_requirements(example_path()),
              keep_matched=False, bucket_rows=400)
    edges = picture["epoch"].unique().sort().gather_every(11)
    cut = picture.join(pl.DataFrame({"epoch": edges, "__b": range(len(edges))}), on="epoch", how="left").sort("epoch")
    parts = [p.drop("__b") for p in cut.with_columns(pl.col("__b").forward_fill().fill_null(0))
             .partition_by("__b", maintain_order=True)]
    windows = []
    for k, part in enumerate(parts):
        windows.append(tmp_path / "windows" / f"w={k:06d}.parquet")
        windows[-1].parent.mkdir(exist_ok=True)
        part.write_parquet(windows[-1])
    want = evaluate_each([iter(parts)], ref, **kw)          # matched and scored in memory
    monkeypatch.setattr(matched_apart, "PIECE_ROWS", -(-picture.height // 4))
    monkeypatch.setattr(buckets, "FILE_SLICE_ROWS", -(-picture.height // 5))
    fanout = Apart()
    got = evaluate_each([matched_apart.PictureFiles("system", windows, picture.columns, _as_is, 300, fanout)], ref,
                        spill=tmp_path / "apart", **kw)
    # the stretches, then the buckets of tracks and of aircraft the metrics are computed in
    assert 3 <= fanout.pieces["_match_piece"] <= 4 and len(parts) > 6
    assert fanout.pieces["_track_piece"] > 1 and fanout.pieces["_bucket_piece"] > 1
    # the rows filed by bucket a slice a piece (tracks; aircraft for coverage, matched and
    # expected for the metrics), the coverage and the merged tracks a bucket of aircraft a piece
    assert fanout.pieces["_file_slice"] >= 4 * 4 and fanout.pieces["_coverage_piece"] > 1
    assert fanout.pieces["_merged_piece"] > 1
    assert want.metrics.filter(pl.col("metric") == "siap_track_changes_per_hour").height
    for name in ("metrics", "requirements", "by_epoch", "samples", "id_map"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.columns == b.columns, name
        assert_frame_equal(_sorted(a), _sorted(b), check_dtypes=False, rel_tol=1e-9, abs_tol=1e-9)


def test_association_labels_joined_in_blocks_equal_the_whole_join(monkeypatch):
    """The association rows are labelled with their reports' aircraft a block of rows at a time
    (memory). With blocks of 4 rows over 37 rows (reports seen by two radars, clutter,
    a report of another run with the same id), the labelled rows (in order) and every
    association metric equal one join's. Fails if a block's rows are lost, repeated or
    reordered."""
    from datetime import datetime, timedelta, timezone
    from tertiary.evaluation import association
    from tertiary.evaluation.association import _report_truth, association_metrics
    rng = np.random.default_rng(5)
    n = 37
    t0 = datetime(2021, 1, 1, tzinfo=timezone.utc)
    assoc = pl.DataFrame({"run": rng.integers(0, 2, n), "epoch": [t0 + timedelta(seconds=4 * int(k))
                                                                  for k in rng.integers(0, 6, n)],
                          "target_id": rng.integers(1, 6, n), "report_id": rng.integers(0, 20, n)},
                         schema={"run": pl.UInt32, "epoch": pl.Datetime("us", "UTC"), "target_id": pl.UInt64,
                                 "report_id": pl.UInt64})
    truth_of = pl.DataFrame({"run": [0] * 20 + [1] * 20, "report_id": list(range(20)) * 2,
                             "truth_id": [None if k % 7 == 0 else k % 4 for k in range(40)]},
                            schema={"run": pl.UInt32, "report_id": pl.UInt64, "truth_id": pl.Int64})
    whole = _report_truth(assoc, truth_of)
    want = association_metrics(assoc, truth_of)
    monkeypatch.setattr(association, "LABEL_BLOCK_ROWS", 4)
    assert_frame_equal(_report_truth(assoc, truth_of), whole)
    assert_frame_equal(association_metrics(assoc, truth_of), want)
    assert whole.height == n and whole["truth_id"].null_count() < n


def test_a_reference_file_gives_the_slices_of_the_frame(tmp_path, monkeypatch):
    """A time slice read from a reference file (coarse test in the scan, exact one after) holds
    the rows of the in-memory slice, in order: samples inside, the last one before and the
    first one after each aircraft's gaps, aircraft with one sample, slices between samples."""
    import numpy as np
    from datetime import datetime, timedelta, timezone
    from tertiary.evaluation import evaluate as E
    monkeypatch.setattr(E, "REFERENCE_GROUP_ROWS", 64)
    rng = np.random.default_rng(5)
    t0 = datetime(2021, 10, 7, 8, tzinfo=timezone.utc)
    rows = []
    for tid in range(1, 40):
        times = np.sort(rng.choice(3600, size=int(rng.integers(1, 60)), replace=False))
        rows += [(0, tid, t0 + timedelta(seconds=int(s)), float(s), 0.0, 1000.0) for s in times]
    truth = pl.DataFrame(rows, schema={"run": pl.UInt32, "truth_id": pl.Int64, "time": pl.Datetime("us", "UTC"),
                                       "x_m": pl.Float64, "y_m": pl.Float64, "z_m": pl.Float64},
                         orient="row").sort("time")
    path = E.write_reference(truth, tmp_path / "ref.parquet")
    on_disk, in_memory = E.Reference(path), E.Reference(truth)
    for a in list(rng.integers(0, 3700, 40)) + [0, 3599]:
        lo = t0 + timedelta(seconds=int(a))
        hi = lo + timedelta(seconds=int(rng.integers(0, 200)))
        want = in_memory.between(lo, hi)
        assert_frame_equal(on_disk.between(lo, hi), want)


@pytest.mark.parametrize("sparse", [False, True])
def test_association_rows_read_back_are_scored_in_blocks_as_whole(monkeypatch, sparse):
    """A run whose association scores were not carried (the Dask engine's relabelled rows) is
    scored from its rows read back, gathered to blocks of whole windows (the national
    day's rows whole took the client to 22 623 MiB): the metrics equal one call on every row.
    Two runs, 12 epochs in 5 windows, targets that change aircraft across windows (swaps),
    clutter; blocks of at least 70 rows gather 2–3 windows. With ``sparse`` report ids
    the lookup falls back to the join. Fails if a block is scored out of order, lost or
    repeated, or labelled with another run's aircraft."""
    from datetime import datetime, timedelta, timezone
    from tertiary import pipeline
    from tertiary.evaluation.association import association_metrics, association_score
    rng = np.random.default_rng(11)
    t0 = datetime(2021, 1, 1, tzinfo=timezone.utc)
    n = 160
    step = 1_000_003 if sparse else 1
    epoch = np.sort(rng.integers(0, 12, n))
    assoc = pl.DataFrame({"run": rng.integers(0, 2, n), "epoch": [t0 + timedelta(seconds=4 * int(k)) for k in epoch],
                          "target_id": rng.integers(1, 7, n), "report_id": np.arange(n) * step},
                         schema={"run": pl.UInt32, "epoch": pl.Datetime("us", "UTC"), "target_id": pl.UInt64,
                                 "report_id": pl.UInt64})
    reports = pl.DataFrame({"run": assoc["run"], "report_id": assoc["report_id"],
                            "truth_id": [None if k % 9 == 0 else int(rng.integers(0, 4)) for k in range(n)]},
                           schema={"run": pl.UInt32, "report_id": pl.UInt64, "truth_id": pl.Int64})
    assert (scoring.report_truth(reports) is None) == sparse
    want = association_metrics(assoc, reports)
    assert want.filter(pl.col("metric") == "swaps")["value"][0] > 0
    window = (pl.col("epoch").dt.epoch("s") - int(t0.timestamp())) // 10
    parts = assoc.with_columns(window.alias("__w")).partition_by("__w", maintain_order=True)
    monkeypatch.setattr(scoring, "ASSOCIATION_BLOCK_ROWS", 70)
    got = association_score(scoring.scored_blocks((p.drop("__w") for p in parts), reports))
    assert len(parts) == 5
    assert_frame_equal(got, want)


def test_evaluate_judges_the_same_default_requirements_as_run(small, tmp_path):
    """Without --requirements, `evaluate` judges the shipped example requirements, as `run` does,
    and prints them as a requirements × pictures matrix."""
    root, _ds, files = small
    out = tmp_path / "ev"
    res = runner.invoke(app, ["evaluate", str(files[0]), "--dataset", str(root / "ds"), "--out", str(out),
                              "--no-report"], terminal_width=250)
    assert res.exit_code == 0, res.output
    con = duckdb.connect(str(out / "results.duckdb"), read_only=True)
    judged = {r[0] for r in con.sql("SELECT DISTINCT requirement FROM requirements").fetchall()}
    assert judged == {r.name for r in load_requirements(example_path()).items}
    assert pipeline.PipelineConfig().requirements_file is None      # run's default: the same example file
    assert "Requirements × pictures" in res.output and "H-RMS-ENR" in res.output


def test_pictures_matched_together_in_a_window_equal_each_matched_alone(small):
    """The evaluation's window stage matches a window's pictures of one schema in one call and
    steps their multi-target states together. Each picture's matched rows, its reference at its
    own epochs and its OSPA/GOSPA/SIAP rows equal those of the picture matched alone — with two
    pictures whose epochs differ (one drops every third epoch, the other an aircraft). Fails if a
    picture's expected rows are the window's instead of its own, or if the pictures' states mix."""
    from tertiary.evaluation.evaluate import Reference, match_block
    from tertiary.evaluation.multitarget import MultiTargetState, multitarget_result
    from tertiary.evaluation.streamed import PICTURE_VALUES, MatchState, match_window
    root, ds, files = small
    a = read_picture(files[0]).with_columns(pl.lit("a").alias("method"))
    b = read_picture(files[1]).with_columns(pl.lit("b").alias("method"))
    epochs = a["epoch"].unique().sort()
    a = a.filter(~pl.col("epoch").is_in(epochs.gather_every(3).implode()))
    b = b.filter(pl.col("track_id") != b["track_id"].min()).select(a.columns)
    reference, cfg = Reference(ds.truth), EvaluationConfig()
    cut = epochs[len(epochs) // 2]
    state = MatchState()
    got: dict[str, list[pl.DataFrame]] = {}
    for inside in (pl.col("epoch") < cut, pl.col("epoch") >= cut):
        pictures = [("a", "track_id", a.filter(inside)), ("b", "track_id", b.filter(inside))]
        out, state = match_window(state, pictures, reference, cfg, multitarget=True)
        for name, frame in out.items():
            got.setdefault(name, []).append(frame)
        # the percentile sketch's counts go with the window, not in the carried state
        assert state.metrics is not None and "values" not in state.metrics.sums
        assert out[PICTURE_VALUES].height > 0
    for name, rows in (("a", a), ("b", b)):
        mt, want_m, want_e = MultiTargetState(), [], []
        for inside in (pl.col("epoch") < cut, pl.col("epoch") >= cut):
            m, e, mt = match_block(rows.filter(inside), None, reference, cfg, "track_id", mt, slim=True)
            want_m.append(m)
            want_e.append(e)
        for kind, want in (("matched.", want_m), ("expected.", want_e)):
            tables = [t for t in got if t.startswith(kind)]
            assert len(tables) == 1           # the two pictures share a schema: one table per window
            mine = pl.concat(got[tables[0]]).filter(pl.col("method") == name)
            assert_frame_equal(_sorted(mine.drop("method") if kind == "expected." else mine),
                               _sorted(pl.concat(want)))
        assert_frame_equal(multitarget_result(state.pictures[name], name), multitarget_result(mt, name))
    expected = pl.concat(got[next(t for t in got if t.startswith("expected."))])
    assert expected.filter(pl.col("method") == "a").height < expected.filter(pl.col("method") == "b").height


def test_a_second_track_on_an_aircraft_is_scored_a_duplicate_and_a_ghost_false(small):
    """Through the evaluation stage (the columns it hands the surveillance metrics): three epochs
    of a copy of a track 200 m aside (the matching leaves it to the original) add one duplicate
    track, one split track and no false one; a ghost 80 km from everything adds one false track.
    Fails if the matcher's gate is not handed to the metrics (the copy would count as false), or
    if a split is looked for among matched rows only (the one-to-one matching never gives one)."""
    root, ds, files = small
    base = read_picture(files[0])
    first = base.filter(pl.col("track_id") == base["track_id"].min()).sort("epoch")
    epochs = first["epoch"].unique().sort()[5:8]
    copy = first.filter(pl.col("epoch").is_in(epochs.implode())).with_columns(
        pl.lit(999_001, pl.UInt64).alias("track_id"), pl.col("x_m") + 200.0)
    ghost = first.with_columns(pl.lit(999_002, pl.UInt64).alias("track_id"), pl.col("x_m") + 8.0e4,
                               pl.col("y_m") + 8.0e4)

    def counts(picture: pl.DataFrame) -> tuple[float, float]:
        m = evaluate_pictures(picture, ds.truth, surveillance=True).metrics
        at = m.filter((pl.col("stage") == "evaluation") & (pl.col("segment") == "all"))
        return tuple(at.filter(pl.col("metric") == k)["value"].item()
                     for k in ("false_tracks", "duplicate_tracks", "split_tracks"))
    f0, d0, s0 = counts(base)
    f1, d1, s1 = counts(pl.concat([base, copy.cast(base.schema), ghost.cast(base.schema)]))
    assert (f1 - f0, d1 - d0, s1 - s0) == (1.0, 1.0, 1.0)
