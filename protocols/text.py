"""Text for error messages (stdlib only)."""

from __future__ import annotations


def short_repr(value: object, limit: int = 200) -> str:
    """``repr(value)`` for a one-line message: at most ``limit`` characters, and never an error
    (an int beyond the interpreter's str-conversion digit limit cannot be printed)."""
    try:
        text = repr(value)
    except ValueError:
        text = f"<{type(value).__name__} too large to print>"
    return text if len(text) <= limit else text[:limit - 3] + "..."
