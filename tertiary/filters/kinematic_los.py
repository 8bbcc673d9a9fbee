"""Line-of-sight kinematics of monograph chapter 3 (§§3.2–3.3, Tables 3.1–3.2, eqs. 3.1–3.11, 3.61–3.62).

Frames, all vectorised over any leading shape:

* normal frame O x_g y_g z_g: x north, y up, z east (treated as fixed); :func:`enu_to_normal`.
* trajectory frame: x_T along the velocity, reached by the path angle φ about y_g and the
  flight-path angle θ about z_T; Table 3.1 columns (:func:`trajectory_matrix`)
  e_xT = (cosθ cosφ, sinθ, −sinφ cosθ), e_yT = (−sinθ cosφ, cosθ, sinφ sinθ), e_zT = (sinφ, 0, cosφ).
  φ is measured counter-clockwise from north seen from above (φ = −true track), θ up.
* beam (LOS) frame: elevation ε_B, azimuth ε_Г (counter-clockwise from north: ε_Г = −radar
  azimuth); Table 3.2 (:func:`beam_matrix`). As printed, its (OZ_г, OX_л) entry is
  −sin ε_B cos ε_Г, which is not orthonormal; the corrected entry is −cos ε_B sin ε_Г
  (``variant="printed" | "corrected"``).

Kinematics: trajectory-frame acceleration (3.5), LOS velocity (3.9), LOS acceleration (3.11)
with V multiplying all three bracketed terms (as in (3.12), (3.15); the printed (3.11) closes
the bracket early), the LOS load factor n_XL from the trajectory-frame load factor (derived
form of (3.61)) and the range acceleration of (3.62) printed (g·n_XL) or corrected
(g(n_XL − sin ε_B) + (V² − V_L²)/D).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tertiary.core.units import G0

F64 = NDArray[np.float64]
BeamVariant = Literal["corrected", "printed"]
AccVariant = Literal["printed", "corrected"]

__all__ = ["G0", "enu_to_normal", "normal_to_enu", "trajectory_matrix", "beam_matrix", "flight_angles",
           "flight_rates", "los_angles", "los_rates", "trajectory_acceleration", "los_velocity",
           "los_acceleration", "los_cosines", "trajectory_load_factor", "los_load_factor",
           "coordinated_load_factors", "range_acceleration", "range_acceleration_truth", "wrap_pi"]


def _f(a: ArrayLike) -> F64:
    return np.asarray(a, dtype=np.float64)


def wrap_pi(a: ArrayLike) -> F64:
    """Angle(s) wrapped to (−π, π]."""
    return np.pi - np.mod(np.pi - _f(a), 2.0 * np.pi)


def enu_to_normal(v: ArrayLike) -> F64:
    """ENU vectors (..., 3) → normal frame (north, up, east)."""
    v = _f(v)
    return np.stack([v[..., 1], v[..., 2], v[..., 0]], axis=-1)


def normal_to_enu(v: ArrayLike) -> F64:
    """Normal-frame vectors (north, up, east) (..., 3) → ENU."""
    v = _f(v)
    return np.stack([v[..., 2], v[..., 0], v[..., 1]], axis=-1)


def _frame(cb: F64, sb: F64, cg: F64, sg: F64) -> F64:
    """Columns (e_x, e_y, e_z) of the frame reached by angle g about y then b about z (Table 3.1 form)."""
    m = np.empty(np.broadcast(cb, cg).shape + (3, 3))
    m[..., 0, 0], m[..., 1, 0], m[..., 2, 0] = cb * cg, sb, -sg * cb
    m[..., 0, 1], m[..., 1, 1], m[..., 2, 1] = -sb * cg, cb, sg * sb
    m[..., 0, 2], m[..., 1, 2], m[..., 2, 2] = sg, 0.0, cg
    return m


def trajectory_matrix(theta: ArrayLike, phi: ArrayLike) -> F64:
    """Table 3.1: (..., 3, 3) whose columns are e_xT, e_yT, e_zT in the normal frame
    (v_normal = M @ v_trajectory)."""
    th, ph = np.broadcast_arrays(_f(theta), _f(phi))
    return _frame(np.cos(th), np.sin(th), np.cos(ph), np.sin(ph))


def beam_matrix(eps_b: ArrayLike, eps_g: ArrayLike, variant: BeamVariant = "corrected") -> F64:
    """Table 3.2: (..., 3, 3) whose columns are e_xL, e_yL, e_zL (beam frame) in the normal frame.

    ``variant="printed"`` keeps the printed (OZ_г, OX_л) entry −sin ε_B cos ε_Г (not
    orthonormal); ``"corrected"`` uses −cos ε_B sin ε_Г so that e_xL is the unit LOS vector."""
    eb, eg = np.broadcast_arrays(_f(eps_b), _f(eps_g))
    m = _frame(np.cos(eb), np.sin(eb), np.cos(eg), np.sin(eg))
    if variant == "printed":
        m[..., 2, 0] = -np.sin(eb) * np.cos(eg)
    elif variant != "corrected":
        raise ValueError(f"unknown Table 3.2 variant {variant!r}; use 'corrected' or 'printed'")
    return m


def flight_angles(vel_normal: ArrayLike) -> tuple[F64, F64, F64]:
    """Speed V, flight-path angle θ and path angle φ of normal-frame velocities (..., 3), from (3.8)
    v = V (cosθ cosφ, sinθ, −cosθ sinφ)."""
    v = _f(vel_normal)
    speed = np.linalg.norm(v, axis=-1)
    theta = np.arctan2(v[..., 1], np.hypot(v[..., 0], v[..., 2]))
    return speed, theta, np.arctan2(-v[..., 2], v[..., 0])


def flight_rates(vel_normal: ArrayLike, acc_normal: ArrayLike) -> tuple[F64, F64, F64]:
    """V̇, ω_θ = θ̇ and ω_φ = φ̇ from normal-frame velocity and acceleration (derivatives of (3.8))."""
    v, a = _f(vel_normal), _f(acc_normal)
    speed = np.linalg.norm(v, axis=-1)
    hor2 = v[..., 0] ** 2 + v[..., 2] ** 2
    v_dot = np.sum(v * a, axis=-1) / speed
    w_theta = (a[..., 1] * speed - v[..., 1] * v_dot) / (speed * np.sqrt(hor2))
    w_phi = (v[..., 2] * a[..., 0] - v[..., 0] * a[..., 2]) / hor2
    return v_dot, w_theta, w_phi


def los_angles(rel_normal: ArrayLike) -> tuple[F64, F64, F64]:
    """Range D, elevation ε_B and azimuth ε_Г of target-minus-radar vectors (normal frame), from
    e_L = (cos ε_B cos ε_Г, sin ε_B, −cos ε_B sin ε_Г)."""
    r = _f(rel_normal)
    d = np.linalg.norm(r, axis=-1)
    return d, np.arcsin(r[..., 1] / d), np.arctan2(-r[..., 2], r[..., 0])


def los_rates(rel_normal: ArrayLike, vel_normal: ArrayLike) -> tuple[F64, F64, F64]:
    """Ḋ (= V_L), ω_B = ε̇_B and ω_Г = ε̇_Г for a fixed radar (analytic derivatives of :func:`los_angles`)."""
    r, v = _f(rel_normal), _f(vel_normal)
    d = np.linalg.norm(r, axis=-1)
    d_dot = np.sum(r * v, axis=-1) / d
    hor2 = r[..., 0] ** 2 + r[..., 2] ** 2
    w_b = (v[..., 1] * d - r[..., 1] * d_dot) / (d * np.sqrt(hor2))
    w_g = (r[..., 2] * v[..., 0] - r[..., 0] * v[..., 2]) / hor2
    return d_dot, w_b, w_g


def trajectory_acceleration(speed: ArrayLike, v_dot: ArrayLike, w_theta: ArrayLike, w_phi: ArrayLike,
                            theta: ArrayLike) -> F64:
    """(3.5): acceleration in the trajectory frame (..., 3) = (V̇, V ω_θ, −V ω_φ cos θ)."""
    v = _f(speed)
    return np.stack(np.broadcast_arrays(_f(v_dot), v * _f(w_theta), -v * _f(w_phi) * np.cos(_f(theta))), axis=-1)


def los_velocity(speed: ArrayLike, theta: ArrayLike, phi: ArrayLike, eps_b: ArrayLike, eps_g: ArrayLike) -> F64:
    """(3.9): V_L = V [cos θ cos ε_B cos(φ − ε_Г) + sin θ sin ε_B]."""
    th, eb = _f(theta), _f(eps_b)
    return _f(speed) * (np.cos(th) * np.cos(eb) * np.cos(_f(phi) - _f(eps_g)) + np.sin(th) * np.sin(eb))


def los_acceleration(speed: ArrayLike, theta: ArrayLike, w_theta: ArrayLike, phi: ArrayLike, w_phi: ArrayLike,
                     eps_b: ArrayLike, w_b: ArrayLike, eps_g: ArrayLike, w_g: ArrayLike,
                     v_dot: ArrayLike = 0.0, variant: BeamVariant = "corrected") -> F64:
    """(3.11)/(3.32): a_L = dV_L/dt for a fixed radar (= D̈ with the true LOS rates),

        a_L = V̇ c_x + V [cos θ sin ε_B (ω_θ − ω_B cos Δ) + sin θ cos ε_B (ω_B − ω_θ cos Δ)
                         + cos θ cos ε_B sin Δ (ω_Г − ω_φ)],   Δ = φ − ε_Г,

    V multiplying all three terms (the printed (3.11) closes the bracket early). (3.11) is the
    V̇ = 0 case; ``v_dot`` adds the along-track term V̇ c_x (c_x of :func:`los_cosines`).
    ``variant="printed"`` closes the V bracket before the third term as printed (that term then
    lacks the factor V: not an acceleration; kept to measure the erratum's effect)."""
    th, eb, dl = _f(theta), _f(eps_b), _f(phi) - _f(eps_g)
    ct, st, ce, se, cd, sd = np.cos(th), np.sin(th), np.cos(eb), np.sin(eb), np.cos(dl), np.sin(dl)
    wt, wb = _f(w_theta), _f(w_b)
    third = ct * ce * sd * (_f(w_g) - _f(w_phi))
    first_two = ct * se * (wt - wb * cd) + st * ce * (wb - wt * cd)
    if variant == "printed":
        return _f(v_dot) * (se * st + ce * ct * cd) + _f(speed) * first_two + third
    if variant != "corrected":
        raise ValueError(f"unknown (3.11) variant {variant!r}; use 'corrected' or 'printed'")
    return _f(v_dot) * (se * st + ce * ct * cd) + _f(speed) * (first_two + third)


def los_cosines(theta: ArrayLike, phi: ArrayLike, eps_b: ArrayLike, eps_g: ArrayLike) -> tuple[F64, F64, F64]:
    """Components (c_x, c_y, c_z) of the unit LOS vector e_L in the trajectory frame (Tables 3.1 × 3.2)."""
    th, eb, dl = _f(theta), _f(eps_b), _f(eps_g) - _f(phi)
    cx = np.sin(eb) * np.sin(th) + np.cos(eb) * np.cos(th) * np.cos(dl)
    cy = np.sin(eb) * np.cos(th) - np.sin(th) * np.cos(eb) * np.cos(dl)
    return cx, cy, -np.cos(eb) * np.sin(dl)


def trajectory_load_factor(n_x: ArrayLike, n_y: ArrayLike, n_z: ArrayLike, gamma: ArrayLike) -> F64:
    """Surface-force load factor (n_x longitudinal, n_y normal, n_z lateral; bank γ_v, positive
    right wing down) in the trajectory frame: (n_x, n_y cos γ − n_z sin γ, n_y sin γ + n_z cos γ)."""
    g = _f(gamma)
    ny, nz = _f(n_y), _f(n_z)
    return np.stack(np.broadcast_arrays(_f(n_x), ny * np.cos(g) - nz * np.sin(g), ny * np.sin(g) + nz * np.cos(g)), axis=-1)


def los_load_factor(n_x: ArrayLike, n_y: ArrayLike, n_z: ArrayLike, gamma: ArrayLike, theta: ArrayLike,
                    phi: ArrayLike, eps_b: ArrayLike, eps_g: ArrayLike) -> F64:
    """n_XL, the load factor along the LOS ((3.61) in the form derived from Tables 3.1/3.2):

        n_XL = n_x c_x + n_y (cos γ c_y + sin γ c_z) + n_z (−sin γ c_y + cos γ c_z).
    """
    cx, cy, cz = los_cosines(theta, phi, eps_b, eps_g)
    g = _f(gamma)
    return _f(n_x) * cx + _f(n_y) * (np.cos(g) * cy + np.sin(g) * cz) + _f(n_z) * (-np.sin(g) * cy + np.cos(g) * cz)


def coordinated_load_factors(theta: ArrayLike, gamma: ArrayLike, v_dot: ArrayLike = 0.0, w_theta: ArrayLike = 0.0,
                             speed: ArrayLike = 1.0, g: float = G0) -> tuple[F64, F64, F64]:
    """Load factors of coordinated flight (no sideslip, n_z = 0) from θ, bank γ_v and optional
    V̇, ω_θ: n_x = V̇/g + sin θ, n_y = (V ω_θ/g + cos θ)/cos γ (from (3.5) and a = g n − g ŷ)."""
    th = _f(theta)
    n_x = _f(v_dot) / g + np.sin(th)
    n_y = (_f(speed) * _f(w_theta) / g + np.cos(th)) / np.cos(_f(gamma))
    return np.broadcast_arrays(n_x, n_y, np.zeros_like(n_y))


def range_acceleration(n_xl: ArrayLike, eps_b: ArrayLike, speed: ArrayLike, v_los: ArrayLike, rng: ArrayLike,
                       variant: AccVariant = "corrected", g: float = G0) -> F64:
    """The kinematic+dynamic channel's input u, (3.62)/(3.86).

    * ``"printed"``:   u = g n_XL  (no gravity, no LOS-rotation term)
    * ``"corrected"``: u = D̈ = g (n_XL − sin ε_B) + (V² − V_L²)/D
    """
    if variant == "printed":
        return g * _f(n_xl) + 0.0 * _f(rng)
    if variant != "corrected":
        raise ValueError(f"unknown (3.62) variant {variant!r}; use 'printed' or 'corrected'")
    return g * (_f(n_xl) - np.sin(_f(eps_b))) + (_f(speed) ** 2 - _f(v_los) ** 2) / _f(rng)


def range_acceleration_truth(rel_normal: ArrayLike, vel_normal: ArrayLike, acc_normal: ArrayLike) -> F64:
    """Exact D̈ of a fixed radar: a·e_L + (|v|² − V_L²)/D (independent of the angle parametrisation)."""
    r, v, a = _f(rel_normal), _f(vel_normal), _f(acc_normal)
    d = np.linalg.norm(r, axis=-1)
    vl = np.sum(r * v, axis=-1) / d
    return np.sum(r * a, axis=-1) / d + (np.sum(v * v, axis=-1) - vl * vl) / d
