"""The raw GNSS receiver of ``python -m sitl ardupilot --gnss raw`` without ArduPilot: LNAV/SFRBX
and MSM4 encoders against the companion's own decoders, the moved sky, the live truth fit, the
receiver on a synthetic SITL truth (time tags, positions) and the receiver process on real
sockets and a real pseudo-terminal."""
from __future__ import annotations

import dataclasses
import json
import math
import os
import socket
import threading
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.gnss.dgps import DgpsCorrector
from companion.gnss.ephemeris import satellite_state
from companion.gnss.ephemeris_store import EphemerisStore
from companion.gnss.spp import spp_epoch
from companion.io.rtcm import RtcmDecoder
from companion.io.ubx import UbxDecoder
from companion.messages import SECONDS_PER_WEEK, BaseStationPosition, GnssEpoch, GpsEphemeris, gps_time
from companion.nav.earth import C_n_e, ecef_to_geodetic, geodetic_to_ecef
from sitl import lnav_encode as L
from sitl import sky
from sitl.ardupilot_gnss import LiveReceiver, sitl_gps_time
from sitl.ardupilot_sky import live_scenario, reepoch, visible_count
from sitl.ardupilot_truth import Truth, home_e7
from sitl.rtcm_msm import Msm4Encoder

HOME = (-35.363261, 149.165230, 584.0)
HOME_RAD = (math.radians(HOME[0]), math.radians(HOME[1]), HOME[2])
# 2026-12-01, GPS time 29 s into a 30-s LNAV frame: subframes 1-3 (after 6 s of lock) end 7, 13, 19 s later
START_UNIX = 1_796_000_021


def _geonet(t_from_start_s: float = 0.0) -> list[GpsEphemeris]:
    t = gps_time(1316, 6 * 86400.0 + 1200.0) + t_from_start_s
    return list(sky.select_ephemerides(sky.geonet_ephemerides(), t, t + 600.0).values())


# -- LNAV subframes / SFRBX ------------------------------------------------------------------
def test_sfrbx_subframes_decode_to_the_quantised_ephemeris_with_parity_checked():
    for e in _geonet()[:6]:
        q = L.quantised(e)
        dec = UbxDecoder(week_hint=e.week)                    # parity checked (the decoder's default)
        tow = e.toe_s - 18.0
        out = []
        for sfid in (1, 2, 3):
            words = L.ephemeris_subframe(e, sfid, tow + 6.0 * sfid)
            assert (words[1] & 0x3) == 0 and (words[9] & 0x3) == 0   # t bits: D29 = D30 = 0
            out += dec.feed(L.sfrbx_frame(int(e.sat[1:]), words))
        ephs = [m for m in out if isinstance(m, GpsEphemeris)]
        assert len(ephs) == 1 and ephs[0] == q, e.sat
        assert dec.counters.get("sfrbx_parity", 0) == 0
        # at the broadcast resolution: the orbit and clock move by well under a millimetre
        for dt in (0.0, 3600.0):
            a, b = satellite_state(e, e.t_oe_gps + dt), satellite_state(q, e.t_oe_gps + dt)
            assert np.linalg.norm(a[0] - b[0]) < 1e-3 and abs(a[2] - b[2]) * 3e8 < 1e-3


def test_subframes_sent_across_a_week_boundary_carry_the_transmission_week():
    """A toe late in the week before, its subframes sent early in the next (the live sky at the
    start of a GPS week, Sunday 00:00-02:00 GPST): subframe 1's WN is the week they are sent in, as
    a satellite's is, and the ephemeris decodes to its own toe.  Before, WN was toe's week: the
    decoder placed toe a week early, 7 of 16 satellites had no ephemeris and ArduCopter SITL's
    test flight failed on those two hours of the week."""
    for e in _geonet()[:3]:
        e_prev = dataclasses.replace(e, week=e.week - 1, toe_s=SECONDS_PER_WEEK - 1200.0,
                                     toc_s=SECONDS_PER_WEEK - 1200.0)
        q = L.quantised(e_prev)
        for tow0, week_sent in ((1800.0, e.week), (SECONDS_PER_WEEK - 3600.0, e.week - 1)):
            dec = UbxDecoder(week_hint=week_sent)
            out = []
            for sfid in (1, 2, 3):
                assert L.transmission_week(e_prev, tow0 + 6.0 * sfid) == week_sent
                out += dec.feed(L.sfrbx_frame(int(e.sat[1:]), L.ephemeris_subframe(e_prev, sfid, tow0 + 6.0 * sfid)))
            ephs = [m for m in out if isinstance(m, GpsEphemeris)]
            assert len(ephs) == 1 and ephs[0].t_oe_gps == q.t_oe_gps == e_prev.t_oe_gps, (e.sat, tow0)


