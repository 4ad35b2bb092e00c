"""MQTT with a real mosquitto broker on a free loopback port (started by the test): RTCM
subscriber and telemetry publisher, including a broker restart."""
from __future__ import annotations

import asyncio
import json
import math
import shutil
import socket
import subprocess
import time
from pathlib import Path

import aiomqtt
import numpy as np
import pytest

from companion.io.corrections import CorrectionPipeline
from companion.io.mqtt import MqttRtcmSubscriber, MqttTelemetryPublisher, solution_to_json
from companion.messages import BaseStationPosition, GnssEpoch, NavSolution
from companion.nav.earth import C_n_e, euler_to_dcm, geodetic_to_ecef
from tests._data import data_path

RTCM_FILE = data_path("qzsl6tool-hiroshima-rtcm3-ubx/20221213-010900.rtcm")
MOSQUITTO = shutil.which("mosquitto") or ("/usr/sbin/mosquitto" if Path("/usr/sbin/mosquitto").exists() else None)
needs_mosquitto = pytest.mark.skipif(MOSQUITTO is None, reason="mosquitto not installed: no real MQTT broker")


def free_tcp_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    p = s.getsockname()[1]
    s.close()
    return p


class Broker:
    def __init__(self, tmp_path: Path):
        self.port = free_tcp_port()
        self.conf = tmp_path / "mosquitto.conf"
        self.conf.write_text(f"listener {self.port} 127.0.0.1\nallow_anonymous true\npersistence false\n")
        self.proc = None

    def start(self):
        self.proc = subprocess.Popen([MOSQUITTO, "-c", str(self.conf)], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.2).close()
                return
            except OSError:
                time.sleep(0.05)
        raise RuntimeError("mosquitto did not start")

    def stop(self):
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait(timeout=5)
            self.proc = None


@pytest.fixture
def broker(tmp_path):
    b = Broker(tmp_path)
    b.start()
    yield b
    b.stop()


async def _wait(pred, timeout=5.0):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if pred():
            return True
        await asyncio.sleep(0.02)
    return pred()


def _solution():
    lat, lon = math.radians(34.4), math.radians(132.4)
    Cne = C_n_e(lat, lon)
    return NavSolution(t_gps=1.4e9, r_e=geodetic_to_ecef(lat, lon, 50.0), v_e=Cne @ np.array([1.0, 2.0, 0.5]),
                       C_b_e=Cne @ euler_to_dcm(0.0, 0.0, math.radians(45)), sigma_r_n_m=np.array([0.1, 0.1, 0.2]),
                       sigma_v_n_mps=np.array([0.02, 0.02, 0.03]), sigma_att_rad=np.array([0.01, 0.01, 0.02]),
                       status="nav", reset_counter=2)


def test_solution_json_is_plain_and_in_degrees():
    d = solution_to_json(_solution())
    json.dumps(d)
    assert d["lat_deg"] == pytest.approx(34.4) and d["height_m"] == pytest.approx(50.0, abs=1e-6)
    assert d["yaw_deg"] == pytest.approx(45.0) and d["v_n_mps"] == pytest.approx([1.0, 2.0, 0.5])
    assert d["last_gnss_update_t_gps"] is None and d["status"] == "nav"
    assert d["hpl_m"] is None and d["inject"] is False          # no protection level in this solution


