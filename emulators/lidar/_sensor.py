"""What an OS0-64 emits frame by frame: the emulator's lidar packets with their headers
finished (frame_id, init_id, serial number, CRC), the IMU packets interleaved at 100 Hz in
send order, and the lidar faults that change what leaves the sensor (a dropped frame, a
re-initialisation: new init_id, frame_id from 0, silence meanwhile) and the UDP faults that
change what reaches the wire."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from emulators.faults import FaultEvent, LidarFaultPlan, UdpFaults, next_init_id
from emulators.lidar._os0 import FrameResult
from emulators.lidar._stream import Datagram
from protocols.ouster import ImuPacket, SensorMetadata, encode_imu_packet, finish_lidar_packets

IMU_PERIOD_NS = 10_000_000  # 100 Hz, the OS0's IMU packet rate (LEGACY IMU profile)

CrcRows = Callable[[NDArray[np.uint8]], NDArray[np.uint64]]


class ImuSource(Protocol):
    """The sensor's specific force and angular rate at times t (as a trajectory gives)."""

    def imu(self, t_ns: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(acceleration (n, 3) m/s^2 gravity included, angular rate (n, 3) rad/s)."""
        ...


class FrameSource(Protocol):
    """What makes a sensor's frames (:class:`~emulators.lidar.Os0Emulator`, or a standing
    machine's frames sent again): frame k starts at ``start_ns + k * period_ns``."""

    start_ns: int
    period_ns: int

    def frame(self, k: int) -> FrameResult:
        """Frame k, its packets encoded, their headers and CRCs left to the sensor."""
        ...


@dataclass
class SensorFrame:
    """One frame as it leaves the sensor. ``action``: ``send``, ``drop`` (no lidar packets),
    ``reinit`` or ``silent`` (nothing at all)."""

    result: FrameResult
    datagrams: list[Datagram]
    events: list[FaultEvent]
    action: str

    @property
    def sent(self) -> bool:
        return self.action == "send"


class Os0Sensor:
    """The frames of ``emu`` as the sensor sends them (see the module docstring). ``meta``
    follows a re-initialisation (a new ``init_id``). ``first_frame_id``: the frame_id of the
    first frame, as of a sensor that has been running a while (16 bits: it wraps)."""

    def __init__(self, emu: FrameSource, meta: SensorMetadata, imu: ImuSource, *,
                 lidar_faults: LidarFaultPlan | None = None,
                 udp_faults: UdpFaults | None = None, crc_rows: CrcRows | None = None,
                 first_frame_id: int = 0, first_imu_ns: int | None = None) -> None:
        self.emu, self.meta, self.imu = emu, meta, imu
        self.lidar_faults, self.udp_faults, self.crc_rows = lidar_faults, udp_faults, crc_rows
        self._next_imu = emu.start_ns if first_imu_ns is None else first_imu_ns
        # frame_id counts from here (None: re-initialising, it restarts at 0 with the next
        # frame that is sent)
        self._fid_base: int | None = -first_frame_id

    def skip_to(self, k: int) -> None:
        """The sensor as after making frames up to ``k`` - 1, without making them: only
        where no fault plan runs (their draws are made frame by frame)."""
        if self.lidar_faults is not None or self.udp_faults is not None:
            raise ValueError("a sensor with fault plans makes every frame in order")
        self._next_imu = self.emu.start_ns + k * self.emu.period_ns

    def frame(self, k: int) -> SensorFrame:
        """Frame ``k`` (frames are asked for in order)."""
        meta, emu = self.meta, self.emu
        fmt = meta.packet_format
        fr = emu.frame(k)
        action, event = "send", None
        if self.lidar_faults is not None:
            action, event = self.lidar_faults.frame(k, emu.start_ns + k * emu.period_ns,
                                                    emu.period_ns)
        events = [event] if event is not None else []
        if action == "reinit":
            old = meta.init_id
            self.meta = meta = meta.with_changes(init_id=next_init_id(old))
            events[0].update(init_id_old=old, init_id=meta.init_id)
            self._fid_base = None
        elif self._fid_base is None and action != "silent":
            self._fid_base = k
        arr = fr.packets
        finish_lidar_packets(fmt, arr, frame_id=(k - (self._fid_base or 0)) & 0xFFFF,
                             init_id=meta.init_id, prod_sn=meta.prod_sn, crc_rows=self.crc_rows)
        out = self._interleave(fr, arr, fmt.columns_per_packet)
        if action in ("reinit", "silent"):
            out = []  # re-initialising: nothing at all leaves the sensor
        elif action == "drop":
            out = [d for d in out if d.port != meta.udp_port_lidar]  # IMU goes on
        if self.udp_faults is not None:
            out, more = self.udp_faults.apply(out, k)
            events += more
        return SensorFrame(fr, out, events, action)

    def _interleave(self, fr: FrameResult, arr: NDArray[np.uint8], cpp: int) -> list[Datagram]:
        """Lidar packets at their last column's time stamp, IMU packets at 100 Hz between."""
        lp, ip = self.meta.udp_port_lidar, self.meta.udp_port_imu
        sends = fr.timestamps_ns[cpp - 1::cpp].tolist()
        imu_t = np.arange(self._next_imu, sends[-1] + 1, IMU_PERIOD_NS, dtype=np.int64)
        acc, gyro = self.imu.imu(imu_t) if len(imu_t) else (np.zeros((0, 3)),) * 2
        out = []
        j = 0
        for i, t_send in enumerate(sends):
            while j < len(imu_t) and imu_t[j] <= t_send:
                t = int(imu_t[j])
                out.append(Datagram(t, ip, encode_imu_packet(ImuPacket(
                    t, t, t, tuple(acc[j].tolist()), tuple(gyro[j].tolist())))))
                j += 1
            out.append(Datagram(t_send, lp, memoryview(arr[i]).toreadonly()))  # (the frame's)
        if len(imu_t):
            self._next_imu = int(imu_t[-1]) + IMU_PERIOD_NS
        return out
