"""MAVLink bytes for the shell: the pymavlink dialect (MAVLink 2, ardupilotmega), our component's
identity, and deterministic packing and parsing of single messages (field-log records and tests).

MAVLINK20 is set before pymavlink is imported: ODOMETRY (331) and GPS_INPUT need MAVLink 2."""
from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink2  # noqa: E402

m = mavlink2
MAV_COMP_ID_ONBOARD_COMPUTER = m.MAV_COMP_ID_ONBOARD_COMPUTER      # 191
SERIAL_CONTROL_DEV_GPS1 = m.SERIAL_CONTROL_DEV_GPS1
SERIAL_CONTROL_DEV_GPS2 = m.SERIAL_CONTROL_DEV_GPS2
SERIAL_CONTROL_DATA_LEN = 70


def _encoder(src_system: int = 1, src_component: int = MAV_COMP_ID_ONBOARD_COMPUTER):
    return mavlink2.MAVLink(None, srcSystem=src_system, srcComponent=src_component)


ENCODER = _encoder()


def pack(msg, src_system: int = 1, src_component: int = MAV_COMP_ID_ONBOARD_COMPUTER, seq: int = 0) -> bytes:
    """Serialise a message object to MAVLink 2 bytes (deterministic: explicit ids and sequence)."""
    mav = _encoder(src_system, src_component)
    mav.seq = seq & 0xFF
    return bytes(msg.pack(mav))


def parse_bytes(data: bytes) -> list:
    """Parse MAVLink bytes back into message objects (bad data is returned as BAD_DATA messages)."""
    mav = mavlink2.MAVLink(None)
    mav.robust_parsing = True
    return mav.parse_buffer(bytes(data)) or []



__all__ = ["mavlink2", "m", "pack", "parse_bytes", "MAV_COMP_ID_ONBOARD_COMPUTER", "SERIAL_CONTROL_DEV_GPS1",
           "SERIAL_CONTROL_DEV_GPS2", "SERIAL_CONTROL_DATA_LEN"]
