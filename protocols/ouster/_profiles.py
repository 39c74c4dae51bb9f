"""Packet layouts as tables (ouster-sdk 1.0.1, ``ouster_core/src/parsing.cpp``; see
shared/research/ouster-wire.md §2). All little-endian.

A pixel field is read as ``value = (word & mask) >> shift`` (``<< -shift`` when shift is
negative) from the word of ``dtype`` starting ``offset`` bytes into the pixel; writing is the
inverse. Sizes of packets and columns are derived from these tables, never hard-coded.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["PROFILES", "Field", "Profile"]


@dataclass(frozen=True, slots=True)
class Field:
    name: str
    offset: int  # byte offset of the word inside the pixel
    dtype: str  # numpy dtype of the word, little-endian
    mask: int  # bits of the word that hold the field
    shift: int  # value = (word & mask) >> shift; negative: << -shift

    @property
    def bits(self) -> int:
        """Width of the decoded value in bits."""
        width = self.mask.bit_length() - (self.mask & -self.mask).bit_length() + 1
        return width - self.shift if self.shift < 0 else width


@dataclass(frozen=True, slots=True)
class Profile:
    name: str
    legacy: bool
    header_bytes: int  # packet header
    col_header_bytes: int
    pixel_bytes: int
    col_footer_bytes: int
    footer_bytes: int  # packet footer (the last 8 bytes hold the CRC when not legacy)
    fields: tuple[Field, ...]

    def col_bytes(self, pixels: int) -> int:
        return self.col_header_bytes + pixels * self.pixel_bytes + self.col_footer_bytes

    def packet_bytes(self, pixels: int, columns_per_packet: int) -> int:
        return self.header_bytes + columns_per_packet * self.col_bytes(pixels) + self.footer_bytes

    def field(self, name: str) -> Field:
        for f in self.fields:
            if f.name == name:
                return f
        raise KeyError(f"profile {self.name} has no field {name!r}; it has "
                       f"{', '.join(f.name for f in self.fields)}")


PROFILES: dict[str, Profile] = {p.name: p for p in (
    Profile("LEGACY", True, 0, 16, 12, 4, 0, (
        Field("RANGE", 0, "<u4", 0x000FFFFF, 0),
        Field("FLAGS", 0, "<u4", 0xF0000000, 28),
        Field("REFLECTIVITY", 4, "<u1", 0xFF, 0),
        Field("SIGNAL", 6, "<u2", 0xFFFF, 0),
        Field("NEAR_IR", 8, "<u2", 0xFFFF, 0),
    )),
    Profile("RNG19_RFL8_SIG16_NIR16", False, 32, 12, 12, 0, 32, (
        Field("RANGE", 0, "<u4", 0x0007FFFF, 0),
        Field("FLAGS", 0, "<u4", 0x00F80000, 19),
        Field("REFLECTIVITY", 4, "<u1", 0xFF, 0),
        Field("SIGNAL", 6, "<u2", 0xFFFF, 0),
        Field("NEAR_IR", 8, "<u2", 0xFFFF, 0),
        Field("WINDOW", 11, "<u1", 0xFF, 0),
    )),
    Profile("RNG19_RFL8_SIG16_NIR16_DUAL", False, 32, 12, 16, 0, 32, (
        Field("RANGE", 0, "<u4", 0x0007FFFF, 0),
        Field("FLAGS", 0, "<u4", 0x00F80000, 19),
        Field("REFLECTIVITY", 0, "<u4", 0xFF000000, 24),
        Field("RANGE2", 4, "<u4", 0x0007FFFF, 0),
        Field("FLAGS2", 4, "<u4", 0x00F80000, 19),
        Field("REFLECTIVITY2", 4, "<u4", 0xFF000000, 24),
        Field("SIGNAL", 8, "<u2", 0xFFFF, 0),
        Field("SIGNAL2", 10, "<u2", 0xFFFF, 0),
        Field("NEAR_IR", 12, "<u2", 0xFFFF, 0),
        Field("WINDOW", 15, "<u1", 0xFF, 0),
    )),
    Profile("RNG15_RFL8_NIR8", False, 32, 12, 4, 0, 32, (
        Field("RANGE", 0, "<u2", 0x7FFF, -3),
        Field("FLAGS", 0, "<u2", 0x8000, 15),
        Field("REFLECTIVITY", 2, "<u1", 0xFF, 0),
        Field("NEAR_IR", 3, "<u1", 0xFF, -4),
    )),
)}
