"""UBX decoder on the real ZED-F9P log (Hiroshima, 2023-09-19) and on frames built by pyubx2."""
from __future__ import annotations

import datetime as dt
import math
import random
from collections import Counter

import numpy as np
import pytest
from pyubx2 import GET, UBXMessage, UBXReader

from companion.gnss.ephemeris import rotate_to_reception_frame, satellite_state, transmit_time
from companion.gnss.lnav import word_parity_ok
from companion.io.ubx import UbxDecoder, decode_ubx_file
from companion.messages import (GPS_L1_WAVELENGTH_M, SECONDS_PER_WEEK, SPEED_OF_LIGHT_MPS,
                                GnssEpoch, GnssFix, GpsEphemeris)
from companion.nav.earth import ecef_to_geodetic
from tests._data import data_path

F9P = data_path("qzsl6tool-hiroshima-rtcm3-ubx/20230919-114418.ubx")
# antenna reference point of the Hiroshima base in the same folder's RTCM 1005 (different day,
# same site; checked against our own 1005 decoding in test_io_rtcm.py)
HIROSHIMA_ARP = np.array([-3551876.8287, 3887786.8598, 3586946.3873])

pytestmark = pytest.mark.real_data


@pytest.fixture(scope="module")
def f9p():
    msgs, dec = decode_ubx_file(str(F9P))
    epochs = [m for m in msgs if isinstance(m, GnssEpoch)]
    # GPS LNAV (the other systems' SFRBX ephemerides: tests/test_ubx_sfrbx_multignss.py)
    ephs = [m for m in msgs if isinstance(m, GpsEphemeris) and m.system == "G"]
    return msgs, dec, epochs, ephs


def _frames(data: bytes) -> list[bytes]:
    import io
    return [raw for raw, _ in UBXReader(io.BytesIO(data), protfilter=2, quitonerror=0)]


def test_rawx_epochs_time_and_content(f9p):
    msgs, dec, epochs, _ = f9p
    assert len(epochs) == dec.counters["rawx"] == 36
    # the first RAWX: week 2280, rcvTow 215080.992 (independently parsed by pyubx2)
    first = next(p for _, p in UBXReader(F9P.open("rb"), protfilter=2, quitonerror=0)
                 if p.identity == "RXM-RAWX")
    assert epochs[0].t_gps == pytest.approx(first.week * SECONDS_PER_WEEK + first.rcvTow, abs=1e-9)
    utc = dt.datetime(1980, 1, 6) + dt.timedelta(seconds=epochs[0].t_gps - 18)
    assert utc.date() == dt.date(2023, 9, 19) and utc.hour == 11 and 44 <= utc.minute <= 45
    assert np.allclose(np.diff([e.t_gps for e in epochs]), 1.0, atol=1e-3)
    e = epochs[0]
    systems = Counter(o.sat[0] for o in e.observations)
    assert systems["G"] >= 16 and {"R", "E", "C", "J"} <= set(systems)
    sigs = {(o.sat[0], o.signal) for o in e.observations}
    assert {("G", "L1C"), ("G", "L2L"), ("E", "L1C"), ("E", "L7Q"), ("C", "L2I"), ("C", "L7I"),
            ("R", "L1C"), ("R", "L2C"), ("J", "L1C")} <= sigs
    for o in e.observations:
        assert len(o.sat) == 3 and o.sat[1:].isdigit()
        if o.sat[0] == "R":   # GLONASS FDMA wavelength from the slot: 1602 + k*0.5625 MHz
            assert 0.1865 < o.wavelength_m < 0.2450
        elif o.signal == "L1C":
            assert o.wavelength_m == pytest.approx(GPS_L1_WAVELENGTH_M)
        if math.isfinite(o.carrier_cycles) and math.isfinite(o.pseudorange_m):
            # carrier phase in RINEX sign: phase*lambda tracks the pseudorange (same receiver clock)
            assert abs(o.carrier_cycles * o.wavelength_m - o.pseudorange_m) < 300.0


def _solve(epoch, ephs):
    """4-unknown least squares on GPS L1 C/A; returns (position, clock m, residuals, rows)."""
    rows = []
    for o in epoch.observations:
        if o.sat in ephs and o.signal == "L1C" and math.isfinite(o.pseudorange_m):
            rows.append((o, ephs[o.sat]))
    x = np.zeros(4)
    for _ in range(8):
        h, z = [], []
        for o, eph in rows:
            tt = transmit_time(epoch.t_gps, o.pseudorange_m, eph)
            r, v, b, _ = satellite_state(eph, tt)
            r, _ = rotate_to_reception_frame(r, v, epoch.t_gps - tt)
            rho = np.linalg.norm(r - x[:3])
            h.append([*((x[:3] - r) / rho), 1.0])
            z.append(o.pseudorange_m + (b - eph.tgd_s) * SPEED_OF_LIGHT_MPS - rho - x[3])
        x += np.linalg.lstsq(np.array(h), np.array(z), rcond=None)[0]
    return x[:3], x[3], np.array(z), rows


