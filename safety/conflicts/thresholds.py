"""Thresholds (5.15)–(5.17): the estimation term from the tracks' propagated covariances (or
fixed), the piloting term, the level-pair vertical threshold, and per-track bounds of them for
the screen (docs/methods.md, "Conflict prediction (STCA)": "Thresholds", "Level pairs")."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import polars as pl
from numpy.typing import NDArray

from safety.conflicts.config import ConflictConfig

__all__ = ["PointTerms", "point_terms", "threshold_time", "pair_thresholds", "applied_thresholds", "Bounds",
           "threshold_bounds"]

class PointTerms(NamedTuple):
    """Per-track propagated position covariance as polynomials in the look-ahead t (m²):
    P(t) = c0 + c1·t + c2·t² for P_xx (a), P_xy (b), P_yy (d) in the system tangent plane and
    the height variance q (along the local up at the target, or the ``alt_*`` variances).
    Each field is a (3, n) array of (c0, c1, c2) rows (contiguous rows gather fast)."""

    a: NDArray[np.float64]
    b: NDArray[np.float64]
    d: NDArray[np.float64]
    q: NDArray[np.float64]

    def at(self, t: float | NDArray[np.float64], idx: NDArray[np.int64] | None = None
           ) -> tuple[NDArray[np.float64], ...]:
        """(a, b, d, q) at time(s) t for rows ``idx`` (all rows if None)."""
        out = []
        for c in self:
            c0, c1, c2 = (c[0], c[1], c[2]) if idx is None else (c[0][idx], c[1][idx], c[2][idx])
            c2 = c2 * t
            c2 += c1
            c2 *= t
            c2 += c0
            out.append(c2)
        return tuple(out)

    def take(self, idx: NDArray[np.int64]) -> "PointTerms":
        return PointTerms(*(np.ascontiguousarray(c[:, idx]) for c in self))

    @property
    def n(self) -> int:
        return self.a.shape[1]


def _poly(p0: NDArray, p1: NDArray, p2: NDArray) -> NDArray[np.float64]:
    return np.ascontiguousarray(np.vstack([p0, p1, p2]), dtype=np.float64)


def point_terms(tracks: pl.DataFrame, up: NDArray[np.float64] | None = None,
                from_alt: NDArray[np.bool_] | None = None) -> PointTerms:
    """P_pos(t) = P_pp + t(P_pv + P_vp) + t²P_vv of every track as polynomial coefficients.

    Horizontal: the x, y block. Vertical: uᵀP_pos(t)u with u = ``up`` (the local vertical at the
    target, :func:`height_and_rate`; None = ENU z) from the full 6×6 ``cov``, or with only
    ``cov_diag`` (diagonal fallback: no position–velocity or cross-axis terms, documented
    under-estimate for a tracker whose position and velocity errors correlate). Rows with an
    ``alt_m`` channel (``from_alt``) and an ``alt_var_m2`` column take q = alt_var +
    2t·alt_cov + t²·alt_rate_var instead."""
    n = tracks.height
    u = np.tile([0.0, 0.0, 1.0], (n, 1)) if up is None else up
    if "cov" in tracks.columns:
        c = tracks["cov"].to_numpy().reshape(-1, 6, 6)
        p0, pv, p2 = c[:, :3, :3], c[:, :3, 3:], c[:, 3:, 3:]
        p1 = pv + pv.transpose(0, 2, 1)
        mats = (p0, p1, p2)
    elif "cov_diag" in tracks.columns:
        c = tracks["cov_diag"].to_numpy().reshape(-1, 6)
        z = np.zeros((n, 3, 3))
        p0, p2 = z.copy(), z.copy()
        idx = np.arange(3)
        p0[:, idx, idx] = c[:, :3]
        p2[:, idx, idx] = c[:, 3:]
        mats = (p0, z, p2)
    else:
        raise ValueError("threshold_mode='covariance' needs a 'cov' (Array(Float64, 36)) or "
                         "'cov_diag' (Array(Float64, 6)) column; use threshold_mode='fixed' otherwise")
    a = _poly(*(m[:, 0, 0] for m in mats))
    b = _poly(*(m[:, 0, 1] for m in mats))
    d = _poly(*(m[:, 1, 1] for m in mats))
    q = _poly(*(np.einsum("ni,nij,nj->n", u, m, u) for m in mats))
    if from_alt is not None and from_alt.any() and "alt_var_m2" in tracks.columns:
        col = lambda name: (tracks[name].cast(pl.Float64).to_numpy() if name in tracks.columns  # noqa: E731
                            else np.zeros(n))
        qa = _poly(col("alt_var_m2"), 2.0 * col("alt_cov_m2ps"), col("alt_rate_var_m2ps2"))
        use = from_alt & np.isfinite(qa).all(axis=0)
        q = np.where(use[None, :], qa, q)
    terms = PointTerms(a, b, d, q)
    if not all(np.all(np.isfinite(x)) for x in terms):
        raise ValueError("covariances must be finite")
    return terms


def _lambda_max(a, b, d):
    """Largest eigenvalue of the symmetric 2×2 [[a, b], [b, d]]."""
    return 0.5 * (a + d) + np.hypot(0.5 * (a - d), b)


def threshold_time(cfg: "ConflictConfig", t_min: NDArray[np.float64]) -> NDArray[np.float64]:
    """Time at which the estimation and piloting terms are evaluated: clip(T_min, 0, T^пор) in
    corrected mode (the error that matters is the one at the closest approach; T^пор for
    parallel motion), T^пор in seed mode ((5.15)/(5.16) as printed)."""
    t_thr = cfg.t_thr_s
    if cfg.mode == "seed":
        return np.full(np.shape(t_min), t_thr)
    return np.where(np.isfinite(t_min), np.clip(t_min, 0.0, t_thr), t_thr)


def pair_thresholds(cfg: "ConflictConfig", terms: PointTerms | None, i: NDArray, j: NDArray,
                    t: float | NDArray[np.float64] | None = None
                    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """R_г^пор (5.15) and R_в^пор (5.16) of pairs (i, j) with the estimation and piloting terms
    at look-ahead ``t`` (scalar or per pair; None = T^пор as printed); ``terms`` from the
    tracks' covariances (None for ``threshold_mode="fixed"``)."""
    n = len(i)
    t = cfg.t_thr_s if t is None else t
    t_arr = np.broadcast_to(np.asarray(t, np.float64), (n,))
    pil_h = cfg.pilot_h_m + cfg.pilot_h_rate_mps * t_arr
    pil_v = cfg.pilot_v_m + cfg.pilot_v_rate_mps * t_arr
    if cfg.threshold_mode == "fixed" or terms is None:
        return cfg.sep_h_m + cfg.fixed_est_h_m + pil_h, cfg.sep_v_m + cfg.fixed_est_v_m + pil_v
    ai, bi, di, qi = terms.at(t_arr, i)
    aj, bj, dj, qj = terms.at(t_arr, j)
    lam = _lambda_max(ai + aj, bi + bj, di + dj)
    est_h = cfg.k_h * np.sqrt(np.maximum(lam, 0.0))
    est_v = cfg.k_v * np.sqrt(np.maximum(qi + qj, 0.0))
    return cfg.sep_h_m + est_h + pil_h, cfg.sep_v_m + est_v + pil_v


