"""``python -m sitl px4``: a real PX4 (v1.15 SITL, SIH physics) flies on the companion's estimate.

1. starts PX4 SIH (quad X) from the shared folder with ``deploy/px4-vision.params`` set at boot,
   unchanged, and reads every parameter of it back (serial-port ones do not exist on SITL);
2. runs ``companion run`` on PX4's onboard link (``udpin:127.0.0.1:14540+N``) with
   ``deploy/companion.toml`` changed only in its connection, log directory and GNSS source
   ("none": GPS_RAW_INT of PX4's own GPS, loosely coupled) -- as ``python -m sitl ardupilot``;
3. waits on the ground (``--duration``), then streams OFFBOARD setpoints, switches to OFFBOARD,
   arms (PX4 refuses while EKF2 settles: retried), climbs, flies the box at ``--speed`` with a
   moving setpoint and velocity feed-forward, and lands (NAV_LAND);
4. scores against SIH's truth (HIL_STATE_QUATERNION) what PX4 reports on its GCS link: our
   estimates (forwarded by PX4), EKF2's LOCAL_POSITION_NED, its control-status flags (polled with
   PX4's ``listener``), STATUSTEXT, HEARTBEAT; figures under the ArduPilot harness's keys.

Ctrl-C stops the flight; every process started here is stopped on the way out.
"""
from __future__ import annotations

import math
import struct
import shutil
import sys
import threading
import time
from pathlib import Path

from . import ardupilot_score as S
from .ardupilot import SUMMARY_KEYS, _save_records, report, say
from .ardupilot_procs import REPO, CompanionProcess, companion_config
from .px4_gcs import OFFBOARD, Px4Gcs, mode_name
from .px4_procs import Px4Sitl, dist_problem, find_dist, hardware_only, read_params
from .px4_result import score

DEPLOY = REPO / "deploy"
PARAM_FILE = DEPLOY / "px4-vision.params"
AUTO_LAND = (4 << 16) | (6 << 24)
INT_PARAM_TYPES = {1: "<B", 2: "<b", 3: "<H", 4: "<h", 5: "<I", 6: "<i"}


def param_value(msg) -> float:
    """PARAM_VALUE's value: PX4 sends integer parameters bytewise in the float field."""
    fmt = INT_PARAM_TYPES.get(msg.param_type)
    if fmt is None:
        return float(msg.param_value)
    raw = struct.pack("<f", msg.param_value)
    return float(struct.unpack(fmt, raw[:struct.calcsize(fmt)])[0])


def check_params(gcs: Px4Gcs, wanted: dict[str, float], timeout_s: float = 2.0) -> tuple[dict, list]:
    """({name: problem}, [serial-port names SITL lacks]) for the parameter file read back."""
    problems, absent_hw = {}, []
    for name, value in wanted.items():
        got = None
        for _ in range(3):
            gcs.conn.mav.param_request_read_send(gcs.target_system, 1, name.encode(), -1)
            t_end = time.monotonic() + timeout_s / 3
            while time.monotonic() < t_end and got is None:
                msg = gcs.conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.1)
                if msg is not None and msg.param_id.rstrip("\x00") == name:
                    got = param_value(msg)
            if got is not None:
                break
        if got is None:
            if hardware_only(name):
                absent_hw.append(name)
            else:
                problems[name] = "does not exist on this firmware"
        elif not math.isclose(got, value, rel_tol=1e-6, abs_tol=1e-6):
            problems[name] = f"is {got:g}, file says {value:g}"
    return problems, absent_hw


