"""Real-receiver time in the RTCM decoder: lost frames on a real MSM7 stream (NovAtel OEM729,
six systems, sets of 8 MSM frames followed by 1005/1033 or ephemerides).

The defects reproduced (issue 11, measured on u-blox M8P streams): after a lost frame GLONASS
observations were relabelled by whole seconds "as a leap-second mismatch", and an epoch whose last
frame was lost was emitted only by the next epoch's first MSM, 1 s late.
"""
from __future__ import annotations

import math

import pytest
from pyrtcm import RTCMReader

from companion.io.rtcm import RtcmDecoder, RtcmFramer, decode_rtcm_file, frame_message_type
from companion.messages import GnssEpoch
from tests._data import DATA_DIR

HIROSHIMA = DATA_DIR / "qzsl6tool-hiroshima-rtcm3-ubx/20221213-010900.rtcm"
GEONET_MSM = DATA_DIR / "rtklib-testdata-geonet-2005/rcvraw/GMSD7_20121014.rtcm3"
WEEK = 2240

pytestmark = pytest.mark.real_data


def _is_msm(mtype: int) -> bool:
    return 1070 <= mtype <= 1137


@pytest.fixture(scope="module")
def frames():
    """[(frame, message type, set index or None, last-of-set flag)] of the real stream."""
    out = []
    set_idx, new_set = -1, True
    for f in RtcmFramer().feed(HIROSHIMA.read_bytes()):
        t = frame_message_type(f)
        if _is_msm(t):
            if new_set:
                set_idx, new_set = set_idx + 1, False
            last = not int(RTCMReader.parse(f, validate=0).DF393)
            new_set = last
            out.append((f, t, set_idx, last))
        else:
            out.append((f, t, None, False))
    return out


@pytest.fixture(scope="module")
def truth():
    """(sat, signal, pseudorange) -> GPS time of its epoch, from the undamaged stream."""
    msgs, dec = decode_rtcm_file(str(HIROSHIMA), week_hint=WEEK)
    assert dec.counters.get("epoch_incomplete", 0) == 0
    return {(o.sat, o.signal, o.pseudorange_m): e.t_gps for e in msgs if isinstance(e, GnssEpoch)
            for o in e.observations}


def _decode(frame_list, decoder=None, t_rx=None):
    """Decode frame by frame: [(index of the frame that released it, message)]."""
    dec = decoder or RtcmDecoder(week_hint=WEEK)
    out = []
    for i, (f, *_rest) in enumerate(frame_list):
        for m in (dec.decode_frame(f) if t_rx is None else dec.decode_frame(f, t_rx[i])):
            out.append((i, m))
    out += [(len(frame_list), m) for m in dec.flush()]
    return out, dec


def _check_times(out, truth):
    """Every observation sits in an epoch at its own time; no epoch time twice; in order."""
    times = [m.t_gps for _, m in out if isinstance(m, GnssEpoch)]
    assert times == sorted(times) and len(set(times)) == len(times)
    n = 0
    for _, m in out:
        if isinstance(m, GnssEpoch):
            for o in m.observations:
                if math.isfinite(o.pseudorange_m):
                    assert truth[(o.sat, o.signal, o.pseudorange_m)] == m.t_gps, (o.sat, m.t_gps)
                    n += 1
    return n


@pytest.mark.parametrize("k", [1, 2, 3, 5, 7])
def test_a_lost_frame_never_relabels_glonass(frames, truth, k):
    """Frames lost from the GLONASS MSM of set 10 up to (not including) the GLONASS MSM of set
    10 + k: the first frame after the gap is GLONASS k seconds after the open GPS-only set.  The
    old decoder filed it (and its whole-second "mismatch") under the open set, k s off."""
    first = next(i for i, (_, t, s, _) in enumerate(frames) if s == 10 and t == 1087)
    resume = next(i for i, (_, t, s, _) in enumerate(frames) if s == 10 + k and t == 1087)
    damaged = frames[:first] + frames[resume:]
    out, dec = _decode(damaged)
    n = _check_times(out, truth)
    assert n > 8000
    assert dec.counters.get("system_time_offset_adopted", 0) == 0
    assert dec.counters["epoch_time_lost_frame"] == 1
    glo_times = {m.t_gps for _, m in out if isinstance(m, GnssEpoch) for o in m.observations if o.sat[0] == "R"}
    assert len(glo_times) == 60 - k          # every set but the k lost ones has its GLONASS


