"""The program under test: its command line (placeholders filled from the endpoints), its
environment (the ``TCF_*`` variables), and its process, supervised in a process group of
its own with its output recorded."""

from __future__ import annotations

import contextlib
import os
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO, cast

from emulators.harvester import BusSpec
from emulators.lidar import SensorApi
from protocols.harvester import eds_path
from protocols.ouster import SensorMetadata
from tcf_hil.run.recorder import MAX_PUBLICATION_BYTES, Inbox

ENV_DOC: tuple[tuple[str, str], ...] = (
    ("TCF_RUN_DIR", "the run directory"),
    ("TCF_METADATA", "the sensor's metadata JSON file"),
    ("TCF_SENSOR_URL", "the sensor's HTTP API, http://HOST (port 80, as a real sensor's)"),
    ("TCF_SENSOR_HOST", "the sensor's own address: packets come from it, its API answers "
                        "on port 80 there (SensorFrameSetSource(HOST) works)"),
    ("TCF_LIDAR_BIND", "the address they go to (the metadata's udp_dest)"),
    ("TCF_LIDAR_PORT", "lidar UDP port"),
    ("TCF_IMU_PORT", "IMU UDP port"),
    ("TCF_CAN_SPEC", "the bus as tcf-hil writes it (socketcand:HOST:PORT:CHANNEL, ...)"),
    ("TCF_CAN_INTERFACE", "python-can interface (socketcand, socketcan, virtual)"),
    ("TCF_CAN_CHANNEL", "CAN channel (vcan0)"),
    ("TCF_CAN_HOST", "socketcand host (socketcand only)"),
    ("TCF_CAN_PORT", "socketcand port (socketcand only)"),
    ("TCF_CAN_NODE_ID", "the harvester's CANopen node id"),
    ("TCF_EDS", "the harvester node's EDS file"),
    ("TCF_PUBLISH_URL", "POST forests here (http://127.0.0.1:PORT/publish)"),
    ("TCF_PUBLISH_FILE", "or rewrite this file atomically with each forest"),
    ("TCF_PUBLISH", "where tcf-hil's reference SIC publishes (stdout unless set: "
                    "file:PATH or an http:// URL; yours may ignore it)"),
)

SIGTERM_WAIT_S = 15.0  # after --grace: SIGTERM, this long to publish and exit, then SIGKILL
_PLACEHOLDER = re.compile(r"\{([A-Za-z_][A-Za-z0-9_]*)\}")


def sic_command(command: str, env: dict[str, str], shell: bool) -> list[str] | str:
    """The COMMAND with ``{placeholders}`` (lower-case names of the TCF_ variables without
    the prefix, e.g. ``{lidar_port}``, and ``{python}``) filled in; other braces are left
    alone. Split without a shell unless asked.

    Raises:
        ValueError: an unknown placeholder, or an empty command.
    """
    values = {k[4:].lower(): v for k, v in env.items() if k.startswith("TCF_")}
    values["python"] = sys.executable

    def fill(s: str) -> str:
        def one(m: re.Match[str]) -> str:
            if m.group(1) not in values:
                raise ValueError(f"--sic {command!r}: unknown placeholder {m.group(0)}; "
                                 "known: " + ", ".join("{" + k + "}" for k in sorted(values)))
            return values[m.group(1)]
        return _PLACEHOLDER.sub(one, s)

    if shell:
        if not command.strip():
            raise ValueError("--sic: empty command")
        return fill(command)
    try:
        args = [fill(a) for a in shlex.split(command)]
    except ValueError as err:
        if "placeholder" in str(err):
            raise
        raise ValueError(f"--sic {command!r}: {err}") from err
    if not args:
        raise ValueError("--sic: empty command")
    return args


def check_sic_command(command: str, shell: bool) -> None:
    """Fail before anything starts when COMMAND cannot be filled in."""
    sic_command(command, {k: "x" for k, _ in ENV_DOC}, shell)


def sic_reference_command(preset: str = "field") -> str:
    """The reference SIC as an external program."""
    return f"{{python}} -m tcf_hil.sic --preset {preset}"


def sensor_url(api: SensorApi) -> str:
    """The API's base URL (no port when it is 80, as for a real sensor)."""
    h, p = cast(tuple[str, int], api.address[:2])
    return f"http://{h}" if p == 80 else f"http://{h}:{p}"


def sic_environment(out: Path, meta: SensorMetadata, metadata_path: Path, spec: BusSpec,
                    api: SensorApi, publish_url: str, node_id: int) -> dict[str, str]:
    """The SIC's environment: this process's, with every variable of :data:`ENV_DOC`."""
    env = dict(os.environ)
    env.update({
        "TCF_RUN_DIR": str(out.resolve()),
        "TCF_METADATA": str(metadata_path.resolve()),
        "TCF_SENSOR_URL": sensor_url(api),
        "TCF_SENSOR_HOST": str(api.address[0]),
        "TCF_LIDAR_BIND": meta.udp_dest,
        "TCF_LIDAR_PORT": str(meta.udp_port_lidar),
        "TCF_IMU_PORT": str(meta.udp_port_imu),
        "TCF_CAN_SPEC": str(spec),
        "TCF_CAN_INTERFACE": spec.interface,
        "TCF_CAN_CHANNEL": spec.channel,
        "TCF_CAN_HOST": spec.host,
        "TCF_CAN_PORT": str(spec.port or ""),
        "TCF_CAN_NODE_ID": str(node_id),
        "TCF_EDS": str(eds_path()),
        "TCF_PUBLISH_URL": publish_url,
        "TCF_PUBLISH_FILE": str((out / "sic" / "published.json").resolve()),
        "PYTHONUNBUFFERED": "1",
    })
    # the SIC's own --publish default is stdout; tcf-hil's reference SIC reads TCF_PUBLISH
    env.setdefault("TCF_PUBLISH", "stdout")
    return env


