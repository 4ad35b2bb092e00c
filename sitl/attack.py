"""``python -m sitl attack``: the simulated flight under hostile input (issue 14, item 7).

The flight of ``python -m sitl fly`` (the emulated autopilot, the base station behind an NTRIP
caster, ``companion run`` as its own process, everything on 127.0.0.1) is flown once per attack
plus a clean control flight, through :func:`sitl.faults.run_cases` like the fault matrix.  Every
flight, the control included, gets its corrections through :mod:`sitl.hostile_caster` (its own
process; in the control it only relays), so the attack is the only difference.  The attacks:

* ``rtcm_false_sync_{2,8,32}k``: the false sync ``D3 03`` at 2, 8, 32 kB/s mixed into the real
  corrections (between whole real frames); ``rtcm_crafted_sync_32k``: ``D3 00 FF 43 50``, which
  passes every framing check but the CRC, at 32 kB/s;
* ``udp_second_sender``: a stranger on the companion's MAVLink ``udpin`` port (its own address),
  from 5 s on: HEARTBEATs claiming to be the autopilot (system 1, component 1) and forged
  HIGHRES_IMU frames at 200 Hz; ``udp_1000_senders``: the same plus 1000 more addresses that send
  one HEARTBEAT each;
* ``disk_full_30s``: the field log directory is a small tmpfs (needs root: ``mount``); at 30 s a
  file fills it, at 45 s the file goes (space returns);
* ``caster_flood_10MBps``: the caster sends random bytes at up to 10 MB/s besides the real stream;
* ``slow_header_caster``: the caster's first answer is an endless header, one byte every 0.2 s
  (later connections are served normally); ``corrections_late_10s`` (a *reference*, not judged):
  no attack, the base station is silent for the first 10 s -- the delay the slow header costs,
  without the caster, to tell the NTRIP client's part from the navigation's (optional: flown with
  ``--references`` or when named in ``--only``);
* ``forged_imu_signing_required`` / ``forged_imu_no_signing``: unsigned HIGHRES_IMU frames as
  system 1 component 1 from the autopilot's own address (what anyone on a radio link can do),
  200 Hz from 5 s on, between the real samples, biased by 3 m/s^2 and 0.3 rad/s; in the first the
  emulated autopilot signs (:mod:`sitl.autopilot`, a fresh key file of ``companion signing setup``'s
  kind) and the companion requires signing (``mavlink.signing_key_file``, ``signing_required``); in
  the second (a *reference*, not judged) nobody signs, which shows what the forgery does when it
  gets in; ``signing_required_no_attack`` (optional reference): signing alone.

Per flight: ``estimate_rate_hz``, ``rms_h_m``, ``latency_ms_p99`` (arrival of an estimate at the
autopilot minus the autopilot's send time of the IMU sample it is stamped with, as ``sitl fly``),
``companion_rss_mb`` (VmRSS at the end of the flight) and ``companion_peak_rss_mb`` (VmHWM), their
growth against the control, ``field_log_bytes`` (the directory at the end) against the cap the
flights run with (``log.max_total_bytes`` = 100 kB per flight second, ~2.7 x what the control
writes), and the evidence that the defence worked (the companion's own counters from the health
report in its field log, the attacker's counters).  Pass (:func:`judge`): estimate rate >= 95 % of
the control's, horizontal RMS <= 110 % of the control's, p99 latency <= 20 ms, RSS growth (end and
peak) <= 20 MB, field log within its cap, and the attack's own evidence (e.g. the stranger got
nothing back, the forged frames were rejected).
"""
from __future__ import annotations

import asyncio
import json
import math
import os
import shutil
import socket
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

RATE_MIN_FRACTION = 0.95
RMS_MAX_FRACTION = 1.10
LATENCY_P99_MAX_MS = 20.0
RSS_GROWTH_MAX_MB = 20.0
FIELD_LOG_CAP_BYTES_PER_S = 100_000      # the control writes ~37 kB/s
FIELD_LOG_FILES_PER_CAP = 6              # log.max_bytes = cap / 6: retention works file by file
ATTACK_START_S = 5.0                     # stranger / forger start (after the peer lock, before init)
DISK_FULL_AT_S = 30.0
DISK_FREE_AT_S = 45.0
TMPFS_MB = 16
LATENCY_WINDOW_S = 10.0                  # latency_ms_p99_per_window
LATE_CORRECTIONS_S = 10.0                # when the slow-header caster's corrections begin (10-s header timeout)
FORGED_ACCEL_BIAS_MPS2 = 3.0
FORGED_GYRO_BIAS_RADPS = 0.3


