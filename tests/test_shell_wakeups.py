"""The cheaper shell (issue 16): the link's periodic work on deadlines instead of a 10-ms task,
the SERIAL_CONTROL poll from cached frames and loop timers, the field log written in batches and
bounded in age -- each against the behaviour it must keep."""
from __future__ import annotations

import asyncio
import os
import struct
import threading
import time

import pytest

import companion.io.mavlink as M
from companion.io import mavlink_codec
from companion.io import mavlink_encode
from companion.io.fieldlog import FieldLogWriter, encode_record, read_field_log
from companion.io.serial_control import SerialControlTunnel, run_every
from tests.test_mavlink_io import _start_pair, _wait, free_udp_port

mav = mavlink_codec.mavlink2
HB = mav.MAVLink_heartbeat_message(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4, 3)


def _count_timer_runs(link) -> list:
    runs = []
    real = link._on_timer

    def spy():
        runs.append(time.monotonic())
        real()
    link._on_timer = spy
    link._arm(time.monotonic())          # re-armed through the spy
    return runs


def test_link_timer_wakes_for_deadlines_only_and_keeps_heartbeat_timesync_and_timeout():
    async def main():
        port = free_udp_port()
        link, ap, transport = await _start_pair(port, heartbeat_interval_s=0.5, link_timeout_s=0.8,
                                                timesync_interval_s=0.3)
        try:
            ap.send(HB)
            assert await _wait(lambda: link.connected)
            runs = _count_timer_runs(link)
            n_hb, n_ts = len(ap.of_type("HEARTBEAT")), len(ap.of_type("TIMESYNC"))
            t0 = time.monotonic()
            while time.monotonic() - t0 < 0.7:          # the autopilot keeps beating: link stays up
                ap.send(HB)
                await asyncio.sleep(0.1)
            assert link.connected
            span = time.monotonic() - t0
            # heartbeats every 0.5 s, TIMESYNC every 0.3 s, safety net every 0.25 s: a handful of
            # wake-ups, not one per 10 ms (70 in this span before)
            assert 2 <= len(runs) <= span / M.TIMER_SAFETY_NET_S + span / 0.3 + span / 0.5 + 3, runs
            assert len(ap.of_type("HEARTBEAT")) - n_hb >= 1
            assert len(ap.of_type("TIMESYNC")) - n_ts >= 2
            # the autopilot goes silent: the loss is seen on its deadline, not late by a poll period
            t_last = link.last_heartbeat_mono
            assert await _wait(lambda: not link.connected, timeout=2.0)
            assert time.monotonic() - t_last < 0.8 + 0.1
            assert link.counters["link_losses"] == 1
            ap.send(HB)                                  # recovery re-requests and re-arms at once
            assert await _wait(lambda: link.connected)
            n_ts = len(ap.of_type("TIMESYNC"))
            assert await _wait(lambda: len(ap.of_type("TIMESYNC")) > n_ts, timeout=0.2)
        finally:
            transport.close()
            await link.close()
        assert link._timer is None                       # close leaves nothing scheduled

    asyncio.run(asyncio.wait_for(main(), 15))


def test_link_timer_survives_an_exception_in_its_work():
    async def main():
        port = free_udp_port()
        link, ap, transport = await _start_pair(port, heartbeat_interval_s=0.2)
        ap.send(HB)                                      # udpin learns where to send
        assert await _wait(lambda: link.connected)
        real = link._send_next_interval
        calls = []

        def boom():
            calls.append(1)
            if len(calls) == 1:
                raise RuntimeError("a bug")
            real()
        link._send_next_interval = boom
        try:
            n = len(ap.of_type("HEARTBEAT"))
            assert await _wait(lambda: len(calls) >= 2, timeout=2.0)
            assert await _wait(lambda: len(ap.of_type("HEARTBEAT")) >= n + 2, timeout=2.0)
            assert link.counters["timer_errors"] == 1
        finally:
            transport.close()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 10))


def test_send_fixed_is_byte_for_byte_what_send_sends_and_advances_the_sequence():
    async def main():
        port = free_udp_port()
        link, ap, transport = await _start_pair(port)
        try:
            ap.send(HB)
            assert await _wait(lambda: link.connected)
            tunnel = SerialControlTunnel(link, mav.SERIAL_CONTROL_DEV_GPS1, queue_replies=False)
            frames = []
            real_write = link.conn.write
            link.conn.write = lambda b: (frames.append(bytes(b)), real_write(b))[1]
            for seq0 in (5, 255):                       # wraps at 256 as pymavlink's seq does
                link.conn.mav.seq = seq0
                tunnel.poll()                           # the cached path (no data, no baud)
                tunnel.poll()
                assert link.conn.mav.seq == (seq0 + 2) % 256
            cached = frames[:]
            frames.clear()
            for seq0 in (5, 255):                       # the same requests through pymavlink's pack
                link.conn.mav.seq = seq0
                for _ in range(2):
                    link.send(mavlink_encode.serial_control_request(mav.SERIAL_CONTROL_DEV_GPS1, b"", flags=tunnel.flags,
                                                       target_system=1, target_component=1))
            assert cached == frames and len(frames) == 4
            assert tunnel.counters["polls"] == 4 and link.counters["tx_messages"] >= 8
            # data to write goes out with the poll, through the normal path
            tunnel.write(b"\xb5\x62\x06\x04")
            tunnel.poll()
            assert tunnel.counters["tx_bytes"] == 4
            assert await _wait(lambda: any(m.count == 4 for m in ap.of_type("SERIAL_CONTROL")))
        finally:
            transport.close()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 10))


