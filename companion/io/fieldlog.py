"""The field log: append-only, crash-safe, replayable record of every input the shell receives.

File format (all integers little-endian), version 1
---------------------------------------------------

Each file starts with a 24-byte header::

    magic      8 bytes  b"\\x89CFLOG\\r\\n"   (PNG-style: detects text-mode mangling)
    version    u16      1
    reserved   u16      0
    sequence   u32      rotation sequence number of this file within its session
    created    i64      wall-clock time the file was opened, ns since the Unix epoch

followed by records::

    magic      4 bytes  b"\\xd7\\x1eRC"
    length     u32      payload length in bytes
    t_mono_ns  i64      receive time, CLOCK_MONOTONIC ns (orders records, measures latency)
    t_wall_ns  i64      receive time, wall clock, ns since the Unix epoch
    kind_len   u8
    kind       kind_len bytes, ASCII: stream id/kind, e.g. 'mavlink', 'ubx', 'rtcm', 'solution', 'event',
               'aid_status' (companion.aid_status_record: per aid source status, versioned JSON)
    payload    length bytes, raw as received
    crc32      u32      zlib.crc32 of everything from ``length`` through ``payload``

Crash safety: records are only ever appended.  A ``kill -9`` (or power loss after the last
fsync) leaves a file whose complete records all verify; a partial record at the end is detected
(too short for its header/length, no later record magic) and reported as a truncated tail.  A
corrupt record in the middle (CRC mismatch, impossible length) is reported and skipped: the reader
resynchronises by scanning for the next record magic.  A payload may contain the magic bytes; a
false resync then simply fails its CRC and the scan continues.

Flush policy: records are queued in memory and written (one ``os.write`` per batch, not per
record) + ``os.fsync``-ed together by a small background thread when the oldest queued record is
``fsync_interval_s`` old (without the thread, by ``write`` when the interval since the last sync
has elapsed), and on ``flush``/``close``.  So ``kill -9`` or a power cut loses at most the records
of the last ``fsync_interval_s`` plus one write + fsync (the service uses 0.4 s); a normal stop
loses nothing, and neither does an interpreter exit without ``close`` (an ``atexit`` hook closes
every open writer).  Files are created 0600 (they hold everything the vehicle received).

Rotation: when a file would exceed ``max_bytes`` a new file with the next sequence number is
started; ``max_total_bytes`` caps the directory, deleting the oldest files (see FieldLogWriter).  Names are ``<stem>.<sequence:05d>.cflog``; files are created with ``O_EXCL`` and never
overwritten.  Given a directory the writer picks ``stem = fieldlog-<UTC start time>``.
"""
from __future__ import annotations

import atexit
import errno
import logging
import os
import struct
import threading
import time
import weakref
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

log = logging.getLogger(__name__)

FILE_MAGIC = b"\x89CFLOG\r\n"
FILE_VERSION = 1
FILE_HEADER = struct.Struct("<8sHHIq")
RECORD_MAGIC = b"\xd7\x1eRC"
RECORD_HEAD = struct.Struct("<4sIqqB")      # magic, length, t_mono, t_wall, kind_len
CRC = struct.Struct("<I")
SUFFIX = ".cflog"
MAX_RECORD_PAYLOAD = 16 * 1024 * 1024


@dataclass(frozen=True, slots=True)
class FieldLogRecord:
    t_mono_ns: int
    t_wall_ns: int
    kind: str
    payload: bytes
    file: str = ""
    offset: int = 0


_BODY_HEAD = struct.Struct("<IqqB")         # RECORD_HEAD without its magic: what the CRC covers first
_KINDS: dict[str, bytes] = {}               # kind -> its ASCII bytes (a handful of kinds, ~300 records/s)


def encode_record(kind: str, payload: bytes, t_mono_ns: int, t_wall_ns: int) -> bytes:
    k = _KINDS.get(kind)
    if k is None:
        k = kind.encode("ascii")
        if len(k) > 255:
            raise ValueError("kind longer than 255 characters")
        if len(_KINDS) < 64:
            _KINDS[kind] = k
    if len(payload) > MAX_RECORD_PAYLOAD:
        raise ValueError(f"payload larger than {MAX_RECORD_PAYLOAD} bytes")
    body = b"".join((_BODY_HEAD.pack(len(payload), t_mono_ns, t_wall_ns, len(k)), k, payload))
    return b"".join((RECORD_MAGIC, body, CRC.pack(zlib.crc32(body))))


class _NewFile:
    """Marker in the write queue: the records after it go to the next file."""


