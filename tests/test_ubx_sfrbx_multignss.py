"""GPS, QZSS, Galileo and BeiDou broadcast ephemerides from u-blox RXM-SFRBX, on the real ZED-F9P
log (Hiroshima, 2023-09-19, 35 s), against RTKLIB's ``convbin`` RINEX 3 output of the same file.

* Every field of every G, E, C (D1), J ephemeris against convbin's navigation file, and the
  satellite positions and clocks over an hour.  RTKLIB 2.4.3 b34 reads Galileo SFRBX only in the
  u-blox M8 layout of 9 words (``raw->len < 44 + off`` rejects the F9P's 8): convbin gets a copy
  of the log whose Galileo frames carry a 9th, zero word (the data words untouched); on the
  original it writes no Galileo ephemeris at all.
* Galileo: besides, the E1-B pages alone and the E5b pages alone (two independent page streams)
  give the same ephemerides, and the iono-free pseudoranges fit the position that GPS, BeiDou and
  QZSS give, up to one Galileo clock offset.
* BeiDou D2 (GEO): no GEO in this log; decoded from pages built from a real RTCM 1042 GEO
  ephemeris (a layout round trip, see ``test_beidou_d2_pages_round_trip``).
* The navigation engine fuses the systems it is configured for (``filter.systems``) and holds the
  other systems' ephemerides without using them.

Run:  python -m pytest -q -s tests/test_ubx_sfrbx_multignss.py   (prints the figures)
"""
from __future__ import annotations

import dataclasses
import math
import shutil
import subprocess
import struct

import numpy as np
import pytest

from companion.config import config_from_dict
from companion.gnss.beidou_nav import _D2, BeidouEphemerisAssembler, PREAMBLE
from companion.gnss.ephemeris import satellite_state
from companion.gnss.ephemeris_store import EphemerisStore
from companion.gnss.inav import InavEphemerisAssembler
from companion.gnss.lnav import URA_M
from companion.gnss.prepare import prepare_epoch
from companion.gnss.rinex import read_rinex_nav
from companion.gnss.spp import spp_epoch
from companion.io.ubx import decode_ubx_file, ubx_sat_id
from companion.messages import SECONDS_PER_WEEK, GnssEpoch, GpsEphemeris
from companion.pipeline import NavPipeline
from tests._data import data_path

pytestmark = [pytest.mark.real_data,
              pytest.mark.skipif(shutil.which("convbin") is None, reason="RTKLIB's convbin not installed")]
UBX = data_path("qzsl6tool-hiroshima-rtcm3-ubx") / "20230919-114418.ubx"
#: float fields: the RINEX file holds 12 significant digits
REL_TOL = 1e-11
FLOAT_FIELDS = [f.name for f in dataclasses.fields(GpsEphemeris)
                if f.type == "float" and f.name not in ("ura_m", "fit_interval_h")]


@pytest.fixture(scope="module")
def decoded():
    msgs, dec = decode_ubx_file(str(UBX))
    return msgs, dec


def _m8_galileo_layout(data: bytes) -> bytes:
    """The UBX stream with each Galileo RXM-SFRBX frame padded to the M8's 9 words (a zero word
    appended, length and checksum redone); every other byte unchanged."""
    out = bytearray()
    i = last = 0
    while (j := data.find(b"\xb5\x62", i)) >= 0 and j + 8 <= len(data):
        n = struct.unpack_from("<H", data, j + 4)[0]
        if data[j + 2:j + 4] == b"\x02\x13" and data[j + 6] == 2 and data[j + 10] == 8:
            p = bytearray(data[j + 6:j + 6 + n])
            p[4] = 9
            body = b"\x02\x13" + struct.pack("<H", n + 4) + bytes(p) + bytes(4)
            a = b = 0
            for x in body:
                a = (a + x) & 0xFF
                b = (b + a) & 0xFF
            out += data[last:j] + b"\xb5\x62" + body + bytes((a, b))
            last = j + 8 + n
        i = j + 8 + n
    return bytes(out + data[last:])


