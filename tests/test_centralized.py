"""Centralised measurement-level Kalman filter: equals filterpy, beats every single radar,
and is consistent (NEES)."""

from __future__ import annotations

from datetime import timedelta

import dataclasses

import numpy as np
import polars as pl
import pytest
from filterpy.kalman import KalmanFilter

from tertiary.core import geo
from tertiary.stages.fusion.centralized import (POS, VEL, CentralizedConfig, centralized_filter, centralized_fusion,
                                                centralized_step, converted_plots, init_centralized_state,
                                                initial_state, transition)
from tertiary.evaluation.accuracy import (AccuracyConfig, accuracy_from_matched, scored_rows)
from tertiary.evaluation.consistency import consistency_metrics
from tertiary.evaluation.matching import match_to_reference


def _scored(fused: pl.DataFrame, truth: pl.DataFrame) -> pl.DataFrame:
    """The pictures matched by the one matcher, scored after the 20 s transient."""
    matched = match_to_reference(fused, truth, id_col="target_id").rename({"target_id": "track_id"})
    return scored_rows(matched, AccuracyConfig(skip_first_s=20.0))
from tertiary.contract import TABLES, validate
from tertiary.simulate import load_scenario, simulate

STATE = ["x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"]


def _random_sequences(rng: np.random.Generator, lengths: list[int]):
    """Converted plots of a few targets: noisy straight lines, random SPD R, irregular times
    (including simultaneous plots of two radars)."""
    t, z, r = [], [], []
    for n in lengths:
        dt = rng.choice([0.0, 0.5, 1.0, 4.0], size=n - 1, p=[0.2, 0.3, 0.3, 0.2])
        tt = np.concatenate([[rng.uniform(0, 5)], rng.uniform(0, 5) + np.cumsum(dt)])
        v = rng.normal(0, 100, 3)
        p0 = rng.normal(0, 20_000, 3)
        a = rng.normal(size=(n, 3, 3)) * rng.uniform(5, 80, (n, 1, 1))
        rr = a @ a.transpose(0, 2, 1) + 25.0 * np.eye(3)
        noise = np.einsum("nij,nj->ni", np.linalg.cholesky(rr), rng.normal(size=(n, 3)))
        t.append(tt), z.append(p0 + (tt - tt[0])[:, None] * v + noise), r.append(rr)
    lengths_a = np.array(lengths)
    starts = np.concatenate([[0], np.cumsum(lengths_a)[:-1]])
    return np.concatenate(t), np.concatenate(z), np.concatenate(r), starts, lengths_a


@pytest.mark.parametrize("variant", ["printed", "exact"])
def test_batched_filter_matches_filterpy_step_for_step(variant):
    rng = np.random.default_rng(42)
    cfg = CentralizedConfig(variant=variant, sigma_m=3.0)
    lengths = [40, 7, 25, 1, 40]
    t, z, r, starts, lengths_a = _random_sequences(rng, lengths)
    xs, ps = centralized_filter(t, z, r, starts, lengths_a, cfg)
    for s, n in zip(starts, lengths):
        kf = KalmanFilter(dim_x=9, dim_z=3)
        kf.H = np.zeros((3, 9))
        kf.H[[0, 1, 2], POS] = 1.0
        x0, p0 = initial_state(z[s:s + 1], r[s:s + 1], cfg)
        kf.x, kf.P = x0[0].copy(), p0[0].copy()
        np.testing.assert_allclose(xs[s], kf.x, rtol=1e-12)
        for i in range(s + 1, s + n):
            phi, q = transition(np.array([t[i] - t[i - 1]]), cfg)
            kf.F, kf.Q = phi[0], q[0]
            kf.predict()
            kf.update(z[i], R=r[i])
            scale_x, scale_p = np.abs(kf.x).max(), np.abs(kf.P).max()
            np.testing.assert_allclose(xs[i], kf.x, rtol=1e-9, atol=1e-9 * scale_x)
            np.testing.assert_allclose(ps[i], kf.P, rtol=1e-9, atol=1e-9 * scale_p)


