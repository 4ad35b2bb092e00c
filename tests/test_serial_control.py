"""Detect, then claim: the autopilot's GPS port through SERIAL_CONTROL (companion.io.serial_control).

Against a fake ArduPilot on loopback UDP (tests/_fake_ardupilot.py: real pymavlink bytes, the
lock and GPS-driver behaviour of GCS_serial_control.cpp / AP_GPS.cpp), with a receiver that sends
NAV-PVT only (SITL's, a factory u-blox) or a real u-blox recording with RXM-RAWX/SFRBX.
"""
from __future__ import annotations

import asyncio

import numpy as np
import pytest

from companion.io.serial_control import (MIN_RAW_MEASUREMENTS, PortClaim, SerialControlTunnel, UbxFrameScanner,
                                         cfg_msg_current_port, rawx_measurements)
from companion.io.ubx import UbxDecoder, ubx_frame
from companion.messages import GnssEpoch
from tests._data import data_path
from tests._fake_ardupilot import FakeArduPilot, mav, nav_pvt, start_pair, wait_for

UBX_FILE = data_path("qzsl6tool-hiroshima-rtcm3-ubx") / "20230919-114418.ubx"
EXCL = mav.SERIAL_CONTROL_FLAG_EXCLUSIVE
RESP = mav.SERIAL_CONTROL_FLAG_RESPOND


def nav_only_receiver():
    """5 Hz NAV-PVT, no raw observations."""
    state = {"next": 0.0}

    def produce(t):
        out = b""
        while t >= state["next"]:
            out += nav_pvt(state["next"])
            state["next"] += 0.2
        return out
    return produce


def recording_receiver(data: bytes, rate_bps: float, until_s: float = float("inf")):
    """The recorded receiver's frames, each whole once its bytes would have been sent at
    ``rate_bps``, with 5 Hz NAV-PVT between them; NAV-PVT only from ``until_s`` on."""
    frames = [ubx_frame(*f) for f in UbxFrameScanner().feed(data)]
    ends = np.cumsum([len(f) for f in frames]) / rate_bps
    nav = nav_only_receiver()
    state = {"k": 0}

    def produce(t):
        out = b""
        while t < until_s and state["k"] < len(frames) and ends[state["k"]] <= t:
            out += frames[state["k"]]
            state["k"] += 1
        return out + nav(t)
    return produce


def never_a_nonexclusive_read(ap) -> bool:
    """A request that reads (RESPOND) without the lock would split the driver's byte stream."""
    return all(not (f & RESP) or (f & EXCL) for _, f in ap.requests)


# --------------------------------------------------------------------------------------------
# pure parts

@pytest.mark.real_data
def test_frame_scanner_splits_checks_and_resyncs():
    raw = UBX_FILE.read_bytes()[:40000]
    whole = UbxFrameScanner().feed(raw)
    assert len(whole) > 100 and {(c, i) for c, i, _ in whole} <= {(2, 0x13), (2, 0x15)}
    # any chunking gives the same frames; garbage before, and the frame whose class byte is
    # corrupted (checksum), are skipped, and the scanner resynchronises on the next frame
    cut = len(ubx_frame(*whole[0])) + 2
    noisy = b"$GPGGA,garbage*00\r\n\xb5" + raw[:cut] + bytes([raw[cut] ^ 0xFF]) + raw[cut + 1:]
    sc = UbxFrameScanner()
    got = []
    for i in range(0, len(noisy), 37):
        got += sc.feed(noisy[i:i + 37])
    assert sc.bad_frames >= 1
    assert got == [whole[0]] + whole[2:]
    # a length beyond the limit, a class u-blox does not have, a RAWX length that is not
    # 16 + 32 n: none is waited for, the next real frame comes out at once
    first = ubx_frame(*whole[0])
    for false_sync in (b"\xb5\x62\x02\x13\xff\x7f", b"\xb5\x62\x77\x01\x00\x10", b"\xb5\x62\x02\x15\x11\x00"):
        assert UbxFrameScanner(max_payload=4096).feed(false_sync + first) == [whole[0]]


@pytest.mark.real_data
def test_rawx_measurements_and_cfg_msg():
    rawx = [p for c, i, p in UbxFrameScanner().feed(UBX_FILE.read_bytes()[:40000]) if (c, i) == (2, 0x15)]
    assert rawx and all(rawx_measurements(p) == 70 for p in rawx)
    assert rawx_measurements(rawx[0][:-1]) is None                     # length must be 16 + 32 n
    frame = cfg_msg_current_port(0x02, 0x13, 1)
    from pyubx2 import UBXReader
    parsed = UBXReader.parse(frame)
    assert parsed.identity == "CFG-MSG" and parsed.msgClass == 2 and parsed.msgID == 0x13 and parsed.rateDDC == 1


