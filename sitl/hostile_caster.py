"""A hostile NTRIP caster for ``python -m sitl attack``, run as its own process.

It relays the simulated base station (:class:`sitl.caster.RtcmSource`, a TCP server on 127.0.0.1)
to its NTRIP clients (revision 1: ``ICY 200 OK``) like :class:`sitl.caster.MiniNtripCaster`, and
can misbehave in the ways issue 14 lists:

* ``flood_bps``: bytes of ``flood_pattern`` per second mixed into the real stream, written
  *between* real frames (every frame of the base station arrives whole; the client's framer has
  to find it among the flood): ``d3_03`` (the false sync ``D3 03`` repeated), ``crafted_1077``
  (``D3 00 FF 43 50``: a false sync that passes every check but the CRC) or ``random`` bytes.
  The flood is paced in ``flood_chunk_s`` slices and waits for the socket to drain, so a client
  that reads slower (the NTRIP client's byte-rate cap) pushes back: the real frames then queue
  behind the flood, as they would behind any caster that floods;
* ``slow_header_connections``: the first N connections get an endless response header, one byte
  every ``slow_header_byte_s`` (``HTTP/1.1 200 OK`` then a header line that never ends): without a
  header timeout a client waits forever; later connections are served normally.

It runs in a process of its own so that its writes (up to 10 MB/s) cost the harness's emulated
autopilot nothing: the autopilot's timing is what the latency is measured against.  It listens on
127.0.0.1 only, prints ``PORT <n>`` on stdout once it listens, and on SIGTERM writes its counters
as JSON to ``--stats``.  The password comes from the environment (``HOSTILE_CASTER_PASSWORD``),
not the command line.
"""
from __future__ import annotations

import argparse
import asyncio
import base64
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

PASSWORD_ENV = "HOSTILE_CASTER_PASSWORD"
PATTERNS = ("d3_03", "crafted_1077", "random")
TRICKLE_HEAD = b"HTTP/1.1 200 OK\r\nX-Trickle: "


