"""Simulated base station: RTCM 3 from the scenario's base epochs, served through an NTRIP caster.

Encoding
--------
pyrtcm 1.2 only *parses* (``RTCMMessage(payload=...)``); it has no field-wise constructor, so the
messages are encoded here with a small MSB-first bit writer, straight from RTCM 10403.x, and
cross-checked by decoding them back with :class:`companion.io.rtcm.RtcmDecoder` (tests):

* **1005** station ARP (ECEF, 0.1 mm), with **1033** the base's antenna and receiver descriptors
  (what a CORS caster sends: the companion names its base on the health report and status page);
* **1004** GPS L1 observations (extended: pseudorange modulo one light-millisecond at 2 cm,
  integer milliseconds, phase-range minus pseudorange at 0.5 mm, lock-time indicator, C/N0); L2
  fields are sent as "invalid" (the simulated receivers are single frequency).  The carrier is
  referenced to the *quantised* pseudorange so that its 0.5 mm resolution survives; its integer
  cycle offset (DF012 only spans +-262 m) is chosen per satellite at the first epoch of a lock and
  kept constant (the decoder's roll-over logic does the rest), so time-differenced carrier is exact;
* or, with ``observations='msm7'`` (the dual-frequency ``rtk`` scenarios, and any sky beyond GPS),
  **1077** GPS MSM7 L1 C/A and L2 (as 2W and 2X) with Doppler, and for a multi-GNSS sky also
  **1097** Galileo (E1 1C, E5b 7Q) and **1127** BeiDou (B1I 2I, B3I 6I), one epoch's frames back
  to back with the multiple-message bit: :class:`sitl.rtcm_msm.MultiMsm7Encoder`;
* **1019** GPS, **1046** Galileo I/NAV and **1042** BeiDou ephemerides
  (:mod:`sitl.rtcm_eph_encode`; the ephemerides go to the companion this way instead of as UBX
  RXM-SFRBX subframes from the rover: simpler, and what a multi-GNSS base or caster sends;
  documented in :mod:`sitl.autopilot`).

Serving
-------
:class:`RtcmSource` is an asyncio TCP *server* that writes the frames to every connected client at
the simulated time each base epoch becomes available (epoch + ``latency_s``), paced by the shared
:class:`sitl.autopilot.SimClock`; 1005 every ``station_interval_s`` and all 1019 every
``ephemeris_interval_s`` (and at the first epoch).  :func:`start_caster` puts an NTRIP caster in
front of it: RTKLIB ``str2str -in tcpcli://127.0.0.1:SRC -out ntripc://user:pass@:PORT/MOUNT``
when ``str2str`` is installed, else :class:`MiniNtripCaster` (a few lines of asyncio that answers
``GET /MOUNT`` with ``ICY 200 OK`` and relays the stream; no source table beyond a minimal one).

Exposure: the source and :class:`MiniNtripCaster` listen on 127.0.0.1 only.  RTKLIB's ``ntripc``
output cannot be given a listen address (2.4.3: ``ntripc://u:p@127.0.0.1:PORT/MNT`` still binds
0.0.0.0, checked with ``ss -ltn``), so with str2str the caster is reachable from the network while
the harness runs; the password is therefore a fresh random token per run unless the caller gives
one (the stream is the simulation's, but a fixed ``sitl:sitl`` would let anyone on the LAN in).
"""
from __future__ import annotations

import asyncio
import base64
import logging
import math
import secrets
import shutil
import subprocess
from dataclasses import dataclass

from companion.io.rtcm import crc24q, lock_time_df013
from companion.messages import SECONDS_PER_WEEK, BaseStationPosition, GnssEpoch, GpsEphemeris

log = logging.getLogger(__name__)

LIGHT_MS_M = 299792.458
PI_GPS = 3.1415926535898


class BitWriter:
    """MSB-first bit packing (RTCM 3 field order)."""

    def __init__(self):
        self.value = 0
        self.nbits = 0

    def u(self, n: int, v: int) -> "BitWriter":
        v = int(v)
        if v < 0 or v >= (1 << n):
            raise ValueError(f"{v} does not fit in {n} unsigned bits")
        self.value = (self.value << n) | v
        self.nbits += n
        return self

    def s(self, n: int, v: int) -> "BitWriter":
        v = int(v)
        if not -(1 << (n - 1)) <= v < (1 << (n - 1)):
            raise ValueError(f"{v} does not fit in {n} signed bits")
        return self.u(n, v & ((1 << n) - 1))

    def to_bytes(self) -> bytes:
        pad = (-self.nbits) % 8
        nbytes = (self.nbits + pad) // 8
        return (self.value << pad).to_bytes(nbytes, "big")