@dataclass
class AttackCase:
    name: str
    what: str
    caster: dict = field(default_factory=dict)     # sitl.hostile_caster options
    side: str | None = None                        # the attacker's task during the flight (SIDE_TASKS)
    side_opts: dict = field(default_factory=dict)
    signing: bool = False                          # the companion requires signed MAVLink 2
    reference: bool = False                        # shows an unprotected effect: reported, not judged
    needs: str | None = None                       # 'root' (tmpfs)
    optional: bool = False                         # flown with --references or when named in --only
    fly: dict = field(default_factory=dict)        # extra sitl.fly.fly keyword arguments


def attack_cases() -> list[AttackCase]:
    return [
        AttackCase("control", "no attack (the caster relays the base station)"),
        *[AttackCase(f"rtcm_false_sync_{k}k", f"RTCM false sync D3 03 at {k} kB/s mixed into the corrections",
                     caster={"flood_bps": k * 1000, "flood_pattern": "d3_03"}) for k in (2, 8, 32)],
        AttackCase("rtcm_crafted_sync_32k", "RTCM false sync D3 00 FF 43 50 (only the CRC rejects it) at 32 kB/s",
                   caster={"flood_bps": 32000, "flood_pattern": "crafted_1077"}),
        AttackCase("udp_second_sender", "a second UDP sender on the MAVLink port: HEARTBEAT + HIGHRES_IMU as 1/1",
                   side="udp_stranger", side_opts={"extra_senders": 0}),
        AttackCase("udp_1000_senders", "the second sender plus 1000 addresses sending one HEARTBEAT each",
                   side="udp_stranger", side_opts={"extra_senders": 1000}),
        AttackCase("forged_imu_signing_required", "unsigned HIGHRES_IMU as 1/1 from the autopilot's address, "
                   "signing required", side="forge_imu", signing=True),
        AttackCase("forged_imu_no_signing", "the same forgery, signing off (reference: what it does unprotected)",
                   side="forge_imu", reference=True),
        AttackCase("disk_full_30s", f"field log disk full at {DISK_FULL_AT_S:g} s, space back at "
                   f"{DISK_FREE_AT_S:g} s", side="disk_full", needs="root"),
        AttackCase("caster_flood_10MBps", "the caster floods random bytes at 10 MB/s besides the corrections",
                   caster={"flood_bps": 10_000_000, "flood_pattern": "random"}),
        AttackCase("slow_header_caster", "the caster's first answer: an endless header, one byte per 0.2 s",
                   caster={"slow_header_connections": 1, "slow_header_byte_s": 0.2}),
        AttackCase(f"corrections_late_{LATE_CORRECTIONS_S:g}s", f"no attack: the base station is silent for the "
                   f"first {LATE_CORRECTIONS_S:g} s (reference: what the slow-header caster's delay costs alone)",
                   reference=True, optional=True, fly={"base_outage_s": (0.0, LATE_CORRECTIONS_S)}),
        AttackCase("signing_required_no_attack", "no attack, signing required (reference: what signing costs)",
                   signing=True, reference=True, optional=True),
    ]


