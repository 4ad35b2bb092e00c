"""Bounded fuzzing of the untrusted-input entry points of companion.io (issue 14): a few thousand
seeded random and mutated inputs each, seconds in all.  The contract: never raise anything but
the documented error, count what is dropped, do bounded work per byte."""
from __future__ import annotations

import logging
import random

import pytest

from companion.io.fieldlog import FieldLogWriter, read_field_log
from companion.io.ntrip import ChunkedDecoder, NtripError, parse_response_head
from companion.io.rtcm import MAX_FRAME, RtcmDecoder, RtcmFramer
from tests._data import data_path

RTCM = data_path("qzsl6tool-hiroshima-rtcm3-ubx/20221213-010900.rtcm")


@pytest.fixture(autouse=True)
def _quiet():
    logging.disable(logging.WARNING)
    yield
    logging.disable(logging.NOTSET)


def _mutate(rng: random.Random, data: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randrange(1, 8)):
        op = rng.randrange(4)
        if op == 0 and b:
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
        elif op == 1:
            i = rng.randrange(len(b) + 1)
            b[i:i] = bytes(rng.getrandbits(8) for _ in range(rng.randrange(1, 16)))
        elif op == 2 and b:
            i = rng.randrange(len(b))
            del b[i:i + rng.randrange(1, 32)]
        else:
            i = rng.randrange(len(b) + 1)
            b[i:i] = b"\xd3" + bytes([rng.randrange(4)]) + bytes(rng.getrandbits(8) for _ in range(3))
    return bytes(b)


def test_rtcm_decoder_never_raises_and_work_per_byte_is_bounded():
    rng = random.Random(14)
    frames = RtcmFramer().feed(RTCM.read_bytes()[:50000])
    for _ in range(2000):
        k = rng.randrange(len(frames) - 3)
        data = _mutate(rng, b"".join(frames[k:k + 3]))
        dec = RtcmDecoder(week_hint=2240)
        i = 0
        while i < len(data):
            n = rng.randrange(1, 400)
            dec.feed(data[i:i + n])
            i += n
        dec.flush()
        c = dec.framer.counters
        # each candidate 0xD3 costs at most one CRC over at most 1026 bytes
        assert c.get("crc_bytes", 0) <= 1026 * (data.count(0xD3) + 1)
        assert dec.framer.pending_bytes < MAX_FRAME


def test_ntrip_response_parser_raises_only_ntrip_error():
    rng = random.Random(15)
    seeds = [b"ICY 200 OK\r\n\xd3\x00", b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n5\r\nabcde\r\n",
             b"SOURCETABLE 200 OK\r\nContent-Type: gnss/sourcetable\r\n\r\nSTR;x\r\nENDSOURCETABLE\r\n",
             b"HTTP/1.0 401 Unauthorized\r\n", "HTTP/1.1 \u00b200 OK\r\n\r\n".encode()]
    for _ in range(3000):
        data = _mutate(rng, rng.choice(seeds))
        for eof in (False, True):
            try:
                head = parse_response_head(data, eof=eof)
            except NtripError:
                continue
            if head is not None:
                assert 0 <= head.status <= 999


def test_chunked_decoder_raises_only_ntrip_error_and_buffers_boundedly():
    rng = random.Random(16)
    good = b"".join(b"%x\r\n" % n + bytes(n) + b"\r\n" for n in (5, 300, 17, 1)) + b"0\r\n\r\n"
    for _ in range(3000):
        data = _mutate(rng, good)
        d = ChunkedDecoder()
        try:
            for i in range(0, len(data), 7):
                d.feed(data[i:i + 7])
                assert len(d._buf) <= 1024 + 7
        except NtripError:
            pass


def test_field_log_reader_never_raises_on_mutated_logs(tmp_path):
    rng = random.Random(17)
    with FieldLogWriter(tmp_path / "seed.cflog", background_flush=False) as w:
        for i in range(40):
            w.write(("rtcm", "mavlink", "event")[i % 3], bytes(rng.getrandbits(8) for _ in range(i)))
    seed = w.files[0].read_bytes()
    p = tmp_path / "m.cflog"
    for _ in range(1500):
        p.write_bytes(_mutate(rng, seed))
        reader = read_field_log(p)
        recs = list(reader)
        assert reader.stats.records == len(recs) <= 40 + 8
