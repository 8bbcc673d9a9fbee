"""Centralised measurement-level Kalman filter: a centralised **reference** for fusion.

All radars' **plots** (the measured range, azimuth and elevation of every report — not the
radars' own track estimates) that the association assigned to one system target go, in time
order, into a single Kalman filter per target. Fusion methods that average the radars' track
estimates (stage 5) are compared with this reference: it uses every associated measurement
once with the radars' nominal noise model. It is **not a bound**: it linearises the polar
noise at the measured point, takes the association as given, ignores the Mode C channel in
its state and assumes a Singer model the truth does not follow, so a track-to-track method
can beat it on some figures (e.g. height, where the fused ``alt_m`` channels differ). The
lower bound is the posterior Cramér–Rao bound of :mod:`tertiary.evaluation.bound` (metrics stage
``bound``).

Model
-----
Per Cartesian axis of the system frame (x, y, z) the Singer manoeuvre model of the radars'
own channels (monograph (2.49)–(2.63), tertiary (4.46)): state [p, v, a] per axis, so the
9-state vector is (x, vx, ax, y, vy, ay, z, vz, az) and

    Φ(τ) = blockdiag(φ(τ), φ(τ), φ(τ)),   Q(τ) = blockdiag(q(τ), q(τ), q(τ))        (2.51)/(4.46)

with φ, q from :func:`tertiary.filters.singer.singer_phi` / ``singer_q`` (``variant="printed"``
by default: φ₃₃ = 1 − ατ, D_a = σ_m²(2ατ − α²τ²)).

Measurement: an MLAT / WAM report's Cartesian plot as it is (:mod:`tertiary.sensors.mlat`,
(MLAT-1)–(MLAT-2): z = M z_local + o, R = M R_local Mᵀ, H = [I₃ on the positions]); a radar's
plot converted to Cartesian coordinates, radar polar → radar-local ENU → system ENU (:func:`tertiary.core.geo.polar_to_enu`, :func:`tertiary.core.geo.frame_to_frame`), with
H = [I₃ on the three positions] and the converted covariance

    R = M J R_polar Jᵀ Mᵀ                                       (seed 002 eq. 12)

where R_polar = diag(σ_r², σ_β², σ_ε²) holds the radar's **nominal** sigmas (the elevation
variance comes from the Mode C altitude accuracy when the elevation is derived from altitude,
as in :func:`tertiary.sensors.local_tracks.measurement_polar`), J the polar Jacobian at the measured
point and M the site-to-system rotation. Kalman update (2.10)–(2.14) in Joseph form:

    S = H P⁻ Hᵀ + R,  K = P⁻ Hᵀ S⁻¹,  x⁺ = x⁻ + K (z − H x⁻),
    P⁺ = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ

With ``use_velocity``, a Mode S reply's downlinked ground velocity (:func:`downlinked_velocity`)
is a second measurement at the plot's time, H = [I₂ on vx, vy]. Off by default: the filter then
averages a radar's plots over many scans as if independent, and the radars' residual biases,
which it does not model, make its horizontal covariance too small (national scenario:
horizontal position NEES 4.1 against 2, with the horizontal error 40 m instead of 116 m).

Initiation from the first plot: position = the plot, P_pos = its R; velocity 0 with variance
``v0_sigma_mps``² (then, with ``use_velocity``, the reply's downlinked velocity); acceleration 0 with
variance σ_m² (the stationary Singer variance). Plots of several radars at the same instant are
processed one after another (Φ(0) = I, Q(0) = 0), which equals a stacked joint update.

Output
------
At every requested (run, epoch, target_id) from the target's first plot on: the state
predicted from the last update at or before the epoch to the epoch, in the ``fused`` schema
plus ``tentative`` (below), with ``method = "centralized"``, ``weights = []``, ``radar_ids`` =
the radars whose plots the target has received so far and ``n_sources`` = the number of plots
used since the target's previous output epoch (for the first output epoch: since the start).
Epochs before the target's first plot produce no row.

Confirmation: the reference publishes what a track manager would. ``tentative`` comes first
from the fused pictures' rule and parameter (:func:`tertiary.stages.fusion.confirm.confirm_targets_step`,
``min_plots``) run on the same association rows — each report fresh at its first association
epoch —, and with ``confirmation="three_scan"`` (the default) a target is confirmed only once
three successive scans of its own plots also move like an aircraft, the secondary tracker's
initiation test with its parameters (:mod:`tertiary.stages.fusion.scan_confirm`): a radar's
false local track of a few clutter plots passes the count but not the kinematics, as it would
not pass the trackers' own initiation. Every consumer that leaves tentative rows out
(evaluation, clustering, report) leaves them out of the reference too. An epoch between a
target's reports takes the status reached by then.

Vertical channel: the ``fused`` columns ``alt_m`` … ``alt_cov_m2ps`` from one two-state Mode C
filter per target over all its radars' replies in time order (:mod:`tertiary.stages.tracking.altitude`:
quantum 25 ft with ``mode_s``, 100 ft without, R = q²/12, garble gate), predicted to the epoch
like the state; a target without Mode C falls back to the geodetic height of the filter's
state (its variance along the local vertical) — never the ENU z.

Vectorisation: reports are sorted by (run, target_id, time) and the Python loop runs over the
report rank within a target, with batched (m, 9, 9) linear algebra over the m targets (of all
runs) that have at least that many plots — never a loop per report.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.stages.fusion.config import FusionConfig
from tertiary.stages.fusion.plots import EHS_VELOCITY_COLUMNS, converted_plots, downlinked_velocity
from tertiary.stages.fusion.confirm import ConfirmState, confirm_associations_step, tentative_at
from tertiary.stages.fusion.scan_confirm import ScanState, scans_of, three_scan_step
from tertiary.stages.tracking.altitude import (ALT_COLUMNS, QUANTUM_MODE_C_M, QUANTUM_MODE_S_M, AltitudeConfig, AltState, FilterCarry, filter_tracks_carry, geodetic_channel, predict_combined, quantisation_variance)
from tertiary.filters.singer import Variant, singer_phi, singer_q
from tertiary.stages.tracking.config import TrackerConfig
from tertiary.stages.tracking.gating import downlink_covariance
from tertiary.contract import ADSB_QUALITY_COLUMNS, MLAT_PLOT_COLUMNS, TABLES, TIME

__all__ = ["CentralizedConfig", "centralized_fusion", "centralized_filter", "centralized_filter_carry",
           "CentralizedState", "init_centralized_state", "centralized_step", "transition",
           "METHOD", "POS", "VEL", "STATE6"]

F64 = NDArray[np.float64]

METHOD = "centralized"
#: indices of the positions / velocities in the 9-state (x, vx, ax, y, vy, ay, z, vz, az)
POS = np.array([0, 3, 6])
VEL = np.array([1, 4, 7])
#: 9-state indices of the horizontal velocity (vx, vy): what a downlinked ground velocity measures
HVEL = VEL[:2]
#: 9-state indices of the fused 6-state (x, y, z, vx, vy, vz)
STATE6 = np.concatenate([POS, VEL])
STATE_COLS = ["x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"]
US = 1_000_000
#: the report columns the stage reads
PLOT_COLUMNS = ["run", "report_id", "radar_id", "time", "range_m", "azimuth_deg", "elevation_deg", "altitude_m"]


@dataclass(frozen=True)
class CentralizedConfig:
    """Parameters of the centralised filter (the radars' channel defaults).

    * ``alpha``: Singer inverse manoeuvre time constant α (s⁻¹), 1/30.
    * ``sigma_m``: manoeuvre intensity per Cartesian axis (m/s²), 2.
    * ``variant``: Singer Φ, ``"printed"`` (seed) or ``"exact"``.
    * ``v0_sigma_mps``: initial velocity standard deviation per axis (one-point initiation).
    * ``altitude_sigma_m``: Mode C accuracy used when the elevation is derived from altitude.
    * ``altitude``: the per-target Mode C filter of the vertical channel.
    * ``conversion``: ``"linear"`` (the plot converted as measured) or ``"debiased"``
      (:func:`tertiary.stages.fusion.plots.debias_enu`, the multiplicative unbiased conversion).
    * ``conversion_gate``: ``"reject"`` leaves plots failing the seed 002 (13) validity gate
      (:func:`tertiary.stages.align.conversion_valid`) out of the filter; ``"off"`` uses every plot.
    * ``min_plots``, ``min_plots_primary``: target confirmation (``tentative``), the fused pictures'
      parameters (:class:`tertiary.stages.fusion.config.FusionConfig`); set them alike, or the reference
      publishes other targets than the pictures it is compared with.
    * ``confirmation``: ``"three_scan"``: the plot count and the three-scan test (module
      docstring) with ``v_min_mps``, ``v_max_mps`` and ``confirm_gate_m``, the secondary tracker's
      (:class:`tertiary.stages.tracking.config.TrackerConfig`); ``"plots"``: the count alone.
    * ``use_velocity``: the downlinked ground velocity (BDS 5,0) is measured too (module
      docstring), with σ ``velocity_speed_sigma_mps`` along the track, ``velocity_track_sigma_deg``
      across (the register noise :class:`tertiary.simulate.ehs.EhsConfig` draws), a register up
      to ``velocity_refresh_s`` old (:func:`tertiary.stages.tracking.gating.downlink_covariance`).
    """

    alpha: float = 1.0 / 30.0
    sigma_m: float = 2.0
    variant: Variant = "printed"
    v0_sigma_mps: float = 300.0
    altitude_sigma_m: float = 30.0
    altitude: AltitudeConfig = AltitudeConfig()
    conversion: Literal["linear", "debiased"] = "linear"
    conversion_gate: Literal["off", "reject"] = "off"
    min_plots: int = FusionConfig.min_plots
    min_plots_primary: int = FusionConfig.min_plots_primary
    use_velocity: bool = False
    velocity_speed_sigma_mps: float = 0.5
    velocity_track_sigma_deg: float = 0.2
    velocity_refresh_s: float = TrackerConfig.velocity_refresh_s
    confirmation: Literal["plots", "three_scan"] = "three_scan"
    v_min_mps: float = TrackerConfig.v_min_mps
    v_max_mps: float = TrackerConfig.v_max_mps
    confirm_gate_m: float = TrackerConfig.confirm_gate_m

    def __post_init__(self) -> None:
        if self.min_plots < 1 or self.min_plots_primary < 1:
            raise ValueError(f"min_plots and min_plots_primary must be >= 1, got {self.min_plots}, "
                             f"{self.min_plots_primary}")
        if self.confirmation not in ("plots", "three_scan"):
            raise ValueError(f"confirmation must be 'plots' or 'three_scan', got {self.confirmation!r}")
        if not (0 <= self.v_min_mps < self.v_max_mps and self.confirm_gate_m > 0):
            raise ValueError("need 0 <= v_min_mps < v_max_mps and confirm_gate_m > 0")
        if not (self.velocity_speed_sigma_mps > 0 and self.velocity_track_sigma_deg > 0
                and self.velocity_refresh_s >= 0):          # NaN fails too
            raise ValueError("velocity_speed_sigma_mps and velocity_track_sigma_deg must be > 0, "
                             "velocity_refresh_s >= 0")


# --------------------------------------------------------------------------- model


def _blockdiag3(b: F64) -> F64:
    """(m, 3, 3) per-axis blocks → (m, 9, 9) block-diagonal matrices."""
    out = np.zeros(b.shape[:-2] + (9, 9))
    for a in range(3):
        out[..., 3 * a:3 * a + 3, 3 * a:3 * a + 3] = b
    return out


def transition(tau: F64, cfg: CentralizedConfig) -> tuple[F64, F64]:
    """Φ(τ) and Q(τ), each (m, 9, 9), for the 9-state Singer model (2.51)/(4.46)."""
    tau = np.asarray(tau, dtype=float)
    return (_blockdiag3(singer_phi(tau, cfg.alpha, cfg.variant)),
            _blockdiag3(singer_q(tau, cfg.alpha, cfg.sigma_m, cfg.variant)))


def initial_state(z: F64, r: F64, cfg: CentralizedConfig) -> tuple[F64, F64]:
    """One-point initiation from converted plots z (m, 3), R (m, 3, 3): x (m, 9), P (m, 9, 9)."""
    m = len(z)
    x = np.zeros((m, 9))
    x[:, POS] = z
    p = np.zeros((m, 9, 9))
    p[:, POS[:, None], POS[None, :]] = r
    p[:, VEL, VEL] = cfg.v0_sigma_mps ** 2
    p[:, POS + 2, POS + 2] = cfg.sigma_m ** 2
    return x, p


def _abat(a: F64, b: F64) -> F64:
    """A B Aᵀ for stacks of small matrices (two batched matmuls: faster than einsum here)."""
    return a @ b @ a.swapaxes(-1, -2)


# flat indices (row-major 3×3) of the cofactors c00, c01, c02, c11, c12, c22 of a symmetric
# matrix, c_ij = s[A] s[B] − s[C] s[D], read from its upper triangle
_COF = np.array([[4, 8, 5, 5], [2, 5, 1, 8], [1, 5, 2, 4], [0, 8, 2, 2], [1, 2, 0, 5], [0, 4, 1, 1]]).T
_ADJ = np.array([0, 1, 2, 1, 3, 4, 2, 4, 5])             # cofactor of each of the 9 entries


def _inv3_sym(s: F64) -> F64:
    """Inverse of symmetric 3×3 matrices (m, 3, 3) by the adjugate (cofactors / determinant),
    from their upper triangle; a few vector operations over all m matrices at once."""
    f = s.reshape(-1, 9)
    cof = f[:, _COF[0]] * f[:, _COF[1]] - f[:, _COF[2]] * f[:, _COF[3]]
    det = (f[:, :3] * cof[:, :3]).sum(axis=1)
    return (cof[:, _ADJ] / det[:, None]).reshape(-1, 3, 3)


def _update(x: F64, p: F64, z: F64, r: F64, h: NDArray[np.int64] = POS) -> tuple[F64, F64]:
    """Batched Kalman update (2.10)–(2.14), Joseph form, H = the 9-state's components ``h``
    (the positions; :data:`HVEL` for a downlinked velocity).

    The products with I − K H use the sparsity of H (only the ``h`` columns of K H are
    non-zero): (I − K H) P = P − K (H P), then A (I − K H)ᵀ = A − (A Hᵀ) Kᵀ."""
    ph = p[:, :, h]                                     # P Hᵀ  (m, 9, len(h))
    s = ph[:, h, :] + r                                 # H P Hᵀ + R
    k = ph @ (_inv3_sym(s) if len(h) == 3 else np.linalg.inv(s))   # P Hᵀ S⁻¹
    x = x + (k @ (z - x[:, h])[:, :, None])[:, :, 0]
    a = p - k @ p[:, h, :]
    # A (I − K H)ᵀ + K R Kᵀ = A − (A Hᵀ − K R) Kᵀ: one product with Kᵀ instead of two
    return x, a - (a[:, :, h] - k @ r) @ k.swapaxes(1, 2)


def centralized_filter(t: F64, z: F64, r: F64, starts: NDArray[np.int64], lengths: NDArray[np.int64],
                       cfg: CentralizedConfig = CentralizedConfig(), keep: NDArray[np.bool_] | None = None,
                       vel: tuple[F64, F64] | None = None) -> tuple[F64, F64]:
    """Run the filter over every target's plot sequence.

    ``t`` (n,) seconds, ``z`` (n, 3) converted plots and ``r`` (n, 3, 3) their covariances,
    sorted so that target g owns rows ``starts[g] : starts[g] + lengths[g]`` in time order;
    ``vel``: each row's downlinked horizontal velocity (n, 2) and its covariance (n, 2, 2), NaN
    where the report has none, a second update at the plot's time (Φ(0) = I, as a joint one).
    Returns the updated state (n_keep, 9) and covariance (n_keep, 9, 9) after each kept row
    (``keep`` mask; all rows by default), in row order.
    """
    out_x, out_p, _ = centralized_filter_carry(t, z, r, starts, lengths, cfg, keep, vel=vel)
    return out_x, out_p


def centralized_filter_carry(t: F64, z: F64, r: F64, starts: NDArray[np.int64], lengths: NDArray[np.int64],
                             cfg: CentralizedConfig = CentralizedConfig(), keep: NDArray[np.bool_] | None = None,
                             init: tuple[F64, F64, F64] | None = None, vel: tuple[F64, F64] | None = None
                             ) -> tuple[F64, F64, tuple[F64, F64, F64]]:
    """:func:`centralized_filter` continued from ``init`` = (x (G, 9), P (G, 9, 9), t_last (G,))
    per target (t_last NaN: a target never updated, initiated from its first plot; ``t`` on the
    same time base), also returning each target's (x, P, t_last) after its last plot. A
    carried target's first plot is a predict (Φ, Q over t − t_last) + update, exactly as the
    next plot of a one-call run."""
    has_v = (np.zeros(len(t), bool) if vel is None
             else np.isfinite(vel[0]).all(axis=1) & np.isfinite(vel[1]).all(axis=(1, 2)))
    n = len(t)
    keep = np.ones(n, dtype=bool) if keep is None else np.asarray(keep, dtype=bool)
    slot = np.full(n, -1)
    slot[keep] = np.arange(int(keep.sum()))
    out_x = np.full((int(keep.sum()), 9), np.nan)
    out_p = np.full((int(keep.sum()), 9, 9), np.nan)
    order = np.argsort(-np.asarray(lengths), kind="stable")
    st, ln = np.asarray(starts)[order], np.asarray(lengths)[order]
    n_targets = len(st)
    x = np.zeros((n_targets, 9))
    p = np.zeros((n_targets, 9, 9))
    t = np.asarray(t, dtype=float)
    t_prev = np.full(n_targets, np.nan) if init is None else np.asarray(init[2], float)[order]
    carried = np.isfinite(t_prev)
    # every row's per-axis Φ(τ), Q(τ) from the target's previous plot, in one call (rows
    # starting a new target get τ = 0 and are never read; a carried target's first row gets
    # τ from its last update in an earlier call)
    tau = np.zeros(n)
    tau[1:] = np.diff(t)
    tau[st[carried]] = t[st[carried]] - t_prev[carried]
    phi3 = singer_phi(tau, cfg.alpha, cfg.variant)
    q3 = singer_q(tau, cfg.alpha, cfg.sigma_m, cfg.variant)
    if init is not None:
        x[carried], p[carried] = np.asarray(init[0])[order][carried], np.asarray(init[1])[order][carried]
    # lengths sorted descending: the targets with more than k plots are a prefix
    alive = np.searchsorted(-ln, -np.arange(ln.max(initial=0)), side="left")
    for k, m in enumerate(alive):
        idx = st[:m] + k
        if k == 0:
            xs, ps = initial_state(z[idx], r[idx], cfg)
            go = np.flatnonzero(carried[:m])
        else:
            go = np.arange(m)
        if go.size:
            sel = idx[go]
            phi = _blockdiag3(phi3[sel])
            xg = (phi @ x[go, :, None])[:, :, 0]
            pg = _abat(phi, p[go])
            qk = q3[sel]
            for a in range(3):                          # Q is block-diagonal: add the blocks
                pg[:, 3 * a:3 * a + 3, 3 * a:3 * a + 3] += qk
            xg, pg = _update(xg, pg, z[sel], r[sel])
            if k == 0:
                xs[go], ps[go] = xg, pg
            else:
                xs, ps = xg, pg
        hv = has_v[idx]
        if hv.any():        # the downlinked velocity, after the plot of the same reply
            xs[hv], ps[hv] = _update(xs[hv], ps[hv], vel[0][idx[hv]], vel[1][idx[hv]], HVEL)
        x[:m], p[:m] = xs, ps
        sl = slot[idx]
        hit = sl >= 0
        out_x[sl[hit]], out_p[sl[hit]] = xs[hit], ps[hit]
    t_last = np.where(ln > 0, t[np.maximum(st + ln - 1, 0)] if n else t_prev, t_prev)
    inv = np.empty_like(order)
    inv[order] = np.arange(n_targets)
    return out_x, out_p, (x[inv], p[inv], t_last[inv])


# --------------------------------------------------------------------------- plots


def _downlinks(reports: pl.DataFrame, z: F64, origin: geo.LocalFrame, cfg: CentralizedConfig
               ) -> tuple[F64, F64] | None:
    """Each report's downlinked horizontal velocity (n, 2) in the system frame and its
    covariance (n, 2, 2) (:func:`downlink_covariance`), NaN where it has none; None when no
    report has one."""
    if "ehs_gs_mps" not in reports.columns:
        return None
    v = downlinked_velocity(reports, z, origin)
    ok = np.isfinite(v[:, :2]).all(axis=1)
    if not ok.any():
        return None
    r = np.full((len(v), 2, 2), np.nan)
    r[ok] = downlink_covariance(v[ok, :2], v[ok, 2], cfg.velocity_speed_sigma_mps, cfg.velocity_track_sigma_deg,
                                cfg.velocity_refresh_s)
    return v[:, :2], r


# --------------------------------------------------------------------------- stage


def _first_association(associations: pl.DataFrame) -> pl.DataFrame:
    """report → target (and ``__epoch``) at each report's first association epoch."""
    return (associations.select(pl.col("run").cast(pl.UInt32), pl.col("report_id").cast(pl.UInt64),
                                pl.col("target_id").cast(pl.UInt64), pl.col("epoch").cast(TIME))
            .sort("epoch").unique(subset=["run", "report_id"], keep="first", maintain_order=True)
            .rename({"epoch": "__epoch"}))


#: the output: the ``fused`` columns and, as the fusion stage adds it, ``tentative``
_SCHEMA = {**TABLES["fused"].columns, "tentative": pl.Boolean}


def _empty_fused() -> pl.DataFrame:
    return pl.DataFrame(schema=_SCHEMA)


def _predict_to_epochs(x_post: F64, p_post: F64, src: NDArray[np.int64], tau: F64, cfg: CentralizedConfig,
                       block: int = 32_768) -> tuple[F64, F64]:
    """Each output row's last update predicted by ``tau`` to its epoch, as the 6-state and its
    flattened 6×6 covariance; in blocks, so the 9×9 temporaries stay small."""
    m = len(src)
    state, cov6 = np.empty((m, 6)), np.empty((m, 36))
    for lo in range(0, m, block):
        sl = slice(lo, min(lo + block, m))
        phi, q = transition(tau[sl], cfg)
        xe = np.einsum("mij,mj->mi", phi, x_post[src[sl]])
        pe = _abat(phi, p_post[src[sl]]) + q
        state[sl] = xe[:, STATE6]
        cov6[sl] = pe[:, STATE6[:, None], STATE6[None, :]].reshape(-1, 36)
    return state, cov6


@dataclass(frozen=True)
class CentralizedState:
    """Everything :func:`centralized_step` carries between windows (natural keys only):

    * ``targets``: per (run, target_id) with at least one plot: the filter after its last plot
      (``x`` 9, ``p`` 81 row-major, ``t_last`` s on the ``ref_us`` base), ``n_plots`` (plots
      used so far), ``cum_out`` (plots used up to the target's last output epoch: the base of
      ``n_sources``), the Mode C filter (:class:`~tertiary.stages.tracking.altitude.FilterCarry` ``af_*``
      columns, with its output after the last reply);
    * ``radars``: (run, target_id, radar_id) whose plots the target has received;
    * ``last_ids``: (run, report_id) associated at ``last_epoch_us``, the latest association
      epoch seen — a report held into the next window is one of them (its association rows are
      consecutive epochs), so it is not taken as new there;
    * ``ref_us``: the time base of the filters (the first plot time ever used), so times are the
      same floats as in one whole-run call; ``reached_us``: the end of the last window;
    * ``confirm``: target confirmation (:class:`~tertiary.stages.fusion.confirm.ConfirmState`);
      ``scan``: the three-scan test's (:class:`~tertiary.stages.fusion.scan_confirm.ScanState`).

    ``targets``/``radars`` and the confirmed targets keep one row per target seen, or, with
    :func:`centralized_step`'s ``live``, per target that may still be associated."""

    targets: pl.DataFrame | None
    radars: pl.DataFrame
    last_ids: pl.DataFrame
    last_epoch_us: int | None = None
    ref_us: int | None = None
    reached_us: int | None = None
    confirm: ConfirmState = field(default_factory=ConfirmState.empty)
    scan: ScanState = field(default_factory=ScanState.empty)


def init_centralized_state() -> CentralizedState:
    """The state before the first window."""
    return CentralizedState(None, pl.DataFrame(schema={"run": pl.UInt32, "target_id": pl.UInt64,
                                                       "radar_id": pl.UInt32}),
                            pl.DataFrame(schema={"run": pl.UInt32, "report_id": pl.UInt64}))


def centralized_fusion(reports: pl.DataFrame, radars: pl.DataFrame, associations: pl.DataFrame,
                       epochs: pl.DataFrame, origin: geo.LocalFrame,
                       cfg: CentralizedConfig = CentralizedConfig()) -> pl.DataFrame:
    """Centralised measurement-level Kalman filter (a reference, not a bound) of every associated
    target (module docstring).

    ``reports``: plots with ``report_id``, ``radar_id``, ``time``, ``range_m``, ``azimuth_deg``
    and ``elevation_deg`` and/or ``altitude_m`` (``run`` defaults to 0); ``associations``: the
    association table (report_id → target_id; a report associated at several epochs counts at
    its first); ``epochs``: any frame with (run, epoch, target_id) — e.g. ``fused`` — at which
    to output; ``origin``: the system frame. Returns rows in the ``fused`` schema plus
    ``tentative``, method ``"centralized"``, sorted by (run, epoch, target_id). The whole run as
    one window of :func:`centralized_step`.
    """
    return centralized_step(init_centralized_state(), reports, radars, associations, epochs, origin, cfg)[0]


def _new_associations(state: CentralizedState, associations: pl.DataFrame
                      ) -> tuple[pl.DataFrame, pl.DataFrame, int | None]:
    """The window's association rows of reports not associated before it, and the new
    (last_ids, last_epoch_us)."""
    a = associations.select(pl.col("run").cast(pl.UInt32), pl.col("report_id").cast(pl.UInt64),
                            pl.col("target_id").cast(pl.UInt64), pl.col("epoch").cast(TIME))
    if a.is_empty():
        return a, state.last_ids, state.last_epoch_us
    new = a.join(state.last_ids, on=["run", "report_id"], how="anti")
    last = a["epoch"].max()
    last_ids = a.filter(pl.col("epoch") == last).select("run", "report_id").unique()
    return new, last_ids, int(a["epoch"].dt.epoch("us").max())


def _carry_frame(state: CentralizedState, keys: pl.DataFrame) -> pl.DataFrame:
    """``keys`` (run, target_id) joined to the carried targets (null columns where not carried)."""
    if state.targets is None:
        return keys
    return keys.join(state.targets, on=["run", "target_id"], how="left", maintain_order="left")


def centralized_step(state: CentralizedState, reports_window: pl.DataFrame, radars: pl.DataFrame,
                     associations_window: pl.DataFrame, keys_window: pl.DataFrame, origin: geo.LocalFrame,
                     cfg: CentralizedConfig = CentralizedConfig(), t0_us: int | None = None,
                     t1_us: int | None = None, live: pl.DataFrame | None = None
                     ) -> tuple[pl.DataFrame, CentralizedState]:
    """:func:`centralized_fusion` of one time window [``t0_us``, ``t1_us``) (µs since the Unix
    epoch; None = unbounded), carrying every target's filters in ``state``.

    ``live``: (run, target_id) of the targets that may still be associated after this window
    (:meth:`tertiary.stages.association.associate.AssociateState.live_targets`); the returned state keeps only
    them, so it is bounded by the traffic of a window, not by the recording (otherwise it would
    hold every target ever seen). A target outside it can never reach this step again, so the outputs do not
    change. None keeps every target.

    ``associations_window``: the association rows with epoch in the window (every aligned
    row's, as :func:`tertiary.stages.association.associate.associate` returns them; target
    confirmation counts them as the fusion stage counts its rows); ``keys_window``: the (run,
    epoch, target_id) to output, epochs in the window; ``reports_window``: (at least) the
    reports first associated in the window — a report's first association is its first epoch,
    so the reports with time in [t0_us − epoch period − max collection delay, t1_us) suffice;
    others are ignored. Stepping a run's windows in order and concatenating the outputs gives
    :func:`centralized_fusion` of the whole run, provided every plot of a target arrives after
    the target's earlier plots (true without collection delays: a report's first epoch is the
    first at or after its time). A late plot (older than the target's last update, possible
    with collection delays) is filtered at the time of that update (τ clipped to 0), and the
    whole-run call, which sorts by time, may already use it at epochs before it was available.
    The state passed in is not modified."""
    out, new = _centralized_step(state, reports_window, radars, associations_window, keys_window, origin, cfg,
                                 t0_us, t1_us)
    if live is not None:
        keys = live.select(pl.col("run").cast(pl.UInt32), pl.col("target_id").cast(pl.UInt64)).unique()
        new = replace(new, radars=new.radars.join(keys, on=["run", "target_id"], how="semi", maintain_order="left"),
                      targets=None if new.targets is None else
                      new.targets.join(keys, on=["run", "target_id"], how="semi", maintain_order="left"),
                      confirm=replace(new.confirm, targets=new.confirm.targets.join(
                          keys, on=["run", "target_id"], how="semi", maintain_order="left")),
                      scan=new.scan.keep(keys))
    return out, new


def _centralized_step(state: CentralizedState, reports_window: pl.DataFrame, radars: pl.DataFrame,
                      associations_window: pl.DataFrame, keys_window: pl.DataFrame, origin: geo.LocalFrame,
                      cfg: CentralizedConfig, t0_us: int | None, t1_us: int | None
                      ) -> tuple[pl.DataFrame, CentralizedState]:
    reached = t1_us if t1_us is not None else state.reached_us
    if keys_window.height and (t0_us is not None or t1_us is not None):
        e = keys_window["epoch"].cast(TIME).dt.epoch("us")
        if (t0_us is not None and e.min() < t0_us) or (t1_us is not None and e.max() >= t1_us):
            raise ValueError(f"centralized_step: keys_window has epochs outside [{t0_us}, {t1_us}) µs")
    assoc, last_ids, last_epoch = _new_associations(state, associations_window)
    rep = reports_window if "run" in reports_window.columns else reports_window.with_columns(
        pl.lit(0, pl.UInt32).alias("run"))
    rep = rep.select(c for c in [*PLOT_COLUMNS, *MLAT_PLOT_COLUMNS, *ADSB_QUALITY_COLUMNS, "mode_s",
                                 *(EHS_VELOCITY_COLUMNS if cfg.use_velocity else ())]
                     if c in rep.columns)  # not the wide track columns
    rep = rep.with_columns(pl.col("run").cast(pl.UInt32), pl.col("report_id").cast(pl.UInt64),
                           pl.col("time").cast(TIME))
    groups, confirm = confirm_associations_step(state.confirm, associations_window, assoc, rep, cfg.min_plots,
                                                cfg.min_plots_primary)
    base = replace(state, last_ids=last_ids, last_epoch_us=last_epoch, reached_us=reached, confirm=confirm)
    rep = rep.join(_first_association(assoc), on=["run", "report_id"], how="inner")
    z, r, ok = converted_plots(rep, radars, origin, cfg.altitude_sigma_m, conversion=cfg.conversion,
                               gate=cfg.conversion_gate == "reject")
    vel = _downlinks(rep, z, origin, cfg) if cfg.use_velocity else None
    scan_groups, scan = _scan_confirmation(state.scan, rep, z, ok, cfg)
    base = replace(base, scan=scan)
    rep = rep.with_columns(pl.Series("__ok", ok))
    alt_cols = [c for c in ("altitude_m", "mode_s") if c in rep.columns]
    rep = (rep.select("run", "target_id", "time", "radar_id", "report_id", "__ok", *alt_cols)
           .with_columns(pl.int_range(pl.len()).alias("__pos")).filter(pl.col("__ok"))
           .sort(["run", "target_id", "time", "radar_id", "report_id"]))
    if rep.is_empty() and (state.targets is None or keys_window.is_empty()):
        return _empty_fused(), base                     # nothing filtered, nothing to output
    pos = rep["__pos"].to_numpy()
    z, r = z[pos], r[pos]
    vel = None if vel is None else (vel[0][pos], vel[1][pos])
    n = rep.height
    t_us = rep["time"].dt.epoch("us").to_numpy()
    ref = state.ref_us if state.ref_us is not None else int(t_us.min())
    t = (t_us - ref) * 1e-6

    keys = rep.select("run", "target_id").to_numpy()
    new = np.ones(n, dtype=bool)
    new[1:] = np.any(keys[1:] != keys[:-1], axis=1)
    starts = np.flatnonzero(new)
    lengths = np.diff(np.append(starts, n))
    group_start = np.repeat(starts, lengths)
    tgt = rep[starts].select("run", "target_id")
    carry = _carry_frame(state, tgt)
    n_prev = carry["n_plots"].fill_null(0).to_numpy() if "n_plots" in carry.columns else np.zeros(len(tgt), np.int64)

    # the last report at or before each requested epoch (one row per report time)
    rep = rep.with_columns(pl.int_range(pl.len(), dtype=pl.Int64).alias("__ri"),
                           pl.Series("__start", group_start, dtype=pl.Int64),
                           pl.Series("__base", np.repeat(n_prev, lengths), dtype=pl.Int64))
    last = (rep.group_by(["run", "target_id", "time"]).agg(pl.col("__ri").max(), pl.col("__start").first(),
                                                           pl.col("__base").first())
            .sort("time"))
    want = (keys_window.select(pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME),
                               pl.col("target_id").cast(pl.UInt64)).unique()
            .sort("epoch"))
    want = want.join_asof(last, left_on="epoch", right_on="time", by=["run", "target_id"],
                          strategy="backward", check_sortedness=False)
    old = state.targets
    old_cols = ["n_plots", "cum_out"]
    want = (want.join(old.select("run", "target_id", *old_cols), on=["run", "target_id"], how="left")
            if old is not None else want.with_columns(pl.lit(None, pl.Int64).alias(c) for c in old_cols))
    # plots used up to each epoch (this window's plus the carried count); n_sources = its increase
    # since the target's previous output epoch (carried across windows in cum_out)
    want = want.sort(["run", "target_id", "epoch"]).with_columns(
        pl.coalesce(pl.col("__ri") - pl.col("__start") + 1 + pl.col("__base"), pl.col("n_plots"), pl.lit(0))
        .cast(pl.Int64).alias("__cum"))
    want = want.with_columns(pl.col("__cum").shift(1).over(["run", "target_id"])
                             .fill_null(pl.col("cum_out").fill_null(0)).alias("__prev"))
    cum_out = want.group_by(["run", "target_id"]).agg(pl.col("__cum").last().alias("__cum_out"))
    want = want.filter(pl.col("__cum") > 0).with_columns((pl.col("__cum") - pl.col("__prev")).alias("n_sources"))
    want = want.select("run", "epoch", "target_id", "n_sources", "__ri").sort(["run", "epoch", "target_id"])

    from_win = want["__ri"].is_not_null().to_numpy()
    ri = want["__ri"].fill_null(0).to_numpy().astype(np.int64)
    keep = np.zeros(n, dtype=bool)
    keep[ri[from_win]] = True
    init = None
    if old is not None and n:
        was = carry["t_last"].is_not_null().to_numpy()
        x0, p0 = np.full((n_tg := carry.height, 9), np.nan), np.full((n_tg, 81), np.nan)
        if was.any():
            x0[was] = np.stack(carry.filter(pl.Series(was))["x"].to_numpy())
            p0[was] = np.stack(carry.filter(pl.Series(was))["p"].to_numpy())
        init = (x0, p0.reshape(-1, 9, 9), carry["t_last"].fill_null(np.nan).to_numpy())
    x_post, p_post, (x_end, p_end, t_end) = centralized_filter_carry(t, z, r, starts, lengths, cfg, keep, init, vel)
    slot = np.cumsum(keep) - 1

    # output rows whose last plot is an earlier window's: the carried filter of their target
    held = want.filter(pl.col("__ri").is_null()).select("run", "target_id")
    src = np.where(from_win, slot[ri] if n else 0, 0)
    t_src = np.where(from_win, t[ri] if n else 0.0, 0.0)
    if (~from_win).any():
        hc = held.join(old, on=["run", "target_id"], how="left", maintain_order="left")
        hx = np.stack(hc["x"].to_numpy())
        hp = np.stack(hc["p"].to_numpy()).reshape(-1, 9, 9)
        src[~from_win] = len(x_post) + np.arange(held.height)
        t_src[~from_win] = hc["t_last"].to_numpy()
        x_post, p_post = np.concatenate([x_post, hx]), np.concatenate([p_post, hp])
    tau = (want["epoch"].dt.epoch("us").to_numpy() - ref) * 1e-6 - t_src
    state6, cov6 = _predict_to_epochs(x_post, p_post, src, tau, cfg)
    alt, alt_end = _vertical_step(rep, t, starts, lengths, ri, from_win, held, old, tau, state6, cov6,
                                  origin, cfg.altitude, carry)

    targets = _new_targets(old, tgt, x_end, p_end, t_end, n_prev + lengths, alt_end, cum_out)
    seen = (rep.group_by(["run", "target_id", "radar_id"]).agg(pl.col("time").min().alias("__first")))
    radar_ids = (want.select("run", "target_id", "epoch").join(seen, on=["run", "target_id"], how="inner")
                 .filter(pl.col("__first") <= pl.col("epoch")).select("run", "target_id", "epoch", "radar_id"))
    # a carried radar's first plot precedes the window, hence every epoch in it
    carried_r = want.select("run", "target_id", "epoch").join(state.radars, on=["run", "target_id"], how="inner")
    radar_ids = (pl.concat([radar_ids, carried_r.select(radar_ids.columns)]).unique()
                 .group_by(["run", "target_id", "epoch"]).agg(pl.col("radar_id").sort().alias("radar_ids")))
    radars_seen = pl.concat([state.radars, seen.select("run", "target_id", "radar_id")]).unique(maintain_order=True)
    new_state = replace(base, targets=targets, radars=radars_seen, ref_us=ref if (n or state.ref_us is not None)
                        else None)
    if want.is_empty():
        return _empty_fused(), new_state
    out = want.select("run", "epoch", "target_id", "n_sources").with_columns(
        pl.lit(METHOD).alias("method"),
        *[pl.Series(c, state6[:, i]) for i, c in enumerate(STATE_COLS)],
        pl.Series("cov", cov6, dtype=pl.Array(pl.Float64, 36)),
        pl.lit([], dtype=pl.List(pl.Float64)).alias("weights"),
        *(pl.Series(c, alt[c]) for c in ALT_COLUMNS),
        _tentative(state, groups, scan_groups, want),
    ).join(radar_ids, on=["run", "target_id", "epoch"], how="left", maintain_order="left")
    return out.select([pl.col(c).cast(tp) for c, tp in _SCHEMA.items()]), new_state  # `want` is in output order


