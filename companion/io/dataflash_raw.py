"""A u-blox's raw observations in an ArduPilot DataFlash log, back into RXM-RAWX frames.

With ``GPS_RAW_DATA = 1`` ArduPilot logs every RXM-RAWX of a u-blox field by field
(``AP_GPS_UBLOX::log_rxm_rawx``): one ``GRXH`` record (rcvTime, week, leapS, numMeas, recStat) and
``numMeas`` ``GRXS`` records (prMes, cpMes, doMes, gnss, sv, freq, lock, cno, prD, cpD, doD,
trk), all stamped with the same TimeUS, the autopilot's boot time when it logged them.  The
frames rebuilt here go through the same UBX decoder as the live receiver stream
(:class:`companion.io.ubx.UbxDecoder`), at the TimeUS they were logged.

**The signal is not logged**: a GRXS record has the frequency slot (GLONASS) but not the sigId,
so a dual-frequency receiver's two measurements of a satellite look alike.  The band is recovered
from the measurement itself: a u-blox starts its carrier-phase count near the pseudorange in
cycles (u-blox interface description, cpMes), so ``c cpMes / prMes`` is the carrier frequency to
about 1e-5 (the ionosphere's code-carrier divergence and the receiver clock over a pseudorange of
20 000 km).  The nearest band of the satellite's system is taken when the estimate lies within
half the distance to the next one (E5a and E5b, the closest pair, are 2.6 % apart) and within
:data:`MAX_FREQUENCY_ERROR` of it; the sigId is the one a u-blox F9/X20 reports on that band.  A
measurement without a valid carrier is taken as L1 when it is its satellite's only measurement in
the epoch (a single-frequency receiver), else dropped; a frequency that fits no band (a carrier
count not started near the pseudorange) is dropped.  Both are counted.
"""
from __future__ import annotations

import math
import struct
from collections import Counter
from dataclasses import dataclass, field

from ..messages import SPEED_OF_LIGHT_MPS
from .ubx import RAWX_HEAD, RAWX_MEAS, UBX_SIGNAL, carrier_frequency_hz, ubx_frame, ubx_sat_id

#: a carrier-frequency estimate further than this (relative) from every band of its system is not
#: a u-blox's carrier count: the measurement is dropped
MAX_FREQUENCY_ERROR = 0.05

#: u-blox gnssId -> band -> the sigId an F9/X20 reports there (interface description, "Signal
#: identifiers"; GPS L2 as L2 CL and QZSS's as L2 CL, what an F9P tracks; BeiDou D1 here, D2 for
#: its GEO satellites in :data:`_BEIDOU_D2`)
SIG_ID_BY_BAND = {
    0: {"1": 0, "2": 3, "5": 7},
    1: {"1": 0},
    2: {"1": 0, "5": 4, "7": 6, "6": 9},
    3: {"2": 0, "7": 2, "6": 4, "1": 5, "5": 7},
    5: {"1": 0, "2": 5, "5": 9},
    6: {"1": 0, "2": 2},
    7: {"5": 0},
}
_BEIDOU_D2 = {0: 1, 2: 3, 4: 10}        # B1I, B2I, B3I from the GEO satellites (PRN 1-5, 59-63)


@dataclass
class RawEpoch:
    """One GRXH record and the GRXS records logged with it."""
    t_us: int
    rcv_tow_s: float
    week: int
    leap_s: int
    num_meas: int
    rec_stat: int
    meas: list = field(default_factory=list)     # GRXS rows: (prMes, cpMes, doMes, gnss, sv, freq, lock, cno,
    #                                              prD, cpD, doD, trk)


def _band_frequencies(gnss_id: int, sv_id: int, freq_id: int) -> dict[str, float]:
    """band -> carrier frequency (Hz) of the bands :data:`SIG_ID_BY_BAND` knows for this satellite."""
    sat = ubx_sat_id(gnss_id, sv_id)
    if sat is None:
        return {}
    glo_k = freq_id - 7 if sat[0] == "R" else None
    out = {}
    for band, sig in SIG_ID_BY_BAND.get(gnss_id, {}).items():
        signal = UBX_SIGNAL.get((gnss_id, sig))
        f = carrier_frequency_hz(sat, signal, glo_k) if signal else math.nan
        if math.isfinite(f):
            out[band] = f
    return out


def band_of(gnss_id: int, sv_id: int, freq_id: int, pr_m: float, cp_cycles: float) -> str | None:
    """The band a measurement was tracked on, from its carrier count and pseudorange; None when
    they do not tell (see the module doc)."""
    if not (pr_m > 0.0 and math.isfinite(cp_cycles) and cp_cycles != 0.0):
        return None
    bands = _band_frequencies(gnss_id, sv_id, freq_id)
    if not bands:
        return None
    f_est = SPEED_OF_LIGHT_MPS * abs(cp_cycles) / pr_m
    ranked = sorted(bands.items(), key=lambda kv: abs(kv[1] - f_est))
    band, f = ranked[0]
    err = abs(f_est - f)
    if err > MAX_FREQUENCY_ERROR * f:
        return None
    if len(ranked) > 1 and err >= 0.5 * abs(ranked[1][1] - f):
        return None
    return band