@pytest.fixture(scope="module")
def convbin_nav(tmp_path_factory):
    d = tmp_path_factory.mktemp("sfrbx")
    (d / "m8.ubx").write_bytes(_m8_galileo_layout(UBX.read_bytes()))
    navs = {}
    for name in ("f9p", "m8"):
        src = UBX if name == "f9p" else d / "m8.ubx"
        subprocess.run(["convbin", "-r", "ubx", "-od", "-os", "-o", str(d / f"{name}.obs"), "-n",
                        str(d / f"{name}.nav"), str(src)], check=True, capture_output=True)
        navs[name] = read_rinex_nav(d / f"{name}.nav")
    # the padding changes nothing but Galileo: convbin decodes it only from the M8 layout
    assert not any(e.system == "E" for e in navs["f9p"])
    assert [e for e in navs["m8"] if e.system != "E"] == navs["f9p"]
    return navs["m8"]


def _ephs(msgs):
    return [m for m in msgs if isinstance(m, GpsEphemeris)]


def _epochs(msgs):
    return [m for m in msgs if isinstance(m, GnssEpoch)]


def _ura_index_rinex(ura_m: float) -> int:
    """RTKLIB writes the nominal URA 2^(1 + N/2) (2.0, 2.8, 4.0 ... m); ours is the upper bound of
    the range (IS-GPS-200 20.3.3.3.1.3: 2.4, 3.4, 4.85 ... m), as the RTCM decoder: compare N."""
    return int(round(2.0 * (math.log2(ura_m) - 1.0)))


def test_every_system_is_decoded(decoded):
    msgs, dec = decoded
    by = {c: sorted(e.sat for e in _ephs(msgs) if e.system == c) for c in "GEJC"}
    print("\nephemerides from SFRBX:", {c: len(v) for c, v in by.items()}, by)
    assert {c: len(v) for c, v in by.items()} == {"G": 9, "E": 7, "J": 4, "C": 8}
    c = dec.counters
    assert (c["ephemerides_G"], c["ephemerides_E"], c["ephemerides_J"], c["ephemerides_C"]) == (9, 7, 4, 8)
    # every Galileo page passed its CRC, every BeiDou and LNAV word its parity
    assert dec.sfrbx.galileo.counters["crc"] == 0 and dec.sfrbx.galileo.counters["pages"] == 234
    assert dec.sfrbx.beidou.counters["parity"] == 0 and dec.sfrbx.beidou.counters["subframes"] == 78
    assert not any(k.startswith("sfrbx_") and k[6:] in ("parity", "crc", "preamble") for k in c)
    # what is not decoded is counted per system: L2C CNAV (G, J), QZSS L1S, SBAS (GLONASS's strings
    # are: tests/test_glonass_sfrbx.py)
    assert {k for k in c if k.startswith("sfrbx_not_decoded_")} == {f"sfrbx_not_decoded_{s}" for s in "GJS"}
    assert c["ephemerides_R"] >= 9
    # QZSS's Klobuchar page is kept apart from GPS's (GPS's is not in these 35 s)
    assert dec.ephemerides.klobuchar is None and dec.sfrbx.qzss.klobuchar is not None
    assert dec.sfrbx.qzss.klobuchar[0][0] == pytest.approx(0.3353e-07, rel=1e-3)
    assert dec.sfrbx.galileo.nequick is not None and dec.sfrbx.galileo.nequick[0] > 0.0


def test_every_field_and_position_matches_convbin(decoded, convbin_nav):
    msgs, _ = decoded
    ref = {(e.sat, e.toe_s): e for e in convbin_nav}
    t0 = _epochs(msgs)[0].t_gps
    worst_r = worst_clk = 0.0
    n = {}
    for e in _ephs(msgs):
        r = ref[(e.sat, e.toe_s)]
        for name in ("week", "iode", "health"):
            assert getattr(e, name) == getattr(r, name), (e.sat, name)
        # Galileo has no IODC: rinex.py reads 0, the RTCM 1046 decoder and this one give IODnav
        assert e.iodc == (e.iode if e.system == "E" else r.iodc), e.sat
        for name in FLOAT_FIELDS:
            a, b = getattr(e, name), getattr(r, name)
            assert a == pytest.approx(b, rel=REL_TOL, abs=1e-300), (e.sat, name, a, b)
        if e.system == "E":
            assert e.ura_m == r.ura_m                        # SISA
        else:
            assert URA_M.index(e.ura_m) == _ura_index_rinex(r.ura_m), e.sat
        if e.system == "J":
            assert e.fit_interval_h in (2.0, 4.0)           # QZSS flag 0 = 2 h (rinex.py: always 4 h)
        else:
            assert e.fit_interval_h == r.fit_interval_h and e.t_oe_gps == r.t_oe_gps
        for t in (t0, t0 + 35.0, e.t_oe_gps + 3600.0):
            ra, _, ca, _ = satellite_state(e, t)
            rb, _, cb, _ = satellite_state(r, t)
            worst_r = max(worst_r, float(np.linalg.norm(ra - rb)))
            worst_clk = max(worst_clk, abs(ca - cb))
        n[e.system] = n.get(e.system, 0) + 1
    print(f"\n{n} ephemerides vs convbin: worst position {worst_r * 1e3:.3f} mm, clock {worst_clk:.1e} s")
    assert n == {"G": 9, "E": 7, "C": 8, "J": 4} and worst_r < 2e-3 and worst_clk < 1e-12


