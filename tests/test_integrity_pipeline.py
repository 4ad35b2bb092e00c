"""Integrity at pipeline level, from MAVLink/UBX/RTCM bytes of a simulated flight fed offline
(deterministic, no sockets or clocks): IMU faults are bridged and the injected error stays
bounded; a filter that is wrong stops injecting at once, re-initialises from GNSS and resumes only
after a consistent window; GPS_RAW_INT latency and its missing vertical velocity; no mode flapping."""
from __future__ import annotations

import itertools
import math
import os
from types import SimpleNamespace

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mav  # noqa: E402

from companion.config import loads_config  # noqa: E402
from companion.nav.earth import C_n_e, dcm_to_euler, ecef_to_geodetic  # noqa: E402
from companion.pipeline import NavPipeline  # noqa: E402

G = 9.80665
GPS_EPOCH_UNIX_S = 315964800
LEAP_S = 13


def flight_records(sim, duration_s, *, tight=True, imu_fault=None, gps_raw_latency_s=0.06, corrections=True,
                   t_start_s=0.0):
    """(kind, t_rx_ns, bytes) of an ArduPilot-like stream, in arrival order: HIGHRES_IMU at the
    simulated rate, SYSTEM_TIME/HEARTBEAT at 1 Hz, ATTITUDE at 10 Hz, GPS_RAW_INT per epoch
    (``gps_raw_latency_s`` after it), RXM-RAWX (60 ms after the epoch) and RTCM (150 ms).
    ``imu_fault(t_rel, w_b, f_b) -> (w_b, f_b)`` corrupts rates."""
    from sitl.autopilot import rawx_frame
    from sitl.caster import Rtcm1004Encoder, encode_1005, encode_1019
    enc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    t0 = float(sim.truth.t_gps[0])
    boot0 = math.floor(t0) - 30.0
    rng = np.random.default_rng(5)
    pending = []          # (t_gps available, kind, bytes)
    if tight:
        for ep in sim.rover_epochs:
            pending.append((ep.t_gps + 0.06, "ubx", rawx_frame(ep, LEAP_S)))
    if corrections:
        rtcm = Rtcm1004Encoder(sim.base.station_id)
        first = True
        for ep in sim.base_epochs:
            out = bytearray()
            if first:
                out += encode_1005(sim.base.station_id, sim.base.r_e)
                for e in sim.ephemerides:
                    out += encode_1019(e)
                first = False
            out += rtcm.encode(ep)
            pending.append((ep.t_gps + 0.15, "rtcm", bytes(out)))
    for ep in sim.rover_epochs:
        r = sim.antenna_at(ep.t_gps) + rng.normal(0.0, 0.7, 3)
        _, v, _ = sim.truth_at(ep.t_gps)
        lat, lon, h = ecef_to_geodetic(r)
        v_n = C_n_e(lat, lon).T @ v
        cog = (math.degrees(math.atan2(v_n[1], v_n[0])) + 360.0) % 360.0
        t_rx = ep.t_gps + gps_raw_latency_s
        msg = enc.gps_raw_int_encode(int(round((t_rx - boot0) * 1e6)), 3, int(round(math.degrees(lat) * 1e7)),
                                     int(round(math.degrees(lon) * 1e7)), int(round(h * 1000)), 120, 180,
                                     int(round(math.hypot(v_n[0], v_n[1]) * 100)), int(round(cog * 100)) % 36000,
                                     len(ep.observations), int(round(h * 1000)), 1050, 1750, 300, 0, 0)
        pending.append((t_rx, "mavlink", bytes(msg.pack(enc))))
    pending.sort(key=lambda p: p[0])
    out = []
    i = 0
    t_end = t0 + duration_s
    next_1hz = next_10hz = -1e18
    for s in sim.imu:
        t = s.t_gps
        if t > t_end:
            break
        if t < t0 + t_start_s:
            continue
        while i < len(pending) and pending[i][0] <= t:
            out.append((pending[i][1], int(pending[i][0] * 1e9), pending[i][2]))
            i += 1
        boot_us = int(round((t - boot0) * 1e6))
        if t >= next_1hz:
            next_1hz = t + 1.0
            unix_us = int(round((boot0 + (boot_us // 1000) * 1e-3 + GPS_EPOCH_UNIX_S - LEAP_S) * 1e6))
            out.append(("mavlink", int(t * 1e9), bytes(enc.system_time_encode(unix_us, boot_us // 1000).pack(enc))))
            status = mav.MAV_STATE_STANDBY if t - t0 < 8.0 else mav.MAV_STATE_ACTIVE
            out.append(("mavlink", int(t * 1e9), bytes(enc.heartbeat_encode(
                mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, status).pack(enc))))
        if t >= next_10hz:
            next_10hz = t + 0.1
            r, v, C = sim.truth_at(t)
            lat, lon, _ = ecef_to_geodetic(r)
            roll, pitch, yaw = dcm_to_euler(C_n_e(lat, lon).T @ C)
            out.append(("mavlink", int(t * 1e9), bytes(enc.attitude_encode(boot_us // 1000, roll, pitch, yaw,
                                                                           0, 0, 0).pack(enc))))
        w, f = s.dtheta_b / s.dt_s, s.dv_b / s.dt_s
        if imu_fault is not None:
            w, f = imu_fault(t - t0, w.copy(), f.copy())
        out.append(("mavlink", int(t * 1e9), bytes(enc.highres_imu_encode(
            boot_us, f[0], f[1], f[2], w[0], w[1], w[2], 0, 0, 0, 0, 0, 0, 25.0, 0x3F, 0).pack(enc))))
    return out


def pipeline_config(sim, *, tight=True, corrections=True, extra=""):
    from sitl.fly import companion_config_toml
    caster = SimpleNamespace(port=2101, mountpoint="SIM", user="", password="") if corrections else None
    text = companion_config_toml(sim, udp_port=14550, caster=caster, log_dir="/tmp/unused", rate_hz=25.0,
                                 output_mode="vision", max_sigma_h_m=2.0, max_sigma_v_m=4.0, leap_seconds=LEAP_S,
                                 imu_message="HIGHRES_IMU", gnss_source="mavlink_serial_control" if tight else "none")
    return loads_config(text + extra, "sim.toml")


def fly_offline(sim, records, config, *, screen=True, on_solution=None, setup=None):
    """Feed the records; per solution: (t_rel, inject, horizontal error of the IMU position, status)."""
    pipe = NavPipeline(config)
    if setup is not None:
        setup(pipe)
    if not screen:
        pipe.engine.imu_screen = None
    t0 = float(sim.truth.t_gps[0])
    lat0, lon0, _ = ecef_to_geodetic(sim.truth.r_e[0])
    up = -C_n_e(lat0, lon0)[:, 2]
    rows, events = [], []
    for kind, t_ns, data in records:
        for sol in pipe.feed(kind, t_ns, data):
            r_true, _, _ = sim.truth_at(sol.t_gps)
            d = sol.r_e - r_true
            rows.append((sol.t_gps - t0, bool(sol.extras["inject"]), float(np.linalg.norm(d - up * (d @ up))),
                         sol.status))
            if on_solution is not None:
                on_solution(pipe, sol)
        events += [(t_ns * 1e-9 - t0, text) for _, text in pipe.drain_events()]
    return pipe, rows, events


@pytest.fixture(scope="module")
def uav70():
    from sitl.fly import load_sim
    return load_sim("uav", 0, 70.0)


def _max_injected(rows, t_from):
    errs = [e for t, inj, e, _ in rows if inj and t >= t_from]
    return max(errs) if errs else math.nan


FAULT_T_S = 40.0


def _fault(kind):
    def f(t_rel, w, a):
        k = int(round((t_rel - FAULT_T_S) * 200.0))
        if kind == "16g" and k == 0:
            a[0] = 16.0 * G
        elif kind == "4xfs" and 0 <= k < 4:
            a[2] = -32.767 * G          # RAW_IMU's full scale, as the issue measured
        elif kind == "gyro2000" and k == 0:
            w[0] = math.radians(2000.0)
        elif kind == "1e5" and k == 0:
            a[0] = 1e5
        return w, a
    return f


# ---------------------------------------------------------------------------------------------
# IMU faults: bridged, injected error as in the clean flight


@pytest.fixture(scope="module")
def clean_run(uav70):
    cfg = pipeline_config(uav70)
    return fly_offline(uav70, flight_records(uav70, 70.0), cfg)


@pytest.mark.parametrize("kind", ["16g", "4xfs", "gyro2000", "1e5"])
def test_imu_fault_in_flight_is_bridged_and_injection_stays_accurate(uav70, clean_run, kind):
    cfg = pipeline_config(uav70)
    pipe, rows, events = fly_offline(uav70, flight_records(uav70, 70.0, imu_fault=_fault(kind)), cfg)
    _, clean_rows, _ = clean_run
    worst, worst_clean = _max_injected(rows, FAULT_T_S), _max_injected(clean_rows, FAULT_T_S)
    print(f"{kind}: max injected horizontal error after the fault {worst:.3f} m (clean flight {worst_clean:.3f} m)")
    assert pipe.engine.counters["imu_screen.samples_bridged"] == (4 if kind == "4xfs" else 1)
    assert worst < worst_clean + 0.05
    assert sum(r[1] for r in rows) == sum(r[1] for r in clean_rows)       # nothing withheld either
    assert pipe.engine.reset_counter == 1 and not any("re-init" in e for _, e in events)
    assert pipe.health()["engine"]["imu_screen.samples_bridged"] >= 1     # reported


def test_unscreened_imu_fault_is_caught_by_the_divergence_monitor(uav70):
    """Without the screen (what the screen prevents): the 16-g sample corrupts the state; the
    monitor stops injecting at the first inconsistent epoch, re-initialises and resumes."""
    cfg = pipeline_config(uav70)
    pipe, rows, events = fly_offline(uav70, flight_records(uav70, 70.0, imu_fault=_fault("16g")), cfg, screen=False)
    texts = [e for _, e in events]
    print(texts)
    assert any(e.startswith("nav re-init: diverged") for e in texts)
    assert pipe.engine.reset_counter == 2 and pipe.counters["re-init: diverged"] == 1
    assert pipe.counters["re-init: sensor biases kept"] == 1
    late = [r for r in rows if r[0] > 55.0]
    assert sum(r[1] for r in late) >= 0.8 * len(late)                    # resumed
    assert max(r[2] for r in late if r[1]) < 2.0


# ---------------------------------------------------------------------------------------------
# a wrong state / a contradicting IMU: diverged -> no injection -> re-init -> probation -> injection


def _displace_at(t_rel_s, d_n_m):
    """on_solution hook: move the filter's position (and its history) d_n_m north at t_rel_s,
    leaving its covariance as it was: a wrong state that the filter believes."""
    done = []

    def hook(pipe, sol):
        eng = pipe.engine
        if done or sol.t_gps - eng.t_gps != 0.0 or sol.t_gps < t0_of(pipe) + t_rel_s:
            return
        lat, lon, _ = ecef_to_geodetic(eng.r_e)
        d_e = C_n_e(lat, lon) @ np.array([d_n_m, 0.0, 0.0])
        eng.r_e = eng.r_e + d_e
        eng._hist.correct(d_e, None, None)
        done.append(sol.t_gps)
    hook.done = done
    return hook


def t0_of(pipe):
    return pipe._sim_t0


@pytest.mark.slow
def test_wrong_state_stops_injection_at_once_reinitialises_and_resumes_after_a_window():
    """The filter's position moves 30 m while its velocity stays right (a corrupted state).  Once
    the TDCP after the step agrees with the INS again this looks like a spoofer's GNSS position
    jump, so the filter may first hold the GNSS position back (up to ``hold_max_s``, 30 s) before it
    concludes the INS was wrong; either way it stops injecting at once, re-initialises from GNSS
    exactly once, on probation, and resumes only after a consistent window."""
    from sitl.fly import load_sim
    sim = load_sim("uav", 0, 110.0)
    cfg = pipeline_config(sim)
    hook = _displace_at(40.0, 30.0)
    NavPipeline._sim_t0 = float(sim.truth.t_gps[0])
    try:
        pipe, rows, events = fly_offline(sim, flight_records(sim, 105.0), cfg, on_solution=hook)
    finally:
        del NavPipeline._sim_t0
    t_jump = hook.done[0] - float(sim.truth.t_gps[0])
    texts = [e for _, e in events]
    print(f"jump at {t_jump:.2f} s;", [(round(t, 1), e) for t, e in events if t > 30])
    first_bad = next(t for t, inj, e, st in rows if t > t_jump and st in ("suspect", "diverged"))
    resumed = next(t for t, inj, e, st in rows if t > first_bad and inj)
    print(f"first withheld {first_bad - t_jump:.2f} s after the jump, resumed {resumed - t_jump:.2f} s after it")
    assert first_bad - t_jump < 1.3                   # the next GNSS epoch (1 Hz, 60 ms late)
    assert not any(inj for t, inj, e, st in rows if first_bad <= t < resumed)
    assert sum(e.startswith("nav re-init: diverged") for e in texts) == 1
    assert pipe.engine.reset_counter == 2
    held = any("GNSS position rejected" in x for x in texts)
    assert (35.0 if held else 5.0) <= resumed - first_bad < 50.0   # (the hold,) then a consistency window
    after = [e for t, inj, e, st in rows if inj and t >= resumed]
    assert max(after) < 3.0 and after[-1] < 1.5
    h = pipe.health()
    assert h["filter"]["integrity"]["state"] == "ok" and h["engine"]["integrity.diverged"] == 1
    assert h["aid_sources"]["tdcp"]["fused"] and h["aid_sources"]["pseudorange"]["window"]["rejected"] == 0


def test_contradicting_imu_is_not_injected_for_long(uav70):
    """A gyro that goes wrong by 3 deg/s about z (below every screen limit) at 40 s: the filter
    cannot follow it (6 sigma of its bias model); it must stop injecting rather than drift."""
    def bias(t_rel, w, a):
        if t_rel >= FAULT_T_S:
            w[2] += math.radians(3.0)
        return w, a
    cfg = pipeline_config(uav70)
    pipe, rows, events = fly_offline(uav70, flight_records(uav70, 70.0, imu_fault=bias), cfg)
    texts = [e for t, e in events if t > FAULT_T_S]
    inj_err = [e for t, inj, e, st in rows if inj and t >= FAULT_T_S]
    print(f"max injected horizontal error after the gyro fault {max(inj_err):.2f} m; "
          f"{len(inj_err)} of {sum(1 for r in rows if r[0] >= FAULT_T_S)} injected; events {texts}")
    assert max(inj_err) < 3.0
    assert pipe.counters["re-init: diverged"] >= 1 or pipe.engine.counters["integrity.suspect"] >= 1

    def unmonitored(p):
        import dataclasses
        p.engine.cfg = dataclasses.replace(p.engine.cfg, integrity_enabled=False)
    _, rows_u, _ = fly_offline(uav70, flight_records(uav70, 70.0, imu_fault=bias), cfg, setup=unmonitored)
    worst_u = max(e for t, inj, e, st in rows_u if inj and t >= FAULT_T_S)
    print(f"without the monitor: {worst_u:.2f} m")
    assert worst_u > 2.0 * max(inj_err)


# ---------------------------------------------------------------------------------------------
# GPS_RAW_INT: latency, no vertical velocity; no mode flapping without corrections


def _h_rms(rows, t_from=20.0):
    e = np.array([err for t, inj, err, st in rows if t >= t_from])
    return float(np.sqrt(np.mean(e ** 2)))


def test_gps_raw_int_latency_is_applied(uav70):
    cfg = pipeline_config(uav70, tight=False, corrections=False)
    recs = flight_records(uav70, 70.0, tight=False, corrections=False, gps_raw_latency_s=0.2)
    _, rows_late, _ = fly_offline(uav70, recs, cfg)
    def with_latency(p):
        p.gps_raw_latency_s = 0.2
    pipe, rows, _ = fly_offline(uav70, recs, cfg, setup=with_latency)
    late, exact = _h_rms(rows_late), _h_rms(rows)
    print(f"loose GPS_RAW_INT, 200 ms receiver latency: horizontal RMS {late:.3f} m ignored, {exact:.3f} m applied")
    assert pipe.mode == "loose" and pipe.counters["loose fixes fused"] > 50
    assert exact < 0.8 * late


def test_no_mode_flapping_without_corrections(uav70):
    """Raw observations but no ephemerides (no corrections stream): loose GPS_RAW_INT fusion and
    one announcement of it, not a tight/loose switch every second."""
    cfg = pipeline_config(uav70, corrections=False)
    recs = flight_records(uav70, 60.0, corrections=False)
    pipe, rows, events = fly_offline(uav70, recs, cfg)
    texts = [e for _, e in events]
    print(len(texts), texts)
    assert pipe.mode == "loose" and pipe.counters["loose fixes fused"] > 40
    assert not any("tight coupling" in e for e in texts)
    # (+2: one pause of injection, and its end, at the first horizontal motion until the yaw from
    # motion confirms the ATTITUDE heading: companion.nav.yaw_gsf)
    assert len(texts) <= 4 + 2
    assert sum(r[1] for r in rows) > 0.8 * len(rows)


def test_injection_does_not_flap_when_sigma_hovers_at_the_threshold():
    from companion.config import config_from_dict
    from companion.messages import NavSolution
    pipe = NavPipeline(config_from_dict({}))
    pipe.mode = "tight"
    lim = pipe.cfg.output.max_sigma_h_m
    r = np.array([-3976219.5, 3382372.6, 3652513.0])
    injected = []
    for k in range(200):
        sig_h = lim * (1.0 + 0.05 * math.sin(0.7 * k))    # +-5 % around the threshold, many crossings
        sol = NavSolution(float(k), r, np.zeros(3), np.eye(3), np.array([sig_h / math.sqrt(2)] * 2 + [0.1]),
                          np.full(3, 0.1), np.full(3, 0.01), "nav")
        injected.append(pipe._finish(sol).extras["inject"])
    events = pipe.drain_events()
    print(events)
    assert injected[0] and not all(injected)
    # one stop, then no resumption above 80 % of the threshold: two announcements, not one per crossing
    assert len(events) == 2 and sum(a != b for a, b in itertools.pairwise(injected)) == 1


def test_broadcast_klobuchar_is_adopted_for_the_standalone_models():
    from companion.config import config_from_dict
    pipe = NavPipeline(config_from_dict({}))
    assert pipe.engine.cfg.klobuchar is None
    klob = ((1.1e-8, -2.2e-8, -3.6e-6, 6.0e-6), (163840.0, 81920.0, -131072.0, 196608.0))
    # what the LNAV assembler keeps from subframe 4 page 18 (companion.gnss.lnav, proposed)
    pipe.ubx.ephemerides.klobuchar = klob
    from companion.messages import GpsEphemeris
    pipe._feed_messages([GpsEphemeris("G05", 1315, 0, 0, *([0.0] * 18))])
    assert pipe.engine.cfg.klobuchar == klob
    assert pipe.counters["klobuchar from the navigation message"] == 1


def _spoofed(sim, t_from_s, t_to_s, d_ned_m):
    """The simulation with its rover epochs as a spoofer makes them between t_from and t_to: every
    code and carrier moved by the range change of a position offset by ``d_ned_m`` (consistent
    across satellites, so no single row looks wrong)."""
    import copy
    import dataclasses
    from sitl.sky import light_time_range
    t0 = float(sim.truth.t_gps[0])
    ephs = {e.sat: e for e in sim.ephemerides}
    out = []
    for ep in sim.rover_epochs:
        if t_from_s <= ep.t_gps - t0 < t_to_s:
            r = sim.antenna_at(ep.t_gps)
            lat, lon, _ = ecef_to_geodetic(r)
            d_e = C_n_e(lat, lon) @ np.asarray(d_ned_m, float)
            obs = []
            for o in ep.observations:
                _, _, r_s, _, _, _ = light_time_range(ephs[o.sat], ep.t_gps, r)
                dm = -float((r_s - r) @ d_e) / float(np.linalg.norm(r_s - r))
                obs.append(dataclasses.replace(o, pseudorange_m=o.pseudorange_m + dm,
                                               carrier_cycles=o.carrier_cycles + dm / o.wavelength_m))
            ep = dataclasses.replace(ep, observations=tuple(obs))
        out.append(ep)
    sim2 = copy.copy(sim)
    sim2.rover_epochs = out
    return sim2


@pytest.mark.slow
def test_spoofed_position_is_held_back_not_adopted():
    """A spoofer moves the GNSS position 100 m north for 20 s, codes and carriers alike.  The TDCP
    still agrees with the INS, so the filter holds the GNSS position back instead of re-initialising
    onto it: nothing is injected during the hold, no injected estimate is more than 1 m off, the
    ground station is told, and injection resumes once the GNSS agrees again."""
    from sitl.fly import load_sim
    sim = _spoofed(load_sim("uav", 0, 90.0), 40.0, 60.0, (100.0, 0.0, 0.0))
    pipe, rows, events = fly_offline(sim, flight_records(sim, 88.0), pipeline_config(sim))
    injected = [(t, e) for t, inj, e, _ in rows if inj]
    assert max(e for _, e in injected) < 1.0
    texts = [text for _, text in events]
    assert any("GNSS position rejected" in x for x in texts) and any("agrees with INS again" in x for x in texts)
    assert not any("re-init" in x for x in texts), texts
    assert any(t > 62.0 for t, _ in injected) and sum(1 for t, _ in injected if t > 62.0) > 0.9 * 25 * (88 - 63)
    assert pipe.engine.counters["integrity.position_hold"] == 1
