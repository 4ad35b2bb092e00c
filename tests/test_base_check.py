"""companion.nav.base_check: the announced base position against the base's own pseudoranges,
and a network switching base stations mid-flight (the rtk scenario, its second base 3 km east).
The real car's cases (a 1005 5 km off; a 2-m re-survey) are in tests/test_rtk_engine_real_car.py."""
from __future__ import annotations

import dataclasses
import functools
from collections import Counter

import numpy as np
import pytest

from companion.messages import BaseStationPosition
from companion.nav.base_check import ADOPT, BASE_POSITION_MAX_SPP_DIFF_M, SKIP, USE, BaseStationCheck

HERE = np.array([-3959400.0, 3385704.0, 3667523.0])
EAST_3KM = np.array([-2130.0, -2490.0, 0.0])          # 3.28 km away


def test_a_position_is_believed_when_the_base_code_agrees_or_cannot_tell_yet():
    c = BaseStationCheck(Counter())
    assert c.announced(BaseStationPosition(1, HERE))                 # no epoch yet: its epochs judge it
    assert c.judge_epoch(None, BaseStationPosition(1, HERE)) == SKIP  # no SPP: never checked, not used
    assert c.counters["base epochs not used: position not checked yet"] == 1
    assert c.judge_epoch(HERE + 9.0, BaseStationPosition(1, HERE)) == USE
    assert c.judge_epoch(None, BaseStationPosition(1, HERE)) == USE   # checked once: used, counted
    assert c.counters["base epochs not checked: no single-point solution"] == 1
    assert c.announced(BaseStationPosition(1, HERE + 0.5 * BASE_POSITION_MAX_SPP_DIFF_M))
    assert not c.announced(BaseStationPosition(2, HERE + EAST_3KM))
    assert c.candidate.station_id == 2 and c.counters["base position not believed: far from the base's own pseudoranges"] == 1


def test_epochs_from_elsewhere_are_not_used_until_a_position_agrees_with_them():
    c = BaseStationCheck(Counter())
    believed = BaseStationPosition(1, HERE)
    c.announced(believed)
    assert c.judge_epoch(HERE + EAST_3KM, believed) == SKIP and c.skipping
    assert c.judge_epoch(HERE + EAST_3KM + 5.0, believed) == SKIP
    assert c.counters["base epochs not used: far from the base position"] == 2
    assert not c.announced(BaseStationPosition(2, HERE + 2 * EAST_3KM))    # nowhere near them either
    assert c.judge_epoch(HERE + EAST_3KM, believed) == SKIP
    ours = BaseStationPosition(2, HERE + EAST_3KM + 20.0)       # theirs, by their last SPP: believed
    assert c.announced(ours) and c.candidate is None
    assert c.judge_epoch(HERE + EAST_3KM - 3.0, ours) == USE and not c.skipping


def test_a_candidate_waits_while_the_old_station_still_sends():
    """A network's next station may announce itself a few epochs before its own epochs come."""
    c = BaseStationCheck(Counter())
    old, new = BaseStationPosition(1, HERE), BaseStationPosition(2, HERE + EAST_3KM)
    c.announced(old)
    c.judge_epoch(HERE, old)
    assert not c.announced(new)
    for _ in range(5):
        assert c.judge_epoch(HERE + 4.0, old) == USE
    assert c.judge_epoch(HERE + EAST_3KM + 4.0, old) == ADOPT


@functools.lru_cache(maxsize=1)
def _other_base():
    """The rtk scenario's flight again with its base 3 km east (station 2): the same rover
    epochs (same seed), another base's epochs and 1005."""
    from sitl.scenario import build_scenario
    from sitl.simulate import simulate
    from companion.nav.earth import C_n_e, ecef_to_geodetic
    scn = dataclasses.replace(build_scenario("rtk"), duration_s=110.0)
    lat, lon, _ = ecef_to_geodetic(np.asarray(scn.base_r_e, float))
    other = dataclasses.replace(scn, base_r_e=np.asarray(scn.base_r_e, float) + 3000.0 * C_n_e(lat, lon)[:, 1],
                                base_station_id=2)
    return simulate(other, 0)