def _galileo_only(path, sig_id: int):
    """Galileo ephemerides decoded from one signal's pages only (E1-B 1, E5b-I 5)."""
    data = path.read_bytes()
    asm = InavEphemerisAssembler()
    out = {}
    i = 0
    while (i := data.find(b"\xb5\x62", i)) >= 0 and i + 8 <= len(data):
        n = struct.unpack_from("<H", data, i + 4)[0]
        p = data[i + 6:i + 6 + n]
        if data[i + 2:i + 4] == b"\x02\x13" and p[0] == 2 and p[2] == sig_id:
            eph = asm.add(ubx_sat_id(2, p[1]), struct.unpack_from("<8I", p, 8))
            if eph is not None:
                out[eph.sat] = eph
        i += 8 + n
    return out


def test_galileo_e1b_and_e5b_pages_agree(decoded):
    msgs, _ = decoded
    gal = {e.sat: e for e in _ephs(msgs) if e.system == "E"}
    e1, e5 = _galileo_only(UBX, 1), _galileo_only(UBX, 5)
    both = set(e1) & set(e5)
    assert len(both) >= 4, (sorted(e1), sorted(e5))
    for s in both:
        assert e1[s] == e5[s] == gal[s], s
    for e in gal.values():
        # week: GST week 1256 + 1024; toe on the hour grid; healthy; SISA 3.12 m; clock and BGD sane
        assert e.week == 2280 and e.toe_s % 600 == 0 and abs(e.t_oe_gps - _epochs(msgs)[0].t_gps) < 4 * 3600
        assert 0.0 < e.ura_m < 10.0 and e.iode == e.iodc
        assert abs(e.af0_s) < 2e-3 and abs(e.tgd_s) < 2e-8 and e.tgd2_s == 0.0
        if e.sat == "E18":
            # launched into an eccentric orbit (2014): E1-B and E5b signal health 1 (out of service)
            assert e.health == (1 << 7) | (1 << 1) and 0.15 < e.e < 0.17
        else:
            assert e.health == 0 and 5440.0 < e.sqrt_a < 5441.0 and e.e < 0.01     # nominal MEO, 29600 km


def _reference_position(epochs, store):
    """Mean iono-free SPP of GPS, BeiDou and QZSS (no Galileo) over the log."""
    sols = [spp_epoch(ep, store, signal="IF", systems="GCJ") for ep in epochs]
    r = np.array([s.r_e for s in sols if s is not None])
    assert len(r) >= 30
    return r.mean(axis=0)


def test_galileo_pseudoranges_fit_the_position_of_the_other_systems(decoded):
    """Iono-free (E1/E5b, no group delay involved) residuals at the mean G+C+J position, each
    system's median removed (its clock): a wrong scale or sign of any orbit or clock term moves a
    satellite by metres to kilometres.  Galileo's residuals are no larger than GPS's."""
    msgs, _ = decoded
    store = EphemerisStore(_ephs(msgs))
    epochs = _epochs(msgs)
    r_ref = _reference_position(epochs, store)
    per_sat: dict[str, list[float]] = {}
    worst = {"G": 0.0, "E": 0.0}
    for ep in epochs[5:]:
        p = prepare_epoch(ep, store, r_ref, signal="IF", systems="GE")
        res = p.pseudorange_m - np.linalg.norm(p.r_sat_e - r_ref, axis=1)
        for c in worst:
            idx = [i for i, s in enumerate(p.sats) if s[0] == c and math.isfinite(res[i])]
            x = res[idx] - np.median(res[idx])
            worst[c] = max(worst[c], float(np.max(np.abs(x))))
            for i, v in zip(idx, x):
                per_sat.setdefault(p.sats[i], []).append(float(v))
    mean = {s: float(np.mean(v)) for s, v in sorted(per_sat.items())}
    print("\niono-free residual at the G+C+J position, mean per satellite [m]:",
          {s: round(v, 2) for s, v in mean.items()}, "worst single:", {c: round(v, 2) for c, v in worst.items()})
    gal = [s for s in mean if s[0] == "E"]
    assert len(gal) == 5                     # E02 has no E5b, E18 is unhealthy
    assert max(abs(mean[s]) for s in gal) <= max(abs(v) for s, v in mean.items() if s[0] == "G")
    assert worst["E"] < 5.0