# ---------------------------------------------------------------------------------------------
# the attackers that run beside the flight (sitl.fly's ``during`` hook)
async def udp_stranger(ctx, report: dict, *, extra_senders: int = 0, imu_rate_hz: float = 200.0) -> None:
    """Another address on the companion's udpin port: HEARTBEAT as the autopilot (1/1) at 1 Hz and
    forged HIGHRES_IMU at ``imu_rate_hz``; ``extra_senders`` more addresses send one GCS HEARTBEAT
    each.  ``report``: datagrams sent, and received back from the companion (must stay 0)."""
    from .autopilot import m
    await ctx.until_flight_s(ATTACK_START_S)
    enc = m.MAVLink(None, srcSystem=1, srcComponent=1)
    gcs = m.MAVLink(None, srcSystem=255, srcComponent=190)
    main = _udp_socket()
    extra = []
    report.update(sent=0, received=0, extra_senders=extra_senders, extra_sent=0, extra_received=0)
    try:
        for _ in range(extra_senders):
            s = _udp_socket()
            extra.append(s)
            s.sendto(gcs.heartbeat_encode(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0).pack(gcs), ctx.ap.addr)
            report["extra_sent"] += 1
            if len(extra) % 50 == 0:
                await asyncio.sleep(0.01)
        period = 1.0 / imu_rate_hz
        k = 0
        loop = asyncio.get_running_loop()
        t_next = loop.time()
        while True:
            if k % int(imu_rate_hz) == 0:
                main.sendto(enc.heartbeat_encode(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0,
                                                 m.MAV_STATE_ACTIVE).pack(enc), ctx.ap.addr)
                report["sent"] += 1
            main.sendto(_forged_imu(ctx, enc).pack(enc), ctx.ap.addr)
            report["sent"] += 1
            k += 1
            report["received"] += _drain(main)
            if k % 200 == 0:
                report["extra_received"] += sum(_drain(s) for s in extra)
            t_next += period
            await asyncio.sleep(max(0.0, t_next - loop.time()))
    finally:
        report["received"] += _drain(main)
        report["extra_received"] += sum(_drain(s) for s in extra)
        for s in [main, *extra]:
            s.close()


async def forge_imu(ctx, report: dict, *, imu_rate_hz: float = 200.0) -> None:
    """Unsigned HIGHRES_IMU as system 1 component 1 through the autopilot's own socket (same
    address: the peer lock cannot tell), stamped half way between the real samples."""
    from .autopilot import m
    await ctx.until_flight_s(ATTACK_START_S)
    enc = m.MAVLink(None, srcSystem=1, srcComponent=1)      # no signing
    report.update(sent=0)
    period = 1.0 / imu_rate_hz
    loop = asyncio.get_running_loop()
    t_next = loop.time()
    while True:
        ctx.ap.sock.sendto(_forged_imu(ctx, enc).pack(enc), ctx.ap.addr)
        report["sent"] += 1
        t_next += period
        await asyncio.sleep(max(0.0, t_next - loop.time()))


def _forged_imu(ctx, enc):
    """A plausible HIGHRES_IMU at the autopilot's current boot time (half a real sample period on),
    with the true-ish gravity reading plus a bias: destructive if it is fused."""
    ap = ctx.ap
    boot_us = ap.boot_us(ctx.clock.now_gps()) + int(0.5e6 / ap.imu_rate_hz)
    b, w = FORGED_ACCEL_BIAS_MPS2, FORGED_GYRO_BIAS_RADPS
    return enc.highres_imu_encode(boot_us, b, 0.0, -9.80665, 0.0, 0.0, w, 0, 0, 0, 0, 0, 0, 25.0, 0x3F, 0)


async def disk_full(ctx, report: dict) -> None:
    """Fill the field log's filesystem at DISK_FULL_AT_S, free it at DISK_FREE_AT_S."""
    await ctx.until_flight_s(DISK_FULL_AT_S)
    filler = ctx.log_dir / "filler.bin"
    report.update(filled_at_s=round(ctx.t_flight_s(), 2), filler_bytes=0)
    # in a thread: the emulated autopilot shares this event loop, and its timing is the yardstick
    await asyncio.to_thread(_fill, filler, report)
    report["full_after_s"] = round(ctx.t_flight_s(), 2)
    await ctx.until_flight_s(DISK_FREE_AT_S)
    filler.unlink()
    report["freed_at_s"] = round(ctx.t_flight_s(), 2)


def _fill(path: Path, report: dict) -> None:
    """Write zeros to ``path`` until the filesystem is full (1 MB blocks, then 4 kB ones)."""
    with open(path, "wb", buffering=0) as fh:
        for block in (b"\0" * (1 << 20), b"\0" * 4096):
            try:
                while True:
                    report["filler_bytes"] += fh.write(block)
            except OSError as exc:
                report["fill_error"] = exc.strerror


SIDE_TASKS = {"udp_stranger": udp_stranger, "forge_imu": forge_imu, "disk_full": disk_full}


def _udp_socket() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.setblocking(False)
    return s


def _drain(s: socket.socket) -> int:
    n = 0
    while True:
        try:
            s.recv(65535)
            n += 1
        except (BlockingIOError, InterruptedError):
            return n
        except OSError:                 # ICMP port unreachable and the like
            continue


