"""A fake ArduPilot on loopback UDP for the GPS-port claim and origin read-back tests.

Real pymavlink bytes both ways; what it models, from ArduPilot 4.x:

* ``GCS_MAVLINK::handle_serial_control``: EXCLUSIVE locks the GPS1 port (``AP_GPS::lock_port``),
  any request without it unlocks; data is written to the receiver; only RESPOND requests are
  answered, <= 70 bytes per reply, MULTI replies while bytes are available (at most
  ``max_replies`` per request: the channel's payload space).
* ``AP_GPS::update_instance`` at 10 Hz: nothing while the port is locked; otherwise the driver
  reads the port (consuming its bytes), a UBX NAV-PVT with a 3-D fix is a new fix
  (GPS_RAW_INT ``time_usec`` = boot time of that fix); no message for ``GPS_TIMEOUT_S`` -> the
  driver is dropped and detection starts again (``detect_s`` of unlocked time).
* The receiver: ``receiver(t) -> bytes`` called every 50 ms fills the port's receive buffer
  (4 kB, oldest bytes lost, like a UART ring).
* ``GCS_MAVLINK::set_ekf_origin``: the first SET_GPS_GLOBAL_ORIGIN is kept (altitude in whole
  cm), later ones are ignored; GPS_GLOBAL_ORIGIN is sent when it is set and on
  MAV_CMD_REQUEST_MESSAGE 49 while set (the command is ACCEPTED either way);
  ``answer_origin=False``: an autopilot that never sends it.
* HEARTBEAT at 2 Hz (``armed`` -> MAV_MODE_FLAG_SAFETY_ARMED), GPS_RAW_INT at 5 Hz.
"""
from __future__ import annotations

import asyncio
import socket
import time

from companion.io import mavlink as M
from companion.io import mavlink_codec
from companion.io.serial_control import UbxFrameScanner

mav = mavlink_codec.mavlink2
GPS_TIMEOUT_S = 4.0          # AP_GPS GPS_TIMEOUT_MS


def free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def nav_pvt(t: float) -> bytes:
    """A UBX NAV-PVT with a 3-D fix, built with pyubx2."""
    from pyubx2 import GET, UBXMessage
    return UBXMessage("NAV", "NAV-PVT", GET, iTOW=int(t * 1000) % 604_800_000, fixType=3, gnssFixOK=1, numSV=12,
                      lat=-35.363261, lon=149.165230, height=584000, hMSL=584000, hAcc=700, vAcc=1200).serialize()


