"""Compiled kernels (numba), imported lazily: off the CLI's import path, and optional.

A kernel is a plain Python function written with numpy scalars; :func:`compiled` gives its
numba build (loaded from numba's on-disk cache after the first time on a machine), or None
where numba is missing or ``TCF_HIL_NO_JIT`` is set: the caller then runs its numpy path,
which the tests hold to the same bits.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from typing import Any


@functools.cache
def compiled(fn: Callable[..., Any]) -> Callable[..., Any] | None:
    if os.environ.get("TCF_HIL_NO_JIT", "") not in ("", "0"):
        return None
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a dependency; numpy stands in
        return None
    kernel: Callable[..., Any] = numba.njit(cache=True, nogil=True)(fn)
    return kernel
