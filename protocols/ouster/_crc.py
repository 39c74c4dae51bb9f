"""CRC-64/XZ (ECMA-182 polynomial, reflected, init and xorout all ones), stdlib + numpy.

``crc64_xz(data)`` is a table-driven reference for one buffer. ``crc64_xz_rows(rows)``
computes the CRC of every row of an (n, L) uint8 array at once: the CRC is affine in the
message bits, so crc(m) = crc(0^L) XOR (XOR over positions i of T_i[m_i]), where T_i[b] is
the contribution of byte b at position i. The tables for one length are built once (256
entries per position) and a whole frame's packets then cost one gather and one XOR-reduce.
The emulator may pass a compiled CRC instead (fastcrc); both give the same values.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

_POLY = 0xC96C5795D7870F42  # reflected ECMA-182
_MASK = (1 << 64) - 1


def _byte_table() -> NDArray[np.uint64]:
    t = np.arange(256, dtype=np.uint64)
    poly = np.uint64(_POLY)
    for _ in range(8):
        t = np.where(t & np.uint64(1), (t >> np.uint64(1)) ^ poly, t >> np.uint64(1))
    return t


_TABLE = _byte_table()
_TABLE_PY = [int(v) for v in _TABLE]


def crc64_xz(data: bytes | bytearray | memoryview) -> int:
    """CRC-64/XZ of ``data`` (check value of b"123456789" is 0x995DC9BBDF1939FA)."""
    crc = _MASK
    t = _TABLE_PY
    for b in bytes(data):
        crc = (crc >> 8) ^ t[(crc ^ b) & 0xFF]
    return crc ^ _MASK


@lru_cache(maxsize=6)
def _position_tables(length: int) -> tuple[NDArray[np.uint64], int]:
    """(T of shape (length * 256,), crc of ``length`` zero bytes)."""
    tables = np.empty((length, 256), dtype=np.uint64)
    # Linear part: contribution of byte b at the last position, then shifted back through
    # one zero byte per position (x -> (x >> 8) ^ TABLE[x & 0xff]).
    cur = _TABLE[np.arange(256)].copy()  # raw CRC register after the byte b, init 0
    tables[length - 1] = cur
    eight = np.uint64(8)
    ff = np.uint64(0xFF)
    for i in range(length - 2, -1, -1):
        cur = (cur >> eight) ^ _TABLE[(cur & ff).astype(np.intp)]
        tables[i] = cur
    zero = crc64_xz(bytes(length)) if length < 4096 else _zero_crc(length)
    return tables.reshape(-1), zero


def _zero_crc(length: int) -> int:
    crc = _MASK
    t = _TABLE_PY
    for _ in range(length):
        crc = (crc >> 8) ^ t[crc & 0xFF]
    return crc ^ _MASK


def crc64_xz_rows(rows: NDArray[np.uint8]) -> NDArray[np.uint64]:
    """CRC-64/XZ of every row of an (n, L) uint8 array, vectorised."""
    rows = np.ascontiguousarray(rows, dtype=np.uint8)
    n, length = rows.shape
    if length == 0:
        return np.zeros(n, dtype=np.uint64)
    tables, zero = _position_tables(length)
    idx = rows.astype(np.intp) + (np.arange(length, dtype=np.intp) * 256)[None, :]
    out: NDArray[np.uint64] = np.bitwise_xor.reduce(tables[idx], axis=1) ^ np.uint64(zero)
    return out
