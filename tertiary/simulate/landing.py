"""Seed 002 landing-pattern scenario (digest §2.7 "default scenario") and the IMM-vs-raw study.

The paper's Fig. 1 is missing, so the geometry is the digest's implementation choice: a
left-hand pattern flown by an An-26, radar at the origin, X = east, Y = north, landing heading
west along y = 0:

1. downwind leg heading east at 72 m/s for 40 s;
2. 3rd turn: left 90° at 72 m/s, 15° bank (ω = g tan 15°/v = 0.0365 rad/s, radius 1973 m);
3. base leg north, 3000 m at 72 m/s;
4. 4th turn: left 90° at 69 m/s, 15° bank (ω = 0.0381 rad/s, radius 1812 m), ending at
   A = (13000, 0);
5. final A → B, 4000 m at 69 m/s;  6. B → C, 8000 m at 58 m/s to C = (1000, 0).

The start point is computed backwards from A, giving (9959, −6785) m as in the digest. Speed
changes are instantaneous at segment boundaries; the nominal path is evaluated analytically
at every scan (exact arcs). The truth of each Monte-Carlo run is the nominal path plus a
random-acceleration perturbation (white acceleration, PSD q = 0.01 m²/s³ per axis — the
paper's Q_k = diag(0.01, 0.01), units as chosen in the digest), propagated exactly with the CV
model. The radar measures range (σ_r = 30 m) and azimuth (σ_θ = 1°) every Δt = 0.7 s.

:func:`run_imm_landing` runs the seed-002 IMM on the converted measurements (R = J Rᵖ Jᵀ) and
reports the per-scan position and azimuth RMSE of the raw converted measurements and of the
IMM output over N runs (RMSE = √(mean over runs of the squared error), table 2.6 row 21).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from tertiary.core.units import G0
from tertiary.filters.imm import (PAPER_MU0, PAPER_OMEGAS, PAPER_P00, PAPER_TPM, HorizontalIMM, conversion_range_limit, convert_polar_2d, q_cv)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class LandingPattern:
    """Geometry, speeds, sensor and truth-noise parameters of the default landing scenario."""

    v_downwind: float = 72.0       # m/s, downwind, 3rd turn and base (between the 3rd and 4th turns)
    v_final: float = 69.0          # m/s, 4th turn and final A→B (to glide-path entry)
    v_glide: float = 58.0          # m/s, glide path B→C with flaps
    bank_deg: float = 15.0
    downwind_s: float = 40.0
    base_m: float = 3000.0
    ab_m: float = 4000.0
    bc_m: float = 8000.0
    point_a: tuple[float, float] = (13000.0, 0.0)
    dt: float = 0.7
    sigma_r: float = 30.0
    sigma_theta_deg: float = 1.0
    q_truth: float = 0.01          # m²/s³ per axis

    def turn_rate(self, v: float) -> float:
        return G0 * np.tan(np.radians(self.bank_deg)) / v

    def segments(self) -> list[dict]:
        """Segments with start point, heading (math angle from +X), speed, ω, duration."""
        r3 = self.v_downwind / self.turn_rate(self.v_downwind)
        r4 = self.v_final / self.turn_rate(self.v_final)
        ax, ay = self.point_a
        start = np.array([ax + r4 - r3 - self.v_downwind * self.downwind_s, ay - r4 - self.base_m - r3])
        legs = [  # (name, speed, omega, duration)
            ("downwind", self.v_downwind, 0.0, self.downwind_s),
            ("turn3", self.v_downwind, self.turn_rate(self.v_downwind), 0.5 * np.pi / self.turn_rate(self.v_downwind)),
            ("base", self.v_downwind, 0.0, self.base_m / self.v_downwind),
            ("turn4", self.v_final, self.turn_rate(self.v_final), 0.5 * np.pi / self.turn_rate(self.v_final)),
            ("final_ab", self.v_final, 0.0, self.ab_m / self.v_final),
            ("final_bc", self.v_glide, 0.0, self.bc_m / self.v_glide),
        ]
        out, p, phi, t0 = [], start, 0.0, 0.0
        for name, v, w, dur in legs:
            out.append({"name": name, "p0": p.copy(), "phi0": phi, "v": v, "omega": w, "t0": t0, "duration": dur})
            p, _ = _arc(p, phi, v, w, np.array([dur]))
            p = p[0]
            phi += w * dur
            t0 += dur
        return out

    @property
    def duration(self) -> float:
        s = self.segments()[-1]
        return s["t0"] + s["duration"]


def _arc(p0: F64, phi0: float, v: float, w: float, tau: F64) -> tuple[F64, F64]:
    """Position and velocity after τ on an arc (ω ≠ 0) or a line (ω = 0), math-angle heading."""
    phi = phi0 + w * tau
    if w == 0.0:
        pos = p0 + v * tau[:, None] * np.array([np.cos(phi0), np.sin(phi0)])
    else:
        pos = p0 + (v / w) * np.stack([np.sin(phi) - np.sin(phi0), np.cos(phi0) - np.cos(phi)], axis=-1)
    vel = v * np.stack([np.cos(phi), np.sin(phi)], axis=-1)
    return pos, vel


def nominal_path(pattern: LandingPattern = LandingPattern()) -> tuple[F64, F64, F64, NDArray[np.int64]]:
    """Nominal (noise-free) path on the scan grid: t (T,), pos (T, 2), vel (T, 2), segment (T,)."""
    segs = pattern.segments()
    n = int(np.floor(pattern.duration / pattern.dt + 1e-9)) + 1
    t = np.arange(n) * pattern.dt
    pos, vel = np.empty((n, 2)), np.empty((n, 2))
    seg = np.searchsorted([s["t0"] for s in segs], t, side="right") - 1
    for i, s in enumerate(segs):
        k = seg == i
        pos[k], vel[k] = _arc(s["p0"], s["phi0"], s["v"], s["omega"], t[k] - s["t0"])
    return t, pos, vel, seg.astype(np.int64)


@dataclass
class LandingRuns:
    """N Monte-Carlo runs of the scenario: truth and polar measurements on T scans."""

    t: F64                     # (T,)
    pos: F64                   # (N, T, 2) truth, east/north
    vel: F64                   # (N, T, 2)
    segment: NDArray[np.int64]  # (T,) index into pattern.segments()
    range_m: F64               # (N, T)
    azimuth_deg: F64           # (N, T) clockwise from north (project convention)
    pattern: LandingPattern = field(default_factory=LandingPattern)

    @property
    def theta(self) -> F64:
        """Paper's angle θ from +X (east) towards +Y (north), rad."""
        return np.pi / 2 - np.radians(self.azimuth_deg)


