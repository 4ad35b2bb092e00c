"""``python -m sitl ardupilot``: a real ArduCopter (SITL) flies on the companion's estimate.

1. starts ArduPilot's own ArduCopter SITL binary with ``deploy/``'s parameter file, unchanged
   (``ardupilot-vision.parm``; ``ardupilot-gps-input.parm`` for ``--output gps_input``), and
   checks every parameter of it back;
2. runs ``companion run`` as its own process on SERIAL2 with ``deploy/companion.toml`` changed only
   in its connection, log directory, GNSS source and output mode.  GNSS source: ``--gnss
   gps_raw_int`` (default) "none", GPS_RAW_INT, loosely coupled, since SITL's u-blox sends no raw
   observations; ``--gnss raw`` "serial" on the pseudo-terminal of our simulated receiver
   (:mod:`sitl.ardupilot_gnss`: it follows SITL's truth on SERIAL1 and emits UBX RXM-RAWX/SFRBX,
   its base station RTCM MSM4 + 1005 through an NTRIP caster), with the corrections source set to
   that caster: tightly coupled DGPS + TDCP.  SITL then starts with ``--start-time`` (its GPS
   clock is that plus its boot time, which the receiver's time tags follow);
3. waits on the ground (``--duration``), arms, takes off in GUIDED, flies a box, lands;
4. scores, from SITL's truth (SIMSTATE) and what the autopilot reports on SERIAL0: our estimates
   (routed there by ArduPilot), its own LOCAL_POSITION_NED, EKF_STATUS_REPORT and STATUSTEXT.

Ctrl-C stops the flight; every process started here is stopped on the way out.
"""
from __future__ import annotations

import json
import math
import re
import sys
import time
from pathlib import Path

from . import ardupilot_score as S
from .ardupilot_gcs import MODE_NAMES, Gcs
from .ardupilot_procs import (
    REPO,
    ArduCopterSitl,
    CompanionProcess,
    GnssReceiverProcess,
    binary_problem,
    companion_config,
    find_binary,
)
from .ardupilot_result import ESTIMATE_TYPES, companion_figures, score

DEPLOY = REPO / "deploy"
PARM_FILES = {"vision": "ardupilot-vision.parm", "odometry": "ardupilot-vision.parm",
              "gps_input": "ardupilot-gps-input.parm"}
MODE_NAMES_COMPANION = {0: "init", 1: "tight", 2: "loose"}      # CC_MODE (companion.io.gcs_values)
GNSS_SOURCES = {"gps_raw_int": "none", "raw": "serial"}           # --gnss -> gnss.source
SCENARIO_MARGIN_S = 900.0      # the receiver's epochs cover the ground wait plus this (arming, the box, landing)
EKF_FLAG_NAMES = ("att", "vel_h", "vel_v", "pos_h_rel", "pos_h_abs", "pos_v_abs", "pos_v_agl", "const_pos",
                  "pred_pos_h_rel", "pred_pos_h_abs", "uninitialized", "gps_glitch")


def say(text: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {text}", flush=True)


def read_parm(path: Path) -> dict[str, float]:
    out = {}
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            name, value = re.split(r"[\s,=]+", line, maxsplit=1)
            out[name] = float(value)
    return out


def check_params(gcs: Gcs, wanted: dict[str, float], timeout_s: float = 2.0) -> dict[str, str]:
    """Read every parameter of the parm file back: {name: problem} for missing or different ones."""
    problems = {}
    for name, value in wanted.items():
        gcs.conn.mav.param_request_read_send(gcs.target_system, 1, name.encode(), -1)
        t_end = time.monotonic() + timeout_s
        got = None
        while time.monotonic() < t_end and got is None:
            msg = gcs.conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.2)
            if msg is not None and msg.param_id.rstrip("\x00") == name:
                got = msg.param_value
        if got is None:
            problems[name] = "does not exist on this firmware"
        elif not math.isclose(got, value, rel_tol=1e-6, abs_tol=1e-6):
            problems[name] = f"is {got:g}, file says {value:g}"
    return problems