def test_downlinked_velocities_are_a_second_update_as_in_filterpy():
    """Rows with a downlinked horizontal velocity get, after the plot's update, a velocity
    update (H on vx, vy) — filterpy's, step for step; the first plot of a target included
    (its one-point initiation then takes the velocity); rows without one are unchanged."""
    rng = np.random.default_rng(7)
    cfg = CentralizedConfig(sigma_m=3.0, use_velocity=True)
    lengths = [30, 1, 12]
    t, z, r, starts, lengths_a = _random_sequences(rng, lengths)
    v = rng.normal(0, 150, (len(t), 2))
    a = rng.normal(size=(len(t), 2, 2))
    rv = a @ a.transpose(0, 2, 1) + 0.25 * np.eye(2)
    v[rng.random(len(t)) < 0.3] = np.nan                  # replies without the register
    xs, ps = centralized_filter(t, z, r, starts, lengths_a, cfg, vel=(v, rv))
    hv = np.zeros((2, 9))
    hv[[0, 1], VEL[:2]] = 1.0
    for s, n in zip(starts, lengths):
        kf = KalmanFilter(dim_x=9, dim_z=3)
        kf.H = np.zeros((3, 9))
        kf.H[[0, 1, 2], POS] = 1.0
        for i in range(s, s + n):
            if i == s:
                x0, p0 = initial_state(z[i:i + 1], r[i:i + 1], cfg)
                kf.x, kf.P = x0[0].copy(), p0[0].copy()
            else:
                phi, q = transition(np.array([t[i] - t[i - 1]]), cfg)
                kf.F, kf.Q = phi[0], q[0]
                kf.predict()
                kf.update(z[i], R=r[i])
            if np.isfinite(v[i]).all():
                kf.update(v[i], R=rv[i], H=hv)
            scale_x, scale_p = np.abs(kf.x).max(), np.abs(kf.P).max()
            np.testing.assert_allclose(xs[i], kf.x.ravel(), rtol=1e-9, atol=1e-9 * scale_x)
            np.testing.assert_allclose(ps[i], kf.P, rtol=1e-9, atol=1e-9 * scale_p)
    one = starts[1]                                       # a target seen once: velocity from its reply
    assert np.isfinite(v[one]).all() and np.abs(xs[one, VEL[:2]] - v[one]).max() < 5.0


def test_keep_mask_returns_the_same_posteriors():
    rng = np.random.default_rng(1)
    t, z, r, starts, lengths = _random_sequences(rng, [12, 5, 9])
    xs, ps = centralized_filter(t, z, r, starts, lengths)
    keep = rng.random(len(t)) < 0.4
    xk, pk = centralized_filter(t, z, r, starts, lengths, keep=keep)
    np.testing.assert_array_equal(xk, xs[keep])
    np.testing.assert_array_equal(pk, ps[keep])


# --------------------------------------------------------------------------- on big-box


@pytest.fixture(scope="module")
def big_box10():
    return simulate(load_scenario("big-box").replace(runs=10))


def _truth_associations(reports: pl.DataFrame) -> pl.DataFrame:
    """Trivial associations: target_id = truth_id, epoch = report time."""
    return reports.filter(pl.col("truth_id").is_not_null()).select(
        "run", pl.col("time").alias("epoch"), "radar_id", "local_track_id", "report_id",
        pl.col("truth_id").cast(pl.UInt64).alias("target_id"), pl.lit(0.0).alias("cost"))


def _radar_tracks(ds, radar_id: int) -> pl.DataFrame:
    """One radar's own track estimates moved to the system frame, as ``fused``-like rows."""
    rep = ds.reports.filter(pl.col("radar_id") == radar_id)
    row = ds.radars.filter(pl.col("radar_id") == radar_id).row(0, named=True)
    site = geo.LocalFrame(row["lat_deg"], row["lon_deg"], row["alt_m"])
    p, v, c = geo.frame_to_frame(rep.select(STATE[:3]).to_numpy(), site, ds.origin,
                                 vel=rep.select(STATE[3:]).to_numpy(),
                                 cov=rep["est_cov"].to_numpy().reshape(-1, 6, 6))
    state = np.hstack([p, v])
    return rep.select("run", pl.col("time").alias("epoch"), pl.col("truth_id").cast(pl.UInt64).alias("target_id")
                      ).with_columns(pl.lit(f"radar{radar_id}").alias("method"),
                                     *[pl.Series(n, state[:, i]) for i, n in enumerate(STATE)],
                                     pl.Series("cov", c.reshape(-1, 36), dtype=pl.Array(pl.Float64, 36)))