def test_klobuchar_page_and_the_subframe_schedule():
    alpha, beta = (1.1176e-08, 7.451e-09, -5.96e-08, -5.96e-08), (90110.0, 16380.0, -196600.0, -65540.0)
    dec = UbxDecoder(week_hint=2400)
    dec.feed(L.sfrbx_frame(7, L.klobuchar_subframe(alpha, beta, 1206.0)))
    got_a, got_b = dec.ephemerides.klobuchar
    assert got_a == pytest.approx(alpha, rel=0.02) and got_b == pytest.approx(beta, rel=0.02)
    week = 2400 * 604800.0
    # subframe 1 goes out over tow [0, 6) and is complete at tow 6; the five repeat every 30 s
    assert [L.subframe_due(week + t) for t in (6.0, 12.0, 18.0, 24.0, 30.0, 36.0)] == \
        [(1, 6.0), (2, 12.0), (3, 18.0), (4, 24.0), (5, 30.0), (1, 36.0)]
    assert L.subframe_due(week + 6.2) is None
    assert L.subframe_due(week) == (5, 0.0)                  # the week's last subframe ends at tow 0


# -- MSM4 ------------------------------------------------------------------------------------
def _base_epochs(scn, seed=0, n=40):
    from sitl.simulate import ReceiverModel, _Atmosphere
    ephs = list(scn.ephemerides)
    model = ReceiverModel(scn, seed, "base", _Atmosphere(scn, seed, [e.sat for e in ephs]), ephs)
    return [model.epoch(k) for k in range(n)]


@pytest.fixture(scope="module")
def scn():
    return live_scenario(HOME_RAD, sitl_gps_time(START_UNIX, 0.0), 120.0, 5.0)


def test_msm4_round_trip_through_the_companions_decoder_and_pyrtcm(scn):
    from io import BytesIO

    from pyrtcm import RTCMReader
    epochs = _base_epochs(scn)
    # a loss of lock on one satellite halfway: the decoder must see a new lock there
    sat = epochs[20].observations[0].sat
    epochs[20] = dataclasses.replace(epochs[20], observations=tuple(
        dataclasses.replace(o, carrier_cycles=o.carrier_cycles + 7, lock_time_s=0.0, loss_of_lock=True)
        if o.sat == sat else o for o in epochs[20].observations))
    enc = Msm4Encoder(scn.base_station_id)
    data = b"".join(enc.encode(e) for e in epochs)
    parsed = [m for _, m in RTCMReader(BytesIO(data))]
    assert [m.identity for m in parsed] == ["1074"] * len(epochs)
    assert parsed[0].NSat == len(epochs[0].observations) and parsed[0].CELLSIG_01 == "1C"
    dec = RtcmDecoder(week_hint=scn.ephemerides[0].week)
    got = [m for m in dec.feed(data) if isinstance(m, GnssEpoch)]   # one system: every message closes its epoch
    assert len(got) == len(epochs)
    prev = None
    for sent, back in zip(epochs, got):
        assert back.t_gps == pytest.approx(sent.t_gps, abs=1e-6)
        b = {o.sat: o for o in back.observations}
        assert set(b) == {o.sat for o in sent.observations}
        for o in sent.observations:
            assert abs(b[o.sat].pseudorange_m - o.pseudorange_m) <= 0.0090      # 2^-24 ms / 2
            assert b[o.sat].cn0_dbhz == round(o.cn0_dbhz)
            assert b[o.sat].loss_of_lock == (o.sat == sat and sent is epochs[20])
        if prev is not None:      # carrier differences are exact to the 0.56 mm resolution
            for o in sent.observations:
                p = prev[0].get(o.sat)
                if p is None or b[o.sat].loss_of_lock:
                    continue
                d_sent = (o.carrier_cycles - p.carrier_cycles) * o.wavelength_m
                d_back = (b[o.sat].carrier_cycles - prev[1][o.sat].carrier_cycles) * o.wavelength_m
                assert abs(d_back - d_sent) < 6e-4
        prev = ({o.sat: o for o in sent.observations}, b)