def test_an_epoch_whose_last_frame_is_lost_is_released_by_the_next_frame(frames, truth):
    """The last MSM of set 20 is lost.  It used to wait for the next set's first MSM (after 1005,
    1033: 1 s later on a 1 Hz stream); now the 1005 that follows it closes the set."""
    lost = next(i for i, (_, t, s, last) in enumerate(frames) if s == 20 and last)
    damaged = frames[:lost] + frames[lost + 1:]
    out, dec = _decode(damaged)
    _check_times(out, truth)
    (released_at, ep), = [(i, m) for i, m in out if isinstance(m, GnssEpoch) and m.t_gps == truth_time(truth, frames, 20)]
    assert damaged[released_at][1] not in range(1070, 1138)            # a non-MSM frame, right after
    assert released_at == lost
    next_set = next(i for i, (_, t, s, _) in enumerate(damaged) if s == 21)
    assert released_at < next_set
    assert dec.counters["epoch_incomplete"] == 1 and dec.counters["epoch_incomplete_other_frame"] == 1
    assert {o.sat[0] for o in ep.observations} == {"G", "R", "E", "J", "C"}      # only NavIC lost


def truth_time(truth, frames, set_idx):
    """GPS time of a set of the clean stream (the sets are 1 s apart and complete)."""
    times = sorted(set(truth.values()))
    first_set = min(s for *_x, s, _l in frames if s is not None)
    return times[set_idx - first_set]


def test_timeout_closes_an_epoch_when_no_frame_follows(frames, truth):
    """A stream that sends nothing between its sets: only the receive time can close a set whose
    last frame was lost.  Frames timed as a 1 Hz base sends them (set at t, frames 10 ms apart)."""
    msm_only = [fr for fr in frames if fr[2] is not None]
    t_rx = []
    for j, fr in enumerate(msm_only):
        in_set = 0 if j == 0 or msm_only[j - 1][2] != fr[2] else in_set + 1
        t_rx.append(fr[2] * 1.0 + 0.01 * in_set)
    lost = next(i for i, fr in enumerate(msm_only) if fr[2] == 30 and fr[3])
    damaged, t_rx = msm_only[:lost] + msm_only[lost + 1:], t_rx[:lost] + t_rx[lost + 1:]
    dec = RtcmDecoder(week_hint=WEEK)
    released = {}
    for i, (f, *_r) in enumerate(damaged):
        for m in dec.decode_frame(f, t_rx[i]):
            released[m.t_gps] = ("frame", t_rx[i])
        # the service polls between records (here every 50 ms of receive time)
        t = t_rx[i]
        while i + 1 < len(damaged) and t + 0.05 < t_rx[i + 1]:
            t += 0.05
            for m in dec.poll(t):
                released[m.t_gps] = ("poll", t)
    t30 = truth_time(truth, frames, 30)
    how, when = released[t30]
    last_frame_rx = t_rx[lost - 1]
    assert how == "poll" and when - last_frame_rx <= 0.3 + 0.05 + 1e-9 and when < 31.0
    assert dec.counters["epoch_incomplete_timeout"] == 1
    # without receive times the same stream releases it with set 31's first frame, 1 s late
    out, dec2 = _decode(damaged)
    (i31, _), = [(i, m) for i, m in out if isinstance(m, GnssEpoch) and m.t_gps == t30]
    assert damaged[i31][2] == 31 and dec2.counters["epoch_incomplete_later_epoch"] == 1


