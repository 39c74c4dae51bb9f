"""Recorded traffic read back: a tcf-hil run directory, or a field recording (an Ouster pcap
as ouster-cli or ouster-ros write it, with its metadata JSON, and optionally a CAN log in
candump .log, .asc, .blf or .trc), read onto one time line (:func:`events`), as python-can's
``LogReader`` reads a log. Sending it again, paced, is :mod:`tcf_hil.run._send`'s; the
session that serves it (the HTTP API with the recorded metadata, the SIC, the score) is
:class:`tcf_hil.run.ReplayTraffic`'s.

Recordings are streamed from disk, never read whole: a first pass checks that every lidar
packet fits the metadata (the first that does not is one error naming it) and counts
frames, IMU packets and other traffic; each pass of the replay then reads the pcap and the
CAN log again as it sends them (memory stays flat whatever the recording's length).

Both recordings are put on one time line: a run's pcap records carry simulation time and its
CAN log's wall-clock time stamps are mapped onto it through the run manifest's clock
(``unix_ns_at_sim_t0``); a field recording's pcap and CAN log both carry wall-clock time
(``can_offset_s`` moves the CAN log where the two clocks differ). With ``loop``, each pass
shifts frame_id (continuing where the last pass ended, which ouster-sdk's own replay does
not do), the column time stamps and the pose time on CAN by the recording's length, so that a
consumer sees one continuous drive.
"""

from __future__ import annotations

import heapq
import os
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np

from protocols.harvester import HARVESTER_OD, POSE, TIME_WRAP_US, decode_pdo, encode_pdo
from protocols.ouster import (
    IMU_PACKET_BYTES,
    FrameAssembler,
    MetadataError,
    ProtocolError,
    SensorMetadata,
    decode_lidar_packet,
    decode_lidar_packets,
    shift_lidar_packet,
)
from protocols.pcap import PcapError, UdpReader
from tcf_hil._crc import fast_crc_rows
from tcf_hil._io import read_json
from tcf_hil.errors import InputError
from tcf_hil.recording.osf import is_osf, osf_to_recording
from tcf_hil.recording.rosbag import bag_to_recording, is_bag
from tcf_hil.recording.rundir import RunDir

_TIME_KEY = (POSE, 8)
CAN_LOG_SUFFIXES = (".log", ".asc", ".blf", ".trc")
_CHECK_BATCH = 256  # lidar packets checked at once
_MAX_STRAYS = 1000  # lidar packets that do not fit before one does: the metadata is wrong
_GUESS_SAMPLE = 4096  # UDP datagrams read to find ports the metadata leaves at 0


def find_metadata(pcap: Path) -> Path:
    """The metadata JSON beside ``pcap``, found as ouster-cli finds it: the ``.json`` file in
    the same directory whose name shares the longest prefix with the pcap's (at least one
    character); a tcf-hil run's ``metadata.json`` where none does."""
    names = [f for f in os.listdir(pcap.parent) if f.lower().endswith(".json")
             and (pcap.parent / f).is_file()]
    score = {f: _common(f, pcap.name) for f in names}
    best = max(score.values(), default=0)
    found = sorted(f for f, n in score.items() if n == best and n > 0)
    if len(found) > 1:
        raise InputError(str(pcap), "", f"{len(found)} metadata files beside it share its "
                         f"name's prefix ({', '.join(found)}); give one with --meta")
    if found:
        return pcap.parent / found[0]
    if (pcap.parent / "metadata.json").is_file():
        return pcap.parent / "metadata.json"
    raise InputError(str(pcap), "", "no metadata JSON beside it shares its name's prefix "
                     "(as ouster-cli looks for one); give it with --meta")


def _common(a: str, b: str) -> int:
    """The length of the common prefix of two names, character by character."""
    n = 0
    for x, y in zip(a, b, strict=False):
        if x != y:
            break
        n += 1
    return n