def simulate_landing(n_runs: int = 130, pattern: LandingPattern = LandingPattern(), seed: int = 2022) -> LandingRuns:
    """Truth (nominal path + white-acceleration perturbation) and polar measurements, vectorised
    over runs."""
    rng = np.random.default_rng(seed)
    t, pos0, vel0, seg = nominal_path(pattern)
    n_t = len(t)
    qd = q_cv(pattern.dt, pattern.q_truth)
    lq = np.linalg.cholesky(qd)
    w = rng.standard_normal((n_t - 1, n_runs, 4)) @ lq.T
    d = np.zeros((n_t, n_runs, 4))                       # [x, vx, y, vy] perturbation
    for k in range(1, n_t):
        prev = d[k - 1]
        d[k, :, 0] = prev[:, 0] + pattern.dt * prev[:, 1]
        d[k, :, 1] = prev[:, 1]
        d[k, :, 2] = prev[:, 2] + pattern.dt * prev[:, 3]
        d[k, :, 3] = prev[:, 3]
        d[k] += w[k - 1]
    d = d.transpose(1, 0, 2)
    pos = pos0[None] + d[..., [0, 2]]
    vel = vel0[None] + d[..., [1, 3]]
    rng_true = np.hypot(pos[..., 0], pos[..., 1])
    az_true = np.degrees(np.arctan2(pos[..., 0], pos[..., 1]))
    range_m = rng_true + pattern.sigma_r * rng.standard_normal(rng_true.shape)
    az = np.mod(az_true + pattern.sigma_theta_deg * rng.standard_normal(rng_true.shape), 360.0)
    return LandingRuns(t, pos, vel, seg, range_m, az, pattern)


