"""The compiled CRC-64/XZ for whole frames of packets (fastcrc), shared by the emulator's
encoder and the onboard SIC's decoder; protocols' numpy tables stand in without it."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def fast_crc_rows() -> Callable[[np.ndarray], np.ndarray] | None:
    try:
        import fastcrc
    except ImportError:
        return None  # protocols' numpy tables

    def rows(a: np.ndarray) -> np.ndarray:
        return np.fromiter((fastcrc.crc64.xz(r.tobytes()) for r in a), np.uint64, len(a))
    return rows
