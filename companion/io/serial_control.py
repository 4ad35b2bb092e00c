"""The receiver on the autopilot's GPS port, through MAVLink SERIAL_CONTROL: detect, then claim.

:class:`SerialControlTunnel` is the byte stream; :class:`PortClaim` decides when the companion may
hold the port at all.  What ArduPilot does (``GCS_serial_control.cpp``, ``AP_GPS.cpp``, 4.x):

* A request with EXCLUSIVE calls ``AP_GPS::lock_port(instance, true)``: from then on
  ``AP_GPS::update_instance`` returns at once -- no detection, no reading, no timeout -- so the
  autopilot's GPS state is frozen (GPS_RAW_INT repeats its last fix with the same ``time_usec``).
  The lock has **no timeout**: it lasts until a request *without* EXCLUSIVE arrives (or a
  reboot).  A companion that dies holding it leaves the autopilot without GPS.
* A request without EXCLUSIVE unlocks; with RESPOND it would also *read* the port, taking bytes
  from under the GPS driver (both would get a split stream), so the release request carries no
  flags at all.  ``timeout`` > 0 makes the autopilot's MAVLink thread sleep waiting for data
  (kept 0); ``baudrate`` != 0 re-opens the port.
* Replies (<= 70 bytes each) come only in answer to RESPOND requests; MULTI keeps replying while
  bytes are available and the channel has room.
* After the unlock the driver reads again.  If the last message it parsed is older than
  ``GPS_TIMEOUT_MS`` (4 s) it is deleted and detection starts over: measured on ArduCopter
  4.7.0-dev SITL, GPS_RAW_INT moved again 0.16 s after a 3 s lock, but 9.0 s after a 6 s lock.
  Hence a probe window of 3 s by default.
* ArduPilot's u-blox driver makes RXM-RAWX itself with ``GPS_RAW_DATA`` 1 (it requests the rate
  and logs the frames).  With 0 it leaves RAWX alone but counts every non-NAV frame it does not
  handle (RXM-SFRBX, and RAWX) as unexpected and, every 256th, sends CFG-MSG rate 0 for it: a
  receiver configured for raw output is slowly silenced while the autopilot reads it.  So the
  parameter file explains ``GPS_RAW_DATA 1`` (for a raw-capable receiver) and, once the port is
  claimed, the companion switches RXM-SFRBX on (volatile CFG-MSG for the current port,
  ``gnss.serial_control_enable_sfrbx``).
* PX4 (``MavlinkReceiver::handle_message_serial_control``) serves only its shell device: every
  probe finds nothing and its GPS is never touched.

:class:`PortClaim` (``gnss.serial_control_claim = "detect"``, the default):

* **released** (the autopilot's GPS driver owns the port): no requests at all.
* **probing**: EXCLUSIVE polls for ``probe_s``; a checked RXM-RAWX frame with at least
  :data:`MIN_RAW_MEASUREMENTS` measurements in what comes back = raw observations are flowing
  -> **claimed** at once; none -> release (the unlock is sent three times, UDP may drop one),
  retry after a back-off doubling from ``retry_initial_s`` (5 s) to ``retry_max_s`` (600 s):
  each probe freezes the autopilot's GPS for its window, so after the first minutes (when
  ArduPilot's driver, with ``GPS_RAW_DATA`` 1, has switched RAWX on) they become rare.  No probe starts
  while the vehicle is armed (HEARTBEAT ``MAV_MODE_FLAG_SAFETY_ARMED``) unless ``probe_when_armed``:
  the autopilot's GPS is not interrupted in flight to look for something it has not had so far.
* **claimed**: EXCLUSIVE polls for as long as raw epochs keep coming; none for
  ``release_after_s`` -> release (and probe again later).  After a link loss or an autopilot
  reboot a claim is re-checked as a fresh probe.
* ``close()`` (service shutdown) releases the port whenever it was ever locked.
* After each release the time until GPS_RAW_INT carries a new 3-D fix is measured
  (``autopilot_gps_back_s``): the proof the autopilot got its GPS back.  After a release because
  raw epochs stopped (the sky was blocked, the receiver lost track) that new fix also means the
  receiver tracks again: the next probe starts at once instead of after the back-off (a 30-s
  outage left the port to the autopilot for 5 s after the sky was back, and the RTK fix with it),
  armed or not (raw GNSS flowed in this run: otherwise an outage in flight lost it until landing).
* ``"always"``: the old behaviour, EXCLUSIVE from the start and never released -- only for a port
  with no GPS driver of the autopilot on it (``GPSn_TYPE 0``).

Events worth a STATUSTEXT (claim, the first probe of a series finding nothing, release) are
queued in :attr:`PortClaim.events` as (MAV_SEVERITY, text).
"""
from __future__ import annotations