# --------------------------------------------------------------------------------------------
# against the fake ArduPilot

def _claim(link, **kw):
    tunnel = SerialControlTunnel(link, mav.SERIAL_CONTROL_DEV_GPS1, poll_interval_s=0.02)
    kw = {"probe_s": 0.8, "release_after_s": 1.0, "retry_initial_s": 1.5, "retry_max_s": 3.0, **kw}
    return tunnel, PortClaim(tunnel, **kw)


def test_no_raw_observations_the_port_goes_back_and_the_autopilot_keeps_its_gps():
    async def main():
        ap = FakeArduPilot(nav_only_receiver())
        link = await start_pair(ap)
        tunnel, claim = _claim(link)
        runner = asyncio.create_task(claim.run())
        try:
            assert await wait_for(lambda: link.connected)
            t_up = ap.now()
            assert await wait_for(lambda: len(ap.lock_periods()) >= 3 and not ap.locked, 12.0)
            periods = ap.lock_periods()
            assert len(periods) >= 3
            # the first probe starts with the link; none holds the port longer than its window
            assert periods[0][0] - t_up < 0.3
            assert all(b - a <= 0.8 + 0.25 for a, b in periods), periods
            # back-off: 1.5 s, then 3 s (the maximum) between a release and the next probe
            gaps = [periods[i + 1][0] - periods[i][1] for i in range(len(periods) - 1)]
            assert 1.3 < gaps[0] < 1.9 and 2.8 < gaps[1] < 3.4, gaps
            assert never_a_nonexclusive_read(ap)
            assert claim.counters["claims"] == 0 and claim.counters["probes without raw"] >= 3
            assert claim.state == "released"
            # the autopilot's GPS driver was never torn down (locks < 4 s) and its fix came back
            assert ap.detections == 1 and ap.driver_timeouts == 0
            n_rel = claim.counters["releases: no raw in probe"]
            assert await wait_for(lambda: claim.counters["autopilot GPS back after release"] == n_rel, 1.0)
            assert claim.autopilot_gps_back_s < 0.8      # the next NAV-PVT the driver reads
            texts = [t for _, t in claim.drain_events()]
            assert texts == ["GPS1: no RXM-RAWX, port left to autopilot"]      # once, not per probe
            h = claim.health()
            assert h["state"] == "released" and h["next_probe_in_s"] is not None
        finally:
            runner.cancel()
            claim.close()
            ap.stop()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 30))


@pytest.mark.real_data
def test_raw_observations_claim_the_port_until_they_stop():
    raw = UBX_FILE.read_bytes()

    async def main():
        # the recording at 40 kB/s for 3 s, then the receiver sends NAV-PVT only
        ap = FakeArduPilot(recording_receiver(raw, 30_000.0, until_s=3.0))
        link = await start_pair(ap)
        tunnel, claim = _claim(link)
        got = bytearray()
        tunnel.listeners.append(got.extend)
        runner = asyncio.create_task(claim.run())
        try:
            assert await wait_for(lambda: claim.state == "claimed", 3.0)
            t_claim = ap.now()
            assert claim.counters["probes"] == 1 and claim.counters["raw epochs"] >= 1
            # SFRBX switched on through the tunnel, byte for byte
            assert await wait_for(lambda: cfg_msg_current_port(2, 0x13, 1) in bytes(ap.uart_written), 1.0)
            assert await wait_for(lambda: claim.state == "released", 6.0)
            t_rel = ap.now()
            # held continuously from the probe until raw stopped, released release_after_s later
            periods = ap.lock_periods()
            assert len(periods) == 1 and periods[0][0] < t_claim
            t_last_raw = claim.last_raw_mono - ap.t0           # the fake's clock
            assert 2.0 < t_last_raw < 3.2 and 1.0 <= t_rel - t_last_raw < 1.5, (t_last_raw, t_rel, periods)
            assert await wait_for(lambda: not ap.locked, 1.0)
            assert claim.counters["releases: raw stopped"] == 1 and never_a_nonexclusive_read(ap)
            # what came through is the receiver's raw data: real epochs, every measurement
            epochs = [x for x in UbxDecoder(week_hint=2280).feed(bytes(got)) if isinstance(x, GnssEpoch)]
            assert len(epochs) >= 3 and len(epochs[0].observations) >= MIN_RAW_MEASUREMENTS
            texts = [t for _, t in claim.drain_events()]
            assert texts[:2] == ["GPS1: raw GNSS seen, port claimed", "GPS1: raw GNSS stopped, port released"]
            # the autopilot's driver times out after a >4 s lock and detects its GPS again
            assert await wait_for(lambda: claim.autopilot_gps_back_s is not None, 3.0)
            assert ap.fix_type == 3
        finally:
            runner.cancel()
            claim.close()
            ap.stop()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 30))


