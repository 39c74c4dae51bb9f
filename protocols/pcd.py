"""Point Cloud Data (PCD v0.7) encoding and decoding, binary and ASCII.

The format that open3d, PCL and CloudCompare read. A cloud is a mapping of field name to a
1-D numpy array; all arrays share one length. Sans-IO: bytes in, bytes out.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

__all__ = ["PcdError", "decode_pcd", "encode_pcd", "pcd_header"]

_TYPES: dict[tuple[str, int], str] = {
    ("F", 4): "<f4", ("F", 8): "<f8", ("U", 1): "<u1", ("U", 2): "<u2", ("U", 4): "<u4",
    ("U", 8): "<u8", ("I", 1): "<i1", ("I", 2): "<i2", ("I", 4): "<i4", ("I", 8): "<i8",
}
_CODES = {np.dtype(v): k for k, v in _TYPES.items()}


class PcdError(ValueError):
    """A PCD document is malformed; the message says what was expected and what arrived."""


def _header(names: list[str], codes: list[tuple[str, int]], count: int, binary: bool,
            comments: Sequence[str] = ()) -> str:
    return "\n".join([
        "# .PCD v0.7 - Point Cloud Data file format",
        *(f"# {c}" for c in comments),
        "VERSION 0.7",
        "FIELDS " + " ".join(names),
        "SIZE " + " ".join(str(s) for _, s in codes),
        "TYPE " + " ".join(t for t, _ in codes),
        "COUNT " + " ".join("1" for _ in codes),
        f"WIDTH {count}",
        "HEIGHT 1",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {count}",
        "DATA binary" if binary else "DATA ascii",
    ]) + "\n"


def pcd_header(dtype: np.dtype[np.void], count: int, comments: Sequence[str] = ()) -> bytes:
    """The header of a binary PCD whose body is ``count`` records of the structured
    ``dtype`` (packed, little-endian: what ``records.tobytes()`` writes), for a writer that
    streams the body and learns the count at the end; ``comments`` as ``#`` lines."""
    codes = []
    names = list(dtype.names or ())
    for name in names:
        dt = dtype.fields[name][0] if dtype.fields else None
        if dt is None or dt.newbyteorder("<") not in _CODES or dt.byteorder == ">":
            raise PcdError(f"field {name!r} has unsupported dtype {dt}")
        if not name.isidentifier():
            raise PcdError(f"field name {name!r} is not a plain identifier")
        codes.append(_CODES[np.dtype(dt)])
    if not names:
        raise PcdError("a PCD cloud needs at least one field")
    if dtype.itemsize != sum(size for _, size in codes):
        raise PcdError(f"records of {dtype.itemsize} bytes are not packed")
    if any("\n" in c for c in comments):
        raise PcdError("a comment holds a line break")
    return _header(names, codes, count, True, comments).encode("ascii")


def encode_pcd(fields: Mapping[str, NDArray[np.generic]], *, binary: bool = True) -> bytes:
    """Encode named 1-D arrays as a PCD file (``DATA binary`` by default).

    Supported dtypes: float32/64, (u)int8/16/32/64. Field order is the mapping's order.
    """
    if not fields:
        raise PcdError("a PCD cloud needs at least one field")
    arrays = {k: np.asarray(v) for k, v in fields.items()}
    n = {len(v) for v in arrays.values()}
    if len(n) != 1:
        raise PcdError(f"fields differ in length: { {k: len(v) for k, v in arrays.items()} }")
    count = n.pop()
    codes = []
    for name, arr in arrays.items():
        if arr.ndim != 1:
            raise PcdError(f"field {name!r} must be 1-D, got shape {arr.shape}")
        if not name.isidentifier():
            raise PcdError(f"field name {name!r} is not a plain identifier")
        dt = arr.dtype.newbyteorder("<") if arr.dtype.byteorder == ">" else arr.dtype
        if np.dtype(dt) not in _CODES:
            raise PcdError(f"field {name!r} has unsupported dtype {arr.dtype}")
        codes.append(_CODES[np.dtype(dt)])
    header = _header(list(arrays), codes, count, binary)
    if binary:
        rec = np.empty(count, dtype=[(k, _TYPES[c]) for k, c in zip(arrays, codes, strict=True)])
        for k, v in arrays.items():
            rec[k] = v
        return header.encode("ascii") + rec.tobytes()
    cols = [np.char.mod("%.17g" if a.dtype.kind == "f" else "%d", a) for a in arrays.values()]
    lines = [" ".join(row) for row in zip(*cols, strict=True)] if count else []
    return (header + "".join(line + "\n" for line in lines)).encode("ascii")


def decode_pcd(data: bytes) -> dict[str, NDArray[np.generic]]:
    """Decode a PCD file (``DATA ascii`` or ``binary``) into named 1-D arrays.

    Raises:
        PcdError: on a malformed header, unsupported type or short data.
    """
    meta: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = data.find(b"\n", pos)
        if end < 0:
            raise PcdError("header ends before the DATA line")
        try:
            line = data[pos:end].decode("ascii").strip()
        except UnicodeDecodeError as err:
            raise PcdError(f"header line is not ASCII at byte {pos}") from err
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        meta[key.upper()] = vals
        if key.upper() == "DATA":
            break
    for key in ("FIELDS", "SIZE", "TYPE", "POINTS", "DATA"):
        if key not in meta:
            raise PcdError(f"header lacks {key}")
    names = meta["FIELDS"]
    counts = meta.get("COUNT", ["1"] * len(names))
    if not (len(names) == len(meta["SIZE"]) == len(meta["TYPE"]) == len(counts)):
        raise PcdError("FIELDS, SIZE, TYPE and COUNT differ in length")
    try:
        n = int(meta["POINTS"][0])
        sizes = [int(s) for s in meta["SIZE"]]
        cnts = [int(c) for c in counts]
    except (ValueError, IndexError) as err:
        raise PcdError(f"non-integer POINTS, SIZE or COUNT ({err})") from err
    if n < 0 or any(c != 1 for c in cnts):
        raise PcdError("only COUNT 1 fields and POINTS >= 0 are supported")
    dtypes = []
    for name, t, s in zip(names, meta["TYPE"], sizes, strict=True):
        if (t, s) not in _TYPES:
            raise PcdError(f"field {name!r}: unsupported TYPE {t} SIZE {s}")
        dtypes.append((name, _TYPES[(t, s)]))
    try:
        dt = np.dtype(dtypes)
    except (ValueError, TypeError) as err:
        raise PcdError(f"bad field list {names} ({err})") from err
    kind = meta["DATA"][0].lower() if meta["DATA"] else ""
    if kind == "binary":
        need = n * dt.itemsize
        if len(data) - pos < need:
            raise PcdError(f"binary data holds {len(data) - pos} bytes, {need} expected "
                           f"for {n} points")
        rec = np.frombuffer(data, dtype=dt, count=n, offset=pos)
        return {name: rec[name].copy() for name in names}
    if kind == "ascii":
        rows = data[pos:].decode("ascii", errors="replace").split()
        if len(rows) < n * len(names):
            raise PcdError(f"ascii data holds {len(rows)} values, {n * len(names)} expected")
        table = np.array(rows[: n * len(names)], dtype=object).reshape(n, len(names))
        out: dict[str, NDArray[np.generic]] = {}
        for k, name in enumerate(names):
            try:
                out[name] = table[:, k].astype(str).astype(dt[name])
            except (ValueError, OverflowError) as err:
                raise PcdError(f"ascii field {name!r} is not {dt[name]} ({err})") from err
        return out
    raise PcdError(f"DATA {kind!r} is not supported (ascii or binary expected)")
