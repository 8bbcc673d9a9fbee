"""Mode S enhanced-surveillance (EHS) parameters a radar extracts from a transponder.

The monograph's chapter 3 range channels take onboard parameters "sent over the discrete-address
datalink". A real Mode S radar gets them by Comm-B extraction of the EHS registers; this module
simulates those replies from the aircraft's own state (truth is used only to generate what the
aircraft's navigation system would put in its registers, as a real transponder does):

BDS 5,0 (track and turn report) and BDS 6,0 (heading and speed report), ICAO Doc 9871 / Annex 10:

==================  ===========  ===================  ===============  =======================
parameter           register     LSB (resolution)     range            sensor noise σ (chosen)
==================  ===========  ===================  ===============  =======================
roll angle          BDS 5,0      45/256° ≈ 0.176°     ±90°             0.3°  (AHRS/IRS attitude)
true track angle    BDS 5,0      90/512° ≈ 0.176°     ±180°            0.2°  (GNSS/IRS track at
                                                                              100–300 m/s)
ground speed        BDS 5,0      2 kt ≈ 1.03 m/s      0–2046 kt        0.5 m/s (GNSS velocity)
track angle rate    BDS 5,0      8/256 °/s            ±16 °/s          0.05 °/s
inertial vert. rate BDS 6,0      32 ft/min ≈ 0.16 m/s ±16 352 ft/min   0.3 m/s (hybrid IRS/baro)
==================  ===========  ===================  ===============  =======================

BDS 4,0 (selected vertical intention): the MCP/FCU selected altitude, 16 ft LSB, 0–65 520 ft
(12 bits), reported as ``selected_alt_m`` (:data:`SELECTED_ALT_COLUMN`) in the pressure-altitude
reference of ``altitude_m``. It is the level the crew selected at the reply time — the
aircraft's clearance as the traffic generator flies it, changed where the crew's procedure
changes it (an arrival's missed-approach altitude once on the glide path;
:class:`tertiary.simulate.traffic.base.TrafficTrajectories`; level busts: the wrong level selected,
see there), never a value read off the future trajectory — quantised, without noise (a setting, not a measurement). Null without a decoded
Mode S reply, for aircraft that do not downlink it (non-EHS, or a trajectory source without
intent: big box, ADS-B) and for a fraction ``selected_alt_missing`` of replies (the
register not extracted that scan).

Values are rounded to the nearest LSB and clipped to the field's range, after adding the
sensor noise (white, per reply: a simplification — real navigation errors are correlated over
seconds; the quantisation dominates at these resolutions anyway). Optional register staleness:
``refresh_s`` > 0 holds each register at the value of the last onboard refresh (a per-aircraft
phase, a golden-ratio fraction of its identity), as a register updated every ~1 s read by a faster
interrogator.

Roll angle is that of a coordinated turn (tan γ = V_h χ̇ / g: the simulator flies coordinated
turns); the track-angle rate χ̇ and the accelerations come from the trajectory's velocity by a
central difference over ±dt/2. The velocity is the trajectory's samples interpolated linearly
(the navigation system's own velocity; for ADS-B truth the aircraft's reported velocity), so on
the generators' constant-rate arcs the rate is sin(ω dt)/dt, within 0.2 % of ω up to 6 °/s at
dt = 1 s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl
from numpy.typing import ArrayLike, NDArray

from tertiary.core import geo
from tertiary.core.errors import DataError
from tertiary.core.units import FT, G0, US
from tertiary.contract import EHS_REPORT_COLUMNS
from tertiary.simulate.trajectory import Trajectories

F64 = NDArray[np.float64]
KT = 1852.0 / 3600.0
FPM = FT / 60.0

#: (LSB, lower, upper) of each EHS field, in the table's units
RESOLUTION = {
    "ground_speed_mps": (2.0 * KT, 0.0, 2046.0 * KT),
    "true_track_deg": (90.0 / 512.0, -180.0, 180.0),
    "track_rate_dps": (8.0 / 256.0, -16.0, 16.0),
    "roll_deg": (45.0 / 256.0, -90.0, 90.0),
    "vertical_rate_mps": (32.0 * FPM, -16352.0 * FPM, 16352.0 * FPM),
}
EHS_COLUMNS = tuple(RESOLUTION)
#: BDS 4,0 MCP/FCU selected altitude: (LSB, lower, upper) in metres
SELECTED_ALT_RESOLUTION = (16.0 * FT, 0.0, 65520.0 * FT)
#: the ``reports`` column of the BDS 4,0 selected altitude (:data:`tertiary.contract.SELECTED_ALT_COLUMN`)
SELECTED_ALT_COLUMN = "selected_alt_m"

#: EHS field → the ``reports`` column carrying it (:data:`tertiary.contract.EHS_REPORT_COLUMNS`)
REPORT_COLUMN = dict(zip(EHS_COLUMNS, EHS_REPORT_COLUMNS))
#: spawn key of the EHS noise stream: a child of the scenario seed no other simulator stream uses
#: (radars use children 0 … n_radars), so switching EHS on or off leaves every other column
#: bit-identical
EHS_SPAWN_KEY = 0x454853
#: the columns :func:`ehs_report_columns` returns, in its order
SIMULATED_COLUMNS = (*(REPORT_COLUMN[c] for c in EHS_COLUMNS), SELECTED_ALT_COLUMN)
#: 1/φ: consecutive aircraft numbers get well-spread refresh phases
GOLDEN = 0.6180339887498949

__all__ = ["EhsConfig", "RESOLUTION", "EHS_COLUMNS", "SELECTED_ALT_RESOLUTION", "SELECTED_ALT_COLUMN",
           "selected_altitude", "REPORT_COLUMN", "EHS_SPAWN_KEY", "ehs_truth", "quantise",
           "ehs_parameters", "ehs_table", "ehs_rng", "ehs_report_columns", "SIMULATED_COLUMNS"]


@dataclass(frozen=True)
class EhsConfig:
    """Sensor noise σ per field (table units) and register staleness (module docstring)."""

    ground_speed_mps: float = 0.5
    true_track_deg: float = 0.2
    track_rate_dps: float = 0.05
    roll_deg: float = 0.3
    vertical_rate_mps: float = 0.3
    refresh_s: float = 0.0
    #: fraction of Mode S replies whose BDS 4,0 selected altitude was not extracted
    selected_alt_missing: float = 0.03


def quantise(values: ArrayLike, column: str) -> F64:
    """Round to the field's LSB and clip to its range (track angle wrapped to [−180, 180))."""
    lsb, lo, hi = RESOLUTION[column]
    v = np.asarray(values, float)
    if column == "true_track_deg":
        q = np.round(np.mod(v + 180.0, 360.0) / lsb) * lsb
        return np.mod(q, 360.0) - 180.0
    return np.clip(np.round(v / lsb) * lsb, lo, hi)


