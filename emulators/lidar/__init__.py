"""The emulated Ouster OS0-64: per-column poses, ray casting through an injected scene, the
return model, and paced UDP sending of frames encoded with :mod:`protocols.ouster`."""

from emulators.lidar._http import SensorApi
from emulators.lidar._os0 import (
    FrameResult,
    Os0Emulator,
    PoseSource,
    RayScene,
    ReturnModel,
    carried_range_m,
    warm_up,
)
from emulators.lidar._stream import Datagram, PacedSender, Route, SendStats

__all__ = ["Datagram", "FrameResult", "Os0Emulator", "PacedSender", "PoseSource", "RayScene",
           "ReturnModel", "Route", "SendStats", "SensorApi", "carried_range_m",
           "warm_up"]
