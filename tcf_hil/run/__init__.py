"""A run: the program under test (a SIC) against traffic on the wire, recorded and scored.

One :class:`RunSession` serves every kind of run, its traffic opened from the run's source by
:func:`open_traffic`: ``tcf-hil run`` (:class:`LiveTraffic`:
the emulated OS0-64 and harvester on one clock), ``run --replay`` and ``replay``
(:class:`ReplayTraffic`: a recording sent again) and ``soak`` (a long live run). The
session owns the endpoints, supervises the SIC's process, records its publications, writes
the typed :class:`Manifest` and scores the result; a feature added there reaches them all.
The recorder's intake (:mod:`.recorder`) keeps what the SIC publishes; :mod:`.soak` is the
long live run.

May import everything below it (scenario, world, recording, evaluation, devices, results).
"""

from tcf_hil.run._figures import LiveFigures
from tcf_hil.run._live import RUN_T0_NS, LiveTraffic
from tcf_hil.run._manifest import Manifest, RunStatus, SicRecord
from tcf_hil.run._replay import ReplayTraffic, copy_recording
from tcf_hil.run._session import (
    RunResult,
    RunSession,
    Traffic,
    Wire,
    follow_redirects,
    udp_port_taken,
    wait_for_listener,
)
from tcf_hil.run._sic import (
    ENV_DOC,
    SicProcess,
    check_sic_command,
    sensor_url,
    sic_command,
    sic_environment,
    sic_reference_command,
)
from tcf_hil.run._traffic import open_traffic, replay_run, run_bridge

__all__ = ["ENV_DOC", "RUN_T0_NS", "LiveFigures", "LiveTraffic", "Manifest", "ReplayTraffic",
           "RunResult", "RunSession", "RunStatus", "SicProcess", "SicRecord", "Traffic", "Wire",
           "check_sic_command", "copy_recording", "follow_redirects", "open_traffic", "replay_run",
           "run_bridge", "sensor_url", "sic_command", "sic_environment",
           "sic_reference_command", "udp_port_taken", "wait_for_listener"]
