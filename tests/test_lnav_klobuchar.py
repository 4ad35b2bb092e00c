"""Klobuchar coefficients from LNAV subframe 4 page 18 (IS-GPS-200 Fig. 20-1, Table 20-X), with the
real broadcast values of the GEONET navigation file's header packed into a subframe."""
from __future__ import annotations

import pytest

from companion.gnss.lnav import LnavEphemerisAssembler, decode_klobuchar, parse_subframe
from companion.gnss.rinex import read_rinex_nav_header_iono
from tests._data import data_path

pytestmark = pytest.mark.real_data

ALPHA_SCALE = (2.0 ** -30, 2.0 ** -27, 2.0 ** -24, 2.0 ** -24)
BETA_SCALE = (2.0 ** 11, 2.0 ** 14, 2.0 ** 16, 2.0 ** 16)


def _subframe4_page18(alpha, beta, sv_id: int = 56) -> list[int]:
    """Ten words, data bits 1..24 in bits 29..6 of each (parity left zero)."""
    def s8(v, scale):
        n = round(v / scale)
        # a broadcast value is an integer times the scale; RINEX prints it to 4 digits
        assert abs(n * scale - v) <= 1e-3 * abs(v) and -128 <= n <= 127
        return n & 0xFF
    a = [s8(v, k) for v, k in zip(alpha, ALPHA_SCALE)]
    b = [s8(v, k) for v, k in zip(beta, BETA_SCALE)]
    data = [0] * 10
    data[0] = 0x8B << 16                                   # TLM preamble
    data[1] = (100 << 7) | (4 << 2)                        # HOW: TOW count, subframe ID 4 in bits 20-22
    data[2] = (1 << 22) | (sv_id << 16) | (a[0] << 8) | a[1]
    data[3] = (a[2] << 16) | (a[3] << 8) | b[0]
    data[4] = (b[1] << 16) | (b[2] << 8) | b[3]
    return [d << 6 for d in data]


def test_broadcast_coefficients_round_trip():
    alpha, beta = read_rinex_nav_header_iono(data_path("rtklib-testdata-geonet-2005/rinex/07590920.05n"))
    words = _subframe4_page18(alpha, beta)
    sf = parse_subframe(words, check_parity=False)
    assert sf is not None and sf.subframe_id == 4
    got_a, got_b = decode_klobuchar(sf)
    assert got_a == pytest.approx(tuple(alpha), rel=1e-3) and got_b == pytest.approx(tuple(beta), rel=1e-3)
    assert got_a[0] == 12 * 2.0 ** -30 and got_b[2] == -3 * 2.0 ** 16     # 1.118e-08 and -196600 in the header
    asm = LnavEphemerisAssembler(check_parity=False)
    assert asm.add("G05", words, 1316) is None and asm.klobuchar == (got_a, got_b)
    assert asm.counters["klobuchar"] == 1


def test_other_pages_are_not_klobuchar():
    alpha, beta = read_rinex_nav_header_iono(data_path("rtklib-testdata-geonet-2005/rinex/07590920.05n"))
    sf = parse_subframe(_subframe4_page18(alpha, beta, sv_id=57), check_parity=False)
    assert decode_klobuchar(sf) is None