# ---------------------------------------------------------------------------------------------
# one flight
def field_log_cap_bytes(duration_s: float) -> int:
    return int(max(1.0, duration_s) * FIELD_LOG_CAP_BYTES_PER_S)


def final_health(field_log_dir) -> dict:
    """The last health report the companion wrote into its field log (the one at shutdown)."""
    from companion.io.fieldlog import read_field_log
    h = {}
    try:
        for rec in read_field_log(field_log_dir):
            if rec.kind == "event":
                obj = json.loads(rec.payload)
                if obj.get("event") in ("stop", "health"):
                    h = obj["health"]
    except (OSError, ValueError):
        pass
    return h


def _dir_bytes(d: Path) -> int:
    return sum(f.stat().st_size for f in Path(d).glob("*.cflog"))


def _unavailable(case: AttackCase) -> str | None:
    if case.needs == "root" and (os.geteuid() != 0 or shutil.which("mount") is None):
        return "needs root for a tmpfs (mount -t tmpfs); run as root to include it"
    return None


def _signing_settings(out: Path) -> tuple[dict, dict]:
    """({section: {key: value}} for the companion, extra sitl.fly.fly keyword arguments) of a
    flight whose companion requires signed MAVLink 2 and whose autopilot signs (a fresh key file,
    0600, in the flight's directory: the companion's ``signing setup`` way)."""
    from companion.io.mavlink_signing import generate_key_file, load_key
    path = Path(out) / "signing.key"
    path.unlink(missing_ok=True)
    generate_key_file(path)
    key = load_key(path).key
    return ({"mavlink": {"signing_key_file": str(path.resolve()), "signing_required": True}},
            {"signing_key": key})