@needs_mosquitto
def test_rtcm_subscriber_feeds_pipeline_and_survives_broker_restart(broker):
    data = RTCM_FILE.read_bytes()[:60000]

    async def main():
        sub = MqttRtcmSubscriber("127.0.0.1", broker.port, "rtcm/base", reconnect_initial_s=0.1,
                                 reconnect_max_s=0.3)
        frames_forwarded = []
        pipe = CorrectionPipeline(sub, week_hint=2240, forward=frames_forwarded.append)
        msgs = []

        async def consume():
            async for batch in pipe.stream():
                msgs.extend(batch.messages)
        task = asyncio.create_task(consume())
        assert await _wait(lambda: sub.connected)

        async def publish(chunk_bytes):
            async with aiomqtt.Client("127.0.0.1", broker.port) as pub:
                for i in range(0, len(chunk_bytes), 1000):
                    await pub.publish("rtcm/base", chunk_bytes[i:i + 1000], qos=1)

        await publish(data[:30000])
        assert await _wait(lambda: sub.counters["bytes"] == 30000)
        await asyncio.to_thread(broker.stop)
        assert await _wait(lambda: not sub.connected)
        await asyncio.to_thread(broker.start)
        assert await _wait(lambda: sub.connected and sub.counters["connects"] == 2, timeout=8)
        await publish(data[30000:])
        assert await _wait(lambda: sub.counters["bytes"] == len(data))
        await asyncio.sleep(0.1)
        task.cancel()
        try:
            await task
        except asyncio.CancelledError:
            pass
        return sub, pipe, msgs, frames_forwarded

    sub, pipe, msgs, fwd = asyncio.run(asyncio.wait_for(main(), 25))
    assert sub.counters["disconnects"] == 1 and sub.counters["errors"] >= 1
    assert any(isinstance(m, BaseStationPosition) for m in msgs)
    assert sum(isinstance(m, GnssEpoch) and m.source == "base" for m in msgs) >= 5
    assert len(fwd) == pipe.counters["frames"] > 50 and pipe.decoder.counters.get("bad_crc", 0) == 0


@needs_mosquitto
def test_telemetry_publisher_topics_and_reconnect(broker):
    async def main():
        pub = MqttTelemetryPublisher("127.0.0.1", broker.port, "uav7", rate_hz=20, reconnect_initial_s=0.1,
                                     reconnect_max_s=0.3)
        runner = asyncio.create_task(pub.run())
        got: dict[str, list] = {"uav7/solution": [], "uav7/health": [], "uav7/aid_status": []}

        async def listen():
            while True:
                try:
                    async with aiomqtt.Client("127.0.0.1", broker.port) as c:
                        await c.subscribe("uav7/#")
                        async for m in c.messages:
                            got[str(m.topic)].append(json.loads(m.payload))
                except aiomqtt.MqttError:
                    await asyncio.sleep(0.1)
        listener = asyncio.create_task(listen())
        assert await _wait(lambda: pub.connected)
        await asyncio.sleep(0.3)
        pub.publish_health({"link": "up", "imu_samples": 10})
        pub.publish_aid_status({"v": 1, "hpl_m": 1.5, "sources": {}})
        pub.publish_solution(_solution())
        assert await _wait(lambda: got["uav7/solution"] and got["uav7/health"] and got["uav7/aid_status"])
        await asyncio.to_thread(broker.stop)
        assert await _wait(lambda: not pub.connected)
        pub.publish_health({"link": "up", "imu_samples": 20})     # pending while the broker is down
        await asyncio.to_thread(broker.start)
        assert await _wait(lambda: pub.connected and pub.counters["connects"] == 2, timeout=8)
        # retained health reaches a subscriber that connects afterwards
        async with aiomqtt.Client("127.0.0.1", broker.port) as late:
            await late.subscribe("uav7/health")
            async for m in late.messages:
                health = json.loads(m.payload)
                assert m.retain
                break
        listener.cancel()
        runner.cancel()
        for t in (listener, runner):
            try:
                await t
            except asyncio.CancelledError:
                pass
        return got, health, pub

    got, health, pub = asyncio.run(asyncio.wait_for(main(), 25))
    assert got["uav7/solution"][0]["lat_deg"] == pytest.approx(34.4)
    assert got["uav7/health"][0] == {"link": "up", "imu_samples": 10}
    assert got["uav7/aid_status"][0] == {"v": 1, "hpl_m": 1.5, "sources": {}}
    assert health == {"link": "up", "imu_samples": 20}
    assert pub.counters["disconnects"] == 1