class Flight:
    """The ground wait and the flight, driven through :class:`Gcs`; events in host monotonic time."""

    def __init__(self, gcs: Gcs, companion: CompanionProcess, output: str, receiver: GnssReceiverProcess | None = None):
        self.gcs = gcs
        self.companion = companion
        self.receiver = receiver
        self.output = output
        self.events: dict[str, float] = {}
        self.corners_reached = 0
        self.arm_attempts = 0

    def _check_companion(self) -> None:
        for child in (self.companion, self.receiver):
            if child is not None and not child.alive():
                raise RuntimeError(f"{child.name} exited (code {child.proc.returncode}):\n{child.tail()}")

    def ground(self, duration_s: float, progress_every_s: float = 15.0) -> None:
        say(f"on the ground for {duration_s:.0f} s")
        t_end = time.monotonic() + duration_s
        while time.monotonic() < t_end:
            self.gcs.pump(min(progress_every_s, t_end - time.monotonic()))
            self._check_companion()
            say("  " + self.status_line())

    def status_line(self) -> str:
        g = self.gcs
        n_est = len(g.records.get(ESTIMATE_TYPES[self.output], ()))
        ekf = g.last("EKF_STATUS_REPORT")
        flags = [n for i, n in enumerate(EKF_FLAG_NAMES) if ekf is not None and ekf.flags & (1 << i)]
        yaw = ""
        sim, est = g.last("SIMSTATE"), g.last(ESTIMATE_TYPES[self.output])
        if sim is not None and est is not None and self.output != "gps_input":
            ours = est.yaw if self.output == "vision" else S.quat_yaw(est.q)
            yaw = f", yaw error {math.degrees(float(S.wrap_pi(ours - sim.yaw))):+.1f} deg"
        mode = g.named_value("CC_MODE")
        mode = "" if mode is None else f", ours {MODE_NAMES_COMPANION.get(int(mode), mode)}"
        return (f"estimates {n_est}{yaw}{mode}, EKF flags {'+'.join(flags) or '-'}, "
                f"mode {MODE_NAMES.get(g.custom_mode, g.custom_mode)}, {'armed' if g.armed else 'disarmed'}")

    def arm(self, timeout_s: float = 90.0) -> bool:
        say("GUIDED and arm")
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            self._check_companion()
            if self.gcs.custom_mode != 4:
                self.gcs.set_mode("GUIDED")
            self.arm_attempts += 1
            self.gcs.arm()
            self.gcs.pump(1.0)
            if self.gcs.armed:
                self.events["armed"] = time.monotonic()
                say(f"  armed (attempt {self.arm_attempts})")
                return True
            self.gcs.pump(2.0)
        say("  arming refused")
        return False

    def takeoff(self, alt_m: float, timeout_s: float = 40.0) -> bool:
        say(f"takeoff to {alt_m:.0f} m")
        self.events["takeoff"] = time.monotonic()
        z0 = (self.gcs.local_ned() or (0, 0, 0))[2]
        self.gcs.takeoff(alt_m)
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end and self.gcs.armed:
            self.gcs.pump(0.2)
            ned = self.gcs.local_ned()
            if ned is not None and z0 - ned[2] >= 0.95 * alt_m:
                say(f"  at {z0 - ned[2]:.1f} m")
                return True
        say("  takeoff did not reach its height")
        return False

    def box(self, side_m: float, speed_mps: float, legs: int = 4, leg_timeout_s: float = 30.0,
            reach_m: float = 1.0) -> bool:
        n0, e0, d0 = self.gcs.local_ned()
        corners = [(n0 + side_m, e0), (n0 + side_m, e0 + side_m), (n0, e0 + side_m), (n0, e0)][:legs]
        say(f"box: {legs} leg(s) of {side_m:.0f} m at {speed_mps:.0f} m/s")
        self.gcs.set_speed(speed_mps)
        for i, (n, e) in enumerate(corners):
            t_end = time.monotonic() + leg_timeout_s
            next_send = 0.0
            while True:
                self._check_companion()
                if time.monotonic() >= next_send:
                    self.gcs.goto_local(n, e, d0)
                    next_send = time.monotonic() + 1.0
                self.gcs.pump(0.1)
                pn, pe, _ = self.gcs.local_ned()
                if math.hypot(pn - n, pe - e) <= reach_m:
                    self.corners_reached += 1
                    say(f"  corner {i + 1} reached; {self.status_line()}")
                    break
                if time.monotonic() > t_end or not self.gcs.armed:
                    say(f"  corner {i + 1} not reached (at {pn - n:+.1f} {pe - e:+.1f} m from it)")
                    return False
        return True

    def mission(self, alt_m: float, side_m: float, speed_mps: float, legs: int) -> tuple[bool, bool]:
        """Arm, take off, fly the box, land: (armed, box completed)."""
        armed = self.arm()
        box_done = armed and self.takeoff(alt_m) and self.box(side_m, speed_mps, legs)
        if self.gcs.armed:
            self.land()
        else:
            self.events.setdefault("disarmed", time.monotonic())
        self.gcs.pump(2.0)
        return armed, bool(box_done)

    def land(self, timeout_s: float = 90.0) -> bool:
        say("LAND")
        self.events["land"] = time.monotonic()
        self.gcs.set_mode("LAND")
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end and self.gcs.armed:
            self.gcs.pump(0.5)
        self.events["disarmed"] = time.monotonic()
        if self.gcs.armed:
            say("  still armed after the landing timeout")
            return False
        say("  landed and disarmed")
        return True


