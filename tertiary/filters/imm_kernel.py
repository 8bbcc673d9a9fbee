"""The IMM's prediction and update per track, compiled (numba, ``cache=True``): the equations of
:mod:`tertiary.filters.imm` written out per track, used by
:class:`~tertiary.filters.imm.IMMFilter` when its q is isotropic (the numpy path
stays the reference, compared in the tests)."""

from __future__ import annotations

import numba
import numpy as np
from numba import types as nbt

from tertiary.core.jit import register_kernel

__all__ = ["imm_output_kernel", "imm_predict_kernel", "imm_update_kernel", "imm_velocity_kernel"]


def _imm_predict_py(x, p, mu, dt, omegas, tpm, q, xv, pv, qz):  # noqa: ANN001, ANN202 - numba kernel
    """One IMM + vertical CV prediction per track, written out for numba (same equations as
    :func:`~.imm.imm_mix`, :func:`~.imm.a_ct`, :func:`~.imm.q_ct` (isotropic q) and the vertical CV prediction of
    :class:`~.imm.IMMFilter`):
    c̄ = πᵀμ, μ^{i|j} = π_ij μ_i / c̄_j, mixed x̄_j, P̄_j (spread about the mixed mean), then
    x⁻_j = A_j x̄_j, P⁻_j = sym(A_j P̄_j A_jᵀ + Q_j). Per-track work, so the interpreter cost
    per epoch no longer grows with the number of numpy calls of the model set."""
    b_n, m_n = mu.shape
    xo = np.empty_like(x)
    po = np.empty_like(p)
    co = np.empty_like(mu)
    xvo = np.empty_like(xv)
    pvo = np.empty_like(pv)
    w = np.empty((m_n, m_n))
    xm = np.empty(4)
    pm = np.empty((4, 4))
    a = np.zeros((4, 4))
    qm = np.zeros((4, 4))
    ap = np.empty((4, 4))
    pi = np.pi
    # the models the TPM lets into each model j (the symmetric grid's turn models mix with
    # themselves and CV alone): src[j, :cnt[j]]
    src = np.empty((m_n, m_n), np.int64)
    cnt = np.zeros(m_n, np.int64)
    for j in range(m_n):
        for i in range(m_n):
            if tpm[i, j] != 0.0:
                src[j, cnt[j]] = i
                cnt[j] += 1
    for b in range(b_n):
        t = dt[b]
        for j in range(m_n):
            c = 0.0
            for i in range(m_n):
                c += mu[b, i] * tpm[i, j]
            co[b, j] = c
            den = c if c > 0 else 1.0
            for i in range(m_n):
                w[i, j] = tpm[i, j] * mu[b, i] / den
        for j in range(m_n):
            # the models mixed into j only, and the upper triangle (P̄_j is symmetric as its
            # terms are); the sums in the order of the dense formulas
            for n in range(4):
                acc = 0.0
                for k in range(cnt[j]):
                    acc += w[src[j, k], j] * x[b, src[j, k], n]
                xm[n] = acc
            for r in range(4):
                for n in range(r, 4):
                    acc = 0.0
                    for k in range(cnt[j]):
                        acc += w[src[j, k], j] * p[b, src[j, k], r, n]
                    for k in range(cnt[j]):
                        i = src[j, k]
                        acc += w[i, j] * (x[b, i, r] - xm[r]) * (x[b, i, n] - xm[n])
                    pm[r, n] = acc
                    pm[n, r] = acc
            # model matrices (a_ct, q_ct): every coefficient exact at ω → 0
            om = omegas[j]
            xx = om * t
            y = xx / pi
            sinc = 1.0 if y == 0.0 else np.sin(pi * y) / (pi * y)
            y2 = xx / (2.0 * pi)
            sh = 1.0 if y2 == 0.0 else np.sin(pi * y2) / (pi * y2)
            h2 = 0.5 * sh * sh
            x2 = xx * xx
            if abs(xx) < 0.5:
                g3 = (1 / 6 - x2 / 120 * (1 - x2 / 42 * (1 - x2 / 72 * (1 - x2 / 110 * (1 - x2 / 156
                                                                                        * (1 - x2 / 210))))))
            else:
                g3 = (xx - np.sin(xx)) / (xx * xx * xx)
            s_w = t * sinc
            c_w = t * xx * h2
            q1_w2 = t * t * h2
            q2_w2 = t * t * xx * g3
            q2_w3 = t ** 3 * g3
            cs, sn = np.cos(xx), np.sin(xx)
            a[0, 0] = a[2, 2] = 1.0
            a[0, 1] = s_w
            a[0, 3] = -c_w
            a[1, 1] = cs
            a[1, 3] = -sn
            a[2, 1] = c_w
            a[2, 3] = s_w
            a[3, 1] = sn
            a[3, 3] = cs
            qm[0, 0] = qm[2, 2] = q * (2.0 * q2_w3)
            qm[0, 1] = qm[1, 0] = qm[2, 3] = qm[3, 2] = q * q1_w2
            qm[0, 3] = qm[3, 0] = q * q2_w2
            qm[1, 2] = qm[2, 1] = q * -q2_w2
            qm[1, 1] = qm[3, 3] = q * t
            for r in range(4):
                acc = 0.0
                for n in range(4):
                    acc += a[r, n] * xm[n]
                xo[b, j, r] = acc
                for n in range(4):
                    acc = 0.0
                    for k in range(4):
                        acc += a[r, k] * pm[k, n]
                    ap[r, n] = acc
            for r in range(4):
                for n in range(4):
                    acc = 0.0
                    for k in range(4):
                        acc += ap[r, k] * a[n, k]
                    po[b, j, r, n] = acc + qm[r, n]
            for r in range(4):
                for n in range(r + 1, 4):
                    v = 0.5 * (po[b, j, r, n] + po[b, j, n, r])
                    po[b, j, r, n] = v
                    po[b, j, n, r] = v
        # vertical CV channel (cv1_predict)
        xvo[b, 0] = xv[b, 0] + t * xv[b, 1]
        xvo[b, 1] = xv[b, 1]
        ap0 = pv[b, 0, 0] + t * pv[b, 1, 0]
        ap1 = pv[b, 0, 1] + t * pv[b, 1, 1]
        p00 = ap0 + ap1 * t + t ** 3 / 3 * qz
        p01 = ap1 + t ** 2 / 2 * qz
        p10 = pv[b, 1, 0] + pv[b, 1, 1] * t + t ** 2 / 2 * qz
        p11 = pv[b, 1, 1] + t * qz
        pvo[b, 0, 0] = p00
        pvo[b, 1, 1] = p11
        pvo[b, 0, 1] = pvo[b, 1, 0] = 0.5 * (p01 + p10)
    return xo, po, co, xvo, pvo


