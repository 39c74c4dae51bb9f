"""Where the libraries' log records go while a command runs.

python-can and canopen log through :mod:`logging`; with nothing configured, Python prints
every warning on the terminal (``Got incomplete message => waiting for more data`` whenever
TCP splits a socketcand frame, which is normal and harmless), in the middle of a progress
bar. While a command runs they go to the run's log file instead (``bench.log`` in the run
directory), with time and logger name; without a run directory only their errors reach the
terminal, each with the logger's name.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from pathlib import Path

__all__ = ["LIBRARY_LOGGERS", "library_logs"]

#: the libraries whose records are kept off the terminal (ours stay: they say what happens)
LIBRARY_LOGGERS = ("can", "canopen")
_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


@contextlib.contextmanager
def library_logs(path: Path | None) -> Iterator[None]:
    """python-can's and canopen's records (INFO and up) to ``path`` while in the block, and
    nowhere else (an outer block's handlers are set aside); with ``path`` None, their errors
    only, to stderr. Restored on exit. A directory that cannot be made: as with None (the
    command itself then says what is wrong with it)."""
    if path is not None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError:
            path = None
    if path is not None:
        handler: logging.Handler = logging.FileHandler(path, encoding="utf-8", delay=True)
        handler.setFormatter(logging.Formatter(_FORMAT))
        level = logging.INFO
    else:
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("%(name)s: %(message)s"))
        level = logging.ERROR
    handler.setLevel(level)
    saved = []
    for name in LIBRARY_LOGGERS:
        lg = logging.getLogger(name)
        saved.append((lg, lg.propagate, lg.level, list(lg.handlers)))
        for h in list(lg.handlers):
            lg.removeHandler(h)
        lg.addHandler(handler)
        lg.propagate = False
        if lg.level == logging.NOTSET or lg.level > level:
            lg.setLevel(level)
    try:
        yield
    finally:
        for lg, propagate, lvl, handlers in saved:
            lg.removeHandler(handler)
            for h in handlers:
                lg.addHandler(h)
            lg.propagate = propagate
            lg.setLevel(lvl)
        handler.close()
