"""Independent oracle tests for ``tertiary.core.geo``.

Oracles
-------
* pymap3d (WGS-84) for geodetic / ECEF / ENU / AER conversions and ENU vector rotations.
* Monte-Carlo sampling of polar errors for the covariance propagation (J R Jᵀ).
* Central finite differences of independently written conversions for the Jacobians.
* Closed-form values (seed 002 eq. 14) for ``conversion_valid``.

Position errors are always measured in metres: geodetic results are compared by mapping both
to ECEF with pymap3d's closed-form forward transform and taking the Euclidean distance, which
turns latitude/longitude differences into metres and stays well defined at the poles.
"""

from __future__ import annotations

import numpy as np
import pymap3d as pm
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tertiary.core import geo

MM = 1e-3  # 1 millimetre
SETTINGS = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# ----------------------------------------------------------------------------- strategies

finite = dict(allow_nan=False, allow_infinity=False)
lat_st = st.one_of(
    st.floats(-90.0, 90.0, **finite),
    st.floats(89.9, 90.0, **finite),      # near / at the north pole
    st.floats(-90.0, -89.9, **finite),    # near / at the south pole
)
lon_st = st.floats(-180.0, 180.0, **finite)
alt_st = st.floats(-500.0, 40_000.0, **finite)
origin_alt_st = st.floats(-500.0, 5_000.0, **finite)


def _a(x) -> np.ndarray:
    """1-element float array (pymap3d's vectorised code path; also a fresh copy)."""
    return np.atleast_1d(np.array(x, dtype=np.float64))


def _geod_dist_m(lat1, lon1, h1, lat2, lon2, h2) -> np.ndarray:
    """Distance in metres between two geodetic points (via pymap3d's closed-form forward)."""
    p1 = np.stack(pm.geodetic2ecef(_a(lat1), _a(lon1), _a(h1)), axis=-1)
    p2 = np.stack(pm.geodetic2ecef(_a(lat2), _a(lon2), _a(h2)), axis=-1)
    return np.linalg.norm(p1 - p2, axis=-1)


def _vec_dist(a, b) -> np.ndarray:
    return np.linalg.norm(np.stack([np.asarray(x) for x in a], -1) - np.stack([np.asarray(x) for x in b], -1),
                          axis=-1)


def _random_geodetic(rng: np.random.Generator, n: int):
    # latitude uniform on the sphere plus an explicit share right next to the poles
    lat = np.degrees(np.arcsin(rng.uniform(-1.0, 1.0, n)))
    k = n // 10
    lat[:k] = rng.choice([-1.0, 1.0], k) * rng.uniform(89.9, 90.0, k)
    lat[k:k + 4] = [90.0, -90.0, 89.999999, -89.999999]
    lon = rng.uniform(-180.0, 180.0, n)
    alt = rng.uniform(-500.0, 40_000.0, n)
    return lat, lon, alt


# observed maxima, printed at the end of the session with ``pytest -s`` (diagnostic only)
MAX_ERR: dict[str, float] = {}


def _record(name: str, value) -> float:
    v = float(np.max(np.abs(value)))
    MAX_ERR[name] = max(MAX_ERR.get(name, 0.0), v)
    return v


@pytest.fixture(scope="session", autouse=True)
def _report_max_errors():
    yield
    if MAX_ERR:
        print("\nmax observed errors (tests/test_geo.py):")
        for k in sorted(MAX_ERR):
            print(f"  {k:45s} {MAX_ERR[k]:.3e}")


# ============================================================================ 1. geodesy


@SETTINGS
@given(lat_st, lon_st, alt_st)
def test_geodetic_to_ecef_matches_pymap3d(lat, lon, alt):
    ours = geo.geodetic_to_ecef(lat, lon, alt)
    ref = pm.geodetic2ecef(_a(lat), _a(lon), _a(alt))
    assert _record("geodetic->ecef [m]", _vec_dist(ours, ref)) <= MM


