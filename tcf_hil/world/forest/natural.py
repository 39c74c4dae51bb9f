"""Natural stems: species, taper, height from DBH, suppressed stems and defects as shapes.

Used by :func:`tcf_hil.world.forest.generate_forest` where ``stand.kind = "natural"``. The stems
keep the paper's placement, terrain, count and class shares (``stems.class_mix``); what
changes is what a stem is:

- **species** by the shares of ``[stand.pine]``, ``[stand.spruce]``, ``[stand.birch]``
  (exact counts, largest remainder), each with its taper curve and height model
  (:mod:`tcf_hil.world.forest.species`: Laasasenaho 1982, Pukkala et al. 2009);
- **DBH** from ``stems.dbh`` (``weibull``, ``normal``, ...), per species where its table
  gives a mean and SD; **suppressed** stems (``stand.suppressed_share``) draw theirs
  uniformly in ``stand.suppressed_dbh_m``;
- **height** on the species' height curve plus its published residual (a normal truncated
  at two SD, scaled by ``stand.height_sd_scale``), never below 0.6 of the curve's height nor
  below 2 m (assumptions: the published SD is one figure for all sizes, which would give
  small stems implausible heights);
- **defects as shapes**: every stem has a sweep (the paper's bow, drawn in its class's
  ``stems.sweep_m`` range) and its lean; an X stem gets the one defect that makes it X,
  drawn by the ``stand.defects.x_*`` shares: a sweep beyond ``other_threshold_m``, a
  **crook** (a sideways shift over less than a metre), a **fork** (a second leader from
  the stem), a **broken top** (the stem ends at a fraction of its intact height, as thick as
  it was there) or a **double stem** (a second stem parting near the ground). The sizes and
  shares are assumptions (no published rates were found; see the README).

The class follows :func:`classify_defects`; the ground truth lists every defect
(``{type, height_m, magnitude_m}``) and the one that decided the class.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tcf_hil.scenario import CLASSES, Scenario
from tcf_hil.world.forest.classes import class_counts
from tcf_hil.world.forest.dbh import draw_dbh
from tcf_hil.world.forest.species import HEIGHT_SD_M, SPECIES, mean_height
from tcf_hil.world.forest.stems import BREAST_HEIGHT_M, StemSet, lean_axes, unit_perp

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

X_DEFECTS: tuple[str, ...] = ("sweep", "crook", "fork", "broken_top", "double_stem")
"""Defects that can make a stem X (``stand.defects.x_<name>`` gives each one's share)."""
DEFECT_KINDS: tuple[str, ...] = ("sweep", "crook", "fork", "broken_top", "double_stem", "lean")
_PART_TOP_RADIUS_M = 0.005
_PART_TAPER = 0.8


def classify_defects(defects: list[dict[str, Any]], curve_threshold_m: float,
                     other_threshold_m: float) -> tuple[str, int | None]:
    """The class of a stem from its defects, and the index of the defect that decided it.

    X if it has a crook, a fork, a broken top or a double stem, or a sweep at or above
    ``other_threshold_m``; else C if its sweep is at or above ``curve_threshold_m``; else S.
    Of several defects that make a stem X, the lowest on the stem decides (the harvester
    head meets it first); a lean never decides. S has no deciding defect (None).
    """
    x = [i for i, d in enumerate(defects)
         if d["type"] in ("crook", "fork", "broken_top", "double_stem")
         or (d["type"] == "sweep" and d["magnitude_m"] >= other_threshold_m)]
    if x:
        return "X", min(x, key=lambda i: (defects[i]["height_m"], i))
    c = [i for i, d in enumerate(defects)
         if d["type"] == "sweep" and d["magnitude_m"] >= curve_threshold_m]
    if c:
        return "C", c[0]
    return "S", None


@dataclass
class Natural:
    """What a natural forest knows beyond the paper's stems: per stem its species code,
    whether it is suppressed, its defects (lists of dicts) and the index of the deciding
    defect (-1: none); the parts (second leaders and second stems) with their owners."""

    species: IntArray
    suppressed: NDArray[np.bool_]
    defects: list[list[dict[str, Any]]]
    deciding: IntArray
    parts: StemSet
    part_owner: IntArray  # 0-based stem index of each part
    part_kind: list[str]  # "fork" or "double_stem"


def _labels(shares: dict[str, float], n: int, rng: np.random.Generator) -> NDArray[np.str_]:
    """``n`` labels in exact shares, in random order."""
    counts = class_counts(shares, n)
    out = np.array([k for k in shares for _ in range(counts[k])], dtype="<U16")
    return out[rng.permutation(n)] if n else out


@dataclass
class _Draw:
    """Every random choice of a natural stand, so that a stem can be turned (a conflict
    re-draw) and its shapes rebuilt."""

    base: FloatArray
    species: IntArray
    suppressed: NDArray[np.bool_]
    dbh: FloatArray
    height: FloatArray  # intact height
    classes: NDArray[np.str_]
    x_kind: NDArray[np.str_]  # "" for S and C stems
    sweep: FloatArray
    peak: FloatArray
    lean: FloatArray
    lean_az: FloatArray
    bend_ang: FloatArray
    u: FloatArray  # (n, 5) uniform draws for the defect's position, size, shape, angle
    part_az: FloatArray


def draw(scn: Scenario, base: FloatArray, rng: np.random.Generator) -> _Draw:
    """Draw everything of ``len(base)`` natural stems."""
    st, sd = scn.stems, scn.stand
    n = len(base)
    sp_shares = {name: getattr(sd, name).share for name in SPECIES}
    species = np.array([SPECIES.index(str(s)) for s in _labels(sp_shares, n, rng)],
                       dtype=np.int64)
    n_sup = round(sd.suppressed_share * n)
    suppressed = np.zeros(n, dtype=bool)
    suppressed[rng.permutation(n)[:n_sup]] = True
    dbh = np.empty(n)
    for code, name in enumerate(SPECIES):
        cfg = getattr(sd, name)
        rows = np.flatnonzero((species == code) & ~suppressed)
        d = replace(st.dbh, mean_m=cfg.dbh_mean_m or st.dbh.mean_m,
                    sd_m=cfg.dbh_sd_m or st.dbh.sd_m)
        dbh[rows] = draw_dbh(d, len(rows), rng)
    dbh[suppressed] = rng.uniform(*sd.suppressed_dbh_m, n_sup)
    curve = mean_height(species, dbh, sd.site)
    z = rng.standard_normal(n)
    for _ in range(50):  # a normal truncated at two SD
        far = np.abs(z) > 2.0
        if not far.any():
            break
        z[far] = rng.standard_normal(int(far.sum()))
    z = np.clip(z, -2.0, 2.0)
    height = np.maximum.reduce([curve + z * HEIGHT_SD_M[species] * sd.height_sd_scale,
                                0.6 * curve, np.full(n, 2.0)])
    mix = {c: getattr(st.class_mix, c) for c in CLASSES}
    classes = _labels(mix, n, rng).astype("<U1")
    xs = np.flatnonzero(classes == "X")
    x_kind = np.full(n, "", dtype="<U16")
    x_kind[xs] = _labels({k: getattr(sd.defects, "x_" + k) for k in X_DEFECTS}, len(xs), rng)
    # The sweep: its class's range; an X stem made X by another defect sweeps as S or C do.
    sweep = np.zeros(n)
    sweep_class = classes.copy()
    other = (classes == "X") & (x_kind != "sweep")
    sc = mix["S"] + mix["C"]
    p_c = mix["C"] / sc if sc > 0 else 0.0
    sweep_class[other] = np.where(rng.uniform(0.0, 1.0, int(other.sum())) < p_c, "C", "S")
    for c in CLASSES:
        m = sweep_class == c
        lo, hi = getattr(st.sweep_m, c)
        sweep[m] = rng.uniform(lo, hi, int(m.sum()))
    return _Draw(
        base=base, species=species, suppressed=suppressed, dbh=dbh, height=height,
        classes=classes, x_kind=x_kind, sweep=sweep, peak=rng.uniform(0.35, 0.65, n),
        lean=rng.uniform(st.lean_deg[0], st.lean_deg[1], n),
        lean_az=rng.uniform(0.0, 2.0 * math.pi, n),
        bend_ang=rng.uniform(0.0, 2.0 * math.pi, n), u=rng.uniform(0.0, 1.0, (n, 5)),
        part_az=rng.uniform(0.0, 2.0 * math.pi, n))


def _lerp(rng_pair: tuple[float, float], u: FloatArray) -> FloatArray:
    lo, hi = rng_pair
    out: FloatArray = lo + (hi - lo) * u
    return out


def build(scn: Scenario, dr: _Draw) -> tuple[StemSet, StemSet, IntArray, list[str]]:
    """The stems and their parts (second leaders, second stems) from the draws."""
    st, df = scn.stems, scn.stand.defects
    n = len(dr.base)
    axis = lean_axes(dr.lean, dr.lean_az)
    intact = dr.height / axis[:, 2]
    length = intact.copy()
    broken = dr.x_kind == "broken_top"
    # a broken top stands above breast height (half a metre at least: it has a DBH)
    length[broken] = np.maximum(intact[broken] * _lerp(df.broken_height, dr.u[broken, 0]),
                                np.minimum(0.98 * intact[broken], BREAST_HEIGHT_M + 0.5))
    crook = np.zeros((n, 3))
    crook_s = np.full(n, 1.0)
    crook_w = np.full(n, 1.0)
    ck = np.flatnonzero(dr.x_kind == "crook")
    if len(ck):
        # within the stem: above breast height where it can, ending 0.3 m below the top
        crook_w[ck] = np.minimum(_lerp(df.crook_length_m, dr.u[ck, 1]), 0.4 * intact[ck])
        hi = intact[ck] - crook_w[ck] - 0.3
        lo = np.minimum(BREAST_HEIGHT_M + 0.2, hi)
        crook_s[ck] = np.clip(_lerp(df.crook_height, dr.u[ck, 0]) * intact[ck], lo, hi)
        crook[ck] = (_lerp(df.crook_offset_m, dr.u[ck, 2])[:, None]
                     * unit_perp(axis[ck], 2.0 * math.pi * dr.u[ck, 3]))
    stems = StemSet(
        base=dr.base, axis=axis, bend=unit_perp(axis, dr.bend_ang), length=length,
        sweep=dr.sweep, peak=dr.peak, r_bh=dr.dbh / 2.0, r_top=np.zeros(n),
        taper=np.ones(n), below=np.full(n, st.below_ground_m), species=dr.species,
        taper_length=intact, crook=crook, crook_s=crook_s, crook_w=crook_w)
    # Parts: a fork's second leader, a double stem's second stem.
    rows, kinds, s0, ang, ratio = [], [], [], [], []
    for i in np.flatnonzero((dr.x_kind == "fork") | (dr.x_kind == "double_stem")).tolist():
        fork = dr.x_kind[i] == "fork"
        u = dr.u[i]
        rows.append(i)
        kinds.append("fork" if fork else "double_stem")
        s0.append(float(_lerp(df.fork_height, u[0:1])[0] * intact[i]) if fork
                  else float(_lerp(df.double_height_m, u[0:1])[0]))
        ang.append(float(_lerp(df.fork_angle_deg if fork else df.double_angle_deg, u[1:2])[0]))
        ratio.append(float(_lerp(df.fork_diameter_ratio if fork else df.double_diameter_ratio,
                                 u[2:3])[0]))
    idx = np.asarray(rows, dtype=np.int64)
    s = np.asarray(s0, dtype=np.float64)
    pbase = stems.centre(idx, s) if len(idx) else np.zeros((0, 3))
    r0 = stems.radius(idx, s) * np.asarray(ratio) if len(idx) else np.zeros(0)
    a = np.radians(np.asarray(ang, dtype=np.float64))
    pax = (np.cos(a)[:, None] * axis[idx]
           + np.sin(a)[:, None] * unit_perp(axis[idx], dr.part_az[idx])) if len(idx) \
        else np.zeros((0, 3))
    # the second leader or stem reaches about as high as the stem (0.85-1 of the rest)
    plen = (intact[idx] - s) * (0.85 + 0.15 * dr.u[idx, 4]) / np.maximum(
        np.cos(a), 0.2) if len(idx) else np.zeros(0)
    plen = np.maximum(plen, BREAST_HEIGHT_M + 0.5)
    r_top = np.minimum(_PART_TOP_RADIUS_M, 0.5 * r0)
    # power law with r(0) = r0: r_bh from r(0) = r_top + (r_bh - r_top) (L/(L-1.3))^p
    r_bh = r_top + (r0 - r_top) * ((plen - BREAST_HEIGHT_M) / plen) ** _PART_TAPER
    m = len(idx)
    parts = StemSet(
        base=pbase, axis=pax, bend=unit_perp(pax, np.zeros(m)) if m else np.zeros((0, 3)),
        length=plen, sweep=np.zeros(m), peak=np.full(m, 0.5), r_bh=r_bh, r_top=r_top,
        taper=np.full(m, _PART_TAPER), below=np.zeros(m))
    return stems, parts, idx, kinds


def _deviations(stems: StemSet, idx: IntArray, a: FloatArray, b: FloatArray,
                samples: int = 257, chunk: int = 1024) -> FloatArray:
    """Largest distance of each stem ``idx[k]``'s centre line between axial ``a[k]`` and
    ``b[k]`` from the chord between them (vectorised over stems, ``chunk`` at a time)."""
    out = np.zeros(len(idx))
    u = np.linspace(0.0, 1.0, samples)
    for lo in range(0, len(idx), chunk):
        hi = min(lo + chunk, len(idx))
        m = hi - lo
        s = a[lo:hi, None] + (b[lo:hi] - a[lo:hi])[:, None] * u[None, :]
        c = stems.centre(np.repeat(idx[lo:hi], samples), s.ravel()).reshape(m, samples, 3)
        chord = c[:, -1] - c[:, 0]
        norm = np.linalg.norm(chord, axis=1)
        dev = np.linalg.norm(np.cross(c - c[:, :1], chord[:, None, :]), axis=2).max(axis=1)
        out[lo:hi] = np.where(norm > 0.0, dev / np.where(norm > 0.0, norm, 1.0), 0.0)
    return out


def maxcurve(stems: StemSet) -> FloatArray:
    """The paper's maxcurve, measured on the centre line (base to top): with a crook it is
    more than the bow's sweep."""
    n = len(stems)
    return _deviations(stems, np.arange(n), np.zeros(n), stems.length.astype(np.float64))


Defects = list[list[dict[str, Any]]]


def defects_of(scn: Scenario, dr: _Draw, stems: StemSet, parts: StemSet, owner: IntArray,
               kinds: list[str], origin: FloatArray
               ) -> tuple[Defects, IntArray, NDArray[np.str_]]:
    """Every stem's defects, the deciding one and the class the rule gives."""
    df, st = scn.stand.defects, scn.stems
    n = len(stems)
    az = stems.axis[:, 2]
    out: list[list[dict[str, Any]]] = [[] for _ in range(n)]
    # every stem's whole logs from the base, their sweep at once
    n_logs = np.floor((stems.length + 1e-9) / df.log_length_m).astype(np.int64)
    log_stem = np.repeat(np.arange(n), n_logs)
    log_k = np.arange(len(log_stem)) - np.repeat(np.cumsum(n_logs) - n_logs, n_logs)
    log_a: FloatArray = (log_k * df.log_length_m).astype(np.float64)
    log_b: FloatArray = log_a + df.log_length_m
    sweep = (100.0 * _deviations(stems, log_stem, log_a, log_b) / df.log_length_m).tolist()
    first_log = np.cumsum(n_logs) - n_logs
    for i in range(n):
        L = float(stems.length[i])
        logs = [round(v, 2) for v in sweep[first_log[i]:first_log[i] + n_logs[i]]]
        out[i].append({"type": "sweep", "height_m": round(float(dr.peak[i] * L * az[i]), 3),
                       "magnitude_m": round(float(dr.sweep[i]), 4),
                       "per_log_cm_per_m": logs, "log_length_m": df.log_length_m})
        if dr.x_kind[i] == "crook":
            mid = float(stems.crook_s[i] + 0.5 * stems.crook_w[i])  # type: ignore[index]
            out[i].append({"type": "crook", "height_m": round(mid * float(az[i]), 3),
                           "magnitude_m": round(float(np.linalg.norm(
                               stems.crook[i])), 4),  # type: ignore[index]
                           "length_m": round(float(stems.crook_w[i]), 3)})  # type: ignore[index]
        if dr.x_kind[i] == "broken_top":
            out[i].append({"type": "broken_top", "height_m": round(L * float(az[i]), 3),
                           "magnitude_m": round(2.0 * float(stems.radius(
                               np.array([i]), np.array([L]))[0]), 4),
                           "intact_height_m": round(float(dr.height[i]), 3)})
        if dr.lean[i] >= df.lean_record_deg and dr.lean[i] > 0.0:
            out[i].append({"type": "lean", "height_m": 0.0,
                           "magnitude_m": round(L * math.sin(math.radians(float(dr.lean[i]))),
                                                4),
                           "lean_deg": round(float(dr.lean[i]), 3)})
    for k, (i, kind) in enumerate(zip(owner.tolist(), kinds, strict=True)):
        base_h = float(parts.base[k, 2] - stems.base[i, 2])
        r0 = float(parts.radius(np.array([k]), np.zeros(1))[0])
        cl, radii = parts.centerline(k)
        out[i].append({"type": kind, "height_m": round(base_h, 3),
                       "magnitude_m": round(2.0 * r0, 4),
                       "angle_deg": round(math.degrees(math.acos(float(np.clip(
                           parts.axis[k] @ stems.axis[i], -1.0, 1.0)))), 2),
                       "centerline": np.round(cl + origin, 4).tolist(),
                       "radii": np.round(radii, 5).tolist()})
    for d in out:
        d.sort(key=lambda e: (e["height_m"], DEFECT_KINDS.index(e["type"])))
    deciding = np.full(n, -1, dtype=np.int64)
    classes = np.empty(n, dtype="<U1")
    for i in range(n):
        c, decider = classify_defects(out[i], st.curve_threshold_m, st.other_threshold_m)
        classes[i] = c
        deciding[i] = -1 if decider is None else decider
    return out, deciding, classes
