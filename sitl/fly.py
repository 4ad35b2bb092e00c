"""``python -m sitl fly``: the whole system on loopback, scored against the truth.

* simulates the scenario (``sitl.simulate``; cached as a pickle under ``~/.cache/companion-sitl``);
* starts the base station (:class:`sitl.caster.RtcmSource`) behind an NTRIP caster (RTKLIB
  ``str2str`` when installed, else :class:`sitl.caster.MiniNtripCaster`);
* writes a configuration (MAVLink ``udpin`` on a free port, raw GNSS through SERIAL_CONTROL on
  GPS1, NTRIP corrections, filter noise from :func:`sitl.tuning.tuning_for` -- the simulator's own
  sensor models, nothing tuned on the truth) and starts ``companion run`` as its own process
  (``python -m companion.run_cli run --config ...``);
* runs the emulated autopilot (:class:`sitl.autopilot.EmulatedAutopilot`) in real time x
  ``speedup`` once the companion's HEARTBEAT arrives;
* scores the estimates the autopilot actually received: position error against the truth at the
  GPS time of the IMU sample each estimate is stamped with (VISION_POSITION_ESTIMATE NED is turned
  back into ECEF with the origin the autopilot has (its GPS_GLOBAL_ORIGIN), inverting ArduPilot's spherical
  ``get_distance_NED``), latency = arrival of the estimate minus the emulator's send time of that
  IMU sample, CPU and RSS of the companion process from ``/proc``.

Rates are per *simulated* second (equal to wall-clock rates at ``--speedup 1``).
"""
from __future__ import annotations

import asyncio
import dataclasses
import json
import math
import os
import pickle
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from companion.nav.earth import C_n_e, ecef_to_geodetic, geodetic_to_ecef

LOCATION_SCALING_FACTOR_M = 0.011131884502145034
CACHE_DIR = Path(os.environ.get("COMPANION_SITL_CACHE", Path.home() / ".cache" / "companion-sitl"))


def load_sim(scenario: str, seed: int, duration_s: float | None, imu_rate_hz: float | None = None):
    """The simulated flight (cached); ``imu_rate_hz``: the scenario's IMU at another rate (same noise
    densities), e.g. a 400-Hz autopilot."""
    from .scenario import build_scenario
    from .simulate import simulate
    scn = build_scenario(scenario)
    if duration_s is not None and duration_s < scn.duration_s:
        scn = dataclasses.replace(scn, duration_s=float(duration_s))
    rate_tag = ""
    if imu_rate_hz is not None and float(imu_rate_hz) != scn.imu.rate_hz:
        scn = dataclasses.replace(scn, imu=dataclasses.replace(scn.imu, rate_hz=float(imu_rate_hz)))
        rate_tag = f"-imu{float(imu_rate_hz):g}"
    if getattr(scn, "systems", "G") != "G":        # a moved sky's revision: no stale pickle of an older one
        from .sky_multignss import SKY_REVISION
        rate_tag += f"-sky{SKY_REVISION}"
    key = CACHE_DIR / f"{scenario}-s{seed}-d{scn.duration_s:g}{rate_tag}.pkl"
    try:
        with key.open("rb") as fh:
            return pickle.load(fh)
    except Exception:
        pass
    sim = simulate(scn, seed)
    try:
        CACHE_DIR.mkdir(parents=True, exist_ok=True)
        tmp = key.with_suffix(f".{os.getpid()}.tmp")      # parallel test workers write their own
        with tmp.open("wb") as fh:
            pickle.dump(sim, fh, protocol=pickle.HIGHEST_PROTOCOL)
        tmp.replace(key)
    except Exception:
        pass
    return sim


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def companion_config_toml(sim, *, udp_port: int, caster, log_dir: str, rate_hz: float, output_mode: str,
                          max_sigma_h_m: float, max_sigma_v_m: float, leap_seconds: int, imu_message: str,
                          gnss_source: str = "mavlink_serial_control", imu_units: int = 1,
                          moving_baseline_b_m=None, gps_yaw_sigma_deg: float | None = None,
                          named_value_rate_hz: float | None = None, max_hpl_m: float | None = None) -> str:
    from .tuning import tuning_for
    t = tuning_for(sim.scenario)
    n = t.noise
    la = [float(x) for x in sim.lever_arm_b]
    corr = "none" if caster is None else "ntrip"
    lines = [
        "[mavlink]", f'connection = "udpin:127.0.0.1:{udp_port}"', f'imu_message = "{imu_message}"',
        f"imu_rate_hz = {float(sim.scenario.imu.rate_hz)}", "attitude_rate_hz = 10.0", "gps_raw_rate_hz = 5.0",
        "link_timeout_s = 3.0",
        *([f"imu_cluster = {json.dumps([imu_message, 'SCALED_IMU2', 'SCALED_IMU3'][:imu_units])}"] if imu_units > 1 else []),
        "",
        "[gnss]", f'source = "{gnss_source}"', 'serial_control_device = "GPS1"',
        "serial_control_poll_interval_s = 0.02", f"lever_arm_b_m = [{la[0]!r}, {la[1]!r}, {la[2]!r}]",
        f"leap_seconds = {leap_seconds}",
        *([f"moving_baseline_b_m = {json.dumps([float(x) for x in moving_baseline_b_m])}"]
          if moving_baseline_b_m is not None else []),
        *([f"gps_raw_yaw_sigma_deg = {float(gps_yaw_sigma_deg)!r}"] if gps_yaw_sigma_deg is not None else []),
        "",
        "[corrections]", f'source = "{corr}"', "forward_to_autopilot = false", "",
    ]
    if caster is not None:
        lines += ["[corrections.ntrip]", 'host = "127.0.0.1"', f"port = {caster.port}",
                  f'mountpoint = "{caster.mountpoint}"', f'user = "{caster.user}"', f'password = "{caster.password}"',
                  "version = 1", "timeout_s = 10.0", ""]
    lines += [
        "[output]", f'mode = "{output_mode}"', f"rate_hz = {float(rate_hz)}", "set_ekf_origin = true",
        f"max_sigma_h_m = {float(max_sigma_h_m)}", f"max_sigma_v_m = {float(max_sigma_v_m)}",
        *([f"named_value_rate_hz = {float(named_value_rate_hz)!r}"] if named_value_rate_hz is not None else []),
        *([f"max_hpl_m = {float(max_hpl_m)!r}"] if max_hpl_m is not None else []), "",
        "[filter]",
        f"gyro_arw_rad_per_sqrt_s = {n.gyro_arw_rad_per_sqrt_s!r}",
        f"accel_vrw_mps_per_sqrt_s = {n.accel_vrw_mps_per_sqrt_s!r}",
        f"gyro_bias_rw_radps_per_sqrt_s = {n.gyro_bias_rw_radps_per_sqrt_s!r}",
        f"accel_bias_rw_mps2_per_sqrt_s = {n.accel_bias_rw_mps2_per_sqrt_s!r}",
        f"clock_bias_psd_m2ps = {n.clock_bias_psd_m2ps!r}", f"clock_drift_psd_m2ps3 = {n.clock_drift_psd_m2ps3!r}",
        "use_pseudorange = true", f"use_dgps = {'true' if caster is not None else 'false'}", "use_tdcp = true",
        *_tuning_lines(t), f"elevation_mask_deg = {float(sim.scenario.mask_deg)}",
        *(_rtk_lines(sim.scenario, t) if caster is not None and sim.scenario.dual_frequency else []), "",
        "[log]", f'dir = "{log_dir}"', "fsync_interval_s = 1.0", "",
    ]
    return "\n".join(lines) + "\n"


