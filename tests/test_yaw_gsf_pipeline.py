"""Heading from motion at pipeline level (companion.nav.yaw_gsf in companion.pipeline): the
simulated multirotor flight and the car, fed as MAVLink/UBX/RTCM bytes, without ATTITUDE or with
its yaw 180 deg off, get their heading within 30 s of the first horizontal motion, and nothing
is injected with the wrong heading."""
from __future__ import annotations

import math
import os

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mav  # noqa: E402

from companion.nav.earth import C_n_e, dcm_to_euler, ecef_to_geodetic  # noqa: E402
from test_integrity_pipeline import flight_records, fly_offline, pipeline_config  # noqa: E402


def _attitude_fault(records, fault: str):
    """ATTITUDE removed (``'none'``) or its yaw turned by 180 deg (``'yaw180'``)."""
    parser = mav.MAVLink(None)
    parser.robust_parsing = True
    enc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    out = []
    for kind, t_ns, data in records:
        if kind == "mavlink" and data[0] == 0xFD and int.from_bytes(data[7:10], "little") == mav.MAVLINK_MSG_ID_ATTITUDE:
            if fault == "none":
                continue
            if fault != "yaw180":
                out.append((kind, t_ns, data))
                continue
            msg = parser.parse_buffer(data)[0]
            yaw = (msg.yaw + 2.0 * math.pi) % (2.0 * math.pi) - math.pi
            data = bytes(enc.attitude_encode(msg.time_boot_ms, msg.roll, msg.pitch, yaw, 0, 0, 0).pack(enc))
        out.append((kind, t_ns, data))
    return out


def _run(sim, records, cfg):
    """Per solution (t_rel, inject, horizontal error m, heading error deg)."""
    t0 = float(sim.truth.t_gps[0])
    head = []

    def on_solution(pipe, sol):
        _, _, C = sim.truth_at(sol.t_gps)
        lat, lon, _ = ecef_to_geodetic(sol.r_e)
        Cen = C_n_e(lat, lon).T
        d = dcm_to_euler(Cen @ sol.C_b_e)[2] - dcm_to_euler(Cen @ C)[2]
        head.append(math.degrees((d + math.pi) % (2.0 * math.pi) - math.pi))

    pipe, rows, events = fly_offline(sim, records, cfg, on_solution=on_solution)
    return pipe, [(t, inj, e, h) for (t, inj, e, _), h in zip(rows, head)], events, t0


def _first_motion_s(sim, speed_mps=0.5):
    """Seconds from the start to the first horizontal speed above ``speed_mps`` (heading is
    unobservable before: a vertical climb shows no heading)."""
    tr = sim.truth
    lat, lon, _ = ecef_to_geodetic(tr.r_e[0])
    v_n = tr.v_e @ C_n_e(lat, lon)
    k = int(np.argmax(np.hypot(v_n[:, 0], v_n[:, 1]) > speed_mps))
    return float(tr.t_gps[k] - tr.t_gps[0])


@pytest.fixture(scope="module")
def uav70():
    from sitl.fly import load_sim
    return load_sim("uav", 0, 70.0)


@pytest.fixture(scope="module")
def uav_records(uav70):
    return flight_records(uav70, 70.0)


@pytest.mark.parametrize("fault", ["none", "yaw180"])
def test_multirotor_heading_from_motion(uav70, uav_records, fault):
    sim = uav70
    pipe, rows, events, _ = _run(sim, _attitude_fault(uav_records, fault), pipeline_config(sim))
    t_move = _first_motion_s(sim)
    print(fault, "first motion", t_move, pipe.health()["yaw_gsf"], events[-6:])
    print([(round(t), round(h, 1), inj) for t, inj, _, h in rows[::50]])
    good = [t for t, _, _, h in rows if abs(h) < 5.0 and t > t_move]
    assert good and good[0] <= t_move + 30.0
    # the wrong heading is never injected in motion, and nothing injected is far off
    assert all(abs(h) < 60.0 for t, i, _, h in rows if i and t > t_move)
    assert max(e for _, i, e, _ in rows if i) < 2.0
    resets = sum("heading reset" in text for _, text in events)
    assert resets == pipe.heading.heading_resets
    if fault == "none":
        assert pipe.counters["init: heading from the yaw from motion"] >= 1
        assert not any(i for t, i, _, _ in rows if t < t_move)     # no heading at all before the motion
    else:
        assert resets >= 1 or pipe.counters["ATTITUDE yaw no longer trusted"] == 1
        assert not pipe.heading.attitude_yaw_trusted