# -- the sky ---------------------------------------------------------------------------------
def test_reepoch_moves_the_constellation_rigidly_in_time_and_longitude():
    ephs = _geonet()
    shift, rot = 16.0 * 43_000_000, math.radians(33.0)
    moved = reepoch(ephs, shift, rot)
    t = ephs[0].t_oe_gps + 1234.5
    c, s = math.cos(rot), math.sin(rot)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    for a, b in zip(ephs, moved):
        ra, _, ca, _ = satellite_state(a, t)
        rb, _, cb, _ = satellite_state(b, t + shift)
        assert np.linalg.norm(R @ ra - rb) < 1e-4 and cb == pytest.approx(ca, abs=1e-15)
        assert b.toe_s % 16.0 == 0.0 and 0.0 <= b.toe_s < 604800.0
    with pytest.raises(ValueError):
        reepoch(ephs, 1.0, 0.0)


def test_live_scenario_shows_sitls_home_enough_satellites(scn):
    r = geodetic_to_ecef(*HOME_RAD)
    counts = [visible_count(scn.ephemerides, r, scn.t0_gps + t, math.radians(scn.mask_deg)) for t in (0.0, 60.0, 120.0)]
    assert min(counts) >= 7
    assert scn.lever_arm_b == (0.0, 0.0, 0.0) and scn.gnss_rate_hz == 5.0 and scn.rover_outages == ()
    base_ned = C_n_e(*HOME_RAD[:2]).T @ (scn.base_r_e - r)
    assert np.hypot(base_ned[0], base_ned[1]) == pytest.approx(3000.0, rel=1e-3)
    # the ephemerides are what LNAV carries: quantising again changes nothing
    assert all(L.quantised(e) == e for e in scn.ephemerides)


# -- SITL's clock ----------------------------------------------------------------------------
def test_sitl_gps_time_is_start_time_plus_boot_time_in_gps_seconds():
    # SIM_GPS.cpp: week/ms from (start_time_UTC + boot) - (315964800 - 18)
    assert sitl_gps_time(315964800, 0.0) == 18.0
    t = sitl_gps_time(START_UNIX, 12.5)
    assert t == START_UNIX - 315964800 + 18 + 12.5


# -- the live truth ----------------------------------------------------------------------------
class _Sitl:
    """A synthetic SITL truth: a climb and a 6 m/s leg with a turn (NED about home, SITL's own
    flat-Earth latitude/longitude), as ArduPilot sends it: ATTITUDE then SIM_STATE, 50 Hz."""

    lat_e7, lon_e7 = home_e7(HOME[0], HOME[1])

    TAU_S = 0.5          # the leg starts with up to 3 m/s^2

    @classmethod
    def ned(cls, t):
        x = (t - 2.0) / cls.TAU_S
        n = 6.0 * cls.TAU_S * (max(x, 0.0) + math.log1p(math.exp(-abs(x))))     # softplus: 0 -> 6 m/s
        return np.array([n, 1.5 * math.sin(0.4 * t), -(2.0 + 0.5 * t)])

    @classmethod
    def vel(cls, t):
        return np.array([6.0 / (1.0 + math.exp(-(t - 2.0) / cls.TAU_S)), 0.6 * math.cos(0.4 * t), -0.5])

    def messages(self, t_boot_s: float):
        from sitl.fly import LOCATION_SCALING_FACTOR_M
        n, e, d = self.ned(t_boot_s)
        lat = self.lat_e7 + n / LOCATION_SCALING_FACTOR_M
        scale = math.cos(math.radians((lat + self.lat_e7) * 0.5e-7))
        lon = self.lon_e7 + e / (LOCATION_SCALING_FACTOR_M * scale)
        ms = int(math.floor(t_boot_s * 1000.0))
        v = self.vel(t_boot_s)
        att = mav.MAVLink_attitude_message(ms, 0, 0, 0, 0, 0, 0)
        st = mav.MAVLink_sim_state_message(1, 0, 0, 0, 0, 0, 0, 0, 0, -9.8, 0, 0, 0, lat * 1e-7, lon * 1e-7,
                                           HOME[2] - d, 0, 0, v[0], v[1], v[2], int(round(lat)), int(round(lon)))
        return att, st


