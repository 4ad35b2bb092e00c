"""The MAVLink link to the autopilot (asyncio): :class:`MavlinkLink`, built from the configuration by
:func:`link_from_config`.

The pure parts live beside it: :mod:`~companion.io.mavlink_codec` (the dialect, packing and
parsing), :mod:`~companion.io.mavlink_time` (boot time to GPS time),
:mod:`~companion.io.mavlink_decode` (IMU and GPS_RAW_INT decoders) and
:mod:`~companion.io.mavlink_encode` (the fused outputs' encoders); the GPS port's tunnel is
:class:`~companion.io.serial_control.SerialControlTunnel`.

Design of the link (asyncio, no reader thread): pymavlink opens every supported transport
non-blocking (UDP/TCP sockets ``setblocking(False)``, serial ``timeout=0``), so the link registers
the connection's file descriptor with ``loop.add_reader`` and drains ``recv_msg()`` until it returns
``None`` whenever the fd is readable (a transport without an fd is polled every 10 ms).  The
periodic work (heartbeat, TIMESYNC, link timeout, interval retries) is one loop timer armed for
its next deadline, at least every 0.25 s -- no task waking every 10 ms.  All state lives on the event loop thread: no locks, sends are ordinary calls.  A reader
thread would only add a queue hop and locking around pymavlink's shared parser state.  On UDP
without signing the link reads datagrams itself and decodes their high-rate frames with
:mod:`companion.io.mavlink_fast` (same messages as pymavlink's, which parses everything else);
:meth:`MavlinkLink.deliver_to` hands messages to a synchronous consumer instead of the queue.
"""
from __future__ import annotations

import asyncio
import logging
import os
import socket
import time
from collections import deque
from dataclasses import dataclass
from typing import AsyncIterator, Callable

os.environ.setdefault("MAVLINK20", "1")        # mavutil picks its dialect when imported: MAVLink 2
from pymavlink import mavutil  # noqa: E402

from .mavlink_codec import ENCODER, MAV_COMP_ID_ONBOARD_COMPUTER, m  # noqa: E402
from .mavlink_decode import parse_imu_stream  # noqa: E402
from .mavlink_encode import command_set_message_interval, heartbeat  # noqa: E402
from .mavlink_time import BootToGpsTime  # noqa: E402

log = logging.getLogger(__name__)

# 'auto' requests HIGHRES_IMU alone (SI floats) and RAW_IMU (int16 mG, mrad/s) only if the autopilot
# refuses HIGHRES_IMU or it does not arrive: one IMU stream on the link, never two at 200 Hz
IMU_AUTO_FALLBACK = {"HIGHRES_IMU": "RAW_IMU"}
STREAM_FALLBACK_AFTER_S = 3.0
TIMER_SAFETY_NET_S = 0.25      # the link's periodic work runs at least this often (see _arm)
POLL_NO_FD_S = 0.01            # a transport without a file descriptor is polled this often
MIN_RX_PAUSE_S = 0.002         # a shorter sleep saves no wake-up (rx_pause)
# a read that brought more than this many messages (or bad frames) is not followed by a sleep: a 40-ms one
# brings ~10 at 200 Hz; a burst (a parameter download) or a flood would overflow the socket's
# buffer (~200 small datagrams in Linux's default 208 KB) or a serial port's (4 KB) meanwhile
RX_BUSY_MESSAGES = 48
UDP_RX_BUFFER_BYTES = 1 << 20  # asked for the UDP socket (Linux's default 208 KB: ~200 small datagrams)
HOOK_EARLY_S = 0.002           # a hook due as the paused reader wakes runs this much before (_arm_paused_hooks)
HOOK_WINDOW_S = 0.008          # ... when due within this after the wake (the wait for the slot's sample)
TIMESYNC_REPLY_WAIT_S = 0.1    # the reader does not pause this long after our TIMESYNC request (rx_pause)
DEADLINE_SLACK_S = 0.002       # a timeout checked just after it expires, not just before


# =============================================================================================
# (c) the link
@dataclass(frozen=True, slots=True)
class LinkMessage:
    t_mono_ns: int        # receive time, CLOCK_MONOTONIC
    raw: bytes            # the message's bytes as received (for the field log)
    msg: object           # the pymavlink message


@dataclass
class _PendingInterval:
    msg_id: int
    rate_hz: float
    acked: bool = False
    sent: int = 0
    last_sent_mono: float = -1e9
    result: int | None = None


def _offset_rate(samples, max_rate: float = 0.05) -> float:
    """Least-squares slope of the TIMESYNC offsets against our time (>= 3 samples over >= 2 s),
    clamped to +-``max_rate``; 0 otherwise."""
    if len(samples) < 3 or samples[-1][2] - samples[0][2] < 2_000_000_000:
        return 0.0
    n = len(samples)
    mt = sum(s[2] for s in samples) / n
    mo = sum(s[1] for s in samples) / n
    stt = sum((s[2] - mt) ** 2 for s in samples)
    slope = sum((s[2] - mt) * (s[1] - mo) for s in samples) / stt
    return min(max(slope, -max_rate), max_rate)


