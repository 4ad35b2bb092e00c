"""Seeded fuzz inputs and one-input runners for the untrusted entry points of the companion (issue 14).

Shared by the bounded CI suite (``tests/test_fuzz_io.py``: a few thousand inputs per target) and
the long run (``python -m tests.fuzz``: a million).  A :class:`Target` makes one input from a
``random.Random`` (:meth:`Target.generate`) and feeds it to the entry point (:meth:`Target.run`),
checking the documented contract:

* nothing but the documented error escapes (NtripError for NTRIP responses, ConfigError for a
  configuration, nothing at all for the binary decoders and the field-log reader): anything else
  propagates, and the long run counts it as an *uncaught exception* and saves the input;
* what is dropped is counted and the buffered state stays bounded: a broken bound raises
  ``AssertionError``, which the long run reports the same way.

``run`` depends on the input bytes alone (chunk boundaries come from a generator seeded with the
input's CRC-32), so a saved input reproduces its failure: ``python -m tests.fuzz --replay FILE``.

The generators mix three kinds of input: byte-level mutations of real recordings (bit flips,
insertions, deletions, fake sync headers), *well-formed* frames whose payload is random or mutated
but whose checksum is recomputed (so the payload decoders behind the framers are reached, not just
the checksum test), and splices of both.
"""
from __future__ import annotations

import asyncio
import functools
import math
import random
import struct
import tempfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from companion.io.ubx import ubx_frame
from tests._data import data_path

RTCM_FILE = "qzsl6tool-hiroshima-rtcm3-ubx/20221213-010900.rtcm"
UBX_FILE = "qzsl6tool-hiroshima-rtcm3-ubx/20230919-114418.ubx"


def _rng_for(data: bytes) -> random.Random:
    """Chunking randomness that depends on the input alone (reproducible from a saved input)."""
    return random.Random(zlib.crc32(data))


def _chunks(data: bytes, rng: random.Random, max_chunk: int = 400):
    i = 0
    while i < len(data):
        n = rng.randrange(1, max_chunk)
        yield data[i:i + n]
        i += n


def _randbytes(rng: random.Random, n: int) -> bytes:
    return rng.getrandbits(8 * n).to_bytes(n, "little") if n > 0 else b""


def mutate(rng: random.Random, data: bytes, sync: bytes = b"\xd3") -> bytes:
    """1-7 byte-level edits: bit flip, random insertion, deletion, or a fake ``sync`` header."""
    b = bytearray(data)
    for _ in range(rng.randrange(1, 8)):
        op = rng.randrange(4)
        if op == 0 and b:
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
        elif op == 1:
            i = rng.randrange(len(b) + 1)
            b[i:i] = _randbytes(rng, rng.randrange(1, 16))
        elif op == 2 and b:
            i = rng.randrange(len(b))
            del b[i:i + rng.randrange(1, 32)]
        else:
            i = rng.randrange(len(b) + 1)
            b[i:i] = sync + bytes([rng.randrange(4)]) + _randbytes(rng, 3)
    return bytes(b)


@dataclass
class Target:
    name: str
    generate: Callable[[random.Random], bytes]
    run: Callable[[bytes], None]
    doc: str = ""


# ----------------------------------------------------------------------------------------- RTCM
@functools.lru_cache(maxsize=None)
def _rtcm_frames() -> tuple[bytes, ...]:
    from companion.io.rtcm import RtcmFramer
    return tuple(RtcmFramer().feed(data_path(RTCM_FILE).read_bytes()[:50000]))


def rtcm_frame(payload: bytes) -> bytes:
    """A CRC-valid RTCM 3 frame around ``payload`` (at most 1023 bytes)."""
    from companion.io.crc24q import crc24q
    payload = payload[:1023]
    head = bytes([0xD3, len(payload) >> 8, len(payload) & 0xFF]) + payload
    return head + crc24q(head).to_bytes(3, "big")


_RTCM_TYPES = (1001, 1002, 1003, 1004, 1005, 1006, 1009, 1010, 1011, 1012, 1019, 1020, 1033, 1041, 1042,
               1044, 1045, 1046, 1074, 1075, 1076, 1077, 1084, 1085, 1086, 1087, 1094, 1095, 1096, 1097,
               1104, 1107, 1114, 1117, 1124, 1125, 1126, 1127, 1230, 4072)


