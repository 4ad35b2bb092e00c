"""The MAVLink parameter protocol of companion.io.mavlink_params, with real MAVLink 2 bytes: a
pymavlink ground station (system 255) packs the requests, the server's answers are packed and parsed
back as the ground station would see them."""
from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.config import load_config
from companion.io.mavlink_codec import parse_bytes
from companion.io.mavlink_params import PARAMETERS, ParameterServer

GCS = mav.MAVLink(None, srcSystem=255, srcComponent=190)
US = mav.MAVLink(None, srcSystem=1, srcComponent=191)


def _wire(msg, enc):
    """msg -> bytes -> parsed message (what the other side receives)."""
    out = parse_bytes(bytes(msg.pack(enc)))
    assert len(out) == 1 and out[0].get_type() != "BAD_DATA"
    return out[0]


def _ask(server, msg) -> list:
    return [_wire(r, US) for r in server.handle(_wire(msg, GCS))]


@pytest.fixture
def setup(tmp_path):
    path = tmp_path / "companion.toml"
    path.write_text("# my comment\n[gnss]\nlever_arm_b_m = [0.1, -0.05, -0.2]\n[output]\nmode = \"odometry\"\n")
    changes = []
    server = ParameterServer(load_config(path), system_id=1, component_id=191,
                             on_change=lambda cfg, keys: changes.append((cfg, keys)))
    return server, path, changes


def _set(server, pid: str, value: float, target_component: int = 191):
    return _ask(server, GCS.param_set_encode(1, target_component, pid.encode(), value,
                                             mav.MAV_PARAM_TYPE_REAL32))


def test_list_gives_every_parameter_with_its_value_index_and_count(setup):
    server, _, _ = setup
    replies = _ask(server, GCS.param_request_list_encode(1, 191))
    assert [r.param_index for r in replies] == list(range(len(PARAMETERS)))
    assert all(r.param_count == len(PARAMETERS) for r in replies)
    got = {r.param_id: r for r in replies}
    assert got["CC_LEVER_Y"].param_value == pytest.approx(-0.05, abs=1e-7)
    assert got["CC_OUT_MODE"].param_value == 1.0 and got["CC_OUT_MODE"].param_type == mav.MAV_PARAM_TYPE_INT32
    assert got["CC_BASELINE_X"].param_value == 0.0          # unset moving baseline
    # read by id and by index
    r, = _ask(server, GCS.param_request_read_encode(1, 191, b"CC_MAX_HPL", -1))
    assert r.param_id == "CC_MAX_HPL" and r.param_value == 5.0
    r, = _ask(server, GCS.param_request_read_encode(1, 191, b"", 0))
    assert r.param_id == "CC_LEVER_X"
    assert _ask(server, GCS.param_request_read_encode(1, 191, b"NOT_OURS", -1)) == []


def test_an_accepted_set_is_answered_saved_and_applied(setup):
    server, path, changes = setup
    r, = _set(server, "CC_LEVER_X", 0.3)
    assert r.param_id == "CC_LEVER_X" and r.param_value == pytest.approx(0.3, abs=1e-7)
    cfg = load_config(path)                               # the file is still a valid configuration
    assert cfg.gnss.lever_arm_b_m == (0.3, -0.05, -0.2)   # 0.3, not float32's 0.30000001192...
    assert cfg.output.mode == "odometry"                  # nothing else changed
    assert "# my comment" in path.with_name("companion.toml.bak").read_text()
    assert len(changes) == 1 and changes[0][1] == ("gnss.lever_arm_b_m",)
    assert changes[0][0].gnss.lever_arm_b_m == (0.3, -0.05, -0.2)
    r, = _set(server, "CC_OUT_MODE", 2)
    assert r.param_value == 2.0 and load_config(path).output.mode == "gps_input"
    # the same value again: answered, not saved again, no change reported
    _set(server, "CC_OUT_MODE", 2)
    assert len(changes) == 2


def test_a_refused_set_keeps_the_value_and_says_why(setup):
    server, path, changes = setup
    before = path.read_text()
    replies = _set(server, "CC_MAX_SIG_H", -1.0)
    assert replies[0].get_type() == "PARAM_VALUE" and replies[0].param_value == 5.0
    text = "".join(r.text for r in replies[1:] if r.get_type() == "STATUSTEXT")
    assert text.startswith("CC_MAX_SIG_H refused:") and "must be" in text
    for bad in (7, 1.5, math.nan):
        r = _set(server, "CC_OUT_MODE", bad)[0]
        assert r.param_value == 1.0
    r = _set(server, "CC_LEVER_Z", 25.0)[0]               # beyond the key's 20-m range
    assert r.param_value == pytest.approx(-0.2, abs=1e-7)
    assert path.read_text() == before and changes == []
    assert server.counters["sets refused"] == 5


def test_moving_baseline_set_and_unset(setup):
    server, path, _ = setup
    _set(server, "CC_BASELINE_X", 0.6)
    assert load_config(path).gnss.moving_baseline_b_m == (0.6, 0.0, 0.0)
    r = _set(server, "CC_BASELINE_Y", 0.01)[0]             # still >= 5 cm long: fine
    assert r.param_value == pytest.approx(0.01, abs=1e-7)
    r = _set(server, "CC_BASELINE_X", 0.0)[0]             # (0, 0.01, 0): 1 cm, refused
    assert r.param_value == pytest.approx(0.6, abs=1e-7)
    _set(server, "CC_BASELINE_Y", 0.0)
    r = _set(server, "CC_BASELINE_X", 0.0)[0]             # all zero: unset
    assert r.param_value == 0.0 and load_config(path).gnss.moving_baseline_b_m is None


def test_requests_for_other_components_are_ignored(setup):
    server, path, _ = setup
    assert _ask(server, GCS.param_request_list_encode(1, 1)) == []          # the autopilot's
    assert _ask(server, GCS.param_request_list_encode(2, 0)) == []          # another vehicle
    assert len(_ask(server, GCS.param_request_list_encode(1, 0))) == len(PARAMETERS)   # broadcast
    assert _set(server, "CC_LEVER_X", 1.0, target_component=1) == []
    assert _ask(server, GCS.param_set_encode(1, 0, b"ATC_RAT_RLL_P", 0.1, mav.MAV_PARAM_TYPE_REAL32)) == []
    assert load_config(path).gnss.lever_arm_b_m[0] == 0.1
