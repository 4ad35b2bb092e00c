"""MQTT (aiomqtt 2.x, on paho-mqtt): RTCM subscriber and telemetry publisher, both reconnecting.

Topics published by :class:`MqttTelemetryPublisher` (``<prefix>`` = ``telemetry.topic_prefix``):

* ``<prefix>/solution`` -- JSON of the latest :class:`~companion.messages.NavSolution`
  (:func:`solution_to_json`): ``t_gps``, ``status``, ``lat_deg``, ``lon_deg``, ``height_m``
  (ellipsoidal), ``v_n_mps`` [N, E, D], ``roll_deg``/``pitch_deg``/``yaw_deg``, ``sigma_r_n_m``,
  ``sigma_v_n_mps``, ``reset_counter``, ``last_gnss_update_t_gps``, ``hpl_m`` (horizontal
  protection level, companion.nav.protection; null when there is none), ``inject``.  QoS 0, not
  retained, at most ``rate_hz`` (newer solutions replace older unsent ones).
* ``<prefix>/aid_status`` -- the per aid source status record (companion.aid_status_record:
  innovations, variances, test ratios of each source's last update, the protection level).  QoS 0,
  not retained, sent with the solution (the newest replaces an unsent one).
* ``<prefix>/health`` -- JSON dict supplied by the service (counters, link state).  QoS 1,
  **retained**, so a dashboard that subscribes later sees the last health at once.

:class:`MqttRtcmSubscriber` yields each message payload on its topic as raw RTCM bytes (a
publisher may split or merge frames; the RTCM framer downstream does not care).

Both reconnect after broker loss with exponential backoff (``reconnect_initial_s`` doubling up to
``reconnect_max_s``) and count ``connects``, ``disconnects``, ``errors``; payload counters
``messages``/``bytes`` (subscriber), ``published``/``dropped`` (publisher).
"""
from __future__ import annotations

import asyncio
import json
import logging
import math
from typing import AsyncIterator

import numpy as np

from ..extras import require
from ..messages import NavSolution
from ..nav.earth import C_n_e, dcm_to_euler, ecef_to_geodetic

aiomqtt = require("aiomqtt", "mqtt", "MQTT (telemetry.enabled, corrections.source = 'mqtt')")
log = logging.getLogger(__name__)

# An RTCM frame is at most 1029 bytes; a payload of many frames is fine, a megabyte is not.
MAX_RTCM_PAYLOAD = 65536
MAX_QUEUED_MESSAGES = 1000        # aiomqtt's incoming queue is unbounded by default


def _finite_or_none(x: float):
    return float(x) if math.isfinite(x) else None


def solution_to_json(sol: NavSolution) -> dict:
    """A JSON-ready dict of a solution (degrees and NED at the edge, SI otherwise)."""
    lat, lon, h = ecef_to_geodetic(sol.r_e)
    Cne = C_n_e(lat, lon)
    v_n = Cne.T @ np.asarray(sol.v_e, float)
    roll, pitch, yaw = dcm_to_euler(Cne.T @ np.asarray(sol.C_b_e, float))
    return {
        "t_gps": float(sol.t_gps), "status": sol.status,
        "lat_deg": math.degrees(lat), "lon_deg": math.degrees(lon), "height_m": float(h),
        "v_n_mps": [float(x) for x in v_n],
        "roll_deg": math.degrees(roll), "pitch_deg": math.degrees(pitch), "yaw_deg": math.degrees(yaw) % 360.0,
        "sigma_r_n_m": [float(x) for x in sol.sigma_r_n_m],
        "sigma_v_n_mps": [float(x) for x in sol.sigma_v_n_mps],
        "reset_counter": int(sol.reset_counter),
        "last_gnss_update_t_gps": _finite_or_none(sol.last_gnss_update_t_gps),
        "hpl_m": _finite_or_none(float(sol.extras.get("hpl_m", math.nan))),
        "inject": bool(sol.extras.get("inject")),
        # carrier-phase RTK: 'none' / 'float' / 'fixed', LAMBDA ratio (None unless fixed), DD ambiguities fixed
        "fix_state": sol.fix_state, "fix_ratio": _finite_or_none(float(sol.fix_ratio)),
        "n_fixed": int(sol.n_fixed),
    }


