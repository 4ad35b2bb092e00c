"""The whole service (Service.run) answers a ground station's parameter protocol on its MAVLink
link and serves the status page: real UDP and TCP sockets on 127.0.0.1, real MAVLink 2 bytes from
pymavlink.  The test is the autopilot (system 1, component 1: HEARTBEAT) and, through the same
socket as an autopilot routes it, the ground station (system 255)."""
from __future__ import annotations

import asyncio
import json
import socket
import urllib.request

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.config import load_config
from companion.io.mavlink_codec import parse_bytes
from companion.io.mavlink_params import PARAMETERS
from companion.service import Service

AP = mav.MAVLink(None, srcSystem=1, srcComponent=1)
GCS = mav.MAVLink(None, srcSystem=255, srcComponent=190)


def _free_port(kind=socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _fetch(url: str) -> bytes:
    return urllib.request.urlopen(url, timeout=5).read()


def test_parameters_and_status_page_through_the_running_service(tmp_path, monkeypatch):
    port, http_port = _free_port(), _free_port(socket.SOCK_STREAM)
    path = tmp_path / "companion.toml"
    path.write_text(f'[mavlink]\nconnection = "udpin:127.0.0.1:{port}"\ntimesync_interval_s = 0\n'
                    f'[gnss]\nsource = "none"\nlever_arm_b_m = [0.1, 0.0, -0.2]\n'
                    f'[log]\ndir = "{tmp_path / "log"}"\n[status_page]\nport = {http_port}\n')
    path.chmod(0o600)
    cfg = load_config(path)

    async def main():
        svc = Service(cfg, install_signal_handlers=False)
        task = asyncio.create_task(svc.run())
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setblocking(False)
        loop = asyncio.get_running_loop()
        got: list = []

        def send(enc, msg):
            sock.sendto(bytes(msg.pack(enc)), ("127.0.0.1", port))

        async def pump(seconds: float):
            end = loop.time() + seconds
            while loop.time() < end:
                try:
                    data = sock.recv(65536)
                    got.extend(m for m in parse_bytes(data) if m.get_type() != "BAD_DATA")
                except BlockingIOError:
                    await asyncio.sleep(0.01)

        def of(kind):
            return [m for m in got if m.get_type() == kind]

        try:
            for _ in range(20):                  # the autopilot appears, the service links up
                send(AP, AP.heartbeat_encode(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 3))
                await pump(0.1)
                if svc.link is not None and svc.link.connected:
                    break
            assert svc.link is not None and svc.link.connected
            send(GCS, GCS.param_request_list_encode(1, 191))
            await pump(1.0)
            values = {m.param_id: m for m in of("PARAM_VALUE")}
            assert set(values) == {p.param_id for p in PARAMETERS}
            assert values["CC_LEVER_Z"].param_value == pytest.approx(-0.2, abs=1e-7)
            got.clear()
            send(GCS, GCS.param_set_encode(1, 191, b"CC_LEVER_X", 0.25, mav.MAV_PARAM_TYPE_REAL32))
            await pump(0.5)
            assert [m.param_value for m in of("PARAM_VALUE") if m.param_id == "CC_LEVER_X"] == [pytest.approx(0.25)]
            assert svc.pipeline.engine.lever_arm_b[0] == 0.25 and svc.pipeline.lever_b[0] == 0.25
            assert load_config(path).gnss.lever_arm_b_m == (0.25, 0.0, -0.2)
            assert (path.stat().st_mode & 0o777) == 0o600            # still private
            got.clear()
            send(GCS, GCS.param_set_encode(1, 191, b"CC_MAX_HPL", -3.0, mav.MAV_PARAM_TYPE_REAL32))
            await pump(0.5)
            assert [m.param_value for m in of("PARAM_VALUE")] == [5.0]
            assert any("CC_MAX_HPL refused" in m.text for m in of("STATUSTEXT"))
            # the status page of the same service
            base = f"http://127.0.0.1:{http_port}"
            page, st = await asyncio.gather(asyncio.to_thread(_fetch, base + "/"),
                                            asyncio.to_thread(_fetch, base + "/status.json"))
            assert b"companion status" in page
            assert json.loads(st)["v"] == 1
        finally:
            svc.stop()
            await asyncio.wait_for(task, 10)
            sock.close()
        assert svc.status_server is None                            # closed at shutdown

    asyncio.run(asyncio.wait_for(main(), 60))
    # the field log holds the change: a replay applies it at the same record
    from companion.pipeline import NavPipeline
    from companion.replay import replay_field_log
    applied = []
    original = NavPipeline.apply_settings
    monkeypatch.setattr(NavPipeline, "apply_settings",
                        lambda self, c: (applied.append(c.gnss.lever_arm_b_m), original(self, c)))
    res = replay_field_log(tmp_path / "log")
    assert res.config_from == "field log" and applied == [(0.25, 0.0, -0.2)]


def test_a_port_in_use_does_not_stop_the_service(tmp_path):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        path = tmp_path / "c.toml"
        path.write_text(f'[mavlink]\nconnection = "udpin:127.0.0.1:{_free_port()}"\n[gnss]\nsource = "none"\n'
                        f'[log]\nenabled = false\n[status_page]\nport = {busy.getsockname()[1]}\n')

        async def main():
            svc = Service(load_config(path), install_signal_handlers=False)
            task = asyncio.create_task(svc.run())
            await asyncio.sleep(1.5)
            assert not task.done() and svc.status_server is None
            assert svc.counters["status page not started"] == 1
            svc.stop()
            await asyncio.wait_for(task, 10)

        asyncio.run(asyncio.wait_for(main(), 30))
