"""The set of voxels a map tile holds: which of a frame's points fall in voxels the tile does
not hold yet (the first of each), at a cost that follows the frame, not the tile.

A tile beside the track holds millions of voxels and gains a few thousand a frame. Compiled
(numba), the set is an open-addressing hash table of the voxel keys (linear probing,
Fibonacci hashing, 40-75 % full): a frame's keys are looked up and inserted one after the
other, in the order they came, so the first of equal keys is the one kept. No add waits for
the table to grow: from 60 % full, the next table (half as big again) is zeroed 4 MiB at
each add; then the keys move into it a step at each add, both tables looked in until the
move ends.

Without compiled kernels (``TCF_HIL_NO_JIT``, numba missing) the same answers come from
sorted runs of keys, merged as they grow (a log-structured merge: numpy's sort and
searchsorted); the tests hold the two to the same masks.

Keys are int64 and never 0 (the map's voxel indices are offset to be positive); 0 marks an
empty slot."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from emulators.jit import jit_enabled, numba_module
from tcf_hil.sic._fast import run_starts, sorted_with_order

IntArray = NDArray[np.int64]

_FULL = 0.75  # the most a hash table is filled
_PREP = 0.6  # filled this much, the next table (half as big again) is made ready
_GROWTH = 1.5  # a table is between 40 and 75 % full: 11-20 bytes a key
_ZERO_STEP = 1 << 19  # slots of the next table zeroed at each add (4 MiB)
_FIB = 0x9E3779B97F4A7C15  # 2**64 / golden ratio: Knuth's multiplicative hash


def _find(table: Any, k: Any) -> Any:
    """The slot of key ``k`` in ``table``, or of the empty slot where it would go (linear
    probing from its home slot: the top 32 bits of its Fibonacci hash scaled to the size,
    Lemire's multiply-shift range reduction: any size, no division)."""
    size = table.shape[0]
    h = (np.uint64(k) * np.uint64(_FIB)) >> np.uint64(32)
    s: Any = np.int64((h * np.uint64(size)) >> np.uint64(32))
    while table[s] != 0 and table[s] != k:
        s += 1
        if s == size:
            s = 0
    return s


def insert_keys(table: Any, old: Any, keys: Any, new: Any) -> int:
    """Insert ``keys`` in order into ``table`` (0 = empty), setting ``new[i]`` where
    ``keys[i]`` was in neither ``table`` nor ``old`` (a table being moved into this one;
    size 1: none); returns how many were new."""
    added = 0
    for i in range(keys.shape[0]):
        k = keys[i]
        s = _find(table, k)
        if table[s] == k or (old.shape[0] > 1 and old[_find(old, k)] == k):
            new[i] = False  # held, or not moved yet
            continue
        table[s] = k
        new[i] = True
        added += 1
    return added


def move_keys(old: Any, start: int, stop: int, table: Any) -> None:
    """Insert the keys of ``old[start:stop]`` (a table being moved) into ``table``, which
    holds none of them."""
    for j in range(start, stop):
        k = old[j]
        if k != 0:
            table[_find(table, k)] = k


def _size_for(n: int) -> int:
    """A table size (at least 1024) that holds ``n`` keys ``_PREP`` full."""
    return max(1024, math.ceil(n / _PREP) + 1)


_KERNELS: list[Any] = []
_NONE = np.zeros(1, np.int64)  # no table being moved


def _kernel() -> Any:
    """:func:`insert_keys` and :func:`move_keys` compiled, or None where compiled kernels
    are off."""
    if not jit_enabled():
        return None
    if not _KERNELS:
        global _find
        njit = numba_module().njit
        if not hasattr(_find, "py_func"):  # not yet numba's
            _find = njit(cache=True, nogil=True, inline="always")(_find)
        _KERNELS.extend((njit(cache=True, nogil=True)(insert_keys),
                         njit(cache=True, nogil=True)(move_keys)))
    return _KERNELS


def warm() -> bool:
    """Compile (or load from numba's cache) the kernels now: a live SIC does it before it
    listens, not on its first frame. False where compiled kernels are off."""
    if _kernel() is None:
        return False
    v = VoxelSet()
    for k in range(3):  # a table grown and moved: both kernels
        v.add(np.arange(1 + 1000 * k, 1001 + 1000 * k, dtype=np.int64))
    return True


class VoxelSet:
    """Voxel keys (int64, non-zero) held; :meth:`add` returns which of new keys were new."""

    __slots__ = (
        "_compiled",
        "_keys",
        "_moved",
        "_n",
        "_next",
        "_old",
        "_runs",
        "_table",
        "_zeroed",
        "step",
    )

    def __init__(self, *, compiled: bool = True) -> None:
        """``compiled=False``: the sorted runs even where kernels are on (tests)."""
        self._compiled = compiled
        self._n = 0
        self._table: IntArray | None = None  # compiled: the hash table
        # a table that grew: its keys move to the new one a little at each add (a frame
        # must not wait for millions of keys to move at once); until then both are looked in
        self._old: IntArray | None = None
        self._moved = 0
        self._next: IntArray | None = None  # the next table, zeroed up to _zeroed
        self._zeroed = 0
        self._keys: IntArray = np.zeros(0, np.int64)  # numpy: sorted runs
        self._runs: list[IntArray] = []
        self.step = 32768  # the least slots a move's step takes

    def __len__(self) -> int:
        return self._n

    @property
    def compiled(self) -> bool:
        """Whether it may use the hash table (where compiled kernels are on)."""
        return self._compiled

    @property
    def nbytes(self) -> int:
        if self._table is not None:
            return sum(int(t.nbytes) for t in (self._table, self._old, self._next)
                       if t is not None)
        return int(self._keys.nbytes + sum(r.nbytes for r in self._runs))

    def add(self, keys: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Takes ``keys`` in, in order; True where a key was not held before (and is not an
        earlier key's repeat)."""
        keys = np.ascontiguousarray(keys, dtype=np.int64)
        kernels = _kernel() if self._compiled else None
        if kernels is None:
            return self._add_sorted(keys)
        insert, move = kernels
        need = self._n + len(keys)
        if self._table is None:
            self._table = np.zeros(_size_for(need), np.int64)
        elif self._next is None and need > _PREP * len(self._table):
            # the next table, zeroed a step at each add (a fresh 128 MB table's first
            # touch, page by page, held up a frame by 75 ms)
            self._next = np.empty(max(int(_GROWTH * len(self._table)), _size_for(need)),
                                  np.int64)
            self._zeroed = 0
        if self._next is not None:
            force = need > _FULL * len(self._table)
            if force and len(self._next) < _size_for(need):
                # more keys at once than the next table was sized for: a bigger one
                self._next = np.empty(_size_for(need), np.int64)
                self._zeroed = 0
            z = len(self._next) if force else min(len(self._next), self._zeroed + _ZERO_STEP)
            self._next[self._zeroed:z] = 0
            self._zeroed = z
            if z == len(self._next):
                self._switch(move)
        if self._old is not None:
            # a step of the move: at least ``step`` slots, more for a frame with more
            # keys (the move ends long before the new table fills)
            stop = min(len(self._old), self._moved + max(self.step, 8 * len(keys)))
            move(self._old, self._moved, stop, self._table)
            self._moved = stop
        old = _NONE if self._old is None else self._old
        new = np.empty(len(keys), np.bool_)
        self._n += int(insert(self._table, old, keys, new))
        if self._old is not None and self._moved == len(self._old):
            self._old = None
        return new

    def _switch(self, move: Any) -> None:
        """The zeroed next table becomes the table; the keys start to move into it."""
        assert self._table is not None and self._next is not None
        if self._old is not None:  # the last move had not ended: end it now
            move(self._old, self._moved, len(self._old), self._table)
        self._old, self._moved = self._table, 0
        self._table, self._next = self._next, None

    def _add_sorted(self, keys: IntArray) -> NDArray[np.bool_]:
        new = np.zeros(len(keys), np.bool_)
        if not len(keys):
            return new
        # the first of equal keys (a stable sort), then those no run holds
        sk, order = sorted_with_order(keys)
        first = run_starts(sk)
        uk, ui = sk[first], order[first]
        for run in (self._keys, *self._runs):
            if len(run) and len(uk):
                fresh = run[np.minimum(np.searchsorted(run, uk), len(run) - 1)] != uk
                uk, ui = uk[fresh], ui[fresh]
        if len(uk):
            # runs merge while the newer is a quarter of the older or more: a frame's merges
            # are small, the big ones rare (timsort merges two sorted runs in one pass)
            self._runs.append(uk)
            while len(self._runs) >= 2 and 4 * len(self._runs[-1]) >= len(self._runs[-2]):
                b = self._runs.pop()
                self._runs[-1] = np.sort(np.concatenate([self._runs[-1], b]), kind="stable")
            if 4 * len(self._runs[0]) >= len(self._keys):
                self._keys = np.sort(np.concatenate([self._keys, self._runs.pop(0)]),
                                     kind="stable")
        new[ui] = True
        self._n += len(uk)
        return new

    def sorted(self) -> IntArray:
        """Every key held, ascending (for tests and checks)."""
        if self._table is not None:
            # a key moved from the old table is in both until the old one goes
            held = [t[t != 0] for t in (self._table, self._old) if t is not None]
            return np.unique(np.concatenate(held))
        return np.sort(np.concatenate([self._keys, *self._runs]))
