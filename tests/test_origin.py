"""The EKF origin read back (companion.io.origin) through the service's output path.

The service's own output code (Service._send_estimate / _maybe_send_origin) against a fake
ArduPilot on loopback UDP (tests/_fake_ardupilot.py: real pymavlink bytes; the first
SET_GPS_GLOBAL_ORIGIN is kept in whole cm, later ones ignored; GPS_GLOBAL_ORIGIN on set and on
MAV_CMD_REQUEST_MESSAGE).  Each estimate the autopilot gets is turned back into ECEF with the
origin *the autopilot has* (ArduPilot's spherical NED, sitl.fly.ned_to_ecef_ardupilot) and must
land on the position the companion meant.
"""
from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest

from companion.config import loads_config
from companion.io.origin import CONFIRM_WAIT_S, OriginE7, OriginManager
from companion.messages import NavSolution
from companion.nav.earth import C_n_e, geodetic_to_ecef
from companion.service import Service
from sitl.fly import ned_to_ecef_ardupilot
from tests._fake_ardupilot import FakeArduPilot, mav, start_pair, wait_for

LAT0, LON0, H0 = -35.3632611, 149.1652297, 584.4567
K = 0.011131884502145034          # ArduPilot LOCATION_SCALING_FACTOR, m per 1e-7 deg


def solution(k: int, t0: float = 1e9) -> NavSolution:
    """An injectable estimate 0.3 m further north-east every step."""
    lat = math.radians(LAT0) + 0.3 * k / 6378137.0
    lon = math.radians(LON0) + 0.3 * k / (6378137.0 * math.cos(math.radians(LAT0)))
    r = geodetic_to_ecef(lat, lon, H0 + 0.01 * k)
    return NavSolution(t_gps=t0 + 0.04 * k, r_e=np.asarray(r), v_e=np.zeros(3), C_b_e=C_n_e(lat, lon),
                       sigma_r_n_m=np.array([0.2, 0.2, 0.4]), sigma_v_n_mps=np.full(3, 0.1),
                       sigma_att_rad=np.full(3, 0.01), status="nav", reset_counter=1,
                       extras={"inject": True, "t_boot_us": 1_000_000 + 40_000 * k})


def origin_off(dn: float, de: float, du: float) -> tuple[int, int, int]:
    return (round(LAT0 * 1e7 + dn / K), round(LON0 * 1e7 + de / (K * math.cos(math.radians(LAT0)))),
            10 * round((H0 + du) * 100))


def landed_errors(ap, sols) -> list[float]:
    """3-D error of every VISION_POSITION_ESTIMATE in the autopilot's frame (its origin)."""
    by_t = {s.extras["t_boot_us"]: s for s in sols}
    out = []
    for _, msg in ap.of_type("VISION_POSITION_ESTIMATE"):
        r = ned_to_ecef_ardupilot((msg.x, msg.y, msg.z), *ap.origin_e7)
        out.append(float(np.linalg.norm(r - by_t[msg.usec].r_e)))
    return out


async def fly_outputs(ap, n: int = 40, dt: float = 0.04, extra_s: float = 0.0, lead_s: float = 0.3):
    """The service's output path for ``n`` estimates (25 Hz) and its 4 Hz origin tick, the first
    estimate ``lead_s`` after the link came up (in the field: seconds)."""
    svc = Service(loads_config('[output]\nmode = "vision"\n'), install_signal_handlers=False)
    link = await start_pair(ap)
    svc._subscribe(link)
    svc.link = link
    assert await wait_for(lambda: link.connected)
    svc._maybe_send_origin()
    await asyncio.sleep(lead_s)
    sols = [solution(k) for k in range(n)]
    t_tick = 0.0
    for k, s in enumerate(sols):
        if k * dt >= t_tick:
            svc._maybe_send_origin()
            t_tick += 0.25
        svc._send_estimate(s)
        await asyncio.sleep(dt)
    end = asyncio.get_running_loop().time() + extra_s
    while asyncio.get_running_loop().time() < end:
        svc._maybe_send_origin()
        await asyncio.sleep(0.25)
    await asyncio.sleep(0.1)
    return svc, link, sols


