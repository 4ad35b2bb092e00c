"""In-motion heading alignment from the GNSS course over ground (ground vehicles).

A rover, a car or an aircraft on its take-off roll often has no usable heading at start-up: the
compass sits next to motors and steel, and a MEMS gyro cannot find north.  At rest heading is
unobservable to a GNSS/INS filter; once the vehicle drives straight ahead, the direction of its
horizontal velocity *is* its heading (up to the side-slip, a fraction of a degree for a car on
tarmac).  This module turns the first few GNSS velocities at speed into heading measurements:

    heading ~= course = atan2(v_east, v_north) of the IMU velocity,
    sigma^2  = sigma_v_cross^2 / v_h^2  +  n * sigma_slip^2,

where ``sigma_v_cross`` is the GNSS velocity uncertainty across the track and the side-slip term
is inflated by the number ``n`` of course measurements fused, because the slip of one straight is
one error, not ``n`` independent ones.

If the filter's own heading is uncertain by more than ``reset_above_rad`` (no compass) or the
course disagrees with it by more than that (a disturbed compass), the heading is *reset*: the
attitude is rotated about the local vertical onto the course and the heading variance replaced,
since a linear Kalman update cannot absorb an error of tens of degrees.  Otherwise the course is
fused as an ordinary heading measurement and gated like any other.

Assumptions, stated because they can be false: the vehicle moves forward along its body x axis
(reversing is recognised only when the filter's heading is already known to 45 deg; with no idea
of the heading, forward motion is assumed), and it does not crab -- a boat in a current or a
sideways-drifting aircraft must not use this (``course_alignment_enabled`` is off by default, and
the engine uses it only while on the ground).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .earth import C_n_e, ecef_to_geodetic, rotation_from_rotvec


@dataclass(frozen=True)
class CourseMeasurement:
    """Heading from the course over ground at one GNSS epoch."""

    t_gps: float
    heading_rad: float           # clockwise from true north, the direction of the IMU's horizontal velocity
    sigma_rad: float
    speed_h_mps: float


def course_from_velocity(t_gps: float, v_imu_e: np.ndarray, cov_v_e: np.ndarray, r_e: np.ndarray,
                         sigma_slip_rad: float, n_fused: int = 0) -> CourseMeasurement:
    """Course over ground of an ECEF velocity (m/s) with its 3x3 covariance (m^2/s^2), at ECEF
    position ``r_e`` (for the local NED frame).  ``n_fused`` course measurements already used
    inflate the side-slip variance (see the module docstring)."""
    lat, lon, _ = ecef_to_geodetic(r_e)
    C_e_n = C_n_e(lat, lon).T
    v_n = C_e_n @ np.asarray(v_imu_e, float)
    speed = math.hypot(v_n[0], v_n[1])
    course = math.atan2(v_n[1], v_n[0])
    across = np.array([-math.sin(course), math.cos(course), 0.0])       # unit vector across the track (NED)
    var_across = float(across @ (C_e_n @ np.asarray(cov_v_e, float) @ C_e_n.T) @ across)
    var = var_across / max(speed, 1e-9) ** 2 + (n_fused + 1) * sigma_slip_rad ** 2
    return CourseMeasurement(t_gps, course, math.sqrt(var), speed)


def heading_of(C_b_e: np.ndarray, r_e: np.ndarray) -> float:
    """Heading (rad, clockwise from true north) of the body x axis projected on the horizontal."""
    lat, lon, _ = ecef_to_geodetic(r_e)
    x_n = C_n_e(lat, lon).T @ C_b_e[:, 0]
    return math.atan2(x_n[1], x_n[0])


def down_axis_e(r_e: np.ndarray) -> np.ndarray:
    """Unit vector of local down, ECEF."""
    lat, lon, _ = ecef_to_geodetic(r_e)
    return C_n_e(lat, lon)[:, 2]


def heading_variance(P_att: np.ndarray, u_down_e: np.ndarray) -> float:
    """Variance (rad^2) of the misalignment about local down: the heading part of the attitude error."""
    return float(u_down_e @ P_att @ u_down_e)


def heading_reset(P: np.ndarray, att: slice, u_down_e: np.ndarray, delta_heading_rad: float,
                  sigma_heading_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """A heading reset: the rotation ``R`` (ECEF, apply as ``R @ C_b_e``) that turns the attitude by
    ``delta_heading_rad`` about local down, and the covariance with the heading variance replaced by
    ``sigma_heading_rad**2``.  The heading's correlations with every other state are dropped (they
    described an error that no longer exists); the tilt part is kept.  Returns (R, P), new arrays."""
    R = rotation_from_rotvec(u_down_e * delta_heading_rad)
    u = u_down_e.reshape(3, 1)
    T = np.eye(P.shape[0])
    T[att, att] = np.eye(3) - u @ u.T                # projector onto the tilt plane
    P_new = T @ P @ T.T
    P_new[att, att] += sigma_heading_rad ** 2 * (u @ u.T)
    return R, 0.5 * (P_new + P_new.T)
