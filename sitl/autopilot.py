"""An emulated autopilot on loopback UDP (MAVLink 2, pymavlink encoders), driven by a simulated flight.

What it does (ArduPilot-like, system 1 component 1, ``MAV_AUTOPILOT_ARDUPILOTMEGA``/``MAV_TYPE_QUADROTOR``):

* sends to the companion's UDP port (the companion listens, ``udpin``; like ArduPilot's
  ``SERIALn_PROTOCOL=2`` telemetry port or ``--out udp:``) and receives its replies on the same socket;
* HEARTBEAT at 1 Hz (``system_status`` STANDBY while the simulated vehicle is at rest before take-off,
  i.e. disarmed, else ACTIVE with ``MAV_MODE_FLAG_SAFETY_ARMED``) and SYSTEM_TIME at 1 Hz by default (ArduPilot sends it in its EXTRA3
  stream group); everything else only after the companion asks for it with
  MAV_CMD_SET_MESSAGE_INTERVAL (answered with COMMAND_ACK; -1 disables, 0 restores the default);
* HIGHRES_IMU (or RAW_IMU, in mG and mrad/s, int16, like ArduPilot) from the simulated IMU samples:
  rate = increment / dt, ``time_usec`` = boot time of the end of the sample interval; up to the
  simulated IMU rate (200 Hz for 'uav'), decimated for lower requested rates;
* with ``imu_units`` 2 or 3: SCALED_IMU2 / SCALED_IMU3 (mG, mrad/s, ``time_boot_ms``) of redundant
  IMUs with their own error realisations (:meth:`sitl.simulate.SimData.extra_imu_units`);
  ``Faults.imu_unit_bias`` adds a gyro bias step to one of them;
* SYSTEM_TIME sent at whole boot milliseconds, ``time_unix_usec`` = UTC = GPS - ``leap_seconds``
  (13 s in 2005, the 'uav' scenario's epoch): exact, so the companion's boot-to-GPS mapping is exact;
* ATTITUDE (truth + Gaussian noise of ``attitude_noise_deg``, a stand-in for the autopilot's own EKF);
* GPS_RAW_INT from the rover's epochs: truth antenna position + ``gps_noise_m`` white noise, speed and
  course from the truth, ``time_usec`` = boot time the fix "arrived" (epoch + ``receiver_latency_s``,
  as ArduPilot's ``last_fix_time_ms``), fix type 0 during a rover outage;
* SERIAL_CONTROL on device GPS1: the simulated receiver's UBX byte stream (RXM-RAWX packed from
  the rover GnssEpochs as pyubx2's ``UBXMessage`` would build it, appended to the port buffer ``receiver_latency_s``
  after each epoch) is returned only in answer to requests with RESPOND, <= 70 bytes per reply,
  more replies while full ones were sent and MULTI is set (ArduPilot ``handle_serial_control``).
  Bytes stay in the buffer only while a request with EXCLUSIVE holds the port locked: unlocked,
  ArduPilot's own GPS driver reads them.  Every system of the sky goes out (gnssId/sigId:
  :data:`RAWX_SIG_ID`).  Ephemerides are *not* sent as RXM-SFRBX: the base station's RTCM 1019 /
  1046 / 1042 (sitl.caster, sitl.rtcm_eph_encode) carry them;
* TIMESYNC: answers requests (tc1 = boot time in ns);
* the EKF origin like ArduPilot (``GCS_MAVLINK::set_ekf_origin``): the first SET_GPS_GLOBAL_ORIGIN
  is kept (altitude in whole cm, ``altitude / 10``), later ones are ignored, GPS_GLOBAL_ORIGIN
  is sent when it is set and on MAV_CMD_REQUEST_MESSAGE (49) once set; a reboot forgets it;
* records every VISION_POSITION_ESTIMATE, ODOMETRY, GPS_INPUT, SET_GPS_GLOBAL_ORIGIN and STATUSTEXT
  it receives with its arrival time (monotonic ns), every GPS_GLOBAL_ORIGIN it sends (the
  origin its NED frame has; ``Faults.preset_origin_ned_m``: one it had before the companion), and the send time of every IMU sample, so the
  estimates can be scored against the truth and their latency measured.

Pacing: a :class:`SimClock` maps simulated GPS time to the monotonic clock (``speedup`` x real time).
Each IMU sample is sent when the clock reaches it; a late loop sends what is due at once (no
catch-up drift).  Faults for the tests: ``corrupt`` (garbage datagrams and bit-flipped frames),
``reboot`` (silence, then boot time restarts from 0 and the stream requests are forgotten),
``clock_jump`` (the boot clock steps forward), ``gnss_outage`` (the receiver outputs nothing).

``signing_key`` (32 bytes): MAVLink 2 signing, as an ArduPilot set up with SETUP_SIGNING (signs all
it sends, verifies what it receives).
"""
from __future__ import annotations

import asyncio
import dataclasses
import math
import os
import random
import socket
import time
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink2  # noqa: E402