async def fly_attack(case: AttackCase, *, duration_s: float, out_dir: Path, seed: int = 0,
                     speedup: float = 1.0) -> dict:
    from .fly import fly
    from .hostile_caster import read_stats, start_hostile_caster
    out = Path(out_dir) / case.name
    row = {"attack": case.name, "what": case.what, "reference": case.reference}
    why = _unavailable(case)
    if why:
        row.update(skipped=why)
        return row
    out.mkdir(parents=True, exist_ok=True)
    cap = field_log_cap_bytes(duration_s)
    keys = {"log": {"max_total_bytes": cap, "max_bytes": cap // FIELD_LOG_FILES_PER_CAP}}
    fly_kw = {}
    if case.signing:
        extra_keys, fly_kw = _signing_settings(out)
        for sec, kv in extra_keys.items():
            keys.setdefault(sec, {}).update(kv)
    report: dict = {}
    during = None
    if case.side is not None:
        task = SIDE_TASKS[case.side]

        async def during(ctx):
            await task(ctx, report, **case.side_opts)

    log_dir = out / "fieldlog"
    mounted = False
    if case.side == "disk_full":
        log_dir.mkdir(parents=True, exist_ok=True)
        subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={TMPFS_MB}m,mode=0700", "tmpfs", str(log_dir)],
                       check=True)
        mounted = True
    try:
        captured: dict = {}
        res = await fly("uav", duration_s, speedup, seed=seed, out_dir=str(out), handle_signals=True,
                        keep_autopilot=captured,
                        caster_factory=lambda port, d: start_hostile_caster(port, d, **case.caster),
                        config_keys=keys, during=during, **case.fly, **fly_kw)
        if res["interrupted"]:
            raise KeyboardInterrupt
        series = res.pop("_series", None) or {}
        log_bytes = _dir_bytes(log_dir)
        health = final_health(log_dir)
    finally:
        if mounted:
            subprocess.run(["umount", str(log_dir)], check=False)
    ap = captured["ap"]
    row.update({k: res.get(k) for k in (
        "estimates_received", "estimate_rate_hz", "rms_h_m", "rms_3d_m", "latency_ms_p50", "latency_ms_p99",
        "companion_rss_mb", "companion_peak_rss_mb", "companion_cpu_pct", "companion_exit_code",
        "first_estimate_s")})
    row.update(field_log_bytes=log_bytes, field_log_cap_bytes=cap, duration_s=res["duration_s"],
               latency_ms_p99_per_window=latency_p99_per_window(series.get("t_s", []), series.get("latency_ms", [])),
               statustext=res["statustext"][-20:], attacker=report, caster=read_stats(out),
               evidence=evidence(health, ap))
    return row


def latency_p99_per_window(t_s, latency_ms, window_s: float = LATENCY_WINDOW_S) -> list[list[float]]:
    """[window start s, p99 latency ms, estimates] per ``window_s`` of flight time: where in the
    flight a long latency happened (at the attack's start, or spread like a loaded machine's)."""
    import numpy as np
    t, lat = np.asarray(t_s, float), np.asarray(latency_ms, float)
    out = []
    if not len(t):
        return out
    for w0 in np.arange(0.0, float(t.max()) + 1e-9, window_s):
        sel = (t >= w0) & (t < w0 + window_s)
        if sel.any():
            out.append([round(float(w0), 1), round(float(np.percentile(lat[sel], 99)), 2), int(sel.sum())])
    return out


def evidence(health: dict, ap=None) -> dict:
    """The companion's own counters that show what an attack did and what stopped it."""
    link = health.get("link", {})
    ev = {
        "corrections_source": {k: v for k, v in health.get("corrections_source", {}).items()
                               if k in ("bytes", "connects", "reconnects", "errors", "timeouts", "header_timeouts",
                                        "rate_limited", "last_error")},
        "rtcm_framer": health.get("rtcm", {}),
        "rate_caps": health.get("rate_caps", {}),
        "rtcm_bytes_logged": health.get("inputs", {}).get("bytes", {}).get("rtcm"),
        "base_epochs": health.get("engine", {}).get("base epochs"),
        "udp_peer": link.get("udp_peer"),
        "link_bad_data": link.get("bad_data"),
        "link_bad_data_reasons": link.get("bad_data_reasons"),
        "signing": {k: v for k, v in link.items() if k.startswith("signing")},
        "imu_screen": {k: v for k, v in health.get("engine", {}).items() if k.startswith("imu_screen") and v},
        "field_log": health.get("field_log", {}),
        "field_log_counters": {k: v for k, v in health.get("outputs", {}).items() if k.startswith("field log")},
        "task_restarts": health.get("task_restarts", {}),
        "reinitialisations": health.get("pipeline", {}).get("initialisations"),
    }
    if ap is not None:        # what the autopilot refused of the companion's (BAD_DATA: e.g. a bad signature)
        ev["autopilot_rx_bad"] = ap.counters.get("rx_parse_errors", 0) + ap.counters.get("rx_BAD_DATA", 0)
    return ev


# ---------------------------------------------------------------------------------------------
# judging
def _check(name: str, value, limit, ok: bool, unit: str = "") -> dict:
    return {"check": name, "value": value, "limit": limit, "ok": bool(ok), "unit": unit}


def judge(row: dict, control: dict | None) -> list[dict]:
    """The acceptance checks of one flight (issue 14): against the control's figures where the
    criterion is relative, plus the attack's own evidence.  A missing figure fails its check."""
    checks = []
    fin = lambda x: x is not None and isinstance(x, (int, float)) and math.isfinite(x)  # noqa: E731
    if row["attack"] != "control" and control is not None:
        c_rate, rate = control.get("estimate_rate_hz"), row.get("estimate_rate_hz")
        checks.append(_check("estimate rate >= 95 % of control", rate,
                             round(RATE_MIN_FRACTION * c_rate, 3) if fin(c_rate) else None,
                             fin(rate) and fin(c_rate) and rate >= RATE_MIN_FRACTION * c_rate, "Hz"))
        c_rms, rms = control.get("rms_h_m"), row.get("rms_h_m")
        checks.append(_check("horizontal RMS <= 110 % of control", rms,
                             round(RMS_MAX_FRACTION * c_rms, 4) if fin(c_rms) else None,
                             fin(rms) and fin(c_rms) and rms <= RMS_MAX_FRACTION * c_rms, "m"))
        for key, label in (("companion_rss_mb", "RSS growth (end) <= 20 MB"),
                           ("companion_peak_rss_mb", "RSS growth (peak) <= 20 MB")):
            a, c = row.get(key), control.get(key)
            g = round(a - c, 1) if fin(a) and fin(c) else None
            checks.append(_check(label, g, RSS_GROWTH_MAX_MB, g is not None and g <= RSS_GROWTH_MAX_MB, "MB"))
    lat = row.get("latency_ms_p99")
    checks.append(_check("p99 latency <= 20 ms", lat, LATENCY_P99_MAX_MS, fin(lat) and lat <= LATENCY_P99_MAX_MS,
                         "ms"))
    fl, cap = row.get("field_log_bytes"), row.get("field_log_cap_bytes")
    checks.append(_check("field log within its cap", fl, cap, fin(fl) and fin(cap) and fl <= cap, "B"))
    checks.append(_check("companion exited cleanly", row.get("companion_exit_code"), 0,
                         row.get("companion_exit_code") == 0))
    checks += _attack_evidence_checks(row)
    return checks


def _attack_evidence_checks(row: dict) -> list[dict]:
    name, ev, att = row["attack"], row.get("evidence", {}), row.get("attacker", {})
    cs, caster = ev.get("corrections_source", {}), row.get("caster", {})
    out = []
    if name.startswith("rtcm_") or name == "caster_flood_10MBps":
        out.append(_check("flood reached the companion (caster flood bytes)", caster.get("flood_bytes", 0), "> 0",
                          caster.get("flood_bytes", 0) > 0, "B"))
    if name.startswith("rtcm_"):
        # under the read cap every real frame must come through: the last one may be in flight at the end
        found, relayed = (ev.get("rtcm_framer") or {}).get("frames", 0), caster.get("frames", 0)
        out.append(_check("every real RTCM frame decoded", found, f">= {relayed} - 1",
                          relayed > 0 and found >= relayed - 1, "frames"))
    if name == "caster_flood_10MBps":
        dur = row.get("duration_s") or 0.0
        rt = ev.get("rtcm_bytes_logged") or 0
        # the NTRIP client's cap (64 kB/s by default, 1 s burst) bounds what is logged and decoded
        lim = 64_000 * (dur + 10.0)
        out.append(_check("RTCM bytes logged within the read cap", rt, int(lim), rt <= lim, "B"))
        out.append(_check("NTRIP client throttled the caster", cs.get("rate_limited"), "> 0",
                          (cs.get("rate_limited") or 0) > 0))
    if name.startswith("udp_"):
        peer = ev.get("udp_peer") or {}
        sent = att.get("sent", 0) + att.get("extra_sent", 0)
        got = att.get("received", 0) + att.get("extra_received", 0)
        out.append(_check("strangers received nothing", got, 0, sent > 0 and got == 0, "datagrams"))
        out.append(_check("their datagrams were dropped unread", peer.get("foreign_datagrams"), f">= 0.9 x {sent}",
                          (peer.get("foreign_datagrams") or 0) >= 0.9 * sent > 0, "datagrams"))
        out.append(_check("peer lock never moved", peer.get("locks"), 1, peer.get("locks") == 1))
    if name == "forged_imu_signing_required":
        sg = ev.get("signing") or {}
        rejected, accepted = sg.get("signing: rejected unsigned", 0), sg.get("signing: accepted unsigned", 0)
        out.append(_check("forged unsigned frames rejected", rejected, f">= 0.9 x {att.get('sent', 0)}",
                          att.get("sent", 0) > 0 and rejected >= 0.9 * att.get("sent", 0), "frames"))
        out.append(_check("no unsigned frame accepted", accepted, 0, accepted == 0, "frames"))
        out.append(_check("the autopilot's signed frames verified", sg.get("signing: good", 0), "> 0",
                          sg.get("signing: good", 0) > 0, "frames"))
        out.append(_check("the companion's signed frames verified at the autopilot", ev.get("autopilot_rx_bad"), 0,
                          ev.get("autopilot_rx_bad") == 0, "frames"))
    if name == "disk_full_30s":
        fl = ev.get("field_log", {})
        st = row.get("statustext") or []
        paused = [t for t in st if "paused" in t and "disk full" in t]
        resumed = [t for t in st if "field log resumed" in t]
        out.append(_check("the disk did fill", att.get("fill_error"), "No space left on device",
                          att.get("fill_error") == "No space left on device"))
        out.append(_check("one 'disk full' STATUSTEXT", len(paused), 1, len(paused) == 1))
        out.append(_check("logging resumed when space returned", len(resumed), 1,
                          len(resumed) == 1 and fl.get("resumed", 0) >= 1))
    if name == "slow_header_caster":
        out.append(_check("header timeout freed the client", cs.get("header_timeouts"), ">= 1",
                          (cs.get("header_timeouts") or 0) >= 1))
        out.append(_check("corrections flowed after it", ev.get("base_epochs"), "> 0",
                          (ev.get("base_epochs") or 0) > 0))
    return out


def score_rows(rows: list[dict]) -> list[dict]:
    """Add ``rss_growth_mb``, ``peak_rss_growth_mb``, ``checks`` and ``pass`` to every flown row."""
    control = next((r for r in rows if r["attack"] == "control" and "skipped" not in r), None)
    for r in rows:
        if "skipped" in r:
            r["pass"] = None
            continue
        for key, out in (("companion_rss_mb", "rss_growth_mb"), ("companion_peak_rss_mb", "peak_rss_growth_mb")):
            a, c = r.get(key), None if control is None else control.get(key)
            r[out] = round(a - c, 1) if a is not None and c is not None else None
        r["checks"] = judge(r, control)
        r["pass"] = None if r["reference"] else all(c["ok"] for c in r["checks"])
    return rows


# ---------------------------------------------------------------------------------------------
# output
def _fmt(x, f):
    return "n/a" if x is None else format(x, f)


def format_rows(rows: list[dict]) -> str:
    head = (f"{'attack':28s} {'est Hz':>7s} {'RMS h m':>8s} {'p99 ms':>7s} {'RSS MB':>7s} {'dRSS':>6s} "
            f"{'dPeak':>6s} {'log MB':>7s} {'cap MB':>6s}  verdict")
    lines = [head, "-" * len(head)]
    for r in rows:
        if "skipped" in r:
            lines.append(f"{r['attack']:28s} skipped: {r['skipped']}")
            continue
        verdict = "reference" if r["reference"] else ("pass" if r["pass"] else "FAIL")
        failed = [c["check"] for c in r["checks"] if not c["ok"]]
        lines.append(
            f"{r['attack']:28s} {_fmt(r['estimate_rate_hz'], '7.2f')} {_fmt(r['rms_h_m'], '8.3f')} "
            f"{_fmt(r['latency_ms_p99'], '7.2f')} {_fmt(r['companion_rss_mb'], '7.1f')} "
            f"{_fmt(r.get('rss_growth_mb'), '+6.1f')} {_fmt(r.get('peak_rss_growth_mb'), '+6.1f')} "
            f"{r['field_log_bytes'] / 1e6:7.2f} {r['field_log_cap_bytes'] / 1e6:6.1f}  {verdict}"
            + (f" ({'; '.join(failed)})" if failed else ""))
    flown = [r for r in rows if "skipped" not in r and not r["reference"]]
    lines.append(f"overall: {sum(1 for r in flown if r['pass'])}/{len(flown)} pass"
                 + ("" if all(r["pass"] for r in flown) else "; failed: " + ", ".join(
                     r["attack"] for r in flown if not r["pass"])))
    lines.append("dRSS / dPeak: companion VmRSS at the end / VmHWM, minus the control's; "
                 "latency = estimate arrival - IMU sample send, at the autopilot")
    return "\n".join(lines)


def plot(rows: list[dict], path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    flown = [r for r in rows if "skipped" not in r]
    control = next((r for r in flown if r["attack"] == "control"), None)
    names = [r["attack"] for r in flown]
    metrics = [("estimate_rate_hz", "estimate rate (Hz)", None if control is None else
                RATE_MIN_FRACTION * control["estimate_rate_hz"], "estimate rate >= 95 % of control"),
               ("rms_h_m", "horizontal RMS (m)", None if control is None or control["rms_h_m"] is None else
                RMS_MAX_FRACTION * control["rms_h_m"], "horizontal RMS <= 110 % of control"),
               ("latency_ms_p99", "p99 latency (ms)", LATENCY_P99_MAX_MS, "p99 latency <= 20 ms"),
               ("peak_rss_growth_mb", "peak RSS growth vs control (MB)", RSS_GROWTH_MAX_MB,
                "RSS growth (peak) <= 20 MB"),
               ("field_log_mb", "field log (MB)", flown[0]["field_log_cap_bytes"] / 1e6 if flown else None,
                "field log within its cap")]

    def colour(r, check):
        if r["reference"]:
            return "0.6"
        c = next((c for c in r["checks"] if c["check"] == check), None)
        return "tab:blue" if c is None else ("tab:green" if c["ok"] else "tab:red")
    fig, axes = plt.subplots(len(metrics), 1, figsize=(10, 2.3 * len(metrics)), sharex=True)
    for ax, (key, label, limit, check) in zip(axes, metrics):
        vals = [(r["field_log_bytes"] / 1e6 if key == "field_log_mb" else r.get(key)) for r in flown]
        vals = [math.nan if v is None else v for v in vals]
        colors = [colour(r, check) for r in flown]
        ax.bar(range(len(names)), vals, color=colors)
        if limit is not None:
            ax.axhline(limit, color="k", ls="--", lw=1)
        ax.set_ylabel(label, fontsize=8)
        ax.grid(axis="y", alpha=0.3)
    axes[-1].set_xticks(range(len(names)))
    axes[-1].set_xticklabels(names, rotation=30, ha="right", fontsize=8)
    fig.suptitle("python -m sitl attack: each bar green/red by its own check, blue control, grey reference "
                 "(not judged); dashed: limit", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def cmd_attack(args) -> int:
    from .faults import run_cases, select_cases
    cases = select_cases(attack_cases(), args.only, what="attack")
    if cases is None:
        return 2
    if not args.only and not args.references:
        cases = [c for c in cases if not c.optional]
    if not any(c.name == "control" for c in cases):
        cases.insert(0, attack_cases()[0])           # every figure is judged against a control
    if args.duration < DISK_FREE_AT_S + 5.0 and any(c.side == "disk_full" for c in cases):
        print(f"--duration {args.duration:g} s is too short for disk_full_30s (needs {DISK_FREE_AT_S + 5.0:g} s)",
              file=sys.stderr)
        return 2

    def describe(row):
        if "skipped" in row:
            return f"skipped: {row['skipped']}"
        return (f"{row['estimate_rate_hz']} Hz, RMS h {row['rms_h_m']} m, p99 {row['latency_ms_p99']} ms, "
                f"RSS {row['companion_rss_mb']} MB, field log {row['field_log_bytes']} B")

    rows, interrupted = run_cases(
        cases, lambda case: fly_attack(case, duration_s=args.duration, out_dir=Path(args.out), seed=args.seed),
        describe, what="attack", cmd="sitl attack")
    score_rows(rows)
    print(format_rows(rows))
    try:
        load = os.getloadavg()
    except OSError:
        load = None
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({
            "attacks": rows, "interrupted": interrupted, "duration_s": args.duration, "seed": args.seed,
            "criteria": {"estimate_rate_min_fraction_of_control": RATE_MIN_FRACTION,
                         "rms_h_max_fraction_of_control": RMS_MAX_FRACTION,
                         "latency_ms_p99_max": LATENCY_P99_MAX_MS, "rss_growth_max_mb": RSS_GROWTH_MAX_MB,
                         "field_log_cap_bytes_per_s": FIELD_LOG_CAP_BYTES_PER_S},
            "load_average_at_end": load, "cpu_count": os.cpu_count()}, indent=2, default=str))
        print(f"wrote {args.json}")
    if args.plot and rows:
        plot(rows, args.plot)
        print(f"wrote {args.plot}")
    if interrupted:
        return 130
    judged = [r for r in rows if r.get("pass") is not None]
    return 0 if judged and all(r["pass"] for r in judged) else 1


def register(subparsers) -> None:
    p = subparsers.add_parser("attack", help="the simulated flight under each attack of issue 14 plus a control, "
                                             "judged against the acceptance criteria")
    p.add_argument("--duration", type=float, default=60.0, help="simulated seconds per flight (default 60)")
    p.add_argument("--only", help="comma-separated attack names (the control is always flown)")
    p.add_argument("--references", action="store_true",
                   help="also fly the optional reference flights (corrections_late_10s, signing_required_no_attack)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="out/attack", help="directory for each flight's config and logs")
    p.add_argument("--json", help="write the figures, checks and verdicts as JSON here")
    p.add_argument("--plot", help="write a bar chart per metric (PNG) here")
    p.set_defaults(func=cmd_attack)