def _rtk_lines(scenario, tuning) -> list[str]:
    """[filter] RTK keys for a dual-frequency scenario: on, with the single-difference phase and
    code sigmas of the scenario's two receivers (sitl.rtk_score.rtk_config: the simulator's noise
    models, as every other tuning line; nothing fitted to the truth)."""
    from .rtk_score import rtk_config
    c = rtk_config(scenario, tuning)
    return ["rtk_enabled = true", f"rtk_sigma_phase_a_m = {float(c.rtk_sigma_phase_a_m)!r}",
            f"rtk_sigma_phase_b_m = {float(c.rtk_sigma_phase_b_m)!r}",
            f"rtk_code_phase_ratio = {float(c.rtk_code_phase_ratio)!r}"]


def set_config_keys(cfg_text: str, keys: dict) -> str:
    """``cfg_text`` (the harness's TOML, one ``[section]`` header per table) with ``keys``
    ({section: {key: value}}) set: a key the section already has gets the new value, others are
    added at the section's end, a missing section is appended."""
    from companion.config import _toml_value
    lines = cfg_text.rstrip("\n").split("\n")
    for section, kv in keys.items():
        head = f"[{section}]"
        if head not in lines:
            lines += ["", head]
        start = lines.index(head) + 1
        end = start
        while end < len(lines) and not lines[end].startswith("["):
            end += 1
        for k, v in kv.items():
            line = f"{k} = {_toml_value(v)}"
            for i in range(start, end):
                if lines[i].split("=", 1)[0].strip() == k:
                    lines[i] = line
                    break
            else:
                while end > start and not lines[end - 1].strip():
                    end -= 1
                lines.insert(end, line)
                end += 1
    return "\n".join(lines) + "\n"


@dataclasses.dataclass
class FlightContext:
    """What a ``during`` task of :func:`fly` gets: the emulated autopilot (its socket, ``addr`` =
    the companion's MAVLink port, ``clock``, ``t0``), the companion's process and directories."""
    ap: object
    sim: object
    proc: subprocess.Popen
    clock: object
    out_dir: Path
    log_dir: Path
    udp_port: int

    def t_flight_s(self) -> float:
        """Simulated seconds since the start of the flight."""
        return self.clock.now_gps() - self.ap.t0

    async def until_flight_s(self, t_s: float) -> None:
        await self.clock.sleep_until(self.ap.t0 + t_s)


def _tuning_lines(t) -> list[str]:
    """Every [filter] key the scenario's tuning (sitl.tuning) sets, in TOML."""
    from companion.config import FilterConfig, _toml_value
    out = []
    for f in dataclasses.fields(FilterConfig):
        if f.name in ("use_pseudorange", "use_dgps", "use_tdcp", "elevation_mask_deg") or f.name.endswith(
                ("_per_sqrt_s", "_psd_m2ps", "_psd_m2ps3")):
            continue
        if hasattr(t, f.name):
            v = getattr(t, f.name)
            if isinstance(v, (bool, int, float, str)):
                out.append(f"{f.name} = {_toml_value(float(v) if isinstance(v, int) and not isinstance(v, bool) and isinstance(f.default, float) else v)}")
    return out


def _proc_cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as fh:
        parts = fh.read().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(parts[11]) + int(parts[12])) / ticks


