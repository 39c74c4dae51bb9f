"""The emulated Ouster OS0-64: per-column poses, ray casting through an injected scene, the
return model, and frames encoded with :mod:`protocols.ouster`."""

from emulators.lidar._os0 import FrameResult, Os0Emulator, PoseSource, RayScene, ReturnModel

__all__ = ["FrameResult", "Os0Emulator", "PoseSource", "RayScene", "ReturnModel"]
