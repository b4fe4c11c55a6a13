"""Paths and controllers: the paper's step 6, ``u_t`` from the state.

Paths are planar curves in the world (``map``) frame, parametrised by arc
length ``s`` (m):

* :class:`CirclePath` -- centre, radius, direction (``+1``/``"ccw"`` turns left);
* :class:`PolylinePath` -- waypoints, open or closed;
* :class:`FigureEightPath` -- a lemniscate of Gerono, ``size`` wide and
  ``size / 2`` high.

Each answers ``point(s)``, ``tangent(s)``, ``curvature(s)`` and
:meth:`PlanarPath.project` (closest point, arc length and signed cross-track
error, positive when the robot is left of the path).

Controllers are callables ``controller(state) -> Twist``:

* :class:`PurePursuit` follows a path at a speed profile that respects the
  robot's limits (speed, turn rate, per-wheel rate, deceleration to the end of
  an open path);
* :class:`GoalReacher` drives to a point (and optionally a heading).

Bad input fails early with :class:`PathError` naming what is wrong: a path
leaving the room's bounds, a curve tighter than the robot can turn at the
requested speed, an empty or non-finite polyline.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..bus.msgs import Twist
from ..contract import schema
from ..errors import PathError, SpeedLimitError
from ..utils.geometry import wrap_angle
from .kinematics import KinematicState, RobotSpec, make_twist, robot_spec

log = logging.getLogger(__name__)


def _finite_point(p, what: str, n: int = 2) -> np.ndarray:
    try:
        a = np.asarray(p, float).reshape(-1)
    except (TypeError, ValueError):
        raise PathError(f"{what}: expected {n} numbers, got {p!r}") from None
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise PathError(f"{what}: expected {n} finite numbers, got {p!r}")
    return a


def _positive(x, what: str) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise PathError(f"{what}: expected a number, got {x!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise PathError(f"{what}: expected a positive finite number, got {x!r}")
    return v


@dataclass(frozen=True)
class Projection:
    """The closest point of a path to a query point.

    Attributes:
        s: arc length of the closest point, m (``0 <= s < length`` on a closed path).
        point: closest point ``[2]``, m.
        tangent: unit tangent there ``[2]``.
        error: signed cross-track error, m (positive = query point left of the path).
    """

    s: float
    point: np.ndarray
    tangent: np.ndarray
    error: float


class PlanarPath:
    """A planar path parametrised by arc length. Subclasses fill the geometry."""

    closed: bool = False
    length: float = 0.0
    name: str = "path"

    # ---- geometry (vectorised over s) ----
    def point(self, s) -> np.ndarray:
        """Points ``[..., 2]`` (m) at arc lengths ``s`` ``[...]`` (m)."""
        raise NotImplementedError

    def tangent(self, s) -> np.ndarray:
        """Unit tangents ``[..., 2]`` at ``s``."""
        raise NotImplementedError

    def curvature(self, s) -> np.ndarray:
        """Signed curvature ``[...]`` (1/m, positive turning left) at ``s``."""
        raise NotImplementedError

    def project(self, p, hint: float | None = None, window: float | None = None) -> Projection:
        """Closest point of the path to ``p`` ``[2]`` (m).

        Args:
            hint: arc length near which to search (e.g. the last projection);
                with ``window`` it restricts the search to ``hint +- window`` m,
                which keeps a follower on its branch where a path crosses itself.
        """
        raise NotImplementedError

    # ---- derived ----
    def wrap(self, s):
        """Arc length mapped into ``[0, length)`` (closed) or clipped to ``[0, length]``."""
        s = np.asarray(s, float)
        return np.mod(s, self.length) if self.closed else np.clip(s, 0.0, self.length)

    def sample(self, n: int = 512) -> np.ndarray:
        """``[n, 2]`` points evenly spaced in arc length."""
        return self.point(np.linspace(0.0, self.length, n, endpoint=not self.closed))

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box ``(lo [2], hi [2])`` of the path, m."""
        pts = self.sample(2048)
        return pts.min(axis=0), pts.max(axis=0)

    @property
    def max_curvature(self) -> float:
        """Largest ``|curvature|`` along the path, 1/m (corners of polylines excluded)."""
        k = np.abs(self.curvature(np.linspace(0.0, self.length, 2048, endpoint=False)))
        return float(k.max())

    def check_in_room(self, lo, hi, margin: float = 0.0) -> None:
        """Raise :class:`PathError` if the path (grown by ``margin`` m) leaves ``[lo, hi]``.

        Args:
            lo, hi: room bounds ``[2]`` or ``[3]`` (only x and y are used), m.
            margin: clearance to keep, m (e.g. the robot's footprint radius).
        """
        lo = np.asarray(lo, float)[:2]
        hi = np.asarray(hi, float)[:2]
        plo, phi = self.bounds()
        bad = []
        for i, ax in enumerate("xy"):
            if plo[i] - margin < lo[i] - 1e-9 or phi[i] + margin > hi[i] + 1e-9:
                bad.append(f"{ax} {plo[i] - margin:.3f}..{phi[i] + margin:.3f} m not inside "
                           f"{lo[i]:.3f}..{hi[i]:.3f} m")
        if bad:
            raise PathError(f"{self.describe()} leaves the room (with {margin:.3f} m clearance): "
                            + "; ".join(bad))

    def describe(self) -> str:
        return self.name