def _proc_rss_mb(pid: int) -> tuple[float, float]:
    rss = hwm = float("nan")
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                rss = int(line.split()[1]) / 1024.0
            elif line.startswith("VmHWM:"):
                hwm = int(line.split()[1]) / 1024.0
    return rss, hwm


def ned_to_ecef_ardupilot(ned, origin_lat_e7: int, origin_lon_e7: int, origin_alt_mm: int) -> np.ndarray:
    """Inverse of ArduPilot's ``Location::get_distance_NED`` (as encoded by companion.io.mavlink_encode)."""
    lat0 = origin_lat_e7 * 1e-7
    lon0 = origin_lon_e7 * 1e-7
    lat = lat0 + ned[0] / LOCATION_SCALING_FACTOR_M * 1e-7
    scale = max(math.cos(math.radians(0.5 * (lat + lat0))), 0.01)
    lon = lon0 + ned[1] / (LOCATION_SCALING_FACTOR_M * scale) * 1e-7
    alt = origin_alt_mm * 1e-3 - ned[2]
    return geodetic_to_ecef(math.radians(lat), math.radians(lon), alt)


def _origin_of(r, origin):
    """The autopilot's EKF origin after this record: the GPS_GLOBAL_ORIGIN it sent (what its NED
    frame has; a SET_GPS_GLOBAL_ORIGIN it ignored does not count)."""
    if r.msg_type == "GPS_GLOBAL_ORIGIN":
        return (r.msg.latitude, r.msg.longitude, r.msg.altitude)
    return origin


def _estimate_error(ap, sim, r, origin):
    """(latency_ms, t_gps, error 3-D, error horizontal, reset_counter) of one received estimate, or
    None when it cannot be scored (no matching IMU sample, or a local estimate before the origin)."""
    mt, msg = r.msg_type, r.msg
    boot_us = msg.usec if mt == "VISION_POSITION_ESTIMATE" else msg.time_usec
    rec = ap.imu_send_record(boot_us, r.t_mono_ns)
    if rec is None:
        return None
    send_ns, t_gps = rec
    reset = None
    if mt == "GPS_INPUT":
        r_est = geodetic_to_ecef(math.radians(msg.lat * 1e-7), math.radians(msg.lon * 1e-7), msg.alt)
    else:
        if origin is None:
            return None
        r_est = ned_to_ecef_ardupilot((msg.x, msg.y, msg.z), *origin)
        reset = msg.reset_counter
    r_true, _, _ = sim.truth_at(t_gps)
    d = r_est - r_true
    lat, lon, _ = ecef_to_geodetic(r_true)
    d_n = C_n_e(lat, lon).T @ d
    return (r.t_mono_ns - send_ns) * 1e-6, t_gps, float(np.linalg.norm(d)), float(math.hypot(d_n[0], d_n[1])), reset


ESTIMATE_TYPES = ("VISION_POSITION_ESTIMATE", "ODOMETRY", "GPS_INPUT")


def scored_estimates(ap, sim):
    """(received estimate, _estimate_error of it or None) for every estimate the autopilot got."""
    origin = None
    for r in ap.received:
        origin = _origin_of(r, origin)
        if r.msg_type in ESTIMATE_TYPES:
            yield r, _estimate_error(ap, sim, r, origin)


def score(ap, sim, rate_hz: float, duration_s: float) -> dict:
    """Errors, rates and latencies of the estimates the emulated autopilot received."""
    errs3, errsh, lat_ms, t_list = [], [], [], []
    unmatched = 0
    resets = set()
    for _r, e in scored_estimates(ap, sim):
        if e is None:
            unmatched += 1
            continue
        lat_ms.append(e[0])
        t_list.append(e[1] - ap.t0)
        errs3.append(e[2])
        errsh.append(e[3])
        if e[4] is not None:
            resets.add(e[4])
    n = len(errs3)
    e3, eh = np.array(errs3), np.array(errsh)
    out = {"estimates_received": len(ap.estimates()),
           "estimate_rate_hz": round(len(ap.estimates()) / duration_s, 2),
           "estimate_rate_fraction": round(len(ap.estimates()) / (rate_hz * duration_s), 4),
           "rms_3d_m": round(float(np.sqrt(np.mean(e3 ** 2))), 4) if n else None,
           "rms_h_m": round(float(np.sqrt(np.mean(eh ** 2))), 4) if n else None,
           "p95_3d_m": round(float(np.percentile(e3, 95)), 4) if n else None,
           "latency_ms_p50": round(float(np.percentile(lat_ms, 50)), 3) if lat_ms else None,
           "latency_ms_p99": round(float(np.percentile(lat_ms, 99)), 3) if lat_ms else None,
           "first_estimate_s": round(min(t_list), 3) if t_list else None,
           "estimates_scored": n, "estimates_unmatched": unmatched,
           "max_3d_m": round(float(e3.max()), 4) if n else None,
           "reset_counters_seen": sorted(resets)}
    if t_list:
        t0 = min(t_list)
        span = max(duration_s - t0, 1e-9)
        out["estimate_rate_fraction_after_first"] = round(len(t_list) / (rate_hz * span), 4)
    out["_series"] = {"t_s": t_list, "err_3d_m": errs3, "err_h_m": errsh, "latency_ms": lat_ms}
    return out


WRONG_FIX_H_M = 0.1      # a fixed estimate whose true horizontal error exceeds this is a wrong fix


