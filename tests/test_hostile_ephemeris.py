"""Broadcast ephemerides no satellite can have: a hostile or corrupt record with a valid CRC (an
RTCM 1019 whose sqrt(A) is 0, a GLONASS state at the earth's centre) would divide by zero or leave
a function's domain at every epoch of its validity, hours of GNSS lost to one frame.  The store
refuses them (:func:`companion.gnss.ephemeris.implausible`, :func:`companion.gnss.glonass.implausible`)
and the service's health report counts them; every real record of the recordings passes."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from companion.config import config_from_dict
from companion.gnss.ephemeris_store import EphemerisStore
from companion.gnss.rinex import read_rinex_nav
from companion.io.crc24q import crc24q
from companion.io.rtcm import RtcmDecoder
from companion.messages import GnssEpoch, GpsEphemeris
from companion.pipeline import NavPipeline
from tests._data import data_path

pytestmark = pytest.mark.real_data

RTCM = data_path("qzsl6tool-hiroshima-rtcm3-ubx") / "20221213-010900.rtcm"
NAVS = [data_path("matrtklib-septentrio-static-2024") / "base.nav.gz", data_path("cssrlib-fujisawa-car-2021") / "nav.rnx.gz",
        data_path("rokubun-mosaicx5-car-2020") / "nav.rnx.gz",
        data_path("georust-rinex4-nav-kms3-2022") / "KMS300DNK_R_20221591000_01H_MN.rnx.gz"]
# 1019 payload bit offsets: IODE (DF071, 8 bits), IODC (DF085, 10 bits), sqrt(A) (DF092, 32 bits)
DF071_BIT, DF085_BIT, DF092_BIT = 48, 118, 256


def _engine_rejections(pipe) -> dict:
    return {k: v for k, v in pipe.health()["engine"].items() if k.startswith("ephemerides rejected")}


def test_every_real_record_passes():
    for nav in NAVS:
        ephs = read_rinex_nav(nav, "GRECJ")
        store = EphemerisStore(ephs)
        assert not {k for k in store.rejections if k != "duplicate"}, (nav.name, dict(store.rejections))


def _frames(data: bytes):
    i = 0
    while i + 6 <= len(data):
        if data[i] == 0xD3:
            n = ((data[i + 1] & 0x03) << 8) | data[i + 2]
            f = data[i:i + 6 + n]
            if len(f) == 6 + n and crc24q(f[:-3]) == int.from_bytes(f[-3:], "big"):
                yield f
                i += 6 + n
                continue
        i += 1


def _field(bits: int, n: int, start: int, width: int) -> int:
    return (bits >> (n - start - width)) & ((1 << width) - 1)


def _set(bits: int, n: int, start: int, width: int, value: int) -> int:
    shift = n - start - width
    return (bits & ~(((1 << width) - 1) << shift)) | ((value & ((1 << width) - 1)) << shift)


def _with_zero_sqrt_a(frame: bytes) -> bytes:
    """The same 1019 as a new issue (IODE + 1, IODC's low byte with it) with DF092 (sqrt A) = 0, and
    a valid CRC."""
    payload = frame[3:-3]
    n = len(payload) * 8
    bits = int.from_bytes(payload, "big")
    iode = (_field(bits, n, DF071_BIT, 8) + 1) & 0xFF
    bits = _set(bits, n, DF071_BIT, 8, iode)
    bits = _set(bits, n, DF085_BIT, 10, (_field(bits, n, DF085_BIT, 10) & 0x300) | iode)
    bits = _set(bits, n, DF092_BIT, 32, 0)
    head = frame[:3] + bits.to_bytes(len(payload), "big")
    return head + crc24q(head).to_bytes(3, "big")


def test_a_1019_with_a_zero_orbit_is_refused_counted_and_the_epochs_still_prepare():
    frames = list(_frames(RTCM.read_bytes()))
    k = next(i for i, f in enumerate(frames) if ((f[3] << 4) | (f[4] >> 4)) == 1019)
    hostile = _with_zero_sqrt_a(frames[k])
    dec = RtcmDecoder(week_hint=2240)
    msgs = dec.feed(b"".join(frames[:k + 1] + [hostile] + frames[k + 1:]), 0.0)
    ephs = [m for m in msgs if isinstance(m, GpsEphemeris)]
    zero = [e for e in ephs if e.sqrt_a == 0.0]
    assert len(zero) == 1                          # the decoder let it through: a new issue by its fields
    pipe = NavPipeline(config_from_dict({}))
    pipe.feed_decoded(0, [m for m in msgs if not isinstance(m, GnssEpoch)])
    counted = _engine_rejections(pipe)
    counted.pop("ephemerides rejected: duplicate", None)      # the stream repeats its issues
    assert counted == {"ephemerides rejected: implausible orbit: semi-major axis": 1}
    assert zero[0] not in pipe.engine.ephemerides.all(zero[0].sat)
    # an epoch prepares without an exception, the satellite on its real ephemeris
    from companion.gnss.prepare import prepare_epoch
    ep = [m for m in msgs if isinstance(m, GnssEpoch) and any(o.sat == zero[0].sat for o in m.observations)][-1]
    prep = prepare_epoch(ep, pipe.engine.ephemerides, np.array([-3551876.8287, 3887786.8598, 3586946.3873]),
                         systems="G")
    assert zero[0].sat in prep.sats and len(prep.sats) >= 5


def test_a_glonass_record_no_satellite_can_have_is_refused_and_counted():
    """A hostile or corrupt GLONASS ephemeris (a valid frame with a zero position would divide by a
    zero radius in the integration) never reaches the store; the service's health report counts
    it; the real ones pass."""
    real = [e for e in read_rinex_nav(NAVS[0], "R")]
    store = EphemerisStore(real)
    assert not store.rejections and len(store) == len(real)
    good = real[0]
    bad = [dataclasses.replace(good, t_oe_gps=good.t_oe_gps + 60.0 * k, **kw) for k, kw in enumerate((
        {"r_e": np.zeros(3)}, {"v_e": good.v_e * 10.0}, {"a_e": np.full(3, 1.0)}, {"clock_bias_s": float("nan")},
        {"frequency_channel": 40}), start=1)]
    pipe = NavPipeline(config_from_dict({"filter": {"systems": ["G", "R"]}}))
    for e in [good, *bad]:
        pipe.engine.process(e)
    assert pipe.engine.ephemerides.all(good.sat) == [good]
    assert _engine_rejections(pipe) == {"ephemerides rejected: implausible GLONASS state: orbit radius": 1,
                       "ephemerides rejected: implausible GLONASS state: velocity or acceleration": 2,
                       "ephemerides rejected: implausible GLONASS state: non-finite": 1,
                       "ephemerides rejected: implausible GLONASS state: frequency channel": 1}
