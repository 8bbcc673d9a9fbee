"""Pair geometry on height, never ENU z: the vertical channel, the closest approach (5.10)–(5.13)
and the same-time conflict intervals, linear or with heights stopped at the selected level
(docs/methods.md, "Conflict prediction (STCA)": "Geometry of one pair", "Vertical channel",
"Decision rules", "Selected level")."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import polars as pl
from numpy.typing import ArrayLike, NDArray

from tertiary.core import geo
from tertiary.core.geo import height_and_rate
from tertiary.core.units import STATE

__all__ = ["ALT_COLUMNS", "height_and_rate", "R_CURV_MIN_M", "tangent_plane_error_bound", "vertical_state",
           "state_arrays", "PairGeometry", "closest_approach", "endpoint_min", "seed_vertical", "conflict_interval",
           "clamped_dz", "clamped_vmin", "conflict_interval_levelled", "level_off_times", "pair_geometry"]


#: optional height channel of a track table (barometric or otherwise): used instead of the
#: geodetic height of the ENU position wherever ``alt_m`` is not null
ALT_COLUMNS = ("alt_m", "alt_rate_mps", "alt_var_m2", "alt_rate_var_m2ps2", "alt_cov_m2ps")


#: smallest radius of curvature of the WGS-84 ellipsoid (meridional, at the equator), m
R_CURV_MIN_M = geo.WGS84_A * (1.0 - geo.WGS84_E2)


def tangent_plane_error_bound(d_m: ArrayLike, rho_m: ArrayLike, h_m: ArrayLike, dh_m: ArrayLike) -> NDArray[np.float64]:
    """Upper bound (m) of |d_plane − d_geodesic| for the horizontal separation measured on the
    system ENU tangent plane: two aircraft whose footprints are d apart on the ellipsoid
    (geodesic), both within ρ of the centre, heights ≤ h, height difference |Δh|:

        |err| ≤ d·(ρ²/2R² + h/R) + |Δh|·ρ/R + 1 m,   R = 6 335 439 m (smallest curvature radius)

    — the projection's scale change (1 − cos(ρ/R)), the growth of horizontal distances with
    height, and the tilt ρ/R of the local vertical that turns a height difference into a
    horizontal offset (1 m covers rounding and the ellipsoid's second-order terms). Checked
    against pymap3d's Vincenty distance in tests/test_conflicts.py. Over the coverage (ρ ≤ 150 km,
    h ≤ 12 km) a pair 10 km apart errs by ≤ 31 m with |Δh| ≤ 300 m and ≤ 47 m with |Δh| ≤ 1 km —
    under 1 % of the 3 NM minimum, so the horizontal geometry may stay on the tangent plane;
    the vertical may not (ρ²/2R = 1.8 km at 150 km), hence :func:`height_and_rate`."""
    d, rho, h, dh = (np.asarray(a, np.float64) for a in (d_m, rho_m, h_m, dh_m))
    r = R_CURV_MIN_M
    return d * (0.5 * (rho / r) ** 2 + h / r) + np.abs(dh) * rho / r + 1.0


def vertical_state(tracks: pl.DataFrame, frame: geo.LocalFrame | None
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """(h, ḣ, up, from_alt) of every row: ``alt_m`` / ``alt_rate_mps`` where the table carries
    them (not null; a missing rate column means ḣ from the geodetic conversion), else the
    geodetic height and rate of the ENU state (:func:`height_and_rate`) — never ENU z."""
    pos = tracks.select(pl.col(["x_m", "y_m", "z_m"]).cast(pl.Float64)).to_numpy()
    vel = tracks.select(pl.col(["vx_mps", "vy_mps", "vz_mps"]).cast(pl.Float64)).to_numpy()
    h, hdot, up = height_and_rate(pos, vel, frame)
    from_alt = np.zeros(len(h), bool)
    if "alt_m" in tracks.columns:
        alt = tracks["alt_m"].cast(pl.Float64).to_numpy()
        from_alt = np.isfinite(alt)
        h = np.where(from_alt, alt, h)
        if "alt_rate_mps" in tracks.columns:
            rate = tracks["alt_rate_mps"].cast(pl.Float64).to_numpy()
            hdot = np.where(from_alt & np.isfinite(rate), rate, hdot)
    if not (np.all(np.isfinite(h)) and np.all(np.isfinite(hdot))):
        raise ValueError("tracks: heights and vertical rates must be finite")
    return h, hdot, up, from_alt


class PairGeometry(NamedTuple):
    """Per-pair geometry (arrays); i is the first, j the second aircraft."""

    r0: NDArray[np.float64]           # |r| now (m)
    r_min: NDArray[np.float64]        # (5.10) (m)
    t_min: NDArray[np.float64]        # (5.11) (s), +inf for parallel motion
    closure: NDArray[np.float64]      # r̂·v = −d|r|/dt (m/s)
    dz: NDArray[np.float64]           # Δh = h_j − h_i (5.12) (m)
    dvz: NDArray[np.float64]          # vz_j − vz_i (m/s)
    dz_min_seed: NDArray[np.float64]  # R_в^min = |Δh| − V_close·T_min (5.13), signed (m)
    dz_min: NDArray[np.float64]       # min over t ∈ [0, t_thr] of |Δh + Δvz t| (corrected) (m)


def closest_approach(rx, ry, vx, vy, eps):
    """R_min (5.10), T_min (5.11), |r| and closure, vectorised."""
    r0 = np.hypot(rx, ry)
    vv = vx * vx + vy * vy
    speed = np.sqrt(vv)
    moving = speed >= eps
    with np.errstate(divide="ignore", invalid="ignore"):
        r_min = np.where(moving, np.abs(rx * vy - ry * vx) / speed, r0)
        t_min = np.where(moving, (rx * vx + ry * vy) / vv, np.inf)
        closure = np.where(r0 > 0, (rx * vx + ry * vy) / r0, speed)
    return r0, r_min, t_min, closure, moving


def endpoint_min(a: NDArray, b: NDArray) -> NDArray:
    """min over a segment of |f| for f linear with end values a, b (0 if it changes sign)."""
    return np.where(a * b <= 0.0, 0.0, np.minimum(np.abs(a), np.abs(b)))


def seed_vertical(dz, dvz, t_min):
    """R_в^min = |Δh| − V_close·T_min with V_close = −sign(Δh)·Δvz (5.13), T_в^min := T_min."""
    v_close = -np.sign(dz) * dvz
    with np.errstate(invalid="ignore"):
        prod = np.where(v_close == 0.0, 0.0, v_close * t_min)
    return np.abs(dz) - prod


def _horizontal_interval(rx: NDArray, ry: NDArray, vx: NDArray, vy: NDArray, r_thr: NDArray, eps: float
                         ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Roots of |r − v t|² = R² (the times the pair is within R horizontally), see
    :func:`conflict_interval`; (−inf, inf) or (inf, −inf) for |v| < eps."""
    vv = vx * vx + vy * vy
    rv = rx * vx + ry * vy
    cross = rx * vy - ry * vx
    inside = rx * rx + ry * ry <= r_thr * r_thr
    disc = vv * r_thr * r_thr - cross * cross
    moving = vv >= eps * eps
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        sq = np.sqrt(np.maximum(disc, 0.0))
        h_lo = np.where(moving, (rv - sq) / vv, np.where(inside, -np.inf, np.inf))
        h_hi = np.where(moving, (rv + sq) / vv, np.where(inside, np.inf, -np.inf))
        h_lo = np.where(moving & (disc < 0.0), np.inf, h_lo)
    return h_lo, h_hi


