"""A run as an OSF file (Ouster's own recording format) written by ouster-sdk from the run's
capture: ``ouster-cli source FILE info``, ``... viz`` and ``... sensor_replay`` read it."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from tcf_hil._io import atomic_path
from tcf_hil.errors import InputError
from tcf_hil.recording.osf import ouster_sdk
from tcf_hil.recording.rundir import RunDir

__all__ = ["OsfResult", "write_osf"]


@dataclass(frozen=True)
class OsfResult:
    path: Path
    frames: int


def write_osf(run_dir: str | Path, out: str | Path,
              progress: Callable[[int, int], None] | None = None) -> OsfResult:
    """Every lidar frame of the run's ``lidar.pcap`` as ouster-sdk reads it (with the run's
    ``metadata.json``), saved into the OSF file ``out`` by ouster-sdk's own writer (written
    to a temporary name and renamed)."""
    osf = ouster_sdk()
    from ouster.sdk import pcap as opcap

    run = RunDir(run_dir).require(RunDir.LIDAR, RunDir.METADATA,
                                  missing="not a run directory with its lidar recorded")
    try:
        src = opcap.PcapFrameSetSource(str(run / RunDir.LIDAR),
                                       meta=[str(run / RunDir.METADATA)])
    except Exception as err:  # ouster-sdk's own errors
        raise InputError(str(run / RunDir.LIDAR), "", f"ouster-sdk cannot read it: "
                         f"{str(err).splitlines()[0] if str(err) else type(err).__name__}"
                         ) from err
    n = 0
    with atomic_path(Path(out)) as tmp:
        w = osf.Writer(str(tmp), src.sensor_info[0])
        try:
            for fs in src:
                fr = fs[0] if len(fs) else None
                if fr is None:
                    continue
                w.save(0, fr)
                n += 1
                if progress is not None:
                    progress(n, 0)
        finally:
            w.close()
    return OsfResult(Path(out), n)
