"""The harvester's path through the forest and the poses along it.

A track is a polyline (start, waypoints, end) driven in one or more passes. Corners are rounded
with circular arcs (``turn_radius_m``, shrunk where legs are short); a pass that returns along
the same road is driven in reverse gear after a standstill, a pass beside it (``pass_offset_m``)
is reached by a U-turn. Each leg (between standstills) has a trapezoidal speed profile
(``accel_m_s2``; 0 is the paper's constant speed). The machine's base point rests on the
ground under its footprint (the mean height under its four edges); pitch and roll follow that
ground (REP-103: x forward, y left, z up; R = Rz(yaw) Ry(pitch) Rx(roll), positive pitch = nose
down). The lidar sits on the machine at the
mount pose.

Everything is a function of simulation time in integer nanoseconds and works on arrays, so the
lidar emulator can take one pose per column. Velocities, accelerations and angular rates (for
the IMU) are central differences over ``DIFF_NS``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray

from emulators.jit import compiled, register_kernel_source
from tcf_hil._rotations import rotation_ypr
from tcf_hil.errors import ConfigError
from tcf_hil.scenario import PoseErrorConfig, TrackConfig
from tcf_hil.world.terrain import Terrain

register_kernel_source(__file__)  # _eval_pieces is a kernel (see emulators.jit)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

GRAVITY_M_S2 = 9.80665
DIFF_NS = 1_000_000  # step of the central differences (1 ms)
_CUSP_RAD = math.pi - 1e-6
# Knots of Trajectory.sensor_pose_dense: at most this far apart in time, and close enough
# that no wave or turn the pose follows advances more than this phase between two.
DENSE_KNOT_NS = 6_400_000
DENSE_PHASE_RAD = 0.03


@dataclass(frozen=True)
class _Leg:
    """Segments between two standstills, in travel direction: arrays over segments."""

    x0: FloatArray
    y0: FloatArray
    th0: FloatArray  # travel direction at the segment start (rad, counter-clockwise from +x)
    k: FloatArray  # curvature (1/m, left positive); 0: straight
    s0: FloatArray  # arc length at the segment start
    tag: IntArray  # pass number of each segment
    length: float
    gear: int  # +1 forward, -1 reverse
    # speed profile
    t_acc: float
    t_cruise: float
    v_peak: float
    accel: float

    @property
    def duration_s(self) -> float:
        return 2 * self.t_acc + self.t_cruise

    def distance(self, tau: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Arc length and speed (>= 0) at time tau (s) after the leg's start."""
        T, ta, v, a = self.duration_s, self.t_acc, self.v_peak, self.accel
        before = tau < 0.0
        tau = np.clip(tau, 0.0, T)
        if ta == 0.0:
            return np.minimum(v * tau, self.length), np.where(before | (tau >= T), 0.0, v)
        d_a = 0.5 * a * ta * ta
        s = np.where(tau < ta, 0.5 * a * tau * tau,
                     np.where(tau <= ta + self.t_cruise, d_a + v * (tau - ta),
                              self.length - 0.5 * a * (T - tau) ** 2))
        sp = np.where(tau < ta, a * tau, np.where(tau <= ta + self.t_cruise, v, a * (T - tau)))
        return np.clip(s, 0.0, self.length), np.where(before, 0.0, np.maximum(sp, 0.0))

    def time_at(self, s: FloatArray) -> FloatArray:
        """The inverse of :meth:`distance`: time after the leg's start at arc length s."""
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, self.length)
        ta, tc, v, a = self.t_acc, self.t_cruise, self.v_peak, self.accel
        if v <= 0.0:
            return np.zeros_like(s)
        if ta == 0.0:
            return s / v
        d_a = 0.5 * a * ta * ta
        result: FloatArray = np.where(
            s < d_a, np.sqrt(2.0 * s / a),
            np.where(s <= d_a + v * tc, ta + (s - d_a) / v,
                     self.duration_s - np.sqrt(np.maximum(2.0 * (self.length - s) / a, 0.0))))
        return result

    def point(self, s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, IntArray]:
        """x, y, travel direction and pass tag at arc length s."""
        if len(self.s0) == 0:
            z = np.zeros_like(s)
            return z + self.x0_fallback[0], z + self.x0_fallback[1], z, np.zeros(len(s), np.int64)
        i = np.clip(np.searchsorted(self.s0, s, side="right") - 1, 0, len(self.s0) - 1)
        ds = s - self.s0[i]
        th0, k = self.th0[i], self.k[i]
        th = th0 + k * ds
        straight = k == 0.0
        safe_k = np.where(straight, 1.0, k)
        x = self.x0[i] + np.where(straight, ds * np.cos(th0), (np.sin(th) - np.sin(th0)) / safe_k)
        y = self.y0[i] + np.where(straight, ds * np.sin(th0), (np.cos(th0) - np.cos(th)) / safe_k)
        return x, y, th, self.tag[i]

    x0_fallback: tuple[float, float] = (0.0, 0.0)


