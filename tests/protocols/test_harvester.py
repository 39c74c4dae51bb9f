"""The CANopen pose profile: EDS and DBC agree with the object dictionary (as canopen and
cantools read them), the shipped files are what the renderers make, and the codecs round-trip
within quantisation for any pose; any bytes decode to a value or the documented error."""

from __future__ import annotations

import math

import canopen
import cantools
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocols.harvester import (
    HARVESTER_OD,
    POSE,
    CanProtocolError,
    PdoLengthError,
    Pose,
    PoseAssembler,
    PoseRangeError,
    Record,
    Variable,
    dbc_path,
    decode_pdo,
    decode_time,
    eds_path,
    encode_pdo,
    encode_pose,
    encode_time,
    pose_to_raw,
    render_dbc,
    render_eds,
    unwrap_time_us,
)

ALL_VARS = [v for o in HARVESTER_OD.objects
            for v in (o.entries if isinstance(o, Record) else (o,))]

poses = st.builds(
    Pose,
    x_m=st.floats(-2_000_000, 2_000_000), y_m=st.floats(-2_000_000, 2_000_000),
    z_m=st.floats(-10_000, 10_000), heading_deg=st.floats(-720, 720),
    pitch_deg=st.floats(-179.9, 179.9), roll_deg=st.floats(-179.9, 179.9),
    speed_m_s=st.floats(-32, 32), time_us=st.integers(0, 2**40),
    status=st.integers(0, 0xFFFF))