def measure_imu_noise(gcs: Px4Gcs, rate_hz: float, seconds: float = 6.0) -> dict | None:
    """White noise of SIH's IMU as the companion will receive it (HIGHRES_IMU at ``rate_hz``,
    vehicle at rest before arming): per-axis standard deviations, and the worst axis as random
    walks (sd x sqrt(sample interval)), the units of filter.gyro_arw / accel_vrw."""
    import numpy as np
    msg_id = mav_id("HIGHRES_IMU")
    gcs.command_ack(mav_cmd("MAV_CMD_SET_MESSAGE_INTERVAL"), msg_id, 1e6 / rate_hz, timeout_s=1.0)
    n0 = len(gcs.records.get("HIGHRES_IMU", ()))
    gcs.pump(seconds)
    gcs.command_ack(mav_cmd("MAV_CMD_SET_MESSAGE_INTERVAL"), msg_id, -1, timeout_s=1.0)   # off again
    imu = [m for _, m in gcs.records.get("HIGHRES_IMU", ())[n0:]]
    if len(imu) < 50:
        return None
    t = np.array([m.time_usec for m in imu]) * 1e-6
    acc = np.array([[m.xacc, m.yacc, m.zacc] for m in imu])
    gyro = np.array([[m.xgyro, m.ygyro, m.zgyro] for m in imu])
    dt = float(np.median(np.diff(t)))
    sa, sg = acc.std(axis=0), gyro.std(axis=0)
    return {"samples": len(imu), "interval_s": round(dt, 4), "accel_sd_mps2": [round(float(x), 3) for x in sa],
            "gyro_sd_radps": [round(float(x), 4) for x in sg],
            "accel_vrw_mps_per_sqrt_s": float(sa.max() * math.sqrt(dt)),
            "gyro_arw_rad_per_sqrt_s": float(sg.max() * math.sqrt(dt))}


def mav_id(name: str) -> int:
    from pymavlink import mavutil
    return getattr(mavutil.mavlink, f"MAVLINK_MSG_ID_{name}")


def mav_cmd(name: str) -> int:
    from pymavlink import mavutil
    return getattr(mavutil.mavlink, name)


def imu_noise_overrides(deploy_toml: str, noise: dict | None) -> dict[str, str]:
    """filter.gyro_arw / accel_vrw for the simulator's IMU: the measured noise where it exceeds
    deploy/'s (a real IMU's); never below deploy/'s values."""
    import tomllib
    if noise is None:
        return {}
    f = tomllib.loads(deploy_toml)["filter"]
    out = {}
    for key in ("gyro_arw_rad_per_sqrt_s", "accel_vrw_mps_per_sqrt_s"):
        if noise[key] > f[key]:
            out[f"filter.{key}"] = f"{noise[key]:.4g}"
    return out


class FlagPoller:
    """EKF2's estimator_status_flags every ``period_s`` in a thread (``listener`` takes ~0.1 s;
    the setpoint stream must not wait for it): [(t_mono_s, {flag: bool})]."""

    def __init__(self, sitl: Px4Sitl, period_s: float = 2.0):
        self.sitl, self.period_s = sitl, period_s
        self.samples: list[tuple[float, dict]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ekf2-flags", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            flags = self.sitl.estimator_flags()
            if flags is not None:
                self.samples.append((time.monotonic(), flags))

    def last(self) -> dict:
        return self.samples[-1][1] if self.samples else {}

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)