def test_ours_is_confirmed_then_no_longer_sent_and_sent_again_after_a_reboot():
    async def main():
        ap = FakeArduPilot()                      # no origin yet
        svc, link, sols = await fly_outputs(ap, n=40, extra_s=1.5)
        try:
            h = svc.health()["origin"]
            assert h["confirmed"] and h["mismatch_m"] == 0.0 and h["source"] == "autopilot"
            # ours, rounded to 1e-7 deg and whole cm, is what the autopilot keeps: no 9 mm cut
            assert ap.origin_e7 == (h["ours"]["lat_e7"], h["ours"]["lon_e7"], h["ours"]["alt_mm"])
            assert h["ours"]["alt_mm"] == 584460
            # confirmed within a round trip: one SET, never repeated in the 3 s that followed
            assert len(ap.of_type("SET_GPS_GLOBAL_ORIGIN")) == 1
            out = svc.counters
            assert out["estimates held: origin not read back"] <= 2
            assert out["sent VISION_POSITION_ESTIMATE"] >= 38
            assert max(landed_errors(ap, sols)) < 0.005
            texts = [m.text for _, m in ap.of_type("STATUSTEXT")]
            assert "CC: origin confirmed by autopilot" in texts
            # the autopilot reboots (its origin is gone): ours, unchanged, goes out again
            ap.origin_e7 = None
            svc.pipeline.counters["autopilot reboots"] += 1
            svc._maybe_send_origin()
            assert await wait_for(lambda: ap.origin_e7 is not None, 1.0)
            assert ap.origin_e7 == (h["ours"]["lat_e7"], h["ours"]["lon_e7"], h["ours"]["alt_mm"])
            assert await wait_for(lambda: svc.origin_mgr.confirmed, 1.0)
            assert svc.origin_mgr.epoch == 0          # the frame did not move
        finally:
            ap.stop()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 30))


@pytest.mark.parametrize("lead_s", [0.3, 0.0])
def test_an_origin_the_autopilot_already_had_is_adopted(lead_s):
    async def main():
        ap = FakeArduPilot(origin_e7=origin_off(8.0, -6.0, 0.5))    # e.g. set from its own GPS
        svc, link, sols = await fly_outputs(ap, n=30, lead_s=lead_s)
        try:
            h = svc.health()["origin"]
            assert h["confirmed"] and not h["refused"]
            assert abs(h["mismatch_m"] - math.sqrt(8.0 ** 2 + 6.0 ** 2 + 0.5 ** 2)) < 0.05
            assert h["used"] == {"lat_e7": ap.origin_e7[0], "lon_e7": ap.origin_e7[1], "alt_mm": ap.origin_e7[2]}
            if lead_s > 0:
                assert ap.of_type("SET_GPS_GLOBAL_ORIGIN") == []     # known before the first estimate
            else:      # the first estimate before the answer: our SET (ignored), held, then adopted
                assert len(ap.of_type("SET_GPS_GLOBAL_ORIGIN")) == 1
            errs = landed_errors(ap, sols)
            assert len(errs) >= 28 and max(errs) < 0.005
            # with our own origin they would have landed 10 m off
            msg = ap.of_type("VISION_POSITION_ESTIMATE")[0][1]
            o = h["ours"]
            r_ours = ned_to_ecef_ardupilot((msg.x, msg.y, msg.z), o["lat_e7"], o["lon_e7"], o["alt_mm"])
            assert np.linalg.norm(r_ours - sols[0].r_e) > 9.0
            texts = [m.text for _, m in ap.of_type("STATUSTEXT")]
            assert any(t.startswith("CC: AP origin 10.0") and t.endswith("adopted") for t in texts), texts
            assert svc.origin_mgr.counters["origin adopted from autopilot"] == 1
        finally:
            ap.stop()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 30))


def test_an_origin_far_away_is_refused():
    async def main():
        ap = FakeArduPilot(origin_e7=origin_off(200e3, 0.0, 0.0))
        svc, link, sols = await fly_outputs(ap, n=20)
        try:
            h = svc.health()["origin"]
            assert h["refused"] and not h["confirmed"] and h["mismatch_m"] > 190e3
            assert ap.of_type("VISION_POSITION_ESTIMATE") == []
            assert svc.counters["estimates not sent: autopilot origin too far"] == 20
            st = [m for _, m in ap.of_type("STATUSTEXT")]
            assert any(m.severity == mav.MAV_SEVERITY_ERROR and "no ext nav" in m.text for m in st)
            assert "origin refused" in svc.health_line()
        finally:
            ap.stop()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 30))