def gen_rtcm(rng: random.Random) -> bytes:
    frames = _rtcm_frames()
    k = rng.randrange(len(frames) - 3)
    r = rng.random()
    if r < 0.6:                                   # the suite's original: three real frames, mutated
        return mutate(rng, b"".join(frames[k:k + 3]))
    if r < 0.85:                                  # a real frame with a mutated payload, CRC fixed
        f = frames[k]
        payload = bytearray(f[3:-3])
        for _ in range(rng.randrange(1, 6)):
            if payload:
                payload[rng.randrange(len(payload))] = rng.getrandbits(8)
        if rng.random() < 0.3:
            payload = payload[:rng.randrange(2, max(3, len(payload)))]
        return frames[k - 1] + rtcm_frame(bytes(payload)) + frames[k + 1]
    # a supported message number with a random body, CRC fixed
    mtype = rng.choice(_RTCM_TYPES)
    n = rng.choice((rng.randrange(2, 30), rng.randrange(2, 1024)))
    body = bytearray(_randbytes(rng, n))
    body[0], body[1] = mtype >> 4, ((mtype & 0xF) << 4) | (body[1] & 0x0F)
    return frames[k] + rtcm_frame(bytes(body))


def run_rtcm(data: bytes) -> None:
    from companion.io.rtcm import MAX_FRAME, RtcmDecoder
    rng = _rng_for(data)
    dec = RtcmDecoder(week_hint=2240)
    for chunk in _chunks(data, rng):
        dec.feed(chunk)
    dec.flush()
    c = dec.framer.counters
    # each candidate 0xD3 costs at most one CRC over at most 1026 bytes
    assert c.get("crc_bytes", 0) <= 1026 * (data.count(0xD3) + 1), "RTCM CRC work beyond one per 0xD3"
    assert dec.framer.pending_bytes < MAX_FRAME, "RTCM framer buffers more than a frame"


# ------------------------------------------------------------------------------------------ UBX
@functools.lru_cache(maxsize=None)
def _ubx_bytes() -> bytes:
    return data_path(UBX_FILE).read_bytes()


_UBX_IDS = ((0x02, 0x15), (0x02, 0x13), (0x01, 0x07), (0x01, 0x20), (0x01, 0x3C), (0x01, 0x35), (0x05, 0x01),
            (0x0A, 0x04), (0x01, 0x03))


def _ubx_frames_in(data: bytes) -> list[tuple[int, int]]:
    """(start, end) of the checksum-valid UBX frames in ``data``."""
    from companion.io.ubx import ubx_checksum
    out, i = [], data.find(b"\xb5\x62")
    while 0 <= i and i + 8 <= len(data):
        n = data[i + 4] | data[i + 5] << 8
        end = i + 8 + n
        if end <= len(data) and ubx_checksum(data[i + 2:end - 2]) == (data[end - 2], data[end - 1]):
            out.append((i, end))
            i = data.find(b"\xb5\x62", end)
        else:
            i = data.find(b"\xb5\x62", i + 2)
    return out


def gen_ubx(rng: random.Random) -> bytes:
    raw = _ubx_bytes()
    start = rng.randrange(len(raw) - 2000)
    window = raw[start:start + rng.randrange(60, 2000)]
    r = rng.random()
    if r < 0.45:
        return mutate(rng, window, sync=b"\xb5\x62")
    if r < 0.8:                                   # a real frame with a mutated payload, checksum fixed
        frames = _ubx_frames_in(window)
        if not frames:
            return mutate(rng, window, sync=b"\xb5\x62")
        s, e = rng.choice(frames)
        payload = bytearray(window[s + 6:e - 2])
        for _ in range(rng.randrange(1, 8)):
            if payload:
                payload[rng.randrange(len(payload))] = rng.getrandbits(8)
        if rng.random() < 0.3:
            payload = payload[:rng.randrange(0, len(payload) + 1)]
        return window[:s] + ubx_frame(window[s + 2], window[s + 3], bytes(payload)) + window[e:]
    cls, mid = rng.choice(_UBX_IDS)                # a handled message with a random payload
    n = rng.choice((rng.randrange(0, 100), rng.randrange(0, 2000)))
    return window[:rng.randrange(len(window) + 1)] + ubx_frame(cls, mid, _randbytes(rng, n))


def run_ubx(data: bytes) -> None:
    from companion.io.ubx import MAX_PAYLOAD, UbxDecoder
    rng = _rng_for(data)
    dec = UbxDecoder(week_hint=2280)
    for chunk in _chunks(data, rng):
        dec.feed(chunk)
        assert dec.pending_bytes <= 8 + MAX_PAYLOAD + len(chunk), "UBX decoder buffers more than a frame"


