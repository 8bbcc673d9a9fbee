"""Coarse gating ("грубое отождествление", monograph §1.4, §4.1).

Candidate pairs of aligned reports from *different* radars at the same (run, epoch) whose
coordinates and velocity components agree within wide tolerances. One KD-tree holds every
(run, epoch) at once: points live in (x, y, z·s, g·L) where s maps the vertical tolerance onto
the horizontal one, g is the dense (run, epoch) index and L is larger than the gate, so the
ellipsoidal gate (Δx² + Δy²)/Δr² + Δz²/Δh² ≤ 1 is a single ``query_pairs`` and points of
different epochs are never paired. No loop over epochs, reports or pairs.

Options: the Mahalanobis gate d² = Δpᵀ(C_a + C_b)⁻¹Δp ≤ χ²₃(P_gate) on top of the box;
the Bayes minimum-error H1/H2 decision (monograph §1.4): with Δ ~ N(0, S) under
H1 (same target) and Δ uniform over the gate volume V_G under H2 (different targets), the
rule "decide H1 iff P(H1) N(Δ; 0, S) ≥ P(H2)/V_G" is d² ≤ γ with

    γ = 2 ln[P(H1) V_G / (P(H2) (2π)^{m/2} |S|^{1/2})],   m = 3

a threshold per pair (|S| differs); and Mode S: two reports with different Mode S addresses
are never the same aircraft.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import polars as pl
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from tertiary.core.distributions import chi2_ppf


@dataclass(frozen=True)
class GatingConfig:
    """Tolerances of the coarse comparison.

    * ``pos_tol_m`` horizontal and ``alt_tol_m`` vertical (heights from radar elevation are
      poor: 0.15° at 100 km is 260 m); ``vel_tol_mps`` per horizontal velocity component,
      widened by three standard deviations of the velocity difference (new local tracks).
    * ``method="mahalanobis"`` additionally requires d² ≤ χ²₃(``gate_prob``).
    * ``method="bayes"`` additionally requires d² ≤ γ of :func:`bayes_threshold` with the
      prior ``prior_h1`` = P(H1) and the gate volume ``gate_volume_m3`` (None: the volume of
      the coarse ellipsoidal gate, (4/3)π ``pos_tol_m``² ``alt_tol_m``).
    * Mode C: two reports that both carry a barometric altitude are one aircraft only if the
      altitudes agree within ``mode_c_tol_m`` plus ``max_vrate_mps`` times the time between the
      two replies (each report's altitude is from its own reply time). Aircraft stacked 1 000 ft
      apart (holding) are then never merged, however close they are horizontally. For such a
      pair the Mode C test *is* the vertical gate, and the vertical term of ``sqdist`` is the
      altitude difference: the heights from radar elevation are not compared (at 150–300 km an
      en-route radar's elevation height is off by kilometres — two radars' z of one aircraft
      differed by a median 1.8 km on the national scenario's split targets, beyond
      ``alt_tol_m``, so the aircraft split while its Mode C altitudes agreed to the foot).
      Two reports of one Mode S address are one airframe whatever their codes: a disagreement
      is a garbled code (one bit off), which the fusion's garble gate refuses, so the pair is
      kept and its altitudes are not compared. A radar's older report of an address it has a
      newer report of at the same epoch (:func:`superseded_rows`) gates with nothing.
    """

    pos_tol_m: float = 3000.0
    alt_tol_m: float = 1500.0
    vel_tol_mps: float = 60.0
    method: Literal["box", "mahalanobis", "bayes"] = "box"
    gate_prob: float = 0.9999
    prior_h1: float = 0.5
    gate_volume_m3: float | None = None
    use_mode_s: bool = True
    use_mode_c: bool = True
    mode_c_tol_m: float = 120.0
    max_vrate_mps: float = 20.0


@dataclass
class Pairs:
    """Gated candidate pairs (indices into the aligned frame) with their distances."""

    a: NDArray[np.int64]
    b: NDArray[np.int64]
    sqdist: NDArray[np.float64]     # squared 3-D distance (m²)
    d2: NDArray[np.float64]         # Mahalanobis distance² of the positions

    def __len__(self) -> int:
        return len(self.a)


def group_index(aligned: pl.DataFrame) -> NDArray[np.int64]:
    """Dense index of (run, epoch) per row."""
    key = aligned.select(pl.struct("run", "epoch").rank("dense").cast(pl.Int64) - 1).to_series()
    return key.to_numpy()


def gate_volume(cfg: GatingConfig) -> float:
    """V_G of the H2 hypothesis: ``cfg.gate_volume_m3``, else the coarse gate's ellipsoid."""
    return cfg.gate_volume_m3 if cfg.gate_volume_m3 is not None else 4.0 / 3.0 * np.pi * cfg.pos_tol_m ** 2 * cfg.alt_tol_m


def bayes_threshold(det_s: NDArray[np.float64] | float, prior_h1: float, volume: float, m: int = 3
                    ) -> NDArray[np.float64]:
    """Minimum-error H1/H2 threshold on d²:
    γ = 2 ln[P(H1) V_G / (P(H2) (2π)^{m/2} |S|^{1/2})]; H1 iff d² ≤ γ (γ < 0: never)."""
    if not (0.0 < prior_h1 < 1.0) or not volume > 0:
        raise ValueError(f"bayes gate needs 0 < prior_h1 < 1 and a volume > 0, got {prior_h1}, {volume}")
    det_s = np.asarray(det_s, dtype=float)
    return 2.0 * (np.log(prior_h1 * volume / (1.0 - prior_h1)) - 0.5 * m * np.log(2 * np.pi) - 0.5 * np.log(det_s))


def position_mahalanobis(pos_a, pos_b, cov_a, cov_b) -> NDArray[np.float64]:
    """d² = Δpᵀ (C_a + C_b)⁻¹ Δp for stacks of 3-D positions and 3×3 covariances."""
    d = pos_a - pos_b
    s = cov_a + cov_b
    return np.einsum("ni,ni->n", d, np.linalg.solve(s, d[..., None])[..., 0])


def superseded_rows(aligned: pl.DataFrame) -> NDArray[np.bool_]:
    """Rows whose radar has a newer report of the same Mode S address at the same epoch: a
    local track the radar still extrapolates after it started another one on the airframe
    (a radar's duplicate track). Such a row gates with nothing, so the newer one joins the
    aircraft's other radars instead of a second target of its own."""
    if "time" not in aligned.columns or "mode_s" not in aligned.columns or aligned.height == 0:
        return np.zeros(aligned.height, bool)
    key = ["run", "epoch", "radar_id", "mode_s"]
    newest = pl.col("time").max().over(key)
    return aligned.select((pl.col("mode_s").is_not_null() & (pl.col("time") < newest)).fill_null(False)
                          ).to_series().to_numpy()


def candidate_pairs(aligned: pl.DataFrame, cfg: GatingConfig = GatingConfig(),
                    groups: NDArray[np.int64] | None = None, stale: NDArray[np.bool_] | None = None) -> Pairs:
    """All gated report pairs across radars within each (run, epoch); ``stale``: the rows'
    :func:`superseded_rows`, when the caller has them."""
    n = aligned.height
    if n < 2:
        empty = np.zeros(0, np.int64)
        return Pairs(empty, empty, np.zeros(0), np.zeros(0))
    g = group_index(aligned) if groups is None else groups
    pos = aligned.select("x_m", "y_m", "z_m").to_numpy()
    alt = (aligned["altitude_m"].cast(pl.Float64).fill_null(np.nan).to_numpy()
           if cfg.use_mode_c and "altitude_m" in aligned.columns and "age_s" in aligned.columns else None)
    scale = cfg.pos_tol_m / cfg.alt_tol_m
    # with Mode C the tree is horizontal (the Mode C test below is the vertical gate of the pairs
    # that both carry an altitude); without it, the ellipsoid (x, y, z·s) in one query
    z = pos[:, 2] * scale if alt is None else np.zeros(len(pos))
    pts = np.column_stack([pos[:, 0], pos[:, 1], z, g * (4.0 * cfg.pos_tol_m)])
    pairs = cKDTree(pts).query_pairs(cfg.pos_tol_m, output_type="ndarray")
    a, b = pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)
    both_c = np.zeros(len(a), bool) if alt is None else np.isfinite(alt[a]) & np.isfinite(alt[b])
    use_s = cfg.use_mode_s and "mode_s" in aligned.columns
    if use_s:
        ms = aligned["mode_s"]
        known = ms.is_not_null().to_numpy()
        codes = ms.cast(pl.Categorical).to_physical().fill_null(0).to_numpy().astype(np.int64)
    if alt is not None:          # pairs without two altitudes: the elevation heights' ellipsoid
        dxy2 = (pos[a, 0] - pos[b, 0]) ** 2 + (pos[a, 1] - pos[b, 1]) ** 2
        inside = dxy2 + ((pos[a, 2] - pos[b, 2]) * scale) ** 2 <= cfg.pos_tol_m ** 2
        # one address on both: one airframe, whose elevation heights are kilometres apart at
        # en-route ranges (the Mode C of one of them is missing)
        inside |= known[a] & known[b] & (codes[a] == codes[b]) if use_s else False
        a, b, both_c = a[both_c | inside], b[both_c | inside], both_c[both_c | inside]

    radar = aligned["radar_id"].to_numpy()
    vel = aligned.select("vx_mps", "vy_mps").to_numpy()
    cov36 = aligned["cov"].to_numpy()
    vel_var = cov36[:, [21, 28]]                          # var(vx), var(vy)
    # a freshly initiated local track knows its velocity poorly: widen by 3σ of the difference
    vel_gate = cfg.vel_tol_mps + 3.0 * np.sqrt(vel_var[a] + vel_var[b])
    keep = (radar[a] != radar[b]) & (g[a] == g[b]) & np.all(np.abs(vel[a] - vel[b]) <= vel_gate, axis=1)
    same = np.zeros(len(a), bool)           # one Mode S address on both: one airframe
    if use_s:
        keep &= ~(known[a] & known[b] & (codes[a] != codes[b]))
        same = known[a] & known[b] & (codes[a] == codes[b])
        stale = superseded_rows(aligned) if stale is None else stale
        keep &= ~(stale[a] | stale[b])
    if alt is not None:
        age = aligned["age_s"].to_numpy()
        tol = cfg.mode_c_tol_m + cfg.max_vrate_mps * np.abs(age[a] - age[b])
        off = np.abs(alt[a] - alt[b]) > tol           # NaN (no Mode C) never splits
        # with one address on both, a Mode C disagreement is a garbled code (one bit off), not a
        # second aircraft: the pair stays, and its altitudes are not compared (the fusion's
        # garble gate refuses the wrong one)
        keep &= ~off | same
        both_c &= ~(off & same)
    a, b, both_c, same = a[keep], b[keep], both_c[keep], same[keep]
    cov_pos = cov36[:, [0, 1, 2, 6, 7, 8, 12, 13, 14]]   # the 3×3 position block of the 6×6
    ca, cb = cov_pos[a].reshape(-1, 3, 3), cov_pos[b].reshape(-1, 3, 3)
    d2 = position_mahalanobis(pos[a], pos[b], ca, cb) if len(a) else np.zeros(0)
    if cfg.method == "mahalanobis":
        ok = d2 <= chi2_ppf(cfg.gate_prob, 3)
        a, b, d2, both_c, same = a[ok], b[ok], d2[ok], both_c[ok], same[ok]
    elif cfg.method == "bayes":
        ok = d2 <= bayes_threshold(np.linalg.det(ca + cb), cfg.prior_h1, gate_volume(cfg)) if len(a) else d2 > 0
        a, b, d2, both_c, same = a[ok], b[ok], d2[ok], both_c[ok], same[ok]
    # the vertical term: the altitude difference where both have one (GatingConfig); none for a
    # pair of one address without two valid codes (its elevation heights are kilometres off at
    # en-route ranges)
    no_z = same & (alt is not None)
    dz = np.where(both_c, (alt[a] - alt[b]) if alt is not None else 0.0, np.where(no_z, 0.0, pos[a, 2] - pos[b, 2]))
    sq = np.sum((pos[a, :2] - pos[b, :2]) ** 2, axis=1) + dz ** 2
    return Pairs(a, b, sq, d2)
