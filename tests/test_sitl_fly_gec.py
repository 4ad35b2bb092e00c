"""Issue 12, multi-GNSS through the service: the simulated rover's RXM-RAWX and the simulated
base's RTCM (MSM7 1077/1097/1127, ephemerides 1019/1046/1042) for every system of the 'rtk-gec'
sky, decoded back by the companion's own decoders, and a short live flight that fixes on G+E+C."""
from __future__ import annotations

import dataclasses
import io
import math

import pytest

from companion.io.rtcm import RtcmDecoder
from companion.io.ubx import UbxDecoder


@pytest.fixture(scope="module")
def gec():
    from sitl.scenario import build_scenario
    from sitl.simulate import simulate
    scn = dataclasses.replace(build_scenario("rtk-gec"), duration_s=4.0)
    return scn, simulate(scn, 0)


def test_moved_galileo_beidou_ephemerides_round_trip_through_rtcm_1046_1042(gec):
    """The moved sky is encodable (toe/toc on their grids, node on its 2^-31-semicircle grid), so
    the frames the base sends decode to the simulator's ephemerides in every field, bit for bit."""
    from sitl.rtcm_eph_encode import encode_ephemeris
    scn, _ = gec
    ephs = [e for e in scn.ephemerides if e.sat[0] in "EC"]
    assert {e.sat[0] for e in ephs} == {"E", "C"} and any(int(e.sat[1:]) <= 5 for e in ephs if e.sat[0] == "C")
    dec = RtcmDecoder(week_hint=lambda: scn.t0_gps)
    for e in ephs:
        fr = encode_ephemeris(e)
        assert len(fr) - 6 == {"E": 63, "C": 64}[e.sat[0]]
        out = dec.feed(fr)
        assert len(out) == 1, (e.sat, dec.counters)
        for f in dataclasses.fields(e):
            assert getattr(out[0], f.name) == getattr(e, f.name), (e.sat, f.name)


def test_an_ephemeris_off_the_broadcast_time_grid_is_refused(gec):
    from sitl.rtcm_eph_encode import encode_1046
    scn, _ = gec
    e = next(x for x in scn.ephemerides if x.sat[0] == "E")
    with pytest.raises(ValueError, match="toe"):
        encode_1046(dataclasses.replace(e, toe_s=e.toe_s + 38.0))


def test_msm7_of_every_system_decodes_to_one_base_epoch(gec):
    """GPS 1077, Galileo 1097, BeiDou 1127 of one epoch, back to back with DF393: one epoch at the
    right GPS time (BeiDou's BDT undone) with every signal, code to 1 mm, Doppler to 1 mm/s, the
    time-differenced carrier to 0.2 mm, each on its own carrier wavelength."""
    from pyrtcm import RTCMReader
    from sitl.rtcm_msm import MultiMsm7Encoder
    scn, sim = gec
    enc = MultiMsm7Encoder(scn.base_station_id, "GEC")
    dec = RtcmDecoder(week_hint=lambda: scn.t0_gps)
    frames = [enc.encode(ep) for ep in sim.base_epochs[:3]]
    ids = [m.identity for _raw, m in RTCMReader(io.BytesIO(frames[0]))]
    assert ids == ["1077", "1097", "1127"]
    out = [m for fr in frames for m in dec.feed(fr)]
    assert len(out) == 3 and dec.counters.get("epoch_incomplete", 0) == 0, dec.counters
    for k in (1, 2):
        got = {(o.sat, o.signal): o for o in out[k].observations}
        prev = {(o.sat, o.signal): o for o in out[k - 1].observations}
        truth_prev = {(o.sat, o.signal): o for o in sim.base_epochs[k - 1].observations}
        assert out[k].t_gps == sim.base_epochs[k].t_gps
        for o in sim.base_epochs[k].observations:
            q = got[(o.sat, o.signal)]
            assert abs(q.pseudorange_m - o.pseudorange_m) < 1e-3
            assert abs(q.wavelength_m - o.wavelength_m) < 1e-12
            if math.isfinite(o.doppler_hz):
                assert abs((q.doppler_hz - o.doppler_hz) * o.wavelength_m) < 1e-3
            d_true = o.carrier_cycles - truth_prev[(o.sat, o.signal)].carrier_cycles
            assert abs(q.carrier_cycles - prev[(o.sat, o.signal)].carrier_cycles - d_true) * o.wavelength_m < 2e-4
    systems = {o.sat[0] for o in out[1].observations}
    assert systems == {"G", "E", "C"}


def test_gps_only_msm7_is_unchanged():
    """A GPS-only sky (the 'rtk' flight) gets exactly the 1077 it always got."""
    from sitl.rtcm_msm import Msm7Encoder, MultiMsm7Encoder
    from sitl.scenario import build_scenario
    from sitl.simulate import simulate
    scn = dataclasses.replace(build_scenario("rtk"), duration_s=3.0)
    sim = simulate(scn, 0)
    a, b = Msm7Encoder(759), MultiMsm7Encoder(759, "G")
    for ep in sim.base_epochs:
        assert a.encode(ep) == b.encode(ep)