import asyncio
import logging
import time
from typing import TYPE_CHECKING, Callable

from .mavlink_codec import m
from .mavlink_encode import serial_control_request
from .ubx import ubx_checksum, ubx_frame

if TYPE_CHECKING:
    from .mavlink import MavlinkLink

log = logging.getLogger(__name__)

SERIAL_CONTROL_DATA_LEN = 70
UBX_SYNC = b"\xb5\x62"
UBX_CLASS_RXM, UBX_RXM_RAWX, UBX_RXM_SFRBX = 0x02, 0x15, 0x13
MIN_RAW_MEASUREMENTS = 4          # a RAWX epoch with fewer cannot give a position: not "flowing"
UBX_MAX_PAYLOAD = 8192
# u-blox message classes (NAV RXM INF ACK CFG UPD MON AID TIM ESF MGA LOG SEC HNR NAV2): a sync
# pattern inside a payload followed by another class is skipped at once instead of making the
# scanner wait for up to UBX_MAX_PAYLOAD bytes of a frame that is not one
UBX_CLASSES = frozenset((0x01, 0x02, 0x04, 0x05, 0x06, 0x09, 0x0A, 0x0B, 0x0D, 0x10, 0x13, 0x21, 0x27, 0x28,
                         0x29))
RELEASE_REPEATS_S = (0.0, 0.2, 0.5)   # the unlock, repeated: a lost one would leave the GPS locked
MAV_SEVERITY_WARNING, MAV_SEVERITY_NOTICE, MAV_SEVERITY_INFO = 4, 5, 6


async def run_every(fn: Callable[[], object], delay_s: Callable[[], float], link=None) -> None:
    """``fn()``, then again ``delay_s()`` later, forever (cancel to stop); raises what ``fn`` raised.

    No task sleeping in a loop: the calls are due on a fixed grid (so the average rate is exactly
    ``1 / delay_s()``) and made from ``link``'s receive callback (:attr:`MavlinkLink.rx_hooks`)
    when a datagram is processed after the due time -- a wake-up the process has anyway, 200 a
    second with the IMU stream -- or by a loop timer half a period late when none comes (a quiet
    link).  Without ``link`` the timer alone, on time.  ``delay_s() == 0``: again at once."""
    loop = asyncio.get_running_loop()
    done = loop.create_future()
    handle = None
    state = {"due": loop.time(), "period": 0.0}

    def fire() -> None:
        nonlocal handle
        if handle is not None:
            handle.cancel()
            handle = None
        if done.done():
            return
        try:
            fn()
            d = delay_s()
        except BaseException as exc:   # noqa: B902 -- handed to the awaiting task
            done.set_exception(exc)
            return
        now = loop.time()
        if d <= 0:
            state["due"], state["period"] = now, 0.0
            handle = loop.call_soon(fire)
            return
        due = state["due"] + d
        if due < now - d:              # fell behind by more than a period: no burst to catch up
            due = now
        state["due"], state["period"] = due, d
        handle = loop.call_at(due + (0.5 * d if link is not None else 0.0), fire)

    def on_rx() -> None:
        if state["period"] > 0 and loop.time() >= state["due"]:
            fire()

    def early() -> None:
        if state["period"] > 0:
            state["due"] = loop.time()   # the grid restarts now: no gap longer than a period
            fire()

    # a paced reader (MavlinkLink.rx_pause) calls it by then, or a little early (run_early)
    on_rx.next_due = lambda: state["due"] if state["period"] > 0 else None
    on_rx.run_early = early
    if link is not None:
        link.rx_hooks.append(on_rx)
    handle = loop.call_soon(fire)
    try:
        await done
    finally:
        if handle is not None:
            handle.cancel()
        if link is not None and on_rx in link.rx_hooks:
            link.rx_hooks.remove(on_rx)