def run(*, duration_s: float = 120.0, output: str = "vision", sitl_bin: str | None = None,
        out_dir: str = "out/ardupilot", alt_m: float = 10.0, side_m: float = 20.0, speed_mps: float = 5.0,
        legs: int = 4, overrides: dict[str, str] | None = None, gnss: str = "gps_raw_int",
        gnss_rate_hz: float = 1.0) -> dict:
    binary = find_binary(sitl_bin)
    problem = binary_problem(binary)
    if problem:
        raise RuntimeError(problem)
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    parm = DEPLOY / PARM_FILES[output]
    start_unix = int(time.time()) if gnss == "raw" else None
    sitl = ArduCopterSitl(binary, [parm], out / "sitl", start_time_unix_s=start_unix)
    companion = receiver = None
    gcs = None
    res: dict = {"output": output, "gnss": gnss, "parm_file": str(parm), "sitl_bin": str(binary),
                 "config_overrides": dict(overrides or {}), "ground_s": duration_s, "sitl_start_time_unix_s": start_unix}
    try:
        say(f"starting ArduCopter SITL {binary} with {parm.name} (instance {sitl.instance})")
        sitl.start()
        gcs = Gcs(sitl.port(0), on_statustext=lambda t: say(f"  AP: {t}"))
        gcs.wait_heartbeat()
        res["param_problems"] = check_params(gcs, read_parm(parm))
        for name, why in res["param_problems"].items():
            say(f"  parameter {name} {why}")
        gcs.request_streams()
        source = {}
        if gnss == "raw":
            receiver = GnssReceiverProcess(out / "gnss", sitl_port=sitl.port(1), start_time_unix_s=start_unix,
                                           duration_s=duration_s + SCENARIO_MARGIN_S, rate_hz=gnss_rate_hz)
            say(f"starting the GNSS receiver (truth from SERIAL1, tcp:127.0.0.1:{sitl.port(1)})")
            ready = receiver.start()
            res["gnss_receiver"] = {k: ready[k] for k in ("satellites", "sky", "rate_hz", "t0_gps")}
            say(f"  UBX on {receiver.slave_path}, RTCM via {ready['caster']['kind']} on "
                f"127.0.0.1:{ready['caster']['port']}/{ready['caster']['mountpoint']}, "
                f"{len(ready['satellites'])} GPS satellites")
            source = raw_gnss_keys(receiver.slave_path, ready["caster"])
        companion = _start_companion(out, sitl.port(2), output, overrides, GNSS_SOURCES[gnss], source)
        flight = Flight(gcs, companion, output, receiver)
        gcs.pump(3.0)
        cpu0, t_cpu0 = companion.cpu_s(), time.monotonic()
        rx_cpu0 = receiver.cpu_s() if receiver is not None else None
        flight.ground(duration_s)
        gcs.request_message("GPS_GLOBAL_ORIGIN")
        res["armed"], res["box_completed"] = flight.mission(alt_m, side_m, speed_mps, legs)
        cpu1, t_cpu1 = companion.cpu_s(), time.monotonic()
        if rx_cpu0 is not None and receiver.cpu_s() is not None:
            res["gnss_receiver_cpu_pct"] = round(100.0 * (receiver.cpu_s() - rx_cpu0) / (t_cpu1 - t_cpu0), 1)
        res["corners_reached"] = flight.corners_reached
        res["companion_cpu_pct"] = (round(100.0 * (cpu1 - cpu0) / (t_cpu1 - t_cpu0), 1)
                                    if cpu0 is not None and cpu1 is not None else None)
        res["companion_origin"] = companion.origin()
        res["events_mono_s"] = flight.events
    except KeyboardInterrupt:
        say("interrupted: stopping")
        res["interrupted"] = True
    finally:
        if companion is not None:
            res["companion_exit_code"] = companion.stop()
        if receiver is not None:
            res["gnss_receiver_exit_code"] = receiver.stop()
            res.setdefault("gnss_receiver", {}).update(receiver.result() or {})
        if gcs is not None:
            gcs.close()
        sitl.stop()
        say("SITL and companion stopped")
    res.update(companion_figures(out / "fieldlog"))
    if gcs is not None:
        res.update(score(gcs.records, gcs.statustext, res, output))
        _save_records(gcs, out / "records.pkl")
    if gnss == "raw":
        res.update(companion_health(out / "fieldlog"))
    res["companion_log"] = str(out / "companion.log")
    res["sitl_log"] = str(sitl.log_path)
    return res


