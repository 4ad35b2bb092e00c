"""``python -m sitl.ardupilot_gnss``: the raw GNSS receiver and the base station of
``python -m sitl ardupilot --gnss raw``, run by the harness as a process of its own.

* Follows ArduPilot SITL's truth live on a MAVLink port of its own (SIM_STATE + ATTITUDE at
  ``TRUTH_RATE_HZ``, :mod:`sitl.ardupilot_truth`), in SITL's own clock.
* GPS time.  SITL's simulated GPS gives the physics state at boot time ``t`` the GPS time
  ``start_time + t - GPS epoch + 18 s`` (``SIM_GPS.cpp``: ``simulation_timeval`` is
  ``--start-time`` + SITL's boot clock, GPS - UTC = 18 s); the harness starts SITL with
  ``--start-time`` so that number is known exactly.  Our receiver uses the same scale: its epochs
  are true GPS times on that clock (tagged with its own receiver clock, as any receiver), so they
  agree with what SITL's own u-blox reports, not with ArduPilot's UTC.  ArduPilot's SYSTEM_TIME
  (what the companion maps the IMU's boot time with) is about 0.17 s late on this scale, measured
  (SITL's u-blox output is 100 ms late and stamped at the 200 ms below its send time, and the
  autopilot takes its UTC from it as it arrives): the companion's IMU time-offset state (GPS time
  = IMU tag + dt_imu) has to find that +0.17 s, as it would find a real autopilot's GPS latency.
* Every epoch (``rate_hz``, receiver-time grid) as soon as SITL's truth has passed it by
  ``LEAD_S``: the rover epoch from :class:`sitl.simulate.ReceiverModel` with the antenna on the
  fitted truth, written as UBX RXM-RAWX (:func:`sitl.autopilot.rawx_frame`) plus the RXM-SFRBX
  subframe every tracked satellite completes at that time (:mod:`sitl.lnav_encode`) to the
  pseudo-terminal the companion reads (``gnss.source = "serial"``); the base epoch as RTCM MSM4
  (1074, :mod:`sitl.rtcm_msm`) with 1005 every ``STATION_INTERVAL_S``, served on 127.0.0.1 to the
  NTRIP caster (:func:`sitl.caster.start_caster`: RTKLIB str2str).  Ephemerides reach the
  companion only as SFRBX: a base caster with MSM + 1005 sends none.
* Writes ``ready.json`` (caster port, mountpoint, user, password, sky) into ``--out`` when it
  serves, and ``receiver.json`` (counters) when it stops (SIGTERM or the SITL link closing).

Errors and sky: :mod:`sitl.ardupilot_sky` (the 'uav' scenario's models at SITL's home).  Rate:
1 Hz by default (a u-blox receiver's default, and the rate the companion's TDCP clock model holds
at); ``--rate 5`` works here, but there the receiver clock's white frequency noise over a 0.2-s
interval (0.2 m/s for the scenario's TCXO) is more than the companion's TDCP rows and clock-drift
process noise allow for.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import signal
import sys
import time
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mav  # noqa: E402

from companion.io.mavlink_time import GPS_EPOCH_UNIX_S  # noqa: E402

from .ardupilot_sky import live_scenario  # noqa: E402
from .ardupilot_truth import Truth, home_e7  # noqa: E402
from .autopilot import rawx_frame  # noqa: E402
from .caster import RtcmServer, encode_1005, start_caster  # noqa: E402
from .lnav_encode import ephemeris_subframe, klobuchar_subframe, sfrbx_frame, subframe_due  # noqa: E402
from .rtcm_msm import Msm4Encoder  # noqa: E402
from .simulate import ReceiverModel, _Atmosphere  # noqa: E402

SITL_LEAP_S = 18                 # ArduPilot's GPS_LEAPSECONDS_MILLIS, also in SITL's GPS
TRUTH_RATE_HZ = 50.0
DEFAULT_RATE_HZ = 1.0            # a u-blox receiver's default measurement rate (see the module docstring)
LEAD_S = 0.03                    # truth needed past an epoch before it is made (the fit's support)
STATION_INTERVAL_S = 5.0
MIN_LOCK_FOR_SUBFRAME_S = 6.0    # a subframe is output only when its whole 6 s were tracked


def sitl_gps_time(start_unix_s: int, boot_s: float) -> float:
    """GPS time of SITL's boot time ``boot_s`` (see the module docstring)."""
    return start_unix_s - GPS_EPOCH_UNIX_S + SITL_LEAP_S + boot_s


