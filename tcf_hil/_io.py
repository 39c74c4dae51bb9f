"""Small file helpers: atomic writes (temporary name, then rename) and strict JSON reading."""

from __future__ import annotations

import contextlib
import gc
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from tcf_hil.errors import InputError

_UMASK = os.umask(0)
os.umask(_UMASK)


def ensure_dir(path: str | os.PathLike[str]) -> Path:
    """Create a directory (and parents); InputError naming it when that is impossible."""
    p = Path(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(str(p), "", f"cannot create the directory ({err.strerror or err})"
                         ) from err
    return p


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only on success.

    A crash or an exception leaves either the old file or nothing, never half a file.
    """
    final = Path(path)
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".part", dir=final.parent)
    except OSError as err:
        raise InputError(str(final), "", f"cannot write here ({err.strerror or err})") from err
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the file normal modes
    try:
        yield tmp_path
        os.replace(tmp_path, final)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike[str], mode: str = "w") -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path`` and rename it onto ``path`` when closed cleanly."""
    with atomic_path(path) as tmp:
        encoding = None if "b" in mode else "utf-8"
        with open(tmp, mode, encoding=encoding) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())


def write_bytes_atomic(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_open(path, "wb") as fh:
        fh.write(data)


def dumps_json(doc: Any) -> str:
    """Serialise ``doc`` deterministically (sorted keys off: order is part of the format)."""
    return json.dumps(doc, indent=1, allow_nan=False, ensure_ascii=False) + "\n"


def write_json_atomic(path: str | os.PathLike[str], doc: Any) -> None:
    """Write a JSON document atomically; NaN and infinity are refused."""
    text = dumps_json(doc)
    with atomic_open(path, "w") as fh:
        fh.write(text)


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not valid JSON")


def read_json(path: str | os.PathLike[str]) -> Any:
    """Read a JSON file strictly: NaN/Infinity literals are errors; errors name the file."""
    p = str(path)
    try:
        with open(p, encoding="utf-8") as fh:
            text = fh.read()
    except OSError as err:
        raise InputError(p, "", f"cannot read file ({err.strerror or err})") from err
    except UnicodeDecodeError as err:
        raise InputError(p, "", f"not UTF-8 text ({err.reason} at byte {err.start})") from err
    return loads_json(text, p)


def loads_json(text: str, source: str = "<memory>") -> Any:
    """Parse JSON text strictly, raising :class:`InputError` with the line and column."""
    try:
        return json.loads(text, parse_constant=_reject_constant)
    except json.JSONDecodeError as err:
        raise InputError(source, "", f"invalid JSON: {err.msg} (line {err.lineno}, "
                                     f"column {err.colno})") from err
    except ValueError as err:
        raise InputError(source, "", f"invalid JSON: {err}") from err
    except RecursionError as err:
        raise InputError(source, "", "invalid JSON: nested too deeply") from err


def name_process(name: str) -> None:
    """This process's name as ``top`` and ``ps`` show it (Linux: ``/proc/self/comm``, 15
    bytes at most): a bench's helpers are told apart from each other and from the program
    under test. Nothing happens where the system has no such file."""
    with contextlib.suppress(OSError):
        with open("/proc/self/comm", "w") as fh:
            fh.write(name[:15])


def settle_heap() -> None:
    """In a forked worker: what it inherited (the built scene, the modules: at 2048x10 on
    forest-x about 250,000 objects) moved out of the garbage collector's sight
    (``gc.freeze``), so the collections its frames' allocations set off no longer walk
    them all (about 3 ms of a 75 ms frame), and the inherited pages stay shared with the
    parent instead of being written by the collector (Python's ``gc.freeze`` docs)."""
    gc.freeze()


_IOV_MAX = 1024  # Linux's UIO_MAXIOV: the most pieces one writev takes


def write_gathered(fd: int, parts: list[Any]) -> int:
    """Bytes-like ``parts`` written to the file descriptor ``fd`` one after another, with
    as few ``writev`` calls as it takes (no joined copy in between; a short write goes on
    where it stopped); how many bytes."""
    views = [memoryview(p).cast("B") for p in parts if len(p)]
    total = sum(len(v) for v in views)
    i = 0
    while i < len(views):
        n = os.writev(fd, views[i:i + _IOV_MAX])
        while n and i < len(views):
            if n >= len(views[i]):
                n -= len(views[i])
                i += 1
            else:
                views[i] = views[i][n:]
                n = 0
    return total


def read_exact(fd: int, n: int) -> bytearray:
    """``n`` bytes from the file descriptor ``fd`` read straight into one buffer; EOFError
    where it ends first."""
    buf = bytearray(n)
    view = memoryview(buf)
    got = 0
    while got < n:
        r = os.readv(fd, [view[got:]])
        if r == 0:
            raise EOFError(f"end of input after {got} of {n} bytes")
        got += r
    return buf