def _models_update_py(x, p, mu, xo, po, muo, b, z0, z1, r, i0, i1, mu_floor, k, ks, lw):  # noqa: ANN001, ANN202
    """Every model of track ``b`` updated with the measurement (``z0``, ``z1``) of its state
    components ``i0``, ``i1`` (covariance ``r``, 2 × 2) into ``xo``, ``po``, and its mode
    probabilities into ``muo`` (:func:`~.imm.imm_update`: log-domain likelihoods, μ floor);
    ``k``, ``ks``, ``lw``: scratch."""
    m_n, n_x = mu.shape[1], x.shape[2]
    log2pi = np.log(2.0 * np.pi)
    for j in range(m_n):
        m00 = p[b, j, i0, i0] + r[0, 0]
        m01 = p[b, j, i0, i1] + r[0, 1]
        m10 = p[b, j, i1, i0] + r[1, 0]
        m11 = p[b, j, i1, i1] + r[1, 1]
        dm = m00 * m11 - m01 * m10
        n00, n01, n10, n11 = m11 / dm, -m01 / dm, -m10 / dm, m00 / dm
        v0 = z0 - x[b, j, i0]
        v1 = z1 - x[b, j, i1]
        for n in range(n_x):
            h0, h1 = p[b, j, n, i0], p[b, j, n, i1]
            k[n, 0] = h0 * n00 + h1 * n10
            k[n, 1] = h0 * n01 + h1 * n11
            ks[n, 0] = k[n, 0] * m00 + k[n, 1] * m10
            ks[n, 1] = k[n, 0] * m01 + k[n, 1] * m11
            xo[b, j, n] = x[b, j, n] + k[n, 0] * v0 + k[n, 1] * v1
        for q in range(n_x):
            for n in range(n_x):
                po[b, j, q, n] = p[b, j, q, n] - (ks[q, 0] * k[n, 0] + ks[q, 1] * k[n, 1])
        for q in range(n_x):
            for n in range(q + 1, n_x):
                v = 0.5 * (po[b, j, q, n] + po[b, j, n, q])
                po[b, j, q, n] = v
                po[b, j, n, q] = v
        sn0 = n00 * v0 + n01 * v1
        sn1 = n10 * v0 + n11 * v1
        loglik = -0.5 * (v0 * sn0 + v1 * sn1) - 0.5 * np.log(dm) - log2pi
        lw[j] = np.log(max(mu[b, j], 1e-300)) + loglik
    top = lw[0]
    for j in range(1, m_n):            # NaN wins, as in ndarray.max
        if lw[j] > top or lw[j] != lw[j]:
            top = lw[j]
    tot = 0.0
    for j in range(m_n):
        lw[j] = np.exp(lw[j] - top)
        tot += lw[j]
    for j in range(m_n):
        lw[j] = lw[j] / tot
    if mu_floor > 0:
        tot = 0.0
        for j in range(m_n):
            lw[j] = max(lw[j], mu_floor)
            tot += lw[j]
        for j in range(m_n):
            lw[j] = lw[j] / tot
    for j in range(m_n):
        muo[b, j] = lw[j]