class MavlinkLink:
    """Asyncio MAVLink link to one autopilot.

    Usage::

        link = MavlinkLink("udpin:127.0.0.1:14550", message_rates_hz={"HIGHRES_IMU": 200, ...})
        await link.start()
        async for lm in link:          # LinkMessage(t_mono_ns, raw, msg), every message received
            ...
        link.send(msg)                 # a pymavlink message object, packed with our ids
        await link.close()

    Behaviour:

    * HEARTBEAT every ``heartbeat_interval_s`` as MAV_TYPE_ONBOARD_CONTROLLER / MAV_AUTOPILOT_INVALID.
    * On the autopilot's first HEARTBEAT, after a link loss and after a reboot (boot time going
      backwards in SYSTEM_TIME/ATTITUDE/IMU), sends MAV_CMD_SET_MESSAGE_INTERVAL for every entry of
      ``message_rates_hz`` and re-sends each every ``interval_retry_s`` until a COMMAND_ACK
      (result ACCEPTED) names it -- acks cannot name the message id, so commands are sent one at a
      time and the ack is matched to the oldest outstanding one.
    * Sends TIMESYNC requests every ``timesync_interval_s`` and keeps the round trip time and the
      autopilot-boot minus our monotonic clock offset (:attr:`timesync_offset_ns`, from the
      lowest-RTT exchange of the last 16; forgotten when the autopilot reboots).
    * Answers TIMESYNC requests (``tc1 == 0``) with ``tc1`` = our clock *in autopilot boot time*
      (our monotonic ns + that offset; plain monotonic ns until the first reply).  Our estimates are
      stamped in autopilot boot time (the IMU samples' own stamps), and PX4 converts every incoming
      timestamp by the offset it learns from our answers (``Timesync::sync_stamp``): answering in
      the same time base makes that offset ~0 instead of the boot-to-monotonic difference.
      ArduPilot learns its own offset (jitter correction) and is indifferent.
    * Link loss: no HEARTBEAT from ``target_system`` for ``link_timeout_s`` -> ``connected`` False,
      counted; a HEARTBEAT brings it back (counted) and re-requests the streams.
    * Bad CRC / unknown ids / truncated frames: counted by reason (``bad_data``), never yielded.
    * ``fallback_streams`` {primary: alternative}: when the autopilot refuses the primary's interval
      or none of it arrives within ``fallback_after_s`` of the link coming up, the alternative is
      requested at the primary's rate instead (counted ``stream_fallbacks``; 'auto' IMU).
    * ``subscribe(type, callback)``: callback(msg, t_mono_ns) on the event loop for every message of
      that type (e.g. the SERIAL_CONTROL tunnel) in addition to the iterator.
    * The receive queue is bounded (``queue_size``); when full the newest message is dropped and
      counted (``rx_queue_overflow``) -- the consumer is too slow, the link keeps running.
    * ``signing`` (a :class:`~companion.io.mavlink_signing.LinkSigning`): MAVLink 2 signing of what
      we send and checks of what we receive; a refused frame goes nowhere and is counted there
      (``signing: ...`` keys in :meth:`health`), not as ``bad_data``.
    """

    def __init__(self, connection: str, *, source_system: int = 1,
                 source_component: int = MAV_COMP_ID_ONBOARD_COMPUTER, target_system: int = 1,
                 target_component: int = 1, message_rates_hz: dict[str, float] | None = None,
                 heartbeat_interval_s: float = 1.0, link_timeout_s: float = 3.0,
                 timesync_interval_s: float = 1.0, interval_retry_s: float = 1.0,
                 interval_max_retries: int = 10, queue_size: int = 20000,
                 time_map: BootToGpsTime | None = None, fallback_streams: dict[str, str] | None = None,
                 fallback_after_s: float = STREAM_FALLBACK_AFTER_S, signing=None):
        self.connection = connection
        self.signing = signing             # LinkSigning (companion.io.mavlink_signing) or None
        self.source_system = source_system
        self.source_component = source_component
        self.target_system = target_system
        self.target_component = target_component
        self.message_rates_hz = dict(message_rates_hz or {})
        self.heartbeat_interval_s = heartbeat_interval_s
        self.link_timeout_s = link_timeout_s
        self.timesync_interval_s = timesync_interval_s
        self.interval_retry_s = interval_retry_s
        self.interval_max_retries = interval_max_retries
        self.time_map = time_map if time_map is not None else BootToGpsTime()
        self.conn = None
        self.counters: dict[str, int] = {
            "rx_messages": 0, "rx_bytes": 0, "tx_messages": 0, "tx_errors": 0, "bad_data": 0,
            "rx_queue_overflow": 0, "heartbeats_rx": 0, "link_losses": 0, "link_recoveries": 0,
            "interval_requests": 0, "interval_acks": 0, "interval_nacks": 0, "interval_gave_up": 0,
            "timesync_answered": 0, "timesync_sent": 0, "timesync_replies": 0, "autopilot_reboots": 0,
            "stream_fallbacks": 0, "rx_pauses": 0, "rx_busy_reads": 0}
        self.bad_data_reasons: dict[str, int] = {}
        self.connected = False
        self.last_heartbeat_mono: float | None = None
        self.autopilot_type: int | None = None
        self.autopilot_autopilot: int | None = None
        self.timesync_rtt_ns: int | None = None
        self.timesync_offset_ns: int | None = None
        self._ts_samples: deque = deque(maxlen=16)     # (rtt, offset, our mid-point time), ns
        self._ts_rate = 0.0                             # d(offset)/d(our time)
        self._ts_best = (0, 0, 0)
        self._ts_sent: dict[int, int] = {}
        self._ts_reply_by = 0.0                         # monotonic s: a TIMESYNC reply may come until then
        self._queue: asyncio.Queue | None = None
        self._queue_size = queue_size
        self._tasks: list[asyncio.Task] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._fd: int | None = None
        self._subs: dict[str, list[Callable]] = {}
        self._intervals: deque[_PendingInterval] = deque()
        self._closed = False
        self._seen_reboot_epoch = 0
        self._last_boot_ms: int | None = None
        # primaries still waiting for their first message -> their alternative
        self._fallback = {k: v for k, v in (fallback_streams or {}).items() if k in self.message_rates_hz}
        self._fallback_after_s = fallback_after_s
        self._link_up_mono: float | None = None
        self.peer_lock = None              # UdpPeerLock on a udpin connection
        self._fast = None                  # DatagramParser on a UDP link without signing
        self._sink: Callable | None = None  # deliver_to's consumer, called instead of queueing
        self._sink_done: asyncio.Future | None = None
        # called after each receive callback: periodic work that rides on a wake-up the process
        # has anyway (the SERIAL_CONTROL poll, serial_control.run_every); a hook's ``next_due()``
        # (monotonic s or None), when it has one, is kept while the reader sleeps (rx_pause)
        self.rx_hooks: list[Callable[[], None]] = []
        # after each read of the descriptor: how long the reader may sleep (seconds; 0 = read on
        # arrival).  What arrives meanwhile waits in the socket and is read in one go: fewer
        # wake-ups (companion.io.rx_pacing).  Never while our TIMESYNC request is out.
        self.rx_pause: Callable[[], float] | None = None
        self._rx_resume: asyncio.TimerHandle | None = None
        self._hooks_timer: asyncio.TimerHandle | None = None
        self._timer: asyncio.TimerHandle | None = None    # the periodic work (_arm)
        self._timer_when = 0.0
        self._next_hb = self._next_ts = 0.0

    # -- lifecycle ---------------------------------------------------------------------------
    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._queue = asyncio.Queue(maxsize=self._queue_size)
        self.conn = mavutil.mavlink_connection(self.connection, source_system=self.source_system,
                                               source_component=self.source_component,
                                               dialect="ardupilotmega", autoreconnect=True)
        self.conn.mav.robust_parsing = True
        if self.signing is not None:
            self.signing.attach(self.conn)
        if isinstance(self.conn, mavutil.mavudp):
            try:      # room for what arrives while the reader sleeps (rx_pause) or the loop is busy
                self.conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RX_BUFFER_BYTES)
            except OSError:
                pass                     # the kernel's default (Linux caps it at net.core.rmem_max)
        if isinstance(self.conn, mavutil.mavudp) and self.conn.udp_server:
            from .udp_peer import UdpPeerLock
            self.peer_lock = UdpPeerLock(self.conn, relock_after_s=max(5.0, 2 * self.link_timeout_s))
        if self.signing is None and isinstance(self.conn, mavutil.mavudp) and os.environ.get(
                "COMPANION_MAVLINK_FAST", "1") != "0":
            # one datagram at a time: its leading high-rate frames without pymavlink's per-byte
            # machinery (companion.io.mavlink_fast); signing needs every frame through pymavlink
            from .mavlink_fast import DatagramParser
            self._fast = DatagramParser(self.conn.mav, post=self.conn.post_message,
                                        on_error=lambda exc: self._bad("exception: " + type(exc).__name__))
        fd = getattr(self.conn, "fd", None)
        if fd is None:
            port = getattr(self.conn, "port", None)
            fd = port.fileno() if port is not None and hasattr(port, "fileno") else None
        if fd is not None and fd >= 0:
            try:
                self._loop.add_reader(fd, self._drain)
                self._fd = fd
            except (ValueError, OSError, NotImplementedError):
                self._fd = None
        self.send(heartbeat())
        self._start_timer()

    async def close(self) -> None:
        self._closed = True
        for h in (self._rx_resume, self._hooks_timer):
            if h is not None:
                h.cancel()
        self._rx_resume = self._hooks_timer = None
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            try:
                await t
            except (asyncio.CancelledError, Exception):
                pass
        self._tasks = []
        if self._fd is not None and self._loop is not None:
            self._loop.remove_reader(self._fd)
            self._fd = None
        if self.conn is not None:
            try:
                self.conn.close()
            except Exception:
                pass
        if self._sink_done is not None and not self._sink_done.done():
            self._sink_done.set_result(None)
        if self._queue is not None:
            try:
                self._queue.put_nowait(None)
            except asyncio.QueueFull:
                pass

    async def __aenter__(self):
        await self.start()
        return self

    async def __aexit__(self, *exc):
        await self.close()

    def __aiter__(self) -> AsyncIterator[LinkMessage]:
        return self._iter()

    async def _iter(self):
        while True:
            item = await self._queue.get()
            if item is None:
                return
            yield item

    async def deliver_to(self, sink: Callable[[LinkMessage], None]) -> None:
        """Hand every received message to ``sink`` synchronously, from the receive callback, instead
        of the queue (no task wake-up and no extra event-loop pass per message); returns when the link
        closes, raises what ``sink`` raised (the sink is then detached: the caller restarts)."""
        fut = self._loop.create_future()
        self._sink, self._sink_done = sink, fut
        try:
            await fut
        finally:
            if self._sink_done is fut:
                self._sink = self._sink_done = None

    async def recv(self, timeout: float | None = None) -> LinkMessage | None:
        """The next received message (None on timeout or close)."""
        try:
            return await asyncio.wait_for(self._queue.get(), timeout)
        except asyncio.TimeoutError:
            return None

    def subscribe(self, msg_type: str, callback: Callable) -> None:
        self._subs.setdefault(msg_type, []).append(callback)

    # -- sending -----------------------------------------------------------------------------
    def send(self, msg) -> bool:
        """Pack with our system/component ids and send.  Never raises on I/O errors (counted)."""
        if self.conn is None:
            return False
        try:
            self.conn.mav.send(msg)
            self.counters["tx_messages"] += 1
            return True
        except Exception as exc:  # socket errors, closed serial port
            self.counters["tx_errors"] += 1
            log.debug("MAVLink send failed: %r", exc)
            return False

    def send_fixed(self, msg, cache: dict) -> bool:
        """Send ``msg``, whose fields never change (the SERIAL_CONTROL poll, 50 a second), from
        ``cache``: its frame packed once per sequence number, ids and protocol version -- byte for
        byte what :meth:`send` would send, without pymavlink's pack each time.  Signed links pack
        every frame (the signature changes)."""
        conn = self.conn
        if conn is None:
            return False
        mav = conn.mav
        if getattr(mav.signing, "sign_outgoing", False) or mav.send_callback is not None:
            return self.send(msg)
        key = (mav.seq, mav.srcSystem, mav.srcComponent, type(mav))     # type: a v1 switch replaces it
        try:
            buf = cache.get(key)
            if buf is None:
                buf = cache[key] = bytes(msg.pack(mav))
            conn.write(buf)
            mav.seq = (mav.seq + 1) % 256
            mav.total_packets_sent += 1
            mav.total_bytes_sent += len(buf)
            self.counters["tx_messages"] += 1
            return True
        except Exception as exc:  # socket errors, closed serial port
            self.counters["tx_errors"] += 1
            log.debug("MAVLink send failed: %r", exc)
            return False

    # -- receiving ---------------------------------------------------------------------------
    def _drain(self) -> None:
        c = self.counters
        n0 = c["rx_messages"] + c["bad_data"]
        if self._fast is not None:
            self._drain_datagrams()
        else:
            self._drain_messages()
        for hook in self.rx_hooks:
            hook()
        if self.rx_pause is not None and self._fd is not None:
            if c["rx_messages"] + c["bad_data"] - n0 > RX_BUSY_MESSAGES:
                c["rx_busy_reads"] += 1                   # a burst or a flood: keep reading
            else:
                self._maybe_pause()

    # -- paced reading (rx_pause) ------------------------------------------------------------
    def _maybe_pause(self) -> None:
        """Stop reading for ``rx_pause()`` seconds; not while our TIMESYNC request waits for its
        reply (its round trip would count the sleep)."""
        now = time.monotonic()
        if now < self._ts_reply_by:
            return
        pause = self.rx_pause()
        if pause < MIN_RX_PAUSE_S:
            return
        self._loop.remove_reader(self._fd)
        self._rx_resume = self._loop.call_later(pause, self._resume_reading)
        self.counters["rx_pauses"] += 1
        self._arm_paused_hooks(now)

    def _arm_paused_hooks(self, now: float) -> None:
        """While the reader sleeps, the hooks due before it wakes (the SERIAL_CONTROL poll keeps its
        grid: the autopilot's GPS port buffers ~22 ms) run from a timer of their own, without a
        read: a read then would cost a wake-up's worth of datagrams.  A hook due just after the
        reader wakes, while it waits for the next output slot's sample, runs ``HOOK_EARLY_S``
        before instead (``run_early``, when it has one): its reply then comes with the batch
        rather than as a wake-up of its own."""
        if self._rx_resume is None:
            return
        resume = now + (self._rx_resume.when() - self._loop.time())
        when = None
        for hook in self.rx_hooks:
            plan = self._hook_time(hook, resume)
            if plan is not None and (when is None or plan[0] < when):
                when = plan[0]
        if when is not None:
            self._hooks_timer = self._loop.call_later(max(0.0, when - now), self._paused_hooks)

    @staticmethod
    def _hook_time(hook, resume: float) -> tuple[float, bool] | None:
        """When the paused reader's timer runs ``hook`` (monotonic s) and whether early, or None
        (at the next read)."""
        next_due = getattr(hook, "next_due", None)
        due = next_due() if next_due is not None else None
        if due is None:
            return None
        if due + DEADLINE_SLACK_S < resume - HOOK_EARLY_S:
            return due + DEADLINE_SLACK_S, False    # just after: the hook finds itself due
        if due < resume + HOOK_WINDOW_S and getattr(hook, "run_early", None) is not None:
            return resume - HOOK_EARLY_S, True
        return None

    def _paused_hooks(self) -> None:
        self._hooks_timer = None
        if self._rx_resume is None:
            return                       # reading again: the hooks ride on the reads
        now = time.monotonic()
        resume = now + (self._rx_resume.when() - self._loop.time())
        for hook in self.rx_hooks:
            plan = self._hook_time(hook, resume)
            if plan is not None and plan[1] and now >= plan[0]:
                hook.run_early()
            else:
                hook()                   # runs only when due
        self._arm_paused_hooks(time.monotonic())

    def _resume_reading(self) -> None:
        self._rx_resume = None
        if self._hooks_timer is not None:
            self._hooks_timer.cancel()
            self._hooks_timer = None
        if self._closed or self._fd is None:
            return
        self._loop.add_reader(self._fd, self._drain)
        self._drain()                    # what arrived meanwhile, at once

    def _drain_messages(self) -> None:
        conn = self.conn
        for _ in range(10000):
            try:
                msg = conn.recv_msg()
            except Exception as exc:  # pymavlink raises on some malformed input
                self._bad("exception: " + type(exc).__name__)
                continue
            if msg is None:
                break
            self._handle(msg, time.monotonic_ns())
        if self.signing is not None:
            # at once, not at the next timer: a protocol auto-switch in recv_msg replaced the
            # MAVLink object, and what we send next must be signed again
            self.signing.tick()

    def _drain_datagrams(self) -> None:
        """The UDP receive path: each datagram through :class:`~companion.io.mavlink_fast.DatagramParser`
        (the lean decoder for its leading high-rate frames, pymavlink for the rest) -- the messages
        ``recv_msg`` would have given, in the same order."""
        conn = self.conn
        feed = self._fast.feed
        for _ in range(10000):
            try:
                data = conn.recv()
            except Exception as exc:
                self._bad("exception: " + type(exc).__name__)
                return
            if not data:
                return
            t_ns = time.monotonic_ns()
            if conn.first_byte:                 # pymavlink's MAVLink 1/2 detection, as recv_msg does
                conn.auto_mavlink_version(data)
            for msg in feed(data):
                self._handle(msg, t_ns)

    def _bad(self, reason: str) -> None:
        self.counters["bad_data"] += 1
        key = reason.split(",")[0][:60]
        self.bad_data_reasons[key] = self.bad_data_reasons.get(key, 0) + 1

    def _handle(self, msg, t_ns: int) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            if self.signing is not None and self.signing.rejected(msg):
                return                           # refused by signing: counted there, not bad data
            self._bad(str(getattr(msg, "reason", "bad data")))
            return
        if mtype.startswith("UNKNOWN_"):
            # an id outside the dialect: its CRC cannot be checked; after a truncated frame this
            # is usually garbage, so it is counted and not passed on
            self._bad("unknown message id")
            return
        raw = bytes(msg.get_msgbuf())
        self.counters["rx_messages"] += 1
        self.counters["rx_bytes"] += len(raw)
        from_ap = msg.get_srcSystem() == self.target_system
        if self._fallback and mtype in self._fallback:
            del self._fallback[mtype]            # the primary arrives: no fallback needed
        if mtype == "HEARTBEAT" and from_ap and msg.type != m.MAV_TYPE_GCS \
                and msg.get_srcComponent() == self.target_component:
            self._on_heartbeat(msg)
        elif mtype == "TIMESYNC":
            self._on_timesync(msg, t_ns)
        elif mtype == "COMMAND_ACK" and from_ap:
            self._on_command_ack(msg)
        if from_ap and mtype in ("SYSTEM_TIME", "ATTITUDE"):
            boot_ms = int(msg.time_boot_ms)
            if mtype == "SYSTEM_TIME":
                self.time_map.update_system_time(int(msg.time_unix_usec), boot_ms)
            else:
                self.time_map.observe_boot_time(boot_ms * 1e-3)
        if self.time_map.boot_epoch != self._seen_reboot_epoch:
            self._seen_reboot_epoch = self.time_map.boot_epoch
            self.counters["autopilot_reboots"] += 1
            self._ts_samples.clear()             # its boot clock restarted: the old offset is void
            self.timesync_offset_ns = None
            self._request_streams("autopilot reboot")
        for cb in self._subs.get(mtype, ()):
            try:
                cb(msg, t_ns)
            except Exception:
                log.exception("MAVLink subscriber for %s failed", mtype)
        sink = self._sink
        if sink is not None:
            try:
                sink(LinkMessage(t_ns, raw, msg))
            except Exception as exc:
                self._sink = None                # later messages queue until the caller is back
                if not self._sink_done.done():
                    self._sink_done.set_exception(exc)
            return
        try:
            self._queue.put_nowait(LinkMessage(t_ns, raw, msg))
        except asyncio.QueueFull:
            self.counters["rx_queue_overflow"] += 1

    def _on_heartbeat(self, msg) -> None:
        if self.peer_lock is not None:
            self.peer_lock.lock()          # the datagram just parsed came from the autopilot
        self.counters["heartbeats_rx"] += 1
        self.last_heartbeat_mono = time.monotonic()
        self.autopilot_type = msg.type
        self.autopilot_autopilot = msg.autopilot
        if not self.connected:
            if self.counters["heartbeats_rx"] > 1 or self.counters["link_losses"]:
                self.counters["link_recoveries"] += 1
                log.info("autopilot link recovered")
            self.connected = True
            self._link_up_mono = self.last_heartbeat_mono
            self._request_streams("link up")
            self._wake_now()               # TIMESYNC and the timeout/fallback deadlines start now

    def _on_timesync(self, msg, t_ns: int) -> None:
        if msg.tc1 == 0:
            ours_ns = t_ns if self.timesync_offset_ns is None else t_ns + self._timesync_offset_at(t_ns)
            reply = ENCODER.timesync_encode(ours_ns, msg.ts1)
            if hasattr(reply, "target_system"):
                reply.target_system = msg.get_srcSystem()
                reply.target_component = msg.get_srcComponent()
            self.send(reply)
            self.counters["timesync_answered"] += 1
            return
        sent = self._ts_sent.pop(int(msg.ts1), None)
        if sent is None:
            return
        self._ts_reply_by = 0.0
        rtt = t_ns - sent
        self.counters["timesync_replies"] += 1
        # autopilot time tc1 (ns since its boot) corresponds to our mid-point
        offset = int(msg.tc1) - (sent + rtt // 2)
        self._ts_samples.append((rtt, offset, sent + rtt // 2))
        self._ts_rate = _offset_rate(self._ts_samples)
        self._ts_best = min(self._ts_samples)
        self.timesync_rtt_ns = rtt
        self.timesync_offset_ns = self._timesync_offset_at(t_ns)

    def _timesync_offset_at(self, t_ns: int) -> int:
        """The lowest-RTT offset of the window, carried to ``t_ns`` at the offset's drift rate: PX4
        SITL's lockstep boot clock runs ~1.3 % slow, so a 16-s-old best sample is 0.2 s off, and
        PX4 resets its time synchroniser after 5 answers more than 0.1 s from its estimate ("time
        jump detected"), converting our estimates' stamps wrongly meanwhile (EKF2 lost our vision)."""
        _, off, t_ref = self._ts_best
        return int(off + self._ts_rate * (t_ns - t_ref))

    def mono_to_boot_us(self, t_mono_ns: int) -> int | None:
        """Our monotonic time -> autopilot boot time (us), from TIMESYNC; None before a reply."""
        if self.timesync_offset_ns is None:
            return None
        return (t_mono_ns + self._timesync_offset_at(t_mono_ns)) // 1000

    def _on_command_ack(self, msg) -> None:
        if msg.command != m.MAV_CMD_SET_MESSAGE_INTERVAL:
            return
        pend = next((p for p in self._intervals if not p.acked and p.sent > 0), None)
        if pend is None:
            return
        pend.result = int(msg.result)
        if msg.result == m.MAV_RESULT_ACCEPTED:
            pend.acked = True
            self.counters["interval_acks"] += 1
        else:
            pend.acked = True          # a refusal will not change by repeating it
            self.counters["interval_nacks"] += 1
            log.warning("autopilot refused SET_MESSAGE_INTERVAL for message %d (result %d)",
                        pend.msg_id, msg.result)
            primary = next((k for k in self._fallback if getattr(m, f"MAVLINK_MSG_ID_{k}", None) == pend.msg_id),
                           None)
            if primary is not None:
                self._fall_back(primary, "refused")
        self._send_next_interval()

    def _fall_back(self, primary: str, why: str) -> None:
        alt = self._fallback.pop(primary)
        rate = self.message_rates_hz[primary]
        self.message_rates_hz[alt] = rate
        self._intervals.append(_PendingInterval(getattr(m, f"MAVLINK_MSG_ID_{alt}"), float(rate)))
        self.counters["stream_fallbacks"] += 1
        log.warning("%s %s by the autopilot: requesting %s at %g Hz instead", primary, why, alt, rate)

    # -- stream rates ------------------------------------------------------------------------
    def _request_streams(self, why: str) -> None:
        if not self.message_rates_hz:
            return
        log.info("requesting message intervals (%s)", why)
        self._intervals.clear()
        for name, rate in self.message_rates_hz.items():
            msg_id = getattr(m, f"MAVLINK_MSG_ID_{name}", None)
            if msg_id is None:
                log.error("unknown MAVLink message %s in message_rates_hz", name)
                continue
            self._intervals.append(_PendingInterval(msg_id, float(rate)))
        self._send_next_interval()

    def _send_next_interval(self) -> None:
        now = time.monotonic()
        for p in self._intervals:
            if p.acked:
                continue
            if p.sent and now - p.last_sent_mono < self.interval_retry_s:
                return                  # one outstanding at a time
            if p.sent >= self.interval_max_retries:
                p.acked = True
                self.counters["interval_gave_up"] += 1
                log.warning("no COMMAND_ACK for SET_MESSAGE_INTERVAL of message %d", p.msg_id)
                continue
            self.send(command_set_message_interval(p.msg_id, p.rate_hz, self.target_system,
                                                   self.target_component, confirmation=min(p.sent, 255)))
            p.sent += 1
            p.last_sent_mono = now
            self.counters["interval_requests"] += 1
            return

    @property
    def intervals_acknowledged(self) -> bool:
        return bool(self._intervals) and all(p.acked and p.result == m.MAV_RESULT_ACCEPTED
                                             for p in self._intervals)

    # -- periodic work -----------------------------------------------------------------------
    # No polling task: one loop timer (``call_at``) armed for the earliest deadline -- heartbeat,
    # TIMESYNC, link timeout, stream fallback, interval retry -- at most TIMER_SAFETY_NET_S ahead,
    # so anything not computed here is late by at most that; a transport without a file
    # descriptor (nothing to wake the loop) is still drained every POLL_NO_FD_S.
    def _start_timer(self) -> None:
        now = time.monotonic()
        self._next_hb = self._next_ts = now
        self._arm(now)

    def _arm(self, when: float) -> None:
        """(Re-)arm the timer for ``when`` (monotonic s) unless it already fires earlier."""
        if self._closed or self._loop is None:
            return
        h = self._timer
        if h is not None:
            if not h.cancelled() and self._timer_when <= when:
                return
            h.cancel()
        # loop.time() is time.monotonic() for the default loops; converted anyway
        self._timer_when = when
        self._timer = self._loop.call_at(self._loop.time() + (when - time.monotonic()), self._on_timer)

    def _wake_now(self) -> None:
        """A state change (link up) brings deadlines forward: run the periodic work next pass."""
        self._arm(time.monotonic())

    def _on_timer(self) -> None:
        self._timer = None
        now = time.monotonic()
        try:
            self._tick(now)
        except Exception:      # a bug here must not end the heartbeats and the timeout checks
            self.counters["timer_errors"] = self.counters.get("timer_errors", 0) + 1
            log.exception("MAVLink link periodic work failed")
        finally:
            self._arm(self._next_deadline(time.monotonic()))

    def _tick(self, now: float) -> None:
        if self._fd is None:
            self._drain()
        if self.signing is not None:
            self.signing.tick()
        if now >= self._next_hb:
            self.send(heartbeat())
            self._next_hb = now + self.heartbeat_interval_s
        if self.timesync_interval_s > 0 and now >= self._next_ts and self.connected:
            ts1 = time.monotonic_ns()
            self._ts_sent[ts1] = ts1
            self._ts_reply_by = now + TIMESYNC_REPLY_WAIT_S     # read it on arrival: its RTT counts
            if len(self._ts_sent) > 32:
                self._ts_sent.pop(next(iter(self._ts_sent)))
            req = ENCODER.timesync_encode(0, ts1)
            if hasattr(req, "target_system"):
                req.target_system = self.target_system
                req.target_component = self.target_component
            self.send(req)
            self.counters["timesync_sent"] += 1
            self._next_ts = now + self.timesync_interval_s
        if self.connected and self.last_heartbeat_mono is not None \
                and now - self.last_heartbeat_mono > self.link_timeout_s:
            self.connected = False
            self.counters["link_losses"] += 1
            log.warning("autopilot link lost (no HEARTBEAT for %.1f s)", now - self.last_heartbeat_mono)
        if self._fallback and self.connected and self._link_up_mono is not None \
                and now - self._link_up_mono > self._fallback_after_s:
            for primary in list(self._fallback):
                self._fall_back(primary, f"not sent within {self._fallback_after_s:g} s")
        self._send_next_interval()

    def _next_deadline(self, now: float) -> float:
        t = min(now + TIMER_SAFETY_NET_S, self._next_hb)
        if self._fd is None:
            t = min(t, now + POLL_NO_FD_S)
        if self.connected:
            if self.timesync_interval_s > 0:
                t = min(t, self._next_ts)
            if self.last_heartbeat_mono is not None:
                t = min(t, self.last_heartbeat_mono + self.link_timeout_s + DEADLINE_SLACK_S)
            if self._fallback and self._link_up_mono is not None:
                t = min(t, self._link_up_mono + self._fallback_after_s + DEADLINE_SLACK_S)
        for p in self._intervals:
            if not p.acked:            # one outstanding at a time: the first not acknowledged
                t = min(t, p.last_sent_mono + self.interval_retry_s if p.sent else now)
                break
        return max(t, now + 0.001)

    def health(self) -> dict:
        return {"connected": self.connected, **self.counters, "bad_data_reasons": dict(self.bad_data_reasons),
                **({} if self.signing is None else {**self.signing.counters, "signing": self.signing.health()}),
                "udp_peer": None if self.peer_lock is None else {
                    "peer": self.peer_lock.peer and "%s:%d" % self.peer_lock.peer, **self.peer_lock.counters},
                "time_map": dict(self.time_map.counters), "timesync_rtt_ms":
                    None if self.timesync_rtt_ns is None else self.timesync_rtt_ns * 1e-6}


def message_rates_from_config(cfg) -> dict[str, float]:
    """The stream rates to request for a :class:`companion.config.MavlinkConfig`."""
    rates: dict[str, float] = {}
    if cfg.imu_cluster:
        for name in cfg.imu_cluster:
            rates[parse_imu_stream(name)[0]] = cfg.imu_rate_hz
    else:   # one stream: 'auto' asks for HIGHRES_IMU, RAW_IMU only as its fallback (link_from_config)
        rates[cfg.imu_message if cfg.imu_message != "auto" else "HIGHRES_IMU"] = cfg.imu_rate_hz
    rates["SYSTEM_TIME"] = cfg.system_time_rate_hz
    if cfg.gps_raw_rate_hz > 0:
        rates["GPS_RAW_INT"] = cfg.gps_raw_rate_hz
    if cfg.attitude_rate_hz > 0:
        rates["ATTITUDE"] = cfg.attitude_rate_hz
    if cfg.extended_sys_state_rate_hz > 0:
        rates["EXTENDED_SYS_STATE"] = cfg.extended_sys_state_rate_hz
    return rates


def link_from_config(cfg, time_map: BootToGpsTime | None = None) -> MavlinkLink:
    """A :class:`MavlinkLink` for a :class:`companion.config.MavlinkConfig` (raises
    :class:`~companion.io.mavlink_signing.SigningKeyError` for an unusable signing key file)."""
    from .mavlink_signing import signing_from_config
    return MavlinkLink(cfg.connection, source_system=cfg.source_system, source_component=cfg.source_component,
                       target_system=cfg.target_system, target_component=cfg.target_component,
                       message_rates_hz=message_rates_from_config(cfg),
                       heartbeat_interval_s=cfg.heartbeat_interval_s, link_timeout_s=cfg.link_timeout_s,
                       timesync_interval_s=cfg.timesync_interval_s, interval_retry_s=cfg.interval_retry_s,
                       time_map=time_map,
                       fallback_streams=IMU_AUTO_FALLBACK if cfg.imu_message == "auto" and not cfg.imu_cluster
                       else None, signing=signing_from_config(cfg))


__all__ = ["LinkMessage", "MavlinkLink", "message_rates_from_config", "link_from_config", "IMU_AUTO_FALLBACK"]
