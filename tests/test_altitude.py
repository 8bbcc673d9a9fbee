"""The vertical channel (tertiary.stages.tracking.altitude) and its use by simulation, fusion and evaluation."""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pymap3d
import pytest
from filterpy.kalman import KalmanFilter

from tertiary.core import geo
from tertiary.stages.tracking.altitude import (FT_M, QUANTUM_MODE_C_M, QUANTUM_MODE_S_M, AltitudeConfig, AltState, filter_tracks, filter_tracks_carry, geodetic_channel, geodetic_height_rate, predict, quantisation_variance, update2)
from tertiary.evaluation.accuracy import error_columns
from tertiary.simulate.radar import quantum_m, transponder_altitude
from tertiary.simulate.trajectory import Trajectories

PARIS = geo.LocalFrame(48.85, 2.35, 0.0)


def _filterpy_run(t, z, r, cfg):
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.x = np.array([[z[0]], [0.0]])
    kf.P = np.diag([r, cfg.v0_sigma_mps ** 2])
    kf.H = np.array([[1.0, 0.0]])
    kf.R = np.array([[r]])
    out = [kf.x[:, 0].copy()]
    covs = [kf.P.copy()]
    for k in range(1, len(t)):
        tau = t[k] - t[k - 1]
        kf.F = np.array([[1.0, tau], [0.0, 1.0]])
        q = cfg.q_m2ps3
        kf.Q = q * np.array([[tau ** 3 / 3, tau ** 2 / 2], [tau ** 2 / 2, tau]])
        kf.predict()
        kf.update(np.array([[z[k]]]))
        out.append(kf.x[:, 0].copy())
        covs.append(kf.P.copy())
    return np.array(out), np.array(covs)