def test_tunnel_without_queue_hands_replies_to_listeners_only():
    async def main():
        port = free_udp_port()
        link, ap, transport = await _start_pair(port)
        ap.uart = bytes(range(200))
        try:
            ap.send(HB)
            assert await _wait(lambda: link.connected)
            tunnel = SerialControlTunnel(link, mav.SERIAL_CONTROL_DEV_GPS1, queue_replies=False)
            got = bytearray()
            tunnel.listeners.append(got.extend)
            poller = asyncio.create_task(tunnel.run())
            assert await _wait(lambda: len(got) >= 200)
            poller.cancel()
            assert bytes(got) == ap.uart
            with pytest.raises(RuntimeError):
                await tunnel.read(0.01)
        finally:
            transport.close()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 10))


def test_run_every_calls_on_schedule_propagates_errors_and_stops_on_cancel():
    async def main():
        calls = []
        task = asyncio.create_task(run_every(lambda: calls.append(time.monotonic()), lambda: 0.02))
        await asyncio.sleep(0.25)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        n = len(calls)
        assert 5 <= n <= 14, n
        await asyncio.sleep(0.1)
        assert len(calls) == n                         # cancelled: no timer left behind

        def bad():
            raise ValueError("step failed")
        with pytest.raises(ValueError):
            await asyncio.wait_for(run_every(bad, lambda: 0.01), 1.0)

    asyncio.run(main())


# ------------------------------------------------------------------------------------- field log
def test_field_log_one_write_per_flush_not_per_record(tmp_path):
    w = FieldLogWriter(tmp_path / "b", fsync_interval_s=0.05)
    writes = []
    real = w._os_write

    def spy(fd, data):
        writes.append(len(data))
        return real(fd, data)
    w._os_write = spy
    for i in range(300):
        w.write("mavlink", struct.pack("<I", i) + bytes(26))
        if i % 50 == 0:
            time.sleep(0.02)
    w.close()
    recs = list(read_field_log(tmp_path / "b"))
    assert [struct.unpack_from("<I", r.payload)[0] for r in recs] == list(range(300))
    assert len(writes) <= 30, len(writes)              # batches, not 300 system calls


def test_field_log_a_record_waits_at_most_the_interval(tmp_path):
    # what a power cut can lose: records younger than fsync_interval_s (plus one write + fsync)
    interval = 0.2
    w = FieldLogWriter(tmp_path / "age", fsync_interval_s=interval)
    synced_at = []
    real = w._os_fsync

    def spy(fd):
        real(fd)
        synced_at.append(time.monotonic())
    w._os_fsync = spy
    written = []
    t_end = time.monotonic() + 1.2
    while time.monotonic() < t_end:
        written.append(time.monotonic())
        w.write("mavlink", bytes(30))
        time.sleep(0.005)
    time.sleep(interval + 0.15)
    worst = 0.0
    for t in written:
        done = next((s for s in synced_at if s >= t), None)
        assert done is not None
        worst = max(worst, done - t)
    w.close()
    assert worst <= interval + 0.1, worst               # 0.1 s of scheduling slack on a loaded machine


def test_field_log_partial_batch_failure_counts_only_what_did_not_reach_the_file(tmp_path):
    w = FieldLogWriter(tmp_path / "p", background_flush=False, fsync_interval_s=10.0, retry_interval_s=0.0)
    recs = [struct.pack("<I", i) + bytes(20) for i in range(10)]
    for r in recs:
        w.write("rtcm", r)
    rec_len = len(encode_record("rtcm", recs[0], 0, 0))
    real = w._os_write
    calls = []

    def short_then_full(fd, data):
        calls.append(len(data))
        if len(calls) == 1:                            # the disk takes 3.5 records, then is full
            return real(fd, bytes(data[:int(3.5 * rec_len)]))
        raise OSError(28, "No space left on device")
    w._os_write = short_then_full
    w.flush()
    assert w.paused and w.counters["dropped_records"] == 7     # 3 whole records reached the file
    w._os_write = real
    w.close()


