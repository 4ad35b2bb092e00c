"""Paced reading of the MAVLink link (companion.io.rx_pacing, MavlinkLink.rx_pause): the reader
sleeps until shortly before the IMU sample that opens the next output slot; nothing is lost or
reordered, the hooks (the SERIAL_CONTROL poll) keep their grid, and the due time is never later
than the sample it predicts."""
from __future__ import annotations

import asyncio
import random
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

import companion.io.mavlink as M
from companion.io import mavlink_codec
from companion.io import serial_control
from companion.io.rx_pacing import OutputPacedReads
from tests.test_mavlink_io import FakeAutopilot, _wait, free_udp_port

IMU_DT_S = 0.005


def _stream(n: int, *, ratio: float = 1.0, t_rx0: float = 1000.0, t_gps0: float = 5000.0, seed: int = 1,
            late_every: int = 7):
    """(t_rx, t_gps, arrival) of a 200-Hz stream: each sample arrives 0.2-2.5 ms after its clean
    time; every ``late_every``-th run of three is read late, together (a batch: one stamp)."""
    rng = random.Random(seed)
    out = []
    for k in range(n):
        g = t_gps0 + k * IMU_DT_S
        arrival = t_rx0 + ratio * (g - t_gps0) + rng.uniform(0.0002, 0.0025)
        out.append([arrival, g, arrival])
    for k in range(0, n - 3, 3 * late_every):           # read in one go after the third arrived
        for j in range(3):
            out[k + j][0] = out[k + 2][2] + 0.0003
    return out


@pytest.mark.parametrize("ratio", [1.0, 0.5])       # live, and a simulation at 2x
def test_due_time_is_the_earliest_arrival_never_later(ratio):
    pacer = OutputPacedReads(margin_s=0.004)
    s = _stream(800, ratio=ratio)
    for t_rx, g, _ in s[:600]:
        pacer.observe(t_rx, g)
    for _, g, arrival in s[600:]:
        due = pacer.due_s(g)
        assert due is not None
        assert due <= arrival + 1e-9                # never after the sample: no added latency
        assert arrival - due < 0.003                 # and not much earlier than the jitter (2.5 ms)
    # the pause: until margin_s before the next slot's sample, capped, never negative
    t_rx, g, _ = s[599]
    slot_t = g + 0.03
    p = pacer.pause_s(t_rx, slot_t)
    assert p == pytest.approx(pacer.due_s(slot_t) - 0.004 - t_rx)
    assert 0.0 < p < ratio * 0.03
    assert pacer.pause_s(t_rx, g + 10.0) == pacer.max_pause_s
    assert pacer.pause_s(t_rx, g) == 0.0              # already due: read on arrival
    assert pacer.pause_s(t_rx, None) == 0.0           # no output slot running


def test_timing_relearned_after_a_gap_or_a_jump():
    pacer = OutputPacedReads()
    s = _stream(600)
    for t_rx, g, _ in s[:20]:
        pacer.observe(t_rx, g)
    assert pacer.due_s(s[30][1]) is None              # under a second of stream: unknown
    for t_rx, g, _ in s[20:600]:
        pacer.observe(t_rx, g)
    assert pacer.due_s(s[-1][1] + 0.02) is not None
    t_rx, g, _ = s[-1]
    pacer.observe(t_rx + 3.0, g + 3.0)                # a 3-s gap: learnt again from there
    assert pacer.due_s(g + 3.02) is None and pacer.pause_s(t_rx + 3.0, g + 3.02) == 0.0
    pacer.observe(t_rx + 3.01, g - 100.0)             # GPS time backwards (a reboot, a jump)
    assert pacer.due_s(g - 99.9) is None


def _imu(k: int):
    return mav.MAVLink_highres_imu_message(1_000_000 + 5000 * k, 0, 0, -9.8, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)


def _times_usec(n: int, first: int = 0) -> list[int]:
    return [1_000_000 + 5000 * k for k in range(first, first + n)]


