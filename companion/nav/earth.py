"""WGS-84 earth model, the paper's normal gravity, frames and small rotation helpers.

Frames: ECEF ``e``; local North-East-Down ``n``; body Forward-Right-Down ``b``.
``C_b_e`` maps body-frame coordinates to ECEF coordinates (v_e = C_b_e @ v_b).
"""
from __future__ import annotations

import math

import numpy as np

WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_B_M = WGS84_A_M * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)
OMEGA_IE_RADPS = 7.2921151467e-5          # earth rotation rate (WGS-84, IS-GPS-200)
GM_M3PS2 = 3.986005e14                     # IS-GPS-200 value, used for orbits

# Normal gravity, seed 000 eq 10 (a1 corrected from the OCR's 9.7803266715 to the standard value).
_GAMMA_A1 = 9.7803267715
_GAMMA_A2 = 0.0052790414
_GAMMA_A3 = 0.0000232718
_GAMMA_A4 = -0.0000030876910891
_GAMMA_A5 = 0.0000000043977311
_GAMMA_A6 = 0.0000000000007211

OMEGA_IE_E = np.array([0.0, 0.0, OMEGA_IE_RADPS])


def skew(v) -> np.ndarray:
    """Cross-product matrix: skew(a) @ b == cross(a, b)."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


OMEGA_IE_SKEW = skew(OMEGA_IE_E)


def normal_gravity_mps2(lat_rad: float, h_m: float) -> float:
    """Magnitude of normal gravity (gravitation + centrifugal) at geodetic latitude and height (seed 000 eq 10)."""
    s2 = math.sin(lat_rad) ** 2
    return (_GAMMA_A1 * (1.0 + _GAMMA_A2 * s2 + _GAMMA_A3 * s2 * s2)
            + (_GAMMA_A4 + _GAMMA_A5 * s2) * h_m + _GAMMA_A6 * h_m * h_m)


def radii_of_curvature(lat_rad: float) -> tuple[float, float]:
    """(meridian M, prime vertical N) radii of curvature in metres."""
    s2 = math.sin(lat_rad) ** 2
    d = 1.0 - WGS84_E2 * s2
    n = WGS84_A_M / math.sqrt(d)
    m = WGS84_A_M * (1.0 - WGS84_E2) / (d * math.sqrt(d))
    return m, n


def geodetic_to_ecef(lat_rad: float, lon_rad: float, h_m: float) -> np.ndarray:
    sl, cl = math.sin(lat_rad), math.cos(lat_rad)
    n = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * sl * sl)
    return np.array([(n + h_m) * cl * math.cos(lon_rad),
                     (n + h_m) * cl * math.sin(lon_rad),
                     (n * (1.0 - WGS84_E2) + h_m) * sl])


def ecef_to_geodetic(r_e) -> tuple[float, float, float]:
    """ECEF (m) to geodetic (lat rad, lon rad, h m).

    Bowring's closed form followed by one Newton refinement: sub-millimetre from the Earth's
    centre region out to GPS orbit altitude.
    """
    x, y, z = float(r_e[0]), float(r_e[1]), float(r_e[2])
    p = math.hypot(x, y)
    lon = math.atan2(y, x)
    if p < 1e-9:
        lat = math.copysign(math.pi / 2, z)
        return lat, lon, abs(z) - WGS84_B_M
    theta = math.atan2(z * WGS84_A_M, p * WGS84_B_M)
    st, ct = math.sin(theta), math.cos(theta)
    lat = math.atan2(z + WGS84_EP2 * WGS84_B_M * st ** 3, p - WGS84_E2 * WGS84_A_M * ct ** 3)
    for _ in range(2):  # refinement: keeps accuracy at high altitude
        sl = math.sin(lat)
        n = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * sl * sl)
        h = p / math.cos(lat) - n if abs(lat) < 1.3 else z / sl - n * (1.0 - WGS84_E2)
        lat = math.atan2(z, p * (1.0 - WGS84_E2 * n / (n + h)))
    sl = math.sin(lat)
    n = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * sl * sl)
    h = p / math.cos(lat) - n if abs(lat) < 1.3 else z / sl - n * (1.0 - WGS84_E2)
    return lat, lon, h


def C_n_e(lat_rad: float, lon_rad: float) -> np.ndarray:
    """Rotation from local NED to ECEF (v_e = C_n_e @ v_n)."""
    sl, cl = math.sin(lat_rad), math.cos(lat_rad)
    so, co = math.sin(lon_rad), math.cos(lon_rad)
    return np.array([[-sl * co, -so, -cl * co],
                     [-sl * so, co, -cl * so],
                     [cl, 0.0, -sl]])


def ecef_to_ned(r_e, r_ref_e) -> np.ndarray:
    """Position ``r_e`` relative to ``r_ref_e`` in the NED frame at ``r_ref_e`` (m)."""
    lat, lon, _ = ecef_to_geodetic(r_ref_e)
    return C_n_e(lat, lon).T @ (np.asarray(r_e, float) - np.asarray(r_ref_e, float))


def ned_to_ecef(d_n, r_ref_e) -> np.ndarray:
    lat, lon, _ = ecef_to_geodetic(r_ref_e)
    return np.asarray(r_ref_e, float) + C_n_e(lat, lon) @ np.asarray(d_n, float)


def gravity_ecef(r_e) -> np.ndarray:
    """Gravity (gravitation + centrifugal) vector in ECEF, m/s^2, from the paper's normal gravity.

    Normal gravity acts along the ellipsoid normal (down).  The geodetic latitude comes from a
    single Bowring step, accurate to well below 1e-7 rad below 10 km, which is all gravity needs.
    """
    x, y, z = float(r_e[0]), float(r_e[1]), float(r_e[2])
    p = math.hypot(x, y)
    theta = math.atan2(z * WGS84_A_M, p * WGS84_B_M)
    st, ct = math.sin(theta), math.cos(theta)
    lat = math.atan2(z + WGS84_EP2 * WGS84_B_M * st * st * st, p - WGS84_E2 * WGS84_A_M * ct * ct * ct)
    sl, cl = math.sin(lat), math.cos(lat)
    n = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * sl * sl)
    h = p / cl - n if cl > 1e-3 else abs(z) - WGS84_B_M
    g = normal_gravity_mps2(lat, h)
    # down unit vector = -(cos lat cos lon, cos lat sin lon, sin lat); cos lon = x/p, sin lon = y/p
    if p > 1e-9:
        return np.array([-g * cl * x / p, -g * cl * y / p, -g * sl])
    return np.array([0.0, 0.0, -math.copysign(g, z)])


def gravity_gradient_ecef(r_e) -> np.ndarray:
    """d(gravitation)/d(r) for a point mass, plus the centrifugal term's gradient.

    Used in the error-state model: its horizontal part produces the Schuler oscillation,
    its vertical part the vertical-channel instability.
    """
    r = np.asarray(r_e, float)
    rn2 = float(r @ r)
    rn = math.sqrt(rn2)
    g_over_r3 = GM_M3PS2 / (rn2 * rn)
    grad = -g_over_r3 * (np.eye(3) - 3.0 * np.outer(r, r) / rn2)
    grad[0, 0] += OMEGA_IE_RADPS ** 2
    grad[1, 1] += OMEGA_IE_RADPS ** 2
    return grad


def rotation_from_rotvec(phi) -> np.ndarray:
    """Rodrigues: rotation matrix exp([phi x]) (seed 004 eq 6)."""
    x, y, z = float(phi[0]), float(phi[1]), float(phi[2])
    a2 = x * x + y * y + z * z
    if a2 < 1e-16:
        s, c = 1.0, 0.5
    else:
        a = math.sqrt(a2)
        s, c = math.sin(a) / a, (1.0 - math.cos(a)) / a2
    # I + s K + c K^2 with K = [phi x], written out (plain floats: a quarter of the numpy version's
    # cost, every closed-loop feedback)
    xy, xz, yz = c * x * y, c * x * z, c * y * z
    return np.array([[1.0 - c * (y * y + z * z), xy - s * z, xz + s * y],
                     [xy + s * z, 1.0 - c * (x * x + z * z), yz - s * x],
                     [xz - s * y, yz + s * x, 1.0 - c * (x * x + y * y)]])


def euler_to_dcm(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """Body-to-NED rotation C_b_n from aerospace ZYX Euler angles."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([
        [cp * cy, -cr * sy + sr * sp * cy, sr * sy + cr * sp * cy],
        [cp * sy, cr * cy + sr * sp * sy, -sr * cy + cr * sp * sy],
        [-sp, sr * cp, cr * cp],
    ])


def dcm_to_euler(C_b_n) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in rad from C_b_n (ZYX)."""
    roll = math.atan2(C_b_n[2, 1], C_b_n[2, 2])
    pitch = -math.asin(max(-1.0, min(1.0, C_b_n[2, 0])))
    yaw = math.atan2(C_b_n[1, 0], C_b_n[0, 0])
    return roll, pitch, yaw


def orthonormalize(C) -> np.ndarray:
    """Nearest rotation matrix (SVD), removes numerical drift from repeated products."""
    u, _, vt = np.linalg.svd(C)
    return u @ vt
