"""Short-term conflict prediction with accuracy-aware thresholds (monograph §5.2, (5.1)–(5.17);
digest ``docs/seeds/tertiary-and-safety.md`` §7, algorithm 7.1, worked example 7.2).

Geometry of one pair (i = ``id_a`` < j = ``id_b``), horizontal plane, digest convention §10.7
---------------------------------------------------------------------------------------------
    r = p_j − p_i,   v = v_i − v_j        (so the separation evolves as r(t) = r − v t)

    R_min = |r_x v_y − r_y v_x| / |v|                                                   (5.10)
    T_min = (r · v) / |v|²                                                              (5.11)

T_min > 0 for approaching aircraft. When |v| < ``eps_mps`` (parallel tracks, not treated in the
seed) R_min = |r| and T_min = +∞. Vertical: Δh = h_j − h_i (5.12), Δḣ = ḣ_j − ḣ_i.

Vertical channel: height, never ENU z
-------------------------------------
h and ḣ are the ``alt_m`` / ``alt_rate_mps`` columns where a table carries them (a barometric
channel), else the WGS-84 geodetic height of the system-frame ENU position and its rate along
the local up *at the target* (:func:`height_and_rate`, ``frame`` = the system origin). ENU z
is not height: at 100 km from the centre a level aircraft sits ρ²/2R ≈ 785 m lower in z, and
flying radially shows v·ρ/R ≈ 3 m/s of false z-rate. Horizontal geometry stays on the system
tangent plane; :func:`tangent_plane_error_bound` bounds that error (≤ 47 m for a pair 10 km
apart, |Δh| ≤ 1 km, anywhere within 150 km of the centre at ≤ 12 km).

Two decision rules (``ConflictConfig.mode``)
-------------------------------------------
* ``"seed"`` — faithful to (5.13)/(5.14) as printed (digest algorithm 7.1)::

      vertical ok  ⇔  |Δh| ≤ R_в^пор  (co-level)  or  R_в^min ≤ R_в^пор,
      R_в^min = |Δh| − V_close·T_min,  V_close = −sign(Δh)·Δḣ   (T_в^min := T_min)      (5.13)
      alert ⇔ R_min ≤ R_г^пор ∧ T_min ≤ T^пор ∧ vertical ok                             (5.14)

  A *negative* T_min passes, so pairs that have already passed each other are flagged, and
  horizontal and vertical closeness need not happen at the same time (the seed's flaws, kept
  on purpose). ``dz_min_m`` is R_в^min (signed: negative = the aircraft crossed levels before
  T_min). Thresholds (5.15)/(5.16) at T^пор, as printed.
* ``"corrected"`` (default) — the same-time rule::

      alert ⇔ ∃ t ∈ [0, T^пор]:  |r − v t| ≤ R_г^пор  ∧  |Δh + Δḣ t| ≤ R_в^пор

  the intersection of the horizontal interval (roots of a quadratic) with the vertical one
  (linear) and [0, T^пор], closed form and vectorised (:func:`conflict_interval`); ``t_in_s``
  is its start (NaN without alert). The climbing pair of issue 11 (CPA 0 m at 100 s, B 300 m
  above A climbing 10 m/s, 1 300 m apart at the CPA) alerts in seed mode, not here.
  ``dz_min_m`` = |Δh| at t* = clip(T_min, 0, T^пор) (the vertical separation at the closest
  horizontal approach within the look-ahead).

Selected level (corrected mode, ``ConflictConfig.use_selected_level``). A real STCA does not
extrapolate a climb through the level the aircraft is about to level off at: where a row carries
the Mode S selected altitude (``selected_alt_m``, BDS 4,0) and a barometric ``alt_m`` channel,
and the selected level is consistent with the vertical motion — climbing with it above, or
descending with it below, allowing ``selected_level_tolerance_m`` on the wrong side (the
capture/overshoot of a level-off) — the predicted height is

    h(t) = h0 + ḣ·min(t, τ),   τ = (L − h0)/ḣ ≥ 0,   L = max(s, h0) climbing, min(s, h0) descending

(:func:`level_off_times`). An aircraft moving away from its selected level beyond the tolerance
(a bust in progress, or a stale selection) and rows without one keep the linear prediction.
Where no selected level is downlinked (a Mode C-only aircraft, or a Mode S one that does not
downlink BDS 4,0) the row's cleared level from flight data (``cleared_alt_m``,
:mod:`tertiary.stages.flight_data`) takes its place under the same consistency test, as real STCAs use
the controller's CFL: the crew's selection wins where both are known (it is what the aircraft
will do; a wrong selection is a bust).
Δh(t) of a pair is then piecewise linear with at most three pieces (breaks at τ_i, τ_j);
:func:`conflict_interval_levelled` intersects, piece by piece, the set |Δh(t)| ≤ R_в^пор with
the horizontal interval (closed form, vectorised); the alert needs a non-empty piece, ``t_in_s``
is the earliest. On a piece where both aircraft are predicted level (both at their selected
levels, or one there and the other level now) the level-pair threshold below applies, as it
does to pairs level now. The estimation terms are evaluated as without the clamp (the height
variance still grows with t after the level-off: conservative).

Turning aircraft (corrected mode, ``ConflictConfig.use_turn_rate``; off by default, see its
docstring for what it did on the default scenario). A real STCA follows a turn
from the downlinked Mode S EHS data (BDS 5,0 track-angle rate) rather than extrapolating the
tangent of the arc through it. Rows whose ``ehs_track_rate_dps`` (:data:`TURN_RATE_COLUMN`,
carried to the tracks like the selected altitude) is at least ``turn_rate_min_dps`` (0.5 °/s:
10 σ of the register's 0.05 °/s noise, a third of a rate-one-half turn) in magnitude are
predicted along a constant-turn-rate arc (:func:`arc_offsets`) for at most ``max_turn_deg``
(30°) of turn, then straight on the track reached. Why bounded, and why 30°: the register says
how fast the aircraft turns, not how far — held for the whole look-ahead, 3 °/s would be a 315°
loop that only a holding pattern flies. Seen at a random instant of a fly-by turn of Θ, the
part still to come is uniform on [0, Θ]; for the 40–90° turns of terminal procedures (here
42–60° on the STARs/SIDs) its median is 20–45°, and the bound that minimises the expected
track error after the turn is that median — the straight line is the 0° bound, and a 90° bound
overshot the 42° STAR turn at the merge by ~70° on the default scenario (three arrival pairs
predicted into each other: false alerts). The duration is bounded by the look-ahead itself.
The vertical prediction is unchanged (linear, or stopped at the selected level), and so are the
estimation terms (propagated at constant velocity: the turn rate's own error, 0.05 °/s, moves a
130 m/s aircraft by ≈ v·δω·t²/2 ≈ 6 m over 105 s).

The rule stays "∃ t ∈ [0, T^пор] with horizontal ≤ R_г^пор and vertical ≤ R_в^пор", but an arc
has no closed-form intersection, so a pair with a turning member is decided on the time grid
t_k = k·T^пор/K, K = ⌈T^пор/``turn_grid_s``⌉ (0.5 s: 211 samples), vectorised over pairs ×
times (:func:`conflict_interval_arc`); pairs with no turning member keep the closed form. Grid
error: between samples the horizontal distance moves by ≤ (|v_i| + |v_j|)·Δt/2 from the nearest
sample (≤ 130 m for two 260 m/s aircraft, ≤ 65 m at terminal speeds), |Δh| by ≤ |Δḣ|·Δt/2
(≤ 5 m at 20 m/s): a grid alert is always a true one, a conflict entering the thresholds by
less than that (or for less than Δt) can be missed and ``t_in_s`` is late by < Δt. For such
pairs ``r_min_m`` / ``t_min_s`` are the arc's minimum horizontal distance over the grid of
[0, T^пор] and its time (for straight pairs (5.10)/(5.11), whose T_min may lie beyond T^пор),
and the thresholds are evaluated there. The KD-tree screen stays conservative: a turning row is
centred at its current position with reach |v|·T^пор (an arc of length |v|·t stays within |v|·t
of its start; :func:`_screen_states`).

All comparisons use equality (≤), as the digest chose for (5.8)/(5.16)/(5.17).

Thresholds (5.15)–(5.17)
------------------------
    T^пор  = Σ t_i + t_ман (+ ``t_margin_s``)                                          (5.17)
    R_г^пор = Δr_г + |ΔR_го(t*)| + |ΔR_гп(t*)|                                           (5.15)
    R_в^пор = Δr_в + |ΔR_во(t*)| + |ΔR_вп(t*)|                                           (5.16)

with t* = T^пор in seed mode (as printed) and t* = clip(T_min, 0, T^пор) in corrected mode — the
error that matters is the one at the closest approach, not at the end of the look-ahead
(:func:`threshold_time`; T^пор for parallel motion).

* Separation minima Δr: ``airspace="terminal"`` 3 NM / 1000 ft, ``"en-route"`` 5 NM / 1000 ft,
  or explicit ``dr_h_m`` / ``dr_v_m``.
* Estimation term, ``threshold_mode="covariance"`` (per pair): each track's covariance is
  propagated under constant velocity, P_pos(t) = P_pp + t(P_pv + P_vp) + t² P_vv, from the full
  6×6 ``cov`` (position–velocity cross terms included) or, when a table has only ``cov_diag``
  (today's ``tracks``), from the diagonal — a documented fallback that drops the cross terms
  (for a tracker whose position and velocity errors correlate positively it under-states the
  growth). The relative position covariance of the pair is P_i(t*) + P_j(t*) (independent
  errors). Horizontally (system x, y block)

      |ΔR_го| = k_h · sqrt(λ_max(P_rel,xy)),   k_h = sqrt(χ²₂⁻¹(confidence))

  — the circle of that radius contains the 2-D relative error with probability ≥ confidence
  (equality for an isotropic covariance): k_h = 2.448 at 95 %. Vertically, along each track's
  local up u (height, not z): σ_h²(t) = uᵀP_pos(t)u (or ``alt_var_m2`` + 2t·``alt_cov_m2ps`` +
  t²·``alt_rate_var_m2ps2`` for rows with an ``alt_m`` channel and those columns),

      |ΔR_во| = k_v · sqrt(σ_h,i² + σ_h,j²),   k_v = Φ⁻¹((1 + confidence)/2)   (1.960 at 95 %).

  ``threshold_mode="fixed"`` uses the constants ``fixed_est_h_m`` / ``fixed_est_v_m`` instead
  (the seed's scalar error bounds, digest §7.2) for comparison.
* Piloting term: ``pilot_h_m + pilot_h_rate_mps·t*`` (and likewise vertical); the defaults
  (500 m, 60 m, no growth) are the digest §7.2 values.

Output set ("candidates within the look-ahead") and the output diet
-------------------------------------------------------------------
Not all pairs: a pair of the same (run, epoch, method) is reported iff, over the screening
window W, its horizontal separation comes within R_г^пор + m_h **and** its vertical separation
within R_в^пор + m_v (each at some t ∈ W, not necessarily the same t; m = the near margins,
1 NM / 300 ft by default). W = [0, T^пор] in corrected mode and [−T^пор, T^пор] in seed mode, so
every alert of either rule is in the output — except that seed-mode pairs whose closest
approach was more than T^пор ago are not screened (the printed rule would flag them too).
``alert`` is the decision of the chosen rule; ``near`` = alert or the same-time rule holds with
both thresholds widened by the margins. :func:`slim_conflicts` keeps alert | near rows.

Tracks that are not established — velocity sigma above ``max_vel_sigma_mps`` (default 50 m/s;
a target's first epochs carry the 300 m/s velocity prior) — are left out before pairing, and so
are tracks that have coasted (no plot) for more than ``max_coast_s`` (default 10 s, 2–3 scans
of the terminal radars): a track that lost its aircraft (landed below coverage, left the area)
is extrapolated on its last velocity and would alert against whatever lies ahead of it. The
coast age is measured from the track's own rows (``plot_target_id`` null = a coasting row).

Level pairs (corrected mode). Two aircraft in level flight at flight levels the vertical minimum
apart (1 000 ft, e.g. adjacent levels of a holding stack) are separated by definition; adding
the estimation and piloting terms to Δr_в would make every such pair alert for as long as it
overlaps horizontally. When both tracks are level (|ḣ| ≤ ``level_rate_mps``, 1 m/s ≈ 200 ft/min)
the vertical threshold is min(R_в^пор, Δr_в − ``level_pair_tolerance_m``) (100 ft: above the
25 ft / 100 ft Mode S / Mode C quantisation error of a level difference, below the 900 ft
difference of a level bust). A pair where either aircraft climbs or descends — a level bust, a
climb into an occupied level — keeps the full (5.16) threshold. Seed mode is unchanged.

``severity`` = clip(1 − R_min / R_г^пор, 0, 1) for alerts (1 = collision course, 0 = grazing
the threshold), 0 for non-alert rows. ``closure_mps`` = r̂·v = −d|r|/dt at the epoch (positive
when closing). ``dz_m`` = Δh at the epoch (signed, h_b − h_a).

Final-approach volumes (corrected mode, ``ConflictConfig.approach_volumes``). Real STCA
systems use their own parameters in designated volumes of airspace. On a final approach the
approach controller spaces arrivals in trail, and the speed schedule (each arrival slows at the
same points of the final) makes a linear prediction see a follower closing on its slower leader
at 15–35 m/s that it never closes — on the default scenario every remaining false alert of the
best picture but two was such a pair, 8.6–8.9 km apart (the 1.5× minimum is 8.3 km). A pair
whose two tracks are both *established on the same final* (:class:`ApproachVolume`: within the
volume's length and half-width of the extended centreline, below its ceiling, tracking within
``track_tolerance_deg`` of the final course) is decided with that volume's parameters — the
reduced in-trail minimum of ICAO Doc 4444 §8.7.3.2 (2.5 NM) and a shorter look-ahead — by the
same rule (:func:`approach_membership`). Every other pair, including a pair with one member on
the final and one crossing it, keeps the configured ones. The scoring (losses of separation,
genuine / nuisance / false) does not change: it keeps the configured minima.

En-route airspace (``ConflictConfig.enroute_above_m``). Radar separation is 5 NM; the reduced
3 NM minimum applies where the authority specifies it, a terminal area (ICAO Doc 4444
§8.7.3.1–8.7.3.2), so to a pair only when both aircraft are in it. The minima Δr of
(5.15)–(5.16) are the configured (terminal) ones for a pair whose two tracks are both below the
en-route floor (height, the channel the prediction uses), and the en-route ones for every other
pair, decided by the same rule (:meth:`ConflictConfig.enroute`; its screen reaches 5 NM). Unlike
the final-approach volumes this is a separation standard, not an alerting parameter, so the
scoring follows it: :func:`safety.alerts.separation_intervals` judges a truth segment pair by the
terminal minima when its four end heights are below the floor, by the en-route ones otherwise
(a 4 NM pass at FL300 is a loss of separation). Where the traffic is planned 5 NM apart (the
national scenario, above FL150), one terminal parameter set scored such passes as false alerts:
not losses of 3 NM, yet predicted within the 3 NM thresholds plus margins.

Aerodrome zones (``ConflictConfig.aerodrome_zones``). Around a runway the aerodrome controller
separates departures from arrivals (runway separation; ICAO Doc 4444 chapter 7, aerodrome
control service), not radar separation: a departure is cleared for take-off with the next
arrival 2–4 NM out on final, 3 NM and less than 1 000 ft from it. STCA systems inhibit alerts in
such volumes. A pair whose two tracks are both inside one :class:`AerodromeZone` (within its
radius of the aerodrome and below its ceiling) is not predicted; a pair with one member inside
and one outside is. The scoring follows it (:func:`safety.alerts.separation_intervals`): a
truth segment pair whose four ends are inside one zone is not a loss of separation. On the
national scenario's 08:00 hour 137 of the 180 losses of separation of the truth were such
pairs (zones of 4 NM, 2 000 ft) — mostly a departure at lift-off and an arrival 1–6 km out below
300 m: losses only of a radar minimum nobody applies there.

Candidate search
----------------
One KD-tree over all (run, epoch, method) groups at once (a fourth coordinate = group index ×
a constant larger than any query radius, as in ``tertiary.stages.association.gating``): no O(N²) loop, no dense
N×N matrix. Every track is placed at its position at the centre t_c of W (half-length T_w).
If a pair comes within the thresholds at some t ∈ W then, horizontally,

    |c_j − c_i| ≤ (|v_i| + |v_j|)·T_w + R_г^пор(i, j),
    R_г^пор(i, j) ≤ Δr_г + |ΔR_гп| + k_h·sqrt(λ_i + λ_j)       (λ_max(A + B) ≤ λ_max A + λ_max B)

(λ_i = the larger of λ_max of track i's propagated horizontal covariance at t = 0 and at
t = T^пор — λ_max(P(t)) is convex in t, so that bounds it over the look-ahead) and likewise
vertically with the height variances; the near margins m_h, m_v are added to both reaches — so
the screen is conservative. For a set of tracks the maxima of these terms give a horizontal and
a vertical reach; the query is a Chebyshev box in (x, y, h·s) with the height scaled by
s = reach_h / reach_v. In seed mode (t_c = 0, T_w = T^пор) the horizontal reach is the
R^пор + 2·v_max·T^пор around the current positions; the corrected window [0, T^пор] halves the
closing distance. Three tiers keep the boxes tight:

* the **bulk** (speed, vertical speed, λ and z variance within their ``bulk_quantile``; speed
  ≤ ``v_max_mps`` when set) is split at the median vertical speed into a level and a climbing/
  descending part: level × level and climbing × climbing pairs come from one ``query_pairs``
  each (level flight has a small vertical reach), climbing × level pairs from one
  ``sparse_distance_matrix``;
* the few tracks beyond the bulk (very fast, very uncertain) are queried individually against
  all tracks with their own radius (``query_ball_point``).

No pair is missed whatever ``v_max_mps`` or ``bulk_quantile`` (they only affect speed). The
exact tests then run vectorised in chunks of ``chunk_pairs`` (vertical first, then horizontal,
then the full geometry of the survivors). To bound memory, whole groups are batched into
blocks of about ``block_points`` tracks, one set of trees per block (a block holds many epochs
of ordinary traffic; a 10 000-aircraft epoch is a block of its own).

Windowed processing (issue 16)
------------------------------
:func:`conflicts_step` (state, the picture's rows with epoch in [t0, t1), …) → (conflicts of
those epochs, state) is the stage's step function; :func:`predict_conflicts` is
:func:`init_conflict_state` + one step over (−∞, +∞). Pairs never span (run, epoch, method)
groups, so screening and geometry are window-local; what spans epochs is carried in
:class:`ConflictState`: the m-of-n confirmation (the last n − 1 epochs of each picture's epoch
grid and the raw alerts at them) and each established track's last plot epoch (the coast age of
``max_coast_s``). No margin of rows before or after a window is needed.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import numpy as np
import polars as pl
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from safety.confirmation import confirm_alerts
from tertiary.core import geo
from tertiary.core.distributions import chi2_ppf, norm_ppf
from tertiary.contract.schema import CLEARED_ALT_COLUMN, SELECTED_ALT_COLUMN, TABLES, TIME, TURN_RATE_COLUMN

__all__ = [
    "NM_M",
    "FT_M",
    "SEPARATION_MINIMA",
    "ConflictConfig",
    "ApproachVolume",
    "AerodromeZone",
    "zone_index",
    "approach_membership",
    "PairGeometry",
    "pair_geometry",
    "pair_thresholds",
    "candidate_pairs",
    "predict_conflicts",
    "conflict_interval",
    "conflict_interval_levelled",
    "level_off_times",
    "arc_offsets",
    "conflict_interval_arc",
    "turn_rates",
    "TURN_RATE_COLUMN",
    "SELECTED_ALT_COLUMN",
    "vertical_state",
    "height_and_rate",
    "slim_conflicts",
    "ALT_COLUMNS",
    "CONFLICT_EXTRA",
    "tangent_plane_error_bound",
    "threshold_time",
    "ConflictState",
    "init_conflict_state",
    "conflicts_step",
    "conflicts_steps",
    "T_MIN_US",
    "T_MAX_US",
]

NM_M = 1852.0
FT_M = 0.3048
#: (horizontal, vertical) separation minima in metres per airspace class
SEPARATION_MINIMA: dict[str, tuple[float, float]] = {
    "terminal": (3.0 * NM_M, 1000.0 * FT_M),
    "en-route": (5.0 * NM_M, 1000.0 * FT_M),
}

STATE = ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")
#: optional height channel of a track table (barometric or otherwise): used instead of the
#: geodetic height of the ENU position wherever ``alt_m`` is not null
ALT_COLUMNS = ("alt_m", "alt_rate_mps", "alt_var_m2", "alt_rate_var_m2ps2", "alt_cov_m2ps")


# --------------------------------------------------------------------------- vertical channel


def height_and_rate(pos: ArrayLike, vel: ArrayLike, frame: geo.LocalFrame | None
                    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Height above the WGS-84 ellipsoid, its rate and the local up unit vector at the target,
    from system-frame ENU positions/velocities ``(n, 3)``.

    h = geodetic height of the ECEF point frame.to_ecef(pos); ḣ = n̂·v with n̂ the ellipsoid
    normal *at the target* (∇h = n̂ exactly), expressed in the system ENU axes — not the
    origin's up (ENU z), which tilts by ρ/R: at ρ = 100 km a level aircraft's z drops
    ρ²/2R ≈ 785 m and a level radial flight at 200 m/s shows v·ρ/R ≈ 3 m/s of false z-rate.

    ``frame=None`` (no origin known): a sphere of radius :data:`tertiary.core.geo.EARTH_RADIUS_M`
    through the origin (h measured from the origin's height; the radius of curvature varies by
    ±0.5 % with azimuth, so the height of an aircraft at ρ errs by ≤ 0.005·ρ²/2R: ≤ 9 m at
    150 km, ≤ 4 m at 100 km). Pass the scenario origin whenever it is known.
    Returns (h (n,), ḣ (n,), up (n, 3)).
    """
    p = np.asarray(pos, np.float64).reshape(-1, 3)
    v = np.asarray(vel, np.float64).reshape(-1, 3)
    if frame is None:
        r = geo.EARTH_RADIUS_M
        c = p + np.array([0.0, 0.0, r])
        norm_c = np.sqrt(np.einsum("ij,ij->i", c, c))
        up = c / norm_c[:, None]
        h = norm_c - r
    else:
        lat, lon, h = geo.ecef_to_geodetic(*frame.to_ecef(p[:, 0], p[:, 1], p[:, 2]))
        la, lo = np.radians(lat), np.radians(lon)
        n_ecef = np.column_stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)])
        up = n_ecef @ frame.rotation.T                   # the ECEF normal in the system ENU axes
        h = np.asarray(h, np.float64)
    hdot = np.einsum("ij,ij->i", up, v)
    return h, hdot, up


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



