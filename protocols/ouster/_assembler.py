"""Lidar packets in, whole frames out (sans-IO): what a receiver and a replay need between
the socket (or the capture) and the decoder.

Packets are placed by their frame (init_id, frame_id) and by their place in it (the first
column's measurement_id over columns per packet); where the fields are is read from the
packet format's header tables (:data:`protocols.ouster.HEADERS`), so LEGACY, STANDARD and
FUSA packets (a 32-bit frame_id) are assembled alike. Up to ``open_frames`` frames are open
at once: a packet overtaken by the next frame's still lands in its own frame; a frame is
handed on when it holds every packet its column window needs, or when one frame too many
has begun (then as it is, incomplete); frames go out in the order they began. A packet that
arrives twice, or after its frame was handed on, is counted and skipped; a new init_id (the
sensor restarted) hands on every open frame first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from protocols.ouster._packets import PacketFormat
from protocols.ouster._profiles import Field

__all__ = ["AssembledFrame", "AssemblerStats", "FrameAssembler", "window_places"]


@dataclass(frozen=True)
class AssembledFrame:
    """One frame's packets: ``packets`` (k, packet_bytes) in place order, ``places`` (k,)
    their places in the frame (0 .. packets_per_frame - 1), ``complete``: it holds every
    place its column window needs."""

    init_id: int
    frame_id: int
    packets: NDArray[np.uint8]
    places: NDArray[np.int64]
    complete: bool


@dataclass
class AssemblerStats:
    packets: int = 0  # placed in a frame
    bad_size: int = 0  # not this format's size (other traffic, another sensor)
    bad_place: int = 0  # a measurement_id beyond the frame
    duplicates: int = 0  # a place already filled in an open frame
    late: int = 0  # for a frame already handed on
    frames: int = 0  # handed on
    incomplete: int = 0  # handed on without every place
    frames_lost: int = 0  # frame ids skipped between the frames begun
    restarts: int = 0  # init_id changes


def window_places(fmt: PacketFormat, column_window: tuple[int, int] | None = None
                  ) -> frozenset[int]:
    """The packet places that carry the columns of ``column_window`` (first, last; inclusive,
    wrapping past the frame's end as the sensor's azimuth window may): what a complete frame
    holds. None: the whole frame."""
    W, C = fmt.columns_per_frame, fmt.columns_per_packet
    if column_window is None:
        return frozenset(range(W // C))
    a, b = column_window
    cols = range(a, b + 1) if a <= b else [*range(a, W), *range(0, b + 1)]
    return frozenset(c // C for c in cols)


def _reader(f: Field, base: int = 0) -> tuple[int, int, int, int]:
    size = np.dtype(f.dtype).itemsize
    return base + f.offset, size, f.mask, f.shift


def _get(buf: bytes | bytearray | memoryview, spec: tuple[int, int, int, int]) -> int:
    at, size, mask, shift = spec
    v = int.from_bytes(buf[at:at + size], "little") & mask
    return v >> shift if shift >= 0 else v << -shift


class FrameAssembler:
    """Assemble ``fmt``'s lidar packets into frames (see the module's doc string).

    Feed each datagram's payload to :meth:`feed`, which returns the frames it completed
    (usually none or one); :meth:`flush` hands on what is still open (the end of a capture).
    ``column_window``: the metadata's (first, last) columns the sensor sends (default: all).
    """

    LATE_WINDOW = 8  # frame ids this far behind the newest are late, not a restart

    def __init__(self, fmt: PacketFormat, *, column_window: tuple[int, int] | None = None,
                 open_frames: int = 2) -> None:
        if open_frames < 1:
            raise ValueError(f"open_frames {open_frames}; at least 1")
        self.fmt = fmt
        self.open_frames = open_frames
        self.needed = window_places(fmt, column_window)
        self.stats = AssemblerStats()
        h = fmt.header
        cols = fmt.profile.header_bytes
        mid = h.field("measurement_id")
        assert mid is not None
        self._mid = _reader(mid, cols)
        fid = h.field("frame_id")
        assert fid is not None
        self._fid = _reader(fid, cols if fmt.profile.legacy else 0)
        init = h.field("init_id")
        self._init = _reader(init) if init is not None else None
        self._modulus = fmt.frame_id_modulus
        self._open: dict[tuple[int, int], dict[int, bytes]] = {}
        self._newest: tuple[int, int] | None = None  # (init_id, frame_id) last begun

    def feed(self, payload: bytes | bytearray | memoryview) -> list[AssembledFrame]:
        fmt, st = self.fmt, self.stats
        if len(payload) != fmt.packet_bytes:
            st.bad_size += 1
            return []
        place = _get(payload, self._mid) // fmt.columns_per_packet
        if place >= fmt.packets_per_frame:
            st.bad_place += 1
            return []
        init = _get(payload, self._init) if self._init is not None else 0
        fid = _get(payload, self._fid)
        key = (init, fid)
        out: list[AssembledFrame] = []
        parts = self._open.get(key)
        if parts is None:
            newest = self._newest
            if newest is not None and newest[0] != init:
                st.restarts += 1
                out += self.flush()
            elif newest is not None:
                behind = (newest[1] - fid) % self._modulus
                if behind < self.LATE_WINDOW:  # a frame already handed on
                    st.late += 1
                    return out
                ahead = (fid - newest[1]) % self._modulus
                if ahead < 1000:  # (further off: the sensor restarted its count)
                    st.frames_lost += ahead - 1
            self._newest = key
            parts = self._open[key] = {}
            while len(self._open) > self.open_frames:
                out.append(self._hand_on(next(iter(self._open))))
        if place in parts:
            st.duplicates += 1
            return out
        parts[place] = bytes(payload)
        st.packets += 1
        if self.needed <= parts.keys():
            for old in list(self._open):  # older frames first, as they are
                out.append(self._hand_on(old))
                if old == key:
                    break
        return out

    def flush(self) -> list[AssembledFrame]:
        """Hand on every open frame, complete or not, oldest first."""
        return [self._hand_on(k) for k in list(self._open)]

    def _hand_on(self, key: tuple[int, int]) -> AssembledFrame:
        parts = self._open.pop(key)
        places = sorted(parts)
        arr = np.frombuffer(b"".join(parts[k] for k in places), np.uint8).reshape(
            len(places), self.fmt.packet_bytes)
        complete = self.needed <= parts.keys()
        self.stats.frames += 1
        self.stats.incomplete += not complete
        return AssembledFrame(key[0], key[1], arr, np.asarray(places, np.int64), complete)
