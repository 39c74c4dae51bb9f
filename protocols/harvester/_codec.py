"""Pure codecs for the harvester's frames: pose TPDOs (from the mapping in the object
dictionary), the CANopen TIME object, heartbeat and NMT. No bus, no clock."""

from __future__ import annotations

import math
from dataclasses import dataclass

from protocols.harvester._od import (
    HARVESTER_OD,
    HEADING,
    PITCH,
    POSE,
    ROLL,
    SPEED,
    STATUS,
    STATUS_VALID,
    TIME,
    Mapping,
    ObjectDictionary,
    X,
    Y,
    Z,
)


class CanProtocolError(ValueError):
    """A frame or value the harvester codec cannot encode or decode; says what was expected
    and what arrived. Subclasses name the kind."""


class PdoLengthError(CanProtocolError):
    pass


class PoseRangeError(CanProtocolError):
    pass


TIME_WRAP_US = 1 << 32
_DAY_MS = 86_400_000
#: CANopen TIME counts days from 1984-01-01; that day in Unix days:
EPOCH_1984_DAYS = 5113


@dataclass(frozen=True)
class Pose:
    """The machine's pose as it goes on the bus. Position relative to the datum (object 0x2001);
    heading compass degrees (0 = north = +y, clockwise); pitch and roll REP-103 degrees;
    ``time_us`` the full (unwrapped) simulation time in microseconds."""

    x_m: float
    y_m: float
    z_m: float
    heading_deg: float
    pitch_deg: float
    roll_deg: float
    speed_m_s: float
    time_us: int
    status: int = STATUS_VALID

    @property
    def yaw_rad(self) -> float:
        """Mathematical yaw (counter-clockwise from +x = east)."""
        return math.radians(90.0 - self.heading_deg)