def test_beidou_iono_free_fits_and_no_bds3_b2i_false_lock(decoded):
    """BeiDou B1I/B2I iono-free residuals at the G+C+J position, per satellite, within a few metres
    of the system's median.  The log holds one 'B2I' pseudorange of BDS-3 C36 (10 dB-Hz, lock 0,
    360 m off its B1I: BDS-3 broadcasts no B2I), which put C36's residual 525 m off."""
    msgs, _ = decoded
    store = EphemerisStore(_ephs(msgs))
    epochs = _epochs(msgs)
    assert any(o.sat == "C36" and o.signal == "L7I" for ep in epochs for o in ep.observations)
    r_ref = _reference_position(epochs, store)
    per_sat: dict[str, list[float]] = {}
    for ep in epochs[5:]:
        p = prepare_epoch(ep, store, r_ref, signal="IF", systems="GC")
        res = p.pseudorange_m - np.linalg.norm(p.r_sat_e - r_ref, axis=1)
        idx = [i for i, s in enumerate(p.sats) if s[0] == "C" and math.isfinite(res[i])]
        for i in idx:
            per_sat.setdefault(p.sats[i], []).append(float(res[i] - np.median(res[idx])))
    assert len(per_sat) >= 5 and "C36" not in per_sat       # C36 has B1I only
    assert max(abs(float(np.mean(v))) for v in per_sat.values()) < 3.0


def _first_times(msgs):
    """Seconds into the log (from its first RXM-RAWX) at which, ephemerides arriving as in a live
    stream: >= 4 satellites with a pseudorange and an ephemeris, and the first SPP solution."""
    t0 = None
    held: list[GpsEphemeris] = []
    out = {}
    for m in msgs:
        if isinstance(m, GpsEphemeris):
            held.append(m)
            continue
        if not isinstance(m, GnssEpoch):
            continue
        t0 = m.t_gps if t0 is None else t0
        store = EphemerisStore(held)
        have = set(store.sats)
        for systems in ("G", "GECJ"):
            sats = {o.sat for o in m.observations if o.sat in have and o.sat[0] in systems
                    and math.isfinite(o.pseudorange_m)}
            if len(sats) >= 4:
                out.setdefault(("4 sats", systems), m.t_gps - t0)
            if ("spp", systems) not in out and len(sats) >= 4:
                if spp_epoch(m, store, systems=systems) is not None:
                    out[("spp", systems)] = m.t_gps - t0
    return out


def test_all_systems_give_a_position_earlier_than_gps_alone(decoded):
    msgs, _ = decoded
    t = _first_times(msgs)
    print("\ntime into the log [s]:", {f"{k[0]} {k[1]}": v for k, v in sorted(t.items())})
    assert t[("4 sats", "GECJ")] < t[("4 sats", "G")]
    assert t[("spp", "GECJ")] <= t[("spp", "G")]