class Px4Flight:
    """Ground wait and flight through :class:`Px4Gcs`; events in host monotonic time."""

    def __init__(self, gcs: Px4Gcs, companion: CompanionProcess, flags: FlagPoller):
        self.gcs = gcs
        self.companion = companion
        self.flags = flags
        self.events: dict[str, float] = {}
        self.commanded: list[tuple[float, int]] = []       # (t, custom_mode) we asked for
        self.corners_reached = 0
        self.arm_attempts = 0

    def _check_companion(self) -> None:
        if not self.companion.alive():
            raise RuntimeError(f"companion exited (code {self.companion.proc.returncode}):\n{self.companion.tail()}")

    def ground(self, duration_s: float, progress_every_s: float = 15.0) -> None:
        say(f"on the ground for {duration_s:.0f} s")
        t_end = time.monotonic() + duration_s
        while time.monotonic() < t_end:
            self.gcs.pump(min(progress_every_s, t_end - time.monotonic()))
            self._check_companion()
            say("  " + self.status_line())

    def wait_for_external_nav(self, timeout_s: float = 90.0) -> float | None:
        """Pump until EKF2 fuses our position (cs_ev_pos), as an operator waits for "nav OK"
        before arming: PX4 SIH streams ATTITUDE (which the companion needs for its heading) only
        once EKF2 has aligned, 30-40 s after boot, so a short ground phase can end before our first
        estimate.  Seconds waited, None on timeout."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout_s:
            if self.flags.last().get("cs_ev_pos"):
                waited = time.monotonic() - t0
                if waited > 0.5:
                    say(f"  EKF2 fuses our position after {waited:.1f} s more; {self.status_line()}")
                return waited
            self.gcs.pump(0.5)
            self._check_companion()
        say(f"  EKF2 does not fuse our position after {timeout_s:.0f} s more; {self.status_line()}")
        return None

    def status_line(self) -> str:
        g = self.gcs
        n_est = len(g.records.get("VISION_POSITION_ESTIMATE", ()))
        f = self.flags.last()
        on = [k[3:] for k in ("cs_ev_pos", "cs_ev_hgt", "cs_ev_yaw", "cs_gps", "cs_mag_hdg", "cs_mag_3d",
                              "cs_baro_hgt", "cs_inertial_dead_reckoning") if f.get(k)]
        yaw = ""
        hil, est = g.last("HIL_STATE_QUATERNION"), g.last("VISION_POSITION_ESTIMATE")
        if hil is not None and est is not None:
            true_yaw = S.quat_yaw(hil.attitude_quaternion)
            yaw = f", yaw error {math.degrees(float(S.wrap_pi(est.yaw - true_yaw))):+.1f} deg"
        return (f"estimates {n_est}{yaw}, EKF2 {'+'.join(on) or '-'}, mode {mode_name(g.custom_mode)}, "
                f"{'armed' if g.armed else 'disarmed'}")

    def _hold_here(self) -> tuple[float, float, float]:
        n, e, d = self.gcs.local_ned()
        self.gcs.setpoint = ((n, e, d), (0.0, 0.0, 0.0))
        return n, e, d

    def arm(self, timeout_s: float = 120.0) -> bool:
        say("OFFBOARD and arm")
        self._hold_here()
        self.gcs.pump(1.0)               # setpoints flowing before OFFBOARD is asked for
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            self._check_companion()
            if self.gcs.main_mode != OFFBOARD:
                self._hold_here()
                self.commanded.append((time.monotonic(), OFFBOARD << 16))
                self.gcs.set_px4_mode(OFFBOARD)
            self.arm_attempts += 1
            self.gcs.arm()
            self.gcs.pump(1.0)
            if self.gcs.armed:
                self.events["armed"] = time.monotonic()
                say(f"  armed (attempt {self.arm_attempts}) in {mode_name(self.gcs.custom_mode)}")
                return True
            self.gcs.pump(2.0)
        say("  arming refused")
        return False

    def takeoff(self, alt_m: float, timeout_s: float = 40.0) -> bool:
        say(f"takeoff to {alt_m:.0f} m")
        self.events["takeoff"] = time.monotonic()
        # from where the vehicle is now: EKF2 resets its position when it starts fusing ours, which
        # can fall between the hold point taken for OFFBOARD and the arming (a 35-m "take-off")
        n0, e0, z0 = self._hold_here()
        self.gcs.setpoint = ((n0, e0, z0 - alt_m), (0.0, 0.0, 0.0))
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end and self.gcs.armed:
            self._check_companion()
            self.gcs.pump(0.2)
            ned = self.gcs.local_ned()
            if ned is not None and z0 - ned[2] >= 0.95 * alt_m:
                say(f"  at {z0 - ned[2]:.1f} m; {self.status_line()}")
                return True
        say("  takeoff did not reach its height")
        return False

    def box(self, side_m: float, speed_mps: float, legs: int = 4, leg_timeout_s: float = 30.0,
            reach_m: float = 1.0) -> bool:
        """Each leg: the setpoint moves from corner to corner at ``speed_mps`` (velocity fed
        forward), then waits on the corner until the vehicle is within ``reach_m``."""
        n0, e0, d0 = self.gcs.setpoint[0]
        corners = [(n0 + side_m, e0), (n0 + side_m, e0 + side_m), (n0, e0 + side_m), (n0, e0)][:legs]
        say(f"box: {legs} leg(s) of {side_m:.0f} m at {speed_mps:.0f} m/s")
        start = (n0, e0)
        for i, (n, e) in enumerate(corners):
            dn, de = n - start[0], e - start[1]
            length = math.hypot(dn, de)
            un, ue = dn / length, de / length
            t0 = time.monotonic()
            t_end = t0 + length / speed_mps + leg_timeout_s
            while True:
                self._check_companion()
                s = min(speed_mps * (time.monotonic() - t0), length)
                v = speed_mps if s < length else 0.0
                self.gcs.setpoint = ((start[0] + un * s, start[1] + ue * s, d0), (un * v, ue * v, 0.0))
                self.gcs.pump(0.05)
                pn, pe, _ = self.gcs.local_ned()
                if s >= length and math.hypot(pn - n, pe - e) <= reach_m:
                    self.corners_reached += 1
                    say(f"  corner {i + 1} reached; {self.status_line()}")
                    break
                if time.monotonic() > t_end or not self.gcs.armed or self.gcs.main_mode != OFFBOARD:
                    say(f"  corner {i + 1} not reached (at {pn - n:+.1f} {pe - e:+.1f} m from it, "
                        f"mode {mode_name(self.gcs.custom_mode)})")
                    return False
            start = (n, e)
        return True

    def land(self, timeout_s: float = 90.0) -> bool:
        say("LAND")
        self.events["land"] = time.monotonic()
        self.commanded.append((time.monotonic(), AUTO_LAND))
        self.gcs.land()
        t_end = time.monotonic() + 5.0
        while time.monotonic() < t_end and self.gcs.custom_mode != AUTO_LAND:
            self.gcs.pump(0.1)
        self.gcs.setpoint = None          # after the mode change: no offboard loss
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end and self.gcs.armed:
            self.gcs.pump(0.5)
        self.events["disarmed"] = time.monotonic()
        if self.gcs.armed:
            say("  still armed after the landing timeout")
            return False
        say("  landed and disarmed")
        return True

    def mission(self, alt_m: float, side_m: float, speed_mps: float, legs: int) -> tuple[bool, bool]:
        """Arm, take off, fly the box, land: (armed, box completed)."""
        armed = self.arm()
        box_done = armed and self.takeoff(alt_m) and self.box(side_m, speed_mps, legs)
        if self.gcs.armed:
            self.land()
        else:
            self.events.setdefault("disarmed", time.monotonic())
        self.gcs.setpoint = None
        self.gcs.pump(2.0)
        return armed, bool(box_done)


def console_warnings(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith(("WARN", "ERROR"))]


#: what `--ulog` keeps: every IMU sample, the receiver, the autopilot's estimates and SIH's truth
#: (about 1 MB a minute instead of 15 for PX4's default profile)
ULOG_TOPICS = {"sensor_combined": 0, "vehicle_gps_position": 0, "vehicle_attitude": 50, "vehicle_status": 200,
               "vehicle_global_position": 50, "vehicle_global_position_groundtruth": 20,
               "vehicle_attitude_groundtruth": 20}


def run(*, duration_s: float = 120.0, px4_dir: str | None = None, out_dir: str = "out/px4", alt_m: float = 10.0,
        side_m: float = 20.0, speed_mps: float = 5.0, legs: int = 4,
        overrides: dict[str, str] | None = None, ulog: bool = False) -> dict:
    dist = find_dist(px4_dir)
    problem = dist_problem(dist)
    if problem:
        raise RuntimeError(problem)
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    params = read_params(PARAM_FILE)
    sitl = Px4Sitl(dist, params, out / "px4", ulog_topics=ULOG_TOPICS if ulog else None)
    companion = gcs = flags = None
    flight = None
    res: dict = {"autopilot": "px4", "output": "vision", "param_file": str(PARAM_FILE), "px4_dir": str(dist),
                 "config_overrides": dict(overrides or {}), "ground_s": duration_s}
    try:
        say(f"starting PX4 SIH from {dist} with {PARAM_FILE.name} (instance {sitl.instance})")
        sitl.start()
        gcs = Px4Gcs(sitl.port("gcs_local"), sitl.port("display_remote"), target_system=sitl.system_id,
                     on_statustext=lambda t: say(f"  PX4: {t}"))
        gcs.wait_heartbeat()
        res["param_problems"], res["params_absent_on_sitl"] = check_params(gcs, params)
        for name, why in res["param_problems"].items():
            say(f"  parameter {name} {why}")
        gcs.request_streams()
        deploy_toml = (DEPLOY / "companion.toml").read_text()
        import tomllib
        imu_rate_hz = tomllib.loads(deploy_toml)["mavlink"]["imu_rate_hz"]
        res["imu_noise_measured"] = measure_imu_noise(gcs, imu_rate_hz)
        overrides = {**imu_noise_overrides(deploy_toml, res["imu_noise_measured"]), **dict(overrides or {})}
        say(f"  SIH IMU noise at rest: {res['imu_noise_measured']}")
        companion = _start_companion(out, sitl.port("onboard_remote"), sitl.system_id, overrides)
        res["config_overrides"] = companion.overrides
        flags = FlagPoller(sitl)
        flags.start()
        flight = Px4Flight(gcs, companion, flags)
        gcs.pump(3.0)
        cpu0, t_cpu0 = companion.cpu_s(), time.monotonic()
        flight.ground(duration_s)
        res["ground_wait_for_ev_pos_s"] = flight.wait_for_external_nav()
        gcs.request_message("GPS_GLOBAL_ORIGIN")
        res["armed"], res["box_completed"] = flight.mission(alt_m, side_m, speed_mps, legs)
        gcs.request_message("GPS_GLOBAL_ORIGIN")
        gcs.pump(1.0)
        cpu1, t_cpu1 = companion.cpu_s(), time.monotonic()
        res["corners_reached"] = flight.corners_reached
        res["arm_attempts"] = flight.arm_attempts
        res["companion_cpu_pct"] = (round(100.0 * (cpu1 - cpu0) / (t_cpu1 - t_cpu0), 1)
                                    if cpu0 is not None and cpu1 is not None else None)
        res["companion_origin"] = companion.origin()
    except KeyboardInterrupt:
        say("interrupted: stopping")
        res["interrupted"] = True
    finally:
        if flags is not None:
            flags.stop()
        if companion is not None:
            res["companion_exit_code"] = companion.stop()
        if gcs is not None:
            gcs.close()
        res["px4_exit_code"] = sitl.stop()
        say("PX4 and companion stopped")
        if ulog and sitl.ulog_files():
            res["ulog"] = str(out / "flight.ulg")
            shutil.copyfile(sitl.ulog_files()[-1], res["ulog"])
            say(f"ULog of the flight: {res['ulog']}")
    if flight is not None:
        res["events_mono_s"] = flight.events
        res.update(score(gcs.records, gcs.statustext, res, flag_samples=flags.samples,
                         console_lines=console_warnings(sitl.log_text()), states=gcs.states, modes=gcs.modes,
                         commanded=flight.commanded))
        _save_records(gcs, out / "records.pkl")
    res["companion_log"] = str(out / "companion.log")
    res["sitl_log"] = str(sitl.log_path)
    return res


def _start_companion(out: Path, port: int, target_system: int, overrides) -> CompanionProcess:
    """``companion run`` on PX4's onboard link with deploy/companion.toml, changed only where it must
    be: connection, log directory, GNSS source, and what is SIH's, not a real vehicle's: its GPS's
    output latency, and (``overrides`` from :func:`imu_noise_overrides`) its IMU's noise."""
    over = dict(overrides or {})
    # SIH's simulated receiver stamps GPS_RAW_INT with the fix's time of validity (no output
    # latency: gps_raw_best_lag_s of the result measures it); deploy's 0.075 s is ArduPilot SITL's
    # u-blox, whose fixes PX4's would otherwise be taken as 75 ms older than they are
    over.setdefault("gnss.gps_raw_latency_s", "0.0")
    if target_system != 1:              # a second PX4 instance is system 2 (not the case by default)
        over.setdefault("mavlink.target_system", str(target_system))
    cfg_text = companion_config((DEPLOY / "companion.toml").read_text(), connection=f"udpin:127.0.0.1:{port}",
                                log_dir=str(out / "fieldlog"), gnss_source="none", output_mode="vision",
                                overrides=over)
    cfg_path = out / "companion.toml"
    cfg_path.write_text(cfg_text)
    companion = CompanionProcess(cfg_path, out / "companion.log")
    companion.overrides = over
    say(f"starting companion run --config {cfg_path} on PX4's onboard link (udpin:127.0.0.1:{port}), "
        f"with {over}")
    companion.start()
    return companion