def raw_gnss_keys(pty_path: str, caster: dict) -> dict[str, str]:
    """The GNSS source's and the corrections source's keys for ``--gnss raw``: the receiver's
    pseudo-terminal, the caster (NTRIP revision and everything else as shipped)."""
    q = json.dumps
    return {"gnss.serial.port": q(pty_path), "corrections.source": q("ntrip"),
            "corrections.ntrip.host": q("127.0.0.1"), "corrections.ntrip.port": str(int(caster["port"])),
            "corrections.ntrip.mountpoint": q(caster["mountpoint"]), "corrections.ntrip.user": q(caster["user"]),
            "corrections.ntrip.password": q(caster["password"])}


def companion_health(fieldlog_dir: Path) -> dict:
    """What the companion's field log says at the end (its last health record): the mode, the
    IMU time offset it estimated and its GNSS counters, for the JSON's details."""
    from companion.io.fieldlog import read_field_log
    last = None
    try:
        for rec in read_field_log(fieldlog_dir):
            if rec.kind == "event":
                obj = json.loads(rec.payload)
                if obj.get("event") in ("health", "stop") and "health" in obj:
                    last = obj["health"]
    except (OSError, ValueError) as exc:
        return {"companion_health_error": str(exc)}
    return {} if last is None else {"companion_health": last}


def _start_companion(out: Path, port: int, output: str, overrides, gnss_source: str = "none",
                     source_keys: dict[str, str] | None = None) -> CompanionProcess:
    """``companion run`` on SITL's SERIAL2 with deploy/companion.toml, changed only where it must be:
    connection, log directory, GNSS source (and, for raw GNSS, its port and the corrections
    caster), output mode; ``overrides`` are the experiments of ``--set``."""
    cfg_text = companion_config((DEPLOY / "companion.toml").read_text(), connection=f"tcp:127.0.0.1:{port}",
                                log_dir=str(out / "fieldlog"), gnss_source=gnss_source, output_mode=output,
                                overrides={**(source_keys or {}), **(overrides or {})})
    cfg_path = out / "companion.toml"
    cfg_path.write_text(cfg_text)
    cfg_path.chmod(0o600)          # it may hold the caster's password (the companion warns otherwise)
    companion = CompanionProcess(cfg_path, out / "companion.log")
    say(f"starting companion run --config {cfg_path} on SERIAL2 (tcp:127.0.0.1:{port})")
    companion.start()
    return companion


def _save_records(gcs: Gcs, path: Path) -> None:
    """Everything the ground station recorded, as {type: [(t_mono_s, fields)]}, for re-scoring."""
    import pickle
    recs = {k: [(t, m.to_dict()) for t, m in v] for k, v in gcs.records.items()}
    recs["STATUSTEXT"] = list(gcs.statustext)
    try:
        with path.open("wb") as fh:
            pickle.dump(recs, fh, protocol=pickle.HIGHEST_PROTOCOL)
    except (OSError, pickle.PicklingError) as exc:
        say(f"could not save the recording to {path}: {exc}")


SUMMARY_KEYS = ("armed", "box_completed", "ext_nav_used", "rms_h_m", "ekf_rms_h_m", "yaw_rms_deg_ground",
                "max_error_h_m", "estimate_rate_hz", "companion_cpu_pct", "failsafes")


