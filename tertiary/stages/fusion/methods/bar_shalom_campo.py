"""Track-to-track fusion with the common-process-noise cross-covariance (``bar_shalom_campo``):
Bar-Shalom–Campo for two sources, the BLUE of N correlated estimates for more, with the
cross-covariance P_ij = ρ C_i^{1/2} C_j^{1/2} between the radars' tracks
(:func:`fuse_bar_shalom_campo`). Reported weight tr W_n / 6."""

from __future__ import annotations

import numpy as np

from tertiary.stages.fusion.base import EIG_FLOOR, F, Fused, Ix, inv_spd, keep_single, per_row, segsum, sym
from tertiary.stages.fusion.registry import FusionMethod, register

__all__ = ["fuse_bar_shalom_campo"]


def _spd_roots(c: F) -> tuple[F, F]:
    """C⁻¹ and the symmetric C^{-1/2} of symmetric covariances (eigenvalues floored at
    1e-12 × the largest, as :func:`chol`)."""
    w, v = np.linalg.eigh(sym(c))
    w = np.maximum(w, EIG_FLOOR * np.maximum(w.max(axis=-1, keepdims=True), 1e-300))
    vt = np.swapaxes(v, -1, -2)
    return (v / w[..., None, :]) @ vt, (v / np.sqrt(w)[..., None, :]) @ vt


def fuse_bar_shalom_campo(x: F, cov: F, starts: Ix, rho: float = 0.4) -> Fused:
    """Track-to-track fusion with the common-process-noise cross-covariance.

    The radars' track errors of one target are correlated because every local filter follows
    the same manoeuvre (common process noise). Two sources: Bar-Shalom & Campo (1986)

        x = x₁ + (P₁ − P₁₂)(P₁ + P₂ − P₁₂ − P₂₁)⁻¹ (x₂ − x₁),
        P = P₁ − (P₁ − P₁₂)(P₁ + P₂ − P₁₂ − P₂₁)⁻¹ (P₁ − P₂₁).                       (BC)

    The fusion centre does not see the local gains needed for the exact cross-covariance
    recursion, so P_ij uses the constant-correlation approximation (Bar-Shalom & Li 1995,
    *Multitarget-multisensor tracking*, §8.3): P_ij = ρ S_i S_j, S_i = C_i^{1/2} (symmetric
    root). N sources — the generalisation: the BLUE of N correlated estimates of one state
    (Chang, Saha & Bar-Shalom 1997), x = (Hᵀ Σ⁻¹ H)⁻¹ Hᵀ Σ⁻¹ x̄ with the 6N×6N joint covariance
    Σ_ij = P_ij, H = stacked identities; it reduces to (BC) for N = 2. With this P_ij,
    Σ = S̃ (M ⊗ I₆) S̃, S̃ = blockdiag(S_i), M = ρ 11ᵀ + (1 − ρ) I, whose inverse is known:
    M⁻¹ = (I − c 11ᵀ)/(1 − ρ), c = ρ / (1 + (N − 1)ρ). Hence, summing the blocks of Σ⁻¹,

        P⁻¹ = [Σ_i C_i⁻¹ − c (Σ_i S_i⁻¹)(Σ_j S_j⁻¹)] / (1 − ρ),
        x   = P [Σ_i C_i⁻¹ x_i − c (Σ_i S_i⁻¹)(Σ_j S_j⁻¹ x_j)] / (1 − ρ),

    segment sums over each group (no per-group loop). Weight of source j:
    W_j = P [C_j⁻¹ − c (Σ_i S_i⁻¹) S_j⁻¹]/(1 − ρ) (Σ_j W_j = I); reported tr W_j / 6. ρ = 0 is
    information fusion."""
    if not 0.0 <= rho < 1.0:
        raise ValueError(f"rho must lie in [0, 1), got {rho}")
    n = len(x)
    n_row = per_row(np.diff(np.append(starts, n)), starts, n).astype(float)
    c = rho / (1.0 + (n_row - 1.0) * rho)
    cinv, sinv = _spd_roots(cov)
    dx = x - per_row(x[starts], starts, n)          # relative to the group's first source
    s_sum = segsum(sinv, starts)
    s_sum_row = per_row(s_sum, starts, n)
    c_g = c[starts]
    info = (segsum(cinv, starts) - c_g[:, None, None] * s_sum @ s_sum) / (1.0 - rho)
    pf = inv_spd(info)
    vec = (segsum(np.einsum("nij,nj->ni", cinv, dx), starts)
           - c_g[:, None] * np.einsum("gij,gj->gi", s_sum, segsum(np.einsum("nij,nj->ni", sinv, dx), starts)))
    xf = x[starts] + np.einsum("gij,gj->gi", pf, vec / (1.0 - rho))
    wmat = (cinv - c[:, None, None] * s_sum_row @ sinv) / (1.0 - rho)
    w = np.einsum("nij,nji->n", per_row(pf, starts, n), wmat) / 6.0
    w = w / per_row(segsum(w, starts), starts, n)
    return keep_single(Fused(xf, pf, w), x, cov, starts)


register(FusionMethod("bar_shalom_campo", "bar_shalom_campo",
                      lambda b: fuse_bar_shalom_campo(b.x, b.cov, b.starts, b.run.cfg.bc_rho), rank=6, info_plots=True))