# compiled before the kernels that call it (numba inlines it into them)
_models_update = numba.njit(cache=True, nogil=True, error_model="numpy")(_models_update_py)


def _imm_update_py(x, p, mu, xv, pv, z, rh, rz, ok, mu_floor):  # noqa: ANN001, ANN202 - numba kernel
    """:meth:`IMMFilter.update` per track, written out for numba (same equations as
    :func:`imm_combine` (innovation and NIS of the combined prediction), :func:`imm_update`
    (model-conditioned updates, log-domain likelihoods, μ floor) and the vertical CV update).
    Tracks without ``ok`` keep x⁻, P⁻, c̄ and get NaN innovations."""
    b_n, m_n = mu.shape
    xo = x.copy()
    po = p.copy()
    muo = mu.copy()
    xvo = xv.copy()
    pvo = pv.copy()
    # np.full and ndarray.max written as loops: their library implementations cost ~1.4 s of
    # compilation on a fresh install, the loops nothing
    nu_o = np.empty((b_n, 3))
    s_o = np.empty((b_n, 3))
    nis_o = np.empty(b_n)
    for b in range(b_n):
        nis_o[b] = np.nan
        for n in range(3):
            nu_o[b, n] = np.nan
            s_o[b, n] = np.nan
    xc = np.empty(4)
    k = np.empty((4, 2))
    ks = np.empty((4, 2))
    lw = np.empty(m_n)
    for b in range(b_n):
        if not ok[b]:
            continue
        # combined prediction: innovation and NIS (gating statistics)
        for n in range(4):
            acc = 0.0
            for j in range(m_n):
                acc += mu[b, j] * x[b, j, n]
            xc[n] = acc
        c00 = 0.0
        c02 = 0.0
        c20 = 0.0
        c22 = 0.0
        for j in range(m_n):
            d0 = x[b, j, 0] - xc[0]
            d2 = x[b, j, 2] - xc[2]
            c00 += mu[b, j] * p[b, j, 0, 0]
            c02 += mu[b, j] * p[b, j, 0, 2]
            c20 += mu[b, j] * p[b, j, 2, 0]
            c22 += mu[b, j] * p[b, j, 2, 2]
        for j in range(m_n):
            d0 = x[b, j, 0] - xc[0]
            d2 = x[b, j, 2] - xc[2]
            c00 += mu[b, j] * d0 * d0
            c02 += mu[b, j] * d0 * d2
            c20 += mu[b, j] * d2 * d0
            c22 += mu[b, j] * d2 * d2
        off = 0.5 * (c02 + c20)
        s00 = c00 + rh[b, 0, 0]
        s01 = off + rh[b, 0, 1]
        s10 = off + rh[b, 1, 0]
        s11 = c22 + rh[b, 1, 1]
        det = s00 * s11 - s01 * s10
        n0 = z[b, 0] - xc[0]
        n1 = z[b, 1] - xc[2]
        nz = z[b, 2] - xv[b, 0]
        sz = pv[b, 0, 0] + rz[b]
        nis_o[b] = (n0 * (s11 / det) * n0 + n0 * (-s01 / det) * n1 + n1 * (-s10 / det) * n0
                    + n1 * (s00 / det) * n1) + nz * nz / sz
        nu_o[b, 0], nu_o[b, 1], nu_o[b, 2] = n0, n1, nz
        s_o[b, 0], s_o[b, 1], s_o[b, 2] = s00, s11, sz
        # model-conditioned updates with H = [[1,0,0,0],[0,0,1,0]]
        _models_update(x, p, mu, xo, po, muo, b, z[b, 0], z[b, 1], rh[b], 0, 2, mu_floor, k, ks, lw)
        # vertical CV channel, H = [1, 0]
        k0 = pv[b, 0, 0] / sz
        k1 = pv[b, 1, 0] / sz
        xvo[b, 0] = xv[b, 0] + k0 * nz
        xvo[b, 1] = xv[b, 1] + k1 * nz
        pvo[b, 0, 0] = pv[b, 0, 0] - sz * k0 * k0
        pvo[b, 1, 1] = pv[b, 1, 1] - sz * k1 * k1
        pvo[b, 0, 1] = pvo[b, 1, 0] = 0.5 * ((pv[b, 0, 1] - sz * k0 * k1) + (pv[b, 1, 0] - sz * k1 * k0))
    return xo, po, muo, xvo, pvo, nu_o, s_o, nis_o