class _Backoff:
    def __init__(self, initial_s: float, max_s: float):
        self.initial_s, self.max_s, self.n = initial_s, max_s, 0

    def next(self) -> float:
        d = min(self.max_s, self.initial_s * 2 ** self.n)
        self.n = min(self.n + 1, 30)
        return d

    def reset(self) -> None:
        self.n = 0


class MqttRtcmSubscriber:
    """``async for payload in sub.stream()`` -> RTCM bytes from ``topic`` (reconnects forever)."""

    def __init__(self, host: str, port: int, topic: str, *, qos: int = 0, identifier: str | None = None,
                 reconnect_initial_s: float = 0.5, reconnect_max_s: float = 10.0):
        self.host, self.port, self.topic, self.qos = host, int(port), topic, qos
        self.identifier = identifier
        self._backoff = _Backoff(reconnect_initial_s, reconnect_max_s)
        self.counters: dict[str, int] = {"connects": 0, "disconnects": 0, "errors": 0, "messages": 0, "bytes": 0,
                                         "dropped_empty": 0, "dropped_oversize": 0}
        self.connected = False
        self.last_error = ""
        self.name = f"mqtt://{host}:{port}/{topic}"
        self._last_drop_log = -math.inf
        self._closed = False

    def close(self) -> None:
        self._closed = True

    def _drop(self, reason: str, n: int) -> None:
        self.counters[reason] += 1
        now = asyncio.get_running_loop().time()
        if now - self._last_drop_log >= 10.0:
            self._last_drop_log = now
            log.warning("MQTT %s: payload dropped (%s, %d bytes; %d so far)", self.name, reason, n,
                        self.counters[reason])

    async def stream(self) -> AsyncIterator[bytes]:
        while not self._closed:
            try:
                async with aiomqtt.Client(self.host, self.port, identifier=self.identifier,
                                          max_queued_incoming_messages=MAX_QUEUED_MESSAGES) as client:
                    await client.subscribe(self.topic, qos=self.qos)
                    self.connected = True
                    self.counters["connects"] += 1
                    self._backoff.reset()
                    log.info("MQTT subscribed to %s", self.name)
                    async for message in client.messages:
                        payload = message.payload
                        if isinstance(payload, str):
                            payload = payload.encode("latin-1")
                        if not isinstance(payload, (bytes, bytearray)) or not payload:
                            self._drop("dropped_empty", 0)
                            continue
                        if len(payload) > MAX_RTCM_PAYLOAD:
                            self._drop("dropped_oversize", len(payload))
                            continue
                        self.counters["messages"] += 1
                        self.counters["bytes"] += len(payload)
                        yield bytes(payload)
            except aiomqtt.MqttError as exc:
                self.counters["errors"] += 1
                self.last_error = str(exc)
                if self.connected:
                    self.counters["disconnects"] += 1
                    log.warning("MQTT %s lost: %s", self.name, exc)
            finally:
                self.connected = False
            if not self._closed:
                await asyncio.sleep(self._backoff.next())

    def __aiter__(self):
        return self.stream()

    def health(self) -> dict:
        return {"name": self.name, "connected": self.connected, "last_error": self.last_error, **self.counters}