def test_filter_matches_filterpy_on_several_tracks():
    rng = np.random.default_rng(1)
    # no gating, one model, no inflated output before confirmation: a plain Kalman filter
    cfg = AltitudeConfig(model="cv", gate_floor_m=1e9, unconfirmed_sigma_m=None)
    lengths = np.array([30, 7, 55])
    t = np.concatenate([np.cumsum(rng.uniform(3.0, 6.0, n)) for n in lengths])
    z = np.concatenate([3000 + 8.0 * np.arange(n) + rng.normal(0, 3, n) for n in lengths])
    r = 9.0
    starts = np.r_[0, np.cumsum(lengths)[:-1]]
    est, has, rej = filter_tracks(t, z, np.full(len(t), r), starts, lengths, cfg)
    first = np.zeros(len(t), bool)
    first[starts] = True
    assert (has == ~first).all() and not rej.any()      # output from the second (confirming) reply on
    for s, n in zip(starts, lengths):
        ref, cov = _filterpy_run(t[s:s + n], z[s:s + n], r, cfg)
        sl = slice(s, s + n)
        np.testing.assert_allclose(est.h[sl], ref[:, 0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(est.r[sl], ref[:, 1], rtol=0, atol=1e-9)
        np.testing.assert_allclose(est.phh[sl], cov[:, 0, 0], rtol=1e-9)
        np.testing.assert_allclose(est.phr[sl], cov[:, 0, 1], rtol=1e-9)
        np.testing.assert_allclose(est.prr[sl], cov[:, 1, 1], rtol=1e-9)


def _filterpy_imm(t, z, r, cfg):
    from filterpy.kalman import IMMEstimator
    tau = t[1] - t[0]
    filters = []
    for q in (cfg.q_level_m2ps3, cfg.q_m2ps3):
        kf = KalmanFilter(dim_x=2, dim_z=1)
        kf.x = np.array([[z[0]], [0.0]])
        kf.P = np.diag([r, cfg.v0_sigma_mps ** 2])
        kf.H = np.array([[1.0, 0.0]])
        kf.R = np.array([[r]])
        kf.F = np.array([[1.0, tau], [0.0, 1.0]])
        kf.Q = q * np.array([[tau ** 3 / 3, tau ** 2 / 2], [tau ** 2 / 2, tau]])
        filters.append(kf)
    p_l, p_m = 1 - np.exp(-tau / cfg.level_sojourn_s), 1 - np.exp(-tau / cfg.manoeuvre_sojourn_s)
    imm = IMMEstimator(filters, np.array([0.5, 0.5]), np.array([[1 - p_l, p_l], [p_m, 1 - p_m]]))
    out, covs, mus = [imm.x[:, 0].copy()], [np.diag([r, cfg.v0_sigma_mps ** 2])], [imm.mu.copy()]
    for k in range(1, len(t)):
        imm.predict()
        imm.update(np.array([[z[k]]]))
        out.append(imm.x[:, 0].copy())
        covs.append(imm.P.copy())
        mus.append(imm.mu.copy())
    return np.array(out), np.array(covs), np.array(mus)


def test_imm_altitude_filter_matches_filterpy_imm():
    """(A5)–(A9) against filterpy's IMMEstimator: level, climb, level-off, constant interval
    (the plain IMM: no garble gate, no held replies)."""
    rng = np.random.default_rng(7)
    cfg = AltitudeConfig(gate_floor_m=1e9, unconfirmed_sigma_m=None, hold_sigma=0.0)
    t = np.arange(80) * 4.0
    h = np.where(t < 100, 3000.0, np.where(t < 200, 3000.0 + 10.0 * (t - 100), 4000.0))
    z = h + rng.normal(0, 2.2, len(t))
    r = 2.2 ** 2
    est, has, rej = filter_tracks(t, z, np.full(len(t), r), np.array([0]), np.array([len(t)]), cfg)
    ref, cov, _ = _filterpy_imm(t, z, r, cfg)
    np.testing.assert_allclose(est.h, ref[:, 0], rtol=0, atol=1e-8)
    np.testing.assert_allclose(est.r, ref[:, 1], rtol=0, atol=1e-8)
    np.testing.assert_allclose(est.phh, cov[:, 0, 0], rtol=1e-8)
    np.testing.assert_allclose(est.phr, cov[:, 0, 1], rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(est.prr, cov[:, 1, 1], rtol=1e-8)


def test_level_aircraft_rate_is_known_and_a_climb_is_followed():
    """Level at a 25 ft quantum: the IMM's rate σ falls well below the single filter's
    (~1 m/s), which is what keeps aircraft 1 000 ft apart out of a conflict probe; a 10 m/s
    climb is still followed within half a minute."""
    t = np.arange(100) * 4.0
    h = np.where(t < 200, 3048.0, 3048.0 + 10.0 * (t - 200))
    q = QUANTUM_MODE_S_M
    z = np.round(h / q) * q
    r = np.full(len(t), quantisation_variance(q))
    imm, _, _ = filter_tracks(t, z, r, np.array([0]), np.array([len(t)]), AltitudeConfig())
    cv, _, _ = filter_tracks(t, z, r, np.array([0]), np.array([len(t)]), AltitudeConfig(model="cv"))
    level = t == 196.0
    assert np.sqrt(imm.prr[level][0]) < 0.2 < 0.6 < np.sqrt(cv.prr[level][0])
    assert abs(imm.r[level][0]) < 0.1
    after = t == 232.0                             # 32 s into the climb
    assert abs(imm.r[after][0] - 10.0) < 1.5


def test_a_garbled_first_reply_is_never_confirmed():
    """Found on the default job: a track whose first Mode C reply was garbled (FL381 for an
    aircraft at 1 400 ft) held that altitude for two scans (11 km vertical error). Now an
    unconfirmed filter restarts on the next reply outside its gate and is output only with an
    inflated σ (or not at all), so a confirmed source always wins."""
    t = np.arange(10) * 4.0
    z = np.full(10, 426.72)
    z[0] = 11620.5                                   # garbled first code
    r = np.full(10, quantisation_variance(QUANTUM_MODE_S_M))
    strict = AltitudeConfig(unconfirmed_sigma_m=None)
    est, has, _ = filter_tracks(t, z, r, np.array([0]), np.array([10]), strict)
    assert not has[0] and not has[1]                 # reply 1 disagrees: restart, still unconfirmed
    assert has[2:].all() and np.abs(est.h[2:] - 426.72).max() < 1.0
    est, has, _ = filter_tracks(t, z, r, np.array([0]), np.array([10]), AltitudeConfig())
    assert has.all() and np.sqrt(est.phh[:2]).min() >= 60.0 and np.sqrt(est.phh[2:]).max() < 10.0
    assert est.h[1] == 426.72                        # restarted on the true altitude at once


def test_a_new_identity_on_the_track_restarts_the_filter_at_once():
    """A radar track that swaps aircraft (its Mode S address changes) must not carry the first
    aircraft's altitude for max_rejects replies."""
    t = np.arange(12) * 4.0
    z = np.where(np.arange(12) < 6, 11582.4, 426.72)
    ident = np.where(np.arange(12) < 6, 0xCE6732, 0x829BDC)
    r = np.full(12, quantisation_variance(QUANTUM_MODE_S_M))
    est, has, rej = filter_tracks(t, z, r, np.array([0]), np.array([12]), AltitudeConfig(), ident=ident)
    assert not rej[6] and est.h[6] == z[6] and np.sqrt(est.phh[6]) >= 60.0   # restarted, unconfirmed
    assert has[7:].all() and np.abs(est.h[7:] - 426.72).max() < 1.0
    without, has2, rej2 = filter_tracks(t, z, r, np.array([0]), np.array([12]), AltitudeConfig())
    assert rej2[6] and has2[6] and without.h[6] > 11000           # what the identity prevents


def test_garble_is_rejected_and_a_real_jump_restarts_the_filter():
    cfg = AltitudeConfig()
    t = np.arange(40) * 4.0
    z = np.full(40, 3048.0)
    z[10] += 25 * 2 ** 7 * 0.3048                  # one garbled code (a bit flip, ~975 m)
    z[25:] += 600.0                               # a genuine level change held afterwards
    z[5] = np.nan                                 # missing altitude
    r = np.full(40, quantisation_variance(QUANTUM_MODE_S_M))
    est, has, rej = filter_tracks(t, z, r, np.array([0]), np.array([40]), cfg)
    assert rej[10] and abs(est.h[10] - 3048.0) < 1.0
    assert has[5] and abs(est.h[5] - 3048.0) < 1.0
    assert rej[25] and not rej[26] and est.h[26] == z[26]   # the 2nd (max_rejects) outlier restarts the filter
    assert abs(est.h[-1] - 3648.0) < 1.0


def test_update2_is_the_kalman_update_with_h_identity():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(5, 2, 2))
    p = a @ a.transpose(0, 2, 1) + np.eye(2)
    b = rng.normal(size=(5, 2, 2))
    r = b @ b.transpose(0, 2, 1) + 0.5 * np.eye(2)
    x, z = rng.normal(size=(5, 2)), rng.normal(size=(5, 2))
    s = AltState(x[:, 0], x[:, 1], p[:, 0, 0], p[:, 0, 1], p[:, 1, 1])
    m = AltState(z[:, 0], z[:, 1], r[:, 0, 0], r[:, 0, 1], r[:, 1, 1])
    out = update2(s, m)
    k = p @ np.linalg.inv(p + r)
    xe = x + np.einsum("nij,nj->ni", k, z - x)
    pe = (np.eye(2) - k) @ p
    np.testing.assert_allclose(np.c_[out.h, out.r], xe, atol=1e-12)
    np.testing.assert_allclose(np.c_[out.phh, out.phr, out.prr], pe[:, [0, 0, 1], [0, 1, 1]], atol=1e-12)


def test_predict_is_constant_rate_with_white_acceleration():
    s = AltState(np.array([100.0]), np.array([5.0]), np.array([4.0]), np.array([1.0]), np.array([2.0]))
    out = predict(s, np.array([10.0]), 0.5)
    f = np.array([[1, 10.0], [0, 1]])
    q = 0.5 * np.array([[1000 / 3, 50], [50, 10]])
    p = f @ np.array([[4.0, 1.0], [1.0, 2.0]]) @ f.T + q
    assert out.h[0] == pytest.approx(150.0) and out.r[0] == 5.0
    np.testing.assert_allclose([out.phh[0], out.phr[0], out.prr[0]], [p[0, 0], p[0, 1], p[1, 1]])


def test_geodetic_height_matches_pymap3d_and_is_not_enu_z():
    rng = np.random.default_rng(4)
    pos = np.c_[rng.uniform(-150e3, 150e3, 50), rng.uniform(-150e3, 150e3, 50), rng.uniform(0, 9000, 50)]
    vel = rng.normal(0, 100, (50, 3))
    h, hdot, up = geodetic_height_rate(pos, vel, PARIS)
    _, _, h_ref = pymap3d.enu2geodetic(pos[:, 0], pos[:, 1], pos[:, 2], 48.85, 2.35, 0.0)
    np.testing.assert_allclose(h, h_ref, atol=1e-3)
    # rate = numerical derivative of the height along the velocity
    dt = 1e-3
    h2, _, _ = geodetic_height_rate(pos + vel * dt, vel, PARIS)
    np.testing.assert_allclose(hdot, (h2 - h) / dt, atol=1e-2)
    rho = np.hypot(pos[:, 0], pos[:, 1])
    far = rho > 60e3
    assert np.all(h[far] - pos[far, 2] > 0.9 * rho[far] ** 2 / (2 * 6.4e6))   # z falls below h by ρ²/2R
    # the spherical fallback stays within its documented 9 m at 150 km
    hs, _, _ = geodetic_height_rate(pos, vel, None)
    assert np.all(np.abs(hs - h) <= 9.0)


def test_level_pair_far_from_centre_has_equal_height():
    """Two aircraft at the same geodetic height 120 km from the centre, 10 km apart: the same
    alt_m although their ENU z differ."""
    e, n, u = PARIS.from_geodetic(np.array([49.9, 49.95]), np.array([2.35, 2.45]), np.array([3000.0, 3000.0]))
    pos = np.c_[e, n, u]
    h, _, _ = geodetic_height_rate(pos, np.zeros((2, 3)), PARIS)
    np.testing.assert_allclose(h, 3000.0, atol=1e-6)
    assert abs(u[1] - u[0]) > 10.0


def test_geodetic_channel_variance_is_along_the_local_up():
    pos = np.array([[100e3, 0.0, 5000.0, 200.0, 0.0, 0.0]])
    cov = np.diag([1e4, 1e4, 1e2, 1.0, 1.0, 1.0])[None]
    s = geodetic_channel(pos, cov, PARIS)
    _, _, up = geodetic_height_rate(pos[:, :3], pos[:, 3:], PARIS)
    assert s.phh[0] == pytest.approx(float(up[0] @ cov[0, :3, :3] @ up[0]))
    assert s.phh[0] > 1e2 + 0.9 * 1e4 * (100e3 / 6.4e6) ** 2          # the tilt mixes in horizontal variance
    assert abs(s.r[0]) == pytest.approx(200.0 * 100e3 / 6.38e6, rel=0.01)  # ḣ of a "level in z" radial flight


def test_transponder_altitude_quanta_garbles_and_missing():
    rng = np.random.default_rng(5)
    n = 200_000
    alt = rng.uniform(500, 9000, n)
    q = np.where(np.arange(n) % 2 == 0, QUANTUM_MODE_S_M, QUANTUM_MODE_C_M)
    rep = transponder_altitude(alt, q, rng)
    ok = np.isfinite(rep)
    assert abs((~ok).mean() - 0.01) < 0.002
    steps = rep[ok] / q[ok]
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-9)      # on the quantum grid
    err = np.abs(rep[ok] - alt[ok])
    good = err <= q[ok] / 2 + 1e-9
    assert abs((~good).mean() - 0.005 * 10 / 11) < 0.0015              # bit 0 of a garble stays within ±q
    assert np.all(rep[ok] >= 0) and np.all(err <= 8000.0)
    assert err[q[ok] == QUANTUM_MODE_S_M].max() > 4000.0               # high bits do flip


def test_quantum_from_mode_s_address():
    traj = Trajectories(dt=1.0, pos=np.zeros((3, 2, 3)), vel=np.zeros((3, 2, 3)), active=np.ones((3, 2), bool),
                        segment=np.zeros((3, 2), np.int8), truth_id=np.arange(3),
                        meta={"icao24": np.array(["abc123", "", "def456"])})
    np.testing.assert_allclose(quantum_m(traj), [QUANTUM_MODE_S_M, QUANTUM_MODE_C_M, QUANTUM_MODE_S_M])


def test_truth_carries_geodetic_alt():
    pos = np.array([[[80e3, 50e3, 4000.0], [80.2e3, 50e3, 4000.0]]])
    vel = np.array([[[200.0, 0.0, 0.0], [200.0, 0.0, 0.0]]])
    traj = Trajectories(dt=1.0, pos=pos, vel=vel, active=np.ones((1, 2), bool),
                        segment=np.zeros((1, 2), np.int8), truth_id=np.array([7]))
    tr = traj.to_frame(frame=PARIS)
    _, _, h_ref = pymap3d.enu2geodetic(pos[0, :, 0], pos[0, :, 1], pos[0, :, 2], 48.85, 2.35, 0.0)
    np.testing.assert_allclose(tr["alt_m"].to_numpy(), h_ref, atol=1e-3)
    assert (tr["alt_rate_mps"] > 2.0).all()         # level in z is climbing in height away from the centre
    assert "alt_m" not in traj.to_frame().columns


def test_height_error_uses_alt_when_both_carry_it():
    df = pl.DataFrame({"segment": ["straight"] * 2, **{c: [0.0, 0.0] for c in
                       ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")},
                       **{f"true_{c}": [0.0, 0.0] for c in ("x_m", "y_m", "vx_mps", "vy_mps", "vz_mps")},
                       "true_z_m": [500.0, 500.0], "alt_m": [1010.0, None], "true_alt_m": [1000.0, 1000.0]})
    out = df.with_columns(error_columns(True))
    assert out["e2_height"].to_list() == [100.0, 250000.0]               # Δalt², else Δz²
    assert df.with_columns(error_columns(False))["e2_height"].to_list() == [250000.0, 250000.0]


def test_pipeline_heights_come_from_mode_c(small_terminal):
    """Simulated terminal area → fusion, centralised reference and tracker all carry the Mode C
    channel: height RMSE of a few metres (elevation-based heights are off by ~100 m), and a
    target whose reports lose their altitude falls back to the geodetic height."""
    from tertiary.evaluation.accuracy import AccuracyConfig, scored_rows
    from tertiary.evaluation.evaluate import evaluate_pictures
    from tertiary.stages.fusion import fuse
    from tertiary.evaluation.matching import MatchConfig, match_to_reference
    from tertiary.pipeline import PipelineConfig, process
    from tertiary.contract import validate

    res = process(small_terminal, PipelineConfig(methods=("arithmetic",), filters=("singer",)))
    validate(res.fused, "fused")
    validate(res.tracks.drop("status", "plot_target_id"), "tracks")
    # a wide vertical gate: the fallback below has heights hundreds of metres off
    wide = MatchConfig(gate_v_m=3000.0)

    def match(fused: pl.DataFrame) -> pl.DataFrame:
        matched = match_to_reference(fused, small_terminal.truth, wide, id_col="target_id")
        return scored_rows(matched.rename({"target_id": "track_id"}), AccuracyConfig())

    m = match(res.fused)
    err = (m["alt_m"] - m["true_alt_m"]).abs()
    assert err.median() < 5.0
    for method in ("arithmetic", "centralized"):
        sub = m.filter(pl.col("method") == method)
        assert (sub["alt_m"] - sub["true_alt_m"]).abs().median() < 5.0
    pictures = res.tracks.with_columns(pl.format("{}+{}", "method", "filter").alias("method")).drop("filter")
    tm = evaluate_pictures(pictures, small_terminal.truth).metrics.filter(pl.col("stage") == "tracker")
    h = tm.filter((pl.col("metric") == "rmse_height_m") & (pl.col("segment") == "all"))["value"][0]
    assert h < 30.0
    # without Mode C: geodetic fallback (elevation-based), far worse but still height, not z
    rows = res.aligned.with_columns(res.associations["target_id"]).sort("run", "epoch", "target_id", "radar_id")
    f0 = fuse(rows.with_columns(pl.lit(None, pl.Float64).alias("altitude_m")), small_terminal.radars,
              ["arithmetic"], origin=small_terminal.origin)
    m0 = match(f0)
    e0 = (m0["alt_m"] - m0["true_alt_m"]).abs()
    ez = (m0["z_m"] - m0["true_alt_m"]).abs()
    assert 20.0 < e0.median() < 400.0
    assert e0.median() < ez.median()


# --------------------------------------------------------------------------- compiled recursion


def _replies(rng: np.random.Generator, n_tracks: int = 200):
    """Tracks of 1–80 Mode C / Mode S replies: level and climbing aircraft, 3 % garbles of
    0.1–3 km, 5 % missing altitudes, an identity that changes on 1 % of the replies."""
    lengths = rng.integers(1, 80, n_tracks)
    starts = np.r_[0, np.cumsum(lengths)[:-1]]
    n = int(lengths.sum())
    t = np.concatenate([np.cumsum(rng.uniform(3.0, 13.0, m)) for m in lengths])
    h0, rate = rng.uniform(1_000.0, 10_000.0, n_tracks), rng.choice([0.0, 0.0, 8.0, -6.0], n_tracks)
    z = np.concatenate([h0[g] + rate[g] * (t[s:s + m] - t[s]) for g, (s, m) in enumerate(zip(starts, lengths))])
    z += rng.normal(0.0, 7.0, n)
    garble = rng.random(n) < 0.03
    z[garble] += rng.choice([-1.0, 1.0], garble.sum()) * rng.uniform(100.0, 3_000.0, garble.sum())
    low_bit = rng.random(n) < 0.03         # 100 / 200 ft codes: inside the garble gate, held
    z[low_bit] += rng.choice([-1.0, 1.0], low_bit.sum()) * rng.choice([100.0, 200.0], low_bit.sum()) * FT_M
    z[rng.random(n) < 0.05] = np.nan
    var = quantisation_variance(np.where(rng.random(n) < 0.5, QUANTUM_MODE_S_M, QUANTUM_MODE_C_M))
    ident = np.where(rng.random(n) < 0.01, 7, 3)
    ident[rng.random(n) < 0.1] = -1
    return t, z, var, starts, lengths, ident


def _assert_same_filter(a, b) -> None:
    (oa, ha, ra, ca), (ob, hb, rb, cb) = a, b
    for f in ("h", "r", "phh", "phr", "prr"):
        np.testing.assert_allclose(getattr(ob, f), getattr(oa, f), rtol=1e-12, atol=1e-9, err_msg=f)
    assert np.array_equal(ha, hb) and np.array_equal(ra, rb)
    for f in ("models", "mu", "t_last", "ok", "conf", "miss", "last_id", "post", "has", "held", "held_id"):
        x, y = getattr(ca, f), getattr(cb, f)
        if x.dtype.kind == "f":
            np.testing.assert_allclose(y, x, rtol=1e-12, atol=1e-9, err_msg=f)
        else:
            assert np.array_equal(x, y), f


@pytest.mark.parametrize("cfg", [AltitudeConfig(), AltitudeConfig(model="cv"),
                                 AltitudeConfig(unconfirmed_sigma_m=None, max_rejects=3)],
                         ids=["imm", "cv", "confirmed-only"])
def test_compiled_filter_equals_the_vectorised_reference(cfg):
    """The compiled per-track recursion (tertiary.stages.tracking.altitude_kernel) gives the vectorised loop's
    estimates, masks and carry — in one call, and in two calls per track (the second from the
    first's carry), with garbles, missing altitudes and identity swaps."""
    t, z, var, starts, lengths, ident = _replies(np.random.default_rng(5))
    want = filter_tracks_carry(t, z, var, starts, lengths, cfg, ident=ident, compiled=False)
    got = filter_tracks_carry(t, z, var, starts, lengths, cfg, ident=ident, compiled=True)
    _assert_same_filter(want, got)
    assert want[2].sum() > 20 and (~want[1]).sum() > 0 and not np.isnan(want[0].h).all()   # not vacuous
    if cfg.model == "imm":          # replies were held and decided both ways
        without = filter_tracks_carry(t, z, var, starts, lengths, dataclasses.replace(cfg, hold_sigma=0.0),
                                      ident=ident, compiled=False)
        assert (np.abs(without[0].h - want[0].h) > 1.0).sum() > 20
    # each track's replies in two calls: the first half, then the rest from the carry
    first = np.maximum(lengths // 2, 1)
    keep = np.concatenate([np.arange(s, s + m) for s, m in zip(starts, first)])
    s1 = np.r_[0, np.cumsum(first)[:-1]]
    rest_len = lengths - first
    more = rest_len > 0
    rest = np.concatenate([np.arange(s + m, s + L) for s, m, L in zip(starts, first, lengths) if L > m])
    s2 = np.r_[0, np.cumsum(rest_len[more])[:-1]]
    for compiled in (False, True):
        a = filter_tracks_carry(t[keep], z[keep], var[keep], s1, first, cfg, ident=ident[keep], compiled=compiled)
        b = filter_tracks_carry(t[rest], z[rest], var[rest], s2, rest_len[more], cfg, ident=ident[rest],
                                init=a[3].take(np.flatnonzero(more)), compiled=compiled)
        np.testing.assert_allclose(b[0].h, want[0].h[rest], rtol=1e-12, atol=1e-9)
        assert np.array_equal(b[1], want[1][rest])



def _level_with_garbles(garble_ft: float, scan_s: float = 8.0):
    """A level Mode S aircraft at FL391 seen every ``scan_s``, one reply of which carries a code
    ``garble_ft`` low (a low bit flipped), and the filter's estimate of every row."""
    t = np.arange(40) * scan_s
    z = np.full(len(t), 11_925.3)
    z[25] -= garble_ft * FT_M
    var = np.full(len(t), float(quantisation_variance(QUANTUM_MODE_S_M)))
    return t, z, var


@pytest.mark.parametrize("garble_ft", [100.0, 200.0])
@pytest.mark.parametrize("compiled", [True, False])
def test_a_low_bit_garble_does_not_start_a_descent(garble_ft, compiled):
    """One garbled reply inside the garble gate of a level aircraft is held, then dropped when
    the next reply is level again: the rate stays at zero and the height at the level. Without
    the hold (``hold_sigma=0``) the same reply gives a 4–10 m/s phantom descent, which a
    conflict probe extrapolates by ~0.5–1 km over its look-ahead."""
    t, z, var = _level_with_garbles(garble_ft)
    one = (np.array([0]), np.array([len(t)]))
    est, has, rej = filter_tracks_carry(t, z, var, *one, AltitudeConfig(), compiled=compiled)[:3]
    assert has[5:].all() and not rej.any()            # inside the garble gate: not a "garble" to it
    assert np.abs(est.r[20:]).max() < 0.2
    assert np.abs(est.h[20:] - 11_925.3).max() < 2.0
    old = filter_tracks_carry(t, z, var, *one, AltitudeConfig(hold_sigma=0.0), compiled=compiled)[0]
    assert old.r[25] < -3.0                            # what the hold removes


@pytest.mark.parametrize("compiled", [True, False])
def test_a_real_descent_starts_one_reply_later(compiled):
    """A descent at 10 m/s from level flight: the first reply off the level is held, the second
    confirms it, and both are applied — the estimate then follows as without the hold."""
    t = np.arange(60) * 4.0
    h = np.where(t < 100.0, 9_000.0, 9_000.0 - 10.0 * (t - 100.0))
    rng = np.random.default_rng(3)
    z = np.round((h + rng.normal(0.0, 1.0, len(t))) / QUANTUM_MODE_S_M) * QUANTUM_MODE_S_M
    var = np.full(len(t), float(quantisation_variance(QUANTUM_MODE_S_M)))
    one = (np.array([0]), np.array([len(t)]))
    est = filter_tracks_carry(t, z, var, *one, AltitudeConfig(), compiled=compiled)[0]
    free = filter_tracks_carry(t, z, var, *one, AltitudeConfig(hold_sigma=0.0), compiled=compiled)[0]
    late = t >= 140.0                                  # 40 s into the descent
    np.testing.assert_allclose(est.r[late], -10.0, atol=1.0)
    np.testing.assert_allclose(est.h[late], free.h[late], atol=5.0)
    onset = int(np.argmax(np.abs(free.r) > 2.0))      # the first row the free filter sees the descent at
    assert abs(est.r[onset]) < abs(free.r[onset]) and abs(est.r[onset + 1]) > 2.0


# --------------------------------------------------------------------------- extrapolation of the IMM's estimate


def test_the_combined_estimate_is_extrapolated_with_the_mode_weighted_intensity():
    """(A5) over τ: c_M = μ_M(1 − p_ML) + (1 − μ_M)p_LM; the intensity is c_L q_L + c_M q_M (the
    manoeuvre model's alone where μ is unknown, the one model's for "cv")."""
    from tertiary.stages.tracking.altitude import mixture_q
    cfg = AltitudeConfig()
    tau = np.array([4.0, 4.0, 4.0, 10.0])
    mu = np.array([0.0, 1.0, np.nan, 0.2])
    p_lm, p_ml = 1 - np.exp(-tau / cfg.level_sojourn_s), 1 - np.exp(-tau / cfg.manoeuvre_sojourn_s)
    c_m = np.array([p_lm[0], 1 - p_ml[1], 1.0, 0.2 * (1 - p_ml[3]) + 0.8 * p_lm[3]])
    np.testing.assert_allclose(mixture_q(mu, tau, cfg), (1 - c_m) * cfg.q_level_m2ps3 + c_m * cfg.q_m2ps3, rtol=1e-12)
    np.testing.assert_allclose(mixture_q(mu, tau, AltitudeConfig(model="cv")), cfg.q_m2ps3)


def test_a_level_aircraft_rate_stays_known_between_its_replies():
    """A radar track of a level aircraft (Mode S, a reply every 10 s) read at epochs up to 9 s
    after its last reply: the vertical channel's rate σ stays that of the level model (a few
    cm/s grown by the small chance of a manoeuvre), never the manoeuvre model's q_M·τ — which
    made a conflict probe see every level aircraft as possibly climbing at ~1 m/s (a 95 %
    vertical estimation term of ~200 m over the look-ahead) and alert pairs 1 000 ft apart."""
    from tertiary.stages.fusion.vertical import _mode_c_per_row
    n = 60
    t0 = np.datetime64("2021-10-07T08:00:00", "us")
    times = t0 + (np.arange(n) * 10_000_000).astype("timedelta64[us]")
    rows = pl.DataFrame({"run": np.zeros(n, np.uint32), "radar_id": np.ones(n, np.uint32),
                         "local_track_id": np.full(n, 7, np.uint32), "report_id": np.arange(n, dtype=np.uint64),
                         "time": times, "epoch": times + np.timedelta64(9, "s"), "altitude_m": np.full(n, 10668.0),
                         "fresh": np.ones(n, bool), "mode_s": ["3c6444"] * n}
                        ).with_columns(pl.col("time", "epoch").cast(pl.Datetime("us", "UTC")))
    est, has, _ = _mode_c_per_row(rows, AltitudeConfig())
    assert has[5:].all()
    assert np.sqrt(est.prr[-20:]).max() < 0.6                 # q_M·τ alone would give √(0.5·9) ≈ 2.1 m/s
    assert np.abs(est.r[-20:]).max() < 1e-6


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "reference"])
def test_a_refused_reply_is_no_better_than_its_residual_so_a_levelled_off_source_wins(compiled):
    """An aircraft climbing at 16.5 m/s levels off; two radars' filters (replies every 8 s, 4 s
    apart) both refuse the first level replies. A refused reply's output variance holds its
    residual, so from the moment one source has restarted on the level it wins the
    minimum-variance choice, instead of the other filter that is still extrapolating the climb.
    Fails when a refused row outputs the prediction's own variance (the extrapolating filter,
    a few metres of σ, is kept, 230 m above the level)."""
    from tertiary.stages.tracking.altitude import combine_min_variance, predict_combined
    cfg = AltitudeConfig()
    level_t, rate, h0 = 200.0, 16.5, 5000.0

    def height(t):
        return h0 + rate * np.minimum(t, level_t)
    ta, tb = np.arange(0.0, 300.0, 8.0), np.arange(4.0, 300.0, 8.0)
    t = np.r_[ta, tb]
    z = np.round(height(t) / QUANTUM_MODE_S_M) * QUANTUM_MODE_S_M
    var = np.full(len(t), quantisation_variance(QUANTUM_MODE_S_M))
    starts, lengths = np.array([0, len(ta)]), np.array([len(ta), len(tb)])
    est, has, rej, _, mu = filter_tracks_carry(t, z, var, starts, lengths, cfg, compiled=compiled, with_mu=True)
    assert rej.any()
    refused = np.flatnonzero(rej)
    assert (est.phh[refused] > (z[refused] - (est.h[refused])) ** 2).all()
    # the first restart on the level: the second refused reply of one source
    first = t[(t > level_t) & ~rej & (np.abs(est.h - height(t)) < QUANTUM_MODE_S_M)].min()
    assert first < level_t + 16.0
    worst = 0.0
    for epoch in np.arange(first + 2.0, 280.0, 4.0):     # every epoch after it
        last = [s + np.searchsorted(t[s:s + n], epoch, side="right") - 1 for s, n in zip(starts, lengths)]
        now = predict_combined(est.take(np.array(last)), epoch - t[last], mu[last], cfg)
        pick, ok = combine_min_variance(now, has[last], np.zeros(2, np.int64), 1)
        assert ok[0]
        worst = max(worst, abs(pick.h[0] - height(epoch)))
    assert worst < 10.0, worst


def test_a_source_that_saw_the_level_off_is_kept_over_older_ones_still_extrapolating_the_climb():
    """An aircraft climbing at 16.7 m/s levels off (instantly, as the simulator flies it). Three
    en-route radars see it every 12 s: two replied last 4–5 s before the level-off, the third
    0.2 s after it, with a downlinked vertical rate of zero, and restarts on that reply. Once the
    older filters' extrapolated climb is beyond the garble gate of the newer one (some 70 m,
    4 s after the level-off), and until they reply again, the target's height follows the
    newer source: the older filters, confident in a steady climb, have the smaller variance.
    Fails without :func:`superseded` (the minimum-variance choice keeps the climb, 80–110 m up)."""
    from tertiary.stages.tracking.altitude import combine_min_variance, predict_combined, superseded
    cfg = AltitudeConfig()
    level_t, rate, h0 = 300.0, 16.7, 5000.0

    def height(t):
        return h0 + rate * np.minimum(t, level_t)
    phases = (-5.0, -4.0, 0.2)                          # each radar's reply time relative to the level-off
    times = [np.arange(level_t + ph - 288.0, level_t + 60.0, 12.0) for ph in phases]
    t = np.concatenate(times)
    z = np.round(height(t) / QUANTUM_MODE_S_M) * QUANTUM_MODE_S_M
    var = np.full(len(t), quantisation_variance(QUANTUM_MODE_S_M))
    vr = np.where(t < level_t, rate, 0.0)
    lengths = np.array([len(x) for x in times])
    starts = np.r_[0, np.cumsum(lengths)[:-1]]
    est, has, _, _, mu = filter_tracks_carry(t, z, var, starts, lengths, cfg, with_mu=True, vrate=vr)
    group = np.zeros(3, np.int64)
    for epoch in (level_t + 5.0, level_t + 6.0, level_t + 6.9):   # before the older radars reply again
        last = np.array([s + np.searchsorted(t[s:s + n], epoch, side="right") - 1 for s, n in zip(starts, lengths)])
        now = predict_combined(est.take(last), epoch - t[last], mu[last], cfg)
        valid = has[last] & ~superseded(now, has[last], group, (t[last] * 1e6).astype(np.int64), cfg)
        pick, ok = combine_min_variance(now, valid, group, 1)
        assert ok[0]
        assert abs(pick.h[0] - height(epoch)) < 10.0, (epoch, pick.h[0], height(epoch))


def test_an_accepted_garble_or_an_unconfirmed_restart_supersedes_nothing():
    """The newest source differs from an older one by less than the garble gate (a garble its
    filter accepted), or carries an unconfirmed filter's inflated σ: the older, better source
    stays; beyond the gate of confirmed filters, the older source is superseded."""
    from tertiary.stages.tracking.altitude import superseded
    cfg = AltitudeConfig()
    s = AltState(np.array([5000.0, 5030.0, 5000.0, 5250.0]), np.zeros(4), np.array([4.0, 9.0, 4.0, 3600.0]),
                 np.zeros(4), np.full(4, 0.01))
    group = np.array([0, 0, 1, 1])
    t_reply = np.array([1_000_000, 3_000_000, 1_000_000, 3_000_000])
    assert not superseded(s, np.ones(4, bool), group, t_reply, cfg).any()
    far = AltState(s.h.copy(), s.r, s.phh.copy(), s.phr, s.prr)
    far.h[1], far.h[3], far.phh[3] = 5100.0, 5400.0, 9.0   # beyond the gate, and a confirmed 400 m jump
    assert superseded(far, np.ones(4, bool), group, t_reply, cfg).tolist() == [True, False, True, False]

def _level_offs(rng: np.random.Generator, n_tracks: int = 150):
    """Tracks that climb or descend at 5–20 m/s and level off (or level aircraft that start a
    climb) part-way, a reply every 4–12 s, with each reply's downlinked vertical rate (σ 1 m/s,
    missing on a third), 3 % garbles of 0.1–3 km and 5 % missing altitudes."""
    lengths = rng.integers(2, 60, n_tracks)
    starts = np.r_[0, np.cumsum(lengths)[:-1]]
    t = np.concatenate([np.cumsum(rng.uniform(4.0, 12.0, m)) for m in lengths])
    z, vr = np.empty(len(t)), np.empty(len(t))
    for g, (s, m) in enumerate(zip(starts, lengths)):
        tt = t[s:s + m] - t[s]
        change = rng.uniform(0.0, tt[-1] + 1.0)
        before, after = (rng.choice([-1.0, 1.0]) * rng.uniform(5.0, 20.0), 0.0)
        if g % 3 == 0:
            before, after = after, before
        rate = np.where(tt < change, before, after)
        z[s:s + m] = 3000.0 + before * np.minimum(tt, change) + after * np.maximum(tt - change, 0.0)
        vr[s:s + m] = rate + rng.normal(0.0, 1.0, m)
    z = np.round(z / QUANTUM_MODE_S_M) * QUANTUM_MODE_S_M
    garble = rng.random(len(t)) < 0.03
    z[garble] += rng.choice([-1.0, 1.0], garble.sum()) * rng.uniform(100.0, 3_000.0, garble.sum())
    z[rng.random(len(t)) < 0.05] = np.nan
    vr[rng.random(len(t)) < 0.33] = np.nan
    return t, z, np.full(len(t), quantisation_variance(QUANTUM_MODE_S_M)), starts, lengths, vr


@pytest.mark.parametrize("cfg", [AltitudeConfig(), AltitudeConfig(model="cv")], ids=["imm", "cv"])
def test_the_compiled_filter_equals_the_reference_with_downlinked_rates(cfg):
    """With downlinked vertical rates the compiled recursion still gives the vectorised loop's
    estimates, masks and carry, and the registers do restart filters (not vacuous)."""
    t, z, var, starts, lengths, vr = _level_offs(np.random.default_rng(9))
    want = filter_tracks_carry(t, z, var, starts, lengths, cfg, compiled=False, vrate=vr)
    got = filter_tracks_carry(t, z, var, starts, lengths, cfg, compiled=True, vrate=vr)
    _assert_same_filter(want, got)
    blind = filter_tracks_carry(t, z, var, starts, lengths, cfg, compiled=False)
    assert (np.abs(blind[0].h - want[0].h) > 30.0).sum() > 10


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "reference"])
def test_a_level_off_said_by_the_register_restarts_the_filter_at_once(compiled):
    """A climb at 16.5 m/s levels off between two replies (every 8 s). The first level reply is
    outside the garble gate; its downlinked vertical rate (0 m/s) says the aircraft changed its
    vertical motion, so the filter restarts on it at once with that rate, instead of
    extrapolating the climb (+130 m) until the second refused reply. A garbled code whose
    register agrees with the filter's rate is still refused. Fails without the register's
    restart."""
    cfg = AltitudeConfig()
    t = np.arange(0.0, 320.0, 8.0)
    h = 5000.0 + 16.5 * np.minimum(t, 200.0)
    z = np.round(h / QUANTUM_MODE_S_M) * QUANTUM_MODE_S_M
    vr = np.where(t <= 200.0, 16.5, 0.0)
    z[10] += 25 * 2 ** 7 * FT_M                   # a garbled code in the climb, its register the climb's
    var = np.full(len(t), quantisation_variance(QUANTUM_MODE_S_M))
    est, has, rej, _ = filter_tracks_carry(t, z, var, np.array([0]), np.array([len(t)]), cfg, compiled=compiled,
                                           vrate=vr)
    first = int(np.searchsorted(t, 200.0, side="right"))        # the first level reply
    assert rej[10] and abs(est.h[10] - h[10]) < 10.0
    assert not rej[first] and abs(est.h[first] - h[first]) < QUANTUM_MODE_S_M and abs(est.r[first]) < 1e-9
    assert np.abs(est.h[first:] - h[first:]).max() < QUANTUM_MODE_S_M
    blind = filter_tracks_carry(t, z, var, np.array([0]), np.array([len(t)]), cfg, compiled=compiled)[0]
    assert blind.h[first] - h[first] > 100.0                   # what the register prevents