def _scan_confirmation(before: ScanState, rep: pl.DataFrame, z: F64, ok: NDArray[np.bool_], cfg: CentralizedConfig
                       ) -> tuple[pl.DataFrame | None, ScanState]:
    """The three-scan test's groups and state on the window's plots (None: not asked for)."""
    if cfg.confirmation != "three_scan":
        return None, before
    plots = (rep.select("run", "target_id", pl.col("__epoch").alias("epoch"), "time", "radar_id", "report_id")
             .with_columns(pl.Series("x", z[:, 0]), pl.Series("y", z[:, 1])).filter(pl.Series(ok)))
    return three_scan_step(before, scans_of(plots), cfg.v_min_mps, cfg.v_max_mps, cfg.confirm_gate_m)


def _tentative(before: CentralizedState, groups: pl.DataFrame, scan_groups: pl.DataFrame | None,
               keys: pl.DataFrame) -> pl.Series:
    """``tentative`` at the output ``keys``: until the plot count and, if asked for, the three-scan
    test have both confirmed the target."""
    count = tentative_at(before.confirm.targets, groups, keys)
    return count if scan_groups is None else count | tentative_at(before.scan.targets, scan_groups, keys)


def _vertical_step(rep: pl.DataFrame, t: F64, starts: NDArray[np.int64], lengths: NDArray[np.int64],
                   ri: NDArray[np.int64], from_win: NDArray[np.bool_], held: pl.DataFrame, old: pl.DataFrame | None,
                   tau: F64, state: F64, cov6: F64, origin: geo.LocalFrame, cfg: AltitudeConfig,
                   carry: pl.DataFrame) -> tuple[dict[str, F64], FilterCarry | None]:
    """Vertical channel of each output row (module docstring): the target's Mode C filter after
    its last plot (row ``ri`` of this window, or the carried filter's output for the ``held``
    rows) predicted by ``tau``, else the geodetic height of the 6-state; and the filters' end
    state per target of ``rep`` (None without Mode C)."""
    fb = geodetic_channel(state, cov6.reshape(-1, 6, 6), origin).columns()
    if "altitude_m" not in rep.columns:
        return fb, None
    post_cols, has_rows = {c: np.full(len(ri), np.nan) for c in _FIELDS}, np.zeros(len(ri), bool)
    mu_rows = np.full(len(ri), np.nan)
    end = None
    if rep.height:
        z = rep["altitude_m"].cast(pl.Float64).fill_null(np.nan).to_numpy()
        mode_s = rep["mode_s"].is_not_null().to_numpy() if "mode_s" in rep.columns else np.ones(len(z), bool)
        var = quantisation_variance(np.where(mode_s, QUANTUM_MODE_S_M, QUANTUM_MODE_C_M))
        default = FilterCarry.fresh(1, cfg).columns()
        init = FilterCarry.from_columns({c: (carry[c].fill_null(v[0]).to_numpy() if c in carry.columns
                                             else np.repeat(v, carry.height)) for c, v in default.items()}, cfg)
        post, has, _, end, mu = filter_tracks_carry(t, z, var, starts, lengths, cfg, init=init, with_mu=True)
        w = ri[from_win]
        for f in _FIELDS:
            post_cols[f][from_win] = getattr(post, f)[w]
        has_rows[from_win] = has[w]
        mu_rows[from_win] = mu[w]
    if (~from_win).any() and old is not None and "af_has" in old.columns:
        hc = held.join(old, on=["run", "target_id"], how="left", maintain_order="left")
        for f in _FIELDS:
            post_cols[f][~from_win] = hc[f"af_post_{f}"].fill_null(np.nan).to_numpy()
        has_rows[~from_win] = hc["af_has"].fill_null(False).to_numpy()
        last_mu = sorted(c for c in hc.columns if c.startswith("af_mu"))[-1]
        mu_rows[~from_win] = hc[last_mu].cast(pl.Float64).fill_null(np.nan).to_numpy()
    # the IMM's combined estimate extrapolated with its mode-weighted q (vertical.py, same reason)
    mc = predict_combined(AltState(*(post_cols[f] for f in _FIELDS)), tau, mu_rows, cfg).columns()
    return {c: np.where(has_rows, mc[c], fb[c]) for c in ALT_COLUMNS}, end


