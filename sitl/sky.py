"""Satellites for the simulator: the paper's six ephemerides (seed 000 Table 3), the GEONET
broadcast ephemerides, elevation/azimuth and the light-time solution of the geometric range.

Geometric range (what the receiver sees before clocks and errors):
``rho = | R3(omega_e * tau) r_sat(t_tx) - r_ant(t_rx) |`` with ``t_tx = t_rx - tau`` and
``tau = rho / c`` iterated to convergence (t_rx and t_tx in true GPS time; the satellite position is
the broadcast orbit, orbit errors are added separately along the line of sight).
"""
from __future__ import annotations

import math
from importlib import resources
from pathlib import Path

import numpy as np

from companion.gnss.ephemeris import rotate_to_reception_frame, satellite_state
from companion.gnss.ephemeris_store import EphemerisStore
from companion.gnss.rinex import read_rinex_nav
from companion.messages import SPEED_OF_LIGHT_MPS, GpsEphemeris
from companion.nav.earth import C_n_e, ecef_to_geodetic

#: GEONET 0759's broadcast navigation file, shipped with the package (``sitl/data``, provenance and
#: licence there): found through importlib.resources so an installed wheel has it too
GEONET_NAV = Path(str(resources.files("sitl") / "data" / "07590920.05n"))
#: RINEX header APPROX POSITION XYZ of the two GEONET stations (m)
GEONET_3040_R_E = np.array([-3978242.4348, 3382841.1715, 3649902.7667])
GEONET_0759_R_E = np.array([-3976219.5082, 3382372.5671, 3652512.9849])

# Seed 000 Table 3 (as transcribed in design/seeds.md, OCR fixes there); angles in semicircles.
# Columns: SV1..SV6.
PAPER_TABLE3 = {
    "crs_m": (-59.875, 65.281, -85.656, 46.969, 62.00, 54.563),
    "delta_n_sc": (1.5294e-9, 1.6692e-9, 1.4644e-9, 1.4919e-9, 1.1192e-9, 1.6494e-9),
    "m0_sc": (-0.48401, -0.87179, -0.88417, -0.88899, -0.97589, 0.11990),
    "cuc_rad": (-2.0840e-6, 3.3500e-6, -4.5337e-6, 2.4196e-6, 1.3784e-7, 2.8610e-6),
    "e": (3.7472e-3, 1.1916e-3, 6.8008e-3, 6.7628e-3, 7.8766e-3, 5.0219e-3),
    "cus_rad": (7.8715e-6, 3.3546e-6, 6.5677e-6, 1.1941e-5, 1.1863e-5, 3.4180e-6),
    "sqrt_a": (5153.6, 5153.5, 5153.7, 5153.7, 5153.8, 5153.7),
    "toe_s": (251980.0, 252000.0, 252000.0, 252000.0, 252000.0, 252000.0),
    "cic_rad": (-2.2352e-8, -5.0291e-8, -4.4703e-8, -1.2852e-7, 7.2643e-8, -1.6764e-8),
    "omega0_sc": (0.6408, -0.70009, -0.35952, 0.96454, -0.27200, -0.70123),
    "cis_rad": (1.3039e-7, 4.0078e-7, -1.2480e-7, -9.1270e-8, -6.3918e-8, 6.3918e-8),
    "i0_sc": (0.30394, 0.30031, 0.30513, 0.30066, 0.31381, 0.30266),
    "crc_m": (224.94, 303.63, 250.19, 142.13, 161.28, 307.16),
    "omega_sc": (-0.51669, -0.28071, -0.82533, 0.82234, -0.60022, 0.51312),
    "omega_dot_sc": (-2.5994e-9, -2.7268e-9, -2.5919e-9, -2.5278e-9, -2.3444e-9, -2.7663e-9),
}
#: Broadcast clock terms the paper does not give; chosen (fixed, scenario constants) to be of
#: typical size so that the satellite-clock code path is exercised: af0 s, af1 s/s.
PAPER_AF0_S = (1.25e-5, -3.71e-5, 6.02e-5, -8.4e-6, 2.33e-5, -4.90e-5)
PAPER_AF1_SPS = (1.1e-12, -2.3e-12, 4.0e-13, 0.0, -1.7e-12, 3.1e-12)


