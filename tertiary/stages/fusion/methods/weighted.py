"""Weighted fusion with weights fixed by the covariances or the configuration: arithmetic mean,
a-priori weights, information fusion, covariance intersection and the single best source.

Reported ``weights``: one per contributing radar, same order as ``radar_ids``, summing to 1.

* ``arithmetic`` (4.1): x = mean of the states, P = (1/N²) Σ C_n (independent errors).
  Weights 1/N.
* ``apriori`` (4.3)–(4.4) for N radars, per coordinate c ∈ {x, y, z}:
  b_{n,c} = σ⁻²_{n,c} / Σ_m σ⁻²_{m,c} with σ²_{n,c} = ``nominal_var[c]``; each velocity
  coordinate uses the weight of its position axis. P = Σ_n B_n C_n B_n, B_n = diag(b_n).
  Reported weight: the mean of the x, y, z weights of the radar (sums to 1 because each
  coordinate's weights do).
* ``information``: P = (Σ C_n⁻¹)⁻¹, x = P Σ C_n⁻¹ x_n over the full 6-D state. Reported
  weight tr(P C_n⁻¹)/6 (the weights sum to 1 because Σ P C_n⁻¹ = I; renormalised against
  rounding).
* ``covariance_intersection``: P⁻¹ = Σ ω_n C_n⁻¹, x = P Σ ω_n C_n⁻¹ x_n, ω on the simplex.
  Two sources: ω minimises tr P (or det P, ``ci_objective="det"``) by a golden-section search
  vectorised over targets, on the closed form of P(ω) after simultaneous diagonalisation.
  N > 2: the fast-CI weights ω_n ∝ 1/tr C_n (Niehsen 2002), whatever ``ci_objective``.
  Reported weights: ω.
* ``best_source`` (optional) — the single most accurate source (monograph §1.3 (c)): the
  report with the smallest position-error trace tr C_n[0:3, 0:3] (m²; the velocity block is in
  other units), unchanged. Weights one-hot.

Single-source targets: every method returns the report unchanged with weight [1.0].
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np
from numpy.typing import NDArray

from tertiary.stages.fusion.base import EIG_FLOOR, F, Fused, Ix, Layout, chol, inv_spd, keep_single, mix, per_row, segsum, sym
from tertiary.stages.fusion.config import CI_OBJECTIVES
from tertiary.stages.fusion.registry import FusionMethod, register

__all__ = [
    "apriori_weights", "ci_pair_weights", "fuse_apriori", "fuse_arithmetic", "fuse_best_source",
    "fuse_covariance_intersection", "fuse_information", "fuse_weighted", "information_mix", "onehot_min",
]

_GOLDEN_ITERATIONS = 60  # bracket 0.618^60 ≈ 3e-13 of [0, 1]


def fuse_arithmetic(x: F, cov: F, starts: Ix) -> Fused:
    """Arithmetic mean (4.1): x = (1/N) Σ x_n, P = (1/N²) Σ C_n; weights 1/N."""
    n_row = per_row(np.diff(np.append(starts, len(x))), starts, len(x)).astype(float)
    w = 1.0 / n_row
    xf, pf = mix(x, cov, w, starts)
    return keep_single(Fused(xf, pf, w), x, cov, starts)


def apriori_weights(nominal_var: F, starts: Ix) -> F:
    """Per-coordinate a-priori weights (4.3)–(4.4) for N radars, shape (n, 3):
    b_{n,c} = σ⁻²_{n,c} / Σ_m σ⁻²_{m,c}."""
    if not (np.isfinite(nominal_var).all() and (nominal_var > 0).all()):
        raise ValueError("apriori: nominal_var must be finite and positive in every row")
    inv = 1.0 / nominal_var
    return inv / per_row(segsum(inv, starts), starts, len(inv))


def fuse_apriori(x: F, cov: F, nominal_var: F, starts: Ix) -> Fused:
    """A-priori weights (4.3)–(4.4) per coordinate; velocity uses its position axis's weight.

    P = Σ B_n C_n B_n (independent radars). Reported weight: mean of the x, y, z weights."""
    b3 = apriori_weights(nominal_var, starts)
    xf, pf = mix(x, cov, np.tile(b3, 2), starts)
    return keep_single(Fused(xf, pf, b3.mean(axis=1)), x, cov, starts)


def fuse_weighted(x: F, cov: F, w: F, starts: Ix) -> Fused:
    """(4.72) with given per-row weights on every coordinate: x = Σ b_n x_n, P = Σ b_n² C_n."""
    xf, pf = mix(x, cov, w, starts)
    return keep_single(Fused(xf, pf, w), x, cov, starts)


# ---------------------------------------------------------------------------
# information fusion and covariance intersection
# ---------------------------------------------------------------------------


def information_mix(x: F, cov: F, omega: F, starts: Ix, cov_inv: F | None = None) -> Fused:
    """P⁻¹ = Σ ω_n C_n⁻¹, x = x_ref + P Σ ω_n C_n⁻¹ (x_n − x_ref) (x_ref: the group's first
    row, which leaves identical reports exactly unchanged); weights tr(P ω_n C_n⁻¹)/6.
    ``cov_inv``: the C_n⁻¹ when already computed (shared by information fusion and CI)."""
    n = len(x)
    info = omega[:, None, None] * (inv_spd(cov) if cov_inv is None else cov_inv)
    pf = inv_spd(segsum(info, starts))  # inv_spd reads the symmetric part: no sym needed
    dx = x - per_row(x[starts], starts, n)
    xf = x[starts] + np.einsum("gij,gj->gi", pf, segsum(np.einsum("nij,nj->ni", info, dx), starts))
    w = np.einsum("nij,nji->n", per_row(pf, starts, n), info) / 6.0
    w = w / per_row(segsum(w, starts), starts, n)
    return Fused(xf, pf, w)


def fuse_information(x: F, cov: F, starts: Ix, cov_inv: F | None = None) -> Fused:
    """Inverse-covariance fusion: P = (Σ C_n⁻¹)⁻¹, x = P Σ C_n⁻¹ x_n."""
    res = information_mix(x, cov, np.ones(len(x)), starts, cov_inv)
    return keep_single(res, x, cov, starts)


def _ci_profile(c1: F, c2: F) -> tuple[F, F, F]:
    """Simultaneous diagonalisation of a pair: C2 = L Lᵀ, L⁻¹ C1 L⁻ᵀ = U Γ Uᵀ, W = L U.

    Then P(ω) = W diag(γ/(ω + γ(1−ω))) Wᵀ, so tr P = Σ a_k γ_k/(ω + γ_k(1−ω)) with
    a_k = ‖W_k‖², and log det P = const − Σ log(ω + γ_k(1−ω)). Returns (γ, a, W)."""
    lower = chol(c2)
    linv = np.linalg.solve(lower, np.broadcast_to(np.eye(6), lower.shape))
    gam, u = np.linalg.eigh(sym(linv @ sym(c1) @ np.swapaxes(linv, -1, -2)))
    gam = np.maximum(gam, EIG_FLOOR * np.maximum(gam.max(axis=-1, keepdims=True), 1e-300))
    w = lower @ u
    return gam, np.einsum("gik,gik->gk", w, w), w


def _ci_objective(omega: F, gam: F, a: F, objective: str) -> F:
    """tr P(ω) or log det P(ω) up to a constant (both convex in ω ∈ [0, 1])."""
    den = omega[:, None] + gam * (1.0 - omega[:, None])
    if objective == "det":
        return -np.log(den).sum(axis=1)
    return (a * gam / den).sum(axis=1)


def _golden_min(f: Callable[[F], F], size: int, atol: float = 0.0) -> F:
    """Minimiser on [0, 1] of convex functions, vectorised over groups (golden section;
    0.5 and the endpoints are candidates too; ties within 1e-12·|f| + ``atol`` prefer them
    in that order)."""
    phi = (np.sqrt(5.0) - 1.0) / 2.0
    lo, hi = np.zeros(size), np.ones(size)
    c, d = hi - phi * (hi - lo), lo + phi * (hi - lo)
    fc, fd = f(c), f(d)
    for _ in range(_GOLDEN_ITERATIONS):
        left = fc <= fd
        hi, lo = np.where(left, d, hi), np.where(left, lo, c)
        new = np.where(left, hi - phi * (hi - lo), lo + phi * (hi - lo))
        fnew = f(new)
        c, d = np.where(left, new, d), np.where(left, c, new)
        fc, fd = np.where(left, fnew, fd), np.where(left, fc, fnew)
    # candidates in order of preference; a near-tie (flat objective, e.g. identical
    # covariances) goes to equal weights rather than to wherever rounding led the search
    cand = np.stack([np.full(size, 0.5), 0.5 * (lo + hi), np.zeros(size), np.ones(size)])
    vals = np.stack([f(v) for v in cand])
    best = vals.min(axis=0)
    pick = np.argmax(vals <= best + 1e-12 * np.abs(best) + atol, axis=0)
    return cand[pick, np.arange(size)]


def ci_pair_weights(c1: F, c2: F, objective: str = "trace") -> F:
    """ω of the first source of each pair, minimising tr P or det P (two-source CI)."""
    gam, a, _ = _ci_profile(c1, c2)
    atol = 1e-12 if objective == "det" else 0.0  # log det is O(1) near a tie, tr P is not
    return _golden_min(lambda om: _ci_objective(om, gam, a, objective), len(c1), atol)


def fuse_covariance_intersection(x: F, cov: F, starts: Ix, objective: str = "trace",
                                 cov_inv: F | None = None) -> Fused:
    """Covariance intersection: P⁻¹ = Σ ω_n C_n⁻¹, x = P Σ ω_n C_n⁻¹ x_n.

    Two sources: ω optimal for ``objective``; more: fast CI ω_n ∝ 1/tr C_n (Niehsen 2002)."""
    if objective not in CI_OBJECTIVES:
        raise ValueError(f"objective must be one of {CI_OBJECTIVES}, got {objective!r}")
    n = len(x)
    tr = np.einsum("nii->n", cov)
    omega = (1.0 / tr) / per_row(segsum(1.0 / tr, starts), starts, n)
    counts = np.diff(np.append(starts, n))
    first = starts[counts == 2]
    if len(first):
        om = ci_pair_weights(cov[first], cov[first + 1], objective)
        omega[first], omega[first + 1] = om, 1.0 - om
    res = information_mix(x, cov, omega, starts, cov_inv)
    res = Fused(res.x, res.cov, omega)
    return keep_single(res, x, cov, starts)


def onehot_min(v: F, starts: Ix) -> F:
    """1.0 at the first row of each group holding the group's minimum of ``v`` (NaN never wins
    unless the whole group is NaN: then the first row), 0 elsewhere."""
    n = len(v)
    key = np.where(np.isnan(v), np.inf, v)
    gid = np.repeat(np.arange(len(starts)), np.diff(np.append(starts, n)))
    low = np.minimum.reduceat(key, starts)[gid]
    hit = key == low
    first = np.minimum.reduceat(np.where(hit, np.arange(n), n), starts)
    w = np.zeros(n)
    w[first] = 1.0
    return w


def fuse_best_source(x: F, cov: F, starts: Ix) -> Fused:
    """The single most accurate source (monograph §1.3 (c)): each group's report with the smallest
    position-error trace tr C_n[0:3, 0:3], state and covariance unchanged; weights one-hot."""
    w = onehot_min(np.einsum("nii->n", cov[:, :3, :3]), starts)
    pick = np.flatnonzero(w)
    return Fused(x[pick].copy(), cov[pick].copy(), w)


# ---------------------------------------------------------------------------
# registration
# ---------------------------------------------------------------------------


def _apriori_plot_weights(a: Mapping[str, NDArray], lay: Layout, idx: Ix, rp: F, starts: Ix) -> F:
    """The fresh plots of ``apriori`` take the per-coordinate a-priori weights."""
    return apriori_weights(a["nominal_var"], lay.starts)[idx]


def _best_plot(a: Mapping[str, NDArray], lay: Layout, idx: Ix, rp: F, starts: Ix) -> F:
    """``best_source`` keeps the most accurate fresh plot (smallest tr R)."""
    return onehot_min(np.einsum("nii->n", rp), starts)


register(FusionMethod("arithmetic", "weighted", lambda b: fuse_arithmetic(b.x, b.cov, b.starts), rank=0))
register(FusionMethod("apriori", "weighted", lambda b: fuse_apriori(b.x, b.cov, b.col("nominal_var"), b.starts),
                      rank=1, plot_weights=_apriori_plot_weights))
register(FusionMethod("information", "weighted", lambda b: fuse_information(b.x, b.cov, b.starts, b.cov_inv),
                      rank=4, info_plots=True, shares_cov_inv=True))
register(FusionMethod("covariance_intersection", "weighted",
                      lambda b: fuse_covariance_intersection(b.x, b.cov, b.starts, b.run.cfg.ci_objective, b.cov_inv),
                      rank=5, info_plots=True, shares_cov_inv=True))
register(FusionMethod("best_source", "weighted", lambda b: fuse_best_source(b.x, b.cov, b.starts), rank=7,
                      default=False, plot_weights=_best_plot))
