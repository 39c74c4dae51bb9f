"""What a run puts on the wire, opened from its source (:func:`open_traffic`), and the two
entry points every command uses: a live run (:func:`run_bridge`) and a run on recorded
traffic (:func:`replay_run`), each a :class:`~tcf_hil.run.RunSession` driving that traffic."""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tcf_hil.evaluation import EvalConfig
from tcf_hil.run._figures import LiveFigures
from tcf_hil.run._live import LiveTraffic
from tcf_hil.run._replay import ReplayTraffic
from tcf_hil.run._session import Announce, RunResult, RunSession, Traffic, quiet
from tcf_hil.scenario import Scenario

__all__ = ["open_traffic", "replay_run", "run_bridge"]


def open_traffic(source: Scenario | str | Path, **options: Any) -> Traffic:
    """The traffic of a run from its source: a scenario drives the emulated OS0-64 and
    harvester live (:class:`~tcf_hil.run.LiveTraffic`); a path is a recording sent again,
    a tcf-hil run directory or a field recording (:class:`~tcf_hil.run.ReplayTraffic`).
    ``options`` go to that class."""
    if isinstance(source, Scenario):
        return LiveTraffic(source, **options)
    return ReplayTraffic(Path(source), **options)


def run_bridge(scn: Scenario, sic: str, out: Path, *, mode: str = "2048x10",
               profile: str = "RNG19_RFL8_SIG16_NIR16", seed: int | None = None,
               speed: float = 1.0, can: str = "own", shell: bool = False,
               sensor_ip: str | None = None, lead_s: float = 3.0, grace_s: float = 30.0,
               duration_s: float | None = None, backend: str = "auto",
               eval_cfg: EvalConfig | None = None, stop: threading.Event | None = None,
               announce: Announce = quiet, progress: Any = None, ready_s: float = 15.0,
               record_lidar: bool = True, on_start: Any = None,
               watch: Callable[[LiveFigures], None] | None = None,
               render: str = "auto") -> RunResult:
    """One live run of the program ``sic`` against ``scn`` into ``out``: a
    :class:`RunSession` driving :class:`LiveTraffic` (see both; ``render``: where the
    frames come from, :data:`tcf_hil.devices.lidar.RENDER_MODES`)."""
    traffic = open_traffic(scn, mode=mode, profile=profile, seed=seed, speed=speed,
                           lead_s=lead_s, duration_s=duration_s, backend=backend,
                           record_lidar=record_lidar, progress=progress, announce=announce,
                           render=render, standing_s=ready_s + lead_s + 2.0,
                           standing_after_s=grace_s + 10.0, halt=stop)
    return RunSession(traffic, sic, out, shell=shell, can=can, sensor_ip=sensor_ip,
                      grace_s=grace_s, ready_s=ready_s, stop=stop, announce=announce,
                      eval_cfg=eval_cfg, on_start=on_start, watch=watch).run()


def replay_run(src: Path, sic: str | None, out: Path | None, *, speed: float = 1.0,
               shell: bool = False, can_spec: str = "own", grace_s: float = 30.0,
               lead_s: float = 3.0, ready_s: float = 15.0, sensor_ip: str | None = None,
               http_port: int | None = 0, dest: str | None = None, loop: bool = False,
               stop: threading.Event | None = None, announce: Announce = quiet,
               eval_cfg: Any = None, meta: Path | None = None, can_log: Path | None = None,
               can_offset_s: float = 0.0, ports: tuple[int | None, int | None] = (None, None),
               progress: Callable[[int, int], None] | None = None,
               truth: Path | None = None,
               watch: Callable[[LiveFigures], None] | None = None) -> RunResult:
    """``tcf-hil run --replay SRC --sic COMMAND``: another SIC scored on recorded traffic
    (a run directory, or an Ouster pcap with ``meta`` and ``can_log``: see
    :class:`ReplayTraffic`). The new run directory holds the same recording (replayable in
    turn), this SIC's publications and score. With ``sic`` None (``tcf-hil replay``) the
    traffic alone; ``progress(bytes, of bytes)`` while the recording is checked."""
    traffic = open_traffic(src, speed=speed, loop=loop, dest=dest, lead_s=lead_s, meta=meta,
                           can_log=can_log, can_offset_s=can_offset_s, progress=progress,
                           ports=ports, truth=truth)
    return RunSession(traffic, sic, out, shell=shell, can=can_spec, sensor_ip=sensor_ip,
                      http_port=http_port, grace_s=grace_s, ready_s=ready_s, stop=stop,
                      announce=announce, eval_cfg=eval_cfg, watch=watch).run()
