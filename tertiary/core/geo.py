"""Geodesy and coordinate conversions, vectorised over arrays.

Frames
------
* WGS-84 geodetic (lat_deg, lon_deg, alt_m) and ECEF (x, y, z) in metres.
* Local ENU tangent plane at an origin (east, north, up) — every radar's local frame and the
  system frame (the processing centre) are ENU frames.
* Radar polar: range (m), azimuth (deg, clockwise from north, [0, 360)), elevation (deg).

Covariances are propagated with J R Jᵀ (seed 002 eq. 12) through every conversion; angles in
covariance matrices are in radians. All functions broadcast over leading array dimensions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_B = WGS84_A * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)
EARTH_RADIUS_M = 6371008.8
#: effective Earth radius factor for standard refraction (4/3 Earth)
REFRACTION_K = 4.0 / 3.0

F64 = NDArray[np.float64]


def _f(a: ArrayLike) -> F64:
    return np.asarray(a, dtype=np.float64)


#: rows per BLAS call in :func:`_rows_times`
BLAS_ROWS = 16_384


def _rows_times(x: F64, m: F64) -> F64:
    """``x @ m`` for stacks of short row vectors (..., k), in blocks of :data:`BLAS_ROWS` rows.

    Each block stays below OpenBLAS's threading threshold: for 3×3 products starting threads
    costs more than the product, and on a busy machine the spinning threads stalled the
    simulator's frame changes tenfold. Same result as one ``x @ m``.
    """
    flat = x.reshape(-1, x.shape[-1])
    out = np.empty((len(flat), m.shape[-1]))
    for lo in range(0, len(flat), BLAS_ROWS):
        np.matmul(flat[lo:lo + BLAS_ROWS], m, out=out[lo:lo + BLAS_ROWS])
    return out.reshape(x.shape[:-1] + (m.shape[-1],))


def sandwich(j: ArrayLike, c: ArrayLike) -> F64:
    """J C Jᵀ for stacks of small matrices: j (..., m, k), c (..., k, k) → (..., m, m).

    One optimised ``einsum`` contraction; numpy's batched ``matmul`` chain is several times
    slower on stacks of 6×6 matrices (it loops over the tiny matrices one at a time).
    """
    return np.einsum("...ij,...jk,...lk->...il", _f(j), _f(c), _f(j), optimize=True)


# --------------------------------------------------------------------------- geodetic / ECEF


def geodetic_to_ecef(lat_deg: ArrayLike, lon_deg: ArrayLike, alt_m: ArrayLike) -> tuple[F64, F64, F64]:
    """WGS-84 geodetic to ECEF."""
    lat, lon, h = np.radians(_f(lat_deg)), np.radians(_f(lon_deg)), _f(alt_m)
    sl, cl = np.sin(lat), np.cos(lat)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sl * sl)
    x = (n + h) * cl * np.cos(lon)
    y = (n + h) * cl * np.sin(lon)
    z = (n * (1.0 - WGS84_E2) + h) * sl
    return x, y, z


def ecef_to_geodetic(x: ArrayLike, y: ArrayLike, z: ArrayLike) -> tuple[F64, F64, F64]:
    """ECEF to WGS-84 geodetic: Bowring's closed-form start, then one fixed-point refinement of
    the latitude (max error 5e-8 m over -500 m … 40 km, all latitudes; Bowring alone: 1.4e-5 m).
    """
    x, y, z = _f(x), _f(y), _f(z)
    p = np.hypot(x, y)
    lon = np.arctan2(y, x)
    theta = np.arctan2(z * WGS84_A, p * WGS84_B)
    lat = np.arctan2(z + WGS84_EP2 * WGS84_B * np.sin(theta) ** 3,
                     p - WGS84_E2 * WGS84_A * np.cos(theta) ** 3)
    for _ in range(1):
        sl = np.sin(lat)
        n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sl * sl)
        cl = np.cos(lat)
        h = np.where(np.abs(cl) > 1e-10, p / cl - n, np.abs(z) - WGS84_B)
        lat = np.arctan2(z, p * (1.0 - WGS84_E2 * n / (n + h)))
    sl, cl = np.sin(lat), np.cos(lat)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sl * sl)
    # numerically stable height for all latitudes
    h = p * cl + z * sl - WGS84_A * WGS84_A / n
    return np.degrees(lat), np.degrees(lon), h


def enu_rotation(lat0_deg: float, lon0_deg: float) -> F64:
    """Rotation matrix R such that enu = R @ (ecef - ecef0)."""
    lat, lon = np.radians(lat0_deg), np.radians(lon0_deg)
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    return np.array([[-so, co, 0.0],
                     [-sl * co, -sl * so, cl],
                     [cl * co, cl * so, sl]])


@dataclass(frozen=True)
class LocalFrame:
    """A local ENU tangent plane at a WGS-84 origin (a radar site or the processing centre)."""

    lat_deg: float
    lon_deg: float
    alt_m: float = 0.0

    @property
    def rotation(self) -> F64:
        return enu_rotation(self.lat_deg, self.lon_deg)

    @property
    def origin_ecef(self) -> F64:
        return np.array(geodetic_to_ecef(self.lat_deg, self.lon_deg, self.alt_m))

    def from_ecef(self, x: ArrayLike, y: ArrayLike, z: ArrayLike) -> tuple[F64, F64, F64]:
        """ECEF to ENU of this frame."""
        d = np.stack([_f(x), _f(y), _f(z)], axis=-1) - self.origin_ecef
        enu = _rows_times(d, self.rotation.T)
        return enu[..., 0], enu[..., 1], enu[..., 2]

    def to_ecef(self, e: ArrayLike, n: ArrayLike, u: ArrayLike) -> tuple[F64, F64, F64]:
        """ENU of this frame to ECEF."""
        enu = np.stack([_f(e), _f(n), _f(u)], axis=-1)
        xyz = _rows_times(enu, self.rotation) + self.origin_ecef
        return xyz[..., 0], xyz[..., 1], xyz[..., 2]

    def from_geodetic(self, lat_deg: ArrayLike, lon_deg: ArrayLike, alt_m: ArrayLike) -> tuple[F64, F64, F64]:
        return self.from_ecef(*geodetic_to_ecef(lat_deg, lon_deg, alt_m))

    def to_geodetic(self, e: ArrayLike, n: ArrayLike, u: ArrayLike) -> tuple[F64, F64, F64]:
        return ecef_to_geodetic(*self.to_ecef(e, n, u))

    def rotation_to(self, other: "LocalFrame") -> F64:
        """Rotation taking a vector from this frame's ENU axes to ``other``'s."""
        return other.rotation @ self.rotation.T

    def offset_in(self, other: "LocalFrame") -> F64:
        """This frame's origin expressed in ``other``'s ENU coordinates."""
        return np.array(other.from_ecef(*self.origin_ecef))


def geodetic_to_enu(lat_deg: ArrayLike, lon_deg: ArrayLike, alt_m: ArrayLike,
                    lat0_deg: float, lon0_deg: float, alt0_m: float) -> tuple[F64, F64, F64]:
    """Geodetic to local ENU at (lat0, lon0, alt0)."""
    return LocalFrame(lat0_deg, lon0_deg, alt0_m).from_geodetic(lat_deg, lon_deg, alt_m)


def enu_to_geodetic(e: ArrayLike, n: ArrayLike, u: ArrayLike,
                    lat0_deg: float, lon0_deg: float, alt0_m: float) -> tuple[F64, F64, F64]:
    """Local ENU at (lat0, lon0, alt0) to geodetic."""
    return LocalFrame(lat0_deg, lon0_deg, alt0_m).to_geodetic(e, n, u)


def local_vector_to_frame(e: ArrayLike, n: ArrayLike, u: ArrayLike, lat_deg: ArrayLike, lon_deg: ArrayLike,
                          frame: LocalFrame) -> tuple[F64, F64, F64]:
    """Vectors given in the ENU axes at each point (lat, lon) — an aircraft's velocity over true
    north and the local vertical — expressed in ``frame``'s ENU axes: v = R₀ R(lat, lon)ᵀ v_local.
    Away from the frame's origin the two differ by the meridian convergence (about Δlon·sin lat
    in azimuth) and the tilt of the local vertical (the great-circle angle to the origin)."""
    lat, lon = np.radians(_f(lat_deg)), np.radians(_f(lon_deg))
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    e, n, u = _f(e), _f(n), _f(u)
    # ECEF components: the columns of R(lat, lon)ᵀ (east, north, up unit vectors) weighted
    ecef = np.stack([-so * e - sl * co * n + cl * co * u,
                     co * e - sl * so * n + cl * so * u,
                     cl * n + sl * u], axis=-1)
    out = _rows_times(ecef, frame.rotation.T)
    return out[..., 0], out[..., 1], out[..., 2]


def frame_vector_to_local(e: ArrayLike, n: ArrayLike, u: ArrayLike, lat_deg: ArrayLike, lon_deg: ArrayLike,
                          frame: LocalFrame) -> tuple[F64, F64, F64]:
    """The inverse of :func:`local_vector_to_frame`: vectors in ``frame``'s ENU axes expressed in
    the ENU axes at each point (lat, lon), v_local = R(lat, lon) R₀ᵀ v (over true north and the
    local vertical there)."""
    ecef = _rows_times(np.stack(np.broadcast_arrays(_f(e), _f(n), _f(u)), axis=-1), frame.rotation)
    lat, lon = np.radians(_f(lat_deg)), np.radians(_f(lon_deg))
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    x, y, z = ecef[..., 0], ecef[..., 1], ecef[..., 2]
    return -so * x + co * y, -sl * co * x - sl * so * y + cl * z, cl * co * x + cl * so * y + sl * z


# --------------------------------------------------------------------------- frame to frame


def frame_to_frame(pos: ArrayLike, src: LocalFrame, dst: LocalFrame, vel: ArrayLike | None = None,
                   cov: ArrayLike | None = None) -> tuple[F64, F64 | None, F64 | None]:
    """Positions (..., 3), optional velocities (..., 3) and covariances (..., 3|6, 3|6) from
    ``src`` ENU to ``dst`` ENU (e.g. radar-local to the system frame).

    The transform is affine (rotation + translation), so the covariance maps exactly by
    M P Mᵀ with M = blockdiag(R, R).
    """
    rot = src.rotation_to(dst)
    p = _rows_times(_f(pos), rot.T) + src.offset_in(dst)
    v = None if vel is None else _rows_times(_f(vel), rot.T)
    c = None
    if cov is not None:
        c = _f(cov)
        c = congruence(np.kron(np.eye(c.shape[-1] // 3), rot), c)
    return p, v, c


def congruence(m: F64, c: ArrayLike) -> F64:
    """M C Mᵀ for one matrix m (k, k) and a stack c (..., k, k): two large matrix products
    over the whole stack (BLAS), much faster than a batched contraction of tiny matrices."""
    c = _f(c)
    k = m.shape[0]
    flat = c.reshape(-1, k, k)
    n = len(flat)
    cm = (flat.reshape(n * k, k) @ m.T).reshape(n, k, k)                              # C Mᵀ
    out = (cm.swapaxes(1, 2).reshape(n * k, k) @ m.T).reshape(n, k, k).swapaxes(1, 2)  # M (C Mᵀ)
    return out.reshape(c.shape)


# --------------------------------------------------------------------------- radar polar


def polar_to_enu(range_m: ArrayLike, azimuth_deg: ArrayLike, elevation_deg: ArrayLike) -> tuple[F64, F64, F64]:
    """Radar polar (azimuth clockwise from north) to radar-local ENU."""
    r, az, el = _f(range_m), np.radians(_f(azimuth_deg)), np.radians(_f(elevation_deg))
    ce = np.cos(el)
    return r * ce * np.sin(az), r * ce * np.cos(az), r * np.sin(el)


def enu_to_polar(e: ArrayLike, n: ArrayLike, u: ArrayLike) -> tuple[F64, F64, F64]:
    """Radar-local ENU to polar: range (m), azimuth (deg in [0, 360)), elevation (deg)."""
    e, n, u = _f(e), _f(n), _f(u)
    horiz = np.hypot(e, n)
    az = np.mod(np.degrees(np.arctan2(e, n)), 360.0)
    az = np.where(az >= 360.0, 0.0, az)  # mod can round up to exactly 360
    return np.hypot(horiz, u), az, np.degrees(np.arctan2(u, horiz))


def polar_jacobian(range_m: ArrayLike, azimuth_deg: ArrayLike, elevation_deg: ArrayLike) -> F64:
    """d(e, n, u)/d(range, azimuth_rad, elevation_rad), shape (..., 3, 3)."""
    r, az, el = np.broadcast_arrays(_f(range_m), np.radians(_f(azimuth_deg)), np.radians(_f(elevation_deg)))
    sa, ca, se, ce = np.sin(az), np.cos(az), np.sin(el), np.cos(el)
    j = np.empty(r.shape + (3, 3))
    j[..., 0, :] = np.stack([ce * sa, r * ce * ca, -r * se * sa], axis=-1)
    j[..., 1, :] = np.stack([ce * ca, -r * ce * sa, -r * se * ca], axis=-1)
    j[..., 2, :] = np.stack([se, np.zeros_like(r), r * ce], axis=-1)
    return j


def polar_cov_to_enu(range_m: ArrayLike, azimuth_deg: ArrayLike, elevation_deg: ArrayLike,
                     cov_polar: ArrayLike) -> F64:
    """Covariance of (range m, azimuth rad, elevation rad) to ENU: J R Jᵀ (seed 002 eq. 12)."""
    return sandwich(polar_jacobian(range_m, azimuth_deg, elevation_deg), cov_polar)


def polar_sigmas_to_enu_cov(range_m: ArrayLike, azimuth_deg: ArrayLike, elevation_deg: ArrayLike,
                            sigma_range_m: ArrayLike, sigma_azimuth_deg: ArrayLike,
                            sigma_elevation_deg: ArrayLike) -> F64:
    """ENU covariance of a plot with independent polar errors of the given standard deviations."""
    r = np.broadcast_shapes(*(np.shape(v) for v in (range_m, azimuth_deg, elevation_deg, sigma_range_m,
                                                    sigma_azimuth_deg, sigma_elevation_deg)))
    d = np.zeros(r + (3, 3))
    d[..., 0, 0] = np.broadcast_to(_f(sigma_range_m) ** 2, r)
    d[..., 1, 1] = np.broadcast_to(np.radians(_f(sigma_azimuth_deg)) ** 2, r)
    d[..., 2, 2] = np.broadcast_to(np.radians(_f(sigma_elevation_deg)) ** 2, r)
    return polar_cov_to_enu(range_m, azimuth_deg, elevation_deg, d)


def conversion_valid(range_m: ArrayLike, sigma_range_m: ArrayLike, sigma_angle_rad: ArrayLike) -> NDArray[np.bool_]:
    """Validity of the linearised polar-to-Cartesian conversion (seed 002 eq. 13):
    r σ_θ² / σ_r < 0.4 and σ_θ < 0.4 rad (range limit (14): r < 0.4 σ_r / σ_θ²)."""
    r, sr, sa = _f(range_m), _f(sigma_range_m), _f(sigma_angle_rad)
    return (r * sa * sa / sr < 0.4) & (sa < 0.4)


def polar_state_to_enu(range_m: ArrayLike, azimuth_deg: ArrayLike, elevation_deg: ArrayLike,
                       range_rate: ArrayLike, azimuth_rate_dps: ArrayLike, elevation_rate_dps: ArrayLike,
                       cov: ArrayLike | None = None) -> tuple[F64, F64, F64 | None]:
    """A polar track state (position and its rates) to ENU position, velocity and 6×6 covariance.

    ``cov`` is the (..., 6, 6) covariance of (r, az, el, ṙ, az˙, el˙) with angles in rad and
    angular rates in rad/s; the result's covariance is J P Jᵀ with the exact Jacobian of
    (e, n, u, ė, ṅ, u̇).
    """
    r, az, el, rd, azd, eld = np.broadcast_arrays(
        _f(range_m), np.radians(_f(azimuth_deg)), np.radians(_f(elevation_deg)),
        _f(range_rate), np.radians(_f(azimuth_rate_dps)), np.radians(_f(elevation_rate_dps)))
    sa, ca, se, ce = np.sin(az), np.cos(az), np.sin(el), np.cos(el)
    pos = np.stack([r * ce * sa, r * ce * ca, r * se], axis=-1)
    # velocity = d/dt of position
    u = np.stack([ce * sa, ce * ca, se], axis=-1)          # dpos/dr
    a = np.stack([ce * ca, -ce * sa, np.zeros_like(r)], axis=-1)  # dpos/daz / r
    b = np.stack([-se * sa, -se * ca, ce], axis=-1)        # dpos/del / r
    vel = rd[..., None] * u + (r * azd)[..., None] * a + (r * eld)[..., None] * b
    if cov is None:
        return pos, vel, None
    # second derivatives of the unit directions
    u_az, u_el = a, b
    a_az = np.stack([-ce * sa, -ce * ca, np.zeros_like(r)], axis=-1)
    a_el = np.stack([-se * ca, se * sa, np.zeros_like(r)], axis=-1)
    b_az = np.stack([-se * ca, se * sa, np.zeros_like(r)], axis=-1)
    b_el = np.stack([-ce * sa, -ce * ca, -se], axis=-1)
    j = np.zeros(r.shape + (6, 6))
    j[..., 0:3, 0] = u
    j[..., 0:3, 1] = r[..., None] * a
    j[..., 0:3, 2] = r[..., None] * b
    j[..., 3:6, 0] = azd[..., None] * a + eld[..., None] * b
    j[..., 3:6, 1] = (rd[..., None] * u_az + (r * azd)[..., None] * a_az + (r * eld)[..., None] * b_az)
    j[..., 3:6, 2] = (rd[..., None] * u_el + (r * azd)[..., None] * a_el + (r * eld)[..., None] * b_el)
    j[..., 3:6, 3] = u
    j[..., 3:6, 4] = r[..., None] * a
    j[..., 3:6, 5] = r[..., None] * b
    return pos, vel, sandwich(j, cov)


def polar_channels_to_enu(range_m: ArrayLike, azimuth_deg: ArrayLike, elevation_deg: ArrayLike,
                          range_rate: ArrayLike, azimuth_rate_dps: ArrayLike, elevation_rate_dps: ArrayLike,
                          p_pos: ArrayLike, p_cross: ArrayLike, p_rate: ArrayLike) -> tuple[F64, F64, F64]:
    """:func:`polar_state_to_enu` for a covariance of decoupled channels.

    ``p_pos``, ``p_cross``, ``p_rate`` are (3, ...): per channel (range, azimuth rad, elevation
    rad) the variance of the coordinate, its covariance with its rate and the variance of the
    rate — the only non-zero terms of P. Returns position and velocity (..., 3) (bit-identical to
    :func:`polar_state_to_enu`) and J P Jᵀ (..., 6, 6), exactly symmetric.

    With J = [[A, 0], [B, A]] by channel columns a_c, b_c and h_c = p00 b_c + p01 a_c,
    g_c = p01 b_c + p11 a_c: J P Jᵀ = Σ_c [[p00 a aᵀ, a hᵀ], [h aᵀ, b hᵀ + a gᵀ]] — 21 sums of a few
    products of (N,) vectors instead of N 6×6 matrix products; structural zeros are skipped.
    """
    r, az, el, rd, azd, eld = (np.asarray(v, dtype=np.float64) for v in (
        range_m, np.radians(_f(azimuth_deg)), np.radians(_f(elevation_deg)),
        range_rate, np.radians(_f(azimuth_rate_dps)), np.radians(_f(elevation_rate_dps))))
    sa, ca, se, ce = np.sin(az), np.cos(az), np.sin(el), np.cos(el)
    u = (ce * sa, ce * ca, se)                    # dpos/dr
    a = (ce * ca, -ce * sa, None)                 # dpos/daz / r (None: structural zero)
    b = (-se * sa, -se * ca, ce)                  # dpos/del / r
    pos = np.stack([r * ce * sa, r * ce * ca, r * se], axis=-1)
    raz, rel = r * azd, r * eld
    vel = np.stack([rd * u[0] + raz * a[0] + rel * b[0], rd * u[1] + raz * a[1] + rel * b[1],
                    rd * u[2] + raz * 0.0 + rel * b[2]], axis=-1)
    a_el = (-se * ca, se * sa, None)              # = d a/d el = d b/d az
    cols_a = (u, _scaled(r, a), _scaled(r, b))    # position rows (and velocity rows of the rates)
    cols_b = (_combine((azd, a), (eld, b)),       # velocity rows of the positions
              _combine((rd, a), (raz, (-u[0], -u[1], None)), (rel, a_el)),
              _combine((rd, b), (raz, a_el), (rel, (-u[0], -u[1], -u[2]))))
    p00, p01, p11 = _f(p_pos), _f(p_cross), _f(p_rate)
    cols_h = [_combine((p00[c], cols_b[c]), (p01[c], cols_a[c])) for c in range(3)]
    cols_g = [_combine((p01[c], cols_b[c]), (p11[c], cols_a[c])) for c in range(3)]
    cols_pa = [_scaled(p00[c], cols_a[c]) for c in range(3)]
    cov = np.empty(r.shape + (6, 6))
    for i in range(3):
        for j in range(3):
            cov[..., i, 3 + j] = cov[..., 3 + j, i] = _dot(((cols_a[c][i], cols_h[c][j]) for c in range(3)), 0.0)
            if j >= i:
                cov[..., i, j] = cov[..., j, i] = _dot(((cols_a[c][i], cols_pa[c][j]) for c in range(3)), 0.0)
                cov[..., 3 + i, 3 + j] = cov[..., 3 + j, 3 + i] = _dot((pair for c in range(3) for pair in (
                    (cols_b[c][i], cols_h[c][j]), (cols_a[c][i], cols_g[c][j]))), 0.0)
    return pos, vel, cov


Vec3 = tuple[F64 | None, F64 | None, F64 | None]


def _scaled(s: F64, v: Vec3) -> Vec3:
    return tuple(None if x is None else s * x for x in v)


def _combine(*terms: tuple[F64, Vec3]) -> Vec3:
    """Σ s·v over (scalar array, 3-vector) terms, component by component."""
    return tuple(_dot((s, v[i]) for s, v in terms) for i in range(3))


def _dot(pairs, zero: float | None = None) -> F64 | float | None:
    """Σ x·y over pairs, skipping structural zeros (None); ``zero`` when every term is zero."""
    terms = [x * y for x, y in pairs if x is not None and y is not None]
    if not terms:
        return zero
    total = terms[0]
    for term in terms[1:]:
        total = total + term
    return total


def elevation_from_altitude(range_m: ArrayLike, target_alt_m: ArrayLike, radar_alt_m: ArrayLike,
                            earth_radius_m: float = EARTH_RADIUS_M * REFRACTION_K) -> F64:
    """Elevation angle (deg) of a target at slant range ``range_m`` and altitude ``target_alt_m``
    seen from a radar at ``radar_alt_m``, on a spherical Earth of radius ``earth_radius_m``
    (default 4/3 Earth for standard refraction; pass the true radius for geometric elevation).

    Law of cosines in the triangle (Earth centre, radar, target):
    (R + h_t)² = (R + h_r)² + r² + 2 r (R + h_r) sin ε.
    """
    r, ht, hr = _f(range_m), _f(target_alt_m), _f(radar_alt_m)
    rr = earth_radius_m + hr
    s = ((earth_radius_m + ht) ** 2 - rr ** 2 - r ** 2) / (2.0 * r * rr)
    return np.degrees(np.arcsin(np.clip(s, -1.0, 1.0)))


def wrap_deg(angle_deg: ArrayLike) -> F64:
    """Wrap an angle difference to [-180, 180)."""
    return np.mod(_f(angle_deg) + 180.0, 360.0) - 180.0


def height_and_rate(pos: ArrayLike, vel: ArrayLike, frame: LocalFrame | None) -> tuple[F64, F64, F64]:
    """Height above the WGS-84 ellipsoid, its rate and the local up unit vector at the target,
    from system-frame ENU positions/velocities ``(n, 3)``.

    h = geodetic height of the ECEF point frame.to_ecef(pos); ḣ = n̂·v with n̂ the ellipsoid
    normal *at the target* (∇h = n̂ exactly), expressed in the system ENU axes — not the
    origin's up (ENU z), which tilts by ρ/R: at ρ = 100 km a level aircraft's z drops
    ρ²/2R ≈ 785 m and a level radial flight at 200 m/s shows v·ρ/R ≈ 3 m/s of false z-rate.

    ``frame=None`` (no origin known): a sphere of radius :data:`EARTH_RADIUS_M` through the
    origin (h measured from the origin's height; the radius of curvature varies by ±0.5 % with
    azimuth, so the height of an aircraft at ρ errs by ≤ 0.005·ρ²/2R: ≤ 9 m at 150 km, ≤ 4 m at
    100 km). Pass the scenario origin whenever it is known.
    Returns (h (n,), ḣ (n,), up (n, 3)).
    """
    p = np.asarray(pos, np.float64).reshape(-1, 3)
    v = np.asarray(vel, np.float64).reshape(-1, 3)
    if frame is None:
        r = EARTH_RADIUS_M
        c = p + np.array([0.0, 0.0, r])
        norm_c = np.sqrt(np.einsum("ij,ij->i", c, c))
        up = c / norm_c[:, None]
        h = norm_c - r
    else:
        lat, lon, h = ecef_to_geodetic(*frame.to_ecef(p[:, 0], p[:, 1], p[:, 2]))
        la, lo = np.radians(lat), np.radians(lon)
        n_ecef = np.column_stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)])
        up = n_ecef @ frame.rotation.T                   # the ECEF normal in the system ENU axes
        h = np.asarray(h, np.float64)
    hdot = np.einsum("ij,ij->i", up, v)
    return h, hdot, up


def up_at_height(frame: LocalFrame, e: ArrayLike, n: ArrayLike, height_m: ArrayLike, iterations: int = 3) -> F64:
    """The up coordinate u in ``frame``'s ENU of the point with east ``e``, north ``n`` (that
    frame) and geodetic height ``height_m`` (WGS-84): a Cartesian plot placed at its Mode C
    height. Fixed point from the spherical drop, u₀ = h − h₀ − (e² + n²)/2R, then
    u ← u + h − h(e, n, u) (the height changes along u at rate ≈ 1: mm after three steps)."""
    e, n, h = _f(e), _f(n), _f(height_m)
    u = h - frame.alt_m - (e * e + n * n) / (2.0 * EARTH_RADIUS_M)
    for _ in range(iterations):
        u = u + h - frame.to_geodetic(e, n, u)[2]
    return u
