"""GLONASS ephemerides from a u-blox capture's RXM-SFRBX strings (companion.gnss.glonass_nav):
the real F9P capture of tests/data/qzsl6tool-hiroshima-rtcm3-ubx against RTKLIB convbin's
decoding of the same bytes, field by field; the Hamming check against every single-bit error of
its real strings; and the pseudoranges of the same receiver against the decoded orbits (a wrong
day, time scale or field layout puts them kilometres off)."""
from __future__ import annotations

import dataclasses
import shutil
import struct
import subprocess

import numpy as np
import pytest
from pyubx2 import UBXMessage, UBXReader

from companion.gnss.ephemeris_store import EphemerisStore
from companion.gnss.glonass import GlonassEphemeris
from companion.gnss.glonass_nav import hamming_ok, string_bits
from companion.gnss.rinex import read_rinex_nav
from companion.gnss.rinex_obs import read_rinex_obs
from companion.gnss.rtk import RtkConfig
from companion.gnss.rtk_post import glonass_ar_of
from companion.io.ubx import UbxDecoder, decode_ubx_file
from companion.messages import GnssEpoch
from tests._data import data_path
from tests.test_glonass import _code_spread_m

pytestmark = pytest.mark.real_data

CAPTURE = data_path("qzsl6tool-hiroshima-rtcm3-ubx") / "20230919-114418.ubx"


def _glonass_strings() -> list[tuple]:
    out = []
    with open(CAPTURE, "rb") as f:
        for raw, msg in UBXReader(f, protfilter=2, quitonerror=0):
            if msg is not None and msg.identity == "RXM-SFRBX" and msg.gnssId == 6:
                p = raw[6:-2]
                out.append(struct.unpack_from(f"<{p[4]}I", p, 8))
    return out


def test_every_real_string_passes_the_hamming_check_and_no_single_bit_error_does():
    strings = _glonass_strings()
    assert len(strings) == 306
    assert all(hamming_ok(string_bits(w)) for w in strings)
    for words in strings[::25]:
        bits = string_bits(words)
        for k in range(1, 86):
            flipped = list(bits)
            flipped[k] ^= 1
            assert not hamming_ok(flipped), f"bit {k} flipped passes"


@pytest.fixture(scope="module")
def convbin(tmp_path_factory):
    if shutil.which("convbin") is None:
        pytest.skip("RTKLIB convbin not installed (apt install rtklib)")
    d = tmp_path_factory.mktemp("glo_sfrbx")
    obs, nav = d / "h.obs", d / "h.nav"
    subprocess.run(["convbin", "-r", "ubx", "-v", "3.04", "-od", "-os", "-o", str(obs), "-n", str(nav),
                    str(CAPTURE)], check=True, capture_output=True, timeout=120)
    return obs, nav


def _ours() -> dict[str, GlonassEphemeris]:
    msgs, dec = decode_ubx_file(str(CAPTURE))
    assert dec.counters.get("ephemerides_R", 0) >= 9 and dec.sfrbx.glonass.counters["hamming"] == 0
    return {m.sat: m for m in msgs if isinstance(m, GlonassEphemeris)}


def test_strings_decode_to_rtklibs_ephemerides(convbin):
    """Every GLONASS record convbin writes from the capture (9 satellites, t_b 11:45 UTC) is ours,
    to the last digit RINEX keeps: state vector, lunisolar acceleration, clock, channel, t_b."""
    _, nav = convbin
    theirs = {e.sat: e for e in read_rinex_nav(nav, "R")}
    ours = _ours()
    assert len(theirs) == 9 and set(theirs) <= set(ours)
    for sat, ref in theirs.items():
        e = ours[sat]
        assert e.t_oe_gps == ref.t_oe_gps and e.iode == ref.iode
        assert e.frequency_channel == ref.frequency_channel and e.health == ref.health
        for a, b in ((e.r_e, ref.r_e), (e.v_e, ref.v_e), (e.a_e, ref.a_e)):
            np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)
        assert e.clock_bias_s == pytest.approx(ref.clock_bias_s, rel=1e-10, abs=1e-16)
        assert e.clock_rate == pytest.approx(ref.clock_rate, rel=1e-10, abs=1e-20)


def test_pseudoranges_fit_the_decoded_orbits_as_well_as_gps(convbin):
    """The capture's own code at convbin's position of it, about each epoch's median (the clock):
    GLONASS from the decoded strings spreads as GPS does; t_b read as UTC (18 s early) does not."""
    obs, _ = convbin
    hdr, _ = read_rinex_obs(obs, "G")
    msgs, _ = decode_ubx_file(str(CAPTURE))
    epochs = [m for m in msgs if isinstance(m, GnssEpoch)]
    ephs = [m for m in msgs if hasattr(m, "sat") and m.sat[0] in "GR" and not isinstance(m, GnssEpoch)]
    spread = _code_spread_m(EphemerisStore(ephs), epochs, np.asarray(hdr["approx_position_e"], float))
    print({k: np.round(v, 2) for k, v in spread.items()})
    assert max(spread["R"]) < max(spread["G"]) + 1.0
    utc = [dataclasses.replace(e, t_oe_gps=e.t_oe_gps - 18.0) if e.sat[0] == "R" else e for e in ephs]
    assert min(_code_spread_m(EphemerisStore(utc), epochs, np.asarray(hdr["approx_position_e"], float))["R"]) > 100.0


def _mon_ver(model: str) -> bytes:
    def pad(s: str, n: int) -> bytes:
        return s.encode() + b"\0" * (n - len(s))
    payload = (pad("EXT CORE 1.00 (3fda8e)", 30) + pad("00190000", 10) + pad("FWVER=HPG 1.32", 30)
               + pad(f"MOD={model}", 30))
    return UBXMessage(0x0A, 0x04, 0, payload=payload).serialize()


def test_mon_ver_names_the_model_and_one_model_at_both_ends_fixes_glonass():
    """MON-VER's model decides GLONASS's integers as RINEX's REC # / TYPE does; a capture without
    it (the Hiroshima one) says nothing, and GLONASS stays float."""
    def model_of(raw: bytes) -> str:
        d = UbxDecoder()
        d.feed(raw)
        return d.receiver_model
    f9p, m8t = model_of(_mon_ver("ZED-F9P")), model_of(_mon_ver("NEO-M8T"))
    assert f9p == "u-blox ZED-F9P" and m8t == "u-blox NEO-M8T"
    cfg = RtkConfig(systems="GR")
    assert glonass_ar_of(cfg, {"receiver": f9p}, {"receiver": f9p})[0].glonass_ar == "on"
    assert glonass_ar_of(cfg, {"receiver": f9p}, {"receiver": m8t})[0].glonass_ar == "off"
    _, dec = decode_ubx_file(str(CAPTURE))
    assert dec.receiver_model == ""
    assert glonass_ar_of(cfg, {"receiver": ""}, {"receiver": ""})[0].glonass_ar == "off"
