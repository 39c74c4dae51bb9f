"""Things that talk on the wire (the OS0-64 lidar, the harvester's CANopen node).

Empty until the Ouster and CAN issues land; the package exists so the layout is fixed.
"""