def test_truth_pairs_sim_state_with_attitude_and_fits_within_millimetres():
    sitl = _Sitl()
    truth = Truth(sitl.lat_e7, sitl.lon_e7, HOME[2])
    for i in range(300):
        att, st = sitl.messages(0.0025 + i * 0.02)
        if i == 100:
            truth.on_message(st)            # a SIM_STATE whose ATTITUDE was lost
            continue
        truth.on_message(att)
        truth.on_message(st)
    assert truth.counters["unpaired"] == 1 and truth.counters["paired"] == 299
    for t in (1.0, 2.55, 4.3):
        coef = truth.fit(t)
        err = Truth.ned_at(coef, 0.0) - sitl.ned(t)
        assert np.all(np.abs(err) < 3e-3), (t, err)
        assert np.allclose(coef[1], sitl.vel(t), atol=0.01)
    assert truth.fit(5.99) is None                        # not yet surrounded by samples


def test_live_receiver_time_tags_and_positions_follow_sitls_clock(scn):
    """The rover's epochs come out on SITL's GPS time: every pseudorange holds the geometric range
    from the truth at the boot time of its tag (0.1 s off would be up to 0.6 m at 6 m/s), and
    the decoded UBX and RTCM position the antenna by DGPS."""
    from sitl.sky import light_time_range
    sitl = _Sitl()
    truth = Truth(sitl.lat_e7, sitl.lon_e7, HOME[2])
    ubx, rtcm = bytearray(), bytearray()
    rx = LiveReceiver(scn, 0, truth, START_UNIX, ubx=ubx.extend, rtcm=rtcm.extend)
    for i in range(int(21.0 * 50)):
        att, st = sitl.messages(0.0025 + i * 0.02)
        truth.on_message(att)
        truth.on_message(st)
        rx.step()
    assert rx.counters["rover_epochs"] >= 100 and rx.counters["rover_epochs_without_truth"] == 0
    t0 = sitl_gps_time(START_UNIX, 0.0)
    dec = UbxDecoder(week_hint=lambda: t0)
    out = dec.feed(bytes(ubx))
    rover = [m for m in out if isinstance(m, GnssEpoch)]
    assert {m.sat for m in out if isinstance(m, GpsEphemeris)} <= {e.sat for e in scn.ephemerides}
    assert [m for m in out if isinstance(m, GpsEphemeris)], "ephemerides from SFRBX"
    rdec = RtcmDecoder(week_hint=lambda: t0)
    msgs = rdec.feed(bytes(rtcm))
    base = {round(m.t_gps, 1): m for m in msgs if isinstance(m, GnssEpoch)}
    station = next(m for m in msgs if isinstance(m, BaseStationPosition))
    assert np.allclose(station.r_e, scn.base_r_e, atol=1e-3)
    assert all(abs(e.t_gps * 5.0 - round(e.t_gps * 5.0)) < 1e-6 for e in rover)       # the 5 Hz grid
    assert len(base) == rx.counters["base_epochs"]
    ephs = {e.sat: e for e in scn.ephemerides}
    model = rx.rover
    worst = 0.0
    for ep in rover:
        k = int(round((ep.t_gps - model.T_rx[0]) * 5.0))
        r_true = truth.antenna_e(sitl.ned(ep.t_gps - t0))       # the truth at the tag's SITL boot time
        for j, sat in enumerate(model.errors()["sats"]):
            rho_used = model.errs["geometric_m"][k, j]
            if math.isfinite(rho_used):
                rho = light_time_range(ephs[sat], float(model.t_true[k]), r_true)[0]
                worst = max(worst, abs(rho - rho_used))
    assert worst < 0.01, worst
    store = EphemerisStore(list(scn.ephemerides))
    dgps = DgpsCorrector()
    errs = []
    for ep in rover:
        dgps.update_base(base[round(ep.t_gps, 1)], station, store)
        sol = spp_epoch(ep, store, dgps=dgps)
        lat, lon, _ = ecef_to_geodetic(sol.r_e)
        d = C_n_e(lat, lon).T @ (sol.r_e - truth.antenna_e(sitl.ned(ep.t_gps - t0)))
        errs.append(math.hypot(d[0], d[1]))
    assert max(errs) < 3.5 and np.sqrt(np.mean(np.square(errs))) < 1.5     # snapshot DGPS, drone antenna