@SETTINGS
@given(lat_st, lon_st, alt_st)
def test_ecef_to_geodetic_matches_pymap3d_and_truth(lat, lon, alt):
    x, y, z = pm.geodetic2ecef(_a(lat), _a(lon), _a(alt))
    la, lo, h = geo.ecef_to_geodetic(x, y, z)
    rla, rlo, rh = pm.ecef2geodetic(x.copy(), y.copy(), z.copy())
    assert _record("ecef->geodetic vs pymap3d [m]", _geod_dist_m(la, lo, h, rla, rlo, rh)) <= MM
    # and against the generating point itself (ground truth)
    assert _record("ecef->geodetic vs truth [m]", _geod_dist_m(la, lo, h, lat, lon, alt)) <= MM
    assert abs(h - alt) <= MM
    assert -90.0 <= la <= 90.0 and -180.0 <= lo <= 180.0


@SETTINGS
@given(lat_st, lon_st, alt_st, lat_st, lon_st, origin_alt_st)
def test_geodetic_to_enu_matches_pymap3d(lat, lon, alt, lat0, lon0, alt0):
    ours = geo.geodetic_to_enu(lat, lon, alt, lat0, lon0, alt0)
    ref = pm.geodetic2enu(_a(lat), _a(lon), _a(alt), lat0, lon0, alt0)
    assert _record("geodetic->enu [m]", _vec_dist(ours, ref)) <= MM


@SETTINGS
@given(st.floats(-400e3, 400e3, **finite), st.floats(-400e3, 400e3, **finite),
       st.floats(-2_000.0, 40_000.0, **finite), lat_st, lon_st, origin_alt_st)
def test_enu_to_geodetic_matches_pymap3d(e, n, u, lat0, lon0, alt0):
    la, lo, h = geo.enu_to_geodetic(e, n, u, lat0, lon0, alt0)
    rla, rlo, rh = pm.enu2geodetic(_a(e), _a(n), _a(u), lat0, lon0, alt0)
    assert _record("enu->geodetic [m]", _geod_dist_m(la, lo, h, rla, rlo, rh)) <= MM
    # round trip back to ENU
    back = geo.geodetic_to_enu(la, lo, h, lat0, lon0, alt0)
    assert _record("enu->geodetic->enu roundtrip [m]", _vec_dist(back, (e, n, u))) <= MM


@SETTINGS
@given(lat_st, lon_st, alt_st, lat_st, lon_st, origin_alt_st)
def test_ecef_to_enu_matches_pymap3d(lat, lon, alt, lat0, lon0, alt0):
    x, y, z = pm.geodetic2ecef(_a(lat), _a(lon), _a(alt))
    ours = geo.LocalFrame(lat0, lon0, alt0).from_ecef(x, y, z)
    ref = pm.ecef2enu(x, y, z, lat0, lon0, alt0)
    assert _record("ecef->enu [m]", _vec_dist(ours, ref)) <= MM
    back = geo.LocalFrame(lat0, lon0, alt0).to_ecef(*ours)
    assert _record("ecef->enu->ecef roundtrip [m]", _vec_dist(back, (x, y, z))) <= MM


def test_vectorised_batch_10000():
    rng = np.random.default_rng(20240611)
    n = 10_000
    lat, lon, alt = _random_geodetic(rng, n)
    lat0, lon0, alt0 = 47.45, 8.56, 432.0  # a fixed processing centre

    xyz = geo.geodetic_to_ecef(lat, lon, alt)
    assert all(c.shape == (n,) for c in xyz)
    assert _record("batch geodetic->ecef [m]", _vec_dist(xyz, pm.geodetic2ecef(lat, lon, alt))) <= MM

    rx, ry, rz = pm.geodetic2ecef(lat, lon, alt)
    g = geo.ecef_to_geodetic(rx, ry, rz)
    assert all(c.shape == (n,) for c in g)
    ref_g = pm.ecef2geodetic(rx.copy(), ry.copy(), rz.copy())
    assert _record("batch ecef->geodetic vs pymap3d [m]", _geod_dist_m(*g, *ref_g)) <= MM
    assert _record("batch ecef->geodetic vs truth [m]", _geod_dist_m(*g, lat, lon, alt)) <= MM

    enu = geo.geodetic_to_enu(lat, lon, alt, lat0, lon0, alt0)
    assert _record("batch geodetic->enu [m]",
                   _vec_dist(enu, pm.geodetic2enu(lat, lon, alt, lat0, lon0, alt0))) <= MM
    assert _record("batch ecef->enu [m]",
                   _vec_dist(geo.LocalFrame(lat0, lon0, alt0).from_ecef(rx, ry, rz),
                             pm.ecef2enu(rx, ry, rz, lat0, lon0, alt0))) <= MM

    # ENU -> geodetic around several origins, incl. polar ones
    e = rng.uniform(-400e3, 400e3, n)
    nn = rng.uniform(-400e3, 400e3, n)
    u = rng.uniform(-2_000.0, 40_000.0, n)
    for o in [(lat0, lon0, alt0), (89.95, -120.0, 10.0), (-89.99, 45.0, 2800.0), (0.0, 179.99, 0.0),
              (-33.9, 151.2, 6.0)]:
        ours = geo.enu_to_geodetic(e, nn, u, *o)
        ref = pm.enu2geodetic(e, nn, u, *o)
        assert _record("batch enu->geodetic [m]", _geod_dist_m(*ours, *ref)) <= MM

    # broadcasting over a 2-D batch keeps the shape
    g2 = geo.ecef_to_geodetic(rx.reshape(100, 100), ry.reshape(100, 100), rz.reshape(100, 100))
    assert g2[0].shape == (100, 100)
    np.testing.assert_array_equal(g2[2].ravel(), g[2])