def test_ephemerides_from_sfrbx_position_the_receiver(f9p):
    _, dec, epochs, ephs = f9p
    assert dec.ephemerides.counters["parity"] == 0
    by_sat = {e.sat: e for e in ephs}
    assert len(by_sat) >= 8 and len(ephs) == len(by_sat)   # one per satellite, no repeats
    for e in ephs:
        assert e.week == 2280 and e.iode == e.iodc & 0xFF
        assert 5150 < e.sqrt_a < 5160 and 0 < e.e < 0.03 and 0.9 < e.i0_rad < 1.0
        assert abs(e.t_oe_gps - epochs[0].t_gps) < 4 * 3600
    for epoch in (epochs[0], epochs[-1]):
        pos, clock_m, resid, rows = _solve(epoch, by_sat)
        assert len(rows) >= 8
        assert np.max(np.abs(resid)) < 15.0           # unmodelled iono/tropo only
        assert np.linalg.norm(pos - HIROSHIMA_ARP) < 100.0
        lat, lon, h = ecef_to_geodetic(pos)
        assert 34.0 < math.degrees(lat) < 34.8 and 132.0 < math.degrees(lon) < 133.0
        # pseudoranges minus the common receiver clock are geometric ranges to GPS orbit
        for o, _ in rows:
            assert 2.0e7 < o.pseudorange_m - clock_m < 2.6e7


def test_doppler_has_rinex_sign(f9p):
    """Doppler*lambda must be minus the pseudorange rate, up to one common clock drift."""
    _, _, epochs, _ = f9p
    e0, e1 = epochs[10], epochs[11]
    prev = {(o.sat, o.signal): o for o in e0.observations}
    same, flipped = [], []
    for o in e1.observations:
        p = prev.get((o.sat, o.signal))
        if o.sat[0] != "G" or p is None or not (math.isfinite(o.pseudorange_m) and math.isfinite(p.pseudorange_m)):
            continue
        rate = (o.pseudorange_m - p.pseudorange_m) / (e1.t_gps - e0.t_gps)
        dop = 0.5 * (o.doppler_hz + p.doppler_hz) * o.wavelength_m
        same.append(rate + dop)
        flipped.append(rate - dop)
    assert len(same) >= 10
    assert np.ptp(same) < 5.0            # m/s: only noise once the common drift is removed
    assert np.ptp(flipped) > 500.0


def test_chunking_does_not_matter(f9p):
    msgs, _, _, _ = f9p
    data = F9P.read_bytes()
    rng = random.Random(1)
    dec = UbxDecoder()
    out, i = [], 0
    while i < len(data):
        n = rng.choice([1, 2, 7, 100, 3000])
        out.extend(dec.feed(data[i:i + n]))
        i += n
    assert [type(m) for m in out] == [type(m) for m in msgs]
    assert [m.t_gps for m in out if isinstance(m, GnssEpoch)] == [m.t_gps for m in msgs if isinstance(m, GnssEpoch)]
    assert dec.pending_bytes == 0


