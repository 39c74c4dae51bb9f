"""Published stem models of Scots pine, Norway spruce and silver birch: taper and height.

**Taper** (Laasasenaho 1982, Communicationes Instituti Forestalis Fenniae 108, the basic
curve): with x = 1 - h/H the relative distance from the top (h height along the stem, H the
stem's height), the diameter relative to the diameter at 20 % of the height is::

    d(h) / d20 = c1 x + c2 x^2 + c3 x^3 + c4 x^5 + c5 x^8 + c6 x^13 + c7 x^21 + c8 x^34

so d(h) = DBH * P(x) / P(1 - 1.3/H). The coefficients below are the 1982 basic coefficients
as Luke's simulator codes them (``lukefi/metsi``, ``crk.py``, ``CRKPK`` rows 0-2) and as
``dmela/Laasasenaho`` (``Laasasenaho.R``) does: the same digits in both; P(0.8) = 1 for
each (the curve is normalised at 20 % height; a test holds it). The tree-specific correction
polynomial of the same work (which bends the curve by DBH and height) is not applied: the
basic curve is the species' mean form. P(1) is the swell at the ground (1.4-1.6 DBH).

**Height from DBH** (Pukkala, Lähde and Laiho 2009, For. Ecol. Manage. 258: 207-216,
doi:10.1016/j.foreco.2009.03.052, fitted on Finnish uneven-sized stands)::

    h = (a1 + a_site) / (1 + b1/d + b2/d^2)        d in cm, h in m

with the residual standard deviation the paper reports (pine 2.360 m, spruce 2.104 m, birch
2.001 m). Coefficients read from ``Silviculturalist/forester`` (``R/Pukkala_2009.R``), which
codes the paper's table; the paper itself was not read. Site terms: "mt" (mesic or
richer), "vt" (sub-xeric), "ct" (xeric), "clt" (barren); spruce and birch have no ClT term
(0, as coded there).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

SPECIES: tuple[str, ...] = ("pine", "spruce", "birch")
"""Species codes: the index in this tuple (-1: the paper's power-law pole)."""

TAPER_POWERS = np.array([1.0, 2.0, 3.0, 5.0, 8.0, 13.0, 21.0, 34.0])
TAPER_COEFFS = np.array([
    [2.1288, -0.63157, -1.6082, 2.4886, -2.4147, 2.3619, -1.7539, 1.0817],  # pine
    [2.3366, -3.2684, 3.6513, -2.2608, 0.0, 2.1501, -2.7412, 1.8876],  # spruce
    [0.93838, 4.1060, -7.8517, 7.8993, -7.5018, 6.3863, -4.3918, 2.1604],  # birch
])

# Pukkala et al. 2009, height model: a1, site terms (mt, vt, ct, clt), b1, b2, residual SD (m)
HEIGHT_A1 = np.array([25.014, 33.726, 29.375])
HEIGHT_SITE = {"mt": np.array([7.680, 5.965, 7.714]), "vt": np.array([6.376, 2.178, 3.059]),
               "ct": np.array([-1.787, -1.399, -2.870]), "clt": np.array([-3.296, 0.0, 0.0])}
HEIGHT_B1 = np.array([19.260, 25.683, 22.640])
HEIGHT_B2 = np.array([31.721, 37.785, -8.0])
HEIGHT_SD_M = np.array([2.360, 2.104, 2.001])


def taper_poly(species: IntArray, x: FloatArray, derivative: int = 0) -> FloatArray:
    """P(x) (or its first or second derivative in x) of each stem's species; x is clipped
    to [0, 1] (no taper beyond the top or below the ground)."""
    xc = np.clip(x, 0.0, 1.0)[:, None]
    c = TAPER_COEFFS[species]
    p = TAPER_POWERS[None, :]
    if derivative == 0:
        return np.sum(c * xc ** p, axis=1)
    if derivative == 1:
        return np.sum(c * p * xc ** (p - 1.0), axis=1)
    return np.sum(c * p * (p - 1.0) * np.where(p > 1.0, xc ** np.maximum(p - 2.0, 0.0), 0.0),
                  axis=1)


def mean_height(species: IntArray, dbh_m: FloatArray, site: str) -> FloatArray:
    """Height (m) on Pukkala et al.'s curve for each stem's species and DBH."""
    d = 100.0 * dbh_m
    a = HEIGHT_A1[species] + HEIGHT_SITE[site][species]
    out: FloatArray = a / (1.0 + HEIGHT_B1[species] / d + HEIGHT_B2[species] / d**2)
    return out