def _fillet_leg(pts: list[tuple[float, float, int]], radius: float
                ) -> tuple[list[tuple[float, float, float, float, float, int]], float]:
    """Segments (x0, y0, th0, length, k, tag) of a polyline with rounded corners."""
    P = np.array([(p[0], p[1]) for p in pts], dtype=np.float64)
    tags = [p[2] for p in pts]
    d = np.diff(P, axis=0)
    lens = np.hypot(d[:, 0], d[:, 1])
    u = d / lens[:, None]
    n = len(P)
    tan_len = np.zeros(n)
    k_at = np.zeros(n)
    turn = np.zeros(n)
    for i in range(1, n - 1):
        delta = math.atan2(u[i - 1, 0] * u[i, 1] - u[i - 1, 1] * u[i, 0], float(u[i - 1] @ u[i]))
        if abs(delta) < 1e-12:
            continue
        share_in = lens[i - 1] if i - 1 == 0 else lens[i - 1] / 2
        share_out = lens[i] if i == n - 2 else lens[i] / 2
        t = min(radius * math.tan(abs(delta) / 2), share_in, share_out)
        r = t / math.tan(abs(delta) / 2)
        tan_len[i], k_at[i], turn[i] = t, math.copysign(1.0 / r, delta), delta
    segs = []
    total = 0.0
    for i in range(n - 1):
        a = P[i] + u[i] * tan_len[i]
        b = P[i + 1] - u[i] * tan_len[i + 1]
        th = math.atan2(u[i, 1], u[i, 0])
        ln = float(np.hypot(*(b - a)))
        if ln > 0:
            segs.append((float(a[0]), float(a[1]), th, ln, 0.0, tags[i + 1]))
            total += ln
        if i + 1 < n - 1 and turn[i + 1] != 0.0:
            r = 1.0 / abs(k_at[i + 1])
            segs.append((float(b[0]), float(b[1]), th, r * abs(turn[i + 1]), k_at[i + 1],
                         tags[i + 1]))
            total += r * abs(turn[i + 1])
    return segs, total


def _profile(length: float, v: float, a: float) -> tuple[float, float, float]:
    """(t_acc, t_cruise, v_peak) of a trapezoid (a = 0: constant speed)."""
    if length <= 0:
        return 0.0, 0.0, 0.0
    if a == 0.0:
        return 0.0, length / v, v
    d_a = v * v / (2 * a)
    if 2 * d_a <= length:
        return v / a, (length - 2 * d_a) / v, v
    vp = math.sqrt(a * length)
    return vp / a, 0.0, vp