def format_result(r: dict) -> str:
    lines = ["", "python -m sitl ardupilot: result"]
    for k in SUMMARY_KEYS + ("rms_h_m_ground", "yaw_err_deg_ground_last", "yaw_rms_deg_flight",
                             "ekf_yaw_rms_deg_ground", "ekf_origin_minus_ours_m", "origin_confirmed",
                             "origin_mismatch_m", "gps_port", "param_problems"):
        lines.append(f"  {k:24s} {r.get(k)}")
    return "\n".join(lines)


def cmd_ardupilot(args) -> int:
    if args.autopilot == "px4":         # the same flight on PX4 SITL: sitl/px4.py
        from .px4 import cmd_px4
        if args.out == "out/ardupilot":
            args.out = "out/px4"
        return cmd_px4(args)
    try:
        res = run(duration_s=args.duration, output=args.output, sitl_bin=args.sitl_bin, out_dir=args.out,
                  legs=args.legs, side_m=args.side, alt_m=args.alt, speed_mps=args.speed,
                  overrides=dict(kv.split("=", 1) for kv in args.set or ()), gnss=args.gnss,
                  gnss_rate_hz=args.gnss_rate)
    except RuntimeError as exc:
        print(f"sitl ardupilot: {exc}", file=sys.stderr)
        return 2
    return report(res, format_result(res), args.json)


def report(res: dict, text: str, json_path: str | None) -> int:
    """Print a flight's result, write its JSON (the summary keys, then the details) and return
    the exit status: 0 flown (armed, box completed, external navigation used, no failsafe), 1 not,
    130 interrupted.  Shared by the ArduPilot and PX4 flights."""
    print(text)
    if json_path:
        obj = {k: res.get(k) for k in SUMMARY_KEYS}
        obj["details"] = {k: v for k, v in res.items() if k not in SUMMARY_KEYS}
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        Path(json_path).write_text(json.dumps(obj, indent=2, default=str))
        print(f"wrote {json_path}")
    if res.get("interrupted"):
        return 130
    ok = res.get("armed") and res.get("box_completed") and res.get("ext_nav_used") and not res.get("failsafes")
    return 0 if ok else 1


def register(subparsers) -> None:
    p = subparsers.add_parser("ardupilot", help="ArduCopter SITL flies a box on the companion's estimate, scored")
    p.add_argument("--duration", type=float, default=120.0, help="seconds on the ground before arming (default 120)")
    p.add_argument("--output", default="vision", choices=tuple(PARM_FILES))
    p.add_argument("--gnss", default="gps_raw_int", choices=tuple(GNSS_SOURCES),
                   help="gps_raw_int: the autopilot's GPS_RAW_INT, loosely coupled (default); raw: our simulated "
                        "receiver on SITL's truth (UBX RXM-RAWX/SFRBX on a pseudo-terminal) and base station "
                        "(RTCM MSM4 + 1005 through an NTRIP caster): tightly coupled DGPS + TDCP")
    p.add_argument("--gnss-rate", type=float, default=1.0, metavar="HZ",
                   help="--gnss raw: epochs per second of the receiver and the base (default 1, a u-blox "
                        "receiver's default; 5 and 10 work too)")
    p.add_argument("--json", help="write the figures as JSON here")
    p.add_argument("--sitl-bin", help="ArduCopter SITL binary (default $COMPANION_ARDUPILOT_BIN, "
                                      "else <repo>/../shared/ardupilot/arducopter)")
    p.add_argument("--out", default="out/ardupilot", help="directory for configs and logs")
    p.add_argument("--legs", type=int, default=4, choices=(1, 2, 3, 4), help="box legs to fly (default 4)")
    p.add_argument("--side", type=float, default=20.0, help="box side, m")
    p.add_argument("--alt", type=float, default=10.0, help="takeoff height, m")
    p.add_argument("--speed", type=float, default=5.0, help="horizontal speed, m/s")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=TOML",
                   help="experiment: override one key of deploy/companion.toml, e.g. filter.zupt_enabled=true")
    p.add_argument("--autopilot", default="ardupilot", choices=("ardupilot", "px4"),
                   help="px4: the same flight on PX4 SITL (SIH) in OFFBOARD, as python -m sitl px4")
    from .px4 import add_arguments
    add_arguments(p)
    p.set_defaults(func=cmd_ardupilot)