def _run_paced(pause_s: float, scenario, protocol=FakeAutopilot, timeout_s: float = 20.0):
    """A real UDP link whose reader sleeps ``pause_s`` after each read, a fake autopilot on
    loopback, every received message collected: ``await scenario(link, ap, got)``; returns
    (link, ap, got)."""
    async def main():
        port = free_udp_port()
        link = M.MavlinkLink(f"udpin:127.0.0.1:{port}", timesync_interval_s=0)
        await link.start()
        loop = asyncio.get_running_loop()
        transport, ap = await loop.create_datagram_endpoint(protocol, remote_addr=("127.0.0.1", port))
        link.rx_pause = lambda: pause_s
        got: list = []
        consumer = asyncio.create_task(link.deliver_to(got.append))
        try:
            await scenario(link, ap, got)
        finally:
            transport.close()
            await link.close()
            consumer.cancel()
        return link, ap, got
    return asyncio.run(asyncio.wait_for(main(), timeout_s))


async def _stream_imu(ap, n: int, first: int = 0) -> None:
    """``n`` HIGHRES_IMU at 200 Hz, on a fixed grid."""
    t_next = time.monotonic()
    for k in range(first, first + n):
        ap.send(_imu(k))
        t_next += IMU_DT_S
        await asyncio.sleep(max(0.0, t_next - time.monotonic()))


def _imu_of(got) -> list:
    return [lm for lm in got if lm.msg.get_type() == "HIGHRES_IMU"]