@pytest.fixture(scope="module")
def big_box_fused(big_box10):
    ds = big_box10
    assoc = _truth_associations(ds.reports)
    epochs = assoc.select("run", "epoch", "target_id").unique()
    cen = centralized_fusion(ds.reports, ds.radars, assoc, epochs, ds.origin)
    return ds, assoc, cen


def test_output_is_in_the_fused_schema(big_box_fused):
    ds, assoc, cen = big_box_fused
    assert cen.schema == pl.Schema({**TABLES["fused"].columns, "tentative": pl.Boolean})
    validate(cen.drop("tentative"), "fused")
    assert cen["tentative"].null_count() == 0
    assert cen.height == 10 * 852
    assert set(cen["method"]) == {"centralized"}
    assert cen["n_sources"].unique().to_list() == [2]          # two synchronous radars per 1 s epoch
    assert cen["radar_ids"].list.len().unique().to_list() == [2]
    assert cen["weights"].list.len().unique().to_list() == [0]


def test_centralized_beats_every_single_radar(big_box_fused):
    ds, assoc, cen = big_box_fused
    radars = [_radar_tracks(ds, rid) for rid in ds.radars["radar_id"]]
    fused = pl.concat([cen.select(radars[0].columns), *radars])
    m = accuracy_from_matched(_scored(fused, ds.truth))
    pos = dict(m.filter((pl.col("metric") == "rmse_pos_m") & (pl.col("segment") == "all"))
               .select("method", "value").iter_rows())
    assert m["n_runs"].unique().to_list() == [10]
    for rid in ds.radars["radar_id"]:
        assert pos["centralized"] < pos[f"radar{rid}"], pos
    # the centralised reference is clearly better than one radar (≈ 22 m vs ≈ 35 m here)
    assert pos["centralized"] < 0.8 * min(pos["radar1"], pos["radar2"])


def test_centralized_is_consistent(big_box_fused):
    """Monte-Carlo consistency done properly (tertiary.evaluation.accuracy.consistency_metrics): the
    position NEES averaged over the N = 10 runs at each epoch lies in the two-sided 95 % band
    χ²(3N)/N on most epochs; the same test rejects a covariance twice too large or too small."""
    ds, assoc, cen = big_box_fused
    matched = _scored(cen, ds.truth)
    m = consistency_metrics(matched, "nees_pos", 3, "nees", "fusion")
    frac = m.filter((pl.col("metric") == "nees_in_band_frac") & (pl.col("segment") == "all"))["value"].item()
    print(f"centralized NEES in band on {frac:.3f} of epochs")
    assert frac >= 0.85
    for scale in (2.0, 0.5):
        off = matched.with_columns(pl.col("nees_pos") * scale)
        bad = consistency_metrics(off, "nees_pos", 3, "nees", "fusion")
        assert bad.filter((pl.col("metric") == "nees_in_band_frac") & (pl.col("segment") == "all"))["value"].item() < 0.5


def test_centralized_is_above_the_posterior_cramer_rao_bound(big_box_fused):
    """The PCRB for the motion the truth flies (tertiary.evaluation.bound: each manoeuvre's
    onset and shape known, not its size) and the radars' polar noise bounds the centralised
    filter — every plot, but a Singer model that knows nothing of the manoeuvres — from below,
    and not by an order of magnitude: RMSE within [1, 2] PCRB. The bound of the radar plots
    alone: the centralised filter does not take the downlinked velocities."""
    from tertiary.evaluation.bound import BoundConfig, illuminations, pcrb_at
    ds, assoc, cen = big_box_fused
    matched = _scored(cen, ds.truth)
    cfg = dataclasses.replace(BoundConfig.from_scenario(ds.scenario), downlinked_velocity=False)
    ev = illuminations(ds.truth, ds.radars, ds.reports, ds.origin, cfg)
    b = pcrb_at(matched.select("truth_id", "epoch"), ev, cfg, truth=ds.truth)
    pcrb = float(np.sqrt(b["b2_pos"].mean()))
    rmse = float(np.sqrt(matched["e2_pos"].mean()))
    print(f"centralized RMSE {rmse:.2f} m, PCRB {pcrb:.2f} m")
    assert pcrb <= rmse <= 2.0 * pcrb


