"""The protection level in the outputs: solution record version 2 (version 1 still decodes and
compares), the injection gate with its hysteresis, NAMED_VALUE_FLOAT CC_HPL, MQTT JSON, the
aid-status record and the fault matrix's matching of CC_HPL to the estimates."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from companion.aid_status_record import (
    AidStatusPacer,
    aid_status_dict,
    decode_aid_status,
    encode_aid_status,
)
from companion.config import config_from_dict
from companion.messages import NavSolution
from companion.pipeline import NavPipeline
from companion.log_records import _SOL_V1, SOLUTION_RECORD_VERSION, decode_solution, encode_solution, solution_records_equal

R_E = np.array([-3976219.5, 3382372.6, 3652513.0])


def _sol(t=100.0, sig_h=0.5, hpl=2.0, status="nav"):
    return NavSolution(float(t), R_E.copy(), np.zeros(3), np.eye(3), np.array([sig_h / math.sqrt(2)] * 2 + [0.3]),
                       np.full(3, 0.1), np.full(3, 0.01), status, 99.5, 1,
                       {"hpl_m": hpl, "hpl_cov_m": hpl, "hpl_ss_m": math.nan, "integrity": "ok"})


def test_solution_record_v2_round_trip_and_v1_still_decodes():
    assert SOLUTION_RECORD_VERSION == 3          # version 3 appended the RTK fix state (tests/test_rtk_outputs.py)
    s = _sol(hpl=2.345678901234)
    s.extras.update({"inject": True, "mode": "tight", "imu_count": 7, "t_boot_us": 123})
    b = encode_solution(s)
    d = decode_solution(b)
    assert d.extras["hpl_m"] == s.extras["hpl_m"] and encode_solution(d) == b
    # a version-1 record of an old field log: same fields without the HPL
    v1 = _SOL_V1.pack(1, *_SOL_V1.unpack(b[:_SOL_V1.size])[1:])
    old = decode_solution(v1)
    assert "hpl_m" not in old.extras and old.t_gps == s.t_gps and np.array_equal(old.r_e, s.r_e)
    assert old.extras["inject"] and old.status == "nav"
    assert solution_records_equal(v1, b)           # replay of an old log still compares bit for bit
    changed = bytearray(v1)
    changed[-1] ^= 1
    assert not solution_records_equal(bytes(changed), b)
    assert not solution_records_equal(encode_solution(_sol(hpl=2.0)), encode_solution(_sol(hpl=2.1)))


def test_hpl_gate_stops_injection_and_resumes_only_below_the_fraction():
    pipe = NavPipeline(config_from_dict({"output": {"max_hpl_m": 5.0, "resume_hpl_fraction": 0.8}}))
    pipe.mode = "tight"
    seq = [3.0, 4.9, 5.1, 4.5, 4.1, 5.5, 3.9, 4.5, 4.99]
    got = [pipe._finish(_sol(t=k, hpl=h)).extras["inject"] for k, h in enumerate(seq)]
    assert got == [True, True, False, False, False, False, True, True, True]
    events = [t for _, t in pipe.drain_events()]
    assert any("HPL 5.1 m" in t for t in events) and len(events) == 3      # OK, stop, OK again
    # a NaN HPL (not computable) is never injected; the sigma gate still works on its own
    assert not pipe._finish(_sol(t=20, hpl=math.nan)).extras["inject"]
    assert not pipe._finish(_sol(t=21, sig_h=6.0, hpl=1.0)).extras["inject"]


def test_hpl_in_health_named_values_and_mqtt():
    from companion.io.gcs_values import named_values
    pipe = NavPipeline(config_from_dict({}))
    pipe.mode = "tight"
    sol = pipe._finish(_sol(hpl=2.5))
    assert pipe.health()["filter"]["protection_level"]["hpl_m"] == 2.5
    vals = {m.name.rstrip("\x00") if isinstance(m.name, str) else m.name.decode().rstrip("\x00"): m.value
            for m in named_values(sol, 1000)}
    assert vals["CC_HPL"] == pytest.approx(2.5)
    pytest.importorskip("aiomqtt")
    from companion.io.mqtt import solution_to_json
    j = solution_to_json(sol)
    assert j["hpl_m"] == 2.5 and j["inject"] is True
    assert solution_to_json(_sol(hpl=math.nan))["hpl_m"] is None


def test_aid_status_record_is_compact_versioned_and_paced():
    from companion.nav.filter import UpdateReport
    pipe = NavPipeline(config_from_dict({}))
    rep = UpdateReport("pseudorange", ["G01", "G02"], np.array([0.3, -12.0]), np.array([1.0, 1.0]),
                       np.array([0.0083, 13.3]), np.array([True, False]))
    pipe.engine.aid.record(rep, 99.0, 10.83)
    obj = aid_status_dict(pipe, _sol(hpl=2.25))
    payload = encode_aid_status(obj)
    assert b" " not in payload and decode_aid_status(payload) == obj
    pr = obj["sources"]["pseudorange"]
    assert pr["labels"] == ["G01", "G02"] and pr["accepted"] == [True, False] and pr["test_ratio"][1] == 13.3
    assert obj["hpl_m"] == 2.25 and obj["hpl_ss_m"] is None and obj["v"] == 1
    assert decode_aid_status(payload.replace(b'"v":1', b'"v":99')) is None
    pacer = AidStatusPacer(2.0)
    sols = [_sol(t=100.0 + 0.1 * k) for k in range(20)]            # 2 s of 10-Hz solutions
    assert len(pacer.records(pipe, sols)) == 4
    assert AidStatusPacer(0.0).records(pipe, sols) == []


def test_fault_matrix_scores_against_the_last_hpl_received_before_the_estimate():
    from sitl.faults import _hpl_for, _named_value_series
    nv = lambda t, name, v: SimpleNamespace(t_mono_ns=t, msg_type="NAMED_VALUE_FLOAT",
                                            msg=SimpleNamespace(name=name, value=v))
    ap = SimpleNamespace(received=[nv(1_000_000_000, "CC_SIGH", 0.5), nv(1_000_000_100, "CC_HPL", 2.0),
                                   nv(1_100_000_100, "CC_HPL", 3.0), nv(1_200_000_100, "CC_HPL", -1.0)])
    t, v = _named_value_series(ap, "CC_HPL")
    assert t == [1_000_000_100, 1_100_000_100, 1_200_000_100] and v[:2] == [2.0, 3.0] and math.isnan(v[2])
    est = lambda t: SimpleNamespace(t_mono_ns=t)
    assert math.isnan(_hpl_for(est(999_000_000), t, v))            # before any CC_HPL: 3 sigma is used
    assert _hpl_for(est(1_100_000_000), t, v) == 2.0               # not the later (larger) one
    assert _hpl_for(est(1_150_000_000), t, v) == 3.0
    assert math.isnan(_hpl_for(est(1_100_000_100 + 10**9), t, v))  # too old