from companion.io.ubx import RAWX_HEAD, RAWX_MEAS, ubx_frame  # noqa: E402
from companion.messages import SECONDS_PER_WEEK, SPEED_OF_LIGHT_MPS, gps_week_tow  # noqa: E402
from companion.nav.earth import C_n_e, dcm_to_euler, ecef_to_geodetic  # noqa: E402
from .sky import light_time_range  # noqa: E402

m = mavlink2
GPS_EPOCH_UNIX_S = 315964800           # 1980-01-06 00:00:00 UTC
STANDARD_GRAVITY_MPS2 = 9.80665


class SimClock:
    """Simulated GPS time <-> monotonic clock, ``speedup`` x real time, started once."""

    def __init__(self, speedup: float = 1.0):
        self.speedup = float(speedup)
        self.started = asyncio.Event()
        self.m0 = 0.0
        self.t_start_gps = 0.0

    def start(self, t_start_gps: float) -> None:
        self.t_start_gps = float(t_start_gps)
        self.m0 = time.monotonic()
        self.started.set()

    def now_gps(self) -> float:
        return self.t_start_gps + (time.monotonic() - self.m0) * self.speedup

    def mono_at(self, t_gps: float) -> float:
        return self.m0 + (t_gps - self.t_start_gps) / self.speedup

    async def sleep_until(self, t_gps: float) -> None:
        await self.started.wait()
        d = self.mono_at(t_gps) - time.monotonic()
        if d > 0:
            await asyncio.sleep(d)


def relposned_frame(t_gps: float, ned_m, sigma_ned_m) -> bytes:
    """UBX NAV-RELPOSNED (version 1, carrier fixed) for a moving-baseline vector, built with pyubx2."""
    from pyubx2 import GET, UBXMessage
    week, tow = gps_week_tow(t_gps)
    cm = [int(math.floor(x * 100.0)) for x in ned_m]                  # cm part, then 0.1 mm part
    hp = [float(round((x * 100.0 - c) * 100.0)) * 0.01 for x, c in zip(ned_m, cm)]   # pyubx2 scale 0.01 cm
    hp = [min(h, 0.99) for h in hp]
    length = float(np.linalg.norm(ned_m))
    heading = (math.degrees(math.atan2(ned_m[1], ned_m[0])) + 360.0) % 360.0
    sig = [float(round(x * 1e4)) * 0.1 + 0.05 for x in sigma_ned_m]  # mm, pyubx2 scale 0.1 (+0.05: no truncation)
    msg = UBXMessage("NAV", "NAV-RELPOSNED", GET, version=1, iTOW=int(round(tow * 1000.0)), relPosN=cm[0],
                     relPosE=cm[1], relPosD=cm[2], relPosLength=int(length * 100.0), relPosHeading=round(heading, 5),
                     _HPrelPosN=hp[0], _HPrelPosE=hp[1], _HPrelPosD=hp[2], accN=sig[0], accE=sig[1], accD=sig[2],
                     accLength=sig[0], accHeading=0.5, gnssFixOK=1, diffSoln=1, relPosValid=1, carrSoln=2,
                     isMoving=1, relPosHeadingValid=1)
    return msg.serialize()


#: simulator signal -> UBX sigId (gnssId 0, GPS) the emulated receiver reports it as: a u-blox F9
#: tracks L1 C/A and L2C(L) (sigId 3, RINEX L2L), not P(Y): the dual-frequency simulator's one L2
#: observable goes out as L2C, as from an F9P
RAWX_GPS_SIG_ID = {"L1C": 0, "L2W": 3}
#: u-blox gnssId per system and, per simulator signal, the sigId (u-blox interface description,
#: "Signal identifiers"): Galileo E1 C 0, E5b Q 6 (an F9P's E1/E5b); BeiDou B1I D1 0 / D2 1, B3I D1 4
#: / D2 10 (the simulator's second BeiDou frequency is B3I; an F9P's is B2I, sigId 2/3).  D2 (the
#: GEO navigation message) is what the GEO satellites (PRN 1-5, 59-63) broadcast.
RAWX_GNSS_ID = {"G": 0, "E": 2, "C": 3, "J": 5}
RAWX_SIG_ID = {"G": RAWX_GPS_SIG_ID, "E": {"L1C": 0, "L7Q": 6}, "C": {"L2I": 0, "L6I": 4},
               "J": {"L1C": 0, "L2L": 5}}
_BEIDOU_D2_SIG_ID = {0: 1, 4: 10}


def _rawx_sig_id(sat: str, signal: str) -> int | None:
    sig = RAWX_SIG_ID.get(sat[0], {}).get(signal)
    prn = int(sat[1:])
    if sig is not None and sat[0] == "C" and (prn <= 5 or prn >= 59):
        sig = _BEIDOU_D2_SIG_ID[sig]
    return sig


def _rawx_sv_id(sat: str) -> int:
    """UBX svId: the PRN, QZSS 193-202."""
    return int(sat[1:]) + (192 if sat[0] == "J" else 0)


