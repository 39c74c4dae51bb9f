"""Meshes from a geometric tolerance: stems as closed tubes, terrain as a grid.

Stem tessellation splits the tolerance between the two directions, so their sum is bounded:
the polygon inscribed in a circle of radius r with n sides has a chord error (sagitta) of
r(1 - cos(pi/n)); n is the smallest count that keeps it within 3/4 of the tolerance at the
stem's largest radius. Rings are spaced so that the straight segments between them stay within
1/4 of it from the curved, tapered surface, (|C''| + |r''|) * ds² / 8, and never more than
``max_ring_step_m`` apart. Points of the mesh are then within the tolerance of the true
surface: inside it on a straight stretch, possibly outside on the inner side of a bend.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.ndimage import maximum_filter1d

from tcf_hil.errors import ConfigError
from tcf_hil.world.forest.stems import StemSet
from tcf_hil.world.terrain import Terrain

FloatArray = NDArray[np.float64]


def sides_for(radius_m: float, tolerance_m: float, minimum: int = 6) -> int:
    """Polygon sides so that the inscribed polygon's chord error stays within tolerance."""
    if radius_m <= tolerance_m:
        return minimum
    return max(minimum, math.ceil(math.pi / math.acos(1.0 - tolerance_m / radius_m)))


def ring_positions(stems: StemSet, i: int, tolerance_m: float,
                   max_ring_step_m: float = 2.0, probe_step_m: float = 0.05) -> FloatArray:
    """Axial positions of the rings of stem ``i`` from ``-below`` to the top."""
    return all_ring_positions(stems, tolerance_m, max_ring_step_m, probe_step_m,
                              np.array([i]))[0]


_PROBES_PER_BATCH = 200_000


def all_ring_positions(stems: StemSet, tolerance_m: float, max_ring_step_m: float = 2.0,
                       probe_step_m: float = 0.05, ids: NDArray[np.int64] | None = None,
                       reach_m: float = 0.0) -> list[FloatArray]:
    """The ring positions of stems ``ids`` (all by default), from ``-below`` to the top:
    the curvature of each stem's centre line and radius probed every ``probe_step_m``, and
    rings spaced so that the straight segments between them stay within ``tolerance_m`` of
    the bent, tapered surface ((|C''| + |r''|) ds^2 / 8), at most ``max_ring_step_m`` apart,
    with one at the base (s = 0), where the stem meets the ground.

    ``reach_m`` > 0: each probe takes the greatest curvature within that distance of it, so
    that a segment which runs into a sharp bend (a crook's start) is spaced for the bend,
    not for the straight stem before it (without it, rays grazing a crooked stem 0.2 mm
    inside its surface crossed it whole just before the crook: the segment there had been
    spaced by the straight stem's curvature). 0 keeps each probe's own (the meshes').

    The probes of stems of about the same length are evaluated together (a few hundred
    thousand at a time), each stem's exactly as on its own."""
    ix = np.arange(len(stems)) if ids is None else np.asarray(ids, np.int64)
    out: list[FloatArray] = [np.zeros(0)] * len(ix)
    lo_all = -stems.below[ix].astype(np.float64)
    L_all = stems.length[ix].astype(np.float64)
    # np.arange(lo, L, step)'s points: lo + j * ((lo + step) - lo), ceil((L - lo) / step)
    delta = (lo_all + probe_step_m) - lo_all
    n_all = np.maximum(np.ceil((L_all - lo_all) / probe_step_m), 0).astype(np.int64)
    order = np.argsort(n_all, kind="stable")
    a = 0
    while a < len(order):
        b = a + 1
        while b < len(order) and (b - a + 1) * n_all[order[b]] <= _PROBES_PER_BATCH:
            b += 1
        rows = order[a:b]
        width = int(n_all[rows[-1]])
        j = np.arange(width, dtype=np.float64)
        probe = lo_all[rows, None] + j[None, :] * delta[rows, None]
        valid = j[None, :] < n_all[rows, None]
        idx = np.broadcast_to(ix[rows, None], probe.shape)[valid]
        pv = probe[valid]
        bend = np.zeros(probe.shape)
        bend[valid] = stems.curvature_bound(idx, pv) + stems.radius_d2(idx, pv)
        if reach_m > 0:  # probes past a stem's top are 0: they raise nothing
            bend = maximum_filter1d(bend, 2 * math.ceil(reach_m / probe_step_m) + 1, axis=1,
                                    mode="nearest")
        step = np.minimum(max_ring_step_m,
                          np.sqrt(8.0 * tolerance_m / np.maximum(bend, 1e-12)))
        density = np.cumsum(np.where(valid, probe_step_m / step, 0.0), axis=1)
        for k, r in enumerate(rows.tolist()):
            n = int(n_all[r])
            lo, L = float(lo_all[r]), float(L_all[r])
            dens = np.concatenate([[0.0], density[k, :n]])
            grid = np.concatenate([probe[k, :n], [L]])
            count = max(1, math.ceil(dens[-1]))
            targets = np.linspace(0.0, dens[-1], count + 1)
            s = np.interp(targets, dens, grid)
            s[0], s[-1] = lo, L
            out[r] = np.unique(np.concatenate([s, [0.0]]))
        a = b
    return out


