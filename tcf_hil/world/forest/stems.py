"""Stem geometry as a struct of arrays, evaluated vectorised over (stem index, axial s).

A stem is a tube around a centre line. With base point B (on the terrain), unit axis A (tilted
by the lean), axial length L, unit bend direction D (perpendicular to A), sweep w and bow peak p::

    C(s) = B + s*A + w * f(s/L) * D,      f(t) = sin(pi/2 * t/p)          for t <= p
                                                 sin(pi/2 * (1-t)/(1-p))  for t >  p

f is C1, 0 at both ends and 1 at t = p, and D is perpendicular to the chord B -> B + L*A, so the
maximum deviation of the centre line from its chord (``maxcurve``) is exactly w. The radius
tapers from the breast-height value r_bh at s = 1.3 m to r_top at the top::

    r(s) = r_top + (r_bh - r_top) * ((L - s) / (L - 1.3)) ** taper

Below the base (s < 0) the tube continues straight along A so no gap opens on slopes.

Natural stems (:mod:`tcf_hil.world.forest.natural`) add three things, each only where it is set
(the paper's stems leave them None and are evaluated exactly as before):

- ``species`` >= 0: the radius follows the species' taper curve (:mod:`~.species`) scaled
  to the radius at breast height, ``r(s) = r_bh P(1 - s/T) / P(1 - 1.3/T)`` with T the
  ``taper_length`` (the intact length: a broken top keeps the thickness it broke at);
  below the base it goes on with the butt's slope, ``r(0) + r'(0) s``;
- a crook: a sideways shift ``K`` (perpendicular to A) over a short stretch from ``crook_s``
  to ``crook_s + crook_w``, ``C(s) += K g((s - crook_s)/crook_w)`` with g the quintic
  smoothstep (C2, 0 below the stretch, 1 above it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

BREAST_HEIGHT_M = 1.3


def _bow(t: FloatArray, p: FloatArray, order: int = 0) -> FloatArray:
    """f(t) (``order`` 0), f'(t) (1) or f''(t) (2) of the bow profile; t outside [0, 1]
    gives zeros."""
    inside = (t >= 0.0) & (t <= 1.0)
    lo = t <= p
    q = np.where(lo, p, 1.0 - p)
    u = np.where(lo, t / p, (1.0 - t) / (1.0 - p))
    a = 0.5 * math.pi / q
    if order == 1:
        out = np.where(lo, 1.0, -1.0) * a * np.cos(0.5 * math.pi * u)
    else:
        out = np.sin(0.5 * math.pi * u)
        if order == 2:
            out = -(a**2) * out
    return np.where(inside, out, np.zeros_like(t))


@dataclass(frozen=True)
class StemSet:
    """All stems of a forest in local coordinates (metres), one row per stem."""

    base: FloatArray  # (n, 3)
    axis: FloatArray  # (n, 3) unit
    bend: FloatArray  # (n, 3) unit, perpendicular to axis
    length: FloatArray  # (n,) axial length L
    sweep: FloatArray  # (n,) maximum deviation from the chord
    peak: FloatArray  # (n,) bow peak position in (0, 1)
    r_bh: FloatArray  # (n,) radius at breast height
    r_top: FloatArray  # (n,)
    taper: FloatArray  # (n,)
    below: FloatArray  # (n,) mesh extension below the base
    species: IntArray | None = None  # (n,) taper curve: -1 the power law, else a species code
    taper_length: FloatArray | None = None  # (n,) length the taper curve spans (>= length)
    crook: FloatArray | None = None  # (n, 3) sideways shift, perpendicular to axis (or 0)
    crook_s: FloatArray | None = None  # (n,) where the crook starts along the axis
    crook_w: FloatArray | None = None  # (n,) its length along the axis (> 0)

    def __len__(self) -> int:
        return len(self.length)

    @property
    def binormal(self) -> FloatArray:
        """Constant normal of each stem's bend plane (axis x bend)."""
        return np.cross(self.axis, self.bend)

    @property
    def height(self) -> FloatArray:
        """Vertical height from base to top (m)."""
        return self.length * self.axis[:, 2]

    def _dcds(self, idx: IntArray, s: FloatArray) -> FloatArray:
        """dC/ds (not normalised); below the base it is the value at the base."""
        L = self.length[idx]
        df = _bow(np.clip(s, 0.0, None) / L, self.peak[idx], 1)
        out = self.axis[idx] + (self.sweep[idx] * df / L)[:, None] * self.bend[idx]
        if self.crook is not None:
            k = self._crooked(idx)
            _, dg, _ = self._crook(idx[k], np.clip(s[k], 0.0, None))
            out[k] += dg[:, None] * self.crook[idx[k]]
        return out

    def _crooked(self, idx: IntArray) -> NDArray[np.bool_]:
        """Which of stems ``idx`` have a crook (the others' adds nothing)."""
        out: NDArray[np.bool_] = self._has_crook[idx]
        return out

    @cached_property
    def _has_crook(self) -> NDArray[np.bool_]:
        assert self.crook is not None
        out: NDArray[np.bool_] = np.any(self.crook != 0.0, axis=1)
        return out

    def _crook(self, idx: IntArray, s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """g, dg/ds and d2g/ds2 of each stem's crook at ``s`` (the smoothstep; zeros where
        there is none)."""
        assert self.crook_s is not None and self.crook_w is not None
        w = self.crook_w[idx]
        u = np.clip((s - self.crook_s[idx]) / w, 0.0, 1.0)
        g = u**3 * (10.0 + u * (-15.0 + 6.0 * u))
        dg = 30.0 * u**2 * (1.0 - u) ** 2 / w
        d2g = 60.0 * u * (1.0 - u) * (1.0 - 2.0 * u) / w**2
        return g, dg, d2g

    def centre(self, idx: IntArray, s: FloatArray) -> FloatArray:
        """Centre-line points (m, 3) of stems ``idx`` at axial positions ``s``. Below the
        base (s < 0) the line goes on straight along its direction at the base, so it has no
        kink where the stem meets the ground."""
        t = s / self.length[idx]
        f = _bow(t, self.peak[idx])
        out = (self.base[idx] + s[:, None] * self.axis[idx]
               + (self.sweep[idx] * f)[:, None] * self.bend[idx])
        if self.crook is not None:
            k = self._crooked(idx)
            g, _, _ = self._crook(idx[k], s[k])
            out[k] += g[:, None] * self.crook[idx[k]]
        below = s < 0
        if below.any():
            ib = idx[below]
            out[below] = self.base[ib] + s[below, None] * self._dcds(ib, np.zeros(len(ib)))
        return out

    def tangent(self, idx: IntArray, s: FloatArray) -> FloatArray:
        """Unit tangents (m, 3) of the centre line."""
        d = self._dcds(idx, s)
        return d / np.linalg.norm(d, axis=1)[:, None]

    def ring_frame(self, idx: IntArray, s: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Two unit vectors spanning the plane perpendicular to the centre line at ``s``
        (a cross-section's axes): ``binormal x tangent`` and the binormal, which are
        orthonormal where the stem bends in its bend plane only (the paper's bow); with a
        crook, which bends it out of that plane, they are made so."""
        t = self.tangent(idx, s)
        b = self.binormal[idx]
        u = np.cross(b, t)
        if self.crook is None:
            return u, b
        u /= np.linalg.norm(u, axis=1)[:, None]
        return u, np.cross(t, u)

    def speed(self, idx: IntArray, s: FloatArray) -> FloatArray:
        """|dC/ds| (arc length per axial length, >= 1)."""
        return np.linalg.norm(self._dcds(idx, s), axis=1)

    def max_speed(self, idx: IntArray | None = None) -> FloatArray:
        """Largest |dC/ds| of stems ``idx`` (all by default), at the bow's steepest point."""
        ix = np.arange(len(self)) if idx is None else idx
        q = np.minimum(self.peak[ix], 1.0 - self.peak[ix])
        slope = self.sweep[ix] * 0.5 * math.pi / q / self.length[ix]
        if self.crook is not None:  # the two slopes are perpendicular to the axis: a bound
            assert self.crook_w is not None
            slope = slope + 1.875 * np.linalg.norm(self.crook[ix], axis=1) / self.crook_w[ix]
        return np.sqrt(1.0 + slope**2)

    def curvature_bound(self, idx: IntArray, s: FloatArray) -> FloatArray:
        """|d2C/ds2| (1/m): how fast the centre line bends."""
        L = self.length[idx]
        d2f = _bow(s / L, self.peak[idx], 2)
        out = np.abs(self.sweep[idx] * d2f) / L**2
        if self.crook is not None:
            k = self._crooked(idx)
            _, _, d2g = self._crook(idx[k], s[k])
            out[k] += np.abs(d2g) * np.linalg.norm(self.crook[idx[k]], axis=1)
        return out

    def radius(self, idx: IntArray, s: FloatArray) -> FloatArray:
        """Stem radius (m) at axial positions ``s``."""
        L = self.length[idx]
        rel = np.clip(L - s, 0.0, None) / (L - BREAST_HEIGHT_M)
        out = self.r_top[idx] + (self.r_bh[idx] - self.r_top[idx]) * rel ** self.taper[idx]
        if self.species is not None:
            out = np.where(self.species[idx] >= 0, self._taper_curve(idx, s, 0), out)
        return out

    def _taper_curve(self, idx: IntArray, s: FloatArray, derivative: int) -> FloatArray:
        """The species taper curve's radius (or its derivatives in s) at ``s``; rows whose
        species is -1 get the pine curve (callers take the power law there)."""
        from tcf_hil.world.forest.species import taper_poly

        assert self.species is not None and self.taper_length is not None
        sp = np.maximum(self.species[idx], 0)
        T = self.taper_length[idx]
        scale = self._taper_scale[idx]
        inside = (s <= T) & (s >= 0.0)
        d = taper_poly(sp, 1.0 - s / T, derivative) * (-1.0 / T) ** derivative
        out = scale * np.where(inside | (derivative == 0), d, 0.0)
        below = s < 0.0
        if derivative < 2 and below.any():
            # below the base the butt's slope goes on straight (C1: no kink where the stem
            # meets the ground, which a slope shows on its downhill side)
            slope = scale[below] * taper_poly(sp[below], np.ones(int(below.sum())), 1) / -T[below]
            out[below] = slope if derivative == 1 else out[below] + slope * s[below]
        return out

    @cached_property
    def _taper_scale(self) -> FloatArray:
        """Each stem's r_bh / P(1 - 1.3/T): its taper curve's radius per unit of P."""
        from tcf_hil.world.forest.species import taper_poly

        assert self.species is not None and self.taper_length is not None
        out: FloatArray = self.r_bh / taper_poly(
            np.maximum(self.species, 0), 1.0 - BREAST_HEIGHT_M / self.taper_length)
        return out

    def radius_d2(self, idx: IntArray, s: FloatArray) -> FloatArray:
        """|d2r/ds2| (1/m)."""
        L = self.length[idx]
        p = self.taper[idx]
        rem = np.clip(L - s, 1e-3, None)
        out = np.abs((self.r_bh[idx] - self.r_top[idx]) * p * (p - 1.0)
                     * rem ** (p - 2.0) / (L - BREAST_HEIGHT_M) ** p)
        if self.species is not None:
            out = np.where(self.species[idx] >= 0, np.abs(self._taper_curve(idx, s, 2)), out)
        return out

    def volume(self, samples: int = 513, chunk: int = 2048) -> FloatArray:
        """Above-ground wood volume per stem (m³): integral of pi r² along the arc length
        (trapezoid rule; the integrand is smooth, 513 samples agree with 4097 to 1e-5)."""
        n = len(self)
        out = np.empty(n)
        u = np.linspace(0.0, 1.0, samples)
        for a in range(0, n, chunk):
            idx_rows = np.arange(a, min(n, a + chunk))
            m = len(idx_rows)
            s = (u[None, :] * self.length[idx_rows, None]).ravel()
            idx = np.repeat(idx_rows, samples)
            g = (math.pi * self.radius(idx, s) ** 2 * self.speed(idx, s)).reshape(m, samples)
            out[idx_rows] = (np.trapezoid(g, dx=1.0, axis=1) * self.length[idx_rows]
                             / (samples - 1))
        return out

    def centerline(self, i: int, max_step_m: float = 0.5) -> tuple[FloatArray, FloatArray]:
        """Centre-line polyline base -> top with vertices at most ``max_step_m`` apart (along
        the arc), and the radius at each vertex."""
        L = float(self.length[i])
        # Equal axial steps of at most max_step / max|dC/ds|: every arc, hence every chord,
        # between vertices is at most max_step.
        vmax = float(self.max_speed(np.array([i]))[0])
        n = max(2, math.ceil(L * vmax / max_step_m) + 1)
        s = np.linspace(0.0, L, n)
        idx = np.full(n, i)
        return self.centre(idx, s), self.radius(idx, s)

    def max_reach(self, idx: IntArray | None = None) -> FloatArray:
        """Largest horizontal distance of any stem surface point from its base (m), of
        stems ``idx`` (all by default; each stem's the same either way)."""
        ix = np.arange(len(self)) if idx is None else np.asarray(idx, np.int64)
        n = len(ix)
        m = 64
        s = (np.linspace(-1.0, 1.0, m)[None, :]
             * np.maximum(self.length[ix], self.below[ix])[:, None])
        s = np.clip(s, -self.below[ix, None], self.length[ix, None]).ravel()
        rows = np.repeat(ix, m)
        c = self.centre(rows, s)
        horiz = np.hypot(c[:, 0] - self.base[rows, 0],
                         c[:, 1] - self.base[rows, 1]).reshape(n, m)
        r = self.radius(rows, s).reshape(n, m)
        out: FloatArray = np.max(horiz + r, axis=1)
        return out


def axial_samples(lo: FloatArray, hi: FloatArray, step: float) -> tuple[FloatArray, IntArray]:
    """Each row's ``np.arange(lo, hi, step)``, all at once: the points (concatenated) and
    how many each row has (the same values as the calls one by one)."""
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    counts = np.maximum(np.ceil((hi - lo) / step), 0).astype(np.int64)
    row = np.repeat(np.arange(len(lo)), counts)
    k = np.arange(len(row)) - np.repeat(np.cumsum(counts) - counts, counts)
    delta = (lo + step) - lo  # what np.arange steps by
    return lo[row] + k * delta[row], counts


def concat_stems(a: StemSet, b: StemSet) -> StemSet:
    """The stems of ``a`` then ``b`` in one set; a natural field one side lacks is filled
    with its "none" value (power-law taper, the intact length, no crook)."""
    if len(b) == 0:
        return a

    def opt(name: str, fill: Any) -> Any:
        va, vb = getattr(a, name), getattr(b, name)
        if va is None and vb is None:
            return None
        return np.concatenate([fill(a) if va is None else va, fill(b) if vb is None else vb])

    plain = {f: np.concatenate([getattr(a, f), getattr(b, f)])
             for f in ("base", "axis", "bend", "length", "sweep", "peak", "r_bh", "r_top",
                       "taper", "below")}
    return StemSet(
        **plain,
        species=opt("species", lambda s: np.full(len(s), -1, dtype=np.int64)),
        taper_length=opt("taper_length", lambda s: s.length),
        crook=opt("crook", lambda s: np.zeros((len(s), 3))),
        crook_s=opt("crook_s", lambda s: np.ones(len(s))),
        crook_w=opt("crook_w", lambda s: np.ones(len(s))))


def unit_perp(axis: FloatArray, angle: FloatArray) -> FloatArray:
    """Unit vectors perpendicular to ``axis`` at azimuth-like ``angle`` around it."""
    ref = np.where(np.abs(axis[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(ref, axis)
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    e2 = np.cross(axis, e1)
    return np.cos(angle)[:, None] * e1 + np.sin(angle)[:, None] * e2


def lean_axes(lean_deg: FloatArray, azimuth: FloatArray) -> FloatArray:
    """Unit stem axes leaning ``lean_deg`` from the vertical towards ``azimuth`` (radians)."""
    lean = np.radians(lean_deg)
    return np.stack([np.sin(lean) * np.cos(azimuth), np.sin(lean) * np.sin(azimuth),
                     np.cos(lean)], axis=1)
