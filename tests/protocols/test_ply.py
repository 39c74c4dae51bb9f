"""PLY encoding: read back by trimesh (an independent reader), float64 kept, errors clear."""

from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from protocols.ply import PlyError, encode_ply


@settings(max_examples=40, deadline=None)
@given(st.integers(3, 60), st.integers(0, 80), st.integers(0, 2**31 - 1))
def test_trimesh_reads_what_we_write(nv: int, nf: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    v = rng.uniform(-1, 1, (nv, 3)) + [500_000.0, 6_900_000.0, 100.0]
    f = rng.integers(0, nv, (nf, 3))
    ids = rng.integers(-5, 10**6, nf).astype(np.int32)
    data = encode_ply(v, f, {"stem_id": ids}, comments=["test"])
    m = trimesh.load(io.BytesIO(data), file_type="ply", process=False)
    np.testing.assert_array_equal(m.vertices, v)
    if nf:
        np.testing.assert_array_equal(m.faces, f)
        raw = m.metadata["_ply_raw"]["face"]["data"]
        np.testing.assert_array_equal(raw["stem_id"].ravel(), ids)


def test_errors_name_the_problem() -> None:
    v = np.zeros((3, 3))
    with pytest.raises(PlyError, match=r"\(m, 3\)"):
        encode_ply(v, np.zeros((1, 4), dtype=int))
    with pytest.raises(PlyError, match="indices must lie"):
        encode_ply(v, np.array([[0, 1, 3]]))
    with pytest.raises(PlyError, match="must be \\(1,\\)"):
        encode_ply(v, np.array([[0, 1, 2]]), {"stem_id": np.zeros(2, dtype=int)})
    with pytest.raises(PlyError, match="vertices must be"):
        encode_ply(np.zeros((3, 2)), np.array([[0, 1, 2]]))
