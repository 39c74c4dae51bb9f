"""Render the same frames as a DBC for raw-frame tools (cantools, SavvyCAN): the pose TPDOs of
one node id, heartbeat, SYNC, TIME and NMT. Generated from the object dictionary, like the EDS,
so the two cannot disagree; the DBC does not know SDO or PDO remapping."""

from __future__ import annotations

import re

from protocols.harvester._od import (
    HARVESTER_OD,
    HEARTBEAT_BASE,
    NMT_STATES,
    SYNC_COB,
    TIME_COB,
    ObjectDictionary,
)

NODE = "HARVESTER"


def _ident(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]", "_", s)


def _num(x: float) -> str:
    return repr(float(x)).removesuffix(".0") if float(x).is_integer() else repr(float(x))


def render_dbc(node_id: int = 10, od: ObjectDictionary = HARVESTER_OD) -> str:
    if not 1 <= node_id <= 127:
        raise ValueError(f"node id: expected 1..127, got {node_id}")
    lines = ['VERSION "tcf-hil harvester"', "", "NS_ :", "", "BS_:", "", f"BU_: {NODE}", ""]
    comments = []
    for m in od.tpdos:
        layout = od.frame_layout(m)
        size = (layout[-1][1] + layout[-1][0].dtype.bits + 7) // 8
        cob = m.cob_id(node_id)
        lines.append(f"BO_ {cob} TPDO{m.number}: {size} {NODE}")
        for v, off in layout:
            lo, hi = v.limits
            sign = "-" if v.dtype.signed else "+"
            name = f"{_ident(v.name)}"
            lines.append(
                f" SG_ {name} : {off}|{v.dtype.bits}@1{sign} ({_num(v.factor)},0) "
                f"[{_num(lo * v.factor)}|{_num(hi * v.factor)}] \"{v.unit}\" Vector__XXX")
            if v.description:
                comments.append(f'CM_ SG_ {cob} {name} "{v.description}";')
        lines.append("")
    hb = HEARTBEAT_BASE + node_id
    lines += [f"BO_ {hb} Heartbeat: 1 {NODE}",
              ' SG_ NMT_State : 0|7@1+ (1,0) [0|127] "" Vector__XXX', "",
              f"BO_ {TIME_COB} TIME: 6 {NODE}",
              ' SG_ Ms_After_Midnight : 0|28@1+ (1,0) [0|86399999] "ms" Vector__XXX',
              ' SG_ Days_Since_1984 : 32|16@1+ (1,0) [0|65535] "d" Vector__XXX', "",
              f"BO_ {SYNC_COB} SYNC: 0 {NODE}", "",
              "BO_ 0 NMT: 2 Vector__XXX",
              ' SG_ Command : 0|8@1+ (1,0) [0|255] "" Vector__XXX',
              ' SG_ Node_ID : 8|8@1+ (1,0) [0|127] "" Vector__XXX', ""]
    lines += comments
    lines.append(f'CM_ BO_ {hb} "NMT state of the harvester node {node_id}";')
    lines.append("")
    states = " ".join(f'{k} "{v.replace("-", "_")}"' for k, v in sorted(NMT_STATES.items()))
    lines.append(f"VAL_ {hb} NMT_State {states} ;")
    lines.append('VAL_ 0 Command 1 "START" 2 "STOP" 128 "PRE_OPERATIONAL" 129 "RESET_NODE" '
                 '130 "RESET_COMMUNICATION" ;')
    return "\n".join(lines) + "\n"