def cfg_msg_current_port(msg_class: int, msg_id: int, rate: int) -> bytes:
    """UBX-CFG-MSG, 3-byte form: output rate of one message on the port it arrives on (volatile)."""
    return ubx_frame(0x06, 0x01, bytes([msg_class, msg_id, rate]))


class UbxFrameScanner:
    """Splits a byte stream into checksum-checked UBX frames ``(class, id, payload)``; everything
    else (NMEA, garbage, a frame cut by a lock change) is skipped.  Bounded: at most one frame
    (``max_payload`` + 8 bytes) is ever buffered.  Only the u-blox classes (:data:`UBX_CLASSES`)
    and RXM-RAWX lengths of 16 + 32 n are waited for."""

    def __init__(self, max_payload: int = UBX_MAX_PAYLOAD):
        self.max_payload = max_payload
        self._buf = bytearray()
        self.bad_frames = 0

    def feed(self, data: bytes) -> list[tuple[int, int, bytes]]:
        buf = self._buf
        buf += data
        out = []
        i = 0
        while True:
            j = buf.find(UBX_SYNC, i)
            if j < 0:
                i = len(buf) - 1 if buf.endswith(UBX_SYNC[:1]) else len(buf)
                break
            if len(buf) - j < 6:
                i = j
                break
            n = buf[j + 4] | (buf[j + 5] << 8)
            if n > self.max_payload or buf[j + 2] not in UBX_CLASSES or (
                    (buf[j + 2], buf[j + 3]) == (UBX_CLASS_RXM, UBX_RXM_RAWX) and (n < 16 or (n - 16) % 32)):
                self.bad_frames += 1
                i = j + 2
                continue
            if len(buf) - j < n + 8:
                i = j
                break
            body = bytes(buf[j + 2:j + 6 + n])
            if bytes(ubx_checksum(body)) == bytes(buf[j + 6 + n:j + 8 + n]):
                out.append((body[0], body[1], body[4:]))
                i = j + 8 + n
            else:
                self.bad_frames += 1
                i = j + 2
        del buf[:i]
        return out


def rawx_measurements(payload: bytes) -> int | None:
    """numMeas of a well-formed RXM-RAWX payload (16 + 32 x numMeas bytes), else None."""
    if len(payload) < 16 or len(payload) != 16 + 32 * payload[11]:
        return None
    return payload[11]