class MqttTelemetryPublisher:
    """Publishes the latest solution and health; :meth:`run` keeps the connection (a task).

    ``publish_solution``/``publish_health`` never block: they replace the pending value, which
    :meth:`run` sends when connected (at most ``rate_hz`` solutions per second)."""

    def __init__(self, host: str, port: int, topic_prefix: str = "companion", *, rate_hz: float = 1.0,
                 identifier: str | None = None, reconnect_initial_s: float = 0.5, reconnect_max_s: float = 10.0):
        self.host, self.port = host, int(port)
        self.prefix = topic_prefix.rstrip("/")
        self.solution_topic = f"{self.prefix}/solution"
        self.health_topic = f"{self.prefix}/health"
        self.aid_status_topic = f"{self.prefix}/aid_status"
        self.min_interval_s = 1.0 / rate_hz
        self.identifier = identifier
        self._backoff = _Backoff(reconnect_initial_s, reconnect_max_s)
        self._solution: dict | None = None
        self._health: dict | None = None
        self._aid_status: dict | None = None
        self._event = asyncio.Event()
        self.counters: dict[str, int] = {"connects": 0, "disconnects": 0, "errors": 0, "published": 0,
                                         "replaced": 0}
        self.connected = False
        self.last_error = ""

    def publish_solution(self, sol: NavSolution | dict) -> None:
        if self._solution is not None:
            self.counters["replaced"] += 1
        self._solution = sol if isinstance(sol, dict) else solution_to_json(sol)
        self._event.set()

    def publish_aid_status(self, obj: dict) -> None:
        """The per aid source status (sent with the next solution; a newer one replaces it)."""
        self._aid_status = obj
        self._event.set()

    def publish_health(self, health: dict) -> None:
        self._health = dict(health)
        self._event.set()

    @staticmethod
    async def _watch(client) -> None:
        """Iterating the (empty) message queue is how aiomqtt reports a broker loss while idle."""
        async for _ in client.messages:
            pass
        raise aiomqtt.MqttError("disconnected")

    async def _publish_pending(self, client) -> None:
        if self._health is not None:
            h, self._health = self._health, None
            try:
                await client.publish(self.health_topic, json.dumps(h, default=str), qos=1, retain=True)
            except aiomqtt.MqttError:
                self._health = self._health or h
                raise
            self.counters["published"] += 1
        if self._aid_status is not None:
            a, self._aid_status = self._aid_status, None
            try:
                await client.publish(self.aid_status_topic, json.dumps(a, separators=(",", ":")), qos=0)
            except aiomqtt.MqttError:
                self._aid_status = self._aid_status or a
                raise
            self.counters["published"] += 1
        if self._solution is not None:
            s, self._solution = self._solution, None
            try:
                await client.publish(self.solution_topic, json.dumps(s), qos=0)
            except aiomqtt.MqttError:
                self._solution = self._solution or s
                raise
            self.counters["published"] += 1
            await asyncio.sleep(self.min_interval_s)

    async def run(self) -> None:
        while True:
            watcher = None
            try:
                async with aiomqtt.Client(self.host, self.port, identifier=self.identifier) as client:
                    self.connected = True
                    self.counters["connects"] += 1
                    self._backoff.reset()
                    watcher = asyncio.create_task(self._watch(client))
                    while True:
                        waiter = asyncio.create_task(self._event.wait())
                        done, _ = await asyncio.wait({waiter, watcher}, return_when=asyncio.FIRST_COMPLETED)
                        if watcher in done:
                            waiter.cancel()
                            watcher.result()          # raises the MqttError
                        self._event.clear()
                        await self._publish_pending(client)
            except aiomqtt.MqttError as exc:
                self.counters["errors"] += 1
                self.last_error = str(exc)
                if self.connected:
                    self.counters["disconnects"] += 1
                    log.warning("MQTT telemetry broker %s:%d lost: %s", self.host, self.port, exc)
            finally:
                self.connected = False
                if watcher is not None and not watcher.done():
                    watcher.cancel()
            self._event.set()          # re-send what is pending after reconnecting
            await asyncio.sleep(self._backoff.next())


__all__ = ["MqttRtcmSubscriber", "MqttTelemetryPublisher", "solution_to_json"]
