"""The stem classes S, C and X: the split of a stand's stems by the scenario's shares, and the
rule from maxcurve (the paper's thresholds)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["class_counts", "classify"]


def class_counts(mix: dict[str, float], n: int) -> dict[str, int]:
    """Split ``n`` stems by the shares in ``mix`` (largest remainder; exact total)."""
    total = sum(mix.values())
    if n == 0 or total <= 0:
        return {c: 0 for c in mix}
    raw = {c: n * v / total for c, v in mix.items()}
    out = {c: math.floor(v) for c, v in raw.items()}
    rest = n - sum(out.values())
    for c in sorted(raw, key=lambda c: (-(raw[c] - out[c]), list(mix).index(c)))[:rest]:
        out[c] += 1
    return out


def classify(maxcurve: Any, curve_threshold_m: float, other_threshold_m: float) -> Any:
    """Class labels from maxcurve: S below the curve threshold, X at or above the other
    threshold, C between. Works on scalars and arrays."""
    mc = np.asarray(maxcurve, dtype=np.float64)
    out = np.where(mc >= other_threshold_m, "X", np.where(mc >= curve_threshold_m, "C", "S"))
    return str(out) if out.ndim == 0 else out