def ehs_truth(traj: Trajectories, aircraft: ArrayLike, t: ArrayLike, frame: geo.LocalFrame | None = None
              ) -> tuple[dict[str, F64], NDArray[np.bool_]]:
    """What the aircraft's own navigation system knows at time ``t`` (s after the epoch): the EHS
    fields before noise and quantisation, and validity (on the trajectory's active grid).

    ``frame``: the system frame the trajectories are in. The registers are over true north and
    the local vertical at the aircraft, so its velocity is turned into the ENU axes there
    (:func:`tertiary.core.geo.frame_vector_to_local`; at 500 km from the system origin the
    axes differ by several degrees: a level aircraft has a system-frame vertical velocity of
    ~18 m/s at 230 m/s). None: the trajectories' axes are taken as the local ones (a flat
    synthetic trajectory)."""
    aircraft = np.asarray(aircraft, np.int64)
    t = np.asarray(t, float)
    h = 0.5 * traj.dt
    lo, hi = np.clip(t - h, 0.0, traj.duration), np.clip(t + h, 0.0, traj.duration)
    # the navigation system's velocity: the trajectory's sampled velocities, not the derivative of
    # its position interpolant (:meth:`~tertiary.simulate.trajectory.Trajectories.velocity_at`)
    vel, ok = traj.velocity_at(aircraft, t)
    v_lo, ok_lo = traj.velocity_at(aircraft, lo)
    v_hi, ok_hi = traj.velocity_at(aircraft, hi)
    if frame is not None:
        # all three in the axes at the aircraft's position at t: the axes' own turn over ±dt/2
        # (v/R ≈ 0.002 °/s) is far below the track-rate LSB
        pos, _ = traj.position_at(aircraft, t)
        lat, lon, _ = frame.to_geodetic(pos[..., 0], pos[..., 1], pos[..., 2])
        vel, v_lo, v_hi = (np.stack(geo.frame_vector_to_local(v[..., 0], v[..., 1], v[..., 2], lat, lon, frame),
                                    axis=-1) for v in (vel, v_lo, v_hi))
    acc = (v_hi - v_lo) / np.maximum(hi - lo, 1e-9)[..., None]
    ve, vn = vel[..., 0], vel[..., 1]
    gs2 = np.maximum(ve * ve + vn * vn, 1e-12)
    chi_dot = (vn * acc[..., 0] - ve * acc[..., 1]) / gs2           # clockwise track rate (rad/s)
    gs = np.sqrt(gs2)
    values = {
        "ground_speed_mps": gs,
        "true_track_deg": np.degrees(np.arctan2(ve, vn)),
        "track_rate_dps": np.degrees(chi_dot),
        "roll_deg": np.degrees(np.arctan2(gs * chi_dot, G0)),
        "vertical_rate_mps": vel[..., 2],
    }
    return values, ok & ok_lo & ok_hi


