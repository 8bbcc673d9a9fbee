"""Alignment to the system frame and the common epoch grid."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

from tertiary.stages import align
from tertiary.core import geo

US = 1_000_000


def _radars(period=(4.0, 12.0)) -> pl.DataFrame:
    return pl.DataFrame({
        "radar_id": pl.Series([1, 2], dtype=pl.UInt32), "name": ["A", "B"],
        "lat_deg": [48.9, 48.6], "lon_deg": [2.3, 2.7], "alt_m": [100.0, 50.0],
        "scan_period_s": list(period), "sigma_range_m": [30.0, 60.0], "sigma_azimuth_deg": [0.05, 0.1],
        "sigma_elevation_deg": [0.1, 0.2], "max_range_m": [2e5, 2e5]})


def _report(radar_id, track, t_s, state, cov=None, **extra) -> dict:
    cov = np.diag([100.0, 100.0, 400.0, 4.0, 4.0, 1.0]) if cov is None else cov
    return {"run": 0, "radar_id": radar_id, "local_track_id": track, "t": t_s,
            "x_m": state[0], "y_m": state[1], "z_m": state[2], "vx_mps": state[3], "vy_mps": state[4],
            "vz_mps": state[5], "est_cov": cov.ravel().tolist(), "range_m": float(np.linalg.norm(state[:3])),
            "azimuth_deg": float(np.degrees(np.arctan2(state[0], state[1])) % 360), "est_elevation_deg": 2.0,
            "res_range_m": 1.0, "res_range_var_m2": 2.0, **extra}


def _frame(rows) -> pl.DataFrame:
    t0 = 1_633_608_000 * US
    df = pl.DataFrame(rows)
    return df.with_columns(
        pl.Series("time", [t0 + int(round(r["t"] * US)) for r in rows]).cast(pl.Datetime("us", "UTC")),
        pl.col("radar_id").cast(pl.UInt32), pl.col("local_track_id").cast(pl.UInt32), pl.col("run").cast(pl.UInt32),
        pl.col("est_cov").cast(pl.Array(pl.Float64, 36)),
        pl.int_range(pl.len(), dtype=pl.UInt64).alias("report_id")).drop("t")


def test_extrapolation_matches_matrix_form():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(40, 6, 6))
    p = a @ a.transpose(0, 2, 1)
    x = rng.normal(size=(40, 6))
    dt = rng.uniform(0, 12, 40)
    xo, po = align.extrapolate(x, p.reshape(40, 36), dt, 4.0)
    f = np.tile(np.eye(6), (40, 1, 1))
    f[:, :3, 3:] = dt[:, None, None] * np.eye(3)
    d = dt[:, None, None]
    q = np.zeros((40, 6, 6))
    q[:, :3, :3] = 4 * d**3 / 3 * np.eye(3)
    q[:, :3, 3:] = q[:, 3:, :3] = 4 * d**2 / 2 * np.eye(3)
    q[:, 3:, 3:] = 4 * d * np.eye(3)
    np.testing.assert_allclose(po.reshape(40, 6, 6), f @ p @ f.transpose(0, 2, 1) + q, atol=1e-9)
    np.testing.assert_allclose(xo, np.einsum("nij,nj->ni", f, x))


def test_epoch_grid_straight_line_and_reuse():
    origin = geo.LocalFrame(48.75, 2.5, 0.0)
    radars = _radars()
    v = np.array([100.0, -50.0, 0.0])
    rows = [
        _report(1, 7, 0.5, [1000.0, 2000.0, 3000.0, *v]),
        _report(1, 7, 4.5, [1400.0, 1800.0, 3000.0, *v]),
        _report(2, 3, 1.0, [5000.0, 0.0, 2000.0, *v]),      # 12 s radar: reused at 4 and 8 s (≤ 1.5 scans)
    ]
    al, rej = align.align(_frame(rows), radars, origin)
    assert rej.height == 0
    t0 = 1_633_608_000 * US                               # the grid starts at the first report's whole second
    e = ((al["epoch"].dt.epoch("us") - t0) / US).to_list()
    by = al.with_columns(pl.Series("e", e))
    r2 = by.filter(pl.col("radar_id") == 2).sort("e")
    # 1 s report on a 4 s grid starting at the whole second 0: epochs 4, 8, ... up to 1 + 18 s
    assert r2["e"].to_list() == [4.0, 8.0, 12.0, 16.0]
    assert r2["fresh"].to_list() == [True, False, False, False]
    np.testing.assert_allclose(r2["age_s"].to_numpy(), [3.0, 7.0, 11.0, 15.0])
    # straight-line motion in the system frame: positions advance by v·Δt between epochs
    site = geo.LocalFrame(48.6, 2.7, 50.0)
    p0, v0, _ = geo.frame_to_frame(np.array([5000.0, 0.0, 2000.0]), site, origin, vel=v)
    expect = p0 + np.outer(r2["age_s"].to_numpy(), v0)
    np.testing.assert_allclose(r2.select("x_m", "y_m", "z_m").to_numpy(), expect, atol=1e-6)
    # covariance grows with the extrapolation interval
    var_x = r2["cov"].to_numpy()[:, 0]
    assert np.all(np.diff(var_x) > 0)
    # radar 1 (4 s scans, max age 1.5 scans = 6 s): report at 0.5 s → epoch 4 (its successor at
    # 4.5 s takes epoch 8); the 4.5 s report covers epoch 8 only (epoch 12 would be 7.5 s old)
    r1 = by.filter(pl.col("radar_id") == 1).sort("e")
    assert r1["e"].to_list() == [4.0, 8.0]
    assert r1["fresh"].to_list() == [True, True]


def test_superseded_and_implausible_reports_are_rejected():
    origin = geo.LocalFrame(48.75, 2.5, 0.0)
    v = [100.0, 0.0, 0.0]
    rows = [
        _report(1, 1, 0.2, [1000.0, 0.0, 1000.0, *v]),
        _report(1, 1, 0.9, [1070.0, 0.0, 1000.0, *v]),      # same epoch (4 s): supersedes the first
        _report(1, 2, 1.0, [9000.0, 0.0, 1000.0, 5000.0, 0.0, 0.0]),   # 5 km/s: diverged track
        _report(2, 5, 1.0, [np.nan, 0.0, 1000.0, *v]),
    ]
    al, rej = align.align(_frame(rows), _radars(), origin)
    reasons = dict(zip(rej["report_id"].to_list(), rej["reason"].to_list()))
    assert reasons[0].startswith("superseded")
    assert reasons[2].startswith("implausible track speed")
    assert reasons[3].startswith("no usable track estimate")
    assert set(al["report_id"].to_list()) == {1}
    # row accounting
    assert set(al["report_id"].unique().to_list()) | set(reasons) == {0, 1, 2, 3}


def test_plot_only_reports_get_estimates(big_box_runs):
    """Reports without estimate columns are tracked by the package's own Singer channels."""
    ds = big_box_runs
    plots = ds.reports.select("report_id", "run", "radar_id", "time", "local_track_id", "range_m", "azimuth_deg",
                              "elevation_deg", "truth_id")
    assert align.needs_estimates(plots)
    al, rej = align.align(plots, ds.radars, ds.origin)
    full, _ = align.align(ds.reports, ds.radars, ds.origin)
    assert rej.height == 0 and al.height == full.height
    np.testing.assert_allclose(al["x_m"].to_numpy(), full["x_m"].to_numpy(), rtol=1e-9)


