"""The devices of a run as the bench composes them from the world: the OS0-64 lidar
(:mod:`.lidar`: the lidar run, frames to packets, paced onto UDP through the frame ring of
:mod:`._ring` and the sender of :mod:`._sender`, rendered by the forked renderers of
:mod:`._renderers`, always on with the standing machine of :mod:`._standing`), the offline
pcap writer (:mod:`.offline`: ``tcf-hil lidar pcap``), the sensor as a client meets a real
one (:mod:`.sensor_service`: its HTTP API, re-initialised on request), the harvester's
CANopen node (:mod:`.harvester`), the
log of the faults injected into both (:mod:`.faults`), the endpoints a run owns
(:mod:`.endpoints`: loopback hosts, ports, the CAN bus) and a track's render made by a Dask
cluster's workers (:mod:`.dask_render`).

The wire itself (packets, sockets, the CANopen node) is :mod:`emulators`; this package feeds
them the world. May import :mod:`protocols`, :mod:`emulators`, the scenario, :mod:`tcf_hil.world`,
:mod:`tcf_hil.recording` (the writers) and the small shared helpers; never a run, the
evaluation or the results.
"""
