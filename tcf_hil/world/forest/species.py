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
    to [0, 1] (no taper beyond the top or below the ground).

    The powers are products, not calls of ``pow`` (which took a sixth of a natural stand's
    generation): the exponents less the derivative's order m, e_k = p_k - m, follow
    e_k = e_(k-1) + e_(k-2) + m (the powers are Fibonacci numbers), so each is the two
    before it times x^m; the terms are summed in order."""
    xc = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    m = derivative
    coef = TAPER_COEFFS * _FALLING[m][None, :]
    sp = np.asarray(species)
    same = sp.size > 0 and bool(np.all(sp == sp.flat[0]))
    xm = (None, xc, xc * xc)[m]
    w: list[FloatArray | None] = [
        (xc, None, None)[m], (xc * xc, xc, None)[m]]  # x^(1-m), x^(2-m); x^0: None
    for k in range(2, len(TAPER_POWERS)):
        if m == 2 and k == 2:
            w.append(xc)  # x^1 (the rule would need x^-1)
            continue
        a, b = w[k - 1], w[k - 2]
        prod = a if b is None else (b if a is None else a * b)
        w.append(prod if xm is None else (xm if prod is None else prod * xm))
    out = np.zeros_like(xc)
    for k, wk in enumerate(w):
        if not _FALLING[m][k]:
            continue
        ck = coef[int(sp.flat[0]), k] if same else coef[:, k][sp]
        out += ck * (1.0 if wk is None else wk)
    return out


_FALLING = (np.ones(len(TAPER_POWERS)), TAPER_POWERS.copy(),
            TAPER_POWERS * (TAPER_POWERS - 1.0))
"""The factors the derivatives bring down: 1, p, p (p - 1)."""


def mean_height(species: IntArray, dbh_m: FloatArray, site: str) -> FloatArray:
    """Height (m) on Pukkala et al.'s curve for each stem's species and DBH."""
    d = 100.0 * dbh_m
    a = HEIGHT_A1[species] + HEIGHT_SITE[site][species]
    out: FloatArray = a / (1.0 + HEIGHT_B1[species] / d + HEIGHT_B2[species] / d**2)
    return out


# --- Crowns -----------------------------------------------------------------------------
# Crown length (m) from DBH d (cm) and height h (m): pine 2.653 + 0.26 d, spruce
# 2.686 + 0.52 d (Rautiainen et al. 2008, Silva Fennica 42); birch 0.5525 h/d + d^0.7032
# (Nilson et al. 1999). Crown radius (m), southern Sweden: (a dS + b)/20 with the stump
# diameter dS = 2 + 1.25 d (Jakobsons 1970; dS from Laasasenaho 1975). All as coded, with
# their references, in M. Mõttus's allometric functions for Finland (2017-2018); the
# originals were not read.
CROWN_RADIUS_A = np.array([1.14, 1.06, 1.51])
CROWN_RADIUS_B = np.array([10.7, 15.5, 12.8])

# Foliage: dry needle/leaf mass (kg) per tree, Repola 2009 (pine model 1a eq. 7, spruce 1c
# eq. 15) and Repola 2008 (birch, d > 11 cm; Johansson 1999 below), as coded in the same
# file; specific leaf weight (g/m2) and STAR (shoot silhouette to total area) as used by
# Majasalmi et al. 2013 (For. Ecol. Manage. 292: 10-18): SLW 161.3 / 202.0 / 74.07
# (Palmroth & Hari 2001; Stenberg et al. 1999; Lintunen et al. 2011), STAR 0.147 / 0.161 /
# 0.25 (Smolander et al. 1994; Stenberg et al. 1995; a flat leaf's 0.25 for birch).
SLW_G_M2 = np.array([161.3, 202.0, 74.07])
STAR = np.array([0.147, 0.161, 0.25])

# Branches: no published whorl or branch model with coefficients was found (Mäkinen & Colin
# 1998 and Kantola & Mäkelä give forms, not numbers we could read). These are assumptions,
# except spruce's branch angle 40-70 degrees (Fabrika et al. 2019, BioResources 14(1): 908).
WHORL_SPACING_M = np.array([0.40, 0.35, 0.30])  # birch: branches spaced along the crown
BRANCHES_PER_WHORL = np.array([4, 5, 2])
BRANCH_ANGLE_DEG = np.array([[50.0, 75.0], [40.0, 70.0], [30.0, 55.0]])
BRANCH_DIAMETER_SHARE = 0.12  # of the stem's diameter where it leaves (assumption)
BRANCH_DIAMETER_MAX_M = 0.04
# Dead branches stay on the lower stem of pine and spruce for decades (dead branch to
# occlusion > 40 years in Scots pine: Mäkinen, Silva Fennica, 19 thinning experiments);
# birch sheds them within about a metre under its crown (assumption).
DEAD_ZONE_FROM_M = np.array([0.8, 0.5, -1.0])  # height the dead branches start (-1: crown - 1 m)
DEAD_LENGTH_SHARE = (0.15, 0.45)  # of the crown radius: broken stubs (assumption)


def crown_length(species: IntArray, dbh_m: FloatArray, height_m: FloatArray) -> FloatArray:
    """Living crown length (m), at most 0.9 of the height and at least 0.5 m."""
    d = 100.0 * dbh_m
    conifer = np.where(species == 0, 2.653 + 0.26 * d, 2.686 + 0.52 * d)
    birch = 0.5525 * height_m / np.maximum(d, 1.0) + np.maximum(d, 1.0) ** 0.7032
    out: FloatArray = np.clip(np.where(species == 2, birch, conifer), 0.5, 0.9 * height_m)
    return out


def crown_radius(species: IntArray, dbh_m: FloatArray) -> FloatArray:
    """Crown radius (m) at its widest."""
    ds = 2.0 + 125.0 * dbh_m
    out: FloatArray = (CROWN_RADIUS_A[species] * ds + CROWN_RADIUS_B[species]) / 20.0
    return out


def foliage_mass_kg(species: IntArray, dbh_m: FloatArray, height_m: FloatArray) -> FloatArray:
    """Dry foliage mass (kg) per tree (Repola 2008, 2009; Johansson 1999 for small birch)."""
    ds = 2.0 + 125.0 * dbh_m
    h = height_m
    pine = np.exp(-6.303 + 14.472 * ds / (ds + 6) - 3.976 * h / (h + 1) + (0.109 + 0.118) / 2)
    spruce = np.exp(-2.994 + 12.251 * ds / (ds + 10) - 3.415 * h / (h + 1)
                    + (0.107 + 0.089) / 2)
    birch = np.where(100.0 * dbh_m > 11.0, np.exp(-29.566 + 33.372 * ds / (ds + 2) + 0.077 / 2),
                     0.00371 * (10.0 * ds) ** 1.11993)
    out: FloatArray = np.choose(species, [pine, spruce, birch])
    return out
