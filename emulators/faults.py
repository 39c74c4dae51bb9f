"""Faults injected on purpose: what the network and the bus do to a sensor's traffic in the
field, applied deterministically from a seed so a faulty run can be repeated exactly.

- :class:`UdpFaults` turns one frame's datagrams into what arrives: random loss, loss bursts
  (a Gilbert model: a burst starts with probability ``burst_rate`` per datagram and lasts
  ``burst_packets`` datagrams on average), duplicates, neighbours swapped, and jitter (each
  datagram leaves up to ``jitter_us`` later; a delayed one may be overtaken).
- :class:`LidarFaultPlan` says which whole frames are missing (random dropouts, dropouts at
  given times) and when the sensor re-initialises (a new init_id, frame_id from 0, and nothing
  sent for ``reinit_gap_ns``, as a real sensor after ``reinit``).
- :class:`CanFaultPlan` says what happens to the harvester node's frames: random loss,
  poses sent late, bus-off windows (silent, then EMCY "recovered from bus-off") and NMT
  reset commands from a second master.

Every fault becomes an event (a small dict with ``kind`` and the simulation time ``t_ns``)
handed to the caller, who logs it. Nothing here does I/O.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Protocol, TypeVar

import numpy as np

__all__ = ["CanFaultPlan", "FaultEvent", "LidarFaultPlan", "UdpFaults"]

FaultEvent = dict[str, Any]


class _Datagram(Protocol):
    @property
    def t_ns(self) -> int: ...

    @property
    def port(self) -> int: ...


D = TypeVar("D", bound=_Datagram)


@dataclass
class UdpFaults:
    """Per-datagram faults on the way from the sensor to the receiver.

    ``ports``: the destination ports the faults apply to (empty: all).
    """

    loss: float = 0.0
    burst_rate: float = 0.0
    burst_packets: float = 10.0
    duplicate: float = 0.0
    reorder: float = 0.0
    jitter_us: float = 0.0
    ports: tuple[int, ...] = ()
    seed: int = 0
    _rng: np.random.Generator = field(init=False, repr=False)
    _in_burst: bool = field(init=False, default=False, repr=False)

    def __post_init__(self) -> None:
        for name in ("loss", "burst_rate", "duplicate", "reorder"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"udp fault {name}: expected a probability 0..1, got {v}")
        if self.burst_packets < 1.0 or self.jitter_us < 0.0:
            raise ValueError("udp fault burst_packets: expected >= 1; jitter_us: >= 0")
        self._rng = np.random.default_rng([self.seed, 0x0D9])

    @property
    def active(self) -> bool:
        return any((self.loss, self.burst_rate, self.duplicate, self.reorder, self.jitter_us))

    def apply(self, dgs: Sequence[D], frame: int) -> tuple[list[D], list[FaultEvent]]:
        """What arrives of one frame's datagrams (in send order), and the events (one per
        kind of fault that struck this frame, with the datagram indices it struck)."""
        if not self.active or not dgs:
            return list(dgs), []
        n = len(dgs)
        rng = self._rng
        u = rng.random((n, 4))
        hit = np.ones(n, dtype=bool) if not self.ports else np.isin(
            np.fromiter((d.port for d in dgs), dtype=np.int64, count=n), self.ports)
        lost = (u[:, 0] < self.loss) & hit
        burst = np.zeros(n, dtype=bool)
        if self.burst_rate:
            leave = 1.0 / self.burst_packets
            b = self._in_burst
            for i in np.flatnonzero(hit).tolist():  # a short loop: only where faults apply
                b = (u[i, 1] >= leave) if b else (u[i, 1] < self.burst_rate)
                burst[i] = b
            self._in_burst = b
            burst &= ~lost
        dup = (u[:, 2] < self.duplicate) & hit & ~lost & ~burst
        swap = (u[:, 3] < self.reorder) & hit
        out: list[D] = []
        for i, d in enumerate(dgs):
            if lost[i] or burst[i]:
                continue
            out.append(d)
            if dup[i]:
                out.append(d)
        events: list[FaultEvent] = []
        t0 = int(dgs[0].t_ns)
        for kind, mask in (("udp_loss", lost), ("udp_burst_loss", burst),
                           ("udp_duplicate", dup)):
            if mask.any():
                events.append({"kind": kind, "t_ns": int(dgs[int(np.argmax(mask))].t_ns),
                               "frame": frame, "count": int(mask.sum()),
                               "datagrams": np.flatnonzero(mask).tolist()})
        # neighbours swap places; each keeps its slot's send time, so the schedule stays.
        # Swap decisions are drawn per original datagram and follow it (and its duplicate).
        want = [bool(swap[j]) for j in range(n) if not (lost[j] or burst[j])
                for _ in range(2 if dup[j] else 1)]
        times = [d.t_ns for d in out]
        swapped: list[int] = []
        i = 0
        while i < len(out) - 1:
            if want[i]:
                out[i], out[i + 1] = out[i + 1], out[i]
                swapped.append(i)
                i += 2
            else:
                i += 1
        out = [_at(d, t) for d, t in zip(out, times, strict=True)]
        if swapped:
            events.append({"kind": "udp_reorder", "t_ns": int(times[swapped[0]]),
                           "frame": frame, "count": len(swapped), "positions": swapped})
        if self.jitter_us and out:
            delay = (rng.random(len(out)) * self.jitter_us * 1000.0).astype(np.int64)
            if self.ports:
                delay[[d.port not in self.ports for d in out]] = 0
            out = [_at(d, int(d.t_ns) + int(x)) for d, x in zip(out, delay.tolist(),
                                                                strict=True)]
            order = sorted(range(len(out)), key=lambda j: out[j].t_ns)  # stable
            overtaken = sum(1 for a, b in itertools.pairwise(order) if b < a)
            out = [out[j] for j in order]
            events.append({"kind": "udp_jitter", "t_ns": t0, "frame": frame,
                           "count": int(np.count_nonzero(delay)),
                           "max_us": round(float(delay.max()) / 1000.0, 1),
                           "overtaken": overtaken})
        return out, events


def _at(d: D, t_ns: int) -> D:
    return d if d.t_ns == t_ns else replace(d, t_ns=t_ns)  # type: ignore[type-var]


@dataclass
class LidarFaultPlan:
    """Whole-frame faults of the sensor itself. Times are simulation ns."""

    dropout: float = 0.0  # probability that a frame is missing
    dropout_at_ns: tuple[int, ...] = ()
    dropout_frames: int = 1  # frames missing from each time in dropout_at_ns
    reinit_at_ns: tuple[int, ...] = ()
    reinit_gap_ns: int = 1_000_000_000
    seed: int = 0
    _rng: np.random.Generator = field(init=False, repr=False)
    _reinits_done: int = field(init=False, default=0, repr=False)

    def __post_init__(self) -> None:
        if not 0.0 <= self.dropout <= 1.0:
            raise ValueError(f"lidar fault dropout: expected 0..1, got {self.dropout}")
        self._rng = np.random.default_rng([self.seed, 0x11D])

    @property
    def active(self) -> bool:
        return bool(self.dropout or self.dropout_at_ns or self.reinit_at_ns)

    def frame(self, k: int, t_start_ns: int, period_ns: int) -> tuple[str, FaultEvent | None]:
        """What the sensor does with frame ``k`` starting at ``t_start_ns``: ``"send"``,
        ``"drop"`` (its lidar packets are missing), ``"reinit"`` (the first frame of a
        re-initialisation: a new init_id from here), or ``"silent"`` (inside a
        re-initialisation: nothing at all is sent)."""
        for i, t in enumerate(self.reinit_at_ns):
            if t <= t_start_ns < t + self.reinit_gap_ns:
                if i >= self._reinits_done:
                    self._reinits_done = i + 1
                    return "reinit", {"kind": "lidar_reinit", "t_ns": t_start_ns, "frame": k,
                                      "gap_s": self.reinit_gap_ns / 1e9}
                return "silent", None
        u = self._rng.random()  # drawn for every frame: a later change keeps earlier draws
        for t in self.dropout_at_ns:  # the frame under way at t and dropout_frames - 1 more
            if t_start_ns + period_ns > t and \
                    t_start_ns <= t + (self.dropout_frames - 1) * period_ns:
                return "drop", {"kind": "lidar_dropout", "t_ns": t_start_ns, "frame": k,
                                "cause": "scheduled"}
        if u < self.dropout:
            return "drop", {"kind": "lidar_dropout", "t_ns": t_start_ns, "frame": k,
                            "cause": "random"}
        return "send", None


def next_init_id(init_id: int) -> int:
    """The init_id after a re-initialisation (24 bits, never 0), as the sensor API does."""
    return (init_id * 1103515245 + 12345) % (1 << 24) or 1


@dataclass
class CanFaultPlan:
    """Faults of the harvester node's frames. Times are simulation ns."""

    loss: float = 0.0  # probability that a frame the node sends is lost
    pose_delay_ns: int = 0  # TPDOs leave this much after their SYNC
    bus_off_at_ns: tuple[int, ...] = ()
    bus_off_ns: int = 1_000_000_000
    nmt_reset_at_ns: tuple[int, ...] = ()
    nmt_restart_ns: int = 500_000_000  # the master starts the node again (0: never)
    seed: int = 0
    _rng: np.random.Generator = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not 0.0 <= self.loss <= 1.0:
            raise ValueError(f"can fault loss: expected 0..1, got {self.loss}")
        self._rng = np.random.default_rng([self.seed, 0xCA7])

    @property
    def active(self) -> bool:
        return bool(self.loss or self.pose_delay_ns or self.bus_off_at_ns
                    or self.nmt_reset_at_ns)

    def lose(self) -> bool:
        """Whether the next frame is lost (one draw per frame)."""
        return bool(self.loss) and bool(self._rng.random() < self.loss)

    def bus_off(self, t_ns: int) -> int | None:
        """The index of the bus-off window ``t_ns`` lies in, or None."""
        for i, t in enumerate(self.bus_off_at_ns):
            if t <= t_ns < t + self.bus_off_ns:
                return i
        return None