@dataclass
class Recording:
    """Recorded traffic on one time line, streamed from its files (see the module's doc).

    ``meta`` describes the pcap (its ports are the recorded ones); ``meta_text`` is the
    document as recorded; ``port_map`` sends a recorded port to the port used now."""

    meta: SensorMetadata
    meta_text: str
    pcap: Path
    can_log: Path | None = None
    can_clock: tuple[int, int, float] = (0, 0, 1.0)  # sim_t0_ns, unix_ns_at_sim_t0, speed
    manifest: dict[str, Any] | None = None
    frames: int = 0
    span_ns: int = 0
    lidar_start_ns: int = 0
    frame_span: int = 0  # frame ids from the first frame to the last (what a loop adds)
    counts: Counter[str] = field(default_factory=Counter)
    port_map: dict[int, int] = field(default_factory=dict)
    can_frames: int = 0
    # the sensor's source address: where the first packet that fits the metadata came from
    # (another sensor sending to the same port is other traffic)
    sensor_ip: str | None = None
    # a field CAN log's SDO answers: the node that gave them and the values
    sdo_node: int | None = None
    sdo_values: dict[tuple[int, int], bytes] = field(default_factory=dict)
    # the ports found in the capture where the metadata names none (udp_port_lidar or
    # udp_port_imu 0: a sensor saved before they were set, a legacy flat file); None: as named
    guessed_ports: tuple[int, int] | None = None

    @property
    def is_run(self) -> bool:
        return self.manifest is not None

    @classmethod
    def load(cls, path: Path, *, meta: Path | None = None, can_log: Path | None = None,
             can_offset_s: float = 0.0,
             progress: Callable[[int, int], None] | None = None) -> Recording:
        """A run directory (its ``lidar.pcap``, ``metadata.json``, ``manifest.json`` and
        ``can.log``) or an Ouster pcap (``meta``: its metadata, found beside it when None;
        ``can_log``: a CAN log to put on the bus), checked in one streaming pass
        (``progress(bytes read, bytes)``)."""
        if (path.is_dir() and is_bag(path)) or is_osf(path):
            return cls._written_out(path, meta, can_log, can_offset_s, progress)
        if path.is_dir():
            rec = cls._run_dir(path, meta, can_log)
            t0, unix0, speed = rec.can_clock
            rec.can_clock = (t0, unix0 - round(can_offset_s * 1e9), speed)
        else:
            if not path.is_file():
                raise InputError(str(path), "", "no such file or directory")
            meta_path = meta or find_metadata(path)
            rec = cls(*_read_meta(meta_path), path, can_log)
            rec.can_clock = (0, -round(can_offset_s * 1e9), 1.0)
        rec._check(progress)
        return rec

    def _check(self, progress: Callable[[int, int], None] | None) -> None:
        """The CAN log readable, the ports known (found in the capture where the metadata
        names none), every packet checked in one pass."""
        if self.can_log is not None:
            _check_can_log(self.can_log)
        if not self.meta.udp_port_lidar or not self.meta.udp_port_imu:
            self._guess_ports()
        self._scan(progress)

    @classmethod
    def _written_out(cls, path: Path, meta: Path | None, can_log: Path | None,
                     can_offset_s: float, progress: Callable[[int, int], None] | None
                     ) -> Recording:
        """A ROS 2 bag (its packets) or an OSF file (its frames as the packets of its
        profile), written out as a capture in a folder of this process's and read as a field
        recording; an error in it names ``path``."""
        work = _work_dir(path)
        try:
            if path.is_dir():
                pcap, own_meta, own_can = bag_to_recording(path, work)
            else:
                (pcap, own_meta), own_can = osf_to_recording(path, work), None
            rec = cls(*_read_meta(meta or own_meta), pcap, can_log or own_can)
            rec.can_clock = (0, -round(can_offset_s * 1e9), 1.0)
            rec._check(progress)
        except InputError as err:
            if err.path.startswith(str(work)):
                raise InputError(str(path), err.field, f"{err.problem} (in its packets "
                                 "written out as a capture)") from err
            raise
        return rec

    @classmethod
    def _run_dir(cls, run_dir: Path, meta: Path | None, can_log: Path | None) -> Recording:
        RunDir(run_dir).require(RunDir.LIDAR, RunDir.METADATA, RunDir.MANIFEST)
        man = read_json(run_dir / "manifest.json")
        try:
            clock = man["clock"]
            t0, unix0, speed = (int(clock["sim_t0_ns"]), int(clock["unix_ns_at_sim_t0"]),
                                float(clock["speed"]))
        except (KeyError, TypeError, ValueError) as err:
            raise InputError(str(run_dir / "manifest.json"), "clock",
                             f"missing or malformed ({err})") from err
        # can.log from a run; a replayed field recording's log keeps its own format
        own = [run_dir / f"can{x}" for x in CAN_LOG_SUFFIXES if (run_dir / f"can{x}").exists()]
        return cls(*_read_meta(meta or run_dir / "metadata.json"), run_dir / "lidar.pcap",
                   can_log or (own[0] if own else None), (t0, unix0, speed), man)

    # ------------------------------------------------------------------------- reading
    def datagrams(self) -> Iterator[tuple[int, int, bytes]]:
        """(time ns, recorded destination port, payload) of every lidar and IMU datagram, in
        capture order, read from the file as they come."""
        lidar, imu = self.meta.udp_port_lidar, self.meta.udp_port_imu
        with open(self.pcap, "rb") as f:
            for d in UdpReader(f):
                if (d.dst_port == lidar or (d.dst_port == imu and
                                            len(d.payload) == IMU_PACKET_BYTES)) and \
                        d.src_ip == self.sensor_ip:
                    yield d.timestamp_ns, d.dst_port, d.payload

    def can_messages(self) -> Iterator[tuple[int, can.Message]]:
        """(time ns on the pcap's time line, frame) of every frame of the CAN log."""
        if self.can_log is None:
            return
        t0, unix0, speed = self.can_clock
        with _can_reader(self.can_log) as reader:
            for m in reader:
                if m.is_error_frame:
                    continue
                yield t0 + round((m.timestamp * 1e9 - unix0) * speed), m

    def _scan(self, progress: Callable[[int, int], None] | None) -> None:
        """Check every lidar packet against the metadata (size, packet type, ids, CRC where
        the firmware writes one) and count frames, IMU packets and other traffic."""
        meta, fmt = self.meta, self.meta.packet_format
        lidar, imu = meta.udp_port_lidar, meta.udp_port_imu
        asm = FrameAssembler(fmt, column_window=meta.column_window)
        crc = fast_crc_rows()
        batch: list[tuple[int, bytes]] = []
        ids: list[int] = []
        first = last = None
        sensor: str | None = None  # the source address of the metadata's sensor
        strays: dict[str, InputError] = {}  # the first misfit from each address till then
        imu_from: Counter[str] = Counter()
        n = self.counts
        size = self.pcap.stat().st_size

        def check() -> None:
            arr = np.frombuffer(b"".join(b for _i, b in batch), np.uint8).reshape(
                len(batch), fmt.packet_bytes)
            try:
                decode_lidar_packets(fmt, arr, init_id=meta.init_id, prod_sn=meta.prod_sn,
                                     crc_rows=crc, fields=())
            except ProtocolError:
                for i, b in batch:  # the first that does not fit, with its own message
                    try:
                        decode_lidar_packet(fmt, b, init_id=meta.init_id,
                                            prod_sn=meta.prod_sn, crc_rows=crc)
                    except ProtocolError as err:
                        raise self._bad(i, str(err)) from err
            batch.clear()

        try:
            with open(self.pcap, "rb") as f:
                reader = UdpReader(f)
                for i, d in enumerate(reader, 1):
                    if d.dst_port == imu and len(d.payload) == IMU_PACKET_BYTES:
                        imu_from[d.src_ip] += 1  # (first: a sensor may send both to one port)
                    elif d.dst_port == lidar:
                        if sensor is None:  # which address is the metadata's sensor?
                            why = self._misfit(d.payload, crc)
                            if why is not None:
                                strays.setdefault(d.src_ip, self._bad(i, why))
                                n["stray"] += 1
                                if n["stray"] >= _MAX_STRAYS:
                                    raise next(iter(strays.values()))
                                continue
                            if d.src_ip in strays:  # the sensor's own packet did not fit
                                raise strays[d.src_ip]
                            sensor = d.src_ip
                            n["other sensors"] += n.pop("stray", 0)
                        elif d.src_ip != sensor:
                            n["other sensors"] += 1
                            continue
                        elif len(d.payload) != fmt.packet_bytes:
                            raise self._bad(i, self._misfit(d.payload, crc) or "")
                        n["lidar"] += 1
                        first = d.timestamp_ns if first is None else first
                        last = d.timestamp_ns
                        batch.append((i, d.payload))
                        if len(batch) == _CHECK_BATCH:
                            check()
                        ids.extend(fr.frame_id for fr in asm.feed(d.payload))
                        del ids[1:-1]  # (the first and the last are what is needed)
                    else:
                        n["other"] += 1
                        n[f"port {d.dst_port}"] += 1
                    if progress is not None and i % 4096 == 0:
                        progress(f.tell(), size)
                if batch:
                    check()
                n["not udp"] += reader.skipped
        except PcapError as err:
            raise InputError(str(self.pcap), "", str(err)) from err
        except OSError as err:
            raise InputError(str(self.pcap), "", err.strerror or str(err)) from err
        ids.extend(fr.frame_id for fr in asm.flush())
        self.frames = asm.stats.frames
        if sensor is None and strays:
            raise next(iter(strays.values()))
        self.sensor_ip = sensor
        n["imu"] = imu_from.pop(sensor, 0) if sensor is not None else 0
        n["other sensors"] += sum(imu_from.values())
        if ids:
            self.frame_span = (ids[-1] - ids[0]) % fmt.frame_id_modulus + 1
        if not n["lidar"]:
            ports = ", ".join(f"{k[5:]} ({v})" for k, v in n.most_common() if
                              k.startswith("port ")) or "none"
            raise InputError(str(self.pcap), "", (
                f"no lidar packet to port {lidar} (the metadata's udp_port_lidar); UDP "
                f"ports in the capture: {ports}"))
        # a pass of a loop lasts the lidar recording plus one frame period, so that the
        # next pass's first frame follows the last at the sensor's own rate
        period = 1_000_000_000 // meta.frequency_hz
        assert first is not None and last is not None
        self.lidar_start_ns, self.span_ns = first, last - first + period
        self._scan_can_log()
        if progress is not None:
            progress(size, size)

    def _scan_can_log(self) -> None:
        """Count the CAN log's frames and (a field log's) the SDO answers it recorded, in one
        pass; a log that breaks off is one error naming it."""
        if self.can_log is None:
            return
        frames: list[can.Message] = []

        def counted() -> Iterator[can.Message]:
            for _t, m in self.can_messages():
                self.can_frames += 1
                if 0x581 <= m.arbitration_id <= 0x5FF:
                    frames.append(m)
                yield m

        try:
            for _m in counted():
                pass
        except Exception as err:  # python-can's readers raise what their parsers raise
            raise InputError(str(self.can_log), f"after frame {self.can_frames}",
                             f"not a readable CAN log: {_first_line(err)}") from err
        if not self.is_run:
            self.sdo_node, self.sdo_values = recorded_sdo(iter(frames))

    def _guess_ports(self, sample: int = _GUESS_SAMPLE) -> None:
        """The ports the metadata leaves at 0, found in the capture's first ``sample`` UDP
        datagrams as ouster-sdk guesses them for a pcap: the lidar port the one most of the
        datagrams that fit the metadata's lidar packet (its size, then the packet check) go
        to, the IMU port the one most IMU-sized datagrams go to (0 where there are none)."""
        meta, crc = self.meta, fast_crc_rows()
        lidar: Counter[int] = Counter()
        imu: Counter[int] = Counter()
        size = meta.packet_format.packet_bytes
        try:
            with open(self.pcap, "rb") as f:
                for i, d in enumerate(UdpReader(f)):
                    if i == sample:
                        break
                    if len(d.payload) == IMU_PACKET_BYTES:
                        imu[d.dst_port] += 1
                    elif len(d.payload) == size and self._misfit(d.payload, crc) is None:
                        lidar[d.dst_port] += 1
        except PcapError as err:
            raise InputError(str(self.pcap), "", str(err)) from err
        except OSError as err:
            raise InputError(str(self.pcap), "", err.strerror or str(err)) from err
        lp = meta.udp_port_lidar or (lidar.most_common(1)[0][0] if lidar else 0)
        if not lp:
            raise InputError(str(self.pcap), "", (
                "the metadata names no udp_port_lidar and no datagram in the capture's "
                f"first {sample} fits its lidar packets ({meta.profile}, {size} bytes)"))
        ip = meta.udp_port_imu or (imu.most_common(1)[0][0] if imu else 0)
        self.guessed_ports = (lp, ip)
        self.meta = meta.with_changes(udp_port_lidar=lp, udp_port_imu=ip)

    def _misfit(self, payload: bytes, crc: Any) -> str | None:
        """Why a lidar packet does not fit the metadata (None: it fits)."""
        fmt = self.meta.packet_format
        if len(payload) != fmt.packet_bytes:
            return (f"a lidar packet of {len(payload)} bytes; {fmt.profile.name} with "
                    f"{fmt.pixels_per_column} pixels and {fmt.columns_per_packet} columns per "
                    f"packet is {fmt.packet_bytes} bytes")
        try:
            decode_lidar_packet(fmt, payload, init_id=self.meta.init_id,
                                prod_sn=self.meta.prod_sn, crc_rows=crc)
        except ProtocolError as err:
            return str(err)
        return None

    def _bad(self, i: int, why: str) -> InputError:
        return InputError(str(self.pcap), f"datagram {i}", f"{why}: the capture does not fit "
                          f"its metadata")