def _fix_states_by_boot_us(field_log_dir) -> dict:
    """t_boot_us -> (fix_state, n_fixed) of every solution the companion logged."""
    from companion.io.fieldlog import read_field_log
    from companion.log_records import decode_solution
    out = {}
    for rec in read_field_log(field_log_dir):
        if rec.kind == "solution":
            s = decode_solution(rec.payload)
            out[int(s.extras.get("t_boot_us", -1))] = (s.fix_state, s.n_fixed)
    return out


def rtk_score(ap, sim, field_log_dir, outages) -> dict:
    """The RTK figures of a flight, over the estimates the autopilot received (each one's fix state
    is the logged solution's of the same IMU sample; errors against the truth as :func:`score`):

    * ``first_fix_s``: flight time of the first estimate with fix state 'fixed';
    * ``rms_h_after_first_fix_m``: horizontal RMS of every estimate from the first fix on, those
      inside a rover outage (flight seconds ``outages``) left out, fixed or not; and over the
      fixed estimates only;
    * ``fixed_share``: fixed estimates / estimates from the first fix on, outside outages;
    * ``refix_after_outage_s``: per outage, from its end to the first fixed estimate after it
      (None: never again);
    * ``wrong_fixes``: fixed estimates with a true horizontal error above WRONG_FIX_H_M (and
      ``wrong_fixes_3d``: 3-D error above it);
    * ``fix_types``: GPS_INPUT fix_type counts (gps_input output only)."""
    states = _fix_states_by_boot_us(field_log_dir)
    rows = []                  # (t flight s, fix state, err 3d, err h)
    fix_types: dict = {}
    for r, e in scored_estimates(ap, sim):
        if r.msg_type == "GPS_INPUT":
            fix_types[int(r.msg.fix_type)] = fix_types.get(int(r.msg.fix_type), 0) + 1
        if e is None:
            continue
        boot_us = r.msg.usec if r.msg_type == "VISION_POSITION_ESTIMATE" else r.msg.time_usec
        rows.append((e[1] - ap.t0, states.get(int(boot_us), ("none", 0))[0], e[2], e[3]))

    def inside(t):
        return any(a <= t < b for a, b in outages)
    fixed_t = [t for t, st, _, _ in rows if st == "fixed"]
    first = min(fixed_t) if fixed_t else None
    after = [x for x in rows if first is not None and x[0] >= first and not inside(x[0])]
    eh = np.array([x[3] for x in after])
    eh_fixed = np.array([x[3] for x in after if x[1] == "fixed"])
    refix = []
    for a, b in outages:
        nxt = [t for t in fixed_t if t >= b]
        refix.append(round(min(nxt) - b, 2) if nxt else None)
    counts: dict = {}
    for x in rows:
        counts[x[1]] = counts.get(x[1], 0) + 1
    return {"first_fix_s": None if first is None else round(first, 2),
            "rms_h_after_first_fix_m": round(float(np.sqrt(np.mean(eh ** 2))), 4) if len(eh) else None,
            "rms_h_fixed_m": round(float(np.sqrt(np.mean(eh_fixed ** 2))), 4) if len(eh_fixed) else None,
            "max_h_after_first_fix_m": round(float(eh.max()), 4) if len(eh) else None,
            "fixed_share": round(len(eh_fixed) / len(eh), 4) if len(eh) else None,
            "outages_s": [list(o) for o in outages], "refix_after_outage_s": refix,
            "wrong_fixes": sum(1 for x in rows if x[1] == "fixed" and x[3] > WRONG_FIX_H_M),
            "wrong_fixes_3d": sum(1 for x in rows if x[1] == "fixed" and x[2] > WRONG_FIX_H_M),
            "estimates_by_fix_state": counts, "gps_input_fix_types": fix_types}


class _Progress:
    """Set-up steps and a status line every ``every_s`` of wall clock while the flight runs (stderr)."""

    def __init__(self, enabled: bool, every_s: float = 5.0):
        self.enabled, self.every_s = enabled, every_s
        self.t0 = time.monotonic()

    def step(self, text: str) -> None:
        if self.enabled:
            print(f"[{time.monotonic() - self.t0:6.1f} s] {text}", file=sys.stderr, flush=True)

    async def follow(self, ap, sim, duration_s: float, proc) -> None:
        """Status lines until cancelled: simulated time, estimates received, latest horizontal error."""
        if not self.enabled:
            return
        origin, seen = None, 0
        last_err_h = None
        while True:
            await asyncio.sleep(self.every_s)
            received = ap.received
            for r in received[seen:]:
                origin = _origin_of(r, origin)
                if r.msg_type in ESTIMATE_TYPES:
                    e = _estimate_error(ap, sim, r, origin)
                    if e is not None:
                        last_err_h = e[3]
            seen = len(received)
            t_sim = max(0.0, ap.clock.now_gps() - ap.t0) if ap.clock.started.is_set() else 0.0
            n_est = sum(1 for r in received if r.msg_type in ESTIMATE_TYPES)
            err = "n/a" if last_err_h is None else f"{last_err_h:.2f} m"
            state = "" if proc.poll() is None else f"  COMPANION EXITED ({proc.returncode})"
            self.step(f"flying {min(t_sim, duration_s):5.1f}/{duration_s:.0f} s  estimates {n_est}  "
                      f"horizontal error {err}{state}")


