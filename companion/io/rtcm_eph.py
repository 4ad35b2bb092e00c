"""RTCM 3 broadcast ephemerides -> :class:`~companion.messages.GpsEphemeris` (GPS 1019, QZSS 1044,
Galileo F/NAV 1045 and I/NAV 1046, BeiDou 1042) and :class:`~companion.gnss.glonass.GlonassEphemeris` (1020).

pyrtcm extracts the fields already scaled by the RTCM 10403.3 resolutions: seconds, metres,
radians for the harmonic corrections, but **semicircles** (and semicircles/s) for the angles and
angle rates, as the messages carry them; these functions multiply by the ICDs' pi (every ICD
prescribes 3.1415926535898).  Exceptions pyrtcm leaves unscaled: BeiDou TGD1/TGD2 (DF513/514) come
in ns, GLONASS gamma_n, tau_n, delta tau_n (DF121, DF124, DF125) as integers (sign-magnitude
already undone).  Every value here was checked
field by field against RTKLIB's ``convbin`` RINEX 3 output of the same frames (tests/test_rtcm_eph.py).

Conventions are those of :class:`~companion.messages.GpsEphemeris`: times of week in the
satellite's own system time (BDT for BeiDou), ``week`` in GPS weeks (GST week + 1024, BDT week +
1356), the week being the one of toe resolved against the decoder's current time;
``iode``: GPS/QZSS IODE, Galileo IODnav, BeiDou AODE (``iodc``: BeiDou AODC).
"""
from __future__ import annotations

import numpy as np

from ..gnss.glonass import GlonassEphemeris, t_b_gps
from ..gnss.lnav import URA_M, fit_interval_h, resolve_week
from ..messages import SECONDS_PER_WEEK, SYSTEM_TO_GPS_S, SYSTEM_WEEK_TO_GPS_WEEK, GpsEphemeris

PI_ICD = 3.1415926535898
#: fit interval (h, whole interval around toe) for systems that broadcast none: RTKLIB's
#: MAXDTOE_GAL / MAXDTOE_CMP (+-4 h, +-6 h), field-proven; selection takes the nearest toe anyway
FIT_INTERVAL_GALILEO_H = 8.0
FIT_INTERVAL_BEIDOU_H = 12.0
#: Galileo SISA 255 "no accuracy prediction available" (NAPA): RTKLIB's 6144 m (a satellite to avoid)
SISA_NAPA_M = 6144.0
#: Galileo data sources (RINEX 3 nav "data sources" bit field): I/NAV E1-B + E5b, F/NAV E5a-I
GALILEO_INAV, GALILEO_FNAV = "inav", "fnav"


def galileo_sisa_m(index: int) -> float:
    """Galileo SISA index -> metres (Galileo OS SIS ICD 5.1.12, table 89)."""
    if index <= 49:
        return index * 0.01
    if index <= 74:
        return 0.5 + (index - 50) * 0.02
    if index <= 99:
        return 1.0 + (index - 75) * 0.04
    if index <= 125:
        return 2.0 + (index - 100) * 0.16
    return SISA_NAPA_M


def _week_of_toe(system: str, week_sys_mod: int, modulus: int, toe_s: float, ref_gps: float) -> int:
    """GPS week of toe from the broadcast (system, possibly truncated) week number: the full week
    nearest the reference, then the week of toe within half a week of it (a message sent late on
    Saturday may carry next week's toe; RTKLIB's rule)."""
    offset = SYSTEM_WEEK_TO_GPS_WEEK[system]
    ref_week_sys = ref_gps / SECONDS_PER_WEEK - offset
    week = resolve_week(week_sys_mod, round(ref_week_sys), modulus) + offset
    dt = week * SECONDS_PER_WEEK + toe_s + SYSTEM_TO_GPS_S[system] - ref_gps
    if dt < -SECONDS_PER_WEEK / 2:
        week += 1
    elif dt >= SECONDS_PER_WEEK / 2:
        week -= 1
    return week


