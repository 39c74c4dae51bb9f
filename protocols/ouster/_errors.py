"""Errors of the Ouster codecs. Every message says what was expected and what arrived.

::

    ProtocolError (ValueError)          never raised itself
     ├── PacketSizeError                a buffer of the wrong length
     ├── PacketTypeError                packet_type is not lidar (1)
     ├── CrcError                       the CRC-64/XZ footer does not match
     ├── PacketIdError                  init_id / prod_sn differ from the metadata
     ├── MeasurementIdError             a column's measurement_id is not below the frame width
     ├── PacketValueError               a field holds what no sensor sends (a NaN IMU reading)
     └── MetadataError                  a metadata document is missing or has a bad field
"""

from __future__ import annotations


class ProtocolError(ValueError):
    """Base of the Ouster codec errors; raise a subclass."""

    def __init__(self, message: str) -> None:
        if type(self) is ProtocolError:
            raise TypeError("raise a ProtocolError subclass, not ProtocolError itself")
        super().__init__(message)


class PacketSizeError(ProtocolError):
    pass


class PacketTypeError(ProtocolError):
    pass


class CrcError(ProtocolError):
    pass


class PacketIdError(ProtocolError):
    pass


class MeasurementIdError(ProtocolError):
    pass


class PacketValueError(ProtocolError):
    pass


class MetadataError(ProtocolError):
    pass