def test_an_autopilot_that_never_answers_gets_ours_after_the_wait():
    async def main():
        ap = FakeArduPilot(answer_origin=False)
        n = int((CONFIRM_WAIT_S + 0.6) / 0.04)
        svc, link, sols = await fly_outputs(ap, n=n)
        try:
            h = svc.health()["origin"]
            assert not h["confirmed"] and h["source"] == "companion (unconfirmed)"
            held = svc.counters["estimates held: origin not read back"]
            assert CONFIRM_WAIT_S / 0.04 * 0.6 < held <= CONFIRM_WAIT_S / 0.04 + 2
            assert svc.counters["estimates sent: origin unconfirmed"] >= 5
            assert max(landed_errors(ap, sols)) < 0.005       # it did take ours
            assert len(ap.of_type("SET_GPS_GLOBAL_ORIGIN")) >= 4         # repeated while unconfirmed
            assert "CC: origin not confirmed by autopilot" in [m.text for _, m in ap.of_type("STATUSTEXT")]
        finally:
            ap.stop()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 30))


def test_an_origin_that_moves_later_is_followed_as_a_reset():
    async def main():
        ap = FakeArduPilot()
        svc, link, sols = await fly_outputs(ap, n=10)
        try:
            assert svc.origin_mgr.confirmed
            # the autopilot moves its reference (PX4 re-basing, a GCS on a PX4) and says so
            ap.origin_e7 = origin_off(3.0, 4.0, 0.0)
            ap._send_origin()
            assert await wait_for(lambda: svc.origin_mgr.used == OriginE7(*ap.origin_e7), 1.0)
            more = [solution(k) for k in range(10, 20)]
            for s in more:
                svc._send_estimate(s)
                await asyncio.sleep(0.02)
            await asyncio.sleep(0.1)
            vis = [m for _, m in ap.of_type("VISION_POSITION_ESTIMATE")]
            assert {m.reset_counter for m in vis[:5]} == {1} and {m.reset_counter for m in vis[-5:]} == {2}
            assert svc.origin_mgr.epoch == 1
            new = [m for m in vis if m.reset_counter == 2]
            by_t = {s.extras["t_boot_us"]: s for s in more}
            errs = [np.linalg.norm(ned_to_ecef_ardupilot((m.x, m.y, m.z), *ap.origin_e7) - by_t[m.usec].r_e)
                    for m in new]
            assert len(errs) == 10 and max(errs) < 0.005
        finally:
            ap.stop()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 30))


def test_origin_manager_matching_and_altitude_rounding():
    from companion.io.mavlink_encode import Origin
    mgr = OriginManager()
    mgr.propose(Origin(math.radians(LAT0), math.radians(LON0), 584.4567), 0.0)
    assert mgr.ours.alt_mm == 584460 and mgr.output_origin(0.1) is None      # held for the read-back
    msgs = mgr.tick(0.1)
    assert [m.get_type() for m in msgs] == ["SET_GPS_GLOBAL_ORIGIN", "COMMAND_LONG"]
    assert msgs[0].altitude == 584460 and msgs[1].command == mav.MAV_CMD_REQUEST_MESSAGE and msgs[1].param1 == 49
    # an autopilot keeping mm (PX4) 4 mm different is still ours; 2 cm is not
    fake = mav.MAVLink_gps_global_origin_message(mgr.ours.lat_e7, mgr.ours.lon_e7, 584464, 0)
    fake._header.srcSystem = 1
    mgr.on_gps_global_origin(fake, 0.2)
    assert mgr.confirmed and mgr.counters["origin confirmed"] == 1 and mgr.mismatch_m < 0.005
    assert mgr.tick(0.3) == []                    # no SET once confirmed, next check in 10 s
    fake2 = mav.MAVLink_gps_global_origin_message(mgr.ours.lat_e7, mgr.ours.lon_e7, 584480, 0)
    fake2._header.srcSystem = 1
    mgr.on_gps_global_origin(fake2, 0.4)
    assert mgr.counters["origin adopted from autopilot"] == 1 and mgr.used.alt_mm == 584480
