"""The emulated Ouster OS0-64: per-column poses, ray casting through an injected scene, the
return model, what the sensor emits per frame (finished headers, IMU interleaved, faults),
and paced UDP sending of frames encoded with :mod:`protocols.ouster`."""

from emulators.lidar._http import SensorApi
from emulators.lidar._os0 import (
    DensePoseSource,
    FastRayScene,
    FrameResult,
    Os0Emulator,
    PosePieces,
    PoseSource,
    RayScene,
    ReturnModel,
    carried_range_m,
    fast_scene,
    warm_up,
)
from emulators.lidar._physics import (
    DEFAULT_SENSOR,
    MATERIALS,
    SENSOR_PRESETS,
    SIGNAL_MULTIPLIERS,
    Physics,
    Reflectance,
    SensorModel,
    Surfaces,
)
from emulators.lidar._sensor import IMU_PERIOD_NS, ImuSource, Os0Sensor, SensorFrame
from emulators.lidar._stream import Datagram, PacedSender, Route, SendStats

__all__ = [
    "DEFAULT_SENSOR",
    "IMU_PERIOD_NS",
    "MATERIALS",
    "SENSOR_PRESETS",
    "SIGNAL_MULTIPLIERS",
    "Datagram",
    "DensePoseSource",
    "FastRayScene",
    "FrameResult",
    "ImuSource",
    "Os0Emulator",
    "Os0Sensor",
    "PacedSender",
    "Physics",
    "PosePieces",
    "PoseSource",
    "RayScene",
    "Reflectance",
    "ReturnModel",
    "Route",
    "SendStats",
    "SensorApi",
    "SensorFrame",
    "SensorModel",
    "Surfaces",
    "carried_range_m",
    "fast_scene",
    "warm_up",
]