def _vertical_interval(dz: NDArray, dvz: NDArray, z_thr: NDArray, eps: float
                       ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Times with |dz + dvz t| ≤ Z: between (±Z − dz)/dvz; |dvz| < eps: all t or none."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        climbing = np.abs(dvz) >= eps
        a = (-z_thr - dz) / dvz
        b = (z_thr - dz) / dvz
        level_in = np.abs(dz) <= z_thr
        v_lo = np.where(climbing, np.minimum(a, b), np.where(level_in, -np.inf, np.inf))
        v_hi = np.where(climbing, np.maximum(a, b), np.where(level_in, np.inf, -np.inf))
    return v_lo, v_hi


def conflict_interval(rx: NDArray, ry: NDArray, vx: NDArray, vy: NDArray, dz: NDArray, dvz: NDArray,
                      r_thr: NDArray | float, z_thr: NDArray | float, t_thr: float, eps: float = 1e-6
                      ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """[t_in, t_out] ⊂ [0, t_thr] during which the predicted pair is inside *both* thresholds at
    the same time (corrected rule); empty (t_in > t_out) when there is no such t.

    Separation r(t) = r − v t (horizontal, r = p_j − p_i, v = v_i − v_j) and Δh(t) = dz + dvz·t.
    Horizontal: |r − v t|² ≤ R²  ⇔  |v|²t² − 2(r·v)t + |r|² − R² ≤ 0, the interval between the
    roots (r·v ± √D)/|v|² with D = |v|²R² − (r×v)² (the cancellation-free form of
    (r·v)² − |v|²(|r|² − R²)); |v| < eps: all t if |r| ≤ R, none otherwise. Vertical:
    |dz + dvz t| ≤ Z, the interval between (±Z − dz)/dvz; |dvz| < eps: all t or none.
    The result is the intersection with [0, t_thr]: closed form, vectorised over pairs.
    """
    rx, ry, vx, vy, dz, dvz = np.broadcast_arrays(*(np.asarray(a, np.float64) for a in (rx, ry, vx, vy, dz, dvz)))
    r_thr = np.broadcast_to(np.asarray(r_thr, np.float64), rx.shape)
    z_thr = np.broadcast_to(np.asarray(z_thr, np.float64), rx.shape)
    h_lo, h_hi = _horizontal_interval(rx, ry, vx, vy, r_thr, eps)
    v_lo, v_hi = _vertical_interval(dz, dvz, z_thr, eps)
    t_in = np.maximum(np.maximum(h_lo, v_lo), 0.0)
    t_out = np.minimum(np.minimum(h_hi, v_hi), t_thr)
    return t_in, t_out


def clamped_dz(dz: NDArray, vz_i: NDArray, vz_j: NDArray, tau_i: NDArray, tau_j: NDArray, t: NDArray | float
                ) -> NDArray[np.float64]:
    """Δh(t) = dz + ḣ_j·min(t, τ_j) − ḣ_i·min(t, τ_i) (heights stopped at the selected levels)."""
    return dz + vz_j * np.minimum(t, tau_j) - vz_i * np.minimum(t, tau_i)


def _pieces(dz, vz_i, vz_j, tau_i, tau_j, w0: float, w1: float):
    """The ≤ 3 linear pieces of the clamped Δh(t) over [w0, w1]: knots k0 = w0 ≤ k1 ≤ k2 ≤ k3 = w1
    (the level-off times clipped to the window), Δh at the knots and each piece's slope
    (both moving; only the later one moving; neither)."""
    k1 = np.clip(np.minimum(tau_i, tau_j), w0, w1)
    k2 = np.clip(np.maximum(tau_i, tau_j), w0, w1)
    knots = (np.full_like(k1, w0), k1, k2, np.full_like(k1, w1))
    values = tuple(clamped_dz(dz, vz_i, vz_j, tau_i, tau_j, k) for k in knots)
    slope2 = np.where(tau_j > tau_i, vz_j, 0.0) - np.where(tau_i > tau_j, vz_i, 0.0)
    slopes = (vz_j - vz_i, slope2, np.zeros_like(k1))
    return knots, values, slopes


def clamped_vmin(dz, vz_i, vz_j, tau_i, tau_j, w0: float, w1: float) -> NDArray[np.float64]:
    """min over [w0, w1] of |Δh(t)| for the clamped prediction (0 where it changes sign)."""
    _, f, _ = _pieces(dz, vz_i, vz_j, tau_i, tau_j, w0, w1)
    return np.minimum(np.minimum(endpoint_min(f[0], f[1]), endpoint_min(f[1], f[2])), endpoint_min(f[2], f[3]))


def conflict_interval_levelled(rx: NDArray, ry: NDArray, vx: NDArray, vy: NDArray, dz: NDArray, vz_i: NDArray,
                               vz_j: NDArray, tau_i: NDArray, tau_j: NDArray, r_thr: NDArray | float,
                               z_thr: NDArray | float | tuple, t_thr: float, eps: float = 1e-6
                               ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`conflict_interval` with each aircraft's height stopped at its selected level:
    h(t) = h0 + ḣ·min(t, τ) (τ = +inf: linear; :func:`level_off_times`), so that
    Δh(t) = dz + ḣ_j·min(t, τ_j) − ḣ_i·min(t, τ_i) is linear on ≤ 3 pieces of [0, t_thr]
    (breaks at τ_i, τ_j). On each piece [p, q] with Δh = f_p + m·(t − p) the vertical set
    |Δh| ≤ Z is the interval between p + (±Z − f_p)/m (all or none for |m| < eps); it is
    intersected with the horizontal interval and [p, q]. ``z_thr``: one threshold or one per
    piece (a 3-tuple). Returns the first stretch of the (possibly disconnected) set: t_in its
    start, t_out its end (adjacent pieces joined); empty (t_in > t_out) when there is none.
    With τ_i = τ_j = +inf it equals :func:`conflict_interval`."""
    rx, ry, vx, vy, dz, vz_i, vz_j, tau_i, tau_j = np.broadcast_arrays(
        *(np.asarray(a, np.float64) for a in (rx, ry, vx, vy, dz, vz_i, vz_j, tau_i, tau_j)))
    z = z_thr if isinstance(z_thr, tuple) else (z_thr,) * 3
    z = tuple(np.broadcast_to(np.asarray(zk, np.float64), rx.shape) for zk in z)
    r_thr = np.broadcast_to(np.asarray(r_thr, np.float64), rx.shape)
    h_lo, h_hi = _horizontal_interval(rx, ry, vx, vy, r_thr, eps)
    knots, f, m = _pieces(dz, vz_i, vz_j, tau_i, tau_j, 0.0, t_thr)
    t_in = np.full(rx.shape, np.inf)
    t_out = np.full(rx.shape, -np.inf)
    for k in range(3):                      # three pieces, each vectorised over all pairs
        v_lo, v_hi = _vertical_interval(f[k], m[k], z[k], eps)
        lo = np.maximum(np.maximum(h_lo, v_lo + knots[k]), knots[k])
        hi = np.minimum(np.minimum(h_hi, v_hi + knots[k]), knots[k + 1])
        got = lo <= hi
        first = got & ~(t_in <= t_out)                      # the first non-empty piece
        join = got & (t_in <= t_out) & (lo <= t_out) & (t_out >= knots[k])   # continues the stretch
        t_in = np.where(first, lo, t_in)
        t_out = np.where(first | join, np.where(join, np.maximum(t_out, hi), hi), t_out)
    return t_in, t_out


def level_off_times(h: NDArray, hdot: NDArray, selected: NDArray, usable: NDArray[np.bool_],
                    tolerance_m: float) -> NDArray[np.float64]:
    """τ of each row (docs/methods.md "Selected level"): the time its predicted height reaches
    the level L it stops at — L = max(s, h0) climbing with s ≥ h0 − tol, min(s, h0) descending
    with s ≤ h0 + tol (a selected level within the tolerance on the wrong side: level now, τ = 0)
    —, +inf where the selected level ``s`` is missing (NaN), not ``usable`` (no barometric
    channel), inconsistent with the motion, or the row is level (ḣ = 0)."""
    h, hdot, s = (np.asarray(a, np.float64) for a in (h, hdot, selected))
    ok = np.asarray(usable, bool) & np.isfinite(s) & (hdot != 0.0)
    climb = hdot > 0.0
    ok &= np.where(climb, s >= h - tolerance_m, s <= h + tolerance_m)
    level = np.where(climb, np.maximum(s, h), np.minimum(s, h))
    with np.errstate(divide="ignore", invalid="ignore"):
        tau = (level - h) / hdot
    return np.where(ok, np.maximum(tau, 0.0), np.inf)


def pair_geometry(p_i: ArrayLike, v_i: ArrayLike, p_j: ArrayLike, v_j: ArrayLike,
                  t_thr: float = 105.0, eps: float = 1e-6) -> PairGeometry:
    """Geometry of aircraft pairs from positions/velocities ``(..., 3)`` (x, y, h) — (5.10)–(5.13).

    r = p_j − p_i and v = v_i − v_j horizontally, so T_min > 0 when approaching.
    ``dz_min_seed`` is the seed's R_в^min (5.13) with T_в^min = T_min; ``dz_min`` the corrected
    min over t ∈ [0, t_thr] of |Δh + Δvz t|. |v| < eps → R_min = |r|, T_min = +∞.
    """
    pi, vi, pj, vj = (np.asarray(a, dtype=np.float64) for a in (p_i, v_i, p_j, v_j))
    rx, ry = pj[..., 0] - pi[..., 0], pj[..., 1] - pi[..., 1]
    vx, vy = vi[..., 0] - vj[..., 0], vi[..., 1] - vj[..., 1]
    r0, r_min, t_min, closure, _ = closest_approach(rx, ry, vx, vy, eps)
    dz = pj[..., 2] - pi[..., 2]
    dvz = vj[..., 2] - vi[..., 2]
    return PairGeometry(r0, r_min, t_min, closure, dz, dvz, seed_vertical(dz, dvz, t_min),
                        endpoint_min(dz, dz + dvz * t_thr))


def state_arrays(tracks: pl.DataFrame, frame: geo.LocalFrame | None = None
                  ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """(x, y, h), (vx, vy, ḣ), up, from_alt of every row: horizontal on the system tangent plane,
    vertical on height (:func:`vertical_state`)."""
    missing = [c for c in STATE if c not in tracks.columns]
    if missing:
        raise ValueError(f"tracks: missing column(s) {', '.join(missing)}")
    st = tracks.select(pl.col(list(STATE)).cast(pl.Float64)).to_numpy()
    if not np.all(np.isfinite(st)):
        raise ValueError("tracks: states must be finite")
    h, hdot, up, from_alt = vertical_state(tracks, frame)
    pos = np.ascontiguousarray(np.column_stack([st[:, 0], st[:, 1], h]))
    vel = np.ascontiguousarray(np.column_stack([st[:, 3], st[:, 4], hdot]))
    return pos, vel, up, from_alt