class CirclePath(PlanarPath):
    """A circle, the bundled lab's trajectory (centre (4, 3), radius 1.5 m).

    Args:
        centre: ``[2]`` m.
        radius: m (> 0).
        direction: ``+1`` or ``"ccw"`` (counter-clockwise, turning left), ``-1`` or ``"cw"``.
        start_angle: polar angle (rad) of the point ``s = 0`` about the centre.
    """

    closed = True

    def __init__(self, centre: Sequence[float], radius: float, direction: int | str = "ccw",
                 start_angle: float = 0.0):
        self.centre = _finite_point(centre, "circle centre")
        self.radius = _positive(radius, "circle radius")
        d = {"ccw": 1, "cw": -1, 1: 1, -1: -1}.get(direction)
        if d is None:
            raise PathError(f"circle direction: expected 'ccw', 'cw', +1 or -1, got {direction!r}")
        self.direction = d
        if not math.isfinite(start_angle):
            raise PathError(f"circle start_angle: expected a finite angle, got {start_angle!r}")
        self.start_angle = float(start_angle)
        self.length = 2 * math.pi * self.radius
        self.name = "circle"

    def describe(self) -> str:
        return (f"circle centre ({self.centre[0]:g}, {self.centre[1]:g}) "
                f"radius {self.radius:g} m")

    def _angle(self, s):
        return self.start_angle + self.direction * np.asarray(s, float) / self.radius

    def point(self, s):
        a = self._angle(s)
        return self.centre + self.radius * np.stack([np.cos(a), np.sin(a)], axis=-1)

    def tangent(self, s):
        a = self._angle(s)
        return self.direction * np.stack([-np.sin(a), np.cos(a)], axis=-1)

    def curvature(self, s):
        return np.full(np.shape(s), self.direction / self.radius)

    @property
    def max_curvature(self) -> float:
        return 1.0 / self.radius

    def bounds(self):
        return self.centre - self.radius, self.centre + self.radius

    def project(self, p, hint=None, window=None) -> Projection:
        d = np.asarray(p, float)[:2] - self.centre
        rho = float(np.hypot(*d))
        a = math.atan2(d[1], d[0]) if rho > 0 else self.start_angle
        s = float(np.mod(self.direction * (a - self.start_angle) * self.radius, self.length))
        # left of a ccw circle is inside
        return Projection(s, self.point(s), self.tangent(s), self.direction * (self.radius - rho))


