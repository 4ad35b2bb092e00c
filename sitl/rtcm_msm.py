"""RTCM 3 MSM4 (GPS: message 1074) and MSM7 (GPS 1077 L1 + L2, Galileo 1097 E1 + E5b, BeiDou
1127 B1I + B3I) from a simulated base epoch, RTCM 10403.3 3.5.12.

MSM4 is what a u-blox base sends by default (with 1005): pseudorange, carrier phase range, lock
time and C/N0 per satellite and signal, no Doppler.  Written with :class:`sitl.caster.BitWriter`
(pyrtcm only parses) and cross-checked by decoding it back with pyrtcm and with the companion's
:class:`companion.io.rtcm.RtcmDecoder` (tests):

* header: DF002, DF003, DF004 (GPS ms of week), DF393 (multiple message: 0, one system), DF409
  IODS 0, 7 reserved bits, DF411 clock steering 1 (the simulated receivers steer their clocks),
  DF412 0, DF417 0, DF418 0, DF394 satellite mask, DF395 signal mask (GPS L1 C/A = signal 2),
  DF396 cell mask (all 1: every satellite has its one signal);
* satellite data: DF397 rough range in whole milliseconds, DF398 its 1/1024 ms part (the
  pseudorange rounded to 2^-10 ms);
* signal data: DF400 fine pseudorange (2^-24 ms, 1.8 cm), DF401 fine phase range (2^-29 ms,
  0.56 mm), DF402 lock time indicator, DF420 half-cycle ambiguity 0, DF403 C/N0 (1 dB-Hz).

The carrier is referenced to the rough range with :class:`sitl.caster.CarrierReference`: DF401
spans +-2^-8 ms (+-1171 m), so its integer cycles are chosen at the first epoch of a lock and
kept; when the code-carrier divergence runs out of that range the lock time restarts at 0 (the
decoder then sees the new reference as a new lock, as it must).
"""
from __future__ import annotations

import math

from companion.io.rtcm import lock_time_df402, lock_time_df407
from companion.messages import SECONDS_PER_WEEK, GnssEpoch

from .caster import LIGHT_MS_M, BitWriter, CarrierReference, frame

GPS_L1CA_SIGNAL_ID = 2
FINE_PR_LSB_MS = 2.0 ** -24
FINE_PH_LSB_MS = 2.0 ** -29
ROUGH_LSB_MS = 2.0 ** -10


def lock_indicator_df402(lock_s: float) -> int:
    """Largest DF402 indicator whose minimum lock time does not exceed ``lock_s``."""
    if not math.isfinite(lock_s) or lock_s <= 0:
        return 0
    return max((i for i in range(16) if lock_time_df402(i) <= lock_s), default=0)


