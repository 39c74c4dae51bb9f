"""The harvester node's object dictionary as data: the one source of truth from which the EDS,
the DBC and the PDO codec are all derived.

Units on the wire (CAN contract, DESIGN.md): position in mm (INTEGER32) relative to the datum
(0x2001, INTEGER64 mm, so UTM-sized coordinates survive), heading UNSIGNED16 in 0.01 deg
(compass: 0 = north (+y), clockwise), pitch and roll INTEGER16 in 0.01 deg, speed INTEGER16 in
mm/s (negative when reversing), the pose's simulation time UNSIGNED32 in microseconds (wraps
every 71.6 minutes) and a status word.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum


class DataType(IntEnum):
    """CiA 301 data types used here (EDS ``DataType`` codes)."""

    BOOLEAN = 0x01
    INTEGER8 = 0x02
    INTEGER16 = 0x03
    INTEGER32 = 0x04
    UNSIGNED8 = 0x05
    UNSIGNED16 = 0x06
    UNSIGNED32 = 0x07
    VISIBLE_STRING = 0x09
    INTEGER64 = 0x15
    UNSIGNED64 = 0x1B

    @property
    def bits(self) -> int:
        return _BITS[self]

    @property
    def signed(self) -> bool:
        return self in (DataType.INTEGER8, DataType.INTEGER16, DataType.INTEGER32,
                        DataType.INTEGER64)


_BITS = {DataType.BOOLEAN: 1, DataType.INTEGER8: 8, DataType.INTEGER16: 16,
         DataType.INTEGER32: 32, DataType.UNSIGNED8: 8, DataType.UNSIGNED16: 16,
         DataType.UNSIGNED32: 32, DataType.VISIBLE_STRING: 0, DataType.INTEGER64: 64,
         DataType.UNSIGNED64: 64}


@dataclass(frozen=True)
class Variable:
    """One value: a VAR object (subindex 0) or a sub-object of a RECORD."""

    index: int
    subindex: int
    name: str
    dtype: DataType
    access: str = "ro"  # ro, rw, const
    default: int | str = 0
    pdo: bool = False
    unit: str = ""
    factor: float = 1.0  # physical value = raw * factor (in ``unit``)
    description: str = ""
    default_text: str = ""  # EDS spelling when it needs $NODEID

    @property
    def limits(self) -> tuple[int, int]:
        b = self.dtype.bits
        return (-(1 << (b - 1)), (1 << (b - 1)) - 1) if self.dtype.signed else (0, (1 << b) - 1)


@dataclass(frozen=True)
class Record:
    """A RECORD object: sub 0 (highest subindex) is implied."""

    index: int
    name: str
    entries: tuple[Variable, ...]
    count: int | None = None  # sub 0 value when it is a count (PDO mappings), not the top


@dataclass(frozen=True)
class Mapping:
    """One TPDO: COB-ID base (node id is added), transmission type, event timer and the mapped
    variables in frame order."""

    number: int  # 1..4
    cob_base: int
    trans_type: int  # 1..240: every n-th SYNC; 254/255: event driven (event timer)
    event_timer_ms: int
    variables: tuple[tuple[int, int], ...]  # (index, subindex)

    def cob_id(self, node_id: int) -> int:
        return self.cob_base + node_id


@dataclass(frozen=True)
class ObjectDictionary:
    objects: tuple[Variable | Record, ...]
    tpdos: tuple[Mapping, ...]
    device_name: str = "tcf-hil harvester"
    vendor_id: int = 0x00000000
    product_code: int = 0x7CF0_0001
    revision: int = 0x0001_0000
    by_key: dict[tuple[int, int], Variable] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        d: dict[tuple[int, int], Variable] = {}
        for o in self.objects:
            for v in (o.entries if isinstance(o, Record) else (o,)):
                d[(v.index, v.subindex)] = v
        object.__setattr__(self, "by_key", d)

    def var(self, index: int, subindex: int = 0) -> Variable:
        return self.by_key[(index, subindex)]

    def frame_layout(self, m: Mapping) -> tuple[tuple[Variable, int], ...]:
        """((variable, bit offset), ...) of one TPDO, little-endian bit packing (CiA 301)."""
        out, bit = [], 0
        for key in m.variables:
            v = self.by_key[key]
            out.append((v, bit))
            bit += v.dtype.bits
        if bit > 64:
            raise ValueError(f"TPDO{m.number} maps {bit} bits; a classic CAN frame holds 64")
        return tuple(out)


# Pose record 0x2000 sub-indices (also the keys of the PDO codec's raw values).
POSE = 0x2000
X, Y, Z, HEADING, PITCH, ROLL, SPEED, TIME, STATUS = range(1, 10)
DATUM = 0x2001
MOUNT = 0x2002

# Status word bits (0x2000 sub 9).
STATUS_VALID = 1 << 0  # the pose is valid
STATUS_MOVING = 1 << 1  # the machine is moving
STATUS_REVERSE = 1 << 2  # driving backwards
STATUS_POSE_ERROR = 1 << 3  # a simulated GNSS/INS error is applied to what is on the bus
STATUS_PASS_SHIFT = 8  # bits 8..15: pass number along the strip road (0-based)

NMT_STATES = {0: "INITIALISING", 4: "STOPPED", 5: "OPERATIONAL", 127: "PRE-OPERATIONAL"}
SYNC_COB = 0x80
TIME_COB = 0x100
HEARTBEAT_BASE = 0x700


def _u32(i: int, s: int, name: str, default: int = 0, access: str = "rw",
         text: str = "") -> Variable:
    return Variable(i, s, name, DataType.UNSIGNED32, access, default, default_text=text)


def _tpdo_comm(m: Mapping) -> Record:
    i = 0x1800 + m.number - 1
    return Record(i, f"TPDO{m.number} communication parameter", (
        _u32(i, 1, "COB-ID", m.cob_base, text=f"$NODEID+0x{m.cob_base:X}"),
        Variable(i, 2, "Transmission type", DataType.UNSIGNED8, "rw", m.trans_type),
        Variable(i, 3, "Inhibit time", DataType.UNSIGNED16, "rw", 0, unit="100 us"),
        Variable(i, 5, "Event timer", DataType.UNSIGNED16, "rw", m.event_timer_ms, unit="ms"),
    ))


def _tpdo_map(m: Mapping, od_vars: dict[tuple[int, int], Variable]) -> Record:
    i = 0x1A00 + m.number - 1
    entries = []
    for n in range(1, 9):
        if n <= len(m.variables):
            idx, sub = m.variables[n - 1]
            code = (idx << 16) | (sub << 8) | od_vars[(idx, sub)].dtype.bits
        else:
            code = 0
        entries.append(_u32(i, n, f"Mapped object {n}", code))
    return Record(i, f"TPDO{m.number} mapping parameter", tuple(entries), len(m.variables))


def _build() -> ObjectDictionary:
    I32, I16, U16, U32, I64 = (DataType.INTEGER32, DataType.INTEGER16, DataType.UNSIGNED16,
                               DataType.UNSIGNED32, DataType.INTEGER64)
    pose = Record(POSE, "Pose", (
        Variable(POSE, X, "X", I32, "ro", 0, True, "m", 0.001,
                 "easting of the machine base point minus the datum, mm"),
        Variable(POSE, Y, "Y", I32, "ro", 0, True, "m", 0.001,
                 "northing of the machine base point minus the datum, mm"),
        Variable(POSE, Z, "Z", I32, "ro", 0, True, "m", 0.001,
                 "height of the machine base point (on the ground) minus the datum, mm"),
        Variable(POSE, HEADING, "Heading", U16, "ro", 0, True, "deg", 0.01,
                 "compass heading of the machine's forward axis, 0 = north, clockwise"),
        Variable(POSE, PITCH, "Pitch", I16, "ro", 0, True, "deg", 0.01,
                 "rotation about the machine's left axis (REP-103: positive = nose down)"),
        Variable(POSE, ROLL, "Roll", I16, "ro", 0, True, "deg", 0.01,
                 "rotation about the machine's forward axis (positive = left side up)"),
        Variable(POSE, SPEED, "Speed", I16, "ro", 0, True, "m/s", 0.001,
                 "signed speed along the forward axis, mm/s"),
        Variable(POSE, TIME, "Time", U32, "ro", 0, True, "us", 1.0,
                 "simulation time of this pose, microseconds modulo 2^32"),
        Variable(POSE, STATUS, "Status", U16, "ro", 0, True, "", 1.0,
                 "bit0 valid, bit1 moving, bit2 reverse, bit3 pose error applied, "
                 "bits 8-15 pass number"),
    ))
    datum = Record(DATUM, "Datum", (
        Variable(DATUM, 1, "Easting", I64, "ro", 0, False, "m", 0.001,
                 "world x of the pose origin, mm"),
        Variable(DATUM, 2, "Northing", I64, "ro", 0, False, "m", 0.001,
                 "world y of the pose origin, mm"),
        Variable(DATUM, 3, "Height", I64, "ro", 0, False, "m", 0.001,
                 "world z of the pose origin, mm"),
    ))
    mount = Record(MOUNT, "Lidar mount", (
        Variable(MOUNT, 1, "X", I32, "ro", 0, False, "m", 0.001,
                 "lidar sensor frame origin in the machine frame (x forward), mm"),
        Variable(MOUNT, 2, "Y", I32, "ro", 0, False, "m", 0.001, "y left, mm"),
        Variable(MOUNT, 3, "Z", I32, "ro", 2000, False, "m", 0.001, "z up, mm"),
        Variable(MOUNT, 4, "Yaw", I16, "ro", 0, False, "deg", 0.01,
                 "sensor yaw in the machine frame (REP-103 order: yaw, pitch, roll)"),
        Variable(MOUNT, 5, "Pitch", I16, "ro", 0, False, "deg", 0.01, "sensor pitch"),
        Variable(MOUNT, 6, "Roll", I16, "ro", 0, False, "deg", 0.01, "sensor roll"),
    ))
    tpdos = (
        Mapping(1, 0x180, 1, 0, ((POSE, X), (POSE, Y))),
        Mapping(2, 0x280, 1, 0, ((POSE, Z), (POSE, HEADING), (POSE, PITCH))),
        Mapping(3, 0x380, 1, 0, ((POSE, ROLL), (POSE, SPEED), (POSE, TIME))),
        Mapping(4, 0x480, 255, 100, ((POSE, STATUS), (POSE, TIME))),
    )
    pose_vars = {(v.index, v.subindex): v for v in pose.entries}
    comm: list[Variable | Record] = [
        Variable(0x1000, 0, "Device type", U32, "ro", 0),
        Variable(0x1001, 0, "Error register", DataType.UNSIGNED8, "ro", 0),
        _u32(0x1005, 0, "COB-ID SYNC", SYNC_COB),
        _u32(0x1006, 0, "Communication cycle period", 10_000),
        Variable(0x1008, 0, "Manufacturer device name", DataType.VISIBLE_STRING, "const",
                 "tcf-hil harvester"),
        _u32(0x1012, 0, "COB-ID TIME", 0x4000_0000 | TIME_COB),
        Variable(0x1017, 0, "Producer heartbeat time", U16, "rw", 100, unit="ms"),
        Record(0x1018, "Identity object", (
            _u32(0x1018, 1, "Vendor-ID", 0, "ro"),
            _u32(0x1018, 2, "Product code", 0x7CF0_0001, "ro"),
            _u32(0x1018, 3, "Revision number", 0x0001_0000, "ro"),
            _u32(0x1018, 4, "Serial number", 0, "ro"),
        )),
    ]
    comm += [_tpdo_comm(m) for m in tpdos]
    comm += [_tpdo_map(m, pose_vars) for m in tpdos]
    return ObjectDictionary(tuple(comm) + (pose, datum, mount), tpdos)


HARVESTER_OD = _build()
