"""LEGACY IMU packets (48 bytes): three u64 time stamps (ns), acceleration (g) and angular
velocity (deg/s) as float32 x, y, z."""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from protocols.ouster._errors import PacketSizeError, PacketValueError

__all__ = ["IMU_PACKET_BYTES", "ImuPacket", "decode_imu_packet", "encode_imu_packet"]

_IMU = struct.Struct("<QQQ6f")
IMU_PACKET_BYTES = _IMU.size


@dataclass(frozen=True, slots=True)
class ImuPacket:
    sys_ts_ns: int
    accel_ts_ns: int
    gyro_ts_ns: int
    accel_g: tuple[float, float, float]
    gyro_deg_s: tuple[float, float, float]

    def __post_init__(self) -> None:
        for name in ("sys_ts_ns", "accel_ts_ns", "gyro_ts_ns"):
            v = getattr(self, name)
            if not 0 <= v < 1 << 64:
                raise ValueError(f"{name} = {v}; expected 0 .. 2**64 - 1")
        for name in ("accel_g", "gyro_deg_s"):
            v = getattr(self, name)
            if len(v) != 3 or not all(math.isfinite(x) for x in v):
                raise ValueError(f"{name} = {v!r}; expected three finite numbers")


def encode_imu_packet(pkt: ImuPacket) -> bytes:
    return _IMU.pack(pkt.sys_ts_ns, pkt.accel_ts_ns, pkt.gyro_ts_ns, *pkt.accel_g,
                     *pkt.gyro_deg_s)


def decode_imu_packet(buf: bytes | bytearray | memoryview) -> ImuPacket:
    if len(buf) != IMU_PACKET_BYTES:
        raise PacketSizeError(f"IMU packet of {len(buf)} bytes; LEGACY IMU packets are "
                              f"{IMU_PACKET_BYTES} bytes")
    s, a, g, ax, ay, az, gx, gy, gz = _IMU.unpack(bytes(buf))
    for name, v in (("accel_g", (ax, ay, az)), ("gyro_deg_s", (gx, gy, gz))):
        if not all(math.isfinite(x) for x in v):
            raise PacketValueError(f"IMU {name} = {v!r}; expected three finite float32 values")
    return ImuPacket(s, a, g, (ax, ay, az), (gx, gy, gz))
