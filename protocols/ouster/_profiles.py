"""Packet layouts as tables (ouster-sdk 1.0.1, ``ouster_core/src/parsing.cpp``; every profile
the SDK knows, with the bit maps in ``ouster-sdk-1.0.1-layouts.md`` beside this file, and
shared/research/ouster-wire.md §2). All little-endian.

A field is read as ``value = (word & mask) >> shift`` (``<< -shift`` when shift is negative)
from the word of ``dtype`` starting ``offset`` bytes into its block (a pixel, a column
header, a packet header); writing is the inverse. Pixel fields of the profiles added for
replay (:func:`_px`) sit in the aligned 32-bit word that holds them, so that fields sharing
a word are combined, never overwritten; the SDK reads the same bits (its ``field_info``
rule: value = ((pixel >> bit_start) & (2**bits - 1)) << upshift). Header fields follow the
SDK's own rule (:func:`_hdr`). Sizes of packets and columns are derived from these tables,
never hard-coded.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["EMULATED_PROFILES", "HEADERS", "PROFILES", "Field", "Header", "Profile"]


@dataclass(frozen=True, slots=True)
class Field:
    name: str
    offset: int  # byte offset of the word inside its block (pixel, column, packet header)
    dtype: str  # numpy dtype of the word, little-endian
    mask: int  # bits of the word that hold the field
    shift: int  # value = (word & mask) >> shift; negative: << -shift

    @property
    def bits(self) -> int:
        """Width of the decoded value in bits."""
        width = self.mask.bit_length() - (self.mask & -self.mask).bit_length() + 1
        return width + self.upshift

    @property
    def bit_start(self) -> int:
        """The first bit of the field in its block (bit 0: the block's first byte's lowest)."""
        return 8 * self.offset + (self.mask & -self.mask).bit_length() - 1

    @property
    def upshift(self) -> int:
        """How far the carried bits are shifted up into the value (RNG15's range: 3)."""
        return (self.mask & -self.mask).bit_length() - 1 - self.shift


def _px(name: str, bit_start: int, bits: int, upshift: int = 0) -> Field:
    """A pixel field as the SDK's ``field_info(bit_start, bits, upshift)``, placed in the
    aligned 32-bit word that holds it (every field of every profile fits in one)."""
    b = bit_start % 32
    if b + bits > 32:
        raise ValueError(f"{name}: bits {bit_start}..{bit_start + bits - 1} cross a 32-bit word")
    return Field(name, bit_start // 32 * 4, "<u4", ((1 << bits) - 1) << b, b - upshift)


def _hdr(name: str, bit_start: int, bits: int) -> Field:
    """A header field as the SDK's ``field_info(bit_start, bits)``: the smallest word from
    the field's first byte that holds it."""
    b = bit_start % 8
    size = next(s for s in (1, 2, 4, 8) if b + bits <= 8 * s)
    return Field(name, bit_start // 8, f"<u{size}", ((1 << bits) - 1) << b, b)


@dataclass(frozen=True, slots=True)
class Header:
    """Where a packet's and its columns' identity lies: the packet header's fields (from the
    packet's first byte), the column header's (from the column's) and the column footer's
    (from the footer's first byte); whether the packet footer's last 8 bytes are a CRC."""

    name: str
    packet: tuple[Field, ...]
    column: tuple[Field, ...]
    column_footer: tuple[Field, ...]
    crc: bool

    def field(self, name: str) -> Field | None:
        for f in self.packet + self.column + self.column_footer:
            if f.name == name:
                return f
        return None


_STATUS = (_hdr("countdown_thermal_shutdown", 128, 8), _hdr("countdown_shot_limiting", 136, 8),
           _hdr("thermal_shutdown", 144, 4), _hdr("shot_limiting", 152, 4))
_COLUMN = (_hdr("timestamp", 0, 64), _hdr("measurement_id", 64, 16))
HEADERS: dict[str, Header] = {h.name: h for h in (
    # parsing.cpp:479-510: no packet header or footer; frame_id and encoder count per column
    Header("LEGACY", (), _COLUMN + (_hdr("frame_id", 80, 16), _hdr("encoder_count", 96, 32)),
           (_hdr("status", 0, 32),), crc=False),
    # parsing.cpp:523-535
    Header("STANDARD", (_hdr("packet_type", 0, 16), _hdr("frame_id", 16, 16),
                        _hdr("init_id", 32, 24), _hdr("prod_sn", 56, 40),
                        _hdr("alert_flags", 96, 8)) + _STATUS,
           _COLUMN + (_hdr("status", 80, 16),), (), crc=True),
    # parsing.cpp:511-522: a 32-bit frame_id; the SDK neither reads nor writes a CRC
    Header("FUSA", (_hdr("packet_type", 0, 8), _hdr("init_id", 8, 24),
                    _hdr("frame_id", 32, 32), _hdr("alert_flags", 64, 8),
                    _hdr("prod_sn", 88, 40)) + _STATUS,
           _COLUMN + (_hdr("status", 80, 16),), (), crc=False),
)}


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
    header: str = "STANDARD"  # the header type the SDK assumes when metadata names none
    returns: int = 1  # SensorInfo.num_returns()

    def col_bytes(self, pixels: int) -> int:
        return self.col_header_bytes + pixels * self.pixel_bytes + self.col_footer_bytes

    def packet_bytes(self, pixels: int, columns_per_packet: int) -> int:
        return self.header_bytes + columns_per_packet * self.col_bytes(pixels) + self.footer_bytes

    def field(self, name: str) -> Field:
        for f in self.fields:
            if f.name == name:
                return f
        if name.startswith("RAW32_WORD") and name[10:].isdecimal() and \
                1 <= int(name[10:]) <= self.pixel_bytes // 4:
            k = int(name[10:]) - 1
            return Field(name, 4 * k, "<u4", 0xFFFFFFFF, 0)
        raise KeyError(f"profile {self.name} has no field {name!r}; it has "
                       f"{', '.join(f.name for f in self.fields)}")


def _std(name: str, pixel_bytes: int, fields: tuple[Field, ...], header: str = "STANDARD",
         returns: int = 1) -> Profile:
    return Profile(name, False, 32, 12, pixel_bytes, 0, 32, fields, header, returns)


# the low-bandwidth pixel (parsing.cpp:181-186) and its dual (304-315)
_LB = (_px("RANGE", 0, 15, 3), _px("FLAGS", 15, 1), _px("REFLECTIVITY", 16, 8),
       _px("NEAR_IR", 24, 8, 4))
_LB_DUAL = _LB + (_px("RANGE2", 32, 15, 3), _px("FLAGS2", 47, 1),
                  _px("REFLECTIVITY2", 48, 8), _px("WINDOW", 56, 8))
# the first two words of the 16-bit-signal dual pixels (parsing.cpp:213-244, 317-331)
_DUAL_HEAD = (_px("RANGE", 0, 19), _px("FLAGS", 19, 5), _px("REFLECTIVITY", 24, 8),
              _px("RANGE2", 32, 19), _px("FLAGS2", 51, 5), _px("REFLECTIVITY2", 56, 8),
              _px("SIGNAL", 64, 16), _px("SIGNAL2", 80, 16))

PROFILES: dict[str, Profile] = {p.name: p for p in (
    # the four tcf-hil emulates, written out word by word as checked bit for bit
    Profile("LEGACY", True, 0, 16, 12, 4, 0, (
        Field("RANGE", 0, "<u4", 0x000FFFFF, 0),
        Field("FLAGS", 0, "<u4", 0xF0000000, 28),
        Field("REFLECTIVITY", 4, "<u1", 0xFF, 0),
        Field("SIGNAL", 6, "<u2", 0xFFFF, 0),
        Field("NEAR_IR", 8, "<u2", 0xFFFF, 0),
    ), "LEGACY"),
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
    ), returns=2),
    Profile("RNG15_RFL8_NIR8", False, 32, 12, 4, 0, 32, (
        Field("RANGE", 0, "<u2", 0x7FFF, -3),
        Field("FLAGS", 0, "<u2", 0x8000, 15),
        Field("REFLECTIVITY", 2, "<u1", 0xFF, 0),
        Field("NEAR_IR", 3, "<u1", 0xFF, -4),
    )),
    # the rest ouster-sdk 1.0.1 decodes (parsing.cpp:170-331), read from field recordings
    _std("RNG15_RFL8_NIR8_DUAL", 8, _LB_DUAL, returns=2),
    _std("FUSA_RNG15_RFL8_NIR8_DUAL", 8, _LB_DUAL, "FUSA", returns=2),
    _std("RNG15_RFL8_WIN8", 4, _LB[:3] + (_px("WINDOW", 24, 8),)),
    _std("RNG19_RFL8_SIG16_NIR16_ZONE16", 12, (
        _px("RANGE", 0, 19), _px("FLAGS", 19, 5), _px("REFLECTIVITY", 32, 8),
        _px("WINDOW", 40, 8), _px("SIGNAL", 48, 16), _px("NEAR_IR", 64, 16),
        _px("ZONE_MASK", 80, 16))),
    _std("RNG15_RFL8_NIR8_ZONE16", 8, _LB + (_px("ZONE_MASK", 32, 16), _px("WINDOW", 48, 8))),
    _std("RNG19_RFL8_SIG16_ZONE16_DUAL", 16, _DUAL_HEAD + (
        _px("ZONE_MASK", 96, 16), _px("WINDOW", 120, 8)), returns=2),
    # R, G and B: the raw 16-bit (half-float) patterns, as ouster-sdk's RGB field holds them
    _std("RNG19_RFL8_SIG16_NIR16_RGB16", 16, (
        _px("RANGE", 0, 19), _px("FLAGS", 19, 5), _px("REFLECTIVITY", 24, 8),
        _px("SIGNAL", 32, 16), _px("NEAR_IR", 48, 16), _px("R", 64, 16), _px("G", 80, 16),
        _px("B", 96, 16))),
    _std("RNG19_RFL8_SIG16_NIR16_RGB16_DUAL", 20, _DUAL_HEAD + (
        _px("NEAR_IR", 96, 16), _px("R", 112, 16), _px("G", 128, 16), _px("B", 144, 16)),
        returns=2),
    # ouster-sdk's frame holds only RAW32_WORD1..5 of it; the packet fields are these
    _std("FIVE_WORD_PIXEL", 20, _DUAL_HEAD + (_px("NEAR_IR", 96, 16),)),
)}

# the profiles tcf-hil's OS0-64 emulator writes (the others are read and replayed)
EMULATED_PROFILES: tuple[str, ...] = ("LEGACY", "RNG19_RFL8_SIG16_NIR16",
                                      "RNG19_RFL8_SIG16_NIR16_DUAL", "RNG15_RFL8_NIR8")
