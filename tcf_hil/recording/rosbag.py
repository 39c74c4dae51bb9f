"""ROS 2 bags (rosbag2: MCAP or SQLite storage, read with the ``rosbags`` library, no ROS
install) of an Ouster sensor as recordings to replay: a bag tcf-hil wrote
(:mod:`tcf_hil.results.rosbag`) or one ouster-ros recorded (its ``record.launch.xml``:
``/ouster/lidar_packets``, ``/ouster/imu_packets``, ``/ouster/metadata``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tcf_hil.errors import InputError

__all__ = ["CAN_FRAME_MSG", "PACKET_MSG", "PACKET_TYPES", "bag_to_recording", "is_bag",
           "typestore"]

PACKET_MSG = "ouster_sensor_msgs/msg/PacketMsg"
#: what ouster-ros's packet message was called over its releases (ROS 2: ouster_msgs, then
#: ouster_sensor_msgs; the ROS 1 driver's ouster_ros/PacketMsg): a bag of any is read
PACKET_TYPES = (PACKET_MSG, "ouster_msgs/msg/PacketMsg", "ouster_ros/msg/PacketMsg")
CAN_FRAME_MSG = "can_msgs/msg/Frame"
_CAN_FRAME_DEF = ("std_msgs/Header header\nuint32 id\nbool is_rtr\nbool is_extended\n"
                  "bool is_error\nuint8 dlc\nuint8[8] data\n")  # ros2 can_msgs/msg/Frame


def typestore() -> Any:
    """ROS 2 Humble's message types with ouster-ros's packet and ``can_msgs``' frame."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name in PACKET_TYPES:
        types.update(get_types_from_msg("uint8[] buf\n", name))
    types.update(get_types_from_msg(_CAN_FRAME_DEF, CAN_FRAME_MSG))
    store.register(types)
    return store


def is_bag(path: Path) -> bool:
    """A rosbag2 folder (``metadata.yaml`` beside its storage files)."""
    return path.is_dir() and (path / "metadata.yaml").is_file()



def bag_to_recording(bag: Path, work: Path) -> tuple[Path, Path, Path | None]:
    """A rosbag2 folder of Ouster packets (one tcf-hil wrote, or ouster-ros recorded) as
    the files a replay reads, written into ``work``: ``lidar.pcap`` (every lidar and IMU
    packet at its bag time, from the sensor to the metadata's ports; 7502/7503 where it
    names none), ``metadata.json`` (the metadata topic's document) and ``can.log`` (the
    ``can_msgs/msg/Frame`` topic's frames, candump format; None without one)."""
    from rosbags.rosbag2 import Reader

    store = typestore()
    try:
        reader = Reader(bag)
        reader.open()
    except Exception as err:  # rosbags raises its own errors for a bag it cannot read
        raise InputError(str(bag), "metadata.yaml", f"not a readable rosbag2: {err}") from err
    try:
        return _written_out(bag, reader, store, work)
    except InputError:
        raise
    except Exception as err:  # rosbags' errors on a damaged bag or message
        first = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise InputError(str(bag), "", f"cannot be read: {first}") from err
    finally:
        reader.close()


def _written_out(bag: Path, reader: Any, store: Any, work: Path
                 ) -> tuple[Path, Path, Path | None]:
    from protocols.ouster import MetadataError, SensorMetadata
    from protocols.pcap import PcapWriter, UdpDatagram

    conns = reader.connections
    meta_c = [c for c in conns if c.msgtype == "std_msgs/msg/String"
              and c.topic.rstrip("/").endswith("metadata")]
    pkt_c = [c for c in conns if c.msgtype in PACKET_TYPES]
    if not meta_c or not pkt_c:
        raise InputError(str(bag), "", "no Ouster metadata topic (std_msgs/msg/String "
                         "ending in 'metadata') or no packet topic (ouster-ros's "
                         "PacketMsg): not a bag of an Ouster sensor")
    text = ""
    for c, _t, raw in reader.messages(connections=meta_c[:1]):
        text = store.deserialize_cdr(raw, c.msgtype).data
        break
    try:
        meta = SensorMetadata.loads(text)
    except MetadataError as err:
        raise InputError(str(bag), meta_c[0].topic, str(err)) from err
    lp, ip = meta.udp_port_lidar or 7502, meta.udp_port_imu or 7503
    if (lp, ip) != (meta.udp_port_lidar, meta.udp_port_imu):
        text = meta.with_changes(udp_port_lidar=lp, udp_port_imu=ip).dumps()
    work.mkdir(parents=True, exist_ok=True)
    (work / "metadata.json").write_text(text, encoding="utf-8")
    w = PcapWriter()
    dst = meta.udp_dest or "127.0.0.1"
    with open(work / "lidar.pcap", "wb") as out:
        out.write(w.header())
        for c, t, raw in reader.messages(connections=pkt_c):
            buf = bytes(store.deserialize_cdr(raw, c.msgtype).buf)
            port = ip if "imu" in c.topic else lp
            out.write(w.records(UdpDatagram(t, "169.254.0.1", dst, 7502, port, buf)))
    can_c = [c for c in conns if c.msgtype == CAN_FRAME_MSG]
    can_log = None
    if can_c:
        can_log = work / "can.log"
        with open(can_log, "w", encoding="ascii") as out:
            for c, t, raw in reader.messages(connections=can_c):
                f = store.deserialize_cdr(raw, c.msgtype)
                if f.is_error:
                    continue
                ident = f"{f.id:08X}" if f.is_extended else f"{f.id:03X}"
                body = "R" if f.is_rtr else bytes(f.data[:f.dlc]).hex().upper()
                out.write(f"({t // 10**9}.{t % 10**9 // 1000:06d}) "
                          f"{f.header.frame_id or 'can0'} {ident}#{body}\n")
    return work / "lidar.pcap", work / "metadata.json", can_log
