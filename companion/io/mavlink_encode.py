"""Fused outputs encoded as pymavlink message objects (pure: ``msg.pack(mav)`` gives bytes; the
link does that): :func:`vision_position_estimate`, :func:`odometry`, :func:`gps_input`,
:func:`set_gps_global_origin`, :func:`statustext`, :func:`gps_rtcm_data_messages`,
:func:`command_set_message_interval`, :func:`heartbeat`, :func:`serial_control_request`.

Frames: positions sent to the autopilot are NED relative to the EKF origin **as ArduPilot computes
them** (``Location::get_distance_NED``: spherical scaling ``LOCATION_SCALING_FACTOR`` =
0.011131884502145034 m per 1e-7 deg and ``cos(mean latitude)`` for east), so the global position
the autopilot reports from the fused NED state matches ours (a WGS-84 tangent plane differs by
~0.2 % of the distance from the origin)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..messages import SECONDS_PER_WEEK, NavSolution, gps_week_tow
from ..nav.earth import C_n_e, dcm_to_euler, ecef_to_geodetic
from .mavlink_codec import ENCODER, SERIAL_CONTROL_DATA_LEN, m
from .rtcm import GPS_RTCM_DATA_LEN, GpsRtcmDataFragmenter

LOCATION_SCALING_FACTOR_M = 0.011131884502145034   # ArduPilot: metres per 1e-7 degree of latitude


@dataclass(frozen=True, slots=True)
class Origin:
    """The EKF origin: geodetic (rad, rad, m) in the height reference sent to the autopilot."""
    lat_rad: float
    lon_rad: float
    alt_m: float

    @classmethod
    def from_ecef(cls, r_e, geoid_undulation_m: float = 0.0) -> "Origin":
        lat, lon, h = ecef_to_geodetic(r_e)
        return cls(lat, lon, h - geoid_undulation_m)

    def lat_e7(self) -> int:
        return int(round(math.degrees(self.lat_rad) * 1e7))

    def lon_e7(self) -> int:
        return int(round(math.degrees(self.lon_rad) * 1e7))


def ardupilot_ned_from_origin(lat_rad: float, lon_rad: float, alt_m: float, origin: Origin) -> np.ndarray:
    """NED offset of a point from ``origin`` exactly as ArduPilot's ``Location::get_distance_NED``
    computes it (spherical scaling, east scaled by cos of the mean latitude)."""
    dlat_e7 = (math.degrees(lat_rad) - math.degrees(origin.lat_rad)) * 1e7
    dlon_deg = math.degrees(lon_rad) - math.degrees(origin.lon_rad)
    dlon_deg = (dlon_deg + 180.0) % 360.0 - 180.0
    scale = max(math.cos(0.5 * (lat_rad + origin.lat_rad)), 0.01)
    return np.array([dlat_e7 * LOCATION_SCALING_FACTOR_M,
                     dlon_deg * 1e7 * LOCATION_SCALING_FACTOR_M * scale,
                     -(alt_m - origin.alt_m)])


def _solution_geodetic(sol: NavSolution, geoid_undulation_m: float) -> tuple[float, float, float, np.ndarray]:
    lat, lon, h = ecef_to_geodetic(sol.r_e)
    return lat, lon, h - geoid_undulation_m, C_n_e(lat, lon)


def _C_b_n(sol: NavSolution, Cne: np.ndarray) -> np.ndarray:
    return Cne.T @ np.asarray(sol.C_b_e, float)


def _att_var_rpy(sol: NavSolution, Cne: np.ndarray) -> tuple[float, float, float]:
    """Roll/pitch/yaw variances from the ECEF-axis attitude sigmas: rotated to NED, tilt about
    N and E shared by roll and pitch, rotation about D = yaw (small-angle approximation)."""
    s = np.asarray(sol.sigma_att_rad, float)
    P_n = Cne.T @ np.diag(s ** 2) @ Cne
    tilt = 0.5 * (P_n[0, 0] + P_n[1, 1])
    return tilt, tilt, P_n[2, 2]


def upper_triangle_covariance(diag: list[float] | np.ndarray) -> list[float]:
    """21-float row-major upper triangle of a 6x6 diagonal covariance (MAVLink convention)."""
    d = list(map(float, diag))
    out = []
    for i in range(6):
        for j in range(i, 6):
            out.append(d[i] if i == j else 0.0)
    return out


def quality_from_sigma(sigma_h_m: float, max_sigma_h_m: float) -> int:
    """ODOMETRY quality 1..100 (0 = unknown is reserved, -1 = failed) from the horizontal sigma."""
    if not math.isfinite(sigma_h_m) or sigma_h_m > max_sigma_h_m:
        return -1
    return max(1, min(100, int(round(100.0 * (1.0 - sigma_h_m / max_sigma_h_m)))))


def _rot_to_quat(C: np.ndarray) -> list[float]:
    """Rotation matrix -> quaternion [w, x, y, z] (Shepperd)."""
    tr = C[0, 0] + C[1, 1] + C[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        w, x, y, z = 0.25 * s, (C[2, 1] - C[1, 2]) / s, (C[0, 2] - C[2, 0]) / s, (C[1, 0] - C[0, 1]) / s
    elif C[0, 0] > C[1, 1] and C[0, 0] > C[2, 2]:
        s = math.sqrt(1.0 + C[0, 0] - C[1, 1] - C[2, 2]) * 2
        w, x, y, z = (C[2, 1] - C[1, 2]) / s, 0.25 * s, (C[0, 1] + C[1, 0]) / s, (C[0, 2] + C[2, 0]) / s
    elif C[1, 1] > C[2, 2]:
        s = math.sqrt(1.0 + C[1, 1] - C[0, 0] - C[2, 2]) * 2
        w, x, y, z = (C[0, 2] - C[2, 0]) / s, (C[0, 1] + C[1, 0]) / s, 0.25 * s, (C[1, 2] + C[2, 1]) / s
    else:
        s = math.sqrt(1.0 + C[2, 2] - C[0, 0] - C[1, 1]) * 2
        w, x, y, z = (C[1, 0] - C[0, 1]) / s, (C[0, 2] + C[2, 0]) / s, (C[1, 2] + C[2, 1]) / s, 0.25 * s
    q = np.array([w, x, y, z])
    q /= np.linalg.norm(q)
    if q[0] < 0:
        q = -q
    return q.tolist()


# (b) encoders: outputs
def vision_position_estimate(sol: NavSolution, origin: Origin, reset_counter: int, t_boot_us: int,
                             geoid_undulation_m: float = 0.0):
    """VISION_POSITION_ESTIMATE: NED position of the IMU relative to the EKF origin (ArduPilot's
    spherical convention, :func:`ardupilot_ned_from_origin`), roll/pitch/yaw of ``C_b_n``, and the
    21-float covariance (x, y, z, roll, pitch, yaw variances on the diagonal).  ArduPilot reduces
    the covariance to ``posErr``/``angErr`` from the diagonal entries 0, 6, 11 and 15, 18, 20.
    ``t_boot_us`` is the time stamp (ArduPilot corrects any offboard time base for jitter)."""
    lat, lon, alt, Cne = _solution_geodetic(sol, geoid_undulation_m)
    ned = ardupilot_ned_from_origin(lat, lon, alt, origin)
    roll, pitch, yaw = dcm_to_euler(_C_b_n(sol, Cne))
    vr, vp, vy = _att_var_rpy(sol, Cne)
    s = np.asarray(sol.sigma_r_n_m, float) ** 2
    cov = upper_triangle_covariance([s[0], s[1], s[2], vr, vp, vy])
    return ENCODER.vision_position_estimate_encode(int(t_boot_us), float(ned[0]), float(ned[1]), float(ned[2]),
                                                roll, pitch, yaw, cov, int(reset_counter) & 0xFF)


def odometry(sol: NavSolution, origin: Origin, reset_counter: int, t_boot_us: int, *,
             quality: int = 0, geoid_undulation_m: float = 0.0):
    """ODOMETRY for ArduPilot's ``GCS_MAVLINK::handle_odometry``, which ignores anything but
    ``frame_id = MAV_FRAME_LOCAL_FRD`` (20) and ``child_frame_id = MAV_FRAME_BODY_FRD`` (12);
    velocity in the *body* frame (ArduPilot rotates it to NED with ``q``), ``q`` = body-to-NED
    [w, x, y, z], angular rates NaN (unknown), ``estimator_type = MAV_ESTIMATOR_TYPE_VISION``,
    ``quality`` 0..100 (``VISO_QUAL_MIN`` drops low ones; see :func:`quality_from_sigma`)."""
    lat, lon, alt, Cne = _solution_geodetic(sol, geoid_undulation_m)
    ned = ardupilot_ned_from_origin(lat, lon, alt, origin)
    Cbn = _C_b_n(sol, Cne)
    v_n = Cne.T @ np.asarray(sol.v_e, float)
    v_b = Cbn.T @ v_n
    vr, vp, vy = _att_var_rpy(sol, Cne)
    s = np.asarray(sol.sigma_r_n_m, float) ** 2
    sv = np.asarray(sol.sigma_v_n_mps, float) ** 2
    pose_cov = upper_triangle_covariance([s[0], s[1], s[2], vr, vp, vy])
    # body-frame velocity variance: isotropic bound (the NED sigmas rotated would need the full matrix)
    vmax = float(np.max(sv))
    vel_cov = upper_triangle_covariance([vmax, vmax, vmax, math.nan, math.nan, math.nan])
    nan = math.nan
    return ENCODER.odometry_encode(int(t_boot_us), m.MAV_FRAME_LOCAL_FRD, m.MAV_FRAME_BODY_FRD,
                                float(ned[0]), float(ned[1]), float(ned[2]), _rot_to_quat(Cbn),
                                float(v_b[0]), float(v_b[1]), float(v_b[2]), nan, nan, nan,
                                pose_cov, vel_cov, int(reset_counter) & 0xFF,
                                m.MAV_ESTIMATOR_TYPE_VISION, int(max(-1, min(100, quality))))


#: GPS_INPUT fix_type (MAVLink GPS_FIX_TYPE, ArduPilot's AP_GPS::GPS_Status takes it as is)
GPS_FIX_NO_FIX, GPS_FIX_3D, GPS_FIX_DGPS, GPS_FIX_RTK_FLOAT, GPS_FIX_RTK_FIXED = 1, 3, 4, 5, 6


def gps_fix_type(sol: NavSolution) -> int:
    """GPS_INPUT fix type of a solution: no fix unless navigating (status 'nav' or 'coasting');
    then RTK fixed (6) / float (5) from the carrier-phase fix state, else DGPS (4) when
    ``sol.extras['dgps']``, else 3-D (3).  ArduPilot's EKF uses the fix type for its GPS checks
    and reports it (GPS_RAW_INT, the GCS's "RTK Fixed"); the position accuracy it fuses with is
    the sigma sent beside it, which for a fixed solution is the filter's own covariance."""
    if sol.status not in ("nav", "coasting"):
        return GPS_FIX_NO_FIX
    if sol.fix_state == "fixed":
        return GPS_FIX_RTK_FIXED
    if sol.fix_state == "float":
        return GPS_FIX_RTK_FLOAT
    return GPS_FIX_DGPS if sol.extras.get("dgps") else GPS_FIX_3D


def gps_input(sol: NavSolution, t_gps: float | None = None, *, t_boot_us: int = 0, gps_id: int = 0,
              fix_type: int | None = None, satellites_visible: int = 10, geoid_undulation_m: float = 0.0,
              uere_m: float = 1.0, min_dop: float = 0.6):
    """GPS_INPUT (ArduPilot ``GPS1_TYPE = 14``, ``AP_GPS_MAV``): all fields provided (no ignore
    flags), yaw 0 = not provided.  ``alt`` is MSL: ellipsoidal height minus
    ``geoid_undulation_m``.  ArduPilot needs ``fix_type >= 3`` and ``time_week > 0`` to use the
    time stamp; hdop/vdop are synthetic (sigma / ``uere_m``, at least ``min_dop``) because
    ArduPilot's GPS checks look at hdop.  Set the autopilot's ``GPS1_POS`` to 0: this is the IMU
    position.  ``fix_type`` default: :func:`gps_fix_type` (6/5 for an RTK fixed/float solution)."""
    t = sol.t_gps if t_gps is None else t_gps
    week, tow = gps_week_tow(t)
    lat, lon, h = ecef_to_geodetic(sol.r_e)
    v_n = C_n_e(lat, lon).T @ np.asarray(sol.v_e, float)
    sr = np.asarray(sol.sigma_r_n_m, float)
    sv = np.asarray(sol.sigma_v_n_mps, float)
    sig_h = float(math.hypot(sr[0], sr[1]))
    if fix_type is None:
        fix_type = gps_fix_type(sol)
    return ENCODER.gps_input_encode(
        int(t_boot_us), int(gps_id), 0, int(round(tow * 1000.0)) % int(SECONDS_PER_WEEK * 1000), int(week),
        int(fix_type), int(round(math.degrees(lat) * 1e7)), int(round(math.degrees(lon) * 1e7)),
        float(h - geoid_undulation_m), max(min_dop, sig_h / uere_m), max(min_dop, float(sr[2]) / uere_m),
        float(v_n[0]), float(v_n[1]), float(v_n[2]), float(math.sqrt(float(np.sum(sv ** 2)))),
        sig_h, float(sr[2]), int(satellites_visible), 0)


def set_gps_global_origin(lat_deg: float, lon_deg: float, alt_m: float, target_system: int = 1,
                          time_usec: int = 0):
    """SET_GPS_GLOBAL_ORIGIN (lat/lon 1e7 deg, altitude mm; ArduPilot treats it as AMSL and only
    accepts it while no origin is set)."""
    return ENCODER.set_gps_global_origin_encode(int(target_system), int(round(lat_deg * 1e7)),
                                             int(round(lon_deg * 1e7)), int(round(alt_m * 1000.0)),
                                             int(time_usec))


def set_gps_global_origin_from(origin: Origin, target_system: int = 1):
    return set_gps_global_origin(math.degrees(origin.lat_rad), math.degrees(origin.lon_rad), origin.alt_m,
                                 target_system)


def statustext_chunks(severity: int, text: str, msg_id: int = 0) -> list:
    """STATUSTEXT, split into 50-byte chunks (MAVLink 2 ``id``/``chunk_seq``) when longer."""
    raw = text.encode("utf-8", "replace")
    if len(raw) <= 50:
        return [ENCODER.statustext_encode(int(severity), raw, 0, 0)]
    parts = [raw[i:i + 50] for i in range(0, len(raw), 50)]
    return [ENCODER.statustext_encode(int(severity), p, (msg_id or 1) & 0xFFFF, k) for k, p in enumerate(parts)]


def statustext(severity: int, text: str):
    """One STATUSTEXT (text truncated to 50 bytes)."""
    return ENCODER.statustext_encode(int(severity), text.encode("utf-8", "replace")[:50], 0, 0)


def gps_rtcm_data_messages(frame: bytes, fragmenter: GpsRtcmDataFragmenter) -> list:
    """GPS_RTCM_DATA messages for one RTCM frame (fragmentation from :mod:`companion.io.rtcm`)."""
    out = []
    for flags, data in fragmenter.fragments(frame):
        padded = list(data) + [0] * (GPS_RTCM_DATA_LEN - len(data))
        out.append(ENCODER.gps_rtcm_data_encode(flags, len(data), padded))
    return out


def heartbeat():
    return ENCODER.heartbeat_encode(m.MAV_TYPE_ONBOARD_CONTROLLER, m.MAV_AUTOPILOT_INVALID, 0, 0, m.MAV_STATE_ACTIVE)


def command_set_message_interval(message_id: int, rate_hz: float, target_system: int = 1,
                                 target_component: int = 1, confirmation: int = 0):
    """COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL: param1 message id, param2 interval in us
    (-1 = disable; 0 = default rate)."""
    interval_us = -1.0 if rate_hz <= 0 else 1e6 / rate_hz
    return ENCODER.command_long_encode(int(target_system), int(target_component),
                                    m.MAV_CMD_SET_MESSAGE_INTERVAL, confirmation,
                                    float(message_id), float(interval_us), 0, 0, 0, 0, 0)


def serial_control_request(device: int, data: bytes = b"", *, flags: int | None = None, timeout_ms: int = 0,
                           baudrate: int = 0, target_system: int = 1, target_component: int = 1):
    """SERIAL_CONTROL request: up to 70 bytes to write, flags RESPOND|EXCLUSIVE|MULTI by default.

    ArduPilot (``GCS_MAVLINK::handle_serial_control``): EXCLUSIVE locks the port away from its own
    GPS driver (``AP_GPS::lock_port``) so the two do not split the byte stream -- the autopilot
    then has no GPS of its own from that port; a request without EXCLUSIVE gives it back.  Data
    is only returned in answer to a request with RESPOND, at most 70 bytes per reply; MULTI makes
    it keep replying while bytes are available.  ``timeout_ms`` > 0 makes the autopilot *sleep*
    in its MAVLink thread waiting for data: keep it 0 and poll instead."""
    if len(data) > SERIAL_CONTROL_DATA_LEN:
        raise ValueError("SERIAL_CONTROL carries at most 70 bytes")
    if flags is None:
        flags = (m.SERIAL_CONTROL_FLAG_RESPOND | m.SERIAL_CONTROL_FLAG_EXCLUSIVE
                 | m.SERIAL_CONTROL_FLAG_MULTI)
    payload = list(data) + [0] * (SERIAL_CONTROL_DATA_LEN - len(data))
    msg = ENCODER.serial_control_encode(int(device), int(flags), int(timeout_ms), int(baudrate), len(data), payload)
    if hasattr(msg, "target_system"):
        msg.target_system = int(target_system)
        msg.target_component = int(target_component)
    return msg


__all__ = ["Origin", "ardupilot_ned_from_origin", "vision_position_estimate", "odometry", "gps_input",
           "set_gps_global_origin", "set_gps_global_origin_from", "statustext", "statustext_chunks",
           "gps_rtcm_data_messages", "heartbeat", "command_set_message_interval", "serial_control_request",
           "quality_from_sigma", "upper_triangle_covariance", "gps_fix_type", "LOCATION_SCALING_FACTOR_M"]