def _stop_on_signals(loop, stop: asyncio.Event, progress: _Progress) -> list:
    """First SIGINT/SIGTERM: set ``stop`` (everything this run started is then shut down and the
    result says interrupted); the handler is removed at once, so a second Ctrl-C is the default."""
    installed = []

    def on_signal(sig):
        progress.enabled = True
        progress.step(f"{signal.Signals(sig).name}: stopping the autopilot, the caster and the companion")
        for s in installed:
            loop.remove_signal_handler(s)
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, on_signal, sig)
            installed.append(sig)
        except (NotImplementedError, RuntimeError, ValueError):   # not the main thread / no signals
            pass
    return installed


async def _until(stop: asyncio.Event, aw) -> bool:
    """Await ``aw`` unless ``stop`` is set first (then cancel it); True when it completed."""
    task = asyncio.ensure_future(aw)
    stopper = asyncio.ensure_future(stop.wait())
    try:
        await asyncio.wait({task, stopper}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        stopper.cancel()
    if task.done():
        task.result()
        return True
    task.cancel()
    try:
        await task
    except (asyncio.CancelledError, Exception):
        pass
    return False


async def fly(scenario: str = "uav", duration_s: float = 120.0, speedup: float = 1.0, *, rate_hz: float = 25.0,
              seed: int = 0, out_dir: str = "out/fly", output_mode: str = "vision", max_sigma_h_m: float = 2.0,
              max_sigma_v_m: float = 4.0, faults=None, use_caster: bool = True, imu_message: str = "HIGHRES_IMU",
              gnss_source: str = "mavlink_serial_control", leap_seconds: int = 13,
              keep_companion_log: bool = True, imu_units: int = 1, max_imu_rate_hz: float | None = None,
              moving_baseline_b_m=None, gps_yaw_sigma_deg: float | None = None,
              system_time_late_s: float = 0.0, progress: bool = False, handle_signals: bool = False,
              base_outage_s: tuple[float, float] | None = None, keep_autopilot: dict | None = None,
              extra_config: str = "", named_value_rate_hz: float | None = None,
              max_hpl_m: float | None = None, caster_factory=None, config_keys: dict | None = None,
              during=None, signing_key: bytes | None = None,
              rover_outage_s: tuple[float, float] | None = None, imu_rate_hz: float | None = None) -> dict:
    """Fly once; ``progress`` prints set-up steps and status lines to stderr, ``handle_signals`` makes
    the first SIGINT/SIGTERM a clean stop (the result then has ``interrupted`` True and the figures
    of the part that was flown).  ``base_outage_s`` (start, end from the start of the flight): the
    base station sends nothing then.  ``keep_autopilot`` (a dict) receives the emulated autopilot
    and the simulation ('ap', 'sim') for scoring of one's own.  ``extra_config``: TOML sections
    appended to the companion's configuration (e.g. an ``[nmea]`` output).  ``named_value_rate_hz``:
    the companion's NAMED_VALUE_FLOAT rate (default: its configuration's), e.g. to score against
    the protection level it sends (CC_HPL); ``max_hpl_m``: its protection-level injection gate
    (default: its configuration's, ``output.max_hpl_m``).

    Hooks for ``python -m sitl attack``: ``caster_factory`` (``async f(source_port, out_dir) ->
    sitl.caster.Caster``) replaces :func:`sitl.caster.start_caster` in front of the base station;
    ``config_keys`` ({section: {key: value}}) sets keys in the companion's configuration (replacing
    the harness's own value of a key); ``during`` (``async f(FlightContext)``) runs beside the
    flight from the moment the autopilot starts streaming and is cancelled when the flight ends
    (an exception of its own fails the flight); ``signing_key`` (32 bytes): the emulated autopilot
    signs (give the companion the same key with ``config_keys``).  ``rover_outage_s`` (start,
    end from the start of the flight): the rover receiver outputs nothing then (a
    ``Faults.gnss_outage``), e.g. the rtk scenario's 30-s outage inside a flight shorter than the
    scenario's own (130-160 s).  A dual-frequency scenario (rtk) runs with RTK on and MSM7 from the
    base, and the result gains ``rtk`` (:func:`rtk_score`)."""
    from .autopilot import EmulatedAutopilot, SimClock
    from .caster import RtcmSource, start_caster
    prog = _Progress(progress)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_setup = time.monotonic()
    prog.step(f"simulating scenario '{scenario}' ({duration_s + 3.0:g} s, seed {seed}; cached in {CACHE_DIR})")
    sim = load_sim(scenario, seed, duration_s + 3.0, imu_rate_hz)
    duration_s = min(duration_s, sim.scenario.duration_s - 1.0)
    # from here on a signal is a clean stop (before, Ctrl-C interrupts the simulation at once)
    handlers = _stop_on_signals(loop, stop, prog) if handle_signals else []
    clock = SimClock(speedup)
    src = caster = proc = comp_log = ap = None
    tasks: list[asyncio.Task] = []
    interrupted = stop.is_set()
    cpu0 = cpu1 = None
    wall0 = wall1 = None
    rss = hwm = float("nan")
    setup_s = None
    udp_port = free_udp_port()
    side = None
    log_dir = out / "fieldlog"
    try:
        if use_caster and not stop.is_set():
            prog.step("starting the simulated base station and the NTRIP caster")
            base_epochs = sim.base_epochs
            if base_outage_s is not None:
                t_b0 = float(sim.truth.t_gps[0])
                base_epochs = [e for e in base_epochs
                               if not base_outage_s[0] <= e.t_gps - t_b0 < base_outage_s[1]]
            src = RtcmSource(base_epochs, sim.ephemerides, sim.base, clock,
                             observations="msm7" if sim.scenario.dual_frequency
                             or getattr(sim.scenario, "systems", "G") != "G" else "1004")
            src_port = await src.start()
            if caster_factory is not None:
                caster = await caster_factory(src_port, out)
            else:
                caster = await start_caster(src_port, log_path=str(out / "str2str.log"))
            prog.step(f"caster: {caster.kind} on 127.0.0.1:{caster.port}")
        if log_dir.exists():
            for f in log_dir.glob("*.cflog"):
                f.unlink()
        cfg_text = companion_config_toml(sim, udp_port=udp_port, caster=caster, log_dir=str(log_dir),
                                         rate_hz=rate_hz, output_mode=output_mode, max_sigma_h_m=max_sigma_h_m,
                                         max_sigma_v_m=max_sigma_v_m, leap_seconds=leap_seconds,
                                         imu_message=imu_message, gnss_source=gnss_source, imu_units=imu_units,
                                         moving_baseline_b_m=moving_baseline_b_m,
                                         gps_yaw_sigma_deg=gps_yaw_sigma_deg,
                                         named_value_rate_hz=named_value_rate_hz, max_hpl_m=max_hpl_m)
        if config_keys:
            cfg_text = set_config_keys(cfg_text, config_keys)
        cfg_path = out / "companion.toml"
        cfg_path.write_text(cfg_text + ("\n" + extra_config if extra_config else ""))
        if rover_outage_s is not None:
            from .autopilot import Faults
            faults = dataclasses.replace(faults or Faults(),
                                         gnss_outage=[*(faults.gnss_outage if faults else []), tuple(rover_outage_s)])
        ap = EmulatedAutopilot(sim, companion_port=udp_port, speedup=speedup, clock=clock, faults=faults,
                               leap_seconds=leap_seconds, imu_message=imu_message, seed=seed, imu_units=imu_units,
                               max_imu_rate_hz=max_imu_rate_hz, moving_baseline_b_m=moving_baseline_b_m,
                               gps_yaw_sigma_deg=gps_yaw_sigma_deg, system_time_late_s=system_time_late_s,
                               signing_key=signing_key)
        if not stop.is_set():
            prog.step(f"starting companion run (log {out / 'companion.log'})")
            comp_log = open(out / "companion.log", "wb")
            env = dict(os.environ, PYTHONUNBUFFERED="1")
            proc = subprocess.Popen([sys.executable, "-m", "companion.run_cli", "-v", "run", "--config",
                                     str(cfg_path)], stdout=comp_log, stderr=subprocess.STDOUT, env=env,
                                    cwd=str(Path(__file__).resolve().parent.parent))
            tasks = [asyncio.create_task(ap.run(duration_s))]
            if src is not None:
                tasks.append(asyncio.create_task(src.run()))
            prog.step("waiting for the companion's HEARTBEAT")
        if proc is not None and await _until(stop, clock.started.wait()):
            setup_s = time.monotonic() - t_setup
            prog.step(f"set up in {setup_s:.1f} s; flying {duration_s:g} s at x{speedup:g}")
            tasks.append(asyncio.create_task(prog.follow(ap, sim, duration_s, proc)))
            if during is not None:
                side = asyncio.create_task(during(FlightContext(ap=ap, sim=sim, proc=proc, clock=clock,
                                                                out_dir=out, log_dir=log_dir,
                                                                udp_port=udp_port)))
                tasks.append(side)
            if proc.poll() is None:
                cpu0, wall0 = _proc_cpu_s(proc.pid), time.monotonic()
            await _until(stop, tasks[0])
            if proc.poll() is None:
                cpu1, wall1 = _proc_cpu_s(proc.pid), time.monotonic()
                rss, hwm = _proc_rss_mb(proc.pid)
        interrupted = stop.is_set()
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        if side is not None and side.done() and not side.cancelled() and side.exception() is not None:
            raise side.exception()
        if not interrupted:
            await asyncio.sleep(0.3)
    except asyncio.CancelledError:
        interrupted = True
        raise
    finally:
        prog.step("stopping the companion, the caster and the base station")
        for t in tasks:
            t.cancel()
        _terminate(proc)
        if comp_log is not None:
            comp_log.close()
        if ap is not None:
            ap.close()
        if src is not None:
            await src.close()
        if caster is not None:
            await caster.close()
        for sig in handlers:
            if stop.is_set():
                break
            loop.remove_signal_handler(sig)
    flown_s = duration_s
    if interrupted:   # rates over the part that was flown
        flown_s = max(0.0, min(duration_s, clock.now_gps() - ap.t0)) if clock.started.is_set() else 0.0
    res = score(ap, sim, rate_hz, max(flown_s, 1e-3))
    series = res.pop("_series")
    res.update({
        "interrupted": interrupted, "flown_s": round(flown_s, 2),
        "companion_cpu_pct": round(100.0 * (cpu1 - cpu0) / (wall1 - wall0), 2) if cpu1 is not None else None,
        "companion_rss_mb": round(rss, 1), "companion_peak_rss_mb": round(hwm, 1),
        "companion_exit_code": None if proc is None else proc.returncode,
        "scenario": scenario, "seed": seed, "duration_s": duration_s, "speedup": speedup,
        "configured_rate_hz": rate_hz, "imu_rate_hz": sim.scenario.imu.rate_hz, "output_mode": output_mode,
        "caster": None if caster is None else caster.kind,
        "autopilot": {k: v for k, v in ap.counters.items() if not k.startswith("rx_") or k in (
            "rx_VISION_POSITION_ESTIMATE", "rx_SERIAL_CONTROL", "rx_TIMESYNC", "rx_COMMAND_LONG", "rx_STATUSTEXT")},
        "rtcm_source": None if src is None else dict(src.counters),
        "statustext": [r.msg.text for r in ap.received if r.msg_type == "STATUSTEXT"],
        "last_output": {r.msg_type: r.msg.to_dict() for r in ap.received if r.msg_type in ESTIMATE_TYPES},
        "field_log_dir": str(log_dir), "companion_log": str(out / "companion.log"),
        # set-up: simulation (or its cache), caster, companion start, until the autopilot streams
        "setup_s": None if setup_s is None else round(setup_s, 1),
        "run_s": round(time.monotonic() - t_setup, 1)})
    if imu_units > 1:
        res["imu_cluster"] = _final_cluster_health(log_dir)
    if use_caster and sim.scenario.dual_frequency and clock.started.is_set():
        outages = [(a - ap.t0, b - ap.t0) for a, b in sim.scenario.rover_outages]
        outages += [tuple(o) for o in (faults.gnss_outage if faults is not None else [])]
        res["rtk"] = rtk_score(ap, sim, log_dir, [o for o in outages if o[0] < flown_s])
    res["_series"] = series
    if keep_autopilot is not None:
        keep_autopilot.update(ap=ap, sim=sim)
    return res


def _terminate(proc) -> None:
    """SIGTERM, then SIGKILL after 10 s: the companion closes its field log on SIGTERM."""
    if proc is None or proc.poll() is not None:
        if proc is not None:
            proc.wait()
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _final_cluster_health(field_log_dir) -> dict | None:
    """The service's last IMU-cluster health (from the health/stop events of its field log)."""
    from companion.io.fieldlog import read_field_log
    last = None
    for rec in read_field_log(field_log_dir):
        if rec.kind == "event":
            obj = json.loads(rec.payload)
            if obj.get("event") in ("stop", "health") and "imu_cluster" in obj.get("health", {}):
                last = obj["health"]["imu_cluster"]
    return last


def format_result(r: dict) -> str:
    def f(x, fmt):
        return "n/a" if x is None else format(x, fmt)
    return "\n".join([
        f"sitl fly: scenario {r['scenario']} {r['duration_s']:.0f} s x{r['speedup']:g}, {r['output_mode']} at "
        f"{r['configured_rate_hz']:g} Hz, IMU {r['imu_rate_hz']:g} Hz, caster {r['caster']}"
        + ("  ** INTERRUPTED **" if r.get("interrupted") else ""),
        f"  estimates received {r['estimates_received']} ({f(r['estimate_rate_hz'], '.2f')} Hz, "
        f"{100 * r['estimate_rate_fraction']:.1f} % of configured; first at {f(r['first_estimate_s'], '.2f')} s)",
        f"  error: RMS 3-D {f(r['rms_3d_m'], '.3f')} m, RMS horizontal {f(r['rms_h_m'], '.3f')} m, "
        f"p95 3-D {f(r['p95_3d_m'], '.3f')} m, max {f(r['max_3d_m'], '.3f')} m",
        f"  latency p50 {f(r['latency_ms_p50'], '.2f')} ms, p99 {f(r['latency_ms_p99'], '.2f')} ms",
        f"  companion CPU {f(r['companion_cpu_pct'], '.1f')} % of one core, RSS {f(r['companion_rss_mb'], '.1f')} MB",
    ] + ([] if not r.get("rtk") else [
        "  RTK: first fix {} s; from it on, outside outages: fixed {} of the estimates, RMS_h {} m (fixed only {} m, "
        "max {} m); re-fix after the outages {} s, wrong fixes {} (3-D {})".format(
            f(r["rtk"]["first_fix_s"], ".1f"),
            "n/a" if r["rtk"]["fixed_share"] is None else f"{100 * r['rtk']['fixed_share']:.1f} %",
            f(r["rtk"]["rms_h_after_first_fix_m"], ".4f"), f(r["rtk"]["rms_h_fixed_m"], ".4f"),
            f(r["rtk"]["max_h_after_first_fix_m"], ".3f"),
            r["rtk"]["refix_after_outage_s"], r["rtk"]["wrong_fixes"], r["rtk"]["wrong_fixes_3d"])]) + (
        [] if not r.get("imu_cluster") else [
        "  IMU cluster: " + ", ".join(f"{name} {'healthy' if u['healthy'] else 'DROPPED'}"
                                      for name, u in r["imu_cluster"]["units"].items())]))


def cmd_fly(args) -> int:
    from .autopilot import Faults
    faults = Faults(imu_unit_bias=[(t, int(u), b) for t, u, b in args.imu_fault]) if args.imu_fault else None
    try:
        res = asyncio.run(fly(args.scenario, args.duration, args.speedup, rate_hz=args.rate, seed=args.seed,
                              out_dir=args.out, output_mode=args.output, imu_units=args.imu_units, faults=faults,
                              system_time_late_s=args.system_time_late, progress=not args.quiet,
                              handle_signals=True, rover_outage_s=_rover_outage(args), imu_rate_hz=args.imu_rate_hz,
                              config_keys=_config_keys(args.set)))
    except KeyboardInterrupt:
        # interrupted before the flight started (during the simulation): nothing to score
        print("sitl fly: interrupted before the flight started", file=sys.stderr)
        if args.json:
            _write_json(args.json, {"interrupted": True, "estimates_received": 0})
        return 130
    series = res.pop("_series")
    print(format_result(res))
    if args.json:
        keys = ("interrupted", "estimates_received", "estimate_rate_hz", "estimate_rate_fraction", "rms_3d_m",
                "rms_h_m", "p95_3d_m", "latency_ms_p50", "latency_ms_p99", "companion_cpu_pct",
                "companion_rss_mb", "setup_s")
        obj = {k: res[k] for k in keys}
        obj["details"] = {k: v for k, v in res.items() if k not in keys}
        if args.series:
            obj["series"] = series
        _write_json(args.json, obj)
        print(f"wrote {args.json}")
    if res["interrupted"]:
        print("sitl fly: INTERRUPTED: the figures above cover only the part that was flown", file=sys.stderr)
        return 130
    return 0 if res["estimates_received"] else 1


def _config_keys(items) -> dict | None:
    """--set SECTION.KEY=TOML (repeatable, as ``sitl ardupilot``'s) -> {section: {key: value}}."""
    import tomllib
    if not items:
        return None
    keys: dict = {}
    for item in items:
        name, sep, text = item.partition("=")
        section, dot, key = name.strip().rpartition(".")
        if not sep or not dot or not key:
            raise SystemExit(f"sitl fly: --set {item!r}: expected SECTION.KEY=TOML, e.g. mavlink.rx_pacing=false")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError as exc:
            raise SystemExit(f"sitl fly: --set {item!r}: the value is not TOML ({exc}); a string needs quotes")
        keys.setdefault(section, {})[key] = value
    return keys


#: the rtk (and rtk-gec) scenario's 30-s outage moved into a flight too short for its own (130-160 s): after the
#: first slip (60 s), swallowing the second (95 s), 20 s left to re-fix in a 120-s flight
RTK_FLY_OUTAGE_S = (70.0, 100.0)


def _rover_outage(args):
    """--rover-outage, or for the rtk scenario a flight that ends before its own outage is over:
    RTK_FLY_OUTAGE_S (the acceptance asks for a re-fix after a 30-s outage within 120 s)."""
    if args.rover_outage is not None:
        return tuple(args.rover_outage) if args.rover_outage[1] > args.rover_outage[0] else None
    if args.scenario in ("rtk", "rtk-gec"):
        from .scenario import RTK_OUTAGE_S
        if args.duration < RTK_OUTAGE_S[1] + 10.0:
            return RTK_FLY_OUTAGE_S
    return None


def _write_json(path: str, obj: dict) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(obj, indent=2, default=str))


