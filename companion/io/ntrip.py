"""Asyncio NTRIP client (revision 1 and 2) yielding raw RTCM bytes.

* Request (:func:`build_request`): ``GET /<mountpoint>`` with ``User-Agent: NTRIP companion/0.1``,
  HTTP Basic authentication when a user is given; revision 2 adds ``HTTP/1.1``, ``Host`` and
  ``Ntrip-Version: Ntrip/2.0``.
* Response (:func:`parse_response_head`): ``ICY 200 OK`` (revision 1: the stream follows the
  status line directly -- RTKLIB's caster sends no blank line), ``HTTP/1.x 200`` with headers
  (revision 2, the body usually ``Transfer-Encoding: chunked``, undone by :class:`ChunkedDecoder`),
  ``SOURCETABLE 200 OK`` or ``Content-Type: gnss/sourcetable`` (the mountpoint does not exist:
  :class:`NtripMountpointError`), ``401`` (:class:`NtripAuthError`).  A caster that answers a
  revision-2 request with ``ICY 200 OK`` (RTKLIB's str2str does) is accepted.
* GGA upload for network (VRS) mountpoints: every ``gga_interval_s`` the client sends an NMEA GGA
  sentence (:func:`nmea_gga`) built from ``position_cb()`` -> (lat_deg, lon_deg, height_msl_m) or
  None; one is also sent right after the request.
* Reconnection: any error or ``timeout_s`` without data closes the connection; the next attempt
  waits ``backoff`` = min(``backoff_max_s``, ``backoff_initial_s`` * 2^n) scaled by a random factor
  in [0.5, 1] ("equal jitter", so a fleet does not reconnect in lock step); n resets after a
  connection that delivered data.  Authentication failures are retried too (a caster may be
  misconfigured for a moment) but counted and logged as errors with the caster's answer.

* Hostile casters: a status line that is not ``ICY 200`` / ``SOURCETABLE 200`` / ``HTTP/1.x`` with
  a three-digit ASCII code (``HTTP/1.1 \u00b200``) is an :class:`NtripError`; the whole response
  header must arrive within ``header_timeout_s`` (a caster that sends it one byte at a time is
  dropped, ``header_timeouts``); the stream is read at most at ``max_rate_bps`` (bursts of one
  second): a caster that floods is throttled (the client pauses reading, so TCP pushes back on the
  caster instead of our SD card and CPU taking the flood; ``rate_limited`` counts the pauses); a
  source table larger than 1 MB is an error.

Counters (``client.counters``): ``bytes``, ``chunks``, ``connects``, ``reconnects``,
``auth_failures``, ``mountpoint_errors``, ``errors``, ``timeouts``, ``header_timeouts``,
``rate_limited``, ``gga_sent``.
``client.last_error`` holds the last error text.
"""
from __future__ import annotations

import asyncio
import base64
import logging
import random
import re
import time
from typing import AsyncIterator, Callable

from .ratecap import ByteRateCap

log = logging.getLogger(__name__)

MAX_SOURCETABLE_BYTES = 1 << 20
DEFAULT_MAX_RATE_BPS = 64_000.0     # 10x a four-constellation MSM7 stream at 1 Hz
_STATUS_CODE = re.compile(r"[0-9]{3}")      # ASCII only: str.isdigit() accepts '\u00b2'

USER_AGENT = "NTRIP companion/0.1"


class NtripError(ConnectionError):
    """The caster refused or broke the request."""


class NtripAuthError(NtripError):
    """401 Unauthorized: wrong user or password for the mountpoint."""


class NtripMountpointError(NtripError):
    """The caster answered with its source table: the mountpoint does not exist (or is down)."""


# ---------------------------------------------------------------------------------------------
# pure helpers
def build_request(mountpoint: str, host: str, port: int, user: str = "", password: str = "",
                  version: int = 2, user_agent: str = USER_AGENT) -> bytes:
    path = "/" + mountpoint.lstrip("/")
    lines = [f"GET {path} HTTP/1.1" if version == 2 else f"GET {path} HTTP/1.0",
             f"User-Agent: {user_agent}"]
    if version == 2:
        lines += [f"Host: {host}:{port}", "Ntrip-Version: Ntrip/2.0", "Connection: close"]
    if user:
        token = base64.b64encode(f"{user}:{password}".encode()).decode("ascii")
        lines.append(f"Authorization: Basic {token}")
    return ("\r\n".join(lines) + "\r\n\r\n").encode("ascii")


def nmea_checksum(body: str) -> int:
    """XOR of the characters between '$' and '*'."""
    c = 0
    for ch in body.encode("ascii"):
        c ^= ch
    return c