class SampledPath(PlanarPath):
    """A path given by a dense ordered point list (linear between points).

    Args:
        points: ``[N, 2]`` m, N >= 2, no two consecutive points equal.
        closed: join the last point back to the first.
        curvature_fn: optional exact curvature as a function of arc length.
    """

    def __init__(self, points, closed: bool = False, name: str = "polyline"):
        self.name = name
        pts = np.asarray(points, float)
        if pts.size == 0:
            raise PathError(f"{name}: needs at least 2 waypoints, got 0")
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise PathError(f"{name}: expected waypoints [N, 2], got shape {pts.shape}")
        if len(pts) < 2:
            raise PathError(f"{name}: needs at least 2 waypoints, got {len(pts)}")
        bad = np.flatnonzero(~np.all(np.isfinite(pts), axis=1))
        if bad.size:
            raise PathError(f"{name}: waypoint {bad[0]} is not finite: {pts[bad[0]].tolist()}")
        if closed:
            pts = np.vstack([pts, pts[:1]])
        seg = np.diff(pts, axis=0)
        seglen = np.hypot(seg[:, 0], seg[:, 1])
        zero = np.flatnonzero(seglen < 1e-9)
        if zero.size:
            i = int(zero[0])
            j = (i + 1) % (len(pts) - 1) if closed else i + 1
            raise PathError(f"{name}: waypoints {i} and {j} coincide "
                            f"({pts[i].tolist()}): zero-length segment")
        self.closed = closed
        self.vertices = pts  # [M, 2], closed paths repeat the first point at the end
        self.seg = seg
        self.seglen = seglen
        self.cum = np.concatenate([[0.0], np.cumsum(seglen)])
        self.length = float(self.cum[-1])
        self._heading = np.arctan2(seg[:, 1], seg[:, 0])

    def _locate(self, s):
        s = self.wrap(s)
        i = np.clip(np.searchsorted(self.cum, s, side="right") - 1, 0, len(self.seglen) - 1)
        return s, i

    def point(self, s):
        s, i = self._locate(s)
        f = (s - self.cum[i]) / self.seglen[i]
        return self.vertices[i] + f[..., None] * self.seg[i]

    def tangent(self, s):
        _, i = self._locate(s)
        return self.seg[i] / self.seglen[i][..., None]

    def curvature(self, s):
        # straight segments: 0 (corners are handled by the controller's lookahead)
        return np.zeros(np.shape(s))

    def bounds(self):
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def project(self, p, hint=None, window=None) -> Projection:
        p = np.asarray(p, float)[:2]
        nseg = len(self.seglen)
        idx = None
        if hint is not None and window is not None and 2 * window < self.length:
            # only the segments overlapping [hint - window, hint + window] (wrapping if closed)
            lo, hi = float(hint) - window, float(hint) + window
            if self.closed:
                ranges = [(lo, hi)] if 0 <= lo and hi <= self.length else \
                    [(lo % self.length, self.length), (0.0, hi % self.length)] if lo < 0 else \
                    [(lo, self.length), (0.0, hi - self.length)]
            else:
                ranges = [(max(lo, 0.0), min(hi, self.length))]
            parts = []
            for a_, b_ in ranges:
                i0 = max(int(np.searchsorted(self.cum, a_, side="right")) - 1, 0)
                i1 = min(int(np.searchsorted(self.cum, b_, side="left")), nseg)
                parts.append(np.arange(i0, max(i1, i0 + 1)))
            idx = np.unique(np.concatenate(parts))
        a = self.vertices[:-1] if idx is None else self.vertices[idx]
        seg = self.seg if idx is None else self.seg[idx]
        sl = self.seglen if idx is None else self.seglen[idx]
        c0 = self.cum[:-1] if idx is None else self.cum[idx]
        f = np.clip(np.einsum("ij,ij->i", p - a, seg) / sl ** 2, 0.0, 1.0)
        q = a + f[:, None] * seg
        d2 = np.sum((q - p) ** 2, axis=1)
        i = int(np.argmin(d2))
        t = seg[i] / sl[i]
        r = p - q[i]
        err = float(t[0] * r[1] - t[1] * r[0])
        return Projection(float(self.wrap(c0[i] + f[i] * sl[i])), q[i], t, err)