def format_result(r: dict) -> str:
    lines = ["", "python -m sitl px4: result"]
    for k in SUMMARY_KEYS + ("rms_h_m_ground", "yaw_err_deg_ground_last", "yaw_rms_deg_flight",
                             "ekf_yaw_rms_deg_ground", "ekf_origin_minus_ours_m", "ekf_flags_flight",
                             "estimate_latency_ms", "gps_raw_best_lag_s", "param_problems", "params_absent_on_sitl"):
        lines.append(f"  {k:24s} {r.get(k)}")
    return "\n".join(lines)


def cmd_px4(args) -> int:
    try:
        res = run(duration_s=args.duration, px4_dir=args.px4_dir, out_dir=args.out, legs=args.legs,
                  side_m=args.side, alt_m=args.alt, speed_mps=args.speed,
                  overrides=dict(kv.split("=", 1) for kv in args.set or ()), ulog=getattr(args, "ulog", False))
    except RuntimeError as exc:
        print(f"sitl px4: {exc}", file=sys.stderr)
        return 2
    return report(res, format_result(res), args.json)


def add_arguments(p, *, out_default: str = "out/px4") -> None:
    """The options of ``python -m sitl px4`` (also taken by ``sitl ardupilot --autopilot px4``)."""
    p.add_argument("--px4-dir", help="PX4 SITL folder with start_sih.sh and bin/px4 (default $COMPANION_PX4_DIR, "
                                     "else <repo>/../shared/px4)")
    if not any(a.dest == "duration" for a in p._actions):
        p.add_argument("--duration", type=float, default=120.0,
                       help="seconds on the ground before arming (default 120)")
        p.add_argument("--json", help="write the figures as JSON here")
        p.add_argument("--out", default=out_default, help="directory for configs and logs")
        p.add_argument("--legs", type=int, default=4, choices=(1, 2, 3, 4), help="box legs to fly (default 4)")
        p.add_argument("--side", type=float, default=20.0, help="box side, m")
        p.add_argument("--alt", type=float, default=10.0, help="takeoff height, m")
        p.add_argument("--speed", type=float, default=5.0, help="horizontal speed, m/s")
        p.add_argument("--ulog", action="store_true",
                       help="keep a ULog of the flight (IMU, GPS, estimates, SIH truth) as OUT/flight.ulg")
        p.add_argument("--set", action="append", metavar="SECTION.KEY=TOML",
                       help="experiment: override one key of deploy/companion.toml, e.g. filter.zupt_enabled=true")


def register(subparsers) -> None:
    p = subparsers.add_parser("px4", help="PX4 SITL (SIH) flies a box in OFFBOARD on the companion's estimate, scored")
    add_arguments(p)
    p.set_defaults(func=cmd_px4)


__all__ = ["cmd_px4", "register", "run"]
