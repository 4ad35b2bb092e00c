"""PX4 v1.15 (../shared/px4, SIH) has no MAVLink signing: it ignores SETUP_SIGNING, sends unsigned
frames and takes our signed ones.  So a key with ``signing_required = false`` works with it and
``signing_required = true`` cannot (every frame it sends is dropped, counted).  About 20 s."""
from __future__ import annotations

import asyncio
import time

import pytest

import companion.io.mavlink as M
from companion.io.mavlink_signing import LinkSigning, generate_key_file, load_key
from sitl.px4_procs import Px4Sitl, dist_problem, find_dist


async def _run_link(port: int, system_id: int, key_file, required: bool, seconds: float):
    link = M.MavlinkLink(f"udpin:127.0.0.1:{port}", message_rates_hz={"HIGHRES_IMU": 50.0}, target_system=system_id,
                         signing=LinkSigning(load_key(key_file), required=required))
    await link.start()
    try:
        imu = []
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end and not (link.intervals_acknowledged and len(imu) >= 50):
            lm = await link.recv(timeout=0.2)
            if lm is not None and lm.msg.get_type() == "HIGHRES_IMU":
                imu.append(lm.msg)
        return link.health(), imu, link.intervals_acknowledged, link.connected
    finally:
        await link.close()


@pytest.mark.slow
@pytest.mark.parametrize("first_instance", [0, 1])
def test_px4_v1_15_takes_signed_frames_and_sends_unsigned(tmp_path, first_instance):
    """From instance 1 on (system id 2 and up) is what a worker gets while another PX4 test runs:
    CI failed there when the link still targeted system 1 and so never saw PX4's COMMAND_ACK."""
    problem = dist_problem(find_dist())
    if problem:
        pytest.skip(problem)
    px4 = Px4Sitl(find_dist(), {}, tmp_path / "px4", first_instance=first_instance)
    px4.start()
    try:
        port = px4.port("onboard_remote")
        key_file = tmp_path / "mavlink.key"
        assert generate_key_file(key_file)
        from companion.cli import main
        # no signed HEARTBEAT follows SETUP_SIGNING: exit 1
        assert main(["signing", "setup", "--key-file", str(key_file), "--connection",
                     f"udpin:127.0.0.1:{port}", "--target-system", str(px4.system_id), "--timeout", "4"]) == 1
        h, imu, acked, _ = asyncio.run(_run_link(port, px4.system_id, key_file, required=False, seconds=10))
        assert acked, "PX4 acknowledged our signed SET_MESSAGE_INTERVAL"
        assert len(imu) >= 50 and not any(m.get_signed() for m in imu)
        assert h["signing: accepted unsigned"] > 50 and h["signing: good"] == 0
        h, imu, acked, connected = asyncio.run(_run_link(port, px4.system_id, key_file, required=True, seconds=3))
        assert not connected and not imu and not acked
        assert h["signing: rejected unsigned"] > 5 and h["rx_messages"] == 0
    finally:
        px4.stop()
