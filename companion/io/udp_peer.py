"""One peer on a MAVLink ``udpin`` socket: the autopilot.

pymavlink's ``mavudp`` in server mode adds every address that ever sends it a datagram to
``clients`` and sends everything to all of them (``udp_timeout=0``: forever), so one datagram
from a stranger buys them the companion's whole output, and each new sender makes every send
slower.  :class:`UdpPeerLock` replaces the connection's ``recv``:

* before the lock, ``clients`` holds only the latest sender (bounded: one address), so the
  heartbeats and stream requests go to whoever spoke last -- the autopilot, on a normal link;
* :meth:`lock` (the link calls it on the autopilot's HEARTBEAT: system/component id and a
  non-GCS type) fixes the peer to the address that datagram came from; from then on datagrams
  from any other address are dropped unread (``foreign_datagrams``, one warning per 10 s) and
  ``clients`` is exactly the peer;
* a peer silent for ``relock_after_s`` is released (``peer_lost``), so an autopilot that comes
  back from a reboot on another source port is found again.

It filters by address only: a forger who can spoof the autopilot's address or ids needs MAVLink 2
signing to be kept out.  Counters: ``foreign_datagrams``, ``locks``, ``peer_lost``.
"""
from __future__ import annotations

import errno
import logging
import time
from typing import Callable

log = logging.getLogger(__name__)

UDP_MAX_PACKET_LEN = 65535
WARN_INTERVAL_S = 10.0


class UdpPeerLock:
    def __init__(self, conn, *, relock_after_s: float = 5.0, clock: Callable[[], float] = time.monotonic):
        self.conn = conn
        self.relock_after_s = relock_after_s
        self._clock = clock
        self.peer: tuple | None = None
        self.last_addr: tuple | None = None
        self._peer_seen = 0.0
        self._last_warn = -float("inf")
        self.counters: dict[str, int] = {"foreign_datagrams": 0, "locks": 0, "peer_lost": 0}
        conn.recv = self._recv                  # instance attribute: shadows mavudp.recv

    def _set_client(self, addr) -> None:
        c = self.conn
        c.clients = {addr}
        c.clients_last_alive = {addr: time.time()}

    def lock(self) -> None:
        """The datagram just parsed was the autopilot's: talk to its sender only."""
        addr = self.last_addr
        if addr is None or addr == self.peer:
            return
        self.peer = addr
        self._peer_seen = self._clock()
        self._set_client(addr)
        self.counters["locks"] += 1
        log.info("MAVLink udpin locked onto the autopilot at %s:%d", addr[0], addr[1])

    def _recv(self, n=None):
        port = self.conn.port
        for _ in range(256):
            try:
                data, addr = port.recvfrom(UDP_MAX_PACKET_LEN)
            except OSError as exc:
                if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
                    return ""
                raise
            now = self._clock()
            if self.peer is not None and addr != self.peer and now - self._peer_seen > self.relock_after_s:
                self.counters["peer_lost"] += 1
                log.warning("MAVLink udpin: autopilot at %s:%d silent for %.0f s; accepting a new peer",
                            self.peer[0], self.peer[1], now - self._peer_seen)
                self.peer = None
            if self.peer is None or addr == self.peer:
                if self.peer is None and addr != self.last_addr:
                    self._set_client(addr)      # unlocked: answer the latest sender only
                if addr == self.peer:
                    self._peer_seen = now
                self.last_addr = addr
                return data
            self.counters["foreign_datagrams"] += 1
            if now - self._last_warn >= WARN_INTERVAL_S:
                self._last_warn = now
                log.warning("MAVLink udpin: datagram from %s:%d ignored (locked onto %s:%d; %d so far)",
                            addr[0], addr[1], self.peer[0], self.peer[1], self.counters["foreign_datagrams"])
        return ""


__all__ = ["UdpPeerLock"]