def _imm_velocity_update_py(x, p, mu, z, r, ok, mu_floor):  # noqa: ANN001, ANN202 - numba kernel
    """:func:`~.imm.imm_velocity_update` per track, written out for numba: every model updated
    with the measured horizontal velocity (H picks vx, vy: state indices 1 and 3) and the mode
    probabilities with its likelihood under each model (:func:`~.imm.imm_update` with
    ``h=VEL_IDX``: log-domain likelihoods, μ floor). Tracks without ``ok`` are carried."""
    b_n, m_n = mu.shape
    n_x = x.shape[2]
    xo = x.copy()
    po = p.copy()
    muo = mu.copy()
    k = np.empty((n_x, 2))
    ks = np.empty((n_x, 2))
    lw = np.empty(m_n)
    for b in range(b_n):
        if ok[b]:
            _models_update(x, p, mu, xo, po, muo, b, z[b, 0], z[b, 1], r[b], 1, 3, mu_floor, k, ks, lw)
    return xo, po, muo


def _imm_output_py(x, p, mu, xv, pv):  # noqa: ANN001, ANN202 - numba kernel
    """:meth:`~.imm.IMMFilter.output` per track, written out for numba (same equations as
    :func:`~.imm.imm_combine`: x̂ = Σ_j μ_j x_j, P = sym(Σ_j μ_j P_j + Σ_j μ_j d_j d_jᵀ),
    d_j = x_j − x̂): the state (B, 6) = (x, y, z, vx, vy, vz) and its 6 × 6 covariance, the
    horizontal block from the combination and the vertical CV channel's beside it. The tracker
    asks for it two to three times per epoch, where the numpy path's einsums and scatters cost
    more than the sums themselves."""
    b_n, m_n = mu.shape
    out = np.empty((b_n, 6))
    cov = np.zeros((b_n, 6, 6))
    xc = np.empty(4)
    pc = np.empty((4, 4))
    place = np.array([0, 3, 1, 4])     # (x, vx, y, vy) → their places in (x y z vx vy vz)
    for b in range(b_n):
        for n in range(4):
            acc = 0.0
            for j in range(m_n):
                acc += mu[b, j] * x[b, j, n]
            xc[n] = acc
        for r in range(4):
            for n in range(4):
                acc = 0.0
                for j in range(m_n):
                    acc += mu[b, j] * p[b, j, r, n]
                spread = 0.0
                for j in range(m_n):
                    spread += mu[b, j] * (x[b, j, r] - xc[r]) * (x[b, j, n] - xc[n])
                pc[r, n] = acc + spread
        for r in range(4):
            for n in range(4):
                cov[b, place[r], place[n]] = 0.5 * (pc[r, n] + pc[n, r])
        out[b, 0], out[b, 1], out[b, 2] = xc[0], xc[2], xv[b, 0]
        out[b, 3], out[b, 4], out[b, 5] = xc[1], xc[3], xv[b, 1]
        cov[b, 2, 2] = pv[b, 0, 0]
        cov[b, 2, 5] = pv[b, 0, 1]
        cov[b, 5, 2] = pv[b, 1, 0]
        cov[b, 5, 5] = pv[b, 1, 1]
    return out, cov


