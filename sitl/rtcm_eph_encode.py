"""RTCM 3 broadcast ephemerides of Galileo (1046, I/NAV) and BeiDou (1042, D1/D2) from a
:class:`~companion.messages.GpsEphemeris`: what the simulated base station streams so that the
service has the orbits of every system of the sky (GPS: :func:`sitl.caster.encode_1019`).

Bit packing straight from RTCM 10403.3 (3.5.12, tables 3.5-99 and 3.5-102; pyrtcm only parses),
cross-checked by decoding the frames back with pyrtcm through
:class:`companion.io.rtcm.RtcmDecoder` (tests/test_sitl_fly_gec.py).  The inverse of
:mod:`companion.io.rtcm_eph`'s conventions: angles in semicircles of the ICD pi, ``week`` in GPS
weeks (GST week + 1024, BDT week + 1356), times of week in the system's own time, Galileo
``health`` the RINEX 3 bit field, BeiDou ``tgd_s`` / ``tgd2_s`` TGD1 / TGD2.

toe and toc must lie on their grids (Galileo 60 s, BeiDou 8 s): :mod:`sitl.sky_multignss` moves
the recorded ephemerides by a shift that keeps them there; anything else raises rather than
sending a different orbit.  A BeiDou ephemeris moved before BDT's origin (the 2005 scenarios) goes
out with its week modulo 8192, which the decoder resolves back against its current time.
"""
from __future__ import annotations


from companion.gnss.lnav import URA_M
from companion.io.rtcm_eph import PI_ICD, galileo_sisa_m
from companion.messages import SYSTEM_WEEK_TO_GPS_WEEK, GpsEphemeris

from .caster import BitWriter, _wrap_sc, encode_1019, frame


def _q(x: float, lsb: float) -> int:
    return round(x / lsb)


def _on_grid(t_s: float, step_s: float, what: str) -> int:
    k = t_s / step_s
    if abs(k - round(k)) > 1e-6:
        raise ValueError(f"{what} {t_s} s is not a multiple of {step_s:g} s: not encodable")
    return round(k)


def _sc(x_rad: float) -> float:
    """Radians -> semicircles in [-1, 1)."""
    return _wrap_sc(x_rad / PI_ICD)


def sisa_index(sisa_m: float) -> int:
    """The Galileo SISA index whose value is nearest ``sisa_m`` (255: NAPA)."""
    return min(list(range(126)) + [255], key=lambda i: abs(galileo_sisa_m(i) - sisa_m))


def ura_index(ura_m: float) -> int:
    """The URA index (GPS/BeiDou table) whose value is nearest ``ura_m``."""
    return min(range(15), key=lambda i: abs(URA_M[i] - ura_m))


def encode_1046(e: GpsEphemeris) -> bytes:
    """Galileo I/NAV ephemeris (63-byte payload); ``tgd_s`` goes out as BGD(E5b,E1), BGD(E5a,E1) 0."""
    h = int(e.health)
    w = BitWriter()
    w.u(12, 1046).u(6, int(e.sat[1:])).u(12, (e.week - SYSTEM_WEEK_TO_GPS_WEEK["E"]) % 4096)
    w.u(10, e.iode & 0x3FF).u(8, sisa_index(e.ura_m))
    w.s(14, _q(e.idot_radps / PI_ICD, 2 ** -43)).u(14, _on_grid(e.toc_s, 60.0, "toc"))
    w.s(6, _q(e.af2_sps2, 2 ** -59)).s(21, _q(e.af1_sps, 2 ** -46)).s(31, _q(e.af0_s, 2 ** -34))
    w.s(16, _q(e.crs_m, 2 ** -5)).s(16, _q(e.delta_n_radps / PI_ICD, 2 ** -43))
    w.s(32, _q(_sc(e.m0_rad), 2 ** -31)).s(16, _q(e.cuc_rad, 2 ** -29)).u(32, _q(e.e, 2 ** -33))
    w.s(16, _q(e.cus_rad, 2 ** -29)).u(32, _q(e.sqrt_a, 2 ** -19)).u(14, _on_grid(e.toe_s, 60.0, "toe"))
    w.s(16, _q(e.cic_rad, 2 ** -29)).s(32, _q(_sc(e.omega0_rad), 2 ** -31)).s(16, _q(e.cis_rad, 2 ** -29))
    w.s(32, _q(_sc(e.i0_rad), 2 ** -31)).s(16, _q(e.crc_m, 2 ** -5)).s(32, _q(_sc(e.omega_rad), 2 ** -31))
    w.s(24, _q(e.omega_dot_radps / PI_ICD, 2 ** -43))
    w.s(10, 0).s(10, _q(e.tgd_s, 2 ** -32))                       # BGD(E5a,E1), BGD(E5b,E1)
    w.u(2, (h >> 7) & 3).u(1, (h >> 6) & 1).u(2, (h >> 1) & 3).u(1, h & 1).u(2, 0)
    return frame(w.to_bytes())


def encode_1042(e: GpsEphemeris) -> bytes:
    """BeiDou D1/D2 ephemeris (64-byte payload; 511 bits and one pad bit)."""
    w = BitWriter()
    w.u(12, 1042).u(6, int(e.sat[1:])).u(13, (e.week - SYSTEM_WEEK_TO_GPS_WEEK["C"]) % 8192)
    w.u(4, ura_index(e.ura_m)).s(14, _q(e.idot_radps / PI_ICD, 2 ** -43)).u(5, e.iode & 0x1F)
    w.u(17, _on_grid(e.toc_s, 8.0, "toc")).s(11, _q(e.af2_sps2, 2 ** -66)).s(22, _q(e.af1_sps, 2 ** -50))
    w.s(24, _q(e.af0_s, 2 ** -33)).u(5, e.iodc & 0x1F).s(18, _q(e.crs_m, 2 ** -6))
    w.s(16, _q(e.delta_n_radps / PI_ICD, 2 ** -43)).s(32, _q(_sc(e.m0_rad), 2 ** -31))
    w.s(18, _q(e.cuc_rad, 2 ** -31)).u(32, _q(e.e, 2 ** -33)).s(18, _q(e.cus_rad, 2 ** -31))
    w.u(32, _q(e.sqrt_a, 2 ** -19)).u(17, _on_grid(e.toe_s, 8.0, "toe")).s(18, _q(e.cic_rad, 2 ** -31))
    w.s(32, _q(_sc(e.omega0_rad), 2 ** -31)).s(18, _q(e.cis_rad, 2 ** -31)).s(32, _q(_sc(e.i0_rad), 2 ** -31))
    w.s(18, _q(e.crc_m, 2 ** -6)).s(32, _q(_sc(e.omega_rad), 2 ** -31))
    w.s(24, _q(e.omega_dot_radps / PI_ICD, 2 ** -43))
    w.s(10, _q(e.tgd_s, 1e-10)).s(10, _q(getattr(e, "tgd2_s", 0.0), 1e-10)).u(1, int(e.health) & 1)
    return frame(w.to_bytes())


_ENCODERS = {"G": encode_1019, "E": encode_1046, "C": encode_1042}


def encode_ephemeris(e: GpsEphemeris) -> bytes | None:
    """The RTCM ephemeris frame of ``e`` (GPS 1019, Galileo 1046, BeiDou 1042); None for a system
    without an encoder here (QZSS 1044: the simulated skies have no QZSS ephemerides)."""
    enc = _ENCODERS.get(e.sat[0])
    return None if enc is None else enc(e)


__all__ = ["encode_1042", "encode_1046", "encode_ephemeris", "sisa_index", "ura_index"]