_RADIAL_SHARE = 0.75


def _tube_faces(m: int, n: int) -> NDArray[np.int64]:
    """Faces of a closed tube of ``m`` rings with ``n`` sides; vertex ``m*n`` is the bottom
    centre and ``m*n + 1`` the top centre."""
    k = np.arange(m - 1)[:, None] * n
    j = np.arange(n)[None, :]
    a0, a1 = k + j, k + (j + 1) % n
    b0, b1 = a0 + n, a1 + n
    side = np.concatenate([np.stack([a0, a1, b1], -1), np.stack([a0, b1, b0], -1)],
                          axis=1).reshape(-1, 3)
    jj = np.arange(n)
    bottom = np.stack([np.full(n, m * n), (jj + 1) % n, jj], -1)
    top = np.stack([np.full(n, m * n + 1), (m - 1) * n + jj, (m - 1) * n + (jj + 1) % n], -1)
    return np.vstack([side, bottom, top]).astype(np.int64)


def _tubes(stems: StemSet, ids: NDArray[np.int64], s: FloatArray, n: int) -> FloatArray:
    """Vertices (k, m*n + 2, 3) of the tubes of stems ``ids`` with ring positions s (k, m)."""
    k, m = s.shape
    idx = np.repeat(ids, m)
    sf = s.ravel()
    c = stems.centre(idx, sf)
    u, b = stems.ring_frame(idx, sf)
    r = stems.radius(idx, sf)
    th = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    ring = (np.cos(th)[None, :, None] * u[:, None, :] + np.sin(th)[None, :, None] * b[:, None, :])
    verts = (c[:, None, :] + r[:, None, None] * ring).reshape(k, m * n, 3)
    c = c.reshape(k, m, 3)
    return np.concatenate([verts, c[:, :1], c[:, -1:]], axis=1)


def stem_mesh(stems: StemSet, tolerance_m: float,
              origin: FloatArray | None = None,
              ids: NDArray[np.int32] | None = None) -> trimesh.Trimesh:
    """All stems as one mesh; face attribute ``stem_id`` (1-based) tells which stem a face is
    (``ids``: the stem id of each tube, e.g. :meth:`Forest.tubes`'s; default 1..n).

    Stems are meshed in batches that share a ring and side count (one vectorised pass per
    batch); faces are ordered by stem id.

    Args:
        stems: the forest's stems (local coordinates).
        tolerance_m: maximum distance between the mesh and the true surface.
        origin: added to every vertex (world = local + origin), float64.
    """
    n_stems = len(stems)
    if n_stems == 0:
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    rings = all_ring_positions(stems, (1.0 - _RADIAL_SHARE) * tolerance_m)
    r0 = stems.radius(np.arange(n_stems), -stems.below)
    sides = np.array([sides_for(float(r), _RADIAL_SHARE * tolerance_m) for r in r0])
    ring_n = np.array([len(r) for r in rings])
    nverts = ring_n * sides + 2
    nfaces = 2 * (ring_n - 1) * sides + 2 * sides
    v_off = np.concatenate([[0], np.cumsum(nverts)])
    f_off = np.concatenate([[0], np.cumsum(nfaces)])
    verts = np.empty((int(v_off[-1]), 3))
    faces = np.empty((int(f_off[-1]), 3), dtype=np.int64)
    sid = np.arange(1, n_stems + 1, dtype=np.int32) if ids is None else ids.astype(np.int32)
    stem_id = np.repeat(sid, nfaces)
    keys = ring_n * 100_000 + sides
    for key in np.unique(keys):
        batch = np.flatnonzero(keys == key)
        m, n = int(ring_n[batch[0]]), int(sides[batch[0]])
        s = np.stack([rings[i] for i in batch])
        vv = _tubes(stems, batch, s, n)
        tmpl = _tube_faces(m, n)
        vrow = (v_off[batch][:, None] + np.arange(m * n + 2)[None, :]).ravel()
        verts[vrow] = vv.reshape(-1, 3)
        frow = (f_off[batch][:, None] + np.arange(len(tmpl))[None, :]).ravel()
        faces[frow] = (tmpl[None, :, :] + v_off[batch][:, None, None]).reshape(-1, 3)
    if origin is not None:
        verts = verts + origin
    mesh = trimesh.Trimesh(verts, faces, process=False)
    mesh.face_attributes["stem_id"] = stem_id
    return mesh