def test_rawx_reports_every_system_with_u_blox_signal_ids(gec):
    """The emulated receiver's RXM-RAWX: GPS L1 C/A + L2C(L), Galileo E1C + E5bQ, BeiDou B1I + B3I
    (D2 sigIds on the GEOs), decoded by the companion's UBX decoder to the simulator's carriers."""
    from pyubx2 import UBXReader
    from sitl.autopilot import rawx_frame
    _, sim = gec
    ep = sim.rover_epochs[1]
    raw = rawx_frame(ep, 13)
    msg = UBXReader.parse(raw)
    sig = {(getattr(msg, f"gnssId_{i:02d}"), getattr(msg, f"svId_{i:02d}"), getattr(msg, f"sigId_{i:02d}"))
           for i in range(1, msg.numMeas + 1)}
    def is_geo(g, sv):
        return g == 3 and (sv <= 5 or sv >= 59)
    geo = [s for s in sig if is_geo(s[0], s[1])]
    assert geo and {s[2] for s in geo} == {1, 10}
    assert {(g, s) for g, sv, s in sig if not is_geo(g, sv)} == {(0, 0), (0, 3), (2, 0), (2, 6), (3, 0), (3, 4)}
    got = UbxDecoder(week_hint=lambda: ep.t_gps).feed(raw)[0]
    assert len(got.observations) == len(ep.observations)
    names = {"G": {"L1C": "L1C", "L2W": "L2L"}}
    by = {(o.sat, o.signal): o for o in got.observations}
    for o in ep.observations:
        q = by[(o.sat, names.get(o.sat[0], {}).get(o.signal, o.signal))]
        assert q.carrier_cycles == pytest.approx(o.carrier_cycles, abs=1e-6)
        assert q.wavelength_m == pytest.approx(o.wavelength_m, rel=1e-12)


def test_rtk_gec_flight_fixes_on_every_system_through_the_service(tmp_path):
    """A short live rtk-gec flight (x2): the service fixes with Galileo and BeiDou ambiguities too
    (more DD ambiguities than GPS's 7 satellites on two frequencies can give: 12), soon, right."""
    from tests._flyhelp import run_fly
    r = run_fly(tmp_path, scenario="rtk-gec", duration_s=24.0, speedup=2.0)
    assert r["companion_exit_code"] == 0
    rtk = r["rtk"]
    print(rtk)
    assert rtk["first_fix_s"] is not None and rtk["first_fix_s"] < 16.0, rtk
    assert rtk["wrong_fixes"] == 0 and rtk["rms_h_fixed_m"] < 0.03, rtk
    from sitl.fly import _fix_states_by_boot_us
    n_fixed = max(n for _st, n in _fix_states_by_boot_us(r["field_log_dir"]).values())
    assert n_fixed > 12, n_fixed


def _rawx_pyubx2(epoch, leap_seconds: int) -> bytes:
    """The reference: the RXM-RAWX sitl.autopilot built with pyubx2 1.4 before (the same keywords; pyubx2
    ignores version and the std-dev names, which it calls prStd etc., and writes 0 there)."""
    from pyubx2 import GET, UBXMessage
    from companion.messages import SECONDS_PER_WEEK
    from sitl.autopilot import RAWX_GNSS_ID, _rawx_sig_id, _rawx_sv_id
    week = int(epoch.t_gps // SECONDS_PER_WEEK)
    kw, n = {}, 0
    for o in sorted(epoch.observations, key=lambda o: "GECJ".find(o.sat[0]) % 5):
        sig = _rawx_sig_id(o.sat, o.signal)
        if sig is None:
            continue
        n += 1
        s = f"_{n:02d}"
        pr_ok, cp_ok = math.isfinite(o.pseudorange_m), math.isfinite(o.carrier_cycles)
        lock = o.lock_time_s if math.isfinite(o.lock_time_s) else 0
        kw.update({f"prMes{s}": o.pseudorange_m if pr_ok else 0.0, f"cpMes{s}": o.carrier_cycles if cp_ok else 0.0,
                   f"doMes{s}": o.doppler_hz if math.isfinite(o.doppler_hz) else 0.0,
                   f"gnssId{s}": RAWX_GNSS_ID[o.sat[0]], f"svId{s}": _rawx_sv_id(o.sat), f"sigId{s}": sig,
                   f"freqId{s}": 0, f"locktime{s}": int(min(64500, max(0, round(lock * 1000)))),
                   f"cno{s}": int(max(0, min(255, round(o.cn0_dbhz if math.isfinite(o.cn0_dbhz) else 0)))),
                   f"prStdev{s}": 5, f"cpStdev{s}": 2, f"doStdev{s}": 4, f"prValid{s}": int(pr_ok),
                   f"cpValid{s}": int(cp_ok), f"halfCyc{s}": int(cp_ok and not o.half_cycle_ambiguous),
                   f"subHalfCyc{s}": 0})
    return UBXMessage("RXM", "RXM-RAWX", GET, rcvTow=epoch.t_gps - week * SECONDS_PER_WEEK, week=week,
                      leapS=leap_seconds, numMeas=n, leapSec=1, version=1, **kw).serialize()


def test_packed_rawx_is_byte_for_byte_pyubx2s(gec):
    """The struct-packed RXM-RAWX equals pyubx2's, also with invalid code / carrier, a half-cycle
    ambiguous carrier and no Doppler."""
    from sitl.autopilot import rawx_frame
    _, sim = gec
    ep = sim.rover_epochs[2]
    obs = list(ep.observations)
    obs[0] = dataclasses.replace(obs[0], pseudorange_m=math.nan)
    obs[1] = dataclasses.replace(obs[1], carrier_cycles=math.nan, doppler_hz=math.nan)
    obs[2] = dataclasses.replace(obs[2], half_cycle_ambiguous=True, lock_time_s=100.0)
    for e in (ep, dataclasses.replace(ep, observations=tuple(obs))):
        assert rawx_frame(e, 13) == _rawx_pyubx2(e, 13)
