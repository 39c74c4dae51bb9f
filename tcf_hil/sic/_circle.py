"""Circle fits for stem slices: algebraic (Kåsa) and robust geometric (IRLS Gauss-Newton).

The geometric fit minimises sum w_i (|p_i - c| - r)² with Huber-type weights, starting from
the algebraic fit; the radius is kept within bounds, so a short, noisy arc gives a bounded
answer instead of a wild one.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray


class Circle(NamedTuple):
    cx: float
    cy: float
    r: float
    rms: float  # RMS of geometric residuals (m)
    arc_deg: float  # angular coverage of the points around the centre


def _arc_coverage(ang: NDArray[np.float64]) -> float:
    if len(ang) < 2:
        return 0.0
    a = np.sort(np.mod(ang, 2.0 * math.pi))
    gaps = np.diff(np.concatenate([a, [a[0] + 2.0 * math.pi]]))
    return math.degrees(2.0 * math.pi - float(gaps.max()))


def fit_circle_algebraic(xy: NDArray[np.float64]) -> Circle | None:
    """Kåsa fit (linear least squares); None with fewer than 3 points or collinear points."""
    if len(xy) < 3:
        return None
    m = xy.mean(axis=0)
    p = xy - m
    A = np.column_stack([p, np.ones(len(p))])
    b = -(p[:, 0] ** 2 + p[:, 1] ** 2)
    sol, _, rank, _ = np.linalg.lstsq(A, b, rcond=None)
    if rank < 3:
        return None
    cx, cy = -sol[0] / 2.0, -sol[1] / 2.0
    r2 = cx * cx + cy * cy - sol[2]
    if not r2 > 0:
        return None
    r = math.sqrt(r2)
    d = np.hypot(p[:, 0] - cx, p[:, 1] - cy)
    rms = float(np.sqrt(np.mean((d - r) ** 2)))
    arc = _arc_coverage(np.arctan2(p[:, 1] - cy, p[:, 0] - cx))
    return Circle(float(cx + m[0]), float(cy + m[1]), r, rms, arc)


def fit_circle(xy: NDArray[np.float64], r_min: float = 0.01, r_max: float = 1.0,
               iterations: int = 15, huber_m: float = 0.01) -> Circle | None:
    """Robust geometric circle fit with the radius bounded to [r_min, r_max].

    Returns None with fewer than 3 points or when no bounded fit exists.
    """
    init = fit_circle_algebraic(xy)
    if init is None:
        return None
    m = xy.mean(axis=0)
    p = xy - m
    cx, cy = init.cx - m[0], init.cy - m[1]
    r = min(max(init.r, r_min), r_max)
    if math.hypot(cx, cy) > 10.0 * r_max:  # nearly straight points: start on the far side
        cx, cy = 0.0, 0.0
    lam = 1e-3
    for _ in range(iterations):
        dx, dy = p[:, 0] - cx, p[:, 1] - cy
        d = np.maximum(np.hypot(dx, dy), 1e-12)
        res = d - r
        a = np.abs(res)
        w = np.where(a <= huber_m, 1.0, huber_m / np.maximum(a, 1e-12))
        J = np.column_stack([-dx / d, -dy / d, -np.ones(len(d))])
        JW = J * w[:, None]
        H = JW.T @ J
        g = JW.T @ res
        try:
            step = np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), -g)
        except np.linalg.LinAlgError:
            break
        cx, cy = cx + step[0], cy + step[1]
        r = min(max(r + step[2], r_min), r_max)
        if float(np.abs(step).max()) < 1e-7:
            break
    d = np.hypot(p[:, 0] - cx, p[:, 1] - cy)
    rms = float(np.sqrt(np.mean((d - r) ** 2)))
    if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(r)):
        return None
    arc = _arc_coverage(np.arctan2(p[:, 1] - cy, p[:, 0] - cx))
    return Circle(float(cx + m[0]), float(cy + m[1]), float(r), rms, arc)