def _work_dir(bag: Path) -> Path:
    """Where a bag's packets are written out as a capture for this process (removed when it
    exits)."""
    import atexit
    import shutil
    import tempfile

    work = Path(tempfile.mkdtemp(prefix=f"tcf-hil-{bag.name[:40]}-"))
    atexit.register(shutil.rmtree, work, True)
    return work


def _read_meta(path: Path) -> tuple[SensorMetadata, str]:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(str(path), "", f"cannot read the metadata: {err}") from err
    try:
        return SensorMetadata.loads(text), text
    except MetadataError as err:
        raise InputError(str(path), "", str(err)) from err


def _can_reader(path: Path) -> Any:
    """python-can's reader for a CAN log by its suffix; ASC files read with absolute time
    stamps (their header's date), as the other formats carry them."""
    suffix = path.suffix.lower()
    if suffix == ".asc":
        return can.ASCReader(str(path), relative_timestamp=False)
    return can.LogReader(str(path))


def _check_can_log(path: Path) -> None:
    if path.suffix.lower() not in CAN_LOG_SUFFIXES:
        raise InputError(str(path), "", f"a CAN log must be one of "
                         f"{', '.join(CAN_LOG_SUFFIXES)} (candump, Vector ASC or BLF, PCAN "
                         "TRC)")
    if not path.is_file():
        raise InputError(str(path), "", "no such file")
    try:
        with _can_reader(path) as reader:
            next(iter(reader), None)
    except Exception as err:  # python-can's readers raise what their parsers raise
        raise InputError(str(path), "", f"not a readable CAN log: {_first_line(err)}"
                         ) from err


