"""sitl.rtcm_msm.Msm7Encoder (the rtk scenario's base stream) decoded back by the companion's
RtcmDecoder: L1 C/A as 1C, the simulator's L2 as 2W and 2X, code and phase to their field
resolution, the carrier's integer reference kept while locked, Doppler on L1 only."""
from __future__ import annotations

import dataclasses
import math

import pytest

from companion.io.rtcm import RtcmDecoder
from sitl.rtcm_msm import MSM7_FINE_PH_LSB_MS, MSM7_FINE_PR_LSB_MS, Msm7Encoder

LIGHT_MS_M = 299792.458


@pytest.fixture(scope="module")
def base_epochs():
    from sitl.scenario import build_scenario
    from sitl.simulate import simulate
    scn = dataclasses.replace(build_scenario("rtk"), duration_s=6.0)
    return simulate(scn, 0).base_epochs


def test_msm7_round_trip(base_epochs):
    enc = Msm7Encoder(759)
    dec = RtcmDecoder(week_hint=int(base_epochs[0].t_gps // 604800))
    offsets = {}          # (sat, code) -> integer cycles between decoded and simulated carrier
    for ep in base_epochs:
        frame = enc.encode(ep)
        assert frame[0] == 0xD3 and (frame[3] << 4 | frame[4] >> 4) == 1077
        got = [m for m in dec.feed(frame, 0.0) + dec.poll(100.0) if hasattr(m, "observations")]
        assert len(got) == 1 and got[0].t_gps == ep.t_gps and got[0].source == "base"
        obs = {(o.sat, o.signal): o for o in got[0].observations}
        sim_l2 = [o for o in ep.observations if o.signal == "L2W"]
        assert sim_l2 and len(obs) == len(ep.observations) + len(sim_l2)      # L2 twice: 2W and 2X
        for o in ep.observations:
            for code in (("L1C",) if o.signal == "L1C" else ("L2W", "L2X")):
                g = obs[(o.sat, code)]
                assert g.pseudorange_m == pytest.approx(o.pseudorange_m, abs=MSM7_FINE_PR_LSB_MS * LIGHT_MS_M)
                k = g.carrier_cycles - o.carrier_cycles
                assert abs(k - round(k)) * o.wavelength_m <= MSM7_FINE_PH_LSB_MS * LIGHT_MS_M
                assert offsets.setdefault((o.sat, code), round(k)) == round(k)    # same reference while locked
                assert not g.loss_of_lock
                if code == "L1C":
                    assert g.doppler_hz == pytest.approx(o.doppler_hz, abs=1e-4 / o.wavelength_m)
                else:
                    assert math.isnan(g.doppler_hz)       # the simulator's L2 has no Doppler
    assert dec.counters.get("msm7", 0) == len(base_epochs)