_FIELDS = ("h", "r", "phh", "phr", "prr")


def _new_targets(old: pl.DataFrame | None, tgt: pl.DataFrame, x: F64, p: F64, t_last: F64, n_plots: NDArray,
                 alt: FilterCarry | None, cum_out: pl.DataFrame) -> pl.DataFrame | None:
    """The carried targets with this window's filtered targets replaced, and ``cum_out`` updated
    for the targets output in this window."""
    now = tgt.with_columns(pl.Series("x", x, dtype=pl.Array(pl.Float64, 9)),
                           pl.Series("p", p.reshape(-1, 81), dtype=pl.Array(pl.Float64, 81)),
                           pl.Series("t_last", t_last), pl.Series("n_plots", n_plots, dtype=pl.Int64))
    if alt is not None:
        now = now.with_columns(pl.Series(c, v) for c, v in alt.columns().items())
    keep_cum = old.select("run", "target_id", "cum_out") if old is not None else None
    if old is not None:
        now = pl.concat([old.drop("cum_out").join(now, on=["run", "target_id"], how="anti"), now],
                        how="diagonal_relaxed")
    elif tgt.is_empty():
        return None
    now = now.join(keep_cum, on=["run", "target_id"], how="left") if keep_cum is not None else now
    now = now.join(cum_out, on=["run", "target_id"], how="left").with_columns(
        pl.coalesce("__cum_out", *(["cum_out"] if "cum_out" in now.columns else []), pl.lit(0))
        .cast(pl.Int64).alias("cum_out")).drop("__cum_out")
    return now