def test_garbage_flips_and_truncation_never_raise(f9p):
    _, ref_dec, ref_epochs, _ = f9p
    frames = _frames(F9P.read_bytes())
    rawx = [f for f in frames if f[2:4] == b"\x02\x15"]
    rng = random.Random(7)
    stream = bytearray()
    expected_ok = 0
    kinds = []
    for k, f in enumerate(rawx):
        stream += bytes(rng.randrange(256) for _ in range(rng.randrange(0, 300)))   # garbage
        mode = k % 4
        kinds.append(mode)
        if mode == 0:
            stream += f
            expected_ok += 1
        elif mode == 1:                                  # one flipped byte inside the frame
            g = bytearray(f)
            g[rng.randrange(6, len(g) - 2)] ^= 1 << rng.randrange(8)
            stream += g
        elif mode == 2:                                  # truncated frame
            stream += f[:rng.randrange(3, len(f) - 1)]
        else:                                            # sync + absurd length
            stream += b"\xb5\x62\x02\x15\xff\xff" + f[6:40]
    stream += rawx[0]                                    # a valid frame right after everything
    expected_ok += 1
    dec = UbxDecoder()
    out = []
    for i in range(0, len(stream), 997):
        out.extend(dec.feed(bytes(stream[i:i + 997])))
    epochs = [m for m in out if isinstance(m, GnssEpoch)]
    good_times = {e.t_gps for e in ref_epochs}
    assert len(epochs) == expected_ok
    assert all(e.t_gps in good_times for e in epochs)
    assert dec.counters["bad_checksum"] >= kinds.count(1)
    assert dec.counters.get("bad_length", 0) >= 1 and dec.counters["garbage_bytes"] > 1000
    # pure random garbage, including many fake sync words
    dec2 = UbxDecoder()
    junk = bytes(rng.randrange(256) for _ in range(20000)).replace(b"\x00", b"\xb5\x62")
    assert all(not isinstance(m, GnssEpoch) for m in dec2.feed(junk))
    assert sum(dec2.counters.values()) > 0


def test_rawx_flags_from_pyubx2_frame():
    msg = UBXMessage("RXM", "RXM-RAWX", GET, rcvTow=100000.5, week=2280, leapS=18, numMeas=3,
                     version=1,
                     prMes_01=2.1e7, cpMes_01=1.1e8, doMes_01=-500.0, gnssId_01=0, svId_01=5,
                     sigId_01=0, locktime_01=1000, cno_01=40, prValid_01=0, cpValid_01=1, halfCyc_01=0,
                     prMes_02=2.2e7, cpMes_02=1.2e8, doMes_02=300.0, gnssId_02=6, svId_02=7,
                     sigId_02=2, freqId_02=3, locktime_02=64500, cno_02=30, prValid_02=1,
                     cpValid_02=0, halfCyc_02=1,
                     prMes_03=3.8e7, cpMes_03=2.0e8, doMes_03=10.0, gnssId_03=1, svId_03=137,
                     sigId_03=0, locktime_03=20, cno_03=35, prValid_03=1, cpValid_03=1, halfCyc_03=1)
    frame = msg.serialize()
    dec = UbxDecoder()
    (e,) = dec.feed(frame)
    assert e.t_gps == 2280 * SECONDS_PER_WEEK + 100000.5
    g, r, s = e.observations
    assert (g.sat, g.signal) == ("G05", "L1C")
    assert math.isnan(g.pseudorange_m) and g.carrier_cycles == 1.1e8 and g.half_cycle_ambiguous
    assert g.lock_time_s == 1.0 and g.doppler_hz == -500.0 and g.cn0_dbhz == 40.0
    assert (r.sat, r.signal) == ("R07", "L2C")
    assert r.pseudorange_m == 2.2e7 and math.isnan(r.carrier_cycles) and not r.half_cycle_ambiguous
    assert r.wavelength_m == pytest.approx(SPEED_OF_LIGHT_MPS / (1246.0e6 + (3 - 7) * 0.4375e6))
    assert (s.sat, s.signal) == ("S37", "L1C") and not s.half_cycle_ambiguous
    # the same satellite/signal one second later with a shorter lock time: loss of lock
    msg2 = UBXMessage("RXM", "RXM-RAWX", GET, rcvTow=100001.5, week=2280, numMeas=1, version=1,
                      prMes_01=2.1e7, cpMes_01=1.1e8, gnssId_01=0, svId_01=5, sigId_01=0,
                      locktime_01=500, cno_01=40, prValid_01=1, cpValid_01=1, halfCyc_01=1)
    (e2,) = dec.feed(msg2.serialize())
    assert e2.observations[0].loss_of_lock
    # ... and 10 s later with a lock time of 3 s: the gap is not covered -> loss of lock too
    msg3 = UBXMessage("RXM", "RXM-RAWX", GET, rcvTow=100011.5, week=2280, numMeas=1, version=1,
                      prMes_01=2.1e7, cpMes_01=1.1e8, gnssId_01=0, svId_01=5, sigId_01=0,
                      locktime_01=3000, cno_01=40, prValid_01=1, cpValid_01=1, halfCyc_01=1)
    (e3,) = dec.feed(msg3.serialize())
    assert e3.observations[0].loss_of_lock and e3.observations[0].lock_time_s == 3.0


