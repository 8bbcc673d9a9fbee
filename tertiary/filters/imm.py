"""IMM with constant-turn (CT) and constant-velocity (CV) models — seed 002 (Volovyk 2022).

Horizontal plane: state ``[x, vx, y, vy]`` (x = east, y = north of the system ENU frame), with
one Kalman filter per model; the vertical axis runs a separate CV channel ``[z, vz]``.

Models:

* CT(ω):  A_ct(ω, Δt) = expm(A_c Δt) of  v̇x = −ω vy,  v̇y = ω vx  (positive ω turns the velocity
  from +X towards +Y: a **left** turn with X = east, Y = north), and the isotropic closed form
  Q_ct = q·[[2Q₂/ω³, Q₁/ω², 0, Q₂/ω²], [Q₁/ω², Δt, −Q₂/ω², 0], [0, −Q₂/ω², 2Q₂/ω³, Q₁/ω²],
  [Q₂/ω², 0, Q₁/ω², Δt]] with Q₁ = 1 − cos ωΔt, Q₂ = ωΔt − sin ωΔt (valid only for q_x = q_y;
  the anisotropic case is computed numerically by Van Loan, :func:`q_van_loan`).
* CV = CT(ω = 0): A_cv, Q_cv (continuous white-noise acceleration, PSD q_x, q_y in m²/s³).
  Every coefficient is written with ``sinc``-type functions that are exact at ω → 0, so
  ω = 0 *is* the CV model (bit-for-bit A_cv and Q_cv).

IMM cycle (the "intended" form; every printed error of the paper's table 2.6 corrected):
π row-stochastic (π_ij = P(m_k = j | m_{k−1} = i)), c̄ = πᵀμ, mixing weights
μ^{i|j} = π_ij μ_i / c̄_j, mixed estimates from the *filtered* estimates with the spread about
the *mixed* mean, prediction, innovation, update P⁺ = P⁻ − K S Kᵀ (symmetrised), Gaussian
likelihoods in the log domain, μ_j ∝ c̄_j L_j (the *predicted* probability, printed error 7),
and the output combination with the spread about the combined estimate (not fed back).

Default parameters are the paper's (§2.7): ω = (0.001, 0.045, 0 = CV) rad/s, TPM
[[0.99, 0.01, 0], [0.01, 0.98, 0.01], [0, 0.01, 0.99]], μ₀ = [0.53, 0.33, 0.13]/0.99,
P₀₀ = diag(10³, 0.05, 10³, 0.05) (m², (m/s)²). The filter process noise q is not given by the
paper (only the truth's q = 0.01 m²/s³); the default is q = 1 m²/s³.

Measurements: the 2-D converted-measurement form of the paper (§2.4) is
:func:`convert_polar_2d` — (r, θ) → (r cos θ, r sin θ) with R = J Rᵖ Jᵀ, J at the measured point;
θ is measured from +X towards +Y (with X = east: θ = π/2 − azimuth). As a
:class:`~tertiary.filters.base.TrackFilter` the IMM takes fused ENU plots: ``r`` (B, 3) diagonal
variances or a full (B, 3, 3) covariance, whose horizontal 2×2 block is used in full (the
horizontal–vertical cross-covariance is ignored: the vertical channel is separate).

Only positive (left) turn rates are in the paper's model set; for traffic turning both ways pass
e.g. ``omegas=(0.045, -0.045, 0.0)`` with a matching ``tpm`` and ``mu0``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import special
from scipy.linalg import expm

from tertiary.core.jit import arg, ready_for
from tertiary.core.units import G0
from tertiary.filters.base import F64, Innovation, Output, State, TrackFilter, register
from tertiary.filters.imm_kernel import (imm_output_kernel, imm_predict_kernel, imm_update_kernel,
                                         imm_velocity_kernel)

#: paper's model set (rad/s; 0 = CV), TPM and normalised μ₀ (the paper's table 2.6 row 20)
PAPER_OMEGAS = (0.001, 0.045, 0.0)
PAPER_TPM = ((0.99, 0.01, 0.0), (0.01, 0.98, 0.01), (0.0, 0.01, 0.99))
PAPER_MU0 = tuple(np.array([0.53, 0.33, 0.13]) / 0.99)
PAPER_P00 = (1e3, 0.05, 1e3, 0.05)

_HIDX = np.array([0, 2])  # H = [[1,0,0,0],[0,0,1,0]]
#: the horizontal velocity components of the models' states [x, vx, y, vy(, ω)]
VEL_IDX = np.array([1, 3])
#: σ of a downlinked turn rate's error (rad/s) the IMMs' mode evidence allows for: well above the
#: register's own noise and LSB (0.05, 1/32 °/s), for a rate a few seconds older than its plot and
#: for registers read off noisy recorded trajectories
RATE_SIGMA = float(np.radians(0.5))


# --------------------------------------------------------------------------- model matrices


def _g3(x: F64) -> F64:
    """(x − sin x)/x³, accurate for every x (series below |x| = 0.5, error < 1e-16 relative)."""
    x = np.asarray(x, dtype=np.float64)
    x2 = x * x
    series = (1 / 6 - x2 / 120 * (1 - x2 / 42 * (1 - x2 / 72 * (1 - x2 / 110 * (1 - x2 / 156 * (1 - x2 / 210))))))
    small = np.abs(x) < 0.5
    xs = np.where(small, 1.0, x)
    return np.where(small, series, (xs - np.sin(xs)) / (xs * xs * xs))


def _ct_parts(omega: ArrayLike, dt: ArrayLike) -> tuple[F64, ...]:
    """sin(ωΔt)/ω, (1 − cos ωΔt)/ω, cos ωΔt, sin ωΔt, Q₁/ω², Q₂/ω², Q₂/ω³, all exact at ω → 0."""
    omega, dt = np.broadcast_arrays(np.asarray(omega, float), np.asarray(dt, float))
    x = omega * dt
    sinc = np.sinc(x / np.pi)                  # sin x / x
    h2 = 0.5 * np.sinc(x / (2.0 * np.pi)) ** 2  # (1 − cos x)/x² = 2 sin²(x/2)/x²
    g3 = _g3(x)
    s_w = dt * sinc
    c_w = dt * x * h2
    q1_w2 = dt * dt * h2
    q2_w2 = dt * dt * x * g3
    q2_w3 = dt ** 3 * g3
    return s_w, c_w, np.cos(x), np.sin(x), q1_w2, q2_w2, q2_w3


def a_ct(omega: ArrayLike, dt: ArrayLike) -> F64:
    """CT transition matrices (..., 4, 4) for state [x, vx, y, vy]; ω = 0 gives A_cv exactly."""
    s_w, c_w, c, s, *_ = _ct_parts(omega, dt)
    a = np.zeros(s_w.shape + (4, 4))
    a[..., 0, 0] = a[..., 2, 2] = 1.0
    a[..., 0, 1] = s_w
    a[..., 0, 3] = -c_w
    a[..., 1, 1] = c
    a[..., 1, 3] = -s
    a[..., 2, 1] = c_w
    a[..., 2, 3] = s_w
    a[..., 3, 1] = s
    a[..., 3, 3] = c
    return a


def a_cv(dt: ArrayLike) -> F64:
    """CV transition matrices (..., 4, 4)."""
    dt = np.asarray(dt, float)
    a = np.zeros(dt.shape + (4, 4))
    a[..., 0, 0] = a[..., 1, 1] = a[..., 2, 2] = a[..., 3, 3] = 1.0
    a[..., 0, 1] = a[..., 2, 3] = dt
    return a


def q_cv(dt: ArrayLike, qx: ArrayLike, qy: ArrayLike | None = None) -> F64:
    """CV process noise (..., 4, 4) for white-acceleration PSDs q_x, q_y (m²/s³)."""
    qy = qx if qy is None else qy
    dt, qx, qy = np.broadcast_arrays(*(np.asarray(v, float) for v in (dt, qx, qy)))
    q = np.zeros(dt.shape + (4, 4))
    for i, qq in ((0, qx), (2, qy)):
        q[..., i, i] = dt ** 3 / 3 * qq
        q[..., i, i + 1] = q[..., i + 1, i] = dt ** 2 / 2 * qq
        q[..., i + 1, i + 1] = dt * qq
    return q


def q_ct(omega: ArrayLike, dt: ArrayLike, q: ArrayLike) -> F64:
    """The paper's closed-form CT process noise (5) (..., 4, 4), isotropic PSD q (m²/s³).
    Exact (= Van Loan) only for q_x = q_y = q; ω = 0 gives Q_cv."""
    _, _, _, _, q1_w2, q2_w2, q2_w3 = _ct_parts(omega, dt)
    dt_b = np.broadcast_to(np.asarray(dt, float), q1_w2.shape)
    qq = np.broadcast_to(np.asarray(q, float), q1_w2.shape)
    m = np.zeros(q1_w2.shape + (4, 4))
    m[..., 0, 0] = m[..., 2, 2] = 2.0 * q2_w3
    m[..., 0, 1] = m[..., 1, 0] = m[..., 2, 3] = m[..., 3, 2] = q1_w2
    m[..., 0, 3] = m[..., 3, 0] = q2_w2
    m[..., 1, 2] = m[..., 2, 1] = -q2_w2
    m[..., 1, 1] = m[..., 3, 3] = dt_b
    return qq[..., None, None] * m


def q_van_loan(omega: float, dt: ArrayLike, qx: float, qy: float | None = None) -> F64:
    """Exact CT process noise ∫₀^Δt e^{A_c s} G diag(q_x, q_y) Gᵀ e^{A_cᵀ s} ds by Van Loan's
    method (scalar ω, any shape of Δt → (..., 4, 4)); valid for anisotropic noise q_x ≠ q_y,
    where the printed (5) is not."""
    qy = qx if qy is None else qy
    dt = np.asarray(dt, float)
    ac = np.array([[0, 1, 0, 0], [0, 0, 0, -omega], [0, 0, 0, 1], [0, omega, 0, 0]], float)
    g = np.array([[0, 0], [1, 0], [0, 0], [0, 1]], float)
    qc = g @ np.diag([qx, qy]) @ g.T
    m = np.zeros((8, 8))
    m[:4, :4] = -ac
    m[:4, 4:] = qc
    m[4:, 4:] = ac.T
    e = expm(m * dt[..., None, None])                    # batched over dt
    phi = np.swapaxes(e[..., 4:, 4:], -1, -2)
    q = phi @ e[..., :4, 4:]
    return 0.5 * (q + np.swapaxes(q, -1, -2))


def model_matrices(omega: float, dt: ArrayLike, q: float | tuple[float, float]) -> tuple[F64, F64]:
    """(A, Q) of one model for every dt: closed forms for isotropic q, Van Loan (batched over
    the distinct dt) for anisotropic (q_x, q_y)."""
    dt = np.asarray(dt, float)
    qx, qy = (q, q) if np.isscalar(q) else q
    # a batch of tracks has few distinct dt (scan periods): build each distinct one once, then
    # gather (bit-identical to building every row); HorizontalIMM caches the result per dt set
    uniq, inv = np.unique(dt, return_inverse=True)
    inv = inv.reshape(dt.shape)
    return a_ct(omega, uniq)[inv], _model_q(omega, uniq, qx, qy)[inv]


#: distinct-dt sets a HorizontalIMM keeps (A, Q) for; the cache is cleared when it is full
_MODEL_CACHE_MAX = 256


def _model_q(omega: float, dt: F64, qx: float, qy: float) -> F64:
    """Q of one model for the 1-D ``dt``."""
    if qx == qy:
        return q_ct(omega, dt, qx)
    if omega == 0.0:
        return q_cv(dt, qx, qy)
    return q_van_loan(omega, dt, qx, qy)


# --------------------------------------------------------------------------- converted measurements


def convert_polar_2d(range_m: ArrayLike, theta_rad: ArrayLike, sigma_r: ArrayLike, sigma_theta_rad: ArrayLike
                     ) -> tuple[F64, F64]:
    """Seed 002 (10)–(12): z = (r cos θ, r sin θ) and R = J diag(σ_r², σ_θ²) Jᵀ with J at the
    measured (r, θ). θ from +X towards +Y. Returns z (..., 2), R (..., 2, 2)."""
    r, th = np.broadcast_arrays(np.asarray(range_m, float), np.asarray(theta_rad, float))
    sr2 = np.broadcast_to(np.asarray(sigma_r, float) ** 2, r.shape)
    st2 = np.broadcast_to(np.asarray(sigma_theta_rad, float) ** 2, r.shape)
    c, s = np.cos(th), np.sin(th)
    z = np.stack([r * c, r * s], axis=-1)
    rr = r * r * st2
    cov = np.empty(r.shape + (2, 2))
    cov[..., 0, 0] = sr2 * c * c + rr * s * s
    cov[..., 1, 1] = sr2 * s * s + rr * c * c
    cov[..., 0, 1] = cov[..., 1, 0] = (sr2 - rr) * s * c
    return z, cov


def conversion_range_limit(sigma_r: float, sigma_theta_rad: float) -> float:
    """Seed 002 (14): the converted-measurement linearisation holds for r < 0.4 σ_r/σ_θ²."""
    return 0.4 * sigma_r / sigma_theta_rad ** 2


# --------------------------------------------------------------------------- batched IMM core


def _sym(p: F64) -> F64:
    return 0.5 * (p + np.swapaxes(p, -1, -2))


def _inv2(s: F64) -> tuple[F64, F64]:
    """Inverse and determinant of stacks of 2×2 matrices."""
    det = s[..., 0, 0] * s[..., 1, 1] - s[..., 0, 1] * s[..., 1, 0]
    inv = np.empty_like(s)
    inv[..., 0, 0] = s[..., 1, 1] / det
    inv[..., 1, 1] = s[..., 0, 0] / det
    inv[..., 0, 1] = -s[..., 0, 1] / det
    inv[..., 1, 0] = -s[..., 1, 0] / det
    return inv, det


def _mul2(a: F64, b: F64) -> F64:
    """a @ b for stacks of (n, 2) @ (2, 2) matrices."""
    return a[..., :, 0, None] * b[..., None, 0, :] + a[..., :, 1, None] * b[..., None, 1, :]


def imm_mix(x: F64, p: F64, mu: F64, tpm: F64) -> tuple[F64, F64, F64]:
    """Steps 1–4: predicted mode probabilities c̄ (B, M), mixed states (B, M, n) and covariances
    (B, M, n, n) from the filtered x (B, M, n), P (B, M, n, n) and μ (B, M)."""
    cbar = mu @ tpm                                          # c̄_j = Σ_i π_ij μ_i
    w = tpm[None] * mu[:, :, None] / np.where(cbar > 0, cbar, 1.0)[:, None, :]  # μ^{i|j}, (B, i, j)
    xm = np.einsum("bij,bin->bjn", w, x)
    d = x[:, :, None, :] - xm[:, None, :, :]                # (B, i, j, n)
    # (w d) dᵀ as a two-operand einsum: same products in the same order, much faster than three
    pm = np.einsum("bij,bimn->bjmn", w, p) + np.einsum("bijm,bijn->bjmn", w[..., None] * d, d)
    return cbar, xm, _sym(pm)


def imm_combine(x: F64, p: F64, mu: F64) -> tuple[F64, F64]:
    """Step 10: moment-matched combination (B, n), (B, n, n)."""
    xc = np.einsum("bj,bjn->bn", mu, x)
    d = x - xc[:, None, :]
    pc = np.einsum("bj,bjmn->bmn", mu, p) + np.einsum("bjm,bjn->bmn", mu[..., None] * d, d)
    return xc, _sym(pc)


def imm_combine_diag(x: F64, p: F64, mu: F64) -> tuple[F64, F64]:
    """:func:`imm_combine`'s estimate (B, n) and covariance diagonal (B, n), skipping the
    off-diagonal terms (same values: the diagonal is untouched by the symmetrisation)."""
    xc = np.einsum("bj,bjn->bn", mu, x)
    d = x - xc[:, None, :]
    var = (np.einsum("bj,bjn->bn", mu, np.diagonal(p, axis1=-2, axis2=-1))
           + np.einsum("bjn,bjn->bn", mu[..., None] * d, d))
    return xc, var


def imm_update(x: F64, p: F64, mu_pred: F64, z: F64, rr: F64, mask: NDArray[np.bool_],
               mu_floor: float = 0.0, h: NDArray[np.intp] = _HIDX) -> tuple[F64, F64, F64, F64]:
    """Steps 6–9 for the horizontal models with H = [[1,0,0,0],[0,0,1,0]]: x⁻ (B, M, 4),
    P⁻ (B, M, 4, 4), c̄ (B, M), z (B, 2), R (B, 2, 2). Tracks outside ``mask`` keep x⁻, P⁻, c̄.
    ``h``: the two state components measured (default the positions; :data:`VEL_IDX` the
    velocities). Returns x⁺, P⁺, μ, and the per-model log-likelihoods (B, M)."""
    nu = z[:, None, :] - x[:, :, h]                          # (B, M, 2)
    pht = p[:, :, :, h]                                      # (B, M, 4, 2)
    s = pht[:, :, h, :] + rr[:, None]                        # (B, M, 2, 2)
    si, det = _inv2(s)
    # the 2-wide inner products written out: stacked tiny matmuls/einsums cost far more per call
    k = _mul2(pht, si)                                       # (B, M, 4, 2)
    xu = x + k[..., 0] * nu[..., 0, None] + k[..., 1] * nu[..., 1, None]
    ks = _mul2(k, s)
    pu = _sym(p - (ks[..., :, 0, None] * k[..., None, :, 0] + ks[..., :, 1, None] * k[..., None, :, 1]))
    sn = si[..., 0] * nu[..., 0, None] + si[..., 1] * nu[..., 1, None]
    d2 = nu[..., 0] * sn[..., 0] + nu[..., 1] * sn[..., 1]
    loglik = -0.5 * d2 - 0.5 * np.log(det) - np.log(2.0 * np.pi)
    lw = np.log(np.maximum(mu_pred, 1e-300)) + loglik
    lw = lw - lw.max(axis=1, keepdims=True)
    mu = np.exp(lw)
    mu /= mu.sum(axis=1, keepdims=True)
    if mu_floor > 0:
        mu = np.maximum(mu, mu_floor)
        mu /= mu.sum(axis=1, keepdims=True)
    m = mask[:, None]
    return (np.where(m[..., None], xu, x), np.where(m[..., None, None], pu, p),
            np.where(m, mu, mu_pred), np.where(m, loglik, np.nan))


def _ramp(x: F64, sigma: float) -> F64:
    """E[(x + n)₊] for n ~ N(0, σ²): x Φ(x/σ) + σ φ(x/σ) (the ramp itself at σ = 0)."""
    if sigma == 0.0:
        return np.maximum(x, 0.0)
    u = x / sigma
    return x * special.ndtr(u) + sigma * np.exp(-0.5 * u * u) / np.sqrt(2.0 * np.pi)


def turn_rate_evidence(omegas: Sequence[float], omega: F64, floor: float, sigma: float = 0.0) -> F64:
    """The evidence (B, M) a measured turn rate ``omega`` (B,) rad/s gives each model of the
    fixed rates ``omegas`` (M,).

    Each model's weight is its hat function on the sorted rates: 1 on its own rate, falling
    linearly to 0 at its neighbours' (the extreme models keep 1 beyond the extreme rates), so
    a rate between two models is shared by linear interpolation, as the IMM's moment-matched
    output then mixes them towards it. The measured rate's error (σ ``sigma``, rad/s) is
    averaged over: the hats are written as sums of ramps (x − ω_k)₊, and each ramp's
    expectation under N(0, σ²) is :func:`_ramp`. The weights are scaled into [``floor``, 1],
    so that no model is excluded by a wrong or stale value. NaN rates give 1 everywhere (no
    evidence)."""
    w = np.asarray(omegas, float)
    omega = np.asarray(omega, float)
    ev = np.ones((len(omega), len(w)))
    if len(w) < 2 or len(omega) == 0:
        return ev
    order = np.argsort(w, kind="stable")
    g = w[order]
    if (np.diff(g) <= 0).any():
        raise ValueError(f"turn-rate evidence needs distinct model rates, got {tuple(w)}")
    ok = np.isfinite(omega)
    x = np.where(ok, omega, 0.0)[:, None]
    r = _ramp(x - g[None, :], sigma)                            # (B, M): E[(ω − g_k)₊]
    inv = 1.0 / np.diff(g)                                      # (M − 1,) slopes between neighbours
    hat = np.zeros_like(r)
    # rising edge of model k from g_{k−1}, falling edge to g_{k+1}
    hat[:, 1:] += (r[:, :-1] - r[:, 1:]) * inv
    hat[:, :-1] -= (r[:, :-1] - r[:, 1:]) * inv
    hat[:, 0] += 1.0                                            # the lowest model: 1 below its rate
    ev[:, order] = np.where(ok[:, None], floor + (1.0 - floor) * np.clip(hat, 0.0, 1.0), 1.0)
    return ev


class HorizontalIMM:
    """The horizontal IMM on plain arrays (state [x, vx, y, vy] per model), batched over B."""

    def __init__(self, omegas: Sequence[float] = PAPER_OMEGAS, tpm: ArrayLike = PAPER_TPM,
                 mu0: ArrayLike = PAPER_MU0, q: float | tuple[float, float] = 1.0, mu_floor: float = 1e-12):
        self.omegas = tuple(float(w) for w in omegas)
        self.tpm = np.asarray(tpm, float)
        mu0 = np.asarray(mu0, float)
        self.mu0 = mu0 / mu0.sum()
        self.q = q
        self.mu_floor = float(mu_floor)
        self._cache: dict[bytes, tuple[F64, F64]] = {}
        m = len(self.omegas)
        if self.tpm.shape != (m, m) or self.mu0.shape != (m,):
            raise ValueError("tpm must be (M, M) and mu0 (M,) for M = len(omegas)")
        if not np.allclose(self.tpm.sum(axis=1), 1.0):
            raise ValueError("tpm rows must sum to 1 (π_ij = P(j | i))")

    @property
    def n_models(self) -> int:
        return len(self.omegas)

    def init(self, x0: F64, p0: F64) -> tuple[F64, F64, F64]:
        """Every model starts from x0 (B, 4), P0 (B, 4, 4); μ = μ₀."""
        b, m = len(x0), self.n_models
        return (np.repeat(x0[:, None], m, axis=1), np.repeat(p0[:, None], m, axis=1),
                np.broadcast_to(self.mu0, (b, m)).copy())

    def predict(self, x: F64, p: F64, mu: F64, dt: F64) -> tuple[F64, F64, F64]:
        """Mixing and model-conditioned prediction; returns x⁻, P⁻ and c̄ (the predicted μ)."""
        cbar, xm, pm = imm_mix(x, p, mu, self.tpm)
        a, q = self._matrices(dt)
        # all models in one batched product: per-call overhead dominates at tracker batch sizes
        xs = np.einsum("bmij,bmj->bmi", a, xm)
        return xs, _sym(a @ pm @ np.swapaxes(a, -1, -2) + q), cbar

    def _matrices(self, dt: F64) -> tuple[F64, F64]:
        """(A, Q) of every model for every dt, (B, M, 4, 4) each; cached per distinct-dt set."""
        uniq, inv = np.unique(dt, return_inverse=True)
        key = uniq.tobytes()
        hit = self._cache.get(key)
        if hit is None:
            pairs = [model_matrices(w, uniq, self.q) for w in self.omegas]
            if len(self._cache) >= _MODEL_CACHE_MAX:
                self._cache.clear()
            hit = self._cache[key] = (np.stack([a for a, _ in pairs], axis=1),
                                      np.stack([q for _, q in pairs], axis=1))
        inv = inv.reshape(np.shape(dt))
        return hit[0][inv], hit[1][inv]

    def update(self, x: F64, p: F64, mu_pred: F64, z: F64, rr: F64, mask: NDArray[np.bool_] | None = None
               ) -> tuple[F64, F64, F64, F64]:
        mask = np.ones(len(x), bool) if mask is None else np.asarray(mask, bool)
        return imm_update(x, p, mu_pred, z, rr, mask, self.mu_floor)

    @staticmethod
    def combine(x: F64, p: F64, mu: F64) -> tuple[F64, F64]:
        return imm_combine(x, p, mu)


# --------------------------------------------------------------------------- TrackFilter


def cv1_predict(x: F64, p: F64, dt: F64, q: float) -> tuple[F64, F64]:
    """Scalar-axis CV prediction on (B, 2), (B, 2, 2); A P Aᵀ + Q written out (A = [[1, dt], [0, 1]]):
    stacked 2×2 matmuls cost far more per call."""
    x = np.stack([x[:, 0] + dt * x[:, 1], x[:, 1]], axis=1)
    ap0 = p[:, 0] + dt[:, None] * p[:, 1]                    # row 0 of A P (row 1 is P's)
    out = np.empty_like(p)
    out[:, 0, 0] = ap0[:, 0] + ap0[:, 1] * dt + dt ** 3 / 3 * q
    out[:, 0, 1] = ap0[:, 1] + dt ** 2 / 2 * q
    out[:, 1, 0] = p[:, 1, 0] + p[:, 1, 1] * dt + dt ** 2 / 2 * q
    out[:, 1, 1] = p[:, 1, 1] + dt * q
    return x, _sym(out)


def split_r(r: F64) -> tuple[F64, F64]:
    """The horizontal 2×2 block (B, 2, 2) and the vertical variance (B,) of a plot covariance
    given as diagonal variances (B, 3) or in full (B, 3, 3)."""
    if r.ndim == 3:
        return r[:, :2, :2], r[:, 2, 2]
    rh = np.zeros((len(r), 2, 2))
    rh[:, 0, 0], rh[:, 1, 1] = r[:, 0], r[:, 1]
    return rh, r[:, 2]


def cv1_update(xv: F64, pv: F64, nu_z: F64, s_z: F64, ok: NDArray[np.bool_]) -> tuple[F64, F64]:
    """Scalar-axis CV update (H = [1, 0]) of the vertical channel with innovation ``nu_z`` and
    its variance ``s_z``; tracks outside ``ok`` keep x⁻, P⁻."""
    k = pv[:, :, 0] / s_z[:, None]
    xu = xv + k * nu_z[:, None]
    pu = _sym(pv - s_z[:, None, None] * k[:, :, None] * k[:, None, :])
    return np.where(ok[:, None], xu, xv), np.where(ok[:, None, None], pu, pv)


@register
class IMMFilter(TrackFilter):
    """Seed 002 IMM (horizontal CT/CT/CV) + vertical CV channel, batched over tracks.

    Parameters (defaults = the paper's):
        omegas:   turn rate per model, rad/s (0 = CV), default (0.001, 0.045, 0)
        tpm:      row-stochastic mode transition matrix, default the paper's
        mu0:      initial mode probabilities (normalised), default [0.53, 0.33, 0.13]/0.99
        q:        horizontal white-acceleration PSD of the filters (m²/s³), scalar or (q_x, q_y);
                  default 1 (the paper gives only the truth's 0.01)
        q_z:      vertical CV channel PSD (m²/s³), default 1
        p00:      diag of P₀₀ for :meth:`init_state` (paper: (10³, 0.05, 10³, 0.05))
        sigma_v0: horizontal velocity σ (m/s) when a track starts from a single plot
                  (:meth:`init`; velocity 0, vertical velocity σ = sigma_v0/10), default 150
        mu_floor: floor on μ after each update (renormalised), default 1e-12
        rate_floor: the least evidence a downlinked turn rate gives a model
                  (:meth:`observe_turn_rate`, :func:`turn_rate_evidence`), default 0.01
        rate_sigma: σ (rad/s) of a downlinked turn rate's error, averaged over by the evidence
        compiled: predict and update with compiled per-track kernels (numba, cached on disk;
                  same equations, round-off differences only) when q is isotropic; False: numpy
        max_load_factor: the predicted mode probabilities are conditioned on the turn rates an
                  aircraft can fly at the track's speed within this load factor
                  (:func:`feasible_modes`); None (default): every model at every speed
    """

    name = "imm"
    #: the horizontal 2×2 block of R (E–N correlation of a converted plot) is used in full; the
    #: vertical channel is a separate CV filter, so the horizontal–vertical terms are dropped
    full_r = True

    def __init__(self, omegas: Sequence[float] = PAPER_OMEGAS, tpm: ArrayLike = PAPER_TPM,
                 mu0: ArrayLike = PAPER_MU0, q: float | tuple[float, float] = 1.0, q_z: float = 1.0,
                 p00: Sequence[float] = PAPER_P00, sigma_v0: float = 150.0, mu_floor: float = 1e-12,
                 rate_floor: float = 0.01, rate_sigma: float = RATE_SIGMA, compiled: bool = True,
                 max_load_factor: float | None = None):
        if not (0.0 < rate_floor <= 1.0 and rate_sigma >= 0.0):          # NaN fails too
            raise ValueError(f"need rate_floor in (0, 1] and rate_sigma >= 0, got {rate_floor}, {rate_sigma}")
        if max_load_factor is not None and not max_load_factor >= 1.0:
            raise ValueError(f"max_load_factor must be >= 1 (level flight) or None, got {max_load_factor}")
        self.max_load_factor = None if max_load_factor is None else float(max_load_factor)
        self.core = HorizontalIMM(omegas, tpm, mu0, q, mu_floor)
        self.rate_floor, self.rate_sigma = float(rate_floor), float(rate_sigma)
        qx, qy = (q, q) if np.isscalar(q) else q
        # the compiled prediction has the isotropic closed form only (anisotropic q: Van Loan)
        self._q_iso = float(qx) if compiled and float(qx) == float(qy) else None
        self._omegas = np.asarray(self.core.omegas, float)
        self.q_z = float(q_z)
        self.p00 = np.asarray(p00, float)
        self.sigma_v0 = float(sigma_v0)

    @property
    def compiled(self) -> bool:
        """Whether predict and update run the compiled kernels (isotropic ``q``, ``compiled``)."""
        return self._q_iso is not None

    # ---- construction
    def init(self, z: F64, r: F64) -> State:
        z = np.asarray(z, float)
        rh, rz = split_r(np.asarray(r, float))
        b = len(z)
        x0 = np.zeros((b, 4))
        x0[:, 0], x0[:, 2] = z[:, 0], z[:, 1]
        p0 = np.zeros((b, 4, 4))
        p0[:, [0, 0, 2, 2], [0, 2, 0, 2]] = rh.reshape(b, 4)
        p0[:, 1, 1] = p0[:, 3, 3] = self.sigma_v0 ** 2
        xv = np.stack([z[:, 2], np.zeros(b)], axis=1)
        pv = np.zeros((b, 2, 2))
        pv[:, 0, 0], pv[:, 1, 1] = rz, self.sigma_v0 ** 2 / 100.0
        return self.init_state(x0, p0, xv, pv)

    def init_state(self, x0: F64, p0: F64 | None = None, xv: F64 | None = None, pv: F64 | None = None) -> State:
        """Start from horizontal states x0 (B, 4) = [x, vx, y, vy] (paper: P₀₀ if ``p0`` is None)
        and optional vertical states xv (B, 2), pv (B, 2, 2)."""
        x0 = np.asarray(x0, float)
        b = len(x0)
        p0 = np.broadcast_to(np.diag(self.p00), (b, 4, 4)).copy() if p0 is None else np.asarray(p0, float)
        x, p, mu = self.core.init(x0, p0)
        xv = np.zeros((b, 2)) if xv is None else np.asarray(xv, float)
        pv = np.broadcast_to(np.diag([1e4, 1e2]), (b, 2, 2)).copy() if pv is None else np.asarray(pv, float)
        return {"x": x, "P": p, "mu": mu, "xv": xv, "Pv": pv}

    # ---- cycle
    def predict(self, state: State, dt: F64) -> State:
        dt = np.broadcast_to(np.asarray(dt, float), (len(state["mu"]),))
        if self._q_iso is not None and len(dt):
            ready_for("imm_predict")
            x, p, cbar, xv, pv = imm_predict_kernel(
                arg(state["x"]), arg(state["P"]), arg(state["mu"]), arg(dt), arg(self._omegas),
                arg(self.core.tpm), self._q_iso, arg(state["xv"]), arg(state["Pv"]), self.q_z)
        else:
            x, p, cbar = self.core.predict(state["x"], state["P"], state["mu"], dt)
            xv, pv = cv1_predict(state["xv"], state["Pv"], dt, self.q_z)
        if self.max_load_factor is not None and len(dt):
            cbar = condition_on_feasible(cbar, feasible_modes(self._omegas, self._speed(state), self.max_load_factor))
        return {"x": x, "P": p, "mu": cbar, "xv": xv, "Pv": pv}

    @staticmethod
    def _speed(state: State) -> F64:
        """Each track's horizontal speed from its combined (moment-matched) velocity."""
        v = np.einsum("bm,bmi->bi", state["mu"], state["x"][:, :, [1, 3]])
        return np.hypot(v[:, 0], v[:, 1])

    def update(self, state: State, z: F64, r: F64, mask: NDArray[np.bool_]) -> tuple[State, Innovation]:
        z, mask = np.asarray(z, float), np.asarray(mask, bool)
        rh, rz = split_r(np.asarray(r, float))
        ok = mask & np.all(np.isfinite(z), axis=1)
        if self._q_iso is not None and len(ok):
            ready_for("imm_update")
            x, p, mu, xv, pv, nu, s, nis = imm_update_kernel(
                arg(state["x"]), arg(state["P"]), arg(state["mu"]), arg(state["xv"]), arg(state["Pv"]), arg(z),
                arg(rh), arg(rz), arg(ok, np.bool_), float(self.core.mu_floor))
            return {"x": x, "P": p, "mu": mu, "xv": xv, "Pv": pv}, Innovation(nu, s, nis)
        zz = np.where(ok[:, None], z, 0.0)
        rh = np.where(ok[:, None, None], rh, np.eye(2))
        rz = np.where(ok, rz, 1.0)
        # innovation of the combined prediction (for gating / NIS)
        xc, pc = imm_combine(state["x"], state["P"], state["mu"])
        nu_h = zz[:, :2] - xc[:, _HIDX]
        s_h = pc[:, _HIDX][:, :, _HIDX] + rh
        si, _ = _inv2(s_h)
        nu_z = zz[:, 2] - state["xv"][:, 0]
        s_z = state["Pv"][:, 0, 0] + rz
        nis = np.einsum("bi,bij,bj->b", nu_h, si, nu_h) + nu_z ** 2 / s_z
        # horizontal IMM
        x, p, mu, _ = self.core.update(state["x"], state["P"], state["mu"], zz[:, :2], rh, ok)
        # vertical CV channel
        xv, pvu = cv1_update(state["xv"], state["Pv"], nu_z, s_z, ok)
        return {"x": x, "P": p, "mu": mu, "xv": xv, "Pv": pvu}, innovation(nu_h, nu_z, s_h, s_z, nis, ok)

    def observe_turn_rate(self, state: State, omega: F64, mask: NDArray[np.bool_]) -> State:
        """The mode probabilities given the downlinked turn rate as well: μ_j ∝ μ_j e_j with
        e_j the rate's evidence for model j (:func:`turn_rate_evidence`). The rate is a
        measurement of the mode, independent of the position given the mode, so the mode
        posterior multiplies by its likelihood; the models' states are unchanged. On a straight
        leg this keeps the turn models' probability, and the spread their offsets add to the
        combined covariance, down; at a turn's onset it moves the probability to the turning
        models before the positions can."""
        omega = np.where(np.asarray(mask, bool), np.asarray(omega, float), np.nan)
        ok = np.isfinite(omega)
        if not ok.any():
            return state
        mu = state["mu"] * turn_rate_evidence(self.core.omegas, omega, self.rate_floor, self.rate_sigma)
        mu = mu / mu.sum(axis=1, keepdims=True)
        if self.core.mu_floor > 0:
            mu = np.maximum(mu, self.core.mu_floor)
            mu = mu / mu.sum(axis=1, keepdims=True)
        return {**state, "mu": np.where(ok[:, None], mu, state["mu"])}

    def observe_velocity(self, state: State, v: F64, r: F64, mask: NDArray[np.bool_]) -> State:
        """Every model updated with the measured horizontal velocity (H picks vx, vy), and the
        mode probabilities with its likelihood under each model: a velocity measurement tells a
        turn model from CV at once, where positions need several scans."""
        return imm_velocity_update(state, v, r, mask, self.core.mu_floor, compiled=self.compiled)

    def output(self, state: State) -> Output:
        if self.compiled and len(state["mu"]):
            ready_for("imm_output")
            out, cov = imm_output_kernel(arg(state["x"]), arg(state["P"]), arg(state["mu"]), arg(state["xv"]),
                                         arg(state["Pv"]))
            return Output(out, np.einsum("bii->bi", cov), state["mu"].copy(), cov)
        xc, pc = imm_combine(state["x"], state["P"], state["mu"])
        xv, pv = state["xv"], state["Pv"]
        out = np.stack([xc[:, 0], xc[:, 2], xv[:, 0], xc[:, 1], xc[:, 3], xv[:, 1]], axis=1)
        cov = np.zeros((len(xc), 6, 6))
        h = np.array([0, 3, 1, 4])                      # (x, vx, y, vy) → their places in (x y z vx vy vz)
        cov[:, h[:, None], h[None, :]] = _sym(pc)
        v = np.array([2, 5])
        cov[:, v[:, None], v[None, :]] = pv
        return Output(out, np.einsum("bii->bi", cov), state["mu"].copy(), cov)

    def combined_horizontal(self, state: State) -> tuple[F64, F64]:
        """Combined horizontal estimate (B, 4) and covariance (B, 4, 4)."""
        return imm_combine(state["x"], state["P"], state["mu"])


def imm_velocity_update(state: State, v: F64, r: F64, mask: NDArray[np.bool_], mu_floor: float,
                        compiled: bool = False) -> State:
    """The IMM states ``x`` (B, M, N ≥ 4), ``P``, ``mu`` updated with horizontal velocities ``v``
    (B, 2) of covariance ``r`` (B, 2, 2) where ``mask`` and both are finite (:func:`imm_update`
    with :data:`VEL_IDX`); the other entries of ``state`` are carried. ``compiled``: the same
    equations per track (:func:`~tertiary.filters.imm_kernel.imm_velocity_kernel`)."""
    v, r = np.asarray(v, float), np.asarray(r, float)
    ok = np.asarray(mask, bool) & np.isfinite(v).all(axis=1) & np.isfinite(r).all(axis=(1, 2))
    if not ok.any():
        return state
    vv = np.where(ok[:, None], v, 0.0)
    rr = np.where(ok[:, None, None], r, np.eye(2))
    if compiled:
        ready_for("imm_velocity")
        x, p, mu = imm_velocity_kernel(arg(state["x"]), arg(state["P"]), arg(state["mu"]), arg(vv), arg(rr),
                                       arg(ok, np.bool_), float(mu_floor))
        return {**state, "x": x, "P": p, "mu": mu}
    x, p, mu, _ = imm_update(state["x"], state["P"], state["mu"], vv, rr, ok, mu_floor, h=VEL_IDX)
    return {**state, "x": x, "P": p, "mu": mu}


def innovation(nu_h: F64, nu_z: F64, s_h: F64, s_z: F64, nis: F64, ok: NDArray[np.bool_]) -> Innovation:
    """The :class:`Innovation` of a horizontal (2-D) plus vertical update: (x, y, z) innovations,
    their variances and the NIS, NaN where no plot updated the track."""
    nu = np.concatenate([nu_h, nu_z[:, None]], axis=1)
    s = np.stack([s_h[:, 0, 0], s_h[:, 1, 1], s_z], axis=1)
    nan = ~ok
    return Innovation(np.where(nan[:, None], np.nan, nu), np.where(nan[:, None], np.nan, s),
                      np.where(nan, np.nan, nis))


def feasible_modes(omegas: Sequence[float], speed: F64, max_load_factor: float | None) -> NDArray[np.bool_]:
    """(B, M): whether each model's turn rate ω_j can be flown at each track's ``speed`` (m/s)
    within the limit load factor n: a level turn at speed v and rate ω needs the horizontal
    acceleration ω·v = g·tan φ, and the load factor 1/cos φ, so
    |ω| ≤ g·sqrt(n² − 1)/v. CV (ω = 0) is always feasible; None: every model is."""
    w = np.abs(np.asarray(omegas, float))[None, :]
    if max_load_factor is None:
        return np.ones((len(speed), w.shape[1]), bool)
    a_max = G0 * np.sqrt(max_load_factor ** 2 - 1.0)
    return (w * np.asarray(speed, float)[:, None] <= a_max) | (w == 0.0)


def condition_on_feasible(mu: F64, feasible: NDArray[np.bool_]) -> F64:
    """The mode probabilities ``mu`` (B, M) conditioned on the mode being feasible: the
    infeasible ones set to 0, the rest renormalised (a row with none feasible is kept)."""
    kept = np.where(feasible, mu, 0.0)
    total = kept.sum(axis=1, keepdims=True)
    return np.where(total > 0, kept / np.where(total > 0, total, 1.0), mu)


def symmetric_tpm(n_turn: int, stay_turn: float = 0.98, stay_cv: float = 0.998) -> F64:
    """TPM of ``n_turn`` turn models followed by one CV model, where every turn model
    communicates only through CV: turn i stays with ``stay_turn`` or goes to CV; CV stays with
    ``stay_cv`` or goes to each turn model with (1 − stay_cv)/n_turn."""
    m = n_turn + 1
    tpm = np.zeros((m, m))
    tpm[np.arange(n_turn), np.arange(n_turn)] = stay_turn
    tpm[:n_turn, -1] = 1.0 - stay_turn
    tpm[-1, :n_turn] = (1.0 - stay_cv) / n_turn
    tpm[-1, -1] = stay_cv
    return tpm


#: the limit manoeuvring load factor of a transport aircraft (CS/FAR 25.337(b): not less than 2.5,
#: the value of most jets), the bound of ``imm_sym``'s feasible turn rates
LIMIT_LOAD_FACTOR = 2.5

#: ``imm_sym``'s turn rates (rad/s) — 0.23, 0.57, 1.4, 3.2 and 6.3 °/s, left and right — then CV
SYM_OMEGAS = (0.004, -0.004, 0.01, -0.01, 0.025, -0.025, 0.055, -0.055, 0.11, -0.11, 0.0)


@register
class SymmetricIMMFilter(IMMFilter):
    """:class:`IMMFilter` with a symmetric grid of fixed turn rates and CV (:data:`SYM_OMEGAS`).

    A fixed-rate CT model fits a turn only near its own rate, and its acceleration ω·v grows
    with speed: a single CT(±0.045) pair (2.6 °/s; 10 m/s² at 230 m/s) fits neither a wide
    circle of a few mrad/s nor a gentle en-route turn (0.3–1.5 °/s), so there the IMM
    alternates between CV and a model turning far too fast, and lags. The grid spaces the rates
    by ×2–2.5 from 0.004 to 0.11 rad/s, so every rate of 0–6 °/s either way lies between two
    neighbouring models. Between them the IMM mixes the two; at cruise speed a rate midway
    between grid rates (Δω·v ≈ 1.7 m/s² at 230 m/s) is still followed less closely than by a
    model that estimates ω (:class:`tertiary.filters.turn.IMMCTFilter`, ``imm_ct``).

    The turn models communicate only through CV (:func:`symmetric_tpm`: a turn model stays with
    0.98, CV with 0.998). The moment-matched output adds Σ μ_j d_j d_jᵀ, and a turn model's
    velocity offset d_j ≈ ω_j v Δt is tens of m/s, so even a small μ_j on a straight leg
    widens the combined velocity covariance well beyond the error (pessimistic NEES; the
    conflict prediction grows P_vv by t² up to 105 s). The low CV→turn prior keeps the turn
    models' probability, and that spread, small on straight legs; a real turn still wins within
    a few scans, its likelihood ratio growing every scan.

    Only the turn rates an aircraft can fly at the track's speed take part in a prediction
    (``max_load_factor``, default :data:`LIMIT_LOAD_FACTOR`; :func:`feasible_modes`): at
    215 m/s a 0.11 rad/s turn needs 23.7 m/s² (2.6 g, 69° of bank), beyond any transport
    aircraft, yet with a probability of 10⁻⁴ it rotates the velocity by 90 m/s in a 4 s
    prediction and alone widens the combined velocity σ between two scans from ~1.5 to ~5 m/s.
    Below 204 m/s every model stays. The ground speed stands for the airspeed (the wind is not
    known), so a tailwind tightens the bound by its share of the speed.

    Default ``q`` = 0.3 m²/s³ (the seed's IMM: 1): with the tracker fed independent plots
    (no re-extrapolated estimates) the turn models carry the manoeuvres, so the models' own
    noise can stay low. With ``omegas`` given and ``tpm`` None, the last rate must be the CV
    model (0).
    """

    name = "imm_sym"

    def __init__(self, omegas: Sequence[float] = SYM_OMEGAS, tpm: ArrayLike | None = None,
                 mu0: ArrayLike | None = None, q: float | tuple[float, float] = 0.3,
                 max_load_factor: float | None = LIMIT_LOAD_FACTOR, **kwargs):
        n_turn = len(omegas) - 1
        if tpm is None:
            if float(omegas[-1]) != 0.0:
                raise ValueError("with the default tpm the last of omegas must be the CV model (0)")
            tpm = symmetric_tpm(n_turn)
        if mu0 is None:
            mu0 = np.r_[np.full(n_turn, 0.5 / max(n_turn, 1)), 0.5]
        super().__init__(omegas=omegas, tpm=tpm, mu0=mu0, q=q, max_load_factor=max_load_factor, **kwargs)