def _angle_diff(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def test_shipped_files_are_what_the_renderers_make() -> None:
    assert eds_path().read_text() == render_eds(HARVESTER_OD)
    assert dbc_path().read_text() == render_dbc(10)


@pytest.mark.parametrize("node_id", [1, 10, 127])
def test_canopen_reads_the_eds_as_the_object_dictionary_says(node_id: int) -> None:
    od = canopen.import_od(str(eds_path()), node_id)
    for v in ALL_VARS:
        obj = od[v.index]
        var = obj if isinstance(obj, canopen.objectdictionary.ODVariable) else obj[v.subindex]
        assert var.data_type == int(v.dtype), (hex(v.index), v.subindex)
        assert var.access_type == v.access
        assert var.pdo_mappable == v.pdo
        assert var.factor == v.factor
        assert var.unit == v.unit
    for m in HARVESTER_OD.tpdos:
        assert od[0x1800 + m.number - 1][1].default == m.cob_id(node_id)
        assert od[0x1800 + m.number - 1][2].default == m.trans_type
        mp = od[0x1A00 + m.number - 1]
        assert mp[0].default == len(m.variables)
        codes = [mp[i].default for i in range(1, len(m.variables) + 1)]
        assert [(c >> 16, (c >> 8) & 0xFF) for c in codes] == list(m.variables)
        assert [c & 0xFF for c in codes] == [HARVESTER_OD.var(*k).dtype.bits
                                            for k in m.variables]


@given(poses)
@settings(max_examples=200, deadline=None)
def test_codec_round_trips_within_quantisation(p: Pose) -> None:
    frames = encode_pose(p, 10)
    asm = PoseAssembler(10)
    out = [asm.feed(cob, data) for cob, data in frames]
    assert out[:-1] == [None] * (len(frames) - 1)
    q = out[-1]
    assert q is not None
    for a, b in ((q.x_m, p.x_m), (q.y_m, p.y_m), (q.z_m, p.z_m), (q.speed_m_s, p.speed_m_s)):
        assert abs(a - b) <= 0.0005 + 1e-9
    for a, b in ((q.heading_deg, p.heading_deg), (q.pitch_deg, p.pitch_deg),
                 (q.roll_deg, p.roll_deg)):
        assert _angle_diff(a, b) <= 0.005 + 1e-9
    assert 0 <= q.heading_deg < 360
    assert q.time_us == p.time_us % 2**32


@given(poses)
@settings(max_examples=100, deadline=None)
def test_cantools_decodes_our_frames_as_our_codec_does(p: Pose) -> None:
    db = cantools.database.load_string(render_dbc(10), "dbc")
    raw = pose_to_raw(p)
    for m in HARVESTER_OD.tpdos:
        data = encode_pdo(m, raw)
        decoded = db.decode_message(m.cob_id(10), data, decode_choices=False)
        for (idx, sub) in m.variables:
            v = HARVESTER_OD.var(idx, sub)
            assert decoded[v.name] == pytest.approx(raw[(idx, sub)] * v.factor, abs=1e-9)


def test_dbc_describes_heartbeat_time_and_nmt() -> None:
    db = cantools.database.load_string(render_dbc(42), "dbc")
    hb = db.get_message_by_frame_id(0x700 + 42)
    assert hb.decode(bytes([5]))["NMT_State"] == "OPERATIONAL"
    t = db.decode_message(0x100, encode_time(1_767_225_600_123))  # 2026-01-01T00:00:00.123Z
    assert t["Ms_After_Midnight"] == 123
    assert t["Days_Since_1984"] == (1_767_225_600_123 // 86_400_000) - 5113
    assert {m.frame_id for m in db.messages} >= {0x180 + 42, 0x280 + 42, 0x380 + 42, 0x480 + 42}
    with pytest.raises(ValueError, match="node id"):
        render_dbc(0)


def test_time_of_day_round_trips_and_rejects_garbage() -> None:
    for ms in (441_763_200_000, 1_767_225_600_123, 1_767_311_999_999):
        assert decode_time(encode_time(ms)) == ms
    with pytest.raises(PdoLengthError):
        decode_time(b"\x00" * 5)
    with pytest.raises(CanProtocolError, match="beyond one day"):
        decode_time((86_400_000).to_bytes(4, "little") + b"\x00\x00")
    with pytest.raises(CanProtocolError):
        encode_time(0)  # 1970 is before the CANopen epoch


def test_positions_beyond_int32_millimetres_ask_for_a_datum() -> None:
    p = Pose(0.0, 6_900_000.0, 0.0, 0, 0, 0, 0, 0)
    with pytest.raises(PoseRangeError, match="datum"):
        encode_pose(p, 10)
    with pytest.raises(PoseRangeError, match="finite"):
        encode_pose(Pose(math.nan, 0, 0, 0, 0, 0, 0, 0), 10)


def test_time_stamps_unwrap_across_the_32_bit_wrap() -> None:
    assert unwrap_time_us(5, 2**32 - 10) == 2**32 + 5
    assert unwrap_time_us(2**32 - 10, 2**32 + 5) == 2**32 - 10
    assert unwrap_time_us(123, None) == 123
    asm = PoseAssembler(10)
    full = []
    for t in (2**32 - 20_000, 2**32 - 10_000, 2**32, 2**32 + 10_000):
        frames = encode_pose(Pose(0, 0, 0, 0, 0, 0, 0, t), 10)
        full += [p.time_us for c, d in frames if (p := asm.feed(c, d)) is not None]
    assert full == [2**32 - 20_000, 2**32 - 10_000, 2**32, 2**32 + 10_000]


def test_status_comes_from_the_event_tpdo() -> None:
    asm = PoseAssembler(10)
    ev = encode_pose(Pose(0, 0, 0, 0, 0, 0, 0, 77, status=0x0207), 10, synchronous=False)
    assert [c for c, _ in ev] == [0x48A]
    assert asm.feed(*ev[0]) is None
    frames = encode_pose(Pose(1, 2, 3, 4, 5, 6, 0.5, 78), 10)
    got = [p for c, d in frames if (p := asm.feed(c, d)) is not None]
    assert got[0].status == 0x0207 and got[0].x_m == 1.0


@given(st.integers(0, 0x7FF), st.binary(max_size=8))
@settings(max_examples=300, deadline=None)
def test_any_frame_gives_a_value_or_the_documented_error(cob: int, data: bytes) -> None:
    asm = PoseAssembler(10)
    try:
        asm.feed(cob, data)
    except CanProtocolError:
        pass
    for m in HARVESTER_OD.tpdos:
        try:
            vals = decode_pdo(m, data)
        except PdoLengthError:
            continue
        assert encode_pdo(m, vals) == data  # every bit pattern is a value, and back
    try:
        decode_time(data)
    except CanProtocolError:
        pass


def test_variables_know_their_limits() -> None:
    assert Variable(POSE, 1, "X", HARVESTER_OD.var(POSE, 1).dtype).limits == (-2**31, 2**31 - 1)
    assert HARVESTER_OD.var(POSE, 4).limits == (0, 65535)
