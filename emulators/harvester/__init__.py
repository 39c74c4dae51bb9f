"""The harvester on the CAN bus: a CANopen pose node (NMT, heartbeat, SYNC, TPDOs, TIME) on
any python-can transport, the simulation clock, bus specifications and CAN logs."""

from emulators.harvester._bus import (
    DEFAULT_SOCKETCAND_PORT,
    BusSpec,
    BusSpecError,
    kernel_has_vcan,
    parse_bus_spec,
    socketcand_answers,
)
from emulators.harvester._clock import RunClock, SimClock
from emulators.harvester._log import CanLog, check_log_path
from emulators.harvester._node import (
    HarvesterNode,
    NodeConfig,
    NodeStats,
    describe,
    node_id_in_use,
)

__all__ = [
    "DEFAULT_SOCKETCAND_PORT", "BusSpec", "BusSpecError", "CanLog", "HarvesterNode",
    "NodeConfig", "NodeStats", "RunClock", "SimClock", "check_log_path", "describe",
    "kernel_has_vcan",
    "node_id_in_use",
    "parse_bus_spec", "socketcand_answers",
]