class PolylinePath(SampledPath):
    """Straight segments through ``waypoints`` ``[N, 2]`` (m); ``closed`` loops back."""

    def __init__(self, waypoints, closed: bool = False):
        n = len(waypoints) if hasattr(waypoints, "__len__") else 0
        if n > schema.MAX_WAYPOINTS:
            raise PathError(f"polyline: {n} waypoints, beyond the limit of "
                            f"{schema.MAX_WAYPOINTS}")
        super().__init__(waypoints, closed=closed, name="polyline")

    def describe(self) -> str:
        return f"polyline of {len(self.vertices) - int(self.closed)} waypoints"


class FigureEightPath(SampledPath):
    """A figure eight (lemniscate of Gerono) centred at ``centre``.

    ``x = cx + a sin t``, ``y = cy + a sin t cos t`` with ``a = size / 2``: the
    curve is ``size`` m wide (x) and ``size / 2`` m high (y), crosses itself at
    the centre and turns with radius ``a`` at its two ends. Sampled densely
    (``n`` points) for the queries; curvature is exact.

    Args:
        centre: ``[2]`` m.
        size: width, m (> 0).
        heading: rotation of the figure about its centre, rad.
    """

    def __init__(self, centre: Sequence[float], size: float, heading: float = 0.0,
                 n: int = 4000):
        self.centre = _finite_point(centre, "figure-eight centre")
        self.size = _positive(size, "figure-eight size")
        self.a = self.size / 2
        self.heading = float(heading)
        t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
        super().__init__(self._xy(t), closed=True, name="figure-eight")
        self._t = np.append(t, 2 * np.pi)  # parameter at each vertex

    def describe(self) -> str:
        return f"figure-eight centre ({self.centre[0]:g}, {self.centre[1]:g}) size {self.size:g} m"

    def _xy(self, t):
        a = self.a
        x, y = a * np.sin(t), a * np.sin(t) * np.cos(t)
        c, s = math.cos(self.heading), math.sin(self.heading)
        return self.centre + np.stack([c * x - s * y, s * x + c * y], axis=-1)

    def curvature(self, s):
        s, i = self._locate(s)
        f = (s - self.cum[i]) / self.seglen[i]
        t = self._t[i] + f * (self._t[i + 1] - self._t[i])
        a = self.a
        dx, dy = a * np.cos(t), a * np.cos(2 * t)
        ddx, ddy = -a * np.sin(t), -2 * a * np.sin(2 * t)
        return (dx * ddy - dy * ddx) / np.power(dx * dx + dy * dy, 1.5)


# --------------------------------------------------------------------------- controllers


def _speed_for_curvature(spec: RobotSpec, v_max: float, kappa: float) -> float:
    """Largest ``v <= v_max`` such that ``w = v kappa`` keeps all limits (turn and wheel rates)."""
    k = abs(kappa)
    v = v_max
    if k > 0:
        v = min(v, spec.max_angular / k)
    # per-wheel: |v (1 + k L / 2)| / r <= max_wheel_rate
    v = min(v, spec.max_wheel_rate * spec.wheel_radius / (1 + k * spec.wheel_separation / 2))
    return v


def _check_speed(spec: RobotSpec, speed: float | None) -> float:
    if speed is None:
        return spec.max_linear
    v = float(speed)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"speed: expected a positive finite number of m/s, got {speed!r}")
    if v > spec.max_linear + 1e-12:
        raise SpeedLimitError(f"speed {v:g} m/s exceeds the {spec.model} limit of "
                              f"{spec.max_linear} m/s")
    return v


