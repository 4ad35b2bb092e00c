"""Field log: round trip, crash (SIGKILL) safety, corruption resync, truncated tails, rotation."""
from __future__ import annotations

import os
import signal
import struct
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from companion.io.fieldlog import (FILE_HEADER, RECORD_MAGIC, FieldLogWriter, encode_record,
                                   field_log_files, read_field_log)

REPO = Path(__file__).resolve().parents[1]


def _records(n):
    out = []
    for i in range(n):
        kind = ("ubx", "rtcm", "mavlink", "event")[i % 4]
        # payloads include the record magic and arbitrary bytes to exercise resync
        payload = struct.pack("<I", i) + (RECORD_MAGIC if i % 7 == 0 else b"") + os.urandom(i % 50)
        out.append((kind, payload, 1_000_000 + i, 1_700_000_000_000_000_000 + 10 * i))
    return out


def test_round_trip(tmp_path):
    recs = _records(200)
    with FieldLogWriter(tmp_path / "flight.cflog") as w:
        for kind, payload, tm, tw in recs:
            w.write(kind, payload, t_mono_ns=tm, t_wall_ns=tw)
        w.write("event", b"")  # default timestamps, empty payload
    files = field_log_files(tmp_path)
    assert [f.name for f in files] == ["flight.00000.cflog"]
    reader = read_field_log(tmp_path / "flight.cflog")
    got = list(reader)
    assert len(got) == 201
    for (kind, payload, tm, tw), r in zip(recs, got):
        assert (r.kind, r.payload, r.t_mono_ns, r.t_wall_ns) == (kind, payload, tm, tw)
    assert got[-1].payload == b"" and abs(got[-1].t_wall_ns - time.time_ns()) < 60e9
    s = reader.stats
    assert s.records == 201 and s.crc_errors == 0 and not s.truncated_tail and s.skipped_bytes == 0


def test_truncated_tail_at_every_cut(tmp_path):
    w = FieldLogWriter(tmp_path / "t.cflog", background_flush=False)
    for kind, payload, tm, tw in _records(5):
        w.write(kind, payload, t_mono_ns=tm, t_wall_ns=tw)
    w.close()
    data = w.files[0].read_bytes()
    last = encode_record(*_records(5)[-1])
    start = len(data) - len(last)
    for cut in range(start + 1, len(data)):
        p = tmp_path / f"cut{cut}.cflog"
        p.write_bytes(data[:cut])
        reader = read_field_log(p)
        got = list(reader)
        assert len(got) == 4, cut
        assert reader.stats.truncated_tails == [(str(p), cut - start)]
        assert reader.stats.crc_errors == 0


@pytest.mark.parametrize("where", ["payload", "length", "magic", "kind", "crc"])
def test_corruption_in_the_middle_is_skipped(tmp_path, where):
    recs = _records(30)
    w = FieldLogWriter(tmp_path / "c.cflog", background_flush=False)
    for kind, payload, tm, tw in recs:
        w.write(kind, payload, t_mono_ns=tm, t_wall_ns=tw)
    w.close()
    path = w.files[0]
    data = bytearray(path.read_bytes())
    off = FILE_HEADER.size + sum(len(encode_record(*r)) for r in recs[:12])   # record 12
    rec_len = len(encode_record(*recs[12]))
    delta = {"magic": 1, "length": 6, "kind": 4 + 4 + 16 + 1, "payload": 4 + 4 + 16 + 1 + 3 + 2,
             "crc": rec_len - 2}[where]
    data[off + delta] ^= 0x40
    path.write_bytes(bytes(data))
    reader = read_field_log(path)
    got = list(reader)
    indices = [struct.unpack_from("<I", r.payload)[0] for r in got]
    assert indices == [i for i in range(30) if i != 12]
    s = reader.stats
    assert s.crc_errors + s.bad_records + (1 if where == "magic" else 0) >= 1
    assert s.errors and not s.truncated_tail


def test_rotation_keeps_order_and_never_overwrites(tmp_path):
    d = tmp_path / "logs"
    with FieldLogWriter(d, max_bytes=4096, background_flush=False) as w:
        for i in range(500):
            w.write("ubx", struct.pack("<I", i) + bytes(40), t_mono_ns=i, t_wall_ns=i)
    assert len(w.files) >= 5
    assert all(f.stat().st_size <= 4096 for f in w.files)
    before = {f: f.read_bytes() for f in w.files}
    # a second session in the same directory must not touch the first one's files
    with FieldLogWriter(d, max_bytes=4096, background_flush=False) as w2:
        for i in range(500, 600):
            w2.write("ubx", struct.pack("<I", i) + bytes(40), t_mono_ns=i, t_wall_ns=i)
    assert all(f.read_bytes() == b for f, b in before.items())
    assert not set(w2.files) & set(w.files)
    reader = read_field_log(d)
    got = [struct.unpack_from("<I", r.payload)[0] for r in reader]
    assert got == list(range(600))
    assert reader.stats.files == len(w.files) + len(w2.files)


_CHILD = textwrap.dedent("""
    import sys, time, struct
    sys.path.insert(0, sys.argv[2])
    from companion.io.fieldlog import FieldLogWriter
    w = FieldLogWriter(sys.argv[1], max_bytes=256 * 1024, fsync_interval_s=float(sys.argv[3]))
    i = 0
    while True:
        w.write("rtcm", struct.pack("<Iq", i, time.monotonic_ns()) + bytes(100))
        if i == 100:
            print("ready", flush=True)
        i += 1
        time.sleep(0.0005)
""")


def test_sigkill_loses_at_most_the_last_interval(tmp_path):
    interval = 0.5
    d = tmp_path / "crash"
    proc = subprocess.Popen([sys.executable, "-c", _CHILD, str(d), str(REPO), str(interval)],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(2.3)            # long enough to rotate through a few files
    finally:
        t_kill = time.monotonic_ns()
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    reader = read_field_log(d)
    got = list(reader)
    idx = [struct.unpack_from("<I", r.payload)[0] for r in got]
    assert idx == list(range(len(idx)))           # complete, in order, no gap
    assert reader.stats.crc_errors == 0 and reader.stats.bad_records == 0
    assert reader.stats.files >= 2                # rotation happened while being killed
    last_write = struct.unpack_from("<Iq", got[-1].payload)[1]
    lost_s = (t_kill - last_write) * 1e-9
    assert lost_s < interval + 0.5, lost_s        # at most about one flush interval lost
    # record timestamps are the child's monotonic clock at write time
    assert all(r.t_mono_ns >= struct.unpack_from("<Iq", r.payload)[1] for r in got[:50])
