"""Names of the MAVLink IMU streams the companion can fuse: plain data, so the configuration can
validate ``mavlink.imu_message`` and ``mavlink.imu_cluster`` without importing pymavlink or numpy
(``companion config check`` answers in a fraction of a second).  :mod:`companion.io.mavlink_decode` and :mod:`companion.io.mavlink` use them.
"""
from __future__ import annotations

IMU_MESSAGES = ("HIGHRES_IMU", "RAW_IMU", "SCALED_IMU2", "SCALED_IMU3")   # 'auto' picks among these
# IMU streams an IMU cluster can name: these, PX4's SCALED_IMU, and HIGHRES_IMU of one unit ("HIGHRES_IMU:1")
IMU_CLUSTER_STREAMS = IMU_MESSAGES + ("SCALED_IMU",) + tuple(f"HIGHRES_IMU:{i}" for i in range(8))

__all__ = ["IMU_MESSAGES", "IMU_CLUSTER_STREAMS"]
