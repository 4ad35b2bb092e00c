"""The tightly coupled engine with GPS, Galileo, BeiDou and QZSS on a real receiver: the NovAtel
OEM729 base stream (Hiroshima, 2022-12-13, 60 s of RTCM3 MSM7 + ephemerides, decoded by our RTCM
decoder) with a synthetic IMU at rest (earth rate and gravity, white noise), standalone
(pseudoranges + TDCP).  Truth: the stream's own RTCM 1005 antenna reference point.

Checked: every epoch fuses all four systems (one receiver clock, inter-system bias states for
Galileo and BeiDou, QZSS on GPS's clock); the biases the filter settles on are the ones the
epoch-by-epoch SPP finds; the multi-GNSS solution is no worse than GPS alone on L1 and on the
iono-free pair, and at the level of our (and RTKLIB's) multi-GNSS SPP on the same data (README:
G+E+C+J iono-free 1.16 m, L1 3.12 m 3-D).

Run:  python -m pytest -q -s tests/test_engine_multignss.py   (prints the figures)
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.gnss.atmosphere import KLOBUCHAR_DEFAULT
from companion.gnss.spp import spp_epoch
from companion.io.rtcm import decode_rtcm_file
from companion.messages import GnssEpoch, GpsEphemeris, ImuSample
from companion.nav.earth import C_n_e, OMEGA_IE_RADPS, ecef_to_geodetic, ecef_to_ned, gravity_ecef
from companion.nav.engine import EngineConfig, NavEngine
from companion.nav.filter import ProcessNoise
from tests._data import data_path

pytestmark = pytest.mark.real_data
RTCM = data_path("qzsl6tool-hiroshima-rtcm3-ubx") / "20221213-010900.rtcm"
ARP_E = np.array([-3551876.8287, 3887786.8598, 3586946.3873])     # its RTCM 1005
IMU_DT_S = 0.005
GNSS_LATENCY_S = 0.1


@pytest.fixture(scope="module")
def stream():
    msgs, _ = decode_rtcm_file(str(RTCM), week_hint=2240)
    ephs = [m for m in msgs if isinstance(m, GpsEphemeris)]
    epochs = [dataclasses.replace(m, source="rover") for m in msgs if isinstance(m, GnssEpoch)]
    assert {e.sat[0] for e in ephs} >= set("GECJ") and len(epochs) == 60
    return ephs, epochs


def _run(stream, systems: str, signal: str):
    ephs, epochs = stream
    eng = NavEngine(EngineConfig(noise=ProcessNoise(1e-4, 1e-3, 1e-6, 1e-5), use_dgps=False, use_tdcp=True,
                                 systems=systems, pseudorange_signal=signal, klobuchar=KLOBUCHAR_DEFAULT,
                                 elevation_mask_deg=10.0))
    for e in ephs:
        eng.process(e)
    k0, sol = next((k, s) for k, s in ((k, spp_epoch(ep, eng.ephemerides, klobuchar=KLOBUCHAR_DEFAULT,
                                                     systems=systems, signal=signal))
                                       for k, ep in enumerate(epochs)) if s is not None)
    lat, lon, _ = ecef_to_geodetic(sol.r_e)
    C_b_e = C_n_e(lat, lon)                       # level, facing north, at rest
    t = epochs[k0].t_gps - 0.5
    eng.initialize(t, sol.r_e, np.zeros(3), C_b_e, dict(pos_m=5.0, vel_mps=0.1, tilt_rad=0.01, heading_rad=0.05,
                                                         ba_mps2=0.05, bg_radps=1e-3))
    w_ie_e = np.array([0.0, 0.0, OMEGA_IE_RADPS])
    f_e = -(gravity_ecef(sol.r_e))                # specific force at rest: minus gravity (incl. centrifugal)
    rng = np.random.default_rng(0)
    err_ned, by_system, spp_isb = [], [], []
    for ep in epochs[k0:]:
        while t < ep.t_gps + GNSS_LATENCY_S:
            t += IMU_DT_S
            eng.process(ImuSample(t, IMU_DT_S, C_b_e.T @ w_ie_e * IMU_DT_S + rng.normal(0, 1e-4 * math.sqrt(IMU_DT_S), 3),
                                  C_b_e.T @ f_e * IMU_DT_S + rng.normal(0, 1e-3 * math.sqrt(IMU_DT_S), 3)))
        rep = eng.process(ep)
        by_system.append(rep.sats_by_system)
        err_ned.append(ecef_to_ned(eng.r_e, ARP_E))
        s = spp_epoch(ep, eng.ephemerides, klobuchar=KLOBUCHAR_DEFAULT, systems=systems, signal=signal)
        if s is not None:
            spp_isb.append(s.isb_m)
    d = np.array(err_ned)
    return {"rms_3d_m": float(np.sqrt(np.mean(np.sum(d ** 2, axis=1)))),
            "rms_h_m": float(np.sqrt(np.mean(np.sum(d[:, :2] ** 2, axis=1)))),
            "by_system": by_system, "isb_m": {k[4:]: float(v[0]) for k, v in eng.block_states.items()},
            "spp_isb_m": {c: float(np.mean([x[c] for x in spp_isb if c in x])) for c in spp_isb[-1]}}


@pytest.fixture(scope="module")
def runs(stream):
    out = {(sy, sg): _run(stream, sy, sg) for sy in ("G", "GECJ") for sg in ("L1C", "IF")}
    print()
    for (sy, sg), r in out.items():
        print(f"  {sy:4s} {sg:3s}: RMS 3-D {r['rms_3d_m']:.3f} m, H {r['rms_h_m']:.3f} m, satellites "
              f"{r['by_system'][-1]}, ISB filter {({k: round(v, 2) for k, v in r['isb_m'].items()})} "
              f"SPP {({k: round(v, 2) for k, v in r['spp_isb_m'].items()})}")
    return out


def test_every_epoch_fuses_four_systems_with_two_bias_states(runs):
    for sg in ("L1C", "IF"):
        r = runs[("GECJ", sg)]
        assert all(set(b) == set("GECJ") for b in r["by_system"][1:]), r["by_system"][:3]
        assert set(r["isb_m"]) == {"E", "C"}
        assert all(set(b) == {"G"} for b in runs[("G", sg)]["by_system"])


def test_the_bias_states_settle_where_spp_puts_them(runs):
    for sg in ("L1C", "IF"):
        r = runs[("GECJ", sg)]
        for c in ("E", "C"):
            assert abs(r["isb_m"][c] - r["spp_isb_m"][c]) < 1.5, (sg, c, r["isb_m"], r["spp_isb_m"])


def test_multignss_no_worse_than_gps_and_at_the_spp_level(runs):
    assert runs[("GECJ", "L1C")]["rms_h_m"] < runs[("G", "L1C")]["rms_h_m"]
    assert runs[("GECJ", "IF")]["rms_3d_m"] <= runs[("G", "IF")]["rms_3d_m"] + 0.02
    assert runs[("GECJ", "IF")]["rms_3d_m"] < 1.3
    assert runs[("GECJ", "L1C")]["rms_3d_m"] < 3.5
