"""The emulated Ouster OS0-64: per-column poses, ray casting through an injected scene, the
return model, what the sensor emits per frame (finished headers, IMU interleaved, faults),
and paced UDP sending of frames encoded with :mod:`protocols.ouster`."""

from typing import TYPE_CHECKING, Any

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

# The sensor model is imported at once (a scenario's [sensor] table is it); the emulator,
# its HTTP API and the sender when first asked for: a CLI that only reads scenarios starts
# without them (http.server, the packet codecs).
_LAZY = {
    "SensorApi": "_http", "DensePoseSource": "_os0", "FastRayScene": "_os0",
    "FrameResult": "_os0", "Os0Emulator": "_os0", "PosePieces": "_os0",
    "PoseSource": "_os0", "RayScene": "_os0", "ReturnModel": "_os0",
    "carried_range_m": "_os0", "fast_scene": "_os0", "warm_up": "_os0",
    "IMU_PERIOD_NS": "_sensor", "ImuSource": "_sensor", "Os0Sensor": "_sensor",
    "SensorFrame": "_sensor", "Datagram": "_stream", "PacedSender": "_stream",
    "Route": "_stream", "SendStats": "_stream",
}

if TYPE_CHECKING:
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
    from emulators.lidar._sensor import IMU_PERIOD_NS, ImuSource, Os0Sensor, SensorFrame
    from emulators.lidar._stream import Datagram, PacedSender, Route, SendStats


def __getattr__(name: str) -> Any:
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f"{__name__}.{mod}"), name)
    globals()[name] = value
    return value


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