@dataclass(frozen=True)
class ApproachVolume:
    """A final approach with its own STCA parameters (module docstring "Final-approach volumes").

    Geometry in the system frame: the runway threshold (``threshold_x_m``, ``threshold_y_m``), the
    final approach course ``course_deg`` (true, the direction arrivals fly), the volume along the
    extended centreline from the threshold out to ``length_m``, ``half_width_m`` either side,
    below ``ceiling_m`` (height, the channel conflict prediction uses); a track is established
    on it when its ground track is within ``track_tolerance_deg`` of the course. Parameters of
    pairs established on it: ``dr_h_m`` (horizontal minimum; 2.5 NM, the reduced in-trail
    minimum on final of ICAO Doc 4444 §8.7.3.2) and ``t_thr_s`` (look-ahead).

    The defaults were measured on the default scenario (``aposteriori+imm_sym``, velocity-σ
    limit 50 m/s; nuisance / false alerts, 10 of 10 losses alerted in every case): no volume 92 / 8;
    (3 NM, 105 s) in the volume 92 / 8; (2.5 NM, 105 s) 48 / 4; (3 NM, 60 s) 13 / 2;
    (2.5 NM, 60 s) 7 / 2; (2.5 NM, 45 s) 7 / 2."""

    threshold_x_m: float
    threshold_y_m: float
    course_deg: float
    length_m: float = 40_000.0
    half_width_m: float = 1_000.0
    ceiling_m: float = 1_500.0
    track_tolerance_deg: float = 15.0
    dr_h_m: float = 2.5 * NM_M
    t_thr_s: float = 60.0
    name: str = "final"

    def __post_init__(self) -> None:
        vals = (self.threshold_x_m, self.threshold_y_m, self.course_deg, self.length_m, self.half_width_m,
                self.ceiling_m, self.track_tolerance_deg, self.dr_h_m, self.t_thr_s)
        if not all(math.isfinite(v) for v in vals):
            raise ValueError(f"approach volume {self.name!r}: every value must be finite")
        if min(self.length_m, self.half_width_m, self.dr_h_m, self.t_thr_s) <= 0:
            raise ValueError(f"approach volume {self.name!r}: length_m, half_width_m, dr_h_m and t_thr_s "
                             "must be positive")
        if not 0 < self.track_tolerance_deg < 90:
            raise ValueError(f"approach volume {self.name!r}: track_tolerance_deg must be in (0, 90), "
                             f"got {self.track_tolerance_deg}")

    def contains(self, pos: NDArray[np.float64], vel: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Rows (x, y, h) / (vx, vy, ḣ) established on this final."""
        c = math.radians(self.course_deg)
        ux, uy = math.sin(c), math.cos(c)                 # unit vector of the course (x east, y north)
        dx, dy = pos[:, 0] - self.threshold_x_m, pos[:, 1] - self.threshold_y_m
        to_go = -(dx * ux + dy * uy)                      # distance before the threshold along the course
        cross = np.abs(dx * uy - dy * ux)
        speed = np.hypot(vel[:, 0], vel[:, 1])
        along = (vel[:, 0] * ux + vel[:, 1] * uy) >= speed * math.cos(math.radians(self.track_tolerance_deg))
        return ((to_go >= 0.0) & (to_go <= self.length_m) & (cross <= self.half_width_m)
                & (pos[:, 2] <= self.ceiling_m) & along & (speed > 0.0))

    def parameters(self, cfg: "ConflictConfig") -> "ConflictConfig":
        """``cfg`` with this volume's minimum and look-ahead (and no volumes of its own)."""
        return dataclasses.replace(cfg, dr_h_m=self.dr_h_m, t_delays_s=(), t_man_s=self.t_thr_s, t_margin_s=0.0,
                                   approach_volumes=())


@dataclass(frozen=True)
class AerodromeZone:
    """An aerodrome's traffic zone, where STCA is inhibited (module docstring "Aerodrome zones"):
    a cylinder around the aerodrome reference point (``x_m``, ``y_m``, system frame) of radius
    ``radius_m`` from the ground up to ``ceiling_m`` (height, the channel conflict prediction
    uses). Defaults: 4 NM and 2 000 ft — an aerodrome traffic zone is 2–2.5 NM, but the tower
    works arrivals from about 4 NM on final, where it releases departures ahead of them. Measured
    on the national scenario's 08:00 hour (losses of separation in the truth, zones at its 13
    airports, 2 000 ft): none 180, 2.5 NM 69, 4 NM 43, 5 NM 42 — the 26 between 2.5 and 4 NM are
    pairs within 5.5 km of the airport: a departure at lift-off with an arrival 4.6–5.5 km out, or
    a departure 4.5 km out on its climb with an arrival about to land or a departure behind it."""

    x_m: float
    y_m: float
    radius_m: float = 4.0 * NM_M
    ceiling_m: float = 2000.0 * FT_M
    name: str = "aerodrome"

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.x_m, self.y_m, self.radius_m, self.ceiling_m)):
            raise ValueError(f"aerodrome zone {self.name!r}: every value must be finite")
        if self.radius_m <= 0 or self.ceiling_m <= 0:
            raise ValueError(f"aerodrome zone {self.name!r}: radius_m and ceiling_m must be positive")

    def contains(self, pos: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Rows (x, y, h) inside the zone."""
        return (np.hypot(pos[:, 0] - self.x_m, pos[:, 1] - self.y_m) <= self.radius_m) & (pos[:, 2] <= self.ceiling_m)


def zone_index(pos: NDArray[np.float64], zones: Sequence[AerodromeZone]) -> NDArray[np.int64]:
    """Per row (x, y, h): the index of the first zone of ``zones`` that contains it, −1 for none."""
    out = np.full(len(pos), -1, np.int64)
    for k in range(len(zones) - 1, -1, -1):
        out[zones[k].contains(pos)] = k
    return out


@dataclass(frozen=True)
class ConflictConfig:
    """Conflict-prediction settings (5.15)–(5.17); see the module docstring.

    * ``airspace`` / ``dr_h_m`` / ``dr_v_m``: separation minima Δr_г, Δr_в (explicit values win).
    * ``t_delays_s`` (detection, command transmission, execution), ``t_man_s``, ``t_margin_s``:
      T^пор = Σ t_i + t_ман + margin (5.17); defaults give 105 s (digest §7.2).
    * ``confidence``: probability content of the covariance-based estimation term.
    * ``pilot_h_m``, ``pilot_h_rate_mps``, ``pilot_v_m``, ``pilot_v_rate_mps``: piloting error
      |ΔR_п(T)| = base + rate·T.
    * ``threshold_mode``: ``"covariance"`` (per pair, from the tracks) or ``"fixed"``
      (``fixed_est_h_m``, ``fixed_est_v_m``).
    * ``mode``: ``"seed"`` (faithful (5.14), negative T_min passes) or ``"corrected"``.
    * ``max_vel_sigma_mps``: tracks whose velocity standard deviation (sqrt of the larger of
      var(vx), var(vy) in ``cov``/``cov_diag``) exceeds this are *not established* (e.g. a
      target's first epochs, velocity still at its prior) and are left out of the prediction —
      no controller alert is raised on a tentative track, and a 300 m/s velocity sigma would
      otherwise give a ~90 km threshold. Applied in both threshold modes whenever a covariance
      column is present; None keeps every track. Default 25 m/s, chosen on the two scoring
      cases (default scenario with its final-approach volume, and adsb-paris; aposteriori /
      information + imm_sym): 50 m/s gave 2 / 4 and 35 / 30 false alerts, 25 m/s gives 1 / 3 and
      33 / 29 at the same losses alerted (10 of 10; 43 of 45) and median warning; 15 m/s (where
      the 95 % estimation term at 105 s, k_h·√2·σ·T, reaches the 3 NM minimum itself) gave
      1 / 2 and 27 / 24 but missed 4 and 3 more real losses on adsb-paris and cost 4–10 s of
      warning on the default scenario. Re-measured at 25 m/s on the block-streamed
      terminal-area data, with alerts linked to the closest approach they predicted
      (:class:`safety.alerts.AlertConfig`): 1 / 1 and 32 / 29 false alerts, 10 of 10 and 43 of
      45 losses alerted.
    * ``max_coast_s``: tracks coasting (no plot) for longer than this are left out (module
      docstring); needs a ``plot_target_id`` column, None keeps every track.
    * ``level_pair_tolerance_m`` / ``level_rate_mps``: the level-pair vertical threshold of the
      corrected rule (module docstring); None disables it.
    * ``use_selected_level`` / ``selected_level_tolerance_m``: corrected mode stops a climb or
      descent at the row's Mode S selected altitude when consistent with the motion (module
      docstring "Selected level"; the tolerance, 100 ft, is how far on the wrong side the
      selected level may be — a level-off capture or overshoot — before it is ignored).
    * ``use_turn_rate`` / ``turn_rate_min_dps`` / ``max_turn_deg`` / ``turn_grid_s``: corrected
      mode predicts rows whose downlinked track-angle rate (``ehs_track_rate_dps``, BDS 5,0)
      is at least ``turn_rate_min_dps`` in magnitude along a constant-turn-rate arc, bounded at
      ``max_turn_deg`` of turn, and decides pairs with such a member on a time grid of step
      ``turn_grid_s`` (module docstring "Turning aircraft"). Off by default: on the default
      scenario it added one false alert per picture (aposteriori+imm_sym 8 → 9, information+imm_sym
      10 → 11) — a partner's later turn at a merge point cannot be known from its turn rate now.
    * ``v_max_mps``: speed bound of the KD-tree bulk radius (None: from the data); it only
      affects speed, never the result.
    * ``eps_mps``: |v| below this counts as parallel motion (R_min = |r|, T_min = ∞).
    * ``confirm_m`` / ``confirm_n``: an alert is raised only when the condition held on m of the
      pair's last n picture epochs (:mod:`safety.confirmation`; 1/1: every raw condition alerts,
      the seed's behaviour, the default here). The pipeline's default is 3 of 4
      (:data:`STCA_CONFIRMATION`): on the default scenario it removed more than half of the
      false alerts of 1/1 for 8 s of median warning (``benchmarks/safety_thresholds.py``).
      The unconfirmed condition is kept as ``raw_alert``.
    * ``same_identity_is_duplicate``: two tracks with the same Mode S address (column
      ``mode_s``) are one aircraft tracked twice, not a pair in conflict: they never alert
      (their rows are kept, with ``alert`` false).
    * ``near_margin_h_m`` / ``near_margin_v_m`` (1 NM / 300 ft): a pair is *near* when the
      same-time rule holds with both thresholds widened by these margins (column ``near``;
      :func:`slim_conflicts` keeps alert or near rows); the output set is screened with the
      widened thresholds.
    * ``approach_volumes``: final approaches whose established pairs are decided with their own
      minimum and look-ahead (:class:`ApproachVolume`, corrected mode; module docstring
      "Final-approach volumes"). The pipeline fills them from the scenario's runways.
    * ``enroute_above_m`` / ``enroute_h_m`` / ``enroute_v_m``: en-route airspace from a floor up
      (height, the channel conflict prediction uses): the configured (terminal) minima decide
      the pairs whose two tracks are both below ``enroute_above_m``, the en-route minima (5 NM /
      1 000 ft) every other pair (module docstring "En-route airspace"); the loss-of-separation
      scoring of :mod:`safety.alerts` applies the same minima to the truth. None (the default):
      one set of minima everywhere.
    * ``aerodrome_zones``: aerodrome traffic zones (:class:`AerodromeZone`): a pair whose two
      tracks are both in one zone is not predicted (STCA inhibition), and the scoring of
      :mod:`safety.alerts` counts no loss of separation between two aircraft both in one zone
      (module docstring "Aerodrome zones"). The pipeline fills them from the scenario's airports.
    """

    airspace: Literal["terminal", "en-route"] = "terminal"
    dr_h_m: float | None = None
    dr_v_m: float | None = None
    t_delays_s: tuple[float, ...] = (10.0, 20.0, 15.0)
    t_man_s: float = 60.0
    t_margin_s: float = 0.0
    confidence: float = 0.95
    pilot_h_m: float = 500.0
    pilot_h_rate_mps: float = 0.0
    pilot_v_m: float = 60.0
    pilot_v_rate_mps: float = 0.0
    threshold_mode: Literal["covariance", "fixed"] = "covariance"
    fixed_est_h_m: float = 300.0
    fixed_est_v_m: float = 50.0
    mode: Literal["seed", "corrected"] = "corrected"
    max_vel_sigma_mps: float | None = 25.0
    max_coast_s: float | None = 10.0
    level_pair_tolerance_m: float | None = 100.0 * FT_M
    level_rate_mps: float = 1.0
    use_selected_level: bool = True
    selected_level_tolerance_m: float = 100.0 * FT_M
    use_turn_rate: bool = False
    turn_rate_min_dps: float = 0.5
    max_turn_deg: float = 30.0
    turn_grid_s: float = 0.5
    confirm_m: int = 1
    confirm_n: int = 1
    same_identity_is_duplicate: bool = True
    near_margin_h_m: float = NM_M
    near_margin_v_m: float = 300.0 * FT_M
    v_max_mps: float | None = None
    eps_mps: float = 1e-6
    bulk_quantile: float = 0.99
    chunk_pairs: int = 1 << 18
    block_points: int = 20_000
    approach_volumes: tuple[ApproachVolume, ...] = ()
    enroute_above_m: float | None = None
    enroute_h_m: float = SEPARATION_MINIMA["en-route"][0]
    enroute_v_m: float = SEPARATION_MINIMA["en-route"][1]
    aerodrome_zones: tuple[AerodromeZone, ...] = ()

    def __post_init__(self) -> None:
        if not all(isinstance(z, AerodromeZone) for z in self.aerodrome_zones):
            raise ValueError("aerodrome_zones must be AerodromeZone instances")
        if self.enroute_above_m is not None and not math.isfinite(self.enroute_above_m):
            raise ValueError(f"enroute_above_m must be finite or None, got {self.enroute_above_m}")
        if not (self.enroute_h_m > 0 and self.enroute_v_m > 0):
            raise ValueError(f"enroute_h_m and enroute_v_m must be positive, got {self.enroute_h_m}, "
                             f"{self.enroute_v_m}")
        if not all(isinstance(v, ApproachVolume) for v in self.approach_volumes):
            raise ValueError("approach_volumes must be ApproachVolume instances")
        if self.airspace not in SEPARATION_MINIMA:
            raise ValueError(f"airspace must be one of {list(SEPARATION_MINIMA)}, got {self.airspace!r}")
        if self.mode not in ("seed", "corrected"):
            raise ValueError(f"mode must be 'seed' or 'corrected', got {self.mode!r}")
        if self.threshold_mode not in ("covariance", "fixed"):
            raise ValueError(f"threshold_mode must be 'covariance' or 'fixed', got {self.threshold_mode!r}")
        if not 1 <= self.confirm_m <= self.confirm_n <= 63:
            raise ValueError(f"alert confirmation needs 1 <= confirm_m <= confirm_n <= 63, "
                             f"got {self.confirm_m} of {self.confirm_n}")
        if not 0.0 < self.confidence < 1.0:
            raise ValueError(f"confidence must be in (0, 1), got {self.confidence}")
        if self.t_thr_s <= 0:
            raise ValueError(f"the look-ahead T^пор must be positive, got {self.t_thr_s}")
        for name in ("dr_h_m", "dr_v_m"):
            val = getattr(self, name)
            if val is not None and val <= 0:
                raise ValueError(f"{name} must be positive, got {val}")
        for name in ("pilot_h_m", "pilot_v_m", "fixed_est_h_m", "fixed_est_v_m", "eps_mps",
                     "pilot_h_rate_mps", "pilot_v_rate_mps", "near_margin_h_m", "near_margin_v_m"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.max_vel_sigma_mps is not None and self.max_vel_sigma_mps <= 0:
            raise ValueError(f"max_vel_sigma_mps must be positive, got {self.max_vel_sigma_mps}")
        if self.max_coast_s is not None and self.max_coast_s < 0:
            raise ValueError(f"max_coast_s must be >= 0, got {self.max_coast_s}")
        if self.level_pair_tolerance_m is not None and self.level_pair_tolerance_m < 0:
            raise ValueError(f"level_pair_tolerance_m must be >= 0, got {self.level_pair_tolerance_m}")
        if not self.selected_level_tolerance_m >= 0:
            raise ValueError(f"selected_level_tolerance_m must be >= 0, got {self.selected_level_tolerance_m}")
        if not (self.turn_rate_min_dps > 0 and 0 < self.max_turn_deg <= 360 and 0 < self.turn_grid_s <= 10):
            raise ValueError("turn prediction needs turn_rate_min_dps > 0, 0 < max_turn_deg <= 360 and "
                             f"0 < turn_grid_s <= 10 s, got {self.turn_rate_min_dps}, {self.max_turn_deg}, "
                             f"{self.turn_grid_s}")
        if not self.level_rate_mps >= 0:
            raise ValueError(f"level_rate_mps must be >= 0, got {self.level_rate_mps}")
        if self.v_max_mps is not None and self.v_max_mps <= 0:
            raise ValueError(f"v_max_mps must be positive, got {self.v_max_mps}")
        if self.chunk_pairs < 1 or self.block_points < 2:
            raise ValueError("chunk_pairs must be >= 1 and block_points >= 2")
        if not 0.0 < self.bulk_quantile <= 1.0:
            raise ValueError(f"bulk_quantile must be in (0, 1], got {self.bulk_quantile}")

    # ---- derived quantities
    @property
    def sep_h_m(self) -> float:
        """Horizontal separation minimum Δr_г (m)."""
        return float(self.dr_h_m) if self.dr_h_m is not None else SEPARATION_MINIMA[self.airspace][0]

    @property
    def sep_v_m(self) -> float:
        """Vertical separation minimum Δr_в (m)."""
        return float(self.dr_v_m) if self.dr_v_m is not None else SEPARATION_MINIMA[self.airspace][1]

    def enroute(self) -> "ConflictConfig":
        """This configuration with the en-route minima and no en-route floor of its own: what
        decides every pair of tracks but those both below ``enroute_above_m``."""
        return dataclasses.replace(self, dr_h_m=self.enroute_h_m, dr_v_m=self.enroute_v_m, enroute_above_m=None)

    @property
    def t_thr_s(self) -> float:
        """Look-ahead T^пор = Σ t_i + t_ман (+ margin), (5.17)."""
        return float(sum(self.t_delays_s)) + self.t_man_s + self.t_margin_s

    @property
    def k_h(self) -> float:
        """Horizontal confidence factor sqrt(χ²₂⁻¹(confidence))."""
        return float(math.sqrt(chi2_ppf(self.confidence, 2)))

    @property
    def k_v(self) -> float:
        """Vertical confidence factor Φ⁻¹((1 + confidence)/2)."""
        return float(norm_ppf(0.5 * (1.0 + self.confidence)))

    @property
    def pilot_h_at_t(self) -> float:
        """|ΔR_гп(T^пор)| (m)."""
        return self.pilot_h_m + self.pilot_h_rate_mps * self.t_thr_s

    @property
    def pilot_v_at_t(self) -> float:
        """|ΔR_вп(T^пор)| (m)."""
        return self.pilot_v_m + self.pilot_v_rate_mps * self.t_thr_s

    @property
    def window_s(self) -> tuple[float, float]:
        """Screening window W: [0, T] (corrected) or [−T, T] (seed)."""
        t = self.t_thr_s
        return (0.0, t) if self.mode == "corrected" else (-t, t)


# --------------------------------------------------------------------------- pair geometry


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


def _horizontal(rx, ry, vx, vy, eps):
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


def _endpoint_min(a: NDArray, b: NDArray) -> NDArray:
    """min over a segment of |f| for f linear with end values a, b (0 if it changes sign)."""
    return np.where(a * b <= 0.0, 0.0, np.minimum(np.abs(a), np.abs(b)))


def _seed_vertical(dz, dvz, t_min):
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


def _clamped_dz(dz: NDArray, vz_i: NDArray, vz_j: NDArray, tau_i: NDArray, tau_j: NDArray, t: NDArray | float
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
    values = tuple(_clamped_dz(dz, vz_i, vz_j, tau_i, tau_j, k) for k in knots)
    slope2 = np.where(tau_j > tau_i, vz_j, 0.0) - np.where(tau_i > tau_j, vz_i, 0.0)
    slopes = (vz_j - vz_i, slope2, np.zeros_like(k1))
    return knots, values, slopes


def _clamped_vmin(dz, vz_i, vz_j, tau_i, tau_j, w0: float, w1: float) -> NDArray[np.float64]:
    """min over [w0, w1] of |Δh(t)| for the clamped prediction (0 where it changes sign)."""
    _, f, _ = _pieces(dz, vz_i, vz_j, tau_i, tau_j, w0, w1)
    return np.minimum(np.minimum(_endpoint_min(f[0], f[1]), _endpoint_min(f[1], f[2])), _endpoint_min(f[2], f[3]))


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
    """τ of each row (module docstring "Selected level"): the time its predicted height reaches
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



# --------------------------------------------------------------------------- turning aircraft


def turn_rates(tracks: pl.DataFrame, cfg: "ConflictConfig") -> NDArray[np.float64] | None:
    """Per row, the turn rate ω (rad/s, clockwise positive like the track angle) its horizontal
    prediction follows: the downlinked track-angle rate (:data:`TURN_RATE_COLUMN`) where it is
    at least ``cfg.turn_rate_min_dps`` in magnitude, else 0 (straight line). None when no row
    turns (or not corrected mode / ``use_turn_rate`` off / no such column)."""
    if cfg.mode != "corrected" or not cfg.use_turn_rate or TURN_RATE_COLUMN not in tracks.columns:
        return None
    rate = tracks[TURN_RATE_COLUMN].cast(pl.Float64).fill_null(np.nan).to_numpy()
    turning = np.isfinite(rate) & (np.abs(rate) >= cfg.turn_rate_min_dps)
    if not turning.any():
        return None
    return np.where(turning, np.radians(np.where(turning, rate, 0.0)), 0.0)


def arc_offsets(vx: ArrayLike, vy: ArrayLike, omega: ArrayLike, t: ArrayLike, max_turn_rad: float
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Horizontal displacement (east, north) after time t of an aircraft with velocity (vx, vy)
    turning at ω (rad/s, clockwise positive: the track angle χ = atan2(vx, vy) grows) — a
    constant-rate arc for t ≤ t_b = max_turn/|ω|, then straight on the track reached:

        θ = ω·min(t, t_b),  S = sin θ / ω,  C = (1 − cos θ) / ω          (ω = 0: S = t, C = 0)
        Δx = vx·S + vy·C + vx'·(t − t_b)₊,   Δy = −vx·C + vy·S + vy'·(t − t_b)₊,
        (vx', vy') = (vx cos θ + vy sin θ, −vx sin θ + vy cos θ)   (the velocity turned by θ)

    Arguments broadcast together (e.g. (n, 1) states against (K,) times)."""
    vx, vy, w, t = (np.asarray(a, np.float64) for a in (vx, vy, omega, t))
    aw = np.abs(w)
    with np.errstate(divide="ignore", invalid="ignore"):
        te = np.minimum(t, np.where(aw > 0, max_turn_rad / np.where(aw > 0, aw, 1.0), np.inf))
        th = w * te
        sn, cs = np.sin(th), np.cos(th)
        big_s = np.where(aw > 0, sn / np.where(aw > 0, w, 1.0), te)
        big_c = np.where(aw > 0, (1.0 - cs) / np.where(aw > 0, w, 1.0), 0.0)
    rest = t - te
    dx = vx * big_s + vy * big_c + (vx * cs + vy * sn) * rest
    dy = -vx * big_c + vy * big_s + (-vx * sn + vy * cs) * rest
    return dx, dy


def conflict_interval_arc(p_i: ArrayLike, v_i: ArrayLike, w_i: ArrayLike, p_j: ArrayLike, v_j: ArrayLike,
                          w_j: ArrayLike, dz: ArrayLike, vz_i: ArrayLike, vz_j: ArrayLike,
                          r_thr: NDArray | float, z_thr: NDArray | float | tuple, t_thr: float,
                          dt: float = 0.5, max_turn_rad: float = math.pi / 6,
                          tau_i: ArrayLike | None = None, tau_j: ArrayLike | None = None,
                          max_elements: int = 1 << 21) -> tuple[NDArray[np.float64], ...]:
    """The same-time rule for pairs with turning members, on a time grid (module docstring
    "Turning aircraft"): each aircraft's horizontal position along its bounded arc
    (:func:`arc_offsets`; ω = 0 is a straight line), heights as :func:`conflict_interval_levelled`
    (stopped at the level-off times τ; None: linear). ``p_*``, ``v_*``: (n, 2) horizontal
    positions / velocities; ``z_thr`` one threshold or one per vertical piece (a 3-tuple, pieces
    split at min τ and max τ). Grid t_k = k·T/K, K = ceil(T/dt); vectorised over pairs × times
    (chunks of ``max_elements``). Returns (t_in, t_out, d_min, t_star): the first grid time
    inside both thresholds and the end of that run of grid times (t_in > t_out: none), the
    minimum horizontal distance over the grid and its time. Between grid times the horizontal
    distance moves by at most (|v_i| + |v_j|)·Δt/2 from the nearest sample and |Δh| by
    |ḣ_i − ḣ_j|·Δt/2: a conflict that enters the thresholds by less than that, or for less than
    Δt, can be missed, and t_in is late by < Δt; a grid alert is always a true one."""
    p_i, v_i, p_j, v_j = (np.asarray(a, np.float64).reshape(-1, 2) for a in (p_i, v_i, p_j, v_j))
    n = len(p_i)
    w_i, w_j, dz, vz_i, vz_j = (np.broadcast_to(np.asarray(a, np.float64), (n,))
                                for a in (w_i, w_j, dz, vz_i, vz_j))
    inf = np.full(n, np.inf)
    tau_i = inf if tau_i is None else np.broadcast_to(np.asarray(tau_i, np.float64), (n,))
    tau_j = inf if tau_j is None else np.broadcast_to(np.asarray(tau_j, np.float64), (n,))
    r_thr = np.broadcast_to(np.asarray(r_thr, np.float64), (n,))
    z = z_thr if isinstance(z_thr, tuple) else (z_thr,) * 3
    z = tuple(np.broadcast_to(np.asarray(zk, np.float64), (n,)) for zk in z)
    k = max(1, int(math.ceil(t_thr / dt - 1e-9)))
    tk = np.linspace(0.0, t_thr, k + 1)
    out = tuple(np.empty(n) for _ in range(4))
    both = np.concatenate([v_i, v_j])
    ox, oy = arc_offsets(both[:, 0, None], both[:, 1, None], np.concatenate([w_i, w_j])[:, None], tk, max_turn_rad)
    idx = np.arange(n)
    for c, d2, hz in _arc_grid_chunks(p_j[:, 0] - p_i[:, 0], p_j[:, 1] - p_i[:, 1], idx, idx + n, ox, oy,
                                      (dz, vz_i, vz_j, tau_i, tau_j), tk, max_elements):
        zk = _piece_grid(tuple(zz[c] for zz in z), tau_i[c], tau_j[c], tk)
        out[0][c], out[1][c] = _first_run((d2 <= r_thr[c, None] ** 2) & (hz <= zk), tk)
        kmin = np.argmin(d2, axis=1)
        out[2][c] = np.sqrt(d2[np.arange(len(kmin)), kmin])
        out[3][c] = tk[kmin]
    return out


def _arc_grid_chunks(dx0: NDArray, dy0: NDArray, a: NDArray[np.int64], b: NDArray[np.int64], ox: NDArray,
                     oy: NDArray, vert, tk: NDArray[np.float64], max_elements: int = 1 << 21):
    """Per chunk of pairs (slice c): the squared horizontal distance (m, K+1) at the grid times
    ``tk`` of pairs whose current separation is (dx0, dy0) = p_j − p_i and whose members'
    displacements are rows ``a`` (i) and ``b`` (j) of ``ox``, ``oy`` (per track, computed once:
    :func:`arc_offsets` at ``tk``); with ``vert`` = (dz, ḣ_i, ḣ_j, τ_i, τ_j) also |Δh| (else None)."""
    n = len(dx0)
    step = max(1, max_elements // len(tk))
    for s in range(0, n, step):
        c = slice(s, min(n, s + step))
        ex = ox[b[c]]
        ex -= ox[a[c]]
        ex += dx0[c, None]
        ey = oy[b[c]]
        ey -= oy[a[c]]
        ey += dy0[c, None]
        ex *= ex
        ey *= ey
        ex += ey
        hz = None
        if vert is not None:
            dz, vz_i, vz_j, tau_i, tau_j = (v[c, None] for v in vert)
            hz = np.abs(_clamped_dz(dz, vz_i, vz_j, tau_i, tau_j, tk))
        yield c, ex, hz


class _ArcTable:
    """The displacements of the turning rows (ω ≠ 0) at the coarse screening grid and the fine
    decision grid, computed once per call of :func:`_pair_rows` (the trigonometry is per track,
    not per pair); other rows move on straight lines (v·t, no table)."""

    def __init__(self, cfg: ConflictConfig, st: NDArray[np.float64], omega: NDArray[np.float64]) -> None:
        t_thr, th = cfg.t_thr_s, math.radians(cfg.max_turn_deg)
        self.turn = np.flatnonzero(omega != 0.0)
        self.slot = np.full(len(omega), -1, np.int64)
        self.slot[self.turn] = np.arange(len(self.turn))
        vx, vy = st[3][self.turn, None], st[4][self.turn, None]
        w = omega[self.turn, None]
        self.grids = {}
        for name, step in (("coarse", ARC_SCREEN_STEP_S), ("fine", cfg.turn_grid_s)):
            tk = np.linspace(0.0, t_thr, max(1, int(math.ceil(t_thr / step - 1e-9))) + 1)
            self.grids[name] = (tk, *arc_offsets(vx, vy, w, tk, th))

    def offsets(self, st: NDArray[np.float64], i: NDArray[np.int64], j: NDArray[np.int64], grid: str):
        """(tk, dx0, dy0, a, b, ox, oy) of pairs (i, j) for :func:`_arc_grid_chunks`: one row
        of displacements per distinct track of the pairs."""
        tk, tx, ty = self.grids[grid]
        x, y, _, vx, vy, _ = st
        rows, inv = np.unique(np.concatenate([i, j]), return_inverse=True)
        inv = inv.ravel()
        ox, oy = vx[rows, None] * tk, vy[rows, None] * tk
        k = self.slot[rows]
        t = k >= 0
        ox[t], oy[t] = tx[k[t]], ty[k[t]]
        return tk, x[j] - x[i], y[j] - y[i], inv[:len(i)], inv[len(i):], ox, oy


def _piece_grid(z: tuple, tau_i: NDArray, tau_j: NDArray, tk: NDArray) -> NDArray[np.float64]:
    """The vertical threshold of each piece (before min τ, between, after max τ) on the grid."""
    k1, k2 = np.minimum(tau_i, tau_j)[:, None], np.maximum(tau_i, tau_j)[:, None]
    return np.where(tk < k1, z[0][:, None], np.where(tk < k2, z[1][:, None], z[2][:, None]))


def _first_run(inside: NDArray[np.bool_], tk: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(first grid time inside, last grid time of that run) per row; (inf, −inf) if never."""
    k = inside.shape[1] - 1
    first = np.argmax(inside, axis=1)
    got = inside[np.arange(len(first)), first]
    gap = ~inside & (np.arange(k + 1)[None, :] > first[:, None])
    last = np.where(gap.any(axis=1), np.argmax(gap, axis=1) - 1, k)
    return np.where(got, tk[first], np.inf), np.where(got, tk[last], -np.inf)


def pair_geometry(p_i: ArrayLike, v_i: ArrayLike, p_j: ArrayLike, v_j: ArrayLike,
                  t_thr: float = 105.0, eps: float = 1e-6) -> PairGeometry:
    """Geometry of aircraft pairs from positions/velocities ``(..., 3)`` (x, y, h) — (5.10)–(5.13).

    r = p_j − p_i and v = v_i − v_j horizontally (digest §10.7), so T_min > 0 when approaching.
    ``dz_min_seed`` is the seed's R_в^min (5.13) with T_в^min = T_min; ``dz_min`` the corrected
    min over t ∈ [0, t_thr] of |Δh + Δvz t|. |v| < eps → R_min = |r|, T_min = +∞.
    """
    pi, vi, pj, vj = (np.asarray(a, dtype=np.float64) for a in (p_i, v_i, p_j, v_j))
    rx, ry = pj[..., 0] - pi[..., 0], pj[..., 1] - pi[..., 1]
    vx, vy = vi[..., 0] - vj[..., 0], vi[..., 1] - vj[..., 1]
    r0, r_min, t_min, closure, _ = _horizontal(rx, ry, vx, vy, eps)
    dz = pj[..., 2] - pi[..., 2]
    dvz = vj[..., 2] - vi[..., 2]
    return PairGeometry(r0, r_min, t_min, closure, dz, dvz, _seed_vertical(dz, dvz, t_min),
                        _endpoint_min(dz, dz + dvz * t_thr))


# --------------------------------------------------------------------------- thresholds


class _PointTerms(NamedTuple):
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

    def take(self, idx: NDArray[np.int64]) -> "_PointTerms":
        return _PointTerms(*(np.ascontiguousarray(c[:, idx]) for c in self))

    @property
    def n(self) -> int:
        return self.a.shape[1]


def _poly(p0: NDArray, p1: NDArray, p2: NDArray) -> NDArray[np.float64]:
    return np.ascontiguousarray(np.vstack([p0, p1, p2]), dtype=np.float64)


def _point_terms(tracks: pl.DataFrame, up: NDArray[np.float64] | None = None,
                 from_alt: NDArray[np.bool_] | None = None) -> _PointTerms:
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
    terms = _PointTerms(a, b, d, q)
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


def pair_thresholds(cfg: "ConflictConfig", terms: _PointTerms | None, i: NDArray, j: NDArray,
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


class _Bounds(NamedTuple):
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


def _bounds(cfg: "ConflictConfig", terms: _PointTerms | None, n: int) -> _Bounds:
    t = cfg.t_thr_s
    mh, mv = cfg.near_margin_h_m, cfg.near_margin_v_m
    if cfg.threshold_mode == "fixed" or terms is None:
        r_h, r_v = pair_thresholds(cfg, None, np.zeros(1, np.int64), np.zeros(1, np.int64))
        return _Bounds(float(r_h[0]) + mh, float(r_v[0]) + mv, np.zeros(n), np.zeros(n), np.zeros(n))
    a1, b1, d1, q1 = terms.at(t)
    lam = _lambda_max(a1, b1, d1)
    q = q1
    if cfg.mode != "seed":
        a0, b0, d0, q0 = terms.at(0.0)
        lam, q = np.maximum(lam, _lambda_max(a0, b0, d0)), np.maximum(q, q0)
    lam = np.maximum(lam, 0.0)
    return _Bounds(cfg.sep_h_m + cfg.pilot_h_at_t + mh, cfg.sep_v_m + cfg.pilot_v_at_t + mv,
                   lam, np.maximum(q, 0.0), cfg.k_h * np.sqrt(lam))


# --------------------------------------------------------------------------- candidate search


def _group_index(tracks: pl.DataFrame, keys: list[str]) -> NDArray[np.int64]:
    """Dense index of the (run, epoch[, method]) group per row (in sorted key order)."""
    if not tracks.height:
        return np.zeros(0, np.int64)
    expr = pl.struct(keys) if len(keys) > 1 else pl.col(keys[0])
    return (tracks.select(expr.rank("dense").cast(pl.Int64) - 1).to_series().to_numpy())


def _flatten(lists) -> NDArray[np.int64]:
    parts = [np.asarray(x, dtype=np.int64) for x in lists]
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)


class _Screen(NamedTuple):
    """What the KD-tree screen of a set of settings reads: the window W = [t0, t1], the
    horizontal / vertical threshold bases (plus the near margins) and, per track, the squared
    covariance reaches lam2 = k_h²·λ and q2 = k_v²·q of :class:`_Bounds` — a pair (i, j) can be
    kept by a setting only if it comes within base_h + sqrt(lam2_i + lam2_j) horizontally and
    base_v + sqrt(q2_i + q2_j) vertically at some t ∈ W."""

    t0: float
    t1: float
    base_h: float
    base_v: float
    lam2: NDArray[np.float64]
    q2: NDArray[np.float64]
    bulk_quantile: float
    v_max_mps: float | None

    def take(self, idx: NDArray[np.int64]) -> "_Screen":
        return self._replace(lam2=self.lam2[idx], q2=self.q2[idx])


def _screen_of(cfg: ConflictConfig, b: _Bounds) -> _Screen:
    """The screen of one setting with bounds ``b``."""
    t0, t1 = cfg.window_s
    return _Screen(t0, t1, b.base_h, b.base_v, cfg.k_h ** 2 * b.lam, cfg.k_v ** 2 * b.q, cfg.bulk_quantile,
                   cfg.v_max_mps)


def _union_screen(screens: Sequence[_Screen]) -> _Screen:
    """A screen that keeps every pair any of ``screens`` keeps: the widest window, the largest
    bases and per-track reaches (sqrt(max_c a_c + max_c b_c) ≥ sqrt(a_c + b_c) for every c)."""
    first = screens[0]
    return first._replace(t0=min(s.t0 for s in screens), t1=max(s.t1 for s in screens),
                          base_h=max(s.base_h for s in screens), base_v=max(s.base_v for s in screens),
                          lam2=np.maximum.reduce([s.lam2 for s in screens]),
                          q2=np.maximum.reduce([s.q2 for s in screens]))


def _candidates(sc: _Screen, g: NDArray[np.int64], pos: NDArray[np.float64], vel: NDArray[np.float64]
                ) -> Iterator[tuple[NDArray[np.int64], NDArray[np.int64]]]:
    """Screened pairs (i ≠ j, each unordered pair once, same group) in up to three parts — see
    "Candidate search" in the module docstring. Parts are yielded one at a time (memory)."""
    n = len(g)
    if n < 2:
        return
    t0, t1 = sc.t0, sc.t1
    tw, tc = 0.5 * (t1 - t0), 0.5 * (t0 + t1)                # half-length and centre of W
    lam, qv = sc.lam2, sc.q2
    vh = np.hypot(vel[:, 0], vel[:, 1])
    vz = np.abs(vel[:, 2])

    def reach(m1: NDArray[np.bool_], m2: NDArray[np.bool_]) -> tuple[float, float]:
        """Upper bounds of the horizontal / vertical reach of any pair (i ∈ m1, j ∈ m2)."""
        rh = (vh[m1].max() + vh[m2].max()) * tw + sc.base_h + math.sqrt(lam[m1].max() + lam[m2].max())
        rv = (vz[m1].max() + vz[m2].max()) * tw + sc.base_v + math.sqrt(qv[m1].max() + qv[m2].max())
        return float(rh), float(rv)

    qq = sc.bulk_quantile
    v_b = sc.v_max_mps if sc.v_max_mps is not None else float(np.quantile(vh, qq))
    vz_b, lam_b, q_b = (float(np.quantile(x, qq)) for x in (vz, lam, qv))
    bulk = (vh <= v_b) & (vz <= vz_b) & (lam <= lam_b) & (qv <= q_b)
    if bulk.sum() < 2:
        bulk[:] = True
    # the bulk in two tiers: the level half (small vertical reach) and the rest
    level = bulk & (vz <= float(np.median(vz[bulk])))
    climb = bulk & ~level
    wide = ~bulk
    allm = np.ones(n, bool)
    r_ll = reach(level, level) if level.sum() >= 2 else (0.0, 1.0)
    r_cc = reach(climb, climb) if climb.sum() >= 2 else (0.0, 1.0)
    r_cl = reach(climb, level) if climb.any() and level.any() else (0.0, 1.0)
    w_idx = np.flatnonzero(wide)
    w_h = (vh[w_idx] + vh.max()) * tw + sc.base_h + np.sqrt(lam[w_idx] + lam.max())
    w_v = (vz[w_idx] + vz.max()) * tw + sc.base_v + np.sqrt(qv[w_idx] + qv.max())
    r_all = reach(allm, allm)
    scale = float(np.max(np.abs(pos))) + float(vh.max() + vz.max()) * max(abs(t0), abs(t1)) + 1.0
    pad = 1.0 + 1e-9 * scale                                   # rounding safety (metres)
    # Chebyshev radius and z scale of each query; the wide radii are ≤ r_all (same scale)
    s_ll, s_cc, s_cl, s_all = (r[0] / r[1] for r in (r_ll, r_cc, r_cl, r_all))
    q_ll, q_cc, q_cl = (r[0] + pad * max(1.0, s) for r, s in ((r_ll, s_ll), (r_cc, s_cc), (r_cl, s_cl)))
    q_w = np.maximum(w_h, w_v * s_all) + pad * max(1.0, s_all)
    sep = 2.0 * max(q_ll, q_cc, q_cl, r_all[0] + pad * max(1.0, s_all)) + 1.0
    # every track at the window centre; the 4th coordinate separates the groups by more than
    # any query radius, so one tree serves all (run, epoch, method) groups of the block
    c = pos + vel * tc
    gc = g.astype(np.float64) * sep

    def points(idx: NDArray[np.int64], s: float) -> NDArray[np.float64]:
        return np.column_stack([c[idx, 0], c[idx, 1], c[idx, 2] * s, gc[idx]])

    def pairs_within(idx: NDArray[np.int64], s: float, r: float):
        pr = cKDTree(points(idx, s)).query_pairs(r, p=np.inf, output_type="ndarray")
        a = idx[pr[:, 0]]
        return a, idx[pr[:, 1]]

    li, ci = np.flatnonzero(level), np.flatnonzero(climb)
    if len(li) >= 2:                                           # level × level
        yield pairs_within(li, s_ll, q_ll)
    if len(ci) >= 2:                                           # climbing/descending × climbing/descending
        yield pairs_within(ci, s_cc, q_cc)
    if len(ci) and len(li):                                    # climbing/descending × level
        sm = cKDTree(points(ci, s_cl)).sparse_distance_matrix(cKDTree(points(li, s_cl)), q_cl, p=np.inf,
                                                             output_type="ndarray")
        yield ci[sm["i"]], li[sm["j"]]
        del sm
    if len(w_idx):                                             # the few wide tracks × all, own radii
        pts = points(np.arange(n), s_all)
        hits = cKDTree(pts).query_ball_point(pts[w_idx], q_w, p=np.inf, return_sorted=False)
        counts = np.fromiter((len(x) for x in hits), np.int64, len(w_idx))
        jj = _flatten(hits)
        ii = np.repeat(w_idx, counts)
        keep = (ii != jj) & (bulk[jj] | (ii < jj))             # wide–wide pairs come twice
        yield ii[keep], jj[keep]


def _blocks(g: NDArray[np.int64], block_points: int):
    """Row indices of consecutive whole groups, about ``block_points`` rows per block (a larger
    group is a block of its own): one KD-tree per block bounds the memory of the candidate pairs
    while keeping the number of trees tiny (a block holds many small epochs)."""
    order = np.argsort(g, kind="stable")
    counts = np.bincount(g)
    ends = np.cumsum(counts)
    start, acc = 0, 0
    for k, c in enumerate(counts):
        if acc and acc + c > block_points:
            yield order[start:ends[k - 1]]
            start, acc = int(ends[k - 1]), 0
        acc += int(c)
    if acc:
        yield order[start:]


def _block_candidates(sc: _Screen, block_points: int, g, pos, vel):
    """(i, j) per part of each block: global row indices of screened pairs."""
    for idx in _blocks(g, block_points):
        for ci, cj in _candidates(sc.take(idx), g[idx], pos[idx], vel[idx]):
            yield idx[ci], idx[cj]


def candidate_pairs(tracks: pl.DataFrame, cfg: ConflictConfig = ConflictConfig(), method_col: str = "method",
                    frame: geo.LocalFrame | None = None) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Screened row-index pairs (i < j, same (run, epoch, method) group) of ``tracks``: a superset
    of the pairs that come within R_г^пор + m_h horizontally and R_в^пор + m_v vertically (the
    near margins) at some t of the screening window (KD-tree, see the module docstring), on
    height (:func:`vertical_state`). Exposed for tests and benchmarks. Unlike
    :func:`predict_conflicts` it keeps tentative tracks (no ``max_vel_sigma_mps``)."""
    g = _group_index(tracks, _group_cols(tracks, method_col))
    pos, vel, up, from_alt = _state_arrays(tracks, frame)
    terms = _point_terms(tracks, up, from_alt) if cfg.threshold_mode == "covariance" else None
    sc = _screen_of(cfg, _bounds(cfg, terms, len(g)))
    parts = list(_block_candidates(sc, cfg.block_points, g, pos, vel))
    if not parts:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    i = np.concatenate([p[0] for p in parts])
    j = np.concatenate([p[1] for p in parts])
    return np.minimum(i, j), np.maximum(i, j)


# --------------------------------------------------------------------------- main entry


def _group_cols(tracks: pl.DataFrame, method_col: str = "method") -> list[str]:
    cols = [c for c in ("run", "epoch") if c in tracks.columns]
    if method_col in tracks.columns:
        cols.append(method_col)
    return cols


def _not_coasting(tracks: pl.DataFrame, cfg: ConflictConfig, id_col: str, method_col: str,
                  last: pl.DataFrame) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Drop rows of tracks coasting for more than ``cfg.max_coast_s`` (see the config).

    The coast age of a row is (epoch − the track's last epoch updated with a plot) in seconds,
    inf before its first plot. ``last`` (:data:`_LAST`: run, method, id, last_update_us) carries
    each track's last plot epoch from earlier windows; returns (kept rows, updated ``last``), the
    entries of ``last`` that can no longer keep a row (older than ``max_coast_s`` before this
    window's latest epoch — later windows only hold later epochs) dropped."""
    if cfg.max_coast_s is None or "plot_target_id" not in tracks.columns or not tracks.height:
        return tracks, last
    keys = list(_LAST)[:3]
    e = _epoch_us_expr()
    k = (tracks.select(*_key_exprs(method_col, id_col), e.alias("__e"),
                       pl.when(pl.col("plot_target_id").is_not_null()).then(e).alias("__u"))
         .with_columns(pl.col("__u").forward_fill().over(keys, order_by="__e"))
         .join(last, on=keys, how="left", maintain_order="left"))
    last_u = pl.coalesce("__u", "last_update_us")
    keep = k.select(((pl.col("__e") - last_u) * 1e-6).fill_null(float("inf")) <= cfg.max_coast_s).to_series()
    upd = k.group_by(keys).agg(pl.col("__u").max().alias("last_update_us")).drop_nulls()
    e_max = int(k["__e"].max())
    merged = (pl.concat([last, upd.cast(_LAST)]).group_by(keys).agg(pl.col("last_update_us").max())
              .filter((pl.lit(e_max, pl.Int64) - pl.col("last_update_us")) * 1e-6 <= cfg.max_coast_s)
              .sort(keys))
    return tracks.filter(keep), merged


def _established(tracks: pl.DataFrame, cfg: ConflictConfig) -> pl.DataFrame:
    """Drop tracks whose velocity sigma exceeds ``cfg.max_vel_sigma_mps`` (see the config)."""
    lim = cfg.max_vel_sigma_mps
    if lim is None:
        return tracks
    if "cov" in tracks.columns:
        var = pl.max_horizontal(pl.col("cov").arr.get(21), pl.col("cov").arr.get(28))
    elif "cov_diag" in tracks.columns:
        var = pl.max_horizontal(pl.col("cov_diag").arr.get(3), pl.col("cov_diag").arr.get(4))
    else:
        return tracks
    return tracks.filter(var <= lim * lim)


def _state_arrays(tracks: pl.DataFrame, frame: geo.LocalFrame | None = None
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


def _empty_conflicts() -> pl.DataFrame:
    return pl.DataFrame(schema={**TABLES["conflicts"].required, **CONFLICT_EXTRA})


#: the pipeline's alert confirmation (confirm_m, confirm_n): 3 of the last 4 picture epochs
STCA_CONFIRMATION = (3, 4)

#: columns of ``conflicts`` beyond ``schema.TABLES["conflicts"]`` (to be added there)
CONFLICT_EXTRA: dict[str, pl.DataType] = dict(TABLES["conflicts"].optional)   # t_in_s, near


def _levelled_rows(tau: NDArray[np.float64] | None, i: NDArray[np.int64], j: NDArray[np.int64], w1: float
                   ) -> NDArray[np.int64]:
    """Pairs (positions in i, j) where either aircraft levels off at its selected level before
    the end of the window (``tau`` None: none)."""
    if tau is None:
        return np.zeros(0, np.int64)
    return np.flatnonzero(np.minimum(tau[i], tau[j]) < w1)


def _window_vmin(dz, dvz, vh, tau, i, j, w0: float, w1: float) -> NDArray[np.float64]:
    """min over the window of |Δh(t)|: linear, or clamped at the selected levels where one applies."""
    vmin = _endpoint_min(dz + dvz * w0, dz + dvz * w1)
    k = _levelled_rows(tau, i, j, w1)
    if k.size:
        vmin[k] = _clamped_vmin(dz[k], vh[i[k]], vh[j[k]], tau[i[k]], tau[j[k]], w0, w1)
    return vmin


def _evaluate_pairs(cfg: ConflictConfig, st: NDArray[np.float64], terms: _PointTerms | None,
                    i: NDArray[np.int64], j: NDArray[np.int64], bnd: _Bounds,
                    tau: NDArray[np.float64] | None = None,
                    arcs: "_ArcTable | None" = None, vmin: NDArray[np.float64] | None = None) -> dict[str, NDArray]:
    """Output-set membership, geometry, thresholds and decision of pairs (i, j); ``st`` holds the
    state columns x, y, h, vx, vy, ḣ as rows; ``bnd`` the per-track threshold bounds
    (:func:`_bounds`); ``tau`` each track's level-off time at its selected level
    (:func:`level_off_times`, corrected mode; None: linear vertical prediction); ``arcs`` each
    track's turn rate as :class:`_ArcTable` (:func:`turn_rates`; None: no row turns). Staged: the vertical window
    test, then the horizontal one (cheap upper bounds of the thresholds first), then the full
    geometry of the survivors only. Pairs with a turning member take their horizontal minimum,
    its time and the decision from the arc grid (:func:`conflict_interval_arc`). ``vmin``: the
    pairs' :func:`_window_vmin` when already computed (settings sharing the window and ``tau``)."""
    x, y, h, vx, vy, vh = st
    t_thr = cfg.t_thr_s
    w0, w1 = cfg.window_s
    mh, mv = cfg.near_margin_h_m, cfg.near_margin_v_m
    fixed = cfg.threshold_mode == "fixed" or terms is None
    base_v = bnd.base_v
    # 1. vertical: min over the window of |Δh(t)| ≤ R_в^пор + m_v (upper bound of R_в^пор)
    dz = h[j] - h[i]
    dvz = vh[j] - vh[i]
    excess = (_window_vmin(dz, dvz, vh, tau, i, j, w0, w1) if vmin is None else vmin) - base_v
    if fixed:
        ok = excess <= 0.0
    else:
        ok = (excess <= 0.0) | (excess * excess <= cfg.k_v ** 2 * (bnd.q[i] + bnd.q[j]))
    sel = np.flatnonzero(ok)
    i, j, dz, dvz = i[sel], j[sel], dz[sel], dvz[sel]
    # 2. horizontal: min over the window of |r − v t| ≤ R_г^пор + m_h
    rx, ry = x[j] - x[i], y[j] - y[i]
    vx_, vy_ = vx[i] - vx[j], vy[i] - vy[j]
    vv = vx_ * vx_ + vy_ * vy_
    moving = vv >= cfg.eps_mps ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        ts = np.where(moving, np.clip((rx * vx_ + ry * vy_) / vv, w0, w1), 0.0)
    ex, ey = rx - vx_ * ts, ry - vy_ * ts
    d2 = ex * ex + ey * ey
    arc = _turning_rows(None if arcs is None else arcs.slot, i, j)
    if arc.size:                       # turning pairs: a lower bound of the arc's distance over [0, T]
        lim = (bnd.base_h + bnd.reach[i[arc]] + bnd.reach[j[arc]]) * (1.0 + 1e-6)
        d2[arc] = _arc_lower_bound(cfg, st, arcs, i[arc], j[arc], np.sqrt(d2[arc]), lim) ** 2
    if not fixed:
        # R_г^пор(i, j, t) + m_h ≤ base_h + reach_i + reach_j, reach = k_h·sqrt(max_t λ_max)
        # (λ_max(A + B) ≤ λ_max A + λ_max B; 1e-6 guards rounding)
        reach = bnd.reach
        ub = (bnd.base_h + reach[i] + reach[j]) * (1.0 + 1e-6)
        is_arc = np.zeros(len(ub), bool)
        is_arc[arc] = True
        sel = np.flatnonzero(d2 <= ub * ub)
        i, j, dz, dvz, rx, ry, vx_, vy_, d2, is_arc = (a[sel] for a in (i, j, dz, dvz, rx, ry, vx_, vy_, d2, is_arc))
        arc = np.flatnonzero(is_arc)
    # 3. geometry (5.10)–(5.13), thresholds at the time that matters, output-set membership
    _, r_min, t_min, closure, _ = _horizontal(rx, ry, vx_, vy_, cfg.eps_mps)
    t_eval = threshold_time(cfg, t_min)
    r_thr, z_thr, z_full, z_level = _thresholds(cfg, terms, i, j, t_eval, vh)
    vmin = _window_vmin(dz, dvz, vh, tau, i, j, w0, w1)
    # a levelled pair's threshold varies by piece: screen it with the largest (z_full)
    z_screen = z_thr.copy()
    lv = _levelled_rows(tau, i, j, w1)
    z_screen[lv] = z_full[lv]
    r_screen = r_thr + mh
    if arc.size:                       # their thresholds come at the arc's closest approach: bound them
        r_screen[arc] = bnd.base_h + bnd.reach[i[arc]] + bnd.reach[j[arc]] if not fixed else r_screen[arc]
        if not fixed:
            z_screen[arc] = bnd.base_v - mv + cfg.k_v * np.sqrt(bnd.q[i[arc]] + bnd.q[j[arc]])
    member = (d2 <= r_screen ** 2) & (vmin <= z_screen + mv)
    sel = np.flatnonzero(member)
    is_arc = np.zeros(len(member), bool)
    is_arc[arc] = True
    i, j, dz, dvz, rx, ry, vx_, vy_, r_thr, z_thr, z_full, z_level, r_min, t_min, closure, t_eval, is_arc, vmin = (
        a[sel] for a in (i, j, dz, dvz, rx, ry, vx_, vy_, r_thr, z_thr, z_full, z_level, r_min, t_min, closure,
                         t_eval, is_arc, vmin))
    arc = np.flatnonzero(is_arc)
    # 4. decision (5.14) as printed, or the same-time rule (interval intersection)
    t_in, t_out = conflict_interval(rx, ry, vx_, vy_, dz, dvz, r_thr, z_thr, t_thr, cfg.eps_mps)
    n_in, n_out = conflict_interval(rx, ry, vx_, vy_, dz, dvz, r_thr + mh, z_thr + mv, t_thr, cfg.eps_mps)
    dz_eval = dz + dvz * t_eval
    lv = _levelled_rows(tau, i, j, w1)
    if lv.size:
        t_in[lv], t_out[lv], n_in[lv], n_out[lv], dz_eval[lv] = _levelled_decision(
            cfg, rx[lv], ry[lv], vx_[lv], vy_[lv], dz[lv], vh[i[lv]], vh[j[lv]], tau[i[lv]], tau[j[lv]], r_thr[lv],
            z_thr[lv], z_full[lv], z_level[lv], t_eval[lv])
    if arc.size:                       # turning pairs: everything from the fine grid of the arcs
        res = _arc_rows(cfg, st, arcs, tau, terms, i[arc], j[arc], dz[arc])
        for name, arr in (("r_min", r_min), ("t_min", t_min), ("t_eval", t_eval), ("r_thr", r_thr),
                          ("z_thr", z_thr), ("t_in", t_in), ("t_out", t_out), ("n_in", n_in), ("n_out", n_out),
                          ("dz_eval", dz_eval)):
            arr[arc] = res[name]
        # the output set proper (step 3 screened them with bounds): within R_г^пор + m_h at some t
        keep = np.ones(len(i), bool)
        keep[arc] = (res["r_min"] <= res["r_thr"] + mh) & (vmin[arc] <= res["z_screen"] + mv)
        if not keep.all():
            sel = np.flatnonzero(keep)
            i, j, dz, dvz, r_thr, z_thr, r_min, t_min, closure, t_in, t_out, n_in, n_out, dz_eval = (
                a[sel] for a in (i, j, dz, dvz, r_thr, z_thr, r_min, t_min, closure, t_in, t_out, n_in, n_out,
                                 dz_eval))
    joint = t_in <= t_out
    if cfg.mode == "corrected":
        dz_min = np.abs(dz_eval)                   # vertical separation at the horizontal CPA in [0, T]
        alert = joint
    else:
        dz_min = _seed_vertical(dz, dvz, t_min)
        vertical = (np.abs(dz) <= z_thr) | (dz_min <= z_thr)
        alert = (r_min <= r_thr) & (t_min <= t_thr) & vertical
    severity = np.where(alert, np.clip(1.0 - r_min / r_thr, 0.0, 1.0), 0.0)
    return {"i": i, "j": j, "r_min_m": r_min, "t_min_s": t_min, "dz_m": dz, "dz_min_m": dz_min,
            "closure_mps": closure, "r_thr_m": r_thr, "t_thr_s": np.full(len(i), t_thr), "z_thr_m": z_thr,
            "alert": alert, "severity": severity, "t_in_s": np.where(joint, t_in, np.nan),
            "near": alert | (n_in <= n_out)}


def _turning_rows(slot: NDArray[np.int64] | None, i: NDArray[np.int64], j: NDArray[np.int64]
                  ) -> NDArray[np.int64]:
    """Pairs (positions in i, j) with a turning member (``slot`` ≥ 0, :class:`_ArcTable`; None: none)."""
    if slot is None:
        return np.zeros(0, np.int64)
    return np.flatnonzero((slot[i] >= 0) | (slot[j] >= 0))


def _thresholds(cfg: ConflictConfig, terms: _PointTerms | None, i: NDArray[np.int64], j: NDArray[np.int64],
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


#: coarse grid step (s) of the turning pairs' screening bound (:func:`_arc_lower_bound`)
ARC_SCREEN_STEP_S = 5.0


def _arc_lower_bound(cfg: ConflictConfig, st: NDArray[np.float64], arcs: _ArcTable,
                     i: NDArray[np.int64], j: NDArray[np.int64], d_line: NDArray[np.float64],
                     limit: NDArray[np.float64]) -> NDArray[np.float64]:
    """A lower bound of the arcs' horizontal distance over [0, T] (screening only). First the
    straight lines' minimum ``d_line`` minus how far bounded arcs can leave their tangents
    (|v(s) − v0| ≤ 2|v|·sin(θ_max/2), so by ≤ 2|v|·sin(θ_max/2)·T); the pairs that bound does not
    settle (bound ≤ ``limit``, the largest reach that could keep the pair), on a coarse grid of
    step Δc = :data:`ARC_SCREEN_STEP_S`: min_k d(t_k) − (|v_i| + |v_j|)·Δc/2 (the distance moves
    by at most that between samples)."""
    t_thr, th = cfg.t_thr_s, math.radians(cfg.max_turn_deg)
    x, y, _, vx, vy, _ = st
    sp_i, sp_j = np.hypot(vx[i], vy[i]), np.hypot(vx[j], vy[j])
    lb = np.maximum(d_line - 2.0 * math.sin(min(th, math.pi) / 2.0) * t_thr * (sp_i + sp_j), 0.0)
    near = np.flatnonzero(lb <= limit)
    if near.size:
        tk, *grid = arcs.offsets(st, i[near], j[near], "coarse")
        d_min = np.empty(len(near))
        for c, d2, _ in _arc_grid_chunks(*grid, None, tk):
            d_min[c] = np.sqrt(d2.min(axis=1))
        lb[near] = np.maximum(lb[near], d_min - (sp_i[near] + sp_j[near]) * tk[1] / 2.0)
    return np.maximum(lb, 0.0)


def _arc_rows(cfg: ConflictConfig, st: NDArray[np.float64], arcs: _ArcTable,
              tau: NDArray[np.float64] | None, terms: _PointTerms | None, i: NDArray[np.int64],
              j: NDArray[np.int64], dz: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
    """Pairs with a turning member on the fine grid (one pass per chunk): the arc's closest
    approach over [0, T] (``r_min``, ``t_min`` = ``t_eval``), the thresholds there, the
    decision and the near test (vertical threshold per piece as :func:`_levelled_decision`),
    Δh at t*, and ``z_screen`` (the largest vertical threshold, for the output set)."""
    t_thr, mh, mv = cfg.t_thr_s, cfg.near_margin_h_m, cfg.near_margin_v_m
    tk, *grid = arcs.offsets(st, i, j, "fine")
    vzi, vzj = st[5][i], st[5][j]
    n = len(i)
    ti = np.full(n, np.inf) if tau is None else tau[i]
    tj = np.full(n, np.inf) if tau is None else tau[j]
    names = ("r_min", "t_min", "t_eval", "r_thr", "z_thr", "z_screen", "t_in", "t_out", "n_in", "n_out", "dz_eval")
    out = {name: np.empty(n) for name in names}
    vert = (dz, vzi, vzj, ti, tj)
    for c, d2, hz in _arc_grid_chunks(*grid, vert, tk):
        rows = np.arange(c.start, c.stop)
        kmin = np.argmin(d2, axis=1)
        t_star = tk[kmin]
        r_thr, z_now, z_full, z_level = _thresholds(cfg, terms, i[c], j[c], t_star, st[5])
        moving = np.where(ti[c] < tj[c], np.abs(vzj[c]), np.abs(vzi[c]))
        z2 = np.where(moving <= cfg.level_rate_mps, z_level, z_full)
        levelled = np.minimum(ti[c], tj[c]) < t_thr
        zs = (z_now, np.where(levelled, z2, z_now), np.where(levelled, z_level, z_now))
        zk = _piece_grid(zs, ti[c], tj[c], tk)
        t_in, t_out = _first_run((d2 <= r_thr[:, None] ** 2) & (hz <= zk), tk)
        n_in, n_out = _first_run((d2 <= (r_thr[:, None] + mh) ** 2) & (hz <= zk + mv), tk)
        vals = (np.sqrt(d2[np.arange(len(kmin)), kmin]), t_star, t_star, r_thr, z_now,
                np.where(levelled, z_full, z_now), t_in, t_out, n_in, n_out,
                _clamped_dz(dz[c], vzi[c], vzj[c], ti[c], tj[c], t_star))
        for name, v in zip(names, vals):
            out[name][rows] = v
    return out


def _levelled_decision(cfg: ConflictConfig, rx, ry, vx, vy, dz, vz_i, vz_j, tau_i, tau_j, r_thr, z_now, z_full,
                       z_level, t_eval) -> tuple[NDArray[np.float64], ...]:
    """(t_in, t_out, near t_in, near t_out, Δh(t_eval)) of pairs whose vertical prediction stops
    at a selected level (:func:`conflict_interval_levelled`). Vertical threshold per piece: now
    (``z_now``: the level-pair threshold if both are level now) on the first; on the second the
    level-pair one if the aircraft still moving is level now, else the full (5.16); on the third
    (both at their selected levels, or level) the level-pair one."""
    t_thr, mh, mv = cfg.t_thr_s, cfg.near_margin_h_m, cfg.near_margin_v_m
    moving = np.where(tau_i < tau_j, np.abs(vz_j), np.abs(vz_i))       # the later one to level off
    z2 = np.where(moving <= cfg.level_rate_mps, z_level, z_full)
    zs = (z_now, z2, z_level)
    t_in, t_out = conflict_interval_levelled(rx, ry, vx, vy, dz, vz_i, vz_j, tau_i, tau_j, r_thr, zs, t_thr,
                                             cfg.eps_mps)
    n_in, n_out = conflict_interval_levelled(rx, ry, vx, vy, dz, vz_i, vz_j, tau_i, tau_j, r_thr + mh,
                                             tuple(z + mv for z in zs), t_thr, cfg.eps_mps)
    return t_in, t_out, n_in, n_out, _clamped_dz(dz, vz_i, vz_j, tau_i, tau_j, t_eval)


# --------------------------------------------------------------------------- windowed engine

#: unbounded window ends (int64 µs): the whole-run call is one step over (−∞, +∞)
T_MIN_US = -(1 << 63)
T_MAX_US = (1 << 63) - 1
#: schemas of the carried state (natural keys, absolute int64 µs times)
_GRID = {"run": pl.UInt32, "method": pl.String, "epoch_us": pl.Int64}
_RAW = {"run": pl.UInt32, "method": pl.String, "epoch_us": pl.Int64, "id_a": pl.UInt64, "id_b": pl.UInt64}
_LAST = {"run": pl.UInt32, "method": pl.String, "id": pl.Int64, "last_update_us": pl.Int64}


def _epoch_us_expr() -> pl.Expr:
    """Row epoch as int64 µs since the Unix epoch (absolute, whatever the Datetime unit/zone)."""
    return pl.col("epoch").dt.epoch("us")


def _key_exprs(method_col: str, id_col: str) -> list[pl.Expr]:
    return [pl.col("run").cast(pl.UInt32).alias("run"), pl.col(method_col).cast(pl.String).alias("method"),
            pl.col(id_col).cast(pl.Int64).alias("id")]


@dataclass(frozen=True)
class ConflictState:
    """What conflict prediction carries from one time window to the next (issue 16); every
    time is int64 µs since the Unix epoch, every key natural. Picklable, never mutated.

    * ``grid`` (run, method, epoch_us): the last ``confirm_n − 1`` epochs of each picture's
      epoch grid (the epochs at which the picture has any row, established or not) — the m-of-n
      alert confirmation counts picture epochs, not seconds, so a window boundary must not
      restart the count;
    * ``raw`` (run, method, epoch_us, id_a, id_b): the pairs whose raw alert condition
      (``raw_alert``) held at those epochs;
    * ``last_update`` (run, method, id, last_update_us): the last epoch at which each
      established track (``max_vel_sigma_mps``) was updated with a plot — the coast age of
      ``max_coast_s``; an entry is dropped once it is more than ``max_coast_s`` older than the
      latest epoch seen (it could no longer keep a row);
    * ``t_us``: the end of the last window processed (None before the first).

    Nothing else spans epochs: ``max_vel_sigma_mps`` is a per-row test, and pairs never span
    (run, epoch, method) groups, so the screening and the pair geometry are window-local."""

    grid: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema=_GRID))
    raw: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema=_RAW))
    last_update: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema=_LAST))
    t_us: int | None = None