def test_downlinked_velocities_make_the_reference_better_and_the_bound_still_bounds(big_box_fused):
    """Big-box Mode S traffic, ``use_velocity``: the reference with the downlinked velocities is
    far better (velocity error ≈ 0.6 m/s against ≈ 6 m/s, position about half) than on the
    plots alone, and the PCRB with the downlinked velocities still lies below it. Fails if the
    velocities are read but not used."""
    from tertiary.evaluation.bound import BoundConfig, illuminations, pcrb_at
    ds, assoc, plots = big_box_fused
    epochs = assoc.select("run", "epoch", "target_id").unique()
    cen = centralized_fusion(ds.reports, ds.radars, assoc, epochs, ds.origin, CentralizedConfig(use_velocity=True))
    rmse = {}
    for name, f in (("with", cen), ("plots", plots)):
        m = _scored(f, ds.truth)
        dv = (m["vx_mps"] - m["true_vx_mps"]) ** 2 + (m["vy_mps"] - m["true_vy_mps"]) ** 2
        rmse[name] = (float(np.sqrt(m["e2_pos"].mean())), float(np.sqrt(dv.mean())))
    cfg = BoundConfig.from_scenario(ds.scenario)
    matched = _scored(cen, ds.truth)
    b = pcrb_at(matched.select("truth_id", "epoch"), illuminations(ds.truth, ds.radars, ds.reports, ds.origin, cfg),
                cfg, truth=ds.truth)
    print(rmse, "PCRB", float(np.sqrt(b["b2_pos"].mean())))
    assert rmse["with"][1] < 0.2 * rmse["plots"][1]
    assert rmse["with"][0] < 0.7 * rmse["plots"][0]
    assert float(np.sqrt(b["b2_pos"].mean())) <= rmse["with"][0]


def test_epochs_between_plots_are_predictions(big_box10):
    """Half-second epochs: the state is the last posterior predicted forward; epochs before the
    first plot give no row; n_sources counts the plots since the previous epoch."""
    ds = big_box10
    rep = ds.reports.filter((pl.col("run") == 0) & (pl.col("time") < ds.reports["time"].min() + timedelta(seconds=6)))
    # radar 2 only from t = 3 s
    t0 = rep["time"].min()
    rep = rep.filter((pl.col("radar_id") == 1) | (pl.col("time") >= t0 + timedelta(seconds=3)))
    assoc = _truth_associations(rep)
    grid = [t0 + timedelta(milliseconds=500 * k) for k in range(-1, 11)]
    epochs = pl.DataFrame({"run": 0, "epoch": grid, "target_id": 0}).with_columns(
        pl.col("run").cast(pl.UInt32), pl.col("target_id").cast(pl.UInt64),
        pl.col("epoch").cast(pl.Datetime("us", "UTC")))
    out = centralized_fusion(rep, ds.radars, assoc, epochs, ds.origin)
    assert out["epoch"].to_list() == grid[1:]
    assert out["n_sources"].to_list() == [1, 0, 1, 0, 1, 0, 2, 0, 2, 0, 2]
    assert out["radar_ids"].to_list() == [[1]] * 6 + [[1, 2]] * 5
    cfg = CentralizedConfig()
    phi, q = transition(np.array([0.5]), cfg)
    sel = np.array([0, 3, 6, 1, 4, 7])
    for k in range(0, 10, 2):                    # epoch k (on a plot) → epoch k + 1 (half a second later)
        a, b = out.row(k, named=True), out.row(k + 1, named=True)
        assert b["n_sources"] == 0
        assert np.all(np.isfinite(b["cov"]))
        assert abs(b["y_m"] - a["y_m"] - 0.5 * a["vy_mps"]) < 5.0    # ≈ straight north at 83 m/s
    # exact check: predict the posterior at the first plot with the filter's own matrices
    z, r, ok = converted_plots(rep.sort("time", "radar_id"), ds.radars, ds.origin)
    x0, p0 = initial_state(z[:1], r[:1], cfg)
    first = out.row(1, named=True)                # 0.5 s after the first plot
    np.testing.assert_allclose([first[c] for c in STATE], (phi[0] @ x0[0])[sel], rtol=1e-12)
    cov = (phi[0] @ p0[0] @ phi[0].T + q[0])[np.ix_(sel, sel)]
    np.testing.assert_allclose(np.asarray(first["cov"]).reshape(6, 6), cov, rtol=1e-12)