def nmea_gga(t_utc_s: float, lat_deg: float, lon_deg: float, height_msl_m: float, *, quality: int = 1,
             num_sats: int = 12, hdop: float = 1.0, geoid_sep_m: float = 0.0, talker: str = "GP") -> str:
    """An NMEA GGA sentence (with checksum and CRLF) for a position at UTC time ``t_utc_s`` (UNIX s)."""
    tod = t_utc_s % 86400.0
    hh, rem = divmod(tod, 3600.0)
    mm, ss = divmod(rem, 60.0)
    alat, alon = abs(lat_deg), abs(lon_deg)
    lat_s = f"{int(alat):02d}{(alat - int(alat)) * 60:08.5f}"
    lon_s = f"{int(alon):03d}{(alon - int(alon)) * 60:08.5f}"
    body = (f"{talker}GGA,{int(hh):02d}{int(mm):02d}{ss:05.2f},{lat_s},{'N' if lat_deg >= 0 else 'S'},"
            f"{lon_s},{'E' if lon_deg >= 0 else 'W'},{quality},{num_sats:02d},{hdop:.1f},"
            f"{height_msl_m:.3f},M,{geoid_sep_m:.3f},M,,")
    return f"${body}*{nmea_checksum(body):02X}\r\n"


class ChunkedDecoder:
    """Incremental HTTP/1.1 chunked transfer-encoding decoder: ``feed(bytes) -> bytes`` of body.

    ``done`` becomes True at the terminating zero-length chunk.  Malformed sizes raise NtripError.
    """

    def __init__(self):
        self._buf = bytearray()
        self._remaining = 0          # body bytes left in the current chunk
        self._need_crlf = False
        self.done = False

    def feed(self, data: bytes) -> bytes:
        self._buf += data
        out = bytearray()
        buf = self._buf
        while not self.done:
            if self._remaining:
                n = min(self._remaining, len(buf))
                if n == 0:
                    break
                out += buf[:n]
                del buf[:n]
                self._remaining -= n
                if self._remaining == 0:
                    self._need_crlf = True
                continue
            if self._need_crlf:
                if len(buf) < 2:
                    break
                if buf[:2] != b"\r\n":
                    raise NtripError("chunked encoding: missing CRLF after chunk")
                del buf[:2]
                self._need_crlf = False
                continue
            i = buf.find(b"\r\n")
            if i < 0:
                if len(buf) > 1024:
                    raise NtripError("chunked encoding: chunk size line too long")
                break
            line = bytes(buf[:i]).split(b";")[0].strip()
            del buf[:i + 2]
            try:
                size = int(line, 16)
            except ValueError:
                raise NtripError(f"chunked encoding: bad chunk size {line[:20]!r}") from None
            if size == 0:
                self.done = True
                break
            self._remaining = size
        return bytes(out)


class ResponseHead:
    def __init__(self, kind: str, status: int, headers: dict[str, str], body_start: bytes):
        self.kind = kind                # 'icy', 'http', 'sourcetable'
        self.status = status
        self.headers = headers
        self.body_start = body_start

    @property
    def chunked(self) -> bool:
        return "chunked" in self.headers.get("transfer-encoding", "").lower()


def parse_response_head(buf: bytes, eof: bool = False) -> ResponseHead | None:
    """Parse the caster's answer from the bytes received so far; None if more are needed.

    ``eof``: the caster closed the connection; parse what there is (RTKLIB answers a bad password
    with ``HTTP/1.0 401 Unauthorized\r\n`` and closes, without the blank line)."""
    if eof and b"\r\n\r\n" not in buf and not buf.startswith(b"ICY"):
        buf = buf.rstrip(b"\r\n") + b"\r\n\r\n"
    i = buf.find(b"\r\n")
    if i < 0:
        if len(buf) > 4096:
            raise NtripError(f"no status line from caster: {buf[:60]!r}")
        return None
    status_line = buf[:i].decode("latin-1").strip()
    if status_line.startswith("ICY 200"):
        rest = buf[i + 2:]
        if rest.startswith(b"\r\n"):
            rest = rest[2:]
        return ResponseHead("icy", 200, {}, rest)
    j = buf.find(b"\r\n\r\n")
    if j < 0:
        if len(buf) > 16384:
            raise NtripError("caster response header too long")
        return None
    head = buf[:j].decode("latin-1").split("\r\n")
    headers = {}
    for line in head[1:]:
        if ":" in line:
            k, v = line.split(":", 1)
            headers[k.strip().lower()] = v.strip()
    parts = status_line.split(None, 2)
    if status_line.startswith("SOURCETABLE"):
        return ResponseHead("sourcetable", 200, headers, buf[j + 4:])
    if len(parts) < 2 or not parts[0].startswith("HTTP/") or not _STATUS_CODE.fullmatch(parts[1]):
        raise NtripError(f"unexpected caster answer: {status_line[:80]!r}")
    status = int(parts[1])
    kind = "http"
    if status == 200 and "sourcetable" in headers.get("content-type", "").lower():
        kind = "sourcetable"
    return ResponseHead(kind, status, headers, buf[j + 4:])