@pytest.mark.real_data
def test_after_an_outage_in_flight_the_port_is_claimed_again_when_the_autopilot_gps_is_back():
    """Raw epochs stop (the sky is blocked: the receiver sends nothing at all), the port goes back to
    the autopilot; once its GPS has a new 3-D fix the receiver tracks again, so the next probe comes
    at once -- armed, where retries wait for the landing -- and finds the raw epochs."""
    raw = UBX_FILE.read_bytes()
    before, after = recording_receiver(raw, 30_000.0), recording_receiver(raw, 30_000.0)
    sky_back_s = 6.0

    def receiver(t):
        if t < 2.5:
            return before(t)
        return b"" if t < sky_back_s else after(t - sky_back_s)

    async def main():
        ap = FakeArduPilot(receiver)
        link = await start_pair(ap)
        tunnel, claim = _claim(link, retry_initial_s=30.0)
        runner = asyncio.create_task(claim.run())
        try:
            assert await wait_for(lambda: claim.state == "claimed", 3.0)
            ap.armed = True                                     # take-off
            assert await wait_for(lambda: claim.state == "released", 4.0)
            assert claim.counters["releases: raw stopped"] == 1
            assert await wait_for(lambda: claim.state == "claimed", sky_back_s + 3.0 - ap.now())
            t_claim = ap.now()
            # the autopilot's driver detected the receiver again (0.3 s), then the probe found RAWX
            assert sky_back_s < t_claim < sky_back_s + 1.5, t_claim
            assert claim.armed and claim.counters["probes on the autopilot's GPS back"] == 1
            assert claim.counters["probes"] == 2 and never_a_nonexclusive_read(ap)
        finally:
            runner.cancel()
            claim.close()
            ap.stop()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 30))


@pytest.mark.real_data
def test_no_probe_while_armed_and_close_gives_the_port_back():
    raw = UBX_FILE.read_bytes()

    async def main():
        ap = FakeArduPilot(recording_receiver(raw, 30_000.0), armed=True)
        link = await start_pair(ap)
        tunnel, claim = _claim(link)
        runner = asyncio.create_task(claim.run())
        try:
            assert await wait_for(lambda: link.connected and claim.armed)
            await asyncio.sleep(1.5)
            assert ap.requests == [] and claim.counters["probes deferred: armed"] == 1
            ap.armed = False                          # landed and disarmed: the probe comes
            assert await wait_for(lambda: claim.state == "claimed", 3.0)
            assert ap.locked
            runner.cancel()
            claim.close()                             # service shutdown
            assert await wait_for(lambda: not ap.locked, 1.0)
            assert ap.requests[-1][1] == 0            # the unlock reads nothing
        finally:
            runner.cancel()
            ap.stop()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 30))


def test_always_mode_locks_from_the_start_and_never_releases():
    async def main():
        ap = FakeArduPilot(nav_only_receiver())
        link = await start_pair(ap)
        tunnel, claim = _claim(link, mode="always")
        runner = asyncio.create_task(claim.run())
        try:
            assert await wait_for(lambda: ap.locked, 3.0)
            await asyncio.sleep(2.5)                  # > probe_s + release_after_s
            assert ap.locked and claim.state == "claimed" and len(ap.lock_periods()) == 1
        finally:
            runner.cancel()
            claim.close()
            ap.stop()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 30))


@pytest.mark.real_data
def test_a_claim_is_checked_again_after_a_link_loss():
    raw = UBX_FILE.read_bytes()

    async def main():
        ap = FakeArduPilot(recording_receiver(raw, 30_000.0))
        link = await start_pair(ap, link_timeout_s=1.2)
        tunnel, claim = _claim(link)
        runner = asyncio.create_task(claim.run())
        try:
            assert await wait_for(lambda: claim.state == "claimed", 3.0)
            ap.heartbeats_on = False
            assert await wait_for(lambda: not link.connected, 3.0)
            polls = tunnel.counters["polls"]
            await asyncio.sleep(0.3)
            assert tunnel.counters["polls"] == polls          # nothing sent into a dead link
            ap.heartbeats_on = True
            assert await wait_for(lambda: claim.counters["re-checks after link loss or reboot"] == 1, 3.0)
            assert await wait_for(lambda: claim.state == "claimed", 2.0)
            assert claim.counters["claims"] == 2 and claim.counters["releases: raw stopped"] == 0
        finally:
            runner.cancel()
            claim.close()
            ap.stop()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 30))