def test_an_engine_fuses_the_systems_it_is_configured_for(decoded):
    """UBX -> engine: every ephemeris lands in the engine's store under its own satellite id; a
    GPS-only engine's epoch preparation rejects the others as 'system not selected', exactly as
    without their ephemerides, and a GECJ engine prepares them all; the pipeline's usable-epoch
    test counts the satellites of the configured systems only."""
    from companion.nav.engine import EngineConfig, NavEngine
    from companion.nav.filter import ProcessNoise

    msgs, _ = decoded
    eng = NavEngine(EngineConfig(noise=ProcessNoise(5e-5, 1e-3, 1e-6, 1e-5), systems="G"))
    for e in _ephs(msgs):
        eng.process(e)
    assert set(s[0] for s in eng.ephemerides.sats) == set("GECJ") and len(eng.ephemerides) == 28
    gps_only = EphemerisStore([e for e in _ephs(msgs) if e.system == "G"])
    epochs = _epochs(msgs)
    r_ref = _reference_position(epochs, eng.ephemerides)
    ep = epochs[-1]
    a = prepare_epoch(ep, eng.ephemerides, r_ref, systems=eng.cfg.systems)
    b = prepare_epoch(ep, gps_only, r_ref)
    assert a.sats == b.sats and all(s[0] == "G" for s in a.sats) and len(a.sats) >= 4
    assert np.array_equal(a.pseudorange_m, b.pseudorange_m)
    assert {s for s, why in a.rejected.items() if why == "system not selected"} == \
        {o.sat for o in ep.observations if o.sat[0] in "RECJ"}
    every = prepare_epoch(ep, eng.ephemerides, r_ref, systems="GECJ")
    assert {s[0] for s in every.sats} == set("GECJ")
    assert EngineConfig(noise=eng.cfg.noise, systems="GECJ").bias_systems() == ("E", "C")
    # pipeline: an epoch with three GPS satellites (two signals each) and many others is usable
    # only when the others are fused
    three = sorted({o.sat for o in ep.observations if o.sat[0] == "G"})[:3]
    few = GnssEpoch(ep.t_gps, tuple(o for o in ep.observations if o.sat in three or o.sat[0] != "G"))
    pipe = NavPipeline(config_from_dict({"filter": {"systems": ["G"]}}))
    pipe.engine = eng
    assert not pipe._usable(few) and pipe._usable(ep)
    pipe_all = NavPipeline(config_from_dict({}))
    for e in _ephs(msgs):
        pipe_all.engine.process(e)
    assert pipe_all.engine.cfg.systems == "GECJ" and pipe_all._usable(few)


def _without_non_gps_sfrbx(data: bytes) -> bytes:
    out = bytearray()
    i = last = 0
    while (j := data.find(b"\xb5\x62", i)) >= 0 and j + 8 <= len(data):
        n = struct.unpack_from("<H", data, j + 4)[0]
        if data[j + 2:j + 4] == b"\x02\x13" and data[j + 6] != 0:
            out += data[last:j]
            last = j + 8 + n
        i = j + 8 + n
    return bytes(out + data[last:])


def test_pipeline_fed_the_ubx_log_uses_every_system_from_its_ephemerides():
    """The service's path (``NavPipeline.feed('ubx', ...)``, as live and in replay), fed the log
    in 4-kB chunks, with and without the non-GPS SFRBX frames: no exception, the store holds every
    system; epochs are usable as soon as four satellites of any system have ephemerides (17 s
    into the log), not when four GPS satellites have (26 s); a GPS-only configuration waits for
    GPS on either stream."""
    def run(data: bytes, systems=("G", "E", "C", "J")):
        pipe = NavPipeline(config_from_dict({"filter": {"systems": list(systems)}}))
        for k in range(0, len(data), 4096):
            pipe.feed("ubx", k, data[k:k + 4096])
        return pipe

    full = run(UBX.read_bytes())
    gps = run(_without_non_gps_sfrbx(UBX.read_bytes()))
    assert not any(k.startswith("pipeline exceptions") for k in list(full.counters) + list(gps.counters))
    # GLONASS's strings give the store 9 more (the engine uses them when [filter] systems names R)
    assert {s[0] for s in full.engine.ephemerides.sats} == set("GRECJ") and len(full.engine.ephemerides) == 28 + 9
    assert {s[0] for s in gps.engine.ephemerides.sats} == {"G"} and len(gps.engine.ephemerides) == 9
    assert full.counters["rover epochs"] == gps.counters["rover epochs"] == 36
    # the first 26 epochs have fewer than four GPS satellites with ephemerides (26 s, see above)
    assert gps.counters["rover epochs without ephemerides"] == 26
    assert full.counters["rover epochs without ephemerides"] == 17
    gps_configured = run(UBX.read_bytes(), systems=("G",))
    assert gps_configured.counters["rover epochs without ephemerides"] == 26


# ------------------------------------------------------------------------------ BeiDou D2 (GEO)
def _bch15_parity(info11: int) -> int:
    r = info11 << 4
    for i in range(14, 3, -1):
        if (r >> i) & 1:
            r ^= 0b10011 << (i - 4)
    return r & 0xF


