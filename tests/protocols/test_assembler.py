"""The sans-IO frame assembler (protocols.ouster.FrameAssembler) under hypothesis: packets in
any order within a frame's length, duplicated, dropped, with frame ids wrapping (16 bits, and
32 with the FUSA header) and the sensor restarting with a new init_id; and against
ouster-sdk's own batcher on a generated capture with a column window."""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from ouster.sdk import pcap as opcap

import protocols.ouster as o
from protocols.pcap import PcapWriter, UdpDatagram

LAYOUTS = [("LEGACY", None), ("RNG19_RFL8_SIG16_NIR16", None),
           ("FUSA_RNG15_RFL8_NIR8_DUAL", None), ("RNG19_RFL8_SIG16_NIR16_DUAL", "FUSA")]
C, W = 4, 32  # columns per packet, per frame: 8 packets a frame
PPF = W // C


def _fmt(profile: str, header: str | None) -> o.PacketFormat:
    return o.PacketFormat.create(profile, 8, C, W, header)


@cache
def _frame(profile: str, header: str | None, init_id: int, frame_id: int, tag: int
           ) -> np.ndarray:
    """A frame's packets whose RANGE tells frame and place apart."""
    fmt = _fmt(profile, header)
    rng = np.full((8, W), 8 * (tag * 100 + 1), np.uint32)
    rng += (np.arange(W) // C * 8).astype(np.uint32)[None, :]
    ts = np.arange(W, dtype=np.uint64) * 1000 + tag * 10**8
    return o.encode_lidar_frame(fmt, {"RANGE": rng}, ts, frame_id=frame_id,
                                init_id=init_id, prod_sn=12345)


@st.composite
def streams(draw: st.DrawFn) -> tuple[str, str | None, int, list[tuple[int, int, bool]],
                                      set[tuple[int, int]], int]:
    """(profile, header, first frame_id, arrivals (frame, place, is_copy), dropped, frames)."""
    profile, header = draw(st.sampled_from(LAYOUTS))
    modulus = _fmt(profile, header).frame_id_modulus
    n = draw(st.integers(1, 5))
    first = (modulus - draw(st.integers(0, 6))) % modulus  # near the wrap
    order = [(f, p) for f in range(n) for p in range(PPF)]
    dropped = {x for x in order if draw(st.integers(0, 9)) == 0}
    # reordered: each packet moves less than a frame's length
    keyed = [(i + draw(st.integers(0, PPF - 1)), i, x, False) for i, x in enumerate(order)
             if x not in dropped]
    copies = [(i + draw(st.integers(0, PPF - 1)), i, x, True) for i, x in enumerate(order)
              if x not in dropped and draw(st.integers(0, 7)) == 0]
    arrivals = [(f, p, dup) for _k, _i, (f, p), dup in sorted(keyed + copies)]
    return profile, header, first, arrivals, dropped, n


@settings(max_examples=300, deadline=None)
@given(streams())
def test_frames_come_out_whole_in_order_and_never_mixed(case) -> None:
    profile, header, first, arrivals, dropped, n = case
    fmt = _fmt(profile, header)
    fid = [(first + k) % fmt.frame_id_modulus for k in range(n)]
    a = o.FrameAssembler(fmt)
    out: list[o.AssembledFrame] = []
    for f, p, _dup in arrivals:
        out += a.feed(_frame(profile, header, 77, fid[f], f)[p].tobytes())
    out += a.flush()
    seen = [k for k in range(n) if any(f == k for f, _p, _d in arrivals)]
    assert [fr.frame_id for fr in out] == [fid[k] for k in seen]
    placed = 0
    for k, fr in zip(seen, out, strict=True):
        want = _frame(profile, header, 77, fid[k], k)
        assert np.array_equal(fr.packets, want[fr.places])  # never another frame's packet
        got = set(fr.places.tolist())
        assert got == {p for p in range(PPF) if (k, p) not in dropped}
        assert fr.complete == (len(got) == PPF)
        assert fr.init_id == (0 if profile == "LEGACY" else 77)
        placed += len(got)
    st_ = a.stats
    assert st_.packets == placed
    assert st_.duplicates + st_.late == sum(d for _f, _p, d in arrivals)
    assert st_.frames == len(out) and st_.incomplete == sum(not fr.complete for fr in out)
    assert st_.frames_lost == (seen[-1] - seen[0] + 1 - len(seen) if seen else 0)


@settings(max_examples=50, deadline=None)
@given(st.sampled_from(LAYOUTS[1:]), st.integers(1, 3), st.integers(1, 3))
def test_a_new_init_id_hands_on_the_open_frames_first(layout, n_old: int, n_new: int) -> None:
    profile, header = layout
    fmt = _fmt(profile, header)
    a = o.FrameAssembler(fmt)
    out: list[o.AssembledFrame] = []
    for k in range(n_old):  # the last old frame is cut short by the restart
        pk = _frame(profile, header, 5, 100 + k, k)
        for p in range(PPF if k < n_old - 1 else PPF // 2):
            out += a.feed(pk[p].tobytes())
    for k in range(n_new):
        pk = _frame(profile, header, 6, k, 10 + k)
        for p in range(PPF):
            out += a.feed(pk[p].tobytes())
    out += a.flush()
    assert [(f.init_id, f.frame_id, f.complete) for f in out] == (
        [(5, 100 + k, k < n_old - 1) for k in range(n_old)]
        + [(6, k, True) for k in range(n_new)])
    assert a.stats.restarts == 1


def test_other_traffic_and_columns_beyond_the_frame_are_counted_not_placed() -> None:
    fmt = _fmt("RNG19_RFL8_SIG16_NIR16", None)
    a = o.FrameAssembler(fmt)
    bad = _frame("RNG19_RFL8_SIG16_NIR16", None, 1, 1, 1)[0].copy()
    bad[32 + 8:32 + 10] = np.frombuffer(np.uint16(W).tobytes(), np.uint8)  # measurement_id W
    assert a.feed(b"x" * 48) == [] and a.feed(bad.tobytes()) == [] and a.flush() == []
    assert (a.stats.bad_size, a.stats.bad_place, a.stats.packets) == (1, 1, 0)


@pytest.mark.parametrize("window", [(1, 256), (370, 85), (0, 511)])
def test_column_windows_complete_as_ouster_sdk_says(tmp_path: Path, window) -> None:
    """A sensor with an azimuth window sends only the packets of its columns (real
    windowed captures in ouster-sdk's test data do): complete when they are all there."""
    m = o.os0_64_metadata("512x10", "RNG15_RFL8_NIR8",
                          column_window=None if window == (0, 511) else window)
    fmt = m.packet_format
    places = sorted(o.window_places(fmt, m.column_window))
    w = PcapWriter()
    chunks = [w.header()]
    a = o.FrameAssembler(fmt, column_window=m.column_window)
    ours = []
    for fid in (7, 8):
        ts = 10**9 + fid * 10**8 + np.arange(512, dtype=np.uint64) * 195_312
        arr = o.encode_lidar_frame(fmt, {"RANGE": np.full((64, 512), 8000, np.uint32)}, ts,
                                   frame_id=fid, init_id=m.init_id, prod_sn=m.prod_sn)
        keep = places if fid == 7 else places[:-1]  # the second frame lacks a packet
        for i in keep:
            chunks.append(w.records(UdpDatagram(int(ts[i * 16]), "127.0.0.1", "127.0.0.1",
                                                7502, 7502, arr[i].tobytes())))
            ours += a.feed(arr[i].tobytes())
    ours += a.flush()
    (tmp_path / "x.pcap").write_bytes(b"".join(chunks))
    (tmp_path / "x.json").write_text(m.dumps())
    src = opcap.PcapFrameSetSource(str(tmp_path / "x.pcap"), meta=[str(tmp_path / "x.json")])
    theirs = [(fs[0].frame_id, fs[0].complete()) for fs in src]
    assert [(f.frame_id, f.complete) for f in ours] == theirs == [(7, True), (8, False)]