def init_conflict_state() -> ConflictState:
    """The empty state (before the first window)."""
    return ConflictState()


def _normalise(picture: pl.DataFrame, id_col: str, method_col: str, default_method: str) -> pl.DataFrame:
    """Check the key columns; add ``run`` (0) and ``method_col`` (``default_method``) if absent."""
    for c in ("epoch", id_col):
        if c not in picture.columns:
            raise ValueError(f"tracks: missing column {c!r}")
    if not isinstance(picture.schema["epoch"], pl.Datetime):
        raise ValueError(f"tracks: column 'epoch' must be a Datetime, got {picture.schema['epoch']}")
    if "run" not in picture.columns:
        picture = picture.with_columns(pl.lit(0, pl.UInt32).alias("run"))
    if method_col not in picture.columns:
        picture = picture.with_columns(pl.lit(default_method, pl.String).alias(method_col))
    return picture


def _check_window(state: ConflictState, picture: pl.DataFrame, t0_us: int, t1_us: int) -> None:
    """Windows come in time order and every row lies in [t0_us, t1_us)."""
    if not t0_us < t1_us:
        raise ValueError(f"conflicts_step: empty or reversed window [{t0_us}, {t1_us}) µs")
    if state.t_us is not None and t0_us < state.t_us:
        raise ValueError(f"conflicts_step: window [{t0_us}, {t1_us}) µs starts before the end of the "
                         f"previous one ({state.t_us} µs)")
    if picture.height:
        lo, hi = picture.select(_epoch_us_expr().min().alias("lo"), _epoch_us_expr().max().alias("hi")).row(0)
        if lo < t0_us or hi >= t1_us:
            raise ValueError(f"tracks: epochs [{lo}, {hi}] µs outside the window [{t0_us}, {t1_us}) µs")