# error_model="numpy": x / 0 is inf or nan, as on the numpy path (not an exception), and less
# compilation without the zero checks; the dispatchers compile (or load from numba's on-disk
# cache) on first use
imm_update_kernel = numba.njit(cache=True, nogil=True, error_model="numpy")(_imm_update_py)
imm_predict_kernel = numba.njit(cache=True, nogil=True, error_model="numpy")(_imm_predict_py)
imm_output_kernel = numba.njit(cache=True, nogil=True, error_model="numpy")(_imm_output_py)
imm_velocity_kernel = numba.njit(cache=True, nogil=True, error_model="numpy")(_imm_velocity_update_py)


def _predict_signature() -> tuple:
    f1, f2, f3, f4 = (nbt.Array(nbt.float64, n, "C") for n in (1, 2, 3, 4))
    return (f3, f4, f2, f1, f1, f2, nbt.float64, f2, f3, nbt.float64)


def _update_signature() -> tuple:
    f1, f2, f3, f4 = (nbt.Array(nbt.float64, n, "C") for n in (1, 2, 3, 4))
    return (f3, f4, f2, f2, f3, f2, f3, f1, nbt.Array(nbt.boolean, 1, "C"), nbt.float64)


register_kernel("imm_predict", __name__, imm_predict_kernel, _predict_signature)
register_kernel("imm_update", __name__, imm_update_kernel, _update_signature)


def _velocity_signature() -> tuple:
    f2, f3, f4 = (nbt.Array(nbt.float64, n, "C") for n in (2, 3, 4))
    return (f3, f4, f2, f2, f3, nbt.Array(nbt.boolean, 1, "C"), nbt.float64)


register_kernel("imm_velocity", __name__, imm_velocity_kernel, _velocity_signature)


def _output_signature() -> tuple:
    f2, f3, f4 = (nbt.Array(nbt.float64, n, "C") for n in (2, 3, 4))
    return (f3, f4, f2, f2, f3)


register_kernel("imm_output", __name__, imm_output_kernel, _output_signature)
