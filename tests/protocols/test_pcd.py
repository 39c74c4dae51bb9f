"""PCD codec: round trips (hypothesis), ASCII and binary, errors, and open3d reading ours."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from protocols.pcd import PcdError, decode_pcd, encode_pcd

DTYPES = [np.float32, np.float64, np.uint8, np.uint16, np.uint32, np.int32, np.int64]


@st.composite
def clouds(draw: st.DrawFn) -> dict[str, np.ndarray]:
    n = draw(st.integers(0, 40))
    k = draw(st.integers(1, 4))
    out = {}
    for i in range(k):
        dt = draw(st.sampled_from(DTYPES))
        elems = (st.floats(allow_nan=False, allow_infinity=False, width=32 if dt == np.float32
                           else 64) if np.dtype(dt).kind == "f" else None)
        out[f"f{i}"] = draw(hnp.arrays(dt, n, elements=elems))
    return out


@settings(max_examples=150, deadline=None)
@given(clouds(), st.booleans())
def test_round_trip(cloud: dict[str, np.ndarray], binary: bool) -> None:
    back = decode_pcd(encode_pcd(cloud, binary=binary))
    assert list(back) == list(cloud)
    for k, v in cloud.items():
        assert back[k].dtype == v.dtype
        np.testing.assert_array_equal(back[k], v)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=400))
def test_arbitrary_bytes_decode_or_raise_pcd_error(data: bytes) -> None:
    try:
        decode_pcd(data)
    except PcdError:
        pass


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=64), st.integers(0, 5))
def test_mutated_header_decodes_or_raises_pcd_error(junk: bytes, cut: int) -> None:
    good = encode_pcd({"x": np.arange(5.0), "y": np.arange(5.0)})
    head_end = good.index(b"DATA binary\n")
    for data in (good[: head_end - cut] + junk, good[:-cut - 1] if cut else good + junk):
        try:
            decode_pcd(data)
        except PcdError:
            pass


def test_errors_say_what_was_expected() -> None:
    good = encode_pcd({"x": np.arange(4.0)})
    with pytest.raises(PcdError, match="32 expected"):
        decode_pcd(good[:-4])
    with pytest.raises(PcdError, match="lacks FIELDS"):
        decode_pcd(b"VERSION 0.7\nPOINTS 1\nDATA ascii\n1\n")
    with pytest.raises(PcdError, match="differ in length"):
        encode_pcd({"x": np.zeros(2), "y": np.zeros(3)})
    with pytest.raises(PcdError, match="compressed"):
        decode_pcd(b"FIELDS x\nSIZE 4\nTYPE F\nCOUNT 1\nPOINTS 1\nDATA binary_compressed\n")


def test_open3d_reads_our_binary_pcd(tmp_path: Path) -> None:
    import open3d as o3d

    rng = np.random.default_rng(3)
    xyz = rng.uniform(-50, 50, (1000, 3)) + [500_000.0, 6_900_000.0, 120.0]
    ids = np.arange(1000, dtype=np.uint32)
    p = tmp_path / "cloud.pcd"
    p.write_bytes(encode_pcd({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "stem_id": ids}))
    pc = o3d.t.io.read_point_cloud(str(p))
    # float64 fields: exact even at UTM-sized coordinates, and the stem_id field comes along.
    np.testing.assert_array_equal(pc.point.positions.numpy(), xyz)
    np.testing.assert_array_equal(pc.point.stem_id.numpy().ravel(), ids)


def test_open3d_legacy_reader_reads_float32_pcd(tmp_path: Path) -> None:
    import open3d as o3d

    xyz = np.random.default_rng(4).uniform(-50, 50, (500, 3)).astype(np.float32)
    p = tmp_path / "cloud32.pcd"
    p.write_bytes(encode_pcd({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}))
    got = np.asarray(o3d.io.read_point_cloud(str(p)).points)
    np.testing.assert_array_equal(got, xyz.astype(np.float64))