# ============================================================================ 2. radar polar


@SETTINGS
@given(st.floats(0.0, 500e3, **finite), st.floats(0.0, 360.0, exclude_max=True, **finite),
       st.floats(-90.0, 90.0, **finite))
def test_polar_to_enu_matches_aer2enu(r, az, el):
    ours = geo.polar_to_enu(r, az, el)
    ref = pm.aer2enu(_a(az), _a(el), _a(r))
    assert _record("polar->enu [m]", _vec_dist(ours, ref)) <= MM


enu_comp = st.one_of(st.floats(-400e3, 400e3, **finite), st.just(0.0), st.just(-0.0),
                     st.floats(-1e-6, 1e-6, **finite))


@SETTINGS
@given(enu_comp, enu_comp, enu_comp)
def test_enu_to_polar_matches_enu2aer(e, n, u):
    r, az, el = geo.enu_to_polar(e, n, u)
    # pymap3d mutates its inputs (zeroes |x| < 1 mm) -> pass copies
    raz, rel, rr = pm.enu2aer(_a(e), _a(n), _a(u))
    assert 0.0 <= az < 360.0
    assert -90.0 <= el <= 90.0
    assert r >= 0.0
    assert abs(r - rr[0]) <= 2 * MM + 1e-12 * r  # pymap3d's 1-mm zeroing alters range by < 2 mm only
    # compare as positions (angles -> metres); pymap3d zeroes components < 1 mm, so the
    # reference itself can be off by up to sqrt(3) mm from the true point: check the true point
    back = geo.polar_to_enu(r, az, el)
    assert _record("enu->polar->enu [m]", _vec_dist(back, (e, n, u))) <= MM
    ref_back = pm.aer2enu(raz, rel, rr)
    assert _vec_dist(back, ref_back)[0] <= 2 * MM
    if min(abs(e), abs(n), abs(u)) >= 1e-3 or (abs(e) >= 1e-3 and abs(n) >= 1e-3):
        horiz = np.hypot(e, n)
        d_az = geo.wrap_deg(az - raz[0])
        assert _record("enu->polar az vs enu2aer [m]", horiz * np.radians(d_az)) <= MM
        assert _record("enu->polar el vs enu2aer [m]", r * np.radians(el - rel[0])) <= MM


@pytest.mark.parametrize("e", [-1e-300, -5e-324, -1e-20, -1e-14, -0.0, 0.0, 1e-300])
@pytest.mark.parametrize("n", [1.0, 100e3, 1e-250])
def test_enu_to_polar_azimuth_never_360(e, n):
    _, az, _ = geo.enu_to_polar(e, n, 1000.0)
    assert 0.0 <= az < 360.0
    if abs(e) <= 1e-12 * n:
        assert min(az, 360.0 - az) < 1e-9  # i.e. (numerically) north
    # vectorised too
    _, azv, _ = geo.enu_to_polar(np.full(4, e), np.full(4, n), np.zeros(4))
    assert np.all((azv >= 0.0) & (azv < 360.0))