class Bounds(NamedTuple):
    """Per-track quantities whose pairwise combination bounds the thresholds (plus the near
    margins) from above at every evaluation time t ∈ [0, T^пор]:
    R_г^пор(i, j) + m_h ≤ base_h + k_h·sqrt(lam_i + lam_j), likewise vertically with q.
    λ_max(A + B) ≤ λ_max(A) + λ_max(B), and λ_max(P(t)) and q(t) are convex in t (P(t) is a
    matrix-convex quadratic, P_vv ⪰ 0), so their maximum over [0, T] is at an end point."""

    base_h: float
    base_v: float
    lam: NDArray[np.float64]
    q: NDArray[np.float64]
    reach: NDArray[np.float64]        # k_h·sqrt(lam)


def threshold_bounds(cfg: "ConflictConfig", terms: PointTerms | None, n: int) -> Bounds:
    t = cfg.t_thr_s
    mh, mv = cfg.near_margin_h_m, cfg.near_margin_v_m
    if cfg.threshold_mode == "fixed" or terms is None:
        r_h, r_v = pair_thresholds(cfg, None, np.zeros(1, np.int64), np.zeros(1, np.int64))
        return Bounds(float(r_h[0]) + mh, float(r_v[0]) + mv, np.zeros(n), np.zeros(n), np.zeros(n))
    a1, b1, d1, q1 = terms.at(t)
    lam = _lambda_max(a1, b1, d1)
    q = q1
    if cfg.mode != "seed":
        a0, b0, d0, q0 = terms.at(0.0)
        lam, q = np.maximum(lam, _lambda_max(a0, b0, d0)), np.maximum(q, q0)
    lam = np.maximum(lam, 0.0)
    return Bounds(cfg.sep_h_m + cfg.pilot_h_at_t + mh, cfg.sep_v_m + cfg.pilot_v_at_t + mv,
                   lam, np.maximum(q, 0.0), cfg.k_h * np.sqrt(lam))


def applied_thresholds(cfg: ConflictConfig, terms: PointTerms | None, i: NDArray[np.int64], j: NDArray[np.int64],
                       t_eval: NDArray[np.float64], vh: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
    """(R_г^пор, R_в^пор as applied now, the full (5.16) R_в^пор, the level-pair one) of pairs at
    ``t_eval`` — the vertical one is the level-pair threshold when both are level now."""
    r_thr, z_full = pair_thresholds(cfg, terms, i, j, t_eval)
    z_thr, z_level = z_full, z_full
    if cfg.mode == "corrected" and cfg.level_pair_tolerance_m is not None:
        z_level = np.minimum(z_full, cfg.sep_v_m - cfg.level_pair_tolerance_m)
        level = (np.abs(vh[i]) <= cfg.level_rate_mps) & (np.abs(vh[j]) <= cfg.level_rate_mps)
        z_thr = np.where(level, z_level, z_full)
    return r_thr, z_thr, z_full, z_level