class LiveReceiver:
    """Rover and base receivers of one scenario, epoch by epoch on a live truth.

    ``ubx(bytes)`` and ``rtcm(bytes)`` take what they output; :meth:`step` makes every epoch the
    truth now covers."""

    def __init__(self, scn, seed: int, truth: Truth, start_unix_s: int, ubx, rtcm, leap_seconds: int = SITL_LEAP_S):
        self.scn, self.truth, self.ubx, self.rtcm = scn, truth, ubx, rtcm
        self.leap_seconds = leap_seconds
        ephs = list(scn.ephemerides)
        self.ephs = {e.sat: e for e in ephs}
        atmo = _Atmosphere(scn, seed, [e.sat for e in ephs])
        self.rover = ReceiverModel(scn, seed, "rover", atmo, ephs)
        self.base = ReceiverModel(scn, seed, "base", atmo, ephs)
        self.gps_at_boot0 = sitl_gps_time(start_unix_s, 0.0)
        self.msm = Msm4Encoder(scn.base_station_id)
        self.k: int | None = None
        self._last_station = -math.inf
        self.counters = {"rover_epochs": 0, "rover_epochs_without_truth": 0, "base_epochs": 0, "sfrbx": 0,
                         "rawx_bytes": 0, "sfrbx_bytes": 0, "rtcm_bytes": 0, "epochs_past_the_scenario": 0,
                         "satellites_last": 0}

    def boot_s(self, t_gps: float) -> float:
        return t_gps - self.gps_at_boot0

    def step(self) -> int:
        """Make every epoch the truth has passed by LEAD_S; how many were made."""
        latest = self.truth.latest_boot_s
        if latest is None:
            return 0
        t_true = self.rover.t_true
        if self.k is None:          # the first epoch with a whole fit window of truth before it
            first = self.truth.samples[0][0] + 0.25
            self.k = int(next((i for i, t in enumerate(t_true) if self.boot_s(t) >= first), len(t_true)))
        n = 0
        while self.k < len(t_true) and self.boot_s(t_true[self.k]) + LEAD_S <= latest:
            self._epoch(self.k)
            self.k += 1
            n += 1
        if self.k >= len(t_true) and n == 0:
            self.counters["epochs_past_the_scenario"] += 1
        return n

    def _epoch(self, k: int) -> None:
        base = self.base.epoch(k)
        out = bytearray()
        if base.t_gps - self._last_station >= STATION_INTERVAL_S:
            out += encode_1005(self.scn.base_station_id, self.scn.base_r_e)
            self._last_station = base.t_gps
        out += self.msm.encode(base)
        self.counters["base_epochs"] += 1
        self.counters["rtcm_bytes"] += len(out)
        self.rtcm(bytes(out))
        t_k = float(self.rover.t_true[k])
        coef = self.truth.fit(self.boot_s(t_k))
        if coef is None:
            self.counters["rover_epochs_without_truth"] += 1
            return
        truth = self.truth

        def antenna(t):
            return truth.antenna_e(truth.ned_at(coef, t - t_k))

        ep = self.rover.epoch(k, antenna)
        if ep is None:
            return
        data = rawx_frame(ep, self.leap_seconds)
        self.counters["rawx_bytes"] += len(data)
        sub = self._subframes(ep)
        self.counters["sfrbx_bytes"] += len(sub)
        self.counters["rover_epochs"] += 1
        self.counters["satellites_last"] = len(ep.observations)
        self.ubx(data + sub)

    def _subframes(self, ep) -> bytes:
        due = subframe_due(ep.t_gps)
        if due is None or due[0] == 5:
            return b""
        sfid, tow_end = due
        out = bytearray()
        for ch, o in enumerate(ep.observations):
            if o.lock_time_s < MIN_LOCK_FOR_SUBFRAME_S or o.sat not in self.ephs:
                continue
            if sfid == 4:
                words = klobuchar_subframe(self.scn.klobuchar_alpha, self.scn.klobuchar_beta, tow_end)
            else:
                words = ephemeris_subframe(self.ephs[o.sat], sfid, tow_end)
            out += sfrbx_frame(int(o.sat[1:]), words, channel=ch)
            self.counters["sfrbx"] += 1
        return bytes(out)


class PtyWriter:
    """Non-blocking writes to the pseudo-terminal's master side: what does not fit is lost
    (counted), as bytes to a UART nobody reads."""

    def __init__(self, fd: int):
        self.fd = fd
        os.set_blocking(fd, False)
        self.counters = {"written": 0, "dropped": 0}

    def __call__(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self.fd, view)
            except BlockingIOError:
                break
            except OSError:
                break
            self.counters["written"] += n
            view = view[n:]
        self.counters["dropped"] += len(view)