def test_enu_to_polar_azimuth_range_batch():
    rng = np.random.default_rng(7)
    e = rng.normal(0, 1e5, 10_000) * rng.choice([1.0, 1e-18, 1e-310], 10_000)
    n = rng.normal(0, 1e5, 10_000)
    r, az, el = geo.enu_to_polar(e, n, rng.uniform(-1e3, 4e4, 10_000))
    assert np.all((az >= 0.0) & (az < 360.0))
    assert az.shape == (10_000,)
    # cardinal directions
    _, az_c, _ = geo.enu_to_polar([0.0, 1.0, 0.0, -1.0], [1.0, 0.0, -1.0, 0.0], 0.0)
    np.testing.assert_allclose(az_c, [0.0, 90.0, 180.0, 270.0], atol=1e-12)


# ============================================================================ 3. frame to frame


def _site_from_system(sys0, dist_m, bearing_deg, site_alt):
    lat, lon, _ = pm.aer2geodetic(_a(bearing_deg), _a(0.0), _a(dist_m), *sys0)
    return geo.LocalFrame(float(lat[0]), float(lon[0]), float(site_alt))


def _oracle_rotation(src: geo.LocalFrame, dst: geo.LocalFrame) -> np.ndarray:
    """Columns: the src-ENU unit vectors expressed in dst-ENU, via pymap3d's vector rotations."""
    eye = np.eye(3)
    u, v, w = pm.enu2uvw(eye[0], eye[1], eye[2], src.lat_deg, src.lon_deg)
    e, n, up = pm.uvw2enu(u, v, w, dst.lat_deg, dst.lon_deg)
    return np.stack([e, n, up], axis=0)  # row i = component i for each unit vector (columns)


@settings(max_examples=60, deadline=None)
@given(st.floats(-75.0, 75.0, **finite), lon_st, st.floats(0.0, 1_000.0, **finite),
       st.floats(50e3, 150e3, **finite), st.floats(0.0, 360.0, **finite), st.floats(0.0, 2_500.0, **finite),
       st.integers(0, 2**32 - 1))
def test_frame_to_frame_matches_pymap3d(lat0, lon0, alt0, dist, bearing, site_alt, seed):
    sys0 = (lat0, lon0, alt0)
    dst = geo.LocalFrame(*sys0)
    src = _site_from_system(sys0, dist, bearing, site_alt)
    rng = np.random.default_rng(seed)
    m = 64
    r = rng.uniform(1e3, 250e3, m)
    az = rng.uniform(0, 360, m)
    el = rng.uniform(-1.0, 20.0, m)
    pos = np.stack(geo.polar_to_enu(r, az, el), axis=-1)
    vel = rng.normal(0, 200.0, (m, 3))
    a = rng.normal(size=(m, 6, 6))
    d = np.diag([50.0, 50.0, 50.0, 5.0, 5.0, 5.0])
    cov6 = d @ a @ np.swapaxes(a, -1, -2) @ d

    p_sys, v_sys, c_sys = geo.frame_to_frame(pos, src, dst, vel=vel, cov=cov6)

    # positions: through geodetic with pymap3d
    glat, glon, gh = pm.enu2geodetic(pos[:, 0], pos[:, 1], pos[:, 2], src.lat_deg, src.lon_deg, src.alt_m)
    ref = np.stack(pm.geodetic2enu(glat, glon, gh, *sys0), axis=-1)
    assert _record("frame_to_frame position [m]", np.linalg.norm(p_sys - ref, axis=-1)) <= MM

    # velocities: pymap3d vector rotation, norm preserved
    ru, rv, rw = pm.enu2uvw(vel[:, 0], vel[:, 1], vel[:, 2], src.lat_deg, src.lon_deg)
    v_ref = np.stack(pm.uvw2enu(ru, rv, rw, *sys0[:2]), axis=-1)
    assert _record("frame_to_frame velocity [m/s]", np.linalg.norm(v_sys - v_ref, axis=-1)) <= 1e-9
    np.testing.assert_allclose(np.linalg.norm(v_sys, axis=-1), np.linalg.norm(vel, axis=-1), rtol=1e-12)

    # covariance: M P Mᵀ with M = blockdiag(R, R), symmetric PSD
    rot = _oracle_rotation(src, dst)
    big = np.kron(np.eye(2), rot)
    c_ref = big @ cov6 @ big.T
    scale = np.linalg.norm(cov6, axis=(-2, -1))[:, None, None]
    assert _record("frame_to_frame cov6 rel", (c_sys - c_ref) / scale) <= 1e-12
    np.testing.assert_allclose(c_sys, np.swapaxes(c_sys, -1, -2), atol=1e-9 * scale.max())
    eig = np.linalg.eigvalsh(0.5 * (c_sys + np.swapaxes(c_sys, -1, -2)))
    assert np.all(eig >= -1e-9 * scale[..., 0])
    np.testing.assert_allclose(np.trace(c_sys, axis1=-2, axis2=-1), np.trace(cov6, axis1=-2, axis2=-1),
                               rtol=1e-12)

    # 3x3 covariance and position-only call
    p2, v2, c3 = geo.frame_to_frame(pos, src, dst, cov=cov6[:, :3, :3])
    assert v2 is None
    np.testing.assert_allclose(c3, rot @ cov6[:, :3, :3] @ rot.T, atol=1e-12 * scale.max())
    np.testing.assert_array_equal(p2, p_sys)
    p3, v3, c4 = geo.frame_to_frame(pos, src, dst)
    assert v3 is None and c4 is None


