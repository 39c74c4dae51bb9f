"""The exception tree of tcf-hil.

::

    TcfHilError
     ├── ConfigError      a scenario or option is invalid (names key, value, what is allowed)
     ├── InputError       an input file is unreadable or breaks its schema (names file and field)
     ├── EndpointError    a run cannot get an endpoint of its own (also an OSError)
     └── SicError         the reference onboard SIC cannot start (no metadata, a silent node)

The CLI maps every ``TcfHilError`` to exit status 1 and a one-line ``Error: ...`` message;
the SIC's own command (``python -m tcf_hil.sic``, ``tcf-hil sic``) ends with a SicError's
message alone, as exit status 1.
"""

from __future__ import annotations

from protocols.text import short_repr

__all__ = ["ConfigError", "EndpointError", "InputError", "SicError", "TcfHilError",
           "short_repr"]


class TcfHilError(Exception):
    """Root of every error tcf-hil raises on purpose."""


class EndpointError(TcfHilError, OSError):
    """A run cannot get an endpoint of its own (every sensor address or UDP port taken)."""


class ConfigError(TcfHilError, ValueError):
    """A configuration value is invalid.

    Args:
        key: dotted key, e.g. ``stems.count``.
        value: the offending value.
        allowed: what would have been accepted.
        source: file the value came from, if any.
    """

    def __init__(self, key: str, value: object, allowed: str, source: str | None = None) -> None:
        self.key = key
        self.value = value
        self.allowed = allowed
        self.source = source
        where = f"{source}: " if source else ""
        super().__init__(f"{where}{key} = {short_repr(value)} is invalid; allowed: {allowed}")


class InputError(TcfHilError, ValueError):
    """An input document is unreadable or invalid.

    Args:
        path: file name (or ``<stdin>``/``<memory>``).
        field: JSON path of the bad field, e.g. ``objects[3].cp[1]``; empty for the whole file.
        problem: what is wrong and what was expected.
    """

    def __init__(self, path: str, field: str, problem: str) -> None:
        self.path = path
        self.field = field
        self.problem = problem
        at = f" at {field}" if field else ""
        super().__init__(f"{path}{at}: {problem}")


class SicError(TcfHilError):
    """The reference onboard SIC cannot start or go on: no metadata to be had (neither file
    nor sensor), or a harvester node that does not answer its SDO reads. The message names
    what and why, starting ``sic:`` as every line the SIC writes; its command prints it and
    exits with status 1."""