@pytest.fixture(scope="module")
def car60():
    from sitl.fly import load_sim
    return load_sim("nhc", 0, 60.0)


@pytest.mark.parametrize("fault", ["none", "yaw180"])
def test_car_heading_from_motion(car60, fault):
    """The car (15 s at rest, then driving), loose GPS_RAW_INT fusion (no base, 1 Hz)."""
    sim = car60
    records = _attitude_fault(flight_records(sim, 60.0, tight=False, corrections=False), fault)
    pipe, rows, events, _ = _run(sim, records, pipeline_config(sim, tight=False, corrections=False))
    t_move = _first_motion_s(sim)
    print(fault, "first motion", t_move, pipe.health()["yaw_gsf"], events[-6:])
    print([(round(t), round(h, 1), inj, round(e, 2)) for t, inj, e, h in rows[::50]])
    good = [t for t, _, _, h in rows if abs(h) < 5.0 and t > t_move]
    assert good and good[0] <= t_move + 30.0
    assert all(abs(h) < 60.0 for t, i, _, h in rows if i and t > t_move)
    assert max(e for _, i, e, _ in rows if i) < 2.0
    if fault == "yaw180":
        assert not pipe.heading.attitude_yaw_trusted


def _outage_then_backlog(records, t0, outage_s, backlog_s):
    """No GNSS at all (RXM-RAWX, GPS_RAW_INT) over ``outage_s`` (from the start), then the raw epochs
    of the ``backlog_s`` seconds after it delivered all at once at its end (a receiver's buffer
    read late), after the GPS_RAW_INT of the same seconds."""
    a, b = (t0 + x for x in outage_s)
    c = t0 + backlog_s
    out, held = [], []
    for kind, t_ns, data in records:
        t = t_ns * 1e-9
        gps_raw = kind == "mavlink" and data[0] == 0xFD and \
            int.from_bytes(data[7:10], "little") == mav.MAVLINK_MSG_ID_GPS_RAW_INT
        if (kind == "ubx" or gps_raw) and a <= t < b:
            continue
        if kind == "ubx" and b <= t < c:
            held.append((kind, t_ns, data))
            continue
        if held and t >= c:
            out += [(k, int(c * 1e9), d) for k, _, d in held]
            held = []
        out.append((kind, t_ns, data))
    return out


def test_a_late_burst_of_epochs_after_an_outage_does_not_mislead_the_yaw_from_motion(uav70, uav_records):
    """After a 15-s GNSS outage the yaw-from-motion bank starts over; the epochs of the next 5 s
    then arrive in one burst (the GPS port claimed again, its backlog read).  Their velocities are
    seconds old where the bank predicts the present: fused, they converged a restarted bank 125 deg
    off in a straight leg of the rtk flight, and it withheld a good RTK solution to the end.  They
    are not fused; the bank converges on the loose fixes and the epochs after the burst."""
    sim = uav70
    t0 = float(sim.truth.t_gps[0])
    records = _outage_then_backlog(uav_records, t0, (20.0, 35.0), 40.0)
    pipe, rows, events, _ = _run(sim, records, pipeline_config(sim))
    print(pipe.health()["yaw_gsf"], events[-6:])
    assert pipe.heading.gsf.gap_restarts >= 1
    assert pipe.counters["yaw from motion: velocity too old or out of order (not fused)"] >= 3
    assert pipe.counters["solutions withheld: heading contradicts the yaw from motion"] < 25    # 1 s at 25 Hz
    assert all(abs(h) < 10.0 for t, _, _, h in rows if t > 42.0)
    # injected again, to the end (fused, the burst's velocities withheld 117 of these)
    assert all(i for t, i, _, _ in rows if t > 44.0)