# =============================================================================================
class SerialControlTunnel:
    """Byte stream to/from the receiver on the autopilot's GPS port, tunnelled in SERIAL_CONTROL.

    ArduPilot only sends receiver bytes in reply to a request, so :meth:`run` (or the
    :class:`PortClaim` driving it) polls every ``poll_interval_s`` with a SERIAL_CONTROL request
    (flags RESPOND | EXCLUSIVE | MULTI, timeout 0; see
    :func:`~companion.io.mavlink_encode.serial_control_request`), carrying up to 70 bytes of pending
    writes (UBX configuration).  Replies (flag REPLY, same device, from the autopilot) are
    appended, in arrival order, to an internal queue -- iterate the tunnel (``async for chunk in
    tunnel``) to get them -- and handed to every callable in :attr:`listeners`.
    :meth:`release` sends one request without any flag, which hands the port back to the
    autopilot's own GPS driver without reading from it.

    Throughput: each reply carries <= 70 bytes; with MULTI ArduPilot keeps replying while data is
    available (as long as its channel has room), so one poll drains the port.

    Cost: the poll keeps its rate (ArduPilot opens a GPS port with a 256-byte receive buffer,
    ``AP_SERIALMANAGER_GPS_BUFSIZE_RX``: ~22 ms of bytes at 115200 baud), but the request
    without data is packed once per sequence number
    (:meth:`~companion.io.mavlink.MavlinkLink.send_fixed`) and the polls are due on a fixed grid,
    sent from the link's receive callback when a datagram is processed after the due time
    (:func:`run_every`): no wake-up of their own while the IMU stream flows.
    ``queue_replies=False`` (the service): the replies go to :attr:`listeners` only.
    """

    def __init__(self, link: "MavlinkLink", device: int = m.SERIAL_CONTROL_DEV_GPS1, poll_interval_s: float = 0.02,
                 baudrate: int = 0, exclusive: bool = True, multi: bool = True, max_queue: int = 4096,
                 queue_replies: bool = True):
        self.link = link
        self.device = device
        self.poll_interval_s = poll_interval_s
        self.baudrate = baudrate
        self.flags = m.SERIAL_CONTROL_FLAG_RESPOND
        if exclusive:
            self.flags |= m.SERIAL_CONTROL_FLAG_EXCLUSIVE
        if multi:
            self.flags |= m.SERIAL_CONTROL_FLAG_MULTI
        self._tx = bytearray()
        # queue_replies False: the bytes go to the listeners only (the service reads them from the
        # logged MAVLink stream; a queue nobody needs would wake a draining task per reply)
        self._rx: asyncio.Queue | None = asyncio.Queue(maxsize=max_queue) if queue_replies else None
        self._empty_poll = None                 # (flags, device, target) -> the request without data
        self._poll_frames: dict = {}            # its packed frames (MavlinkLink.send_fixed)
        self.listeners: list[Callable[[bytes], None]] = []
        self.counters: dict[str, int] = {"polls": 0, "replies": 0, "rx_bytes": 0, "tx_bytes": 0,
                                         "rx_overflow": 0, "foreign_replies": 0, "releases_sent": 0}
        self._baud_sent = False
        link.subscribe("SERIAL_CONTROL", self._on_serial_control)

    @property
    def device_name(self) -> str:
        return {m.SERIAL_CONTROL_DEV_GPS1: "GPS1", m.SERIAL_CONTROL_DEV_GPS2: "GPS2"}.get(self.device,
                                                                                          f"dev{self.device}")

    def write(self, data: bytes) -> None:
        """Queue bytes for the receiver (sent 70 at a time with the next polls)."""
        self._tx += data

    @property
    def tx_pending(self) -> int:
        return len(self._tx)

    def resend_baud(self) -> None:
        """Send ``baudrate`` again with the next poll (the autopilot's driver may have changed it)."""
        self._baud_sent = False

    def _on_serial_control(self, msg, t_ns: int) -> None:
        if not (msg.flags & m.SERIAL_CONTROL_FLAG_REPLY):
            return
        if msg.device != self.device or msg.get_srcSystem() != self.link.target_system:
            self.counters["foreign_replies"] += 1
            return
        n = max(0, min(int(msg.count), SERIAL_CONTROL_DATA_LEN))
        data = bytes(msg.data[:n])
        self.counters["replies"] += 1
        if not data:
            return
        self.counters["rx_bytes"] += n
        for cb in self.listeners:
            try:
                cb(data)
            except Exception:
                log.exception("SERIAL_CONTROL listener failed")
        if self._rx is None:
            return
        try:
            self._rx.put_nowait(data)
        except asyncio.QueueFull:
            self.counters["rx_overflow"] += 1

    def poll(self) -> None:
        """Send one request (with up to 70 pending bytes)."""
        link = self.link
        if not self._tx and (self._baud_sent or not self.baudrate):
            # the usual poll, no data and no baud rate: the same message every time, packed once
            # per sequence number (pymavlink's pack was most of a poll's CPU)
            key = (self.flags, self.device, link.target_system, link.target_component)
            if self._empty_poll is None or self._empty_poll[0] != key:
                self._empty_poll = (key, serial_control_request(
                    self.device, b"", flags=self.flags, target_system=link.target_system,
                    target_component=link.target_component))
                self._poll_frames = {}
            send_fixed = getattr(link, "send_fixed", None)
            if send_fixed is not None:
                send_fixed(self._empty_poll[1], self._poll_frames)
            else:                               # a link without the cache (a test double)
                link.send(self._empty_poll[1])
            self.counters["polls"] += 1
            return
        chunk = bytes(self._tx[:SERIAL_CONTROL_DATA_LEN])
        del self._tx[:len(chunk)]
        baud = self.baudrate if (self.baudrate and not self._baud_sent) else 0
        self._baud_sent = self._baud_sent or bool(baud)
        link.send(serial_control_request(self.device, chunk, flags=self.flags, baudrate=baud,
                                                    target_system=link.target_system,
                                                    target_component=link.target_component))
        self.counters["polls"] += 1
        self.counters["tx_bytes"] += len(chunk)

    async def run(self) -> None:
        """Poll forever (cancel to stop)."""
        await run_every(self.poll, lambda: self.poll_interval_s if not self._tx else 0.0,
                        link=self.link if hasattr(self.link, "rx_hooks") else None)

    def release(self) -> None:
        """Unlock the port: no EXCLUSIVE (unlock), no RESPOND (do not read the driver's bytes)."""
        self.link.send(serial_control_request(self.device, b"", flags=0,
                                                         target_system=self.link.target_system,
                                                         target_component=self.link.target_component))
        self.counters["releases_sent"] += 1

    def __aiter__(self):
        return self._iter()

    async def _iter(self):
        if self._rx is None:
            raise RuntimeError("SERIAL_CONTROL tunnel made with queue_replies=False: use listeners")
        while True:
            yield await self._rx.get()

    async def read(self, timeout: float | None = None) -> bytes:
        if self._rx is None:
            raise RuntimeError("SERIAL_CONTROL tunnel made with queue_replies=False: use listeners")
        try:
            return await asyncio.wait_for(self._rx.get(), timeout)
        except asyncio.TimeoutError:
            return b""


