"""DBH from a stand distribution: fixed, uniform, normal, lognormal or Weibull."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import brentq
from scipy.special import gamma

from tcf_hil.scenario import DbhConfig

FloatArray = NDArray[np.float64]


def weibull_shape(mean: float, sd: float) -> tuple[float, float]:
    """Shape k and scale of the two-parameter Weibull with this mean and SD."""
    cv2 = (sd / mean) ** 2

    def f(k: float) -> float:
        return float(gamma(1.0 + 2.0 / k) / gamma(1.0 + 1.0 / k) ** 2 - 1.0 - cv2)

    k = float(brentq(f, 0.2, 200.0)) if f(200.0) < 0.0 else 200.0  # else nearly fixed
    return k, mean / float(gamma(1.0 + 1.0 / k))


def draw_dbh(d: DbhConfig, n: int, rng: np.random.Generator) -> FloatArray:
    """DBH from a stand distribution, truncated to [min_m, max_m] by redrawing."""
    if d.kind == "fixed":
        return np.full(n, d.mean_m)
    if d.kind == "uniform":
        return rng.uniform(d.min_m, d.max_m, n)
    out = np.empty(n)
    todo = np.arange(n)
    if d.kind == "weibull":
        k, scale = weibull_shape(d.mean_m, d.sd_m)
    for _ in range(100):
        if d.kind == "normal":
            v = rng.normal(d.mean_m, d.sd_m, len(todo))
        elif d.kind == "weibull":
            v = scale * rng.weibull(k, len(todo))
        else:
            sigma2 = math.log(1.0 + (d.sd_m / d.mean_m) ** 2)
            v = rng.lognormal(math.log(d.mean_m) - sigma2 / 2, math.sqrt(sigma2), len(todo))
        out[todo] = v
        todo = todo[(v < d.min_m) | (v > d.max_m)]
        if len(todo) == 0:
            break
    return np.clip(out, d.min_m, d.max_m)
