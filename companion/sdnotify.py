"""systemd notification (``Type=notify``, ``WatchdogSec``) without a dependency.

systemd passes ``NOTIFY_SOCKET`` (a datagram socket path, ``@`` = abstract namespace) and, with
``WatchdogSec``, ``WATCHDOG_USEC``.  :class:`SystemdNotifier` sends ``READY=1`` once,
``WATCHDOG=1`` at most every third of the watchdog period (the service pets it from the event
loop, so a loop that is stuck -- or an IMU path that never returns -- stops the pets and systemd
restarts the service), ``STATUS=...`` and ``STOPPING=1``.  Outside systemd every call is a no-op.
"""
from __future__ import annotations

import os
import socket
import time


class SystemdNotifier:
    def __init__(self, environ=None, clock=time.monotonic):
        env = os.environ if environ is None else environ
        self._addr = env.get("NOTIFY_SOCKET") or None
        if self._addr and self._addr.startswith("@"):
            self._addr = "\0" + self._addr[1:]
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        period = int(usec) * 1e-6 if usec.isdigit() else 0.0
        if pid.isdigit() and int(pid) != os.getpid():
            period = 0.0                         # the watchdog is meant for another process
        self.watchdog_period_s = period
        self._clock = clock
        self._last_pet = -float("inf")
        self._sock: socket.socket | None = None
        self.sent = 0

    @property
    def enabled(self) -> bool:
        return self._addr is not None

    def _send(self, text: str) -> None:
        if self._addr is None:
            return
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto(text.encode(), self._addr)
            self.sent += 1
        except OSError:
            pass                                # systemd gone or socket full: nothing to do

    def ready(self, status: str = "") -> None:
        self._send("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def status(self, text: str) -> None:
        self._send(f"STATUS={text}")

    def stopping(self) -> None:
        self._send("STOPPING=1")

    def pet(self) -> None:
        """Cheap enough for the IMU path: one clock read unless a pet is due."""
        if self.watchdog_period_s <= 0:
            return
        now = self._clock()
        if now - self._last_pet >= self.watchdog_period_s / 3.0:
            self._last_pet = now
            self._send("WATCHDOG=1")


__all__ = ["SystemdNotifier"]