def _sig_id(gnss_id: int, sv_id: int, band: str) -> int:
    sig = SIG_ID_BY_BAND[gnss_id][band]
    if gnss_id == 3 and (sv_id <= 5 or sv_id >= 59):
        sig = _BEIDOU_D2.get(sig, sig)
    return sig


def rawx_frame(epoch: RawEpoch, counters: Counter) -> bytes | None:
    """The RXM-RAWX frame (version 1) of one logged epoch, each measurement with the sigId of its
    band; None when no measurement is left (counted)."""
    per_sat = Counter((m[3], m[4]) for m in epoch.meas)
    packed = []
    for pr, cp, do, gnss_id, sv_id, freq_id, lock_ms, cno, pr_d, cp_d, do_d, trk in epoch.meas:
        if gnss_id not in SIG_ID_BY_BAND:
            counters["raw measurements dropped: unknown system"] += 1
            continue
        cp_valid = bool(int(trk) & 0x02)
        band = band_of(gnss_id, sv_id, freq_id, pr, cp if cp_valid else math.nan)
        if band is None:
            if cp_valid and cp != 0.0:
                counters["raw measurements dropped: carrier fits no band"] += 1
                continue
            if per_sat[(gnss_id, sv_id)] > 1 or "1" not in SIG_ID_BY_BAND[gnss_id]:
                counters["raw measurements dropped: no carrier to tell the band"] += 1
                continue
            band = "1"            # the satellite's only measurement: a single-frequency receiver's L1
            counters["raw measurements taken as L1 (no carrier)"] += 1
        try:
            packed.append(RAWX_MEAS.pack(float(pr), float(cp), float(do), int(gnss_id), int(sv_id),
                                         _sig_id(gnss_id, sv_id, band), int(freq_id), int(lock_ms), int(cno),
                                         int(pr_d), int(cp_d), int(do_d), int(trk)))
        except struct.error:            # a field outside its RXM-RAWX width: not a u-blox's record
            counters["raw measurements dropped: field out of range"] += 1
    if len(epoch.meas) != epoch.num_meas:
        counters["raw epochs with records missing (numMeas)"] += 1
    if not packed:
        counters["raw epochs without a usable measurement"] += 1
        return None
    payload = RAWX_HEAD.pack(float(epoch.rcv_tow_s), int(epoch.week), int(epoch.leap_s), len(packed),
                             int(epoch.rec_stat), 1) + b"".join(packed)
    counters["raw epochs rebuilt as RXM-RAWX"] += 1
    return ubx_frame(0x02, 0x15, payload)


def rawx_frames(epochs: list[RawEpoch]) -> tuple[list[tuple[int, bytes]], Counter]:
    """(TimeUS, RXM-RAWX frame) of every logged epoch that keeps a measurement, and the counters."""
    counters: Counter = Counter()
    out = []
    for ep in epochs:
        frame = rawx_frame(ep, counters)
        if frame is not None:
            out.append((ep.t_us, frame))
    return out, counters


def log_frames(log) -> tuple[list[tuple[int, bytes]], Counter]:
    """:func:`rawx_frames` of a read DataFlash log (:class:`companion.io.dataflash.DataFlashLog`),
    its GRXS records without a GRXH counted too."""
    frames, counters = rawx_frames(log.raw_epochs)
    if log.raw_orphans:
        counters["GRXS records without their GRXH (not used)"] = log.raw_orphans
    return frames, counters


def capture_bytes(path) -> tuple[bytes, Counter]:
    """The RXM-RAWX stream of a DataFlash log's GRXH/GRXS records, as a u-blox capture's bytes (a
    ValueError saying so when the log has none: ``GPS_RAW_DATA`` was 0, or the GPS no u-blox)."""
    from .dataflash import read_dataflash
    log = read_dataflash(path)
    if not log.raw_epochs:
        raise ValueError("no raw observations in the DataFlash log (GRXH/GRXS records: ArduPilot writes them "
                         "with GPS_RAW_DATA 1 and a u-blox receiver)")
    frames, counters = log_frames(log)
    return b"".join(frame for _, frame in frames), counters


__all__ = ["RawEpoch", "band_of", "capture_bytes", "log_frames", "rawx_frame", "rawx_frames", "SIG_ID_BY_BAND",
           "MAX_FREQUENCY_ERROR"]
