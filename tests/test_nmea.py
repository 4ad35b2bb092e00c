"""NMEA output (issue 15): GGA/RMC/GST built for a solution parse back with pynmeagps to the same
position, and a solution the service would not inject goes out as no fix."""
from __future__ import annotations

import math
import socket

import numpy as np
import pytest

from companion.io.nmea import NmeaSink, gga_quality, nmea_sentences
from companion.messages import NavSolution
from companion.nav.earth import C_n_e, geodetic_to_ecef

pynmeagps = pytest.importorskip("pynmeagps")

LAT, LON, H = 35.160872593, 139.613836778, 69.8735


def _sol(status="nav", inject=True, v_ned=(3.0, 4.0, 0.0), **extras) -> NavSolution:
    r = geodetic_to_ecef(math.radians(LAT), math.radians(LON), H)
    v = C_n_e(math.radians(LAT), math.radians(LON)) @ np.array(v_ned)
    return NavSolution(t_gps=796435230.5, r_e=r, v_e=v, C_b_e=np.eye(3), sigma_r_n_m=np.array([0.03, 0.02, 0.05]),
                       sigma_v_n_mps=np.full(3, 0.01), sigma_att_rad=np.full(3, 0.001), status=status,
                       extras={"inject": inject, "mode": "tight", **extras})


def _parse(data: bytes):
    return pynmeagps.NMEAReader.parse(data)


def test_sentences_parse_back_to_the_solution():
    gga, rmc, gst = (_parse(b) for b in nmea_sentences(_sol(), leap_seconds=13, geoid_undulation_m=39.1,
                                                        n_sats=9, differential=True))
    assert gga.msgID == "GGA" and gga.quality == 2 and gga.numSV == 9
    # 7 decimals of a minute: below a millimetre, so an RTK position is not rounded
    assert gga.lat == pytest.approx(LAT, abs=2e-9) and gga.lon == pytest.approx(LON, abs=2e-9)
    assert gga.alt == pytest.approx(H - 39.1, abs=1e-3) and gga.sep == pytest.approx(39.1)
    assert str(gga.time) == "00:00:17.500000"                   # 796435230.5 GPS = 2005-04-02 00:00:17.5 UTC
    assert rmc.status == "A" and rmc.spd == pytest.approx(5.0 * 3600 / 1852, abs=1e-3)
    assert rmc.cog == pytest.approx(math.degrees(math.atan2(4.0, 3.0)), abs=0.01)
    assert str(rmc.date) == "2005-04-02" and rmc.posMode == "D"
    assert gst.stdLat == pytest.approx(0.03) and gst.stdLong == pytest.approx(0.02) and gst.stdAlt == pytest.approx(0.05)


@pytest.mark.parametrize("status,inject,q", [("nav", False, 0), ("diverged", True, 0), ("init", False, 0),
                                             ("coasting", True, 6), ("nav", True, 1)])
def test_what_is_not_injected_is_no_fix(status, inject, q):
    sol = _sol(status=status, inject=inject)
    assert gga_quality(sol) == q
    msgs = [_parse(b) for b in nmea_sentences(sol, leap_seconds=13)]
    gga = next(m for m in msgs if m.msgID == "GGA")
    rmc = next(m for m in msgs if m.msgID == "RMC")
    assert gga.quality == q
    if q == 0:
        assert gga.lat == "" and rmc.status == "V" and not any(m.msgID == "GST" for m in msgs)


def test_rtk_fix_states():
    assert gga_quality(_sol(rtk_fix="fixed")) == 4 and gga_quality(_sol(rtk_fix="float")) == 5
    import dataclasses
    # the filter's own RTK state (NavSolution.fix_state), as companion.nav.rtk_update sets it
    assert gga_quality(dataclasses.replace(_sol(), fix_state="fixed")) == 4
    assert gga_quality(dataclasses.replace(_sol(), fix_state="float"), differential=True) == 5
    from companion.io.gcs_values import named_values
    vals = {m.name: m.value for m in named_values(dataclasses.replace(_sol(), fix_state="fixed"), 0)}
    assert vals["CC_RTK"] == 2.0
    assert {m.name: m.value for m in named_values(_sol(), 0)}["CC_RTK"] == 0.0


def test_udp_sink_on_loopback():
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(5)
    sink = NmeaSink(f"udp:127.0.0.1:{rx.getsockname()[1]}")
    try:
        sink.send(nmea_sentences(_sol(), leap_seconds=13))
        data, _ = rx.recvfrom(4096)
    finally:
        sink.close()
        rx.close()
    lines = data.split(b"\r\n")
    assert [ln[3:6] for ln in lines if ln] == [b"GGA", b"RMC", b"GST"]
    assert sink.counters["sentences"] == 3


@pytest.mark.slow
def test_service_sends_nmea_and_named_values_in_flight(tmp_path):
    """`companion run` with [nmea] to a UDP port on loopback, in the simulated flight: GGA with a
    differential fix near the truth, at the configured 2 Hz; and NAMED_VALUE_FLOAT to the
    autopilot (for its ground station) at 1 Hz."""
    import asyncio
    import threading

    from sitl.fly import fly
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.5)
    got, stop = [], threading.Event()

    def listen():
        while not stop.is_set():
            try:
                got.append(rx.recvfrom(4096)[0])
            except OSError:
                pass

    th = threading.Thread(target=listen, daemon=True)
    th.start()
    keep = {}
    try:
        r = asyncio.run(fly(duration_s=20.0, speedup=1.0, out_dir=str(tmp_path / "fly"), keep_autopilot=keep,
                            extra_config=f'[nmea]\nenabled = true\ndestination = "udp:127.0.0.1:{rx.getsockname()[1]}"\n'
                                         'rate_hz = 2.0\n'))
    finally:
        stop.set()
        th.join(2)
        rx.close()
    assert r["companion_exit_code"] == 0
    ggas = [_parse(ln + b"\r\n") for d in got for ln in d.split(b"\r\n") if ln[3:6] == b"GGA"]
    fixed = [g for g in ggas if g.quality == 2]
    # a fix once injectable: after the initialisation and the protection level of the initial
    # covariance coming below output.max_hpl_m (~9.2 s)
    assert len(ggas) >= 2 * 20 * 0.8 and len(fixed) >= 2 * (20 - 10.5)
    sim = keep["sim"]
    from companion.nav.earth import ecef_to_geodetic
    lat, lon, _ = ecef_to_geodetic(sim.truth.r_e[0])
    g = fixed[-1]
    assert abs(g.lat - math.degrees(lat)) < 0.01 and abs(g.lon - math.degrees(lon)) < 0.01
    # the same flight: NAMED_VALUE_FLOAT for the ground station at 1 Hz, sigma_h as in the estimates
    nv = [rec.msg for rec in keep["ap"].received if rec.msg_type == "NAMED_VALUE_FLOAT"]
    names = {m.name for m in nv}
    assert {"CC_STAT", "CC_INJ", "CC_MODE", "CC_SIGH", "CC_SIGV"} <= names, names
    sigh = [m.value for m in nv if m.name == "CC_SIGH"]
    assert 20 * 0.7 <= len(sigh) <= 20 + 2 and all(0 < v < 10 for v in sigh[-5:])
    assert [m.value for m in nv if m.name == "CC_INJ"][-1] == 1.0