def test_frame_to_frame_identity_and_inverse():
    f = geo.LocalFrame(46.9, 7.4, 550.0)
    g = geo.LocalFrame(47.5, 8.6, 430.0)
    rng = np.random.default_rng(1)
    pos = rng.uniform(-2e5, 2e5, (100, 3))
    vel = rng.normal(0, 250, (100, 3))
    p, v, _ = geo.frame_to_frame(pos, f, f, vel=vel)
    np.testing.assert_allclose(p, pos, atol=1e-6)
    np.testing.assert_allclose(v, vel, atol=1e-9)
    p1, v1, _ = geo.frame_to_frame(pos, f, g, vel=vel)
    p2, v2, _ = geo.frame_to_frame(p1, g, f, vel=v1)
    assert _record("frame_to_frame roundtrip [m]", np.linalg.norm(p2 - pos, axis=-1)) <= MM
    np.testing.assert_allclose(v2, vel, atol=1e-9)


# ============================================================================ 4. covariances


def _rel_frob(a, b) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def _whitened_err(sample_cov, model_cov) -> float:
    """max |L⁻¹ C_mc L⁻ᵀ − I| with C_model = L Lᵀ (scale-free comparison)."""
    l_inv = np.linalg.inv(np.linalg.cholesky(model_cov))
    w = l_inv @ sample_cov @ l_inv.T
    return float(np.max(np.abs(w - np.eye(len(w)))))


GEOMS = [(10e3, 37.0, 2.0), (50e3, 200.0, 8.0), (120e3, 300.0, 0.5), (200e3, 95.0, 4.0),
         (200e3, 359.9, 25.0)]
N_MC = 200_000


@pytest.mark.parametrize("r0,az0,el0", GEOMS)
def test_polar_sigmas_to_enu_cov_vs_monte_carlo(r0, az0, el0):
    s_r, s_az, s_el = 50.0, 0.1, 0.1
    rng = np.random.default_rng(int(r0) + int(az0 * 10))
    r = r0 + s_r * rng.standard_normal(N_MC)
    az = az0 + s_az * rng.standard_normal(N_MC)
    el = el0 + s_el * rng.standard_normal(N_MC)
    pts = np.stack(pm.aer2enu(az, el, r), axis=-1)  # independent conversion
    c_mc = np.cov(pts, rowvar=False)
    c = geo.polar_sigmas_to_enu_cov(r0, az0, el0, s_r, s_az, s_el)
    assert c.shape == (3, 3)
    assert _record("MC 3x3 rel Frobenius", _rel_frob(c_mc, c)) < 0.03
    assert _record("MC 3x3 whitened max", _whitened_err(c_mc, c)) < 0.02
    # same thing through polar_cov_to_enu with an explicit diagonal (rad) covariance
    d = np.diag([s_r ** 2, np.radians(s_az) ** 2, np.radians(s_el) ** 2])
    np.testing.assert_allclose(geo.polar_cov_to_enu(r0, az0, el0, d), c, rtol=1e-12, atol=1e-9)