def frame(payload: bytes) -> bytes:
    """RTCM 3 transport frame: preamble, 10-bit length, payload, CRC-24Q."""
    if len(payload) > 1023:
        raise ValueError("RTCM payload longer than 1023 bytes")
    head = bytes([0xD3, (len(payload) >> 8) & 0x03, len(payload) & 0xFF])
    body = head + payload
    return body + crc24q(body).to_bytes(3, "big")


def encode_1005(station_id: int, r_e) -> bytes:
    w = BitWriter()
    w.u(12, 1005).u(12, station_id).u(6, 0).u(1, 1).u(1, 0).u(1, 0).u(1, 0)
    w.s(38, round(r_e[0] / 1e-4)).u(1, 0).u(1, 0)
    w.s(38, round(r_e[1] / 1e-4)).u(2, 0)
    w.s(38, round(r_e[2] / 1e-4))
    return frame(w.to_bytes())


#: what the simulated base says it is (1033): no IGS antenna, the simulator as the receiver
SITL_BASE_ANTENNA = "NONE NONE"
SITL_BASE_RECEIVER = "COMPANION SITL BASE"


def encode_1033(station_id: int, antenna: str = SITL_BASE_ANTENNA, receiver: str = SITL_BASE_RECEIVER,
                firmware: str = "", antenna_serial: str = "", receiver_serial: str = "") -> bytes:
    """1033: antenna descriptor, setup ID 0 and serial, receiver type, firmware and serial (DF029-
    DF232: after the 24-bit header every field is whole bytes, each string after its 8-bit count)."""
    w = BitWriter()
    w.u(12, 1033).u(12, station_id)
    for text in (antenna, None, antenna_serial, receiver, firmware, receiver_serial):
        if text is None:
            w.u(8, 0)                                # DF031 antenna setup ID
            continue
        raw = text.encode("ascii")
        if len(raw) > 31:
            raise ValueError(f"RTCM descriptor longer than 31 characters: {text!r}")
        w.u(8, len(raw))
        for c in raw:
            w.u(8, c)
    return frame(w.to_bytes())


def lock_indicator_df013(lock_s: float) -> int:
    """Largest DF013 indicator whose guaranteed minimum lock time does not exceed ``lock_s``."""
    if not math.isfinite(lock_s) or lock_s <= 0:
        return 0
    best = 0
    for i in range(128):
        if lock_time_df013(i) <= lock_s:
            best = i
        else:
            break
    return best


class CarrierReference:
    """The integer cycles taken off each satellite's carrier so that what an RTCM message carries,
    phase range minus a reference range, fits its field: chosen at the first epoch of a lock (the
    carrier brought next to the reference) and kept while the satellite stays locked, so the
    time-differenced carrier is exact; chosen again (a new lock) when the difference drifts out of
    ``limit_m``.  ``reference(o, ref_m)`` -> (cycles, why a new reference was taken: None, "lock"
    (a new lock of the signal) or "range" (out of range inside a lock: the encoder must report a
    new lock)); :meth:`forget` the satellites of an epoch that were not seen."""

    def __init__(self, limit_m: float):
        self.limit_m = limit_m
        self._cycles: dict[str, tuple[int, float]] = {}     # sat -> (cycles, last lock time)

    def reference(self, o, ref_m: float) -> tuple[int, str | None]:
        lam = o.wavelength_m
        lock = o.lock_time_s if math.isfinite(o.lock_time_s) else 0.0
        prev = self._cycles.get(o.sat)
        why = "lock" if prev is None or o.loss_of_lock or lock < prev[1] else None
        k = round((o.carrier_cycles * lam - ref_m) / lam) if why else prev[0]
        if abs((o.carrier_cycles - k) * lam - ref_m) >= self.limit_m:     # drifted out of range
            k, why = round((o.carrier_cycles * lam - ref_m) / lam), why or "range"
        self._cycles[o.sat] = (k, lock)
        return k, why

    def forget(self, seen) -> None:
        for sat in [s for s in self._cycles if s not in seen]:
            del self._cycles[sat]