class Msm4Encoder:
    """Stateful GPS MSM4 (1074) encoder: keeps each satellite's carrier reference while locked."""

    def __init__(self, station_id: int):
        self.station_id = station_id
        self._carrier = CarrierReference(limit_m=2.0 ** -8 * LIGHT_MS_M * 0.999)
        self._lock_restart: dict[str, float] = {}      # sat -> its lock time when the reference was last taken

    def encode(self, epoch: GnssEpoch) -> bytes:
        obs = sorted((o for o in epoch.observations if o.sat.startswith("G") and o.signal == "L1C"
                      and math.isfinite(o.pseudorange_m) and 1 <= int(o.sat[1:]) <= 32),
                     key=lambda o: int(o.sat[1:]))
        week = int(epoch.t_gps // SECONDS_PER_WEEK)
        tow_ms = round((epoch.t_gps - week * SECONDS_PER_WEEK) * 1000.0)
        w = BitWriter()
        w.u(12, 1074).u(12, self.station_id).u(30, tow_ms).u(1, 0).u(3, 0).u(7, 0).u(2, 1).u(2, 0).u(1, 0).u(3, 0)
        sat_mask = sum(1 << (64 - int(o.sat[1:])) for o in obs)
        w.u(64, sat_mask).u(32, 1 << (32 - GPS_L1CA_SIGNAL_ID))
        w.u(len(obs), (1 << len(obs)) - 1)                # one signal per satellite: every cell
        rough, cells = [], []
        seen = set()
        for o in obs:
            r_ms = round(o.pseudorange_m / LIGHT_MS_M / ROUGH_LSB_MS) * ROUGH_LSB_MS
            rough.append(r_ms)
            fine_pr = round((o.pseudorange_m / LIGHT_MS_M - r_ms) / FINE_PR_LSB_MS)
            fine_ph, lock = -(1 << 21), 0.0               # DF401 "invalid"
            if math.isfinite(o.carrier_cycles):
                k, why = self._carrier.reference(o, r_ms * LIGHT_MS_M)
                lock = o.lock_time_s if math.isfinite(o.lock_time_s) else 0.0
                if why is not None:               # "range": re-referenced inside a lock, reported as a new lock
                    self._lock_restart[o.sat] = lock if why == "range" else 0.0
                lock -= self._lock_restart[o.sat]
                fine_ph = round(((o.carrier_cycles - k) * o.wavelength_m / LIGHT_MS_M - r_ms) / FINE_PH_LSB_MS)
                seen.add(o.sat)
            cnr = o.cn0_dbhz if math.isfinite(o.cn0_dbhz) else 0.0
            cells.append((fine_pr, fine_ph, lock_indicator_df402(lock), max(0, min(63, round(cnr)))))
        self._carrier.forget(seen)
        for sat in [s for s in self._lock_restart if s not in seen]:
            del self._lock_restart[sat]
        for r_ms in rough:
            w.u(8, int(r_ms))
        for r_ms in rough:
            w.u(10, round((r_ms - int(r_ms)) / ROUGH_LSB_MS))
        for c in cells:
            w.s(15, c[0])
        for c in cells:
            w.s(22, c[1])
        for c in cells:
            w.u(4, c[2])
        for _ in cells:
            w.u(1, 0)
        for c in cells:
            w.u(6, c[3])
        return frame(w.to_bytes())


def lock_indicator_df407(lock_s: float) -> int:
    """Largest DF407 (MSM6/7, 10 bits) indicator whose minimum lock time does not exceed ``lock_s``."""
    if not math.isfinite(lock_s) or lock_s <= 0:
        return 0
    best = 0
    for i in range(705):
        if lock_time_df407(i) <= lock_s:
            best = i
        else:
            break
    return best


#: RTCM GPS MSM signal ids (RTCM 10403.3 table 3.5-91) of the codes the simulator's signals go out as
GPS_MSM_SIGNAL_ID = {"1C": 2, "1P": 3, "1W": 4, "2C": 8, "2P": 9, "2W": 10, "2S": 15, "2L": 16, "2X": 17,
                     "5I": 22, "5Q": 23, "5X": 24}
#: Galileo (table 3.5-99) and BeiDou (3.5-108) MSM signal ids of the codes used here
GALILEO_MSM_SIGNAL_ID = {"1C": 2, "1B": 4, "1X": 5, "7I": 14, "7Q": 15, "7X": 16, "5I": 22, "5Q": 23, "5X": 24}
BEIDOU_MSM_SIGNAL_ID = {"2I": 2, "2X": 4, "6I": 8, "6X": 10, "7I": 14, "7X": 16}
#: per system: MSM7 message number, signal ids, the code whose pseudorange gives the rough range,
#: the simulator signals -> RTCM codes by default, highest PRN, system time - GPS time (s)
MSM7_SYSTEMS = {
    "G": (1077, GPS_MSM_SIGNAL_ID, "1C", {"L1C": ("1C",), "L2W": ("2W", "2X")}, 32, 0.0),
    "E": (1097, GALILEO_MSM_SIGNAL_ID, "1C", {"L1C": ("1C",), "L7Q": ("7Q",)}, 36, 0.0),
    "C": (1127, BEIDOU_MSM_SIGNAL_ID, "2I", {"L2I": ("2I",), "L6I": ("6I",)}, 63, -14.0),
}
MSM7_FINE_PR_LSB_MS = 2.0 ** -29
MSM7_FINE_PH_LSB_MS = 2.0 ** -31
MSM7_FINE_RATE_LSB_MPS = 1e-4


class Msm7Encoder:
    """Stateful MSM7 encoder of one system (``system`` 'G': 1077, 'E': 1097, 'C': 1127): two
    frequencies per satellite, with Doppler (rough range rate per satellite from the first
    frequency, fine rate per cell where the cell's signal has a Doppler).

    ``codes``: simulator signal -> the RTCM codes it is sent as.  GPS default: L1C as ``1C``; the
    simulator's one L2 observable as ``2W`` and ``2X``, like a geodetic CORS that tracks both
    L2 P(Y) and L2C (the simulator has no quarter cycle between them; a u-blox rover reports L2C
    only, so the companion must pair its L2L with the 2X cell and never with 2W).  Galileo: E1 as
    ``1C``, E5b as ``7Q``; BeiDou: B1I as ``2I``, B3I as ``6I`` (:data:`MSM7_SYSTEMS`).  Each
    (satellite, code) keeps its own carrier reference while locked
    (:class:`sitl.caster.CarrierReference`).  BeiDou's epoch time is BDT (GPS - 14 s)."""

    def __init__(self, station_id: int, codes: dict | None = None, system: str = "G"):
        self.station_id = station_id
        self.system = system
        (self.message_number, self.signal_ids, self.rough_code, default_codes, self.max_prn,
         self.time_offset_s) = MSM7_SYSTEMS[system]
        self.codes = codes if codes is not None else default_codes
        limit = 2.0 ** -8 * LIGHT_MS_M * 0.999          # DF406 spans +-2^-8 ms, as MSM4's DF401
        self._carrier = {c: CarrierReference(limit_m=limit) for cs in self.codes.values() for c in cs}
        self._lock_restart: dict[tuple[str, str], float] = {}

    def has_observations(self, epoch: GnssEpoch) -> bool:
        """Whether ``epoch`` has a satellite of this system on the rough-range signal."""
        rough = {sig for sig, cs in self.codes.items() if self.rough_code in cs}
        return any(o.sat[0] == self.system and o.signal in rough and math.isfinite(o.pseudorange_m)
                   for o in epoch.observations)

    def encode(self, epoch: GnssEpoch, more_follow: bool = False) -> bytes:
        """The MSM7 frame of ``epoch``'s observations of this system; ``more_follow``: DF393 set
        (another system's MSM of the same epoch comes next)."""
        cells: dict[int, dict[int, object]] = {}      # prn -> signal id -> observation
        code_of = {}
        for o in epoch.observations:
            if not (o.sat[0] == self.system and 1 <= int(o.sat[1:]) <= self.max_prn
                    and math.isfinite(o.pseudorange_m)):
                continue
            for code in self.codes.get(o.signal, ()):
                sid = self.signal_ids[code]
                cells.setdefault(int(o.sat[1:]), {})[sid] = o
                code_of[sid] = code
        rough_sid = self.signal_ids[self.rough_code]
        prns = sorted(p for p in cells if rough_sid in cells[p])   # rough range from the first frequency
        sids = sorted({sid for p in prns for sid in cells[p]})
        t_sys = epoch.t_gps + self.time_offset_s
        week = int(t_sys // SECONDS_PER_WEEK)
        tow_ms = round((t_sys - week * SECONDS_PER_WEEK) * 1000.0)
        w = BitWriter()
        w.u(12, self.message_number).u(12, self.station_id).u(30, tow_ms).u(1, int(more_follow)).u(3, 0).u(7, 0)
        w.u(2, 1).u(2, 0).u(1, 0).u(3, 0)
        w.u(64, sum(1 << (64 - p) for p in prns)).u(32, sum(1 << (32 - sid) for sid in sids))
        for p in prns:
            for sid in sids:
                w.u(1, int(sid in cells[p]))
        rough, rates, data, seen = [], [], [], set()
        for p in prns:
            l1 = cells[p][rough_sid]
            r_ms = round(l1.pseudorange_m / LIGHT_MS_M / ROUGH_LSB_MS) * ROUGH_LSB_MS
            rough.append(r_ms)
            rate = -l1.doppler_hz * l1.wavelength_m if math.isfinite(l1.doppler_hz) else math.nan
            rates.append(round(rate) if math.isfinite(rate) else None)
            for sid in sids:
                o = cells[p].get(sid)
                if o is None:
                    continue
                code = code_of[sid]
                fine_pr = round((o.pseudorange_m / LIGHT_MS_M - r_ms) / MSM7_FINE_PR_LSB_MS)
                fine_ph, lock = -(1 << 23), 0.0                  # DF406 "invalid"
                if math.isfinite(o.carrier_cycles):
                    k, why = self._carrier[code].reference(o, r_ms * LIGHT_MS_M)
                    lock = o.lock_time_s if math.isfinite(o.lock_time_s) else 0.0
                    key = (o.sat, code)
                    if why is not None:
                        self._lock_restart[key] = lock if why == "range" else 0.0
                    lock -= self._lock_restart[key]
                    fine_ph = round(((o.carrier_cycles - k) * o.wavelength_m / LIGHT_MS_M - r_ms) / MSM7_FINE_PH_LSB_MS)
                    seen.add((o.sat, code))
                fine_rate = -(1 << 14)                           # DF404 "invalid"
                if rates[-1] is not None and math.isfinite(o.doppler_hz):
                    fine_rate = round((-o.doppler_hz * o.wavelength_m - rates[-1]) / MSM7_FINE_RATE_LSB_MPS)
                cnr = o.cn0_dbhz if math.isfinite(o.cn0_dbhz) else 0.0
                data.append((fine_pr, fine_ph, lock_indicator_df407(lock), max(0, min(1023, round(cnr * 16))),
                             fine_rate))
        for code, ref in self._carrier.items():
            ref.forget({sat for sat, c in seen if c == code})
        for key in [k for k in self._lock_restart if k not in seen]:
            del self._lock_restart[key]
        for r_ms in rough:
            w.u(8, int(r_ms))
        for _ in rough:
            w.u(4, 0)                                           # DF419 extended info (GLONASS only)
        for r_ms in rough:
            w.u(10, round((r_ms - int(r_ms)) / ROUGH_LSB_MS))
        for r in rates:
            w.s(14, -(1 << 13) if r is None else r)             # DF399 rough phase range rate, m/s
        for c in data:
            w.s(20, c[0])
        for c in data:
            w.s(24, c[1])
        for c in data:
            w.u(10, c[2])
        for _ in data:
            w.u(1, 0)
        for c in data:
            w.u(10, c[3])
        for c in data:
            w.s(15, c[4])
        return frame(w.to_bytes())


class MultiMsm7Encoder:
    """One epoch of every system as back-to-back MSM7 frames (GPS 1077, Galileo 1097, BeiDou 1127,
    in that order), DF393 set on all but the last -- as a multi-GNSS base sends them.  A sky with
    GPS only gives exactly :class:`Msm7Encoder`'s 1077."""

    def __init__(self, station_id: int, systems: str = "GEC"):
        self.encoders = [Msm7Encoder(station_id, system=s) for s in "GEC" if s in systems]

    def encode(self, epoch: GnssEpoch) -> bytes:
        todo = [e for e in self.encoders if e.has_observations(epoch)] or self.encoders[:1]
        return b"".join(e.encode(epoch, more_follow=i < len(todo) - 1) for i, e in enumerate(todo))


__all__ = ["Msm4Encoder", "Msm7Encoder", "MultiMsm7Encoder", "lock_indicator_df402", "lock_indicator_df407",
           "GPS_MSM_SIGNAL_ID", "GALILEO_MSM_SIGNAL_ID", "BEIDOU_MSM_SIGNAL_ID", "MSM7_SYSTEMS"]
