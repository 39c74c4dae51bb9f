"""Compiled kernels (numba), imported lazily: off the CLI's import path, and optional.

A kernel is a plain Python function written with numpy scalars; :func:`compiled` gives its
numba build (loaded from numba's on-disk cache after the first time on a machine), or None
where numba is missing or ``TCF_HIL_NO_JIT`` is set: the caller then runs its numpy path,
which the tests hold to the same bits.

numba's on-disk cache notices a change to a kernel's own file, not to the kernels it calls
in other files (the fused lidar kernel calls three files' worth). So unless
``NUMBA_CACHE_DIR`` is set, the cache lives in a directory named after a hash of every
kernel source (:data:`KERNEL_SOURCES`): a changed kernel anywhere compiles everything anew.
"""

from __future__ import annotations

import functools
import hashlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

# every file with a kernel in it, relative to the directory above this package
KERNEL_SOURCES = ("emulators/_jit.py", "emulators/_embree.py", "emulators/lidar/_kernel.py",
                  "emulators/lidar/_fused.py", "tcf_hil/trajectory.py")


def jit_enabled() -> bool:
    """Whether compiled kernels are wanted here (``TCF_HIL_NO_JIT`` unset or 0) and numba
    can be had."""
    if os.environ.get("TCF_HIL_NO_JIT", "") not in ("", "0"):
        return False
    return numba_module() is not None


@functools.cache
def numba_module() -> Any:
    """numba, its cache directory set (see the module doc), or None where it is missing."""
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a dependency; numpy stands in
        return None
    if not os.environ.get("NUMBA_CACHE_DIR"):
        root = Path(__file__).resolve().parent.parent
        digest = hashlib.sha256()
        for name in KERNEL_SOURCES:
            path = root / name
            digest.update(path.read_bytes() if path.exists() else name.encode())
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
        config: Any = numba.config
        config.CACHE_DIR = str(base / "tcf-hil" / f"numba-{digest.hexdigest()[:16]}")
    return numba


@functools.cache
def compiled(fn: Callable[..., Any]) -> Callable[..., Any] | None:
    if not jit_enabled():
        return None
    kernel: Callable[..., Any] = numba_module().njit(cache=True, nogil=True)(fn)
    return kernel