class Rtcm1004Encoder:
    """Stateful 1004 encoder (keeps each satellite's carrier cycle offset while it stays locked)."""

    def __init__(self, station_id: int):
        self.station_id = station_id
        self._carrier = CarrierReference(limit_m=262.0)        # DF012 spans +-262 m

    def encode(self, epoch: GnssEpoch, more_follow: bool = False) -> bytes:
        obs = [o for o in epoch.observations if o.sat.startswith("G") and o.signal == "L1C"
               and math.isfinite(o.pseudorange_m)][:31]
        week = int(epoch.t_gps // SECONDS_PER_WEEK)
        tow_ms = round((epoch.t_gps - week * SECONDS_PER_WEEK) * 1000.0)
        w = BitWriter()
        w.u(12, 1004).u(12, self.station_id).u(30, tow_ms).u(1, int(more_follow)).u(5, len(obs))
        w.u(1, 0).u(3, 0)
        seen = set()
        for o in obs:
            prn = int(o.sat[1:])
            amb = int(o.pseudorange_m // LIGHT_MS_M)
            rem = o.pseudorange_m - amb * LIGHT_MS_M
            df011 = round(rem / 0.02)
            if df011 >= (1 << 24) - 1:
                amb, df011 = amb + 1, 0
            pr_q = amb * LIGHT_MS_M + df011 * 0.02
            df012 = -(1 << 19)                         # 0x80000: no valid phase
            if math.isfinite(o.carrier_cycles):
                k, _ = self._carrier.reference(o, pr_q)
                df012 = round(((o.carrier_cycles - k) * o.wavelength_m - pr_q) / 0.0005)
                seen.add(o.sat)
            lock_ind = lock_indicator_df013(o.lock_time_s)
            cnr = o.cn0_dbhz if math.isfinite(o.cn0_dbhz) else 0.0
            w.u(6, prn).u(1, 0).u(24, df011).s(20, df012).u(7, lock_ind).u(8, amb)
            w.u(8, max(0, min(255, round(cnr / 0.25))))
            w.u(2, 0).s(14, -(1 << 13)).s(20, -(1 << 19)).u(7, 0).u(8, 0)   # L2 invalid
        self._carrier.forget(seen)
        return frame(w.to_bytes())


def encode_1019(e: GpsEphemeris) -> bytes:
    sc = PI_GPS
    ura = 0
    for i, v in enumerate((2.4, 3.4, 4.85, 6.85, 9.65, 13.65, 24.0, 48.0, 96.0, 192.0, 384.0, 768.0,
                           1536.0, 3072.0, 6144.0)):
        if e.ura_m <= v:
            ura = i
            break
    w = BitWriter()
    w.u(12, 1019).u(6, int(e.sat[1:])).u(10, e.week % 1024).u(4, ura).u(2, 1)
    w.s(14, round(e.idot_radps / sc / 2 ** -43)).u(8, e.iode & 0xFF)
    w.u(16, round(e.toc_s / 16)).s(8, round(e.af2_sps2 / 2 ** -55)).s(16, round(e.af1_sps / 2 ** -43))
    w.s(22, round(e.af0_s / 2 ** -31)).u(10, e.iodc & 0x3FF).s(16, round(e.crs_m / 2 ** -5))
    w.s(16, round(e.delta_n_radps / sc / 2 ** -43)).s(32, round(e.m0_rad / sc / 2 ** -31))
    w.s(16, round(e.cuc_rad / 2 ** -29)).u(32, round(e.e / 2 ** -33)).s(16, round(e.cus_rad / 2 ** -29))
    w.u(32, round(e.sqrt_a / 2 ** -19)).u(16, round(e.toe_s / 16)).s(16, round(e.cic_rad / 2 ** -29))
    w.s(32, round(_wrap_sc(e.omega0_rad / sc) / 2 ** -31)).s(16, round(e.cis_rad / 2 ** -29))
    w.s(32, round(_wrap_sc(e.i0_rad / sc) / 2 ** -31)).s(16, round(e.crc_m / 2 ** -5))
    w.s(32, round(_wrap_sc(e.omega_rad / sc) / 2 ** -31)).s(24, round(e.omega_dot_radps / sc / 2 ** -43))
    w.s(8, round(e.tgd_s / 2 ** -31)).u(6, e.health & 0x3F).u(1, 0).u(1, 1 if e.fit_interval_h > 4 else 0)
    return frame(w.to_bytes())


def _wrap_sc(x: float) -> float:
    """Semicircles into [-1, 1)."""
    return (x + 1.0) % 2.0 - 1.0


# ---------------------------------------------------------------------------------------------
@dataclass
class _Client:
    writer: asyncio.StreamWriter


class RtcmServer:
    """asyncio TCP server (127.0.0.1) that writes RTCM frames to every connected client: the
    stream an NTRIP caster relays (see :func:`start_caster`)."""

    def __init__(self, *, host: str = "127.0.0.1", port: int = 0):
        self.host, self.port = host, port
        self.clients: list[_Client] = []
        self.counters = {"frames": 0, "bytes": 0, "clients": 0, "epochs": 0}
        self._server = None

    async def start(self) -> int:
        self._server = await asyncio.start_server(self._on_client, self.host, self.port)
        self.port = self._server.sockets[0].getsockname()[1]
        return self.port

    async def _on_client(self, reader, writer) -> None:
        self.clients.append(_Client(writer))
        self.counters["clients"] += 1
        try:
            await reader.read()           # until the client goes away
        except (Exception, asyncio.CancelledError):
            pass
        self.clients = [c for c in self.clients if c.writer is not writer]

    def _send(self, data: bytes) -> None:
        for c in list(self.clients):
            try:
                c.writer.write(data)
            except Exception:
                self.clients.remove(c)
        self.counters["bytes"] += len(data) * max(1, len(self.clients))

    async def close(self) -> None:
        for c in self.clients:
            try:
                c.writer.close()
            except Exception:
                pass
        if self._server is not None:
            self._server.close()


class RtcmSource(RtcmServer):
    """The base station's simulated epochs at simulated time (see module docstring)."""

    def __init__(self, base_epochs: list[GnssEpoch], ephemerides: list[GpsEphemeris], base: BaseStationPosition,
                 clock, *, host: str = "127.0.0.1", port: int = 0, latency_s: float = 0.15,
                 station_interval_s: float = 5.0, ephemeris_interval_s: float = 10.0, observations: str = "1004"):
        super().__init__(host=host, port=port)
        self.epochs = sorted(base_epochs, key=lambda e: e.t_gps)
        self.ephemerides = list(ephemerides)
        self.base, self.clock = base, clock
        self.latency_s = latency_s
        self.station_interval_s, self.ephemeris_interval_s = station_interval_s, ephemeris_interval_s
        if observations == "msm7":        # two frequencies with Doppler, every system (sitl.rtcm_msm)
            from .rtcm_msm import MultiMsm7Encoder
            systems = "".join(sorted({o.sat[0] for ep in self.epochs[:1] for o in ep.observations}
                                     | {e.sat[0] for e in self.ephemerides})) or "G"
            self.enc = MultiMsm7Encoder(base.station_id, systems)
        elif observations == "1004":
            self.enc = Rtcm1004Encoder(base.station_id)
        else:
            raise ValueError(f"observations: '1004' or 'msm7', got {observations!r}")
        self.paused = False          # fault injection: corrections outage

    async def run(self, t_end_gps: float | None = None) -> None:
        """Stream every base epoch at its simulated availability time."""
        from .rtcm_eph_encode import encode_ephemeris
        await self.clock.started.wait()
        last_station = last_eph = -1e18
        for ep in self.epochs:
            if ep.t_gps < self.clock.t_start_gps - 1.0:
                continue
            if t_end_gps is not None and ep.t_gps > t_end_gps:
                break
            await self.clock.sleep_until(ep.t_gps + self.latency_s)
            if self.paused:
                continue
            out = bytearray()
            if ep.t_gps - last_station >= self.station_interval_s:
                out += encode_1005(self.base.station_id, self.base.r_e)
                out += encode_1033(self.base.station_id)
                last_station = ep.t_gps
                self.counters["frames"] += 2
            if ep.t_gps - last_eph >= self.ephemeris_interval_s:
                for e in self.ephemerides:
                    fr = encode_ephemeris(e)
                    if fr is None:
                        self.counters["ephemerides_not_encodable"] = self.counters.get(
                            "ephemerides_not_encodable", 0) + 1
                        continue
                    out += fr
                    self.counters["frames"] += 1
                last_eph = ep.t_gps
            out += self.enc.encode(ep)
            self.counters["frames"] += 1
            self.counters["epochs"] += 1
            self._send(bytes(out))


class MiniNtripCaster:
    """Minimal NTRIP caster (revision 1 answers) relaying one TCP source to any number of clients.
    Used when RTKLIB's str2str is not installed."""

    def __init__(self, source_host: str, source_port: int, mountpoint: str, user: str = "", password: str = "",
                 host: str = "127.0.0.1", port: int = 0):
        self.source = (source_host, source_port)
        self.mountpoint = mountpoint
        self.auth = base64.b64encode(f"{user}:{password}".encode()).decode() if user else None
        self.host, self.port = host, port
        self.clients: list[asyncio.StreamWriter] = []
        self._server = None
        self._task = None

    async def start(self) -> int:
        self._server = await asyncio.start_server(self._on_client, self.host, self.port)
        self.port = self._server.sockets[0].getsockname()[1]
        self._task = asyncio.create_task(self._relay())
        return self.port

    async def _relay(self) -> None:
        while True:
            try:
                reader, _w = await asyncio.open_connection(*self.source)
                while data := await reader.read(4096):
                    for c in list(self.clients):
                        try:
                            c.write(data)
                        except Exception:
                            self.clients.remove(c)
            except (OSError, asyncio.IncompleteReadError):
                pass
            await asyncio.sleep(0.5)

    async def _on_client(self, reader, writer) -> None:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 10.0)
        except Exception:
            writer.close()
            return
        lines = head.decode("latin-1").split("\r\n")
        path = lines[0].split()[1] if len(lines[0].split()) > 1 else "/"
        auth_ok = self.auth is None or any(l.lower().startswith("authorization: basic ") and
                                           l.split()[-1] == self.auth for l in lines)
        if path.lstrip("/") != self.mountpoint:
            writer.write(b"SOURCETABLE 200 OK\r\nContent-Type: text/plain\r\n\r\n"
                         + f"STR;{self.mountpoint};;RTCM 3;;2;GPS;SITL;;0;0;sitl;none;N;N;0;\r\n".encode()
                         + b"ENDSOURCETABLE\r\n")
            writer.close()
            return
        if not auth_ok:
            writer.write(b"HTTP/1.0 401 Unauthorized\r\n\r\n")
            writer.close()
            return
        writer.write(b"ICY 200 OK\r\n")
        self.clients.append(writer)
        try:
            await reader.read()
        except (Exception, asyncio.CancelledError):
            pass
        if writer in self.clients:
            self.clients.remove(writer)

    async def close(self) -> None:
        if self._task:
            self._task.cancel()
        for c in self.clients:
            c.close()
        if self._server:
            self._server.close()


class Caster:
    """Handle on the running caster: ``port``, ``mountpoint``, ``user``, ``password``, ``kind``."""

    def __init__(self, kind, port, mountpoint, user, password, proc=None, mini=None):
        self.kind, self.port, self.mountpoint, self.user, self.password = kind, port, mountpoint, user, password
        self.proc, self.mini = proc, mini

    async def close(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=3)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        if self.mini is not None:
            await self.mini.close()


def free_tcp_port() -> int:
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def start_caster(source_port: int, *, mountpoint: str = "SITL", user: str = "sitl",
                       password: str | None = None, prefer_str2str: bool = True,
                       log_path: str | None = None) -> Caster:
    """NTRIP caster in front of the TCP source on ``source_port`` (str2str if available).
    ``password`` None: a random token for this run (see the module docstring: str2str's caster
    listens on every interface)."""
    if password is None:
        password = secrets.token_hex(12)
    exe = shutil.which("str2str") if prefer_str2str else None
    if exe:
        port = free_tcp_port()
        out = open(log_path, "wb") if log_path else subprocess.DEVNULL
        # -r: reconnect to the source 1 s after it went silent (str2str's default, 10 s, kept the
        # corrections away for up to 10 s after a simulated base outage ended)
        proc = subprocess.Popen([exe, "-in", f"tcpcli://127.0.0.1:{source_port}",
                                 "-out", f"ntripc://{user}:{password}@:{port}/{mountpoint}", "-r", "1000"],
                                stdin=subprocess.DEVNULL, stdout=out, stderr=out)
        # wait until it listens
        for _ in range(50):
            try:
                _r, w = await asyncio.open_connection("127.0.0.1", port)
                w.close()
                break
            except OSError:
                await asyncio.sleep(0.1)
        return Caster("str2str", port, mountpoint, user, password, proc=proc)
    mini = MiniNtripCaster("127.0.0.1", source_port, mountpoint, user, password)
    port = await mini.start()
    return Caster("mini", port, mountpoint, user, password, mini=mini)


__all__ = ["BitWriter", "frame", "encode_1005", "encode_1033", "encode_1019", "CarrierReference", "Rtcm1004Encoder",
           "RtcmServer", "RtcmSource",
           "MiniNtripCaster", "start_caster", "Caster", "lock_indicator_df013"]