# ---------------------------------------------------------------------------------------------
class NtripClient:
    """See the module docstring.  ``async for data in client.stream(): ...`` (runs until
    :meth:`close` or cancellation)."""

    def __init__(self, host: str, port: int, mountpoint: str, user: str = "", password: str = "", *,
                 version: int = 2, gga_interval_s: float = 0.0,
                 position_cb: Callable[[], tuple[float, float, float] | None] | None = None,
                 timeout_s: float = 10.0, connect_timeout_s: float = 5.0, backoff_initial_s: float = 1.0,
                 backoff_max_s: float = 60.0, user_agent: str = USER_AGENT, read_size: int = 4096,
                 rng: random.Random | None = None, header_timeout_s: float | None = None,
                 max_rate_bps: float = DEFAULT_MAX_RATE_BPS):
        if version not in (1, 2):
            raise ValueError("NTRIP version must be 1 or 2")
        self.host, self.port, self.mountpoint = host, int(port), mountpoint
        self.user, self.password, self.version = user, password, version
        self.gga_interval_s = gga_interval_s
        self.position_cb = position_cb
        self.timeout_s = timeout_s
        self.header_timeout_s = timeout_s if header_timeout_s is None else header_timeout_s
        self.max_rate_bps = max_rate_bps
        self.connect_timeout_s = connect_timeout_s
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        self.user_agent = user_agent
        self.read_size = read_size
        self.rng = rng or random.Random()
        self.counters: dict[str, int] = {"bytes": 0, "chunks": 0, "connects": 0, "reconnects": 0,
                                         "auth_failures": 0, "mountpoint_errors": 0, "errors": 0,
                                         "timeouts": 0, "header_timeouts": 0, "rate_limited": 0,
                                         "gga_sent": 0}
        self.last_error: str = ""
        self.connected = False
        self._closed = False
        self._writer: asyncio.StreamWriter | None = None
        self.name = f"ntrip://{host}:{port}/{mountpoint}"

    def close(self) -> None:
        self._closed = True
        if self._writer is not None:
            self._writer.close()

    def backoff_s(self, attempt: int) -> float:
        base = min(self.backoff_max_s, self.backoff_initial_s * (2 ** min(attempt, 30)))
        return base * (0.5 + 0.5 * self.rng.random())

    async def fetch_sourcetable(self) -> str:
        """The caster's source table (``GET /``) as text."""
        reader, writer = await asyncio.wait_for(asyncio.open_connection(self.host, self.port),
                                                self.connect_timeout_s)
        try:
            writer.write(build_request("", self.host, self.port, self.user, self.password, self.version,
                                       self.user_agent))
            await writer.drain()
            data = bytearray()
            while True:
                chunk = await asyncio.wait_for(reader.read(65536), self.timeout_s)
                if not chunk:
                    break
                data += chunk
                if b"ENDSOURCETABLE" in data[-len(chunk) - 16:]:
                    break
                if len(data) > MAX_SOURCETABLE_BYTES:
                    raise NtripError(f"source table larger than {MAX_SOURCETABLE_BYTES} bytes")
            head = parse_response_head(bytes(data))
            if head is None:
                raise NtripError("truncated source table answer")
            if head.status == 401:
                raise NtripAuthError("401 Unauthorized fetching the source table")
            body = head.body_start
            if head.chunked:
                body = ChunkedDecoder().feed(body)
            return body.decode("latin-1")
        finally:
            writer.close()

    def _gga(self) -> bytes | None:
        if self.position_cb is None:
            return None
        pos = self.position_cb()
        if pos is None:
            return None
        lat, lon, h = pos
        return nmea_gga(time.time(), lat, lon, h).encode("ascii")

    async def _gga_loop(self, writer: asyncio.StreamWriter) -> None:
        while True:
            await asyncio.sleep(self.gga_interval_s)
            g = self._gga()
            if g is not None:
                writer.write(g)
                await writer.drain()
                self.counters["gga_sent"] += 1

    async def _session(self) -> AsyncIterator[bytes]:
        reader, writer = await asyncio.wait_for(asyncio.open_connection(self.host, self.port),
                                                self.connect_timeout_s)
        self._writer = writer
        gga_task = None
        try:
            req = build_request(self.mountpoint, self.host, self.port, self.user, self.password,
                                self.version, self.user_agent)
            writer.write(req)
            await writer.drain()
            head = await self._read_head(reader)
            if head.status == 401:
                raise NtripAuthError(f"{self.name}: 401 Unauthorized (check user/password)")
            if head.kind == "sourcetable":
                raise NtripMountpointError(f"{self.name}: mountpoint not found (caster sent its source table)")
            if head.status != 200:
                raise NtripError(f"{self.name}: caster answered {head.status}")
            self.connected = True
            self.counters["connects"] += 1
            log.info("NTRIP connected to %s (%s)", self.name, head.kind)
            if self.gga_interval_s > 0 and self.position_cb is not None:
                g = self._gga()
                if g is not None:
                    writer.write(g)
                    self.counters["gga_sent"] += 1
                gga_task = asyncio.create_task(self._gga_loop(writer))
            dechunk = ChunkedDecoder() if head.chunked else None
            pending = head.body_start
            cap = ByteRateCap(self.max_rate_bps) if self.max_rate_bps else None
            while True:
                data = dechunk.feed(pending) if dechunk is not None else pending
                if data:
                    self.counters["bytes"] += len(data)
                    self.counters["chunks"] += 1
                    yield data
                if cap is not None and pending:
                    pause = cap.delay_s(len(pending))
                    if pause > 0:
                        # a flooding caster: stop reading for a while (TCP back-pressure)
                        n = self.counters["rate_limited"] = self.counters["rate_limited"] + 1
                        if n in (1, 10, 100, 1000) or n % 10000 == 0:
                            log.warning("NTRIP %s sends faster than %.0f B/s: throttled (%d times)",
                                        self.name, self.max_rate_bps, n)
                        await asyncio.sleep(pause)
                if dechunk is not None and dechunk.done:
                    raise NtripError("caster ended the stream")
                try:
                    pending = await asyncio.wait_for(reader.read(self.read_size), self.timeout_s)
                except asyncio.TimeoutError:
                    self.counters["timeouts"] += 1
                    raise NtripError(f"no data for {self.timeout_s:.0f} s") from None
                if not pending:
                    raise NtripError("caster closed the connection")
        finally:
            self.connected = False
            if gga_task is not None:
                gga_task.cancel()
            writer.close()
            self._writer = None

    async def _read_head(self, reader: asyncio.StreamReader) -> ResponseHead:
        """The caster's response header, complete within ``header_timeout_s`` in total (a caster
        that trickles it must not hold the client), or an NtripError."""
        deadline = time.monotonic() + self.header_timeout_s
        buf = b""
        while True:
            remaining = deadline - time.monotonic()
            try:
                if remaining <= 0:
                    raise asyncio.TimeoutError
                chunk = await asyncio.wait_for(reader.read(self.read_size), remaining)
            except asyncio.TimeoutError:
                self.counters["header_timeouts"] += 1
                raise NtripError(f"no complete response header within {self.header_timeout_s:g} s "
                                 f"({len(buf)} bytes: {buf[:40]!r})") from None
            if not chunk:
                head = parse_response_head(buf, eof=True) if buf.strip() else None
                if head is None or head.status == 200 and head.kind != "sourcetable":
                    raise NtripError(f"caster closed the connection before answering ({buf[:60]!r})")
                return head
            buf += chunk
            head = parse_response_head(buf)
            if head is not None:
                return head

    async def stream(self) -> AsyncIterator[bytes]:
        attempt = 0
        first = True
        while not self._closed:
            if not first:
                self.counters["reconnects"] += 1
            first = False
            got_data = False
            try:
                async for data in self._session():
                    got_data = True
                    yield data
            except asyncio.CancelledError:
                raise
            except NtripAuthError as exc:
                self.counters["auth_failures"] += 1
                self.last_error = str(exc)
                log.error("NTRIP %s", exc)
            except NtripMountpointError as exc:
                self.counters["mountpoint_errors"] += 1
                self.last_error = str(exc)
                log.error("NTRIP %s", exc)
            except (OSError, asyncio.TimeoutError, NtripError) as exc:
                self.counters["errors"] += 1
                self.last_error = f"{type(exc).__name__}: {exc}"
                if not self._closed:
                    log.warning("NTRIP %s: %s", self.name, self.last_error)
            if self._closed:
                break
            attempt = 0 if got_data else attempt + 1
            await asyncio.sleep(self.backoff_s(attempt))

    def __aiter__(self):
        return self.stream()

    def health(self) -> dict:
        return {"name": self.name, "connected": self.connected, "last_error": self.last_error, **self.counters}


__all__ = ["NtripClient", "NtripError", "NtripAuthError", "NtripMountpointError", "build_request",
           "parse_response_head", "ChunkedDecoder", "nmea_gga", "nmea_checksum", "USER_AGENT"]