def test_polar_sigmas_to_enu_cov_broadcasts():
    r = np.array([10e3, 50e3, 200e3])
    az = np.array([10.0, 100.0, 250.0])
    el = np.array([1.0, 2.0, 3.0])
    c = geo.polar_sigmas_to_enu_cov(r, az, el, 50.0, 0.1, 0.1)
    assert c.shape == (3, 3, 3)
    for i in range(3):
        np.testing.assert_allclose(c[i], geo.polar_sigmas_to_enu_cov(r[i], az[i], el[i], 50.0, 0.1, 0.1),
                                   rtol=1e-12)
    c2 = geo.polar_sigmas_to_enu_cov(r, az, el, np.array([30.0, 50.0, 70.0]), 0.1, np.array([0.1, 0.2, 0.3]))
    for i, (sr, se) in enumerate([(30.0, 0.1), (50.0, 0.2), (70.0, 0.3)]):
        np.testing.assert_allclose(c2[i], geo.polar_sigmas_to_enu_cov(r[i], az[i], el[i], sr, 0.1, se),
                                   rtol=1e-12)


def _oracle_state(x: np.ndarray) -> np.ndarray:
    """(r, az rad, el rad, ṙ, az˙ rad/s, el˙ rad/s) -> (e, n, u, ė, ṅ, u̇), written independently."""
    r, az, el, rd, azd, eld = np.moveaxis(x, -1, 0)
    e, n, u = pm.aer2enu(az, el, r, deg=False)
    # time derivative of (r cos el sin az, r cos el cos az, r sin el)
    ed = rd * np.cos(el) * np.sin(az) - r * np.sin(el) * eld * np.sin(az) + r * np.cos(el) * np.cos(az) * azd
    nd = rd * np.cos(el) * np.cos(az) - r * np.sin(el) * eld * np.cos(az) - r * np.cos(el) * np.sin(az) * azd
    ud = rd * np.sin(el) + r * np.cos(el) * eld
    return np.stack([e, n, u, ed, nd, ud], axis=-1)


STATE_GEOMS = [
    # r, az deg, el deg, rdot m/s, azdot deg/s, eldot deg/s
    (10e3, 37.0, 2.0, -150.0, 0.5, 0.05),
    (80e3, 200.0, 6.0, 220.0, -0.08, -0.01),
    (200e3, 300.0, 1.0, -240.0, 0.05, 0.002),
    (150e3, 359.95, 30.0, 10.0, 0.0, 0.0),
]


def _state_cov(rng) -> np.ndarray:
    sig = np.array([50.0, np.radians(0.1), np.radians(0.1), 2.0, np.radians(0.01), np.radians(0.01)])
    corr = np.eye(6)
    for i, j, rho in [(0, 3, 0.5), (1, 4, 0.6), (2, 5, -0.4), (0, 1, 0.1)]:
        corr[i, j] = corr[j, i] = rho
    return corr * np.outer(sig, sig)


@pytest.mark.parametrize("state", STATE_GEOMS)
def test_polar_state_to_enu_cov_vs_monte_carlo(state):
    rng = np.random.default_rng(abs(hash(state)) % 2**32)
    p = _state_cov(rng)
    r0, az0, el0, rd0, azd0, eld0 = state
    pos, vel, c = geo.polar_state_to_enu(r0, az0, el0, rd0, azd0, eld0, cov=p)
    assert c.shape == (6, 6)
    x0 = np.array([r0, np.radians(az0), np.radians(el0), rd0, np.radians(azd0), np.radians(eld0)])
    ref = _oracle_state(x0)
    assert _record("polar_state pos [m]", np.linalg.norm(pos - ref[:3])) <= MM
    assert _record("polar_state vel [m/s]", np.linalg.norm(vel - ref[3:])) <= 1e-6

    xs = rng.multivariate_normal(x0, p, size=N_MC, method="cholesky")
    ys = _oracle_state(xs)
    c_mc = np.cov(ys, rowvar=False)
    assert _record("MC 6x6 rel Frobenius", _rel_frob(c_mc, c)) < 0.03
    # blockwise (position and velocity scales differ by orders of magnitude)
    assert _rel_frob(c_mc[3:, 3:], c[3:, 3:]) < 0.03
    assert _record("MC 6x6 whitened max", _whitened_err(c_mc, c)) < 0.02
    np.testing.assert_allclose(c, c.T, atol=1e-9 * np.abs(c).max())


