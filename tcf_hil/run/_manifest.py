"""What a run directory says about its run: ``manifest.json``, typed.

Written when the run starts (``"status": "running"``; from then on the directory is
replayable) and again when it ends, each time to a temporary name and renamed.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import enum
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from tcf_hil._io import write_json_atomic

FORMAT = 1  # manifest.json's "tcf_hil_run"


class RunStatus(enum.StrEnum):
    """How a run ended (``running`` until it has)."""

    RUNNING = "running"
    COMPLETE = "complete"  # the traffic ended and the SIC finished (or was ended after --grace)
    SIC_EXITED = "sic-exited"  # the SIC exited before the traffic ended
    SIC_FAILED = "sic-failed"  # it could not start, or exited with an error code
    CAN_CONFLICT = "can-conflict"  # a second node with the harvester's id on a joined bus
    INTERRUPTED = "interrupted"  # Ctrl-C / SIGTERM: the partial run is recorded and scored
    FAILED = "failed"  # the bench itself failed (the error is raised)


def versions() -> dict[str, str]:
    """Python's and the packages' versions that made the run."""
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": sys.version.split()[0]}
    for pkg in ("tcf-hil", "numpy", "scipy", "python-can", "canopen", "embreex", "trimesh"):
        with contextlib.suppress(PackageNotFoundError):
            out[pkg] = version(pkg)
    return out


def utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat()


@dataclass
class SicRecord:
    command: str
    shell: bool
    pid: int | None = None
    returncode: int | None = None
    ended_by: str | None = None  # the signal the bench had to send
    final_forest: bool | None = None  # whether it published its final forest (see SicProcess)


@dataclass
class Manifest:
    """``manifest.json``. Sections a run does not have (``None``) are left out of the file;
    ``stopped`` is always there (null while running)."""

    scenario: str | None
    seed: int | None
    mode: str | None
    profile: str | None
    speed: float
    sic: SicRecord | None
    can_node: dict[str, Any] | None  # what the harvester node answers by SDO
    started: str = field(default_factory=utc_now)
    stopped: str | None = None
    status: RunStatus = RunStatus.RUNNING
    message: str | None = None
    tcf_hil_run: int = FORMAT
    versions: dict[str, str] = field(default_factory=versions)
    replay_of: str | None = None  # the recorded run this one replays
    backend: str | None = None  # live runs: the ray backend
    lidar_pcap: bool | None = None  # live runs: whether lidar.pcap is kept
    frames_planned: int | None = None
    faults: dict[str, Any] | None = None
    endpoints: dict[str, str] | None = None  # the TCF_* variables the SIC got
    clock: dict[str, Any] | None = None  # sim_t0_ns, unix_ns_at_sim_t0, speed, lead_s
    sensor_redirects: list[dict[str, Any]] | None = None
    lidar: dict[str, Any] | None = None  # what the live sensor sent
    can: dict[str, Any] | None = None  # the live harvester node's figures
    replay_sent: dict[str, int] | None = None  # what a replay sent
    # a replay: the recording's time of its first event and the wall time it went out at,
    # and the replay's speed (the SIC's publications are on the wall clock)
    replay_clock: dict[str, Any] | None = None
    publications: dict[str, int] | None = None

    def to_dict(self) -> dict[str, Any]:
        return {k: v for k, v in asdict(self).items() if v is not None or k == "stopped"}

    def write(self, out: Path) -> None:
        write_json_atomic(out / "manifest.json", self.to_dict())

    def ended(self, status: RunStatus, message: str) -> None:
        self.status, self.message, self.stopped = status, message, utc_now()