CURVE_TOLERANCE_M = 1e-4
"""How far a stem's round linear curve (:func:`stem_curves`) may stray from the true surface
between its points: 0.1 mm, a fifth of issue 21's 0.5 mm aim, the rest left to float32."""
CAP_OVERLAP_M = 5e-5
"""A top's disc is this much wider than the tube it closes, so no ray slips between them."""
CURVE_REACH_M = 0.25
"""How far along a stem a curve's ring spacing looks for sharper bends
(:func:`all_ring_positions`' ``reach_m``)."""
JOINT_INSET_M = 5e-5
"""How far a joint's sphere (:attr:`TubeCurves.joints`) is drawn in under the curve point's:
half the curve's tolerance, so that it stays inside the stem where the profile and the
centre line bend, and still fills a cut that a ray reaches 0.05 mm deep."""


@dataclass(frozen=True)
class TubeCurves:
    """Tubes as round linear curves with flat tops (:func:`stem_curves`): ``points`` (m, 4)
    x, y, z, radius; ``segments`` (k,) each segment's first point; ``flags`` (k,) its
    neighbours (1 one before it, 2 one after it: Embree then joins them without a cap, or
    leaves the end open where the point after is a guide, not a segment's); ``segment_id``
    (k,) its stem id; ``discs`` (q, 4) centre and radius and ``disc_normals`` (q, 3) of the
    flat discs closing the tops; ``disc_id`` (q,) their stem ids; ``joints`` (k, 4) centre
    and radius of a sphere inside the surface at each segment's first point (Embree's
    ``Curves.joints``: it fills the cut where two segments meet)."""

    points: FloatArray
    segments: NDArray[np.int64]
    flags: NDArray[np.uint8]
    segment_id: NDArray[np.int32]
    discs: FloatArray
    disc_normals: FloatArray
    disc_id: NDArray[np.int32]
    joints: FloatArray


