"""Compiled kernels (numba), imported lazily: off the CLI's import path, and optional.

A kernel is a plain Python function written with numpy scalars; :func:`compiled` gives its
numba build (loaded from numba's on-disk cache after the first time on a machine), or None
where numba is missing or ``TCF_HIL_NO_JIT`` is set: the caller then runs its numpy path,
which the tests hold to the same bits.

numba's on-disk cache notices a change to a kernel's own file, not to the kernels it calls
in other files (the fused lidar kernel calls three files' worth). So unless
``NUMBA_CACHE_DIR`` is set, the cache lives in a directory named after a hash of every
kernel source known (:func:`cache_dir`): this package's own (:data:`KERNEL_SOURCES`) and
those of modules outside it, which register their file (:func:`register_kernel_source`) at
import, before they declare a kernel. A changed kernel anywhere compiles everything anew.

numba takes the directory when a kernel is declared (``njit(cache=True)``). A source
registered after some kernels were declared (its module imported later) moves the cache of
the kernels declared from then on, and those declared before keep theirs: still sound, as a
kernel's module imports the modules whose kernels it calls, so they had registered by then.
"""

from __future__ import annotations

import functools
import hashlib
import os
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

_PACKAGE = Path(__file__).resolve().parent
KERNEL_SOURCES = ("jit.py", "embree.py", "media.py", "lidar/_kernel.py", "lidar/_fused.py",
                  "lidar/_footprint.py")
"""The files of this package with kernels in them (this one: how they are built), relative
to it; modules elsewhere register theirs (:func:`register_kernel_source`)."""

_sources: set[Path] = {_PACKAGE / name for name in KERNEL_SOURCES}
_lock = threading.RLock()  # cache_dir() takes it again under register_kernel_source()
_numba: Any = None  # numba once numba_module() has imported it and set its cache directory


def register_kernel_source(path: str | os.PathLike[str]) -> None:
    """Count the file ``path`` (a module's ``__file__``) among the kernel sources that name
    the cache directory: a module outside this package with kernels in it calls this at
    import, before it declares them (see the module doc). Registering again is a no-op."""
    source = Path(path).resolve()
    with _lock:
        if source in _sources:
            return
        _sources.add(source)
        if _numba is not None:  # kernels may have been declared: the next ones go here
            _set_cache_dir(_numba)


def kernel_sources() -> frozenset[Path]:
    """The kernel sources registered so far."""
    with _lock:
        return frozenset(_sources)


def cache_dir() -> Path:
    """Where the compiled kernels are cached, unless ``NUMBA_CACHE_DIR`` says elsewhere:
    ``$XDG_CACHE_HOME`` (or ``~/.cache``) ``/tcf-hil/numba-<hash of the kernel sources>``.
    The hash does not depend on the order of registration or on where the files are."""
    digests = sorted(hashlib.sha256(p.read_bytes() if p.exists() else p.name.encode()).digest()
                     for p in kernel_sources())
    digest = hashlib.sha256(b"".join(digests))
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "tcf-hil" / f"numba-{digest.hexdigest()[:16]}"


def _set_cache_dir(numba: Any) -> None:
    if not os.environ.get("NUMBA_CACHE_DIR"):
        config: Any = numba.config
        config.CACHE_DIR = str(cache_dir())


def jit_enabled() -> bool:
    """Whether compiled kernels are wanted here (``TCF_HIL_NO_JIT`` unset or 0) and numba
    can be had."""
    if os.environ.get("TCF_HIL_NO_JIT", "") not in ("", "0"):
        return False
    return numba_module() is not None


@functools.cache
def numba_module() -> Any:
    """numba, its cache directory set (see the module doc), or None where it is missing."""
    global _numba
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a dependency; numpy stands in
        return None
    with _lock:
        _set_cache_dir(numba)
        _numba = numba
    return numba


@functools.cache
def compiled(fn: Callable[..., Any]) -> Callable[..., Any] | None:
    if not jit_enabled():
        return None
    kernel: Callable[..., Any] = numba_module().njit(cache=True, nogil=True)(fn)
    return kernel
