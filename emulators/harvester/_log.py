"""Record every frame on a bus with python-can's own writers: candump log (``.log``, the
default: line-based and flushed per frame, so a crash leaves a valid file), or ASC / BLF by
suffix. ``python -m can.player FILE`` and ``can.LogReader`` read them back."""

from __future__ import annotations

import contextlib
import logging
import threading
from pathlib import Path
from typing import Any

import can

from emulators.harvester._bus import BusSpec, peer_closed

log = logging.getLogger("tcf_hil.harvester")

SUFFIXES = (".log", ".asc", ".blf")


def check_log_path(path: Path) -> None:
    """Raises ValueError unless ``path`` names a format we write (by its suffix)."""
    if path.suffix.lower() not in SUFFIXES:
        raise ValueError(f"CAN log {path}: expected a file ending in {', '.join(SUFFIXES)} "
                         f"(candump log, ASC, BLF), got {path.suffix or 'no suffix'!r}")


class CanLog(can.Listener):
    """A separate client on the bus (so it also sees the frames of this process's node) that
    writes every frame to ``path``. ``frames`` counts what was written."""

    def __init__(self, path: Path, spec: BusSpec | None = None, *, channel: str = "vcan0"
                 ) -> None:
        self.path = Path(path)
        check_log_path(self.path)
        self._channel = channel
        self._writer: Any = None  # made by start(), once the bus answers
        self._flush = self.path.suffix.lower() in (".log", ".asc")
        self.error: str | None = None  # why writing stopped (e.g. the disk is full)
        self._lock = threading.Lock()
        self.frames = 0
        self.spec = spec
        self.bus_errors = 0
        self.reconnects = 0
        self._bus: can.BusABC | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def start(self) -> CanLog:
        """Join the bus (if a spec was given), then create the file: a bus that is not there
        leaves any older log of that name untouched."""
        if self.spec is not None:
            self._bus = self.spec.open()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            kw = {"channel": self._channel} if self.path.suffix.lower() == ".log" else {}
            self._writer = can.Logger(str(self.path), **kw)
        except BaseException:
            if self._bus is not None:
                with contextlib.suppress(Exception):
                    self._bus.shutdown()
                self._bus = None
            raise
        if self.spec is not None:
            self._thread = threading.Thread(target=self._run, name=f"can-log {self.path.name}",
                                            daemon=True)
            self._thread.start()
        return self

    def _run(self) -> None:
        """Receive until stopped; a bus that fails is reported once and rejoined."""
        assert self.spec is not None
        while not self._stop.is_set():
            bus = self._bus
            try:
                if bus is None:
                    bus = self._bus = self.spec.open()
                    self.reconnects += 1
                    log.warning("CAN log %s: bus %s back", self.path, self.spec)
                msg = bus.recv(0.2)
                if msg is None and peer_closed(bus):
                    raise can.CanOperationError("connection closed by the server")
            except (can.CanError, OSError) as e:
                if bus is not None:
                    log.warning("CAN log %s: bus %s failed (%s); rejoining", self.path,
                                self.spec, e)
                    self.bus_errors += 1
                    with contextlib.suppress(Exception):
                        bus.shutdown()
                    self._bus = None
                self._stop.wait(0.2)
                continue
            if msg is not None:
                self.on_message_received(msg)

    def on_message_received(self, msg: can.Message) -> None:
        with self._lock:
            if self._writer is None:
                return
            try:
                self._writer.on_message_received(msg)
                if self._flush:
                    fh = getattr(self._writer, "file", None)
                    if fh is not None:
                        fh.flush()
            except (OSError, ValueError) as e:  # disk full, file gone: stop, say why
                self.error = f"{type(e).__name__}: {e}"
                log.error("CAN log %s: writing failed (%s); logging stopped", self.path, e)
                self._stop.set()
                with contextlib.suppress(Exception):
                    self._writer.stop()
                self._writer = None
                return
            self.frames += 1

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        if self._bus is not None:
            with contextlib.suppress(Exception):  # frames already received are written too
                while (msg := self._bus.recv(0)) is not None:
                    self.on_message_received(msg)
            with contextlib.suppress(Exception):
                self._bus.shutdown()
            self._bus = None
        with self._lock:
            if self._writer is not None:
                try:
                    self._writer.stop()
                except (OSError, ValueError) as e:
                    self.error = self.error or f"{type(e).__name__}: {e}"
                self._writer = None

    def __enter__(self) -> CanLog:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