@pytest.mark.parametrize("confirmation, flags", [
    ("plots", [True, True, False, False, False, False]),
    ("three_scan", [True, True, True, True, False, False])])
def test_epochs_between_reports_keep_the_confirmation_reached(big_box10, confirmation, flags):
    """One aircraft seen by radar 1 alone for 3 s (one plot a second), epochs every half second.
    Counting plots: tentative at its first plot and half a second after it (one radar, one plot
    so far), confirmed from its local track's second plot on. Three scans: confirmed at its third
    plot (two seconds in: the first two plots move 83 m in a second, the third lies where they
    point). Predicted epochs take the status reached by then, in one window or two."""
    ds = big_box10
    cfg = CentralizedConfig(confirmation=confirmation)
    rep = ds.reports.filter((pl.col("run") == 0) & (pl.col("radar_id") == 1) & (pl.col("truth_id") == 0))
    t0 = rep["time"].min()
    rep = rep.filter(pl.col("time") < t0 + timedelta(seconds=3))
    grid = [t0 + timedelta(milliseconds=500 * k) for k in range(6)]
    epochs = pl.DataFrame({"run": 0, "epoch": grid, "target_id": 0}).with_columns(
        pl.col("run").cast(pl.UInt32), pl.col("target_id").cast(pl.UInt64),
        pl.col("epoch").cast(pl.Datetime("us", "UTC")))
    assoc = _truth_associations(rep)
    out = centralized_fusion(rep, ds.radars, assoc, epochs, ds.origin, cfg)
    assert out["n_sources"].to_list() == [1, 0, 1, 0, 1, 0]
    assert out["tentative"].to_list() == flags
    # the same in windows cut after the first, second and third plots: the status is carried
    for ms in (700, 1200, 1700, 2200):
        cut = int((t0 + timedelta(milliseconds=ms)).timestamp() * 1e6)
        state, got = init_centralized_state(), []
        for before in (True, False):
            def part(f: pl.DataFrame, c: str) -> pl.DataFrame:
                return f.filter((pl.col(c).dt.epoch("us") < cut) == before)
            out, state = centralized_step(state, part(rep, "time"), ds.radars, part(assoc, "epoch"),
                                          part(epochs, "epoch"), ds.origin, cfg)
            got += out["tentative"].to_list()
        assert got == flags, ms


def test_reports_without_association_or_elevation_are_not_used(big_box10):
    ds = big_box10
    rep = ds.reports.filter(pl.col("run") == 0).head(50)
    assoc = _truth_associations(rep).filter(pl.col("report_id") % 2 == 0)
    rep = rep.with_columns(pl.when(pl.col("report_id") == 4).then(None).otherwise(pl.col("elevation_deg"))
                           .alias("elevation_deg"), pl.lit(None, pl.Float64).alias("altitude_m"))
    epochs = assoc.select("run", "epoch", "target_id").unique()
    out = centralized_fusion(rep, ds.radars, assoc, epochs, ds.origin)
    used = assoc.filter(pl.col("report_id") != 4).height
    assert out["n_sources"].sum() == used


def test_empty_inputs_give_an_empty_fused_table(big_box10):
    ds = big_box10
    assoc = _truth_associations(ds.reports).head(0)
    out = centralized_fusion(ds.reports, ds.radars, assoc, assoc.select("run", "epoch", "target_id"), ds.origin)
    assert out.is_empty() and out.schema == pl.Schema({**TABLES["fused"].columns, "tentative": pl.Boolean})
