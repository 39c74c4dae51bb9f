"""PLY (binary little-endian) encoding of triangle meshes, vectorised.

Vertices as float64 (no loss at UTM-sized coordinates), faces as a uchar count plus three
int32 indices, and any number of int32 face properties (e.g. ``stem_id``). One packed numpy
record array per element, written with a single ``tobytes``: plyfile writes list properties
row by row in Python, which costs seconds per million faces.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

__all__ = ["PlyError", "encode_ply", "ply_vertex_header"]


class PlyError(ValueError):
    """The mesh cannot be written as asked (shapes, names)."""


def encode_ply(vertices: NDArray[np.floating], faces: NDArray[np.integer],
               face_properties: Mapping[str, NDArray[np.integer]] | None = None,
               comments: Sequence[str] = ()) -> bytes:
    """Encode a triangle mesh as binary little-endian PLY.

    Args:
        vertices: (n, 3) coordinates, written as float64 ``double x, y, z``.
        faces: (m, 3) vertex indices, written as ``list uchar int vertex_indices``.
        face_properties: name -> (m,) integers, written as ``int`` face properties.
        comments: header comment lines.
    """
    v = np.asarray(vertices, dtype="<f8")
    f = np.asarray(faces)
    props = dict(face_properties or {})
    if v.ndim != 2 or v.shape[1] != 3:
        raise PlyError(f"vertices must be (n, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise PlyError(f"faces must be (m, 3) triangles, got {f.shape}")
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise PlyError(f"face indices must lie in [0, {len(v)}), got [{f.min()}, {f.max()}]")
    for name, arr in props.items():
        if not name.isidentifier() or name == "vertex_indices":
            raise PlyError(f"bad face property name {name!r}")
        if np.shape(arr) != (len(f),):
            raise PlyError(f"face property {name!r} must be ({len(f)},), got {np.shape(arr)}")
    lines = ["ply", "format binary_little_endian 1.0",
             *(f"comment {c}" for c in comments),
             f"element vertex {len(v)}", "property double x", "property double y",
             "property double z", f"element face {len(f)}",
             "property list uchar int vertex_indices",
             *(f"property int {name}" for name in props), "end_header"]
    rec = np.empty(len(f), dtype=np.dtype([("n", "u1"), ("idx", "<i4", (3,)),
                                           *[(k, "<i4") for k in props]]))
    rec["n"] = 3
    rec["idx"] = f
    for k, arr in props.items():
        rec[k] = arr
    return ("\n".join(lines) + "\n").encode("ascii") + v.tobytes() + rec.tobytes()


_PLY_TYPES = {"<f8": "double", "<f4": "float", "|u1": "uchar", "|i1": "char", "<u2": "ushort",
              "<i2": "short", "<u4": "uint", "<i4": "int"}


def ply_vertex_header(dtype: np.dtype[np.void], count: int,
                      comments: Sequence[str] = ()) -> bytes:
    """The header of a binary little-endian PLY point cloud: one ``vertex`` element of
    ``count`` records of the structured ``dtype`` (packed; what ``records.tobytes()``
    writes), for a writer that streams the body and learns the count at the end."""
    lines = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments),
             f"element vertex {count}"]
    for name in dtype.names or ():
        dt = dtype.fields[name][0] if dtype.fields else None
        kind = None if dt is None else _PLY_TYPES.get(dt.str)
        if kind is None:
            raise PlyError(f"vertex property {name!r} has unsupported dtype {dt}")
        if not name.isidentifier():
            raise PlyError(f"vertex property name {name!r} is not a plain identifier")
        lines.append(f"property {kind} {name}")
    if any("\n" in c for c in comments):
        raise PlyError("a comment holds a line break")
    return ("\n".join([*lines, "end_header"]) + "\n").encode("ascii")