def test_encode_record_unchanged_format():
    import zlib
    rec = encode_record("ubx", b"\x01\x02", 7, 9)
    body = struct.pack("<IqqB", 2, 7, 9, 3) + b"ubx" + b"\x01\x02"
    assert rec == b"\xd7\x1eRC" + body + struct.pack("<I", zlib.crc32(body))
    assert encode_record("ubx", bytearray(b"\x01\x02"), 7, 9) == rec
    with pytest.raises(ValueError):
        encode_record("k" * 256, b"", 0, 0)


def test_flusher_thread_does_not_spin_while_paused_with_zero_retry(tmp_path):
    w = FieldLogWriter(tmp_path / "z", fsync_interval_s=0.05, retry_interval_s=0.0)

    def full(fd, data):
        raise OSError(28, "No space left on device")
    calls = []
    real_open = w._open_next

    def counting_open():
        calls.append(1)
        return real_open()
    w._os_write = full
    w.write("mavlink", bytes(10))
    assert _wait_sync(lambda: w.paused)
    w._open_next = counting_open
    t0 = threading.get_ident()
    time.sleep(0.3)
    w._open_next = real_open
    w.close()
    assert t0 and len(calls) <= 0.3 / 0.0125 + 5, len(calls)   # about one retry per idle period


def _wait_sync(pred, timeout=3.0):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if pred():
            return True
        time.sleep(0.01)
    return pred()


if os.name != "posix":   # pragma: no cover
    pytest.skip("loopback UDP tests", allow_module_level=True)


class _HookLink:
    def __init__(self):
        self.rx_hooks = []

    def datagram(self):
        for h in list(self.rx_hooks):
            h()


def test_run_every_rides_on_received_datagrams_and_keeps_its_rate_without_them():
    async def main():
        loop = asyncio.get_running_loop()
        link = _HookLink()
        calls = []
        from_rx = []

        def fn():
            calls.append(loop.time())
            from_rx.append(in_rx[0])
        in_rx = [False]
        task = asyncio.create_task(run_every(fn, lambda: 0.02, link=link))
        await asyncio.sleep(0)
        assert len(link.rx_hooks) == 1
        t0 = loop.time()
        while loop.time() - t0 < 1.0:               # a 200-Hz stream of datagrams
            in_rx[0] = True
            link.datagram()
            in_rx[0] = False
            await asyncio.sleep(0.005)
        n_stream = len(calls)
        share_rx = sum(from_rx) / len(from_rx)
        t1 = loop.time()
        await asyncio.sleep(0.6)                     # then a silent link: the timer keeps the rate
        n_quiet = len(calls) - n_stream
        gaps = [b - a for a, b in zip(calls, calls[1:])]
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        assert link.rx_hooks == []                   # nothing left behind
        assert 40 <= n_stream <= 52, n_stream        # 50 per second on the grid (loaded machine)
        assert share_rx > 0.7, share_rx              # mostly from datagrams: no wake-up of its own
        assert 24 <= n_quiet <= 31, n_quiet
        assert sorted(gaps)[len(gaps) // 2] == pytest.approx(0.02, abs=0.006), sorted(gaps)   # median on the grid
        assert t1 > t0

    asyncio.run(main())


def test_field_log_records_survive_an_exit_without_close(tmp_path):
    # an uncaught exception ends the interpreter without close(): the atexit hook writes the queue
    import subprocess
    import sys
    code = ("import sys; from companion.io.fieldlog import FieldLogWriter\n"
            f"w = FieldLogWriter({str(tmp_path / 'x')!r}, fsync_interval_s=30.0)\n"
            "for i in range(100): w.write('mavlink', i.to_bytes(4, 'little'))\n"
            "raise RuntimeError('crash without close')\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (os.getcwd(), os.environ.get("PYTHONPATH")) if p))
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, timeout=60)
    assert r.returncode != 0 and b"crash without close" in r.stderr
    assert [int.from_bytes(x.payload, "little") for x in read_field_log(tmp_path / "x")] == list(range(100))


def test_send_fixed_packs_every_frame_on_a_signed_link():
    async def main():
        port = free_udp_port()
        link, ap, transport = await _start_pair(port)
        try:
            sent = []
            real = link.send
            link.send = lambda msg: (sent.append(msg), real(msg))[1]
            cache = {}
            msg = mavlink_encode.serial_control_request(mav.SERIAL_CONTROL_DEV_GPS1, b"")
            link.conn.mav.signing.sign_outgoing = True      # what LinkSigning.attach turns on
            link.conn.mav.signing.secret_key = bytes(32)
            assert link.send_fixed(msg, cache) and sent == [msg] and cache == {}
            link.conn.mav.signing.sign_outgoing = False
            assert link.send_fixed(msg, cache) and sent == [msg] and len(cache) == 1
        finally:
            transport.close()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 10))
