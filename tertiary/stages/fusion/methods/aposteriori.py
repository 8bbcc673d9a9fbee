"""A-posteriori fusion: per-row weights from a recursion on the radars' innovations, carried along
each target's history, then the weighted mix (4.72) x = Σ b_n x_n, P = Σ b_n² C_n.

* ``aposteriori_seed`` — (4.72)–(4.77) **as printed**, N radars:
  b_n(k) = L_n(k)(1 − b_n(k−1)) / Σ_m L_m(k)(1 − b_m(k−1)),
  L_n = (2πD_n)^{-1/2} exp(−ΔD_n²/(2D_n)), ΔD_n = ``res_range_m``, D_n fixed per (run, radar,
  local track) = ``res_range_var_m2 − sigma_range_m²`` at the local track's first row with a
  finite innovation (the step-1 predicted variance without R, (4.75)–(4.76)), b_n(0) = 1/N
  (4.77). One weight per radar for all six coordinates; P = Σ b_n² C_n (the monograph fuses
  states only; this is the covariance of a fixed-weight mix of independent estimates). The
  printed prior (1 − b(k−1)) is Markov mixing with π_nn = 0: constant unequal likelihoods give
  a period-2 oscillation, which this method deliberately keeps.
* ``aposteriori`` — the corrected recursion (Markov mixing):
  c_n = Σ_m π_mn b_m(k−1), π_nn = ``p_stay``, π_mn = (1 − p_stay)/(N − 1);
  b_n ∝ N(ν_n; 0, S_n(k)) c_n with S_n(k) = ``res_range_var_m2``; floor ``b_min``, renormalise.
* ``aposteriori_seed_S`` (optional): the printed prior (1 − b(k−1)) of (4.73)–(4.74) with the
  per-step S_n(k) = ``res_range_var_m2`` instead of the fixed D_n.
* ``aposteriori_coord`` (optional) — per-coordinate weights b_{n,c}, c ∈ {x, y, z}, by the
  corrected recursion on N(ν_{n,c}; 0, S_{n,c}) (:func:`los_innovation`); velocity takes its
  position axis's weight.
* ``aposteriori_mv`` (optional) — one weight per radar from the multivariate N(ν_n; 0, S_n) of
  the same 3-D innovation, corrected recursion.

The rows carry only the range innovation ΔD_n and its variance S_n, so the 3-D innovation is
built from it (:func:`los_innovation`): ν_n = u_n ΔD_n along the line of sight u_n (radar site →
reported position, system frame), covariance S_n = a_n u_n u_nᵀ + diag(nominal_var_n),
a_n = max(S_n − σ²_range,n, 0) the predicted range variance without R, diag(nominal_var) the
plot noise per system axis (range and cross-range).

Rules shared by the recursions:

* the recursion state b(k−1) of a (run, target_id, radar_id) is its weight at the previous
  epoch at which the target was fused; when the target's radar set differs from that epoch's
  set (or the target is new) the recursion restarts from b(0) = 1/N for the current set;
* a row carries a usable innovation when it is ``fresh``, its ΔD is finite and its variance
  (D_n or S_n(k)) is finite and positive. Rows without one keep b(k−1); the radars with a
  usable innovation share the remaining mass 1 − Σ_{unusable} b_m(k−1) in proportion to
  L_n c_n (the usual update restricted to them);
* the update runs in the log domain (softmax); a target whose every log-term is −∞/NaN (all
  likelihoods or priors vanish) keeps b(k−1).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import polars as pl

from tertiary.stages.fusion.base import TRACK, B, F, Fused, Ix, Layout, keep_single, mix, track_keys
from tertiary.stages.fusion.methods.weighted import fuse_weighted
from tertiary.stages.fusion.registry import Block, FusionMethod, RunInputs, register

__all__ = [
    "LogPrior", "coord_loglik", "coord_weights", "first_innovation_var", "fuse_aposteriori", "fuse_aposteriori_seed",
    "fuse_axis_weighted", "los_innovation", "markov_weights", "mv_loglik", "mv_weights", "seed_fixed_variance",
    "seed_s_weights", "seed_weights",
]

LogPrior = Callable[[F, F], F]  # (b(k−1), N) per row -> log c_n(k)



def _log_prior_seed(b_prev: F, n: F) -> F:
    """log(1 − b_n(k−1)): the printed prior of (4.73)/(4.74)."""
    with np.errstate(divide="ignore"):
        return np.log1p(-b_prev)


def _log_prior_markov(p_stay: float) -> LogPrior:
    """log c_n = log(p b_n + (1 − p)/(N − 1) (1 − b_n))."""

    def log_prior(b_prev: F, n: F) -> F:
        q = (1.0 - p_stay) / np.maximum(n - 1.0, 1.0)
        with np.errstate(divide="ignore"):
            return np.log(p_stay * b_prev + q * (1.0 - b_prev))

    return log_prior


def _log_normal(nu: F, var: F) -> F:
    """log N(ν; 0, var) = −½ log(2π var) − ν²/(2 var) (the seed's L_n)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return -0.5 * np.log(2.0 * np.pi * var) - nu * nu / (2.0 * var)


def _usable(fresh: B, nu: F, var: F) -> B:
    """A new, finite innovation with a finite positive variance."""
    return fresh & np.isfinite(nu) & np.isfinite(var) & (var > 0)


def _bayes_step(prior: F, loglik: F, usable: B, n: F, starts: Ix, log_prior: LogPrior, b_min: float,
                gid: Ix | None = None) -> F:
    """One update of the weights of the rows of a set of groups (rows sorted by group).

    b_n ∝ L_n c_n over the usable rows, which share the mass Σ_usable b(k−1); other rows and
    groups without a finite log-term keep b(k−1); single-source groups get 1. ``gid``: the
    group (0 … G−1) of each row, derived from ``starts`` when not given."""
    if gid is None:
        gid = np.repeat(np.arange(len(starts)), np.diff(np.append(starts, len(prior))))
    t = np.where(usable, loglik + log_prior(prior, n), -np.inf)
    t = np.where(np.isnan(t), -np.inf, t)
    peak = np.maximum.reduceat(t, starts)[gid]
    ok = usable & np.isfinite(peak)
    with np.errstate(invalid="ignore"):
        e = np.exp(np.where(ok, t - peak, -np.inf))
    p = e / np.where(ok, np.add.reduceat(e, starts)[gid], 1.0)
    if b_min > 0:
        p = np.where(ok, np.maximum(p, b_min), 0.0)
        p = p / np.where(ok, np.add.reduceat(p, starts)[gid], 1.0)
    mass = np.add.reduceat(np.where(ok, prior, 0.0), starts)[gid]
    b = np.where(ok, mass * p, prior)
    return np.where(n == 1, 1.0, b)


def _recursive_weights(loglik: F, usable: B, lay: Layout, log_prior: LogPrior, b_min: float,
                       b0: F | None = None) -> F:
    """Run the recursion level by level (epoch rank along each target's history), on the rows
    permuted into level order so that every level is a contiguous slice. ``b0`` (n,), optional:
    the weight b(k−1) carried from the previous window for rows without an in-call
    predecessor (NaN: restart at 1/N)."""
    b = np.empty(len(loglik))
    if len(loglik) == 0:
        return b
    lv = lay.levels
    lik, use = loglik[lv.order], usable[lv.order]
    start = np.full(len(b), np.nan) if b0 is None else np.asarray(b0, float)[lv.order]
    bp = np.empty(len(b))                               # weights in level order
    for lo, hi in zip(lv.bounds[:-1], lv.bounds[1:]):
        gid = lv.gid[lo:hi] - lv.gid[lo]
        local = np.flatnonzero(lv.first[lo:hi])
        prev, n = lv.prev[lo:hi], lv.n[lo:hi]
        carried = start[lo:hi]
        prior = np.where(prev >= 0, bp[np.maximum(prev, 0)], np.where(np.isfinite(carried), carried, 1.0 / n))
        prior = prior / np.add.reduceat(prior, local)[gid]  # no rounding drift
        bp[lo:hi] = _bayes_step(prior, lik[lo:hi], use[lo:hi], n, local, log_prior, b_min, gid)
    b[lv.order] = bp
    return b


def seed_weights(res: F, d_fixed: F, fresh: B, lay: Layout, b0: F | None = None) -> F:
    """Printed a-posteriori weights (4.73)–(4.74), N radars, b(0) = 1/N (4.77)."""
    loglik = _log_normal(res, d_fixed)
    return _recursive_weights(loglik, _usable(fresh, res, d_fixed), lay, _log_prior_seed, 0.0, b0)


def markov_weights(res: F, res_var: F, fresh: B, lay: Layout, p_stay: float, b_min: float,
                   b0: F | None = None) -> F:
    """Corrected a-posteriori weights with per-step S_n(k) = ``res_var``."""
    loglik = _log_normal(res, res_var)
    usable = _usable(fresh, res, res_var)
    return _recursive_weights(loglik, usable, lay, _log_prior_markov(p_stay), b_min, b0)


def fuse_aposteriori_seed(x: F, cov: F, res: F, d_fixed: F, fresh: B, lay: Layout) -> Fused:
    """(4.72) with the weights of :func:`seed_weights` on every coordinate; P = Σ b_n² C_n."""
    return fuse_weighted(x, cov, seed_weights(res, d_fixed, fresh, lay), lay.starts)


def fuse_aposteriori(x: F, cov: F, res: F, res_var: F, fresh: B, lay: Layout,
                     p_stay: float = 0.95, b_min: float = 0.01) -> Fused:
    """(4.72) with the weights of :func:`markov_weights` on every coordinate; P = Σ b_n² C_n."""
    return fuse_weighted(x, cov, markov_weights(res, res_var, fresh, lay, p_stay, b_min), lay.starts)


# ---------------------------------------------------------------------------
# variants on the line-of-sight innovation and on the per-step variance
# ---------------------------------------------------------------------------


def los_innovation(x: F, site: F, res_var: F, sigma_r2: F, nominal_var: F) -> tuple[F, F, F]:
    """The 3-D innovation model from the range innovation: unit line of sight
    u_n (n, 3) from the radar site to the reported position, a_n = max(S_n − σ²_r, 0) (the
    predicted range variance without R, (4.75)) and the plot-noise diagonal D_n = nominal_var:
    ν_n = u_n ΔD_n, S_n = a_n u_n u_nᵀ + diag(D_n). Returns (u, a, D)."""
    d = x[:, :3] - site
    with np.errstate(invalid="ignore", divide="ignore"):
        u = d / np.linalg.norm(d, axis=1, keepdims=True)
    return u, np.maximum(res_var - sigma_r2, 0.0), nominal_var


def coord_loglik(res: F, u: F, a: F, dvar: F) -> tuple[F, F]:
    """Per-coordinate log-likelihoods (n, 3) of ν_{n,c} = u_c ΔD_n with variance
    S_{n,c} = a_n u_c² + D_c (the diagonal of S_n of :func:`los_innovation`), and S_{n,c}."""
    s = a[:, None] * u * u + dvar
    return _log_normal(u * res[:, None], s), s


def mv_loglik(res: F, u: F, a: F, dvar: F) -> F:
    """log N(ν_n; 0, S_n) with ν = u ΔD, S = a u uᵀ + diag(D) (rank-one update, closed form):
    q = Σ u_c²/D_c, det S = Π D_c (1 + a q), νᵀS⁻¹ν = ΔD² q/(1 + a q)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        q = np.sum(u * u / dvar, axis=1)
        logdet = np.sum(np.log(dvar), axis=1) + np.log1p(a * q)
        return -1.5 * np.log(2.0 * np.pi) - 0.5 * logdet - 0.5 * res * res * q / (1.0 + a * q)


def seed_s_weights(res: F, res_var: F, fresh: B, lay: Layout, b0: F | None = None) -> F:
    """``aposteriori_seed_S``: the printed prior (1 − b(k−1)) of (4.73)–(4.74) with the per-step
    S_n(k) in L_n, b(0) = 1/N (4.77)."""
    return _recursive_weights(_log_normal(res, res_var), _usable(fresh, res, res_var), lay, _log_prior_seed, 0.0,
                              b0)


def coord_weights(res: F, fresh: B, u: F, a: F, dvar: F, lay: Layout, p_stay: float, b_min: float,
                  b0: F | None = None) -> F:
    """Per-coordinate corrected a-posteriori weights b_{n,c} (n, 3): one
    recursion per system axis on :func:`coord_loglik`; ``b0`` (n, 3) carried weights."""
    ll, s = coord_loglik(res, u, a, dvar)
    prior = _log_prior_markov(p_stay)
    return np.stack([_recursive_weights(ll[:, c], _usable(fresh, res, s[:, c]) & np.isfinite(ll[:, c]),
                                        lay, prior, b_min, None if b0 is None else b0[:, c])
                     for c in range(3)], axis=1)


def mv_weights(res: F, fresh: B, u: F, a: F, dvar: F, lay: Layout, p_stay: float, b_min: float,
               b0: F | None = None) -> F:
    """One corrected a-posteriori weight per radar from the multivariate N(ν_n; 0, S_n) of :func:`los_innovation`."""
    ll = mv_loglik(res, u, a, dvar)
    return _recursive_weights(ll, fresh & np.isfinite(ll), lay, _log_prior_markov(p_stay), b_min, b0)


# ---------------------------------------------------------------------------
# D_n of the printed recursion
# ---------------------------------------------------------------------------


def seed_fixed_variance(rows: pl.DataFrame, radars: pl.DataFrame, first: pl.DataFrame | None = None) -> F:
    """D_n of (4.75)–(4.76) per row: the step-1 predicted range variance without R,
    ``res_range_var_m2 − sigma_range_m²`` at the first row of the (run, radar, local track)
    with a finite innovation (NaN when the track has none). ``first`` (:func:`first_innovation_var`
    of the earlier windows): the tracks' first finite ``res_range_var_m2`` seen before ``rows``."""
    unknown = set(rows["radar_id"].unique().to_list()) - set(radars["radar_id"].to_list())
    if unknown:
        raise ValueError(f"aposteriori_seed: radar_id(s) {sorted(unknown)} missing from radars")
    first_var = first_innovation_var(rows, first)
    out = rows.select(*TRACK).join(first_var, on=TRACK, how="left", maintain_order="left").join(
        radars.select(pl.col("radar_id").cast(pl.UInt32), "sigma_range_m"),
        on="radar_id", how="left", maintain_order="left",
    ).select(pl.col("first_var") - pl.col("sigma_range_m") ** 2)
    return out.to_series().fill_null(np.nan).to_numpy().astype(float)


def first_innovation_var(rows: pl.DataFrame, first: pl.DataFrame | None = None) -> pl.DataFrame:
    """Per (run, radar, local track): the ``res_range_var_m2`` of its first row (in ``rows``'
    order, epoch order) with a finite innovation — from ``first`` (the earlier windows) when it
    has the track. Columns TRACK + ``first_var``; tracks without one are absent."""
    finite = pl.col("res_range_m").is_finite() & pl.col("res_range_var_m2").is_finite()
    now = (track_keys(rows.select(*TRACK, "res_range_m", "res_range_var_m2")).filter(finite)
           .group_by(TRACK, maintain_order=True).agg(pl.col("res_range_var_m2").first().cast(pl.Float64)
                                                     .alias("first_var")))
    if first is None or first.is_empty():
        return now
    return pl.concat([first, now.join(first, on=TRACK, how="anti")])


# ---------------------------------------------------------------------------
# registration
# ---------------------------------------------------------------------------


def fuse_axis_weighted(x: F, cov: F, b3: F, starts: Ix) -> Fused:
    """The mix with per-coordinate weights ``b3`` (n, 3), velocity taking its axis's weight;
    reported weight: the mean of the three."""
    xf, pf = mix(x, cov, np.tile(b3, 2), starts)
    return keep_single(Fused(xf, pf, b3.mean(axis=1)), x, cov, starts)


def _mixed(b: Block) -> Fused:
    return fuse_weighted(b.x, b.cov, b.weights, b.starts)


def _los(run: RunInputs) -> tuple:
    """The line-of-sight arguments of :func:`coord_weights` / :func:`mv_weights`."""
    a, cfg = run.a, run.cfg
    return a["res"], a["fresh"], a["u"], a["a_pred"], a["dvar"], run.lay, cfg.p_stay, cfg.b_min


def _seed(run: RunInputs, b0: F | None) -> F:
    return seed_weights(run.a["res"], run.d_fixed(), run.a["fresh"], run.lay, b0)


def _markov(run: RunInputs, b0: F | None) -> F:
    a = run.a
    return markov_weights(a["res"], a["res_var"], a["fresh"], run.lay, run.cfg.p_stay, run.cfg.b_min, b0)


def _seed_s(run: RunInputs, b0: F | None) -> F:
    return seed_s_weights(run.a["res"], run.a["res_var"], run.a["fresh"], run.lay, b0)


register(FusionMethod("aposteriori_seed", "aposteriori", _mixed, rank=2, weights=_seed))
register(FusionMethod("aposteriori", "aposteriori", _mixed, rank=3, weights=_markov))
register(FusionMethod("aposteriori_seed_S", "aposteriori", _mixed, rank=9, default=False, weights=_seed_s))
register(FusionMethod("aposteriori_coord", "aposteriori", lambda b: fuse_axis_weighted(b.x, b.cov, b.weights, b.starts),
                      rank=10, default=False, weights=lambda run, b0: coord_weights(*_los(run), b0), per_axis=True,
                      line_of_sight=True))
register(FusionMethod("aposteriori_mv", "aposteriori", _mixed, rank=11, default=False,
                      weights=lambda run, b0: mv_weights(*_los(run), b0), line_of_sight=True))