class SicProcess:
    """The SIC under test in a session (process group) of its own: stdout read line by line
    (NDJSON forests; other lines kept as its log), stderr straight to a file.

    Raises:
        OSError: the program cannot be started (the log files are closed again).
    """

    def __init__(self, argv: list[str] | str, env: dict[str, str], out: Path, inbox: Inbox,
                 shell: bool) -> None:
        self.stdout_log: IO[bytes] = open(out / "sic" / "stdout.log", "wb")
        self.stderr_log: IO[bytes] = open(out / "sic" / "stderr.log", "wb")
        self.inbox = inbox
        try:
            self.proc = subprocess.Popen(argv, shell=shell, env=env, stdin=subprocess.DEVNULL,
                                         stdout=subprocess.PIPE, stderr=self.stderr_log,
                                         start_new_session=True)
        except OSError:
            self.stdout_log.close()
            self.stderr_log.close()
            raise
        self.signalled: str | None = None  # the signal the bench had to send, if any
        self.published_before_signal: int | None = None  # publications when it was sent
        self.reader = threading.Thread(target=self._read, name="sic-stdout", daemon=True)
        self.reader.start()

    @property
    def pid(self) -> int:
        return self.proc.pid

    def _read(self) -> None:
        """Each stdout line that starts with ``{`` is a publication; a line longer than a
        publication may be is recorded as an invalid one (its start) and skipped to its end,
        so a runaway SIC cannot fill the bench's memory."""
        out = self.proc.stdout
        assert out is not None
        limit = MAX_PUBLICATION_BYTES + 1
        while line := out.readline(limit):
            self.stdout_log.write(line)
            too_long = len(line) == limit and not line.endswith(b"\n")
            while too_long and (rest := out.readline(limit)):  # the rest of that line
                self.stdout_log.write(rest)
                if rest.endswith(b"\n"):
                    break
            self.stdout_log.flush()
            s = line.strip()
            if s.startswith(b"{"):
                self.inbox.record(s, "stdout")
            elif s:
                self.inbox.non_json_lines += 1

    def poll(self) -> int | None:
        return self.proc.poll()

    def end(self, grace_s: float, stop: threading.Event | None = None) -> int:
        """Wait ``grace_s`` (or until ``stop``) for it to finish, then SIGTERM (its cue to
        publish and exit), then SIGKILL; then whatever is left of its process group."""
        deadline = time.monotonic() + grace_s
        while self.proc.poll() is None:
            if time.monotonic() >= deadline or (stop is not None and stop.is_set()):
                self._terminate()
                break
            time.sleep(0.05)
        self._end_group()
        return self.proc.wait()

    def _terminate(self) -> None:
        for sig, wait in ((signal.SIGTERM, SIGTERM_WAIT_S), (signal.SIGKILL, 5.0)):
            if self.published_before_signal is None:
                self.published_before_signal = len(self.inbox.valid)
            self.signalled = sig.name
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.proc.pid, sig)
            try:
                self.proc.wait(wait)
                return
            except subprocess.TimeoutExpired:
                continue

    def _end_group(self) -> None:
        """Children the SIC left behind (a wrapper script's, a shell's) go too."""
        for sig in (signal.SIGTERM, signal.SIGKILL):
            try:
                os.killpg(self.proc.pid, sig)
            except (ProcessLookupError, PermissionError):
                return
            time.sleep(0.2)

    def final_forest(self) -> bool | None:
        """Whether the SIC published its final forest. Where its latest valid forest says
        so (``"sic": {"final": true|false}``, as the reference SIC's does), that; else
        whether it exited by itself with code 0, or published after the bench's SIGTERM
        (its cue). False without a valid forest; None while it runs."""
        code = self.proc.poll()
        if code is None:
            return None
        valid = self.inbox.valid
        if not valid:
            return False
        sic = self.inbox.doc_of(valid[-1]).get("sic")
        if isinstance(sic, dict) and isinstance(sic.get("final"), bool):
            return bool(sic["final"])
        if self.signalled is None:
            return code == 0
        return len(valid) > (self.published_before_signal or 0)  # (after its cue)

    def close(self) -> None:
        self.end(0.0)
        self.reader.join(timeout=5.0)
        self.stdout_log.close()
        self.stderr_log.close()


def describe(argv: list[str] | str) -> str:
    """The command as it is run, for a person to read."""
    return argv if isinstance(argv, str) else shlex.join(argv)


__all__ = ["ENV_DOC", "SicProcess", "check_sic_command", "describe", "sensor_url",
           "sic_command", "sic_environment", "sic_reference_command"]