def test_aligned_errors_consistent_on_terminal_area(small_terminal):
    ds = small_terminal
    al, rej = align.align(ds.reports, ds.radars, ds.origin)
    assert al["report_id"].n_unique() + rej.height == ds.reports.height
    truth = ds.truth.rename({"time": "epoch"})
    j = al.filter(pl.col("truth_id").is_not_null()).join(truth, on=["truth_id", "epoch"], suffix="_t")
    e = j.select([pl.col(c) - pl.col(c + "_t") for c in ("x_m", "y_m", "z_m")]).to_numpy()
    c = j["cov"].to_numpy()[:, [0, 1, 2, 6, 7, 8, 12, 13, 14]].reshape(-1, 3, 3)
    nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(c), e)
    assert 1.5 < nees.mean() < 5.0          # χ²(3) mean is 3
    assert np.median(np.hypot(e[:, 0], e[:, 1])) < 300.0


def test_plan_row_estimate_is_exact_and_bounded(small_terminal):
    """The memory estimate made before allocating is the number of rows expand then builds; a
    limit below it is refused with ResourceError before any aligned row exists."""
    from dataclasses import replace

    from tertiary.core.errors import ResourceError
    ds = small_terminal
    p = align.plan(ds.reports, ds.radars, ds.origin)
    assert p.rows == align.expand(p).height > 0
    with pytest.raises(ResourceError, match="aligned rows"):
        align.plan(ds.reports, ds.radars, ds.origin, replace(align.AlignConfig(), max_rows=p.rows - 1))


def test_no_report_aligns_to_empty_frames():
    al, rej = align.align(pl.DataFrame(schema={"radar_id": pl.UInt32, "time": pl.Datetime("us", "UTC")}),
                          _radars(), geo.LocalFrame(48.8, 2.5, 0.0))
    assert al.height == 0 and rej.height == 0 and "cov" in al.columns


def test_align_rejects_index_the_input_rows(small_terminal):
    """rejects.row_index is the row of the input table for align-stage rejects too: input
    shuffled, with invalid rows first (so validated and input rows differ)."""
    import dataclasses as dc
    from tertiary import pipeline
    from tertiary.stages.align import AlignConfig
    rep = small_terminal.reports.sample(fraction=1.0, shuffle=True, seed=1)
    bad = rep.head(3).with_columns(pl.lit(-5.0).alias("range_m"), (pl.col("report_id") + 10 ** 9).alias("report_id"))
    rep = pl.concat([bad, rep])
    ing = pipeline.screen(dc.replace(small_terminal, reports=rep), pipeline.PipelineConfig(align=AlignConfig(period_s=12.0)))
    rows = ing.rejects.join(rep.with_row_index("input_row").select("report_id", "input_row"), on="report_id")
    assert set(rows["stage"].unique().to_list()) == {"ingest", "align"}
    assert rows.filter(pl.col("stage") == "align").height > 100
    assert (rows["row_index"] == rows["input_row"].cast(pl.UInt64)).all()
