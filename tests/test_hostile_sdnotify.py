"""systemd notify/watchdog protocol against a real AF_UNIX datagram socket."""
from __future__ import annotations

import os
import socket

from companion.sdnotify import SystemdNotifier


def test_ready_and_rate_limited_watchdog_pets(tmp_path):
    path = str(tmp_path / "notify")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(path)
    srv.settimeout(1.0)
    t = [0.0]
    n = SystemdNotifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "3000000", "WATCHDOG_PID": str(os.getpid())},
                        clock=lambda: t[0])
    n.ready("running")
    assert srv.recv(256) == b"READY=1\nSTATUS=running"
    pets = 0
    for k in range(1000):             # 10 s of an IMU at 100 Hz
        t[0] = k * 0.01
        n.pet()
    srv.setblocking(False)
    try:
        while True:
            assert srv.recv(64) == b"WATCHDOG=1"
            pets += 1
    except BlockingIOError:
        pass
    assert 10 <= pets <= 11           # every second (a third of 3 s), not per sample
    srv.close()


def test_outside_systemd_everything_is_a_no_op():
    n = SystemdNotifier({})
    n.ready()
    n.pet()
    n.stopping()
    assert not n.enabled and n.sent == 0
    # a watchdog meant for another process is not ours to pet
    assert SystemdNotifier({"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "1000000", "WATCHDOG_PID": "1"}).watchdog_period_s == 0