_NEW_FILE = _NewFile()
_DISK_FULL = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)}


_OPEN_WRITERS: "weakref.WeakSet[FieldLogWriter]" = weakref.WeakSet()


@atexit.register
def _flush_open_writers() -> None:
    """An interpreter that exits without closing a writer (an exception nobody caught,
    ``sys.exit`` from a callback) still writes what was queued: the flusher is a daemon thread."""
    for w in list(_OPEN_WRITERS):
        try:
            w.close()
        except Exception:       # at exit: never mask the real error
            pass


class FieldLogWriter:
    """Append-only, rotating, periodically fsync-ed field log writer (thread-safe ``write``).

    Resource limits (an SD card on a drone is small, and what feeds the log is partly untrusted):

    * ``max_total_bytes``: the log directory (all sessions' ``*.cflog``) stays below it; when a new
      file is opened, the oldest files go first (never the current one).  Files are then at most
      a quarter of the total, so retention always has whole files to delete.  ``preamble``
      records (the service's configuration) start every file, so a log whose first files were
      deleted still replays.
    * ``write`` only queues: the file I/O (write, fsync, rotation) runs on the flusher thread, so
      a slow card never blocks the caller (the IMU path); the queue is capped at
      ``max_backlog_bytes`` (records beyond it are dropped and counted).
    * A failing disk (ENOSPC, EIO, ...) pauses logging: one error line, one entry in ``events``
      (``(severity, text)``, drained by the service into a STATUSTEXT), records dropped and counted
      while paused; every ``retry_interval_s`` a new file is tried, and logging resumes (one info
      line and event) when space returns.  The caller never sees the exception.

    Counters (``counters``, stable keys): ``records``, ``dropped_records``, ``dropped_bytes``,
    ``write_errors``, ``resumed``, ``files_deleted``, ``bytes_deleted``.
    """

    def __init__(self, path_or_dir: str | os.PathLike, max_bytes: int = 64 * 1024 * 1024,
                 fsync_interval_s: float = 1.0, background_flush: bool = True, *,
                 max_total_bytes: int | None = None, retry_interval_s: float = 5.0,
                 max_backlog_bytes: int = 8 * 1024 * 1024, preamble: list[tuple[str, bytes]] = ()):
        p = Path(path_or_dir)
        if p.is_dir() or str(path_or_dir).endswith(os.sep) or p.suffix == "":
            p.mkdir(parents=True, exist_ok=True)
            self.directory = p
            self.stem = "fieldlog-" + time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        else:
            p.parent.mkdir(parents=True, exist_ok=True)
            self.directory = p.parent
            self.stem = p.name[:-len(SUFFIX)] if p.name.endswith(SUFFIX) else p.stem
        if max_bytes < FILE_HEADER.size + 64:
            raise ValueError("max_bytes too small")
        self.max_bytes = int(max_bytes)
        self.max_total_bytes = None if max_total_bytes is None else int(max_total_bytes)
        if self.max_total_bytes is not None:
            if self.max_total_bytes < 4 * (FILE_HEADER.size + 64):
                raise ValueError("max_total_bytes too small")
            self.max_bytes = min(self.max_bytes, self.max_total_bytes // 4)
        self.fsync_interval_s = float(fsync_interval_s)
        self.retry_interval_s = float(retry_interval_s)
        self.max_backlog_bytes = int(max_backlog_bytes)
        self.files: list[Path] = []
        self.records_written = 0
        self.counters: dict[str, int] = {"records": 0, "dropped_records": 0, "dropped_bytes": 0,
                                         "write_errors": 0, "resumed": 0, "files_deleted": 0,
                                         "bytes_deleted": 0}
        self.events: list[tuple[str, str]] = []
        self.paused = False
        self.last_error = ""
        self._paused_at = 0.0
        self._os_write = os.write            # the file I/O, replaceable by tests (a full disk)
        self._os_fsync = os.fsync
        self._preamble = b"".join(encode_record(k, pl, time.monotonic_ns(), time.time_ns())
                                  for k, pl in preamble)
        self._seq = 0
        self._fd: int | None = None
        self._file_bytes = 0
        self._file_records = 0
        self._queue: list = []               # encoded records and _NEW_FILE markers, in order
        self._backlog = 0
        self._queued_at = 0.0                # when the queue became non-empty (the flusher's deadline)
        self._last_sync = time.monotonic()
        self._lock = threading.Lock()        # the queue and the counters
        self._io_lock = threading.Lock()     # the files
        self._closed = False
        self._open_next()
        self._file_bytes = FILE_HEADER.size + len(self._preamble)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if background_flush and self.fsync_interval_s > 0:
            self._thread = threading.Thread(target=self._flusher, name="fieldlog-flush", daemon=True)
            self._thread.start()
        _OPEN_WRITERS.add(self)

    # -- files (under _io_lock) --------------------------------------------------------------

    def set_preamble(self, preamble: list[tuple[str, bytes]]) -> None:
        """The records that start every later file (a configuration changed while running, so a
        file replayed alone starts from the configuration in force when it was opened)."""
        self._preamble = b"".join(encode_record(k, pl, time.monotonic_ns(), time.time_ns())
                                  for k, pl in preamble)
    def _write_all(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[self._os_write(self._fd, view):]

    def _write_records(self, queue: list, start: int, end: int) -> int:
        """Write records ``queue[start:end]`` in one go; returns ``end``.  On an error ``start`` is
        moved past the records that reached the file whole (so ``_failed`` counts only the others)
        before the exception goes on."""
        data = queue[start] if end == start + 1 else b"".join(queue[start:end])
        view = memoryview(data)
        written = 0
        try:
            while written < len(data):
                written += self._os_write(self._fd, view[written:])
        except OSError:
            i, acc = start, 0
            while i < end and acc + len(queue[i]) <= written:
                acc += len(queue[i])
                i += 1
            del queue[start:i]          # written whole: not lost
            raise
        return end

    def _open_next(self) -> None:
        while True:
            path = self.directory / f"{self.stem}.{self._seq:05d}{SUFFIX}"
            try:
                fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o600)
                break
            except FileExistsError:
                self._seq += 1
        self._seq += 1
        self._fd = fd
        try:
            self._write_all(FILE_HEADER.pack(FILE_MAGIC, FILE_VERSION, 0, self._seq - 1, time.time_ns())
                            + self._preamble)
            self._os_fsync(fd)
        except OSError:
            self._fd = None
            os.close(fd)
            try:                    # no empty file per retry while the disk stays full
                os.unlink(path)
            except OSError:
                pass
            raise
        try:   # make the new directory entry durable too
            dfd = os.open(self.directory, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except OSError:
            pass
        self.files.append(path)
        self._enforce_total_cap()

    def _enforce_total_cap(self) -> None:
        """Delete the oldest log files until they and a full current file fit the cap."""
        if self.max_total_bytes is None:
            return
        current = self.files[-1]
        old = []
        for f in self.directory.glob(f"*{SUFFIX}"):
            if f == current:
                continue
            try:
                st = f.stat()
            except OSError:
                continue
            old.append((st.st_mtime_ns, f.name, f, st.st_size))
        old.sort()
        total = sum(x[3] for x in old)
        budget = self.max_total_bytes - self.max_bytes
        for _mt, _name, f, size in old:
            if total <= budget:
                break
            try:
                f.unlink()
            except OSError as exc:
                log.warning("field log retention: cannot delete %s: %s", f, exc)
                continue
            total -= size
            self.counters["files_deleted"] += 1
            self.counters["bytes_deleted"] += size
            log.info("field log retention: deleted %s (%d bytes) to stay under %d bytes", f.name, size,
                     self.max_total_bytes)

    def _close_fd(self) -> None:
        if self._fd is not None:
            try:
                os.close(self._fd)
            except OSError:
                pass
            self._fd = None

    def _sync(self) -> None:
        """Write the queue to the files and fsync; on an I/O error pause logging (see class doc)."""
        with self._io_lock:
            with self._lock:
                resume = self.paused
                if resume and time.monotonic() - self._paused_at < self.retry_interval_s:
                    return
                queue, self._queue, self._backlog = self._queue, [], 0
            done = 0
            try:
                if resume:
                    self._open_next()
                    self._resumed()
                n = len(queue)
                while done < n:
                    if queue[done] is _NEW_FILE:
                        self._os_fsync(self._fd)
                        self._close_fd()
                        self._open_next()
                        done += 1
                        continue
                    # the records up to the next file change in one write: one system call per
                    # flush, not one per record (~290 a second in flight)
                    end = done + 1
                    while end < n and queue[end] is not _NEW_FILE:
                        end += 1
                    done = self._write_records(queue, done, end)
                if self._fd is not None:
                    self._os_fsync(self._fd)
                self._last_sync = time.monotonic()
            except OSError as exc:
                self._failed(exc, queue[done:])

    def _failed(self, exc: OSError, lost: list) -> None:
        self._close_fd()
        n = sum(1 for x in lost if x is not _NEW_FILE)
        with self._lock:
            was_paused = self.paused
            self.paused = True
            self._paused_at = time.monotonic()
            self.counters["write_errors"] += 1
            self.counters["dropped_records"] += n
            self.counters["dropped_bytes"] += sum(len(x) for x in lost if x is not _NEW_FILE)
            self._file_records = 0
            self._file_bytes = FILE_HEADER.size + len(self._preamble)
            self.last_error = f"{exc.strerror or exc}"
            if not was_paused:
                what = "disk full" if exc.errno in _DISK_FULL else f"write error ({self.last_error})"
                text = f"field log paused: {what}; navigation continues"
                self.events.append(("error", text))
                log.error("%s (%s; retrying every %.0f s)", text, self.directory, self.retry_interval_s)

    def _resumed(self) -> None:
        with self._lock:
            self.paused = False
            self.counters["resumed"] += 1
            text = f"field log resumed ({self.counters['dropped_records']} records dropped so far)"
            self.events.append(("info", text))
        log.info("%s in %s", text, self.current_path)

    # -- public ------------------------------------------------------------------------------
    @property
    def current_path(self) -> Path:
        return self.files[-1]

    def drain_events(self) -> list[tuple[str, str]]:
        with self._lock:
            ev, self.events = self.events, []
        return ev

    def write(self, kind: str, payload: bytes, t_mono_ns: int | None = None,
              t_wall_ns: int | None = None) -> bool:
        """Queue one record; False when it was dropped (logging paused or backlog full)."""
        if t_mono_ns is None:
            t_mono_ns = time.monotonic_ns()
        if t_wall_ns is None:
            t_wall_ns = time.time_ns()
        rec = encode_record(kind, payload, t_mono_ns, t_wall_ns)
        with self._lock:
            if self._closed:
                raise ValueError("write to a closed FieldLogWriter")
            ok = not self.paused and self._backlog + len(rec) <= self.max_backlog_bytes
            if ok:
                if self._file_records > 0 and self._file_bytes + len(rec) > self.max_bytes:
                    self._queue.append(_NEW_FILE)
                    self._file_bytes = FILE_HEADER.size + len(self._preamble)
                    self._file_records = 0
                if not self._queue:
                    self._queued_at = time.monotonic()     # the oldest unwritten record's age
                self._queue.append(rec)
                self._backlog += len(rec)
                self._file_bytes += len(rec)
                self._file_records += 1
                self.records_written += 1
                self.counters["records"] += 1
            else:
                self.counters["dropped_records"] += 1
                self.counters["dropped_bytes"] += len(rec)
            due = self._thread is None and (
                (self.paused and time.monotonic() - self._paused_at >= self.retry_interval_s)
                or (not self.paused and time.monotonic() - self._last_sync >= self.fsync_interval_s))
        if due:
            self._sync()
        return ok

    def flush(self) -> None:
        """Write and fsync everything queued now."""
        self._sync()

    def _flusher(self) -> None:
        # wakes when the oldest queued record is fsync_interval_s old (not on a fixed period), so
        # no record waits in memory longer than that: what a power cut can lose is bounded by
        # fsync_interval_s plus one write + fsync
        idle = max(min(self.fsync_interval_s / 4.0, 0.1), 0.01)
        while True:
            with self._lock:
                if self._closed:
                    return
                now = time.monotonic()
                if self.paused:
                    wait = self._paused_at + self.retry_interval_s - now
                elif self._queue:
                    wait = self._queued_at + self.fsync_interval_s - now
                else:
                    wait = idle              # nothing queued: look again (a record may arrive)
            if wait <= 0:
                self._sync()
                if self.paused and self._stop.wait(idle):     # no busy retry (retry_interval_s 0)
                    return
                continue
            if self._stop.wait(min(wait, max(self.fsync_interval_s, idle))):
                return

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        with self._lock:
            if self._closed:
                return
            self._closed = True
        if not self.paused:
            self._sync()
        with self._io_lock:
            self._close_fd()

    def __enter__(self) -> "FieldLogWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ------------------------------------------------------------------------------------------
@dataclass
class FieldLogStats:
    files: int = 0
    records: int = 0
    payload_bytes: int = 0
    crc_errors: int = 0                 # records whose CRC failed (skipped)
    bad_records: int = 0                # impossible length / kind, bad file header
    skipped_bytes: int = 0              # bytes passed over while resynchronising
    truncated_tails: list = field(default_factory=list)   # (file, bytes) partial records at file ends
    errors: list = field(default_factory=list)            # (file, offset, reason), first 100

    @property
    def truncated_tail(self) -> bool:
        return bool(self.truncated_tails)

    def _error(self, file: str, offset: int, reason: str) -> None:
        if len(self.errors) < 100:
            self.errors.append((file, offset, reason))


def field_log_files(path_or_dir: str | os.PathLike) -> list[Path]:
    """The files of a log in replay order: a directory (all ``*.cflog``), one file, or a stem."""
    p = Path(path_or_dir)
    if p.is_dir():
        return sorted(p.glob(f"*{SUFFIX}"))
    if p.is_file():
        return [p]
    stem = p.name[:-len(SUFFIX)] if p.name.endswith(SUFFIX) else p.name
    return sorted(p.parent.glob(f"{stem}.[0-9][0-9][0-9][0-9][0-9]{SUFFIX}"))


class FieldLogReader:
    """Iterate the records of a field log in order across rotated files; ``stats`` reports
    what was read and what was skipped.  Never raises on corrupt content."""

    def __init__(self, path_or_dir: str | os.PathLike):
        self.files = field_log_files(path_or_dir)
        self.stats = FieldLogStats()

    def __iter__(self) -> Iterator[FieldLogRecord]:
        for f in self.files:
            yield from self._read_file(f)

    def _read_file(self, path: Path) -> Iterator[FieldLogRecord]:
        st = self.stats
        name = str(path)
        try:
            data = path.read_bytes()
        except OSError as exc:
            st._error(name, 0, f"unreadable: {exc}")
            return
        st.files += 1
        if len(data) < FILE_HEADER.size:
            st.truncated_tails.append((name, len(data)))
            st._error(name, 0, "file shorter than its header")
            return
        magic, version, _r, _seq, _created = FILE_HEADER.unpack_from(data, 0)
        pos = FILE_HEADER.size
        if magic != FILE_MAGIC or version != FILE_VERSION:
            st.bad_records += 1
            st._error(name, 0, "bad file header; scanning for records")
        n = len(data)
        head = RECORD_HEAD.size
        while pos < n:
            if data[pos:pos + 4] != RECORD_MAGIC:
                nxt = data.find(RECORD_MAGIC, pos + 1)
                if nxt < 0:
                    if n - pos < 4 and RECORD_MAGIC.startswith(data[pos:]):
                        st.truncated_tails.append((name, n - pos))
                    else:
                        st.skipped_bytes += n - pos
                        st._error(name, pos, "garbage at end of file")
                    return
                st.skipped_bytes += nxt - pos
                st._error(name, pos, f"resync: skipped {nxt - pos} bytes")
                pos = nxt
                continue
            ok_len = True
            if n - pos >= head:
                _m, length, t_mono, t_wall, klen = RECORD_HEAD.unpack_from(data, pos)
                ok_len = length <= MAX_RECORD_PAYLOAD
                end = pos + head + klen + length + 4
            else:
                end = n + 1
            if not ok_len or end > n:
                # incomplete: a truncated tail if nothing follows, else a corrupt length
                nxt = data.find(RECORD_MAGIC, pos + 1)
                if nxt < 0 and ok_len:
                    st.truncated_tails.append((name, n - pos))
                    return
                st.bad_records += 1
                st._error(name, pos, "impossible record length")
                if nxt < 0:
                    st.skipped_bytes += n - pos
                    return
                st.skipped_bytes += nxt - pos
                pos = nxt
                continue
            body = data[pos + 4:end - 4]
            (crc,) = CRC.unpack_from(data, end - 4)
            if zlib.crc32(body) != crc:
                st.crc_errors += 1
                st._error(name, pos, "CRC mismatch")
                nxt = data.find(RECORD_MAGIC, pos + 1)
                if nxt < 0:
                    st.skipped_bytes += n - pos
                    return
                st.skipped_bytes += nxt - pos
                pos = nxt
                continue
            kind_b = data[pos + head:pos + head + klen]
            try:
                kind = kind_b.decode("ascii")
            except UnicodeDecodeError:
                kind = kind_b.decode("ascii", "replace")
            payload = data[pos + head + klen:end - 4]
            st.records += 1
            st.payload_bytes += len(payload)
            yield FieldLogRecord(t_mono, t_wall, kind, payload, name, pos)
            pos = end


def read_field_log(path_or_dir: str | os.PathLike) -> FieldLogReader:
    """Records of a field log (directory, file or stem) in order; see :class:`FieldLogReader`.

    ``reader = read_field_log(d); for rec in reader: ...; reader.stats``
    """
    return FieldLogReader(path_or_dir)