@pytest.mark.parametrize("state", STATE_GEOMS)
def test_polar_state_velocity_is_time_derivative(state):
    """Velocity equals the time derivative of the position along the polar trajectory (pymap3d)."""
    r0, az0, el0, rd0, azd0, eld0 = state
    _, vel, c = geo.polar_state_to_enu(r0, az0, el0, rd0, azd0, eld0)
    assert c is None
    h = 1e-3
    fp = np.array(pm.aer2enu(az0 + azd0 * h, el0 + eld0 * h, r0 + rd0 * h))
    fm = np.array(pm.aer2enu(az0 - azd0 * h, el0 - eld0 * h, r0 - rd0 * h))
    v_fd = (fp - fm) / (2 * h)
    assert _record("polar_state vel vs time-FD [m/s]", np.linalg.norm(vel - v_fd)) < 1e-4


def _fd_jacobian(f, x0: np.ndarray, steps: np.ndarray) -> np.ndarray:
    cols = []
    for k, h in enumerate(steps):
        dx = np.zeros_like(x0)
        dx[k] = h
        cols.append((f(x0 + dx) - f(x0 - dx)) / (2 * h))
    return np.stack(cols, axis=-1)


@settings(max_examples=100, deadline=None)
@given(st.floats(1e3, 300e3, **finite), st.floats(0.0, 360.0, exclude_max=True, **finite),
       st.floats(-5.0, 60.0, **finite))
def test_polar_jacobian_finite_difference(r, az, el):
    j = geo.polar_jacobian(r, az, el)
    f = lambda x: np.array(pm.aer2enu(x[1], x[2], x[0], deg=False))  # noqa: E731
    j_fd = _fd_jacobian(f, np.array([r, np.radians(az), np.radians(el)]), np.array([1.0, 1e-6, 1e-6]))
    err = np.abs(j - j_fd) / np.array([1.0, r, r])  # column-wise scale (unitless / metres per rad)
    assert _record("polar_jacobian FD rel", err) < 1e-7


def test_polar_jacobian_batch_shape():
    r = np.linspace(1e3, 2e5, 12).reshape(3, 4)
    j = geo.polar_jacobian(r, 45.0, 3.0)
    assert j.shape == (3, 4, 3, 3)
    np.testing.assert_allclose(j[2, 1], geo.polar_jacobian(r[2, 1], 45.0, 3.0), rtol=1e-14)


@pytest.mark.parametrize("state", STATE_GEOMS)
def test_polar_state_jacobian_finite_difference(state):
    """J P Jᵀ from polar_state_to_enu equals J_fd P J_fdᵀ with a finite-difference J of an
    independently written state conversion; rank-1 P = e_k e_kᵀ checks each column."""
    r0, az0, el0, rd0, azd0, eld0 = state
    x0 = np.array([r0, np.radians(az0), np.radians(el0), rd0, np.radians(azd0), np.radians(eld0)])
    j_fd = _fd_jacobian(_oracle_state, x0, np.array([1.0, 1e-6, 1e-6, 1e-3, 1e-7, 1e-7]))
    p = _state_cov(np.random.default_rng(0))
    _, _, c = geo.polar_state_to_enu(*state, cov=p)
    c_ref = j_fd @ p @ j_fd.T
    assert _record("polar_state J P J^T vs FD rel", _rel_frob(c, c_ref)) < 1e-6
    # column by column (rank-1 covariances), normalised by the column's magnitude
    covs = np.zeros((6, 6, 6))
    for k in range(6):
        covs[k, k, k] = 1.0
    _, _, ck = geo.polar_state_to_enu(*[np.full(6, v) for v in state], cov=covs)
    for k in range(6):
        ref_k = np.outer(j_fd[:, k], j_fd[:, k])
        scale = max(np.linalg.norm(ref_k), 1e-12)
        assert _record("polar_state J column FD rel", np.linalg.norm(ck[k] - ref_k) / scale) < 1e-6, k


# ============================================================================ 5. elevation