def test_a_leap_second_mismatch_is_adopted_after_three_sets_and_never_relabels_a_lost_frame(frames, truth):
    """gnss.leap_seconds = 17 instead of 18: every GLONASS time is 1 s early.  The first sets
    drop GLONASS (counted), the third adopts the offset; afterwards GLONASS joins its set."""
    msgs, dec = decode_rtcm_file(str(HIROSHIMA), week_hint=WEEK, leap_seconds=17)
    epochs = [m for m in msgs if isinstance(m, GnssEpoch)]
    assert dec.counters["system_time_offset_adopted"] == 1 and dec.counters["epoch_time_mismatch"] == 2
    with_glo = [e for e in epochs if any(o.sat[0] == "R" for o in e.observations)]
    assert len(epochs) == 60 and len(with_glo) == 58
    _check_times([(0, e) for e in epochs], truth)


def test_beidou_sent_in_gps_time_is_adopted(truth):
    """A real 2012 stream whose BeiDou MSM carry GPS time instead of BDT (+14 s): adopted after
    three sets; the old decoder relabelled any whole-second difference at once."""
    msgs, dec = decode_rtcm_file(str(GEONET_MSM), week_hint=1709, leap_seconds=16)
    epochs = [m for m in msgs if isinstance(m, GnssEpoch)]
    assert dec.counters["system_time_offset_adopted"] == 1 and dec.counters["epoch_time_mismatch"] == 2
    assert sum(any(o.sat[0] == "C" for o in e.observations) for e in epochs) == len(epochs) - 2
    assert dec.epochs.offset_s == {"C": -14.0}


def test_an_fnav_only_caster_still_gives_galileo_ephemerides(frames):
    """The same stream without its 1046: the held 1045 come out with the next observation message."""
    dec = RtcmDecoder(week_hint=WEEK)
    out = []
    for f, t, *_r in frames:
        if t != 1046:
            out += dec.decode_frame(f)
    gal = [m for m in out if getattr(m, "sat", "")[:1] == "E" and not isinstance(m, GnssEpoch)]
    assert len(gal) == 9 and "ephemeris_galileo_superseded" not in dec.counters
    assert all(e.ura_m == 6144.0 for e in gal)       # this sender leaves F/NAV's SISA at 255 (NAPA)


def test_the_pipeline_closes_a_base_epoch_on_the_autopilots_stream(frames, truth):
    """In the service, MAVLink records (the IMU at 50-400 Hz) carry the receive time that closes a
    base set whose last frame was lost; RTCM frames alone would release it a second late."""
    from pymavlink.dialects.v20 import common as mav

    from companion.config import config_from_dict
    from companion.pipeline import NavPipeline

    week_s = WEEK * 604800.0
    pipe = NavPipeline(config_from_dict({}))
    pipe.rtcm = RtcmDecoder(week_hint=WEEK)      # the stream is from 2022: its own week
    lost = next(i for i, fr in enumerate(frames) if fr[2] == 30 and fr[3])
    t30 = truth_time(truth, frames, 30)
    t_rx_s, current_set = 1000.0, 0
    for f, _t, set_idx, _last in frames[:lost]:
        # a 1-Hz base: each set within a few ms of its second, other messages after it
        current_set = set_idx if set_idx is not None else current_set
        t_rx_s = max(t_rx_s + 0.001, 1000.0 + current_set)
        pipe.feed("rtcm", int(t_rx_s * 1e9), f)
    assert t30 not in pipe._base_times
    enc = mav.MAVLink(None, srcSystem=pipe.target[0], srcComponent=pipe.target[1])
    hb = enc.heartbeat_encode(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0)
    pipe.feed("mavlink", int((t_rx_s + 0.5) * 1e9), hb.pack(enc))
    assert pipe.rtcm.counters["epoch_incomplete_timeout"] == 1
    assert t30 in pipe._base_times and t30 > week_s
