"""Radar registration: each radar's systematic errors estimated from the reports themselves.

Measurement model (the simulator's sign convention, :mod:`tertiary.simulate.radar`). A radar
``r`` at site ``s_r`` measures an aircraft whose true system-frame position is ``p(t)`` at true
time ``t`` and stamps the report with its own clock ``t̃ = t + δ_r``:

    (R1)  range    ρ̃ = (1 + g_r)·ρ_r(p(t̃ − δ_r)) + b_r + ε_ρ,   ρ_r(p) = |M_r p + o_r|
    (R2)  azimuth  β̃ = β_r(p(t̃ − δ_r)) + a_r + ε_β,             β_r(p) = atan2(e, n) of M_r p + o_r
    (R3)  altitude h̃ = H(p(t̃ − δ_r)) + ε_h                       (Mode C/S, geodetic height)

``M_r``, ``o_r``: rotation and offset from the system ENU frame to the radar's site ENU frame
(exact ellipsoidal geometry, :mod:`tertiary.core.geo`); ``b_r`` range bias (m), ``a_r`` azimuth
bias, ``δ_r`` clock offset (s; radar clock minus true time), ``g_r`` range gain (optional).

Linearisation (one Gauss–Newton step about the current estimate; iterated to convergence, so
the result is the exact least-squares solution of (R1)–(R3), not of the linear model):

    (L1)  ρ̃ − ρ_r(p̂) ≈ b_r + g_r ρ_r − ρ̇_r δ_r + ∇ρ_r·Δp,    ρ̇_r = ∇ρ_r·v   (line-of-sight speed)
    (L2)  β̃ − β_r(p̂) ≈ a_r − β̇_r δ_r + ∇β_r·Δp,              β̇_r = ∇β_r·v   (cross speed / ground range)

so a clock offset is seen through the target's speed along the line of sight (range) and
across it (azimuth), which is what separates it from ``b_r`` and ``a_r``.

Two estimators (:func:`estimate`):

* ``reference`` — against a reference trajectory (truth, or ADS-B positions): ``p(t)`` is
  known (cubic Hermite between samples), ``Δp = 0``; per radar a weighted LS in
  (b, a, δ[, g]) — every parameter is absolute.
* ``multi`` — radar to radar, no reference: reports of different radars on the same aircraft
  are paired by Mode S address and solved **jointly** with one cubic B-spline trajectory per
  target (knots every ``knot_s``) — interpolating another radar's plots instead would cost
  ``a T²/8`` (≈ 140 m for a 3°/s turn between 12 s plots), ten times the biases sought. The
  unknowns are all radars' biases and all targets' spline coefficients, one sparse system
  (normal equations, solved by the Schur complement of the trajectory block:
  :func:`_solve_bordered`) per Gauss–Newton iteration; a weak acceleration prior
  (σ = ``accel_sigma_mps2``) keeps spans seen by one radar only well posed. A common clock
  offset of every radar moves the whole picture in time and is not observable without a
  reference: it is fixed by Σ_r δ_r = 0 (only the differences are estimated).

Uncertainties (both): σ² = diag of (Jᵀ W J)⁻¹ restricted to the bias block, scaled by the
residual variance factor ŝ² = rᵀ W r / (m − n) (W from the radars' nominal σ). Residuals beyond
``gate`` ŝσ (garbled Mode C codes, clutter paired by a wrong address) are left out and the
solution recomputed.

Bias steps (:func:`detect_steps`): per radar and channel, the time-ordered innovations; the
mean of the last ``window`` against the mean of the ``window`` before them,
z = Δmean / (σ̂ √(2/window)) (σ̂ robust, from first differences); an alarm when |z| > ``z_alarm``.
The test is blind to a constant bias (it compares means), so it needs no bias estimate;
vectorised with cumulative sums. Against a reference the innovations are the residuals. Radar
to radar the joint fit's own residuals are no good: a step in radar A is shared out between
A's bias, the trajectories and the other radars (on terminal-area a 60 m step moves A's fit
residuals by ~25 m and every other radar's by −20…−40 m). So each radar's plots are compared
with the trajectory re-solved from the OTHER radars alone (biases held at the joint estimate,
one linear step: :func:`_leave_one_out`), only where their plots bracket it within
``bracket_s``: a step in A then shows whole in A's innovations; B, whose comparison
trajectory contains A, sees a diluted copy, and :func:`detect_steps` keeps the strongest alarm
of one event (``isolate``). Measured (terminal-area, 40 aircraft, 20 min, 60 m range step,
window 60, 5 seeds × TMA-N/TMA-S): 10/10 detected on the right radar, delay 9.9–20.2 s
after the step (against the reference: 3.5–6.7 s), no alarm in the 10 runs without a step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import polars as pl
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.core.errors import DataError, OptionError
from tertiary.sensors import mlat

F64 = NDArray[np.float64]

#: columns of the registration table (``registration.parquet``), in this order
TABLE_COLUMNS = ["radar_id", "name", "range_bias_m", "range_bias_sigma_m", "azimuth_bias_deg",
                 "azimuth_bias_sigma_deg", "time_offset_s", "time_offset_sigma_s", "range_gain",
                 "range_gain_sigma", "method", "n_reports", "residual_scale"]


@dataclass(frozen=True)
class RegistrationConfig:
    """Options of :func:`estimate`.

    * ``method``: "reference" (needs truth/ADS-B positions), "multi" (radar to radar), or
      "auto" (reference when a reference trajectory is present, else multi).
    * ``gain``: also estimate a range gain g_r (R1). Identifiable only with ranges spread
      widely per radar; it then correlates with b_r (the table gives its σ).
    * ``knot_s``: B-spline knot spacing of the per-target trajectories (multi).
    * ``accel_sigma_mps2``: the weak acceleration prior of those trajectories.
    * ``altitude_sigma_m``: accuracy of a Mode C/S altitude (25/100 ft quantisation).
    * ``gate``: residuals beyond this many scaled sigmas are left out.
    * ``iterations``: Gauss–Newton iterations.
    * ``bracket_s``: (multi) a plot gets an innovation against the other radars' trajectory
      only where those radars have plots of the target at most this long before and after it.
    """

    method: Literal["auto", "reference", "multi"] = "auto"
    gain: bool = False
    knot_s: float = 8.0
    accel_sigma_mps2: float = 3.0
    altitude_sigma_m: float = 8.0
    gate: float = 5.0
    iterations: int = 6
    max_ref_gap_s: float = 2.5
    bracket_s: float = 15.0


@dataclass
class Registration:
    """Result of :func:`estimate`: the table (one row per radar) and the per-report residuals
    (``radar_id``, ``t_s`` seconds since ``t0_us``, ``res_range_m``, ``res_azimuth_deg`` of the
    fit, ``innov_range_m``, ``innov_azimuth_deg`` against a trajectory that owes nothing to the
    report's radar — the reference, or radar to radar the other radars' joint trajectory, NaN
    where they do not bracket the plot — ``sigma_range_m``, ``sigma_azimuth_deg``, ``used``)
    for step detection."""

    table: pl.DataFrame
    residuals: pl.DataFrame
    t0_us: int
    notes: list[str]


# --------------------------------------------------------------------------- geometry


@dataclass
class _Sites:
    """Per radar: rotation system→site (R, 3, 3), site offset (R, 3), nominal sigmas."""

    ids: NDArray[np.int64]
    names: list[str]
    rot: F64
    off: F64
    sig_r: F64
    sig_a: F64          # rad


def _sites(radars: pl.DataFrame, origin: geo.LocalFrame) -> _Sites:
    need = ["radar_id", "lat_deg", "lon_deg", "alt_m", "sigma_range_m", "sigma_azimuth_deg"]
    missing = [c for c in need if c not in radars.columns]
    if missing:
        raise DataError(f"radars: column(s) {', '.join(missing)} needed for registration")
    frames = [geo.LocalFrame(r["lat_deg"], r["lon_deg"], r["alt_m"]) for r in radars.iter_rows(named=True)]
    names = radars["name"].to_list() if "name" in radars.columns else [str(i) for i in radars["radar_id"]]
    return _Sites(ids=radars["radar_id"].to_numpy().astype(np.int64), names=[str(n) for n in names],
                  rot=np.stack([origin.rotation_to(f) for f in frames]),
                  off=np.stack([origin.offset_in(f) for f in frames]),
                  sig_r=radars["sigma_range_m"].to_numpy().astype(float),
                  sig_a=np.radians(radars["sigma_azimuth_deg"].to_numpy().astype(float)))


def polar_and_gradients(p: F64, v: F64, ri: NDArray[np.int64], sites: _Sites
                        ) -> tuple[F64, F64, F64, F64, F64, F64]:
    """Range ρ, azimuth β (rad) of system-frame positions ``p`` (n, 3) seen by radar index
    ``ri``, their gradients ∇ρ, ∇β w.r.t. ``p`` (n, 3, system frame) and the rates ρ̇ = ∇ρ·v,
    β̇ = ∇β·v."""
    rot = sites.rot[ri]
    q = np.einsum("nij,nj->ni", rot, p) + sites.off[ri]
    e, n, u = q[:, 0], q[:, 1], q[:, 2]
    h2 = np.maximum(e * e + n * n, 1e-6)
    rho = np.sqrt(h2 + u * u)
    beta = np.arctan2(e, n)
    d_rho = np.einsum("ni,nij->nj", q / rho[:, None], rot)              # (q/ρ)ᵀ M
    d_beta = np.einsum("ni,nij->nj", np.stack([n / h2, -e / h2, np.zeros_like(e)], 1), rot)
    return rho, beta, d_rho, d_beta, np.einsum("ni,ni->n", d_rho, v), np.einsum("ni,ni->n", d_beta, v)


def _wrap(x: F64) -> F64:
    return np.mod(x + np.pi, 2 * np.pi) - np.pi


# --------------------------------------------------------------------------- inputs


@dataclass
class _Obs:
    """Reports usable for registration (float seconds since ``t0_us``)."""

    ri: NDArray[np.int64]          # radar index into _Sites
    t: F64
    rng: F64
    az: F64                        # rad
    alt: F64                       # NaN without altitude
    run: NDArray[np.int64]
    key: NDArray[np.int64]         # target key (truth id or Mode S rank), -1 none


def _observations(reports: pl.DataFrame, sites: _Sites, key: str) -> tuple[_Obs, int]:
    need = ["radar_id", "time", "range_m", "azimuth_deg"]
    missing = [c for c in need + [key] if c not in reports.columns]
    if missing:
        raise DataError(f"reports: column(s) {', '.join(missing)} needed for registration")
    df = reports.filter(pl.col(key).is_not_null() & pl.col("range_m").is_finite()
                        & pl.col("azimuth_deg").is_finite() & pl.col("radar_id").is_in(list(sites.ids)))
    us = df["time"].dt.epoch("us").to_numpy()
    t0 = int(us.min()) if len(us) else 0
    lookup = np.full(int(sites.ids.max()) + 1, -1, np.int64)
    lookup[sites.ids] = np.arange(len(sites.ids))
    col = df[key]
    keys = (col.cast(pl.Int64).to_numpy() if col.dtype.is_integer()
            else col.cast(pl.String).rank("dense").cast(pl.Int64).to_numpy())
    alt = (df["altitude_m"].cast(pl.Float64).fill_null(np.nan).to_numpy() if "altitude_m" in df.columns
           else np.full(df.height, np.nan))
    run = df["run"].cast(pl.Int64).to_numpy() if "run" in df.columns else np.zeros(df.height, np.int64)
    return _Obs(ri=lookup[df["radar_id"].to_numpy().astype(np.int64)], t=(us - t0) * 1e-6,
                rng=df["range_m"].to_numpy().astype(float), az=np.radians(df["azimuth_deg"].to_numpy().astype(float)),
                alt=alt, run=run, key=keys), t0


def _empty_table() -> pl.DataFrame:
    return pl.DataFrame(schema={c: (pl.UInt32 if c == "radar_id" else pl.Int64 if c == "n_reports" else
                                    pl.String if c in ("name", "method") else pl.Float64) for c in TABLE_COLUMNS})


def _table(sites: _Sites, x: F64, cov: F64, gain: bool, method: str, n: NDArray[np.int64], scale: F64
           ) -> pl.DataFrame:
    k = 4 if gain else 3
    xb = x.reshape(-1, k)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0)).reshape(-1, k)
    nan = np.full(len(sites.ids), np.nan)
    return pl.DataFrame({
        "radar_id": pl.Series(sites.ids, dtype=pl.UInt32), "name": sites.names,
        "range_bias_m": xb[:, 0], "range_bias_sigma_m": sd[:, 0],
        "azimuth_bias_deg": np.degrees(xb[:, 1]), "azimuth_bias_sigma_deg": np.degrees(sd[:, 1]),
        "time_offset_s": xb[:, 2], "time_offset_sigma_s": sd[:, 2],
        "range_gain": xb[:, 3] if gain else nan, "range_gain_sigma": sd[:, 3] if gain else nan,
        "method": method, "n_reports": pl.Series(n, dtype=pl.Int64), "residual_scale": scale,
    }).select(TABLE_COLUMNS)


# --------------------------------------------------------------------------- reference


def hermite(t_query: F64, key_query: NDArray[np.int64], t: F64, key: NDArray[np.int64], pos: F64, vel: F64,
            max_gap_s: float) -> tuple[F64, F64, NDArray[np.bool_]]:
    """Position and velocity of reference trajectories (samples ``t``, ``key``, ``pos``,
    ``vel``; any order) at (``key_query``, ``t_query``): cubic Hermite between the bracketing
    samples of the same key (the simulator's own interpolation), valid when both exist and lie
    at most ``max_gap_s`` apart."""
    order = np.lexsort((t, key))
    t, key, pos, vel = t[order], key[order], pos[order], vel[order]
    span = float(max(np.ptp(t), np.ptp(t_query) if len(t_query) else 0.0)) + 10.0
    lo = float(min(t.min(), t_query.min() if len(t_query) else 0.0))
    kr, kq = np.unique(key, return_inverse=True)
    pos_q = np.searchsorted(kr, key_query)
    known = (pos_q < len(kr)) & (kr[np.minimum(pos_q, len(kr) - 1)] == key_query)
    comp = kq.reshape(-1) * span + (t - lo)
    cq = np.where(known, pos_q, -1) * span + (t_query - lo)
    j = np.clip(np.searchsorted(comp, cq, side="right") - 1, 0, len(t) - 2)
    ok = known & (key[j] == key_query) & (key[j + 1] == key_query) & (t[j] <= t_query) & (t_query <= t[j + 1])
    dt = np.maximum(t[j + 1] - t[j], 1e-9)
    ok &= dt <= max_gap_s
    s = ((t_query - t[j]) / dt)[:, None]
    p0, p1, v0, v1 = pos[j], pos[j + 1], vel[j] * dt[:, None], vel[j + 1] * dt[:, None]
    s2, s3 = s * s, s * s * s
    p = (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * v0 + (-2 * s3 + 3 * s2) * p1 + (s3 - s2) * v1
    v = ((6 * s2 - 6 * s) * p0 + (3 * s2 - 4 * s + 1) * v0 + (-6 * s2 + 6 * s) * p1 + (3 * s2 - 2 * s) * v1) / dt[:, None]
    return p, v, ok


def _bias_columns(ri: NDArray[np.int64], rho: F64, rho_dot: F64, beta_dot: F64, gain: bool, n_radars: int
                  ) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Sparse design rows of (L1) and (L2) in the bias unknowns (b, a, δ[, g]) per radar."""
    k = 4 if gain else 3
    n = len(ri)
    base = ri * k
    rows = np.arange(n)
    cols_r = [base, base + 2] + ([base + 3] if gain else [])
    vals_r = [np.ones(n), -rho_dot] + ([rho] if gain else [])
    a_r = sp.csr_matrix((np.concatenate(vals_r), (np.tile(rows, len(cols_r)), np.concatenate(cols_r))),
                        shape=(n, n_radars * k))
    a_b = sp.csr_matrix((np.concatenate([np.ones(n), -beta_dot]), (np.tile(rows, 2), np.concatenate([base + 1, base + 2]))),
                        shape=(n, n_radars * k))
    return a_r, a_b


def _reference(obs: _Obs, sites: _Sites, truth: pl.DataFrame, key_truth: NDArray[np.int64], t0_us: int,
               cfg: RegistrationConfig) -> tuple[F64, F64, F64, NDArray[np.bool_], F64, F64]:
    """(x, cov, scale per radar, used, range residuals, azimuth residuals) against the reference."""
    tt = (truth["time"].dt.epoch("us").to_numpy() - t0_us) * 1e-6
    pos = truth.select("x_m", "y_m", "z_m").to_numpy().astype(float)
    vel = truth.select("vx_mps", "vy_mps", "vz_mps").to_numpy().astype(float)
    nr, k = len(sites.ids), (4 if cfg.gain else 3)
    x = np.zeros(nr * k)
    used = np.ones(len(obs.t), bool)
    for it in range(cfg.iterations):
        delta = x.reshape(nr, k)[:, 2][obs.ri]
        p, v, ok = hermite(obs.t - delta, obs.key, tt, key_truth, pos, vel, cfg.max_ref_gap_s)
        rho, beta, _, _, rdot, bdot = polar_and_gradients(np.nan_to_num(p), np.nan_to_num(v), obs.ri, sites)
        xb = x.reshape(nr, k)
        gain = xb[:, 3][obs.ri] if cfg.gain else 0.0
        e_r = obs.rng - ((1 + gain) * rho + xb[:, 0][obs.ri])
        e_b = _wrap(obs.az - beta - xb[:, 1][obs.ri])
        if it == 0:
            used = ok
        a_r, a_b = _bias_columns(obs.ri, rho, (1 + gain) * rdot, bdot, cfg.gain, nr)
        w_r, w_b = 1.0 / sites.sig_r[obs.ri], 1.0 / sites.sig_a[obs.ri]
        if it >= 2:   # gate on the residuals of a converged-enough fit
            scale = _scale_per_radar(obs.ri, e_r * w_r, e_b * w_b, used, nr, k)
            used = ok & (np.abs(e_r * w_r) < cfg.gate * scale[obs.ri]) & (np.abs(e_b * w_b) < cfg.gate * scale[obs.ri])
        m = used.astype(float)
        a = sp.vstack([sp.diags(w_r * m) @ a_r, sp.diags(w_b * m) @ a_b]).tocsr()
        rhs = np.concatenate([e_r * w_r * m, e_b * w_b * m])
        n_mat = (a.T @ a).toarray()
        dx = np.linalg.lstsq(n_mat, a.T @ rhs, rcond=None)[0]
        x = x + dx
        if np.max(np.abs(dx)) < 1e-12:
            break
    scale = _scale_per_radar(obs.ri, e_r * w_r, e_b * w_b, used, nr, k)
    cov = np.linalg.pinv(n_mat)
    s2 = np.repeat(scale ** 2, k)
    return x, cov * np.sqrt(s2)[:, None] * np.sqrt(s2)[None, :], scale, used, e_r, e_b


def _scale_per_radar(ri, zr, zb, used, nr, k) -> F64:
    """√(rᵀWr / (m − n)) per radar (ŝ of the residual variance factor), ≥ a tiny floor."""
    ss = np.bincount(ri[used], weights=(zr * zr + zb * zb)[used], minlength=nr)
    m = 2 * np.bincount(ri[used], minlength=nr)
    return np.sqrt(np.where(m > k, ss / np.maximum(m - k, 1), 1.0)) + 1e-15


# --------------------------------------------------------------------------- multi-radar


def _bspline(u: F64) -> tuple[F64, F64]:
    """Uniform cubic B-spline basis (n, 4) and its derivative w.r.t. u at fractions ``u``."""
    s = u[:, None]
    b = np.hstack([(1 - s) ** 3, 3 * s ** 3 - 6 * s ** 2 + 4, -3 * s ** 3 + 3 * s ** 2 + 3 * s + 1, s ** 3]) / 6.0
    d = np.hstack([-3 * (1 - s) ** 2, 9 * s ** 2 - 12 * s, -9 * s ** 2 + 6 * s + 3, 3 * s ** 2]) / 6.0
    return b, d


@dataclass
class _Splines:
    """Per target: first time, coefficient offset, count; per observation: target index."""

    tgt: NDArray[np.int64]
    t_first: F64
    offset: NDArray[np.int64]
    count: NDArray[np.int64]
    h: float

    def locate(self, t: F64) -> tuple[NDArray[np.int64], F64, F64]:
        """First coefficient index (global), basis and its time derivative for each observation."""
        u = (t - self.t_first[self.tgt]) / self.h
        i = np.clip(np.floor(u).astype(np.int64), 0, self.count[self.tgt] - 4)
        b, d = _bspline(u - i)
        return self.offset[self.tgt] + i, b, d / self.h


def _spline_rows(first: NDArray[np.int64], basis: F64, col0: int) -> tuple[NDArray[np.int64], F64]:
    """Column indices (n, 3, 4) and values of p = Σ B_j c_{i+j} per axis (coefficients are
    stored (index, axis) so column = col0 + 3·index + axis)."""
    idx = first[:, None] + np.arange(4)[None, :]
    cols = col0 + 3 * idx[:, None, :] + np.arange(3)[None, :, None]
    return cols, np.broadcast_to(basis[:, None, :], cols.shape)


def _multi(obs: _Obs, sites: _Sites, origin: geo.LocalFrame, cfg: RegistrationConfig
           ) -> tuple[F64, F64, F64, NDArray[np.bool_], F64, F64, NDArray[np.int64], F64, F64]:
    """Joint LS of all radars' biases and per-target B-spline trajectories (see module doc)."""
    nr, k = len(sites.ids), (4 if cfg.gain else 3)
    # targets = (run, key) seen by at least two radars
    tk = np.stack([obs.run, obs.key], 1)
    uniq, tgt = np.unique(tk, axis=0, return_inverse=True)
    tgt = tgt.reshape(-1)
    radars_per = np.zeros((len(uniq), nr), bool)
    radars_per[tgt, obs.ri] = True
    keep = radars_per.sum(1)[tgt] >= 2
    obs = _Obs(*(getattr(obs, f)[keep] for f in obs.__dataclass_fields__))
    _, tgt = np.unique(tgt[keep], return_inverse=True)
    tgt = tgt.reshape(-1)
    nt = int(tgt.max()) + 1 if len(tgt) else 0
    if nt == 0:
        raise DataError("registration: no aircraft (Mode S address) is seen by two radars; nothing to register")
    t_first = np.full(nt, np.inf)
    np.minimum.at(t_first, tgt, obs.t)
    t_last = np.full(nt, -np.inf)
    np.maximum.at(t_last, tgt, obs.t)
    t_first -= 1.0                       # room for the clock offsets
    count = np.floor((t_last + 1.0 - t_first) / cfg.knot_s).astype(np.int64) + 4
    offset = np.concatenate([[0], np.cumsum(count)[:-1]])
    spl = _Splines(tgt, t_first, offset, count, cfg.knot_s)
    nb, nc = nr * k, 3 * int(count.sum())
    n_unk = nb + nc

    coef = _initial_trajectories(obs, sites, origin, spl, nc)
    x = np.zeros(nb)
    prior, prior_rhs = _acceleration_prior(spl, nb, n_unk, cfg)
    used = np.isfinite(obs.rng)
    has_alt = np.isfinite(obs.alt)
    ecef_c = np.array([0.0, 0.0, -(geo.EARTH_RADIUS_M + origin.alt_m)])
    for it in range(cfg.iterations):
        xb = x.reshape(nr, k)
        first, basis, dbasis = spl.locate(obs.t - xb[:, 2][obs.ri])
        cols, vals = _spline_rows(first, basis, nb)
        c3 = coef.reshape(-1, 3)
        idx = first[:, None] + np.arange(4)
        p = np.einsum("nj,nja->na", basis, c3[idx])
        v = np.einsum("nj,nja->na", dbasis, c3[idx])
        rho, beta, d_rho, d_beta, rdot, bdot = polar_and_gradients(p, v, obs.ri, sites)
        gain = xb[:, 3][obs.ri] if cfg.gain else 0.0
        e_r = obs.rng - ((1 + gain) * rho + xb[:, 0][obs.ri])
        e_b = _wrap(obs.az - beta - xb[:, 1][obs.ri])
        h_now = origin.to_geodetic(*p.T)[2]
        e_h = np.where(has_alt, obs.alt - h_now, 0.0)
        up = p - ecef_c
        d_h = up / np.linalg.norm(up, axis=1, keepdims=True)
        w_r, w_b, w_h = 1.0 / sites.sig_r[obs.ri], 1.0 / sites.sig_a[obs.ri], 1.0 / cfg.altitude_sigma_m
        if it >= 2:
            s = _scale_per_radar(obs.ri, e_r * w_r, e_b * w_b, used, nr, k)
            used = (np.abs(e_r * w_r) < cfg.gate * s[obs.ri]) & (np.abs(e_b * w_b) < cfg.gate * s[obs.ri])
            has_alt = np.isfinite(obs.alt) & (np.abs(e_h * w_h) < cfg.gate * max(float(np.median(s)), 1.0) * 2)
        elif it == 1:       # gross errors only (garbled altitude codes) before the biases settle
            has_alt = np.isfinite(obs.alt) & (np.abs(e_h) < 500.0)
        a_r, a_b = _bias_columns(obs.ri, rho, (1 + gain) * rdot, bdot, cfg.gain, nr)
        j_r = _traj_block(a_r, cols, vals, (1 + gain)[..., None] * d_rho if cfg.gain else d_rho, n_unk)
        j_b = _traj_block(a_b, cols, vals, d_beta, n_unk)
        j_h = _traj_block(sp.csr_matrix((len(obs.t), nb)), cols, vals, d_h, n_unk)
        # the clock offset also moves the altitude sample: ∂h/∂δ = −∇h·v
        j_h = j_h + sp.csr_matrix((-np.einsum("ni,ni->n", d_h, v), (np.arange(len(obs.t)), obs.ri * k + 2)),
                                  shape=j_h.shape)
        m_rb, m_h = used.astype(float), (has_alt & used).astype(float)
        a = sp.vstack([sp.diags(w_r * m_rb) @ j_r, sp.diags(w_b * m_rb) @ j_b, sp.diags(w_h * m_h) @ j_h,
                       prior, _gauge(nr, k, n_unk)]).tocsr()
        theta = np.concatenate([x, coef])
        rhs = np.concatenate([e_r * w_r * m_rb, e_b * w_b * m_rb, e_h * w_h * m_h, prior_rhs - prior @ theta,
                              -_gauge(nr, k, n_unk) @ theta])
        dtheta, s_inv = _solve_bordered((a.T @ a).tocsr(), a.T @ rhs, nb)
        x, coef = x + dtheta[:nb], coef + dtheta[nb:]
        if np.max(np.abs(dtheta[:nb])) < 1e-10:
            break
    n_obs = int(2 * used.sum() + (has_alt & used).sum())
    s2 = float(rhs @ rhs - rhs @ (a @ dtheta)) / max(n_obs - n_unk + prior.shape[0], 1)
    cov = s_inv * s2
    scale = _scale_per_radar(obs.ri, e_r * w_r, e_b * w_b, used, nr, k)
    # residuals at the final estimate (linear in the last, ~0, update), then the innovations
    e_fin = [e - jm @ dtheta for e, jm in ((e_r, j_r), (e_b, j_b), (e_h, j_h))]
    n = len(obs.t)
    lin = _Linearised(spl=spl, jac=[jm[:, nb:].tocsr() for jm in (j_r, j_b, j_h)], res=e_fin,
                      w=[w_r, w_b, np.full(n, w_h)], rows=[used, used, has_alt & used], prior=prior[:, nb:].tocsr(),
                      prior_res=prior_rhs - prior @ np.concatenate([x, coef]))
    i_r, i_b = _leave_one_out(obs.ri, obs.t, lin, nr, cfg.bracket_s)
    keep_idx = np.flatnonzero(keep)
    return x, cov, scale, used, e_fin[0], e_fin[1], keep_idx, i_r, i_b


def _solve_bordered(normal: sp.csr_matrix, g: F64, nb: int) -> tuple[F64, F64]:
    """Solve the normal equations [[B, C], [Cᵀ, D]] θ = g of the joint problem by the Schur
    complement of D, and return θ and S⁻¹ = (B − C D⁻¹ Cᵀ)⁻¹, the bias block of the inverse.

    Every plot couples its radar's few bias columns to its aircraft's spline coefficients, so
    the normal matrix is block diagonal in the aircraft (D, each block banded) bordered by nb
    dense bias rows and columns. A sparse LU of the whole matrix does not keep those dense
    columns last and fills in; D alone factors without fill, and the border is a dense nb × nb
    system."""
    b = normal[:nb, :nb].toarray()
    c = normal[:nb, nb:]
    lu_d = spla.splu(normal[nb:, nb:].tocsc())
    y = lu_d.solve(np.ascontiguousarray(c.T.toarray()))          # D⁻¹ Cᵀ, (nc, nb)
    s_inv = np.linalg.inv(b - c @ y)
    s_inv = 0.5 * (s_inv + s_inv.T)
    d_inv_gc = lu_d.solve(g[nb:])
    db = s_inv @ (g[:nb] - c @ d_inv_gc)
    dc = d_inv_gc - y @ db
    return np.concatenate([db, dc]), s_inv


@dataclass
class _Linearised:
    """The joint problem linearised at the final estimate, trajectory columns only: per
    channel (range, azimuth, altitude) the Jacobian in the spline coefficients, the residual,
    the weight and the rows in use; the acceleration prior's rows and residual."""

    spl: _Splines
    jac: list[sp.csr_matrix]
    res: list[F64]
    w: list[F64]
    rows: list[NDArray[np.bool_]]
    prior: sp.csr_matrix
    prior_res: F64


def _bracketed(tgt: NDArray[np.int64], t: F64, other: NDArray[np.bool_], gap_s: float) -> NDArray[np.bool_]:
    """True where a plot (``tgt``, ``t``) has a plot of ``other`` (same target) at most
    ``gap_s`` before it and one at most ``gap_s`` after it: the other radars' trajectory is
    interpolated there, not extrapolated by the prior."""
    if not other.any():
        return np.zeros(len(t), bool)
    span = float(np.ptp(t)) + 4 * gap_s + 1.0
    key = tgt * span + (t - t.min())
    ref = np.sort(key[other])
    j = np.searchsorted(ref, key, side="right")
    prev = ref[np.maximum(j - 1, 0)]
    nxt = ref[np.minimum(j, len(ref) - 1)]
    return (j > 0) & (key - prev <= gap_s) & (j < len(ref)) & (nxt - key <= gap_s) & (key - prev >= 0)


def _leave_one_out(ri: NDArray[np.int64], t: F64, lin: _Linearised, nr: int, gap_s: float) -> tuple[F64, F64]:
    """Innovations of each radar's plots against the trajectories of the OTHER radars alone.

    For radar r the spline coefficients are re-solved (one linear step, biases held at the
    joint estimate) from the other radars' rows and the prior: Δc_r = argmin Σ_{i∉r} w_i²(e_i −
    J_i Δc)² + ‖p − P Δc‖²; the innovation of a plot of r is e_i − J_i Δc_r. A step in radar
    r's bias is then seen whole in its innovations (the joint fit would absorb part of it into
    the trajectories and spread the rest over the other radars). NaN where r's plot is not
    bracketed by other radars' plots within ``gap_s`` (module doc, Bias steps)."""
    out = [np.full(len(t), np.nan), np.full(len(t), np.nan)]
    n_c = lin.prior.shape[1]
    ridge = sp.identity(n_c, format="csr") * 1e-9
    for r in range(nr):                       # one sparse solve per radar
        mine = ri == r
        other_rows = [rows & ~mine for rows in lin.rows]
        ok = mine & lin.rows[0] & _bracketed(lin.spl.tgt, t, other_rows[0], gap_s)
        if not ok.any():
            continue
        a = sp.vstack([sp.diags(w * m) @ j for j, w, m in zip(lin.jac, lin.w, other_rows)] + [lin.prior]).tocsr()
        rhs = np.concatenate([r_ * w * m for r_, w, m in zip(lin.res, lin.w, other_rows)] + [lin.prior_res])
        dc = spla.splu((a.T @ a + ridge).tocsc()).solve(a.T @ rhs)
        for ch in (0, 1):
            out[ch][ok] = (lin.res[ch] - lin.jac[ch] @ dc)[ok]
    return out[0], out[1]


def _traj_block(a_bias: sp.csr_matrix, cols: NDArray[np.int64], vals: F64, grad: F64, n_unk: int) -> sp.csr_matrix:
    """Rows of a Jacobian: the bias part plus ∇f·∂p/∂c (grad (n, 3) times the B-spline basis)."""
    n = len(grad)
    data = (vals * grad[:, :, None]).reshape(n, -1)
    rows = np.repeat(np.arange(n), 12)
    traj = sp.csr_matrix((data.reshape(-1), (rows, cols.reshape(-1))), shape=(n, n_unk))
    bias = sp.csr_matrix((a_bias.data, a_bias.indices, a_bias.indptr), shape=(n, a_bias.shape[1]))
    return sp.hstack([bias, sp.csr_matrix((n, n_unk - a_bias.shape[1]))]).tocsr() + traj


def _gauge(nr: int, k: int, n_unk: int) -> sp.csr_matrix:
    """Σ_r δ_r = 0 with weight 10⁴ s⁻¹: a common clock offset is not observable radar to radar."""
    return sp.csr_matrix((np.full(nr, 1e4), (np.zeros(nr, np.int64), np.arange(nr) * k + 2)), shape=(1, n_unk))


def _acceleration_prior(spl: _Splines, nb: int, n_unk: int, cfg: RegistrationConfig
                        ) -> tuple[sp.csr_matrix, F64]:
    """Rows (c_{i−1} − 2c_i + c_{i+1}) / (h² σ_a) = 0 per target, interior index and axis."""
    tgt_of = np.repeat(np.arange(len(spl.count)), spl.count - 2)
    within = np.arange(len(tgt_of)) - np.repeat(np.cumsum(spl.count - 2) - (spl.count - 2), spl.count - 2)
    centre = spl.offset[tgt_of] + within + 1
    m = len(centre)
    rows = np.repeat(np.arange(3 * m), 3)
    idx = np.stack([centre - 1, centre, centre + 1], 1)                          # (m, 3)
    cols = nb + 3 * idx[:, None, :] + np.arange(3)[None, :, None]               # (m, axis, 3)
    w = 1.0 / (spl.h ** 2 * cfg.accel_sigma_mps2)
    vals = np.broadcast_to(np.array([w, -2 * w, w]), cols.shape)
    return sp.csr_matrix((vals.reshape(-1), (rows, cols.reshape(-1))), shape=(3 * m, n_unk)), np.zeros(3 * m)


def _initial_trajectories(obs: _Obs, sites: _Sites, origin: geo.LocalFrame, spl: _Splines, nc: int) -> F64:
    """Spline coefficients fitted (linear LS) to the plots converted to the system frame, the
    elevation taken from the altitude (geometric, spherical Earth) or else 1°."""
    site_alt = np.array([origin.to_geodetic(*(-sites.rot[i].T @ sites.off[i]))[2] for i in range(len(sites.ids))])
    el = geo.elevation_from_altitude(obs.rng, np.nan_to_num(obs.alt, nan=3000.0), site_alt[obs.ri],
                                     earth_radius_m=geo.EARTH_RADIUS_M)
    local = np.stack(geo.polar_to_enu(obs.rng, np.degrees(obs.az), el), 1) - sites.off[obs.ri]
    p = np.einsum("nji,nj->ni", sites.rot[obs.ri], local)                         # Mᵀ (q − o)
    first, basis, _ = spl.locate(obs.t)
    cols, vals = _spline_rows(first, basis, 0)
    n = len(p)
    a = sp.csr_matrix((vals.reshape(-1), (np.repeat(np.arange(3 * n), 4), cols.transpose(0, 1, 2).reshape(-1))),
                      shape=(3 * n, nc))
    reg = sp.identity(nc, format="csr") * 1e-6
    normal = (a.T @ a + reg).tocsc()
    return spla.splu(normal).solve(a.T @ p.reshape(-1))


# --------------------------------------------------------------------------- public


def _reference_keys(reports: pl.DataFrame, truth: pl.DataFrame) -> tuple[str, NDArray[np.int64]] | None:
    """How reports meet the reference: ``truth_id`` (simulation) or Mode S ↔ ``icao24``."""
    cols = {"time", "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"}
    if truth is None or truth.height == 0 or not cols <= set(truth.columns):
        return None
    if "truth_id" in reports.columns and "truth_id" in truth.columns:
        return "truth_id", truth["truth_id"].cast(pl.Int64).to_numpy()
    return None


def estimate(reports: pl.DataFrame, radars: pl.DataFrame, origin: geo.LocalFrame,
             truth: pl.DataFrame | None = None, cfg: RegistrationConfig = RegistrationConfig()) -> Registration:
    """Each radar's range bias, azimuth bias and clock offset (and range gain with
    ``cfg.gain``) with 1σ uncertainties; see the module docstring for the model. MLAT sensors
    (:mod:`tertiary.sensors.mlat`) measure no range or azimuth: they and their reports are left
    out (no row in the table: alignment leaves them as they are)."""
    if mlat.mlat_ids(radars).size:
        reports = reports.filter(~pl.Series(mlat.is_mlat(reports, radars)))
        radars = radars.filter(~pl.col("radar_id").cast(pl.Int64).is_in(mlat.mlat_ids(radars).tolist()))
    if cfg.method not in ("auto", "reference", "multi"):
        raise OptionError(f"choose auto, reference or multi, got {cfg.method!r}", option="registration.method")
    if not (cfg.knot_s > 0 and cfg.accel_sigma_mps2 > 0 and cfg.gate > 0 and cfg.iterations >= 1):
        raise OptionError("knot_s, accel_sigma_mps2 and gate must be > 0, iterations >= 1", option="registration")
    sites = _sites(radars, origin)
    ref = _reference_keys(reports, truth) if cfg.method != "multi" else None
    if cfg.method == "reference" and ref is None:
        raise DataError("registration: method 'reference' needs truth (time, x_m … vz_mps, truth_id) "
                        "matching the reports' truth_id")
    notes: list[str] = []
    if ref is not None:
        obs, t0 = _observations(reports, sites, ref[0])
        x, cov, scale, used, e_r, e_b = _reference(obs, sites, truth, ref[1], t0, cfg)
        method, sel = "reference", np.arange(len(obs.t))
        i_r, i_b = e_r, e_b                 # the reference is independent of every radar
    else:
        if "mode_s" not in reports.columns:
            raise DataError("registration: reports have no mode_s column (needed to pair radars) and no reference")
        obs, t0 = _observations(reports, sites, "mode_s")
        x, cov, scale, used, e_r, e_b, sel, i_r, i_b = _multi(obs, sites, origin, cfg)
        method = "multi"
        notes.append("radar-to-radar registration: clock offsets are relative (their sum is fixed at 0)")
    ri = obs.ri[sel]
    n = np.bincount(ri[used], minlength=len(sites.ids))
    table = _table(sites, x, cov, cfg.gain, method, n, scale)
    residuals = pl.DataFrame({
        "radar_id": pl.Series(sites.ids[ri], dtype=pl.UInt32), "t_s": obs.t[sel], "res_range_m": e_r,
        "res_azimuth_deg": np.degrees(e_b), "innov_range_m": i_r, "innov_azimuth_deg": np.degrees(i_b),
        "sigma_range_m": sites.sig_r[ri],
        "sigma_azimuth_deg": np.degrees(sites.sig_a[ri]), "used": used})
    return Registration(table, residuals.sort("radar_id", "t_s"), t0, notes)


def read_table(path) -> pl.DataFrame:
    """A stored registration table; unreadable or lacking the correction columns is a :class:`DataError`."""
    try:
        table = pl.read_parquet(path)
    except Exception as exc:  # polars, pyarrow and OS errors alike: the file is unusable
        raise DataError(f"not a readable registration table ({type(exc).__name__})", path=str(path)) from exc
    missing = [c for c in ("radar_id", "range_bias_m", "azimuth_bias_deg", "time_offset_s") if c not in table.columns]
    if missing:
        raise DataError(f"column(s) {', '.join(missing)} missing", path=str(path))
    return table


def detect_steps(residuals: pl.DataFrame, window: int = 60, z_alarm: float = 6.0, isolate: bool = True
                 ) -> pl.DataFrame:
    """Bias steps per radar and channel (windowed innovation-mean test, module doc).

    Tests the innovations (``innov_*``: against the reference, or radar to radar against the
    other radars' trajectory) when present, else the fit residuals (``res_*``). Returns one row
    per (radar, channel) that alarms: ``radar_id``, ``channel`` (range / azimuth),
    ``alarm_t_s`` (time of the first alarm, s since the registration t0), ``change_t_s`` (the
    window boundary where |z| peaks within ``window`` reports of the alarm: the step's
    estimated time), ``step`` (mean after − mean before there, m or deg) and ``z`` (the peak).

    Radar to radar a step in radar A also moves the trajectories B is compared with, so B may
    alarm too, more weakly. With ``isolate`` only the strongest alarm (largest |z| peak) of a
    channel is kept among alarms whose times lie within one test span (2 windows) of it."""
    schema = {"radar_id": pl.UInt32, "channel": pl.String, "alarm_t_s": pl.Float64, "change_t_s": pl.Float64,
              "step": pl.Float64, "z": pl.Float64, "span_s": pl.Float64}
    innov = "innov_range_m" in residuals.columns
    channels = (("range", "innov_range_m" if innov else "res_range_m"),
                ("azimuth", "innov_azimuth_deg" if innov else "res_azimuth_deg"))
    out = []
    df = residuals.filter(pl.col("used")).sort("radar_id", "t_s")
    for rid in df["radar_id"].unique(maintain_order=True).to_list():     # loop over radars only
        d = df.filter(pl.col("radar_id") == rid)
        for channel, col in channels:
            e = d[col].to_numpy()
            ok = np.isfinite(e)
            hit = _mean_shift(e[ok], d["t_s"].to_numpy()[ok], window, z_alarm)
            if hit is not None:
                out.append({"radar_id": rid, "channel": channel, **hit})
    found = pl.DataFrame(out, schema=schema)
    if isolate and found.height > 1:
        found = _isolate(found)
    return found.drop("span_s")


def _mean_shift(e: F64, t: F64, window: int, z_alarm: float) -> dict[str, float] | None:
    """First alarm of the two-window mean test on one time-ordered series (cumulative sums)."""
    if len(e) < 2 * window:
        return None
    c = np.concatenate([[0.0], np.cumsum(e)])
    after = (c[2 * window:] - c[window:-window]) / window              # mean of e[k−w+1..k]
    before = (c[window:-window] - c[:-2 * window]) / window          # mean of the w before
    # robust σ from first differences: blind to the step itself and to a constant bias
    diff = np.diff(e)
    spread = 1.4826 * float(np.median(np.abs(diff - np.median(diff)))) / np.sqrt(2.0)
    z = (after - before) / (max(spread, 1e-300) * np.sqrt(2.0 / window))
    hit = np.flatnonzero(np.abs(z) > z_alarm)
    if not hit.size:
        return None
    i = int(hit[0])
    j = i + int(np.argmax(np.abs(z[i:i + window + 1])))
    return {"alarm_t_s": float(t[i + 2 * window - 1]), "change_t_s": float(t[j + window]),
            "step": float(after[j] - before[j]), "z": float(z[j]), "span_s": float(t[i + 2 * window - 1] - t[i])}


def _isolate(found: pl.DataFrame) -> pl.DataFrame:
    """Keep, per channel, the alarms not within one test span of a stronger one."""
    rows = sorted(found.iter_rows(named=True), key=lambda r: -abs(r["z"]))      # a handful of alarms
    kept: list[dict] = []
    for r in rows:
        if not any(k["channel"] == r["channel"]
                   and abs(k["alarm_t_s"] - r["alarm_t_s"]) <= max(k["span_s"], r["span_s"]) for k in kept):
            kept.append(r)
    return pl.DataFrame(kept, schema=found.schema).sort("radar_id", "channel")