def register(subparsers) -> None:
    p = subparsers.add_parser("fly", help="companion + emulated autopilot + NTRIP caster on loopback, scored")
    p.add_argument("--scenario", default="uav")
    p.add_argument("--duration", type=float, default=120.0, help="simulated seconds (default 120)")
    p.add_argument("--speedup", type=float, default=1.0, help="simulated time per wall-clock second")
    p.add_argument("--rate", type=float, default=25.0, help="estimate rate requested from the companion, Hz")
    p.add_argument("--output", default="vision", choices=("vision", "odometry", "gps_input"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="out/fly", help="directory for config, logs and the field log")
    p.add_argument("--json", help="write the figures as JSON here")
    p.add_argument("--series", action="store_true", help="include per-estimate error/latency series in the JSON")
    p.add_argument("--quiet", action="store_true", help="no set-up steps or status lines on stderr")
    p.add_argument("--imu-rate-hz", type=float, default=None, metavar="HZ",
                   help="the scenario's IMU at this rate (default: the scenario's, 200 Hz for uav), e.g. 400")
    p.add_argument("--imu-units", type=int, default=1, choices=(1, 2, 3),
                   help="IMUs the autopilot reports (2, 3: + SCALED_IMU2/3, fused by the companion's IMU cluster)")
    p.add_argument("--system-time-late", type=float, default=0.0, metavar="S",
                   help="the autopilot's SYSTEM_TIME lags true time by S seconds (its UTC clock is set from "
                        "GPS fixes as they arrive; default 0 = exact)")
    p.add_argument("--imu-fault", type=float, nargs=3, action="append", metavar=("T_S", "UNIT", "BIAS_RADPS"),
                   help="from T_S on, unit UNIT's x gyro reads BIAS_RADPS too much (repeatable)")
    p.add_argument("--rover-outage", type=float, nargs=2, metavar=("START_S", "END_S"),
                   help="the rover receiver outputs nothing from START_S to END_S of the flight (0 0: none); "
                        f"default for the rtk and rtk-gec scenarios when the flight ends before their own "
                        f"130-160 s outage: "
                        f"{RTK_FLY_OUTAGE_S[0]:g} {RTK_FLY_OUTAGE_S[1]:g}")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=TOML",
                   help="a key of the companion's configuration for this flight (repeatable), e.g. "
                        "--set mavlink.rx_pacing=false to measure the same flight reading every datagram on arrival")
    p.set_defaults(func=cmd_fly)


def main(argv=None) -> int:
    import argparse
    p = argparse.ArgumentParser(prog="python -m sitl")
    sub = p.add_subparsers(dest="cmd", required=True)
    register(sub)
    args = p.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
