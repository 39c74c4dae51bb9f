"""The harvester's CANopen pose profile (sans-IO): the object dictionary as data, the EDS and
DBC rendered from it, and pure codecs for the pose TPDOs, TIME, heartbeat and NMT frames.

``harvester.eds`` (node-id independent) and ``harvester.dbc`` (node 10) ship beside this file;
a test proves they equal what :func:`render_eds` and :func:`render_dbc` produce."""

from importlib import resources
from pathlib import Path

from protocols.harvester._codec import (
    TIME_WRAP_US,
    CanProtocolError,
    PdoLengthError,
    Pose,
    PoseAssembler,
    PoseRangeError,
    decode_pdo,
    decode_time,
    encode_pdo,
    encode_pose,
    encode_time,
    pose_to_raw,
    raw_to_pose,
    unwrap_time_us,
)
from protocols.harvester._dbc import render_dbc
from protocols.harvester._eds import render_eds
from protocols.harvester._od import (
    DATUM,
    HARVESTER_OD,
    HEARTBEAT_BASE,
    MOUNT,
    NMT_STATES,
    POSE,
    STATUS_MOVING,
    STATUS_PASS_SHIFT,
    STATUS_POSE_ERROR,
    STATUS_REVERSE,
    STATUS_VALID,
    SYNC_COB,
    TIME_COB,
    DataType,
    Mapping,
    ObjectDictionary,
    Record,
    Variable,
)

#: NMT command specifiers (first byte of COB-ID 0).
NMT_COMMANDS = {1: "OPERATIONAL", 2: "STOPPED", 128: "PRE-OPERATIONAL", 129: "RESET",
                130: "RESET COMMUNICATION"}


def eds_path() -> Path:
    """The packaged EDS (node-id independent)."""
    return Path(str(resources.files("protocols.harvester") / "harvester.eds"))


def dbc_path() -> Path:
    """The packaged DBC for node id 10 (render others with :func:`render_dbc`)."""
    return Path(str(resources.files("protocols.harvester") / "harvester.dbc"))


__all__ = [
    "DATUM", "HARVESTER_OD", "HEARTBEAT_BASE", "MOUNT", "NMT_COMMANDS", "NMT_STATES", "POSE",
    "STATUS_MOVING", "STATUS_PASS_SHIFT", "STATUS_POSE_ERROR", "STATUS_REVERSE", "STATUS_VALID",
    "SYNC_COB", "TIME_COB", "TIME_WRAP_US", "CanProtocolError", "DataType", "Mapping",
    "ObjectDictionary",
    "PdoLengthError", "Pose", "PoseAssembler", "PoseRangeError", "Record", "Variable",
    "dbc_path", "decode_pdo", "decode_time", "eds_path", "encode_pdo", "encode_pose",
    "encode_time", "pose_to_raw", "raw_to_pose", "render_dbc", "render_eds", "unwrap_time_us",
]
