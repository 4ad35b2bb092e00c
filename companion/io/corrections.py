"""Correction (RTCM 3) sources behind one interface, and the pipeline to core messages.

A *source* has ``name``, ``counters`` (dict), ``health()`` and ``stream()`` -> async iterator of raw
byte chunks exactly as received; it reconnects by itself and only stops when closed/cancelled
(a file source stops at its end unless looping).  Sources:

* :class:`~companion.io.ntrip.NtripClient` (NTRIP rev 1/2 caster)
* :class:`SerialCorrectionSource` -- a radio on a serial port (pyserial, non-blocking, read on
  the event loop via ``add_reader``; reopened when the port goes away)
* :class:`~companion.io.mqtt.MqttRtcmSubscriber` -- payloads of an MQTT topic
* :class:`FileCorrectionSource` -- a recorded file, paced at ``rate_bps`` or as fast as possible

:class:`CorrectionPipeline` frames the bytes (CRC-checked, :class:`~companion.io.rtcm.RtcmFramer`),
decodes each frame (:class:`~companion.io.rtcm.RtcmDecoder`) into core messages
(``GnssEpoch(source='base')``, ``BaseStationPosition``, ``GpsEphemeris``) and optionally passes each
whole frame to a forwarder (e.g. GPS_RTCM_DATA to the autopilot via
:func:`companion.io.mavlink_encode.gps_rtcm_data_messages`).  It yields :class:`CorrectionBatch` items
(receive time, raw chunk for the field log, frames, messages).
"""
from __future__ import annotations

import asyncio
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import AsyncIterator, Callable, Protocol

import numpy as np

from ..messages import BaseStationPosition
from .rtcm import RtcmDecoder
from .ubx import WeekHint

log = logging.getLogger(__name__)


class CorrectionSource(Protocol):
    name: str
    counters: dict

    def stream(self) -> AsyncIterator[bytes]: ...


class SerialCorrectionSource:
    """RTCM from a serial port (radio modem).  Opened non-blocking; read when the fd is readable;
    on an error (USB radio unplugged) the port is closed and reopened every ``reopen_interval_s``."""

    def __init__(self, port: str, baud: int = 57600, *, reopen_interval_s: float = 1.0, read_size: int = 4096):
        self.port, self.baud = port, int(baud)
        self.reopen_interval_s = reopen_interval_s
        self.read_size = read_size
        self.name = f"serial:{port}@{baud}"
        self.counters: dict[str, int] = {"bytes": 0, "chunks": 0, "opens": 0, "errors": 0}
        self.last_error = ""
        self._closed = False

    def close(self) -> None:
        self._closed = True

    async def stream(self) -> AsyncIterator[bytes]:
        import serial  # pyserial
        loop = asyncio.get_running_loop()
        while not self._closed:
            try:
                ser = serial.Serial(self.port, self.baud, timeout=0)
            except (serial.SerialException, OSError) as exc:
                self.counters["errors"] += 1
                self.last_error = str(exc)
                await asyncio.sleep(self.reopen_interval_s)
                continue
            self.counters["opens"] += 1
            queue: asyncio.Queue = asyncio.Queue()
            fd = ser.fileno()

            def on_readable():
                try:
                    data = os.read(fd, self.read_size)
                except OSError as exc:      # EIO when the other side of a pty/USB goes away
                    loop.remove_reader(fd)
                    queue.put_nowait(exc)
                    return
                if not data:
                    loop.remove_reader(fd)
                    queue.put_nowait(EOFError("serial port closed"))
                    return
                queue.put_nowait(data)

            loop.add_reader(fd, on_readable)
            try:
                while True:
                    item = await queue.get()
                    if isinstance(item, BaseException):
                        raise item
                    self.counters["bytes"] += len(item)
                    self.counters["chunks"] += 1
                    yield item
            except (OSError, EOFError) as exc:
                self.counters["errors"] += 1
                self.last_error = str(exc)
                log.warning("%s: %s; reopening", self.name, exc)
            finally:
                loop.remove_reader(fd)
                ser.close()
            await asyncio.sleep(self.reopen_interval_s)

    def __aiter__(self):
        return self.stream()

    def health(self) -> dict:
        return {"name": self.name, "last_error": self.last_error, **self.counters}


class FileCorrectionSource:
    """A recorded RTCM file: ``realtime`` paces the bytes at ``rate_bps`` (RTCM files carry no
    time tags of their own), otherwise chunks come as fast as the consumer takes them."""

    def __init__(self, path: str | Path, *, realtime: bool = True, rate_bps: float = 2000.0, loop: bool = False,
                 chunk_size: int = 1024):
        self.path = Path(path)
        self.realtime, self.rate_bps, self.loop = realtime, float(rate_bps), loop
        self.chunk_size = chunk_size
        self.name = f"file:{self.path}"
        self.counters: dict[str, int] = {"bytes": 0, "chunks": 0, "loops": 0}

    async def stream(self) -> AsyncIterator[bytes]:
        t0 = time.monotonic()
        sent = 0
        while True:
            with self.path.open("rb") as fh:
                while chunk := fh.read(self.chunk_size):
                    if self.realtime:
                        due = t0 + sent / self.rate_bps
                        delay = due - time.monotonic()
                        if delay > 0:
                            await asyncio.sleep(delay)
                    else:
                        await asyncio.sleep(0)
                    sent += len(chunk)
                    self.counters["bytes"] += len(chunk)
                    self.counters["chunks"] += 1
                    yield chunk
            if not self.loop:
                return
            self.counters["loops"] += 1

    def __aiter__(self):
        return self.stream()

    def health(self) -> dict:
        return {"name": self.name, **self.counters}