def test_paused_link_delivers_everything_in_order_with_fewer_reads_and_hooks_on_their_grid():
    """The reader sleeps 60 ms after each read, a 200-Hz stream: every message arrives, in order,
    in a fraction of the reads; a hook on a 20-ms grid is still called on time while the reader
    sleeps (the SERIAL_CONTROL poll's case)."""
    n = 200
    grid = {"due": None, "late": []}

    def hook():
        now = time.monotonic()
        if grid["due"] is None:
            grid["due"] = now + 0.02
        elif now >= grid["due"]:
            grid["late"].append(now - grid["due"])
            grid["due"] += 0.02
    hook.next_due = lambda: grid["due"]

    async def scenario(link, ap, got):
        link.rx_hooks.append(hook)
        ap.send(mav.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3))
        await _stream_imu(ap, n)
        await _wait(lambda: len(_imu_of(got)) >= n, timeout=2.0)

    link, _, got = _run_paced(0.06, scenario)
    imu = _imu_of(got)
    assert [lm.msg.time_usec for lm in imu] == _times_usec(n)
    stamps = [lm.t_mono_ns for lm in imu]       # one read stamps its datagrams microseconds apart
    reads = 1 + sum(b - a > 1_000_000 for a, b in zip(stamps, stamps[1:]))
    assert link.counters["rx_pauses"] >= 5
    assert reads < n / 3, f"{reads} reads for {n} datagrams"
    late_ms = sorted(x * 1e3 for x in grid["late"])
    assert len(late_ms) >= 30
    # on time while the reader sleeps 60 ms; riding on the reads alone they would be ~30 ms late
    assert late_ms[len(late_ms) // 2] < 5.0 and late_ms[-1] < 40.0, late_ms


def test_no_pause_while_our_timesync_request_waits_for_its_reply():
    async def scenario(link, ap, got):
        link._ts_reply_by = time.monotonic() + 60.0           # a request just went out
        await _stream_imu(ap, 20)
        await _wait(lambda: len(got) >= 20, timeout=2.0)

    link, _, got = _run_paced(0.06, scenario)
    assert len(got) == 20 and link.counters["rx_pauses"] == 0


class _TimedAutopilot(FakeAutopilot):
    """The fake autopilot, noting when each SERIAL_CONTROL poll reaches it."""

    def __init__(self):
        super().__init__()
        self.poll_times: list[float] = []

    def datagram_received(self, data, addr):
        n = len(self.received)
        super().datagram_received(data, addr)
        self.poll_times += [time.monotonic() for m in self.received[n:] if m.get_type() == "SERIAL_CONTROL"]


def test_serial_control_poll_keeps_its_period_through_a_paced_reader():
    """The tunnel's 20-ms poll (the autopilot's GPS port buffers ~22 ms at 115200 baud) with the
    reader sleeping 35 ms after each read: no gap between polls much longer than the period (a
    poll due just after the reader wakes goes early, with the grid restarted there), and the poll
    rate kept."""
    period = 0.02

    async def scenario(link, ap, got):
        tunnel = serial_control.SerialControlTunnel(link, mavlink_codec.SERIAL_CONTROL_DEV_GPS1, poll_interval_s=period)
        ap.send(mav.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3))
        assert await _wait(lambda: link.connected)
        poller = asyncio.create_task(tunnel.run())
        await _stream_imu(ap, 300)                  # 1.5 s of a 200-Hz stream
        poller.cancel()

    link, ap, _ = _run_paced(0.035, scenario, protocol=_TimedAutopilot)
    times = ap.poll_times
    assert link.counters["rx_pauses"] >= 20
    gaps_ms = sorted((b - a) * 1e3 for a, b in zip(times[5:], times[6:]))
    assert len(gaps_ms) >= 50
    # riding on the reads alone the gaps would reach the 35-ms sleeps
    assert gaps_ms[len(gaps_ms) // 2] <= period * 1e3 + 3.0, gaps_ms
    assert gaps_ms[int(0.9 * len(gaps_ms))] < period * 1e3 + 10.0, gaps_ms
    span = times[-1] - times[5]
    assert len(times) - 6 >= 0.9 * span / period


def test_paused_reader_runs_a_hook_on_time_or_early_never_into_the_wait():
    """Where the paused reader's timer puts a hook: just after its due time when that is before
    the wake; HOOK_EARLY_S before the wake when it falls due in the wait for the slot's sample
    (its reply then comes with the batch); not at all when due later (the next read's hooks)."""
    resume = 100.0

    def hook_due(t, early=True):
        def hook():
            pass
        hook.next_due = lambda: t
        if early:
            hook.run_early = lambda: None
        return hook
    at = M.MavlinkLink._hook_time
    assert at(hook_due(99.9), resume) == (pytest.approx(99.9 + M.DEADLINE_SLACK_S), False)
    assert at(hook_due(resume - 0.001), resume) == (pytest.approx(resume - M.HOOK_EARLY_S), True)
    assert at(hook_due(resume + 0.005), resume) == (pytest.approx(resume - M.HOOK_EARLY_S), True)
    assert at(hook_due(resume + 0.005, early=False), resume) is None
    assert at(hook_due(resume + 0.05), resume) is None
    assert at(lambda: None, resume) is None


def test_a_burst_is_read_on_arrival_not_slept_across():
    """A read that brings more than RX_BUSY_MESSAGES (a parameter download, a flood) is not
    followed by a sleep: the socket's buffer would overflow meanwhile."""
    n = 1 + 2 * M.RX_BUSY_MESSAGES

    async def scenario(link, ap, got):
        ap.send(_imu(0))                         # read on arrival, then a 50-ms sleep
        await asyncio.sleep(0.01)
        for k in range(1, n):                    # a burst while the reader sleeps
            ap.send(_imu(k))
        await _wait(lambda: len(got) >= n, timeout=2.0)

    link, _, got = _run_paced(0.05, scenario)
    assert [lm.msg.time_usec for lm in got] == _times_usec(n)
    assert link.counters["rx_pauses"] == 1 and link.counters["rx_busy_reads"] == 1


def test_timing_relearned_after_the_clock_goes_back_a_day():
    """A reboot that puts GPS time back (or a replayed stream): the ratio is estimated again from
    the new samples, not waited for until the old time comes round."""
    pacer = OutputPacedReads()
    for t_rx, g, _ in _stream(600):
        pacer.observe(t_rx, g)
    assert pacer.due_s(5003.0 + 0.02) is not None
    for t_rx, g, _ in _stream(600, t_rx0=2000.0, t_gps0=5000.0 - 86400.0):
        pacer.observe(t_rx, g)
    due = pacer.due_s(5000.0 - 86400.0 + 3.0)
    assert due is not None and abs(due - 2003.0) < 0.003