def _first_line(err: BaseException) -> str:
    return str(err).splitlines()[0] if str(err) else type(err).__name__


def _shift_imu(payload: bytes, dt_ns: int) -> bytes:
    if dt_ns == 0 or len(payload) != IMU_PACKET_BYTES:
        return payload
    ts = np.frombuffer(payload[:24], "<u8") + np.uint64(dt_ns)
    return ts.astype("<u8").tobytes() + payload[24:]


def _shift_can(msg: can.Message, node_id: int, dt_ns: int) -> can.Message:
    if dt_ns == 0:
        return msg
    for m in HARVESTER_OD.tpdos:
        if msg.arbitration_id == m.cob_id(node_id) and _TIME_KEY in m.variables:
            raw = decode_pdo(m, bytes(msg.data))
            raw[_TIME_KEY] = (raw[_TIME_KEY] + dt_ns // 1000) % TIME_WRAP_US
            return can.Message(arbitration_id=msg.arbitration_id, data=encode_pdo(m, raw),
                               is_extended_id=False)
    return msg


def events(rec: Recording, loop: bool, node_id: int | None, *, answered: bool = True
           ) -> Iterator[tuple[int, str, Any]]:
    """(ns, "udp"/"can", item) in time order (the pcap's datagrams in capture order, the CAN
    log's frames between them), forever when ``loop``; read from the files as they go.
    ``node_id``: the harvester node, whose pose time a loop moves on; ``answered``: its
    recorded SDO exchanges are left out (a responder answers them now)."""
    lo = rec.lidar_start_ns
    fmt = rec.meta.packet_format
    lidar, imu = rec.meta.udp_port_lidar, rec.meta.udp_port_imu
    sdo = (0x580 + node_id, 0x600 + node_id) if node_id is not None and answered else ()
    crc = fast_crc_rows()
    k = 0
    while True:
        dt = k * rec.span_ns
        dframe = k * rec.frame_span
        udp: Iterator[tuple[int, int, Any]] = (
            (t, 0, (port, payload)) for t, port, payload in rec.datagrams())
        bus: Iterator[tuple[int, int, Any]] = ((t, 1, m) for t, m in rec.can_messages())
        item: Any
        for t, kind, item in heapq.merge(udp, bus, key=lambda e: (e[0], e[1])):
            # after the first pass, only the frames of one span: the run's lead (the pose
            # before the first lidar frame) and its tail are not driven again
            if k and not lo <= t < lo + rec.span_ns:
                continue
            if kind == 0:
                port, payload = item
                if port == imu and len(payload) == IMU_PACKET_BYTES:  # (first: one port may
                    payload = _shift_imu(payload, dt)                 # carry both)
                elif port == lidar:
                    payload = shift_lidar_packet(fmt, payload, dframe, dt, crc)
                yield t + dt, "udp", (rec.port_map.get(port, port), payload)
            elif item.arbitration_id not in sdo:  # recorded SDO exchanges answer nobody now
                yield t + dt, "can", _shift_can(item, node_id, dt) if node_id else item
        if not loop:
            return
        k += 1


def recorded_sdo(messages: Iterator[can.Message]) -> tuple[int | None,
                                                          dict[tuple[int, int], bytes]]:
    """The SDO uploads a CAN log recorded a node answering (expedited and segmented, as
    CiA 301 frames them): (the node that answered most, {(index, subindex): data})."""
    values: dict[int, dict[tuple[int, int], bytes]] = {}
    pending: dict[int, tuple[int, int, int, bytearray]] = {}  # node -> index, sub, size, data
    for m in messages:
        node = m.arbitration_id - 0x580
        if not 1 <= node <= 127 or m.is_extended_id or len(m.data) != 8:
            continue
        d = bytes(m.data)
        scs = d[0] >> 5
        if scs == 2:  # initiate upload response
            index, sub = d[1] | d[2] << 8, d[3]
            if d[0] & 0x2:  # expedited: up to 4 bytes in the frame
                n = (d[0] >> 2) & 0x3 if d[0] & 0x1 else 0
                values.setdefault(node, {})[(index, sub)] = d[4:8 - n]
            else:
                size = int.from_bytes(d[4:8], "little") if d[0] & 0x1 else -1
                pending[node] = (index, sub, size, bytearray())
        elif scs == 0 and node in pending:  # upload segment response
            index, sub, size, buf = pending[node]
            buf += d[1:8 - ((d[0] >> 1) & 0x7)]
            if d[0] & 0x1:  # the last segment
                del pending[node]
                values.setdefault(node, {})[(index, sub)] = bytes(
                    buf if size < 0 else buf[:size])
    if not values:
        return None, {}
    node = max(values, key=lambda k: len(values[k]))
    return node, values[node]
