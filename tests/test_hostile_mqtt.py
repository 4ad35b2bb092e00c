"""MQTT RTCM subscriber against a real mosquitto: oversize and empty payloads are dropped and counted."""
from __future__ import annotations

import asyncio

import aiomqtt

from companion.io.mqtt import MAX_RTCM_PAYLOAD, MqttRtcmSubscriber
from tests.test_mqtt import _wait, broker, needs_mosquitto  # noqa: F401 - the fixture


@needs_mosquitto
def test_oversize_and_empty_payloads_are_dropped_and_counted(broker):  # noqa: F811
    async def main():
        sub = MqttRtcmSubscriber("127.0.0.1", broker.port, "rtcm/base", reconnect_initial_s=0.1)
        got = []

        async def consume():
            async for data in sub.stream():
                got.append(data)
        task = asyncio.create_task(consume())
        assert await _wait(lambda: sub.connected)
        async with aiomqtt.Client("127.0.0.1", broker.port) as pub:
            await pub.publish("rtcm/base", b"\xd3" * (MAX_RTCM_PAYLOAD + 1), qos=1)
            await pub.publish("rtcm/base", b"", qos=1)
            await pub.publish("rtcm/base", b"\xd3\x00\x13", qos=1)
        assert await _wait(lambda: sub.counters["messages"] == 1)
        sub.close()
        task.cancel()
        return got, sub.counters
    got, c = asyncio.run(main())
    assert got == [b"\xd3\x00\x13"]
    assert c["dropped_oversize"] == 1 and c["dropped_empty"] == 1
