"""The posterior Cramér–Rao bound's recursion (T34) on the bound's model M (9 states, per axis
constant acceleration with the truth's rank-one deviations; :mod:`tertiary.evaluation.bound`),
compiled (numba, ``cache=True``).

:func:`tertiary.evaluation.bound.pcrb_linear` runs the recursion vectorised over aircraft per event rank:
a few numpy calls on stacks of 9×9 matrices per rank, and an aircraft seen for hours keeps the
loop going with a handful of sequences. Here each aircraft's events run one after another.
Φ and Q are block diagonal (one 3×3 block per axis: the constant-acceleration φ(τ) and d dᵀ), so
the prediction is done per block; the update is (T34) with H selecting the three positions (a
plot) or the three velocities (a downlinked velocity) and the 3×3 innovation matrix solved by
Cholesky. :func:`tertiary.evaluation.bound.pcrb_linear` stays the reference (compared in the
tests).
"""

from __future__ import annotations

import numba
import numpy as np
from numba import types as nbt

from tertiary.core.jit import register_kernel

_jit = numba.njit(cache=True, error_model="numpy", nogil=True)

#: the positions and velocities of the 9-state (x, ẋ, ẍ, y, ẏ, ÿ, z, ż, z̈)
_POS = (0, 3, 6)


@_jit
def _predict(p, tau, dev, phi, tmp):
    """P ← Φ P Φᵀ + Q in place: Φ = blockdiag(φ, φ, φ), φ the 3×3 constant-acceleration
    transition over ``tau`` (written into ``phi``, zero below the diagonal), Q = blockdiag(d_x d_xᵀ,
    d_y d_yᵀ, d_z d_zᵀ) (``dev`` (3, 3): axis, (p, v, a))."""
    phi[0, 1] = phi[1, 2] = tau
    phi[0, 2] = 0.5 * tau * tau
    for a in range(3):
        for b in range(3):
            for i in range(3):                 # tmp = block(a, b) of P Φᵀ
                for j in range(3):
                    s = 0.0
                    for m in range(3):
                        s += p[3 * a + i, 3 * b + m] * phi[j, m]
                    tmp[3 * a + i, 3 * b + j] = s
    for a in range(3):
        for b in range(3):
            for i in range(3):
                for j in range(3):
                    s = 0.0
                    for m in range(3):
                        s += phi[i, m] * tmp[3 * a + m, 3 * b + j]
                    p[3 * a + i, 3 * b + j] = s + (dev[a, i] * dev[a, j] if a == b else 0.0)


@_jit
def _update(p, r, ph, s, tmp, off):
    """P ← P − P Hᵀ (H P Hᵀ + R)⁻¹ H P, symmetrised; H selects the positions (``off`` 0) or the
    velocities (``off`` 1)."""
    for i in range(9):
        for k in range(3):
            ph[i, k] = p[i, _POS[k] + off]
    for i in range(3):
        for j in range(3):
            s[i, j] = ph[_POS[i] + off, j] + r[i, j]
    # Cholesky S = L Lᵀ (S is the positions' bound plus a covariance: positive definite)
    l00 = np.sqrt(s[0, 0])
    l10 = s[1, 0] / l00
    l20 = s[2, 0] / l00
    l11 = np.sqrt(s[1, 1] - l10 * l10)
    l21 = (s[2, 1] - l20 * l10) / l11
    l22 = np.sqrt(s[2, 2] - l20 * l20 - l21 * l21)
    for i in range(9):                          # K = P Hᵀ S⁻¹, row by row: L Lᵀ kᵢ = (P Hᵀ)ᵢ
        y0 = ph[i, 0] / l00
        y1 = (ph[i, 1] - l10 * y0) / l11
        y2 = (ph[i, 2] - l20 * y0 - l21 * y1) / l22
        k2 = y2 / l22
        k1 = (y1 - l21 * k2) / l11
        k0 = (y0 - l10 * k1 - l20 * k2) / l00
        for j in range(9):
            tmp[i, j] = p[i, j] - (k0 * ph[j, 0] + k1 * ph[j, 1] + k2 * ph[j, 2])
    for i in range(9):
        for j in range(9):
            p[i, j] = 0.5 * (tmp[i, j] + tmp[j, i])


@_jit
def pcrb_ca9(tau, dev, r_eq, has, vel, starts, lengths, p0, slot, out, p_end):
    """(T34) over every sequence g (rows ``starts[g] : starts[g] + lengths[g]``, time order):
    from ``p0[g]`` at its first row, the prediction over ``tau[i]`` from the previous row with
    the deviations ``dev[i]`` (3 axes × (p, v, a)) of model M, then the update with ``r_eq[i]``
    where ``has[i]``, of the positions, or of the velocities where ``vel[i]``. At rows with
    ``slot[i] >= 0``, ``out[slot[i]]`` = (tr P_pos,
    P_xx + P_yy, tr P_vel) after the update; ``p_end[g]``: P after the sequence's last row (the
    recursion carried on from there by a later call with it as ``p0``)."""
    p = np.empty((9, 9))
    tmp = np.empty((9, 9))
    ph = np.empty((9, 3))
    s = np.empty((3, 3))
    phi = np.eye(3)
    for g in range(len(starts)):
        first = starts[g]
        p[:, :] = p0[g]
        for i in range(first, first + lengths[g]):
            if i > first:
                _predict(p, tau[i], dev[i], phi, tmp)
            if has[i]:
                _update(p, r_eq[i], ph, s, tmp, 1 if vel[i] else 0)
            k = slot[i]
            if k >= 0:
                out[k, 0] = p[0, 0] + p[3, 3] + p[6, 6]
                out[k, 1] = p[0, 0] + p[3, 3]
                out[k, 2] = p[1, 1] + p[4, 4] + p[7, 7]
        p_end[g] = p


def _signature() -> tuple:
    """The one signature :func:`tertiary.evaluation.bound.bound_stage` calls it with."""
    f1, f2, f3 = (nbt.Array(nbt.float64, k, "C") for k in (1, 2, 3))
    i1, b1 = nbt.Array(nbt.int64, 1, "C"), nbt.Array(nbt.boolean, 1, "C")
    return (f1, f3, f3, b1, b1, i1, i1, f3, i1, f2, f3)


register_kernel("pcrb", __name__, pcrb_ca9, _signature)
