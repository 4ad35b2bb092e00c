"""MAVLink 2 signing against the real ArduCopter SITL (../shared/ardupilot): ``companion signing
setup`` gives it our key over SERIAL1, it signs from then on, our signed link gets its streams and
acknowledgements, and an unsigned or wrongly signed peer on SERIAL2 is ignored.  About 20 s."""
from __future__ import annotations

import asyncio
import os
import time

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

import companion.io.mavlink as M  # noqa: E402
from companion.io import mavlink_codec
from companion.io.mavlink_signing import LinkSigning, generate_key_file, load_key  # noqa: E402
from sitl.ardupilot_procs import ArduCopterSitl, binary_problem, find_binary  # noqa: E402

mav = mavlink_codec.mavlink2


def _acked(conn, command: int, signing_key: bytes | None, timeout_s: float = 3.0) -> bool:
    """Send COMMAND_LONG ``command`` (a harmless REQUEST_MESSAGE) and wait for its COMMAND_ACK."""
    if signing_key is not None:
        conn.setup_signing(signing_key, sign_outgoing=True, allow_unsigned_callback=lambda *_: True, link_id=3)
    t_end = time.monotonic() + timeout_s
    next_send = 0.0
    while time.monotonic() < t_end:
        if time.monotonic() >= next_send:
            conn.mav.command_long_send(1, 1, command, 0, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0)
            next_send = time.monotonic() + 0.5
        m = conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.1)
        if m is not None and m.command == command:
            return True
    return False


@pytest.mark.slow
def test_arducopter_takes_our_key_and_answers_only_signed_traffic(tmp_path):
    problem = binary_problem(find_binary())
    if problem:
        pytest.skip(problem)
    sitl = ArduCopterSitl(find_binary(), [], tmp_path / "sitl")
    sitl.start()
    gcs = other = None
    try:
        # SITL starts once SERIAL0 has a client; channel 0 accepts anything once signing is on
        gcs = mavutil.mavlink_connection(f"tcp:127.0.0.1:{sitl.port(0)}", source_system=255)
        assert gcs.wait_heartbeat(timeout=20) is not None
        other = mavutil.mavlink_connection(f"tcp:127.0.0.1:{sitl.port(2)}", source_system=250,
                                           source_component=190)
        assert other.wait_heartbeat(timeout=10) is not None
        assert _acked(other, mav.MAV_CMD_REQUEST_MESSAGE, None), "unsigned commands work before the key"

        key_file = tmp_path / "mavlink.key"
        assert generate_key_file(key_file)
        from companion.cli import main
        assert main(["signing", "setup", "--key-file", str(key_file), "--connection",
                     f"tcp:127.0.0.1:{sitl.port(1)}", "--timeout", "10"]) == 0

        async def signed_link():
            link = M.MavlinkLink(f"tcp:127.0.0.1:{sitl.port(1)}", message_rates_hz={"HIGHRES_IMU": 50.0},
                                 signing=LinkSigning(load_key(key_file), required=True))
            await link.start()
            try:
                imu = []
                t_end = time.monotonic() + 10
                while time.monotonic() < t_end and not (link.intervals_acknowledged and len(imu) >= 50):
                    lm = await link.recv(timeout=0.2)
                    if lm is not None and lm.msg.get_type() == "HIGHRES_IMU":
                        imu.append(lm.msg)
                return link.health(), imu, link.intervals_acknowledged
            finally:
                await link.close()

        h, imu, acked = asyncio.run(signed_link())
        assert acked, "ArduPilot acknowledged our signed SET_MESSAGE_INTERVAL"
        assert len(imu) >= 50 and all(m.get_signed() for m in imu), "its IMU stream arrives, signed"
        assert h["signing: good"] > 50 and h["signing: rejected unsigned"] == 0
        assert h["signing: bad signature"] == 0 and h["signing: replayed"] == 0

        # the unsigned peer on SERIAL2 now gets nothing done; a wrong key neither
        assert not _acked(other, mav.MAV_CMD_REQUEST_MESSAGE, None)
        assert not _acked(other, mav.MAV_CMD_REQUEST_MESSAGE, bytes(range(32)))
        # ... and sees ArduPilot's frames carry a signature (incompat flag 0x01; not ours to verify)
        hb = other.recv_match(type="HEARTBEAT", blocking=True, timeout=3)
        assert hb is not None and hb.get_msgbuf()[2] & 0x01 and not hb.get_signed()
    finally:
        for c in (gcs, other):
            if c is not None:
                c.close()
        sitl.stop()
