"""`sensor_msgs/msg/LaserScan` in CDR: `decode_laser_scan` and `encode_laser_scan`.

Layout (ROS 2 message definition order): `std_msgs/Header header` (`builtin_interfaces/Time stamp`:
int32 sec, uint32 nanosec; string frame_id), float32 angle_min, angle_max, angle_increment,
time_increment, scan_time, range_min, range_max, float32[] ranges, float32[] intensities.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from fleetmap.ros.cdr import CdrError, CdrReader, CdrWriter

ROS_TYPE = "sensor_msgs/msg/LaserScan"


@dataclass(frozen=True, eq=False)
class LaserScanMsg:
    """The fields of a LaserScan fleetmap uses (intensities are read past, not kept)."""

    sec: int
    nanosec: int
    frame_id: str
    angle_min: float
    angle_max: float
    angle_increment: float
    time_increment: float
    scan_time: float
    range_min: float
    range_max: float
    ranges: npt.NDArray[np.float32]

    @property
    def stamp(self) -> float:
        """The header stamp in seconds."""
        return self.sec + self.nanosec * 1e-9


def decode_laser_scan(payload: bytes) -> LaserScanMsg:
    """Decode a whole LaserScan payload; raises `CdrError` if it is not exactly one."""
    r = CdrReader(payload)
    sec, nanosec = r.int32(), r.uint32()
    frame_id = r.string()
    a_min, a_max, a_inc, t_inc, scan_time, r_min, r_max = (r.float32() for _ in range(7))
    ranges = r.sequence_float32()
    r.sequence_float32()  # intensities: length-checked, not kept
    if r.remaining > 3:  # a writer may pad the end to 4 bytes; more is not a LaserScan
        raise CdrError(f"{r.remaining} bytes after the end of a LaserScan")
    return LaserScanMsg(sec, nanosec, frame_id, a_min, a_max, a_inc, t_inc, scan_time, r_min, r_max, ranges)


def encode_laser_scan(msg: LaserScanMsg, intensities: npt.ArrayLike = ()) -> bytes:
    """A LaserScan payload (little-endian CDR) of `msg`."""
    w = CdrWriter()
    w.write_int32(msg.sec)
    w.write_uint32(msg.nanosec)
    w.write_string(msg.frame_id)
    for value in (
        msg.angle_min, msg.angle_max, msg.angle_increment, msg.time_increment, msg.scan_time,
        msg.range_min, msg.range_max,
    ):  # fmt: skip
        w.write_float32(value)
    w.write_sequence_float32(msg.ranges)
    w.write_sequence_float32(np.asarray(intensities, dtype=np.float32))
    return w.getvalue()


__all__ = ["ROS_TYPE", "LaserScanMsg", "decode_laser_scan", "encode_laser_scan"]