class PurePursuit:
    """Pure-pursuit path follower: ``controller(state) -> Twist``.

    Each call projects the robot onto the path (searching near the last
    projection, so a figure eight is followed through its crossing), takes the
    point ``lookahead`` m further along, and steers on the arc through it:
    ``kappa = 2 y_l / d^2`` with ``(x_l, y_l)`` the point in base_link and ``d``
    its distance. The speed is the requested ``speed``, lowered so that the
    turn rate and each wheel stay within limits for both the steering arc and
    the path's curvature over the next lookahead, and so that an open path's
    end is reached decelerating at the robot's acceleration limit.

    Args:
        path: the :class:`PlanarPath` to follow.
        spec: robot model (:class:`RobotSpec` or name).
        lookahead: m (> 0).
        speed: cruise speed, m/s (default: the model's limit).
        bounds: optional room bounds ``(lo, hi)`` (``[2]`` or ``[3]`` each, m); a
            path leaving them (with the robot's footprint) raises :class:`PathError`.
        goal_tolerance: distance to an open path's end at which it is done, m.

    Raises:
        PathError: the path leaves ``bounds``, or curves tighter than the robot
            can turn at ``speed`` (the message gives the minimum radius and the
            fastest feasible speed).
        SpeedLimitError: ``speed`` above the model's limit.
    """

    def __init__(self, path: PlanarPath, spec: RobotSpec | str = "burger", *,
                 lookahead: float = 0.25,
                 speed: float | None = None, bounds=None, goal_tolerance: float = 0.03):
        if not isinstance(path, PlanarPath):
            raise TypeError(f"path: expected a PlanarPath, got {type(path).__name__}")
        self.path = path
        self.spec = robot_spec(spec) if isinstance(spec, str) else spec
        self.lookahead = _positive(lookahead, "lookahead")
        self.speed = _check_speed(self.spec, speed)
        self.goal_tolerance = _positive(goal_tolerance, "goal_tolerance")
        if bounds is not None:
            path.check_in_room(bounds[0], bounds[1], margin=self.spec.footprint_radius)
        kmax = path.max_curvature
        if kmax * self.speed > self.spec.max_angular * (1 + 1e-9):
            rmin = self.speed / self.spec.max_angular
            raise PathError(
                f"{path.describe()} is unreachable for a {self.spec.model} at {self.speed:g} m/s: "
                f"its tightest radius {1 / kmax:.3f} m is below the minimum turning radius "
                f"{rmin:.3f} m at that speed (w_max {self.spec.max_angular} rad/s); "
                f"use speed <= {math.floor(self.spec.max_angular / kmax * 1000) / 1000:.3f} m/s")
        v_ok = _speed_for_curvature(self.spec, self.speed, kmax)
        if v_ok < self.speed - 1e-9:
            log.debug("%s: the per-wheel limit lowers the speed to %.3f m/s on the tightest "
                      "curve", path.describe(), v_ok)
        self._s: float | None = None
        self.travelled = 0.0  #: arc length progressed along the path, m (counts laps)
        self.error = 0.0  #: last signed cross-track error, m
        self.done = False

    def reset(self) -> None:
        self._s, self.travelled, self.error, self.done = None, 0.0, 0.0, False

    def __call__(self, state: KinematicState) -> Twist:
        v, w = self.command(state)
        return make_twist(v, w)

    def command(self, state: KinematicState) -> tuple[float, float]:
        """``(v m/s, w rad/s)`` for ``state`` (the same as calling, without the Twist)."""
        path, spec = self.path, self.spec
        win = 2.0 * self.lookahead + 0.5
        proj = path.project(state.pose[:2], hint=self._s, window=win if self._s is not None
                            else None)
        if self._s is not None:
            ds = proj.s - self._s
            if path.closed:
                ds = (ds + path.length / 2) % path.length - path.length / 2
            self.travelled += ds
        self._s, self.error = proj.s, proj.error
        if self.done:
            return 0.0, 0.0

        remaining = None
        if not path.closed:
            remaining = path.length - proj.s
            end = path.point(path.length)
            if remaining < self.lookahead and \
                    np.hypot(*(end - state.pose[:2])) < self.goal_tolerance:
                self.done = True
                log.debug("pure pursuit: reached the end of %s", path.describe())
                return 0.0, 0.0
        s_t = proj.s + self.lookahead
        target = path.point(s_t if path.closed else min(s_t, path.length))
        c, s = math.cos(state.yaw), math.sin(state.yaw)
        dx, dy = target - state.pose[:2]
        xl, yl = c * dx + s * dy, -s * dx + c * dy
        d2 = xl * xl + yl * yl
        if d2 < 1e-12:
            return 0.0, 0.0
        if xl < 0 and abs(yl) < abs(xl):
            # target behind: turn in place toward it
            alpha = math.atan2(yl, xl)
            w = math.copysign(min(spec.max_angular, 2.0 * abs(alpha)), alpha)
            return 0.0, w
        kappa = 2.0 * yl / d2
        ks = path.curvature(np.linspace(proj.s, proj.s + self.lookahead, 5))
        v = _speed_for_curvature(spec, self.speed, max(abs(kappa), float(np.max(np.abs(ks)))))
        if remaining is not None:
            dist_end = float(np.hypot(*(path.point(path.length) - state.pose[:2])))
            v = min(v, math.sqrt(2 * spec.max_linear_accel * 0.5 * dist_end))
            v = min(v, max(dist_end, 0.02) * 2.0)  # proportional near the end
        return v, v * kappa