def _kepler(msg, f: dict[str, str]) -> dict:
    """The orbit fields common to every Keplerian message; ``f`` maps our names to DF numbers."""
    g = lambda k: float(getattr(msg, f[k]))          # noqa: E731
    pi = PI_ICD
    return dict(
        sqrt_a=g("sqrt_a"), e=g("e"), i0_rad=g("i0") * pi, omega0_rad=g("omega0") * pi,
        omega_rad=g("omega") * pi, m0_rad=g("m0") * pi, delta_n_radps=g("dn") * pi,
        idot_radps=g("idot") * pi, omega_dot_radps=g("omegadot") * pi,
        cuc_rad=g("cuc"), cus_rad=g("cus"), crc_m=g("crc"), crs_m=g("crs"), cic_rad=g("cic"),
        cis_rad=g("cis"), af0_s=g("af0"), af1_sps=g("af1"), af2_sps2=g("af2"))


_GPS_F = dict(sqrt_a="DF092", e="DF090", i0="DF097", omega0="DF095", omega="DF099", m0="DF088",
              dn="DF087", idot="DF079", omegadot="DF100", cuc="DF089", cus="DF091", crc="DF098",
              crs="DF086", cic="DF094", cis="DF096", af0="DF084", af1="DF083", af2="DF082")
_QZS_F = dict(sqrt_a="DF441", e="DF439", i0="DF446", omega0="DF444", omega="DF448", m0="DF437",
              dn="DF436", idot="DF450", omegadot="DF449", cuc="DF438", cus="DF440", crc="DF447",
              crs="DF435", cic="DF443", cis="DF445", af0="DF433", af1="DF432", af2="DF431")
_GAL_F = dict(sqrt_a="DF303", e="DF301", i0="DF308", omega0="DF306", omega="DF310", m0="DF299",
              dn="DF298", idot="DF292", omegadot="DF311", cuc="DF300", cus="DF302", crc="DF309",
              crs="DF297", cic="DF305", cis="DF307", af0="DF296", af1="DF295", af2="DF294")
_BDS_F = dict(sqrt_a="DF504", e="DF502", i0="DF509", omega0="DF507", omega="DF511", m0="DF500",
              dn="DF499", idot="DF491", omegadot="DF512", cuc="DF501", cus="DF503", crc="DF510",
              crs="DF498", cic="DF506", cis="DF508", af0="DF496", af1="DF495", af2="DF494")


def gps_ephemeris(msg, ref_gps: float) -> GpsEphemeris:
    """RTCM 1019 (GPS LNAV)."""
    toe = float(msg.DF093)
    iodc = int(msg.DF085)
    return GpsEphemeris(
        sat=f"G{int(msg.DF009):02d}", week=_week_of_toe("G", int(msg.DF076), 1024, toe, ref_gps),
        toe_s=toe, toc_s=float(msg.DF081), **_kepler(msg, _GPS_F),
        tgd_s=float(msg.DF101), iode=int(msg.DF071), iodc=iodc, health=int(msg.DF102),
        ura_m=URA_M[int(msg.DF077) & 0x0F], fit_interval_h=fit_interval_h(int(msg.DF137), iodc))


def qzss_ephemeris(msg, ref_gps: float) -> GpsEphemeris:
    """RTCM 1044 (QZSS LNAV).  DF429 is the satellite id 1-10 (PRN 193-202, RINEX J01-J10); fit
    interval flag 0 means 2 h, 1 "more than 2 h" (IS-QZSS-PNT): taken as 4 h (RTKLIB's +-2 h)."""
    toe = float(msg.DF442)
    return GpsEphemeris(
        sat=f"J{int(msg.DF429):02d}", week=_week_of_toe("J", int(msg.DF452), 1024, toe, ref_gps),
        toe_s=toe, toc_s=float(msg.DF430), **_kepler(msg, _QZS_F),
        tgd_s=float(msg.DF455), iode=int(msg.DF434), iodc=int(msg.DF456), health=int(msg.DF454),
        ura_m=URA_M[int(msg.DF453) & 0x0F], fit_interval_h=4.0 if int(msg.DF457) else 2.0)