async def _request_streams(writer, enc, acked: set, stop: asyncio.Event) -> None:
    """SET_MESSAGE_INTERVAL for SIM_STATE and ATTITUDE, again every second until both are acked."""
    ids = (mav.MAVLINK_MSG_ID_SIM_STATE, mav.MAVLINK_MSG_ID_ATTITUDE)
    while not stop.is_set() and not all(i in acked for i in ids):
        for i in ids:
            if i not in acked:
                msg = enc.command_long_encode(1, 1, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0, i, 1e6 / TRUTH_RATE_HZ,
                                              0, 0, 0, 0, 0)
                writer.write(bytes(msg.pack(enc)))
        await writer.drain()
        try:
            await asyncio.wait_for(stop.wait(), 1.0)
        except asyncio.TimeoutError:
            pass


async def serve(args) -> dict:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    lat_deg, lon_deg, alt_m = (float(x) for x in args.home.split(",")[:3])
    t0_gps = sitl_gps_time(args.start_unix, 0.0)
    scn = live_scenario((math.radians(lat_deg), math.radians(lon_deg), alt_m), t0_gps, args.duration, args.rate)
    truth = Truth(*home_e7(lat_deg, lon_deg), alt_m)
    server = RtcmServer()
    await server.start()
    caster = await start_caster(server.port, log_path=str(out / "str2str.log"))
    pty = PtyWriter(args.pty_fd)
    rx = LiveReceiver(scn, args.seed, truth, args.start_unix, ubx=pty, rtcm=server._send)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    ready = {"caster": {"kind": caster.kind, "port": caster.port, "mountpoint": caster.mountpoint,
                        "user": caster.user, "password": caster.password},
             "t0_gps": t0_gps, "satellites": [e.sat for e in scn.ephemerides], "sky": scn.notes,
             "rate_hz": args.rate, "base_r_e": [float(x) for x in scn.base_r_e]}
    tmp = out / "ready.json.tmp"
    tmp.write_text(json.dumps(ready, indent=2))
    tmp.replace(out / "ready.json")
    status = {"t_start_mono": time.monotonic(), "link": "connecting"}
    try:
        reader, writer = await asyncio.open_connection("127.0.0.1", args.sitl_port)
        status["link"] = "up"
        enc = mav.MAVLink(None, srcSystem=255, srcComponent=mav.MAV_COMP_ID_GPS)
        parser = mav.MAVLink(None)
        parser.robust_parsing = True
        acked: set = set()
        req = asyncio.create_task(_request_streams(writer, enc, acked, stop))
        stopper = asyncio.create_task(stop.wait())
        while not stop.is_set():
            read = asyncio.create_task(reader.read(65536))
            await asyncio.wait({read, stopper}, return_when=asyncio.FIRST_COMPLETED)
            if not read.done():
                read.cancel()
                break
            data = read.result()
            if not data:
                status["link"] = "closed by SITL"
                break
            for msg in parser.parse_buffer(data) or []:
                truth.on_message(msg)
            # COMMAND_ACK does not say which message it is for: the streams arriving are the ack
            if truth.counters["sim_state"]:
                acked.add(mav.MAVLINK_MSG_ID_SIM_STATE)
            if truth.counters["attitude"]:
                acked.add(mav.MAVLINK_MSG_ID_ATTITUDE)
            rx.step()
        req.cancel()
        writer.close()
    except OSError as exc:
        status["link"] = f"failed: {exc}"
    finally:
        await server.close()
        await caster.close()
    result = {"status": status, "receiver": rx.counters, "truth": truth.counters, "pty": pty.counters,
              "rtcm_server": server.counters, "sky": scn.notes}
    (out / "receiver.json").write_text(json.dumps(result, indent=2, default=str))
    return result


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m sitl.ardupilot_gnss", description=__doc__.split("\n\n")[0])
    p.add_argument("--sitl-port", type=int, required=True, help="SITL MAVLink TCP port for the truth (SERIAL1)")
    p.add_argument("--pty-fd", type=int, required=True, help="master side of the pseudo-terminal (inherited)")
    p.add_argument("--start-unix", type=int, required=True, help="SITL's --start-time (UNIX s)")
    p.add_argument("--home", required=True, help="SITL's home: lat,lon,alt[,yaw] (deg, deg, m)")
    p.add_argument("--duration", type=float, required=True, help="seconds of epochs from SITL's start")
    p.add_argument("--rate", type=float, default=DEFAULT_RATE_HZ, help=f"epochs per second (default {DEFAULT_RATE_HZ:g})")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="directory for ready.json, receiver.json and str2str.log")
    args = p.parse_args(argv)
    asyncio.run(serve(args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