def _epoch_grid(carried: pl.DataFrame, picture: pl.DataFrame, method_col: str) -> pl.DataFrame:
    """(run, method, epoch_us, epoch_k) of the carried grid tail and this window's epochs: the
    rank of each epoch in its picture's grid (an offset of :func:`epoch_index`'s; only
    differences matter to the confirmation)."""
    win = picture.select(pl.col("run").cast(pl.UInt32), pl.col(method_col).cast(pl.String).alias("method"),
                         _epoch_us_expr().alias("epoch_us"))
    return (pl.concat([carried, win]).unique().sort("run", "method", "epoch_us")
            .with_columns(pl.int_range(pl.len()).over("run", "method").cast(pl.Int64).alias("epoch_k")))


def _confirm(out: pl.DataFrame, grid: pl.DataFrame, carried: pl.DataFrame, cfg: ConflictConfig) -> pl.DataFrame:
    """:func:`confirm_alerts` of this window's rows, with the raw alerts of the carried epochs
    prepended so that the m-of-n count runs across the window boundary."""
    if cfg.confirm_m == 1 or not out.height:
        return confirm_alerts(out, grid, cfg.confirm_m, cfg.confirm_n)
    rows = out.select("run", "method", _epoch_us_expr().alias("epoch_us"), "id_a", "id_b", "alert")
    mini = pl.concat([carried.with_columns(pl.lit(True).alias("alert")), rows]).rename({"epoch_us": "epoch"})
    conf = confirm_alerts(mini, grid.rename({"epoch_us": "epoch"}), cfg.confirm_m, cfg.confirm_n)["alert"]
    return out.with_columns(pl.col("alert").alias("raw_alert"), conf.tail(out.height).alias("alert"))


