"""MAVLink udpin peer lock on real loopback UDP sockets with pymavlink's own mavudp."""
from __future__ import annotations

import socket
import time

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mav2

from companion.io.udp_peer import UdpPeerLock


def _frame(sysid: int, compid: int, mav_type=mav2.MAV_TYPE_QUADROTOR) -> bytes:
    enc = mav2.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    return enc.heartbeat_encode(mav_type, mav2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0).pack(enc)


def _udp():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(0.05)
    return s


def _drain(conn, lock, on_msg=None, seconds=0.3):
    got = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        m = conn.recv_msg()
        if m is None:
            time.sleep(0.005)
            continue
        got.append(m)
        if on_msg:
            on_msg(m)
    return got


def _received(sock) -> int:
    n = 0
    try:
        while True:
            sock.recv(65535)
            n += 1
    except (socket.timeout, BlockingIOError):
        return n


def test_after_the_autopilot_heartbeat_strangers_get_nothing_and_are_ignored():
    probe = _udp()
    port = probe.getsockname()[1]
    probe.close()
    conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=191)
    lock = UdpPeerLock(conn)
    ap, stranger = _udp(), _udp()
    try:
        def on_msg(m):
            if m.get_type() == "HEARTBEAT" and m.get_srcSystem() == 1 and m.get_srcComponent() == 1:
                lock.lock()

        stranger.sendto(_frame(200, 1), ("127.0.0.1", port))
        ap.sendto(_frame(1, 1), ("127.0.0.1", port))
        _drain(conn, lock, on_msg)
        assert lock.peer == ap.getsockname() and lock.counters["locks"] == 1
        # many strangers after the lock: all dropped, counted, never clients
        others = [_udp() for _ in range(20)]
        for s in others:
            s.sendto(_frame(1, 1), ("127.0.0.1", port))       # even forged autopilot ids
        stranger.sendto(_frame(1, 1), ("127.0.0.1", port))
        ap.sendto(_frame(1, 1), ("127.0.0.1", port))
        msgs = _drain(conn, lock, on_msg)
        assert len(msgs) == 1                                    # the autopilot's only
        assert lock.counters["foreign_datagrams"] == 21
        assert conn.clients == {ap.getsockname()}
        _received(stranger)
        _received(ap)
        for _ in range(50):
            conn.write(_frame(1, 191))
        assert _received(ap) == 50
        assert _received(stranger) == 0 and all(_received(s) == 0 for s in others)
        for s in others:
            s.close()
    finally:
        conn.close()
        ap.close()
        stranger.close()


def test_a_silent_peer_is_released_so_a_rebooted_autopilot_is_found_again():
    probe = _udp()
    port = probe.getsockname()[1]
    probe.close()
    t = [0.0]
    conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}")
    lock = UdpPeerLock(conn, relock_after_s=5.0, clock=lambda: t[0])
    ap1, ap2 = _udp(), _udp()
    try:
        ap1.sendto(_frame(1, 1), ("127.0.0.1", port))
        _drain(conn, lock, lambda m: lock.lock())
        assert lock.peer == ap1.getsockname()
        t[0] = 2.0                                           # within the window: refused
        ap2.sendto(_frame(1, 1), ("127.0.0.1", port))
        assert _drain(conn, lock) == [] and lock.counters["foreign_datagrams"] == 1
        t[0] = 10.0                                          # ap1 silent for 10 s: released
        ap2.sendto(_frame(1, 1), ("127.0.0.1", port))
        _drain(conn, lock, lambda m: lock.lock())
        assert lock.peer == ap2.getsockname() and lock.counters["peer_lost"] == 1
        assert conn.clients == {ap2.getsockname()}
    finally:
        conn.close()
        ap1.close()
        ap2.close()