@dataclass
class LandingResult:
    """Per-scan RMSE over the runs and their time-averaged ratios (scans ``first_scan`` … end)."""

    rmse_meas: F64            # (T,) position RMSE of the converted measurements, m
    rmse_imm: F64             # (T,) position RMSE of the IMM output, m
    rmse_az_meas: F64         # (T,) azimuth RMSE, deg
    rmse_az_imm: F64
    mu_mean: F64              # (T, M) mean model probabilities over runs
    ratio: float              # mean(rmse_meas) / mean(rmse_imm) over scans first_scan…
    ratio_az: float
    first_scan: int
    nees_mean: float          # mean position NEES (2 DOF) of the IMM output over runs and scans
    runs: LandingRuns


def run_imm_landing(n_runs: int = 130, pattern: LandingPattern = LandingPattern(), seed: int = 2022,
                    q_filter: float = 1.0, omegas=PAPER_OMEGAS, tpm=PAPER_TPM, mu0=PAPER_MU0,
                    p00=PAPER_P00, first_scan: int = 20) -> LandingResult:
    """Run the seed-002 IMM on converted measurements of :func:`simulate_landing` and compare the
    position / azimuth RMSE with the raw converted measurements (the paper claims 1.3–1.5×).

    Initialisation (digest §2.7): x̂₀ = truth + N(0, P₀₀) with the paper's P₀₀, all models, μ₀;
    the scan-0 measurement then updates that prior, later scans predict + update.
    """
    runs = simulate_landing(n_runs, pattern, seed)
    rng = np.random.default_rng(seed + 1)
    sig_th = np.radians(pattern.sigma_theta_deg)
    if np.any(runs.range_m >= conversion_range_limit(pattern.sigma_r, sig_th)):
        raise ValueError("measurements outside the seed-002 (14) conversion limit")
    z, rr = convert_polar_2d(runs.range_m, runs.theta, pattern.sigma_r, sig_th)   # (N, T, 2), (N, T, 2, 2)
    imm = HorizontalIMM(omegas, tpm, mu0, q_filter)
    p0 = np.diag(np.asarray(p00, float))
    truth4 = np.stack([runs.pos[:, 0, 0], runs.vel[:, 0, 0], runs.pos[:, 0, 1], runs.vel[:, 0, 1]], axis=1)
    x0 = truth4 + rng.standard_normal((n_runs, 4)) @ np.linalg.cholesky(p0).T
    x, p, mu = imm.init(x0, np.broadcast_to(p0, (n_runs, 4, 4)).copy())
    n_t = len(runs.t)
    est = np.empty((n_runs, n_t, 2))
    nees = np.empty((n_runs, n_t))
    mus = np.empty((n_runs, n_t, imm.n_models))
    dt = np.full(n_runs, pattern.dt)
    for k in range(n_t):
        if k > 0:
            x, p, mu = imm.predict(x, p, mu, dt)
        x, p, mu, _ = imm.update(x, p, mu, z[:, k], rr[:, k])
        xc, pc = imm.combine(x, p, mu)
        est[:, k] = xc[:, [0, 2]]
        e = est[:, k] - runs.pos[:, k]
        pp = pc[:, [0, 2]][:, :, [0, 2]]
        nees[:, k] = np.einsum("bi,bij,bj->b", e, np.linalg.inv(pp), e)
        mus[:, k] = mu
    err_m = np.linalg.norm(z - runs.pos, axis=-1)
    err_f = np.linalg.norm(est - runs.pos, axis=-1)
    rmse_m = np.sqrt(np.mean(err_m ** 2, axis=0))
    rmse_f = np.sqrt(np.mean(err_f ** 2, axis=0))
    az_true = np.arctan2(runs.pos[..., 1], runs.pos[..., 0])

    def az_err(p2: F64) -> F64:
        return np.degrees(np.angle(np.exp(1j * (np.arctan2(p2[..., 1], p2[..., 0]) - az_true))))

    rmse_az_m = np.sqrt(np.mean(az_err(z) ** 2, axis=0))
    rmse_az_f = np.sqrt(np.mean(az_err(est) ** 2, axis=0))
    s = slice(first_scan, None)
    return LandingResult(rmse_m, rmse_f, rmse_az_m, rmse_az_f, mus.mean(axis=0),
                         float(rmse_m[s].mean() / rmse_f[s].mean()),
                         float(rmse_az_m[s].mean() / rmse_az_f[s].mean()), first_scan,
                         float(nees[:, s].mean()), runs)