def galileo_ephemeris(msg, ref_gps: float) -> tuple[GpsEphemeris, str]:
    """RTCM 1045 (F/NAV) or 1046 (I/NAV) -> (ephemeris, GALILEO_FNAV | GALILEO_INAV).

    Each clock goes with its own group delay (OS SIS ICD 5.1.5): F/NAV's with BGD(E1,E5a),
    I/NAV's with BGD(E1,E5b); both serve an E1 user, ``tgd_s`` is that BGD, ``tgd2_s`` 0.
    ``health`` is the RINEX 3 bit field: I/NAV E1-B DVS bit 0, HS bits 1-2, E5b DVS bit 6, HS bits
    7-8; F/NAV E5a DVS bit 3, HS bits 4-5."""
    inav = int(msg.identity) == 1046
    toe = float(msg.DF304)
    if inav:
        health = ((int(msg.DF316) << 7) | (int(msg.DF317) << 6) | (int(msg.DF287) << 1)
                  | int(msg.DF288))
        sisa, bgd = int(msg.DF286), float(msg.DF313)
    else:
        health = (int(msg.DF314) << 4) | (int(msg.DF315) << 3)
        sisa, bgd = int(msg.DF291), float(msg.DF312)
    eph = GpsEphemeris(
        sat=f"E{int(msg.DF252):02d}", week=_week_of_toe("E", int(msg.DF289), 4096, toe, ref_gps),
        toe_s=toe, toc_s=float(msg.DF293), **_kepler(msg, _GAL_F),
        tgd_s=bgd, iode=int(msg.DF290), iodc=int(msg.DF290), health=health,
        ura_m=galileo_sisa_m(sisa), fit_interval_h=FIT_INTERVAL_GALILEO_H)
    return eph, GALILEO_INAV if inav else GALILEO_FNAV


def beidou_ephemeris(msg, ref_gps: float) -> GpsEphemeris:
    """RTCM 1042 (BeiDou D1/D2).  Clock referred to B3I: ``tgd_s`` = TGD1 (B1I), ``tgd2_s`` = TGD2
    (B2I); pyrtcm gives them in ns.  ``iode`` = AODE, ``iodc`` = AODC; URA index as GPS's."""
    toe = float(msg.DF505)
    return GpsEphemeris(
        sat=f"C{int(msg.DF488):02d}", week=_week_of_toe("C", int(msg.DF489), 8192, toe, ref_gps),
        toe_s=toe, toc_s=float(msg.DF493), **_kepler(msg, _BDS_F),
        tgd_s=float(msg.DF513) * 1e-9, tgd2_s=float(msg.DF514) * 1e-9,
        iode=int(msg.DF492), iodc=int(msg.DF497), health=int(msg.DF515),
        ura_m=URA_M[int(msg.DF490) & 0x0F], fit_interval_h=FIT_INTERVAL_BEIDOU_H)


def glonass_ephemeris(msg, ref_gps: float, leap_seconds: int) -> GlonassEphemeris:
    """RTCM 1020.  t_b (DF110, 15-min units of Moscow time of day) resolved to the day nearest
    ``ref_gps``; km -> m."""
    km = 1e3
    return GlonassEphemeris(
        sat=f"R{int(msg.DF038):02d}", t_oe_gps=t_b_gps(int(msg.DF110), ref_gps, leap_seconds),
        r_e=np.array([msg.DF112, msg.DF115, msg.DF118], float) * km,
        v_e=np.array([msg.DF111, msg.DF114, msg.DF117], float) * km,
        a_e=np.array([msg.DF113, msg.DF116, msg.DF119], float) * km,
        clock_bias_s=-int(msg.DF124) * 2.0 ** -30, clock_rate=int(msg.DF121) * 2.0 ** -40,
        frequency_channel=int(msg.DF040) - 7, health=int(msg.DF108), iode=int(msg.DF110),
        delta_tau_n_s=int(msg.DF125) * 2.0 ** -30, age_days=int(msg.DF126))


__all__ = ["GlonassEphemeris", "GALILEO_FNAV", "GALILEO_INAV", "beidou_ephemeris", "galileo_ephemeris",
           "galileo_sisa_m", "glonass_ephemeris", "gps_ephemeris", "qzss_ephemeris"]