def test_nav_pvt_from_pyubx2_frame():
    pvt = UBXMessage("NAV", "NAV-PVT", GET, iTOW=215081000, year=2023, month=9, day=19, hour=11,
                     min=44, second=23, validDate=1, validTime=1, fixType=3, gnssFixOk=1,
                     carrSoln=2, numSV=20, lon=132.45, lat=34.39, height=50000, hAcc=20, vAcc=30,
                     velN=1000, velE=-2000, velD=500, sAcc=50)
    dec = UbxDecoder()        # no RAWX seen and no hint: the week comes from the UTC date
    (fix,) = dec.feed(pvt.serialize())
    assert isinstance(fix, GnssFix)
    assert fix.t_gps == 2280 * SECONDS_PER_WEEK + 215081.0
    lat, lon, h = ecef_to_geodetic(fix.r_e)
    assert math.degrees(lat) == pytest.approx(34.39, abs=1e-7)
    assert math.degrees(lon) == pytest.approx(132.45, abs=1e-7) and h == pytest.approx(50.0, abs=1e-3)
    from companion.nav.earth import C_n_e
    assert C_n_e(lat, lon).T @ fix.v_e == pytest.approx([1.0, -2.0, 0.5], abs=1e-9)
    assert fix.fix_type == 6 and fix.num_sats == 20
    assert (fix.sigma_h_m, fix.sigma_v_m, fix.sigma_vel_mps) == pytest.approx((0.02, 0.03, 0.05))


def test_nav_relposned_v1_and_v0_from_pyubx2_frames():
    """Dual-antenna moving baseline: NED vector (cm + 0.1 mm parts), accuracies, carrier state."""
    from companion.messages import GnssBaseline
    v1 = UBXMessage("NAV", "NAV-RELPOSNED", GET, version=1, iTOW=215081000, relPosN=-45, relPosE=87,
                    relPosD=-3, relPosLength=98, relPosHeading=117.34, _HPrelPosN=0.12, _HPrelPosE=-0.07,
                    _HPrelPosD=0.03, accN=5.2, accE=7.5, accD=14.0, accLength=7.0, accHeading=0.5,
                    gnssFixOK=1, diffSoln=1, relPosValid=1, carrSoln=2, isMoving=1, relPosHeadingValid=1)
    v0 = UBXMessage("NAV", "NAV-RELPOSNED", GET, version=0, iTOW=215082000, relPosN=100, relPosE=0,
                    relPosD=5, _HPrelPosN=-0.05, accN=25.0, accE=25.0, accD=50.0, gnssFixOK=1, relPosValid=1,
                    carrSoln=1)
    not_valid = UBXMessage("NAV", "NAV-RELPOSNED", GET, version=1, iTOW=215083000, relPosN=-45, gnssFixOK=1,
                           relPosValid=0, carrSoln=0)
    dec = UbxDecoder(week_hint=2280)
    out = dec.feed(v1.serialize() + v0.serialize() + not_valid.serialize())
    assert [type(x) for x in out] == [GnssBaseline, GnssBaseline]
    b1, b0 = out
    assert b1.t_gps == 2280 * SECONDS_PER_WEEK + 215081.0
    assert b1.rel_pos_ned_m == pytest.approx([-0.4488, 0.8693, -0.0297], abs=1e-9)
    assert b1.sigma_ned_m == pytest.approx([0.0052, 0.0075, 0.0140], abs=1e-9)
    assert b1.length_sigma_m == pytest.approx(0.0070) and b1.carrier_fixed
    # the heading the receiver reports is the azimuth of that vector
    assert math.degrees(math.atan2(b1.rel_pos_ned_m[1], b1.rel_pos_ned_m[0])) == pytest.approx(117.3, abs=0.1)
    assert b0.rel_pos_ned_m == pytest.approx([0.9995, 0.0, 0.05], abs=1e-9) and not b0.carrier_fixed
    assert math.isnan(b0.length_sigma_m)
    assert dec.counters["nav_relposned"] == 2 and dec.counters["relposned_invalid"] == 1


def test_sfrbx_parity_layout_on_real_words():
    """Every GPS L1 C/A word of the real log passes the parity check; a flipped data bit fails."""
    n = 0
    for _, p in UBXReader(F9P.open("rb"), protfilter=2, quitonerror=0):
        if p.identity == "RXM-SFRBX" and p.gnssId == 0 and p.numWords == 10 and str(p.sigId) in ("0", "L1_C/A"):
            words = [getattr(p, f"dwrd_{i:02d}") for i in range(1, 11)]
            assert all(word_parity_ok(w) for w in words)
            assert not word_parity_ok(words[3] ^ (1 << 17))
            n += 1
    assert n >= 50