class FakeArduPilot(asyncio.DatagramProtocol):
    def __init__(self, receiver=None, *, armed: bool = False, detect_s: float = 0.3, max_replies: int = 12,
                 origin_e7: tuple[int, int, int] | None = None, answer_origin: bool = True):
        self.enc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
        self.parser = mav.MAVLink(None)
        self.parser.robust_parsing = True
        self.receiver = receiver or (lambda t: b"")
        self.armed = armed
        self.heartbeats_on = True               # False: a silent link (no HEARTBEAT)
        self.detect_s = detect_s
        self.max_replies = max_replies
        self.origin_e7 = origin_e7
        self.answer_origin = answer_origin
        self.transport = None
        self.t0 = time.monotonic()
        self.uart_rx = bytearray()              # receiver -> autopilot
        self.uart_written = bytearray()         # companion -> receiver (through SERIAL_CONTROL)
        self.locked = False
        self.lock_changes: list[tuple[float, bool]] = []     # (t, locked)
        self.requests: list[tuple[float, int]] = []          # SERIAL_CONTROL (t, flags)
        self.received: list[tuple[float, object]] = []
        self.driver = False
        self.detect_elapsed = 0.0
        self.last_msg_t = None
        self.last_fix_us = 0
        self.fix_type = 0
        self.driver_timeouts = 0
        self.uart_overflow = 0                  # receiver bytes lost: nobody read the port in time
        self.detections = 0
        self._scanner = UbxFrameScanner()
        self._tasks = []

    # -- plumbing ------------------------------------------------------------------------------
    def now(self) -> float:
        return time.monotonic() - self.t0

    def connection_made(self, transport):
        self.transport = transport

    def send(self, msg):
        self.transport.sendto(bytes(msg.pack(self.enc)))

    def start(self):
        self._tasks = [asyncio.create_task(self._heartbeats()), asyncio.create_task(self._gps())]

    def stop(self):
        for t in self._tasks:
            t.cancel()
        if self.transport is not None:
            self.transport.close()

    def of_type(self, mtype):
        return [(t, m) for t, m in self.received if m.get_type() == mtype]

    def lock_periods(self) -> list[tuple[float, float]]:
        """(start, end) of every locked period (end = now while still locked)."""
        out, start = [], None
        for t, locked in self.lock_changes:
            if locked and start is None:
                start = t
            elif not locked and start is not None:
                out.append((start, t))
                start = None
        if start is not None:
            out.append((start, self.now()))
        return out

    # -- incoming ------------------------------------------------------------------------------
    def datagram_received(self, data, addr):
        for msg in self.parser.parse_buffer(data) or []:
            self.received.append((self.now(), msg))
            t = msg.get_type()
            if t == "SERIAL_CONTROL":
                self._serial_control(msg)
            elif t == "SET_GPS_GLOBAL_ORIGIN" and self.origin_e7 is None:
                self.origin_e7 = (int(msg.latitude), int(msg.longitude), int(msg.altitude / 10) * 10)
                self._send_origin()
            elif t == "COMMAND_LONG":
                self.send(mav.MAVLink_command_ack_message(msg.command, mav.MAV_RESULT_ACCEPTED, 0, 0,
                                                          msg.get_srcSystem(), msg.get_srcComponent()))
                if msg.command == mav.MAV_CMD_REQUEST_MESSAGE and int(msg.param1) == 49:
                    self._send_origin()

    def _send_origin(self):
        if self.origin_e7 is not None and self.answer_origin:
            self.send(mav.MAVLink_gps_global_origin_message(*self.origin_e7, int(self.now() * 1e6)))

    def _serial_control(self, msg):
        if msg.flags & mav.SERIAL_CONTROL_FLAG_REPLY or msg.device != mav.SERIAL_CONTROL_DEV_GPS1:
            return
        self.requests.append((self.now(), int(msg.flags)))
        exclusive = bool(msg.flags & mav.SERIAL_CONTROL_FLAG_EXCLUSIVE)
        if exclusive != self.locked:
            self.locked = exclusive
            self.lock_changes.append((self.now(), exclusive))
        if msg.count:
            self.uart_written += bytes(msg.data[:msg.count])
        if not msg.flags & mav.SERIAL_CONTROL_FLAG_RESPOND:
            return
        for _ in range(self.max_replies):
            n = min(70, len(self.uart_rx))
            if n == 0:
                return
            chunk = bytes(self.uart_rx[:n])
            del self.uart_rx[:n]
            self.send(mav.MAVLink_serial_control_message(msg.device, mav.SERIAL_CONTROL_FLAG_REPLY, 0, 0, n,
                                                         list(chunk) + [0] * (70 - n)))
            if not msg.flags & mav.SERIAL_CONTROL_FLAG_MULTI:
                return

    # -- the autopilot's own loops -------------------------------------------------------------
    async def _heartbeats(self):
        while True:
            base = mav.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0
            if self.heartbeats_on:
                self.send(mav.MAVLink_heartbeat_message(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, base, 0,
                                                        mav.MAV_STATE_ACTIVE if self.armed else mav.MAV_STATE_STANDBY,
                                                        3))
            await asyncio.sleep(0.5 if self.heartbeats_on else 0.05)

    async def _gps(self):
        dt = 0.05
        k = 0
        while True:
            await asyncio.sleep(dt)
            t = self.now()
            self.uart_rx += self.receiver(t)
            if len(self.uart_rx) > 4096:
                self.uart_overflow += len(self.uart_rx) - 4096
                del self.uart_rx[:len(self.uart_rx) - 4096]
            if k % 2 == 0:
                self._update_instance(t, 2 * dt)
            if k % 4 == 0:
                self.send(mav.MAVLink_gps_raw_int_message(self.last_fix_us, self.fix_type, -353632610, 1491652300,
                                                          584000, 70, 120, 0, 0, 12))
            k += 1

    def _update_instance(self, t, dt):
        if self.locked:
            return                                  # AP_GPS::update_instance: the port is locked
        if not self.driver:
            self.detect_elapsed += dt
            data = bytes(self.uart_rx)
            self.uart_rx.clear()
            if self.detect_elapsed >= self.detect_s and any(c == 0x01 for c, _, _ in self._scanner.feed(data)):
                self.driver = True
                self.detections += 1
                self.last_msg_t = t
            return
        data = bytes(self.uart_rx)
        self.uart_rx.clear()
        got = False
        for cls, mid, payload in self._scanner.feed(data):
            if (cls, mid) == (0x01, 0x07):
                got = True
                self.fix_type = 3
                self.last_fix_us = int(t * 1e6)
        if got:
            self.last_msg_t = t
        elif t - self.last_msg_t > GPS_TIMEOUT_S:
            self.driver = False                     # timed out: state cleared, detection again
            self.driver_timeouts += 1
            self.detect_elapsed = 0.0
            self.fix_type = 0


async def start_pair(ap: FakeArduPilot, **link_kw):
    """A MavlinkLink (udpin on a free port) and the fake autopilot talking to it."""
    port = free_udp_port()
    link = M.MavlinkLink(f"udpin:127.0.0.1:{port}", timesync_interval_s=0, **link_kw)
    await link.start()
    loop = asyncio.get_running_loop()
    await loop.create_datagram_endpoint(lambda: ap, remote_addr=("127.0.0.1", port))
    ap.start()
    return link


async def wait_for(cond, timeout_s: float = 5.0, step_s: float = 0.02) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        await asyncio.sleep(step_s)
    return cond()