def _carry_confirmation(grid: pl.DataFrame, carried: pl.DataFrame, out: pl.DataFrame, n: int
                        ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """The new (grid, raw) of :class:`ConflictState`: the last n − 1 epochs of each picture and
    the raw alerts at them."""
    tail = (grid.filter(pl.col("epoch_k") > pl.col("epoch_k").max().over("run", "method") - n + 1)
            .select(list(_GRID)))
    raw_now = (out.filter(pl.col("raw_alert")).select("run", "method", _epoch_us_expr().alias("epoch_us"),
                                                      "id_a", "id_b")
               if out.height else pl.DataFrame(schema=_RAW))
    raw = (pl.concat([carried, raw_now.cast(_RAW)]).join(tail, on=list(_GRID), how="semi")
           .sort(list(_RAW)))
    return tail, raw


def conflicts_step(state: ConflictState, picture: pl.DataFrame, cfg: ConflictConfig = ConflictConfig(),
                   id_col: str = "track_id", frame: geo.LocalFrame | None = None,
                   t0_us: int = T_MIN_US, t1_us: int = T_MAX_US, *, method_col: str = "method",
                   default_method: str = "none", slim: bool = True) -> tuple[pl.DataFrame, ConflictState]:
    """One time window [t0_us, t1_us) of conflict prediction (issue 16 step contract).

    ``picture``: the picture's rows with epoch in [t0_us, t1_us) (every row of those epochs,
    tentative/coasting ones included — they count in the confirmation's epoch grid), same
    columns as :func:`predict_conflicts`; no margin before or after the window is needed, the
    history lives in ``state`` (:class:`ConflictState`). Returns (the window's ``conflicts`` —
    :func:`slim_conflicts` of :func:`predict_conflicts`'s rows when ``slim``, every screened
    row otherwise —, the new state). Over consecutive windows the concatenated outputs equal
    ``predict_conflicts`` (then ``slim_conflicts``) of the whole picture. Pure: ``state`` is
    not modified. Raises ValueError for rows outside the window or a window that starts before
    the previous one ended."""
    return conflicts_steps([state], picture, [cfg], id_col, frame, t0_us, t1_us, method_col=method_col,
                           default_method=default_method, slim=slim)[0]


def conflicts_steps(states: Sequence[ConflictState], picture: pl.DataFrame, cfgs: Sequence[ConflictConfig],
                    id_col: str = "track_id", frame: geo.LocalFrame | None = None,
                    t0_us: int = T_MIN_US, t1_us: int = T_MAX_US, *, method_col: str = "method",
                    default_method: str = "none", slim: bool = True,
                    map_: Callable[..., Iterable] = map) -> list[tuple[pl.DataFrame, ConflictState]]:
    """:func:`conflicts_step` of one window under several settings at once, ``states[k]`` the
    state of ``cfgs[k]``: element k equals ``conflicts_step(states[k], picture, cfgs[k], …)``.
    What does not depend on the thresholds is done once — the rows kept, their state on height,
    covariance terms, and the KD-tree screen (one union screen, :func:`_union_screen`, for the
    settings that share the screen's other inputs: the output set is decided per setting by the
    exact tests, so a wider screen changes no row). ``map_`` (e.g. a thread pool's ``map``)
    runs the per-setting work."""
    if len(states) != len(cfgs):
        raise ValueError("conflicts_steps: one state per configuration")
    tracks = _normalise(picture, id_col, method_col, default_method)
    for state in states:
        _check_window(state, tracks, t0_us, t1_us)
    grids = _shared([s.grid for s in states], lambda carried: _epoch_grid(carried, tracks, method_col))
    kept: list[tuple[pl.DataFrame, pl.DataFrame]] = []
    memo: list[tuple[tuple, pl.DataFrame, tuple[pl.DataFrame, pl.DataFrame]]] = []
    for state, cfg in zip(states, cfgs):
        key = (cfg.max_vel_sigma_mps, cfg.max_coast_s)
        hit = next((v for k, last, v in memo if k == key and _same(last, state.last_update)), None)
        if hit is None:
            hit = _not_coasting(_established(tracks, cfg), cfg, id_col, method_col, state.last_update)
            memo.append((key, state.last_update, hit))
        kept.append(hit)
    pair_rows: list[pl.DataFrame | None] = [None] * len(cfgs)
    for table in {id(k[0]): k[0] for k in kept}.values():
        ks = [k for k in range(len(cfgs)) if kept[k][0] is table]
        rows = _Rows(table, frame, id_col, method_col)
        for k, out in zip(ks, _volume_rows(rows, [cfgs[k] for k in ks], map_)):
            pair_rows[k] = out
    spec = {**TABLES["conflicts"].required, **CONFLICT_EXTRA}

    def finish(k: int) -> tuple[pl.DataFrame, ConflictState]:
        state, cfg = states[k], cfgs[k]
        out = _confirm(pair_rows[k], grids[k], state.raw, cfg).select(list(spec)).cast(spec)
        g_tail, raw = _carry_confirmation(grids[k], state.raw, out, cfg.confirm_n)
        new = ConflictState(g_tail, raw, kept[k][1], t1_us if state.t_us is None else max(state.t_us, t1_us))
        return (slim_conflicts(out) if slim else out), new
    return list(map_(finish, range(len(cfgs))))


def _same(a: pl.DataFrame, b: pl.DataFrame) -> bool:
    return a is b or (a.schema == b.schema and a.equals(b))


def _shared(frames: Sequence[pl.DataFrame], fn: Callable[[pl.DataFrame], pl.DataFrame]) -> list[pl.DataFrame]:
    """``[fn(f) for f in frames]``, computed once per distinct (equal) frame."""
    done: list[tuple[pl.DataFrame, pl.DataFrame]] = []
    out = []
    for f in frames:
        hit = next((v for k, v in done if _same(k, f)), None)
        if hit is None:
            hit = fn(f)
            done.append((f, hit))
        out.append(hit)
    return out


def predict_conflicts(tracks: pl.DataFrame, cfg: ConflictConfig = ConflictConfig(), id_col: str = "track_id",
                      method_col: str = "method", default_method: str = "none",
                      frame: geo.LocalFrame | None = None) -> pl.DataFrame:
    """Predicted conflicts of an air picture — (5.10)–(5.17), rule ``cfg.mode``.

    ``tracks``: any track table with ``run``, ``epoch``, ``id_col`` (``track_id``; fused
    tables: ``target_id``), the system-frame ENU state ``x_m … vz_mps``, optionally the height
    channel :data:`ALT_COLUMNS` and, for ``threshold_mode="covariance"``, ``cov`` (row-major
    6×6) or ``cov_diag``. Heights: ``alt_m`` where present, else the geodetic height of the ENU
    position in ``frame`` (the system origin; None: spherical fallback, see
    :func:`height_and_rate`) — never ENU z. Pairs are formed within each (run, epoch,
    ``method_col``) group; without a method column the label is ``default_method``. Returns
    the ``conflicts`` table plus :data:`CONFLICT_EXTRA` (``t_in_s``: start of the predicted
    same-time conflict interval, NaN if none; ``near``; ``raw_alert``), id_a < id_b, sorted by
    (run, epoch, method, id_a, id_b). The whole run is one :func:`conflicts_step` over
    (−∞, +∞) from :func:`init_conflict_state`.
    """
    out, _ = conflicts_step(init_conflict_state(), tracks, cfg, id_col, frame, method_col=method_col,
                            default_method=default_method, slim=False)
    return out


def approach_membership(tracks: pl.DataFrame, cfg: ConflictConfig, frame: geo.LocalFrame | None = None
                        ) -> NDArray[np.int64]:
    """Per row, the index in ``cfg.approach_volumes`` of the final it is established on (the first
    that contains it), −1 for none — always −1 in seed mode (module docstring "Final-approach
    volumes")."""
    return _membership(_Rows(tracks, frame), cfg)


def _membership(rows: "_Rows", cfg: ConflictConfig) -> NDArray[np.int64]:
    member = np.full(rows.tracks.height, -1, np.int64)
    if cfg.mode != "corrected" or not cfg.approach_volumes or not rows.tracks.height:
        return member
    pos, vel, _, _ = rows.state()
    for k in range(len(cfg.approach_volumes) - 1, -1, -1):
        member[cfg.approach_volumes[k].contains(pos, vel)] = k
    return member


class _Rows:
    """The rows one window screens, with what every setting reads of them computed once, on
    first use: the group index (after the duplicate check), the ids, the state on height
    (:func:`_state_arrays`), the covariance terms, the key columns. The STCA curves predict the
    same rows under many settings. Not thread-safe until :meth:`prepare`d."""

    def __init__(self, tracks: pl.DataFrame, frame: geo.LocalFrame | None, id_col: str = "track_id",
                 method_col: str = "method") -> None:
        self.tracks, self.frame, self.id_col, self.method_col = tracks, frame, id_col, method_col
        self._memo: dict[str, object] = {}

    def _get(self, name: str, fn: Callable[[], object]):
        if name not in self._memo:
            self._memo[name] = fn()
        return self._memo[name]

    def group(self) -> NDArray[np.int64]:
        def make():
            groups = ["run", "epoch", self.method_col]
            dup = self.tracks.select(pl.struct([*groups, self.id_col]).is_duplicated().any()).item()
            if dup:
                raise ValueError(f"tracks: duplicate {self.id_col} within a (run, epoch, {self.method_col}) group")
            return _group_index(self.tracks, groups)
        return self._get("g", make)

    def state(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
        return self._get("state", lambda: _state_arrays(self.tracks, self.frame))

    def terms(self) -> _PointTerms:
        _, _, up, from_alt = self.state()
        return self._get("terms", lambda: _point_terms(self.tracks, up, from_alt))

    def ids(self) -> NDArray[np.int64]:
        return self._get("ids", lambda: self.tracks[self.id_col].cast(pl.Int64).to_numpy())

    def keys(self) -> pl.DataFrame:
        return self._get("keys", lambda: self.tracks.select(
            pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME),
            pl.col(self.method_col).cast(pl.String).alias("method")))

    def prepare(self, covariance: bool) -> None:
        """Compute what the settings read (before they run in threads)."""
        self.group(), self.state(), self.ids(), self.keys()
        if covariance:
            self.terms()

    def subset(self, mask: NDArray[np.bool_]) -> "_Rows":
        """The rows of ``mask``, with the arrays computed so far sliced, not recomputed."""
        sub = _Rows(self.tracks.filter(pl.Series(mask)), self.frame, self.id_col, self.method_col)
        idx = np.flatnonzero(mask)
        for name, v in self._memo.items():
            if name == "state":
                sub._memo[name] = tuple(a if a is None else a[idx] for a in v)
            elif name == "terms":
                sub._memo[name] = v.take(idx)
            else:                               # g, ids (arrays), keys (a frame)
                sub._memo[name] = v[idx]
        return sub


def _volume_rows(rows: _Rows, cfgs: Sequence[ConflictConfig], map_: Callable[..., Iterable] = map
                 ) -> list[pl.DataFrame]:
    """:func:`_airspace_rows` of each setting, without the pairs whose two tracks are both in one
    of its aerodrome zones (module docstring "Aerodrome zones")."""
    outs = _airspace_rows(rows, cfgs, map_)
    member: dict[tuple, NDArray[np.int64]] = {}
    for k, c in enumerate(cfgs):
        if c.aerodrome_zones and rows.tracks.height and outs[k].height:
            if c.aerodrome_zones not in member:
                member[c.aerodrome_zones] = zone_index(rows.state()[0], c.aerodrome_zones)
            if np.any(member[c.aerodrome_zones] >= 0):
                outs[k] = _replaced(outs[k], [], rows, member[c.aerodrome_zones])
    return outs


def _airspace_rows(rows: _Rows, cfgs: Sequence[ConflictConfig], map_: Callable[..., Iterable] = map
                   ) -> list[pl.DataFrame]:
    """:func:`_approach_rows` of each setting; a setting with an en-route floor decides the pairs
    whose two tracks are both below it with its minima and every other pair with its en-route
    minima (module docstring "En-route airspace")."""
    outs: list[pl.DataFrame | None] = [None] * len(cfgs)
    plain = [k for k, c in enumerate(cfgs) if c.enroute_above_m is None]
    if plain:
        for k, out in zip(plain, _approach_rows(rows, [cfgs[k] for k in plain], map_)):
            outs[k] = out
    floors: dict[float, list[int]] = {}
    for k, c in enumerate(cfgs):
        if c.enroute_above_m is not None:
            floors.setdefault(c.enroute_above_m, []).append(k)
    for floor, ks in floors.items():
        low = rows.state()[0][:, 2] < floor if rows.tracks.height else np.zeros(0, bool)
        if low.all():                            # a terminal area only: the configured minima
            for k, out in zip(ks, _approach_rows(rows, [cfgs[k] for k in ks], map_)):
                outs[k] = out
            continue
        above = _approach_rows(rows, [cfgs[k].enroute() for k in ks], map_)
        below = (_approach_rows(rows.subset(low), [cfgs[k] for k in ks], map_) if low.sum() >= 2
                 else [_empty_conflicts() for _ in ks])
        for k, a, b in zip(ks, above, below):
            outs[k] = _replaced(a, [b], rows, np.where(low, 0, -1))
    return outs


def _replaced(base: pl.DataFrame, parts: Sequence[pl.DataFrame], rows: _Rows, group: NDArray[np.int64]
              ) -> pl.DataFrame:
    """``base`` without its pairs of two rows in one group (``group`` ≥ 0 per row; −1: none), with
    ``parts`` (those pairs, decided otherwise) in their place, in the pair order."""
    key = ["run", "epoch", "method"]
    flag = rows.keys().with_columns(pl.Series("__id", rows.ids()).cast(pl.UInt64), pl.Series("__g", group))
    ga = pl.col("__ga").fill_null(-1)
    kept = (base.join(flag.rename({"__id": "id_a", "__g": "__ga"}), on=[*key, "id_a"], how="left")
            .join(flag.rename({"__id": "id_b", "__g": "__gb"}), on=[*key, "id_b"], how="left")
            .filter(~((ga >= 0) & (ga == pl.col("__gb").fill_null(-2)))).drop("__ga", "__gb"))
    out = [p for p in (kept, *parts) if p.height]   # an empty part has the empty table's extra columns
    return pl.concat(out, how="vertical_relaxed").sort([*key, "id_a", "id_b"]) if out else _empty_conflicts()


def _approach_rows(rows: _Rows, cfgs: Sequence[ConflictConfig], map_: Callable[..., Iterable] = map
                   ) -> list[pl.DataFrame]:
    """:func:`_pair_rows` of each setting, with the pairs whose two tracks are established on the
    same final decided by that volume's parameters instead (:class:`ApproachVolume`)."""
    outs = _pair_rows(rows, cfgs, map_)
    by_vols: dict[tuple, list[int]] = {}
    for k, c in enumerate(cfgs):
        by_vols.setdefault((c.mode, c.approach_volumes), []).append(k)
    for ks in by_vols.values():
        vols = cfgs[ks[0]].approach_volumes
        member = _membership(rows, cfgs[ks[0]])
        if not np.any(member >= 0):
            continue
        inside: dict[int, list[pl.DataFrame]] = {k: [] for k in ks}
        for kv, v in enumerate(vols):
            mask = member == kv
            if mask.sum() >= 2:
                for k, part in zip(ks, _pair_rows(rows.subset(mask), [v.parameters(cfgs[k]) for k in ks], map_)):
                    inside[k].append(part)
        for k in ks:
            outs[k] = _replaced(outs[k], inside[k], rows, member)
    return outs


def _screen_key(cfg: ConflictConfig) -> tuple:
    """Settings with equal keys share one KD-tree screen (same turning rows, same tiers)."""
    return (cfg.mode, cfg.use_turn_rate, cfg.turn_rate_min_dps, cfg.block_points, cfg.bulk_quantile, cfg.v_max_mps)


def _pair_rows(rows: _Rows, cfgs: Sequence[ConflictConfig], map_: Callable[..., Iterable] = map
               ) -> list[pl.DataFrame]:
    """Per setting, the screened pairs of the (established, not coasting) rows with their
    geometry, thresholds and raw decision (``alert`` before confirmation), sorted by (run,
    epoch, method, id_a, id_b). The settings of a :func:`_screen_key` share one screen."""
    tracks = rows.tracks
    if tracks.height < 2:
        return [_empty_conflicts() for _ in cfgs]
    rows.prepare(any(c.threshold_mode == "covariance" for c in cfgs))
    g, ids = rows.group(), rows.ids()
    pos, vel, _, from_alt = rows.state()
    st = np.ascontiguousarray(np.concatenate([pos, vel], axis=1).T)
    setup, taus = [], {}
    for c in cfgs:
        terms = rows.terms() if c.threshold_mode == "covariance" else None
        omega = turn_rates(tracks, c)
        key = (c.mode, c.use_selected_level, c.selected_level_tolerance_m, c.window_s[1])
        if key not in taus:        # one object per distinct level-off input: the vertical test is shared by it
            taus[key] = _track_level_off(tracks, c, pos[:, 2], vel[:, 2], from_alt)
        setup.append((terms, _bounds(c, terms, len(g)), taus[key], omega,
                      None if omega is None else _ArcTable(c, st, omega)))
    chunks: list[list[dict[str, NDArray]]] = [[] for _ in cfgs]
    by_screen: dict[tuple, list[int]] = {}
    for k, c in enumerate(cfgs):
        by_screen.setdefault(_screen_key(c), []).append(k)
    for ks in by_screen.values():
        sc = _union_screen([_screen_of(cfgs[k], setup[k][1]) for k in ks])
        pos_s, vel_s = _screen_states(0.5 * (sc.t0 + sc.t1), pos, vel, setup[ks[0]][3])
        step = min(cfgs[k].chunk_pairs for k in ks)

        def evaluate(k: int, a: NDArray[np.int64], b: NDArray[np.int64], vmin: NDArray[np.float64]
                     ) -> dict[str, NDArray]:
            terms, bnd, tau, _, arcs = setup[k]
            return _evaluate_pairs(cfgs[k], st, terms, a, b, bnd, tau, arcs, vmin)
        for ci, cj in _block_candidates(sc, cfgs[ks[0]].block_points, g, pos_s, vel_s):
            for s in range(0, len(ci), step):
                a, b = ci[s:s + step], cj[s:s + step]
                swap = ids[a] > ids[b]               # order each pair so that id_a < id_b
                a, b = np.where(swap, b, a), np.where(swap, a, b)
                vmins: dict[tuple, NDArray[np.float64]] = {}
                for k in ks:
                    key = (cfgs[k].window_s, id(setup[k][2]))
                    if key not in vmins:
                        vmins[key] = _window_vmin(pos[b, 2] - pos[a, 2], vel[b, 2] - vel[a, 2], vel[:, 2], setup[k][2],
                                                  a, b, *cfgs[k].window_s)
                mins = [vmins[(cfgs[k].window_s, id(setup[k][2]))] for k in ks]
                for k, res in zip(ks, map_(lambda k, v: evaluate(k, a, b, v), ks, mins)):
                    chunks[k].append(res)
            del ci, cj
    return list(map_(lambda k: _assemble(rows, cfgs[k], chunks[k]), range(len(cfgs))))


def _assemble(rows: _Rows, cfg: ConflictConfig, chunks: list[dict[str, NDArray]]) -> pl.DataFrame:
    """The conflicts rows of one setting's evaluated pairs, in (group, id_a, id_b) order."""
    if not chunks or sum(len(c["i"]) for c in chunks) == 0:
        return _empty_conflicts()
    g, ids, tracks = rows.group(), rows.ids(), rows.tracks
    cols = {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}
    i, j = cols.pop("i"), cols.pop("j")
    order = _pair_order(g, ids, i, j)
    i, j = i[order], j[order]
    keys = rows.keys()[i]
    # one polars gather of all value columns (parallel over columns) instead of one numpy take each
    vals = pl.DataFrame([pl.Series("id_a", ids[i]).cast(pl.UInt64), pl.Series("id_b", ids[j]).cast(pl.UInt64)]
                        ).hstack(pl.DataFrame(cols)[order])
    out = keys.hstack(vals)
    if cfg.same_identity_is_duplicate and "mode_s" in tracks.columns:
        ms = tracks["mode_s"].cast(pl.String)
        a, b = ms.gather(i), ms.gather(j)
        dup = (a.is_not_null() & (a == b)).fill_null(False)
        out = out.with_columns(pl.col("alert") & ~pl.Series(dup))
    return out


def _screen_states(tc: float, pos: NDArray[np.float64], vel: NDArray[np.float64],
                   omega: NDArray[np.float64] | None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """States the KD-tree screen places the tracks with: as they are, except turning rows (ω ≠ 0),
    which the screen must find wherever their arc takes them: an arc of length |v|·t stays
    within |v|·t of its start, so such a row is centred at its current position with twice its
    horizontal speed (reach 2|v|·T/2 = |v|·T over the corrected window [0, T], centre ``tc``) —
    conservative."""
    if omega is None:
        return pos, vel
    turn = omega != 0.0
    vel_s = vel.copy()
    vel_s[turn, :2] *= 2.0
    pos_s = pos.copy()
    pos_s[turn, :2] -= vel_s[turn, :2] * tc          # centre pos_s + vel_s·t_c = the current position
    return pos_s, vel_s


def _track_level_off(tracks: pl.DataFrame, cfg: ConflictConfig, h: NDArray[np.float64], hdot: NDArray[np.float64],
                     from_alt: NDArray[np.bool_]) -> NDArray[np.float64] | None:
    """Per row, τ of :func:`level_off_times` from its ``selected_alt_m``, or where it has none its
    ``cleared_alt_m`` (flight data) — corrected mode with ``use_selected_level`` only, and only
    on the barometric channel (``from_alt``: both are pressure altitudes); None when no row
    levels off within the look-ahead."""
    cols = [c for c in (SELECTED_ALT_COLUMN, CLEARED_ALT_COLUMN) if c in tracks.columns]
    if cfg.mode != "corrected" or not cfg.use_selected_level or not cols:
        return None
    # the crew's selection where downlinked, else the controller's clearance (tertiary.stages.flight_data)
    sel = tracks.select(pl.coalesce([pl.col(c).cast(pl.Float64).fill_nan(None) for c in cols])).to_series()
    sel = sel.fill_null(np.nan).to_numpy()
    tau = level_off_times(h, hdot, sel, from_alt, cfg.selected_level_tolerance_m)
    return tau if np.any(tau < cfg.window_s[1]) else None


def slim_conflicts(conflicts: pl.DataFrame, margin_h_m: float | None = None, margin_v_m: float | None = None
                   ) -> pl.DataFrame:
    """The output diet: rows that alert or are *near* — within the near margins of both
    thresholds at the same predicted time (column ``near`` of :func:`predict_conflicts`, with
    the margins of its ``ConflictConfig``). Explicit margins (or a table without ``near``)
    use the stored geometry instead: keep alert | (r_min ≤ r_thr + m_h ∧ dz_min ≤ z_thr + m_v
    ∧ T_min ≤ t_thr)."""
    if margin_h_m is None and margin_v_m is None and "near" in conflicts.columns:
        return conflicts.filter(pl.col("alert") | pl.col("near"))
    mh = NM_M if margin_h_m is None else float(margin_h_m)
    mv = 300.0 * FT_M if margin_v_m is None else float(margin_v_m)
    near = ((pl.col("r_min_m") <= pl.col("r_thr_m") + mh) & (pl.col("dz_min_m") <= pl.col("z_thr_m") + mv)
            & (pl.col("t_min_s") <= pl.col("t_thr_s")))
    return conflicts.filter(pl.col("alert") | near)


def _pair_order(g: NDArray[np.int64], ids: NDArray[np.int64], i: NDArray[np.int64], j: NDArray[np.int64]
                ) -> NDArray[np.int64]:
    """Permutation sorting pairs (i, j) by (group, id_i, id_j) — g is the dense rank of (run, epoch,
    method), so this is the (run, epoch, method, id_a, id_b) order: one stable argsort of a packed
    int64 key (ids as dense ranks), np.lexsort only when the packed key could overflow."""
    uniq, rank = np.unique(ids, return_inverse=True)
    rank = rank.ravel().astype(np.int64)
    m, n_groups = len(uniq), int(g.max()) + 1
    if n_groups * m * m < 1 << 62:
        return np.argsort((g[i] * m + rank[i]) * m + rank[j], kind="stable")
    return np.lexsort((ids[j], ids[i], g[i]))