@pytest.mark.parametrize("announced_after_s", [5.0, -5.0], ids=["epochs-first", "1005-first"])
def test_a_network_switching_base_stations_mid_flight(announced_after_s):
    """At 60 s the caster's base becomes a station 3 km away; its 1005 arrives 5 s after its first
    epoch, or 5 s before it.  Epochs first: they are not used until their 1005 (4 epochs), then
    the ambiguities restart and fix again at once.  1005 first: it waits as a candidate until its
    epochs come, then the same.  No wrong fix, no divergence.  Before, both ways:
    one station's epochs taken against the other's position, the engine declared itself diverged
    (all 21 pseudorange rows rejected in 2 s); 1005 first, it fixed 27 of the 34 epochs from 56 s
    to 90 s (now 34), 0.18 m off at worst.  The INS-predicted phase test kept every fix right."""
    from sitl.rtk_score import run_rtk
    other = _other_base()
    t0 = float(other.truth.t_gps[0])
    switch_s = 60.0
    announced = []

    def base_hook(epochs):
        return ([e for e in epochs if e.t_gps < t0 + switch_s]
                + [e for e in other.base_epochs if e.t_gps >= t0 + switch_s])

    def hook(eng, t_s):
        if not announced and t_s >= switch_s + announced_after_s:
            announced.append(t_s)
            eng.process(other.base)

    r = run_rtk(seed=0, duration_s=110.0, base_hook=base_hook, hook=hook)
    c = r["counters"]
    after = [e for e in r["epochs"] if e[0] >= switch_s + max(announced_after_s, 0.0) + 1.0]
    print(f"1005 {announced_after_s:+.0f} s: counters { {k: v for k, v in c.items() if 'base' in k} }, "
          f"{sum(e[1] == 'fixed' for e in after)} of {len(after)} fixed after it, wrong {r['wrong_fixes']}")
    assert c["base station changed: ambiguities and corrections restarted"] == 1
    assert c.get("base epochs not used: far from the base position", 0) == (4 if announced_after_s > 0 else 0)
    assert r["wrong_fixes"] == 0 and c["integrity.diverged"] == 0
    assert all(e[1] == "fixed" for e in after)


def test_a_real_base_stream_checked_against_a_configured_position():
    """The real Hiroshima base (RTCM3 MSM7, 1005, ephemerides; 60 s).  As sent: every epoch with a
    single-point solution is used, that solution 9 m from its 1005 (measured).  With
    ``corrections.base_position_ecef_m`` mistyped 3 km east: no epoch is used, and one STATUSTEXT
    says so, not one per 1005; the same position with ``corrections.base_max_spp_diff_m`` above
    its distance is used."""
    import calendar

    from companion.config import config_from_dict
    from companion.io.mavlink_time import unix_to_gps_s
    from companion.io.rtcm import RtcmDecoder
    from companion.pipeline import NavPipeline
    from tests._data import data_path
    t_gps = unix_to_gps_s(calendar.timegm((2022, 12, 13, 1, 9, 0)))
    dec = RtcmDecoder(week_hint=lambda: t_gps)
    msgs = dec.feed(data_path("qzsl6tool-hiroshima-rtcm3-ubx/20221213-010900.rtcm").read_bytes()) + dec.flush()
    sent = NavPipeline(config_from_dict({}))
    sent._feed_rtcm_messages(msgs)
    c = sent.engine.counters
    n_base = sum(1 for x in msgs if getattr(x, "source", "") == "base")
    print(f"as sent: {c['base epochs']} of {n_base} base epochs used, "
          f"{c['base epochs not used: position not checked yet']} before the ephemerides; SPP "
          f"{np.linalg.norm(sent.engine.base_check.spp_r_e - sent.engine.base.r_e):.1f} m from the 1005")
    assert c["base epochs"] >= 0.85 * n_base and sent.events == []
    assert np.linalg.norm(sent.engine.base_check.spp_r_e - sent.engine.base.r_e) < 20.0
    wrong = (sent.engine.base.r_e + np.array([-2130.0, -2490.0, 0.0])).tolist()
    typo = NavPipeline(config_from_dict({"corrections": {"base_position_ecef_m": wrong}}))
    typo._feed_rtcm_messages(msgs)
    c = typo.engine.counters
    assert c["base epochs"] == 0 and c["base epochs not used: far from the base position"] >= 0.85 * n_base
    assert [text for _, text in typo.events] == ["base epochs far from base position: unused",
                                                 "base position far from its own code: not believed"]
    # a position deliberately 3.3 km from the base's code (another datum) with the limit raised past
    # it (corrections.base_max_spp_diff_m): believed, its epochs used as sent, nothing announced
    datum = NavPipeline(config_from_dict({"corrections": {"base_position_ecef_m": wrong,
                                                          "base_max_spp_diff_m": 5000.0}}))
    datum._feed_rtcm_messages(msgs)
    assert datum.engine.counters["base epochs"] == sent.engine.counters["base epochs"] and datum.events == []
    assert np.allclose(datum.engine.base.r_e, wrong)