def stem_curves(stems: StemSet, ids: NDArray[np.int32] | None = None,
                tolerance_m: float = CURVE_TOLERANCE_M) -> TubeCurves:
    """All stems as round linear curves (Embree's ``ROUND_LINEAR_CURVE``: a sphere swept
    along a polyline, its radius linear along each segment), an exact surface to within
    ``tolerance_m`` rather than a tessellation (``ids``: the stem id of each tube, default
    1..n).

    The points follow the mesh's ring positions for ``tolerance_m`` (:func:`ring_positions`,
    probed every centimetre, each probe taking the sharpest bend within
    :data:`CURVE_REACH_M`: straight segments stay within it of the bent, tapered surface).
    Each is the sphere that touches the true surface all along one ring: centred
    where the surface's normals from that ring meet the centre line (``r r'`` along the
    tangent from the ring's centre, a few centimetres below it where the butt swells) with
    radius ``r sqrt(1 + r'^2)``; the sweep between two such spheres touches both rings and
    stays within the tolerance between them. (Spheres at the rings' centres, of radius
    ``r cos a``, miss the surface by ``r |r'| r'' ds``-sized steps: 0.6 mm at a big
    pine's butt.) The top is flat, as the stem's (a broken top is a cut):
    the last segment is flagged as having a neighbour, a guide point straight on, so Embree
    leaves it open instead of rounding it with a sphere, and a disc closes it. The bottom,
    below the ground, keeps its sphere. Where two segments join, Embree cuts their tubes
    at the ring the joint's sphere touches, and a grazing ray can slip through the cut:
    ``joints`` holds each segment's first sphere, drawn in by :data:`JOINT_INSET_M`, to
    fill it."""
    n_stems = len(stems)
    sid = np.arange(1, n_stems + 1, dtype=np.int32) if ids is None else ids.astype(np.int32)
    if n_stems == 0:
        z4, z3 = np.zeros((0, 4)), np.zeros((0, 3))
        return TubeCurves(z4, np.zeros(0, np.int64), np.zeros(0, np.uint8),
                          np.zeros(0, np.int32), z4, z3, np.zeros(0, np.int32), z4)
    rings = all_ring_positions(stems, tolerance_m, probe_step_m=0.01, reach_m=CURVE_REACH_M)
    counts = np.array([len(r) for r in rings], np.int64)
    idx = np.repeat(np.arange(n_stems), counts)
    s = np.concatenate(rings)
    c = stems.centre(idx, s)
    r = stems.radius(idx, s)
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    last = first + counts - 1
    # the taper's slope at each point (dr/ds of the smooth radius, by a central difference
    # of a tenth of a millimetre; one-sided at a broken top, where the radius stops)
    at = np.arange(len(s))
    h = 1e-4
    length = np.repeat(stems.length, counts)  # each point's stem's
    hi = np.minimum(s + h, length)
    lo = hi - 2.0 * h
    slope = (stems.radius(idx, hi) - stems.radius(idx, lo)) / (2.0 * h)
    # the sphere that touches the surface along the ring at s: centred where the surface's
    # normal there meets the centre line, r r' along it, of radius r sqrt(1 + r'^2) (a
    # tapering stem's spheres sit a few centimetres below the rings they touch where the
    # butt swells); a tube's end points keep their ring's centre, so that the tube ends
    # there, and the radius r cos a of the cone they start or end
    end = np.zeros(len(s), bool)
    end[first] = end[last] = True
    shift = np.where(end, 0.0, r * slope)
    pts = np.column_stack([c + shift[:, None] * stems.tangent(idx, s),
                           np.where(end, r / np.sqrt(1.0 + slope**2),
                                    r * np.sqrt(1.0 + slope**2))])
    # a guide point after each tube's top, straight on along its last segment
    axis = c[last] - c[last - 1]
    axis /= np.linalg.norm(axis, axis=1)[:, None]
    guide = np.column_stack([c[last] + 0.1 * axis, pts[last, 3]])
    at_out = at + np.repeat(np.arange(n_stems), counts)  # each tube shifted by the guides
    points = np.empty((len(s) + n_stems, 4))
    points[at_out] = pts
    points[last + np.arange(n_stems) + 1] = guide
    seg_mask = np.ones(len(s), bool)
    seg_mask[last] = False
    segments = at_out[seg_mask]
    seg_stem = idx[seg_mask]
    flags = np.full(len(segments), 3, np.uint8)
    flags[np.searchsorted(segments, at_out[first])] &= np.uint8(2)  # nothing before the first
    top = r[last] > CAP_OVERLAP_M
    # at each segment's first point, its sphere drawn in by JOINT_INSET_M: it touches the
    # surface along the ring, where Embree's cut between two segments lies, and lies
    # inside the stem elsewhere (a test holds it); never past a flat top
    top_gap = length - (s + shift)
    joints = np.column_stack([pts[:, :3], np.maximum(np.minimum(pts[:, 3], top_gap)
                                                     - JOINT_INSET_M, 0.0)])[seg_mask]
    return TubeCurves(points, segments.astype(np.int64), flags, sid[seg_stem],
                      np.column_stack([c[last], r[last] + CAP_OVERLAP_M])[top], axis[top],
                      sid[top], joints)


def terrain_grid(terrain: Terrain, bounds: tuple[float, float, float, float],
                 tolerance_m: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The terrain's vertex lattice over ``bounds`` at ``tolerance_m`` (xs, ys, z[ny, nx]):
    what :func:`terrain_mesh` triangulates; a ConfigError where it needs too many vertices."""
    try:
        return terrain.grid(bounds, tolerance_m)
    except ValueError as err:
        raise ConfigError("terrain.tolerance_mm", tolerance_m * 1000, str(err)) from err


def terrain_mesh(terrain: Terrain, bounds: tuple[float, float, float, float],
                 tolerance_m: float, origin: FloatArray | None = None) -> trimesh.Trimesh:
    """The terrain over ``bounds`` as a regular triangulated grid (float64 vertices), each
    cell split along its diagonal from (x_i, y_j) to (x_i+1, y_j+1)."""
    xs, ys, z = terrain_grid(terrain, bounds, tolerance_m)
    nx, ny = len(xs), len(ys)
    X, Y = np.meshgrid(xs, ys)
    verts = np.column_stack([X.ravel(), Y.ravel(), z.ravel()])
    if origin is not None:
        verts = verts + origin
    k = (np.arange(ny - 1)[:, None] * nx + np.arange(nx - 1)[None, :]).ravel()
    faces = np.concatenate([np.stack([k, k + 1, k + nx + 1], -1),
                            np.stack([k, k + nx + 1, k + nx], -1)])
    return trimesh.Trimesh(verts, faces, process=False)
