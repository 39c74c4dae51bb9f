"""Render the object dictionary as an EDS (CiA 306) that canopen, CANopen tools and the
harvester's own node load. COB-IDs are written ``$NODEID+0x180`` so one file serves every node
id. ``Factor`` and ``Unit`` are python-canopen's extensions (``.phys`` in m, deg, m/s)."""

from __future__ import annotations

from protocols.harvester._od import (
    DataType,
    ObjectDictionary,
    Variable,
)


def _value(v: Variable) -> str:
    if v.default_text:
        return v.default_text
    if v.dtype is DataType.VISIBLE_STRING:
        return str(v.default)
    n = int(v.default)
    return f"0x{n:X}" if not v.dtype.signed and n > 9 else str(n)


def _var_lines(section: str, v: Variable) -> list[str]:
    lines = [f"[{section}]", f"ParameterName={v.name}", "ObjectType=0x7",
             f"DataType=0x{int(v.dtype):04X}", f"AccessType={v.access}",
             f"DefaultValue={_value(v)}", f"PDOMapping={int(v.pdo)}"]
    if v.factor != 1.0:
        lines.append(f"Factor={v.factor!r}")
    if v.unit:
        lines.append(f"Unit={v.unit}")
    if v.description:
        lines.append(f"Description={v.description}")
    return [*lines, ""]


def render_eds(od: ObjectDictionary, *, file_name: str = "harvester.eds") -> str:
    """The EDS text (``\\n`` line ends, deterministic: no dates from the clock)."""
    mandatory = [o for o in od.objects if o.index in (0x1000, 0x1001, 0x1018)]
    optional = [o for o in od.objects if 0x1000 <= o.index < 0x2000 and o not in mandatory]
    manufacturer = [o for o in od.objects if o.index >= 0x2000]
    out = [
        "[FileInfo]", f"FileName={file_name}", "FileVersion=1", "FileRevision=0",
        "EDSVersion=4.0", f"Description={od.device_name}: machine pose (CANopen pose profile)",
        "CreatedBy=tcf-hil", "CreationDate=01-01-2026", "CreationTime=12:00AM", "",
        "[DeviceInfo]", "VendorName=tcf-hil", f"VendorNumber=0x{od.vendor_id:X}",
        f"ProductName={od.device_name}", f"ProductNumber=0x{od.product_code:X}",
        f"RevisionNumber=0x{od.revision:X}", "OrderCode=tcf-hil-harvester",
        *(f"BaudRate_{r}=1" for r in (125, 250, 500, 1000)),
        "SimpleBootUpMaster=0", "SimpleBootUpSlave=1", "Granularity=8",
        "DynamicChannelsSupported=0", "GroupMessaging=0", "NrOfRXPDO=0",
        f"NrOfTXPDO={len(od.tpdos)}", "LSS_Supported=0", "",
        "[DummyUsage]", *(f"Dummy000{i}=0" for i in range(1, 8)), "",
    ]
    for title, objs in (("MandatoryObjects", mandatory), ("OptionalObjects", optional),
                        ("ManufacturerObjects", manufacturer)):
        out += [f"[{title}]", f"SupportedObjects={len(objs)}"]
        out += [f"{n}=0x{o.index:04X}" for n, o in enumerate(objs, 1)]
        out.append("")
        for o in objs:
            if isinstance(o, Variable):
                out += _var_lines(f"{o.index:04X}", o)
                continue
            out += [f"[{o.index:04X}]", f"ParameterName={o.name}", "ObjectType=0x9",
                    f"SubNumber={len(o.entries) + 1}", ""]
            if o.count is None:
                sub0 = Variable(o.index, 0, "Highest sub-index supported", DataType.UNSIGNED8,
                                "const", max(e.subindex for e in o.entries))
            else:
                sub0 = Variable(o.index, 0, "Number of mapped objects", DataType.UNSIGNED8,
                                "rw", o.count)
            out += _var_lines(f"{o.index:04X}sub0", sub0)
            for e in o.entries:
                out += _var_lines(f"{o.index:04X}sub{e.subindex:X}", e)
    return "\n".join(out)