class GoalReacher:
    """Drive to a goal point (and optionally a final heading): ``controller(state) -> Twist``.

    Turns toward the goal when it is more than ``turn_in_place`` rad off the
    nose, otherwise drives with ``v = min(speed, k_rho rho, sqrt(a rho))`` and
    ``w = k_alpha alpha``; within ``tolerance`` it turns to ``goal[2]`` if one
    was given, then stops and sets :attr:`done`.

    Args:
        goal: ``[x, y]`` or ``[x, y, yaw]`` (m, rad) in the world frame.
        spec: robot model.
        tolerance: position tolerance, m; yaw_tolerance: rad.
        speed: cruise speed, m/s (default: the model's limit).
        bounds: optional room bounds ``(lo, hi)``; a goal closer to a wall than
            the robot's footprint radius raises :class:`PathError`.
    """

    def __init__(self, goal: Sequence[float], spec: RobotSpec | str = "burger", *,
                 tolerance: float = 0.03, yaw_tolerance: float = 0.03,
                 speed: float | None = None, bounds=None, k_rho: float = 1.0,
                 k_alpha: float = 3.0, turn_in_place: float = math.pi / 4):
        g = np.asarray(goal, float).reshape(-1)
        if g.shape not in ((2,), (3,)) or not np.all(np.isfinite(g)):
            raise PathError(f"goal: expected [x, y] or [x, y, yaw] finite numbers, got {goal!r}")
        self.goal = g
        self.spec = robot_spec(spec) if isinstance(spec, str) else spec
        self.tolerance = _positive(tolerance, "tolerance")
        self.yaw_tolerance = _positive(yaw_tolerance, "yaw_tolerance")
        self.speed = _check_speed(self.spec, speed)
        self.k_rho, self.k_alpha, self.turn_in_place = k_rho, k_alpha, turn_in_place
        if bounds is not None:
            lo, hi = np.asarray(bounds[0], float)[:2], np.asarray(bounds[1], float)[:2]
            m = self.spec.footprint_radius
            if np.any(g[:2] - m < lo) or np.any(g[:2] + m > hi):
                raise PathError(f"goal ({g[0]:g}, {g[1]:g}) is outside the room or closer than "
                                f"the {self.spec.model}'s footprint radius {m} m to a wall "
                                f"(room x {lo[0]:g}..{hi[0]:g}, y {lo[1]:g}..{hi[1]:g} m)")
        self.done = False

    def __call__(self, state: KinematicState) -> Twist:
        return make_twist(*self.command(state))

    def command(self, state: KinematicState) -> tuple[float, float]:
        """``(v m/s, w rad/s)`` for ``state``."""
        spec = self.spec
        dx, dy = self.goal[:2] - state.pose[:2]
        rho = math.hypot(dx, dy)
        if rho < self.tolerance or self.done:
            if len(self.goal) == 3:
                e = float(wrap_angle(self.goal[2] - state.yaw))
                if abs(e) > self.yaw_tolerance and not self.done:
                    w = math.copysign(min(spec.max_angular, self.k_alpha * abs(e)), e)
                    return 0.0, w
            self.done = True
            return 0.0, 0.0
        alpha = float(wrap_angle(math.atan2(dy, dx) - state.yaw))
        w = max(-spec.max_angular, min(spec.max_angular, self.k_alpha * alpha))
        if abs(alpha) > self.turn_in_place:
            return 0.0, w
        v = min(self.speed, self.k_rho * rho, math.sqrt(spec.max_linear_accel * rho))
        v *= math.cos(alpha)
        if w != 0:
            v = min(v, _speed_for_curvature(spec, v, w / max(v, 1e-9)))
        return v, w