def rawx_frame(epoch, leap_seconds: int) -> bytes:
    """UBX RXM-RAWX (version 1) for a rover GnssEpoch: every system of :data:`RAWX_SIG_ID` (GPS
    L1C/A, and L2 as L2C(L) when the scenario is dual frequency; Galileo, BeiDou, QZSS on their
    signals), GPS first.  Packed with struct, byte for byte what pyubx2 1.4's ``UBXMessage`` built
    here before (tests/test_sitl_fly_gec.py; its version byte and the std-dev fields stay 0, as
    pyubx2 wrote them), which took ~0.25 s of CPU for a 70-measurement G+E+C epoch: that long
    inside the autopilot's IMU loop every second."""
    week = int(epoch.t_gps // SECONDS_PER_WEEK)
    tow = epoch.t_gps - week * SECONDS_PER_WEEK
    meas = []
    order = sorted(epoch.observations, key=lambda o: "GECJ".find(o.sat[0]) % 5)   # stable: GPS first
    for o in order:
        sig = _rawx_sig_id(o.sat, o.signal)
        if sig is None:
            continue
        pr_ok = math.isfinite(o.pseudorange_m)
        cp_ok = math.isfinite(o.carrier_cycles)
        lock_ms = int(min(64500, max(0, round((o.lock_time_s if math.isfinite(o.lock_time_s) else 0) * 1000))))
        cno = int(max(0, min(255, round(o.cn0_dbhz if math.isfinite(o.cn0_dbhz) else 0))))
        trk = int(pr_ok) | int(cp_ok) << 1 | int(cp_ok and not o.half_cycle_ambiguous) << 2
        meas.append(RAWX_MEAS.pack(o.pseudorange_m if pr_ok else 0.0, o.carrier_cycles if cp_ok else 0.0,
                                    o.doppler_hz if math.isfinite(o.doppler_hz) else 0.0,
                                    RAWX_GNSS_ID[o.sat[0]], _rawx_sv_id(o.sat), sig, 0, lock_ms, cno,
                                    0, 0, 0, trk))      # prStdev, cpStdev, doStdev 0, trkStat
    payload = RAWX_HEAD.pack(tow, week, leap_seconds, len(meas), 0x01, 0) + b"".join(meas)   # recStat: leapSec
    return ubx_frame(0x02, 0x15, payload)


@dataclass
class Received:
    t_mono_ns: int
    msg_type: str
    msg: object


@dataclass
class Faults:
    """Scheduled faults, times in seconds from the start of the simulated run."""
    corrupt: list = field(default_factory=list)          # (t_start, t_end, probability per frame)
    reboot: list = field(default_factory=list)           # (t, silent_s)
    clock_jump: list = field(default_factory=list)       # (t, jump_s): boot clock steps forward
    gnss_outage: list = field(default_factory=list)      # (t_start, t_end): no UBX bytes, GPS_RAW_INT no fix
    imu_unit_bias: list = field(default_factory=list)    # (t, unit, gyro_x_bias_radps): a unit's gyro fails
    imu_loss: list = field(default_factory=list)         # (t_start, t_end, probability): IMU frames lost on the
    #                                                      link (a full socket buffer on a loaded companion)
    # the integrity fault matrix (python -m sitl faults):
    imu_override: list = field(default_factory=list)     # (t_start, n_samples, accel_b m/s^2 | None, gyro_b rad/s
    #                                                      | None): the reported sample replaced (clip, spike)
    imu_noise: list = field(default_factory=list)        # (t_start, t_end, accel_sigma m/s^2, gyro_sigma rad/s)
    gnss_offset_ned: list = field(default_factory=list)  # (t_start, t_end, (dn, de, dd) m): spoofed position, in
    #                                                      the raw observations and in GPS_RAW_INT
    rover_clock_jump: list = field(default_factory=list)  # (t, jump_s): the receiver clock steps (all codes and
    #                                                       carriers move by c * jump_s from then on)
    attitude_yaw_error_deg: float = 0.0                  # the autopilot's ATTITUDE yaw is this far off
    no_attitude: bool = False                            # the autopilot never sends ATTITUDE
    preset_origin_ned_m: tuple | None = None             # (dn, de, dd) m: the autopilot already has an EKF
    #                                                      origin (from its own GPS, a GCS) this far from the
    #                                                      start position; SET_GPS_GLOBAL_ORIGIN is then ignored


class EmulatedAutopilot:
    def __init__(self, sim, *, companion_port: int, speedup: float = 1.0, leap_seconds: int = 13,
                 imu_message: str = "HIGHRES_IMU", attitude_noise_deg: float = 0.3, gps_noise_m: float = 0.7,
                 receiver_latency_s: float = 0.06, boot_lead_s: float = 30.0, seed: int = 0,
                 faults: Faults | None = None, clock: SimClock | None = None, imu_units: int = 1,
                 max_imu_rate_hz: float | None = None, moving_baseline_b_m=None,
                 baseline_sigma_ned_m=(0.005, 0.005, 0.010), gps_yaw_sigma_deg: float | None = None,
                 system_time_late_s: float = 0.0, signing_key: bytes | None = None):
        self.sim = sim
        self.addr = ("127.0.0.1", companion_port)
        self.clock = clock or SimClock(speedup)
        self.leap_seconds = leap_seconds
        self.imu_message = imu_message
        self.attitude_noise_rad = math.radians(attitude_noise_deg)
        self.gps_noise_m = gps_noise_m
        self.receiver_latency_s = receiver_latency_s
        # dual-antenna GPS: NAV-RELPOSNED in the UBX stream, and/or yaw in GPS_RAW_INT
        self.moving_baseline_b = None if moving_baseline_b_m is None else np.asarray(moving_baseline_b_m, float)
        self.baseline_sigma_ned_m = np.asarray(baseline_sigma_ned_m, float)
        self.gps_yaw_sigma_deg = gps_yaw_sigma_deg
        # ArduPilot's UTC clock is set from GPS fixes as they arrive, so SYSTEM_TIME lags true time
        # by the receiver's output latency (tens of ms): this emulates that lag
        self.system_time_late_s = system_time_late_s
        self.faults = faults or Faults()
        self.rng = np.random.default_rng([seed, 777])
        self.prng = random.Random(seed)
        self.loss_rng = random.Random(seed + 4242)       # its own stream: other faults' draws unchanged
        self.fault_rng = np.random.default_rng([seed, 4243])
        self._ephs = {e.sat: e for e in sim.ephemerides}   # for the spoofer's lines of sight
        t0 = float(sim.truth.t_gps[0])
        self.t0 = t0
        # GPS time of boot time 0: a whole number of seconds before the first sample
        self.boot0_gps = math.floor(t0) - boot_lead_s
        self.boot_epoch = 0
        self.mav = m.MAVLink(None, srcSystem=1, srcComponent=1)
        self.parser = m.MAVLink(None)
        self.parser.robust_parsing = True
        if signing_key is not None:
            self._setup_signing(signing_key)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.imu_rate_hz = sim.scenario.imu.rate_hz
        # an autopilot that streams the IMU slower than asked (ArduPilot's scheduler/link budget)
        self.imu_stream_max_hz = min(self.imu_rate_hz, max_imu_rate_hz or self.imu_rate_hz)
        # redundant IMUs 1, 2 (SCALED_IMU2, SCALED_IMU3 like ArduPilot): independent error realisations
        if not 1 <= imu_units <= 3:
            raise ValueError("imu_units: 1 to 3")
        self.extra_imu = sim.extra_imu_units(imu_units - 1)
        self.default_intervals = {m.MAVLINK_MSG_ID_HEARTBEAT: 1e6, m.MAVLINK_MSG_ID_SYSTEM_TIME: 1e6}
        self.intervals: dict[int, float] = dict(self.default_intervals)
        self.gps1 = bytearray()
        # GPS1 locked by a SERIAL_CONTROL request with EXCLUSIVE (AP_GPS::lock_port); while it is
        # not, ArduPilot's own GPS driver reads the port, so the receiver's bytes do not pile up
        # for the companion's next probe (they did: a re-claim after an outage read a 4-s backlog)
        self.gps1_locked = False
        self.received: list[Received] = []
        self.imu_sent: dict[int, list] = defaultdict(list)    # boot_us -> [(send_mono_ns, t_gps)]
        self.counters = defaultdict(int)
        self.companion_seen = asyncio.Event()
        self.silent_until_gps = -1e18
        self.ekf_origin: tuple[int, int, int] | None = None    # lat e7, lon e7, alt mm (cm resolution)
        if self.faults.preset_origin_ned_m is not None:
            self.ekf_origin = self._origin_near_start(self.faults.preset_origin_ned_m)
        self._next_due: dict[int, float] = {}
        self._ubx_frames = []
        self._build_receiver_stream()
        self._fix_list = self._build_fixes()
        self.done = asyncio.Event()

    def _setup_signing(self, key: bytes) -> None:
        """MAVLink 2 signing as ArduPilot after SETUP_SIGNING: everything sent is signed (link id 0,
        timestamp from the wall clock in 10-us units since 2015, +1 per frame), and incoming frames
        must verify (pymavlink's own check; no unsigned ones: they arrive as BAD_DATA)."""
        from companion.io.mavlink_signing import sign_encoder
        sign_encoder(self.mav, key, link_id=0)
        self.parser.signing.secret_key = bytes(key)

    # -- simulated receiver ------------------------------------------------------------------
    def _build_receiver_stream(self) -> None:
        lat = self.receiver_latency_s
        rng = np.random.default_rng([int(self.rng.integers(1 << 31)), 779])
        for ep in self.sim.rover_epochs:
            extra = b""
            if self.moving_baseline_b is not None:
                r, _, C_b_e = self.sim.truth_at(ep.t_gps)
                la, lo, _ = ecef_to_geodetic(r)
                ned = C_n_e(la, lo).T @ C_b_e @ self.moving_baseline_b
                extra = relposned_frame(ep.t_gps, ned + rng.standard_normal(3) * self.baseline_sigma_ned_m,
                                        self.baseline_sigma_ned_m)
            self._ubx_frames.append((ep.t_gps + lat, ep, extra))

    def _build_fixes(self):
        out = []
        for ep in self.sim.rover_epochs:
            r = self.sim.antenna_at(ep.t_gps)
            r = r + self.rng.normal(0.0, self.gps_noise_m, 3)
            r_imu, v, C_b_e = self.sim.truth_at(ep.t_gps)
            yaw_cdeg = 0                                  # 0 = this GPS provides no yaw
            if self.gps_yaw_sigma_deg is not None:
                la, lo, _ = ecef_to_geodetic(r_imu)
                C = C_n_e(la, lo).T @ C_b_e
                yaw = math.degrees(math.atan2(C[1, 0], C[0, 0])) + self.rng.normal(0.0, self.gps_yaw_sigma_deg)
                yaw_cdeg = int(round((yaw % 360.0) * 100.0)) % 36000 or 36000     # 36000 = north
            out.append((ep.t_gps, r, v, len(ep.observations), yaw_cdeg))
        return out

    # -- time --------------------------------------------------------------------------------
    def boot_us(self, t_gps: float) -> int:
        return int(round((t_gps - self.boot0_gps) * 1e6))

    # -- sending -----------------------------------------------------------------------------
    def send(self, msg) -> None:
        data = bytes(msg.pack(self.mav))
        t_rel = self.clock.now_gps() - self.t0
        for (a, b, p) in self.faults.corrupt:
            if a <= t_rel < b and self.prng.random() < p:
                self.counters["corrupted_frames"] += 1
                bad = bytearray(data)
                k = self.prng.randrange(len(bad))
                bad[k] ^= 0xFF
                data = bytes(bad)
                if self.prng.random() < 0.5:
                    self._sendto(bytes(self.prng.randrange(256) for _ in range(self.prng.randrange(1, 40))))
                break
        self._sendto(data)

    # -- faults of the integrity matrix ------------------------------------------------------
    def _faulty_rates(self, k: int, t_rel: float, w, a):
        """Faults.imu_override and imu_noise on the primary IMU's rates of sample ``k``."""
        f = self.faults
        if not (f.imu_override or f.imu_noise):
            return w, a
        for t0, n, acc, gyr in f.imu_override:
            if t0 <= t_rel < t0 + (n - 0.5) / self.imu_rate_hz:
                a = np.asarray(acc, float) if acc is not None else a
                w = np.asarray(gyr, float) if gyr is not None else w
                self.counters["imu_samples_overridden"] += 1
        for t0, t1, sa, sg in f.imu_noise:
            if t0 <= t_rel < t1:
                a = a + self.fault_rng.normal(0.0, sa, 3)
                w = w + self.fault_rng.normal(0.0, sg, 3)
        return w, a

    def _spoof_offset_e(self, t_gps: float, r_e) -> np.ndarray:
        """ECEF offset of the spoofed position at ``t_gps`` (Faults.gnss_offset_ned), else zero."""
        for t0, t1, ned in self.faults.gnss_offset_ned:
            if t0 <= t_gps - self.t0 < t1:
                lat, lon, _ = ecef_to_geodetic(r_e)
                return C_n_e(lat, lon) @ np.asarray(ned, float)
        return np.zeros(3)

    def _faulty_epoch(self, ep):
        """The rover epoch as a spoofer or a stepping receiver clock makes it: every code and carrier
        moved by the range change of the offset position (line of sight from the broadcast orbit)
        and by c * (clock jumps so far)."""
        f = self.faults
        jump_s = sum(j for t, j in f.rover_clock_jump if ep.t_gps - self.t0 >= t)
        r_ant = self.sim.antenna_at(ep.t_gps)
        d_e = self._spoof_offset_e(ep.t_gps, r_ant)
        if jump_s == 0.0 and not d_e.any():
            return ep
        obs = []
        for o in ep.observations:
            d_m = jump_s * SPEED_OF_LIGHT_MPS
            eph = self._ephs.get(o.sat)
            if d_e.any() and eph is not None:
                _, _, r_sat, _, _, _ = light_time_range(eph, ep.t_gps, r_ant)
                u = (r_sat - r_ant) / np.linalg.norm(r_sat - r_ant)
                d_m -= float(u @ d_e)
            obs.append(dataclasses.replace(o, pseudorange_m=o.pseudorange_m + d_m,
                                           carrier_cycles=o.carrier_cycles + d_m / o.wavelength_m))
        self.counters["rover_epochs_faulty"] += 1
        return dataclasses.replace(ep, observations=tuple(obs))

    def _imu_frame_lost(self, t_rel: float) -> bool:
        """Faults.imu_loss: this IMU frame never reaches the companion (decided per frame)."""
        for a, b, p in self.faults.imu_loss:
            if a <= t_rel < b and self.loss_rng.random() < p:
                return True
        return False

    def _sendto(self, data: bytes) -> None:
        try:
            self.sock.sendto(data, self.addr)
            self.counters["tx_datagrams"] += 1
        except OSError:
            self.counters["tx_errors"] += 1

    def _interval_due(self, msg_id: int, t_gps: float) -> bool:
        iv = self.intervals.get(msg_id)
        if iv is None or iv <= 0:
            return False
        nd = self._next_due.get(msg_id)
        if nd is None or t_gps >= nd - 1e-9:
            period = iv * 1e-6
            base = nd if nd is not None and t_gps - nd < period else t_gps
            self._next_due[msg_id] = base + period
            return True
        return False

    # -- receiving ---------------------------------------------------------------------------
    def _on_readable(self) -> None:
        while True:
            try:
                data, addr = self.sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            t = time.monotonic_ns()
            try:
                msgs = self.parser.parse_buffer(data) or []
            except Exception:
                self.counters["rx_parse_errors"] += 1
                continue
            for msg in msgs:
                self._handle(msg, t)

    def _handle(self, msg, t_ns: int) -> None:
        mt = msg.get_type()
        self.counters["rx_" + mt] += 1
        if mt == "HEARTBEAT":
            self.companion_seen.set()
            return
        if self.clock.started.is_set() and self.clock.now_gps() < self.silent_until_gps:
            return                      # rebooting: deaf
        if mt in ("VISION_POSITION_ESTIMATE", "ODOMETRY", "GPS_INPUT", "SET_GPS_GLOBAL_ORIGIN", "STATUSTEXT",
                  "GPS_RTCM_DATA", "NAMED_VALUE_FLOAT"):
            self.received.append(Received(t_ns, mt, msg))
            if mt == "SET_GPS_GLOBAL_ORIGIN" and self.ekf_origin is None:
                self.ekf_origin = (int(msg.latitude), int(msg.longitude), int(msg.altitude / 10) * 10)
                self._send_origin()
        elif mt == "COMMAND_LONG" and msg.command == m.MAV_CMD_REQUEST_MESSAGE:
            self.send(self.mav.command_ack_encode(msg.command, m.MAV_RESULT_ACCEPTED))
            if int(msg.param1) == m.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
                self._send_origin()
        elif mt == "COMMAND_LONG" and msg.command == m.MAV_CMD_SET_MESSAGE_INTERVAL:
            mid, iv = int(msg.param1), float(msg.param2)
            if iv == 0:
                self.intervals[mid] = self.default_intervals.get(mid, 0.0)
            elif iv < 0:
                self.intervals[mid] = 0.0
            else:
                self.intervals[mid] = max(iv, 1e6 / self.imu_stream_max_hz if mid in (
                    m.MAVLINK_MSG_ID_HIGHRES_IMU, m.MAVLINK_MSG_ID_RAW_IMU, m.MAVLINK_MSG_ID_SCALED_IMU2,
                    m.MAVLINK_MSG_ID_SCALED_IMU3) else 1e3)
            self._next_due.pop(mid, None)
            self.send(self.mav.command_ack_encode(msg.command, m.MAV_RESULT_ACCEPTED))
        elif mt == "TIMESYNC" and msg.tc1 == 0 and self.clock.started.is_set():
            now_boot_ns = int((self.clock.now_gps() - self.boot0_gps) * 1e9)
            self.send(self.mav.timesync_encode(now_boot_ns, msg.ts1))
        elif mt == "SERIAL_CONTROL" and msg.device == m.SERIAL_CONTROL_DEV_GPS1:
            self.counters["serial_control_requests"] += 1
            self.gps1_locked = bool(msg.flags & m.SERIAL_CONTROL_FLAG_EXCLUSIVE)
            if not (msg.flags & m.SERIAL_CONTROL_FLAG_RESPOND):
                return
            replies = 0
            while True:
                n = min(70, len(self.gps1))
                chunk = bytes(self.gps1[:n])
                del self.gps1[:n]
                self.send(self.mav.serial_control_encode(msg.device, m.SERIAL_CONTROL_FLAG_REPLY, 0, 0, n,
                                                         list(chunk) + [0] * (70 - n)))
                replies += 1
                if not (msg.flags & m.SERIAL_CONTROL_FLAG_MULTI and n >= 70 and replies < 16):
                    break

    def _origin_near_start(self, ned_m) -> tuple[int, int, int]:
        """lat e7, lon e7, alt mm of the truth start position moved by ``ned_m`` (ArduPilot's scaling)."""
        lat, lon, h = ecef_to_geodetic(self.sim.truth_at(self.t0)[0])
        k = 0.011131884502145034                   # ArduPilot LOCATION_SCALING_FACTOR, m per 1e-7 deg
        return (int(round(math.degrees(lat) * 1e7 + ned_m[0] / k)),
                int(round(math.degrees(lon) * 1e7 + ned_m[1] / (k * math.cos(lat)))),
                10 * int(round((h - ned_m[2]) * 100.0)))

    def _send_origin(self) -> None:
        """GPS_GLOBAL_ORIGIN, also recorded: the origin the autopilot's NED frame really has."""
        if self.ekf_origin is not None:
            boot_us = int((self.clock.now_gps() - self.boot0_gps) * 1e6) if self.clock.started.is_set() else 0
            msg = self.mav.gps_global_origin_encode(*self.ekf_origin, max(boot_us, 0))
            self.send(msg)
            self.received.append(Received(time.monotonic_ns(), "GPS_GLOBAL_ORIGIN", msg))

    # -- the stream --------------------------------------------------------------------------
    async def wait_for_companion(self, timeout_s: float = 30.0) -> bool:
        """HEARTBEATs (only) until the companion answers; True when it did."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            self.send(self.mav.heartbeat_encode(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0,
                                                m.MAV_STATE_STANDBY))
            try:
                await asyncio.wait_for(self.companion_seen.wait(), 0.5)
                return True
            except asyncio.TimeoutError:
                pass
        return False

    async def run(self, duration_s: float, warmup_s: float = 1.0) -> None:
        loop = asyncio.get_running_loop()
        loop.add_reader(self.sock.fileno(), self._on_readable)
        try:
            await self.wait_for_companion()
            # warm-up: heartbeats while the companion sets up its streams (in real time)
            t_end_w = time.monotonic() + warmup_s
            while time.monotonic() < t_end_w:
                self.send(self.mav.heartbeat_encode(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0,
                                                    m.MAV_STATE_STANDBY))
                await asyncio.sleep(0.2)
            self.clock.start(self.t0)
            await self._stream(duration_s)
        finally:
            loop.remove_reader(self.sock.fileno())
            self.done.set()

    def _rest_until_gps(self) -> float:
        events = getattr(self.sim.scenario.trajectory, "events", None) or []
        for ev in events:
            if ev[0] == "rest":
                return self.t0 + ev[2]
        return self.t0 + 8.0

    async def _stream(self, duration_s: float) -> None:
        sim = self.sim
        imu = sim.imu
        t_end = self.t0 + duration_s
        dec = 1
        i_ubx = 0
        i_fix = 0
        last_fix = None
        armed_at = self._rest_until_gps()
        faults = self.faults
        reboots = sorted(faults.reboot)
        jumps = sorted(faults.clock_jump)
        for k, s in enumerate(imu):
            t = s.t_gps
            if t > t_end:
                break
            due = self.clock.mono_at(t)
            d = due - time.monotonic()
            if d > 0.0005:
                await asyncio.sleep(d)
            elif k % 20 == 0:
                await asyncio.sleep(0)
            t_rel = t - self.t0
            # faults: reboot / clock jump
            if reboots and t_rel >= reboots[0][0]:
                _, silent = reboots.pop(0)
                self.silent_until_gps = t + silent
                self.boot0_gps = t + silent          # boot time restarts at 0 after the silence
                self.boot_epoch += 1
                self.intervals = dict(self.default_intervals)
                self._next_due.clear()
                self.gps1.clear()
                self.gps1_locked = False
                self.ekf_origin = None
                self.counters["reboots"] += 1
            if jumps and t_rel >= jumps[0][0]:
                _, j = jumps.pop(0)
                self.boot0_gps -= j
                self.counters["clock_jumps"] += 1
            if t < self.silent_until_gps:
                continue
            # receiver: UBX bytes into the GPS1 port buffer
            while i_ubx < len(self._ubx_frames) and self._ubx_frames[i_ubx][0] <= t:
                t_out, ep, extra = self._ubx_frames[i_ubx]
                i_ubx += 1
                if any(a <= ep.t_gps - self.t0 < b for a, b in faults.gnss_outage):
                    continue
                self.gps1 += rawx_frame(self._faulty_epoch(ep), self.leap_seconds) + extra
                if not self.gps1_locked:
                    self.gps1.clear()                # the autopilot's GPS driver took them
                elif len(self.gps1) > 16384:        # a UART buffer overflows: oldest bytes lost
                    del self.gps1[:len(self.gps1) - 16384]
            while i_fix < len(self._fix_list) and self._fix_list[i_fix][0] + self.receiver_latency_s <= t:
                last_fix = self._fix_list[i_fix]
                i_fix += 1
            boot_us = self.boot_us(t)
            # IMU
            iv = self.intervals.get(m.MAVLINK_MSG_ID_HIGHRES_IMU if self.imu_message == "HIGHRES_IMU"
                                    else m.MAVLINK_MSG_ID_RAW_IMU, 0.0)
            if iv and iv > 0:
                dec = max(1, int(round(iv * 1e-6 * self.imu_rate_hz)))
                if k % dec == 0:
                    w, a = self._faulty_rates(k, t_rel, s.dtheta_b / s.dt_s, s.dv_b / s.dt_s)
                    if self.imu_message == "HIGHRES_IMU":
                        msg = self.mav.highres_imu_encode(boot_us, a[0], a[1], a[2], w[0], w[1], w[2],
                                                          0, 0, 0, 0, 0, 0, 25.0, 0x3F, 0)
                    else:
                        ka = 1000.0 / STANDARD_GRAVITY_MPS2
                        q = [int(max(-32768, min(32767, round(x)))) for x in (*(a * ka), *(w * 1000.0))]
                        msg = self.mav.raw_imu_encode(boot_us, q[0], q[1], q[2], q[3], q[4], q[5], 0, 0, 0, 0, 25)
                    if self._imu_frame_lost(t_rel):
                        self.counters["imu_lost"] += 1
                    else:
                        self.send(msg)
                        self.imu_sent[boot_us].append((time.monotonic_ns(), t))
                        self.counters["imu_sent"] += 1
            for unit, (dth_u, dv_u) in enumerate(self.extra_imu, start=1):
                mid = (m.MAVLINK_MSG_ID_SCALED_IMU2, m.MAVLINK_MSG_ID_SCALED_IMU3)[unit - 1]
                iv = self.intervals.get(mid, 0.0)
                if not (iv and iv > 0) or k % max(1, int(round(iv * 1e-6 * self.imu_rate_hz))):
                    continue
                w = dth_u[k] / s.dt_s
                a = dv_u[k] / s.dt_s
                for t_f, u_f, bias in faults.imu_unit_bias:
                    if u_f == unit and t_rel >= t_f:
                        w = w + np.array([bias, 0.0, 0.0])
                ka = 1000.0 / STANDARD_GRAVITY_MPS2     # mG and mrad/s, int16, time_boot_ms
                q = [int(max(-32768, min(32767, round(x)))) for x in (*(a * ka), *(w * 1000.0))]
                enc = self.mav.scaled_imu2_encode if unit == 1 else self.mav.scaled_imu3_encode
                if self._imu_frame_lost(t_rel):
                    self.counters[f"imu_unit{unit}_lost"] += 1
                    continue
                self.send(enc(boot_us // 1000, q[0], q[1], q[2], q[3], q[4], q[5], 0, 0, 0, 0))
                self.counters[f"imu_unit{unit}_sent"] += 1
            # other streams
            if self._interval_due(m.MAVLINK_MSG_ID_HEARTBEAT, t):
                armed = t >= armed_at
                status = m.MAV_STATE_ACTIVE if armed else m.MAV_STATE_STANDBY
                self.send(self.mav.heartbeat_encode(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                    m.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0, 0, status))
            if self._interval_due(m.MAVLINK_MSG_ID_SYSTEM_TIME, t):
                boot_ms = boot_us // 1000
                t_gps_ms = self.boot0_gps + boot_ms * 1e-3
                unix_us = int(round((t_gps_ms + GPS_EPOCH_UNIX_S - self.leap_seconds
                                     - self.system_time_late_s) * 1e6))
                self.send(self.mav.system_time_encode(unix_us, boot_ms))
            if self._interval_due(m.MAVLINK_MSG_ID_ATTITUDE, t) and not faults.no_attitude:
                r, v, C = sim.truth_at(t)
                lat, lon, _ = ecef_to_geodetic(r)
                roll, pitch, yaw = dcm_to_euler(C_n_e(lat, lon).T @ C)
                nz = self.rng.normal(0.0, self.attitude_noise_rad, 3)
                yaw += nz[2] + math.radians(faults.attitude_yaw_error_deg)
                self.send(self.mav.attitude_encode(boot_us // 1000, roll + nz[0], pitch + nz[1],
                                                   (yaw + math.pi) % (2 * math.pi) - math.pi, 0, 0, 0))
            if self._interval_due(m.MAVLINK_MSG_ID_GPS_RAW_INT, t):
                self._send_gps_raw(last_fix, t)
        self.counters["sim_seconds"] = int(t - self.t0)

    def _send_gps_raw(self, fix, t: float) -> None:
        outage = fix is None or t - fix[0] > 1.5 or self.boot_us(fix[0] + self.receiver_latency_s) < 0 \
            or any(a <= fix[0] - self.t0 < b for a, b in self.faults.gnss_outage)
        if outage:
            self.send(self.mav.gps_raw_int_encode(self.boot_us(t), 1, 0, 0, 0, 65535, 65535, 65535, 65535, 0))
            return
        t_fix, r, v, nsat, yaw_cdeg = fix
        r = r + self._spoof_offset_e(t_fix, r)
        lat, lon, h = ecef_to_geodetic(r)
        v_n = C_n_e(lat, lon).T @ v
        speed = math.hypot(v_n[0], v_n[1])
        cog = (math.degrees(math.atan2(v_n[1], v_n[0])) + 360.0) % 360.0
        self.send(self.mav.gps_raw_int_encode(
            self.boot_us(t_fix + self.receiver_latency_s), 3, int(round(math.degrees(lat) * 1e7)),
            int(round(math.degrees(lon) * 1e7)), int(round(h * 1000)), 120, 180, int(round(speed * 100)),
            int(round(cog * 100)) % 36000, nsat, int(round(h * 1000)), int(self.gps_noise_m * 1500),
            int(self.gps_noise_m * 2500), 300, 0, yaw_cdeg))

    # -- results -----------------------------------------------------------------------------
    def estimates(self):
        return [r for r in self.received if r.msg_type in ("VISION_POSITION_ESTIMATE", "ODOMETRY", "GPS_INPUT")]

    def imu_send_record(self, boot_us: int, arrival_ns: int):
        """(send_mono_ns, t_gps) of the IMU sample with this boot time sent last before ``arrival_ns``."""
        best = None
        for rec in self.imu_sent.get(int(boot_us), ()):
            if rec[0] <= arrival_ns and (best is None or rec[0] > best[0]):
                best = rec
        return best

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass


__all__ = ["EmulatedAutopilot", "SimClock", "Faults", "rawx_frame", "Received"]