# -- the process ---------------------------------------------------------------------------------
class _FakeSitlPort:
    """A TCP listener standing in for SITL's SERIAL1: sends the synthetic truth in real time once
    the receiver asked for SIM_STATE and ATTITUDE (SET_MESSAGE_INTERVAL)."""

    def __init__(self, seconds: float):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(1)
        self.port = self.sock.getsockname()[1]
        self.asked: set[int] = set()
        self.seconds = seconds
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        conn, _ = self.sock.accept()
        self.sock.close()
        conn.settimeout(0.01)
        enc, parser = mav.MAVLink(None, srcSystem=1, srcComponent=1), mav.MAVLink(None)
        sitl = _Sitl()
        t0 = time.monotonic()
        i = 0
        while time.monotonic() - t0 < self.seconds:
            try:
                for m in parser.parse_buffer(conn.recv(4096)) or []:
                    if m.get_type() == "COMMAND_LONG" and m.command == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
                        self.asked.add(int(m.param1))
            except (socket.timeout, BlockingIOError):
                pass
            except OSError:                 # the receiver stopped first (connection reset)
                break
            if {mav.MAVLINK_MSG_ID_SIM_STATE, mav.MAVLINK_MSG_ID_ATTITUDE} <= self.asked:
                att, st = sitl.messages(0.0025 + i * 0.02)
                try:
                    conn.sendall(bytes(att.pack(enc)) + bytes(st.pack(enc)))
                except OSError:             # the receiver stopped first
                    break
                i += 1
                time.sleep(max(0.0, t0 + 0.5 + i * 0.02 - time.monotonic()))
        conn.close()


def test_receiver_process_serves_ubx_on_the_pty_and_rtcm_through_the_caster(tmp_path):
    from companion.io.ntrip import build_request
    from sitl.ardupilot_procs import GnssReceiverProcess
    fake = _FakeSitlPort(seconds=5.0)
    proc = GnssReceiverProcess(tmp_path, sitl_port=fake.port, start_time_unix_s=START_UNIX, duration_s=60.0,
                               home=",".join(str(x) for x in HOME), rate_hz=5.0)
    try:
        ready = proc.start()
        caster = ready["caster"]
        fd = os.open(proc.slave_path, os.O_RDONLY | os.O_NONBLOCK)
        nt = socket.create_connection(("127.0.0.1", caster["port"]), timeout=5)
        nt.sendall(build_request(caster["mountpoint"], "127.0.0.1", caster["port"], caster["user"],
                                 caster["password"], version=1))
        nt.settimeout(0.05)
        ubx, rtcm = bytearray(), bytearray()
        t_end = time.monotonic() + 4.0
        while time.monotonic() < t_end:
            try:
                ubx += os.read(fd, 65536)
            except BlockingIOError:
                pass
            try:
                rtcm += nt.recv(65536)
            except socket.timeout:
                pass
        os.close(fd)
        nt.close()
    finally:
        code = proc.stop()
    assert code == 0, proc.tail()
    t0 = sitl_gps_time(START_UNIX, 0.0)
    rover = [m for m in UbxDecoder(week_hint=lambda: t0).feed(bytes(ubx)) if isinstance(m, GnssEpoch)]
    assert len(rover) >= 12 and len({o.sat for e in rover for o in e.observations}) >= 7
    assert rtcm.startswith(b"ICY 200 OK")
    base = [m for m in RtcmDecoder(week_hint=lambda: t0).feed(bytes(rtcm[rtcm.index(b"\xd3"):]))
            if isinstance(m, GnssEpoch)]
    assert len(base) >= 12
    result = proc.result()
    assert result["receiver"]["rover_epochs"] >= len(rover) and result["truth"]["paired"] > 150
    assert json.loads((tmp_path / "ready.json").read_text())["satellites"]
