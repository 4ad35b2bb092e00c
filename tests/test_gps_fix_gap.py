"""After a sky outage the autopilot's GPS_RAW_INT fixes come back before the receiver's raw
observations (the SERIAL_CONTROL port is re-claimed in ~1-2 s).  When the last raw epoch was
RTK-fixed those first fixes are not fused loosely: the raw observations get RAW_TIMEOUT_S again
(companion.pipeline.GPS_FIX_GAP_S), since they re-fix within seconds at centimetres where the loose
fixes would be injected a metre off.  Without RTK nothing changes (the loose fixes are as good as
the DGPS path; waiting only withheld the output longer: tests/test_yaw_gsf_pipeline.py).  A receiver
whose raw output does not come back still falls back to loose fusion RAW_TIMEOUT_S later.

The flight is the DGPS 'uav' flight offline with the RTK status stubbed as fixed (the rule's
trigger is tested on its own below); the rtk flights through the service are measured in the
README (RTK inside the filter)."""
from __future__ import annotations

import os

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mav  # noqa: E402

from companion import pipeline as pipeline_module  # noqa: E402
from test_integrity_pipeline import flight_records, fly_offline, pipeline_config  # noqa: E402

OUTAGE_S = (35.0, 55.0)       # relative to the start: nothing from the sky
RAW_LATE_S = 1.5              # raw observations come back this much after the GPS_RAW_INT fixes


def _is_gps_raw_int(data: bytes) -> bool:
    return data[0] == 0xFD and int.from_bytes(data[7:10], "little") == mav.MAVLINK_MSG_ID_GPS_RAW_INT


def _outage(records, t0, raw_back_s):
    """Records without GNSS (fixes, corrections) in OUTAGE_S and without raw observations from
    its start to ``raw_back_s`` (relative to the start)."""
    out = []
    for kind, t_ns, data in records:
        t = t_ns * 1e-9 - t0
        if kind == "ubx" and OUTAGE_S[0] <= t < raw_back_s:
            continue
        if (kind == "rtcm" or kind == "mavlink" and _is_gps_raw_int(data)) and OUTAGE_S[0] <= t < OUTAGE_S[1]:
            continue
        out.append((kind, t_ns, data))
    return out


@pytest.fixture(scope="module")
def uav70():
    from sitl.fly import load_sim
    return load_sim("uav", 0, 70.0)


def _fly(sim, raw_back_s, monkeypatch=None, rtk_fixed=True):
    if monkeypatch is not None:
        monkeypatch.setattr(pipeline_module.NavPipeline, "_rtk_fixed_last", lambda self: rtk_fixed)
    records = _outage(flight_records(sim, 70.0), float(sim.truth.t_gps[0]), raw_back_s)
    return fly_offline(sim, records, pipeline_config(sim))


def test_fixes_back_before_raw_are_not_fused_loosely_after_an_rtk_fix(uav70, monkeypatch):
    pipe, rows, _ = _fly(uav70, OUTAGE_S[1] + RAW_LATE_S, monkeypatch)
    assert pipe.counters["GPS_RAW_INT back after a gap: raw observations awaited first"] == 1
    assert pipe.counters["loose fixes fused"] == 0
    assert pipe.mode != "loose"
    after = [e for t, inj, e, _ in rows if inj and t > OUTAGE_S[1] + RAW_LATE_S + 3.0]
    assert after and max(after) < 1.0


def test_without_the_rule_the_first_fixes_would_be_fused_loosely(uav70, monkeypatch):
    """The same flight with the rule off: the test above can fail."""
    monkeypatch.setattr(pipeline_module, "GPS_FIX_GAP_S", float("inf"))
    pipe, _, _ = _fly(uav70, OUTAGE_S[1] + RAW_LATE_S, monkeypatch)
    assert pipe.counters["GPS_RAW_INT back after a gap: raw observations awaited first"] == 0
    assert pipe.counters["loose fixes fused"] >= 1


def test_without_an_rtk_fix_the_fixes_after_the_gap_are_fused_loosely(uav70):
    """The default DGPS flight (no RTK): the rule stays out of the way."""
    pipe, _, _ = _fly(uav70, OUTAGE_S[1] + RAW_LATE_S)
    assert pipe.counters["GPS_RAW_INT back after a gap: raw observations awaited first"] == 0
    assert pipe.counters["loose fixes fused"] >= 1


def test_raw_that_does_not_come_back_still_falls_back_to_loose(uav70, monkeypatch):
    pipe, _, _ = _fly(uav70, 1e9, monkeypatch)
    assert pipe.counters["GPS_RAW_INT back after a gap: raw observations awaited first"] == 1
    # 70 - 55 s of fixes, the first RAW_TIMEOUT_S of them awaiting raw observations
    n = pipe.counters["loose fixes fused"]
    assert 70.0 - OUTAGE_S[1] - pipeline_module.RAW_TIMEOUT_S - 2.0 <= n <= 70.0 - OUTAGE_S[1] - pipeline_module.RAW_TIMEOUT_S + 1.0
    assert pipe.mode == "loose"


def test_the_trigger_is_the_rtk_status_of_the_last_raw_epoch():
    from types import SimpleNamespace
    from companion.nav.rtk_update import FIX_FIXED, FIX_FLOAT
    pipe = SimpleNamespace(rtk_enabled=True, engine=SimpleNamespace(rtk=SimpleNamespace(status=None)))
    fixed_last = pipeline_module.NavPipeline._rtk_fixed_last
    assert not fixed_last(pipe)
    pipe.engine.rtk.status = SimpleNamespace(fix_state=FIX_FLOAT)
    assert not fixed_last(pipe)
    pipe.engine.rtk.status = SimpleNamespace(fix_state=FIX_FIXED)
    assert fixed_last(pipe)
    pipe.rtk_enabled = False
    assert not fixed_last(pipe)
    pipe.rtk_enabled, pipe.engine.rtk = True, None
    assert not fixed_last(pipe)