def _wrap180(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0


def pose_to_raw(p: Pose, od: ObjectDictionary = HARVESTER_OD) -> dict[tuple[int, int], int]:
    """Quantise a pose into the object dictionary's raw integers (keys (0x2000, sub))."""
    vals = {X: p.x_m * 1000.0, Y: p.y_m * 1000.0, Z: p.z_m * 1000.0,
            PITCH: _wrap180(p.pitch_deg) * 100.0, ROLL: _wrap180(p.roll_deg) * 100.0,
            SPEED: p.speed_m_s * 1000.0}
    raw: dict[tuple[int, int], int] = {}
    for sub, v in vals.items():
        var = od.var(POSE, sub)
        if not math.isfinite(v):
            raise PoseRangeError(f"pose {var.name}: expected a finite number, got {v}")
        n = round(v)
        lo, hi = var.limits
        if not lo <= n <= hi:
            raise PoseRangeError(
                f"pose {var.name}: {n} raw units ({v * var.factor:g} {var.unit}) outside "
                f"{var.dtype.name} [{lo}, {hi}]; move the datum (object 0x2001) closer")
        raw[(POSE, sub)] = n
    if not math.isfinite(p.heading_deg):
        raise PoseRangeError(f"pose Heading: expected a finite number, got {p.heading_deg}")
    raw[(POSE, HEADING)] = round((p.heading_deg % 360.0) * 100.0) % 36000
    raw[(POSE, TIME)] = int(p.time_us) % TIME_WRAP_US
    if not 0 <= p.status <= 0xFFFF:
        raise PoseRangeError(f"pose Status: expected 0..65535, got {p.status}")
    raw[(POSE, STATUS)] = int(p.status)
    return raw


def raw_to_pose(raw: dict[tuple[int, int], int], *, time_us: int | None = None) -> Pose:
    """Physical pose from raw values (``time_us``: the unwrapped time, default the raw one)."""
    return Pose(raw[(POSE, X)] / 1000.0, raw[(POSE, Y)] / 1000.0, raw[(POSE, Z)] / 1000.0,
                raw[(POSE, HEADING)] / 100.0, raw[(POSE, PITCH)] / 100.0,
                raw[(POSE, ROLL)] / 100.0, raw[(POSE, SPEED)] / 1000.0,
                raw[(POSE, TIME)] if time_us is None else time_us,
                raw.get((POSE, STATUS), STATUS_VALID))


def encode_pdo(m: Mapping, raw: dict[tuple[int, int], int],
               od: ObjectDictionary = HARVESTER_OD) -> bytes:
    """Pack the mapped values little-endian, bit after bit, as CiA 301 maps them."""
    acc, bits = 0, 0
    for v, off in od.frame_layout(m):
        n = raw[(v.index, v.subindex)]
        lo, hi = v.limits
        if not lo <= n <= hi:
            raise PoseRangeError(f"0x{v.index:04X}sub{v.subindex} {v.name}: {n} outside "
                                 f"{v.dtype.name} [{lo}, {hi}]")
        acc |= (n & ((1 << v.dtype.bits) - 1)) << off
        bits = off + v.dtype.bits
    return acc.to_bytes((bits + 7) // 8, "little")


def decode_pdo(m: Mapping, data: bytes,
               od: ObjectDictionary = HARVESTER_OD) -> dict[tuple[int, int], int]:
    layout = od.frame_layout(m)
    nbytes = (layout[-1][1] + layout[-1][0].dtype.bits + 7) // 8
    if len(data) != nbytes:
        raise PdoLengthError(f"TPDO{m.number}: expected {nbytes} data bytes, got {len(data)}")
    acc = int.from_bytes(data, "little")
    out = {}
    for v, off in layout:
        b = v.dtype.bits
        n = (acc >> off) & ((1 << b) - 1)
        if v.dtype.signed and n >= 1 << (b - 1):
            n -= 1 << b
        out[(v.index, v.subindex)] = n
    return out


def encode_pose(p: Pose, node_id: int, od: ObjectDictionary = HARVESTER_OD,
                *, synchronous: bool = True) -> list[tuple[int, bytes]]:
    """(COB-ID, data) of every TPDO of one pose sample: the SYNC-triggered ones
    (``synchronous``) or the event-driven ones, all from the same quantised values, so no
    frame ever mixes two poses."""
    raw = pose_to_raw(p, od)
    return [(m.cob_id(node_id), encode_pdo(m, raw, od)) for m in od.tpdos
            if (1 <= m.trans_type <= 240) == synchronous]


def unwrap_time_us(raw: int, previous_us: int | None) -> int:
    """Full time from a 32-bit microsecond count: the value nearest ``previous_us``."""
    if previous_us is None:
        return raw
    d = (raw - previous_us) % TIME_WRAP_US
    if d >= TIME_WRAP_US // 2:
        d -= TIME_WRAP_US
    return previous_us + d


class PoseAssembler:
    """Builds poses from the TPDOs of one node as they arrive, for consumers that do not use
    an EDS: ``feed(cob_id, data)`` returns a :class:`Pose` when the SYNC-triggered TPDOs of
    one sample are complete (they carry the same time stamp by construction), else None."""

    def __init__(self, node_id: int, od: ObjectDictionary = HARVESTER_OD) -> None:
        self.od = od
        self.by_cob = {m.cob_id(node_id): m for m in od.tpdos}
        self.sync_keys = {k for m in od.tpdos if 1 <= m.trans_type <= 240 for k in m.variables}
        self._group: dict[tuple[int, int], int] = {}
        self._status = STATUS_VALID
        self._last_us: int | None = None

    def reset(self) -> None:
        self._group.clear()

    def feed(self, cob_id: int, data: bytes) -> Pose | None:
        m = self.by_cob.get(cob_id)
        if m is None:
            return None
        vals = decode_pdo(m, data, self.od)
        if not 1 <= m.trans_type <= 240:
            self._status = vals.get((POSE, STATUS), self._status)
            return None
        self._group.update(vals)
        if not self.sync_keys <= self._group.keys():
            return None
        raw, self._group = self._group, {}
        self._last_us = unwrap_time_us(raw[(POSE, TIME)], self._last_us)
        raw[(POSE, STATUS)] = self._status
        return raw_to_pose(raw, time_us=self._last_us)


def encode_time(unix_ms: int) -> bytes:
    """CANopen TIME_OF_DAY: ms after midnight (28 bits) and days since 1984-01-01 (16 bits)."""
    days, ms = divmod(int(unix_ms), _DAY_MS)
    d = days - EPOCH_1984_DAYS
    if not 0 <= d <= 0xFFFF:
        raise CanProtocolError(f"TIME: date outside 1984-01-01 + 65535 days: {unix_ms} ms")
    return ms.to_bytes(4, "little") + d.to_bytes(2, "little")


def decode_time(data: bytes) -> int:
    """Unix time in ms from a TIME_OF_DAY payload."""
    if len(data) != 6:
        raise PdoLengthError(f"TIME: expected 6 data bytes, got {len(data)}")
    ms = int.from_bytes(data[:4], "little") & 0x0FFF_FFFF
    if ms >= _DAY_MS:
        raise CanProtocolError(f"TIME: {ms} ms after midnight is beyond one day")
    return (int.from_bytes(data[4:], "little") + EPOCH_1984_DAYS) * _DAY_MS + ms