def test_the_fused_vertical_channel_reads_the_reports_downlinked_rate():
    """A radar track's reports (every 8 s) of a climb that levels off, each with its downlinked
    vertical rate (the measured plots' ``plot_vrate_mps``): the fused vertical channel's row of the first level report is at the level, not 130 m above
    it. Fails when the channel does not hand the reports' registers to its filters."""
    from tertiary.stages.fusion.vertical import _mode_c_per_row
    n = 40
    sec = np.arange(n) * 8.0
    h = 5000.0 + 16.5 * np.minimum(sec, 200.0)
    t0 = np.datetime64("2021-10-07T08:00:00", "us")
    times = t0 + (sec * 1e6).astype("timedelta64[us]")
    rows = pl.DataFrame({"run": np.zeros(n, np.uint32), "radar_id": np.ones(n, np.uint32),
                         "local_track_id": np.full(n, 7, np.uint32), "report_id": np.arange(n, dtype=np.uint64),
                         "time": times, "epoch": times, "fresh": np.ones(n, bool), "mode_s": ["3c6444"] * n,
                         "altitude_m": np.round(h / QUANTUM_MODE_S_M) * QUANTUM_MODE_S_M,
                         "ehs_vrate_mps": np.where(sec <= 200.0, 16.5, 0.0)}
                        ).with_columns(pl.col("time", "epoch").cast(pl.Datetime("us", "UTC")))
    # the aligned rows do not carry the register: the measured plots do
    plots = rows.select("run", "report_id", pl.col("ehs_vrate_mps").alias("plot_vrate_mps"))
    rows = rows.drop("ehs_vrate_mps")
    est, has, _ = _mode_c_per_row(rows, AltitudeConfig(), plots=plots)
    first = int(np.searchsorted(sec, 200.0, side="right"))
    assert has[first] and abs(est.h[first] - h[first]) < QUANTUM_MODE_S_M
    blind, _, _ = _mode_c_per_row(rows, AltitudeConfig())
    assert blind.h[first] - h[first] > 100.0


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "reference"])
def test_a_register_updates_the_rate_of_a_reply_inside_the_garble_gate(compiled):
    """A climb at 16.5 m/s levels off 1 s before a reply (every 12 s): the reply's altitude is
    inside the garble gate, so only its downlinked vertical rate (0 m/s) can show the level-off.
    The rate update takes it (the gate grown by the vertical acceleration allowed over 12 s), and
    the channel read between the replies stays at the level instead of climbing 200 m to the next
    reply. Fails without the rate update of a used reply."""
    from tertiary.stages.tracking.altitude import predict_combined
    cfg = AltitudeConfig()
    t = np.arange(0.0, 400.0, 12.0) + 1.0
    level_t = 12.0 * 16
    h = 5000.0 + 16.5 * np.minimum(t, level_t)
    z = np.round(h / QUANTUM_MODE_S_M) * QUANTUM_MODE_S_M
    vr = np.where(t <= level_t, 16.5, 0.0)
    var = np.full(len(t), quantisation_variance(QUANTUM_MODE_S_M))
    one = (np.array([0]), np.array([len(t)]))
    est, has, rej, _, mu = filter_tracks_carry(t, z, var, *one, cfg, compiled=compiled, with_mu=True, vrate=vr)
    k = int(np.searchsorted(t, level_t, side="right"))     # the first level reply, 1 s after the level-off
    assert not rej[k] and abs(est.r[k]) < 1.5
    ahead = predict_combined(est.take(np.array([k])), np.array([11.0]), mu[[k]], cfg)
    assert abs(ahead.h[0] - (5000.0 + 16.5 * level_t)) < 25.0
    assert not rej[k + 1:].any()
    blind = filter_tracks_carry(t, z, var, *one, cfg, compiled=compiled, with_mu=True)
    far = predict_combined(blind[0].take(np.array([k])), np.array([11.0]), blind[4][[k]], cfg)
    assert far.h[0] - (5000.0 + 16.5 * level_t) > 150.0