def ehs_parameters(traj: Trajectories, aircraft: ArrayLike, t: ArrayLike, rng: np.random.Generator,
                   cfg: EhsConfig = EhsConfig(), frame: geo.LocalFrame | None = None
                   ) -> tuple[dict[str, F64], NDArray[np.bool_]]:
    """EHS fields as extracted at times ``t`` for ``aircraft`` (indices into ``traj``): truth at
    the register's sampling time + sensor noise, quantised to the BDS 5,0/6,0 resolutions
    (``frame``: :func:`ehs_truth`)."""
    aircraft = np.asarray(aircraft, np.int64)
    t = np.asarray(t, float)
    if cfg.refresh_s > 0:
        # each aircraft's own refresh phase on the absolute clock, keyed by its identity (not its
        # row in ``traj`` nor ``traj``'s epoch, which depend on the window a streamed simulation
        # looks up): golden-ratio fractions
        phase = cfg.refresh_s * np.mod((np.asarray(traj.truth_id, np.float64)[aircraft] + 1.0) * GOLDEN, 1.0)
        base = np.mod(traj.epoch.timestamp(), cfg.refresh_s)
        t = np.maximum(np.floor((t + base - phase) / cfg.refresh_s) * cfg.refresh_s + phase - base, 0.0)
    truth, ok = ehs_truth(traj, aircraft, t, frame)
    out = {c: quantise(truth[c] + getattr(cfg, c) * rng.standard_normal(t.shape), c) for c in EHS_COLUMNS}
    return out, ok


def ehs_table(reports: pl.DataFrame, traj: Trajectories, rng: np.random.Generator,
              cfg: EhsConfig = EhsConfig(), frame: geo.LocalFrame | None = None) -> pl.DataFrame:
    """EHS parameters extracted with each Mode S report (reports without an address get none).

    Keyed like the reports (``run``, ``radar_id``, ``local_track_id``, ``time``) plus ``mode_s``
    and the :data:`EHS_COLUMNS`; no truth column. ``reports`` needs ``truth_id`` to know which
    aircraft replied (the simulator's reports carry it)."""
    need = {"radar_id", "time", "local_track_id", "mode_s", "truth_id"}
    if missing := need - set(reports.columns):
        raise DataError(f"table reports lacks column(s) {', '.join(sorted(missing))} needed for EHS extraction")
    ms = reports.filter(pl.col("mode_s").is_not_null() & pl.col("truth_id").is_not_null())
    index = {int(tid): i for i, tid in enumerate(traj.truth_id)}
    lookup = pl.DataFrame({"truth_id": pl.Series(list(index), dtype=pl.Int64),
                           "__ac": pl.Series(list(index.values()), dtype=pl.Int64)})
    ms = ms.join(lookup, on="truth_id", how="inner", maintain_order="left")
    epoch_us = int(traj.epoch.timestamp() * US)
    t = (ms["time"].cast(pl.Datetime("us", "UTC")).dt.epoch("us").to_numpy() - epoch_us) * 1e-6
    values, ok = ehs_parameters(traj, ms["__ac"].to_numpy(), t, rng, cfg, frame)
    keys = [c for c in ("run", "radar_id", "local_track_id", "time", "mode_s") if c in ms.columns]
    table = ms.select(keys).with_columns(**{c: pl.Series(c, v) for c, v in values.items()})
    return table.filter(pl.Series(ok))