# =============================================================================================
class PortClaim:
    """Detect, then claim (see the module doc): drives a :class:`SerialControlTunnel` so the
    autopilot keeps its GPS port unless raw observations are actually flowing."""

    RELEASED, PROBING, CLAIMED = "released", "probing", "claimed"

    def __init__(self, tunnel: SerialControlTunnel, *, mode: str = "detect", probe_s: float = 3.0,
                 release_after_s: float = 10.0, retry_initial_s: float = 5.0, retry_max_s: float = 600.0,
                 probe_when_armed: bool = False, enable_sfrbx: bool = True,
                 clock: Callable[[], float] = time.monotonic):
        if mode not in ("detect", "always"):
            raise ValueError(f"mode must be 'detect' or 'always', got {mode!r}")
        self.tunnel = tunnel
        self.link = tunnel.link
        self.mode = mode
        self.probe_s = probe_s
        self.release_after_s = release_after_s
        self.retry_initial_s = retry_initial_s
        self.retry_max_s = max(retry_max_s, retry_initial_s)
        self.probe_when_armed = probe_when_armed
        self.enable_sfrbx = enable_sfrbx
        self.clock = clock
        self.state = self.RELEASED
        self.armed = False
        self.events: list[tuple[int, str]] = []
        self.counters: dict[str, int] = {
            "probes": 0, "probes without raw": 0, "claims": 0, "releases: raw stopped": 0,
            "releases: no raw in probe": 0, "re-checks after link loss or reboot": 0, "raw epochs": 0,
            "raw epochs too few measurements": 0, "sfrbx frames": 0, "ubx frames": 0,
            "probes deferred: armed": 0, "autopilot GPS back after release": 0,
            "probes on the autopilot's GPS back": 0}
        self.last_raw_mono: float | None = None
        self.autopilot_gps_back_s: float | None = None
        self._scanner = UbxFrameScanner()
        self._probe_t0 = 0.0
        self._next_probe = -float("inf")          # the first probe as soon as the link is up
        self._retry_s = retry_initial_s
        self._quiet_probe = False                 # a failed probe in a series: no STATUSTEXT again
        self._probe_frames0 = 0                   # "ubx frames" when the probe started
        self._releases_due: list[float] = []
        self._ever_locked = False
        self._link_down = False
        self._reboots_seen = self.link.counters.get("autopilot_reboots", 0)
        self._deferred_logged = False
        self._gps_wait: tuple[float, int | None] | None = None   # (release time, GPS_RAW_INT time_usec then)
        self._probe_when_gps_back = False         # released because raw stopped: probe on the next 3-D fix
        self._probing_on_gps_back = False         # that probe is due (it may start while armed)
        self._gps_time_usec: int | None = None
        tunnel.listeners.append(self._on_bytes)
        self.link.subscribe("HEARTBEAT", self._on_heartbeat)
        self.link.subscribe("GPS_RAW_INT", self._on_gps_raw)

    # -- inputs ------------------------------------------------------------------------------
    def _from_autopilot(self, msg) -> bool:
        return msg.get_srcSystem() == self.link.target_system and msg.get_srcComponent() == self.link.target_component

    def _on_heartbeat(self, msg, t_ns: int = 0) -> None:
        if self._from_autopilot(msg) and msg.type != m.MAV_TYPE_GCS:
            self.armed = bool(msg.base_mode & m.MAV_MODE_FLAG_SAFETY_ARMED)

    def _on_gps_raw(self, msg, t_ns: int = 0) -> None:
        if not self._from_autopilot(msg):
            return
        tu = int(msg.time_usec)
        self._gps_time_usec = tu
        if self._gps_wait is not None and tu != self._gps_wait[1] and int(msg.fix_type) >= 3:
            self.autopilot_gps_back_s = round(self.clock() - self._gps_wait[0], 3)
            self.counters["autopilot GPS back after release"] += 1
            log.info("the autopilot's GPS has a 3-D fix again %.2f s after the port was released",
                     self.autopilot_gps_back_s)
            self._gps_wait = None
            if self._probe_when_gps_back and self.state == self.RELEASED:
                self._probe_when_gps_back = False
                self._probing_on_gps_back = True      # armed or not: raw GNSS was flowing in this run
                self._next_probe = -float("inf")
                self.counters["probes on the autopilot's GPS back"] += 1

    def _on_bytes(self, data: bytes) -> None:
        for cls, mid, payload in self._scanner.feed(data):
            self.counters["ubx frames"] += 1
            if cls != UBX_CLASS_RXM:
                continue
            if mid == UBX_RXM_SFRBX:
                self.counters["sfrbx frames"] += 1
            elif mid == UBX_RXM_RAWX:
                n = rawx_measurements(payload)
                if n is not None and n >= MIN_RAW_MEASUREMENTS:
                    self.counters["raw epochs"] += 1
                    self.last_raw_mono = self.clock()
                else:
                    self.counters["raw epochs too few measurements"] += 1

    # -- the state machine -------------------------------------------------------------------
    def _event(self, severity: int, text: str) -> None:
        self.events.append((severity, text))
        (log.warning if severity <= MAV_SEVERITY_WARNING else log.info)("%s", text)

    def drain_events(self) -> list[tuple[int, str]]:
        ev, self.events = self.events, []
        return ev

    def _start_probe(self, now: float, why: str) -> None:
        self.state = self.PROBING
        self._probe_t0 = now
        self._releases_due.clear()
        self.tunnel.resend_baud()
        self.counters["probes"] += 1
        self._probe_frames0 = self.counters["ubx frames"]
        log.info("%s: probing for raw GNSS (%s, %.1f s)", self.tunnel.device_name, why, self.probe_s)

    def _claim(self, now: float) -> None:
        self.state = self.CLAIMED
        self.counters["claims"] += 1
        self._retry_s = self.retry_initial_s
        self._quiet_probe = False
        self._probe_when_gps_back = False
        if self.mode == "always":
            self._event(MAV_SEVERITY_INFO, f"{self.tunnel.device_name}: port claimed (always)")
        else:
            self._event(MAV_SEVERITY_INFO, f"{self.tunnel.device_name}: raw GNSS seen, port claimed")
        if self.enable_sfrbx and self.mode == "detect":
            # the autopilot's driver may have switched SFRBX off while it had the port
            self.tunnel.write(cfg_msg_current_port(UBX_CLASS_RXM, UBX_RXM_SFRBX, 1))

    def _release(self, now: float, reason: str) -> None:
        self.state = self.RELEASED
        self._releases_due = [now + dt for dt in RELEASE_REPEATS_S]
        self._send_due_releases(now)
        self._gps_wait = (now, self._gps_time_usec)     # autopilot_gps_back_s: the last one measured
        dev = self.tunnel.device_name
        if reason == "raw stopped":
            self.counters["releases: raw stopped"] += 1
            self._probe_when_gps_back = True
            self._retry_s = self.retry_initial_s
            self._next_probe = now + self._retry_s
            self._quiet_probe = False
            self._event(MAV_SEVERITY_WARNING, f"{dev}: raw GNSS stopped, port released")
        else:
            self.counters["releases: no raw in probe"] += 1
            self.counters["probes without raw"] += 1
            self._next_probe = now + self._retry_s
            log.info("%s: no raw GNSS in %.1f s: port released, next probe in %.0f s", dev, self.probe_s,
                     self._retry_s)
            self._retry_s = min(self.retry_max_s, 2.0 * self._retry_s)
            if not self._quiet_probe:
                self._quiet_probe = True
                # by name: a factory-default u-blox answers with NAV/NMEA but no RXM-RAWX (issue 15);
                # STATUSTEXT is cut at 50 bytes with the service's "CC: ": the hint goes to the log
                frames = self.counters["ubx frames"] - self._probe_frames0
                self._event(MAV_SEVERITY_NOTICE, f"{dev}: {'no RXM-RAWX' if frames else 'no UBX reply'}, "
                                                 "port left to autopilot")
                log.warning("%s: %s: 'companion gnss configure --mavlink ...' switches RXM-RAWX and "
                            "RXM-SFRBX on (with the service stopped)", dev,
                            f"{frames} UBX frames but no RXM-RAWX" if frames else "no UBX from the receiver")

    def _send_due_releases(self, now: float) -> None:
        while self._releases_due and now >= self._releases_due[0]:
            self._releases_due.pop(0)
            self.tunnel.release()

    def step(self, now: float | None = None) -> bool:
        """Advance the state machine; poll when the port is (to be) held.  True = polled."""
        now = self.clock() if now is None else now
        link = self.link
        if not link.connected:
            self._link_down = self._link_down or self.state != self.RELEASED
            return False
        reboots = link.counters.get("autopilot_reboots", 0)
        if reboots != self._reboots_seen or self._link_down:
            self._reboots_seen = reboots
            self._link_down = False
            if self.state == self.CLAIMED and self.mode == "detect":
                # the autopilot may have rebooted (lock gone) or the receiver changed meanwhile
                self.counters["re-checks after link loss or reboot"] += 1
                self._start_probe(now, "re-check after link loss or reboot")
        self._send_due_releases(now)
        if self.state == self.RELEASED:
            if self.mode == "always":
                self._claim(now)
            elif now < self._next_probe:
                return False
            elif self.armed and not (self.probe_when_armed or self._probing_on_gps_back):
                self.counters["probes deferred: armed"] += int(not self._deferred_logged)
                self._deferred_logged = True
                return False
            else:
                self._deferred_logged = False
                why = "autopilot's GPS back" if self._probing_on_gps_back else (
                    "first" if self.counters["probes"] == 0 else "retry")
                self._probing_on_gps_back = False
                self._start_probe(now, why)
        if self.state == self.PROBING:
            if self.last_raw_mono is not None and self.last_raw_mono >= self._probe_t0:
                self._claim(now)
            elif now - self._probe_t0 >= self.probe_s:
                self._release(now, "no raw in probe")
                return False
        elif self.state == self.CLAIMED and self.mode == "detect":
            last = self.last_raw_mono if self.last_raw_mono is not None else -float("inf")
            if now - last > self.release_after_s:
                self._release(now, "raw stopped")
                return False
        self.tunnel.poll()
        self._ever_locked = True
        return True

    async def run(self) -> None:
        """Step forever (cancel to stop); pending writes go out without waiting."""
        await run_every(self.step, lambda: self.tunnel.poll_interval_s
                        if not (self.tunnel.tx_pending and self.state != self.RELEASED) else 0.0,
                        link=self.link if hasattr(self.link, "rx_hooks") else None)

    def close(self) -> None:
        """Give the port back (service shutdown): the lock would otherwise outlive us."""
        if self._ever_locked:
            self.tunnel.release()
            self.tunnel.release()
        self.state = self.RELEASED

    def health(self) -> dict:
        now = self.clock()
        return {"mode": self.mode, "state": self.state, "armed": self.armed, **self.counters,
                "raw_age_s": None if self.last_raw_mono is None else round(now - self.last_raw_mono, 2),
                "next_probe_in_s": (round(max(0.0, self._next_probe - now), 1)
                                    if self.state == self.RELEASED and self._next_probe > -float("inf") else None),
                "autopilot_gps_back_s": self.autopilot_gps_back_s, "ubx_bad_frames": self._scanner.bad_frames}


__all__ = ["SerialControlTunnel", "PortClaim", "UbxFrameScanner", "rawx_measurements", "cfg_msg_current_port",
           "MIN_RAW_MEASUREMENTS", "SERIAL_CONTROL_DATA_LEN"]
