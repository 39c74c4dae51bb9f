"""Ouster OS0-64 wire formats (sans-IO): lidar packet profiles, LEGACY IMU packets, the
CRC-64/XZ footer, metadata JSON and the SDK's ray model. Checked against ouster-sdk 1.0.1."""

from protocols.ouster._crc import crc64_xz, crc64_xz_rows
from protocols.ouster._errors import (
    CrcError,
    MeasurementIdError,
    MetadataError,
    PacketIdError,
    PacketSizeError,
    PacketTypeError,
    PacketValueError,
    ProtocolError,
)
from protocols.ouster._imu import IMU_PACKET_BYTES, ImuPacket, decode_imu_packet, encode_imu_packet
from protocols.ouster._metadata import (
    MODES,
    OS0_64_MODES,
    SensorMetadata,
    beam_rays,
    os0_64_metadata,
    parse_mode,
    xyz_from_range,
)
from protocols.ouster._packets import (
    DecodedFrame,
    LidarPacket,
    PacketBatch,
    PacketFormat,
    decode_lidar_packet,
    decode_lidar_packets,
    encode_lidar_columns,
    encode_lidar_frame,
    encode_pixel_fields,
    finish_lidar_packets,
    frame_from_packets,
    shift_lidar_packet,
)
from protocols.ouster._profiles import PROFILES, Field, Profile

__all__ = [
    "IMU_PACKET_BYTES",
    "MODES",
    "OS0_64_MODES",
    "PROFILES",
    "CrcError",
    "DecodedFrame",
    "Field",
    "ImuPacket",
    "LidarPacket",
    "MeasurementIdError",
    "MetadataError",
    "PacketBatch",
    "PacketFormat",
    "PacketIdError",
    "PacketSizeError",
    "PacketTypeError",
    "PacketValueError",
    "Profile",
    "ProtocolError",
    "SensorMetadata",
    "beam_rays",
    "crc64_xz",
    "crc64_xz_rows",
    "decode_imu_packet",
    "decode_lidar_packet",
    "decode_lidar_packets",
    "encode_imu_packet",
    "encode_lidar_columns",
    "encode_lidar_frame",
    "encode_pixel_fields",
    "finish_lidar_packets",
    "frame_from_packets",
    "os0_64_metadata",
    "parse_mode",
    "shift_lidar_packet",
    "xyz_from_range",
]