def selected_altitude(traj: Trajectories, aircraft: ArrayLike, rng: np.random.Generator,
                      missing: float = EhsConfig.selected_alt_missing, t: ArrayLike | None = None) -> F64:
    """BDS 4,0 selected altitude (m) of ``aircraft`` (indices into ``traj``) as extracted with
    each reply: the crew's selection at the reply time ``t`` (s after the epoch;
    ``traj.selected_at``, which changes where the crew's procedure changes it — None: the
    initial ``traj.selected_alt_m``; NaN where none) rounded to 16 ft and clipped to the field;
    NaN for a fraction ``missing`` of replies (one draw per reply from ``rng``) and for
    trajectories without selected altitudes."""
    aircraft = np.asarray(aircraft, np.int64)
    lost = rng.random(aircraft.shape) < missing
    sel = getattr(traj, "selected_alt_m", None)
    if sel is None:
        return np.full(aircraft.shape, np.nan)
    lsb, lo, hi = SELECTED_ALT_RESOLUTION
    now = (traj.selected_at(aircraft, np.asarray(t, float)) if t is not None and hasattr(traj, "selected_at")
           else np.asarray(sel, float)[aircraft])
    value = np.clip(np.round(now / lsb) * lsb, lo, hi)
    return np.where(lost, np.nan, value)


def ehs_rng(seed: int, radar_index: int, block: int | None = None) -> np.random.Generator:
    """The EHS noise stream of one radar: child (:data:`EHS_SPAWN_KEY`, radar_index) of the
    scenario seed — (…, ``block``) for one block of a streamed simulation — independent of (and
    not consuming from) every other simulator stream."""
    key = (EHS_SPAWN_KEY, radar_index) if block is None else (EHS_SPAWN_KEY, radar_index, block)
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=key))


def ehs_report_columns(traj: Trajectories, aircraft: ArrayLike, t_true: ArrayLike, replied: ArrayLike,
                       rng: np.random.Generator, cfg: EhsConfig = EhsConfig(), frame: geo.LocalFrame | None = None
                       ) -> dict[str, F64]:
    """The ``reports`` EHS columns (:data:`REPORT_COLUMN` names) of one radar's plots: the
    parameters extracted (Comm-B) with each reply whose Mode S address was decoded
    (``replied``), sampled at the true illumination time ``t_true`` (s after the epoch); NaN for
    clutter, non-Mode-S replies and times off the trajectory. With them ``selected_alt_m``
    (BDS 4,0, :func:`selected_altitude`; its draws follow the BDS 5,0/6,0 noise in ``rng``, so
    those columns do not depend on it). ``frame``: the trajectories' system frame
    (:func:`ehs_truth`)."""
    aircraft = np.asarray(aircraft, np.int64)
    sel = np.flatnonzero(np.asarray(replied, bool) & (aircraft >= 0))
    out = {REPORT_COLUMN[c]: np.full(len(aircraft), np.nan) for c in EHS_COLUMNS}
    out[SELECTED_ALT_COLUMN] = np.full(len(aircraft), np.nan)
    if sel.size:
        values, ok = ehs_parameters(traj, aircraft[sel], np.asarray(t_true, float)[sel], rng, cfg, frame)
        for c in EHS_COLUMNS:
            out[REPORT_COLUMN[c]][sel] = np.where(ok, values[c], np.nan)
        selected = selected_altitude(traj, aircraft[sel], rng, cfg.selected_alt_missing,
                                     np.asarray(t_true, float)[sel])
        out[SELECTED_ALT_COLUMN][sel] = np.where(ok, selected, np.nan)
    return out