# -------------------------------------------------------------------------------------- MAVLink
_MAV_CONSUMED = ("HIGHRES_IMU", "RAW_IMU", "SCALED_IMU2", "SCALED_IMU3", "SYSTEM_TIME", "ATTITUDE",
                 "GPS_RAW_INT", "HEARTBEAT", "EXTENDED_SYS_STATE", "SERIAL_CONTROL", "TIMESYNC", "COMMAND_ACK")


def mavlink_frame(msg_id: int, payload: bytes, sysid: int = 1, compid: int = 1, seq: int = 0) -> bytes:
    """A CRC-valid MAVLink 2 frame (unsigned) around ``payload`` for message ``msg_id``."""
    from pymavlink.dialects.v20 import ardupilotmega as mav
    payload = payload[:255]
    head = struct.pack("<BBBBBBBHB", 0xFD, len(payload), 0, 0, seq & 0xFF, sysid, compid,
                       msg_id & 0xFFFF, msg_id >> 16)
    crc = mav.x25crc(head[1:] + payload)
    extra = mav.mavlink_map[msg_id].crc_extra if msg_id in mav.mavlink_map else 0
    crc.accumulate(bytes([extra]))
    return head + payload + struct.pack("<H", crc.crc)


def _mav_plausible(rng: random.Random, name: str, t_us: int) -> bytes:
    """A sensible message (so the pipeline gets going) packed as the autopilot, 1/1."""
    from pymavlink.dialects.v20 import ardupilotmega as mav
    enc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    if name == "SYSTEM_TIME":
        m = mav.MAVLink_system_time_message(int(1.7e15) + t_us, t_us // 1000)
    elif name == "HEARTBEAT":
        m = mav.MAVLink_heartbeat_message(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0,
                                          rng.choice((3, 4)), 3)
    elif name == "RAW_IMU":
        m = mav.MAVLink_raw_imu_message(t_us, rng.randrange(-50, 50), rng.randrange(-50, 50), -1000, 0, 0, 0,
                                        0, 0, 0, 0, 0)
    else:
        m = mav.MAVLink_highres_imu_message(t_us, rng.gauss(0, 0.1), rng.gauss(0, 0.1), -9.8, 0, 0, 0, 0, 0, 0,
                                            0, 0, 0, 0, 0, 0)
    return bytes(m.pack(enc))


def gen_mavlink(rng: random.Random) -> bytes:
    from pymavlink.dialects.v20 import ardupilotmega as mav
    out = bytearray()
    t_us = rng.randrange(1, 10**9)
    for _ in range(rng.randrange(1, 24)):
        t_us += 5000
        r = rng.random()
        if r < 0.35:
            out += _mav_plausible(rng, rng.choice(("SYSTEM_TIME", "HEARTBEAT", "RAW_IMU", "HIGHRES_IMU")), t_us)
        elif r < 0.85:                             # a consumed message, random payload, valid CRC
            name = rng.choice(_MAV_CONSUMED)
            cls = getattr(mav, f"MAVLink_{name.lower()}_message")
            full = cls.unpacker.size                # wire length with every extension field
            n = rng.choice((full, rng.randrange(0, full + 1), rng.randrange(0, 256)))
            sysid, compid = (1, 1) if rng.random() < 0.8 else (rng.randrange(256), rng.randrange(256))
            out += mavlink_frame(cls.id, _randbytes(rng, min(n, 255)), sysid, compid, rng.randrange(256))
        else:                                      # any id (unknown ones too)
            out += mavlink_frame(rng.randrange(1 << 24) if rng.random() < 0.2 else rng.choice(list(mav.mavlink_map)),
                                 _randbytes(rng, rng.randrange(0, 256)), 1, 1)
    data = bytes(out)
    return mutate(rng, data, sync=b"\xfd") if rng.random() < 0.4 else data


@functools.lru_cache(maxsize=None)
def _mav_configs():
    import dataclasses

    from companion.config import Config
    c = Config()
    return (c, dataclasses.replace(c, gnss=dataclasses.replace(c.gnss, source="none")))


def run_mavlink(data: bytes) -> None:
    """Bytes -> pymavlink's robust parser -> the link's per-message handling -> the pipeline, as in
    the service (``feed_mavlink``, not the last-resort wrapper, so an exception surfaces here)."""
    from pymavlink.dialects.v20 import ardupilotmega as mav

    from companion.io.mavlink import MavlinkLink
    from companion.pipeline import NavPipeline
    rng = _rng_for(data)
    cfg = _mav_configs()[rng.randrange(2)]
    link = MavlinkLink("udpin:127.0.0.1:0", message_rates_hz={"HIGHRES_IMU": 200.0})
    link._queue = asyncio.Queue(maxsize=1000)            # as start() makes it, without a socket
    pipe = NavPipeline(cfg)
    parser = mav.MAVLink(None)
    parser.robust_parsing = True
    t_ns = 1_000_000_000
    n_msgs = 0
    for chunk in _chunks(data, rng, 120):
        for msg in parser.parse_buffer(chunk) or []:
            t_ns += 5_000_000
            n_msgs += 1
            link._handle(msg, t_ns)
            pipe.feed_mavlink(t_ns, msg)
    assert link.counters["rx_messages"] + link.counters["bad_data"] >= n_msgs - link.counters["rx_queue_overflow"] \
        or n_msgs == 0, "MAVLink messages neither delivered nor counted"
    assert len(parser.buf) - parser.buf_index <= 280, "MAVLink parser buffers more than a frame"


# ----------------------------------------------------------------------------------------- NTRIP
_NTRIP_SEEDS = (b"ICY 200 OK\r\n\xd3\x00", b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n5\r\nabcde\r\n",
                b"SOURCETABLE 200 OK\r\nContent-Type: gnss/sourcetable\r\n\r\nSTR;x\r\nENDSOURCETABLE\r\n",
                b"HTTP/1.0 401 Unauthorized\r\n", "HTTP/1.1 \u00b200 OK\r\n\r\n".encode(),
                b"HTTP/1.1 200 OK\r\nNtrip-Version: Ntrip/2.0\r\nContent-Type: gnss/data\r\nContent-Length: 12\r\n\r\n",
                b"HTTP/1.1 404 Not Found\r\nConnection: close\r\n\r\n")


def gen_ntrip_head(rng: random.Random) -> bytes:
    return mutate(rng, rng.choice(_NTRIP_SEEDS), sync=b"\r\n")


def run_ntrip_head(data: bytes) -> None:
    from companion.io.ntrip import NtripError, parse_response_head
    for eof in (False, True):
        try:
            head = parse_response_head(data, eof=eof)
        except NtripError:
            continue
        if head is not None:
            assert 0 <= head.status <= 999, "NTRIP status outside 0-999"


_CHUNKED_GOOD = b"".join(b"%x\r\n" % n + bytes(n) + b"\r\n" for n in (5, 300, 17, 1)) + b"0\r\n\r\n"


def gen_ntrip_chunked(rng: random.Random) -> bytes:
    return mutate(rng, _CHUNKED_GOOD, sync=b"\r\n")


def run_ntrip_chunked(data: bytes) -> None:
    from companion.io.ntrip import ChunkedDecoder, NtripError
    d = ChunkedDecoder()
    try:
        for i in range(0, len(data), 7):
            d.feed(data[i:i + 7])
            assert len(d._buf) <= 1024 + 7, "chunked decoder buffers without bound"
    except NtripError:
        pass


# -------------------------------------------------------------------------------------- field log
@functools.lru_cache(maxsize=None)
def _fieldlog_seed() -> bytes:
    from companion.io.fieldlog import FieldLogWriter
    rng = random.Random(17)
    with tempfile.TemporaryDirectory() as d:
        with FieldLogWriter(Path(d) / "seed.cflog", background_flush=False) as w:
            for i in range(40):
                w.write(("rtcm", "mavlink", "event")[i % 3], _randbytes(rng, i))
        return w.files[0].read_bytes()


def gen_fieldlog(rng: random.Random) -> bytes:
    return mutate(rng, _fieldlog_seed(), sync=b"\xd7\x1eRC")


@functools.lru_cache(maxsize=None)
def _scratch_dir() -> Path:
    return Path(tempfile.mkdtemp(prefix="companion-fuzz-"))


def run_fieldlog(data: bytes) -> None:
    from companion.io.fieldlog import read_field_log
    p = _scratch_dir() / "m.cflog"
    p.write_bytes(data)
    reader = read_field_log(p)
    recs = list(reader)
    assert reader.stats.records == len(recs), "field log stats disagree with the records read"
    assert len(recs) <= max(1, len(data) // 29), "more field-log records than bytes allow"


# ----------------------------------------------------------------------------------------- config
_TOML_VALUES = ("0", "-1", "1e300", "-1e300", "nan", "inf", "-inf", "1.5", "9223372036854775807",
                "-9223372036854775808", "true", "false", '""', '"x"', '"\\u00b2"', "[]", "[1, 2, 3]",
                '["RAW_IMU", "RAW_IMU"]', "[1.0, 2.0]", "[[1]]", "{}", "{a = 1}", "1979-05-27",
                "1979-05-27T07:32:00Z", "0x7f", "'''multi\nline'''", '["HIGHRES_IMU:0", "SCALED_IMU2"]',
                "[6.4e6, 0.0, 0.0]", "[1e300, 0, 0]", '"ntrip"', '"none"')


@functools.lru_cache(maxsize=None)
def _config_lines() -> tuple[str, ...]:
    from companion.config import example_config_toml
    return tuple(example_config_toml().splitlines())


def gen_config(rng: random.Random) -> bytes:
    lines = list(_config_lines())
    for _ in range(rng.choice((1, 1, 2, 3, 5))):      # few edits: many files stay valid
        idx = [i for i, ln in enumerate(lines) if " = " in ln and not ln.startswith("#")]
        r = rng.random()
        if r < 0.6 and idx:                        # a key gets a value of any type
            i = rng.choice(idx)
            key = lines[i].split(" = ", 1)[0]
            lines[i] = f"{key} = {rng.choice(_TOML_VALUES)}"
        elif r < 0.7:                              # an unknown key or section
            lines.insert(rng.randrange(len(lines) + 1),
                         rng.choice(("bogus = 1", "[bogus]", "[mavlink.extra]", "imu_rate = 5", "[[x]]")))
        elif r < 0.8 and idx:                      # a key goes, or is duplicated
            i = rng.choice(idx)
            if rng.random() < 0.5:
                del lines[i]
            else:
                lines.insert(i, lines[i])
        elif r < 0.9:                              # a section header is moved
            heads = [i for i, ln in enumerate(lines) if ln.startswith("[")]
            if heads:
                lines.insert(rng.randrange(len(lines) + 1), lines.pop(rng.choice(heads)))
        else:
            lines = lines[:rng.randrange(len(lines) + 1)]
    data = "\n".join(lines).encode()
    return mutate(rng, data, sync=b"=") if rng.random() < 0.15 else data


def run_config(data: bytes) -> None:
    """load_config raises ConfigError and nothing else; a configuration it accepts writes back to
    TOML that loads to the same configuration."""
    from companion.config import ConfigError, load_config, loads_config, redacted, secrets_readable_by_others
    p = _scratch_dir() / "c.toml"
    p.write_bytes(data)
    try:
        cfg = load_config(p)
    except ConfigError:
        return
    secrets_readable_by_others(cfg)
    redacted(cfg)
    again = loads_config(cfg.to_toml(comments=False))
    assert again == cfg, "a valid configuration does not survive to_toml -> loads_config"
    assert all(not (isinstance(v, float) and not math.isfinite(v)) for v in _floats(cfg)), "non-finite value"


def _floats(obj):
    import dataclasses
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            yield from _floats(v)
        elif isinstance(v, tuple):
            yield from (x for x in v if isinstance(x, float))
        elif isinstance(v, float):
            yield v


TARGETS: dict[str, Target] = {t.name: t for t in (
    Target("ubx", gen_ubx, run_ubx, "UBX from the receiver (serial port or SERIAL_CONTROL)"),
    Target("rtcm", gen_rtcm, run_rtcm, "RTCM 3 corrections (NTRIP, radio, MQTT)"),
    Target("mavlink", gen_mavlink, run_mavlink, "MAVLink bytes from the link: parser, link, pipeline"),
    Target("ntrip_head", gen_ntrip_head, run_ntrip_head, "an NTRIP caster's response header"),
    Target("ntrip_chunked", gen_ntrip_chunked, run_ntrip_chunked, "NTRIP 2 chunked transfer coding"),
    Target("fieldlog", gen_fieldlog, run_fieldlog, "a field log file (replay)"),
    Target("config", gen_config, run_config, "a TOML configuration file"),
)}

__all__ = ["TARGETS", "Target", "mutate", "rtcm_frame", "mavlink_frame"]