def flood_block(pattern: str, n: int, seed: int = 1) -> bytes:
    """``n`` bytes (rounded down to whole pattern units) of a flood pattern."""
    if pattern == "d3_03":
        return b"\xd3\x03" * (n // 2)
    if pattern == "crafted_1077":
        return b"\xd3\x00\xff\x43\x50" * (n // 5)
    if pattern == "random":
        return random.Random(seed).randbytes(n)
    raise ValueError(f"flood pattern {pattern!r}; known: {', '.join(PATTERNS)}")


class FrameSplitter:
    """Complete RTCM 3 frames of a *trusted* stream (the harness's own base station), by their
    length field only: the relay writes whole frames so the flood never lands inside one."""

    def __init__(self):
        self.buf = bytearray()
        self.skipped = 0

    def feed(self, data: bytes) -> list[bytes]:
        self.buf += data
        out = []
        buf = self.buf
        while True:
            if buf and buf[0] != 0xD3:
                i = buf.find(b"\xd3")
                cut = len(buf) if i < 0 else i
                self.skipped += cut
                del buf[:cut]
            if len(buf) < 3:
                return out
            n = 6 + (((buf[1] & 0x03) << 8) | buf[2])
            if len(buf) < n:
                return out
            out.append(bytes(buf[:n]))
            del buf[:n]


class HostileCaster:
    def __init__(self, source_port: int, mountpoint: str, user: str = "", password: str = "", *,
                 flood_bps: float = 0.0, flood_pattern: str = "d3_03", flood_chunk_s: float = 0.05,
                 slow_header_connections: int = 0, slow_header_byte_s: float = 0.2,
                 host: str = "127.0.0.1", port: int = 0, seed: int = 1):
        self.source = ("127.0.0.1", source_port)
        self.mountpoint = mountpoint
        self.auth = base64.b64encode(f"{user}:{password}".encode()).decode() if user else None
        self.host, self.port = host, port
        self.flood_bps = float(flood_bps)
        self.flood_chunk_s = flood_chunk_s
        self.slow_header_connections = slow_header_connections
        self.slow_header_byte_s = slow_header_byte_s
        # one second of flood, cycled: the pattern's unit divides the slice sizes used below
        unit = {"d3_03": 2, "crafted_1077": 5, "random": 1}[flood_pattern]
        self._unit = unit
        self._block = flood_block(flood_pattern, max(unit, int(self.flood_bps) // unit * unit * 2), seed) \
            if self.flood_bps > 0 else b""
        self.clients: list[asyncio.StreamWriter] = []
        self.counters = {"connections": 0, "served": 0, "slow_header_connections": 0, "slow_header_bytes": 0,
                         "slow_header_held_s": 0.0, "frames": 0, "real_bytes": 0, "flood_bytes": 0,
                         "flood_chunks": 0, "flood_behind": 0, "source_skipped_bytes": 0}
        self._server = None
        self._tasks: list[asyncio.Task] = []
        self._splitter = FrameSplitter()

    async def start(self) -> int:
        self._server = await asyncio.start_server(self._on_client, self.host, self.port)
        self.port = self._server.sockets[0].getsockname()[1]
        self._tasks.append(asyncio.create_task(self._relay()))
        return self.port

    async def _relay(self) -> None:
        while True:
            try:
                reader, _w = await asyncio.open_connection(*self.source)
                while data := await reader.read(4096):
                    for fr in self._splitter.feed(data):
                        self.counters["frames"] += 1
                        for c in list(self.clients):
                            try:
                                c.write(fr)
                                self.counters["real_bytes"] += len(fr)
                            except Exception:
                                self.clients.remove(c)
                    self.counters["source_skipped_bytes"] = self._splitter.skipped
            except (OSError, asyncio.IncompleteReadError):
                pass
            await asyncio.sleep(0.5)

    async def _flood(self, writer: asyncio.StreamWriter) -> None:
        """``flood_bps`` in slices; a slice that could not be written in time (the client reads
        slower) is not made up later: the offered rate is a ceiling."""
        per = self.flood_bps * self.flood_chunk_s
        credit = 0.0
        pos = 0
        block = self._block
        t_next = time.monotonic()
        while True:
            credit = min(credit + per, 2 * per)
            n = int(credit) // self._unit * self._unit
            if n:
                credit -= n
                while n:
                    k = min(n, len(block) - pos)
                    writer.write(block[pos:pos + k])
                    pos = (pos + k) % len(block)
                    n -= k
                    self.counters["flood_bytes"] += k
                self.counters["flood_chunks"] += 1
                await writer.drain()
            t_next += self.flood_chunk_s
            d = t_next - time.monotonic()
            if d > 0:
                await asyncio.sleep(d)
            else:
                self.counters["flood_behind"] += 1
                t_next = time.monotonic()
                credit = 0.0

    async def _trickle(self, reader, writer) -> None:
        """An endless response header, one byte at a time, until the client goes away."""
        self.counters["slow_header_connections"] += 1
        t0 = time.monotonic()
        gone = asyncio.create_task(reader.read())
        try:
            head = TRICKLE_HEAD
            i = 0
            while not gone.done():
                writer.write(head[i:i + 1] if i < len(head) else b"a")
                i += 1
                self.counters["slow_header_bytes"] += 1
                await writer.drain()
                await asyncio.wait({gone}, timeout=self.slow_header_byte_s)
        except (ConnectionError, OSError):
            pass
        finally:
            gone.cancel()
            self.counters["slow_header_held_s"] += round(time.monotonic() - t0, 3)
            writer.close()

    async def _on_client(self, reader, writer) -> None:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 10.0)
        except Exception:
            writer.close()
            return
        lines = head.decode("latin-1").split("\r\n")
        parts = lines[0].split()
        path = parts[1] if len(parts) > 1 else "/"
        auth_ok = self.auth is None or any(line.lower().startswith("authorization: basic ") and
                                           line.split()[-1] == self.auth for line in lines)
        if path.lstrip("/") != self.mountpoint or not auth_ok:
            writer.write(b"HTTP/1.0 401 Unauthorized\r\n\r\n")
            writer.close()
            return
        self.counters["connections"] += 1
        if self.counters["connections"] <= self.slow_header_connections:
            await self._trickle(reader, writer)
            return
        self.counters["served"] += 1
        writer.write(b"ICY 200 OK\r\n")
        self.clients.append(writer)
        flood = asyncio.create_task(self._flood(writer)) if self.flood_bps > 0 else None
        try:
            await reader.read()
        except (Exception, asyncio.CancelledError):
            pass
        finally:
            if flood is not None:
                flood.cancel()
            if writer in self.clients:
                self.clients.remove(writer)

    async def close(self) -> None:
        for t in self._tasks:
            t.cancel()
        for c in self.clients:
            c.close()
        if self._server is not None:
            self._server.close()


# ---------------------------------------------------------------------------------------------
# harness side
async def start_hostile_caster(source_port: int, out_dir: Path, *, mountpoint: str = "SITL", user: str = "sitl",
                               password: str | None = None, **opts):
    """Start the caster process in front of ``source_port``; a :class:`sitl.caster.Caster` whose
    ``close`` stops it (its counters are then in ``out_dir / 'hostile_caster.json'``)."""
    import secrets
    from .caster import Caster
    password = password or secrets.token_hex(12)
    stats = Path(out_dir) / "hostile_caster.json"
    stats.unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "sitl.hostile_caster", "--source-port", str(source_port),
           "--mountpoint", mountpoint, "--user", user, "--stats", str(stats)]
    for k, v in opts.items():
        cmd += ["--" + k.replace("_", "-"), str(v)]
    env = dict(os.environ, **{PASSWORD_ENV: password})
    log = open(Path(out_dir) / "hostile_caster.log", "wb")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, stdin=subprocess.DEVNULL, env=env,
                            cwd=str(Path(__file__).resolve().parent.parent))
    log.close()
    loop = asyncio.get_running_loop()
    line = await asyncio.wait_for(loop.run_in_executor(None, proc.stdout.readline), 30.0)
    if not line.startswith(b"PORT "):
        proc.kill()
        raise RuntimeError(f"hostile caster did not start: {line!r} (see {out_dir}/hostile_caster.log)")
    return Caster("hostile", int(line.split()[1]), mountpoint, user, password, proc=proc)


def read_stats(out_dir: Path) -> dict:
    try:
        return json.loads((Path(out_dir) / "hostile_caster.json").read_text())
    except (OSError, ValueError):
        return {}


async def _main(args) -> None:
    c = HostileCaster(args.source_port, args.mountpoint, args.user, os.environ.get(PASSWORD_ENV, ""),
                      flood_bps=args.flood_bps, flood_pattern=args.flood_pattern, flood_chunk_s=args.flood_chunk_s,
                      slow_header_connections=args.slow_header_connections,
                      slow_header_byte_s=args.slow_header_byte_s)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    port = await c.start()
    print(f"PORT {port}", flush=True)
    await stop.wait()
    await c.close()
    if args.stats:
        Path(args.stats).write_text(json.dumps(c.counters, indent=1))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python -m sitl.hostile_caster", description=__doc__.split("\n")[0])
    p.add_argument("--source-port", type=int, required=True)
    p.add_argument("--mountpoint", default="SITL")
    p.add_argument("--user", default="sitl")
    p.add_argument("--flood-bps", type=float, default=0.0)
    p.add_argument("--flood-pattern", default="d3_03", choices=PATTERNS)
    p.add_argument("--flood-chunk-s", type=float, default=0.05)
    p.add_argument("--slow-header-connections", type=int, default=0)
    p.add_argument("--slow-header-byte-s", type=float, default=0.2)
    p.add_argument("--stats", help="write the counters here as JSON on SIGTERM")
    asyncio.run(_main(p.parse_args(argv)))


if __name__ == "__main__":
    main()
