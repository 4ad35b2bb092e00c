"""The harness's ground station on SITL's SERIAL0: records truth and the autopilot's outputs, flies.

Everything arrives on one pymavlink TCP connection and is stamped with our monotonic receive time:
SITL's truth (SIMSTATE, SIM_STATE), the autopilot's estimate (LOCAL_POSITION_NED,
EKF_STATUS_REPORT), STATUSTEXT, HEARTBEAT (armed, mode) and the companion's estimates, which
ArduPilot routes to every other MAVLink channel because they carry no target
(VISION_POSITION_ESTIMATE, ODOMETRY, GPS_INPUT).  :meth:`Gcs.pump` is the only reader; the flight
steps call it while they wait.
"""
from __future__ import annotations

import math
import time
from collections import defaultdict

from pymavlink import mavutil

mav = mavutil.mavlink

COPTER_MODES = {"STABILIZE": 0, "GUIDED": 4, "LOITER": 5, "RTL": 6, "LAND": 9}
MODE_NAMES = {v: k for k, v in COPTER_MODES.items()}

# what the ground station asks for on SERIAL0 (Hz)
STREAMS_HZ = {"SIMSTATE": 50.0, "SIM_STATE": 10.0, "LOCAL_POSITION_NED": 25.0, "ATTITUDE": 25.0,
              "EKF_STATUS_REPORT": 2.0, "GLOBAL_POSITION_INT": 5.0, "GPS2_RAW": 5.0, "SYSTEM_TIME": 1.0,
              "EXTENDED_SYS_STATE": 2.0}
RECORDED = ("SIMSTATE", "SIM_STATE", "LOCAL_POSITION_NED", "ATTITUDE", "EKF_STATUS_REPORT",
            "VISION_POSITION_ESTIMATE", "ODOMETRY", "GPS_INPUT", "GPS_RAW_INT", "GPS2_RAW",
            "GPS_GLOBAL_ORIGIN", "EXTENDED_SYS_STATE", "NAMED_VALUE_FLOAT")


class Gcs:
    recorded = RECORDED          # message types kept in :attr:`records` (PX4's ground station adds its own)

    def __init__(self, port: int, *, target_system: int = 1, on_statustext=None, url: str | None = None):
        """SITL's SERIAL0 on TCP ``port``; ``url``: another pymavlink connection instead (PX4: UDP)."""
        self.conn = mavutil.mavlink_connection(url or f"tcp:127.0.0.1:{port}", source_system=255,
                                               source_component=190, dialect="ardupilotmega",
                                               autoreconnect=False)
        self.target_system = target_system
        self.records: dict[str, list] = defaultdict(list)       # type -> [(t_mono_s, msg)]
        self.statustext: list[tuple[float, str]] = []
        self.armed = False
        self.custom_mode: int | None = None
        self.heartbeats = 0
        self.acks: list[tuple[float, int, int]] = []             # (t, command, result)
        self._on_statustext = on_statustext
        self._next_hb = 0.0

    def close(self) -> None:
        try:
            self.conn.close()
        except Exception:
            pass

    # -- receiving ----------------------------------------------------------------------------
    def pump(self, seconds: float) -> None:
        """Read and record messages for ``seconds`` (also sends our 1 Hz HEARTBEAT)."""
        t_end = time.monotonic() + seconds
        while True:
            now = time.monotonic()
            if now >= self._next_hb:
                self.conn.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                self._next_hb = now + 1.0
            left = t_end - now
            if left <= 0:
                return
            msg = self.conn.recv_match(blocking=True, timeout=min(left, 0.2))
            if msg is not None:
                self._record(msg, time.monotonic())

    def _record(self, msg, t: float) -> None:
        mtype = msg.get_type()
        if mtype == "HEARTBEAT":
            if msg.get_srcSystem() == self.target_system and msg.get_srcComponent() == 1:
                self.heartbeats += 1
                self.armed = bool(msg.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)
                self.custom_mode = msg.custom_mode
        elif mtype == "STATUSTEXT":
            text = msg.text.rstrip("\x00")
            self.statustext.append((t, text))
            if self._on_statustext:
                self._on_statustext(text)
        elif mtype == "COMMAND_ACK":
            self.acks.append((t, msg.command, msg.result))
        elif mtype in self.recorded:
            self.records[mtype].append((t, msg))

    def named_value(self, name: str) -> float | None:
        """The latest NAMED_VALUE_FLOAT ``name`` (the companion's CC_* values), or None."""
        for _, m in reversed(self.records.get("NAMED_VALUE_FLOAT", ())):
            if m.name.rstrip("\x00") == name:
                return m.value
        return None

    def last(self, mtype: str):
        r = self.records.get(mtype)
        return r[-1][1] if r else None

    def wait_heartbeat(self, timeout_s: float = 30.0) -> None:
        t_end = time.monotonic() + timeout_s
        while self.heartbeats == 0:
            if time.monotonic() > t_end:
                raise RuntimeError(f"no HEARTBEAT from the autopilot within {timeout_s:.0f} s")
            self.pump(0.2)

    # -- commands -----------------------------------------------------------------------------
    def command(self, command: int, *params: float) -> None:
        p = list(params) + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(self.target_system, 1, command, 0, *p)

    def command_ack(self, command: int, *params: float, timeout_s: float = 3.0) -> int | None:
        """Send COMMAND_LONG and wait for its COMMAND_ACK; the result (None = no ack)."""
        n0 = len(self.acks)
        self.command(command, *params)
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            self.pump(0.05)
            for _, cmd, result in self.acks[n0:]:
                if cmd == command:
                    return result
        return None

    def request_streams(self, rates_hz: dict[str, float] = STREAMS_HZ) -> None:
        for name, rate in rates_hz.items():
            msg_id = getattr(mav, f"MAVLINK_MSG_ID_{name}")
            self.command_ack(mav.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / rate, timeout_s=1.0)

    def request_message(self, name: str) -> None:
        self.command(mav.MAV_CMD_REQUEST_MESSAGE, getattr(mav, f"MAVLINK_MSG_ID_{name}"))

    def set_mode(self, name: str, timeout_s: float = 5.0) -> bool:
        want = COPTER_MODES[name]
        self.command_ack(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, want)
        t_end = time.monotonic() + timeout_s
        while self.custom_mode != want and time.monotonic() < t_end:
            self.pump(0.1)
        return self.custom_mode == want

    def arm(self) -> int | None:
        return self.command_ack(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)

    def takeoff(self, alt_m: float) -> int | None:
        return self.command_ack(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, 0, 0, alt_m)

    def set_speed(self, speed_mps: float) -> int | None:
        return self.command_ack(mav.MAV_CMD_DO_CHANGE_SPEED, 1, speed_mps, -1)

    def goto_local(self, n_m: float, e_m: float, d_m: float) -> None:
        """GUIDED position target in the EKF's local NED frame (position bits only)."""
        mask = 0b0000_1111_1111_1000      # ignore velocity, acceleration, yaw, yaw rate
        self.conn.mav.set_position_target_local_ned_send(0, self.target_system, 1, mav.MAV_FRAME_LOCAL_NED,
                                                         mask, n_m, e_m, d_m, 0, 0, 0, 0, 0, 0, 0, 0)

    def local_ned(self):
        """The autopilot's latest LOCAL_POSITION_NED as (n, e, d), or None."""
        m = self.last("LOCAL_POSITION_NED")
        return None if m is None else (m.x, m.y, m.z)