def _d2_words(bits300: int) -> list[int]:
    """Ten u-blox words from a 300-bit subframe whose parity positions are zero: BCH filled in."""
    words = []
    for k in range(10):
        w = (bits300 >> (300 - 30 * (k + 1))) & 0x3FFFFFFF
        if k == 0:
            w = (w & ~0xF) | _bch15_parity((w >> 4) & 0x7FF)
        else:
            i1, i2 = (w >> 19) & 0x7FF, (w >> 8) & 0x7FF
            w = (i1 << 19) | (i2 << 8) | (_bch15_parity(i1) << 4) | _bch15_parity(i2)
        words.append(w)
    return words


def test_beidou_d2_pages_round_trip(tmp_path):
    """A real GEO ephemeris (C01, RTCM 1042 of the OEM729 stream via convbin) written into D2
    subframe-1 pages 1-10 at the ICD positions and decoded back: every field (scale, sign, the
    fields split across pages) and the GEO position.  Checks the decoder's arithmetic, not the
    positions themselves (no GEO D2 in the F9P log)."""
    rtcm = data_path("qzsl6tool-hiroshima-rtcm3-ubx") / "20221213-010900.rtcm"
    subprocess.run(["convbin", "-r", "rtcm3", "-tr", "2022/12/13", "01:09:00", "-o", str(tmp_path / "b.obs"),
                    "-n", str(tmp_path / "b.nav"), str(rtcm)], check=True, capture_output=True)
    ref = next(e for e in read_rinex_nav(tmp_path / "b.nav") if e.sat == "C01")
    sc = 3.1415926535898
    ints = {
        "health": ref.health, "aodc": ref.iodc, "urai": 0, "week": ref.week - 1356,
        "toc": int(ref.toc_s / 8), "tgd1": round(ref.tgd_s / 0.1e-9), "tgd2": round(ref.tgd2_s / 0.1e-9),
        "af0": round(ref.af0_s / 2.0 ** -33), "af1": round(ref.af1_sps / 2.0 ** -50), "af2": round(ref.af2_sps2 / 2.0 ** -66),
        "aode": ref.iode, "dn": round(ref.delta_n_radps / sc / 2.0 ** -43), "cuc": round(ref.cuc_rad / 2.0 ** -31),
        "m0": round(ref.m0_rad / sc / 2.0 ** -31), "cus": round(ref.cus_rad / 2.0 ** -31), "e": round(ref.e / 2.0 ** -33),
        "sqrt_a": round(ref.sqrt_a / 2.0 ** -19), "cic": round(ref.cic_rad / 2.0 ** -31), "cis": round(ref.cis_rad / 2.0 ** -31),
        "toe": int(ref.toe_s / 8), "i0": round(ref.i0_rad / sc / 2.0 ** -31), "crc": round(ref.crc_m / 2.0 ** -6),
        "crs": round(ref.crs_m / 2.0 ** -6), "omega_dot": round(ref.omega_dot_radps / sc / 2.0 ** -43),
        "omega0": round(ref.omega0_rad / sc / 2.0 ** -31), "omega": round(ref.omega_rad / sc / 2.0 ** -31),
        "idot": round(ref.idot_radps / sc / 2.0 ** -43)}
    pages = {k: 0 for k in (1, 3, 4, 5, 6, 7, 8, 9, 10)}
    for name, parts in _D2.items():
        n = sum(length for _, _, length in parts)
        x = ints[name] & ((1 << n) - 1)
        for page, start, length in parts:
            n -= length
            pages[page] |= ((x >> n) & ((1 << length) - 1)) << (300 - start - length)
    sow1 = int(ref.toe_s) + 60
    asm = BeidouEphemerisAssembler()
    eph = None
    for k, bits in pages.items():
        sow = sow1 + 3 * (k - 1)
        hdr = (PREAMBLE << 19) | (1 << 12) | ((sow >> 12) << 4)
        bits |= hdr << 270 | (sow & 0xFFF) << 258 | k << 254
        eph = asm.add("C01", _d2_words(bits)) or eph
    assert eph is not None and asm.counters["parity"] == 0
    for name in FLOAT_FIELDS:
        assert getattr(eph, name) == pytest.approx(getattr(ref, name), rel=1e-9, abs=1e-20), name
    assert (eph.week, eph.iode, eph.iodc, eph.health) == (ref.week, ref.iode, ref.iodc, ref.health)
    t = ref.t_oe_gps + 1800.0
    assert np.linalg.norm(satellite_state(eph, t)[0] - satellite_state(ref, t)[0]) < 1e-3
    assert eph.t_oe_gps % SECONDS_PER_WEEK == pytest.approx((ref.toe_s + 14.0) % SECONDS_PER_WEEK)
