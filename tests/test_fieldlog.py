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


# -- resource limits (issue 14) ----------------------------------------------------------------
def test_total_size_cap_deletes_the_oldest_files_first_and_every_file_replays(tmp_path):
    d = tmp_path / "capped"
    # an older session in the same directory goes first
    with FieldLogWriter(d / "old.cflog", max_bytes=4096, background_flush=False) as w0:
        for i in range(100):
            w0.write("ubx", bytes(60))
    old_files = list(w0.files)
    cap = 40_000
    cfg = ("event", b'{"event": "config", "toml": ""}')
    with FieldLogWriter(d / "new.cflog", max_bytes=1 << 20, background_flush=False,
                        max_total_bytes=cap, preamble=[cfg]) as w:
        assert w.max_bytes == cap // 4                 # files are a quarter of the cap
        for i in range(3000):
            w.write("rtcm", struct.pack("<I", i) + bytes(60), t_mono_ns=i, t_wall_ns=i)
            total = sum(f.stat().st_size for f in d.glob("*.cflog"))
            assert total <= cap, (i, total)
    assert not any(f.exists() for f in old_files)      # the other session's files went first
    assert w.counters["files_deleted"] >= len(old_files) + 1
    kept = field_log_files(d)
    assert kept and w.files[0] not in kept and w.files[-1] in kept
    # what is left is the newest records, contiguous, and every file starts with the preamble
    idx = []
    for f in kept:
        recs = list(read_field_log(f))
        assert recs[0].kind == "event" and recs[0].payload == cfg[1]
        idx += [struct.unpack_from("<I", r.payload)[0] for r in recs[1:]]
    assert idx == list(range(idx[0], 3000))


class _FullDisk:
    """os.write stand-in: raises ENOSPC while ``full``."""

    def __init__(self):
        self.full = False
        self.calls = 0

    def __call__(self, fd, data):
        self.calls += 1
        if self.full:
            raise OSError(28, "No space left on device")
        return os.write(fd, data)


def test_disk_full_pauses_once_drops_counted_and_resumes(tmp_path, caplog):
    import errno
    import logging
    assert errno.ENOSPC == 28
    d = tmp_path / "full"
    w = FieldLogWriter(d, background_flush=False, fsync_interval_s=0.0, retry_interval_s=0.0)
    disk = _FullDisk()
    w._os_write = disk
    for i in range(10):
        assert w.write("rtcm", struct.pack("<I", i))
    disk.full = True
    with caplog.at_level(logging.INFO, logger="companion.io.fieldlog"):
        results = [w.write("rtcm", struct.pack("<I", i)) for i in range(10, 510)]   # never raises
        errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
        assert len(errors) == 1 and "disk full" in errors[0].getMessage()    # one line, not 500
        ev = w.drain_events()
        assert ev == [("error", "field log paused: disk full; navigation continues")]
        assert w.paused and not any(results[1:])
        assert w.counters["write_errors"] >= 1 and w.counters["dropped_records"] >= 499
        files_while_full = set(d.glob("*.cflog"))
        disk.full = False                                 # space returns
        for i in range(510, 520):
            w.write("rtcm", struct.pack("<I", i))
        assert not w.paused and w.counters["resumed"] == 1
        assert [e[0] for e in w.drain_events()] == ["info"]
        assert any("resumed" in r.getMessage() for r in caplog.records)
    assert set(d.glob("*.cflog")) - files_while_full       # logging went on in a new file
    w.close()
    reader = read_field_log(d)
    idx = [struct.unpack_from("<I", r.payload)[0] for r in reader]
    assert idx[:10] == list(range(10)) and idx[-9:] == list(range(511, 520))
    assert reader.stats.crc_errors == 0


def test_disk_full_on_the_flusher_thread_never_reaches_the_writer(tmp_path):
    w = FieldLogWriter(tmp_path / "bg", fsync_interval_s=0.05, retry_interval_s=0.05)
    disk = _FullDisk()
    w._os_write = disk
    disk.full = True
    deadline = time.monotonic() + 10
    while not w.paused and time.monotonic() < deadline:
        w.write("mavlink", bytes(30))
        time.sleep(0.005)
    assert w.paused
    disk.full = False
    while w.paused and time.monotonic() < deadline:
        w.write("mavlink", bytes(30))
        time.sleep(0.005)
    assert not w.paused and w.counters["resumed"] == 1
    w.close()


def test_write_only_queues_the_flusher_thread_does_the_io(tmp_path):
    # the caller (the IMU path) must never wait for a slow card: no os.write on its thread
    import threading
    w = FieldLogWriter(tmp_path / "q", fsync_interval_s=0.05)
    callers = set()
    real = w._os_write

    def spy(fd, data):
        callers.add(threading.current_thread().name)
        return real(fd, data)
    w._os_write = spy
    for i in range(200):
        w.write("mavlink", bytes(30))
        time.sleep(0.001)
    time.sleep(0.3)
    assert callers == {"fieldlog-flush"}
    w.close()
    assert len(list(read_field_log(tmp_path / "q"))) == 200


def test_files_are_private(tmp_path):
    with FieldLogWriter(tmp_path / "p.cflog", background_flush=False) as w:
        w.write("event", b"{}")
    assert (w.files[0].stat().st_mode & 0o077) == 0
