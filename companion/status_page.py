"""A live status page served by the service: health, fix state, satellites and their test ratios,
sigma and protection-level plots, the last events, for a browser on the board's network.

``StatusBoard`` keeps what the page shows (bounded: the last ``history_s`` of solutions at 1 Hz
of GPS time, the last ``max_events`` events); the service feeds it.  ``StatusPageServer`` answers
``GET /`` (one self-contained HTML page: no external scripts, styles or fonts, so it works on a
field network without internet), ``GET /status.json`` (what the page polls every second) and
``GET /health.json`` (the full health report).

HTTP is written on asyncio streams rather than taken from a framework: the service needs three
read-only routes, and aiohttp or similar would be a dependency on the board for that.  Every
request is bounded (8 KiB of headers, 5 s to send them, GET/HEAD only, one request per
connection), and the page is served on 127.0.0.1 unless configured otherwise: it shows where the
vehicle is.
"""
from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from collections import deque
from importlib import resources

from .aid_status_record import json_number

log = logging.getLogger(__name__)


def _num(x, nd: int = 3):
    return json_number(x, nd)

MAX_HEADER_BYTES = 8192
HEADER_TIMEOUT_S = 5.0


class StatusBoard:
    """What the page shows, fed by the service; all methods are cheap and bounded."""

    def __init__(self, history_s: float = 600.0, max_events: int = 50):
        self.solutions: deque = deque(maxlen=int(history_s))
        self.events: deque = deque(maxlen=max_events)
        self.aid_status: dict | None = None
        self.health: dict | None = None
        self._last_slot = None
        self.t_start = time.time()

    def add_solution(self, sol) -> None:
        """One point per second of GPS time (the latest solution of that second wins the next)."""
        slot = math.floor(sol.t_gps)
        if slot == self._last_slot:
            return
        self._last_slot = slot
        s = sol.sigma_r_n_m
        x = sol.extras
        self.solutions.append({
            "t_gps": _num(sol.t_gps), "status": sol.status, "fix_state": sol.fix_state,
            "fix_ratio": _num(sol.fix_ratio, 2), "sigma_h_m": _num(math.hypot(s[0], s[1])),
            "sigma_v_m": _num(s[2]), "hpl_m": _num(x.get("hpl_m")), "inject": bool(x.get("inject")),
            "mode": x.get("mode"), "reset_counter": sol.reset_counter,
        })

    def add_event(self, severity: int, text: str) -> None:
        self.events.append({"t_unix": round(time.time(), 1), "severity": int(severity), "text": str(text)})

    def set_aid_status(self, obj: dict) -> None:
        self.aid_status = obj

    def set_health(self, health: dict) -> None:
        self.health = health

    def snapshot(self) -> dict:
        """The object of /status.json."""
        sources = {}
        for name, src in ((self.aid_status or {}).get("sources") or {}).items():
            sources[name] = {k: src.get(k) for k in ("t_gps", "fused", "labels", "test_ratio", "accepted",
                                                     "rows_fused", "rows_rejected")}
        # satellites whose pseudorange (or double difference) the last update accepted
        used = {lab for name, src in sources.items() if "pseudorange" in name or "rtk" in name
                for lab, ok in zip(src.get("labels") or (), src.get("accepted") or ()) if ok}
        health = self.health or {}
        f = health.get("filter", {})
        return {"v": 1, "uptime_s": round(time.time() - self.t_start, 1),
                "last": self.solutions[-1] if self.solutions else None,
                "satellites_used": len({sat for lab in used for sat in _satellites_of(lab)}),
                # per constellation, from the last rover epoch (the health report's)
                "satellites_by_system": dict(f.get("satellites_by_system") or {}),
                "history": list(self.solutions), "sources": sources, "events": list(self.events),
                "filter": {k: f.get(k) for k in ("status", "mode", "reset_counter") if k in f},
                # the base as its RTCM 1007 / 1008 / 1033 describe it (printable ASCII already)
                "base": _base_text(health.get("rtcm_base"), health.get("rtk_antennas"))}


def _satellites_of(label) -> list[str]:
    """The satellites a row label names: 'G05', 'G05:L1C', or both of a double difference,
    'G07-G11 L1C phase' (the reference satellite is used too)."""
    return str(label).split(" ")[0].split(":")[0].split("-")


def _base_text(desc: dict | None, antennas: dict | None = None) -> str | None:
    """'receiver / antenna' of the base, and whether RTK calibrates that antenna ([filter] rtk_antennas)."""
    if not desc:
        return None
    parts = [desc.get("receiver") or "", desc.get("antenna") or ""]
    text = " / ".join(p for p in parts if p) or f"station {desc.get('station_id')}"
    if antennas and desc.get("antenna"):
        text += " (calibrated)" if (antennas.get("base") or {}).get("calibration") else " (not calibrated)"
    return text


def _page_html() -> bytes:
    return resources.files("companion").joinpath("status_page.html").read_bytes()


class StatusPageServer:
    """GET /, /status.json, /health.json on ``host:port`` (port 0: any free port, see ``port``)."""

    def __init__(self, board: StatusBoard, host: str = "127.0.0.1", port: int = 8765):
        self.board = board
        self.host = host
        self.requested_port = port
        self.port: int | None = None
        self._server: asyncio.base_events.Server | None = None
        self._page = _page_html()
        self.counters = {"requests": 0, "not found": 0, "bad requests": 0}

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._serve, self.host, self.requested_port)
        self.port = self._server.sockets[0].getsockname()[1]
        log.info("status page on http://%s:%d/", self.host, self.port)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
            self._server = None

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            try:
                head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HEADER_TIMEOUT_S)
            except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, asyncio.TimeoutError):
                self.counters["bad requests"] += 1
                return
            if len(head) > MAX_HEADER_BYTES:
                self.counters["bad requests"] += 1
                await self._reply(writer, 431, "text/plain", b"headers too large\n")
                return
            parts = head.split(b"\r\n", 1)[0].decode("latin-1").split()
            if len(parts) != 3 or parts[0] not in ("GET", "HEAD"):
                self.counters["bad requests"] += 1
                await self._reply(writer, 405, "text/plain", b"GET only\n")
                return
            self.counters["requests"] += 1
            path = parts[1].split("?", 1)[0]
            if path in ("/", "/index.html"):
                body, ctype = self._page, "text/html; charset=utf-8"
            elif path == "/status.json":
                body, ctype = json.dumps(self.board.snapshot(), default=str).encode(), "application/json"
            elif path == "/health.json":
                body, ctype = json.dumps(self.board.health or {}, default=str).encode(), "application/json"
            else:
                self.counters["not found"] += 1
                await self._reply(writer, 404, "text/plain", b"not found\n")
                return
            await self._reply(writer, 200, ctype, body, head_only=parts[0] == "HEAD")
        except (ConnectionError, OSError):
            pass
        finally:
            writer.close()

    @staticmethod
    async def _reply(writer, code: int, ctype: str, body: bytes, head_only: bool = False) -> None:
        reason = {200: "OK", 404: "Not Found", 405: "Method Not Allowed", 431: "Request Header Fields Too Large"}[code]
        writer.write((f"HTTP/1.1 {code} {reason}\r\nContent-Type: {ctype}\r\nContent-Length: {len(body)}\r\n"
                      "Cache-Control: no-store\r\nConnection: close\r\n\r\n").encode("latin-1"))
        if not head_only:
            writer.write(body)
        await writer.drain()
