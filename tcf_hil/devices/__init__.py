"""The devices of a run as the bench composes them from the world: the OS0-64 lidar
(:mod:`.lidar`: frames to packets, to a pcap file or paced onto UDP through the frame ring
of :mod:`._ring`, and its HTTP API), the harvester's CANopen node (:mod:`.harvester`), the
log of the faults injected into both (:mod:`.faults`), the endpoints a run owns
(:mod:`.endpoints`: loopback hosts, ports, the CAN bus) and a track's render made by a Dask
cluster's workers (:mod:`.dask_render`).

The wire itself (packets, sockets, the CANopen node) is :mod:`emulators`; this package feeds
them the world. May import :mod:`protocols`, :mod:`emulators`, the scenario, :mod:`tcf_hil.world`,
:mod:`tcf_hil.recording` (the writers) and the small shared helpers; never a run, the
evaluation or the results.
"""