def controller_from_spec(spec: dict, model: RobotSpec | str = "burger", *, bounds=None,
                         lookahead: float = 0.25):
    """A controller from a path spec, the form ``twin.toml``'s ``[devices.path]``,
    live-link commands and network path messages share.

    Args:
        spec: ``{"kind": "circle", "centre": [x, y], "radius": r, "direction": "ccw"}``,
            ``{"kind": "polyline", "waypoints": [[x, y], ...], "closed": false}``,
            ``{"kind": "figure_eight", "centre": [x, y], "size": s}`` or
            ``{"kind": "goal", "goal": [x, y]}``; optional ``"speed"`` (m/s).
        model: robot model (:class:`RobotSpec` or name).
        bounds: room bounds ``(lo, hi)`` the path must stay inside, or None.
        lookahead: pure-pursuit lookahead, m.

    Raises:
        ValueError: unknown kind; :class:`PathError` for unreachable or out-of-room paths.
    """
    if spec.get("kind") == "goal":
        return GoalReacher(spec["goal"], model, bounds=bounds)
    return PurePursuit(path_from_spec(spec), model, speed=spec.get("speed"), bounds=bounds,
                       lookahead=lookahead)


def path_from_spec(spec: dict, start: Sequence[float] | None = None) -> PlanarPath:
    """The planar curve a path spec (see :func:`controller_from_spec`) describes.

    A ``"goal"`` spec is the straight segment from ``start`` (``[2]`` m, the
    robot's position; required for that kind) to the goal.

    Raises:
        ValueError: unknown kind, or a goal without ``start``; :class:`PathError`
            for a malformed path.
    """
    kind = spec.get("kind")
    if kind == "circle":
        return CirclePath(spec["centre"], spec["radius"], spec.get("direction", "ccw"))
    if kind == "polyline":
        return PolylinePath(spec["waypoints"], closed=spec.get("closed", False))
    if kind == "figure_eight":
        return FigureEightPath(spec["centre"], spec["size"])
    if kind == "goal":
        if start is None:
            raise ValueError("path spec: a goal path needs the robot's start point")
        return PolylinePath([list(start)[:2], list(spec["goal"])[:2]])
    raise ValueError(f"path spec: unknown kind {kind!r} "
                     "(expected circle, polyline, figure_eight or goal)")