def paper_ephemerides(week: int = 1316) -> list[GpsEphemeris]:
    """The six satellites of seed 000 Table 3 as 'G01'..'G06' (IDOT 0, toc = toe, TGD 0)."""
    T = PAPER_TABLE3
    pi = math.pi
    out = []
    for k in range(6):
        out.append(GpsEphemeris(
            sat=f"G{k + 1:02d}", week=week, toe_s=T["toe_s"][k], toc_s=T["toe_s"][k],
            sqrt_a=T["sqrt_a"][k], e=T["e"][k], i0_rad=T["i0_sc"][k] * pi,
            omega0_rad=T["omega0_sc"][k] * pi, omega_rad=T["omega_sc"][k] * pi,
            m0_rad=T["m0_sc"][k] * pi, delta_n_radps=T["delta_n_sc"][k] * pi, idot_radps=0.0,
            omega_dot_radps=T["omega_dot_sc"][k] * pi, cuc_rad=T["cuc_rad"][k],
            cus_rad=T["cus_rad"][k], crc_m=T["crc_m"][k], crs_m=T["crs_m"][k],
            cic_rad=T["cic_rad"][k], cis_rad=T["cis_rad"][k], af0_s=PAPER_AF0_S[k],
            af1_sps=PAPER_AF1_SPS[k], af2_sps2=0.0, tgd_s=0.0, iode=k + 1, iodc=k + 1))
    return out


def geonet_ephemerides(path=GEONET_NAV) -> list[GpsEphemeris]:
    return read_rinex_nav(path)


def select_ephemerides(ephs, t_gps: float, t_end_gps: float | None = None) -> dict[str, GpsEphemeris]:
    """One healthy ephemeris per satellite, valid (fit interval) at ``t_gps`` and, if given,
    also at ``t_end_gps`` (the same ephemeris is used for the whole run: no mid-run switch)."""
    store = EphemerisStore(ephs)
    out = {}
    for sat in store.sats:
        e = store.select(sat, t_gps)
        if e is None:
            continue
        if t_end_gps is not None and abs(t_end_gps - e.t_oe_gps) > e.fit_interval_h * 1800.0:
            continue
        out[sat] = e
    return out


def enu_basis(r_rx_e) -> np.ndarray:
    lat, lon, _ = ecef_to_geodetic(r_rx_e)
    return C_n_e(lat, lon)           # columns: north, east, down in ECEF


def elevation_azimuth(r_rx_e, r_sat_e) -> tuple[float, float]:
    """(elevation, azimuth) in rad of the satellite seen from the receiver (geodetic local level)."""
    d = np.asarray(r_sat_e, float) - np.asarray(r_rx_e, float)
    ned = enu_basis(r_rx_e).T @ d
    el = math.atan2(-ned[2], math.hypot(ned[0], ned[1]))
    az = math.atan2(ned[1], ned[0]) % (2.0 * math.pi)
    return el, az


def light_time_range(eph: GpsEphemeris, t_rx_gps: float, r_ant_e: np.ndarray,
                     tau_guess_s: float = 0.075, iterations: int = 3):
    """Solve the light time.  Returns (rho m, tau s, r_sat m (rx frame), v_sat m/s (rx frame),
    broadcast clock bias s (incl. relativity, excl. TGD), broadcast clock drift s/s)."""
    tau = tau_guess_s
    for _ in range(iterations):
        r_s, v_s, clk, dclk = satellite_state(eph, t_rx_gps - tau)
        r_rx, v_rx = rotate_to_reception_frame(r_s, v_s, tau)
        rho = float(np.linalg.norm(r_rx - r_ant_e))
        tau = rho / SPEED_OF_LIGHT_MPS
    r_s, v_s, clk, dclk = satellite_state(eph, t_rx_gps - tau)
    r_rx, v_rx = rotate_to_reception_frame(r_s, v_s, tau)
    rho = float(np.linalg.norm(r_rx - r_ant_e))
    return rho, tau, r_rx, v_rx, clk, dclk


def sky_table(ephs, r_rx_e, t_gps_list) -> dict[str, np.ndarray]:
    """Elevation (deg) of each satellite at each time seen from a static point: for visibility checks."""
    out = {}
    for e in ephs:
        els = []
        for t in t_gps_list:
            _, _, r_s, _, _, _ = light_time_range(e, t, r_rx_e)
            els.append(math.degrees(elevation_azimuth(r_rx_e, r_s)[0]))
        out[e.sat] = np.array(els)
    return out