@dataclass(frozen=True)
class VehicleState:
    """The machine at some times (arrays over samples)."""

    position: FloatArray  # (n, 3) base point on the ground, local world frame
    yaw: FloatArray  # rad, counter-clockwise from +x (east)
    pitch: FloatArray  # rad, REP-103 (positive nose down)
    roll: FloatArray  # rad (positive left side up)
    speed: FloatArray  # m/s along the forward axis (negative in reverse)
    pass_no: IntArray
    moving: NDArray[np.bool_]

    @property
    def heading_deg(self) -> FloatArray:
        """Compass heading: 0 = north (+y), clockwise, in [0, 360)."""
        result: FloatArray = np.mod(90.0 - np.degrees(self.yaw), 360.0)
        return result

    @property
    def rotation(self) -> FloatArray:
        return rotation_ypr(self.yaw, self.pitch, self.roll)


@dataclass(frozen=True)
class Trajectory:
    """A scenario's track over its terrain, starting to move at ``t0_ns``."""

    track: TrackConfig
    terrain: Terrain
    t0_ns: int = 1_000_000_000
    legs: tuple[_Leg, ...] = field(init=False, repr=False)
    leg_start_s: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        tr = self.track
        base = [(tr.start_m[0], tr.start_m[1]), *tr.waypoints_m, (tr.end_m[0], tr.end_m[1])]
        d = np.array(base[-1]) - np.array(base[0])
        dn = float(np.hypot(*d))
        normal = np.array([-d[1], d[0]]) / dn if dn > 0 else np.array([0.0, 0.0])
        if tr.passes > 1 and tr.pass_offset_m > 0 and dn == 0:
            raise ConfigError("track.pass_offset_m", tr.pass_offset_m,
                              "0 when start and end coincide (no direction to offset)", None)
        pts: list[tuple[float, float, int]] = []
        for p in range(tr.passes):
            seq = base if p % 2 == 0 else base[::-1]
            off = normal * tr.pass_offset_m * p
            for x, y in seq:
                q = (float(x + off[0]), float(y + off[1]), p)
                if not pts or math.hypot(q[0] - pts[-1][0], q[1] - pts[-1][1]) > 1e-9:
                    pts.append(q)
        # split into legs at cusps (the road driven back: reverse gear)
        legs_pts: list[list[tuple[float, float, int]]] = [pts[:2]]
        for i in range(2, len(pts)):
            a, b, c = pts[i - 2], pts[i - 1], pts[i]
            u = (b[0] - a[0], b[1] - a[1])
            w = (c[0] - b[0], c[1] - b[1])
            ang = abs(math.atan2(u[0] * w[1] - u[1] * w[0], u[0] * w[0] + u[1] * w[1]))
            if ang >= _CUSP_RAD:
                legs_pts.append([b, c])
            else:
                legs_pts[-1].append(c)
        legs = []
        for j, lp in enumerate(legs_pts):
            segs: list[tuple[float, float, float, float, float, int]] = []
            length = 0.0
            if len(lp) >= 2:
                segs, length = _fillet_leg(lp, tr.turn_radius_m)
            ta, tc, vp = _profile(length, tr.speed_m_s, tr.accel_m_s2)
            arr = np.array([s[:5] for s in segs], dtype=np.float64).reshape(-1, 5)
            s0 = np.concatenate([[0.0], np.cumsum(arr[:, 3])[:-1]]) if len(arr) else np.zeros(0)
            legs.append(_Leg(arr[:, 0].copy(), arr[:, 1].copy(), arr[:, 2].copy(),
                             arr[:, 4].copy(), s0, np.array([s[5] for s in segs], np.int64),
                             length, 1 if j % 2 == 0 else -1, ta, tc, vp, tr.accel_m_s2,
                             (lp[0][0], lp[0][1])))
        starts = [0.0]
        for leg in legs[:-1]:
            starts.append(starts[-1] + leg.duration_s + tr.stop_s)
        object.__setattr__(self, "legs", tuple(legs))
        object.__setattr__(self, "leg_start_s", np.array(starts))

    @classmethod
    def from_config(cls, track: TrackConfig, terrain: Terrain,
                    t0_ns: int = 1_000_000_000) -> Trajectory:
        return cls(track, terrain, t0_ns)

    @property
    def length_m(self) -> float:
        return float(sum(leg.length for leg in self.legs))

    @property
    def duration_ns(self) -> int:
        """From ``t0_ns`` until the machine stops at the end."""
        return round((self.leg_start_s[-1] + self.legs[-1].duration_s) * 1e9)

    @property
    def end_ns(self) -> int:
        return self.t0_ns + self.duration_ns

    # -- poses ------------------------------------------------------------------------------
    def vehicle_state(self, t_ns: IntArray | int, *, pointwise: bool = False) -> VehicleState:
        """The machine's state at each of ``t_ns``. ``pointwise``: the terrain's heights
        evaluated point by point (:meth:`Terrain.height`), so each state has the same bits as
        when asked alone."""
        t = np.atleast_1d(np.asarray(t_ns, dtype=np.int64))
        ts = (t - self.t0_ns).astype(np.float64) / 1e9
        j = np.clip(np.searchsorted(self.leg_start_s, ts, side="right") - 1, 0,
                    len(self.legs) - 1)
        n = len(t)
        x, y, th, sp = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
        tag = np.zeros(n, np.int64)
        gear = np.empty(n)
        for li, leg in enumerate(self.legs):
            m = j == li
            if not m.any():
                continue
            s, v = leg.distance(ts[m] - self.leg_start_s[li])
            x[m], y[m], th[m], tag[m] = leg.point(s)
            sp[m] = v
            gear[m] = leg.gear
        if len(self.legs[0].s0) == 0:  # a standing machine facing from start to end
            tr = self.track
            th[:] = math.atan2(tr.end_m[1] - tr.start_m[1], tr.end_m[0] - tr.start_m[0])
        yaw = th + np.where(gear < 0, math.pi, 0.0)
        yaw = np.mod(yaw + math.pi, 2 * math.pi) - math.pi
        pitch, roll = np.zeros(n), np.zeros(n)
        if self.track.follow_terrain and not self.terrain.is_flat:
            # the machine rests on its footprint: height, pitch and roll from the ground under
            # its front, rear, left and right edges (bumps shorter than it are bridged)
            L, W = self.track.footprint_m
            fx, fy = np.cos(yaw), np.sin(yaw)
            def h(hx: FloatArray, hy: FloatArray) -> FloatArray:
                return self.terrain.height(hx, hy, pointwise=pointwise)

            front, rear = h(x + fx * L / 2, y + fy * L / 2), h(x - fx * L / 2, y - fy * L / 2)
            left, right = h(x - fy * W / 2, y + fx * W / 2), h(x + fy * W / 2, y - fx * W / 2)
            pitch = np.arctan2(rear - front, L)
            roll = np.arctan2(left - right, W)
            z = (front + rear + left + right) / 4.0
        else:
            z = self.terrain.height(x, y, pointwise=pointwise)
        return VehicleState(np.column_stack([x, y, z]), yaw, pitch, roll, sp * gear,
                            tag, sp > 0)

    def sensor_pose(self, t_ns: IntArray) -> tuple[FloatArray, FloatArray]:
        """Lidar sensor frame in the local world: positions (n, 3), rotations (n, 3, 3)."""
        st = self.vehicle_state(t_ns)
        R = st.rotation
        tr = self.track
        m = np.array([tr.mount_xy_m[0], tr.mount_xy_m[1], tr.start_m[2]])
        r, p, y = np.radians(tr.mount_rpy_deg)
        Rm = rotation_ypr(np.array([y]), np.array([p]), np.array([r]))[0]
        return st.position + R @ m, R @ Rm

    @cached_property
    def breaks_ns(self) -> IntArray:
        """Times where the pose is not smooth, bracketed to the nanosecond: each leg's start
        and end (the speed jumps, or the acceleration), the ends of its acceleration ramps, and
        the joints of its segments (where an arc meets a straight the yaw rate jumps). Between
        two of them the pose is an analytic function of time (sines and polynomials of it,
        the terrain a sum of plane waves)."""
        taus: list[float] = []
        for start, leg in zip(self.leg_start_s.tolist(), self.legs, strict=True):
            ts = [0.0, leg.duration_s]
            if leg.t_acc > 0.0:
                ts += [leg.t_acc, leg.t_acc + leg.t_cruise]
            if len(leg.s0) > 1:
                ts += leg.time_at(leg.s0[1:]).tolist()
            taus += [start + t for t in ts]
        ns = np.array(taus, dtype=np.float64) * 1e9
        both = np.concatenate([np.floor(ns), np.ceil(ns)]).astype(np.int64) + self.t0_ns
        result: IntArray = np.unique(both)
        return result

    def dense_knot_ns(self) -> int:
        """Knot spacing of :meth:`sensor_pose_dense`: ``DENSE_KNOT_NS``, or shorter so that
        nothing the pose depends on turns by more than ``DENSE_PHASE_RAD`` between knots: the
        yaw (speed times the sharpest curvature) and the phase of the shortest terrain wave
        under the fastest point of the footprint (driving plus turning about the base)."""
        v = max((leg.v_peak for leg in self.legs), default=0.0)
        kappa = max((float(np.abs(leg.k).max()) for leg in self.legs if len(leg.k)),
                    default=0.0)
        tr = self.track
        reach = math.hypot(tr.footprint_m[0] / 2, tr.footprint_m[1] / 2) + math.hypot(
            *tr.mount_xy_m)
        waves = self.terrain.waves
        k_max = float(np.hypot(waves[:, 0], waves[:, 1]).max()) if len(waves) else 0.0
        rate = max(v * kappa, k_max * v * (1.0 + kappa * reach))
        if rate <= 0.0:
            return DENSE_KNOT_NS
        return max(1, min(DENSE_KNOT_NS, int(DENSE_PHASE_RAD / rate * 1e9)))

    def sensor_pose_dense(self, t_ns: IntArray, knot_ns: int | None = None,
                          pieces: DensePoses | None = None) -> tuple[FloatArray, FloatArray]:
        """:meth:`sensor_pose` at many close, ascending times (a lidar frame's columns), fast.

        The exact pose is taken at knots on the grid of multiples of ``knot_ns`` (default
        :meth:`dense_knot_ns`; so a time gets the same knots whatever else is asked with it),
        at every one of :attr:`breaks_ns` between them, and at the
        middle of each interval; in between, the quadratic through those three exact poses.
        Positions and the nine rotation entries are interpolated alike (the rotation stays
        orthonormal up to the interpolation error). Between breaks the pose is smooth, and the
        error on an interval of length h is at most max|f'''| h^3 / (72 sqrt 3); the tests
        bound it on real tracks (corners, U-turns, reversing, ramps, rolling terrain, fast
        driving). Falls back to the exact poses when the times are few, not ascending, or
        sparse (fewer than two per knot). ``pieces`` (from :meth:`dense_poses`, covering the
        times) are used instead of building them: the same poses."""
        t = np.asarray(t_ns, dtype=np.int64)
        use = self.dense_pieces(t, knot_ns, pieces)
        return self.sensor_pose(t) if use is None else use.at(t)

    def dense_pieces(self, t_ns: IntArray, knot_ns: int | None = None,
                     pieces: DensePoses | None = None) -> DensePoses | None:
        """The pieces :meth:`sensor_pose_dense` evaluates for these times (``pieces`` where
        they cover them, else new ones), or None where it takes the exact poses."""
        t = np.asarray(t_ns, dtype=np.int64)
        if t.ndim != 1 or len(t) < 8:
            return None
        lo, hi = int(t[0]), int(t[-1])
        if hi <= lo or bool(np.any(t[1:] < t[:-1])):
            return None
        h = pieces.knot_ns if pieces is not None else (knot_ns or self.dense_knot_ns())
        # knots on the absolute grid of multiples of h, the last one past every time: a
        # time's pose does not depend on which other times were asked with it (a frame
        # alone, or a second of frames at once through ``pieces``)
        g0, g1 = lo // h * h, (hi // h + 1) * h
        if pieces is None or not pieces.knots[0] <= g0 < g1 <= pieces.knots[-1]:
            knots = self._dense_knots(g0, g1, h)
            return None if 4 * len(knots) > len(t) else self._dense_pieces(h, knots)
        k0, k1 = np.searchsorted(pieces.knots, [g0, g1])
        return None if 4 * (k1 - k0 + 1) > len(t) else pieces

    def dense_poses(self, lo_ns: int, hi_ns: int, knot_ns: int | None = None) -> DensePoses:
        """The pieces :meth:`sensor_pose_dense` evaluates, for times in [lo_ns, hi_ns): a
        caller that asks for many frames in turn builds them once for a stretch of them."""
        h = knot_ns or self.dense_knot_ns()
        return self._dense_pieces(h, self._dense_knots(lo_ns, hi_ns, h))

    def _dense_knots(self, lo_ns: int, hi_ns: int, h: int) -> IntArray:
        g0, g1 = lo_ns // h, -(-hi_ns // h)
        grid = np.arange(g0, max(g1, g0 + 1) + 1, dtype=np.int64) * h
        brk = self.breaks_ns
        brk = brk[(brk > grid[0]) & (brk < grid[-1])]
        return np.unique(np.concatenate([grid, brk])) if len(brk) else grid

    def _dense_pieces(self, h: int, knots: IntArray) -> DensePoses:
        mids = (knots[:-1] + knots[1:]) // 2
        pos, rot = self.sensor_pose(np.concatenate([knots, mids]))
        vals = np.concatenate([pos, rot.reshape(-1, 9)], axis=1)
        nk = len(knots)
        va, vb, vm = vals[:nk - 1], vals[1:nk], vals[nk:]
        # Newton's form on each interval, nodes a (at 0), m (at hm) and b (at hb) in ns:
        # f(x) = f(a) + x (d1 + (x - hm) d2). An interval of 1 ns (a break bracketed by two
        # knots) has m == a: linear there.
        hm = (mids - knots[:-1]).astype(np.float64)
        hb = np.diff(knots).astype(np.float64)
        lin = hm <= 0.0
        hm1 = np.where(lin, 1.0, hm)[:, None]
        d_am = (vm - va) / hm1
        d_mb = (vb - vm) / np.where(lin[:, None], 1.0, hb[:, None] - hm1)
        d1 = np.where(lin[:, None], (vb - va) / hb[:, None], d_am)
        d2 = np.where(lin[:, None], 0.0, (d_mb - d_am) / hb[:, None])
        coef = np.concatenate([va, d1, d2, np.where(lin, 0.0, hm)[:, None]], axis=1)
        return DensePoses(h, knots, coef)

    def sensor_kinematics(self, t_ns: IntArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Sensor velocity and acceleration (n, 3) in the world, angular velocity (n, 3) in the
        sensor frame (rad/s), by central differences over ``DIFF_NS``."""
        vel, acc, w, _ = self._kinematics(np.atleast_1d(np.asarray(t_ns, dtype=np.int64)))
        return vel, acc, w

    def _kinematics(self, t: IntArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """:meth:`sensor_kinematics` and the rotation at ``t``, from one :meth:`sensor_pose`
        of the three times each needs (element by element: the same bits as three calls)."""
        h = DIFF_NS
        n = len(t)
        p, R = self.sensor_pose(np.concatenate([t - h, t, t + h]))
        p0, p1, p2 = p[:n], p[n:2 * n], p[2 * n:]
        R0, R1, R2 = R[:n], R[n:2 * n], R[2 * n:]
        hs = h / 1e9
        vel = (p2 - p0) / (2 * hs)
        acc = (p2 - 2 * p1 + p0) / (hs * hs)
        Rrel = np.swapaxes(R0, 1, 2) @ R2
        w = np.stack([Rrel[:, 2, 1] - Rrel[:, 1, 2], Rrel[:, 0, 2] - Rrel[:, 2, 0],
                      Rrel[:, 1, 0] - Rrel[:, 0, 1]], axis=1) / 2.0
        return vel, acc, w / (2 * hs), R1

    def imu(self, t_ns: IntArray) -> tuple[FloatArray, FloatArray]:
        """What an IMU fixed to the sensor frame reads: specific force in g (gravity included:
        a level sensor at rest reads (0, 0, 1)) and angular rate in deg/s, (n, 3) each."""
        _, acc, w, R = self._kinematics(np.atleast_1d(np.asarray(t_ns, dtype=np.int64)))
        f = acc + np.array([0.0, 0.0, GRAVITY_M_S2])
        accel = np.einsum("nji,nj->ni", R, f) / GRAVITY_M_S2
        return accel, np.degrees(w)


def _eval_pieces(t: Any, knots: Any, va: Any, d1: Any, d2: Any, hm: Any, pos: Any,
                 rot: Any) -> None:
    """:meth:`DensePoses.at`, one time at a time, with numpy's operations in numpy's order
    (the same bits; compiled by numba where it is installed)."""
    last = len(knots) - 2
    for n in range(len(t)):
        i = min(max(np.searchsorted(knots, t[n], side="right") - 1, 0), last)
        x = np.float64(t[n] - knots[i])
        for q in range(12):
            v = (x - hm[0, i]) * d2[q, i]
            v += d1[q, i]
            v *= x
            v += va[q, i]
            if q < 3:
                pos[n, q] = v
            else:
                rot[n, (q - 3) // 3, (q - 3) % 3] = v


def warm_up() -> None:
    """Compile the pose pieces' kernel (numba; or load it from its on-disk cache) now, not
    in the first frame of a live stream."""
    DensePoses(10, np.array([0, 10], np.int64), np.zeros((1, 37))).at(
        np.arange(8, dtype=np.int64))


def _pieces_kernel() -> Callable[..., None] | None:
    return compiled(_eval_pieces)


@dataclass(frozen=True)
class DensePoses:
    """Quadratic pieces of the sensor pose between knots (:meth:`Trajectory.dense_poses`):
    per interval the pose at its start, Newton's two differences and its middle node."""

    knot_ns: int  # the grid spacing
    knots: IntArray  # (k,) ascending: the grid and the breaks between
    coef: FloatArray  # (k - 1, 37): value (12), d1 (12), d2 (12), middle node offset (ns)

    def at(self, t_ns: IntArray) -> tuple[FloatArray, FloatArray]:
        """Positions (n, 3) and rotations (n, 3, 3) at times within the knots."""
        t = np.asarray(t_ns, dtype=np.int64)
        knots = self.knots
        va, d1, d2, hm = self._parts  # (12, k - 1) each, hm (1, k - 1)
        kernel = _pieces_kernel()
        if kernel is not None and t.ndim == 1:
            pos = np.empty((len(t), 3))
            rot = np.empty((len(t), 3, 3))
            kernel(t, knots, va, d1, d2, hm, pos, rot)
            return pos, rot
        if len(t) > 1 and bool(np.all(t[1:] >= t[:-1])):
            # ascending times: each interval's run of them, its coefficients repeated
            edges = np.empty(len(knots), np.int64)
            edges[0], edges[-1] = 0, len(t)
            edges[1:-1] = np.searchsorted(t, knots[1:-1])
            n = edges[1:] - edges[:-1]
            start = np.repeat(knots[:-1], n)
            va, d1, d2, hm = (np.repeat(c, n, axis=1) for c in (va, d1, d2, hm))
        else:
            i = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, len(knots) - 2)
            start = knots[i]
            va, d1, d2, hm = (c[:, i] for c in (va, d1, d2, hm))
        x = (t - start).astype(np.float64)  # (n,): broadcast along the last axis
        out = (x - hm) * d2
        out += d1
        out *= x
        out += va
        return np.ascontiguousarray(out[:3].T), np.ascontiguousarray(out[3:].T).reshape(-1, 3, 3)

    @cached_property
    def _parts(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        c = self.coef.T
        return (np.ascontiguousarray(c[:12]), np.ascontiguousarray(c[12:24]),
                np.ascontiguousarray(c[24:36]), np.ascontiguousarray(c[36:37]))


@dataclass(frozen=True)
class PoseError:
    """GNSS/INS error put on what goes on the bus (the truth is kept elsewhere): white noise
    on position and heading, a constant bias and a horizontal drift. Deterministic: the error
    at a time stamp depends only on (seed, time stamp)."""

    cfg: PoseErrorConfig
    seed: int = 0
    t0_ns: int = 1_000_000_000

    @property
    def active(self) -> bool:
        c = self.cfg
        return bool(c.position_sd_m or c.heading_sd_deg or any(c.bias_m) or c.drift_m_per_s)

    def apply(self, position: FloatArray, heading_deg: FloatArray, t_ns: IntArray
              ) -> tuple[FloatArray, FloatArray]:
        if not self.active:
            return position, heading_deg
        c = self.cfg
        t = np.atleast_1d(np.asarray(t_ns, dtype=np.int64))
        ang = np.random.default_rng([self.seed, 0x0D1F7]).uniform(0, 2 * math.pi)
        el = np.maximum((t - self.t0_ns).astype(np.float64) / 1e9, 0.0) * c.drift_m_per_s
        pos = position + np.array(c.bias_m) + np.column_stack(
            [el * math.cos(ang), el * math.sin(ang), np.zeros(len(t))])
        hd = np.array(heading_deg, dtype=np.float64, copy=True)
        for i, ti in enumerate(t.tolist()):
            g = np.random.default_rng([self.seed, 0x9E55, ti & ((1 << 63) - 1)])
            pos[i] += g.normal(0.0, 1.0, 3) * c.position_sd_m
            hd[i] = (hd[i] + g.normal() * c.heading_sd_deg) % 360.0
        return pos, hd


def distance_to_track(xy: NDArray[np.float64], track: NDArray[np.float64]
                       ) -> NDArray[np.float64]:
    """Horizontal distance of each point from the polyline ``track`` (exact: only segments
    with an end within the nearest vertex's distance plus the longest segment can be
    nearer, and those are all checked)."""
    if not len(track) or not len(xy):
        return np.full(len(xy), np.nan)
    from scipy.spatial import cKDTree

    tree = cKDTree(track)
    d_v, _ = tree.query(xy)
    if len(track) == 1:
        return np.asarray(d_v, np.float64)
    a, ab = track[:-1], np.diff(track, axis=0)
    reach = d_v + float(np.sqrt(np.sum(ab * ab, 1)).max()) + 1e-9
    near = tree.query_ball_point(xy, reach)
    pt = np.repeat(np.arange(len(xy)), [len(c) for c in near])
    v = np.concatenate([np.asarray(c, np.int64) for c in near])
    pt, seg = np.concatenate([pt, pt]), np.concatenate([v, v - 1])  # the vertex's two segments
    ok = (seg >= 0) & (seg < len(ab))
    pt, seg = pt[ok], seg[ok]
    ap = xy[pt] - a[seg]
    u = np.clip(np.sum(ap * ab[seg], 1) / np.maximum(np.sum(ab[seg] ** 2, 1), 1e-300), 0, 1)
    d = np.sqrt(np.sum((ap - u[:, None] * ab[seg]) ** 2, 1))
    best = np.asarray(d_v, np.float64).copy()
    np.minimum.at(best, pt, d)
    return best