@dataclass
class CorrectionBatch:
    t_mono_ns: int                   # when the chunk arrived
    raw: bytes                       # the chunk as received (field log)
    frames: list[bytes] = field(default_factory=list)     # whole CRC-checked RTCM frames
    messages: list = field(default_factory=list)          # core messages decoded from them


class CorrectionPipeline:
    """Source bytes -> frames -> core messages (+ optional forwarding of every frame).

    ``forward``: callable(frame: bytes) called for every good frame (e.g. wrap into GPS_RTCM_DATA
    and send).  ``base_position_ecef_m``: when given, every decoded BaseStationPosition has its
    ``r_e`` replaced by it (surveyed coordinates better than the caster's), and one is emitted
    with the first batch even before the stream's own 1005/1006 arrives.
    """

    def __init__(self, source, *, week_hint: WeekHint = None, forward: Callable[[bytes], None] | None = None,
                 base_position_ecef_m=None, station_id: int = 0, leap_seconds: int = 18):
        self.source = source
        self.decoder = RtcmDecoder(week_hint=week_hint, leap_seconds=leap_seconds)
        self.framer = self.decoder.framer
        self.forward = forward
        self.base_override = None if base_position_ecef_m is None else np.asarray(base_position_ecef_m, float)
        self.station_id = station_id
        self._override_sent = False
        self.counters: dict[str, int] = {"chunks": 0, "frames": 0, "messages": 0, "forwarded": 0,
                                         "forward_errors": 0}

    def process(self, raw: bytes, t_mono_ns: int | None = None) -> CorrectionBatch:
        """Pure step (apart from the forwarder): one chunk in, its batch out."""
        batch = CorrectionBatch(time.monotonic_ns() if t_mono_ns is None else t_mono_ns, bytes(raw))
        self.counters["chunks"] += 1
        if self.base_override is not None and not self._override_sent:
            batch.messages.append(BaseStationPosition(self.station_id, self.base_override.copy()))
            self._override_sent = True
        for frame in self.framer.feed(raw):
            batch.frames.append(frame)
            self.counters["frames"] += 1
            if self.forward is not None:
                try:
                    self.forward(frame)
                    self.counters["forwarded"] += 1
                except Exception:
                    self.counters["forward_errors"] += 1
                    log.exception("RTCM forwarder failed")
            for msg in self.decoder.decode_frame(frame):
                if self.base_override is not None and isinstance(msg, BaseStationPosition):
                    msg = BaseStationPosition(msg.station_id, self.base_override.copy(), msg.antenna_height_m)
                batch.messages.append(msg)
        self.counters["messages"] += len(batch.messages)
        return batch

    async def stream(self) -> AsyncIterator[CorrectionBatch]:
        async for raw in self.source.stream():
            yield self.process(raw)
        for msg in self.decoder.flush():       # a finite source (file) ended mid-epoch
            yield CorrectionBatch(time.monotonic_ns(), b"", [], [msg])

    def __aiter__(self):
        return self.stream()

    def health(self) -> dict:
        src = self.source.health() if hasattr(self.source, "health") else {"name": getattr(self.source, "name", "?")}
        return {"source": src, **self.counters, "rtcm": self.decoder.counters}


def correction_source_from_config(cfg, position_cb=None):
    """The source for a :class:`companion.config.CorrectionsConfig`; None for 'none'."""
    s = cfg.source
    if s == "none":
        return None
    if s == "ntrip":
        from .ntrip import NtripClient
        n = cfg.ntrip
        from .ntrip import DEFAULT_MAX_RATE_BPS
        return NtripClient(n.host, n.port, n.mountpoint, n.user, n.password, version=n.version,
                           gga_interval_s=n.gga_interval_s, position_cb=position_cb, timeout_s=n.timeout_s,
                           header_timeout_s=getattr(n, "header_timeout_s", None),
                           max_rate_bps=getattr(n, "max_rate_bps", DEFAULT_MAX_RATE_BPS))
    if s == "serial":
        return SerialCorrectionSource(cfg.serial.port, cfg.serial.baud)
    if s == "mqtt":
        from .mqtt import MqttRtcmSubscriber
        return MqttRtcmSubscriber(cfg.mqtt.host, cfg.mqtt.port, cfg.mqtt.topic)
    if s == "file":
        return FileCorrectionSource(cfg.file.path, realtime=cfg.file.realtime, rate_bps=cfg.file.rate_bps,
                                    loop=cfg.file.loop)
    raise ValueError(f"unknown corrections source {s!r}")


__all__ = ["CorrectionSource", "SerialCorrectionSource", "FileCorrectionSource", "CorrectionBatch",
           "CorrectionPipeline", "correction_source_from_config"]