@pytest.mark.parametrize("radar_alt", [0.0, 50.0, 800.0])
@pytest.mark.parametrize("target_alt", [1_000.0, 5_000.0, 11_000.0])
@pytest.mark.parametrize("ground_dist", [10e3, 50e3, 100e3, 200e3])
def test_elevation_from_altitude_vs_ellipsoid_geometry(radar_alt, target_alt, ground_dist):
    """Geometric elevation from pymap3d on WGS-84 vs the spherical model with a true radius.

    * Due east of a radar on the equator the ellipsoid's cross-section is the equatorial circle of
      radius a (normals pass through the centre), so the spherical model with R = a is *exact*.
    * In other directions the local radius of curvature differs from R (north at the equator
      M = a(1 − e²) ≈ 6335 km); ε ≈ Δh/r − r/(2R), so |dε| ≈ r ΔR/(2R²) ≈ 2.5e-3° at 100 km for the
      36 km mismatch of the mean radius (observed 2.5e-3° north, 1.0e-3° at 45°). We allow 0.01° at ≤ 100 km (the brief's tolerance) and scale it
      linearly with range beyond.
    """
    radar = (0.0, 0.0, radar_alt)
    for bearing, radius, tol in [
        (90.0, geo.WGS84_A, 1e-8),
        (0.0, geo.WGS84_A * (1 - geo.WGS84_E2), 1e-5),  # M varies along the meridian
        (45.0, geo.EARTH_RADIUS_M, 0.01 * max(1.0, ground_dist / 100e3)),
        (0.0, geo.EARTH_RADIUS_M, 0.01 * max(1.0, ground_dist / 100e3)),
    ]:
        # target at a known altitude, roughly ground_dist away along the bearing
        tlat, tlon, _ = pm.aer2geodetic(_a(bearing), _a(0.0), _a(ground_dist), 0.0, 0.0, 0.0)
        _, el_ref, srange = pm.geodetic2aer(tlat, tlon, _a(target_alt), *radar)
        el = geo.elevation_from_altitude(srange[0], target_alt, radar_alt, earth_radius_m=radius)
        assert _record(f"elevation_from_altitude err [deg] R={radius:.0f}", el - el_ref[0]) <= tol


def test_elevation_from_altitude_refraction_raises_elevation():
    r = np.linspace(15e3, 300e3, 60)  # r > Δh, else both clip to 90°
    for ht, hr in [(1_000.0, 0.0), (10_000.0, 500.0), (300.0, 50.0)]:
        el_43 = geo.elevation_from_altitude(r, ht, hr)
        el_true = geo.elevation_from_altitude(r, ht, hr, earth_radius_m=geo.EARTH_RADIUS_M)
        # a beam bent down towards the Earth (4/3 model) needs a higher launch elevation
        assert np.all(el_43 > el_true)
        assert el_43.shape == r.shape
    # flat-Earth limit: R -> inf gives asin(Δh / r) (curvature term r/2R ~ 1e-6 deg here)
    el_flat = geo.elevation_from_altitude(50e3, 5_000.0, 0.0, earth_radius_m=1e12)
    assert abs(el_flat - np.degrees(np.arcsin(5_000.0 / 50e3))) < 1e-5
    # consistency with polar_to_enu on a sphere: a point straight up is at 90 deg
    assert abs(geo.elevation_from_altitude(10e3, 10_000.0, 0.0) - 90.0) < 1e-6


# ============================================================================ 6. validity / wrap


def test_conversion_valid_range_limit_eq14():
    s_r, s_th = 30.0, np.radians(1.0)
    limit = 0.4 * s_r / s_th ** 2
    assert limit == pytest.approx(39_393.7, abs=0.1)  # "39.39 km"
    assert bool(geo.conversion_valid(39_300.0, s_r, s_th)) is True
    assert bool(geo.conversion_valid(39_500.0, s_r, s_th)) is False
    v = geo.conversion_valid(np.array([1e3, 39_300.0, 39_500.0, 1e5]), s_r, s_th)
    np.testing.assert_array_equal(v, [True, True, False, False])
    # angular limit σθ < 0.4 rad regardless of range
    assert bool(geo.conversion_valid(1.0, 1e6, 0.41)) is False
    assert bool(geo.conversion_valid(1.0, 1e6, 0.39)) is True


@SETTINGS
@given(st.floats(-1e6, 1e6, **finite))
def test_wrap_deg(x):
    w = float(geo.wrap_deg(x))
    assert -180.0 <= w < 180.0
    k = (x - w) / 360.0
    assert abs(k - round(k)) * 360.0 < 1e-6
