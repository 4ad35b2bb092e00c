"""The harness's ground station for PX4 SITL: its GCS link (commands, EKF2's outputs, our
estimates), its SIH display link (truth), and OFFBOARD setpoints.

* GCS link: ``udpout`` to PX4's bound port 18570+N (PX4 answers whoever last sent there).  Both
  that link and the onboard link run with forwarding (``mavlink start -f``), so the companion's
  VISION_POSITION_ESTIMATE (no target: broadcast) also arrives here, as ArduPilot routes it.
* Display link: ``udpin`` on 19410+N, where SIH sends HIL_STATE_QUATERNION, its truth.  That
  message carries no time (``time_usec`` 0), so ATTITUDE is requested on the same link and its
  ``time_boot_ms`` maps receive times to PX4 boot time (the transport floor, as for SIMSTATE).
* OFFBOARD: :attr:`setpoint` (NED position and optional velocity feed-forward, EKF2's local
  frame) is streamed at 10 Hz by :meth:`pump` whenever it is set; PX4 needs it before and during
  OFFBOARD (COM_OF_LOSS_T).

Everything is stamped with our monotonic receive time, as in :class:`sitl.ardupilot_gcs.Gcs`.
"""
from __future__ import annotations

import select
import time

from pymavlink import mavutil

from .ardupilot_gcs import RECORDED, Gcs

mav = mavutil.mavlink

# PX4 custom_mode: main mode in bits 16-23, sub mode in bits 24-31 (px4_custom_mode.h)
MAIN_MODES = {1: "MANUAL", 2: "ALTCTL", 3: "POSCTL", 4: "AUTO", 5: "ACRO", 6: "OFFBOARD", 7: "STABILIZED"}
AUTO_SUB_MODES = {1: "READY", 2: "TAKEOFF", 3: "LOITER", 4: "MISSION", 5: "RTL", 6: "LAND", 8: "FOLLOW",
                  9: "PRECLAND"}
OFFBOARD = 6

# what the ground station asks for on the GCS link (Hz); LOCAL_POSITION_NED and ATTITUDE come at
# 50 Hz there by default
STREAMS_HZ = {"ESTIMATOR_STATUS": 2.0, "EXTENDED_SYS_STATE": 2.0, "GPS_RAW_INT": 5.0, "HOME_POSITION": 0.5}
DISPLAY_STREAMS_HZ = {"ATTITUDE": 50.0}
MASK_POS_VEL = 0b0000_1101_1100_0000     # use position and velocity; ignore acceleration, yaw, yaw rate


def mode_name(custom_mode: int | None) -> str:
    if custom_mode is None:
        return "?"
    main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
    name = MAIN_MODES.get(main, str(main))
    return f"{name}.{AUTO_SUB_MODES.get(sub, sub)}" if main == 4 else name


class Px4Gcs(Gcs):
    recorded = RECORDED + ("HIGHRES_IMU", "HIL_STATE_QUATERNION", "DISPLAY_ATTITUDE", "ESTIMATOR_STATUS",
                           "HOME_POSITION")

    def __init__(self, gcs_port: int, display_port: int, *, target_system: int = 1, on_statustext=None):
        super().__init__(0, target_system=target_system, on_statustext=on_statustext,
                         url=f"udpout:127.0.0.1:{gcs_port}")
        self.display = mavutil.mavlink_connection(f"udpin:127.0.0.1:{display_port}", source_system=255,
                                                  source_component=190, dialect="ardupilotmega")
        self.setpoint: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
        self.setpoints_sent = 0
        self.modes: list[tuple[float, int, bool]] = []        # (t, custom_mode, armed) at every change
        self.states: list[tuple[float, int, bool]] = []       # (t, system_status, armed) at every change
        self._next_sp = 0.0
        self._display_requested = False

    def close(self) -> None:
        super().close()
        try:
            self.display.close()
        except Exception:
            pass

    def pump(self, seconds: float) -> None:
        """Read both links for ``seconds``; sends our 1 Hz HEARTBEAT and the 10 Hz setpoint."""
        t_end = time.monotonic() + seconds
        socks = [c.port for c in (self.conn, self.display)]
        while True:
            now = time.monotonic()
            if now >= self._next_hb:
                self.conn.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                self._next_hb = now + 1.0
            if self.setpoint is not None and now >= self._next_sp:
                self._send_setpoint()
                self._next_sp = now + 0.1
            left = t_end - now
            if left <= 0:
                return
            ready, _, _ = select.select(socks, [], [], min(left, 0.05))
            for conn in (self.conn, self.display):
                if conn.port not in ready:
                    continue
                while True:
                    msg = conn.recv_msg()
                    if msg is None:
                        break
                    if conn is self.display:
                        self._record_display(msg, time.monotonic())
                    else:
                        self._record(msg, time.monotonic())

    def _record(self, msg, t: float) -> None:
        if msg.get_type() == "HEARTBEAT" and msg.get_srcSystem() == self.target_system \
                and msg.get_srcComponent() == 1:
            armed = bool(msg.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)
            if not self.modes or self.modes[-1][1] != msg.custom_mode:
                self.modes.append((t, msg.custom_mode, armed))
            if not self.states or self.states[-1][1:] != (msg.system_status, armed):
                self.states.append((t, msg.system_status, armed))
        super()._record(msg, t)

    def _record_display(self, msg, t: float) -> None:
        mtype = msg.get_type()
        if mtype == "HIL_STATE_QUATERNION":
            self.records[mtype].append((t, msg))
            if not self._display_requested:      # udpin: replies go to PX4's display port now
                self._display_requested = True
                for name, rate in DISPLAY_STREAMS_HZ.items():
                    self.display.mav.command_long_send(self.target_system, 1, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                       getattr(mav, f"MAVLINK_MSG_ID_{name}"), 1e6 / rate,
                                                       0, 0, 0, 0, 0)
        elif mtype == "ATTITUDE":
            self.records["DISPLAY_ATTITUDE"].append((t, msg))

    def request_streams(self, rates_hz: dict[str, float] = STREAMS_HZ) -> None:
        super().request_streams(rates_hz)

    # -- flying -------------------------------------------------------------------------------
    def _send_setpoint(self) -> None:
        (n, e, d), (vn, ve, vd) = self.setpoint
        self.conn.mav.set_position_target_local_ned_send(int(time.monotonic() * 1e3) & 0xFFFFFFFF,
                                                         self.target_system, 1, mav.MAV_FRAME_LOCAL_NED,
                                                         MASK_POS_VEL, n, e, d, vn, ve, vd, 0, 0, 0, 0, 0)
        self.setpoints_sent += 1

    def set_px4_mode(self, main: int, sub: int = 0, timeout_s: float = 3.0) -> bool:
        want = (main << 16) | (sub << 24)
        self.command_ack(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub)
        t_end = time.monotonic() + timeout_s
        while self.custom_mode != want and time.monotonic() < t_end:
            self.pump(0.1)
        return self.custom_mode == want

    def land(self) -> int | None:
        return self.command_ack(mav.MAV_CMD_NAV_LAND, 0, 0, 0, float("nan"), float("nan"), float("nan"),
                                float("nan"))

    @property
    def main_mode(self) -> int | None:
        return None if self.custom_mode is None else (self.custom_mode >> 16) & 0xFF
