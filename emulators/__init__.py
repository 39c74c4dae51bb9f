"""Things that talk on the wire (the OS0-64 lidar, the harvester's CANopen node).

Public here: `lidar`, `harvester`, `canbus`, `faults`, `pacing` (the one pacer of live and
replayed streams), and the compiled-kernel helpers `jit` (numba, optional) and `embree`
(Embree bound for kernels, optional).
"""
